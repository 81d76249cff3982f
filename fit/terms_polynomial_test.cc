#include "fit/terms_polynomial.h"

#include <gtest/gtest.h>

#include <Eigen/Eigenvalues>

#include <algorithm>
#include <cstdlib>
#include <iostream>
#include <map>
#include <set>
#include <random>
#include <stdexcept>

#include "core/correction.h"
#include "fit/model_file.h"
#include "fit/sim_test_support.h"

namespace trackcal::fit {
namespace {

using testing::FourHeightGrid;

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


// On a grid with 4 heights, z^4 equals a cubic at every station: the degree-4 fit has a near-null
// direction that the noise sets. ridge: auto (leave-one-out, one-standard-error rule) shrinks it, so
// the polynomial stays near the truth between and beyond the heights, where the plain fit does not.
TEST(PolynomialTerm, AFourHeightGridsUndeterminedDirectionIsHeldOrShrunk) {
  std::mt19937 rng(11);
  const PolynomialTerm truth = RandomTruth(2, &rng);  // smooth: what the grid does determine
  const auto correction = truth.ToCorrection();
  const std::vector<FitStation> stations = FourHeightGrid(*correction, &rng);
  auto worst_between_heights = [&](const PolynomialTerm& fitted) {
    const auto c = fitted.ToCorrection();
    double worst = 0;
    for (double z = 0.1; z <= 0.5; z += 0.01) {  // 5 cm beyond the grid's heights on both sides
      Rigid3d p;
      p.translation = Eigen::Vector3d(0.3, -0.2, z);
      worst = std::max(worst, PositionErrorNorm(c->Apply(p).pose, correction->Apply(p).pose));
    }
    return worst;
  };
  PolynomialTermOptions options;
  options.degree = 4;
  options.max_amplification = 0;  // fit every direction
  PolynomialTerm plain(options);
  plain.Prepare(stations);
  ASSERT_TRUE(plain.InitializeLinear(stations, Eigen::Vector2d(1e-4, 1e-4)));
  // The default holds the direction the 4 heights do not determine (z^4 against the heights'
  // quartic) and fits the rest: no ridge needed.
  options.max_amplification = PolynomialTermOptions().max_amplification;
  PolynomialTerm held(options);
  held.Prepare(stations);
  ASSERT_TRUE(held.InitializeLinear(stations, Eigen::Vector2d(1e-4, 1e-4)));
  ASSERT_EQ(held.undetermined().dropped_amplifications.size(), 1u);
  EXPECT_EQ(held.undetermined().isolated_stations, 0);
  {
    // Three hemisphere flips (reported at -p) stretch the input box over empty space; they are
    // isolated, left out of the volume, and the same single direction is undetermined (before:
    // 3, amplifications 206, 31 and 24 on the workflow's hemisphere_flips seed 1).
    std::vector<FitStation> flipped = stations;
    for (size_t i : {17u, 200u, 401u}) flipped[i].reported.translation *= -1.0;
    PolynomialTermOptions o;
    o.degree = 4;
    PolynomialTerm with_flips(o);
    with_flips.Prepare(flipped);
    ASSERT_TRUE(with_flips.InitializeLinear(flipped, Eigen::Vector2d(1e-4, 1e-4)));
    EXPECT_EQ(with_flips.undetermined().dropped_amplifications.size(), 1u);
    EXPECT_EQ(with_flips.undetermined().isolated_stations, 3);
  }
  {
    // Half the stations measured twice (2 mm apart): the median nearest-neighbour distance is then
    // the repeats', and without the floor every other station would be "isolated" (review).
    std::vector<FitStation> repeated = stations;
    for (const auto& s : stations) {
      if (s.reported.translation.z() < 0.3) {
        FitStation again = s;
        again.reported.translation.x() += 0.002;
        repeated.push_back(again);
      }
    }
    Eigen::MatrixXd u(static_cast<Eigen::Index>(repeated.size()), 3);
    PolynomialTerm probe(options);
    probe.Prepare(repeated);
    for (size_t i = 0; i < repeated.size(); ++i) {
      double ui[3];
      NormalizePolynomialInput(repeated[i].reported.translation.data(),
                               probe.options().input_offset, probe.options().input_scale, ui);
      u.row(static_cast<Eigen::Index>(i)) << ui[0], ui[1], ui[2];
    }
    const std::vector<bool> isolated = PolynomialTerm::IsolatedStations(u);
    EXPECT_EQ(std::count(isolated.begin(), isolated.end(), true), 0);
  }
  // h / (6 delta) = 0.1 m / 0.6 mm ~ 170 (docs/model-file.md); the test needs only "> 20".
  EXPECT_GT(held.undetermined().dropped_amplifications[0], 100.0);
  EXPECT_LT(held.undetermined().max_kept_amplification, 3.0);
  options.ridge_auto = true;
  PolynomialTerm ridge(options);
  ridge.Prepare(stations);
  ASSERT_TRUE(ridge.InitializeLinear(stations, Eigen::Vector2d(1e-4, 1e-4)));
  EXPECT_GT(ridge.ridge_used()[0], 0.0);
  const double plain_error = worst_between_heights(plain), ridge_error = worst_between_heights(ridge);
  const double held_error = worst_between_heights(held);
  std::cout << "worst position error off the heights: every direction " << plain_error * 1e3
            << " mm, undetermined held " << held_error * 1e3 << " mm, ridge " << ridge_error * 1e3
            << " mm (ridge " << ridge.ridge_used()[0] << ")\n";
  // The stations' noise is 0.1 mm; 5 cm beyond the outer heights (a third of the spacing) the
  // extrapolation amplifies it: the ridge fit stays within 1 mm (measured 0.46 mm), the fit of
  // every direction fits the near-null one to the noise and swings by more than 10 times as much
  // (12.5 mm), holding it stays within 1 mm too.
  EXPECT_LT(ridge_error, 1e-3);
  EXPECT_LT(held_error, 1e-3);
  EXPECT_GT(plain_error, 10.0 * ridge_error);
}

// Degrees above the layer count: the grid of the test above (4 heights) under degrees 5 and 6 has
// 4 and 10 undetermined directions; whatever is fitted must meet the limit (the subspace's own
// largest amplification), and a smooth field is still followed between the heights.
TEST(PolynomialTerm, DegreesAboveTheLayerCountKeepOnlyDeterminedDirections) {
  std::mt19937 rng(11);
  const PolynomialTerm truth = RandomTruth(2, &rng);
  const auto correction = truth.ToCorrection();
  const std::vector<FitStation> stations = FourHeightGrid(*correction, &rng);
  for (const auto& [degree, held] : {std::pair{5, 4u}, {6, 10u}}) {
    SCOPED_TRACE("degree " + std::to_string(degree));
    PolynomialTermOptions options;
    options.degree = degree;
    PolynomialTerm fitted(options);
    fitted.Prepare(stations);
    ASSERT_TRUE(fitted.InitializeLinear(stations, Eigen::Vector2d(1e-4, 1e-4)));
    EXPECT_EQ(fitted.undetermined().dropped_amplifications.size(), held);
    // The subspace fitted: its own largest amplification (the generalized eigenproblem restricted
    // to the basis) within the limit.
    Eigen::MatrixXd a(static_cast<Eigen::Index>(stations.size()), NumPolynomialTerms(degree));
    std::vector<double> m(static_cast<size_t>(NumPolynomialTerms(degree)));
    for (size_t i = 0; i < stations.size(); ++i) {
      double u[3];
      NormalizePolynomialInput(stations[i].reported.translation.data(),
                               fitted.options().input_offset, fitted.options().input_scale, u);
      EvaluateMonomials(degree, u, m.data());
      for (size_t j = 0; j < m.size(); ++j) {
        a(static_cast<Eigen::Index>(i), static_cast<Eigen::Index>(j)) = m[j];
      }
    }
    const Eigen::MatrixXd& b = fitted.undetermined().basis;
    const Eigen::MatrixXd gs =
        b.transpose() * a.transpose() * a * b / static_cast<double>(a.rows());
    const Eigen::MatrixXd gv = b.transpose() * PolynomialTerm::BoxGram(degree) * b;
    const Eigen::GeneralizedSelfAdjointEigenSolver<Eigen::MatrixXd> kept(gs, gv);
    EXPECT_LE(1.0 / std::sqrt(kept.eigenvalues().minCoeff()), options.max_amplification);
    // The quadratic field between and 5 cm beyond the heights: within 1 mm (noise 0.1 mm).
    const auto c = fitted.ToCorrection();
    double worst = 0;
    for (double z = 0.1; z <= 0.5; z += 0.01) {
      Rigid3d p;
      p.translation = Eigen::Vector3d(0.3, -0.2, z);
      worst = std::max(worst, PositionErrorNorm(c->Apply(p).pose, correction->Apply(p).pose));
    }
    std::cout << "degree " << degree << ": worst position error off the heights " << worst * 1e3
              << " mm\n";
    EXPECT_LT(worst, 1e-3);
  }
}

// The blocked folds keep a grid's layers whole: 4 heights give 4 slabs of one height each, 12 x
// positions give 6 slabs of two columns each.
TEST(PolynomialTerm, BlockedFoldsKeepGridLayersWhole) {
  std::mt19937 rng(5);
  std::normal_distribution<double> normal;
  Eigen::MatrixXd u(480, 3);
  int i = 0;
  for (int x = 0; x < 12; ++x) {
    for (int y = 0; y < 10; ++y) {
      for (int z = 0; z < 4; ++z, ++i) {
        // Layers 2/11, 2/9, 2/3 apart with a wobble of 1 % of the extent (a distorted report).
        u.row(i) << -1 + x * 2.0 / 11, -1 + y * 2.0 / 9, -1 + z * 2.0 / 3;
        u.row(i) += 0.01 * Eigen::RowVector3d(normal(rng), normal(rng), normal(rng));
      }
    }
  }
  const auto folds = PolynomialTerm::BlockedFolds(u);
  ASSERT_EQ(folds.size(), 3u);
  i = 0;
  for (int x = 0; x < 12; ++x) {
    for (int y = 0; y < 10; ++y) {
      for (int z = 0; z < 4; ++z, ++i) {
        EXPECT_EQ(folds[2][static_cast<size_t>(i)], z);
      }
    }
  }
  // x, y: 12 and 10 columns into 6 slabs each (the cuts snap to the widest gap near each quantile,
  // so a slab holds 1 to 3 columns), every column whole.
  for (int axis = 0; axis < 2; ++axis) {
    std::map<int, std::set<int>> slabs_of_column;
    std::set<int> slabs;
    i = 0;
    for (int x = 0; x < 12; ++x) {
      for (int y = 0; y < 10; ++y) {
        for (int z = 0; z < 4; ++z, ++i) {
          const int f = folds[static_cast<size_t>(axis)][static_cast<size_t>(i)];
          slabs_of_column[axis == 0 ? x : y].insert(f);
          slabs.insert(f);
        }
      }
    }
    EXPECT_EQ(slabs.size(), 6u) << "axis " << axis;
    for (const auto& [c, s] : slabs_of_column) EXPECT_EQ(s.size(), 1u) << "axis " << axis << " column " << c;
  }
}

TEST(PolynomialTerm, BlockedRidgeCvPredictsHeldOutLayersAsTheLinearPolicy) {
  // A distortion linear in the input, fitted by a degree-2 polynomial without noise: every fold
  // recovers it, so a held-out slab predicted by the runtime's linear policy (first order from the
  // fold's box, core/correction.h) has no error at lambda = 0, while held at the box (clamp) the
  // outer slabs are off by the slope times their distance. The reach caps it again.
  Eigen::MatrixXd u(6 * 5 * 4, 3), b(6 * 5 * 4, 3);
  const Eigen::Matrix3d slope = (Eigen::Matrix3d() << 0.01, -0.02, 0.005, 0.003, 0.01, -0.01,
                                 0.02, 0.0, 0.01).finished();
  int i = 0;
  for (int x = 0; x < 6; ++x) {
    for (int y = 0; y < 5; ++y) {
      for (int z = 0; z < 4; ++z, ++i) {
        u.row(i) << -1 + x * 2.0 / 5, -1 + y * 2.0 / 4, -1 + z * 2.0 / 3;
        b.row(i) = (slope * u.row(i).transpose() + Eigen::Vector3d(0.001, 0.002, -0.003)).transpose();
      }
    }
  }
  const int degree = 2, r = NumPolynomialTerms(degree);
  Eigen::MatrixXd a(u.rows(), r);
  std::vector<double> monomials(static_cast<size_t>(r));
  for (Eigen::Index k = 0; k < u.rows(); ++k) {
    const Eigen::Vector3d uk = u.row(k).transpose();
    EvaluateMonomials(degree, uk.data(), monomials.data());
    for (int j = 0; j < r; ++j) a(k, j) = monomials[static_cast<size_t>(j)];
  }
  std::vector<bool> shrunk;
  for (const auto& e : PolynomialTermExponents(degree)) shrunk.push_back(e[0] + e[1] + e[2] >= 2);
  const std::vector<double> grid = {0.0};
  const Eigen::Vector3d scale(0.6, 0.5, 0.3);  // [m] per unit of u
  const int slabs = PolynomialTerm::kBlockedSlabsPerAxis;
  const double clamp = PolynomialTerm::BlockedRidgeCv(degree, u, a, b, shrunk, grid)[0];
  const double linear =
      PolynomialTerm::BlockedRidgeCv(degree, u, a, b, shrunk, grid, slabs, scale, 10.0)[0];
  const double capped =
      PolynomialTerm::BlockedRidgeCv(degree, u, a, b, shrunk, grid, slabs, scale, 0.01)[0];
  // Noise-free: the linear prediction is exact to rounding of the normal equations (cond ~1e3 on
  // 1e-2 values: ~1e-24 squared per station); the clamp's error is the slope (~1e-2) times a layer
  // spacing (0.4-0.67 in u) on every outer station: ~1e-5 squared each.
  EXPECT_LT(linear, 1e-20);
  EXPECT_GT(clamp, 1e-4);
  EXPECT_GT(capped, linear);
  EXPECT_LT(capped, clamp);
}

// Leave-one-out cannot see what a weight does away from the stations: every held-out station has
// training neighbours on all sides, and at a station the near-null directions of a layered grid
// cost nothing. The blocked folds hold out whole layers (outer ones beyond the training box, inner
// ones between training layers) and see it. The grid is the paper preset's (12 x 10 x 4 at 0.15 m),
// the error field that of two far dipoles (not a polynomial, ~10 mm), the noise 0.1 mm, the
// polynomial of degree 8 (position part). Test stations lie inside the box between the heights and
// up to 75 mm beyond it (as the preset's validation stations), corrected as the runtime does (the
// calibrated volume's default policy: the polynomial continued to first order from the box).
struct RidgeComparison {
  double ridge_blocked = 0, ridge_loo = 0;
  double blocked_mm = 0, loo_mm = 0;  // mean position error over the test stations
  double clamp_floor_mm = 0;          // the true field held at the box: the clamp's own error
};

RidgeComparison CompareRidgeSelection(double layer_scatter_m) {
  std::mt19937 rng(3);
  std::normal_distribution<double> normal;
  auto field = [](const Eigen::Vector3d& p) {
    Eigen::Vector3d e = Eigen::Vector3d::Zero();
    for (const Eigen::Vector3d& s : {Eigen::Vector3d(1.6, 1.0, -0.5), Eigen::Vector3d(0.0, -2.1, -0.3)}) {
      const Eigen::Vector3d d = p - s;
      const double r = d.norm();
      e += 0.04 * (3.0 * d.dot(p) * d / (r * r) - p) / (r * r * r);
    }
    return e;
  };
  auto station = [&](const Eigen::Vector3d& p, double noise) {
    FitStation s;
    s.reported.translation = p;
    s.reported.rotation = Eigen::Quaterniond::UnitRandom();
    s.reference = s.reported;
    s.reference.translation += field(p) + noise * Eigen::Vector3d(normal(rng), normal(rng), normal(rng));
    return s;
  };
  std::vector<FitStation> grid;
  for (int i = 0; i < 12; ++i) {
    for (int j = 0; j < 10; ++j) {
      for (int k = 0; k < 4; ++k) {
        const Eigen::Vector3d p = Eigen::Vector3d(-0.825 + 0.15 * i, -0.675 + 0.15 * j, -0.8 + 0.15 * k) +
                                  layer_scatter_m * Eigen::Vector3d(normal(rng), normal(rng), normal(rng));
        grid.push_back(station(p, 1e-4));
      }
    }
  }
  CalibratedVolume volume;
  volume.min = volume.max = grid[0].reported.translation;
  for (const auto& s : grid) {
    volume.min = volume.min.cwiseMin(s.reported.translation);
    volume.max = volume.max.cwiseMax(s.reported.translation);
  }
  std::uniform_real_distribution<double> ux(-0.9, 0.9), uy(-0.75, 0.75), uz(-0.875, -0.275);
  std::vector<FitStation> test;  // noise-free
  while (test.size() < 600) test.push_back(station(Eigen::Vector3d(ux(rng), uy(rng), uz(rng)), 0.0));
  RidgeComparison out;
  for (const auto& s : test) {
    const Eigen::Vector3d p = s.reported.translation;
    out.clamp_floor_mm += 1e3 * (field(volume.Nearest(p)) - field(p)).norm() / static_cast<double>(test.size());
  }
  auto fit = [&](PolynomialTermOptions::RidgeSelection selection, double* ridge) {
    PolynomialTermOptions options;
    options.degree = 8;
    options.orientation = false;
    options.ridge_auto = true;
    options.ridge_selection = selection;
    PolynomialTerm term(options);
    term.Prepare(grid);
    EXPECT_TRUE(term.InitializeLinear(grid, Eigen::Vector2d(1e-4, 1e-4)));
    *ridge = term.ridge_used()[0];
    CorrectionChain chain;
    chain.Append(term.ToCorrection());
    chain.SetVolume(volume);
    double sum = 0;
    for (const auto& s : test) sum += PositionErrorNorm(chain.Apply(s.reported).pose, s.reference);
    return 1e3 * sum / static_cast<double>(test.size());
  };
  out.blocked_mm = fit(PolynomialTermOptions::RidgeSelection::kBlocked, &out.ridge_blocked);
  out.loo_mm = fit(PolynomialTermOptions::RidgeSelection::kLeaveOneOut, &out.ridge_loo);
  std::cout << "layer scatter " << layer_scatter_m * 1e3 << " mm: mean position error blocked "
            << out.blocked_mm << " mm (ridge " << out.ridge_blocked << "), leave-one-out "
            << out.loo_mm << " mm (ridge " << out.ridge_loo << "); the true field clamped "
            << out.clamp_floor_mm << " mm\n";
  return out;
}

TEST(PolynomialTerm, BlockedRidgeCvSeesWhatLeaveOneOutCannot) {
  // Stations exactly on the layers (a perfect physical term before the polynomial, noise only in
  // the reference): z^4 .. z^8 are exact combinations of lower powers at the stations. Leave-one-out
  // sees no cost in them and keeps no ridge (measured: 0, ~2e11 mm off between the heights); the
  // blocked folds pick a weight that holds the polynomial to the field (measured 0.01, 0.42 mm
  // with the linear policy outside the box, 0.62 mm when it was clamped, against the true field
  // clamped: 0.45 mm). The bounds are far from both: 1 mm, and 1000 mm.
  const RidgeComparison exact = CompareRidgeSelection(0.0);
  EXPECT_GT(exact.ridge_blocked, exact.ridge_loo);
  EXPECT_LT(exact.blocked_mm, 1.0);
  EXPECT_GT(exact.loo_mm, 1000.0);
  // With 0.1 mm of scatter about the layers (what a real physical term leaves) the near-null
  // directions are visible to leave-one-out too on this smooth field: both pick the same weight
  // (measured 0.1 each, 0.52 mm; 0.65 mm clamped). The blocked choice must not be worse: within 2 % (one grid step
  // of difference moves the mean by ~1 % here).
  const RidgeComparison scattered = CompareRidgeSelection(1e-4);
  EXPECT_LT(scattered.blocked_mm, 1.02 * scattered.loo_mm);
  EXPECT_LT(scattered.blocked_mm, 1.0);
}

// Stations on a plane leave free (constant and linear) columns dependent. On a plane normal to an
// axis that axis's column is zero: the ridge path inverted a singular triangular factor, and the
// fit threw "parameter block polynomial.position_coefficients: value 0 is not finite" (ridge: 1
// and both ridge: auto selections). A field linear in x and y (which the ridge does not shrink) is
// now reproduced at the stations. (A tilted plane's z = 0.3 + 0.2 (x - y / 2) is dependent only to
// rounding and was fitted before too; kept as a check.)
TEST(PolynomialTerm, RidgeOnStationsOnAPlaneFitsWhatTheyDetermine) {
  std::mt19937 rng(31);
  PolynomialTermOptions truth_options;
  truth_options.degree = 1;
  truth_options.input_offset = Eigen::Vector3d(0, 0, 0.3);
  truth_options.input_scale = Eigen::Vector3d(0.5, 0.5, 0.5);
  PolynomialTerm truth(truth_options);
  std::normal_distribution<double> normal;
  for (int j = 0; j < 3; ++j) {  // 1, x, y: no z dependence
    for (int k = 0; k < 3; ++k) {
      truth.blocks()[0].values[static_cast<size_t>(j * 3 + k)] = 0.005 * normal(rng);
      truth.blocks()[1].values[static_cast<size_t>(j * 3 + k)] = 0.01 * normal(rng);
    }
  }
  const auto correction = truth.ToCorrection();
  for (const double tilt : {0.0, 0.2}) {
    std::uniform_real_distribution<double> pos(-0.5, 0.5);
    std::vector<FitStation> stations;
    for (int i = 0; i < 200; ++i) {
      FitStation s;
      s.station = i;
      const double x = pos(rng), y = pos(rng);
      s.reported.translation = Eigen::Vector3d(x, y, 0.3 + tilt * (x - 0.5 * y));
      s.reported.rotation =
          Eigen::Quaterniond(normal(rng), normal(rng), normal(rng), normal(rng)).normalized();
      s.reference = correction->Apply(s.reported).pose;
      stations.push_back(s);
    }
    for (const std::string ridge : {"1", "auto", "auto, ridge_cv: leave_one_out"}) {
      SCOPED_TRACE("tilt " + std::to_string(tilt) + ", ridge: " + ridge);
      ModelSpec spec =
          ParseModelYaml("terms: [{type: polynomial, degree: 2, ridge: " + ridge + "}]", "m.yaml");
      FitResult result;
      ASSERT_NO_THROW(result = FitModel(stations, &spec));
      for (const auto& block : spec.terms[0]->blocks()) {
        for (double v : block.values) ASSERT_TRUE(std::isfinite(v)) << block.name;
      }
      // Noise-free and unshrunk: to the solver's tolerance (errors of ~5 mm and ~0.01).
      for (const auto& s : stations) {
        const Rigid3d corrected = result.chain.Apply(s.reported).pose;
        EXPECT_LT(PositionErrorNorm(corrected, s.reference), 1e-9);
        EXPECT_LT(OrientationErrorAngle(corrected, s.reference), 1e-9);
      }
    }
  }
}

// A ridge shrinks the coefficients of degree >= 2; degrees 0 and 1 have none, so it is plain least
// squares there. Both crashed the fit (segmentation fault in Eigen's SVD of the empty shrunk part),
// with a fixed weight and with auto.
TEST(PolynomialTerm, RidgeOnDegreeZeroAndOneIsLeastSquares) {
  std::mt19937 rng(37);
  for (const int degree : {0, 1}) {
    const PolynomialTerm truth = RandomTruth(degree, &rng);
    const auto stations = MakeStations(truth, 60, &rng);
    for (const std::string ridge : {"0.1", "auto", "auto, ridge_cv: leave_one_out"}) {
      SCOPED_TRACE("degree " + std::to_string(degree) + ", ridge: " + ridge);
      ModelSpec spec =
          ParseModelYaml("terms: [{type: polynomial, degree: " + std::to_string(degree) +
                             ", ridge: " + ridge + "}]",
                         "m.yaml");
      FitResult result;
      ASSERT_NO_THROW(result = FitModel(stations, &spec));
      // Noise-free: reproduced to the solver's tolerance (errors of ~5 mm and ~0.01).
      for (const auto& s : stations) {
        const Rigid3d corrected = result.chain.Apply(s.reported).pose;
        EXPECT_LT(PositionErrorNorm(corrected, s.reference), 1e-9);
        EXPECT_LT(OrientationErrorAngle(corrected, s.reference), 1e-9);
      }
    }
  }
}

// Fewer stations than terms (paper eq. 8 is then under-determined): a ridge is what makes the fit
// determined, so `ridge: auto` must still choose a weight. It returned before choosing one (the
// check N >= R came first), the weight stayed 0 and the solver interpolated the 30 noisy stations
// exactly with 35 free coefficients per part (measured: RMS 0.000 mm at the stations, 1.37 and
// 1.15 mm mean 5 cm from them); leave-one-out then also scored the weight 0 as perfect (every
// station has leverage 1). Fixed: weights 3.2 / 100 (blocked), 100 / 100 (leave-one-out), RMS
// 0.76 / 0.86 mm at the stations (the noise), 0.38 / 0.32 mm 5 cm from them.
TEST(PolynomialTerm, RidgeAutoWithFewerStationsThanTermsChoosesAWeight) {
  std::mt19937 rng(41);
  const PolynomialTerm truth = RandomTruth(1, &rng);  // a linear field: degree >= 2 is not needed
  const auto truth_correction = truth.ToCorrection();
  std::normal_distribution<double> noise(0.0, 0.5e-3);  // 0.5 mm per axis on the references
  std::vector<FitStation> stations = MakeStations(truth, 30, &rng);
  ASSERT_LT(static_cast<int>(stations.size()), NumPolynomialTerms(4));
  for (size_t i = 0; i < stations.size(); ++i) {
    stations[i].station = static_cast<int>(i);
    stations[i].reference.translation += Eigen::Vector3d(noise(rng), noise(rng), noise(rng));
  }
  for (const std::string ridge : {"auto", "auto, ridge_cv: leave_one_out"}) {
    SCOPED_TRACE("ridge: " + ridge);
    ModelSpec spec =
        ParseModelYaml("terms: [{type: polynomial, degree: 4, ridge: " + ridge + "}]", "m.yaml");
    FitResult result;
    ASSERT_NO_THROW(result = FitModel(stations, &spec));
    const auto& term = dynamic_cast<const PolynomialTerm&>(*spec.terms[0]);
    EXPECT_GT(term.ridge_used()[0], 0.0);
    EXPECT_GT(term.ridge_used()[1], 0.0);
    // Between the stations (5 cm from each, random directions) the fit follows the linear truth,
    // and at the stations it leaves their noise (0.5 mm per axis, 0.87 mm RMS in norm) instead of
    // fitting it: bounds halfway between the measured fixed and interpolating values.
    std::uniform_real_distribution<double> direction(-1.0, 1.0);
    double sum = 0.0;
    for (const auto& s : stations) {
      Rigid3d probe = s.reported;
      probe.translation +=
          0.05 * Eigen::Vector3d(direction(rng), direction(rng), direction(rng)).normalized();
      sum += PositionErrorNorm(result.chain.Apply(probe).pose, truth_correction->Apply(probe).pose);
    }
    const double mean_between = sum / static_cast<double>(stations.size());
    double sum_sq_at = 0.0;
    for (const auto& s : stations) {
      sum_sq_at += std::pow(PositionErrorNorm(result.chain.Apply(s.reported).pose, s.reference), 2);
    }
    const double rms_at = std::sqrt(sum_sq_at / static_cast<double>(stations.size()));
    std::cout << "ridge: " << ridge << ": weights " << term.ridge_used().transpose()
              << ", RMS at the stations " << rms_at * 1e3 << " mm, mean error 5 cm from them "
              << mean_between * 1e3 << " mm\n";
    EXPECT_GT(rms_at, 0.4e-3);
    EXPECT_LT(mean_between, 1e-3);
  }
}

TEST(PolynomialTerm, NoMoreStationsThanTermsWithoutARidgeIsTheFirstFlag) {
  // Degree 4 (35 terms) on 30 or 35 stations without a ridge passes through every station, noise
  // included (eq. 8 needs N > R): the fit says so first among its flags (the report shows the first
  // ten, and the covariance's per-coordinate flags number thousands here), with what to do.
  std::mt19937 rng(43);
  const PolynomialTerm truth = RandomTruth(1, &rng);
  for (const int count : {30, 35}) {
    SCOPED_TRACE(std::to_string(count) + " stations");
    std::vector<FitStation> stations = MakeStations(truth, count, &rng);
    std::normal_distribution<double> noise(0.0, 0.5e-3);
    for (size_t i = 0; i < stations.size(); ++i) {
      stations[i].station = static_cast<int>(i);
      stations[i].reference.translation += Eigen::Vector3d(noise(rng), noise(rng), noise(rng));
    }
    ModelSpec spec = ParseModelYaml("terms: [{type: polynomial, degree: 4}]", "m.yaml");
    FitResult result;
    ASSERT_NO_THROW(result = FitModel(stations, &spec));
    ASSERT_FALSE(result.identifiability_flags.empty());
    const std::string& reason = result.identifiability_flags[0].reason;
    EXPECT_NE(reason.find(std::to_string(count) + " stations for 35 terms"), std::string::npos)
        << reason;
    EXPECT_NE(reason.find("ridge: auto"), std::string::npos) << reason;
  }
  // With a ridge, or with more stations than terms, no such flag.
  std::vector<FitStation> stations = MakeStations(truth, 30, &rng);
  ModelSpec ridged =
      ParseModelYaml("terms: [{type: polynomial, degree: 4, ridge: auto}]", "m.yaml");
  const FitResult result = FitModel(stations, &ridged);
  for (const auto& f : result.identifiability_flags) {
    EXPECT_EQ(f.reason.find("terms"), std::string::npos) << f.reason;
  }
}

TEST(PolynomialTerm, RidgeAndAmplificationErrorsNameFileLineAndField) {
  EXPECT_NO_THROW(ParseModelYaml("terms:\n  - type: polynomial\n    ridge: auto\n", "m.yaml"));
  EXPECT_NO_THROW(ParseModelYaml("terms:\n  - type: polynomial\n    ridge: 0.1\n", "m.yaml"));
  EXPECT_NO_THROW(ParseModelYaml(
      "terms:\n  - type: polynomial\n    ridge: auto\n    ridge_cv: leave_one_out\n", "m.yaml"));
  try {
    ParseModelYaml("terms:\n  - type: polynomial\n    ridge: auto\n    ridge_cv: kfold\n", "m.yaml");
    ADD_FAILURE() << "no error for ridge_cv: kfold";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("m.yaml:4:"), std::string::npos) << e.what();
    EXPECT_NE(std::string(e.what()).find("ridge_cv"), std::string::npos) << e.what();
  }
  for (const std::string bad : {"-1", "fast", ".nan"}) {
    try {
      ParseModelYaml("terms:\n  - type: polynomial\n    ridge: " + bad + "\n", "m.yaml");
      ADD_FAILURE() << "no error for ridge: " << bad;
    } catch (const std::invalid_argument& e) {
      EXPECT_NE(std::string(e.what()).find("m.yaml:3:"), std::string::npos) << e.what();
      EXPECT_NE(std::string(e.what()).find("ridge"), std::string::npos) << e.what();
    }
  }
  EXPECT_NO_THROW(
      ParseModelYaml("terms:\n  - type: polynomial\n    max_amplification: 0\n", "m.yaml"));
  for (const std::string bad : {"0.5", "-3", ".inf", "many"}) {
    try {
      ParseModelYaml("terms:\n  - type: polynomial\n    max_amplification: " + bad + "\n",
                     "m.yaml");
      ADD_FAILURE() << "no error for max_amplification: " << bad;
    } catch (const std::invalid_argument& e) {
      EXPECT_NE(std::string(e.what()).find("m.yaml:3:"), std::string::npos) << e.what();
      EXPECT_NE(std::string(e.what()).find("max_amplification"), std::string::npos) << e.what();
    }
  }
}

}  // namespace
}  // namespace trackcal::fit
