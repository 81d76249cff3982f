#pragma once
// The station residual the fit minimises and the metric that makes a physical group's
// report-space residual (ModelTerm::EvaluateToward) weigh pose errors (docs/fit.md).

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <optional>

#include "core/pose.h"
#include "fit/model.h"

namespace trackcal::fit {

using Matrix6 = Eigen::Matrix<double, 6, 6>;

// The station residual ((p_c - p_ref) / sigma_p, VectorPart(q_c conj(q_ref)) / sigma_o) of a
// corrected pose (ambient, 7) against a reference.
template <typename T>
void StationResidual(const T* pose7, const Vector3<T>& p_ref, const Eigen::Quaternion<T>& q_ref,
                     double sigma_p, double sigma_o, T* residual6) {
  for (int k = 0; k < 3; ++k) residual6[k] = (pose7[k] - p_ref[k]) / T(sigma_p);
  const Eigen::Quaternion<T> q = QuaternionFromXyzwArray(pose7 + 3);
  const Vector3<T> v = OrientationErrorVector<T>(q, q_ref);
  for (int k = 0; k < 3; ++k) residual6[3 + k] = v[k] / T(sigma_o);
}
template <typename T>
void StationResidual(const T* pose7, const Rigid3d& reference, double sigma_p, double sigma_o,
                     T* residual6) {
  StationResidual<T>(pose7, reference.translation.cast<T>(), reference.rotation.cast<T>(), sigma_p,
                     sigma_o, residual6);
}

// The right-tangent chart of a pose (p + eps_p, q normalize(1, eps_w / 2)), equal to q Exp(eps_w)
// to second order. d ambient / d tangent (7 x 6) at a pose:
Eigen::Matrix<double, 7, 6> AmbientOfTangent(const AmbientPose& pose);
// d tangent / d ambient (6 x 7) at an ambient pose whose quaternion need not be of unit norm:
// eps_w = 2 vec(conj(q) dq) for q normalised, so the quaternion's norm direction maps to zero
// (TangentOfAmbient(x) AmbientOfTangent(x) = I).
Eigen::Matrix<double, 6, 7> TangentOfAmbient(const AmbientPose& pose);

// A station's residual through a physical group in report form (where the model's inverse does not
// resolve its report, fit/fit_engine.cc BuildProblem) is the report's misfit, carried to the pose
// by the free-space chord: r ~ A r_pose to first order, where r_pose is the residual of the pose the
// model's inverse finds from the report (what a calibration is judged by) and A = dy/dx, the
// model's report per true pose (whitened, on the reference's tangent). Given the corrected pose
// the residual is computed from and its derivative by the reference the group was evaluated
// toward (EvaluateChain's d_output_d_target; zero without a group), returns A = D D_pose^-1:
// D = d r / d reference and D_pose its direct part, r_pose's only dependence on the reference.
// Null if not finite or D_pose is singular.
std::optional<Matrix6> ReportPerPose(const AmbientPose& pose,
                                     const Eigen::Matrix<double, 7, 7>& d_pose_d_target,
                                     const Rigid3d& reference, double sigma_p, double sigma_o);

// The metric K a station's residual is multiplied by (docs/model-file.md,
// noise.amplification_threshold): K = A^-1, so the fit weighs the station's pose error, as the
// paper's Table 1 and the runtime judge a calibration, not its report's; but along each direction
// in which A^-1 amplifies the report noise by s_i > threshold (A^-1 = U S V^T), by the threshold
// only: K = U diag(min(s_i, threshold)) V^T. Where the model's inverse has no root (A singular)
// the pose error is not defined and the station weighs its report's misfit. `gain` is the largest
// s_i (NaN if A is null, infinite if singular).
struct PoseMetric {
  std::optional<Matrix6> k;  // null: A could not be evaluated (the residual is left unweighted)
  double gain = 1.0;
};
PoseMetric PoseMetricOf(const std::optional<Matrix6>& a, double threshold);

}  // namespace trackcal::fit
