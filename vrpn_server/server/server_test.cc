// VrpnServer's connection slots under clients that stall (halfway through a message, or not
// reading), and its connection log lines. Timeouts are injected through ServerOptions; the
// waits below are bounded polls that end as soon as the server has acted.
#include "vrpn_server/server/server.h"

#include <gtest/gtest.h>
#include <poll.h>
#include <sys/socket.h>

#include <algorithm>
#include <chrono>
#include <functional>
#include <mutex>
#include <regex>
#include <string>
#include <thread>
#include <vector>

#include "vrpn_server/client/tracker_client.h"
#include "vrpn_server/net/socket_util.h"
#include "vrpn_server/server/loopback_testing.h"

namespace trackcal::vrpn {
namespace {

using trackcal::testing::LoopbackOptions;
using trackcal::testing::PollUntil;

using Clock = std::chrono::steady_clock;

std::shared_ptr<ServerCatalog> MakeCatalog() {
  auto catalog = std::make_shared<ServerCatalog>();
  TrackerSpec spec;
  spec.name = "Tracker0";
  spec.num_sensors = 1;
  catalog->AddTracker(spec);
  return catalog;
}

// A raw TCP connection to the server (rcvbuf > 0: that receive buffer, set before connecting).
UniqueFd RawConnect(int port, int rcvbuf = 0) {
  UniqueFd fd(::socket(AF_INET, SOCK_STREAM, 0));
  if (rcvbuf > 0) ::setsockopt(fd.get(), SOL_SOCKET, SO_RCVBUF, &rcvbuf, sizeof(rcvbuf));
  const sockaddr_in dst = MakeSockaddr(*ParseIpv4("127.0.0.1"), port);
  EXPECT_EQ(::connect(fd.get(), reinterpret_cast<const sockaddr*>(&dst), sizeof(dst)), 0);
  return fd;
}

void SendAll(const UniqueFd& fd, const std::vector<std::uint8_t>& bytes) {
  ASSERT_EQ(::send(fd.get(), bytes.data(), bytes.size(), MSG_NOSIGNAL),
            static_cast<ssize_t>(bytes.size()));
}

std::vector<std::uint8_t> Cookie() {
  const auto c = MakeCookie();
  return std::vector<std::uint8_t>(c.begin(), c.end());
}

// The cookie, then a header announcing a 1000-byte message and 10 bytes of its payload.
std::vector<std::uint8_t> CookieAndPartOfAMessage() {
  std::vector<std::uint8_t> bytes(kCookieSize + kHeaderSize + 10, 0);
  const auto cookie = MakeCookie();
  std::copy(cookie.begin(), cookie.end(), bytes.begin());
  StoreU32(1000, bytes.data() + kCookieSize);
  return bytes;
}

// Whether the server closed a raw peer's connection within timeout_s (reading what it sent).
bool ClosedByServer(const UniqueFd& fd, double timeout_s) {
  const auto end = Clock::now() + std::chrono::duration<double>(timeout_s);
  std::vector<std::uint8_t> buf(1 << 16);
  while (Clock::now() < end) {
    pollfd p{fd.get(), POLLIN, 0};
    if (::poll(&p, 1, 10) <= 0) continue;
    const ssize_t n = ::recv(fd.get(), buf.data(), buf.size(), 0);
    if (n == 0 || (n < 0 && errno == ECONNRESET)) return true;
  }
  return false;
}

// Log lines, collected from the server's threads.
struct Lines {
  std::mutex mutex;
  std::vector<std::string> lines;
  LogFunction Sink() {
    return [this](const std::string& line) {
      std::lock_guard<std::mutex> lock(mutex);
      lines.push_back(line);
    };
  }
  int Count(const std::string& what) {
    std::lock_guard<std::mutex> lock(mutex);
    return static_cast<int>(std::count_if(lines.begin(), lines.end(), [&](const std::string& l) {
      return l.find(what) != std::string::npos;
    }));
  }
  // The number in the first line matching `pattern` (one capture group), or -1.
  long Number(const std::string& pattern) {
    std::lock_guard<std::mutex> lock(mutex);
    const std::regex re(pattern);
    for (const std::string& l : lines) {
      std::smatch m;
      if (std::regex_search(l, m, re)) return std::stol(m[1]);
    }
    return -1;
  }
};

// A client that sent a valid cookie and a header, then stalled, kept its slot for ever (only a
// bad length or cookie closed a connection). A byte now and then does not keep it either: the
// clock runs from the message's first byte. A served client that sends nothing stays.
TEST(VrpnServerSlots, AClientStuckHalfwayThroughAMessageIsClosed) {
  ServerOptions options = LoopbackOptions();
  options.incomplete_message_timeout_s = 0.3;
  VrpnServer server(MakeCatalog(), options, [](const std::string&) {});
  server.Start();
  VrpnTrackerClient good("Tracker0@tcp://127.0.0.1:" + std::to_string(server.port()));
  ASSERT_TRUE(PollUntil({&good}, [&] { return good.pong_received(); }));

  const auto stuck = RawConnect(server.port());
  SendAll(stuck, CookieAndPartOfAMessage());
  const auto trickle = RawConnect(server.port());
  SendAll(trickle, CookieAndPartOfAMessage());
  const auto start = Clock::now();
  bool trickle_closed = false;
  // One more byte of the message every 50 ms (the 1000 bytes would take 50 s).
  while (!trickle_closed && Clock::now() - start < std::chrono::seconds(10)) {
    trickle_closed =
        ::send(trickle.get(), "x", 1, MSG_NOSIGNAL) != 1 || ClosedByServer(trickle, 0.05);
    good.Poll(0.0);
  }
  EXPECT_TRUE(trickle_closed);
  EXPECT_TRUE(ClosedByServer(stuck, 5.0));
  EXPECT_TRUE(PollUntil({&good}, [&] { return server.stats().closed_protocol == 2; }));
  EXPECT_TRUE(good.connected());
  EXPECT_EQ(server.stats().clients, 1);
}

// A client that connects and sends nothing gets our cookie at once (both sides write theirs without
// waiting, as the reference does) and is closed when handshake_timeout_s ends; a client whose
// cookie comes in two pieces, a while apart, completes its handshake and is served.
TEST(VrpnServerSlots, AClientThatSendsNoCookieIsClosedOneWhoseCookieIsSplitIsServed) {
  ServerOptions options = LoopbackOptions();
  options.handshake_timeout_s = 0.5;
  Lines lines;
  VrpnServer server(MakeCatalog(), options, lines.Sink());
  server.Start();
  const auto silent = RawConnect(server.port());
  const auto split = RawConnect(server.port());
  const auto cookie = Cookie();
  SendAll(split, std::vector<std::uint8_t>(cookie.begin(), cookie.begin() + 10));
  std::vector<std::uint8_t> first(kCookieSize);
  ASSERT_EQ(::recv(silent.get(), first.data(), first.size(), MSG_WAITALL),
            static_cast<ssize_t>(kCookieSize));
  EXPECT_EQ(first, cookie);
  std::this_thread::sleep_for(std::chrono::milliseconds(200));
  SendAll(split, std::vector<std::uint8_t>(cookie.begin() + 10, cookie.end()));
  EXPECT_TRUE(ClosedByServer(silent, 5.0));
  EXPECT_EQ(lines.Count("handshake timed out"), 1);
  // Well past the split client's own handshake deadline.
  EXPECT_FALSE(ClosedByServer(split, 0.8));
  EXPECT_EQ(server.stats().clients, 1);
}

// A stream that is never between two messages, each of which completes in time, is not a stall:
// the clock restarts with every whole message.
TEST(VrpnServerSlots, MessagesThatEachCompleteInTimeKeepTheConnection) {
  ServerOptions options = LoopbackOptions();
  options.incomplete_message_timeout_s = 1.0;
  VrpnServer server(MakeCatalog(), options, [](const std::string&) {});
  server.Start();
  // 40-byte messages with ids never described (dropped by the server, harmlessly).
  std::vector<std::uint8_t> message;
  AppendMessage(&message, Timestamp{}, 5, 9, 0, std::vector<std::uint8_t>(16, 0));
  ASSERT_EQ(message.size(), 40u);
  const auto fd = RawConnect(server.port());
  std::vector<std::uint8_t> bytes = Cookie();
  bytes.insert(bytes.end(), message.begin(), message.begin() + 20);
  SendAll(fd, bytes);
  // Every 0.1 s the rest of a message and the first half of the next: 1.5 s, always mid-message.
  for (int i = 0; i < 15; ++i) {
    ASSERT_FALSE(ClosedByServer(fd, 0.1));
    bytes.assign(message.begin() + 20, message.end());
    bytes.insert(bytes.end(), message.begin(), message.begin() + 20);
    SendAll(fd, bytes);
  }
  EXPECT_FALSE(ClosedByServer(fd, 0.1));
  EXPECT_EQ(server.stats().closed_protocol, 0u);
  EXPECT_EQ(server.stats().clients, 1);
}

// A client that takes none of its output kept its slot until max_output_bytes overflowed: at a
// tracker's rate hours later, and never when nothing more is published. It is dropped after
// unread_output_timeout_s; a client that reads is not.
TEST(VrpnServerSlots, AClientThatTakesNoneOfItsOutputIsDropped) {
  ServerOptions options = LoopbackOptions();
  options.unread_output_timeout_s = 1.0;  // the good client below reads far more often
  options.max_output_bytes = 256 << 20;   // never reached here: only the timeout can drop it
  VrpnServer server(MakeCatalog(), options, [](const std::string&) {});
  server.Start();
  VrpnTrackerClient good("Tracker0@tcp://127.0.0.1:" + std::to_string(server.port()));
  int reports = 0;
  good.SetPoseCallback([&](const TrackerReport&) { ++reports; });
  ASSERT_TRUE(PollUntil({&good}, [&] { return good.pong_received(); }));
  const auto deaf = RawConnect(server.port(), /*rcvbuf=*/4096);
  SendAll(deaf, Cookie());
  ASSERT_TRUE(PollUntil({&good}, [&] { return server.stats().clients == 2; }));
  // 100000 reports (8.8 MB) fill every buffer between the server and the deaf client (4 MB at
  // most of send buffer on Linux, tcp_wmem), then publishing stops.
  for (int i = 0; i < 100000; ++i) {
    server.PublishPose(0, 0, Rigid3d(), Timestamp::Now());
    if (i % 1000 == 999) good.Poll(0.0);
  }
  EXPECT_TRUE(PollUntil({&good}, [&] { return server.stats().dropped_slow == 1; }));
  EXPECT_TRUE(ClosedByServer(deaf, 5.0));
  EXPECT_TRUE(PollUntil(
      {&good}, [&] { return reports == 100000; }, 30.0));
  EXPECT_TRUE(good.connected());
  EXPECT_EQ(server.stats().clients, 1);
}

// Each client could hold max_output_bytes (1 MiB) of unsent output: 256 MiB at --max-clients 256
// with half-open clients. Past max_total_output_bytes across clients, the client with the most
// unsent output is dropped, with one line, and counted; a client that reads is not affected, nor
// is a non-reading client with less waiting while the total is back under the cap.
TEST(VrpnServerSlots, TheClientWithTheMostUnsentOutputIsDroppedPastTheTotalCap) {
  ServerOptions options = LoopbackOptions();
  options.max_output_bytes = 256 << 20;      // never reached here: only the total can drop one
  options.max_total_output_bytes = 8 << 20;  // reached by the two deaf clients together
  options.unread_output_timeout_s = 600.0;   // far beyond the test
  options.dead_client_timeout_s = 0.0;       // the kernel does not time them out either
  ServerOptions tiny = options;
  tiny.max_total_output_bytes = 100;
  EXPECT_THROW(tiny.Check(), std::invalid_argument);
  Lines log;
  VrpnServer server(MakeCatalog(), options, log.Sink());
  server.Start();
  VrpnTrackerClient good("Tracker0@tcp://127.0.0.1:" + std::to_string(server.port()));
  int reports = 0;
  good.SetPoseCallback([&](const TrackerReport&) { ++reports; });
  ASSERT_TRUE(PollUntil({&good}, [&] { return good.pong_received(); }));
  int published = 0;
  const auto publish = [&](int n) {
    for (int i = 0; i < n; ++i, ++published) {
      server.PublishPose(0, 0, Rigid3d(), Timestamp::Now());
      if (published % 1000 == 999) good.Poll(0.0);
    }
  };
  const auto most = RawConnect(server.port(), /*rcvbuf=*/4096);
  SendAll(most, Cookie());
  ASSERT_TRUE(PollUntil({&good}, [&] { return server.stats().clients == 2; }));
  // 100000 reports (8.8 MB) fill the kernel's buffers towards `most` (4 MB at most of send buffer
  // on Linux, tcp_wmem) and leave several MB waiting in the server: under the cap alone.
  publish(100000);
  EXPECT_EQ(server.stats().clients, 2);
  const auto less = RawConnect(server.port(), /*rcvbuf=*/4096);
  SendAll(less, Cookie());
  ASSERT_TRUE(PollUntil({&good}, [&] { return server.stats().clients == 3; }));
  // Both now get every report, `most` always with more waiting: published until the total passes
  // the cap (at most 8 MiB more: `most` alone would pass it).
  for (int batch = 0; batch < 100 && server.stats().dropped_over_total == 0; ++batch) publish(1000);
  EXPECT_EQ(server.stats().dropped_over_total, 1u);
  EXPECT_TRUE(ClosedByServer(most, 5.0));
  EXPECT_TRUE(PollUntil(
      {&good}, [&] { return reports == published; }, 30.0));
  EXPECT_TRUE(good.connected());
  EXPECT_EQ(server.stats().clients, 2);  // the good client and `less`
  EXPECT_EQ(server.stats().dropped_slow, 0u);
  EXPECT_EQ(log.Count("the most unsent output of all clients"), 1);
}

// A client that stops reading with a small receive buffer is ended by the kernel (the TCP user
// timeout of dead_client_timeout_s, its window staying closed) before unread_output_timeout_s:
// that close was logged as "read: Connection timed out" and not counted as dropped for not
// reading (a live run: 5 deaf clients closed so, status "0 dropped for not reading").
TEST(VrpnServerSlots, AClientTheKernelTimesOutIsSaidToHaveStoppedReading) {
  ServerOptions options = LoopbackOptions();
  options.dead_client_timeout_s = 1.0;      // the kernel's limit, reached first
  options.unread_output_timeout_s = 600.0;  // far beyond the test
  options.max_output_bytes = 256 << 20;     // never reached here
  Lines log;
  VrpnServer server(MakeCatalog(), options, log.Sink());
  server.Start();
  VrpnTrackerClient good("Tracker0@tcp://127.0.0.1:" + std::to_string(server.port()));
  ASSERT_TRUE(PollUntil({&good}, [&] { return good.pong_received(); }));
  const auto deaf = RawConnect(server.port(), /*rcvbuf=*/4096);
  SendAll(deaf, Cookie());
  ASSERT_TRUE(PollUntil({&good}, [&] { return server.stats().clients == 2; }));
  // Reports at about 10 kHz until the deaf client is gone; its window closes within milliseconds.
  // Generous against a loaded machine: the kernel acts after 1 s (measured 1.2 s).
  const auto end = Clock::now() + std::chrono::seconds(20);
  while (server.stats().clients == 2 && Clock::now() < end) {
    for (int i = 0; i < 10; ++i) server.PublishPose(0, 0, Rigid3d(), Timestamp::Now());
    good.Poll(0.001);
  }
  EXPECT_EQ(server.stats().clients, 1);
  EXPECT_TRUE(good.connected());
  EXPECT_EQ(server.stats().dropped_slow, 1u);
  EXPECT_EQ(log.Count("Connection timed out"), 0);
  EXPECT_EQ(log.Count(": nothing acknowledged for 1 s (not reading, or its host is gone): dropped"),
            1);
}

// Served connections stuck halfway through a message filled max_clients and every new client was
// refused (only connections waiting for their handshake made room). The one stalled longest now
// makes room; a client being served is never closed for another.
TEST(VrpnServerSlots, StalledConnectionsCannotLockNewClientsOut) {
  ServerOptions options = LoopbackOptions();
  options.max_clients = 3;
  options.incomplete_message_timeout_s = 600.0;  // far beyond the test: only eviction helps
  options.min_stall_to_evict_s = 0.05;
  VrpnServer server(MakeCatalog(), options, [](const std::string&) {});
  server.Start();
  std::vector<UniqueFd> stuck;
  for (int i = 0; i < 3; ++i) {
    stuck.push_back(RawConnect(server.port()));
    SendAll(stuck.back(), CookieAndPartOfAMessage());
    // One at a time, so the order of their stalls is the connect order.
    ASSERT_TRUE(PollUntil({}, [&] { return server.stats().clients == i + 1; }));
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  }
  VrpnTrackerClient good("Tracker0@tcp://127.0.0.1:" + std::to_string(server.port()));
  ASSERT_TRUE(PollUntil({&good}, [&] { return good.pong_received(); }));
  EXPECT_TRUE(ClosedByServer(stuck[0], 5.0));  // stalled longest
  EXPECT_FALSE(ClosedByServer(stuck[1], 0.1));
  VrpnTrackerClient second("Tracker0@tcp://127.0.0.1:" + std::to_string(server.port()));
  VrpnTrackerClient third("Tracker0@tcp://127.0.0.1:" + std::to_string(server.port()));
  ASSERT_TRUE(PollUntil({&good, &second, &third},
                        [&] { return second.pong_received() && third.pong_received(); }));
  EXPECT_EQ(server.stats().evicted, 3u);
  // Now every slot holds a client being served: a new connection is refused.
  const auto refused = RawConnect(server.port());
  SendAll(refused, Cookie());
  EXPECT_TRUE(ClosedByServer(refused, 5.0));
  for (int i = 0; i < 10; ++i) server.PublishPose(0, 0, Rigid3d(), Timestamp::Now());
  for (auto* c : {&good, &second, &third}) c->Poll(0.05);
  EXPECT_TRUE(good.connected() && second.connected() && third.connected());
  EXPECT_EQ(server.stats().clients, 3);
  EXPECT_EQ(server.stats().evicted, 3u);
}

// Each connection closed for a protocol fault said why twice ("<client>: closing: X", then
// "closed <client>: X"), and connection lines had no cap: a connect flood wrote tens of thousands
// of lines. The reason is said once, and connection lines are capped per window like refusals,
// with the count of those left out logged when the window ends.
TEST(VrpnServerSlots, ConnectionLinesSayTheReasonOnceAndAreCapped) {
  ServerOptions options = LoopbackOptions();
  options.refusal_log_window_s =
      2.0;  // the 150 connections take ~0.1 s; 2 s spares a loaded machine
  Lines log;
  VrpnServer server(MakeCatalog(), options, log.Sink());
  server.Start();
  std::vector<std::uint8_t> bad = Cookie();
  bad[0] = 'X';
  for (int i = 0; i < 150; ++i) {
    const auto fd = RawConnect(server.port());
    SendAll(fd, bad);
    ASSERT_TRUE(ClosedByServer(fd, 5.0));
  }
  ASSERT_EQ(server.stats().closed_protocol, 150u);
  // 300 connection lines (connected, closed): 100 logged, the count of the others once the
  // window has ended, without any further connection.
  ASSERT_TRUE(PollUntil(
      {}, [&] { return log.Count("were not logged") == 1; }, 10.0));
  EXPECT_EQ(log.Count("closing"), 0);
  const int connected = log.Count("connected tcp client");
  const int closed = log.Count("bad cookie");
  EXPECT_EQ(connected + closed, 100);
  EXPECT_EQ(log.Count("connection lines logged in 2 s"), 1);
  EXPECT_EQ(log.Number(R"((\d+) connection lines .* were not logged)"), 200);
  // The next window logs again.
  const auto fd = RawConnect(server.port());
  SendAll(fd, bad);
  ASSERT_TRUE(ClosedByServer(fd, 5.0));
  EXPECT_TRUE(PollUntil({}, [&] { return log.Count("bad cookie") == closed + 1; }));
}

// The count of the lines left out was logged only when the window ended: a server stopped
// before that (any run shorter than a minute after a flood) never said how many it left out
// (measured: 1000 connections, 745 closed to make room, 100 of those logged, no count).
TEST(VrpnServerSlots, TheCountOfLinesLeftOutIsLoggedAtStop) {
  ServerOptions options = LoopbackOptions();
  options.refusal_log_window_s = 3600.0;  // does not end during the test
  Lines log;
  VrpnServer server(MakeCatalog(), options, log.Sink());
  server.Start();
  std::vector<std::uint8_t> bad = Cookie();
  bad[0] = 'X';
  for (int i = 0; i < 60; ++i) {
    const auto fd = RawConnect(server.port());
    SendAll(fd, bad);
    ASSERT_TRUE(ClosedByServer(fd, 5.0));
  }
  ASSERT_EQ(server.stats().closed_protocol, 60u);
  EXPECT_EQ(log.Count("were not logged"), 0);
  server.Stop();
  // 120 connection lines (connected, closed): 100 logged, the count of the other 20 at stop.
  EXPECT_EQ(log.Count("were not logged"), 1);
  EXPECT_EQ(log.Number(R"((\d+) connection lines .* were not logged)"), 20);
  EXPECT_EQ(log.Count("refused or ignored"), 0);  // nothing to count there
}

TEST(VrpnServerSlots, BadStallOptionsThrowNamingTheField) {
  for (auto set : std::vector<std::function<void(ServerOptions&)>>{
           [](ServerOptions& o) { o.incomplete_message_timeout_s = 0; },
           [](ServerOptions& o) { o.unread_output_timeout_s = -1; },
           [](ServerOptions& o) { o.min_stall_to_evict_s = -0.5; }}) {
    ServerOptions o = LoopbackOptions();
    set(o);
    EXPECT_THROW(VrpnServer(MakeCatalog(), o), std::invalid_argument);
  }
}

}  // namespace
}  // namespace trackcal::vrpn
