#include "core/physical_correction.h"

#include <ceres/jet.h>

#include <Eigen/LU>
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
}

bool PhysicalCorrection::InvertReport(const Rigid3d& reported, Rigid3d* transmitter_from_receiver,
                                      int* iterations) const {
  *transmitter_from_receiver = reported;
  if (iterations != nullptr) *iterations = 0;
  if (!reported.translation.allFinite() || !reported.rotation.coeffs().allFinite()) return false;
  // The report's free-space signal and its Jacobian: the tracker's normal equations at y.
  const Eigen::Matrix3d rotation_y = reported.rotation.normalized().toRotationMatrix();
  const Jet6 k(field_.field_constant);
  Vector9 s_free;
  Matrix96 j_free;
  Unpack(PerturbedRotationTranspose(rotation_y) *
             (k * DipoleCoupling<Jet6>(PerturbedPosition(reported.translation))),
         &s_free, &j_free);
  const Eigen::Matrix<double, 6, 9> j_free_t = j_free.transpose();

  Eigen::Vector3d p = reported.translation;
  Eigen::Matrix3d rotation = rotation_y;
  Vector9 s;
  Matrix96 j_s;
  for (int it = 0; it < options_.max_iterations; ++it) {
    if (iterations != nullptr) *iterations = it + 1;
    // B(p) and dB/dp by a 3-slot Jet; the rotation's derivative is analytic:
    // d/dw_i [G Exp(-w) R^T B] = -G [e_i]x R^T B.
    Vector3<Jet3> pj;
    for (int i = 0; i < 3; ++i) pj(i) = Jet3(p(i), i);
    Matrix3<Jet3> b =
        has_octupole_
            ? TransmitterField<Jet3>(Jet3(k.a), field_.transmitter_octupole_m2.cast<Jet3>(), pj)
            : Matrix3<Jet3>(Jet3(k.a) * DipoleCoupling<Jet3>(pj));
    for (const Source& source : sources_) {
      const Matrix3<Jet3> d = DipoleCoupling<Jet3>(pj - source.center.cast<Jet3>());
      for (int c = 0; c < 3; ++c) {
        for (int r = 0; r < 3; ++r) {
          b(r, c) += d(r, 0) * source.moment(0, c) + d(r, 1) * source.moment(1, c) +
                     d(r, 2) * source.moment(2, c);
        }
      }
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
    for (int c = 0; c < 3; ++c) {
      for (int r = 0; r < 3; ++r) {
        s(3 * c + r) = s_value(r, c);
        for (int i = 0; i < 6; ++i) j_s(3 * c + r, i) = ds[i](r, c);
      }
    }
    const Vector6 g = j_free_t * (s - s_free);
    const Matrix6 h = j_free_t * j_s;
    const Vector6 step = -h.partialPivLu().solve(g);
    if (!step.allFinite()) return false;
    p += step.head<3>();
    rotation = rotation * ExpMap(step.tail<3>());
    // Newton converges quadratically: after a step of size s the remaining error is about
    // s^2 / L, with L the length over which the distortion's Jacobian changes (metres: the
    // distance to the sources). Stopping when s^2 / (1 m) < tolerance saves the confirming step;
    // the tests check the result against the truth to 1e-9.
    const double step_size = std::max(step.head<3>().norm(), step.tail<3>().norm());
    if (step_size * step_size < options_.tolerance_m) {
      Eigen::Quaterniond q(rotation);
      q.normalize();
      *transmitter_from_receiver = Rigid3d(q, p);
      return true;
    }
  }
  Eigen::Quaterniond q(rotation);
  q.normalize();
  if (p.allFinite() && q.coeffs().allFinite()) *transmitter_from_receiver = Rigid3d(q, p);
  return false;
}

CorrectedPose PhysicalCorrection::Apply(const Rigid3d& reported) const {
  CorrectedPose out;
  Rigid3d transmitter_from_receiver;
  out.extrapolated = !InvertReport(reported, &transmitter_from_receiver);
  out.pose = receiver_from_body_ ? transmitter_from_receiver * *receiver_from_body_
                                 : transmitter_from_receiver;
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
