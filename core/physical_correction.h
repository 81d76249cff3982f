// The physical-model correction ("type": "physical"): undoes what the field model of core/field.h
// does to the tracker's free-space solver (core/tracker_solver.h).
//
// The tracker measures S = G R^T B(p) in a field B shaped by planes, objects and finite coils, and
// reports the pose y = (p_y, R_y) whose free-space signal S_free(y) = R_y^T k D(p_y) fits S best in
// least squares. At a converged report the normal equations hold:
//
//   J_y^T vec(S(x) - S_free(y)) = 0,        J_y = d vec(S_free) / d(p, w) at y,
//
// six equations in the six unknowns of the true pose x, with J_y and S_free(y) fixed by the report.
// Apply solves them by Newton's method from x = y (Jacobian of S(x) by ceres::Jet autodiff of the
// same templated field code fit/ differentiates), a handful of steps, no allocation. The corrected
// pose is then x composed with the optional sensor offset: transmitter_from_body =
// transmitter_from_receiver * receiver_from_body.
//
// Equivalent to trackcal::InvertReportedPose (the fixed-point inverse of "report = solver(S(x))")
// but without re-running the free-space solver per iteration; the test checks both agree.
//
// Robustness (held-out stations, poses next to a strong object or far outside the calibrated
// volume). Steps are capped (a trust region of a quarter of the range and 1 rad) and halved until
// the iterate is in the model's domain; a run that does not converge returns its last iterate.
// The model's domain: within
// `max_correction_fraction` of the report's range from the reported position (a larger correction
// means a distortion as large as the field itself, where the report carries no range information),
// outside every object's sphere (radius |polarisability|^(1/3), x2^(1/3) for a conductor: a
// receiver cannot sit inside the object) and on the transmitter's side of every plane. The result is
// therefore finite and bounded for every finite report, with a status:
// - kNotConverged: no root within the domain in `max_iterations` (the last iterate is returned);
// - kAmbiguous: a root, but the forward map folds there (det dy/dx <= 0), report noise is amplified
//   more than `max_noise_gain` times, or a second root exists near an object: within about
//   rho = (2 |alpha| r^4 / |l|^3)^(1/4) of an induced dipole at l the dipole's field gradient
//   exceeds the transmitter's, so the map from true to reported pose folds and one report has
//   several true poses (at 0.2 m from the paper's toolbox every true pose is on the folded sheet and
//   Newton from the report finds another root 0.4-0.6 m from the object). For a root within
//   `fold_reach` rho of such an object a second Newton run from the fold zone looks for another root.
#pragma once

#include <Eigen/Core>
#include <cmath>
#include <memory>
#include <nlohmann/json.hpp>
#include <optional>
#include <string>
#include <vector>

#include "core/correction.h"
#include "core/field.h"
#include "core/json_reader.h"
#include "core/pose.h"

namespace trackcal {

struct PhysicalCorrectionOptions {
  int max_iterations = 8;  // Newton steps per pose (converges in 3-4 in a room like the paper's)
  // Stop when the remaining error, estimated as (Newton step)^2 / 1 m, is below this [m, rad].
  double tolerance_m = 1e-12;
  // The corrected position stays within this fraction of the report's range |p_y| from the reported
  // position. 0.5: the signal falls as r^-3, so a range off by half means a distortion at least as
  // large as the field itself (the report then says nothing about the range).
  double max_correction_fraction = 0.5;
  // A root whose report-noise amplification (1 / smallest singular value of dy/dx, position scaled
  // by the range; 1 in free space, <= 1.3 in the paper room) exceeds this is called ambiguous.
  double max_noise_gain = 10.0;
  // Roots within this many fold radii rho of an object are checked for a second root (see above;
  // the other root of a folded report lay within 2.2 rho of the paper's toolbox).
  double fold_reach = 3.0;
  // Throws std::invalid_argument naming the field.
  void Check() const;
};

class PhysicalCorrection : public Correction {
 public:
  static constexpr const char* kTypeName = "physical";

  // `field` is the true field the receiver sits in (its field_constant is the k the tracker's
  // solver assumes too); `receiver_gain_matrix` is G; `receiver_from_body`, if set, is the rigid
  // offset from the receiver coil to the reference body whose pose the correction outputs.
  PhysicalCorrection(FieldModel field, const Eigen::Matrix3d& receiver_gain_matrix,
                     std::optional<Rigid3d> receiver_from_body = std::nullopt,
                     PhysicalCorrectionOptions options = {});

  std::string TypeName() const override { return kTypeName; }

