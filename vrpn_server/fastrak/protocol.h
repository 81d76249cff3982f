// The bytes of the Polhemus Fastrak serial protocol that trackcal's driver uses, with no I/O:
// command strings, the status record and the binary record layout. Facts: FASTRAK.md (VRPN 07.38
// reference driver, verified against captured transcripts), see docs/fastrak-driver.md.

#pragma once

#include <cstddef>
#include <cstdint>
#include <optional>
#include <string>
#include <string_view>

namespace trackcal::fastrak {

inline constexpr int kMaxStations = 4;

// Length units of the position in the device's records: `U` selects inches, `u` centimetres.
enum class Units { kInches, kCentimetres };

inline constexpr double kMetresPerInch = 0.0254;
inline constexpr double kMetresPerCentimetre = 0.01;
double MetresPerUnit(Units units);
const char* UnitsName(Units units);  // "inches" / "centimetres"
char UnitsCommand(Units units);      // 'U' / 'u'

// Single-byte commands.
inline constexpr char kStopContinuous = 'c';
inline constexpr char kStartContinuous = 'C';
inline constexpr char kBinaryFormat = 'f';
inline constexpr char kRequestStatus = 'S';
inline constexpr char kReinitialise = 0x19;  // Ctrl-Y
inline constexpr char kToggleExtendedMode = 't';
inline constexpr char kTrackingMode = 'Y';

// Filter commands the reference sends on every reset (its vrpn.cfg path always enables them).
inline constexpr std::string_view kPositionFilterCommand = "x0.2,0.2,0.8,0.8\r";
inline constexpr std::string_view kAttitudeFilterCommand = "v0.2,0.2,0.8,0.8\r";

// "O<station>,2,11[,16],0\r": position, quaternion, [stylus switch], space. Station is 1-based.
std::string OutputListCommand(int station, bool stylus);
// "e<station>,0\r": stylus button reports its state in every record (mouse mode).
std::string StylusModeCommand(int station);

// Bytes the reference writes before `S` on reset attempt n (1-based): the escalation of FASTRAK.md
// section 4 (1: c; 2: CR c; 3-4: CR ^Y c; 5: CR t ^Y c; 6+: CR Y t ^Y c).
std::string ResetPreamble(int attempt);
// True if that attempt reinitialises the tracker (^Y) and must wait for it.
bool ResetPreambleReinitialises(int attempt);

// Size of a binary record with output list 2,11[,16],0.
inline constexpr size_t kRecordSize = 32;
inline constexpr size_t kStylusRecordSize = 34;
inline size_t RecordSize(bool stylus) { return stylus ? kStylusRecordSize : kRecordSize; }

// The 55-byte status record: '2', station, 'S', 3 hex configuration, 3 hex BIT errors, 6 spaces,
// 6 chars firmware version, 32 chars system id, CR, LF.
inline constexpr size_t kStatusRecordSize = 55;
struct StatusRecord {
  int station = 0;               // station digit of the reply (1..4; 0 when not a digit 1..4)
  uint32_t configuration = 0;    // 3 hex digits
  uint32_t bit_errors = 0;       // 3 hex digits; non-zero = built-in test failures
  std::string firmware_version;  // trimmed
  std::string system_id;         // trimmed
  // Empty when the reply has the 55-byte Fastrak layout above and every field parsed. Otherwise
  // what differs (a 54-byte IS-900 reply, another firmware's fields), and the fields above are
  // unknown (left at their defaults): the reply is still a status, as the reference takes it.
  std::string layout_note;
};
// A status reply as the reference driver accepts it: the first byte is '2' (records start with
// '0', so output still streaming is refused) and the last is LF. Anything else returns nullopt
// and says why in *why. The fields are parsed when the reply has the Fastrak's 55-byte layout;
// a reply that does not (StatusRecord::layout_note) is still accepted, since the reference checks
// nothing more and a stricter check would keep a working unit in the reset loop forever.
std::optional<StatusRecord> ParseStatusRecord(std::string_view bytes, std::string* why);

// One binary record decoded but not converted: values as the device sent them.
struct RawRecord {
  int station = 0;             // 1..4
  char status = ' ';           // ' ' or a letter (error/warning code)
  float position[3] = {};      // x, y, z in the device's units
  float wxyz[4] = {};          // quaternion, scalar first as on the wire
  std::optional<bool> stylus;  // switch state if the record carries item 16
};

// Reads float32 little-endian (the Fastrak's binary float format) regardless of host order.
float ReadFloat32Le(const uint8_t* bytes);

// Decodes a record of `size` bytes (kRecordSize or kStylusRecordSize) if its framing is valid:
// '0', station '1'..'4', status space or letter, stylus digit '0'/'1', final space, finite values,
// a unit quaternion (within kMaxQuaternionNormError) and a position within kMaxPositionUnits.
// These checks are what lets the parser find record boundaries again after garbage.
std::optional<RawRecord> DecodeRecord(const uint8_t* bytes, size_t size);

// The Fastrak outputs normalised quaternions (float32, so |q| = 1 within ~1e-7); 1e-3 is 10^4 times
// that, so any device rounding passes, while a quaternion whose last component was replaced by
// other bytes (a merged record) fails unless that component was below 0.045 (2.6 deg). The old
// 0.05 let a component up to 0.31 (36 deg of rotation) vanish unnoticed.
inline constexpr double kMaxQuaternionNormError = 1e-3;
// Per-axis bound in device units, larger than any Fastrak range (30 ft = 914 cm with the long-range
// transmitter) in either unit; RecordParser also bounds |position| in metres (kMaxRangeM).
inline constexpr double kMaxPositionUnits = 1000.0;

}  // namespace trackcal::fastrak
