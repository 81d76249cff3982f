#include "fit/fit_engine.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <iostream>
#include <random>
#include <string>
#include <nlohmann/json.hpp>

#include "fit/sim_test_support.h"
#include "fit/terms_polynomial.h"
#include "sim/scene.h"
#include "sim/simulator.h"

namespace trackcal::fit {
namespace {

using testing::FourHeightGrid;

std::vector<FitStation> NoiseFreeStations(const Correction& truth, int n, std::mt19937* rng) {
  std::uniform_real_distribution<double> pos(-0.5, 0.5);
  std::normal_distribution<double> normal;
  std::vector<FitStation> out;
  for (int i = 0; i < n; ++i) {
    FitStation s;
    s.station = i;
    s.reported.translation = Eigen::Vector3d(pos(*rng), pos(*rng), 0.3 + pos(*rng));
    s.reported.rotation =
        Eigen::Quaterniond(normal(*rng), normal(*rng), normal(*rng), normal(*rng)).normalized();
    s.reference = truth.Apply(s.reported).pose;
    out.push_back(s);
  }
  return out;
}

std::unique_ptr<Correction> RandomPolynomial(int degree, std::mt19937* rng) {
  const int r = NumPolynomialTerms(degree);
  std::normal_distribution<double> normal;
  std::vector<double> p(static_cast<size_t>(r) * 3), q(static_cast<size_t>(r) * 3);
  for (auto& v : p) v = 0.005 * normal(*rng);
  for (auto& v : q) v = 0.01 * normal(*rng);
  return PolynomialCorrection::FromPositionAndOrientation(
      degree, Eigen::Vector3d(0, 0, 0.3), Eigen::Vector3d(0.5, 0.5, 0.5), p, q);
}

// `n` stations of a random degree-`degree` polynomial distortion (seed `seed`), their reference
// positions with 1 mm of white noise per axis.
std::vector<FitStation> NoisyPolynomialStations(unsigned seed, int degree, int n) {
  std::mt19937 rng(seed);
  const auto truth = RandomPolynomial(degree, &rng);
  auto stations = NoiseFreeStations(*truth, n, &rng);
  std::normal_distribution<double> noise(0.0, 1e-3);
  for (auto& s : stations) {
    s.reference.translation += Eigen::Vector3d(noise(rng), noise(rng), noise(rng));
  }
  return stations;
}

TEST(FitModel, Nominal_NoiseFreePolynomialRecoveredTo1e6Relative) {
  std::mt19937 rng(5);
  const auto truth = RandomPolynomial(3, &rng);
  const auto stations = NoiseFreeStations(*truth, 300, &rng);
  // The model covariance: noise-free residuals give a sandwich of zero (fit/covariance.h); the
  // stds compared below are the model's on both paths.
  ModelSpec spec = ParseModelYaml(R"(solver: {covariance_estimator: model}
terms:
  - type: polynomial
    degree: 3
)",
                                  "m");
  // Fix the normalisation to the truth's so the coefficients are comparable.
  PolynomialTermOptions options;
  options.degree = 3;
  options.input_offset = Eigen::Vector3d(0, 0, 0.3);
  options.input_scale = Eigen::Vector3d(0.5, 0.5, 0.5);
  spec.terms[0] = std::make_unique<PolynomialTerm>(options);
  const FitResult result = FitModel(stations, &spec);
  EXPECT_TRUE(result.converged) << result.solver_message;
  const auto& fitted = dynamic_cast<const PolynomialCorrection&>(result.chain.term(0));
  const auto& expected = dynamic_cast<const PolynomialCorrection&>(*truth).coefficients();
  const double scale = Eigen::Map<const Eigen::VectorXd>(expected.data(), expected.size())
                           .cwiseAbs()
                           .maxCoeff();
  for (size_t i = 0; i < expected.size(); ++i) {
    EXPECT_NEAR(fitted.coefficients()[i], expected[i], /*rtol=*/1e-6 * scale) << i;
  }
  EXPECT_LT(result.final_cost, 1e-12);  // noise-free: residuals at rounding level
  // Every free coefficient has a finite standard deviation.
  ASSERT_EQ(result.parameters.size(), 2u);
  for (double s : result.parameters[0].stddev) EXPECT_TRUE(std::isfinite(s));
  EXPECT_FALSE(result.rank_deficient);
  EXPECT_TRUE(result.outliers.empty());
  EXPECT_EQ(result.solver_message, "linear least squares (paper eq. 9)");

  // A prior too weak to matter forces the joint Ceres path: same coefficients, same position stds
  // (the position residual is linear in its coefficients, so its covariance is exactly sigma^2
  // (A^T A)^-1 on both paths; 1e-3 relative allows the prior's 1e-6 relative contribution).
  ModelSpec joint = ParseModelYaml(R"(solver: {covariance_estimator: model}
terms:
  - type: polynomial
    degree: 3
    parameters:
      position_coefficients: {prior: {mean: 0, sigma: 1000}}
)",
                                   "m");
  joint.terms[0] = std::make_unique<PolynomialTerm>(options);
  const FitResult ceres_result = FitModel(stations, &joint);
  EXPECT_NE(ceres_result.solver_message, result.solver_message);
  const auto& joint_fitted = dynamic_cast<const PolynomialCorrection&>(ceres_result.chain.term(0));
  for (size_t i = 0; i < expected.size(); ++i) {
    EXPECT_NEAR(joint_fitted.coefficients()[i], expected[i], /*rtol=*/1e-6 * scale) << i;
  }
  for (size_t i = 0; i < result.parameters[0].stddev.size(); ++i) {
    EXPECT_NEAR(ceres_result.parameters[0].stddev[i], result.parameters[0].stddev[i],
                1e-3 * result.parameters[0].stddev[i]);
  }
}

