// Runtime corrections: a correction maps a reported pose (transmitter_from_receiver, as the tracker
// reported it) to a corrected pose. Concrete types: PolynomialCorrection (core/polynomial.h),
// TrilinearLutCorrection (core/lut.h), PhysicalCorrection (core/physical_correction.h); other
// types can be added through the registry below.
//
// A CorrectionChain applies its terms in order, each to the output of the previous one, and guards its
// explicit terms (polynomial, LUT: fits that only interpolate their data) with the calibrated volume:
// an axis-aligned box in *reported* position outside which no such term is evaluated far from its
// data. For a report outside the box, each run of consecutive guarded terms is evaluated at the
// nearest point of the box to its input and the resulting correction (position offset and rotation
// q_e) is transferred to the actual pose: continued to first order from the box point (`linear`, the
// default: value plus the run's one-sided derivative times the distance, the distance capped at
// `linear_reach`), held (`clamp`) or scaled down to identity over `fade_distance` (`fade`). Terms
// that are not guarded (a physical model, whose field equations hold outside the data as well as
// inside) are applied at the actual pose. Such poses are flagged `extrapolated`.
#pragma once

#include <Eigen/Core>
#include <cstddef>
#include <cstdint>
#include <functional>
#include <limits>
#include <memory>
#include <mutex>
#include <nlohmann/json.hpp>
#include <optional>
#include <string>
#include <vector>

#include "core/json_reader.h"
#include "core/pose.h"

namespace trackcal {

// How a term that inverts a model (the physical correction, core/physical_correction.h) arrived at
// its pose. Terms without an inverse always report kConverged. Ordered by severity: a chain reports
// the worst status of its terms.
enum class CorrectionStatus : uint8_t {
  kConverged = 0,     // a unique true pose was found
  kAmbiguous = 1,     // converged, but another true pose explains the same report (a fold of the
                      // model near a strong object) or report noise is amplified beyond use
  kNotConverged = 2,  // no true pose found: the pose is a bounded best guess (or the report itself)
};
// "converged", "ambiguous", "not_converged".
const char* CorrectionStatusName(CorrectionStatus status);

struct CorrectedPose {
  Rigid3d pose;               // corrected transmitter_from_receiver
  bool extrapolated = false;  // the reported position was outside the calibrated volume
  CorrectionStatus status = CorrectionStatus::kConverged;  // of a model inverse (see above)
};

class Correction {
 public:
  virtual ~Correction() = default;

  // The "type" field of the correction in the calibration file ("polynomial", "trilinear_lut", ...).
  virtual std::string TypeName() const = 0;

  // Corrects one pose. `extrapolated` is set when the term had to leave its own domain (a LUT queried
  // outside its grid); a polynomial has no domain of its own and never sets it (the chain's volume
  // guards it).
  virtual CorrectedPose Apply(const Rigid3d& reported) const = 0;

  // Corrects n poses given as raw row-major arrays: positions n x 3 [m], quaternions n x 4 (x, y, z, w).
  // Outputs may alias the inputs (in-place correction). `extrapolated` (n entries) may be null.
  virtual void ApplyBatch(size_t n, const double* positions, const double* quaternions_xyzw,
                          double* out_positions, double* out_quaternions_xyzw,
                          uint8_t* extrapolated) const;

  // As ApplyBatch, and each pose's status (n entries; may be null). The default runs ApplyBatch and
  // reports kConverged: a term whose Apply can report another status (a model inverse) overrides
  // it.
  virtual void ApplyBatchWithStatus(size_t n, const double* positions,
                                    const double* quaternions_xyzw, double* out_positions,
                                    double* out_quaternions_xyzw, uint8_t* extrapolated,
                                    CorrectionStatus* status) const;

  // The correction's entry of the file's "corrections" array, including "type".
  virtual nlohmann::json ToJson() const = 0;

  virtual std::unique_ptr<Correction> Clone() const = 0;

  // Whether a chain's calibrated volume guards this term (see above). True for terms that only
  // interpolate their data; a physical model returns false and is applied at the actual pose.
  virtual bool GuardedByVolume() const { return true; }

 protected:
  // Pose by pose through Apply (the default ApplyBatch); `extrapolated` and `status` may be null.
  void ApplyPerPose(size_t n, const double* positions, const double* quaternions_xyzw,
                    double* out_positions, double* out_quaternions_xyzw, uint8_t* extrapolated,
                    CorrectionStatus* status) const;
};

enum class ExtrapolationPolicy {
  kClamp,   // "clamp": evaluate at the nearest point of the volume and apply that correction in full
  kFade,    // "fade": as clamp, scaled to zero (identity) over fade_distance from the volume
  kLinear,  // "linear": the nearest point's correction plus its first-order change out to the
            // actual position (one-sided derivatives at the box), the distance capped at linear_reach
};

std::string ExtrapolationPolicyName(ExtrapolationPolicy policy);
// Throws std::invalid_argument for names other than "clamp", "fade" and "linear".
ExtrapolationPolicy ExtrapolationPolicyFromName(const std::string& name);

// The axis-aligned box of reported positions the calibration data covered, and what to do outside.
struct CalibratedVolume {
  Eigen::Vector3d min = Eigen::Vector3d::Zero();  // lower corner [m], transmitter frame
  Eigen::Vector3d max = Eigen::Vector3d::Zero();  // upper corner [m], transmitter frame
  // Behaviour outside the box. `linear` by default: holding an explicit fit's edge value (clamp)
  // costs 4-11x the noise floor on the paper preset's stations outside the calibration box
  // (docs/calibration-file.md).
  ExtrapolationPolicy extrapolation = ExtrapolationPolicy::kLinear;
  double fade_distance = 0.0;  // [m] distance from the box at which a `fade` reaches identity
  // [m] for `linear`: the first-order continuation follows the distance from the box up to this
  // reach and is held beyond it, so a steep edge slope cannot grow without bound far from the data.
  static constexpr double kDefaultLinearReach = 0.1;
  double linear_reach = kDefaultLinearReach;

