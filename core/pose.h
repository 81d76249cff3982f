// Pose math and the conventions every trackcal module shares.
//
// - Units: metres and seconds; angles in radians inside the math (degrees only in reports).
// - A rigid transform is named after the frames it relates: `b_from_a` maps a point of frame a into
//   frame b with an active rotation, `x_in_b = b_from_a.rotation * x_in_a + b_from_a.translation`.
//   A tracker pose is `transmitter_from_receiver`.
// - Quaternion arrays (numpy, the VRPN wire, the calibration file) are ordered x, y, z, w, which is
//   also Eigen's storage order. Eigen's four-scalar constructor takes w first; build quaternions only
//   through the named helpers below so the order is always written at the call site.
// - Orientation error is the world-frame (transmitter-frame) error quaternion
//   q_e = q_ref * conj(q_reported) (Ikits et al. 2001, eq. 3); a correction applies q = q_e * q_reported
//   (eq. 4). Its minimal form is the vector part of q_e with the sign that makes the scalar part
//   non-negative (eq. 6), so q and -q give the same error vector.
// - Position error is p_ref - p_reported (eq. 1).
//
// Everything templated on the scalar type is used by Ceres autodiff in fit/ and must stay free of
// branches on values that would break derivatives where it matters (documented per function).

#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <cmath>
#include <numbers>
#include <string>

namespace trackcal {

template <typename T>
using Vector3 = Eigen::Matrix<T, 3, 1>;

inline constexpr double kDegPerRad = 180.0 / std::numbers::pi;
inline constexpr double kRadPerDeg = std::numbers::pi / 180.0;
inline constexpr double kMetresPerInch = 0.0254;

// Quaternion from its components given scalar first.
template <typename T>
Eigen::Quaternion<T> QuaternionFromWxyz(const T& w, const T& x, const T& y, const T& z) {
  return Eigen::Quaternion<T>(w, x, y, z);
}

// Quaternion from components given scalar last (the array, wire and Eigen-storage order).
template <typename T>
Eigen::Quaternion<T> QuaternionFromXyzw(const T& x, const T& y, const T& z, const T& w) {
  return Eigen::Quaternion<T>(w, x, y, z);
}

// Quaternion from a pointer to 4 scalars ordered x, y, z, w.
template <typename T>
Eigen::Quaternion<T> QuaternionFromXyzwArray(const T* xyzw) {
  return Eigen::Quaternion<T>(xyzw[3], xyzw[0], xyzw[1], xyzw[2]);
}

// Writes q as x, y, z, w.
template <typename T>
void QuaternionToXyzwArray(const Eigen::Quaternion<T>& q, T* xyzw) {
  xyzw[0] = q.x();
  xyzw[1] = q.y();
  xyzw[2] = q.z();
  xyzw[3] = q.w();
}

// Unit quaternion whose vector part is v and whose scalar part is sqrt(1 - |v|^2) >= 0 (paper eq. 6).
// |v| >= 1 cannot come from a unit quaternion; it is mapped to the 180 degree rotation about v so that
// an over-reaching fit degrades smoothly instead of producing NaN.
template <typename T>
Eigen::Quaternion<T> QuaternionFromVectorPart(const Vector3<T>& v) {
  using std::sqrt;
  const T n2 = v.squaredNorm();
  if (n2 < T(1)) {
    return QuaternionFromXyzw<T>(v.x(), v.y(), v.z(), sqrt(T(1) - n2));
  }
  const T n = sqrt(n2);
  return QuaternionFromXyzw<T>(v.x() / n, v.y() / n, v.z() / n, T(0));
}

// Vector part of q with the sign that makes the scalar part non-negative (q and -q are equal).
template <typename T>
Vector3<T> VectorPart(const Eigen::Quaternion<T>& q) {
  const Vector3<T> v = q.vec();
  return q.w() < T(0) ? Vector3<T>(-v) : v;
}

// Rotation angle of q in [0, pi], independent of the sign of q.
inline double RotationAngle(const Eigen::Quaterniond& q) {
  const double n = q.vec().norm();
  return 2.0 * std::atan2(n, std::abs(q.w()));
}

// Angle of the rotation between a and b in [0, pi]; a and -a are the same rotation.
inline double AngularDistance(const Eigen::Quaterniond& a, const Eigen::Quaterniond& b) {
  return RotationAngle(a * b.conjugate());
}

// A rigid transform b_from_a; storage: rotation as a unit quaternion (x, y, z, w), then translation.
struct Rigid3d {
  Eigen::Quaterniond rotation = Eigen::Quaterniond::Identity();
  Eigen::Vector3d translation = Eigen::Vector3d::Zero();

  Rigid3d() = default;
  Rigid3d(const Eigen::Quaterniond& rotation, const Eigen::Vector3d& translation)
      : rotation(rotation), translation(translation) {}

  // x_in_b = b_from_a * x_in_a.
  Eigen::Vector3d operator*(const Eigen::Vector3d& x_in_a) const {
    return rotation * x_in_a + translation;
  }
  // c_from_a = c_from_b * b_from_a.
  Rigid3d operator*(const Rigid3d& b_from_a) const {
    return Rigid3d(rotation * b_from_a.rotation, rotation * b_from_a.translation + translation);
  }
  // a_from_b.
  Rigid3d Inverse() const {
    const Eigen::Quaterniond r_inv = rotation.conjugate();
    return Rigid3d(r_inv, -(r_inv * translation));
  }
  // "Rigid3d(rotation_xyzw=[x, y, z, w], translation=[x, y, z])".
  std::string ToString() const;
};

// Error of a reported pose against a reference pose, both transmitter_from_receiver.
struct PoseError {
  Eigen::Vector3d position = Eigen::Vector3d::Zero();     // p_ref - p_reported [m] (eq. 1)
  Eigen::Vector3d orientation = Eigen::Vector3d::Zero();  // vector part of q_ref * conj(q_rep) (eq. 3, 6)
};

template <typename T>
Vector3<T> OrientationErrorVector(const Eigen::Quaternion<T>& q_reference,
                                  const Eigen::Quaternion<T>& q_reported) {
  return VectorPart<T>(q_reference * q_reported.conjugate());
}

inline PoseError ComputePoseError(const Rigid3d& reported, const Rigid3d& reference) {
  PoseError e;
  e.position = reference.translation - reported.translation;
  e.orientation = OrientationErrorVector<double>(reference.rotation, reported.rotation);
  return e;
}

// Applies an error (as predicted by a correction) to a reported pose: p + e_p, q_e * q (eq. 4).
template <typename T>
void ApplyPoseError(const Vector3<T>& position_error, const Vector3<T>& orientation_error,
                    Vector3<T>* position, Eigen::Quaternion<T>* rotation) {
  *position += position_error;
  *rotation = QuaternionFromVectorPart<T>(orientation_error) * *rotation;
}

// Magnitudes used in every table: position error in metres, orientation error angle in radians.
inline double PositionErrorNorm(const Rigid3d& a, const Rigid3d& b) {
  return (a.translation - b.translation).norm();
}
inline double OrientationErrorAngle(const Rigid3d& a, const Rigid3d& b) {
  return AngularDistance(a.rotation, b.rotation);
}

}  // namespace trackcal
