#include "vrpn_server/fastrak/message_limiter.h"

#include <gtest/gtest.h>

namespace trackcal::fastrak {
namespace {

using Clock = MessageLimiter::Clock;
using std::chrono::milliseconds;

TEST(MessageLimiter, Nominal) {
  MessageLimiter limiter(milliseconds(1000));
  const Clock::time_point t0{};
  ASSERT_TRUE(limiter.Submit({Severity::kInfo, "a"}, t0).has_value());
  EXPECT_FALSE(limiter.NextDeadline().has_value());
  const auto b = limiter.Submit({Severity::kInfo, "b"}, t0 + milliseconds(1000));
  ASSERT_TRUE(b.has_value());
  EXPECT_EQ(b->text, "b");
  EXPECT_EQ(limiter.suppressed(), 0u);
}

TEST(MessageLimiter, AtMostOnePerIntervalAndTheLatestStateGetsThrough) {
  MessageLimiter limiter(milliseconds(1000));
  const Clock::time_point t0{};
  std::vector<std::pair<Clock::time_point, DriverMessage>> emitted;
  auto take = [&](std::optional<DriverMessage> m, Clock::time_point t) {
    if (m) emitted.emplace_back(t, *m);
  };
  // 430 failed opens per second for 5 s, as the reference did after an unplug.
  for (int i = 0; i < 2150; ++i) {
    const Clock::time_point t = t0 + std::chrono::microseconds(i * 2326);
    take(limiter.Submit({Severity::kError, "cannot open " + std::to_string(i)}, t), t);
    take(limiter.Poll(t), t);
  }
  const Clock::time_point end = t0 + milliseconds(5000);
  take(limiter.Submit({Severity::kInfo, "reset completed"}, end), end);
  for (int ms = 5000; ms <= 7000; ms += 10) {
    take(limiter.Poll(t0 + milliseconds(ms)), t0 + milliseconds(ms));
  }
  ASSERT_GE(emitted.size(), 2u);
  EXPECT_LE(emitted.size(), 7u);  // one per second over 5 s, plus the final state
  for (size_t i = 1; i < emitted.size(); ++i) {
    EXPECT_GE(emitted[i].first - emitted[i - 1].first, milliseconds(1000));
  }
  // The last state is delivered within one interval, with the most severe level it replaced.
  EXPECT_EQ(emitted.back().second.text.rfind("reset completed", 0), 0u);
  EXPECT_NE(emitted.back().second.text.find("suppressed"), std::string::npos);
  EXPECT_EQ(emitted.back().second.severity, Severity::kError);
  EXPECT_LE(emitted.back().first - end, milliseconds(1000));
  EXPECT_FALSE(limiter.NextDeadline().has_value());
  EXPECT_EQ(limiter.suppressed() + emitted.size(), 2151u);
}

}  // namespace
}  // namespace trackcal::fastrak
