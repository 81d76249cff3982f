#include "fit/terms_physical_standalone.h"

#include <ceres/ceres.h>
#include <ceres/jet.h>

#include <Eigen/LU>
#include <algorithm>
#include <cmath>
#include <stdexcept>

namespace trackcal::fit {

namespace {

// Free parameters of all terms, one Euclidean block (small changes of the sensor-offset rotation
// and plane normals use local charts around their initial values, so no manifold is needed).
constexpr int kMaxParameters = 48;
constexpr int kSlots = 6 + kMaxParameters;  // pose tangent (dp, dw), then the parameters
using Jet = ceres::Jet<double, kSlots>;

// Where each free term sits in the parameter vector theta (-1: fixed).
struct Layout {
  int sensor_offset = -1;    // omega (3, rotation chart), translation (3)
  int receiver_gain = -1;    // G row-major (9)
  int near_field = -1;       // octupole per coil (3)
  std::vector<int> planes;   // per plane: distance (1), normal chart (2), attenuation (1)
  std::vector<int> objects;  // per object: location (3), polarisability (1)
  int size = 0;
  std::vector<std::string> names;
};

// Orthonormal tangent basis of the sphere at n.
void TangentBasis(const Eigen::Vector3d& n, Eigen::Vector3d* t1, Eigen::Vector3d* t2) {
  const Eigen::Vector3d a =
      std::abs(n.x()) < 0.9 ? Eigen::Vector3d::UnitX() : Eigen::Vector3d::UnitY();
  *t1 = n.cross(a).normalized();
  *t2 = n.cross(*t1);
}

// The physical model at parameters theta (T: double or Jet), around the fixed base model.
template <typename T>
struct Model {
  const PhysicalCorrection* base;
  const Layout* layout;
  const T* theta;

