#include "fit/candidates.h"

#include <yaml-cpp/yaml.h>

#include <Eigen/Eigenvalues>
#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <iomanip>
#include <limits>
#include <map>
#include <memory>
#include <mutex>
#include <numeric>
#include <set>
#include <sstream>
#include <stdexcept>
#include <thread>

#include "fit/model_file.h"
#include "fit/registration.h"
#include "fit/terms_time_offset.h"

namespace trackcal::fit {
namespace {

// A replacement's held-out mean may be this much higher (percent) and still count as no higher: the
// held-out means' own precision (see DiagnoseCandidates' significance rule).
constexpr double kReplacementTiePercent = 0.5;

using Clock = std::chrono::steady_clock;

double SecondsSince(Clock::time_point start) {
  return std::chrono::duration<double>(Clock::now() - start).count();
}

nlohmann::json NumberOrNull(double v) {
  return std::isfinite(v) ? nlohmann::json(v) : nlohmann::json();
}

// Per-station errors of a chain: magnitudes for the tables, whitened squared residuals (the fit's
// own station residual, fit/model.h, with the station's sigmas as the fit whitens it:
// ModelSpec::StationSigmas, range-dependent when the model's noise says so) for the paired test
// and BIC.
struct StationErrors {
  std::vector<double> position_mm;
  std::vector<double> orientation_deg;
  std::vector<double> whitened_sq;  // |r|^2 of the 6 whitened residuals
  std::vector<Rigid3d> corrected;
  // The chain's runtime inverse did not give the one true pose behind the report: no root (its
  // best guess) or an ambiguous one (a fold next to a strong object, where report noise is
  // amplified beyond max_noise_gain: core/physical_correction.h). The error there measures the
  // amplification, not the model's misfit.
  std::vector<bool> unresolved;
};

// `reference_shift_s`: a clock offset fitted jointly with the chain moved the stations' reference
// poses along their velocities by this much from where they were paired (dt - dt0, as the fit's
// residuals, fit/terms_time_offset.h); the errors are taken against the moved poses.
void AppendErrors(const CorrectionChain& chain, const FitStation& s, const ModelSpec& noise,
                  StationErrors* out, size_t index, double reference_shift_s = 0.0) {
  const CorrectedPose applied = chain.Apply(s.reported);
  const Rigid3d& c = applied.pose;
  out->unresolved[index] = applied.status != CorrectionStatus::kConverged;
  Rigid3d reference = s.reference;
  if (reference_shift_s != 0.0) {
    ShiftReference<double>(s.reference, s.reference_velocity, s.reference_angular_velocity,
                           reference_shift_s, &reference.translation, &reference.rotation);
  }
  const Eigen::Vector3d dp = c.translation - reference.translation;
  const Eigen::Vector3d dq = OrientationErrorVector<double>(c.rotation, reference.rotation);
  out->position_mm[index] = dp.norm() * 1e3;
  out->orientation_deg[index] = OrientationErrorAngle(c, reference) * kDegPerRad;
  const Eigen::Vector2d sigmas = noise.StationSigmas(s.reported);
  out->whitened_sq[index] =
      dp.squaredNorm() / (sigmas[0] * sigmas[0]) + dq.squaredNorm() / (sigmas[1] * sigmas[1]);
  out->corrected[index] = c;
}

StationErrors MakeErrors(size_t n) {
  StationErrors e;
  e.position_mm.assign(n, NAN);
  e.orientation_deg.assign(n, NAN);
  e.whitened_sq.assign(n, NAN);
  e.corrected.assign(n, Rigid3d());
  e.unresolved.assign(n, false);
  return e;
}

double Mean(const std::vector<double>& v) {
  return v.empty() ? NAN : std::accumulate(v.begin(), v.end(), 0.0) / static_cast<double>(v.size());
}

// k-fold cross-validation of one model text: station i is held out in fold fold_of[i] (i % k for
// the base; the same folds for every model, so per-station errors pair up).
StationErrors CrossValidateStations(const std::vector<FitStation>& stations,
                                    const std::vector<int>& fold_of, const std::string& text,
                                    const std::string& source, int folds, const ModelSpec& noise,
                                    const std::function<void(int)>& on_fold) {
  StationErrors e = MakeErrors(stations.size());
  for (int f = 0; f < folds; ++f) {
    if (on_fold) on_fold(f);
    std::vector<FitStation> train;
    for (size_t i = 0; i < stations.size(); ++i) {
      if (fold_of[i] != f) train.push_back(stations[i]);
    }
    ModelSpec spec = ParseModelYaml(text, source);
    const double paired_at = spec.time_offset ? spec.time_offset->value : 0.0;
    FitOptions fo;
    fo.compute_covariance = false;
    const FitResult fit = FitModel(train, &spec, fo);
    // A clock offset fitted with the model (streams with velocities) moves the references.
    const double shift = spec.time_offset ? spec.time_offset->value - paired_at : 0.0;
    for (size_t i = 0; i < stations.size(); ++i) {
      if (fold_of[i] == f) AppendErrors(fit.chain, stations[i], noise, &e, i, shift);
    }
  }
  return e;
}

std::string FormatSeconds(double seconds) {
  std::ostringstream s;
  s << std::fixed << std::setprecision(1) << seconds;
  return s.str();
}

// Where a fit's time went, for the progress messages (docs/diagnose.md, Speed).
std::string FitTimeNote(const FitResult& fit) {
  std::ostringstream s;
  s << std::fixed << std::setprecision(1) << "fitted in " << fit.seconds << " s (start "
    << fit.seconds_initialize << " s, solve " << fit.seconds_solve - fit.seconds_initialize
    << " s in " << fit.iterations << " iterations, " << fit.whitening_passes
    << " whitening passes; covariance " << fit.seconds_covariance << " s)";
  return s.str();
}

// The same, from the fit on all stations (`fitted`: the spec FitModel left): each fold re-estimated
// by Levenberg-Marquardt steps from the full fit (RefitFoldsFromFull; CandidateOptions::exact_cv
// false). `left_out`: the stations the full fit left out (FitResult::left_out), in no fold's
// training; `report_form`: its residual forms (FitResult::report_form), which the folds keep.
// `report` gets the steps each fold took. Returns nothing when a fold's refit stayed exactly at
// the full fit's values (FoldRefit::stayed_at_full_fit): its held-out errors would be in-sample,
// and the caller cross-validates from scratch instead. Measured (a degree-4 polynomial base, a
// strong object 0.075 m from the grid, docs/diagnose.md "Speed"): near_field with its octupole at
// 0, no fold moved (the fit's cost was dominated by one station and every step failed), "held-out"
// drop 17.5 % at p = 5e-18; from scratch, -114 %.
std::optional<StationErrors> FastCrossValidateStations(
    const std::vector<FitStation>& stations, const std::vector<int>& fold_of, ModelSpec* fitted,
    const std::vector<int>& left_out, const std::vector<bool>& report_form, int folds,
    const ModelSpec& noise, const std::function<void(const std::string&)>& report) {
  StationErrors e = MakeErrors(stations.size());
  FoldRefitOptions refit_options;
  refit_options.left_out = left_out;
  refit_options.report_form = report_form;
  const std::vector<FoldRefit> refits =
      RefitFoldsFromFull(stations, fitted, fold_of, folds, refit_options);
  std::string steps;
  int solver = 0, unconverged = 0, jacobians = 0, bound_folds = 0, stayed = 0;
  double seconds = 0.0;
  for (const auto& r : refits) {
    if (!steps.empty()) steps += ',';
    steps += std::to_string(r.steps);
    jacobians += r.jacobian_evaluations;
    bound_folds += r.bound_steps > 0 ? 1 : 0;
    seconds += r.seconds;
    solver += r.solver_refit ? 1 : 0;
    unconverged += !r.solver_refit && !r.converged ? 1 : 0;
    stayed += r.stayed_at_full_fit ? 1 : 0;
  }
  report("fold refits took " + steps + " steps (" + std::to_string(jacobians) + " Jacobians, " +
         FormatSeconds(seconds) + " s)" +
         (unconverged ? "; " + std::to_string(unconverged) + " stopped at the step limit" : "") +
         (solver ? "; " + std::to_string(solver) + " refitted by the solver" : "") +
         (bound_folds ? "; " + std::to_string(bound_folds) + " held coordinates on a bound" : "") +
         (stayed ? "; " + std::to_string(stayed) +
                       " stayed at the full fit's values (in-sample): every fold fitted afresh"
                 : ""));
  if (stayed > 0) return std::nullopt;
  for (size_t i = 0; i < stations.size(); ++i) {
    AppendErrors(refits[static_cast<size_t>(fold_of[i])].chain, stations[i], noise, &e, i);
  }
  return e;
}

// Whether the fast cross-validation applies: not to a clock offset fitted from streams (its fit
// shifts the reference relative to the pairing's offset, which the fitted spec no longer holds).
bool FastCrossValidationApplies(const std::vector<FitStation>& stations, const ModelSpec& spec) {
  if (!spec.time_offset || spec.time_offset->fixed) return true;
  for (const auto& s : stations) {
    if (!s.reference_velocity.isZero() || !s.reference_angular_velocity.isZero()) return false;
  }
  return true;
}

// Runs task(0) ... task(n - 1) on up to `threads` threads (each task writes only its own results,
// so the outcome does not depend on the schedule). The first exception is rethrown after all end.
void ParallelFor(size_t n, int threads, const std::function<void(size_t)>& task) {
  const size_t workers = std::min(n, static_cast<size_t>(std::max(1, threads)));
  if (workers <= 1) {
    for (size_t i = 0; i < n; ++i) task(i);
    return;
  }
  std::atomic<size_t> next{0};
  std::mutex mutex;
  std::exception_ptr error;
  std::vector<std::thread> pool;
  for (size_t w = 0; w < workers; ++w) {
    pool.emplace_back([&] {
      for (size_t i = next++; i < n; i = next++) {
        try {
          task(i);
        } catch (...) {
          std::lock_guard<std::mutex> lock(mutex);
          if (!error) error = std::current_exception();
        }
      }
    });
  }
  for (auto& t : pool) t.join();
  if (error) std::rethrow_exception(error);
}

// chi2 and the number of stations beyond the loss scale (0 without a loss): a robust loss is scored
// as the mean-shift outlier model, in which every rejected station has its own 6 free parameters
// and contributes nothing to chi2.
struct Chi2 {
  double chi2 = 0.0;
  std::vector<int> outliers;  // station ids
};

Chi2 ComputeChi2(const std::vector<FitStation>& stations, const StationErrors& full,
                 const LossOptions& loss, const std::vector<bool>& use = {}) {
  Chi2 c;
  for (size_t i = 0; i < stations.size(); ++i) {
    if (!use.empty() && !use[i]) continue;
    const double e = full.whitened_sq[i];
    if (loss.type != LossType::kNone && std::sqrt(e / 6.0) > loss.scale) {
      c.outliers.push_back(stations[i].station);
      continue;
    }
    c.chi2 += e;
  }
  return c;
}

// BIC with the noise scale profiled out: the whitening sigmas of a model file are guesses, and a
// common factor on them must not decide whether an effect is claimed. n ln(chi2 / n) + k ln(n).
double Bic(double chi2, int n, int k) {
  if (k >= n) return std::numeric_limits<double>::infinity();  // saturated: no evidence either way
  const double floor = 1e-300;  // a perfect fit (noise-free tests) must not give -inf
  return n * std::log(std::max(chi2, floor) / n) + k * std::log(static_cast<double>(n));
}

// Gross outliers (hemisphere flips, bad reference poses) are the stations a robust fit rejects. A
// least-squares fit cannot show them: a flexible model bends to an isolated station (a flip reports
// -p, far from every other station, where a degree-4 polynomial is free), so the flip fits to
// within a few sigma, and the mean-shift model on the stations beyond the loss scale then finds
// only the tail of a missing effect's structure (measured, workflow capture, seed 1: the 10
// stations beyond 3 sigma were all near the workbench frame; the 2 flips, 1.1 and 1.7 m off when
// held out, were not among them). A robust fit that starts away from them (fit/fit_engine.cc: a
// linear term starts at zero under a loss, which rejects stations beyond 30 scales) leaves them at
// their full 2 |p|.
struct GrossOutliers {
  std::vector<size_t> index;  // into the stations, most extreme first
  double p_value = 1.0;       // Bonferroni over the stations (see FindGrossOutliers)
  // Stations as far beyond the capture's errors but not beyond their neighbours': a local effect
  // the model lacks, not outliers (most extreme first).
  std::vector<size_t> local_structure;
};

// The robust outlier test on the log of each station's whitened squared error e (of a robust fit).
// The log, because e spans orders of magnitude over a tracking volume even when nothing is wrong
// (distortion and noise grow steeply with distance; a missing effect's structure has a long,
// continuous tail), while a gross outlier is off by orders of magnitude more: measured on the
// workflow capture (seed 1, degree-4 polynomial, held out): the two flips at e = 3.3e6 and 1.8e6,
// then a continuous tail 146, 97, 66, 65, ... down to the median 1.7. A test on e itself (or the
// mean-shift BIC choosing how many to drop) eats into that tail: it took 26 stations there. Centre
// and scale of ln e are the median and 1.4826 MAD of all stations (robust to the outliers
// themselves); a station is an outlier when its robust z exceeds the one-sided normal deviate of
// alpha / N (Bonferroni over the N stations). For Gaussian residuals of a right model (ln chi2_6:
// MAD ~0.4) that is e > ~13 times the median, a chi2_6 tail of 1e-12. p is the test's Bonferroni p
// of the least extreme outlier.
//
// A gross outlier is also isolated: a flip or a bad reference pose has nothing to do with the
// stations around it, while a source the model lacks raises the errors of a whole neighbourhood.
// So a station must also pass the same test against its `neighbours` nearest stations (by
// `positions`, the reference's): the centre is their second largest ln e, the scale the capture's.
// Measured on the paper capture with the toolbox 0.27 m from the volume (seed 3, a
// degree-4 polynomial under the robust loss): the 3 stations nearest it were 4.4-4.9 scales
// beyond the capture's median (the threshold 4.5 at 480 stations) and 1.4-2.5 beyond their
// neighbours' (2-64 mm errors around 50-95 mm), and a robust loss claimed them as "hemisphere
// flips"; a flip is 1-2 m off among mm errors, as far beyond its neighbours as beyond the
// capture. Empty positions: the global test only.
//
// Stations marked `untested` (empty: none) are neither tested nor in the centre and scale, but
// remain neighbours: a station next to several the runtime inverse does not resolve keeps them in
// its neighbourhood's level (see gross_outliers in DiagnoseCandidates).
GrossOutliers FindGrossOutliers(const std::vector<double>& whitened_sq,
                                const std::vector<Eigen::Vector3d>& positions, int neighbours,
                                double alpha, const std::vector<bool>& untested = {}) {
  GrossOutliers out;
  std::vector<size_t> order;      // tested stations
  std::vector<size_t> neighbour;  // every station with a finite error
  for (size_t i = 0; i < whitened_sq.size(); ++i) {
    if (!(std::isfinite(whitened_sq[i]) && whitened_sq[i] > 0)) continue;
    neighbour.push_back(i);
    if (i >= untested.size() || !untested[i]) order.push_back(i);
  }
  const size_t count = order.size();
  if (count < 12) return out;  // too few stations for a robust scale
  std::stable_sort(order.begin(), order.end(),
                   [&](size_t a, size_t b) { return whitened_sq[a] > whitened_sq[b]; });
  auto median = [](std::vector<double> v) {
    const auto mid = v.begin() + static_cast<std::ptrdiff_t>(v.size() / 2);
    std::nth_element(v.begin(), mid, v.end());
    return *mid;
  };
  std::vector<double> logs;
  for (size_t i : order) logs.push_back(std::log(whitened_sq[i]));
  const double centre = median(logs);
  std::vector<double> dev;
  for (double l : logs) dev.push_back(std::abs(l - centre));
  const double scale = 1.4826 * median(dev);
  if (!(scale > 0)) return out;
  const double n_stations = static_cast<double>(count);
  const double z_min = TwoSidedNormalDeviate(std::min(1.0, 2.0 * alpha / n_stations));
  if (!positions.empty() && positions.size() != whitened_sq.size()) {
    throw std::logic_error("FindGrossOutliers: one position per station");
  }
  // The level of the `neighbours` stations nearest station i (finite errors only): the second
  // largest ln e among them, so one other outlier nearby does not hide a flip, while at the edge
  // of a missing source's field (where half the neighbours are outside it) the ones towards the
  // source still count.
  auto local_centre = [&](size_t i) {
    std::vector<std::pair<double, size_t>> by_distance;
    for (size_t k : neighbour) {
      if (k != i) by_distance.emplace_back((positions[k] - positions[i]).squaredNorm(), k);
    }
    const size_t m = std::min(by_distance.size(), static_cast<size_t>(neighbours));
    std::partial_sort(by_distance.begin(), by_distance.begin() + static_cast<std::ptrdiff_t>(m),
                      by_distance.end());
    std::vector<double> near;
    for (size_t k = 0; k < m; ++k) near.push_back(std::log(whitened_sq[by_distance[k].second]));
    std::sort(near.rbegin(), near.rend());
    return near.size() >= 2 ? near[1] : near.empty() ? -std::numeric_limits<double>::infinity()
                                                      : near[0];
  };
  for (size_t j = 0; 2 * (j + 1) <= count; ++j) {  // outliers are a minority
    double z = (logs[j] - centre) / scale;
    if (!(z > z_min)) break;
    if (!positions.empty() && neighbours > 0) {
      const double z_local = (logs[j] - local_centre(order[j])) / scale;
      if (!(z_local > z_min)) {
        out.local_structure.push_back(order[j]);
        continue;
      }
      z = std::min(z, z_local);
    }
    out.index.push_back(order[j]);
    // One-sided normal tail of z, Bonferroni over the stations: the least extreme outlier's.
    out.p_value = std::max(out.index.size() == 1 ? 0.0 : out.p_value,
                           std::min(1.0, n_stations * 0.5 * std::erfc(z / std::sqrt(2.0))));
  }
  return out;
}

const std::set<std::string>& ExplicitTermTypes() {
  static const std::set<std::string> types = {"polynomial", "lut"};
  return types;
}

// The name the model file gives an unnamed term of `type` (fit/model_file.cc): the type, or
// type_2, type_3, ... when `taken` has it.
std::string NumberedName(const std::string& type, const std::set<std::string>& taken) {
  if (!taken.count(type)) return type;
  int k = 2;
  while (taken.count(type + "_" + std::to_string(k))) ++k;
  return type + "_" + std::to_string(k);
}

// A `terms:` item of a model file: its name as ParseModelYaml gives it (fit/model_file.cc: repeated
// types are numbered unless named), its type, and whether the file holds one of its blocks fixed
// (a room's known plane).
struct ModelTermName {
  std::string name;
  std::string type;
  bool held_fixed = false;
};

std::vector<ModelTermName> ModelTermNames(const std::string& model_text) {
  std::vector<ModelTermName> out;
  std::set<std::string> taken;
  for (const auto& t : YAML::Load(model_text)["terms"]) {
    ModelTermName item;
    item.type = t.IsMap() && t["type"] ? t["type"].as<std::string>() : "";
    item.name = t.IsMap() && t["name"] ? t["name"].as<std::string>() : NumberedName(item.type, taken);
    taken.insert(item.name);
    const YAML::Node settings = t.IsMap() ? t["parameters"] : YAML::Node();
    if (settings && settings.IsMap()) {
      for (const auto& kv : settings) {
        const YAML::Node fixed = kv.second.IsMap() ? kv.second["fixed"] : YAML::Node();
        bool held = false;  // as the model file reads it (true, True, yes, on, ...)
        if (fixed && fixed.IsScalar() && YAML::convert<bool>::decode(fixed, held) && held) {
          item.held_fixed = true;
        }
      }
    }
    out.push_back(std::move(item));
  }
  return out;
}

// Where a physical term goes: after the leading physical terms, before the first explicit one.
int PhysicalInsertIndex(const YAML::Node& terms) {
  int index = 0;
  for (const auto& t : terms) {
    if (t.IsMap() && t["type"] && ExplicitTermTypes().count(t["type"].as<std::string>())) break;
    ++index;
  }
  return index;
}

std::string Emit(const YAML::Node& node) {
  YAML::Emitter out;
  out << node;
  return std::string(out.c_str()) + "\n";
}

// The list items "- type: ...\n  key: ...\n" for term mappings (one per term, in order).
std::string TermListItems(const std::vector<YAML::Node>& terms) {
  YAML::Node seq(YAML::NodeType::Sequence);
  for (const auto& t : terms) seq.push_back(t);
  return Emit(seq);
}

std::string FormatNumber(double v, int precision) {
  std::ostringstream s;
  s << std::fixed << std::setprecision(precision) << v;
  std::string out = s.str();
  if (out == "-0" || out.rfind("-0.", 0) == 0) {
    // "-0.00" reads as a sign that is not there.
    bool all_zero = true;
    for (char ch : out) all_zero = all_zero && (ch == '-' || ch == '0' || ch == '.');
    if (all_zero) out = out.substr(1);
  }
  return out;
}

std::string FormatSignificant(double v, int digits) {
  std::ostringstream s;
  s << std::setprecision(digits) << v;
  return s.str();
}

std::string FormatVector(const std::vector<double>& v, double scale, int precision) {
  std::string out = "(";
  for (size_t i = 0; i < v.size(); ++i)
    out += (i ? ", " : "") + FormatNumber(v[i] * scale, precision);
  return out + ")";
}

const ParameterReport* FindBlock(const std::vector<ParameterReport>& blocks,
                                 const std::string& name) {
  for (const auto& b : blocks) {
    if (b.block == name) return &b;
  }
  return nullptr;
}

// Precision for values whose sigma is s (two significant digits of sigma).
int PrecisionFor(const std::vector<double>& stddev, double scale) {
  double smallest = std::numeric_limits<double>::infinity();
  for (double s : stddev) {
    if (std::isfinite(s) && s > 0) smallest = std::min(smallest, s * scale);
  }
  if (!std::isfinite(smallest)) return 3;
  return std::clamp(static_cast<int>(std::ceil(-std::log10(smallest))) + 1, 0, 8);
}

// "(12.1, -7.0, 20.3) mm +- (0.3, 0.3, 0.4)" for one block, scaled to the display unit.
std::string BlockStatement(const ParameterReport& b, double scale, const std::string& unit) {
  const int precision = PrecisionFor(b.stddev, scale);
  std::string out = (b.values.size() == 1 ? FormatNumber(b.values[0] * scale, precision)
                                          : FormatVector(b.values, scale, precision)) +
                    (unit.empty() ? "" : " " + unit);
  bool any = false;
  for (double s : b.stddev) any = any || std::isfinite(s);
  if (any) {
    std::vector<double> s = b.stddev;
    out += " +- " + (s.size() == 1 ? FormatNumber(s[0] * scale, precision)
                                   : FormatVector(s, scale, precision));
  }
  return out;
}

// Display unit of a stored unit: lengths in mm unless they are locations (m), angles in deg.
std::pair<double, std::string> DisplayUnit(const ParameterReport& b) {
  if (b.unit == "rad") return {kDegPerRad, "deg"};
  if (b.unit == "m" && b.block.find("location") == std::string::npos &&
      b.block.find("point") == std::string::npos) {
    return {1e3, "mm"};
  }
  return {1.0, b.unit == "1" ? "" : b.unit};
}

// Generic statement: every free block of the added term.
std::string GenericStatement(const std::vector<ParameterReport>& blocks) {
  std::string out;
  for (const auto& b : blocks) {
    if (b.fixed) continue;
    const auto [scale, unit] = DisplayUnit(b);
    if (!out.empty()) out += "; ";
    out += b.block + " " + BlockStatement(b, scale, unit);
  }
  return out;
}

double At(const std::vector<double>& v, size_t i) { return i < v.size() ? v[i] : NAN; }

// A report derived from another block (display values computed from it).
ParameterReport Derived(const ParameterReport& from, const std::string& block,
                        const std::string& unit, std::vector<double> values,
                        std::vector<double> stddev) {
  ParameterReport r;
  r.term = from.term;
  r.block = block;
  r.unit = unit;
  r.fixed = from.fixed;
  r.values = std::move(values);
  r.stddev = std::move(stddev);
  return r;
}

// The receiver gain matrix G (rows: the coils' sensitivity axes) split into what is a gain effect
// and what is not. Near the identity G = (I + K)(I + S) with K antisymmetric and S symmetric: S's
// diagonal holds the coil gains, its off-diagonal sums g_ij + g_ji the coils' non-orthogonality
// (small angles); K, the antisymmetric part (g_ij - g_ji) / 2, turns the whole coil triad, which is
// a rotation of the sensor (what sensor_offset's rotation models; docs/physical-model.md: with a
// free sensor_offset G is held symmetric for that reason). Uncertainties come from the block's
// covariance mapped linearly (its standard deviations alone when it has none).
struct GainMatrixParts {
  // g00 - 1, g11 - 1, g22 - 1, g01 + g10, g02 + g20, g12 + g21.
  Eigen::Matrix<double, 6, 1> gain;
  Eigen::Matrix<double, 6, 6> gain_covariance;
  Eigen::Matrix<double, 6, 1> gain_stddev;
  // The triad's rotation vector from K (w_x = (g21 - g12) / 2, ...), its angle and the angle's
  // standard deviation (first order in the covariance).
  Eigen::Vector3d rotation = Eigen::Vector3d::Zero();
  double rotation_angle_rad = 0.0;
  double rotation_angle_stddev_rad = NAN;
};

// g.values has the 9 entries of G (the callers check).
GainMatrixParts SplitGainMatrix(const ParameterReport& g) {
  Eigen::Matrix<double, 9, 9> c = Eigen::Matrix<double, 9, 9>::Zero();
  if (g.covariance.size() == 81) {
    for (int i = 0; i < 81; ++i) c(i / 9, i % 9) = g.covariance[static_cast<size_t>(i)];
  } else {
    for (int i = 0; i < 9; ++i) c(i, i) = std::pow(At(g.stddev, static_cast<size_t>(i)), 2);
  }
  Eigen::Matrix<double, 9, 1> v;
  for (int i = 0; i < 9; ++i) v(i) = g.values[static_cast<size_t>(i)] - (i % 4 == 0 ? 1.0 : 0.0);
  Eigen::Matrix<double, 6, 9> a = Eigen::Matrix<double, 6, 9>::Zero();
  a(0, 0) = a(1, 4) = a(2, 8) = 1.0;
  a(3, 1) = a(3, 3) = 1.0;  // xy
  a(4, 2) = a(4, 6) = 1.0;  // xz
  a(5, 5) = a(5, 7) = 1.0;  // yz
  Eigen::Matrix<double, 3, 9> b = Eigen::Matrix<double, 3, 9>::Zero();
  b(0, 7) = 0.5, b(0, 5) = -0.5;  // (g21 - g12) / 2
  b(1, 2) = 0.5, b(1, 6) = -0.5;  // (g02 - g20) / 2
  b(2, 3) = 0.5, b(2, 1) = -0.5;  // (g10 - g01) / 2
  GainMatrixParts parts;
  parts.gain = a * v;
  parts.gain_covariance = a * c * a.transpose();
  parts.gain_stddev = parts.gain_covariance.diagonal().cwiseMax(0.0).cwiseSqrt();
  parts.rotation = b * v;
  parts.rotation_angle_rad = parts.rotation.norm();
  if (parts.rotation_angle_rad > 0) {
    const Eigen::Vector3d u = parts.rotation / parts.rotation_angle_rad;
    parts.rotation_angle_stddev_rad = std::sqrt(std::max(0.0, u.dot(b * c * b.transpose() * u)));
  }
  return parts;
}

}  // namespace

// Statements of the physical term types (block names of fit/terms_physical.h); empty if a block is
// missing (then the generic statement is used).
std::string PhysicalStatement(const std::string& type, const std::vector<ParameterReport>& p) {
  if (type == "sensor_offset") {
    const ParameterReport* t = FindBlock(p, "translation");
    const ParameterReport* r = FindBlock(p, "rotation");
    if (!t || !r || r->values.size() != 4) return "";
    // Rotation: the quaternion's rotation vector [deg]; its stddev is in the tangent space (rad).
    const Eigen::Quaterniond q = QuaternionFromXyzwArray(r->values.data());
    const Eigen::AngleAxisd aa(q.w() < 0 ? Eigen::Quaterniond(-q.coeffs()) : q);
    const Eigen::Vector3d rv = aa.angle() * aa.axis();
    const ParameterReport rotation =
        Derived(*r, r->block, "rad", {rv.x(), rv.y(), rv.z()}, r->stddev);
    return "a sensor offset of " + BlockStatement(*t, 1e3, "mm") + ", rotated by " +
           BlockStatement(rotation, kDegPerRad, "deg") + " (rotation vector)";
  }
  if (type == "receiver_gain") {
    const ParameterReport* g = FindBlock(p, "gain_matrix");
    if (!g || g->values.size() != 9) return "";
    const GainMatrixParts parts = SplitGainMatrix(*g);
    ParameterReport gains = Derived(*g, "gains", "%", {}, {});
    ParameterReport skew = Derived(*g, "non_orthogonality", "deg", {}, {});
    for (int i = 0; i < 6; ++i) {
      ParameterReport& to = i < 3 ? gains : skew;
      to.values.push_back(parts.gain(i));
      to.stddev.push_back(parts.gain_stddev(i));
    }
    std::string out = "receiver coil gains " + BlockStatement(gains, 100.0, "%") +
                      " (x, y, z coils), non-orthogonality " +
                      BlockStatement(skew, kDegPerRad, "deg") + " (xy, xz, yz)";
    // The rotation part is stated so the numbers account for all of G, but it is not a gain.
    const ParameterReport turn = Derived(*g, "turn", "rad", {parts.rotation_angle_rad},
                                         {parts.rotation_angle_stddev_rad});
    if (parts.rotation_angle_rad > 0) {
      out += "; the coil triad turned as a whole by " + BlockStatement(turn, kDegPerRad, "deg") +
             " (a rotation of the sensor, which sensor_offset models, not a gain)";
    }
    return out;
  }
  if (type == "dipole") {
    const ParameterReport* l = FindBlock(p, "location_in_transmitter");
    const ParameterReport* a = FindBlock(p, "polarisability_m3");
    if (!l || !a || a->values.empty()) return "";
    return std::string(a->values[0] >= 0 ? "a ferromagnetic" : "a conducting") + " object near " +
           BlockStatement(*l, 1.0, "m") + " (transmitter frame), polarisability " +
           BlockStatement(*a, 1.0, "m^3");
  }
  if (type == "plane") {
    const ParameterReport* d = FindBlock(p, "distance_m");
    const ParameterReport* n = FindBlock(p, "normal_in_transmitter");
    const ParameterReport* a = FindBlock(p, "attenuation");
    if (!d || !n || !a || n->values.size() != 3 || a->values.empty()) return "";
    double sigma_deg = NAN;  // the normal's tangent-space stddev: two angles [rad]
    if (n->stddev.size() >= 2) sigma_deg = std::hypot(n->stddev[0], n->stddev[1]) * kDegPerRad;
    // (d, n) and (-d, -n) are the same plane: state the distance from the transmitter as positive.
    const double sign = d->values.empty() || d->values[0] >= 0 ? 1.0 : -1.0;
    ParameterReport distance = *d;
    for (double& v : distance.values) v *= sign;
    std::vector<double> normal_values = n->values;
    for (double& v : normal_values) v *= sign;
    const ParameterReport normal = Derived(*n, n->block, "", normal_values, {});
    std::string out = std::string(a->values[0] >= 0 ? "a conducting" : "a permeable") + " plane " +
                      BlockStatement(distance, 1.0, "m") +
                      " from the transmitter along the normal " + BlockStatement(normal, 1.0, "");
    if (std::isfinite(sigma_deg)) out += " +- " + FormatNumber(sigma_deg, 2) + " deg";
    return out + ", attenuation " + BlockStatement(*a, 1.0, "");
  }
  if (type == "background_field") {
    const ParameterReport* c = FindBlock(p, "coefficients");
    if (!c || c->values.size() % 3 != 0 || c->values.empty()) return "";
    // The uniform part (core/field.h BackgroundBasis: the first 3 coefficients of each coil) as
    // a fraction of the transmitter's field at 1 m on a coil's equator (k = 1 in these units).
    const size_t n = c->values.size() / 3;
    // Its stddev to first order from the coefficients' own (their correlations are not in the
    // report, so it is left out when one is missing).
    const bool has_stddev = c->stddev.size() == c->values.size();
    std::vector<double> uniform, uniform_stddev;
    for (size_t j = 0; j < 3; ++j) {
      double sq = 0, var = 0;
      for (size_t k = 0; k < 3 && k < n; ++k) {
        const double v = c->values[j * n + k];
        sq += v * v;
        if (has_stddev) var += v * v * c->stddev[j * n + k] * c->stddev[j * n + k];
      }
      uniform.push_back(std::sqrt(sq));
      if (has_stddev) uniform_stddev.push_back(sq > 0 ? std::sqrt(var / sq) : NAN);
    }
    const ParameterReport u = Derived(*c, "uniform_part", "", uniform, uniform_stddev);
    return "distant sources: a smooth background field (" + std::to_string(c->values.size()) +
           " harmonic coefficients), uniform part " + BlockStatement(u, 1e3, "") +
           " x 1e-3 of the transmitter's field at 1 m (x, y, z coils)";
  }
  if (type == "near_field") {
    const ParameterReport* o = FindBlock(p, "octupole_m2");
    if (!o) return "";
    // A loop of radius a has c = -3/4 a^2 (docs/scene.md): the equivalent coil radius.
    double c = 0;
    for (double v : o->values) c += std::abs(v) / static_cast<double>(o->values.size());
    return "finite transmitter coils: octupole " + BlockStatement(*o, 1.0, "m^2") +
           " per coil (x, y, z), like loops of radius ~" +
           FormatNumber(std::sqrt(c / 0.75) * 1e2, 1) + " cm";
  }
  return "";
}

namespace {

YAML::Node FlowList(const std::vector<double>& v, int precision) {
  YAML::Node list(YAML::NodeType::Sequence);
  for (double x : v) list.push_back(FormatNumber(x, precision));
  list.SetStyle(YAML::EmitterStyle::Flow);
  return list;
}

// Writes the fitted values of a searched term (dipole, plane) into its mapping as start values, so
// the model change reproduces this fit without the search. False if the blocks are not there.
bool AddFittedStart(const std::string& type, const std::vector<ParameterReport>& p,
                    YAML::Node* term) {
  if (type == "dipole") {
    const ParameterReport* l = FindBlock(p, "location_in_transmitter");
    const ParameterReport* a = FindBlock(p, "polarisability_m3");
    if (!l || !a || l->values.size() != 3 || a->values.size() != 1) return false;
    (*term)["location_in_transmitter"] = FlowList(l->values, 4);  // 0.1 mm
    (*term)["polarisability_m3"] = FormatSignificant(a->values[0], 4);
    return true;
  }
  if (type == "plane") {
    const ParameterReport* d = FindBlock(p, "distance_m");
    const ParameterReport* n = FindBlock(p, "normal_in_transmitter");
    const ParameterReport* a = FindBlock(p, "attenuation");
    if (!d || !n || !a || d->values.size() != 1 || n->values.size() != 3 || a->values.size() != 1) {
      return false;
    }
    const Eigen::Vector3d normal =
        Eigen::Vector3d(n->values[0], n->values[1], n->values[2]).normalized();
    const Eigen::Vector3d point = d->values[0] * normal;
    (*term)["point_in_transmitter"] = FlowList({point.x(), point.y(), point.z()}, 4);
    (*term)["normal_in_transmitter"] = FlowList({normal.x(), normal.y(), normal.z()}, 5);
    (*term)["attenuation"] = FormatSignificant(a->values[0], 4);
    return true;
  }
  return false;
}

// " (without 25 stations where ...)": the stations a comparison left out as unresolved.
std::string UnresolvedNote(int n) {
  return " (without " + std::to_string(n) + " station" + (n == 1 ? "" : "s") +
         " where a runtime inverse finds no root or an ambiguous one)";
}

// A source term's start at this fraction of its strength (polarisability, attenuation): near the
// model without it, where it was placed.
constexpr double kGrowFromFraction = 1e-3;
// A candidate that contains the base (the base plus an effect) whose fit ends at more than this
// factor of the base's final cost did not find its optimum (below, where the candidates are
// fitted). Its optimum is at most about the base's cost: 10 leaves room for the ridge weight and
// noise metrics the fit chooses afresh, and is far below the failures it catches (a factor 5e13).
constexpr double kMaxNestedCostRatio = 10.0;
// The stations' chi2 (the BIC's) of such a candidate may end above the base's by at most this
// fraction. Its final cost is no measure of that: the fit minimises its own cost (a physical
// group's pose-form residuals under metrics it chooses at its values, the polynomial's prior), not
// this chi2, and the two disagree. Measured on the guard suites (fit/candidates*_test,
// search_sim_test, best_chain_sim_test): nested candidates ended at final costs up to 1.45 times
// the base's (dipole_pair, paper capture with flips) at a chi2 0.26 times its; of 168 nested
// fits, all ended at most at the base's chi2 (equal: a fit that stayed at the effect's null) but
// two under a loss (the base's chi2 0: all its stations outliers) and two 77000 times above it
// (dipole, dipole_pair: candidates_sim_test AHeldPlaneStays..., costs below the base's). The
// failures it catches end 10 % above (fit/candidates_fast_test.cc NestedFitsAboveTheBaseFailed)
// and, reported on a workflow capture, 5.9 times above (a background field: delta BIC +8478, listed
// as tested with its coefficients 20.2 sigma from their null).
constexpr double kMaxNestedChi2Excess = 0.01;
// ... plus this much per residual of the stations compared: a base that fits them exactly (chi2 0,
// a noiseless capture or as many parameters as residuals) would otherwise fail every candidate
// whose chi2 ends at rounding noise above it (measured: 60 noiseless stations, the degree-3
// fallback at 2.3e-25 against 0; fit/candidates_test.cc ACandidateOfABaseThatFitsExactlyIsScored).
// 1e-6 is a whitened RMS of 1e-3 sigma (0.06 um at a Fastrak's 0.06 mm): above the runtime
// inverse's precision (it stops at an estimated 1e-12 m, tested to 1e-9 m: 2e-5 sigma, 3e-10 per
// residual) and 1e4 times below the smallest failure caught (10 % above a base at chi2 / n = 0.14:
// 0.014 per residual). It decides only below chi2 / n = 1e-4, a noise 100 times overstated; a
// right noise model's chi2 / n is ~1, where the relative rule governs.
constexpr double kMaxNestedChi2ExcessPerResidual = 1e-6;

// Why the added term `name` of the fitted `spec` cannot take its null value, the value at which the
// candidate is the base (empty: it can): a catalog term (CandidateOptions::catalog, a user's) whose
// `parameters:` hold a strength block fixed off its null or bound it away from it does not contain
// the base, so the rules that rest on that (the retry from the base's optimum with the term at
// its null, the nested cost and chi2 rules) do not apply to it: a worse fit is then a result.
// Measured before (fit/candidates_test.cc ACandidateThatExcludesItsNullIsNotNested): an offset
// fixed at 0.2 mm was "fit failed: ... worse than the base it contains", bounded gains "did not
// find the optimum", and a dipole fixed at 1e-3 m^3 was refitted and reported at 1e-6 m^3.
// The null values are the strength blocks' of PhysicalEvidence (sensor_offset: rotation identity
// and translation 0; receiver_gain G = I; dipole, plane, near_field, background_field: strength
// 0; polynomial, lut: every coefficient 0). A term type of no known null with a fixed or bounded
// block is not presumed to contain the base.
std::string NullExcludedWhy(const ModelSpec& spec, const std::string& name) {
  const ModelFileTerm* file = nullptr;
  for (const ModelFileTerm& f : spec.file_terms) {
    if (f.name == name) file = &f;
  }
  if (file == nullptr || file->model_term < 0 ||
      static_cast<size_t>(file->model_term) >= spec.terms.size()) {
    return "";
  }
  const ModelTerm& term = *spec.terms[static_cast<size_t>(file->model_term)];
  const std::string& type = file->type;
  for (const ParameterBlock& b : term.blocks()) {
    if ((b.term.empty() ? term.name() : b.term) != name) continue;
    const std::vector<double> zero(b.values.size(), 0.0);
    std::vector<std::vector<double>> nulls;  // any of them reproduces the base; empty: no strength
    if (type == "sensor_offset") {
      if (b.name == "rotation") nulls = {{0, 0, 0, 1}, {0, 0, 0, -1}};
      if (b.name == "translation") nulls = {zero};
    } else if (type == "receiver_gain") {
      if (b.name == "gain_matrix") nulls = {{1, 0, 0, 0, 1, 0, 0, 0, 1}};
    } else if (type == "dipole" || type == "plane" || type == "near_field" ||
               type == "background_field") {
      if (b.name == "polarisability_m3" || b.name == "attenuation" || b.name == "octupole_m2" ||
          b.name == "coefficients") {
        nulls = {zero};
      }
    } else if (type == "polynomial" || type == "lut") {
      nulls = {zero};
    } else if (b.fixed || !b.lower.empty() || !b.upper.empty()) {
      return "its block " + b.name + " is held fixed or bounded and the null value of a " + type +
             " is not known";
    }
    if (nulls.empty()) continue;
    bool feasible = false;
    for (const auto& null : nulls) {
      bool in = null.size() == b.values.size();
      for (size_t i = 0; in && i < null.size(); ++i) {
        in = b.fixed ? b.values[i] == null[i]
                     : (b.lower.empty() || b.lower[i] <= null[i]) &&
                           (b.upper.empty() || null[i] <= b.upper[i]);
      }
      feasible = feasible || in;
    }
    if (!feasible) {
      return "its block " + b.name + (b.fixed ? " is held fixed off" : " is bounded away from") +
             " its null value";
    }
  }
  return "";
}

// Scales the strength of a dipole's or plane's start (as AddFittedStart wrote it); false for other
// terms or a missing value.
bool ScaleSourceStrength(double factor, YAML::Node* term) {
  for (const char* key : {"polarisability_m3", "attenuation"}) {
    if ((*term)[key]) {
      (*term)[key] = FormatSignificant((*term)[key].as<double>() * factor, 4);
      return true;
    }
  }
  return false;
}

}  // namespace

std::string HoldSourceLocation(const std::string& type, const std::string& term_yaml) {
  std::vector<std::string> held;
  if (type == "dipole") held = {"location_in_transmitter"};
  if (type == "plane") held = {"distance_m", "normal_in_transmitter"};
  if (held.empty()) return term_yaml;
  YAML::Node term = YAML::Load(term_yaml);
  // Merged into the term's own settings, not in place of them: a user's catalog term keeps its
  // fixed blocks, priors and bounds (fit/candidates_test.cc
  // TheRetryHoldsASourceWhereItWasPlacedAndKeepsTheUsersSettings).
  YAML::Node parameters(YAML::NodeType::Map);
  if (term["parameters"] && term["parameters"].IsMap()) parameters = term["parameters"];
  for (const std::string& block : held) {
    YAML::Node settings(YAML::NodeType::Map);
    if (parameters[block] && parameters[block].IsMap()) settings = parameters[block];
    settings["fixed"] = true;
    // A `value:` is a start (docs/model-file.md) and would replace the one written in the
    // mapping: the location is held where the first fit placed it.
    settings.remove("value");
    parameters[block] = settings;
  }
  term["parameters"] = parameters;
  return Emit(term);
}

namespace {

// "+y (0.46, 0.84, 0.28)": a unit vector by its dominant transmitter axis, then its components.
std::string AxisWords(const Eigen::Vector3d& u) {
  Eigen::Index axis = 0;
  u.cwiseAbs().maxCoeff(&axis);
  const char* names[] = {"x", "y", "z"};
  return std::string(u(axis) >= 0 ? "+" : "-") + names[axis] + " " +
         FormatVector({u.x(), u.y(), u.z()}, 1.0, 2);
}

// The blocks of one term (by its name in reports).
std::vector<ParameterReport> BlocksOfTerm(const std::vector<ParameterReport>& blocks,
                                          const std::string& term) {
  std::vector<ParameterReport> out;
  for (const auto& b : blocks) {
    if (b.term == term) out.push_back(b);
  }
  return out;
}

// Whether `a` is weaker evidence than `b`: it fails a physical condition that `b` passes, or both
// pass (or both fail) and its strength is fewer sigmas from its null value.
bool WeakerEvidence(const PhysicalEvidence& a, const PhysicalEvidence& b) {
  if (a.supported() != b.supported()) return !a.supported();
  const double sa = std::isfinite(a.strength_sigma) ? a.strength_sigma : -1.0;
  const double sb = std::isfinite(b.strength_sigma) ? b.strength_sigma : -1.0;
  return sa < sb;
}

std::string Statement(const CatalogEffect& effect, const Candidate& c, double loss_scale) {
  if (effect.kind == CandidateKind::kRobustLoss) {
    std::string ids;
    for (size_t i = 0; i < c.outlier_stations.size() && i < 10; ++i) {
      ids += (i ? ", " : "") + std::to_string(c.outlier_stations[i]);
    }
    if (c.outlier_stations.size() > 10) ids += ", ...";
    if (c.outlier_stations.empty()) return "its fit rejects no station as a gross outlier";
    return std::to_string(c.outlier_stations.size()) + " outlier station" +
           (c.outlier_stations.size() == 1 ? "" : "s") +
           " its fit rejects (error far beyond the others'" + (ids.empty() ? "" : ": " + ids) +
           "): hemisphere flips or bad reference poses; a " + FormatSignificant(loss_scale, 3) +
           " sigma loss keeps them from pulling the fit";
  }
  if (effect.kind == CandidateKind::kTerm) {
    const std::string type = YAML::Load(effect.term_yaml)["type"].as<std::string>();
    const std::string physical = PhysicalStatement(type, c.parameters);
    if (!physical.empty()) return physical;
  }
  return GenericStatement(c.parameters);
}

// The clock-offset candidate: the joint fit's estimate with its standard deviation (the pairing's
// search gave the start), and, when the model's other terms can mimic a time shift along this
// stream's path (FitResult::time_offset_variance_inflation), that the estimate is not reliable.
// Multiplies the blocks' standard deviations by `scale` and their covariances by its square.
void ScaleStddevs(double scale, std::vector<ParameterReport>* blocks) {
  if (scale == 1.0) return;
  for (auto& b : *blocks) {
    for (double& x : b.stddev) x *= scale;
    for (double& x : b.covariance) x *= scale * scale;
  }
}

// `stddev_scale` multiplies the fit's standard deviation (the noise scale of a model covariance).
std::string TimeOffsetStatement(const FitResult& fit, double paired_offset_s, double stddev_scale) {
  const ParameterReport* joint = nullptr;
  for (const auto& r : fit.parameters) {
    if (r.term == "time_offset" && r.values.size() == 1) joint = &r;
  }
  std::string out = "a clock offset of ";
  if (joint && !joint->stddev.empty() && std::isfinite(joint->stddev[0])) {
    out += FormatNumber(joint->values[0] * 1e3, 2) + " +- " +
           FormatNumber(joint->stddev[0] * stddev_scale * 1e3, 2) +
           " ms (reference minus tracker; fitted with the model from the pairing's " +
           FormatNumber(paired_offset_s * 1e3, 2) + " ms)";
  } else {
    out += FormatNumber((joint ? joint->values[0] : paired_offset_s) * 1e3, 2) +
           " ms (reference minus tracker; no standard deviation)";
  }
  const double vif = fit.time_offset_variance_inflation;
  if (std::isfinite(vif) && vif > kMaxTimeOffsetVarianceInflation) {
    out += "; poorly identified: it " + TimeOffsetMimicryNote(vif);
  }
  return out;
}

// Wald statistic of `v` (the block minus its null value) against the block's covariance `cov`
// (row-major k x k; empty: the standard deviations alone, as uncorrelated), with the degrees of
// freedom it has (directions of zero variance carry no information and are dropped). nullopt when
// a standard deviation is missing.
struct Wald {
  double chi2 = 0.0;
  int dof = 0;
};
std::optional<Wald> WaldOfBlock(const Eigen::VectorXd& v, const std::vector<double>& stddev,
                                const std::vector<double>& cov) {
  const Eigen::Index k = v.size();
  if (static_cast<Eigen::Index>(stddev.size()) != k) return std::nullopt;
  for (double s : stddev) {
    if (!std::isfinite(s)) return std::nullopt;
  }
  Eigen::MatrixXd c = Eigen::MatrixXd::Zero(k, k);
  if (static_cast<Eigen::Index>(cov.size()) == k * k) {
    for (Eigen::Index r = 0; r < k; ++r) {
      for (Eigen::Index q = 0; q < k; ++q) c(r, q) = cov[static_cast<size_t>(r * k + q)];
    }
    c = 0.5 * (c + c.transpose());
  } else {
    for (Eigen::Index r = 0; r < k; ++r)
      c(r, r) = stddev[static_cast<size_t>(r)] * stddev[static_cast<size_t>(r)];
  }
  const Eigen::SelfAdjointEigenSolver<Eigen::MatrixXd> eig(c);
  const double largest = eig.eigenvalues().cwiseAbs().maxCoeff();
  Wald w;
  for (Eigen::Index i = 0; i < k; ++i) {
    const double lambda = eig.eigenvalues()(i);
    // Relative cut: the covariance comes from a (pseudo-)inverse in double precision.
    if (!(lambda > 1e-12 * largest)) continue;
    const double u = eig.eigenvectors().col(i).dot(v);
    w.chi2 += u * u / lambda;
    ++w.dof;
  }
  if (w.dof == 0) return std::nullopt;
  return w;
}

// Largest standard deviation of a block (the covariance's largest principal axis when given).
double LargestSigma(const std::vector<double>& stddev, const std::vector<double>& cov) {
  const Eigen::Index k = static_cast<Eigen::Index>(stddev.size());
  double s = 0.0;
  for (double x : stddev)
    s = std::max(s, std::isfinite(x) ? x : std::numeric_limits<double>::infinity());
  if (k > 0 && static_cast<Eigen::Index>(cov.size()) == k * k && std::isfinite(s)) {
    Eigen::MatrixXd c(k, k);
    for (Eigen::Index r = 0; r < k; ++r) {
      for (Eigen::Index q = 0; q < k; ++q) c(r, q) = cov[static_cast<size_t>(r * k + q)];
    }
    const Eigen::SelfAdjointEigenSolver<Eigen::MatrixXd> eig(0.5 * (c + c.transpose()));
    s = std::sqrt(std::max(0.0, eig.eigenvalues().maxCoeff()));
  }
  return s;
}

// Where the receiver was (the reference positions, transmitter frame): the measured volume. Not
// the reported positions: a hemisphere flip reports -p and would stretch the box across the
// transmitter, over the sources on the other side.
std::vector<Eigen::Vector3d> MeasuredPositions(const std::vector<FitStation>& stations) {
  std::vector<Eigen::Vector3d> out;
  out.reserve(stations.size());
  for (const auto& s : stations) out.push_back(s.reference.translation);
  return out;
}

void Progress(const CandidateOptions& options, const std::string& message) {
  static std::mutex mutex;  // the callback is called from worker threads, one call at a time
  if (!options.progress) return;
  std::lock_guard<std::mutex> lock(mutex);
  options.progress(message);
}

struct PreparedCandidate {
  const CatalogEffect* effect = nullptr;
  Candidate candidate;
  std::vector<YAML::Node> terms;     // kTerm: the inserted mappings (for model_change)
  std::vector<FitStation> stations;  // kTimeOffset: the re-paired stations (else empty: the base's)
  std::vector<int> base_index;       // per own station: the base station it is (-1: none)
  double time_offset_s = 0.0;
  bool flexible = false;                    // a flexible fallback, not an effect
  std::vector<double> cv_whitened_by_base;  // held-out whitened error per base station (NaN: none)
  YAML::Node root;                          // the candidate model file
  std::shared_ptr<ModelSpec>
      fitted;  // the fit on all stations (the fast cross-validation starts there)
  std::vector<int> left_out;  // that fit's left-out stations (FitResult::left_out)
  std::vector<bool> report_form;  // and its residual forms (FitResult::report_form)
  // kRobustLoss: its fit's whitened squared error per station and the gross outliers among them,
  // and the stations its or the base's runtime inverse does not resolve.
  std::vector<double> full_whitened_sq;
  std::vector<bool> full_unresolved;
  GrossOutliers gross;
};

// The removals' effect: not in the catalog (nothing is added), but every candidate refers to one.
const CatalogEffect& RemovalEffect() {
  static const CatalogEffect effect{kRemoveEffect, CandidateKind::kRemoval, "", false, false,
                                    "a source term these data no longer identify"};
  return effect;
}

}  // namespace

std::vector<CatalogEffect> DefaultCatalog() {
  return {
      {"sensor_offset", CandidateKind::kTerm, "type: sensor_offset", true, false,
       "a sensor offset (the reference body is not at the receiver coil)"},
      {"receiver_gain", CandidateKind::kTerm, "type: receiver_gain", true, false,
       "receiver coil gains and non-orthogonality"},
      {"dipole", CandidateKind::kTerm, "type: dipole", true, true,
       "a ferromagnetic or conducting object"},
      // Two objects at once: two sources whose fields overlap over the volume (two monitors side by
      // side) can each be too weak or too vague alone for the physical conditions, while a plane
      // stands in for both; searched together, each is placed (fit/search_sim_test).
      {"dipole_pair", CandidateKind::kTerm, "type: dipole", true, true,
       "two ferromagnetic or conducting objects", 2},
      {"plane", CandidateKind::kTerm, "type: plane", true, true,
       "a conducting plane (floor, wall, door)"},
      {"near_field", CandidateKind::kTerm, "type: near_field", true, false,
       "finite transmitter coils (near field)"},
      // Distant sources (monitors across the room, a door): their field over the volume is smooth
      // and mostly a polynomial's, but the receiver gains, a sensor offset and nearby sources
      // interact with it, so leaving it out biases their parameters (docs/diagnose.md).
      // A located source that explains the same structure goes before it (RankFirst).
      {"background_field", CandidateKind::kTerm, "type: background_field", true, false,
       "distant sources (a smooth background field over the volume)", 1,
       /*yields_to_located=*/true},
      {"robust_loss", CandidateKind::kRobustLoss, "", false, false,
       "outlier stations (hemisphere flips or bad reference poses)"},
      {"time_offset", CandidateKind::kTimeOffset, "", false, false,
       "a clock offset between tracker and reference streams"},
  };
}

std::vector<CatalogEffect> DefaultFlexibleFallback() {
  return {{"polynomial_3", CandidateKind::kTerm, "{type: polynomial, degree: 3}", false, true,
           "a smooth field (degree-3 polynomial) beyond the catalog"}};
}

void CandidateOptions::Check() const {
  if (folds < 2) throw std::invalid_argument("CandidateOptions.folds: must be at least 2");
  if (!(family_alpha > 0 && family_alpha < 1)) {
    throw std::invalid_argument("CandidateOptions.family_alpha: must be in (0, 1)");
  }
  if (!(min_drop_percent >= 0 && min_drop_percent < 100)) {
    throw std::invalid_argument("CandidateOptions.min_drop_percent: must be in [0, 100)");
  }
  if (!std::isfinite(max_delta_bic)) {
    throw std::invalid_argument("CandidateOptions.max_delta_bic: must be finite");
  }
  if (!(max_outlier_fraction >= 0 && max_outlier_fraction < 0.5)) {
    throw std::invalid_argument("CandidateOptions.max_outlier_fraction: must be in [0, 0.5)");
  }
  if (!(max_unresolved_fraction >= 0 && max_unresolved_fraction < 0.5)) {
    throw std::invalid_argument("CandidateOptions.max_unresolved_fraction: must be in [0, 0.5)");
  }
  if (outlier_neighbours < 0) {
    throw std::invalid_argument("CandidateOptions.outlier_neighbours: must be >= 0");
  }
  if (serial_blocks < 0) {
    throw std::invalid_argument("CandidateOptions.serial_blocks: must be >= 0");
  }
  if (!(min_strength_sigma >= 0) || !std::isfinite(min_strength_sigma)) {
    throw std::invalid_argument("CandidateOptions.min_strength_sigma: must be finite and >= 0");
  }
  if (!(max_normal_sigma_rad > 0) || !std::isfinite(max_normal_sigma_rad)) {
    throw std::invalid_argument("CandidateOptions.max_normal_sigma_rad: must be finite and > 0");
  }
  if (num_threads < 0) throw std::invalid_argument("CandidateOptions.num_threads: must be >= 0");
  if (cross_validate_top < 0) {
    throw std::invalid_argument("CandidateOptions.cross_validate_top: must be >= 0");
  }
  if (robust_loss.type == LossType::kNone || !(robust_loss.scale > 0)) {
    throw std::invalid_argument("CandidateOptions.robust_loss: needs a loss type and a scale > 0");
  }
  std::set<std::string> names;
  std::vector<CatalogEffect> all = catalog;
  all.insert(all.end(), flexible.begin(), flexible.end());
  for (const auto& e : all) {
    if (e.effect.empty() || !names.insert(e.effect).second) {
      throw std::invalid_argument("CandidateOptions.catalog: empty or repeated effect name '" +
                                  e.effect + "'");
    }
    if (e.kind == CandidateKind::kTerm) {
      YAML::Node node;
      try {
        node = YAML::Load(e.term_yaml);
      } catch (const YAML::Exception& ex) {
        throw std::invalid_argument("CandidateOptions.catalog." + e.effect +
                                    ".term_yaml: " + ex.what());
      }
      if (!node.IsMap() || !node["type"]) {
        throw std::invalid_argument("CandidateOptions.catalog." + e.effect +
                                    ".term_yaml: must be a mapping with a 'type'");
      }
      if (e.count < 1 || (e.count > 1 && (!e.repeatable || node["name"]))) {
        throw std::invalid_argument("CandidateOptions.catalog." + e.effect +
                                    ".count: must be 1, or more for a repeatable term without a "
                                    "name");
      }
    }
  }
  for (const auto& name : effects) {
    if (!names.count(name) && name != kRemoveEffect) {
      std::string known;
      for (const auto& e : catalog) known += (known.empty() ? "" : ", ") + e.effect;
      throw std::invalid_argument("CandidateOptions.effects: unknown effect '" + name +
                                  "' (catalog: " + known + "; and " + kRemoveEffect + ")");
    }
  }
}

double WilcoxonSignedRankGreater(const std::vector<double>& differences) {
  std::vector<double> d;
  for (double v : differences) {
    if (std::isfinite(v) && v != 0.0) d.push_back(v);
  }
  const size_t n = d.size();
  if (n == 0) return 1.0;
  std::vector<size_t> order(n);
  std::iota(order.begin(), order.end(), 0);
  std::sort(order.begin(), order.end(),
            [&](size_t a, size_t b) { return std::abs(d[a]) < std::abs(d[b]); });
  double w_plus = 0.0, tie_term = 0.0;
  for (size_t i = 0; i < n;) {
    size_t j = i;
    while (j + 1 < n && std::abs(d[order[j + 1]]) == std::abs(d[order[i]])) ++j;
    const double rank = 0.5 * static_cast<double>(i + j) + 1.0;  // average rank, 1-based
    const double t = static_cast<double>(j - i + 1);
    tie_term += t * t * t - t;
    for (size_t k = i; k <= j; ++k) {
      if (d[order[k]] > 0) w_plus += rank;
    }
    i = j + 1;
  }
  const double nn = static_cast<double>(n);
  const double mean = nn * (nn + 1) / 4.0;
  const double var = nn * (nn + 1) * (2 * nn + 1) / 24.0 - tie_term / 48.0;
  if (var <= 0) return 1.0;
  const double z = (w_plus - mean - 0.5) / std::sqrt(var);  // continuity correction
  return 0.5 * std::erfc(z / std::sqrt(2.0));
}

// Ranking: significant first, then by held-out error. When the held-out best and another
// significant source term explain the same structure (the other's held-out errors are not
// significantly larger, paired test at family_alpha), the one with the lower BIC on all stations
// goes first: a dipole at a plane's mirror image of the transmitter and the plane fit nearly the
// same field (both 4 parameters, so this is the better likelihood), and where held-out data
// cannot tell them apart the fit on all stations still sees the difference between a plane's
// image moments a (I - 2 n n^T) and an induced dipole's. Measured on the workflow captures (held
// out, p = 0.51-0.94 that either is worse): the floor (hemisphere_flips seed 1, receiver_gains
// seed 1) has delta BIC -1179 / -2050 as a plane against -1150 / -1997 as a dipole at its image;
// the workbench frame (receiver_gains seed 2) -4248 as a dipole against -4185 as a plane at 0.32
// m whose image it is. The rule before (the better-determined strength) picked that plane
// (attenuation 43.7 sigma against the polarisability's 39.3), a spurious term. BIC decides only
// when the difference is decisive (beyond |max_delta_bic|); within it the better-determined
// strength does (sensor_offset seed 3: the floor's image dipole -2362.5 against the plane's
// -2355.7, attenuation 11.4 sigma against 5.3: the plane).
// A catch-all (background_field: 24 coefficients for every source not placed) that is best held
// out by a margin the paired test cannot confirm gives way to a located source: the source has 4
// parameters with a meaning, and the background can still follow it at the next step, while a
// background added first takes a share of the source's field (the workflow's toolbox, 0.58 m
// outside the volume, traded location and strength with the background's gradient).
double PairedDifferencesGreaterP(const std::vector<double>& differences,
                                 const std::vector<int>& block_of) {
  if (block_of.empty()) return WilcoxonSignedRankGreater(differences);
  if (block_of.size() != differences.size()) {
    throw std::invalid_argument("PairedDifferencesGreaterP: one block per difference");
  }
  // Mean difference of each block over its finite differences (a block without any: none).
  std::map<int, std::pair<double, int>> sums;
  for (size_t k = 0; k < differences.size(); ++k) {
    if (block_of[k] < 0 || !std::isfinite(differences[k])) continue;
    auto& [sum, count] = sums[block_of[k]];
    sum += differences[k];
    ++count;
  }
  std::vector<double> means;
  for (const auto& [block, s] : sums) means.push_back(s.first / s.second);
  return WilcoxonSignedRankGreater(means);
}

double PairedGreaterP(const std::vector<double>& a, const std::vector<double>& b,
                      const std::vector<int>& block_of) {
  std::vector<double> d;
  std::vector<int> blocks;
  const size_t n = std::min(a.size(), b.size());
  for (size_t k = 0; k < n; ++k) {
    if (!std::isfinite(a[k]) || !std::isfinite(b[k])) continue;
    d.push_back(a[k] - b[k]);
    if (!block_of.empty()) blocks.push_back(k < block_of.size() ? block_of[k] : -1);
  }
  return PairedDifferencesGreaterP(d, blocks);
}

double WilcoxonSmallestP(int n) {
  if (n <= 0) return 1.0;
  std::vector<double> d(static_cast<size_t>(n));
  std::iota(d.begin(), d.end(), 1.0);
  return WilcoxonSignedRankGreater(d);
}

RankPick RankFirst(const std::vector<RankEntry>& entries, double family_alpha,
                   double max_delta_bic, const std::vector<int>& block_of) {
  RankPick pick;
  if (entries.size() < 2) return pick;
  const RankEntry& front = entries.front();
  if (!std::isfinite(front.strength_sigma)) return pick;
  if (!front.has_location && !front.yields_to_located) return pick;
  // p that entry o's held-out errors are larger than the held-out best's, paired by station.
  auto p_worse = [&](const RankEntry& o) {
    return PairedGreaterP(o.cv_whitened_by_station, front.cv_whitened_by_station, block_of);
  };
  auto bic_note = [](const RankEntry& o, const RankEntry& b) {
    return "delta BIC " + FormatNumber(o.delta_bic, 1) + " against " + FormatNumber(b.delta_bic, 1);
  };
  const double decisive_gap = std::abs(max_delta_bic);
  // A catch-all front: no located source that fits all stations decisively worse than it goes
  // first, also not by the located rule against a source promoted over it.
  const RankEntry* catch_all = front.has_location ? nullptr : &front;
  for (size_t i = 1; i < entries.size(); ++i) {
    const RankEntry& o = entries[i];
    const RankEntry& best = entries[pick.index];
    if (!o.has_location || !std::isfinite(o.strength_sigma)) continue;
    if (catch_all && o.delta_bic - catch_all->delta_bic > decisive_gap) continue;
    const double bic_gap = best.delta_bic - o.delta_bic;  // > 0: o fits all stations better
    const bool decisive = std::abs(bic_gap) > decisive_gap;
    std::string why;
    if (best.has_location) {
      // Which of two located sources: the better likelihood when the fits to all stations differ
      // decisively, else the better-determined strength.
      const bool better = decisive ? bic_gap > 0 : o.strength_sigma > best.strength_sigma;
      if (!better) continue;
      why = decisive ? "it fits all stations better (" + bic_note(o, best) + ")"
                     : "their fits to all stations do not differ decisively (" + bic_note(o, best) +
                           "), and its strength is better determined (" +
                           FormatNumber(o.strength_sigma, 1) + " sigma against " +
                           FormatNumber(best.strength_sigma, 1) + ")";
    } else {
      // The held-out best is a catch-all, and o does not fit all stations decisively worse
      // (checked above): the located source goes first.
      why = "it places a source where " + best.effect + " stands for sources it does not place (" +
            bic_note(o, best) + ")";
    }
    const double p = p_worse(o);
    if (p < family_alpha) continue;
    pick.index = i;
    pick.note = "ranked first over " + front.effect +
                ": their held-out errors do not differ (p = " + FormatSignificant(p, 2) +
                " that it is worse) and " + why;
  }
  return pick;
}

std::optional<StandIn> FindStandIn(const std::vector<double>& claimed,
                                   const std::vector<std::vector<double>>& others,
                                   double family_alpha, const std::vector<int>& block_of) {
  for (size_t o = 0; o < others.size(); ++o) {
    const double p = PairedGreaterP(claimed, others[o], block_of);
    if (p < family_alpha) return StandIn{o, p};
  }
  return std::nullopt;
}

double HotellingUpperTail(double w, int dof, int clusters) {
  if (dof < 1) throw std::invalid_argument("HotellingUpperTail: dof must be >= 1");
  if (clusters <= dof) return 1.0;
  const double g = clusters, k = dof;
  return FDistributionUpperTail(w * (g - k) / ((g - 1.0) * k), k, g - k);
}

double TwoSidedNormalDeviate(double p) {
  if (!(p > 0)) return std::numeric_limits<double>::infinity();
  if (p >= 1) return 0.0;
  // erfc(z / sqrt 2) = p is monotone in z: bisection to double precision.
  double lo = 0.0, hi = 40.0;
  for (int i = 0; i < 200 && hi - lo > 1e-12; ++i) {
    const double mid = 0.5 * (lo + hi);
    (std::erfc(mid / std::sqrt(2.0)) > p ? lo : hi) = mid;
  }
  return 0.5 * (lo + hi);
}

namespace {
PhysicalEvidence AssessScaled(const std::string& term_type,
                              const std::vector<ParameterReport>& blocks,
                              const std::vector<Eigen::Vector3d>& volume_points,
                              double min_strength_sigma, double max_normal_sigma_rad,
                              PhysicalEvidence e);
}  // namespace

PhysicalEvidence AssessPhysicalEvidence(const std::string& term_type,
                                        const std::vector<ParameterReport>& blocks,
                                        const std::vector<Eigen::Vector3d>& volume_points,
                                        double min_strength_sigma, double noise_scale,
                                        double max_normal_sigma_rad, int num_clusters) {
  PhysicalEvidence e;
  e.noise_scale = noise_scale;
  e.strength_clusters = std::max(0, num_clusters);
  // The fit's standard deviations and covariances, scaled.
  std::vector<ParameterReport> scaled = blocks;
  for (auto& b : scaled) {
    for (double& x : b.stddev) x *= noise_scale;
    for (double& x : b.covariance) x *= noise_scale * noise_scale;
  }
  return AssessScaled(term_type, scaled, volume_points, min_strength_sigma, max_normal_sigma_rad,
                      std::move(e));
}

namespace {
PhysicalEvidence AssessScaled(const std::string& term_type,
                              const std::vector<ParameterReport>& blocks,
                              const std::vector<Eigen::Vector3d>& volume_points,
                              double min_strength_sigma, double max_normal_sigma_rad,
                              PhysicalEvidence e) {
  // Strength blocks and their null values: (block, what, v = value - null in the stddev's
  // coordinates).
  struct Strength {
    const ParameterReport* block;
    std::string what;
    Eigen::VectorXd v;
    // The stddev and covariance of v: the block's own unless v is derived from it.
    std::vector<double> stddev;
    std::vector<double> covariance;
  };
  std::vector<Strength> strengths;
  auto euclidean = [&](const std::string& name, const std::string& what,
                       const std::vector<double>& null) {
    const ParameterReport* b = FindBlock(blocks, name);
    if (!b || b->fixed || b->values.size() != null.size()) return;
    Eigen::VectorXd v(static_cast<Eigen::Index>(null.size()));
    for (size_t i = 0; i < null.size(); ++i)
      v(static_cast<Eigen::Index>(i)) = b->values[i] - null[i];
    strengths.push_back({b, what, v, b->stddev, b->covariance});
  };
  if (term_type == "dipole") {
    euclidean("polarisability_m3", "polarisability_m3", {0.0});
  } else if (term_type == "plane") {
    euclidean("attenuation", "attenuation", {0.0});
  } else if (term_type == "near_field") {
    euclidean("octupole_m2", "octupole_m2", {0.0, 0.0, 0.0});
  } else if (term_type == "background_field") {
    const ParameterReport* b = FindBlock(blocks, "coefficients");
    if (b) euclidean("coefficients", "background field coefficients",
                     std::vector<double>(b->values.size(), 0.0));
  } else if (term_type == "receiver_gain") {
    // Only the symmetric part of G - I is a gain effect (SplitGainMatrix): a whole-triad rotation
    // found by a model without sensor_offset is the sensor's rotation, which would otherwise make
    // the gains "significant" while every gain is within its sigma of zero.
    const ParameterReport* b = FindBlock(blocks, "gain_matrix");
    if (b && !b->fixed && b->values.size() == 9) {
      const GainMatrixParts parts = SplitGainMatrix(*b);
      std::vector<double> stddev(parts.gain_stddev.data(), parts.gain_stddev.data() + 6);
      std::vector<double> covariance;
      if (b->covariance.size() == 81) {
        for (int r = 0; r < 6; ++r) {
          for (int q = 0; q < 6; ++q) covariance.push_back(parts.gain_covariance(r, q));
        }
      }
      if (std::none_of(b->stddev.begin(), b->stddev.end(),
                       [](double x) { return std::isfinite(x); })) {
        stddev.assign(6, NAN);
      }
      strengths.push_back({b, "coil gains and non-orthogonality", parts.gain, stddev, covariance});
    }
  } else if (term_type == "sensor_offset") {
    euclidean("translation", "translation", {0.0, 0.0, 0.0});
    const ParameterReport* r = FindBlock(blocks, "rotation");
    if (r && !r->fixed && r->values.size() == 4) {
      // The tangent coordinates are rotation vectors [rad]; the null is the identity, reached from
      // the estimate by minus its rotation vector (the sign does not matter to the quadratic form).
      const Eigen::Quaterniond q = QuaternionFromXyzwArray(r->values.data());
      const Eigen::AngleAxisd aa(q.w() < 0 ? Eigen::Quaterniond(-q.coeffs()) : q);
      strengths.push_back({r, "rotation", aa.angle() * aa.axis(), r->stddev, r->covariance});
    }
  } else {
    return e;  // no physical strength to test
  }
  e.assessed = true;
  if (strengths.empty()) {
    // The type has strength blocks, but they are fixed or missing: nothing was estimated.
    e.strength_ok = false;
    e.strength_what = "no free strength parameter";
    return e;
  }
  double best_p = 2.0;
  // A block whose sandwich rests on no more clusters than it has coordinates has no test (G <= k):
  // it was reported as p = 1, "0.0 sigma from its null value", a strength stated to be nil that
  // was never measured (a degree-2 background's 45 coefficients over 32 runs of stream samples).
  std::string untestable;
  for (const auto& s : strengths) {
    const std::optional<Wald> w = WaldOfBlock(s.v, s.stddev, s.covariance);
    if (!w) continue;
    if (e.strength_clusters > 0 && e.strength_clusters <= w->dof) {
      if (untestable.empty()) {
        untestable = s.what + " (" + std::to_string(w->dof) + " coordinates over " +
                     std::to_string(e.strength_clusters) + " clusters: too few for a test)";
      }
      continue;
    }
    const double p = e.strength_clusters > 0
                         ? HotellingUpperTail(w->chi2, w->dof, e.strength_clusters)
                         : ChiSquareUpperTail(w->chi2, w->dof);
    if (best_p > 1.0 || p < best_p) {
      best_p = p;
      e.strength_what = s.what;
      e.strength_chi2 = w->chi2;
      e.strength_dof = w->dof;
    }
  }
  if (best_p > 1.0) {
    e.strength_ok = false;
    e.strength_what =
        untestable.empty() ? strengths.front().what + " (no standard deviation)" : untestable;
  } else {
    e.strength_p = std::min(1.0, best_p * static_cast<double>(strengths.size()));  // Bonferroni
    // Far in the tail p underflows: the deviate of a 1-dof statistic, sqrt(chi2), is then a floor.
    e.strength_sigma =
        e.strength_p > 0 ? TwoSidedNormalDeviate(e.strength_p) : std::sqrt(e.strength_chi2);
    e.strength_ok = e.strength_sigma >= min_strength_sigma;
  }

  // Location.
  if (volume_points.empty() || min_strength_sigma <= 0) return e;
  Eigen::Vector3d lo = volume_points.front(), hi = lo;
  for (const auto& p : volume_points) {
    lo = lo.cwiseMin(p);
    hi = hi.cwiseMax(p);
  }
  if (term_type == "dipole") {
    const ParameterReport* l = FindBlock(blocks, "location_in_transmitter");
    if (!l || l->values.size() != 3) return e;
    e.has_location = true;
    const Eigen::Vector3d x(l->values[0], l->values[1], l->values[2]);
    e.location_distance_m = (x - x.cwiseMax(lo).cwiseMin(hi)).norm();
    e.location_sigma_m = l->fixed ? 0.0 : LargestSigma(l->stddev, l->covariance);
    const Eigen::Vector3d towards = x - 0.5 * (lo + hi);
    if (towards.norm() > 0) e.direction = towards.normalized();
  } else if (term_type == "plane") {
    const ParameterReport* d = FindBlock(blocks, "distance_m");
    const ParameterReport* n = FindBlock(blocks, "normal_in_transmitter");
    if (!d || !n || d->values.size() != 1 || n->values.size() != 3) return e;
    e.has_location = true;
    const Eigen::Vector3d normal =
        Eigen::Vector3d(n->values[0], n->values[1], n->values[2]).normalized();
    double s_min = std::numeric_limits<double>::infinity(), s_max = -s_min;
    for (const auto& p : volume_points) {
      const double s = normal.dot(p) - d->values[0];
      s_min = std::min(s_min, s);
      s_max = std::max(s_max, s);
    }
    // A plane through the measured volume has distance 0 (the receiver cannot pass through it).
    e.location_distance_m = s_min > 0 ? s_min : (s_max < 0 ? -s_max : 0.0);
    // The plane's position at the volume: its distance's sigma, and the normal's angular sigma
    // [rad] times the lever arm of the volume's centre across the normal.
    const double sigma_d = d->fixed ? 0.0 : At(d->stddev, 0);
    double sigma_angle = 0.0;
    if (!n->fixed) {
      sigma_angle = n->stddev.size() >= 2 ? std::hypot(n->stddev[0], n->stddev[1]) : NAN;
    }
    const Eigen::Vector3d c = 0.5 * (lo + hi);
    const double lever = (c - normal.dot(c) * normal).norm();
    e.location_sigma_m = std::hypot(sigma_d, sigma_angle * lever);
    // The normal itself: the position test above weighs it by the lever arm of the volume's
    // centre, which is short when the normal points near the centre, so a plane whose orientation
    // is open by 20 deg still passed it (measured, the main job's capture after the sensor offset,
    // the workbench frame and the floor: 1.70 m +- 0.14 along a normal +- 19.9 deg, position +-
    // 0.24 m at the volume against 1.20 m away, claimed, standing in for the +y monitors; 10.0 deg
    // in the units of session 38, which halved the normal's reported sigma to its true value). Which
    // wall a plane is, is its orientation: its field is that of the transmitter's mirror image,
    // which such a normal moves sideways by 2 d sigma = 1.2 m.
    e.normal_sigma_rad = sigma_angle;
    e.normal_ok = std::isfinite(sigma_angle) && sigma_angle <= max_normal_sigma_rad;
    const double towards = d->values[0] - normal.dot(c);  // from the centre to the plane, along n
    if (towards != 0) e.direction = (towards > 0 ? 1.0 : -1.0) * normal;
  }
  if (e.has_location) {
    e.location_ok = std::isfinite(e.location_sigma_m) && e.location_distance_m > 0 &&
                    e.location_sigma_m <= e.location_distance_m && e.normal_ok;
  }
  return e;
}
}  // namespace

// A source location with a standard deviation beyond this is not stated as a number [m].
constexpr double kUndeterminedLocationM = 100.0;

std::string PhysicalEvidence::Describe() const {
  if (!assessed) return "";
  std::ostringstream r;
  if (std::isfinite(strength_sigma)) {
    r << strength_what << " " << FormatNumber(strength_sigma, 1) << " sigma from its null value";
  } else {
    r << strength_what << ": strength not tested";
  }
  if (noise_scale != 1.0)
    r << " (sigmas x " << FormatSignificant(noise_scale, 2) << ", sqrt(chi2/dof))";
  if (has_location && !(location_sigma_m < kUndeterminedLocationM)) {
    r << "; location undetermined";  // a source that drifted away with no strength left
  } else if (has_location) {
    r << "; location +- " << FormatNumber(location_sigma_m, 3) << " m, "
      << FormatNumber(location_distance_m, 3) << " m from the measured volume";
  }
  if (std::isfinite(normal_sigma_rad)) {
    r << "; normal +- " << FormatNumber(normal_sigma_rad * kDegPerRad, 1) << " deg";
  }
  return r.str();
}

nlohmann::json PhysicalEvidence::ToJson() const {
  if (!assessed) return nullptr;
  nlohmann::json j = {{"strength",
                       {{"what", strength_what},
                        {"chi2", NumberOrNull(strength_chi2)},
                        {"dof", strength_dof},
                        {"clusters", strength_clusters},
                        {"p_value", NumberOrNull(strength_p)},
                        {"sigma", NumberOrNull(strength_sigma)},
                        {"ok", strength_ok}}},
                      {"noise_scale", noise_scale},
                      {"supported", supported()}};
  j["location"] =
      has_location ? nlohmann::json{{"sigma_m", NumberOrNull(location_sigma_m)},
                                    {"distance_from_volume_m", NumberOrNull(location_distance_m)},
                                    {"determined", location_ok}}
                   : nlohmann::json();
  if (has_location) {
    if (std::isfinite(normal_sigma_rad)) {
      j["location"]["normal_sigma_deg"] = normal_sigma_rad * kDegPerRad;
      j["location"]["normal_determined"] = normal_ok;
    }
    if (!direction.isZero()) {
      j["location"]["direction"] = {direction.x(), direction.y(), direction.z()};
    }
  }
  return j;
}

// The flexible fallback with the best held-out gain that the held-out test supports (p below the
// threshold, drop at least min_drop_percent) although it is not significant (BIC); null if none.
static const Candidate* FlexibleWithHeldOutGain(const Diagnosis& d,
                                                const CandidateOptions& options) {
  const Candidate* best = nullptr;
  for (const auto& f : d.flexible) {
    if (!f.cross_validated || !(f.p_value < d.p_threshold) ||
        !(std::fmax(f.drop_position_percent, f.drop_orientation_percent) >=
          options.min_drop_percent))  // fmax and >=: a NaN drop (unknown base error) never passes
      continue;
    if (!best || f.cv_whitened_mean < best->cv_whitened_mean) best = &f;
  }
  return best;
}

Diagnosis DiagnoseCandidates(const std::vector<FitStation>& stations, const std::string& model_text,
                             const std::string& model_source, const std::string& data_source,
                             const CandidateOptions& options) {
  options.Check();
  const auto start = Clock::now();
  const size_t min_stations = std::max<size_t>(12, 2 * static_cast<size_t>(options.folds));
  if (stations.size() < min_stations) {
    throw std::invalid_argument(data_source + ": diagnose needs at least " +
                                std::to_string(min_stations) + " calibration stations, got " +
                                std::to_string(stations.size()));
  }
  Diagnosis d;
  d.model = model_source;
  d.data = data_source;
  d.folds = options.folds;
  d.num_stations = static_cast<int>(stations.size());
  const int n_residuals = 6 * static_cast<int>(stations.size());

  // The base model (also validates the file: errors name its lines).
  ModelSpec base_spec = ParseModelYaml(model_text, model_source);
  // Every candidate model has the base's `noise:` (a candidate changes terms, loss or time offset);
  // only these settings of base_spec are read while its fast folds move its values.
  const ModelSpec& noise = base_spec;

  // The candidates. Term types as written in the file (the engine may merge several file terms
  // into one, e.g. consecutive physical terms into one field model).
  std::set<std::string> present;
  for (const auto& t : YAML::Load(model_text)["terms"]) {
    if (t.IsMap() && t["type"]) present.insert(t["type"].as<std::string>());
  }
  std::vector<PreparedCandidate> prepared;
  std::vector<std::pair<const CatalogEffect*, bool>> to_test;  // (effect, flexible)
  for (const CatalogEffect& e : options.catalog) to_test.emplace_back(&e, false);
  for (const CatalogEffect& e : options.flexible) to_test.emplace_back(&e, true);
  for (const auto& [effect, flexible] : to_test) {
    const CatalogEffect& e = *effect;
    if (!flexible && !options.effects.empty() &&
        std::find(options.effects.begin(), options.effects.end(), e.effect) ==
            options.effects.end()) {
      continue;
    }
    PreparedCandidate p;
    p.effect = &e;
    p.flexible = flexible;
    p.candidate.effect = e.effect;
    p.candidate.kind = e.kind;
    YAML::Node changed = YAML::Load(model_text);  // a deep copy to modify
    if (e.kind == CandidateKind::kTimeOffset) {
      if (!options.pair_streams) {
        d.skipped.push_back(e.effect + ": the data are not streams");
        continue;
      }
      if (base_spec.time_offset && !base_spec.time_offset->fixed) {
        d.skipped.push_back(e.effect + ": the model estimates it");
        continue;
      }
      const TimeOffsetSpec t = base_spec.time_offset.value_or(TimeOffsetSpec());
      YAML::Node offset(YAML::NodeType::Map);
      offset["value"] = FormatSignificant(t.value, 17);
      offset["fixed"] = false;
      offset["search_range"] = FormatSignificant(t.search_range, 17);
      changed["time_offset"] = offset;
    } else if (e.kind == CandidateKind::kRobustLoss) {
      if (base_spec.loss.type != LossType::kNone) {
        d.skipped.push_back(e.effect + ": the model has a robust loss");
        continue;
      }
      YAML::Node loss(YAML::NodeType::Map);
      loss["type"] = LossTypeName(options.robust_loss.type);
      loss["scale"] = FormatSignificant(options.robust_loss.scale, 6);
      changed["loss"] = loss;
      YAML::Node item(YAML::NodeType::Map);
      item["loss"] = loss;
      p.candidate.model_change = Emit(item);
    } else {
      const std::string type = YAML::Load(e.term_yaml)["type"].as<std::string>();
      if (!TermRegistry::Global().Contains(type)) {
        d.skipped.push_back(e.effect + ": term type '" + type + "' is not available in this build");
        continue;
      }
      if (!e.repeatable && present.count(type)) {
        d.skipped.push_back(e.effect + ": the model has it");
        continue;
      }
      YAML::Node terms = changed["terms"];
      // A repeated type gets a name of its own so its parameters can be found in the reports
      // (unnamed repeats are numbered type, type_2, ...: counting past them avoids a clash); so
      // does every term after the first of a pair.
      std::set<std::string> names;
      int count = 0;
      for (const auto& t : terms) {
        if (t.IsMap() && t["name"]) names.insert(t["name"].as<std::string>());
        if (t.IsMap() && t["type"] && t["type"].as<std::string>() == type) ++count;
      }
      for (int copy = 0; copy < e.count; ++copy) {
        YAML::Node term = YAML::Load(e.term_yaml);
        term.SetStyle(YAML::EmitterStyle::Block);
        if (e.repeatable && !term["name"] && count > 0) {
          std::string name;
          for (int k = count + 1; name.empty() || names.count(name); ++k) {
            name = type + "_" + std::to_string(k);
          }
          term["name"] = name;
          names.insert(name);
        }
        ++count;
        p.candidate.term_names.push_back(term["name"] ? term["name"].as<std::string>() : type);
        p.terms.push_back(term);
      }
      p.candidate.term_name = p.candidate.term_names.front();
      const int index = e.physical ? PhysicalInsertIndex(terms) : static_cast<int>(terms.size());
      YAML::Node seq(YAML::NodeType::Sequence);
      int i = 0;
      for (const auto& t : terms) {
        if (i++ == index) {
          for (const auto& added : p.terms) seq.push_back(added);
        }
        seq.push_back(t);
      }
      if (index >= static_cast<int>(terms.size())) {
        for (const auto& added : p.terms) seq.push_back(added);
      }
      changed["terms"] = seq;
      p.candidate.insert_index = index;
      p.candidate.model_change = TermListItems(p.terms);
    }
    p.candidate.model_text = Emit(changed);
    p.root = changed;
    prepared.push_back(std::move(p));
  }

  // Replacements: each source term of the model (dipole, plane) swapped for the other kind, which
  // searches its own start in that place. Terms with a block the file holds fixed (a room's known
  // plane) stay. The new term takes the name the model file's numbering gives it (fit/model_file.cc:
  // repeated types are numbered unless named).
  {
    const std::vector<ModelTermName> items = ModelTermNames(model_text);
    std::vector<std::string> names;  // each item's term name, as ParseModelYaml names it
    for (const auto& item : items) names.push_back(item.name);
    for (size_t i = 0; i < names.size(); ++i) {
      const std::string& type = items[i].type;
      if ((type != "dipole" && type != "plane") || items[i].held_fixed) continue;
      const std::string other = type == "dipole" ? "plane" : "dipole";
      const CatalogEffect* e = nullptr;
      for (const CatalogEffect& c : options.catalog) {
        if (c.effect == other && c.kind == CandidateKind::kTerm && c.count == 1) e = &c;
      }
      if (e == nullptr || !TermRegistry::Global().Contains(other) ||
          (!options.effects.empty() &&
           std::find(options.effects.begin(), options.effects.end(), other) ==
               options.effects.end())) {
        continue;
      }
      PreparedCandidate p;
      p.effect = e;
      p.candidate.effect = e->effect;
      p.candidate.kind = CandidateKind::kTerm;
      p.candidate.replaces = names[i];
      YAML::Node term = YAML::Load(e->term_yaml);
      term.SetStyle(YAML::EmitterStyle::Block);
      std::set<std::string> taken;
      for (size_t j = 0; j < names.size(); ++j) {
        if (j != i) taken.insert(names[j]);
      }
      const std::string name = NumberedName(other, taken);
      if (name != other) term["name"] = name;
      p.candidate.term_names = {name};
      p.candidate.term_name = name;
      p.terms.push_back(term);
      YAML::Node changed = YAML::Load(model_text);
      YAML::Node seq(YAML::NodeType::Sequence);
      for (size_t j = 0; j < names.size(); ++j) {
        seq.push_back(j == i ? term : changed["terms"][j]);
      }
      changed["terms"] = seq;
      p.candidate.insert_index = static_cast<int>(i);
      p.candidate.model_change = TermListItems(p.terms);
      p.candidate.model_text = Emit(changed);
      p.root = changed;
      prepared.push_back(std::move(p));
    }
  }

  // The model's own source terms whose support the base fit is asked for: (item, name, type).
  std::vector<std::tuple<int, std::string, std::string>> base_sources;
  {
    const std::vector<ModelTermName> items = ModelTermNames(model_text);
    for (size_t i = 0; i < items.size(); ++i) {
      if ((items[i].type == "dipole" || items[i].type == "plane") && !items[i].held_fixed) {
        base_sources.emplace_back(static_cast<int>(i), items[i].name, items[i].type);
      }
    }
  }

  // Base: full fit (cost, BIC) and cross-validation.
  StationErrors base_full = MakeErrors(stations.size());
  int base_k = 0;            // free parameters of the base fit
  bool base_linear = false;  // solved by linear least squares: its exact folds cost nothing
  // The base's fitted state (a copy: the base's fast cross-validation moves base_spec's values
  // while candidates are fitted), where a candidate whose own start fits worse starts again.
  FitStart base_start;
  std::vector<int> base_left_out;  // the base fit's (FitResult::left_out): no fold trains on them
  std::vector<bool> base_report_form;  // the base fit's residual forms, which its folds keep
  {
    const auto t0 = Clock::now();
    Progress(options, "base model: fit on " + std::to_string(stations.size()) + " stations");
    FitOptions fo;
    // Standard deviations only to assess the model's own source terms (below).
    fo.compute_covariance = !base_sources.empty() && options.min_strength_sigma > 0;
    const FitResult fit = FitModel(stations, &base_spec, fo);
    // Every candidate is judged against the base: a base at its start values (the solver failed)
    // would rank them by how they repair that.
    if (fit.Failed()) {
      throw std::runtime_error(model_source + ": the model's own fit to " + data_source +
                               " failed (" + fit.termination_type + ": " + fit.solver_message +
                               "): no candidate can be compared with it");
    }
    base_start = TakeFitStart(base_spec);
    base_left_out = fit.left_out;
    base_report_form = fit.report_form;
    for (size_t i = 0; i < stations.size(); ++i) {
      AppendErrors(fit.chain, stations[i], noise, &base_full, i);
    }
    base_k = fit.num_free_parameters;
    base_linear = fit.linear_least_squares;
    const Chi2 c = ComputeChi2(stations, base_full, base_spec.loss);
    BaseScores& b = d.base;
    b.converged = fit.converged;
    b.final_cost = fit.final_cost;
    b.num_residuals = n_residuals;
    const int k = fit.num_free_parameters + 6 * static_cast<int>(c.outliers.size());
    b.num_free_parameters = fit.num_free_parameters;
    b.chi2 = c.chi2;
    b.chi2_per_dof = n_residuals > k ? c.chi2 / (n_residuals - k) : NAN;
    b.bic = Bic(c.chi2, n_residuals, k);
    b.seconds = SecondsSince(t0);
    if (fo.compute_covariance) {
      // As for a candidate: model-covariance sigmas take the noise the fit leaves (the mean-shift
      // model's: its outliers' parameters leave the degrees of freedom as their residuals chi2).
      const int noise_dof = n_residuals - k;
      const bool empirical = fit.covariance_estimator.rfind("sandwich", 0) == 0;
      const double noise_scale =
          !empirical && noise_dof > 0 && c.chi2 > 0 ? std::sqrt(c.chi2 / noise_dof) : 1.0;
      for (const auto& [index, name, type] : base_sources) {
        const PhysicalEvidence ev = AssessPhysicalEvidence(
            type, BlocksOfTerm(fit.parameters, name), MeasuredPositions(stations),
            options.min_strength_sigma, noise_scale, options.max_normal_sigma_rad,
            empirical ? fit.covariance_clusters : 0);
        if (ev.assessed && !ev.supported()) d.unsupported_terms.push_back({name, type, index, ev});
      }
    }
  }
  // Removals: each source term the base fit no longer identifies, tried without it. Often a
  // source added to stand in for one that a later term explains better (measured, paper room with
  // a sensor offset and receiver gains, seed 4: a second dipole stood in for the floor until the
  // floor plane went in, then stayed at 1.5 sigma with its location open by 0.13 m).
  if (options.effects.empty() || std::find(options.effects.begin(), options.effects.end(),
                                           kRemoveEffect) != options.effects.end()) {
    int correction_terms = 0;  // the model's terms other than a time offset
    for (const auto& item : ModelTermNames(model_text)) correction_terms += item.type != "time_offset";
    for (const auto& u : d.unsupported_terms) {
      if (correction_terms <= 1) {  // a model needs one correction term (fit/model_file.h)
        d.skipped.push_back(std::string(kRemoveEffect) + " " + u.term +
                            ": it is the model's only correction term");
        continue;
      }
      PreparedCandidate p;
      p.effect = &RemovalEffect();
      Candidate& c = p.candidate;
      c.effect = kRemoveEffect;
      c.kind = CandidateKind::kRemoval;
      c.replaces = u.term;
      c.insert_index = u.index;
      c.statement = "without " + u.term + " (" + u.evidence.Describe() + ")";
      YAML::Node changed = YAML::Load(model_text);
      YAML::Node seq(YAML::NodeType::Sequence);
      int j = 0;
      for (const auto& t : changed["terms"]) {
        if (j++ != u.index) seq.push_back(t);
      }
      changed["terms"] = seq;
      c.model_text = Emit(changed);
      p.root = changed;
      prepared.push_back(std::move(p));
    }
  }
  // Folds. Static stations: station i in fold i mod k. Serial stations (stream samples ~10 ms
  // apart, whose neighbours share the model's misfit): i mod k would put a held-out sample's
  // neighbours in the training folds, and a per-sample paired test would count thousands of
  // correlated differences as independent. So they are cut into contiguous blocks of time
  // (serial_block, CandidateOptions::serial_blocks), block b goes to fold b mod k, and the paired
  // test takes the blocks' mean differences (PairedGreaterP). Not k contiguous stretches (as the
  // covariate analysis's binned means, python/trackcal/validation.py): a fifth of a 20 s stream
  // is a stretch of path the others do not visit, where a degree-4 polynomial extrapolates
  // (measured, paper room, seed 1: held-out error 7.27 mm against 0.72 with folds i mod k, every
  // candidate 5-9 times worse than the base). Measured before (folds i mod k, test per sample),
  // the same stream, no clock offset: receiver_gain p = 6e-41, sensor_offset p = 4e-26
  // (docs/diagnose.md, "Stream samples are tested over blocks of time").
  const std::vector<int> serial_block =
      SerialTestBlocks(stations, options.serial_blocks, options.folds);
  const int num_blocks =
      serial_block.empty() ? 0 : 1 + *std::max_element(serial_block.begin(), serial_block.end());
  d.paired_test_blocks = num_blocks;
  // The first tracker time of each block (increasing), to place a re-paired candidate's stations.
  std::vector<double> block_start(static_cast<size_t>(num_blocks),
                                  std::numeric_limits<double>::infinity());
  for (size_t i = 0; i < serial_block.size(); ++i) {
    double& t = block_start[static_cast<size_t>(serial_block[i])];
    t = std::min(t, stations[i].time);
  }
  for (int k = num_blocks - 2; k >= 0; --k) {  // a block without stations (not expected) ends
    double& t = block_start[static_cast<size_t>(k)];  // where the next begins: still increasing
    t = std::min(t, block_start[static_cast<size_t>(k + 1)]);
  }
  auto fold_of_block = [&](int block) { return block % options.folds; };
  auto block_at_time = [&](double time) {
    const auto it = std::upper_bound(block_start.begin(), block_start.end(), time);
    return std::max(0, static_cast<int>(it - block_start.begin()) - 1);
  };
  // The rule of trackcal-fit fit's cross-validation (CrossValidate), so the base's held-out table
  // is the fit's and carries its name (at the default serial_blocks, the fit's own folds).
  bool base_by_blocks = false;
  const std::vector<int> base_folds =
      CrossValidationFolds(stations, options.folds, options.serial_blocks, &base_by_blocks);
  const int threads = options.num_threads > 0
                          ? options.num_threads
                          : std::max(1, static_cast<int>(std::thread::hardware_concurrency()));
  StationErrors base_cv;
  double base_cv_seconds = 0.0;
  auto validate_base = [&] {
    const auto t0 = Clock::now();
    bool fast_done = false;
    if (!options.exact_cv && !base_linear && FastCrossValidationApplies(stations, base_spec)) {
      Progress(options,
               "base model: " + std::to_string(options.folds) + " fold refits from the full fit");
      std::optional<StationErrors> fast = FastCrossValidateStations(
          stations, base_folds, &base_spec, base_left_out, base_report_form, options.folds, noise,
          [&](const std::string& m) { Progress(options, "base model: " + m); });
      if (fast) base_cv = std::move(*fast);
      fast_done = fast.has_value();
    }
    if (!fast_done) {
      base_cv =
          CrossValidateStations(stations, base_folds, model_text, model_source, options.folds,
                                noise, [&](int f) {
                                  Progress(options, "base model: fold " + std::to_string(f + 1) +
                                                        "/" + std::to_string(options.folds));
                                });
    }
    base_cv_seconds = SecondsSince(t0);
  };
  auto base_table = [&] {
    std::vector<Rigid3d> reported, reference;
    for (const auto& s : stations) {
      reported.push_back(s.reported);
      reference.push_back(s.reference);
    }
    d.base.table1 = MakeTable1(CrossValidationTableName(options.folds, base_by_blocks), reported,
                               base_cv.corrected, reference);
    d.base.cv_position_mm_mean = Mean(base_cv.position_mm);
    d.base.cv_orientation_deg_mean = Mean(base_cv.orientation_deg);
    d.base.seconds += base_cv_seconds;  // full fit and cross-validation
  };

  // Candidates: fit on all stations (parameters, BIC).
  auto fit_candidate = [&](PreparedCandidate& p) {
    Candidate& c = p.candidate;
    const auto t0 = Clock::now();
    try {
      int extra_parameters = 0;
      if (c.kind == CandidateKind::kTimeOffset) {
        // The stations themselves change: pair the streams again, estimating the offset.
        TimeOffsetSpec t = base_spec.time_offset.value_or(TimeOffsetSpec());
        t.fixed = false;
        Progress(options, c.effect + ": pairing the streams, estimating the clock offset");
        PairedStations paired = options.pair_streams(t);
        p.stations = std::move(paired.stations);
        p.time_offset_s = paired.time_offset_s;
        extra_parameters = 1;
        YAML::Node item(YAML::NodeType::Map);
        YAML::Node offset(YAML::NodeType::Map);
        offset["value"] = FormatSignificant(paired.time_offset_s, 6);  // 0.037, not 0.03699999...
        offset["fixed"] = false;
        offset["search_range"] = FormatSignificant(t.search_range, 6);
        item["time_offset"] = offset;
        c.model_change = Emit(item);
        // The fit (and each fold's) starts from the offset the stations were paired at: with the
        // reference's velocities it is the reference of the joint estimate's linearisation.
        YAML::Node root = YAML::Load(c.model_text);
        root["time_offset"]["value"] = FormatSignificant(paired.time_offset_s, 17);
        c.model_text = Emit(root);
      }
      const std::vector<FitStation>& own = p.stations.empty() ? stations : p.stations;
      // Which base station each of the candidate's stations is (by tracker time when re-paired).
      p.base_index.assign(own.size(), -1);
      if (p.stations.empty()) {
        std::iota(p.base_index.begin(), p.base_index.end(), 0);
      } else {
        std::map<double, int> by_time;
        for (size_t i = 0; i < stations.size(); ++i)
          by_time[stations[i].time] = static_cast<int>(i);
        for (size_t j = 0; j < own.size(); ++j) {
          auto it = by_time.find(own[j].time);
          if (it != by_time.end()) p.base_index[j] = it->second;
        }
      }
      Progress(options, c.effect + ": fit on " + std::to_string(own.size()) + " stations");
      ModelSpec spec = ParseModelYaml(c.model_text, model_source + " + " + c.effect);
      FitOptions fo;
      // A flexible term's parameters are not reported, nor a removal's (it adds none).
      fo.compute_covariance = !p.flexible && c.kind != CandidateKind::kRemoval;
      FitResult fit = FitModel(own, &spec, fo);
      Progress(options, c.effect + ": " + FitTimeNote(fit));
      // Go on once from where a fit stopped at the iteration limit (every term at the values it
      // reached, FitOptions::start), so that a slow valley (a distant object trading location and
      // strength) is not mistaken for no optimum. Measured, paper preset, ferromagnetic_object
      // seed 3, degree-4 polynomial: the toolbox dipole stopped at 100 iterations 15 mm from its
      // optimum; from there it converged in 48.
      auto go_on = [&](FitResult* f, ModelSpec* s, const std::string& text,
                       const std::string& what) {
        if (f->converged || c.kind != CandidateKind::kTerm) return;
        try {
          const FitStart reached = TakeFitStart(*s);
          FitOptions from = fo;
          from.start = &reached;
          // The added terms' starts written out too: a searched source is not searched again.
          YAML::Node root = YAML::Load(text);
          for (size_t t = 0; c.insert_index && t < p.terms.size(); ++t) {
            YAML::Node term = root["terms"][static_cast<size_t>(*c.insert_index) + t];
            AddFittedStart(p.terms[t]["type"].as<std::string>(),
                           BlocksOfTerm(f->parameters, c.term_names[t]), &term);
          }
          ModelSpec again = ParseModelYaml(Emit(root), model_source + " + " + c.effect);
          FitResult more = FitModel(own, &again, from);
          Progress(options, c.effect + " (" + what + "continued): " + FitTimeNote(more));
          if (more.final_cost <= f->final_cost) {
            *f = std::move(more);
            *s = std::move(again);
          }
        } catch (const std::exception& ex) {  // keep the fit it continued
          Progress(options, c.effect + " (" + what + "continued): failed: " + ex.what());
        }
      };
      go_on(&fit, &spec, c.model_text, "");
      bool grown_kept = false;  // the kept fit grew the added sources from near zero
      // The candidate contains the base (the base plus an effect whose null value it can take, on
      // the same stations): the retry and the nested rules below rest on that (NullExcludedWhy).
      std::string not_nested;
      for (const auto& name : c.term_names) {
        if (not_nested.empty()) not_nested = NullExcludedWhy(spec, name);
      }
      if (!not_nested.empty()) {
        Progress(options, c.effect + ": does not contain the base model: " + not_nested);
      }
      const bool nested = c.kind == CandidateKind::kTerm && c.insert_index && c.replaces.empty() &&
                          p.stations.empty() && not_nested.empty();
      if (nested) {
        // The base plus an effect that fits the stations worse than the base: the joint fit left
        // the base's optimum for a worse one (an added source at its searched strength pulls the
        // others and the polynomial's start away; the polynomial's `ridge: auto` weight and the
        // noise whitening are chosen afresh from a different start). The base is inside the
        // candidate's model, so fit again from the base's optimum (FitOptions::start: its values,
        // polynomial normalisation and ridge weight) with the added terms near their null: a
        // source at kGrowFromFraction of its fitted strength where it was placed, another effect
        // at its null start. The cheaper fit by the stations' chi2 on the runtime chain (the
        // BIC's; not final_cost, which includes a polynomial prior whose weight differs between
        // the two fits) over the stations the base resolves is kept. Measured, full paper capture
        // (ferromagnetic_object seed 2, after the frame and the toolbox): the floor plane from its
        // searched strength, delta BIC +1031; from the base's optimum, -1429.
        std::vector<bool> compared(own.size(), false);
        for (size_t j = 0; j < own.size(); ++j) {
          const int b = p.base_index[j];
          compared[j] = b >= 0 && !base_full.unresolved[static_cast<size_t>(b)];
        }
        auto station_chi2 = [&](const FitResult& f, const ModelSpec& s) {
          StationErrors e = MakeErrors(own.size());
          for (size_t j = 0; j < own.size(); ++j) {
            AppendErrors(f.chain, own[j], noise, &e, j);
          }
          return ComputeChi2(own, e, s.loss, compared).chi2;
        };
        const double base_chi2 = ComputeChi2(stations, base_full, base_spec.loss, compared).chi2;
        const double first_chi2 = station_chi2(fit, spec);
        // `root`: the added terms at their null start; `placed`: the same with each added
        // source's location held where the first fit put it.
        YAML::Node root = YAML::Load(c.model_text), placed = YAML::Load(c.model_text);
        bool restart = first_chi2 > base_chi2;
        bool grows = false;
        for (size_t t = 0; restart && t < p.terms.size(); ++t) {
          const size_t at = static_cast<size_t>(*c.insert_index) + t;
          YAML::Node term = root["terms"][at], term_placed = placed["terms"][at];
          const std::string type = p.terms[t]["type"].as<std::string>();
          if (type == "dipole" || type == "plane") {
            const auto blocks = BlocksOfTerm(fit.parameters, c.term_names[t]);
            restart = AddFittedStart(type, blocks, &term) &&
                      ScaleSourceStrength(kGrowFromFraction, &term) &&
                      AddFittedStart(type, blocks, &term_placed) &&
                      ScaleSourceStrength(kGrowFromFraction, &term_placed);
            placed["terms"][at] = YAML::Load(HoldSourceLocation(type, Emit(term_placed)));
            grows = true;
          }
        }
        if (restart) {
          const std::string how = grows ? "grown from near zero" : "from the base's optimum";
          try {
            const std::string text = Emit(root);
            FitOptions from = fo;
            from.start = &base_start;
            // A source grows first where it was placed: at a small strength its location barely
            // moves the field, so the solver would move it freely (measured, full paper capture,
            // ferromagnetic_object seed 3 after the toolbox: the floor plane let free from a
            // thousandth of its strength ended 1 m +- 22 from the transmitter at no strength,
            // delta BIC +36, against -806 from its searched start). Then everything is let free
            // from there.
            FitStart grown_placed;
            if (grows) {
              ModelSpec held = ParseModelYaml(Emit(placed), model_source + " + " + c.effect);
              FitOptions stage_options = from;
              stage_options.compute_covariance = false;  // a start, not reported
              const FitResult stage = FitModel(own, &held, stage_options);
              Progress(options, c.effect + " (grown where it was placed): " + FitTimeNote(stage));
              grown_placed = TakeFitStart(held);
              from.start = &grown_placed;
            }
            ModelSpec again = ParseModelYaml(text, model_source + " + " + c.effect);
            FitResult refit = FitModel(own, &again, from);
            Progress(options, c.effect + " (" + how + "): " + FitTimeNote(refit));
            go_on(&refit, &again, text, how + ", ");
            if (station_chi2(refit, again) < first_chi2) {
              fit = std::move(refit);
              spec = std::move(again);
              grown_kept = grows;
            }
          } catch (const std::exception& ex) {  // keep the first fit
            Progress(options, c.effect + " (" + how + "): failed: " + ex.what());
          }
        }
      }
      // A fit that failed, or a nested one that ended far above the base's cost, is no result:
      // its values are where the solver stopped, not the candidate's optimum, and scoring them
      // said "fitted, no better than the base" of an effect that was never tested. The base is
      // the candidate at the added effect's null value, so at its optimum the candidate's cost
      // is at most about the base's (the polynomial's ridge weight and the noise metrics are
      // chosen afresh: a few percent, not a factor kMaxNestedCostRatio). Measured, ideal preset,
      // paper_small grid, a 0.0005 m^3 object 0.075 m beside the grid (seed 6,
      // fit/candidates_fast_test.cc NestedFitsFarAboveTheBaseFailed): near_field, plane,
      // sensor_offset, receiver_gain and background_field over the degree-4 polynomial all stayed
      // at their start, cost 1.1e19 against the base's 2.1e5 (one station's pose-form residual 2e9
      // sigma, every step failing to evaluate), Ceres said CONVERGENCE, and each was listed as
      // fitted at 0.000 with delta BIC equal to its parameter penalty.
      if (fit.Failed()) {
        throw std::runtime_error("the fit failed (" + fit.termination_type + ": " +
                                 fit.solver_message + ")");
      }
      if (nested && !(fit.final_cost <= std::max(kMaxNestedCostRatio * d.base.final_cost,
                                                 d.base.final_cost + n_residuals))) {
        throw std::runtime_error("the fit did not find the optimum: its final cost " +
                                 FormatSignificant(fit.final_cost, 3) + " is " +
                                 FormatSignificant(fit.final_cost / d.base.final_cost, 2) +
                                 " times the base model's " +
                                 FormatSignificant(d.base.final_cost, 3) +
                                 " on the same stations, which the candidate contains (" +
                                 fit.termination_type + " after " + std::to_string(fit.iterations) +
                                 " iterations: " + fit.solver_message + ")");
      }
      c.converged = fit.converged;
      StationErrors full = MakeErrors(own.size());
      // A clock offset fitted with the model moved the references from where they were paired.
      const double shift = c.kind == CandidateKind::kTimeOffset && spec.time_offset
                               ? spec.time_offset->value - p.time_offset_s
                               : 0.0;
      for (size_t i = 0; i < own.size(); ++i)
        AppendErrors(fit.chain, own[i], noise, &full, i, shift);
      // BIC on the stations both models have (all of them unless the streams were re-paired).
      std::vector<bool> use_own(own.size()), use_base(stations.size(), false);
      for (size_t j = 0; j < own.size(); ++j) {
        use_own[j] = p.base_index[j] >= 0;
        if (use_own[j]) use_base[static_cast<size_t>(p.base_index[j])] = true;
      }
      // Stations where either chain's runtime inverse does not resolve the report (no root, or an
      // ambiguous one next to a strong object) are left out of the BIC when they are few: their
      // error is the inverse's best guess or report noise amplified past max_noise_gain, not the
      // model's misfit (the fit's residual there is taken at the reference). One such station
      // decided it (measured, full paper capture, ferromagnetic_object seed 3 after the toolbox:
      // station 350, 0.28 m from it, 75 mm off under the candidate workbench frame, turned delta
      // BIC from below -1000 to +2792 although the frame lowered the held-out error 47 %,
      // p = 2e-64). The held-out comparison leaves out the base's (below).
      std::vector<size_t> unresolved;
      for (size_t j = 0; j < own.size(); ++j) {
        if (!use_own[j]) continue;
        if (full.unresolved[j] || base_full.unresolved[static_cast<size_t>(p.base_index[j])]) {
          unresolved.push_back(j);
        }
      }
      // (A robust loss's delta BIC is the mean-shift model's, below, without the same stations.)
      if (c.kind != CandidateKind::kRobustLoss && !unresolved.empty() &&
          static_cast<double>(unresolved.size()) <=
              options.max_unresolved_fraction * static_cast<double>(own.size())) {
        for (size_t j : unresolved) {
          use_own[j] = false;
          use_base[static_cast<size_t>(p.base_index[j])] = false;
        }
        c.bic_unresolved_left_out = static_cast<int>(unresolved.size());
      }
      if (c.kind == CandidateKind::kRobustLoss) {
        p.full_whitened_sq = full.whitened_sq;
        p.full_unresolved.assign(own.size(), false);
        for (size_t j : unresolved) p.full_unresolved[j] = true;
      }
      const Chi2 chi = ComputeChi2(own, full, spec.loss, use_own);
      const Chi2 base_chi = ComputeChi2(stations, base_full, base_spec.loss, use_base);
      // A nested candidate whose stations fit worse than the base's did not find its optimum
      // either, even with its cost within kMaxNestedCostRatio (kMaxNestedChi2Excess): at the
      // effect's null value it scores as the base. The retry from the base's optimum above has
      // already been taken; the stations are the BIC's (unresolved ones left out as there). Not
      // under a robust loss: the mean-shift chi2 drops each model's own outliers, so the two need
      // not be ordered, and the cost rule stands alone there.
      const double compared_residuals =
          6.0 * static_cast<double>(std::count(use_own.begin(), use_own.end(), true));
      if (nested && spec.loss.type == LossType::kNone &&
          chi.chi2 > (1.0 + kMaxNestedChi2Excess) * base_chi.chi2 +
                         kMaxNestedChi2ExcessPerResidual * compared_residuals) {
        c.ended_above_base = true;
        // Two causes, which its final cost does not tell apart (see kMaxNestedChi2Excess): the
        // solver stopped short of the optimum, or the runtime inverse that scores the chi2 resolves
        // some stations to other poses than the fit's pose-form residuals did (a fold's other
        // root; candidates_sim_test AHeldPlaneStays...: a dipole at 77000 times the base's chi2
        // with its final cost below the base's).
        throw std::runtime_error(
            "it fits the stations worse than the base it contains: its chi2 " +
            FormatSignificant(chi.chi2, 4) + " is above the base model's " +
            FormatSignificant(base_chi.chi2, 4) +
            " on the same stations (the fit stopped short of its optimum, or the runtime inverse "
            "that scores it finds other roots than the fit at some stations; " +
            fit.termination_type + " after " + std::to_string(fit.iterations) + " iterations)");
      }
      c.fitted = true;
      const int n = 6 * static_cast<int>(std::count(use_own.begin(), use_own.end(), true));
      // A clock offset the fit estimated jointly is already in its count; one found by the
      // pairing's search alone (stations without velocities) is not.
      if (std::any_of(fit.parameters.begin(), fit.parameters.end(),
                      [](const ParameterReport& r) { return r.term == "time_offset"; })) {
        extra_parameters = 0;
      }
      c.num_free_parameters = fit.num_free_parameters + extra_parameters;
      const int k = c.num_free_parameters + 6 * static_cast<int>(chi.outliers.size());
      // Outliers are a minority by definition: when half the stations exceed the loss scale, the
      // model is wrong, and the mean-shift model that explains them away is not scored.
      c.bic = 2 * chi.outliers.size() > own.size() ? std::numeric_limits<double>::infinity()
                                                   : Bic(chi.chi2, n, k);
      c.delta_bic =
          c.bic - Bic(base_chi.chi2, n, base_k + 6 * static_cast<int>(base_chi.outliers.size()));
      c.outlier_stations = chi.outliers;
      if (c.insert_index) {
        for (const auto& name : c.term_names) {
          for (const auto& r : fit.parameters) {
            if (r.term == name) c.parameters.push_back(r);
          }
        }
      }
      // The noise scale profiled out (as in the BIC): sqrt(chi2/dof) of this fit, for sigmas from
      // the model covariance (the model file's noise). A sandwich covariance (the default,
      // fit/covariance.h) already takes its scale from the residuals: scaling it again would
      // shrink the sigmas by sqrt(chi2/dof) a second time. The statement and the JSON state the
      // scaled sigmas, as the claim rule judges them: with the default noise (1 mm, 15 times a
      // Fastrak's scatter) the model covariance said "+- (0.39, 1.28, 0.41) m" of a dipole whose
      // evidence gave +- 0.043 m.
      // (Under a loss, of the mean-shift model: `k` counts its outliers' parameters, whose
      // residuals left chi2.)
      const int noise_dof = n - k;
      const bool empirical = fit.covariance_estimator.rfind("sandwich", 0) == 0;
      const double noise_scale =
          !empirical && noise_dof > 0 && chi.chi2 > 0 ? std::sqrt(chi.chi2 / noise_dof) : 1.0;
      c.stddev_scale = noise_scale;
      const std::vector<ParameterReport> model_sigmas = c.parameters;  // for the evidence
      ScaleStddevs(noise_scale, &c.parameters);
      if (!options.exact_cv && !fit.linear_least_squares && FastCrossValidationApplies(own, spec)) {
        p.fitted = std::make_shared<ModelSpec>(std::move(spec));  // the folds start here
        p.left_out = fit.left_out;
        p.report_form = fit.report_form;
      }
      if (c.kind == CandidateKind::kTerm && c.term_names.size() > 1) {
        // One statement per added term ("a ferromagnetic object near ...; a ferromagnetic object
        // near ...").
        c.statement.clear();
        for (const auto& name : c.term_names) {
          Candidate one = c;
          one.parameters = BlocksOfTerm(c.parameters, name);
          c.statement += (c.statement.empty() ? "" : "; ") +
                         Statement(*p.effect, one, options.robust_loss.scale);
        }
      } else if (c.kind == CandidateKind::kRemoval) {
        // The statement of the term removed, set when it was prepared.
      } else if (c.kind != CandidateKind::kTimeOffset) {
        c.statement = Statement(*p.effect, c, options.robust_loss.scale);
        if (!c.replaces.empty() && !c.statement.empty()) {
          c.statement = "in place of " + c.replaces + ", " + c.statement;
        }
      } else {
        for (const auto& r : fit.parameters) {
          if (r.term == "time_offset") c.parameters.push_back(r);
        }
        ScaleStddevs(noise_scale, &c.parameters);
        c.statement = TimeOffsetStatement(fit, p.time_offset_s, noise_scale);
      }
      if (c.kind == CandidateKind::kTerm && !p.flexible && options.min_strength_sigma > 0) {
        // Several added terms: each must identify its source, so the candidate carries the
        // weakest term's evidence (one that fails, else the least strong).
        for (size_t t = 0; t < c.term_names.size(); ++t) {
          const PhysicalEvidence ev = AssessPhysicalEvidence(
              p.terms[t]["type"].as<std::string>(), BlocksOfTerm(model_sigmas, c.term_names[t]),
              MeasuredPositions(own), options.min_strength_sigma, noise_scale,
              options.max_normal_sigma_rad, empirical ? fit.covariance_clusters : 0);
          if (t == 0 || WeakerEvidence(ev, c.evidence)) c.evidence = ev;
        }
        // A strength held or bounded away from its null is not measured against the null: the
        // Wald test would find a bounded gain 12.5 sigma from G = I because the bound put it there.
        if (!not_nested.empty() && c.evidence.assessed) {
          c.evidence.strength_ok = false;
          c.evidence.strength_what = not_nested;
          c.evidence.strength_chi2 = c.evidence.strength_p = c.evidence.strength_sigma = NAN;
          c.evidence.strength_dof = 0;
        }
      }
      bool started = c.kind == CandidateKind::kTerm;
      for (size_t t = 0; started && t < p.terms.size(); ++t) {
        started = AddFittedStart(p.terms[t]["type"].as<std::string>(),
                                 BlocksOfTerm(c.parameters, c.term_names[t]), &p.terms[t]);
      }
      if (started) {
        // The change carries the fitted start, and the cross-validation evaluates exactly that
        // change: each fold's fit starts there instead of searching again. (A search per fold can
        // land a dipole inside the volume, where the inverse has no meaning; the start uses the
        // held-out stations only to pick the basin, the fold's fit finds its own optimum.)
        // A source grown from near zero is grown again in each fold (from its fitted start it
        // fell into the worse optimum).
        c.model_change = TermListItems(p.terms);
        for (size_t t = 0; t < p.terms.size(); ++t) {
          YAML::Node term = p.root["terms"][static_cast<size_t>(*c.insert_index) + t];
          AddFittedStart(p.terms[t]["type"].as<std::string>(),
                         BlocksOfTerm(c.parameters, c.term_names[t]), &term);
          if (grown_kept) ScaleSourceStrength(kGrowFromFraction, &term);
        }
        c.model_text = Emit(p.root);
      }
    } catch (const std::exception& ex) {
      c.error = ex.what();
    }
    c.seconds = SecondsSince(t0);
  };

  // Which candidates are cross-validated: all, or the best by BIC (cross_validate_top).
  // The base's cross-validation and the candidates' fits are independent tasks.
  {
    std::vector<PreparedCandidate*> to_fit;
    for (auto& p : prepared) {
      if (!p.flexible) to_fit.push_back(&p);
    }
    // Longest first, so the workers finish together: terms that search their start (dipole, plane)
    // cost several times the others.
    auto searched = [](const PreparedCandidate* p) {
      if (p->candidate.kind != CandidateKind::kTerm) return false;
      const std::string type = p->terms.front()["type"].as<std::string>();
      return type == "dipole" || type == "plane";
    };
    std::stable_partition(to_fit.begin(), to_fit.end(), searched);
    ParallelFor(to_fit.size() + 1, threads, [&](size_t i) {
      if (i == 0) {
        validate_base();
      } else {
        fit_candidate(*to_fit[i - 1]);
      }
    });
    base_table();
  }
  // Bonferroni over every candidate tested (fitted), screened-out ones included: screening looked
  // at them too. Replacements count as additions do: they are tested on the same held-out data,
  // and the family is every candidate the diagnosis looked at, not only those whose claim rule
  // reads the p-value. A nested fit that ended above the base's chi2 counts too: its fit ran and
  // was looked at (candidates_sim_test AHeldPlaneStays...: a dipole and a dipole pair whose runtime
  // inverse found other roots; leaving them out moved the threshold from 0.00111 to 0.00143).
  int tested = 0;
  for (const auto& p : prepared) {
    tested += (p.candidate.fitted || p.candidate.ended_above_base) && !p.flexible ? 1 : 0;
  }
  d.p_threshold = options.family_alpha / std::max(1, tested);
  // What the paired test can show at best: a short stream (few blocks of time) or few stations
  // cannot reach the threshold, and then "nothing significant" says nothing about the data.
  {
    const bool blocks = d.paired_test_blocks > 0;
    const int n = blocks ? d.paired_test_blocks : d.num_stations;
    d.paired_test_smallest_p = WilcoxonSmallestP(n);
    if (tested > 0 && !(d.paired_test_smallest_p < d.p_threshold)) {
      int needed = n;
      while (needed < 100000 && !(WilcoxonSmallestP(needed) < d.p_threshold)) ++needed;
      std::ostringstream v;
      v << "The paired test has " << n
        << (blocks ? " blocks of time (at least " + FormatNumber(kSerialBlockMinSeconds, 1) +
                         " s and " + std::to_string(kSerialBlockMinSamples) +
                         " samples each) on this stream"
                   : std::string(" stations"))
        << ": its smallest p (every one favouring a candidate) is "
        << FormatSignificant(d.paired_test_smallest_p, 2) << ", not below the threshold "
        << FormatSignificant(d.p_threshold, 2) << " for " << tested
        << (tested == 1 ? " candidate" : " candidates") << ", so no "
        << "candidate can be claimed on these data (robust_loss aside: its outliers have their own "
           "test), whatever they show. ";
      if (blocks && needed <= options.serial_blocks) {
        v << "Record a longer stream (" << needed << " blocks: at least "
          << FormatNumber(needed * kSerialBlockMinSeconds, 1) << " s and "
          << needed * kSerialBlockMinSamples << " samples)";
      } else if (!blocks) {
        v << "Capture more stations (at least " << needed << ")";
      } else {
        v << "More blocks would not be enough";
      }
      v << " or test fewer effects (--effects).";
      d.test_power_note = v.str();
    }
  }

  // Gross outliers are the stations a robust fit rejects (FindGrossOutliers on its residuals): the
  // robust_loss candidate's (its outliers and p; its BIC is the mean-shift model, in which each
  // outlier has its own 6-parameter pose shift and leaves the chi2, against the base's least
  // squares) and, when the model already has a loss, the base's, which stay out of every held-out
  // comparison: a flip held out is off by 1-2 m under every model, and that error changes by chance
  // from model to model (measured: a plane "lowered" the held-out mean 48 % at p = 0.11 by moving
  // the extrapolation at two flips).
  // Over the stations not `left` out (empty: all; unresolved_left_out below).
  auto mean_shift_bic = [&](const std::vector<double>& whitened_sq, const GrossOutliers& o, int k,
                            const std::vector<bool>& left) {
    std::vector<bool> out(whitened_sq.size(), false);
    for (size_t i : o.index) out[i] = true;
    double chi2 = 0.0;
    int n = 0;
    for (size_t i = 0; i < whitened_sq.size(); ++i) {
      if (i < left.size() && left[i]) continue;
      n += 6;
      chi2 += out[i] ? 0.0 : whitened_sq[i];
    }
    return Bic(chi2, n, k + 6 * static_cast<int>(o.index.size()));
  };
  auto claimable_outliers = [&](const GrossOutliers& o, double delta_bic) {
    return !o.index.empty() &&
           static_cast<double>(o.index.size()) <=
               options.max_outlier_fraction * static_cast<double>(stations.size()) &&
           delta_bic < options.max_delta_bic && o.p_value < d.p_threshold;
  };
  std::vector<Eigen::Vector3d> positions;  // the reference's, for the outliers' neighbourhoods
  for (const auto& s : stations) positions.push_back(s.reference.translation);
  // Stations a runtime inverse does not resolve (no root or an ambiguous one, next to a strong
  // object) are not outliers: their error is report noise the inverse amplified, or its best
  // guess, not a bad pose. When they are few (max_unresolved_fraction, as for the other
  // candidates' BIC) they are not tested, stay neighbours of the tested ones (FindGrossOutliers),
  // and are left out of the mean-shift BIC's sums. Measured, full paper capture with the toolbox,
  // under the TRUE model (fit/candidates_sim_test, StationsTheInverseCannotResolveAreNotOutliers):
  // stations 131 and 350, 0.28-0.33 m from the toolbox and ambiguous, 16 mm off at 350 where the
  // others are 0.1-0.2 mm, were "2 outlier stations (hemisphere flips or bad reference poses)" and
  // the robust loss was claimed on seeds 2 and 3 (held-out error of the kept stations -28 %); the
  // demo's loop (seed 2) claimed it at its last step for station 350.
  auto unresolved_left_out = [&](const std::vector<bool>& unresolved) {
    const auto count = std::count(unresolved.begin(), unresolved.end(), true);
    const bool few = static_cast<double>(count) <=
                     options.max_unresolved_fraction * static_cast<double>(stations.size());
    return count > 0 && few ? unresolved : std::vector<bool>();
  };
  auto gross_outliers = [&](const std::vector<double>& whitened_sq,
                            const std::vector<bool>& left) {
    return FindGrossOutliers(whitened_sq, positions, options.outlier_neighbours, d.p_threshold,
                             left);
  };
  // "N stations (ids) ... near (x, y, z) m": where the robust fit's large errors are a local
  // effect.
  auto local_structure_words = [&](const GrossOutliers& g) {
    Eigen::Vector3d mean = Eigen::Vector3d::Zero();
    std::vector<int> ids;
    for (size_t i : g.local_structure) {
      mean += positions[i];
      ids.push_back(stations[i].station);
    }
    mean /= static_cast<double>(std::max<size_t>(1, g.local_structure.size()));
    std::sort(ids.begin(), ids.end());
    std::string list;
    for (size_t i = 0; i < ids.size() && i < 10; ++i) {
      list += (i ? ", " : "") + std::to_string(ids[i]);
    }
    if (ids.size() > 10) list += ", ...";
    return std::to_string(ids.size()) + " station" + (ids.size() == 1 ? "" : "s") +
           " far beyond the others' errors (" + list +
           ") lie among stations with errors as large, around (" + FormatNumber(mean.x(), 2) +
           ", " + FormatNumber(mean.y(), 2) + ", " + FormatNumber(mean.z(), 2) +
           ") m (transmitter frame): an effect the model lacks there, not outliers";
  };
  std::vector<bool> base_outlier(stations.size(), false);
  if (base_spec.loss.type != LossType::kNone) {
    const std::vector<bool> left = unresolved_left_out(base_full.unresolved);
    const GrossOutliers o = gross_outliers(base_full.whitened_sq, left);
    const double delta = mean_shift_bic(base_full.whitened_sq, o, base_k, left) -
                         mean_shift_bic(base_full.whitened_sq, GrossOutliers(), base_k, left);
    if (claimable_outliers(o, delta)) {
      for (size_t i : o.index) base_outlier[i] = true;
    }
  }
  for (auto& p : prepared) {
    Candidate& c = p.candidate;
    if (p.flexible || !c.fitted || c.kind != CandidateKind::kRobustLoss) continue;
    const std::vector<bool> left = unresolved_left_out(p.full_unresolved);
    c.bic_unresolved_left_out =
        static_cast<int>(std::count(left.begin(), left.end(), true));
    p.gross = gross_outliers(p.full_whitened_sq, left);
    c.outlier_stations.clear();
    for (size_t i : p.gross.index) c.outlier_stations.push_back(stations[i].station);
    std::sort(c.outlier_stations.begin(), c.outlier_stations.end());
    c.local_structure_stations.clear();
    for (size_t i : p.gross.local_structure) {
      c.local_structure_stations.push_back(stations[i].station);
    }
    std::sort(c.local_structure_stations.begin(), c.local_structure_stations.end());
    c.delta_bic = mean_shift_bic(p.full_whitened_sq, p.gross, c.num_free_parameters, left) -
                  mean_shift_bic(base_full.whitened_sq, GrossOutliers(), base_k, left);
    c.statement = Statement(*p.effect, c, options.robust_loss.scale);
    if (!p.gross.local_structure.empty()) {
      c.local_structure_note = local_structure_words(p.gross);
      c.statement += (c.outlier_stations.empty() ? "; but " : "; besides, ") +
                     c.local_structure_note;
    }
  }
  auto can_be_claimed = [&](const PreparedCandidate* p) {
    return p->candidate.kind == CandidateKind::kRobustLoss
               ? claimable_outliers(p->gross, p->candidate.delta_bic)
               : p->candidate.evidence.supported();
  };

  std::vector<PreparedCandidate*> to_validate, replacements;
  for (auto& p : prepared) {
    if (!p.candidate.fitted || p.flexible) continue;
    (p.candidate.replaces.empty() ? to_validate : replacements).push_back(&p);
  }
  if (options.cross_validate_top > 0 &&
      static_cast<int>(to_validate.size()) > options.cross_validate_top) {
    // Candidates that cannot be claimed whatever their cross-validation shows (the physical
    // conditions, decided on the full fit; a robust loss whose fit rejects no gross outlier) do not
    // take a cross-validation slot from one that can.
    auto before = [&](const PreparedCandidate* a, const PreparedCandidate* b) {
      const bool sa = can_be_claimed(a);
      const bool sb = can_be_claimed(b);
      if (sa != sb) return sa;
      return a->candidate.delta_bic < b->candidate.delta_bic;
    };
    std::stable_sort(to_validate.begin(), to_validate.end(), before);
    // A term pair takes no slot of its own: its extra parameters buy it a lower BIC than its
    // single term's almost always, so it would push a candidate of another type out of the
    // cross-validation. It is cross-validated beside the N single candidates when it ranks
    // among them.
    auto multi = [](const PreparedCandidate* p) { return p->effect->count > 1; };
    std::vector<PreparedCandidate*> singles, kept;
    for (PreparedCandidate* p : to_validate) {
      if (!multi(p)) singles.push_back(p);
    }
    if (static_cast<int>(singles.size()) > options.cross_validate_top) {
      singles.resize(static_cast<size_t>(options.cross_validate_top));
    }
    for (PreparedCandidate* p : to_validate) {
      if (!multi(p)) {
        if (std::find(singles.begin(), singles.end(), p) != singles.end()) kept.push_back(p);
      } else if (static_cast<int>(singles.size()) < options.cross_validate_top ||
                 before(p, singles.back())) {
        kept.push_back(p);
      }
    }
    to_validate = std::move(kept);
  }
  // A replacement takes no slot: it is cross-validated when it could be claimed (BIC prefers it
  // decisively and its term identifies a source), whatever the additions' BIC.
  for (PreparedCandidate* p : replacements) {
    if (p->candidate.delta_bic < options.max_delta_bic && can_be_claimed(p)) {
      to_validate.push_back(p);
    }
  }

  auto validate_candidate = [&](PreparedCandidate* p) {
    Candidate& c = p->candidate;
    const auto t0 = Clock::now();
    try {
      const std::vector<FitStation>& own = p->stations.empty() ? stations : p->stations;
      // The base's folds (by the base station, or for a re-paired sample no base station has, by
      // its time for serial stations).
      std::vector<int> fold_of(own.size());
      for (size_t j = 0; j < own.size(); ++j) {
        const int b = p->base_index[j];
        if (!serial_block.empty()) {
          fold_of[j] = b >= 0 ? base_folds[static_cast<size_t>(b)]
                              : fold_of_block(block_at_time(own[j].time));
        } else {
          fold_of[j] = (b >= 0 ? b : static_cast<int>(j)) % options.folds;
        }
      }
      StationErrors cv;
      bool fast_done = false;
      if (p->fitted) {
        Progress(options, c.effect + ": " + std::to_string(options.folds) +
                              " fold refits from the full fit");
        std::optional<StationErrors> fast = FastCrossValidateStations(
            own, fold_of, p->fitted.get(), p->left_out, p->report_form, options.folds, noise,
            [&](const std::string& m) { Progress(options, c.effect + ": " + m); });
        if (fast) cv = std::move(*fast);
        fast_done = fast.has_value();
      }
      if (!fast_done) {
        cv =
            CrossValidateStations(own, fold_of, c.model_text, model_source + " + " + c.effect,
                                  options.folds, noise, [&](int f) {
                                    Progress(options, c.effect + ": fold " + std::to_string(f + 1) +
                                                          "/" + std::to_string(options.folds));
                                  });
      }
      c.cross_validated = true;
      Progress(options, c.effect + ": cross-validated in " +
                            FormatNumber(SecondsSince(t0), 1) + " s");
      // Stations left out of the comparison: the gross outliers the model's loss rejects, and a
      // robust loss's own outliers (its held-out error is that of the stations it keeps; the base's
      // is that of all of them).
      const bool robust = c.kind == CandidateKind::kRobustLoss;
      std::vector<bool> own_outlier(stations.size(), false);
      if (robust) {
        for (size_t i : p->gross.index) own_outlier[i] = true;
      }
      // Stations whose held-out report the base's runtime inverse does not resolve (no root or an
      // ambiguous one, as for the BIC above), when they are few. The base's alone: every
      // candidate is then compared on the same stations, and one whose own inverse folds at a
      // station (where its field is strongest, often where it errs most) keeps that error.
      // Measured, full paper capture (480 stations on 4 heights), ferromagnetic_object seed 2
      // after the workbench frame and the toolbox: 26 stations within ~0.35 m of the toolbox are
      // ambiguous or unresolved, their errors 5-22 mm (13.5 mm at one of them under the true
      // model) and 175 mm under one candidate. With them the background, floor and sensor-offset
      // candidates scored delta BIC +485, +1031 and +2179 and no held-out gain, and the loop
      // stopped at 12.5x the noise floor; without them the background lowers the held-out error
      // (fit/candidates_sim_test) and is claimed. A robust loss leaves them out too: they are not
      // its outliers (gross_outliers above), and its held-out drop is over the same stations.
      std::vector<bool> cv_left_out(stations.size(), false);
      {
        int count = 0;
        for (size_t j = 0; j < own.size(); ++j) {
          const int b = p->base_index[j];
          if (b < 0 || base_outlier[static_cast<size_t>(b)]) continue;
          if (base_cv.unresolved[static_cast<size_t>(b)]) {
            cv_left_out[static_cast<size_t>(b)] = true;
            ++count;
          }
        }
        if (static_cast<double>(count) <=
            options.max_unresolved_fraction * static_cast<double>(own.size())) {
          c.cv_unresolved_left_out = count;
        } else {
          std::fill(cv_left_out.begin(), cv_left_out.end(), false);
        }
      }
      p->cv_whitened_by_base.assign(stations.size(), NAN);
      for (size_t j = 0; j < own.size(); ++j) {
        const int b = p->base_index[j];
        if (b >= 0 && !base_outlier[static_cast<size_t>(b)] &&
            !cv_left_out[static_cast<size_t>(b)]) {
          p->cv_whitened_by_base[static_cast<size_t>(b)] = cv.whitened_sq[j];
        }
      }
      // Means and the paired test over the stations both models have.
      std::vector<double> cand_p, cand_o, cand_w, base_p, base_o, diff;
      std::vector<int> diff_block;  // serial stations: the block of each difference
      for (size_t j = 0; j < own.size(); ++j) {
        const int b = p->base_index[j];
        if (b < 0) continue;
        const size_t bi = static_cast<size_t>(b);
        if (base_outlier[bi] || cv_left_out[bi]) continue;
        base_p.push_back(base_cv.position_mm[bi]);
        base_o.push_back(base_cv.orientation_deg[bi]);
        if (own_outlier[bi]) continue;
        cand_p.push_back(cv.position_mm[j]);
        cand_o.push_back(cv.orientation_deg[j]);
        cand_w.push_back(cv.whitened_sq[j]);
        diff.push_back(base_cv.whitened_sq[bi] - cv.whitened_sq[j]);
        if (!serial_block.empty()) diff_block.push_back(serial_block[bi]);
      }
      c.cv_position_mm_mean = Mean(cand_p);
      c.cv_orientation_deg_mean = Mean(cand_o);
      c.cv_whitened_mean = Mean(cand_w);
      c.cv_base_position_mm_mean = Mean(base_p);
      c.cv_base_orientation_deg_mean = Mean(base_o);
      c.drop_position_percent =
          ImprovementPercent(c.cv_base_position_mm_mean, c.cv_position_mm_mean);
      c.drop_orientation_percent =
          ImprovementPercent(c.cv_base_orientation_deg_mean, c.cv_orientation_deg_mean);
      // A robust loss: the outlier test of its stations (the paired test of the kept stations
      // would ask whether the loss also improves them, which it need not: its claim is that the
      // others are not pose errors the model can explain).
      c.p_value = robust ? p->gross.p_value : PairedDifferencesGreaterP(diff, diff_block);
    } catch (const std::exception& ex) {
      c.error = std::string("cross-validation failed: ") + ex.what();
    }
    c.seconds += SecondsSince(t0);
  };

  // Significance and the reason in words.
  auto judge = [&](PreparedCandidate& p) {
    Candidate& c = p.candidate;
    if (!c.fitted) {
      c.reason = "fit failed: " + c.error;
      return;
    }
    if (!c.cross_validated) {
      c.reason = c.error.empty() ? "screened out by BIC (delta " + FormatNumber(c.delta_bic, 1) +
                                       "); not cross-validated"
                                 : c.error;
      if (c.error.empty() && !c.evidence.supported()) {
        c.reason = "not cross-validated: the physical conditions reject it (" +
                   c.evidence.Describe() + "); delta BIC " + FormatNumber(c.delta_bic, 1);
      }
      if (c.error.empty() && c.kind == CandidateKind::kRobustLoss && !can_be_claimed(&p)) {
        c.reason =
            "not cross-validated: " +
            (c.outlier_stations.empty()
                 ? std::string("its fit rejects no station as a gross outlier") +
                       (p.gross.local_structure.empty()
                            ? ""
                            : "; " + local_structure_words(p.gross))
                 : "its " + std::to_string(c.outlier_stations.size()) +
                       " outliers are not gross (p = " + FormatSignificant(p.gross.p_value, 2) +
                       ", delta BIC " + FormatNumber(c.delta_bic, 1) + ", " +
                       FormatNumber(100.0 * static_cast<double>(c.outlier_stations.size()) /
                                        static_cast<double>(stations.size()),
                                    0) +
                       " % of the stations)");
      }
      return;
    }
    const bool robust = c.kind == CandidateKind::kRobustLoss;
    const double drop = std::fmax(c.drop_position_percent, c.drop_orientation_percent);
    const double outlier_fraction =
        static_cast<double>(c.outlier_stations.size()) / static_cast<double>(stations.size());
    const bool outliers_ok = !robust || (!c.outlier_stations.empty() &&
                                         outlier_fraction <= options.max_outlier_fraction);
    // A replacement adds no source, so its claim is a choice between two explanations of one
    // structure: BIC decisively for it, and neither held-out mean error higher (no minimum drop
    // and no p-value: the two models have much the same errors by construction; measured,
    // sensor_offset seed 4, the floor as a plane in place of a dipole at its mirror image: delta
    // BIC -28.9, held-out errors 0.1 % and 0.3 % lower, Wilcoxon p = 0.055). "Higher" beyond
    // kReplacementTiePercent, the held-out means' own precision (the fast and exact fold refits
    // agree to 0.2 %, docs/diagnose.md): the same case since the report-space station residual
    // (session 20) is delta BIC -27.1, position 0.2 % lower, orientation 0.1 % higher.
    // A removal is judged the same way: the smaller model is claimed when BIC prefers it
    // decisively (the parameters it saves are worth more than the chi2 it gives up) and neither
    // held-out mean rises; the term's own tests have already failed (unsupported_terms).
    const bool replacing = !c.replaces.empty();
    const bool p_ok = replacing || c.p_value < d.p_threshold;
    const bool drop_ok = replacing ? c.drop_position_percent >= -kReplacementTiePercent &&
                                         c.drop_orientation_percent >= -kReplacementTiePercent
                                   : drop >= options.min_drop_percent;
    const bool bic_ok = c.delta_bic < options.max_delta_bic;
    const PhysicalEvidence& ev = c.evidence;
    // A physical term's claim rests on its standard deviations (the strength and location tests),
    // which mean something only at an optimum: a fit that stopped at the iteration limit is not
    // claimed (measured, ferromagnetic_object seed 1: an unconverged plane 0.37 m from the
    // transmitter, 0.09 m from the workbench frame, passed them at 13.6 sigma and was spurious).
    const bool converged_ok = c.converged || !ev.assessed;
    // A fit that did not converge stopped at the iteration limit (a failed one is not fitted).
    const std::string stopped = "stopped at solver.max_iterations (" +
                                std::to_string(base_spec.max_iterations) + ") before converging";
    const std::string raise = "raise solver.max_iterations in " +
                              (d.model == "<string>" ? std::string("the model") : d.model) +
                              " to let it finish";
    c.significant = p_ok && drop_ok && bic_ok && outliers_ok && ev.supported() && converged_ok;
    std::ostringstream r;
    const bool removal = c.kind == CandidateKind::kRemoval;
    if (replacing) r << (removal ? "without " : "in place of ") << c.replaces << ": ";
    r << (robust ? "held-out error of the stations it keeps " : "held-out error ")
      << (c.drop_position_percent >= 0 ? "falls " : "rises ")
      << FormatNumber(std::abs(c.drop_position_percent), 1) << " % (position), "
      << (c.drop_orientation_percent >= 0 ? "falls " : "rises ")
      << FormatNumber(std::abs(c.drop_orientation_percent), 1) << " % (orientation)";
    if (c.cv_unresolved_left_out > 0) r << UnresolvedNote(c.cv_unresolved_left_out);
    r << "; " << (robust ? "outlier test p = " : "p = ") << FormatSignificant(c.p_value, 2);
    if (!replacing) r << (p_ok ? " < " : " >= ") << FormatSignificant(d.p_threshold, 2);
    r << "; delta BIC "
      << (robust ? "(mean-shift outliers) " : "") << FormatNumber(c.delta_bic, 1);
    if (c.bic_unresolved_left_out > 0) r << UnresolvedNote(c.bic_unresolved_left_out);
    if (ev.assessed) r << "; " << ev.Describe();
    if (!c.significant) {
      std::vector<std::string> why;
      if (!p_ok) {
        why.push_back(robust ? "the model's own held-out noise explains its outliers"
                             : "the held-out improvement is not significant");
      }
      if (!drop_ok) {
        why.push_back(replacing ? "a held-out mean error is higher than with " + c.replaces
                                : "the held-out drop is below " +
                                      FormatNumber(options.min_drop_percent, 0) + " %");
      }
      if (!bic_ok)
        why.push_back("BIC does not support it (needs < " + FormatNumber(options.max_delta_bic, 0) +
                      ")");
      if (!ev.strength_ok) {
        why.push_back(std::isfinite(ev.strength_sigma)
                          ? "its strength (" + ev.strength_what + ") is " +
                                FormatNumber(ev.strength_sigma, 1) +
                                " sigma from its null value (needs " +
                                FormatNumber(options.min_strength_sigma, 0) + ")"
                          : "its strength cannot be tested (" + ev.strength_what + ")");
      }
      if (!ev.normal_ok) {
        why.push_back("its normal is not determined (+- " +
                      FormatNumber(ev.normal_sigma_rad * kDegPerRad, 1) + " deg, more than " +
                      FormatNumber(options.max_normal_sigma_rad * kDegPerRad, 1) +
                      "): no particular plane");
      }
      const bool placed =
          ev.location_distance_m > 0 && ev.location_sigma_m <= ev.location_distance_m;
      if (!ev.location_ok && !placed) {
        why.push_back(
            ev.location_distance_m > 0
                ? "its location is not determined (+- " + FormatNumber(ev.location_sigma_m, 2) +
                      " m, more than its " + FormatNumber(ev.location_distance_m, 2) +
                      " m from the measured volume): not that object"
                : "it lies in the measured volume, where no source can be: not that object");
      }
      if (robust && !p.gross.local_structure.empty()) {
        why.push_back(local_structure_words(p.gross));
      }
      if (robust && c.outlier_stations.empty()) {
        why.push_back("its fit rejects no station as a gross outlier");
      } else if (!outliers_ok) {
        why.push_back(
            FormatNumber(100 * outlier_fraction, 0) +
            " % of the stations exceed the loss scale: that is structure the model lacks, "
            "not outliers");
      }
      if (!converged_ok) {
        why.push_back("its fit (the model with it, on every station) " + stopped +
                      ", so its standard deviations are not at an optimum (" + raise + ")");
      }
      r << ". Not claimed: ";
      for (size_t i = 0; i < why.size(); ++i) r << (i ? ", " : "") << why[i];
    }
    if (!c.converged && converged_ok) {
      r << " (its fit, the model with it on every station, " << stopped
        << ": its numbers are the best the solver found, not the optimum; " << raise << ")";
    }
    c.reason = r.str();
  };

  ParallelFor(to_validate.size(), threads, [&](size_t i) { validate_candidate(to_validate[i]); });
  for (auto& p : prepared) {
    if (!p.flexible) judge(p);
  }
  // A term that explains less of the structure than another whose fit does not identify its
  // source is standing in for that source: not claimed. The other passes every statistical test
  // (held-out p and drop, BIC) and fails only the physical conditions, and its held-out errors are
  // smaller station by station (paired test at family_alpha). Pairs are not the other (a pair
  // holds the single and one more source). Measured, full paper capture, ferromagnetic_object
  // seed 3, after the frame, the background and the toolbox: the floor plane lowered the held-out
  // error 21.6 % but its attenuation stayed 0.5 sigma from zero (the background holds most of the
  // floor's field); near_field, which the scene does not have, lowered it 7.2 % with its octupole
  // 3.5 sigma from zero and was claimed.
  std::set<const PreparedCandidate*> stood_in;  // still hold back pairs and replacements (below)
  // A catch-all (the background) is not held back: standing for sources it does not place is what
  // it claims (measured, full paper capture, seed 2 after the frame and the toolbox: a floor plane
  // whose normal stayed 8.1 deg open explained more, and holding the background back left nothing
  // to claim).
  for (auto& p : prepared) {
    Candidate& c = p.candidate;
    if (p.flexible || !c.significant || c.kind != CandidateKind::kTerm || !c.replaces.empty() ||
        p.effect->yields_to_located) {
      continue;
    }
    std::vector<const PreparedCandidate*> unidentified;
    std::vector<std::vector<double>> their_errors;
    for (const auto& o : prepared) {
      const Candidate& oc = o.candidate;
      // (Not a catch-all either: the background stands for sources it does not place.)
      if (&o == &p || o.flexible || o.effect->count > 1 || o.effect->yields_to_located ||
          oc.kind != CandidateKind::kTerm || !oc.replaces.empty() || !oc.cross_validated ||
          !oc.converged || oc.evidence.supported() || !(oc.p_value < d.p_threshold) ||
          !(std::fmax(oc.drop_position_percent, oc.drop_orientation_percent) >=
            options.min_drop_percent) ||
          !(oc.delta_bic < options.max_delta_bic)) {
        continue;
      }
      unidentified.push_back(&o);
      their_errors.push_back(o.cv_whitened_by_base);
    }
    const std::optional<StandIn> stand_in =
        FindStandIn(p.cv_whitened_by_base, their_errors, options.family_alpha, serial_block);
    if (!stand_in) continue;
    const Candidate& oc = unidentified[stand_in->other]->candidate;
    c.significant = false;
    stood_in.insert(&p);
    const bool by_position = oc.drop_position_percent >= oc.drop_orientation_percent;
    c.reason += ". Not claimed: a " + oc.effect +
                " term explains more of the structure (held-out " +
                (by_position ? "position" : "orientation") + " error falls " +
                FormatNumber(
                    by_position ? oc.drop_position_percent : oc.drop_orientation_percent, 1) +
                " %, p = " + FormatSignificant(stand_in->p_value, 2) +
                " that this term's errors are larger) but does not identify its source, so this " +
                "term may stand in for that source";
  }
  // Terms go in one at a time where one at a time works: a pair of terms is claimed only when no
  // single candidate is. Otherwise the single goes in first and the next diagnosis searches the
  // second with it in the model. A pair that merely beats the single adds a second source the
  // single did not need to identify (measured, finite_transmitter_coils seed 1, when the pair only
  // had to beat every significant single on held-out data and BIC: the workbench frame plus a
  // dipole at the floor's mirror image of the transmitter, claimed over the frame alone, spurious);
  // the pair is for sources that no single term identifies (two monitors side by side).
  for (auto& p : prepared) {
    Candidate& c = p.candidate;
    if (p.flexible || p.effect->count <= 1 || !c.significant) continue;
    for (const auto& o : prepared) {
      if (&o == &p || o.flexible || o.effect->count > 1 ||
          (!o.candidate.significant && !stood_in.count(&o)) || !o.candidate.replaces.empty()) {
        continue;  // a replacement waits for additions, pairs included (below)
      }
      c.significant = false;
      c.reason += ". Not claimed: a single candidate is (" + o.candidate.effect +
                  "): terms go in one at a time, the pair only where no single one is claimed";
      break;
    }
  }
  // A replacement waits while an effect is missing: the addition goes in first, and the next
  // diagnosis weighs the swap with it in the model (what the model lacked may be what made the
  // first choice; measured, sensor_offset seed 4: a dipole at the floor's mirror image of the
  // transmitter went in before the background field, 12 BIC points ahead of the plane; with the
  // background in the model the plane is 28.9 points ahead).
  std::string first_addition;
  for (const auto& p : prepared) {
    if (!p.flexible && (p.candidate.significant || stood_in.count(&p)) &&
        p.candidate.replaces.empty()) {
      first_addition = p.candidate.effect;
      break;
    }
  }
  for (auto& p : prepared) {
    Candidate& c = p.candidate;
    if (p.flexible || c.replaces.empty() || !c.significant || first_addition.empty()) continue;
    c.significant = false;
    c.reason += ". Not claimed now: an effect the model lacks goes in first (" + first_addition +
                "); the " + (c.kind == CandidateKind::kRemoval ? "removal" : "swap") +
                " is weighed again with it";
  }
  // A term the data no longer identify is removed before another takes its place: the smaller
  // model first, and the next diagnosis asks whether anything is missing without it.
  for (auto& p : prepared) {
    Candidate& c = p.candidate;
    if (p.flexible || c.kind != CandidateKind::kTerm || c.replaces.empty() || !c.significant) {
      continue;
    }
    for (const auto& o : prepared) {
      if (o.candidate.kind == CandidateKind::kRemoval && o.candidate.significant &&
          o.candidate.replaces == c.replaces) {
        c.significant = false;
        c.reason += ". Not claimed now: " + c.replaces +
                    " is removed first (the model without it fits as well); the swap is weighed "
                    "again without it";
        break;
      }
    }
  }
  bool any_significant = false;
  for (const auto& p : prepared) {
    any_significant = any_significant || (!p.flexible && p.candidate.significant);
  }
  // The flexible fallback only matters when no effect is claimed (it is the costliest fit).
  for (auto& p : prepared) {
    if (!p.flexible) continue;
    if (any_significant) {
      p.candidate.reason = "not fitted: a catalog effect is significant";
      continue;
    }
    fit_candidate(p);
    if (p.candidate.fitted) validate_candidate(&p);
    judge(p);
  }

  // Ranking: significant first, then by held-out error, except where RankFirst's tie rule puts
  // another significant candidate first (the reasons and measurements are at RankFirst).
  // The candidate moved to the top by the tie rule: (effect, term it replaces); effect empty: none.
  std::pair<std::string, std::string> promoted;
  {
    std::vector<PreparedCandidate*> sig;
    for (auto& p : prepared) {
      if (!p.flexible && p.candidate.significant) sig.push_back(&p);
    }
    std::stable_sort(sig.begin(), sig.end(),
                     [](const PreparedCandidate* a, const PreparedCandidate* b) {
                       return a->candidate.cv_whitened_mean < b->candidate.cv_whitened_mean;
                     });
    std::vector<RankEntry> entries;
    for (const PreparedCandidate* p : sig) {
      RankEntry e;
      e.effect = p->candidate.effect;
      e.cv_whitened_mean = p->candidate.cv_whitened_mean;
      e.cv_whitened_by_station = p->cv_whitened_by_base;
      e.delta_bic = p->candidate.delta_bic;
      e.has_location = p->candidate.evidence.has_location;
      e.strength_sigma = p->candidate.evidence.strength_sigma;
      e.yields_to_located = p->effect->yields_to_located;
      entries.push_back(std::move(e));
    }
    const RankPick pick =
        RankFirst(entries, options.family_alpha, options.max_delta_bic, serial_block);
    if (pick.index != 0) {
      sig[pick.index]->candidate.reason += "; " + pick.note;
      // Catalog names are unique (Check); replacements also name the term they replace.
      promoted = {sig[pick.index]->candidate.effect, sig[pick.index]->candidate.replaces};
    }
  }
  std::vector<Candidate> ranked;
  for (auto& p : prepared) {
    (p.flexible ? d.flexible : ranked).push_back(std::move(p.candidate));
  }
  auto key = [&promoted](const Candidate& c) {
    return std::make_tuple(
        c.significant ? 0 : 1,
        std::make_pair(c.effect, c.replaces) == promoted ? 0 : 1,
        // Tested on held-out data before untested: a candidate screened out or refused (a robust
        // loss that rejects no station) says nothing about held-out error, and listed first it
        // read as the best of those not claimed.
        c.cross_validated ? 0 : 1, c.evidence.supported() ? 0 : 1, c.fitted ? 0 : 1,
        std::isfinite(c.cv_whitened_mean) ? c.cv_whitened_mean
                                          : std::numeric_limits<double>::infinity(),
        std::isfinite(c.delta_bic) ? c.delta_bic : std::numeric_limits<double>::infinity());
  };
  std::stable_sort(ranked.begin(), ranked.end(),
                   [&](const Candidate& a, const Candidate& b) { return key(a) < key(b); });
  d.candidates = std::move(ranked);

  // Verdict.
  auto description = [&](const std::string& effect) {
    for (const auto& e : options.catalog) {
      if (e.effect == effect) return e.description;
    }
    return effect;
  };
  if (!d.candidates.empty() && d.candidates.front().significant) {
    const Candidate& top = d.candidates.front();
    d.verdict_effect = top.effect;
    std::ostringstream v;
    std::string desc = description(top.effect);
    if (!desc.empty())
      desc[0] = static_cast<char>(std::toupper(static_cast<unsigned char>(desc[0])));
    if (top.kind == CandidateKind::kRemoval) {
      v << "Remove " << top.replaces << " (`terms:` item " << top.insert_index.value_or(-1)
        << "): these data no longer identify it, and the model without it fits as well";
    } else {
      v << desc << " (" << top.effect << ")";
      if (!top.replaces.empty()) {
        v << " in place of " << top.replaces << " explains its structure better";
      }
    }
    v << (top.replaces.empty() ? " explains the remaining structure" : "")
      << ": held-out position error "
      << FormatNumber(std::isfinite(top.cv_base_position_mm_mean) ? top.cv_base_position_mm_mean
                                                                  : d.base.cv_position_mm_mean,
                      3)
      << " -> " << FormatNumber(top.cv_position_mm_mean, 3) << " mm ("
      << FormatNumber(top.drop_position_percent, 1) << " %), orientation "
      << FormatNumber(std::isfinite(top.cv_base_orientation_deg_mean)
                          ? top.cv_base_orientation_deg_mean
                          : d.base.cv_orientation_deg_mean,
                      3)
      << " -> " << FormatNumber(top.cv_orientation_deg_mean, 3) << " deg";
    if (top.cv_unresolved_left_out > 0) v << UnresolvedNote(top.cv_unresolved_left_out);
    v << ", p = " << FormatSignificant(top.p_value, 2) << ", delta BIC "
      << FormatNumber(top.delta_bic, 1) << ".";
    if (top.kind == CandidateKind::kRemoval) {
      // What the base fit says of the term (its strength or location test failed).
      for (const auto& u : d.unsupported_terms) {
        if (u.term == top.replaces) v << " In the model now: " << u.evidence.Describe() << ".";
      }
    } else if (!top.statement.empty()) {
      v << " Fitted: " << top.statement << ".";
    }
    int others = 0;
    for (size_t i = 1; i < d.candidates.size(); ++i) others += d.candidates[i].significant ? 1 : 0;
    if (others > 0) {
      v << " " << others << " other candidate" << (others == 1 ? " is" : "s are")
        << " also significant (often the same structure seen by a related effect): "
        << (top.kind == CandidateKind::kRemoval ? "make the removal" : "add the top one")
        << ", then diagnose again.";
    }
    d.verdict_text = v.str();
  } else {
    std::ostringstream v;
    // The claim covers only the candidates tested on held-out data: those screened out by
    // cross_validate_top, refused on the fit to all stations or not fitted were not. A replacement
    // is named with the term it would replace: its effect's addition may have been tested. A
    // removal explains no structure, tested or not: it does not narrow the claim.
    std::vector<std::string> untested;
    size_t tested = 0;
    for (const auto& c : d.candidates) {
      if (c.kind == CandidateKind::kRemoval) continue;
      if (c.cross_validated) {
        ++tested;
        continue;
      }
      const std::string name = c.effect + (c.replaces.empty() ? "" : " in place of " + c.replaces);
      if (std::find(untested.begin(), untested.end(), name) == untested.end()) {
        untested.push_back(name);
      }
    }
    std::string names;
    for (size_t i = 0; i < untested.size(); ++i) names += (i ? ", " : "") + untested[i];
    if (d.candidates.empty()) {
      v << "No catalog effect explains the remaining structure (no candidate could be tested)";
    } else if (untested.empty()) {
      v << "No catalog effect explains the remaining structure";
    } else if (tested == 0) {
      v << "No candidate was tested on held-out data (not tested: " << names << ")";
    } else {
      v << "None of the " << tested << " candidate" << (tested == 1 ? "" : "s")
        << " tested on held-out data explains the remaining structure (not tested there: "
        << names << ")";
    }
    v << ". ";
    // Candidates that explain structure by the statistics but fail the physical conditions: the
    // structure is there, its source is not identified.
    for (const auto& c : d.candidates) {
      // Only the held-out statistics show structure: BIC alone favours a searched source term on
      // effect-free data (see "Significance" in docs/diagnose.md).
      if (!c.cross_validated || c.evidence.supported() || !(c.delta_bic < options.max_delta_bic) ||
          !(c.p_value < d.p_threshold) ||
          std::max(c.drop_position_percent, c.drop_orientation_percent) <
              options.min_drop_percent) {
        continue;
      }
      v << "A " << c.effect << " term fits structure that is there";
      if (!c.evidence.direction.isZero()) {
        // Where the structure comes from, which the user can look for in the room.
        v << " from outside the measured volume, along " << AxisWords(c.evidence.direction)
          << " from its centre";
      }
      // Both drops: the gate is either one (a structure in orientation alone showed as "held-out
      // position error falls -0.4 %").
      v << " (held-out error " << (c.drop_position_percent >= 0 ? "falls " : "rises ")
        << FormatNumber(std::abs(c.drop_position_percent), 1) << " % (position), "
        << (c.drop_orientation_percent >= 0 ? "falls " : "rises ")
        << FormatNumber(std::abs(c.drop_orientation_percent), 1) << " % (orientation), delta BIC "
        << FormatNumber(c.delta_bic, 1) << "), but its fit does not identify the source ("
        << c.evidence.Describe() << "), so it is not claimed: source not identified. ";
      d.unexplained_structure = true;
    }
    // A robust fit's errors far beyond the rest, but among neighbours as bad: where to look. That
    // is structure no candidate explains (the note says "an effect the model lacks there"), so it
    // is unexplained structure: without the flag the binding's verdict said "nothing significant
    // remains" (an object 0.075 m from the grid, 26 mm left on the validation set, the dipole's
    // search lost in the fold's stations).
    for (const auto& c : d.candidates) {
      if (c.kind == CandidateKind::kRobustLoss && c.outlier_stations.empty() &&
          !c.local_structure_note.empty()) {
        v << "The robust loss finds no outliers: " << c.local_structure_note << ". ";
        d.unexplained_structure = true;
      }
    }
    const double chi2_dof = d.base.chi2_per_dof;
    const Candidate* flexible = nullptr;
    for (const auto& f : d.flexible) {
      if (f.significant && (!flexible || f.cv_whitened_mean < flexible->cv_whitened_mean))
        flexible = &f;
    }
    if (flexible) {
      d.unexplained_structure = true;
      v << "The structure that remains is real: a flexible " << flexible->effect
        << " term lowers the held-out error by " << FormatNumber(flexible->drop_position_percent, 1)
        << " % (position) and " << FormatNumber(flexible->drop_orientation_percent, 1)
        << " % (orientation), p = " << FormatSignificant(flexible->p_value, 2)
        << ", but it is not one of the catalog's effects: look at which covariate the residual "
           "follows "
           "(trackcal diagnose), or keep the flexible term.";
    } else if (const Candidate* held_out = FlexibleWithHeldOutGain(d, options)) {
      // Held-out data still prefer the flexible term, but BIC does not support its parameters:
      // structure may remain that no catalog effect explains; say so rather than "nothing".
      d.unexplained_structure = true;
      v << "A flexible " << held_out->effect << " term still lowers the held-out error by "
        << FormatNumber(held_out->drop_position_percent, 1) << " % (position) and "
        << FormatNumber(held_out->drop_orientation_percent, 1)
        << " % (orientation), p = " << FormatSignificant(held_out->p_value, 2)
        << ", but BIC does not support its "
        << held_out->num_free_parameters - d.base.num_free_parameters
        << " extra parameters (delta BIC " << FormatNumber(held_out->delta_bic, 1)
        << "): some structure may remain that no catalog effect explains; look at which covariate "
           "the residual follows (trackcal diagnose).";
    } else if (std::isfinite(chi2_dof) && chi2_dof >= 0.5 && chi2_dof < 2.0) {
      v << "The model fits to within its noise model (chi2/dof " << FormatNumber(chi2_dof, 2)
        << "): nothing is missing that these data can show.";
    } else if (std::isfinite(chi2_dof) && chi2_dof < 0.5) {
      v << "No held-out test finds more structure. (chi2/dof " << FormatNumber(chi2_dof, 2)
        << " is far below 1: the model file's noise is larger than the scatter the fit leaves, so "
           "chi2 cannot tell whether anything is missing; give the tracker's noise in `noise:`.)";
    } else {
      v << "The model leaves "
        << (std::isfinite(chi2_dof) ? "chi2/dof " + FormatNumber(chi2_dof, 2) : "residuals")
        << " against its noise model; if that is more than noise, look at which covariate the "
           "residual "
           "follows (trackcal diagnose) or add a flexible term (a higher polynomial degree, a "
           "lut).";
    }
    d.verdict_text = v.str();
  }
  // The note names the unidentified terms, but not the one the verdict removes.
  std::vector<const Diagnosis::UnsupportedTerm*> unsupported;
  for (const auto& u : d.unsupported_terms) {
    const bool removed = d.verdict_effect && *d.verdict_effect == kRemoveEffect &&
                         d.candidates.front().replaces == u.term;
    if (!removed) unsupported.push_back(&u);
  }
  if (!unsupported.empty()) {
    std::ostringstream v;
    v << " Already in the model but not identified by these data: ";
    for (size_t i = 0; i < unsupported.size(); ++i) {
      const auto& u = *unsupported[i];
      v << (i ? "; " : "") << u.term << " (`terms:` item " << u.index << ", "
        << u.evidence.Describe() << ")";
    }
    const char* them = unsupported.size() == 1 ? "it" : "them";
    // Whether each was tried removed (a removal candidate, claimed or not, says why).
    bool all_tried = true;
    for (const auto* u : unsupported) {
      bool tried = false;
      for (const auto& c : d.candidates) {
        tried = tried || (c.kind == CandidateKind::kRemoval && c.replaces == u->term && c.fitted);
      }
      all_tried = all_tried && tried;
    }
    if (all_tried) {
      v << ". A term added after " << them << " may explain the same structure; the model without "
        << them << " was tried (`remove` in the ranking, with why it is not claimed now).";
    } else {
      v << ". A term added after " << them << " may explain the same structure: fit the model "
        << "without " << them << " and keep the change if the held-out error does not rise "
        << "(trackcal history).";
    }
    d.unsupported_note = v.str().substr(1);
    d.verdict_text += v.str();
  }
  if (!d.test_power_note.empty()) d.verdict_text += " " + d.test_power_note;
  d.seconds = SecondsSince(start);
  return d;
}

namespace {
nlohmann::json CandidateToJson(const Candidate& c) {
  {
    nlohmann::json params = nlohmann::json::array();
    for (const auto& p : c.parameters) {
      nlohmann::json stddev = nlohmann::json::array();
      for (double s : p.stddev) stddev.push_back(NumberOrNull(s));
      params.push_back({{"term", p.term},
                        {"block", p.block},
                        {"unit", p.unit},
                        {"coordinate_names", p.coordinate_names},
                        {"values", p.values},
                        {"stddev", stddev},
                        {"stddev_names", p.stddev_names},  // manifold blocks: tangent coordinates
                        {"stddev_unit", p.stddev_unit},
                        {"fixed", p.fixed}});
    }
    return {
        {"effect", c.effect},
        {"kind", c.kind == CandidateKind::kTerm         ? "term"
                 : c.kind == CandidateKind::kRobustLoss ? "loss"
                 : c.kind == CandidateKind::kRemoval    ? "removal"
                                                        : "time_offset"},
        {"model_change", c.model_change},
        {"insert_index", c.insert_index ? nlohmann::json(*c.insert_index) : nlohmann::json()},
        {"replaces", c.replaces.empty() ? nlohmann::json() : nlohmann::json(c.replaces)},
        {"term_names", c.term_names},
        {"cv_position_mm_mean", NumberOrNull(c.cv_position_mm_mean)},
        {"cv_orientation_deg_mean", NumberOrNull(c.cv_orientation_deg_mean)},
        {"cv_base_position_mm_mean", NumberOrNull(c.cv_base_position_mm_mean)},
        {"cv_base_orientation_deg_mean", NumberOrNull(c.cv_base_orientation_deg_mean)},
        {"cv_drop_percent",
         {{"position", NumberOrNull(c.drop_position_percent)},
          {"orientation", NumberOrNull(c.drop_orientation_percent)}}},
        {"cv_whitened_mean", NumberOrNull(c.cv_whitened_mean)},
        {"bic", NumberOrNull(c.bic)},
        {"delta_bic", NumberOrNull(c.delta_bic)},
        {"num_free_parameters", c.num_free_parameters},
        {"p_value", NumberOrNull(c.p_value)},
        {"significant", c.significant},
        {"cross_validated", c.cross_validated},
        {"fitted", c.fitted},
        {"converged", c.converged},
        {"error", c.error.empty() ? nlohmann::json() : nlohmann::json(c.error)},
        {"reason", c.reason},
        {"evidence", c.evidence.ToJson()},
        {"parameters", params},
        {"stddev_scale", c.stddev_scale},
        {"outlier_stations", c.outlier_stations},
        {"local_structure_stations", c.local_structure_stations},
        {"bic_unresolved_left_out", c.bic_unresolved_left_out},
        {"cv_unresolved_left_out", c.cv_unresolved_left_out},
        {"statement", c.statement},
        {"seconds", c.seconds},
    };
  }
}
}  // namespace

nlohmann::json Diagnosis::ToJson() const {
  nlohmann::json cands = nlohmann::json::array();
  for (const auto& c : candidates) cands.push_back(CandidateToJson(c));
  nlohmann::json flex = nlohmann::json::array();
  for (const auto& c : flexible) flex.push_back(CandidateToJson(c));
  nlohmann::json verdict = {
      {"effect", verdict_effect ? nlohmann::json(*verdict_effect) : nlohmann::json()},
      {"replaces", verdict_effect && !candidates.empty() && !candidates.front().replaces.empty()
                       ? nlohmann::json(candidates.front().replaces)
                       : nlohmann::json()},
      {"text", verdict_text},
      {"unexplained_structure", unexplained_structure},
      {"unsupported_note", unsupported_note},
      {"test_power_note", test_power_note}};
  nlohmann::json unsupported = nlohmann::json::array();
  for (const auto& u : unsupported_terms) {
    unsupported.push_back({{"term", u.term},
                           {"type", u.type},
                           {"index", u.index},
                           {"evidence", u.evidence.ToJson()},
                           {"reason", u.evidence.Describe()}});
  }
  return {{"command", "diagnose"},
          {"model", model},
          {"data", data},
          {"folds", folds},
          {"num_stations", num_stations},
          {"paired_test_blocks", paired_test_blocks},
          {"paired_test_smallest_p", paired_test_smallest_p},
          {"time_offset_s", time_offset_s ? nlohmann::json(*time_offset_s) : nlohmann::json()},
          {"base",
           {{"cv_position_mm_mean", NumberOrNull(base.cv_position_mm_mean)},
            {"cv_orientation_deg_mean", NumberOrNull(base.cv_orientation_deg_mean)},
            {"final_cost", base.final_cost},
            {"num_residuals", base.num_residuals},
            {"num_free_parameters", base.num_free_parameters},
            {"chi2", base.chi2},
            {"chi2_per_dof", NumberOrNull(base.chi2_per_dof)},
            {"bic", base.bic},
            {"converged", base.converged},
            {"table1", Table1ToJson(base.table1)}}},
          {"candidates", cands},
          {"flexible_fallback", flex},
          {"skipped", skipped},
          {"p_threshold", p_threshold},
          {"verdict", verdict},
          {"unsupported_terms", unsupported},
          {"seconds", seconds}};
}

std::string FormatDiagnosis(const Diagnosis& d) {
  std::ostringstream out;
  out << "Base model " << d.model << " on " << d.data << " (" << d.num_stations << " stations, "
      << d.folds << "-fold cross-validation"
      << (d.paired_test_blocks > 0 ? " and paired test over " +
                                         std::to_string(d.paired_test_blocks) + " blocks of time"
                                   : std::string())
      << "): held-out error "
      << FormatNumber(d.base.cv_position_mm_mean, 3) << " mm, "
      << FormatNumber(d.base.cv_orientation_deg_mean, 3) << " deg; " << d.base.num_free_parameters
      << " free parameters, chi2/dof " << FormatNumber(d.base.chi2_per_dof, 2) << ", BIC "
      << FormatNumber(d.base.bic, 1) << "\n";
  if (d.time_offset_s) {
    out << "Streams paired at a clock offset of " << FormatNumber(*d.time_offset_s * 1e3, 3)
        << " ms (reference minus tracker)\n";
  }
  out << "\n";
  out << "Candidate effects (ranked; significant: p < " << FormatSignificant(d.p_threshold, 2)
      << ", held-out drop >= 5 %, delta BIC < -10, strength >= 3 sigma, location determined):\n";
  out << std::left << std::setw(4) << "#" << std::setw(16) << "effect" << std::right
      << std::setw(11) << "pos [mm]" << std::setw(9) << "drop %" << std::setw(11) << "ori [deg]"
      << std::setw(9) << "drop %" << std::setw(11) << "dBIC" << std::setw(10) << "p"
      << "  significant\n";
  int rank = 1;
  for (const auto& c : d.candidates) {
    // A replacement is named "plane for dipole_2", a removal "remove dipole_2" (they may
    // overflow the column).
    out << std::left << std::setw(4) << rank++ << std::setw(16)
        << (c.replaces.empty()                    ? c.effect
            : c.kind == CandidateKind::kRemoval ? c.effect + " " + c.replaces
                                                  : c.effect + " for " + c.replaces)
        << std::right;
    if (c.cross_validated) {
      out << std::setw(11) << FormatNumber(c.cv_position_mm_mean, 3) << std::setw(9)
          << FormatNumber(c.drop_position_percent, 1) << std::setw(11)
          << FormatNumber(c.cv_orientation_deg_mean, 3) << std::setw(9)
          << FormatNumber(c.drop_orientation_percent, 1);
    } else {
      out << std::setw(40) << "(not cross-validated)";
    }
    out << std::setw(11) << (std::isfinite(c.delta_bic) ? FormatNumber(c.delta_bic, 1) : "-")
        << std::setw(10) << (std::isfinite(c.p_value) ? FormatSignificant(c.p_value, 2) : "-")
        << "  " << (c.significant ? "yes" : "no") << "\n";
    if (!c.statement.empty()) out << "      " << c.statement << "\n";
    if (!c.fitted) out << "      " << c.reason << "\n";
  }
  for (const auto& c : d.candidates) {
    // The same stations for every candidate: say so once, with the base's mean.
    if (c.cv_unresolved_left_out > 0) {
      out << "  Held-out means and drops" << UnresolvedNote(c.cv_unresolved_left_out)
          << "; the base over the others: " << FormatNumber(c.cv_base_position_mm_mean, 3)
          << " mm, " << FormatNumber(c.cv_base_orientation_deg_mean, 3) << " deg.\n";
      break;
    }
  }
  for (const auto& s : d.skipped) out << "  (not tested: " << s << ")\n";
  for (const auto& f : d.flexible) {
    out << "Flexible fallback (not an effect): " << f.effect;
    if (f.cross_validated) {
      out << ": held-out " << FormatNumber(f.cv_position_mm_mean, 3) << " mm ("
          << FormatNumber(f.drop_position_percent, 1) << " %), "
          << FormatNumber(f.cv_orientation_deg_mean, 3) << " deg ("
          << FormatNumber(f.drop_orientation_percent, 1)
          << " %), p = " << FormatSignificant(f.p_value, 2) << ", delta BIC "
          << FormatNumber(f.delta_bic, 1)
          << (f.significant ? ": the remaining structure is real" : ": nothing more to gain");
    } else {
      out << ": " << f.reason;
    }
    out << "\n";
  }
  out << "\nVerdict: " << d.verdict_text << "\n";
  if (d.verdict_effect && d.candidates.front().kind == CandidateKind::kRemoval) {
    const Candidate& top = d.candidates.front();
    out << "\nIn " << d.model << ", remove `terms:` item " << top.insert_index.value_or(-1) << " ("
        << top.replaces << ", counting from 0).\n";
  } else if (d.verdict_effect) {
    const Candidate& top = d.candidates.front();
    if (!top.insert_index) {
      // A top-level key (`loss:`, `time_offset:`): the model may have it already (a fixed
      // `time_offset:` is tested), and a model file refuses a key given twice, so the change
      // replaces it there rather than adding a second one.
      const std::string key = top.model_change.substr(0, top.model_change.find(':'));
      out << "\nIn " << d.model << ", set the top-level key `" << key
          << ":` (in place of the one there, if any):\n";
    } else {
      out << (top.replaces.empty() ? "\nAdd to " : "\nIn ") << d.model;
      if (!top.replaces.empty()) {
        out << ", replace `terms:` item " << *top.insert_index << " (" << top.replaces
            << ", counting from 0) by:\n";
      } else {
        out << " (in `terms:`, as item " << *top.insert_index << " counting from 0):\n";
      }
    }
    std::istringstream lines(top.model_change);
    for (std::string line; std::getline(lines, line);) out << "  " << line << "\n";
  }
  return out.str();
}

}  // namespace trackcal::fit
