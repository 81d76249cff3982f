// vrpn.cfg: the device configuration file of the VRPN server, read the way labs already write it,
// plus two trackcal lines. Format reference: docs/vrpn-config.md.
//
//   vrpn_Tracker_Fastrak <name> <port> <baud> [IS900time] [\ or /]
//     \-continuation lines: extra reset commands ("*N" = sleep N seconds)
//     /-continuation lines: FTStylus <button_name> <sensor> | Stylus <name> <sensor> |
//                           Wand <name> <sensor> c0min c0lo c0hi c0max c1min c1lo c1hi c1max
//   vrpn_Tracker_NULL <name> <sensors> <rate_hz>
//   trackcal_Calibration <tracker> <calibration_file> [raw=<raw_name>] [outside=clamp|fade]
//                        [fade_distance=<metres>]
//   trackcal_Tracker_Passthrough <name> <source>        source: [*]Device@host[:port] or *Device
//   # comment, blank lines
//
// Differences from the reference parser: trailing spaces/tabs and CRLF line ends do not end a
// continuation, comment lines inside a continuation block are skipped, an unknown device line is a
// warning (with its continuation lines skipped) instead of a fatal error, a blank line ends a
// continuation block with a warning (a line after it that starts no device is an error), and two
// Fastrak lines on one serial port (compared by canonical path) are an error naming both lines.
// Device names must be 1-95 printable bytes without '@' (what a client can address as Name@host);
// one that is not UTF-8 is served with a warning (a client must send its bytes). Errors throw
// std::invalid_argument "file:line: field 'x': what". Errors and warnings quote the file with
// control characters and bytes that are not UTF-8 written as \xNN (PrintableForLog).

#pragma once

#include <array>
#include <filesystem>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

namespace trackcal::vrpn {

// Where a spec came from, for messages.
struct ConfigLocation {
  std::string file;
  int line = 0;  // 1-based
  std::string ToString() const;  // "file:line"
};

enum class ButtonDeviceKind {
  kFastrakStylus,  // FTStylus: 1 button from output item 16
  kIs900Stylus,    // Stylus: IS-900, 2 buttons (parsed, not driven by trackcal's Fastrak driver)
  kIs900Wand,      // Wand: IS-900, 6 buttons + 2 analog channels (parsed, not driven)
};

// A button device attached to a tracker sensor by a '/' continuation line.
struct ButtonDeviceSpec {
  ButtonDeviceKind kind = ButtonDeviceKind::kFastrakStylus;
  std::string name;                   // VRPN device name of the button (and analog) device; may be
                                      // the tracker's own name (one sender for both, as in VRPN)
  int sensor = 0;                     // 0-based sensor (Fastrak station - 1)
  std::array<double, 8> wand_ranges{};  // Wand only: c0min c0lo c0hi c0max c1min c1lo c1hi c1max
  ConfigLocation location;
};

// vrpn_Tracker_Fastrak line and its continuation lines.
struct FastrakTrackerSpec {
  std::string name;                         // VRPN device name (sender) of the tracker
  std::string port;                         // serial device path, e.g. /dev/ttyUSB0
  int baud = 115200;                        // one of the rates termios supports (300 .. 115200)
  bool is900_time = false;                  // IS900time token present (InterSense only)
  std::vector<std::string> extra_commands;  // '\' lines, without the trailing '\' or '/'
  std::vector<ButtonDeviceSpec> buttons;    // '/' device lines
  ConfigLocation location;
};

// vrpn_Tracker_NULL <name> <sensors> <rate>: identity poses at a fixed rate (for tests and demos).
struct NullTrackerSpec {
  std::string name;
  int sensors = 1;
  double rate_hz = 0.0;  // 0 = never reports
  ConfigLocation location;
};

// What a correction does for a pose outside the calibrated volume.
enum class OutsidePolicy {
  kDefault,  // not given: the calibration file's own setting
  kClamp,    // evaluate the correction at the nearest point of the volume
  kFade,     // fade the correction out to zero outside the volume
  kLinear,   // continue the explicit terms to first order from the volume (up to the file's linear_reach)
};

// trackcal_Calibration <tracker> <file> [raw=<name>] [outside=clamp|fade|linear] [fade_distance=<m>]: serve <tracker> corrected
// by the calibration file, and optionally also its uncorrected reports under <raw=name>.
struct CalibrationSpec {
  std::string tracker;                  // name of a tracker device defined in this file
  std::filesystem::path file;           // calibration file; relative paths are relative to vrpn.cfg
  std::optional<std::string> raw_name;  // serve the raw reports too, under this device name
  OutsidePolicy outside = OutsidePolicy::kDefault;
  std::optional<double> fade_distance_m;  // fade_distance=<m>: where `fade` reaches no correction
  // sensor=<n>: correct only this VRPN sensor (0-based, Fastrak station n+1); none = every sensor.
  // A tracker has either one calibration for every sensor or one per listed sensor.
  std::optional<int> sensor;
  ConfigLocation location;
};

// trackcal_Tracker_Passthrough <name> <source>: a tracker whose reports come from another VRPN
// server (or from a device of this server) and are re-served under <name>, so they can be corrected.
struct PassthroughSpec {
  std::string name;            // device name served here
  std::string source;          // the source exactly as written, e.g. "*Tracker0@lab-pc:3883"
  std::string source_device;   // "Tracker0"
  std::string source_host;     // "lab-pc"; empty = this server (source written as "*Tracker0")
  int source_port = 3883;      // VRPN default port unless ":port" is given
  bool source_tcp_only = false;  // "Device@tcp://host:port": TCP, no UDP
  ConfigLocation location;
};

// A warning found while reading (unknown device line, ignored token...); the rest is still used.
struct ConfigWarning {
  ConfigLocation location;
  std::string message;
  std::string ToString() const;  // "file:line: warning: message", through PrintableForLog
};

struct VrpnConfig {
  std::vector<FastrakTrackerSpec> fastrak_trackers;
  std::vector<NullTrackerSpec> null_trackers;
  std::vector<PassthroughSpec> passthroughs;
  std::vector<CalibrationSpec> calibrations;
  std::vector<ConfigWarning> warnings;

  // The calibration attached to tracker `name`, if any.
  const CalibrationSpec* FindCalibration(std::string_view name) const;
};

// Parses the text of a vrpn.cfg. `file_name` is used in messages and to resolve relative
// calibration paths (relative to its directory). Throws std::invalid_argument naming file, line and
// field for malformed known lines; unknown device lines become warnings.
VrpnConfig ParseVrpnConfig(std::string_view text, const std::string& file_name);

// Reads and parses a vrpn.cfg file (throws std::runtime_error if it cannot be read).
VrpnConfig ReadVrpnConfig(const std::filesystem::path& path);

// The baud rates a serial port accepts (same set as the reference driver).
bool IsSupportedBaudRate(int baud);

}  // namespace trackcal::vrpn
