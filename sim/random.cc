#include "sim/random.h"

#include <cmath>
#include <numbers>

#include "core/pose.h"

namespace trackcal::sim {

namespace {
uint64_t SplitMix64(uint64_t x) {
  x += 0x9E3779B97F4A7C15ULL;
  x = (x ^ (x >> 30)) * 0xBF58476D1CE4E5B9ULL;
  x = (x ^ (x >> 27)) * 0x94D049BB133111EBULL;
  return x ^ (x >> 31);
}
uint64_t Fnv1a(std::string_view s) {
  uint64_t h = 0xcbf29ce484222325ULL;
  for (unsigned char c : s) {
    h ^= c;
    h *= 0x100000001b3ULL;
  }
  return h;
}
}  // namespace

Rng::Rng(uint64_t seed, std::string_view stream) : engine_(SplitMix64(seed ^ Fnv1a(stream))) {}

double Rng::Uniform() { return static_cast<double>(engine_() >> 11) * 0x1.0p-53; }

double Rng::Uniform(double lo, double hi) { return lo + (hi - lo) * Uniform(); }

double Rng::Normal() {
  // 1 - U is in (0, 1], so the log is finite.
  const double u1 = 1.0 - Uniform();
  const double u2 = Uniform();
  return std::sqrt(-2.0 * std::log(u1)) * std::cos(2.0 * std::numbers::pi * u2);
}

Eigen::Vector3d Rng::Normal3() {
  const double x = Normal();
  const double y = Normal();
  const double z = Normal();
  return Eigen::Vector3d(x, y, z);
}

Eigen::Quaterniond Rng::UniformRotation() {
  const double x = Normal();
  const double y = Normal();
  const double z = Normal();
  const double w = Normal();
  Eigen::Quaterniond q = QuaternionFromXyzw(x, y, z, w);
  q.normalize();
  if (q.w() < 0) q.coeffs() = -q.coeffs();
  return q;
}

Eigen::Quaterniond Rng::SmallRotation(double sigma_rad) {
  const Eigen::Vector3d v = sigma_rad * Normal3();
  const double angle = v.norm();
  if (angle == 0.0) return Eigen::Quaterniond::Identity();
  return Eigen::Quaterniond(Eigen::AngleAxisd(angle, v / angle));
}

}  // namespace trackcal::sim
