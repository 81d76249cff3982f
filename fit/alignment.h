// Closed-form rigid alignment of point sets (the starting points of the iterative estimators).

#pragma once

#include <Eigen/Core>
#include <vector>

#include "core/pose.h"

namespace trackcal::fit {

// The rotation closest to m in the Frobenius norm (det = +1), via the SVD m = U S V^T.
Eigen::Matrix3d NearestRotation(const Eigen::Matrix3d& m);

// to_from_from minimising sum_i w_i |to_i - (R from_i + t)|^2 (Horn / Kabsch, no scale). Weights
// default to one. Throws std::invalid_argument if sizes differ or fewer than one point is given;
// degenerate configurations (fewer than 3 non-collinear points) give one of the minimisers.
Rigid3d AlignPoints(const std::vector<Eigen::Vector3d>& from,
                    const std::vector<Eigen::Vector3d>& to,
                    const std::vector<double>& weights = {});

}  // namespace trackcal::fit
