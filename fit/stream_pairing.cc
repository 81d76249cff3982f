#include "fit/stream_pairing.h"

#include <Eigen/Dense>
#include <algorithm>
#include <cmath>
#include <limits>
#include <set>
#include <sstream>
#include <stdexcept>
#include <utility>
#include <vector>

#include "fit/rotation.h"

namespace trackcal::fit {

bool StreamPairingOptions::Check(std::string* error) const {
  auto fail = [&](const std::string& m) {
    if (error) *error = m;
    return false;
  };
  if (!std::isfinite(time_offset)) return fail("time_offset must be finite");
  // Infinite ones passed and the scan gave NaN offsets.
  if (!(search_range > 0.0 && std::isfinite(search_range))) {
    return fail("search_range must be a finite number > 0");
  }
  if (!(tolerance > 0.0 && std::isfinite(tolerance)))
    return fail("tolerance must be a finite number > 0");
  if (!(max_gap_s > 0.0)) return fail("max_gap_s must be > 0");
  if (decimate < 1) return fail("decimate must be >= 1");
  if (set.empty()) return fail("set must not be empty");
  if (detrend_degree < -1 || detrend_degree > 6) return fail("detrend_degree must be in [-1, 6]");
  if (max_gauss_newton_steps < 1) return fail("max_gauss_newton_steps must be >= 1");
  if (!(correlation_time_s >= 0.0)) return fail("correlation_time_s must be >= 0");
  if (!(max_variance_inflation >= 1.0)) return fail("max_variance_inflation must be >= 1");
  if (!(std::abs(clock_drift) < 0.1)) return fail("clock_drift must be finite and within +-0.1");
  if (std::isinf(clock_drift_origin)) return fail("clock_drift_origin must be finite or NaN");
  return true;
}

namespace {

// Whether consecutive reference samples at times a < b are too far apart to interpolate between.
// A spacing equal to the limit is no gap: a 10 Hz reference's steps of 0.1 s come out a few ulps
// above 0.1 from its printed times, and half its samples were dropped at the default. Those ulps
// are of the times, not of the step: on a Unix-epoch clock (1.7e9 s, ulp 2.4e-7 s) the steps came
// out up to an ulp above 0.1, and a relative 1e-9 of the limit still dropped half the samples.
bool IsGap(double a, double b, double max_gap_s) {
  const double rounding =
      8.0 * std::numeric_limits<double>::epsilon() * std::max(std::abs(a), std::abs(b));
  return !(b - a > 0.0) || b - a > max_gap_s * (1.0 + 1e-9) + rounding;
}

}  // namespace

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
  if (IsGap(a.time, b.time, max_gap_s)) return std::nullopt;
  const double s = std::clamp((t - a.time) / dt, 0.0, 1.0);
  Rigid3d out;
  out.translation =
      (1.0 - s) * a.transmitter_from_body.translation + s * b.transmitter_from_body.translation;
  out.rotation = a.transmitter_from_body.rotation.slerp(s, b.transmitter_from_body.rotation);
  return out;
}

