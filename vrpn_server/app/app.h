// trackcal-server assembled from its pieces, independent of where the device list comes from
// (vrpn.cfg in main.cc, code in tests): report sources (Fastrak driver, NULL tracker, pass-through
// from another VRPN server) feed TrackerDevices, which apply the calibration and publish through
// one VrpnServer. Calibrations are reloaded on request (SIGHUP) or when their file changes; a bad
// new file is rejected with a logged reason and the old correction stays active.

#pragma once

#include <sys/stat.h>

#include <chrono>
#include <filesystem>
#include <functional>
#include <memory>
#include <optional>
#include <span>
#include <string>
#include <vector>

#include "vrpn_server/client/tracker_client.h"
#include "vrpn_server/server/devices.h"
#include "vrpn_server/server/server.h"

namespace trackcal::vrpn {

// What a source reports, on its own thread.
struct SourceCallbacks {
  std::function<void(int sensor, const Rigid3d& transmitter_from_receiver, Timestamp time)> on_pose;
  // Optional: reports that arrived together (one serial read), published as one batch. A source
  // that can batch calls this instead of on_pose when it is set.
  std::function<void(std::span<const SensorReport> reports)> on_poses;
  std::function<void(TextSeverity severity, const std::string& text)> on_text;
  // Stylus/button of a sensor changed.
  std::function<void(int sensor, bool pressed, Timestamp time)> on_button;
};

// A producer of tracker reports (a driver thread, a timer, a network client).
class ReportSource {
 public:
  virtual ~ReportSource() = default;
  // Starts producing; callbacks run on the source's own thread and must return quickly.
  virtual void Start(SourceCallbacks callbacks) = 0;
  // Stops and joins; idempotent.
  virtual void Stop() = 0;
  virtual std::string Describe() const = 0;
  // Called before Start with the server's --realtime-priority (> 0): a source with its own
  // reading thread (the Fastrak driver) runs it at that priority too. Default: ignored.
  virtual void SetRealtimePriority(int /*priority*/) {}
};

// vrpn_Tracker_NULL: `pose` for every sensor at a fixed rate.
std::unique_ptr<ReportSource> MakeNullSource(int num_sensors, double rate_hz, Rigid3d pose = Rigid3d());
// Reports of a tracker served by another VRPN server (any connect mode of VrpnTrackerClient).
std::unique_ptr<ReportSource> MakePassthroughSource(const std::string& vrpn_name);

// Loads a calibration file into a corrector; throws with the reason on a bad file. `outside`
// overrides the file's behaviour outside the calibrated volume ("clamp", "fade" or "linear") and
// `fade_distance` [m] the file's fade_distance, each when set.
using CorrectorLoader = std::function<std::shared_ptr<const PoseCorrector>(
    const std::filesystem::path& path, const std::optional<std::string>& outside,
    const std::optional<double>& fade_distance)>;

// A calibration of one sensor of a tracker (vrpn.cfg's sensor=<n>).
struct SensorCalibration {
  int sensor = 0;  // 0-based VRPN sensor (Fastrak station n is sensor n-1)
  std::filesystem::path calibration;
  std::optional<std::string> outside;   // as TrackerSetup::outside
  std::optional<double> fade_distance;  // as TrackerSetup::fade_distance
  std::string origin;                   // where it was configured ("vrpn.cfg:13"), for messages
};

struct TrackerSetup {
  // Device name of the corrected stream (the name clients already use).
  std::string name;
  // Sensors (for Unit_To_Sensor answers); reports of any sensor number are served.
  int num_sensors = 1;
  // Also serve the uncorrected reports under this name.
  std::optional<std::string> raw_name;
  // Calibration file for every sensor; none = reports are served unchanged (except the sensors of
  // `sensor_calibrations`).
  std::optional<std::filesystem::path> calibration;
  // Calibrations of single sensors, used for that sensor instead of `calibration` (a calibration is
  // fitted for one receiver: its sensor offset and coil gains are not another receiver's). At most
  // one per sensor.
  std::vector<SensorCalibration> sensor_calibrations;
  // Override of the calibration's extrapolation policy ("clamp", "fade" or "linear").
  std::optional<std::string> outside;
  // Override of the calibration's fade_distance [m] (vrpn.cfg's fade_distance=<metres>).
  std::optional<double> fade_distance;
  // Builds the report source (called once, at Start).
  std::function<std::unique_ptr<ReportSource>()> make_source;
  // Button devices fed by the source's stylus events: (device name, sensor). A button may take the
  // tracker's own name (one VRPN sender for both, told apart by message type); every other name
  // must be unused.
  std::vector<std::pair<std::string, int>> buttons;
  // Where it was configured ("vrpn.cfg:12"), for messages.
  std::string origin;
  // Hemispheres the tracker is configured to (a Fastrak's `Hs,x,y,z` extra commands, the last of
  // each station; none for hemisphere tracking `Hs,0,0,0` or no command): (0-based sensor,
  // direction). A calibration whose volume lies wholly on the other side of a sensor's
  // hemisphere is refused for that sensor: its reports can never fall in the volume.
  std::vector<std::pair<int, Eigen::Vector3d>> hemispheres;
  // Where its calibration and raw name were configured, when that is another line; for messages.
  std::string calibration_origin;
};

struct AppOptions {
  ServerOptions server;
  // Record raw and corrected streams of every tracker here (tracker stream CSV format).
  std::optional<std::filesystem::path> record_dir;
};

class TrackcalServerApp {
 public:
  // Validates the setup (names, duplicates) and loads every calibration: a bad calibration at start
  // is an error (std::invalid_argument naming the calibration's origin and the file). `log`
  // (default LogToStderr) gets every line already through PrintableForLog, from any thread.
  TrackcalServerApp(std::vector<TrackerSetup> trackers, AppOptions options, CorrectorLoader loader,
                    LogFunction log = nullptr);
  ~TrackcalServerApp();

  // Binds the server and starts every source.
  void Start();
  void Stop();
  int port() const { return server_->port(); }
  VrpnServer& server() { return *server_; }

  // Reloads every calibration file (SIGHUP). Returns how many were replaced.
  int ReloadCalibrations();
  // Reloads the calibrations whose file changed (size, time or inode) since the last load.
  int ReloadChangedCalibrations();
  // One line for the log (SIGUSR1, stop): clients, reports, connections dropped for not reading,
  // closed to make room or for protocol errors, refused, and per tracker
  // the corrected poses that were extrapolated (VRPN has no field for that flag).
  std::string StatusLine() const;
  // Corrected poses of tracker `name` that were extrapolated since the start; 0 for unknown names.
  std::uint64_t ExtrapolatedPoses(const std::string& name) const;
  // Directories holding calibration files (to watch for changes), and those of their targets when
  // they are symbolic links.
  std::vector<std::filesystem::path> CalibrationDirectories() const;

 private:
  struct Tracker;
  struct Slot;
  bool Reload(Tracker& t, Slot& slot, bool only_if_changed);
  void Install(Tracker& t, const Slot& slot, std::shared_ptr<const PoseCorrector> corrector);
  // Every line goes through PrintableForLog before `log_`, whatever the sink: lines quote vrpn.cfg
  // names, calibration paths and text a device or another VRPN server sent.
  void Log(const std::string& line);

  AppOptions options_;
  CorrectorLoader loader_;
  LogFunction log_;
  std::shared_ptr<ServerCatalog> catalog_;
  std::unique_ptr<VrpnServer> server_;
  std::vector<std::unique_ptr<Tracker>> trackers_;
};

}  // namespace trackcal::vrpn
