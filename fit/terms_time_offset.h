// The clock offset between the tracker and reference streams as a parameter of the fit.
//
// A stream sample pairs the tracker's reading at tracker time t with the reference interpolated at
// reference time t + dt0 (fit/stream_pairing.h). With the offset dt instead, the reference moves by
// its velocity: to first order
//
//   p_ref(dt) = p_ref + v (dt - dt0),   q_ref(dt) = exp(w (dt - dt0)) q_ref
//
// with v the reference's linear velocity and w its angular velocity in the transmitter frame
// (FitStation::reference_velocity, reference_angular_velocity). The fit engine (fit/fit_engine.h)
// adds dt as one parameter block when the model file's `time_offset` is not fixed and the stations
// carry velocities; dt0 is the model file's `time_offset.value`, the offset the stations were
// paired at. The linearisation error is |acceleration| (dt - dt0)^2 / 2 (0.5 mm for 37 ms at 0.8
// m/s^2), so a caller re-pairs at the estimate when it moved far (trackcal-fit does).
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>

#include "core/pose.h"
#include "fit/rotation.h"

namespace trackcal::fit {

// The reference pose moved by (dt - dt0) along its velocity; T may be a ceres::Jet in dt.
template <typename T>
void ShiftReference(const Rigid3d& reference, const Eigen::Vector3d& velocity,
                    const Eigen::Vector3d& angular_velocity, const T& dt_minus_dt0,
                    Vector3<T>* position, Eigen::Quaternion<T>* rotation) {
  *position = reference.translation.cast<T>() + velocity.cast<T>() * dt_minus_dt0;
  const Vector3<T> rotation_vector = angular_velocity.cast<T>() * dt_minus_dt0;
  T dq_xyzw[4];
  RotationVectorToQuaternion(rotation_vector.data(), dq_xyzw);
  *rotation = QuaternionFromXyzwArray(dq_xyzw) * reference.rotation.cast<T>();
}

}  // namespace trackcal::fit
