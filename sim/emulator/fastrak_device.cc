#include "sim/emulator/fastrak_device.h"

#include <algorithm>
#include <bit>
#include <cerrno>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <limits>
#include <stdexcept>

namespace trackcal::emulator {
namespace {

// A line command longer than this is garbage (the longest real one, `x` with four floats, is ~20).
constexpr size_t kMaxLineLength = 256;
// The most items an output list may hold ('O' command, Fastrak manual Rev. G: "up to 32 data
// items"); a longer list is ignored whole, like one with an unsupported item.
constexpr size_t kMaxOutputItems = 32;
constexpr char kCtrlY = 0x19;
constexpr char kCtrlK = 0x0B;

// Power-up output list of a Fastrak: position, Euler angles, CR LF [bg].
const std::vector<int>& DefaultOutputList() {
  static const std::vector<int> list = {kItemPosition, kItemEulerAngles, kItemCrLf};
  return list;
}

size_t BinaryItemSize(int item) {
  switch (item) {
    case kItemSpace:
      return 1;
    case kItemCrLf:
      return 2;
    case kItemPosition:
    case kItemEulerAngles:
    case kItemXDirectionCosines:
    case kItemYDirectionCosines:
    case kItemZDirectionCosines:
      return 12;
    case kItemQuaternion:
      return 16;
    case kItemStylusSwitch:
      return 2;
    default:
      return 0;
  }
}

std::string Trim(std::string_view s) {
  size_t b = 0, e = s.size();
  while (b < e && (s[b] == ' ' || s[b] == '\t')) ++b;
  while (e > b && (s[e - 1] == ' ' || s[e - 1] == '\t')) --e;
  return std::string(s.substr(b, e - b));
}

std::vector<std::string> SplitCommas(std::string_view s) {
  std::vector<std::string> parts;
  size_t start = 0;
  while (true) {
    const size_t comma = s.find(',', start);
    parts.push_back(
        Trim(s.substr(start, comma == std::string_view::npos ? s.npos : comma - start)));
    if (comma == std::string_view::npos) break;
    start = comma + 1;
  }
  return parts;
}

bool ParseInt(const std::string& s, int* value) {
  if (s.empty()) return false;
  char* end = nullptr;
  errno = 0;
  const long v = std::strtol(s.c_str(), &end, 10);
  // Out of int's range is malformed: a cast would wrap 2^32 + 2 to 2.
  if (*end != '\0' || errno == ERANGE || v < std::numeric_limits<int>::min() ||
      v > std::numeric_limits<int>::max()) {
    return false;
  }
  *value = static_cast<int>(v);
  return true;
}

bool ParseDouble(const std::string& s, double* value) {
  if (s.empty()) return false;
  char* end = nullptr;
  const double v = std::strtod(s.c_str(), &end);
  if (*end != '\0' || !std::isfinite(v)) return false;
  *value = v;
  return true;
}

std::string Printable(std::string_view s) {
  std::string out;
  for (const char c : s) {
    if (c >= 0x20 && c < 0x7f) {
      out += c;
    } else {
      char buf[8];
      std::snprintf(buf, sizeof(buf), "\\x%02x", static_cast<unsigned char>(c));
      out += buf;
    }
  }
  return out;
}

void AppendAsciiField(double v, const char* format, std::string* out) {
  char buf[32];
  std::snprintf(buf, sizeof(buf), format, v);
  std::string field = buf;
  // A value that rounds to zero is printed without a sign ("  -0.00" -> "   0.00").
  if (field.find_first_not_of(" -0.") == std::string::npos) {
    const size_t minus = field.find('-');
    if (minus != std::string::npos) field[minus] = ' ';
  }
  *out += field;
}

}  // namespace

bool IsSupportedOutputItem(int item) { return BinaryItemSize(item) > 0; }

void AppendFloat32Le(float v, std::string* out) {
  const uint32_t bits = std::bit_cast<uint32_t>(v);
  for (int i = 0; i < 4; ++i) out->push_back(static_cast<char>((bits >> (8 * i)) & 0xff));
}

float ReadFloat32Le(const char* bytes) {
  uint32_t bits = 0;
  for (int i = 0; i < 4; ++i)
    bits |= static_cast<uint32_t>(static_cast<unsigned char>(bytes[i])) << (8 * i);
  return std::bit_cast<float>(bits);
}

void FastrakDeviceOptions::Check() const {
  if (num_stations < 1 || num_stations > kMaxStations) {
    throw std::invalid_argument("FastrakDeviceOptions.num_stations: must be 1 to 4, got " +
                                std::to_string(num_stations));
  }
  if (firmware_version.size() > 6) {
    throw std::invalid_argument("FastrakDeviceOptions.firmware_version: at most 6 characters");
  }
  if (!hemisphere.allFinite()) {
    throw std::invalid_argument("FastrakDeviceOptions.hemisphere: not finite");
  }
  if (system_id.size() > 32) {
    throw std::invalid_argument("FastrakDeviceOptions.system_id: at most 32 characters");
  }
}

FastrakDevice::FastrakDevice(FastrakDeviceOptions options) : options_(std::move(options)) {
  options_.Check();
  Reinitialise();
}

void FastrakDevice::SaveConfiguration() {
  SavedConfiguration saved;
  saved.continuous = continuous_;
  saved.binary = binary_;
  saved.metric = metric_;
  saved.stations = stations_;
  saved.position_filter = position_filter_;
  saved.attitude_filter = attitude_filter_;
  saved_ = std::move(saved);
}

void FastrakDevice::Reinitialise() {
  stylus_pressed_ = false;
  stylus_paused_ = false;
  line_.clear();
  in_line_ = false;
  line_overflow_ = false;
  if (saved_) {
    continuous_ = saved_->continuous;
    binary_ = saved_->binary;
    metric_ = saved_->metric;
    stations_ = saved_->stations;
    position_filter_ = saved_->position_filter;
    attitude_filter_ = saved_->attitude_filter;
    for (StationState& s : stations_) {
      if (!s.hemisphere.isZero()) s.last_position_m = s.hemisphere;
    }
    return;
  }
  continuous_ = options_.continuous;
  binary_ = options_.binary;
  metric_ = options_.metric;
  position_filter_.clear();
  attitude_filter_.clear();
  for (int i = 0; i < kMaxStations; ++i) {
    StationState& s = stations_[i];
    s = StationState();
    s.connected = i < options_.num_stations;
    s.active = s.connected;
    s.output_list = DefaultOutputList();
    s.hemisphere = options_.hemisphere;
    if (!s.hemisphere.isZero()) s.last_position_m = s.hemisphere;
  }
}

const StationState& FastrakDevice::station(int station) const {
  if (station < 1 || station > kMaxStations) {
    throw std::out_of_range("FastrakDevice::station: station must be 1 to 4");
  }
  return stations_[station - 1];
}

std::vector<int> FastrakDevice::ActiveStations() const {
  std::vector<int> active;
  for (int i = 0; i < kMaxStations; ++i) {
    if (stations_[i].active) active.push_back(i + 1);
  }
  return active;
}

std::vector<std::string> FastrakDevice::TakeLog() {
  std::vector<std::string> out;
  out.swap(log_);
  return out;
}

void FastrakDevice::Log(std::string message) { log_.push_back(std::move(message)); }

std::string FastrakDevice::Receive(std::string_view bytes, const Measure& measure) {
  std::string reply;
  for (const char c : bytes) {
    if (c == kCtrlY || c == kCtrlK) {
      // Reinitialisation and saving win over anything half received.
      HandleSingle(c, measure, &reply);
      continue;
    }
    if (in_line_) {
      if (c == '\r' || c == '\n') {
        if (line_overflow_) {
          ++commands_ignored_;
          Log("ignored over-long line");
        } else {
          HandleLine(line_);
        }
        line_.clear();
        in_line_ = false;
        line_overflow_ = false;
      } else if (static_cast<unsigned char>(c) >= 0x20) {
        if (line_.size() < kMaxLineLength) {
          line_ += c;
        } else {
          line_overflow_ = true;
        }
      } else {
        // Line noise inside a line, as outside one: dropped, counted and logged.
        ++commands_ignored_;
        Log("ignored byte " + Printable(std::string_view(&c, 1)) + " in a line");
      }
      continue;
    }
    switch (c) {
      case '\r':
      case '\n':
        break;  // blank line or the CR/LF after a single-character command
      case 'c':
      case 'C':
      case 'P':
      case 'S':
      case 'f':
      case 'F':
      case 'u':
      case 'U':
      case 't':
      case 'Y':
        HandleSingle(c, measure, &reply);
        break;
      default:
        if (static_cast<unsigned char>(c) > 0x20 && static_cast<unsigned char>(c) < 0x7f) {
          in_line_ = true;
          line_.assign(1, c);
        } else {
          // Spaces, other control characters and 8-bit bytes are line noise to a Fastrak.
          ++commands_ignored_;
          Log("ignored byte " + Printable(std::string_view(&c, 1)));
        }
    }
  }
  return reply;
}

void FastrakDevice::HandleSingle(char c, const Measure& measure, std::string* reply) {
  ++commands_accepted_;
  Log("command '" + Printable(std::string_view(&c, 1)) + "'");
  switch (c) {
    case kCtrlY:
      Reinitialise();
      break;
    case kCtrlK:
      SaveConfiguration();
      break;
    case 'c':
      continuous_ = false;
      stylus_paused_ = false;
      break;
    case 'C':
      continuous_ = true;
      stylus_paused_ = false;
      break;
    case 'P':
      for (const int s : ActiveStations()) *reply += FormatRecord(s, measure(s));
      break;
    case 'S':
      *reply += StatusRecord();
      break;
    case 'f':
      binary_ = true;
      break;
    case 'F':
      binary_ = false;
      break;
    case 'u':
      metric_ = true;
      break;
    case 'U':
      metric_ = false;
      break;
    default:
      // `t` (extended mode toggle) and `Y` (tracking mode) per the driver's comments: no effect on
      // what this emulator outputs.
      break;
  }
}

std::string FastrakDevice::StylusSwitch(bool pressed, const Measure& measure) {
  const bool press = pressed && !stylus_pressed_;
  stylus_pressed_ = pressed;
  std::string reply;
  if (!press || !stations_[0].connected || stations_[0].stylus_function != 1) return reply;
  if (continuous_) {
    stylus_paused_ = !stylus_paused_;
    Log(stylus_paused_ ? "stylus switch: output off" : "stylus switch: output on");
  } else {
    for (const int s : ActiveStations()) reply += FormatRecord(s, measure(s));
    Log("stylus switch: point record");
  }
  return reply;
}

bool FastrakDevice::ParseStationCommand(const std::string& args, int* station,
                                        std::vector<std::string>* rest) {
  std::vector<std::string> parts = SplitCommas(args);
  if (!ParseInt(parts[0], station) || *station < 1 || *station > kMaxStations) return false;
  rest->assign(parts.begin() + 1, parts.end());
  return true;
}

void FastrakDevice::HandleLine(const std::string& line) {
  const char command = line[0];
  const std::string args = line.substr(1);
  auto ignore = [&](const std::string& why) {
    ++commands_ignored_;
    Log("ignored line '" + Printable(line) + "': " + why);
  };
  int s = 0;
  std::vector<std::string> rest;
  switch (command) {
    case 'O': {
      if (!ParseStationCommand(args, &s, &rest)) return ignore("bad station");
      std::vector<int> items;
      for (const std::string& field : rest) {
        int item = 0;
        if (!ParseInt(field, &item)) return ignore("bad item '" + field + "'");
        if (!IsSupportedOutputItem(item)) return ignore("unsupported item " + field);
        items.push_back(item);
      }
      if (items.empty()) return ignore("empty output list");
      if (items.size() > kMaxOutputItems) return ignore("more than 32 items");
      stations_[s - 1].output_list = items;
      break;
    }
    case 'H': {
      if (!ParseStationCommand(args, &s, &rest) || rest.size() != 3)
        return ignore("expects station,x,y,z");
      Eigen::Vector3d h;
      for (int i = 0; i < 3; ++i) {
        if (!ParseDouble(rest[i], &h[i])) return ignore("bad component '" + rest[i] + "'");
      }
      stations_[s - 1].hemisphere = h;
      break;
    }
    case 'l': {
      int state = 0;
      if (!ParseStationCommand(args, &s, &rest) || rest.size() != 1 || !ParseInt(rest[0], &state)) {
        return ignore("expects station,state");
      }
      if (!stations_[s - 1].connected && state != 0) return ignore("no receiver on that station");
      stations_[s - 1].active = state != 0;
      break;
    }
    case 'e': {
      int function = 0;
      if (!ParseStationCommand(args, &s, &rest) || rest.size() != 1 ||
          !ParseInt(rest[0], &function)) {
        return ignore("expects station,function");
      }
      stations_[s - 1].stylus_function = function;
      break;
    }
    case 'x':
      position_filter_ = args;
      break;
    case 'v':
      attitude_filter_ = args;
      break;
    default:
      return ignore("unknown command");
  }
  ++commands_accepted_;
  Log("line command '" + Printable(line) + "'");
}

size_t FastrakDevice::BinaryRecordSize(int station) const {
  size_t n = 3;
  for (const int item : this->station(station).output_list) n += BinaryItemSize(item);
  return n;
}

std::string FastrakDevice::FormatRecord(int station_number, const StationMeasurement& measurement) {
  StationState& st = stations_.at(station_number - 1);
  // A dipole field is symmetric under p -> -p: the device reports the solution in the selected
  // hemisphere (or, with a zero hemisphere vector, the one continuous with the last report).
  Eigen::Vector3d p = measurement.transmitter_from_receiver.translation;
  const Eigen::Vector3d reference = st.hemisphere.isZero() ? st.last_position_m : st.hemisphere;
  if (p.dot(reference) < 0) p = -p;
  st.last_position_m = p;
  const double scale = (metric_ ? 100.0 : 100.0 / kCentimetresPerInch);  // metres -> cm or inches
  const Eigen::Vector3d p_units = p * scale;
  Eigen::Quaterniond q = measurement.transmitter_from_receiver.rotation.normalized();
  if (q.w() < 0) q.coeffs() *= -1.0;  // report the scalar-non-negative representative
  const Eigen::Matrix3d r = q.toRotationMatrix();

  std::string out;
  out += '0';
  out += static_cast<char>('0' + station_number);
  out += ' ';
  auto triple = [&](double a, double b, double c, const char* ascii_format) {
    if (binary_) {
      AppendFloat32Le(static_cast<float>(a), &out);
      AppendFloat32Le(static_cast<float>(b), &out);
      AppendFloat32Le(static_cast<float>(c), &out);
    } else {
      AppendAsciiField(a, ascii_format, &out);
      AppendAsciiField(b, ascii_format, &out);
      AppendAsciiField(c, ascii_format, &out);
    }
  };
  for (const int item : st.output_list) {
    switch (item) {
      case kItemSpace:
        out += ' ';
        break;
      case kItemCrLf:
        out += "\r\n";
        break;
      case kItemPosition:
        triple(p_units.x(), p_units.y(), p_units.z(), "%7.2f");
        break;
      case kItemEulerAngles: {
        // R = Rz(azimuth) * Ry(elevation) * Rx(roll).
        const double azimuth = std::atan2(r(1, 0), r(0, 0));
        const double elevation = std::atan2(-r(2, 0), std::hypot(r(0, 0), r(1, 0)));
        const double roll = std::atan2(r(2, 1), r(2, 2));
        triple(azimuth * kDegPerRad, elevation * kDegPerRad, roll * kDegPerRad, "%7.2f");
        break;
      }
      case kItemXDirectionCosines:
      case kItemYDirectionCosines:
      case kItemZDirectionCosines: {
        // Item 5, 6, 7 = rows 0, 1, 2 of the rotation, so that (5a, 6a, 7a) is the receiver x axis.
        const int row = item - kItemXDirectionCosines;
        triple(r(row, 0), r(row, 1), r(row, 2), "%7.4f");
        break;
      }
      case kItemQuaternion:
        if (binary_) {
          AppendFloat32Le(static_cast<float>(q.w()), &out);
          AppendFloat32Le(static_cast<float>(q.x()), &out);
          AppendFloat32Le(static_cast<float>(q.y()), &out);
          AppendFloat32Le(static_cast<float>(q.z()), &out);
        } else {
          for (const double v : {q.w(), q.x(), q.y(), q.z()}) AppendAsciiField(v, "%7.4f", &out);
        }
        break;
      case kItemStylusSwitch:
        // The stylus switch works only on station 1 (Fastrak manual, `e` command); a stylus on
        // another receiver port tracks but its switch always reads open.
        out += ' ';
        out += station_number == 1 && measurement.stylus_button ? '1' : '0';
        break;
      default:
        break;  // unreachable: `O` only stores supported items
    }
  }
  return out;
}

std::string FastrakDevice::StatusRecord() const {
  // Configuration bits [bg, not verified]: 0 binary, 1 centimetres, 3 continuous; 0x0A0 are fixed
  // bits that reproduce the reference transcript's "0A0" in the power-up state.
  const int config = 0x0A0 | (binary_ ? 0x1 : 0) | (metric_ ? 0x2 : 0) | (continuous_ ? 0x8 : 0);
  const std::vector<int> active = ActiveStations();
  char buf[64];
  std::snprintf(buf, sizeof(buf), "2%cS%03X000      %6s%-32s\r\n",
                static_cast<char>('0' + (active.empty() ? 1 : active.front())), config,
                options_.firmware_version.c_str(), options_.system_id.c_str());
  return buf;
}

}  // namespace trackcal::emulator