// A polynomial coefficient bounded away from its least-squares value: the linear initialisation
// put it beyond the bound and the fit refused its own start, "parameter block
// polynomial.position_coefficients: value -0.002000 outside its bounds at 0" (any `value:`, on the
// bound or not, is replaced by the linear solution), naming no file. A user's bound is in the
// coefficients' own unit (m for position, no rescaling): the fit starts on the bound and ends
// there, the free coefficients at the truth, by every initialisation (least squares, ridge, the
// robust loss's zero start).
TEST(FitModel, ABoundedPolynomialCoefficientStartsWithinItsBounds) {
  std::mt19937 rng(7);
  // A constant offset of -2 mm in x, 1 mm in y; none in orientation.
  const auto truth = PolynomialCorrection::FromPositionAndOrientation(
      0, Eigen::Vector3d::Zero(), Eigen::Vector3d::Ones(), {-0.002, 0.001, 0.0}, {0.0, 0.0, 0.0});
  const auto stations = NoiseFreeStations(*truth, 100, &rng);
  const std::string bounded = R"(
    parameters:
      position_coefficients:
        value: [0.001, 0, 0]
        lower: [0.001, -1, -1]
)";
  for (const std::string& settings : {std::string("terms:\n  - type: polynomial\n    degree: 0"),
                                      std::string("terms:\n  - type: polynomial\n    degree: 0\n"
                                                  "    ridge: 0.1"),
                                      std::string("loss: {type: huber}\n"
                                                  "terms:\n  - type: polynomial\n    degree: 0")}) {
    ModelSpec spec = ParseModelYaml(settings + bounded, "model.yaml");
    FitResult result;
    ASSERT_NO_THROW(result = FitModel(stations, &spec)) << settings;
    EXPECT_TRUE(result.converged) << settings << ": " << result.solver_message;
    ASSERT_EQ(result.parameters.size(), 2u);
    const std::vector<double>& p = result.parameters[0].values;
    ASSERT_EQ(p.size(), 3u);
    // On its bound; the free coordinates where the noise-free stations put them, to the solver's
    // precision: 1e-6 m is 1e-3 of the model's default 1 mm noise (measured: 1e-7 m under the
    // Huber loss, whose solve stops at its function tolerance; the others to rounding).
    EXPECT_DOUBLE_EQ(p[0], 0.001) << settings;
    EXPECT_NEAR(p[1], 0.001, 1e-6) << settings;
    EXPECT_NEAR(p[2], 0.0, 1e-6) << settings;
  }
  // A value outside its bounds is an error naming the file, line and field, in the coefficients'
  // unit with the digits that tell it from the bound.
  try {
    ModelSpec spec = ParseModelYaml(
        "terms:\n  - type: polynomial\n    degree: 0\n    parameters:\n"
        "      position_coefficients: {value: [0.0005, 0, 0], lower: [0.001, -1, -1]}\n",
        "model.yaml");
    FitModel(stations, &spec);
    ADD_FAILURE() << "no error";
  } catch (const std::invalid_argument& e) {
    EXPECT_THAT(e.what(), ::testing::HasSubstr(
                              "model.yaml:5:30: $.terms[0].parameters.position_coefficients: "));
    EXPECT_THAT(e.what(), ::testing::HasSubstr(
                              "value 0.0005 at 0 (px[1]) outside its bounds [0.001, inf] m"));
  }
}

TEST(FitModel, SandwichStdsOnTheLinearPathEqualTheJointPaths) {
  // Position noise that grows with the distance from the origin (as a tracker's does): the
  // default sandwich covariance is computed on the station residuals at the linear solution, and
  // gives the same stds as the Ceres path (1e-3 relative: the weak prior's share and the solve's
  // tolerance), and a different one from the model covariance.
  std::mt19937 rng(11);
  const auto truth = RandomPolynomial(2, &rng);
  auto stations = NoiseFreeStations(*truth, 300, &rng);
  std::normal_distribution<double> normal;
  for (auto& s : stations) {
    const double r = s.reported.translation.norm();
    s.reference.translation += 2e-4 * std::pow(r / 0.5, 4) * Eigen::Vector3d(normal(rng), normal(rng), normal(rng));
  }
  auto fit = [&](const std::string& yaml) {
    ModelSpec spec = ParseModelYaml(yaml, "m");
    return FitModel(stations, &spec);
  };
  const std::string poly = "terms:\n  - type: polynomial\n    degree: 2\n";
  const FitResult linear = fit(poly);
  const FitResult joint = fit(poly + "    parameters:\n      position_coefficients: {prior: {mean: 0, "
                                     "sigma: 1000}}\n");
  const FitResult model = fit("solver: {covariance_estimator: model}\n" + poly);
  EXPECT_EQ(linear.solver_message, "linear least squares (paper eq. 9)");
  EXPECT_NE(joint.solver_message, linear.solver_message);
  EXPECT_EQ(linear.covariance_estimator, "sandwich (CR2)");
  EXPECT_EQ(joint.covariance_estimator, "sandwich (CR2)");
  EXPECT_EQ(model.covariance_estimator, "model");
  EXPECT_EQ(linear.ToJson()["covariance_estimator"], "sandwich (CR2)");
  const auto& a = linear.parameters[0].stddev;
  const auto& b = joint.parameters[0].stddev;
  const auto& m = model.parameters[0].stddev;
  ASSERT_EQ(a.size(), b.size());
  double ratio = 0;
  for (size_t i = 0; i < a.size(); ++i) {
    EXPECT_NEAR(a[i], b[i], 1e-3 * a[i]) << i;
    ratio = std::max(ratio, std::max(a[i] / m[i], m[i] / a[i]));
  }
  // The model covariance (1 mm default noise against 0.2 mm and less) is several times off.
  EXPECT_GT(ratio, 2.0);
}

// Samples of a stream (most less than 0.5 s after the previous one of their sensor) are not
// independent: the sandwich clusters them in runs of time (32 by default; 0: the model
// covariance). Two sensors sampled at the same times are a stream too. Static stations (2 s apart)
// are one cluster each.
TEST(FitModel, StreamSamplesAreClusteredInRunsOfTime) {
  std::mt19937 rng(12);
  const auto truth = RandomPolynomial(2, &rng);
  std::vector<FitStation> stations = NoiseFreeStations(*truth, 200, &rng);
  std::normal_distribution<double> normal;
  for (auto& s : stations) s.reference.translation += 1e-4 * Eigen::Vector3d(normal(rng), normal(rng), normal(rng));
  auto estimator = [&](const std::vector<FitStation>& data, const std::string& solver) {
    ModelSpec spec = ParseModelYaml(solver + "terms:\n  - type: polynomial\n    degree: 2\n", "m");
    return FitModel(data, &spec).covariance_estimator;
  };
  std::vector<FitStation> one = stations, two;
  for (size_t i = 0; i < one.size(); ++i) one[i].time = 0.01 * static_cast<double>(i);
  for (size_t i = 0; i < one.size(); ++i) {
    FitStation s = stations[i];
    s.time = 0.01 * static_cast<double>(i / 2);
    s.sensor = 1 + static_cast<int>(i % 2);
    two.push_back(s);
  }
  std::vector<FitStation> still = stations;
  for (size_t i = 0; i < still.size(); ++i) still[i].time = 2.0 * static_cast<double>(i);
  EXPECT_EQ(estimator(one, ""), "sandwich (CR2, 32 clusters)");
  EXPECT_EQ(estimator(two, ""), "sandwich (CR2, 32 clusters)");
  EXPECT_EQ(estimator(one, "solver: {stream_clusters: 0}\n"), "model");
  EXPECT_EQ(estimator(one, "solver: {stream_clusters: 8}\n"), "sandwich (CR2, 8 clusters)");
  // 200 samples are too few for 50 runs of 5.
  EXPECT_EQ(estimator(one, "solver: {stream_clusters: 50}\n"), "model");
  EXPECT_EQ(estimator(still, ""), "sandwich (CR2)");
}

TEST(FitModel, FlagsUnidentifiableCoefficients) {
  // All stations on the plane z = 0.3: the z-dependent monomials are not identifiable.
  std::mt19937 rng(9);
  const auto truth = RandomPolynomial(1, &rng);
  auto stations = NoiseFreeStations(*truth, 100, &rng);
  for (auto& s : stations) {
    s.reported.translation.z() = 0.3;
    s.reference = truth->Apply(s.reported).pose;
  }
  // Fitting every direction: the covariance finds the rank deficiency.
  ModelSpec all =
      ParseModelYaml("terms: [{type: polynomial, degree: 1, max_amplification: 0}]", "m");
  const FitResult every = FitModel(stations, &all);
  EXPECT_TRUE(every.rank_deficient);
  EXPECT_FALSE(every.identifiability_flags.empty());
  // By default the direction the stations do not determine (z) is held at zero and flagged; the
  // others are fitted and reproduce the noise-free stations.
  ModelSpec spec = ParseModelYaml("terms: [{type: polynomial, degree: 1}]", "m");
  const FitResult result = FitModel(stations, &spec);
  EXPECT_FALSE(result.rank_deficient);
  ASSERT_EQ(result.identifiability_flags.size(), 2u);  // position and orientation parts
  EXPECT_EQ(result.identifiability_flags[0].coordinate, "polynomial.position_coefficients");
  EXPECT_EQ(result.identifiability_flags[0].reason.find("1 of its 4 directions not determined"), 0u)
      << result.identifiability_flags[0].reason;
  for (const auto& s : stations) {
    EXPECT_LT(PositionErrorNorm(result.chain.Apply(s.reported).pose, s.reference), 1e-9);
  }
}

