#include "sim/tracker_solver.h"

#include <ceres/jet.h>

#include <Eigen/Eigenvalues>
#include <Eigen/SVD>
#include <cmath>
#include <limits>
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

Rigid3d MakePose(const Eigen::Matrix3d& rotation, const Eigen::Vector3d& p) {
  Eigen::Quaterniond q(rotation);
  q.normalize();
  return Rigid3d(q, p);
}

// Levenberg-Marquardt on |S - G R^T B(p)|^2 over (p, R), R -> R Exp(w). `field` is a callable
// returning B(p) for double and Jet6 positions.
template <typename FieldFn>
void Refine(const Eigen::Matrix3d& signal, const Eigen::Matrix3d& gain, const FieldFn& field,
            int max_iterations, double step_tolerance, Eigen::Vector3d* p_io,
            Eigen::Matrix3d* rotation_io, TrackerSolution* solution) {
  Eigen::Vector3d p = *p_io;
  Eigen::Matrix3d rotation = *rotation_io;
  const auto cost_at = [&](const Eigen::Vector3d& pos, const Eigen::Matrix3d& rot) {
    return (signal - gain * rot.transpose() * field(pos)).squaredNorm();
  };
  double cost = cost_at(p, rotation);
  double lambda = 1e-6;
  Vector9 residual;
  Matrix96 jacobian;
  const Matrix3<Jet6> gain_jet = gain.cast<Jet6>();
  solution->converged = false;
  double previous_step_norm = std::numeric_limits<double>::infinity();
  for (int it = 0; it < max_iterations; ++it) {
    solution->iterations = it + 1;
    if (cost == 0.0) {
      solution->converged = true;
      break;
    }
    // Residual and Jacobian at w = 0; (R Exp(w))^T = Exp(-w) R^T, first order in w suffices.
    Vector3<Jet6> pj;
    Vector3<Jet6> wj;
    for (int i = 0; i < 3; ++i) {
      pj(i) = Jet6(p(i), i);
      wj(i) = Jet6(0.0, 3 + i);
    }
    Matrix3<Jet6> exp_minus_w = Matrix3<Jet6>::Identity();
    exp_minus_w(0, 1) = wj(2);
    exp_minus_w(0, 2) = -wj(1);
    exp_minus_w(1, 0) = -wj(2);
    exp_minus_w(1, 2) = wj(0);
    exp_minus_w(2, 0) = wj(1);
    exp_minus_w(2, 1) = -wj(0);
    const Matrix3<Jet6> model =
        gain_jet * (exp_minus_w * (rotation.transpose().cast<Jet6>() * field(pj)));
    for (int c = 0; c < 3; ++c) {
      for (int r = 0; r < 3; ++r) {
        const int i = 3 * c + r;
        residual(i) = signal(r, c) - model(r, c).a;
        jacobian.row(i) = -model(r, c).v.transpose();
      }
    }
    const Eigen::Matrix<double, 6, 6> jtj = jacobian.transpose() * jacobian;
    const Eigen::Matrix<double, 6, 1> jtr = jacobian.transpose() * residual;
    bool improved = false;
    Eigen::Matrix<double, 6, 1> step = Eigen::Matrix<double, 6, 1>::Zero();
    const double scale = std::max(1.0, p.norm());
    for (int attempt = 0; attempt < 30 && !improved; ++attempt) {
      Eigen::Matrix<double, 6, 6> a = jtj;
      a.diagonal() += lambda * jtj.diagonal();
      step = -a.ldlt().solve(jtr);
      const Eigen::Vector3d p_new = p + step.head<3>();
      const Eigen::Vector3d w = step.tail<3>();
      const double angle = w.norm();
      const Eigen::Matrix3d r_new =
          angle > 0
              ? NearestRotation(rotation * Eigen::AngleAxisd(angle, w / angle).toRotationMatrix())
              : rotation;
      const double cost_new = cost_at(p_new, r_new);
      // Near the minimum the cost cannot resolve steps below sqrt(eps) of the residual; tiny
      // Gauss-Newton steps are taken on the gradient's word so the pose converges to rounding.
      const bool tiny = step.norm() < 1e-7 * scale;
      if (cost_new <= cost || tiny) {
        improved = true;
        p = p_new;
        rotation = r_new;
        cost = cost_new;
        lambda = std::max(lambda * 0.1, 1e-12);
      } else {
        lambda *= 10.0;
      }
    }
    const double step_norm = step.norm();
    // Converged: a step below tolerance, no decrease even with heavy damping, or tiny steps that
    // stopped shrinking (rounding noise).
    if (!improved || step_norm < step_tolerance * scale ||
        (step_norm < 1e-7 * scale && step_norm > 0.5 * previous_step_norm)) {
      solution->converged = true;
      break;
    }
    previous_step_norm = step_norm;
  }
  *p_io = p;
  *rotation_io = rotation;
  solution->residual_norm = std::sqrt(cost);
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
  Eigen::Matrix3d rotation =
      NearestRotation((signal * ((r * r * r / k) * inverse_shape)).transpose());
  Eigen::Vector3d p = r * u;
  solution.closed_form = MakePose(rotation, p);

  const auto free_space = [k](const auto& x) {
    using T = typename std::decay_t<decltype(x)>::Scalar;
    return Matrix3<T>(T(k) * DipoleCoupling<T>(x));
  };
  Refine(signal, Eigen::Matrix3d::Identity(), free_space, options.max_iterations,
         options.step_tolerance, &p, &rotation, &solution);
  // D(-p) = D(p): the refined position may be flipped into the chosen hemisphere freely.
  if (p.dot(h) < 0) p = -p;
  solution.transmitter_from_receiver = MakePose(rotation, p);
  return solution;
}

