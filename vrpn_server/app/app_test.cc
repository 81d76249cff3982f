#include "vrpn_server/app/app.h"

#include <gtest/gtest.h>

#include <chrono>
#include <fstream>
#include <mutex>
#include <thread>

#include "tests/test_utils.h"

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
                                                const std::optional<std::string>&) {
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
