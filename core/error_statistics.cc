#include "core/error_statistics.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <limits>
#include <stdexcept>

namespace trackcal {
namespace {

double Quantile(const std::vector<double>& sorted, double q) {
  if (sorted.empty()) return 0.0;
  const double pos = q * static_cast<double>(sorted.size() - 1);
  const size_t lo = static_cast<size_t>(std::floor(pos));
  const size_t hi = std::min(lo + 1, sorted.size() - 1);
  const double frac = pos - static_cast<double>(lo);
  return sorted[lo] + frac * (sorted[hi] - sorted[lo]);
}

}  // namespace

ErrorSummary SummarizeErrors(std::span<const double> values) {
  ErrorSummary s;
  s.count = static_cast<int>(values.size());
  if (values.empty()) return s;
  // An unknown error (NaN) makes every statistic unknown: std::max would skip it while the mean
  // took it, and std::sort's order is undefined with it.
  if (std::any_of(values.begin(), values.end(), [](double v) { return std::isnan(v); })) {
    const double nan = std::numeric_limits<double>::quiet_NaN();
    s.mean = s.std = s.max = s.rms = s.median = s.p95 = nan;
    return s;
  }
  double sum = 0.0, sum_sq = 0.0;
  for (double v : values) {
    sum += v;
    sum_sq += v * v;
    s.max = std::max(s.max, v);
  }
  const double n = static_cast<double>(values.size());
  s.mean = sum / n;
  s.rms = std::sqrt(sum_sq / n);
  if (values.size() > 1) {
    double ss = 0.0;  // two-pass for accuracy
    for (double v : values) ss += (v - s.mean) * (v - s.mean);
    s.std = std::sqrt(ss / (n - 1.0));
  }
  std::vector<double> sorted(values.begin(), values.end());
  std::sort(sorted.begin(), sorted.end());
  s.median = Quantile(sorted, 0.5);
  s.p95 = Quantile(sorted, 0.95);
  return s;
}

void ComputeErrorMagnitudes(std::span<const Rigid3d> estimated, std::span<const Rigid3d> reference,
                            std::vector<double>* position_mm, std::vector<double>* orientation_deg) {
  if (estimated.size() != reference.size()) {
    throw std::invalid_argument("ComputeErrorMagnitudes: " + std::to_string(estimated.size()) +
                                " estimated poses but " + std::to_string(reference.size()) +
                                " reference poses");
  }
  position_mm->resize(estimated.size());
  orientation_deg->resize(estimated.size());
  for (size_t i = 0; i < estimated.size(); ++i) {
    (*position_mm)[i] = 1e3 * PositionErrorNorm(estimated[i], reference[i]);
    (*orientation_deg)[i] = kDegPerRad * OrientationErrorAngle(estimated[i], reference[i]);
  }
}

PoseErrorSummary SummarizePoseErrors(std::span<const Rigid3d> estimated,
                                     std::span<const Rigid3d> reference) {
  std::vector<double> position_mm, orientation_deg;
  ComputeErrorMagnitudes(estimated, reference, &position_mm, &orientation_deg);
  return {SummarizeErrors(position_mm), SummarizeErrors(orientation_deg)};
}

bool IsHemisphereFlip(const Eigen::Vector3d& reported_position,
                      const Eigen::Vector3d& reference_position) {
  return reported_position.dot(reference_position) < 0.0;
}

std::vector<int> HemisphereFlipsToLeaveOut(std::span<const Eigen::Vector3d> reported_positions,
                                           std::span<const Eigen::Vector3d> reference_positions) {
  if (reported_positions.size() != reference_positions.size()) {
    throw std::invalid_argument("HemisphereFlipsToLeaveOut: " +
                                std::to_string(reported_positions.size()) +
                                " reported positions but " +
                                std::to_string(reference_positions.size()) +
                                " reference positions");
  }
  std::vector<int> flips;
  for (size_t i = 0; i < reported_positions.size(); ++i) {
    if (IsHemisphereFlip(reported_positions[i], reference_positions[i])) {
      flips.push_back(static_cast<int>(i));
    }
  }
  if (2 * flips.size() >= reported_positions.size()) flips.clear();
  return flips;
}

Table1 MakeTable1(std::string set_name, std::span<const Rigid3d> reported,
                  std::span<const Rigid3d> corrected, std::span<const Rigid3d> reference) {
  if (reported.size() != reference.size() || corrected.size() != reference.size()) {
    throw std::invalid_argument("MakeTable1: " + std::to_string(reported.size()) + " reported, " +
                                std::to_string(corrected.size()) + " corrected and " +
                                std::to_string(reference.size()) + " reference poses");
  }
  std::vector<Eigen::Vector3d> reported_positions, reference_positions;
  for (size_t i = 0; i < reported.size(); ++i) {
    reported_positions.push_back(reported[i].translation);
    reference_positions.push_back(reference[i].translation);
  }
  const std::vector<int> flips = HemisphereFlipsToLeaveOut(reported_positions, reference_positions);
  std::vector<Rigid3d> kept_reported, kept_corrected, kept_reference;
  size_t next_flip = 0;
  for (size_t i = 0; i < reported.size(); ++i) {
    if (next_flip < flips.size() && flips[next_flip] == static_cast<int>(i)) {
      ++next_flip;
      continue;
    }
    kept_reported.push_back(reported[i]);
    kept_corrected.push_back(corrected[i]);
    kept_reference.push_back(reference[i]);
  }
  Table1 table;
  table.set_name = std::move(set_name);
  table.before = SummarizePoseErrors(kept_reported, kept_reference);
  table.after = SummarizePoseErrors(kept_corrected, kept_reference);
  table.flips_left_out = static_cast<int>(flips.size());
  return table;
}

double ImprovementPercent(double before, double after) {
  // An unknown statistic gives an unknown improvement (a NaN `before` read as 0 %), and an error
  // that appears where there was none is no "0 %": it is unboundedly worse.
  if (std::isnan(before) || std::isnan(after)) return std::numeric_limits<double>::quiet_NaN();
  if (before > 0.0) return 100.0 * (before - after) / before;
  return after > 0.0 ? -std::numeric_limits<double>::infinity() : 0.0;
}

std::string FormatTable1(const Table1& t) {
  std::string out;
  char line[160];
  auto block = [&](const char* title, const ErrorSummary& b, const ErrorSummary& a) {
    std::snprintf(line, sizeof(line), "%-22s %10s %10s %12s\n", title, "Original", "Corrected",
                  "Improvement");
    out += line;
    const struct {
      const char* name;
      double before, after;
    } rows[] = {{"Mean", b.mean, a.mean}, {"Standard dev.", b.std, a.std}, {"Maximum", b.max, a.max}};
    for (const auto& r : rows) {
      const double improvement = ImprovementPercent(r.before, r.after);
      if (std::isfinite(improvement)) {
        std::snprintf(line, sizeof(line), "  %-20s %10.3f %10.3f %11.1f %%\n", r.name, r.before,
                      r.after, improvement);
      } else {  // undefined: an error where there was none, or an unknown statistic
        std::snprintf(line, sizeof(line), "  %-20s %10.3f %10.3f %13s\n", r.name, r.before, r.after,
                      "n/a");
      }
      out += line;
    }
  };
  std::snprintf(line, sizeof(line), "%s set (%d poses)\n", t.set_name.c_str(),
                t.before.position_mm.count);
  out += line;
  if (t.flips_left_out > 0) {
    std::snprintf(line, sizeof(line),
                  "  %d more left out: reported in the other hemisphere than their reference "
                  "(hemisphere flips)\n",
                  t.flips_left_out);
    out += line;
  }
  block("Position error (mm)", t.before.position_mm, t.after.position_mm);
  block("Orientation error (deg)", t.before.orientation_deg, t.after.orientation_deg);
  return out;
}

}  // namespace trackcal
