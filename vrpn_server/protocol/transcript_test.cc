// Replays the captured reference sessions (tests/data/vrpn/) through the protocol library.
#include <gtest/gtest.h>

#include <algorithm>
#include <map>
#include <set>

#include "vrpn_server/protocol/connection.h"
#include "vrpn_server/protocol/payloads.h"
#include "vrpn_server/protocol/transcript_testing.h"

namespace trackcal::vrpn {
namespace {

using testing::ReadBytes;
using testing::TranscriptScenarios;

TEST(Transcripts, EveryStreamParsesCompletely) {
  const auto scenarios = TranscriptScenarios();
  ASSERT_EQ(scenarios.size(), 10u);
  for (const auto& dir : scenarios) {
    for (const char* file : {"server_to_client.bin", "client_to_server.bin"}) {
      SCOPED_TRACE(dir.filename().string() + "/" + file);
      const auto bytes = ReadBytes(dir / file);
      MessageStreamParser parser;
      std::size_t n = 0;
      std::size_t consumed = kCookieSize;
      EXPECT_EQ(parser.Feed(bytes,
                            [&](const Message& m) {
                              ++n;
                              consumed += m.header.wire_size();
                            }),
                MessageStreamParser::Status::kOk);
      EXPECT_TRUE(parser.cookie_received());
      EXPECT_EQ(parser.peer_log_mode(), '0');
      EXPECT_EQ(parser.buffered(), 0u);
      EXPECT_EQ(consumed, bytes.size());
      EXPECT_GT(n, 10u);
    }
    if (std::filesystem::exists(dir / "server_to_client_udp.bin")) {
      const auto bytes = ReadBytes(dir / "server_to_client_udp.bin");
      std::size_t n = 0;
      EXPECT_TRUE(ParseDatagram(bytes, kDefaultMaxMessageLength, [&](const Message&) { ++n; }));
      EXPECT_GT(n, 0u);
    }
    if (std::filesystem::exists(dir / "client_to_server_udp_lob.bin")) {
      const auto req = DecodeLobRequest(ReadBytes(dir / "client_to_server_udp_lob.bin"));
      ASSERT_TRUE(req);
      EXPECT_EQ(req->host, "127.0.0.1");
    }
  }
}

struct DecodedPose {
  int sensor;
  double v[7];
  Timestamp time;
};

// Decodes the reference server's bytes as our client would: TCP stream, then UDP datagrams whose
// ids resolve through the TCP descriptions.
std::vector<DecodedPose> DecodeServerPoses(const std::filesystem::path& dir) {
  auto names = std::make_shared<NameRegistry>();
  Connection connection(names, Connection::Options{});
  std::vector<DecodedPose> poses;
  std::map<std::string, int> type_counts;
  auto handler = [&](const ReceivedMessage& m) {
    ++type_counts[std::string(m.type)];
    if (m.type != kPosQuatType) return;
    EXPECT_EQ(m.sender, "Tracker0");
    const auto p = DecodePosQuat(m.payload);
    EXPECT_TRUE(p);
    if (!p) return;
    DecodedPose d{p->sensor, {}, m.time};
    const auto& t = p->transmitter_from_receiver;
    d.v[0] = t.translation.x();
    d.v[1] = t.translation.y();
    d.v[2] = t.translation.z();
    QuaternionToXyzwArray(t.rotation, d.v + 3);
    poses.push_back(d);
  };
  EXPECT_TRUE(connection.OnTcpBytes(ReadBytes(dir / "server_to_client.bin"), handler));
  if (std::filesystem::exists(dir / "server_to_client_udp.bin")) {
    connection.OnDatagram(ReadBytes(dir / "server_to_client_udp.bin"), handler);
  }
  EXPECT_EQ(connection.counters().bad_description, 0u);
  EXPECT_EQ(connection.counters().bad_datagram, 0u);
  return poses;
}

TEST(Transcripts, DecodedServerPosesEqualReferenceClientCsv) {
  int scenarios_with_poses = 0;
  for (const auto& dir : TranscriptScenarios()) {
    if (!std::filesystem::exists(dir / "client.csv")) continue;
    SCOPED_TRACE(dir.filename().string());
    ++scenarios_with_poses;
    auto decoded = DecodeServerPoses(dir);
    auto csv = testing::ReadClientCsv(dir / "client.csv");
    // The capture may have ended after the client's last print, or the client may have stopped
    // printing before the capture ended: compare the common prefix in time order and require it to
    // cover the whole csv.
    auto by_time = [](const auto& a, const auto& b) {
      return std::tie(a.time.sec, a.time.usec, a.sensor) < std::tie(b.time.sec, b.time.usec, b.sensor);
    };
    std::stable_sort(decoded.begin(), decoded.end(), by_time);
    ASSERT_FALSE(csv.empty());
    ASSERT_GE(decoded.size(), csv.size());
    for (std::size_t i = 0; i < csv.size(); ++i) {
      SCOPED_TRACE(i);
      EXPECT_EQ(decoded[i].sensor, csv[i].sensor);
      EXPECT_EQ(decoded[i].time.sec, csv[i].sec);
      EXPECT_EQ(decoded[i].time.usec, csv[i].usec);
      // client.csv prints 17 significant digits, which round-trips a double exactly.
      for (int k = 0; k < 7; ++k) EXPECT_EQ(decoded[i].v[k], csv[i].v[k]) << "field " << k;
    }
  }
  EXPECT_EQ(scenarios_with_poses, 9);
}

TEST(Transcripts, WatchdogTextMessagesDecode) {
  auto names = std::make_shared<NameRegistry>();
  Connection connection(names, Connection::Options{});
  std::vector<TextMessage> texts;
  const auto dir = testing::TranscriptDir() / "09_fastrak_watchdog_text_messages";
  ASSERT_TRUE(connection.OnTcpBytes(ReadBytes(dir / "server_to_client.bin"), [&](const ReceivedMessage& m) {
    if (m.type == kTextType) texts.push_back(*DecodeText(m.payload));
  }));
  ASSERT_EQ(texts.size(), 6u);
  EXPECT_EQ(texts[2].text, "Resetting the tracker (attempt 1)");
  EXPECT_EQ(texts[2].severity, TextSeverity::kWarning);
  EXPECT_EQ(texts[3].severity, TextSeverity::kError);
}

TEST(Transcripts, ClientDescriptionsAndUdpDescriptionAreLearnt) {
  auto names = std::make_shared<NameRegistry>();
  Connection connection(names, Connection::Options{});
  const auto dir = testing::TranscriptDir() / "02_null_tracker_udp_lob";
  std::multiset<std::string> seen;
  ASSERT_TRUE(connection.OnTcpBytes(ReadBytes(dir / "client_to_server.bin"),
                                    [&](const ReceivedMessage& m) { seen.insert(std::string(m.type)); }));
  ASSERT_TRUE(connection.peer_udp());
  EXPECT_EQ(connection.peer_udp()->first, "127.0.0.1");
  EXPECT_EQ(connection.peer_udp()->second, 37178);
  EXPECT_EQ(seen.count(std::string(kPingType)), 1u);
  EXPECT_EQ(connection.peer_types().size(), 20u);
}

}  // namespace
}  // namespace trackcal::vrpn
