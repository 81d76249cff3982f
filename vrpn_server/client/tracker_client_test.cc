// Our server and our client over loopback: both connect modes, UDP channel, many clients, and
// misbehaving clients that must not disturb the others.
#include "vrpn_server/client/tracker_client.h"

#include <arpa/inet.h>
#include <fcntl.h>
#include <gtest/gtest.h>
#include <linux/sockios.h>
#include <poll.h>
#include <sys/ioctl.h>
#include <sys/resource.h>
#include <sys/socket.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <stdexcept>
#include <string_view>
#include <thread>

#include "tests/test_utils.h"
#include "vrpn_server/net/socket_util.h"
#include "vrpn_server/server/loopback_testing.h"
#include "vrpn_server/server/server.h"

namespace trackcal::vrpn {
namespace {

using trackcal::testing::LoopbackOptions;
using trackcal::testing::PollUntil;

using Clock = std::chrono::steady_clock;

std::shared_ptr<ServerCatalog> MakeCatalog(int sensors = 2) {
  auto catalog = std::make_shared<ServerCatalog>();
  TrackerSpec spec;
  spec.name = "Tracker0";
  spec.num_sensors = sensors;
  catalog->AddTracker(spec);
  catalog->AddButton(ButtonSpec{"Stylus0", 2});
  return catalog;
}

struct Collected {
  std::vector<TrackerReport> reports;
  std::vector<std::string> texts;
  std::vector<std::string> types;
};

void Attach(VrpnTrackerClient& client, Collected& c) {
  client.SetPoseCallback([&c](const TrackerReport& r) { c.reports.push_back(r); });
  client.SetMessageCallback([&c](const ReceivedMessage& m) {
    c.types.emplace_back(m.type);
    if (m.type == kTextType) c.texts.push_back(DecodeText(m.payload)->text);
  });
}

Rigid3d RandomPose() {
  auto& rng = testing::TestRng();
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  return Rigid3d(testing::RandomRotation(rng), Eigen::Vector3d(u(rng), u(rng), u(rng)));
}

TEST(ParseVrpnName, Nominal) {
  auto n = ParseVrpnName("Tracker0@tcp://localhost:3999");
  EXPECT_EQ(n.device, "Tracker0");
  EXPECT_EQ(n.host, "localhost");
  EXPECT_EQ(n.port, 3999);
  EXPECT_TRUE(n.tcp);
  n = ParseVrpnName("Tracker0@localhost");
  EXPECT_FALSE(n.tcp);
  EXPECT_EQ(n.port, kDefaultPort);
  n = ParseVrpnName("Tracker0@x-vrpn://h:4000");
  EXPECT_FALSE(n.tcp);
  EXPECT_EQ(n.host, "h");
  EXPECT_EQ(n.port, 4000);
  n = ParseVrpnName("Tracker0@tcp:h:4001");
  EXPECT_TRUE(n.tcp);
  EXPECT_EQ(n.port, 4001);
  // The reference reads the device up to the first '@' (vrpn_copy_service_name): "a@b@h" never
  // reaches a device "a@b" there, and is an error saying why here.
  try {
    ParseVrpnName("a@b@tcp://h");
    ADD_FAILURE() << "no error";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("a second '@'"), std::string::npos) << e.what();
  }
  EXPECT_THROW(ParseVrpnName("Tracker0"), std::invalid_argument);
  EXPECT_THROW(ParseVrpnName("Tracker0@h:99999"), std::invalid_argument);
  // Hosts the lookup would retry for ever: a blank, a second port, IPv6.
  for (const char* bad : {"Tracker0@ host", "Tracker0@[::1]:3883",
                          "Tracker0@tcp://127.0.0.1:3883:1", "Tracker0@host name"}) {
    EXPECT_THROW(ParseVrpnName(bad), std::invalid_argument) << bad;
  }
  EXPECT_EQ(ParseVrpnName("Head@lab-pc_2.example.org").host, "lab-pc_2.example.org");
}

// A served device name never holds a blank or a control byte (vrpn.cfg splits its lines at blanks),
// so a client asking for " Tracker0" or "Tracker0\t" would wait for ever for a device that cannot
// exist: the name is refused, and the message shows where the blank is.
TEST(ParseVrpnName, BlankOrControlInDeviceIsRefused) {
  for (const std::string& bad :
       std::vector<std::string>{" Tracker0@localhost", "Tracker0 @localhost", "Track er0@localhost",
                                "Tracker0\t@localhost", std::string("Tra\x01ker0@localhost")}) {
    try {
      ParseVrpnName(bad);
      ADD_FAILURE() << "no error for '" << bad << "'";
    } catch (const std::invalid_argument& e) {
      EXPECT_NE(std::string(e.what()).find("device name"), std::string::npos) << e.what();
      EXPECT_NE(std::string(e.what()).find("blank or control"), std::string::npos) << e.what();
    }
  }
  // A name that is not ASCII is not refused: the reference serves any printable bytes.
  EXPECT_EQ(ParseVrpnName("Ger\xc3\xa4t@localhost").device, "Ger\xc3\xa4t");
}

TEST(ParseVrpnName, UnknownSchemeIsNamed) {
  // Before, "udp://host" was read as host "udp" with a bad port "//host".
  try {
    ParseVrpnName("Tracker0@udp://host:3883");
    FAIL() << "accepted an unknown scheme";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("unknown scheme 'udp://'"), std::string::npos) << e.what();
  }
}

TEST(VrpnServer, NominalDirectTcp) {
  VrpnServer server(MakeCatalog(), LoopbackOptions(), [](const std::string&) {});
  server.Start();
  VrpnTrackerClient client("Tracker0@tcp://127.0.0.1:" + std::to_string(server.port()));
  Collected got;
  Attach(client, got);
  ASSERT_TRUE(PollUntil({&client}, [&] { return client.pong_received(); }));
  std::vector<Rigid3d> sent;
  for (int i = 0; i < 20; ++i) {
    sent.push_back(RandomPose());
    server.PublishPose(0, i % 2, sent.back(), Timestamp{1795255605u, static_cast<std::uint32_t>(i)});
  }
  ASSERT_TRUE(PollUntil({&client}, [&] { return got.reports.size() == 20; }));
  for (int i = 0; i < 20; ++i) {
    EXPECT_EQ(got.reports[i].sensor, i % 2);
    EXPECT_EQ(got.reports[i].time.usec, static_cast<std::uint32_t>(i));
    EXPECT_FALSE(got.reports[i].via_udp);  // tcp:// never uses UDP
    // Doubles travel bit-exactly.
    EXPECT_EQ(got.reports[i].transmitter_from_receiver.translation, sent[i].translation);
    EXPECT_EQ(got.reports[i].transmitter_from_receiver.rotation.coeffs(), sent[i].rotation.coeffs());
  }
  EXPECT_EQ(server.stats().clients, 1);
}

TEST(VrpnServer, LobCallbackWithUdpChannel) {
  VrpnServer server(MakeCatalog(), LoopbackOptions(), [](const std::string&) {});
  server.Start();
  VrpnTrackerClient client("Tracker0@127.0.0.1:" + std::to_string(server.port()));
  Collected got;
  Attach(client, got);
  ASSERT_TRUE(PollUntil({&client}, [&] { return client.pong_received(); }));
  // The server learns our UDP port from the description sent right after the cookie; reports
  // published after the pong travel over UDP.
  const Rigid3d pose = RandomPose();
  for (int i = 0; i < 10; ++i) server.PublishPose(0, 1, pose, Timestamp::Now());
  ASSERT_TRUE(PollUntil({&client}, [&] { return got.reports.size() == 10; }));
  EXPECT_TRUE(client.udp_active());
  EXPECT_EQ(got.reports.back().transmitter_from_receiver.translation, pose.translation);
}

TEST(VrpnServer, TwoClientsBothModesGetEveryReportTextAndButtons) {
  VrpnServer server(MakeCatalog(), LoopbackOptions(), [](const std::string&) {});
  server.Start();
  const std::string port = std::to_string(server.port());
  VrpnTrackerClient tcp("Tracker0@tcp://127.0.0.1:" + port);
  VrpnTrackerClient lob("Tracker0@127.0.0.1:" + port);
  VrpnTrackerClient stylus("Stylus0@tcp://127.0.0.1:" + port);
  Collected a, b, s;
  Attach(tcp, a);
  Attach(lob, b);
  Attach(stylus, s);
  ASSERT_TRUE(PollUntil({&tcp, &lob, &stylus}, [&] {
    return tcp.pong_received() && lob.pong_received() && stylus.pong_received();
  }));
  for (int i = 0; i < 50; ++i) server.PublishPose(0, 0, RandomPose(), Timestamp::Now());
  server.PublishText(0, TextSeverity::kWarning, "Resetting the tracker");
  server.PublishButton(0, 1, true, Timestamp::Now());
  ASSERT_TRUE(PollUntil({&tcp, &lob, &stylus}, [&] {
    return a.reports.size() == 50 && b.reports.size() == 50 && a.texts.size() == 1 &&
           b.texts.size() == 1 && std::count(s.types.begin(), s.types.end(), kButtonChangeType) == 1;
  }));
  EXPECT_EQ(a.texts[0], "Resetting the tracker");
  // Button states were sent on connect and with the pong (as the reference does), before the
  // change: once more for each further ping the client sent before its pong came.
  const auto change = std::find(s.types.begin(), s.types.end(), kButtonChangeType);
  EXPECT_GE(std::count(s.types.begin(), change, kButtonStatesType), 2);
  EXPECT_EQ(std::count(change, s.types.end(), kButtonStatesType), 0);
  EXPECT_EQ(server.stats().clients, 3);
}

TEST(VrpnServer, UnservedNameGetsNoPongButConnects) {
  VrpnServer server(MakeCatalog(), LoopbackOptions(), [](const std::string&) {});
  server.Start();
  TrackerClientOptions fast;
  fast.ping_interval_s = 0.05;
  VrpnTrackerClient client("Tracker9@tcp://127.0.0.1:" + std::to_string(server.port()), fast);
  ASSERT_TRUE(PollUntil({&client}, [&] { return client.connected(); }));
  PollUntil({&client}, [] { return false; }, 0.5);  // ten pings' worth
  EXPECT_FALSE(client.pong_received());
}

TEST(VrpnServer, StatisticsForRequests) {
  VrpnServer server(MakeCatalog(3), LoopbackOptions(), [](const std::string&) {});
  server.Start();
  VrpnTrackerClient client("Tracker0@tcp://127.0.0.1:" + std::to_string(server.port()));
  Collected got;
  Attach(client, got);
  client.RequestStaticInfo();
  ASSERT_TRUE(PollUntil({&client}, [&] {
    return std::count(got.types.begin(), got.types.end(), kWorkspaceType) == 1;
  }));
  EXPECT_EQ(std::count(got.types.begin(), got.types.end(), kUnitToSensorType), 3);
  EXPECT_EQ(std::count(got.types.begin(), got.types.end(), kToRoomType), 1);
}

