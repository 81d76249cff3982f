// Registration refined with a fitted correction (docs/registration.md, "Refinement").
//
// The registration (fit/registration.h) trusts the tracker at the registration stations up to
// random noise. Where the field is distorted there (the paper room's workbench frame, 0.35 m from
// the transmitter), the tracker readings are biased by millimetres and tenths of a degree, and so
// is optical_from_transmitter. RefineRegistration iterates
//
//   register (tracker readings as corrected so far)
//     -> extract the reference pose of every calibration station from its markers
//     -> fit a correction to (raw tracker reading, extracted reference) at the calibration stations
//     -> correct the registration stations' raw readings with it
//     -> re-register, with the tracker noise of the priors raised by the correction's residual RMS
//
// until optical_from_transmitter stops moving. The fitter is a callback, so any model works: the
// fit engine with a model file (MakeEngineFitter), or a physical model.
//
// What can and cannot work: a correction that can represent a rigid change of the transmitter frame
// (a polynomial of degree >= 1, a LUT) re-expresses itself in whatever frame the registration
// chose, so in theory every registration is a fixed point; in practice a polynomial also
// extrapolates badly at the registration stations (near the transmitter, outside the calibration
// grid) and the loop drifts away, which the loop detects (`diverged`: a round moved further than
// the previous one) and then keeps the initial registration. Only a model whose structure fixes the
// transmitter frame (a physical model: the free-space dipole field is centred and oriented in the
// transmitter's own frame) can tell a distorted field from a rotated frame and pull the
// registration to the true one. docs/registration.md shows both.
//
// The covariance of the refined registration is conditioned on the last fitted correction: the
// correction's parameters are held at their estimates; their uncertainty, and the model's misfit,
// enter only through the tracker noise of the priors, raised to sqrt(noise^2 + RMS^2) per axis with
// the correction's residual RMS at the calibration stations (which includes the reference noise,
// so it is conservative for a perfect model).

#pragma once

#include <functional>
#include <string>
#include <vector>

#include "core/correction.h"
#include "fit/fit_engine.h"
#include "fit/model_file.h"
#include "fit/pose_extraction.h"
#include "fit/registration.h"

namespace trackcal::fit {

// A correction fitted to calibration stations (reported = raw tracker reading, reference =
// extracted pose).
struct FittedCorrection {
  CorrectionChain chain;    // applied to the registration stations' raw readings (no volume guard)
  std::string description;  // one line for reports ("polynomial degree 4, chi2/dof 1.02")
  bool converged = true;    // the fitter's own convergence
};

// Fits a correction; throws std::invalid_argument if it cannot (too few stations, bad model).
using CorrectionFitter = std::function<FittedCorrection(const std::vector<FitStation>&)>;

// The fit engine (fit/fit_engine.h) with a fresh spec from make_spec at every call.
CorrectionFitter MakeEngineFitter(std::function<ModelSpec()> make_spec);

struct RegistrationRefinementOptions {
  RegistrationOptions registration;  // every registration of the loop (noise of the raw readings)
  PoseExtractionOptions extraction;  // reference poses of the calibration stations
  int max_iterations = 20;           // register-fit-correct rounds after the initial registration
  // Converged when one round moves optical_from_transmitter by less than both of these.
  double rotation_tolerance_rad = 1e-6;
  double translation_tolerance_m = 1e-6;
  // Raise the priors' tracker noise by the correction's residual RMS (see the file comment).
  bool add_correction_residual_to_tracker_noise = true;
  // At least this many calibration stations with a usable pose are required.
  int min_calibration_stations = 10;
  bool Check() const;
};

// One round of the loop.
struct RefinementRound {
  int round = 0;                     // 1, 2, ...
  Rigid3d optical_from_transmitter;  // after this round's registration
  double rotation_change_rad = 0.0;  // angle moved since the previous registration
  double translation_change_m = 0.0;
  double chi_square_z = 0.0;               // of this round's registration
  int num_calibration_stations = 0;        // fitted (usable extracted pose)
  double correction_position_rms_m = 0.0;  // residual RMS per axis at the calibration stations
  double correction_orientation_rms_rad = 0.0;
  // Mean change the correction makes to the registration stations' readings.
  double mean_registration_correction_m = 0.0;
  double mean_registration_correction_rad = 0.0;
  std::string correction;  // FittedCorrection::description
};

struct RegistrationRefinementResult {
  RegistrationResult initial;  // from the raw tracker readings (the paper's registration)
  RegistrationResult refined;  // from the corrected readings of the last round
  std::vector<RefinementRound> rounds;
  bool converged = false;  // the transform stopped moving within max_iterations
  // A round moved the transform further than the one before (rotation and translation): the loop
  // stopped and `refined` is `initial` (see the file comment on polynomials).
  bool diverged = false;
  FittedCorrection correction;       // the last fitted correction
  std::vector<ExtractedPose> poses;  // calibration stations, extracted with `refined`
  std::string conditioning;          // what the refined covariance is conditioned on
  std::string ToString() const;
  nlohmann::json ToJson() const;  // {initial, refined, rounds, converged, conditioning}
};

// Throws std::invalid_argument for invalid options, input the registration rejects, or fewer
// than min_calibration_stations usable calibration stations.
RegistrationRefinementResult RefineRegistration(
    const std::vector<RegistrationStation>& registration_stations,
    const std::vector<RegistrationStation>& calibration_stations, const CorrectionFitter& fitter,
    const RegistrationRefinementOptions& options = {});

}  // namespace trackcal::fit
