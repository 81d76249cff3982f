// Acceptance of the candidate ranking on the simulator's paper preset (docs/diagnose.md): from a
// model that fits the effect-free scene (the paper room's planes and objects as fixed physical
// terms plus a degree-1 polynomial), each hidden effect ranks first, is significant and is fitted
// within 3 sigma of the truth; without a hidden effect nothing is claimed (3 seeds).
#include <gmock/gmock.h>
#include <gtest/gtest.h>
#include <yaml-cpp/yaml.h>

#include <cmath>
#include <iostream>
#include <sstream>

#include "fit/candidates.h"
#include "fit/fit_run.h"
#include "sim/scene.h"
#include "sim/simulator.h"

namespace trackcal::fit {
namespace {

std::string Vec(const Eigen::Vector3d& v) {
  std::ostringstream s;
  s.precision(17);
  s << "[" << v.x() << ", " << v.y() << ", " << v.z() << "]";
  return s.str();
}

// The room of `scene` as fixed physical terms, then a degree-1 polynomial (free parameters for the
// robust loss to matter), whitened by the effect-free twin's noise floor (per axis; the orientation
// sigma is that of the error quaternion's vector part, half the angle).
std::string RoomModel(const sim::Scene& scene, const PoseErrorSummary& noise_floor) {
  std::ostringstream m;
  m.precision(17);
  const double sigma_p_mm = noise_floor.position_mm.rms / std::sqrt(3.0);
  const double sigma_o_deg = 0.5 * noise_floor.orientation_deg.rms / std::sqrt(3.0);
  m << "noise: {position_mm: " << sigma_p_mm << ", orientation_deg: " << sigma_o_deg << "}\n";
  m << "terms:\n";
  for (const auto& p : scene.environment.planes) {
    m << "  - type: plane\n    name: " << p.name
      << "\n    point_in_transmitter: " << Vec(p.point_in_transmitter)
      << "\n    normal_in_transmitter: " << Vec(p.normal_in_transmitter)
      << "\n    attenuation: " << p.attenuation
      << "\n    parameters:\n      distance_m: {fixed: true}\n      normal_in_transmitter: {fixed: "
         "true}\n      attenuation: {fixed: true}\n";
  }
  for (const auto& o : scene.environment.objects) {
    m << "  - type: dipole\n    name: " << o.name
      << "\n    location_in_transmitter: " << Vec(o.location_in_transmitter)
      << "\n    polarisability_m3: " << o.polarisability_m3
      << "\n    parameters:\n      location_in_transmitter: {fixed: true}\n      "
         "polarisability_m3: "
         "{fixed: true}\n";
  }
  m << "  - type: polynomial\n    degree: 1\n";
  return m.str();
}

struct PaperRun {
  Diagnosis diagnosis;
  sim::HiddenEffects truth;
};

PaperRun Diagnose(const std::string& hidden, uint64_t seed) {
  sim::Scene twin = sim::LoadScene("paper");
  twin.seed = seed;
  const sim::SimulatedCapture clean = sim::Simulator(twin).Generate();
  sim::Scene scene = twin;
  if (!hidden.empty()) scene.hidden.Enable(hidden);
  const sim::SimulatedCapture capture = sim::Simulator(scene).Generate();
  std::vector<FitStation> stations = StationsOfSet(capture.poses, "calib");
  CandidateOptions options;
  // Test time: cross-validate the 2 best candidates by BIC (the rest are screened out, never
  // significant) and leave the flexible fallback to fit/candidates_test.
  options.cross_validate_top = 2;
  options.flexible.clear();
  const std::string model = RoomModel(twin, clean.noise_floor.at("calib"));
  PaperRun run{DiagnoseCandidates(stations, model, "room.yaml", "paper+" + hidden, options),
               scene.hidden};
  std::cout << "hidden " << (hidden.empty() ? "none" : hidden) << ", seed " << seed << ":\n"
            << FormatDiagnosis(run.diagnosis) << "\n";
  return run;
}

const ParameterReport& Block(const Candidate& c, const std::string& name) {
  for (const auto& p : c.parameters) {
    if (p.block == name) return p;
  }
  throw std::runtime_error(c.effect + ": no block " + name);
}

// |fitted - truth| within the 3-sigma level (99.73 %) for the block as a whole: with m coordinates
// each gets the Bonferroni-corrected two-sided level 0.27 % / m (3.0 sigma for one, 3.32 for three,
// 3.62 for nine). The sigmas come from the fit's covariance under the model file's constant noise,
// while the simulator's noise grows as r^4: they are approximate, hence no tighter claim.
void ExpectWithin3Sigma(const ParameterReport& p, const std::vector<double>& truth) {
  ASSERT_EQ(p.values.size(), truth.size()) << p.block;
  const double alpha = 0.0027 / static_cast<double>(truth.size());
  double lo = 0, hi = 10;  // z with erfc(z / sqrt(2)) = alpha, by bisection
  for (int i = 0; i < 60; ++i) {
    const double mid = 0.5 * (lo + hi);
    (std::erfc(mid / std::sqrt(2.0)) > alpha ? lo : hi) = mid;
  }
  for (size_t i = 0; i < truth.size(); ++i) {
    ASSERT_TRUE(std::isfinite(p.stddev[i])) << p.block << "[" << i << "]";
    EXPECT_LT(std::abs(p.values[i] - truth[i]), hi * p.stddev[i])
        << p.block << "[" << i << "] = " << p.values[i] << " +- " << p.stddev[i] << ", truth "
        << truth[i] << " (bound " << hi << " sigma)";
  }
}

const Candidate& ExpectTop(const Diagnosis& d, const std::string& effect) {
  EXPECT_FALSE(d.candidates.empty());
  const Candidate& top = d.candidates.front();
  EXPECT_EQ(top.effect, effect);
  EXPECT_TRUE(top.significant) << top.reason;
  EXPECT_EQ(d.verdict_effect.value_or(""), effect);
  return top;
}

// The toolbox: six calibration stations 0.285-0.32 m from it sit next to its fold zone, where the
// inverse amplifies report noise 30-45 times (station 350: 13.9 mm error under the TRUE model).
// With the model file's constant noise alone they dominated the cost and the searched dipole ended
// in a local minimum ((0.637, 0.916, -0.538) m, 0.00155 m^3, chi2/dof 218). The fit now whitens
// each station by the noise its inverse amplifies (fit/fit_engine.cc,
// noise.amplification_threshold): measured (0.60137, 0.94845, -0.50115) +- (0.0014, 0.0022, 0.0010)
// m, 0.001987 +- 0.000029 m^3 (truth (0.6, 0.95, -0.5), 0.002), held-out 4.27 -> 0.119 mm; 81 s
// wall, 12 s CPU under load.
// Disabled in session 4 after the search's variable projection landed: the dipole ranked first,
// held-out 4.27 -> 0.143 mm, but at (0.6039, 0.9440, -0.5044) +- (0.00066, 0.00074, 0.00096) m,
// 0.001934 +- 0.000014 m^3, 4-8 sigma from the truth: the cost was discontinuous at stations whose
// inverse did not converge near the object. With the station residual continuous (two Newton steps
// from the reference, PhysicalGroupTerm::EvaluateToward; the polynomial after the group is pulled
// back by fixed-point steps, fit/fit_engine.cc): (0.60021, 0.95027, -0.50014) +- (0.00015, 0.00022,
// 0.00011) m, 0.0020070 +- 0.0000038 m^3, held-out 4.27 -> 0.139 mm; 97 s wall under load. Since
// session 20 the residual is the report's misfit under the pose metric (fit/pose_metric.h).
TEST(DiagnoseCandidatesPaper, FerromagneticObject) {
  const PaperRun r = Diagnose("ferromagnetic_object", 20010313);
  const Candidate& top = ExpectTop(r.diagnosis, "dipole");
  if (top.effect != "dipole") return;
  const Eigen::Vector3d l = r.truth.object.location_in_transmitter;
  ExpectWithin3Sigma(Block(top, "location_in_transmitter"), {l.x(), l.y(), l.z()});
  ExpectWithin3Sigma(Block(top, "polarisability_m3"), {r.truth.object.polarisability_m3});
  EXPECT_THAT(top.model_change, ::testing::HasSubstr("location_in_transmitter: ["));
}

TEST(DiagnoseCandidatesPaper, Nominal_SensorOffset) {
  const PaperRun r = Diagnose("sensor_offset", 20010313);
  const Candidate& top = ExpectTop(r.diagnosis, "sensor_offset");
  if (top.effect != "sensor_offset") return;
  const Eigen::Vector3d t = r.truth.receiver_from_body.translation;
  ExpectWithin3Sigma(Block(top, "translation"), {t.x(), t.y(), t.z()});
  // Rotation: the angle between fitted and true rotation against the tangent-space sigmas (rad).
  const ParameterReport& q = Block(top, "rotation");
  const double angle = AngularDistance(QuaternionFromXyzwArray(q.values.data()),
                                       r.truth.receiver_from_body.rotation);
  double sigma = 0;
  for (double s : q.stddev) sigma = std::max(sigma, s);
  EXPECT_LT(angle, 3.0 * std::sqrt(3.0) * sigma) << "rotation off by " << angle << " rad";
}

TEST(DiagnoseCandidatesPaper, ReceiverGains) {
  const PaperRun r = Diagnose("receiver_gains", 20010313);
  const Candidate& top = ExpectTop(r.diagnosis, "receiver_gain");
  if (top.effect != "receiver_gain") return;
  // The room model ends in a polynomial, which absorbs a uniform gain (an isotropic scaling of
  // positions): the fit holds trace G = 3 (docs/model-file.md, gain_scale), so the truth is
  // compared as 3 G / trace(G).
  const Eigen::Matrix3d truth =
      3.0 * r.truth.receiver_gain_matrix / r.truth.receiver_gain_matrix.trace();
  std::vector<double> g;
  for (int i = 0; i < 3; ++i) {
    for (int j = 0; j < 3; ++j) g.push_back(truth(i, j));
  }
  ExpectWithin3Sigma(Block(top, "gain_matrix"), g);
}

TEST(DiagnoseCandidatesPaper, FiniteTransmitterCoils) {
  const PaperRun r = Diagnose("finite_transmitter_coils", 20010313);
  const Candidate& top = ExpectTop(r.diagnosis, "near_field");
  if (top.effect != "near_field") return;
  const Eigen::Vector3d o = r.truth.octupole_m2;
  ExpectWithin3Sigma(Block(top, "octupole_m2"), {o.x(), o.y(), o.z()});
}

TEST(DiagnoseCandidatesPaper, HemisphereFlipsCallForTheRobustLoss) {
  const PaperRun r = Diagnose("hemisphere_flips", 20010313);
  const Candidate& top = ExpectTop(r.diagnosis, "robust_loss");
  EXPECT_FALSE(top.outlier_stations.empty());
}

// The full paper capture with the hidden toolbox (ferromagnetic_object): its scene and calibration
// stations.
struct PaperToolbox {
  sim::Scene scene;
  std::vector<FitStation> stations;
};
PaperToolbox SimulatePaperToolbox(uint64_t seed) {
  PaperToolbox out{sim::LoadScene("paper"), {}};
  out.scene.seed = seed;
  out.scene.hidden.Enable("ferromagnetic_object");
  out.stations = StationsOfSet(sim::Simulator(out.scene).Generate().poses, "calib");
  return out;
}

// The paper's degree-4 polynomial on the paper capture with the toolbox 0.27 m from the grid's
// +y face (ferromagnetic_object, seed 3): under the robust loss the stations nearest the toolbox
// are 4.4-4.9 scales beyond the capture's errors (the Bonferroni threshold is ~4.5), but their
// neighbours' errors are almost as large. They are the object's field, not flips: the robust
// loss is not claimed (it was, before the neighbourhood test), and the reason points at them.
// The toolbox itself is claimed: its fit stops at the 100-iteration limit 15 mm from its optimum
// and is continued from there (it was not claimed before, "its fit did not converge").
TEST(DiagnoseCandidatesPaper, StationsNearAnObjectAreNotOutliersTheObjectIsClaimed) {
  const PaperToolbox paper = SimulatePaperToolbox(3);
  const sim::Scene& scene = paper.scene;
  const std::vector<FitStation>& stations = paper.stations;
  CandidateOptions options;
  options.effects = {"robust_loss", "dipole"};
  options.flexible.clear();
  const Diagnosis d = DiagnoseCandidates(stations, "terms:\n  - type: polynomial\n    degree: 4\n",
                                         "paper.yaml", "paper+toolbox", options);
  std::cout << FormatDiagnosis(d) << "\n";
  ASSERT_EQ(d.candidates.size(), 2u);
  EXPECT_EQ(d.verdict_effect.value_or("none"), "dipole") << d.verdict_text;
  const Candidate& dipole = d.candidates[d.candidates[0].effect == "dipole" ? 0 : 1];
  const Candidate& robust = d.candidates[d.candidates[0].effect == "dipole" ? 1 : 0];
  EXPECT_TRUE(dipole.converged) << dipole.reason;
  EXPECT_TRUE(dipole.significant) << dipole.reason;
  EXPECT_FALSE(robust.significant) << robust.reason;
  EXPECT_TRUE(robust.outlier_stations.empty()) << robust.reason;
  ASSERT_FALSE(robust.local_structure_stations.empty()) << robust.reason;
  EXPECT_THAT(robust.reason, ::testing::HasSubstr("not outliers"));
  // Every one of them within 0.5 m of the toolbox (the grid's nearest stations are 0.28 m away, its
  // step 0.15 m; since the loss scale is the stations' RMS, also for Ceres, station 109 at 0.465 m
  // is among them).
  const Eigen::Vector3d toolbox = scene.hidden.object.location_in_transmitter;
  for (int id : robust.local_structure_stations) {
    for (const FitStation& s : stations) {
      if (s.station == id) {
        EXPECT_LT((s.reference.translation - toolbox).norm(), 0.5) << id;
      }
    }
  }

  // The next step, with the toolbox where that step put it: the workbench frame. Its runtime
  // inverse finds no root at a few stations next to the toolbox (75 mm off at station 350), which
  // alone made delta BIC +2792; they are left out of the BIC (and of the held-out comparison) and
  // the frame is claimed.
  CandidateOptions next = options;
  next.effects = {"dipole"};
  const Diagnosis after = DiagnoseCandidates(
      stations,
      "terms:\n  - type: dipole\n    location_in_transmitter: [0.6420, 0.9136, -0.4455]\n"
      "    polarisability_m3: 0.001338\n  - type: polynomial\n    degree: 4\n",
      "paper_toolbox.yaml", "paper+toolbox", next);
  std::cout << FormatDiagnosis(after) << "\n";
  ASSERT_EQ(after.candidates.size(), 1u);
  const Candidate& frame = after.candidates[0];
  EXPECT_TRUE(frame.significant) << frame.reason;
  EXPECT_GT(frame.bic_unresolved_left_out, 0) << frame.reason;
  const Eigen::Vector3d frame_truth(0.5, 0.0, 0.35);  // sim/scenes/paper.yaml, workbench_frame
  ASSERT_FALSE(frame.parameters.empty());
  EXPECT_LT((Eigen::Vector3d(frame.parameters[0].values.data()) - frame_truth).norm(), 0.1)
      << frame.statement;
}

// The demo's loop on the full paper capture (ferromagnetic_object, seed 2), after the workbench
// frame and the toolbox (their fitted values), on the 4-height base with `ridge: auto`: 26
// stations within ~0.35 m of the toolbox are ambiguous or unresolved under the runtime inverse,
// their errors 5-22 mm and up to 175 mm under a candidate. Counted, they made the background's
// delta BIC +485 and its held-out position error fall only 3.9 % (orientation +4.4 %), and the
// loop stopped at 12.5x the noise floor with the floor, the door and the monitors unmodelled. Left
// out of both comparisons, the background lowers the held-out error by 11.6 % and is claimed.
// The floor plane's fit from its searched strength ended above the base's cost (delta BIC +1031: a
// nested model fitting worse); grown from near zero where it was placed, it ends below it.
TEST(DiagnoseCandidatesPaper, StationsTheInverseCannotResolveDoNotDecideAComparison) {
  const std::vector<FitStation> stations = SimulatePaperToolbox(2).stations;
  CandidateOptions options;
  options.effects = {"background_field", "plane"};
  options.flexible.clear();
  const Diagnosis d = DiagnoseCandidates(
      stations,
      "terms:\n  - type: dipole\n    location_in_transmitter: [0.5078, -0.0242, 0.3584]\n"
      "    polarisability_m3: -0.008322\n  - type: dipole\n    name: dipole_2\n"
      "    location_in_transmitter: [0.5883, 0.9719, -0.5163]\n    polarisability_m3: 0.00267\n"
      "  - type: polynomial\n    degree: 4\n    ridge: auto\n",
      "paper_frame_toolbox.yaml", "paper+toolbox", options);
  std::cout << FormatDiagnosis(d) << "\n";
  const Candidate* background = nullptr;
  const Candidate* plane = nullptr;
  for (const Candidate& c : d.candidates) {
    if (c.effect == "background_field") background = &c;
    if (c.effect == "plane" && c.replaces.empty()) plane = &c;
  }
  ASSERT_NE(background, nullptr);
  ASSERT_NE(plane, nullptr);
  EXPECT_GT(background->cv_unresolved_left_out, 0) << background->reason;
  EXPECT_GT(background->bic_unresolved_left_out, 0) << background->reason;
  EXPECT_TRUE(background->significant) << background->reason;
  EXPECT_LT(background->delta_bic, options.max_delta_bic) << background->reason;
  EXPECT_THAT(background->reason, ::testing::HasSubstr("an ambiguous one"));
  // At most max_unresolved_fraction of the 480 stations (25 measured), and the same stations for
  // every candidate (the base's).
  EXPECT_LE(background->cv_unresolved_left_out, 48) << background->reason;
  if (plane->cross_validated) {
    EXPECT_EQ(plane->cv_unresolved_left_out, background->cv_unresolved_left_out) << plane->reason;
  }
  // Not a claim (its normal is too vague: 8.1 deg), but a fit at least as good as the base's: the
  // plane's 4 parameters cost about 4 ln(2880) = 32 BIC points, measured -1429 from the base's
  // optimum (+1031 from its searched strength). The background is claimed although the plane
  // explains more: a catch-all is not held back as a stand-in.
  EXPECT_LT(plane->delta_bic, 32.0) << plane->reason;
}

// Under the TRUE model of the paper room with the toolbox (each source fixed at its value), a few
// calibration stations 0.28-0.33 m from the toolbox are ambiguous under the runtime inverse (its
// fold amplifies the report noise: 16 mm at station 350 where the others are 0.1-0.2 mm). They are
// not outliers, and nothing is left to claim. Measured before such stations were kept out of the
// outlier test: on both seeds the robust loss was claimed for stations 131 and 350 as "hemisphere
// flips or bad reference poses" (held-out error of the kept stations -28.5 / -28.4 %, p = 1.4e-6 /
// 1e-5, delta BIC -9020 / -9233); the demo's loop (seed 2) claimed it at its last step for 350.
TEST(DiagnoseCandidatesPaper, StationsTheInverseCannotResolveAreNotOutliers) {
  for (uint64_t seed : {2u, 3u}) {
    sim::Scene scene = sim::LoadScene("paper");
    scene.seed = seed;
    scene.hidden.Enable("ferromagnetic_object");
    const sim::SimulatedCapture capture = sim::Simulator(scene).Generate();
    sim::Scene room = scene;
    room.environment.objects.push_back(scene.hidden.object);
    CandidateOptions options;
    options.effects = {"robust_loss"};
    options.flexible.clear();
    const Diagnosis d = DiagnoseCandidates(StationsOfSet(capture.poses, "calib"),
                                           RoomModel(room, capture.noise_floor.at("calib")),
                                           "room_toolbox.yaml", "paper+toolbox", options);
    std::cout << "seed " << seed << ":\n" << FormatDiagnosis(d) << "\n";
    ASSERT_EQ(d.candidates.size(), 1u) << seed;
    const Candidate& robust = d.candidates[0];
    EXPECT_FALSE(robust.significant) << "seed " << seed << ": " << robust.reason;
    EXPECT_TRUE(robust.outlier_stations.empty()) << "seed " << seed << ": " << robust.reason;
    // The stations were there to be mistaken (when the inverse resolves every station, the test
    // shows nothing): left out of the held-out comparison, as for every candidate.
    EXPECT_GT(robust.cv_unresolved_left_out, 0) << "seed " << seed << ": " << robust.reason;
    EXPECT_FALSE(d.verdict_effect.has_value()) << "seed " << seed << ": " << d.verdict_text;
  }
}

TEST(DiagnoseCandidatesPaper, NothingIsClaimedWithoutAHiddenEffect) {
  for (uint64_t seed : {20010313u, 1u, 2u}) {
    const PaperRun r = Diagnose("", seed);
    for (const Candidate& c : r.diagnosis.candidates) {
      EXPECT_FALSE(c.significant) << "seed " << seed << ": " << c.effect << ": " << c.reason;
    }
    EXPECT_FALSE(r.diagnosis.verdict_effect.has_value()) << seed;
  }
}

// The workflow loop's capture (tests/data/workflow/paper_small.yaml, python/tests/test_workflow.py):
// the paper room with an 8 x 6 x 5 grid at 0.15 m and 60 validation stations.
constexpr char kPaperSmall[] = R"(base: paper
name: paper_small
capture:
  calibration:
    origin_in_transmitter: [-0.525, -0.375, -0.875]
    counts: [8, 6, 5]
    spacing_m: 0.15
  validation:
    count: 60
    min_in_transmitter: [-0.525, -0.375, -0.875]
    max_in_transmitter: [0.525, 0.375, -0.275]
  registration:
    count: 6
  stream:
    duration_s: 30
)";

Diagnosis DiagnosePaperSmall(const std::string& hidden, uint64_t seed, const std::string& model,
                             sim::Scene* scene) {
  *scene = sim::ParseScene(kPaperSmall, "paper_small.yaml");
  scene->seed = seed;
  scene->hidden.Enable(hidden);
  const sim::SimulatedCapture capture = sim::Simulator(*scene).Generate();
  CandidateOptions options;
  options.cross_validate_top = 2;  // as the loop (python/trackcal/demo.py)
  options.flexible.clear();
  const Diagnosis d = DiagnoseCandidates(StationsOfSet(capture.poses, "calib"), model, "step2.yaml",
                                         "paper_small+" + hidden, options);
  std::cout << FormatDiagnosis(d) << "\n";
  return d;
}

// The floor plane of the paper room and the checks of the workflow test's room matching
// (test_workflow.py ROOM_MATCH_M, ROOM_MATCH_DEG: a quarter of the distances and angles between the
// room's sources).
void ExpectTheFloor(const sim::Scene& scene, const Candidate& plane) {
  const ConductingPlane* floor = nullptr;
  for (const auto& p : scene.environment.planes) {
    if (p.name == "floor_reinforcement") floor = &p;
  }
  ASSERT_NE(floor, nullptr);
  const Eigen::Vector3d n_true = floor->normal_in_transmitter.normalized();
  const ParameterReport& n = Block(plane, "normal_in_transmitter");
  const Eigen::Vector3d n_fit = Eigen::Vector3d(n.values[0], n.values[1], n.values[2]).normalized();
  EXPECT_LT(std::acos(std::min(1.0, std::abs(n_fit.dot(n_true)))) * kDegPerRad, 22.5);
  EXPECT_NEAR(std::abs(Block(plane, "distance_m").values[0]),
              std::abs(floor->point_in_transmitter.dot(n_true)), 0.15);
  EXPECT_TRUE(plane.evidence.supported()) << plane.evidence.Describe();
}

// The loop's third diagnosis (hidden sensor offset, seed 1): the model has the sensor offset and the
// workbench frame (at the start values its second diagnosis printed) before the paper's degree-4
// polynomial, with the default noise model. What remains is the floor (0.8 m along +z, attenuation
// 0.27). Before the physical conditions of the claim rule, a dipole near (-0.12, -0.29, 1.40) m, the
// floor's mirror image, was ranked first (held-out error -53 % against the plane's -54 %, its
// polarisability -0.33 +- 0.66 m^3 with the model's 1 mm noise) and the plane never came.
TEST(DiagnoseCandidatesPaperSmall, TheFloorIsClaimedAsAPlane) {
  const std::string model = R"(terms:
  - type: sensor_offset
  - type: dipole
    location_in_transmitter: [0.4412, -0.0054, 0.4199]
    polarisability_m3: -0.0133
  - type: polynomial
    degree: 4
)";
  sim::Scene scene;
  const Diagnosis d = DiagnosePaperSmall("sensor_offset", 1, model, &scene);
  const Candidate& top = ExpectTop(d, "plane");
  if (top.effect != "plane") return;
  ExpectTheFloor(scene, top);
  // And the attenuation within 3 of the fit's standard deviations.
  for (const auto& p : scene.environment.planes) {
    if (p.name == "floor_reinforcement") ExpectWithin3Sigma(Block(top, "attenuation"), {p.attenuation});
  }
}

