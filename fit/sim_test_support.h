// Test support for the fit/ tests on simulated scenes: model-file snippets of a scene's true room
// and lookups in a fit's parameter report. Header-only; tests only.
#pragma once

#include <Eigen/Core>
#include <iomanip>
#include <sstream>
#include <stdexcept>
#include <string>

#include "core/field.h"
#include "fit/fit_engine.h"

namespace trackcal::fit::testing {

// "[x, y, z]" at full precision, for model-file YAML.
inline std::string YamlVector3(const Eigen::Vector3d& v) {
  std::ostringstream out;
  out << std::setprecision(17) << "[" << v.x() << ", " << v.y() << ", " << v.z() << "]";
  return out.str();
}

// The room's planes and objects as fixed physical terms (items of `terms:`, indented for it): what
// a previous calibration of the room found, here the truth.
inline std::string FixedRoomTermsYaml(const FieldModel& room) {
  std::ostringstream out;
  out << std::setprecision(17);
  for (const auto& p : room.planes) {
    out << "  - type: plane\n    name: " << p.name
        << "\n    point_in_transmitter: " << YamlVector3(p.point_in_transmitter)
        << "\n    normal_in_transmitter: " << YamlVector3(p.normal_in_transmitter)
        << "\n    attenuation: " << p.attenuation
        << "\n    parameters: {distance_m: {fixed: true}, normal_in_transmitter: {fixed: true}, "
           "attenuation: {fixed: true}}\n";
  }
  for (const auto& o : room.objects) {
    out << "  - type: dipole\n    name: " << o.name
        << "\n    location_in_transmitter: " << YamlVector3(o.location_in_transmitter)
        << "\n    polarisability_m3: " << o.polarisability_m3
        << "\n    parameters: {location_in_transmitter: {fixed: true}, polarisability_m3: {fixed: "
           "true}}\n";
  }
  return out.str();
}

// The report of one parameter block; throws when the fit has none of that name.
inline const ParameterReport& FindParameter(const FitResult& result, const std::string& term,
                                            const std::string& block) {
  for (const auto& p : result.parameters) {
    if (p.term == term && p.block == block) return p;
  }
  throw std::runtime_error("no parameter " + term + "." + block);
}

}  // namespace trackcal::fit::testing
