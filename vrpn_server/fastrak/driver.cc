#include "vrpn_server/fastrak/driver.h"

#include <fcntl.h>
#include <poll.h>
#include <pthread.h>
#include <sched.h>
#include <sys/file.h>
#include <sys/stat.h>
#include <termios.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <cerrno>
#include <cmath>
#include <cstring>
#include <limits>
#include <optional>
#include <sstream>
#include <stdexcept>

#include "core/printable_text.h"
#include "vrpn_server/config.h"

namespace trackcal::fastrak {
namespace {

using SteadyClock = std::chrono::steady_clock;
using SystemClock = std::chrono::system_clock;

// While the port cannot be opened, the same error reaches clients and the server's log at most
// this often (the first failure and the reopen are always reported).
constexpr std::chrono::seconds kOutageReminder{60};

// Waits are clamped to 1e9 s (32 years): longer ones ("*N" sleeps and timings are any finite
// N >= 0) would overflow the clock's 64-bit nanoseconds, or a deadline computed from now.
SteadyClock::duration Seconds(double s) {
  constexpr double kMaxWaitS = 1e9;
  return std::chrono::duration_cast<SteadyClock::duration>(
      std::chrono::duration<double>(std::min(s, kMaxWaitS)));
}

std::string FormatSeconds(double s) {
  std::ostringstream out;
  out.precision(3);
  out << s << " s";
  return out.str();
}

// Bytes a unit sent, for a text: printable ASCII as is, everything else (CR, LF, binary) as \xNN,
// at most kMaxQuoted bytes (then "..." and the total), in single quotes.
std::string QuoteBytes(std::string_view bytes) {
  constexpr size_t kMaxQuoted = 80;  // a status reply (55 bytes) and the start of another
  std::string out = "'" + Printable(bytes.substr(0, kMaxQuoted), PrintableFor::kDeviceBytes) + "'";
  if (bytes.size() > kMaxQuoted) out += "... (" + std::to_string(bytes.size()) + " bytes)";
  return out;
}

// True if `candidate` is a status reply in the layout of `unit_reply`, the reply the unit gave to
// the reset's `S` (accepted on its first byte and final LF alone, as by the reference): the same
// length, '2', a station byte, 'S' (the Fastrak's status record type, which an IS-900's 54-byte
// reply shares; a reply to a query among the extra commands, such as "21H..." to `H1`, has its
// command's letter there), the same final CR LF and no LF before it (a window over the end of one
// reply and the start of the next). Only for a `unit_reply` that itself has 'S' at byte 2 and ends
// with CR LF: without a known layout nothing confirms but the Fastrak's.
bool InUnitStatusLayout(std::string_view candidate, std::string_view unit_reply) {
  constexpr size_t kMinSize = 5;  // '2', station, 'S', CR, LF
  if (unit_reply.size() < kMinSize || unit_reply[0] != '2' || unit_reply[2] != 'S' ||
      !unit_reply.ends_with("\r\n")) {
    return false;
  }
  return candidate.size() == unit_reply.size() && candidate[0] == '2' && candidate[2] == 'S' &&
         candidate.ends_with("\r\n") && candidate.find('\n') == candidate.size() - 1;
}

// Thrown inside the driver thread to unwind to the main loop.
struct StopRequested {};
struct PortLost {
  std::string reason;
};

speed_t BaudConstant(int baud) {
  switch (baud) {
    case 300:
      return B300;
    case 1200:
      return B1200;
    case 2400:
      return B2400;
    case 4800:
      return B4800;
    case 9600:
      return B9600;
    case 19200:
      return B19200;
    case 38400:
      return B38400;
    case 57600:
      return B57600;
    case 115200:
      return B115200;
    default:
      throw std::invalid_argument("unsupported baud rate " + std::to_string(baud));
  }
}

// open() + termios exactly as the reference (FASTRAK.md section 2): 8N1, no flow control, raw,
// VMIN = VTIME = 0. Returns -1 and sets *error on failure.
int OpenSerialPort(const std::string& path, int baud, std::string* error) {
  const int fd = ::open(path.c_str(), O_RDWR | O_NOCTTY | O_NONBLOCK | O_CLOEXEC);
  if (fd < 0) {
    *error = std::strerror(errno);
    return -1;
  }
  // `path` may be a symbolic link that is removed or re-pointed while we open it (an unplugged
  // adapter, the emulator's disconnect). Resolving the link and opening its target are two steps:
  // if the old target's device number was meanwhile given to another device (pty numbers are
  // reused at once), we would stream someone else's records. Only keep the fd if the path still
  // names the device we opened.
  struct stat opened {}, named {};
  if (::fstat(fd, &opened) != 0 || ::stat(path.c_str(), &named) != 0 ||
      opened.st_rdev != named.st_rdev || opened.st_ino != named.st_ino) {
    *error = "the device behind the path changed while opening it";
    ::close(fd);
    return -1;
  }
  // One driver per device: an advisory lock on the device node (held until close) makes a second
  // trackcal driver that reaches the same port (a stale link to a reused pty number, two servers
  // configured with one port) fail and retry instead of sharing the byte stream and the commands.
  if (::flock(fd, LOCK_EX | LOCK_NB) != 0) {
    *error = errno == EWOULDBLOCK ? std::string("in use by another trackcal driver")
                                  : std::string("cannot lock (") + std::strerror(errno) + ")";
    ::close(fd);
    return -1;
  }
  termios tio{};
  if (::tcgetattr(fd, &tio) != 0) {
    *error = std::string("not a serial port (") + std::strerror(errno) + ")";
    ::close(fd);
    return -1;
  }
  tio.c_iflag = IGNBRK | IGNPAR;
  tio.c_oflag = 0;
  tio.c_lflag = 0;
  tio.c_cflag = CS8 | CREAD | CLOCAL;
  tio.c_cc[VMIN] = 0;
  tio.c_cc[VTIME] = 0;
  const speed_t speed = BaudConstant(baud);
  if (::cfsetispeed(&tio, speed) != 0 || ::cfsetospeed(&tio, speed) != 0 ||
      ::tcsetattr(fd, TCSANOW, &tio) != 0) {
    *error = std::string("cannot configure the line (") + std::strerror(errno) + ")";
    ::close(fd);
    return -1;
  }
  ::tcflush(fd, TCIFLUSH);
  return fd;
}

}  // namespace

// ---------------------------------------------------------------------------------------------
// Options

FastrakTimings FastrakTimings::Fast() {
  FastrakTimings t;
  t.settle_after_preamble_s = 0.05;
  t.reinitialise_wait_s = 0.1;
  t.settle_after_flush_s = 0.05;
  // Ends at the reply's LF; only a missing or corrupt reply waits it out. 2 s so that a loaded
  // host does not turn a slow answer into a failed reset.
  t.status_timeout_s = 2.0;
  t.command_gap_s = 0.005;
  t.filter_settle_s = 0.02;
  t.extras_settle_s = 0.05;
  // Ends at the second record (about 17 ms with the emulator), so the length only matters when
  // the device is not streaming; 1 s lets a resume succeed on a heavily loaded host.
  t.resume_probe_s = 1.0;
  // Status polls after a loss: the same as the reference timings except a shorter window, so
  // tests of the full reset's escalation do not wait long (a stall of the emulator ends within it).
  t.restart_window_s = 3.0;
  t.restart_settle_s = 0.02;
  return t;
}

double FastrakTimings::StatusTimeout(int baud) const {
  constexpr double kReplyBits = 55.0 * 10.0;  // 55 bytes, 10 bits each on the line
  return std::max(status_timeout_s, 2.0 * kReplyBits / std::max(baud, 1));
}

double FastrakTimings::RestartSettle(int baud) const {
  constexpr double kRecordBits = 34.0 * 10.0;  // the longest record of ours, 10 bits a byte
  return std::max(restart_settle_s, 2.0 * kRecordBits / std::max(baud, 1));
}

double FastrakTimings::RestartPoll(int baud) const {
  constexpr double kReplyBits = 55.0 * 10.0;
  return std::max(restart_poll_s, RestartSettle(baud) + 2.0 * kReplyBits / std::max(baud, 1));
}

void FastrakTimings::Check() const {
  const std::pair<const char*, double> fields[] = {
      {"settle_after_preamble_s", settle_after_preamble_s},
      {"reinitialise_wait_s", reinitialise_wait_s},
      {"settle_after_flush_s", settle_after_flush_s},
      {"status_timeout_s", status_timeout_s},
      {"command_gap_s", command_gap_s},
      {"filter_settle_s", filter_settle_s},
      {"extras_settle_s", extras_settle_s},
      {"watchdog_s", watchdog_s},
      {"resume_probe_s", resume_probe_s},
      {"restart_window_s", restart_window_s},
      {"restart_poll_s", restart_poll_s},
      {"restart_settle_s", restart_settle_s},
      {"reopen_backoff_min_s", reopen_backoff_min_s},
      {"reopen_backoff_max_s", reopen_backoff_max_s},
      {"message_interval_s", message_interval_s},
  };
  for (const auto& [name, value] : fields) {
    if (!std::isfinite(value) || value < 0.0) {
      throw std::invalid_argument(std::string("FastrakTimings.") + name + " must be finite and >= 0");
    }
  }
  if (status_timeout_s <= 0.0) throw std::invalid_argument("FastrakTimings.status_timeout_s must be > 0");
  if (watchdog_s <= 0.0) throw std::invalid_argument("FastrakTimings.watchdog_s must be > 0");
  if (restart_window_s > 0.0 && restart_poll_s <= restart_settle_s) {
    throw std::invalid_argument("FastrakTimings.restart_poll_s must be > restart_settle_s");
  }
  if (reopen_backoff_min_s <= 0.0) {
    throw std::invalid_argument("FastrakTimings.reopen_backoff_min_s must be > 0 (no busy reopen loop)");
  }
  if (reopen_backoff_max_s < reopen_backoff_min_s) {
    throw std::invalid_argument("FastrakTimings.reopen_backoff_max_s must be >= reopen_backoff_min_s");
  }
}

void FastrakOptions::Check() const {
  if (port.empty()) throw std::invalid_argument("FastrakOptions.port is empty");
  if (!vrpn::IsSupportedBaudRate(baud)) {
    throw std::invalid_argument("FastrakOptions.baud " + std::to_string(baud) +
                                " is not 300, 1200, 2400, 4800, 9600, 19200, 38400, 57600 or 115200");
  }
  if (realtime_priority < 0 || realtime_priority > 99) {
    throw std::invalid_argument("FastrakOptions.realtime_priority must be 0..99");
  }
  if (num_stations < 1 || num_stations > kMaxStations) {
    throw std::invalid_argument("FastrakOptions.num_stations must be 1..4");
  }
  for (int s : stylus_sensors) {
    if (s < 0 || s >= num_stations) {
      throw std::invalid_argument("FastrakOptions.stylus_sensors: sensor " + std::to_string(s) +
                                  " is not one of the configured stations");
    }
  }
  for (const std::string& cmd : extra_commands) {
    if (cmd.empty()) throw std::invalid_argument("FastrakOptions.extra_commands: empty command");
    if (cmd.front() == '*') {
      char* end = nullptr;
      const double s = std::strtod(cmd.c_str() + 1, &end);
      if (end == cmd.c_str() + 1 || *end != '\0' || !std::isfinite(s) || s < 0.0) {
        throw std::invalid_argument("FastrakOptions.extra_commands: '" + cmd +
                                    "' is not a valid '*N' sleep");
      }
    }
    if (cmd.find_first_of("\r\n") != std::string::npos) {
      throw std::invalid_argument("FastrakOptions.extra_commands: a command contains CR or LF");
    }
  }
  timings.Check();
}

Units FastrakOptions::EffectiveUnits() const {
  Units result = units;
  for (const std::string& cmd : extra_commands) {
    if (cmd == "u") result = Units::kCentimetres;
    if (cmd == "U") result = Units::kInches;
  }
  return result;
}

const char* DriverStateName(DriverState state) {
  switch (state) {
    case DriverState::kStopped:
      return "stopped";
    case DriverState::kOpening:
      return "opening";
    case DriverState::kResetting:
      return "resetting";
    case DriverState::kStreaming:
      return "streaming";
  }
  return "?";
}

// ---------------------------------------------------------------------------------------------
// Session: everything the thread owns.

class FastrakDriver::Session {
 public:
  explicit Session(FastrakDriver* driver)
      : driver_(driver),
        options_(driver->options_),
        timings_(options_.timings),
        units_(options_.EffectiveUnits()),
        parser_(StylusStations(options_), units_, options_.num_stations, options_.baud),
        limiter_(Seconds(timings_.message_interval_s)) {}

