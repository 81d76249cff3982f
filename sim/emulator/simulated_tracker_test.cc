#include "sim/emulator/simulated_tracker.h"

#include <fcntl.h>
#include <gtest/gtest.h>
#include <poll.h>
#include <unistd.h>

#include "sim/emulator/emulator.h"
#include "tests/test_utils.h"

namespace trackcal::emulator {
namespace {

std::shared_ptr<const sim::Simulator> PaperSimulator(bool noise) {
  sim::Scene scene = sim::LoadScene("paper");
  if (!noise) scene.tracker.signal_noise = 0.0;
  return std::make_shared<const sim::Simulator>(scene);
}

// A pose inside the paper scene's working volume (transmitter above, hemisphere -z).
Rigid3d PosesInVolume() {
  return Rigid3d(QuaternionFromWxyz(0.9, 0.1, -0.3, 0.2).normalized(),
                 Eigen::Vector3d(0.25, -0.15, -0.45));
}

TEST(SimulatedTracker, Nominal) {
  const auto simulator = PaperSimulator(/*noise=*/false);
  SimulatedTracker tracker(simulator, /*seed=*/1);
  const Rigid3d truth = PosesInVolume();
  const Rigid3d reported = tracker.Reported(1, truth, 0.0);
  // The plumbing: exactly the simulator's noise-free report.
  const Rigid3d expected = simulator->tracker().Report(truth, 1, nullptr).transmitter_from_receiver;
  EXPECT_TRUE(testing::PosesNear(expected, reported, 0, 0));
  // The physics: the paper scene's distortion moves the report by millimetres to centimetres
  // (its Table 1 errors), far above solver round-off.
  EXPECT_GT(PositionErrorNorm(truth, reported), 1e-3);
  EXPECT_LT(PositionErrorNorm(truth, reported), 0.2);
  EXPECT_GE(reported.translation.dot(simulator->scene().tracker.hemisphere_in_transmitter), 0.0);
}

TEST(SimulatedTracker, NoiseIsSeeded) {
  const auto simulator = PaperSimulator(/*noise=*/true);
  SimulatedTracker a(simulator, 5), b(simulator, 5), c(simulator, 6);
  const Rigid3d truth = PosesInVolume();
  const Rigid3d ra = a.Reported(1, truth, 0.0);
  EXPECT_TRUE(testing::PosesNear(ra, b.Reported(1, truth, 0.0), 0, 0));
  EXPECT_FALSE(testing::PosesNear(ra, c.Reported(1, truth, 0.0), 1e-12, 1e-12));
  SimulatedTracker quiet(simulator, 5, /*add_noise=*/false);
  const Rigid3d mean = quiet.Reported(1, truth, 0.0);
  // Signal noise 0.001 of a unit field at 1 m gives sub-millimetre scatter at 0.5 m; 1 cm bounds
  // it.
  EXPECT_LT(PositionErrorNorm(mean, ra), 0.01);
  EXPECT_GT(PositionErrorNorm(mean, ra), 0.0);
}

TEST(SceneTrajectorySource, FollowsSimulatorReceivers) {
  const auto simulator = PaperSimulator(false);
  SceneTrajectorySource source(simulator);
  for (int s = 1; s <= 4; ++s) {
    EXPECT_TRUE(
        testing::PosesNear(simulator->TruePoseAt(1.5, s - 1), source.TruePose(s, 1.5), 0, 0));
  }
  EXPECT_THROW(source.TruePose(5, 0), std::out_of_range);
}

// The physics-backed emulator end to end: a polled binary record over the pty is the simulator's
// report, formatted by the device in the scene's hemisphere, byte for byte.
TEST(SimulatedTracker, ThroughTheEmulator) {
  const auto simulator = PaperSimulator(false);
  EmulatorOptions options;
  options.device.num_stations = 1;
  options.device.hemisphere = simulator->scene().tracker.hemisphere_in_transmitter;
  BackgroundEmulator emulator(
      options, std::make_unique<StaticPoseSource>(std::vector<Rigid3d>{PosesInVolume()}),
      std::make_unique<SimulatedTracker>(simulator, 1, false));
  const int fd = open(emulator.initial_device_path().c_str(), O_RDWR | O_NOCTTY | O_NONBLOCK);
  ASSERT_GE(fd, 0);
  const std::string command = "fO1,2,11,0\rP";
  ASSERT_EQ(write(fd, command.data(), command.size()), static_cast<ssize_t>(command.size()));
  std::string record;
  pollfd p{fd, POLLIN, 0};
  while (record.size() < 32 && poll(&p, 1, 1000) > 0) {
    char buffer[64];
    const ssize_t n = read(fd, buffer, sizeof(buffer));
    if (n <= 0) break;
    record.append(buffer, n);
  }
  close(fd);
  FastrakDeviceOptions device_options;
  device_options.hemisphere = options.device.hemisphere;
  FastrakDevice reference(device_options);
  reference.Receive("fO1,2,11,0\r", [](int) { return StationMeasurement{}; });
  StationMeasurement m;
  m.transmitter_from_receiver =
      simulator->tracker().Report(PosesInVolume(), 1, nullptr).transmitter_from_receiver;
  EXPECT_EQ(record, reference.FormatRecord(1, m));
  // And it is not the true pose: the distortion shows in the bytes.
  StationMeasurement truth;
  truth.transmitter_from_receiver = PosesInVolume();
  EXPECT_NE(record, reference.FormatRecord(1, truth));
}

}  // namespace
}  // namespace trackcal::emulator
