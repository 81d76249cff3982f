// Named, seeded random streams that give the same numbers on every platform and compiler.
//
// Each part of a capture (calibration orientations, tracker noise, reference noise, ...) draws from
// its own stream, seeded from the scene seed and the stream's name, so adding draws to one part
// never shifts the numbers of another. Only std::mt19937_64 (fully specified by the standard) is
// used from <random>; uniform and normal variates are computed here because the standard library's
// distributions are implementation-defined.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <cstdint>
#include <random>
#include <string_view>

namespace trackcal::sim {

class Rng {
 public:
  Rng(uint64_t seed, std::string_view stream);

  double Uniform();                      // in [0, 1)
  double Uniform(double lo, double hi);  // in [lo, hi)
  double Normal();                       // standard normal (Box-Muller)
  Eigen::Vector3d Normal3();             // three independent standard normals
  Eigen::Quaterniond UniformRotation();  // uniform on SO(3), scalar part >= 0
  // Rotation by a random vector with independent normal components of std `sigma_rad`.
  Eigen::Quaterniond SmallRotation(double sigma_rad);

 private:
  std::mt19937_64 engine_;
};

}  // namespace trackcal::sim
