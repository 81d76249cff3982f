#include "vrpn_server/server/devices.h"

#include <fcntl.h>
#include <stdio.h>
#include <unistd.h>

#include <cerrno>
#include <chrono>
#include <cmath>
#include <cstring>
#include <iomanip>
#include <sstream>
#include <stdexcept>
#include <system_error>

namespace trackcal::vrpn {

namespace {

// A time in microseconds as seconds with six decimals ("-0.250000").
std::string FormatSeconds(std::int64_t us) {
  const std::uint64_t magnitude =
      us < 0 ? static_cast<std::uint64_t>(-us) : static_cast<std::uint64_t>(us);
  std::ostringstream text;
  text << (us < 0 ? "-" : "") << magnitude / 1'000'000 << '.' << std::setw(6) << std::setfill('0')
       << magnitude % 1'000'000;
  return text.str();
}

}  // namespace

StreamRecorder::StreamRecorder(const std::filesystem::path& dir, const std::string& device_name) {
  // The folder is made like `mkdir DIR` (one level; the parent must exist), as `trackcal record -o`
  // makes its own. Recorders of several trackers share it: an existing folder is used as it is.
  std::error_code ec;
  if (!std::filesystem::create_directory(dir, ec) && ec) {
    std::error_code status_ec;
    const auto status = std::filesystem::symlink_status(dir, status_ec);
    if (std::filesystem::exists(status)) {
      throw std::invalid_argument("--record " + dir.string() + ": not a directory");
    }
    if (ec == std::errc::no_such_file_or_directory || ec == std::errc::not_a_directory) {
      // Only DIR itself is made: a mistyped parent should not grow a new tree of folders.
      const std::filesystem::path parent = dir.parent_path();
      throw std::invalid_argument("--record " + dir.string() + ": does not exist, and " +
                                  (ec == std::errc::not_a_directory
                                       ? "a folder above it is not a directory"
                                       : "neither does " + parent.string()) +
                                  " (the server makes only the last folder, like mkdir)");
    }
    throw std::invalid_argument("--record " + dir.string() + ": cannot create: " + ec.message());
  }
  CheckNotRecorded(dir, device_name);
  final_path_ = dir / (device_name + "_tracker_stream.csv");
  partial_path_ = final_path_;
  partial_path_ += ".partial";
  // Created exclusively, so that a second server recording the same device into the same folder
  // (started between the check above and here) cannot truncate this one's recording.
  const int fd = ::open(partial_path_.c_str(), O_WRONLY | O_CREAT | O_EXCL | O_CLOEXEC, 0666);
  if (fd < 0) {
    if (errno == EEXIST) {
      throw std::invalid_argument("--record: " + partial_path_.string() +
                                  " already exists; recordings are never overwritten");
    }
    throw std::runtime_error(partial_path_.string() + ": cannot create: " + std::strerror(errno));
  }
  ::close(fd);
  out_.open(partial_path_);
  if (!out_) throw std::runtime_error(partial_path_.string() + ": cannot open for writing");
  out_ << "time,sensor,x,y,z,qw,qx,qy,qz\n" << std::setprecision(17);
}

void StreamRecorder::CheckNotRecorded(const std::filesystem::path& dir,
                                      const std::string& device_name) {
  const std::filesystem::path final_path = dir / (device_name + "_tracker_stream.csv");
  std::filesystem::path partial_path = final_path;
  partial_path += ".partial";
  for (const auto& path : {final_path, partial_path}) {
    std::error_code ec;
    if (std::filesystem::exists(std::filesystem::symlink_status(path, ec))) {
      throw std::invalid_argument("--record: " + path.string() +
                                  " already exists; recordings are never overwritten");
    }
  }
}

StreamRecorder::~StreamRecorder() { Close(); }

void StreamRecorder::Write(int sensor, const Rigid3d& pose, Timestamp time) {
  std::lock_guard<std::mutex> lock(mutex_);
  if (!out_.is_open()) return;
  const auto& t = pose.translation;
  const auto& q = pose.rotation;
  // Normalised: a pass-through forwards its upstream's tv_usec as it came, which may be 1,000,000
  // or more, or negative (setw(6) wrote 12 s + 1,500,000 us as 12.1500000).
  const std::int64_t us = time.Microseconds();
  // One sample per sensor and time, or the recording saves and then fails to load. Not after the
  // sensor's latest time (a source clock that did not tick or stepped back, a report sent twice):
  // left out and counted. Only the latest is kept, so memory does not grow with the recording
  // (which runs as long as the server); a clock stepped back loses the reports until it is past
  // the latest again, said by the log line and the count.
  const auto [latest, first] = latest_us_.try_emplace(sensor, us);
  if (!first) {
    if (us <= latest->second) {
      if (left_out_++ == 0) {
        LogToStderr("recording " + partial_path_.filename().string() + ": sensor " +
                    std::to_string(sensor + 1) + "'s report at " + FormatSeconds(us) +
                    " s is not after its latest recorded time " + FormatSeconds(latest->second) +
                    " s (one sample per sensor and time): left out, as the next ones that are not "
                    "(counted when the recording ends)");
      }
      return;
    }
    latest->second = us;
  }
  out_ << FormatSeconds(us) << ',' << sensor + 1 << ',' << t.x() << ',' << t.y() << ',' << t.z()
       << ',' << q.w() << ',' << q.x() << ',' << q.y() << ',' << q.z() << '\n';
}

std::uint64_t StreamRecorder::left_out() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return left_out_;
}

