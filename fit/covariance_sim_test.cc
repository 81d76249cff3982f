// Coverage of the fit's standard deviations on the simulator (sim/, the paper preset): over many
// seeds, the z-scores (estimate - truth) / stddev of a well-identified physical parameter must
// scatter with unit spread. The simulated tracker's noise grows steeply with range (noise on the
// signal matrix, whose field falls as r^-3), while the model file whitens with a constant noise,
// so the model covariance H^-1 is wrong; the sandwich (fit/covariance.h) must pass.
#include <gtest/gtest.h>

#include <cmath>
#include <iomanip>
#include <iostream>
#include <sstream>
#include <string>
#include <vector>

#include "fit/fit_engine.h"
#include "fit/fit_run.h"
#include "fit/model_file.h"
#include "fit/sim_test_support.h"
#include "sim/scene.h"
#include "sim/simulator.h"

namespace trackcal::fit {
namespace {

using testing::FindParameter;
using testing::FixedRoomTermsYaml;
using testing::YamlVector3;

// z-scores of the sensor offset's 6 coordinates (translation x, y, z; rotation vector x, y, z in
// the tangent of the quaternion block) of one fit.
std::vector<double> SensorOffsetZ(const FitResult& fit, const Rigid3d& truth) {
  std::vector<double> z;
  const ParameterReport& t = FindParameter(fit, "sensor_offset", "translation");
  for (int k = 0; k < 3; ++k) {
    z.push_back((t.values[static_cast<size_t>(k)] - truth.translation(k)) /
                t.stddev[static_cast<size_t>(k)]);
  }
  // The tangent of EigenQuaternionManifold is a left (world) rotation vector.
  const ParameterReport& r = FindParameter(fit, "sensor_offset", "rotation");
  const Eigen::AngleAxisd error(QuaternionFromXyzwArray(r.values.data()) *
                                truth.rotation.conjugate());
  const Eigen::Vector3d w = error.angle() * error.axis();
  for (int k = 0; k < 3; ++k) z.push_back(w(k) / r.stddev[static_cast<size_t>(k)]);
  return z;
}

// Number of seeds. Under a correct stddev, N * RMS(z)^2 of one coordinate is chi-square with N
// degrees of freedom (the seeds are independent; the stddev's own sampling error over 480
// stations is a few percent and neglected). 24 seeds keep the test under a minute of CPU and
// resolve a factor 1.45 in the spread (the band below); the old stddev is off by far more.
constexpr int kSeeds = 24;
// Two-sided 0.05 % / 99.95 % quantiles of chi-square(24) are 7.45 and 53.5 (6 coordinates tested:
// a false failure rate of about 0.6 %): RMS(z) must lie in [sqrt(7.45 / 24), sqrt(53.5 / 24)].
constexpr double kRmsZLow = 0.557;
constexpr double kRmsZHigh = 1.493;

TEST(StandardDeviationCoverage, Nominal_SandwichCoversTheSensorOffsetOverSeeds) {
  sim::Scene base = sim::LoadScene("paper");
  base.hidden.Enable("sensor_offset");
  base.capture.stream.duration_s = 0;  // static stations only
  const Rigid3d truth = base.hidden.receiver_from_body;
  // The model file's default noise (constant 1 mm and 0.2 deg), as a user who does not know the
  // tracker's noise writes it.
  const std::string yaml =
      "terms:\n" + FixedRoomTermsYaml(base.environment) + "  - type: sensor_offset\n";
  std::vector<std::vector<double>> z_model(6), z_sandwich(6);
  double chi2_per_dof_sum = 0;
  for (int seed = 1; seed <= kSeeds; ++seed) {
    sim::Scene scene = base;
    scene.seed = static_cast<uint64_t>(seed);
    const sim::SimulatedCapture capture = sim::Simulator(scene).Generate();
    std::vector<FitStation> calib = StationsOfSet(capture.poses, "calib");
    // The estimator is chosen by the model file only: the same estimates, two covariances.
    ModelSpec model_spec =
        ParseModelYaml(yaml + "solver: {covariance_estimator: model}\n", "model.yaml");
    ModelSpec sandwich_spec = ParseModelYaml(yaml, "sandwich.yaml");  // the default
    const FitResult with_model = FitModel(calib, &model_spec);
    const FitResult with_sandwich = FitModel(calib, &sandwich_spec);
    ASSERT_TRUE(with_model.converged) << with_model.solver_message;
    EXPECT_EQ(with_model.covariance_estimator, "model");
    EXPECT_EQ(with_sandwich.covariance_estimator, "sandwich (CR2)");
    // Same estimates (the estimator changes only the covariance).
    const auto& a = FindParameter(with_model, "sensor_offset", "translation").values;
    const auto& b = FindParameter(with_sandwich, "sensor_offset", "translation").values;
    for (size_t k = 0; k < 3; ++k) EXPECT_EQ(a[k], b[k]);
    const std::vector<double> zm = SensorOffsetZ(with_model, truth);
    const std::vector<double> zs = SensorOffsetZ(with_sandwich, truth);
    for (int k = 0; k < 6; ++k) {
      z_model[static_cast<size_t>(k)].push_back(zm[static_cast<size_t>(k)]);
      z_sandwich[static_cast<size_t>(k)].push_back(zs[static_cast<size_t>(k)]);
    }
    chi2_per_dof_sum += with_model.chi2_per_dof;
  }
  auto rms = [](const std::vector<double>& z) {
    double s = 0;
    for (double v : z) s += v * v;
    return std::sqrt(s / static_cast<double>(z.size()));
  };
  const char* names[6] = {"t.x", "t.y", "t.z", "r.x", "r.y", "r.z"};
  std::cout << "RMS z over " << kSeeds << " seeds (band [" << kRmsZLow << ", " << kRmsZHigh
            << "]); mean chi2/dof " << chi2_per_dof_sum / kSeeds << "\n";
  int model_outside = 0;
  for (int k = 0; k < 6; ++k) {
    const double m = rms(z_model[static_cast<size_t>(k)]);
    const double s = rms(z_sandwich[static_cast<size_t>(k)]);
    std::cout << "  sensor_offset " << names[k] << ": model " << m << ", sandwich " << s << "\n";
    EXPECT_GT(s, kRmsZLow) << names[k];
    EXPECT_LT(s, kRmsZHigh) << names[k];
    if (m < kRmsZLow || m > kRmsZHigh) ++model_outside;
  }
  // The old (model) stddev fails the same test, so this test can tell them apart.
  EXPECT_GE(model_outside, 4);
}

}  // namespace
}  // namespace trackcal::fit
