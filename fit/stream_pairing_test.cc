#include "fit/stream_pairing.h"

#include <gtest/gtest.h>

#include <cmath>

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

void MakeStreams(double offset, TrackerStream* tracker, ReferenceStream* reference) {
  for (int i = 0; i < 30 * 120; ++i) {  // 30 s at 120 Hz, tracker clock = true time
    TrackerStreamSample s;
    s.time = i / 120.0;
    s.transmitter_from_receiver = TrueAt(s.time);
    s.transmitter_from_receiver.translation += Eigen::Vector3d(0.01, -0.005, 0.002);  // distortion
    tracker->records.push_back(s);
  }
  for (int i = 0; i < 30 * 100; ++i) {  // 100 Hz, reference clock = true time + offset
    ReferenceStreamSample s;
    const double t_true = i / 100.0 - 0.2;
    s.time = t_true + offset;
    s.transmitter_from_body = TrueAt(t_true);
    reference->records.push_back(s);
  }
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

}  // namespace
}  // namespace trackcal::fit
