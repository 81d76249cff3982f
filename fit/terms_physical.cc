#include "fit/terms_physical.h"

#include <ceres/autodiff_cost_function.h>
#include <ceres/jet.h>
#include <ceres/loss_function.h>
#include <ceres/manifold.h>
#include <ceres/problem.h>
#include <ceres/solver.h>
#include <ceres/sphere_manifold.h>

#include <Eigen/LU>
#include <algorithm>
#include <cmath>
#include <limits>
#include <stdexcept>

#include "core/field.h"

namespace trackcal::fit {
namespace {

// Free coordinates per Jet pass: 6 pose-tangent slots, then up to kChunk parameters.
constexpr int kChunk = 26;
constexpr int kSlots = 6 + kChunk;
using JetX = ceres::Jet<double, kSlots>;
using Jet6 = ceres::Jet<double, 6>;
using Matrix96 = Eigen::Matrix<double, 9, 6>;
using Vector9 = Eigen::Matrix<double, 9, 1>;
using Matrix6 = Eigen::Matrix<double, 6, 6>;
using Vector6 = Eigen::Matrix<double, 6, 1>;

// Block indices within an effect.
constexpr int kOffsetRotation = 0, kOffsetTranslation = 1;
constexpr int kGainMatrix = 0;
constexpr int kOctupole = 0;
constexpr int kDipoleLocation = 0, kDipolePolarisability = 1;
constexpr int kPlaneDistance = 0, kPlaneNormal = 1, kPlaneAttenuation = 2;

// Identifiability scales: a dipole location or plane distance known worse than 10 cm, a normal worse
// than 0.1 rad (6 deg), is flagged: at that point the term describes no definite object.
constexpr double kLocationScaleM = 0.1;
constexpr double kNormalScaleRad = 0.1;

// The chart the inverse's Jacobians use: q * normalize(1, w / 2), equal to q * Exp(w) to second
// order (so nested Jets give the right second derivatives too).
template <typename T>
Eigen::Quaternion<T> RightPerturbed(const Eigen::Quaterniond& q, const T& w0, const T& w1,
                                    const T& w2) {
  using std::sqrt;
  const T half0 = w0 / T(2), half1 = w1 / T(2), half2 = w2 / T(2);
  const T s = T(1) / sqrt(T(1) + half0 * half0 + half1 * half1 + half2 * half2);
  const Eigen::Quaternion<T> dq = QuaternionFromWxyz<T>(s, half0 * s, half1 * s, half2 * s);
  return q.cast<T>() * dq;
}

// vec() of a 3 x 3 matrix, column-major (index 3 c + r), as core/physical_correction.cc.
template <typename T>
Eigen::Matrix<T, 9, 1> Vec(const Matrix3<T>& m) {
  Eigen::Matrix<T, 9, 1> v;
  for (int c = 0; c < 3; ++c)
    for (int r = 0; r < 3; ++r) v(3 * c + r) = m(r, c);
  return v;
}

// The report's free-space signal and its Jacobian J_y (9 x 6) in the right-tangent chart.
void FreeSpaceSignal(const Rigid3d& y, Vector9* s_free, Matrix96* j_free) {
  Vector3<Jet6> p;
  for (int i = 0; i < 3; ++i) p(i) = Jet6(y.translation(i), i);
  const Eigen::Quaternion<Jet6> q = RightPerturbed<Jet6>(y.rotation.normalized(), Jet6(0.0, 3),
                                                         Jet6(0.0, 4), Jet6(0.0, 5));
  const Matrix3<Jet6> s = q.toRotationMatrix().transpose() * DipoleCoupling<Jet6>(p);
  const auto v = Vec<Jet6>(s);
  for (int e = 0; e < 9; ++e) {
    (*s_free)(e) = v(e).a;
    j_free->row(e) = v(e).v.transpose();
  }
}

// d g / d y (6 x 6) for g(y) = J(y)^T (s - S_free(y)) with s fixed, y moved along its tangent
// (p + eps_p, R Exp(eps_w)). -J^T J is exact; the term with the derivative of J (second
// derivatives of S_free) is a central difference of the autodiff J: its error, O(h^2) with
// h = 1e-5 plus rounding 1e-16 / h, is below 1e-10 relative. (ceres::Jet does not nest with
// Eigen's and core/field.h's integer constants, so a Jet of Jets is not available.)
Matrix6 NormalEquationsInputDerivative(const Rigid3d& y, const Vector9& s) {
  Vector9 s_free;
  Matrix96 j_free;
  FreeSpaceSignal(y, &s_free, &j_free);
  const Vector9 r = s - s_free;
  Matrix6 out = -j_free.transpose() * j_free;
  constexpr double h = 1e-5;
  for (int k = 0; k < 6; ++k) {
    Matrix96 j_plus, j_minus;
    Vector9 unused;
    for (const double sign : {1.0, -1.0}) {
      Rigid3d moved = y;
      if (k < 3) {
        moved.translation(k) += sign * h;
      } else {
        Eigen::Vector3d w = Eigen::Vector3d::Zero();
        w(k - 3) = sign * h;
        moved.rotation = y.rotation.normalized() * Eigen::Quaterniond(Eigen::AngleAxisd(h, w / h));
      }
      FreeSpaceSignal(moved, &unused, sign > 0 ? &j_plus : &j_minus);
    }
    out.col(k) += ((j_plus - j_minus) / (2.0 * h)).transpose() * r;
  }
  return out;
}

// The forward model of a group at block values of type T (all blocks, blocks() order).
template <typename T>
struct GroupModel {
  const std::vector<PhysicalGroupTerm::Effect>* effects;
  const std::vector<bool>* disabled;
  const T* const* v;

