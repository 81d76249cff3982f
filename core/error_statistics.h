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

// Every statistic is NaN when a value is NaN (count is still the number of values).
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

// A report in the other hemisphere than its reference (reported . reference < 0, positions in the
// transmitter frame): the Fastrak's hemisphere ambiguity, which reports -p once the receiver
// crosses the hemisphere's plane. No calibration corrects it: it stays 2 |p| off. The fit treats
// such a station as a bad report (fit/fit_engine.cc BuildProblem), and the statistics leave it
// out (HemisphereFlipsToLeaveOut).
bool IsHemisphereFlip(const Eigen::Vector3d& reported_position,
                      const Eigen::Vector3d& reference_position);

// Indices of the hemisphere flips among the poses when they are fewer than half of them; none
// otherwise: most reports in the other hemisphere is a wrong hemisphere setting (the Fastrak's H
// command) or a wrong registration, which the statistics must show, not hide. Throws on sizes
// that differ.
std::vector<int> HemisphereFlipsToLeaveOut(std::span<const Eigen::Vector3d> reported_positions,
                                           std::span<const Eigen::Vector3d> reference_positions);

// The paper's Table 1 for one set: before (reported vs reference) and after (corrected vs reference).
struct Table1 {
  std::string set_name;  // "calib", "valid", "cross-validation", ...
  PoseErrorSummary before;
  PoseErrorSummary after;
  // Hemisphere flips left out of both columns (HemisphereFlipsToLeaveOut): a few gross reports
  // that no calibration changes would otherwise dominate the mean, std and maximum.
  int flips_left_out = 0;
};

// Table 1 of one set, the hemisphere flips of `reported` against `reference` left out of both
// columns and counted in `flips_left_out`. The three spans are aligned; throws when they are not.
Table1 MakeTable1(std::string set_name, std::span<const Rigid3d> reported,
                  std::span<const Rigid3d> corrected, std::span<const Rigid3d> reference);

// 100 * (before - after) / before; 0 when both are 0, -infinity when only before is 0 (an error
// where there was none), NaN when either is NaN.
double ImprovementPercent(double before, double after);

// Plain-text rendering in the paper's layout (two blocks: position in mm, orientation in deg).
std::string FormatTable1(const Table1& table);

}  // namespace trackcal