std::vector<FitStation> StationsOfSet(const PoseCapture& poses, const std::string& set) {
  std::vector<FitStation> out;
  for (const auto& r : poses.records) {
    if (r.set != set) continue;
    out.push_back({r.reported, r.reference, r.time, r.sensor, r.station});
  }
  return out;
}

TEST(FitModel, PaperPresetDegree4MeetsPaperImprovement) {
  const sim::Simulator simulator(sim::LoadScene("paper"));
  const sim::SimulatedCapture capture = simulator.Generate();
  const auto calib = StationsOfSet(capture.poses, "calib");
  const auto valid = StationsOfSet(capture.poses, "valid");
  ASSERT_GT(calib.size(), 100u);
  ASSERT_GT(valid.size(), 10u);
  ModelSpec spec = ParseModelYaml("terms: [{type: polynomial, degree: 4}]", "m");
  const FitResult result = FitModel(calib, &spec);
  const Table1 table = EvaluateTable1(result.chain, valid, "valid");
  const double position = ImprovementPercent(table.before.position_mm.mean, table.after.position_mm.mean);
  const double orientation =
      ImprovementPercent(table.before.orientation_deg.mean, table.after.orientation_deg.mean);
  std::cout << FormatTable1(table) << "fit " << result.seconds * 1e3 << " ms (solve " << result.seconds_solve * 1e3 << " ms), " << result.iterations << " iterations, " << calib.size() << " stations " << result.solver_message << "\n";
  // The paper's Table 1 figures (degree 4, validation set).
  EXPECT_GE(position, 88.6);
  EXPECT_GE(orientation, 80.3);
}

TEST(FitModel, PaperPresetPolynomialPlusLutChain) {
  const sim::Simulator simulator(sim::LoadScene("paper"));
  const sim::SimulatedCapture capture = simulator.Generate();
  const auto calib = StationsOfSet(capture.poses, "calib");
  const auto valid = StationsOfSet(capture.poses, "valid");
  ModelSpec spec = ParseModelYaml(
      "terms:\n  - {type: polynomial, degree: 4}\n  - {type: lut, cell_size_mm: 300, smoothness: 10}\n",
      "m");
  const FitResult result = FitModel(calib, &spec);
  // The joint problem is nearly linear: a handful of iterations once the ridge fixes the
  // LUT/polynomial gauge (without it, 100 iterations drifting along the null space).
  EXPECT_TRUE(result.converged) << result.solver_message;
  EXPECT_LT(result.iterations, 10);
  const Table1 table = EvaluateTable1(result.chain, valid, "valid");
  EXPECT_GE(ImprovementPercent(table.before.position_mm.mean, table.after.position_mm.mean), 88.6);
  EXPECT_GE(ImprovementPercent(table.before.orientation_deg.mean, table.after.orientation_deg.mean),
            80.3);
  std::cout << "polynomial + LUT fit " << result.seconds * 1e3 << " ms (solve "
            << result.seconds_solve * 1e3 << " ms), chi2/dof " << result.chi2_per_dof << "\n";
}

TEST(FitModel, RobustLossIgnoresHemisphereFlips) {
  std::mt19937 rng(13);
  const auto truth = RandomPolynomial(2, &rng);
  auto stations = NoiseFreeStations(*truth, 300, &rng);
  std::normal_distribution<double> noise(0.0, 1e-4);
  for (auto& s : stations) {
    for (int k = 0; k < 3; ++k) s.reported.translation[k] += noise(rng);
  }
  std::vector<int> flipped;
  for (size_t i = 0; i < stations.size(); i += 20) {  // 5% flipped: reported at -p
    stations[i].reported.translation = -stations[i].reported.translation;
    flipped.push_back(stations[i].station);
  }
  auto max_error_on_clean = [&](const FitResult& result) {
    double worst = 0.0;
    for (size_t i = 0; i < stations.size(); ++i) {
      if (i % 20 == 0) continue;
      const Rigid3d c = result.chain.Apply(stations[i].reported).pose;
      worst = std::max(worst, PositionErrorNorm(c, stations[i].reference));
    }
    return worst;
  };
  ModelSpec plain = ParseModelYaml("noise: {position_mm: 0.1}\nterms: [{type: polynomial, degree: 2}]", "m");
  const double plain_error = max_error_on_clean(FitModel(stations, &plain));
  ModelSpec robust = ParseModelYaml(
      "noise: {position_mm: 0.1}\nloss: {type: cauchy, scale: 3}\n"
      "terms: [{type: polynomial, degree: 2}]",
      "m");
  const FitResult result = FitModel(stations, &robust);
  const double robust_error = max_error_on_clean(result);
  // Position noise 0.1 mm per axis: the robust fit stays within ~5 sigma of the clean data, the
  // least-squares fit is dragged by the flips by far more.
  EXPECT_LT(robust_error, 5e-4);
  EXPECT_GT(plain_error, 10 * robust_error);
  std::vector<int> flagged;
  for (const auto& o : result.outliers) flagged.push_back(o.station);
  EXPECT_THAT(flagged, ::testing::UnorderedElementsAreArray(flipped));
}

// The loss scale is in sigmas of the station's whitened RMS, as the outlier list, the rejection
// at 30 scales and diagnose's mean-shift model read it: a station whose 6 whitened residuals have
// RMS below the scale is not down-weighted. Ceres' loss takes its scale on the norm of the residual
// block (sqrt(6) times the RMS): given as it is, a Huber loss at 3 sigma down-weighted stations
// from RMS 1.22 on, and its fit left the least-squares optimum on data without any outlier.
TEST(FitModel, TheLossScaleIsInSigmasOfTheStationsRms) {
  std::vector<FitStation> stations;
  for (int i = 0; i < 60; ++i) {
    FitStation s;
    s.station = i;
    s.reported.translation = Eigen::Vector3d(0.01 * i, 0.2 - 0.005 * i, 0.5);
    s.reported.rotation = Eigen::Quaterniond::Identity();
    s.reference = s.reported;
    // A 2 mm offset along x; every fifth station 0.5 mm further: a whitened norm of 5 (0.1 mm
    // noise), RMS 2.04, within a 3-sigma loss.
    s.reference.translation.x() += 2e-3 + (i % 5 == 0 ? 5e-4 : 0.0);
    stations.push_back(s);
  }
  const std::string terms = "terms: [{type: polynomial, degree: 0, orientation: false}]";
  ModelSpec plain = ParseModelYaml("noise: {position_mm: 0.1}\n" + terms, "m");
  ModelSpec huber =
      ParseModelYaml("noise: {position_mm: 0.1}\nloss: {type: huber, scale: 3}\n" + terms, "m");
  const FitResult least_squares = FitModel(stations, &plain);
  const FitResult robust = FitModel(stations, &huber);
  EXPECT_TRUE(robust.outliers.empty());
  const Eigen::Vector3d at(0.1, 0.1, 0.5);
  const Rigid3d report(Eigen::Quaterniond::Identity(), at);
  const Eigen::Vector3d p_plain = least_squares.chain.Apply(report).pose.translation;
  const Eigen::Vector3d p_huber = robust.chain.Apply(report).pose.translation;
  EXPECT_NEAR(p_plain.x() - at.x(), 2.1e-3, 1e-9);  // the mean offset
  EXPECT_NEAR(p_huber.x(), p_plain.x(), 1e-8);
}