// A raw TCP peer for misbehaviour tests.
UniqueFd RawConnect(int port, int rcvbuf = 0) {
  UniqueFd fd(::socket(AF_INET, SOCK_STREAM, 0));
  if (rcvbuf > 0) ::setsockopt(fd.get(), SOL_SOCKET, SO_RCVBUF, &rcvbuf, sizeof(rcvbuf));
  sockaddr_in sa = MakeSockaddr(*ParseIpv4("127.0.0.1"), port);
  EXPECT_EQ(::connect(fd.get(), reinterpret_cast<sockaddr*>(&sa), sizeof(sa)), 0);
  return fd;
}

TEST(VrpnServer, GarbageAndOversizedClientsAreClosedOthersUnaffected) {
  VrpnServer server(MakeCatalog(), LoopbackOptions(), [](const std::string&) {});
  server.Start();
  VrpnTrackerClient good("Tracker0@tcp://127.0.0.1:" + std::to_string(server.port()));
  Collected got;
  Attach(good, got);
  ASSERT_TRUE(PollUntil({&good}, [&] { return good.pong_received(); }));

  auto http = RawConnect(server.port());
  const std::string get = "GET / HTTP/1.1\r\nHost: x\r\n\r\n";
  ASSERT_GT(::send(http.get(), get.data(), get.size(), 0), 0);
  auto oversized = RawConnect(server.port());
  auto bytes = MakeCookie();
  std::vector<std::uint8_t> msg(bytes.begin(), bytes.end());
  msg.resize(48, 0);
  StoreU32(0x7fffffff, msg.data() + 24);
  ASSERT_GT(::send(oversized.get(), msg.data(), msg.size(), 0), 0);
  auto random = RawConnect(server.port());
  std::vector<std::uint8_t> junk(5000);
  std::uniform_int_distribution<int> byte(0, 255);
  const auto cookie = MakeCookie();
  std::copy(cookie.begin(), cookie.end(), junk.begin());
  for (std::size_t i = 24; i < junk.size(); ++i) junk[i] = static_cast<std::uint8_t>(byte(testing::TestRng()));
  ::send(random.get(), junk.data(), junk.size(), MSG_NOSIGNAL);

  ASSERT_TRUE(PollUntil({&good}, [&] { return server.stats().closed_protocol >= 2; }));
  for (int i = 0; i < 10; ++i) server.PublishPose(0, 0, RandomPose(), Timestamp::Now());
  ASSERT_TRUE(PollUntil({&good}, [&] { return got.reports.size() == 10; }));
}

// Whether the server closed a raw peer's connection within timeout_s (reading past its cookie).
bool ClosedByServer(const UniqueFd& fd, double timeout_s) {
  const auto end = Clock::now() + std::chrono::duration<double>(timeout_s);
  std::uint8_t buf[4096];
  while (Clock::now() < end) {
    pollfd p{fd.get(), POLLIN, 0};
    if (::poll(&p, 1, 20) <= 0) continue;
    const ssize_t n = ::recv(fd.get(), buf, sizeof(buf), 0);
    if (n == 0 || (n < 0 && errno == ECONNRESET)) return true;
  }
  return false;
}

// Connections that never send their cookie (a port scan, a flood of idle connects) filled
// max_clients and every new client was refused until the handshake timeout (10 s by default,
// again and again while the flood goes on). The one that has waited longest now makes room; a
// client that completed its handshake is never closed for another.
TEST(VrpnServer, IdleConnectionsCannotLockNewClientsOut) {
  ServerOptions options = LoopbackOptions();
  options.max_clients = 3;
  options.handshake_timeout_s = 120.0;  // far beyond the test: only eviction lets clients in
  VrpnServer server(MakeCatalog(), options, [](const std::string&) {});
  server.Start();
  std::vector<UniqueFd> idle;
  for (int i = 0; i < 3; ++i) {
    idle.push_back(RawConnect(server.port()));
    // One at a time, so the server's accept order (and so their ages) is the connect order.
    ASSERT_TRUE(PollUntil({}, [&] { return server.stats().clients == i + 1; }));
  }
  VrpnTrackerClient good("Tracker0@tcp://127.0.0.1:" + std::to_string(server.port()));
  Collected got;
  Attach(good, got);
  ASSERT_TRUE(PollUntil({&good}, [&] { return good.pong_received(); }));
  EXPECT_TRUE(ClosedByServer(idle[0], 5.0));  // the oldest idle connection made room
  EXPECT_FALSE(ClosedByServer(idle[1], 0.1));
  // More idle connects push out each other, never the client that completed its handshake.
  for (int i = 0; i < 6; ++i) {
    idle.push_back(RawConnect(server.port()));
    good.Poll(0.01);
  }
  for (int i = 0; i < 10; ++i) server.PublishPose(0, 0, RandomPose(), Timestamp::Now());
  ASSERT_TRUE(PollUntil({&good}, [&] { return got.reports.size() == 10; }));
  EXPECT_TRUE(good.connected());
  EXPECT_EQ(server.stats().clients, 3);
}

TEST(VrpnServer, StalledClientIsDroppedWithoutBlockingOthers) {
  ServerOptions options = LoopbackOptions();
  options.max_output_bytes = 64 * 1024;
  VrpnServer server(MakeCatalog(), options, [](const std::string&) {});
  server.Start();
  VrpnTrackerClient good("Tracker0@tcp://127.0.0.1:" + std::to_string(server.port()));
  Collected got;
  Attach(good, got);
  ASSERT_TRUE(PollUntil({&good}, [&] { return good.pong_received(); }));
  // Sends its cookie and describes Tracker0 (so the server streams to it), then never reads.
  auto stalled = RawConnect(server.port(), /*rcvbuf=*/4096);
  auto names = std::make_shared<NameRegistry>();
  names->AddSender("Tracker0");
  Connection hello(names, Connection::Options{});
  hello.Start();
  ASSERT_EQ(::send(stalled.get(), hello.tcp_output().data(), hello.tcp_output().size(), 0),
            static_cast<ssize_t>(hello.tcp_output().size()));
  ASSERT_TRUE(PollUntil({&good}, [&] { return server.stats().clients == 2; }));
  // Publish until the stalled client's socket buffers and max_output_bytes overflow (loopback
  // buffers auto-tune to several MB, so the count needed is not fixed), polling the good client.
  int n = 0;
  while (server.stats().dropped_slow == 0 && n < 2000000) {
    for (int i = 0; i < 1000; ++i, ++n) server.PublishPose(0, 0, RandomPose(), Timestamp::Now());
    good.Poll(0.0);
    std::this_thread::sleep_for(std::chrono::milliseconds(1));
  }
  ASSERT_TRUE(PollUntil({&good}, [&] { return static_cast<int>(got.reports.size()) == n; }, 30.0));
  EXPECT_EQ(server.stats().dropped_slow, 1u);
  EXPECT_EQ(server.stats().clients, 1);
}

TEST(VrpnServer, RequestsFromAClientThatDoesNotReadCannotGrowTheServerPastItsOutputLimit) {
  // Each 24-byte Request_Unit_To_Sensor is answered with one 88-byte message per sensor: a client
  // that sends requests and never reads must not make the server build hundreds of MB of replies
  // (every request of a read used to be answered before the output limit was looked at).
  auto catalog = std::make_shared<ServerCatalog>();
  TrackerSpec spec;
  spec.name = "Tracker0";
  spec.num_sensors = 256;
  catalog->AddTracker(spec);
  VrpnServer server(catalog, LoopbackOptions(), [](const std::string&) {});
  server.Start();
  auto fd = RawConnect(server.port(), /*rcvbuf=*/4096);
  auto names = std::make_shared<NameRegistry>();
  const std::int32_t tracker = names->AddSender("Tracker0");
  const std::int32_t request = names->AddType(kRequestUnitToSensorType);
  Connection conn(names, Connection::Options{});
  conn.Start();
  // 10000 requests (240 kB) would be 225 MB of answers.
  for (int i = 0; i < 10000; ++i) conn.Pack(tracker, request, Timestamp::Now(), {});
  rusage before{};
  ::getrusage(RUSAGE_SELF, &before);
  const auto& out = conn.tcp_output();
  std::size_t sent = 0;
  while (sent < out.size()) {
    const ssize_t n = ::send(fd.get(), out.data() + sent, out.size() - sent, MSG_NOSIGNAL);
    if (n <= 0) break;
    sent += static_cast<std::size_t>(n);
  }
  // Every byte reached the server's socket; a client that connects afterwards and gets its pong
  // was served after the server read (and handled) them.
  ASSERT_TRUE(PollUntil({}, [&] {
    int unsent = 0;
    return ::ioctl(fd.get(), SIOCOUTQ, &unsent) == 0 && unsent == 0;
  }));
  VrpnTrackerClient good("Tracker0@tcp://127.0.0.1:" + std::to_string(server.port()));
  ASSERT_TRUE(PollUntil({&good}, [&] { return good.pong_received(); }));
  rusage after{};
  ::getrusage(RUSAGE_SELF, &after);
  // ru_maxrss is in kB: the peak may grow by a few times the 1 MiB limit, not by 100 MB.
  EXPECT_LT(after.ru_maxrss - before.ru_maxrss, 32 * 1024);
}

// Publishes poses of Tracker0 (device 0) and `tracker1` until done(counts) or 10 s, counting the
// Pos_Quat messages per sender that arrive on the raw connection `fd` decoded by `conn`.
std::map<std::string, int> CountPosQuatPerSender(
    VrpnServer& server, int tracker1, int fd, Connection& conn,
    const std::function<bool(std::map<std::string, int>&)>& done) {
  std::map<std::string, int> counts;
  std::uint8_t buf[65536];
  const auto end = Clock::now() + std::chrono::seconds(10);
  while (Clock::now() < end && !done(counts)) {
    server.PublishPose(0, 0, Rigid3d(), Timestamp::Now());
    server.PublishPose(tracker1, 0, Rigid3d(), Timestamp::Now());
    pollfd p{fd, POLLIN, 0};
    if (::poll(&p, 1, 10) <= 0) continue;
    const ssize_t n = ::recv(fd, buf, sizeof(buf), 0);
    EXPECT_GT(n, 0);
    if (n <= 0) break;
    EXPECT_TRUE(conn.OnTcpBytes(std::span<const std::uint8_t>(buf, static_cast<std::size_t>(n)),
                                [&](const ReceivedMessage& m) {
                                  if (m.type == kPosQuatType) ++counts[std::string(m.sender)];
                                }));
  }
  return counts;
}

