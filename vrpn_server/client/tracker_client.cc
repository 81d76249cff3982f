#include "vrpn_server/client/tracker_client.h"

#include <algorithm>
#include <cctype>
#include <charconv>
#include <chrono>
#include <optional>
#include <stdexcept>
#include <vector>

#include "vrpn_server/net/socket_compat.h"
#include "vrpn_server/net/socket_util.h"

namespace trackcal::vrpn {
namespace {

using Clock = std::chrono::steady_clock;

Clock::duration Seconds(double s) {
  return std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(s));
}

int ParsePort(const std::string& text, const std::string& name) {
  int port = 0;
  auto [ptr, ec] = std::from_chars(text.data(), text.data() + text.size(), port);
  if (ec != std::errc() || ptr != text.data() + text.size() || port < 1 || port > 65535) {
    throw std::invalid_argument("VRPN name '" + name + "': bad port '" + text + "'");
  }
  return port;
}

// getaddrinfo's first IPv4 address of `host`; nullopt when the name has no address; throws when
// the lookup failed for now (EAI_AGAIN: no network or DNS server yet), to be tried again.
std::optional<std::string> ResolveWithGetaddrinfo(const std::string& host) {
  addrinfo hints{};
  hints.ai_family = AF_INET;
  hints.ai_socktype = SOCK_STREAM;
  addrinfo* res = nullptr;
  const int rc = ::getaddrinfo(host.c_str(), nullptr, &hints, &res);
  if (rc == EAI_NONAME || rc == EAI_FAIL
#ifdef EAI_NODATA
      || rc == EAI_NODATA
#endif
      || (rc == 0 && res == nullptr)) {
    return std::nullopt;
  }
  if (rc != 0) throw std::runtime_error(::gai_strerror(rc));
  const std::string address = FormatIpv4(reinterpret_cast<sockaddr_in*>(res->ai_addr)->sin_addr);
  ::freeaddrinfo(res);
  return address;
}

// A name lookup in flight, shared with the thread that runs it (which may outlive the client).
struct Lookup {
  std::mutex mutex;
  bool done = false;                   // guarded by mutex
  std::optional<std::string> address;  // guarded by mutex
  bool failed_for_now = false;         // guarded by mutex: the resolver threw
};

}  // namespace

VrpnName ParseVrpnName(const std::string& name) {
  // The device is the text before the first '@', as the reference's vrpn_copy_service_name reads
  // it: a client of the reference never reaches a device whose name holds '@', nor does this one.
  const auto at = name.find('@');
  if (at == std::string::npos || at == 0 || at + 1 == name.size()) {
    throw std::invalid_argument("VRPN name '" + name + "': expected Device@host[:port]");
  }
  if (name.find('@', at + 1) != std::string::npos) {
    throw std::invalid_argument("VRPN name '" + name +
                                "': a second '@' (the device is the text before the first '@', as "
                                "VRPN clients read it; a device name cannot hold '@')");
  }
  // vrpn.cfg splits its lines at blanks, so no served device name holds a blank or a control byte:
  // a client asking for one would wait for ever for a device that cannot exist.
  for (std::size_t i = 0; i < at; ++i) {
    const auto c = static_cast<unsigned char>(name[i]);
    if (c <= 0x20 || c == 0x7f) {
      throw std::invalid_argument(
          "VRPN name '" + name +
          "': the device name holds a blank or control character at position " +
          std::to_string(i + 1) + " (a served device name never does; is there a stray space?)");
    }
  }
  VrpnName n;
  n.device = name.substr(0, at);
  std::string rest = name.substr(at + 1);
  n.tcp = rest.find("tcp:") != std::string::npos;
  for (const char* prefix : {"tcp://", "x-vrpn://", "tcp:"}) {
    if (rest.starts_with(prefix)) {
      rest = rest.substr(std::char_traits<char>::length(prefix));
      break;
    }
  }
  // Any other scheme ("udp://", "mpi://") would otherwise be read as a host and a bad port.
  if (const auto scheme_end = rest.find("://"); scheme_end != std::string::npos) {
    throw std::invalid_argument("VRPN name '" + name + "': unknown scheme '" +
                                rest.substr(0, scheme_end) +
                                "://' (a VRPN name takes tcp:// or x-vrpn://, or none)");
  }
  const auto colon = rest.rfind(':');
  if (colon != std::string::npos) {
    n.port = ParsePort(rest.substr(colon + 1), name);
    rest = rest.substr(0, colon);
  }
  if (rest.empty()) throw std::invalid_argument("VRPN name '" + name + "': empty host");
  // A host name or an IPv4 address: anything else (a blank, a second port, an IPv6 literal) would
  // be looked up and retried for ever without an error.
  for (const char c : rest) {
    if (!std::isalnum(static_cast<unsigned char>(c)) && c != '.' && c != '-' && c != '_') {
      throw std::invalid_argument("VRPN name '" + name + "': host '" + rest +
                                  "' is not a host name or IPv4 address (IPv6 is not supported)");
    }
  }
  n.host = rest;
  if (n.device.size() > kMaxNameLength) {
    throw std::invalid_argument("VRPN name '" + name + "': device name over 95 characters");
  }
  return n;
}

