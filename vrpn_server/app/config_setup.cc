#include "vrpn_server/app/config_setup.h"

#include <stdexcept>

#include "vrpn_server/app/fastrak_source.h"
#include "vrpn_server/fastrak/from_config.h"
#include "vrpn_server/server/catalog.h"
#include "vrpn_server/server/devices.h"

namespace trackcal::vrpn {

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
    target->calibration = spec.file;
    target->calibration_origin = spec.location.ToString();
    target->raw_name = spec.raw_name;
    if (spec.outside == OutsidePolicy::kClamp) target->outside = "clamp";
    if (spec.outside == OutsidePolicy::kFade) target->outside = "fade";
    if (spec.outside == OutsidePolicy::kLinear) target->outside = "linear";
    target->fade_distance = spec.fade_distance_m;
  }
  return out;
}

}  // namespace trackcal::vrpn