void StreamRecorder::Close() {
  std::lock_guard<std::mutex> lock(mutex_);
  if (!out_.is_open()) return;
  out_.close();
  if (left_out_ > 0) {
    LogToStderr("recording " + final_path_.filename().string() + ": " + std::to_string(left_out_) +
                " report" + (left_out_ > 1 ? "s" : "") +
                " left out, not after their sensor's latest recorded time");
  }
  const bool written = !out_.fail();
  // Never replaces a file that appeared under the final name while recording: renameat2's
  // RENAME_NOREPLACE, or a hard link where the file system lacks it. Otherwise (or on a write
  // error) the recording stays in the .partial file, and stderr says so.
  std::string failure;
  if (!written) {
    failure = "a write failed (disk full?)";
  } else if (::renameat2(AT_FDCWD, partial_path_.c_str(), AT_FDCWD, final_path_.c_str(),
                         RENAME_NOREPLACE) != 0) {
    if (errno == EINVAL || errno == ENOSYS) {
      if (::link(partial_path_.c_str(), final_path_.c_str()) == 0) {
        ::unlink(partial_path_.c_str());
      } else {
        failure = std::strerror(errno);
      }
    } else {
      failure = std::strerror(errno);
    }
  }
  if (!failure.empty()) {
    // Through the log's queue, after the lines before it ("stopping"): a direct write to a stderr
    // nobody reads blocked the stopping server for ever, before the other recorders were closed.
    LogToStderr("recording kept as " + partial_path_.string() + ", not moved to " +
                final_path_.string() + ": " + failure);
  }
}

TrackerDevice::TrackerDevice(VrpnServer* server, int tracker, std::optional<int> raw_tracker)
    : server_(server), tracker_(tracker), raw_tracker_(raw_tracker) {
  if (server_ == nullptr) throw std::invalid_argument("TrackerDevice: server is null");
}

void TrackerDevice::SetCorrector(std::shared_ptr<const PoseCorrector> corrector) {
  std::lock_guard<std::mutex> lock(mutex_);
  corrector_ = std::move(corrector);
  non_finite_told_ = false;  // a new correction's first non-finite pose is told again
}

void TrackerDevice::SetSensorCorrector(int sensor, std::shared_ptr<const PoseCorrector> corrector) {
  if (sensor < 0) throw std::invalid_argument("TrackerDevice: negative sensor");
  std::lock_guard<std::mutex> lock(mutex_);
  if (static_cast<std::size_t>(sensor) >= sensor_correctors_.size()) {
    if (!corrector) return;
    sensor_correctors_.resize(static_cast<std::size_t>(sensor) + 1);
  }
  sensor_correctors_[static_cast<std::size_t>(sensor)] = std::move(corrector);
  non_finite_told_ = false;
}

std::shared_ptr<const PoseCorrector> TrackerDevice::corrector() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return corrector_;
}

void TrackerDevice::SetRecorders(std::unique_ptr<StreamRecorder> raw,
                                 std::unique_ptr<StreamRecorder> corrected) {
  std::lock_guard<std::mutex> lock(mutex_);
  raw_recorder_ = std::move(raw);
  corrected_recorder_ = std::move(corrected);
}

void TrackerDevice::OnReport(int sensor, const Rigid3d& reported, Timestamp time) {
  const SensorReport report{sensor, reported, time};
  OnReports(std::span<const SensorReport>(&report, 1));
}

// VRPN clients take the wire's quaternion as a rotation without normalising it (Unity, the
// reference's vrpn_Tracker_Remote): a Fastrak's record is accepted with |q| off by up to 1e-3 (4
// printed decimals), and a pass-through source sends what it got.
Rigid3d WithUnitRotation(const Rigid3d& pose) {
  const double norm = pose.rotation.norm();
  if (!(norm > 0.0) || !std::isfinite(norm) || norm == 1.0) return pose;
  return Rigid3d(Eigen::Quaterniond(pose.rotation.coeffs() / norm), pose.translation);
}

