// The model file (YAML): which terms the correction has, in order, and how they are fitted.
// Format reference: docs/model-file.md.
//
//   noise: {position_mm: 1.0, orientation_deg: 0.2}   # whitening of the station residuals
//   loss: {type: huber, scale: 3}                     # robust loss, scale in sigmas (optional)
//   solver: {max_iterations: 100}
//   time_offset: {value: 0.0, fixed: true}            # t_reference - t_tracker [s] (optional)
//   terms:
//     - type: polynomial
//       degree: 4
//     - type: lut
//       cell_size_mm: 100
//       smoothness: 1.0
//       parameters:                # generic per-block settings, for every term type
//         node_values: {fixed: false}
//
// Term types are looked up in TermRegistry::Global(): fit/ registers polynomial, lut and the physical
// effects (sensor_offset, receiver_gain, dipole, plane, near_field, background_field;
// fit/terms_physical.h); other
// modules register theirs without touching the parser. Consecutive physical terms are merged into one
// PhysicalGroupTerm (one forward field model) and must precede the explicit terms. Every error names
// the file, line, column and field; unknown keys are rejected.
#pragma once

#include <yaml-cpp/yaml.h>

#include <filesystem>
#include <functional>
#include <memory>
#include <mutex>
#include <optional>
#include <set>
#include <string>
#include <vector>

#include "fit/covariance.h"
#include "fit/model.h"

namespace trackcal::fit {

// Reads one YAML mapping, remembers which keys were read, and rejects the rest in Finish(). Every
// error is std::invalid_argument "FILE:LINE:COLUMN: PATH: message".
class YamlMapReader {
 public:
  YamlMapReader(YAML::Node node, std::string source, std::string path);

  const std::string& source() const { return source_; }
  const std::string& path() const { return path_; }
  const YAML::Node& node() const { return node_; }

  bool Has(const std::string& key) const;
  // Typed reads; the *Or variants return `fallback` when the key is absent.
  double GetDouble(const std::string& key) const;
  double GetDoubleOr(const std::string& key, double fallback) const;
  int GetInt(const std::string& key) const;
  int GetIntOr(const std::string& key, int fallback) const;
  bool GetBoolOr(const std::string& key, bool fallback) const;
  std::string GetString(const std::string& key) const;
  std::string GetStringOr(const std::string& key, const std::string& fallback) const;
  std::vector<double> GetDoubleList(const std::string& key) const;
  // A nested mapping (throws if absent or not a mapping).
  YamlMapReader GetMap(const std::string& key) const;
  // Marks a key as read without reading it (handled elsewhere).
  void MarkRead(const std::string& key) const { read_.insert(key); }

  // Throws naming the first key that was not read.
  void Finish() const;

  // Throws "FILE:LINE:COLUMN: PATH.key: message" at `key` (or at the map if key is empty).
  [[noreturn]] void Fail(const std::string& key, const std::string& message) const;
  // Throws for a required `key` that is absent: at a key of the mapping that misspells it ("PATH.
  // term: unknown key; did you mean 'terms' (a required field)?"), else "PATH.key: missing
  // required field" at the mapping.
  [[noreturn]] void FailMissing(const std::string& key) const;

 private:
  YAML::Node Get(const std::string& key) const;
  YAML::Node node_;
  std::string source_;
  std::string path_;
  mutable std::set<std::string> read_;
};

// Builds a term from its mapping in the model file. The reader is positioned on the term's mapping;
// "type", "name" and "parameters" are handled by the parser, the factory reads every other key it
// accepts (the parser rejects the rest).
using TermFactory = std::function<std::unique_ptr<ModelTerm>(const YamlMapReader& reader)>;

class TermRegistry {
 public:
  // Holds polynomial and lut on first use.
  static TermRegistry& Global();
  // Throws std::invalid_argument if the name is empty or taken.
  void Register(const std::string& type, TermFactory factory);
  bool Contains(const std::string& type) const;
  std::vector<std::string> Types() const;
  // Throws (through reader.Fail) for an unknown type, naming the known ones.
  std::unique_ptr<ModelTerm> Create(const std::string& type, const YamlMapReader& reader) const;