void TrackerClientOptions::Check() const {
  if (!(ping_interval_s > 0))
    throw std::invalid_argument("TrackerClientOptions.ping_interval_s: must be > 0");
  if (!(lob_retry_s > 0))
    throw std::invalid_argument("TrackerClientOptions.lob_retry_s: must be > 0");
  if (!(liveness_timeout_s > 0)) {
    throw std::invalid_argument("TrackerClientOptions.liveness_timeout_s: must be > 0");
  }
  if (!(connect_timeout_s > 0)) {
    throw std::invalid_argument("TrackerClientOptions.connect_timeout_s: must be > 0");
  }
  if (!(reconnect_delay_s >= 0)) {
    throw std::invalid_argument("TrackerClientOptions.reconnect_delay_s: must be >= 0");
  }
  if (max_message_length < kHeaderSize + kTextSize) {
    throw std::invalid_argument(
        "TrackerClientOptions.max_message_length: must hold a text message");
  }
}

struct VrpnTrackerClient::Impl {
  enum class State { kIdle, kConnecting, kLobWaiting, kConnected } state = State::kIdle;
  std::shared_ptr<NameRegistry> names = std::make_shared<NameRegistry>();
  std::int32_t device_id = 0, ping_type = 0;
  std::int32_t request_types[3] = {};
  std::unique_ptr<Connection> connection;
  UniqueSocket tcp, listen, udp;
  std::size_t out_offset = 0;
  std::optional<sockaddr_in> server;
  std::optional<sockaddr_in> last_server;  // the one before a fresh lookup, if that lookup fails
  std::shared_ptr<Lookup> lookup;          // a host name being resolved
  in_addr local_ip{};
  Clock::time_point next_retry = Clock::time_point::min();
  Clock::time_point connect_deadline = Clock::time_point::max();
  Clock::time_point next_lob = Clock::time_point::max();
  Clock::time_point next_ping = Clock::time_point::max();
  Clock::time_point last_heard = Clock::time_point::min();  // the last message from the server
  bool request_pending = false;
  // Start()'s thread waits in PollSockets for up to 50 ms; Stop() sends a datagram here (a UDP
  // socket on loopback, connected to itself) so it returns at once. Invalid: Stop() waits.
  UniqueSocket wake_socket;
};

namespace {

// A UDP socket on 127.0.0.1 connected to itself, or an invalid one if that cannot be made.
UniqueSocket OpenWakeSocket() {
  UniqueSocket s(OpenSocket(SOCK_DGRAM, /*nonblocking=*/true));
  if (!s.valid()) return s;
  in_addr loopback{};
  loopback.s_addr = htonl(INADDR_LOOPBACK);
  sockaddr_in address = MakeSockaddr(loopback, 0);
  socklen_t len = sizeof(address);
  if (::bind(s.get(), reinterpret_cast<const sockaddr*>(&address), sizeof(address)) != 0 ||
      ::getsockname(s.get(), reinterpret_cast<sockaddr*>(&address), &len) != 0 ||
      ::connect(s.get(), reinterpret_cast<const sockaddr*>(&address), sizeof(address)) != 0) {
    s.Reset();
  }
  return s;
}

}  // namespace

VrpnTrackerClient::VrpnTrackerClient(const std::string& name, TrackerClientOptions options)
    : name_(ParseVrpnName(name)), options_(options), impl_(std::make_unique<Impl>()) {
  options_.Check();
  InitSockets();
  auto& n = *impl_->names;
  n.AddSender(kControlSender);
  impl_->device_id = n.AddSender(name_.device);
  for (auto t : {kPosQuatType, kVelocityType, kAccelerationType, kToRoomType, kUnitToSensorType,
                 kRequestToRoomType, kRequestUnitToSensorType, kWorkspaceType,
                 kRequestWorkspaceType, kSetUpdateRateType, kResetOriginType, kTextType, kPingType,
                 kPongType, kButtonChangeType, kButtonStatesType}) {
    n.AddType(t);
  }
  impl_->ping_type = *n.FindType(kPingType);
  impl_->request_types[0] = *n.FindType(kRequestToRoomType);
  impl_->request_types[1] = *n.FindType(kRequestUnitToSensorType);
  impl_->request_types[2] = *n.FindType(kRequestWorkspaceType);
}

