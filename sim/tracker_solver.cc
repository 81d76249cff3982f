#include "sim/tracker_solver.h"

#include <ceres/jet.h>

#include <Eigen/Eigenvalues>
#include <Eigen/SVD>
#include <cmath>
#include <stdexcept>

#include "sim/field.h"

namespace trackcal::sim {

void TrackerSolverOptions::Check() const {
  if (!(std::isfinite(field_constant) && field_constant > 0)) {
    throw std::invalid_argument("tracker solver: field_constant must be positive");
  }
  if (!hemisphere_in_transmitter.allFinite() || hemisphere_in_transmitter.norm() < 1e-12) {
    throw std::invalid_argument("tracker solver: hemisphere must be a non-zero vector");
  }
  if (max_iterations < 0) throw std::invalid_argument("tracker solver: max_iterations < 0");
  if (!(step_tolerance > 0)) throw std::invalid_argument("tracker solver: step_tolerance <= 0");
}

namespace {

using Matrix96 = Eigen::Matrix<double, 9, 6>;
using Vector9 = Eigen::Matrix<double, 9, 1>;
using Jet6 = ceres::Jet<double, 6>;

Eigen::Matrix3d NearestRotation(const Eigen::Matrix3d& a) {
  Eigen::JacobiSVD<Eigen::Matrix3d> svd(a, Eigen::ComputeFullU | Eigen::ComputeFullV);
  Eigen::Matrix3d d = Eigen::Matrix3d::Identity();
  d(2, 2) = (svd.matrixU() * svd.matrixV().transpose()).determinant() < 0 ? -1.0 : 1.0;
  return svd.matrixU() * d * svd.matrixV().transpose();
}

// Residual S - R^T k D(p) and its Jacobian with respect to (dp, dtheta), R -> R Exp(dtheta).
void Linearise(const Eigen::Matrix3d& signal, double k, const Eigen::Vector3d& p,
               const Eigen::Matrix3d& rotation, Vector9* residual, Matrix96* jacobian) {
  Vector3<Jet6> pj;
  Vector3<Jet6> wj;
  for (int i = 0; i < 3; ++i) {
    pj(i) = Jet6(p(i), i);
    wj(i) = Jet6(0.0, 3 + i);
  }
  // (R Exp(w))^T = Exp(-w) R^T; first order in w is exact for the Jacobian at w = 0.
  Matrix3<Jet6> exp_minus_w = Matrix3<Jet6>::Identity();
  exp_minus_w(0, 1) = wj(2);
  exp_minus_w(0, 2) = -wj(1);
  exp_minus_w(1, 0) = -wj(2);
  exp_minus_w(1, 2) = wj(0);
  exp_minus_w(2, 0) = wj(1);
  exp_minus_w(2, 1) = -wj(0);
  const Matrix3<Jet6> model =
      exp_minus_w * (rotation.transpose().cast<Jet6>() * (Jet6(k) * DipoleCoupling<Jet6>(pj)));
  for (int c = 0; c < 3; ++c) {
    for (int r = 0; r < 3; ++r) {
      const int i = 3 * c + r;
      (*residual)(i) = signal(r, c) - model(r, c).a;
      jacobian->row(i) = -model(r, c).v.transpose();
    }
  }
}

double Cost(const Eigen::Matrix3d& signal, double k, const Eigen::Vector3d& p,
            const Eigen::Matrix3d& rotation) {
  return (signal - rotation.transpose() * (k * DipoleCoupling<double>(p))).squaredNorm();
}

Rigid3d MakePose(const Eigen::Matrix3d& rotation, const Eigen::Vector3d& p) {
  Eigen::Quaterniond q(rotation);
  q.normalize();
  return Rigid3d(q, p);
}

}  // namespace

TrackerSolution SolveFreeSpacePose(const Eigen::Matrix3d& signal,
                                   const TrackerSolverOptions& options) {
  options.Check();
  TrackerSolution solution;
  const double k = options.field_constant;
  const Eigen::Vector3d h = options.hemisphere_in_transmitter.normalized();
  const Eigen::Matrix3d sts = signal.transpose() * signal;
  const double trace = sts.trace();
  if (!signal.allFinite() || !(trace > 0)) return solution;

  // Closed form.
  const Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> eig(sts);
  Eigen::Vector3d u = eig.eigenvectors().col(2);  // eigenvalues ascend: the 4 k^2 / r^6 one
  if (u.dot(h) < 0) u = -u;
  const double r = std::pow(6.0 * k * k / trace, 1.0 / 6.0);
  Eigen::Matrix3d inverse_shape = 1.5 * u * u.transpose();
  inverse_shape.diagonal().array() -= 1.0;
  Eigen::Matrix3d rotation = NearestRotation((signal * ((r * r * r / k) * inverse_shape)).transpose());
  Eigen::Vector3d p = r * u;
  solution.closed_form = MakePose(rotation, p);

  // Levenberg-Marquardt refinement.
  double cost = Cost(signal, k, p, rotation);
  double lambda = 1e-6;
  Vector9 residual;
  Matrix96 jacobian;
  for (int it = 0; it < options.max_iterations; ++it) {
    solution.iterations = it + 1;
    if (cost == 0.0) {
      solution.converged = true;
      break;
    }
    Linearise(signal, k, p, rotation, &residual, &jacobian);
    const Eigen::Matrix<double, 6, 6> jtj = jacobian.transpose() * jacobian;
    const Eigen::Matrix<double, 6, 1> jtr = jacobian.transpose() * residual;
    bool improved = false;
    Eigen::Matrix<double, 6, 1> step = Eigen::Matrix<double, 6, 1>::Zero();
    for (int attempt = 0; attempt < 30 && !improved; ++attempt) {
      Eigen::Matrix<double, 6, 6> a = jtj;
      a.diagonal() += lambda * jtj.diagonal();
      step = -a.ldlt().solve(jtr);
      const Eigen::Vector3d p_new = p + step.head<3>();
      const Eigen::Vector3d w = step.tail<3>();
      const Eigen::Matrix3d r_new =
          rotation * Eigen::AngleAxisd(w.norm(), w.norm() > 0 ? w.normalized()
                                                              : Eigen::Vector3d::UnitX())
                         .toRotationMatrix();
      const double cost_new = Cost(signal, k, p_new, r_new);
      if (cost_new <= cost) {
        improved = true;
        p = p_new;
        rotation = NearestRotation(r_new);
        cost = cost_new;
        lambda = std::max(lambda * 0.1, 1e-12);
      } else {
        lambda *= 10.0;
      }
    }
    if (!improved || step.norm() < options.step_tolerance * std::max(1.0, p.norm())) {
      solution.converged = true;
      break;
    }
  }
  // D(-p) = D(p): the refined position may be flipped into the chosen hemisphere freely.
  if (p.dot(h) < 0) p = -p;
  solution.transmitter_from_receiver = MakePose(rotation, p);
  solution.residual_norm = std::sqrt(cost);
  return solution;
}

}  // namespace trackcal::sim