// The loop's third diagnosis with hidden hemisphere flips (seed 1): the model has the robust loss
// and the workbench frame (the start values its second diagnosis printed). The calibration set has
// two flipped stations, whose reports (-p) lie beyond the transmitter on the floor's side with
// whitened residuals ~1e3 where the others are ~1-10. They chose the plane search's start (a plane
// at -2.07 m, attenuation 1.26) and kept the floor out of its range, so the floor's mirror image was
// claimed as a dipole, (-0.004, 0.085, 1.456) m, -0.47 +- 0.14 m^3. The search leaves gross
// outliers out (fit/terms_physical.cc, GrossOutlierMask): the floor is found (0.72 m, attenuation
// 0.26 +- 0.04) and claimed as a plane.
TEST(DiagnoseCandidatesPaperSmall, HemisphereFlipsDoNotHideTheFloor) {
  sim::Scene scene;
  const Diagnosis d = DiagnosePaperSmall("hemisphere_flips", 1, R"(loss: {type: cauchy, scale: 3}
terms:
  - type: dipole
    location_in_transmitter: [0.4752, 0.0001, 0.3961]
    polarisability_m3: -0.01247
  - type: polynomial
    degree: 4
)",
                                         &scene);
  const Candidate& top = ExpectTop(d, "plane");
  if (top.effect == "plane") ExpectTheFloor(scene, top);
}