// A server with Tracker0 and Tracker1, and a raw client that describes `senders` (none: it
// sends its cookie only), pings from those of them in `pings`, and counts Pos_Quat per sender
// until `done`.
std::map<std::string, int> PosQuatPerSenderWhenDescribing(
    const std::vector<std::string>& senders,
    const std::function<bool(std::map<std::string, int>&)>& done,
    const std::vector<std::string>& pings = {}) {
  auto catalog = MakeCatalog();
  TrackerSpec other;
  other.name = "Tracker1";
  const int tracker1 = catalog->AddTracker(other);
  VrpnServer server(catalog, LoopbackOptions(), [](const std::string&) {});
  server.Start();
  auto fd = RawConnect(server.port());
  auto names = std::make_shared<NameRegistry>();
  for (const std::string& sender : senders) names->AddSender(sender);
  const std::int32_t ping = names->AddType(kPingType);
  Connection conn(names, Connection::Options{});
  conn.Start();
  for (const std::string& sender : pings)
    conn.Pack(*names->FindSender(sender), ping, Timestamp::Now(), {});
  if (::send(fd.get(), conn.tcp_output().data(), conn.tcp_output().size(), 0) <= 0) {
    ADD_FAILURE() << "cannot send the client's cookie";
    return {};
  }
  return CountPosQuatPerSender(server, tracker1, fd.get(), conn, done);
}

TEST(VrpnServer, ClientsOnlyGetTheDevicesTheyUse) {
  // Once the server has our ping from Tracker0 (a remote object for it), it streams Tracker0 to
  // us, never Tracker1, although we describe both (as the reference library does: it describes
  // back every name the server describes).
  auto counts = PosQuatPerSenderWhenDescribing(
      {"Tracker0", "Tracker1"}, [](auto& c) { return c["Tracker0"] >= 20; }, {"Tracker0"});
  EXPECT_GE(counts["Tracker0"], 20);
  EXPECT_EQ(counts.count("Tracker1"), 0u);
}

TEST(VrpnServer, ClientDescribingNoNamesGetsEveryDevice) {
  // A minimal third-party client that sends its cookie and never describes a sender filters by
  // itself, as with the reference server: it must still get every device's reports.
  auto counts = PosQuatPerSenderWhenDescribing(
      {}, [](auto& c) { return c["Tracker0"] >= 20 && c["Tracker1"] >= 20; });
  EXPECT_GE(counts["Tracker0"], 20);
  EXPECT_GE(counts["Tracker1"], 20);
}

TEST(VrpnServer, ReferenceClientDescribingOnlyVrpnControlGetsEveryDevice) {
  // Every peer built on the reference library describes its "VRPN Control" sender, with or
  // without a remote object for a device: one that registers handlers for any sender (a logger,
  // a monitor) describes no device name and must get every device, as from the reference server.
  auto counts = PosQuatPerSenderWhenDescribing(
      {std::string(kControlSender)}, [](auto& c) { return c["Tracker0"] >= 20 && c["Tracker1"] >= 20; });
  EXPECT_GE(counts["Tracker0"], 20);
  EXPECT_GE(counts["Tracker1"], 20);
}

// The reference client describes back every name a server describes: in capture 08 a client that
// opened Tracker0 alone describes Stylus0 (the server's button) right after pinging from Tracker0.
// Its descriptions therefore cannot tell which devices it uses; its pings can (every remote object
// pings from its device name when it starts). That client's captured bytes, replayed: it must get
// Tracker0's reports and not the button changes of Stylus0, which it never opened.
TEST(VrpnServer, ReferenceClientGetsTheDeviceItPingsFromNotTheNamesItDescribesBack) {
  VrpnServer server(MakeCatalog(), LoopbackOptions(), [](const std::string&) {});  // as capture 08
  server.Start();
  std::ifstream in(trackcal::testing::SourceDir() / "tests" / "data" / "vrpn" /
                       "08_fastrak_emulated_udp_lob_stylus_cm" / "client_to_server.bin",
                   std::ios::binary);
  const std::vector<std::uint8_t> reference_client(std::istreambuf_iterator<char>(in), {});
  ASSERT_EQ(reference_client.size(), 1704u);
  auto fd = RawConnect(server.port());
  ASSERT_EQ(::send(fd.get(), reference_client.data(), reference_client.size(), MSG_NOSIGNAL),
            static_cast<ssize_t>(reference_client.size()));
  Connection conn(std::make_shared<NameRegistry>(), Connection::Options{});
  std::map<std::string, int> counts;  // "sender type" -> messages
  std::uint8_t buf[65536];
  const auto end = Clock::now() + std::chrono::seconds(10);
  bool pressed = false;
  while (Clock::now() < end && counts["Tracker0 " + std::string(kPosQuatType)] < 20) {
    // Publish once the client's bytes (its ping included) have been handled: the pong came.
    if (counts["Tracker0 " + std::string(kPongType)] > 0) {
      server.PublishPose(0, 0, Rigid3d(), Timestamp::Now());
      server.PublishButton(0, 0, pressed = !pressed, Timestamp::Now());
    }
    pollfd p{fd.get(), POLLIN, 0};
    if (::poll(&p, 1, 10) <= 0) continue;
    const ssize_t n = ::recv(fd.get(), buf, sizeof(buf), 0);
    ASSERT_GT(n, 0);
    ASSERT_TRUE(conn.OnTcpBytes(std::span<const std::uint8_t>(buf, static_cast<std::size_t>(n)),
                                [&](const ReceivedMessage& m) {
                                  ++counts[std::string(m.sender) + " " + std::string(m.type)];
                                }));
  }
  EXPECT_EQ(counts["Tracker0 " + std::string(kPongType)], 1);
  EXPECT_GE(counts["Tracker0 " + std::string(kPosQuatType)], 20);
  EXPECT_EQ(counts["Stylus0 " + std::string(kButtonChangeType)], 0);
}

// The reference client's bytes of capture 06 (cookie, descriptions, the three static-information
// requests, a ping), with the version in its cookie replaced by `version`, sent to a live server
// split where TCP may split them: the cookie in two pieces, its second piece together with the
// first description's header, then everything else in one segment. Returns what came back as
// "sender type payload-size" -> count, with "closed" set when the server closed the connection.
std::map<std::string, int> ReplayCapture06(VrpnServer& server, std::string_view version) {
  std::ifstream in(trackcal::testing::SourceDir() / "tests" / "data" / "vrpn" /
                       "06_static_transform_requests_tcp" / "client_to_server.bin",
                   std::ios::binary);
  std::vector<std::uint8_t> bytes(std::istreambuf_iterator<char>(in), {});
  std::map<std::string, int> counts;
  EXPECT_EQ(bytes.size(), 1504u);
  EXPECT_EQ(version.size(), kCookieVersion.size());
  if (bytes.size() != 1504u || version.size() != kCookieVersion.size()) return counts;
  std::copy(version.begin(), version.end(), bytes.begin());
  auto fd = RawConnect(server.port());
  for (const auto& [from, to] : {std::pair<std::size_t, std::size_t>{0, 7}, {7, 40}, {40, 1504}}) {
    EXPECT_EQ(::send(fd.get(), bytes.data() + from, to - from, MSG_NOSIGNAL),
              static_cast<ssize_t>(to - from));
    std::this_thread::sleep_for(std::chrono::milliseconds(30));  // separate segments
  }
  Connection conn(std::make_shared<NameRegistry>(), Connection::Options{});
  std::uint8_t buf[65536];
  const auto end = Clock::now() + std::chrono::seconds(10);
  const std::string pos_quat = "Tracker0 " + std::string(kPosQuatType) + " 64";
  while (Clock::now() < end && counts[pos_quat] < 4 && counts["closed"] == 0) {
    // Publish once the client's bytes (its ping is the last message) have been handled.
    if (counts["Tracker0 " + std::string(kPongType) + " 0"] > 0) {
      server.PublishPose(0, 1, RandomPose(), Timestamp::Now());
    }
    pollfd p{fd.get(), POLLIN, 0};
    if (::poll(&p, 1, 10) <= 0) continue;
    const ssize_t n = ::recv(fd.get(), buf, sizeof(buf), 0);
    if (n <= 0) {
      ++counts["closed"];
      break;
    }
    EXPECT_TRUE(conn.OnTcpBytes(std::span<const std::uint8_t>(buf, static_cast<std::size_t>(n)),
                                [&](const ReceivedMessage& m) {
                                  ++counts[std::string(m.sender) + " " + std::string(m.type) + " " +
                                           std::to_string(m.payload.size())];
                                }));
  }
  return counts;
}

TEST(VrpnServer, ReferenceClientBytesSplitAnywhereGetTheReferenceServersAnswers) {
  // Capture 06's server (2 sensors) answered with one pong, one To_Room (56 bytes), one
  // Unit_To_Sensor (64 bytes) per sensor and one Workspace (48 bytes); the client library checks
  // those lengths exactly and drops the connection on any other.
  VrpnServer server(MakeCatalog(/*sensors=*/2), LoopbackOptions(), [](const std::string&) {});
  server.Start();
  for (std::string_view version : {"vrpn: ver. 07.38", "vrpn: ver. 07.35", "vrpn: ver. 07.99"}) {
    SCOPED_TRACE(std::string(version));
    auto got = ReplayCapture06(server, version);
    EXPECT_EQ(got["closed"], 0);
    EXPECT_EQ(got["Tracker0 " + std::string(kPongType) + " 0"], 1);
    EXPECT_EQ(got["Tracker0 " + std::string(kToRoomType) + " 56"], 1);
    EXPECT_EQ(got["Tracker0 " + std::string(kUnitToSensorType) + " 64"], 2);
    EXPECT_EQ(got["Tracker0 " + std::string(kWorkspaceType) + " 48"], 1);
    EXPECT_GE(got["Tracker0 " + std::string(kPosQuatType) + " 64"], 4);
  }
  // Another major version is refused, as the reference refuses it: closed, nothing answered.
  for (std::string_view version : {"vrpn: ver. 06.38", "vrpn: ver. 08.00"}) {
    SCOPED_TRACE(std::string(version));
    auto got = ReplayCapture06(server, version);
    EXPECT_EQ(got["closed"], 1);
    EXPECT_EQ(got["Tracker0 " + std::string(kPongType) + " 0"], 0);
    EXPECT_EQ(got["Tracker0 " + std::string(kPosQuatType) + " 64"], 0);
  }
  EXPECT_EQ(server.stats().closed_protocol, 2u);
}

