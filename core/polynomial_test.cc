#include "core/polynomial.h"

#include <ceres/jet.h>
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <set>

#include "tests/test_utils.h"

namespace trackcal {
namespace {

using testing::RandomRotation;
using testing::TestRng;

Eigen::Vector3d RandomPoint(double half_extent) {
  std::uniform_real_distribution<double> u(-half_extent, half_extent);
  return Eigen::Vector3d(u(TestRng()), u(TestRng()), u(TestRng()));
}

int TermIndex(int degree, int a, int b, int c) {
  const auto terms = PolynomialTermExponents(degree);
  const auto it = std::find(terms.begin(), terms.end(), std::array<int, 3>{a, b, c});
  EXPECT_NE(it, terms.end());
  return static_cast<int>(it - terms.begin());
}

TEST(NumPolynomialTerms, Nominal) {
  EXPECT_EQ(NumPolynomialTerms(0), 1);
  EXPECT_EQ(NumPolynomialTerms(1), 4);
  EXPECT_EQ(NumPolynomialTerms(2), 10);
  EXPECT_EQ(NumPolynomialTerms(4), 35);  // the paper's R for r = 4
  EXPECT_EQ(NumPolynomialTerms(8), 165);
  for (int r = 0; r <= kMaxPolynomialDegree; ++r) {
    EXPECT_EQ(static_cast<int>(PolynomialTermExponents(r).size()), NumPolynomialTerms(r));
  }
}

TEST(PolynomialTermExponents, CanonicalOrder) {
  const std::vector<std::array<int, 3>> expected = {{0, 0, 0}, {1, 0, 0}, {0, 1, 0}, {0, 0, 1},
                                                    {2, 0, 0}, {1, 1, 0}, {1, 0, 1}, {0, 2, 0},
                                                    {0, 1, 1}, {0, 0, 2}};
  EXPECT_EQ(PolynomialTermExponents(2), expected);
  EXPECT_EQ(PolynomialTermName({2, 1, 0}), "x^2*y");
  EXPECT_EQ(PolynomialTermName({0, 0, 0}), "1");
  // Complete, unique, graded then descending x then descending y, for every degree.
  for (int r = 0; r <= kMaxPolynomialDegree; ++r) {
    const auto terms = PolynomialTermExponents(r);
    std::set<std::array<int, 3>> unique(terms.begin(), terms.end());
    EXPECT_EQ(unique.size(), terms.size());
    for (size_t j = 1; j < terms.size(); ++j) {
      const auto& p = terms[j - 1];
      const auto& t = terms[j];
      const auto key = [](const std::array<int, 3>& e) {
        return std::array<int, 3>{e[0] + e[1] + e[2], -e[0], -e[1]};
      };
      EXPECT_LT(key(p), key(t)) << "degree " << r << " term " << j;
      EXPECT_LE(t[0] + t[1] + t[2], r);
    }
  }
  EXPECT_THROW(PolynomialTermExponents(-1), std::invalid_argument);
  EXPECT_THROW(PolynomialTermExponents(kMaxPolynomialDegree + 1), std::invalid_argument);
}

TEST(EvaluateMonomials, MatchesPowersForEveryDegree) {
  for (int r = 0; r <= kMaxPolynomialDegree; ++r) {
    const Eigen::Vector3d u = RandomPoint(1.2);
    std::vector<double> m(static_cast<size_t>(NumPolynomialTerms(r)));
    EvaluateMonomials(r, u.data(), m.data());
    const auto terms = PolynomialTermExponents(r);
    for (size_t j = 0; j < terms.size(); ++j) {
      const double expected = std::pow(u.x(), terms[j][0]) * std::pow(u.y(), terms[j][1]) *
                              std::pow(u.z(), terms[j][2]);
      // Products of at most 12 factors of magnitude <= 1.2: a few ulps of relative error.
      EXPECT_NEAR(m[j], expected, 1e-14 * std::max(1.0, std::abs(expected))) << r << " " << j;
    }
  }
}

// A hand-written polynomial in normalised coordinates, evaluated independently of the term order.
void KnownError(const Eigen::Vector3d& u, double* e) {
  const double x = u.x(), y = u.y(), z = u.z();
  e[0] = 0.01 + 0.002 * x * y - 0.003 * z * z * z + 0.0005 * x * x * x * x;
  e[1] = -0.02 * y + 0.004 * x * z;
  e[2] = 0.001 * x * y * z * z;
  e[3] = 0.01 * z;
  e[4] = -0.002 + 0.003 * y * y;
  e[5] = 0.0015 * x * x * y * z;
}

TEST(PolynomialCorrection, KnownPolynomialReproducedExactly) {
  const int r = 4;
  std::vector<double> c(6 * NumPolynomialTerms(r), 0.0);
  auto set = [&](int a, int b, int cc, int k, double v) { c[6 * TermIndex(r, a, b, cc) + k] = v; };
  set(0, 0, 0, 0, 0.01);
  set(1, 1, 0, 0, 0.002);
  set(0, 0, 3, 0, -0.003);
  set(4, 0, 0, 0, 0.0005);
  set(0, 1, 0, 1, -0.02);
  set(1, 0, 1, 1, 0.004);
  set(1, 1, 2, 2, 0.001);
  set(0, 0, 1, 3, 0.01);
  set(0, 0, 0, 4, -0.002);
  set(0, 2, 0, 4, 0.003);
  set(2, 1, 1, 5, 0.0015);
  const Eigen::Vector3d offset(0.1, -0.2, 0.4), scale(0.9, 0.75, 0.45);
  const PolynomialCorrection poly(r, offset, scale, c);
  for (int i = 0; i < 200; ++i) {
    const Eigen::Vector3d p = offset + RandomPoint(1.0).cwiseProduct(scale);
    double e[6], expected[6];
    poly.EvaluateError(p.data(), e);
    KnownError((p - offset).cwiseQuotient(scale), expected);
    // Same real-number polynomial, different summation order: rounding only (terms <= 0.02).
    for (int k = 0; k < 6; ++k) EXPECT_NEAR(e[k], expected[k], 1e-16) << k;

    // The templated generic path gives the same numbers as the fast double path.
    double e_generic[6];
    EvaluatePolynomialError<double>(r, c.data(), offset, scale, p.data(), e_generic);
    for (int k = 0; k < 6; ++k) EXPECT_NEAR(e_generic[k], e[k], 1e-17);

    const Rigid3d reported(RandomRotation(TestRng()), p);
    const CorrectedPose out = poly.Apply(reported);
    EXPECT_FALSE(out.extrapolated);
    EXPECT_TRUE(out.pose.translation.isApprox(p + Eigen::Vector3d(e[0], e[1], e[2]), 1e-15));
    const Eigen::Quaterniond q_e = out.pose.rotation * reported.rotation.conjugate();
    EXPECT_TRUE(VectorPart(q_e).isApprox(Eigen::Vector3d(e[3], e[4], e[5]), 1e-12));
  }
}

TEST(PolynomialCorrection, ConstantRotationIsWorldFrame) {
  // Degree 0: a constant error. q_e is applied on the left (eq. 4), i.e. in the transmitter frame.
  const Eigen::Quaterniond q_e(Eigen::AngleAxisd(3.0 * kRadPerDeg, Eigen::Vector3d::UnitZ()));
  const std::vector<double> c = {0.01, 0.02, -0.03, q_e.x(), q_e.y(), q_e.z()};
  const PolynomialCorrection poly(0, Eigen::Vector3d::Zero(), Eigen::Vector3d::Ones(), c);
  for (int i = 0; i < 20; ++i) {
    const Rigid3d reported(RandomRotation(TestRng()), RandomPoint(1.0));
    const CorrectedPose out = poly.Apply(reported);
    const Rigid3d expected(q_e * reported.rotation,
                           reported.translation + Eigen::Vector3d(0.01, 0.02, -0.03));
    EXPECT_TRUE(testing::PosesNear(expected, out.pose, 1e-15, 1e-12));
  }
}

TEST(PolynomialCorrection, BatchMatchesSingleAndRunsInPlace) {
  const int r = 3;
  std::vector<double> c(6 * NumPolynomialTerms(r));
  std::normal_distribution<double> n(0.0, 0.01);
  for (double& v : c) v = n(TestRng());
  const PolynomialCorrection poly(r, Eigen::Vector3d(0, 0, 0.3), Eigen::Vector3d(1, 1, 0.5), c);
  const size_t count = 50;
  std::vector<double> pos(3 * count), quat(4 * count);
  for (size_t i = 0; i < count; ++i) {
    const Eigen::Vector3d p = RandomPoint(1.0);
    const Eigen::Quaterniond q = RandomRotation(TestRng());
    for (int k = 0; k < 3; ++k) pos[3 * i + k] = p[k];
    QuaternionToXyzwArray(q, &quat[4 * i]);
  }
  std::vector<double> out_pos(3 * count), out_quat(4 * count);
  std::vector<uint8_t> flags(count, 7);
  poly.ApplyBatch(count, pos.data(), quat.data(), out_pos.data(), out_quat.data(), flags.data());
  for (size_t i = 0; i < count; ++i) {
    const Rigid3d reported(QuaternionFromXyzwArray(&quat[4 * i]),
                           Eigen::Vector3d(pos[3 * i], pos[3 * i + 1], pos[3 * i + 2]));
    const CorrectedPose single = poly.Apply(reported);
    const Rigid3d batch(QuaternionFromXyzwArray(&out_quat[4 * i]),
                        Eigen::Vector3d(out_pos[3 * i], out_pos[3 * i + 1], out_pos[3 * i + 2]));
    EXPECT_TRUE(testing::PosesNear(single.pose, batch, 1e-15, 1e-15));
    EXPECT_EQ(flags[i], 0);
  }
  // In place: outputs alias inputs.
  poly.ApplyBatch(count, pos.data(), quat.data(), pos.data(), quat.data(), nullptr);
  EXPECT_EQ(pos, out_pos);
  EXPECT_EQ(quat, out_quat);
}

TEST(PolynomialCorrection, BothBatchKernelsMatchSinglePose) {
  // Degrees 0..kMax, batch sizes that leave partial tiles; the baseline kernel forced, then the
  // machine's best (AVX2 + FMA where available).
  std::normal_distribution<double> n(0.0, 0.01);
  for (int r = 0; r <= kMaxPolynomialDegree; r += 3) {
    std::vector<double> c(6 * NumPolynomialTerms(r));
    for (double& v : c) v = n(TestRng()) / (1 + r);
    const PolynomialCorrection poly(r, Eigen::Vector3d(0.1, 0, 0.2), Eigen::Vector3d(0.6, 0.5, 0.4),
                                    c);
    const size_t count = 13;
    std::vector<double> pos(3 * count), quat(4 * count);
    for (size_t i = 0; i < count; ++i) {
      const Eigen::Vector3d p = RandomPoint(0.5);
      for (int k = 0; k < 3; ++k) pos[3 * i + k] = p[k];
      QuaternionToXyzwArray(RandomRotation(TestRng()), &quat[4 * i]);
    }
    for (bool force_baseline : {true, false}) {
      internal::ForceBaselinePolynomialKernel(force_baseline);
      std::vector<double> out_pos(3 * count), out_quat(4 * count);
      poly.ApplyBatch(count, pos.data(), quat.data(), out_pos.data(), out_quat.data(), nullptr);
      for (size_t i = 0; i < count; ++i) {
        const CorrectedPose single = poly.Apply(Rigid3d(
            QuaternionFromXyzwArray(&quat[4 * i]), Eigen::Vector3d(&pos[3 * i])));
        const Rigid3d batch(QuaternionFromXyzwArray(&out_quat[4 * i]),
                            Eigen::Vector3d(&out_pos[3 * i]));
        // Different summation order and FMA: rounding of sums of up to 455 terms of ~0.01.
        EXPECT_TRUE(testing::PosesNear(single.pose, batch, 1e-15, 1e-15))
            << "degree " << r << " pose " << i << " baseline " << force_baseline;
      }
    }
    internal::ForceBaselinePolynomialKernel(false);
  }
}

TEST(PolynomialCorrection, RejectsBadParameters) {
  const std::vector<double> c35(6 * 35, 0.0);
  EXPECT_NO_THROW(PolynomialCorrection(4, Eigen::Vector3d::Zero(), Eigen::Vector3d::Ones(), c35));
  EXPECT_THROW(PolynomialCorrection(3, Eigen::Vector3d::Zero(), Eigen::Vector3d::Ones(), c35),
               std::invalid_argument);
  EXPECT_THROW(PolynomialCorrection(-1, Eigen::Vector3d::Zero(), Eigen::Vector3d::Ones(), c35),
               std::invalid_argument);
  EXPECT_THROW(PolynomialCorrection(4, Eigen::Vector3d::Zero(), Eigen::Vector3d(1, 0, 1), c35),
               std::invalid_argument);
  std::vector<double> bad = c35;
  bad[17] = std::nan("");
  EXPECT_THROW(PolynomialCorrection(4, Eigen::Vector3d::Zero(), Eigen::Vector3d::Ones(), bad),
               std::invalid_argument);
  EXPECT_THROW(PolynomialCorrection::FromPositionAndOrientation(
                   4, Eigen::Vector3d::Zero(), Eigen::Vector3d::Ones(),
                   std::vector<double>(3 * 34), std::vector<double>(3 * 35)),
               std::invalid_argument);
}

TEST(EvaluatePolynomialError, AutodiffThroughCoefficientsAndPosition) {
  // fit/ optimises coefficients with ceres::Jet through exactly this function: the derivative of
  // error component k with respect to coefficient (j, k) is monomial j, and the derivative with respect
  // to the position matches a central difference.
  using Jet = ceres::Jet<double, 3>;
  const int r = 4;
  const int terms = NumPolynomialTerms(r);
  std::vector<double> c(6 * terms);
  std::normal_distribution<double> n(0.0, 0.01);
  for (double& v : c) v = n(TestRng());
  const Eigen::Vector3d offset(0.1, 0.0, 0.3), scale(0.8, 0.8, 0.4);
  const Eigen::Vector3d p = RandomPoint(0.5);

  // d/dp through the position.
  std::vector<Jet> c_jet(c.begin(), c.end());
  Jet p_jet[3] = {Jet(p.x(), 0), Jet(p.y(), 1), Jet(p.z(), 2)};
  Jet e_jet[6];
  EvaluatePolynomialError<Jet>(r, c_jet.data(), offset, scale, p_jet, e_jet);
  const double h = 1e-6;
  for (int d = 0; d < 3; ++d) {
    Eigen::Vector3d pp = p, pm = p;
    pp[d] += h;
    pm[d] -= h;
    double ep[6], em[6];
    EvaluatePolynomialError<double>(r, c.data(), offset, scale, pp.data(), ep);
    EvaluatePolynomialError<double>(r, c.data(), offset, scale, pm.data(), em);
    for (int k = 0; k < 6; ++k) {
      // Central difference of a smooth polynomial with h = 1e-6: truncation ~h^2, rounding ~1e-10.
      EXPECT_NEAR(e_jet[k].v[d], (ep[k] - em[k]) / (2 * h), 1e-8) << d << " " << k;
    }
  }

  // d/dc: seed three coefficients of component 1.
  std::vector<double> monomials(terms);
  const Eigen::Vector3d u = (p - offset).cwiseQuotient(scale);
  EvaluateMonomials(r, u.data(), monomials.data());
  const int seeded[3] = {0, 7, 34};
  for (int s = 0; s < 3; ++s) c_jet[6 * seeded[s] + 1] = Jet(c[6 * seeded[s] + 1], s);
  Jet p_const[3] = {Jet(p.x()), Jet(p.y()), Jet(p.z())};
  EvaluatePolynomialError<Jet>(r, c_jet.data(), offset, scale, p_const, e_jet);
  for (int s = 0; s < 3; ++s) {
    EXPECT_NEAR(e_jet[1].v[s], monomials[seeded[s]], 1e-15);
    EXPECT_EQ(e_jet[0].v[s], 0.0);
  }
}

}  // namespace
}  // namespace trackcal
