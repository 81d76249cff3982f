#include "vrpn_server/server/server.h"

#include <arpa/inet.h>
#include <fcntl.h>
#include <linux/errqueue.h>
#include <netinet/in.h>
#include <netinet/ip_icmp.h>
#include <netinet/tcp.h>
#include <pthread.h>
#include <sched.h>
#include <sys/epoll.h>
#include <sys/eventfd.h>
#include <sys/socket.h>
#include <sys/uio.h>
#include <time.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <chrono>
#include <condition_variable>
#include <csignal>
#include <cstring>
#include <ctime>
#include <deque>
#include <functional>
#include <iostream>
#include <map>
#include <set>
#include <sstream>
#include <stdexcept>

#include "core/printable_text.h"
#include "vrpn_server/net/socket_util.h"

namespace trackcal::vrpn {
namespace {

using Clock = std::chrono::steady_clock;

// epoll user data: id << 3 | kind.
enum Kind : std::uint64_t { kTcpListen = 0, kUdpLob = 1, kWake = 2, kEndpointTcp = 3, kEndpointUdp = 4 };
std::uint64_t Tag(std::uint64_t id, Kind kind) { return (id << 3) | kind; }

// After accept() failed for lack of resources (no free file descriptor), how long the listener
// stays out of the epoll set unless a connection closes first.
constexpr auto kAcceptRetry = std::chrono::milliseconds(250);

Clock::duration Seconds(double s) {
  return std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(s));
}

// `t + d`, or time_point::max() for a timer that is not running (t == max()).
Clock::time_point After(Clock::time_point t, Clock::duration d) {
  return t == Clock::time_point::max() ? t : t + d;
}

// Caps one kind of log line at kLinesPerWindow per window: further lines are counted, and the
// count is logged once the window has ended (the network thread wakes for it), so a flood cannot
// fill the log and still shows in it.
class LineLimiter {
 public:
  static constexpr int kLinesPerWindow = 100;
  using Sink = std::function<void(const std::string&)>;

  // `what`: the lines, for the notice when the cap is reached ("refusals"); `unlogged`: what the
  // count of left-out lines counts.
  LineLimiter(std::string what, std::string unlogged)
      : what_(std::move(what)), unlogged_what_(std::move(unlogged)) {}

  // Whether a line may be logged now; the first line left out in a window logs a notice.
  bool Allow(Clock::time_point now, double window_s, const Sink& log) {
    Report(now, window_s, log);
    if (logged_ < kLinesPerWindow) {
      ++logged_;
      return true;
    }
    if (unlogged_++ == 0) {
      std::ostringstream window;
      window << window_s;
      log(std::to_string(kLinesPerWindow) + " " + what_ + " logged in " + window.str() +
          " s: until the period ends, further ones are counted, not logged");
    }
    return false;
  }

  // If the window has ended: logs how many lines it left out, and starts a new one.
  void Report(Clock::time_point now, double window_s, const Sink& log) {
    if (now - window_start_ < Seconds(window_s)) return;
    if (unlogged_ > 0) log(std::to_string(unlogged_) + " " + unlogged_what_ + " were not logged");
    window_start_ = now;
    logged_ = 0;
    unlogged_ = 0;
  }

  // Logs the count of the lines left out so far, if any, whether or not the window has ended
  // (the server is stopping: the window's end will not come).
  void ReportNow(const Sink& log) {
    if (unlogged_ > 0) log(std::to_string(unlogged_) + " " + unlogged_what_ + " were not logged");
    unlogged_ = 0;
  }

  // When Report has a count to log; max() when it has none.
  Clock::time_point report_due(double window_s) const {
    return unlogged_ > 0 ? window_start_ + Seconds(window_s) : Clock::time_point::max();
  }

 private:
  std::string what_;
  std::string unlogged_what_;
  Clock::time_point window_start_;
  int logged_ = 0;
  std::uint64_t unlogged_ = 0;
};

// Only an address of one of this host's interfaces (or loopback) can be bound.
bool IsAddressOfThisHost(in_addr address) {
  if ((ntohl(address.s_addr) >> 24) == 127) return true;
  UniqueFd probe(::socket(AF_INET, SOCK_DGRAM | SOCK_CLOEXEC, 0));
  sockaddr_in local = MakeSockaddr(address, 0);
  return probe.valid() &&
         ::bind(probe.get(), reinterpret_cast<sockaddr*>(&local), sizeof(local)) == 0;
}

// Whether an ICMP error says the client's UDP port cannot be reached: port unreachable, or
// communication administratively prohibited (a firewall rejecting it). Not "fragmentation needed"
// (a hop with a smaller MTU: the kernel lowers its path MTU and later datagrams pass), nor host or
// network unreachable (the TCP connection fails too, and is closed on its own).
bool UdpPortUnreachable(const sock_extended_err& err) {
  if (err.ee_origin != SO_EE_ORIGIN_ICMP || err.ee_type != ICMP_DEST_UNREACH) return false;
  return err.ee_code == ICMP_PORT_UNREACH || err.ee_code == ICMP_NET_ANO ||
         err.ee_code == ICMP_HOST_ANO || err.ee_code == ICMP_PKT_FILTERED;
}

}  // namespace

void ServerOptions::Check() const {
  if (!ParseIpv4(bind_address)) {
    throw std::invalid_argument("ServerOptions.bind_address '" + bind_address +
                                "': not an IPv4 address");
  }
  if (port < 0 || port > 65535) throw std::invalid_argument("ServerOptions.port: must be in [0, 65535]");
  AllowList::Parse(allow);  // throws naming the entry
  if (max_clients < 1) throw std::invalid_argument("ServerOptions.max_clients: must be >= 1");
  if (max_output_bytes < 4096) {
    throw std::invalid_argument("ServerOptions.max_output_bytes: must be >= 4096");
  }
  if (max_total_output_bytes < 4096) {
    throw std::invalid_argument("ServerOptions.max_total_output_bytes: must be >= 4096");
  }
  if (max_message_length < kHeaderSize + kTextSize) {
    throw std::invalid_argument("ServerOptions.max_message_length: must hold a text message (1056)");
  }
  if (listen_backlog < 1) throw std::invalid_argument("ServerOptions.listen_backlog: must be >= 1");
  if (realtime_priority < 0 || realtime_priority > 99) {
    throw std::invalid_argument("ServerOptions.realtime_priority: must be in [0, 99]");
  }
  if (!(handshake_timeout_s > 0)) {
    throw std::invalid_argument("ServerOptions.handshake_timeout_s: must be > 0");
  }
  if (!(incomplete_message_timeout_s > 0 && incomplete_message_timeout_s <= 86400)) {
    throw std::invalid_argument(
        "ServerOptions.incomplete_message_timeout_s: must be in (0, 86400]");
  }
  if (!(unread_output_timeout_s > 0 && unread_output_timeout_s <= 86400)) {
    throw std::invalid_argument("ServerOptions.unread_output_timeout_s: must be in (0, 86400]");
  }
  if (!(min_stall_to_evict_s >= 0 && min_stall_to_evict_s <= 86400)) {
    throw std::invalid_argument("ServerOptions.min_stall_to_evict_s: must be in [0, 86400]");
  }
  if (!(refusal_log_window_s > 0 && refusal_log_window_s <= 86400)) {
    throw std::invalid_argument("ServerOptions.refusal_log_window_s: must be in (0, 86400]");
  }
  if (!(dead_client_timeout_s >= 0 && dead_client_timeout_s <= 86400)) {
    throw std::invalid_argument(
        "ServerOptions.dead_client_timeout_s: must be in [0, 86400] (0 disables)");
  }
}

