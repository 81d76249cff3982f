// Physical effects as terms of the fitting engine (fit/model.h): the parameters of the runtime
// correction core/physical_correction.h, written in the model file (docs/model-file.md) as
//
//   - type: sensor_offset   # receiver_from_body: rotation (quaternion) and translation [m]
//   - type: receiver_gain   # G, 3 x 3 (receiver coil gains and non-orthogonality)
//   - type: dipole          # an induced dipole: location [m], polarisability [m^3]; may repeat
//   - type: plane           # a conducting plane: distance [m], normal (unit), attenuation in [-1, 1]
//   - type: near_field      # the transmitter octupole coefficient of each coil [m^2]
//   - type: background_field  # distant sources: a harmonic field of degree 0 .. 2 (core/field.h)
//
// Every term type creates a PhysicalGroupTerm with one effect; the model-file parser merges
// consecutive physical terms into one group (MergePhysicalGroups), so a station runs ONE inverse of
// ONE forward field model, and the calibration file holds one `physical` entry. Each block keeps the
// name of the effect it belongs to (ParameterBlock::term), so reports and `parameters:` settings
// address "dipole_2.location_in_transmitter" as written in the file.
//
// Evaluate(): the corrected pose is x*(theta, y) composed with the sensor offset, where x* is the
// true receiver pose behind the report y: it solves the tracker's normal equations
// g(x, theta, y) = J_y^T vec(S(x; theta) - S_free(y)) = 0 (core/physical_correction.h; the inverse
// runs there, in double). Its derivatives come from the implicit function theorem,
//   dx/dtheta = -(dg/dx)^-1 dg/dtheta,   dx/dy = -(dg/dx)^-1 dg/dy,
// with dg/dx, dg/dtheta by ceres::Jet autodiff of the templated field code (core/field.h) and dg/dy
// (which needs the derivative of J_y, i.e. second derivatives of S_free) by central differences of
// the autodiff J_y (Jets do not nest with the field code; terms_physical.cc
// NormalEquationsInputDerivative).
//
// Start values by search (InitializeLinear): a dipole without a location, or a plane without a
// point and normal, is placed by scoring a grid of candidates by the linearised least-squares fit
// of its strength to the residual the group leaves without it, in the orthogonal complement of
// what the refit absorbs anyway (the group's other free parameters, linearised, and the
// polynomials that follow the group: variable projection). The best few well-separated candidates
// are refined on the same linearisation and kept as starts; the group's refinement tries them in
// order, refusing any that leaves the physical bounds (docs/model-file.md, "Start values by
// search"). Two consecutive dipoles to be searched are placed together: pairs of locations scored
// by the joint fit of both strengths (SearchDipolePair).
#pragma once

#include <map>
#include <memory>
#include <string>
#include <vector>

#include "core/physical_correction.h"
#include "fit/model.h"
#include "fit/model_file.h"

