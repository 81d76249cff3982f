// Acceptance of the physical terms on the simulator's hidden effects (sim/, the paper preset): the
// effect-free room is given in the model file as fixed physical terms (the model that fits the
// effect-free twin exactly), the matching term is added, and FitModel must bring the validation
// error within 10% of the twin's and the effect's parameters within 3 sigma of the truth.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <iomanip>
#include <set>
#include <sstream>

#include "fit/fit_engine.h"
#include "fit/fit_run.h"
#include "fit/model_file.h"
#include "fit/sim_test_support.h"
#include "fit/terms_physical.h"
#include "sim/random.h"
#include "sim/scene.h"
#include "sim/simulator.h"

namespace trackcal::fit {
namespace {

using testing::FindParameter;
using testing::FixedRoomTermsYaml;
using testing::YamlVector3;

// Stations drawn like the paper preset's: a calibration and a validation set of random poses in the
// validation box (same seeds for a scene and its effect-free twin).
struct Dataset {
  std::vector<FitStation> calibration;
  std::vector<FitStation> validation;
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
    FitStation s;
    s.reported = report.transmitter_from_receiver;
    s.reference = truth * simulator.receiver_from_body();
    s.station = i;
    (i < calibration_count ? d.calibration : d.validation).push_back(s);
  }
  return d;
}

double RmsPositionError(const Correction& model, const std::vector<FitStation>& set) {
  double sum = 0;
  for (const FitStation& s : set) {
    sum += (model.Apply(s.reported).pose.translation - s.reference.translation).squaredNorm();
  }
  return std::sqrt(sum / static_cast<double>(set.size()));
}

// The model file's noise section: the tracker's noise grows as r^4 in position and r^3 in
// orientation (a dipole field falls as r^-3); the scales are the RMS of the exact model's errors on
// the twin's calibration set divided by those laws (what a user measures on an effect-free
// capture).
std::string NoiseYaml(const Correction& exact, const std::vector<FitStation>& set) {
  double cp = 0, co = 0;
  for (const FitStation& s : set) {
    const PoseError e = ComputePoseError(exact.Apply(s.reported).pose, s.reference);
    const double r = s.reported.translation.norm();
    cp += e.position.squaredNorm() / std::pow(r, 8);
    co += e.orientation.squaredNorm() / std::pow(r, 6);
  }
  const double n = 3.0 * static_cast<double>(set.size());
  std::ostringstream out;
  out << std::setprecision(17) << "noise:\n  position_mm: " << std::sqrt(cp / n) * 1e3
      << "\n  orientation_deg: " << std::sqrt(co / n) * kDegPerRad
      << "\n  position_range_exponent: 4\n  orientation_range_exponent: 3\n";
  return out.str();
}

// Fits room + `term_yaml` to the scene with `effect` hidden; checks the validation error against
// the twin's and returns the fit for the parameter checks.
FitResult FitHiddenEffect(const std::string& effect, const std::string& term_yaml,
                          sim::Scene* hidden_out) {
  const sim::Scene twin = sim::LoadScene("paper");
  sim::Scene hidden = twin;
  hidden.hidden.Enable(effect);
  *hidden_out = hidden;
  const Dataset clean = Simulate(twin, 240, 120);
  const Dataset data = Simulate(hidden, 240, 120);
  const PhysicalCorrection exact(twin.environment, twin.tracker.receiver_gain_matrix);
  const double floor_twin = RmsPositionError(exact, clean.validation);
  const double before = RmsPositionError(exact, data.validation);
  const std::string yaml = NoiseYaml(exact, clean.calibration) + "terms:\n" +
                           FixedRoomTermsYaml(twin.environment) + term_yaml;
  ModelSpec spec = ParseModelYaml(yaml, effect + ".yaml");
  FitResult result = FitModel(data.calibration, &spec);
  EXPECT_TRUE(result.converged) << result.solver_message;
  CorrectionChain chain = result.chain;
  chain.ClearVolume();  // validation stations may lie just outside the calibration stations' box
  const double after = RmsPositionError(chain, data.validation);
  std::cout << effect << ": twin floor " << floor_twin * 1e3 << " mm, hidden with the room model "
            << before * 1e3 << " mm, with the term " << after * 1e3 << " mm (" << result.seconds
            << " s)\n";
  EXPECT_GT(before, 1.5 * floor_twin);  // the effect is visible, so the test can fail
  EXPECT_LT(after, 1.1 * floor_twin);   // the issue's acceptance: within 10% of the twin
  return result;
}

void ExpectWithin3Sigma(const ParameterReport& p, const std::vector<double>& truth) {
  ASSERT_EQ(p.values.size(), truth.size());
  ASSERT_EQ(p.stddev.size(), truth.size());
  for (size_t k = 0; k < truth.size(); ++k) {
    EXPECT_TRUE(std::isfinite(p.stddev[k]) && p.stddev[k] > 0) << p.term << "." << p.block << k;
    EXPECT_LT(std::abs(p.values[k] - truth[k]), 3.0 * p.stddev[k])
        << p.term << "." << p.block << "[" << k << "] = " << p.values[k] << " +- " << p.stddev[k]
        << ", truth " << truth[k];
  }
}

TEST(PhysicalTermsOnSimulator, SensorOffset) {
  sim::Scene hidden;
  const FitResult fit = FitHiddenEffect("sensor_offset", "  - type: sensor_offset\n", &hidden);
  const Rigid3d& truth = hidden.hidden.receiver_from_body;
  const auto& t = truth.translation;
  ExpectWithin3Sigma(FindParameter(fit, "sensor_offset", "translation"), {t.x(), t.y(), t.z()});
  // Rotation: the tangent of EigenQuaternionManifold is a left (world) rotation vector, so the
  // error is log(q_fit q_truth^-1), compared per axis with the tangent stds.
  const auto& rotation = FindParameter(fit, "sensor_offset", "rotation");
  ASSERT_EQ(rotation.stddev.size(), 3u);
  const Eigen::AngleAxisd error(QuaternionFromXyzwArray(rotation.values.data()) *
                                truth.rotation.conjugate());
  const Eigen::Vector3d w = error.angle() * error.axis();
  for (int k = 0; k < 3; ++k) {
    EXPECT_LT(std::abs(w(k)), 3.0 * rotation.stddev[static_cast<size_t>(k)])
        << "rotation " << k << ": " << w(k) << " vs std "
        << rotation.stddev[static_cast<size_t>(k)];
  }
}

TEST(PhysicalTermsOnSimulator, ReceiverGains) {
  sim::Scene hidden;
  const FitResult fit = FitHiddenEffect("receiver_gains", "  - type: receiver_gain\n", &hidden);
  const Eigen::Matrix3d& g = hidden.hidden.receiver_gain_matrix;
  ExpectWithin3Sigma(
      FindParameter(fit, "receiver_gain", "gain_matrix"),
      {g(0, 0), g(0, 1), g(0, 2), g(1, 0), g(1, 1), g(1, 2), g(2, 0), g(2, 1), g(2, 2)});
}

// The uniform-gain gauge (docs/model-file.md): with a polynomial after the group, a uniform gain is
// an isotropic scaling of positions the polynomial absorbs, so trace G is held at 3 (mean coil
// gain 1) and G reports the truth's relative gains and non-orthogonality, 3 G_true / trace(G_true).
// Room fixed + gain + the paper's degree-4 polynomial, as the workflow loop builds it; 3 seeds.
Eigen::Matrix3d GainOf(const ParameterReport& p) {
  Eigen::Matrix3d g;
  for (int k = 0; k < 9; ++k) g(k / 3, k % 3) = p.values[static_cast<size_t>(k)];
  return g;
}

// The paper preset on `seed` with hidden receiver gains and its effect-free twin, simulated alike.
struct GainCase {
  sim::Scene twin;
  sim::Scene hidden;
  Dataset clean;
  Dataset data;
};

GainCase SimulateGainCase(uint64_t seed) {
  GainCase c;
  c.twin = sim::LoadScene("paper");
  c.twin.seed = seed;
  c.hidden = c.twin;
  c.hidden.hidden.Enable("receiver_gains");
  c.clean = Simulate(c.twin, 240, 120);
  c.data = Simulate(c.hidden, 240, 120);
  return c;
}

FitResult FitGainWithPolynomial(uint64_t seed, const std::string& gain_yaml,
                                sim::Scene* hidden_out) {
  const GainCase c = SimulateGainCase(seed);
  const sim::Scene& twin = c.twin;
  const Dataset& clean = c.clean;
  const Dataset& data = c.data;
  *hidden_out = c.hidden;
  const PhysicalCorrection exact(twin.environment, twin.tracker.receiver_gain_matrix);
  const std::string yaml = NoiseYaml(exact, clean.calibration) + "terms:\n" +
                           FixedRoomTermsYaml(twin.environment) + gain_yaml +
                           "  - type: polynomial\n    degree: 4\n";
  ModelSpec spec = ParseModelYaml(yaml, "gain_poly.yaml");
  FitResult fit = FitModel(data.calibration, &spec);
  EXPECT_TRUE(fit.converged) << fit.solver_message;
  CorrectionChain chain = fit.chain;
  chain.ClearVolume();
  // The polynomial takes the scaling: the held-out error stays at the twin's (10 %, the issue's
  // acceptance for a hidden effect).
  EXPECT_LT(RmsPositionError(chain, data.validation),
            1.1 * RmsPositionError(exact, clean.validation));
  return fit;
}

TEST(PhysicalTermsOnSimulator, ReceiverGainScaleIsHeldWhenAPolynomialFollows) {
  for (uint64_t seed : {1u, 2u, 3u}) {
    SCOPED_TRACE("seed " + std::to_string(seed));
    sim::Scene hidden;
    const FitResult fit = FitGainWithPolynomial(seed, "  - type: receiver_gain\n", &hidden);
    const ParameterReport& p = FindParameter(fit, "receiver_gain", "gain_matrix");
    // trace G = 3 to the gauge residual's 1e-8 (10x margin).
    EXPECT_NEAR(GainOf(p).trace(), 3.0, 1e-7);
    bool held = false;
    for (const auto& t : fit.terms) {
      for (const auto& e : t.value("effects", nlohmann::json::array())) {
        held = held || e.value("unit_mean_gain", false);
      }
    }
    EXPECT_TRUE(held) << "the description says the mean gain was held";
    const Eigen::Matrix3d g =
        3.0 * hidden.hidden.receiver_gain_matrix / hidden.hidden.receiver_gain_matrix.trace();
    // 3 sigma for the block as a whole: with 9 coordinates each gets the Bonferroni-corrected
    // two-sided level 0.27 % / 9, 3.62 sigma (as fit/candidates_sim_test.cc); 27 comparisons over
    // the 3 seeds at 3.0 sigma each would fail 7 % of the time by chance.
    ASSERT_EQ(p.stddev.size(), 9u);
    for (int k = 0; k < 9; ++k) {
      const double sd = p.stddev[static_cast<size_t>(k)];
      EXPECT_TRUE(std::isfinite(sd) && sd > 0) << k;
      EXPECT_LT(std::abs(p.values[static_cast<size_t>(k)] - g(k / 3, k % 3)), 3.62 * sd)
          << "G" << k / 3 << k % 3 << " = " << p.values[static_cast<size_t>(k)] << " +- " << sd
          << ", normalised truth " << g(k / 3, k % 3);
    }
    std::cout << "seed " << seed << ": G (mean gain 1) diagonal " << p.values[0] << " "
              << p.values[4] << " " << p.values[8] << " +- " << p.stddev[0] << ", normalised truth "
              << g(0, 0) << " " << g(1, 1) << " " << g(2, 2) << " (" << fit.seconds << " s)\n";
  }
}

// The same with the room known only near the volume (the workbench frame and the floor, as the
// workflow's loop finds them), the three CRT monitors and the door 1.9-2.1 m away left out: the
// gains multiply their field too, and what the polynomial cannot absorb of that product biases G
// by a few sigma (docs/diagnose.md). A background_field (degree 1) in the group takes their field.
// |value - truth| / stddev of the 9 coordinates of G (normalised to mean gain 1, as the fit's).
std::vector<double> GainDeviations(const FitResult& fit, const sim::Scene& hidden) {
  const ParameterReport& p = FindParameter(fit, "receiver_gain", "gain_matrix");
  const Eigen::Matrix3d g =
      3.0 * hidden.hidden.receiver_gain_matrix / hidden.hidden.receiver_gain_matrix.trace();
  std::vector<double> z;
  for (int k = 0; k < 9; ++k) {
    const double sd = p.stddev[static_cast<size_t>(k)];
    EXPECT_TRUE(std::isfinite(sd) && sd > 0) << k;
    z.push_back(std::abs(p.values[static_cast<size_t>(k)] - g(k / 3, k % 3)) / sd);
  }
  return z;
}

// The room's sources as free terms started at the truth (FixedRoomTermsYaml without its
// `parameters:` lines).
std::string FreeRoomTermsYaml(const FieldModel& room) {
  std::istringstream in(FixedRoomTermsYaml(room));
  std::string out, line;
  while (std::getline(in, line)) {
    if (line.find("parameters:") == std::string::npos) out += line + "\n";
  }
  return out;
}

TEST(PhysicalTermsOnSimulator, BackgroundFieldTakesTheDistantSourcesOffTheGains) {
  double sum_sq[2] = {0, 0};
  for (uint64_t seed : {1u, 2u, 3u}) {
    SCOPED_TRACE("seed " + std::to_string(seed));
    const GainCase c = SimulateGainCase(seed);
    const PhysicalCorrection exact(c.twin.environment, c.twin.tracker.receiver_gain_matrix);
    FieldModel near = c.twin.environment;
    std::erase_if(near.objects,
                  [](const InducedDipole& o) { return o.name.find("monitor") != std::string::npos; });
    std::erase_if(near.planes, [](const ConductingPlane& p) { return p.name == "metal_door"; });
    ASSERT_EQ(near.objects.size(), 1u);
    ASSERT_EQ(near.planes.size(), 1u);
    double worst[2] = {0, 0};
    for (const bool background : {false, true}) {
      const std::string yaml =
          NoiseYaml(exact, c.clean.calibration) + "terms:\n" + FreeRoomTermsYaml(near) +
          "  - type: receiver_gain\n" +
          (background ? "  - type: background_field\n    degree: 1\n" : "") +
          "  - type: polynomial\n    degree: 4\n";
      ModelSpec spec = ParseModelYaml(yaml, "distant.yaml");
      const FitResult fit = FitModel(c.data.calibration, &spec);
      EXPECT_TRUE(fit.converged) << fit.solver_message;
      for (double z : GainDeviations(fit, c.hidden)) {
        worst[background] = std::max(worst[background], z);
        sum_sq[background] += z * z;
      }
    }
    std::cout << "seed " << seed << ": largest G deviation without the background " << worst[0]
              << " sigma, with it " << worst[1] << " sigma\n";
    // 3.62 sigma: the Bonferroni level of a 3 sigma test of the 9-coordinate block (as above).
    EXPECT_LT(worst[1], 3.62);
  }
  const double rms[2] = {std::sqrt(sum_sq[0] / 27), std::sqrt(sum_sq[1] / 27)};
  std::cout << "RMS G deviation over the 3 seeds: without the background " << rms[0]
            << " sigma, with it " << rms[1] << " sigma\n";
  // The distant sources' bias shows in the spread of the deviations; the background takes it off
  // (the test fails if it does not). Measured: RMS 1.60 sigma without, 1.17 with (1 for an
  // unbiased estimate with honest stddevs); largest per seed 2.73, 2.38, 2.71 without, 1.59, 2.04,
  // 2.38 with.
  EXPECT_LT(rms[1], rms[0]);
}

// The paper preset's grid has 4 heights. A degree-4 polynomial after a room model that is right
// sees the stations at their true positions, where (z - z1)(z - z2)(z - z3)(z - z4) vanishes:
// fitted,
// that direction takes the noise and swings between the heights. The fit holds it (an
// identifiability flag says so) and the validation stations, at random heights, stay at the room
// model's own error. (Measured, seed 20010313: the room alone 0.115 mm RMS on validation, with
// the polynomial 0.124 mm, fitting every direction 22.7 mm.)
TEST(PhysicalTermsOnSimulator, APolynomialAfterTheRoomHoldsWhatFourHeightsCannotDetermine) {
  const sim::Scene scene = sim::LoadScene("paper");
  const sim::SimulatedCapture capture = sim::Simulator(scene).Generate();
  const std::vector<FitStation> calibration = StationsOfSet(capture.poses, "calib");
  const std::vector<FitStation> validation = StationsOfSet(capture.poses, "valid");
  const PhysicalCorrection exact(scene.environment, scene.tracker.receiver_gain_matrix);
  const double room = RmsPositionError(exact, validation);
  double error[2] = {0, 0};
  for (const bool held : {true, false}) {
    const std::string yaml = "terms:\n" + FixedRoomTermsYaml(scene.environment) +
                             "  - type: polynomial\n    degree: 4\n" +
                             (held ? "" : "    max_amplification: 0\n");
    ModelSpec spec = ParseModelYaml(yaml, "room_polynomial.yaml");
    const FitResult fit = FitModel(calibration, &spec);
    EXPECT_TRUE(fit.converged) << fit.solver_message;
    CorrectionChain chain = fit.chain;
    chain.ClearVolume();  // validation stations reach 5-7.5 cm beyond the grid
    error[held] = RmsPositionError(chain, validation);
    bool flagged = false;
    for (const auto& f : fit.identifiability_flags) {
      flagged = flagged || (f.coordinate == "polynomial.position_coefficients" &&
                            f.reason.find("1 of its 35 directions not determined") == 0);
    }
    EXPECT_EQ(flagged, held);
    const ParameterReport& p = FindParameter(fit, "polynomial", "position_coefficients");
    ASSERT_EQ(p.stddev.size(), p.values.size());  // the values' own, mapped from the subspace
    for (double sd : p.stddev) EXPECT_TRUE(std::isfinite(sd) && sd >= 0);
    if (held) {
      EXPECT_EQ(fit.num_free_parameters, 2 * 3 * (35 - 1));
    }
  }
  std::cout << "validation RMS position error: room " << room * 1e3 << " mm, room + polynomial "
            << error[1] * 1e3 << " mm, fitting every direction " << error[0] * 1e3 << " mm\n";
  EXPECT_LT(error[1], 1.5 * room);   // the polynomial's own 70 free coefficients cost a little
  EXPECT_GT(error[0], 10.0 * room);  // and the test can fail
}

TEST(PhysicalTermsOnSimulator, FerromagneticObjectFoundWithoutStart) {
  sim::Scene hidden;
  // No start value: the search places the object.
  const FitResult fit = FitHiddenEffect("ferromagnetic_object", "  - type: dipole\n", &hidden);
  const InducedDipole& truth = hidden.hidden.object;
  const auto& l = truth.location_in_transmitter;
  ExpectWithin3Sigma(FindParameter(fit, "dipole", "location_in_transmitter"),
                     {l.x(), l.y(), l.z()});
  ExpectWithin3Sigma(FindParameter(fit, "dipole", "polarisability_m3"), {truth.polarisability_m3});
}

// The toolbox on the paper protocol's stations (sim::Simulator::Generate: the calibration grid and
// the validation stations of the preset), where six calibration stations 0.29-0.32 m from the
// object sit just outside its fold zone and the inverse amplifies their report noise 30-45 times.
// Whitened with the model file's noise alone they steer the searched dipole into a local minimum
// (0.637, 0.916, -0.538) m, 0.00155 m^3 on seed 20010313; with their pose metric capped where the
// fitted inverse amplifies their noise (fit/pose_metric.h, noise.amplification_threshold) the fit
// finds the object.
// The issue's acceptance per seed: validation within 10 % of the room model's error on the
// effect-free twin, location and strength within 3 sigma.
void FitFerromagneticOnProtocol(uint64_t seed) {
  sim::Scene twin = sim::LoadScene("paper");
  twin.seed = seed;
  sim::Scene hidden = twin;
  hidden.hidden.Enable("ferromagnetic_object");
  const sim::SimulatedCapture clean = sim::Simulator(twin).Generate();
  const sim::SimulatedCapture capture = sim::Simulator(hidden).Generate();
  const std::vector<FitStation> twin_calibration = StationsOfSet(clean.poses, "calib");
  const std::vector<FitStation> twin_validation = StationsOfSet(clean.poses, "valid");
  const std::vector<FitStation> calibration = StationsOfSet(capture.poses, "calib");
  const std::vector<FitStation> validation = StationsOfSet(capture.poses, "valid");
  const PhysicalCorrection exact(twin.environment, twin.tracker.receiver_gain_matrix);
  const double floor_twin = RmsPositionError(exact, twin_validation);
  const double before = RmsPositionError(exact, validation);
  ModelSpec spec = ParseModelYaml(NoiseYaml(exact, twin_calibration) + "terms:\n" +
                                      FixedRoomTermsYaml(twin.environment) + "  - type: dipole\n",
                                  "toolbox.yaml");
  const FitResult fit = FitModel(calibration, &spec);
  EXPECT_TRUE(fit.converged) << fit.solver_message;
  CorrectionChain chain = fit.chain;
  chain.ClearVolume();
  // A validation station inside the object's fold zone has no true pose the true model can find
  // from its report (seed 1: station 545, 0.22 m from the object, 7.7 mm off under the true model,
  // not_converged): no model can reach the twin's error there, and the fitted model must say so.
  // The acceptance holds on the stations the true model resolves.
  FieldModel truth_field = twin.environment;
  truth_field.objects.push_back(hidden.hidden.object);
  const PhysicalCorrection truth_model(truth_field, twin.tracker.receiver_gain_matrix);
  std::vector<FitStation> resolvable;
  for (const FitStation& s : validation) {
    if (truth_model.Apply(s.reported).status != CorrectionStatus::kNotConverged) {
      resolvable.push_back(s);
    } else {
      EXPECT_NE(chain.Apply(s.reported).status, CorrectionStatus::kConverged) << s.station;
    }
  }
  // At most 2 of the 120 (the fold zone holds ~1 % of the validation volume).
  EXPECT_LE(validation.size() - resolvable.size(), 2u);
  const double after = RmsPositionError(chain, resolvable);
  const ParameterReport& l = FindParameter(fit, "dipole", "location_in_transmitter");
  const ParameterReport& a = FindParameter(fit, "dipole", "polarisability_m3");
  std::cout << "seed " << seed << ": twin " << floor_twin * 1e3 << " mm, room model "
            << before * 1e3 << " mm, with the dipole " << after * 1e3 << " mm on the "
            << resolvable.size() << " stations the true model resolves (true model "
            << RmsPositionError(truth_model, resolvable) * 1e3 << " mm); dipole at (" << l.values[0]
            << ", " << l.values[1] << ", " << l.values[2] << ") +- (" << l.stddev[0] << ", "
            << l.stddev[1] << ", " << l.stddev[2] << ") m, " << a.values[0] << " +- " << a.stddev[0]
            << " m^3; " << fit.noise_whitened.size()
            << " stations with a capped pose metric, " << fit.whitening_passes
            << " solves, " << fit.unresolved.size() << " unresolved (" << fit.seconds << " s)\n";
  EXPECT_GT(before, 1.5 * floor_twin);  // the object is visible, so the test can fail
  EXPECT_LT(after, 1.1 * floor_twin);   // the issue's acceptance: within 10 % of the twin
  const InducedDipole& truth = hidden.hidden.object;
  const Eigen::Vector3d& t = truth.location_in_transmitter;
  // 3 sigma for the location as a whole: each of its 3 coordinates gets the Bonferroni-corrected
  // two-sided level 0.27 % / 3, 3.32 sigma (as fit/candidates_sim_test.cc); the strength 3.0.
  for (int k = 0; k < 3; ++k) {
    EXPECT_LT(std::abs(l.values[static_cast<size_t>(k)] - t(k)),
              3.32 * l.stddev[static_cast<size_t>(k)])
        << "location[" << k << "] = " << l.values[static_cast<size_t>(k)] << " +- "
        << l.stddev[static_cast<size_t>(k)] << ", truth " << t(k);
  }
  ExpectWithin3Sigma(a, {truth.polarisability_m3});
  // The fold zone's stations are in report form, and some of them get a capped pose metric (6-7
  // per seed since session 22, the form chosen by the inverse alone): at least one, so the test
  // exercises the cap.
  EXPECT_FALSE(fit.noise_whitened.empty());
  // The report form is for the fold zone only: every capped and every unresolved station is in it,
  // and a station the fitted model resolves is not, unless an earlier solve put it there (a
  // station once in report form stays in it).
  ASSERT_EQ(fit.report_form.size(), calibration.size());
  const std::set<int> report_form(fit.report_form_stations.begin(),
                                  fit.report_form_stations.end());
  EXPECT_EQ(report_form.size(), static_cast<size_t>(std::count(
                                    fit.report_form.begin(), fit.report_form.end(), true)));
  std::set<int> fold_zone;
  for (const auto& w : fit.noise_whitened) {
    EXPECT_TRUE(report_form.count(w.station)) << w.station;
    fold_zone.insert(w.station);
  }
  for (const auto& u : fit.unresolved) {
    EXPECT_TRUE(report_form.count(u.station)) << u.station;
    fold_zone.insert(u.station);
  }
  size_t held = 0;
  for (int station : report_form) held += fold_zone.count(station) ? 0 : 1;
  std::cout << "seed " << seed << ": " << report_form.size() << " stations in report form, "
            << held << " of them resolved and not capped at the solution\n";
  EXPECT_LE(held, 2u);
}

// Three seeds. Seeds 20010313 and 2 failed while the fit's station residual ran the model's inverse
// from the report (session 4: 2.27 mm against the twin's 0.115 mm; location y 4.5 sigma off): a
// station whose inverse does not converge near the object (24-25 per seed) contributed Newton's
// last iterate, which jumps with changes of 1e-7 in the values, and the fit stopped where its path
// left it. The residual became Newton steps from the reference, continuous in the values, and is
// since session 20 the report's misfit under the pose metric
// (PhysicalGroupTerm::EvaluateToward, fit/pose_metric.h), differentiated exactly also at those
// stations: measured, the dipole within 0.2 mm of the truth on all three seeds.
TEST(PhysicalTermsOnSimulator, FerromagneticObjectOnThePaperProtocol) {
  for (uint64_t seed : {1u, 20010313u, 2u}) {
    SCOPED_TRACE("seed " + std::to_string(seed));
    FitFerromagneticOnProtocol(seed);
  }
}

// The residual's form follows the runtime inverse alone: the amplification of the report noise,
// which the fitted values move, caps K in report form but does not choose it. Chosen by it too, a
// fit could lower its cost by raising the amplification at stations it misfits and so moving them
// into the capped report form. Measured on this capture (the paper room with the hidden toolbox,
// seed 2; the demo's frame and toolbox dipoles, a background field and the ridge polynomial): 192
// of 480 stations ended in report form (191 capped), validation 1.097 mm mean; with the form
// chosen by the inverse, 26-27 (the fold zone: the 25 stations no model resolves there, and one or
// two found unresolved at a start) and 0.890 mm. The bound: the unresolved ones plus 5. Here, on
// the 120 validation stations: rms 1.97 mm with 192 in report form, 1.43 with 27; 1.7 between.
TEST(PhysicalTermsOnSimulator, AmplificationDoesNotChooseTheResidualForm) {
  sim::Scene scene = sim::LoadScene("paper");
  scene.seed = 2;
  scene.hidden.Enable("ferromagnetic_object");
  const sim::SimulatedCapture capture = sim::Simulator(scene).Generate();
  const std::vector<FitStation> calibration = StationsOfSet(capture.poses, "calib");
  const std::vector<FitStation> validation = StationsOfSet(capture.poses, "valid");
  ModelSpec spec = ParseModelYaml(R"(terms:
  - type: dipole
    location_in_transmitter: [0.5078, -0.0242, 0.3584]
    polarisability_m3: -0.008322
  - type: dipole
    name: dipole_2
    location_in_transmitter: [0.5883, 0.9719, -0.5163]
    polarisability_m3: 0.00267
  - type: background_field
  - type: polynomial
    degree: 4
    ridge: auto
)",
                                  "background.yaml");
  FitOptions options;
  options.compute_covariance = false;
  const FitResult fit = FitModel(calibration, &spec, options);
  CorrectionChain chain = fit.chain;
  chain.ClearVolume();
  std::cout << fit.report_form_stations.size() << " of " << calibration.size()
            << " stations in report form (" << fit.noise_whitened.size() << " capped), "
            << fit.unresolved.size() << " unresolved; validation rms "
            << RmsPositionError(chain, validation) * 1e3 << " mm\n";
  EXPECT_LE(fit.report_form_stations.size(), fit.unresolved.size() + 5);
  EXPECT_LT(RmsPositionError(chain, validation), 1.7e-3);
}

