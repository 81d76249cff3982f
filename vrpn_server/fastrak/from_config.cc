#include "vrpn_server/fastrak/from_config.h"

namespace trackcal::fastrak {

FastrakOptions FastrakOptionsFromSpec(const vrpn::FastrakTrackerSpec& spec,
                                      std::vector<vrpn::ConfigWarning>* warnings) {
  FastrakOptions options;
  options.port = spec.port;
  options.baud = spec.baud;
  options.extra_commands = spec.extra_commands;
  if (spec.is900_time) {
    warnings->push_back({spec.location,
                         "IS900time is an InterSense IS-900 option; trackcal's Fastrak driver uses "
                         "host timestamps and ignores it"});
  }
  for (const vrpn::ButtonDeviceSpec& button : spec.buttons) {
    if (button.kind == vrpn::ButtonDeviceKind::kFastrakStylus) {
      options.stylus_sensors.push_back(button.sensor);
    } else {
      warnings->push_back({button.location,
                           "IS-900 Stylus/Wand button device '" + button.name +
                               "' is not supported by the Fastrak driver; ignored"});
    }
  }
  return options;
}

}  // namespace trackcal::fastrak
