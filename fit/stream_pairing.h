// Pairs a tracker stream with a reference stream by time (paper's static stations, from dynamic
// captures): every tracker sample at tracker time t gets the reference pose at reference time
// t + time_offset, interpolated linearly in position and by slerp in rotation between the two
// neighbouring reference samples. Samples whose reference time falls outside the reference stream,
// or in a gap longer than max_gap_s, are dropped.
//
// The clock offset (reference clock minus tracker clock, as the simulator's clock_offset effect) is
// either given or estimated, from the position difference d_i(dt) = p_reported(t_i) -
// p_reference(t_i + dt). The tracker's distortion is part of d, and along a trajectory it
// correlates with the velocity (an open path through a non-uniform error field), so minimising the
// plain variance of d, as a first version did, biased the offset by ~1.3 ms on the paper scene.
// Instead, d is regressed on a smooth model of the tracker's error, a polynomial of degree
// `detrend_degree` in the reported position (plus R_reported u, a constant body offset in the
// receiver frame, when `detrend_body_offset`), and the score is the residual variance. The
// estimate: a coarse scan of that score over [initial - range, initial + range] finds the basin,
// then Gauss-Newton on dt with the reference velocity as the derivative
// (d_i(dt) ~ d_i(dt_k) - v_i (dt - dt_k)), each step a linear least squares over the error model
// and dt together. Its standard deviation comes from the same regression with a Newey-West
// (Bartlett, `correlation_time_s`) estimate of the residuals' serial correlation, since the error
// model's misfit is smooth in time.
#pragma once

#include <Eigen/Core>
#include <filesystem>
#include <limits>
#include <nlohmann/json.hpp>
#include <optional>
#include <string>
#include <vector>

#include "core/capture.h"
#include "fit/model.h"