struct VrpnServer::Event {
  enum Type { kPose, kText, kButton } type = kPose;
  int device = 0;
  int index = 0;  // sensor or button
  Rigid3d pose;
  Timestamp time;
  TextSeverity severity = TextSeverity::kNormal;
  std::string text;
  bool pressed = false;
  Clock::time_point enqueued;
};

struct VrpnServer::Endpoint {
  std::uint64_t id = 0;
  UniqueFd fd;
  UniqueFd udp_fd;  // our UDP data socket (lob connections only)
  bool connecting = false;
  bool lob = false;
  std::string label;
  sockaddr_in peer{};
  std::string callback_key;  // "ip:port" of a lob call-back, for de-duplication
  std::unique_ptr<ServerSession> session;
  std::size_t out_offset = 0;
  bool want_write = false;
  Clock::time_point opened;    // accepted, or call-back started
  Clock::time_point deadline;  // for the handshake; max() once it is done
  // Since when the client's current message has waited for its rest (max(): none waits), and the
  // count of whole messages when it was last looked at (a new one means the stream moved on).
  Clock::time_point incomplete_since = Clock::time_point::max();
  std::uint64_t messages_seen = 0;
  // Since when output has waited with the client taking none of it (max(): none waits).
  Clock::time_point unread_since = Clock::time_point::max();
  std::optional<sockaddr_in> udp_peer;
  // The client's UDP port was unreachable (ICMP): its reports go over TCP from then on.
  bool udp_unreachable = false;
  // An unusable UDP description was logged (once: the check runs after every read).
  bool udp_description_logged = false;
  std::vector<std::uint8_t> datagram;
};

struct VrpnServer::Impl {
  // Guards everything below but the queue: held by the network thread while it handles events and
  // by a device thread that fans its report out directly.
  std::mutex net_mutex;
  AllowList allow;
  std::map<std::uint64_t, std::unique_ptr<Endpoint>> endpoints;
  std::set<std::string> callback_keys;
  std::uint64_t next_id = 1;
  std::mutex queue_mutex;
  std::vector<Event> queue;
  std::vector<Event> work;
  std::vector<std::vector<std::int32_t>> button_states;
  std::vector<std::uint8_t> encoded;
  LineLimiter refusal_lines{"refusals", "refused or ignored connections, datagrams or call-backs"};
  LineLimiter connection_lines{"connection lines",
                               "connection lines (connected, closed, a client's faults)"};
  // A device thread started a timer the sleeping network thread does not know of (Kick wakes it).
  bool timers_changed = false;
  Clock::time_point loop_wake = Clock::time_point::max();  // when the network thread next wakes
  // accept() failed (out of file descriptors): the queued connection keeps the listener readable,
  // so it leaves the epoll set until a connection closes or accept_retry passes.
  bool accept_paused = false;
  Clock::time_point accept_retry;
  bool accept_failure_logged = false;  // once per episode, until an accept succeeds again
  bool keepalive_failure_logged = false;  // logged once
  std::vector<float> fanout_us;  // guarded by the server's stats_mutex_
  std::vector<mmsghdr> mmsg;     // DrainEvents scratch
  std::vector<iovec> iovs;
  std::vector<std::uint64_t> ids;
  std::vector<std::uint64_t> owners;  // the endpoint of each datagram in mmsg
  std::vector<std::pair<std::size_t, std::uint64_t>> waiting;  // LimitTotalOutput: bytes, id
};

namespace {

// "<UTC time> trackcal-server: line\n", `line` through PrintableForLog.
std::string Stamped(const std::string& line) {
  const std::time_t now = std::time(nullptr);
  std::tm tm{};
  ::gmtime_r(&now, &tm);
  char stamp[32];
  std::strftime(stamp, sizeof(stamp), "%Y-%m-%dT%H:%M:%SZ", &tm);
  // Lines quote vrpn.cfg's device names and device text: the terminal gets them escaped
  // (VrpnServer::Log and TrackcalServerApp::Log escape their lines before any sink, and
  // PrintableForLog leaves its own output unchanged).
  return std::string(stamp) + " trackcal-server: " + PrintableForLog(line) + "\n";
}

// The lines of LogToStderr, written to fd 2 by a thread of their own. The network thread logs every
// connection: a blocking write() there stopped every client's reports, and SIGTERM, while stderr
// was not read (a terminal paused with Ctrl-S, a pipe to a stalled reader). Lines wait here
// instead, up to kMaxQueuedBytes (the batch being written included); beyond that they are counted,
// dropped, and the count is logged once stderr takes lines again. Never destroyed: its thread may
// be blocked in write() when the process exits.
class StderrWriter {
 public:
  static StderrWriter& Get() {
    static StderrWriter* const writer = new StderrWriter();
    return *writer;
  }

  void Push(std::string line) {
    {
      std::lock_guard<std::mutex> lock(mutex_);
      if (queued_bytes_ + line.size() > kMaxQueuedBytes) {
        // The writer is woken for the count too: a line larger than the whole queue comes to an
        // idle writer, and without a line after it its count was never written (and
        // FlushStderrLog waited for it to its timeout).
        ++dropped_;
      } else {
        QueueDropNotice();  // where the lines went missing, before the next one
        Queue(std::move(line));
      }
    }
    wake_.notify_one();
  }

  bool Flush(std::chrono::milliseconds timeout) {
    std::unique_lock<std::mutex> lock(mutex_);
    return idle_.wait_for(lock, timeout,
                          [this] { return lines_.empty() && dropped_ == 0 && !writing_; });
  }

 private:
  // About 10000 lines of 100 bytes: minutes of a connection flood, bounded memory.
  static constexpr std::size_t kMaxQueuedBytes = 1 << 20;

  StderrWriter() {
    std::thread([this] { Run(); }).detach();
  }

  static void WriteAll(const std::string& text) {
    std::size_t done = 0;
    while (done < text.size()) {
      const ssize_t n = ::write(STDERR_FILENO, text.data() + done, text.size() - done);
      if (n < 0 && errno == EINTR) continue;
      if (n <= 0) return;  // stderr closed or broken: nothing else to tell
      done += static_cast<std::size_t>(n);
    }
  }

  void Queue(std::string line) {
    queued_bytes_ += line.size();
    lines_.push_back(std::move(line));
  }

  void QueueDropNotice() {
    if (dropped_ == 0) return;
    Queue(Stamped(std::to_string(dropped_) +
                  " log line(s) dropped: stderr was not read fast enough"));
    dropped_ = 0;
  }

  void Run() {
    // Signals stay with the threads that handle them (trackcal-server's main thread reads them
    // from a signalfd); this thread may start before they are blocked.
    sigset_t all;
    sigfillset(&all);
    pthread_sigmask(SIG_BLOCK, &all, nullptr);
    std::unique_lock<std::mutex> lock(mutex_);
    for (;;) {
      wake_.wait(lock, [this] { return !lines_.empty() || dropped_ > 0; });
      if (lines_.empty()) QueueDropNotice();  // no line came after the dropped ones
      std::string text;
      while (!lines_.empty()) {
        text += lines_.front();
        lines_.pop_front();
      }
      writing_ = true;
      lock.unlock();
      WriteAll(text);
      lock.lock();
      writing_ = false;
      // The batch counts against the queue until it is written: released when taken, another
      // kMaxQueuedBytes was queued behind a batch blocked in write(), twice the bound.
      queued_bytes_ -= text.size();
      if (lines_.empty() && dropped_ == 0) idle_.notify_all();
    }
  }