  ~Session() { ClosePort(); }

  void Run() {
    if (options_.realtime_priority > 0) {
      sched_param param{};
      param.sched_priority = options_.realtime_priority;
      const int rc = ::pthread_setschedparam(::pthread_self(), SCHED_FIFO, &param);
      if (rc != 0) {
        Emit(Severity::kWarning, "cannot use real-time priority " + std::to_string(options_.realtime_priority) +
                                     " (" + std::strerror(rc) + "); running at normal priority");
      }
    }
    if (units_ != options_.units) {
      Emit(Severity::kInfo, std::string("extra commands switch the tracker to ") + UnitsName(units_) +
                                "; positions are converted from " + UnitsName(units_));
    }
    for (const std::string& cmd : options_.extra_commands) {
      if (cmd.front() == 'O') {
        Emit(Severity::kWarning, "extra command '" + cmd +
                                     "' changes an output list; records that do not match 2,11[,16],0 "
                                     "are discarded");
      }
    }
    while (true) {
      try {
        if (fd_ < 0) OpenWithBackoff();
        // The probe (listening only) also runs between reset attempts: it finds a unit that came
        // back still streaming (a cable out and in). The short restart runs once per loss, not
        // again before each retried attempt, which itself asks for the status: its 6 s before
        // every attempt put a silent unit's ^Y (attempt 3) 40 s after its last record (the
        // reference: 16 s).
        bool streaming = configured_once_ && TryResume();
        if (!streaming && configured_once_ && after_loss_) streaming = QuickRestart();
        after_loss_ = false;
        if (!streaming) streaming = Reset();
        if (streaming) {
          Stream();
          // Watchdog: reopen the port like the reference (a USB adapter may have re-enumerated).
          ClosePort();
          after_loss_ = true;
        }
      } catch (const PortLost& lost) {
        Count(&DriverStats::port_losses);
        after_loss_ = true;
        // Lost again before a single record: the open back-off never applies to a port that opens
        // but hangs up at once, so back off here too (else a reopen loop as fast as the hang-ups).
        if (!records_since_open_) {
          loss_backoff_s_ = loss_backoff_s_ > 0.0
                                ? std::min(2.0 * loss_backoff_s_, timings_.reopen_backoff_max_s)
                                : timings_.reopen_backoff_min_s;
        }
        Emit(Severity::kError,
             "serial port " + options_.port + " lost (" + lost.reason + "); reopening" +
                 (loss_backoff_s_ > 0.0 ? " in " + FormatSeconds(loss_backoff_s_) : ""));
        ClosePort();
      } catch (const StopRequested&) {
        break;
      }
    }
    ClosePort();
  }

