// The Polhemus Fastrak as a state machine: command parser, device state and record formatting,
// with no I/O and no clock, so every byte it answers is unit-testable without a pseudo-terminal.
//
// Facts come from ../shared/vrpn/FASTRAK.md (copied knowledge, see docs/emulator.md): what the VRPN
// reference driver sends and accepts was verified byte for byte against its transcripts; the rest
// of the command set (ASCII records, Euler angles, direction cosines, hemisphere, `l`) is general
// Polhemus knowledge, implemented as documented in docs/emulator.md and not verified against
// hardware.
//
// Command framing (what a Fastrak does, as far as the driver needs it):
// - single-character commands act at once, with or without a following CR: `c` `C` `P` `S` `f` `F`
//   `u` `U` `t` `Y`, Ctrl-Y (0x19, reinitialise) and Ctrl-K (0x0B, save the configuration);
// - every other printable character starts a line command that ends at CR or LF (`O1,2,11,0\r`);
//   CR LF, LF CR, bare CR and blank lines are all accepted; an unknown command is ignored and
//   counted.

#pragma once

#include <array>
#include <cstdint>
#include <functional>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "core/pose.h"

namespace trackcal::emulator {

inline constexpr int kMaxStations = 4;
inline constexpr double kCentimetresPerInch = 2.54;

// Output list items (the numbers of the `O` command).
enum OutputItem : int {
  kItemSpace = 0,              // one space character
  kItemCrLf = 1,               // CR LF
  kItemPosition = 2,           // x, y, z in the current units
  kItemEulerAngles = 4,        // azimuth, elevation, roll in degrees (ZYX)
  kItemXDirectionCosines = 5,  // first row of the rotation matrix (x components of the axes)
  kItemYDirectionCosines = 6,  // second row
  kItemZDirectionCosines = 7,  // third row
  kItemQuaternion = 11,        // w, x, y, z
  kItemStylusSwitch = 16,      // ' ' then '0' or '1' (binary and ASCII)
};

// True for the output items this emulator can format.
bool IsSupportedOutputItem(int item);

// What one receiver measures at one instant, in metres (device units are applied when formatting).
struct StationMeasurement {
  Rigid3d transmitter_from_receiver;  // reported pose of the receiver in the transmitter frame
  bool stylus_button = false;         // stylus switch pressed
};

struct FastrakDeviceOptions {
  // Receivers plugged in (stations 1..n, 1 to 4); the others cannot be activated.
  int num_stations = 2;
  // Firmware version field of the status record, right-aligned in 6 characters.
  std::string firmware_version = "3.00";
  // System identification field of the status record, padded to 32 characters.
  std::string system_id = "EMULATED POLHEMUS FASTRAK";
  // Power-up output format: false = ASCII (the Fastrak default), true = binary.
  bool binary = false;
  // Power-up output mode: false = polled (the Fastrak default), true = continuous.
  bool continuous = false;
  // Power-up units: false = inches (the default), true = centimetres.
  bool metric = false;
  // Power-up hemisphere of every station (`H` command); a Fastrak's factory default is +x. A scene
  // with the transmitter above the volume sets its own, as a lab's saved configuration would.
  Eigen::Vector3d hemisphere = Eigen::Vector3d::UnitX();

  // Throws std::invalid_argument naming the field.
  void Check() const;
};

// One station's configuration.
struct StationState {
  bool connected = false;                    // a receiver is plugged in
  bool active = false;                       // reported in records (`l` command)
  std::vector<int> output_list;              // `O` command, items in order
  Eigen::Vector3d hemisphere{1, 0, 0};       // `H` command; zero vector = hemisphere tracking
  Eigen::Vector3d last_position_m{1, 0, 0};  // for hemisphere tracking
  // `e` command: 1 (the Fastrak's default) = point/track mode, the stylus switch of station 1
  // outputs a record in polled mode and toggles continuous output; 0 = it is only reported (item
  // 16). Drivers that use a stylus send `e1,0`.
  int stylus_function = 1;
};

class FastrakDevice {
 public:
  // Measures station (1-based) now; called for polled records only.
  using Measure = std::function<StationMeasurement(int station)>;

