// Rate limit for the driver's status/error texts, which the server forwards to every client: at
// most one message per interval. A message that arrives too early is held (the newest one replaces
// an older held one) and goes out when the interval has passed, saying how many messages were
// dropped and of which severities, so the latest state always reaches clients within one interval.
// It keeps its own severity: an info text ("opened at 115200 baud") that replaced errors is not
// labelled an error; the note counts the errors it replaced and quotes the first of them (why the
// trouble began, e.g. the watchdog's reopen). (The reference sent 2,663 texts per
// client during a 5 s unplug.)

#pragma once

#include <array>
#include <chrono>
#include <cstdint>
#include <optional>
#include <string>

namespace trackcal::fastrak {

// Same values as VRPN's text severities (vrpn_TEXT_NORMAL, _WARNING, _ERROR).
enum class Severity { kInfo = 0, kWarning = 1, kError = 2 };
const char* SeverityName(Severity severity);

struct DriverMessage {
  Severity severity = Severity::kInfo;
  std::string text;
};

class MessageLimiter {
 public:
  using Clock = std::chrono::steady_clock;

  explicit MessageLimiter(Clock::duration interval) : interval_(interval) {}

  // Returns the message to emit now (this one), or nullopt if it is held.
  std::optional<DriverMessage> Submit(DriverMessage message, Clock::time_point now);
  // Returns the held message once the interval since the last emission has passed.
  std::optional<DriverMessage> Poll(Clock::time_point now);
  // When Poll will have something to emit (nullopt: nothing held).
  std::optional<Clock::time_point> NextDeadline() const;

  uint64_t suppressed() const { return suppressed_total_; }

 private:
  Clock::duration interval_;
  std::optional<Clock::time_point> last_emitted_;
  std::optional<DriverMessage> held_;
  int dropped_while_held_ = 0;  // messages replaced by a newer held one
  std::array<int, 3> dropped_by_severity_{};  // the same, indexed by Severity
  std::optional<std::string> first_dropped_error_;  // text of the first error among them
  uint64_t suppressed_total_ = 0;
};

}  // namespace trackcal::fastrak