// Sends `server` a lob request from the UDP socket `udp` naming a listener on 127.0.0.1 and returns
// the server's call-back connection (invalid if none came within 10 s).
UniqueFd AcceptLobCallback(const VrpnServer& server, int udp,
                           const std::string& address = "127.0.0.1") {
  UniqueFd listener(::socket(AF_INET, SOCK_STREAM, 0));
  sockaddr_in la = MakeSockaddr(*ParseIpv4(address), 0);
  if (::bind(listener.get(), reinterpret_cast<sockaddr*>(&la), sizeof(la)) != 0 ||
      ::listen(listener.get(), 1) != 0) {
    return UniqueFd();
  }
  socklen_t len = sizeof(la);
  ::getsockname(listener.get(), reinterpret_cast<sockaddr*>(&la), &len);
  const sockaddr_in dst = MakeSockaddr(*ParseIpv4("127.0.0.1"), server.port());
  const auto lob = EncodeLobRequest(LobRequest{address, ntohs(la.sin_port)});
  if (::sendto(udp, lob.data(), lob.size(), 0, reinterpret_cast<const sockaddr*>(&dst),
               sizeof(dst)) <= 0) {
    return UniqueFd();
  }
  pollfd p{listener.get(), POLLIN, 0};
  if (::poll(&p, 1, 10000) != 1) return UniqueFd();
  return UniqueFd(::accept(listener.get(), nullptr, nullptr));
}

TEST(VrpnServer, AForeignUdpDescriptionIsLoggedOnceNotOnEveryRead) {
  // A lob client announcing a UDP port on another address gets its reports over TCP; the server
  // says so once, not on every later read from that client (which would let one client fill the
  // log without limit).
  std::atomic<int> ignored_lines{0};
  VrpnServer server(MakeCatalog(), LoopbackOptions(), [&](const std::string& line) {
    if (line.find("ignoring UDP description") != std::string::npos) ++ignored_lines;
  });
  server.Start();
  UniqueFd udp(::socket(AF_INET, SOCK_DGRAM, 0));
  UniqueFd fd = AcceptLobCallback(server, udp.get());
  ASSERT_TRUE(fd.valid());

  auto names = std::make_shared<NameRegistry>();
  const std::int32_t tracker = names->AddSender("Tracker0");
  const std::int32_t ping = names->AddType(kPingType);
  Connection conn(names, Connection::Options{});
  conn.Start(std::make_pair(std::string("127.0.0.2"), 40000));
  constexpr int kPings = 30;
  int pongs = 0;
  std::uint8_t buf[65536];
  for (int i = 0; i < kPings; ++i) {
    conn.Pack(tracker, ping, Timestamp::Now(), {});
    auto& out = conn.tcp_output();
    ASSERT_EQ(::send(fd.get(), out.data(), out.size(), 0), static_cast<ssize_t>(out.size()));
    out.clear();
    // Wait for this ping's pong, so that every ping is a read of its own on the server.
    const auto end = Clock::now() + std::chrono::seconds(10);
    while (pongs <= i && Clock::now() < end) {
      pollfd r{fd.get(), POLLIN, 0};
      if (::poll(&r, 1, 100) <= 0) continue;
      const ssize_t n = ::recv(fd.get(), buf, sizeof(buf), 0);
      ASSERT_GT(n, 0);
      ASSERT_TRUE(conn.OnTcpBytes(std::span<const std::uint8_t>(buf, static_cast<std::size_t>(n)),
                                  [&](const ReceivedMessage& m) {
                                    if (m.type == kPongType) ++pongs;
                                  }));
    }
  }
  EXPECT_EQ(pongs, kPings);
  EXPECT_EQ(ignored_lines.load(), 1);
}

// A lob client made of raw sockets on `address` (a loopback address): it takes the server's
// call-back and describes a UDP data port, either its own open socket or (udp_reachable false) a
// port nobody listens on, so the server's datagrams there come back as ICMP port unreachable.
// Counts the Pos_Quat reports that reach it on each channel.
class RawLobClient {
 public:
  RawLobClient(const VrpnServer& server, bool udp_reachable,
               const std::string& address = "127.0.0.1") {
    data_ = UniqueFd(::socket(AF_INET, SOCK_DGRAM | SOCK_NONBLOCK, 0));
    sockaddr_in ua = MakeSockaddr(*ParseIpv4(address), 0);
    if (::bind(data_.get(), reinterpret_cast<sockaddr*>(&ua), sizeof(ua)) != 0) return;
    socklen_t len = sizeof(ua);
    ::getsockname(data_.get(), reinterpret_cast<sockaddr*>(&ua), &len);
    udp_port_ = ntohs(ua.sin_port);
    if (!udp_reachable) data_.Reset();  // the port is closed: datagrams to it are refused
    UniqueFd lob(::socket(AF_INET, SOCK_DGRAM, 0));
    sockaddr_in la = MakeSockaddr(*ParseIpv4(address), 0);
    if (::bind(lob.get(), reinterpret_cast<sockaddr*>(&la), sizeof(la)) != 0) return;
    tcp_ = AcceptLobCallback(server, lob.get(), address);
    if (!tcp_.valid()) return;
    names_ = std::make_shared<NameRegistry>();
    const std::int32_t tracker = names_->AddSender("Tracker0");
    const std::int32_t ping = names_->AddType(kPingType);
    conn_ = std::make_unique<Connection>(names_, Connection::Options{});
    conn_->Start(std::make_pair(address, udp_port_));
    // The pong tells that the server has read our UDP description (sent before the ping).
    conn_->Pack(tracker, ping, Timestamp::Now(), {});
    auto& out = conn_->tcp_output();
    if (::send(tcp_.get(), out.data(), out.size(), 0) != static_cast<ssize_t>(out.size())) return;
    out.clear();
    ReadUntil([this] { return pongs_ > 0; }, 10.0);
  }

  bool ready() const { return pongs_ > 0; }
  int udp_port() const { return udp_port_; }
  int tcp_reports() const { return tcp_reports_; }
  int udp_reports() const { return udp_reports_; }

  // Reads both sockets until done() holds or timeout_s passes; false if the connection broke.
  bool ReadUntil(const std::function<bool()>& done, double timeout_s) {
    const auto end = Clock::now() + std::chrono::duration<double>(timeout_s);
    std::uint8_t buf[65536];
    const auto count = [this](const ReceivedMessage& m) {
      if (m.type == kPongType) ++pongs_;
      if (m.type == kPosQuatType) ++(m.via_udp ? udp_reports_ : tcp_reports_);
    };
    while (!done() && Clock::now() < end) {
      pollfd p[2] = {{tcp_.get(), POLLIN, 0}, {data_.get(), POLLIN, 0}};
      if (::poll(p, data_.valid() ? 2 : 1, 10) <= 0) continue;
      if (p[0].revents) {
        const ssize_t n = ::recv(tcp_.get(), buf, sizeof(buf), 0);
        if (n <= 0) return false;
        if (!conn_->OnTcpBytes(std::span<const std::uint8_t>(buf, static_cast<std::size_t>(n)),
                               count)) {
          return false;
        }
      }
      if (data_.valid() && p[1].revents) {
        const ssize_t n = ::recv(data_.get(), buf, sizeof(buf), 0);
        if (n > 0) {
          conn_->OnDatagram(std::span<const std::uint8_t>(buf, static_cast<std::size_t>(n)), count);
        }
      }
    }
    return done();
  }

 private:
  UniqueFd data_;
  UniqueFd tcp_;
  int udp_port_ = 0;
  std::shared_ptr<NameRegistry> names_;
  std::unique_ptr<Connection> conn_;
  int pongs_ = 0;
  int tcp_reports_ = 0;
  int udp_reports_ = 0;
};

TEST(VrpnServer, ALobClientWhoseUdpPortIsUnreachableGetsItsReportsOverTcp) {
  // A lob client whose UDP port cannot be reached (a firewall rejecting it, a client that closed
  // the socket it described) got no report at all: the server kept sending datagrams into ICMP
  // port unreachable for ever. Now the first such error moves that client to TCP, said once.
  std::atomic<int> switch_lines{0};
  VrpnServer server(MakeCatalog(), LoopbackOptions(), [&](const std::string& line) {
    if (line.find("UDP port unreachable") != std::string::npos) ++switch_lines;
  });
  server.Start();
  RawLobClient client(server, /*udp_reachable=*/false);
  ASSERT_TRUE(client.ready());
  // The first report goes to the dead port (UDP may lose it): the error comes back from it.
  server.PublishPose(0, 0, RandomPose(), Timestamp::Now());
  const auto end = Clock::now() + std::chrono::seconds(10);
  while (switch_lines.load() == 0 && Clock::now() < end) {
    std::this_thread::sleep_for(std::chrono::milliseconds(5));
  }
  constexpr int kReports = 80;
  for (int i = 0; i < kReports; ++i) server.PublishPose(0, 0, RandomPose(), Timestamp::Now());
  client.ReadUntil([&] { return client.tcp_reports() >= kReports; }, 10.0);
  // Every report published after the switch arrives; the first one, sent over UDP, may or may not.
  EXPECT_GE(client.tcp_reports(), kReports);
  EXPECT_EQ(client.udp_reports(), 0);
  EXPECT_EQ(switch_lines.load(), 1);
}

TEST(VrpnServer, AnUnreachableClientCostsAnotherClientNoReport) {
  // Every lob client's datagrams leave from the server's one UDP socket. The error of one
  // client's datagram (ICMP port unreachable) was left on that socket and made the next send
  // from it fail: that datagram, another client's, was skipped and its report lost. Each send
  // that fails is now sent again once the socket's errors are read.
  VrpnServer server(MakeCatalog(), LoopbackOptions(), [](const std::string&) {});
  server.Start();
  // Made first, the healthy client's datagram is the first of every send: it meets the error
  // the other client's datagram of the report before left on the socket, unless the server has
  // read that error in between (a race: before the fix it lost a report in 4 of 5 runs here).
  RawLobClient healthy(server, /*udp_reachable=*/true);
  RawLobClient unreachable(server, /*udp_reachable=*/false);
  ASSERT_TRUE(healthy.ready());
  ASSERT_TRUE(unreachable.ready());
  constexpr int kReports = 80;
  for (int i = 0; i < kReports; ++i) {
    server.PublishPose(0, 0, RandomPose(), Timestamp::Now());
    // One report at a time: each send meets the error the previous one caused, if any.
    ASSERT_TRUE(healthy.ReadUntil([&] { return healthy.udp_reports() > i; }, 2.0)) << i;
  }
  EXPECT_EQ(healthy.udp_reports(), kReports);
  EXPECT_EQ(healthy.tcp_reports(), 0);
  // The unreachable client's reports go to its dead port until its first error comes back:
  // on loopback within one or two reports (the ICMP message is handled after the send returns).
  unreachable.ReadUntil([&] { return unreachable.tcp_reports() >= kReports - 2; }, 10.0);
  EXPECT_GE(unreachable.tcp_reports(), kReports - 2);
}

