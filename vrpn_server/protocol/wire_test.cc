#include "vrpn_server/protocol/wire.h"

#include <gtest/gtest.h>

#include <cmath>
#include <cstring>
#include <limits>

namespace trackcal::vrpn {
namespace {

TEST(Cookie, Nominal) {
  const auto cookie = MakeCookie();
  // Bytes of the reference's cookie (PROTOCOL notes, identical from server and client).
  const std::uint8_t expected[24] = {'v', 'r', 'p', 'n', ':', ' ', 'v', 'e', 'r', '.', ' ', '0',
                                     '7', '.', '3', '8', ' ', ' ', '0', 0,   0,   0,   0,   0};
  EXPECT_EQ(0, std::memcmp(cookie.data(), expected, 24));
  char log_mode = 'x';
  EXPECT_EQ(CheckCookie(cookie, &log_mode), CookieStatus::kOk);
  EXPECT_EQ(log_mode, '0');
}

TEST(Cookie, OtherMinorAcceptedOtherMajorRefused) {
  auto cookie = MakeCookie();
  std::memcpy(cookie.data(), "vrpn: ver. 07.35", 16);
  EXPECT_EQ(CheckCookie(cookie, nullptr), CookieStatus::kOk);
  std::memcpy(cookie.data(), "vrpn: ver. 06.38", 16);
  EXPECT_EQ(CheckCookie(cookie, nullptr), CookieStatus::kBadVersion);
  std::memcpy(cookie.data(), "GET / HTTP/1.1\r\n", 16);
  EXPECT_EQ(CheckCookie(cookie, nullptr), CookieStatus::kBadVersion);
}

TEST(AppendMessage, PingMatchesReferenceBytes) {
  // Transcript 01, client_to_server.bin offset 1408.
  const std::uint8_t expected[24] = {0x00, 0x00, 0x00, 0x18, 0x6b, 0x01, 0x6d, 0x36,
                                     0x00, 0x0e, 0x43, 0x9d, 0x00, 0x00, 0x00, 0x01,
                                     0x00, 0x00, 0x00, 0x10, 0x00, 0x00, 0x00, 0x17};
  std::vector<std::uint8_t> out;
  AppendMessage(&out, Timestamp{0x6b016d36, 0x000e439d}, 1, 16, 23, {});
  ASSERT_EQ(out.size(), 24u);
  EXPECT_EQ(0, std::memcmp(out.data(), expected, 24));
  const MessageHeader h = DecodeHeader(out.data());
  EXPECT_EQ(h.length, 24u);
  EXPECT_EQ(h.sender, 1);
  EXPECT_EQ(h.type, 16);
  EXPECT_EQ(h.sequence, 23u);
  EXPECT_EQ(h.time, (Timestamp{0x6b016d36, 0x000e439d}));
}

TEST(AppendMessage, PadsPayloadToMultipleOfEightButLengthIsUnpadded) {
  for (std::size_t n = 0; n <= 17; ++n) {
    std::vector<std::uint8_t> payload(n, 0xab);
    std::vector<std::uint8_t> out;
    AppendMessage(&out, Timestamp{}, -2, 3, 0, payload);
    EXPECT_EQ(out.size(), 24 + Ceil8(n));
    EXPECT_EQ(out.size() % 8, 0u);
    EXPECT_EQ(DecodeHeader(out.data()).length, 24 + n);
    for (std::size_t i = 24 + n; i < out.size(); ++i) EXPECT_EQ(out[i], 0);
  }
}

TEST(ByteWriter, DoubleIsBigEndian) {
  std::vector<std::uint8_t> out;
  ByteWriter(&out).PutF64(0.1);
  const std::vector<std::uint8_t> expected = {0x3f, 0xb9, 0x99, 0x99, 0x99, 0x99, 0x99, 0x9a};
  EXPECT_EQ(out, expected);
  ByteReader r(out);
  EXPECT_EQ(r.GetF64(), 0.1);
  EXPECT_TRUE(r.ok());
  EXPECT_EQ(r.GetU32(), 0u);
  EXPECT_FALSE(r.ok());
}

TEST(Timestamp, FromSecondsRoundTrips) {
  const Timestamp t = Timestamp::FromSeconds(1795255606.934813);
  EXPECT_EQ(t.sec, 1795255606u);
  EXPECT_EQ(t.usec, 934813u);
  EXPECT_EQ(Timestamp::FromSeconds(1.9999999).usec, 0u);
  EXPECT_EQ(Timestamp::FromSeconds(1.9999999).sec, 2u);
}

// VRPN's tv_usec is a signed 32-bit field that an upstream server may send unnormalised: the time
// is the one it means (Seconds() read -250,000 us as +4294.717296 s).
TEST(Timestamp, ReadsAnUnnormalisedMicrosecondFieldAsSigned) {
  const Timestamp late{12, 1'500'000};
  const Timestamp negative{12, static_cast<std::uint32_t>(-250'000)};
  EXPECT_EQ(late.Microseconds(), 13'500'000);
  EXPECT_EQ(negative.Microseconds(), 11'750'000);
  EXPECT_EQ((Timestamp{0, static_cast<std::uint32_t>(-1)}).Microseconds(), -1);
  // 1e-15 s: the double sum's rounding at 12 s (about 2e-15).
  EXPECT_NEAR(late.Seconds(), 13.5, 1e-14);
  EXPECT_NEAR(negative.Seconds(), 11.75, 1e-14);
}

TEST(Timestamp, FromSecondsSaturatesOutsideTheWireRange) {
  // The wire's seconds are an unsigned 32-bit count: converting a double outside [0, 2^32) to it
  // was undefined behaviour (x86-64 gave 4294967295 for -1 s and 705032704 for 5e9 s). Such a
  // time now saturates to the nearest end, and NaN gives the epoch.
  constexpr std::uint32_t kMax = std::numeric_limits<std::uint32_t>::max();
  const double inf = std::numeric_limits<double>::infinity();
  EXPECT_EQ(Timestamp::FromSeconds(-1.0), (Timestamp{0, 0}));
  EXPECT_EQ(Timestamp::FromSeconds(-0.25), (Timestamp{0, 0}));
  EXPECT_EQ(Timestamp::FromSeconds(-1e300), (Timestamp{0, 0}));
  EXPECT_EQ(Timestamp::FromSeconds(-inf), (Timestamp{0, 0}));
  EXPECT_EQ(Timestamp::FromSeconds(std::nan("")), (Timestamp{0, 0}));
  EXPECT_EQ(Timestamp::FromSeconds(5e9), (Timestamp{kMax, 999999}));
  EXPECT_EQ(Timestamp::FromSeconds(inf), (Timestamp{kMax, 999999}));
  // The last representable microsecond, and a value that rounds past it.
  EXPECT_EQ(Timestamp::FromSeconds(4294967295.999999), (Timestamp{kMax, 999999}));
  EXPECT_EQ(Timestamp::FromSeconds(4294967295.9999999), (Timestamp{kMax, 999999}));
  // The ends themselves are exact.
  EXPECT_EQ(Timestamp::FromSeconds(0.0), (Timestamp{0, 0}));
  EXPECT_EQ(Timestamp::FromSeconds(-0.0), (Timestamp{0, 0}));
  EXPECT_EQ(Timestamp::FromSeconds(4294967295.0), (Timestamp{kMax, 0}));
}

}  // namespace
}  // namespace trackcal::vrpn
