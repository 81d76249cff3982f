#include "fit/terms_polynomial.h"

#include <gtest/gtest.h>

#include <random>

namespace trackcal::fit {
namespace {

// Random stations in a 1 m box whose reference is the reported pose corrected by `truth`.
std::vector<FitStation> MakeStations(const PolynomialTerm& truth, int n, std::mt19937* rng) {
  std::uniform_real_distribution<double> pos(-0.5, 0.5);
  std::normal_distribution<double> normal;
  const auto correction = truth.ToCorrection();
  std::vector<FitStation> out;
  for (int i = 0; i < n; ++i) {
    FitStation s;
    s.reported.translation = Eigen::Vector3d(pos(*rng), pos(*rng), 0.3 + pos(*rng));
    s.reported.rotation =
        Eigen::Quaterniond(normal(*rng), normal(*rng), normal(*rng), normal(*rng)).normalized();
    s.reference = correction->Apply(s.reported).pose;
    out.push_back(s);
  }
  return out;
}

PolynomialTerm RandomTruth(int degree, std::mt19937* rng) {
  PolynomialTermOptions options;
  options.degree = degree;
  options.input_offset = Eigen::Vector3d(0, 0, 0.3);
  options.input_scale = Eigen::Vector3d(0.5, 0.5, 0.5);
  PolynomialTerm truth(options);
  std::normal_distribution<double> normal;
  for (auto& v : truth.blocks()[0].values) v = 0.005 * normal(*rng);  // a few mm
  for (auto& v : truth.blocks()[1].values) v = 0.01 * normal(*rng);   // ~1 degree
  return truth;
}

TEST(PolynomialTerm, Nominal_LinearFitRecoversNoiseFreeCoefficients) {
  std::mt19937 rng(7);
  for (int degree : {0, 1, 4, 8}) {
    const PolynomialTerm truth = RandomTruth(degree, &rng);
    const auto stations = MakeStations(truth, 3 * NumPolynomialTerms(degree) + 50, &rng);
    PolynomialTermOptions options;
    options.degree = degree;
    PolynomialTerm fitted(options);
    fitted.Prepare(stations);
    ASSERT_TRUE(fitted.InitializeLinear(stations, Eigen::Vector2d(1e-3, 1e-3)));
    // The fitted normalisation (data bounding box) differs from the truth's, so compare the
    // corrections rather than the coefficients: noise-free data must be reproduced to rounding
    // (1e-6 relative to the millimetre-scale errors is ~1e-9 m; allow 1e-10 m / 1e-10 rad).
    const auto correction = fitted.ToCorrection();
    for (const auto& s : stations) {
      const Rigid3d corrected = correction->Apply(s.reported).pose;
      EXPECT_LT(PositionErrorNorm(corrected, s.reference), 1e-10) << "degree " << degree;
      EXPECT_LT(OrientationErrorAngle(corrected, s.reference), 1e-10) << "degree " << degree;
    }
  }
}

TEST(PolynomialTerm, SameNormalisationRecoversCoefficientsTo1e6Relative) {
  std::mt19937 rng(3);
  const PolynomialTerm truth = RandomTruth(4, &rng);
  const auto stations = MakeStations(truth, 400, &rng);
  PolynomialTerm fitted(truth.options());  // explicit normalisation: Prepare keeps it
  fitted.Prepare(stations);
  ASSERT_TRUE(fitted.InitializeLinear(stations, Eigen::Vector2d(1e-3, 1e-3)));
  for (size_t b = 0; b < 2; ++b) {
    const auto& t = truth.blocks()[b].values;
    const auto& f = fitted.blocks()[b].values;
    const double scale = Eigen::Map<const Eigen::VectorXd>(t.data(), t.size()).cwiseAbs().maxCoeff();
    for (size_t i = 0; i < t.size(); ++i) {
      EXPECT_NEAR(f[i], t[i], /*rtol=*/1e-6 * scale) << truth.blocks()[b].coordinate_names[i];
    }
  }
}

TEST(PolynomialTerm, JacobiansMatchCentralDifferences) {
  std::mt19937 rng(11);
  const PolynomialTerm term = RandomTruth(3, &rng);
  AmbientPose input = ToAmbient(
      Rigid3d(Eigen::Quaterniond(0.9, 0.1, -0.3, 0.2).normalized(), Eigen::Vector3d(0.1, -0.2, 0.4)));
  const StationBinding binding = term.Bind(input);
  std::vector<const double*> values = {term.blocks()[0].values.data(),
                                       term.blocks()[1].values.data()};
  TermEvaluation eval;
  ASSERT_TRUE(term.Evaluate(binding, values.data(), input, true, &eval));
  TermEvaluation plain;
  ASSERT_TRUE(term.Evaluate(binding, values.data(), input, false, &plain));
  EXPECT_LT((plain.output - eval.output).norm(), 1e-15);
  // Output matches the runtime correction.
  const Rigid3d runtime = term.ToCorrection()->Apply(FromAmbient(input)).pose;
  EXPECT_LT((ToAmbient(runtime).head<3>() - eval.output.head<3>()).norm(), 1e-14);
  const double h = 1e-6;  // central differences: truncation ~h^2, rounding ~1e-16/h ~ 1e-10
  for (int c = 0; c < 7; ++c) {
    AmbientPose plus = input, minus = input;
    plus[c] += h;
    minus[c] -= h;
    TermEvaluation ep, em;
    term.Evaluate(binding, values.data(), plus, false, &ep);
    term.Evaluate(binding, values.data(), minus, false, &em);
    const AmbientPose numeric = (ep.output - em.output) / (2 * h);
    EXPECT_LT((numeric - eval.d_output_d_input.col(c)).norm(), 1e-7) << "input " << c;
  }
  std::vector<double> coefficients = term.blocks()[0].values;
  std::vector<const double*> perturbed = {coefficients.data(), values[1]};
  for (size_t c = 0; c < coefficients.size(); c += 7) {
    const double v = coefficients[c];
    coefficients[c] = v + h;
    TermEvaluation ep, em;
    term.Evaluate(binding, perturbed.data(), input, false, &ep);
    coefficients[c] = v - h;
    term.Evaluate(binding, perturbed.data(), input, false, &em);
    coefficients[c] = v;
    const AmbientPose numeric = (ep.output - em.output) / (2 * h);
    EXPECT_LT((numeric - eval.d_output_d_blocks[0].col(static_cast<int>(c))).norm(), 1e-7);
  }
}

}  // namespace
}  // namespace trackcal::fit
