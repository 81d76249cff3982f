// VRPN wire basics: big-endian codec, the 24-byte cookie, the 24-byte message header and padding.
//
// Layout facts come from docs/vrpn.md (protocol notes, checked against captured sessions of the
// reference implementation VRPN 07.38). Every multi-byte field on the wire is big-endian; a message is
// a header {length = 24 + unpadded payload length, seconds, microseconds, sender id, type id,
// sequence} followed by the payload and zero to seven padding bytes up to a multiple of 8.

#pragma once

#include <array>
#include <cstddef>
#include <cstdint>
#include <span>
#include <string>
#include <string_view>
#include <vector>

namespace trackcal::vrpn {

inline constexpr std::size_t kCookieSize = 24;
inline constexpr std::size_t kHeaderSize = 24;
// The version we announce; the reference only requires the major version prefix to match.
inline constexpr std::string_view kCookieVersion = "vrpn: ver. 07.38";
inline constexpr std::string_view kCookieCompatiblePrefix = "vrpn: ver. 07.";
// The reference receive buffer: a message whose length field exceeds this is rejected.
inline constexpr std::uint32_t kDefaultMaxMessageLength = 64000;
// Largest UDP datagram the reference sends (Ethernet MTU minus IP and UDP headers).
inline constexpr std::size_t kMaxDatagramSize = 1472;
inline constexpr int kDefaultPort = 3883;
// A description payload longer than 100 bytes is rejected by the reference: 4 + name + NUL <= 100.
inline constexpr std::size_t kMaxNameLength = 95;

// System message types (negative type ids); for these the header's sender field is a parameter.
enum SystemType : std::int32_t {
  kSenderDescription = -1,  // sender field = id described; payload = description
  kTypeDescription = -2,    // sender field = id described; payload = description
  kUdpDescription = -3,     // sender field = UDP port; payload = dotted IPv4 + NUL
  kLogDescription = -4,     // only after a cookie with log mode != '0'; ignored by us
  kDisconnectMessage = -5,  // only in log files, never on the wire
};

constexpr std::size_t Ceil8(std::size_t n) { return (n + 7) & ~std::size_t{7}; }

// Header timestamp: sender's wall clock, Unix epoch.
struct Timestamp {
  std::uint32_t sec = 0;
  std::uint32_t usec = 0;

  static Timestamp Now();
  // Rounded to the microsecond; outside the wire's range [0, 2^32) s it saturates to the nearest
  // end ({0, 0} or {2^32 - 1, 999999}), and NaN gives {0, 0}.
  static Timestamp FromSeconds(double seconds);
  // usec as VRPN sends it: a signed 32-bit field, which an upstream server may send unnormalised
  // (1,000,000 or more, or negative). Both give the time the header means.
  double Seconds() const { return sec + 1e-6 * static_cast<std::int32_t>(usec); }
  std::int64_t Microseconds() const {
    return std::int64_t{sec} * 1'000'000 + static_cast<std::int32_t>(usec);
  }
  bool operator==(const Timestamp&) const = default;
};

// Appends big-endian fields to a byte vector.
class ByteWriter {
 public:
  explicit ByteWriter(std::vector<std::uint8_t>* out) : out_(out) {}
  void PutU32(std::uint32_t v);
  void PutI32(std::int32_t v) { PutU32(static_cast<std::uint32_t>(v)); }
  void PutF64(double v);
  void PutBytes(std::span<const std::uint8_t> bytes);
  void PutString(std::string_view s);  // raw bytes, no NUL
  void PutZeros(std::size_t n);

 private:
  std::vector<std::uint8_t>* out_;
};

// Reads big-endian fields from a byte span; a read past the end sets !ok() and returns zeros.
class ByteReader {
 public:
  explicit ByteReader(std::span<const std::uint8_t> bytes) : bytes_(bytes) {}
  std::uint32_t GetU32();
  std::int32_t GetI32() { return static_cast<std::int32_t>(GetU32()); }
  double GetF64();
  std::span<const std::uint8_t> GetBytes(std::size_t n);
  void Skip(std::size_t n) { GetBytes(n); }
  std::size_t remaining() const { return bytes_.size() - pos_; }
  bool ok() const { return ok_; }

 private:
  std::span<const std::uint8_t> bytes_;
  std::size_t pos_ = 0;
  bool ok_ = true;
};

std::uint32_t LoadU32(const std::uint8_t* p);
void StoreU32(std::uint32_t v, std::uint8_t* p);

struct MessageHeader {
  std::uint32_t length = kHeaderSize;  // 24 + unpadded payload length
  Timestamp time;
  std::int32_t sender = 0;
  std::int32_t type = 0;
  std::uint32_t sequence = 0;

  std::size_t payload_size() const { return length - kHeaderSize; }
  // Header plus padded payload: how many bytes the message occupies in the stream.
  std::size_t wire_size() const { return kHeaderSize + Ceil8(payload_size()); }
};

// Decodes the 24 header bytes at p (no validation of the length field).
MessageHeader DecodeHeader(const std::uint8_t* p);
// Byte offset of the sequence field in a header (patched per connection when broadcasting).
inline constexpr std::size_t kSequenceOffset = 20;

// Appends header, payload and zero padding.
void AppendMessage(std::vector<std::uint8_t>* out, Timestamp time, std::int32_t sender,
                   std::int32_t type, std::uint32_t sequence,
                   std::span<const std::uint8_t> payload);

// "vrpn: ver. 07.38", two spaces, the log-mode digit, NUL padding to 24 bytes.
std::array<std::uint8_t, kCookieSize> MakeCookie(char log_mode = '0');

enum class CookieStatus {
  kOk,             // same major version (minor may differ, as the reference allows)
  kBadVersion,     // different major version or not a VRPN cookie: refuse the connection
};
// Checks a received cookie; on success stores the peer's log-mode character.
CookieStatus CheckCookie(std::span<const std::uint8_t, kCookieSize> cookie, char* log_mode);

}  // namespace trackcal::vrpn
