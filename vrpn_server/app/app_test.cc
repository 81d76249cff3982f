#include "vrpn_server/app/app.h"

#include <arpa/inet.h>
#include <gtest/gtest.h>
#include <sys/socket.h>
#include <unistd.h>

#include <cerrno>
#include <chrono>
#include <fstream>
#include <functional>
#include <map>
#include <mutex>
#include <thread>

#include "core/printable_text.h"
#include "tests/test_utils.h"
#include "vrpn_server/net/socket_util.h"
#include "vrpn_server/protocol/stream_parser.h"

namespace trackcal::vrpn {
namespace {

using Clock = std::chrono::steady_clock;

// Test calibration format: one line "dx dy dz" = a position offset.
class OffsetCorrector : public PoseCorrector {
 public:
  explicit OffsetCorrector(Eigen::Vector3d d) : d_(d) {}
  Rigid3d Correct(const Rigid3d& r) const override { return Rigid3d(r.rotation, r.translation + d_); }
  std::string Describe() const override { return "offset"; }

 private:
  Eigen::Vector3d d_;
};

std::shared_ptr<const PoseCorrector> LoadOffset(const std::filesystem::path& path,
                                                const std::optional<std::string>&,
                                                const std::optional<double>&) {
  std::ifstream in(path);
  Eigen::Vector3d d;
  if (!(in >> d.x() >> d.y() >> d.z())) throw std::invalid_argument(path.string() + ": expected dx dy dz");
  return std::make_shared<OffsetCorrector>(d);
}

void WriteFile(const std::filesystem::path& path, const std::string& text) {
  // Atomic replace, as editors and trackcal-fit do; the new inode marks the change.
  const auto tmp = path.string() + ".tmp";
  std::ofstream(tmp) << text;
  std::filesystem::rename(tmp, path);
}

AppOptions Loopback() {
  AppOptions o;
  o.server.bind_address = "127.0.0.1";
  o.server.port = 0;
  return o;
}

// Latest pose x per client, updated on the client's own thread.
struct Watch {
  std::mutex mutex;
  double x = NAN;
  int count = 0;
  void Attach(VrpnTrackerClient& c) {
    c.SetPoseCallback([this](const TrackerReport& r) {
      std::lock_guard<std::mutex> lock(mutex);
      x = r.transmitter_from_receiver.translation.x();
      ++count;
    });
  }
  bool WaitFor(double expected, double timeout_s = 10) {
    const auto end = Clock::now() + std::chrono::duration<double>(timeout_s);
    while (Clock::now() < end) {
      {
        std::lock_guard<std::mutex> lock(mutex);
        if (x == expected) return true;
      }
      std::this_thread::sleep_for(std::chrono::milliseconds(5));
    }
    return false;
  }
};

TrackerSetup NullSetup(const std::filesystem::path& calibration) {
  TrackerSetup s;
  s.name = "Tracker0";
  s.raw_name = "Tracker0_raw";
  s.num_sensors = 2;
  s.calibration = calibration;
  s.make_source = [] { return MakeNullSource(2, 100.0); };
  s.origin = "test.cfg:1";
  return s;
}

TEST(TrackcalServerApp, CorrectedRawAndReload) {
  const auto dir = testing::MakeTempDir("app");
  const auto calib = dir / "calib.txt";
  WriteFile(calib, "0.25 0 0\n");
  std::vector<std::string> log;
  std::mutex log_mutex;
  AppOptions options = Loopback();
  options.record_dir = dir;
  TrackcalServerApp app({NullSetup(calib)}, options, LoadOffset, [&](const std::string& l) {
    std::lock_guard<std::mutex> lock(log_mutex);
    log.push_back(l);
  });
  app.Start();
  const std::string port = std::to_string(app.port());
  VrpnTrackerClient corrected("Tracker0@tcp://127.0.0.1:" + port);
  VrpnTrackerClient raw("Tracker0_raw@127.0.0.1:" + port);
  Watch wc, wr;
  wc.Attach(corrected);
  wr.Attach(raw);
  corrected.Start();
  raw.Start();
  EXPECT_TRUE(wc.WaitFor(0.25));
  EXPECT_TRUE(wr.WaitFor(0.0));

  WriteFile(calib, "0.5 0 0\n");
  EXPECT_EQ(app.ReloadChangedCalibrations(), 1);
  EXPECT_EQ(app.ReloadChangedCalibrations(), 0);  // unchanged since
  EXPECT_TRUE(wc.WaitFor(0.5));

  WriteFile(calib, "garbage\n");
  EXPECT_EQ(app.ReloadCalibrations(), 0);
  {
    std::lock_guard<std::mutex> lock(log_mutex);
    EXPECT_NE(log.back().find("rejected"), std::string::npos);
    EXPECT_NE(log.back().find("expected dx dy dz"), std::string::npos);
  }
  std::this_thread::sleep_for(std::chrono::milliseconds(100));
  EXPECT_TRUE(wc.WaitFor(0.5));  // the previous correction stays active
  // Clients were never dropped.
  EXPECT_EQ(corrected.connections(), 1u);
  EXPECT_EQ(raw.connections(), 1u);
  corrected.Stop();
  raw.Stop();
  app.Stop();
  // Every report was corrected; the offset correction has no volume, so none is extrapolated.
  const std::string status = app.StatusLine();
  EXPECT_NE(status.find("Tracker0: "), std::string::npos) << status;
  EXPECT_EQ(status.find("Tracker0: 0 corrected"), std::string::npos) << status;
  EXPECT_NE(status.find(" corrected, 0 extrapolated (0.0 %), 0 unresolved"), std::string::npos)
      << status;
  // Every way the server closes or refuses a connection is counted (an operator asking why a
  // client lost its connection found only "dropped for not reading").
  EXPECT_NE(status.find(" 0 dropped for not reading, 0 dropped with the most output waiting over "
                        "the total, 0 closed to make room, 0 closed for "
                        "protocol errors, 0 refused, "),
            std::string::npos)
      << status;
  // Both streams recorded.
  for (const char* f : {"Tracker0_raw_tracker_stream.csv", "Tracker0_corrected_tracker_stream.csv"}) {
    std::ifstream in(dir / f);
    ASSERT_TRUE(in) << f;
    std::string line;
    int rows = 0;
    while (std::getline(in, line)) ++rows;
    EXPECT_GT(rows, 2) << f;
  }
}

TEST(TrackcalServerApp, ARefusedRecordingCreatesNoOtherRecording) {
  // The second tracker's corrected recording exists: the start is refused, and the first tracker's
  // recordings are not created (they were, header-only, and refused the next start as existing).
  const auto dir = testing::MakeTempDir("app_record_refused");
  const auto calib = dir / "calib.txt";
  WriteFile(calib, "0.25 0 0\n");
  const auto record = dir / "rec";
  std::filesystem::create_directory(record);
  WriteFile(record / "Tracker1_corrected_tracker_stream.csv", "time,sensor\n");
  TrackerSetup second = NullSetup(calib);
  second.name = "Tracker1";
  second.raw_name = "Tracker1_raw";
  AppOptions options = Loopback();
  options.record_dir = record;
  try {
    TrackcalServerApp app({NullSetup(calib), second}, options, LoadOffset,
                          [](const std::string&) {});
    ADD_FAILURE() << "no error";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("Tracker1_corrected_tracker_stream.csv already exists"),
              std::string::npos)
        << e.what();
  }
  std::vector<std::string> files;
  for (const auto& entry : std::filesystem::directory_iterator(record)) {
    files.push_back(entry.path().filename().string());
  }
  EXPECT_EQ(files, std::vector<std::string>{"Tracker1_corrected_tracker_stream.csv"});
}

TEST(TrackcalServerApp, BadSetupThrowsNamingOrigin) {
  const auto dir = testing::MakeTempDir("app_bad");
  WriteFile(dir / "bad.txt", "x\n");
  try {
    TrackcalServerApp app({NullSetup(dir / "bad.txt")}, Loopback(), LoadOffset, [](const std::string&) {});
    FAIL();
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("test.cfg:1"), std::string::npos);
  }
  auto a = NullSetup(dir / "bad.txt");
  a.calibration.reset();
  auto b = a;
  b.raw_name = "Tracker0";  // clashes with a's name
  EXPECT_THROW(TrackcalServerApp({a, b}, Loopback(), LoadOffset, [](const std::string&) {}),
               std::invalid_argument);
}

