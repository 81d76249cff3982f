#include "fit/synthetic_registration.h"

#include <algorithm>
#include <numeric>

#include "fit/rotation.h"

namespace trackcal::fit {
namespace {

Eigen::Quaterniond UniformRotation(std::mt19937_64* rng) {
  // A normalised 4-D Gaussian is uniform on SO(3).
  std::normal_distribution<double> n(0.0, 1.0);
  const double x = n(*rng), y = n(*rng), z = n(*rng), w = n(*rng);
  return QuaternionFromXyzw(x, y, z, w).normalized();
}

Eigen::Vector3d Gaussian3(double sigma, std::mt19937_64* rng) {
  std::normal_distribution<double> n(0.0, 1.0);
  const double x = n(*rng), y = n(*rng), z = n(*rng);
  return sigma * Eigen::Vector3d(x, y, z);
}

}  // namespace

SyntheticRegistration MakeSyntheticRegistration(const SyntheticRegistrationOptions& options,
                                                std::mt19937_64* rng) {
  std::uniform_real_distribution<double> unit(-1.0, 1.0);
  SyntheticRegistration data;
  const Eigen::Vector3d direction =
      Eigen::Vector3d(unit(*rng), unit(*rng), unit(*rng)).normalized();
  data.optical_from_transmitter =
      Rigid3d(UniformRotation(rng), options.optical_distance_m * direction);

  std::uniform_real_distribution<double> distance(options.marker_distance_min_m,
                                                  options.marker_distance_max_m);
  for (int j = 0; j < options.num_markers; ++j) {
    Eigen::Vector3d axis = Eigen::Vector3d::Zero();
    axis((j / 2) % 3) = (j % 2 == 0) ? 1.0 : -1.0;
    const double d = distance(*rng);
    const Eigen::Vector3d jitter(unit(*rng), unit(*rng), unit(*rng));
    data.marker_in_receiver[j + 1] = d * axis + options.marker_jitter_m * jitter;
  }

  const Eigen::Quaterniond fixed_orientation = UniformRotation(rng);
  const int max_visible = std::min(options.max_visible, options.num_markers);
  std::uniform_int_distribution<int> num_visible(std::min(options.min_visible, max_visible),
                                                 max_visible);
  std::vector<int> ids(options.num_markers);
  std::iota(ids.begin(), ids.end(), 1);
  for (int i = 0; i < options.num_stations; ++i) {
    Rigid3d truth;
    if (options.identical_stations && i > 0) {
      truth = data.true_transmitter_from_receiver.front();
    } else {
      Eigen::Quaterniond q = options.random_orientations ? UniformRotation(rng) : fixed_orientation;
      if (options.random_orientations && options.max_rotation_from_nominal_rad > 0.0) {
        // Uniform direction, angle uniform in [0, max]: a tilt around the nominal orientation.
        const Eigen::Vector3d axis = Gaussian3(1.0, rng).normalized();
        std::uniform_real_distribution<double> angle(0.0, options.max_rotation_from_nominal_rad);
        q = QuaternionFromRotationVector(angle(*rng) * axis) * fixed_orientation;
      }
      const Eigen::Vector3d p =
          options.station_center_in_transmitter +
          options.station_half_size_m * Eigen::Vector3d(unit(*rng), unit(*rng), unit(*rng));
      truth = Rigid3d(q, p);
    }
    data.true_transmitter_from_receiver.push_back(truth);

    RegistrationStation station;
    station.station = i + 1;
    const Eigen::Quaterniond noise_q =
        QuaternionFromRotationVector(Gaussian3(options.tracker_orientation_noise_rad, rng));
    station.tracker_transmitter_from_receiver =
        Rigid3d((noise_q * truth.rotation).normalized(),
                truth.translation + Gaussian3(options.tracker_position_noise_m, rng));
    std::shuffle(ids.begin(), ids.end(), *rng);
    const int k = num_visible(*rng);
    std::vector<int> visible(ids.begin(), ids.begin() + k);
    std::sort(visible.begin(), visible.end());
    for (int id : visible) {
      MarkerObservation m;
      m.marker = id;
      m.marker_in_optical =
          data.optical_from_transmitter * (truth * data.marker_in_receiver.at(id)) +
          Gaussian3(options.optical_noise_m, rng);
      station.markers.push_back(m);
    }
    data.stations.push_back(station);
  }
  return data;
}

}  // namespace trackcal::fit