 private:
  static std::array<bool, kMaxStations> StylusStations(const FastrakOptions& options) {
    std::array<bool, kMaxStations> stylus{};
    for (int s : options.stylus_sensors) stylus[s] = true;
    return stylus;
  }

  void SetState(DriverState state) { driver_->state_.store(state); }

  void Count(uint64_t DriverStats::*field, uint64_t n = 1) {
    std::lock_guard<std::mutex> lock(driver_->stats_mutex_);
    driver_->stats_.*field += n;
  }

  void Deliver(const DriverMessage& m) {
    if (driver_->callbacks_.on_message) driver_->callbacks_.on_message(m.severity, m.text);
  }

  void Emit(Severity severity, std::string text) {
    text = "Fastrak " + options_.port + ": " + text;
    if (driver_->callbacks_.on_log) driver_->callbacks_.on_log(severity, text);
    if (auto m = limiter_.Submit({severity, std::move(text)}, SteadyClock::now())) {
      Deliver(*m);
    }
    UpdateSuppressedCount();
  }

  // For texts that repeat one already delivered: the caller's own log only.
  void LogOnly(Severity severity, const std::string& text) {
    if (driver_->callbacks_.on_log)
      driver_->callbacks_.on_log(severity, "Fastrak " + options_.port + ": " + text);
  }

