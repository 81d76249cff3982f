// One client endpoint of the server, without sockets: the cookie and descriptions sent at once,
// answers to pings and tracker requests, and the rules for what a client may send.
//
// Nothing a client sends changes anything beyond its own session: unknown or malformed messages are
// dropped with a (rate-limited) log line, state-changing requests (set_update_rate, Reset_Origin)
// are logged and ignored, and a length field out of range makes OnTcpBytes return false so the owner
// closes this connection only.

#pragma once

#include <cstdint>
#include <functional>
#include <limits>
#include <memory>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "vrpn_server/protocol/connection.h"
#include "vrpn_server/server/catalog.h"

namespace trackcal::vrpn {

using LogFunction = std::function<void(const std::string&)>;

class ServerSession {
 public:
  // Per-session cap on log lines about client misbehaviour; later ones are counted, not printed.
  static constexpr int kMaxLogLines = 20;

  // Replies (pongs, answers to requests) are not made while more than max_output_bytes wait in
  // connection().tcp_output(): a client that sends requests and does not read cannot make the
  // session build output without bound before its owner drops it.
  ServerSession(std::shared_ptr<const ServerCatalog> catalog, Connection::Options options,
                std::string peer_label, LogFunction log,
                std::size_t max_output_bytes = std::numeric_limits<std::size_t>::max());

  // Queues cookie, our UDP description (lob connections), all descriptions, and the current state
  // of every button device (as the reference does on a new connection). `button_states` (one
  // vector per catalog button) must outlive the session: a ping from a button's name is answered
  // with its states then current, as the reference does, so that a button remote opened on a
  // connection already up learns them.
  void Start(std::optional<std::pair<std::string, int>> our_udp,
             std::span<const std::vector<std::int32_t>> button_states);

  // Feeds received TCP bytes; replies are appended to connection().tcp_output(). False: close
  // (error() says why; the owner logs it).
  bool OnTcpBytes(std::span<const std::uint8_t> bytes);
  void OnDatagram(std::span<const std::uint8_t> datagram);

  Connection& connection() { return connection_; }
  const std::string& peer_label() const { return peer_label_; }
  std::uint64_t pings_answered() const { return pings_answered_; }
  // Whether the client uses the served device with our sender id `sender`: it pinged from that
  // name (on TCP). Every VRPN remote object (tracker, button, text receiver) pings from its device
  // name when it starts; descriptions cannot tell, as the reference library describes back every
  // name a server describes (capture 08: a client of Tracker0 alone describes the server's
  // Stylus0).
  bool Uses(std::int32_t sender) const {
    return sender >= 0 && static_cast<std::size_t>(sender) < used_.size() && used_[sender];
  }
  // The client pinged from at least one served device (before that, or for a client that never
  // pings, it gets every device's messages, as from the reference server).
  bool uses_any_device() const { return uses_any_device_; }
  std::uint64_t dropped_messages() const { return dropped_messages_; }
  std::string error() const { return connection_.error(); }

 private:
  void Handle(const ReceivedMessage& m);
  // False (and the message counted as dropped) when the client has left too many bytes unread.
  bool RoomForReply(const ReceivedMessage& m);
  void Log(const std::string& line);

  std::shared_ptr<const ServerCatalog> catalog_;
  Connection connection_;
  std::string peer_label_;
  LogFunction log_;
  std::size_t max_output_bytes_;
  int log_lines_ = 0;
  std::uint64_t pings_answered_ = 0;
  std::uint64_t dropped_messages_ = 0;
  std::uint64_t last_unknown_id_count_ = 0;
  std::span<const std::vector<std::int32_t>> button_states_;  // see Start()
  std::vector<bool> used_;  // indexed by our sender id, see Uses()
  bool uses_any_device_ = false;
};

}  // namespace trackcal::vrpn