  Eigen::Quaternion<T> OffsetRotation() const {
    const Eigen::Quaterniond q0 = base->receiver_from_body() ? base->receiver_from_body()->rotation
                                                             : Eigen::Quaterniond::Identity();
    if (layout->sensor_offset < 0) return q0.cast<T>();
    const T* w = theta + layout->sensor_offset;
    // Chart q0 * normalize(1, w / 2): smooth at w = 0, first order equal to Exp(w).
    Eigen::Quaternion<T> dq = QuaternionFromWxyz<T>(T(1), w[0] / T(2), w[1] / T(2), w[2] / T(2));
    dq.normalize();
    return q0.cast<T>() * dq;
  }
  Vector3<T> OffsetTranslation() const {
    if (layout->sensor_offset < 0) {
      return base->receiver_from_body()
                 ? Vector3<T>(base->receiver_from_body()->translation.cast<T>())
                 : Vector3<T>::Zero();
    }
    const T* t = theta + layout->sensor_offset + 3;
    return Vector3<T>(t[0], t[1], t[2]);
  }
  Matrix3<T> Gain() const {
    if (layout->receiver_gain < 0) return base->receiver_gain_matrix().cast<T>();
    Matrix3<T> g;
    for (int r = 0; r < 3; ++r)
      for (int c = 0; c < 3; ++c) g(r, c) = theta[layout->receiver_gain + 3 * r + c];
    return g;
  }
  Matrix3<T> Field(const Vector3<T>& p) const {
    const FieldModel& f = base->field();
    const T k(f.field_constant);
    Vector3<T> octupole = f.transmitter_octupole_m2.cast<T>();
    if (layout->near_field >= 0) {
      const T* o = theta + layout->near_field;
      octupole = Vector3<T>(o[0], o[1], o[2]);
    }
    Matrix3<T> b = TransmitterField<T>(k, octupole, p);
    for (size_t i = 0; i < f.planes.size(); ++i) {
      const ConductingPlane& plane = f.planes[i];
      if (layout->planes[i] < 0) {
        b += PlaneImageField<T>(k, plane.point_in_transmitter.cast<T>(),
                                plane.normal_in_transmitter.cast<T>(), T(plane.attenuation), p);
        continue;
      }
      const T* x = theta + layout->planes[i];
      Eigen::Vector3d t1, t2;
      const Eigen::Vector3d n0 = plane.normal_in_transmitter.normalized();
      TangentBasis(n0, &t1, &t2);
      const Vector3<T> n = (n0.cast<T>() + t1.cast<T>() * x[1] + t2.cast<T>() * x[2]).normalized();
      b += PlaneImageField<T>(k, Vector3<T>(n * x[0]), n, x[3], p);
    }
    for (size_t i = 0; i < f.objects.size(); ++i) {
      const InducedDipole& object = f.objects[i];
      if (layout->objects[i] < 0) {
        b += InducedDipoleField<T>(k, object.location_in_transmitter.cast<T>(),
                                   T(object.polarisability_m3), p);
        continue;
      }
      const T* x = theta + layout->objects[i];
      b += InducedDipoleField<T>(k, Vector3<T>(x[0], x[1], x[2]), x[3], p);
    }
    return b;
  }
};

Layout MakeLayout(const PhysicalCorrection& initial, const PhysicalFitOptions& options) {
  Layout l;
  const auto add = [&l](const std::string& prefix, const std::vector<std::string>& coords) {
    const int start = l.size;
    for (const std::string& c : coords) l.names.push_back(prefix + c);
    l.size += static_cast<int>(coords.size());
    return start;
  };
  if (options.sensor_offset) {
    l.sensor_offset = add("sensor_offset.", {"rotation.x", "rotation.y", "rotation.z",
                                             "translation.x", "translation.y", "translation.z"});
  }
  if (options.receiver_gain) {
    std::vector<std::string> c;
    for (int r = 0; r < 3; ++r)
      for (int k = 0; k < 3; ++k) c.push_back("G" + std::to_string(r) + std::to_string(k));
    l.receiver_gain = add("receiver_gain.", c);
  }
  if (options.near_field) l.near_field = add("near_field.octupole_m2.", {"x", "y", "z"});
  l.planes.assign(initial.field().planes.size(), -1);
  for (int i : options.free_planes) {
    l.planes[i] = add("planes[" + std::to_string(i) + "].",
                      {"distance", "normal_chart.a", "normal_chart.b", "attenuation"});
  }
  l.objects.assign(initial.field().objects.size(), -1);
  for (int i : options.free_objects) {
    l.objects[i] = add("objects[" + std::to_string(i) + "].",
                       {"location_in_transmitter.x", "location_in_transmitter.y",
                        "location_in_transmitter.z", "polarisability_m3"});
  }
  return l;
}

std::vector<double> InitialTheta(const PhysicalCorrection& initial, const Layout& l) {
  std::vector<double> theta(l.size, 0.0);
  if (l.sensor_offset >= 0 && initial.receiver_from_body()) {
    for (int i = 0; i < 3; ++i)
      theta[l.sensor_offset + 3 + i] = initial.receiver_from_body()->translation(i);
  }
  if (l.receiver_gain >= 0) {
    for (int r = 0; r < 3; ++r)
      for (int c = 0; c < 3; ++c)
        theta[l.receiver_gain + 3 * r + c] = initial.receiver_gain_matrix()(r, c);
  }
  if (l.near_field >= 0) {
    for (int i = 0; i < 3; ++i)
      theta[l.near_field + i] = initial.field().transmitter_octupole_m2(i);
  }
  for (size_t i = 0; i < l.planes.size(); ++i) {
    if (l.planes[i] < 0) continue;
    const ConductingPlane& p = initial.field().planes[i];
    theta[l.planes[i]] = p.point_in_transmitter.dot(p.normal_in_transmitter.normalized());
    theta[l.planes[i] + 3] = p.attenuation;
  }
  for (size_t i = 0; i < l.objects.size(); ++i) {
    if (l.objects[i] < 0) continue;
    const InducedDipole& o = initial.field().objects[i];
    for (int k = 0; k < 3; ++k) theta[l.objects[i] + k] = o.location_in_transmitter(k);
    theta[l.objects[i] + 3] = o.polarisability_m3;
  }
  return theta;
}

// The correction at theta; throws std::invalid_argument if theta leaves the model's domain.
PhysicalCorrection Unpack(const PhysicalCorrection& base, const Layout& l, const double* theta) {
  const Model<double> m{&base, &l, theta};
  FieldModel field = base.field();
  if (l.near_field >= 0) field.transmitter_octupole_m2 = Eigen::Vector3d(theta + l.near_field);
  for (size_t i = 0; i < l.planes.size(); ++i) {
    if (l.planes[i] < 0) continue;
    const double* x = theta + l.planes[i];
    Eigen::Vector3d t1, t2;
    const Eigen::Vector3d n0 = field.planes[i].normal_in_transmitter.normalized();
    TangentBasis(n0, &t1, &t2);
    const Eigen::Vector3d n = (n0 + x[1] * t1 + x[2] * t2).normalized();
    field.planes[i].normal_in_transmitter = n;
    field.planes[i].point_in_transmitter = x[0] * n;
    field.planes[i].attenuation = x[3];
  }
  for (size_t i = 0; i < l.objects.size(); ++i) {
    if (l.objects[i] < 0) continue;
    const double* x = theta + l.objects[i];
    field.objects[i].location_in_transmitter = Eigen::Vector3d(x[0], x[1], x[2]);
    field.objects[i].polarisability_m3 = x[3];
  }
  std::optional<Rigid3d> offset = base.receiver_from_body();
  if (l.sensor_offset >= 0) offset = Rigid3d(m.OffsetRotation(), m.OffsetTranslation());
  // The fit may start far from the truth, where Newton needs more steps than at run time.
  PhysicalCorrectionOptions options = base.options();
  options.max_iterations = std::max(options.max_iterations, 50);
  return PhysicalCorrection(std::move(field), m.Gain(), offset, options);
}

// Pose x (+ tangent slots 0..5) as Jets: position p + dp, rotation q * normalize(1, dw / 2).
void PerturbedPose(const Rigid3d& x, Vector3<Jet>* p, Eigen::Quaternion<Jet>* q) {
  for (int i = 0; i < 3; ++i) (*p)(i) = Jet(x.translation(i), i);
  Eigen::Quaternion<Jet> dq = QuaternionFromWxyz<Jet>(Jet(1.0), Jet(0.0, 3) / Jet(2),
                                                      Jet(0.0, 4) / Jet(2), Jet(0.0, 5) / Jet(2));
  dq.normalize();
  *q = x.rotation.cast<Jet>() * dq;
}

// One station's whitened pose residual through the implicit inverse.
class ImplicitPoseCost : public ceres::CostFunction {
 public:
  ImplicitPoseCost(const PhysicalCorrection* base, const Layout* layout, PhysicalObservation obs,
                   double position_sigma, double orientation_sigma)
      : base_(base),
        layout_(layout),
        obs_(obs),
        position_sigma_(position_sigma),
        orientation_sigma_(orientation_sigma) {
    set_num_residuals(6);
    mutable_parameter_block_sizes()->push_back(layout->size);
    // Free-space signal of the report and its Jacobian (the tracker's normal equations).
    Vector3<Jet> p;
    Eigen::Quaternion<Jet> q;
    PerturbedPose(obs_.reported, &p, &q);
    const Matrix3<Jet> s = q.toRotationMatrix().transpose() *
                           (Jet(base->field().field_constant) * DipoleCoupling<Jet>(p));
    for (int c = 0; c < 3; ++c) {
      for (int r = 0; r < 3; ++r) {
        s_free_(3 * c + r) = s(r, c).a;
        j_free_.row(3 * c + r) = s(r, c).v.head<6>().transpose();
      }
    }
  }

