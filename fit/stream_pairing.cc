#include "fit/stream_pairing.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <stdexcept>

namespace trackcal::fit {

bool StreamPairingOptions::Check(std::string* error) const {
  auto fail = [&](const std::string& m) {
    if (error) *error = m;
    return false;
  };
  if (!std::isfinite(time_offset)) return fail("time_offset must be finite");
  if (!(search_range > 0.0)) return fail("search_range must be > 0");
  if (!(tolerance > 0.0)) return fail("tolerance must be > 0");
  if (!(max_gap_s > 0.0)) return fail("max_gap_s must be > 0");
  if (decimate < 1) return fail("decimate must be >= 1");
  if (set.empty()) return fail("set must not be empty");
  return true;
}

std::optional<Rigid3d> InterpolateReference(const ReferenceStream& reference, double t,
                                            double max_gap_s) {
  const auto& r = reference.records;
  if (r.size() < 2 || !(t >= r.front().time) || !(t <= r.back().time)) return std::nullopt;
  auto it = std::upper_bound(r.begin(), r.end(), t,
                             [](double v, const ReferenceStreamSample& s) { return v < s.time; });
  if (it == r.end()) it = r.end() - 1;
  if (it == r.begin()) it = r.begin() + 1;
  const auto& b = *it;
  const auto& a = *(it - 1);
  const double dt = b.time - a.time;
  if (!(dt > 0.0) || dt > max_gap_s) return std::nullopt;
  const double s = std::clamp((t - a.time) / dt, 0.0, 1.0);
  Rigid3d out;
  out.translation = (1.0 - s) * a.transmitter_from_body.translation + s * b.transmitter_from_body.translation;
  out.rotation = a.transmitter_from_body.rotation.slerp(s, b.transmitter_from_body.rotation);
  return out;
}

namespace {

struct Pairing {
  PoseCapture poses;
  double cost = std::numeric_limits<double>::infinity();
  int dropped = 0;
};

Pairing Pair(const TrackerStream& tracker, const ReferenceStream& reference,
             const StreamPairingOptions& options, int sensor, double offset) {
  Pairing out;
  out.poses.extra_columns.clear();
  Eigen::Vector3d sum = Eigen::Vector3d::Zero();
  double sum2 = 0.0;
  int count = 0;
  int index = 0;
  for (const auto& s : tracker.records) {
    if (s.sensor != sensor) continue;
    if (index++ % options.decimate != 0) continue;
    const auto ref = InterpolateReference(reference, s.time + offset, options.max_gap_s);
    if (!ref) {
      ++out.dropped;
      continue;
    }
    PoseRecord r;
    r.station = static_cast<int>(out.poses.records.size()) + 1;
    r.set = options.set;
    r.sensor = s.sensor;
    r.time = s.time;
    r.reported = s.transmitter_from_receiver;
    r.reference = *ref;
    const Eigen::Vector3d d = r.reported.translation - r.reference.translation;
    sum += d;
    sum2 += d.squaredNorm();
    ++count;
    out.poses.records.push_back(std::move(r));
  }
  if (count >= 2) {
    const Eigen::Vector3d mean = sum / count;
    out.cost = sum2 / count - mean.squaredNorm();
  }
  return out;
}

}  // namespace

StreamPairingResult PairStreams(const TrackerStream& tracker, const ReferenceStream& reference,
                                const StreamPairingOptions& options) {
  std::string error;
  if (!options.Check(&error)) throw std::invalid_argument("stream pairing: " + error);
  if (tracker.records.size() < 2) throw std::invalid_argument("tracker stream has fewer than 2 samples");
  if (reference.records.size() < 2) {
    throw std::invalid_argument("reference stream has fewer than 2 samples");
  }
  for (size_t i = 1; i < reference.records.size(); ++i) {
    if (!(reference.records[i].time > reference.records[i - 1].time)) {
      throw std::invalid_argument("reference stream: time not strictly increasing at sample " +
                                  std::to_string(i + 1));
    }
  }
  const int sensor = options.sensor != 0 ? options.sensor : tracker.records.front().sensor;
  double offset = options.time_offset;
  if (options.estimate_time_offset) {
    // Coarse scan (step 1/40 of the range) to land in the right basin, then golden section.
    const int steps = 80;
    const double lo0 = options.time_offset - options.search_range;
    const double step = 2.0 * options.search_range / steps;
    double best = lo0, best_cost = std::numeric_limits<double>::infinity();
    for (int i = 0; i <= steps; ++i) {
      const double o = lo0 + i * step;
      const double c = Pair(tracker, reference, options, sensor, o).cost;
      if (c < best_cost) best_cost = c, best = o;
    }
    double a = best - step, b = best + step;
    const double g = (std::sqrt(5.0) - 1.0) / 2.0;
    double c = b - g * (b - a), d = a + g * (b - a);
    double fc = Pair(tracker, reference, options, sensor, c).cost;
    double fd = Pair(tracker, reference, options, sensor, d).cost;
    while (b - a > options.tolerance) {
      if (fc < fd) {
        b = d, d = c, fd = fc;
        c = b - g * (b - a);
        fc = Pair(tracker, reference, options, sensor, c).cost;
      } else {
        a = c, c = d, fc = fd;
        d = a + g * (b - a);
        fd = Pair(tracker, reference, options, sensor, d).cost;
      }
    }
    offset = 0.5 * (a + b);
  }
  Pairing p = Pair(tracker, reference, options, sensor, offset);
  if (p.poses.records.empty()) {
    throw std::invalid_argument("stream pairing: no tracker sample has a reference at offset " +
                                std::to_string(offset) + " s (do the streams overlap in time?)");
  }
  StreamPairingResult result;
  result.poses = std::move(p.poses);
  result.time_offset = offset;
  result.cost = p.cost;
  result.dropped = p.dropped;
  return result;
}

}  // namespace trackcal::fit