namespace trackcal::fit {

enum class PhysicalEffect {
  kSensorOffset,
  kReceiverGain,
  kDipole,
  kPlane,
  kNearField,
  kBackground
};

// "sensor_offset", "receiver_gain", "dipole", "plane", "near_field", "background_field".
const char* PhysicalEffectType(PhysicalEffect effect);
// The physical term types in model-file order of the table above.
const std::vector<std::string>& PhysicalTermTypes();

// Options of the start-value search (InitializeLinear).
struct PhysicalSearchOptions {
  double margin_m = 1.5;         // dipole candidates up to this far outside the data's bounding box
  double dipole_spacing_m = 0.15;  // grid spacing of dipole candidate locations
  // Search candidates closer than this to a station (or the transmitter) are skipped (the
  // linearised score is dominated by that station there); a refined dipole this close to the
  // transmitter is refused.
  double min_station_distance_m = 0.1;
  // A refined dipole closer than this to a station is refused (the receiver would sit in the
  // object: a steel sphere of radius 0.05 m has 1.25e-4 m^3). Smaller than the search's distance:
  // an object just outside the grid is found by a refinement from a start farther out.
  double min_refined_station_distance_m = 0.05;
  int refine_candidates = 5;     // well-separated best candidates refined and kept as starts
  // Two consecutive dipoles to be searched are searched as a pair: the pairs of this many
  // well-separated best grid points of the single search are scored jointly (two objects whose
  // fields overlap over the volume: the single best location lies between them).
  int pair_seeds = 24;
  int plane_normals = 60;        // normals on the half sphere (plus the 3 axes)
  double plane_distance_step_m = 0.1;  // distance grid step beyond the data
  // A searched source is bounded to this far outside the data's bounding box (a plane: beyond the
  // data and the transmitter); a refinement that reaches the bound is refused.
  double reach_m = 3.0;
  int max_refinements = 4;       // refinements of the group (one per start tried) at most
  // Score in the orthogonal complement of what the refit absorbs (variable projection); false:
  // against the raw residual (the behaviour before, for comparison).
  bool project_refit = true;
  bool Check() const;
};

// One start a search found: a dipole location or a plane (normal, distance), the linearised
// strength and the cost reduction it buys (in whitened units, after the projection).
struct PhysicalSearchStart {
  Eigen::Vector3d location = Eigen::Vector3d::Zero();  // dipole
  Eigen::Vector3d normal = Eigen::Vector3d::UnitZ();   // plane
  double distance = 0.0;                               // plane
  double strength = 0.0;  // polarisability [m^3] or attenuation
  double reduction = 0.0;
};

class PhysicalGroupTerm : public ModelTerm {
 public:
  static constexpr const char* kType = "physical";

  // One effect of the group and where its blocks are.
  struct Effect {
    PhysicalEffect kind;
    std::string name;     // the file-level term name ("dipole_2")
    int first_block = 0;  // index of its first block in blocks()
    int line = 0;         // model-file line (1-based; 0 unknown), for errors
    bool search_location = false;  // dipole: location not given -> searched
    bool search_plane = false;     // plane: point (distance) not given -> searched
    bool normal_given = false;     // plane: normal given (a search keeps it)
    bool strength_given = true;    // polarisability / attenuation given in the file
    int degree = 0;                // background_field: the field's polynomial degree
  };

  // receiver_gain's `gain_scale`: what fixes the uniform scale of G. A uniform gain g scales every
  // measured field by g, so the tracker reports r g^(-1/3): an exact isotropic scaling of positions,
  // which an explicit term after the group (polynomial of degree >= 1 with its position part, LUT)
  // reproduces. The data then cannot tell g apart from that term.
  enum class GainScale {
    kAuto,      // trace G = 3 if a later term absorbs the scaling (the default), else free
    kFree,      // always estimated (only the physical model identifies it)
    kUnitMean,  // always trace G = 3 (mean coil gain 1): relative gains and non-orthogonality
  };

  // A group of one effect with its default start values (identity offset and gain, zero octupole,
  // a dipole/plane to be searched).
  explicit PhysicalGroupTerm(PhysicalEffect effect);
  // Factory of the registry: reads the effect's optional start values from the term's mapping.
  static std::unique_ptr<ModelTerm> FromYaml(PhysicalEffect effect, const YamlMapReader& reader);

  std::string type() const override { return kType; }
  const std::vector<Effect>& effects() const { return effects_; }
  // Names the (single) effect and its blocks; used by the parser before merging.
  void SetEffectName(const std::string& name, int line);
  // Marks a block's start value as given (a `parameters: {block: {value: ...}}` setting).
  void MarkStartGiven(const std::string& effect_name, const std::string& block);
  // Moves the effects and blocks of `other` (a later group) into this one. Throws
  // std::invalid_argument if an effect that may occur once (sensor_offset, receiver_gain,
  // near_field, background_field) would occur twice.
  void Absorb(PhysicalGroupTerm&& other);