// A source the test drives by hand: the app hands it its callbacks at Start.
class ManualSource : public ReportSource {
 public:
  explicit ManualSource(std::shared_ptr<SourceCallbacks> callbacks)
      : callbacks_(std::move(callbacks)) {}
  void Start(SourceCallbacks callbacks) override { *callbacks_ = std::move(callbacks); }
  void Stop() override {}
  std::string Describe() const override { return "manual"; }

 private:
  std::shared_ptr<SourceCallbacks> callbacks_;
};

// What a raw VRPN client saw from the server: every sender description, the type names by id, and
// the user messages in order with their sender id as it was on the wire.
struct WireLog {
  struct Received {
    std::int32_t sender = 0;
    std::string type;
    std::vector<std::uint8_t> payload;
  };
  std::vector<std::pair<std::int32_t, std::string>> sender_descriptions;
  std::map<std::int32_t, std::string> types;
  std::vector<Received> messages;
  const Received* Find(std::string_view type) const {
    for (const Received& m : messages) {
      if (m.type == type) return &m;
    }
    return nullptr;
  }
};

// Reads from `fd` into `log` until `done` holds or 10 s pass; false on timeout or a broken stream.
bool ReadUntil(int fd, MessageStreamParser& parser, WireLog& log,
               const std::function<bool(const WireLog&)>& done) {
  const auto end = Clock::now() + std::chrono::seconds(10);
  std::uint8_t buf[4096];
  while (!done(log)) {
    if (Clock::now() > end) return false;
    const ssize_t n = ::recv(fd, buf, sizeof(buf), 0);
    if (n < 0 && (errno == EAGAIN || errno == EWOULDBLOCK || errno == EINTR)) continue;
    if (n <= 0) return false;
    const auto status = parser.Feed(
        std::span<const std::uint8_t>(buf, static_cast<std::size_t>(n)), [&](const Message& m) {
          if (m.header.type == kSenderDescription) {
            log.sender_descriptions.emplace_back(m.header.sender,
                                                 DecodeDescription(m.payload).value_or("?"));
          } else if (m.header.type == kTypeDescription) {
            log.types[m.header.sender] = DecodeDescription(m.payload).value_or("?");
          } else if (m.header.type >= 0) {
            log.messages.push_back(
                {m.header.sender, log.types[m.header.type], {m.payload.begin(), m.payload.end()}});
          }
        });
    if (status != MessageStreamParser::Status::kOk) return false;
  }
  return true;
}