  // Throws std::invalid_argument naming the field: non-finite corners, min >= max on an axis (an
  // empty volume), fade without a positive finite fade_distance, a negative or non-finite
  // linear_reach.
  void Check() const;

  bool Contains(const Eigen::Vector3d& p) const {
    return (p.array() >= min.array()).all() && (p.array() <= max.array()).all();
  }
  Eigen::Vector3d Nearest(const Eigen::Vector3d& p) const { return p.cwiseMax(min).cwiseMin(max); }

  // Weight of the correction at distance d >= 0 outside the box: 1 for clamp; for fade the smoothstep
  // 1 - s^2 (3 - 2 s) of s = d / fade_distance clipped to [0, 1], continuous with zero slope at the box
  // and at fade_distance.
  double Weight(double distance) const;
};

class CorrectionChain : public Correction {
 public:
  CorrectionChain() = default;
  CorrectionChain(const CorrectionChain& other);
  CorrectionChain& operator=(const CorrectionChain& other);
  CorrectionChain(CorrectionChain&&) = default;
  CorrectionChain& operator=(CorrectionChain&&) = default;

  static constexpr const char* kTypeName = "chain";
  std::string TypeName() const override { return kTypeName; }

  void Append(std::unique_ptr<Correction> term);
  size_t size() const { return terms_.size(); }
  const Correction& term(size_t i) const { return *terms_.at(i); }

  // Without a volume the terms are applied everywhere (and only a term's own domain flags poses).
  void SetVolume(const CalibratedVolume& volume);
  void ClearVolume() { volume_.reset(); }
  const std::optional<CalibratedVolume>& volume() const { return volume_; }

  CorrectedPose Apply(const Rigid3d& reported) const override;
  void ApplyBatch(size_t n, const double* positions, const double* quaternions_xyzw,
                  double* out_positions, double* out_quaternions_xyzw,
                  uint8_t* extrapolated) const override;
  // The worst status of the terms per pose (as Apply).
  void ApplyBatchWithStatus(size_t n, const double* positions, const double* quaternions_xyzw,
                            double* out_positions, double* out_quaternions_xyzw,
                            uint8_t* extrapolated, CorrectionStatus* status) const override;
  // {"type": "chain", "corrections": [...]} (the file stores the terms and the volume separately).
  nlohmann::json ToJson() const override;
  std::unique_ptr<Correction> Clone() const override;

 private:
  CorrectedPose ApplyTerms(const Rigid3d& pose) const;
  // Terms [begin, end) (all guarded) applied to `input` outside the volume's guard: at the nearest
  // point of the box when the input position lies outside it, the correction transferred.
  CorrectedPose ApplyGuardedRun(size_t begin, size_t end, const Rigid3d& input) const;

  std::vector<std::unique_ptr<Correction>> terms_;
  std::optional<CalibratedVolume> volume_;
};

// Parses one entry of the "corrections" array. The reader is positioned on the entry (its path is
// e.g. "$.corrections[1]"); the parser must read every field it accepts (including "type"), so the
// caller's CheckNoUnknownKeys() rejects the rest, and throw through reader.Fail() on bad values.
using CorrectionParser = std::function<std::unique_ptr<Correction>(const JsonObjectReader& reader)>;

// Correction types by name. The built-in types (polynomial, trilinear_lut, physical) are registered on
// first use of Global(), so every reader of calibration files (server, Python) knows them; further
// types can be registered at start-up without touching the file reader.
class CorrectionRegistry {
 public:
  static CorrectionRegistry& Global();

  // Throws std::invalid_argument if the name is empty or taken.
  void Register(const std::string& type_name, CorrectionParser parser);
  bool Contains(const std::string& type_name) const;
  std::vector<std::string> TypeNames() const;

  // Dispatches on value["type"]; unknown types are an error naming the path and the known types.
  std::unique_ptr<Correction> Parse(const nlohmann::json& value, const std::string& source,
                                    const std::string& path) const;

 private:
  CorrectionRegistry() = default;
  mutable std::mutex mutex_;
  std::vector<std::pair<std::string, CorrectionParser>> parsers_;
};

}  // namespace trackcal
