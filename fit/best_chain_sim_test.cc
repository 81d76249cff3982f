// Acceptance of issue #5's best chain on the simulator's paper preset without hidden effects: a
// chain found without truth values reaches a validation error within 1.5 times the noise floor (the
// error the true model leaves on the same data, truth.json's statistics.valid.noise_floor). Every
// figure is of the calibration file as trackcal-fit writes it (its calibrated volume included):
// what the server applies.
#include <gtest/gtest.h>

#include <Eigen/Dense>
#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <cstdlib>
#include <ctime>
#include <filesystem>
#include <fstream>
#include <iomanip>
#include <iostream>
#include <limits>
#include <sstream>

#include "core/calibration_file.h"
#include "core/error_statistics.h"
#include "core/polynomial.h"
#include "fit/chain_builder.h"
#include "fit/fit_engine.h"
#include "fit/model_file.h"
#include "fit/sim_test_support.h"
#include "fit/terms_polynomial.h"
#include "sim/scene.h"
#include "sim/simulator.h"

namespace trackcal::fit {
namespace {

struct PaperCapture {
  std::vector<FitStation> calibration, validation;
  PoseErrorSummary floor;  // noise floor on the validation set
  // Per validation station, the error the true model leaves (tracker and reference noise only,
  // as the simulator computes the floor): position [mm], orientation [deg].
  std::vector<double> floor_position_mm, floor_orientation_deg;
};

PaperCapture Simulate(uint64_t seed) {
  sim::Scene scene = sim::LoadScene("paper");
  scene.seed = seed;
  const sim::SimulatedCapture capture = sim::Simulator(scene).Generate();
  PaperCapture out;
  for (size_t i = 0; i < capture.poses.records.size(); ++i) {
    const auto& r = capture.poses.records[i];
    const FitStation s{r.reported, r.reference, r.time, r.sensor, r.station};
    if (r.set == "calib") out.calibration.push_back(s);
    if (r.set != "valid") continue;
    out.validation.push_back(s);
    const sim::StationTruth& t = capture.stations[i];
    const Eigen::Vector3d floor_p =
        (r.reference.translation - r.reported.translation) -
        (t.transmitter_from_body.translation - t.reported_noise_free.translation);
    const Eigen::Quaterniond e_capture = r.reference.rotation * r.reported.rotation.conjugate();
    const Eigen::Quaterniond e_model =
        t.transmitter_from_body.rotation * t.reported_noise_free.rotation.conjugate();
    out.floor_position_mm.push_back(1e3 * floor_p.norm());
    out.floor_orientation_deg.push_back(kDegPerRad * AngularDistance(e_capture, e_model));
  }
  out.floor = capture.noise_floor.at("valid");
  return out;
}

// Validation means of a correction over the floor's, overall and split by whether the station's
// reported position lies inside the calibrated volume (the calibration stations' box).
struct Outcome {
  double position_ratio = 0, orientation_ratio = 0, seconds = 0;
  double inside_position_ratio = 0, inside_orientation_ratio = 0;
  double outside_position_ratio = 0, outside_orientation_ratio = 0;
  int outside = 0;
};

// The calibration file exactly as trackcal-fit writes it (the chain with its calibrated volume),
// through the file format and back: what the server applies.
Calibration WrittenFile(const FitResult& fit) {
  Calibration cal;
  cal.chain = fit.chain;
  cal.provenance.tool = "best_chain_sim_test";
  cal.provenance.tool_version = "test";
  cal.provenance.created_utc = CurrentUtcTimestamp();
  return ParseCalibrationJson(CalibrationToJsonText(cal), "best_chain.json");
}

Outcome Validate(const PaperCapture& data, const CorrectionChain& chain,
                 const CalibratedVolume& box, const std::string& name, bool print_worst) {
  double sum[2][2] = {{0, 0}, {0, 0}}, floor_sum[2][2] = {{0, 0}, {0, 0}};  // [outside][pos/ori]
  int count[2] = {0, 0};
  struct Row {
    double position_mm, orientation_deg, floor_mm, outside_mm;
    int station;
  };
  std::vector<Row> rows;
  for (size_t i = 0; i < data.validation.size(); ++i) {
    const FitStation& s = data.validation[i];
    const Rigid3d corrected = chain.Apply(s.reported).pose;
    const double p = 1e3 * PositionErrorNorm(corrected, s.reference);
    const double o = kDegPerRad * OrientationErrorAngle(corrected, s.reference);
    const double d = 1e3 * (s.reported.translation - box.Nearest(s.reported.translation)).norm();
    const int k = d > 0 ? 1 : 0;
    sum[k][0] += p;
    sum[k][1] += o;
    floor_sum[k][0] += data.floor_position_mm[i];
    floor_sum[k][1] += data.floor_orientation_deg[i];
    ++count[k];
    rows.push_back({p, o, data.floor_position_mm[i], d, s.station});
  }
  Outcome out;
  out.outside = count[1];
  out.position_ratio = (sum[0][0] + sum[1][0]) / (floor_sum[0][0] + floor_sum[1][0]);
  out.orientation_ratio = (sum[0][1] + sum[1][1]) / (floor_sum[0][1] + floor_sum[1][1]);
  out.inside_position_ratio = sum[0][0] / floor_sum[0][0];
  out.inside_orientation_ratio = sum[0][1] / floor_sum[0][1];
  if (count[1] > 0) {
    out.outside_position_ratio = sum[1][0] / floor_sum[1][0];
    out.outside_orientation_ratio = sum[1][1] / floor_sum[1][1];
  }
  const double n = static_cast<double>(data.validation.size());
  std::cout << std::setprecision(3) << name << ": validation " << (sum[0][0] + sum[1][0]) / n
            << " mm / " << (sum[0][1] + sum[1][1]) / n << " deg = " << out.position_ratio << "x / "
            << out.orientation_ratio << "x the floor; inside the box (" << count[0] << ") "
            << out.inside_position_ratio << "x / " << out.inside_orientation_ratio << "x; outside ("
            << count[1] << ") " << out.outside_position_ratio << "x / "
            << out.outside_orientation_ratio << "x\n";
  if (print_worst) {
    std::sort(rows.begin(), rows.end(), [](const Row& a, const Row& b) {
      return a.position_mm - a.floor_mm > b.position_mm - b.floor_mm;
    });
    std::cout << "  worst (station: mm against the floor's, deg, mm outside the box):";
    for (size_t i = 0; i < std::min<size_t>(6, rows.size()); ++i) {
      std::cout << " " << rows[i].station << ": " << rows[i].position_mm << "/" << rows[i].floor_mm
                << ", " << rows[i].orientation_deg << ", " << rows[i].outside_mm << ";";
    }
    std::cout << "\n";
  }
  return out;
}

// Fits `model` to the calibration set and validates the calibration file as written (the
// polynomial and LUT clamped outside the calibrated volume, physical terms at the actual pose);
// `also_unguarded` prints the same chain without the volume for comparison.
Outcome FitAndValidate(const PaperCapture& data, const std::string& model, const std::string& name,
                       bool also_unguarded = false) {
  ModelSpec spec = ParseModelYaml(model, name);
  FitOptions options;
  options.compute_covariance = false;
  const auto start = std::chrono::steady_clock::now();
  const FitResult fit = FitModel(data.calibration, &spec, options);
  const double seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  const Calibration file = WrittenFile(fit);
  Outcome o = Validate(data, file.chain, file.volume(), name + " (file)", true);
  o.seconds = seconds;
  if (also_unguarded) {
    CorrectionChain chain = file.chain;
    chain.ClearVolume();
    Validate(data, chain, file.volume(), name + " (no volume)", false);
    if (chain.size() >= 2 && !chain.term(0).GuardedByVolume()) {
      // The volume as the box of what the explicit terms receive (the physical group's output)
      // rather than of the reported positions.
      CalibratedVolume inputs = file.volume();
      inputs.min = inputs.max = chain.term(0).Apply(data.calibration[0].reported).pose.translation;
      for (const auto& s : data.calibration) {
        const Eigen::Vector3d p = chain.term(0).Apply(s.reported).pose.translation;
        inputs.min = inputs.min.cwiseMin(p);
        inputs.max = inputs.max.cwiseMax(p);
      }
      chain.SetVolume(inputs);
      Validate(data, chain, file.volume(), name + " (volume of the explicit terms' inputs)", true);
    }
  }
  std::cout << "  " << fit.iterations << " iterations, " << o.seconds << " s\n";
  for (const auto& t : fit.terms) {
    if (t.value("type", "") != "lut") std::cout << "  " << t.dump() << "\n";
  }
  for (const auto& p : fit.parameters) {
    if (p.term == "polynomial" || p.block.rfind("node_values", 0) == 0) continue;
    std::cout << "  " << p.term << "." << p.block << " =";
    for (double v : p.values) std::cout << " " << v;
    std::cout << "\n";
  }
  return o;
}

// The noise model a user writes for an EM tracker without knowing the truth: sigma grows as r^4 in
// position and r^3 in orientation (a dipole field falls as r^-3); 0.25 mm / 0.04 deg at 1 m is the
// order of the paper preset's scatter.
constexpr const char* kNoise =
    "noise: {position_mm: 0.25, orientation_deg: 0.04, position_range_exponent: 4, "
    "orientation_range_exponent: 3}\n"
    "solver: {max_iterations: 300, covariance: false}\n";

// The paper's method: a degree-4 polynomial alone, fitted by plain least squares (eq. 8-9: every
// station weighted alike). Without kNoise: its range exponents weight a station by r^-8 (position)
// and r^-6 (orientation), which is not the paper's fit; the baseline fitted so was 10.0 mm on seed
// 1 against 2.77 mm unweighted (PaperBaselineIsPlainLeastSquares).
constexpr const char* kPaperPolynomial = "terms:\n  - type: polynomial\n    degree: 4\n";

// The model file every baseline of this file fits as "the paper's".
std::string PaperBaselineModel() { return kPaperPolynomial; }

// Validation means over the floor's, measured with the calibration file as trackcal-fit writes it
// (the polynomial clamped outside the calibrated volume, the physical group at the actual pose;
// "unclamped": the same chain without the volume), this file's Explore and ChainChosen:
//                                                     seed 1          seed 2          seed 3
//   true room held fixed + degree 1 ............... 1.12x / 1.00x   1.05x / 1.02x   1.04x / 1.05x
//   searched dipole + plane, degree 8, ridge 0.25 . 1.97x / 1.47x   2.68x / 1.89x   4.13x / 2.05x
//     unclamped ................................... 1.75x / 1.41x   2.30x / 1.74x   2.88x / 1.75x
//     inside the calibration box .................. 1.39x / 1.19x   1.78x / 1.31x   1.51x / 1.27x
//     outside it (19 / 34 / 26 of 120 stations) ... 4.02x / 2.76x   3.93x / 3.18x   11.5x / 4.34x
//   the same after the search's variable projection (session 4), clamped:
//                                                   2.34x / 1.81x   4.19x / 2.54x   4.59x / 2.29x
//     inside the calibration box .................. 1.60x / 1.36x   2.94x / 1.66x   1.88x / 1.44x
//     outside it .................................. 4.94x / 3.88x   5.91x / 4.49x   12.2x / 4.79x
//   the same fits, the linear policy (reach 0.1 m; PoliciesOnSavedFits, session 5):
//                                                   2.03x / 1.70x   3.73x / 2.28x   2.97x / 1.73x
//     outside the box ............................. 3.54x / 3.28x   4.82x / 3.65x   6.03x / 2.60x
//     reach 0.01 / 0.03 / 1 m, position, all ...... 2.25 2.09 2.03  3.98 3.78 3.73  4.28 3.79 2.91
//     fade over 0.1 m ............................. 3.26x / 2.30x   6.16x / 3.75x   10.2x / 5.08x
//     the paper's degree-4 polynomial alone (unweighted, as the paper fits it), clamp / linear
//     0.1 m / fade 0.1 m, position, all:   30.8/28.6/48.7x 29.6/26.6/73.9x 31.5/31.3/51.1x
//     (the 111/124/116x, 118/143/143x, 115/142/119x measured here before were of the polynomial
//     fitted with kNoise's range weights, not the paper's fit; trackcal-fit writes linear only for
//     chains with a physical term, fit_engine.cc VolumeOf, a choice made on those figures)
//     seed 3's station 583 (57 mm out): 13.4 mm clamped, 1.66 mm linear; seed 2's worst outside
//     stations (578: 3.7 mm, 56 mm out) do not change: what is left there is not the extrapolation
//     of the explicit terms.
//   same, ridge: auto, blocked CV (3.2 / 3.2 chosen) 4.54x / 2.59x
//   same, ridge: auto, leave-one-out (0.01 / 0.32) . 609x / 24.4x: it cannot see between the layers
//   ChainChosen: degree by blocked CV (8), ridge: auto (3.2 / 1.0) 4.53x / 1.71x
//   ChainChosen after the search's variable projection, linear policy (session 5): degree 8, ridge
//     0.1 / 0.1, 0.32 / 0.32, 0.1 / 0.1 ........... 3.00x / 3.22x   3.21x / 2.01x   2.86x / 1.68x
//     ridge: auto's blocked CV predicting held-out slabs to first order as the runtime (a build
//     passing linear_reach 0.1 in InitializeLinear; not kept):
//     position ridge 0.1 on all three ........... 3.00x / 3.22x   12.9x / 2.26x   5.20x / 4.36x
//   ChainChosen's second pass: the weight chosen again by blocked CV on what the joint fit's group
//     leaves (0.32), refitted: 76x / 31x: the joint fit moved the plane off (normal (0.95, -0.30,
//     0.07), attenuation 0.001) and let the polynomial take its part
// Earlier, unclamped (session 3): degree 6 ridge 0.25 4.0x / 2.0x; degree 4 + LUT 2.3-2.6x; 6
// searched sources + degree 2 5.5x / 3.3x.
// Where the error is left: the stations outside the calibrated volume (the box of the calibration
// stations' reported positions; the preset's validation box is 75 mm larger on every side) at
// 3.9-11.5x in position, where the clamped polynomial holds the boundary value of what only the far
// sources (the CRT monitors, the door) explain and the search does not find; inside the box
// 1.4-1.8x. On seed 3 one station 57 mm outside (583) is 13.9 mm off, a third of the mean. The
// clamp itself costs there: without the volume the chain is at 1.75-2.88x on the three seeds, and
// with the volume taken as the box of the explicit terms' inputs (the group's output, Explore's
// third line) rather than of the reported positions it is worse, 5.25x on seed 3 (583: 16.9 mm).
// The true room (every source modelled physically) is at 1.0-1.1x
// inside and outside alike. Session 5: the linear policy (the first-order continuation of the
// explicit terms, now the default) takes the outside stations to 3.5-6.0x and 583 to 1.7 mm; what
// is left is inside the box too (1.6-2.9x in position, seed 2 worst), where only the fit helps.
// Why ridge: auto over-smooths here: it is chosen when the polynomial is initialised, on what the
// physical group fitted alone leaves (mm-scale structure the joint fit then moves into the group);
// on that residual the blocked CV's optimum is a weight of 1-3. A weaker weight lets the joint fit
// trade the physical terms for polynomial coefficients (the second pass above), so 0.25 on seed 1
// is a fortunate hand-pick rather than a rule.
// Session 6, where kBestChain's gap comes from (Explore with the {ROOM}/{FAR}/{NEAR} placeholders;
// validation means over the floor's, position / orientation, the file as written):
//                                                          seed 1          seed 2
//   true room held fixed + degree 0 ....................... 1.00x / 0.99x   0.98x / 0.99x
//   true room freed from the truth + degree 0 ............. 1.05x / 1.01x   1.02x / 1.01x
//   true room freed + degree 2 ............................ 1.17x / 1.09x   1.09x / 1.07x
//   true room held + degree 8 ridge 0.25 .................. 1.50x / 1.35x   1.62x / 1.68x
//   searched dipole + plane, true far sources held, deg 0 . 1.03x / 1.00x   1.00x / 0.99x
//     the same, degree 2 .................................. 1.12x / 1.08x   1.08x / 1.03x
//     far sources freed, degree 2 ......................... 1.17x / 1.09x   1.09x / 1.07x
//     far sources held, degree 8 ridge 0.25 ............... 1.65x / 1.60x   2.76x / 2.08x
//   kBestChain (searched dipole + plane, degree 8 ridge) .. 2.03x / 1.70x   3.73x / 2.28x
//     the same with the frame and floor started at the truth and freed: identical
// So the search finds the frame and the floor; what is left is the far sources (monitors, door),
// which the degree-8 polynomial absorbs badly (1.65 -> 2.03x, 2.76 -> 3.73x), and the degree-8
// polynomial's own variance, even with nothing left to model (1.0 -> 1.5-1.65x; 1.0 -> 1.65-2.76x
// with the near sources searched). The cure is the far sources as physical terms and a
// low-degree explicit term: fit/chain_builder.h (TheChainBuiltByHeldOutError).
constexpr const char* kBestChain =
    "terms:\n"
    "  - type: dipole\n"
    "  - type: plane\n"
    "  - type: polynomial\n"
    "    degree: 8\n"
    "    ridge: 0.25\n";

// The chain chosen by held-out calibration data, the same procedure for every capture: searched
// physical sources (a dipole and a plane) followed by a polynomial of degree 4 .. 8 with ridge:
// auto. The degree and, per degree, the ridge weight are scored by the polynomial's blocked
// cross-validation (PolynomialTerm::BlockedRidgeCv: whole layers of the calibration grid held out
// in turn, so held-out stations lie between and beyond the training stations as validation
// stations do) on the poses the searched physical group leaves; the degree with the smallest
// whitened held-out error (position and orientation parts together) is fitted jointly.
struct ChosenChain {
  int degree = 0;
  std::vector<double> score;  // per degree 4 .. 8: whitened blocked-CV error at the best ridge
  std::string model;          // the model file fitted
};

constexpr int kMinDegree = 4, kMaxDegree = 8;
constexpr double kSigmaPositionM = 0.25e-3, kSigmaOrientationRad = 0.04 * kRadPerDeg;  // kNoise

std::string ChainModel(int degree, int max_iterations) {
  return "noise: {position_mm: 0.25, orientation_deg: 0.04, position_range_exponent: 4, "
         "orientation_range_exponent: 3}\n"
         "solver: {max_iterations: " +
         std::to_string(max_iterations) +
         ", covariance: false}\n"
         "terms:\n  - type: dipole\n  - type: plane\n  - type: polynomial\n    degree: " +
         std::to_string(degree) + "\n    ridge: auto\n";
}

// The blocked cross-validation of a degree-`degree` polynomial after `group` (the physical
// correction) on the calibration stations: per part the summed squared held-out error per weight of
// PolynomialTerm::RidgeGrid().
struct GroupCv {
  std::vector<double> position, orientation;
  double BestPosition() const { return *std::min_element(position.begin(), position.end()); }
  double BestOrientation() const {
    return *std::min_element(orientation.begin(), orientation.end());
  }
  double PositionRidge() const {
    return PolynomialTerm::RidgeGrid()[static_cast<size_t>(
        std::min_element(position.begin(), position.end()) - position.begin())];
  }
};

GroupCv BlockedCvAfter(const Correction& group, const std::vector<FitStation>& calibration,
                       int degree) {
  const int n = static_cast<int>(calibration.size());
  Eigen::MatrixXd b_position(n, 3), b_orientation(n, 3), p(n, 3);
  for (int i = 0; i < n; ++i) {
    const Rigid3d input = group.Apply(calibration[static_cast<size_t>(i)].reported).pose;
    const PoseError e = ComputePoseError(input, calibration[static_cast<size_t>(i)].reference);
    b_position.row(i) = e.position.transpose();
    b_orientation.row(i) = e.orientation.transpose();
    p.row(i) = input.translation.transpose();
  }
  // The polynomial's normalisation: the inputs' box onto [-1, 1].
  const Eigen::RowVector3d lo = p.colwise().minCoeff(), hi = p.colwise().maxCoeff();
  const Eigen::MatrixXd u =
      (p.rowwise() - 0.5 * (lo + hi)).array().rowwise() / (0.5 * (hi - lo)).array();
  const int r = NumPolynomialTerms(degree);
  Eigen::MatrixXd a(n, r);
  std::vector<double> monomials(static_cast<size_t>(r));
  for (int i = 0; i < n; ++i) {
    const Eigen::Vector3d ui = u.row(i).transpose();
    EvaluateMonomials(degree, ui.data(), monomials.data());
    for (int j = 0; j < r; ++j) a(i, j) = monomials[static_cast<size_t>(j)];
  }
  std::vector<bool> shrunk;
  for (const auto& e : PolynomialTermExponents(degree)) shrunk.push_back(e[0] + e[1] + e[2] >= 2);
  const std::vector<double> grid = PolynomialTerm::RidgeGrid();
  // Held-out stations predicted as ridge: auto does (the box value held); with
  // TRACKCAL_BEST_CHAIN_CV_LINEAR=1 continued to first order as the runtime's default policy.
  const Eigen::Vector3d scale = (0.5 * (hi - lo)).transpose();
  const int slabs = PolynomialTerm::kBlockedSlabsPerAxis;
  const double reach = std::getenv("TRACKCAL_BEST_CHAIN_CV_LINEAR") != nullptr
                           ? CalibratedVolume::kDefaultLinearReach
                           : 0.0;
  return {PolynomialTerm::BlockedRidgeCv(degree, u, a, b_position, shrunk, grid, slabs, scale, reach),
          PolynomialTerm::BlockedRidgeCv(degree, u, a, b_orientation, shrunk, grid, slabs, scale,
                                         reach)};
}

ChosenChain ChooseChain(const std::vector<FitStation>& calibration) {
  // The physical group as the engine initialises it (searched, then fitted alone; one joint
  // iteration): what the explicit part will see.
  ModelSpec first = ParseModelYaml(ChainModel(kMaxDegree, 1), "choose");
  FitOptions options;
  options.compute_covariance = false;
  const FitResult fit = FitModel(calibration, &first, options);
  ChosenChain out;
  double best = std::numeric_limits<double>::infinity();
  for (int degree = kMinDegree; degree <= kMaxDegree; ++degree) {
    const GroupCv cv = BlockedCvAfter(fit.chain.term(0), calibration, degree);
    const double score = cv.BestPosition() / (kSigmaPositionM * kSigmaPositionM) +
                         cv.BestOrientation() / (kSigmaOrientationRad * kSigmaOrientationRad);
    out.score.push_back(score / static_cast<double>(calibration.size()));
    if (score < best) {
      best = score;
      out.degree = degree;
    }
  }
  out.model = ChainModel(out.degree, 300);
  return out;
}

// Seeds of the opt-in explorations below: TRACKCAL_BEST_CHAIN_SEEDS=1,2,3 (default 1).
std::vector<uint64_t> ExplorationSeeds() {
  const char* seeds_env = std::getenv("TRACKCAL_BEST_CHAIN_SEEDS");
  std::vector<uint64_t> seeds;
  std::stringstream ss(seeds_env ? seeds_env : "1");
  for (std::string s; std::getline(ss, s, ',');) seeds.push_back(std::stoull(s));
  return seeds;
}

// The chain chosen by held-out calibration data, the same procedure on every seed:
// TRACKCAL_BEST_CHAIN_CHOOSE=1 [TRACKCAL_BEST_CHAIN_SEEDS=1,2,3]. Exploration, not run by default:
// it does not beat the hand-picked ridge yet (figures above) and takes ~3 fits of CPU per seed.
TEST(BestChainOnPaperPreset, ChainChosenByBlockedCrossValidation) {
  if (std::getenv("TRACKCAL_BEST_CHAIN_CHOOSE") == nullptr)
    GTEST_SKIP() << "set TRACKCAL_BEST_CHAIN_CHOOSE";
  for (uint64_t seed : ExplorationSeeds()) {
    const PaperCapture data = Simulate(seed);
    const auto start = std::chrono::steady_clock::now();
    const ChosenChain chosen = ChooseChain(data.calibration);
    const double choose_seconds =
        std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
    std::cout << "seed " << seed << ": blocked-CV score per degree " << kMinDegree << ".."
              << kMaxDegree << ":";
    for (double v : chosen.score) std::cout << " " << v;
    std::cout << " -> degree " << chosen.degree << " (" << choose_seconds << " s)\n";
    const Outcome best =
        FitAndValidate(data, chosen.model, "chosen chain seed " + std::to_string(seed));
    (void)best;
    // Second pass: the weight chosen again on what the jointly fitted group leaves.
    ModelSpec spec = ParseModelYaml(chosen.model, "pass1");
    FitOptions options;
    options.compute_covariance = false;
    const FitResult fit = FitModel(data.calibration, &spec, options);
    const GroupCv cv = BlockedCvAfter(fit.chain.term(0), data.calibration, chosen.degree);
    std::cout << "second pass cv rms position [mm] per ridge:";
    for (double v : cv.position)
      std::cout << " " << std::sqrt(v / (3.0 * data.calibration.size())) * 1e3;
    std::cout << " -> ridge " << cv.PositionRidge() << "\n";
    std::string model2 = chosen.model;
    model2.replace(model2.find("ridge: auto"), 11, "ridge: " + std::to_string(cv.PositionRidge()));
    FitAndValidate(data, model2, "second pass seed " + std::to_string(seed));
  }
}

// Exploration of the ridge weight's selection: TRACKCAL_BEST_CHAIN_RIDGE=1 (seeds as above).
// The explicit part's inputs from the physical group as ChooseChain gets them; per degree and
// weight the polynomial's linear fit alone (no joint refinement), validated as the file would be,
// beside the blocked cross-validation's scores for several slab counts.
TEST(BestChainOnPaperPreset, ExploreRidge) {
  if (std::getenv("TRACKCAL_BEST_CHAIN_RIDGE") == nullptr)
    GTEST_SKIP() << "set TRACKCAL_BEST_CHAIN_RIDGE";
  for (uint64_t seed : ExplorationSeeds()) {
    const PaperCapture data = Simulate(seed);
    ModelSpec first = ParseModelYaml(ChainModel(kMaxDegree, 1), "choose");
    FitOptions options;
    options.compute_covariance = false;
    const FitResult fit = FitModel(data.calibration, &first, options);
    const Correction& group = fit.chain.term(0);
    std::vector<FitStation> inputs;
    for (const auto& s : data.calibration) {
      FitStation t = s;
      t.reported = group.Apply(s.reported).pose;
      inputs.push_back(t);
    }
    const CalibratedVolume volume = *fit.chain.volume();
    for (int degree : {6, 8}) {
      for (double lambda : PolynomialTerm::RidgeGrid()) {
        PolynomialTermOptions po;
        po.degree = degree;
        po.ridge = lambda;
        PolynomialTerm term(po);
        term.Prepare(inputs);
        term.InitializeLinear(inputs, Eigen::Vector2d(kSigmaPositionM, kSigmaOrientationRad));
        CorrectionChain chain;
        chain.Append(group.Clone());
        chain.Append(term.ToCorrection());
        chain.SetVolume(volume);
        Validate(data, chain, volume,
                 "seed " + std::to_string(seed) + " degree " + std::to_string(degree) + " ridge " +
                     std::to_string(lambda),
                 false);
      }
      const int n = static_cast<int>(inputs.size());
      const int r = NumPolynomialTerms(degree);
      PolynomialTermOptions po;
      po.degree = degree;
      PolynomialTerm norm(po);
      norm.Prepare(inputs);
      Eigen::MatrixXd a(n, r), u(n, 3), bp(n, 3), bo(n, 3);
      std::vector<double> monomials(static_cast<size_t>(r));
      for (int i = 0; i < n; ++i) {
        double ui[3];
        NormalizePolynomialInput(inputs[static_cast<size_t>(i)].reported.translation.data(),
                                 norm.options().input_offset, norm.options().input_scale, ui);
        EvaluateMonomials(degree, ui, monomials.data());
        for (int j = 0; j < r; ++j) a(i, j) = monomials[static_cast<size_t>(j)];
        for (int k = 0; k < 3; ++k) u(i, k) = ui[k];
        const PoseError e = ComputePoseError(inputs[static_cast<size_t>(i)].reported,
                                             inputs[static_cast<size_t>(i)].reference);
        bp.row(i) = e.position.transpose();
        bo.row(i) = e.orientation.transpose();
      }
      std::vector<bool> shrunk;
      for (const auto& e : PolynomialTermExponents(degree))
        shrunk.push_back(e[0] + e[1] + e[2] >= 2);
      for (int slabs : {4, 6, 12}) {
        const auto cv_p = PolynomialTerm::BlockedRidgeCv(degree, u, a, bp, shrunk,
                                                         PolynomialTerm::RidgeGrid(), slabs);
        const auto cv_o = PolynomialTerm::BlockedRidgeCv(degree, u, a, bo, shrunk,
                                                         PolynomialTerm::RidgeGrid(), slabs);
        std::cout << "degree " << degree << " slabs " << slabs
                  << " cv rms position [mm] / orientation [deg]:";
        for (size_t g = 0; g < cv_p.size(); ++g) {
          std::cout << " " << std::sqrt(cv_p[g] / (3.0 * n)) * 1e3 << "/"
                    << std::sqrt(cv_o[g] / (3.0 * n)) * 2 * kDegPerRad;
        }
        std::cout << "\n";
      }
    }
  }
}

// Exploration of the runtime policy outside the calibrated volume without refitting:
// TRACKCAL_BEST_CHAIN_SAVE=DIR fits kBestChain once per seed (TRACKCAL_BEST_CHAIN_SEEDS) and writes
// DIR/seed<N>.json; TRACKCAL_BEST_CHAIN_POLICIES=DIR then validates each saved file under every
// extrapolation policy (the chain and box unchanged), split inside / outside the box.
TEST(BestChainOnPaperPreset, SaveFits) {
  const char* dir = std::getenv("TRACKCAL_BEST_CHAIN_SAVE");
  if (dir == nullptr) GTEST_SKIP() << "set TRACKCAL_BEST_CHAIN_SAVE=DIR";
  for (uint64_t seed : ExplorationSeeds()) {
    const PaperCapture data = Simulate(seed);
    // The best chain (seed<N>.json) and the paper's degree-4 polynomial (seed<N>_paper.json).
    for (const auto& [model, suffix] :
         std::vector<std::pair<std::string, std::string>>{{kBestChain, ""}, {kPaperPolynomial, "_paper"}}) {
      // The paper's polynomial unweighted, as the paper fits it (kPaperPolynomial).
      ModelSpec spec = ParseModelYaml(
          suffix == "_paper" ? PaperBaselineModel() : std::string(kNoise) + model, "model");
      FitOptions options;
      options.compute_covariance = false;
      const FitResult fit = FitModel(data.calibration, &spec, options);
      const Calibration file = WrittenFile(fit);
      WriteCalibrationFile(std::string(dir) + "/seed" + std::to_string(seed) + suffix + ".json",
                           file);
      Validate(data, file.chain, file.volume(),
               "seed " + std::to_string(seed) + suffix + " (file)", true);
    }
  }
}

TEST(BestChainOnPaperPreset, PoliciesOnSavedFits) {
  const char* dir = std::getenv("TRACKCAL_BEST_CHAIN_POLICIES");
  if (dir == nullptr) GTEST_SKIP() << "set TRACKCAL_BEST_CHAIN_POLICIES=DIR";
  for (uint64_t seed : ExplorationSeeds()) {
    const PaperCapture data = Simulate(seed);
   for (const std::string suffix : {"", "_paper"}) {
    const std::filesystem::path path =
        std::string(dir) + "/seed" + std::to_string(seed) + suffix + ".json";
    if (!std::filesystem::exists(path)) continue;
    const Calibration file = ReadCalibrationFile(path);
    // clamp; fade over 0.1 m; linear with reaches from 0 (clamp) to beyond every station.
    const std::vector<std::pair<std::string, double>> policies = {
        {"clamp", 0.0},   {"fade", 0.1},    {"linear", 0.0},  {"linear", 0.01}, {"linear", 0.02},
        {"linear", 0.03}, {"linear", 0.05}, {"linear", 0.1},  {"linear", 1.0}};
    for (const auto& [policy, distance] : policies) {
      CorrectionChain chain = file.chain;
      CalibratedVolume volume = file.volume();
      volume.extrapolation = ExtrapolationPolicyFromName(policy);
      volume.fade_distance = policy == "fade" ? distance : 0.0;
      volume.linear_reach = distance;
      chain.SetVolume(volume);
      Validate(data, chain, volume,
               "seed " + std::to_string(seed) + suffix + " " + policy + " " +
                   std::to_string(distance),
               policy == "linear" && distance == CalibratedVolume::kDefaultLinearReach);
    }
   }
  }
}

// The chain BuildChain (fit/chain_builder.h) builds from the calibration stations alone, with the
// noise model of kNoise; prints the builder's steps and validates the file as written.
Outcome BuildAndValidate(const PaperCapture& data, const ChainBuilderOptions& options,
                         const std::string& name) {
  FitOptions fit_options;
  fit_options.compute_covariance = false;
  const auto start = std::chrono::steady_clock::now();
  const std::clock_t cpu_start = std::clock();
  const BuiltChain built = BuildChain(data.calibration, options, fit_options);
  const double seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  const double cpu = static_cast<double>(std::clock() - cpu_start) / CLOCKS_PER_SEC;
  for (const auto& step : built.steps) {
    std::cout << "  round " << step.round << " +" << (step.added.empty() ? "nothing" : step.added)
              << ": score " << step.score << " (degree " << step.degree << ")"
              << (step.kept ? " kept" : "") << ", " << step.seconds << " s\n";
  }
  std::cout << "  degree " << built.degree << ", ridge " << built.ridge.transpose() << "; "
            << built.fit.iterations << " iterations; " << seconds << " s wall, " << cpu
            << " s CPU\n";
  const Calibration file = WrittenFile(built.fit);
  Outcome o = Validate(data, file.chain, file.volume(), name, true);
  o.seconds = seconds;
  for (const auto& p : built.fit.parameters) {
    if (p.term.rfind("polynomial", 0) == 0) continue;
    std::cout << "  " << p.term << "." << p.block << " =";
    for (double v : p.values) std::cout << " " << v;
    std::cout << "\n";
  }
  if (std::getenv("TRACKCAL_BUILD_VARIANTS")) {
    // The sources found, fitted jointly with a plain polynomial of a few degrees.
    for (int degree : {0, 2, 4}) {
      FitAndValidate(data,
                     options.settings_yaml + "terms:\n" + built.sources +
                         "  - type: polynomial\n    degree: " + std::to_string(degree) + "\n",
                     name + " sources + degree " + std::to_string(degree));
    }
  }
  return o;
}

// The baseline this file calls the paper's is the paper's fit: eq. 8-9 by plain least squares,
// every calibration station weighted alike. Solved here independently of fit/: complete degree-4
// monomials of the reported position in metres about the stations' mean (an affine change of the
// variable spans the same polynomials, so the fit is the same whatever the engine's normalisation).
// A range-weighted fit (kNoise's exponents) moves the corrected calibration poses by millimetres.
TEST(BestChainOnPaperPreset, PaperBaselineIsPlainLeastSquares) {
  const PaperCapture data = Simulate(1);
  ModelSpec spec = ParseModelYaml(PaperBaselineModel(), "paper");
  FitOptions options;
  options.compute_covariance = false;
  const FitResult fit = FitModel(data.calibration, &spec, options);

  const std::vector<std::array<int, 3>> exponents = PolynomialTermExponents(4);
  const int n = static_cast<int>(data.calibration.size());
  const int r = static_cast<int>(exponents.size());
  Eigen::Vector3d centre = Eigen::Vector3d::Zero();
  for (const FitStation& s : data.calibration) centre += s.reported.translation / n;
  Eigen::MatrixXd a(n, r), b(n, 6);
  for (int i = 0; i < n; ++i) {
    const FitStation& s = data.calibration[i];
    const Eigen::Vector3d u = s.reported.translation - centre;
    for (int j = 0; j < r; ++j) {
      a(i, j) = std::pow(u.x(), exponents[j][0]) * std::pow(u.y(), exponents[j][1]) *
                std::pow(u.z(), exponents[j][2]);
    }
    const PoseError e = ComputePoseError(s.reported, s.reference);  // eq. 1, 3
    b.row(i) << e.position.transpose(), e.orientation.transpose();
  }
  const Eigen::MatrixXd c = a.colPivHouseholderQr().solve(b);
  const Eigen::MatrixXd predicted = a * c;
  double worst_position_m = 0, worst_angle_rad = 0;
  for (int i = 0; i < n; ++i) {
    Rigid3d expected = data.calibration[i].reported;
    ApplyPoseError<double>(predicted.row(i).head<3>().transpose(),
                           predicted.row(i).tail<3>().transpose(), &expected.translation,
                           &expected.rotation);  // eq. 4
    const Rigid3d corrected = fit.chain.Apply(data.calibration[i].reported).pose;
    worst_position_m = std::max(worst_position_m, PositionErrorNorm(corrected, expected));
    worst_angle_rad = std::max(worst_angle_rad, OrientationErrorAngle(corrected, expected));
  }
  std::cout << "paper baseline against plain least squares: " << worst_position_m << " m, "
            << worst_angle_rad << " rad\n";
  // Measured 1.7e-16 m and 3.5e-16 rad apart (the two solvers' rounding); the range-weighted fit
  // (kNoise + kPaperPolynomial) was 36 mm and 4.1 deg apart. 1e-9 is far from both.
  EXPECT_LT(worst_position_m, 1e-9);
  EXPECT_LT(worst_angle_rad, 1e-9);
}

// Issue #5's acceptance: the chain trackcal-fit build makes (fit/chain_builder.h: sources added
// while the blocked cross-validation of the explicit term after them improves, then the explicit
// term's degree and weights chosen the same way on what the final group leaves, the group held)
// within 1.5x the noise floor on validation, on three seeds.
TEST(BestChainOnPaperPreset, TheChainBuiltByHeldOutError) {
  struct Bound {
    uint64_t seed;
    double position, orientation;
  };
  // Measured with the file as written (validation means over the floor's, position / orientation):
  //   seed 1: 1.14x / 1.01x   inside the box 1.16x / 1.00x   outside 1.04x / 1.03x
  //   seed 2: 1.06x / 1.04x   inside the box 1.10x / 1.03x   outside 1.01x / 1.04x
  //   seed 3: 1.08x / 1.06x   inside the box 1.05x / 1.05x   outside 1.18x / 1.09x
  // The builder found on every seed the workbench frame and the floor (a dipole + plane in round
  // 1), the three CRT monitors within 2 cm (round 2's dipole, round 3's pair), and the door as a
  // plane at 2.09-2.1 m (seeds 1, 2) or as a dipole pair beyond it (seed 3), plus one plane doing
  // little (attenuation ~0 or a stand-in far off); the explicit term came out degree 2-3 with
  // strong weights (ridge 31.6-100). CPU of the builder and its fit: 111 / 113 / 74 s (wall
  // 192 / 244 / 146 s on the shared machine under load ~10).
  // (kBestChain, the hand-picked searched dipole + plane + degree-8 ridge 0.25 polynomial this
  // test ran before: 2.03x / 1.70x, 3.73x / 2.28x, 2.97x / 1.73x.) The bounds hold what is reached
  // with ~7 % for solver and platform differences, so a regression fails; all are below the
  // issue's 1.5x.
  const std::vector<Bound> bounds = {{1, 1.22, 1.08}, {2, 1.13, 1.11}, {3, 1.16, 1.13}};
  ChainBuilderOptions options;
  options.settings_yaml = kNoise;
  for (const Bound& bound : bounds) {
    SCOPED_TRACE("seed " + std::to_string(bound.seed));
    const PaperCapture data = Simulate(bound.seed);
    const Outcome paper = FitAndValidate(data, PaperBaselineModel(), "paper degree 4");
    const Outcome best = BuildAndValidate(data, options, "built chain");
    // The paper's polynomial is far above the floor (the issue: ~30x), so this test can fail.
    EXPECT_GT(paper.position_ratio, 10.0);
    EXPECT_GT(paper.orientation_ratio, 5.0);
    EXPECT_LE(best.position_ratio, bound.position);
    EXPECT_LE(best.orientation_ratio, bound.orientation);
    EXPECT_LE(best.position_ratio, 1.5);
    EXPECT_LE(best.orientation_ratio, 1.5);
  }
}

// Exploration of the builder's options: TRACKCAL_BEST_CHAIN_BUILD=1 [TRACKCAL_BEST_CHAIN_SEEDS],
// TRACKCAL_BUILD_TYPES=dipole,plane,dipole_pair, TRACKCAL_BUILD_REFIT=1 (joint final fit),
// TRACKCAL_BUILD_REACH=0.1, TRACKCAL_BUILD_MAX_SOURCES=6, TRACKCAL_BUILD_GAIN=0.03.
TEST(BestChainOnPaperPreset, ExploreBuilder) {
  if (std::getenv("TRACKCAL_BEST_CHAIN_BUILD") == nullptr)
    GTEST_SKIP() << "set TRACKCAL_BEST_CHAIN_BUILD";
  ChainBuilderOptions options;
  options.settings_yaml = kNoise;
  if (const char* t = std::getenv("TRACKCAL_BUILD_TYPES")) {
    options.source_types.clear();
    std::stringstream ss(t);
    for (std::string s; std::getline(ss, s, ',');) options.source_types.push_back(s);
  }
  if (std::getenv("TRACKCAL_BUILD_REFIT")) options.refit_group = true;
  if (const char* r = std::getenv("TRACKCAL_BUILD_REACH")) options.cv_linear_reach = std::stod(r);
  if (const char* m = std::getenv("TRACKCAL_BUILD_MAX_SOURCES")) options.max_sources = std::stoi(m);
  if (const char* g = std::getenv("TRACKCAL_BUILD_GAIN")) options.min_relative_gain = std::stod(g);
  if (const char* d = std::getenv("TRACKCAL_BUILD_SEARCH_DEGREE")) options.search_degree = std::stoi(d);
  const FieldModel room = sim::LoadScene("paper").environment;
  for (uint64_t seed : ExplorationSeeds()) {
    const PaperCapture data = Simulate(seed);
    if (std::getenv("TRACKCAL_BUILD_REFERENCE")) {
      // The builder's score after the true room (held fixed): what noise alone leaves; after a
      // searched dipole and plane with the true far sources; after a searched dipole and plane.
      FieldModel far = room;
      far.planes.erase(far.planes.begin());  // the floor
      far.objects.pop_back();                // the workbench frame
      for (const auto& [what, terms] : std::vector<std::pair<std::string, std::string>>{
               {"true room", testing::FixedRoomTermsYaml(room)},
               {"searched dipole + plane, true far", "  - type: dipole\n  - type: plane\n" +
                                                         testing::FixedRoomTermsYaml(far)},
               {"searched dipole + plane", "  - type: dipole\n  - type: plane\n"}}) {
        ModelSpec spec = ParseModelYaml(
            std::string(kNoise) + "terms:\n" + terms + "  - type: polynomial\n    degree: 0\n",
            "room");
        FitOptions fo;
        fo.compute_covariance = false;
        const FitResult fit = FitModel(data.calibration, &spec, fo);
        const ExplicitCv cv = ExplicitTermCv(&fit.chain.term(0), data.calibration, spec, 0, 8,
                                             options.cv_linear_reach);
        std::cout << "seed " << seed << " " << what << ": score per degree 0..8:";
        for (double v : cv.score) std::cout << " " << v;
        std::cout << "\n";
      }
    }
    BuildAndValidate(data, options, "built chain seed " + std::to_string(seed));
  }
}

// Exploration: TRACKCAL_BEST_CHAIN_MODELS=a.yaml,b.yaml TRACKCAL_BEST_CHAIN_SEEDS=1,2 fits each.
TEST(BestChainOnPaperPreset, Explore) {
  const char* models = std::getenv("TRACKCAL_BEST_CHAIN_MODELS");
  if (models == nullptr) GTEST_SKIP() << "set TRACKCAL_BEST_CHAIN_MODELS to explore";
  for (uint64_t seed : ExplorationSeeds()) {
    const PaperCapture data = Simulate(seed);
    std::stringstream ms(models);
    for (std::string path; std::getline(ms, path, ',');) {
      std::ifstream in(path);
      std::stringstream text;
      text << in.rdbuf();
      // Placeholders for the scene's true planes and objects: "{ROOM}" all of them, "{FAR}" those
      // farther than kFarM from the transmitter (the door and the monitors), "{NEAR}" the others
      // (the frame and the floor), held fixed; "{ROOM_FREE}", "{FAR_FREE}", "{NEAR_FREE}": the
      // same, started at the truth and fitted.
      std::string yaml = text.str();
      const FieldModel room = sim::LoadScene("paper").environment;
      constexpr double kFarM = 1.5;
      FieldModel far = room, near = room;
      far.planes.clear();
      far.objects.clear();
      near.planes.clear();
      near.objects.clear();
      for (const auto& p : room.planes) {
        (std::abs(p.point_in_transmitter.dot(p.normal_in_transmitter)) > kFarM ? far : near)
            .planes.push_back(p);
      }
      for (const auto& o : room.objects) {
        (o.location_in_transmitter.norm() > kFarM ? far : near).objects.push_back(o);
      }
      const auto freed = [](std::string terms) {
        for (size_t at; (at = terms.find("{fixed: true}")) != std::string::npos;)
          terms.replace(at, 13, "{fixed: false}");
        return terms;
      };
      for (const auto& [key, terms] : std::vector<std::pair<std::string, std::string>>{
               {"{ROOM_FREE}", freed(testing::FixedRoomTermsYaml(room))},
               {"{FAR_FREE}", freed(testing::FixedRoomTermsYaml(far))},
               {"{NEAR_FREE}", freed(testing::FixedRoomTermsYaml(near))},
               {"{ROOM}", testing::FixedRoomTermsYaml(room)},
               {"{FAR}", testing::FixedRoomTermsYaml(far)},
               {"{NEAR}", testing::FixedRoomTermsYaml(near)}}) {
        const size_t at = yaml.find(key);
        if (at != std::string::npos) yaml.replace(at, key.size(), terms);
      }
      FitAndValidate(data, yaml, path + " seed " + std::to_string(seed), true);
    }
  }
}

}  // namespace
}  // namespace trackcal::fit
