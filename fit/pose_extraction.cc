#include "fit/pose_extraction.h"

#include <ceres/ceres.h>

#include <Eigen/Dense>
#include <algorithm>
#include <cmath>
#include <map>
#include <set>
#include <sstream>
#include <stdexcept>

#include "fit/alignment.h"
#include "fit/distributions.h"
#include "fit/marker_model.h"
#include "fit/rotation.h"

namespace trackcal::fit {

namespace {
// Chance that a good station is marked a bad fit, given the stated optical noise.
constexpr double kBadFitFalseAlarm = 1e-3;
}  // namespace

bool PoseExtractionOptions::Check() const {
  return optical_noise_m > 0.0 && min_markers >= 3 && min_marker_spread_m >= 0.0 &&
         max_marker_rms_m > 0.0 && max_num_iterations > 0;
}

const char* PoseStatusName(PoseStatus status) {
  switch (status) {
    case PoseStatus::kOk:
      return "ok";
    case PoseStatus::kTooFewMarkers:
      return "too_few_markers";
    case PoseStatus::kDegenerate:
      return "degenerate";
    case PoseStatus::kBadFit:
      return "bad_fit";
  }
  return "unknown";
}

// Why a marker id is unknown to the registration, as both errors below say it.
constexpr char kUnknownMarker[] =
    ": marker id not in the registration (no registration station it used saw it: a marker of "
    "another body, or a mislabelled one)";

ExtractedPose ExtractPose(int station, const std::vector<MarkerObservation>& markers,
                          const OpticalRegistration& registration,
                          const PoseExtractionOptions& options) {
  if (!options.Check()) throw std::invalid_argument("PoseExtractionOptions: invalid options");
  const std::string where = "station " + std::to_string(station) + ", marker ";
  std::set<int> seen;
  std::vector<Eigen::Vector3d> in_receiver, in_transmitter;
  const Rigid3d transmitter_from_optical = registration.optical_from_transmitter.Inverse();
  for (const MarkerObservation& m : markers) {
    if (!seen.insert(m.marker).second) {
      throw std::invalid_argument(where + std::to_string(m.marker) + ": measured twice");
    }
    if (!m.marker_in_optical.allFinite()) {
      throw std::invalid_argument(where + std::to_string(m.marker) + ": x/y/z not finite");
    }
  }

  ExtractedPose pose;
  pose.station = station;
  pose.num_markers = static_cast<int>(markers.size());
  for (const MarkerObservation& m : markers) {
    if (m.line > 0 && (pose.line == 0 || m.line < pose.line)) pose.line = m.line;
  }
  // Before the marker ids: a station with too few markers has no pose whatever they are, and a
  // marker seen only at such a station is not in the registration either (it skipped the station).
  if (pose.num_markers < options.min_markers) {
    pose.status = PoseStatus::kTooFewMarkers;
    pose.message = std::to_string(pose.num_markers) + " marker(s) visible, need " +
                   std::to_string(options.min_markers);
    return pose;
  }
  for (const MarkerObservation& m : markers) {
    const auto it = registration.marker_in_receiver.find(m.marker);
    if (it == registration.marker_in_receiver.end()) {
      throw std::invalid_argument(where + std::to_string(m.marker) + kUnknownMarker);
    }
    in_receiver.push_back(it->second);
    in_transmitter.push_back(transmitter_from_optical * m.marker_in_optical);
  }
  // Spread: the second singular value of the centred registered positions; collinear markers
  // leave the rotation about their line undetermined.
  Eigen::MatrixXd centred(pose.num_markers, 3);
  Eigen::Vector3d mean = Eigen::Vector3d::Zero();
  for (const auto& r : in_receiver) mean += r;
  mean /= pose.num_markers;
  for (int k = 0; k < pose.num_markers; ++k) centred.row(k) = (in_receiver[k] - mean).transpose();
  const Eigen::Vector3d sv = Eigen::JacobiSVD<Eigen::MatrixXd>(centred).singularValues();
  const double spread = sv(1) / std::sqrt(static_cast<double>(pose.num_markers));
  if (spread < options.min_marker_spread_m) {
    pose.status = PoseStatus::kDegenerate;
    pose.message =
        "visible markers nearly collinear (spread " + std::to_string(spread * 1e3) + " mm)";
    return pose;
  }

  pose.transmitter_from_receiver = AlignPoints(in_receiver, in_transmitter);

  // Refinement and covariance: markers and registration held constant.
  double q0[4], q[4];
  Eigen::Vector3d t0 = registration.optical_from_transmitter.translation;
  QuaternionToXyzwArray(registration.optical_from_transmitter.rotation.normalized(), q0);
  QuaternionToXyzwArray(pose.transmitter_from_receiver.rotation, q);
  Eigen::Vector3d t = pose.transmitter_from_receiver.translation;
  std::vector<Eigen::Vector3d> r = in_receiver;
  ceres::Problem problem;
  SetQuaternionManifold(&problem, q0);
  SetQuaternionManifold(&problem, q);
  const auto sqrt_info = IsotropicSqrtInformation<3>(options.optical_noise_m);
  for (int k = 0; k < pose.num_markers; ++k) {
    problem.AddResidualBlock(
        Whitened<MarkerPositionCost>::Create(sqrt_info, markers[k].marker_in_optical), nullptr, q0,
        t0.data(), q, t.data(), r[k].data());
    problem.SetParameterBlockConstant(r[k].data());
  }
  problem.SetParameterBlockConstant(q0);
  problem.SetParameterBlockConstant(t0.data());
  if (options.refine) {
    ceres::Solver::Options solver_options;
    solver_options.linear_solver_type = ceres::DENSE_QR;
    solver_options.max_num_iterations = options.max_num_iterations;
    solver_options.function_tolerance = 1e-14;
    solver_options.parameter_tolerance = 1e-12;
    solver_options.gradient_tolerance = 1e-14;
    solver_options.logging_type = ceres::SILENT;
    ceres::Solver::Summary summary;
    ceres::Solve(solver_options, &problem, &summary);
    if (summary.IsSolutionUsable()) {
      pose.transmitter_from_receiver = Rigid3d(QuaternionFromXyzwArray(q).normalized(), t);
    }
  }
  QuaternionToXyzwArray(pose.transmitter_from_receiver.rotation, q);
  t = pose.transmitter_from_receiver.translation;

  // Covariance from the 3k x 6 whitened Jacobian in the manifold's tangent space.
  ceres::Problem::EvaluateOptions eval;
  eval.parameter_blocks = {q, t.data()};
  ceres::CRSMatrix crs;
  double cost = 0.0;
  if (problem.Evaluate(eval, &cost, nullptr, nullptr, &crs) && crs.num_cols == 6) {
    Eigen::MatrixXd j = Eigen::MatrixXd::Zero(crs.num_rows, 6);
    for (int row = 0; row < crs.num_rows; ++row) {
      for (int k = crs.rows[row]; k < crs.rows[row + 1]; ++k) j(row, crs.cols[k]) = crs.values[k];
    }
    Eigen::Matrix<double, 6, 6> unit = Eigen::Matrix<double, 6, 6>::Identity();
    unit.topLeftCorner<3, 3>() *= kQuaternionTangentToRotationVector;
    const Eigen::Matrix<double, 6, 6> information = j.transpose() * j;
    pose.covariance = unit * information.inverse() * unit;
  }

  double sum_sq = 0.0;
  for (int k = 0; k < pose.num_markers; ++k) {
    const double e = (pose.transmitter_from_receiver * in_receiver[k] - in_transmitter[k]).norm();
    sum_sq += e * e;
    pose.max_marker_residual_m = std::max(pose.max_marker_residual_m, e);
  }
  pose.marker_rms_m = std::sqrt(sum_sq / pose.num_markers);
  // Above the limit and beyond what the stated noise explains: sum_sq / sigma^2 is chi-square with
  // 3k - 6 degrees of freedom for a good station. Without the second test, 0.5 mm optical noise
  // marked 2 % of good stations (4 markers) bad against the 1 mm limit.
  const int dof = 3 * pose.num_markers - 6;
  const bool beyond_noise =
      dof <= 0 || ChiSquareUpperTail(sum_sq / (options.optical_noise_m * options.optical_noise_m),
                                     dof) < kBadFitFalseAlarm;
  if (pose.marker_rms_m > options.max_marker_rms_m && beyond_noise) {
    pose.status = PoseStatus::kBadFit;
    pose.message = "marker residual RMS " + std::to_string(pose.marker_rms_m * 1e3) + " mm above " +
                   std::to_string(options.max_marker_rms_m * 1e3) + " mm";
  } else {
    pose.status = PoseStatus::kOk;
  }
  // A swapped label among symmetric markers fits as well as the right one: on the simulated paper
  // capture, two labels exchanged at a 3-marker station moved its pose by 180 deg and 69 mm,
  // status kOk, nothing printed. Measure how close the markers in view come to such a symmetry.
  for (int a = 0; a < pose.num_markers; ++a) {
    for (int b = a + 1; b < pose.num_markers; ++b) {
      std::vector<Eigen::Vector3d> swapped = in_receiver;
      std::swap(swapped[a], swapped[b]);
      const Rigid3d fit = AlignPoints(swapped, in_receiver);
      double swap_sq = 0.0;
      for (int k = 0; k < pose.num_markers; ++k) {
        swap_sq += (fit * swapped[k] - in_receiver[k]).squaredNorm();
      }
      const double rms = std::sqrt(swap_sq / pose.num_markers);
      if (rms < pose.label_swap_rms_m) {
        pose.label_swap_rms_m = rms;
        pose.label_swap_markers = {markers[a].marker, markers[b].marker};
      }
    }
  }
  return pose;
}

std::vector<ExtractedPose> ExtractPoses(const std::vector<RegistrationStation>& stations,
                                        const OpticalRegistration& registration,
                                        const PoseExtractionOptions& options,
                                        const std::string& source) {
  std::vector<ExtractedPose> poses;
  poses.reserve(stations.size());
  for (const RegistrationStation& s : stations) {
    for (const MarkerObservation& m : s.markers) {
      if (source.empty() || static_cast<int>(s.markers.size()) < options.min_markers ||
          registration.marker_in_receiver.count(m.marker)) {
        continue;  // (too few markers: no pose, see ExtractPose)
      }
      throw std::invalid_argument(source + (m.line > 0 ? ":" + std::to_string(m.line) : "") +
                                  ": column marker: station " + std::to_string(s.station) +
                                  ", marker " + std::to_string(m.marker) + kUnknownMarker);
    }
    try {
      poses.push_back(ExtractPose(s.station, s.markers, registration, options));
    } catch (const std::invalid_argument& e) {
      if (source.empty()) throw;
      throw std::invalid_argument(source + ": " + e.what());
    }
  }
  return poses;
}

std::string SymmetricMarkersWarning(const std::vector<ExtractedPose>& poses,
                                    const PoseExtractionOptions& options) {
  int count = 0;
  const ExtractedPose* first = nullptr;
  for (const ExtractedPose& p : poses) {
    if (p.status != PoseStatus::kOk || !(p.label_swap_rms_m < options.max_marker_rms_m)) continue;
    if (count++ == 0) first = &p;
  }
  if (first == nullptr) return "";
  std::ostringstream out;
  out.precision(2);
  out << std::fixed << count << " of " << poses.size()
      << " poses come from markers in view so symmetric that two labels swapped would fit as well "
         "(e.g. station "
      << first->station << ", markers " << first->label_swap_markers.first << " and "
      << first->label_swap_markers.second << " exchanged misfit by "
      << first->label_swap_rms_m * 1e3 << " mm, under the " << options.max_marker_rms_m * 1e3
      << " mm bad-fit limit): a swapped label there gives a pose turned up to 180 deg that no "
         "check catches; keep four or more asymmetrically placed markers in view";
  return out.str();
}

std::string NoPoseSummary(const std::vector<ExtractedPose>& poses,
                          const std::vector<int>& stations) {
  const std::set<int> wanted(stations.begin(), stations.end());
  std::map<std::string, std::pair<int, const ExtractedPose*>> why;  // status -> count, first
  for (const ExtractedPose& e : poses) {
    if (!wanted.count(e.station)) continue;
    ++why.emplace(PoseStatusName(e.status), std::make_pair(0, &e)).first->second.first;
  }
  std::string summary;
  for (const auto& [status, entry] : why) {
    // The line too: a markers file is found by line, and its station ids need not be in order.
    const int line = entry.second->line;
    summary += (summary.empty() ? "" : "; ") + std::to_string(entry.first) + " " + status +
               " (e.g. station " + std::to_string(entry.second->station) +
               (line > 0 ? ", line " + std::to_string(line) : "") +
               (entry.second->message.empty() ? "" : ": " + entry.second->message) + ")";
  }
  return summary;
}

}  // namespace trackcal::fit
