// Optical registration (Ikits et al. 2001, section 3.1 and appendix A).
//
// At ~20 registration stations near the transmitter, where field distortion is small, the tracker
// reports the receiver pose transmitter_from_receiver and the optical system measures the positions
// of the markers rigidly mounted around the receiver. RegisterOpticalToTransmitter estimates
//   - optical_from_transmitter (p0, q0 of eq. 10), and
//   - marker_in_receiver for every marker (r_j),
// by total least squares (eq. 14): the true receiver poses are parameters too, pulled towards the
// tracker readings (whitened by the tracker's position and orientation noise), while the predicted
// marker positions are pulled towards the optical measurements (whitened by the optical noise).
// Quaternions live on ceres::EigenQuaternionManifold, which plays the role of the paper's dynamic
// reparameterisation (appendix B).
//
// Gauge: nothing else fixes the receiver frame: moving every receiver pose by a common transform
// and the markers by its inverse leaves the optical predictions unchanged, so the receiver frame is
// the one the tracker reports, defined through the tracker priors.
//
// Residual structure (ResidualStructure): chi-square measures the size of the residuals against
// the assumed noise, so a distortion hides in a generous tracker noise; the spatial trend of the
// per-station tracker residuals does not depend on the assumed noise (an F test).
//
// Goodness of fit: chi_square is the sum of squared whitened residuals at the solution; with
// Gaussian noise of the stated sizes it has expected value nu = (number of optical coordinates) -
// (6 + 3 * number of markers) and standard deviation sqrt(2 nu) (appendix A; the tracker priors and
// the receiver poses add as many residuals as parameters and cancel).

#pragma once

#include <Eigen/Core>
#include <map>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "core/pose.h"
#include "fit/covariance.h"
#include "fit/distributions.h"