  Matrix3<T> Gain() const {
    for (const auto& e : *effects) {
      if (e.kind != PhysicalEffect::kReceiverGain) continue;
      const T* g = v[e.first_block + kGainMatrix];
      Matrix3<T> m;
      for (int r = 0; r < 3; ++r)
        for (int c = 0; c < 3; ++c) m(r, c) = g[3 * r + c];
      return m;
    }
    return Matrix3<T>::Identity();
  }
  // Sensor offset (identity without the effect).
  bool Offset(Eigen::Quaternion<T>* q, Vector3<T>* t) const {
    for (const auto& e : *effects) {
      if (e.kind != PhysicalEffect::kSensorOffset) continue;
      *q = QuaternionFromXyzwArray<T>(v[e.first_block + kOffsetRotation]).normalized();
      const T* x = v[e.first_block + kOffsetTranslation];
      *t = Vector3<T>(x[0], x[1], x[2]);
      return true;
    }
    *q = Eigen::Quaternion<T>::Identity();
    *t = Vector3<T>::Zero();
    return false;
  }
  Matrix3<T> Field(const Vector3<T>& p) const {
    const T k(1.0);
    Vector3<T> octupole = Vector3<T>::Zero();
    for (const auto& e : *effects) {
      if (e.kind != PhysicalEffect::kNearField) continue;
      const T* o = v[e.first_block + kOctupole];
      octupole = Vector3<T>(o[0], o[1], o[2]);
    }
    Matrix3<T> b = TransmitterField<T>(k, octupole, p);
    for (size_t i = 0; i < effects->size(); ++i) {
      const auto& e = (*effects)[i];
      if (!disabled->empty() && (*disabled)[i]) continue;
      if (e.kind == PhysicalEffect::kPlane) {
        const T* n = v[e.first_block + kPlaneNormal];
        const Vector3<T> normal = Vector3<T>(n[0], n[1], n[2]).normalized();
        const T d = v[e.first_block + kPlaneDistance][0];
        b += PlaneImageField<T>(k, Vector3<T>(normal * d), normal,
                                v[e.first_block + kPlaneAttenuation][0], p);
      } else if (e.kind == PhysicalEffect::kDipole) {
        const T* l = v[e.first_block + kDipoleLocation];
        b += InducedDipoleField<T>(k, Vector3<T>(l[0], l[1], l[2]),
                                   v[e.first_block + kDipolePolarisability][0], p);
      }
    }
    return b;
  }
};

ParameterBlock MakeBlock(std::string name, std::vector<double> values,
                         std::vector<std::string> coordinate_names, std::string unit) {
  ParameterBlock b;
  b.name = std::move(name);
  b.values = std::move(values);
  b.coordinate_names = std::move(coordinate_names);
  b.unit = std::move(unit);
  return b;
}

// Whitened station residual (as the engine's) and its derivative by the corrected pose (6 x 7).
void WhitenedResidual(const AmbientPose& pose, const Rigid3d& reference,
                      const Eigen::Vector2d& sigmas, Vector6* r,
                      Eigen::Matrix<double, 6, 7>* d_r) {
  using Jet7 = ceres::Jet<double, 7>;
  Jet7 x[7];
  for (int k = 0; k < 7; ++k) x[k] = Jet7(pose[k], k);
  for (int k = 0; k < 3; ++k) {
    const Jet7 e = (x[k] - Jet7(reference.translation[k])) / Jet7(sigmas[0]);
    (*r)(k) = e.a;
    d_r->row(k) = e.v.transpose();
  }
  const Vector3<Jet7> o = OrientationErrorVector<Jet7>(QuaternionFromXyzwArray<Jet7>(x + 3),
                                                       reference.rotation.cast<Jet7>());
  for (int k = 0; k < 3; ++k) {
    const Jet7 e = o[k] / Jet7(sigmas[1]);
    (*r)(3 + k) = e.a;
    d_r->row(3 + k) = e.v.transpose();
  }
}

// The linearisation of one station for the search: its residual r and the 6 x 9 map K with
// d r / d strength = K vec(B_unit(p)) for a new source of unit strength with field matrix B_unit at
// the station's true position p.
struct SearchStation {
  Eigen::Vector3d p;
  Vector6 r;
  Eigen::Matrix<double, 6, 9> k;
};

// Candidate score: the cost reduction of the best strength, and that strength.
struct Score {
  double reduction = 0.0;
  double strength = 0.0;
};

template <typename UnitField>
Score ScoreCandidate(const std::vector<SearchStation>& stations, const UnitField& unit_field) {
  double a = 0.0, c = 0.0;
  for (const auto& s : stations) {
    Matrix3<double> b;
    if (!unit_field(s.p, &b)) return {};
    const Vector6 u = s.k * Vec<double>(b);
    a += u.dot(s.r);
    c += u.squaredNorm();
  }
  if (!(c > 0.0) || !std::isfinite(a) || !std::isfinite(c)) return {};
  return {a * a / c, -a / c};
}

// Pattern search minimising -reduction from x over its coordinates, steps halving to `min_step`.
template <typename Objective>
std::vector<double> PatternSearch(std::vector<double> x, std::vector<double> step,
                                  double min_step_ratio, const Objective& f) {
  double best = f(x);
  std::vector<double> initial_step = step;
  for (int iteration = 0; iteration < 200; ++iteration) {
    bool moved = false;
    for (size_t i = 0; i < x.size(); ++i) {
      for (double sign : {1.0, -1.0}) {
        std::vector<double> trial = x;
        trial[i] += sign * step[i];
        const double value = f(trial);
        if (value < best) {
          best = value;
          x = trial;
          moved = true;
          break;
        }
      }
    }
    if (!moved) {
      bool small = true;
      for (size_t i = 0; i < step.size(); ++i) {
        step[i] *= 0.5;
        small = small && step[i] < min_step_ratio * initial_step[i];
      }
      if (small) break;
    }
  }
  return x;
}

// Unit vectors spread over the half sphere z >= 0 (Fibonacci lattice) plus the three axes.
std::vector<Eigen::Vector3d> HalfSphereDirections(int count) {
  std::vector<Eigen::Vector3d> out = {Eigen::Vector3d::UnitX(), Eigen::Vector3d::UnitY(),
                                      Eigen::Vector3d::UnitZ()};
  const double golden = M_PI * (3.0 - std::sqrt(5.0));
  for (int i = 0; i < count; ++i) {
    const double z = (i + 0.5) / count;
    const double radius = std::sqrt(1.0 - z * z);
    out.emplace_back(radius * std::cos(golden * i), radius * std::sin(golden * i), z);
  }
  return out;
}

void TangentBasis(const Eigen::Vector3d& n, Eigen::Vector3d* t1, Eigen::Vector3d* t2) {
  const Eigen::Vector3d a =
      std::abs(n.x()) < 0.9 ? Eigen::Vector3d::UnitX() : Eigen::Vector3d::UnitY();
  *t1 = n.cross(a).normalized();
  *t2 = n.cross(*t1);
}

std::vector<double> ReadVector(const YamlMapReader& reader, const std::string& key, size_t n) {
  const std::vector<double> v = reader.GetDoubleList(key);
  if (v.size() != n) reader.Fail(key, "expected " + std::to_string(n) + " numbers");
  return v;
}

}  // namespace

const char* PhysicalEffectType(PhysicalEffect effect) {
  switch (effect) {
    case PhysicalEffect::kSensorOffset: return "sensor_offset";
    case PhysicalEffect::kReceiverGain: return "receiver_gain";
    case PhysicalEffect::kDipole: return "dipole";
    case PhysicalEffect::kPlane: return "plane";
    case PhysicalEffect::kNearField: return "near_field";
  }
  return "";
}

const std::vector<std::string>& PhysicalTermTypes() {
  static const std::vector<std::string> types = {"sensor_offset", "receiver_gain", "dipole",
                                                 "plane", "near_field"};
  return types;
}

bool PhysicalSearchOptions::Check() const {
  return margin_m >= 0.0 && dipole_spacing_m > 0.0 && min_station_distance_m >= 0.0 &&
         refine_candidates >= 1 && plane_normals >= 0 && plane_distance_step_m > 0.0;
}

PhysicalGroupTerm::PhysicalGroupTerm(PhysicalEffect effect) {
  set_name(kType);
  Effect e{effect, PhysicalEffectType(effect), 0, 0, false, false, false, true};
  if (effect == PhysicalEffect::kDipole) {
    e.search_location = true;
    e.strength_given = false;
  } else if (effect == PhysicalEffect::kPlane) {
    e.search_plane = true;
    e.strength_given = false;
  }
  AddEffectBlocks(&e);
  effects_.push_back(e);
}

void PhysicalGroupTerm::AddEffectBlocks(Effect* e) {
  e->first_block = static_cast<int>(blocks_.size());
  const std::string& term = e->name;
  auto add = [&](ParameterBlock b) {
    b.term = term;
    blocks_.push_back(std::move(b));
  };
  switch (e->kind) {
    case PhysicalEffect::kSensorOffset: {
      ParameterBlock rotation =
          MakeBlock("rotation", {0, 0, 0, 1}, {"qx", "qy", "qz", "qw"}, "1 (quaternion x, y, z, w)");
      rotation.make_manifold = [] { return new ceres::EigenQuaternionManifold(); };
      rotation.tangent_names = {"rotation_vector.x", "rotation_vector.y", "rotation_vector.z"};
      rotation.tangent_unit = "rad";
      rotation.tangent_scale = 2.0;  // EigenQuaternionManifold: Exp(delta) rotates by 2 |delta|
      add(std::move(rotation));
      add(MakeBlock("translation", {0, 0, 0}, {"x", "y", "z"}, "m"));
      break;
    }
    case PhysicalEffect::kReceiverGain:
      add(MakeBlock("gain_matrix", {1, 0, 0, 0, 1, 0, 0, 0, 1},
                    {"G00", "G01", "G02", "G10", "G11", "G12", "G20", "G21", "G22"}, "1"));
      break;
    case PhysicalEffect::kNearField:
      add(MakeBlock("octupole_m2", {0, 0, 0}, {"coil_x", "coil_y", "coil_z"}, "m^2"));
      break;
    case PhysicalEffect::kDipole: {
      ParameterBlock location =
          MakeBlock("location_in_transmitter", {0, 0, 1}, {"x", "y", "z"}, "m");
      location.identifiability_scale = kLocationScaleM;
      add(std::move(location));
      add(MakeBlock("polarisability_m3", {0}, {"polarisability"}, "m^3"));
      break;
    }
    case PhysicalEffect::kPlane: {
      ParameterBlock distance = MakeBlock("distance_m", {1}, {"distance"}, "m");
      distance.identifiability_scale = kLocationScaleM;
      add(std::move(distance));
      ParameterBlock normal = MakeBlock("normal_in_transmitter", {0, 0, 1}, {"x", "y", "z"}, "1");
      normal.make_manifold = [] { return new ceres::SphereManifold<3>(); };
      normal.tangent_names = {"angle_a", "angle_b"};
      normal.tangent_unit = "rad";
      normal.identifiability_scale = kNormalScaleRad;
      add(std::move(normal));
      ParameterBlock attenuation = MakeBlock("attenuation", {0}, {"attenuation"}, "1");
      attenuation.lower = {-1.0};
      attenuation.upper = {1.0};
      add(std::move(attenuation));
      break;
    }
  }
}

std::unique_ptr<ModelTerm> PhysicalGroupTerm::FromYaml(PhysicalEffect effect,
                                                       const YamlMapReader& reader) {
  auto term = std::make_unique<PhysicalGroupTerm>(effect);
  Effect& e = term->effects_[0];
  auto& blocks = term->blocks_;
  switch (effect) {
    case PhysicalEffect::kSensorOffset:
      if (reader.Has("receiver_from_body")) {
        const YamlMapReader r = reader.GetMap("receiver_from_body");
        if (r.Has("rotation_xyzw")) {
          std::vector<double> q = ReadVector(r, "rotation_xyzw", 4);
          const double norm = Eigen::Map<Eigen::Vector4d>(q.data()).norm();
          // Rounded unit quaternions are accepted and normalised.
          if (std::abs(norm - 1.0) > 1e-3) r.Fail("rotation_xyzw", "must be a unit quaternion");
          for (double& x : q) x /= norm;
          blocks[kOffsetRotation].values = q;
        }
        if (r.Has("translation")) blocks[kOffsetTranslation].values = ReadVector(r, "translation", 3);
        r.Finish();
      }
      break;
    case PhysicalEffect::kReceiverGain:
      if (reader.Has("receiver_gain_matrix")) {
        const YAML::Node node = reader.node()["receiver_gain_matrix"];
        std::vector<double> g;
        bool ok = node.IsSequence();
        if (ok && node.size() == 3) {
          for (const auto& row : node) {
            ok = ok && row.IsSequence() && row.size() == 3;
            if (!ok) break;
            for (const auto& x : row) {
              double value = 0.0;
              ok = ok && x.IsScalar() && YAML::convert<double>::decode(x, value) && std::isfinite(value);
              g.push_back(value);
            }
          }
        } else if (ok && node.size() == 9) {
          g = ReadVector(reader, "receiver_gain_matrix", 9);
        } else {
          ok = false;
        }
        if (!ok) reader.Fail("receiver_gain_matrix", "expected 3 rows of 3 numbers");
        if (!(Eigen::Map<Eigen::Matrix<double, 3, 3, Eigen::RowMajor>>(g.data()).determinant() >
              1e-6)) {
          reader.Fail("receiver_gain_matrix", "must have a positive determinant");
        }
        blocks[kGainMatrix].values = g;
      }
      if (reader.Has("gain_scale")) {
        const std::string scale = reader.GetString("gain_scale");
        if (scale == "auto") {
          term->gain_scale_ = GainScale::kAuto;
        } else if (scale == "free") {
          term->gain_scale_ = GainScale::kFree;
        } else if (scale == "unit_mean") {
          term->gain_scale_ = GainScale::kUnitMean;
        } else {
          reader.Fail("gain_scale", "expected auto, free or unit_mean, got '" + scale + "'");
        }
      }
      break;
    case PhysicalEffect::kNearField:
      if (reader.Has("octupole_m2")) blocks[kOctupole].values = ReadVector(reader, "octupole_m2", 3);
      break;
    case PhysicalEffect::kDipole:
      if (reader.Has("location_in_transmitter")) {
        blocks[kDipoleLocation].values = ReadVector(reader, "location_in_transmitter", 3);
        if (Eigen::Map<Eigen::Vector3d>(blocks[kDipoleLocation].values.data()).norm() < 1e-3) {
          reader.Fail("location_in_transmitter", "an object cannot sit at the transmitter");
        }
        e.search_location = false;
      }
      if (reader.Has("polarisability_m3")) {
        blocks[kDipolePolarisability].values = {reader.GetDouble("polarisability_m3")};
        e.strength_given = true;
      }
      break;
    case PhysicalEffect::kPlane: {
      const bool has_point = reader.Has("point_in_transmitter");
      const bool has_normal = reader.Has("normal_in_transmitter");
      if (has_point && !has_normal) {
        reader.Fail("point_in_transmitter", "give normal_in_transmitter with the point");
      }
      if (has_normal) {
        const std::vector<double> n = ReadVector(reader, "normal_in_transmitter", 3);
        const Eigen::Vector3d normal(n[0], n[1], n[2]);
        if (!(normal.norm() > 1e-9)) reader.Fail("normal_in_transmitter", "must not be zero");
        const Eigen::Vector3d unit = normal.normalized();
        blocks[kPlaneNormal].values = {unit.x(), unit.y(), unit.z()};
        e.normal_given = true;
        if (has_point) {
          const std::vector<double> p = ReadVector(reader, "point_in_transmitter", 3);
          blocks[kPlaneDistance].values = {Eigen::Vector3d(p[0], p[1], p[2]).dot(unit)};
          e.search_plane = false;
        }
      }
      // A normal alone: the distance is searched along it.
      if (reader.Has("attenuation")) {
        const double a = reader.GetDouble("attenuation");
        if (!(a >= -1.0 && a <= 1.0)) reader.Fail("attenuation", "must be in [-1, 1]");
        blocks[kPlaneAttenuation].values = {a};
        e.strength_given = true;
      }
      break;
    }
  }
  return term;
}

void PhysicalGroupTerm::SetEffectName(const std::string& name, int line) {
  if (effects_.size() != 1) throw std::logic_error("SetEffectName on a merged group");
  effects_[0].name = name;
  effects_[0].line = line;
  for (auto& b : blocks_) b.term = name;
}

void PhysicalGroupTerm::MarkStartGiven(const std::string& effect_name, const std::string& block) {
  for (auto& e : effects_) {
    if (e.name != effect_name) continue;
    if (e.kind == PhysicalEffect::kDipole) {
      if (block == "location_in_transmitter") e.search_location = false;
      if (block == "polarisability_m3") e.strength_given = true;
    } else if (e.kind == PhysicalEffect::kPlane) {
      if (block == "distance_m") e.search_plane = false;
      if (block == "normal_in_transmitter") e.normal_given = true;
      if (block == "attenuation") e.strength_given = true;
    }
  }
}

void PhysicalGroupTerm::Absorb(PhysicalGroupTerm&& other) {
  for (Effect e : other.effects_) {
    const bool single = e.kind == PhysicalEffect::kSensorOffset ||
                        e.kind == PhysicalEffect::kReceiverGain ||
                        e.kind == PhysicalEffect::kNearField;
    if (single) {
      for (const Effect& mine : effects_) {
        if (mine.kind == e.kind) {
          throw std::invalid_argument(std::string("a model has at most one ") +
                                      PhysicalEffectType(e.kind) + " term");
        }
      }
    }
    if (e.kind == PhysicalEffect::kReceiverGain) gain_scale_ = other.gain_scale_;
    const int offset = static_cast<int>(blocks_.size());
    e.first_block += offset;
    effects_.push_back(e);
  }
  for (auto& b : other.blocks_) blocks_.push_back(std::move(b));
  other.blocks_.clear();
  other.effects_.clear();
}

void PhysicalGroupTerm::Prepare(const std::vector<FitStation>& inputs) {
  if (inputs.empty()) throw std::invalid_argument("physical terms: no calibration stations");
  data_min_ = data_max_ = inputs[0].reported.translation;
  for (const auto& s : inputs) {
    data_min_ = data_min_.cwiseMin(s.reported.translation);
    data_max_ = data_max_.cwiseMax(s.reported.translation);
  }
}

StationBinding PhysicalGroupTerm::Bind(const AmbientPose& /*input*/) const {
  StationBinding binding;
  for (size_t i = 0; i < blocks_.size(); ++i) {
    if (!blocks_[i].fixed) binding.blocks.push_back(static_cast<int>(i));
  }
  return binding;
}

PhysicalCorrection PhysicalGroupTerm::MakeCorrection(const double* const* v,
                                                     PhysicalCorrectionOptions options) const {
  FieldModel field;
  field.field_constant = 1.0;
  const GroupModel<double> model{&effects_, &disabled_, v};
  std::optional<Rigid3d> offset;
  for (size_t i = 0; i < effects_.size(); ++i) {
    const Effect& e = effects_[i];
    const bool off = !disabled_.empty() && disabled_[i];
    switch (e.kind) {
      case PhysicalEffect::kSensorOffset: {
        Eigen::Quaterniond q;
        Eigen::Vector3d t;
        model.Offset(&q, &t);
        offset = Rigid3d(q, t);
        break;
      }
      case PhysicalEffect::kReceiverGain: break;
      case PhysicalEffect::kNearField:
        field.transmitter_octupole_m2 = Eigen::Vector3d(v[Block(e, kOctupole)]);
        break;
      case PhysicalEffect::kPlane: {
        if (off) break;
        const Eigen::Vector3d n = Eigen::Vector3d(v[Block(e, kPlaneNormal)]);
        if (!(n.norm() > 1e-12)) throw std::invalid_argument(e.name + ": zero normal");
        ConductingPlane plane;
        plane.name = e.name;
        plane.normal_in_transmitter = n.normalized();
        plane.point_in_transmitter = v[Block(e, kPlaneDistance)][0] * plane.normal_in_transmitter;
        plane.attenuation = v[Block(e, kPlaneAttenuation)][0];
        field.planes.push_back(plane);
        break;
      }
      case PhysicalEffect::kDipole: {
        if (off) break;
        InducedDipole object;
        object.name = e.name;
        object.location_in_transmitter = Eigen::Vector3d(v[Block(e, kDipoleLocation)]);
        object.polarisability_m3 = v[Block(e, kDipolePolarisability)][0];
        field.objects.push_back(object);
        break;
      }
    }
  }
  return PhysicalCorrection(std::move(field), model.Gain(), offset, options);
}

bool PhysicalGroupTerm::Evaluate(const StationBinding& binding, const double* const* block_values,
                                 const AmbientPose& input, bool jacobians,
                                 TermEvaluation* result) const {
  const size_t num_blocks = blocks_.size();
  std::vector<const double*> v(num_blocks);
  for (size_t i = 0; i < num_blocks; ++i) v[i] = blocks_[i].values.data();
  for (size_t j = 0; j < binding.blocks.size(); ++j) {
    v[static_cast<size_t>(binding.blocks[j])] = block_values[j];
  }
  const Rigid3d y = FromAmbient(input);
  Rigid3d x;
  std::optional<Rigid3d> offset;
  try {
    // The fit may start far from the truth, where Newton needs more steps than at run time.
    PhysicalCorrectionOptions options;
    options.max_iterations = 50;
    const PhysicalCorrection model = MakeCorrection(v.data(), options);
    // A non-converged inverse still yields the best iterate, and its residual is what the model
    // explains there; only a non-finite one stops the step.
    model.InvertReport(y, &x);
    offset = model.receiver_from_body();
  } catch (const std::invalid_argument&) {
    return false;  // the values left the model's domain: Ceres shortens the step
  }
  if (!x.translation.allFinite() || !x.rotation.coeffs().allFinite()) return false;
  result->output = ToAmbient(offset ? x * *offset : x);
  if (!jacobians) return true;

  // Free coordinates (bound block, coordinate), in binding order.
  std::vector<std::pair<int, int>> coords;
  for (size_t j = 0; j < binding.blocks.size(); ++j) {
    for (int c = 0; c < blocks_[static_cast<size_t>(binding.blocks[j])].size(); ++c) {
      coords.emplace_back(static_cast<int>(j), c);
    }
  }
  const int n = static_cast<int>(coords.size());
  Vector9 s_free;
  Matrix96 j_free;
  FreeSpaceSignal(y, &s_free, &j_free);
  const Eigen::Matrix<double, 6, 9> j_free_t = j_free.transpose();

  Matrix6 g_x;
  Eigen::Matrix<double, 7, 6> o_x;
  Eigen::MatrixXd g_theta(6, n), o_theta(7, n);
  Vector9 s_at_x;
  std::vector<std::vector<JetX>> theta(num_blocks);
  std::vector<const JetX*> theta_ptrs(num_blocks);
  for (int start = 0; start == 0 || start < n; start += kChunk) {
    for (size_t i = 0; i < num_blocks; ++i) {
      theta[i].assign(static_cast<size_t>(blocks_[i].size()), JetX());
      for (int c = 0; c < blocks_[i].size(); ++c) theta[i][static_cast<size_t>(c)] = JetX(v[i][c]);
    }
    for (int k = start; k < std::min(n, start + kChunk); ++k) {
      const auto [j, c] = coords[static_cast<size_t>(k)];
      theta[static_cast<size_t>(binding.blocks[static_cast<size_t>(j)])][static_cast<size_t>(c)]
          .v[6 + k - start] = 1.0;
    }
    for (size_t i = 0; i < num_blocks; ++i) theta_ptrs[i] = theta[i].data();
    const GroupModel<JetX> model{&effects_, &disabled_, theta_ptrs.data()};
    Vector3<JetX> p;
    for (int i = 0; i < 3; ++i) p(i) = JetX(x.translation(i), i);
    const Eigen::Quaternion<JetX> q =
        RightPerturbed<JetX>(x.rotation, JetX(0.0, 3), JetX(0.0, 4), JetX(0.0, 5));
    const Matrix3<JetX> s = model.Gain() * (q.toRotationMatrix().transpose() * model.Field(p));
    const auto s_vec = Vec<JetX>(s);
    Eigen::Matrix<double, 9, kSlots> j_s;
    for (int e = 0; e < 9; ++e) {
      j_s.row(e) = s_vec(e).v.transpose();
      s_at_x(e) = s_vec(e).a;
    }
    const Eigen::Matrix<double, 6, kSlots> j_g = j_free_t * j_s;
    Eigen::Quaternion<JetX> q_off;
    Vector3<JetX> t_off;
    model.Offset(&q_off, &t_off);
    const Vector3<JetX> p_out = p + q * t_off;
    const Eigen::Quaternion<JetX> q_out = q * q_off;
    JetX out[7] = {p_out(0), p_out(1), p_out(2), q_out.x(), q_out.y(), q_out.z(), q_out.w()};
    if (start == 0) {
      g_x = j_g.leftCols<6>();
      for (int r = 0; r < 7; ++r) o_x.row(r) = out[r].v.head<6>().transpose();
    }
    const int count = std::min(n, start + kChunk) - start;
    if (count > 0) {
      g_theta.middleCols(start, count) = j_g.middleCols(6, count);
      for (int r = 0; r < 7; ++r) {
        o_theta.block(r, start, 1, count) = out[r].v.segment(6, count).transpose();
      }
    }
    if (n == 0) break;
  }
  const Eigen::PartialPivLU<Matrix6> lu(g_x);
  // Implicit function theorem: dx/dtheta = -(dg/dx)^-1 dg/dtheta, dx/dy likewise.
  const Eigen::MatrixXd d_out_d_theta = o_theta - o_x * lu.solve(g_theta);
  result->d_output_d_blocks.resize(binding.blocks.size());
  for (size_t j = 0, k = 0; j < binding.blocks.size(); ++j) {
    const int size = blocks_[static_cast<size_t>(binding.blocks[j])].size();
    result->d_output_d_blocks[j] = d_out_d_theta.middleCols(static_cast<Eigen::Index>(k), size);
    k += static_cast<size_t>(size);
  }
  // d output / d input: tangent eps of y (p + eps_p, R Exp(eps_w)) from the ambient input.
  const Matrix6 g_y = NormalEquationsInputDerivative(y, s_at_x);
  Eigen::Matrix<double, 6, 7> eps_d_input = Eigen::Matrix<double, 6, 7>::Zero();
  eps_d_input.topLeftCorner<3, 3>().setIdentity();
  {
    using Jet4 = ceres::Jet<double, 4>;
    Eigen::Quaternion<Jet4> q_in =
        QuaternionFromXyzw<Jet4>(Jet4(input[3], 0), Jet4(input[4], 1), Jet4(input[5], 2),
                                 Jet4(input[6], 3));
    q_in.normalize();
    const Eigen::Quaternion<Jet4> rel = y.rotation.conjugate().cast<Jet4>() * q_in;
    for (int k = 0; k < 3; ++k) {
      eps_d_input.block<1, 4>(3 + k, 3) = (Jet4(2.0) * rel.vec()(k)).v.transpose();
    }
  }
  result->d_output_d_input = -o_x * lu.solve(g_y * eps_d_input);
  return true;
}

namespace {

// Gauge of G against the sensor offset's rotation: G R^T = P (R U^T)^T for the polar decomposition
// G = P U, so only the symmetric part P of G is seen once the offset rotation is free. This
// residual holds G symmetric (its antisymmetric part, whitened by 1e-4). The data carry no
// information along the gauge, so any weight pins it at zero at the optimum; 1e-4 is of the order
// of the stds of G from a capture, keeping the information matrix well conditioned for the
// covariance.
struct SymmetricGainResidual {
  template <typename T>
  bool operator()(const T* g, T* r) const {
    const T scale(1e4);
    r[0] = (g[1] - g[3]) * scale;
    r[1] = (g[2] - g[6]) * scale;
    r[2] = (g[5] - g[7]) * scale;
    return true;
  }
};

// Gauge of the uniform gain: a uniform gain g scales every measured field by g, and the dipole
// field falls as r^-3, so the tracker reports p g^(-1/3): an isotropic scaling of positions, which a
// polynomial (degree >= 1) or LUT after the group reproduces exactly. With such a term the data do
// not fix the scale of G; this residual holds the mean coil gain trace(G) / 3 at 1, so G reports the
// relative gains and the non-orthogonality (3 G / trace(G) of the truth), which the data do fix.
// The constraint is linear, so one Gauss-Newton step satisfies it exactly (a det G = 1 penalty is
// cubic and upset the fast fold refits of fit/candidates.cc). Weight 1e8: the gauge direction's
// std becomes 1e-8, two orders below the smallest stds of G seen from a capture (1e-6 on the paper
// preset with its true noise; 1e-4 with the default noise), so it does not inflate the reported
// stds.
struct UnitMeanGainResidual {
  template <typename T>
  bool operator()(const T* g, T* r) const {
    r[0] = (g[0] + g[4] + g[8] - T(3)) * T(1e8);
    return true;
  }
};

}  // namespace

void PhysicalGroupTerm::SetFollowingTerms(const std::vector<const ModelTerm*>& later) {
  later_terms_ = later;
}

bool PhysicalGroupTerm::GainScaleHeld() const {
  const Effect* gain = nullptr;
  for (const auto& e : effects_) {
    if (e.kind == PhysicalEffect::kReceiverGain) gain = &e;
  }
  if (gain == nullptr || blocks_[static_cast<size_t>(Block(*gain, kGainMatrix))].fixed) return false;
  switch (gain_scale_) {
    case GainScale::kFree: return false;
    case GainScale::kUnitMean: return true;
    case GainScale::kAuto: break;
  }
  bool absorbed = false;
  for (const ModelTerm* t : later_terms_) absorbed = absorbed || t->AbsorbsIsotropicScaling();
  return absorbed;
}

int PhysicalGroupTerm::AddExtraResiduals(ceres::Problem* problem,
                                         const std::vector<FitStation>& /*inputs*/) {
  const Effect* gain = nullptr;
  const Effect* offset = nullptr;
  for (const auto& e : effects_) {
    if (e.kind == PhysicalEffect::kReceiverGain) gain = &e;
    if (e.kind == PhysicalEffect::kSensorOffset) offset = &e;
  }
  if (gain == nullptr) return 0;
  int added = 0;
  ParameterBlock& g = blocks_[static_cast<size_t>(Block(*gain, kGainMatrix))];
  // Evaluated now, when every term's block settings are applied; Describe() reports it.
  later_absorbs_scaling_ = GainScaleHeld();
  if (later_absorbs_scaling_) {
    problem->AddResidualBlock(
        new ceres::AutoDiffCostFunction<UnitMeanGainResidual, 1, 9>(new UnitMeanGainResidual),
        nullptr, g.values.data());
    ++added;
  }
  if (offset == nullptr) return added;
  if (g.fixed || blocks_[static_cast<size_t>(Block(*offset, kOffsetRotation))].fixed) return added;
  problem->AddResidualBlock(
      new ceres::AutoDiffCostFunction<SymmetricGainResidual, 3, 9>(new SymmetricGainResidual),
      nullptr, g.values.data());
  return added + 1;
}

std::unique_ptr<Correction> PhysicalGroupTerm::ToCorrection() const {
  std::vector<const double*> v;
  for (const auto& b : blocks_) v.push_back(b.values.data());
  return std::make_unique<PhysicalCorrection>(MakeCorrection(v.data()));
}

nlohmann::json PhysicalGroupTerm::Describe() const {
  nlohmann::json effects = nlohmann::json::array();
  for (const auto& e : effects_) {
    nlohmann::json entry = {{"type", PhysicalEffectType(e.kind)}, {"name", e.name}};
    if (e.kind == PhysicalEffect::kReceiverGain) {
      static const char* const kScale[] = {"auto", "free", "unit_mean"};
      entry["gain_scale"] = kScale[static_cast<int>(gain_scale_)];
      // What the fit did: trace G held at 3 (G = relative gains) or the uniform gain estimated.
      entry["unit_mean_gain"] = later_absorbs_scaling_;
    }
    effects.push_back(entry);
  }
  return {{"effects", effects}};
}

// --- start values by search -------------------------------------------------------------------

namespace {

// Linearises every station at the group's current values (effects in `disabled` switched off).
std::vector<SearchStation> LineariseStations(const PhysicalGroupTerm& term,
                                             const std::vector<FitStation>& inputs,
                                             const Eigen::Vector2d& sigmas) {
  std::vector<const double*> v;
  for (const auto& b : term.blocks()) v.push_back(b.values.data());
  PhysicalCorrectionOptions options;
  options.max_iterations = 50;
  const PhysicalCorrection model = term.MakeCorrection(v.data(), options);
  std::vector<SearchStation> out;
  out.reserve(inputs.size());
  for (const FitStation& s : inputs) {
    Rigid3d x;
    // A station without a converged inverse has no meaningful linearisation (its pose is a bounded
    // best guess): left out of the search.
    if (!model.InvertReport(s.reported, &x)) continue;
    const Rigid3d body = model.receiver_from_body() ? x * *model.receiver_from_body() : x;
    Vector6 r;
    Eigen::Matrix<double, 6, 7> d_r;
    WhitenedResidual(ToAmbient(body), s.reference, sigmas, &r, &d_r);
    // g_x and d body / d x at x by Jets over the x tangent.
    Vector9 s_free;
    Matrix96 j_free;
    FreeSpaceSignal(s.reported, &s_free, &j_free);
    Vector3<Jet6> p;
    for (int i = 0; i < 3; ++i) p(i) = Jet6(x.translation(i), i);
    const Eigen::Quaternion<Jet6> q =
        RightPerturbed<Jet6>(x.rotation, Jet6(0.0, 3), Jet6(0.0, 4), Jet6(0.0, 5));
    const Eigen::Matrix3d gain = model.receiver_gain_matrix();
    const Matrix3<Jet6> sig =
        gain.cast<Jet6>() * (q.toRotationMatrix().transpose() * model.field().Field<Jet6>(p));
    const auto sv = Vec<Jet6>(sig);
    Matrix96 j_s;
    for (int e = 0; e < 9; ++e) j_s.row(e) = sv(e).v.transpose();
    const Matrix6 g_x = j_free.transpose() * j_s;
    const Rigid3d off = model.receiver_from_body().value_or(Rigid3d());
    const Vector3<Jet6> p_out = p + q * off.translation.cast<Jet6>();
    const Eigen::Quaternion<Jet6> q_out = q * off.rotation.cast<Jet6>();
    const Jet6 o[7] = {p_out(0), p_out(1), p_out(2), q_out.x(), q_out.y(), q_out.z(), q_out.w()};
    Eigen::Matrix<double, 7, 6> o_x;
    for (int k = 0; k < 7; ++k) o_x.row(k) = o[k].v.transpose();
    // d r / d strength = -d_r o_x g_x^-1 J_y^T vec(G R^T B_unit).
    Eigen::Matrix<double, 9, 9> gain_rt = Eigen::Matrix<double, 9, 9>::Zero();
    const Eigen::Matrix3d grt = gain * x.rotation.toRotationMatrix().transpose();
    for (int c = 0; c < 3; ++c) gain_rt.block<3, 3>(3 * c, 3 * c) = grt;
    SearchStation st;
    st.p = x.translation;
    st.r = r;
    st.k = -(d_r * o_x) * g_x.partialPivLu().solve(j_free.transpose() * gain_rt);
    if (!st.k.allFinite() || !st.r.allFinite()) continue;
    out.push_back(st);
  }
  return out;
}

}  // namespace

bool PhysicalGroupTerm::InitializeLinear(const std::vector<FitStation>& inputs,
                                         const Eigen::Vector2d& noise_sigmas) {
  if (!search_options_.Check()) throw std::invalid_argument("physical terms: bad search options");
  // Effects still to be searched are switched off until their turn.
  disabled_.assign(effects_.size(), false);
  for (size_t i = 0; i < effects_.size(); ++i) {
    const Effect& e = effects_[i];
    auto fixed = [&](int k) { return blocks_[static_cast<size_t>(Block(e, k))].fixed; };
    disabled_[i] = (e.kind == PhysicalEffect::kDipole &&
                    ((e.search_location && !fixed(kDipoleLocation)) ||
                     (!e.strength_given && !fixed(kDipolePolarisability)))) ||
                   (e.kind == PhysicalEffect::kPlane &&
                    ((e.search_plane && !fixed(kPlaneDistance)) ||
                     (!e.strength_given && !fixed(kPlaneAttenuation))));
  }
  for (size_t i = 0; i < effects_.size(); ++i) {
    if (!disabled_[i]) continue;
    if (effects_[i].kind == PhysicalEffect::kDipole) {
      SearchDipole(effects_[i], inputs, noise_sigmas);
    } else {
      SearchPlane(effects_[i], inputs, noise_sigmas);
    }
    disabled_[i] = false;
  }
  disabled_.clear();
  RefineAlone(inputs, noise_sigmas);
  // Start on the gauge (trace G = 3): the later terms initialise on what the group then leaves.
  if (GainScaleHeld()) {
    for (const auto& e : effects_) {
      if (e.kind != PhysicalEffect::kReceiverGain) continue;
      auto& g = blocks_[static_cast<size_t>(Block(e, kGainMatrix))].values;
      const double mean = (g[0] + g[4] + g[8]) / 3.0;
      if (mean > 0.0) {
        for (double& x : g) x /= mean;
      }
    }
  }
  return true;
}

namespace {

// One station's whitened residual through the group alone (for RefineAlone).
class GroupStationCost : public ceres::CostFunction {
 public:
  GroupStationCost(const PhysicalGroupTerm* term, const StationBinding* binding,
                   const FitStation& station, const Eigen::Vector2d& sigmas)
      : term_(term), binding_(binding), station_(station), sigmas_(sigmas) {
    set_num_residuals(6);
    for (int b : binding->blocks) {
      mutable_parameter_block_sizes()->push_back(term->blocks()[static_cast<size_t>(b)].size());
    }
  }
  bool Evaluate(double const* const* parameters, double* residuals,
                double** jacobians) const override {
    TermEvaluation eval;
    if (!term_->Evaluate(*binding_, parameters, ToAmbient(station_.reported), jacobians != nullptr,
                         &eval)) {
      return false;
    }
    Vector6 r;
    Eigen::Matrix<double, 6, 7> d_r;
    WhitenedResidual(eval.output, station_.reference, sigmas_, &r, &d_r);
    Eigen::Map<Vector6> out(residuals);
    out = r;
    if (jacobians == nullptr) return true;
    for (size_t b = 0; b < binding_->blocks.size(); ++b) {
      if (jacobians[b] == nullptr) continue;
      const auto& d = eval.d_output_d_blocks[b];
      Eigen::Map<Eigen::Matrix<double, 6, Eigen::Dynamic, Eigen::RowMajor>>(jacobians[b], 6,
                                                                            d.cols()) = d_r * d;
    }
    return true;
  }

