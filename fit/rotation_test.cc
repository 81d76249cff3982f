#include "fit/rotation.h"

#include <ceres/manifold.h>
#include <gtest/gtest.h>

#include "tests/test_utils.h"

namespace trackcal::fit {
namespace {

using testing::RandomRotation;
using testing::TestRng;

TEST(RotatePoint, Nominal) {
  for (int i = 0; i < 50; ++i) {
    const Eigen::Quaterniond q = RandomRotation(TestRng());
    const Eigen::Vector3d p(0.3, -1.2, 2.0);
    double xyzw[4];
    QuaternionToXyzwArray(q, xyzw);
    Eigen::Vector3d out;
    RotatePoint(xyzw, p.data(), out.data());
    EXPECT_TRUE(out.isApprox(q * p, 1e-14));  // both exact to rounding
  }
}

TEST(QuaternionToRotationVector, MatchesAngleAxisAndIgnoresSign) {
  for (int i = 0; i < 50; ++i) {
    const Eigen::Quaterniond q = RandomRotation(TestRng());
    double xyzw[4], minus[4];
    QuaternionToXyzwArray(q, xyzw);
    for (int k = 0; k < 4; ++k) minus[k] = -xyzw[k];
    Eigen::Vector3d v, v_minus;
    QuaternionToRotationVector(xyzw, v.data());
    QuaternionToRotationVector(minus, v_minus.data());
    const Eigen::AngleAxisd aa(q);
    const double angle = aa.angle() <= M_PI ? aa.angle() : 2 * M_PI - aa.angle();
    EXPECT_NEAR(v.norm(), angle, 1e-12);
    EXPECT_TRUE(v.isApprox(v_minus, 1e-12));
    EXPECT_TRUE(testing::RotationsNear(q, QuaternionFromRotationVector(v), 1e-12));
  }
}

TEST(RotationVectorBetween, WorldFrameError) {
  const Eigen::Quaterniond b = RandomRotation(TestRng());
  const Eigen::Vector3d delta(0.01, -0.02, 0.03);
  const Eigen::Quaterniond a = QuaternionFromRotationVector(delta) * b;
  EXPECT_TRUE(RotationVectorBetween<double>(a, b).isApprox(delta, 1e-12));
}

// The manifold's tangent is a half angle: q + d rotates by 2|d| about world axes. The covariance
// code relies on this factor (kQuaternionTangentToRotationVector).
TEST(EigenQuaternionManifold, TangentIsHalfAngleLeftPerturbation) {
  const Eigen::Quaterniond q = RandomRotation(TestRng());
  double xyzw[4], out[4];
  QuaternionToXyzwArray(q, xyzw);
  const Eigen::Vector3d d(1e-3, -2e-3, 0.5e-3);
  ceres::EigenQuaternionManifold manifold;
  ASSERT_TRUE(manifold.Plus(xyzw, d.data(), out));
  const Eigen::Quaterniond moved = QuaternionFromXyzwArray(out);
  EXPECT_TRUE(RotationVectorBetween<double>(moved, q).isApprox(
      kQuaternionTangentToRotationVector * d, 1e-9));
}

}  // namespace
}  // namespace trackcal::fit
