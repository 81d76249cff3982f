#include "vrpn_server/server/devices.h"

#include <gtest/gtest.h>

#include <chrono>
#include <fstream>
#include <functional>
#include <limits>
#include <mutex>
#include <thread>

#include "core/capture.h"
#include "core/physical_correction.h"
#include "tests/test_utils.h"
#include "vrpn_server/client/tracker_client.h"

namespace trackcal::vrpn {
namespace {

using Clock = std::chrono::steady_clock;

// A known rigid correction: corrected = offset * reported.
class OffsetCorrector : public PoseCorrector {
 public:
  explicit OffsetCorrector(Rigid3d offset) : offset_(offset) {}
  Rigid3d Correct(const Rigid3d& reported) const override { return offset_ * reported; }
  std::string Describe() const override { return "offset"; }

 private:
  Rigid3d offset_;
};

// Flags poses with x > 0.5 m as extrapolated (outside a calibrated volume) and leaves them as they
// are.
class BoxCorrector : public PoseCorrector {
 public:
  Rigid3d Correct(const Rigid3d& reported) const override { return reported; }
  CorrectionResult CorrectWithFlag(const Rigid3d& reported) const override {
    return {reported, reported.translation.x() > 0.5};
  }
  std::string Describe() const override { return "box"; }
};

// Fan-outs recorded by the server until at least `n` (the timing of a fan-out is recorded just
// after its last send, so a client may see the reports first), plus any that follow within 0.1 s.
std::size_t CountFanouts(VrpnServer& server, std::size_t n) {
  std::size_t count = 0;
  const auto end = Clock::now() + std::chrono::seconds(10);
  while (count < n && Clock::now() < end) {
    count += server.TakeFanoutMicros().size();
    std::this_thread::sleep_for(std::chrono::milliseconds(5));
  }
  std::this_thread::sleep_for(std::chrono::milliseconds(100));
  return count + server.TakeFanoutMicros().size();
}

bool PollUntil(const std::vector<VrpnTrackerClient*>& clients, const std::function<bool()>& pred,
               double timeout_s = 10.0) {
  const auto end = Clock::now() + std::chrono::duration<double>(timeout_s);
  while (Clock::now() < end && !pred()) {
    for (auto* c : clients) c->Poll(0.002);
  }
  return pred();
}

struct Fixture {
  std::shared_ptr<ServerCatalog> catalog = std::make_shared<ServerCatalog>();
  std::unique_ptr<VrpnServer> server;
  int corrected = 0, raw = 0;
  explicit Fixture(int realtime_priority = 0) {
    TrackerSpec spec;
    spec.name = "Tracker0";
    spec.num_sensors = 2;
    corrected = catalog->AddTracker(spec);
    spec.name = "Tracker0_raw";
    raw = catalog->AddTracker(spec);
    ServerOptions o;
    o.bind_address = "127.0.0.1";
    o.port = 0;
    o.realtime_priority = realtime_priority;
    server = std::make_unique<VrpnServer>(catalog, o, [](const std::string&) {});
    server->Start();
  }
  std::string Name(const std::string& device) const {
    return device + "@tcp://127.0.0.1:" + std::to_string(server->port());
  }
};

TEST(WithUnitRotation, Nominal) {
  // A Fastrak record's quaternion, |q| = 1.0003 after its 4 printed decimals.
  const Rigid3d reported(QuaternionFromXyzw(0.1, -0.2, 0.3, 0.9286),
                         Eigen::Vector3d(0.1, 0.2, 0.3));
  ASSERT_NE(reported.rotation.norm(), 1.0);
  const Rigid3d unit = WithUnitRotation(reported);
  // 1e-15: one division by the norm, a few ulps.
  EXPECT_NEAR(unit.rotation.norm(), 1.0, 1e-15);
  EXPECT_NEAR(AngularDistance(unit.rotation, reported.rotation.normalized()), 0.0, 1e-15);
  EXPECT_EQ(unit.translation, reported.translation);
  EXPECT_TRUE(IsFinite(unit));
}

TEST(WithUnitRotation, LeavesWhatIsNoRotationForIsFiniteToRefuse) {
  const double nan = std::numeric_limits<double>::quiet_NaN();
  const Rigid3d zero(QuaternionFromXyzw(0.0, 0.0, 0.0, 0.0), Eigen::Vector3d(0.1, 0.2, 0.3));
  EXPECT_EQ(WithUnitRotation(zero).rotation.coeffs(), zero.rotation.coeffs());
  EXPECT_FALSE(IsFinite(WithUnitRotation(zero)));
  const Rigid3d nan_q(QuaternionFromXyzw(nan, 0.0, 0.0, 1.0), Eigen::Vector3d(0.1, 0.2, 0.3));
  EXPECT_FALSE(IsFinite(WithUnitRotation(nan_q)));
  const Rigid3d nan_p(Eigen::Quaterniond::Identity(), Eigen::Vector3d(nan, 0.2, 0.3));
  EXPECT_FALSE(IsFinite(WithUnitRotation(nan_p)));
}

TEST(TrackerDevice, ServesCorrectedAndRawNames) {
  Fixture f;
  TrackerDevice device(f.server.get(), f.corrected, f.raw);
  const Rigid3d offset(testing::RandomRotation(testing::TestRng()),
                       Eigen::Vector3d(0.01, -0.02, 0.03));
  device.SetCorrector(std::make_shared<OffsetCorrector>(offset));
  VrpnTrackerClient corrected_client(f.Name("Tracker0"));
  VrpnTrackerClient raw_client(f.Name("Tracker0_raw"));
  std::vector<TrackerReport> corrected, raw;
  corrected_client.SetPoseCallback([&](const TrackerReport& r) { corrected.push_back(r); });
  raw_client.SetPoseCallback([&](const TrackerReport& r) { raw.push_back(r); });
  ASSERT_TRUE(PollUntil({&corrected_client, &raw_client}, [&] {
    return corrected_client.pong_received() && raw_client.pong_received();
  }));
  const Rigid3d reported(testing::RandomRotation(testing::TestRng()),
                         Eigen::Vector3d(0.3, 0.1, -0.2));
  device.OnReport(1, reported, Timestamp{100, 5});
  ASSERT_TRUE(PollUntil({&corrected_client, &raw_client},
                        [&] { return corrected.size() == 1 && raw.size() == 1; }));
  const Rigid3d expected = offset * reported;
  // Only the wire's bit-exact doubles are between the correction and the client.
  EXPECT_EQ(corrected[0].transmitter_from_receiver.translation, expected.translation);
  EXPECT_EQ(raw[0].transmitter_from_receiver.translation, reported.translation);
  EXPECT_EQ(raw[0].sensor, 1);
  EXPECT_EQ(corrected[0].time, (Timestamp{100, 5}));

  // Swapping the correction (calibration reload) keeps the clients and applies to the next report.
  device.SetCorrector(nullptr);
  device.OnReport(0, reported, Timestamp{101, 0});
  ASSERT_TRUE(PollUntil({&corrected_client}, [&] { return corrected.size() == 2; }));
  EXPECT_EQ(corrected[1].transmitter_from_receiver.translation, reported.translation);
  EXPECT_EQ(corrected_client.connections(), 1u);
}

TEST(TrackerDevice, ReportsReadTogetherGoOutInOneFanout) {
  // With a real-time network thread (runs normally, with a logged warning, without CAP_SYS_NICE)
  // every fan-out is made by that thread instead of the publishing one: same result.
  for (int realtime_priority : {0, 5}) {
    SCOPED_TRACE(realtime_priority);
    Fixture f(realtime_priority);
    TrackerDevice device(f.server.get(), f.corrected, f.raw);
    VrpnTrackerClient client(f.Name("Tracker0"));
    std::vector<TrackerReport> got;
    client.SetPoseCallback([&](const TrackerReport& r) { got.push_back(r); });
    ASSERT_TRUE(PollUntil({&client}, [&] { return client.pong_received(); }));
    f.server->TakeFanoutMicros();
    std::vector<SensorReport> batch;
    for (int s = 0; s < 4; ++s) {
      batch.push_back(
          SensorReport{s, Rigid3d(Eigen::Quaterniond::Identity(), Eigen::Vector3d(0.1 * s, 0, 0)),
                       Timestamp{200, static_cast<std::uint32_t>(s)}});
    }
    device.OnReports(batch);
    ASSERT_TRUE(PollUntil({&client}, [&] { return got.size() == 4; }));
    // Raw and corrected names of 4 stations: 8 messages, one fan-out (one send per client).
    EXPECT_EQ(CountFanouts(*f.server, 1), 1u);
    EXPECT_EQ(f.server->stats().reports_published, 8u);
    for (int s = 0; s < 4; ++s) {
      EXPECT_EQ(got[s].sensor, s);
      EXPECT_EQ(got[s].time, (Timestamp{200, static_cast<std::uint32_t>(s)}));
      EXPECT_EQ(got[s].transmitter_from_receiver.translation.x(), 0.1 * s);
    }
    // One at a time, the same reports take one fan-out each when the publishing thread sends
    // them itself (the network thread is idle: the client sends nothing after its pong). A
    // real-time network thread may find several queued when it wakes and send them together.
    for (const SensorReport& r : batch)
      device.OnReport(r.sensor, r.transmitter_from_receiver, r.time);
    ASSERT_TRUE(PollUntil({&client}, [&] { return got.size() == 8; }));
    const std::size_t fanouts = CountFanouts(*f.server, realtime_priority == 0 ? 4 : 1);
    if (realtime_priority == 0) {
      EXPECT_EQ(fanouts, 4u);
    } else {
      EXPECT_GE(fanouts, 1u);
      EXPECT_LE(fanouts, 4u);
    }
    EXPECT_THROW(
        f.server->PublishPoses(std::vector<PoseUpdate>{PoseUpdate{7, 0, Rigid3d(), Timestamp{}}}),
        std::invalid_argument);
  }
}

TEST(TrackerDevice, CountsExtrapolatedPosesAndTellsClientsAtMostOncePerSecond) {
  Fixture f;
  TrackerDevice device(f.server.get(), f.corrected, f.raw);
  device.SetCorrector(std::make_shared<BoxCorrector>());
  std::vector<std::string> log;
  std::mutex log_mutex;
  device.SetLog([&](const std::string& line) {
    std::lock_guard<std::mutex> lock(log_mutex);
    log.push_back(line);
  });
  VrpnTrackerClient client(f.Name("Tracker0"));
  VrpnTrackerClient raw_client(f.Name("Tracker0_raw"));
  std::vector<std::string> texts, raw_texts;
  std::size_t poses = 0;
  client.SetPoseCallback([&](const TrackerReport&) { ++poses; });
  client.SetMessageCallback([&](const ReceivedMessage& m) {
    if (m.type == kTextType) texts.push_back(DecodeText(m.payload)->text);
  });
  raw_client.SetMessageCallback([&](const ReceivedMessage& m) {
    if (m.type == kTextType) raw_texts.push_back(DecodeText(m.payload)->text);
  });
  ASSERT_TRUE(PollUntil({&client, &raw_client},
                        [&] { return client.pong_received() && raw_client.pong_received(); }));
  const Rigid3d inside(Eigen::Quaterniond::Identity(), Eigen::Vector3d(0.2, 0, 0));
  const Rigid3d outside(Eigen::Quaterniond::Identity(), Eigen::Vector3d(0.7, 0, 0));
  // 3 outside, 2 inside: the first extrapolated pose is told at once (count 1), the rest of this
  // burst is held because the next notice may only come a second later.
  const auto t0 = std::chrono::steady_clock::now();
  device.OnReport(0, outside, Timestamp{1, 0});
  device.OnReport(0, inside, Timestamp{1, 1});
  device.OnReport(1, outside, Timestamp{1, 2});
  device.OnReport(1, outside, Timestamp{1, 3});
  device.OnReport(2, inside, Timestamp{1, 4});
  ASSERT_TRUE(PollUntil({&client, &raw_client}, [&] { return poses == 5 && !texts.empty(); }));
  EXPECT_EQ(device.extrapolated_poses(), 3u);
  ASSERT_EQ(texts.size(), 1u);
  EXPECT_NE(texts[0].find("1 corrected pose(s) extrapolated"), std::string::npos) << texts[0];
  // After the interval, the next report (even one inside) releases the held count of 2.
  std::this_thread::sleep_until(t0 + TrackerDevice::kExtrapolationNoticeInterval +
                                std::chrono::milliseconds(50));
  device.OnReport(2, inside, Timestamp{2, 0});
  ASSERT_TRUE(PollUntil({&client, &raw_client}, [&] { return texts.size() == 2; }));
  EXPECT_NE(texts[1].find("2 corrected pose(s) extrapolated"), std::string::npos) << texts[1];
  EXPECT_NE(texts[1].find("3 in total"), std::string::npos) << texts[1];
  EXPECT_EQ(device.extrapolated_poses(), 3u);
  EXPECT_EQ(device.corrected_poses(), 6u);
  // Raw poses are not corrected, so their clients are not told.
  EXPECT_TRUE(raw_texts.empty());
  std::lock_guard<std::mutex> lock(log_mutex);
  EXPECT_EQ(log.size(), 2u);
}

// The physical model's inverse as the server applies it (CalibrationCorrector passes the status).
class PhysicalCorrector : public PoseCorrector {
 public:
  PhysicalCorrector() : correction_(Field(), Eigen::Matrix3d::Identity()) {}
  static FieldModel Field() {
    FieldModel field;
    field.objects.push_back({"toolbox", Eigen::Vector3d(0.6, 0.95, -0.5), 0.002});
    return field;
  }
  Rigid3d Correct(const Rigid3d& reported) const override { return correction_.Apply(reported).pose; }
  CorrectionResult CorrectWithFlag(const Rigid3d& reported) const override {
    const CorrectedPose c = correction_.Apply(reported);
    return {c.pose, c.extrapolated, c.status};
  }
  std::string Describe() const override { return "physical"; }

