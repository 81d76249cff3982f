#include "core/physical_correction.h"

#include <ceres/jet.h>

#include <Eigen/Eigenvalues>
#include <Eigen/LU>
#include <algorithm>
#include <cmath>
#include <stdexcept>

namespace trackcal {

void PhysicalCorrectionOptions::Check() const {
  if (max_iterations < 1 || max_iterations > 100) {
    throw std::invalid_argument("physical correction: max_iterations must be in [1, 100], got " +
                                std::to_string(max_iterations));
  }
  if (!(std::isfinite(tolerance_m) && tolerance_m > 0)) {
    throw std::invalid_argument("physical correction: tolerance_m must be positive and finite");
  }
  // Below 0.9 so that the bound keeps the corrected position away from the transmitter.
  if (!(max_correction_fraction > 0 && max_correction_fraction <= 0.9)) {
    throw std::invalid_argument("physical correction: max_correction_fraction must be in (0, 0.9]");
  }
  if (!(max_noise_gain >= 1 && std::isfinite(max_noise_gain))) {
    throw std::invalid_argument("physical correction: max_noise_gain must be finite and >= 1");
  }
  if (!(fold_reach >= 0 && std::isfinite(fold_reach))) {
    throw std::invalid_argument("physical correction: fold_reach must be finite and >= 0");
  }
}

namespace {

using Jet6 = ceres::Jet<double, 6>;
using Jet3 = ceres::Jet<double, 3>;
using Matrix96 = Eigen::Matrix<double, 9, 6>;
using Vector9 = Eigen::Matrix<double, 9, 1>;
using Matrix6 = Eigen::Matrix<double, 6, 6>;
using Vector6 = Eigen::Matrix<double, 6, 1>;

// (R Exp(w))^T to first order in w, with w the Jet's derivative slots 3..5: Exp(-w) R^T.
Matrix3<Jet6> PerturbedRotationTranspose(const Eigen::Matrix3d& rotation) {
  Matrix3<Jet6> exp_minus_w = Matrix3<Jet6>::Identity();
  const Jet6 w0(0.0, 3), w1(0.0, 4), w2(0.0, 5);
  exp_minus_w(0, 1) = w2;
  exp_minus_w(0, 2) = -w1;
  exp_minus_w(1, 0) = -w2;
  exp_minus_w(1, 2) = w0;
  exp_minus_w(2, 0) = w1;
  exp_minus_w(2, 1) = -w0;
  return exp_minus_w * rotation.transpose().cast<Jet6>();
}

Vector3<Jet6> PerturbedPosition(const Eigen::Vector3d& p) {
  Vector3<Jet6> pj;
  for (int i = 0; i < 3; ++i) pj(i) = Jet6(p(i), i);
  return pj;
}

// Splits a Jet matrix into vec (column-major) value and 9 x 6 Jacobian.
void Unpack(const Matrix3<Jet6>& m, Vector9* value, Matrix96* jacobian) {
  for (int c = 0; c < 3; ++c) {
    for (int r = 0; r < 3; ++r) {
      (*value)(3 * c + r) = m(r, c).a;
      jacobian->row(3 * c + r) = m(r, c).v.transpose();
    }
  }
}

Eigen::Matrix3d ExpMap(const Eigen::Vector3d& w) {
  const double angle = w.norm();
  if (angle == 0.0) return Eigen::Matrix3d::Identity();
  return Eigen::AngleAxisd(angle, w / angle).toRotationMatrix();
}

nlohmann::json VectorJson(const Eigen::Vector3d& v) { return {v.x(), v.y(), v.z()}; }

}  // namespace

PhysicalCorrection::PhysicalCorrection(FieldModel field,
                                       const Eigen::Matrix3d& receiver_gain_matrix,
                                       std::optional<Rigid3d> receiver_from_body,
                                       PhysicalCorrectionOptions options)
    : field_(std::move(field)),
      receiver_gain_matrix_(receiver_gain_matrix),
      receiver_from_body_(receiver_from_body),
      options_(options) {
  field_.Check();
  options_.Check();
  Precompute();
  if (!receiver_gain_matrix_.allFinite() || !(receiver_gain_matrix_.determinant() > 1e-6)) {
    throw std::invalid_argument(
        "physical correction: receiver_gain_matrix must be finite with a positive determinant");
  }
  if (receiver_from_body_) {
    if (!receiver_from_body_->translation.allFinite() ||
        !receiver_from_body_->rotation.coeffs().allFinite() ||
        std::abs(receiver_from_body_->rotation.norm() - 1.0) > 1e-6) {
      throw std::invalid_argument(
          "physical correction: receiver_from_body must be finite with a unit quaternion");
    }
    receiver_from_body_->rotation.normalize();
  }
}

void PhysicalCorrection::Precompute() {
  const double k = field_.field_constant;
  sources_.clear();
  for (const ConductingPlane& plane : field_.planes) {
    // The image dipole of core/field.h PlaneImageField: at the mirror point, moments a (I - 2nn^T).
    const Eigen::Vector3d n = plane.normal_in_transmitter.normalized();
    Eigen::Matrix3d moment = -(2.0 * plane.attenuation) * (n * n.transpose());
    moment.diagonal().array() += plane.attenuation;
    sources_.push_back({(2.0 * plane.point_in_transmitter.dot(n)) * n, k * moment});
  }
  for (const InducedDipole& object : field_.objects) {
    // InducedDipoleField: moment polarisability * D(location) (the transmitter's field there).
    sources_.push_back(
        {object.location_in_transmitter,
         (k * object.polarisability_m3) * DipoleCoupling<double>(object.location_in_transmitter)});
  }
  has_octupole_ = !field_.transmitter_octupole_m2.isZero(0.0);
  object_radius_.clear();
  for (const InducedDipole& object : field_.objects) {
    // A sphere of radius a has polarisability a^3 (ferromagnetic) or -a^3 / 2 (conducting).
    const double alpha = object.polarisability_m3;
    object_radius_.push_back(std::cbrt(alpha >= 0.0 ? alpha : -2.0 * alpha));
  }
}

struct PhysicalCorrection::ReportFrame {
  Vector9 s_free;
  Eigen::Matrix<double, 6, 9> j_free_t;
  Matrix6 a;                    // J_y^T J_y: dg/dy at the report (g = A (y' - y) to first order)
  Eigen::Vector3d p_y;          // reported position
  double range = 1.0;           // |p_y| [m]
  double max_correction = 0.5;  // bound on |p - p_y| [m]
};

void PhysicalCorrection::NormalEquations(const ReportFrame& frame, const Eigen::Vector3d& p,
                                         const Eigen::Matrix3d& rotation, Vector6* g,
                                         Matrix6* h) const {
  // B(p) and dB/dp by a 3-slot Jet; the rotation's derivative is analytic:
  // d/dw_i [G Exp(-w) R^T B] = -G [e_i]x R^T B.
  const double k = field_.field_constant;
  Vector3<Jet3> pj;
  for (int i = 0; i < 3; ++i) pj(i) = Jet3(p(i), i);
  Matrix3<Jet3> b =
      has_octupole_
          ? TransmitterField<Jet3>(Jet3(k), field_.transmitter_octupole_m2.cast<Jet3>(), pj)
          : Matrix3<Jet3>(Jet3(k) * DipoleCoupling<Jet3>(pj));
  for (const Source& source : sources_) {
    const Matrix3<Jet3> d = DipoleCoupling<Jet3>(pj - source.center.cast<Jet3>());
    for (int c = 0; c < 3; ++c) {
      for (int r = 0; r < 3; ++r) {
        b(r, c) += d(r, 0) * source.moment(0, c) + d(r, 1) * source.moment(1, c) +
                   d(r, 2) * source.moment(2, c);
      }
    }
  }
  if (field_.background.present()) {
    // In units of k, as in FieldModel::Field.
    b += Jet3(k) * BackgroundFieldMatrix<Jet3>(field_.background.degree,
                                               field_.background.coefficients.data(), pj);
  }
  const Eigen::Matrix3d gain_rt = receiver_gain_matrix_ * rotation.transpose();
  Eigen::Matrix3d b_value;
  Eigen::Matrix3d db[3];
  for (int c = 0; c < 3; ++c) {
    for (int r = 0; r < 3; ++r) {
      b_value(r, c) = b(r, c).a;
      for (int i = 0; i < 3; ++i) db[i](r, c) = b(r, c).v(i);
    }
  }
  const Eigen::Matrix3d rt_b = rotation.transpose() * b_value;
  const Eigen::Matrix3d s_value = receiver_gain_matrix_ * rt_b;
  Eigen::Matrix3d ds[6];
  for (int i = 0; i < 3; ++i) {
    ds[i] = gain_rt * db[i];
    Eigen::Matrix3d e_cross = Eigen::Matrix3d::Zero();  // [e_i]x
    e_cross((i + 2) % 3, (i + 1) % 3) = 1.0;
    e_cross((i + 1) % 3, (i + 2) % 3) = -1.0;
    ds[3 + i] = -receiver_gain_matrix_ * (e_cross * rt_b);
  }
  Vector9 s;
  Matrix96 j_s;
  for (int c = 0; c < 3; ++c) {
    for (int r = 0; r < 3; ++r) {
      s(3 * c + r) = s_value(r, c);
      for (int i = 0; i < 6; ++i) j_s(3 * c + r, i) = ds[i](r, c);
    }
  }
  *g = frame.j_free_t * (s - frame.s_free);
  *h = frame.j_free_t * j_s;
}

bool PhysicalCorrection::InDomain(const ReportFrame& frame, const Eigen::Vector3d& p) const {
  if (!p.allFinite() || (p - frame.p_y).norm() > frame.max_correction) return false;
  for (size_t i = 0; i < field_.objects.size(); ++i) {
    if ((p - field_.objects[i].location_in_transmitter).norm() < object_radius_[i]) return false;
  }
  for (const ConductingPlane& plane : field_.planes) {
    // The receiver is on the transmitter's side: (p - q).n has the sign of (0 - q).n.
    const Eigen::Vector3d n = plane.normal_in_transmitter;
    if ((p - plane.point_in_transmitter).dot(n) * plane.point_in_transmitter.dot(n) >= 0.0) {
      return false;
    }
  }
  return true;
}

PhysicalCorrection::Run PhysicalCorrection::Newton(const ReportFrame& frame,
                                                   const Eigen::Vector3d& p_start,
                                                   const Eigen::Matrix3d& rotation_start) const {
  Run run{p_start, rotation_start, Matrix6::Zero(), 0, false};
  if (!InDomain(frame, run.p)) return run;
  Vector6 g;
  NormalEquations(frame, run.p, run.rotation, &g, &run.h);
  // A run that does not converge returns its last iterate (in the domain, hence bounded). Returning
  // the iterate of least merit |D A^-1 g| instead was tried: it changes the fit's cost landscape
  // near strong objects, and the noise-free dipole search of fit/terms_physical_test then ends in
  // another basin.
  const auto give_up = [&] { return run; };
  for (int it = 0; it < options_.max_iterations; ++it) {
    run.iterations = it + 1;
    Vector6 step = -run.h.partialPivLu().solve(g);
    if (!step.allFinite()) return give_up();
    // Trust region: a step longer than a quarter of the range or 1 rad leaves the region where the
    // linearisation means anything, and is shortened (never the case for the paper room's
    // centimetre corrections).
    const double shrink = std::min({1.0, 0.25 * frame.range / step.head<3>().norm(),
                                    1.0 / step.tail<3>().norm()});
    step *= shrink;
    // Damping: halved until the iterate is in the model's domain (at most 2^-10: a step that must
    // shrink a thousandfold to stay in the domain means no root in it nearby). Full Newton steps
    // are kept otherwise: a line search on the merit changes the root Newton reaches near strong
    // objects (measured: the fit then loses the noise-free optimum of fit/terms_physical_test).
    double alpha = 1.0;
    Eigen::Vector3d p_new;
    Eigen::Matrix3d rotation_new;
    for (int halving = 0;; ++halving) {
      p_new = run.p + alpha * step.head<3>();
      rotation_new = run.rotation * ExpMap(alpha * step.tail<3>());
      if (InDomain(frame, p_new)) break;
      if (halving == 10) return give_up();
      alpha *= 0.5;
    }
    run.p = p_new;
    run.rotation = rotation_new;
    // Newton converges quadratically: after a step of size s the remaining error is about
    // s^2 / L, with L the length over which the distortion's Jacobian changes (metres: the
    // distance to the sources). Stopping when s^2 / (1 m) < tolerance saves the confirming step;
    // the tests check the result against the truth to 1e-9.
    const double size = alpha * std::max(step.head<3>().norm(), step.tail<3>().norm());
    if (shrink == 1.0 && alpha == 1.0 && size * size < options_.tolerance_m) {
      run.converged = true;
      return run;
    }
    NormalEquations(frame, run.p, run.rotation, &g, &run.h);
  }
  return give_up();
}

PhysicalCorrection::Inverse PhysicalCorrection::Invert(const Rigid3d& reported,
                                                       Classify classify) const {
  Inverse out;
  out.transmitter_from_receiver = reported;
  if (!reported.translation.allFinite() || !reported.rotation.coeffs().allFinite() ||
      !(reported.translation.norm() > 0.0) || !(reported.rotation.norm() > 0.0)) {
    return out;
  }
  // The report's free-space signal and its Jacobian: the tracker's normal equations at y.
  const Eigen::Matrix3d rotation_y = reported.rotation.normalized().toRotationMatrix();
  const Jet6 k(field_.field_constant);
  ReportFrame frame;
  Matrix96 j_free;
  Unpack(PerturbedRotationTranspose(rotation_y) *
             (k * DipoleCoupling<Jet6>(PerturbedPosition(reported.translation))),
         &frame.s_free, &j_free);
  frame.j_free_t = j_free.transpose();
  frame.a = frame.j_free_t * j_free;
  frame.p_y = reported.translation;
  frame.range = reported.translation.norm();
  frame.max_correction = options_.max_correction_fraction * frame.range;

  const Run run = Newton(frame, reported.translation, rotation_y);
  out.iterations = run.iterations;
  Eigen::Quaterniond q(run.rotation);
  q.normalize();
  // The matrix fixes the rotation, not the sign of its quaternion, which Eigen's conversion picks
  // by branch and so flips discontinuously along a smooth path. Keep the report's sign (the
  // correction is far below 90 degrees): an identity correction returns the report unchanged and a
  // stream of corrected quaternions stays continuous.
  if (q.dot(reported.rotation) < 0.0) q.coeffs() *= -1.0;
  out.transmitter_from_receiver = Rigid3d(q, run.p);
  if (!run.converged) return out;
  // Nothing below changes the pose: it only tells kAmbiguous from kConverged.
  if (classify == Classify::kRootOnly) {
    out.status = CorrectionStatus::kConverged;
    return out;
  }

  // dy/dx = A^-1 h is the report's response to the true pose; the inverse's response to report
  // noise is its inverse dx/dy = h^-1 A, position scaled by the range (D dx/dy D^-1, D = diag(I /
  // range, I)). The noise gain is its 2-norm (1 / smallest singular value of dy/dx). Its Frobenius
  // norm bounds it from above (within sqrt(6)), so the eigen-solve runs only when the bound exceeds
  // max_noise_gain: never in a room like the paper's (bound <= ~3).
  const Eigen::PartialPivLU<Matrix6> lu(run.h);
  // det(dy/dx) = det(h) / det(A) with det(A) > 0 (A = J_y^T J_y): the fold is where det h <= 0.
  const bool folded = !(lu.determinant() > 0.0);
  Matrix6 dx_dy = lu.solve(frame.a);
  dx_dy.topRightCorner<3, 3>() /= frame.range;
  dx_dy.bottomLeftCorner<3, 3>() *= frame.range;
  out.noise_gain = dx_dy.norm();
  if (!folded && out.noise_gain > options_.max_noise_gain && dx_dy.allFinite()) {
    const Eigen::SelfAdjointEigenSolver<Matrix6> eig(dx_dy.transpose() * dx_dy,
                                                     Eigen::EigenvaluesOnly);
    out.noise_gain = std::sqrt(std::max(eig.eigenvalues()(5), 0.0));
  }
  out.status = CorrectionStatus::kConverged;
  if (folded || !(out.noise_gain <= options_.max_noise_gain)) {
    out.status = CorrectionStatus::kAmbiguous;
    return out;
  }
  // A second root near an object whose fold zone is within reach (see the header).
  const double r4 = std::pow(run.p.norm(), 4);
  for (size_t i = 0; i < field_.objects.size(); ++i) {
    const InducedDipole& object = field_.objects[i];
    const Eigen::Vector3d& l = object.location_in_transmitter;
    const double rho =
        std::pow(2.0 * std::abs(object.polarisability_m3) * r4 / std::pow(l.norm(), 3), 0.25);
    const Eigen::Vector3d away = run.p - l;
    const double distance = away.norm();
    if (!(distance < options_.fold_reach * rho) || !(rho > object_radius_[i])) continue;
    // Starts in the fold zone between the object's surface a and rho, on the root's side: the
    // folded sheet's root of a report lies there (near the surface for the strongest folds).
    for (const double f : {0.05, 0.3}) {
      const double from_centre = object_radius_[i] + f * (rho - object_radius_[i]);
      const Eigen::Vector3d start = l + (from_centre / distance) * away;
      const Run other = Newton(frame, start, run.rotation);
      // 1 mm: far above the roots' rounding, far below any two distinct true poses.
      if (other.converged && (other.p - run.p).norm() > 1e-3) {
        out.status = CorrectionStatus::kAmbiguous;
        return out;
      }
    }
  }
  return out;
}

bool PhysicalCorrection::InvertReport(const Rigid3d& reported, Rigid3d* transmitter_from_receiver,
                                      int* iterations) const {
  const Inverse inverse = Invert(reported, Classify::kRootOnly);
  *transmitter_from_receiver = inverse.transmitter_from_receiver;
  if (iterations != nullptr) *iterations = inverse.iterations;
  return inverse.status != CorrectionStatus::kNotConverged;
}

CorrectedPose PhysicalCorrection::Apply(const Rigid3d& reported) const {
  const Inverse inverse = Invert(reported);
  CorrectedPose out;
  out.status = inverse.status;
  out.pose = receiver_from_body_ ? inverse.transmitter_from_receiver * *receiver_from_body_
                                 : inverse.transmitter_from_receiver;
  return out;
}

nlohmann::json PhysicalCorrection::ToJson() const {
  nlohmann::json j;
  j["type"] = kTypeName;
  j["field_constant"] = field_.field_constant;
  j["transmitter_octupole_m2"] = VectorJson(field_.transmitter_octupole_m2);
  nlohmann::json planes = nlohmann::json::array();
  for (const ConductingPlane& plane : field_.planes) {
    planes.push_back({{"name", plane.name},
                      {"point_in_transmitter", VectorJson(plane.point_in_transmitter)},
                      {"normal_in_transmitter", VectorJson(plane.normal_in_transmitter)},
                      {"attenuation", plane.attenuation}});
  }
  j["planes"] = planes;
  nlohmann::json objects = nlohmann::json::array();
  for (const InducedDipole& object : field_.objects) {
    objects.push_back({{"name", object.name},
                       {"location_in_transmitter", VectorJson(object.location_in_transmitter)},
                       {"polarisability_m3", object.polarisability_m3}});
  }
  j["objects"] = objects;
  if (field_.background.present()) {
    j["background"] = {{"degree", field_.background.degree},
                       {"coefficients", field_.background.coefficients}};
  }
  nlohmann::json gain = nlohmann::json::array();
  for (int r = 0; r < 3; ++r) {
    gain.push_back(VectorJson(receiver_gain_matrix_.row(r).transpose()));
  }
  j["receiver_gain_matrix"] = gain;
  if (receiver_from_body_) {
    const Eigen::Quaterniond& q = receiver_from_body_->rotation;
    j["receiver_from_body"] = {{"rotation_xyzw", {q.x(), q.y(), q.z(), q.w()}},
                               {"translation", VectorJson(receiver_from_body_->translation)}};
  }
  j["max_iterations"] = options_.max_iterations;
  j["tolerance_m"] = options_.tolerance_m;
  j["max_correction_fraction"] = options_.max_correction_fraction;
  j["max_noise_gain"] = options_.max_noise_gain;
  j["fold_reach"] = options_.fold_reach;
  return j;
}

std::unique_ptr<Correction> PhysicalCorrection::FromJson(const JsonObjectReader& reader) {
  reader.Enum("type", {kTypeName});
  FieldModel field;
  field.field_constant = reader.PositiveNumber("field_constant");
  field.transmitter_octupole_m2 = reader.Vector3("transmitter_octupole_m2");

  const auto read_array = [&reader](const std::string& key) -> const nlohmann::json& {
    const nlohmann::json& a = reader.Get(key);
    if (!a.is_array()) reader.Fail(key, "expected an array, got " + JsonSnippet(a));
    return a;
  };
  const nlohmann::json& planes = read_array("planes");
  for (size_t i = 0; i < planes.size(); ++i) {
    const JsonObjectReader r(planes[i], reader.source(), JsonIndexPath(reader.PathOf("planes"), i));
    ConductingPlane plane;
    plane.name = r.String("name");
    plane.point_in_transmitter = r.Vector3("point_in_transmitter");
    plane.normal_in_transmitter = r.Vector3("normal_in_transmitter");
    plane.attenuation = r.Number("attenuation");
    r.CheckNoUnknownKeys();
    if (!(plane.normal_in_transmitter.norm() > 1e-9)) {
      r.Fail("normal_in_transmitter", "must be a non-zero vector");
    }
    if (std::abs(plane.attenuation) > 1.0) r.Fail("attenuation", "must be in [-1, 1]");
    if (std::abs(plane.point_in_transmitter.dot(plane.normal_in_transmitter.normalized())) <=
        1e-3) {
      r.Fail("point_in_transmitter", "the plane passes through the transmitter");
    }
    field.planes.push_back(plane);
  }
  const nlohmann::json& objects = read_array("objects");
  for (size_t i = 0; i < objects.size(); ++i) {
    const JsonObjectReader r(objects[i], reader.source(),
                             JsonIndexPath(reader.PathOf("objects"), i));
    InducedDipole object;
    object.name = r.String("name");
    object.location_in_transmitter = r.Vector3("location_in_transmitter");
    object.polarisability_m3 = r.Number("polarisability_m3");
    r.CheckNoUnknownKeys();
    if (!(object.location_in_transmitter.norm() > 1e-3)) {
      r.Fail("location_in_transmitter", "must be away from the transmitter (> 1 mm)");
    }
    field.objects.push_back(object);
  }

  // Optional (files without distant sources, and those written before it, lack it).
  if (reader.Has("background")) {
    const JsonObjectReader r = reader.Object("background");
    const int degree = r.Integer("degree");
    if (degree < 0 || degree > kMaxBackgroundDegree) {
      r.Fail("degree", "must be 0 .. " + std::to_string(kMaxBackgroundDegree));
    }
    field.background.degree = degree;
    field.background.coefficients = r.NumberArray("coefficients");
    const size_t n = 3 * static_cast<size_t>(BackgroundBasisSize(degree));
    if (field.background.coefficients.size() != n) {
      r.Fail("coefficients", "expected " + std::to_string(n) + " numbers for degree " +
                                 std::to_string(degree) + ", got " +
                                 std::to_string(field.background.coefficients.size()));
    }
    r.CheckNoUnknownKeys();
  }

  const nlohmann::json& gain_json = read_array("receiver_gain_matrix");
  const std::string gain_path = reader.PathOf("receiver_gain_matrix");
  if (gain_json.size() != 3) reader.Fail("receiver_gain_matrix", "expected 3 rows");
  Eigen::Matrix3d gain;
  for (int r = 0; r < 3; ++r) {
    const std::string row_path = JsonIndexPath(gain_path, r);
    const nlohmann::json& row = gain_json[r];
    if (!row.is_array() || row.size() != 3) {
      ThrowJsonError(reader.source(), row_path, "expected 3 numbers, got " + JsonSnippet(row));
    }
    for (int c = 0; c < 3; ++c) {
      gain(r, c) = JsonFiniteNumber(row[c], reader.source(), JsonIndexPath(row_path, c));
    }
  }
  if (!(gain.determinant() > 1e-6)) {
    reader.Fail("receiver_gain_matrix",
                "must have a positive determinant (a reversed or missing "
                "coil is a wiring fault, not a calibration)");
  }

  std::optional<Rigid3d> receiver_from_body;
  if (reader.Has("receiver_from_body")) {
    const JsonObjectReader r = reader.Object("receiver_from_body");
    const std::vector<double> q = r.NumberArray("rotation_xyzw");
    if (q.size() != 4) r.Fail("rotation_xyzw", "expected 4 numbers (x, y, z, w)");
    const Eigen::Quaterniond rotation = QuaternionFromXyzw(q[0], q[1], q[2], q[3]);
    if (std::abs(rotation.norm() - 1.0) > 1e-6) {
      r.Fail("rotation_xyzw",
             "must be a unit quaternion (|q| = " + std::to_string(rotation.norm()) + ")");
    }
    receiver_from_body = Rigid3d(rotation.normalized(), r.Vector3("translation"));
    r.CheckNoUnknownKeys();
  }

  PhysicalCorrectionOptions options;
  if (reader.Has("max_iterations")) options.max_iterations = reader.Integer("max_iterations");
  if (reader.Has("tolerance_m")) options.tolerance_m = reader.PositiveNumber("tolerance_m");
  // Optional (files written before the bounded inverse lack them: defaults).
  if (reader.Has("max_correction_fraction")) {
    options.max_correction_fraction = reader.PositiveNumber("max_correction_fraction");
  }
  if (reader.Has("max_noise_gain")) options.max_noise_gain = reader.PositiveNumber("max_noise_gain");
  if (reader.Has("fold_reach")) options.fold_reach = reader.Number("fold_reach");
  try {
    options.Check();
    field.Check();
  } catch (const std::invalid_argument& e) {
    reader.Fail("", e.what());
  }
  return std::make_unique<PhysicalCorrection>(std::move(field), gain, receiver_from_body, options);
}

std::unique_ptr<Correction> PhysicalCorrection::Clone() const {
  return std::make_unique<PhysicalCorrection>(*this);
}

}  // namespace trackcal
