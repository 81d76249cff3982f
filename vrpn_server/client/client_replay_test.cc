// Our client against the reference server's captured bytes: a fake server replays
// server_to_client.bin (and, in lob scenarios, the UDP datagrams with their captured sizes) and the
// client must decode exactly the poses the reference client printed (client.csv).
#include <arpa/inet.h>
#include <gtest/gtest.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <fstream>
#include <regex>
#include <thread>

#include "vrpn_server/client/tracker_client.h"
#include "vrpn_server/net/socket_util.h"
#include "vrpn_server/protocol/transcript_testing.h"

namespace trackcal::vrpn {
namespace {

using Clock = std::chrono::steady_clock;

// Sizes of the server -> client data datagrams in udp_datagrams.txt (the lob line is skipped).
std::vector<std::size_t> DatagramSizes(const std::filesystem::path& file) {
  std::ifstream in(file);
  std::vector<std::size_t> sizes;
  std::string line;
  const std::regex re(R"(udp \d+ -> \d+ len (\d+)$)");
  std::smatch m;
  while (std::getline(in, line)) {
    if (std::regex_search(line, m, re)) sizes.push_back(std::stoul(m[1]));
  }
  return sizes;
}

UniqueFd Bound(int type) {
  UniqueFd fd(::socket(AF_INET, type, 0));
  sockaddr_in sa = MakeSockaddr(*ParseIpv4("127.0.0.1"), 0);
  EXPECT_EQ(::bind(fd.get(), reinterpret_cast<sockaddr*>(&sa), sizeof(sa)), 0);
  return fd;
}

int PortOf(int fd) {
  sockaddr_in sa{};
  socklen_t len = sizeof(sa);
  ::getsockname(fd, reinterpret_cast<sockaddr*>(&sa), &len);
  return ntohs(sa.sin_port);
}

void SendAll(int fd, std::span<const std::uint8_t> bytes) {
  std::size_t off = 0;
  while (off < bytes.size()) {
    const ssize_t n = ::send(fd, bytes.data() + off, bytes.size() - off, MSG_NOSIGNAL);
    if (n <= 0) return;
    off += static_cast<std::size_t>(n);
  }
}

// Replays one scenario to our client and returns the poses it decoded.
std::vector<TrackerReport> Replay(const std::filesystem::path& dir, std::size_t expected) {
  const bool lob = std::filesystem::exists(dir / "client_to_server_udp_lob.bin");
  const auto tcp_bytes = testing::ReadBytes(dir / "server_to_client.bin");
  UniqueFd listener = Bound(SOCK_STREAM);
  ::listen(listener.get(), 1);
  UniqueFd lob_socket = Bound(SOCK_DGRAM);
  const int port = lob ? PortOf(lob_socket.get()) : PortOf(listener.get());
  std::atomic<bool> done{false};

  std::thread fake([&] {
    UniqueFd conn;
    if (!lob) {
      conn.Reset(::accept(listener.get(), nullptr, nullptr));
      SendAll(conn.get(), tcp_bytes);
      while (!done) std::this_thread::sleep_for(std::chrono::milliseconds(5));
      return;
    }
    // Lob: wait for the request, call back, learn the client's UDP port from its description.
    std::uint8_t buf[2048];
    pollfd p{lob_socket.get(), POLLIN, 0};
    if (::poll(&p, 1, 10000) <= 0) return;
    const ssize_t n = ::recv(lob_socket.get(), buf, sizeof(buf), 0);
    const auto req = DecodeLobRequest(std::span<const std::uint8_t>(buf, static_cast<std::size_t>(n)));
    if (!req) return;
    conn.Reset(::socket(AF_INET, SOCK_STREAM, 0));
    sockaddr_in sa = MakeSockaddr(*ParseIpv4(req->host), req->port);
    if (::connect(conn.get(), reinterpret_cast<sockaddr*>(&sa), sizeof(sa)) != 0) return;
    Connection reader(std::make_shared<NameRegistry>(), Connection::Options{});
    while (!reader.peer_udp()) {
      const ssize_t r = ::recv(conn.get(), buf, sizeof(buf), 0);
      if (r <= 0) return;
      reader.OnTcpBytes(std::span<const std::uint8_t>(buf, static_cast<std::size_t>(r)),
                        [](const ReceivedMessage&) {});
    }
    SendAll(conn.get(), tcp_bytes);
    std::this_thread::sleep_for(std::chrono::milliseconds(200));  // descriptions first, as captured
    const auto udp_bytes = testing::ReadBytes(dir / "server_to_client_udp.bin");
    UniqueFd udp(::socket(AF_INET, SOCK_DGRAM, 0));
    sockaddr_in to = MakeSockaddr(*ParseIpv4(reader.peer_udp()->first), reader.peer_udp()->second);
    std::size_t off = 0;
    for (std::size_t size : DatagramSizes(dir / "udp_datagrams.txt")) {
      if (off + size > udp_bytes.size()) break;
      ::sendto(udp.get(), udp_bytes.data() + off, size, 0, reinterpret_cast<sockaddr*>(&to), sizeof(to));
      off += size;
      std::this_thread::sleep_for(std::chrono::microseconds(300));  // loopback UDP buffer headroom
    }
    while (!done) std::this_thread::sleep_for(std::chrono::milliseconds(5));
  });

  VrpnTrackerClient client(std::string("Tracker0@") + (lob ? "" : "tcp://") + "127.0.0.1:" +
                           std::to_string(port));
  std::vector<TrackerReport> reports;
  client.SetPoseCallback([&](const TrackerReport& r) { reports.push_back(r); });
  const auto end = Clock::now() + std::chrono::seconds(20);
  while (Clock::now() < end && reports.size() < expected) client.Poll(0.01);
  // Keep reading briefly: there must be no further, unexpected reports.
  for (int i = 0; i < 20; ++i) client.Poll(0.005);
  done = true;
  fake.join();
  return reports;
}

TEST(VrpnTrackerClient, DecodesReferenceServerBytesLikeTheReferenceClient) {
  int scenarios = 0;
  for (const auto& dir : testing::TranscriptScenarios()) {
    if (!std::filesystem::exists(dir / "client.csv")) continue;
    SCOPED_TRACE(dir.filename().string());
    const auto csv = testing::ReadClientCsv(dir / "client.csv");
    auto reports = Replay(dir, csv.size());
    ASSERT_GE(reports.size(), csv.size());
    std::stable_sort(reports.begin(), reports.end(), [](const auto& a, const auto& b) {
      return std::tie(a.time.sec, a.time.usec, a.sensor) < std::tie(b.time.sec, b.time.usec, b.sensor);
    });
    for (std::size_t i = 0; i < csv.size(); ++i) {
      SCOPED_TRACE(i);
      const auto& r = reports[i];
      EXPECT_EQ(r.sensor, csv[i].sensor);
      EXPECT_EQ(r.time.sec, csv[i].sec);
      EXPECT_EQ(r.time.usec, csv[i].usec);
      double v[7] = {r.transmitter_from_receiver.translation.x(), r.transmitter_from_receiver.translation.y(),
                     r.transmitter_from_receiver.translation.z()};
      QuaternionToXyzwArray(r.transmitter_from_receiver.rotation, v + 3);
      // 17 significant digits in client.csv round-trip doubles exactly.
      for (int k = 0; k < 7; ++k) EXPECT_EQ(v[k], csv[i].v[k]) << k;
    }
    ++scenarios;
  }
  EXPECT_EQ(scenarios, 9);
}

}  // namespace
}  // namespace trackcal::vrpn
