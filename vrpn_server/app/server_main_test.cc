// trackcal-server as a process: vrpn.cfg in, VRPN out, signals.
#include <arpa/inet.h>
#include <fcntl.h>
#include <gtest/gtest.h>
#include <signal.h>
#include <sys/socket.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <cmath>
#include <cstdlib>
#include <fstream>
#include <map>
#include <sstream>
#include <thread>

#include "core/calibration_file.h"
#include "core/file_util.h"
#include "core/polynomial.h"
#include "tests/test_utils.h"
#include "vrpn_server/app/calibration_corrector.h"
#include "vrpn_server/app/config_setup.h"
#include "vrpn_server/client/tracker_client.h"
#include "vrpn_server/config.h"
#include "vrpn_server/net/socket_util.h"

namespace trackcal::vrpn {
namespace {

using Clock = std::chrono::steady_clock;

std::string ServerBinary() {
  const char* dir = std::getenv("TRACKCAL_BINARY_DIR");
  return std::string(dir ? dir : ".") + "/vrpn_server/app/trackcal-server";
}

int FreePort() {
  UniqueFd fd(::socket(AF_INET, SOCK_STREAM, 0));
  sockaddr_in sa = MakeSockaddr(*ParseIpv4("127.0.0.1"), 0);
  ::bind(fd.get(), reinterpret_cast<sockaddr*>(&sa), sizeof(sa));
  socklen_t len = sizeof(sa);
  ::getsockname(fd.get(), reinterpret_cast<sockaddr*>(&sa), &len);
  return ntohs(sa.sin_port);
}

struct Process {
  pid_t pid = -1;
  std::filesystem::path stderr_path;
  Process(const std::vector<std::string>& args, const std::filesystem::path& err) : stderr_path(err) {
    pid = ::fork();
    if (pid == 0) {
      FILE* f = std::fopen(err.c_str(), "w");
      ::dup2(fileno(f), 2);
      std::vector<char*> argv;
      for (const auto& a : args) argv.push_back(const_cast<char*>(a.c_str()));
      argv.push_back(nullptr);
      ::execv(argv[0], argv.data());
      std::_Exit(127);
    }
  }
  int Wait() {
    int status = 0;
    ::waitpid(pid, &status, 0);
    pid = -1;
    return WIFEXITED(status) ? WEXITSTATUS(status) : -WTERMSIG(status);
  }
  ~Process() {
    if (pid > 0) {
      ::kill(pid, SIGKILL);
      Wait();
    }
  }
  std::string Stderr() const {
    std::ifstream in(stderr_path);
    std::stringstream ss;
    ss << in.rdbuf();
    return ss.str();
  }
};

TEST(TrackcalServerMain, ServesNullTrackerWarnsOnUnknownLineAndStopsOnSigterm) {
  const auto dir = testing::MakeTempDir("server_main");
  std::ofstream(dir / "vrpn.cfg") << "# lab config\n"
                                     "vrpn_Tracker_Liberty Liberty0 /dev/ttyS9 115200\n"
                                     "vrpn_Tracker_NULL Tracker0 2 60.0\n";
  const int port = FreePort();
  Process server({ServerBinary(), "-f", (dir / "vrpn.cfg").string(), std::to_string(port), "--bind",
                  "127.0.0.1", "--allow", "127.0.0.0/8"},
                 dir / "stderr.txt");
  VrpnTrackerClient client("Tracker0@127.0.0.1:" + std::to_string(port));
  int reports = 0;
  client.SetPoseCallback([&](const TrackerReport&) { ++reports; });
  const auto end = Clock::now() + std::chrono::seconds(15);
  while (Clock::now() < end && reports < 10) client.Poll(0.01);
  EXPECT_GE(reports, 10);
  EXPECT_TRUE(client.pong_received());
  ::kill(server.pid, SIGHUP);  // no calibration attached: a no-op reload, the server keeps serving
  const int before = reports;
  const auto end2 = Clock::now() + std::chrono::seconds(10);
  while (Clock::now() < end2 && reports < before + 10) client.Poll(0.01);
  EXPECT_GE(reports, before + 10);
  ::kill(server.pid, SIGTERM);
  EXPECT_EQ(server.Wait(), 0);
  const std::string err = server.Stderr();
  EXPECT_NE(err.find("vrpn.cfg:2"), std::string::npos) << err;
  EXPECT_NE(err.find("vrpn_Tracker_Liberty"), std::string::npos) << err;
  EXPECT_NE(err.find("SIGHUP"), std::string::npos) << err;
}

// A calibration that adds `offset` to every position (degree-0 polynomial) in the volume
// [volume_min, 1]^3 (clamped outside, fade_distance 0 as trackcal-fit writes).
void WriteOffsetCalibration(const std::filesystem::path& path, const Eigen::Vector3d& offset,
                            const Eigen::Vector3d& volume_min = Eigen::Vector3d(-1, -1, -1),
                            int sensor = 0) {
  Calibration cal;
  cal.sensor = sensor;
  cal.chain.Append(PolynomialCorrection::FromPositionAndOrientation(
      0, Eigen::Vector3d::Zero(), Eigen::Vector3d::Ones(), {offset.x(), offset.y(), offset.z()},
      {0.0, 0.0, 0.0}));
  CalibratedVolume volume;
  volume.min = volume_min;
  volume.max = Eigen::Vector3d(1, 1, 1);
  volume.extrapolation = ExtrapolationPolicy::kClamp;
  cal.chain.SetVolume(volume);
  cal.provenance.tool = "server_main_test";
  cal.provenance.tool_version = "0";
  cal.provenance.created_utc = CurrentUtcTimestamp();
  cal.provenance.inputs.push_back({"none", Sha256Hex("x"), "calibration_capture"});
  const auto tmp = path.string() + ".new";
  std::filesystem::remove(tmp);
  WriteCalibrationFile(tmp, cal);
  std::filesystem::rename(tmp, path);  // replaced as a whole, as trackcal-fit's atomic writes do
}

TEST(TrackcalServerMain, CalibrationRawNameAndReloadOnChangeAndSighup) {
  const auto dir = testing::MakeTempDir("server_main_calib");
  WriteOffsetCalibration(dir / "calib.json", Eigen::Vector3d(0.1, 0, 0));
  std::ofstream(dir / "vrpn.cfg") << "vrpn_Tracker_NULL Tracker0 1 100.0\n"
                                     "trackcal_Calibration Tracker0 calib.json raw=Tracker0_raw\n";
  const int port = FreePort();
  Process server({ServerBinary(), "-f", (dir / "vrpn.cfg").string(), std::to_string(port), "--bind",
                  "127.0.0.1"},
                 dir / "stderr.txt");
  VrpnTrackerClient corrected("Tracker0@tcp://127.0.0.1:" + std::to_string(port));
  VrpnTrackerClient raw("Tracker0_raw@tcp://127.0.0.1:" + std::to_string(port));
  double x = NAN, raw_x = NAN;
  corrected.SetPoseCallback([&](const TrackerReport& r) { x = r.transmitter_from_receiver.translation.x(); });
  raw.SetPoseCallback([&](const TrackerReport& r) { raw_x = r.transmitter_from_receiver.translation.x(); });
  auto wait_for = [&](double expected) {
    const auto end = Clock::now() + std::chrono::seconds(15);
    while (Clock::now() < end && (x != expected || std::isnan(raw_x))) {
      corrected.Poll(0.005);
      raw.Poll(0.0);
    }
    return x == expected && !std::isnan(raw_x);
  };
  EXPECT_TRUE(wait_for(0.1)) << server.Stderr();
  EXPECT_EQ(raw_x, 0.0);
  // A changed file is picked up on its own.
  WriteOffsetCalibration(dir / "calib.json", Eigen::Vector3d(0.2, 0, 0));
  EXPECT_TRUE(wait_for(0.2)) << server.Stderr();
  // A bad file is rejected; SIGHUP does not make it active either.
  std::ofstream(dir / "calib.json.new") << "{}";
  std::filesystem::rename(dir / "calib.json.new", dir / "calib.json");
  ::kill(server.pid, SIGHUP);
  for (int i = 0; i < 100; ++i) corrected.Poll(0.005);
  EXPECT_EQ(x, 0.2);
  EXPECT_EQ(corrected.connections(), 1u);
  ::kill(server.pid, SIGTERM);
  EXPECT_EQ(server.Wait(), 0);
  const std::string err = server.Stderr();
  EXPECT_NE(err.find("rejected"), std::string::npos) << err;
}

// A trackcal-server on dir/cfg/vrpn.cfg (a NULL tracker at 100 Hz whose calibration is
// cfg/calib.json, which the test makes a symbolic link) and a client of its corrected Tracker0
// noting the x of the last pose: the NULL tracker reports the origin, so x is the offset served.
struct ServedCalibrationLink {
  explicit ServedCalibrationLink(const std::filesystem::path& dir)
      : port(FreePort()),
        server(
            [&] {
              std::ofstream(dir / "cfg" / "vrpn.cfg")
                  << "vrpn_Tracker_NULL Tracker0 1 100.0\n"
                     "trackcal_Calibration Tracker0 calib.json\n";
              return std::vector<std::string>{
                  ServerBinary(),       "-f",     (dir / "cfg" / "vrpn.cfg").string(),
                  std::to_string(port), "--bind", "127.0.0.1"};
            }(),
            dir / "stderr.txt"),
        corrected("Tracker0@tcp://127.0.0.1:" + std::to_string(port)) {
    corrected.SetPoseCallback(
        [this](const TrackerReport& r) { x = r.transmitter_from_receiver.translation.x(); });
  }
  // True once the served x equals `expected` (within 15 s).
  bool WaitFor(double expected) {
    const auto end = Clock::now() + std::chrono::seconds(15);
    while (Clock::now() < end && x != expected) corrected.Poll(0.005);
    return x == expected;
  }
  int port;
  Process server;
  VrpnTrackerClient corrected;
  double x = NAN;
};

// A calibration given as a symbolic link into another directory (calib.json ->
// ../releases/lab.json) is reloaded when the target changes: the server used to watch only the
// link's directory, which sees no event, and kept serving the old correction until a SIGHUP.
TEST(TrackcalServerMain, CalibrationSymlinkTargetChangeIsReloaded) {
  const auto dir = testing::MakeTempDir("server_main_symlink");
  std::filesystem::create_directories(dir / "cfg");
  std::filesystem::create_directories(dir / "releases");
  WriteOffsetCalibration(dir / "releases" / "lab.json", Eigen::Vector3d(0.1, 0, 0));
  std::filesystem::create_symlink("../releases/lab.json", dir / "cfg" / "calib.json");
  ServedCalibrationLink served(dir);
  EXPECT_TRUE(served.WaitFor(0.1)) << served.server.Stderr();
  WriteOffsetCalibration(dir / "releases" / "lab.json", Eigen::Vector3d(0.2, 0, 0));
  EXPECT_TRUE(served.WaitFor(0.2)) << served.server.Stderr();
  ::kill(served.server.pid, SIGTERM);
  EXPECT_EQ(served.server.Wait(), 0);
}

// A release process that re-points the link (calib.json -> ../releases/v2/lab.json, swapped by
// renaming a new link over it) and later rewrites the new target: the new target's directory must
// be watched too. The server used to watch only the directories it found at start, so the rewrite
// of v2/lab.json went unseen and the old correction stayed until a SIGHUP.
TEST(TrackcalServerMain, CalibrationSymlinkRepointedToAnotherDirectoryIsWatched) {
  const auto dir = testing::MakeTempDir("server_main_symlink_repoint");
  std::filesystem::create_directories(dir / "cfg");
  std::filesystem::create_directories(dir / "releases" / "v1");
  std::filesystem::create_directories(dir / "releases" / "v2");
  WriteOffsetCalibration(dir / "releases" / "v1" / "lab.json", Eigen::Vector3d(0.1, 0, 0));
  WriteOffsetCalibration(dir / "releases" / "v2" / "lab.json", Eigen::Vector3d(0.2, 0, 0));
  std::filesystem::create_symlink("../releases/v1/lab.json", dir / "cfg" / "calib.json");
  ServedCalibrationLink served(dir);
  EXPECT_TRUE(served.WaitFor(0.1)) << served.server.Stderr();
  // Atomic re-point, as `ln -sfn` does it: a new link renamed over the old one.
  std::filesystem::create_symlink("../releases/v2/lab.json", dir / "cfg" / "calib.json.new");
  std::filesystem::rename(dir / "cfg" / "calib.json.new", dir / "cfg" / "calib.json");
  EXPECT_TRUE(served.WaitFor(0.2)) << served.server.Stderr();
  // The new target is rewritten in place of itself (atomically, in its own directory).
  WriteOffsetCalibration(dir / "releases" / "v2" / "lab.json", Eigen::Vector3d(0.3, 0, 0));
  EXPECT_TRUE(served.WaitFor(0.3)) << served.server.Stderr();
  ::kill(served.server.pid, SIGTERM);
  EXPECT_EQ(served.server.Wait(), 0);
}

// A calibration is fitted for one receiver (its sensor offset and coil gains belong to that
// receiver), so sensor=<n> applies it to that sensor only: each sensor gets its own file, a sensor
// without one is served uncorrected, and a changed file is reloaded for its sensor alone. Before,
// sensor= was an unknown option and the one calibration of a tracker corrected every sensor.
TEST(TrackcalServerMain, CalibrationPerSensor) {
  const auto dir = testing::MakeTempDir("server_main_sensor");
  WriteOffsetCalibration(dir / "a.json", Eigen::Vector3d(0.1, 0, 0));
  WriteOffsetCalibration(dir / "b.json", Eigen::Vector3d(0.3, 0, 0));
  std::ofstream(dir / "vrpn.cfg") << "vrpn_Tracker_NULL Tracker0 3 100.0\n"
                                     "trackcal_Calibration Tracker0 a.json sensor=0\n"
                                     "trackcal_Calibration Tracker0 b.json sensor=1 raw=Raw0\n";
  const int port = FreePort();
  Process server({ServerBinary(), "-f", (dir / "vrpn.cfg").string(), std::to_string(port), "--bind",
                  "127.0.0.1"},
                 dir / "stderr.txt");
  VrpnTrackerClient corrected("Tracker0@tcp://127.0.0.1:" + std::to_string(port));
  VrpnTrackerClient raw("Raw0@tcp://127.0.0.1:" + std::to_string(port));
  std::map<int, double> x, raw_x;
  corrected.SetPoseCallback(
      [&](const TrackerReport& r) { x[r.sensor] = r.transmitter_from_receiver.translation.x(); });
  raw.SetPoseCallback([&](const TrackerReport& r) {
    raw_x[r.sensor] = r.transmitter_from_receiver.translation.x();
  });
  auto wait_for = [&](const std::map<int, double>& expected) {
    const auto end = Clock::now() + std::chrono::seconds(15);
    while (Clock::now() < end && (x != expected || raw_x.size() < 3)) {
      corrected.Poll(0.005);
      raw.Poll(0.0);
    }
    return x == expected;
  };
  // The null tracker reports the origin: the offsets are exact.
  EXPECT_TRUE(wait_for({{0, 0.1}, {1, 0.3}, {2, 0.0}})) << server.Stderr();
  EXPECT_EQ(raw_x, (std::map<int, double>{{0, 0.0}, {1, 0.0}, {2, 0.0}}));
  WriteOffsetCalibration(dir / "b.json", Eigen::Vector3d(0.4, 0, 0));
  EXPECT_TRUE(wait_for({{0, 0.1}, {1, 0.4}, {2, 0.0}})) << server.Stderr();
  ::kill(server.pid, SIGTERM);
  EXPECT_EQ(server.Wait(), 0);
  const std::string err = server.Stderr();
  EXPECT_NE(err.find("Tracker0 sensor 1: reloaded"), std::string::npos) << err;
  // The reload line names the file once (it said "reloaded b.json (b.json (...))").
  const std::string reloaded = err.substr(err.find("Tracker0 sensor 1: reloaded"),
                                          err.find('\n', err.find("Tracker0 sensor 1: reloaded")) -
                                              err.find("Tracker0 sensor 1: reloaded"));
  const std::string b = (dir / "b.json").string();
  ASSERT_NE(reloaded.find(b), std::string::npos) << reloaded;
  EXPECT_EQ(reloaded.find(b), reloaded.rfind(b)) << reloaded;
  EXPECT_NE(err.find("for sensor 1 (other sensors uncorrected)"), std::string::npos) << err;
}

// A calibration holds one receiver's sensor offset and coil gains: a file fitted for receiver 1
// (capture sensor 1, VRPN sensor 0) on a `sensor=1` line served receiver 2 with receiver 1's
// correction without a word (cm-level errors). The file records its receiver; the server refuses a
// mismatch at start naming the line, rejects it on reload (keeping the previous correction), and
// logs the receiver with the correction. Files without the field, and lines without sensor=, are
// served as before.
TEST(SetupFromConfig, CalibrationOfAnotherReceiverIsRefused) {
  const auto dir = testing::MakeTempDir("server_main_fitted_sensor");
  const Eigen::Vector3d low(-1, -1, -1);
  WriteOffsetCalibration(dir / "r1.json", Eigen::Vector3d(0.1, 0, 0), low, 1);
  WriteOffsetCalibration(dir / "old.json", Eigen::Vector3d(0.1, 0, 0), low, 0);
  auto app_of = [&](const std::string& cfg, std::vector<std::string>* log) {
    ConfigSetup setup = SetupFromConfig(
        ParseVrpnConfig("vrpn_Tracker_NULL T 2 60\n" + cfg, (dir / "vrpn.cfg").string()),
        "127.0.0.1:3883");
    return std::make_unique<TrackcalServerApp>(std::move(setup.trackers), AppOptions{},
                                               LoadCalibrationCorrector,
                                               [log](const std::string& l) { log->push_back(l); });
  };
  std::vector<std::string> log;
  try {
    app_of("trackcal_Calibration T r1.json sensor=1\n", &log);
    ADD_FAILURE() << "receiver 1's file was accepted on VRPN sensor 1";
  } catch (const std::invalid_argument& e) {
    const std::string what = e.what();
    EXPECT_NE(what.find("vrpn.cfg:2: calibration of 'T sensor 1': "), std::string::npos) << what;
    EXPECT_NE(what.find("fitted for receiver 1"), std::string::npos) << what;
    EXPECT_NE(what.find("VRPN sensor=0, not sensor=1"), std::string::npos) << what;
  }
  // On its own receiver's line: served, and the log says which receiver it was fitted for.
  log.clear();
  auto app = app_of("trackcal_Calibration T r1.json sensor=0\n", &log);
  ASSERT_FALSE(log.empty());
  EXPECT_NE(log.back().find("fitted for receiver 1 = VRPN sensor 0"), std::string::npos)
      << log.back();
  // A new file of another receiver is rejected on reload; the previous correction stays.
  WriteOffsetCalibration(dir / "r1.json", Eigen::Vector3d(0.2, 0, 0), low, 2);
  EXPECT_EQ(app->ReloadCalibrations(), 0);
  EXPECT_NE(log.back().find("rejected new"), std::string::npos) << log.back();
  EXPECT_NE(log.back().find("fitted for receiver 2"), std::string::npos) << log.back();
  // Unrecorded receiver (older files), or a line for every sensor: served as before.
  EXPECT_NO_THROW(app_of("trackcal_Calibration T old.json sensor=1\n", &log));
  EXPECT_NO_THROW(app_of("trackcal_Calibration T r1.json\n", &log));
}

// A Fastrak reports each receiver in the hemisphere its H command sets (FASTRAK.md: vrpn.cfg's
// extra command lines, sent at every reset, as the reference does). A calibration captured in +x
// (its volume at x > 0) served with `H1,-1,0,0` saw every report mirrored to x < 0, outside its
// volume, and extrapolated every pose without a word. Refused for the station the command sets;
// another station's hemisphere, hemisphere tracking (H1,0,0,0) or the same hemisphere are served.
TEST(SetupFromConfig, CalibrationOfAnotherHemisphereIsRefused) {
  const auto dir = testing::MakeTempDir("server_main_hemisphere");
  WriteOffsetCalibration(dir / "plus_x.json", Eigen::Vector3d(0.1, 0, 0),
                         Eigen::Vector3d(0.05, -1, -1));  // a capture in the +x hemisphere
  auto error_of = [&](const std::string& commands, const std::string& calibration) {
    ConfigSetup setup =
        SetupFromConfig(ParseVrpnConfig("vrpn_Tracker_Fastrak T /dev/null 115200 \\\n" + commands +
                                            "\ntrackcal_Calibration T " + calibration + "\n",
                                        (dir / "vrpn.cfg").string()),
                        "127.0.0.1:3883");
    try {
      TrackcalServerApp app(std::move(setup.trackers), AppOptions{}, LoadCalibrationCorrector,
                            [](const std::string&) {});
    } catch (const std::invalid_argument& e) {
      return std::string(e.what());
    }
    return std::string("no error");
  };
  for (const std::string calibration : {"plus_x.json", "plus_x.json sensor=0"}) {
    const std::string error = error_of("H1,-1,0,0", calibration);
    EXPECT_NE(error.find("vrpn.cfg:3: calibration of 'T"), std::string::npos) << error;
    EXPECT_NE(error.find("other hemisphere than H1,-1,0,0"), std::string::npos) << error;
    EXPECT_NE(error.find("for station 1 (VRPN sensor 0)"), std::string::npos) << error;
  }
  EXPECT_EQ(error_of("H1,1,0,0", "plus_x.json sensor=0"), "no error");
  EXPECT_EQ(error_of("H1,-1,0,0\\\nH1,0,0,0", "plus_x.json"), "no error");  // tracking
  EXPECT_EQ(error_of("H2,-1,0,0", "plus_x.json sensor=0"), "no error");     // another station
  EXPECT_NE(error_of("H2,-1,0,0", "plus_x.json sensor=1").find("for station 2"), std::string::npos);
  EXPECT_EQ(error_of("*0.5", "plus_x.json"), "no error");
}

// Errors name the vrpn.cfg line they come from: the server's limits on a vrpn_Tracker_NULL line are
// checked when the file is read (they used to fail at start-up, naming only the tracker), and a
// calibration file names its trackcal_Calibration line (it used to name the tracker's).
TEST(SetupFromConfig, ErrorsNameTheLineTheyComeFrom) {
  auto error_of = [](const std::string& line) {
    try {
      SetupFromConfig(ParseVrpnConfig("# lab\n" + line + "\n", "vrpn.cfg"), "127.0.0.1:3883");
    } catch (const std::invalid_argument& e) {
      return std::string(e.what());
    }
    return std::string("no error");
  };
  EXPECT_NE(
      error_of("vrpn_Tracker_NULL Tracker0 2000 60").find("vrpn.cfg:2: TrackerSpec.num_sensors"),
      std::string::npos)
      << error_of("vrpn_Tracker_NULL Tracker0 2000 60");
  EXPECT_NE(error_of("vrpn_Tracker_NULL Tracker0 2 20000").find("vrpn.cfg:2: NullTracker: rate"),
            std::string::npos)
      << error_of("vrpn_Tracker_NULL Tracker0 2 20000");
  EXPECT_EQ(error_of("vrpn_Tracker_NULL Tracker0 1024 10000"), "no error");
  // A calibration that cannot be loaded is named by its own line, not the tracker's.
  ConfigSetup setup = SetupFromConfig(
      ParseVrpnConfig(
          "vrpn_Tracker_NULL T 1 60\n# calibrations\ntrackcal_Calibration T missing.json\n",
          "vrpn.cfg"),
      "127.0.0.1:3883");
  try {
    TrackcalServerApp app(std::move(setup.trackers), AppOptions{}, LoadCalibrationCorrector);
    ADD_FAILURE() << "expected an error for missing.json";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("vrpn.cfg:3: calibration of 'T'"), std::string::npos)
        << e.what();
  }
  // A sensor the tracker does not have would never be corrected.
  EXPECT_EQ(error_of("vrpn_Tracker_NULL T 2 60\ntrackcal_Calibration T c.json sensor=2"),
            "vrpn.cfg:3: field 'sensor': tracker 'T' has sensors 0..1, got 2");
  // A pass-through of this server's own tracker is marked, for the allow-list.
  EXPECT_TRUE(SetupFromConfig(ParseVrpnConfig("vrpn_Tracker_NULL T 1 60\n"
                                              "trackcal_Tracker_Passthrough Head *T\n",
                                              "vrpn.cfg"),
                              "127.0.0.1:3883")
                  .reads_this_server);
  EXPECT_FALSE(
      SetupFromConfig(ParseVrpnConfig("vrpn_Tracker_NULL T 1 60\n", "vrpn.cfg"), "127.0.0.1:3883")
          .reads_this_server);
}

TEST(TrackcalServerMain, AllowListAdmitsThePassthroughOfItsOwnTracker) {
  // "*Tracker0" connects from this host to this server: an allow-list of another network must not
  // refuse it, or Head waits for ever with no error.
  const auto dir = testing::MakeTempDir("server_main_allow");
  std::ofstream(dir / "vrpn.cfg") << "vrpn_Tracker_NULL Tracker0 1 100.0\n"
                                     "trackcal_Tracker_Passthrough Head *Tracker0\n";
  Process server({ServerBinary(), "-f", (dir / "vrpn.cfg").string(), std::to_string(FreePort()),
                  "--bind", "127.0.0.1", "--allow", "10.0.0.0/8"},
                 dir / "stderr.txt");
  // The pass-through connects within its first retry (well under 1 s on an idle host); 3 s leaves
  // room for a loaded CI machine.
  std::this_thread::sleep_for(std::chrono::seconds(3));
  ::kill(server.pid, SIGTERM);
  EXPECT_EQ(server.Wait(), 0);
  const std::string err = server.Stderr();
  EXPECT_EQ(err.find("not in allow-list"), std::string::npos) << err;
  EXPECT_NE(err.find("status: 1 client(s)"), std::string::npos) << err;
}

// vrpn.cfg's fade_distance=<metres> is what `outside=fade` fades over (the file's own fade_distance
// is 0 for every file trackcal-fit writes with another policy).
TEST(TrackcalServerMain, OutsideFadeUsesTheConfiguredFadeDistance) {
  const auto dir = testing::MakeTempDir("server_main_fade");
  // The null tracker reports the origin, 0.1 m outside the volume's x >= 0.1 face.
  WriteOffsetCalibration(dir / "calib.json", Eigen::Vector3d(0.1, 0, 0),
                         Eigen::Vector3d(0.1, -1, -1));
  std::ofstream(dir / "vrpn.cfg") << "vrpn_Tracker_NULL Tracker0 1 100.0\n"
                                     "trackcal_Calibration Tracker0 calib.json outside=fade "
                                     "fade_distance=0.2\n";
  const int port = FreePort();
  Process server({ServerBinary(), "-f", (dir / "vrpn.cfg").string(), std::to_string(port), "--bind",
                  "127.0.0.1"},
                 dir / "stderr.txt");
  VrpnTrackerClient corrected("Tracker0@tcp://127.0.0.1:" + std::to_string(port));
  double x = NAN;
  corrected.SetPoseCallback(
      [&](const TrackerReport& r) { x = r.transmitter_from_receiver.translation.x(); });
  const auto end = Clock::now() + std::chrono::seconds(15);
  while (Clock::now() < end && std::isnan(x)) corrected.Poll(0.005);
  // Half way through the fade: smoothstep weight 1 - 0.5^2 (3 - 2 * 0.5) = 0.5 of the 0.1 m offset.
  EXPECT_NEAR(x, 0.05, 1e-12) << server.Stderr();
  ::kill(server.pid, SIGTERM);
  server.Wait();
}

// fade_distance=<metres> only acts with outside=fade (given, or the file's own policy); with any
// other policy it was ignored without a word, and the lab believed the correction faded out.
TEST(TrackcalServerMain, FadeDistanceWithoutFadeIsRefusedNamingTheLine) {
  const auto dir = testing::MakeTempDir("server_main_fade_distance");
  WriteOffsetCalibration(dir / "calib.json", Eigen::Vector3d(0.1, 0, 0),
                         Eigen::Vector3d(0.1, -1, -1));  // written with outside = clamp
  const auto start = [&](const std::string& options) {
    ConfigSetup setup =
        SetupFromConfig(ParseVrpnConfig("vrpn_Tracker_NULL T 1 60\ntrackcal_Calibration T " +
                                            (dir / "calib.json").string() + options + "\n",
                                        "vrpn.cfg"),
                        "127.0.0.1:3883");
    try {
      TrackcalServerApp app(std::move(setup.trackers), AppOptions{}, LoadCalibrationCorrector);
    } catch (const std::invalid_argument& e) {
      return std::string(e.what());
    }
    return std::string("no error");
  };
  const std::string refused = start(" fade_distance=0.2");
  EXPECT_NE(refused.find("vrpn.cfg:2: calibration of 'T'"), std::string::npos) << refused;
  EXPECT_NE(refused.find("fade_distance=0.2 has no effect: outside the calibrated volume is "
                         "'clamp' (add outside=fade)"),
            std::string::npos)
      << refused;
  EXPECT_NE(start(" outside=linear fade_distance=0.2").find("is 'linear'"), std::string::npos);
  EXPECT_EQ(start(" outside=fade fade_distance=0.2"), "no error");
  EXPECT_EQ(start(""), "no error");
}

TEST(TrackcalServerMain, BindTakesAHostNameAsVrpnServersNicDoes) {
  // vrpn_server -NIC takes an interface's name as well as its address; a lab's start script with
  // `-NIC localhost` (or the host's own name) refused to start.
  const auto dir = testing::MakeTempDir("server_main_nic");
  std::ofstream(dir / "vrpn.cfg") << "vrpn_Tracker_NULL Tracker0 1 60.0\n";
  const int port = FreePort();
  Process server({ServerBinary(), "-f", (dir / "vrpn.cfg").string(), std::to_string(port), "-NIC",
                  "localhost"},
                 dir / "stderr.txt");
  VrpnTrackerClient client("Tracker0@127.0.0.1:" + std::to_string(port));
  int reports = 0;
  client.SetPoseCallback([&](const TrackerReport&) { ++reports; });
  const auto end = Clock::now() + std::chrono::seconds(15);
  while (Clock::now() < end && reports < 5) client.Poll(0.01);
  EXPECT_GE(reports, 5);
  ::kill(server.pid, SIGTERM);
  EXPECT_EQ(server.Wait(), 0);
  EXPECT_NE(server.Stderr().find("-NIC localhost: listening on 127.0.0.1"), std::string::npos)
      << server.Stderr();
}

// What the server prints quotes vrpn.cfg with control bytes and bytes that are not UTF-8 escaped:
// an escape sequence in the file reached the operator's terminal raw in the fatal error. (A device
// name can no longer carry one: vrpn.cfg refuses it; the log lines that quote names are escaped by
// LogToStderr and TrackcalServerApp::Log, tested in app_test.)
TEST(TrackcalServerMain, PrintsTheFilesBytesEscaped) {
  const auto dir = testing::MakeTempDir("server_main_escape");
  std::ofstream(dir / "vrpn.cfg") << "vrpn_Tracker_NULL T\x1b[2J\xff 2 60\n";
  Process bad({ServerBinary(), "-f", (dir / "vrpn.cfg").string()}, dir / "e1.txt");
  EXPECT_EQ(bad.Wait(), 1);
  EXPECT_EQ(bad.Stderr(), "trackcal-server: error: " + (dir / "vrpn.cfg").string() +
                              ":1: field 'name': device name 'T\\x1b[2J\\xff' contains a control "
                              "character (a name must be printable; control bytes reach clients' "
                              "logs and terminals)\n");

  std::ofstream(dir / "vrpn.cfg") << "vrpn_Tracker_NULL T 2 60\n"
                                     "trackcal_Calibration T c.json sensor=5\x1b[2J\xff\n";
  Process bad_sensor({ServerBinary(), "-f", (dir / "vrpn.cfg").string()}, dir / "e2.txt");
  EXPECT_EQ(bad_sensor.Wait(), 1);
  const std::string err = bad_sensor.Stderr();
  EXPECT_NE(err.find("vrpn.cfg:2: field 'sensor'"), std::string::npos) << err;
  EXPECT_NE(err.find("5\\x1b[2J\\xff"), std::string::npos) << err;
  EXPECT_EQ(err.find('\x1b'), std::string::npos) << err;
  EXPECT_EQ(err.find('\xff'), std::string::npos) << err;
}

// A stderr nobody reads (a full pipe) must not keep a stopping server from exiting. The warning
// that a recording could not be published (its final name taken while recording) was written to
// std::cerr directly, bypassing LogToStderr's queue: with the pipe full it blocked the main thread
// in app.Stop() for ever, SIGKILL was needed and the recorders after it were never published.
TEST(TrackcalServerMain, AnUnreadStderrDoesNotHoldTheStopOfARecordingServer) {
  const auto dir = testing::MakeTempDir("server_main_unread");
  const auto rec = dir / "rec";
  std::filesystem::create_directory(rec);
  std::ofstream(dir / "vrpn.cfg") << "vrpn_Tracker_NULL Tracker0 1 60.0\n";
  int fds[2];
  ASSERT_EQ(::pipe2(fds, O_CLOEXEC), 0);
  // Filled before the server starts: every line it writes to stderr would block.
  ASSERT_EQ(::fcntl(fds[1], F_SETFL, O_NONBLOCK), 0);
  const std::string filler(4096, '.');
  while (::write(fds[1], filler.data(), filler.size()) > 0) {
  }
  ASSERT_EQ(::fcntl(fds[1], F_SETFL, 0), 0);
  const std::vector<std::string> args = {ServerBinary(),
                                         "-f",
                                         (dir / "vrpn.cfg").string(),
                                         std::to_string(FreePort()),
                                         "--bind",
                                         "127.0.0.1",
                                         "--record",
                                         rec.string()};
  const pid_t pid = ::fork();
  if (pid == 0) {
    ::dup2(fds[1], 2);
    std::vector<char*> argv;
    for (const auto& a : args) argv.push_back(const_cast<char*>(a.c_str()));
    argv.push_back(nullptr);
    ::execv(argv[0], argv.data());
    std::_Exit(127);
  }
  ::close(fds[1]);
  const auto raw = rec / "Tracker0_raw_tracker_stream.csv";
  const auto corrected = rec / "Tracker0_corrected_tracker_stream.csv";
  auto partial = [](std::filesystem::path p) { return p += ".partial"; };
  const auto started = Clock::now() + std::chrono::seconds(15);
  while (Clock::now() < started &&
         !(std::filesystem::exists(partial(raw)) && std::filesystem::exists(partial(corrected)))) {
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  ASSERT_TRUE(std::filesystem::exists(partial(corrected)));
  std::ofstream(raw) << "someone else's file\n";  // the raw recording cannot take its name
  ::kill(pid, SIGTERM);
  // The server waits at most 2 s for its queued lines (kLogFlushTimeout); generous beyond that.
  int status = 0;
  pid_t done = 0;
  const auto end = Clock::now() + std::chrono::seconds(20);
  while (Clock::now() < end && (done = ::waitpid(pid, &status, WNOHANG)) == 0) {
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  if (done == 0) {
    ::kill(pid, SIGKILL);
    ::waitpid(pid, &status, 0);
  }
  ::close(fds[0]);
  EXPECT_EQ(done, pid) << "trackcal-server did not stop while its stderr was not read";
  EXPECT_TRUE(WIFEXITED(status) && WEXITSTATUS(status) == 0) << status;
  // The raw recording stays in its .partial file; the corrected one is published.
  EXPECT_TRUE(std::filesystem::exists(partial(raw)));
  EXPECT_TRUE(std::filesystem::exists(corrected));
  EXPECT_FALSE(std::filesystem::exists(partial(corrected)));
}

TEST(TrackcalServerMain, BadArgumentsAndBusyPortFail) {
  const auto dir = testing::MakeTempDir("server_main_bad");
  std::ofstream(dir / "vrpn.cfg") << "vrpn_Tracker_NULL Tracker0 1 10.0\n";
  {
    Process p({ServerBinary(), "-f", (dir / "vrpn.cfg").string(), "--allow", "10.0.0.0/99"}, dir / "e1.txt");
    EXPECT_EQ(p.Wait(), 1);
    EXPECT_NE(p.Stderr().find("10.0.0.0/99"), std::string::npos);
  }
  {
    UniqueFd busy(::socket(AF_INET, SOCK_STREAM, 0));
    sockaddr_in sa = MakeSockaddr(*ParseIpv4("127.0.0.1"), 0);
    ::bind(busy.get(), reinterpret_cast<sockaddr*>(&sa), sizeof(sa));
    ::listen(busy.get(), 1);
    socklen_t len = sizeof(sa);
    ::getsockname(busy.get(), reinterpret_cast<sockaddr*>(&sa), &len);
    const std::string port = std::to_string(ntohs(sa.sin_port));
    Process p({ServerBinary(), "-f", (dir / "vrpn.cfg").string(), port, "--bind", "127.0.0.1"}, dir / "e2.txt");
    EXPECT_EQ(p.Wait(), 1);
    EXPECT_NE(p.Stderr().find(port), std::string::npos) << p.Stderr();
  }
  {
    Process p({ServerBinary(), "-f", (dir / "missing.cfg").string()}, dir / "e3.txt");
    EXPECT_EQ(p.Wait(), 1);
    EXPECT_NE(p.Stderr().find("missing.cfg"), std::string::npos);
  }
}

}  // namespace
}  // namespace trackcal::vrpn
