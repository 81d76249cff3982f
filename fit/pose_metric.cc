#include "fit/pose_metric.h"

#include <ceres/jet.h>

#include <Eigen/LU>
#include <Eigen/SVD>
#include <limits>

namespace trackcal::fit {

Eigen::Matrix<double, 7, 6> AmbientOfTangent(const AmbientPose& pose) {
  Eigen::Matrix<double, 7, 6> out = Eigen::Matrix<double, 7, 6>::Zero();
  out.topLeftCorner<3, 3>().setIdentity();
  const Eigen::Quaterniond q = QuaternionFromXyzwArray(pose.data() + 3).normalized();
  for (int k = 0; k < 3; ++k) {
    Eigen::Vector3d half = Eigen::Vector3d::Zero();
    half(k) = 0.5;
    const Eigen::Quaterniond dq = q * QuaternionFromXyzw(half.x(), half.y(), half.z(), 0.0);
    out.block<4, 1>(3, 3 + k) << dq.x(), dq.y(), dq.z(), dq.w();
  }
  return out;
}

Eigen::Matrix<double, 6, 7> TangentOfAmbient(const AmbientPose& pose) {
  Eigen::Matrix<double, 6, 7> out = Eigen::Matrix<double, 6, 7>::Zero();
  out.topLeftCorner<3, 3>().setIdentity();
  using Jet4 = ceres::Jet<double, 4>;
  Eigen::Quaternion<Jet4> q = QuaternionFromXyzw<Jet4>(Jet4(pose[3], 0), Jet4(pose[4], 1),
                                                       Jet4(pose[5], 2), Jet4(pose[6], 3));
  q.normalize();
  const Eigen::Quaterniond q0 =
      QuaternionFromXyzw(pose[3], pose[4], pose[5], pose[6]).normalized();
  const Eigen::Quaternion<Jet4> rel = q0.conjugate().cast<Jet4>() * q;
  for (int k = 0; k < 3; ++k) out.block<1, 4>(3 + k, 3) = (Jet4(2.0) * rel.vec()(k)).v.transpose();
  return out;
}

std::optional<Matrix6> ReportPerPose(const AmbientPose& pose,
                                     const Eigen::Matrix<double, 7, 7>& d_pose_d_target,
                                     const Rigid3d& reference, double sigma_p, double sigma_o) {
  // r by Jets over the pose (slots 0-6) and the reference's tangent (7-12, AmbientOfTangent's
  // chart).
  using Jet = ceres::Jet<double, 13>;
  Jet pose_jet[7], r[6];
  for (int k = 0; k < 7; ++k) pose_jet[k] = Jet(pose[k], k);
  Vector3<Jet> p_ref;
  for (int k = 0; k < 3; ++k) p_ref(k) = Jet(reference.translation(k), 7 + k);
  const Jet half0 = Jet(0.0, 10) / 2.0, half1 = Jet(0.0, 11) / 2.0, half2 = Jet(0.0, 12) / 2.0;
  const Eigen::Quaternion<Jet> q_ref =
      reference.rotation.normalized().cast<Jet>() *
      QuaternionFromXyzw<Jet>(half0, half1, half2, Jet(1.0)).normalized();
  StationResidual<Jet>(pose_jet, p_ref, q_ref, sigma_p, sigma_o, r);
  Eigen::Matrix<double, 6, 7> d_r;
  Matrix6 d_direct;
  for (int i = 0; i < 6; ++i) {
    d_r.row(i) = r[i].v.head<7>().transpose();
    d_direct.row(i) = r[i].v.tail<6>().transpose();
  }
  const Matrix6 d = d_direct + d_r * d_pose_d_target * AmbientOfTangent(ToAmbient(reference));
  const Eigen::FullPivLU<Matrix6> lu(d_direct.transpose());
  if (!lu.isInvertible()) return std::nullopt;
  const Matrix6 a = lu.solve(d.transpose()).transpose();  // D D_pose^-1
  if (!a.allFinite()) return std::nullopt;
  return a;
}

PoseMetric PoseMetricOf(const std::optional<Matrix6>& a, double threshold) {
  PoseMetric out;
  if (!a) {
    out.gain = std::numeric_limits<double>::quiet_NaN();
    return out;
  }
  // A^-1 = (U S V^T)^-1 = V S^-1 U^T: amplifications 1 / s, the largest from the smallest s.
  const Eigen::JacobiSVD<Matrix6> svd(*a, Eigen::ComputeFullU | Eigen::ComputeFullV);
  const Eigen::Matrix<double, 6, 1> s = svd.singularValues();  // decreasing
  out.gain = s(5) > 0.0 ? 1.0 / s(5) : std::numeric_limits<double>::infinity();
  Eigen::Matrix<double, 6, 1> k;
  for (int i = 0; i < 6; ++i) k(i) = s(i) * threshold > 1.0 ? 1.0 / s(i) : threshold;
  out.k = svd.matrixV() * k.asDiagonal() * svd.matrixU().transpose();
  return out;
}

}  // namespace trackcal::fit