  void Prepare(const std::vector<FitStation>& inputs) override;
  // Runs the start-value searches (dipoles and planes not given), then fits the group alone to the
  // references (it is the model's first term). Returns true.
  bool InitializeLinear(const std::vector<FitStation>& inputs,
                        const Eigen::Vector2d& noise_sigmas) override;
  // Binds the free blocks only; fixed blocks are read from blocks() in Evaluate().
  StationBinding Bind(const AmbientPose& input) const override;
  bool Evaluate(const StationBinding& binding, const double* const* block_values,
                const AmbientPose& input, bool jacobians, TermEvaluation* result) const override;
  // The fit's forms (the joint problem's station residual, fit/fit_engine.cc BuildProblem chooses
  // per station). binding.pose_form: EvaluateFrom() toward the target, the root Newton reaches
  // from it (where the runtime inverse resolves the report). Otherwise the report form: the
  // report's misfit carried to the pose, with no inverse of the model. From x_t, the receiver pose
  // behind `target` (the target composed with the inverse sensor offset), the output is x_t [+]
  // -J_y^+ (s(x_t) - S_free(y)) composed with the offset again: s the model's signal, S_free and
  // J_y the free-space signal at the report y and its Jacobian, so J_y^+ is the tracker's own
  // free-space inverse, linearised at the report. At a fit the output is the target (no misfit);
  // otherwise the residual is the report's misfit y - y(x_t) to first order, in the report's units:
  // defined, smooth and with exact derivatives (by blocks, input and target; d_output_d_target is
  // filled) wherever the model can be evaluated, also where the model's inverse has no root (a fold
  // zone next to a strong object). The engine weighs it by the pose metric (fit/pose_metric.h), so
  // the fit still weighs pose errors where they are defined. A report in the other hemisphere than
  // the target (a flip) is compared with the mirrored pose's signal, as the runtime inverse would
  // see it.
  bool UsesTarget() const override { return true; }
  bool EvaluateToward(const StationBinding& binding, const double* const* block_values,
                      const AmbientPose& input, const AmbientPose& target, bool jacobians,
                      TermEvaluation* result) const override;
  // With both receiver_gain and sensor_offset free, holds G symmetric: its rotation part is the
  // same as a rotation of the sensor offset (a gauge), see the .cc. With GainScaleHeld(), holds
  // trace G = 3 (the uniform-gain gauge: mean coil gain 1).
  int AddExtraResiduals(ceres::Problem* problem, const std::vector<FitStation>& inputs) override;
  // Remembers whether a later term absorbs an isotropic scaling (for GainScale::kAuto).
  void SetFollowingTerms(const std::vector<const ModelTerm*>& later) override;
  // True if the group has a free receiver_gain whose uniform scale is held (trace G = 3).
  bool GainScaleHeld() const;
  GainScale gain_scale() const { return gain_scale_; }
  std::unique_ptr<Correction> ToCorrection() const override;
  nlohmann::json Describe() const override;

  // The options of the group's inverse: the fit's inverse from the report (Evaluate(), the search)
  // and the calibration file's (ToCorrection()) alike, so the runtime applies the inverse the fit
  // evaluated. 50 Newton steps: the fit meets poses (and values) where Newton needs more than the
  // runtime default of 8, and the runtime must not stop short where the fit's inverse converged.
  static PhysicalCorrectionOptions InverseOptions();
  // The runtime correction at the given block values (all blocks, blocks() order). Throws
  // std::invalid_argument if they leave the model's domain.
  PhysicalCorrection MakeCorrection(const double* const* all_values,
                                    PhysicalCorrectionOptions options = InverseOptions()) const;

  PhysicalSearchOptions& search_options() { return search_options_; }

