// Test support for the fit/ tests on simulated scenes: model-file snippets of a scene's true room,
// lookups in a fit's parameter report, a grid of stations on four heights and a stream whose
// misfit wanders in time. Header-only; tests only.
#pragma once

#include <Eigen/Core>
#include <cmath>
#include <functional>
#include <iomanip>
#include <random>
#include <sstream>
#include <stdexcept>
#include <string>
#include <vector>

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

// A 12 x 10 x 4 grid in a 1 m box, heights 0.1 m apart, as a physical term leaves it: the true
// positions to 0.1 mm; the references corrected by `truth` plus 0.1 mm of noise. On 4 heights z^4
// equals a cubic at every station: a degree-4 polynomial has a direction they do not determine.
inline std::vector<FitStation> FourHeightGrid(const Correction& truth, std::mt19937* rng) {
  std::normal_distribution<double> normal;
  auto noise = [&]() -> Eigen::Vector3d {
    return 1e-4 * Eigen::Vector3d(normal(*rng), normal(*rng), normal(*rng));
  };
  std::vector<FitStation> stations;
  for (int i = 0; i < 12; ++i) {
    for (int j = 0; j < 10; ++j) {
      for (int k = 0; k < 4; ++k) {
        FitStation s;
        s.reported.translation =
            Eigen::Vector3d(-0.5 + i / 11.0, -0.5 + j / 9.0, 0.15 + k * 0.1) + noise();
        s.reported.rotation = Eigen::Quaterniond::UnitRandom();
        s.reference = truth.Apply(s.reported).pose;
        s.reference.translation += noise();
        stations.push_back(s);
      }
    }
  }
  return stations;
}

// Stream samples (100 Hz, 20 s) along `path` (the reported pose at time t) whose reference is off
// by a misfit that wanders in time: per axis an Ornstein-Uhlenbeck process, standard deviation
// 0.3 mm, correlation time 0.5 s (neighbouring samples share it, as they share a model's misfit
// along a real stream's path), zero mean; plus `offset` and white noise of `white_sigma` [m] per
// axis. `times` false: the same samples at time 0 (static stations).
inline std::vector<FitStation> WanderingMisfitStream(const std::function<Rigid3d(double)>& path,
                                                     unsigned seed, double white_sigma,
                                                     const Eigen::Vector3d& offset,
                                                     bool times = true) {
  constexpr int kSamples = 2000;
  constexpr double kDt = 0.01, kTau = 0.5, kSigma = 3e-4;
  std::mt19937 rng(seed);
  std::normal_distribution<double> g;
  const double a = std::exp(-kDt / kTau), b = kSigma * std::sqrt(1.0 - a * a);
  Eigen::Vector3d misfit(kSigma * g(rng), kSigma * g(rng), kSigma * g(rng));
  std::vector<FitStation> out;
  for (int i = 0; i < kSamples; ++i) {
    const double t = kDt * i;
    FitStation s;
    s.station = i + 1;
    s.time = times ? t : 0.0;
    s.reported = path(t);
    s.reference = s.reported;
    s.reference.translation +=
        offset + misfit + white_sigma * Eigen::Vector3d(g(rng), g(rng), g(rng));
    out.push_back(s);
    misfit = a * misfit + b * Eigen::Vector3d(g(rng), g(rng), g(rng));
  }
  return out;
}

}  // namespace trackcal::fit::testing