  std::mutex mutex_;
  std::condition_variable wake_;
  std::condition_variable idle_;
  std::deque<std::string> lines_;
  std::size_t queued_bytes_ = 0;
  std::uint64_t dropped_ = 0;
  bool writing_ = false;
};

}  // namespace

void LogToStderr(const std::string& line) { StderrWriter::Get().Push(Stamped(line)); }

bool FlushStderrLog(std::chrono::milliseconds timeout) {
  return StderrWriter::Get().Flush(timeout);
}

VrpnServer::VrpnServer(std::shared_ptr<const ServerCatalog> catalog, ServerOptions options,
                       LogFunction log)
    : catalog_(std::move(catalog)),
      options_(std::move(options)),
      log_(log ? std::move(log) : LogFunction(LogToStderr)),
      impl_(std::make_unique<Impl>()) {
  if (!catalog_) throw std::invalid_argument("VrpnServer: catalog is null");
  options_.Check();
  impl_->allow = AllowList::Parse(options_.allow);
  for (const auto& b : catalog_->buttons()) {
    impl_->button_states.emplace_back(static_cast<std::size_t>(b.num_buttons), 0);
  }
}

VrpnServer::~VrpnServer() { Stop(); }

void VrpnServer::Start() {
  if (running_) return;
  const in_addr bind_ip = *ParseIpv4(options_.bind_address);
  const std::string where = options_.bind_address + ":" + std::to_string(options_.port);
  UniqueFd tcp(::socket(AF_INET, SOCK_STREAM | SOCK_NONBLOCK | SOCK_CLOEXEC, 0));
  if (!tcp.valid()) throw std::runtime_error("socket: " + ErrnoText(errno));
  int one = 1;
  ::setsockopt(tcp.get(), SOL_SOCKET, SO_REUSEADDR, &one, sizeof(one));
  sockaddr_in sa = MakeSockaddr(bind_ip, options_.port);
  if (::bind(tcp.get(), reinterpret_cast<sockaddr*>(&sa), sizeof(sa)) != 0) {
    throw std::runtime_error("cannot bind TCP " + where + ": " + ErrnoText(errno));
  }
  if (::listen(tcp.get(), options_.listen_backlog) != 0) {
    throw std::runtime_error("cannot listen on " + where + ": " + ErrnoText(errno));
  }
  socklen_t len = sizeof(sa);
  ::getsockname(tcp.get(), reinterpret_cast<sockaddr*>(&sa), &len);
  port_ = ntohs(sa.sin_port);

  UniqueFd udp(::socket(AF_INET, SOCK_DGRAM | SOCK_NONBLOCK | SOCK_CLOEXEC, 0));
  if (!udp.valid()) throw std::runtime_error("socket: " + ErrnoText(errno));
  ::setsockopt(udp.get(), SOL_SOCKET, SO_REUSEADDR, &one, sizeof(one));
  // The lob clients' datagrams leave from this socket: without IP_RECVERR the kernel drops the
  // ICMP errors they cause (an unconnected socket), and a client whose UDP port is unreachable
  // would get no report, ever.
  ::setsockopt(udp.get(), IPPROTO_IP, IP_RECVERR, &one, sizeof(one));
  sa = MakeSockaddr(bind_ip, port_);
  if (::bind(udp.get(), reinterpret_cast<sockaddr*>(&sa), sizeof(sa)) != 0) {
    throw std::runtime_error("cannot bind UDP " + options_.bind_address + ":" +
                             std::to_string(port_) + ": " + ErrnoText(errno));
  }
  UniqueFd ep(::epoll_create1(EPOLL_CLOEXEC));
  UniqueFd ev(::eventfd(0, EFD_NONBLOCK | EFD_CLOEXEC));
  if (!ep.valid() || !ev.valid()) throw std::runtime_error("epoll/eventfd: " + ErrnoText(errno));
  auto add = [&](int fd, Kind kind) {
    epoll_event e{};
    e.events = EPOLLIN;
    e.data.u64 = Tag(0, kind);
    ::epoll_ctl(ep.get(), EPOLL_CTL_ADD, fd, &e);
  };
  add(tcp.get(), kTcpListen);
  add(udp.get(), kUdpLob);
  add(ev.get(), kWake);
  tcp_fd_ = tcp.Release();
  udp_fd_ = udp.Release();
  epoll_fd_ = ep.Release();
  event_fd_ = ev.Release();
  running_ = true;
  Log("serving on " + options_.bind_address + ":" + std::to_string(port_) + " (TCP and UDP)" +
      (impl_->allow.empty() ? "" : ", allow-list active"));
  thread_ = std::thread([this] { Run(); });
  // Reports queued before Start() wake the loop once.
  const std::uint64_t wake = 1;
  [[maybe_unused]] auto n = ::write(event_fd_, &wake, sizeof(wake));
}

void VrpnServer::Stop() {
  if (!running_.exchange(false)) return;
  const std::uint64_t one = 1;
  [[maybe_unused]] auto n = ::write(event_fd_, &one, sizeof(one));
  if (thread_.joinable()) thread_.join();
  std::lock_guard<std::mutex> net(impl_->net_mutex);
  for (LineLimiter* limiter : {&impl_->refusal_lines, &impl_->connection_lines}) {
    limiter->ReportNow([this](const std::string& line) { Log(line); });
  }
  impl_->endpoints.clear();
  impl_->callback_keys.clear();
  for (int* fd : {&tcp_fd_, &udp_fd_, &event_fd_, &epoll_fd_}) {
    if (*fd >= 0) ::close(*fd);
    *fd = -1;
  }
}

void VrpnServer::Push(Event event) {
  event.enqueued = Clock::now();
  bool was_empty;
  {
    std::lock_guard<std::mutex> lock(impl_->queue_mutex);
    was_empty = impl_->queue.empty();
    impl_->queue.push_back(std::move(event));
  }
  Kick(was_empty);
}

void VrpnServer::Kick(bool queue_was_empty) {
  // Fast path: if the network thread is idle, send from this thread at once (saves a thread
  // wake-up, tens of microseconds on a busy host). Never waits: when the loop is busy the report
  // stays queued and the loop sends it, in order, right after. Not with a real-time network
  // thread: a fan-out on the device thread (normal priority) can be preempted halfway by the
  // very clients it wakes, which is what the real-time priority is there to prevent.
  if (options_.direct_fanout && options_.realtime_priority == 0 && running_) {
    std::unique_lock<std::mutex> net(impl_->net_mutex, std::try_to_lock);
    if (net.owns_lock() && running_) {
      DrainEvents();
      // A client that stopped taking its output started a timer: the network thread may be
      // asleep with no deadline, or a later one.
      if (impl_->timers_changed) {
        impl_->timers_changed = false;
        if (NextWakeUp() < impl_->loop_wake) WakeLoop();
      }
      return;
    }
  }
  // One wake-up per batch: the loop drains everything queued when it runs.
  if (queue_was_empty && event_fd_ >= 0) {
    const std::uint64_t one = 1;
    [[maybe_unused]] auto n = ::write(event_fd_, &one, sizeof(one));
  }
}

void VrpnServer::PublishPoses(std::span<const PoseUpdate> poses) {
  for (const PoseUpdate& p : poses) {
    if (p.tracker < 0 || p.tracker >= static_cast<int>(catalog_->trackers().size())) {
      throw std::invalid_argument("PublishPoses: tracker index " + std::to_string(p.tracker) + " unknown");
    }
  }
  if (poses.empty()) return;
  const Clock::time_point now = Clock::now();
  bool was_empty;
  {
    std::lock_guard<std::mutex> lock(impl_->queue_mutex);
    was_empty = impl_->queue.empty();
    for (const PoseUpdate& p : poses) {
      Event& e = impl_->queue.emplace_back();
      e.type = Event::kPose;
      e.device = p.tracker;
      e.index = p.sensor;
      e.pose = p.transmitter_from_receiver;
      e.time = p.time;
      e.enqueued = now;
    }
  }
  Kick(was_empty);
}

