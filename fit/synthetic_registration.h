// Synthetic registration captures with known truth, for the estimator tests (and later the Python
// fixtures): options in, dataset out.

#pragma once

#include <Eigen/Core>
#include <map>
#include <random>
#include <vector>

#include "core/pose.h"
#include "fit/registration.h"

namespace trackcal::fit {

struct SyntheticRegistrationOptions {
  int num_stations = 20;                // registration stations
  int num_markers = 6;                  // markers on the rigid body, ids 1..num_markers
  double marker_distance_min_m = 0.05;  // markers along +-x, +-y, +-z of the receiver at a
  double marker_distance_max_m = 0.08;  // distance drawn uniformly in [min, max] ...
  double marker_jitter_m = 0.01;        // ... plus this much uniform jitter per coordinate
  // Receiver positions uniform in a cube of this half-size around station_center [m].
  double station_half_size_m = 0.25;
  Eigen::Vector3d station_center_in_transmitter = Eigen::Vector3d(0.3, 0.0, 0.2);
  bool random_orientations = true;  // false: every station has the same orientation
  // > 0: orientations within this angle of one nominal orientation (a platform that is only
  // tilted) instead of uniform over all rotations [rad].
  double max_rotation_from_nominal_rad = 0.0;
  bool identical_stations = false;             // every station at the first station's pose
  int min_visible = 3;                         // visible markers per station drawn uniformly in
  int max_visible = 6;                         // [min_visible, max_visible] (capped by num_markers)
  double optical_distance_m = 2.0;             // |translation| of optical_from_transmitter
  double optical_noise_m = 0.0;                // per-coordinate Gaussian noise of markers
  double tracker_position_noise_m = 0.0;       // per-coordinate Gaussian noise of tracker position
  double tracker_orientation_noise_rad = 0.0;  // per-axis Gaussian rotation-vector noise (left)
};

struct SyntheticRegistration {
  Rigid3d optical_from_transmitter;                     // truth
  std::map<int, Eigen::Vector3d> marker_in_receiver;    // truth
  std::vector<Rigid3d> true_transmitter_from_receiver;  // per station, truth
  std::vector<RegistrationStation> stations;            // noisy measurements
};

SyntheticRegistration MakeSyntheticRegistration(const SyntheticRegistrationOptions& options,
                                                std::mt19937_64* rng);

}  // namespace trackcal::fit
