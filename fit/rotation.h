// The one place where trackcal calls ceres/rotation.h.
//
// Ceres 2.1's rotation.h takes quaternions as w, x, y, z; trackcal (and Eigen) store them as
// x, y, z, w. Every function here takes and returns x, y, z, w and reorders internally, so no other
// file has to remember the difference. Quaternion parameter blocks stored in Eigen order use
// ceres::EigenQuaternionManifold (SetQuaternionManifold); ceres::QuaternionManifold expects w first
// and must never be used on them.
//
// Tangent convention of EigenQuaternionManifold: q ⊞ d = [cos|d|, sin|d| d/|d|] * q, a left
// (transmitter- or world-frame) perturbation whose rotation angle is 2|d|. Covariances in that
// tangent space are converted to rotation vectors (radians) with
// kQuaternionTangentToRotationVector.

#pragma once

#include <ceres/manifold.h>
#include <ceres/problem.h>
#include <ceres/rotation.h>

#include "core/pose.h"

namespace trackcal::fit {

// Rotation vector (radians) per unit of EigenQuaternionManifold tangent: the tangent is a half
// angle, so a rotation vector is twice the tangent vector (to first order).
inline constexpr double kQuaternionTangentToRotationVector = 2.0;

// result = R(q) * point for a unit quaternion q (x, y, z, w); no normalisation is applied.
template <typename T>
void RotatePoint(const T* q_xyzw, const T* point, T* result) {
  const T q_wxyz[4] = {q_xyzw[3], q_xyzw[0], q_xyzw[1], q_xyzw[2]};
  ceres::UnitQuaternionRotatePoint(q_wxyz, point, result);
}

// Rotation vector (axis * angle, angle in [0, pi]) of the quaternion q (x, y, z, w); q and -q give
// the same vector. Differentiable at the identity (Ceres handles the small-angle limit).
template <typename T>
void QuaternionToRotationVector(const T* q_xyzw, T* rotation_vector) {
  const T q_wxyz[4] = {q_xyzw[3], q_xyzw[0], q_xyzw[1], q_xyzw[2]};
  ceres::QuaternionToAngleAxis(q_wxyz, rotation_vector);
}

// Unit quaternion (x, y, z, w) of a rotation vector (axis * angle in radians).
template <typename T>
void RotationVectorToQuaternion(const T* rotation_vector, T* q_xyzw) {
  T q_wxyz[4];
  ceres::AngleAxisToQuaternion(rotation_vector, q_wxyz);
  q_xyzw[0] = q_wxyz[1];
  q_xyzw[1] = q_wxyz[2];
  q_xyzw[2] = q_wxyz[3];
  q_xyzw[3] = q_wxyz[0];
}

// Rotation vector of a * conj(b): the world-frame (left) rotation taking b to a, in radians. This
// is the exact-angle counterpart of the paper's error vector (eq. 3, 6) and the residual trackcal
// whitens with an orientation noise in radians.
template <typename T>
Vector3<T> RotationVectorBetween(const Eigen::Quaternion<T>& a, const Eigen::Quaternion<T>& b) {
  const Eigen::Quaternion<T> delta = a * b.conjugate();
  T xyzw[4];
  QuaternionToXyzwArray(delta, xyzw);
  Vector3<T> v;
  QuaternionToRotationVector(xyzw, v.data());
  return v;
}

inline Eigen::Quaterniond QuaternionFromRotationVector(const Eigen::Vector3d& rotation_vector) {
  double xyzw[4];
  RotationVectorToQuaternion(rotation_vector.data(), xyzw);
  return QuaternionFromXyzwArray(xyzw);
}

// Declares q_xyzw (a 4-scalar block in Eigen order, already added or not) as a unit quaternion.
inline void SetQuaternionManifold(ceres::Problem* problem, double* q_xyzw) {
  problem->AddParameterBlock(q_xyzw, 4, new ceres::EigenQuaternionManifold);
}

}  // namespace trackcal::fit
