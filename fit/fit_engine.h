// The fitting engine: estimates all terms of a model (fit/model.h) jointly with Ceres.
//
//   ModelSpec spec = ReadModelFile("model.yaml");
//   FitResult result = FitModel(calibration_stations, &spec, {});
//   result.chain.Apply(reported);   // the runtime correction, guarded by the calibrated volume
//
// Steps: (1) each term in order is prepared (normalisation, grid) and initialised by its linear least
// squares from the poses the preceding terms produce; (2) one residual block per station
// ((corrected - reference) whitened by the model's noise, with the model's robust loss), the terms'
// extra residuals (regularisers) and the priors form one problem, solved by Levenberg-Marquardt;
// (3) the covariance gives a standard deviation per estimate and flags poorly identified ones
// (fit/covariance.h); stations whose whitened residual exceeds the loss scale are flagged as outliers.
#pragma once

#include <functional>
#include <map>
#include <nlohmann/json.hpp>
#include <optional>
#include <string>
#include <utility>
#include <vector>

#include "core/correction.h"
#include "core/error_statistics.h"
#include "fit/covariance.h"
#include "fit/model.h"
#include "fit/model_file.h"

namespace trackcal::fit {

// Where a model stands after a fit (TakeFitStart), for a fit of a model that holds the same terms
// and more (FitOptions::start): a model with an added effect then starts at the fitted model's
// optimum with the added terms at their own starts (diagnose, fit/candidates.h). Keyed by the
// model-file term's type and name; the fitted model's value of a block, and its term's
// PreparedState() (the polynomial's normalisation and ridge weight, the LUT's grid).
struct FitStart {
  struct Term {
    nlohmann::json prepared;  // ModelTerm::PreparedState()
    std::map<std::string, std::vector<double>> blocks;  // by block name
  };
  std::map<std::pair<std::string, std::string>, Term> terms;  // by (type, name)
  // A clock offset the fit estimated (its time_offset not fixed); the fit from this start begins
  // there when it estimates one too, its stations still moved relative to their pairing's offset.
  std::optional<double> time_offset;
  std::string source;  // the document it was read from (FitStartFromJson), for errors
};
// The start `fitted` (a spec FitModel left) gives; copies, so `fitted` may change afterwards.
FitStart TakeFitStart(const ModelSpec& fitted);
// The start a fit's JSON gives (FitResult::ToJson(), the "fit" of `trackcal-fit fit --json`: its
// parameters, and its terms with their "prepared" states and a physical group's "effects").
// Throws a JsonInputError (a std::invalid_argument) naming `source` and the field's JSON path,
// below `json_path` (where `fit` is in its document: "$" for a document that is the fit itself),
// when the document is not one; LocateJsonErrors adds the line and column.
FitStart FitStartFromJson(const nlohmann::json& fit, const std::string& source,
                          const std::string& json_path = "$.fit");

struct FitOptions {
  bool compute_covariance = true;  // standard deviations and identifiability flags
  // Start from another fit's state (not owned; null: the model file's starts). Each term of the
  // spec that `start` holds (same type and name) keeps that fit's preparation, and its free blocks
  // that `start` holds with the same size start at that fit's values after the term's own
  // initialisation. A physical group's effects that `start` lacks (an added effect) take the
  // values the file gives them (write them: where the file leaves an effect to be searched, the
  // search's start is discarded), and so does a whole term `start` lacks that precedes a term it
  // holds (an effect added before the polynomial): the start is the fitted model's optimum with
  // the added effect at its file start. Fixed blocks keep the file's values. A term `start` lacks
  // that follows the ones it holds (an added polynomial or LUT) is initialised as usual on the
  // poses the preceding terms give at their start values. A block that moves within a subspace (a
  // polynomial's determined directions) starts at the start's values projected onto it.
  const FitStart* start = nullptr;
  // Called with (iteration, cost) after each solver iteration (progress on stderr in the CLI).
  std::function<void(int, double)> progress;
  int num_threads = 1;  // Ceres threads
  // The solver's linear solver; unset: chosen from the problem's size and the fill of its normal
  // matrix (dense Cholesky up to 400 coordinates, or up to 3000 when J^T J is a quarter filled;
  // sparse Cholesky otherwise). Set it only to compare solvers.
  std::optional<ceres::LinearSolverType> linear_solver;
  bool Check() const { return num_threads >= 1; }
};

struct StationFlag {
  int station = 0;              // station id
  double whitened_rms = 0.0;    // |r| / sqrt(6) of the whitened station residual
};

// A station whose corrected pose under the fitted model comes from a physical inverse that did not
// converge or is ambiguous (core/physical_correction.h).
struct UnresolvedStation {
  int station = 0;
  CorrectionStatus status = CorrectionStatus::kNotConverged;
};

// A station in report form (the model's inverse did not resolve it during the fit) whose pose
// metric was capped: the fitted model amplifies its report noise into the pose beyond the model's
// amplification_threshold (fit/pose_metric.h, docs/model-file.md, `noise`).
struct AmplifiedStation {
  int station = 0;
  double gain = 0.0;  // largest amplification of the report noise into the pose (1: none)
};

// A fitted clock offset whose variance inflation (the share of its information the other
// parameters also carry) exceeds this is flagged as poorly identified (FitResult::
// time_offset_variance_inflation; measured values in docs/diagnose.md, Known limits).
inline constexpr double kMaxTimeOffsetVarianceInflation = 10.0;
// ModelSpec::leave_out_unresolved leaves out at most this share of the stations (more: the model
// is not near the data, and none is left out).
inline constexpr double kMaxLeftOutFraction = 0.1;
// What such an offset's flag says: the share of its information the other parameters carry, and the
// remedy (also in trackcal-fit diagnose's time_offset candidate).
std::string TimeOffsetMimicryNote(double variance_inflation);

struct ParameterReport {
  std::string term;       // term name
  std::string block;      // block name
  std::string unit;
  bool fixed = false;
  std::vector<std::string> coordinate_names;
  std::vector<double> values;
  std::vector<double> stddev;  // NaN where unavailable (fixed block, covariance failed)
  // The block's own covariance, row-major over the coordinates of `stddev` (joint tests on a block);
  // empty where unavailable. Not in ToJson().
  std::vector<double> covariance;
  // Manifold blocks (quaternion, unit normal): stddev holds one value per tangent coordinate, named
  // here ("rotation_vector.x", "angle_a"), in stddev_unit ("rad"); empty for Euclidean blocks.
  std::vector<std::string> stddev_names;
  std::string stddev_unit;
};

struct FitResult {
  // The solver reported convergence and the final cost is finite.
  bool converged = false;
  // How the solve ended, Ceres' termination type of the last solve: "CONVERGENCE",
  // "NO_CONVERGENCE" (stopped at solver.max_iterations: the values are the best found, usable but
  // not the optimum), "FAILURE" (the solver could not evaluate or solve the problem, or the cost is
  // not finite whatever the solver said), "USER_SUCCESS" (a statistical stop), "USER_FAILURE";
  // "CONVERGENCE" without a solve (linear least squares, no free parameters). Failed() fits are
  // not written as calibrations (trackcal-fit fit/build, trackcal.FitReport.save).
  std::string termination_type;
  bool Failed() const {
    return termination_type == "FAILURE" || termination_type == "USER_FAILURE";
  }
  // Solved by the lone term's linear least squares (the paper's eq. 9), without the solver: the
  // optimum of a linearised cost, not of the station residuals the solver minimises.
  bool linear_least_squares = false;
  std::string solver_message;
  // Ceres' linear solver of the solve ("DENSE_NORMAL_CHOLESKY", "SPARSE_NORMAL_CHOLESKY"); empty
  // without a solve (linear least squares, no free parameters).
  std::string linear_solver;
  int iterations = 0;
  double initial_cost = 0.0;  // 0.5 * sum of squared whitened residuals (after the linear init)
  double final_cost = 0.0;
  int num_residuals = 0;
  int num_free_parameters = 0;
  double chi2_per_dof = 0.0;  // 2 * final_cost / (num_residuals - num_free_parameters)
  double seconds = 0.0;       // wall time of the fit (initialisation, solve, covariance)
  double seconds_solve = 0.0;       // of which initialisation and solve
  double seconds_initialize = 0.0;  // of which initialisation (start searches, terms' own fits)
  double seconds_covariance = 0.0;  // of which covariance
  std::vector<ParameterReport> parameters;
  std::vector<IdentifiabilityFlag> identifiability_flags;
  bool rank_deficient = false;
  std::string covariance_message;
  // Which covariance gave the stds: "model" (H^-1 with the model file's noise), "sandwich (CR2)"
  // or "sandwich (CR1)" (one cluster per station), "sandwich (CR2, 32 clusters)" (stream samples
  // in runs of time; fit/covariance.h); empty when there are none.
  std::string covariance_estimator;
  // The sandwich's number of clusters (stations, or runs of stream samples); 0 for the model
  // covariance. A Wald test of k coordinates refers to Hotelling's T^2 with it (fit/candidates.h).
  int covariance_clusters = 0;
  // A fitted clock offset's variance inflation (CovarianceResult::variance_inflation): above
  // kMaxTimeOffsetVarianceInflation the other terms can mimic a time shift along the stream's path
  // and the offset is flagged in identifiability_flags. NaN when not fitted or not computed.
  double time_offset_variance_inflation = std::numeric_limits<double>::quiet_NaN();
  // How it was computed (CovarianceResult::method: "dense_sandwich", "schur_banded_groups", ...;
  // "linear" for the lone linear term's own); empty when there are none.
  std::string covariance_method;
  std::vector<StationFlag> outliers;  // stations beyond the loss scale
  // Calibration stations whose physical inverse is not converged or ambiguous under the fitted
  // model (in --json: "unresolved": [{"station", "status"}]).
  std::vector<UnresolvedStation> unresolved;
  // With solver.leave_out_unresolved: the stations left out of the solve (and of the residual
  // count, chi2 and covariance) because the model does not resolve them (in --json: "left_out").
  std::vector<int> left_out;
  std::string left_out_note;  // why none was left out although some are unresolved, if so
  // Stations whose pose metric was capped (in --json: "noise_amplified": [{"station", "gain"}]),
  // and the solves the metrics took (1: they did not change at the solution, or the chain has no
  // physical group; 0: no solver run).
  std::vector<AmplifiedStation> noise_whitened;
  int whitening_passes = 0;
  // Per station given to FitModel, in its order: its residual through the physical group was in
  // report form at the final solve (BuildProblem, docs/fit.md); a left-out station counts as in
  // report form. Empty without a physical group. report_form_stations: the fitted ones' station
  // ids, capped or not (in --json: "report_form"; left-out stations are not in it).
  std::vector<bool> report_form;
  std::vector<int> report_form_stations;
  CorrectionChain chain;              // the fitted correction, with the calibrated volume
  nlohmann::json terms = nlohmann::json::array();  // Describe() of every term

