// Error statistics in the form of the paper's Table 1: mean, standard deviation and maximum of the
// position error magnitude (mm) and the orientation error angle (deg), before and after a correction,
// with the improvement in percent. Shared by trackcal-fit, diagnose, reports and the Python package.
#pragma once

#include <span>
#include <string>
#include <vector>

#include "core/pose.h"

namespace trackcal {

// Summary of non-negative error magnitudes.
struct ErrorSummary {
  int count = 0;
  double mean = 0.0;
  double std = 0.0;  // sample standard deviation (n - 1); 0 for fewer than 2 values
  double max = 0.0;
  double rms = 0.0;
  double median = 0.0;
  double p95 = 0.0;  // 95th percentile, linear interpolation between order statistics
};

ErrorSummary SummarizeErrors(std::span<const double> values);

// Position errors in millimetres and orientation errors in degrees of one set of poses.
struct PoseErrorSummary {
  ErrorSummary position_mm;
  ErrorSummary orientation_deg;
};

// Per-pose error magnitudes of `estimated` against `reference` (both transmitter_from_receiver).
void ComputeErrorMagnitudes(std::span<const Rigid3d> estimated, std::span<const Rigid3d> reference,
                            std::vector<double>* position_mm, std::vector<double>* orientation_deg);

PoseErrorSummary SummarizePoseErrors(std::span<const Rigid3d> estimated,
                                     std::span<const Rigid3d> reference);

// The paper's Table 1 for one set: before (reported vs reference) and after (corrected vs reference).
struct Table1 {
  std::string set_name;  // "calib", "valid", "cross-validation", ...
  PoseErrorSummary before;
  PoseErrorSummary after;
};

// 100 * (before - after) / before; 0 when before is 0.
double ImprovementPercent(double before, double after);

// Plain-text rendering in the paper's layout (two blocks: position in mm, orientation in deg).
std::string FormatTable1(const Table1& table);

}  // namespace trackcal
