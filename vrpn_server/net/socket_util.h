// Small socket helpers shared by the VRPN server and client: an owning fd (POSIX), IPv4 address
// parsing/formatting, and a CIDR allow-list for client networks. The address helpers also build on
// Windows (the Unity plugin, socket_compat.h).

#pragma once

#include "vrpn_server/net/socket_compat.h"

#include <cstdint>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

namespace trackcal::vrpn {

#ifndef _WIN32
// Owns a file descriptor; closes it on destruction.
class UniqueFd {
 public:
  UniqueFd() = default;
  explicit UniqueFd(int fd) : fd_(fd) {}
  UniqueFd(UniqueFd&& o) noexcept : fd_(o.Release()) {}
  UniqueFd& operator=(UniqueFd&& o) noexcept;
  UniqueFd(const UniqueFd&) = delete;
  UniqueFd& operator=(const UniqueFd&) = delete;
  ~UniqueFd() { Reset(); }
  int get() const { return fd_; }
  bool valid() const { return fd_ >= 0; }
  int Release() {
    const int fd = fd_;
    fd_ = -1;
    return fd;
  }
  void Reset(int fd = -1);

 private:
  int fd_ = -1;
};

// Makes the kernel find a peer that vanished without closing (its host crashed, lost power or
// network) within about `timeout_s`: keepalive probes after timeout_s / 2 of silence, three of
// them timeout_s / 6 apart, and data left unacknowledged for timeout_s. A live peer's kernel
// answers the probes, so an idle client is never dropped. The socket then reports an error
// (ETIMEDOUT) to poll/epoll. Returns false if the system refused an option.
bool EnableDeadPeerDetection(int fd, double timeout_s);
#endif

// Parses a dotted IPv4 literal (no name resolution). Address in network byte order.
std::optional<in_addr> ParseIpv4(std::string_view text);
std::string FormatIpv4(in_addr address);
std::string FormatEndpoint(const sockaddr_in& address);  // "a.b.c.d:port"
sockaddr_in MakeSockaddr(in_addr address, int port);

// Allowed client networks. Empty = everyone (the VRPN default).
class AllowList {
 public:
  // Each entry "a.b.c.d/len" or "a.b.c.d" (= /32). Throws std::invalid_argument naming the entry.
  static AllowList Parse(const std::vector<std::string>& cidrs);
  bool Allows(in_addr address) const;
  bool empty() const { return networks_.empty(); }

 private:
  struct Network {
    std::uint32_t base = 0;  // host byte order, already masked
    std::uint32_t mask = 0;
  };
  std::vector<Network> networks_;
};

// errno text, for messages.
std::string ErrnoText(int err);

}  // namespace trackcal::vrpn