  explicit FastrakDevice(FastrakDeviceOptions options);

  // Consumes bytes written by the host and returns the bytes the device answers at once (status
  // record, polled records). Bytes may arrive in any chunking; an incomplete line is kept.
  std::string Receive(std::string_view bytes, const Measure& measure);

  // The record of one station in the current format (binary or ASCII) and units. Applies the
  // hemisphere and updates hemisphere tracking, hence not const.
  std::string FormatRecord(int station, const StationMeasurement& measurement);

  // The 55-byte status record ("2", station, "S", configuration, BIT errors, firmware, id, CR LF).
  std::string StatusRecord() const;

  // Size in bytes of a binary record for the station's current output list.
  size_t BinaryRecordSize(int station) const;

  // The stylus switch of station 1 (the only station whose switch works) at a measurement cycle.
  // In point/track mode (`e1,1`, the default) a press outputs one record per active station when
  // polled (returned, like `P`) and toggles the record stream when continuous.
  std::string StylusSwitch(bool pressed, const Measure& measure);

  // Active stations in increasing order.
  std::vector<int> ActiveStations() const;

  // Power-up state (Ctrl-Y, power on): the configuration saved by Ctrl-K if there is one, else
  // the options' power-up state.
  void Reinitialise();
  // Ctrl-K: the current operational configuration (format, units, continuous mode, every station's
  // output list, hemisphere, active state and stylus function, the filters) becomes the power-up
  // state, as a Fastrak saves it to non-volatile memory.
  void SaveConfiguration();
  bool has_saved_configuration() const { return saved_.has_value(); }

  bool continuous() const { return continuous_; }
  // Continuous and not paused by the stylus switch: records are being output.
  bool streaming() const { return continuous_ && !stylus_paused_; }
  bool binary() const { return binary_; }
  bool metric() const { return metric_; }
  const StationState& station(int station) const;
  // Position filter (`x`) and attitude filter (`v`) parameters as last sent; stored, not applied.
  const std::string& position_filter() const { return position_filter_; }
  const std::string& attitude_filter() const { return attitude_filter_; }
  // Commands accepted / ignored since construction.
  int64_t commands_accepted() const { return commands_accepted_; }
  int64_t commands_ignored() const { return commands_ignored_; }

  // Human-readable log of what each command did ("command 'c'", "ignored line 'Z1'"), drained by
  // the caller (the emulator prints it with timestamps).
  std::vector<std::string> TakeLog();

 private:
  void HandleSingle(char c, const Measure& measure, std::string* reply);
  void HandleLine(const std::string& line);
  void Log(std::string message);
  // Parses "station,..." integers/floats of a line command; false if malformed.
  bool ParseStationCommand(const std::string& args, int* station, std::vector<std::string>* rest);

  // What Ctrl-K saves and Reinitialise restores.
  struct SavedConfiguration {
    bool continuous = false;
    bool binary = false;
    bool metric = false;
    std::array<StationState, kMaxStations> stations;
    std::string position_filter;
    std::string attitude_filter;
  };

  FastrakDeviceOptions options_;
  std::optional<SavedConfiguration> saved_;
  std::array<StationState, kMaxStations> stations_;
  bool continuous_ = false;
  bool binary_ = false;
  bool metric_ = false;
  bool stylus_pressed_ = false;  // switch state at the last StylusSwitch()
  bool stylus_paused_ = false;   // continuous output toggled off by the switch
  std::string position_filter_;
  std::string attitude_filter_;
  std::string line_;  // line command being received
  bool in_line_ = false;
  bool line_overflow_ = false;
  int64_t commands_accepted_ = 0;
  int64_t commands_ignored_ = 0;
  std::vector<std::string> log_;
};

// Helpers shared with tests and the emulator.
// Float32 little-endian bytes of v (the Fastrak binary format).
void AppendFloat32Le(float v, std::string* out);
float ReadFloat32Le(const char* bytes);

}  // namespace trackcal::emulator
