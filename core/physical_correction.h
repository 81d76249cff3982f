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
#pragma once

#include <Eigen/Core>
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

  // The corrected pose; `extrapolated` is set when the Newton iteration did not converge (the
  // pose is then the best iterate, or the report itself if an iterate became non-finite).
  CorrectedPose Apply(const Rigid3d& reported) const override;

  // The true receiver-coil pose behind a report (no sensor offset). Returns false if the
  // iteration did not converge. `iterations` (may be null) receives the Newton steps taken.
  bool InvertReport(const Rigid3d& reported, Rigid3d* transmitter_from_receiver,
                    int* iterations = nullptr) const;

  // {"type": "physical", "field_constant", "transmitter_octupole_m2", "planes": [...],
  //  "objects": [...], "receiver_gain_matrix": [[...],[...],[...]] (row-major),
  //  "receiver_from_body": {"rotation_xyzw", "translation"} (optional), "max_iterations",
  //  "tolerance_m"}.
  nlohmann::json ToJson() const override;
  static std::unique_ptr<Correction> FromJson(const JsonObjectReader& reader);
  std::unique_ptr<Correction> Clone() const override;

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
  void Precompute();

  FieldModel field_;
  std::vector<Source> sources_;  // planes then objects, equal to field_.Field() to rounding
  bool has_octupole_ = false;
  Eigen::Matrix3d receiver_gain_matrix_;
  std::optional<Rigid3d> receiver_from_body_;
  PhysicalCorrectionOptions options_;
};

}  // namespace trackcal
