#include "core/correction.h"

#include <algorithm>
#include <cmath>
#include <stdexcept>

#include "core/lut.h"
#include "core/physical_correction.h"
#include "core/polynomial.h"

namespace trackcal {

void Correction::ApplyBatch(size_t n, const double* positions, const double* quaternions_xyzw,
                            double* out_positions, double* out_quaternions_xyzw,
                            uint8_t* extrapolated) const {
  ApplyPerPose(n, positions, quaternions_xyzw, out_positions, out_quaternions_xyzw, extrapolated,
               nullptr);
}

void Correction::ApplyBatchWithStatus(size_t n, const double* positions,
                                      const double* quaternions_xyzw, double* out_positions,
                                      double* out_quaternions_xyzw, uint8_t* extrapolated,
                                      CorrectionStatus* status) const {
  ApplyBatch(n, positions, quaternions_xyzw, out_positions, out_quaternions_xyzw, extrapolated);
  if (status != nullptr) std::fill(status, status + n, CorrectionStatus::kConverged);
}

void Correction::ApplyPerPose(size_t n, const double* positions, const double* quaternions_xyzw,
                              double* out_positions, double* out_quaternions_xyzw,
                              uint8_t* extrapolated, CorrectionStatus* status) const {
  for (size_t i = 0; i < n; ++i) {
    const Rigid3d reported(QuaternionFromXyzwArray(quaternions_xyzw + 4 * i),
                           Eigen::Vector3d(positions[3 * i], positions[3 * i + 1],
                                           positions[3 * i + 2]));
    const CorrectedPose out = Apply(reported);
    QuaternionToXyzwArray(out.pose.rotation, out_quaternions_xyzw + 4 * i);
    out_positions[3 * i] = out.pose.translation.x();
    out_positions[3 * i + 1] = out.pose.translation.y();
    out_positions[3 * i + 2] = out.pose.translation.z();
    if (extrapolated != nullptr) extrapolated[i] = out.extrapolated ? 1 : 0;
    if (status != nullptr) status[i] = out.status;
  }
}

const char* CorrectionStatusName(CorrectionStatus status) {
  switch (status) {
    case CorrectionStatus::kConverged: return "converged";
    case CorrectionStatus::kAmbiguous: return "ambiguous";
    case CorrectionStatus::kNotConverged: return "not_converged";
  }
  return "unknown";
}

std::string ExtrapolationPolicyName(ExtrapolationPolicy policy) {
  switch (policy) {
    case ExtrapolationPolicy::kClamp:
      return "clamp";
    case ExtrapolationPolicy::kFade:
      return "fade";
    case ExtrapolationPolicy::kLinear:
      return "linear";
  }
  throw std::logic_error("unknown ExtrapolationPolicy");
}

ExtrapolationPolicy ExtrapolationPolicyFromName(const std::string& name) {
  if (name == "clamp") return ExtrapolationPolicy::kClamp;
  if (name == "fade") return ExtrapolationPolicy::kFade;
  if (name == "linear") return ExtrapolationPolicy::kLinear;
  throw std::invalid_argument("extrapolation: unknown policy \"" + name +
                              "\"; expected \"clamp\", \"fade\" or \"linear\"");
}

void CalibratedVolume::Check() const {
  static const char* kAxis[3] = {"x", "y", "z"};
  if (!min.allFinite()) throw std::invalid_argument("calibrated volume: min must be finite");
  if (!max.allFinite()) throw std::invalid_argument("calibrated volume: max must be finite");
  for (int k = 0; k < 3; ++k) {
    if (!(min[k] < max[k])) {
      throw std::invalid_argument(std::string("calibrated volume: empty volume: min.") + kAxis[k] +
                                  " = " + std::to_string(min[k]) + " is not below max." +
                                  kAxis[k] + " = " + std::to_string(max[k]));
    }
  }
  if (extrapolation == ExtrapolationPolicy::kFade &&
      !(std::isfinite(fade_distance) && fade_distance > 0.0)) {
    throw std::invalid_argument(
        "calibrated volume: fade_distance must be positive and finite for the fade policy, got " +
        std::to_string(fade_distance));
  }
  if (!(std::isfinite(fade_distance) && fade_distance >= 0.0)) {
    throw std::invalid_argument("calibrated volume: fade_distance must be >= 0 and finite");
  }
  if (!(std::isfinite(linear_reach) && linear_reach >= 0.0)) {
    throw std::invalid_argument("calibrated volume: linear_reach must be >= 0 and finite, got " +
                                std::to_string(linear_reach));
  }
}

double CalibratedVolume::Weight(double distance) const {
  if (extrapolation != ExtrapolationPolicy::kFade) return 1.0;
  const double s = std::clamp(distance / fade_distance, 0.0, 1.0);
  return 1.0 - s * s * (3.0 - 2.0 * s);
}

CorrectionChain::CorrectionChain(const CorrectionChain& other) : volume_(other.volume_) {
  for (const auto& t : other.terms_) terms_.push_back(t->Clone());
}

CorrectionChain& CorrectionChain::operator=(const CorrectionChain& other) {
  if (this != &other) {
    CorrectionChain copy(other);
    *this = std::move(copy);
  }
  return *this;
}

void CorrectionChain::Append(std::unique_ptr<Correction> term) {
  if (term == nullptr) throw std::invalid_argument("CorrectionChain::Append: null correction");
  terms_.push_back(std::move(term));
}

void CorrectionChain::SetVolume(const CalibratedVolume& volume) {
  volume.Check();
  volume_ = volume;
}

CorrectedPose CorrectionChain::ApplyTerms(const Rigid3d& pose) const {
  CorrectedPose out{pose, false};
  for (const auto& term : terms_) {
    const CorrectedPose step = term->Apply(out.pose);
    out.pose = step.pose;
    out.extrapolated = out.extrapolated || step.extrapolated;
    out.status = std::max(out.status, step.status);
  }
  return out;
}

namespace {

// A run's correction at one input position as 6 numbers: the position offset p_out - p and the
// vector part of q_e = q_out * conj(q) (scalar part non-negative).
using RunCorrection = Eigen::Matrix<double, 6, 1>;

RunCorrection CorrectionOf(const Rigid3d& input, const Rigid3d& output) {
  RunCorrection c;
  c.head<3>() = output.translation - input.translation;
  c.tail<3>() = VectorPart<double>((output.rotation * input.rotation.conjugate()).normalized());
  return c;
}

}  // namespace

CorrectedPose CorrectionChain::ApplyGuardedRun(size_t begin, size_t end,
                                               const Rigid3d& input) const {
  CorrectedPose out{input, false};
  const Eigen::Vector3d& p = input.translation;
  const Eigen::Quaterniond& q = input.rotation;
  const Eigen::Vector3d p_boundary = volume_->Nearest(p);
  const bool inside = volume_->Contains(p);
  // The run's terms in order from `from`; only the first evaluation's flags count (the linear
  // policy's extra evaluations lie inside the box).
  auto run = [&](const Rigid3d& from, CorrectedPose* flags) {
    Rigid3d pose = from;
    for (size_t t = begin; t < end; ++t) {
      const CorrectedPose step = terms_[t]->Apply(pose);
      pose = step.pose;
      if (flags != nullptr) {
        flags->extrapolated = flags->extrapolated || step.extrapolated;
        flags->status = std::max(flags->status, step.status);
      }
    }
    return pose;
  };
  const Rigid3d pose = run(inside ? input : Rigid3d(q, p_boundary), &out);
  if (inside) {
    out.pose = pose;
    return out;
  }
  if (volume_->extrapolation == ExtrapolationPolicy::kLinear) {
    // First order from the box: per axis on which p is outside, the derivative of the correction
    // along the outward direction by the one-sided second-order difference (3 f(0) - 4 f(-h) +
    // f(-2h)) / 2h on points inside the box (exact for a correction linear along the axis, as a
    // LUT's last cell is when 2h stays in it; O(h^2) for a polynomial), times the distance out on
    // that axis. The step along the displacement is capped at linear_reach.
    const RunCorrection c0 = CorrectionOf(Rigid3d(q, p_boundary), pose);
    const Eigen::Vector3d outward = p - p_boundary;
    const double distance = outward.norm();
    const double scale = distance > volume_->linear_reach ? volume_->linear_reach / distance : 1.0;
    RunCorrection c = c0;
    for (int k = 0; k < 3; ++k) {
      if (outward[k] == 0.0) continue;
      // 1 mm (far below the explicit terms' length scales, far above rounding: differences of
      // ~1e-2 m corrections carry ~1e-17 m rounding, 1e-14 relative in the derivative), and at
      // most a tenth of the box so that both points stay inside a thin box.
      const double h = std::min(1e-3, 0.1 * (volume_->max[k] - volume_->min[k]));
      const double sign = outward[k] > 0.0 ? 1.0 : -1.0;
      Eigen::Vector3d x1 = p_boundary, x2 = p_boundary;
      x1[k] -= sign * h;
      x2[k] -= 2.0 * sign * h;
      const RunCorrection c1 = CorrectionOf(Rigid3d(q, x1), run(Rigid3d(q, x1), nullptr));
      const RunCorrection c2 = CorrectionOf(Rigid3d(q, x2), run(Rigid3d(q, x2), nullptr));
      const RunCorrection slope = (3.0 * c0 - 4.0 * c1 + c2) / (2.0 * h);  // per metre outward
      c += slope * (scale * std::abs(outward[k]));
    }
    out.pose.translation = p + c.head<3>();
    out.pose.rotation = QuaternionFromVectorPart<double>(Eigen::Vector3d(c.tail<3>())) * q;
    return out;
  }
  // Transfer the boundary correction to the actual pose.
  const double weight = volume_->Weight((p - p_boundary).norm());
  const Eigen::Vector3d position_error = pose.translation - p_boundary;
  out.pose.translation = p + weight * position_error;
  if (weight == 1.0) {
    out.pose.rotation = pose.rotation;
  } else {
    // q_e = q_out * conj(q); normalised so that a slightly non-unit input does not scale it.
    const Eigen::Quaterniond q_e = (pose.rotation * q.conjugate()).normalized();
    const Eigen::Vector3d v = weight * VectorPart(q_e);
    out.pose.rotation = QuaternionFromVectorPart<double>(v) * q;
  }
  return out;
}

CorrectedPose CorrectionChain::Apply(const Rigid3d& reported) const {
  if (!volume_.has_value() || volume_->Contains(reported.translation)) return ApplyTerms(reported);
  // Outside: unguarded (physical) terms at the actual pose, each run of guarded terms through the
  // volume's guard at its own input.
  CorrectedPose out{reported, true};
  size_t t = 0;
  while (t < terms_.size()) {
    CorrectedPose step;
    if (!terms_[t]->GuardedByVolume()) {
      step = terms_[t]->Apply(out.pose);
      ++t;
    } else {
      size_t end = t;
      while (end < terms_.size() && terms_[end]->GuardedByVolume()) ++end;
      step = ApplyGuardedRun(t, end, out.pose);
      t = end;
    }
    out.pose = step.pose;
    out.status = std::max(out.status, step.status);
  }
  return out;
}

void CorrectionChain::ApplyBatch(size_t n, const double* positions,
                                 const double* quaternions_xyzw, double* out_positions,
                                 double* out_quaternions_xyzw, uint8_t* extrapolated) const {
  ApplyBatchWithStatus(n, positions, quaternions_xyzw, out_positions, out_quaternions_xyzw,
                       extrapolated, nullptr);
}

void CorrectionChain::ApplyBatchWithStatus(size_t n, const double* positions,
                                           const double* quaternions_xyzw, double* out_positions,
                                           double* out_quaternions_xyzw, uint8_t* extrapolated,
                                           CorrectionStatus* status) const {
  // Chunks whose reported positions are all inside the volume (the normal case) go through each
  // term's batch kernel in turn, in place on the output; a chunk with a pose outside takes the
  // per-pose path, which handles clamp and fade.
  constexpr size_t kChunk = 256;
  uint8_t term_flags[kChunk];
  CorrectionStatus term_status[kChunk];
  for (size_t start = 0; start < n; start += kChunk) {
    const size_t count = std::min(kChunk, n - start);
    const double* p_in = positions + 3 * start;
    const double* q_in = quaternions_xyzw + 4 * start;
    double* p_out = out_positions + 3 * start;
    double* q_out = out_quaternions_xyzw + 4 * start;
    uint8_t* flags = extrapolated == nullptr ? nullptr : extrapolated + start;
    CorrectionStatus* chunk_status = status == nullptr ? nullptr : status + start;
    bool all_inside = true;
    if (volume_.has_value()) {
      for (size_t i = 0; i < count && all_inside; ++i) {
        all_inside = volume_->Contains(Eigen::Vector3d(p_in[3 * i], p_in[3 * i + 1], p_in[3 * i + 2]));
      }
    }
    if (!all_inside) {
      ApplyPerPose(count, p_in, q_in, p_out, q_out, flags, chunk_status);
      continue;
    }
    if (terms_.empty()) {
      std::copy(p_in, p_in + 3 * count, p_out);
      std::copy(q_in, q_in + 4 * count, q_out);
    }
    if (flags != nullptr) std::fill(flags, flags + count, uint8_t{0});
    if (chunk_status != nullptr) {
      std::fill(chunk_status, chunk_status + count, CorrectionStatus::kConverged);
    }
    for (size_t t = 0; t < terms_.size(); ++t) {
      // The first term reads the inputs; later terms correct the previous output in place.
      const double* p_from = t == 0 ? p_in : p_out;
      const double* q_from = t == 0 ? q_in : q_out;
      if (chunk_status == nullptr) {
        terms_[t]->ApplyBatch(count, p_from, q_from, p_out, q_out, term_flags);
      } else {
        terms_[t]->ApplyBatchWithStatus(count, p_from, q_from, p_out, q_out, term_flags,
                                        term_status);
        for (size_t i = 0; i < count; ++i) {
          chunk_status[i] = std::max(chunk_status[i], term_status[i]);
        }
      }
      if (flags != nullptr) {
        for (size_t i = 0; i < count; ++i) flags[i] |= term_flags[i];
      }
    }
  }
}

nlohmann::json CorrectionChain::ToJson() const {
  nlohmann::json terms = nlohmann::json::array();
  for (const auto& t : terms_) terms.push_back(t->ToJson());
  return {{"type", kTypeName}, {"corrections", terms}};
}

std::unique_ptr<Correction> CorrectionChain::Clone() const {
  return std::make_unique<CorrectionChain>(*this);
}

CorrectionRegistry& CorrectionRegistry::Global() {
  static CorrectionRegistry* registry = [] {
    auto* r = new CorrectionRegistry();
    r->Register(PolynomialCorrection::kTypeName, &PolynomialCorrection::FromJson);
    r->Register(TrilinearLutCorrection::kTypeName, &TrilinearLutCorrection::FromJson);
    r->Register(PhysicalCorrection::kTypeName, &PhysicalCorrection::FromJson);
    return r;
  }();
  return *registry;
}

void CorrectionRegistry::Register(const std::string& type_name, CorrectionParser parser) {
  if (type_name.empty()) throw std::invalid_argument("CorrectionRegistry: empty type name");
  if (!parser) throw std::invalid_argument("CorrectionRegistry: null parser for " + type_name);
  std::lock_guard<std::mutex> lock(mutex_);
  for (const auto& [name, unused] : parsers_) {
    if (name == type_name) {
      throw std::invalid_argument("CorrectionRegistry: type \"" + type_name +
                                  "\" is already registered");
    }
  }
  parsers_.emplace_back(type_name, std::move(parser));
}

bool CorrectionRegistry::Contains(const std::string& type_name) const {
  std::lock_guard<std::mutex> lock(mutex_);
  for (const auto& [name, unused] : parsers_) {
    if (name == type_name) return true;
  }
  return false;
}

std::vector<std::string> CorrectionRegistry::TypeNames() const {
  std::lock_guard<std::mutex> lock(mutex_);
  std::vector<std::string> names;
  for (const auto& [name, unused] : parsers_) names.push_back(name);
  return names;
}

std::unique_ptr<Correction> CorrectionRegistry::Parse(const nlohmann::json& value,
                                                      const std::string& source,
                                                      const std::string& path) const {
  JsonObjectReader reader(value, source, path);
  const std::string type = reader.String("type");
  CorrectionParser parser;
  std::string known;
  {
    std::lock_guard<std::mutex> lock(mutex_);
    for (const auto& [name, p] : parsers_) {
      known += (known.empty() ? "\"" : ", \"") + name + "\"";
      if (name == type) parser = p;
    }
  }
  if (!parser) reader.Fail("type", "unknown correction type \"" + type + "\"; known: " + known);
  std::unique_ptr<Correction> correction = parser(reader);
  reader.CheckNoUnknownKeys();
  return correction;
}

}  // namespace trackcal