// The automatic linear solver (dense normal equations for a polynomial of 504 coefficients after
// a sensor offset: every station touches every coefficient) gives the parameters of the sparse
// solver the engine used before for problems above 400 coordinates. Both converge to the same
// optimum of a problem that is linear in all but 6 parameters; 1e-9 relative (of the largest
// coefficient of the block) is far above the two factorisations' rounding (~1e-13 measured) and
// far below any statistical meaning.
TEST(FitModel, DenseSolverChoiceGivesTheSparseSolversParameters) {
  const auto stations = NoisyPolynomialStations(11, 6, 400);
  const char* model = R"(terms:
  - type: sensor_offset
  - type: polynomial
    degree: 6
    ridge: 0.1
)";
  ModelSpec dense_spec = ParseModelYaml(model, "m");
  ModelSpec sparse_spec = ParseModelYaml(model, "m");
  FitOptions sparse_options;
  sparse_options.linear_solver = ceres::SPARSE_NORMAL_CHOLESKY;
  const FitResult dense = FitModel(stations, &dense_spec, {});
  const FitResult sparse = FitModel(stations, &sparse_spec, sparse_options);
  ASSERT_TRUE(dense.converged && sparse.converged);
  ASSERT_GT(dense.num_free_parameters, 400);
  EXPECT_EQ(dense.linear_solver, "DENSE_NORMAL_CHOLESKY");
  EXPECT_EQ(sparse.linear_solver, "SPARSE_NORMAL_CHOLESKY");
  ASSERT_EQ(dense.parameters.size(), sparse.parameters.size());
  for (size_t b = 0; b < dense.parameters.size(); ++b) {
    const auto& d = dense.parameters[b].values;
    const auto& s = sparse.parameters[b].values;
    double scale = 0.0;
    for (double v : s) scale = std::max(scale, std::abs(v));
    for (size_t i = 0; i < d.size(); ++i) {
      EXPECT_NEAR(d[i], s[i], 1e-9 * scale) << dense.parameters[b].block << "[" << i << "]";
    }
  }
  EXPECT_NEAR(dense.final_cost, sparse.final_cost, 1e-9 * sparse.final_cost);
}

// The statistical stop (opt-in) ends the solve once a step gains less than 5e-3 chi2/dof: no later than
// Ceres' function tolerance alone, at parameters within a tenth of their standard deviation of
// that solution (the rule's meaning: ~0.1 sigma left to gain; 0.1 allows for it).
TEST(FitModel, StatisticalToleranceStopsWithinATenthOfASigma) {
  const auto stations = NoisyPolynomialStations(5, 3, 300);
  const std::string model = "terms:\n  - type: sensor_offset\n  - type: polynomial\n    degree: 3\n";
  ModelSpec stat_spec = ParseModelYaml("solver: {statistical_tolerance: 5.0e-3}\n" + model, "m");
  ModelSpec tight_spec = ParseModelYaml(model, "m");
  EXPECT_EQ(stat_spec.statistical_tolerance, 5e-3);
  EXPECT_EQ(tight_spec.statistical_tolerance, 0.0);  // opt-in
  const FitResult stat = FitModel(stations, &stat_spec, {});
  const FitResult tight = FitModel(stations, &tight_spec, {});
  ASSERT_TRUE(stat.converged && tight.converged) << stat.solver_message;
  EXPECT_LE(stat.iterations, tight.iterations);
  ASSERT_EQ(stat.parameters.size(), tight.parameters.size());
  for (size_t b = 0; b < stat.parameters.size(); ++b) {
    const auto& p = stat.parameters[b];
    const auto& q = tight.parameters[b];
    for (size_t i = 0; i < p.values.size() && i < q.stddev.size(); ++i) {
      if (!std::isfinite(q.stddev[i]) || !q.stddev_names.empty()) continue;
      EXPECT_LE(std::abs(p.values[i] - q.values[i]), 0.1 * q.stddev[i]) << p.block << "[" << i << "]";
    }
  }
  EXPECT_THROW(ParseModelYaml("solver: {statistical_tolerance: -1}\n" + model, "m"),
               std::invalid_argument);
}

// A progress callback that throws (the Python binding's stop on Ctrl-C) stops the solve at that
// iteration: the exception reaches FitModel's caller, kept while Ceres aborts the solve rather
// than thrown through it, and the callback is not called again.
TEST(FitModel, AnExceptionFromProgressStopsTheSolveAndReachesTheCaller) {
  const auto stations = NoisyPolynomialStations(5, 3, 300);
  struct Stop {};
  ModelSpec spec =
      ParseModelYaml("terms:\n  - type: sensor_offset\n  - type: polynomial\n    degree: 3\n", "m");
  int calls = 0;
  FitOptions options;
  options.progress = [&calls](int iteration, double) {
    ++calls;
    if (iteration >= 1) throw Stop();
  };
  EXPECT_THROW(FitModel(stations, &spec, options), Stop);
  EXPECT_EQ(calls, 2);  // iterations 0 and 1; none after the throw
}

// A set with no error before (error-free data, or a set the model reproduces exactly) has no
// defined improvement. ImprovementPercent gives -inf (an error where there was none) or NaN; in
// the calibration file's fit_statistics they are null, since that file holds finite numbers only
// (-inf made such a fit fail at save, after the fit).
// A model whose whitened residuals overflow (position noise 1e-160 mm: a millimetre's misfit is
// 1e160 sigma, its square beyond the largest double) has an infinite cost from the start. Ceres
// then reports CONVERGENCE ("|cost_change|/cost: nan <= 1e-12") after 0 iterations: the fit said
// "converged", and trackcal-fit wrote the start values as the calibration with exit status 0.
TEST(FitModel, AnInfiniteCostIsAFailureNotAConvergence) {
  std::mt19937 rng(23);
  const auto truth = RandomPolynomial(2, &rng);
  const auto stations = NoiseFreeStations(*truth, 100, &rng);
  for (const std::string terms : {"[{type: sensor_offset}, {type: polynomial, degree: 1}]",
                                  "[{type: polynomial, degree: 1}]"}) {  // joint and linear paths
    SCOPED_TRACE(terms);
    ModelSpec spec =
        ParseModelYaml("noise: {position_mm: 1e-160}\nterms: " + terms + "\n", "m.yaml");
    const FitResult result = FitModel(stations, &spec);
    EXPECT_FALSE(std::isfinite(result.final_cost));
    EXPECT_FALSE(result.converged) << result.solver_message;
    EXPECT_EQ(result.termination_type, "FAILURE") << result.solver_message;
    EXPECT_TRUE(result.Failed());
    EXPECT_THAT(result.solver_message, ::testing::HasSubstr("cost is not finite"));
    EXPECT_GE(result.iterations, 0);
    EXPECT_EQ(result.ToJson()["termination_type"], "FAILURE");
    // No covariance of it (a candidate's in trackcal-fit diagnose crashed in its eigensolver).
    EXPECT_TRUE(result.covariance_estimator.empty()) << result.covariance_estimator;
    EXPECT_EQ(result.covariance_message, "not computed: the fit failed");
  }
}

