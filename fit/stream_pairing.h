// Pairs a tracker stream with a reference stream by time (paper's static stations, from dynamic
// captures): every tracker sample at tracker time t gets the reference pose at reference time
// t + time_offset, interpolated linearly in position and by slerp in rotation between the two
// neighbouring reference samples. Samples whose reference time falls outside the reference stream, or
// in a gap longer than max_gap_s, are dropped.
//
// The clock offset (reference clock minus tracker clock, as the simulator's clock_offset effect) is
// either given or estimated: a coarse scan over [initial - range, initial + range] followed by a
// golden-section refinement minimises the variance of the position difference reported - reference
// (a constant distortion offset does not bias it; the trajectory's motion makes a wrong offset cost).
#pragma once

#include <optional>
#include <string>

#include "core/capture.h"

namespace trackcal::fit {

struct StreamPairingOptions {
  double time_offset = 0.0;  // t_reference - t_tracker [s], used as given or as the search centre
  bool estimate_time_offset = false;
  double search_range = 0.5;   // [s] half-width of the offset search
  double tolerance = 1e-5;     // [s] golden-section stopping width
  double max_gap_s = 0.1;      // [s] longest reference gap interpolated across
  int sensor = 0;              // tracker sensor to pair (0: the first sensor in the stream)
  std::string set = "calib";   // "set" column of the paired poses
  int decimate = 1;            // keep every n-th tracker sample (>= 1)
  bool Check(std::string* error) const;
};

struct StreamPairingResult {
  PoseCapture poses;
  double time_offset = 0.0;   // used (given or estimated) [s]
  double cost = 0.0;          // variance of the position difference at that offset [m^2]
  int dropped = 0;            // tracker samples without a reference
};

// Throws std::invalid_argument for bad options or streams with fewer than 2 samples.
StreamPairingResult PairStreams(const TrackerStream& tracker, const ReferenceStream& reference,
                                const StreamPairingOptions& options);

// The reference pose at reference time t, or nullopt outside the stream or in a gap > max_gap_s.
std::optional<Rigid3d> InterpolateReference(const ReferenceStream& reference, double t,
                                            double max_gap_s);

}  // namespace trackcal::fit