TEST(PhysicalTermsOnSimulator, FiniteTransmitterCoils) {
  sim::Scene hidden;
  const FitResult fit =
      FitHiddenEffect("finite_transmitter_coils", "  - type: near_field\n", &hidden);
  const Eigen::Vector3d truth =
      hidden.environment.transmitter_octupole_m2 + hidden.hidden.octupole_m2;
  ExpectWithin3Sigma(FindParameter(fit, "near_field", "octupole_m2"),
                     {truth.x(), truth.y(), truth.z()});
}

TEST(PhysicalTermsOnSimulator, FloorPlaneRecoveredFromAPerturbedStart) {
  // The floor's image is what the paper room's error is mostly made of: started 10 cm lower, tilted
  // and 30% weaker (the rest of the room fixed), the plane term finds it again.
  const sim::Scene scene = sim::LoadScene("paper");
  const Dataset data = Simulate(scene, 240, 120);
  const PhysicalCorrection exact(scene.environment, scene.tracker.receiver_gain_matrix);
  const double floor = RmsPositionError(exact, data.validation);
  FieldModel room = scene.environment;
  const ConductingPlane truth = room.planes[0];
  room.planes.erase(room.planes.begin());
  const std::string yaml = NoiseYaml(exact, data.calibration) + "terms:\n" +
                           FixedRoomTermsYaml(room) +
                           "  - type: plane\n    name: floor\n"
                           "    point_in_transmitter: [0, 0, 0.9]\n"
                           "    normal_in_transmitter: [0.05, -0.03, 1]\n"
                           "    attenuation: 0.19\n";
  ModelSpec spec = ParseModelYaml(yaml, "floor.yaml");
  const FitResult fit = FitModel(data.calibration, &spec);
  ASSERT_TRUE(fit.converged) << fit.solver_message;
  CorrectionChain chain = fit.chain;
  chain.ClearVolume();
  EXPECT_LT(RmsPositionError(chain, data.validation), 1.1 * floor);
  ExpectWithin3Sigma(FindParameter(fit, "floor", "distance_m"), {truth.point_in_transmitter.z()});
  ExpectWithin3Sigma(FindParameter(fit, "floor", "attenuation"), {truth.attenuation});
  // The normal's error is 2-D: its angle is held to the radius holding 99.7% of a 2-D Gaussian,
  // sqrt(11.83) = 3.44 times the larger of the two tangent stds (radians).
  const auto& n = FindParameter(fit, "floor", "normal_in_transmitter");
  ASSERT_EQ(n.stddev.size(), 2u);
  const Eigen::Vector3d normal(n.values[0], n.values[1], n.values[2]);
  EXPECT_LT(std::acos(std::min(1.0, normal.normalized().dot(truth.normal_in_transmitter))),
            3.44 * std::max(n.stddev[0], n.stddev[1]));
}

