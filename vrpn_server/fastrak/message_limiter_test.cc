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
  // The last state is delivered within one interval, at its own level, saying it replaced errors.
  EXPECT_EQ(emitted.back().second.text.rfind("reset completed", 0), 0u);
  EXPECT_NE(emitted.back().second.text.find("suppressed by the rate limit: error "),
            std::string::npos);
  EXPECT_EQ(emitted.back().second.severity, Severity::kInfo);
  EXPECT_LE(emitted.back().first - end, milliseconds(1000));
  EXPECT_FALSE(limiter.NextDeadline().has_value());
  EXPECT_EQ(limiter.suppressed() + emitted.size(), 2151u);
}

// A held text keeps its own severity: clients saw "error: ... opened at 115200 baud (59 earlier
// messages suppressed)", an info text labelled error because it had replaced errors. The note says
// how many of each severity it replaced, so the errors are still reported as errors.
TEST(MessageLimiter, HeldTextKeepsItsSeverityAndCountsWhatItReplacedBySeverity) {
  MessageLimiter limiter(milliseconds(1000));
  const Clock::time_point t0{};
  ASSERT_TRUE(limiter.Submit({Severity::kError, "cannot open 1"}, t0).has_value());
  EXPECT_FALSE(limiter.Submit({Severity::kError, "cannot open 2"}, t0 + milliseconds(100)));
  EXPECT_FALSE(limiter.Submit({Severity::kError, "cannot open 3"}, t0 + milliseconds(200)));
  EXPECT_FALSE(limiter.Submit({Severity::kWarning, "resetting"}, t0 + milliseconds(300)));
  EXPECT_FALSE(limiter.Submit({Severity::kInfo, "opened at 115200 baud"}, t0 + milliseconds(400)));
  EXPECT_FALSE(limiter.Poll(t0 + milliseconds(999)).has_value());
  const auto held = limiter.Poll(t0 + milliseconds(1000));
  ASSERT_TRUE(held.has_value());
  EXPECT_EQ(held->severity, Severity::kInfo);
  EXPECT_EQ(held->text,
            "opened at 115200 baud (3 earlier messages suppressed by the rate limit: error 2, "
            "warning 1; the first error: 'cannot open 2')");
  EXPECT_EQ(limiter.suppressed(), 3u);
  // The counts start again for the next held text.
  ASSERT_FALSE(limiter.Submit({Severity::kWarning, "w"}, t0 + milliseconds(1100)));
  ASSERT_FALSE(limiter.Submit({Severity::kError, "e"}, t0 + milliseconds(1200)));
  const auto next = limiter.Poll(t0 + milliseconds(2000));
  ASSERT_TRUE(next.has_value());
  EXPECT_EQ(next->severity, Severity::kError);
  EXPECT_EQ(next->text, "e (1 earlier message suppressed by the rate limit: warning 1)");
}

// The watchdog's text says why the port is reopened; the "cannot open" errors of the reopen
// replaced it while it was held, and then "opened at ..." replaced those: clients and the log saw
// "opened at 115200 baud (4 earlier messages suppressed ...: error 4)" and never the reason. The
// note quotes the first error it replaced.
TEST(MessageLimiter, TheFirstErrorAHeldTextReplacedIsQuoted) {
  MessageLimiter limiter(milliseconds(1000));
  const Clock::time_point t0{};
  ASSERT_TRUE(limiter.Submit({Severity::kInfo, "streaming"}, t0).has_value());
  const std::string watchdog = "no record for 2 s; reopening and resetting the tracker";
  EXPECT_FALSE(limiter.Submit({Severity::kWarning, "skipped 3 bytes"}, t0 + milliseconds(50)));
  EXPECT_FALSE(limiter.Submit({Severity::kError, watchdog}, t0 + milliseconds(100)));
  for (int i = 0; i < 3; ++i) {
    EXPECT_FALSE(limiter.Submit({Severity::kError, "cannot open: No such file or directory"},
                                t0 + milliseconds(200 + 100 * i)));
  }
  EXPECT_FALSE(limiter.Submit({Severity::kInfo, "opened at 115200 baud"}, t0 + milliseconds(600)));
  const auto held = limiter.Poll(t0 + milliseconds(1000));
  ASSERT_TRUE(held.has_value());
  EXPECT_EQ(held->severity, Severity::kInfo);
  EXPECT_EQ(held->text,
            "opened at 115200 baud (5 earlier messages suppressed by the rate limit: error 4, "
            "warning 1; the first error: '" +
                watchdog + "')");
  // Forgotten with the note: the next held text quotes its own first error, or none.
  ASSERT_FALSE(limiter.Submit({Severity::kWarning, "w1"}, t0 + milliseconds(1100)));
  ASSERT_FALSE(limiter.Submit({Severity::kWarning, "w2"}, t0 + milliseconds(1200)));
  const auto next = limiter.Poll(t0 + milliseconds(2000));
  ASSERT_TRUE(next.has_value());
  EXPECT_EQ(next->text, "w2 (1 earlier message suppressed by the rate limit: warning 1)");
}

}  // namespace
}  // namespace trackcal::fastrak