// The loop's third diagnosis with hidden receiver gains (seed 1): the model has the receiver gain
// and the workbench frame. The plane search found the floor (0.61 m along z), but the group's
// refinement, which fits without the polynomial, moved the frame off to 2.5e5 m and the plane onto
// the frame's mirror plane (0.32 m along (0.73, 0.01, 0.68)), a joint chi2/dof of 0.0117 against
// 0.0023 with the frame and the floor; the floor's mirror image was then claimed as a dipole. The
// refinement is now also run with the sources' locations standing and the one with the lower cost
// after the polynomial is kept (fit/terms_physical.cc, RefineGroup).
TEST(DiagnoseCandidatesPaperSmall, ReceiverGainsTheFloorIsAPlaneAndTheFrameStays) {
  sim::Scene scene;
  const Diagnosis d = DiagnosePaperSmall("receiver_gains", 1, R"(terms:
  - type: receiver_gain
  - type: dipole
    location_in_transmitter: [0.4478, 0.0068, 0.4167]
    polarisability_m3: -0.01394
  - type: polynomial
    degree: 4
)",
                                         &scene);
  const Candidate& top = ExpectTop(d, "plane");
  if (top.effect == "plane") ExpectTheFloor(scene, top);
}

// The workflow loop's third diagnosis with the hidden sensor offset, seed 3: the model has the sensor
// offset and the workbench frame (the start values its second diagnosis printed). The floor plane
// (0.733 m, attenuation 0.212 +- 0.019, 11.4 sigma) and a dipole at the floor's mirror image
// ((-0.06, -0.26, 1.35) m, -0.28 +- 0.05 m^3, 5.3 sigma) have equal held-out errors and fit all
// stations within 6.8 of each other (delta BIC -2355.7 against -2362.5): the likelihood does not
// decide, so the better-determined strength does, and the floor is a plane. main ranked the dipole
// first by its lower BIC, a spurious term.
TEST(DiagnoseCandidatesPaperSmall, TheFloorIsAPlaneWhenTheLikelihoodsTie) {
  sim::Scene scene;
  const Diagnosis d = DiagnosePaperSmall("sensor_offset", 3, R"(terms:
  - type: sensor_offset
  - type: dipole
    location_in_transmitter: [0.4437, -0.0070, 0.4189]
    polarisability_m3: -0.01331
  - type: polynomial
    degree: 4
)",
                                         &scene);
  const Candidate& top = ExpectTop(d, "plane");
  if (top.effect == "plane") ExpectTheFloor(scene, top);
}

