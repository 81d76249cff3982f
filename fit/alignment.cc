#include "fit/alignment.h"

#include <Eigen/SVD>
#include <stdexcept>

namespace trackcal::fit {

Eigen::Matrix3d NearestRotation(const Eigen::Matrix3d& m) {
  Eigen::JacobiSVD<Eigen::Matrix3d> svd(m, Eigen::ComputeFullU | Eigen::ComputeFullV);
  Eigen::Matrix3d d = Eigen::Matrix3d::Identity();
  if ((svd.matrixU() * svd.matrixV().transpose()).determinant() < 0.0) d(2, 2) = -1.0;
  return svd.matrixU() * d * svd.matrixV().transpose();
}

Rigid3d AlignPoints(const std::vector<Eigen::Vector3d>& from,
                    const std::vector<Eigen::Vector3d>& to, const std::vector<double>& weights) {
  if (from.size() != to.size() || from.empty() ||
      (!weights.empty() && weights.size() != from.size())) {
    throw std::invalid_argument("AlignPoints: need equally many (>= 1) points and weights");
  }
  double total = 0.0;
  Eigen::Vector3d mean_from = Eigen::Vector3d::Zero(), mean_to = Eigen::Vector3d::Zero();
  for (std::size_t i = 0; i < from.size(); ++i) {
    const double w = weights.empty() ? 1.0 : weights[i];
    if (!(w >= 0.0)) throw std::invalid_argument("AlignPoints: weights must be >= 0");
    total += w;
    mean_from += w * from[i];
    mean_to += w * to[i];
  }
  if (!(total > 0.0)) throw std::invalid_argument("AlignPoints: weights sum to zero");
  mean_from /= total;
  mean_to /= total;
  Eigen::Matrix3d cross = Eigen::Matrix3d::Zero();
  for (std::size_t i = 0; i < from.size(); ++i) {
    const double w = weights.empty() ? 1.0 : weights[i];
    cross += w * (to[i] - mean_to) * (from[i] - mean_from).transpose();
  }
  // R maximising trace(R^T cross) is the rotation nearest to cross.
  const Eigen::Matrix3d rotation = NearestRotation(cross);
  const Eigen::Quaterniond q = Eigen::Quaterniond(rotation).normalized();
  return Rigid3d(q, mean_to - q * mean_from);
}

}  // namespace trackcal::fit
