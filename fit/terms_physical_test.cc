#include "fit/terms_physical.h"

#include <gtest/gtest.h>

#include <cmath>

#include "sim/random.h"
#include "sim/scene.h"
#include "sim/simulator.h"
#include "tests/test_utils.h"

namespace trackcal::fit {
namespace {

// Stations drawn like the paper preset's: a calibration set and a validation set of random poses
// in the validation box (same seeds for a scene and its effect-free twin).
struct Dataset {
  std::vector<PhysicalObservation> calibration;
  std::vector<PhysicalObservation> validation;
};

Dataset Simulate(const sim::Scene& scene, int calibration_count, int validation_count) {
  const sim::Simulator simulator(scene);
  const sim::TrackerModel& tracker = simulator.tracker();
  sim::Rng poses(scene.seed, "physical_test_poses");
  sim::Rng noise(scene.seed, "physical_test_noise");
  const Eigen::Vector3d lo = scene.capture.validation.min_in_transmitter;
  const Eigen::Vector3d hi = scene.capture.validation.max_in_transmitter;
  Dataset d;
  for (int i = 0; i < calibration_count + validation_count; ++i) {
    const Rigid3d truth(poses.UniformRotation(),
                        Eigen::Vector3d(poses.Uniform(lo.x(), hi.x()), poses.Uniform(lo.y(), hi.y()),
                                        poses.Uniform(lo.z(), hi.z())));
    const TrackerSolution report =
        tracker.Report(truth, scene.tracker.samples_per_station, &noise);
    PhysicalObservation obs{report.transmitter_from_receiver, truth * simulator.receiver_from_body()};
    (i < calibration_count ? d.calibration : d.validation).push_back(obs);
  }
  return d;
}

double RmsPositionError(const PhysicalCorrection& model, const std::vector<PhysicalObservation>& set) {
  double sum = 0;
  for (const PhysicalObservation& o : set) {
    sum += (model.Apply(o.reported).pose.translation - o.reference.translation).squaredNorm();
  }
  return std::sqrt(sum / set.size());
}

// Per-axis RMS position and orientation error of a model on a set: the whitening sigmas.
void NoiseSigmas(const PhysicalCorrection& model, const std::vector<PhysicalObservation>& set,
                 double* position_sigma, double* orientation_sigma) {
  double sp = 0, so = 0;
  for (const PhysicalObservation& o : set) {
    const PoseError e = ComputePoseError(model.Apply(o.reported).pose, o.reference);
    sp += e.position.squaredNorm();
    so += e.orientation.squaredNorm();
  }
  *position_sigma = std::sqrt(sp / (3.0 * set.size()));
  *orientation_sigma = std::sqrt(so / (3.0 * set.size()));
}

TEST(FitPhysicalModel, FerromagneticObjectIsRecovered) {
  sim::Scene twin = sim::LoadScene("paper");
  sim::Scene hidden = twin;
  hidden.hidden.Enable("ferromagnetic_object");
  const InducedDipole truth = hidden.hidden.object;
  const Dataset clean = Simulate(twin, 240, 120);
  const Dataset data = Simulate(hidden, 240, 120);

  // The model that fits the effect-free scene: its true environment (error = the noise floor).
  const PhysicalCorrection base(twin.environment, twin.tracker.receiver_gain_matrix);
  const double floor_twin = RmsPositionError(base, clean.validation);
  const double before = RmsPositionError(base, data.validation);
  PhysicalFitOptions options;
  NoiseSigmas(base, clean.calibration, &options.position_sigma_m, &options.orientation_sigma_rad);

  // The matching term, started 15-20 cm and a factor 2 away from the truth.
  FieldModel start = twin.environment;
  start.objects.push_back({"object", truth.location_in_transmitter + Eigen::Vector3d(0.15, -0.1, 0.1),
                           0.5 * truth.polarisability_m3});
  options.free_objects = {static_cast<int>(start.objects.size()) - 1};
  const PhysicalFitResult fit = FitPhysicalModel(
      PhysicalCorrection(start, twin.tracker.receiver_gain_matrix), data.calibration, options);
  ASSERT_TRUE(fit.converged) << fit.report;
  const double after = RmsPositionError(fit.model, data.validation);
  std::cout << "floor " << floor_twin * 1e3 << " mm, hidden uncorrected by base " << before * 1e3
            << " mm, with object term " << after * 1e3 << " mm\n";
  EXPECT_GT(before, 1.5 * floor_twin);  // the effect is visible, so the test can fail
  EXPECT_LT(after, 1.1 * floor_twin);   // the acceptance: within 10% of the twin
  for (int k = 0; k < 4; ++k) {
    const double t = k < 3 ? truth.location_in_transmitter(k) : truth.polarisability_m3;
    EXPECT_TRUE(std::isfinite(fit.stddev(k))) << fit.parameter_names[k];
    EXPECT_LT(std::abs(fit.values(k) - t), 3.0 * fit.stddev(k))
        << fit.parameter_names[k] << " = " << fit.values(k) << " +- " << fit.stddev(k)
        << ", truth " << t;
  }
}

TEST(FitPhysicalModel, ReceiverGainsAreRecovered) {
  sim::Scene twin = sim::LoadScene("paper");
  sim::Scene hidden = twin;
  hidden.hidden.Enable("receiver_gains");
  const Eigen::Matrix3d truth = hidden.hidden.receiver_gain_matrix;
  const Dataset clean = Simulate(twin, 240, 120);
  const Dataset data = Simulate(hidden, 240, 120);
  const PhysicalCorrection base(twin.environment, twin.tracker.receiver_gain_matrix);
  const double floor_twin = RmsPositionError(base, clean.validation);
  const double before = RmsPositionError(base, data.validation);
  PhysicalFitOptions options;
  NoiseSigmas(base, clean.calibration, &options.position_sigma_m, &options.orientation_sigma_rad);
  options.receiver_gain = true;
  const PhysicalFitResult fit = FitPhysicalModel(base, data.calibration, options);
  ASSERT_TRUE(fit.converged) << fit.report;
  const double after = RmsPositionError(fit.model, data.validation);
  std::cout << "floor " << floor_twin * 1e3 << " mm, hidden uncorrected by base " << before * 1e3
            << " mm, with gain term " << after * 1e3 << " mm\n";
  EXPECT_GT(before, 1.5 * floor_twin);
  EXPECT_LT(after, 1.1 * floor_twin);
  for (int k = 0; k < 9; ++k) {
    EXPECT_LT(std::abs(fit.values(k) - truth(k / 3, k % 3)), 3.0 * fit.stddev(k))
        << fit.parameter_names[k] << " = " << fit.values(k) << " +- " << fit.stddev(k);
  }
}

TEST(FitPhysicalModel, SensorOffsetIsRecovered) {
  sim::Scene twin = sim::LoadScene("paper");
  sim::Scene hidden = twin;
  hidden.hidden.Enable("sensor_offset");
  const Rigid3d truth = hidden.hidden.receiver_from_body;
  const Dataset clean = Simulate(twin, 240, 120);
  const Dataset data = Simulate(hidden, 240, 120);
  const PhysicalCorrection base(twin.environment, twin.tracker.receiver_gain_matrix);
  const double floor_twin = RmsPositionError(base, clean.validation);
  const double before = RmsPositionError(base, data.validation);
  PhysicalFitOptions options;
  NoiseSigmas(base, clean.calibration, &options.position_sigma_m, &options.orientation_sigma_rad);
  options.sensor_offset = true;
  const PhysicalFitResult fit = FitPhysicalModel(base, data.calibration, options);
  ASSERT_TRUE(fit.converged) << fit.report;
  const double after = RmsPositionError(fit.model, data.validation);
  EXPECT_GT(before, 1.5 * floor_twin);
  EXPECT_LT(after, 1.1 * floor_twin);
  // Rotation chart starts at identity: its value is the rotation vector of the offset (to first
  // order; the chart normalize(1, w / 2) is exact for the angle's tangent: w = 2 tan(a / 2) axis).
  const Eigen::AngleAxisd aa(truth.rotation);
  const Eigen::Vector3d w_truth = 2.0 * std::tan(0.5 * aa.angle()) * aa.axis();
  for (int k = 0; k < 6; ++k) {
    const double t = k < 3 ? w_truth(k) : truth.translation(k - 3);
    EXPECT_LT(std::abs(fit.values(k) - t), 3.0 * fit.stddev(k))
        << fit.parameter_names[k] << " = " << fit.values(k) << " +- " << fit.stddev(k)
        << ", truth " << t;
  }
}

}  // namespace
}  // namespace trackcal::fit
