#include "vrpn_server/net/socket_compat.h"

#include <cstring>
#include <mutex>
#include <stdexcept>

#ifndef _WIN32
#include <fcntl.h>
#include <unistd.h>

#include <cerrno>
#endif

namespace trackcal::vrpn {

void UniqueSocket::Reset(NativeSocket s) {
  if (s_ != kNoSocket) {
#ifdef _WIN32
    ::closesocket(s_);
#else
    ::close(s_);
#endif
  }
  s_ = s;
}

void InitSockets() {
#ifdef _WIN32
  static std::once_flag once;
  static int rc = 0;
  std::call_once(once, [] {
    WSADATA data;
    rc = ::WSAStartup(MAKEWORD(2, 2), &data);
  });
  if (rc != 0) throw std::runtime_error("WSAStartup failed: " + SocketErrorText(rc));
#endif
}

#ifdef _WIN32
namespace {
bool SetNonBlocking(NativeSocket s) {
  u_long one = 1;
  return ::ioctlsocket(s, FIONBIO, &one) == 0;
}
}  // namespace
#endif

NativeSocket OpenSocket(int type, bool nonblocking) {
#ifdef _WIN32
  // Windows sockets are not inherited unless asked (WSA_FLAG_NO_HANDLE_INHERIT).
  NativeSocket s = ::WSASocketW(AF_INET, type, 0, nullptr, 0, WSA_FLAG_NO_HANDLE_INHERIT);
  if (s != kNoSocket && nonblocking && !SetNonBlocking(s)) {
    ::closesocket(s);
    return kNoSocket;
  }
  return s;
#else
  return ::socket(AF_INET, type | SOCK_CLOEXEC | (nonblocking ? SOCK_NONBLOCK : 0), 0);
#endif
}

NativeSocket AcceptSocket(NativeSocket listener, bool nonblocking) {
#ifdef _WIN32
  NativeSocket s = ::accept(listener, nullptr, nullptr);
  if (s != kNoSocket && nonblocking && !SetNonBlocking(s)) {
    ::closesocket(s);
    return kNoSocket;
  }
  return s;
#else
  return ::accept4(listener, nullptr, nullptr, SOCK_CLOEXEC | (nonblocking ? SOCK_NONBLOCK : 0));
#endif
}

void SetNoDelay(NativeSocket s) {
  int one = 1;
  ::setsockopt(s, IPPROTO_TCP, TCP_NODELAY, reinterpret_cast<const char*>(&one), sizeof(one));
}

int LastSocketError() {
#ifdef _WIN32
  return ::WSAGetLastError();
#else
  return errno;
#endif
}

bool IsWouldBlock(int err) {
#ifdef _WIN32
  return err == WSAEWOULDBLOCK || err == WSAEINTR;
#else
  return err == EAGAIN || err == EWOULDBLOCK || err == EINTR;
#endif
}

bool IsConnectInProgress(int err) {
#ifdef _WIN32
  return err == WSAEWOULDBLOCK || err == WSAEINPROGRESS;
#else
  return err == EINPROGRESS;
#endif
}

int PendingSocketError(NativeSocket s) {
  int err = 0;
  socklen_t len = sizeof(err);
  if (::getsockopt(s, SOL_SOCKET, SO_ERROR, reinterpret_cast<char*>(&err), &len) != 0) {
    return LastSocketError();
  }
  return err;
}

std::string SocketErrorText(int err) {
#ifdef _WIN32
  char buf[256] = {};
  ::FormatMessageA(FORMAT_MESSAGE_FROM_SYSTEM | FORMAT_MESSAGE_IGNORE_INSERTS, nullptr,
                   static_cast<DWORD>(err), 0, buf, sizeof(buf), nullptr);
  std::string text(buf);
  while (!text.empty() && (text.back() == '\n' || text.back() == '\r' || text.back() == ' ')) {
    text.pop_back();
  }
  return text.empty() ? "Winsock error " + std::to_string(err) : text;
#else
  return std::strerror(err);
#endif
}

int PollSockets(PollFd* fds, std::size_t count, int timeout_ms) {
#ifdef _WIN32
  if (count == 0) {
    ::Sleep(static_cast<DWORD>(timeout_ms < 0 ? 0 : timeout_ms));  // WSAPoll rejects no sockets
    return 0;
  }
  return ::WSAPoll(fds, static_cast<ULONG>(count), timeout_ms);
#else
  return ::poll(fds, static_cast<nfds_t>(count), timeout_ms);
#endif
}

long SendSocket(NativeSocket s, const void* data, std::size_t size) {
#ifdef _WIN32
  return ::send(s, static_cast<const char*>(data), static_cast<int>(size), 0);
#else
  return ::send(s, data, size, MSG_NOSIGNAL | MSG_DONTWAIT);
#endif
}

long ReceiveSocket(NativeSocket s, void* data, std::size_t size) {
#ifdef _WIN32
  return ::recv(s, static_cast<char*>(data), static_cast<int>(size), 0);
#else
  return ::recv(s, data, size, MSG_DONTWAIT);
#endif
}

}  // namespace trackcal::vrpn