namespace {

// The tracker samples of one sensor in time order (decimated). The tracker stream's reader does
// not require increasing times (receivers interleave), and the offset's standard deviation takes
// the samples as a time series: its Newey-West window pairs samples up to correlation_time_s apart
// in this order (NeweyWestMeat). In stream order, a
// stream whose last sample was its earliest gave a rate of (n - 1) / 1e-9, a window over every
// sample, and a standard deviation 6 times too small.
std::vector<const TrackerStreamSample*> SelectSamples(const TrackerStream& tracker,
                                                      const StreamPairingOptions& options,
                                                      int sensor) {
  std::vector<const TrackerStreamSample*> all;
  for (const auto& s : tracker.records) {
    if (s.sensor == sensor) all.push_back(&s);
  }
  std::stable_sort(
      all.begin(), all.end(),
      [](const TrackerStreamSample* a, const TrackerStreamSample* b) { return a->time < b->time; });
  std::vector<const TrackerStreamSample*> out;
  for (size_t i = 0; i < all.size(); i += static_cast<size_t>(options.decimate)) {
    out.push_back(all[i]);
  }
  return out;
}

// Pairs every selected sample at `offset`.
// With a drift, at the reference time t + offset + drift (t - origin).
StreamPairingResult Pair(const std::vector<const TrackerStreamSample*>& samples,
                         const ReferenceStream& reference, const StreamPairingOptions& options,
                         double offset, double drift = 0.0, double origin = 0.0) {
  StreamPairingResult out;
  out.time_offset = offset;
  out.clock_drift_applied = drift;
  out.clock_drift_origin = origin;
  Eigen::Vector3d sum = Eigen::Vector3d::Zero();
  double sum2 = 0.0;
  for (const TrackerStreamSample* s : samples) {
    const auto ref = InterpolateReference(reference, s->time + offset + drift * (s->time - origin),
                                          options.max_gap_s);
    if (!ref) {
      ++out.dropped;
      continue;
    }
    PoseRecord r;
    r.station = static_cast<int>(out.poses.records.size()) + 1;
    r.set = options.set;
    r.sensor = s->sensor;
    r.time = s->time;
    r.reported = s->transmitter_from_receiver;
    r.reference = *ref;
    const Eigen::Vector3d d = r.reported.translation - r.reference.translation;
    sum += d;
    sum2 += d.squaredNorm();
    out.poses.records.push_back(std::move(r));
  }
  const double n = static_cast<double>(out.poses.records.size());
  out.cost = n >= 2 ? sum2 / n - (sum / n).squaredNorm() : std::numeric_limits<double>::infinity();
  return out;
}

// The tracker error model of the offset estimate: for the samples `rows`, 3 rows each (x, y, z of
// the position difference), the columns of a polynomial of the reported position (same for each
// axis) and, optionally, R_reported (a body offset). Positions are centred and scaled to [-1, 1].
class ErrorModel {
 public:
  ErrorModel(const std::vector<const TrackerStreamSample*>& samples,
             const std::vector<size_t>& rows, const StreamPairingOptions& options) {
    Eigen::Vector3d lo = Eigen::Vector3d::Constant(std::numeric_limits<double>::infinity());
    Eigen::Vector3d hi = -lo;
    for (size_t i : rows) {
      lo = lo.cwiseMin(samples[i]->transmitter_from_receiver.translation);
      hi = hi.cwiseMax(samples[i]->transmitter_from_receiver.translation);
    }
    const Eigen::Vector3d centre = 0.5 * (lo + hi);
    const Eigen::Vector3d half = (0.5 * (hi - lo)).cwiseMax(1e-6);
    std::vector<Eigen::Vector3i> powers;
    for (int a = 0; a <= options.detrend_degree; ++a)
      for (int b = 0; a + b <= options.detrend_degree; ++b)
        for (int c = 0; a + b + c <= options.detrend_degree; ++c) powers.emplace_back(a, b, c);
    const int p = static_cast<int>(powers.size());
    const int k = 3 * p + (options.detrend_body_offset ? 3 : 0);
    a_.setZero(3 * static_cast<Eigen::Index>(rows.size()), k);
    for (size_t r = 0; r < rows.size(); ++r) {
      const Rigid3d& pose = samples[rows[r]]->transmitter_from_receiver;
      const Eigen::Vector3d x = (pose.translation - centre).cwiseQuotient(half);
      const Eigen::Index row = 3 * static_cast<Eigen::Index>(r);
      for (int j = 0; j < p; ++j) {
        const double m = std::pow(x.x(), powers[j].x()) * std::pow(x.y(), powers[j].y()) *
                         std::pow(x.z(), powers[j].z());
        for (int c = 0; c < 3; ++c) a_(row + c, 3 * j + c) = m;
      }
      if (options.detrend_body_offset) {
        a_.block<3, 3>(row, 3 * p) = pose.rotation.normalized().toRotationMatrix();
      }
    }
    if (k > 0) qr_.compute(a_);
  }
  // d minus its least-squares fit by the model.
  Eigen::VectorXd Residual(const Eigen::VectorXd& d) const {
    if (a_.cols() == 0) return d;
    return d - a_ * qr_.solve(d);
  }