VrpnTrackerClient::~VrpnTrackerClient() { Stop(); }

void VrpnTrackerClient::Start() {
  if (running_.exchange(true)) return;
  if (!impl_->wake_socket.valid()) impl_->wake_socket = OpenWakeSocket();
  thread_ = std::thread([this] {
    while (running_) {
      try {
        Poll(0.05);
      } catch (...) {
        // Leaving this thread, it would reach std::terminate and end the process (a Unity player,
        // through the plugin): a callback that throws, std::thread failing to start a host-name
        // lookup, bad_alloc. Poll stopped part-way, so the connection is made again.
        try {
          Reset("exception");
        } catch (...) {
        }
      }
    }
  });
}

void VrpnTrackerClient::Stop() {
  if (running_.exchange(false) && thread_.joinable()) {
    // Wake the thread from its wait rather than let the caller (Unity's main thread) sit out the
    // rest of it: up to 50 ms, several frames.
    if (impl_->wake_socket.valid()) {
      const char byte = 0;
      SendSocket(impl_->wake_socket.get(), &byte, 1);
    }
    thread_.join();
  }
}

void VrpnTrackerClient::RequestStaticInfo() {
  impl_->request_pending = true;
  if (connected_) {
    for (auto t : impl_->request_types)
      impl_->connection->Pack(impl_->device_id, t, Timestamp::Now(), {});
    impl_->request_pending = false;
    FlushTcp();
  }
}

void VrpnTrackerClient::Reset(const std::string& /*why*/) {
  impl_->tcp.Reset();
  impl_->listen.Reset();
  impl_->udp.Reset();
  impl_->connection.reset();
  impl_->out_offset = 0;
  impl_->state = Impl::State::kIdle;
  impl_->next_retry = Clock::now() + Seconds(options_.reconnect_delay_s);
  impl_->next_lob = impl_->next_ping = Clock::time_point::max();
  impl_->connect_deadline = Clock::time_point::max();
  // A host name is looked up again for the next attempt: the server may come back at another
  // address (a new DHCP lease, the name moved to a spare machine).
  if (impl_->server && !ParseIpv4(name_.host)) {
    impl_->last_server = impl_->server;
    impl_->server.reset();
  }
  connected_ = false;
  pong_received_ = false;
  udp_active_ = false;
}

bool VrpnTrackerClient::ResolveServer() {
  if (impl_->server) return true;
  if (const auto literal = ParseIpv4(name_.host)) {
    impl_->server = MakeSockaddr(*literal, name_.port);
    return true;
  }
  if (!impl_->lookup) {
    // On a detached thread: Stop() must not wait for a DNS server that does not answer.
    auto lookup = std::make_shared<Lookup>();
    auto resolve = options_.resolve_host ? options_.resolve_host : ResolveWithGetaddrinfo;
    std::thread([lookup, resolve, host = name_.host] {
      std::optional<std::string> address;
      bool failed_for_now = false;
      try {
        address = resolve(host);
      } catch (...) {
        failed_for_now = true;  // not an unknown host: looked up again at the next retry
      }
      std::lock_guard lock(lookup->mutex);
      lookup->address = std::move(address);
      lookup->failed_for_now = failed_for_now;
      lookup->done = true;
    }).detach();
    impl_->lookup = std::move(lookup);
  }
  std::optional<std::string> address;
  bool failed_for_now = false;
  {
    std::lock_guard lock(impl_->lookup->mutex);
    if (!impl_->lookup->done) {
      impl_->next_retry = Clock::now() + std::chrono::milliseconds(20);  // look again soon
      return false;
    }
    address = impl_->lookup->address;
    failed_for_now = impl_->lookup->failed_for_now;
  }
  impl_->lookup.reset();
  const auto parsed = address ? ParseIpv4(*address) : std::nullopt;
  if (!parsed && impl_->last_server) {
    // A DNS server that is down does not lose a server that is still where it was.
    impl_->server = impl_->last_server;
    return true;
  }
  if (!parsed) {
    host_unknown_ = !failed_for_now;
    impl_->next_retry = Clock::now() + Seconds(options_.reconnect_delay_s);
    return false;
  }
  host_unknown_ = false;
  impl_->server = MakeSockaddr(*parsed, name_.port);
  return true;
}

