// Axes of a Unity scene from the tracker's frame.
//
// VRPN passes the device's own frame (for the Fastrak, the Polhemus source frame: right-handed,
// x forward, y right, z down when the source is mounted as its manual shows). Unity's world is
// left-handed with y up. The mapping is a signed permutation: Unity's x, y and z are each one
// tracker axis, possibly negated, written "y,-z,x" (Unity x = tracker y, Unity y = -tracker z,
// Unity z = tracker x). It must flip handedness (determinant -1), or the scene is mirrored.
//
// A pose transmitter_from_receiver (p_in_tx = R * p_in_rx + t) becomes, with M =
// unity_from_tracker:
//   position_unity = M * t,     rotation_unity = M * R * M^T   (a proper rotation, det = +1).
// As a quaternion (w, v): M R M^T turns about det(M) * M * axis by the same angle, so
//   q_unity = (w, det(M) * M * v) = (w, -M * v).
// Unity's Quaternion(x, y, z, w) then rotates Unity coordinates by the standard formula.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <string>
#include <string_view>

#include "core/pose.h"

namespace trackcal::unity {

// The Polhemus source frame (x forward, y right, z down) to Unity (x right, y up, z forward).
inline constexpr std::string_view kDefaultAxes = "y,-z,x";

struct AxisMap {
  Eigen::Matrix3d unity_from_tracker = Eigen::Matrix3d::Identity();
  std::string spec;  // as parsed, normalised ("y,-z,x")
};

// Parses "y,-z,x" (spaces and upper case allowed; "+x" as "x"). Throws std::invalid_argument naming
// the text and what is wrong: an item that is not an axis, an axis used twice, or a mapping that
// keeps handedness (a mirrored scene).
AxisMap ParseAxisMap(std::string_view spec);

struct UnityPose {
  Eigen::Vector3d position = Eigen::Vector3d::Zero();            // metres, Unity axes
  Eigen::Quaterniond rotation = Eigen::Quaterniond::Identity();  // Unity axes
};

// A quaternion further than this from unit length is normalised by ToUnity.
inline constexpr double kUnitQuaternionTolerance = 1e-6;

// transmitter_from_receiver (tracker frame) in Unity's axes. The quaternion keeps the sign of the
// input's w, so a stream of poses stays continuous; one further than kUnitQuaternionTolerance from
// unit length is normalised. Throws std::invalid_argument for a zero or non-finite quaternion or a
// non-finite position (nothing Unity can show).
UnityPose ToUnity(const AxisMap& axes, const Rigid3d& transmitter_from_receiver);

}  // namespace trackcal::unity