 private:
  PhysicalCorrection correction_;
};

TEST(TrackerDevice, CountsUnresolvedPosesOfAPhysicalInverse) {
  Fixture f;
  TrackerDevice device(f.server.get(), f.corrected, std::nullopt);
  device.SetCorrector(std::make_shared<PhysicalCorrector>());
  VrpnTrackerClient client(f.Name("Tracker0"));
  std::vector<std::string> texts;
  std::vector<TrackerReport> poses;
  client.SetPoseCallback([&](const TrackerReport& r) { poses.push_back(r); });
  client.SetMessageCallback([&](const ReceivedMessage& m) {
    if (m.type == kTextType) texts.push_back(DecodeText(m.payload)->text);
  });
  ASSERT_TRUE(PollUntil({&client}, [&] { return client.pong_received(); }));
  // Far from the object: converged. On the object: no true pose (a receiver cannot be inside it).
  device.OnReport(0, Rigid3d(Eigen::Quaterniond::Identity(), Eigen::Vector3d(-0.5, -0.4, -0.6)),
                  Timestamp{1, 0});
  device.OnReport(0, Rigid3d(Eigen::Quaterniond::Identity(), Eigen::Vector3d(0.6, 0.95, -0.5)),
                  Timestamp{1, 1});
  ASSERT_TRUE(PollUntil({&client}, [&] { return poses.size() == 2 && !texts.empty(); }));
  EXPECT_EQ(device.unresolved_poses(), 1u);
  EXPECT_EQ(device.extrapolated_poses(), 0u);
  EXPECT_NE(texts[0].find("1 corrected pose(s) unresolved"), std::string::npos) << texts[0];
  // The unresolved pose is still served, finite.
  for (const TrackerReport& r : poses) EXPECT_TRUE(r.transmitter_from_receiver.translation.allFinite());
}

// A Fastrak record is accepted with |q| off by up to 1e-3 (kMaxQuaternionNormError), and a
// pass-through source sends what it got; clients use the wire's quaternion as a rotation without
// normalising it, and the correction q_e * q kept the error. Both names serve unit quaternions,
// and the correction is fed one.
TEST(TrackerDevice, ServesUnitQuaternionsAndCorrectsAUnitOne) {
  Fixture f;
  TrackerDevice device(f.server.get(), f.corrected, f.raw);
  const Rigid3d offset(testing::RandomRotation(testing::TestRng()),
                       Eigen::Vector3d(0.01, -0.02, 0.03));
  device.SetCorrector(std::make_shared<OffsetCorrector>(offset));
  VrpnTrackerClient corrected_client(f.Name("Tracker0"));
  VrpnTrackerClient raw_client(f.Name("Tracker0_raw"));
  std::vector<TrackerReport> corrected, raw;
  corrected_client.SetPoseCallback([&](const TrackerReport& r) { corrected.push_back(r); });
  raw_client.SetPoseCallback([&](const TrackerReport& r) { raw.push_back(r); });
  ASSERT_TRUE(PollUntil({&corrected_client, &raw_client}, [&] {
    return corrected_client.pong_received() && raw_client.pong_received();
  }));
  const Eigen::Quaterniond unit = testing::RandomRotation(testing::TestRng());
  for (const double scale : {1.0 + 9e-4, 1.0 - 9e-4, 3.0}) {
    device.OnReport(
        0, Rigid3d(Eigen::Quaterniond(unit.coeffs() * scale), Eigen::Vector3d(0.3, 0.1, -0.2)),
        Timestamp{100, 0});
  }
  ASSERT_TRUE(PollUntil({&corrected_client, &raw_client},
                        [&] { return corrected.size() == 3 && raw.size() == 3; }));
  for (std::size_t i = 0; i < 3; ++i) {
    SCOPED_TRACE(i);
    // Tolerance: a few ulps of the division by the norm and of one quaternion product.
    const double kTol = 1e-14;
    EXPECT_NEAR(raw[i].transmitter_from_receiver.rotation.norm(), 1.0, kTol);
    EXPECT_NEAR(corrected[i].transmitter_from_receiver.rotation.norm(), 1.0, kTol);
    EXPECT_NEAR(AngularDistance(raw[i].transmitter_from_receiver.rotation, unit), 0.0, 1e-7);
    EXPECT_NEAR(
        AngularDistance(corrected[i].transmitter_from_receiver.rotation, offset.rotation * unit),
        0.0, 1e-7);  // 1e-7 rad: acos near 1 loses half the digits of 1e-14
  }
}

// Gives a pose that is not finite for reports with x > 0.5 m (a correction evaluated where its
// math breaks down), the report itself elsewhere.
class NanCorrector : public PoseCorrector {
 public:
  Rigid3d Correct(const Rigid3d& reported) const override {
    if (reported.translation.x() <= 0.5) return reported;
    Rigid3d bad = reported;
    bad.translation.y() = std::numeric_limits<double>::quiet_NaN();
    return bad;
  }
  std::string Describe() const override { return "nan.json"; }
};

// A corrected pose that is not finite went to clients as it was (a Unity object moved to NaN and
// vanished). It is not served: the first one is told to the corrected name's clients and the log,
// the others are only counted; the raw name still serves the report.
TEST(TrackerDevice, ANonFiniteCorrectedPoseIsNotServedToldOnceAndCounted) {
  Fixture f;
  TrackerDevice device(f.server.get(), f.corrected, f.raw);
  device.SetCorrector(std::make_shared<NanCorrector>());
  std::vector<std::string> log;
  std::mutex log_mutex;
  device.SetLog([&](const std::string& line) {
    std::lock_guard<std::mutex> lock(log_mutex);
    log.push_back(line);
  });
  VrpnTrackerClient client(f.Name("Tracker0"));
  VrpnTrackerClient raw_client(f.Name("Tracker0_raw"));
  std::vector<TrackerReport> poses, raw_poses;
  std::vector<std::string> texts;
  client.SetPoseCallback([&](const TrackerReport& r) { poses.push_back(r); });
  raw_client.SetPoseCallback([&](const TrackerReport& r) { raw_poses.push_back(r); });
  client.SetMessageCallback([&](const ReceivedMessage& m) {
    if (m.type == kTextType) texts.push_back(DecodeText(m.payload)->text);
  });
  ASSERT_TRUE(PollUntil({&client, &raw_client},
                        [&] { return client.pong_received() && raw_client.pong_received(); }));
  const Rigid3d good(Eigen::Quaterniond::Identity(), Eigen::Vector3d(0.2, 0, 0));
  const Rigid3d bad(Eigen::Quaterniond::Identity(), Eigen::Vector3d(0.7, 0, 0));
  for (int i = 0; i < 50; ++i) device.OnReport(1, bad, Timestamp{1, static_cast<std::uint32_t>(i)});
  device.OnReport(1, good, Timestamp{2, 0});
  ASSERT_TRUE(PollUntil({&client, &raw_client}, [&] {
    return poses.size() == 1 && raw_poses.size() == 51 && !texts.empty();
  }));
  for (auto* c : {&client, &raw_client}) c->Poll(0.1);  // anything else sent would arrive now
  ASSERT_EQ(poses.size(), 1u);
  EXPECT_EQ(poses[0].time, (Timestamp{2, 0}));
  EXPECT_EQ(device.non_finite_poses(), 50u);
  EXPECT_EQ(device.corrected_poses(), 1u);
  ASSERT_EQ(texts.size(), 1u);
  EXPECT_EQ(texts[0].rfind("sensor 1: the correction nan.json gave ", 0), 0u) << texts[0];
  EXPECT_NE(texts[0].find("not finite: such corrected poses are not served"), std::string::npos)
      << texts[0];
  {
    std::lock_guard<std::mutex> lock(log_mutex);
    EXPECT_EQ(log, texts);
  }
  // A new correction's first one is told again.
  device.SetCorrector(std::make_shared<NanCorrector>());
  device.OnReport(0, bad, Timestamp{3, 0});
  ASSERT_TRUE(PollUntil({&client}, [&] { return texts.size() == 2; }));
  EXPECT_EQ(device.non_finite_poses(), 51u);
  EXPECT_EQ(poses.size(), 1u);
}

// A pass-through source forwards what its server sent: a NaN (or a zero quaternion) went to the
// raw name's clients as it was, and through a correction (BoxCorrector leaves it as it is; a
// clamping one can make it finite and wrong) to the corrected name's. Neither name serves it; both
// are told once, the log once, the rest counted.
TEST(TrackerDevice, AReportThatIsNotAPoseIsServedUnderNeitherName) {
  Fixture f;
  TrackerDevice device(f.server.get(), f.corrected, f.raw);
  device.SetCorrector(std::make_shared<BoxCorrector>());
  std::vector<std::string> log;
  std::mutex log_mutex;
  device.SetLog([&](const std::string& line) {
    std::lock_guard<std::mutex> lock(log_mutex);
    log.push_back(line);
  });
  VrpnTrackerClient client(f.Name("Tracker0"));
  VrpnTrackerClient raw_client(f.Name("Tracker0_raw"));
  std::vector<TrackerReport> poses, raw_poses;
  std::vector<std::string> texts, raw_texts;
  client.SetPoseCallback([&](const TrackerReport& r) { poses.push_back(r); });
  raw_client.SetPoseCallback([&](const TrackerReport& r) { raw_poses.push_back(r); });
  client.SetMessageCallback([&](const ReceivedMessage& m) {
    if (m.type == kTextType) texts.push_back(DecodeText(m.payload)->text);
  });
  raw_client.SetMessageCallback([&](const ReceivedMessage& m) {
    if (m.type == kTextType) raw_texts.push_back(DecodeText(m.payload)->text);
  });
  ASSERT_TRUE(PollUntil({&client, &raw_client},
                        [&] { return client.pong_received() && raw_client.pong_received(); }));
  const double nan = std::numeric_limits<double>::quiet_NaN();
  std::vector<SensorReport> batch = {
      {0, Rigid3d(Eigen::Quaterniond::Identity(), Eigen::Vector3d(nan, 0, 0)), Timestamp{1, 0}},
      {0, Rigid3d(Eigen::Quaterniond(0, 0, 0, 0), Eigen::Vector3d(0.1, 0, 0)), Timestamp{1, 1}},
      {1, Rigid3d(Eigen::Quaterniond(nan, 0, 0, 1), Eigen::Vector3d(0.1, 0, 0)), Timestamp{1, 2}},
      {1, Rigid3d(Eigen::Quaterniond::Identity(), Eigen::Vector3d(0.2, 0, 0)), Timestamp{1, 3}},
  };
  device.OnReports(batch);
  device.OnReports(std::span<const SensorReport>(batch.data(), 1));
  ASSERT_TRUE(PollUntil({&client, &raw_client}, [&] {
    return poses.size() == 1 && raw_poses.size() == 1 && !texts.empty() && !raw_texts.empty();
  }));
  for (auto* c : {&client, &raw_client}) c->Poll(0.1);  // anything else sent would arrive now
  ASSERT_EQ(poses.size(), 1u);
  ASSERT_EQ(raw_poses.size(), 1u);
  EXPECT_EQ(poses[0].time, (Timestamp{1, 3}));
  EXPECT_EQ(raw_poses[0].time, (Timestamp{1, 3}));
  EXPECT_EQ(device.bad_reports(), 4u);
  EXPECT_EQ(device.corrected_poses(), 1u);
  ASSERT_EQ(texts.size(), 1u);
  EXPECT_EQ(raw_texts, texts);
  EXPECT_EQ(texts[0].rfind("sensor 0: the source reported ", 0), 0u) << texts[0];
  EXPECT_NE(texts[0].find("which is not a pose"), std::string::npos) << texts[0];
  std::lock_guard<std::mutex> lock(log_mutex);
  EXPECT_EQ(log, texts);
}

TEST(NullTracker, ReportsEverySensorAtRate) {
  Fixture f;
  TrackerDevice device(f.server.get(), f.corrected, std::nullopt);
  NullTracker null([&](int s, const Rigid3d& p, Timestamp t) { device.OnReport(s, p, t); }, 2,
                   200.0);
  VrpnTrackerClient client(f.Name("Tracker0"));
  std::vector<TrackerReport> got;
  client.SetPoseCallback([&](const TrackerReport& r) { got.push_back(r); });
  ASSERT_TRUE(PollUntil({&client}, [&] { return client.pong_received(); }));
  null.Start();
  ASSERT_TRUE(PollUntil({&client}, [&] { return got.size() >= 20; }));
  null.Stop();
  int sensor1 = 0;
  for (const auto& r : got) {
    sensor1 += r.sensor == 1;
    EXPECT_TRUE(testing::PosesNear(Rigid3d(), r.transmitter_from_receiver, 0.0, 0.0));
  }
  EXPECT_GE(sensor1, 9);
}

TEST(StreamRecorder, WritesStreamFormatAndNeverOverwrites) {
  const auto dir = testing::MakeTempDir("recorder");
  {
    StreamRecorder rec(dir, "Tracker0");
    rec.Write(0, Rigid3d(QuaternionFromXyzw(0.0, 0.0, 1.0, 0.0), Eigen::Vector3d(0.1, 0.2, 0.3)),
              Timestamp{12, 34});
    EXPECT_FALSE(std::filesystem::exists(rec.path()));  // only the .partial exists while recording
  }
  std::ifstream in(dir / "Tracker0_tracker_stream.csv");
  std::string header, row;
  std::getline(in, header);
  std::getline(in, row);
  EXPECT_EQ(header, "time,sensor,x,y,z,qw,qx,qy,qz");
  EXPECT_EQ(row, "12.000034,1,0.10000000000000001,0.20000000000000001,0.29999999999999999,0,0,0,1");
  // The capture reader of core reads it back (sensor = station number 1).
  const TrackerStream stream = ReadTrackerStream(dir / "Tracker0_tracker_stream.csv");
  ASSERT_EQ(stream.records.size(), 1u);
  EXPECT_EQ(stream.records[0].sensor, 1);
  EXPECT_DOUBLE_EQ(stream.records[0].time, 12.000034);
  EXPECT_EQ(stream.records[0].transmitter_from_receiver.translation.z(), 0.3);
  EXPECT_THROW(StreamRecorder(dir, "Tracker0"), std::invalid_argument);
}

// A pass-through source forwards its upstream server's header time as it came: VRPN sends tv_usec
// as a signed 32-bit field, and a server may send 1,000,000 or more (an unnormalised timeval) or a
// negative value. Written with setw(6), 12 s + 1,500,000 us became "12.1500000" (12.15 s) and
// -250,000 us "12.4294717296"; the recording holds the time the header means.
TEST(StreamRecorder, WritesAnUnnormalisedHeaderTimeAsTheTimeItMeans) {
  const auto dir = testing::MakeTempDir("recorder_usec");
  {
    StreamRecorder rec(dir, "Tracker0");
    rec.Write(0, Rigid3d(), Timestamp{12, 1'500'000});
    rec.Write(1, Rigid3d(), Timestamp{12, static_cast<std::uint32_t>(-250'000)});
    rec.Write(2, Rigid3d(), Timestamp{0, static_cast<std::uint32_t>(-250'000)});
    rec.Write(3, Rigid3d(), Timestamp{4'294'967'295u, 999'999});
  }
  std::ifstream in(dir / "Tracker0_tracker_stream.csv");
  std::string line;
  std::vector<std::string> times;
  std::getline(in, line);  // header
  while (std::getline(in, line)) times.push_back(line.substr(0, line.find(',')));
  EXPECT_EQ(times,
            (std::vector<std::string>{"13.500000", "11.750000", "-0.250000", "4294967295.999999"}));
  const TrackerStream stream = ReadTrackerStream(dir / "Tracker0_tracker_stream.csv");
  ASSERT_EQ(stream.records.size(), 4u);
  EXPECT_EQ(stream.records[0].time, 13.5);
  EXPECT_EQ(stream.records[1].time, 11.75);
  EXPECT_EQ(stream.records[2].time, -0.25);
}

// One sensor's time twice (a source clock that did not tick, or stepped back onto a time it gave,
// a report sent twice) made a recording that saved and then failed to load ("time 1 of sensor 1
// repeats line 2"). A report not after its sensor's latest recorded time is left out and counted
// (logged once, and the count when the recording closes), so the recording loads; memory stays one
// time per sensor however long the server records.
TEST(StreamRecorder, LeavesOutAReportNotAfterItsSensorsLatestTimeAndCountsIt) {
  const auto dir = testing::MakeTempDir("recorder_repeat");
  const Rigid3d moved(Eigen::Quaterniond::Identity(), Eigen::Vector3d(0.5, 0.0, 0.0));
  std::uint64_t left_out = 0;
  {
    StreamRecorder rec(dir, "Tracker0");
    rec.Write(0, Rigid3d(), Timestamp{1, 0});
    rec.Write(1, Rigid3d(), Timestamp{1, 0});    // another sensor at that time: kept
    rec.Write(0, moved, Timestamp{1, 0});        // repeats sensor 1's time
    rec.Write(0, moved, Timestamp{0, 500'000});  // a clock stepped back
    rec.Write(0, Rigid3d(), Timestamp{1, 8'333});
    left_out = rec.left_out();
  }
  EXPECT_EQ(left_out, 2u);
  const TrackerStream stream = ReadTrackerStream(dir / "Tracker0_tracker_stream.csv");
  ASSERT_EQ(stream.records.size(), 3u);
  EXPECT_EQ(stream.records[2].time, 1.008333);
  for (const auto& r : stream.records) EXPECT_EQ(r.transmitter_from_receiver.translation.x(), 0.0);
}

std::string RecorderError(const std::filesystem::path& dir) {
  try {
    StreamRecorder rec(dir, "Tracker0");
  } catch (const std::invalid_argument& e) {
    return e.what();
  }
  return "no error";
}

// --record DIR makes DIR like mkdir (one level), as `trackcal record -o` makes its own folder; the
// raw and corrected recorders of one tracker share it, and a recording already in it is kept.
// (Before: a missing DIR stopped the start with "not a directory".)
TEST(StreamRecorder, MakesItsFolderOneLevelDeep) {
  const auto base = testing::MakeTempDir("recorder_mkdir");
  const auto dir = base / "session1";
  {
    StreamRecorder raw(dir, "Tracker0_raw");
    StreamRecorder corrected(dir, "Tracker0_corrected");
    raw.Write(0, Rigid3d(), Timestamp{1, 0});
  }
  EXPECT_TRUE(std::filesystem::is_directory(dir));
  EXPECT_EQ(ReadTrackerStream(dir / "Tracker0_raw_tracker_stream.csv").records.size(), 1u);
  EXPECT_TRUE(std::filesystem::exists(dir / "Tracker0_corrected_tracker_stream.csv"));
  // A second start into the same folder: the earlier recording is not overwritten.
  EXPECT_THROW(StreamRecorder(dir, "Tracker0_raw"), std::invalid_argument);
  EXPECT_EQ(ReadTrackerStream(dir / "Tracker0_raw_tracker_stream.csv").records.size(), 1u);

  // Missing parent: "does not exist", and nothing is made.
  const std::string deep = RecorderError(base / "nowhere" / "session2");
  EXPECT_NE(deep.find("does not exist"), std::string::npos) << deep;
  EXPECT_EQ(deep.find("not a directory"), std::string::npos) << deep;
  EXPECT_FALSE(std::filesystem::exists(base / "nowhere"));
  // "not a directory" only for something that exists and is not a folder.
  std::ofstream(base / "afile") << "x\n";
  const std::string file = RecorderError(base / "afile");
  EXPECT_NE(file.find("not a directory"), std::string::npos) << file;
  EXPECT_EQ(file.find("does not exist"), std::string::npos) << file;
}

// A file that appears under the final name while recording (another server, a user's copy) is
// not replaced: the recording stays in the .partial file. (Before: std::filesystem::rename
// replaced it.)
TEST(StreamRecorder, KeepsTheRecordingBesideAFileThatAppearedWhileRecording) {
  const auto dir = testing::MakeTempDir("recorder_race");
  const auto final_path = dir / "Tracker0_tracker_stream.csv";
  {
    StreamRecorder rec(dir, "Tracker0");
    rec.Write(0, Rigid3d(), Timestamp{1, 0});
    std::ofstream(final_path) << "someone else's file\n";
  }
  std::ifstream kept(final_path);
  std::string line;
  std::getline(kept, line);
  EXPECT_EQ(line, "someone else's file");
  auto partial = final_path;
  partial += ".partial";
  ASSERT_TRUE(std::filesystem::exists(partial));
  EXPECT_EQ(ReadTrackerStream(partial).records.size(), 1u);
}

}  // namespace
}  // namespace trackcal::vrpn
