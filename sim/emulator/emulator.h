// The Fastrak emulator process: a FastrakDevice on a pseudo-terminal, streaming the poses of a
// PoseSource through a MeasurementModel in real time, with a line-based control socket for moving
// stations and injecting faults. Usage, protocol and formats: docs/emulator.md.

#pragma once

#include <atomic>
#include <cstdint>
#include <deque>
#include <functional>
#include <future>
#include <memory>
#include <mutex>
#include <random>
#include <string>
#include <thread>
#include <variant>
#include <vector>

#include "sim/emulator/fastrak_device.h"
#include "sim/emulator/pose_source.h"
#include "sim/emulator/pty.h"

namespace trackcal::emulator {

// Control socket commands (one line each; see ParseControlCommand).
struct MoveCommand {
  int station = 1;
  Rigid3d transmitter_from_receiver;
};
struct ReleaseCommand {
  int station = 1;
};
struct ButtonCommand {
  int station = 1;
  bool pressed = false;
};
struct GarbageFault {
  int num_bytes = 0;
};
struct StallFault {
  double seconds = 0;
};
struct PowerCycleFault {
  double seconds = 0;  // off time
};
struct DisconnectFault {
  double seconds = 0;
};
struct TruncateFault {
  int keep_bytes = -1;  // bytes of the next record that are sent; -1 = half of it
};
struct StatusCommand {};
struct HelpCommand {};
using ControlCommand =
    std::variant<MoveCommand, ReleaseCommand, ButtonCommand, GarbageFault, StallFault,
                 PowerCycleFault, DisconnectFault, TruncateFault, StatusCommand, HelpCommand>;

// Parses one control line:
//   move STATION x y z qw qx qy qz   (metres; quaternion scalar first, normalised)
//   release STATION                  (back to the trajectory/static pose)
//   button STATION 0|1
//   fault garbage N | fault stall SECONDS | fault powercycle SECONDS | fault disconnect SECONDS |
//   fault truncate [BYTES]
//   status | help
// Throws std::invalid_argument naming the field.
ControlCommand ParseControlCommand(const std::string& line);

struct EmulatorOptions {
  // The device model (stations plugged in, power-up state, status record fields).
  FastrakDeviceOptions device;
  // Measurement cycles per second; a Fastrak makes 120 and shares them among the active stations.
  double update_rate_hz = 120.0;
  // true: one station per cycle, round robin (the Fastrak); false: every active station every
  // cycle.
  bool divide_rate_among_stations = true;
  // Serial line speed of the device (its I/O select switches), bits per second with 10 bits per
  // byte (8N1): output leaves at most this fast, each byte reaching the host when its last bit
  // would have. 0 = unlimited. A pty ignores the host's speed setting, so this is the only pacing
  // of the line.
  int baud = 115200;
  // If set, a symbolic link to the slave device, replaced atomically on reconnect, removed at exit.
  std::string link_path;
  // If set, path of the Unix stream socket of the control protocol.
  std::string control_socket_path;
  // Device output waiting for the host beyond this is dropped as whole records (a real serial line
  // loses data nobody reads; a pty would otherwise block the emulator).
  size_t max_pending_output_bytes = 4096;
  // Seed of the garbage-byte generator.
  uint64_t seed = 1;
  // Run() returns after this many seconds; <= 0 runs until RequestStop().
  double run_seconds = 0;

  // Throws std::invalid_argument naming the field.
  void Check() const;
};

struct EmulatorStats {
  int64_t records_sent = 0;     // complete records queued for the host
  int64_t records_dropped = 0;  // records not measured: the line was still busy (or queue full)
  int64_t items_lost = 0;       // records or replies sent while the host's buffer was full
  int64_t bytes_received = 0;   // bytes the host wrote
  int64_t reconnects = 0;       // completed disconnect faults
};

class Emulator {
 public:
  // `source` and `model` must outlive the emulator.
  Emulator(EmulatorOptions options, PoseSource* source, MeasurementModel* model);
  ~Emulator();

  // Opens the pty (and link, control socket). Throws std::runtime_error.
  void Start();
  // Serves until RequestStop(); then removes the link and the control socket.
  void Run();
  // Async-signal-safe and thread-safe.
  void RequestStop();

  // Called with the slave path each time a pty is opened (start and reconnect).
  std::function<void(const std::string&)> on_device_path;
  // Called with each log line (device commands, faults), prefixed with the time in seconds.
  std::function<void(const std::string&)> on_log;