// vrpn.cfg's "FTStylus Tracker0 0" under "vrpn_Tracker_Fastrak Tracker0 ...": the reference serves
// a tracker and a button server named Tracker0, which share one sender; a client opens
// Tracker0@host as vrpn_Tracker_Remote and vrpn_Button_Remote on one connection and tells the two
// apart by message type. On the wire: one sender description, every message with that sender id.
TEST(TrackcalServerApp, ButtonNamedLikeItsTrackerSharesTheTrackersSender) {
  auto callbacks = std::make_shared<SourceCallbacks>();
  TrackerSetup setup;
  setup.name = "Tracker0";
  setup.num_sensors = 2;
  setup.origin = "test.cfg:1";
  setup.buttons = {{"Tracker0", 1}};  // the stylus on sensor 1
  setup.make_source = [callbacks] { return std::make_unique<ManualSource>(callbacks); };
  TrackcalServerApp app({setup}, Loopback(), nullptr, [](const std::string&) {});
  app.Start();
  ASSERT_TRUE(callbacks->on_pose && callbacks->on_button);

  // The client side of both remote objects: one connection describing the name once.
  UniqueFd fd(::socket(AF_INET, SOCK_STREAM, 0));
  ASSERT_TRUE(fd.valid());
  timeval timeout{0, 100000};
  ::setsockopt(fd.get(), SOL_SOCKET, SO_RCVTIMEO, &timeout, sizeof(timeout));
  sockaddr_in server = MakeSockaddr(*ParseIpv4("127.0.0.1"), app.port());
  ASSERT_EQ(::connect(fd.get(), reinterpret_cast<sockaddr*>(&server), sizeof(server)), 0);
  auto client_names = std::make_shared<NameRegistry>();
  const std::int32_t device = client_names->AddSender("Tracker0");
  for (std::string_view type : {kPosQuatType, kButtonChangeType, kButtonStatesType, kPongType}) {
    client_names->AddType(type);
  }
  const std::int32_t ping = client_names->AddType(kPingType);
  Connection client(client_names, Connection::Options{});
  client.Start();
  client.Pack(device, ping, Timestamp::Now(), {});
  const auto& out = client.tcp_output();
  ASSERT_EQ(::send(fd.get(), out.data(), out.size(), MSG_NOSIGNAL),
            static_cast<ssize_t>(out.size()));

  // A plain tracker client of the name (and so a pass-through "*Tracker0") still gets the poses.
  VrpnTrackerClient tracker_client("Tracker0@tcp://127.0.0.1:" + std::to_string(app.port()));
  Watch watch;
  watch.Attach(tracker_client);
  tracker_client.Start();

  MessageStreamParser parser;
  WireLog log;
  // The pong says the server has read our descriptions, so it sends us this device's messages.
  ASSERT_TRUE(ReadUntil(fd.get(), parser, log, [](const WireLog& l) { return l.Find(kPongType); }));
  const auto pong_by = Clock::now() + std::chrono::seconds(10);
  while (!tracker_client.pong_received() && Clock::now() < pong_by) {
    std::this_thread::sleep_for(std::chrono::milliseconds(5));
  }
  ASSERT_TRUE(tracker_client.pong_received());
  const Rigid3d pose(QuaternionFromXyzw(0.0, 0.0, 0.6, 0.8), Eigen::Vector3d(0.1, -0.2, 0.3));
  callbacks->on_pose(1, pose, Timestamp{1000, 7});
  callbacks->on_button(1, true, Timestamp{1000, 9});
  ASSERT_TRUE(ReadUntil(fd.get(), parser, log, [](const WireLog& l) {
    return l.Find(kPosQuatType) && l.Find(kButtonChangeType);
  }));
  EXPECT_TRUE(watch.WaitFor(0.1));
  tracker_client.Stop();
  app.Stop();

  std::vector<std::int32_t> described;
  for (const auto& [id, name] : log.sender_descriptions) {
    if (name == "Tracker0") described.push_back(id);
  }
  ASSERT_EQ(described.size(), 1u) << "one sender description for the shared name";
  const std::int32_t sender = described[0];
  for (std::string_view type : {kPongType, kButtonStatesType, kPosQuatType, kButtonChangeType}) {
    const WireLog::Received* m = log.Find(type);
    ASSERT_NE(m, nullptr) << type;
    EXPECT_EQ(m->sender, sender) << type;
  }
  const auto states = DecodeButtonStates(log.Find(kButtonStatesType)->payload);
  ASSERT_TRUE(states.has_value());
  EXPECT_EQ(*states, std::vector<std::int32_t>{0});  // on connect: one button, released
  const auto report = DecodePosQuat(log.Find(kPosQuatType)->payload);
  ASSERT_TRUE(report.has_value());
  EXPECT_EQ(report->sensor, 1);
  EXPECT_EQ(report->transmitter_from_receiver.translation, pose.translation);
  const auto change = DecodeButtonChange(log.Find(kButtonChangeType)->payload);
  ASSERT_TRUE(change.has_value());
  EXPECT_EQ(change->button, 0);
  EXPECT_EQ(change->state, 1);
}

