// End to end: Fastrak emulator (pty) -> Fastrak driver -> correction -> VRPN server -> our client.
// The emulator's measurement model distorts the truth by a known rigid error; the calibration file
// undoes it, so the corrected device must match the emulator's truth and the raw device what the
// emulator reported.
#include <gtest/gtest.h>

#include <chrono>
#include <iostream>
#include <mutex>
#include <thread>

#include "core/calibration_file.h"
#include "core/file_util.h"
#include "core/polynomial.h"
#include "sim/emulator/emulator.h"
#include "tests/test_utils.h"
#include "vrpn_server/app/app.h"
#include "vrpn_server/app/calibration_corrector.h"
#include "vrpn_server/app/fastrak_source.h"

namespace trackcal::vrpn {
namespace {

using Clock = std::chrono::steady_clock;

// The Fastrak's binary records hold IEEE single floats (inches, quaternion components): the raw
// poses are the emulator's doubles rounded to float, |error| < 1e-7 relative, i.e. below 1e-6 m on
// a 1 m position and below 1e-6 rad on the rotation. The correction is exact in doubles.
constexpr double kPositionTolerance = 1e-6;
constexpr double kAngleTolerance = 1e-6;

const Eigen::Vector3d kDistortionOffset(0.012, -0.007, 0.004);
Eigen::Quaterniond DistortionRotation() {
  return Eigen::Quaterniond(Eigen::AngleAxisd(0.02, Eigen::Vector3d(0.3, -0.5, 0.8).normalized()));
}

class RigidDistortion : public emulator::MeasurementModel {
 public:
  Rigid3d Reported(int /*station*/, const Rigid3d& truth, double /*t_s*/) override {
    return Rigid3d(DistortionRotation() * truth.rotation, truth.translation + kDistortionOffset);
  }
};

// A degree-0 polynomial whose error is the inverse of the distortion (times `scale`).
void WriteCalibration(const std::filesystem::path& path, double scale) {
  const Eigen::Vector3d ep = -scale * kDistortionOffset;
  const Eigen::Vector3d eq = scale * VectorPart<double>(DistortionRotation().conjugate());
  Calibration cal;
  cal.description = "inverse of the e2e test's rigid distortion";
  cal.chain.Append(PolynomialCorrection::FromPositionAndOrientation(
      0, Eigen::Vector3d::Zero(), Eigen::Vector3d::Ones(), {ep.x(), ep.y(), ep.z()},
      {eq.x(), eq.y(), eq.z()}));
  CalibratedVolume volume;
  volume.min = Eigen::Vector3d(-2, -2, -2);
  volume.max = Eigen::Vector3d(2, 2, 2);
  cal.chain.SetVolume(volume);
  cal.provenance.tool = "e2e_test";
  cal.provenance.tool_version = "0";
  cal.provenance.created_utc = CurrentUtcTimestamp();
  cal.provenance.inputs.push_back({"none", Sha256Hex("e2e"), "calibration_capture"});
  std::filesystem::remove(path);
  WriteCalibrationFile(path, cal);
}

struct Collector {
  std::mutex mutex;
  std::map<int, TrackerReport> last;
  int count = 0;
  void Attach(VrpnTrackerClient& c) {
    c.SetPoseCallback([this](const TrackerReport& r) {
      std::lock_guard<std::mutex> lock(mutex);
      last[r.sensor] = r;
      ++count;
    });
  }
  int Count() {
    std::lock_guard<std::mutex> lock(mutex);
    return count;
  }
  std::optional<Rigid3d> Pose(int sensor) {
    std::lock_guard<std::mutex> lock(mutex);
    auto it = last.find(sensor);
    if (it == last.end()) return std::nullopt;
    return it->second.transmitter_from_receiver;
  }
  // Waits until `n` more reports arrived.
  bool WaitMore(int n, double timeout_s = 20) {
    const int target = Count() + n;
    const auto end = Clock::now() + std::chrono::duration<double>(timeout_s);
    while (Clock::now() < end) {
      if (Count() >= target) return true;
      std::this_thread::sleep_for(std::chrono::milliseconds(5));
    }
    return false;
  }
};

class EndToEnd : public ::testing::Test {
 protected:
  void SetUp() override {
    dir_ = testing::MakeTempDir("e2e");
    WriteCalibration(dir_ / "calib.json", 1.0);
    truth_ = {Rigid3d(QuaternionFromXyzw(0.1, 0.2, 0.3, 0.927), Eigen::Vector3d(0.30, -0.12, 0.45)),
              Rigid3d(QuaternionFromXyzw(-0.3, 0.0, 0.1, 0.95), Eigen::Vector3d(0.05, 0.21, -0.33))};
    for (auto& t : truth_) t.rotation.normalize();
    emulator::EmulatorOptions eo;
    eo.device.num_stations = 2;
    // The driver opens the symlink: after a disconnect fault the new pty has another path.
    eo.link_path = (dir_ / "fastrak").string();
    emulator_ = std::make_unique<emulator::BackgroundEmulator>(
        eo, std::make_unique<emulator::StaticPoseSource>(truth_), std::make_unique<RigidDistortion>());
    TrackerSetup setup;
    setup.name = "Tracker0";
    setup.raw_name = "Tracker0_raw";
    setup.num_sensors = 4;
    setup.calibration = dir_ / "calib.json";
    setup.origin = "e2e";
    setup.buttons = {{"Stylus0", 0}};  // FTStylus on station 1
    fastrak::FastrakOptions fo;
    fo.stylus_sensors = {0};
    fo.port = eo.link_path;
    fo.timings = fastrak::FastrakTimings::Fast();
    setup.make_source = [fo] { return MakeFastrakSource(fo); };
    AppOptions ao;
    ao.server.bind_address = "127.0.0.1";
    ao.server.port = 0;
    app_ = std::make_unique<TrackcalServerApp>(std::vector<TrackerSetup>{setup}, ao,
                                               LoadCalibrationCorrector, [this](const std::string& l) {
                                                 std::lock_guard<std::mutex> lock(log_mutex_);
                                                 log_.push_back(l);
                                               });
    app_->Start();
  }
  void TearDown() override {
    for (auto& c : clients_) c->Stop();
    app_->Stop();
    if (HasFailure()) {  // the server's log (driver texts) makes a failure under load diagnosable
      std::lock_guard<std::mutex> lock(log_mutex_);
      for (const std::string& line : log_) std::cerr << "server log: " << line << "\n";
    }
  }
  // A started client that lives until the end of the test.
  VrpnTrackerClient* Client(const std::string& device, bool tcp, Collector& col) {
    clients_.push_back(std::make_unique<VrpnTrackerClient>(
        device + (tcp ? "@tcp://" : "@") + "127.0.0.1:" + std::to_string(app_->port())));
    col.Attach(*clients_.back());
    clients_.back()->Start();
    return clients_.back().get();
  }
  Rigid3d Reported(int i) const { return RigidDistortion().Reported(i + 1, truth_[i], 0); }

