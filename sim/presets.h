// Internal: the scene presets compiled in from sim/scenes/*.yaml (generated presets.cc).
#pragma once

#include <string>
#include <vector>

namespace trackcal::sim::internal {

struct Preset {
  std::string name;  // file name without .yaml
  std::string yaml;  // file contents
};

const std::vector<Preset>& Presets();

}  // namespace trackcal::sim::internal