bool IsFinite(const Rigid3d& pose) {
  return pose.translation.allFinite() && pose.rotation.coeffs().allFinite() &&
         pose.rotation.norm() > 0.0;
}

void TrackerDevice::OnReports(std::span<const SensorReport> reports) {
  if (reports.empty()) return;
  // Reused per device thread: no allocation per report once warm.
  thread_local std::vector<std::shared_ptr<const PoseCorrector>> by_sensor;
  std::shared_ptr<const PoseCorrector> corrector;
  {
    std::lock_guard<std::mutex> lock(mutex_);
    corrector = corrector_;
    by_sensor.assign(sensor_correctors_.begin(), sensor_correctors_.end());
  }
  thread_local std::vector<PoseUpdate> updates;
  thread_local std::vector<Rigid3d> reported, corrected;
  updates.clear();
  reported.clear();
  corrected.clear();
  std::uint64_t extrapolated = 0;
  std::uint64_t unresolved = 0;
  std::uint64_t num_corrected = 0;
  std::uint64_t non_finite = 0, bad_reports = 0;
  std::string first_non_finite, first_bad_report;  // the first of this batch, for the notice
  for (const SensorReport& r : reports) {
    // Served and corrected as a rotation: the correction's q_e * q keeps |q| off by what the
    // report's was.
    reported.push_back(WithUnitRotation(r.transmitter_from_receiver));
    if (!IsFinite(reported.back())) {
      // A pass-through source forwards what its server sent (a Fastrak record with NaN is refused
      // by the driver): it went to raw clients as it was, and a clamping correction could turn it
      // into a finite, wrong pose. Served under neither name, nor corrected.
      if (bad_reports++ == 0) {
        first_bad_report = "sensor " + std::to_string(r.sensor) + ": the source reported " +
                           r.transmitter_from_receiver.ToString();
      }
      corrected.push_back(reported.back());  // kept aligned with `reports`, never written
      continue;
    }
    if (raw_tracker_)
      updates.push_back(PoseUpdate{*raw_tracker_, r.sensor, reported.back(), r.time});
    const PoseCorrector* sensor_corrector = corrector.get();
    if (r.sensor >= 0 && static_cast<std::size_t>(r.sensor) < by_sensor.size() &&
        by_sensor[static_cast<std::size_t>(r.sensor)]) {
      sensor_corrector = by_sensor[static_cast<std::size_t>(r.sensor)].get();
    }
    if (sensor_corrector) {
      const CorrectionResult c = sensor_corrector->CorrectWithFlag(reported.back());
      corrected.push_back(WithUnitRotation(c.pose));
      if (!IsFinite(corrected.back())) {
        // A NaN reaches a client as a pose (Unity moves the object to NaN and it vanishes): not
        // served, and told once, then counted (a line per report would flood the log at 120 Hz).
        if (non_finite++ == 0) {
          first_non_finite = "sensor " + std::to_string(r.sensor) + ": the correction " +
                             sensor_corrector->Describe() + " gave " + corrected.back().ToString() +
                             " for the reported " + reported.back().ToString();
        }
        continue;
      }
      extrapolated += c.extrapolated ? 1 : 0;
      unresolved += c.status != CorrectionStatus::kConverged ? 1 : 0;
      ++num_corrected;
    } else {
      corrected.push_back(reported.back());
    }
    updates.push_back(PoseUpdate{tracker_, r.sensor, corrected.back(), r.time});
  }
  server_->PublishPoses(updates);
  std::lock_guard<std::mutex> lock(mutex_);
  for (std::size_t i = 0; i < reports.size(); ++i) {
    const SensorReport& r = reports[i];
    if (raw_recorder_ && IsFinite(reported[i])) raw_recorder_->Write(r.sensor, reported[i], r.time);
    if (corrected_recorder_ && IsFinite(corrected[i])) {
      corrected_recorder_->Write(r.sensor, corrected[i], r.time);
    }
  }
  by_sensor.clear();  // does not keep a replaced correction alive until the next batch
  corrected_total_ += num_corrected;
  if (non_finite > 0) {
    non_finite_total_ += non_finite;
    if (!non_finite_told_) {
      non_finite_told_ = true;
      const std::string text =
          first_non_finite +
          ", which is not finite: such corrected poses are not served (said once per correction; "
          "the server's status line, on SIGUSR1 and at stop, counts them)";
      server_->PublishText(tracker_, TextSeverity::kError, text);
      if (log_) log_(text);
    }
  }
  if (bad_reports > 0) {
    bad_reports_total_ += bad_reports;
    if (!bad_report_told_) {
      bad_report_told_ = true;
      const std::string text =
          first_bad_report +
          ", which is not a pose (not finite, or a zero quaternion): such reports are served "
          "under neither name (said once; the server's status line, on SIGUSR1 and at stop, "
          "counts them)";
      server_->PublishText(tracker_, TextSeverity::kError, text);
      if (raw_tracker_) server_->PublishText(*raw_tracker_, TextSeverity::kError, text);
      if (log_) log_(text);
    }
  }
  CountExtrapolated(extrapolated, unresolved);
}