TEST(TrackcalServerApp, OtherReusedNamesAreStillServedTwice) {
  auto setup = [](const std::string& name, const std::string& origin) {
    TrackerSetup s;
    s.name = name;
    s.origin = origin;
    s.make_source = [] { return MakeNullSource(1, 0.0); };
    return s;
  };
  auto error = [](std::vector<TrackerSetup> trackers) {
    try {
      TrackcalServerApp app(std::move(trackers), Loopback(), nullptr, [](const std::string&) {});
    } catch (const std::invalid_argument& e) {
      return std::string(e.what());
    }
    return std::string();
  };
  TrackerSetup a = setup("A", "test.cfg:1");
  TrackerSetup b = setup("B", "test.cfg:3");
  a.raw_name = "A_raw";

  // The shared name is accepted once per tracker...
  b.buttons = {{"B", 0}};
  EXPECT_EQ(error({a, b}), "");
  // ...but two buttons of one name clash, as two trackers of one name do.
  b.buttons = {{"B", 0}, {"B", 1}};
  EXPECT_EQ(error({a, b}), "test.cfg:3: device name 'B' is served twice");
  b.buttons.clear();
  EXPECT_EQ(error({a, setup("A", "test.cfg:2")}), "test.cfg:2: device name 'A' is served twice");
  // A button may not take another tracker's name, nor a raw stream's (its own tracker's included).
  b.buttons = {{"A", 0}};
  EXPECT_EQ(error({a, b}), "test.cfg:3: device name 'A' is served twice");
  b.buttons = {{"A_raw", 0}};
  EXPECT_EQ(error({a, b}), "test.cfg:3: device name 'A_raw' is served twice");
  a.buttons = {{"A_raw", 0}};
  EXPECT_EQ(error({a}), "test.cfg:1: device name 'A_raw' is served twice");
  // A tracker or raw stream named like an earlier tracker's button.
  a.buttons = {{"S", 0}};
  EXPECT_EQ(error({a, setup("S", "test.cfg:4")}), "test.cfg:4: device name 'S' is served twice");
  b.buttons.clear();
  b.raw_name = "S";
  EXPECT_EQ(error({a, b}), "test.cfg:3: device name 'S' is served twice");
}

