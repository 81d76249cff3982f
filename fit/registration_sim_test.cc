// The registration on captures from the physics simulator (sim/): markers.csv and tracker.csv as a
// calibration session records them, the true optical_from_transmitter known from the scene.

#include <gtest/gtest.h>

#include <cmath>
#include <iostream>

#include "fit/registration_io.h"
#include "fit/rotation.h"
#include "sim/simulator.h"
#include "tests/test_utils.h"

namespace trackcal::fit {
namespace {

struct SimRun {
  RegistrationResult result;
  Rigid3d truth;
  double mahalanobis2 = 0.0;
  double rotation_error_deg = 0.0;
  double translation_error_mm = 0.0;
};

SimRun RegisterScene(const sim::Scene& scene, const RegistrationOptions& options) {
  sim::Simulator simulator(scene);
  const sim::SimulatedCapture capture = simulator.Generate();
  const std::vector<RegistrationStation> stations =
      PairRegistrationRecords(capture.MarkersOfSet("reg"), capture.TrackerOfSet("reg"),
                              scene.tracker.sensor);
  SimRun run;
  run.result = RegisterOpticalToTransmitter(stations, options);
  run.truth = scene.reference.optical_from_transmitter;
  Eigen::Matrix<double, 6, 1> e;
  e << RotationVectorBetween<double>(run.result.registration.optical_from_transmitter.rotation,
                                     run.truth.rotation),
      run.result.registration.optical_from_transmitter.translation - run.truth.translation;
  run.mahalanobis2 = e.dot(run.result.optical_from_transmitter_covariance.ldlt().solve(e));
  run.rotation_error_deg = e.head<3>().norm() * kDegPerRad;
  run.translation_error_mm = e.tail<3>().norm() * 1e3;
  return run;
}

RegistrationOptions OptionsFor(const sim::Scene& scene) {
  RegistrationOptions o;
  // Markers averaged over the station's samples.
  o.optical_noise_m =
      scene.reference.marker_noise_m / std::sqrt(double(scene.reference.samples_per_station));
  return o;
}

TEST(RegistrationOnSimulatedCapture, DistortionFreeSceneWithinCovariance) {
  // The paper scene without its distortion sources: the tracker is only noisy, as the paper's
  // registration assumes. Its noise at 0.2-0.45 m from the transmitter (120 averaged samples) is
  // about 0.04 mm and 0.01 deg per axis (truth.json noise floor of the reg set).
  sim::Scene scene = sim::LoadScene("paper");
  scene.environment.planes.clear();
  scene.environment.objects.clear();
  RegistrationOptions o = OptionsFor(scene);
  o.tracker_position_noise_m = 5e-5;
  o.tracker_orientation_noise_rad = 0.01 * kRadPerDeg;
  for (uint64_t seed : {20010313ull, 1ull, 2ull}) {
    scene.seed = seed;
    const SimRun run = RegisterScene(scene, o);
    ASSERT_TRUE(run.result.converged) << run.result.ToString();
    EXPECT_TRUE(run.result.identifiable) << run.result.ToString();
    // 99.99 % quantile of chi-square(6).
    EXPECT_LT(run.mahalanobis2, 27.86) << run.result.ToString();
    // The noise is not exactly Gaussian per axis (it grows with distance), so allow 5 sigma.
    EXPECT_LT(std::abs(run.result.ChiSquareZ()), 5.0) << run.result.ToString();
    // No spatial structure in the tracker residuals (false alarm rate 0.1 % per seed).
    EXPECT_FALSE(run.result.residual_structure.Flagged()) << run.result.ToString();
  }
}

TEST(RegistrationOnSimulatedCapture, PaperSceneDistortionBiasesTheTransform) {
  // With the paper scene's distortion (the workbench frame 0.35 m below the transmitter), the
  // tracker is off by ~2 mm and ~0.5 deg at the registration stations, coherently enough to look
  // like a rotated transmitter frame: no registration from these data alone can remove it, and
  // the covariance (random noise only) does not cover it. This test records the size of the
  // effect so a change shows; docs/registration.md discusses it.
  const sim::Scene scene = sim::LoadScene("paper");
  const SimRun run = RegisterScene(scene, OptionsFor(scene));
  ASSERT_TRUE(run.result.converged);
  std::cout << "paper scene: rotation error " << run.rotation_error_deg
            << " deg, translation error " << run.translation_error_mm << " mm, Mahalanobis^2 "
            << run.mahalanobis2 << ", chi-square z " << run.result.ChiSquareZ() << "\n";
  // Measured 0.52 deg and 0.95 mm (seeds 1-5: 0.27-0.49 deg, 0.43-1.05 mm); bounds at about 2x.
  EXPECT_LT(run.rotation_error_deg, 1.0);
  EXPECT_LT(run.translation_error_mm, 2.0);
  // The chi-square with the default (generous) tracker noise may miss it; the trend test of the
  // per-station tracker residuals, which does not depend on the assumed noise, does not.
  std::cout << "residual trend F " << run.result.residual_structure.f_statistic << ", p "
            << run.result.residual_structure.p_value << "\n";
  EXPECT_TRUE(run.result.residual_structure.Flagged()) << run.result.ToString();
}

TEST(RegistrationOnSimulatedCapture, TrendTestFlagsTheDistortionOnEverySeed) {
  for (uint64_t seed : {1ull, 2ull, 3ull}) {
    sim::Scene scene = sim::LoadScene("paper");
    scene.seed = seed;
    const SimRun run = RegisterScene(scene, OptionsFor(scene));
    std::cout << "seed " << seed << ": chi-square z " << run.result.ChiSquareZ() << ", trend F "
              << run.result.residual_structure.f_statistic << ", p "
              << run.result.residual_structure.p_value << "\n";
    EXPECT_TRUE(run.result.residual_structure.Flagged()) << run.result.ToString();
  }
}

TEST(RegistrationOnSimulatedCapture, SwappedLabelAtAThreeMarkerStationIsLeftOut) {
  // The paper's markers (+-60 mm on the receiver axes) seen three at a time form an equilateral
  // triangle, so two labels swapped there still fit the marker body: only the solve that keeps the
  // station shows its misfit, by pulling the transform and the markers, so that sound stations
  // misfit the body too. The station left out first used to be the one whose body fit was worst:
  // for 5 of the 20 stations of this capture a sound one, four sound stations were left out, the
  // swapped station was kept and the transform came out 3-10 deg and 17-61 mm off (chi-square z
  // 3e4, exit 0, poses written). The swapped station carries almost all of chi-square (97 %).
  sim::Scene scene = sim::LoadScene("paper");
  scene.environment.planes.clear();  // no distortion: the transform within its covariance
  scene.environment.objects.clear();
  sim::Simulator simulator(scene);
  const sim::SimulatedCapture capture = simulator.Generate();
  const std::vector<RegistrationStation> stations = PairRegistrationRecords(
      capture.MarkersOfSet("reg"), capture.TrackerOfSet("reg"), scene.tracker.sensor);
  RegistrationOptions o = OptionsFor(scene);
  o.tracker_position_noise_m = 5e-5;  // as DistortionFreeSceneWithinCovariance
  o.tracker_orientation_noise_rad = 0.01 * kRadPerDeg;
  int three_marker_stations = 0;
  for (std::size_t bad = 0; bad < stations.size(); ++bad) {
    if (stations[bad].markers.size() != 3) continue;
    ++three_marker_stations;
    std::vector<RegistrationStation> swapped = stations;
    std::swap(swapped[bad].markers[0].marker, swapped[bad].markers[1].marker);
    const RegistrationResult r = RegisterOpticalToTransmitter(swapped, o);
    EXPECT_EQ(r.rejected_stations.size(), 1u) << "swap at station " << stations[bad].station << "\n"
                                              << r.ToString();
    EXPECT_TRUE(!r.rejected_stations.empty() &&
                r.rejected_stations.back().station == stations[bad].station)
        << "swap at station " << stations[bad].station;
    Eigen::Matrix<double, 6, 1> e;
    e << RotationVectorBetween<double>(r.registration.optical_from_transmitter.rotation,
                                       scene.reference.optical_from_transmitter.rotation),
        r.registration.optical_from_transmitter.translation -
            scene.reference.optical_from_transmitter.translation;
    // 99.99 % quantile of chi-square(6), as DistortionFreeSceneWithinCovariance.
    EXPECT_LT(e.dot(r.optical_from_transmitter_covariance.ldlt().solve(e)), 27.86)
        << "swap at station " << stations[bad].station << "\n"
        << r.ToString();
  }
  EXPECT_GE(three_marker_stations, 10);  // the paper capture: 14 of 20
}

TEST(FDistributionUpperTail, KnownValues) {
  // Closed forms: F(2, d2) has upper tail (1 + 2 f / d2)^(-d2 / 2); F(d1, 2) has 1 - (d1 f /
  // (d1 f + 2))^(d1 / 2); F(1, infinity) is chi-square(1), tail 0.0455 at 4 (2 sigma).
  EXPECT_NEAR(FDistributionUpperTail(1.0, 2.0, 2.0), 0.5, 1e-12);
  EXPECT_NEAR(FDistributionUpperTail(3.0, 2.0, 96.0), std::pow(1.0 + 6.0 / 96.0, -48.0), 1e-12);
  EXPECT_NEAR(FDistributionUpperTail(1.5, 24.0, 2.0), 1.0 - std::pow(36.0 / 38.0, 12.0), 1e-12);
  EXPECT_NEAR(FDistributionUpperTail(4.0, 1.0, 1e7), 0.0455003, 1e-5);
  EXPECT_DOUBLE_EQ(FDistributionUpperTail(0.0, 24.0, 96.0), 1.0);
}

}  // namespace
}  // namespace trackcal::fit
