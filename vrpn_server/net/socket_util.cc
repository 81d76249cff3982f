#include "vrpn_server/net/socket_util.h"

#ifndef _WIN32
#include <netinet/tcp.h>
#include <unistd.h>
#endif

#include <algorithm>
#include <charconv>
#include <cmath>
#include <cstring>
#include <stdexcept>

namespace trackcal::vrpn {

#ifndef _WIN32
UniqueFd& UniqueFd::operator=(UniqueFd&& o) noexcept {
  if (this != &o) Reset(o.Release());
  return *this;
}

void UniqueFd::Reset(int fd) {
  if (fd_ >= 0) ::close(fd_);
  fd_ = fd;
}

bool EnableDeadPeerDetection(int fd, double timeout_s) {
  const int on = 1;
  const int idle_s = std::max(1, static_cast<int>(std::lround(timeout_s / 2.0)));
  const int interval_s = std::max(1, static_cast<int>(std::lround(timeout_s / 6.0)));
  const int probes = 3;
  const unsigned int user_timeout_ms = static_cast<unsigned int>(std::lround(timeout_s * 1000.0));
  return ::setsockopt(fd, SOL_SOCKET, SO_KEEPALIVE, &on, sizeof(on)) == 0 &&
         ::setsockopt(fd, IPPROTO_TCP, TCP_KEEPIDLE, &idle_s, sizeof(idle_s)) == 0 &&
         ::setsockopt(fd, IPPROTO_TCP, TCP_KEEPINTVL, &interval_s, sizeof(interval_s)) == 0 &&
         ::setsockopt(fd, IPPROTO_TCP, TCP_KEEPCNT, &probes, sizeof(probes)) == 0 &&
         ::setsockopt(fd, IPPROTO_TCP, TCP_USER_TIMEOUT, &user_timeout_ms,
                      sizeof(user_timeout_ms)) == 0;
}
#endif

std::optional<in_addr> ParseIpv4(std::string_view text) {
  if (text.size() > 15) return std::nullopt;
  const std::string s(text);
  in_addr a{};
  if (::inet_pton(AF_INET, s.c_str(), &a) != 1) return std::nullopt;
  return a;
}

std::string FormatIpv4(in_addr address) {
  char buf[INET_ADDRSTRLEN] = {};
  ::inet_ntop(AF_INET, &address, buf, sizeof(buf));
  return buf;
}

std::string FormatEndpoint(const sockaddr_in& address) {
  return FormatIpv4(address.sin_addr) + ":" + std::to_string(ntohs(address.sin_port));
}

sockaddr_in MakeSockaddr(in_addr address, int port) {
  sockaddr_in sa{};
  sa.sin_family = AF_INET;
  sa.sin_addr = address;
  sa.sin_port = htons(static_cast<std::uint16_t>(port));
  return sa;
}

AllowList AllowList::Parse(const std::vector<std::string>& cidrs) {
  AllowList list;
  for (const std::string& entry : cidrs) {
    const auto slash = entry.find('/');
    const auto address = ParseIpv4(std::string_view(entry).substr(0, slash));
    int length = 32;
    bool ok = address.has_value();
    if (ok && slash != std::string::npos) {
      const char* first = entry.data() + slash + 1;
      const char* last = entry.data() + entry.size();
      auto [ptr, ec] = std::from_chars(first, last, length);
      ok = ec == std::errc() && ptr == last && first != last && length >= 0 && length <= 32;
    }
    if (!ok) {
      throw std::invalid_argument("allow-list entry '" + entry +
                                  "': expected an IPv4 network like 192.168.1.0/24");
    }
    Network n;
    n.mask = length == 0 ? 0 : ~std::uint32_t{0} << (32 - length);
    n.base = ntohl(address->s_addr) & n.mask;
    list.networks_.push_back(n);
  }
  return list;
}

bool AllowList::Allows(in_addr address) const {
  if (networks_.empty()) return true;
  const std::uint32_t a = ntohl(address.s_addr);
  for (const Network& n : networks_) {
    if ((a & n.mask) == n.base) return true;
  }
  return false;
}

std::string ErrnoText(int err) { return std::strerror(err); }

}  // namespace trackcal::vrpn
