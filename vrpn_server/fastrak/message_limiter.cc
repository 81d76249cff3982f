#include "vrpn_server/fastrak/message_limiter.h"

#include <algorithm>

namespace trackcal::fastrak {

const char* SeverityName(Severity severity) {
  switch (severity) {
    case Severity::kInfo:
      return "info";
    case Severity::kWarning:
      return "warning";
    case Severity::kError:
      return "error";
  }
  return "?";
}

std::optional<DriverMessage> MessageLimiter::Submit(DriverMessage message, Clock::time_point now) {
  if (!held_ && (!last_emitted_ || now - *last_emitted_ >= interval_)) {
    last_emitted_ = now;
    return message;
  }
  ++suppressed_total_;
  if (held_) {
    ++dropped_while_held_;
    ++dropped_by_severity_[static_cast<size_t>(held_->severity)];
    if (held_->severity == Severity::kError && !first_dropped_error_) {
      first_dropped_error_ = std::move(held_->text);
    }
  }
  held_ = std::move(message);
  return Poll(now);
}

std::optional<DriverMessage> MessageLimiter::Poll(Clock::time_point now) {
  if (!held_ || (last_emitted_ && now - *last_emitted_ < interval_)) return std::nullopt;
  DriverMessage message = std::move(*held_);
  held_.reset();
  --suppressed_total_;  // it is emitted after all
  if (dropped_while_held_ > 0) {
    // The note says which severities were dropped (most severe first), so an error that was
    // replaced is still reported as one without relabelling this text.
    std::string counts;
    for (int s = static_cast<int>(Severity::kError); s >= static_cast<int>(Severity::kInfo); --s) {
      const int n = dropped_by_severity_[static_cast<size_t>(s)];
      if (n == 0) continue;
      if (!counts.empty()) counts += ", ";
      counts += std::string(SeverityName(static_cast<Severity>(s))) + " " + std::to_string(n);
    }
    // The first error says why the trouble began (the watchdog's "no record for 2 s; reopening"),
    // which the errors after it ("cannot open ...") and the final state do not.
    const std::string first_error =
        first_dropped_error_ ? "; the first error: '" + *first_dropped_error_ + "'" : "";
    message.text += " (" + std::to_string(dropped_while_held_) + " earlier message" +
                    (dropped_while_held_ == 1 ? "" : "s") +
                    " suppressed by the rate limit: " + counts + first_error + ")";
  }
  dropped_while_held_ = 0;
  dropped_by_severity_.fill(0);
  first_dropped_error_.reset();
  last_emitted_ = now;
  return message;
}

std::optional<MessageLimiter::Clock::time_point> MessageLimiter::NextDeadline() const {
  if (!held_) return std::nullopt;
  return last_emitted_ ? *last_emitted_ + interval_ : Clock::time_point::min();
}

}  // namespace trackcal::fastrak
