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
    message.severity = std::max(message.severity, held_->severity);
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
    message.text += " (" + std::to_string(dropped_while_held_) + " earlier message" +
                    (dropped_while_held_ == 1 ? "" : "s") + " suppressed by the rate limit)";
  }
  dropped_while_held_ = 0;
  last_emitted_ = now;
  return message;
}

std::optional<MessageLimiter::Clock::time_point> MessageLimiter::NextDeadline() const {
  if (!held_) return std::nullopt;
  return last_emitted_ ? *last_emitted_ + interval_ : Clock::time_point::min();
}

}  // namespace trackcal::fastrak