  // Executes one control line and returns the one-line reply ("ok ..." or "error: ...").
  // Called by the control socket; must be called on the Run() thread.
  std::string HandleControlLine(const std::string& line);
  // The same from any other thread while Run() is serving: queued to the Run() thread, waits for
  // the reply (at most 5 s; "error: emulator not running" otherwise).
  std::string Control(const std::string& line);

  // Seconds since Start() on the steady clock (the PoseSource's time).
  double Now() const;
  // Only on the Run() thread or after Run() returned (the control `status` line is the
  // thread-safe way to look from outside).
  EmulatorStats stats() const { return stats_; }
  const FastrakDevice& device() const { return device_; }

 private:
  struct ControlClient {
    int fd = -1;
    std::string input;
    std::string output;
  };

  void OpenPty();
  void ClosePty();
  void OpenControlSocket();
  void Log(const std::string& message);
  void ReadHost(double now);
  void WriteHost(double now);
  // When WriteHost has the next bytes to write (now if the line is idle; infinity: nothing queued).
  double NextOutputDue(double now) const;
  // Hands the stylus switch of station 1 to the device (point/track mode).
  void SampleStylus(double now);
  void StreamRecords(double now);
  // `stream_record`: a record of continuous output (not a reply to `S` or `P`, nor garbage).
  void Enqueue(std::string bytes, bool stream_record = false);
  // Drops queued continuous-output records that have not started to go out (a device that stops
  // streaming finishes the record on the wire and sends no more); replies the host asked for
  // still go out.
  void DropUnstartedRecords();
  void QueueRecord(int station, double now);
  void ServiceControl(short revents_listen, const std::vector<short>& revents_clients);
  void ServicePosted();
  std::string StatusLine();

  EmulatorOptions options_;
  PoseSource* source_;
  MeasurementModel* model_;
  FastrakDevice device_;
  std::unique_ptr<PseudoTerminal> pty_;
  std::string current_slave_path_;
  // Device output not yet written: whole items (records, replies, garbage); the head may be
  // partly written (output_head_sent_ bytes of it).
  struct OutputItem {
    std::string bytes;
    bool stream_record = false;  // a continuous-mode record ('c' drops it), not a reply
    bool lost = false;           // some of its bytes were lost (counted once in items_lost)
  };
  std::deque<OutputItem> output_queue_;
  size_t output_head_sent_ = 0;
  size_t output_bytes_ = 0;
  double line_busy_until_s_ = 0;    // when the last byte written has left the emulated wire
  bool line_start_pending_ = true;  // output queued on an idle line: its timeline starts afresh
  bool was_continuous_ = false;
  double next_cycle_s_ = 0;
  size_t round_robin_ = 0;
  double stall_until_s_ = -1;
  bool power_off_ = false;  // the stall is a power cycle: reinitialise when it ends
  double reconnect_at_s_ = -1;
  int truncate_next_ = 0;  // 0 = none, >0 keep that many bytes, -1 keep half
  std::mt19937_64 rng_;
  int listen_fd_ = -1;
  std::vector<ControlClient> clients_;
  int wake_pipe_[2] = {-1, -1};
  std::mutex posted_mutex_;
  std::deque<std::pair<std::string, std::promise<std::string>>> posted_;
  std::atomic<bool> stop_{false};
  int64_t start_ns_ = 0;
  EmulatorStats stats_;
};

// An emulator serving on its own thread, for end-to-end tests of drivers and servers: the pty is
// open when the constructor returns and everything is closed (link removed) by the destructor.
class BackgroundEmulator {
 public:
  // `model` defaults to PerfectMeasurement. The source is wrapped in a ControlledPoseSource so
  // `move`/`button` work.
  BackgroundEmulator(EmulatorOptions options, std::unique_ptr<PoseSource> source,
                     std::unique_ptr<MeasurementModel> model = nullptr);
  ~BackgroundEmulator();
  BackgroundEmulator(const BackgroundEmulator&) = delete;
  BackgroundEmulator& operator=(const BackgroundEmulator&) = delete;

  // The device path at start ("/dev/pts/N"); after a disconnect fault use the link or `status`.
  const std::string& initial_device_path() const { return initial_device_path_; }
  // A control-protocol line (see ParseControlCommand), executed on the emulator thread.
  std::string Control(const std::string& line) { return emulator_->Control(line); }

 private:
  std::unique_ptr<ControlledPoseSource> source_;
  std::unique_ptr<MeasurementModel> model_;
  std::unique_ptr<Emulator> emulator_;
  std::string initial_device_path_;
  std::thread thread_;
};

}  // namespace trackcal::emulator
