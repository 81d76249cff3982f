// Candidate effects: which physical effect is the model missing? (`trackcal-fit diagnose`)
//
//   Diagnosis d = DiagnoseCandidates(calibration_stations, model_text, "model.yaml", "capture/",
//   {}); std::cout << d.ToJson().dump(2);   // the document of docs/diagnose.md
//
// For every effect of the catalog (DefaultCatalog(): sensor_offset, receiver_gain, dipole,
// dipole_pair, plane, near_field, background_field, robust_loss, time_offset) that the model lacks, the model plus
// that one effect is
// fitted and scored against the model itself:
//   - k-fold cross-validation with the same folds for the base and every candidate (station i in
//     fold i % k; serial stream samples by contiguous blocks of time, block b in fold b % k, the
//     rule of fit/fit_engine.h's CrossValidationFolds): held-out mean position [mm] and
//     orientation [deg] errors and their drop in percent;
//   - a one-sided Wilcoxon signed-rank test of the per-station held-out whitened squared errors
//     (base minus candidate > 0): p_value;
//   - BIC with the noise scale profiled out, n ln(chi2 / n) + k ln(n), over the n = 6 N whitened
//     station residuals of the fit on all stations (a robust loss counts its outliers as 6 free
//     parameters each: the mean-shift outlier model);
// and called significant only if the held-out improvement is real (p below alpha / number of
// candidates tested, and the held-out mean error falls by at least min_drop_percent) and BIC
// prefers it (delta_bic < max_delta_bic) and the added term's fit identifies a physical source
// (PhysicalEvidence: strength 3 sigma from its null value, location determined). Candidates are
// ranked significant first, then by held-out error (between two source terms that explain the same
// structure, the one with the lower BIC on all stations first). The verdict names the top
// significant candidate, or
// says plainly that none explains what remains.
//
// Each source term of the model that the base fit no longer identifies (Diagnosis::
// unsupported_terms) is also tried removed: a removal (effect "remove"), claimed under the
// replacement's rule (BIC decisively for the smaller model, neither held-out mean higher) and only
// when no addition is (docs/diagnose.md, "Removals").
//
// Each source term of the model (dipole, plane; none whose blocks the file holds fixed) is also
// tried swapped for the other kind, searched afresh in its place: a replacement. A dipole at the
// transmitter's mirror image and a plane explain much the same structure, and which one a diagnosis
// adds first can be decided by what the model still lacks then. A replacement is claimed only when
// no addition is, when BIC prefers it decisively and its held-out error is lower (docs/diagnose.md,
// "Replacements").
//
// The candidate model is the model file's YAML with the effect's term inserted into `terms:`
// (physical terms before explicit ones: polynomial, lut) or its `loss:` / `time_offset:` set;
// `model_change` is that YAML, with the fitted values as start values where the term searches them
// (dipole, plane), and the cross-validation evaluates exactly that change. A flexible fallback (a
// degree-3 polynomial) is scored apart when no effect is significant. Reference: docs/diagnose.md.
#pragma once

#include <Eigen/Core>
#include <cmath>
#include <functional>
#include <nlohmann/json.hpp>
#include <optional>
#include <string>
#include <vector>

#include "core/error_statistics.h"
#include "fit/distributions.h"
#include "fit/fit_engine.h"
#include "fit/model.h"

