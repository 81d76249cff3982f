#include "vrpn_server/protocol/stream_parser.h"

#include <stdexcept>

namespace trackcal::vrpn {

MessageStreamParser::MessageStreamParser(Options options) : options_(options) {
  if (!options_.Check()) {
    throw std::invalid_argument("MessageStreamParser::Options.max_message_length: below 24");
  }
  cookie_received_ = !options_.expect_cookie;
}

MessageStreamParser::Status MessageStreamParser::Feed(std::span<const std::uint8_t> bytes,
                                                      const MessageCallback& on_message) {
  if (status_ != Status::kOk) return status_;
  buffer_.insert(buffer_.end(), bytes.begin(), bytes.end());
  while (status_ == Status::kOk) {
    const std::size_t available = buffer_.size() - start_;
    const std::uint8_t* p = buffer_.data() + start_;
    if (!cookie_received_) {
      if (available < kCookieSize) break;
      if (CheckCookie(std::span<const std::uint8_t, kCookieSize>(p, kCookieSize), &peer_log_mode_) !=
          CookieStatus::kOk) {
        status_ = Status::kBadCookie;
        break;
      }
      cookie_received_ = true;
      start_ += kCookieSize;
      continue;
    }
    if (available < kHeaderSize) break;
    const std::uint32_t length = LoadU32(p);
    if (length < kHeaderSize) {
      status_ = Status::kMalformed;
      bad_length_ = length;
      break;
    }
    if (length > options_.max_message_length) {
      status_ = Status::kOversized;
      bad_length_ = length;
      break;
    }
    const std::size_t wire = kHeaderSize + Ceil8(length - kHeaderSize);
    if (available < wire) break;
    Message m;
    m.header = DecodeHeader(p);
    m.payload = std::span<const std::uint8_t>(p + kHeaderSize, length - kHeaderSize);
    start_ += wire;
    ++messages_;
    on_message(m);
  }
  if (status_ != Status::kOk) {
    buffer_.clear();
    buffer_.shrink_to_fit();
    start_ = 0;
  } else if (start_ == buffer_.size()) {
    buffer_.clear();
    start_ = 0;
  } else if (start_ > 4096) {
    buffer_.erase(buffer_.begin(), buffer_.begin() + static_cast<std::ptrdiff_t>(start_));
    start_ = 0;
  }
  return status_;
}

std::string MessageStreamParser::ErrorText() const {
  switch (status_) {
    case Status::kOk:
      return "ok";
    case Status::kBadCookie:
      return "bad cookie (not a VRPN 07.xx peer)";
    case Status::kOversized:
      return "message length " + std::to_string(bad_length_) + " over the limit " +
             std::to_string(options_.max_message_length);
    case Status::kMalformed:
      return "message length " + std::to_string(bad_length_) + " below the 24-byte header";
  }
  return "unknown";
}

bool ParseDatagram(std::span<const std::uint8_t> datagram, std::uint32_t max_message_length,
                   const MessageCallback& on_message) {
  std::size_t pos = 0;
  while (pos < datagram.size()) {
    if (datagram.size() - pos < kHeaderSize) return false;
    const std::uint8_t* p = datagram.data() + pos;
    const std::uint32_t length = LoadU32(p);
    if (length < kHeaderSize || length > max_message_length) return false;
    const std::size_t payload = length - kHeaderSize;
    // The last message of a datagram may omit its padding.
    if (datagram.size() - pos < kHeaderSize + payload) return false;
    Message m;
    m.header = DecodeHeader(p);
    m.payload = datagram.subspan(pos + kHeaderSize, payload);
    on_message(m);
    pos += kHeaderSize + Ceil8(payload);
  }
  return true;
}

}  // namespace trackcal::vrpn