// Stopped at solver.max_iterations: reported as such (not a failure: the values are the best the
// solver found, and the calibration records converged: false).
TEST(FitModel, StoppedAtTheIterationLimitIsNoConvergence) {
  std::mt19937 rng(29);
  const auto truth = RandomPolynomial(2, &rng);
  const auto stations = NoiseFreeStations(*truth, 100, &rng);
  ModelSpec spec = ParseModelYaml(
      "solver: {max_iterations: 1}\nterms: [{type: sensor_offset}, {type: polynomial, degree: "
      "1}]\n",
      "m.yaml");
  const FitResult result = FitModel(stations, &spec);
  EXPECT_FALSE(result.converged) << result.solver_message;
  EXPECT_EQ(result.termination_type, "NO_CONVERGENCE") << result.solver_message;
  EXPECT_FALSE(result.Failed());
  EXPECT_TRUE(std::isfinite(result.final_cost));
}

TEST(Table1ToJson, AnUndefinedImprovementIsNull) {
  Table1 t;
  t.set_name = "calib";
  t.before.position_mm = {3, 0.0, 0.0, 0.0};
  t.after.position_mm = {3, 1.0, 0.5, 2.0};
  t.before.orientation_deg = {3, 2.0, 1.0, 4.0};
  t.after.orientation_deg = {3, 1.0, 0.5, 2.0};
  const nlohmann::json j = Table1ToJson(t);
  EXPECT_TRUE(j["improvement_percent"]["position_mean"].is_null()) << j.dump();
  EXPECT_DOUBLE_EQ(j["improvement_percent"]["orientation_mean"].get<double>(), 50.0);
  // And the text table says n/a there, not "-inf %".
  const std::string text = FormatTable1(t);
  EXPECT_EQ(text.find("inf"), std::string::npos) << text;
  EXPECT_NE(text.find("n/a"), std::string::npos) << text;
}

TEST(CrossValidate, DeterministicFolds) {
  std::mt19937 rng(17);
  const auto truth = RandomPolynomial(1, &rng);
  const auto stations = NoiseFreeStations(*truth, 60, &rng);
  auto make = [] { return ParseModelYaml("terms: [{type: polynomial, degree: 1}]", "m"); };
  const Table1 a = CrossValidate(stations, make, 5);
  const Table1 b = CrossValidate(stations, make, 5);
  EXPECT_EQ(a.after.position_mm.count, 60);
  EXPECT_DOUBLE_EQ(a.after.position_mm.mean, b.after.position_mm.mean);
  // Noise-free data of the same model form: held-out stations inside the training box are corrected
  // exactly (errors in mm; rounding ~1e-9 mm); the few outside it get the clamped correction.
  EXPECT_LT(a.after.position_mm.median, 1e-6);
  EXPECT_LT(a.after.position_mm.mean, 0.2 * a.before.position_mm.mean);
  EXPECT_THROW(CrossValidate(stations, make, 1), std::invalid_argument);
}

// A fold whose fit failed was corrected by its start values and counted as held-out error. The
// overflowing noise of AnInfiniteCostIsAFailureNotAConvergence makes every fold fail.
TEST(CrossValidate, AFailedFoldIsAnErrorNamingIt) {
  std::mt19937 rng(17);
  const auto truth = RandomPolynomial(2, &rng);  // not a degree-1 model's: a residual to overflow
  const auto stations = NoiseFreeStations(*truth, 60, &rng);
  auto make = [] {
    return ParseModelYaml(
        "noise: {position_mm: 1e-160}\nterms: [{type: sensor_offset}, {type: polynomial, degree: "
        "1}]",
        "m");
  };
  try {
    CrossValidate(stations, make, 3);
    ADD_FAILURE() << "no error";
  } catch (const std::runtime_error& e) {
    EXPECT_THAT(e.what(),
                ::testing::HasSubstr("cross-validation fold 1 of 3: the fit failed (FAILURE"));
  }
}

// testing::WanderingMisfitStream (100 Hz, 20 s, a misfit of 0.3 mm wandering with a 0.5 s
// correlation time) along a Lissajous path, with white noise of 0.05 mm. `times` false: the same
// samples without times (static stations).
std::vector<FitStation> WanderingMisfitStream(unsigned seed, bool times = true) {
  const auto lissajous = [](double t) {
    return Rigid3d(
        Eigen::Quaterniond(Eigen::AngleAxisd(0.8 * std::sin(0.9 * t), Eigen::Vector3d::UnitZ())),
        Eigen::Vector3d(0.3 * std::sin(2 * M_PI * t / 7), 0.3 * std::sin(2 * M_PI * t / 5 + 1),
                        -0.5 + 0.1 * std::sin(2 * M_PI * t / 11)));
  };
  return testing::WanderingMisfitStream(lissajous, seed, /*white_sigma=*/5e-5,
                                        Eigen::Vector3d::Zero(), times);
}

TEST(CrossValidationFolds, StaticStationsByIndexStreamSamplesByBlocksOfTime) {
  const auto static_stations = WanderingMisfitStream(1, /*times=*/false);
  bool by_blocks = true;
  const std::vector<int> fixed =
      CrossValidationFolds(static_stations, 5, kDefaultSerialBlocks, &by_blocks);
  EXPECT_FALSE(by_blocks);
  for (size_t i = 0; i < fixed.size(); ++i) EXPECT_EQ(fixed[i], static_cast<int>(i % 5)) << i;

  const auto stream = WanderingMisfitStream(1);
  const std::vector<int> folds = CrossValidationFolds(stream, 5, kDefaultSerialBlocks, &by_blocks);
  EXPECT_TRUE(by_blocks);
  const std::vector<int> blocks = SerialTestBlocks(stream, kDefaultSerialBlocks, 5);
  ASSERT_EQ(blocks.size(), stream.size());
  ASSERT_EQ(folds.size(), stream.size());
  int changes = 0;
  for (size_t i = 0; i < folds.size(); ++i) {
    EXPECT_EQ(folds[i], blocks[i] % 5) << i;
    if (i > 0) changes += folds[i] != folds[i - 1];
  }
  EXPECT_EQ(changes, 31);  // 32 blocks of 62-63 samples (0.6 s): neighbours share their fold
  // serial_blocks 0: the static rule for every capture.
  EXPECT_EQ(CrossValidationFolds(stream, 5, 0, &by_blocks), fixed);
  EXPECT_FALSE(by_blocks);
}

