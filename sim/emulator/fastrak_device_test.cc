#include "sim/emulator/fastrak_device.h"

#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <fstream>
#include <iterator>
#include <sstream>

#include "tests/test_utils.h"

namespace trackcal::emulator {
namespace {

std::string ReadFile(const std::filesystem::path& path) {
  std::ifstream in(path, std::ios::binary);
  EXPECT_TRUE(in) << path;
  return std::string(std::istreambuf_iterator<char>(in), {});
}

std::filesystem::path TranscriptDir(const std::string& name) {
  return testing::SourceDir() / "tests/data/fastrak" / name;
}

// The poses the reference emulator streamed in transcripts 07 and 08 (FASTRAK.md section 11):
// station 1 at (10, -5, 20) in with W,X,Y,Z = (4, 1, 2, 3) / sqrt(30); station 2 at (1.5, 2.5,
// -3.5) in, identity.
StationMeasurement TranscriptStation(int station) {
  StationMeasurement m;
  if (station == 1) {
    m.transmitter_from_receiver.translation = Eigen::Vector3d(10, -5, 20) * kMetresPerInch;
    m.transmitter_from_receiver.rotation = QuaternionFromWxyz(4.0, 1.0, 2.0, 3.0).normalized();
  } else {
    m.transmitter_from_receiver.translation = Eigen::Vector3d(1.5, 2.5, -3.5) * kMetresPerInch;
  }
  return m;
}

FastrakDevice::Measure TranscriptMeasure() {
  return [](int s) { return TranscriptStation(s); };
}

std::string Hex(std::string_view bytes) {
  std::string out;
  char buf[4];
  for (const char c : bytes) {
    std::snprintf(buf, sizeof(buf), "%02x ", static_cast<unsigned char>(c));
    out += buf;
  }
  return out;
}

// What VRPN's vrpn_Tracker_Fastrak does with one binary record (FASTRAK.md section 6): float32 LE
// position times 0.0254 (it assumes inches) and W,X,Y,Z reordered to x,y,z,w.
struct DriverReport {
  int sensor;
  double pos[3];
  double quat_xyzw[4];
};
DriverReport DecodeLikeVrpn(const std::string& record) {
  DriverReport r{};
  r.sensor = record[1] - '1';
  for (int i = 0; i < 3; ++i) r.pos[i] = ReadFloat32Le(&record[3 + 4 * i]) * 0.0254;
  const double w = ReadFloat32Le(&record[15]);
  for (int i = 0; i < 3; ++i) r.quat_xyzw[i] = ReadFloat32Le(&record[19 + 4 * i]);
  r.quat_xyzw[3] = w;
  return r;
}

// client.csv rows: sensor, x, y, z, qx, qy, qz, qw, seconds, microseconds.
std::vector<std::vector<double>> ReadClientCsv(const std::filesystem::path& path) {
  std::ifstream in(path);
  std::vector<std::vector<double>> rows;
  std::string line;
  while (std::getline(in, line)) {
    std::vector<double> row;
    std::stringstream ss(line);
    std::string cell;
    while (std::getline(ss, cell, ',')) row.push_back(std::stod(cell));
    rows.push_back(row);
  }
  return rows;
}

TEST(FastrakDevice, Nominal) {
  // Transcript 07: what the reference driver wrote produces the status record and the record stream
  // the driver accepted, byte for byte.
  const std::string host =
      ReadFile(TranscriptDir("07_fastrak_emulated_tcp") / "serial_host_to_device.bin");
  const std::string device_bytes =
      ReadFile(TranscriptDir("07_fastrak_emulated_tcp") / "serial_device_to_host.bin");
  ASSERT_EQ(device_bytes.size(), 1024u);
  FastrakDevice device(FastrakDeviceOptions{});
  const std::string reply = device.Receive(host, TranscriptMeasure());
  ASSERT_EQ(reply.size(), 55u);
  EXPECT_EQ(reply, device_bytes.substr(0, 55)) << Hex(reply);
  EXPECT_TRUE(device.binary());
  EXPECT_TRUE(device.continuous());
  EXPECT_FALSE(device.metric());
  EXPECT_EQ(device.commands_ignored(), 0);
  for (int s = 1; s <= 4; ++s) {
    EXPECT_EQ(device.station(s).output_list, (std::vector<int>{2, 11, 0})) << s;
  }
  EXPECT_EQ(device.position_filter(), "0.2,0.2,0.8,0.8");
  EXPECT_EQ(device.attitude_filter(), "0.2,0.2,0.8,0.8");
  // Records alternate station 1, 2 from the first byte after the status record.
  std::string stream;
  for (int i = 0; stream.size() < device_bytes.size() - 55; ++i) {
    const int s = 1 + i % 2;
    const std::string record = device.FormatRecord(s, TranscriptStation(s));
    ASSERT_EQ(record.size(), 32u);
    ASSERT_EQ(device.BinaryRecordSize(s), 32u);
    stream += record;
  }
  stream.resize(device_bytes.size() - 55);
  EXPECT_EQ(stream, device_bytes.substr(55)) << Hex(stream.substr(0, 64));

  // And the driver's conversion of these bytes gives exactly what the VRPN client printed.
  const auto client = ReadClientCsv(TranscriptDir("07_fastrak_emulated_tcp") / "client.csv");
  ASSERT_GE(client.size(), 2u);
  for (const auto& row : client) {
    const int s = static_cast<int>(row[0]) + 1;
    const DriverReport r = DecodeLikeVrpn(device.FormatRecord(s, TranscriptStation(s)));
    for (int i = 0; i < 3; ++i) EXPECT_DOUBLE_EQ(r.pos[i], row[1 + i]);
    for (int i = 0; i < 4; ++i) EXPECT_DOUBLE_EQ(r.quat_xyzw[i], row[4 + i]);
  }
}

TEST(FastrakDevice, ByteByByteEqualsOneChunk) {
  const std::string host =
      ReadFile(TranscriptDir("07_fastrak_emulated_tcp") / "serial_host_to_device.bin");
  FastrakDevice whole(FastrakDeviceOptions{});
  FastrakDevice bytewise(FastrakDeviceOptions{});
  const std::string a = whole.Receive(host, TranscriptMeasure());
  std::string b;
  for (const char c : host) b += bytewise.Receive(std::string_view(&c, 1), TranscriptMeasure());
  EXPECT_EQ(a, b);
  EXPECT_EQ(whole.FormatRecord(1, TranscriptStation(1)),
            bytewise.FormatRecord(1, TranscriptStation(1)));
}

TEST(FastrakDevice, StylusCentimetresTranscript) {
  // Transcript 08: FTStylus on sensor 0, extra commands H1,1,0,0 and u (centimetres).
  const std::string dir = "08_fastrak_emulated_udp_lob_stylus_cm";
  const std::string host = ReadFile(TranscriptDir(dir) / "serial_host_to_device.bin");
  FastrakDevice device(FastrakDeviceOptions{});
  const std::string reply = device.Receive(host, TranscriptMeasure());
  // The status record is the same as in transcript 07 (same power-up state when `S` arrives).
  const std::string status07 =
      ReadFile(TranscriptDir("07_fastrak_emulated_tcp") / "serial_device_to_host.bin")
          .substr(0, 55);
  EXPECT_EQ(reply, status07);
  EXPECT_TRUE(device.metric());
  EXPECT_EQ(device.station(1).output_list, (std::vector<int>{2, 11, 16, 0}));
  EXPECT_EQ(device.station(2).output_list, (std::vector<int>{2, 11, 0}));
  EXPECT_EQ(device.station(1).hemisphere, Eigen::Vector3d(1, 0, 0));
  EXPECT_EQ(device.BinaryRecordSize(1), 34u);

  StationMeasurement pressed = TranscriptStation(1);
  pressed.stylus_button = true;
  const std::string r1 = device.FormatRecord(1, pressed);
  ASSERT_EQ(r1.size(), 34u);
  EXPECT_EQ(r1.substr(0, 3), "01 ");
  EXPECT_EQ(ReadFloat32Le(&r1[3]), static_cast<float>(25.4));  // 10 in = 25.4 cm
  EXPECT_EQ(ReadFloat32Le(&r1[7]), static_cast<float>(-12.7));
  EXPECT_EQ(ReadFloat32Le(&r1[11]), static_cast<float>(50.8));
  EXPECT_EQ(r1.substr(31), " 1 ");  // stylus item: space then ASCII digit; then item 0
  EXPECT_EQ(device.FormatRecord(1, TranscriptStation(1)).substr(31), " 0 ");

  // Station 2's record has the layout of the transcript's station-2 records (header, quaternion,
  // trailing space identical; the transcript file holds inch positions, the cm run sent 2.54x).
  const std::string bytes08 = ReadFile(TranscriptDir(dir) / "serial_device_to_host.bin");
  const std::string r2 = device.FormatRecord(2, TranscriptStation(2));
  ASSERT_EQ(r2.size(), 32u);
  EXPECT_EQ(r2.substr(0, 3), bytes08.substr(32, 3));
  EXPECT_EQ(r2.substr(15), bytes08.substr(32 + 15, 17));

  // The driver's decoding (inches assumed) reproduces the 2.54x positions the VRPN client printed.
  const auto client = ReadClientCsv(TranscriptDir(dir) / "client.csv");
  ASSERT_GE(client.size(), 2u);
  for (const auto& row : client) {
    const int s = static_cast<int>(row[0]) + 1;
    const DriverReport r = DecodeLikeVrpn(device.FormatRecord(s, TranscriptStation(s)));
    for (int i = 0; i < 3; ++i) EXPECT_DOUBLE_EQ(r.pos[i], row[1 + i]) << "station " << s;
    for (int i = 0; i < 4; ++i) EXPECT_DOUBLE_EQ(r.quat_xyzw[i], row[4 + i]) << "station " << s;
  }
}

TEST(FastrakDevice, StatusRecordReflectsState) {
  FastrakDevice device(FastrakDeviceOptions{});
  const std::string s0 = device.Receive("S", TranscriptMeasure());
  ASSERT_EQ(s0.size(), 55u);
  EXPECT_EQ(s0.substr(0, 3), "21S");
  EXPECT_EQ(s0.substr(3, 3), "0A0");
  EXPECT_EQ(s0.substr(53), "\r\n");
  const std::string s1 = device.Receive("fuCS", TranscriptMeasure());
  ASSERT_EQ(s1.size(), 55u);
  EXPECT_EQ(s1.substr(3, 3), "0AB");  // binary | cm | continuous
  FastrakDeviceOptions options;
  options.system_id = "LAB 3";
  options.firmware_version = "4.01";
  FastrakDevice other(options);
  const std::string s2 = other.StatusRecord();
  ASSERT_EQ(s2.size(), 55u);
  EXPECT_EQ(s2.substr(15, 6), "  4.01");
  EXPECT_EQ(s2.substr(21, 5), "LAB 3");
}

// Parses the fixed-width ASCII fields following the 3-byte header.
std::vector<double> AsciiFields(const std::string& record, size_t offset, int count) {
  std::vector<double> v;
  for (int i = 0; i < count; ++i) v.push_back(std::stod(record.substr(offset + 7 * i, 7)));
  return v;
}

TEST(FastrakDevice, AsciiDefaultRecord) {
  FastrakDevice device(FastrakDeviceOptions{});
  StationMeasurement m;
  m.transmitter_from_receiver.translation = Eigen::Vector3d(0.3, -0.1, 0.05);
  // azimuth 30, elevation -20, roll 10 degrees: R = Rz(az) Ry(el) Rx(roll).
  m.transmitter_from_receiver.rotation =
      Eigen::AngleAxisd(30 * kRadPerDeg, Eigen::Vector3d::UnitZ()) *
      Eigen::AngleAxisd(-20 * kRadPerDeg, Eigen::Vector3d::UnitY()) *
      Eigen::AngleAxisd(10 * kRadPerDeg, Eigen::Vector3d::UnitX());
  const std::string reply = device.Receive("P", [&](int) { return m; });
  // Power-up: ASCII, output list 2,4,1, stations 1 and 2 active -> two 47-byte records.
  ASSERT_EQ(reply.size(), 2 * 47u) << reply;
  const std::string r = reply.substr(0, 47);
  EXPECT_EQ(r.substr(0, 3), "01 ");
  EXPECT_EQ(r.substr(45), "\r\n");
  const auto p = AsciiFields(r, 3, 3);
  // Two decimals in the field: half a unit of the last digit is the tolerance.
  EXPECT_NEAR(p[0], 0.3 / kMetresPerInch, 0.005);
  EXPECT_NEAR(p[1], -0.1 / kMetresPerInch, 0.005);
  EXPECT_NEAR(p[2], 0.05 / kMetresPerInch, 0.005);
  const auto e = AsciiFields(r, 24, 3);
  EXPECT_NEAR(e[0], 30, 0.005);
  EXPECT_NEAR(e[1], -20, 0.005);
  EXPECT_NEAR(e[2], 10, 0.005);
  EXPECT_EQ(reply.substr(47, 3), "02 ");

  // Centimetres, quaternion and direction cosines.
  device.Receive("uO1,2,11,5,6,7,1\r", [&](int) { return m; });
  const std::string q = device.FormatRecord(1, m);
  ASSERT_EQ(q.size(), 3 + 21 + 28 + 63 + 2u) << q;
  const auto pc = AsciiFields(q, 3, 3);
  EXPECT_NEAR(pc[0], 30.0, 0.005);
  const auto qv = AsciiFields(q, 24, 4);
  const Eigen::Quaterniond expected = m.transmitter_from_receiver.rotation;
  // Four decimals: 0.00005 is half the last digit.
  EXPECT_NEAR(qv[0], expected.w(), 5e-5);
  EXPECT_NEAR(qv[1], expected.x(), 5e-5);
  EXPECT_NEAR(qv[2], expected.y(), 5e-5);
  EXPECT_NEAR(qv[3], expected.z(), 5e-5);
  const auto dc = AsciiFields(q, 52, 9);
  const Eigen::Matrix3d rot = expected.toRotationMatrix();
  for (int row = 0; row < 3; ++row) {
    for (int col = 0; col < 3; ++col) EXPECT_NEAR(dc[3 * row + col], rot(row, col), 5e-5);
  }
}

TEST(FastrakDevice, BinaryEulerAndDirectionCosines) {
  FastrakDevice device(FastrakDeviceOptions{});
  device.Receive("fO1,4,5,6,7\r", TranscriptMeasure());
  StationMeasurement m;
  m.transmitter_from_receiver.translation = Eigen::Vector3d(0.2, 0, 0);
  m.transmitter_from_receiver.rotation =
      Eigen::Quaterniond(Eigen::AngleAxisd(0.5, Eigen::Vector3d(1, 2, 3).normalized()));
  const std::string r = device.FormatRecord(1, m);
  ASSERT_EQ(r.size(), 3 + 48u);
  ASSERT_EQ(device.BinaryRecordSize(1), r.size());
  const double az = ReadFloat32Le(&r[3]) * kRadPerDeg;
  const double el = ReadFloat32Le(&r[7]) * kRadPerDeg;
  const double roll = ReadFloat32Le(&r[11]) * kRadPerDeg;
  const Eigen::Quaterniond back = Eigen::AngleAxisd(az, Eigen::Vector3d::UnitZ()) *
                                  Eigen::AngleAxisd(el, Eigen::Vector3d::UnitY()) *
                                  Eigen::AngleAxisd(roll, Eigen::Vector3d::UnitX());
  // float32 degrees: ~1e-7 relative, far below 1e-5 rad.
  EXPECT_TRUE(testing::RotationsNear(m.transmitter_from_receiver.rotation, back, 1e-5));
  const Eigen::Matrix3d rot = m.transmitter_from_receiver.rotation.toRotationMatrix();
  for (int row = 0; row < 3; ++row) {
    for (int col = 0; col < 3; ++col) {
      EXPECT_NEAR(ReadFloat32Le(&r[15 + 12 * row + 4 * col]), rot(row, col), 1e-6);  // float32
    }
  }
}

TEST(FastrakDevice, Hemisphere) {
  FastrakDevice device(FastrakDeviceOptions{});
  device.Receive("f\rO1,2\r", TranscriptMeasure());
  StationMeasurement m;
  m.transmitter_from_receiver.translation = Eigen::Vector3d(-0.254, 0.127, 0.0254);
  auto position = [&]() {
    const std::string r = device.FormatRecord(1, m);
    return Eigen::Vector3d(ReadFloat32Le(&r[3]), ReadFloat32Le(&r[7]), ReadFloat32Le(&r[11]));
  };
  // Default hemisphere +x: the antipodal solution is reported.
  EXPECT_TRUE(position().isApprox(Eigen::Vector3d(10, -5, -1), 1e-6));
  device.Receive("H1,-1,0,0\r", TranscriptMeasure());
  EXPECT_TRUE(position().isApprox(Eigen::Vector3d(-10, 5, 1), 1e-6));
  // Hemisphere tracking: of the two solutions, the one on the side of the last report.
  device.Receive("H1,0,0,0\r", TranscriptMeasure());
  EXPECT_TRUE(position().isApprox(Eigen::Vector3d(-10, 5, 1), 1e-6));
  m.transmitter_from_receiver.translation = Eigen::Vector3d(1, -5, -1) * kMetresPerInch;
  EXPECT_TRUE(position().isApprox(Eigen::Vector3d(-1, 5, 1), 1e-6));
  m.transmitter_from_receiver.translation = Eigen::Vector3d(1, 5, 1) * kMetresPerInch;
  EXPECT_TRUE(position().isApprox(Eigen::Vector3d(1, 5, 1), 1e-6));
}

TEST(FastrakDevice, LineEndingsAndUnknownCommands) {
  FastrakDevice device(FastrakDeviceOptions{});
  // LF only, CR LF, LF CR, blank lines, a line split across calls.
  device.Receive("O1,2,11,0\n", TranscriptMeasure());
  EXPECT_EQ(device.station(1).output_list, (std::vector<int>{2, 11, 0}));
  device.Receive("\r\n\r\nO2,2,16\r\n", TranscriptMeasure());
  EXPECT_EQ(device.station(2).output_list, (std::vector<int>{2, 16}));
  device.Receive("O1, 2 ,", TranscriptMeasure());
  device.Receive("1\n\r", TranscriptMeasure());
  EXPECT_EQ(device.station(1).output_list, (std::vector<int>{2, 1}));
  EXPECT_EQ(device.commands_ignored(), 0);
  // Unknown commands, unsupported items and bad stations are ignored; what follows still works.
  const std::string reply = device.Receive("Z12\rO1,2,21,0\rO9,2\rq\r\x01S", TranscriptMeasure());
  EXPECT_EQ(device.commands_ignored(), 5);
  EXPECT_EQ(device.station(1).output_list, (std::vector<int>{2, 1}));
  ASSERT_EQ(reply.size(), 55u);
  EXPECT_EQ(reply[0], '2');
  // An endless line does not grow without bound and is dropped at its end.
  device.Receive("O1," + std::string(10000, '2') + "\r", TranscriptMeasure());
  EXPECT_EQ(device.station(1).output_list, (std::vector<int>{2, 1}));
  EXPECT_EQ(device.commands_ignored(), 6);
}

// A Fastrak output list holds at most 32 items (manual Rev. G, 'O'); a longer one was accepted (40
// quaternions made a 643-byte binary record no unit can send). Spaces keep the lists short in
// bytes, so only the item count is tested (the manual's 254-byte limit is not modelled).
TEST(FastrakDevice, OutputListOfMoreThan32ItemsIsIgnored) {
  FastrakDevice device(FastrakDeviceOptions{});
  std::string list = "O1";
  for (int i = 0; i < 32; ++i) list += ",0";
  device.Receive(list + "\r", TranscriptMeasure());
  EXPECT_EQ(device.station(1).output_list.size(), 32u);
  EXPECT_EQ(device.commands_ignored(), 0);
  device.Receive("O1,2,11,0\r" + list + ",0\r", TranscriptMeasure());
  EXPECT_EQ(device.station(1).output_list, (std::vector<int>{2, 11, 0}));
  EXPECT_EQ(device.commands_ignored(), 1);
  EXPECT_EQ(device.BinaryRecordSize(1), 32u);
}

// A number beyond int in a line command is malformed, not wrapped: strtol's long was cast to int,
// so item 4294967298 (2^32 + 2) became item 2 (position), station 4294967297 became station 1 and
// `l1,4294967296` switched station 1 off, each counted as an accepted command.
TEST(FastrakDevice, NumbersBeyondIntAreIgnoredNotWrapped) {
  FastrakDevice device(FastrakDeviceOptions{});
  device.Receive("O1,2,11,0\r", TranscriptMeasure());
  ASSERT_EQ(device.commands_ignored(), 0);
  device.Receive("O1,4294967298\rO4294967297,4\rl1,4294967296\re4294967297,0\r",
                 TranscriptMeasure());
  EXPECT_EQ(device.station(1).output_list, (std::vector<int>{2, 11, 0}));
  EXPECT_TRUE(device.station(1).active);
  EXPECT_EQ(device.station(1).stylus_function, 1);
  EXPECT_EQ(device.commands_ignored(), 4);
  EXPECT_EQ(device.commands_accepted(), 1);
}

// docs/emulator.md: stray control bytes are ignored and counted. Inside a line command they were
// dropped without a count or a log line; the line itself still works, as outside a line.
TEST(FastrakDevice, ControlBytesInsideALineAreCounted) {
  FastrakDevice device(FastrakDeviceOptions{});
  device.Receive(
      "O1,2,\x01"
      "11,\x13"
      "0\r",
      TranscriptMeasure());
  EXPECT_EQ(device.station(1).output_list, (std::vector<int>{2, 11, 0}));
  EXPECT_EQ(device.commands_ignored(), 2);
  EXPECT_EQ(device.commands_accepted(), 1);
  const std::vector<std::string> log = device.TakeLog();
  ASSERT_EQ(log.size(), 3u);
  EXPECT_NE(log[0].find("\\x01"), std::string::npos) << log[0];
  EXPECT_NE(log[1].find("\\x13"), std::string::npos) << log[1];
}

// VRPN's IS900time configuration: `O<s>,2,11,21,0` carries the IS-900 timestamp item 21, so the
// whole list is ignored and the station keeps its list (2,4,1 after power-up: 29 binary bytes, not
// the 36 the driver then expects, nor the 32 of 2,11,0); MT and MZ are ignored too.
TEST(FastrakDevice, Is900TimestampConfigurationKeepsThePreviousList) {
  FastrakDevice device(FastrakDeviceOptions{});
  device.Receive("cSO1,2,11,21,0\rO2,2,11,21,0\rfCMT\rMZ\r", TranscriptMeasure());
  EXPECT_EQ(device.station(1).output_list, (std::vector<int>{2, 4, 1}));
  EXPECT_EQ(device.BinaryRecordSize(1), 29u);
  EXPECT_EQ(device.FormatRecord(1, TranscriptStation(1)).size(), 29u);
  EXPECT_EQ(device.commands_ignored(), 4);
  EXPECT_TRUE(device.binary() && device.continuous());
}

TEST(FastrakDevice, CtrlYReinitialises) {
  FastrakDevice device(FastrakDeviceOptions{});
  device.Receive("fuCO1,11\r", TranscriptMeasure());
  ASSERT_TRUE(device.binary() && device.metric() && device.continuous());
  // Ctrl-Y in the middle of a line drops the line and restores power-up state.
  device.Receive("O2,11", TranscriptMeasure());
  device.Receive("\x19\r", TranscriptMeasure());
  EXPECT_FALSE(device.binary());
  EXPECT_FALSE(device.metric());
  EXPECT_FALSE(device.continuous());
  EXPECT_EQ(device.station(1).output_list, (std::vector<int>{2, 4, 1}));
  EXPECT_EQ(device.station(2).output_list, (std::vector<int>{2, 4, 1}));
  // The escalating reset of the driver (CR, Y, t, ^Y, c) leaves a device that answers S.
  const std::string reply = device.Receive(
      "\rYt\x19"
      "cS",
      TranscriptMeasure());
  EXPECT_EQ(reply.size(), 55u);
}

TEST(FastrakDevice, CtrlKSavesThePowerUpConfiguration) {
  FastrakDevice device(FastrakDeviceOptions{});
  // A lab's saved setup: our output list, centimetres, -z hemisphere, binary, continuous.
  device.Receive("O1,2,11,0\rO2,2,11,0\rH1,0,0,-1\rx0.5,0.2,0.8,0.8\rufC\x0b", TranscriptMeasure());
  ASSERT_TRUE(device.has_saved_configuration());
  // Changed after saving (what a driver sets), then lost at power-up (Ctrl-Y, or power on).
  device.Receive("UFcO1,2,4,1\rH1,0,0,1\rx0.2,0.2,0.8,0.8\r\x19", TranscriptMeasure());
  EXPECT_TRUE(device.binary());
  EXPECT_TRUE(device.metric());
  EXPECT_TRUE(device.continuous());
  EXPECT_EQ(device.station(1).output_list, (std::vector<int>{2, 11, 0}));
  EXPECT_EQ(device.station(2).output_list, (std::vector<int>{2, 11, 0}));
  EXPECT_EQ(device.station(1).hemisphere, Eigen::Vector3d(0, 0, -1));
  EXPECT_EQ(device.station(2).hemisphere, Eigen::Vector3d::UnitX());  // not changed before ^K
  EXPECT_EQ(device.position_filter(), "0.5,0.2,0.8,0.8");
  // The record is in the saved format: 32 bytes, centimetres, in the -z hemisphere (the transcript
  // station 1 is at z = +20 in, so it is reported at -50.8 cm, x and y negated with it).
  const std::string record = device.FormatRecord(1, TranscriptStation(1));
  ASSERT_EQ(record.size(), 32u);
  EXPECT_NEAR(ReadFloat32Le(record.data() + 3), -25.4, 1e-4);
  EXPECT_NEAR(ReadFloat32Le(record.data() + 11), -50.8, 1e-4);
}

TEST(FastrakDevice, PolledAndActiveStations) {
  FastrakDeviceOptions options;
  options.num_stations = 3;
  FastrakDevice device(options);
  EXPECT_EQ(device.ActiveStations(), (std::vector<int>{1, 2, 3}));
  device.Receive("fO1,2,11,0\rO2,2,11,0\rO3,2,11,0\rl2,0\rl4,1\r", TranscriptMeasure());
  EXPECT_EQ(device.ActiveStations(), (std::vector<int>{1, 3}));  // station 4 has no receiver
  int measured = 0;
  const std::string reply = device.Receive("P", [&](int s) {
    ++measured;
    return TranscriptStation(s == 1 ? 1 : 2);
  });
  EXPECT_EQ(measured, 2);
  ASSERT_EQ(reply.size(), 64u);
  EXPECT_EQ(reply.substr(0, 2), "01");
  EXPECT_EQ(reply.substr(32, 2), "03");
  EXPECT_FALSE(device.continuous());
}

TEST(FastrakDevice, StylusSwitchPointAndTrackMode) {
  FastrakDevice device(FastrakDeviceOptions{});
  EXPECT_EQ(device.station(1).stylus_function, 1);  // the Fastrak's power-up default
  device.Receive("fO1,2,11,16,0\rO2,2,11,0\rC", TranscriptMeasure());
  ASSERT_TRUE(device.streaming());
  // Continuous: each press (not the holding) toggles the output.
  EXPECT_EQ(device.StylusSwitch(true, TranscriptMeasure()), "");
  EXPECT_FALSE(device.streaming());
  EXPECT_TRUE(device.continuous());
  device.StylusSwitch(true, TranscriptMeasure());
  EXPECT_FALSE(device.streaming());
  device.StylusSwitch(false, TranscriptMeasure());
  device.StylusSwitch(true, TranscriptMeasure());
  EXPECT_TRUE(device.streaming());
  // Polled: a press outputs a record per active station, like `P`.
  device.Receive("c", TranscriptMeasure());
  device.StylusSwitch(false, TranscriptMeasure());
  const std::string reply = device.StylusSwitch(true, TranscriptMeasure());
  ASSERT_EQ(reply.size(), 34u + 32u);
  EXPECT_EQ(reply.substr(0, 2), "01");
  EXPECT_EQ(reply.substr(34, 2), "02");
  // e1,0: the switch is only reported in item 16.
  device.Receive("e1,0\rC", TranscriptMeasure());
  device.StylusSwitch(false, TranscriptMeasure());
  EXPECT_EQ(device.StylusSwitch(true, TranscriptMeasure()), "");
  EXPECT_TRUE(device.streaming());
}

TEST(FastrakDevice, StylusSwitchWorksOnlyOnStation1) {
  FastrakDevice device(FastrakDeviceOptions{});
  device.Receive("fO1,2,16,0\rO2,2,16,0\r", TranscriptMeasure());
  StationMeasurement pressed = TranscriptStation(2);
  pressed.stylus_button = true;
  EXPECT_EQ(device.FormatRecord(1, pressed).substr(15), " 1 ");
  EXPECT_EQ(device.FormatRecord(2, pressed).substr(15), " 0 ");
}

TEST(FastrakDevice, QuaternionScalarNonNegative) {
  FastrakDevice device(FastrakDeviceOptions{});
  device.Receive("fO1,11\r", TranscriptMeasure());
  StationMeasurement m;
  m.transmitter_from_receiver.translation = Eigen::Vector3d(0.1, 0, 0);
  m.transmitter_from_receiver.rotation = QuaternionFromWxyz(-0.5, 0.5, -0.5, 0.5);
  const std::string r = device.FormatRecord(1, m);
  EXPECT_EQ(ReadFloat32Le(&r[3]), 0.5f);
  EXPECT_EQ(ReadFloat32Le(&r[7]), -0.5f);
  EXPECT_EQ(ReadFloat32Le(&r[11]), 0.5f);
  EXPECT_EQ(ReadFloat32Le(&r[15]), -0.5f);
}

TEST(FastrakDeviceOptions, CheckNamesField) {
  FastrakDeviceOptions options;
  options.num_stations = 5;
  EXPECT_THROW(
      {
        try {
          options.Check();
        } catch (const std::invalid_argument& e) {
          EXPECT_NE(std::string(e.what()).find("num_stations"), std::string::npos);
          throw;
        }
      },
      std::invalid_argument);
}

}  // namespace
}  // namespace trackcal::emulator