 private:
  const PhysicalGroupTerm* term_;
  const StationBinding* binding_;
  FitStation station_;
  Eigen::Vector2d sigmas_;
};

}  // namespace

void PhysicalGroupTerm::RefineAlone(const std::vector<FitStation>& inputs,
                                    const Eigen::Vector2d& sigmas) {
  // The group is the first term of its model (physical terms come first), so its own fit to the
  // references is the start the joint problem needs: the explicit terms after it then initialise
  // on what it leaves, and the joint solve only polishes (a chain with a LUT converges in a few
  // iterations instead of ~30 sparse factorisations). Robust (Cauchy, 5 sigma) so hemisphere flips
  // do not drag the start; priors and the joint loss act in the joint solve.
  const StationBinding binding = Bind(AmbientPose::Zero());
  if (binding.blocks.empty() || inputs.empty()) return;
  ceres::Problem problem;
  for (int b : binding.blocks) {
    ParameterBlock& block = blocks_[static_cast<size_t>(b)];
    problem.AddParameterBlock(block.values.data(), block.size());
    if (block.make_manifold) problem.SetManifold(block.values.data(), block.make_manifold());
    for (int i = 0; i < block.size(); ++i) {
      if (!block.lower.empty() && std::isfinite(block.lower[static_cast<size_t>(i)])) {
        problem.SetParameterLowerBound(block.values.data(), i, block.lower[static_cast<size_t>(i)]);
      }
      if (!block.upper.empty() && std::isfinite(block.upper[static_cast<size_t>(i)])) {
        problem.SetParameterUpperBound(block.values.data(), i, block.upper[static_cast<size_t>(i)]);
      }
    }
  }
  std::vector<double*> pointers;
  for (int b : binding.blocks) pointers.push_back(blocks_[static_cast<size_t>(b)].values.data());
  for (const FitStation& s : inputs) {
    problem.AddResidualBlock(new GroupStationCost(this, &binding, s, sigmas),
                             new ceres::CauchyLoss(5.0), pointers);
  }
  AddExtraResiduals(&problem, inputs);
  ceres::Solver::Options options;
  options.max_num_iterations = 50;
  options.linear_solver_type = ceres::DENSE_QR;
  options.function_tolerance = 1e-10;
  ceres::Solver::Summary summary;
  ceres::Solve(options, &problem, &summary);
}

void PhysicalGroupTerm::SearchDipole(const Effect& e, const std::vector<FitStation>& inputs,
                                     const Eigen::Vector2d& sigmas) {
  const std::vector<SearchStation> stations = LineariseStations(*this, inputs, sigmas);
  ParameterBlock& location = blocks_[static_cast<size_t>(Block(e, kDipoleLocation))];
  ParameterBlock& strength = blocks_[static_cast<size_t>(Block(e, kDipolePolarisability))];
  const double min_distance = search_options_.min_station_distance_m;
  auto score_at = [&](const Eigen::Vector3d& l) {
    if (l.norm() < min_distance) return Score{};
    const Eigen::Matrix3d d_l = DipoleCoupling<double>(l);
    return ScoreCandidate(stations, [&](const Eigen::Vector3d& p, Eigen::Matrix3d* b) {
      const Eigen::Vector3d d = p - l;
      if (d.squaredNorm() < min_distance * min_distance) return false;
      *b = DipoleCoupling<double>(d) * d_l;
      return true;
    });
  };
  Eigen::Vector3d best_location(location.values[0], location.values[1], location.values[2]);
  Score best = score_at(best_location);
  if (e.search_location && !location.fixed) {
    const Eigen::Vector3d lo = data_min_.array() - search_options_.margin_m;
    const Eigen::Vector3d hi = data_max_.array() + search_options_.margin_m;
    const double h = search_options_.dipole_spacing_m;
    const Eigen::Vector3i counts = ((hi - lo) / h).array().ceil().cast<int>() + 1;
    std::vector<std::pair<double, Eigen::Vector3d>> ranked;
    for (int ix = 0; ix < counts.x(); ++ix) {
      for (int iy = 0; iy < counts.y(); ++iy) {
        for (int iz = 0; iz < counts.z(); ++iz) {
          const Eigen::Vector3d l = lo + h * Eigen::Vector3d(ix, iy, iz);
          const Score s = score_at(l);
          if (s.reduction > 0.0) ranked.emplace_back(s.reduction, l);
        }
      }
    }
    const size_t keep = std::min(ranked.size(), static_cast<size_t>(search_options_.refine_candidates));
    std::partial_sort(ranked.begin(), ranked.begin() + static_cast<long>(keep), ranked.end(),
                      [](const auto& a, const auto& b) { return a.first > b.first; });
    best = Score{};
    for (size_t c = 0; c < keep; ++c) {
      const Eigen::Vector3d start = ranked[c].second;
      const std::vector<double> refined = PatternSearch(
          {start.x(), start.y(), start.z()}, {h / 2, h / 2, h / 2}, 1e-3 / h,
          [&](const std::vector<double>& x) {
            return -score_at(Eigen::Vector3d(x[0], x[1], x[2])).reduction;
          });
      const Eigen::Vector3d l(refined[0], refined[1], refined[2]);
      const Score s = score_at(l);
      if (s.reduction > best.reduction) {
        best = s;
        best_location = l;
      }
    }
    location.values = {best_location.x(), best_location.y(), best_location.z()};
  }
  if (!e.strength_given && !strength.fixed && best.reduction > 0.0) {
    strength.values = {best.strength};
  }
}

void PhysicalGroupTerm::SearchPlane(const Effect& e, const std::vector<FitStation>& inputs,
                                    const Eigen::Vector2d& sigmas) {
  const std::vector<SearchStation> stations = LineariseStations(*this, inputs, sigmas);
  ParameterBlock& distance = blocks_[static_cast<size_t>(Block(e, kPlaneDistance))];
  ParameterBlock& normal_block = blocks_[static_cast<size_t>(Block(e, kPlaneNormal))];
  ParameterBlock& attenuation = blocks_[static_cast<size_t>(Block(e, kPlaneAttenuation))];
  auto score_at = [&](const Eigen::Vector3d& n, double d) {
    const Eigen::Vector3d image = 2.0 * d * n;
    if (image.norm() < 1e-3) return Score{};
    return ScoreCandidate(stations, [&](const Eigen::Vector3d& p, Eigen::Matrix3d* b) {
      *b = PlaneImageField<double>(1.0, d * n, n, 1.0, p);
      return true;
    });
  };
  Eigen::Vector3d best_normal(normal_block.values[0], normal_block.values[1],
                              normal_block.values[2]);
  best_normal.normalize();
  double best_distance = distance.values[0];
  Score best = score_at(best_normal, best_distance);
  if (e.search_plane && !distance.fixed) {
    std::vector<Eigen::Vector3d> normals = {best_normal};
    // A plane given by its normal alone keeps it; otherwise normals over the half sphere.
    if (!e.normal_given && !normal_block.fixed) {
      normals = HalfSphereDirections(search_options_.plane_normals);
    }
    std::vector<std::tuple<double, Eigen::Vector3d, double>> ranked;
    const double step = search_options_.plane_distance_step_m;
    const double reach = 3.0 * std::max(1.0, search_options_.margin_m);
    for (const Eigen::Vector3d& n : normals) {
      double a = std::numeric_limits<double>::infinity(), b = -a;
      for (const auto& s : stations) {
        a = std::min(a, s.p.dot(n));
        b = std::max(b, s.p.dot(n));
      }
      for (double offset = step; offset <= reach; offset += step) {
        for (double d : {b + offset, a - offset}) {
          const Score s = score_at(n, d);
          if (s.reduction > 0.0) ranked.emplace_back(s.reduction, n, d);
        }
      }
    }
    const size_t keep = std::min(ranked.size(), static_cast<size_t>(search_options_.refine_candidates));
    std::partial_sort(ranked.begin(), ranked.begin() + static_cast<long>(keep), ranked.end(),
                      [](const auto& x, const auto& y) { return std::get<0>(x) > std::get<0>(y); });
    best = Score{};
    const bool refine_normal = normals.size() > 1;
    for (size_t c = 0; c < keep; ++c) {
      const Eigen::Vector3d n0 = std::get<1>(ranked[c]);
      Eigen::Vector3d t1, t2;
      TangentBasis(n0, &t1, &t2);
      auto unpack = [&](const std::vector<double>& x) {
        return std::make_pair(
            Eigen::Vector3d(refine_normal ? Eigen::Vector3d(n0 + x[1] * t1 + x[2] * t2).normalized()
                                          : n0),
            x[0]);
      };
      const std::vector<double> refined = PatternSearch(
          {std::get<2>(ranked[c]), 0.0, 0.0}, {step / 2, 0.05, 0.05}, 1e-2,
          [&](const std::vector<double>& x) {
            const auto [n, d] = unpack(x);
            return -score_at(n, d).reduction;
          });
      const auto [n, d] = unpack(refined);
      const Score s = score_at(n, d);
      if (s.reduction > best.reduction) {
        best = s;
        best_normal = n;
        best_distance = d;
      }
    }
    distance.values = {best_distance};
    if (!normal_block.fixed) normal_block.values = {best_normal.x(), best_normal.y(), best_normal.z()};
  }
  if (!e.strength_given && !attenuation.fixed && best.reduction > 0.0) {
    attenuation.values = {std::clamp(best.strength, -0.99, 0.99)};
  }
}

void RegisterPhysicalTerms(TermRegistry* registry) {
  for (PhysicalEffect effect : {PhysicalEffect::kSensorOffset, PhysicalEffect::kReceiverGain,
                                PhysicalEffect::kDipole, PhysicalEffect::kPlane,
                                PhysicalEffect::kNearField}) {
    registry->Register(PhysicalEffectType(effect), [effect](const YamlMapReader& reader) {
      return PhysicalGroupTerm::FromYaml(effect, reader);
    });
  }
}

}  // namespace trackcal::fit
