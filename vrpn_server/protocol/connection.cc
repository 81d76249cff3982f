#include "vrpn_server/protocol/connection.h"

#include <stdexcept>

#include "vrpn_server/protocol/payloads.h"

namespace trackcal::vrpn {
namespace {

std::int32_t AddName(std::vector<std::string>* names, std::string_view name) {
  for (std::size_t i = 0; i < names->size(); ++i) {
    if ((*names)[i] == name) return static_cast<std::int32_t>(i);
  }
  EncodeDescription(name);  // validates (throws for an invalid name)
  names->emplace_back(name);
  return static_cast<std::int32_t>(names->size() - 1);
}

std::optional<std::int32_t> FindName(const std::vector<std::string>& names, std::string_view name) {
  for (std::size_t i = 0; i < names.size(); ++i) {
    if (names[i] == name) return static_cast<std::int32_t>(i);
  }
  return std::nullopt;
}

}  // namespace

std::int32_t NameRegistry::AddSender(std::string_view name) { return AddName(&senders_, name); }
std::int32_t NameRegistry::AddType(std::string_view name) { return AddName(&types_, name); }
std::optional<std::int32_t> NameRegistry::FindSender(std::string_view name) const {
  return FindName(senders_, name);
}
std::optional<std::int32_t> NameRegistry::FindType(std::string_view name) const {
  return FindName(types_, name);
}

bool PeerNameTable::Set(std::int32_t id, std::string name) {
  auto it = names_.find(id);
  if (it != names_.end()) {
    it->second = std::move(name);
    ++version_;
    return true;
  }
  if (names_.size() >= kMaxEntries) return false;
  names_.emplace(id, std::move(name));
  ++version_;
  return true;
}

bool PeerNameTable::Contains(std::string_view name) const {
  for (const auto& [id, n] : names_) {
    if (n == name) return true;
  }
  return false;
}

const std::string* PeerNameTable::Find(std::int32_t id) const {
  auto it = names_.find(id);
  return it == names_.end() ? nullptr : &it->second;
}

Connection::Connection(std::shared_ptr<const NameRegistry> local_names, Options options)
    : local_names_(std::move(local_names)),
      options_(options),
      parser_(MessageStreamParser::Options{.expect_cookie = true,
                                           .max_message_length = options.max_message_length}) {
  if (!local_names_) throw std::invalid_argument("Connection: local_names is null");
  if (!options_.Check()) throw std::invalid_argument("Connection::Options.max_message_length: below 24");
}

void Connection::Start(std::optional<std::pair<std::string, int>> our_udp) {
  const auto cookie = MakeCookie('0');
  tcp_output_.insert(tcp_output_.end(), cookie.begin(), cookie.end());
  const Timestamp now = Timestamp::Now();
  if (our_udp) {
    Pack(our_udp->second, kUdpDescription, now, EncodeUdpDescription(our_udp->first));
  }
  const auto& senders = local_names_->senders();
  for (std::size_t i = 0; i < senders.size(); ++i) {
    Pack(static_cast<std::int32_t>(i), kSenderDescription, now, EncodeDescription(senders[i]));
  }
  const auto& types = local_names_->types();
  for (std::size_t i = 0; i < types.size(); ++i) {
    Pack(static_cast<std::int32_t>(i), kTypeDescription, now, EncodeDescription(types[i]));
  }
}

bool Connection::OnTcpBytes(std::span<const std::uint8_t> bytes, const Handler& handler) {
  const auto status =
      parser_.Feed(bytes, [&](const Message& m) { Dispatch(m, /*via_udp=*/false, handler); });
  return status == MessageStreamParser::Status::kOk;
}

void Connection::OnDatagram(std::span<const std::uint8_t> datagram, const Handler& handler) {
  // Collect first so a datagram broken halfway is dropped as a whole.
  struct Held {
    MessageHeader header;
    std::span<const std::uint8_t> payload;
  };
  std::vector<Held> held;
  const bool ok = ParseDatagram(datagram, options_.max_message_length, [&](const Message& m) {
    held.push_back({m.header, m.payload});
  });
  if (!ok) {
    ++counters_.bad_datagram;
    return;
  }
  for (const auto& h : held) Dispatch(Message{h.header, h.payload}, /*via_udp=*/true, handler);
}

void Connection::Dispatch(const Message& m, bool via_udp, const Handler& handler) {
  const std::int32_t type = m.header.type;
  if (type < 0) {
    switch (type) {
      case kSenderDescription:
      case kTypeDescription: {
        // Names travel reliably (on TCP) from every VRPN peer. A UDP port takes datagrams from
        // anyone who finds it: a description arriving there would let a stranger rename the
        // peer's ids and so redirect or cut off its stream.
        if (via_udp) {
          ++counters_.bad_description;
          return;
        }
        auto name = DecodeDescription(m.payload);
        if (!name) {
          ++counters_.bad_description;
          return;
        }
        PeerNameTable& table = type == kSenderDescription ? peer_senders_ : peer_types_;
        if (!table.Set(m.header.sender, std::move(*name))) ++counters_.bad_description;
        return;
      }
      case kUdpDescription: {
        auto host = DecodeUdpDescription(m.payload);
        if (!host || m.header.sender <= 0 || m.header.sender > 65535 || via_udp) {
          ++counters_.bad_description;
          return;
        }
        peer_udp_ = std::make_pair(*host, static_cast<int>(m.header.sender));
        return;
      }
      default:
        ++counters_.unknown_system;  // log descriptions and anything else: ignored
        return;
    }
  }
  const std::string* type_name = peer_types_.Find(type);
  const std::string* sender_name = peer_senders_.Find(m.header.sender);
  if (type_name == nullptr || sender_name == nullptr) {
    ++counters_.unknown_id;
    return;
  }
  ++counters_.delivered;
  handler(ReceivedMessage{*sender_name, *type_name, m.header.time, m.payload, via_udp});
}

void Connection::Pack(std::int32_t sender, std::int32_t type, Timestamp time,
                      std::span<const std::uint8_t> payload) {
  AppendMessage(&tcp_output_, time, sender, type, tcp_sequence_++, payload);
}

void Connection::PackEncoded(std::span<const std::uint8_t> message) {
  const std::size_t at = tcp_output_.size();
  tcp_output_.insert(tcp_output_.end(), message.begin(), message.end());
  StoreU32(tcp_sequence_++, tcp_output_.data() + at + kSequenceOffset);
}

void Connection::PackEncodedUdp(std::span<const std::uint8_t> message,
                                std::vector<std::uint8_t>* datagram) {
  const std::size_t at = datagram->size();
  datagram->insert(datagram->end(), message.begin(), message.end());
  StoreU32(udp_sequence_++, datagram->data() + at + kSequenceOffset);
}

}  // namespace trackcal::vrpn
