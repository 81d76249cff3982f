// The server endpoint against the reference client's bytes (tests/data/vrpn/), and its rules for
// misbehaving clients.
#include "vrpn_server/server/server_session.h"

#include <gtest/gtest.h>

#include <map>
#include <set>
#include <tuple>

#include "vrpn_server/protocol/payloads.h"
#include "vrpn_server/protocol/transcript_testing.h"

namespace trackcal::vrpn {
namespace {

TrackerSpec Tracker0() {
  TrackerSpec spec;
  spec.name = "Tracker0";
  return spec;
}

using Reply = std::tuple<std::string, std::string, std::size_t>;  // sender, type, payload size

// Replies = everything but descriptions and the device's own stream (reports, device text).
bool IsReply(int32_t type, std::string_view type_name) {
  if (type == kSenderDescription || type == kTypeDescription) return false;
  return type_name != kPosQuatType && type_name != kVelocityType &&
         type_name != kAccelerationType && type_name != kTextType;
}

std::multiset<Reply> RepliesIn(std::span<const std::uint8_t> server_bytes) {
  std::multiset<Reply> replies;
  MessageStreamParser parser;
  std::map<int32_t, std::string> senders, types;
  EXPECT_EQ(parser.Feed(server_bytes,
                        [&](const Message& m) {
                          if (m.header.type == kSenderDescription) {
                            senders[m.header.sender] = *DecodeDescription(m.payload);
                          } else if (m.header.type == kTypeDescription) {
                            types[m.header.sender] = *DecodeDescription(m.payload);
                          } else if (m.header.type == kUdpDescription) {
                            replies.insert({"<system>", "UDP description", 0});
                          } else if (IsReply(m.header.type, types[m.header.type])) {
                            replies.insert({senders[m.header.sender], types[m.header.type],
                                            m.payload.size()});
                          }
                        }),
            MessageStreamParser::Status::kOk);
  return replies;
}

std::shared_ptr<ServerCatalog> CatalogFor(const std::string& scenario) {
  auto catalog = std::make_shared<ServerCatalog>();
  TrackerSpec tracker;
  tracker.name = "Tracker0";
  // Sensor counts from each scenario's vrpn.cfg / commands.txt.
  tracker.num_sensors = (scenario.starts_with("03") || scenario.starts_with("04") ||
                         scenario.starts_with("05") || scenario.starts_with("10"))
                            ? 1
                            : 2;
  catalog->AddTracker(tracker);
  if (scenario.starts_with("08")) catalog->AddButton(ButtonSpec{"Stylus0", 1});
  return catalog;
}

TEST(ServerSession, RepliesToReferenceClientMatchReferenceServer) {
  int compared = 0;
  for (const auto& dir : testing::TranscriptScenarios()) {
    const std::string scenario = dir.filename().string();
    // Scenario 10's server is a deliberately minimal test server that never answers pings.
    if (scenario.starts_with("10")) continue;
    SCOPED_TRACE(scenario);
    const bool lob = std::filesystem::exists(dir / "client_to_server_udp_lob.bin");
    std::vector<std::string> log;
    ServerSession session(CatalogFor(scenario), Connection::Options{}, "test",
                          [&](const std::string& l) { log.push_back(l); });
    std::vector<std::vector<std::int32_t>> buttons(scenario.starts_with("08") ? 1 : 0,
                                                   std::vector<std::int32_t>{1});
    session.Start(lob ? std::optional(std::make_pair(std::string("127.0.0.1"), 40000))
                      : std::nullopt,
                  buttons);
    // Feed in odd-sized pieces, as TCP may deliver them.
    const auto client = testing::ReadBytes(dir / "client_to_server.bin");
    for (std::size_t i = 0; i < client.size(); i += 77) {
      ASSERT_TRUE(session.OnTcpBytes(std::span(client).subspan(i, std::min<std::size_t>(77, client.size() - i))));
    }
    const auto ours = RepliesIn(session.connection().tcp_output());
    const auto reference = RepliesIn(testing::ReadBytes(dir / "server_to_client.bin"));
    EXPECT_EQ(ours, reference);
    EXPECT_EQ(session.dropped_messages(), 0u);
    ++compared;
  }
  EXPECT_EQ(compared, 9);
}

TEST(ServerSession, AClientLeftWithoutPongsIsAnsweredEveryPingAndItsWarningsAreLogged) {
  // Capture 10: the reference client, unanswered by a minimal server, pinged once a second and
  // from the third second sent "No response from server" warnings. Every one of those pings gets a
  // pong from us, and the warnings reach the log; nothing is dropped.
  const auto dir = testing::TranscriptDir() / "10_independent_server_no_pong";
  const auto client = testing::ReadBytes(dir / "client_to_server.bin");
  int pings = 0;
  int warnings = 0;
  {
    Connection reader(std::make_shared<NameRegistry>(), Connection::Options{});
    ASSERT_TRUE(reader.OnTcpBytes(client, [&](const ReceivedMessage& m) {
      if (m.type == kPingType) ++pings;
      if (m.type == kTextType) ++warnings;
    }));
  }
  ASSERT_GE(pings, 4);
  ASSERT_GE(warnings, 1);
  std::vector<std::string> log;
  ServerSession session(CatalogFor(dir.filename().string()), Connection::Options{}, "peer",
                        [&](const std::string& l) { log.push_back(l); });
  session.Start(std::nullopt, {});
  ASSERT_TRUE(session.OnTcpBytes(client));
  EXPECT_EQ(session.pings_answered(), static_cast<std::uint64_t>(pings));
  std::multiset<Reply> pongs;
  for (int i = 0; i < pings; ++i) pongs.insert({"Tracker0", std::string(kPongType), 0});
  EXPECT_EQ(RepliesIn(session.connection().tcp_output()), pongs);
  ASSERT_EQ(log.size(), static_cast<std::size_t>(warnings));
  for (const auto& line : log) {
    EXPECT_EQ(line, "peer: client says (Tracker0): No response from server for >= 3 seconds");
  }
  EXPECT_EQ(session.dropped_messages(), 0u);
}

TEST(ServerSession, AClientAskingForRemoteLoggingIsServedWithoutIt) {
  // Cookie log mode '3' asks the peer to log both directions and is followed by a log description
  // (type -4, sender field = the mode, payload: two int32 lengths and two names). We do not log
  // for clients: the description is ignored and the client served as any other.
  auto catalog = std::make_shared<ServerCatalog>();
  catalog->AddTracker(Tracker0());
  ServerSession session(catalog, Connection::Options{}, "peer", nullptr);
  session.Start(std::nullopt, {});
  const auto cookie = MakeCookie('3');
  std::vector<std::uint8_t> bytes(cookie.begin(), cookie.end());
  std::vector<std::uint8_t> log_description;
  ByteWriter w(&log_description);
  w.PutI32(6);
  w.PutI32(7);
  w.PutString("in.log");
  w.PutZeros(1);
  w.PutString("out.log");
  w.PutZeros(1);
  AppendMessage(&bytes, Timestamp{}, 3, kLogDescription, 0, log_description);
  AppendMessage(&bytes, Timestamp{}, 0, kSenderDescription, 1, EncodeDescription("Tracker0"));
  AppendMessage(&bytes, Timestamp{}, 0, kTypeDescription, 2, EncodeDescription(kPingType));
  AppendMessage(&bytes, Timestamp{}, 0, 0, 3, {});
  ASSERT_TRUE(session.OnTcpBytes(bytes));
  EXPECT_EQ(session.connection().counters().unknown_system, 1u);
  EXPECT_EQ(session.pings_answered(), 1u);
  EXPECT_EQ(session.dropped_messages(), 0u);
}

// Our cookie, UDP description and descriptions are the reference server's bytes (PROTOCOL.md
// sections 2, 4 and 5), but for the header timestamp and the ids, which are each side's own.
TEST(ServerSession, CookieAndSystemMessagesAreTheReferenceServersBytes) {
  ServerSession session(CatalogFor("02"), Connection::Options{}, "peer", nullptr);
  // Capture 02's server announced UDP port 37077 on 127.0.0.1.
  session.Start(std::make_pair(std::string("127.0.0.1"), 37077), {});
  const auto& ours = session.connection().tcp_output();
  const auto reference = testing::ReadBytes(testing::TranscriptDir() / "02_null_tracker_udp_lob" /
                                            "server_to_client.bin");
  ASSERT_GE(ours.size(), 64u);
  EXPECT_TRUE(std::equal(ours.begin(), ours.begin() + kCookieSize, reference.begin()));
  // The UDP description: length 34, sender field = port, type -3, sequence 0, "127.0.0.1\0", pad.
  auto without_time = [](std::span<const std::uint8_t> m) {
    std::vector<std::uint8_t> v(m.begin(), m.end());
    std::fill(v.begin() + 4, v.begin() + 12, 0);
    return v;
  };
  EXPECT_EQ(without_time(std::span(ours).subspan(kCookieSize, 40)),
            without_time(std::span(reference).subspan(kCookieSize, 40)));
  // Every description we send is byte for byte one the reference sent (length, type, payload),
  // with the header's id and sequence set aside. Not the padding: the reference's is not always
  // zero (capture 05: the names it describes back carry stack bytes there).
  auto descriptions = [](std::span<const std::uint8_t> stream) {
    std::map<std::string, std::vector<std::uint8_t>> out;
    MessageStreamParser parser;
    parser.Feed(stream, [&](const Message& m) {
      if (m.header.type != kSenderDescription && m.header.type != kTypeDescription) return;
      const std::uint8_t* begin = m.payload.data() - kHeaderSize;
      std::vector<std::uint8_t> bytes(begin, begin + m.header.length);
      std::fill(bytes.begin() + 4, bytes.begin() + 16, 0);   // time, described id
      std::fill(bytes.begin() + 20, bytes.begin() + 24, 0);  // sequence
      out[*DecodeDescription(m.payload)] = bytes;
    });
    return out;
  };
  const auto our_descriptions = descriptions(ours);
  // Button types are described only by capture 08's server (the Fastrak with a stylus).
  std::map<std::string, std::vector<std::uint8_t>> reference_descriptions;
  for (const auto& dir : testing::TranscriptScenarios()) {
    reference_descriptions.merge(descriptions(testing::ReadBytes(dir / "server_to_client.bin")));
  }
  ASSERT_GE(our_descriptions.size(), 10u);
  for (const auto& [name, bytes] : our_descriptions) {
    SCOPED_TRACE(name);
    const auto it = reference_descriptions.find(name);
    ASSERT_NE(it, reference_descriptions.end());
    EXPECT_EQ(bytes, it->second);
  }
}

TEST(ServerSession, NoPongForUnservedDevice) {
  auto catalog = std::make_shared<ServerCatalog>();
  catalog->AddTracker(Tracker0());
  // A client asking for Tracker9 describes that sender and pings from it.
  auto client_names = std::make_shared<NameRegistry>();
  const int32_t t9 = client_names->AddSender("Tracker9");
  const int32_t t0 = client_names->AddSender("Tracker0");
  const int32_t ping = client_names->AddType(kPingType);
  Connection client(client_names, Connection::Options{});
  client.Start();
  client.Pack(t9, ping, Timestamp::Now(), {});
  std::vector<std::string> log;
  ServerSession session(catalog, Connection::Options{}, "peer",
                        [&](const std::string& l) { log.push_back(l); });
  session.Start(std::nullopt, {});
  ASSERT_TRUE(session.OnTcpBytes(client.tcp_output()));
  EXPECT_EQ(session.pings_answered(), 0u);
  EXPECT_TRUE(RepliesIn(session.connection().tcp_output()).empty());
  ASSERT_FALSE(log.empty());
  EXPECT_NE(log.back().find("Tracker9"), std::string::npos);

  client.tcp_output().clear();
  client.Pack(t0, ping, Timestamp::Now(), {});
  ASSERT_TRUE(session.OnTcpBytes(client.tcp_output()));
  EXPECT_EQ(session.pings_answered(), 1u);
  EXPECT_EQ(RepliesIn(session.connection().tcp_output()),
            (std::multiset<Reply>{{"Tracker0", std::string(kPongType), 0}}));
}

// A client's text message and its sender name reach the log; before they were logged raw, so a
// newline forged a second log line and ESC sequences drove the operator's terminal.
TEST(ServerSession, ClientTextIsLoggedPrintable) {
  auto catalog = std::make_shared<ServerCatalog>();
  catalog->AddTracker(Tracker0());
  auto client_names = std::make_shared<NameRegistry>();
  const int32_t sender = client_names->AddSender("Tracker0\x1b[2J");
  const int32_t text = client_names->AddType(kTextType);
  Connection client(client_names, Connection::Options{});
  client.Start();
  client.Pack(sender, text, Timestamp::Now(),
              EncodeText(TextMessage{TextSeverity::kNormal, 0,
                                     "ok\nclosed peer: forged\r\x1b]0;title\x07 caf\xc3\xa9"}));
  std::vector<std::string> log;
  ServerSession session(catalog, Connection::Options{}, "peer",
                        [&](const std::string& l) { log.push_back(l); });
  session.Start(std::nullopt, {});
  ASSERT_TRUE(session.OnTcpBytes(client.tcp_output()));
  ASSERT_EQ(log.size(), 1u);
  EXPECT_EQ(log[0],
            "peer: client says (Tracker0\\x1b[2J): "
            "ok\\x0aclosed peer: forged\\x0d\\x1b]0;title\\x07 caf\xc3\xa9");
}

TEST(ServerSession, GarbageAndOversizedCloseOnlyWithLog) {
  auto catalog = std::make_shared<ServerCatalog>();
  catalog->AddTracker(Tracker0());
  std::vector<std::string> log;
  ServerSession session(catalog, Connection::Options{.max_message_length = 4096}, "peer",
                        [&](const std::string& l) { log.push_back(l); });
  session.Start(std::nullopt, {});
  const auto cookie = MakeCookie();
  std::vector<std::uint8_t> bytes(cookie.begin(), cookie.end());
  // Undescribed ids and an unknown system type: dropped, connection stays.
  AppendMessage(&bytes, Timestamp{}, 5, 9, 0, std::vector<std::uint8_t>(16, 0));
  AppendMessage(&bytes, Timestamp{}, 0, -77, 0, {});
  ASSERT_TRUE(session.OnTcpBytes(bytes));
  EXPECT_EQ(session.dropped_messages(), 1u);
  std::vector<std::uint8_t> huge(24, 0);
  StoreU32(100000, huge.data());
  EXPECT_FALSE(session.OnTcpBytes(huge));
  // The owner logs the close with error() as the reason; the session saying it too put the reason
  // twice in the log for every such connection.
  EXPECT_NE(session.error().find("over the limit"), std::string::npos);
  for (const std::string& line : log) EXPECT_EQ(line.find("over the limit"), std::string::npos);
}

// Appends a message whose header length counts the padding (VRPN's outdated Format_Of_Protocol.txt
// says so; the reference reads such a peer fine, as the padding then is part of the payload).
void AppendPaddedLengthMessage(std::vector<std::uint8_t>* out, std::int32_t sender,
                               std::int32_t type, std::span<const std::uint8_t> payload) {
  std::vector<std::uint8_t> padded(payload.begin(), payload.end());
  padded.resize(Ceil8(padded.size()), 0);
  AppendMessage(out, Timestamp{}, sender, type, 0, padded);
}

TEST(ServerSession, AClientWhoseLengthsCountThePaddingIsUnderstood) {
  auto catalog = std::make_shared<ServerCatalog>();
  catalog->AddTracker(Tracker0());
  ServerSession session(catalog, Connection::Options{}, "peer", nullptr);
  session.Start(std::nullopt, {});
  const auto cookie = MakeCookie();
  std::vector<std::uint8_t> bytes(cookie.begin(), cookie.end());
  // "Tracker0" (4 + 9 bytes) and the ping type (4 + 23 bytes) both need padding.
  AppendPaddedLengthMessage(&bytes, 3, kSenderDescription, EncodeDescription("Tracker0"));
  AppendPaddedLengthMessage(&bytes, 7, kTypeDescription, EncodeDescription(kPingType));
  AppendPaddedLengthMessage(&bytes, 8, kTypeDescription, EncodeDescription(kRequestWorkspaceType));
  AppendPaddedLengthMessage(&bytes, 3, 7, {});
  AppendPaddedLengthMessage(&bytes, 3, 8, {});
  ASSERT_TRUE(session.OnTcpBytes(bytes));
  EXPECT_EQ(session.connection().counters().bad_description, 0u);
  EXPECT_EQ(session.pings_answered(), 1u);
  EXPECT_EQ(RepliesIn(session.connection().tcp_output()),
            (std::multiset<Reply>{{"Tracker0", std::string(kPongType), 0},
                                  {"Tracker0", std::string(kWorkspaceType), kWorkspaceSize}}));
  EXPECT_EQ(session.dropped_messages(), 0u);
}

TEST(ServerSession, RequestsAreAnsweredWhateverTheirPayloadAsByTheReference) {
  // The reference's handlers (vrpn_Tracker::handle_t2r_request, handle_u2s_request,
  // handle_workspace_request) never look at the payload: a client that sends one gets its answer.
  auto catalog = std::make_shared<ServerCatalog>();
  TrackerSpec tracker = Tracker0();
  tracker.num_sensors = 2;
  catalog->AddTracker(tracker);
  ServerSession session(catalog, Connection::Options{}, "peer", nullptr);
  session.Start(std::nullopt, {});
  auto names = std::make_shared<NameRegistry>();
  const int32_t t0 = names->AddSender("Tracker0");
  const int32_t to_room = names->AddType(kRequestToRoomType);
  const int32_t unit_to_sensor = names->AddType(kRequestUnitToSensorType);
  const int32_t workspace = names->AddType(kRequestWorkspaceType);
  Connection client(names, Connection::Options{});
  client.Start();
  const std::vector<std::uint8_t> eight(8, 0);
  client.Pack(t0, to_room, Timestamp{}, eight);
  client.Pack(t0, unit_to_sensor, Timestamp{}, std::vector<std::uint8_t>(3, 1));
  client.Pack(t0, workspace, Timestamp{}, eight);
  ASSERT_TRUE(session.OnTcpBytes(client.tcp_output()));
  EXPECT_EQ(RepliesIn(session.connection().tcp_output()),
            (std::multiset<Reply>{{"Tracker0", std::string(kToRoomType), kToRoomSize},
                                  {"Tracker0", std::string(kUnitToSensorType), kUnitToSensorSize},
                                  {"Tracker0", std::string(kUnitToSensorType), kUnitToSensorSize},
                                  {"Tracker0", std::string(kWorkspaceType), kWorkspaceSize}}));
  EXPECT_EQ(session.dropped_messages(), 0u);
}

TEST(ServerSession, StateChangingRequestsAreIgnoredAndLogSpamIsCapped) {
  auto catalog = std::make_shared<ServerCatalog>();
  catalog->AddTracker(Tracker0());
  std::vector<std::string> log;
  ServerSession session(catalog, Connection::Options{}, "peer",
                        [&](const std::string& l) { log.push_back(l); });
  session.Start(std::nullopt, {});
  auto names = std::make_shared<NameRegistry>();
  const int32_t t0 = names->AddSender("Tracker0");
  const int32_t rate = names->AddType(kSetUpdateRateType);
  Connection client(names, Connection::Options{});
  client.Start();
  for (int i = 0; i < 100; ++i) client.Pack(t0, rate, Timestamp{}, std::vector<std::uint8_t>(8, 0));
  const std::size_t before = session.connection().tcp_output().size();
  ASSERT_TRUE(session.OnTcpBytes(client.tcp_output()));
  EXPECT_EQ(session.connection().tcp_output().size(), before);  // no reply, no state change
  EXPECT_EQ(log.size(), static_cast<std::size_t>(ServerSession::kMaxLogLines) + 1);
}

TEST(ServerSession, DescriptionsOverUdpCannotRedirectTheClientsStream) {
  // A lob client's data socket on the server takes datagrams from anyone who finds its port. A
  // stranger's datagram re-describing the client's sender id as another served device must not
  // change which device the client is taken to use (observed: the client's Tracker0 stream
  // switched to Tracker1 after one such datagram).
  auto catalog = std::make_shared<ServerCatalog>();
  catalog->AddTracker(Tracker0());
  TrackerSpec tracker1;
  tracker1.name = "Tracker1";
  catalog->AddTracker(tracker1);
  ServerSession session(catalog, Connection::Options{}, "peer", nullptr);
  session.Start(std::make_pair(std::string("127.0.0.1"), 40000), {});
  auto names = std::make_shared<NameRegistry>();
  names->AddSender("Tracker0");
  Connection client(names, Connection::Options{});
  client.Start();
  ASSERT_TRUE(session.OnTcpBytes(client.tcp_output()));
  ASSERT_TRUE(session.connection().handshake_done());
  const PeerNameTable& peer = session.connection().peer_senders();
  ASSERT_TRUE(peer.Contains("Tracker0"));
  const auto version = peer.version();

  std::vector<std::uint8_t> datagram;
  AppendMessage(&datagram, Timestamp{}, 0, kSenderDescription, 0, EncodeDescription("Tracker1"));
  AppendMessage(&datagram, Timestamp{}, 0, kTypeDescription, 1, EncodeDescription("x"));
  session.OnDatagram(datagram);
  EXPECT_TRUE(peer.Contains("Tracker0"));
  EXPECT_FALSE(peer.Contains("Tracker1"));
  EXPECT_EQ(peer.version(), version);
  EXPECT_EQ(session.connection().counters().bad_description, 2u);
}

TEST(ServerSession, ReferenceClientUsesTheDeviceItPingsFromNotTheNamesItDescribesBack) {
  // Capture 08: the reference client opened Tracker0 only, pinged from it, then described back
  // the server's Stylus0 (the reference library describes back every name it is told).
  const auto dir = testing::TranscriptDir() / "08_fastrak_emulated_udp_lob_stylus_cm";
  auto catalog = CatalogFor(dir.filename().string());
  ServerSession session(catalog, Connection::Options{}, "peer", nullptr);
  session.Start(std::make_pair(std::string("127.0.0.1"), 40000), {});
  EXPECT_FALSE(session.uses_any_device());
  ASSERT_TRUE(session.OnTcpBytes(testing::ReadBytes(dir / "client_to_server.bin")));
  ASSERT_TRUE(session.connection().peer_senders().Contains("Stylus0"));
  EXPECT_TRUE(session.uses_any_device());
  EXPECT_TRUE(session.Uses(catalog->tracker_sender(0)));
  EXPECT_FALSE(session.Uses(catalog->button_sender(0)));
  EXPECT_FALSE(session.Uses(0));  // VRPN Control

  // A ping in a datagram does not count (only TCP ones do, like descriptions): the client's
  // sender 2 is Stylus0, its type 16 the ping, in that capture.
  std::vector<std::uint8_t> datagram;
  AppendMessage(&datagram, Timestamp{}, 2, 16, 0, {});
  session.OnDatagram(datagram);
  EXPECT_EQ(session.pings_answered(), 2u);  // answered, as the reference does
  EXPECT_FALSE(session.Uses(catalog->button_sender(0)));
}

TEST(ServerSession, APingFromAButtonIsAnsweredWithItsStates) {
  // The reference button server sends its states on a new connection and again on every ping
  // from its name (vrpn_Button_Filter::handle_ping_message: "make sure that the other side hears
  // the initial button states"). A button remote opened on a connection that is already up (a
  // second device of the same client) learns them only that way. Capture 08's client (Tracker0)
  // opens Stylus0 too: its sender 2 is Stylus0 (described back in the capture), type 16 the ping.
  const auto dir = testing::TranscriptDir() / "08_fastrak_emulated_udp_lob_stylus_cm";
  std::vector<std::vector<std::int32_t>> buttons{{0}};
  ServerSession session(CatalogFor(dir.filename().string()), Connection::Options{}, "peer",
                        nullptr);
  session.Start(std::make_pair(std::string("127.0.0.1"), 40000), buttons);
  ASSERT_TRUE(session.OnTcpBytes(testing::ReadBytes(dir / "client_to_server.bin")));
  const auto before = RepliesIn(session.connection().tcp_output());
  buttons[0][0] = 1;  // the stylus button was pressed since the client connected
  std::vector<std::uint8_t> ping;
  AppendMessage(&ping, Timestamp{}, 2, 16, 30, {});
  ASSERT_TRUE(session.OnTcpBytes(ping));
  auto expected = before;
  expected.insert({"Stylus0", std::string(kButtonStatesType), 8});
  expected.insert({"Stylus0", std::string(kPongType), 0});
  EXPECT_EQ(RepliesIn(session.connection().tcp_output()), expected);
  // The states are the current ones.
  std::vector<std::vector<std::int32_t>> states;
  MessageStreamParser parser;
  std::map<int32_t, std::string> types;
  parser.Feed(session.connection().tcp_output(), [&](const Message& m) {
    if (m.header.type == kTypeDescription) types[m.header.sender] = *DecodeDescription(m.payload);
    if (m.header.type >= 0 && types[m.header.type] == kButtonStatesType) {
      states.push_back(*DecodeButtonStates(m.payload));
    }
  });
  ASSERT_EQ(states.size(), 2u);
  EXPECT_EQ(states[0], std::vector<std::int32_t>{0});
  EXPECT_EQ(states[1], std::vector<std::int32_t>{1});
}

}  // namespace
}  // namespace trackcal::vrpn
