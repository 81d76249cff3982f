#include "vrpn_server/protocol/stream_parser.h"

#include <gtest/gtest.h>

#include "tests/test_utils.h"
#include "vrpn_server/protocol/payloads.h"

namespace trackcal::vrpn {
namespace {

struct Seen {
  std::int32_t type;
  std::size_t payload_size;
  std::vector<std::uint8_t> payload;
};

std::vector<std::uint8_t> SampleStream() {
  const auto cookie = MakeCookie();
  std::vector<std::uint8_t> s(cookie.begin(), cookie.end());
  AppendMessage(&s, Timestamp{1, 2}, 0, kSenderDescription, 0, EncodeDescription("Tracker0"));
  AppendMessage(&s, Timestamp{1, 2}, 4, 4, 1, EncodePosQuat(PosQuat{}));
  AppendMessage(&s, Timestamp{1, 3}, 1, 16, 2, {});
  AppendMessage(&s, Timestamp{1, 4}, 1, 15, 3, EncodeText(TextMessage{TextSeverity::kWarning, 3, "hi"}));
  return s;
}

std::vector<Seen> FeedInChunks(const std::vector<std::uint8_t>& stream, std::size_t chunk) {
  MessageStreamParser parser;
  std::vector<Seen> seen;
  for (std::size_t i = 0; i < stream.size(); i += chunk) {
    const std::size_t n = std::min(chunk, stream.size() - i);
    const auto status = parser.Feed(std::span(stream).subspan(i, n), [&](const Message& m) {
      seen.push_back({m.header.type, m.payload.size(), {m.payload.begin(), m.payload.end()}});
    });
    EXPECT_EQ(status, MessageStreamParser::Status::kOk);
  }
  EXPECT_EQ(parser.buffered(), 0u);
  return seen;
}

TEST(MessageStreamParser, Nominal) {
  const auto seen = FeedInChunks(SampleStream(), 1 << 20);
  ASSERT_EQ(seen.size(), 4u);
  EXPECT_EQ(seen[0].type, kSenderDescription);
  EXPECT_EQ(seen[1].payload_size, kPosQuatSize);
  EXPECT_EQ(seen[2].payload_size, 0u);
  EXPECT_EQ(seen[3].payload_size, kTextSize);
}

TEST(MessageStreamParser, AnySplitGivesTheSameMessages) {
  const auto stream = SampleStream();
  const auto whole = FeedInChunks(stream, stream.size());
  for (std::size_t chunk : {1u, 2u, 3u, 7u, 23u, 24u, 25u, 100u}) {
    const auto split = FeedInChunks(stream, chunk);
    ASSERT_EQ(split.size(), whole.size()) << chunk;
    for (std::size_t i = 0; i < whole.size(); ++i) {
      EXPECT_EQ(split[i].type, whole[i].type);
      EXPECT_EQ(split[i].payload, whole[i].payload);
    }
  }
}

TEST(MessageStreamParser, OversizedLengthIsFatal) {
  MessageStreamParser parser(MessageStreamParser::Options{.max_message_length = 2000});
  const auto cookie = MakeCookie();
  std::vector<std::uint8_t> s(cookie.begin(), cookie.end());
  AppendMessage(&s, Timestamp{}, 0, 1, 0, std::vector<std::uint8_t>(1500, 1));  // fits
  std::vector<std::uint8_t> header(24, 0);
  StoreU32(0x7fffffff, header.data());  // a 2 GB claim must not be buffered
  s.insert(s.end(), header.begin(), header.end());
  int count = 0;
  EXPECT_EQ(parser.Feed(s, [&](const Message&) { ++count; }),
            MessageStreamParser::Status::kOversized);
  EXPECT_EQ(count, 1);
  EXPECT_EQ(parser.buffered(), 0u);
  EXPECT_NE(parser.ErrorText().find("2147483647"), std::string::npos);
  // Sticky: later valid input is not parsed.
  std::vector<std::uint8_t> more;
  AppendMessage(&more, Timestamp{}, 0, 1, 0, {});
  EXPECT_EQ(parser.Feed(more, [&](const Message&) { ++count; }),
            MessageStreamParser::Status::kOversized);
  EXPECT_EQ(count, 1);
}

TEST(MessageStreamParser, ShortLengthAndBadCookieAreFatal) {
  const auto cookie = MakeCookie();
  std::vector<std::uint8_t> s(cookie.begin(), cookie.end());
  s.resize(48, 0);
  StoreU32(10, s.data() + 24);
  MessageStreamParser parser;
  EXPECT_EQ(parser.Feed(s, [](const Message&) {}), MessageStreamParser::Status::kMalformed);

  MessageStreamParser http;
  const std::string get = "GET / HTTP/1.1\r\nHost: x\r\n\r\n";
  EXPECT_EQ(http.Feed(std::vector<std::uint8_t>(get.begin(), get.end()), [](const Message&) {}),
            MessageStreamParser::Status::kBadCookie);
}

TEST(MessageStreamParser, RandomGarbageNeverCrashesOrOverBuffers) {
  auto& rng = testing::TestRng();
  std::uniform_int_distribution<int> byte(0, 255);
  for (int trial = 0; trial < 200; ++trial) {
    MessageStreamParser parser(MessageStreamParser::Options{.max_message_length = 4096});
    auto s = SampleStream();
    for (int i = 0; i < 300; ++i) s.push_back(static_cast<std::uint8_t>(byte(rng)));
    parser.Feed(s, [](const Message& m) { ASSERT_LE(m.header.length, 4096u); });
    // At most one incomplete message can be held.
    EXPECT_LE(parser.buffered(), 4096u + 8u);
  }
}

TEST(ParseDatagram, WholeMessagesAndTruncation) {
  std::vector<std::uint8_t> d;
  AppendMessage(&d, Timestamp{}, 1, 4, 0, EncodePosQuat(PosQuat{}));
  AppendMessage(&d, Timestamp{}, 1, 4, 1, EncodePosQuat(PosQuat{}));
  int n = 0;
  EXPECT_TRUE(ParseDatagram(d, kDefaultMaxMessageLength, [&](const Message&) { ++n; }));
  EXPECT_EQ(n, 2);
  d.resize(d.size() - 10);
  EXPECT_FALSE(ParseDatagram(d, kDefaultMaxMessageLength, [](const Message&) {}));
}

}  // namespace
}  // namespace trackcal::vrpn