// Sends the server's UDP socket (on 127.0.0.1) an ICMP "fragmentation needed" about a datagram
// it sent to client:client_port, as a router on a path with a smaller MTU does. False without
// CAP_NET_RAW. `mtu` is what the router reports; 65535 leaves the kernel's path MTU for the
// client's address as it is in practice (no IPv4 packet is larger).
bool InjectFragmentationNeeded(int server_port, const std::string& client, int client_port,
                               int mtu) {
  UniqueFd raw(::socket(AF_INET, SOCK_RAW, IPPROTO_ICMP));
  if (!raw.valid()) return false;
  std::uint8_t packet[8 + 20 + 8] = {};
  packet[0] = 3;  // destination unreachable
  packet[1] = 4;  // fragmentation needed and DF set
  packet[6] = static_cast<std::uint8_t>(mtu >> 8);
  packet[7] = static_cast<std::uint8_t>(mtu);
  // The start of the datagram the ICMP message is about: its IPv4 and UDP headers.
  std::uint8_t* ip = packet + 8;
  ip[0] = 0x45;
  ip[2] = 0x05;  // total length 1500
  ip[3] = 0xdc;
  ip[6] = 0x40;  // DF
  ip[8] = 64;    // TTL
  ip[9] = IPPROTO_UDP;
  const in_addr server_ip = *ParseIpv4("127.0.0.1");
  const in_addr client_ip = *ParseIpv4(client);
  std::memcpy(ip + 12, &server_ip, 4);
  std::memcpy(ip + 16, &client_ip, 4);
  std::uint8_t* udp = ip + 20;
  udp[0] = static_cast<std::uint8_t>(server_port >> 8);
  udp[1] = static_cast<std::uint8_t>(server_port);
  udp[2] = static_cast<std::uint8_t>(client_port >> 8);
  udp[3] = static_cast<std::uint8_t>(client_port);
  udp[4] = 0x05;  // length 1480
  udp[5] = 0xc8;
  std::uint32_t sum = 0;
  for (std::size_t i = 0; i < sizeof(packet); i += 2) sum += (packet[i] << 8) | packet[i + 1];
  while (sum >> 16) sum = (sum & 0xffff) + (sum >> 16);
  packet[2] = static_cast<std::uint8_t>(~sum >> 8);
  packet[3] = static_cast<std::uint8_t>(~sum);
  const sockaddr_in dst = MakeSockaddr(server_ip, 0);
  return ::sendto(raw.get(), packet, sizeof(packet), 0, reinterpret_cast<const sockaddr*>(&dst),
                  sizeof(dst)) == static_cast<ssize_t>(sizeof(packet));
}

TEST(VrpnServer, FragmentationNeededKeepsAClientOnUdp) {
  // An ICMP "fragmentation needed" says a datagram was too large for a hop, not that the
  // client's port is closed: the client stays on UDP and loses no report.
  std::atomic<int> switch_lines{0};
  VrpnServer server(MakeCatalog(), LoopbackOptions(), [&](const std::string& line) {
    if (line.find("UDP port unreachable") != std::string::npos) ++switch_lines;
  });
  server.Start();
  // Its own loopback address: the kernel notes the reported MTU for that address only.
  RawLobClient client(server, /*udp_reachable=*/true, "127.0.0.9");
  ASSERT_TRUE(client.ready());
  if (!InjectFragmentationNeeded(server.port(), "127.0.0.9", client.udp_port(), 65535)) {
    GTEST_SKIP() << "needs CAP_NET_RAW to send an ICMP message";
  }
  constexpr int kReports = 20;
  for (int i = 0; i < kReports; ++i) server.PublishPose(0, 0, RandomPose(), Timestamp::Now());
  client.ReadUntil([&] { return client.udp_reports() + client.tcp_reports() >= kReports; }, 10.0);
  EXPECT_EQ(client.udp_reports(), kReports);
  EXPECT_EQ(client.tcp_reports(), 0);
  EXPECT_EQ(switch_lines.load(), 0);
}

TEST(VrpnServer, AStrangersDatagramToAClientsDataPortIsIgnored) {
  // The server's UDP data socket for a lob client takes datagrams from anyone who finds its port.
  // Only the client's own host may speak for the client there: a stranger's ping (with the
  // client's ids) got a pong sent to the client, and a stranger's descriptions could rename the
  // client's ids.
  std::atomic<int> ignored_lines{0};
  VrpnServer server(MakeCatalog(), LoopbackOptions(), [&](const std::string& line) {
    if (line.find("ignored datagram from 127.0.0.2") != std::string::npos) ++ignored_lines;
  });
  server.Start();
  UniqueFd udp(::socket(AF_INET, SOCK_DGRAM, 0));
  sockaddr_in ua = MakeSockaddr(*ParseIpv4("127.0.0.1"), 0);
  ASSERT_EQ(::bind(udp.get(), reinterpret_cast<sockaddr*>(&ua), sizeof(ua)), 0);
  socklen_t len = sizeof(ua);
  ::getsockname(udp.get(), reinterpret_cast<sockaddr*>(&ua), &len);
  UniqueFd fd = AcceptLobCallback(server, udp.get());
  ASSERT_TRUE(fd.valid());

  auto names = std::make_shared<NameRegistry>();
  const std::int32_t tracker = names->AddSender("Tracker0");
  const std::int32_t ping = names->AddType(kPingType);
  Connection conn(names, Connection::Options{});
  conn.Start(std::make_pair(std::string("127.0.0.1"), static_cast<int>(ntohs(ua.sin_port))));
  auto& out = conn.tcp_output();
  ASSERT_EQ(::send(fd.get(), out.data(), out.size(), 0), static_cast<ssize_t>(out.size()));
  out.clear();
  int pongs = 0;
  std::uint8_t buf[65536];
  auto read_tcp = [&](const std::function<bool()>& done, double timeout_s) {
    const auto end = Clock::now() + std::chrono::duration<double>(timeout_s);
    while (!done() && Clock::now() < end) {
      pollfd r{fd.get(), POLLIN, 0};
      if (::poll(&r, 1, 50) <= 0) continue;
      const ssize_t n = ::recv(fd.get(), buf, sizeof(buf), 0);
      ASSERT_GT(n, 0);
      ASSERT_TRUE(conn.OnTcpBytes(std::span<const std::uint8_t>(buf, static_cast<std::size_t>(n)),
                                  [&](const ReceivedMessage& m) {
                                    if (m.type == kPongType) ++pongs;
                                  }));
    }
  };
  read_tcp([&] { return conn.peer_udp().has_value(); }, 10.0);
  ASSERT_TRUE(conn.peer_udp());
  const sockaddr_in data_port =
      MakeSockaddr(*ParseIpv4(conn.peer_udp()->first), conn.peer_udp()->second);
  std::vector<std::uint8_t> datagram;
  AppendMessage(&datagram, Timestamp::Now(), tracker, ping, 0, {});

  // The stranger's datagram is sent first: the server reads it before the client's own.
  UniqueFd stranger(::socket(AF_INET, SOCK_DGRAM, 0));
  sockaddr_in sa = MakeSockaddr(*ParseIpv4("127.0.0.2"), 0);
  ASSERT_EQ(::bind(stranger.get(), reinterpret_cast<sockaddr*>(&sa), sizeof(sa)), 0);
  const std::uint64_t refused_before = server.stats().refused;
  ASSERT_GT(::sendto(stranger.get(), datagram.data(), datagram.size(), 0,
                     reinterpret_cast<const sockaddr*>(&data_port), sizeof(data_port)),
            0);
  ASSERT_GT(::sendto(udp.get(), datagram.data(), datagram.size(), 0,
                     reinterpret_cast<const sockaddr*>(&data_port), sizeof(data_port)),
            0);
  read_tcp([&] { return pongs >= 1; }, 10.0);
  EXPECT_EQ(pongs, 1);  // the client's own ping is answered
  EXPECT_EQ(server.stats().refused, refused_before + 1);
  EXPECT_EQ(ignored_lines.load(), 1);
  read_tcp([] { return false; }, 0.3);  // a pong for the stranger would have come by now
  EXPECT_EQ(pongs, 1);
}

TEST(VrpnServer, AllowListRefusesOtherNetworks) {
  ServerOptions options = LoopbackOptions();
  options.allow = {"10.0.0.0/8"};
  VrpnServer server(MakeCatalog(), options, [](const std::string&) {});
  server.Start();
  const std::string port = std::to_string(server.port());
  VrpnTrackerClient tcp("Tracker0@tcp://127.0.0.1:" + port);
  VrpnTrackerClient lob("Tracker0@127.0.0.1:" + port);
  PollUntil({&tcp, &lob}, [&] { return server.stats().refused >= 2; }, 5.0);
  EXPECT_GE(server.stats().refused, 2u);
  EXPECT_FALSE(tcp.connected());
  EXPECT_FALSE(lob.connected());
  EXPECT_EQ(server.stats().connections_total, 0u);
}

TEST(VrpnServer, ALobRequestForItsOwnPortIsRefused) {
  // Any local process could otherwise make the server connect to itself and hold two slots (the
  // call-back and its accepted end) for a client that does not exist.
  VrpnServer server(MakeCatalog(), LoopbackOptions(), [](const std::string&) {});
  server.Start();
  UniqueFd udp(::socket(AF_INET, SOCK_DGRAM, 0));
  const sockaddr_in dst = MakeSockaddr(*ParseIpv4("127.0.0.1"), server.port());
  const auto datagram = EncodeLobRequest(LobRequest{"127.0.0.1", server.port()});
  ASSERT_EQ(::sendto(udp.get(), datagram.data(), datagram.size(), 0,
                     reinterpret_cast<const sockaddr*>(&dst), sizeof(dst)),
            static_cast<ssize_t>(datagram.size()));
  ASSERT_TRUE(PollUntil(
      {}, [&] { return server.stats().refused >= 1; }, 5.0));
  // A connection made anyway would show within this time (loopback connects take microseconds).
  std::this_thread::sleep_for(std::chrono::milliseconds(200));
  EXPECT_EQ(server.stats().connections_total, 0u);
  EXPECT_EQ(server.stats().clients, 0);
}

