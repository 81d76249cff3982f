#include "fit/registration_refinement.h"

#include <cmath>
#include <cstdio>
#include <sstream>
#include <stdexcept>

#include "fit/rotation.h"

namespace trackcal::fit {

CorrectionFitter MakeEngineFitter(std::function<ModelSpec()> make_spec) {
  return [make_spec](const std::vector<FitStation>& stations) {
    ModelSpec spec = make_spec();
    FitOptions options;
    options.compute_covariance = false;  // only the fitted values are used
    const FitResult fit = FitModel(stations, &spec, options);
    FittedCorrection out;
    out.chain = fit.chain;
    out.chain.ClearVolume();
    out.converged = fit.converged;
    char buf[160];
    std::snprintf(buf, sizeof(buf), "%s: %zu term(s), chi2/dof %.3g, %d iterations",
                  spec.source.c_str(), spec.terms.size(), fit.chi2_per_dof, fit.iterations);
    out.description = buf;
    return out;
  };
}

bool RegistrationRefinementOptions::Check() const {
  return registration.Check() && extraction.Check() && max_iterations >= 1 &&
         rotation_tolerance_rad > 0.0 && translation_tolerance_m > 0.0 &&
         min_calibration_stations >= 1;
}

namespace {

std::string Fmt(const char* fmt, double v) {
  char buf[64];
  std::snprintf(buf, sizeof(buf), fmt, v);
  return buf;
}

}  // namespace

RegistrationRefinementResult RefineRegistration(
    const std::vector<RegistrationStation>& registration_stations,
    const std::vector<RegistrationStation>& calibration_stations, const CorrectionFitter& fitter,
    const RegistrationRefinementOptions& options) {
  if (!options.Check())
    throw std::invalid_argument("RegistrationRefinementOptions: invalid options");
  if (!fitter) throw std::invalid_argument("RefineRegistration: no correction fitter");
  RegistrationRefinementResult result;
  result.initial = RegisterOpticalToTransmitter(registration_stations, options.registration);
  RegistrationResult current = result.initial;
  std::vector<RegistrationStation> corrected = registration_stations;

  for (int round = 1; round <= options.max_iterations; ++round) {
    RefinementRound r;
    r.round = round;
    // References of the calibration stations in the current transmitter frame.
    result.poses = ExtractPoses(calibration_stations, current.registration, options.extraction);
    std::vector<FitStation> fit_stations;
    for (size_t i = 0; i < calibration_stations.size(); ++i) {
      const ExtractedPose& pose = result.poses[i];
      if (pose.status != PoseStatus::kOk) continue;
      FitStation s;
      s.reported = calibration_stations[i].tracker_transmitter_from_receiver;
      s.reported.rotation.normalize();
      s.reference = pose.transmitter_from_receiver;
      s.station = calibration_stations[i].station;
      fit_stations.push_back(s);
    }
    r.num_calibration_stations = static_cast<int>(fit_stations.size());
    if (r.num_calibration_stations < options.min_calibration_stations) {
      throw std::invalid_argument(
          "registration refinement: " + std::to_string(fit_stations.size()) +
          " calibration station(s) with a usable extracted pose, need at least " +
          std::to_string(options.min_calibration_stations));
    }
    result.correction = fitter(fit_stations);
    r.correction = result.correction.description;

    // The correction's residual at the calibration stations, RMS per axis.
    double sp = 0.0, so = 0.0;
    for (const FitStation& s : fit_stations) {
      const Rigid3d c = result.correction.chain.Apply(s.reported).pose;
      sp += (c.translation - s.reference.translation).squaredNorm();
      so += RotationVectorBetween<double>(c.rotation, s.reference.rotation).squaredNorm();
    }
    r.correction_position_rms_m = std::sqrt(sp / (3.0 * fit_stations.size()));
    r.correction_orientation_rms_rad = std::sqrt(so / (3.0 * fit_stations.size()));

    // Corrected readings at the registration stations.
    double dp = 0.0, dq = 0.0;
    for (size_t i = 0; i < registration_stations.size(); ++i) {
      Rigid3d raw = registration_stations[i].tracker_transmitter_from_receiver;
      raw.rotation.normalize();
      const Rigid3d c = result.correction.chain.Apply(raw).pose;
      dp += (c.translation - raw.translation).norm();
      dq += AngularDistance(c.rotation, raw.rotation);
      corrected[i].tracker_transmitter_from_receiver =
          Rigid3d(c.rotation.normalized(), c.translation);
    }
    const double n = static_cast<double>(registration_stations.size());
    r.mean_registration_correction_m = n > 0 ? dp / n : 0.0;
    r.mean_registration_correction_rad = n > 0 ? dq / n : 0.0;

    RegistrationOptions reg_options = options.registration;
    if (options.add_correction_residual_to_tracker_noise) {
      reg_options.tracker_position_noise_m =
          std::hypot(reg_options.tracker_position_noise_m, r.correction_position_rms_m);
      reg_options.tracker_orientation_noise_rad =
          std::hypot(reg_options.tracker_orientation_noise_rad, r.correction_orientation_rms_rad);
    }
    RegistrationResult next = RegisterOpticalToTransmitter(corrected, reg_options);
    const Rigid3d& a = current.registration.optical_from_transmitter;
    const Rigid3d& b = next.registration.optical_from_transmitter;
    r.rotation_change_rad = AngularDistance(a.rotation, b.rotation);
    r.translation_change_m = (a.translation - b.translation).norm();
    r.optical_from_transmitter = b;
    r.chi_square_z = next.ChiSquareZ();
    current = std::move(next);
    result.rounds.push_back(r);
    if (r.rotation_change_rad < options.rotation_tolerance_rad &&
        r.translation_change_m < options.translation_tolerance_m) {
      result.converged = true;
      break;
    }
    // A loop that does not contract is not converging to a registration: the correction cannot
    // fix the frame (or extrapolates wildly at the registration stations). Keep the initial one.
    if (result.rounds.size() >= 2) {
      const RefinementRound& previous = result.rounds[result.rounds.size() - 2];
      if (r.rotation_change_rad >= previous.rotation_change_rad &&
          r.translation_change_m >= previous.translation_change_m) {
        result.diverged = true;
        break;
      }
    }
  }
  result.refined = result.diverged ? result.initial : std::move(current);
  result.poses =
      ExtractPoses(calibration_stations, result.refined.registration, options.extraction);
  result.conditioning =
      "covariance conditioned on the last fitted correction (its parameters held fixed); the "
      "tracker priors' noise is sqrt(noise^2 + residual RMS^2) per axis with the correction's "
      "residual RMS at the calibration stations (" +
      Fmt("%.3f", result.rounds.back().correction_position_rms_m * 1e3) + " mm, " +
      Fmt("%.4f", result.rounds.back().correction_orientation_rms_rad * kDegPerRad) + " deg)";
  if (result.diverged) {
    result.conditioning =
        "refinement diverged (the transform moved more in each round): the initial registration is "
        "kept; the correction cannot tell a distorted field from a rotated frame (a polynomial or "
        "LUT), or it extrapolates badly at the registration stations";
  } else if (!options.add_correction_residual_to_tracker_noise) {
    result.conditioning =
        "covariance conditioned on the last fitted correction (its parameters held fixed, its "
        "residual not added to the tracker noise)";
  }
  return result;
}

std::string RegistrationRefinementResult::ToString() const {
  std::ostringstream out;
  out << "Initial registration (raw tracker readings):\n" << initial.ToString() << "\n";
  out << "Refinement rounds (register -> extract -> fit correction -> correct readings):\n";
  for (const RefinementRound& r : rounds) {
    out << "  round " << r.round << ": moved " << Fmt("%.5f", r.rotation_change_rad * kDegPerRad)
        << " deg, " << Fmt("%.4f", r.translation_change_m * 1e3) << " mm; chi-square z "
        << Fmt("%.2f", r.chi_square_z) << "; correction at registration stations "
        << Fmt("%.3f", r.mean_registration_correction_m * 1e3) << " mm, "
        << Fmt("%.4f", r.mean_registration_correction_rad * kDegPerRad) << " deg; residual RMS at "
        << r.num_calibration_stations << " calibration stations "
        << Fmt("%.3f", r.correction_position_rms_m * 1e3) << " mm, "
        << Fmt("%.4f", r.correction_orientation_rms_rad * kDegPerRad) << " deg (" << r.correction
        << ")\n";
  }
  out << (converged  ? "converged"
          : diverged ? "DIVERGED: the initial registration is kept"
                     : "NOT converged (transform still moving)")
      << "\n";
  out << "Refined registration:\n" << refined.ToString() << "\n" << conditioning << "\n";
  return out.str();
}

nlohmann::json RegistrationRefinementResult::ToJson() const {
  nlohmann::json round_list = nlohmann::json::array();
  for (const RefinementRound& r : rounds) {
    const Rigid3d& t = r.optical_from_transmitter;
    round_list.push_back(
        {{"round", r.round},
         {"rotation_xyzw", {t.rotation.x(), t.rotation.y(), t.rotation.z(), t.rotation.w()}},
         {"translation", {t.translation.x(), t.translation.y(), t.translation.z()}},
         {"rotation_change_deg", r.rotation_change_rad * kDegPerRad},
         {"translation_change_mm", r.translation_change_m * 1e3},
         {"chi_square_z", r.chi_square_z},
         {"num_calibration_stations", r.num_calibration_stations},
         {"correction_position_rms_mm", r.correction_position_rms_m * 1e3},
         {"correction_orientation_rms_deg", r.correction_orientation_rms_rad * kDegPerRad},
         {"mean_registration_correction_mm", r.mean_registration_correction_m * 1e3},
         {"mean_registration_correction_deg", r.mean_registration_correction_rad * kDegPerRad},
         {"correction", r.correction}});
  }
  return {{"initial", initial.ToJson()}, {"refined", refined.ToJson()},
          {"rounds", round_list},        {"converged", converged},
          {"diverged", diverged},        {"conditioning", conditioning}};
}

}  // namespace trackcal::fit
