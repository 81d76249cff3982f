// Incremental VRPN stream parser: buffers TCP bytes, checks the peer's cookie, and yields whole
// messages. A length field below 24 or above the limit is a fatal error for that stream only (the
// owner closes that one connection); the parser never allocates more than the limit plus one read.

#pragma once

#include <cstdint>
#include <functional>
#include <span>
#include <string>
#include <vector>

#include "vrpn_server/protocol/wire.h"

namespace trackcal::vrpn {

struct Message {
  MessageHeader header;
  std::span<const std::uint8_t> payload;  // unpadded; valid only during the callback
};

using MessageCallback = std::function<void(const Message&)>;

class MessageStreamParser {
 public:
  struct Options {
    // TCP streams start with the peer's 24-byte cookie; datagrams do not.
    bool expect_cookie = true;
    // Largest accepted header length field (24 + payload); larger closes the stream.
    std::uint32_t max_message_length = kDefaultMaxMessageLength;
    bool Check() const { return max_message_length >= kHeaderSize; }
  };

  enum class Status {
    kOk,
    kBadCookie,  // not a VRPN 07.xx cookie
    kOversized,  // length field over max_message_length
    kMalformed,  // length field below the header size
  };

  MessageStreamParser() : MessageStreamParser(Options()) {}
  explicit MessageStreamParser(Options options);

  // Consumes bytes and calls on_message for every complete message, in order. Once an error is
  // returned the parser stays in that state and ignores further input.
  Status Feed(std::span<const std::uint8_t> bytes, const MessageCallback& on_message);

  bool cookie_received() const { return cookie_received_; }
  char peer_log_mode() const { return peer_log_mode_; }
  Status status() const { return status_; }
  // Bytes held waiting for the rest of a message.
  std::size_t buffered() const { return buffer_.size() - start_; }
  // Whole messages parsed so far (the owner can tell a stream that moves on from one stuck in the
  // middle of a message).
  std::uint64_t messages() const { return messages_; }
  std::string ErrorText() const;

 private:
  Options options_;
  std::vector<std::uint8_t> buffer_;
  std::size_t start_ = 0;
  bool cookie_received_ = false;
  char peer_log_mode_ = '0';
  Status status_ = Status::kOk;
  std::uint32_t bad_length_ = 0;
  std::uint64_t messages_ = 0;
};

// Parses one UDP datagram holding whole messages. Returns false (after delivering the messages
// before the fault) when a length field is out of range or a message is truncated.
bool ParseDatagram(std::span<const std::uint8_t> datagram, std::uint32_t max_message_length,
                   const MessageCallback& on_message);

}  // namespace trackcal::vrpn
