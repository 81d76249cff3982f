#include "plugin/unity_axes.h"

#include <gtest/gtest.h>

#include <cmath>
#include <random>

#include "tests/test_utils.h"

namespace trackcal::unity {
namespace {

// Arithmetic on a signed permutation and a unit quaternion: 1e-12 is ~1e4 ulps of the values (<= 2
// m).
constexpr double kTol = 1e-12;

TEST(ParseAxisMap, TheDefaultIsThePolhemusSourceFrameInUnity) {
  const AxisMap axes = ParseAxisMap(kDefaultAxes);
  Eigen::Matrix3d expected;
  expected << 0, 1, 0,  //  Unity x (right)   = tracker y (right)
      0, 0, -1,         //  Unity y (up)      = -tracker z (down)
      1, 0, 0;          //  Unity z (forward) = tracker x (forward)
  EXPECT_EQ(axes.unity_from_tracker, expected);
  EXPECT_EQ(axes.spec, "y,-z,x");
  EXPECT_EQ(ParseAxisMap(" Y , -Z, +x ").spec, "y,-z,x");
  EXPECT_EQ(ParseAxisMap("x,y,-z").spec, "x,y,-z");
}

TEST(ParseAxisMap, BadMappingsAreNamed) {
  const auto message = [](const char* spec) {
    try {
      ParseAxisMap(spec);
    } catch (const std::invalid_argument& e) {
      return std::string(e.what());
    }
    return std::string("no error");
  };
  EXPECT_NE(message("x,y,z").find("mirrored"), std::string::npos) << message("x,y,z");
  EXPECT_EQ(message("-x,-y,-z"), "no error");  // det -1: valid (a point reflection)
  EXPECT_NE(message("x,x,-z").find("tracker axis x is used twice"), std::string::npos);
  EXPECT_NE(message("x,y").find("fewer than three"), std::string::npos);
  EXPECT_NE(message("x,y,z,x").find("more than three"), std::string::npos);
  EXPECT_NE(message("x,up,z").find("Unity y is \"up\""), std::string::npos) << message("x,up,z");
  EXPECT_NE(message("").find("axes \"\""), std::string::npos);
}

TEST(ToUnity, AHandCheckedPose) {
  const AxisMap axes = ParseAxisMap(kDefaultAxes);
  // Receiver 1 m forward, 0.2 m right and 0.5 m below the source, turned 90 deg about the source's
  // z (down): seen from above, forward turns to the right.
  const Rigid3d pose(Eigen::Quaterniond(Eigen::AngleAxisd(M_PI / 2, Eigen::Vector3d::UnitZ())),
                     Eigen::Vector3d(1.0, 0.2, 0.5));
  const UnityPose u = ToUnity(axes, pose);
  EXPECT_NEAR((u.position - Eigen::Vector3d(0.2, -0.5, 1.0)).norm(), 0.0, kTol);
  // In Unity (left-handed, y up) turning right is +90 deg about +y: (0, sin 45, 0, cos 45).
  EXPECT_NEAR(u.rotation.x(), 0.0, kTol);
  EXPECT_NEAR(u.rotation.y(), std::sqrt(0.5), kTol);
  EXPECT_NEAR(u.rotation.z(), 0.0, kTol);
  EXPECT_NEAR(u.rotation.w(), std::sqrt(0.5), kTol);
  // Unity's own rule for that quaternion: forward (0, 0, 1) becomes right (1, 0, 0).
  EXPECT_NEAR((u.rotation * Eigen::Vector3d::UnitZ() - Eigen::Vector3d::UnitX()).norm(), 0.0, kTol);
}

TEST(ToUnity, MapsEveryPointOfTheReceiverAsTheTrackerDoes) {
  auto& rng = testing::TestRng();
  std::uniform_real_distribution<double> u(-1.5, 1.5);
  for (const char* spec : {"y,-z,x", "x,y,-z", "-x,-y,-z", "z,x,-y"}) {
    const AxisMap axes = ParseAxisMap(spec);
    const Eigen::Matrix3d& m = axes.unity_from_tracker;
    for (int i = 0; i < 200; ++i) {
      const Rigid3d pose(testing::RandomRotation(rng), Eigen::Vector3d(u(rng), u(rng), u(rng)));
      const UnityPose up = ToUnity(axes, pose);
      EXPECT_NEAR(up.rotation.norm(), 1.0, kTol);
      EXPECT_NEAR(
          (up.rotation.toRotationMatrix() - m * pose.rotation.toRotationMatrix() * m.transpose())
              .norm(),
          0.0, kTol);
      // A point of the receiver's body, in the tracker and in Unity: the same world point.
      const Eigen::Vector3d p_in_rx(u(rng), u(rng), u(rng));
      const Eigen::Vector3d unity_of_tracker_point = m * (pose * p_in_rx);
      const Eigen::Vector3d unity_point = up.rotation * (m * p_in_rx) + up.position;
      EXPECT_NEAR((unity_of_tracker_point - unity_point).norm(), 0.0, kTol) << spec;
      EXPECT_EQ(std::signbit(up.rotation.w()), std::signbit(pose.rotation.w()));  // continuity
    }
  }
}

TEST(ToUnity, NormalisesAQuaternionThatIsNotUnitAndRefusesOneThatIsNoRotation) {
  const AxisMap axes = ParseAxisMap(kDefaultAxes);
  auto& rng = testing::TestRng();
  const Rigid3d unit(testing::RandomRotation(rng), Eigen::Vector3d(0.1, 0.2, 0.3));
  Rigid3d scaled = unit;
  scaled.rotation.coeffs() *= 0.97;  // a third-party server's sloppy quaternion
  const UnityPose a = ToUnity(axes, unit), b = ToUnity(axes, scaled);
  EXPECT_NEAR(b.rotation.norm(), 1.0, kTol);
  EXPECT_NEAR((a.rotation.coeffs() - b.rotation.coeffs()).norm(), 0.0, kTol);
  EXPECT_EQ(a.position, b.position);
  Rigid3d bad = unit;
  bad.rotation.coeffs().setZero();
  EXPECT_THROW(ToUnity(axes, bad), std::invalid_argument);
  bad = unit;
  bad.translation.x() = std::nan("");
  EXPECT_THROW(ToUnity(axes, bad), std::invalid_argument);
}

}  // namespace
}  // namespace trackcal::unity
