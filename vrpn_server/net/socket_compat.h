// Sockets on POSIX and on Windows (Winsock 2) for the code the Unity plugin carries (the VRPN
// client and the wire protocol; docs/unity.md): the native handle, its owner, and the calls whose
// spelling differs. The server stays POSIX (epoll, ptys) and uses socket_util.h's UniqueFd.
#pragma once

#ifdef _WIN32
#ifndef WIN32_LEAN_AND_MEAN
#define WIN32_LEAN_AND_MEAN
#endif
#ifndef NOMINMAX
#define NOMINMAX
#endif
#include <winsock2.h>
#include <ws2tcpip.h>
#else
#include <arpa/inet.h>
#include <netdb.h>
#include <netinet/in.h>
#include <netinet/tcp.h>
#include <poll.h>
#include <sys/socket.h>
#endif

#include <cstddef>
#include <string>

namespace trackcal::vrpn {

#ifdef _WIN32
using NativeSocket = SOCKET;
inline constexpr NativeSocket kNoSocket = INVALID_SOCKET;
using PollFd = WSAPOLLFD;
#else
using NativeSocket = int;
inline constexpr NativeSocket kNoSocket = -1;
using PollFd = pollfd;
#endif

// Owns a socket; closes it on destruction.
class UniqueSocket {
 public:
  UniqueSocket() = default;
  explicit UniqueSocket(NativeSocket s) : s_(s) {}
  UniqueSocket(UniqueSocket&& o) noexcept : s_(o.Release()) {}
  UniqueSocket& operator=(UniqueSocket&& o) noexcept {
    if (this != &o) Reset(o.Release());
    return *this;
  }
  UniqueSocket(const UniqueSocket&) = delete;
  UniqueSocket& operator=(const UniqueSocket&) = delete;
  ~UniqueSocket() { Reset(); }
  NativeSocket get() const { return s_; }
  bool valid() const { return s_ != kNoSocket; }
  NativeSocket Release() {
    const NativeSocket s = s_;
    s_ = kNoSocket;
    return s;
  }
  void Reset(NativeSocket s = kNoSocket);

 private:
  NativeSocket s_ = kNoSocket;
};

// Starts Winsock once per process (nothing to do on POSIX). Throws std::runtime_error if it fails.
void InitSockets();

// An IPv4 socket of `type` (SOCK_STREAM, SOCK_DGRAM), not inherited by child processes,
// non-blocking if asked. kNoSocket on failure (LastSocketError() says why).
NativeSocket OpenSocket(int type, bool nonblocking);
// accept() on a listening socket; the new socket non-blocking if asked.
NativeSocket AcceptSocket(NativeSocket listener, bool nonblocking);
// TCP_NODELAY on.
void SetNoDelay(NativeSocket s);

// errno, or WSAGetLastError() on Windows.
int LastSocketError();
// A non-blocking call that would have blocked (or was interrupted): try again later.
bool IsWouldBlock(int err);
// A non-blocking connect() that is under way.
bool IsConnectInProgress(int err);
// The pending error of a socket (SO_ERROR), 0 if none.
int PendingSocketError(NativeSocket s);
std::string SocketErrorText(int err);

// poll() / WSAPoll(): the number of ready sockets, 0 on timeout, < 0 on error.
int PollSockets(PollFd* fds, std::size_t count, int timeout_ms);
// Non-blocking send without SIGPIPE; bytes sent or < 0.
long SendSocket(NativeSocket s, const void* data, std::size_t size);
// Non-blocking receive; bytes received, 0 at end of stream, < 0 on error.
long ReceiveSocket(NativeSocket s, void* data, std::size_t size);

}  // namespace trackcal::vrpn
