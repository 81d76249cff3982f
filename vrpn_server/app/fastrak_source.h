// The Fastrak serial driver (vrpn_server/fastrak/, own thread) as a ReportSource of trackcal-server.
#pragma once

#include <memory>
#include <string>

#include "vrpn_server/app/app.h"
#include "vrpn_server/fastrak/driver.h"

namespace trackcal::vrpn {

std::unique_ptr<ReportSource> MakeFastrakSource(fastrak::FastrakOptions options);

}  // namespace trackcal::vrpn