// The main job's fourth diagnosis (`./scripts/demo.sh --no-serve`: paper_small, hidden sensor
// offset, the scene's seed 20010313), with the model its loop had then: the sensor offset, the
// workbench frame and the floor (the start values its diagnoses printed) before the paper's
// polynomial, at 1.50x the noise floor. What remains are the room's far sources: three CRT monitors
// 1.9 m away and the door 2.1 m away. main claimed a permeable plane 1.70 m +- 0.14 along
// (0.46, 0.84, 0.28), attenuation -0.34 +- 0.075 (4.5 sigma), for the +y monitors, which are
// objects: its position at the volume passed condition 5 (+- 0.24 m, 1.20 m away), its normal was
// open by 19.9 deg. A plane whose orientation the data do not fix is no particular wall, so it is
// not claimed (before background_field was in the catalog, the verdict said that structure comes
// from +y and that its source is not identified). The distant sources are what background_field
// stands for, and it is claimed: held-out position error -21.5 %, p = 2.9e-16, coefficients 12.9
// sigma from zero (measured).
TEST(DiagnoseCandidatesPaperSmall, FarMonitorsAreNotClaimedAsAPlane) {
  sim::Scene scene;
  const Diagnosis d = DiagnosePaperSmall("sensor_offset", 20010313u, R"(terms:
  - type: sensor_offset
  - type: dipole
    location_in_transmitter: [0.4470, -0.0106, 0.4148]
    polarisability_m3: -0.01278
  - type: plane
    point_in_transmitter: [-0.0549, -0.1937, 0.8072]
    normal_in_transmitter: [-0.06594, -0.23283, 0.97028]
    attenuation: 0.2617
  - type: polynomial
    degree: 4
)",
                                         &scene);
  EXPECT_EQ(d.verdict_effect.value_or("none"), "background_field") << d.verdict_text;
  const Candidate* plane = nullptr;
  for (const Candidate& c : d.candidates) {
    if (c.effect != "background_field") {
      EXPECT_FALSE(c.significant) << c.effect << ": " << c.reason;
    }
    if (c.effect == "plane" && c.replaces.empty()) plane = &c;  // the addition, not a swap
  }
  ASSERT_NE(plane, nullptr);
  // The structure is there (the held-out statistics), the plane does not place its source.
  EXPECT_TRUE(plane->cross_validated) << plane->reason;
  EXPECT_LT(plane->p_value, d.p_threshold) << plane->reason;
  EXPECT_LT(plane->delta_bic, -10.0) << plane->reason;
  EXPECT_FALSE(plane->evidence.normal_ok) << plane->evidence.Describe();
  EXPECT_GT(plane->evidence.direction.y(), 0.5) << plane->evidence.Describe();
  EXPECT_THAT(plane->reason, ::testing::HasSubstr("its normal is not determined"));
  EXPECT_THAT(d.verdict_text, ::testing::HasSubstr("distant sources"));
}

