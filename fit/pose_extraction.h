// Receiver pose from optical marker positions (Ikits et al. 2001, section 3.2).
//
// With the registration known (optical_from_transmitter and marker_in_receiver), the markers seen
// at a station give the receiver pose transmitter_from_receiver by inverting eq. 10: the measured
// markers are mapped into the transmitter frame and aligned with the registered marker positions
// (closed form, Horn/Kabsch), then refined by Ceres on the optical residuals whitened by the
// optical noise, which also yields the pose covariance. No tracker reading is used, so the result
// is an independent reference for the tracker's report at that station.

#pragma once

#include <Eigen/Core>
#include <limits>
#include <string>
#include <utility>
#include <vector>

#include "core/pose.h"
#include "fit/registration.h"

namespace trackcal::fit {

struct PoseExtractionOptions {
  // Standard deviation of each coordinate of an optical marker position [m].
  double optical_noise_m = 1.5e-4;
  // Fewer visible markers than this: no pose (3 is the minimum for a rigid pose).
  int min_markers = 3;
  // Smallest spread of the visible markers (second singular value of their centred positions in
  // the receiver frame, RMS metres) below which the pose is degenerate (collinear markers).
  double min_marker_spread_m = 5e-3;
  // A station whose marker residual RMS exceeds this is flagged as a bad fit [m], unless
  // optical_noise_m explains it (chi-square tail above 1e-3: only with noise above ~0.4 mm).
  double max_marker_rms_m = 1e-3;
  // Refine the closed form with Ceres (gives the covariance; the closed form is already the
  // least-squares optimum for isotropic equal noise).
  bool refine = true;
  int max_num_iterations = 50;
  bool Check() const;
};

enum class PoseStatus {
  kOk,             // pose estimated and residuals within max_marker_rms_m
  kTooFewMarkers,  // fewer than min_markers visible: no pose
  kDegenerate,     // visible markers (nearly) collinear: no reliable orientation
  kBadFit,         // pose estimated but residual RMS above max_marker_rms_m
};
const char* PoseStatusName(PoseStatus status);

struct ExtractedPose {
  int station = 0;
  int line = 0;  // markers.csv line of the station's first marker row (0: made in memory)
  PoseStatus status = PoseStatus::kTooFewMarkers;
  Rigid3d transmitter_from_receiver;  // valid for kOk and kBadFit
  int num_markers = 0;
  double marker_rms_m = 0.0;  // RMS of residual vector norms [m]
  double max_marker_residual_m = 0.0;
  // [rotation vector (rad) of a left perturbation about transmitter axes; position (m)], from the
  // optical noise alone (the registration's own uncertainty is not propagated).
  Eigen::Matrix<double, 6, 6> covariance = Eigen::Matrix<double, 6, 6>::Zero();
  std::string message;  // why the status is not kOk
  // How well the markers in view would fit with two of their labels exchanged: the smallest RMS
  // [m] of the registered positions, two swapped, aligned onto themselves, over every pair
  // (label_swap_markers). Below max_marker_rms_m a swap between frames gives an kOk pose turned
  // (up to 180 deg) that nothing here detects: a symmetric set of markers in view, e.g. any three
  // of the paper's six (+-60 mm on the receiver axes). Set with a pose; infinity without.
  double label_swap_rms_m = std::numeric_limits<double>::infinity();
  std::pair<int, int> label_swap_markers = {0, 0};
  bool HasPose() const { return status == PoseStatus::kOk || status == PoseStatus::kBadFit; }
};

// Pose of the receiver at one station. Throws std::invalid_argument if a marker id is not in the
// registration, a marker is measured twice, or a value is not finite (naming station and marker).
ExtractedPose ExtractPose(int station, const std::vector<MarkerObservation>& markers,
                          const OpticalRegistration& registration,
                          const PoseExtractionOptions& options = {});

// ExtractPose for every registration-style station (the tracker reading is not used). `source`
// (the markers file, when known) prefixes ExtractPose's errors.
std::vector<ExtractedPose> ExtractPoses(const std::vector<RegistrationStation>& stations,
                                        const OpticalRegistration& registration,
                                        const PoseExtractionOptions& options = {},
                                        const std::string& source = "");

// "" unless some kOk pose comes from markers in view whose label_swap_rms_m is under
// options.max_marker_rms_m; else a sentence that says how many, names the first station and pair,
// and what to do (four or more asymmetrically placed markers in view). For warnings.
std::string SymmetricMarkersWarning(const std::vector<ExtractedPose>& poses,
                                    const PoseExtractionOptions& options = {});

// "" when `stations` is empty; else, for the poses of those stations (the ones given no pose
// record, e.g. MakePoseRecords' left_out), how many per status with the first station, its line
// in markers.csv when known, and its message: "620 degenerate (e.g. station 1, line 2: visible
// markers nearly collinear (spread 0.000 mm))".
// For warnings and errors.
std::string NoPoseSummary(const std::vector<ExtractedPose>& poses,
                          const std::vector<int>& stations);

}  // namespace trackcal::fit
