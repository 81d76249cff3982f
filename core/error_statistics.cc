#include "core/error_statistics.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
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

double ImprovementPercent(double before, double after) {
  return before > 0.0 ? 100.0 * (before - after) / before : 0.0;
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
      std::snprintf(line, sizeof(line), "  %-20s %10.3f %10.3f %11.1f %%\n", r.name, r.before,
                    r.after, ImprovementPercent(r.before, r.after));
      out += line;
    }
  };
  std::snprintf(line, sizeof(line), "%s set (%d poses)\n", t.set_name.c_str(),
                t.before.position_mm.count);
  out += line;
  block("Position error (mm)", t.before.position_mm, t.after.position_mm);
  block("Orientation error (deg)", t.before.orientation_deg, t.after.orientation_deg);
  return out;
}

}  // namespace trackcal
