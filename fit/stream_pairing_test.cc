#include "fit/stream_pairing.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <cmath>
#include <functional>
#include <iostream>
#include <limits>

namespace trackcal::fit {
namespace {

// A smooth trajectory (true pose at true time t) sampled by both clocks.
Rigid3d TrueAt(double t) {
  const Eigen::Vector3d p(0.5 * std::sin(2 * M_PI * t / 7), 0.4 * std::sin(2 * M_PI * t / 5 + 1),
                          -0.4 + 0.2 * std::sin(2 * M_PI * t / 11));
  const Eigen::Quaterniond q(Eigen::AngleAxisd(0.8 * std::sin(2 * M_PI * t / 6),
                                               Eigen::Vector3d(1, 2, 3).normalized()));
  return Rigid3d(q, p);
}

// A constant tracker error.
Eigen::Vector3d ConstantDistortion(const Eigen::Vector3d&) {
  return Eigen::Vector3d(0.01, -0.005, 0.002);
}

// A smooth tracker error of ~5 mm (the paper preset's uncorrected error: 6.8 mm mean) that a
// degree-3 polynomial in the position does not represent.
Eigen::Vector3d FieldDistortion(const Eigen::Vector3d& p) {
  return 0.005 * Eigen::Vector3d(std::sin(4 * p.y() + 1), std::cos(4 * p.z() + 2.8 * p.x()),
                                 std::sin(3.2 * p.x() - 4 * p.y()));
}

void MakeStreams(double offset, TrackerStream* tracker, ReferenceStream* reference,
                 double duration_s = 30.0,
                 const std::function<Eigen::Vector3d(const Eigen::Vector3d&)>& distortion =
                     ConstantDistortion) {
  const int tracker_samples = static_cast<int>(std::lround(duration_s * 120));
  for (int i = 0; i < tracker_samples; ++i) {  // 120 Hz, tracker clock = true time
    TrackerStreamSample s;
    s.time = i / 120.0;
    s.transmitter_from_receiver = TrueAt(s.time);
    s.transmitter_from_receiver.translation += distortion(s.transmitter_from_receiver.translation);
    tracker->records.push_back(s);
  }
  const int reference_samples = static_cast<int>(std::lround(duration_s * 100));
  for (int i = 0; i < reference_samples; ++i) {  // 100 Hz, reference clock = true time + offset
    ReferenceStreamSample s;
    const double t_true = i / 100.0 - 0.2;
    s.time = t_true + offset;
    s.transmitter_from_body = TrueAt(t_true);
    reference->records.push_back(s);
  }
}

TEST(StreamPairingOptions, CheckRefusesWhatTheScanCannotUse) {
  std::string error;
  EXPECT_TRUE(StreamPairingOptions{}.Check(&error)) << error;
  StreamPairingOptions o;
  o.search_range = std::numeric_limits<double>::infinity();  // gave NaN offsets
  EXPECT_FALSE(o.Check(&error));
  EXPECT_EQ(error, "search_range must be a finite number > 0");
  o = {};
  o.tolerance = std::numeric_limits<double>::infinity();
  EXPECT_FALSE(o.Check(&error));
  EXPECT_EQ(error, "tolerance must be a finite number > 0");
  o = {};
  o.search_range = 0.0;
  EXPECT_FALSE(o.Check(&error));
}

TEST(PairStreams, Nominal_RecoversKnownClockOffset) {
  TrackerStream tracker;
  ReferenceStream reference;
  MakeStreams(0.037, &tracker, &reference);
  StreamPairingOptions options;
  options.estimate_time_offset = true;
  const StreamPairingResult result = PairStreams(tracker, reference, options);
  // Linear interpolation at 100 Hz of a ~1 m/s trajectory biases the cost minimum by well under 1 ms.
  EXPECT_NEAR(result.time_offset, 0.037, 5e-4);
  ASSERT_GT(result.poses.records.size(), 3000u);
  // Paired with the estimated offset, the reference matches the true pose to interpolation error.
  for (const auto& r : result.poses.records) {
    EXPECT_LT(PositionErrorNorm(r.reference, TrueAt(r.time)), 2e-3);
  }
}

TEST(PairStreams, AnOffsetOutsideTheSearchRangeIsWarnedAbout) {
  TrackerStream tracker;
  ReferenceStream reference;
  MakeStreams(0.3, &tracker, &reference);
  StreamPairingOptions options;
  options.estimate_time_offset = true;
  options.search_range = 0.1;
  const StreamPairingResult result = PairStreams(tracker, reference, options);
  // Here the refinement found the true offset beyond the scan; it is kept, and said.
  EXPECT_NEAR(result.time_offset, 0.3, 5e-4);
  EXPECT_THAT(result.warning, ::testing::HasSubstr("the estimated clock offset 300"));
  EXPECT_THAT(result.warning, ::testing::HasSubstr("ms lies outside the searched 0 +- 100 ms"));
  options.search_range = 0.5;  // holds it: no word
  EXPECT_EQ(PairStreams(tracker, reference, options).warning, "");
}

TEST(PairStreams, ClocksWithDifferentEpochsAreRefusedWithTheirStarts) {
  // A tracker stamping Unix seconds and a reference counting from 0: the estimate said only "too
  // few paired samples to estimate the offset", a given offset "(do the streams overlap in
  // time?)"; neither said the starts differ by 1.7e9 s nor what to give.
  TrackerStream tracker;
  ReferenceStream reference;
  MakeStreams(0.0, &tracker, &reference, 10.0);
  for (TrackerStreamSample& s : tracker.records) s.time += 1.7e9;
  StreamPairingOptions options;
  options.estimate_time_offset = true;
  for (const bool estimate : {true, false}) {
    options.estimate_time_offset = estimate;
    try {
      PairStreams(tracker, reference, options);
      ADD_FAILURE() << "paired streams 1.7e9 s apart";
    } catch (const std::invalid_argument& e) {
      EXPECT_THAT(e.what(), ::testing::HasSubstr("from 1700000000 to 1700000009.99167 s"));
      EXPECT_THAT(e.what(), ::testing::HasSubstr("different epochs"));
      EXPECT_THAT(e.what(), ::testing::HasSubstr("-1700000000.2 s"));
    }
  }
  // The hint's offset pairs them (tracker times of 1.7e9 s have an ulp of 2.4e-7 s).
  options.estimate_time_offset = true;
  options.time_offset = -1700000000.2;
  const StreamPairingResult r = PairStreams(tracker, reference, options);
  EXPECT_NEAR(r.time_offset, -1.7e9, 1e-5);
}

TEST(PairStreams, GivenOffsetAndInterpolation) {
  TrackerStream tracker;
  ReferenceStream reference;
  MakeStreams(0.037, &tracker, &reference);
  StreamPairingOptions options;
  options.time_offset = 0.037;
  const StreamPairingResult result = PairStreams(tracker, reference, options);
  EXPECT_DOUBLE_EQ(result.time_offset, 0.037);
  EXPECT_GT(result.dropped, 0);  // the tracker stream outlasts the reference stream
  const auto mid = InterpolateReference(reference, reference.records[10].time, 0.1);
  ASSERT_TRUE(mid.has_value());
  EXPECT_LT(PositionErrorNorm(*mid, reference.records[10].transmitter_from_body), 1e-12);
  EXPECT_FALSE(InterpolateReference(reference, -10.0, 0.1).has_value());
  options.decimate = 0;
  EXPECT_THROW(PairStreams(tracker, reference, options), std::invalid_argument);
}

TEST(PairStreams, AReferenceSpacedAtTheGapLimitIsInterpolated) {
  // A 10 Hz reference (times i * 0.1 on a clock far from zero) against max_gap_s 0.1: its steps
  // differ from 0.1 by rounding only, and about half the tracker samples were dropped as in a gap.
  TrackerStream tracker;
  ReferenceStream reference;
  for (int i = 0; i < 3000; ++i) {
    ReferenceStreamSample s;
    s.time = 1000.3 + i * 0.1;
    s.transmitter_from_body = TrueAt(i * 0.1);
    reference.records.push_back(s);
  }
  for (int i = 0; i < 3500; ++i) {  // 12 Hz, inside the reference's span
    TrackerStreamSample s;
    s.time = 1000.35 + i / 12.0;
    s.transmitter_from_receiver = TrueAt(s.time - 1000.3);
    tracker.records.push_back(s);
  }
  StreamPairingOptions options;  // max_gap_s 0.1, offset 0 given
  const StreamPairingResult result = PairStreams(tracker, reference, options);
  EXPECT_EQ(result.dropped, 0);
  // A real gap (a step of twice the spacing) is still not interpolated across.
  reference.records.erase(reference.records.begin() + 100);
  EXPECT_GT(PairStreams(tracker, reference, options).dropped, 0);
}

// The same on a Unix-epoch clock (1.7e9 s, where a double's ulp is 2.4e-7 s): the steps between
// the printed times differ from 0.1 by up to an ulp of the times, far above the relative 1e-9 of
// the limit that was allowed, and 1750 of the 3500 tracker samples were dropped as in a gap.
TEST(PairStreams, AReferenceSpacedAtTheGapLimitIsInterpolatedOnAnEpochClock) {
  const double epoch = 1.7e9;
  TrackerStream tracker;
  ReferenceStream reference;
  for (int i = 0; i < 3000; ++i) {
    ReferenceStreamSample s;
    s.time = epoch + i * 0.1;
    s.transmitter_from_body = TrueAt(i * 0.1);
    reference.records.push_back(s);
  }
  for (int i = 0; i < 3500; ++i) {  // 12 Hz, inside the reference's span
    TrackerStreamSample s;
    s.time = epoch + 0.05 + i / 12.0;
    s.transmitter_from_receiver = TrueAt(s.time - epoch);
    tracker.records.push_back(s);
  }
  StreamPairingOptions options;  // max_gap_s 0.1, offset 0 given
  const StreamPairingResult result = PairStreams(tracker, reference, options);
  EXPECT_EQ(result.dropped, 0);
  // Interpolated, not merely kept: linear interpolation of this path at 10 Hz is off by < 1 mm.
  for (const auto& r : result.poses.records) {
    EXPECT_LT(PositionErrorNorm(r.reference, TrueAt(r.time - epoch)), 1e-3);
  }
  // A real gap (a step of twice the spacing) is still not interpolated across: the tracker
  // samples in it (0.2 s at 12 Hz: 2 or 3) are dropped.
  reference.records.erase(reference.records.begin() + 100);
  const int dropped = PairStreams(tracker, reference, options).dropped;
  EXPECT_GE(dropped, 2);
  EXPECT_LE(dropped, 3);
}

// A path that repeats within the search range (periods 0.9, 1.3 and 2.1 s), on which Gauss-Newton
// alone, from the search centre, finds another minimum: the coarse scan must find the basin.
Rigid3d FastAt(double t) {
  const Eigen::Vector3d p(0.3 * std::sin(2 * M_PI * t / 0.9),
                          0.3 * std::sin(2 * M_PI * t / 1.3 + 1),
                          -0.4 + 0.1 * std::sin(2 * M_PI * t / 2.1));
  return Rigid3d(TrueAt(t).rotation, p);
}

// One occlusion of the reference longer than max_gap_s (0.3 s, 30 samples at 100 Hz). The coarse
// scan's samples were checked for a reference at the window's ends and centre only, so every other
// scanned offset at which one of them fell in the gap was skipped, and Gauss-Newton from the best
// of the rest ended at -553.7 +- 1.5 ms (truth 300 ms; -300 ms gave +555.9), outside the search
// range, without a warning. Without the gap: 300.000 +- 0.0003 ms.
TEST(PairStreams, AGapInTheReferenceDoesNotHideTheOffsetFromTheScan) {
  for (const double truth : {0.3, -0.3}) {
    TrackerStream tracker;
    ReferenceStream reference;
    for (int i = 0; i < 3600; ++i) {  // 30 s at 120 Hz
      TrackerStreamSample s;
      s.time = i / 120.0;
      s.transmitter_from_receiver = FastAt(s.time);
      s.transmitter_from_receiver.translation +=
          FieldDistortion(s.transmitter_from_receiver.translation);
      tracker.records.push_back(s);
    }
    for (int i = 0; i < 3000; ++i) {  // 100 Hz, with samples 1500-1529 missing
      if (i >= 1500 && i < 1530) continue;
      ReferenceStreamSample s;
      const double t_true = i / 100.0 - 0.2;
      s.time = t_true + truth;
      s.transmitter_from_body = FastAt(t_true);
      reference.records.push_back(s);
    }
    StreamPairingOptions options;
    options.estimate_time_offset = true;
    const StreamPairingResult result = PairStreams(tracker, reference, options);
    // The error model and noise-free streams leave ~0.3 us of stddev; 0.1 ms is far from any
    // other minimum (the path's shortest period is 0.9 s) and still tight.
    EXPECT_NEAR(result.time_offset, truth, 1e-4) << "truth " << truth;
    EXPECT_EQ(result.warning, "");
  }
}

// The tracker stream's reader does not require increasing times, and the offset's standard
// deviation read the samples as a time series in stream order: the same samples in reverse order
// gave the same offset at a stddev of 0.0054 ms instead of 0.033 ms (a Newey-West window over
// every sample, from a rate of (n - 1) / 1e-9 when the last sample is the earliest).
TEST(PairStreams, TheResultDoesNotDependOnTheTrackerStreamsOrder) {
  TrackerStream tracker;
  ReferenceStream reference;
  MakeStreams(0.037, &tracker, &reference, 30.0, FieldDistortion);
  StreamPairingOptions options;
  options.estimate_time_offset = true;
  const StreamPairingResult ordered = PairStreams(tracker, reference, options);
  std::reverse(tracker.records.begin(), tracker.records.end());
  const StreamPairingResult reversed = PairStreams(tracker, reference, options);
  // The same samples in the same (time) order give the same numbers to the bit.
  EXPECT_EQ(reversed.time_offset, ordered.time_offset);
  EXPECT_EQ(reversed.time_offset_stddev, ordered.time_offset_stddev);
  ASSERT_EQ(reversed.poses.records.size(), ordered.poses.records.size());
  for (size_t i = 0; i < ordered.poses.records.size(); ++i) {
    EXPECT_EQ(reversed.poses.records[i].time, ordered.poses.records[i].time);
  }
}

// A live recording of two receivers logs whichever reported first; pairing the first row's sensor
// paired the reference with receiver 2 in one recording and receiver 1 in the next.
TEST(PairStreams, TwoReceiversPairTheLowestSensorWhateverCameFirst) {
  TrackerStream one;
  ReferenceStream reference;
  MakeStreams(0.0, &one, &reference, 5.0);
  TrackerStream both;
  for (const TrackerStreamSample& s : one.records) {
    TrackerStreamSample other = s;  // receiver 2, 0.3 m away, logged first
    other.sensor = 2;
    other.transmitter_from_receiver.translation.x() += 0.3;
    both.records.push_back(other);
    both.records.push_back(s);
    both.records.back().sensor = 1;
  }
  StreamPairingOptions options;
  const StreamPairingResult lowest = PairStreams(both, reference, options);
  ASSERT_GT(lowest.poses.records.size(), 400u);
  for (const auto& r : lowest.poses.records) EXPECT_EQ(r.sensor, 1);
  EXPECT_THAT(lowest.warning, ::testing::HasSubstr("sensors 1, 2; paired sensor 1"));
  options.sensor = 2;
  const StreamPairingResult chosen = PairStreams(both, reference, options);
  for (const auto& r : chosen.poses.records) EXPECT_EQ(r.sensor, 2);
  EXPECT_EQ(chosen.warning, "");  // chosen, so nothing to say
  options.sensor = 3;
  try {
    PairStreams(both, reference, options);
    ADD_FAILURE() << "sensor 3 is not in the stream";
  } catch (const std::invalid_argument& e) {
    EXPECT_STREQ(e.what(), "tracker stream has no sensor 3 (it has 1, 2)");
  }
}

// On a 10 s stream the path does not pass the same places at other velocities, so a degree-3
// error model in the reported position can mimic a time shift (variance inflation 5.0e4 here), and
// the offset followed the model's misfit: 12.1 +- 5.1 ms before the variance-inflation check
// (truth 37 ms, z = -4.9). With it the degree is lowered to 1 (inflation 5.1): 37.7 +- 1.3 ms.
// The 5 ms tolerance is ~4 of those stddevs and a fifth of the old error. The 30 s stream keeps
// degree 3 (inflation 3.0, 37.0 +- 0.03 ms) and warns of nothing.
TEST(PairStreams, APauseInTheCaptureDoesNotShrinkTheOffsetsStandardDeviation) {
  // The same samples with the capture paused for 100 s halfway (both streams' second halves 100 s
  // later): the pairs and the error model's misfit are the same, so is the offset's standard
  // deviation. Its Newey-West window was correlation_time_s times the mean rate over the whole
  // span, pause included, so it covered 13 samples (0.11 s) instead of 60 and the standard
  // deviation came out smaller.
  TrackerStream tracker, paused_tracker;
  ReferenceStream reference, paused_reference;
  MakeStreams(0.037, &tracker, &reference, 30.0, FieldDistortion);
  paused_tracker = tracker;
  paused_reference = reference;
  const double split = 15.0, pause = 100.0;  // true (tracker) time
  for (TrackerStreamSample& s : paused_tracker.records) {
    if (s.time >= split) s.time += pause;
  }
  for (ReferenceStreamSample& s : paused_reference.records) {
    if (s.time - 0.037 >= split) s.time += pause;
  }
  StreamPairingOptions options;
  options.estimate_time_offset = true;
  const StreamPairingResult a = PairStreams(tracker, reference, options);
  const StreamPairingResult b = PairStreams(paused_tracker, paused_reference, options);
  std::cout << "continuous: " << 1e3 * a.time_offset << " +- " << 1e3 * a.time_offset_stddev
            << " ms; paused: " << 1e3 * b.time_offset << " +- " << 1e3 * b.time_offset_stddev
            << " ms\n";
  EXPECT_NEAR(b.time_offset, a.time_offset, 0.1 * a.time_offset_stddev);
  // The few samples next to the pause that pair in one and not the other, and the window's terms
  // across the join of the continuous one: a few percent.
  EXPECT_NEAR(b.time_offset_stddev / a.time_offset_stddev, 1.0, 0.05);
}

TEST(PairStreams, ShortPath_AnErrorModelThatMimicsATimeShiftIsLowered) {
  StreamPairingOptions options;
  options.estimate_time_offset = true;
  TrackerStream tracker;
  ReferenceStream reference;
  MakeStreams(0.037, &tracker, &reference, 10.0, FieldDistortion);
  const StreamPairingResult short_path = PairStreams(tracker, reference, options);
  std::cout << "10 s: " << short_path.time_offset * 1e3 << " +- "
            << short_path.time_offset_stddev * 1e3 << " ms, degree " << short_path.detrend_degree
            << ", inflation " << short_path.time_offset_variance_inflation << "\n";
  EXPECT_NEAR(short_path.time_offset, 0.037, 5e-3);
  EXPECT_LT(short_path.detrend_degree, options.detrend_degree);
  EXPECT_LE(short_path.time_offset_variance_inflation, options.max_variance_inflation);
  EXPECT_THAT(short_path.warning, ::testing::HasSubstr("poorly identified with a degree-3"));

  TrackerStream long_tracker;
  ReferenceStream long_reference;
  MakeStreams(0.037, &long_tracker, &long_reference, 30.0, FieldDistortion);
  const StreamPairingResult long_path = PairStreams(long_tracker, long_reference, options);
  EXPECT_NEAR(long_path.time_offset, 0.037, 5e-4);
  EXPECT_EQ(long_path.detrend_degree, 3);
  EXPECT_LE(long_path.time_offset_variance_inflation, options.max_variance_inflation);
  EXPECT_EQ(long_path.warning, "");

  // With no limit the old estimate comes back, with a stddev that does not cover its error.
  options.max_variance_inflation = std::numeric_limits<double>::infinity();
  const StreamPairingResult unchecked = PairStreams(tracker, reference, options);
  std::cout << "10 s unchecked: " << unchecked.time_offset * 1e3 << " +- "
            << unchecked.time_offset_stddev * 1e3 << " ms, inflation "
            << unchecked.time_offset_variance_inflation << "\n";
  EXPECT_EQ(unchecked.detrend_degree, 3);
  EXPECT_GT(unchecked.time_offset_variance_inflation, 1e3);
  EXPECT_GT(std::abs(unchecked.time_offset - 0.037), 3.0 * unchecked.time_offset_stddev);
  options.max_variance_inflation = 0.5;
  EXPECT_THROW(PairStreams(tracker, reference, options), std::invalid_argument);
}

}  // namespace
}  // namespace trackcal::fit
