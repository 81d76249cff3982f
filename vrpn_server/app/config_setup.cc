#include "vrpn_server/app/config_setup.h"

#include <cmath>
#include <cstdlib>
#include <map>
#include <optional>
#include <stdexcept>

#include "vrpn_server/app/fastrak_source.h"
#include "vrpn_server/fastrak/from_config.h"
#include "vrpn_server/server/catalog.h"
#include "vrpn_server/server/devices.h"

namespace trackcal::vrpn {
namespace {

bool IsPassthrough(const VrpnConfig& config, const std::string& name) {
  for (const PassthroughSpec& p : config.passthroughs) {
    if (p.name == name) return true;
  }
  return false;
}

// The hemisphere of each station set by `Hs,x,y,z` extra commands (the last one of a station
// counts; `Hs,0,0,0`, hemisphere tracking, sets none): (0-based sensor, direction).
std::vector<std::pair<int, Eigen::Vector3d>> HemispheresOf(const std::vector<std::string>& commands,
                                                           int num_stations) {
  std::map<int, std::optional<Eigen::Vector3d>> by_sensor;
  for (const std::string& cmd : commands) {
    if (cmd.size() < 2 || cmd[0] != 'H') continue;
    std::vector<double> v;
    const char* p = cmd.c_str() + 1;
    bool ok = true;
    while (ok) {
      char* end = nullptr;
      v.push_back(std::strtod(p, &end));
      ok = end != p && std::isfinite(v.back());
      if (!ok || *end == '\0') break;
      ok = *end == ',';
      p = end + 1;
    }
    if (!ok || v.size() != 4 || v[0] != std::floor(v[0]) || v[0] < 1 || v[0] > num_stations) {
      continue;  // not a hemisphere command this check understands: sent as written, not checked
    }
    const Eigen::Vector3d h(v[1], v[2], v[3]);
    by_sensor[static_cast<int>(v[0]) - 1] = h.isZero() ? std::nullopt : std::optional(h);
  }
  std::vector<std::pair<int, Eigen::Vector3d>> out;
  for (const auto& [sensor, h] : by_sensor) {
    if (h) out.emplace_back(sensor, *h);
  }
  return out;
}

}  // namespace

ConfigSetup SetupFromConfig(const VrpnConfig& config, const std::string& this_server) {
  ConfigSetup out;
  for (const auto& w : config.warnings) out.warnings.push_back(w.ToString());
  for (const FastrakTrackerSpec& spec : config.fastrak_trackers) {
    std::vector<ConfigWarning> warnings;
    fastrak::FastrakOptions options = fastrak::FastrakOptionsFromSpec(spec, &warnings);
    for (const auto& w : warnings) out.warnings.push_back(w.ToString());
    TrackerSetup t;
    t.name = spec.name;
    t.num_sensors = options.num_stations;
    t.origin = spec.location.ToString();
    t.hemispheres = HemispheresOf(spec.extra_commands, options.num_stations);
    for (const ButtonDeviceSpec& b : spec.buttons) {
      if (b.kind == ButtonDeviceKind::kFastrakStylus) t.buttons.emplace_back(b.name, b.sensor);
    }
    t.make_source = [options] { return MakeFastrakSource(options); };
    out.trackers.push_back(std::move(t));
  }
  for (const NullTrackerSpec& spec : config.null_trackers) {
    try {  // the server's limits, checked now so the error names the line
      TrackerSpec tracker;
      tracker.name = spec.name;
      tracker.num_sensors = spec.sensors;
      tracker.Check();
      NullTracker::CheckOptions(spec.sensors, spec.rate_hz);
    } catch (const std::invalid_argument& e) {
      throw std::invalid_argument(spec.location.ToString() + ": " + e.what());
    }
    TrackerSetup t;
    t.name = spec.name;
    t.num_sensors = spec.sensors;
    t.origin = spec.location.ToString();
    const int sensors = spec.sensors;
    const double rate = spec.rate_hz;
    t.make_source = [sensors, rate] { return MakeNullSource(sensors, rate); };
    out.trackers.push_back(std::move(t));
  }
  for (const PassthroughSpec& spec : config.passthroughs) {
    TrackerSetup t;
    t.name = spec.name;
    t.origin = spec.location.ToString();
    std::string source;
    if (spec.source_host.empty()) {
      source = spec.source_device + "@tcp://" + this_server;
      out.reads_this_server = true;
    } else {
      source = spec.source_device + "@" + (spec.source_tcp_only ? "tcp://" : "") + spec.source_host +
               ":" + std::to_string(spec.source_port);
    }
    ParseVrpnName(source);  // validates now, not when the thread starts
    t.make_source = [source] { return MakePassthroughSource(source); };
    out.trackers.push_back(std::move(t));
  }
  for (const CalibrationSpec& spec : config.calibrations) {
    TrackerSetup* target = nullptr;
    for (auto& t : out.trackers) {
      if (t.name == spec.tracker) target = &t;
    }
    if (target == nullptr) {
      throw std::invalid_argument(spec.location.ToString() + ": field 'tracker': no tracker named '" +
                                  spec.tracker + "' in this file");
    }
    std::optional<std::string> outside;
    if (spec.outside == OutsidePolicy::kClamp) outside = "clamp";
    if (spec.outside == OutsidePolicy::kFade) outside = "fade";
    if (spec.outside == OutsidePolicy::kLinear) outside = "linear";
    if (spec.raw_name) {  // the parser allows raw= on one calibration line per tracker
      target->raw_name = spec.raw_name;
      target->calibration_origin = spec.location.ToString();
    }
    if (spec.sensor) {
      // A sensor the tracker never reports would be silently left uncorrected.
      if (*spec.sensor >= target->num_sensors && !IsPassthrough(config, spec.tracker)) {
        throw std::invalid_argument(spec.location.ToString() + ": field 'sensor': tracker '" +
                                    spec.tracker + "' has sensors 0.." +
                                    std::to_string(target->num_sensors - 1) + ", got " +
                                    std::to_string(*spec.sensor));
      }
      target->sensor_calibrations.push_back(SensorCalibration{
          *spec.sensor, spec.file, outside, spec.fade_distance_m, spec.location.ToString()});
      continue;
    }
    target->calibration = spec.file;
    if (target->calibration_origin.empty()) target->calibration_origin = spec.location.ToString();
    target->outside = outside;
    target->fade_distance = spec.fade_distance_m;
  }
  return out;
}

}  // namespace trackcal::vrpn