// A stream's cross-validation holds out blocks of time. With folds i % k every held-out sample's
// neighbours (10 ms away, the same misfit to 2 %) were in the training folds, and a flexible model
// that follows the misfit along the path was scored as if it generalised.
TEST(CrossValidate, StreamSamplesAreHeldOutInBlocksOfTime) {
  auto make = [] {
    return ParseModelYaml(
        "noise: {position_mm: 0.3}\n"
        "terms: [{type: polynomial, degree: 4, orientation: false, ridge: 0}]",
        "m");
  };
  const auto stream = WanderingMisfitStream(1);
  ModelSpec spec = make();
  FitOptions options;
  options.compute_covariance = false;
  const FitResult fit = FitModel(stream, &spec, options);
  ASSERT_FALSE(fit.Failed());
  const double in_sample = EvaluateTable1(fit.chain, stream, "calib").after.position_mm.mean;
  // The truth: the same path with a misfit of its own (another seed), which the fit never saw.
  const double truth =
      EvaluateTable1(fit.chain, WanderingMisfitStream(2), "valid").after.position_mm.mean;
  const Table1 blocked = CrossValidate(stream, make, 5);
  EXPECT_EQ(blocked.set_name, "cross-validation (5-fold, blocks of time)");
  EXPECT_EQ(blocked.after.position_mm.count, 2000);
  // The same samples as static stations keep folds i % k and the name without blocks.
  const Table1 by_index = CrossValidate(WanderingMisfitStream(1, false), make, 5);
  EXPECT_EQ(by_index.set_name, "cross-validation (5-fold)");
  std::cout << "in-sample " << in_sample << " mm, folds i % 5 " << by_index.after.position_mm.mean
            << " mm, blocks of time " << blocked.after.position_mm.mean << " mm, truth " << truth
            << " mm\n";
  // Measured: in-sample 0.242 mm, folds i % 5 0.243 mm (the neighbours trained on: in-sample to
  // 0.3 %), blocks of time 0.426 mm, truth 0.614 mm. Before the fix the stream's table was the
  // i % 5 one (0.243 mm). The thresholds sit between: blocks at least 1.4 times the in-sample
  // error (1.76 measured), i % 5 within 5 % of it, and blocks not above the truth by more than
  // 20 % (a stream's blocks still train on the path on either side of the held-out block).
  EXPECT_LT(by_index.after.position_mm.mean, 1.05 * in_sample);
  EXPECT_GT(blocked.after.position_mm.mean, 1.4 * in_sample);
  EXPECT_GT(blocked.after.position_mm.mean, 1.4 * by_index.after.position_mm.mean);
  EXPECT_LT(blocked.after.position_mm.mean, 1.2 * truth);
  EXPECT_GT(truth, 1.4 * in_sample);  // the scenario: the fit follows this stream's misfit
}

// The ridge weights a fit's polynomial used (its Describe() in FitResult::terms).
std::vector<double> RidgeUsed(const FitResult& result) {
  for (const auto& t : result.terms) {
    const auto& d = t.contains("describe") ? t["describe"] : t;
    if (d.contains("ridge_used")) return d["ridge_used"].get<std::vector<double>>();
  }
  return {};
}

// FitOptions::start: a model with an added effect starts at the fitted smaller model's optimum
// (its physical values, polynomial coefficients, normalisation and ridge weight) with the added
// effect where the file puts it. Paper preset, calibration set; the pose metric switched off
// (amplification_threshold 1e9), so the start's cost is the smaller model's final cost exactly.
TEST(FitModel, StartFromASmallerModelsOptimum) {
  const sim::Simulator simulator(sim::LoadScene("paper"));
  const auto calib = StationsOfSet(simulator.Generate().poses, "calib");
  const std::string head =
      "noise: {amplification_threshold: 1e9}\nterms:\n  - type: sensor_offset\n";
  const std::string poly = "  - {type: polynomial, degree: 3, ridge: auto}\n";
  ModelSpec base = ParseModelYaml(head + poly, "base");
  const FitResult base_fit = FitModel(calib, &base);
  ASSERT_TRUE(base_fit.converged) << base_fit.solver_message;
  const FitStart start = TakeFitStart(base);
  FitOptions from;
  from.start = &start;
  // A dipole too weak to move a report by a nanometre: the added effect as the file writes
  // it, not where the physical group's own refinement (without the polynomial) would put it.
  const std::string added =
      "  - {type: dipole, location_in_transmitter: [0.5, 0.6, -0.4], polarisability_m3: 1e-12}\n";
  ModelSpec bigger = ParseModelYaml(head + added + poly, "bigger");
  const FitResult fit = FitModel(calib, &bigger, from);
  // 1e-6 relative: the start is the base's optimum up to the dipole's field (1e-12 m^3 at 0.3 m
  // moves a report by ~1e-10 m) and rounding.
  EXPECT_NEAR(fit.initial_cost, base_fit.final_cost, 1e-6 * base_fit.final_cost);
  EXPECT_LE(fit.final_cost, base_fit.final_cost * (1 + 1e-9));
  EXPECT_EQ(RidgeUsed(fit), RidgeUsed(base_fit));
  // Without the start, the same model starts elsewhere (the polynomial on what the group alone
  // leaves, its weight chosen afresh): the start is what made the costs equal.
  ModelSpec fresh = ParseModelYaml(head + added + poly, "fresh");
  const FitResult fresh_fit = FitModel(calib, &fresh);
  EXPECT_GT(std::abs(fresh_fit.initial_cost - base_fit.final_cost), 1e-3 * base_fit.final_cost);

  // The same start read back from the fit's JSON (`trackcal-fit fit --start`).
  const FitStart from_json = FitStartFromJson(base_fit.ToJson(), "base.json");
  ASSERT_EQ(from_json.terms.size(), start.terms.size());
  for (const auto& [key, term] : start.terms) {
    ASSERT_TRUE(from_json.terms.count(key)) << key.first << " " << key.second;
    EXPECT_EQ(from_json.terms.at(key).prepared, term.prepared) << key.second;
    EXPECT_EQ(from_json.terms.at(key).blocks, term.blocks) << key.second;
  }
  EXPECT_THROW(FitStartFromJson(nlohmann::json::object(), "x.json"), std::invalid_argument);
}

// A base without physical terms: an added effect before its polynomial starts at the file's values,
// not where the new physical group's own refinement (without the polynomial) puts it, so the start
// is again the base's optimum.
TEST(FitModel, StartAddsAnEffectBeforeTheHeldPolynomial) {
  const sim::Simulator simulator(sim::LoadScene("paper"));
  const auto calib = StationsOfSet(simulator.Generate().poses, "calib");
  const std::string head = "terms:\n";
  const std::string poly = "  - {type: polynomial, degree: 3, ridge: auto}\n";
  ModelSpec base = ParseModelYaml(head + poly, "base");
  const FitResult base_fit = FitModel(calib, &base);
  const FitStart start = TakeFitStart(base);
  FitOptions from;
  from.start = &start;
  ModelSpec bigger = ParseModelYaml(head + "  - type: receiver_gain\n" + poly, "bigger");
  const FitResult fit = FitModel(calib, &bigger, from);
  // Receiver gains at the identity (the file's start) leave the base's chain unchanged. Every
  // station's report is resolved by the group's inverse (the paper room amplifies its noise at
  // most ~1.3 times), so each is fitted in the pose form (fit/fit_engine.cc, BuildProblem): 1e-6
  // relative is the inverse's Newton steps, solved to a tolerance, not exactly. In the report form
  // (amplification_threshold: 1e9, every station) the free-space chord's second-order term,
  // O(d^2 / range) for a misfit d, made it 1.0e-4 (measured, session 20). (The group refined alone
  // would take gains from the paper room's distortion, which the polynomial then corrects a second
  // time.)
  EXPECT_NEAR(fit.initial_cost, base_fit.final_cost, 1e-6 * base_fit.final_cost);
  EXPECT_LE(fit.final_cost, base_fit.final_cost * (1 + 1e-6));
}

