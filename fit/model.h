// The term interface of the fitting engine (fit/fit_engine.h).
//
// A model is an ordered list of terms (the model file, docs/model-file.md). The corrected pose of a
// station is the reported pose passed through every term in order, exactly as the runtime
// CorrectionChain built from the terms' ToCorrection() applies them:
//
//   pose_0 = reported;  pose_{k+1} = term_k.Evaluate(pose_k);  corrected = pose_K
//
// and the station residual is (corrected - reference) whitened by the position and orientation
// noise: ((p_c - p_ref) / sigma_p, VectorPart(q_c * conj(q_ref)) / sigma_o).
//
// Poses move through the chain in the 7-vector "ambient" form (x, y, z [m], qx, qy, qz, qw). A term
// maps one such pose to the next and reports the Jacobians of its output with respect to its input pose
// and to each of its parameter blocks the station uses (TermEvaluation). The engine composes them by the
// chain rule inside one ceres::CostFunction per station. Hence a term need not be an explicit function
// with autodiff:
//   - explicit terms (polynomial, LUT) write one templated Apply<T>() and derive from
//     AutoDiffModelTerm<Derived> (below), which differentiates it with ceres::Jet;
//   - a physical term whose correction is the inverse of a forward model solves the inverse in double
//     and returns Jacobians from the implicit function theorem (autodiff of the forward model);
//   - a term may in addition add its own residual blocks (smoothness regularisers, report-space
//     residuals of a forward model) through AddExtraResiduals().
//
// Parameter blocks are plain double vectors owned by their term (ParameterBlock::values); their
// addresses stay fixed while a ceres::Problem refers to them (blocks are never resized after Prepare()).
#pragma once

#include <ceres/manifold.h>
#include <ceres/problem.h>

#include <Eigen/Core>
#include <functional>
#include <limits>
#include <memory>
#include <string>
#include <vector>

#include "core/correction.h"
#include "core/pose.h"

namespace trackcal::fit {

// A pose in the chain: x, y, z [m], then the rotation quaternion qx, qy, qz, qw.
inline constexpr int kAmbientPoseSize = 7;
using AmbientPose = Eigen::Matrix<double, 7, 1>;
AmbientPose ToAmbient(const Rigid3d& pose);
Rigid3d FromAmbient(const AmbientPose& pose);

// One named group of parameters of a term.
struct ParameterBlock {
  std::string name;                         // "position_coefficients", "node_values", "offset"
  std::vector<double> values;               // current estimate (the initial value before a fit)
  std::vector<std::string> coordinate_names;  // one per value (may be empty: "<name>[i]")
  std::string unit;                         // of the values, for reports ("m", "rad", "1", ...)
  bool fixed = false;                       // held constant in the fit
  // Optional bounds (empty: none; else one per value, +-infinity for an open side).
  std::vector<double> lower;
  std::vector<double> upper;
  // Optional Gaussian prior (empty: none; else one mean and one sigma > 0 per value; an infinite sigma
  // disables the prior on that value). Added by the engine as whitened residuals.
  std::vector<double> prior_mean;
  std::vector<double> prior_sigma;
  // A value's standard deviation above `identifiability_scale` flags it as poorly identified
  // (infinity: only rank deficiency flags it).
  double identifiability_scale = std::numeric_limits<double>::infinity();
  // Manifold of the block (null: Euclidean). Called once per problem; the problem takes ownership.
  std::function<ceres::Manifold*()> make_manifold;
  // The values are a unit vector or unit quaternion (a sphere or quaternion manifold, which keeps
  // the norm a start has): Check() requires |values| = 1 (to 1e-3).
  bool unit_norm = false;
  // Standard deviations after a fit: one per value, or for a manifold block one per tangent
  // coordinate (named by tangent_names, in tangent_unit); NaN for fixed values or unavailable
  // covariance.
  std::vector<double> stddev;
  // The block's own covariance after a fit, row-major over the same coordinates as `stddev`
  // (joint tests on a block, fit/candidates.h); empty when unavailable.
  std::vector<double> covariance;
  // Manifold blocks: names and unit of the tangent coordinates ("rotation_vector.x", "rad"), and
  // the physical units per tangent unit (2 for EigenQuaternionManifold: rotation vectors in rad).
  std::vector<std::string> tangent_names;
  std::string tangent_unit;
  double tangent_scale = 1.0;
  // The model-file term the block belongs to when its ModelTerm groups several file terms (the
  // physical effects of fit/terms_physical.h); empty: the ModelTerm's own name. Reports and
  // `parameters:` settings use it.
  std::string term;
  // A linear-subspace manifold (make_manifold moves the values only along these columns, values x
  // tangent): the engine then reports the values' own standard deviations and covariance, mapped
  // from the tangent's (B C B^T), instead of the tangent's. Empty: none.
  Eigen::MatrixXd ambient_from_tangent;
  // Added to the fit's identifiability flags when not empty (what the term holds and why).
  std::string identifiability_note;