TEST(PhysicalTermsOnSimulator, RobustLossIgnoresHemisphereFlips) {
  sim::Scene scene = sim::LoadScene("paper");
  sim::Scene hidden = scene;
  hidden.hidden.Enable("receiver_gains");
  const Eigen::Matrix3d truth = hidden.hidden.receiver_gain_matrix;
  Dataset data = Simulate(hidden, 240, 120);
  // Three calibration stations reported in the wrong hemisphere (at -p), as a Fastrak does.
  for (int i : {5, 70, 150}) data.calibration[static_cast<size_t>(i)].reported.translation *= -1.0;
  const Dataset clean = Simulate(scene, 240, 120);
  const PhysicalCorrection exact(scene.environment, scene.tracker.receiver_gain_matrix);
  const std::string yaml = NoiseYaml(exact, clean.calibration) +
                           "loss: {type: cauchy, scale: 5}\nterms:\n" +
                           FixedRoomTermsYaml(scene.environment) + "  - type: receiver_gain\n";
  ModelSpec spec = ParseModelYaml(yaml, "flips.yaml");
  const FitResult fit = FitModel(data.calibration, &spec);
  ASSERT_TRUE(fit.converged) << fit.solver_message;
  EXPECT_GE(fit.outliers.size(), 3u);  // the flips are named as outliers
  CorrectionChain chain = fit.chain;
  chain.ClearVolume();
  EXPECT_LT(RmsPositionError(chain, data.validation),
            1.2 * RmsPositionError(exact, clean.validation));
  const auto& g = FindParameter(fit, "receiver_gain", "gain_matrix");
  for (int k = 0; k < 9; ++k) {
    // 1e-3 is 1/20 of the gains' deviation from identity: the flips would drag G far beyond it.
    EXPECT_NEAR(g.values[static_cast<size_t>(k)], truth(k / 3, k % 3), 1e-3) << k;
  }
}

}  // namespace
}  // namespace trackcal::fit