void TrackerDevice::SetLog(std::function<void(const std::string&)> log) {
  std::lock_guard<std::mutex> lock(mutex_);
  log_ = std::move(log);
}

// Called with mutex_ held, after every batch (so a pending count goes out with the next report
// after the interval, even when that report is not extrapolated).
void TrackerDevice::CountExtrapolated(std::uint64_t n, std::uint64_t unresolved) {
  if (n > 0) {
    extrapolated_total_ += n;
    extrapolated_pending_ += n;
  }
  if (unresolved > 0) {
    unresolved_total_ += unresolved;
    unresolved_pending_ += unresolved;
  }
  if (extrapolated_pending_ == 0 && unresolved_pending_ == 0) return;
  const auto now = std::chrono::steady_clock::now();
  if (last_notice_ != std::chrono::steady_clock::time_point{} &&
      now - last_notice_ < kExtrapolationNoticeInterval) {
    return;
  }
  const std::string period =
      last_notice_ == std::chrono::steady_clock::time_point{}
          ? std::string("so far")
          : "in the last " +
                std::to_string(
                    std::chrono::duration_cast<std::chrono::milliseconds>(now - last_notice_)
                        .count()) +
                " ms";
  std::string text;
  if (extrapolated_pending_ > 0) {
    text = std::to_string(extrapolated_pending_) +
           " corrected pose(s) extrapolated (outside the calibrated volume) " + period + "; " +
           std::to_string(extrapolated_total_.load()) + " in total";
  }
  if (unresolved_pending_ > 0) {
    if (!text.empty()) text += "; ";
    text += std::to_string(unresolved_pending_) +
            " corrected pose(s) unresolved (the physical model's inverse did not converge or is "
            "ambiguous) " +
            period + "; " + std::to_string(unresolved_total_.load()) + " in total";
  }
  last_notice_ = now;
  extrapolated_pending_ = 0;
  unresolved_pending_ = 0;
  server_->PublishText(tracker_, TextSeverity::kWarning, text);
  if (log_) log_(text);
}

void TrackerDevice::OnText(TextSeverity severity, const std::string& text) {
  server_->PublishText(tracker_, severity, text);
  if (raw_tracker_) server_->PublishText(*raw_tracker_, severity, text);
}

NullTracker::NullTracker(ReportFunction report, int num_sensors, double rate_hz, Rigid3d pose)
    : report_(std::move(report)), num_sensors_(num_sensors), rate_hz_(rate_hz), pose_(pose) {
  if (!report_) throw std::invalid_argument("NullTracker: report function is empty");
  CheckOptions(num_sensors_, rate_hz_);
}

void NullTracker::CheckOptions(int num_sensors, double rate_hz) {
  if (num_sensors < 1) throw std::invalid_argument("NullTracker: num_sensors must be >= 1");
  if (!(rate_hz >= 0) || rate_hz > 10000) {
    throw std::invalid_argument("NullTracker: rate must be in [0, 10000] Hz");
  }
}

NullTracker::~NullTracker() { Stop(); }

void NullTracker::Start() {
  if (rate_hz_ == 0 || thread_.joinable()) return;
  stop_ = false;
  thread_ = std::thread([this] {
    const auto period = std::chrono::duration_cast<std::chrono::steady_clock::duration>(
        std::chrono::duration<double>(1.0 / rate_hz_));
    auto next = std::chrono::steady_clock::now();
    std::unique_lock<std::mutex> lock(mutex_);
    while (!stop_) {
      lock.unlock();
      const Timestamp now = Timestamp::Now();
      for (int s = 0; s < num_sensors_; ++s) report_(s, pose_, now);
      lock.lock();
      next += period;
      cv_.wait_until(lock, next, [this] { return stop_; });
    }
  });
}

void NullTracker::Stop() {
  {
    std::lock_guard<std::mutex> lock(mutex_);
    stop_ = true;
  }
  cv_.notify_all();
  if (thread_.joinable()) thread_.join();
}

}  // namespace trackcal::vrpn