void VrpnTrackerClient::BeginConnect() {
  if (!ResolveServer()) return;
  ++connect_attempts_;
  const sockaddr_in server = *impl_->server;
  if (name_.tcp) {
    UniqueSocket fd(OpenSocket(SOCK_STREAM, /*nonblocking=*/true));
    if (!fd.valid()) {
      Reset("no socket");
      return;
    }
    SetNoDelay(fd.get());
    const int rc = ::connect(fd.get(), reinterpret_cast<const sockaddr*>(&server), sizeof(server));
    if (rc != 0 && !IsConnectInProgress(LastSocketError())) {
      Reset("connect failed");
      return;
    }
    impl_->tcp = std::move(fd);
    impl_->state = Impl::State::kConnecting;
    impl_->connect_deadline = Clock::now() + Seconds(options_.connect_timeout_s);
    if (rc == 0) OnTcpConnected();
    return;
  }
  // Lob: find our address towards the server, listen there, then send the request datagram.
  UniqueSocket probe(OpenSocket(SOCK_DGRAM, /*nonblocking=*/false));
  sockaddr_in local{};
  socklen_t len = sizeof(local);
  if (::connect(probe.get(), reinterpret_cast<const sockaddr*>(&server), sizeof(server)) != 0 ||
      ::getsockname(probe.get(), reinterpret_cast<sockaddr*>(&local), &len) != 0) {
    Reset("no route to server");
    return;
  }
  impl_->local_ip = local.sin_addr;
  UniqueSocket listener(OpenSocket(SOCK_STREAM, /*nonblocking=*/true));
  sockaddr_in la = MakeSockaddr(local.sin_addr, 0);
  if (::bind(listener.get(), reinterpret_cast<sockaddr*>(&la), sizeof(la)) != 0 ||
      ::listen(listener.get(), 4) != 0) {
    Reset("cannot listen for the call-back");
    return;
  }
  impl_->listen = std::move(listener);
  impl_->state = Impl::State::kLobWaiting;
  impl_->next_lob = Clock::now();  // send at once
  // A host name may have pointed at an address where no server is (its machine not up yet, or
  // back with a new DHCP lease): a call-back that does not come is then a connect that hangs, and
  // the next attempt looks the name up again. An IPv4 address is lobbed at for as long as it takes.
  if (!ParseIpv4(name_.host)) {
    impl_->connect_deadline = Clock::now() + Seconds(options_.connect_timeout_s);
  }
}

void VrpnTrackerClient::OnTcpConnected() {
  impl_->state = Impl::State::kConnected;
  // The cookie exchange is part of connecting: a peer that accepts and never answers (a wedged or
  // stopped server, another service on the port) is abandoned like a connect that hangs.
  impl_->connect_deadline = Clock::now() + Seconds(options_.connect_timeout_s);
  impl_->connection = std::make_unique<Connection>(
      impl_->names, Connection::Options{.max_message_length = options_.max_message_length});
  std::optional<std::pair<std::string, int>> our_udp;
  if (!name_.tcp && options_.udp_channel) {
    UniqueSocket udp(OpenSocket(SOCK_DGRAM, /*nonblocking=*/true));
    sockaddr_in ua = MakeSockaddr(impl_->local_ip, 0);
    socklen_t len = sizeof(ua);
    if (udp.valid() && ::bind(udp.get(), reinterpret_cast<sockaddr*>(&ua), sizeof(ua)) == 0 &&
        ::getsockname(udp.get(), reinterpret_cast<sockaddr*>(&ua), &len) == 0) {
      our_udp = std::make_pair(FormatIpv4(ua.sin_addr), static_cast<int>(ntohs(ua.sin_port)));
      impl_->udp = std::move(udp);
    }
  }
  impl_->connection->Start(our_udp);
  ++connections_;
  FlushTcp();
}

void VrpnTrackerClient::FlushTcp() {
  if (impl_->state != Impl::State::kConnected) return;
  auto& out = impl_->connection->tcp_output();
  while (impl_->out_offset < out.size()) {
    const long n = SendSocket(impl_->tcp.get(), out.data() + impl_->out_offset,
                              out.size() - impl_->out_offset);
    if (n < 0) {
      if (IsWouldBlock(LastSocketError())) return;
      Reset("write failed");
      return;
    }
    impl_->out_offset += static_cast<std::size_t>(n);
  }
  out.clear();
  impl_->out_offset = 0;
}

