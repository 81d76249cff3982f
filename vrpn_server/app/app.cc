#include "vrpn_server/app/app.h"

#include <algorithm>
#include <cstdio>
#include <filesystem>
#include <limits>
#include <set>
#include <stdexcept>

#include "core/printable_text.h"

namespace trackcal::vrpn {
namespace {

class NullSource : public ReportSource {
 public:
  NullSource(int num_sensors, double rate_hz, Rigid3d pose)
      : num_sensors_(num_sensors), rate_hz_(rate_hz), pose_(pose) {}
  void Start(SourceCallbacks callbacks) override {
    callbacks_ = std::move(callbacks);
    tracker_ = std::make_unique<NullTracker>(
        [this](int s, const Rigid3d& p, Timestamp t) { callbacks_.on_pose(s, p, t); }, num_sensors_,
        rate_hz_, pose_);
    tracker_->Start();
  }
  void Stop() override {
    if (tracker_) tracker_->Stop();
  }
  std::string Describe() const override {
    return "NULL tracker, " + std::to_string(num_sensors_) + " sensor(s) at " +
           std::to_string(rate_hz_) + " Hz";
  }

 private:
  int num_sensors_;
  double rate_hz_;
  Rigid3d pose_;
  SourceCallbacks callbacks_;
  std::unique_ptr<NullTracker> tracker_;
};

class PassthroughSource : public ReportSource {
 public:
  explicit PassthroughSource(std::string name) : name_(std::move(name)) {
    ParseVrpnName(name_);  // throws for a malformed name
  }
  void Start(SourceCallbacks callbacks) override {
    callbacks_ = std::move(callbacks);
    client_ = std::make_unique<VrpnTrackerClient>(name_);
    client_->SetPoseCallback([this](const TrackerReport& r) {
      callbacks_.on_pose(r.sensor, r.transmitter_from_receiver, r.time);
    });
    client_->SetMessageCallback([this](const ReceivedMessage& m) {
      if (m.type != kTextType || !callbacks_.on_text) return;
      if (auto text = DecodeText(m.payload)) callbacks_.on_text(text->severity, text->text);
    });
    client_->Start();
  }
  void Stop() override {
    if (client_) client_->Stop();
  }
  std::string Describe() const override { return "pass-through of " + name_; }

