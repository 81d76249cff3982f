#include "fit/terms_physical_standalone.h"

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
    const Rigid3d truth(poses.UniformRotation(), Eigen::Vector3d(poses.Uniform(lo.x(), hi.x()),
                                                                 poses.Uniform(lo.y(), hi.y()),
                                                                 poses.Uniform(lo.z(), hi.z())));
    const TrackerSolution report = tracker.Report(truth, scene.tracker.samples_per_station, &noise);
    PhysicalObservation obs{report.transmitter_from_receiver,
                            truth * simulator.receiver_from_body()};
    (i < calibration_count ? d.calibration : d.validation).push_back(obs);
  }
  return d;
}

double RmsPositionError(const PhysicalCorrection& model,
                        const std::vector<PhysicalObservation>& set) {
  double sum = 0;
  for (const PhysicalObservation& o : set) {
    sum += (model.Apply(o.reported).pose.translation - o.reference.translation).squaredNorm();
  }
  return std::sqrt(sum / set.size());
}

// Whitening: the tracker's noise grows as r^4 in position and r^3 in orientation (a dipole field
// falls as r^-3; sim/tracker_solver_test.cc checks the r^4 law). The scale factors are the RMS of
// the model's errors on `set` divided by those laws; they are written into every observation of
// `sets`, and the per-axis RMS goes into the options as the fallback.
void SetNoiseSigmas(const PhysicalCorrection& model, const std::vector<PhysicalObservation>& set,
                    std::vector<std::vector<PhysicalObservation>*> sets,
                    PhysicalFitOptions* options) {
  double sp = 0, so = 0, cp = 0, co = 0;
  for (const PhysicalObservation& o : set) {
    const PoseError e = ComputePoseError(model.Apply(o.reported).pose, o.reference);
    const double r = o.reported.translation.norm();
    sp += e.position.squaredNorm();
    so += e.orientation.squaredNorm();
    cp += e.position.squaredNorm() / std::pow(r, 8);
    co += e.orientation.squaredNorm() / std::pow(r, 6);
  }
  const double n = 3.0 * set.size();
  options->position_sigma_m = std::sqrt(sp / n);
  options->orientation_sigma_rad = std::sqrt(so / n);
  for (std::vector<PhysicalObservation>* observations : sets) {
    for (PhysicalObservation& o : *observations) {
      const double r = o.reported.translation.norm();
      o.position_sigma_m = std::sqrt(cp / n) * std::pow(r, 4);
      o.orientation_sigma_rad = std::sqrt(co / n) * std::pow(r, 3);
    }
  }
}

TEST(FitPhysicalModel, FerromagneticObjectIsRecovered) {
  sim::Scene twin = sim::LoadScene("paper");
  sim::Scene hidden = twin;
  hidden.hidden.Enable("ferromagnetic_object");
  const InducedDipole truth = hidden.hidden.object;
  const Dataset clean = Simulate(twin, 240, 120);
  Dataset data = Simulate(hidden, 240, 120);

  // The model that fits the effect-free scene: its true environment (error = the noise floor).
  const PhysicalCorrection base(twin.environment, twin.tracker.receiver_gain_matrix);
  const double floor_twin = RmsPositionError(base, clean.validation);
  const double before = RmsPositionError(base, data.validation);
  PhysicalFitOptions options;
  SetNoiseSigmas(base, clean.calibration, {&data.calibration}, &options);

  // The matching term, started 15-20 cm and a factor 2 away from the truth.
  FieldModel start = twin.environment;
  start.objects.push_back({"object",
                           truth.location_in_transmitter + Eigen::Vector3d(0.15, -0.1, 0.1),
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
        << fit.parameter_names[k] << " = " << fit.values(k) << " +- " << fit.stddev(k) << ", truth "
        << t;
  }
}

TEST(FitPhysicalModel, ReceiverGainsAreRecovered) {
  sim::Scene twin = sim::LoadScene("paper");
  sim::Scene hidden = twin;
  hidden.hidden.Enable("receiver_gains");
  const Eigen::Matrix3d truth = hidden.hidden.receiver_gain_matrix;
  const Dataset clean = Simulate(twin, 240, 120);
  Dataset data = Simulate(hidden, 240, 120);
  const PhysicalCorrection base(twin.environment, twin.tracker.receiver_gain_matrix);
  const double floor_twin = RmsPositionError(base, clean.validation);
  const double before = RmsPositionError(base, data.validation);
  PhysicalFitOptions options;
  SetNoiseSigmas(base, clean.calibration, {&data.calibration}, &options);
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
  Dataset data = Simulate(hidden, 240, 120);
  const PhysicalCorrection base(twin.environment, twin.tracker.receiver_gain_matrix);
  const double floor_twin = RmsPositionError(base, clean.validation);
  const double before = RmsPositionError(base, data.validation);
  PhysicalFitOptions options;
  SetNoiseSigmas(base, clean.calibration, {&data.calibration}, &options);
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
        << fit.parameter_names[k] << " = " << fit.values(k) << " +- " << fit.stddev(k) << ", truth "
        << t;
  }
}

