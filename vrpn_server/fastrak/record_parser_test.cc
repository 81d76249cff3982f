#include "vrpn_server/fastrak/record_parser.h"

#include <gtest/gtest.h>

#include <cmath>
#include <fstream>
#include <random>

#include "tests/test_utils.h"
#include "vrpn_server/fastrak/fake_fastrak.h"
#include "vrpn_server/fastrak/protocol.h"

namespace trackcal::fastrak {
namespace {

using testing::MakeRecord;
using TimePoint = std::chrono::system_clock::time_point;

std::string ReadTranscript(const std::string& scenario, const std::string& file) {
  const auto path = trackcal::testing::SourceDir() / "tests/data/fastrak/driver" / scenario / file;
  std::ifstream in(path, std::ios::binary);
  EXPECT_TRUE(in) << path;
  return std::string(std::istreambuf_iterator<char>(in), {});
}

std::span<const uint8_t> Bytes(const std::string& s) {
  return {reinterpret_cast<const uint8_t*>(s.data()), s.size()};
}

// Transcript 07's emulated poses: the client of the reference server saw exactly these.
const Eigen::Vector3d kStation1Position(0.254, -0.127, 0.508);
const Eigen::Vector3d kStation2Position(0.0381, 0.0635, -0.0889);
Eigen::Quaterniond Station1Rotation() {
  const double s = std::sqrt(30.0);
  return QuaternionFromWxyz(4 / s, 1 / s, 2 / s, 3 / s);
}
// Positions are float32 inches (7 significant digits): 20 in has a float spacing of 2e-6 in, so
// 1e-7 m bounds the rounding; quaternion components are float32 of values < 1: spacing 6e-8.
constexpr double kPositionTolM = 1e-7;
constexpr double kQuaternionTol = 1e-7;

void ExpectTranscriptPoses(const std::vector<FastrakReport>& reports) {
  for (const FastrakReport& r : reports) {
    ASSERT_TRUE(r.sensor == 0 || r.sensor == 1);
    const Eigen::Vector3d expected_p = r.sensor == 0 ? kStation1Position : kStation2Position;
    const Eigen::Quaterniond expected_q =
        r.sensor == 0 ? Station1Rotation() : Eigen::Quaterniond::Identity();
    EXPECT_LT((r.position_m - expected_p).norm(), kPositionTolM) << r.position_m.transpose();
    EXPECT_LT((r.rotation.coeffs() - expected_q.coeffs()).cwiseAbs().maxCoeff(), kQuaternionTol);
    EXPECT_EQ(r.status, ' ');
    EXPECT_FALSE(r.stylus_pressed.has_value());
  }
}

TEST(RecordParser, Nominal) {
  // Transcript 07: the 55-byte status record then 32-byte records, sensors alternating.
  const std::string bytes = ReadTranscript("07_fastrak_emulated_tcp", "serial_device_to_host.bin");
  ASSERT_EQ(bytes.size(), 1024u);
  RecordParser parser({}, Units::kInches);
  std::vector<FastrakReport> reports;
  parser.Feed(Bytes(bytes.substr(kStatusRecordSize)), TimePoint(), &reports);
  // (1024 - 55) / 32 = 30 complete records, 9 bytes of the 31st waiting.
  ASSERT_EQ(reports.size(), 30u);
  EXPECT_EQ(parser.discarded_bytes(), 0u);
  EXPECT_EQ(parser.buffered_bytes(), 9u);
  for (size_t i = 0; i < reports.size(); ++i) EXPECT_EQ(reports[i].sensor, static_cast<int>(i % 2));
  ExpectTranscriptPoses(reports);
}

TEST(RecordParser, WireQuaternionOrderAndValuesOfTheFirstRecord) {
  const std::string bytes = ReadTranscript("07_fastrak_emulated_tcp", "serial_device_to_host.bin");
  const std::optional<RawRecord> raw =
      DecodeRecord(reinterpret_cast<const uint8_t*>(bytes.data()) + kStatusRecordSize, kRecordSize);
  ASSERT_TRUE(raw.has_value());
  EXPECT_EQ(raw->station, 1);
  EXPECT_EQ(raw->position[0], 10.0f);
  EXPECT_EQ(raw->position[1], -5.0f);
  EXPECT_EQ(raw->position[2], 20.0f);
  // Wire order is W, X, Y, Z = (4, 1, 2, 3) / sqrt(30).
  EXPECT_EQ(raw->wxyz[0], static_cast<float>(4 / std::sqrt(30.0)));
  EXPECT_EQ(raw->wxyz[1], static_cast<float>(1 / std::sqrt(30.0)));
  // The test record builder produces these very bytes.
  EXPECT_EQ(MakeRecord(1, {10, -5, 20}, {raw->wxyz[0], raw->wxyz[1], raw->wxyz[2], raw->wxyz[3]}),
            bytes.substr(kStatusRecordSize, kRecordSize));
  const FastrakReport report = ConvertRecord(*raw, Units::kInches, TimePoint());
  EXPECT_EQ(report.sensor, 0);
  EXPECT_NEAR(report.rotation.w(), 0.73029674334022143, kQuaternionTol);
  EXPECT_NEAR(report.rotation.x(), 0.18257418583505536, kQuaternionTol);
}

TEST(RecordParser, StatusRecordBeforeRecordsIsSkipped) {
  const std::string bytes = ReadTranscript("07_fastrak_emulated_tcp", "serial_device_to_host.bin");
  RecordParser parser({}, Units::kInches);
  std::vector<FastrakReport> reports;
  parser.Feed(Bytes(bytes), TimePoint(), &reports);
  EXPECT_EQ(reports.size(), 30u);
  EXPECT_EQ(parser.discarded_bytes(), kStatusRecordSize);
  ExpectTranscriptPoses(reports);
}

TEST(RecordParser, ChunkingDoesNotMatterAndRecordsTakeTheTimeOfTheirFirstByte) {
  // Transcript 08: a device that was already streaming; join at an arbitrary byte.
  const std::string bytes =
      ReadTranscript("08_fastrak_emulated_udp_lob_stylus_cm", "serial_device_to_host.bin");
  RecordParser parser({}, Units::kInches);
  std::vector<FastrakReport> reports;
  const size_t start = 17;  // inside the first record
  for (size_t i = start; i < bytes.size(); ++i) {
    parser.Feed(Bytes(bytes.substr(i, 1)), TimePoint(std::chrono::microseconds(i)), &reports);
  }
  // The first partial record is skipped; every later record is intact.
  ASSERT_EQ(reports.size(), (bytes.size() - 32) / 32);
  ExpectTranscriptPoses(reports);
  for (size_t k = 0; k < reports.size(); ++k) {
    EXPECT_EQ(reports[k].time, TimePoint(std::chrono::microseconds(32 * (k + 1))));
  }
}

TEST(RecordParser, CentimetresAreConvertedCorrectly) {
  // After `u` the device sends centimetres: 10 in = 25.4 cm. The reference multiplies by 0.0254
  // and serves 0.64516 m (transcript 08); we must serve 0.254 m.
  const std::string record = MakeRecord(1, {25.4f, -12.7f, 50.8f}, {1, 0, 0, 0});
  RecordParser parser({}, Units::kCentimetres);
  std::vector<FastrakReport> reports;
  parser.Feed(Bytes(record), TimePoint(), &reports);
  ASSERT_EQ(reports.size(), 1u);
  // 25.4 is not exact in float32 (spacing 2e-6 cm): 1e-7 m.
  EXPECT_LT((reports[0].position_m - kStation1Position).norm(), kPositionTolM);
  parser.set_units(Units::kInches);
  reports.clear();
  parser.Feed(Bytes(MakeRecord(1, {10, -5, 20}, {1, 0, 0, 0})), TimePoint(), &reports);
  ASSERT_EQ(reports.size(), 1u);
  EXPECT_LT((reports[0].position_m - kStation1Position).norm(), kPositionTolM);
}

TEST(RecordParser, ResynchronisesAfterGarbageWithoutLosingGoodRecords) {
  std::mt19937_64& rng = trackcal::testing::TestRng();
  std::uniform_int_distribution<int> byte(0, 255);
  std::uniform_int_distribution<int> length(0, 40);
  // Garbage biased towards record-start bytes ('0', '1'..'4', ' ') to provoke false starts.
  const std::string tricky = "0123 0 01 02 0";
  std::uniform_int_distribution<size_t> tricky_pick(0, tricky.size() - 1);
  for (int trial = 0; trial < 200; ++trial) {
    std::string stream;
    int good = 0;
    for (int k = 0; k < 20; ++k) {
      const int n = length(rng);
      for (int i = 0; i < n; ++i) {
        stream.push_back(i % 2 ? static_cast<char>(byte(rng)) : tricky[tricky_pick(rng)]);
      }
      stream += MakeRecord(1 + k % 2, k % 2 ? std::array<float, 3>{1.5f, 2.5f, -3.5f}
                                            : std::array<float, 3>{10, -5, 20},
                           k % 2 ? std::array<float, 4>{1, 0, 0, 0}
                                 : std::array<float, 4>{0.73029674f, 0.18257418f, 0.36514837f,
                                                        0.54772256f});
      ++good;
    }
    RecordParser parser({}, Units::kInches);
    std::vector<FastrakReport> reports;
    // Feed in random chunks.
    size_t pos = 0;
    while (pos < stream.size()) {
      const size_t n = std::min<size_t>(stream.size() - pos, 1 + length(rng));
      parser.Feed(Bytes(stream.substr(pos, n)), TimePoint(), &reports);
      pos += n;
    }
    // Garbage can, very rarely, complete a valid-looking record only if it contains a unit
    // quaternion and a final space in the right place; the biased garbage here cannot.
    ASSERT_EQ(reports.size(), static_cast<size_t>(good)) << "trial " << trial;
    ExpectTranscriptPoses(reports);
  }
}

TEST(RecordParser, TruncatedRecordLosesOnlyItself) {
  const std::string a = MakeRecord(1, {10, -5, 20}, {1, 0, 0, 0});
  const std::string b = MakeRecord(2, {1.5f, 2.5f, -3.5f}, {1, 0, 0, 0});
  for (size_t keep = 1; keep < a.size(); ++keep) {
    RecordParser parser({}, Units::kInches);
    std::vector<FastrakReport> reports;
    parser.Feed(Bytes(a.substr(0, keep) + b + a), TimePoint(), &reports);
    ASSERT_EQ(reports.size(), 2u) << "keep " << keep;
    EXPECT_EQ(reports[0].sensor, 1);
    EXPECT_EQ(reports[1].sensor, 0);
  }
}

TEST(RecordParser, StylusRecords) {
  const std::array<float, 4> identity{1, 0, 0, 0};
  RecordParser parser({true, false, false, false}, Units::kInches);
  std::vector<FastrakReport> reports;
  const std::string stream = MakeRecord(1, {1, 2, 3}, identity, ' ', 1) + MakeRecord(2, {1, 2, 3}, identity) +
                             MakeRecord(1, {1, 2, 3}, identity, 'E', 0);
  EXPECT_EQ(MakeRecord(1, {1, 2, 3}, identity, ' ', 1).size(), kStylusRecordSize);
  parser.Feed(Bytes(stream), TimePoint(), &reports);
  ASSERT_EQ(reports.size(), 3u);
  EXPECT_EQ(reports[0].stylus_pressed, std::optional<bool>(true));
  EXPECT_FALSE(reports[1].stylus_pressed.has_value());
  EXPECT_EQ(reports[2].stylus_pressed, std::optional<bool>(false));
  EXPECT_EQ(reports[2].status, 'E');
}

TEST(DecodeRecord, RejectsBrokenFraming) {
  const std::string good = MakeRecord(1, {10, -5, 20}, {1, 0, 0, 0});
  auto decode = [](const std::string& r) {
    return DecodeRecord(reinterpret_cast<const uint8_t*>(r.data()), r.size()).has_value();
  };
  EXPECT_TRUE(decode(good));
  std::string bad = good;
  bad[0] = '1';
  EXPECT_FALSE(decode(bad));
  bad = good;
  bad[1] = '5';
  EXPECT_FALSE(decode(bad));
  bad = good;
  bad[2] = '#';
  EXPECT_FALSE(decode(bad));
  bad = good;
  bad[31] = 'x';
  EXPECT_FALSE(decode(bad));
  EXPECT_FALSE(decode(MakeRecord(1, {10, -5, 20}, {0.5f, 0, 0, 0})));  // not a unit quaternion
  EXPECT_FALSE(decode(MakeRecord(1, {NAN, 0, 0}, {1, 0, 0, 0})));
  EXPECT_FALSE(decode(MakeRecord(1, {1e6f, 0, 0}, {1, 0, 0, 0})));
  std::string stylus = MakeRecord(1, {1, 2, 3}, {1, 0, 0, 0}, ' ', 1);
  stylus[32] = '7';
  EXPECT_FALSE(decode(stylus));
}

TEST(ParseStatusRecord, Nominal) {
  const std::string bytes = ReadTranscript("07_fastrak_emulated_tcp", "serial_device_to_host.bin");
  std::string why;
  const auto status = ParseStatusRecord(bytes.substr(0, kStatusRecordSize), &why);
  ASSERT_TRUE(status.has_value()) << why;
  EXPECT_EQ(status->station, 1);
  EXPECT_EQ(status->configuration, 0x0A0u);
  EXPECT_EQ(status->bit_errors, 0u);
  EXPECT_EQ(status->firmware_version, "3.00");
  EXPECT_EQ(status->system_id, "EMULATED POLHEMUS FASTRAK");
  EXPECT_EQ(testing::MakeStatusRecord(), bytes.substr(0, kStatusRecordSize));
}

TEST(ParseStatusRecord, RejectsEveryBrokenField) {
  const std::string good = testing::MakeStatusRecord();
  struct Case {
    size_t index;
    char value;
  };
  for (const Case& c : std::vector<Case>{{0, '0'}, {1, '7'}, {2, 's'}, {3, 'G'}, {8, ' '}, {10, 'x'},
                                         {30, '\x01'}, {53, ' '}, {54, '\r'}}) {
    std::string bad = good;
    bad[c.index] = c.value;
    std::string why;
    EXPECT_FALSE(ParseStatusRecord(bad, &why).has_value()) << "byte " << c.index;
    EXPECT_FALSE(why.empty());
  }
  EXPECT_FALSE(ParseStatusRecord(good.substr(0, 54), nullptr).has_value());
  EXPECT_FALSE(ParseStatusRecord(good + "0", nullptr).has_value());
  // A record glued to the status (device still streaming) is not a status.
  EXPECT_FALSE(ParseStatusRecord("01 " + good.substr(3), nullptr).has_value());
}

TEST(Commands, MatchTheReferenceBytes) {
  EXPECT_EQ(OutputListCommand(1, false), "O1,2,11,0\r");
  EXPECT_EQ(OutputListCommand(4, false), "O4,2,11,0\r");
  EXPECT_EQ(OutputListCommand(1, true), "O1,2,11,16,0\r");
  EXPECT_EQ(StylusModeCommand(1), "e1,0\r");
  EXPECT_THROW(OutputListCommand(5, false), std::invalid_argument);
  EXPECT_EQ(ResetPreamble(1), "c");
  EXPECT_EQ(ResetPreamble(2), "\rc");
  EXPECT_EQ(ResetPreamble(3), "\r\x19" "c");
  EXPECT_EQ(ResetPreamble(4), "\r\x19" "c");
  EXPECT_EQ(ResetPreamble(5), "\rt\x19" "c");
  EXPECT_EQ(ResetPreamble(9), "\rYt\x19" "c");
  EXPECT_FALSE(ResetPreambleReinitialises(2));
  EXPECT_TRUE(ResetPreambleReinitialises(3));
  EXPECT_EQ(UnitsCommand(Units::kInches), 'U');
  EXPECT_EQ(UnitsCommand(Units::kCentimetres), 'u');
  EXPECT_DOUBLE_EQ(MetresPerUnit(Units::kCentimetres), 0.01);
  EXPECT_DOUBLE_EQ(MetresPerUnit(Units::kInches), 0.0254);
}

}  // namespace
}  // namespace trackcal::fastrak