  void PollLimiter() {
    if (auto m = limiter_.Poll(SteadyClock::now())) {
      Deliver(*m);
      UpdateSuppressedCount();  // the held text was counted as suppressed until now
    }
  }

  void UpdateSuppressedCount() {
    std::lock_guard<std::mutex> lock(driver_->stats_mutex_);
    driver_->stats_.messages_suppressed = limiter_.suppressed();
  }

  // Also drops partial input: a record is never assembled from bytes of two port openings.
  void ClosePort() {
    if (fd_ >= 0) ::close(fd_);
    fd_ = -1;
    parser_.Clear();
  }

  enum class WaitResult { kTimeout, kReadable };

  // Waits until `deadline`, or until the port has data if `want_data`. Always watches the port for
  // a hang-up (PortLost) and the stop pipe (StopRequested), and releases held messages on time.
  WaitResult Wait(SteadyClock::time_point deadline, bool want_data) {
    while (true) {
      if (driver_->stop_.load()) throw StopRequested{};
      PollLimiter();
      const SteadyClock::time_point now = SteadyClock::now();
      SteadyClock::time_point until = deadline;
      if (auto held = limiter_.NextDeadline()) until = std::min(until, std::max(*held, now));
      if (now >= deadline) return WaitResult::kTimeout;
      // Round up so we never wake just before the deadline and spin.
      const auto ms = std::chrono::ceil<std::chrono::milliseconds>(until - now).count();
      pollfd fds[2] = {{driver_->wake_pipe_[0], POLLIN, 0}, {fd_, static_cast<short>(want_data ? POLLIN : 0), 0}};
      // At most INT_MAX ms per poll (24.8 days; longer waits loop), never negative (no timeout).
      const int timeout_ms =
          static_cast<int>(std::clamp<int64_t>(ms, 0, std::numeric_limits<int>::max()));
      const int n = ::poll(fds, fd_ >= 0 ? 2 : 1, timeout_ms);
      if (n < 0) {
        if (errno == EINTR) continue;
        throw PortLost{std::string("poll: ") + std::strerror(errno)};
      }
      wake_time_ = SystemClock::now();
      if (fds[0].revents != 0) throw StopRequested{};
      if (fd_ >= 0) {
        if (fds[1].revents & (POLLERR | POLLNVAL)) throw PortLost{"error condition on the port"};
        if (want_data && (fds[1].revents & POLLIN)) return WaitResult::kReadable;
        if (fds[1].revents & POLLHUP) throw PortLost{"hang-up"};
      }
    }
  }

  void Sleep(double seconds) {
    if (seconds <= 0.0) return;
    Wait(SteadyClock::now() + Seconds(seconds), false);
  }

  void Write(std::string_view bytes) {
    while (!bytes.empty()) {
      const ssize_t n = ::write(fd_, bytes.data(), bytes.size());
      if (n > 0) {
        bytes.remove_prefix(static_cast<size_t>(n));
        continue;
      }
      if (n < 0 && errno == EINTR) continue;
      if (n < 0 && errno != EAGAIN && errno != EWOULDBLOCK) {
        throw PortLost{std::string("write: ") + std::strerror(errno)};
      }
      // Output buffer full: wait for room (a stuck line is a lost port).
      pollfd fds[2] = {{driver_->wake_pipe_[0], POLLIN, 0}, {fd_, POLLOUT, 0}};
      const int r = ::poll(fds, 2, 1000);
      if (r == 0) throw PortLost{"write timed out"};
      if (fds[0].revents != 0) throw StopRequested{};
      if (fds[1].revents & (POLLERR | POLLHUP | POLLNVAL)) throw PortLost{"hang-up while writing"};
    }
  }
  void Write(char c) { Write(std::string_view(&c, 1)); }

  // Reads everything available after poll() reported data (non-blocking). A hang-up or read error
  // is PortLost.
  size_t ReadAvailable(std::vector<uint8_t>* out) {
    size_t total = 0;
    std::array<uint8_t, 4096> buffer;
    while (true) {
      const ssize_t n = ::read(fd_, buffer.data(), buffer.size());
      if (n > 0) {
        out->insert(out->end(), buffer.begin(), buffer.begin() + n);
        total += static_cast<size_t>(n);
        continue;
      }
      if (n < 0 && errno == EINTR) continue;
      if (n < 0 && errno != EAGAIN && errno != EWOULDBLOCK) {
        throw PortLost{std::string("read: ") + std::strerror(errno)};
      }
      break;  // 0 (VMIN = VTIME = 0: nothing there) or EAGAIN
    }
    // poll() said readable but nothing came, repeatedly: the line is gone (some USB adapters
    // report end-of-file this way instead of POLLHUP).
    empty_reads_ = total == 0 ? empty_reads_ + 1 : 0;
    if (empty_reads_ >= 3) throw PortLost{"readable but no data (end of file)"};
    return total;
  }

  void FlushInput() { ::tcflush(fd_, TCIFLUSH); }