TEST(FitPhysicalModel, FiniteTransmitterCoilsAreRecovered) {
  sim::Scene twin = sim::LoadScene("paper");
  sim::Scene hidden = twin;
  hidden.hidden.Enable("finite_transmitter_coils");
  const Eigen::Vector3d truth =
      twin.environment.transmitter_octupole_m2 + hidden.hidden.octupole_m2;
  const Dataset clean = Simulate(twin, 240, 120);
  Dataset data = Simulate(hidden, 240, 120);
  const PhysicalCorrection base(twin.environment, twin.tracker.receiver_gain_matrix);
  const double floor_twin = RmsPositionError(base, clean.validation);
  const double before = RmsPositionError(base, data.validation);
  PhysicalFitOptions options;
  SetNoiseSigmas(base, clean.calibration, {&data.calibration}, &options);
  options.near_field = true;
  const PhysicalFitResult fit = FitPhysicalModel(base, data.calibration, options);
  ASSERT_TRUE(fit.converged) << fit.report;
  const double after = RmsPositionError(fit.model, data.validation);
  std::cout << "floor " << floor_twin * 1e3 << " mm, hidden uncorrected by base " << before * 1e3
            << " mm, with near-field term " << after * 1e3 << " mm\n";
  EXPECT_GT(before, 1.5 * floor_twin);
  EXPECT_LT(after, 1.1 * floor_twin);
  for (int k = 0; k < 3; ++k) {
    EXPECT_LT(std::abs(fit.values(k) - truth(k)), 3.0 * fit.stddev(k))
        << fit.parameter_names[k] << " = " << fit.values(k) << " +- " << fit.stddev(k);
  }
}

TEST(FitPhysicalModel, PlaneIsRecoveredFromAPerturbedStart) {
  // The floor's image is what the paper room's error is mostly made of: started 10 cm lower,
  // tilted and 30% weaker, the plane term finds it again.
  const sim::Scene scene = sim::LoadScene("paper");
  Dataset data = Simulate(scene, 240, 120);
  const ConductingPlane truth = scene.environment.planes[0];
  const PhysicalCorrection exact(scene.environment, scene.tracker.receiver_gain_matrix);
  const double floor = RmsPositionError(exact, data.validation);
  PhysicalFitOptions options;
  SetNoiseSigmas(exact, data.calibration, {&data.calibration}, &options);
  FieldModel start = scene.environment;
  start.planes[0].point_in_transmitter += Eigen::Vector3d(0, 0, 0.1);
  start.planes[0].normal_in_transmitter = Eigen::Vector3d(0.05, -0.03, 1).normalized();
  start.planes[0].attenuation *= 0.7;
  options.free_planes = {0};
  const PhysicalCorrection initial(start, scene.tracker.receiver_gain_matrix);
  const double before = RmsPositionError(initial, data.validation);
  const PhysicalFitResult fit = FitPhysicalModel(initial, data.calibration, options);
  ASSERT_TRUE(fit.converged) << fit.report;
  const double after = RmsPositionError(fit.model, data.validation);
  EXPECT_GT(before, 10 * floor);
  EXPECT_LT(after, 1.1 * floor);
  const ConductingPlane& fitted = fit.model.field().planes[0];
  // Distance along the normal and attenuation within 3 sigma; the normal's error is 2-D, so its
  // angle is held to the radius holding 99.7% of a 2-D Gaussian, sqrt(11.83) = 3.44 times the
  // larger std of the two chart coordinates (radians for a unit normal).
  EXPECT_LT(std::abs(fit.values(0) - truth.point_in_transmitter.z()), 3.0 * fit.stddev(0));
  EXPECT_LT(std::acos(std::min(1.0, fitted.normal_in_transmitter.normalized().dot(
                                        truth.normal_in_transmitter.normalized()))),
            3.44 * std::max(fit.stddev(1), fit.stddev(2)));
  EXPECT_LT(std::abs(fit.values(3) - truth.attenuation), 3.0 * fit.stddev(3));
}

TEST(FitPhysicalModel, RobustLossIgnoresHemisphereFlips) {
  sim::Scene scene = sim::LoadScene("paper");
  sim::Scene hidden = scene;
  hidden.hidden.Enable("receiver_gains");
  const Eigen::Matrix3d truth = hidden.hidden.receiver_gain_matrix;
  Dataset data = Simulate(hidden, 240, 120);
  // Three calibration stations reported in the wrong hemisphere (at -p), as a Fastrak does.
  for (int i : {5, 70, 150}) data.calibration[i].reported.translation *= -1.0;
  const PhysicalCorrection base(scene.environment, scene.tracker.receiver_gain_matrix);
  PhysicalFitOptions options;
  options.position_sigma_m = 1e-4;  // the floor of the tests above (0.1 mm)
  options.orientation_sigma_rad = 1e-4;
  options.receiver_gain = true;
  options.robust_loss_sigmas = 5.0;
  const PhysicalFitResult fit = FitPhysicalModel(base, data.calibration, options);
  ASSERT_TRUE(fit.converged) << fit.report;
  const Dataset clean = Simulate(scene, 240, 120);
  EXPECT_LT(RmsPositionError(fit.model, data.validation),
            1.2 * RmsPositionError(base, clean.validation));
  for (int k = 0; k < 9; ++k) {
    // The robust fit's covariance is not whitened exactly (sigmas are set by hand): 1e-3 is 10x the
    // std of the gain fit above and 1/20 of the gains' deviation from identity.
    EXPECT_NEAR(fit.values(k), truth(k / 3, k % 3), 1e-3) << fit.parameter_names[k];
  }
}

}  // namespace
}  // namespace trackcal::fit