// The sensor offset, the workbench frame and dipole_2 at the floor's mirror image of the
// transmitter, as the seed-4 loop (hidden sensor offset) had them after its third diagnosis.
constexpr const char* kSeed4Sources = R"(terms:
  - type: sensor_offset
  - type: dipole
    location_in_transmitter: [0.4550, 0.0012, 0.4149]
    polarisability_m3: -0.01339
  - type: dipole
    name: dipole_2
    location_in_transmitter: [-0.0380, -0.2601, 1.3261]
    polarisability_m3: -0.2569)";

// The workflow loop with the hidden sensor offset, seed 4: its third diagnosis added a dipole at the
// floor's mirror image of the transmitter before the plane (delta BIC -2050.2 against -2037.9,
// held-out errors 4.6 % apart), and the fourth added the background field. This is the model the
// loop then had (the start values its diagnoses printed). Swapped for a plane in its place, the
// floor fits all stations 28.9 BIC points better and the held-out errors do not rise (0.1 %, 0.3 %
// lower; since the report-space residual, 27.1 points, 0.2 % lower and 0.1 % higher, a tie): the
// replacement is claimed, and the plane is the floor. Swapping the workbench frame for a
// plane costs 1547 BIC points and is not.
TEST(DiagnoseCandidatesPaperSmall, AFloorTakenForADipoleIsReplacedByAPlane) {
  sim::Scene scene;
  const Diagnosis d = DiagnosePaperSmall("sensor_offset", 4, std::string(kSeed4Sources) + R"(
  - type: background_field
  - type: polynomial
    degree: 4
)",
                                         &scene);
  const Candidate& top = ExpectTop(d, "plane");
  if (top.effect != "plane") return;
  EXPECT_EQ(top.replaces, "dipole_2");
  ASSERT_TRUE(top.insert_index.has_value());
  EXPECT_EQ(*top.insert_index, 2);
  ExpectTheFloor(scene, top);
  EXPECT_LT(top.delta_bic, -10.0) << top.reason;
  // No higher held-out error beyond the rule's tie (0.5 %; measured since the report-space
  // residual: 0.2 % lower, 0.1 % higher).
  EXPECT_GE(top.drop_position_percent, -0.5) << top.reason;
  EXPECT_GE(top.drop_orientation_percent, -0.5) << top.reason;
  // The candidate model has the plane where dipole_2 was, and the frame.
  const YAML::Node terms = YAML::Load(top.model_text)["terms"];
  ASSERT_EQ(terms.size(), 5u);
  EXPECT_EQ(terms[1]["type"].as<std::string>(), "dipole");
  EXPECT_EQ(terms[2]["type"].as<std::string>(), "plane");
  const nlohmann::json doc = d.ToJson();
  EXPECT_EQ(doc["verdict"]["replaces"], "dipole_2");
  EXPECT_EQ(doc["candidates"][0]["replaces"], "dipole_2");
  EXPECT_THAT(FormatDiagnosis(d), ::testing::HasSubstr("replace `terms:` item 2 (dipole_2"));
  for (const Candidate& c : d.candidates) {
    if (c.replaces == "dipole") {
      EXPECT_FALSE(c.significant) << c.reason;
      EXPECT_GT(c.delta_bic, 100.0) << c.reason;
    }
  }
}

