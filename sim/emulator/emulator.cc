#include "sim/emulator/emulator.h"

#include <fcntl.h>
#include <poll.h>
#include <sys/socket.h>
#include <sys/stat.h>
#include <sys/un.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <limits>
#include <sstream>
#include <stdexcept>

namespace trackcal::emulator {
namespace {

// Longest a control line may be before the client is considered broken.
constexpr size_t kMaxControlLine = 4096;
// If the loop falls this far behind the record schedule (a stalled machine), it restarts the
// schedule instead of sending a burst the real device could not have produced.
constexpr double kMaxScheduleLagS = 0.1;
// How late a write may be and still count as back-to-back on the emulated serial line.
constexpr double kLineSlackS = 0.002;
// Paced output is written as its bytes complete on the emulated line; the loop wakes when this many
// more have (0.7 ms at 115200 baud, 8 ms at 9600), like a serial adapter's small transfers.
constexpr size_t kOutputChunkBytes = 8;

int64_t SteadyNowNs() {
  return std::chrono::duration_cast<std::chrono::nanoseconds>(
             std::chrono::steady_clock::now().time_since_epoch())
      .count();
}

std::vector<std::string> Tokens(const std::string& line) {
  std::istringstream ss(line);
  std::vector<std::string> tokens;
  std::string token;
  while (ss >> token) tokens.push_back(token);
  return tokens;
}

double ParseNumber(const std::string& token, const std::string& field) {
  char* end = nullptr;
  const double v = std::strtod(token.c_str(), &end);
  if (token.empty() || *end != '\0' || !std::isfinite(v)) {
    throw std::invalid_argument("field '" + field + "': not a finite number: '" + token + "'");
  }
  return v;
}

int ParseInteger(const std::string& token, const std::string& field, int min, int max) {
  const double v = ParseNumber(token, field);
  if (v != std::floor(v) || v < min || v > max) {
    throw std::invalid_argument("field '" + field + "': must be an integer in [" +
                                std::to_string(min) + ", " + std::to_string(max) + "], got '" +
                                token + "'");
  }
  return static_cast<int>(v);
}

void ExpectArgs(const std::vector<std::string>& t, size_t n, const std::string& usage) {
  if (t.size() != n) throw std::invalid_argument("usage: " + usage);
}

void SetNonBlocking(int fd) { fcntl(fd, F_SETFL, fcntl(fd, F_GETFL) | O_NONBLOCK); }

}  // namespace

ControlCommand ParseControlCommand(const std::string& line) {
  const std::vector<std::string> t = Tokens(line);
  if (t.empty()) throw std::invalid_argument("empty command");
  const std::string& verb = t[0];
  if (verb == "move") {
    ExpectArgs(t, 9, "move STATION x y z qw qx qy qz");
    MoveCommand c;
    c.station = ParseInteger(t[1], "station", 1, kMaxStations);
    c.transmitter_from_receiver.translation =
        Eigen::Vector3d(ParseNumber(t[2], "x"), ParseNumber(t[3], "y"), ParseNumber(t[4], "z"));
    const Eigen::Quaterniond q =
        QuaternionFromWxyz(ParseNumber(t[5], "qw"), ParseNumber(t[6], "qx"),
                           ParseNumber(t[7], "qy"), ParseNumber(t[8], "qz"));
    if (q.norm() < 1e-9) throw std::invalid_argument("fields 'qw qx qy qz': zero quaternion");
    c.transmitter_from_receiver.rotation = q.normalized();
    return c;
  }
  if (verb == "release") {
    ExpectArgs(t, 2, "release STATION");
    return ReleaseCommand{ParseInteger(t[1], "station", 1, kMaxStations)};
  }
  if (verb == "button") {
    ExpectArgs(t, 3, "button STATION 0|1");
    return ButtonCommand{ParseInteger(t[1], "station", 1, kMaxStations),
                         ParseInteger(t[2], "pressed", 0, 1) == 1};
  }
  if (verb == "status") {
    ExpectArgs(t, 1, "status");
    return StatusCommand{};
  }
  if (verb == "help") return HelpCommand{};
  if (verb == "fault") {
    if (t.size() < 2)
      throw std::invalid_argument("usage: fault garbage|stall|powercycle|disconnect|truncate ...");
    const std::string& kind = t[1];
    if (kind == "garbage") {
      ExpectArgs(t, 3, "fault garbage N");
      return GarbageFault{ParseInteger(t[2], "N", 1, 1 << 20)};
    }
    if (kind == "stall") {
      ExpectArgs(t, 3, "fault stall SECONDS");
      const double s = ParseNumber(t[2], "SECONDS");
      if (s <= 0 || s > 3600) throw std::invalid_argument("field 'SECONDS': must be in (0, 3600]");
      return StallFault{s};
    }
    if (kind == "powercycle") {
      ExpectArgs(t, 3, "fault powercycle SECONDS");
      const double s = ParseNumber(t[2], "SECONDS");
      if (s <= 0 || s > 3600) throw std::invalid_argument("field 'SECONDS': must be in (0, 3600]");
      return PowerCycleFault{s};
    }
    if (kind == "disconnect") {
      ExpectArgs(t, 3, "fault disconnect SECONDS");
      const double s = ParseNumber(t[2], "SECONDS");
      if (s < 0 || s > 3600) throw std::invalid_argument("field 'SECONDS': must be in [0, 3600]");
      return DisconnectFault{s};
    }
    if (kind == "truncate") {
      if (t.size() == 2) return TruncateFault{};
      ExpectArgs(t, 3, "fault truncate [BYTES]");
      return TruncateFault{ParseInteger(t[2], "BYTES", 1, 1 << 16)};
    }
    throw std::invalid_argument("field 'fault': unknown fault '" + kind + "'");
  }
  throw std::invalid_argument("unknown command '" + verb + "' (try help)");
}

void EmulatorOptions::Check() const {
  device.Check();
  if (!(update_rate_hz > 0 && update_rate_hz <= 100000)) {
    throw std::invalid_argument("EmulatorOptions.update_rate_hz: must be in (0, 100000]");
  }
  if (baud < 0) throw std::invalid_argument("EmulatorOptions.baud: must be >= 0");
  if (!std::isfinite(run_seconds))
    throw std::invalid_argument("EmulatorOptions.run_seconds: not finite");
  if (max_pending_output_bytes < 64) {
    throw std::invalid_argument("EmulatorOptions.max_pending_output_bytes: must be at least 64");
  }
  if (control_socket_path.size() >= sizeof(sockaddr_un::sun_path)) {
    throw std::invalid_argument("EmulatorOptions.control_socket_path: longer than " +
                                std::to_string(sizeof(sockaddr_un::sun_path) - 1) + " characters");
  }
}

Emulator::Emulator(EmulatorOptions options, PoseSource* source, MeasurementModel* model)
    : options_(std::move(options)),
      source_(source),
      model_(model),
      device_((options_.Check(), options_.device)),
      rng_(options_.seed) {
  if (source_ == nullptr || model_ == nullptr) {
    throw std::invalid_argument("Emulator: source and model are required");
  }
  if (pipe2(wake_pipe_, O_CLOEXEC | O_NONBLOCK) != 0) {
    throw std::runtime_error(std::string("pipe2: ") + std::strerror(errno));
  }
  start_ns_ = SteadyNowNs();
}

Emulator::~Emulator() {
  ClosePty();
  for (ControlClient& c : clients_) close(c.fd);
  if (listen_fd_ >= 0) {
    close(listen_fd_);
    unlink(options_.control_socket_path.c_str());
  }
  close(wake_pipe_[0]);
  close(wake_pipe_[1]);
}

double Emulator::Now() const { return (SteadyNowNs() - start_ns_) * 1e-9; }

void Emulator::Log(const std::string& message) {
  if (!on_log) return;
  char prefix[32];
  std::snprintf(prefix, sizeof(prefix), "%9.3f ", Now());
  on_log(prefix + message);
}

void Emulator::Start() {
  start_ns_ = SteadyNowNs();
  OpenPty();
  if (!options_.control_socket_path.empty()) OpenControlSocket();
}

void Emulator::OpenPty() {
  pty_ = std::make_unique<PseudoTerminal>();
  current_slave_path_ = pty_->slave_path();
  if (!options_.link_path.empty()) ReplaceSymlink(current_slave_path_, options_.link_path);
  Log("pty " + current_slave_path_ +
      (options_.link_path.empty() ? "" : " <- " + options_.link_path));
  if (on_device_path) on_device_path(current_slave_path_);
}

void Emulator::ClosePty() {
  if (!pty_) return;
  if (!options_.link_path.empty()) RemoveSymlinkIfTarget(current_slave_path_, options_.link_path);
  pty_.reset();
  output_queue_.clear();
  output_head_sent_ = 0;
  output_bytes_ = 0;
}

void Emulator::OpenControlSocket() {
  const std::string& path = options_.control_socket_path;
  struct stat st {};
  if (lstat(path.c_str(), &st) == 0) {
    if (!S_ISSOCK(st.st_mode)) throw std::runtime_error(path + ": exists and is not a socket");
    unlink(path.c_str());  // stale socket of a previous run
  }
  listen_fd_ = socket(AF_UNIX, SOCK_STREAM | SOCK_CLOEXEC | SOCK_NONBLOCK, 0);
  if (listen_fd_ < 0) throw std::runtime_error(std::string("socket: ") + std::strerror(errno));
  sockaddr_un addr{};
  addr.sun_family = AF_UNIX;
  std::strncpy(addr.sun_path, path.c_str(), sizeof(addr.sun_path) - 1);
  if (bind(listen_fd_, reinterpret_cast<sockaddr*>(&addr), sizeof(addr)) != 0 ||
      listen(listen_fd_, 8) != 0) {
    const std::string error = std::strerror(errno);
    close(listen_fd_);
    listen_fd_ = -1;
    throw std::runtime_error(path + ": cannot listen: " + error);
  }
}

void Emulator::RequestStop() {
  stop_.store(true);  // (no lock: async-signal-safe)
  const char byte = 1;
  [[maybe_unused]] const ssize_t n = write(wake_pipe_[1], &byte, 1);
}

void Emulator::Run() {
  if (!pty_ && reconnect_at_s_ < 0) Start();
  while (!stop_.load()) {
    double now = Now();
    if (options_.run_seconds > 0 && now >= options_.run_seconds) break;
    if (reconnect_at_s_ >= 0 && now >= reconnect_at_s_) {
      try {
        OpenPty();
        reconnect_at_s_ = -1;
        ++stats_.reconnects;
        next_cycle_s_ = now;
      } catch (const std::runtime_error& e) {
        // Keep serving the control socket and try again, as a re-plugged adapter would reappear.
        Log(std::string("reconnect failed, retrying in 1 s: ") + e.what());
        reconnect_at_s_ = now + 1.0;
      }
    }
    const bool stalled = stall_until_s_ > now;
    if (!stalled && stall_until_s_ >= 0) {
      stall_until_s_ = -1;
      next_cycle_s_ = now;
      line_start_pending_ = true;  // what waited goes out at the line rate from now, no burst
      if (power_off_) {
        // Power on: what the host sent meanwhile was never received; power-up state.
        power_off_ = false;
        if (pty_) {
          char drain[1024];
          while (read(pty_->master_fd(), drain, sizeof(drain)) > 0) {
          }
        }
        device_.Reinitialise();
        Log("power on");
      } else {
        Log("stall over");
      }
    }

    // Wait for host bytes, control traffic, the next record or the end of a fault.
    double wake_at = now + 1.0;
    // (No active station: nothing is scheduled, and waking at a past cycle would spin.)
    if (pty_ && !stalled && device_.streaming() && !device_.ActiveStations().empty()) {
      wake_at = std::min(wake_at, next_cycle_s_);
    }
    // The device reads the stylus switch every cycle while it acts on it (point/track mode).
    if (pty_ && !stalled && device_.station(1).stylus_function == 1) {
      wake_at = std::min(wake_at, now + 1.0 / options_.update_rate_hz);
    }
    const double output_due = NextOutputDue(now);
    const bool line_free = output_due <= now;
    if (pty_ && !stalled && !output_queue_.empty()) wake_at = std::min(wake_at, output_due);
    if (stalled) wake_at = std::min(wake_at, stall_until_s_);
    if (reconnect_at_s_ >= 0) wake_at = std::min(wake_at, reconnect_at_s_);
    if (options_.run_seconds > 0) wake_at = std::min(wake_at, options_.run_seconds);
    const int timeout_ms = std::max(0, static_cast<int>(std::ceil((wake_at - now) * 1000.0)));

    std::vector<pollfd> fds;
    fds.push_back({wake_pipe_[0], POLLIN, 0});
    const int pty_index = (pty_ && !stalled) ? static_cast<int>(fds.size()) : -1;
    if (pty_index >= 0) {
      fds.push_back(
          {pty_->master_fd(),
           static_cast<short>(POLLIN | (output_queue_.empty() || !line_free ? 0 : POLLOUT)), 0});
    }
    const int listen_index = listen_fd_ >= 0 ? static_cast<int>(fds.size()) : -1;
    if (listen_index >= 0) fds.push_back({listen_fd_, POLLIN, 0});
    const size_t first_client = fds.size();
    for (const ControlClient& c : clients_) {
      fds.push_back({c.fd, static_cast<short>(POLLIN | (c.output.empty() ? 0 : POLLOUT)), 0});
    }
    if (poll(fds.data(), fds.size(), timeout_ms) < 0 && errno != EINTR) {
      throw std::runtime_error(std::string("poll: ") + std::strerror(errno));
    }
    if (fds[0].revents & POLLIN) {
      char drain[64];
      while (read(wake_pipe_[0], drain, sizeof(drain)) > 0) {
      }
    }
    now = Now();
    if (pty_index >= 0 && pty_ && (fds[pty_index].revents & POLLIN)) ReadHost(now);
    if (pty_ && stall_until_s_ < 0) {
      SampleStylus(now);
      StreamRecords(now);
      WriteHost(now);
    }
    std::vector<short> client_revents;
    for (size_t i = first_client; i < fds.size(); ++i) client_revents.push_back(fds[i].revents);
    ServiceControl(listen_index >= 0 ? fds[listen_index].revents : 0, client_revents);
    ServicePosted();
  }
  ClosePty();
  // Callers still waiting get an answer instead of a timeout.
  std::lock_guard<std::mutex> lock(posted_mutex_);
  for (auto& [line, reply] : posted_) reply.set_value("error: emulator not running");
  posted_.clear();
}

void Emulator::ServicePosted() {
  std::deque<std::pair<std::string, std::promise<std::string>>> posted;
  {
    std::lock_guard<std::mutex> lock(posted_mutex_);
    posted.swap(posted_);
  }
  for (auto& [line, reply] : posted) reply.set_value(HandleControlLine(line));
}

std::string Emulator::Control(const std::string& line) {
  std::future<std::string> reply;
  {
    std::lock_guard<std::mutex> lock(posted_mutex_);
    if (stop_.load()) return "error: emulator not running";
    posted_.emplace_back(line, std::promise<std::string>());
    reply = posted_.back().second.get_future();
  }
  const char byte = 2;
  [[maybe_unused]] const ssize_t n = write(wake_pipe_[1], &byte, 1);
  if (reply.wait_for(std::chrono::seconds(5)) != std::future_status::ready) {
    return "error: emulator not running";
  }
  return reply.get();
}

BackgroundEmulator::BackgroundEmulator(EmulatorOptions options, std::unique_ptr<PoseSource> source,
                                       std::unique_ptr<MeasurementModel> model)
    : source_(std::make_unique<ControlledPoseSource>(std::move(source))),
      model_(model ? std::move(model) : std::make_unique<PerfectMeasurement>()) {
  emulator_ = std::make_unique<Emulator>(std::move(options), source_.get(), model_.get());
  emulator_->on_device_path = [this](const std::string& path) {
    if (initial_device_path_.empty()) initial_device_path_ = path;
  };
  emulator_->Start();
  thread_ = std::thread([this] { emulator_->Run(); });
}

BackgroundEmulator::~BackgroundEmulator() {
  emulator_->RequestStop();
  thread_.join();
}

void Emulator::ReadHost(double now) {
  char buffer[1024];
  while (pty_) {
    const ssize_t n = read(pty_->master_fd(), buffer, sizeof(buffer));
    if (n <= 0) break;  // EAGAIN: nothing more; EIO cannot happen while our slave fd is open
    stats_.bytes_received += n;
    const bool was_streaming = device_.streaming();
    std::string reply = device_.Receive(std::string_view(buffer, n), [&](int station) {
      return Measure(*source_, *model_, station, now);
    });
    if (was_streaming && !device_.streaming()) DropUnstartedRecords();
    if (!reply.empty()) Enqueue(std::move(reply));
    for (const std::string& line : device_.TakeLog()) Log(line);
  }
}

double Emulator::NextOutputDue(double now) const {
  if (output_queue_.empty()) return std::numeric_limits<double>::infinity();
  if (options_.baud <= 0 || line_start_pending_) return now;
  // The next few bytes (or the rest of a short item): one wake-up per chunk, not per byte.
  const size_t unsent = output_queue_.front().bytes.size() - output_head_sent_;
  return line_busy_until_s_ + std::min(unsent, kOutputChunkBytes) * 10.0 / options_.baud;
}

void Emulator::WriteHost(double now) {
  const double seconds_per_byte = options_.baud > 0 ? 10.0 / options_.baud : 0.0;
  while (pty_ && !output_queue_.empty()) {
    const std::string& head = output_queue_.front().bytes;
    const size_t unsent = head.size() - output_head_sent_;
    // A byte reaches the host when its last bit has: the bytes of an item go out one after the
    // other from the moment the line is free, never the whole item at the start of its line time.
    // Output queued a little after the line freed (poll has millisecond resolution) continues the
    // line's timeline, so the long-run throughput is the line's; a longer idle line starts now.
    if (line_start_pending_) {
      if (line_busy_until_s_ < now - kLineSlackS) line_busy_until_s_ = now;
      line_start_pending_ = false;
    }
    size_t due = unsent;
    if (seconds_per_byte > 0) {
      const double elapsed = now - line_busy_until_s_;
      due = elapsed <= 0 ? 0
                         : std::min(unsent, static_cast<size_t>(elapsed / seconds_per_byte + 1e-9));
      if (due == 0) break;  // the wire is still busy with the bytes before
    }
    ssize_t n = write(pty_->master_fd(), head.data() + output_head_sent_, due);
    if (n < 0 && errno != EAGAIN && errno != EWOULDBLOCK) break;
    if (n <= 0) {
      // The host's input buffer is full (nobody has the port open, or the host stopped reading).
      // The device does not wait: the bytes go over the wire and are lost, as on a real serial
      // line. Keeping them would hand a host that reopens the port seconds-old records.
      n = static_cast<ssize_t>(due);
      if (!output_queue_.front().lost) ++stats_.items_lost;
      output_queue_.front().lost = true;
    }
    line_busy_until_s_ += n * seconds_per_byte;
    output_head_sent_ += n;
    output_bytes_ -= n;
    if (output_head_sent_ == head.size()) {
      output_queue_.pop_front();
      output_head_sent_ = 0;
    }
  }
}

void Emulator::Enqueue(std::string bytes, bool stream_record) {
  if (output_queue_.empty()) line_start_pending_ = true;  // the line was idle
  output_bytes_ += bytes.size();
  output_queue_.push_back({std::move(bytes), stream_record});
}

void Emulator::DropUnstartedRecords() {
  for (size_t i = output_head_sent_ > 0 ? 1 : 0; i < output_queue_.size();) {
    if (!output_queue_[i].stream_record) {
      ++i;
      continue;
    }
    output_bytes_ -= output_queue_[i].bytes.size();
    output_queue_.erase(output_queue_.begin() + static_cast<std::ptrdiff_t>(i));
  }
}

void Emulator::SampleStylus(double now) {
  const bool was_streaming = device_.streaming();
  std::string reply = device_.StylusSwitch(source_->StylusButton(1, now), [&](int station) {
    return Measure(*source_, *model_, station, now);
  });
  if (was_streaming && !device_.streaming()) DropUnstartedRecords();
  if (!reply.empty()) Enqueue(std::move(reply));
  for (const std::string& line : device_.TakeLog()) Log(line);
}

void Emulator::StreamRecords(double now) {
  const bool continuous = device_.streaming();
  if (continuous && !was_continuous_) {
    // Streaming starts now, with the first active station.
    next_cycle_s_ = now;
    round_robin_ = 0;
  }
  was_continuous_ = continuous;
  if (!continuous) return;
  const std::vector<int> active = device_.ActiveStations();
  if (active.empty()) {
    next_cycle_s_ = now;  // a station switched on again starts a fresh schedule, not a burst
    return;
  }
  if (now - next_cycle_s_ > kMaxScheduleLagS) next_cycle_s_ = now;
  const double period = 1.0 / options_.update_rate_hz;
  const double seconds_per_byte = options_.baud > 0 ? 10.0 / options_.baud : 0.0;
  while (next_cycle_s_ <= now) {
    // A line slower than the records: the device measures only when the line can start its
    // output within one cycle, so every record the host gets is fresh (the output rate drops to
    // what the line carries). Queuing them instead would delay every record by the whole queue:
    // 4 s at 9600 baud.
    const double line_free_at =
        std::max(line_busy_until_s_, next_cycle_s_) + output_bytes_ * seconds_per_byte;
    if (line_free_at > next_cycle_s_ + period) {
      stats_.records_dropped += options_.divide_rate_among_stations ? 1 : active.size();
      next_cycle_s_ += period;
      continue;
    }
    if (options_.divide_rate_among_stations) {
      QueueRecord(active[round_robin_ % active.size()], next_cycle_s_);
      round_robin_ = (round_robin_ + 1) % active.size();
    } else {
      for (const int s : active) QueueRecord(s, next_cycle_s_);
    }
    next_cycle_s_ += period;
  }
}

void Emulator::QueueRecord(int station, double t_s) {
  std::string record = device_.FormatRecord(station, Measure(*source_, *model_, station, t_s));
  if (output_bytes_ + record.size() > options_.max_pending_output_bytes) {
    ++stats_.records_dropped;
    return;
  }
  if (truncate_next_ != 0) {
    const size_t keep = truncate_next_ < 0 ? record.size() / 2
                                           : std::min<size_t>(truncate_next_, record.size() - 1);
    Log("fault: record of station " + std::to_string(station) + " truncated to " +
        std::to_string(keep) + " of " + std::to_string(record.size()) + " bytes");
    record.resize(keep);
    truncate_next_ = 0;
  } else {
    ++stats_.records_sent;
  }
  Enqueue(std::move(record), /*stream_record=*/true);
}

void Emulator::ServiceControl(short revents_listen, const std::vector<short>& revents_clients) {
  // Existing clients first (indices match revents_clients), then accept new ones.
  for (size_t i = 0; i < revents_clients.size() && i < clients_.size(); ++i) {
    ControlClient& c = clients_[i];
    bool closed = (revents_clients[i] & (POLLERR | POLLNVAL)) != 0;
    if (revents_clients[i] & (POLLIN | POLLHUP)) {
      char buffer[1024];
      const ssize_t n = read(c.fd, buffer, sizeof(buffer));
      if (n > 0) {
        c.input.append(buffer, n);
      } else if (n == 0 || (errno != EAGAIN && errno != EINTR)) {
        closed = true;
      }
      size_t eol;
      while ((eol = c.input.find('\n')) != std::string::npos) {
        std::string line = c.input.substr(0, eol);
        c.input.erase(0, eol + 1);
        if (!line.empty() && line.back() == '\r') line.pop_back();
        if (line.find_first_not_of(" \t") == std::string::npos) continue;
        c.output += HandleControlLine(line) + "\n";
      }
      if (c.input.size() > kMaxControlLine) {
        c.output += "error: line too long\n";
        c.input.clear();
      }
    }
    if (!c.output.empty()) {
      const ssize_t n = send(c.fd, c.output.data(), c.output.size(), MSG_NOSIGNAL);
      if (n > 0) c.output.erase(0, n);
      if (n < 0 && errno != EAGAIN) closed = true;
    }
    if (closed) {
      close(c.fd);
      c.fd = -1;
    }
  }
  clients_.erase(std::remove_if(clients_.begin(), clients_.end(),
                                [](const ControlClient& c) { return c.fd < 0; }),
                 clients_.end());
  if (revents_listen & POLLIN) {
    while (true) {
      const int fd = accept4(listen_fd_, nullptr, nullptr, SOCK_CLOEXEC | SOCK_NONBLOCK);
      if (fd < 0) break;
      SetNonBlocking(fd);
      clients_.push_back({fd, "", ""});
    }
  }
}

std::string Emulator::StatusLine() {
  std::ostringstream ss;
  ss << "ok path=" << (pty_ ? current_slave_path_ : std::string("-"))
     << " connected=" << (pty_ ? 1 : 0) << " stalled=" << (stall_until_s_ >= 0 ? 1 : 0)
     << " power=" << (power_off_ ? "off" : "on") << " continuous=" << device_.continuous()
     << " format=" << (device_.binary() ? "binary" : "ascii")
     << " units=" << (device_.metric() ? "cm" : "inches") << " active=";
  const std::vector<int> active = device_.ActiveStations();
  for (size_t i = 0; i < active.size(); ++i) ss << (i ? "," : "") << active[i];
  ss << " records=" << stats_.records_sent << " dropped=" << stats_.records_dropped
     << " lost=" << stats_.items_lost << " received=" << stats_.bytes_received
     << " reconnects=" << stats_.reconnects
     << " saved=" << (device_.has_saved_configuration() ? 1 : 0);
  char t[32];
  std::snprintf(t, sizeof(t), " t=%.3f", Now());
  ss << t;
  return ss.str();
}

std::string Emulator::HandleControlLine(const std::string& line) {
  ControlCommand command;
  try {
    command = ParseControlCommand(line);
  } catch (const std::invalid_argument& e) {
    return std::string("error: ") + e.what();
  }
  const double now = Now();
  struct Visitor {
    Emulator* e;
    double now;
    std::string operator()(const MoveCommand& c) {
      auto* controlled = dynamic_cast<ControlledPoseSource*>(e->source_);
      if (!controlled) return "error: this emulator's pose source cannot be moved";
      controlled->Move(c.station, c.transmitter_from_receiver);
      return "ok";
    }
    std::string operator()(const ReleaseCommand& c) {
      auto* controlled = dynamic_cast<ControlledPoseSource*>(e->source_);
      if (!controlled) return "error: this emulator's pose source cannot be moved";
      controlled->Release(c.station);
      return "ok";
    }
    std::string operator()(const ButtonCommand& c) {
      auto* controlled = dynamic_cast<ControlledPoseSource*>(e->source_);
      if (!controlled) return "error: this emulator's pose source has no controllable button";
      controlled->SetButton(c.station, c.pressed);
      return "ok";
    }
    std::string operator()(const GarbageFault& f) {
      if (!e->pty_) return "error: disconnected";
      std::string bytes(f.num_bytes, '\0');
      for (char& b : bytes) b = static_cast<char>(e->rng_() & 0xff);
      e->Enqueue(std::move(bytes));  // between two records, whatever the output backlog
      e->Log("fault: " + std::to_string(f.num_bytes) + " garbage bytes");
      return "ok";
    }
    std::string operator()(const StallFault& f) {
      e->stall_until_s_ = now + f.seconds;
      e->Log("fault: stall for " + std::to_string(f.seconds) + " s");
      return "ok";
    }
    std::string operator()(const PowerCycleFault& f) {
      e->stall_until_s_ = now + f.seconds;
      e->power_off_ = true;
      // Whatever had not left the device is lost, a record on the wire included.
      e->output_queue_.clear();
      e->output_head_sent_ = 0;
      e->output_bytes_ = 0;
      e->Log("fault: power off for " + std::to_string(f.seconds) + " s");
      return "ok";
    }
    std::string operator()(const DisconnectFault& f) {
      if (!e->pty_) return "error: already disconnected";
      e->Log("fault: disconnect " + e->current_slave_path_ + " for " + std::to_string(f.seconds) +
             " s");
      e->ClosePty();
      e->reconnect_at_s_ = now + f.seconds;
      return "ok";
    }
    std::string operator()(const TruncateFault& f) {
      e->truncate_next_ = f.keep_bytes;
      return "ok";
    }
    std::string operator()(const StatusCommand&) { return e->StatusLine(); }
    std::string operator()(const HelpCommand&) {
      return "ok commands: move STATION x y z qw qx qy qz | release STATION | button STATION 0|1 | "
             "fault garbage N | fault stall SECONDS | fault powercycle SECONDS | "
             "fault disconnect SECONDS | "
             "fault truncate [BYTES] | status";
    }
  };
  return std::visit(Visitor{this, now}, command);
}

}  // namespace trackcal::emulator