  bool Evaluate(double const* const* parameters, double* residuals,
                double** jacobians) const override {
    const double* theta = parameters[0];
    const int n = layout_->size;
    Rigid3d x;
    try {
      const PhysicalCorrection model = Unpack(*base_, *layout_, theta);
      // A non-converged inverse still yields the best iterate, and its residual is what the
      // model explains there; only a non-finite one stops the step.
      model.InvertReport(obs_.reported, &x);
      if (!x.translation.allFinite() || !x.rotation.coeffs().allFinite()) return false;
    } catch (const std::invalid_argument&) {
      return false;  // parameters left the model's domain: Ceres shortens the step
    }
    // Jets: slots 0..5 pose tangent at x, 6.. theta.
    std::vector<Jet> theta_jet(n);
    for (int i = 0; i < n; ++i) theta_jet[i] = Jet(theta[i], 6 + i);
    const Model<Jet> model{base_, layout_, theta_jet.data()};
    Vector3<Jet> p;
    Eigen::Quaternion<Jet> q;
    PerturbedPose(x, &p, &q);
    const Matrix3<Jet> s = model.Gain() * (q.toRotationMatrix().transpose() * model.Field(p));
    Eigen::Matrix<double, 9, kSlots> j_s;
    for (int c = 0; c < 3; ++c)
      for (int r = 0; r < 3; ++r) j_s.row(3 * c + r) = s(r, c).v.transpose();
    const Eigen::Matrix<double, 6, kSlots> j_g = j_free_.transpose() * j_s;
    const Eigen::Matrix<double, 6, 6> g_x = j_g.leftCols<6>();

    // Corrected body pose and residual.
    const Eigen::Quaternion<Jet> q_body = q * model.OffsetRotation();
    const Vector3<Jet> p_body = p + q * model.OffsetTranslation();
    Eigen::Matrix<Jet, 6, 1> r;
    r.head<3>() = (p_body - obs_.reference.translation.cast<Jet>()) / Jet(position_sigma_);
    r.tail<3>() = -OrientationErrorVector<Jet>(obs_.reference.rotation.cast<Jet>(), q_body) /
                  Jet(orientation_sigma_);
    for (int i = 0; i < 6; ++i) residuals[i] = r(i).a;
    if (jacobians != nullptr && jacobians[0] != nullptr) {
      Eigen::Matrix<double, 6, kSlots> j_r;
      for (int i = 0; i < 6; ++i) j_r.row(i) = r(i).v.transpose();
      const Eigen::PartialPivLU<Eigen::Matrix<double, 6, 6>> lu(g_x);
      // Implicit function theorem: dx/dtheta = -(dg/dx)^-1 dg/dtheta.
      const Eigen::MatrixXd dx_dtheta = -lu.solve(j_g.middleCols(6, n));
      const Eigen::MatrixXd j = j_r.middleCols(6, n) + j_r.leftCols<6>() * dx_dtheta;
      Eigen::Map<Eigen::Matrix<double, 6, Eigen::Dynamic, Eigen::RowMajor>>(jacobians[0], 6, n) = j;
    }
    return true;
  }