void VrpnServer::PublishPose(int tracker, int sensor, const Rigid3d& pose, Timestamp time) {
  if (tracker < 0 || tracker >= static_cast<int>(catalog_->trackers().size())) {
    throw std::invalid_argument("PublishPose: tracker index " + std::to_string(tracker) + " unknown");
  }
  Event e;
  e.type = Event::kPose;
  e.device = tracker;
  e.index = sensor;
  e.pose = pose;
  e.time = time;
  Push(std::move(e));
}

void VrpnServer::PublishText(int tracker, TextSeverity severity, std::string text) {
  if (tracker < 0 || tracker >= static_cast<int>(catalog_->trackers().size())) {
    throw std::invalid_argument("PublishText: tracker index " + std::to_string(tracker) + " unknown");
  }
  Event e;
  e.type = Event::kText;
  e.device = tracker;
  e.severity = severity;
  e.text = std::move(text);
  e.time = Timestamp::Now();
  Push(std::move(e));
}

void VrpnServer::PublishButton(int button, int index, bool pressed, Timestamp time) {
  if (button < 0 || button >= static_cast<int>(catalog_->buttons().size()) || index < 0 ||
      index >= catalog_->buttons()[button].num_buttons) {
    throw std::invalid_argument("PublishButton: button " + std::to_string(button) + "/" +
                                std::to_string(index) + " unknown");
  }
  Event e;
  e.type = Event::kButton;
  e.device = button;
  e.index = index;
  e.pressed = pressed;
  e.time = time;
  Push(std::move(e));
}

ServerStats VrpnServer::stats() const {
  std::lock_guard<std::mutex> lock(stats_mutex_);
  return stats_;
}

void VrpnServer::Log(const std::string& line) { log_(PrintableForLog(line)); }

double VrpnServer::NetworkThreadCpuSeconds() const {
  if (!running_) return 0.0;
  clockid_t clock;
  if (::pthread_getcpuclockid(const_cast<std::thread&>(thread_).native_handle(), &clock) != 0) return 0.0;
  timespec ts{};
  ::clock_gettime(clock, &ts);
  return ts.tv_sec + 1e-9 * ts.tv_nsec;
}

void VrpnServer::Run() {
  if (options_.realtime_priority > 0) {
    sched_param param{};
    param.sched_priority = options_.realtime_priority;
    const int rc = ::pthread_setschedparam(::pthread_self(), SCHED_FIFO, &param);
    if (rc != 0) Log("cannot use real-time priority " + std::to_string(options_.realtime_priority) + ": " + ErrnoText(rc));
  }
  epoll_event events[64];
  while (running_) {
    // Block indefinitely unless a deadline is pending: no periodic wake-ups when idle.
    int timeout_ms = -1;
    Clock::time_point wake;
    {
      std::lock_guard<std::mutex> net(impl_->net_mutex);
      impl_->timers_changed = false;
      wake = NextWakeUp();
      impl_->loop_wake = wake;
      if (wake != Clock::time_point::max()) {
        const auto ms = std::chrono::ceil<std::chrono::milliseconds>(wake - Clock::now()).count();
        timeout_ms = static_cast<int>(std::clamp<std::int64_t>(ms, 0, 3600 * 1000));
      }
    }
    const int n = ::epoll_wait(epoll_fd_, events, 64, timeout_ms);
    if (n < 0 && errno != EINTR) {
      Log("epoll_wait: " + ErrnoText(errno));
      break;
    }
    std::lock_guard<std::mutex> net(impl_->net_mutex);
    for (int i = 0; i < n && running_; ++i) {
      const std::uint64_t tag = events[i].data.u64;
      const auto kind = static_cast<Kind>(tag & 7);
      switch (kind) {
        case kTcpListen:
          HandleAccept();
          break;
        case kUdpLob:
          if (events[i].events & EPOLLERR) HandleUdpErrors();
          HandleLob();
          break;
        case kWake: {
          std::uint64_t v;
          while (::read(event_fd_, &v, sizeof(v)) > 0) {
          }
          DrainEvents();
          break;
        }
        case kEndpointTcp:
          HandleEndpoint(tag >> 3, events[i].events, /*udp=*/false);
          break;
        case kEndpointUdp:
          HandleEndpoint(tag >> 3, events[i].events, /*udp=*/true);
          break;
      }
    }
    if (Clock::now() >= wake) {
      CheckDeadlines();
      ReportSuppressedLines();
    }
    if (impl_->accept_paused && Clock::now() >= impl_->accept_retry) SetAccepting(true);
  }
}

Clock::time_point VrpnServer::NextWakeUp() const {
  Clock::time_point due = Clock::time_point::max();
  if (impl_->accept_paused) due = impl_->accept_retry;
  const auto incomplete = Seconds(options_.incomplete_message_timeout_s);
  const auto unread = Seconds(options_.unread_output_timeout_s);
  for (const auto& [id, e] : impl_->endpoints) {
    due = std::min(
        {due, e->deadline, After(e->incomplete_since, incomplete), After(e->unread_since, unread)});
  }
  return std::min({due, impl_->refusal_lines.report_due(options_.refusal_log_window_s),
                   impl_->connection_lines.report_due(options_.refusal_log_window_s)});
}

void VrpnServer::WakeLoop() {
  const std::uint64_t one = 1;
  [[maybe_unused]] auto n = ::write(event_fd_, &one, sizeof(one));
}

void VrpnServer::ReportSuppressedLines() {
  const auto now = Clock::now();
  const auto log = [this](const std::string& line) { Log(line); };
  for (LineLimiter* limiter : {&impl_->refusal_lines, &impl_->connection_lines}) {
    if (limiter->report_due(options_.refusal_log_window_s) <= now) {
      limiter->Report(now, options_.refusal_log_window_s, log);
    }
  }
}

void VrpnServer::SetAccepting(bool on) {
  epoll_event ev{};
  ev.events = on ? EPOLLIN : 0u;
  ev.data.u64 = Tag(0, kTcpListen);
  ::epoll_ctl(epoll_fd_, EPOLL_CTL_MOD, tcp_fd_, &ev);
  impl_->accept_paused = !on;
  if (!on) impl_->accept_retry = Clock::now() + kAcceptRetry;
}

void VrpnServer::DetectDeadClient(int fd) {
  if (options_.dead_client_timeout_s <= 0) return;
  if (!EnableDeadPeerDetection(fd, options_.dead_client_timeout_s) &&
      !impl_->keepalive_failure_logged) {
    impl_->keepalive_failure_logged = true;
    Log("setsockopt (keepalive): " + ErrnoText(errno) +
        "; clients whose host vanishes are not dropped");
  }
}