 private:
  // Adds the blocks of one effect.
  void AddEffectBlocks(Effect* effect);
  // Evaluate() (target null: the converged inverse from the report); with a target, kTowardSteps
  // Newton steps on the normal equations from the receiver pose behind it, with the converged
  // root's implicit derivatives (RefineAlone's residual; d_output_d_target zero).
  bool EvaluateFrom(const StationBinding& binding, const double* const* block_values,
                    const AmbientPose& input, const AmbientPose* target, bool jacobians,
                    TermEvaluation* result) const;
  // EvaluateToward()'s report form.
  bool EvaluateTowardReport(const StationBinding& binding, const double* const* block_values,
                            const AmbientPose& input, const AmbientPose& target, bool jacobians,
                            TermEvaluation* result) const;
  int Block(const Effect& e, int k) const { return e.first_block + k; }
  // The starts of a search, best first (empty: the effect keeps its values); `note` says what was
  // projected out.
  std::vector<PhysicalSearchStart> SearchDipole(const Effect& effect,
                                                const std::vector<FitStation>& inputs,
                                                const Eigen::Vector2d& sigmas, std::string* note);
  // Two dipoles at once (effects `first` and first + 1, both with searched locations): pairs of the
  // single search's best grid points scored by the joint least-squares fit of both strengths, the
  // best well-separated pairs refined jointly. (first, second) starts, best first.
  std::vector<std::pair<PhysicalSearchStart, PhysicalSearchStart>> SearchDipolePair(
      const std::vector<FitStation>& inputs, const Eigen::Vector2d& sigmas, std::string* note);
  std::vector<PhysicalSearchStart> SearchPlane(const Effect& effect,
                                               const std::vector<FitStation>& inputs,
                                               const Eigen::Vector2d& sigmas, std::string* note);
  // Writes a start into the effect's free blocks and bounds its searched blocks (see .cc).
  void ApplyStart(const Effect& effect, const PhysicalSearchStart& start);
  // Empty if the effect's current values are physical, else why not.
  std::string Unphysical(const Effect& effect, const std::vector<FitStation>& inputs) const;
  // Fits the group's free blocks alone to the references (the start of the joint solve). Returns
  // false if the solve failed or its cost is not finite.
  // `hold`: blocks (indices into blocks_) that stand during this refinement.
  bool RefineAlone(const std::vector<FitStation>& inputs, const Eigen::Vector2d& sigmas,
                   const std::vector<bool>& hold = {});
  // RefineAlone with every block free, and with the sources' locations standing; keeps the one
  // with the lower ProjectedCost (see terms_physical.cc).
  bool RefineGroup(const std::vector<FitStation>& inputs, const Eigen::Vector2d& sigmas);
  // The cost of the stations after the explicit terms after the group and a linearised refit of
  // the group's free coordinates (the search's projected residual).
  double ProjectedCost(const std::vector<FitStation>& inputs, const Eigen::Vector2d& sigmas) const;

  std::vector<Effect> effects_;
  PhysicalSearchOptions search_options_;
  GainScale gain_scale_ = GainScale::kAuto;
  // Terms after the group (SetFollowingTerms; only valid during FitModel) and what they said.
  std::vector<const ModelTerm*> later_terms_;
  bool later_absorbs_scaling_ = false;
  Eigen::Vector3d data_min_ = Eigen::Vector3d::Zero(), data_max_ = Eigen::Vector3d::Zero();
  // Bounding box of the stations' reference positions (where the receiver really was: reported
  // positions near an object are pulled by it).
  Eigen::Vector3d station_min_ = Eigen::Vector3d::Zero(), station_max_ = Eigen::Vector3d::Zero();
  // Effects switched off while the search runs (strength held at 0 in MakeCorrection()).
  std::vector<bool> disabled_;
  // The last RefineGroup's choice ({"kept", "cost_free", "cost_locations_held"}), for --json.
  nlohmann::json last_refinement_;
  // What the last search of each effect found and which start won (Describe(), by effect name).
  std::map<std::string, nlohmann::json> search_reports_;
  // Blocks whose bounds the search set (reset by the next search; the file's bounds are kept).
  std::vector<bool> search_bounded_;
};

// Registers the six physical term types (called by the registry's built-in registration).
void RegisterPhysicalTerms(TermRegistry* registry);

}  // namespace trackcal::fit