 private:
  Eigen::MatrixXd a_;
  Eigen::ColPivHouseholderQR<Eigen::MatrixXd> qr_;
};

// Position differences (3 per sample) at `offset` for the samples `rows`; false if one has no
// reference there.
bool Differences(const std::vector<const TrackerStreamSample*>& samples,
                 const std::vector<size_t>& rows, const ReferenceStream& reference, double offset,
                 double max_gap_s, Eigen::VectorXd* d) {
  d->resize(3 * static_cast<Eigen::Index>(rows.size()));
  for (size_t r = 0; r < rows.size(); ++r) {
    const auto ref = InterpolateReference(reference, samples[rows[r]]->time + offset, max_gap_s);
    if (!ref) return false;
    d->segment<3>(3 * static_cast<Eigen::Index>(r)) =
        samples[rows[r]]->transmitter_from_receiver.translation - ref->translation;
  }
  return true;
}

// Samples with a reference at every offset of [lo, hi] (and a step h beyond, for velocities).
std::vector<size_t> RowsCovering(const std::vector<const TrackerStreamSample*>& samples,
                                 const ReferenceStream& reference, double lo, double hi,
                                 double max_gap_s) {
  // The reference's gaps [start, end): InterpolateReference has no pose from a gap's first sample
  // up to (not including) its last. A first version checked only the window's ends and middle and
  // kept samples whose window held a gap elsewhere; the coarse scan's window is the whole search
  // range, so with one occlusion over max_gap_s in the reference the scan skipped every offset at
  // which one of those samples fell in it, and the estimate could end in another minimum.
  const auto& r = reference.records;
  std::vector<std::pair<double, double>> gaps;
  for (size_t k = 1; k < r.size(); ++k) {
    if (IsGap(r[k - 1].time, r[k].time, max_gap_s)) gaps.emplace_back(r[k - 1].time, r[k].time);
  }
  std::vector<size_t> rows;
  const double first = r.front().time;
  const double last = r.back().time;
  for (size_t i = 0; i < samples.size(); ++i) {
    const double t = samples[i]->time;
    if (t + lo < first || t + hi > last) continue;
    // The first gap ending after t + lo must start after t + hi.
    const auto g = std::upper_bound(
        gaps.begin(), gaps.end(), t + lo,
        [](double v, const std::pair<double, double>& gap) { return v < gap.second; });
    if (g != gaps.end() && g->first <= t + hi) continue;
    if (!InterpolateReference(reference, t + lo, max_gap_s) ||
        !InterpolateReference(reference, t + hi, max_gap_s)) {
      continue;
    }
    rows.push_back(i);
  }
  return rows;
}

double MedianReferencePeriod(const ReferenceStream& reference) {
  std::vector<double> dt;
  for (size_t i = 1; i < reference.records.size(); ++i) {
    dt.push_back(reference.records[i].time - reference.records[i - 1].time);
  }
  std::nth_element(dt.begin(), dt.begin() + static_cast<long>(dt.size() / 2), dt.end());
  return dt[dt.size() / 2];
}

// The median spacing of the samples' times [s] (1 when none is positive).
double MedianSamplePeriod(const std::vector<const TrackerStreamSample*>& samples) {
  std::vector<double> dt;
  for (size_t i = 1; i < samples.size(); ++i) {
    const double d = samples[i]->time - samples[i - 1]->time;
    if (d > 0.0) dt.push_back(d);
  }
  if (dt.empty()) return 1.0;
  std::nth_element(dt.begin(), dt.begin() + static_cast<long>(dt.size() / 2), dt.end());
  return dt[dt.size() / 2];
}

// The Newey-West "meat" sum_ij w(|t_i - t_j|) s_i s_j^T of per-sample scores (rows of `score`, at
// the times of samples[rows[i]], in time order), with Bartlett weights over the time between the
// samples: w = 1 - |dt| / ((L + 1) period), L = floor(correlation_time_s / period), the median
// sample period; on an evenly sampled stream the usual lag-L window. The window was L neighbours
// in order, L from the mean rate over the whole span: a capture paused for 100 s halfway through
// 30 s shrank it to 13 neighbours (0.11 s), and neighbours across the pause or across a gap in the
// reference, seconds apart, were weighted as if 1/120 s apart.
Eigen::MatrixXd NeweyWestMeat(const Eigen::MatrixXd& score,
                              const std::vector<const TrackerStreamSample*>& samples,
                              const std::vector<size_t>& rows, double correlation_time_s) {
  const double period = MedianSamplePeriod(samples);
  const double window = (std::floor(correlation_time_s / period) + 1.0) * period;
  Eigen::MatrixXd meat = score.transpose() * score;
  const Eigen::Index n = score.rows();
  for (Eigen::Index i = 0; i < n; ++i) {
    const double ti = samples[rows[static_cast<size_t>(i)]]->time;
    for (Eigen::Index j = i + 1; j < n; ++j) {
      const double w = 1.0 - (samples[rows[static_cast<size_t>(j)]]->time - ti) / window;
      if (w <= 1e-9) break;
      for (Eigen::Index a = 0; a < score.cols(); ++a) {
        for (Eigen::Index b = 0; b < score.cols(); ++b) {
          meat(a, b) += w * (score(i, a) * score(j, b) + score(j, a) * score(i, b));
        }
      }
    }
  }
  return meat;
}

struct OffsetEstimate {
  double offset = 0.0;
  double stddev = 0.0;
  double cost = 0.0;
  int steps = 0;
  double variance_inflation = 1.0;  // of the offset against the error model, at the last step
  bool converged = false;           // the last step was below the tolerance
};

// Gauss-Newton on the offset jointly with the error model, from `start`.
OffsetEstimate RefineOffset(const std::vector<const TrackerStreamSample*>& samples,
                            const ReferenceStream& reference, const StreamPairingOptions& options,
                            double start) {
  const double h = 0.5 * MedianReferencePeriod(reference);
  OffsetEstimate est;
  est.offset = start;
  for (int step = 0; step < options.max_gauss_newton_steps; ++step) {
    const std::vector<size_t> rows =
        RowsCovering(samples, reference, est.offset - h, est.offset + h, options.max_gap_s);
    const Eigen::Index n = static_cast<Eigen::Index>(rows.size());
    if (n < 10)
      throw std::invalid_argument("stream pairing: too few paired samples to estimate the offset");
    Eigen::VectorXd d, before, after;
    Differences(samples, rows, reference, est.offset, options.max_gap_s, &d);
    Differences(samples, rows, reference, est.offset - h, options.max_gap_s, &before);
    Differences(samples, rows, reference, est.offset + h, options.max_gap_s, &after);
    // d(dt) ~ d(dt_k) - v (dt - dt_k), v the reference velocity: dd/d(dt) = (after - before) / 2h.
    const Eigen::VectorXd dd = (after - before) / (2.0 * h);
    const ErrorModel model(samples, rows, options);
    // Frisch-Waugh-Lovell: regress the model out of both, then one coefficient.
    const Eigen::VectorXd e0 = model.Residual(d);
    const Eigen::VectorXd g = model.Residual(dd);
    const double gg = g.squaredNorm();
    if (!(gg > 0.0))
      throw std::invalid_argument(
          "stream pairing: the reference does not move, so the offset is undetermined");
    const double delta = -g.dot(e0) / gg;
    const Eigen::VectorXd e = e0 + g * delta;
    est.cost = e.squaredNorm() / (3.0 * n);
    // Newey-West variance of delta from per-sample scores s_i = g_i . e_i.
    Eigen::MatrixXd score(n, 1);
    for (Eigen::Index i = 0; i < n; ++i) {
      score(i, 0) = g.segment<3>(3 * i).dot(e.segment<3>(3 * i));
    }
    const double s = NeweyWestMeat(score, samples, rows, options.correlation_time_s)(0, 0);
    est.stddev = std::sqrt(std::max(s, 0.0)) / gg;
    // H_tt (H^-1)_tt of the joint regression on [model, dd] (uncentred, as the fit engine's).
    est.variance_inflation = dd.squaredNorm() / gg;
    est.offset += delta;
    est.steps = step + 1;
    if (std::abs(delta) < options.tolerance) {
      est.converged = true;
      break;
    }
  }
  return est;
}

// The offset: a coarse scan (step 1/40 of the range) of the detrended residual variance, over the
// samples paired at every scanned offset so that all offsets are scored on the same data, then
// RefineOffset from its minimum.
OffsetEstimate EstimateOffset(const std::vector<const TrackerStreamSample*>& samples,
                              const ReferenceStream& reference,
                              const StreamPairingOptions& options) {
  const int steps = 80;
  const double lo = options.time_offset - options.search_range;
  const double step = 2.0 * options.search_range / steps;
  std::vector<size_t> rows =
      RowsCovering(samples, reference, lo, lo + 2.0 * options.search_range, options.max_gap_s);
  double best = options.time_offset;
  if (rows.size() >= 10) {
    const ErrorModel model(samples, rows, options);
    double best_cost = std::numeric_limits<double>::infinity();
    Eigen::VectorXd d;
    for (int i = 0; i <= steps; ++i) {
      const double o = lo + i * step;
      if (!Differences(samples, rows, reference, o, options.max_gap_s, &d)) continue;
      const double c = model.Residual(d).squaredNorm();
      if (c < best_cost) best_cost = c, best = o;
    }
  } else {
    // Streams overlapping less than the search range: score each offset on what pairs there.
    double best_cost = std::numeric_limits<double>::infinity();
    for (int i = 0; i <= steps; ++i) {
      const double o = lo + i * step;
      const double c = Pair(samples, reference, options, o).cost;
      if (c < best_cost) best_cost = c, best = o;
    }
  }
  return RefineOffset(samples, reference, options, best);
}

// How much of the curvature the offset's standard deviation assumes the data show: the
// detrended residual's rise from `offset` to offset +- delta (delta a whole number of reference
// periods, at least one and at least 3 standard deviations, so that the interpolation's noise
// pattern, periodic in the reference period, is the same at all three), over the rise the
// regression predicts, delta^2 |g|^2, g the detrended reference velocity. The velocity is a
// difference over one reference period, so the reference's noise enters g: with motion slow
// against that noise g is mostly noise, |g|^2 and so the information are overstated, and the rise
// the data show is a small part of the predicted one. NaN when too few samples cover the shifts.
struct Curvature {
  double delta = 0.0;  // [s]
  double ratio = std::numeric_limits<double>::quiet_NaN();
};
Curvature CurvatureRatio(const std::vector<const TrackerStreamSample*>& samples,
                         const ReferenceStream& reference, const StreamPairingOptions& options,
                         double offset, double stddev) {
  const double period = MedianReferencePeriod(reference);
  const double h = 0.5 * period;
  Curvature out;
  const double delta = period * std::max(1.0, std::ceil(3.0 * stddev / period));
  out.delta = delta;
  const std::vector<size_t> rows =
      RowsCovering(samples, reference, offset - delta - h, offset + delta + h, options.max_gap_s);
  if (rows.size() < 10) return out;
  const ErrorModel model(samples, rows, options);
  Eigen::VectorXd d, lo, hi, before, after;
  Differences(samples, rows, reference, offset, options.max_gap_s, &d);
  Differences(samples, rows, reference, offset - delta, options.max_gap_s, &lo);
  Differences(samples, rows, reference, offset + delta, options.max_gap_s, &hi);
  Differences(samples, rows, reference, offset - h, options.max_gap_s, &before);
  Differences(samples, rows, reference, offset + h, options.max_gap_s, &after);
  const double predicted =
      delta * delta * model.Residual((after - before) / (2.0 * h)).squaredNorm();
  const double c0 = model.Residual(d).squaredNorm();
  const double rise =
      0.5 * (model.Residual(lo).squaredNorm() + model.Residual(hi).squaredNorm()) - c0;
  if (predicted > 0.0) out.ratio = rise / predicted;
  return out;
}

// The clock drift: the reference clock's rate relative to the tracker's minus 1, estimated as
// RefineOffset estimates the offset but with a shift offset + rate (t - t_mid) per sample (t_mid
// the middle of the tracker stream), both refined by Gauss-Newton jointly with the error model,
// and a Newey-West covariance of the two from the same per-sample scores. NaN when too few
// samples pair.
struct DriftEstimate {
  double rate = std::numeric_limits<double>::quiet_NaN();
  double stddev = std::numeric_limits<double>::quiet_NaN();
  double span = 0.0;  // [s] of the tracker samples
  double origin = 0.0;  // [s] t_mid, the tracker time at which `offset` holds
  double offset = std::numeric_limits<double>::quiet_NaN();         // [s] refined with the rate
  double offset_stddev = std::numeric_limits<double>::quiet_NaN();  // [s] of `offset`, jointly
  double cost =
      std::numeric_limits<double>::quiet_NaN();  // residual variance [m^2], as the offset's
  // Of the rate against the error model and the offset (H_rr (H^-1)_rr, as the offset's).
  double variance_inflation = std::numeric_limits<double>::quiet_NaN();
};
DriftEstimate EstimateDrift(const std::vector<const TrackerStreamSample*>& samples,
                            const ReferenceStream& reference, const StreamPairingOptions& options,
                            double offset) {
  DriftEstimate out;
  if (samples.size() < 10) return out;
  const double h = 0.5 * MedianReferencePeriod(reference);
  const double first = samples.front()->time, last = samples.back()->time;
  out.span = last - first;
  if (!(out.span > 0.0)) return out;
  const double mid = 0.5 * (first + last);
  out.origin = mid;
  double rate = 0.0;
  for (int step = 0; step < options.max_gauss_newton_steps; ++step) {
    std::vector<size_t> rows;
    std::vector<Rigid3d> at, before, after;
    for (size_t i = 0; i < samples.size(); ++i) {
      const double t = samples[i]->time + offset + rate * (samples[i]->time - mid);
      auto a = InterpolateReference(reference, t, options.max_gap_s);
      auto b = InterpolateReference(reference, t - h, options.max_gap_s);
      auto c = InterpolateReference(reference, t + h, options.max_gap_s);
      if (!a || !b || !c) continue;
      rows.push_back(i);
      at.push_back(*a), before.push_back(*b), after.push_back(*c);
    }
    const Eigen::Index n = static_cast<Eigen::Index>(rows.size());
    if (n < 10) return DriftEstimate{};
    Eigen::VectorXd d(3 * n), dd(3 * n), ddt(3 * n);
    for (Eigen::Index r = 0; r < n; ++r) {
      const TrackerStreamSample& s = *samples[rows[r]];
      d.segment<3>(3 * r) = s.transmitter_from_receiver.translation - at[r].translation;
      const Eigen::Vector3d g = (before[r].translation - after[r].translation) / (2.0 * h);
      dd.segment<3>(3 * r) = g;
      ddt.segment<3>(3 * r) = g * (s.time - mid);
    }
    const ErrorModel model(samples, rows, options);
    const Eigen::VectorXd e0 = model.Residual(d);
    Eigen::MatrixXd g(3 * n, 2);
    g.col(0) = model.Residual(dd);
    g.col(1) = model.Residual(ddt);
    const Eigen::Matrix2d hessian = g.transpose() * g;
    if (!(hessian.determinant() > 0.0)) return DriftEstimate{};
    const Eigen::Matrix2d inverse = hessian.inverse();
    const Eigen::Vector2d delta = -inverse * (g.transpose() * e0);
    const Eigen::VectorXd e = e0 + g * delta;
    Eigen::MatrixXd score(n, 2);
    for (Eigen::Index i = 0; i < n; ++i) {
      score(i, 0) = g.col(0).segment<3>(3 * i).dot(e.segment<3>(3 * i));
      score(i, 1) = g.col(1).segment<3>(3 * i).dot(e.segment<3>(3 * i));
    }
    const Eigen::Matrix2d meat = NeweyWestMeat(score, samples, rows, options.correlation_time_s);
    const Eigen::Matrix2d covariance = inverse * meat * inverse;
    offset += delta[0];
    rate += delta[1];
    out.rate = rate;
    out.offset = offset;
    out.cost = e.squaredNorm() / (3.0 * static_cast<double>(n));
    out.stddev = std::sqrt(std::max(covariance(1, 1), 0.0));
    out.offset_stddev = std::sqrt(std::max(covariance(0, 0), 0.0));
    out.variance_inflation = ddt.squaredNorm() * inverse(1, 1);
    if (std::abs(delta[0]) < options.tolerance &&
        std::abs(delta[1]) * 0.5 * out.span < options.tolerance) {
      break;
    }
  }
  return out;
}

// Above it, the residual of an estimated offset is taken for poses of unrelated times (see
// PairStreams for the measurements).
constexpr double kMaxResidualToPathRatio = 0.1;
// Standard deviations of a drift estimate that are taken for drift.
constexpr double kDriftZ = 4.0;

// The RMS per component of the samples' reported positions about their mean [m].
double PathRms(const std::vector<const TrackerStreamSample*>& samples) {
  Eigen::Vector3d mean = Eigen::Vector3d::Zero();
  for (const TrackerStreamSample* s : samples) mean += s->transmitter_from_receiver.translation;
  mean /= static_cast<double>(samples.size());
  double sum2 = 0.0;
  for (const TrackerStreamSample* s : samples) {
    sum2 += (s->transmitter_from_receiver.translation - mean).squaredNorm();
  }
  return std::sqrt(sum2 / (3.0 * static_cast<double>(samples.size())));
}

std::string Rounded(double v, int precision) {
  std::ostringstream s;
  s.precision(precision);
  s << v;
  return s.str();
}

}  // namespace

