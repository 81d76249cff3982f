// vrpn.cfg (vrpn_server/config.h) -> the trackers trackcal-server serves.
#pragma once

#include <functional>
#include <string>
#include <vector>

#include "vrpn_server/app/app.h"
#include "vrpn_server/config.h"

namespace trackcal::vrpn {

struct ConfigSetup {
  std::vector<TrackerSetup> trackers;
  // Parser and driver warnings ("vrpn.cfg:12: warning: ...") for the log.
  std::vector<std::string> warnings;
  // A pass-through reads a tracker of this server ("*Tracker0"): it connects from this host, so an
  // allow-list must admit the address it connects to.
  bool reads_this_server = false;
};

// `this_server` is the address:port pass-through sources without a host ("*Tracker0") connect to.
// Throws std::invalid_argument naming the config line for a calibration line whose tracker is not
// defined, or a device kind this build cannot serve.
ConfigSetup SetupFromConfig(const VrpnConfig& config, const std::string& this_server);

}  // namespace trackcal::vrpn
