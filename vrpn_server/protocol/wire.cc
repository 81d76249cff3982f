#include "vrpn_server/protocol/wire.h"

#include <bit>
#include <chrono>
#include <cmath>
#include <cstring>
#include <limits>

namespace trackcal::vrpn {

Timestamp Timestamp::Now() {
  const auto now = std::chrono::system_clock::now().time_since_epoch();
  const auto us = std::chrono::duration_cast<std::chrono::microseconds>(now).count();
  return Timestamp{static_cast<std::uint32_t>(us / 1000000), static_cast<std::uint32_t>(us % 1000000)};
}

Timestamp Timestamp::FromSeconds(double seconds) {
  // The double -> uint32 conversions below are only defined inside [0, 2^32): saturate first.
  constexpr std::uint32_t kMaxSec = std::numeric_limits<std::uint32_t>::max();
  if (!(seconds > 0.0)) return Timestamp{0, 0};  // NaN and negative times included
  if (seconds >= 4294967296.0) return Timestamp{kMaxSec, 999999};
  double whole = std::floor(seconds);
  double usec = std::round((seconds - whole) * 1e6);
  if (usec >= 1e6) {
    // Rounded up to the next second, which does not exist past the last one.
    if (whole >= kMaxSec) return Timestamp{kMaxSec, 999999};
    whole += 1.0;
    usec -= 1e6;
  }
  return Timestamp{static_cast<std::uint32_t>(whole), static_cast<std::uint32_t>(usec)};
}

std::uint32_t LoadU32(const std::uint8_t* p) {
  return (std::uint32_t{p[0]} << 24) | (std::uint32_t{p[1]} << 16) | (std::uint32_t{p[2]} << 8) |
         std::uint32_t{p[3]};
}

void StoreU32(std::uint32_t v, std::uint8_t* p) {
  p[0] = static_cast<std::uint8_t>(v >> 24);
  p[1] = static_cast<std::uint8_t>(v >> 16);
  p[2] = static_cast<std::uint8_t>(v >> 8);
  p[3] = static_cast<std::uint8_t>(v);
}

void ByteWriter::PutU32(std::uint32_t v) {
  std::uint8_t b[4];
  StoreU32(v, b);
  out_->insert(out_->end(), b, b + 4);
}

void ByteWriter::PutF64(double v) {
  const auto bits = std::bit_cast<std::uint64_t>(v);
  PutU32(static_cast<std::uint32_t>(bits >> 32));
  PutU32(static_cast<std::uint32_t>(bits));
}

void ByteWriter::PutBytes(std::span<const std::uint8_t> bytes) {
  out_->insert(out_->end(), bytes.begin(), bytes.end());
}

void ByteWriter::PutString(std::string_view s) {
  out_->insert(out_->end(), s.begin(), s.end());
}

void ByteWriter::PutZeros(std::size_t n) { out_->insert(out_->end(), n, 0); }

std::uint32_t ByteReader::GetU32() {
  if (!ok_ || remaining() < 4) {
    ok_ = false;
    return 0;
  }
  const std::uint32_t v = LoadU32(bytes_.data() + pos_);
  pos_ += 4;
  return v;
}

double ByteReader::GetF64() {
  const std::uint64_t hi = GetU32();
  const std::uint64_t lo = GetU32();
  return ok_ ? std::bit_cast<double>((hi << 32) | lo) : 0.0;
}

std::span<const std::uint8_t> ByteReader::GetBytes(std::size_t n) {
  if (!ok_ || remaining() < n) {
    ok_ = false;
    return {};
  }
  auto s = bytes_.subspan(pos_, n);
  pos_ += n;
  return s;
}

MessageHeader DecodeHeader(const std::uint8_t* p) {
  MessageHeader h;
  h.length = LoadU32(p);
  h.time.sec = LoadU32(p + 4);
  h.time.usec = LoadU32(p + 8);
  h.sender = static_cast<std::int32_t>(LoadU32(p + 12));
  h.type = static_cast<std::int32_t>(LoadU32(p + 16));
  h.sequence = LoadU32(p + 20);
  return h;
}

void AppendMessage(std::vector<std::uint8_t>* out, Timestamp time, std::int32_t sender,
                   std::int32_t type, std::uint32_t sequence,
                   std::span<const std::uint8_t> payload) {
  ByteWriter w(out);
  w.PutU32(static_cast<std::uint32_t>(kHeaderSize + payload.size()));
  w.PutU32(time.sec);
  w.PutU32(time.usec);
  w.PutI32(sender);
  w.PutI32(type);
  w.PutU32(sequence);
  w.PutBytes(payload);
  w.PutZeros(Ceil8(payload.size()) - payload.size());
}

std::array<std::uint8_t, kCookieSize> MakeCookie(char log_mode) {
  std::array<std::uint8_t, kCookieSize> c{};
  std::memcpy(c.data(), kCookieVersion.data(), kCookieVersion.size());
  c[16] = ' ';
  c[17] = ' ';
  c[18] = static_cast<std::uint8_t>(log_mode);
  return c;
}

CookieStatus CheckCookie(std::span<const std::uint8_t, kCookieSize> cookie, char* log_mode) {
  if (std::memcmp(cookie.data(), kCookieCompatiblePrefix.data(), kCookieCompatiblePrefix.size()) != 0) {
    return CookieStatus::kBadVersion;
  }
  if (log_mode != nullptr) *log_mode = static_cast<char>(cookie[18]);
  return CookieStatus::kOk;
}

}  // namespace trackcal::vrpn