TrackerSolution SolvePoseInField(const Eigen::Matrix3d& signal, const FieldModel& field,
                                 const Eigen::Matrix3d& receiver_gain_matrix,
                                 const Rigid3d& initial, const TrackerSolverOptions& options) {
  options.Check();
  field.Check();
  TrackerSolution solution;
  solution.closed_form = initial;
  if (!signal.allFinite() || !initial.translation.allFinite()) return solution;
  Eigen::Vector3d p = initial.translation;
  Eigen::Matrix3d rotation = initial.rotation.normalized().toRotationMatrix();
  const auto model_field = [&field](const auto& x) {
    using T = typename std::decay_t<decltype(x)>::Scalar;
    return field.Field<T>(x);
  };
  Refine(signal, receiver_gain_matrix, model_field, options.max_iterations, options.step_tolerance,
         &p, &rotation, &solution);
  solution.transmitter_from_receiver = MakePose(rotation, p);
  return solution;
}

TrackerSolution InvertReportedPose(const Rigid3d& reported, const FieldModel& field,
                                   const Eigen::Matrix3d& receiver_gain_matrix,
                                   const TrackerSolverOptions& options, int max_iterations,
                                   double tolerance) {
  options.Check();
  field.Check();
  TrackerSolution solution;
  solution.closed_form = reported;
  Rigid3d x = reported;
  for (int it = 0; it < max_iterations; ++it) {
    solution.iterations = it + 1;
    const Eigen::Matrix3d s = SignalMatrix<double>(
        receiver_gain_matrix, x.rotation.toRotationMatrix(), field.Field<double>(x.translation));
    const TrackerSolution predicted = SolveFreeSpacePose(s, options);
    if (!predicted.converged) return solution;
    const Rigid3d& f = predicted.transmitter_from_receiver;
    const Eigen::Vector3d dp = reported.translation - f.translation;
    const Eigen::Quaterniond dq = (reported.rotation * f.rotation.conjugate()).normalized();
    x.translation += dp;
    x.rotation = (dq * x.rotation).normalized();
    solution.transmitter_from_receiver = x;
    solution.residual_norm = dp.norm() + RotationAngle(dq);
    if (dp.norm() < tolerance && RotationAngle(dq) < tolerance) {
      solution.converged = true;
      break;
    }
  }
  return solution;
}

}  // namespace trackcal::sim