  nlohmann::json ToJson() const;  // everything above except the chain
};

// True for stations that are samples of a stream rather than static stations: most of them
// less than 0.5 s after the previous one of the same sensor. Stations without distinct times
// (all 0) count as static. The fit's covariance, the cross-validation's folds and trackcal-fit
// diagnose's folds and paired test (SerialTestBlocks below) treat such samples as serially
// correlated.
bool SerialSamples(const std::vector<FitStation>& stations);

// Contiguous runs of about equal count in time (the run of each station, 0 ... max_clusters - 1),
// samples that share a time in one run; empty when `max_clusters` is 0 or there are fewer than
// `min_per_cluster` samples per run. The stream samples' sandwich clusters
// (ModelSpec::stream_clusters).
std::vector<int> TimeClusters(const std::vector<FitStation>& stations, int max_clusters,
                              int min_per_cluster = 5);

// The default number of blocks of time serial stations are cut into for held-out comparisons
// (CandidateOptions::serial_blocks, CrossValidationFolds): the fit's sandwich clusters of stream
// samples (ModelSpec::stream_clusters) treat the same runs as independent.
constexpr int kDefaultSerialBlocks = 32;
// The least a block of time holds where the stream allows: TimeClusters' minimum of samples, and
// the pairing's correlation window (its Newey-West window, 0.5 s): on a 3 s stream, 32 blocks of
// 0.09 s would be as correlated as the samples themselves.
constexpr int kSerialBlockMinSamples = 5;
constexpr double kSerialBlockMinSeconds = 0.5;

// The blocks of the held-out comparison of serial stations (trackcal-fit fit's cross-validation,
// trackcal-fit diagnose's folds and paired test): the block of time of each station (contiguous,
// about equal count, at least 5 samples and 0.5 s each where the stream allows, 0 ... blocks - 1,
// never fewer blocks than `folds`), or empty for static stations (SerialSamples false), for
// `serial_blocks` 0 and for streams of fewer than `folds` samples.
std::vector<int> SerialTestBlocks(const std::vector<FitStation>& stations, int serial_blocks,
                                  int folds);

// The fold (0 ... folds - 1) of each station of a k-fold cross-validation. Static stations: station
// i in fold i % k. Serial stations (SerialTestBlocks not empty): block of time b in fold b % k, so
// that a held-out stream sample's neighbours, which share the model's misfit along the path, are
// held out with it rather than trained on. `by_blocks` (optional) says which rule was taken.
std::vector<int> CrossValidationFolds(const std::vector<FitStation>& stations, int folds,
                                      int serial_blocks = kDefaultSerialBlocks,
                                      bool* by_blocks = nullptr);

// The name of the held-out table of a k-fold cross-validation whose folds CrossValidationFolds
// made: "cross-validation (5-fold)", "cross-validation (5-fold, blocks of time)" when `by_blocks`.
// trackcal-fit fit's table (CrossValidate) and trackcal-fit diagnose's base table use it, so one
// set of folds has one name.
std::string CrossValidationTableName(int folds, bool by_blocks);

// Fits `spec`'s terms to `stations` (the calibration set). The terms keep the fitted values. Throws
// std::invalid_argument for too few stations or inconsistent settings.
FitResult FitModel(const std::vector<FitStation>& stations, ModelSpec* spec,
                   const FitOptions& options = {});

// One station's residual as FitModel's solver sees it in report form (the form of a station whose
// report the physical group's inverse does not resolve), through `spec`'s prepared terms at their
// current values, before its pose metric: 6 values and, per bound block of every term in order
// (the clock offset last when `time_offset` is given, with reference value 0), its 6 x size
// Jacobian in ambient coordinates; with `report_per_pose`, the A its pose metric inverts
// (fit/pose_metric.h; null if it cannot be evaluated). False if a term cannot be evaluated. For
// tests of the chain rule and the metric.
bool EvaluateStationResidual(const ModelSpec& spec, const FitStation& station,
                             std::optional<double> time_offset,
                             Eigen::Matrix<double, 6, 1>* residual,
                             std::vector<Eigen::MatrixXd>* jacobians,
                             std::optional<Eigen::Matrix<double, 6, 6>>* report_per_pose = nullptr);

// Table 1 of the paper for one set: errors of the reported and of the corrected poses, hemisphere
// flips left out (core/error_statistics.h MakeTable1).
Table1 EvaluateTable1(const CorrectionChain& chain, const std::vector<FitStation>& stations,
                      const std::string& set_name);

// k-fold cross-validation, folds by CrossValidationFolds (deterministic; `serial_blocks` as
// there): static stations i % k (stations in file order), serial stations (stream samples)
// contiguous blocks of time b % k; each fold is corrected by a model fitted on the others (made
// fresh by make_spec), and the errors of all folds form one table named by
// CrossValidationTableName (MakeTable1: hemisphere flips left out).
// Throws std::invalid_argument if a training set is too small, std::runtime_error naming the fold
// if a fold's fit failed (FitResult::Failed()).
Table1 CrossValidate(const std::vector<FitStation>& stations,
                     const std::function<ModelSpec()>& make_spec, int folds,
                     const std::function<void(int)>& on_fold = {},
                     int serial_blocks = kDefaultSerialBlocks);

// Fast k-fold refits from a fit on all stations (trackcal-fit diagnose, docs/diagnose.md "Speed").
// Each fold's model is re-estimated on the stations outside the fold, starting from the full fit's
// values and keeping its preparation (polynomial normalisation, LUT grid, searched starts):
// Levenberg-Marquardt steps on the solver's cost with the Jacobian of the whitened residuals, the
// first from the full fit's normal equations with the fold's rows removed (a rank downdate of
// J^T J and J^T r). For a model linear in its parameters one undamped step is the fold's
// least-squares solution; nonlinear (physical) terms take steps until the fold's cost falls by
// less than the tolerance. A fold whose cost cannot be lowered, or a model with more than
// `max_dense_parameters` free parameters, is refitted by the solver from the same warm start.
struct FoldRefitOptions {
  // Steps per fold; a fold still moving after them keeps its best values (FoldRefit::converged
  // false). Poorly determined models (a plane on a capture it does not explain) creep along flat
  // valleys where more steps change the held-out errors little.
  int max_steps = 10;
  // Converged when a step lowers the fold's cost (0.5 chi2) by less than this times chi2/dof of
  // the full fit, or when the Gauss-Newton step would: a remaining step below ~0.1 sigma of the
  // fold's parameters (0.5 delta^T H delta < 0.005), sigma scaled (either way) by the scatter the
  // full fit actually leaves, not the model file's noise.
  double cost_tolerance = 5e-3;
  // Above this many free parameters (dense normal equations cost O(n^3)), every fold is refitted by
  // the solver from the full fit's values.
  int max_dense_parameters = 800;
  // Stations (FitStation::station) the full fit left out (FitResult::left_out,
  // solver.leave_out_unresolved): in no fold's training, still predicted by their fold's refit.
  std::vector<int> left_out;
  // The full fit's residual forms (FitResult::report_form, one per station): each fold keeps its
  // stations' forms, those of the full fit's objective (a form chosen afresh at the full fit's
  // values can differ: a station once in report form stays there during a fit; K is rebuilt at
  // the full fit's values, within the 5 % its passes allow). Empty: chosen afresh.
  std::vector<bool> report_form;
  bool Check() const { return max_steps >= 1 && cost_tolerance > 0 && max_dense_parameters >= 0; }
};

// Per fold: the refitted correction (with the calibrated volume of the fold's training stations)
// and how it was obtained.
struct FoldRefit {
  CorrectionChain chain;
  int steps = 0;              // steps taken
  bool converged = false;     // the steps converged (false: stopped at max_steps, or solver_refit)
  bool solver_refit = false;  // refitted by the solver (fallback)
  int jacobian_evaluations = 0;  // of the fold's stations (each costs about one solver iteration)
  int bound_steps = 0;  // steps that held coordinates on a bound of the full fit (HeldAtBound)
  // Every free parameter ended exactly at the full fit's value (no step lowered the fold's cost,
  // and the solver's fallback made no successful step either): the fold's "held-out" predictions
  // are the full fit's, which was fitted to the held-out stations too, so they are in-sample and
  // must not be scored as held-out (the caller refits such folds from scratch). False for a model
  // without free parameters.
  bool stayed_at_full_fit = false;
  double seconds = 0.0;           // wall time of the fold's refit
};

// `spec` holds the terms as FitModel left them after fitting all of `stations` (its values are
// restored on return); the refits minimise the solver's cost, so after a linear least-squares fit
// (FitResult::linear_least_squares) the exact folds are as cheap and are the consistent choice.
// Station i is held out in fold fold_of[i] (0 <= fold_of[i] < folds).
std::vector<FoldRefit> RefitFoldsFromFull(const std::vector<FitStation>& stations, ModelSpec* spec,
                                          const std::vector<int>& fold_of, int folds,
                                          const FoldRefitOptions& options = {});

nlohmann::json Table1ToJson(const Table1& table);

}  // namespace trackcal::fit