  void OpenWithBackoff() {
    SetState(DriverState::kOpening);
    Sleep(loss_backoff_s_);
    double delay = timings_.reopen_backoff_min_s;
    // An outage (cable out, adapter gone) is reported once: its first failed open, then again
    // only when the error changes or every kOutageReminder, and its end says how long it lasted.
    // Every attempt still goes to on_log.
    int failed = 0;
    std::string last_error;
    SteadyClock::time_point first_failure, last_reported;
    while (true) {
      if (driver_->stop_.load()) throw StopRequested{};
      Count(&DriverStats::open_attempts);
      std::string error;
      fd_ = OpenSerialPort(options_.port, options_.baud, &error);
      const auto now = SteadyClock::now();
      if (fd_ >= 0) {
        Count(&DriverStats::opens);
        empty_reads_ = 0;
        records_since_open_ = false;
        std::string text = "opened at " + std::to_string(options_.baud) + " baud";
        if (failed > 0) {
          text += " after " + std::to_string(failed) +
                  (failed == 1 ? " failed attempt over " : " failed attempts over ") +
                  FormatSeconds(std::chrono::duration<double>(now - first_failure).count()) +
                  " (last: " + last_error + ")";
        }
        Emit(Severity::kInfo, text);
        return;
      }
      const std::string text =
          "cannot open (" + error + "); next attempt in " + FormatSeconds(delay);
      if (failed == 0) first_failure = now;
      ++failed;
      if (failed == 1 || error != last_error) {
        Emit(Severity::kError, text + "; retrying every " +
                                   FormatSeconds(timings_.reopen_backoff_max_s) +
                                   " at most, reported again when it opens or the error changes");
        last_reported = now;
      } else if (now - last_reported >= kOutageReminder) {
        Emit(Severity::kError,
             "still " + text + " (" + std::to_string(failed) + " failed attempts over " +
                 FormatSeconds(std::chrono::duration<double>(now - first_failure).count()) + ")");
        last_reported = now;
      } else {
        LogOnly(Severity::kError, text);
      }
      last_error = error;
      Sleep(delay);
      delay = std::min(2.0 * delay, timings_.reopen_backoff_max_s);
    }
  }

  // After a reopen: a Fastrak that kept its configuration is still streaming records in our format;
  // stop it and configure it again at once instead of spending seconds on a reset.
  bool TryResume() {
    SetState(DriverState::kResetting);
    size_t bytes_seen = 0;
    return ListenForStream(timings_.resume_probe_s, "after reopening", &bytes_seen);
  }

  // Reads (and otherwise discards) what arrives for `seconds`. If the device has been configured by
  // this driver and two valid records in our format arrive, it is streaming (its cable was out, or
  // it missed our `c`): re-assert the configuration (ReassertConfiguration) and return true if that
  // worked. The records themselves are not reported: the record format does not show the units,
  // the hemisphere, the filters or which unit sent them, and a unit that power-cycled into a
  // configuration saved with ^K, or another unit behind a re-enumerated adapter, streams records
  // that look the same (docs/fastrak-driver.md, Failures). Only used in waits that start at least
  // one preamble settle after `c`, so records in flight before `c` are not mistaken for a live
  // stream; input is flushed first.
  bool ListenForStream(double seconds, const char* when, size_t* bytes_seen) {
    FlushInput();
    parser_.Clear();
    std::vector<FastrakReport> reports;
    const SteadyClock::time_point deadline = SteadyClock::now() + Seconds(seconds);
    std::vector<uint8_t> bytes;
    while (!configured_once_ || reports.size() < 2) {
      if (Wait(deadline, true) == WaitResult::kTimeout) return false;
      bytes.clear();
      *bytes_seen += ReadAvailable(&bytes);
      if (configured_once_) parser_.Feed(bytes, wake_time_, &reports);
    }
    Count(&DriverStats::resumes);
    Emit(Severity::kInfo, std::string("tracker still streaming ") + when +
                              "; stopping it to re-send its configuration (no full reset)");
    const SteadyClock::time_point poll_end =
        SteadyClock::now() + Seconds(timings_.RestartPoll(options_.baud));
    return StatusAndConfigure(poll_end, "still streaming");
  }

  // `c`, a settle (a record in flight ends), flush, `S`; at a valid status reply before `poll_end`,
  // Configure() and true. Shared by the short restart and the resume of a stream.
  bool StatusAndConfigure(SteadyClock::time_point poll_end, const char* what) {
    Write(kStopContinuous);
    Sleep(timings_.RestartSettle(options_.baud));
    FlushInput();
    Write(kRequestStatus);
    const std::string reply = ReadStatusReply(poll_end);
    std::string why;
    const std::optional<StatusRecord> status = ParseStatusRecord(reply, &why);
    if (!status) return false;
    reset_attempts_ = 0;
    unit_status_reply_ = reply;
    Emit(Severity::kInfo, std::string("tracker ") + what + " answered (" +
                              (status->layout_note.empty()
                                   ? "firmware '" + status->firmware_version + "'"
                                   : std::string("status reply not in the Fastrak's layout")) +
                              "); configuring without the full reset");
    Configure();
    return true;
  }

