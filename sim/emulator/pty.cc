#include "sim/emulator/pty.h"

#include <fcntl.h>
#include <stdlib.h>
#include <termios.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>
#include <stdexcept>
#include <system_error>

namespace trackcal::emulator {
namespace {

[[noreturn]] void ThrowErrno(const std::string& what) {
  throw std::runtime_error(what + ": " + std::strerror(errno));
}

}  // namespace

PseudoTerminal::PseudoTerminal() {
  master_fd_ = posix_openpt(O_RDWR | O_NOCTTY | O_NONBLOCK | O_CLOEXEC);
  if (master_fd_ < 0) ThrowErrno("posix_openpt");
  if (grantpt(master_fd_) != 0 || unlockpt(master_fd_) != 0) {
    const int saved = errno;
    close(master_fd_);
    errno = saved;
    ThrowErrno("grantpt/unlockpt");
  }
  char name[256];
  if (ptsname_r(master_fd_, name, sizeof(name)) != 0) {
    const int saved = errno;
    close(master_fd_);
    errno = saved;
    ThrowErrno("ptsname_r");
  }
  slave_path_ = name;
  slave_fd_ = open(name, O_RDWR | O_NOCTTY | O_CLOEXEC);
  if (slave_fd_ < 0) {
    const int saved = errno;
    close(master_fd_);
    errno = saved;
    ThrowErrno("open " + slave_path_);
  }
  termios tio{};
  if (tcgetattr(slave_fd_, &tio) == 0) {
    cfmakeraw(&tio);
    tio.c_cflag |= CLOCAL | CREAD;
    tio.c_cc[VMIN] = 0;
    tio.c_cc[VTIME] = 0;
    cfsetispeed(&tio, B115200);
    cfsetospeed(&tio, B115200);
    if (tcsetattr(slave_fd_, TCSANOW, &tio) == 0) return;
  }
  const int saved = errno;
  close(slave_fd_);
  close(master_fd_);
  errno = saved;
  ThrowErrno("raw mode on " + slave_path_);
}

PseudoTerminal::~PseudoTerminal() {
  if (slave_fd_ >= 0) close(slave_fd_);
  if (master_fd_ >= 0) close(master_fd_);
}

void ReplaceSymlink(const std::string& target, const std::filesystem::path& link) {
  std::error_code ec;
  const auto status = std::filesystem::symlink_status(link, ec);
  if (!ec && std::filesystem::exists(status) && !std::filesystem::is_symlink(status)) {
    throw std::runtime_error(link.string() +
                             ": exists and is not a symbolic link; not replacing it");
  }
  std::filesystem::path tmp = link;
  tmp += ".tmp" + std::to_string(getpid());
  std::filesystem::remove(tmp, ec);
  if (symlink(target.c_str(), tmp.c_str()) != 0) ThrowErrno("symlink " + tmp.string());
  if (rename(tmp.c_str(), link.c_str()) != 0) {
    const int saved = errno;
    unlink(tmp.c_str());
    errno = saved;
    ThrowErrno("rename " + tmp.string() + " -> " + link.string());
  }
}

void RemoveSymlinkIfTarget(const std::string& target, const std::filesystem::path& link) {
  std::error_code ec;
  if (!std::filesystem::is_symlink(std::filesystem::symlink_status(link, ec))) return;
  if (std::filesystem::read_symlink(link, ec) == std::filesystem::path(target) && !ec) {
    std::filesystem::remove(link, ec);
  }
}

}  // namespace trackcal::emulator
