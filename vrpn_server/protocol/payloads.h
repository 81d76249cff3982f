// VRPN message type names and payload codecs (tracker, button, base and system messages).
//
// Every encoder produces exactly the payload length the reference client checks; every decoder
// returns std::nullopt when the length is not the exact one (the reference drops the connection on a
// wrong length, we drop only the message). Doubles are big-endian IEEE-754; quaternions are x, y, z, w.

#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "core/pose.h"

namespace trackcal::vrpn {

// Type names, exactly as on the wire (case and spaces matter).
inline constexpr std::string_view kPosQuatType = "vrpn_Tracker Pos_Quat";
inline constexpr std::string_view kVelocityType = "vrpn_Tracker Velocity";
inline constexpr std::string_view kAccelerationType = "vrpn_Tracker Acceleration";
inline constexpr std::string_view kToRoomType = "vrpn_Tracker To_Room";
inline constexpr std::string_view kUnitToSensorType = "vrpn_Tracker Unit_To_Sensor";
inline constexpr std::string_view kWorkspaceType = "vrpn_Tracker Workspace";
inline constexpr std::string_view kRequestToRoomType = "vrpn_Tracker Request_Tracker_To_Room";
inline constexpr std::string_view kRequestUnitToSensorType = "vrpn_Tracker Request_Unit_To_Sensor";
inline constexpr std::string_view kRequestWorkspaceType = "vrpn_Tracker Request_Tracker_Workspace";
inline constexpr std::string_view kSetUpdateRateType = "vrpn_Tracker set_update_rate";
inline constexpr std::string_view kResetOriginType = "vrpn_Tracker Reset_Origin";
inline constexpr std::string_view kTextType = "vrpn_Base text_message";
inline constexpr std::string_view kPingType = "vrpn_Base ping_message";
inline constexpr std::string_view kPongType = "vrpn_Base pong_message";
inline constexpr std::string_view kButtonChangeType = "vrpn_Button Change";
inline constexpr std::string_view kButtonStatesType = "vrpn_Button States";
// The reference describes this sender first (id 0); we do too so our ids match its numbering.
inline constexpr std::string_view kControlSender = "VRPN Control";

inline constexpr std::size_t kPosQuatSize = 64;
inline constexpr std::size_t kVelocitySize = 72;  // also Acceleration
inline constexpr std::size_t kToRoomSize = 56;
inline constexpr std::size_t kUnitToSensorSize = 64;
inline constexpr std::size_t kWorkspaceSize = 48;
inline constexpr std::size_t kTextSize = 1032;
inline constexpr std::size_t kTextFieldSize = 1024;  // text + NUL inside the text payload
inline constexpr std::size_t kSetUpdateRateSize = 8;
inline constexpr std::size_t kButtonChangeSize = 8;

// Pos_Quat: the receiver (sensor) pose in the transmitter (source) frame, metres.
struct PosQuat {
  std::int32_t sensor = 0;
  Rigid3d transmitter_from_receiver;
};
std::vector<std::uint8_t> EncodePosQuat(const PosQuat& report);
// Writes the 64 bytes into out (no allocation; used on the hot path).
void EncodePosQuatInto(const PosQuat& report, std::uint8_t* out);
std::optional<PosQuat> DecodePosQuat(std::span<const std::uint8_t> payload);

// Velocity (m/s) or Acceleration (m/s^2): linear vector plus the rotation over dt seconds.
struct TrackerRate {
  std::int32_t sensor = 0;
  Eigen::Vector3d linear = Eigen::Vector3d::Zero();
  Eigen::Quaterniond delta_rotation = Eigen::Quaterniond::Identity();
  double dt = 1.0;
};
std::vector<std::uint8_t> EncodeTrackerRate(const TrackerRate& rate);
std::optional<TrackerRate> DecodeTrackerRate(std::span<const std::uint8_t> payload);

// To_Room: the tracker (transmitter) frame in room coordinates; information only for clients.
std::vector<std::uint8_t> EncodeToRoom(const Rigid3d& room_from_tracker);
std::optional<Rigid3d> DecodeToRoom(std::span<const std::uint8_t> payload);

// Unit_To_Sensor: per-sensor offset; the pad word is 0 here (unlike Pos_Quat).
struct UnitToSensor {
  std::int32_t sensor = 0;
  Rigid3d sensor_from_unit;
};
std::vector<std::uint8_t> EncodeUnitToSensor(const UnitToSensor& message);
std::optional<UnitToSensor> DecodeUnitToSensor(std::span<const std::uint8_t> payload);

// Workspace: axis-aligned box in the tracker frame, metres.
struct Workspace {
  Eigen::Vector3d min = Eigen::Vector3d(-0.2, -0.2, -0.1);  // reference defaults
  Eigen::Vector3d max = Eigen::Vector3d(0.2, 0.2, 0.2);
};
std::vector<std::uint8_t> EncodeWorkspace(const Workspace& workspace);
std::optional<Workspace> DecodeWorkspace(std::span<const std::uint8_t> payload);

// Text message: severity 0 normal, 1 warning, 2 error; level is free (clients send elapsed seconds).
enum class TextSeverity : std::uint32_t { kNormal = 0, kWarning = 1, kError = 2 };
struct TextMessage {
  TextSeverity severity = TextSeverity::kNormal;
  std::uint32_t level = 0;
  std::string text;
};
// Always 1032 bytes, zero-filled after the NUL; text longer than 1023 bytes is truncated.
std::vector<std::uint8_t> EncodeText(const TextMessage& message);
// Text is read up to the first NUL (bytes after it are garbage in the reference).
std::optional<TextMessage> DecodeText(std::span<const std::uint8_t> payload);

// vrpn_Button Change: int32 button, int32 state (0 released, 1 pressed), 8 bytes. No capture shows
// one; the layout is the reference's own encoder (vrpn_Button::encode_to, VRPN 07.x: vrpn_buffer of
// the button number, then of the state), which its client decodes the same way.
struct ButtonChange {
  std::int32_t button = 0;
  std::int32_t state = 0;
};
std::vector<std::uint8_t> EncodeButtonChange(const ButtonChange& change);
std::optional<ButtonChange> DecodeButtonChange(std::span<const std::uint8_t> payload);

// vrpn_Button States: int32 count, then one int32 per button (8 bytes for one button in capture 08).
std::vector<std::uint8_t> EncodeButtonStates(std::span<const std::int32_t> states);
std::optional<std::vector<std::int32_t>> DecodeButtonStates(std::span<const std::uint8_t> payload);

// set_update_rate: one float64 in Hz.
std::optional<double> DecodeSetUpdateRate(std::span<const std::uint8_t> payload);

// Sender/type description payload: uint32 N = strlen(name) + 1, name, NUL.
// Throws std::invalid_argument for an empty name, a name with a NUL or longer than kMaxNameLength.
std::vector<std::uint8_t> EncodeDescription(std::string_view name);
// nullopt for a payload over 100 bytes, an N beyond the payload, or no NUL ending the N name bytes.
// Bytes after those N are ignored, as by the reference.
std::optional<std::string> DecodeDescription(std::span<const std::uint8_t> payload);

// UDP description payload: dotted IPv4 + NUL (the port travels in the header's sender field).
std::vector<std::uint8_t> EncodeUdpDescription(std::string_view ipv4);
std::optional<std::string> DecodeUdpDescription(std::span<const std::uint8_t> payload);

// The UDP "lob" datagram a client sends to the server port: "<dotted-IPv4> <tcp-port>\0".
struct LobRequest {
  std::string host;
  int port = 0;
};
std::vector<std::uint8_t> EncodeLobRequest(const LobRequest& request);
// Validated as the reference does: two tokens, port in [1024, 65535], host of letters, digits and dots.
std::optional<LobRequest> DecodeLobRequest(std::span<const std::uint8_t> datagram);

// True when a dotted IPv4 or host name only uses letters, digits, dots and hyphens and is non-empty.
bool IsPlausibleHost(std::string_view host);

}  // namespace trackcal::vrpn