namespace trackcal::fit {

struct StreamPairingOptions {
  double time_offset = 0.0;  // t_reference - t_tracker [s], used as given or as the search centre
  bool estimate_time_offset = false;
  double search_range = 0.5;  // [s] half-width of the offset search
  double tolerance = 1e-5;    // [s] golden-section stopping width
  double max_gap_s = 0.1;     // [s] longest reference gap interpolated across
  int sensor = 0;             // tracker sensor to pair (0: the lowest sensor in the stream)
  std::string set = "calib";  // "set" column of the paired poses
  int decimate = 1;           // keep every n-th tracker sample (>= 1)
  // Tracker error model regressed out of the position difference when estimating the offset:
  // polynomial degree in the reported position (-1: none, 0: a constant, as the plain variance).
  int detrend_degree = 3;
  bool detrend_body_offset = true;  // also regress out R_reported * u (a body offset u)
  int max_gauss_newton_steps = 20;  // refinement steps after the coarse scan
  double correlation_time_s = 0.5;  // [s] Bartlett window of the offset's standard deviation
  // Largest variance inflation of the offset against the error model (H_tt (H^-1)_tt of the
  // joint regression, >= 1: 1 / the share of the offset's information the model does not also
  // carry) at which the estimate is kept; above it detrend_degree is lowered by one (not below 0)
  // and the offset estimated again. The fit engine's limit for a fitted offset
  // (kMaxTimeOffsetVarianceInflation, fit/fit_engine.h).
  double max_variance_inflation = 10.0;
  // Clock drift (the reference clock's rate over the tracker's minus 1) of a given offset: the
  // tracker sample at t is paired with the reference at t + time_offset + clock_drift (t - t_mid),
  // t_mid the middle of the paired sensor's (decimated) samples. Ignored when estimating.
  double clock_drift = 0.0;
  // The tracker time at which a given time_offset holds with clock_drift (the t_mid of the pairing
  // that estimated them: StreamPairingResult::clock_drift_origin); NaN: t_mid of these samples.
  // Pairing another capture at a fit's offset and drift needs the fit's origin. Ignored when
  // estimating.
  double clock_drift_origin = std::numeric_limits<double>::quiet_NaN();
  // When estimating: a drift beyond kDriftZ (4) standard deviations (the warning's test) is
  // corrected, the poses paired with the estimated offset and drift as above.
  bool correct_clock_drift = true;
  bool Check(std::string* error) const;
};

struct StreamPairingResult {
  PoseCapture poses;
  double time_offset = 0.0;  // used (given or estimated) [s]
  double cost = 0.0;         // residual variance of the position difference at that offset [m^2]
                             // (after the error model when estimating; plain variance otherwise)
  double time_offset_stddev = 0.0;  // [s] of an estimated offset (0 when given)
  int gauss_newton_steps = 0;       // refinement steps taken
  // Of an estimated offset: the error model's degree it was estimated with (options'
  // detrend_degree, or lower when that could mimic a time shift) and its variance inflation
  // against that model (NaN when given).
  int detrend_degree = -1;
  double time_offset_variance_inflation = std::numeric_limits<double>::quiet_NaN();
  // Of an estimated offset: the clocks' drift, the reference clock's rate relative to the
  // tracker's minus 1 (1e-4: the offset grows by 6 ms a minute), estimated with the offset as
  // offset + drift (t - t_mid) over the stream, and its standard deviation (NaN when given).
  double clock_drift = std::numeric_limits<double>::quiet_NaN();
  double clock_drift_stddev = std::numeric_limits<double>::quiet_NaN();
  double clock_drift_variance_inflation = std::numeric_limits<double>::quiet_NaN();
  // The drift the poses were paired with (0: one offset for the whole stream), and the tracker time
  // t_mid at which time_offset holds: reference time = t + time_offset + applied (t - t_mid).
  // clock_drift_corrected: an estimated drift was significant and is applied (time_offset is then
  // the offset at t_mid).
  double clock_drift_applied = 0.0;
  double clock_drift_origin = 0.0;
  bool clock_drift_corrected = false;
  // Of an estimated offset: the RMS of the position difference left by the error model at the
  // offset (sqrt(cost)) over the RMS spread of the tracker's path about its mean, per component
  // (NaN when given). Small when the offset pairs the streams; a few tenths when it pairs poses
  // of unrelated times (the true offset outside the searched range).
  double residual_to_path_ratio = std::numeric_limits<double>::quiet_NaN();
  // Non-empty when an estimated offset is poorly identified: the degree was lowered, the offset is
  // undetermined even at degree 0, or the refinement did not converge. Callers name the streams.
  std::string warning;
  // Per pose record: the reference's velocity [m/s] and angular velocity (transmitter frame,
  // [rad/s]) at the paired time, by central differences over one reference period (zero where the
  // neighbourhood leaves the stream), for a clock offset fitted with the model (FitStation).
  std::vector<Eigen::Vector3d> reference_velocity;
  std::vector<Eigen::Vector3d> reference_angular_velocity;
  int dropped = 0;  // tracker samples without a reference
};

// The pairing as `trackcal-fit pair --json` prints it and Python's trackcal.pair returns it (one
// document for both, so they cannot drift apart): `output` null when no file was written,
// `estimated`: whether the offset was estimated.
nlohmann::json PairingJson(const StreamPairingResult& result, bool estimated,
                           const std::optional<std::filesystem::path>& output);

// Throws std::invalid_argument for bad options or streams with fewer than 2 samples.
StreamPairingResult PairStreams(const TrackerStream& tracker, const ReferenceStream& reference,
                                const StreamPairingOptions& options);

// PairStreams on streams read from these files: its errors ("tracker stream has fewer than 2
// samples") are prefixed with both paths, as its warning is by the tools.
StreamPairingResult PairStreamsOfFiles(const TrackerStream& tracker,
                                       const ReferenceStream& reference,
                                       const StreamPairingOptions& options,
                                       const std::filesystem::path& tracker_path,
                                       const std::filesystem::path& reference_path);

// The paired records as fit stations carrying the reference velocities a fitted clock offset needs
// (fit/terms_time_offset.h); only records of `set` when it is not empty.
std::vector<FitStation> FitStationsOfPairing(const StreamPairingResult& result,
                                             const std::string& set = {});

// The reference pose at reference time t, or nullopt outside the stream or in a gap > max_gap_s.
std::optional<Rigid3d> InterpolateReference(const ReferenceStream& reference, double t,
                                            double max_gap_s);

}  // namespace trackcal::fit
