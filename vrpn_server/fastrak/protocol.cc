#include "vrpn_server/fastrak/protocol.h"

#include <cctype>
#include <cmath>
#include <cstring>
#include <stdexcept>

namespace trackcal::fastrak {
namespace {

std::string_view Trim(std::string_view s) {
  while (!s.empty() && s.front() == ' ') s.remove_prefix(1);
  while (!s.empty() && s.back() == ' ') s.remove_suffix(1);
  return s;
}

bool ParseHex3(std::string_view s, uint32_t* value) {
  *value = 0;
  for (char c : s) {
    int digit;
    if (c >= '0' && c <= '9') {
      digit = c - '0';
    } else if (c >= 'A' && c <= 'F') {
      digit = c - 'A' + 10;
    } else if (c >= 'a' && c <= 'f') {
      digit = c - 'a' + 10;
    } else {
      return false;
    }
    *value = *value * 16 + static_cast<uint32_t>(digit);
  }
  return true;
}

void CheckStation(int station) {
  if (station < 1 || station > kMaxStations) {
    throw std::invalid_argument("Fastrak station must be 1..4, got " + std::to_string(station));
  }
}

}  // namespace

double MetresPerUnit(Units units) {
  return units == Units::kInches ? kMetresPerInch : kMetresPerCentimetre;
}

const char* UnitsName(Units units) { return units == Units::kInches ? "inches" : "centimetres"; }

char UnitsCommand(Units units) { return units == Units::kInches ? 'U' : 'u'; }

std::string OutputListCommand(int station, bool stylus) {
  CheckStation(station);
  // Built by appending: GCC 12 warns falsely (-Wrestrict) on "literal" + std::string here.
  std::string command(1, 'O');
  command += std::to_string(station);
  command += stylus ? ",2,11,16,0\r" : ",2,11,0\r";
  return command;
}

std::string StylusModeCommand(int station) {
  CheckStation(station);
  std::string command(1, 'e');
  command += std::to_string(station);
  command += ",0\r";
  return command;
}

std::string ResetPreamble(int attempt) {
  if (attempt <= 1) return "c";
  if (attempt == 2) return "\rc";
  if (attempt <= 4)
    return "\r\x19"
           "c";
  if (attempt == 5)
    return "\rt\x19"
           "c";
  return "\rYt\x19"
         "c";
}

bool ResetPreambleReinitialises(int attempt) { return attempt >= 3; }

namespace {

// The 55-byte Fastrak layout's fields into *status; false with the first difference in *note.
bool ParseStatusLayout(std::string_view bytes, StatusRecord* status, std::string* note) {
  auto differs = [&](const std::string& what) {
    *note = what;
    return false;
  };
  if (bytes.size() != kStatusRecordSize) {
    return differs(std::to_string(bytes.size()) + " bytes, not the Fastrak's 55");
  }
  if (bytes[1] < '1' || bytes[1] > '4') return differs("station byte is not 1..4");
  if (bytes[2] != 'S') return differs("byte 2 is not 'S'");
  if (!ParseHex3(bytes.substr(3, 3), &status->configuration)) {
    return differs("configuration field is not 3 hex digits");
  }
  if (!ParseHex3(bytes.substr(6, 3), &status->bit_errors)) {
    return differs("BIT error field is not 3 hex digits");
  }
  for (size_t i = 9; i < 15; ++i) {
    if (bytes[i] != ' ') return differs("bytes 9..14 are not spaces");
  }
  for (size_t i = 15; i < 53; ++i) {
    if (!std::isprint(static_cast<unsigned char>(bytes[i]))) {
      return differs("firmware/system id has a non-printable byte at " + std::to_string(i));
    }
  }
  if (bytes[53] != '\r') return differs("byte 53 is not CR");
  status->station = bytes[1] - '0';
  status->firmware_version = std::string(Trim(bytes.substr(15, 6)));
  status->system_id = std::string(Trim(bytes.substr(21, 32)));
  return true;
}

}  // namespace

std::optional<StatusRecord> ParseStatusRecord(std::string_view bytes, std::string* why) {
  auto fail = [&](const std::string& reason) -> std::optional<StatusRecord> {
    if (why != nullptr) *why = reason;
    return std::nullopt;
  };
  if (bytes.empty()) return fail("no status reply");
  if (bytes[0] != '2') return fail("status reply does not start with '2'");
  if (bytes.back() != '\n') {
    return fail("status reply (" + std::to_string(bytes.size()) + " bytes) does not end with LF");
  }
  StatusRecord status;
  StatusRecord parsed;
  if (ParseStatusLayout(bytes, &parsed, &status.layout_note)) return parsed;
  if (bytes.size() > 1 && bytes[1] >= '1' && bytes[1] <= '4') status.station = bytes[1] - '0';
  return status;
}

float ReadFloat32Le(const uint8_t* bytes) {
  const uint32_t bits = static_cast<uint32_t>(bytes[0]) | (static_cast<uint32_t>(bytes[1]) << 8) |
                        (static_cast<uint32_t>(bytes[2]) << 16) |
                        (static_cast<uint32_t>(bytes[3]) << 24);
  float value;
  static_assert(sizeof(value) == sizeof(bits));
  std::memcpy(&value, &bits, sizeof(value));
  return value;
}

std::optional<RawRecord> DecodeRecord(const uint8_t* bytes, size_t size) {
  if (size != kRecordSize && size != kStylusRecordSize) return std::nullopt;
  if (bytes[0] != '0') return std::nullopt;
  if (bytes[1] < '1' || bytes[1] > '4') return std::nullopt;
  const char status = static_cast<char>(bytes[2]);
  if (status != ' ' && !std::isalpha(static_cast<unsigned char>(status))) return std::nullopt;
  if (bytes[size - 1] != ' ') return std::nullopt;
  RawRecord record;
  record.station = bytes[1] - '0';
  record.status = status;
  for (int i = 0; i < 3; ++i) {
    record.position[i] = ReadFloat32Le(bytes + 3 + 4 * i);
    if (!std::isfinite(record.position[i]) || std::abs(record.position[i]) > kMaxPositionUnits) {
      return std::nullopt;
    }
  }
  double norm2 = 0.0;
  for (int i = 0; i < 4; ++i) {
    record.wxyz[i] = ReadFloat32Le(bytes + 15 + 4 * i);
    if (!std::isfinite(record.wxyz[i])) return std::nullopt;
    norm2 += static_cast<double>(record.wxyz[i]) * record.wxyz[i];
  }
  if (std::abs(std::sqrt(norm2) - 1.0) > kMaxQuaternionNormError) return std::nullopt;
  if (size == kStylusRecordSize) {
    // Item 16 is two bytes: a separator the reference skips, then the switch as an ASCII digit.
    const uint8_t digit = bytes[32];
    if (digit != '0' && digit != '1') return std::nullopt;
    record.stylus = digit == '1';
  }
  return record;
}

}  // namespace trackcal::fastrak