namespace trackcal::fit {

// One optical marker measurement.
struct MarkerObservation {
  int marker = 0;                                               // marker id (markers.csv "marker")
  Eigen::Vector3d marker_in_optical = Eigen::Vector3d::Zero();  // [m], optical frame
  int line = 0;  // line of markers.csv it was read from (0: made in memory), for messages
};

// One registration station: the tracker reading and the markers seen at the same receiver pose.
struct RegistrationStation {
  int station = 0;                            // station id (the "station" column)
  Rigid3d tracker_transmitter_from_receiver;  // tracker reading (the noisy input of eq. 14)
  std::vector<MarkerObservation> markers;     // visible markers (the output of eq. 14)
};

struct RegistrationOptions {
  // Standard deviation of each coordinate of an optical marker position [m].
  double optical_noise_m = 1.5e-4;
  // Standard deviation of each coordinate of the tracker's reported position [m].
  double tracker_position_noise_m = 8e-4;
  // Standard deviation of each component of the tracker's orientation error rotation vector [rad].
  double tracker_orientation_noise_rad = 0.15 * kRadPerDeg;
  // Stations with fewer visible markers are left out (and listed in the result).
  int min_markers_per_station = 3;
  // At least this many usable stations are required.
  int min_stations = 3;
  // Levenberg-Marquardt iteration limit.
  int max_num_iterations = 200;
  // Ceres convergence tolerances (relative cost change, relative step size).
  double function_tolerance = 1e-14;
  double parameter_tolerance = 1e-12;
  // Transform and markers whose standard deviation exceeds these are flagged poorly identified.
  double max_translation_stddev_m = 1e-3;
  double max_rotation_stddev_rad = 1e-3;
  double max_marker_stddev_m = 1e-3;
  // Rank and weak-direction thresholds of the covariance analysis.
  CovarianceOptions covariance;
  // Threads for Ceres.
  int num_threads = 1;
  // Leave out stations whose markers do not fit the marker body (a swapped or misidentified
  // marker label, a reflection taken for a marker): after each solve the worst station beyond
  // both tests below is left out and the registration solved again, until none is or
  // max_rejected_fraction of the stations are out. The test places the registered marker body by
  // its own best optical fit at each station, so a distorted tracker reading, which only moves
  // the whole body, never fails it.
  bool reject_bad_stations = true;
  // The body fit's RMS residual must exceed this [m] ...
  double max_station_marker_rms_m = 1e-3;
  // ... and optical_noise_m must not explain it: chi-square (3 x markers - 6 dof) tail below this.
  double station_false_alarm = 1e-3;
  // At most this fraction of the usable stations is left out (rounded down).
  double max_rejected_fraction = 0.2;
  // A station whose tracker reading is far off the others' registration (a hemisphere flip, a
  // reading metres off near metal, another station's reading) is left out too: its whitened
  // tracker residual (norm of the 6-vector) exceeds this many times the median over the stations
  // and its chi-square (6 dof) tail is below station_false_alarm. Kept in, one reading 0.5 m off
  // of 20 put the paper scene's transform 3.1 deg and 34 mm off (0.5 deg, 0.9 mm without it)
  // with no message. The median scale tolerates a distortion (smooth, centimetres) and a generous
  // assumed noise alike.
  double max_tracker_residual_ratio = 5.0;
  bool Check() const;
};

// The result of a registration that later steps need (pose extraction, calibration files).
struct OpticalRegistration {
  Rigid3d optical_from_transmitter;
  std::map<int, Eigen::Vector3d> marker_in_receiver;  // marker id -> r_j [m]
};

struct RegisteredMarker {
  int marker = 0;
  Eigen::Vector3d marker_in_receiver = Eigen::Vector3d::Zero();  // [m]
  Eigen::Vector3d stddev = Eigen::Vector3d::Zero();              // [m], per coordinate
  int num_observations = 0;                                      // stations that saw it
};

struct RegisteredStation {
  int station = 0;
  Rigid3d transmitter_from_receiver;  // total-least-squares estimate of the true receiver pose
  // Its standard deviations: [rotation vector (rad) about transmitter axes; position (m)].
  Eigen::Matrix<double, 6, 1> stddev = Eigen::Matrix<double, 6, 1>::Zero();
  int num_markers = 0;
  double marker_rms_m = 0.0;                      // RMS of the optical residual vectors' norms [m]
  double tracker_position_residual_m = 0.0;       // |estimate - tracker reading| [m]
  double tracker_orientation_residual_rad = 0.0;  // angle between estimate and reading [rad]
  double chi_square = 0.0;  // this station's whitened squared residuals (optical + prior)
  // The registered marker body placed by its best optical fit at this station (no tracker
  // reading): RMS of the residual vectors' norms [m] and the chi-square tail of the residuals
  // under the stated optical noise (3 x markers - 6 dof; 1 with 2 markers or fewer).
  double marker_body_rms_m = 0.0;
  double marker_body_tail = 1.0;
  // Whitened tracker residual, estimate - reading: [position / tracker_position_noise_m;
  // rotation vector of q_estimate * conj(q_reading) / tracker_orientation_noise_rad].
  Eigen::Matrix<double, 6, 1> tracker_residual_whitened = Eigen::Matrix<double, 6, 1>::Zero();
};

// Is there spatial structure in the tracker residuals? Random noise scatters them independently
// from station to station; a distorted field at the registration stations makes them vary smoothly
// with position. Each component of the whitened tracker residuals is regressed on (1, x, y, z) of
// the station position: F = (explained / trend_dof) / (unexplained / residual_dof), which does not
// depend on the noise levels assumed, compared with the F(trend_dof, residual_dof) distribution.
// The part of a distortion that looks like a rigid change of frame is absorbed by
// optical_from_transmitter and cannot show here; what remains (its variation over the stations) does.
struct ResidualStructure {
  double explained = 0.0;    // sum of squares of the fitted trend
  double unexplained = 0.0;  // sum of squares of what the trend leaves
  int trend_dof = 0;         // 6 components x 4 regressors
  int residual_dof = 0;      // 6 x stations - trend_dof
  double f_statistic = 0.0;
  double p_value = 1.0;  // P(F >= f_statistic) for noise alone
  // Fraction of each component's sum of squares the trend explains (x, y, z, rx, ry, rz).
  Eigen::Matrix<double, 6, 1> explained_fraction = Eigen::Matrix<double, 6, 1>::Zero();
  bool Flagged(double alpha = 1e-3) const { return residual_dof > 0 && p_value < alpha; }
};

// A station left out because its markers do not fit the marker body or its tracker reading is far
// off (RegistrationOptions::reject_bad_stations); its values are from the solve that still
// included it.
struct RejectedStation {
  int station = 0;
  int num_markers = 0;
  double marker_body_rms_m = 0.0;
  double marker_body_tail = 1.0;
  // Why: "marker_body" (its markers misfit the marker body) or "tracker_reading" (its tracker
  // reading is far off the registration of the others; the residuals below say how far).
  std::string reason = "marker_body";
  double tracker_position_residual_m = 0.0;
  double tracker_orientation_residual_rad = 0.0;
  // Why it was left out, in words, for messages: "its 5 markers misfit the marker body by ...".
  std::string Why() const;
};

struct RegistrationResult {
  OpticalRegistration registration;
  // Covariance of optical_from_transmitter as a 6-vector [rotation vector (rad) of a left
  // perturbation, i.e. about optical-frame axes; translation (m)].
  Eigen::Matrix<double, 6, 6> optical_from_transmitter_covariance =
      Eigen::Matrix<double, 6, 6>::Zero();
  Eigen::Matrix<double, 6, 1> optical_from_transmitter_stddev = Eigen::Matrix<double, 6, 1>::Zero();
  std::vector<RegisteredMarker> markers;    // sorted by id
  std::vector<RegisteredStation> stations;  // used stations, input order
  std::vector<int> skipped_stations;        // ids with too few markers
  std::vector<RejectedStation> rejected_stations;  // left out, in the order they were left out

  int num_marker_observations = 0;  // optical measurements used (each 3 coordinates)
  int num_parameters = 0;           // M = 6 + 3 * number of markers
  double chi_square = 0.0;          // at the solution (eq. 14)
  double nu = 0.0;                  // expected chi-square: 3 * observations - M
  double chi_square_stddev = 0.0;   // sqrt(2 nu)
  ResidualStructure residual_structure;  // spatial trend of the tracker residuals
  // (chi_square - nu) / sqrt(2 nu): beyond about +-3 the noise model or the data are suspect.
  double ChiSquareZ() const;

  bool converged = false;       // the solver reported convergence
  bool identifiable = false;    // full-rank information matrix and no flagged transform coordinate
  CovarianceResult covariance;  // transform + markers, with rank report and flags
  std::string initialisation;   // which closed form gave the starting point
  std::string solver_report;    // ceres BriefReport
  int num_iterations = 0;

  // Multi-line summary: transform with standard deviations, chi-square against nu, flags.
  std::string ToString() const;
  // Everything above for --json: transform (rotation_xyzw, translation, covariance, stddev),
  // markers, per-station residuals, chi-square, residual structure, solver and identifiability.
  nlohmann::json ToJson() const;
};

// Throws std::invalid_argument for invalid options or input (non-finite values, duplicate
// station or marker ids, a non-unit tracker quaternion, too few usable stations), naming the
// station, marker and field. A rank-deficient geometry is not an error: it is reported through
// `identifiable` and the covariance flags.

RegistrationResult RegisterOpticalToTransmitter(const std::vector<RegistrationStation>& stations,
                                                const RegistrationOptions& options = {});

}  // namespace trackcal::fit
