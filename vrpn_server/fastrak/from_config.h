// Turns a vrpn.cfg `vrpn_Tracker_Fastrak` block into driver options.

#pragma once

#include <vector>

#include "vrpn_server/config.h"
#include "vrpn_server/fastrak/driver.h"

namespace trackcal::fastrak {

// Port, baud, extra commands and FTStylus sensors come from the spec; timings are the reference's.
// What the Fastrak driver does not implement (IS900time, IS-900 Stylus/Wand lines) is ignored with a
// warning appended to *warnings, so the tracker itself is still served.
FastrakOptions FastrakOptionsFromSpec(const vrpn::FastrakTrackerSpec& spec,
                                      std::vector<vrpn::ConfigWarning>* warnings);

}  // namespace trackcal::fastrak
