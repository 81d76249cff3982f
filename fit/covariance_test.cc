#include "fit/covariance.h"

#include <ceres/ceres.h>
#include <ceres/normal_prior.h>
#include <gtest/gtest.h>

#include <Eigen/Eigenvalues>
#include <array>
#include <cmath>
#include <string>
#include <vector>

#include "fit/cost_functor.h"
#include "fit/marker_model.h"
#include "fit/rotation.h"
#include "tests/test_utils.h"

namespace trackcal::fit {
namespace {

// y = a + b * x, residual a + b x - y.
struct LineCost : AutoDiffCostFunctor<LineCost, 1, 1, 1> {
  LineCost(double x, double y) : x(x), y(y) {}
  template <typename T>
  bool operator()(const T* a, const T* b, T* r) const {
    r[0] = a[0] + b[0] * T(x) - T(y);
    return true;
  }
  double x, y;
};

TEST(ComputeCovariance, Nominal) {
  // Straight-line fit with sigma: the covariance is sigma^2 (X^T X)^-1.
  const double sigma = 0.2;
  double a = 0.0, b = 0.0;
  ceres::Problem problem;
  Eigen::Matrix<double, 5, 2> x;
  for (int i = 0; i < 5; ++i) {
    x.row(i) << 1.0, i;
    problem.AddResidualBlock(
        Whitened<LineCost>::Create(IsotropicSqrtInformation<1>(sigma), i, 1.0 + 2.0 * i), nullptr,
        &a, &b);
  }
  const CovarianceResult c =
      ComputeCovariance(&problem, {{&a, "a", {}, 1.0, 10.0}, {&b, "b", {}, 1.0, 10.0}});
  ASSERT_TRUE(c.success) << c.ToString();
  EXPECT_EQ(c.method, "dense_inverse");  // well conditioned: from the dense analysis
  EXPECT_EQ(c.rank, 2);
  EXPECT_FALSE(c.rank_deficient);
  EXPECT_TRUE(c.flags.empty()) << c.ToString();
  const Eigen::Matrix2d expected = sigma * sigma * (x.transpose() * x).inverse();
  EXPECT_TRUE(c.covariance.isApprox(expected, 1e-10)) << c.covariance;  // same algebra, rounding
  EXPECT_NEAR(c.stddev(1), std::sqrt(expected(1, 1)), 1e-12);
  EXPECT_EQ(c.coordinate_names[0], "a.[0]");
  // Variance inflation H_jj (H^-1)_jj: with x = 0..4, X^T X = [5 10; 10 30] and its inverse
  // [0.6 -0.2; -0.2 0.1], so 5 * 0.6 = 30 * 0.1 = 3 (= 1 / (1 - rho^2), rho^2 = 100 / 150).
  ASSERT_EQ(c.variance_inflation.size(), 2);
  EXPECT_NEAR(c.variance_inflation(0), 3.0, 1e-9);
  EXPECT_NEAR(c.variance_inflation(1), 3.0, 1e-9);
}

// A hard linear constraint (a residual of weight 1e8, as the unit-mean gain gauge of
// fit/terms_physical.cc holds trace G = 3) on weakly determined parameters: the covariance is the
// constrained one, Z (Z^T H Z)^-1 Z^T with Z the constraint's null space and H the data's
// information. Unless the constraint is named (CovarianceOptions::hard_constraints), the data's
// information in the directions it leaves free (here ~0.1 against 1e16 on every column) is scaled
// below the rank tolerance and dropped from the pseudo-inverse: stds of ~1e-9 for ~1.
struct ThreeWayCost {
  Eigen::Vector3d a;
  double y, sigma;
  template <typename T>
  bool operator()(const T* x, T* r) const {
    r[0] = (T(a[0]) * x[0] + T(a[1]) * x[1] + T(a[2]) * x[2] - T(y)) / T(sigma);
    return true;
  }
};
struct TraceGauge {
  template <typename T>
  bool operator()(const T* x, T* r) const {
    r[0] = (x[0] + x[1] + x[2] - T(3)) * T(1e8);
    return true;
  }
};
TEST(ComputeCovariance, AHardConstraintLeavesTheDirectionsItDoesNotHold) {
  double x[3] = {1.2, 0.9, 0.9};
  ceres::Problem problem;
  Eigen::Matrix3d data_information = Eigen::Matrix3d::Zero();
  std::vector<ceres::ResidualBlockId> clusters;
  for (int i = 0; i < 20; ++i) {
    const Eigen::Vector3d a(1.0 + 0.1 * i, std::sin(0.7 * i), std::cos(1.3 * i));
    const double sigma = 10.0;
    data_information += a * a.transpose() / (sigma * sigma);
    // Residuals at x of the noise's size (rms ~1 whitened), so the sandwich is of the model's.
    const double y = a.dot(Eigen::Vector3d(x[0], x[1], x[2])) + sigma * 1.4 * std::sin(2.3 * i + 0.4);
    clusters.push_back(problem.AddResidualBlock(
        new ceres::AutoDiffCostFunction<ThreeWayCost, 1, 3>(new ThreeWayCost{a, y, sigma}),
        nullptr, x));
  }
  const ceres::ResidualBlockId gauge = problem.AddResidualBlock(
      new ceres::AutoDiffCostFunction<TraceGauge, 1, 3>(new TraceGauge), nullptr, x);
  Eigen::Matrix<double, 3, 2> z;  // an orthonormal basis of trace = 0
  z << 1.0 / std::sqrt(2.0), 1.0 / std::sqrt(6.0), -1.0 / std::sqrt(2.0), 1.0 / std::sqrt(6.0),
      0.0, -2.0 / std::sqrt(6.0);
  const Eigen::Matrix3d expected =
      z * (z.transpose() * data_information * z).inverse() * z.transpose();
  for (const auto estimator : {CovarianceEstimator::kModel, CovarianceEstimator::kSandwich}) {
    CovarianceOptions options;
    options.estimator = estimator;
    options.clusters = clusters;
    // Given as an ordinary row, the gauge scales the rest below the rank tolerance (the failure
    // this guards against): 2 of 3 directions dropped; the pseudo-inverse's stds were 3e-9, now
    // those of coordinates in the null space: infinite.
    const CovarianceResult plain = ComputeCovariance(&problem, {{x, "x"}}, options);
    ASSERT_TRUE(plain.success) << plain.ToString();
    EXPECT_EQ(plain.rank, 1);
    EXPECT_TRUE(std::isinf(plain.stddev.maxCoeff())) << plain.stddev.transpose();
    options.hard_constraints = {gauge};
    const CovarianceResult c = ComputeCovariance(&problem, {{x, "x"}}, options);
    ASSERT_TRUE(c.success) << c.ToString();
    EXPECT_EQ(c.estimator, estimator == CovarianceEstimator::kModel ? "model" : "sandwich (CR2)");
    EXPECT_EQ(c.rank, 3) << c.ToString();
    EXPECT_TRUE(c.flags.empty()) << c.ToString();
    if (estimator == CovarianceEstimator::kModel) {
      // The constraint's weight leaves (1e-8)^2 / 3 along the trace: far below this tolerance.
      EXPECT_TRUE(c.covariance.isApprox(expected, 1e-6)) << c.covariance << "\n" << expected;
    } else {
      // The sandwich over the 20 data rows (the constraint is model information): not the model
      // covariance, but of its size (the residuals are not the model's noise).
      for (int k = 0; k < 3; ++k) {
        EXPECT_GT(c.stddev(k), 0.2 * std::sqrt(expected(k, k))) << c.ToString();
        EXPECT_LT(c.stddev(k), 5.0 * std::sqrt(expected(k, k))) << c.ToString();
      }
    }
    EXPECT_NEAR(c.covariance.sum(), 0.0, 1e-9);  // no variance along the held trace
  }
}

// The model covariance from the dense analysis' eigen-decomposition equals Ceres' sparse QR of the
// same Jacobian (forced by a reciprocal-condition threshold above 1) on a cubic fit whose normal
// matrix has a reciprocal condition of ~1e-4 after Jacobi scaling.
struct CubicCost {
  double x, y;
  template <typename T>
  bool operator()(const T* c, T* r) const {
    r[0] = (c[0] + T(x) * (c[1] + T(x) * (c[2] + T(x) * c[3])) - T(y)) / T(0.1);
    return true;
  }
};
TEST(ComputeCovariance, DenseInverseEqualsCeresSparseQr) {
  double c[4] = {0.5, -1.0, 0.25, 2.0};
  ceres::Problem problem;
  for (int i = 0; i < 40; ++i) {
    const double x = 0.05 * i;
    problem.AddResidualBlock(
        new ceres::AutoDiffCostFunction<CubicCost, 1, 4>(new CubicCost{x, std::sin(3.0 * x)}),
        nullptr, c);
  }
  CovarianceOptions dense_options;
  CovarianceOptions ceres_options;
  ceres_options.min_reciprocal_condition_dense_inverse = 2.0;
  const CovarianceResult dense = ComputeCovariance(&problem, {{c, "c"}}, dense_options);
  const CovarianceResult sparse = ComputeCovariance(&problem, {{c, "c"}}, ceres_options);
  ASSERT_TRUE(dense.success && sparse.success) << dense.ToString() << sparse.ToString();
  EXPECT_EQ(dense.method, "dense_inverse");
  EXPECT_EQ(sparse.method, "ceres_sparse_qr");
  EXPECT_GT(dense.reciprocal_condition, 1e-6) << dense.ToString();
  EXPECT_LT(dense.reciprocal_condition, 1e-2) << dense.ToString();
  // Two factorisations of the same matrix: relative error ~ 1e-16 / reciprocal condition.
  EXPECT_TRUE(dense.covariance.isApprox(sparse.covariance, 1e-10)) << dense.covariance << "\n"
                                                                   << sparse.covariance;
}

// Sandwich on a straight line with heteroscedastic residuals: CR2 by its closed form for one
// residual per cluster, (X^T X)^-1 X^T diag(r_i^2 / (1 - h_ii)) X (X^T X)^-1 with the leverages
// h_ii = x_i^T (X^T X)^-1 x_i, and CR1 with its factor G/(G-1) (N-1)/(N-K). The whitening sigma
// cancels: the sandwich does not depend on it.
TEST(ComputeCovariance, SandwichMatchesItsClosedForm) {
  const int n = 12;
  Eigen::MatrixXd x(n, 2);
  Eigen::VectorXd y(n);
  for (int i = 0; i < n; ++i) {
    x.row(i) << 1.0, 0.5 * i;
    // Noise that grows with x, fixed values so the test is deterministic.
    y(i) = 1.0 + 2.0 * x(i, 1) + 0.01 * (1 + i) * ((i * 7) % 5 - 2.0);
  }
  const Eigen::Vector2d beta = (x.transpose() * x).ldlt().solve(x.transpose() * y);
  Eigen::VectorXd r = x * beta;
  r -= y;
  const Eigen::Matrix2d h_inv = (x.transpose() * x).inverse();
  Eigen::Matrix2d meat2 = Eigen::Matrix2d::Zero(), meat1 = Eigen::Matrix2d::Zero();
  for (int i = 0; i < n; ++i) {
    const double h = x.row(i) * h_inv * x.row(i).transpose();
    meat2 += x.row(i).transpose() * x.row(i) * r(i) * r(i) / (1.0 - h);
    meat1 += x.row(i).transpose() * x.row(i) * r(i) * r(i);
  }
  const Eigen::Matrix2d cr2 = h_inv * meat2 * h_inv;
  const Eigen::Matrix2d cr1 =
      h_inv * meat1 * h_inv * (n / (n - 1.0)) * ((n - 1.0) / (n - 2.0));
  for (const double sigma : {0.05, 3.0}) {
    for (const bool leverage : {true, false}) {
      double a = beta(0), b = beta(1);
      ceres::Problem problem;
      CovarianceOptions options;
      options.estimator = CovarianceEstimator::kSandwich;
      options.max_leverage_flops = leverage ? 1e9 : 0.0;
      for (int i = 0; i < n; ++i) {
        options.clusters.push_back(problem.AddResidualBlock(
            Whitened<LineCost>::Create(IsotropicSqrtInformation<1>(sigma), x(i, 1), y(i)),
            nullptr, &a, &b));
      }
      const CovarianceResult c =
          ComputeCovariance(&problem, {{&a, "a", {}, 1.0, 10.0}, {&b, "b", {}, 1.0, 10.0}},
                            options);
      ASSERT_TRUE(c.success) << c.ToString();
      EXPECT_EQ(c.estimator, leverage ? "sandwich (CR2)" : "sandwich (CR1)");
      EXPECT_EQ(c.method, "dense_sandwich");
      // Same algebra in another order: rounding only.
      EXPECT_TRUE(c.covariance.isApprox(leverage ? cr2 : cr1, 1e-9))
          << c.covariance << "\nexpected\n" << (leverage ? cr2 : cr1);
    }
  }
}

// A ridge prior on the slope stated relative to the noise sigma (residual w b / sigma), as a
// polynomial's ridge is: listed in noise_relative, its information enters the meat scaled by s^2 =
// sum of the CR2-corrected residuals squared / n. The closed form, and the point of the scaling:
// the covariance then does not depend on the sigma the residuals are whitened with (the fit's
// solution does not either). Unlisted, the prior's information keeps the whitening's scale, and a
// sigma 60 times larger gives a wider covariance.
TEST(ComputeCovariance, NoiseRelativePriorScalesWithTheResiduals) {
  const int n = 12;
  const double w = 2.0;  // the prior's weight: b ~ N(0, (sigma / w)^2)
  Eigen::MatrixXd x(n, 2);
  Eigen::VectorXd y(n);
  for (int i = 0; i < n; ++i) {
    x.row(i) << 1.0, 0.5 * i;
    y(i) = 1.0 + 2.0 * x(i, 1) + 0.01 * (1 + i) * ((i * 7) % 5 - 2.0);
  }
  // In units of sigma the solution minimises |X beta - y|^2 + w^2 b^2 whatever sigma is.
  Eigen::Matrix2d prior = Eigen::Matrix2d::Zero();
  prior(1, 1) = w * w;
  const Eigen::Vector2d beta = (x.transpose() * x + prior).ldlt().solve(x.transpose() * y);
  std::vector<Eigen::Matrix2d> relative, plain;
  for (const double sigma : {0.05, 3.0}) {
    const Eigen::Matrix2d h_inv = ((x.transpose() * x + prior) / (sigma * sigma)).inverse();
    const Eigen::VectorXd r = (x * beta - y) / sigma;
    Eigen::Matrix2d meat = Eigen::Matrix2d::Zero();
    double sum_sq = 0.0;
    for (int i = 0; i < n; ++i) {
      const Eigen::RowVector2d xi = x.row(i) / sigma;
      const double u_sq = r(i) * r(i) / (1.0 - xi * h_inv * xi.transpose());
      meat += xi.transpose() * xi * u_sq;
      sum_sq += u_sq;
    }
    const Eigen::Matrix2d expected = h_inv * (meat + sum_sq / n * prior / (sigma * sigma)) * h_inv;
    for (const bool listed : {true, false}) {
      double a = beta(0), b = beta(1);
      ceres::Problem problem;
      CovarianceOptions options;
      options.estimator = CovarianceEstimator::kSandwich;
      for (int i = 0; i < n; ++i) {
        options.clusters.push_back(problem.AddResidualBlock(
            Whitened<LineCost>::Create(IsotropicSqrtInformation<1>(sigma), x(i, 1), y(i)),
            nullptr, &a, &b));
      }
      const ceres::ResidualBlockId ridge = problem.AddResidualBlock(
          new ceres::NormalPrior(Eigen::Matrix<double, 1, 1>(w / sigma), Eigen::VectorXd::Zero(1)),
          nullptr, &b);
      if (listed) options.noise_relative.push_back(ridge);
      const CovarianceResult c =
          ComputeCovariance(&problem, {{&a, "a", {}, 1.0, 10.0}, {&b, "b", {}, 1.0, 10.0}},
                            options);
      ASSERT_TRUE(c.success) << c.ToString();
      EXPECT_EQ(c.estimator, "sandwich (CR2)");
      EXPECT_NEAR(c.noise_variance_scale, sum_sq / n, 1e-12 * sum_sq / n);
      (listed ? relative : plain).push_back(c.covariance);
      if (listed) {
        EXPECT_TRUE(c.covariance.isApprox(expected, 1e-9)) << c.covariance << "\nexpected\n"
                                                           << expected;  // rounding only
      }
    }
  }
  EXPECT_TRUE(relative[0].isApprox(relative[1], 1e-8)) << relative[0] << "\n" << relative[1];
  // Unscaled, the prior's share grows with sigma^2 against the data's: here b's variance more
  // than doubles.
  EXPECT_GT(plain[1](1, 1), 2.0 * plain[0](1, 1));
}

// Grouped residual blocks (cluster_groups) are one cluster each: CR2 by its closed form,
// (X^T X)^-1 sum_g X_g^T (I - H_gg)^-1/2 r_g r_g^T (I - H_gg)^-1/2 X_g (X^T X)^-1 with H_gg the
// group's block of the hat matrix, and CR1 with G/(G-1) (N-1)/(N-K) counting groups.
// (X_g, r_g, H_gg of one independent column group; CR1's N and K are the problem's totals.)
// Per cluster the leverage-corrected scores X_g^T (I - H_gg)^-1/2 r_g (CR2) and the plain ones
// X_g^T r_g (CR1), premultiplied by (X^T X)^-1, for one column group.
struct GroupedScores {
  std::vector<Eigen::VectorXd> cr2, cr1;
};
GroupedScores GroupedScoresOf(const Eigen::MatrixXd& x, const Eigen::VectorXd& r,
                              const std::vector<int>& group, int groups) {
  const Eigen::MatrixXd h_inv = (x.transpose() * x).inverse();
  GroupedScores out;
  for (int g = 0; g < groups; ++g) {
    std::vector<int> rows;
    for (int i = 0; i < static_cast<int>(group.size()); ++i) {
      if (group[static_cast<size_t>(i)] == g) rows.push_back(i);
    }
    const int k = static_cast<int>(rows.size());
    Eigen::MatrixXd xg(k, x.cols());
    Eigen::VectorXd rg(k);
    for (int i = 0; i < k; ++i) {
      xg.row(i) = x.row(rows[static_cast<size_t>(i)]);
      rg(i) = r(rows[static_cast<size_t>(i)]);
    }
    Eigen::SelfAdjointEigenSolver<Eigen::MatrixXd> eig(Eigen::MatrixXd::Identity(k, k) -
                                                       xg * h_inv * xg.transpose());
    const Eigen::MatrixXd inv_sqrt = eig.eigenvectors() *
                                     eig.eigenvalues().cwiseSqrt().cwiseInverse().asDiagonal() *
                                     eig.eigenvectors().transpose();
    out.cr2.push_back(h_inv * xg.transpose() * inv_sqrt * rg);
    out.cr1.push_back(h_inv * xg.transpose() * rg);
  }
  return out;
}

// Two column groups that share no residual (a line a + b x and an offset c) whose residual blocks
// share clusters, plus blocks that touch only constant parameters (rows of no column group) in the
// same clusters, a cluster's rows spread over the problem: CR2 by its closed form per column group
// (the hat matrix is block diagonal over them), the scores summed per cluster, and CR1 with
// G/(G-1) (N-1)/(N-K) counting clusters. Shared clusters correlate the two groups' scores: the
// sandwich has cross terms where the model covariance has none. The line's residuals share an
// offset within each cluster (a misfit common to neighbours), which the per-block sandwich misses:
// the grouped one must be the wider.
TEST(ComputeCovariance, GroupedSandwichMatchesItsClosedForm) {
  const int n = 12, groups = 4;
  Eigen::MatrixXd x(n, 2), ones = Eigen::MatrixXd::Ones(n, 1);
  Eigen::VectorXd y(n), w(n);
  std::vector<int> group(n);
  const double group_offset[groups] = {0.08, -0.05, 0.06, -0.09};
  for (int i = 0; i < n; ++i) {
    group[static_cast<size_t>(i)] = i / 3;  // neighbours: 0 0 0 1 1 1 ...
    x.row(i) << 1.0, 0.5 * i;
    y(i) = 1.0 + 2.0 * x(i, 1) + group_offset[i / 3] + 0.01 * ((i * 7) % 5 - 2.0);
    w(i) = 0.3 + 0.02 * ((i * 3) % 7 - 3.0);
  }
  const Eigen::Vector2d beta = (x.transpose() * x).ldlt().solve(x.transpose() * y);
  const double c_hat = w.mean();
  const GroupedScores line = GroupedScoresOf(x, x * beta - y, group, groups);
  const GroupedScores offset =
      GroupedScoresOf(ones, Eigen::VectorXd::Constant(n, c_hat) - w, group, groups);
  // CR1: N = 3n rows (the constant-only rows count), K = 3.
  const double num_rows = 3.0 * n, k_free = 3.0;
  const double cr1 = groups / (groups - 1.0) * (num_rows - 1.0) / (num_rows - k_free);
  const int ids[groups] = {20, 0, 30, 10};  // cluster ids need not be 0..G-1 nor ordered
  for (const bool leverage : {true, false}) {
    Eigen::Matrix3d want = Eigen::Matrix3d::Zero();
    for (int g = 0; g < groups; ++g) {
      Eigen::Vector3d t;
      t << (leverage ? line.cr2 : line.cr1)[static_cast<size_t>(g)],
          (leverage ? offset.cr2 : offset.cr1)[static_cast<size_t>(g)];
      want += t * t.transpose();
    }
    if (!leverage) want *= cr1;
    double a = beta(0), b = beta(1), c = c_hat, zero = 0.0, fixed_a = 0.5, fixed_b = 0.1;
    ceres::Problem problem;
    CovarianceOptions options;
    options.estimator = CovarianceEstimator::kSandwich;
    options.max_leverage_flops = leverage ? 1e9 : 0.0;
    for (int i = 0; i < n; ++i) {
      const int id = ids[group[static_cast<size_t>(i)]];
      options.clusters.push_back(problem.AddResidualBlock(
          Whitened<LineCost>::Create(IsotropicSqrtInformation<1>(0.05), x(i, 1), y(i)), nullptr,
          &a, &b));
      options.cluster_groups.push_back(id);
      options.clusters.push_back(problem.AddResidualBlock(
          Whitened<LineCost>::Create(IsotropicSqrtInformation<1>(0.05), 0.0, w(i)), nullptr, &c,
          &zero));
      options.cluster_groups.push_back(id);
      options.clusters.push_back(problem.AddResidualBlock(
          Whitened<LineCost>::Create(IsotropicSqrtInformation<1>(0.05), 1.0, 0.7 + 0.1 * i),
          nullptr, &fixed_a, &fixed_b));
      options.cluster_groups.push_back(id);
    }
    problem.SetParameterBlockConstant(&zero);
    problem.SetParameterBlockConstant(&fixed_a);
    problem.SetParameterBlockConstant(&fixed_b);
    const std::vector<CovarianceBlock> blocks = {
        {&a, "a", {}, 1.0, 10.0}, {&b, "b", {}, 1.0, 10.0}, {&c, "c", {}, 1.0, 10.0}};
    const CovarianceResult got = ComputeCovariance(&problem, blocks, options);
    ASSERT_TRUE(got.success) << got.ToString();
    EXPECT_EQ(got.estimator,
              leverage ? "sandwich (CR2, 4 clusters)" : "sandwich (CR1, 4 clusters)");
    // Same algebra in another order: rounding only.
    EXPECT_TRUE(got.covariance.isApprox(want, 1e-9)) << got.covariance << "\nexpected\n" << want;
    EXPECT_GT(std::abs(got.covariance(1, 2)), 1e-3 * got.stddev(1) * got.stddev(2));
    options.cluster_groups.clear();
    const CovarianceResult single = ComputeCovariance(&problem, blocks, options);
    ASSERT_TRUE(single.success) << single.ToString();
    // Three residuals of one sign per cluster against one per block: the slope's std grows by
    // up to sqrt(3); 1.5 leaves room for the noise term.
    EXPECT_GT(got.stddev(1), 1.5 * single.stddev(1))
        << got.stddev.transpose() << " vs " << single.stddev.transpose();
  }
  // As many groups as clusters or none.
  CovarianceOptions bad;
  bad.clusters.resize(3);
  bad.cluster_groups = {0, 1};
  EXPECT_FALSE(bad.Check());
}

TEST(ComputeCovariance, SandwichWithoutClustersFallsBackToTheModel) {
  double a = 0.0, b = 0.0;
  ceres::Problem problem;
  for (int i = 0; i < 5; ++i) {
    problem.AddResidualBlock(Whitened<LineCost>::Create(IsotropicSqrtInformation<1>(1.0), i, i),
                             nullptr, &a, &b);
  }
  CovarianceOptions options;
  options.estimator = CovarianceEstimator::kSandwich;
  const CovarianceResult c =
      ComputeCovariance(&problem, {{&a, "a", {}, 1.0, 10.0}, {&b, "b", {}, 1.0, 10.0}}, options);
  ASSERT_TRUE(c.success);
  EXPECT_EQ(c.estimator, "model");
  EXPECT_NE(c.message.find("sandwich covariance unavailable"), std::string::npos) << c.message;
}

TEST(ComputeCovariance, LargeStddevIsFlagged) {
  double a = 0.0, b = 0.0;
  ceres::Problem problem;
  for (int i = 0; i < 5; ++i) {
    problem.AddResidualBlock(Whitened<LineCost>::Create(IsotropicSqrtInformation<1>(1.0), i, i),
                             nullptr, &a, &b);
  }
  const CovarianceResult c =
      ComputeCovariance(&problem, {{&a, "a", {"offset"}, 1.0, 0.1}, {&b, "b", {"slope"}, 1.0, 10}});
  ASSERT_TRUE(c.success);
  ASSERT_EQ(c.flags.size(), 1u) << c.ToString();
  EXPECT_EQ(c.flags[0].coordinate, "a.offset");
}

TEST(ComputeCovariance, RankDeficientFallsBackToPseudoInverseAndFlags) {
  // Every residual sees only a + b: one direction (a - b) is unobservable.
  double d = 0.0, e = 0.0;
  ceres::Problem degenerate;
  for (int i = 0; i < 4; ++i) {
    degenerate.AddResidualBlock(
        Whitened<LineCost>::Create(IsotropicSqrtInformation<1>(0.5), 1.0, 3.0), nullptr, &d, &e);
  }
  const CovarianceResult c =
      ComputeCovariance(&degenerate, {{&d, "d", {}, 1.0, 1e9}, {&e, "e", {}, 1.0, 1e9}});
  ASSERT_TRUE(c.success) << c.ToString();
  EXPECT_EQ(c.method, "dense_pseudo_inverse");
  EXPECT_TRUE(c.rank_deficient);
  EXPECT_EQ(c.rank, 1);
  // Both coordinates are moved by the null direction (d - e) / sqrt(2).
  ASSERT_EQ(c.flags.size(), 2u) << c.ToString();
  // The determined combination d + e has variance sigma^2 / 4 = 0.0625: u^T C u with u = (1, 1).
  EXPECT_NEAR(c.covariance.sum(), 0.0625, 1e-12);
}

// The pseudo-inverse gave each of d and e (only d + e observed) the std 0.112 (the sandwich 0.76),
// numbers for coordinates the data do not determine at all; the line a + b x keeps its stds.
TEST(ComputeCovariance, CoordinatesInTheNullSpaceHaveInfiniteStddev) {
  for (const auto estimator : {CovarianceEstimator::kModel, CovarianceEstimator::kSandwich}) {
    double d = 0.0, e = 0.0, a = 0.0, b = 0.0;
    ceres::Problem problem;
    CovarianceOptions options;
    options.estimator = estimator;
    Eigen::Matrix<double, 5, 2> x;
    for (int i = 0; i < 5; ++i) {
      x.row(i) << 1.0, i;
      options.clusters.push_back(problem.AddResidualBlock(
          Whitened<LineCost>::Create(IsotropicSqrtInformation<1>(0.5), 1.0, 3.0 + 0.1 * (i % 2)),
          nullptr, &d, &e));
      options.clusters.push_back(problem.AddResidualBlock(
          Whitened<LineCost>::Create(IsotropicSqrtInformation<1>(0.2), i, 1.0 + 2.0 * i), nullptr,
          &a, &b));
    }
    const CovarianceResult c =
        ComputeCovariance(&problem, {{&d, "d"}, {&e, "e"}, {&a, "a"}, {&b, "b"}}, options);
    ASSERT_TRUE(c.success) << c.ToString();
    EXPECT_TRUE(c.rank_deficient);
    EXPECT_EQ(c.rank, 3);
    EXPECT_TRUE(std::isinf(c.stddev(0)) && c.stddev(0) > 0) << c.stddev.transpose();
    EXPECT_TRUE(std::isinf(c.stddev(1)) && c.stddev(1) > 0) << c.stddev.transpose();
    EXPECT_EQ(c.flags.size(), 2u) << c.ToString();
    ASSERT_TRUE(std::isfinite(c.stddev(2)) && std::isfinite(c.stddev(3))) << c.stddev.transpose();
    if (estimator == CovarianceEstimator::kModel) {
      // Exactly on the line: sigma^2 (X^T X)^-1, as in Nominal.
      const Eigen::Matrix2d expected = 0.04 * (x.transpose() * x).inverse();
      EXPECT_NEAR(c.stddev(2), std::sqrt(expected(0, 0)), 1e-12);
      EXPECT_NEAR(c.stddev(3), std::sqrt(expected(1, 1)), 1e-12);
    }
  }
}

TEST(ComputeCovariance, QuaternionStddevInRadians) {
  // A pose prior with orientation noise sigma: the rotation-vector std must come out as sigma,
  // which checks the factor 2 between the manifold's tangent and a rotation vector.
  const double sigma_rad = 0.01, sigma_m = 0.002;
  const Rigid3d measured(testing::RandomRotation(testing::TestRng()), Eigen::Vector3d(1, 2, 3));
  double q[4];
  QuaternionToXyzwArray(measured.rotation, q);
  Eigen::Vector3d t = measured.translation;
  ceres::Problem problem;
  SetQuaternionManifold(&problem, q);
  Eigen::Matrix<double, 6, 1> sigmas;
  sigmas << Eigen::Vector3d::Constant(sigma_m), Eigen::Vector3d::Constant(sigma_rad);
  problem.AddResidualBlock(
      Whitened<PosePriorCost>::Create(DiagonalSqrtInformation<6>(sigmas), measured), nullptr, q,
      t.data());
  const CovarianceResult c =
      ComputeCovariance(&problem, {{q, "q", {"rx", "ry", "rz"}, kQuaternionTangentToRotationVector},
                                   {t.data(), "t", {"x", "y", "z"}}});
  ASSERT_TRUE(c.success) << c.ToString();
  for (int i = 0; i < 3; ++i) EXPECT_NEAR(c.stddev(i), sigma_rad, 1e-9);  // at the prior: exact
  for (int i = 3; i < 6; ++i) EXPECT_NEAR(c.stddev(i), sigma_m, 1e-12);
}

// A residual block over two 3-vectors whose first three residuals see only `p` (one coordinate
// each, as a polynomial's position rows see one axis) and whose last three mix `o` (as its
// orientation rows do): the information matrix is block diagonal over p.x, p.y, p.z and o.
struct SplitCost : AutoDiffCostFunctor<SplitCost, 6, 3, 3> {
  SplitCost(double s, double t) : s(s), t(t) {}
  template <typename T>
  bool operator()(const T* p, const T* o, T* r) const {
    for (int k = 0; k < 3; ++k) r[k] = p[k] * T(1.0 + s * (k + 1)) - T(std::sin(3.0 * s + k));
    r[3] = o[0] + T(t) * o[1] - T(0.3 * s);
    r[4] = o[1] * T(s) + o[2] * o[2] - T(t);
    r[5] = o[0] * T(s * t) - o[2] + T(0.1);
    return true;
  }
  double s, t;
};

// Splitting H into its independent groups gives the covariance of the one-group analysis: the
// model and the sandwich (CR2 and CR1), a prior's model information, a rank-deficient group.
TEST(ComputeCovariance, IndependentGroupsGiveTheOneGroupResult) {
  for (const bool deficient : {false, true}) {
    for (const auto estimator : {CovarianceEstimator::kModel, CovarianceEstimator::kSandwich}) {
      for (const bool leverage : {true, false}) {
        double p[3] = {0.1, -0.2, 0.3}, o[3] = {0.5, 0.25, -0.4}, d[2] = {0.0, 0.0};
        ceres::Problem problem;
        std::vector<ceres::ResidualBlockId> clusters;
        for (int i = 0; i < 30; ++i) {
          const double s = 0.1 * i, t = std::cos(1.7 * i);
          clusters.push_back(problem.AddResidualBlock(SplitCost::Create(s, t), nullptr, p, o));
          // `d` alone: with `deficient` only d[0] + d[1] is seen (a null direction).
          problem.AddResidualBlock(LineCost::Create(deficient ? 1.0 : s, 2.0 + s), nullptr, d,
                                   d + 1);
        }
        problem.AddResidualBlock(
            new ceres::NormalPrior(Eigen::Matrix3d::Identity() * 2.0, Eigen::Vector3d(0.4, 0.2, -0.3)),
            nullptr, o);
        CovarianceOptions split;
        split.estimator = estimator;
        split.clusters = clusters;
        split.max_leverage_flops = leverage ? 1e12 : 0.0;
        CovarianceOptions one = split;
        one.split_independent_columns = false;
        const std::vector<CovarianceBlock> blocks = {
            {p, "p", {}, 1.0, 1e9}, {o, "o", {}, 1.0, 1e9}, {d, "d0", {}, 1.0, 1e9},
            {d + 1, "d1", {}, 1.0, 1e9}};
        const CovarianceResult a = ComputeCovariance(&problem, blocks, split);
        const CovarianceResult b = ComputeCovariance(&problem, blocks, one);
        ASSERT_TRUE(a.success && b.success) << a.ToString() << b.ToString();
        // p.x, p.y, p.z, o and d (the LineCost couples d0 and d1).
        EXPECT_EQ(a.num_groups, 5);
        EXPECT_EQ(b.num_groups, 1);
        EXPECT_EQ(a.method, b.method);
        EXPECT_EQ(a.estimator, b.estimator);
        EXPECT_EQ(a.rank, b.rank);
        EXPECT_EQ(a.rank, deficient ? 7 : 8);
        EXPECT_NEAR(a.reciprocal_condition, b.reciprocal_condition,
                    1e-9 * b.reciprocal_condition + 1e-15);
        // The same algebra summed in another order, eigen-decompositions of the blocks instead
        // of the whole (relative rounding ~1e-16 / reciprocal condition ~1e-3).
        const double scale = b.covariance.cwiseAbs().maxCoeff();
        EXPECT_LT((a.covariance - b.covariance).cwiseAbs().maxCoeff(), 1e-9 * scale)
            << a.covariance << "\n\n" << b.covariance;
        ASSERT_EQ(a.flags.size(), b.flags.size()) << a.ToString() << b.ToString();
        for (size_t i = 0; i < a.flags.size(); ++i) {
          EXPECT_EQ(a.flags[i].coordinate, b.flags[i].coordinate);
        }
        EXPECT_EQ(a.flags.empty(), !deficient) << a.ToString();
      }
    }
  }
}

// Two neighbouring "nodes" (local blocks, as a LUT's) and a "physical" block every residual sees.
struct NodePairCost : AutoDiffCostFunctor<NodePairCost, 2, 2, 2, 2> {
  explicit NodePairCost(double s) : s(s) {}
  template <typename T>
  bool operator()(const T* a, const T* b, const T* g, T* r) const {
    r[0] = a[0] + T(0.5) * b[0] + g[0] * T(s) - T(std::sin(s));
    r[1] = a[1] - T(0.3) * b[1] + g[1] * T(s * s) + T(0.1) * g[0] - T(std::cos(s));
    return true;
  }
  double s;
};

// Above max_dense_dimension, the Schur complement on the global block with the nodes' independent
// groups gives Ceres' sparse-QR covariance.
TEST(ComputeCovariance, SchurOnGlobalColumnsEqualsCeresSparseQr) {
  constexpr int kNodes = 81;  // the global block's 80-160 rows against a node coordinate's 3
  std::vector<std::array<double, 2>> nodes(kNodes, {0.0, 0.0});
  double g[2] = {0.2, -0.1};
  ceres::Problem problem;
  for (int i = 0; i + 1 < kNodes; ++i) {
    problem.AddResidualBlock(NodePairCost::Create(0.05 * i), nullptr, nodes[static_cast<size_t>(i)].data(),
                             nodes[static_cast<size_t>(i) + 1].data(), g);
  }
  for (auto& node : nodes) {  // a weak pull to zero, as a LUT's ridge
    problem.AddResidualBlock(new ceres::NormalPrior(Eigen::Matrix2d::Identity() * 0.1, Eigen::Vector2d::Zero()),
                             nullptr, node.data());
  }
  std::vector<CovarianceBlock> blocks = {{g, "g", {}, 1.0, 1e9}};
  for (int i = 0; i < kNodes; ++i) blocks.push_back({nodes[static_cast<size_t>(i)].data(), "n" + std::to_string(i), {}, 1.0, 1e9});
  CovarianceOptions schur;
  schur.max_dense_dimension = 100;  // 164 coordinates: above; each group of node coordinates (81) below
  CovarianceOptions ceres_only = schur;
  ceres_only.schur_large_problems = false;
  const CovarianceResult a = ComputeCovariance(&problem, blocks, schur);
  const CovarianceResult b = ComputeCovariance(&problem, blocks, ceres_only);
  ASSERT_TRUE(a.success && b.success) << a.ToString() << b.ToString();
  EXPECT_EQ(a.method, "schur_banded_groups");
  EXPECT_EQ(b.method, "ceres_sparse_qr");
  EXPECT_EQ(a.num_groups, 3);  // node coordinates 0, node coordinates 1, the global block
  // Normal equations (Cholesky) against QR of the Jacobian: relative rounding ~ condition * 1e-16.
  const double scale = b.covariance.cwiseAbs().maxCoeff();
  EXPECT_LT((a.covariance - b.covariance).cwiseAbs().maxCoeff(), 1e-9 * scale);
  for (int i = 0; i < a.stddev.size(); ++i) EXPECT_NEAR(a.stddev(i), b.stddev(i), 1e-9 * b.stddev(i));
}

// A row that mixes both coordinates of a node with the global block, as the amplification
// whitening mixes a station's position and orientation residuals.
struct MixedNodeCost : AutoDiffCostFunctor<MixedNodeCost, 1, 2, 2> {
  explicit MixedNodeCost(double s) : s(s) {}
  template <typename T>
  bool operator()(const T* a, const T* g, T* r) const {
    r[0] = T(0.8) * a[0] - T(0.6) * a[1] + g[1] * T(s) - T(s * s);
    return true;
  }
  double s;
};

// The fast path of the LUT chain's covariance (a band Cholesky per group, entries formed only as
// asked) against the reference (Ceres' sparse QR) when mixed rows join the nodes' coordinates into
// one group above max_dense_dimension (main refused such a group and fell back to Ceres): the full
// covariance, and each block's own covariance alone as the fit engine asks for it.
TEST(ComputeCovariance, SchurWithMixedRowsEqualsCeresSparseQr) {
  constexpr int kNodes = 81;
  std::vector<std::array<double, 2>> nodes(kNodes, {0.0, 0.0});
  double g[2] = {0.2, -0.1};
  ceres::Problem problem;
  for (int i = 0; i + 1 < kNodes; ++i) {
    problem.AddResidualBlock(NodePairCost::Create(0.05 * i), nullptr, nodes[static_cast<size_t>(i)].data(),
                             nodes[static_cast<size_t>(i) + 1].data(), g);
  }
  for (int i = 0; i < kNodes; i += 7) {
    problem.AddResidualBlock(MixedNodeCost::Create(0.1 * i), nullptr, nodes[static_cast<size_t>(i)].data(), g);
  }
  for (auto& node : nodes) {
    problem.AddResidualBlock(new ceres::NormalPrior(Eigen::Matrix2d::Identity() * 0.1, Eigen::Vector2d::Zero()),
                             nullptr, node.data());
  }
  for (const bool cross : {true, false}) {
    SCOPED_TRACE(cross ? "all cross-covariances" : "own covariances only");
    std::vector<CovarianceBlock> blocks = {{g, "g", {}, 1.0, 1e9}};
    for (int i = 0; i < kNodes; ++i) {
      blocks.push_back({nodes[static_cast<size_t>(i)].data(), "n" + std::to_string(i), {}, 1.0, 1e9, cross});
    }
    CovarianceOptions schur;
    schur.max_dense_dimension = 100;  // 164 coordinates, one node group of 162: both above
    CovarianceOptions ceres_only = schur;
    ceres_only.schur_large_problems = false;
    const CovarianceResult a = ComputeCovariance(&problem, blocks, schur);
    const CovarianceResult b = ComputeCovariance(&problem, blocks, ceres_only);
    ASSERT_TRUE(a.success && b.success) << a.ToString() << b.ToString();
    EXPECT_EQ(a.method, "schur_banded_groups");
    EXPECT_EQ(b.method, "ceres_sparse_qr");
    EXPECT_EQ(a.num_groups, 2);  // the nodes' coordinates, joined by the mixed rows; the global block
    // Normal equations (Cholesky) against QR of the Jacobian: relative rounding ~ condition * 1e-16,
    // far inside the 1e-6 relative the fit's standard deviations need.
    const double scale = b.covariance.cwiseAbs().maxCoeff();
    EXPECT_LT((a.covariance - b.covariance).cwiseAbs().maxCoeff(), 1e-9 * scale);
    for (int i = 0; i < a.stddev.size(); ++i) EXPECT_NEAR(a.stddev(i), b.stddev(i), 1e-9 * b.stddev(i));
    if (!cross) EXPECT_EQ(a.covariance(3, 5), 0.0);  // n0 x n1: not asked for
  }
}

TEST(ComputeCovariance, UnknownOrConstantBlockThrows) {
  double a = 0.0, b = 0.0, stray = 0.0;
  ceres::Problem problem;
  problem.AddResidualBlock(LineCost::Create(1.0, 2.0), nullptr, &a, &b);
  EXPECT_THROW(ComputeCovariance(&problem, {{&stray, "stray", {}}}), std::invalid_argument);
  problem.SetParameterBlockConstant(&b);
  EXPECT_THROW(ComputeCovariance(&problem, {{&b, "b", {}}}), std::invalid_argument);
}

}  // namespace
}  // namespace trackcal::fit
