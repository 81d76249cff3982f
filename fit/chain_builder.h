// A correction chain built by held-out error (issue #5's "best chain trackcal can build"):
//
//   ChainBuilderOptions options;            // noise and solver settings of the model file
//   BuiltChain built = BuildChain(calibration_stations, options);
//   built.fit.chain.Apply(reported);        // the fitted chain; built.model_text reproduces it
//
// Greedy, without truth values:
//   1. Sources. Starting from no physical term, each round tries every source type of
//      `source_types` (a searched dipole then plane, a searched dipole, a searched plane, a
//      searched dipole pair) added to the
//      sources found so far (given as start values, free). The physical group is initialised as
//      the fitting engine does (the start-value searches of fit/terms_physical.h, then the group's
//      refinement, projected against the polynomial that follows), and scored by what an explicit
//      term after it can still do on held-out stations: the blocked cross-validation of a ridge
//      polynomial (PolynomialTerm::BlockedRidgeCv: whole layers of the calibration grid held out
//      in turn) on the poses the group leaves, at the best degree and weight. The best addition is
//      kept while it lowers that score by at least `min_relative_gain`.
//   2. The explicit term. Its degree and per-part ridge weights are the blocked cross-validation's
//      optimum on what the final group leaves (the full chain's physical part, not a group fitted
//      without the sources found later).
//   3. The fit: the final model (sources with their found values as starts, then one position and
//      one orientation polynomial with the chosen weights) fitted by FitModel, the group either
//      held at its values (`refit_group` false: the chain the cross-validation scored) or fitted
//      jointly.
// Reference: docs/model-file.md, "Building a chain".
#pragma once

#include <string>
#include <vector>

#include "fit/fit_engine.h"
#include "fit/model_file.h"

namespace trackcal::fit {

struct ChainBuilderOptions {
  // The model file's settings other than `terms:` (noise, solver, loss), as YAML mapping lines;
  // the builder appends `terms:`. `solver.covariance` and `loss` apply to the final fit only: the
  // search's cross-validations are least squares over every station (docs/model-file.md).
  std::string settings_yaml;
  // Source types tried each round: "dipole_plane" (a dipole, then a plane searched against what
  // it leaves), "dipole", "plane", "dipole_pair" (two dipoles searched together). One at a time,
  // the first source of a near object and a plane is a stand-in (on the paper preset a pair, the
  // frame and the floor's image 1.6 m below the transmitter), which then blocks the floor.
  std::vector<std::string> source_types = {"dipole_plane", "dipole", "plane", "dipole_pair"};
  int max_sources = 8;  // physical sources at most (a pair counts as two)
  // A round's best addition is kept if it lowers the score by at least this fraction.
  double min_relative_gain = 0.03;
  // Degrees of the explicit polynomial scored (each at its best ridge weight).
  int min_degree = 2;
  int max_degree = 8;
  // Degree of the polynomial the source searches project against (what the group's refinement
  // leaves to the explicit term).
  int search_degree = 8;
  // Held-out stations are predicted as the runtime extrapolates explicit terms after a physical
  // group (`linear`, core/correction.h) out to this reach [m]; 0: the box value held (`clamp`).
  double cv_linear_reach = 0.1;
  // false: the final fit holds the group at the values the search and refinement gave (the chain
  // that was scored); true: the group is fitted jointly with the polynomials.
  bool refit_group = false;
  // Throws std::invalid_argument naming the field.
  void Check() const;
};

// One candidate scored.
struct ChainBuilderStep {
  int round = 0;
  std::string added;     // "dipole", "plane", "dipole_pair"; "" for the start (no source)
  double score = 0.0;    // whitened held-out error per station (lower is better)
  int degree = 0;        // the explicit term's best degree there
  bool kept = false;     // the round's winner and kept
  std::string sources;   // the sources' YAML (term items) of this candidate, found values
  double seconds = 0.0;
};

struct BuiltChain {
  std::string model_text;  // the final model file (fit again: the same chain)
  std::string sources;     // the sources found (term items, their values as starts, free)
  int degree = 0;                                        // of the explicit term
  Eigen::Vector2d ridge = Eigen::Vector2d::Zero();       // position, orientation weights
  double score = 0.0;                                    // of the final group
  std::vector<ChainBuilderStep> steps;                   // every candidate, in order
  FitResult fit;                                         // of model_text
  double seconds = 0.0;
};

// Builds and fits the chain on `stations` (the calibration set). Throws std::invalid_argument for
// bad options or settings, and for no more stations than a degree-`min_degree` polynomial has
// coefficients (its cross-validation needs more).
BuiltChain BuildChain(const std::vector<FitStation>& stations, const ChainBuilderOptions& options,
                      const FitOptions& fit_options = {});

// The explicit term's blocked cross-validation after `group` (null: none) on `stations`: per
// degree in [min_degree, max_degree] the held-out error per station, whitened as the fit whitens
// the station residuals (`noise`'s sigmas and range exponents), at each part's best weight of
// PolynomialTerm::RidgeGrid() (the model file's `ridge`: the fit's normal equations are the
// cross-validation's), the best degree and its weights.
struct ExplicitCv {
  std::vector<double> score;  // per degree
  int degree = 0;
  Eigen::Vector2d ridge = Eigen::Vector2d::Zero();
  double best = 0.0;
};
ExplicitCv ExplicitTermCv(const Correction* group, const std::vector<FitStation>& stations,
                          const ModelSpec& noise, int min_degree, int max_degree,
                          double linear_reach);

}  // namespace trackcal::fit
