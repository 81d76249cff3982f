// Server-side devices: what turns a tracker's reports into VRPN messages.
//
// - TrackerDevice: one physical tracker served as its corrected device under the configured name
//   and, on request, its raw device under a second name (so a validation run records both live).
//   The correction is swappable at any time (calibration reload) without touching the clients.
//   Quaternions are scaled to unit length before they are corrected and served.
// - NullTracker: identity (or fixed) poses at a fixed rate, like vrpn_Tracker_NULL; for tests,
//   demos and replaying the reference transcripts.
// - StreamRecorder: writes raw and corrected reports to CSV files in the tracker stream format
//   (time,sensor,x,y,z,qw,qx,qy,qz; sensor is the 1-based station number) for later validation.

#pragma once

#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <filesystem>
#include <fstream>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <span>
#include <string>
#include <thread>
#include <vector>

#include "core/correction.h"
#include "core/pose.h"
#include "vrpn_server/protocol/wire.h"
#include "vrpn_server/server/server.h"

namespace trackcal::vrpn {

// A corrected pose and whether the correction had to leave its calibrated domain.
struct CorrectionResult {
  Rigid3d pose;
  bool extrapolated = false;  // outside the calibrated volume (clamped/faded)
  // A physical model's inverse: not converged (a bounded best guess) or ambiguous (another true
  // pose gives the same report) make the pose "unresolved".
  CorrectionStatus status = CorrectionStatus::kConverged;
};

// The per-report steps of TrackerDevice::OnReports around the correction (public so that
// bench/bench_correction times the server's per-report path with the code the server runs).
// The pose with its rotation scaled to a unit quaternion; a quaternion of no finite, positive norm
// is returned as it is (IsFinite then refuses it).
Rigid3d WithUnitRotation(const Rigid3d& pose);
// Whether a pose can be served: finite position and quaternion, and a non-zero quaternion.
bool IsFinite(const Rigid3d& pose);

// Maps a reported pose (transmitter_from_receiver) to the corrected pose. Apply may be called from
// several device threads at once; implementations must be immutable after construction.
class PoseCorrector {
 public:
  virtual ~PoseCorrector() = default;
  virtual Rigid3d Correct(const Rigid3d& reported) const = 0;
  // The corrected pose with its extrapolation flag; correctors that cannot extrapolate keep the
  // default (never flagged).
  virtual CorrectionResult CorrectWithFlag(const Rigid3d& reported) const {
    return {Correct(reported), false};
  }
  // One line for logs, e.g. "calib.json (polynomial degree 4)".
  virtual std::string Describe() const = 0;
  // The receiver the correction was fitted for, as a capture's 1-based `sensor` column (Fastrak
  // station n is n, VRPN sensor n - 1); 0: not recorded (any sensor).
  virtual int FittedSensor() const { return 0; }
  // The box of reported positions the correction was fitted on (transmitter frame, metres), if it
  // has one: {min, max}.
  virtual std::optional<std::pair<Eigen::Vector3d, Eigen::Vector3d>> FittedBox() const {
    return std::nullopt;
  }
};

// Appends reports of one device to <dir>/<device>_tracker_stream.csv. The file is written as
// "<name>.partial" and renamed when the recorder closes, so a complete file never appears half
// written; an existing file is never overwritten (the constructor throws). A missing <dir> is made
// (one level, like mkdir).
class StreamRecorder {
 public:
  StreamRecorder(const std::filesystem::path& dir, const std::string& device_name);
  // Throws std::invalid_argument if `device_name`'s recording (or its .partial) exists in `dir`,
  // as the constructor does, without creating anything: a server checks every recording before it
  // creates the first, so that a refused start leaves no header-only recording behind.
  static void CheckNotRecorded(const std::filesystem::path& dir, const std::string& device_name);
  ~StreamRecorder();
  // A report whose time is not after its sensor's latest written one (a repeat, or a clock stepped
  // back) is left out and counted: the first is logged, and the count when the recording closes.
  void Write(int sensor, const Rigid3d& pose, Timestamp time);
  void Close();
  std::uint64_t left_out() const;
  const std::filesystem::path& path() const { return final_path_; }

 private:
  mutable std::mutex mutex_;
  std::filesystem::path final_path_;
  std::filesystem::path partial_path_;
  std::ofstream out_;
  std::map<int, std::int64_t> latest_us_;  // sensor -> latest written time [us]
  std::uint64_t left_out_ = 0;
};

// One report of a source: 0-based sensor, pose as the tracker reported it, header timestamp.
struct SensorReport {
  int sensor = 0;
  Rigid3d transmitter_from_receiver;
  Timestamp time;
};

class TrackerDevice {
 public:
  // `tracker` is the catalog index of the corrected device; `raw_tracker` that of the raw one.
  TrackerDevice(VrpnServer* server, int tracker, std::optional<int> raw_tracker);