  std::filesystem::path dir_;
  std::vector<Rigid3d> truth_;
  std::unique_ptr<emulator::BackgroundEmulator> emulator_;
  std::unique_ptr<TrackcalServerApp> app_;
  // Collectors outlive the clients that call into them (clients stop in TearDown).
  Collector corrected_, raw_, late_;
  std::vector<std::unique_ptr<VrpnTrackerClient>> clients_;
  std::mutex log_mutex_;
  std::vector<std::string> log_;
};

TEST_F(EndToEnd, RawMatchesEmulatorCorrectedMatchesTruthBothModes) {
  Collector& corrected = corrected_;
  Collector& raw = raw_;
  auto c1 = Client("Tracker0", /*tcp=*/true, corrected);
  auto c2 = Client("Tracker0_raw", /*tcp=*/false, raw);
  ASSERT_TRUE(corrected.WaitMore(40));
  ASSERT_TRUE(raw.WaitMore(40));
  for (int i = 0; i < 2; ++i) {
    ASSERT_TRUE(corrected.Pose(i) && raw.Pose(i)) << i;
    EXPECT_TRUE(testing::PosesNear(truth_[i], *corrected.Pose(i), kPositionTolerance, kAngleTolerance)) << i;
    EXPECT_TRUE(testing::PosesNear(Reported(i), *raw.Pose(i), kPositionTolerance, kAngleTolerance)) << i;
    // The distortion is far larger than the tolerance: the test can tell raw from corrected.
    EXPECT_FALSE(testing::PosesNear(truth_[i], *raw.Pose(i), 1e-3, 1e-3)) << i;
  }
  EXPECT_TRUE(c1->pong_received());
  EXPECT_TRUE(c2->pong_received());
}

TEST_F(EndToEnd, StylusServedAsButton) {
  Collector unused;
  auto stylus = Client("Stylus0", /*tcp=*/true, unused);
  std::mutex mutex;
  std::vector<ButtonChange> changes;
  stylus->Stop();  // set the callback while the client thread is not running
  stylus->SetMessageCallback([&](const ReceivedMessage& m) {
    if (m.type != kButtonChangeType) return;
    std::lock_guard<std::mutex> lock(mutex);
    changes.push_back(*DecodeButtonChange(m.payload));
  });
  stylus->Start();
  auto wait = [&](std::size_t n) {
    const auto end = Clock::now() + std::chrono::seconds(10);
    while (Clock::now() < end) {
      {
        std::lock_guard<std::mutex> lock(mutex);
        if (changes.size() >= n) return true;
      }
      std::this_thread::sleep_for(std::chrono::milliseconds(5));
    }
    return false;
  };
  const auto pong_by = Clock::now() + std::chrono::seconds(10);
  while (Clock::now() < pong_by && !stylus->pong_received()) std::this_thread::sleep_for(std::chrono::milliseconds(5));
  ASSERT_TRUE(stylus->pong_received());
  ASSERT_EQ(emulator_->Control("button 1 1").rfind("ok", 0), 0u);
  ASSERT_TRUE(wait(1));
  {
    std::lock_guard<std::mutex> lock(mutex);
    // The driver reports the first state after streaming starts (released) and then the press.
    EXPECT_EQ(changes.back().button, 0);
    EXPECT_EQ(changes.back().state, 1);
  }
  const std::size_t before = changes.size();
  ASSERT_EQ(emulator_->Control("button 1 0").rfind("ok", 0), 0u);
  ASSERT_TRUE(wait(before + 1));
  std::lock_guard<std::mutex> lock(mutex);
  EXPECT_EQ(changes.back().state, 0);
}

TEST_F(EndToEnd, ReloadWithoutDroppingClients) {
  Collector& corrected = corrected_;
  auto c = Client("Tracker0", /*tcp=*/false, corrected);
  ASSERT_TRUE(corrected.WaitMore(20));
  // Half the correction: the corrected pose moves half-way back towards the reported one.
  WriteCalibration(dir_ / "calib.json", 0.5);
  EXPECT_EQ(app_->ReloadCalibrations(), 1);
  ASSERT_TRUE(corrected.WaitMore(20));
  const Eigen::Vector3d expected = truth_[0].translation + 0.5 * kDistortionOffset;
  EXPECT_LT((corrected.Pose(0)->translation - expected).norm(), kPositionTolerance);
  // A broken file is rejected; the half correction stays.
  std::ofstream(dir_ / "calib.json") << "{ not json";
  EXPECT_EQ(app_->ReloadCalibrations(), 0);
  ASSERT_TRUE(corrected.WaitMore(20));
  EXPECT_LT((corrected.Pose(0)->translation - expected).norm(), kPositionTolerance);
  EXPECT_EQ(c->connections(), 1u);
}

TEST_F(EndToEnd, EveryEmulatorFaultSurvived) {
  Collector& corrected = corrected_;
  auto c = Client("Tracker0", /*tcp=*/true, corrected);
  ASSERT_TRUE(corrected.WaitMore(20));
  for (const std::string fault : {"fault garbage 200", "fault truncate", "fault stall 3",
                                  "fault powercycle 1", "fault disconnect 1"}) {
    SCOPED_TRACE(fault);
    const std::string reply = emulator_->Control(fault);
    ASSERT_EQ(reply.rfind("ok", 0), 0u) << reply;
    if (fault == "fault stall 3") {
      // While the device is silent (and then reset), a new client is served at once. Checked by
      // what happened meanwhile, not by a stopwatch: the answer must come before the device's
      // reports resume (records already in flight at the fault are a few; 10 are 80 ms of stream).
      const int reports_at_fault = corrected.Count();
      auto late = Client("Tracker0", /*tcp=*/false, late_);
      const auto end = Clock::now() + std::chrono::seconds(20);  // generous for a loaded host
      while (Clock::now() < end && !late->pong_received()) {
        std::this_thread::sleep_for(std::chrono::milliseconds(5));
      }
      EXPECT_TRUE(late->pong_received());
      EXPECT_LT(corrected.Count() - reports_at_fault, 10) << "served only after the device resumed";
    }
    // Reports resume and are still corrected.
    ASSERT_TRUE(corrected.WaitMore(40, 30));
    EXPECT_TRUE(testing::PosesNear(truth_[0], *corrected.Pose(0), kPositionTolerance, kAngleTolerance));
  }
  EXPECT_EQ(c->connections(), 1u);
  EXPECT_EQ(app_->server().stats().clients, 2);
}

}  // namespace
}  // namespace trackcal::vrpn