// A start whose polynomial determined every direction (max_amplification: 0) into a fit that holds
// the direction 4 heights do not determine: the started coefficients are projected onto the held
// fit's subspace, so the fit ends where it ends without a start (the polynomial alone is linear,
// its optimum in the subspace unique). Before, their undetermined component stayed for the whole
// fit.
TEST(FitModel, StartIsProjectedOntoAPolynomialsDeterminedSubspace) {
  std::mt19937 rng(11);
  const auto truth = RandomPolynomial(2, &rng);
  const std::vector<FitStation> stations = FourHeightGrid(*truth, &rng);
  // A sensor offset before the polynomial (the stations have none: it stays near zero), since a
  // lone polynomial's fit is its linear initialisation and takes no start.
  const std::string head =
      "noise: {amplification_threshold: 1e9}\nterms:\n  - type: sensor_offset\n";
  ModelSpec all = ParseModelYaml(
      head + "  - {type: polynomial, degree: 4, max_amplification: 0}\n", "all");
  ASSERT_TRUE(FitModel(stations, &all).converged);
  const FitStart start = TakeFitStart(all);
  const std::string held_model = head + "  - {type: polynomial, degree: 4}\n";
  ModelSpec fresh = ParseModelYaml(held_model, "fresh");
  const FitResult fresh_fit = FitModel(stations, &fresh);
  ModelSpec held = ParseModelYaml(held_model, "held");
  FitOptions from;
  from.start = &start;
  const FitResult fit = FitModel(stations, &held, from);
  int subspace_blocks = 0;
  for (const auto& block : held.terms.back()->blocks()) {
    if (block.ambient_from_tangent.size() == 0) continue;
    ++subspace_blocks;
    const Eigen::MatrixXd& b = block.ambient_from_tangent;
    const Eigen::Map<const Eigen::VectorXd> v(block.values.data(), block.size());
    const Eigen::VectorXd inside = b * (b.transpose() * b).ldlt().solve(b.transpose() * v);
    // Rounding of the solver's steps only (coefficients of a few mm and degrees).
    EXPECT_LT((v - inside).norm(), 1e-9 * (1.0 + v.norm())) << block.name;
  }
  ASSERT_EQ(subspace_blocks, 2) << "4 heights leave degree 4 a direction in both parts";
  // 1e-6 relative: both solves stop at the solver's function tolerance on the same optimum.
  EXPECT_NEAR(fit.final_cost, fresh_fit.final_cost, 1e-6 * fresh_fit.final_cost);
}

// The full paper capture with the hidden toolbox (seed 2): its calibration stations.
std::vector<FitStation> PaperToolboxCalibration() {
  sim::Scene scene = sim::LoadScene("paper");
  scene.seed = 2;
  scene.hidden.Enable("ferromagnetic_object");
  return StationsOfSet(sim::Simulator(scene).Generate().poses, "calib");
}

// The demo's step-3 model on that capture (workbench frame, toolbox, floor plane, then the paper's
// polynomial).
constexpr char kPaperToolboxStep3[] =
    "terms:\n  - type: dipole\n    location_in_transmitter: [0.5078, -0.0242, 0.3584]\n"
    "    polarisability_m3: -0.008322\n  - type: dipole\n    name: dipole_2\n"
    "    location_in_transmitter: [0.5883, 0.9719, -0.5163]\n    polarisability_m3: 0.002644\n"
    "  - type: plane\n    point_in_transmitter: [-0.0439, -0.1479, 0.6636]\n"
    "    normal_in_transmitter: [-0.06437, -0.21701, 0.97404]\n    attenuation: 0.1782\n"
    "  - type: polynomial\n    degree: 4\n    ridge: auto\n";

// solver.leave_out_unresolved on that capture, fitted with the frame, the toolbox and the floor
// plane where the demo's loop placed them: the stations next to the toolbox that the model does not
// resolve are left out, the others fitted, and the setting is off by default.
TEST(FitModel, LeaveOutUnresolvedStations) {
  const auto calib = PaperToolboxCalibration();
  const std::string model = kPaperToolboxStep3;
  ModelSpec kept = ParseModelYaml(model, "kept");
  EXPECT_FALSE(kept.leave_out_unresolved) << "the default";
  const FitResult all = FitModel(calib, &kept);
  EXPECT_TRUE(all.left_out.empty());
  ASSERT_FALSE(all.unresolved.empty()) << "stations next to the toolbox, so the test can fail";
  ModelSpec spec = ParseModelYaml(model + "solver: {leave_out_unresolved: true}\n", "left");
  ASSERT_TRUE(spec.leave_out_unresolved);
  const FitResult fit = FitModel(calib, &spec);
  ASSERT_FALSE(fit.left_out.empty());
  EXPECT_LE(fit.left_out.size(), kMaxLeftOutFraction * calib.size());
  // The solve's residuals are the other stations' (6 each) and the polynomial ridge's.
  EXPECT_EQ(all.num_residuals - fit.num_residuals, 6 * static_cast<int>(fit.left_out.size()));
  // Every station the solution leaves unresolved is out (a station resolved again at the last of
  // the kMaxLeaveOutPasses passes stays out: measured 25 out, 23 unresolved at the end).
  for (const auto& u : fit.unresolved) {
    EXPECT_NE(std::find(fit.left_out.begin(), fit.left_out.end(), u.station), fit.left_out.end())
        << u.station;
  }
  // Without them the others are fitted better, under each chain on the same stations (measured:
  // 536 against 599 mm^2 over 455 stations; 542 against 1099 while the fit's residual stalled at
  // those stations, before the report-space residual).
  std::vector<FitStation> others;
  for (const auto& s : calib) {
    if (std::find(fit.left_out.begin(), fit.left_out.end(), s.station) == fit.left_out.end()) {
      others.push_back(s);
    }
  }
  auto sum_squares_mm = [&](const FitResult& f) {
    double sum = 0.0;
    for (const auto& s : others) {
      sum += (f.chain.Apply(s.reported).pose.translation - s.reference.translation)
                 .squaredNorm() * 1e6;
    }
    return sum;
  };
  const double left_ss = sum_squares_mm(fit), all_ss = sum_squares_mm(all);
  std::cout << fit.left_out.size() << " stations left out; the others' sum of squared position "
            << "errors " << left_ss << " mm^2 against " << all_ss << " with them\n";
  EXPECT_LT(left_ss, all_ss);
  const nlohmann::json json = fit.ToJson();
  EXPECT_EQ(json.at("left_out").get<std::vector<int>>(), fit.left_out);
  EXPECT_THROW(ParseModelYaml(model + "solver: {leave_out_unresolved: sometimes}\n", "bad"),
               std::invalid_argument);
}