// The same capture one diagnosis earlier, before the background field, with the door given as a
// known plane held fixed: the background is what is missing (claimed); swapping dipole_2 for a plane
// then fits worse (delta BIC +78.8: without the background the dipole takes part of it), so the
// replacement is weighed and not claimed, and the held door is not swapped at all.
TEST(DiagnoseCandidatesPaperSmall, AHeldPlaneStaysAndASwapThatFitsWorseIsNotClaimed) {
  sim::Scene scene;
  const Diagnosis d = DiagnosePaperSmall("sensor_offset", 4, std::string(kSeed4Sources) + R"(
  - type: plane
    name: door
    point_in_transmitter: [0, -2.1, 0]
    normal_in_transmitter: [0, 1, 0]
    attenuation: 0.18
    parameters:
      distance_m: {fixed: true}
      normal_in_transmitter: {fixed: true}
      attenuation: {fixed: true}
  - type: polynomial
    degree: 4
)",
                                         &scene);
  ExpectTop(d, "background_field");
  int swaps_of_dipole_2 = 0;
  for (const Candidate& c : d.candidates) {
    EXPECT_NE(c.replaces, "door") << "a held plane is not swapped";
    if (c.replaces == "dipole_2") {
      ++swaps_of_dipole_2;
      EXPECT_EQ(c.effect, "plane");
      EXPECT_FALSE(c.significant) << c.reason;
      EXPECT_GT(c.delta_bic, 0.0) << c.reason;
    }
  }
  EXPECT_EQ(swaps_of_dipole_2, 1);
}

}  // namespace
}  // namespace trackcal::fit
