// A pseudo-terminal that looks like a serial port to a driver: the slave is put in raw mode at once
// and kept open by the emulator (FASTRAK.md section 11, pitfall 2: a fresh pty echoes, maps CR to
// LF and eats 0x11/0x13 as flow control until someone configures it; and a master whose slave has
// no open fd reads EIO).

#pragma once

#include <filesystem>
#include <string>

namespace trackcal::emulator {

class PseudoTerminal {
 public:
  // Opens a master/slave pair; the master is non-blocking. Throws std::runtime_error.
  PseudoTerminal();
  ~PseudoTerminal();
  PseudoTerminal(const PseudoTerminal&) = delete;
  PseudoTerminal& operator=(const PseudoTerminal&) = delete;

  int master_fd() const { return master_fd_; }
  // "/dev/pts/N".
  const std::string& slave_path() const { return slave_path_; }

 private:
  int master_fd_ = -1;
  int slave_fd_ = -1;
  std::string slave_path_;
};

// Points the symbolic link `link` at `target`, atomically (a new link renamed over the old one), so
// a driver never sees the link missing. Refuses (std::runtime_error) to replace anything that is
// not a symbolic link.
void ReplaceSymlink(const std::string& target, const std::filesystem::path& link);

// Removes `link` if it is a symbolic link to `target` (so a link re-pointed by someone else stays).
void RemoveSymlinkIfTarget(const std::string& target, const std::filesystem::path& link);

}  // namespace trackcal::emulator