void VrpnTrackerClient::HandleMessage(const ReceivedMessage& m) {
  if (m.sender != name_.device) return;  // other devices on the same server
  if (m.type == kPosQuatType) {
    const auto p = DecodePosQuat(m.payload);
    if (!p) return;
    ++reports_;
    if (m.via_udp) udp_active_ = true;
    if (on_pose_)
      on_pose_(TrackerReport{p->sensor, p->transmitter_from_receiver, m.time, m.via_udp});
    return;
  }
  if (m.type == kPongType) pong_received_ = true;
  if (on_message_) on_message_(m);
}

void VrpnTrackerClient::Poll(double timeout_s) {
  auto now = Clock::now();
  if (impl_->state == Impl::State::kIdle && now >= impl_->next_retry) BeginConnect();
  auto deadline = now + Seconds(std::max(0.0, timeout_s));

  // Timers.
  if (impl_->state == Impl::State::kLobWaiting && now >= impl_->next_lob) {
    // A fresh UDP socket per attempt, as the reference does.
    UniqueSocket s(OpenSocket(SOCK_DGRAM, /*nonblocking=*/false));
    sockaddr_in la{};
    socklen_t len = sizeof(la);
    ::getsockname(impl_->listen.get(), reinterpret_cast<sockaddr*>(&la), &len);
    const auto dgram =
        EncodeLobRequest(LobRequest{FormatIpv4(impl_->local_ip), ntohs(la.sin_port)});
    ::sendto(s.get(), reinterpret_cast<const char*>(dgram.data()), static_cast<int>(dgram.size()),
             0, reinterpret_cast<const sockaddr*>(&*impl_->server), sizeof(sockaddr_in));
    impl_->next_lob = now + Seconds(options_.lob_retry_s);
  }
  // Liveness: after the first pong, silence for half the timeout starts pings again, and the whole
  // timeout drops the connection.
  bool liveness_ping = false;
  if (connected_ && pong_received_) {
    const auto silent = now - impl_->last_heard;
    if (silent >= Seconds(options_.liveness_timeout_s)) {
      Reset("the server went silent");
      return;
    }
    liveness_ping = silent >= Seconds(0.5 * options_.liveness_timeout_s);
  }
  if (connected_ && (!pong_received_ || liveness_ping) && now >= impl_->next_ping) {
    impl_->connection->Pack(impl_->device_id, impl_->ping_type, Timestamp::Now(), {});
    impl_->next_ping = now + Seconds(options_.ping_interval_s);
    FlushTcp();
  }
  auto wake = deadline;
  if (connected_ && pong_received_) {
    const auto half = impl_->last_heard + Seconds(0.5 * options_.liveness_timeout_s);
    wake = std::min(wake, liveness_ping
                              ? std::min(impl_->next_ping,
                                         impl_->last_heard + Seconds(options_.liveness_timeout_s))
                              : half);
  }
  if (impl_->state == Impl::State::kIdle) wake = std::min(wake, impl_->next_retry);
  if (impl_->state == Impl::State::kLobWaiting) wake = std::min(wake, impl_->next_lob);
  if (connected_ && !pong_received_) wake = std::min(wake, impl_->next_ping);
  if (impl_->state == Impl::State::kConnecting || impl_->state == Impl::State::kLobWaiting ||
      (impl_->state == Impl::State::kConnected && !connected_)) {
    // A connect that neither succeeds nor fails (a host that drops the SYN; WSAPoll, which does not
    // report a refused connect on some Windows versions), a peer that never sends its cookie, or
    // a lob to a host name's address that never calls back (BeginConnect), is retried.
    if (now >= impl_->connect_deadline) {
      Reset("connect timed out");
      return;
    }
    wake = std::min(wake, impl_->connect_deadline);
  }

  PollFd fds[4];
  int nfds = 0;
  int tcp_index = -1, listen_index = -1, udp_index = -1, wake_index = -1;
  if (impl_->tcp.valid()) {
    short ev = POLLIN;
    if (impl_->state == Impl::State::kConnecting ||
        (impl_->connection && impl_->out_offset < impl_->connection->tcp_output().size())) {
      ev |= POLLOUT;
    }
    tcp_index = nfds;
    fds[nfds++] = PollFd{impl_->tcp.get(), ev, 0};
  }
  if (impl_->listen.valid()) {
    listen_index = nfds;
    fds[nfds++] = PollFd{impl_->listen.get(), POLLIN, 0};
  }
  if (impl_->udp.valid()) {
    udp_index = nfds;
    fds[nfds++] = PollFd{impl_->udp.get(), POLLIN, 0};
  }
  if (impl_->wake_socket.valid()) {
    wake_index = nfds;
    fds[nfds++] = PollFd{impl_->wake_socket.get(), POLLIN, 0};
  }
  const auto wait =
      std::chrono::duration_cast<std::chrono::milliseconds>(wake - Clock::now()).count();
  const int rc = PollSockets(fds, static_cast<std::size_t>(nfds),
                             static_cast<int>(std::max<long long>(0, wait)));
  if (rc < 0) {
    // An error that is not an interruption would repeat at once: Start()'s loop must not spin.
    if (!IsWouldBlock(LastSocketError()))
      std::this_thread::sleep_for(std::chrono::milliseconds(10));
    return;
  }
  if (rc == 0) return;
  if (wake_index >= 0 && fds[wake_index].revents) {
    // Drained, and a pending error cleared, so that the next wait is not cut short again.
    if (fds[wake_index].revents & POLLERR) PendingSocketError(impl_->wake_socket.get());
    char byte[16];
    while (ReceiveSocket(impl_->wake_socket.get(), byte, sizeof(byte)) > 0) {
    }
  }
  auto handler = [this](const ReceivedMessage& m) {
    impl_->last_heard = Clock::now();  // any message, any device: the server is alive
    HandleMessage(m);
  };

  if (listen_index >= 0 && (fds[listen_index].revents & POLLIN)) {
    const NativeSocket fd = AcceptSocket(impl_->listen.get(), /*nonblocking=*/true);
    if (fd != kNoSocket) {
      impl_->tcp.Reset(fd);
      impl_->listen.Reset();
      SetNoDelay(fd);
      impl_->next_lob = Clock::time_point::max();
      OnTcpConnected();
      return;
    }
  }
  if (tcp_index >= 0 && fds[tcp_index].revents) {
    if (impl_->state == Impl::State::kConnecting) {
      const int err = PendingSocketError(impl_->tcp.get());
      if (err != 0 || (fds[tcp_index].revents & (POLLERR | POLLHUP))) {
        Reset("connect failed");
        return;
      }
      OnTcpConnected();
      return;
    }
    if (fds[tcp_index].revents & (POLLIN | POLLHUP | POLLERR)) {
      std::uint8_t buf[65536];
      for (int burst = 0; burst < 16; ++burst) {
        const long n = ReceiveSocket(impl_->tcp.get(), buf, sizeof(buf));
        if (n == 0 || (n < 0 && !IsWouldBlock(LastSocketError()))) {
          Reset("connection closed");
          return;
        }
        if (n < 0) break;
        const bool was = impl_->connection->handshake_done();
        if (!impl_->connection->OnTcpBytes(
                std::span<const std::uint8_t>(buf, static_cast<std::size_t>(n)), handler)) {
          Reset(impl_->connection->error());
          return;
        }
        if (!was && impl_->connection->handshake_done()) {
          connected_ = true;
          impl_->connect_deadline = Clock::time_point::max();
          impl_->next_ping = Clock::now();
          impl_->last_heard = Clock::now();
          if (impl_->request_pending) RequestStaticInfo();
        }
        if (static_cast<std::size_t>(n) < sizeof(buf)) break;
      }
    }
    FlushTcp();
  }
  if (udp_index >= 0 && impl_->udp.valid() && (fds[udp_index].revents & POLLIN) &&
      impl_->connection) {
    std::uint8_t buf[kMaxDatagramSize + 64];
    for (int burst = 0; burst < 64; ++burst) {
      const long n = ReceiveSocket(impl_->udp.get(), buf, sizeof(buf));
      if (n <= 0) break;
      impl_->connection->OnDatagram(std::span<const std::uint8_t>(buf, static_cast<std::size_t>(n)),
                                    handler);
    }
  }
  // Send a ping right after the handshake rather than waiting for the next Poll.
  if (connected_ && !pong_received_ && Clock::now() >= impl_->next_ping) {
    impl_->connection->Pack(impl_->device_id, impl_->ping_type, Timestamp::Now(), {});
    impl_->next_ping = Clock::now() + Seconds(options_.ping_interval_s);
    FlushTcp();
  }
}

}  // namespace trackcal::vrpn