TEST(VrpnServer, LobRequestsForClosedPortsCannotFloodTheLog) {
  // Each lob datagram naming a closed port costs a refused call-back; its log line counts
  // toward the cap on lob refusals (a host could otherwise log at the rate it sends datagrams).
  std::atomic<int> lines{0};
  VrpnServer server(MakeCatalog(), LoopbackOptions(), [&](const std::string& line) {
    if (line.find("call-back connect failed") != std::string::npos) ++lines;
  });
  server.Start();
  UniqueFd udp(::socket(AF_INET, SOCK_DGRAM, 0));
  const sockaddr_in dst = MakeSockaddr(*ParseIpv4("127.0.0.1"), server.port());
  for (int i = 0; i < 400; ++i) {
    // Ports nobody listens on (a connect there is refused at once on loopback).
    const auto datagram = EncodeLobRequest(LobRequest{"127.0.0.1", 40000 + i});
    ::sendto(udp.get(), datagram.data(), datagram.size(), 0,
             reinterpret_cast<const sockaddr*>(&dst), sizeof(dst));
    if (i % 50 == 49) std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  std::this_thread::sleep_for(std::chrono::milliseconds(500));
  EXPECT_GE(lines.load(), 1);
  EXPECT_LE(lines.load(), 100);
  EXPECT_EQ(server.stats().clients, 0);
}

// The refusal cap was 100 lines for the server's lifetime: a flood on day one silenced every
// later refusal for good. It is now 100 per period, with the unlogged ones counted.
TEST(VrpnServer, RefusalsAreLoggedAgainInTheNextPeriod) {
  ServerOptions options = LoopbackOptions();
  options.refusal_log_window_s =
      2.0;  // the 150 datagrams below take ~20 ms; 2 s spares a loaded machine
  std::mutex mutex;
  std::vector<std::string> lines;
  VrpnServer server(MakeCatalog(), options, [&](const std::string& line) {
    std::lock_guard<std::mutex> lock(mutex);
    lines.push_back(line);
  });
  server.Start();
  UniqueFd udp(::socket(AF_INET, SOCK_DGRAM, 0));
  const sockaddr_in dst = MakeSockaddr(*ParseIpv4("127.0.0.1"), server.port());
  auto send_junk = [&](int count) {
    for (int i = 0; i < count; ++i) {
      ::sendto(udp.get(), "junk", 4, 0, reinterpret_cast<const sockaddr*>(&dst), sizeof(dst));
      if (i % 50 == 49) std::this_thread::sleep_for(std::chrono::milliseconds(5));
    }
  };
  auto count = [&](const std::string& what) {
    std::lock_guard<std::mutex> lock(mutex);
    return std::count_if(lines.begin(), lines.end(),
                         [&](const std::string& l) { return l.find(what) != std::string::npos; });
  };
  send_junk(150);
  ASSERT_TRUE(PollUntil({}, [&] { return server.stats().refused >= 150; }));
  EXPECT_EQ(count("ignored lob datagram"), 100);
  EXPECT_EQ(count("further ones are counted, not logged"), 1);
  std::this_thread::sleep_for(std::chrono::milliseconds(2100));
  send_junk(1);
  ASSERT_TRUE(PollUntil({}, [&] { return server.stats().refused >= 151; }));
  EXPECT_EQ(count("ignored lob datagram"), 101);
  EXPECT_EQ(count("50 refused or ignored connections, datagrams or call-backs were not logged"), 1);
}

TEST(VrpnServer, SecondServerOnSamePortThrowsNamingIt) {
  VrpnServer first(MakeCatalog(), LoopbackOptions(), [](const std::string&) {});
  first.Start();
  ServerOptions options = LoopbackOptions();
  options.port = first.port();
  VrpnServer second(MakeCatalog(), options, [](const std::string&) {});
  try {
    second.Start();
    FAIL() << "expected a bind error";
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find(std::to_string(first.port())), std::string::npos);
  }
}

TEST(VrpnServer, BadOptionsThrowNamingTheField) {
  ServerOptions o = LoopbackOptions();
  o.allow = {"300.1.1.1/8"};
  EXPECT_THROW(VrpnServer(MakeCatalog(), o), std::invalid_argument);
  o = LoopbackOptions();
  o.bind_address = "localhost";
  EXPECT_THROW(VrpnServer(MakeCatalog(), o), std::invalid_argument);
}

