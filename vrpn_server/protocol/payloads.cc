#include "vrpn_server/protocol/payloads.h"

#include <algorithm>
#include <charconv>
#include <cstring>
#include <stdexcept>

#include "vrpn_server/protocol/wire.h"

namespace trackcal::vrpn {
namespace {

void PutVector(ByteWriter& w, const Eigen::Vector3d& v) {
  w.PutF64(v.x());
  w.PutF64(v.y());
  w.PutF64(v.z());
}

void PutQuaternion(ByteWriter& w, const Eigen::Quaterniond& q) {
  double xyzw[4];
  QuaternionToXyzwArray(q, xyzw);
  for (double c : xyzw) w.PutF64(c);
}

Eigen::Vector3d GetVector(ByteReader& r) {
  const double x = r.GetF64();
  const double y = r.GetF64();
  const double z = r.GetF64();
  return Eigen::Vector3d(x, y, z);
}

Eigen::Quaterniond GetQuaternion(ByteReader& r) {
  double xyzw[4];
  for (double& c : xyzw) c = r.GetF64();
  return QuaternionFromXyzwArray(xyzw);
}

}  // namespace

void EncodePosQuatInto(const PosQuat& report, std::uint8_t* out) {
  StoreU32(static_cast<std::uint32_t>(report.sensor), out);
  // The reference repeats the sensor number in the pad word; receivers ignore it.
  StoreU32(static_cast<std::uint32_t>(report.sensor), out + 4);
  double values[7];
  values[0] = report.transmitter_from_receiver.translation.x();
  values[1] = report.transmitter_from_receiver.translation.y();
  values[2] = report.transmitter_from_receiver.translation.z();
  QuaternionToXyzwArray(report.transmitter_from_receiver.rotation, values + 3);
  for (int i = 0; i < 7; ++i) {
    std::uint64_t bits;
    std::memcpy(&bits, &values[i], 8);
    StoreU32(static_cast<std::uint32_t>(bits >> 32), out + 8 + 8 * i);
    StoreU32(static_cast<std::uint32_t>(bits), out + 12 + 8 * i);
  }
}

std::vector<std::uint8_t> EncodePosQuat(const PosQuat& report) {
  std::vector<std::uint8_t> out(kPosQuatSize);
  EncodePosQuatInto(report, out.data());
  return out;
}

std::optional<PosQuat> DecodePosQuat(std::span<const std::uint8_t> payload) {
  if (payload.size() != kPosQuatSize) return std::nullopt;
  ByteReader r(payload);
  PosQuat p;
  p.sensor = r.GetI32();
  r.Skip(4);
  p.transmitter_from_receiver.translation = GetVector(r);
  p.transmitter_from_receiver.rotation = GetQuaternion(r);
  return p;
}

std::vector<std::uint8_t> EncodeTrackerRate(const TrackerRate& rate) {
  std::vector<std::uint8_t> out;
  out.reserve(kVelocitySize);
  ByteWriter w(&out);
  w.PutI32(rate.sensor);
  w.PutI32(rate.sensor);
  PutVector(w, rate.linear);
  PutQuaternion(w, rate.delta_rotation);
  w.PutF64(rate.dt);
  return out;
}

std::optional<TrackerRate> DecodeTrackerRate(std::span<const std::uint8_t> payload) {
  if (payload.size() != kVelocitySize) return std::nullopt;
  ByteReader r(payload);
  TrackerRate t;
  t.sensor = r.GetI32();
  r.Skip(4);
  t.linear = GetVector(r);
  t.delta_rotation = GetQuaternion(r);
  t.dt = r.GetF64();
  return t;
}

std::vector<std::uint8_t> EncodeToRoom(const Rigid3d& room_from_tracker) {
  std::vector<std::uint8_t> out;
  out.reserve(kToRoomSize);
  ByteWriter w(&out);
  PutVector(w, room_from_tracker.translation);
  PutQuaternion(w, room_from_tracker.rotation);
  return out;
}

std::optional<Rigid3d> DecodeToRoom(std::span<const std::uint8_t> payload) {
  if (payload.size() != kToRoomSize) return std::nullopt;
  ByteReader r(payload);
  Rigid3d t;
  t.translation = GetVector(r);
  t.rotation = GetQuaternion(r);
  return t;
}

std::vector<std::uint8_t> EncodeUnitToSensor(const UnitToSensor& message) {
  std::vector<std::uint8_t> out;
  out.reserve(kUnitToSensorSize);
  ByteWriter w(&out);
  w.PutI32(message.sensor);
  w.PutI32(0);  // the reference writes 0 here (capture 06), unlike Pos_Quat
  PutVector(w, message.sensor_from_unit.translation);
  PutQuaternion(w, message.sensor_from_unit.rotation);
  return out;
}

std::optional<UnitToSensor> DecodeUnitToSensor(std::span<const std::uint8_t> payload) {
  if (payload.size() != kUnitToSensorSize) return std::nullopt;
  ByteReader r(payload);
  UnitToSensor u;
  u.sensor = r.GetI32();
  r.Skip(4);
  u.sensor_from_unit.translation = GetVector(r);
  u.sensor_from_unit.rotation = GetQuaternion(r);
  return u;
}

std::vector<std::uint8_t> EncodeWorkspace(const Workspace& workspace) {
  std::vector<std::uint8_t> out;
  out.reserve(kWorkspaceSize);
  ByteWriter w(&out);
  PutVector(w, workspace.min);
  PutVector(w, workspace.max);
  return out;
}

std::optional<Workspace> DecodeWorkspace(std::span<const std::uint8_t> payload) {
  if (payload.size() != kWorkspaceSize) return std::nullopt;
  ByteReader r(payload);
  Workspace ws;
  ws.min = GetVector(r);
  ws.max = GetVector(r);
  return ws;
}

std::vector<std::uint8_t> EncodeText(const TextMessage& message) {
  std::vector<std::uint8_t> out;
  out.reserve(kTextSize);
  ByteWriter w(&out);
  w.PutU32(static_cast<std::uint32_t>(message.severity));
  w.PutU32(message.level);
  const std::size_t n = std::min(message.text.size(), kTextFieldSize - 1);
  const std::string_view text(message.text.data(), n);
  const std::size_t nul = text.find('\0');
  w.PutString(text.substr(0, nul));
  out.resize(kTextSize, 0);  // NUL terminator and zero fill
  return out;
}

std::optional<TextMessage> DecodeText(std::span<const std::uint8_t> payload) {
  if (payload.size() != kTextSize) return std::nullopt;
  ByteReader r(payload);
  TextMessage m;
  const std::uint32_t severity = r.GetU32();
  if (severity > 2) return std::nullopt;
  m.severity = static_cast<TextSeverity>(severity);
  m.level = r.GetU32();
  auto field = r.GetBytes(kTextFieldSize);
  const auto nul = std::find(field.begin(), field.end(), std::uint8_t{0});
  if (nul == field.end()) return std::nullopt;
  m.text.assign(field.begin(), nul);
  return m;
}

std::vector<std::uint8_t> EncodeButtonChange(const ButtonChange& change) {
  std::vector<std::uint8_t> out;
  ByteWriter w(&out);
  w.PutI32(change.button);
  w.PutI32(change.state);
  return out;
}

std::optional<ButtonChange> DecodeButtonChange(std::span<const std::uint8_t> payload) {
  if (payload.size() != kButtonChangeSize) return std::nullopt;
  ByteReader r(payload);
  ButtonChange c;
  c.button = r.GetI32();
  c.state = r.GetI32();
  return c;
}

std::vector<std::uint8_t> EncodeButtonStates(std::span<const std::int32_t> states) {
  std::vector<std::uint8_t> out;
  ByteWriter w(&out);
  w.PutI32(static_cast<std::int32_t>(states.size()));
  for (std::int32_t s : states) w.PutI32(s);
  return out;
}

std::optional<std::vector<std::int32_t>> DecodeButtonStates(std::span<const std::uint8_t> payload) {
  ByteReader r(payload);
  const std::int32_t n = r.GetI32();
  if (!r.ok() || n < 0 || static_cast<std::size_t>(n) * 4 != r.remaining()) return std::nullopt;
  std::vector<std::int32_t> states(static_cast<std::size_t>(n));
  for (auto& s : states) s = r.GetI32();
  return states;
}

std::optional<double> DecodeSetUpdateRate(std::span<const std::uint8_t> payload) {
  if (payload.size() != kSetUpdateRateSize) return std::nullopt;
  ByteReader r(payload);
  return r.GetF64();
}

std::vector<std::uint8_t> EncodeDescription(std::string_view name) {
  if (name.empty() || name.size() > kMaxNameLength || name.find('\0') != std::string_view::npos) {
    throw std::invalid_argument("VRPN name '" + std::string(name) +
                                "': must be 1 to 95 characters without NUL");
  }
  std::vector<std::uint8_t> out;
  ByteWriter w(&out);
  w.PutU32(static_cast<std::uint32_t>(name.size() + 1));
  w.PutString(name);
  w.PutZeros(1);
  return out;
}

std::optional<std::string> DecodeDescription(std::span<const std::uint8_t> payload) {
  // At most 100 bytes, as the reference (sizeof(cName)).
  if (payload.size() > 4 + kMaxNameLength + 1 || payload.size() < 6) return std::nullopt;
  ByteReader r(payload);
  const std::uint32_t n = r.GetU32();
  // Bytes after the N name bytes are ignored, as by the reference (it puts the NUL at N): a peer
  // that counts the padding in the header length sends them.
  if (n > r.remaining() || n < 2) return std::nullopt;
  auto bytes = r.GetBytes(n);
  if (bytes[n - 1] != 0) return std::nullopt;
  std::string name(bytes.begin(), bytes.end() - 1);
  if (name.find('\0') != std::string::npos) return std::nullopt;
  return name;
}

std::vector<std::uint8_t> EncodeUdpDescription(std::string_view ipv4) {
  std::vector<std::uint8_t> out(ipv4.begin(), ipv4.end());
  out.push_back(0);
  return out;
}

std::optional<std::string> DecodeUdpDescription(std::span<const std::uint8_t> payload) {
  const auto nul = std::find(payload.begin(), payload.end(), std::uint8_t{0});
  if (nul == payload.end()) return std::nullopt;
  std::string host(payload.begin(), nul);
  if (!IsPlausibleHost(host) || host.size() > 255) return std::nullopt;
  return host;
}

bool IsPlausibleHost(std::string_view host) {
  if (host.empty()) return false;
  return std::all_of(host.begin(), host.end(), [](char c) {
    return (c >= '0' && c <= '9') || (c >= 'a' && c <= 'z') || (c >= 'A' && c <= 'Z') || c == '.' ||
           c == '-';
  });
}

std::vector<std::uint8_t> EncodeLobRequest(const LobRequest& request) {
  const std::string s = request.host + " " + std::to_string(request.port);
  std::vector<std::uint8_t> out(s.begin(), s.end());
  out.push_back(0);
  return out;
}

std::optional<LobRequest> DecodeLobRequest(std::span<const std::uint8_t> datagram) {
  if (datagram.size() > 300) return std::nullopt;
  const auto nul = std::find(datagram.begin(), datagram.end(), std::uint8_t{0});
  const std::string s(datagram.begin(), nul);
  // The reference reads the request with sscanf("%s %d"): whitespace before the host and any run
  // of whitespace between host and port are accepted, as is a '+' before the port.
  constexpr std::string_view kSpace = " \t\n\v\f\r";
  const auto host_begin = s.find_first_not_of(kSpace);
  if (host_begin == std::string::npos) return std::nullopt;
  const auto host_end = s.find_first_of(kSpace, host_begin);
  if (host_end == std::string::npos) return std::nullopt;
  LobRequest req;
  req.host = s.substr(host_begin, host_end - host_begin);
  if (req.host.find_first_not_of(
          "0123456789.abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ") != std::string::npos) {
    return std::nullopt;
  }
  auto port_begin = s.find_first_not_of(kSpace, host_end);
  if (port_begin == std::string::npos) return std::nullopt;
  if (s[port_begin] == '+') ++port_begin;
  const std::string port = s.substr(port_begin);
  const char* first = port.data();
  const char* last = port.data() + port.size();
  auto [ptr, ec] = std::from_chars(first, last, req.port);
  if (ec != std::errc() || ptr == first || req.port < 1024 || req.port > 65535) return std::nullopt;
  // Trailing whitespace is tolerated (sscanf semantics in the reference), anything else is not.
  for (const char* p = ptr; p != last; ++p) {
    if (kSpace.find(*p) == std::string_view::npos) return std::nullopt;
  }
  return req;
}

}  // namespace trackcal::vrpn