// The fast cross-validation's fold refits from such a fit leave its left-out stations out of every
// fold's training (FoldRefitOptions::left_out): each fold's correction is the one refitted from
// the others alone, and it still corrects the stations left out.
TEST(RefitFoldsFromFull, LeaveOutTheStationsTheFullFitLeftOut) {
  const auto calib = PaperToolboxCalibration();
  ModelSpec spec =
      ParseModelYaml(std::string(kPaperToolboxStep3) + "solver: {leave_out_unresolved: true}\n",
                     "left");
  FitOptions options;
  options.compute_covariance = false;
  const FitResult fit = FitModel(calib, &spec, options);
  ASSERT_FALSE(fit.left_out.empty()) << "stations next to the toolbox, so the test can fail";
  constexpr int kFolds = 5;
  std::vector<int> fold_of(calib.size());
  for (size_t i = 0; i < calib.size(); ++i) fold_of[i] = static_cast<int>(i) % kFolds;
  FoldRefitOptions refit_options;
  refit_options.left_out = fit.left_out;
  const std::vector<FoldRefit> refits =
      RefitFoldsFromFull(calib, &spec, fold_of, kFolds, refit_options);

  std::vector<FitStation> others;
  std::vector<int> others_fold_of;
  for (size_t i = 0; i < calib.size(); ++i) {
    if (std::find(fit.left_out.begin(), fit.left_out.end(), calib[i].station) !=
        fit.left_out.end()) {
      continue;
    }
    others.push_back(calib[i]);
    others_fold_of.push_back(fold_of[i]);
  }
  const std::vector<FoldRefit> from_others =
      RefitFoldsFromFull(others, &spec, others_fold_of, kFolds);
  // With the left-out stations in training the folds differ.
  const std::vector<FoldRefit> with_them = RefitFoldsFromFull(calib, &spec, fold_of, kFolds);
  ASSERT_EQ(refits.size(), from_others.size());
  // Compared on the stations fitted (the left-out ones sit where the inverse is ill-conditioned,
  // which magnifies any difference of the values).
  double same_mm = 0.0, with_them_mm = 0.0;
  for (size_t f = 0; f < refits.size(); ++f) {
    EXPECT_EQ(refits[f].solver_refit, from_others[f].solver_refit) << "fold " << f;
    for (const auto& s : others) {
      const Eigen::Vector3d a = refits[f].chain.Apply(s.reported).pose.translation;
      same_mm = std::max(
          same_mm, (a - from_others[f].chain.Apply(s.reported).pose.translation).norm() * 1e3);
      with_them_mm = std::max(
          with_them_mm, (a - with_them[f].chain.Apply(s.reported).pose.translation).norm() * 1e3);
    }
  }
  std::cout << "fold corrections against the refits from the others alone: up to " << same_mm
            << " mm; against those with the left-out stations in training: up to " << with_them_mm
            << " mm\n";
  // The same steps on the same residuals: measured 7e-13 mm on these stations (up to 2e-6 m at
  // the left-out ones), and 4.9 mm against the folds trained on the left-out stations too.
  EXPECT_LT(same_mm, 0.01);
  EXPECT_GT(with_them_mm, 0.1);
}

// The station residual's Jacobian through a physical group followed by a polynomial, and by a
// fitted clock offset, against central differences, at stations 0.1-0.2 m from a strong object.
// The group is evaluated toward the reference pulled back through the polynomial, so the
// polynomial's coefficients and the clock offset also move the group's output (EvaluateChain's
// d_output_d_target); without that term their columns are off by O(1) of themselves here.
TEST(EvaluateStationResidual, ChainRuleThroughAGroupTowardAPulledBackTarget) {
  ModelSpec spec = ParseModelYaml(R"(noise: {position_mm: 0.5, orientation_deg: 0.1}
terms:
  - type: sensor_offset
    receiver_from_body:
      rotation_xyzw: [0.1, -0.05, 0.02, 0.99369]
      translation: [0.02, 0.01, -0.03]
  - type: dipole
    location_in_transmitter: [0.42, -0.08, -0.36]
    polarisability_m3: 0.002
  - type: polynomial
    degree: 2
)",
                                  "chain.yaml");
  std::mt19937 rng(7);
  std::normal_distribution<double> normal(0.0, 1.0);
  std::vector<FitStation> stations;
  for (const Eigen::Vector3d& p :
       {Eigen::Vector3d(0.3, -0.2, -0.5), Eigen::Vector3d(0.5, 0.05, -0.3),
        Eigen::Vector3d(0.55, -0.2, -0.45)}) {
    FitStation s;
    s.reference = Rigid3d(Eigen::Quaterniond(Eigen::AngleAxisd(0.4, p.normalized())), p);
    s.reported = Rigid3d(s.reference.rotation * Eigen::Quaterniond(Eigen::AngleAxisd(
                                                    0.03, Eigen::Vector3d(1, -1, 2).normalized())),
                         p + Eigen::Vector3d(0.01, -0.02, 0.015));
    s.reference_velocity = Eigen::Vector3d(0.2, -0.1, 0.3);
    s.reference_angular_velocity = Eigen::Vector3d(0.5, 0.2, -0.4);
    stations.push_back(s);
  }
  for (auto& term : spec.terms) term->Prepare(stations);
  // Polynomial coefficients of 1e-3 (a correction of a few mm over the box, as a fit leaves).
  for (auto& block : spec.terms[1]->blocks()) {
    for (double& v : block.values) v = 1e-3 * normal(rng);
  }
  for (const FitStation& station : stations) {
    Eigen::Matrix<double, 6, 1> r;
    std::vector<Eigen::MatrixXd> jacobians;
    const double dt = 0.004;
    ASSERT_TRUE(EvaluateStationResidual(spec, station, dt, &r, &jacobians));
    // Every bound block in order, then the clock offset.
    std::vector<double*> values;
    for (auto& term : spec.terms) {
      for (auto& block : term->blocks()) values.push_back(block.values.data());
    }
    double dt_value = dt;
    values.push_back(&dt_value);
    ASSERT_EQ(values.size(), jacobians.size());
    // Central differences, h = 1e-7 of residuals whitened by 0.5 mm: entries up to ~1e4, rounding
    // ~1e-16 * 1e3 / 1e-7 = 1e-6 of them. The polynomial's and the offset's columns also carry
    // the pull-back's three fixed-point steps (PullBack), which the derivative takes as
    // converged: their relative error |dP/dz - I|^3 is up to 2.5e-4 on this 0.25 m box; 1e-3 of
    // the column's norm.
    const double h = 1e-7;
    for (size_t b = 0; b < values.size(); ++b) {
      const bool group = b < spec.terms[0]->blocks().size();
      for (Eigen::Index c = 0; c < jacobians[b].cols(); ++c) {
        const double saved = values[b][c];
        Eigen::Matrix<double, 6, 1> plus, minus;
        std::vector<Eigen::MatrixXd> unused;
        values[b][c] = saved + h;
        ASSERT_TRUE(EvaluateStationResidual(spec, station, dt_value, &plus, &unused));
        values[b][c] = saved - h;
        ASSERT_TRUE(EvaluateStationResidual(spec, station, dt_value, &minus, &unused));
        values[b][c] = saved;
        const Eigen::Matrix<double, 6, 1> numeric = (plus - minus) / (2 * h);
        const double scale = std::max(1.0, numeric.norm());
        EXPECT_LT((jacobians[b].col(c) - numeric).norm(), (group ? 1e-5 : 1e-3) * scale)
            << "block " << b << " coordinate " << c << ": analytic "
            << jacobians[b].col(c).transpose() << ", numeric " << numeric.transpose();
      }
    }
  }
}

}  // namespace
}  // namespace trackcal::fit