void VrpnServer::HandleAccept() {
  for (int burst = 0; burst < 256; ++burst) {
    sockaddr_in peer{};
    socklen_t len = sizeof(peer);
    const int fd = ::accept4(tcp_fd_, reinterpret_cast<sockaddr*>(&peer), &len,
                             SOCK_NONBLOCK | SOCK_CLOEXEC);
    if (fd < 0) {
      const int err = errno;
      if (err == EAGAIN || err == EWOULDBLOCK || err == EINTR || err == ECONNABORTED) return;
      // EMFILE, ENFILE, ENOBUFS...: the connection stays queued and the listener readable; retrying
      // at once would spin the loop and flood the log.
      SetAccepting(false);
      if (!impl_->accept_failure_logged) {
        impl_->accept_failure_logged = true;
        Log("accept: " + ErrnoText(err) + "; new connections wait until one closes" +
            (err == EMFILE ? " (raise the open-file limit, ulimit -n, or lower --max-clients)"
                           : ""));
      }
      return;
    }
    impl_->accept_failure_logged = false;
    UniqueFd conn(fd);
    if (!impl_->allow.Allows(peer.sin_addr) || !RoomForNewClient()) {
      std::lock_guard<std::mutex> lock(stats_mutex_);
      ++stats_.refused;
      if (RefusalLogAllowed()) {
        Log("refused TCP connection from " + FormatEndpoint(peer) +
            (impl_->allow.Allows(peer.sin_addr) ? " (client limit reached)" : " (not in allow-list)"));
      }
      continue;
    }
    SetNoDelay(fd);
    DetectDeadClient(fd);
    auto e = std::make_unique<Endpoint>();
    e->id = impl_->next_id++;
    e->fd = std::move(conn);
    e->peer = peer;
    e->label = "tcp client " + FormatEndpoint(peer);
    e->opened = Clock::now();
    e->deadline = e->opened + Seconds(options_.handshake_timeout_s);
    epoll_event ev{};
    ev.events = EPOLLIN | EPOLLRDHUP;
    ev.data.u64 = Tag(e->id, kEndpointTcp);
    ::epoll_ctl(epoll_fd_, EPOLL_CTL_ADD, e->fd.get(), &ev);
    Endpoint& ref = *e;
    impl_->endpoints.emplace(e->id, std::move(e));
    StartSession(ref);
  }
}

void VrpnServer::HandleLob() {
  std::uint8_t buf[512];
  for (int burst = 0; burst < 256; ++burst) {
    sockaddr_in src{};
    socklen_t len = sizeof(src);
    const ssize_t n = ::recvfrom(udp_fd_, buf, sizeof(buf), 0, reinterpret_cast<sockaddr*>(&src), &len);
    if (n < 0) {
      if (errno == EAGAIN || errno == EWOULDBLOCK) return;
      // The pending error of a datagram we sent (ICMP), reported once instead of a datagram.
      HandleUdpErrors();
      continue;
    }
    auto refuse = [&](const std::string& why) {
      std::lock_guard<std::mutex> lock(stats_mutex_);
      ++stats_.refused;
      if (RefusalLogAllowed()) Log("ignored lob datagram from " + FormatEndpoint(src) + ": " + why);
    };
    if (!impl_->allow.Allows(src.sin_addr)) {
      refuse("not in allow-list");
      continue;
    }
    const auto request = DecodeLobRequest(std::span<const std::uint8_t>(buf, static_cast<std::size_t>(n)));
    if (!request) {
      refuse("not a VRPN connection request");
      continue;
    }
    // Call back only to the address the datagram came from: the server never opens connections
    // to third parties on a client's say-so (the reference trusts the text).
    const auto target = ParseIpv4(request->host);
    if (!target || target->s_addr != src.sin_addr.s_addr) {
      refuse("call-back address " + request->host + " differs from the sender");
      continue;
    }
    // A datagram naming our own port from an address of this host would make the server
    // connect to itself and hold a slot for a client that does not exist.
    if (request->port == port_ && IsAddressOfThisHost(*target)) {
      refuse("call-back to this server itself");
      continue;
    }
    const std::string key = request->host + ":" + std::to_string(request->port);
    if (impl_->callback_keys.count(key)) continue;  // a re-sent request while we already serve it
    if (!RoomForNewClient()) {
      refuse("client limit reached");
      continue;
    }
    UniqueFd fd(::socket(AF_INET, SOCK_STREAM | SOCK_NONBLOCK | SOCK_CLOEXEC, 0));
    if (!fd.valid()) {
      // Out of descriptors: one line per datagram would let any host flood the log.
      refuse("call-back socket: " + ErrnoText(errno));
      continue;
    }
    const in_addr bind_ip = *ParseIpv4(options_.bind_address);
    if (bind_ip.s_addr != htonl(INADDR_ANY)) {
      sockaddr_in local = MakeSockaddr(bind_ip, 0);
      ::bind(fd.get(), reinterpret_cast<sockaddr*>(&local), sizeof(local));
    }
    SetNoDelay(fd.get());
    DetectDeadClient(fd.get());
    sockaddr_in dst = MakeSockaddr(*target, request->port);
    const int rc = ::connect(fd.get(), reinterpret_cast<sockaddr*>(&dst), sizeof(dst));
    if (rc != 0 && errno != EINPROGRESS) {
      refuse("call-back connect: " + ErrnoText(errno));
      continue;
    }
    auto e = std::make_unique<Endpoint>();
    e->id = impl_->next_id++;
    e->fd = std::move(fd);
    e->peer = dst;
    e->lob = true;
    e->connecting = true;
    e->callback_key = key;
    e->label = "lob client " + FormatEndpoint(dst);
    e->opened = Clock::now();
    e->deadline = e->opened + Seconds(options_.handshake_timeout_s);
    epoll_event ev{};
    ev.events = EPOLLOUT | EPOLLRDHUP;
    ev.data.u64 = Tag(e->id, kEndpointTcp);
    ::epoll_ctl(epoll_fd_, EPOLL_CTL_ADD, e->fd.get(), &ev);
    impl_->callback_keys.insert(key);
    Endpoint& ref = *e;
    impl_->endpoints.emplace(e->id, std::move(e));
    if (rc == 0) OnConnected(ref);
  }
}

void VrpnServer::HandleUdpErrors() {
  for (int burst = 0; burst < 256; ++burst) {
    sockaddr_in target{};  // where the datagram that caused the error went
    std::uint8_t data[64];
    iovec iov{data, sizeof(data)};
    alignas(cmsghdr) char control[256];
    msghdr msg{};
    msg.msg_name = &target;
    msg.msg_namelen = sizeof(target);
    msg.msg_iov = &iov;
    msg.msg_iovlen = 1;
    msg.msg_control = control;
    msg.msg_controllen = sizeof(control);
    if (::recvmsg(udp_fd_, &msg, MSG_ERRQUEUE | MSG_DONTWAIT) < 0) return;
    for (cmsghdr* c = CMSG_FIRSTHDR(&msg); c != nullptr; c = CMSG_NXTHDR(&msg, c)) {
      if (c->cmsg_level != IPPROTO_IP || c->cmsg_type != IP_RECVERR) continue;
      sock_extended_err err;
      std::memcpy(&err, CMSG_DATA(c), sizeof(err));
      if (!UdpPortUnreachable(err)) continue;
      for (auto& [id, e] : impl_->endpoints) {
        if (!e->udp_peer || e->udp_peer->sin_addr.s_addr != target.sin_addr.s_addr ||
            e->udp_peer->sin_port != target.sin_port) {
          continue;
        }
        e->udp_peer.reset();
        e->udp_unreachable = true;
        if (ConnectionLogAllowed()) {
          Log(e->label + ": UDP port unreachable (" + FormatEndpoint(target) + ": " +
              ErrnoText(static_cast<int>(err.ee_errno)) + "); its reports go over TCP");
        }
      }
    }
  }
}