// The server's socket (in this process) whose peer is `local`, or -1 after `timeout_s`.
int ServerSocketConnectedTo(const sockaddr_in& local, double timeout_s = 5.0) {
  const auto end = Clock::now() + std::chrono::duration<double>(timeout_s);
  while (Clock::now() < end) {
    for (const auto& entry : std::filesystem::directory_iterator("/proc/self/fd")) {
      const int fd = std::stoi(entry.path().filename().string());
      sockaddr_in peer{};
      socklen_t len = sizeof(peer);
      if (::getpeername(fd, reinterpret_cast<sockaddr*>(&peer), &len) == 0 &&
          peer.sin_family == AF_INET && peer.sin_port == local.sin_port &&
          peer.sin_addr.s_addr == local.sin_addr.s_addr) {
        return fd;
      }
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  }
  return -1;
}

bool KeepaliveOnServerSideOfANewConnection(double dead_client_timeout_s) {
  ServerOptions options = LoopbackOptions();
  options.dead_client_timeout_s = dead_client_timeout_s;
  VrpnServer server(MakeCatalog(), options, [](const std::string&) {});
  server.Start();
  UniqueFd client(::socket(AF_INET, SOCK_STREAM, 0));
  sockaddr_in dst = MakeSockaddr(*ParseIpv4("127.0.0.1"), server.port());
  EXPECT_EQ(::connect(client.get(), reinterpret_cast<sockaddr*>(&dst), sizeof(dst)), 0);
  sockaddr_in local{};
  socklen_t len = sizeof(local);
  ::getsockname(client.get(), reinterpret_cast<sockaddr*>(&local), &len);
  const int fd = ServerSocketConnectedTo(local);
  EXPECT_GE(fd, 0) << "the server did not accept";
  int on = 0;
  len = sizeof(on);
  if (fd >= 0) ::getsockopt(fd, SOL_SOCKET, SO_KEEPALIVE, &on, &len);
  return on != 0;
}

TEST(VrpnServer, AClientWhoseHostVanishesIsDetectedByKeepalive) {
  // A lob client talks UDP and leaves TCP idle: without keepalive a crashed or unplugged client
  // host keeps its slot and its UDP stream for ever. (A real dead host cannot be made on loopback,
  // where the kernel answers every probe; the probe timing is tested with the helper.)
  EXPECT_TRUE(KeepaliveOnServerSideOfANewConnection(30.0));
  EXPECT_FALSE(KeepaliveOnServerSideOfANewConnection(0.0));
  ServerOptions bad = LoopbackOptions();
  bad.dead_client_timeout_s = -1;
  EXPECT_THROW(VrpnServer(MakeCatalog(), bad), std::invalid_argument);
}

TEST(VrpnServer, BurstOf128ClientsAllStreaming) {
  VrpnServer server(MakeCatalog(), LoopbackOptions(), [](const std::string&) {});
  server.Start();
  const std::string port = std::to_string(server.port());
  std::vector<std::unique_ptr<VrpnTrackerClient>> clients;
  std::vector<Collected> got(128);
  for (int i = 0; i < 128; ++i) {
    // Half direct TCP, half lob: the TCP backlog and the UDP lob queue both see a burst.
    clients.push_back(std::make_unique<VrpnTrackerClient>(
        (i % 2 ? "Tracker0@tcp://127.0.0.1:" : "Tracker0@127.0.0.1:") + port));
    Attach(*clients.back(), got[i]);
  }
  std::vector<VrpnTrackerClient*> raw;
  for (auto& c : clients) raw.push_back(c.get());
  const auto start = Clock::now();
  // Reports keep flowing while the clients connect; a client is streaming once it got one.
  std::atomic<bool> publishing{true};
  std::thread publisher([&] {
    while (publishing) {
      server.PublishPose(0, 0, Rigid3d(), Timestamp::Now());
      std::this_thread::sleep_for(std::chrono::milliseconds(5));
    }
  });
  const bool all = PollUntil(raw, [&] {
    return std::all_of(got.begin(), got.end(), [](const Collected& c) { return !c.reports.empty(); });
  }, 20.0);
  const double elapsed = std::chrono::duration<double>(Clock::now() - start).count();
  publishing = false;
  publisher.join();
  EXPECT_TRUE(all);
  EXPECT_EQ(server.stats().clients, 128);
  // Functional bound only (the issue asks for 1 s); the loaded CI machine gets slack, the figure
  // itself is printed for the record, not asserted tightly.
  std::cout << "128 clients streaming after " << elapsed << " s\n";
  EXPECT_LT(elapsed, 10.0);
}

// Restores RLIMIT_NOFILE and frees the filler descriptors when a test ends, even on failure.
struct FdLimitGuard {
  rlimit saved{};
  std::vector<UniqueFd> fillers;
  FdLimitGuard() { ::getrlimit(RLIMIT_NOFILE, &saved); }
  ~FdLimitGuard() {
    fillers.clear();
    ::setrlimit(RLIMIT_NOFILE, &saved);
  }
  // Lowers the limit to just above the highest open descriptor and fills the free numbers below
  // it: from here on no new descriptor can be made (the server can neither accept nor open).
  bool Exhaust() {
    int highest = 0;
    for (const auto& entry : std::filesystem::directory_iterator("/proc/self/fd")) {
      highest = std::max(highest, std::stoi(entry.path().filename().string()));
    }
    rlimit low = saved;
    low.rlim_cur = static_cast<rlim_t>(highest) + 1;
    if (::setrlimit(RLIMIT_NOFILE, &low) != 0) return false;
    for (int fd; (fd = ::open("/dev/null", O_RDONLY | O_CLOEXEC)) >= 0;) fillers.emplace_back(fd);
    return true;
  }
};

TEST(VrpnServer, OutOfFileDescriptorsDoesNotSpinOrFloodTheLog) {
  // accept() failing with EMFILE leaves the connection queued and the listener readable: the
  // loop must back off instead of retrying (and logging) as fast as epoll returns.
  std::atomic<int> fd_errors{0};
  VrpnServer server(MakeCatalog(), LoopbackOptions(), [&](const std::string& line) {
    if (line.find(std::strerror(EMFILE)) != std::string::npos) ++fd_errors;
  });
  server.Start();
  // Client sockets exist before the limit is lowered: connecting them needs no new descriptor.
  constexpr int kClients = 3;
  std::vector<UniqueFd> clients;
  for (int i = 0; i < kClients; ++i) clients.emplace_back(::socket(AF_INET, SOCK_STREAM, 0));
  FdLimitGuard guard;
  ASSERT_TRUE(guard.Exhaust());  // from here on the server cannot accept
  const sockaddr_in sa = MakeSockaddr(*ParseIpv4("127.0.0.1"), server.port());
  for (auto& c : clients) {
    ASSERT_EQ(::connect(c.get(), reinterpret_cast<const sockaddr*>(&sa), sizeof(sa)), 0);
  }
  std::this_thread::sleep_for(std::chrono::milliseconds(300));
  // One line when accepting stops; a spinning loop logs thousands in 300 ms.
  EXPECT_GE(fd_errors.load(), 1);
  EXPECT_LE(fd_errors.load(), 2);
  EXPECT_EQ(server.stats().clients, 0);
  // Once descriptors are available again the queued connections are accepted.
  guard.fillers.clear();
  ASSERT_EQ(::setrlimit(RLIMIT_NOFILE, &guard.saved), 0);
  const auto end = Clock::now() + std::chrono::seconds(10);
  while (server.stats().clients < kClients && Clock::now() < end) {
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  }
  EXPECT_EQ(server.stats().clients, kClients);
}

TEST(VrpnServer, LobRequestsWhileOutOfFileDescriptorsCannotFloodTheLog) {
  // With no descriptor free, every lob datagram failed at socket() and logged a line of its own
  // (observed: 2000 datagrams, 2000 lines). They count toward the cap on lob refusals instead.
  std::atomic<int> socket_errors{0};
  VrpnServer server(MakeCatalog(), LoopbackOptions(), [&](const std::string& line) {
    if (line.find(std::strerror(EMFILE)) != std::string::npos) ++socket_errors;
  });
  server.Start();
  // The call-back target and the sender exist before the limit is lowered.
  UniqueFd listener(::socket(AF_INET, SOCK_STREAM, 0));
  sockaddr_in la = MakeSockaddr(*ParseIpv4("127.0.0.1"), 0);
  ASSERT_EQ(::bind(listener.get(), reinterpret_cast<sockaddr*>(&la), sizeof(la)), 0);
  ASSERT_EQ(::listen(listener.get(), 16), 0);
  socklen_t len = sizeof(la);
  ::getsockname(listener.get(), reinterpret_cast<sockaddr*>(&la), &len);
  UniqueFd udp(::socket(AF_INET, SOCK_DGRAM, 0));
  FdLimitGuard guard;
  ASSERT_TRUE(guard.Exhaust());
  const sockaddr_in dst = MakeSockaddr(*ParseIpv4("127.0.0.1"), server.port());
  const auto lob = EncodeLobRequest(LobRequest{"127.0.0.1", ntohs(la.sin_port)});
  // More than the cap of 100 lines, few enough to fit the server's receive buffer.
  constexpr int kDatagrams = 150;
  for (int i = 0; i < kDatagrams; ++i) {
    ASSERT_GT(::sendto(udp.get(), lob.data(), lob.size(), 0,
                       reinterpret_cast<const sockaddr*>(&dst), sizeof(dst)),
              0);
    if (i % 10 == 9) std::this_thread::sleep_for(std::chrono::milliseconds(1));
  }
  // Every datagram is read (the server drains its socket), so once the log is quiet for a while
  // all lines that will come have come.
  int last = -1;
  const auto end = Clock::now() + std::chrono::seconds(10);
  while (socket_errors.load() != last && Clock::now() < end) {
    last = socket_errors.load();
    std::this_thread::sleep_for(std::chrono::milliseconds(200));
  }
  EXPECT_GE(socket_errors.load(), 1);
  EXPECT_LE(socket_errors.load(), 100);
  EXPECT_EQ(server.stats().clients, 0);
}

TEST(VrpnTrackerClient, AHostNameIsResolvedOffTheClientThread) {
  VrpnServer server(MakeCatalog(), LoopbackOptions(), [](const std::string&) {});
  server.Start();
  TrackerClientOptions options;
  // Shared, not referenced: the resolver's thread may outlive this scope.
  auto lookups = std::make_shared<std::atomic<int>>(0);
  auto on_polling_thread = std::make_shared<std::atomic<bool>>(false);
  const auto polling_thread = std::this_thread::get_id();  // PollUntil polls on this thread
  options.resolve_host = [lookups, on_polling_thread,
                          polling_thread](const std::string& host) -> std::optional<std::string> {
    ++*lookups;
    if (std::this_thread::get_id() == polling_thread) *on_polling_thread = true;
    return host == "tracker.lab" ? std::optional<std::string>("127.0.0.1") : std::nullopt;
  };
  VrpnTrackerClient client("Tracker0@tcp://tracker.lab:" + std::to_string(server.port()), options);
  Collected got;
  Attach(client, got);
  ASSERT_TRUE(PollUntil({&client}, [&] { return client.pong_received(); }));
  EXPECT_EQ(*lookups, 1);
  EXPECT_FALSE(*on_polling_thread);
}

TEST(VrpnTrackerClient, AHostNameThatDoesNotResolveIsToldApartFromAServerThatIsDown) {
  // `trackcal record` said "no connection; is a server running at that address?" for a mistyped
  // host name: the client knows the name did not resolve.
  TrackerClientOptions options;
  options.reconnect_delay_s = 0.1;
  options.resolve_host = [](const std::string& host) -> std::optional<std::string> {
    return host == "tracker.lab" ? std::optional<std::string>("127.0.0.1") : std::nullopt;
  };
  VrpnTrackerClient typo("Tracker0@tcp://traker.lab:3883", options);
  EXPECT_TRUE(PollUntil({&typo}, [&] { return typo.host_unknown(); }));
  EXPECT_FALSE(typo.connected());
  // A name that resolves and a dotted address, with no server at the port (1: nothing listens on
  // it here), are not unknown hosts: their connects are tried and fail.
  VrpnTrackerClient known("Tracker0@tcp://tracker.lab:1", options);
  VrpnTrackerClient dotted("Tracker0@tcp://127.0.0.1:1", options);
  // 1 s: each tries a connect within milliseconds; a wrong host_unknown would show by then.
  EXPECT_FALSE(PollUntil(
      {&known, &dotted}, [&] { return known.host_unknown() || dotted.host_unknown(); }, 1.0));
  EXPECT_GE(known.connect_attempts(), 1u);
  EXPECT_GE(dotted.connect_attempts(), 1u);
}

TEST(VrpnTrackerClient, ALookUpThatFailsForNowIsNotAnUnknownHost) {
  // A lookup that fails for now (getaddrinfo's EAI_AGAIN: the network or the DNS server not up
  // yet; resolve_host throws) is retried without calling the host unknown, so `trackcal record
  // --connect-timeout 60` started while a laptop joins the network waits instead of failing.
  auto count = std::make_shared<std::atomic<int>>(0);
  TrackerClientOptions options;
  options.reconnect_delay_s = 0.05;
  options.resolve_host = [count](const std::string&) -> std::optional<std::string> {
    ++*count;
    throw std::runtime_error("Temporary failure in name resolution");
  };
  VrpnTrackerClient client("Tracker0@tcp://tracker.lab:3883", options);
  // 1 s: 0.05 s apart, the lookup is tried many times; one wrong host_unknown would show.
  EXPECT_FALSE(PollUntil(
      {&client}, [&] { return client.host_unknown(); }, 1.0));
  EXPECT_GE(*count, 2);
}

TEST(VrpnTrackerClient, StopDoesNotWaitForADnsServerThatDoesNotAnswer) {
  TrackerClientOptions options;
  auto release = std::make_shared<std::atomic<bool>>(false);
  auto started = std::make_shared<std::atomic<bool>>(false);
  options.resolve_host = [release, started](const std::string&) -> std::optional<std::string> {
    // A resolver stuck for up to 10 s (the test lets it go at the end).
    *started = true;
    for (int i = 0; i < 1000 && !*release; ++i) {
      std::this_thread::sleep_for(std::chrono::milliseconds(10));
    }
    return std::nullopt;
  };
  VrpnTrackerClient client("Tracker0@tcp://unanswered.lab:3883", options);
  client.Start();
  // The lookup is under way (a fixed sleep could measure a Stop() before it began on a loaded
  // machine, and pass whatever Stop() waits for).
  for (int i = 0; i < 2000 && !*started; ++i) {
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  }
  ASSERT_TRUE(*started);
  std::this_thread::sleep_for(std::chrono::milliseconds(100));  // the client thread polls on
  const auto start = Clock::now();
  client.Stop();
  const double stop_s = std::chrono::duration<double>(Clock::now() - start).count();
  *release = true;
  // The client thread polls in 50 ms steps; 2 s is slack for a loaded machine, far below the 10 s
  // the lookup would have held it.
  EXPECT_LT(stop_s, 2.0);
  EXPECT_FALSE(client.connected());
}

// A socket listening on 127.0.0.1 (a free port) that the test never accepts from.
struct IdleListener {
  UniqueSocket socket;
  sockaddr_in address{};
  std::string TcpName() const {
    return "Tracker0@tcp://127.0.0.1:" + std::to_string(ntohs(address.sin_port));
  }
};

IdleListener ListenOnLoopback(int backlog) {
  IdleListener l;
  l.socket = UniqueSocket(OpenSocket(SOCK_STREAM, /*nonblocking=*/true));
  l.address = MakeSockaddr(*ParseIpv4("127.0.0.1"), 0);
  EXPECT_EQ(::bind(l.socket.get(), reinterpret_cast<sockaddr*>(&l.address), sizeof(l.address)), 0);
  EXPECT_EQ(::listen(l.socket.get(), backlog), 0);
  socklen_t len = sizeof(l.address);
  ::getsockname(l.socket.get(), reinterpret_cast<sockaddr*>(&l.address), &len);
  return l;
}

// Short connect timeouts and retries, for the tests of what makes a client give up and retry.
TrackerClientOptions QuickRetries() {
  TrackerClientOptions options;
  options.connect_timeout_s = 0.3;
  options.reconnect_delay_s = 0.1;
  return options;
}

TEST(VrpnTrackerClient, AConnectThatHangsIsRetried) {
  // A listener whose backlog is full: the kernel leaves further SYNs unanswered, so a connect
  // neither succeeds nor fails, as to a host that drops them.
  const IdleListener listener = ListenOnLoopback(0);
  std::vector<UniqueSocket> fillers;
  for (int i = 0; i < 4; ++i) {
    fillers.emplace_back(OpenSocket(SOCK_STREAM, /*nonblocking=*/true));
    ::connect(fillers.back().get(), reinterpret_cast<const sockaddr*>(&listener.address),
              sizeof(listener.address));
  }
  VrpnTrackerClient client(listener.TcpName(), QuickRetries());
  // Each attempt that times out is abandoned and a new one started: the client keeps trying
  // instead of waiting out the kernel's SYN retries (about two minutes).
  PollUntil({&client}, [] { return false; }, 3.0);
  EXPECT_FALSE(client.connected());
  EXPECT_EQ(client.connections(), 0u);
  // 3 s of 0.3 s timeouts and 0.1 s waits: about 7 attempts; a loaded machine polls late, and one
  // attempt is what a client without the timeout makes.
  EXPECT_GE(client.connect_attempts(), 3u);
}

TEST(VrpnTrackerClient, APeerThatNeverSendsItsCookieIsLeft) {
  // A listener that is never accepted from: the kernel completes the TCP handshake, but no VRPN
  // cookie ever comes (a stopped server, another service on the port).
  const IdleListener listener = ListenOnLoopback(16);
  VrpnTrackerClient client(listener.TcpName(), QuickRetries());
  PollUntil({&client}, [] { return false; }, 3.0);
  EXPECT_FALSE(client.connected());
  // Every attempt's TCP connect succeeds; without the timeout the first one is kept for good.
  EXPECT_GE(client.connections(), 3u);
  EXPECT_GE(client.connect_attempts(), 3u);
}

// A TCP relay in front of a server that can freeze the connections it carries without closing
// them: what a client sees of a server that died without a FIN (a crash, a pulled cable, a laptop
// gone to sleep). Connections accepted after Freeze() are relayed again (the server is back).
class FreezableRelay {
 public:
  explicit FreezableRelay(int server_port) : server_port_(server_port) {
    listener_ = UniqueSocket(OpenSocket(SOCK_STREAM, /*nonblocking=*/true));
    sockaddr_in a = MakeSockaddr(*ParseIpv4("127.0.0.1"), 0);
    EXPECT_EQ(::bind(listener_.get(), reinterpret_cast<sockaddr*>(&a), sizeof(a)), 0);
    EXPECT_EQ(::listen(listener_.get(), 16), 0);
    socklen_t len = sizeof(a);
    ::getsockname(listener_.get(), reinterpret_cast<sockaddr*>(&a), &len);
    port_ = ntohs(a.sin_port);
    thread_ = std::thread([this] { Run(); });
  }
  ~FreezableRelay() {
    stop_ = true;
    thread_.join();
  }
  int port() const { return port_; }
  void Freeze() { freeze_below_ = generation_.load(); }

 private:
  struct Pair {
    UniqueSocket client, server;
    int generation = 0;
  };
  void Run() {
    std::vector<Pair> pairs;
    while (!stop_) {
      const NativeSocket c = AcceptSocket(listener_.get(), /*nonblocking=*/true);
      if (c != kNoSocket) {
        Pair p;
        p.client = UniqueSocket(c);
        p.server = UniqueSocket(OpenSocket(SOCK_STREAM, /*nonblocking=*/false));
        sockaddr_in a = MakeSockaddr(*ParseIpv4("127.0.0.1"), server_port_);
        ::connect(p.server.get(), reinterpret_cast<sockaddr*>(&a), sizeof(a));
        p.generation = ++generation_;
        pairs.push_back(std::move(p));
      }
      std::vector<PollFd> fds;
      std::vector<std::pair<Pair*, bool>> owners;  // (pair, from the client side)
      for (auto& p : pairs) {
        if (p.generation <= freeze_below_) continue;  // frozen: nothing read, nothing closed
        fds.push_back(PollFd{p.client.get(), POLLIN, 0});
        owners.emplace_back(&p, true);
        fds.push_back(PollFd{p.server.get(), POLLIN, 0});
        owners.emplace_back(&p, false);
      }
      if (PollSockets(fds.data(), fds.size(), 10) <= 0) continue;
      for (std::size_t i = 0; i < fds.size(); ++i) {
        if (!(fds[i].revents & (POLLIN | POLLHUP))) continue;
        Pair& p = *owners[i].first;
        const bool from_client = owners[i].second;
        char buf[65536];
        const long n = ReceiveSocket(from_client ? p.client.get() : p.server.get(), buf, sizeof(buf));
        if (n > 0) ::send(from_client ? p.server.get() : p.client.get(), buf, n, MSG_NOSIGNAL);
      }
    }
  }
  int server_port_;
  int port_ = 0;
  UniqueSocket listener_;
  std::atomic<int> generation_{0};
  std::atomic<int> freeze_below_{0};
  std::atomic<bool> stop_{false};
  std::thread thread_;
};

TEST(VrpnTrackerClient, AServerThatGoesSilentIsLeftAndFoundAgain) {
  VrpnServer server(MakeCatalog(), LoopbackOptions(), [](const std::string&) {});
  server.Start();
  FreezableRelay relay(server.port());
  TrackerClientOptions options;
  options.liveness_timeout_s = 1.0;
  options.ping_interval_s = 0.1;
  options.reconnect_delay_s = 0.1;
  VrpnTrackerClient client("Tracker0@tcp://127.0.0.1:" + std::to_string(relay.port()), options);
  Collected got;
  Attach(client, got);
  ASSERT_TRUE(PollUntil({&client}, [&] { return client.pong_received(); }));
  // Quiet but alive: the pings after half the timeout keep the connection (3 timeouts of silence
  // from the tracker, the server answering).
  PollUntil({&client}, [] { return false; }, 3.0);
  EXPECT_EQ(client.connections(), 1u);
  EXPECT_TRUE(client.connected());
  // Dead without a FIN: the client leaves after the timeout and connects again through the relay.
  relay.Freeze();
  ASSERT_TRUE(PollUntil({&client}, [&] {
    return client.connections() >= 2 && client.pong_received();
  })) << "connections " << client.connections();
}

// Start()'s thread runs Poll: an exception leaving it (a callback that throws, std::thread failing
// to start a host-name lookup, bad_alloc) would reach std::terminate and end the whole process (a
// Unity player, through the plugin). The client drops the connection and makes it again instead.
TEST(VrpnTrackerClient, AnExceptionOnTheClientThreadCostsTheConnectionNotTheProcess) {
  VrpnServer server(MakeCatalog(), LoopbackOptions(), [](const std::string&) {});
  server.Start();
  TrackerClientOptions options;
  options.reconnect_delay_s = 0.1;
  VrpnTrackerClient client("Tracker0@tcp://127.0.0.1:" + std::to_string(server.port()), options);
  std::atomic<int> reports{0};
  client.SetPoseCallback([&reports](const TrackerReport&) {
    if (++reports == 1) throw std::runtime_error("a callback that throws");
  });
  client.Start();
  const Rigid3d pose = RandomPose();
  // Published until a report arrives after the one that threw, on a connection made again.
  const auto end = Clock::now() + std::chrono::seconds(20);  // generous: a loaded test machine
  while (Clock::now() < end && !(reports >= 3 && client.connections() >= 2)) {
    server.PublishPose(0, 0, pose, Timestamp::Now());
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  }
  EXPECT_GE(reports, 3);
  EXPECT_GE(client.connections(), 2u);
  client.Stop();
}

// A client of Tracker0@tcp://tracker.lab whose host names `resolve` (called with the lookup's
// count, from 1) gets a pong, the server stops and starts again on `restart_address` at the same
// port: true when the client connected again and got a pong there. *lookups: the lookups made.
bool ReconnectsAfterARestart(const std::function<std::optional<std::string>(int)>& resolve,
                             const std::string& restart_address, int* lookups) {
  auto count = std::make_shared<std::atomic<int>>(0);
  TrackerClientOptions options;
  options.reconnect_delay_s = 0.1;
  options.resolve_host = [count, resolve](const std::string&) { return resolve(++*count); };
  auto server =
      std::make_unique<VrpnServer>(MakeCatalog(), LoopbackOptions(), [](const std::string&) {});
  server->Start();
  const int port = server->port();
  VrpnTrackerClient client("Tracker0@tcp://tracker.lab:" + std::to_string(port), options);
  EXPECT_TRUE(PollUntil({&client}, [&] { return client.pong_received(); }));
  server.reset();
  ServerOptions restarted = LoopbackOptions();
  restarted.bind_address = restart_address;
  restarted.port = port;
  VrpnServer again(MakeCatalog(), restarted, [](const std::string&) {});
  again.Start();
  const bool back =
      PollUntil({&client}, [&] { return client.connections() >= 2 && client.pong_received(); });
  *lookups = *count;
  if (!back) ADD_FAILURE() << "connections " << client.connections() << ", lookups " << *count;
  return back;
}

TEST(VrpnTrackerClient, AHostNameIsLookedUpAgainForAReconnect) {
  // The server's machine restarts with another address (a new DHCP lease, the name moved to a
  // spare machine): the address looked up first would be tried for ever.
  int lookups = 0;
  EXPECT_TRUE(ReconnectsAfterARestart(
      [](int n) -> std::optional<std::string> { return n == 1 ? "127.0.0.1" : "127.0.0.2"; },
      "127.0.0.2", &lookups));
}

TEST(VrpnTrackerClient, AFailedLookUpForAReconnectKeepsTheAddressFoundBefore) {
  // The DNS server is down when the server restarts where it was: the address found before is
  // tried rather than none.
  int lookups = 0;
  EXPECT_TRUE(ReconnectsAfterARestart(
      [](int n) -> std::optional<std::string> {
        if (n == 1) return "127.0.0.1";
        return std::nullopt;
      },
      "127.0.0.1", &lookups));
  EXPECT_GE(lookups, 2);
}

TEST(VrpnTrackerClient, ALobToAnAddressWhereNoServerAnswersLooksTheNameUpAgain) {
  // Lob mode (the default, "Tracker0@host"): the first lookup gives an address where no server
  // is (the server's machine not up yet, or back with a new DHCP lease while the old record was
  // still served). The lob is re-sent there for ever unless the wait for the call-back ends like
  // a connect that hangs, with a new lookup that finds the server.
  auto count = std::make_shared<std::atomic<int>>(0);
  TrackerClientOptions options = QuickRetries();
  options.lob_retry_s = 0.1;
  options.resolve_host = [count](const std::string&) -> std::optional<std::string> {
    return ++*count == 1 ? "127.0.0.2" : "127.0.0.1";
  };
  VrpnServer server(MakeCatalog(), LoopbackOptions(), [](const std::string&) {});
  server.Start();
  VrpnTrackerClient client("Tracker0@tracker.lab:" + std::to_string(server.port()), options);
  EXPECT_TRUE(PollUntil({&client}, [&] { return client.pong_received(); }))
      << "lookups " << *count << ", lob attempts " << client.connect_attempts();
  EXPECT_GE(*count, 2);
}

}  // namespace
}  // namespace trackcal::vrpn
