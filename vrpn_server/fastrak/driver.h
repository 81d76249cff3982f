// FastrakDriver: drives a Polhemus Fastrak on a serial port in its own thread, so a reset (seconds
// of waiting) never blocks the network server. The byte sequence is the VRPN reference driver's
// (FASTRAK.md section 4) with these differences (docs/fastrak-driver.md):
// - units are explicit: the driver sends `U`/`u` itself (or tracks a `u`/`U` extra command) and
//   converts inches or centimetres correctly to metres;
// - the status record's fields are parsed and reported when it has the Fastrak's 55-byte layout
//   (it is accepted, as by the reference, on its first byte '2' and its final LF alone);
// - records are parsed by a resynchronising state machine that keeps good records after garbage;
// - a lost port is reopened with capped exponential back-off, and a device that is still streaming
//   in the configured format when the port comes back is stopped and configured again at once
//   (status, output lists, filters, extra commands, units) without the full reset: its records
//   do not show its units, hemisphere, filters or identity;
// - texts to clients are rate-limited (MessageLimiter).
//
// Threading: Start() launches the thread; every callback runs on it and must return quickly (the
// server marshals reports into its own event loop). Stop() (or the destructor) interrupts any wait
// at once and joins.

#pragma once

#include <atomic>
#include <chrono>
#include <cstdint>
#include <functional>
#include <memory>
#include <mutex>
#include <span>
#include <string>
#include <thread>
#include <vector>

#include "vrpn_server/fastrak/message_limiter.h"
#include "vrpn_server/fastrak/protocol.h"
#include "vrpn_server/fastrak/record_parser.h"

namespace trackcal::fastrak {

// Waits of the reset sequence and the failure handling, in seconds.
struct FastrakTimings {
  double settle_after_preamble_s = 2.0;  // after each byte of the reset preamble (`c`, CR, ^Y...)
  double reinitialise_wait_s = 20.0;     // extra wait on attempts that send ^Y (3 and later)
  double settle_after_flush_s = 2.0;     // after flushing input, before reading leftover bytes
  double status_timeout_s = 1.0;         // longest wait for the status reply (ends at its LF)
  double command_gap_s = 0.05;           // after each `O` and `e` line
  double filter_settle_s = 1.0;          // after each filter line (`x`, `v`), only when the
                                         // status round trip after them fails or is disabled
  double extras_settle_s = 2.0;          // after the extra commands, if there are any
  double watchdog_s = 2.0;               // no complete record for this long -> reopen and reset
  double resume_probe_s = 2.0;           // after reopening: listen up to this long for records before
                                         // resetting (ends at the second record; covers short stalls)
  double restart_window_s = 6.0;         // after a loss (the probe found no stream): ask the unit
                                         // for its status this long before the full reset
  double restart_poll_s = 0.5;           // one status request per this interval in that window
  double restart_settle_s = 0.1;         // after `c` in that window, before flushing and `S` (a
                                         // record in flight takes < 40 ms at 9600 baud)
  double reopen_backoff_min_s = 0.1;     // first retry delay when the port cannot be opened
  double reopen_backoff_max_s = 1.0;     // cap of the doubling retry delay
  double message_interval_s = 1.0;       // at most one text per interval to clients