  // The reference reset sequence with its escalation; true when continuous output was started (or
  // the device turned out to be streaming in our format, see ListenForStream).
  bool Reset() {
    SetState(DriverState::kResetting);
    const int attempt = ++reset_attempts_;
    Count(&DriverStats::resets_started);
    // The failed attempt's error came just before this text, often within the rate limit's
    // interval of the text before it: held, it was replaced by this one, and clients and the
    // server log never learnt why the resets failed (nor the baud-rate hint). Say it here too.
    std::string resetting = "resetting the tracker (attempt " + std::to_string(attempt) + ")";
    Severity resetting_severity = Severity::kWarning;
    if (attempt > 1 && !last_reset_failure_.empty()) {
      resetting += "; attempt " + std::to_string(attempt - 1) + ": " + last_reset_failure_;
      resetting_severity = Severity::kError;
    }
    last_reset_failure_.clear();
    Emit(resetting_severity, std::move(resetting));
    const std::array<bool, kMaxStations> stylus = StylusStations(options_);
    if (!stylus_lists_written_) {
      // The reference writes the stylus output list once at configuration time, before any reset.
      for (int s = 0; s < options_.num_stations; ++s) {
        if (stylus[s]) {
          Write(OutputListCommand(s + 1, true));
          Sleep(timings_.command_gap_s);
        }
      }
      stylus_lists_written_ = true;
    }
    for (char c : ResetPreamble(attempt)) {
      Write(c);
      Sleep(timings_.settle_after_preamble_s);
    }
    size_t leftover = 0;
    if (ResetPreambleReinitialises(attempt) &&
        ListenForStream(timings_.reinitialise_wait_s, "during the reset", &leftover)) {
      return true;
    }
    leftover = 0;
    if (ListenForStream(timings_.settle_after_flush_s, "during the reset", &leftover)) return true;
    if (leftover > 0) {
      Emit(Severity::kWarning, "got " + std::to_string(leftover) +
                                   " characters after stopping output; flushing");
      FlushInput();
    }

    Write(kRequestStatus);
    const std::string reply = ReadStatusReply();
    std::string why;
    const std::optional<StatusRecord> status = ParseStatusRecord(reply, &why);
    if (!status) {
      const std::string reason =
          "bad status report (" + (reply.empty() ? std::string("no reply") : why) + ")";
      const std::string hint =
          attempt >= 4 ? "; if this persists, check the cable and that the baud rate matches the "
                         "unit's switches, then power-cycle the Fastrak"
                       : "";
      last_reset_failure_ = reason + hint;
      Emit(Severity::kError, reason + ", retrying reset" + hint);
      return false;
    }
    reset_attempts_ = 0;
    unit_status_reply_ = reply;
    if (!status->layout_note.empty()) {
      // The reference checks only the first and last byte; so do we (ParseStatusRecord).
      Emit(Severity::kInfo, "status OK (a " + std::to_string(reply.size()) +
                                "-byte reply not in the Fastrak's layout: " + status->layout_note +
                                "; its fields are not read)");
    } else {
      std::ostringstream text;
      text << "status OK: firmware '" << status->firmware_version << "', system id '"
           << status->system_id << "', configuration 0x" << std::hex << status->configuration;
      Emit(Severity::kInfo, text.str());
    }
    if (status->bit_errors != 0) {
      std::ostringstream text;
      text << "built-in test reports errors 0x" << std::hex << status->bit_errors;
      Emit(Severity::kWarning, text.str());
    }

    Configure();
    return true;
  }

  // After the status check: output lists, stylus mode, filters, extra commands, units, binary,
  // continuous. The unit answered its status, so it is alive; reports start within a few record
  // periods of this (no blind waits unless confirm_filters is off or the unit does not confirm).
  void Configure() {
    const std::array<bool, kMaxStations> stylus = StylusStations(options_);
    for (int s = 0; s < options_.num_stations; ++s) {
      Write(OutputListCommand(s + 1, stylus[s]));
      Sleep(timings_.command_gap_s);
    }
    if (std::find(stylus.begin(), stylus.end(), true) != stylus.end()) {
      // e1,0 as the reference: the Fastrak reads the stylus switch on station 1 only (manual, 'e'
      // command and "Default Operation with a Stylus"), and its power-up mode there (1, point and
      // track) would make a press toggle the record stream instead of reporting it.
      Write(StylusModeCommand(1));
      Sleep(timings_.command_gap_s);
    }
    if (options_.confirm_filters) {
      // The reference sleeps 1 s after each filter line. A unit reads its commands in order, so
      // its answer to `S` after them shows they were read: continue at the reply (a few ms), and
      // fall back to the reference's waits only if no valid reply comes.
      const SteadyClock::time_point start = SteadyClock::now();
      Write(kPositionFilterCommand);
      Write(kAttitudeFilterCommand);
      FlushInput();
      Write(kRequestStatus);
      const std::string reply = ReadStatusReply();
      std::string why;
      if (!ParseStatusRecord(reply, &why)) {
        Emit(Severity::kWarning,
             (reply.empty()
                  ? std::string("no status reply after the filter commands")
                  : "status reply after the filter commands refused (" + why + "; got " +
                        std::to_string(reply.size()) + " bytes: " + QuoteBytes(reply) + ")") +
                 "; waiting " + FormatSeconds(2 * timings_.filter_settle_s) + " instead");
        const double waited = std::chrono::duration<double>(SteadyClock::now() - start).count();
        Sleep(2 * timings_.filter_settle_s - waited);
      }
    } else {
      Write(kPositionFilterCommand);
      Sleep(timings_.filter_settle_s);
      Write(kAttitudeFilterCommand);
      Sleep(timings_.filter_settle_s);
    }
    for (const std::string& cmd : options_.extra_commands) {
      if (cmd.front() == '*') {
        Sleep(std::strtod(cmd.c_str() + 1, nullptr));
      } else {
        Write(cmd + "\r");
      }
    }
    if (!options_.extra_commands.empty()) {
      if (options_.confirm_filters) {
        // As for the filters: the unit answers `S` after it has read the extra commands. Replies
        // to them (a query among the extras) come first and are skipped: only a reply in the
        // Fastrak's 55-byte status layout, or in the layout of the unit's own reply to the reset's
        // `S` (an IS-900's 54 bytes, InUnitStatusLayout), confirms. Else the reference's blind
        // wait. `*N` waits above are the user's and always made.
        const SteadyClock::time_point start = SteadyClock::now();
        Write(kRequestStatus);
        std::string other;
        if (!ReadFullStatusReply(&other)) {
          Emit(Severity::kWarning, (other.empty() ? std::string("no reply")
                                                  : "no reply in the " + StatusLayoutName() +
                                                        " (got " + std::to_string(other.size()) +
                                                        " bytes: " + QuoteBytes(other) + ")") +
                                       " to the status request after the extra commands; waiting " +
                                       FormatSeconds(timings_.extras_settle_s) + " instead");
          const double waited = std::chrono::duration<double>(SteadyClock::now() - start).count();
          Sleep(timings_.extras_settle_s - waited);
        }
      } else {
        Sleep(timings_.extras_settle_s);
      }
    }
    FlushInput();
    if (options_.force_units) Write(UnitsCommand(units_));
    Write(kBinaryFormat);
    Write(kStartContinuous);
    parser_.Clear();
    configured_once_ = true;
    Count(&DriverStats::resets_completed);
    Emit(Severity::kInfo, std::string("reset completed; binary records in ") + UnitsName(units_));
  }