 private:
  std::string name_;
  SourceCallbacks callbacks_;
  std::unique_ptr<VrpnTrackerClient> client_;
};

struct FileSignature {
  bool exists = false;
  std::int64_t size = 0, mtime_ns = 0;
  std::uint64_t inode = 0;
  bool operator==(const FileSignature&) const = default;
};

FileSignature Signature(const std::filesystem::path& path) {
  struct stat st {};
  FileSignature s;
  if (::stat(path.c_str(), &st) != 0) return s;
  s.exists = true;
  s.size = st.st_size;
  s.mtime_ns = static_cast<std::int64_t>(st.st_mtim.tv_sec) * 1000000000 + st.st_mtim.tv_nsec;
  s.inode = st.st_ino;
  return s;
}

const std::string& CalibrationOrigin(const TrackerSetup& setup) {
  return setup.calibration_origin.empty() ? setup.origin : setup.calibration_origin;
}

// ", calibration a.json", ", calibration a.json for sensor 1 (other sensors uncorrected)", ...
std::string CalibrationSummary(const TrackerSetup& setup) {
  if (!setup.calibration && setup.sensor_calibrations.empty()) return ", uncorrected";
  std::string text;
  if (setup.calibration) text = ", calibration " + setup.calibration->string();
  for (const SensorCalibration& c : setup.sensor_calibrations) {
    text += ", calibration " + c.calibration.string() + " for sensor " + std::to_string(c.sensor);
  }
  if (!setup.calibration) text += " (other sensors uncorrected)";
  return text;
}

}  // namespace

std::unique_ptr<ReportSource> MakeNullSource(int num_sensors, double rate_hz, Rigid3d pose) {
  return std::make_unique<NullSource>(num_sensors, rate_hz, pose);
}

std::unique_ptr<ReportSource> MakePassthroughSource(const std::string& vrpn_name) {
  return std::make_unique<PassthroughSource>(vrpn_name);
}

namespace {

// A calibration fitted for one receiver (its sensor offset and coil gains) served on another
// receiver's sensor= line gives cm-level errors without a sign: refused (at start, and on reload,
// keeping the previous correction). The file records the capture's 1-based sensor; the line's
// sensor= is the 0-based VRPN sensor. A file without the field, or a line without sensor=, is not
// checked.
void CheckFittedSensor(std::optional<int> vrpn_sensor, const PoseCorrector& corrector) {
  const int fitted = corrector.FittedSensor();
  if (!vrpn_sensor || fitted == 0 || fitted == *vrpn_sensor + 1) return;
  throw std::invalid_argument(
      "the file was fitted for receiver " + std::to_string(fitted) +
      " (the capture's sensor column; Fastrak station " + std::to_string(fitted) +
      "), which is VRPN sensor=" + std::to_string(fitted - 1) + ", not sensor=" +
      std::to_string(*vrpn_sensor) + " (Fastrak station " + std::to_string(*vrpn_sensor + 1) +
      "): each receiver has its own sensor offset and coil gains; serve it on sensor=" +
      std::to_string(fitted - 1) + " or fit receiver " + std::to_string(*vrpn_sensor + 1) +
      " (trackcal-fit fit --sensor " + std::to_string(*vrpn_sensor + 1) + ")");
}

// A Fastrak reports, of the two positions +-p its dipole field allows, the one in the configured
// hemisphere (p.h >= 0). A calibration whose volume has no point with p.h > 0 was captured in
// another hemisphere: every report of that sensor is mirrored out of the volume, and the
// correction is extrapolated for every pose (a capture in +x, served with H1,-1,0,0). Refused
// naming the sensor and the command. Only hemispheres the vrpn.cfg sets are known (a unit's
// power-up hemisphere is not), and only a volume wholly on the other side is caught.
void CheckHemispheres(std::optional<int> slot_sensor,
                      const std::vector<std::pair<int, Eigen::Vector3d>>& hemispheres,
                      const std::string& tracker_origin, const PoseCorrector& corrector) {
  const auto box = corrector.FittedBox();
  if (!box) return;
  for (const auto& [sensor, h] : hemispheres) {
    if (slot_sensor && *slot_sensor != sensor) continue;
    double reach = -std::numeric_limits<double>::infinity();  // max of p.h over the box
    for (int corner = 0; corner < 8; ++corner) {
      Eigen::Vector3d p;
      for (int k = 0; k < 3; ++k) p[k] = (corner >> k) & 1 ? box->second[k] : box->first[k];
      reach = std::max(reach, p.dot(h));
    }
    if (reach > 0.0) continue;
    char hemisphere[96];
    std::snprintf(hemisphere, sizeof(hemisphere), "H%d,%g,%g,%g", sensor + 1, h.x(), h.y(), h.z());
    throw std::invalid_argument(
        "the calibrated volume lies wholly in the other hemisphere than " +
        std::string(hemisphere) + " (" + tracker_origin + ") for station " +
        std::to_string(sensor + 1) + " (VRPN sensor " + std::to_string(sensor) +
        "): the Fastrak reports that receiver's positions mirrored through the transmitter, never "
        "inside the volume, so the calibration was captured in another hemisphere; capture and "
        "fit in the configured hemisphere, or configure the hemisphere of the capture");
  }
}

}  // namespace

// One calibration file of a tracker: for every sensor (`sensor` unset) or for one.
struct TrackcalServerApp::Slot {
  std::optional<int> sensor;
  std::filesystem::path file;
  std::optional<std::string> outside;
  std::optional<double> fade_distance;
  std::string origin;
  FileSignature signature;
  // "Tracker0" or "Tracker0 sensor 1", for messages.
  std::string Label(const std::string& tracker) const {
    return sensor ? tracker + " sensor " + std::to_string(*sensor) : tracker;
  }
};

struct TrackcalServerApp::Tracker {
  TrackerSetup setup;
  std::unique_ptr<TrackerDevice> device;
  std::unique_ptr<ReportSource> source;
  std::vector<std::pair<int, int>> buttons;  // (sensor, catalog button index)
  std::vector<Slot> slots;
};

TrackcalServerApp::TrackcalServerApp(std::vector<TrackerSetup> trackers, AppOptions options,
                                     CorrectorLoader loader, LogFunction log)
    : options_(std::move(options)),
      loader_(std::move(loader)),
      log_(log ? std::move(log) : LogFunction(LogToStderr)),
      catalog_(std::make_shared<ServerCatalog>()) {
  std::set<std::string> names;
  auto claim = [&](const std::string& name, const std::string& origin) {
    if (!names.insert(name).second) {
      throw std::invalid_argument(origin + ": device name '" + name + "' is served twice");
    }
  };
  // A button may share the name of the tracker it belongs to (VRPN serves both under one sender,
  // their messages told apart by type), once; any other reused name is served twice.
  std::set<std::string> shared_button_names;
  auto claim_button = [&](const std::string& name, const TrackerSetup& setup) {
    if (name == setup.name && shared_button_names.insert(name).second) return;
    claim(name, setup.origin);
  };
  std::vector<std::pair<int, std::optional<int>>> indices;
  for (TrackerSetup& setup : trackers) {
    if (!setup.make_source) throw std::invalid_argument(setup.origin + ": tracker has no source");
    claim(setup.name, setup.origin);
    TrackerSpec spec;
    spec.name = setup.name;
    spec.num_sensors = setup.num_sensors;
    const int index = catalog_->AddTracker(spec);
    std::optional<int> raw;
    if (setup.raw_name) {
      claim(*setup.raw_name, CalibrationOrigin(setup));
      spec.name = *setup.raw_name;
      raw = catalog_->AddTracker(spec);
    }
    indices.emplace_back(index, raw);
    auto t = std::make_unique<Tracker>();
    for (const auto& [button_name, sensor] : setup.buttons) {
      claim_button(button_name, setup);
      t->buttons.emplace_back(sensor, catalog_->AddButton(ButtonSpec{button_name, 1}));
    }
    t->setup = std::move(setup);
    trackers_.push_back(std::move(t));
  }
  server_ = std::make_unique<VrpnServer>(catalog_, options_.server, log_);
  for (std::size_t i = 0; i < trackers_.size(); ++i) {
    Tracker& t = *trackers_[i];
    t.device = std::make_unique<TrackerDevice>(server_.get(), indices[i].first, indices[i].second);
    if (t.setup.calibration) {
      t.slots.push_back(Slot{std::nullopt,
                             *t.setup.calibration,
                             t.setup.outside,
                             t.setup.fade_distance,
                             CalibrationOrigin(t.setup),
                             {}});
    }
    std::set<int> calibrated_sensors;
    for (const SensorCalibration& c : t.setup.sensor_calibrations) {
      const std::string& origin = c.origin.empty() ? t.setup.origin : c.origin;
      if (c.sensor < 0 || !calibrated_sensors.insert(c.sensor).second) {
        throw std::invalid_argument(origin + ": calibration of '" + t.setup.name + "': sensor " +
                                    std::to_string(c.sensor) +
                                    (c.sensor < 0 ? " is negative" : " has two calibrations"));
      }
      t.slots.push_back(Slot{c.sensor, c.calibration, c.outside, c.fade_distance, origin, {}});
    }
    for (Slot& slot : t.slots) {
      if (!loader_) throw std::invalid_argument(t.setup.origin + ": no calibration loader");
      try {
        slot.signature = Signature(slot.file);
        auto corrector = loader_(slot.file, slot.outside, slot.fade_distance);
        CheckFittedSensor(slot.sensor, *corrector);
        CheckHemispheres(slot.sensor, t.setup.hemispheres, t.setup.origin, *corrector);
        Install(t, slot, corrector);
        Log(slot.Label(t.setup.name) + ": correction " + corrector->Describe());
      } catch (const std::exception& e) {
        throw std::invalid_argument(slot.origin + ": calibration of '" + slot.Label(t.setup.name) +
                                    "': " + e.what());
      }
    }
  }
  if (options_.record_dir) {
    // Every recording is checked before the first is created, and after every calibration loaded:
    // a start refused for the second tracker's recording (or its calibration) left the first
    // tracker's header-only recordings published, which then refused the next start as existing.
    const std::filesystem::path& dir = *options_.record_dir;
    for (const auto& tp : trackers_) {
      StreamRecorder::CheckNotRecorded(dir, tp->setup.name + "_raw");
      StreamRecorder::CheckNotRecorded(dir, tp->setup.name + "_corrected");
    }
    for (const auto& tp : trackers_) {
      auto raw = std::make_unique<StreamRecorder>(dir, tp->setup.name + "_raw");
      auto corrected = std::make_unique<StreamRecorder>(dir, tp->setup.name + "_corrected");
      tp->device->SetRecorders(std::move(raw), std::move(corrected));
    }
  }
}

TrackcalServerApp::~TrackcalServerApp() { Stop(); }

void TrackcalServerApp::Log(const std::string& line) { log_(PrintableForLog(line)); }

void TrackcalServerApp::Start() {
  server_->Start();
  for (auto& tp : trackers_) {
    Tracker& t = *tp;
    t.source = t.setup.make_source();
    Log("serving " + t.setup.name + (t.setup.raw_name ? " (raw: " + *t.setup.raw_name + ")" : "") +
        " from " + t.source->Describe() + CalibrationSummary(t.setup));
    SourceCallbacks callbacks;
    TrackerDevice* device = t.device.get();
    callbacks.on_pose = [device](int sensor, const Rigid3d& pose, Timestamp time) {
      device->OnReport(sensor, pose, time);
    };
    callbacks.on_poses = [device](std::span<const SensorReport> reports) { device->OnReports(reports); };
    device->SetLog([this, name = t.setup.name](const std::string& line) { Log(name + ": " + line); });
    callbacks.on_text = [this, device, name = t.setup.name](TextSeverity severity, const std::string& text) {
      Log(name + ": " + text);
      device->OnText(severity, text);
    };
    callbacks.on_button = [this, &t](int sensor, bool pressed, Timestamp time) {
      for (const auto& [s, index] : t.buttons) {
        if (s == sensor) server_->PublishButton(index, 0, pressed, time);
      }
    };
    if (options_.server.realtime_priority > 0) t.source->SetRealtimePriority(options_.server.realtime_priority);
    t.source->Start(std::move(callbacks));
  }
}

void TrackcalServerApp::Stop() {
  for (auto& t : trackers_) {
    if (t->source) t->source->Stop();
  }
  if (server_) server_->Stop();
  for (auto& t : trackers_) {
    if (t->device) t->device->SetRecorders(nullptr, nullptr);  // closes and publishes the files
  }
}

void TrackcalServerApp::Install(Tracker& t, const Slot& slot,
                                std::shared_ptr<const PoseCorrector> corrector) {
  if (slot.sensor) {
    t.device->SetSensorCorrector(*slot.sensor, std::move(corrector));
  } else {
    t.device->SetCorrector(std::move(corrector));
  }
}

bool TrackcalServerApp::Reload(Tracker& t, Slot& slot, bool only_if_changed) {
  const FileSignature now = Signature(slot.file);
  if (only_if_changed && now == slot.signature) return false;
  slot.signature = now;
  const std::string label = slot.Label(t.setup.name);
  try {
    auto corrector = loader_(slot.file, slot.outside, slot.fade_distance);
    CheckFittedSensor(slot.sensor, *corrector);
    CheckHemispheres(slot.sensor, t.setup.hemispheres, t.setup.origin, *corrector);
    const std::string description = corrector->Describe();
    Install(t, slot, std::move(corrector));
    // A calibration file's description starts with its path: "reloaded calib.json (calib.json
    // (polynomial, ...))" said it twice.
    const std::string file = slot.file.string();
    Log(label + ": reloaded " +
        (description.rfind(file, 0) == 0 ? description : file + " (" + description + ")"));
    return true;
  } catch (const std::exception& e) {
    Log(label + ": rejected new " + slot.file.string() +
        ", keeping the previous correction: " + e.what());
    return false;
  }
}

int TrackcalServerApp::ReloadCalibrations() {
  int n = 0;
  for (auto& t : trackers_) {
    for (Slot& slot : t->slots) n += Reload(*t, slot, /*only_if_changed=*/false);
  }
  return n;
}

int TrackcalServerApp::ReloadChangedCalibrations() {
  int n = 0;
  for (auto& t : trackers_) {
    for (Slot& slot : t->slots) n += Reload(*t, slot, /*only_if_changed=*/true);
  }
  return n;
}

std::string TrackcalServerApp::StatusLine() const {
  const ServerStats stats = server_->stats();
  std::string line = "status: " + std::to_string(stats.clients) + " client(s), " +
                     std::to_string(stats.connections_total) + " connection(s) so far, " +
                     std::to_string(stats.dropped_slow) + " dropped for not reading, " +
                     std::to_string(stats.dropped_over_total) +
                     " dropped with the most output waiting over the total, " +
                     std::to_string(stats.evicted) + " closed to make room, " +
                     std::to_string(stats.closed_protocol) + " closed for protocol errors, " +
                     std::to_string(stats.refused) + " refused, " +
                     std::to_string(stats.reports_published) + " report(s) sent";
  for (const auto& t : trackers_) {
    // The share of corrected poses outside the calibrated volume: a correction mostly
    // extrapolated is not the one the calibration's scores describe.
    const std::uint64_t corrected = t->device->corrected_poses();
    const std::uint64_t extrapolated = t->device->extrapolated_poses();
    line += "; " + t->setup.name + ": " + std::to_string(corrected) + " corrected, " +
            std::to_string(extrapolated) + " extrapolated";
    if (corrected > 0) {
      char share[32];
      std::snprintf(share, sizeof(share), " (%.1f %%)",
                    100.0 * static_cast<double>(extrapolated) / static_cast<double>(corrected));
      line += share;
    }
    line += ", " + std::to_string(t->device->unresolved_poses()) + " unresolved";
    if (const std::uint64_t n = t->device->non_finite_poses(); n > 0) {
      line += ", " + std::to_string(n) + " not finite (not served)";
    }
    if (const std::uint64_t n = t->device->bad_reports(); n > 0) {
      line += ", " + std::to_string(n) + " report(s) not a pose (not served)";
    }
  }
  return line;
}

std::uint64_t TrackcalServerApp::ExtrapolatedPoses(const std::string& name) const {
  for (const auto& t : trackers_) {
    if (t->setup.name == name) return t->device->extrapolated_poses();
  }
  return 0;
}

std::vector<std::filesystem::path> TrackcalServerApp::CalibrationDirectories() const {
  std::set<std::filesystem::path> dirs;
  for (const auto& t : trackers_) {
    for (const Slot& slot : t->slots) {
      auto dir = slot.file.parent_path();
      dirs.insert(dir.empty() ? std::filesystem::path(".") : dir);
      // A symbolic link (calib.json -> ../releases/lab.json): the file that changes is the target,
      // in its own directory; the link's directory sees no event when it is rewritten.
      std::error_code ec;
      const auto target = std::filesystem::canonical(slot.file, ec);
      if (!ec) dirs.insert(target.parent_path());
    }
  }
  return {dirs.begin(), dirs.end()};
}

}  // namespace trackcal::vrpn
