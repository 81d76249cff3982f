#include "vrpn_server/server/server_session.h"

#include "core/printable_text.h"
#include "vrpn_server/protocol/payloads.h"

namespace trackcal::vrpn {

ServerSession::ServerSession(std::shared_ptr<const ServerCatalog> catalog,
                             Connection::Options options, std::string peer_label, LogFunction log,
                             std::size_t max_output_bytes)
    : catalog_(std::move(catalog)),
      connection_(catalog_->names(), options),
      peer_label_(std::move(peer_label)),
      log_(std::move(log)),
      max_output_bytes_(max_output_bytes) {}

void ServerSession::Start(std::optional<std::pair<std::string, int>> our_udp,
                          std::span<const std::vector<std::int32_t>> button_states) {
  connection_.Start(std::move(our_udp));
  button_states_ = button_states;
  const Timestamp now = Timestamp::Now();
  for (std::size_t b = 0; b < catalog_->buttons().size() && b < button_states.size(); ++b) {
    connection_.Pack(catalog_->button_sender(static_cast<int>(b)), catalog_->types().button_states,
                     now, EncodeButtonStates(button_states[b]));
  }
}

bool ServerSession::OnTcpBytes(std::span<const std::uint8_t> bytes) {
  const bool ok = connection_.OnTcpBytes(bytes, [this](const ReceivedMessage& m) { Handle(m); });
  const auto& c = connection_.counters();
  if (c.unknown_id > last_unknown_id_count_) {
    dropped_messages_ += c.unknown_id - last_unknown_id_count_;
    Log("dropped " + std::to_string(c.unknown_id - last_unknown_id_count_) +
        " message(s) with undescribed sender or type ids");
    last_unknown_id_count_ = c.unknown_id;
  }
  return ok;  // false: the owner closes the connection and logs why (error()), once
}

void ServerSession::OnDatagram(std::span<const std::uint8_t> datagram) {
  const auto before = connection_.counters().bad_datagram;
  connection_.OnDatagram(datagram, [this](const ReceivedMessage& m) { Handle(m); });
  if (connection_.counters().bad_datagram != before) {
    ++dropped_messages_;
    Log("dropped a malformed UDP datagram");
  }
}

void ServerSession::Handle(const ReceivedMessage& m) {
  const TypeIds& t = catalog_->types();
  const std::string type(m.type);
  if (m.type == kPingType) {
    const auto sender = catalog_->names()->FindSender(m.sender);
    const bool served = sender && catalog_->Serves(m.sender);
    if (served && !m.via_udp) {
      // The client uses this device (Uses()), whether or not there is room for the pong. Only a
      // ping on TCP counts (every VRPN peer pings there), as only TCP descriptions do: a datagram
      // must not narrow what a client that pinged from no device gets.
      if (used_.size() <= static_cast<std::size_t>(*sender)) used_.resize(*sender + 1, false);
      used_[*sender] = true;
      uses_any_device_ = true;
    }
    if (!RoomForReply(m)) return;
    // Pong only for served names: the missing pong is the only hint a client gets for a misspelt
    // device name (the reference behaves the same).
    if (served) {
      const Timestamp now = Timestamp::Now();
      // A button answers a ping from its name with its states (vrpn_Button_Filter does): a button
      // remote opened on a connection that is already up learns them only so.
      for (std::size_t b = 0; b < catalog_->buttons().size() && b < button_states_.size(); ++b) {
        if (catalog_->buttons()[b].name == m.sender) {
          connection_.Pack(catalog_->button_sender(static_cast<int>(b)), t.button_states, now,
                           EncodeButtonStates(button_states_[b]));
        }
      }
      connection_.Pack(*sender, t.pong, now, {});
      ++pings_answered_;
    } else {
      Log("ping for unserved device '" + std::string(m.sender) + "': no pong");
    }
    return;
  }
  if (m.type == kTextType) {
    if (auto text = DecodeText(m.payload)) {
      Log("client says (" + std::string(m.sender) + "): " + text->text);
    } else {
      ++dropped_messages_;
      Log("dropped malformed text message");
    }
    return;
  }
  const bool request = m.type == kRequestToRoomType || m.type == kRequestUnitToSensorType ||
                       m.type == kRequestWorkspaceType;
  if (request) {
    // The payload (empty from the reference client) is not looked at, as by the reference's
    // handlers: a client that sends one still gets its answer.
    const auto tracker = catalog_->FindTracker(m.sender);
    if (!tracker) {
      ++dropped_messages_;
      Log("dropped " + type + " for '" + std::string(m.sender) + "'");
      return;
    }
    if (!RoomForReply(m)) return;
    const TrackerSpec& spec = catalog_->trackers()[*tracker];
    const std::int32_t sender = catalog_->tracker_sender(*tracker);
    const Timestamp now = Timestamp::Now();
    if (m.type == kRequestToRoomType) {
      connection_.Pack(sender, t.to_room, now, EncodeToRoom(spec.room_from_tracker));
    } else if (m.type == kRequestUnitToSensorType) {
      for (int s = 0; s < spec.num_sensors; ++s) {
        UnitToSensor u;
        u.sensor = s;
        if (!spec.sensor_from_unit.empty()) u.sensor_from_unit = spec.sensor_from_unit[s];
        connection_.Pack(sender, t.unit_to_sensor, now, EncodeUnitToSensor(u));
      }
    } else {
      connection_.Pack(sender, t.workspace, now, EncodeWorkspace(spec.workspace));
    }
    return;
  }
  if (m.type == kSetUpdateRateType || m.type == kResetOriginType) {
    Log("ignored " + type + " from '" + std::string(m.sender) +
        "' (clients cannot change the device)");
    return;
  }
  ++dropped_messages_;
  Log("dropped unhandled message type '" + type + "' (" + std::to_string(m.payload.size()) +
      " bytes)");
}

bool ServerSession::RoomForReply(const ReceivedMessage& m) {
  const std::size_t waiting = connection_.tcp_output().size();
  if (waiting <= max_output_bytes_) return true;
  ++dropped_messages_;
  Log("not reading its replies (" + std::to_string(waiting) + " bytes waiting): dropped " +
      std::string(m.type));
  return false;
}

void ServerSession::Log(const std::string& line) {
  if (!log_) return;
  ++log_lines_;
  if (log_lines_ <= kMaxLogLines) {
    log_(peer_label_ + ": " + PrintableForLog(line));
  } else if (log_lines_ == kMaxLogLines + 1) {
    log_(peer_label_ + ": further messages about this client suppressed");
  }
}

}  // namespace trackcal::vrpn