  // Replaces the correction (nullptr: serve reports unchanged). Thread-safe; takes effect with the
  // next report.
  void SetCorrector(std::shared_ptr<const PoseCorrector> corrector);
  std::shared_ptr<const PoseCorrector> corrector() const;
  // The correction of one sensor (0-based), used for its reports instead of SetCorrector's (a
  // calibration fitted for one receiver: its sensor offset and gains are not another receiver's);
  // nullptr: that sensor falls back to SetCorrector's again. Thread-safe.
  void SetSensorCorrector(int sensor, std::shared_ptr<const PoseCorrector> corrector);
  // Record raw and corrected streams (either may be null).
  void SetRecorders(std::unique_ptr<StreamRecorder> raw, std::unique_ptr<StreamRecorder> corrected);

  // Called by the driver thread for every report: publishes raw (if served) and corrected poses.
  void OnReport(int sensor, const Rigid3d& reported, Timestamp time);
  // The reports that arrived together (one serial read): corrected, then published as one batch
  // (VrpnServer::PublishPoses: one send per client for all of them).
  void OnReports(std::span<const SensorReport> reports);
  // Device status text for clients of both names.
  void OnText(TextSeverity severity, const std::string& text);
  // Where the extrapolation notice also goes (the server's log); optional.
  void SetLog(std::function<void(const std::string&)> log);

  // VRPN's Pos_Quat has no field for the correction's extrapolated flag, so the device counts the
  // corrected poses that were extrapolated (outside the calibrated volume) and, at most once per
  // `kExtrapolationNoticeInterval`, logs and sends a text to the corrected name's clients with the
  // count since the last notice and the total.
  std::uint64_t extrapolated_poses() const { return extrapolated_total_.load(); }
  // Every pose served corrected (the denominator of the two counts).
  std::uint64_t corrected_poses() const { return corrected_total_.load(); }
  // Likewise the corrected poses whose model inverse was not converged or ambiguous (counted and
  // reported in the same notice).
  std::uint64_t unresolved_poses() const { return unresolved_total_.load(); }
  // Corrections that gave a pose that is not finite (NaN or infinite) for a finite report: not
  // served (nor recorded); the first one of each correction is told to the corrected name's
  // clients and the log at error severity, the others only counted here.
  std::uint64_t non_finite_poses() const { return non_finite_total_.load(); }
  // Reports that are not a pose (not finite, or a zero quaternion; a pass-through source forwards
  // what its server sent): served under neither name, nor corrected or recorded; the first one is
  // told to the clients of both names and the log, the others only counted here.
  std::uint64_t bad_reports() const { return bad_reports_total_.load(); }
  static constexpr std::chrono::steady_clock::duration kExtrapolationNoticeInterval =
      std::chrono::seconds(1);
  int tracker() const { return tracker_; }
  std::optional<int> raw_tracker() const { return raw_tracker_; }

 private:
  VrpnServer* server_;
  int tracker_;
  std::optional<int> raw_tracker_;
  mutable std::mutex mutex_;
  std::shared_ptr<const PoseCorrector> corrector_;
  std::vector<std::shared_ptr<const PoseCorrector>>
      sensor_correctors_;  // by sensor; null: corrector_
  std::unique_ptr<StreamRecorder> raw_recorder_;
  std::unique_ptr<StreamRecorder> corrected_recorder_;
  std::function<void(const std::string&)> log_;
  std::atomic<std::uint64_t> corrected_total_{0};
  std::atomic<std::uint64_t> extrapolated_total_{0};
  std::atomic<std::uint64_t> unresolved_total_{0};
  std::atomic<std::uint64_t> non_finite_total_{0};
  bool non_finite_told_ = false;  // guarded by mutex_; reset when the correction is replaced
  std::atomic<std::uint64_t> bad_reports_total_{0};
  bool bad_report_told_ = false;  // guarded by mutex_
  // Guarded by mutex_: poses extrapolated / unresolved since the last notice, and when that notice
  // went out.
  std::uint64_t extrapolated_pending_ = 0;
  std::uint64_t unresolved_pending_ = 0;
  std::chrono::steady_clock::time_point last_notice_{};
  void CountExtrapolated(std::uint64_t n, std::uint64_t unresolved = 0);
};

// Reports `pose` for every sensor at a fixed rate from its own thread (vrpn_Tracker_NULL reports
// identity). Rate 0 never reports.
class NullTracker {
 public:
  using ReportFunction = std::function<void(int sensor, const Rigid3d& pose, Timestamp time)>;
  NullTracker(ReportFunction report, int num_sensors, double rate_hz, Rigid3d pose = Rigid3d());
  ~NullTracker();
  // Throws std::invalid_argument for a sensor count below 1 or a rate outside [0, 10000] Hz.
  static void CheckOptions(int num_sensors, double rate_hz);
  void Start();
  void Stop();

 private:
  ReportFunction report_;
  int num_sensors_;
  double rate_hz_;
  Rigid3d pose_;
  std::thread thread_;
  std::mutex mutex_;
  std::condition_variable cv_;
  bool stop_ = false;
};

}  // namespace trackcal::vrpn