nlohmann::json PairingJson(const StreamPairingResult& result, bool estimated,
                           const std::optional<std::filesystem::path>& output) {
  return {{"command", "pair"},
          {"output", output ? nlohmann::json(output->string()) : nlohmann::json()},
          {"num_poses", result.poses.records.size()},
          {"dropped", result.dropped},
          {"time_offset_s", result.time_offset},
          {"estimated", estimated},
          {"time_offset_stddev_s", result.time_offset_stddev},
          {"position_difference_variance_m2", result.cost},
          {"clock_drift", result.clock_drift},
          {"clock_drift_stddev", result.clock_drift_stddev},
          {"clock_drift_corrected", result.clock_drift_corrected},
          {"clock_drift_applied", result.clock_drift_applied},
          {"clock_drift_origin_s", result.clock_drift_origin},
          {"residual_to_path_ratio", result.residual_to_path_ratio},
          {"warning", result.warning}};
}

StreamPairingResult PairStreams(const TrackerStream& tracker, const ReferenceStream& reference,
                                const StreamPairingOptions& options) {
  std::string error;
  if (!options.Check(&error)) throw std::invalid_argument("stream pairing: " + error);
  if (tracker.records.size() < 2)
    throw std::invalid_argument("tracker stream has fewer than 2 samples");
  if (reference.records.size() < 2) {
    throw std::invalid_argument("reference stream has fewer than 2 samples");
  }
  for (size_t i = 1; i < reference.records.size(); ++i) {
    if (!(reference.records[i].time > reference.records[i - 1].time)) {
      throw std::invalid_argument("reference stream: time not strictly increasing at sample " +
                                  std::to_string(i + 1));
    }
  }
  // Not the first row's sensor: which receiver a live recording logs first changes from one
  // recording to the next, and the reference would be paired with another receiver.
  std::set<int> sensors;
  for (const TrackerStreamSample& r : tracker.records) sensors.insert(r.sensor);
  const int sensor = options.sensor != 0 ? options.sensor : *sensors.begin();
  std::string list;
  for (const int s : sensors) list += (list.empty() ? "" : ", ") + std::to_string(s);
  if (sensors.count(sensor) == 0) {
    throw std::invalid_argument("tracker stream has no sensor " + std::to_string(sensor) +
                                " (it has " + list + ")");
  }
  std::string sensor_note;
  if (options.sensor == 0 && sensors.size() > 1) {
    sensor_note = "the tracker stream has sensors " + list + "; paired sensor " +
                  std::to_string(sensor) +
                  " (the lowest) with the reference; choose another with trackcal-fit pair "
                  "--sensor N (Python: trackcal.pair(..., sensor=N))";
  }
  const std::vector<const TrackerStreamSample*> samples = SelectSamples(tracker, options, sensor);
  // Clocks with different epochs (a tracker in Unix seconds, ~1.7e9, a reference from 0) said only
  // "too few paired samples to estimate the offset" when estimating, or gave a bare offset when
  // not: the spans and the difference of their starts say what happened and what to give.
  const double tracker_first = samples.front()->time, tracker_last = samples.back()->time;
  const double reference_first = reference.records.front().time;
  const double reference_last = reference.records.back().time;
  const std::string spans =
      "the tracker stream's times run from " + Rounded(tracker_first, 15) + " to " +
      Rounded(tracker_last, 15) + " s, the reference stream's from " +
      Rounded(reference_first, 15) + " to " + Rounded(reference_last, 15) +
      " s; if the clocks count from different epochs, give the offset near the difference of "
      "their starts, " +
      Rounded(reference_first - tracker_first, 15) +
      " s (trackcal-fit pair --time-offset S; the model file's time_offset value; Python: "
      "trackcal.pair(..., time_offset=S))";
  if (options.estimate_time_offset &&
      (tracker_last + options.time_offset + options.search_range < reference_first ||
       tracker_first + options.time_offset - options.search_range > reference_last)) {
    throw std::invalid_argument(
        "stream pairing: the streams do not overlap at any searched "
        "clock offset (" +
        Rounded(options.time_offset, 15) + " +- " + Rounded(options.search_range, 6) +
        " s): " + spans);
  }
  double offset = options.time_offset;
  // Given: options' drift about the middle of the samples (EstimateDrift's t_mid).
  double rate = options.estimate_time_offset ? 0.0 : options.clock_drift;
  double origin = !options.estimate_time_offset && std::isfinite(options.clock_drift_origin)
                      ? options.clock_drift_origin
                      : 0.5 * (samples.front()->time + samples.back()->time);
  OffsetEstimate estimate;
  DriftEstimate drift;
  double residual_to_path_ratio = std::numeric_limits<double>::quiet_NaN();
  StreamPairingOptions used = options;
  std::string warning;
  if (options.estimate_time_offset) {
    estimate = EstimateOffset(samples, reference, used);
    // A model that can mimic a time shift along this path leaves the offset to its misfit, which
    // the Newey-West stddev takes for noise. Measured on the paper preset's streams, seeds 1-6:
    // 10 s, degree 3: variance inflation 122-135, errors 1.2-111 ms at a stated 0.09-0.13 ms
    // (|z| 11-1168); lowered to degree 1 (inflation 1.8-7.9): errors 1.6-16 ms at 1.3-6.3 ms
    // (|z| <= 3.4). 15 s: degree 3 at 14-105 (|z| up to 23) goes to degree 2 (|z| <= 3.7). 20 s
    // (4.7-9.3), 30 s (1.8-2.4) and 60 s keep degree 3 and their estimates.
    const double first_inflation = estimate.variance_inflation;
    while (estimate.variance_inflation > used.max_variance_inflation && used.detrend_degree > 0) {
      --used.detrend_degree;
      estimate = EstimateOffset(samples, reference, used);
    }
    offset = estimate.offset;
    const std::string limit = Rounded(used.max_variance_inflation, 3);
    if (estimate.variance_inflation > used.max_variance_inflation) {
      warning = "the clock offset is not determined by these streams: along their path even a "
                "degree-" + std::to_string(used.detrend_degree) +
                " error model can mimic a time shift (variance inflation " +
                Rounded(estimate.variance_inflation, 3) + " > " + limit +
                "); give the offset, or record a longer stream that passes the same places at "
                "other velocities";
    } else if (used.detrend_degree != options.detrend_degree) {
      warning = "the clock offset is poorly identified with a degree-" +
                std::to_string(options.detrend_degree) +
                " error model, which can mimic a time shift along this path (variance inflation " +
                Rounded(first_inflation, 3) + " > " + limit + "); estimated with degree " +
                std::to_string(used.detrend_degree) + " instead (variance inflation " +
                Rounded(estimate.variance_inflation, 3) +
                "), which leaves more of the tracker's error in it; a longer stream that passes the "
                "same places at other velocities identifies it";
    }
    if (std::abs(offset - options.time_offset) > options.search_range) {
      // The refinement went beyond the scanned offsets: the true one there, or another minimum
      // of a periodic path (one occlusion once sent 300 ms to -553.7 ms).
      warning += std::string(warning.empty() ? "" : "; ") + "the estimated clock offset " +
                 Rounded(1e3 * offset, 6) + " ms lies outside the searched " +
                 Rounded(1e3 * options.time_offset, 6) + " +- " +
                 Rounded(1e3 * options.search_range, 6) +
                 " ms: the refinement left the scan's range; check it, or search a range that "
                 "holds it (trackcal-fit pair --search-range S; the model file's time_offset "
                 "search_range; Python: trackcal.pair(..., search_range=S))";
    }
    // Measured on the paper preset's streams (10-30 s, seeds 1-4, with drift or gaps): 0.95-0.99.
    // Waving slowly (amplitudes 2 mm-0.2 m over periods of 20-30 s, 0.3 mm reference noise):
    // 0.002-0.006, with offsets 190-360 ms off (truth 37 ms) at a stated 0.013 ms and no warning.
    const Curvature curvature =
        CurvatureRatio(samples, reference, used, estimate.offset, estimate.stddev);
    if (curvature.ratio < 0.5) {
      warning += std::string(warning.empty() ? "" : "; ") +
                 "the clock offset is not determined by these streams: shifting it by " +
                 Rounded(1e3 * curvature.delta, 3) + " ms raises the residual by only " +
                 Rounded(100.0 * std::max(curvature.ratio, 0.0), 2) +
                 "% of what its standard deviation assumes, so the reference's velocity is "
                 "mostly its noise (motion too slow) or the error model follows the shift; "
                 "give the offset, or record faster motion that passes the same places at "
                 "other velocities";
    }
    if (!estimate.converged) {
      warning += std::string(warning.empty() ? "" : "; ") +
                 "the clock offset's refinement did not converge in " +
                 std::to_string(estimate.steps) + " Gauss-Newton steps";
    }
    // Whether the offset pairs the streams at all. With the true offset outside the searched range
    // (-2.963 s against the default 0 +- 0.5 s) the best scanned offset pairs poses of unrelated
    // times, and the pairing gave +309 +- 38 ms without a word. The position difference the error
    // model leaves is then a fair part of the path's own spread. Measured against the per-component
    // RMS spread of the reported positions, on the paper preset's streams, seeds 1-6: with the
    // true offset in range 0.26-0.40% (20-60 s), 0.21-0.56% (15 s), 1.9-2.3% (10 s, degree 1),
    // 0.7% waving 5 cm; with it 3 s outside the search 26-39%.
    const double residual_rms = std::sqrt(estimate.cost);
    const double path_rms = PathRms(samples);
    residual_to_path_ratio = residual_rms / path_rms;
    if (residual_to_path_ratio > kMaxResidualToPathRatio) {
      warning = "no clock offset in the searched " + Rounded(1e3 * options.time_offset, 6) +
                " +- " + Rounded(1e3 * options.search_range, 6) +
                " ms pairs the streams: at the best one, " + Rounded(1e3 * offset, 6) +
                " ms, the position difference left by the error model is " +
                Rounded(1e3 * residual_rms, 3) + " mm RMS, " +
                Rounded(100.0 * residual_to_path_ratio, 2) + "% of the path's own spread (" +
                Rounded(1e3 * path_rms, 3) +
                " mm RMS), as between poses of unrelated times (under 3% when the offset pairs "
                "them); the offset is likely outside the searched range: search a wider one "
                "(trackcal-fit pair --search-range S; the model file's time_offset search_range; "
                "Python: trackcal.pair(..., search_range=S)) or give it" +
                (warning.empty() ? "" : "; " + warning);
    }
    // Drifting clocks: one offset pairs the middle of the stream and is off by half the drift at
    // its ends (a lab's 10 min at 100 ppm: +-30 ms). Only of an offset the streams determine (no
    // warning above) and a rate the error model cannot mimic. Measured on the paper preset's
    // streams, seeds 1-6: 20, 30 and 60 s without drift |z| <= 2.9, 1.9, 1.6 (15 s: 9.7 at a
    // variance inflation of 92, the others lowered the degree); reference clock 1000 ppm fast
    // over 30 s: 926-1061 ppm, z 17-49; 100 ppm: 26-161 ppm, z 0.5-5.0.
    drift = EstimateDrift(samples, reference, used, offset);
    if (warning.empty() && drift.variance_inflation <= used.max_variance_inflation &&
        std::abs(drift.rate) > kDriftZ * drift.stddev) {
      const double over_stream = drift.rate * drift.span;
      const std::string drifting = "the clocks drift: the clock offset changes by " +
                                   Rounded(1e3 * 60.0 * drift.rate, 3) + " ms per minute (" +
                                   Rounded(1e6 * drift.rate, 4) + " +- " +
                                   Rounded(1e6 * drift.stddev, 2) + " ppm, the reference clock " +
                                   (drift.rate > 0.0 ? "fast" : "slow") +
                                   " against the tracker's), " + Rounded(1e3 * over_stream, 3) +
                                   " ms over the stream's " + Rounded(drift.span, 4) + " s; ";
      if (options.correct_clock_drift && std::isfinite(drift.offset)) {
        // Paired with the drift: one offset left the stream's ends half the drift off (100 ppm
        // over 10 min: 30 ms; see stream_pairing_sim_test's measurements).
        offset = drift.offset;
        rate = drift.rate;
        origin = drift.origin;
        warning =
            drifting + "corrected: each tracker sample at t is paired with the reference at t + " +
            Rounded(1e3 * offset, 6) + " ms + " + Rounded(1e6 * drift.rate, 4) + " ppm * (t - " +
            Rounded(origin, 10) + " s); synchronise the clocks to avoid relying on it";
      } else {
        warning = drifting + "the offset " + Rounded(1e3 * offset, 6) +
                  " ms pairs its middle, and its ends " +
                  Rounded(1e3 * 0.5 * std::abs(over_stream), 3) +
                  " ms off; synchronise the clocks, or correct the reference stream's times for "
                  "the drift (t -> t0 + (t - t0) / (1 + " +
                  Rounded(drift.rate, 4) + ")) and pair again, or pair shorter streams";
      }
    }
  }
  StreamPairingResult result = Pair(samples, reference, options, offset, rate, origin);
  if (result.poses.records.empty()) {
    throw std::invalid_argument("stream pairing: no tracker sample has a reference at offset " +
                                Rounded(offset, 15) +
                                " s (do the streams overlap in time?): " + spans);
  }
  const double h = 0.5 * MedianReferencePeriod(reference);
  for (const PoseRecord& r : result.poses.records) {
    const double t = r.time + offset + rate * (r.time - origin);
    const auto before = InterpolateReference(reference, t - h, options.max_gap_s);
    const auto after = InterpolateReference(reference, t + h, options.max_gap_s);
    Eigen::Vector3d v = Eigen::Vector3d::Zero(), w = Eigen::Vector3d::Zero();
    if (before && after) {
      v = (after->translation - before->translation) / (2.0 * h);
      w = RotationVectorBetween<double>(after->rotation, before->rotation) / (2.0 * h);
    }
    result.reference_velocity.push_back(v);
    result.reference_angular_velocity.push_back(w);
  }
  if (options.estimate_time_offset) {
    result.cost = rate != 0.0 ? drift.cost : estimate.cost;
    result.clock_drift_corrected = rate != 0.0;
    // Of the offset paired with: at t_mid, jointly with the drift, when it is corrected.
    result.time_offset_stddev = rate != 0.0 ? drift.offset_stddev : estimate.stddev;
    result.gauss_newton_steps = estimate.steps;
    result.detrend_degree = used.detrend_degree;
    result.time_offset_variance_inflation = estimate.variance_inflation;
    result.clock_drift = drift.rate;
    result.clock_drift_stddev = drift.stddev;
    result.clock_drift_variance_inflation = drift.variance_inflation;
    result.residual_to_path_ratio = residual_to_path_ratio;
    result.warning = warning;
  }
  if (!sensor_note.empty()) {
    result.warning = sensor_note + (result.warning.empty() ? "" : "; " + result.warning);
  }
  return result;
}

StreamPairingResult PairStreamsOfFiles(const TrackerStream& tracker,
                                       const ReferenceStream& reference,
                                       const StreamPairingOptions& options,
                                       const std::filesystem::path& tracker_path,
                                       const std::filesystem::path& reference_path) {
  try {
    return PairStreams(tracker, reference, options);
  } catch (const std::invalid_argument& e) {
    throw std::invalid_argument(tracker_path.string() + ", " + reference_path.string() + ": " +
                                e.what());
  }
}

std::vector<FitStation> FitStationsOfPairing(const StreamPairingResult& result,
                                             const std::string& set) {
  std::vector<FitStation> out;
  for (size_t i = 0; i < result.poses.records.size(); ++i) {
    const PoseRecord& p = result.poses.records[i];
    if (!set.empty() && p.set != set) continue;
    FitStation s{p.reported, p.reference, p.time, p.sensor, p.station};
    s.reference_velocity = result.reference_velocity[i];
    s.reference_angular_velocity = result.reference_angular_velocity[i];
    out.push_back(s);
  }
  return out;
}

}  // namespace trackcal::fit