void VrpnServer::OnConnected(Endpoint& e) {
  e.connecting = false;
  // Our UDP data socket, on the address the client reached us at.
  sockaddr_in local{};
  socklen_t len = sizeof(local);
  ::getsockname(e.fd.get(), reinterpret_cast<sockaddr*>(&local), &len);
  if (options_.udp_data_channel) {
    UniqueFd udp(::socket(AF_INET, SOCK_DGRAM | SOCK_NONBLOCK | SOCK_CLOEXEC, 0));
    sockaddr_in ua = MakeSockaddr(local.sin_addr, 0);
    if (udp.valid() && ::bind(udp.get(), reinterpret_cast<sockaddr*>(&ua), sizeof(ua)) == 0) {
      epoll_event ev{};
      ev.events = EPOLLIN;
      ev.data.u64 = Tag(e.id, kEndpointUdp);
      ::epoll_ctl(epoll_fd_, EPOLL_CTL_ADD, udp.get(), &ev);
      e.udp_fd = std::move(udp);
    }
  }
  StartSession(e);
}

void VrpnServer::StartSession(Endpoint& e) {
  {
    std::lock_guard<std::mutex> lock(stats_mutex_);
    ++stats_.connections_total;
    stats_.clients = static_cast<int>(impl_->endpoints.size());
  }
  e.session = std::make_unique<ServerSession>(
      catalog_, Connection::Options{.max_message_length = options_.max_message_length}, e.label,
      [this](const std::string& line) {
        if (ConnectionLogAllowed()) Log(line);
      },
      options_.max_output_bytes);
  std::optional<std::pair<std::string, int>> our_udp;
  if (e.udp_fd.valid()) {
    sockaddr_in ua{};
    socklen_t len = sizeof(ua);
    ::getsockname(e.udp_fd.get(), reinterpret_cast<sockaddr*>(&ua), &len);
    our_udp = std::make_pair(FormatIpv4(ua.sin_addr), static_cast<int>(ntohs(ua.sin_port)));
  }
  e.session->Start(our_udp, impl_->button_states);
  if (ConnectionLogAllowed()) Log("connected " + e.label);
  UpdateInterest(e);
  Flush(e);
}

void VrpnServer::UpdateInterest(Endpoint& e) {
  epoll_event ev{};
  ev.events = EPOLLIN | EPOLLRDHUP | (e.want_write || e.connecting ? static_cast<std::uint32_t>(EPOLLOUT) : 0u);
  ev.data.u64 = Tag(e.id, kEndpointTcp);
  ::epoll_ctl(epoll_fd_, EPOLL_CTL_MOD, e.fd.get(), &ev);
}

void VrpnServer::HandleEndpoint(std::uint64_t id, std::uint32_t events, bool udp) {
  auto it = impl_->endpoints.find(id);
  if (it == impl_->endpoints.end()) return;  // closed earlier in this batch
  Endpoint& e = *it->second;
  if (udp) {
    std::uint8_t buf[kMaxDatagramSize + 64];
    for (int burst = 0; burst < 64; ++burst) {
      sockaddr_in src{};
      socklen_t len = sizeof(src);
      const ssize_t n =
          ::recvfrom(e.udp_fd.get(), buf, sizeof(buf), 0, reinterpret_cast<sockaddr*>(&src), &len);
      if (n <= 0) break;
      // Anyone can reach this port; only the client's own host may speak for the client (any
      // source port: clients send from other sockets than the one they describe).
      if (src.sin_addr.s_addr != e.peer.sin_addr.s_addr) {
        std::lock_guard<std::mutex> lock(stats_mutex_);
        ++stats_.refused;
        if (RefusalLogAllowed()) {
          Log("ignored datagram from " + FormatEndpoint(src) + " to the data port of " + e.label);
        }
        continue;
      }
      if (e.session) e.session->OnDatagram(std::span<const std::uint8_t>(buf, static_cast<std::size_t>(n)));
    }
    Flush(e);  // replies to messages that came over UDP travel on TCP
    return;
  }
  if (e.connecting) {
    int err = 0;
    socklen_t len = sizeof(err);
    ::getsockopt(e.fd.get(), SOL_SOCKET, SO_ERROR, &err, &len);
    if (err != 0 || (events & (EPOLLERR | EPOLLHUP))) {
      // Every lob datagram naming a closed port ends here: these lines count toward the cap on
      // lob refusals, or any host could flood the log at the rate it sends datagrams.
      Close(id, "call-back connect failed: " + ErrnoText(err ? err : ECONNREFUSED),
            LineKind::kRefusal);
      return;
    }
    if (events & EPOLLOUT) OnConnected(e);
    return;
  }
  if (events & EPOLLIN) {
    std::uint8_t buf[65536];
    for (int burst = 0; burst < 16; ++burst) {
      const ssize_t n = ::read(e.fd.get(), buf, sizeof(buf));
      if (n == 0) {
        Close(id, "client closed the connection");
        return;
      }
      if (n < 0) {
        if (errno == EAGAIN || errno == EWOULDBLOCK || errno == EINTR) break;
        CloseOnSocketError(id, "read", errno);
        return;
      }
      const bool was_done = e.session->connection().handshake_done();
      if (!e.session->OnTcpBytes(std::span<const std::uint8_t>(buf, static_cast<std::size_t>(n)))) {
        {
          std::lock_guard<std::mutex> lock(stats_mutex_);
          ++stats_.closed_protocol;
        }
        Close(id, e.session->error());
        return;
      }
      if (!was_done && e.session->connection().handshake_done()) {
        e.deadline = Clock::time_point::max();
      }
      // Use the client's UDP port once described, if it is on the client's own address.
      if (e.udp_fd.valid() && !e.udp_peer && !e.udp_unreachable &&
          e.session->connection().peer_udp()) {
        const auto& [host, port] = *e.session->connection().peer_udp();
        const auto ip = ParseIpv4(host);
        if (ip && ip->s_addr == e.peer.sin_addr.s_addr) {
          e.udp_peer = MakeSockaddr(*ip, port);
        } else if (!e.udp_description_logged) {
          e.udp_description_logged = true;
          if (ConnectionLogAllowed()) {
            Log(e.label + ": ignoring UDP description for " + host + " (not the client's address)");
          }
        }
      }
      if (static_cast<std::size_t>(n) < sizeof(buf)) break;
    }
    // A message whose rest has not come starts (or, after whole messages, restarts) the clock of
    // incomplete_message_timeout_s.
    const Connection& c = e.session->connection();
    if (!c.handshake_done() || c.incomplete_tcp_bytes() == 0) {
      e.incomplete_since = Clock::time_point::max();
    } else if (e.incomplete_since == Clock::time_point::max() ||
               c.tcp_messages_received() != e.messages_seen) {
      e.incomplete_since = Clock::now();
    }
    e.messages_seen = c.tcp_messages_received();
    Flush(e);
    if (impl_->endpoints.count(id) == 0) return;
  } else if (events & (EPOLLERR | EPOLLHUP | EPOLLRDHUP)) {
    Close(id, "connection lost");
    return;
  }
  if (events & EPOLLOUT) Flush(e);
}