  int size() const { return static_cast<int>(values.size()); }
  // Free coordinates: the subspace's when there is one, else one per value.
  int free_size() const {
    return ambient_from_tangent.size() > 0 ? static_cast<int>(ambient_from_tangent.cols()) : size();
  }
  // Throws std::invalid_argument naming the block on inconsistent sizes, non-finite values, lower >
  // upper or a value outside its bounds, a non-positive prior sigma, a unit_norm block off the unit
  // sphere.
  void Check(const std::string& term_name) const;
};

// One station as the engine sees it.
struct FitStation {
  Rigid3d reported;   // transmitter_from_receiver as the tracker reported it
  Rigid3d reference;  // transmitter_from_receiver from the reference system
  double time = 0.0;  // tracker clock [s]
  int sensor = 1;     // receiver number
  int station = 0;    // station id (for reports)
  // Streams only: the reference's velocity at the paired time [m/s] and angular velocity in the
  // transmitter frame [rad/s], for a fitted clock offset (fit/terms_time_offset.h). Zero: static.
  Eigen::Vector3d reference_velocity = Eigen::Vector3d::Zero();
  Eigen::Vector3d reference_angular_velocity = Eigen::Vector3d::Zero();
};

// Which parameter blocks of a term a station's residual depends on, fixed when the problem is built.
// `tag` is term-defined context (the LUT stores its cell), passed back to Evaluate().
struct StationBinding {
  std::vector<int> blocks;  // indices into ModelTerm::blocks(), increasing
  long tag = 0;
  // A physical group's residual form for this station (ModelTerm::EvaluateToward): false, the
  // report's misfit carried to the pose by the free-space chord; true, the pose its inverse
  // reaches by Newton steps from the target, exact where the inverse resolves the report
  // (fit/fit_engine.cc, BuildProblem).
  bool pose_form = false;
};

// Output of one term for one station.
struct TermEvaluation {
  AmbientPose output;                 // the pose after this term
  // d output / d input pose (7 x 7, row-major); only filled when requested.
  Eigen::Matrix<double, 7, 7, Eigen::RowMajor> d_output_d_input;
  // Set by the caller: false when it will not read d_output_d_input (the chain's first term, whose
  // input is the constant report). A term whose input derivative is costly (a physical group's,
  // by finite differences of the free-space signal's Jacobian) may then skip it and leave it NaN.
  bool want_d_output_d_input = true;
  // d output / d block, one 7 x size matrix per bound block (in StationBinding::blocks order).
  std::vector<Eigen::Matrix<double, 7, Eigen::Dynamic, Eigen::RowMajor>> d_output_d_blocks;
  // d output / d target (7 x 7, row-major) of ModelTerm::EvaluateToward(), filled with the other
  // derivatives; zero where the output does not depend on the target.
  Eigen::Matrix<double, 7, 7, Eigen::RowMajor> d_output_d_target =
      Eigen::Matrix<double, 7, 7, Eigen::RowMajor>::Zero();
};

class ModelTerm {
 public:
  virtual ~ModelTerm() = default;

  // The term type as written in the model file ("polynomial", "lut", ...).
  virtual std::string type() const = 0;
  // Instance name for reports (the file's optional `name`, default the type; unique in a model).
  const std::string& name() const { return name_; }
  void set_name(std::string name) { name_ = std::move(name); }

  // Sizes the blocks from the calibration data (normalisation box, LUT grid, ...). Called once before
  // any other method below; `inputs` are the stations' poses at this term's input, evaluated with the
  // initial values of the preceding terms. The default does nothing.
  virtual void Prepare(const std::vector<FitStation>& inputs);

  std::vector<ParameterBlock>& blocks() { return blocks_; }
  const std::vector<ParameterBlock>& blocks() const { return blocks_; }

  // Linear initialiser: given each station's pose at this term's input (input[i].reported) and the
  // pose the chain must reach (input[i].reference), set the free values by least squares with the other
  // terms held. Returns false if the term has no linear initialiser (the default) or the system is
  // singular. When the term is the only one and is linear in its parameters, this is the exact fit.
  virtual bool InitializeLinear(const std::vector<FitStation>& inputs,
                                const Eigen::Vector2d& noise_sigmas);

  // True if, when this term is the model's only term and the fit has no robust loss, priors or bounds,
  // a successful InitializeLinear() is the fit (the paper's linear least squares): the engine then
  // skips the nonlinear solve and asks LinearCovariance() for the standard deviations. Default false.
  virtual bool SolvesAloneLinearly() const { return false; }
  // Fills every free block's `stddev` from the linear least-squares covariance of the last
  // InitializeLinear() (noise_sigmas: position [m], orientation [rad]). Default: false (unavailable).
  virtual bool LinearCovariance(const Eigen::Vector2d& noise_sigmas);