  // After a loss (watchdog, port lost) of a unit this driver had configured, when the probe found
  // no stream: the unit may be back at any moment (a stall, a power cycle, a cable) and answer at
  // once. Ask for its status every restart_poll_s (`c` to stop a stream we cannot parse, a short
  // settle, flush, `S`; both longer at low baud rates, RestartPoll/RestartSettle, so that a record
  // in flight ends before the flush and the whole reply fits in the poll) for restart_window_s; at
  // the first valid reply configure it (Configure),
  // so reports resume well within 2 s of the unit answering. Without a valid reply in the window:
  // false, and the reference's full reset (with its escalation) follows.
  bool QuickRestart() {
    if (timings_.restart_window_s <= 0.0) return false;
    SetState(DriverState::kResetting);
    const SteadyClock::time_point end = SteadyClock::now() + Seconds(timings_.restart_window_s);
    Emit(Severity::kWarning, "asking the tracker for its status (up to " +
                                 FormatSeconds(timings_.restart_window_s) + ") before a full reset");
    while (SteadyClock::now() < end) {
      const SteadyClock::time_point poll_end =
          SteadyClock::now() + Seconds(timings_.RestartPoll(options_.baud));
      if (StatusAndConfigure(poll_end, "after the loss")) {
        Count(&DriverStats::quick_restarts);
        return true;
      }
      // Let the poll interval run out (a reply that came too late is flushed by the next poll).
      Sleep(std::chrono::duration<double>(poll_end - SteadyClock::now()).count());
    }
    return false;
  }

  // The status layout that confirms after the extra commands, for texts.
  std::string StatusLayoutName() const {
    if (InUnitStatusLayout(unit_status_reply_, unit_status_reply_) &&
        unit_status_reply_.size() != kStatusRecordSize) {
      return "unit's " + std::to_string(unit_status_reply_.size()) + "-byte status layout";
    }
    return "Fastrak's 55-byte status layout";
  }

  // Reads until a status reply in the Fastrak's 55-byte layout or in the unit's own (the layout of
  // its reply to the reset's `S`, InUnitStatusLayout) has arrived (true) or the status timeout
  // passes (false; *other is then everything that came). Replies to query extra commands come
  // first and are skipped; they need not end with an LF (a `P` record in the output list 2,11,0 has
  // none, so it runs into the status reply), hence the status is looked for as the 55 (or the
  // unit's) bytes up to each LF.
  bool ReadFullStatusReply(std::string* other) {
    // Bounds memory if a unit floods the line (at 115200 baud the status timeout, 1 s, brings
    // 11.5 kB); the status reply is then missed and the blind wait follows.
    constexpr size_t kMaxBytes = 65536;
    const SteadyClock::time_point deadline =
        SteadyClock::now() + Seconds(timings_.StatusTimeout(options_.baud));
    std::vector<uint8_t> bytes;
    size_t scanned = 0;
    // The `size` bytes up to and including the byte at `lf`, or nothing if fewer have come.
    auto window = [&bytes](std::vector<uint8_t>::const_iterator lf, size_t size) {
      if (lf - bytes.cbegin() + 1 < static_cast<std::ptrdiff_t>(size)) return std::string();
      return std::string(lf + 1 - static_cast<std::ptrdiff_t>(size), lf + 1);
    };
    while (true) {
      for (auto lf =
               std::find(bytes.cbegin() + static_cast<std::ptrdiff_t>(scanned), bytes.cend(), '\n');
           lf != bytes.cend(); lf = std::find(lf + 1, bytes.cend(), '\n')) {
        const std::string candidate = window(lf, kStatusRecordSize);
        std::string why;
        const std::optional<StatusRecord> status =
            candidate.empty() ? std::nullopt : ParseStatusRecord(candidate, &why);
        if (status && status->layout_note.empty()) return true;
        if (InUnitStatusLayout(window(lf, unit_status_reply_.size()), unit_status_reply_)) {
          return true;
        }
      }
      scanned = bytes.size();
      if (bytes.size() > kMaxBytes || Wait(deadline, true) == WaitResult::kTimeout) {
        other->assign(bytes.begin(), bytes.end());
        return false;
      }
      ReadAvailable(&bytes);
    }
  }