void VrpnServer::Flush(Endpoint& e) {
  if (e.connecting || !e.session) return;
  auto& out = e.session->connection().tcp_output();
  bool progress = false;
  while (e.out_offset < out.size()) {
    const ssize_t n = ::send(e.fd.get(), out.data() + e.out_offset, out.size() - e.out_offset,
                             MSG_NOSIGNAL | MSG_DONTWAIT);
    if (n < 0) {
      if (errno == EAGAIN || errno == EWOULDBLOCK) break;
      if (errno == EINTR) continue;
      CloseOnSocketError(e.id, "write", errno);
      return;
    }
    e.out_offset += static_cast<std::size_t>(n);
    progress = progress || n > 0;
  }
  const std::size_t pending = out.size() - e.out_offset;
  // Output the client takes none of starts the clock of unread_output_timeout_s.
  if (pending == 0) {
    e.unread_since = Clock::time_point::max();
  } else if (progress || e.unread_since == Clock::time_point::max()) {
    if (e.unread_since == Clock::time_point::max()) impl_->timers_changed = true;
    e.unread_since = Clock::now();
  }
  if (pending == 0) {
    out.clear();
    e.out_offset = 0;
  } else if (e.out_offset > 65536 && e.out_offset > pending) {
    out.erase(out.begin(), out.begin() + static_cast<std::ptrdiff_t>(e.out_offset));
    e.out_offset = 0;
  }
  if (pending > options_.max_output_bytes) {
    {
      std::lock_guard<std::mutex> lock(stats_mutex_);
      ++stats_.dropped_slow;
    }
    Close(e.id, "not reading (" + std::to_string(pending) + " bytes waiting): dropped");
    return;
  }
  const bool want = pending > 0;
  if (want != e.want_write) {
    e.want_write = want;
    UpdateInterest(e);
  }
}

void VrpnServer::LimitTotalOutput() {
  std::size_t total = 0;
  std::vector<std::pair<std::size_t, std::uint64_t>>& waiting = impl_->waiting;  // bytes, id
  waiting.clear();
  for (const auto& [id, e] : impl_->endpoints) {
    if (e->connecting || !e->session) continue;
    const std::size_t pending = e->session->connection().tcp_output().size() - e->out_offset;
    total += pending;
    if (pending > 0) waiting.emplace_back(pending, id);
  }
  if (total <= options_.max_total_output_bytes) return;
  // The most first: a client that reads holds next to nothing, one that stopped holds the most.
  std::sort(waiting.begin(), waiting.end(), std::greater<>());
  for (const auto& [pending, id] : waiting) {
    if (total <= options_.max_total_output_bytes) break;
    {
      std::lock_guard<std::mutex> lock(stats_mutex_);
      ++stats_.dropped_over_total;
    }
    Close(id, "the most unsent output of all clients (" + std::to_string(pending) + " of " +
                  std::to_string(total) + " bytes waiting, over the total of " +
                  std::to_string(options_.max_total_output_bytes) + "): dropped");
    total -= pending;
  }
}

bool VrpnServer::RefusalLogAllowed() {
  const bool allowed = impl_->refusal_lines.Allow(Clock::now(), options_.refusal_log_window_s,
                                                  [this](const std::string& line) { Log(line); });
  if (!allowed) impl_->timers_changed = true;  // the count is to be logged when the window ends
  return allowed;
}

bool VrpnServer::ConnectionLogAllowed() {
  const bool allowed = impl_->connection_lines.Allow(
      Clock::now(), options_.refusal_log_window_s, [this](const std::string& line) { Log(line); });
  if (!allowed) impl_->timers_changed = true;
  return allowed;
}

bool VrpnServer::RoomForNewClient() {
  if (static_cast<int>(impl_->endpoints.size()) < options_.max_clients) return true;
  // The connection stalled longest: waiting for its handshake since it opened, or, served, stuck
  // halfway through a message or not taking its output (waiting in our buffer or in the kernel's)
  // for at least min_stall_to_evict_s. Runs only with the table full.
  const auto now = Clock::now();
  const Endpoint* victim = nullptr;
  Clock::time_point victim_since = Clock::time_point::max();
  for (const auto& [id, e] : impl_->endpoints) {
    Clock::time_point since;
    if (e->deadline != Clock::time_point::max()) {
      since = e->opened;
    } else {
      // Not output waiting in the kernel: a client that stopped reading is seen only when output
      // waits in our buffer (see docs/vrpn.md: the kernel's own measures, the time since the last
      // data segment left and the bytes queued, did not tell a stalled reader reliably).
      since = std::min(e->incomplete_since, e->unread_since);
      if (since == Clock::time_point::max() ||
          now - since < Seconds(options_.min_stall_to_evict_s)) {
        continue;
      }
    }
    if (since < victim_since) {
      victim = e.get();
      victim_since = since;
    }
  }
  if (!victim) return false;
  {
    std::lock_guard<std::mutex> lock(stats_mutex_);
    ++stats_.evicted;
  }
  std::string why;
  if (victim->deadline != Clock::time_point::max()) {
    why = "handshake not done";
  } else if (victim->incomplete_since == victim_since) {
    why = "part of a message received and not the rest";
  } else {
    why = "not taking its output";
  }
  std::ostringstream stalled;
  stalled.precision(3);
  stalled << std::chrono::duration<double>(now - victim_since).count();
  Close(victim->id,
        why + " for " + stalled.str() +
            " s while the client limit was reached: made room for a new client",
        LineKind::kRefusal);
  return true;
}

void VrpnServer::CloseOnSocketError(std::uint64_t id, const char* op, int err) {
  if (err != ETIMEDOUT) {
    Close(id, std::string(op) + ": " + ErrnoText(err));
    return;
  }
  // Only DetectDeadClient's limits time a connection out: the TCP user timeout (nothing
  // acknowledged, or the client's receive window closed, for that long) or unanswered keepalive
  // probes. "read: Connection timed out" did not say that a client that stopped reading ends so
  // (on loopback, long before unread_output_timeout_s), and it was not counted as dropped.
  {
    std::lock_guard<std::mutex> lock(stats_mutex_);
    ++stats_.dropped_slow;
  }
  std::ostringstream timeout;
  timeout << options_.dead_client_timeout_s;
  Close(id, "nothing acknowledged for " + timeout.str() +
                " s (not reading, or its host is gone): dropped");
}

void VrpnServer::Close(std::uint64_t id, const std::string& why, LineKind kind) {
  auto it = impl_->endpoints.find(id);
  if (it == impl_->endpoints.end()) return;
  const bool log = kind == LineKind::kConnection ? ConnectionLogAllowed()
                   : kind == LineKind::kRefusal  ? RefusalLogAllowed()
                                                 : false;
  if (log) Log("closed " + it->second->label + ": " + why);
  if (!it->second->callback_key.empty()) impl_->callback_keys.erase(it->second->callback_key);
  // Closing the fds removes them from the epoll set.
  impl_->endpoints.erase(it);
  if (impl_->accept_paused) SetAccepting(true);  // a descriptor was freed
  std::lock_guard<std::mutex> lock(stats_mutex_);
  stats_.clients = static_cast<int>(impl_->endpoints.size());
}

void VrpnServer::CheckDeadlines() {
  const auto now = Clock::now();
  const auto incomplete = Seconds(options_.incomplete_message_timeout_s);
  const auto unread = Seconds(options_.unread_output_timeout_s);
  std::vector<std::pair<std::uint64_t, std::string>> expired;
  std::uint64_t protocol = 0;
  std::uint64_t slow = 0;
  for (const auto& [id, e] : impl_->endpoints) {
    std::ostringstream why;
    if (e->deadline < now) {
      why << "handshake timed out";
    } else if (After(e->incomplete_since, incomplete) < now) {
      ++protocol;
      why << "sent " << e->session->connection().incomplete_tcp_bytes()
          << " bytes of a message and not the rest for " << options_.incomplete_message_timeout_s
          << " s";
    } else if (After(e->unread_since, unread) < now) {
      ++slow;
      why << "took none of the " << e->session->connection().tcp_output().size() - e->out_offset
          << " bytes waiting for it for " << options_.unread_output_timeout_s << " s: dropped";
    } else {
      continue;
    }
    expired.emplace_back(id, why.str());
  }
  if (protocol + slow > 0) {
    std::lock_guard<std::mutex> lock(stats_mutex_);
    stats_.closed_protocol += protocol;
    stats_.dropped_slow += slow;
  }
  for (const auto& [id, why] : expired) Close(id, why);
}

