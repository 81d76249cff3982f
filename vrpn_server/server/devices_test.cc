#include "vrpn_server/server/devices.h"

#include <gtest/gtest.h>

#include <chrono>
#include <fstream>
#include <functional>

#include "core/capture.h"
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
  Fixture() {
    TrackerSpec spec;
    spec.name = "Tracker0";
    spec.num_sensors = 2;
    corrected = catalog->AddTracker(spec);
    spec.name = "Tracker0_raw";
    raw = catalog->AddTracker(spec);
    ServerOptions o;
    o.bind_address = "127.0.0.1";
    o.port = 0;
    server = std::make_unique<VrpnServer>(catalog, o, [](const std::string&) {});
    server->Start();
  }
  std::string Name(const std::string& device) const {
    return device + "@tcp://127.0.0.1:" + std::to_string(server->port());
  }
};

TEST(TrackerDevice, ServesCorrectedAndRawNames) {
  Fixture f;
  TrackerDevice device(f.server.get(), f.corrected, f.raw);
  const Rigid3d offset(testing::RandomRotation(testing::TestRng()), Eigen::Vector3d(0.01, -0.02, 0.03));
  device.SetCorrector(std::make_shared<OffsetCorrector>(offset));
  VrpnTrackerClient corrected_client(f.Name("Tracker0"));
  VrpnTrackerClient raw_client(f.Name("Tracker0_raw"));
  std::vector<TrackerReport> corrected, raw;
  corrected_client.SetPoseCallback([&](const TrackerReport& r) { corrected.push_back(r); });
  raw_client.SetPoseCallback([&](const TrackerReport& r) { raw.push_back(r); });
  ASSERT_TRUE(PollUntil({&corrected_client, &raw_client}, [&] {
    return corrected_client.pong_received() && raw_client.pong_received();
  }));
  const Rigid3d reported(testing::RandomRotation(testing::TestRng()), Eigen::Vector3d(0.3, 0.1, -0.2));
  device.OnReport(1, reported, Timestamp{100, 5});
  ASSERT_TRUE(PollUntil({&corrected_client, &raw_client}, [&] {
    return corrected.size() == 1 && raw.size() == 1;
  }));
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

TEST(NullTracker, ReportsEverySensorAtRate) {
  Fixture f;
  TrackerDevice device(f.server.get(), f.corrected, std::nullopt);
  NullTracker null([&](int s, const Rigid3d& p, Timestamp t) { device.OnReport(s, p, t); }, 2, 200.0);
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
  EXPECT_THROW(StreamRecorder(dir / "missing", "Tracker0"), std::invalid_argument);
}

}  // namespace
}  // namespace trackcal::vrpn
