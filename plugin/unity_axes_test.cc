#include "plugin/unity_axes.h"

#include <gtest/gtest.h>

#include <cmath>
#include <random>
#include <string>
#include <utility>

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

// UnityEngine.Quaternion * Vector3 as Unity's C# reference source writes it (Quaternion.cs).
Eigen::Vector3d UnityRotate(const Eigen::Quaterniond& q, const Eigen::Vector3d& p) {
  const double x = q.x() * 2, y = q.y() * 2, z = q.z() * 2;
  const double xx = q.x() * x, yy = q.y() * y, zz = q.z() * z;
  const double xy = q.x() * y, xz = q.x() * z, yz = q.y() * z;
  const double wx = q.w() * x, wy = q.w() * y, wz = q.w() * z;
  return {(1 - (yy + zz)) * p.x() + (xy - wz) * p.y() + (xz + wy) * p.z(),
          (xy + wz) * p.x() + (1 - (xx + zz)) * p.y() + (yz - wx) * p.z(),
          (xz - wy) * p.x() + (yz + wx) * p.y() + (1 - (xx + yy)) * p.z()};
}

// Forward, right and up of a frame, in its coordinates (the columns).
Eigen::Matrix3d Directions(const Eigen::Vector3d& forward, const Eigen::Vector3d& right,
                           const Eigen::Vector3d& up) {
  Eigen::Matrix3d f;
  f << forward, right, up;
  return f;
}

// Turns described by where they send forward, right and up (coordinates: forward, right, up), so
// with no handedness of their own: the same words give each frame its rotation.
Eigen::Matrix3d YawRight(double a) {  // forward turns towards right, seen from above
  Eigen::Matrix3d n;
  n << std::cos(a), -std::sin(a), 0, std::sin(a), std::cos(a), 0, 0, 0, 1;
  return n;
}
Eigen::Matrix3d PitchUp(double a) {  // forward turns towards up
  Eigen::Matrix3d n;
  n << std::cos(a), 0, -std::sin(a), 0, 1, 0, std::sin(a), 0, std::cos(a);
  return n;
}
Eigen::Matrix3d RollRight(double a) {  // the right side goes down
  Eigen::Matrix3d n;
  n << 1, 0, 0, 0, std::cos(a), std::sin(a), 0, -std::sin(a), std::cos(a);
  return n;
}

// From first principles, per docs/unity.md's table: a receiver placed and turned as words say
// (forward, right, up of the source) is placed and turned as the same words say in Unity, one turn
// about each axis and a composite, and every point of the receiver's body lands where the words put
// it; the rotation checked with Unity's own rule for Quaternion * Vector3.
TEST(ToUnity, ATurnAboutEachAxisIsTheSameTurnInUnity) {
  const Eigen::Matrix3d unity =
      Directions(Eigen::Vector3d::UnitZ(), Eigen::Vector3d::UnitX(), Eigen::Vector3d::UnitY());
  struct Row {
    const char* axes;
    Eigen::Matrix3d tracker;  // the tracker frame's forward, right and up
  };
  const Row rows[] = {
      // The source as the manual shows: x forward, y right, z down.
      {"y,-z,x", Directions({1, 0, 0}, {0, 1, 0}, {0, 0, -1})},
      // A right-handed y-up frame: x right, y up, z backwards.
      {"x,y,-z", Directions({0, 0, -1}, {1, 0, 0}, {0, 1, 0})},
      // The source upside down: x forward, y left, z up.
      {"-y,z,x", Directions({1, 0, 0}, {0, -1, 0}, {0, 0, 1})},
  };
  const double a = 30.0 * M_PI / 180.0;
  const std::pair<const char*, Eigen::Matrix3d> turns[] = {
      {"yaw right", YawRight(a)},
      {"pitch up", PitchUp(a)},
      {"roll right", RollRight(a)},
      {"yaw, pitch, roll", YawRight(a) * PitchUp(-2 * a) * RollRight(1.5 * a)},
  };
  // The receiver 0.4 m forward, 0.1 m right and 0.2 m up of the source; a point 5 cm in front of
  // it, 2 cm to its right and 1 cm above it (its own forward, right, up).
  const Eigen::Vector3d placed(0.4, 0.1, 0.2), body_point(0.05, 0.02, 0.01);
  for (const Row& row : rows) {
    const AxisMap axes = ParseAxisMap(row.axes);
    const Eigen::Matrix3d& f = row.tracker;
    for (const auto& [what, words] : turns) {
      SCOPED_TRACE(std::string(row.axes) + ", " + what);
      const Eigen::Matrix3d tracker_rotation = f * words * f.transpose();
      ASSERT_NEAR(tracker_rotation.determinant(), 1.0, kTol);
      const UnityPose u = ToUnity(axes, Rigid3d(Eigen::Quaterniond(tracker_rotation), f * placed));
      EXPECT_NEAR((u.position - unity * placed).norm(), 0.0, kTol);
      const Eigen::Matrix3d expected = unity * words * unity.transpose();
      for (int i = 0; i < 3; ++i) {
        const Eigen::Vector3d e = Eigen::Vector3d::Unit(i);
        EXPECT_NEAR((UnityRotate(u.rotation, e) - expected * e).norm(), 0.0, kTol) << i;
      }
      const Eigen::Vector3d point_in_unity =
          UnityRotate(u.rotation, unity * body_point) + u.position;
      EXPECT_NEAR((point_in_unity - unity * (placed + words * body_point)).norm(), 0.0, kTol);
    }
  }
}

// A stream of continuous quaternions (a receiver turning twice round, through w = 0 and beyond)
// stays continuous: consecutive Unity quaternions never jump to the other sign, which a script
// interpolating between frames would see as a turn the long way round.
TEST(ToUnity, AContinuousStreamOfQuaternionsStaysContinuous) {
  const AxisMap axes = ParseAxisMap(kDefaultAxes);
  const Eigen::Vector3d axis = Eigen::Vector3d(0.3, -0.5, 0.8).normalized();
  Eigen::Quaterniond previous_in = Eigen::Quaterniond::Identity(), previous_out = previous_in;
  for (int i = 0; i <= 720; ++i) {
    const Eigen::Quaterniond q(Eigen::AngleAxisd(i * M_PI / 180.0, axis));  // w < 0 past 180 deg
    const UnityPose u = ToUnity(axes, Rigid3d(q, Eigen::Vector3d::Zero()));
    EXPECT_NEAR(u.rotation.norm(), 1.0, kTol);
    if (i > 0) {
      // A signed permutation keeps dot products: the step is the tracker's, about 1 deg.
      EXPECT_NEAR(u.rotation.dot(previous_out), q.dot(previous_in), kTol) << i;
      EXPECT_GT(u.rotation.dot(previous_out), 0.9) << i;
    }
    previous_in = q;
    previous_out = u.rotation;
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