// A caller-supplied sink gets the lines escaped as the default stderr sink prints them: a device
// name (TrackerSetup comes from code, not only from the checked vrpn.cfg) and text a source relays
// (a pass-through relays another VRPN server's text) carry an escape sequence, a forged line and
// bytes that are not UTF-8, and none of them may reach the sink raw.
TEST(TrackcalServerApp, CustomLogSinkGetsEscapedLines) {
  auto callbacks = std::make_shared<SourceCallbacks>();
  TrackerSetup setup;
  setup.name =
      "Tracker\x1b]0;owned\x07"
      "0";
  setup.origin = "test.cfg:1";
  setup.make_source = [callbacks] { return std::make_unique<ManualSource>(callbacks); };
  std::vector<std::string> log;
  std::mutex log_mutex;
  TrackcalServerApp app({setup}, Loopback(), nullptr, [&](const std::string& l) {
    std::lock_guard<std::mutex> lock(log_mutex);
    log.push_back(l);
  });
  app.Start();
  ASSERT_TRUE(callbacks->on_text);
  callbacks->on_text(TextSeverity::kWarning,
                     "\x1b[2J\xff\xfe\nforged: line\xc2\x9b"
                     "1m");
  app.Stop();
  std::lock_guard<std::mutex> lock(log_mutex);
  bool saw_text = false;
  bool saw_serving = false;
  for (const std::string& line : log) {
    for (const char c : line) {
      const auto u = static_cast<unsigned char>(c);
      EXPECT_TRUE(u >= 0x20 && u < 0x7f)
          << "raw byte 0x" << std::hex << int(u) << " in: " << PrintableForLog(line);
    }
    saw_text |=
        line == "Tracker\\x1b]0;owned\\x070: \\x1b[2J\\xff\\xfe\\x0aforged: line\\xc2\\x9b1m";
    saw_serving |= line.rfind("serving Tracker\\x1b]0;owned\\x070 from manual", 0) == 0;
  }
  EXPECT_TRUE(saw_text);
  EXPECT_TRUE(saw_serving);
}

TEST(TrackcalServerApp, PassthroughCorrectsAnotherServersTracker) {
  const auto dir = testing::MakeTempDir("app_pass");
  WriteFile(dir / "calib.txt", "0 0 0.125\n");
  auto upstream_setup = NullSetup(dir / "calib.txt");
  upstream_setup.calibration.reset();
  upstream_setup.raw_name.reset();
  TrackcalServerApp upstream({upstream_setup}, Loopback(), nullptr, [](const std::string&) {});
  upstream.Start();
  TrackerSetup pass;
  pass.name = "Corrected0";
  pass.calibration = dir / "calib.txt";
  pass.origin = "test.cfg:2";
  const std::string source = "Tracker0@127.0.0.1:" + std::to_string(upstream.port());
  pass.make_source = [source] { return MakePassthroughSource(source); };
  TrackcalServerApp app({pass}, Loopback(), LoadOffset, [](const std::string&) {});
  app.Start();
  VrpnTrackerClient client("Corrected0@tcp://127.0.0.1:" + std::to_string(app.port()));
  std::mutex mutex;
  double z = NAN;
  client.SetPoseCallback([&](const TrackerReport& r) {
    std::lock_guard<std::mutex> lock(mutex);
    z = r.transmitter_from_receiver.translation.z();
  });
  client.Start();
  const auto end = Clock::now() + std::chrono::seconds(10);
  bool ok = false;
  while (Clock::now() < end && !ok) {
    std::this_thread::sleep_for(std::chrono::milliseconds(5));
    std::lock_guard<std::mutex> lock(mutex);
    ok = z == 0.125;
  }
  EXPECT_TRUE(ok);
  client.Stop();
}

}  // namespace
}  // namespace trackcal::vrpn