  // The reference driver's waits (known to work with real units). Default.
  static FastrakTimings Reference() { return {}; }
  // Short waits for emulators on a pty, which answer at once (tests, CI).
  static FastrakTimings Fast();
  // Throws std::invalid_argument naming the field.
  void Check() const;
  // status_timeout_s, or twice the 55-byte reply's time on the line if that is longer (the reply
  // takes 1.83 s at 300 baud, so 3.67 s there, where the reference's 1 s never sees it whole).
  double StatusTimeout(int baud) const;
  // The short restart's settle after `c` and its poll interval at `baud`: restart_settle_s, or
  // twice a 34-byte record's line time if longer (a record in flight when `c` arrives is finished
  // first); restart_poll_s, or the settle plus twice the status reply's line time if longer (the
  // reply must fit in a poll: 0.46 s at 1200 baud, 1.83 s at 300, where 0.5 s polls never saw one).
  double RestartSettle(int baud) const;
  double RestartPoll(int baud) const;
};

struct FastrakOptions {
  // Serial device path (a symbolic link works; it is resolved again on every reopen).
  std::string port;
  // Line speed; must match the Fastrak's switches. 300, 1200, ..., 115200.
  int baud = 115200;
  // Stations 1..num_stations get an output list (the reference always configures 4).
  int num_stations = kMaxStations;
  // Sent in order after the filters, each followed by CR; "*N" sleeps N seconds instead.
  std::vector<std::string> extra_commands;
  // 0-based sensors with a stylus (FTStylus): output item 16, `e<station>,0`, button reports.
  std::vector<int> stylus_sensors;
  // Unit the device is put in (or assumed in, see force_units). A `u`/`U` extra command overrides.
  Units units = Units::kInches;
  // true: send `U`/`u` before `f` so the device is certainly in the unit we convert from;
  // false: send exactly the reference's bytes and only track `u`/`U` in extra_commands.
  bool force_units = true;
  // true: after the filter lines send `S` and continue as soon as the status reply arrives (the
  // unit reads its commands in order, so the reply shows the filters were taken), instead of the
  // reference's blind filter_settle_s after each of them; likewise after the extra commands
  // (instead of extras_settle_s; a reply in the 55-byte Fastrak layout is required there, so that
  // replies to the extras are skipped); false: the reference's bytes and waits.
  bool confirm_filters = true;
  // Real-time (SCHED_FIFO) priority of the driver thread, 1..99; 0 keeps the normal scheduler.
  // trackcal-server gives it the network thread's --realtime-priority, so a record is read and
  // handed over without waiting behind other programs. Needs CAP_SYS_NICE (else a warning).
  int realtime_priority = 0;
  FastrakTimings timings;

  // Throws std::invalid_argument naming the field.
  void Check() const;
  // Unit of the records after the reset: `units`, unless the last `u`/`U` extra command says otherwise.
  Units EffectiveUnits() const;
};

enum class DriverState { kStopped, kOpening, kResetting, kStreaming };
const char* DriverStateName(DriverState state);

// Counters for tests, logs and diagnostics.
struct DriverStats {
  uint64_t open_attempts = 0;     // open() calls on the port
  uint64_t opens = 0;             // successful opens
  uint64_t resets_started = 0;    // reset attempts (each escalation step counts)
  uint64_t resets_completed = 0;  // resets that reached continuous mode
  uint64_t resumes = 0;           // reopens/reset waits that found the device streaming (it is
                                  // then configured again without the full reset)
  uint64_t quick_restarts = 0;    // restarts after a loss through the short path (status, configure)
  uint64_t watchdog_timeouts = 0;
  uint64_t port_losses = 0;       // hang-ups and read/write errors
  uint64_t records = 0;           // valid records reported
  uint64_t discarded_bytes = 0;   // garbage skipped while resynchronising
  uint64_t messages_suppressed = 0;
};

class FastrakDriver {
 public:
  struct Callbacks {
    // Every valid record.
    std::function<void(const FastrakReport&)> on_report;
    // Optional: the valid records of one read at once (several when they arrived together); when
    // set it is called instead of on_report, so a server can send them to its clients together.
    std::function<void(std::span<const FastrakReport>)> on_reports;
    // Stylus switch of a sensor changed (and its first state after each (re)start of streaming).
    std::function<void(int sensor, bool pressed, std::chrono::system_clock::time_point time)> on_button;
    // Status/error text for clients, at most one per timings.message_interval_s.
    std::function<void(Severity severity, const std::string& text)> on_message;
    // Optional: every text at once, not rate-limited (for the server's own log file).
    std::function<void(Severity severity, const std::string& text)> on_log;
  };

  // Checks the options (throws std::invalid_argument).
  FastrakDriver(FastrakOptions options, Callbacks callbacks);
  ~FastrakDriver();
  FastrakDriver(const FastrakDriver&) = delete;
  FastrakDriver& operator=(const FastrakDriver&) = delete;

  // Starts the driver thread; returns at once. Errors (port missing...) are reported via on_message.
  void Start();
  // Stops the thread (interrupting any wait) and closes the port. Idempotent.
  void Stop();

  DriverState state() const { return state_.load(); }
  DriverStats stats() const;
  const FastrakOptions& options() const { return options_; }

 private:
  class Session;  // one run of the thread: port, parser, limiter
  void Run();

  FastrakOptions options_;
  Callbacks callbacks_;
  std::thread thread_;
  int wake_pipe_[2] = {-1, -1};
  std::atomic<bool> stop_{false};
  std::atomic<DriverState> state_{DriverState::kStopped};
  mutable std::mutex stats_mutex_;
  DriverStats stats_;
  friend class Session;
};

}  // namespace trackcal::fastrak