  // Reads until the reply's LF or the status timeout (or `until`, if earlier); returns what arrived.
  std::string ReadStatusReply(SteadyClock::time_point until = SteadyClock::time_point::max()) {
    const SteadyClock::time_point deadline =
        std::min(until, SteadyClock::now() + Seconds(timings_.StatusTimeout(options_.baud)));
    std::vector<uint8_t> bytes;
    while (std::find(bytes.begin(), bytes.end(), '\n') == bytes.end() && bytes.size() < 4096) {
      if (Wait(deadline, true) == WaitResult::kTimeout) break;
      ReadAvailable(&bytes);
    }
    auto lf = std::find(bytes.begin(), bytes.end(), '\n');
    if (lf != bytes.end()) ++lf;
    return std::string(bytes.begin(), lf);
  }

  void DeliverReports(const std::vector<FastrakReport>& reports) {
    if (reports.empty()) return;
    records_since_open_ = true;
    loss_backoff_s_ = 0.0;
    Count(&DriverStats::records, reports.size());
    if (driver_->callbacks_.on_reports) driver_->callbacks_.on_reports(reports);
    for (const FastrakReport& report : reports) {
      if (!driver_->callbacks_.on_reports && driver_->callbacks_.on_report) driver_->callbacks_.on_report(report);
      if (report.stylus_pressed) {
        std::optional<bool>& last = last_button_[report.sensor];
        if (last != report.stylus_pressed) {
          last = report.stylus_pressed;
          if (driver_->callbacks_.on_button) {
            driver_->callbacks_.on_button(report.sensor, *report.stylus_pressed, report.time);
          }
        }
      }
    }
  }

  void Stream() {
    SetState(DriverState::kStreaming);
    last_button_.fill(std::nullopt);
    SteadyClock::time_point watchdog = SteadyClock::now() + Seconds(timings_.watchdog_s);
    std::vector<uint8_t> bytes;
    std::vector<FastrakReport> reports;
    uint64_t reported_discards = parser_.discarded_bytes();
    while (true) {
      if (Wait(watchdog, true) == WaitResult::kTimeout) {
        Count(&DriverStats::watchdog_timeouts);
        Emit(Severity::kError, "no record for " + FormatSeconds(timings_.watchdog_s) +
                                   "; reopening and resetting the tracker");
        return;
      }
      bytes.clear();
      reports.clear();
      ReadAvailable(&bytes);
      parser_.Feed(bytes, wake_time_, &reports);
      if (!reports.empty()) watchdog = SteadyClock::now() + Seconds(timings_.watchdog_s);
      DeliverReports(reports);
      if (parser_.discarded_bytes() != reported_discards) {
        const uint64_t n = parser_.discarded_bytes() - reported_discards;
        Count(&DriverStats::discarded_bytes, n);
        reported_discards = parser_.discarded_bytes();
        Emit(Severity::kWarning, "skipped " + std::to_string(n) +
                                     " bytes that were not part of a valid record (resynchronised)");
      }
    }
  }

  FastrakDriver* driver_;
  const FastrakOptions& options_;
  const FastrakTimings& timings_;
  const Units units_;
  RecordParser parser_;
  MessageLimiter limiter_;
  int fd_ = -1;
  int reset_attempts_ = 0;
  int empty_reads_ = 0;
  bool records_since_open_ = false;
  double loss_backoff_s_ = 0.0;  // wait before reopening after losses without a record, or 0
  bool configured_once_ = false;
  bool after_loss_ = false;  // the stream or the port was lost since the last short restart
  bool stylus_lists_written_ = false;
  std::string unit_status_reply_;  // the last status reply accepted before a Configure()
  std::string last_reset_failure_;  // why the last reset attempt failed, for the next one's text
  SystemClock::time_point wake_time_;
  std::array<std::optional<bool>, kMaxStations> last_button_;
};

// ---------------------------------------------------------------------------------------------

FastrakDriver::FastrakDriver(FastrakOptions options, Callbacks callbacks)
    : options_(std::move(options)), callbacks_(std::move(callbacks)) {
  options_.Check();
}

FastrakDriver::~FastrakDriver() { Stop(); }

void FastrakDriver::Start() {
  if (thread_.joinable()) throw std::logic_error("FastrakDriver::Start called twice");
  if (::pipe2(wake_pipe_, O_CLOEXEC | O_NONBLOCK) != 0) {
    throw std::runtime_error(std::string("FastrakDriver: pipe: ") + std::strerror(errno));
  }
  stop_.store(false);
  state_.store(DriverState::kOpening);
  thread_ = std::thread([this] { Run(); });
}

void FastrakDriver::Run() {
  Session session(this);
  session.Run();
  state_.store(DriverState::kStopped);
}

void FastrakDriver::Stop() {
  if (!thread_.joinable()) return;
  stop_.store(true);
  const char byte = 1;
  [[maybe_unused]] const ssize_t n = ::write(wake_pipe_[1], &byte, 1);
  thread_.join();
  ::close(wake_pipe_[0]);
  ::close(wake_pipe_[1]);
  wake_pipe_[0] = wake_pipe_[1] = -1;
}

DriverStats FastrakDriver::stats() const {
  std::lock_guard<std::mutex> lock(stats_mutex_);
  return stats_;
}

}  // namespace trackcal::fastrak