 private:
  const PhysicalCorrection* base_;
  const Layout* layout_;
  PhysicalObservation obs_;
  double position_sigma_;
  double orientation_sigma_;
  Eigen::Matrix<double, 9, 1> s_free_;
  Eigen::Matrix<double, 9, 6> j_free_;
};

}  // namespace

void PhysicalFitOptions::Check(const PhysicalCorrection& initial) const {
  const auto fail = [](const std::string& m) { throw std::invalid_argument("physical fit: " + m); };
  for (int i : free_objects) {
    if (i < 0 || i >= static_cast<int>(initial.field().objects.size()))
      fail("free_objects: index out of range");
  }
  for (int i : free_planes) {
    if (i < 0 || i >= static_cast<int>(initial.field().planes.size()))
      fail("free_planes: index out of range");
  }
  if (!(position_sigma_m > 0)) fail("position_sigma_m must be positive");
  if (!(orientation_sigma_rad > 0)) fail("orientation_sigma_rad must be positive");
  if (!(robust_loss_sigmas >= 0)) fail("robust_loss_sigmas must be >= 0");
  if (max_iterations < 1) fail("max_iterations must be >= 1");
}

PhysicalFitResult FitPhysicalModel(const PhysicalCorrection& initial,
                                   const std::vector<PhysicalObservation>& observations,
                                   const PhysicalFitOptions& options) {
  options.Check(initial);
  const Layout layout = MakeLayout(initial, options);
  if (layout.size == 0) throw std::invalid_argument("physical fit: no free parameters");
  if (layout.size > kMaxParameters) {
    throw std::invalid_argument("physical fit: more than " + std::to_string(kMaxParameters) +
                                " free parameters");
  }
  std::vector<double> theta = InitialTheta(initial, layout);
  ceres::Problem problem;
  for (const PhysicalObservation& obs : observations) {
    ceres::LossFunction* loss = options.robust_loss_sigmas > 0
                                    ? new ceres::CauchyLoss(options.robust_loss_sigmas)
                                    : nullptr;
    const double position_sigma =
        obs.position_sigma_m > 0 ? obs.position_sigma_m : options.position_sigma_m;
    const double orientation_sigma =
        obs.orientation_sigma_rad > 0 ? obs.orientation_sigma_rad : options.orientation_sigma_rad;
    problem.AddResidualBlock(
        new ImplicitPoseCost(&initial, &layout, obs, position_sigma, orientation_sigma), loss,
        theta.data());
  }
  for (size_t i = 0; i < layout.planes.size(); ++i) {
    if (layout.planes[i] < 0) continue;
    problem.SetParameterLowerBound(theta.data(), layout.planes[i] + 3, -1.0);
    problem.SetParameterUpperBound(theta.data(), layout.planes[i] + 3, 1.0);
  }
  ceres::Solver::Options solver_options;
  solver_options.max_num_iterations = options.max_iterations;
  solver_options.linear_solver_type = ceres::DENSE_QR;
  solver_options.function_tolerance = 1e-10;
  ceres::Solver::Summary summary;
  ceres::Solve(solver_options, &problem, &summary);

  PhysicalFitResult result{
      summary.IsSolutionUsable() && summary.termination_type == ceres::CONVERGENCE,
      Unpack(initial, layout, theta.data()),
      layout.names,
      Eigen::Map<Eigen::VectorXd>(theta.data(), layout.size),
      Eigen::VectorXd::Constant(layout.size, std::nan("")),
      {},
      summary.final_cost,
      summary.BriefReport()};
  CovarianceBlock block;
  block.values = theta.data();
  block.name = "physical";
  block.coordinate_names = layout.names;
  const CovarianceResult cov = ComputeCovariance(&problem, {block});
  if (cov.success) result.stddev = cov.stddev;
  result.flags = cov.flags;
  return result;
}

}  // namespace trackcal::fit