void VrpnServer::DrainEvents() {
  {
    std::lock_guard<std::mutex> lock(impl_->queue_mutex);
    impl_->work.swap(impl_->queue);
  }
  if (impl_->work.empty()) return;
  const TypeIds& types = catalog_->types();
  const Clock::time_point first_enqueued = impl_->work.front().enqueued;
  std::uint64_t reports = 0;
  std::vector<std::uint8_t>& msg = impl_->encoded;
  for (const Event& ev : impl_->work) {
    msg.clear();
    bool low_latency = false;
    switch (ev.type) {
      case Event::kPose: {
        std::uint8_t payload[kPosQuatSize];
        EncodePosQuatInto(PosQuat{ev.index, ev.pose}, payload);
        AppendMessage(&msg, ev.time, catalog_->tracker_sender(ev.device), types.pos_quat, 0, payload);
        low_latency = true;
        ++reports;
        break;
      }
      case Event::kText:
        AppendMessage(&msg, ev.time, catalog_->tracker_sender(ev.device), types.text, 0,
                      EncodeText(TextMessage{ev.severity, 0, ev.text}));
        break;
      case Event::kButton:
        impl_->button_states[ev.device][ev.index] = ev.pressed ? 1 : 0;
        AppendMessage(&msg, ev.time, catalog_->button_sender(ev.device), types.button_change, 0,
                      EncodeButtonChange(ButtonChange{ev.index, ev.pressed ? 1 : 0}));
        break;
    }
    const std::int32_t sender = static_cast<std::int32_t>(LoadU32(msg.data() + 12));
    for (auto& [id, e] : impl_->endpoints) {
      if (e->connecting || !e->session) continue;
      // Only clients that use this device get its messages: those that pinged from its name
      // (ServerSession::Uses; the reference sends everything to everyone and lets clients
      // filter). A client that pinged from none of our names (a minimal client, a logger)
      // filters by itself and gets every device's messages, as from the reference server.
      // Before the client's cookie arrived, nothing is sent.
      ServerSession& session = *e->session;
      if (!session.connection().handshake_done()) continue;
      const bool wanted = !session.uses_any_device() || session.Uses(sender);
      if (!wanted) continue;
      if (low_latency && e->udp_peer) {
        if (e->datagram.size() + msg.size() > kMaxDatagramSize) {
          // Flush a full datagram before adding more (from the shared socket, as the rest: its
          // errors are read there).
          mmsghdr h{};
          iovec iov{e->datagram.data(), e->datagram.size()};
          h.msg_hdr.msg_name = &*e->udp_peer;
          h.msg_hdr.msg_namelen = sizeof(sockaddr_in);
          h.msg_hdr.msg_iov = &iov;
          h.msg_hdr.msg_iovlen = 1;
          SendDatagrams(std::span<mmsghdr>(&h, 1), std::span<const std::uint64_t>(&e->id, 1));
          e->datagram.clear();
          if (!e->udp_peer) {  // its port was found unreachable: the rest goes over TCP
            e->session->connection().PackEncoded(msg);
            continue;
          }
        }
        e->session->connection().PackEncodedUdp(msg, &e->datagram);
      } else {
        e->session->connection().PackEncoded(msg);
      }
    }
  }
  impl_->work.clear();
  {
    std::lock_guard<std::mutex> lock(stats_mutex_);
    stats_.reports_published += reports;
  }
  // All UDP datagrams of this batch leave in one sendmmsg() from the server's port: one system call
  // instead of one per client, so the woken clients cannot interleave with the fan-out. Clients
  // accept data datagrams from any source port (the reference's own sending port differs from the
  // port it announces too).
  std::vector<mmsghdr>& headers = impl_->mmsg;
  std::vector<iovec>& iovs = impl_->iovs;
  headers.clear();
  iovs.clear();
  std::vector<std::uint64_t>& ids = impl_->ids;
  ids.clear();
  for (auto& [id, e] : impl_->endpoints) {
    ids.push_back(id);
    if (!e->datagram.empty()) iovs.push_back(iovec{e->datagram.data(), e->datagram.size()});
  }
  std::size_t k = 0;
  std::vector<std::uint64_t>& owners = impl_->owners;
  owners.clear();
  for (auto& [id, e] : impl_->endpoints) {
    if (e->datagram.empty()) continue;
    owners.push_back(id);
    mmsghdr h{};
    h.msg_hdr.msg_name = &*e->udp_peer;
    h.msg_hdr.msg_namelen = sizeof(sockaddr_in);
    h.msg_hdr.msg_iov = &iovs[k++];
    h.msg_hdr.msg_iovlen = 1;
    headers.push_back(h);
  }
  SendDatagrams(headers, owners);
  for (auto& [id, e] : impl_->endpoints) e->datagram.clear();
  for (std::uint64_t id : ids) {
    auto it = impl_->endpoints.find(id);
    if (it == impl_->endpoints.end()) continue;
    Flush(*it->second);
  }
  LimitTotalOutput();
  const float us = std::chrono::duration<float, std::micro>(Clock::now() - first_enqueued).count();
  std::lock_guard<std::mutex> lock(stats_mutex_);
  if (impl_->fanout_us.size() < 1000000) impl_->fanout_us.push_back(us);
}

void VrpnServer::SendDatagrams(std::span<mmsghdr> headers, std::span<const std::uint64_t> owners) {
  std::size_t end = headers.size();
  bool retried = false;
  for (std::size_t sent = 0; sent < end;) {
    const int n =
        ::sendmmsg(udp_fd_, headers.data() + sent, static_cast<unsigned>(end - sent), MSG_DONTWAIT);
    if (n > 0) {
      sent += static_cast<std::size_t>(n);
      retried = false;
      continue;
    }
    // The kernel reports the ICMP error of an earlier datagram (to any client) at the next send
    // from the socket, and sends nothing: read the queued errors (a client whose port is
    // unreachable moves to TCP) and send this datagram again, once, so that one client's error
    // never costs another client a report.
    if (!retried && errno != EAGAIN && errno != EWOULDBLOCK) {
      HandleUdpErrors();
      retried = true;
      // The datagrams not sent yet of a client just moved to TCP go there.
      std::size_t kept = sent;
      for (std::size_t k = sent; k < end; ++k) {
        auto it = impl_->endpoints.find(owners[k]);
        if (it != impl_->endpoints.end() && !it->second->udp_peer && it->second->session) {
          const auto* p = static_cast<const std::uint8_t*>(headers[k].msg_hdr.msg_iov->iov_base);
          const std::size_t size = headers[k].msg_hdr.msg_iov->iov_len;
          for (std::size_t at = 0; at + kHeaderSize <= size;) {
            const std::size_t wire = std::min(size - at, DecodeHeader(p + at).wire_size());
            it->second->session->connection().PackEncoded(std::span(p + at, wire));
            at += wire;
          }
          continue;
        }
        headers[kept] = headers[k];
        ++kept;
      }
      end = kept;
      continue;
    }
    // Still failing (full send buffer, a datagram the path cannot carry): skip it, carry on.
    std::lock_guard<std::mutex> lock(stats_mutex_);
    ++stats_.udp_send_failures;
    ++sent;
    retried = false;
  }
}

std::vector<float> VrpnServer::TakeFanoutMicros() {
  std::lock_guard<std::mutex> lock(stats_mutex_);
  std::vector<float> out;
  out.swap(impl_->fanout_us);
  return out;
}

}  // namespace trackcal::vrpn
