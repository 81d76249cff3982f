// The kinematic model of the optical registration apparatus (Ikits et al. 2001, section 3.1) and
// its Ceres residuals.
//
// A rigid body carries the EM receiver and markers at fixed positions marker_in_receiver (r_j).
// The optical system measures marker positions in its own frame:
//
//   marker_in_optical = optical_from_transmitter * transmitter_from_receiver * marker_in_receiver
//
// which is eq. 10, v_j = p0 + R(q0) (p + R(q) r_j), with (q0, p0) = optical_from_transmitter and
// (q, p) = transmitter_from_receiver. Quaternion blocks are 4 scalars x, y, z, w on
// ceres::EigenQuaternionManifold; translations and points are 3 scalars in metres.

#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>

#include "core/pose.h"
#include "fit/cost_functor.h"
#include "fit/rotation.h"

namespace trackcal::fit {

// Eq. 10. Templated so that Ceres differentiates exactly the code that predicts marker positions.
template <typename T>
Vector3<T> PredictMarkerInOptical(const T* optical_from_transmitter_q,
                                  const T* optical_from_transmitter_t,
                                  const T* transmitter_from_receiver_q,
                                  const T* transmitter_from_receiver_t,
                                  const T* marker_in_receiver) {
  Vector3<T> marker_in_transmitter;
  RotatePoint(transmitter_from_receiver_q, marker_in_receiver, marker_in_transmitter.data());
  marker_in_transmitter += Eigen::Map<const Vector3<T>>(transmitter_from_receiver_t);
  Vector3<T> marker_in_optical;
  RotatePoint(optical_from_transmitter_q, marker_in_transmitter.data(), marker_in_optical.data());
  return marker_in_optical + Eigen::Map<const Vector3<T>>(optical_from_transmitter_t);
}

// Predicted minus measured optical marker position [m] (the y residual of eq. 14).
// Blocks: optical_from_transmitter q (4), t (3); transmitter_from_receiver q (4), t (3);
// marker_in_receiver (3).
class MarkerPositionCost : public AutoDiffCostFunctor<MarkerPositionCost, 3, 4, 3, 4, 3, 3> {
 public:
  explicit MarkerPositionCost(const Eigen::Vector3d& measured_marker_in_optical)
      : measured_(measured_marker_in_optical) {}

  template <typename T>
  bool operator()(const T* optical_from_transmitter_q, const T* optical_from_transmitter_t,
                  const T* transmitter_from_receiver_q, const T* transmitter_from_receiver_t,
                  const T* marker_in_receiver, T* residuals) const {
    Eigen::Map<Vector3<T>> r(residuals);
    r = PredictMarkerInOptical(optical_from_transmitter_q, optical_from_transmitter_t,
                               transmitter_from_receiver_q, transmitter_from_receiver_t,
                               marker_in_receiver) -
        measured_.cast<T>();
    return true;
  }

 private:
  Eigen::Vector3d measured_;
};

// Deviation of an estimated pose from a measured one (the x residual of eq. 14): position
// difference [m] then the rotation vector [rad] of q * conj(q_measured), in the pose's parent
// frame (the world-frame error of eq. 3, exact angle instead of the vector part).
// Blocks: q (4), t (3).
class PosePriorCost : public AutoDiffCostFunctor<PosePriorCost, 6, 4, 3> {
 public:
  explicit PosePriorCost(const Rigid3d& measured) : measured_(measured) {}

  template <typename T>
  bool operator()(const T* q, const T* t, T* residuals) const {
    Eigen::Map<Vector3<T>> position(residuals);
    Eigen::Map<Vector3<T>> orientation(residuals + 3);
    position = Eigen::Map<const Vector3<T>>(t) - measured_.translation.cast<T>();
    orientation =
        RotationVectorBetween<T>(QuaternionFromXyzwArray(q), measured_.rotation.cast<T>());
    return true;
  }

 private:
  Rigid3d measured_;
};

}  // namespace trackcal::fit