namespace trackcal::fit {

enum class CandidateKind {
  kTerm,        // a term inserted into `terms:`
  kRobustLoss,  // `loss:` set (the model has none): outliers such as hemisphere flips
  kTimeOffset,  // `time_offset:` estimated (data paired from streams,
                // CandidateOptions::pair_streams)
  kRemoval,     // a source term of the model removed (Diagnosis::unsupported_terms; effect
                // kRemoveEffect, `replaces` names the term, `insert_index` its item)
};

// The effect name of a removal candidate ("remove"); `effects` may list it.
inline constexpr char kRemoveEffect[] = "remove";

// Stations paired from streams with one time-offset setting (see CandidateOptions::pair_streams).
struct PairedStations {
  std::vector<FitStation> stations;  // the calib stations; `time` is the tracker sample's time
  double time_offset_s = 0.0;        // the offset used (estimated if the setting asked for it)
};

// One effect of the catalog.
struct CatalogEffect {
  std::string effect;  // name in reports and --effects ("dipole", "robust_loss")
  CandidateKind kind = CandidateKind::kTerm;
  std::string term_yaml;    // kTerm: the term's mapping, e.g. "type: dipole" (YAML)
  bool physical = true;     // kTerm: physical terms are inserted before the explicit ones
  bool repeatable = false;  // kTerm: tested even when the model already has a term of this type
  std::string description;  // for the verdict: "a ferromagnetic object", "a sensor offset"
  // kTerm: how many terms of `term_yaml` go in together (> 1 needs `repeatable`). 2 is a pair of
  // sources searched together (a dipole pair: two objects whose fields add up where neither alone
  // is identified); the group searches the second with the first placed and projected out and
  // refines both jointly (fit/terms_physical.h). Each term must pass the physical conditions.
  int count = 1;
  // A catch-all for what is not placed one by one (background_field): where a located source
  // explains the same structure, the located source is ranked first (RankFirst).
  bool yields_to_located = false;
};

// sensor_offset, receiver_gain, dipole (repeatable), dipole_pair (two dipoles), plane
// (repeatable), near_field, background_field, robust_loss, time_offset.
// Term types that are not registered in TermRegistry::Global() are skipped (Diagnosis::skipped).
std::vector<CatalogEffect> DefaultCatalog();

// The flexible fallback: a degree-3 polynomial appended after the model's terms. Not an effect and
// never ranked with them; scored the same way, it tells whether the structure that remains is real
// when no catalog effect explains it.
std::vector<CatalogEffect> DefaultFlexibleFallback();

// The physical evidence for an added term, decided from its fit on all stations (the claim rule's
// physical conditions, docs/diagnose.md "Significance"):
//   - strength: the term's physical strength must lie at least `min_strength_sigma` from its null
//     value (dipole polarisability 0, plane attenuation 0, near_field octupole 0, receiver_gain
//     G = I, sensor_offset translation 0 / rotation identity), by a joint Wald test on each strength
//     block (the block's covariance; its standard deviations alone when that is unavailable),
//     expressed as the equivalent two-sided normal deviate; terms with several strength blocks
//     (sensor_offset) take the strongest, Bonferroni-corrected;
//   - location: a term that places a source (dipole location, plane distance and normal) must place
//     it: the largest standard deviation of the source's position must not exceed its distance from
//     the measured volume (the box of the stations' reference positions), otherwise the fit says
//     "something out there" and not "this object"; a plane's normal must be determined too (its
//     angular standard deviation at most `max_normal_sigma_rad`, the fit's own identifiability
//     scale of a normal): a plane whose orientation is open by 20 deg is no particular wall.
// Term types with no strength block (explicit terms, unknown types) are not assessed.
struct PhysicalEvidence {
  bool assessed = false;           // the term type has a strength block
  std::string strength_what;       // "polarisability_m3", "gain_matrix - I", ...
  double strength_chi2 = NAN;      // Wald statistic of the strongest block
  int strength_dof = 0;            // its degrees of freedom
  // The sandwich's clusters the statistic refers to (Hotelling's T^2 over them); 0: chi-square.
  int strength_clusters = 0;
  double strength_p = NAN;         // its p-value (Bonferroni-corrected over the blocks)
  double strength_sigma = NAN;     // the equivalent two-sided normal deviate of strength_p
  bool has_location = false;       // the term places a source (dipole, plane)
  double location_sigma_m = NAN;   // largest standard deviation of the source's position [m]
  double location_distance_m = NAN;  // distance of the source from the measured volume [m]
  double normal_sigma_rad = NAN;     // plane: the normal's angular standard deviation [rad]
  bool normal_ok = true;             // plane: the normal is determined (part of location_ok)
  // Unit vector from the measured volume's centre towards the source (a dipole's location; a
  // plane's nearest point); zero when unknown. The verdict names it for structure it cannot place.
  Eigen::Vector3d direction = Eigen::Vector3d::Zero();
  double noise_scale = 1.0;        // factor applied to the fit's standard deviations
  bool strength_ok = true;
  bool location_ok = true;
  bool supported() const { return strength_ok && location_ok; }
  std::string Describe() const;  // in words, for `reason`
  nlohmann::json ToJson() const;
};

// Assesses the added term of type `term_type` from its parameter reports (fit/fit_engine.h), with
// `volume_points` the stations' reference positions in the transmitter frame. `noise_scale`
// multiplies every standard deviation: DiagnoseCandidates passes sqrt(chi2/dof) of the candidate's
// fit, profiling the noise scale out as its BIC does (a model file's sigmas are guesses: the
// default 1 mm against a tracker's 0.06 mm would make every standard deviation 17x too large).
// `max_normal_sigma_rad` bounds a plane's normal's angular standard deviation (after scaling).
// `num_clusters`: the sandwich covariance's clusters G (FitResult::covariance_clusters), whose
// k x k block covariances rest on G - 1 degrees of freedom: a block's Wald statistic W is then
// referred to Hotelling's T^2, W (G - k) / ((G - 1) k) ~ F(k, G - k), not to chi-square(k), which
// would be optimistic with few clusters (32 runs of stream samples); G <= k: no test (the block
// is skipped; when no block can be tested, strength_sigma stays NaN, strength_ok is false and
// strength_what says why). 0: the model covariance, chi-square.
PhysicalEvidence AssessPhysicalEvidence(const std::string& term_type,
                                        const std::vector<ParameterReport>& blocks,
                                        const std::vector<Eigen::Vector3d>& volume_points,
                                        double min_strength_sigma = 3.0, double noise_scale = 1.0,
                                        double max_normal_sigma_rad = 0.1, int num_clusters = 0);

// A fitted physical term stated with units and +- 1 sigma ("a conducting plane 0.80 m +- 0.04
// from the transmitter along the normal (0.000, 0.000, 1.000) +- 1.7 deg, attenuation ..."), the
// candidates' `statement`; empty when `parameters` lack a block of `term_type`
// (fit/terms_physical.h block names).
std::string PhysicalStatement(const std::string& term_type,
                              const std::vector<ParameterReport>& parameters);

// P(T^2 > w) for Hotelling's T^2 of `dof` coordinates from a covariance estimated over `clusters`
// independent clusters: FDistributionUpperTail(w (G - k) / ((G - 1) k), k, G - k)
// (fit/registration.h); 1 when G <= k.
double HotellingUpperTail(double w, int dof, int clusters);

// The two-sided normal deviate z with P(|N(0,1)| > z) = p (p in (0, 1]); infinity for p = 0.
double TwoSidedNormalDeviate(double p);

struct CandidateOptions {
  int folds = 5;  // k of the k-fold cross-validation (>= 2)
  // Effects to test (names of the catalog, and "remove" for the removals of the model's
  // unidentified source terms); empty: every applicable one.
  std::vector<std::string> effects;
  // The catalog (default: DefaultCatalog()).
  std::vector<CatalogEffect> catalog = DefaultCatalog();
  // Flexible terms scored separately (Diagnosis::flexible); empty: none.
  std::vector<CatalogEffect> flexible = DefaultFlexibleFallback();
  // Family-wise level of the held-out test: each candidate's p must be below family_alpha / m for m
  // candidates tested (Bonferroni), so the chance of any false claim is at most family_alpha.
  double family_alpha = 0.01;
  // Minimum drop of the held-out mean position or orientation error [%]: a statistically sure but
  // negligible gain (0.5 % of a 0.1 mm error) is not worth a model change.
  double min_drop_percent = 5.0;
  // delta BIC must be below this: -10 is "very strong" evidence (Kass & Raftery 1995, 2 ln B > 10).
  double max_delta_bic = -10.0;
  // robust_loss is claimed only if at most this fraction of the stations exceed the loss scale:
  // outliers are rare by definition (flips, bad reference poses); when many stations exceed it, a
  // robust loss only hides an effect the model lacks.
  double max_outlier_fraction = 0.05;
  // Stations where the base's or a candidate's runtime inverse does not resolve the report (no
  // root, or an ambiguous one: next to a strong object, core/physical_correction.h) are left out
  // of that candidate's comparisons when at most this fraction of the stations are; more, and they
  // count. The full paper capture's toolbox, 0.27 m from the grid, leaves 24-26 of 480 (5 %).
  double max_unresolved_fraction = 0.1;
  // A gross outlier must also be gross against this many nearest stations (by reference position;
  // 6: a grid station's face neighbours): a whole neighbourhood beyond the capture's errors is an
  // effect the model lacks there, not outliers (docs/diagnose.md). 0: the capture-wide test only.
  int outlier_neighbours = 6;
  // The added term's physical strength must lie at least this many standard deviations from its
  // null value, and a source it places must be placed (PhysicalEvidence): a held-out gain from a
  // term whose strength is 0.5 sigma from zero, or whose location is uncertain by more than its
  // distance from the volume, is real structure but not evidence of that object. 3: the issue's
  // "three standard deviations"; 0 disables the physical conditions.
  double min_strength_sigma = 3.0;
  // A plane candidate's normal must be known to this angular standard deviation [rad] (the hypot
  // of its two tangent angles, noise-scaled as the strength): 0.1 rad (5.7 deg) is the fit's own
  // identifiability scale of a normal (fit/terms_physical.cc, kNormalScaleRad: beyond it the fit
  // flags the normal as poorly identified). Measured on the main job's capture after the sensor
  // offset, workbench frame and floor: the floor's normal came out +- 3.0 deg; a plane standing in
  // for the +y monitors +- 19.9 deg (docs/diagnose.md, condition 5).
  double max_normal_sigma_rad = 0.1;
  // 0: cross-validate every candidate. N > 0: fit all on the full set first, then cross-validate
  // only the N with the lowest delta BIC (the rest are reported screened out, never significant). 3
  // by default: with exact folds (exact_cv) cross-validating all six triples the run; the fast
  // folds make the others cheap, but screening also decides which candidates can be claimed, so
  // the default is kept (docs/diagnose.md, Speed).
  int cross_validate_top = 3;
  // Loss of the robust_loss candidate: Cauchy (an outlier's pull vanishes; a Huber loss still pulls
  // with the scale), scale 3 sigma of the whitened residual.
  LossOptions robust_loss = {LossType::kCauchy, 3.0};
  // Set when the stations were paired from streams (fit/stream_pairing.h): pairs the streams again
  // with the given time-offset setting. Enables the time_offset candidate (when the model's offset
  // is absent or fixed), which is scored on the stations both pairings have (matched by time).
  std::function<PairedStations(const TimeOffsetSpec&)> pair_streams;
  // Serial stations (stream samples, SerialSamples in fit/fit_engine.h: neighbours ~10 ms apart
  // share the model's misfit): the stations are cut into this many contiguous blocks of time of
  // about equal count (TimeClusters, at least 5 samples each; fewer blocks on a short stream, but
  // never fewer than `folds`); block b is held out in fold b mod k, and the paired test is the
  // Wilcoxon test on the blocks' mean differences instead of the stations'. 32: the fit's own
  // sandwich clusters of stream samples (ModelSpec::stream_clusters), which treat the same runs as
  // independent; 0.6 s of a 20 s stream, 1.9 s of a 60 s one. Enough blocks that a real effect
  // reaches the Bonferroni level (32 blocks all positive: p = 4e-7), few enough that their means
  // are nearly independent: on the paper room's 20 and 60 s streams every candidate the room does
  // not have got p >= 0.012 (docs/diagnose.md). 0: the static treatment (folds i mod k,
  // per-station test) for every capture.
  int serial_blocks = kDefaultSerialBlocks;
  // Cross-validation method. false (default): each fold's model is re-estimated from the fit on all
  // stations by Gauss-Newton steps with the fold's rows removed (fit/fit_engine.h,
  // RefitFoldsFromFull: one step is exact for terms linear in their parameters, physical terms take
  // steps until the fold's cost settles). true: every fold is fitted from scratch, as
  // `trackcal-fit fit --folds` does (about 10 times the CPU; docs/diagnose.md, Speed).
  bool exact_cv = false;
  // Worker threads for the candidates' fits and cross-validations (0: the hardware's cores). The
  // results do not depend on it: every candidate is computed alone, single-threaded.
  int num_threads = 0;
  // Progress messages ("fitting dipole (fold 3/5)"); the CLI prints them on stderr. Called from
  // worker threads, one call at a time.
  std::function<void(const std::string&)> progress;
  // Throws std::invalid_argument naming the field.
  void Check() const;
};

// Scores of the model itself.
struct BaseScores {
  bool converged = false;
  double cv_position_mm_mean = 0.0;      // held-out mean position error [mm]
  double cv_orientation_deg_mean = 0.0;  // held-out mean orientation error [deg]
  double final_cost = 0.0;               // the fit's cost on all stations
  int num_residuals = 0;                 // station residuals: 6 per station
  int num_free_parameters = 0;           // tangent-space count, as the fit reports
  double chi2 = 0.0;  // sum of squared whitened station residuals (loss applied as inliers)
  double chi2_per_dof = 0.0;
  double bic = 0.0;  // n ln(chi2 / n) + k ln(n)
  Table1 table1;     // cross-validation table (before / after)
  double seconds = 0.0;
};

struct Candidate {
  std::string effect;  // catalog name
  CandidateKind kind = CandidateKind::kTerm;
  std::string model_change;         // YAML to add (a list item for terms, a `loss:` mapping)
  std::optional<int> insert_index;  // kTerm: index in `terms:` before which it goes
  // A replacement: the name of the model's source term (dipole or plane) that the added term takes
  // the place of (item `insert_index` of `terms:` is removed first); empty: an addition. A removal
  // (kRemoval): the term removed, item `insert_index`; its model_change is empty.
  std::string replaces;
  std::string term_name;            // kTerm: the added term's name in reports (the first)
  std::vector<std::string> term_names;  // kTerm: every added term's name (two for a pair)
  std::string model_text;           // the whole candidate model file
  bool fitted = false;              // false: the fit failed (error says why)
  // A nested candidate whose fit ran but ended above the base's chi2 (fitted false): the diagnosis
  // looked at it, so it stays in the Bonferroni family (a smaller family would make every other
  // candidate's test less strict).
  bool ended_above_base = false;
  std::string error;
  bool converged = false;
  bool cross_validated = false;  // false: screened out by BIC (cross_validate_top) or failed
  double cv_position_mm_mean = NAN;
  double cv_orientation_deg_mean = NAN;
  // The base's held-out means over the same stations (without the stations left out of the
  // comparison: the base loss's outliers, unresolved stations); the drops are against these.
  double cv_base_position_mm_mean = NAN;
  double cv_base_orientation_deg_mean = NAN;
  double drop_position_percent = NAN;  // 100 (base - candidate) / base of the held-out mean
  double drop_orientation_percent = NAN;
  double cv_whitened_mean = NAN;  // mean held-out whitened squared error (ranking key)
  double bic = NAN;
  double delta_bic = NAN;  // candidate BIC - base BIC (negative: better)
  int num_free_parameters = 0;
  double p_value = NAN;  // one-sided Wilcoxon signed-rank, held-out errors
  bool significant = false;
  std::string reason;                       // why (not) significant, in words
  // kTerm: strength and location tests of the added term (of several: the weakest one's).
  PhysicalEvidence evidence;
  std::vector<ParameterReport> parameters;  // the added term's blocks; time_offset.value for
                                            // time_offset; empty for robust_loss
  // What the parameters' standard deviations were multiplied by: sqrt(chi2/dof) of the candidate's
  // fit when its covariance is the model's (the model file's noise taken as the truth), 1 for the
  // sandwich (already scaled by the residuals).
  double stddev_scale = 1.0;
  std::vector<int> outlier_stations;        // robust_loss: stations beyond the loss scale
  // robust_loss: stations as far beyond the capture's errors whose neighbours' errors are as large
  // (a local effect the model lacks, not outliers).
  std::vector<int> local_structure_stations;
  std::string local_structure_note;  // where they are, in words (empty: none)
  // Stations left out of delta BIC because the candidate's or the base's runtime inverse found no
  // root or an ambiguous one there (at most max_unresolved_fraction of them; else they count).
  int bic_unresolved_left_out = 0;
  // The same for the held-out comparison (drops, paired test, ranking), by the fold chains.
  int cv_unresolved_left_out = 0;
  std::string statement;                    // physical summary with units and +- 1 sigma
  double seconds = 0.0;
};

struct Diagnosis {
  std::string model;  // model file name
  std::string data;   // data name (capture folder or poses.csv)
  int folds = 0;
  int num_stations = 0;
  BaseScores base;
  std::vector<Candidate> candidates;  // ranked: significant first, then by held-out error
  std::vector<Candidate> flexible;    // flexible fallback (not effects), same scores
  std::vector<std::string> skipped;  // "near_field: model has it", "plane: term type not available"
  // family_alpha / number of candidates tested: every one fitted (additions, pairs and
  // replacements; screened out of the cross-validation or not), not the flexible fallback.
  double p_threshold = 0.0;
  std::optional<std::string> verdict_effect;  // top significant candidate
  std::string verdict_text;
  // No candidate is claimed, but held-out data show structure the model lacks (a candidate that
  // fits it without identifying its source, or a flexible term that lowers the held-out error):
  // the verdict says so rather than "nothing". In --json as verdict.unexplained_structure.
  bool unexplained_structure = false;
  // Source terms of the model (dipole, plane; none with a block the file holds fixed) that the base
  // fit no longer identifies (PhysicalEvidence of the base fit: strength or location fails the
  // claim conditions): often a source added to stand in for one that a later term explains better.
  // The verdict names them; in --json "unsupported_terms".
  struct UnsupportedTerm {
    std::string term;  // its name ("dipole_2")
    std::string type;
    int index = 0;  // its `terms:` item (0-based)
    PhysicalEvidence evidence;
  };
  std::vector<UnsupportedTerm> unsupported_terms;
  std::string unsupported_note;  // the verdict's sentence on them ("" without any)
  double seconds = 0.0;
  // Streams: the clock offset they were paired at (reference minus tracker [s]; set by the caller,
  // who paired them: the model's joint estimate when it frees the offset, fit/fit_run.h
  // PairAtFittedOffset). In --json as "time_offset_s" (null for static stations).
  std::optional<double> time_offset_s;
  // Serial stations (CandidateOptions::serial_blocks): the number of contiguous blocks of time the
  // folds and the paired test use; 0 for static stations (folds i mod k, per-station test). In
  // --json as "paired_test_blocks".
  int paired_test_blocks = 0;
  // The smallest p the paired test can give on these data (WilcoxonSmallestP over the blocks of
  // time, or over the stations when static): with every block or station favouring a candidate.
  // Not below p_threshold: no candidate but robust_loss (its p is its outliers' test) can be
  // claimed, whatever the data show, and test_power_note says so and what would lift the limit.
  // In --json as "paired_test_smallest_p" and verdict.test_power_note.
  double paired_test_smallest_p = 0.0;
  std::string test_power_note;  // "" when the test can reach p_threshold
  // The JSON document of `trackcal-fit diagnose --json` (docs/diagnose.md).
  nlohmann::json ToJson() const;
};

// Fits the model given as model-file text (`model_source` names it in errors) to `stations` (the
// calibration set), then each candidate, scores and ranks them. Throws std::invalid_argument for a
// bad model, bad options or too few stations (fewer than 2 per fold or 12 in all); a candidate
// whose fit fails is reported with `error` set, not thrown.
Diagnosis DiagnoseCandidates(const std::vector<FitStation>& stations, const std::string& model_text,
                             const std::string& model_source, const std::string& data_source,
                             const CandidateOptions& options = {});

// A significant candidate as the ranking's tie rule sees it (RankFirst).
struct RankEntry {
  std::string effect;
  double cv_whitened_mean = 0.0;  // held-out whitened error, mean over stations
  // Held-out whitened error per station of the base fit (NaN: none), for the paired test.
  std::vector<double> cv_whitened_by_station;
  double delta_bic = 0.0;        // on all stations, against the base model
  bool has_location = false;     // the term places a source (dipole, plane)
  double strength_sigma = 0.0;   // its strength's distance from null (PhysicalEvidence)
  bool yields_to_located = false;  // CatalogEffect::yields_to_located
};

struct RankPick {
  size_t index = 0;  // the entry ranked first
  std::string note;  // why it goes before the held-out best (empty: it is the held-out best)
};

// Which of the significant candidates goes first, `entries` sorted by held-out error (front: the
// best). The held-out best, unless another explains the same structure: its held-out errors are
// not significantly larger (one-sided paired Wilcoxon over the stations, p >= family_alpha) and
//   - both place a source: the other fits all stations decisively better (delta BIC lower by
//     more than |max_delta_bic|) or, within that, its strength is better determined;
//   - the held-out best is a catch-all (yields_to_located) and the other places a source whose fit
//     to all stations is not decisively worse: the located source, fewer parameters with a
//     meaning, goes first; the catch-all can follow it. Among several such sources the located
//     rule above decides, and none that fits decisively worse than the catch-all goes first.
// Entries without a finite strength_sigma take no part in the tie rule. Stations without held-out
// errors in both entries are left out of the paired test; with none left it finds no difference
// (p = 1), so the entry counts as not worse.
// `block_of`: the block of time of each base station for serial stations (PairedGreaterP; empty:
// static stations, the test is over stations).
RankPick RankFirst(const std::vector<RankEntry>& entries, double family_alpha, double max_delta_bic,
                   const std::vector<int>& block_of = {});

// The stand-in rule (DiagnoseCandidates, docs/diagnose.md "Stand-ins"): a term that could be
// claimed is held back when another candidate, which passes the statistical tests but not the
// physical conditions, has smaller held-out errors station by station. `claimed` and each of
// `others`: held-out whitened error per base station (NaN: none; stations without both are left
// out). Returns the first other whose paired test (PairedGreaterP on claimed and other)
// gives p < family_alpha, with that p; nullopt if none does.
struct StandIn {
  size_t other = 0;
  double p_value = 1.0;
};
std::optional<StandIn> FindStandIn(const std::vector<double>& claimed,
                                   const std::vector<std::vector<double>>& others,
                                   double family_alpha, const std::vector<int>& block_of = {});

// One-sided Wilcoxon signed-rank test that the differences d are positive (normal approximation
// with tie and continuity corrections; zeros dropped). Returns the p-value (1 when no difference is
// non-zero).
double WilcoxonSignedRankGreater(const std::vector<double>& differences);

// The smallest p WilcoxonSignedRankGreater gives on n differences (all positive, no ties): the
// most a paired test over n stations or blocks can show (5: 0.030, 9: 0.0046, 32: 4e-7). 1 for
// n <= 0.
double WilcoxonSmallestP(int n);

// p that the held-out errors `a` are larger than `b`, paired by station (stations without both
// finite left out). `block_of` empty: WilcoxonSignedRankGreater on the stations' differences a - b.
// Else the block of each station (negative: none): the same test on the blocks' mean differences,
// since serial stations' differences are correlated within a block and a per-station test treats
// thousands of them as independent.
double PairedGreaterP(const std::vector<double>& a, const std::vector<double>& b,
                      const std::vector<int>& block_of = {});

// The same on differences already taken (non-finite ones left out): block means when `block_of`
// (one per difference) is not empty.
double PairedDifferencesGreaterP(const std::vector<double>& differences,
                                 const std::vector<int>& block_of = {});

// The first stage of the retry of an added source (a candidate that contains the base and fits
// its stations worse, fit/candidates.cc): `term_yaml` (a dipole's or plane's mapping with its
// fitted start written in) with the source's location held where that start puts it (a dipole's
// location_in_transmitter, a plane's distance_m and normal_in_transmitter: `fixed: true`, any
// `value:` of theirs dropped). Every other `parameters:` setting of the term stays (a user's
// catalog term: fixed blocks, priors, bounds). Other types: `term_yaml` unchanged.
std::string HoldSourceLocation(const std::string& type, const std::string& term_yaml);

// The terminal rendering: table, verdict, the YAML to add.
std::string FormatDiagnosis(const Diagnosis& diagnosis);

}  // namespace trackcal::fit
