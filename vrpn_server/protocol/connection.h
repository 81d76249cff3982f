// Sans-IO VRPN connection endpoint: what both sides of a connection do, without sockets.
//
// Each peer numbers its own senders (device names) and message types from 0 and describes the
// mapping before using an id; the receiver translates by name. A Connection owns the local
// numbering (a NameRegistry shared by all connections of a process), learns the peer's numbering
// from its descriptions (accepted at any time), and hands every message to the owner with names
// resolved. Outgoing bytes accumulate in tcp_output() for the owner to write.

#pragma once

#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <unordered_map>
#include <vector>

#include "vrpn_server/protocol/stream_parser.h"
#include "vrpn_server/protocol/wire.h"

namespace trackcal::vrpn {

// Local name -> id tables for senders and types (ids are vector indices). Not thread-safe: build
// it before connections start, then share it read-only.
class NameRegistry {
 public:
  // Returns the id of name, registering it if new. Throws std::invalid_argument for invalid names.
  std::int32_t AddSender(std::string_view name);
  std::int32_t AddType(std::string_view name);
  std::optional<std::int32_t> FindSender(std::string_view name) const;
  std::optional<std::int32_t> FindType(std::string_view name) const;
  const std::vector<std::string>& senders() const { return senders_; }
  const std::vector<std::string>& types() const { return types_; }

 private:
  std::vector<std::string> senders_;
  std::vector<std::string> types_;
};

// The peer's id -> name tables, learnt from its descriptions. Bounded so a hostile peer cannot grow
// them without limit.
class PeerNameTable {
 public:
  static constexpr std::size_t kMaxEntries = 4096;
  // False when the table is full (the description is dropped).
  bool Set(std::int32_t id, std::string name);
  const std::string* Find(std::int32_t id) const;
  // True when some id carries this name.
  bool Contains(std::string_view name) const;
  std::size_t size() const { return names_.size(); }
  // Changes with every Set (lets owners cache what they derive from the table).
  std::uint64_t version() const { return version_; }

 private:
  std::unordered_map<std::int32_t, std::string> names_;
  std::uint64_t version_ = 0;
};

// A message with the peer's ids resolved to names.
struct ReceivedMessage {
  std::string_view sender;  // device name, e.g. "Tracker0"
  std::string_view type;    // type name, e.g. "vrpn_Base ping_message"
  Timestamp time;
  std::span<const std::uint8_t> payload;
  bool via_udp = false;
};

class Connection {
 public:
  struct Options {
    // Largest accepted message (header length field); larger closes this connection.
    std::uint32_t max_message_length = kDefaultMaxMessageLength;
    bool Check() const { return max_message_length >= kHeaderSize; }
  };

  // What happened to a message the owner did not get (for logging and tests).
  struct Counters {
    std::uint64_t delivered = 0;
    std::uint64_t unknown_id = 0;         // sender or type never described
    std::uint64_t bad_description = 0;    // malformed, or arrived over UDP (ignored)
    std::uint64_t unknown_system = 0;     // system type we do not handle
    std::uint64_t bad_datagram = 0;       // UDP datagram with a broken message
  };

  using Handler = std::function<void(const ReceivedMessage&)>;

  Connection(std::shared_ptr<const NameRegistry> local_names, Options options);

  // Queues our cookie, then (lob connections only) our UDP description, then descriptions of every
  // local sender and type.
  void Start(std::optional<std::pair<std::string, int>> our_udp = std::nullopt);

  // Feeds received TCP bytes; calls handler for every user message. Returns false when the
  // connection must be closed (bad cookie, malformed or oversized length): see error().
  bool OnTcpBytes(std::span<const std::uint8_t> bytes, const Handler& handler);
  // Feeds one received UDP datagram (whole messages, no cookie); a broken datagram is dropped.
  void OnDatagram(std::span<const std::uint8_t> datagram, const Handler& handler);

  // Appends one message to the TCP output with the next TCP sequence number.
  void Pack(std::int32_t sender, std::int32_t type, Timestamp time,
            std::span<const std::uint8_t> payload);
  // Appends an already encoded message (header + padded payload) and stamps our sequence number.
  void PackEncoded(std::span<const std::uint8_t> message);
  // Stamps the next UDP sequence number into an encoded message and appends it to *datagram.
  void PackEncodedUdp(std::span<const std::uint8_t> message, std::vector<std::uint8_t>* datagram);

  std::vector<std::uint8_t>& tcp_output() { return tcp_output_; }
  bool handshake_done() const { return parser_.cookie_received(); }
  // TCP bytes received of a message whose rest has not arrived yet, and whole TCP messages
  // received so far: together they tell a peer that stopped halfway through a message.
  std::size_t incomplete_tcp_bytes() const { return parser_.buffered(); }
  std::uint64_t tcp_messages_received() const { return parser_.messages(); }
  // Host and port from the peer's UDP description, if it sent one.
  const std::optional<std::pair<std::string, int>>& peer_udp() const { return peer_udp_; }
  const NameRegistry& local_names() const { return *local_names_; }
  const PeerNameTable& peer_senders() const { return peer_senders_; }
  const PeerNameTable& peer_types() const { return peer_types_; }
  const Counters& counters() const { return counters_; }
  std::string error() const { return parser_.ErrorText(); }

 private:
  void Dispatch(const Message& m, bool via_udp, const Handler& handler);

  std::shared_ptr<const NameRegistry> local_names_;
  Options options_;
  MessageStreamParser parser_;
  PeerNameTable peer_senders_;
  PeerNameTable peer_types_;
  std::optional<std::pair<std::string, int>> peer_udp_;
  std::vector<std::uint8_t> tcp_output_;
  std::uint32_t tcp_sequence_ = 0;
  std::uint32_t udp_sequence_ = 0;
  Counters counters_;
};

}  // namespace trackcal::vrpn
