#include "core/pose.h"

#include <gtest/gtest.h>

#include "tests/test_utils.h"

namespace trackcal {
namespace {

using testing::RandomRotation;
using testing::TestRng;

TEST(QuaternionHelpers, Nominal) {
  const double xyzw[4] = {0.1, 0.2, 0.3, 0.9};
  const Eigen::Quaterniond a = QuaternionFromXyzwArray(xyzw);
  const Eigen::Quaterniond b = QuaternionFromWxyz(0.9, 0.1, 0.2, 0.3);
  EXPECT_EQ(a.coeffs(), b.coeffs());
  double out[4];
  QuaternionToXyzwArray(a, out);
  for (int i = 0; i < 4; ++i) EXPECT_EQ(out[i], xyzw[i]);
  // Eigen stores x, y, z, w: the array order of the wire.
  EXPECT_EQ(a.coeffs()[3], 0.9);
}

TEST(VectorPart, SignInvariant) {
  for (int i = 0; i < 100; ++i) {
    const Eigen::Quaterniond q = RandomRotation(TestRng());
    const Eigen::Quaterniond minus_q = QuaternionFromXyzw(-q.x(), -q.y(), -q.z(), -q.w());
    EXPECT_EQ(VectorPart(q), VectorPart(minus_q));
    // Round trip through the minimal representation gives the same rotation.
    EXPECT_TRUE(testing::RotationsNear(q, QuaternionFromVectorPart<double>(VectorPart(q)), 1e-12));
  }
}

TEST(QuaternionFromVectorPart, OverReachingVectorStaysUnit) {
  const Eigen::Quaterniond q = QuaternionFromVectorPart<double>(Eigen::Vector3d(2.0, 0.0, 0.0));
  EXPECT_NEAR(q.norm(), 1.0, 1e-15);
  EXPECT_NEAR(RotationAngle(q), std::numbers::pi, 1e-12);
}

TEST(AngularDistance, QAndMinusQAreEqual) {
  const Eigen::Quaterniond q = RandomRotation(TestRng());
  const Eigen::Quaterniond minus_q = QuaternionFromXyzw(-q.x(), -q.y(), -q.z(), -q.w());
  // A few ulp of the unit quaternion's components: 2e-15. (1e-7 also passed 2 acos(|a . b|),
  // whose rounding of a dot product near 1 is ~3e-8 rad.)
  EXPECT_NEAR(AngularDistance(q, minus_q), 0.0, 2e-15);
  const Eigen::Quaterniond r(Eigen::AngleAxisd(0.3, Eigen::Vector3d::UnitZ()));
  EXPECT_NEAR(AngularDistance(q, r * q), 0.3, 1e-12);
}

TEST(AngularDistance, TinyAnglesAreExactToRounding) {
  // atan2 of the vector and scalar parts keeps tiny angles: the vector part of a conj(b) is
  // computed to a few ulp of 1 (~1e-16 absolute), so the angle is within 2e-15 rad of the truth at
  // every size (worst seen 5e-16 over 10^6 random rotations). An acos of the dot product is
  // ~7e-8 rad off (the dot rounds to 1 below ~2e-8 rad).
  const Eigen::Vector3d axis = Eigen::Vector3d(0.3, -0.5, 0.8).normalized();
  for (double angle : {1e-12, 1e-10, 1e-8, 1e-6, 1e-4}) {
    for (int i = 0; i < 10; ++i) {
      const Eigen::Quaterniond q = RandomRotation(TestRng());
      const Eigen::Quaterniond delta(Eigen::AngleAxisd(angle, axis));
      EXPECT_NEAR(AngularDistance(delta * q, q), angle, 2e-15) << angle;
      EXPECT_NEAR(AngularDistance(q, q * delta), angle, 2e-15) << angle;
      // Both signs of either quaternion.
      const Eigen::Quaterniond minus_q = QuaternionFromXyzw(-q.x(), -q.y(), -q.z(), -q.w());
      EXPECT_NEAR(AngularDistance(delta * q, minus_q), angle, 2e-15) << angle;
    }
  }
}

TEST(PoseError, PaperEquations) {
  // Reference rotated 2 degrees about transmitter x relative to the report, whatever the report's
  // orientation: the world-frame error (eq. 3) does not depend on the receiver's orientation.
  const Eigen::Quaterniond delta(Eigen::AngleAxisd(2.0 * kRadPerDeg, Eigen::Vector3d::UnitX()));
  for (int i = 0; i < 20; ++i) {
    const Rigid3d reported(RandomRotation(TestRng()), Eigen::Vector3d(0.3, -0.2, 0.5));
    const Rigid3d reference(delta * reported.rotation, Eigen::Vector3d(0.31, -0.2, 0.49));
    const PoseError e = ComputePoseError(reported, reference);
    EXPECT_TRUE(e.position.isApprox(Eigen::Vector3d(0.01, 0.0, -0.01), 1e-12));
    EXPECT_TRUE(e.orientation.isApprox(Eigen::Vector3d(std::sin(1.0 * kRadPerDeg), 0, 0), 1e-12));
    Eigen::Vector3d p = reported.translation;
    Eigen::Quaterniond q = reported.rotation;
    ApplyPoseError<double>(e.position, e.orientation, &p, &q);
    EXPECT_TRUE(testing::PosesNear(reference, Rigid3d(q, p), 1e-15, 1e-12));
  }
}

TEST(Rigid3d, ComposeAndInverse) {
  const Rigid3d b_from_a(RandomRotation(TestRng()), Eigen::Vector3d(1, 2, 3));
  const Rigid3d c_from_b(RandomRotation(TestRng()), Eigen::Vector3d(-1, 0.5, 0));
  const Eigen::Vector3d x_in_a(0.2, -0.4, 0.7);
  EXPECT_TRUE(((c_from_b * b_from_a) * x_in_a).isApprox(c_from_b * (b_from_a * x_in_a), 1e-14));
  EXPECT_TRUE((b_from_a.Inverse() * (b_from_a * x_in_a)).isApprox(x_in_a, 1e-14));
  EXPECT_NE(b_from_a.ToString().find("rotation_xyzw=["), std::string::npos);
}

}  // namespace
}  // namespace trackcal
