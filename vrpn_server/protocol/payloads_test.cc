#include "vrpn_server/protocol/payloads.h"

#include <gtest/gtest.h>

#include <cmath>

#include "tests/test_utils.h"
#include "vrpn_server/protocol/wire.h"

namespace trackcal::vrpn {
namespace {

std::vector<std::uint8_t> Hex(const std::string& hex) {
  std::vector<std::uint8_t> out;
  for (std::size_t i = 0; i + 1 < hex.size(); i += 2) {
    out.push_back(static_cast<std::uint8_t>(std::stoi(hex.substr(i, 2), nullptr, 16)));
  }
  return out;
}

TEST(PosQuat, Nominal) {
  // Transcript 04 offset 1216 + 24: pos (0.1, -0.2, 0.3), quat (1,2,3,4)/sqrt(30), sensor 0.
  const auto expected = Hex(
      "0000000000000000"
      "3fb999999999999abfc999999999999a3fd3333333333333"
      "3fc75e9746a0b0983fd75e9746a0b0983fe186f174f884723fe75e9746a0b098");
  PosQuat p;
  p.transmitter_from_receiver.translation = Eigen::Vector3d(0.1, -0.2, 0.3);
  p.transmitter_from_receiver.rotation = QuaternionFromXyzw(
      0.18257418583505536, 0.36514837167011072, 0.54772255750516607, 0.73029674334022143);
  EXPECT_EQ(EncodePosQuat(p), expected);
  const auto decoded = DecodePosQuat(expected);
  ASSERT_TRUE(decoded);
  EXPECT_EQ(decoded->sensor, 0);
  EXPECT_EQ(decoded->transmitter_from_receiver.translation, p.transmitter_from_receiver.translation);
  EXPECT_EQ(decoded->transmitter_from_receiver.rotation.coeffs(),
            p.transmitter_from_receiver.rotation.coeffs());
}

TEST(PosQuat, PadWordRepeatsSensorAndWrongLengthRejected) {
  PosQuat p;
  p.sensor = 3;
  auto bytes = EncodePosQuat(p);
  ASSERT_EQ(bytes.size(), kPosQuatSize);
  EXPECT_EQ(LoadU32(bytes.data()), 3u);
  EXPECT_EQ(LoadU32(bytes.data() + 4), 3u);
  bytes.push_back(0);
  EXPECT_FALSE(DecodePosQuat(bytes));
  bytes.resize(63);
  EXPECT_FALSE(DecodePosQuat(bytes));
}

TEST(TrackerMessages, ExactLengthsAndRoundTrip) {
  auto& rng = testing::TestRng();
  TrackerRate rate;
  rate.sensor = 1;
  rate.linear = Eigen::Vector3d(1, -2, 3);
  rate.delta_rotation = testing::RandomRotation(rng);
  rate.dt = 0.25;
  const auto rate_bytes = EncodeTrackerRate(rate);
  ASSERT_EQ(rate_bytes.size(), kVelocitySize);
  const auto rate2 = DecodeTrackerRate(rate_bytes);
  ASSERT_TRUE(rate2);
  EXPECT_EQ(rate2->dt, 0.25);
  EXPECT_EQ(rate2->linear, rate.linear);
  EXPECT_EQ(rate2->delta_rotation.coeffs(), rate.delta_rotation.coeffs());

  const Rigid3d room(testing::RandomRotation(rng), Eigen::Vector3d(0, 0, -0.28));
  const auto room_bytes = EncodeToRoom(room);
  ASSERT_EQ(room_bytes.size(), kToRoomSize);
  EXPECT_EQ(DecodeToRoom(room_bytes)->translation, room.translation);
  EXPECT_FALSE(DecodeToRoom(rate_bytes));

  UnitToSensor u;
  u.sensor = 7;
  const auto u_bytes = EncodeUnitToSensor(u);
  ASSERT_EQ(u_bytes.size(), kUnitToSensorSize);
  EXPECT_EQ(LoadU32(u_bytes.data() + 4), 0u);  // pad word 0, as the reference (transcript 06)
  EXPECT_EQ(DecodeUnitToSensor(u_bytes)->sensor, 7);

  const auto ws_bytes = EncodeWorkspace(Workspace{});
  ASSERT_EQ(ws_bytes.size(), kWorkspaceSize);
  EXPECT_EQ(DecodeWorkspace(ws_bytes)->min, Eigen::Vector3d(-0.2, -0.2, -0.1));
  EXPECT_FALSE(DecodeWorkspace(u_bytes));
}

TEST(TextMessage, FixedSizeZeroFilledAndParsedUpToNul) {
  TextMessage m{TextSeverity::kError, 4, "Tracker failed"};
  auto bytes = EncodeText(m);
  ASSERT_EQ(bytes.size(), kTextSize);
  for (std::size_t i = 8 + m.text.size(); i < bytes.size(); ++i) ASSERT_EQ(bytes[i], 0);
  // Garbage after the NUL (the reference leaks stack bytes there) is ignored.
  bytes[8 + m.text.size() + 5] = 'Z';
  const auto d = DecodeText(bytes);
  ASSERT_TRUE(d);
  EXPECT_EQ(d->text, "Tracker failed");
  EXPECT_EQ(d->severity, TextSeverity::kError);
  EXPECT_EQ(d->level, 4u);
  // Overlong text is truncated so the NUL still fits.
  const auto long_bytes = EncodeText(TextMessage{TextSeverity::kNormal, 0, std::string(2000, 'a')});
  ASSERT_EQ(long_bytes.size(), kTextSize);
  EXPECT_EQ(DecodeText(long_bytes)->text.size(), kTextFieldSize - 1);
  bytes.resize(1031);
  EXPECT_FALSE(DecodeText(bytes));
}

TEST(Buttons, RoundTrip) {
  const auto change = EncodeButtonChange(ButtonChange{2, 1});
  ASSERT_EQ(change.size(), kButtonChangeSize);
  // The reference (vrpn_Button::encode_to in VRPN 07.x) buffers int32 button, then int32 state,
  // big-endian, and nothing else: no count in front (a third-party protocol description shows
  // one; the reference's encoder and its decoder, which reads exactly these two, do not).
  EXPECT_EQ(change, Hex("0000000200000001"));
  EXPECT_EQ(DecodeButtonChange(change)->button, 2);
  EXPECT_EQ(DecodeButtonChange(change)->state, 1);
  EXPECT_EQ(EncodeButtonChange(ButtonChange{0, 0}), Hex("0000000000000000"));
  EXPECT_FALSE(DecodeButtonChange(Hex("000000010000000000000001")));  // a count-prefixed form
  const std::vector<std::int32_t> states = {1};
  const auto sb = EncodeButtonStates(states);
  EXPECT_EQ(sb, Hex("0000000100000001"));  // transcript 08: Stylus0 states, 8 bytes
  EXPECT_EQ(*DecodeButtonStates(sb), states);
  EXPECT_FALSE(DecodeButtonStates(Hex("00000002")));
  EXPECT_FALSE(DecodeButtonStates(Hex("ffffffff")));
}

TEST(Description, Nominal) {
  const auto d = EncodeDescription("vrpn_Tracker Pos_Quat");
  // Transcript 01: N = 22 counts the NUL.
  ASSERT_EQ(d.size(), 4u + 22u);
  EXPECT_EQ(LoadU32(d.data()), 22u);
  EXPECT_EQ(*DecodeDescription(d), "vrpn_Tracker Pos_Quat");
}

TEST(Description, InvalidRejected) {
  EXPECT_THROW(EncodeDescription(""), std::invalid_argument);
  EXPECT_THROW(EncodeDescription(std::string(96, 'a')), std::invalid_argument);
  EXPECT_NO_THROW(EncodeDescription(std::string(95, 'a')));
  auto d = EncodeDescription("Tracker0");
  d[3] = 20;  // N disagrees with the payload
  EXPECT_FALSE(DecodeDescription(d));
  d = EncodeDescription("Tracker0");
  d.back() = 'x';  // no NUL
  EXPECT_FALSE(DecodeDescription(d));
  std::vector<std::uint8_t> huge(120, 'a');
  StoreU32(116, huge.data());
  huge.back() = 0;
  EXPECT_FALSE(DecodeDescription(huge));
}

TEST(Description, BytesAfterTheNamedLengthAreIgnoredAsByTheReference) {
  // The reference copies the payload and puts the NUL at N (vrpn_Connection.C,
  // handle_sender_message and handle_type_message): bytes after the N name bytes are ignored. A
  // peer written from VRPN's outdated Format_Of_Protocol.txt counts the padding in the header
  // length, so its descriptions carry up to 7 bytes more than 4 + N.
  auto d = EncodeDescription("vrpn_Tracker Pos_Quat");  // 26 bytes
  d.resize(Ceil8(d.size()), 0);                         // 32: the padding inside the payload
  EXPECT_EQ(DecodeDescription(d), "vrpn_Tracker Pos_Quat");
  d = EncodeDescription("Tracker0");
  d.push_back('x');  // not a NUL after it either
  EXPECT_EQ(DecodeDescription(d), "Tracker0");
}

TEST(LobRequest, Nominal) {
  // Transcript 02 datagram.
  const auto bytes = Hex("3132372e302e302e3120333733383500");
  const auto req = DecodeLobRequest(bytes);
  ASSERT_TRUE(req);
  EXPECT_EQ(req->host, "127.0.0.1");
  EXPECT_EQ(req->port, 37385);
  EXPECT_EQ(EncodeLobRequest(*req), bytes);
}

TEST(LobRequest, InvalidRejected) {
  auto decode = [](const std::string& s) {
    return DecodeLobRequest(std::vector<std::uint8_t>(s.begin(), s.end()));
  };
  EXPECT_FALSE(decode("127.0.0.1 80"));         // port below 1024
  EXPECT_FALSE(decode("127.0.0.1 70000"));      // port above 65535
  EXPECT_FALSE(decode("127.0.0.1"));            // one token
  EXPECT_FALSE(decode("127.0.0.1; 4000"));      // bad host character
  EXPECT_FALSE(decode("127.0.0.1 4000x"));      // junk after the port
  EXPECT_FALSE(decode(""));
  EXPECT_TRUE(decode("127.0.0.1 4000"));       // NUL is optional
  EXPECT_FALSE(decode("127.0.0.1 +-4000"));
  EXPECT_FALSE(decode("127.0.0.1 -4000"));
}

// sscanf("%s %d") in the reference skips leading whitespace and any run of it between the tokens;
// a hand-written client that pads the datagram must still get its call-back.
TEST(LobRequest, WhitespaceAsTheReferenceReadsIt) {
  auto decode = [](const std::string& s) {
    return DecodeLobRequest(std::vector<std::uint8_t>(s.begin(), s.end()));
  };
  for (const std::string s :
       {" 127.0.0.1 4000", "127.0.0.1  4000", "127.0.0.1\t4000\n", "\r\n10.0.0.2 \t +4000 "}) {
    const auto req = decode(s);
    ASSERT_TRUE(req) << s;
    EXPECT_EQ(req->port, 4000) << s;
    EXPECT_TRUE(req->host == "127.0.0.1" || req->host == "10.0.0.2") << s;
  }
}

}  // namespace
}  // namespace trackcal::vrpn