  // The corrected pose with the inverse's status (the pose is the bounded best guess when not
  // converged, the report itself when the report is not finite).
  CorrectedPose Apply(const Rigid3d& reported) const override;
  // Pose by pose, with each pose's status.
  void ApplyBatchWithStatus(size_t n, const double* positions, const double* quaternions_xyzw,
                            double* out_positions, double* out_quaternions_xyzw,
                            uint8_t* extrapolated, CorrectionStatus* status) const override {
    ApplyPerPose(n, positions, quaternions_xyzw, out_positions, out_quaternions_xyzw, extrapolated,
                 status);
  }

  // The true receiver-coil pose behind a report (no sensor offset).
  struct Inverse {
    Rigid3d transmitter_from_receiver;  // finite and bounded for a finite report
    CorrectionStatus status = CorrectionStatus::kNotConverged;
    int iterations = 0;        // Newton steps of the main run
    // Report-noise amplification at the root (2-norm of dx/dy, position scaled by the range; 1
    // in free space) when it exceeds max_noise_gain; below, the cheap upper bound that decided the
    // status (Frobenius norm, within sqrt(6) of the 2-norm: sqrt(6) in free space). NaN unless
    // converged.
    double noise_gain = NAN;
  };
  // How far Invert() classifies a root. kFull: the status as documented above (Apply() and every
  // caller that tells kAmbiguous from kConverged). kRootOnly: for callers that only tell a root
  // from none (InvertReport(), the fit): a root is kConverged without the noise-gain check or the
  // second-root search (noise_gain stays NaN). The pose and iterations are those of kFull bit for
  // bit (both follow the main Newton run alone), and the status is kNotConverged exactly when
  // kFull's is; only kAmbiguous is never returned.
  enum class Classify { kFull, kRootOnly };
  Inverse Invert(const Rigid3d& reported, Classify classify = Classify::kFull) const;

  // As Invert(reported, Classify::kRootOnly); returns true unless the status is kNotConverged (the
  // same answer as with kFull, without its cost). `iterations` may be null.
  bool InvertReport(const Rigid3d& reported, Rigid3d* transmitter_from_receiver,
                    int* iterations = nullptr) const;

  // {"type": "physical", "field_constant", "transmitter_octupole_m2", "planes": [...],
  //  "objects": [...], "receiver_gain_matrix": [[...],[...],[...]] (row-major),
  //  "receiver_from_body": {"rotation_xyzw", "translation"} (optional), "max_iterations",
  //  "tolerance_m", "max_correction_fraction", "max_noise_gain", "fold_reach" (the last three
  //  optional)}.
  nlohmann::json ToJson() const override;
  static std::unique_ptr<Correction> FromJson(const JsonObjectReader& reader);
  std::unique_ptr<Correction> Clone() const override;
  // The field model holds outside the calibration data: applied at the actual pose, never clamped.
  bool GuardedByVolume() const override { return false; }

  const FieldModel& field() const { return field_; }
  const Eigen::Matrix3d& receiver_gain_matrix() const { return receiver_gain_matrix_; }
  const std::optional<Rigid3d>& receiver_from_body() const { return receiver_from_body_; }
  const PhysicalCorrectionOptions& options() const { return options_; }

 private:
  // A distortion source as seen by the inverse: B += D(p - center) * moment, with the constant
  // moment (k times the image's moments, or k polarisability D(location)) computed once.
  struct Source {
    Eigen::Vector3d center;
    Eigen::Matrix3d moment;
  };
  // What a report fixes for the inverse: its free-space signal and Jacobian (the normal equations'
  // constants), the merit's metric and the bound.
  struct ReportFrame;
  struct Run {
    Eigen::Vector3d p;
    Eigen::Matrix3d rotation;
    Eigen::Matrix<double, 6, 6> h;  // dg/dx at the last evaluated iterate
    int iterations = 0;
    bool converged = false;
  };
  void Precompute();
  // Signal residual g = J_y^T (S(x) - S_free(y)) and h = dg/dx at (p, rotation).
  void NormalEquations(const ReportFrame& frame, const Eigen::Vector3d& p,
                       const Eigen::Matrix3d& rotation, Eigen::Matrix<double, 6, 1>* g,
                       Eigen::Matrix<double, 6, 6>* h) const;
  // True if p is in the model's domain for the report (bound, objects, planes).
  bool InDomain(const ReportFrame& frame, const Eigen::Vector3d& p) const;
  // Damped Newton from (p, rotation).
  Run Newton(const ReportFrame& frame, const Eigen::Vector3d& p,
             const Eigen::Matrix3d& rotation) const;

  FieldModel field_;
  std::vector<Source> sources_;  // planes then objects, equal to field_.Field() to rounding
  std::vector<double> object_radius_;  // per object: the sphere a receiver cannot enter [m]
  bool has_octupole_ = false;
  Eigen::Matrix3d receiver_gain_matrix_;
  std::optional<Rigid3d> receiver_from_body_;
  PhysicalCorrectionOptions options_;
};

}  // namespace trackcal