 private:
  TermRegistry() = default;
  mutable std::mutex mutex_;
  std::vector<std::pair<std::string, TermFactory>> factories_;
};

enum class LossType { kNone, kHuber, kCauchy };

struct LossOptions {
  LossType type = LossType::kNone;
  double scale = 3.0;  // in sigmas of the whitened residual: a station beyond it is down-weighted
};

// Settings of one parameter block from the file's `parameters:` mapping, applied after Prepare().
struct BlockSettings {
  std::string block;  // block name
  std::string term;   // applies only to blocks whose ParameterBlock::term is this (empty: any)
  std::string where;  // "FILE:LINE:COLUMN: PATH" for errors found when applying
  std::optional<std::vector<double>> value;  // one value (broadcast) or one per coordinate
  std::optional<bool> fixed;
  std::optional<std::vector<double>> lower, upper;
  std::optional<std::vector<double>> prior_mean, prior_sigma;
};

struct TimeOffsetSpec {
  double value = 0.0;  // reference clock minus tracker clock [s]: t_reference = t_tracker + value
  bool fixed = true;   // false: estimated when pairing streams
  double search_range = 0.5;  // [s] half-width of the search interval around `value`
};

// One entry of the file's `terms:` list as written (before physical terms are grouped).
struct ModelFileTerm {
  std::string type;  // "dipole", "polynomial", ...
  std::string name;  // instance name (unique)
  int line = 0;      // 1-based line of the entry in the file
  int model_term = 0;  // index into ModelSpec::terms of the term that holds it
  // "FILE:LINE:COLUMN: $.terms[i]": names the entry in errors found when the data are seen
  // (a LUT cell too fine for the stations' box).
  std::string where;
};

struct ModelSpec {
  std::string source;  // file name (or "<string>")
  double position_sigma = 1e-3;     // [m] position noise for whitening
  double orientation_sigma = 3.4906585039886591e-3;  // [rad] (0.2 deg) orientation noise
  // Range dependence of the noise: a station reported at distance r from the transmitter has
  // sigma * (r / noise_reference_range_m)^exponent. An EM tracker's field falls as r^-3, so its
  // position noise grows as r^4 and its orientation noise as r^3; 0 (default): constant noise.
  double position_range_exponent = 0.0;
  double orientation_range_exponent = 0.0;
  double noise_reference_range_m = 1.0;
  // A station whose residual runs through a physical group is fitted by its pose error: exactly
  // where the group's inverse resolves its report (the pose form); elsewhere (near a strong
  // object's fold) by its report's misfit under the pose metric (fit/pose_metric.h), whose
  // amplification is capped at this. The noise above already holds the room's usual
  // amplification (<= 1.3 in the paper room), hence 2; 1e9 or more puts every such station in
  // report form without the metric (noise.amplification_threshold).
  double amplification_threshold = 2.0;
  // (position, orientation) sigmas of a station reported at `reported`.
  Eigen::Vector2d StationSigmas(const Rigid3d& reported) const;
  LossOptions loss;
  int max_iterations = 100;
  double function_tolerance = 1e-12;
  // > 0: the solver also stops when a step lowers the cost by less than this times chi2/dof (5e-3:
  // a move of ~0.1 standard deviation; fit/fit_engine.cc StatisticalConvergence). 0 (default):
  // 5e-3 above 3000 free coordinates (a LUT chain: each iteration a sparse factorisation), Ceres'
  // tolerances only below (solver.statistical_tolerance): as a default for all problems it changed
  // held-out errors of poorly determined candidates by up to 6 % (fit/candidates_fast_test).
  double statistical_tolerance = 0.0;
  bool covariance = true;  // standard deviations (solver.covariance; dense analysis costs seconds for big LUTs)
  // How the standard deviations are computed (solver.covariance_estimator, fit/covariance.h):
  // sandwich (default; honest when the noise is not the model's `noise:`) or model.
  CovarianceEstimator covariance_estimator = CovarianceEstimator::kSandwich;
  // Stream samples' sandwich (solver.stream_clusters): this many contiguous runs of samples in
  // time, each one cluster, since the model's misfit is smooth along the path (fit/fit_engine.cc
  // TimeClusters). 0, or fewer than 5 samples per run: the model covariance. Static stations are
  // one cluster each.
  int stream_clusters = 32;
  // solver.leave_out_unresolved: after the solve, the stations whose physical inverse the fitted
  // model does not resolve (ambiguous or no root; not with a fitted clock offset, whose stream
  // samples are re-paired as it moves) are left out and the model solved again on the others,
  // until that set no longer changes (FitResult::left_out); the fast cross-validation's folds leave
  // them out of training too. Off by default: the fit's residual is defined and differentiated
  // exactly at those stations too (docs/fit.md, "The station residual through a physical group"),
  // and leaving them out costs accuracy there (docs/fit.md, "Stations the inverse cannot
  // resolve"). At most kMaxLeftOutFraction of the stations, else none is left out.
  bool leave_out_unresolved = false;
  std::optional<TimeOffsetSpec> time_offset;
  std::vector<std::unique_ptr<ModelTerm>> terms;
  std::vector<std::vector<BlockSettings>> block_settings;  // one list per term
  // The file's terms in order; consecutive physical terms share one ModelTerm (a
  // PhysicalGroupTerm, fit/terms_physical.h), so terms.size() <= file_terms.size().
  std::vector<ModelFileTerm> file_terms;
};

// The model file version this parser reads: a file's optional top-level `version` (absent: 1).
inline constexpr int kModelFileVersion = 1;

// Parses the model file; throws std::invalid_argument "FILE:LINE:COLUMN: PATH: message".
ModelSpec ParseModelYaml(const std::string& text, const std::string& source_name);
ModelSpec ReadModelFile(const std::filesystem::path& path);

// `trackcal-fit build`'s settings file: a model file without `terms` (noise, solver, loss; an
// empty file gives the defaults). Throws as ParseModelYaml does, and for a `terms` key.
ModelSpec ParseModelSettingsYaml(const std::string& text, const std::string& source_name);
// The settings as text that a `terms:` list can be appended to (ChainBuilderOptions::
// settings_yaml): `text` itself when it is block style, else the same mapping written out in
// block style (a flow mapping or a JSON file, document markers). Throws as ParseModelSettingsYaml.
std::string ModelSettingsBlockYaml(const std::string& text, const std::string& source_name);

// Applies a term's block settings (after Prepare()); throws naming the file position of the setting.
void ApplyBlockSettings(const std::vector<BlockSettings>& settings, ModelTerm* term);

std::string LossTypeName(LossType type);

}  // namespace trackcal::fit
