#include "vrpn_server/config.h"

#include <gtest/gtest.h>

#include <fstream>
#include <stdexcept>

#include "core/printable_text.h"
#include "tests/test_utils.h"

namespace trackcal::vrpn {
namespace {

// Message of the std::invalid_argument thrown by parsing `text` (empty if none was thrown).
std::string ParseError(const std::string& text) {
  try {
    ParseVrpnConfig(text, "lab.cfg");
  } catch (const std::invalid_argument& e) {
    return e.what();
  }
  return "";
}

TEST(ParseVrpnConfig, Nominal) {
  const VrpnConfig config = ParseVrpnConfig(
      "# plain Fastrak\n"
      "vrpn_Tracker_Fastrak  Tracker0  /dev/ttyS0  115200\n",
      "lab.cfg");
  ASSERT_EQ(config.fastrak_trackers.size(), 1u);
  const FastrakTrackerSpec& t = config.fastrak_trackers[0];
  EXPECT_EQ(t.name, "Tracker0");
  EXPECT_EQ(t.port, "/dev/ttyS0");
  EXPECT_EQ(t.baud, 115200);
  EXPECT_FALSE(t.is900_time);
  EXPECT_TRUE(t.extra_commands.empty());
  EXPECT_TRUE(t.buttons.empty());
  EXPECT_EQ(t.location.line, 2);
  EXPECT_EQ(t.location.file, "lab.cfg");
  EXPECT_TRUE(config.warnings.empty());
}

TEST(ParseVrpnConfig, ReferenceTranscriptFiles) {
  const auto dir = testing::SourceDir() / "tests/data/fastrak/driver";
  const VrpnConfig c07 = ReadVrpnConfig(dir / "07_fastrak_emulated_tcp/vrpn.cfg");
  ASSERT_EQ(c07.fastrak_trackers.size(), 1u);
  EXPECT_EQ(c07.fastrak_trackers[0].port, "/dev/pts/0");

  const VrpnConfig c08 = ReadVrpnConfig(dir / "08_fastrak_emulated_udp_lob_stylus_cm/vrpn.cfg");
  ASSERT_EQ(c08.fastrak_trackers.size(), 1u);
  const FastrakTrackerSpec& t = c08.fastrak_trackers[0];
  EXPECT_EQ(t.extra_commands, (std::vector<std::string>{"H1,1,0,0", "*1", "u"}));
  ASSERT_EQ(t.buttons.size(), 1u);
  EXPECT_EQ(t.buttons[0].kind, ButtonDeviceKind::kFastrakStylus);
  EXPECT_EQ(t.buttons[0].name, "Stylus0");
  EXPECT_EQ(t.buttons[0].sensor, 0);
  EXPECT_EQ(t.buttons[0].location.line, 5);
}

TEST(ParseVrpnConfig, ByteOrderMarkBeforeTheFirstDeviceIsIgnored) {
  // Saved by a Windows editor: without stripping the mark, the first keyword is unknown and the
  // device is dropped with a warning.
  const VrpnConfig config = ParseVrpnConfig(
      "\xEF\xBB\xBFvrpn_Tracker_Fastrak Tracker0 /dev/ttyS0 115200\r\n", "lab.cfg");
  ASSERT_EQ(config.fastrak_trackers.size(), 1u);
  EXPECT_EQ(config.fastrak_trackers[0].name, "Tracker0");
  EXPECT_EQ(config.fastrak_trackers[0].location.line, 1);
  EXPECT_TRUE(config.warnings.empty());
}

TEST(ParseVrpnConfig, ContinuationToleratesTrailingSpacesAndCrlf) {
  // The reference ends the continuation at a trailing space or CR; we must not.
  const std::string lf =
      "vrpn_Tracker_Fastrak Tracker0 /dev/ttyUSB0 115200 \\\nH1,1,0,0\\\n*1\\\nu/\nFTStylus Stylus0 0\n";
  const std::string messy =
      "vrpn_Tracker_Fastrak Tracker0 /dev/ttyUSB0 115200 \\  \r\nH1,1,0,0 \\\t\r\n*1\\ \r\n"
      "u /  \r\nFTStylus Stylus0 0\r\n";
  for (const std::string& text : {lf, messy}) {
    SCOPED_TRACE(text);
    const VrpnConfig config = ParseVrpnConfig(text, "lab.cfg");
    ASSERT_EQ(config.fastrak_trackers.size(), 1u);
    EXPECT_EQ(config.fastrak_trackers[0].extra_commands,
              (std::vector<std::string>{"H1,1,0,0", "*1", "u"}));
    ASSERT_EQ(config.fastrak_trackers[0].buttons.size(), 1u);
    EXPECT_EQ(config.fastrak_trackers[0].buttons[0].name, "Stylus0");
    EXPECT_TRUE(config.warnings.empty());
  }
}

TEST(ParseVrpnConfig, DeviceLinesAndIs900Options) {
  const VrpnConfig config = ParseVrpnConfig(
      "vrpn_Tracker_Fastrak Tracker0 /dev/ttyS0 9600 IS900time /\n"
      "# comment inside the block\n"
      "Stylus Stylus0 1 /\n"
      "Wand Wand0 2 -1 -0.1 0.1 1 -1 -0.2 0.2 1\n"
      "vrpn_Tracker_Fastrak Tracker1 /dev/ttyS1 115200 /\n"
      "FTStylus Pen 3\n",
      "lab.cfg");
  ASSERT_EQ(config.fastrak_trackers.size(), 2u);
  const FastrakTrackerSpec& t0 = config.fastrak_trackers[0];
  EXPECT_TRUE(t0.is900_time);
  EXPECT_EQ(t0.baud, 9600);
  ASSERT_EQ(t0.buttons.size(), 2u);
  EXPECT_EQ(t0.buttons[0].kind, ButtonDeviceKind::kIs900Stylus);
  EXPECT_EQ(t0.buttons[0].sensor, 1);
  EXPECT_EQ(t0.buttons[1].kind, ButtonDeviceKind::kIs900Wand);
  EXPECT_EQ(t0.buttons[1].sensor, 2);
  EXPECT_DOUBLE_EQ(t0.buttons[1].wand_ranges[1], -0.1);
  EXPECT_DOUBLE_EQ(t0.buttons[1].wand_ranges[6], 0.2);
  EXPECT_EQ(t0.buttons[1].location.line, 4);
  const FastrakTrackerSpec& t1 = config.fastrak_trackers[1];
  EXPECT_EQ(t1.location.line, 5);
  ASSERT_EQ(t1.buttons.size(), 1u);
  EXPECT_EQ(t1.buttons[0].sensor, 3);
  // The Fastrak reads the stylus switch on station 1 only: FTStylus on sensor 3 is warned.
  ASSERT_EQ(config.warnings.size(), 1u);
  EXPECT_EQ(config.warnings[0].location.line, 6);
  EXPECT_NE(config.warnings[0].message.find("station 1 (sensor 0) only"), std::string::npos)
      << config.warnings[0].message;
}

TEST(ParseVrpnConfig, SeparateContinuationTokenAndAttachedOne) {
  const VrpnConfig config = ParseVrpnConfig(
      "vrpn_Tracker_Fastrak A /dev/a 115200\\\n"
      "U\n"
      "vrpn_Tracker_Fastrak B /dev/b 115200 / \n"
      "FTStylus BS 0\n",
      "lab.cfg");
  ASSERT_EQ(config.fastrak_trackers.size(), 2u);
  EXPECT_EQ(config.fastrak_trackers[0].extra_commands, std::vector<std::string>{"U"});
  EXPECT_EQ(config.fastrak_trackers[1].buttons.size(), 1u);
}

// A pass-through source is a VRPN client name: every connection form a VRPN client (and
// VrpnTrackerClient, which serves it) accepts is read the same way here, and a host the client
// would refuse at start is an error naming this line. "x-vrpn://host" and "tcp:host" without a port
// used to fail as a bad port ("//lab-pc"), and "tcp:host:port" kept "tcp:" in the host.
TEST(ParseVrpnConfig, PassthroughSourcesReadAsVrpnClientNames) {
  const VrpnConfig config = ParseVrpnConfig(
      "trackcal_Tracker_Passthrough A Tracker0@x-vrpn://lab-pc\n"
      "trackcal_Tracker_Passthrough B Tracker0@x-vrpn://lab-pc:3999\n"
      "trackcal_Tracker_Passthrough C Tracker0@tcp:lab-pc\n"
      "trackcal_Tracker_Passthrough D Tracker0@tcp:10.0.0.2:3884\n",
      "lab.cfg");
  ASSERT_EQ(config.passthroughs.size(), 4u);
  const struct {
    const char* host;
    int port;
    bool tcp_only;
  } expected[] = {{"lab-pc", 3883, false},
                  {"lab-pc", 3999, false},
                  {"lab-pc", 3883, true},
                  {"10.0.0.2", 3884, true}};
  for (int i = 0; i < 4; ++i) {
    const PassthroughSpec& p = config.passthroughs[i];
    EXPECT_EQ(p.source_device, "Tracker0") << p.source;
    EXPECT_EQ(p.source_host, expected[i].host) << p.source;
    EXPECT_EQ(p.source_port, expected[i].port) << p.source;
    EXPECT_EQ(p.source_tcp_only, expected[i].tcp_only) << p.source;
  }
  for (const std::string source :
       {"Tracker0@http://lab-pc:3883", "Tracker0@[::1]:3883", "Tracker0@lab,pc"}) {
    const std::string error = ParseError("trackcal_Tracker_Passthrough P " + source + "\n");
    EXPECT_NE(error.find("lab.cfg:1: field 'source': host"), std::string::npos)
        << source << ": " << error;
  }
  EXPECT_NE(ParseError("trackcal_Tracker_Passthrough P " + std::string(96, 'd') + "@lab-pc\n")
                .find("lab.cfg:1: field 'source': device name"),
            std::string::npos);
}

TEST(ParseVrpnConfig, TrackcalLines) {
  const VrpnConfig config = ParseVrpnConfig(
      "vrpn_Tracker_Fastrak Tracker0 /dev/ttyS0 115200\n"
      "trackcal_Calibration Tracker0 calib/lab.json raw=Tracker0_raw outside=fade fade_distance=0.05\n"
      "trackcal_Tracker_Passthrough Remote0 *Tracker0@lab-pc:3884\n"
      "trackcal_Tracker_Passthrough Remote1 Head@tcp://10.0.0.2\n"
      "trackcal_Tracker_Passthrough Local0 *Tracker0\n"
      "trackcal_Calibration Remote0 /abs/remote.json\n"
      "vrpn_Tracker_NULL Null0 2 5.0\n",
      "/etc/trackcal/vrpn.cfg");
  ASSERT_EQ(config.calibrations.size(), 2u);
  const CalibrationSpec* c = config.FindCalibration("Tracker0");
  ASSERT_NE(c, nullptr);
  EXPECT_EQ(c->file, std::filesystem::path("/etc/trackcal/calib/lab.json"));
  EXPECT_EQ(c->raw_name, "Tracker0_raw");
  EXPECT_EQ(c->outside, OutsidePolicy::kFade);
  EXPECT_EQ(c->fade_distance_m, std::optional<double>(0.05));
  EXPECT_EQ(c->location.line, 2);
  const CalibrationSpec* r = config.FindCalibration("Remote0");
  ASSERT_NE(r, nullptr);
  EXPECT_EQ(r->file, std::filesystem::path("/abs/remote.json"));
  EXPECT_FALSE(r->raw_name.has_value());
  EXPECT_EQ(r->outside, OutsidePolicy::kDefault);
  EXPECT_FALSE(r->fade_distance_m.has_value());
  EXPECT_EQ(config.FindCalibration("Remote1"), nullptr);
  const VrpnConfig linear = ParseVrpnConfig(
      "vrpn_Tracker_NULL T 1 1\ntrackcal_Calibration T c.json outside=linear\n", "lab.cfg");
  ASSERT_EQ(linear.calibrations.size(), 1u);
  EXPECT_EQ(linear.calibrations[0].outside, OutsidePolicy::kLinear);
  EXPECT_FALSE(linear.calibrations[0].sensor.has_value());  // every sensor
  // One calibration per receiver (sensor=<n>, 0-based as FTStylus), raw= on one of the lines.
  const VrpnConfig per_sensor = ParseVrpnConfig(
      "vrpn_Tracker_NULL T 3 1\ntrackcal_Calibration T a.json sensor=0 raw=R\n"
      "trackcal_Calibration T b.json sensor=2\n",
      "lab.cfg");
  ASSERT_EQ(per_sensor.calibrations.size(), 2u);
  EXPECT_EQ(per_sensor.calibrations[0].sensor, std::optional<int>(0));
  EXPECT_EQ(per_sensor.calibrations[1].sensor, std::optional<int>(2));
  EXPECT_EQ(per_sensor.calibrations[0].raw_name, "R");

  ASSERT_EQ(config.passthroughs.size(), 3u);
  EXPECT_EQ(config.passthroughs[0].source_device, "Tracker0");
  EXPECT_EQ(config.passthroughs[0].source_host, "lab-pc");
  EXPECT_EQ(config.passthroughs[0].source_port, 3884);
  EXPECT_FALSE(config.passthroughs[0].source_tcp_only);
  EXPECT_EQ(config.passthroughs[1].source_device, "Head");
  EXPECT_EQ(config.passthroughs[1].source_host, "10.0.0.2");
  EXPECT_EQ(config.passthroughs[1].source_port, 3883);
  EXPECT_TRUE(config.passthroughs[1].source_tcp_only);
  EXPECT_EQ(config.passthroughs[2].source_host, "");
  EXPECT_EQ(config.passthroughs[2].source_device, "Tracker0");

  ASSERT_EQ(config.null_trackers.size(), 1u);
  EXPECT_EQ(config.null_trackers[0].sensors, 2);
  EXPECT_DOUBLE_EQ(config.null_trackers[0].rate_hz, 5.0);
}

TEST(ParseVrpnConfig, UnknownDeviceIsAWarningAndTheRestIsParsed) {
  const VrpnConfig config = ParseVrpnConfig(
      "vrpn_Joylin Joy0 /dev/input/js0\n"
      "vrpn_Tracker_Liberty Lib0 /dev/ttyS1 115200 \\\n"
      "U\\\n"
      "*2\n"
      "vrpn_Tracker_Fastrak Tracker0 /dev/ttyS0 115200\n",
      "lab.cfg");
  ASSERT_EQ(config.fastrak_trackers.size(), 1u);
  EXPECT_EQ(config.fastrak_trackers[0].name, "Tracker0");
  ASSERT_EQ(config.warnings.size(), 2u);
  EXPECT_EQ(config.warnings[0].location.line, 1);
  EXPECT_NE(config.warnings[0].ToString().find("lab.cfg:1: warning: unknown device type 'vrpn_Joylin'"),
            std::string::npos)
      << config.warnings[0].ToString();
  EXPECT_EQ(config.warnings[1].location.line, 2);
  EXPECT_NE(config.warnings[1].message.find("2 continuation line(s)"), std::string::npos);
}

TEST(ParseVrpnConfig, WarningsAndErrorsQuoteTheFileEscaped) {
  // A warning or error quotes text of the file, and the server prints it to the operator's
  // terminal: a control byte in vrpn.cfg reached it raw (ESC ]0;...BEL retitled the terminal, ESC
  // [2J cleared it), and so did bytes that are not UTF-8. They are written as \xNN, as the server's
  // log writes a client's text; printable UTF-8 stays.
  const VrpnConfig config = ParseVrpnConfig(
      "vrpn_Joy\x1b]0;owned\x07lin Joy0\n"
      "vrpn_Tracker_Fastrak T0 /dev/ttyS0 115200 IS900time extra\xe9 \xc2\x9b\n"
      "vrpn_Ger\xc3\xa4t x\n",
      "lab.cfg");
  ASSERT_EQ(config.warnings.size(), 3u);
  EXPECT_EQ(config.warnings[0].ToString(),
            "lab.cfg:1: warning: unknown device type 'vrpn_Joy\\x1b]0;owned\\x07lin'; line ignored "
            "(other devices are still served)");
  EXPECT_EQ(config.warnings[1].ToString(),
            "lab.cfg:2: warning: text after the baud rate and option ignored: "
            "'extra\\xe9 \\xc2\\x9b'");
  EXPECT_EQ(config.warnings[2].ToString(),
            "lab.cfg:3: warning: unknown device type 'vrpn_Ger\xc3\xa4t'; line ignored (other "
            "devices are still served)");
  EXPECT_EQ(ParseError("vrpn_Tracker_NULL T 1 \x1b[2J\xff\n"),
            "lab.cfg:1: field 'rate': expected a number, got '\\x1b[2J\\xff'");
  // A command line (after a line that ends in a backslash) is trimmed, not split: a tab in it is
  // quoted too.
  EXPECT_EQ(ParseError("vrpn_Tracker_Fastrak T0 /dev/ttyS0 115200 \\\n*1\t2\n"),
            "lab.cfg:2: field 'sleep': expected a number, got '1\\x092'");
}

TEST(ParseVrpnConfig, NamesAClientCannotAddressAreErrors) {
  // A device name goes on the wire as a sender description and clients address it as Name@host
  // (the reference reads the name up to the first '@'): a name with '@', a control character or a
  // byte that is not UTF-8 was accepted and served under a name no client could type, and the
  // control bytes reached client logs. Each is an error naming file, line and field.
  const std::string control = "contains a control character";
  const std::string at = "contains '@'";
  const struct {
    std::string text;
    std::string expected;  // prefix of the message
  } cases[] = {
      {"vrpn_Tracker_NULL T\x1b[2J 1 60\n",
       "lab.cfg:1: field 'name': device name 'T\\x1b[2J' " + control},
      {"vrpn_Tracker_NULL T\xc2\x9b 1 60\n",
       "lab.cfg:1: field 'name': device name 'T\\xc2\\x9b' " + control},
      {"vrpn_Tracker_NULL T\x01 1 60\n",
       "lab.cfg:1: field 'name': device name 'T\\x01' " + control},
      {"vrpn_Tracker_Fastrak Tracker0@lab /dev/ttyS0 115200\n",
       "lab.cfg:1: field 'name': device name 'Tracker0@lab' " + at},
      {"vrpn_Tracker_Fastrak T /dev/a 115200 /\nFTStylus S\x7f 0\n",
       "lab.cfg:2: field 'button name': device name 'S\\x7f' " + control},
      {"vrpn_Tracker_NULL T 1 1\ntrackcal_Calibration T c.json raw=R@aw\n",
       "lab.cfg:2: field 'raw': device name 'R@aw' " + at},
      {"trackcal_Tracker_Passthrough P\x1b Tracker0@lab-pc\n",
       "lab.cfg:1: field 'name': device name 'P\\x1b' " + control},
      {"trackcal_Tracker_Passthrough P Track\x1b"
       "er0@lab-pc\n",
       "lab.cfg:1: field 'source': device name 'Track\\x1ber0' " + control},
      {"trackcal_Tracker_Passthrough P A@B@lab-pc\n",
       "lab.cfg:1: field 'source': device name 'A@B' " + at},
  };
  for (const auto& c : cases) {
    const std::string error = ParseError(c.text);
    EXPECT_EQ(error.rfind(c.expected, 0), 0u) << PrintableForLog(c.text) << " gave: " << error;
  }
  // Printable UTF-8 and every printable ASCII character but '@' stay valid names.
  const VrpnConfig config = ParseVrpnConfig(
      "vrpn_Tracker_NULL Ger\xc3\xa4t_0 1 60\n"
      "vrpn_Tracker_NULL Tracker-1.left/[x]:*#! 1 60\n",
      "lab.cfg");
  ASSERT_EQ(config.null_trackers.size(), 2u);
  EXPECT_EQ(config.null_trackers[0].name, "Ger\xc3\xa4t_0");
  EXPECT_EQ(config.null_trackers[1].name, "Tracker-1.left/[x]:*#!");
  EXPECT_TRUE(config.warnings.empty());
}

TEST(ParseVrpnConfig, ANameThatIsNotUtf8IsServedWithAWarning) {
  // A lab's vrpn.cfg saved as Latin-1 worked with the reference (any bytes are a name) and with
  // clients sending those bytes: it is served as it is, with a warning saying what a client must
  // send and how to make the name typeable, naming file, line and field.
  const VrpnConfig config = ParseVrpnConfig(
      "vrpn_Tracker_NULL Ger\xe4t 1 60\n"
      "trackcal_Tracker_Passthrough P Ger\xe4t2@lab-pc\n",
      "lab.cfg");
  ASSERT_EQ(config.null_trackers.size(), 1u);
  EXPECT_EQ(config.null_trackers[0].name, "Ger\xe4t");
  ASSERT_EQ(config.warnings.size(), 2u);
  EXPECT_EQ(
      config.warnings[0].ToString().rfind(
          "lab.cfg:1: warning: field 'name': device name 'Ger\\xe4t' is not UTF-8 (byte \\xe4 at "
          "character 4;",
          0),
      0u)
      << config.warnings[0].ToString();
  EXPECT_NE(config.warnings[0].ToString().find("save vrpn.cfg as UTF-8"), std::string::npos);
  EXPECT_EQ(
      config.warnings[1].ToString().rfind("lab.cfg:2: warning: field 'source': device name", 0), 0u)
      << config.warnings[1].ToString();
}

TEST(ParseVrpnConfig, AnUnknownTrackcalLineIsAnError) {
  // A misspelt trackcal line was an unknown device, a warning: the server started and served the
  // tracker uncorrected. trackcal_ names are trackcal's own: an unknown one is a typo.
  for (const std::string type :
       {"trackcal_Calibraton", "trackcal_calibration", "Trackcal_Tracker_Passthru"}) {
    try {
      ParseVrpnConfig("vrpn_Tracker_NULL Tracker0 1 60\n\n" + type + " Tracker0 calib.json\n",
                      "lab.cfg");
      ADD_FAILURE() << type << ": no error";
    } catch (const std::invalid_argument& e) {
      EXPECT_EQ(std::string(e.what()),
                "lab.cfg:3: field 'device type': unknown trackcal device type '" + type +
                    "' (trackcal's own lines are trackcal_Calibration and "
                    "trackcal_Tracker_Passthrough; names are case-sensitive)");
    }
  }
  // Another program's device stays a warning.
  EXPECT_EQ(ParseVrpnConfig("vrpn_Tracker_NULL T 1 60\ntrackcalibrator_Thing x\n", "lab.cfg")
                .warnings.size(),
            1u);
}

TEST(ParseVrpnConfig, ErrorsNameFileLineAndField) {
  struct Case {
    std::string text;
    std::string expected;  // substring of the message
  };
  const std::vector<Case> cases = {
      {"\nvrpn_Tracker_Fastrak T /dev/ttyS0 12345\n",
       "lab.cfg:2: field 'baud': 12345 is not a supported"},
      {"vrpn_Tracker_Fastrak T /dev/ttyS0 fast\n", "lab.cfg:1: field 'baud': expected an integer"},
      {"vrpn_Tracker_Fastrak T /dev/ttyS0\n", "lab.cfg:1: field 'baud': missing"},
      {"vrpn_Tracker_Fastrak T /dev/ttyS0 115200 IS600\n",
       "lab.cfg:1: field 'option': unexpected token 'IS600' (only IS900time, \\ or / may follow "
       "the baud rate)"},
      {"vrpn_Tracker_Fastrak T /dev/ttyS0 115200 \\\n*x\n", "lab.cfg:2: field 'sleep'"},
      {"vrpn_Tracker_Fastrak T /dev/ttyS0 115200 \\\n", "lab.cfg:1: field 'extra commands'"},
      {"vrpn_Tracker_Fastrak T /dev/ttyS0 115200 /\n# c\nFTStylus S 4\n",
       "lab.cfg:3: field 'sensor'"},
      {"vrpn_Tracker_Fastrak T /dev/ttyS0 115200 /\nButton B 0\n",
       "lab.cfg:2: field 'device line'"},
      {"vrpn_Tracker_Fastrak T /dev/ttyS0 115200 /\nFTStylus S\n", "lab.cfg:2: field 'FTStylus'"},
      {"vrpn_Tracker_Fastrak T /dev/ttyS0 115200 /\n", "lab.cfg:1: field 'device line'"},
      {"vrpn_Tracker_Fastrak T /dev/a 115200\nvrpn_Tracker_Fastrak T /dev/b 115200\n",
       "lab.cfg:2: field 'name': device name 'T' is already used at lab.cfg:1"},
      {"vrpn_Tracker_Fastrak " + std::string(96, 'T') + " /dev/a 115200\n",
       "lab.cfg:1: field 'name': device name '" + std::string(96, 'T') + "' is over 95 characters"},
      {"vrpn_Tracker_NULL T 1 1\ntrackcal_Calibration T c.json raw=" + std::string(96, 'r') + "\n",
       "lab.cfg:2: field 'raw': device name '" + std::string(96, 'r') + "' is over 95 characters"},
      {"vrpn_Tracker_Fastrak T /dev/a 115200 /\nFTStylus " + std::string(96, 'S') + " 0\n",
       "lab.cfg:2: field 'button name': device name '" + std::string(96, 'S') +
           "' is over 95 characters"},
      {"trackcal_Calibration Nope c.json\n", "lab.cfg:1: field 'tracker': no tracker named 'Nope'"},
      {"vrpn_Tracker_NULL T 1 1\ntrackcal_Calibration T c.json outside=wrap\n",
       "lab.cfg:2: field 'outside'"},
      {"vrpn_Tracker_NULL T 1 1\ntrackcal_Calibration T c.json raw=T\n", "lab.cfg:2: field 'raw'"},
      {"vrpn_Tracker_NULL T 1 1\ntrackcal_Calibration T c.json colour=red\n",
       "lab.cfg:2: field 'colour'"},
      {"vrpn_Tracker_NULL T 1 1\ntrackcal_Calibration T a.json\ntrackcal_Calibration T b.json\n",
       "lab.cfg:3: field 'tracker': tracker 'T' already has a calibration at lab.cfg:2"},
      {"vrpn_Tracker_NULL T 2 1\ntrackcal_Calibration T a.json\ntrackcal_Calibration T b.json "
       "sensor=1\n",
       "lab.cfg:3: field 'sensor': tracker 'T' already has a calibration at lab.cfg:2 (for every "
       "sensor)"},
      {"vrpn_Tracker_NULL T 2 1\ntrackcal_Calibration T b.json sensor=1\ntrackcal_Calibration T "
       "a.json\n",
       "lab.cfg:3: field 'tracker': tracker 'T' already has a calibration for sensor 1 at "
       "lab.cfg:2"},
      {"vrpn_Tracker_NULL T 2 1\ntrackcal_Calibration T a.json sensor=1\ntrackcal_Calibration T "
       "b.json sensor=1\n",
       "lab.cfg:3: field 'sensor': sensor 1 of tracker 'T' already has a calibration at lab.cfg:2"},
      {"vrpn_Tracker_NULL T 2 1\ntrackcal_Calibration T a.json sensor=0 raw=R0\n"
       "trackcal_Calibration T b.json sensor=1 raw=R1\n",
       "lab.cfg:3: field 'raw': tracker 'T' already serves its raw reports as 'R0' (lab.cfg:2)"},
      {"vrpn_Tracker_NULL T 2 1\ntrackcal_Calibration T a.json sensor=-1\n",
       "lab.cfg:2: field 'sensor': must be 0..1023"},
      {"vrpn_Tracker_NULL T 2 1\ntrackcal_Calibration T a.json sensor=one\n",
       "lab.cfg:2: field 'sensor': expected an integer"},
      {"trackcal_Calibration T\n", "lab.cfg:1: field 'calibration_file'"},
      {"vrpn_Tracker_NULL T 1 1\ntrackcal_Calibration T c.json outside=clamp outside=fade\n",
       "lab.cfg:2: field 'outside': given twice"},
      {"vrpn_Tracker_NULL T 1 1\n"
       "trackcal_Calibration T c.json fade_distance=0.1 fade_distance=0.2\n",
       "lab.cfg:2: field 'fade_distance': given twice"},
      {"vrpn_Tracker_NULL T 1 1\ntrackcal_Calibration T c.json fade_distance=-1\n",
       "lab.cfg:2: field 'fade_distance'"},
      {"vrpn_Tracker_NULL T 1 1\ntrackcal_Calibration T c.json fade_distance=\n",
       "lab.cfg:2: field 'fade_distance'"},
      {"trackcal_Tracker_Passthrough P Tracker0\n", "lab.cfg:1: field 'source'"},
      {"trackcal_Tracker_Passthrough P Tracker0@host:99999\n", "lab.cfg:1: field 'source port'"},
      {"trackcal_Tracker_Passthrough P Tracker0@\n", "lab.cfg:1: field 'source'"},
      {"trackcal_Tracker_Passthrough P *P\n", "lab.cfg:1: field 'source'"},
      {"vrpn_Tracker_NULL T 1 1\ntrackcal_Tracker_Passthrough P *Tracker0\n",
       "lab.cfg:2: field 'source': no tracker named 'Tracker0' is served by this file"},
      {"vrpn_Tracker_Fastrak T /dev/ttyS0 115200 /\nFTStylus Pen 0\n"
       "trackcal_Tracker_Passthrough P *Pen\n",
       "lab.cfg:3: field 'source': 'Pen' is a button of this server, not a tracker"},
      {"trackcal_Tracker_Passthrough A *B\ntrackcal_Tracker_Passthrough B *A\n",
       "lab.cfg:1: field 'source': pass-throughs read each other in a circle (A -> B -> A)"},
      {"vrpn_Tracker_NULL N zero 1\n", "lab.cfg:1: field 'sensors'"},
  };
  for (const Case& c : cases) {
    const std::string error = ParseError(c.text);
    EXPECT_NE(error.find(c.expected), std::string::npos)
        << "input:\n" << c.text << "error: '" << error << "'\nexpected: '" << c.expected << "'";
  }
}

// The reference creates the button server of an FTStylus line under the name given there; a button
// and a tracker of one name share one VRPN sender (messages told apart by type), so a lab file may
// name the stylus like its tracker and open Tracker0@host as both tracker and button remote.
TEST(ParseVrpnConfig, ButtonMayShareTheNameOfItsTracker) {
  const VrpnConfig config = ParseVrpnConfig(
      "vrpn_Tracker_Fastrak Tracker0 /dev/ttyS0 115200 /\n"
      "FTStylus Tracker0 0\n"
      "vrpn_Tracker_Fastrak Tracker1 /dev/ttyS1 115200 /\n"
      "Stylus Tracker1 1\n"
      "trackcal_Calibration Tracker0 c.json raw=Tracker0_raw\n"
      "trackcal_Tracker_Passthrough View0 *Tracker0\n"
      "trackcal_Tracker_Passthrough View0_raw *Tracker0_raw\n",
      "lab.cfg");
  ASSERT_EQ(config.fastrak_trackers.size(), 2u);
  ASSERT_EQ(config.fastrak_trackers[0].buttons.size(), 1u);
  EXPECT_EQ(config.fastrak_trackers[0].buttons[0].name, "Tracker0");
  EXPECT_EQ(config.fastrak_trackers[0].buttons[0].kind, ButtonDeviceKind::kFastrakStylus);
  ASSERT_EQ(config.fastrak_trackers[1].buttons.size(), 1u);
  EXPECT_EQ(config.fastrak_trackers[1].buttons[0].name, "Tracker1");
  ASSERT_NE(config.FindCalibration("Tracker0"), nullptr);
  EXPECT_EQ(config.FindCalibration("Tracker0")->raw_name, "Tracker0_raw");
  ASSERT_EQ(config.passthroughs.size(), 2u);
  EXPECT_EQ(config.passthroughs[0].source_device, "Tracker0");
  EXPECT_EQ(config.passthroughs[1].source_device, "Tracker0_raw");
  EXPECT_TRUE(config.warnings.empty());
}

// Any other reused name is an error: two devices of one type under one name would mix their
// messages in the reference, and a button named like another device would be served as part of it.
TEST(ParseVrpnConfig, OtherReusedDeviceNamesAreErrors) {
  struct Case {
    std::string text;
    std::string expected;  // the whole message
  };
  const std::string shared = "vrpn_Tracker_Fastrak T0 /dev/a 115200 /\nFTStylus T0 0\n";
  const std::string hint = " (a button may share only the name of the tracker it is attached to)";
  const std::vector<Case> cases = {
      {shared + "vrpn_Tracker_NULL T0 1 1\n",
       "lab.cfg:3: field 'name': device name 'T0' is already used at lab.cfg:1"},
      {shared + "trackcal_Tracker_Passthrough T0 *X\n",
       "lab.cfg:3: field 'name': device name 'T0' is already used at lab.cfg:1"},
      {shared + "trackcal_Calibration T0 c.json raw=T0\n",
       "lab.cfg:3: field 'raw': device name 'T0' is already used at lab.cfg:1"},
      {"vrpn_Tracker_Fastrak T0 /dev/a 115200 /\nFTStylus T0 0 /\nFTStylus T0 1\n",
       "lab.cfg:3: field 'button name': button device name 'T0' is already used at lab.cfg:2"},
      {"vrpn_Tracker_Fastrak T0 /dev/a 115200 /\nFTStylus S 0 /\nFTStylus S 1\n",
       "lab.cfg:3: field 'button name': device name 'S' is already used at lab.cfg:2" + hint},
      {"vrpn_Tracker_NULL T1 1 1\nvrpn_Tracker_Fastrak T0 /dev/a 115200 /\nFTStylus T1 0\n",
       "lab.cfg:3: field 'button name': device name 'T1' is already used at lab.cfg:1" + hint},
      {"vrpn_Tracker_Fastrak T0 /dev/a 115200 /\nFTStylus T1 0\nvrpn_Tracker_Fastrak T1 /dev/b "
       "115200\n",
       "lab.cfg:3: field 'name': device name 'T1' is already used at lab.cfg:2"},
      {"vrpn_Tracker_NULL T1 1 1\ntrackcal_Calibration T1 c.json raw=T1_raw\n"
       "vrpn_Tracker_Fastrak T0 /dev/a 115200 /\nFTStylus T1_raw 0\n",
       "lab.cfg:4: field 'button name': device name 'T1_raw' is already used at lab.cfg:2" + hint},
      {"vrpn_Tracker_Fastrak T0 /dev/a 115200 /\nFTStylus T0_raw 0\n"
       "trackcal_Calibration T0 c.json raw=T0_raw\n",
       "lab.cfg:3: field 'raw': device name 'T0_raw' is already used at lab.cfg:2"},
      {"trackcal_Tracker_Passthrough P *X\nvrpn_Tracker_Fastrak T0 /dev/a 115200 /\nStylus P 0\n",
       "lab.cfg:3: field 'button name': device name 'P' is already used at lab.cfg:1" + hint},
  };
  for (const Case& c : cases) {
    EXPECT_EQ(ParseError(c.text), c.expected) << "input:\n" << c.text;
  }
}

// The reference reads the Fastrak line and the FTStylus/Stylus/Wand lines with sscanf, so whatever
// follows the fields it needs (a trailing comment, a note) is ignored; such a lab file must still
// start the server. Here it is ignored with a warning naming the line.
TEST(ParseVrpnConfig, TextAfterTheFieldsIsIgnoredWithAWarningAsTheReferenceDoes) {
  const VrpnConfig config = ParseVrpnConfig(
      "vrpn_Tracker_Fastrak Tracker0 /dev/ttyS0 115200 IS900time # lab tracker /\n"
      "FTStylus Stylus0 0   # pen on receiver 1 /\n"
      "Wand Wand0 1 -1 0 0 1 -1 0 0 1 spare\n",
      "lab.cfg");
  ASSERT_EQ(config.fastrak_trackers.size(), 1u);
  const FastrakTrackerSpec& t = config.fastrak_trackers[0];
  EXPECT_TRUE(t.is900_time);
  ASSERT_EQ(t.buttons.size(), 2u);
  EXPECT_EQ(t.buttons[0].name, "Stylus0");
  EXPECT_EQ(t.buttons[0].sensor, 0);
  EXPECT_EQ(t.buttons[1].kind, ButtonDeviceKind::kIs900Wand);
  EXPECT_EQ(t.buttons[1].wand_ranges[7], 1.0);
  ASSERT_EQ(config.warnings.size(), 3u);
  for (int i = 0; i < 3; ++i) {
    EXPECT_EQ(config.warnings[i].location.line, i + 1);
    EXPECT_NE(config.warnings[i].message.find("ignored"), std::string::npos)
        << config.warnings[i].message;
  }
  EXPECT_NE(config.warnings[0].message.find("'# lab tracker'"), std::string::npos)
      << config.warnings[0].message;

  // The 4th token itself is still checked, as by the reference; a lone continuation character
  // followed by text continues nothing, so the lines meant to follow would be misread.
  EXPECT_NE(ParseError("vrpn_Tracker_Fastrak T /dev/ttyS0 115200 \\ # hemisphere\nH1,0,0,1\n")
                .find("lab.cfg:1: field 'option': text after '\\'"),
            std::string::npos);
  EXPECT_NE(ParseError("vrpn_Tracker_Fastrak T /dev/ttyS0 115200 # tracker\n")
                .find("lab.cfg:1: field 'option'"),
            std::string::npos);
}

TEST(ParseVrpnConfig, EmptyCommandLineIsWarnedAndSkipped) {
  const VrpnConfig config =
      ParseVrpnConfig("vrpn_Tracker_Fastrak T /dev/a 115200 \\\n\\\n  \\\nH1,1,0,0\n", "lab.cfg");
  EXPECT_EQ(config.fastrak_trackers.at(0).extra_commands, std::vector<std::string>{"H1,1,0,0"});
  EXPECT_EQ(config.warnings.size(), 2u);
}

// Comment lines inside a continuation block are skipped, so a lab that comments out the LAST
// command or device line of a block ("#u" below "H1,1,0,0\\") left the block open: the next device
// line was swallowed, silently sent to the tracker as an extra command (a trackcal_Calibration line
// too: the tracker was served uncorrected) or skipped with an unknown device. The reference sends
// the comment line as a command and reads the next line as a device line.
TEST(ParseVrpnConfig, ADeviceLineEndsABlockWhoseLastLineWasCommentedOut) {
  const VrpnConfig config = ParseVrpnConfig(
      "vrpn_Tracker_Fastrak Tracker0 /dev/ttyUSB0 115200 \\\r\n"  // 1
      "H1,1,0,0\\\r\n"                                            // 2
      "#u\r\n"                                                    // 3
      "trackcal_Calibration Tracker0 calib.json\r\n"              // 4
      "vrpn_Tracker_Liberty Lib0 /dev/ttyUSB1 115200 \\\r\n"      // 5
      "#*2\r\n"                                                   // 6
      "vrpn_Tracker_Fastrak Tracker1 /dev/ttyUSB2 9600 /\r\n"     // 7
      "FTStylus Stylus1 0 /\r\n"                                  // 8
      "# FTStylus Spare 0\r\n"                                    // 9
      "vrpn_Tracker_NULL Null0 1 10\r\n",                         // 10
      "lab.cfg");
  ASSERT_EQ(config.fastrak_trackers.size(), 2u);
  EXPECT_EQ(config.fastrak_trackers[0].extra_commands, std::vector<std::string>{"H1,1,0,0"});
  ASSERT_EQ(config.calibrations.size(), 1u);
  EXPECT_EQ(config.calibrations[0].tracker, "Tracker0");
  EXPECT_EQ(config.calibrations[0].location.line, 4);
  EXPECT_EQ(config.fastrak_trackers[1].location.line, 7);
  ASSERT_EQ(config.fastrak_trackers[1].buttons.size(), 1u);
  EXPECT_EQ(config.fastrak_trackers[1].buttons[0].name, "Stylus1");
  ASSERT_EQ(config.null_trackers.size(), 1u);
  EXPECT_EQ(config.null_trackers[0].location.line, 10);
  // Each block that ran into a device line is warned at that line; the Liberty at its own line.
  std::vector<int> lines;
  for (const ConfigWarning& w : config.warnings) lines.push_back(w.location.line);
  EXPECT_EQ(lines, (std::vector<int>{4, 7, 5, 10})) << ::testing::PrintToString(lines);
  EXPECT_NE(config.warnings[0].ToString().find(
                "lab.cfg:4: warning: 'trackcal_Calibration' starts a device line"),
            std::string::npos)
      << config.warnings[0].ToString();
  EXPECT_NE(config.warnings[0].message.find("continuation block of 'Tracker0' (extra commands)"),
            std::string::npos)
      << config.warnings[0].message;
  EXPECT_NE(config.warnings[2].message.find("line ignored (other devices"), std::string::npos)
      << config.warnings[2].message;
}

// vrpn.cfg has whole-line comments only: a comment after an extra command is part of the command
// and is sent to the tracker with it, as by the reference. With the emulator,
// "H1,-1,0,0   # hemisphere -x" was refused whole ("bad component"), so the hemisphere was not set
// and a receiver on the -x side was served mirrored, without a word. It is kept (the reference's
// bytes) but warned, naming the line.
TEST(ParseVrpnConfig, ACommentAfterAnExtraCommandIsWarned) {
  const VrpnConfig config = ParseVrpnConfig(
      "vrpn_Tracker_Fastrak Tracker0 /dev/ttyUSB0 115200 \\\r\n"
      "H1,-1,0,0   # hemisphere -x \\\r\n"
      "*1\\\r\n"
      "u\t# centimetres\r\n",
      "lab.cfg");
  ASSERT_EQ(config.fastrak_trackers.size(), 1u);
  EXPECT_EQ(config.fastrak_trackers[0].extra_commands,
            (std::vector<std::string>{"H1,-1,0,0   # hemisphere -x", "*1", "u\t# centimetres"}));
  ASSERT_EQ(config.warnings.size(), 2u);
  EXPECT_EQ(config.warnings[0].location.line, 2);
  EXPECT_EQ(config.warnings[1].location.line, 4);
  EXPECT_NE(config.warnings[0].ToString().find(
                "lab.cfg:2: warning: extra command 'H1,-1,0,0   # hemisphere -x' contains '#'"),
            std::string::npos)
      << config.warnings[0].ToString();
}

// Two tracker lines on one serial port: two drivers on one port read each other's bytes and
// reset the unit under each other, so neither tracker is served; it was accepted without a word.
// Spellings of one device (a symbolic link, "/./") are the same port.
TEST(ParseVrpnConfig, TwoTrackersOnOneSerialPortAreAnErrorNamingBothLines) {
  EXPECT_EQ(ParseError("vrpn_Tracker_Fastrak T0 /dev/ttyUSB0 115200\n"
                       "# the second unit\n"
                       "vrpn_Tracker_Fastrak T1 /dev/ttyUSB0 9600\n"),
            "lab.cfg:3: field 'serial_port': serial port '/dev/ttyUSB0' is already opened by "
            "tracker 'T0' at lab.cfg:1; two drivers on one port read each other's bytes (one line "
            "per unit)");
  // A port that does not exist (unplugged at start) is compared by its normal form.
  EXPECT_NE(ParseError("vrpn_Tracker_Fastrak T0 /dev/ttyUSB7 115200\n"
                       "vrpn_Tracker_Fastrak T1 /dev/./ttyUSB7 115200\n")
                .find("lab.cfg:2: field 'serial_port': serial port '/dev/./ttyUSB7' (the same "
                      "device as '/dev/ttyUSB7') is already opened by tracker 'T0' at lab.cfg:1"),
            std::string::npos);
  // An existing one by its canonical path: a symbolic link (as /dev/serial/by-id/ holds) is the
  // device it points to.
  const std::filesystem::path dir = testing::MakeTempDir("config_port_test");
  const std::filesystem::path device = dir / "ttyS9";
  std::ofstream(device).put('\n');
  std::filesystem::create_symlink(device, dir / "fastrak");
  const std::string first = "vrpn_Tracker_Fastrak T0 " + device.string() + " 115200\n";
  for (const std::string& other : {(dir / "fastrak").string(), (dir / "." / "ttyS9").string()}) {
    SCOPED_TRACE(other);
    const std::string error = ParseError(
        first + "vrpn_Tracker_NULL N 1 10\nvrpn_Tracker_Fastrak T1 " + other + " 9600\n");
    EXPECT_EQ(error.rfind("lab.cfg:3: field 'serial_port': serial port '" + other + "'", 0), 0u)
        << error;
    EXPECT_NE(error.find("already opened by tracker 'T0' at lab.cfg:1"), std::string::npos)
        << error;
  }
  // Different ports, and one port in two files, are fine.
  EXPECT_EQ(ParseError(first + "vrpn_Tracker_Fastrak T1 " + (dir / "ttyS8").string() + " 9600\n"),
            "");
  EXPECT_EQ(ParseError(first), "");
}

// A block whose lines after its last command are all comments, at the end of the file ("#u" below
// "H1,1,0,0\" as the file's last line): the Fastrak's was refused as "the file ends before the
// command line", an unknown device's ended without a word. It ends at the end of the file, warned
// at the first comment line, as a device line ends such a block.
TEST(ParseVrpnConfig, ABlockWithOnlyCommentsToTheEndOfTheFileEndsWithAWarning) {
  const VrpnConfig config = ParseVrpnConfig(
      "vrpn_Tracker_Fastrak Tracker0 /dev/ttyUSB0 115200 \\\n"  // 1
      "H1,1,0,0\\\n"                                            // 2
      "#u\n"                                                    // 3
      "# end of the lab's file\n",                              // 4
      "lab.cfg");
  ASSERT_EQ(config.fastrak_trackers.size(), 1u);
  EXPECT_EQ(config.fastrak_trackers[0].extra_commands, std::vector<std::string>{"H1,1,0,0"});
  ASSERT_EQ(config.warnings.size(), 1u);
  EXPECT_EQ(config.warnings[0].ToString().rfind(
                "lab.cfg:3: warning: the continuation block of 'Tracker0' (extra commands) has "
                "only comment lines from here to the end of the file",
                0),
            0u)
      << config.warnings[0].ToString();

  const VrpnConfig buttons = ParseVrpnConfig(
      "vrpn_Tracker_Fastrak T /dev/a 115200 /\nFTStylus S 0 /\n# FTStylus Spare 0\n", "lab.cfg");
  ASSERT_EQ(buttons.fastrak_trackers.at(0).buttons.size(), 1u);
  ASSERT_EQ(buttons.warnings.size(), 1u);
  EXPECT_EQ(buttons.warnings[0].location.line, 3);

  const VrpnConfig unknown =
      ParseVrpnConfig("vrpn_Tracker_Liberty L /dev/a 115200 \\\n#H1,1,0,0\n", "lab.cfg");
  std::vector<int> lines;
  for (const ConfigWarning& w : unknown.warnings) lines.push_back(w.location.line);
  EXPECT_EQ(lines, (std::vector<int>{2, 1})) << ::testing::PrintToString(lines);
  // Nothing at all after the line that continues is still an error.
  EXPECT_NE(ParseError("vrpn_Tracker_Fastrak T /dev/a 115200 \\\n")
                .find("lab.cfg:1: field "
                      "'extra commands'"),
            std::string::npos);
}

// A blank line inside a block ends it (the reference sends it as an empty command and ends the
// block): the commands after it were read as unknown devices and dropped with a warning (a
// hemisphere not set, the unit left in inches), and a '/' block stopped the server ("empty device
// line") even when a device line followed. The blank line is warned; a line after it that does not
// start a device is an error naming its line.
TEST(ParseVrpnConfig, ABlankLineEndsABlockAndAStrayLineAfterItIsAnError) {
  const VrpnConfig config = ParseVrpnConfig(
      "vrpn_Tracker_Fastrak T0 /dev/a 115200 \\\n"  // 1
      "H1,1,0,0/\n"                                 // 2
      "\n"                                          // 3
      "vrpn_Tracker_NULL N 1 10\n"                  // 4
      "vrpn_Tracker_Fastrak T1 /dev/b 115200 /\n"   // 5
      "  \t\n"                                      // 6
      "# the second tracker's stylus is broken\n"   // 7
      "trackcal_Calibration T1 c.json\n",           // 8
      "lab.cfg");
  ASSERT_EQ(config.fastrak_trackers.size(), 2u);
  EXPECT_EQ(config.fastrak_trackers[0].extra_commands, std::vector<std::string>{"H1,1,0,0"});
  EXPECT_TRUE(config.fastrak_trackers[0].buttons.empty());
  EXPECT_EQ(config.null_trackers.size(), 1u);
  EXPECT_EQ(config.calibrations.size(), 1u);
  ASSERT_EQ(config.warnings.size(), 2u);
  EXPECT_EQ(config.warnings[0].ToString().rfind(
                "lab.cfg:3: warning: a blank line ends the continuation block of 'T0' (device "
                "lines)",
                0),
            0u)
      << config.warnings[0].ToString();
  EXPECT_EQ(config.warnings[1].location.line, 6);

  EXPECT_EQ(ParseError("vrpn_Tracker_Fastrak T /dev/a 115200 \\\n"
                       "H1,1,0,0\\\n"
                       "\n"
                       "u\n"),
            "lab.cfg:4: field 'device type': 'u' is not a device line: it follows the "
            "continuation block of 'T' (extra commands), which the blank line at lab.cfg:3 ended; "
            "remove the blank line to continue the block");
  EXPECT_NE(ParseError("vrpn_Tracker_Fastrak T /dev/a 115200 /\n\n# pen\nFTStylus S 0\n")
                .find("lab.cfg:4: field 'device type': 'FTStylus' is not a device line"),
            std::string::npos);
  // A blank line outside a block is not warned, and an unknown line after it is one as before.
  EXPECT_EQ(ParseVrpnConfig("vrpn_Tracker_Fastrak T /dev/a 115200 \\\nu\n\nJoy0 1\n", "lab.cfg")
                .warnings.size(),
            1u);
}

TEST(ReadVrpnConfig, MissingFileThrows) {
  EXPECT_THROW(ReadVrpnConfig("/nonexistent/trackcal/vrpn.cfg"), std::runtime_error);
}

TEST(ParseVrpnConfig, AFileThatIsNotUtf8TextIsOneErrorSayingWhatItIs) {
  // Notepad's "Unicode" save warned "unknown device type" on every line, then said "no device
  // trackcal-server can serve"; so did a PDF or another binary file.
  const std::string text = "vrpn_Tracker_NULL Tracker0 2 60.0\n";
  std::string le16 = "\xFF\xFE", le32("\xFF\xFE\0\0", 4), no_mark;
  for (const char c : text) {
    le16 += std::string{c, '\0'};
    le32 += std::string{c, '\0', '\0', '\0'};
    no_mark += std::string{'\0', c};
  }
  EXPECT_EQ(ParseError(le16),
            "lab.cfg:1: UTF-16 text (a byte order mark FF FE or FE FF); save the VRPN "
            "configuration file as UTF-8");
  EXPECT_EQ(ParseError(le32),
            "lab.cfg:1: UTF-32 text (a byte order mark FF FE 00 00 or 00 00 FE FF); save the VRPN "
            "configuration file as UTF-8");
  EXPECT_EQ(ParseError("# lab\n" + no_mark),
            "lab.cfg:2: a NUL byte: not a text file (UTF-16 without a byte order mark, or a binary "
            "file?); save the VRPN configuration file as UTF-8");
  EXPECT_EQ(
      ParseError("%PDF-1.7\n%\xe2\xe3\xcf\xd3\n"),
      "lab.cfg:1: a PDF document (the file starts with %PDF-), not a VRPN configuration file");
  EXPECT_EQ(ParseError(text), "");  // UTF-8 text is read as before
}

TEST(ReadVrpnConfig, AFileThatCannotBeOpenedSaysWhy) {
  // "cannot open the VRPN configuration file" gave no reason (no such file, permission denied).
  try {
    ReadVrpnConfig("/nonexistent/trackcal/vrpn.cfg");
    ADD_FAILURE() << "no error";
  } catch (const std::runtime_error& e) {
    EXPECT_EQ(std::string(e.what()),
              "/nonexistent/trackcal/vrpn.cfg: cannot open the VRPN configuration file: No such "
              "file or directory");
  }
}

TEST(ReadVrpnConfig, AFolderIsNamedAsAFolder) {
  // `-f configs/` read as an empty file: "no device trackcal-server can serve".
  const std::filesystem::path dir = testing::MakeTempDir("config_test");
  try {
    ReadVrpnConfig(dir);
    ADD_FAILURE() << "no error";
  } catch (const std::runtime_error& e) {
    EXPECT_EQ(std::string(e.what()), dir.string() +
                                         ": is a folder, not a VRPN configuration file "
                                         "(give -f the vrpn.cfg)");
  }
}

}  // namespace
}  // namespace trackcal::vrpn
