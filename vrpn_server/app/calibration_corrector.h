// A trackcal calibration file (core/calibration_file.h) as the server's PoseCorrector.
#pragma once

#include <filesystem>
#include <memory>
#include <optional>
#include <string>

#include "vrpn_server/server/devices.h"

namespace trackcal::vrpn {

// Reads the file (throws with the file, JSON path and reason on a bad file); `outside` ("clamp",
// "fade" or "linear") overrides the file's extrapolation policy and `fade_distance` [m] its
// fade_distance. Matches CorrectorLoader.
std::shared_ptr<const PoseCorrector> LoadCalibrationCorrector(
    const std::filesystem::path& path, const std::optional<std::string>& outside,
    const std::optional<double>& fade_distance = std::nullopt);

}  // namespace trackcal::vrpn