  // The blocks the residual of a station whose pose at this term's input is `input` depends on. The
  // default binds every block.
  virtual StationBinding Bind(const AmbientPose& input) const;

  // Maps `input` through the term with the bound blocks' values (`block_values` in binding order).
  // Fills result->d_output_d_input and result->d_output_d_blocks only if `jacobians` is true.
  // Returns false if the term cannot be evaluated there (the solver then shortens its step).
  virtual bool Evaluate(const StationBinding& binding, const double* const* block_values,
                        const AmbientPose& input, bool jacobians, TermEvaluation* result) const = 0;
  // As Evaluate(), given `target`: the pose the chain must reach after this term (the station's
  // reference when the term is the chain's last). A term whose output is defined implicitly (the
  // physical group's inverse) linearises there instead of solving from `input`, so that its output
  // is a smooth function of the values even where the solve from the input has no solution; it
  // then also fills result->d_output_d_target. The default ignores `target`.
  // True if EvaluateToward() uses its target (the engine then also pulls the reference back through
  // the terms after this one to give it one). Default false.
  virtual bool UsesTarget() const { return false; }
  virtual bool EvaluateToward(const StationBinding& binding, const double* const* block_values,
                              const AmbientPose& input, const AmbientPose& target, bool jacobians,
                              TermEvaluation* result) const {
    (void)target;
    return Evaluate(binding, block_values, input, jacobians, result);
  }

  // Adds residual blocks other than the station residuals (regularisers, report-space residuals),
  // over this term's blocks as held in blocks() (their addresses are the problem's blocks). Returns
  // the number of residual blocks added. Default: none.
  virtual int AddExtraResiduals(ceres::Problem* problem, const std::vector<FitStation>& inputs);
  // True if those residuals are weighted relative to the noise model's sigma (a ridge w c / sigma,
  // a smoothness prior): the sandwich covariance scales their information by the stations' noise
  // variance (fit/covariance.h, CovarianceOptions::noise_relative). Default: false: they are
  // constraints (a gauge), which the covariance takes in the limit of their weight
  // (CovarianceOptions::hard_constraints).
  virtual bool ExtraResidualsRelativeToNoise() const { return false; }

  // The runtime correction of this term with its current values, for the calibration file.
  virtual std::unique_ptr<Correction> ToCorrection() const = 0;

  // Term-specific summary for reports and --json (degree, grid, ...). Default: empty object.
  virtual nlohmann::json Describe() const;

  // What Prepare() derived from the data and InitializeLinear() chose beyond the block values (the
  // polynomial's normalisation and ridge weight, the LUT's grid): with the block values, the state
  // a fit of a larger model starts from (fit/fit_engine.h, FitStart). Default: null (none).
  virtual nlohmann::json PreparedState() const { return nullptr; }
  // Called before Prepare() with PreparedState() of this term as fitted in that model: Prepare()
  // and InitializeLinear() then keep it instead of deriving their own. False if the term cannot
  // (the engine then keeps the term's own start). Default: true for a null state.
  virtual bool AdoptPreparedState(const nlohmann::json& state) { return state.is_null(); }

  // True if this term reproduces an isotropic scaling of the positions about the transmitter,
  // p -> s p, exactly with free parameters (a polynomial of degree >= 1 with a free position part, a
  // LUT): a uniform receiver gain before it is then not identifiable. Default: false.
  virtual bool AbsorbsIsotropicScaling() const { return false; }
  // Called by FitModel before Prepare() with the terms that follow this one in the chain (the
  // physical group holds its gain gauge when one of them absorbs a scaling). Default: nothing.
  virtual void SetFollowingTerms(const std::vector<const ModelTerm*>& /*later*/) {}
  // Called by FitModel before Prepare() with the terms that precede this one in the chain (a LUT's
  // default weights depend on whether it is the first term). Default: nothing.
  virtual void SetPrecedingTerms(const std::vector<const ModelTerm*>& /*earlier*/) {}

 protected:
  std::vector<ParameterBlock> blocks_;

 private:
  std::string name_;
};

// Base for terms that are explicit, differentiable maps of the pose. Derived provides
//
//   template <typename T>
//   bool Apply(const StationBinding& binding, const T* const* block_values, const T* input7,
//              T* output7) const;
//
// and gets Evaluate() with Jacobians from ceres::Jet (forward mode over the input pose and the bound
// blocks, evaluated in chunks of kJetStride derivatives).
template <typename Derived>
class AutoDiffModelTerm : public ModelTerm {
 public:
  bool Evaluate(const StationBinding& binding, const double* const* block_values,
                const AmbientPose& input, bool jacobians, TermEvaluation* result) const override;
};

// Composes a model: builds the runtime chain from the terms (without a volume).
CorrectionChain ModelToChain(const std::vector<std::unique_ptr<ModelTerm>>& terms);

}  // namespace trackcal::fit

#include "fit/model_impl.h"
