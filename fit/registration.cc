#include "fit/registration.h"

#include <ceres/ceres.h>

#include <Eigen/Dense>
#include <Eigen/SVD>
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <limits>
#include <memory>
#include <set>
#include <sstream>
#include <stdexcept>

#include "fit/alignment.h"
#include "fit/marker_model.h"
#include "fit/rotation.h"

namespace trackcal::fit {

bool RegistrationOptions::Check() const {
  return optical_noise_m > 0.0 && tracker_position_noise_m > 0.0 &&
         tracker_orientation_noise_rad > 0.0 && min_markers_per_station >= 1 && min_stations >= 1 &&
         max_num_iterations > 0 && function_tolerance > 0.0 && parameter_tolerance > 0.0 &&
         max_translation_stddev_m > 0.0 && max_rotation_stddev_rad > 0.0 &&
         max_marker_stddev_m > 0.0 && covariance.Check() && num_threads >= 1 &&
         max_station_marker_rms_m >= 0.0 && station_false_alarm > 0.0 &&
         station_false_alarm < 1.0 && max_rejected_fraction >= 0.0 && max_rejected_fraction < 1.0 &&
         max_tracker_residual_ratio > 1.0;
}

double RegistrationResult::ChiSquareZ() const {
  return chi_square_stddev > 0.0 ? (chi_square - nu) / chi_square_stddev : 0.0;
}

namespace {

constexpr int kInitialAlternations = 5;
// Tracker quaternions are normalised; a norm further than this from one is a corrupt reading (a
// Fastrak prints 4-5 decimals, so rounding alone stays below 1e-4).
constexpr double kMaxQuaternionNormError = 1e-3;

std::string Fmt(const char* fmt, double v) {
  char buf[64];
  std::snprintf(buf, sizeof(buf), fmt, v);
  return buf;
}

std::string StationField(const RegistrationStation& s, const std::string& field) {
  return "registration station " + std::to_string(s.station) + ", " + field;
}

void ValidateStations(const std::vector<RegistrationStation>& stations) {
  std::set<int> ids;
  for (const RegistrationStation& s : stations) {
    if (!ids.insert(s.station).second) {
      throw std::invalid_argument("registration station " + std::to_string(s.station) +
                                  ": duplicate station id");
    }
    const Rigid3d& t = s.tracker_transmitter_from_receiver;
    if (!t.translation.allFinite()) {
      throw std::invalid_argument(StationField(s, "tracker x/y/z: not finite"));
    }
    if (!t.rotation.coeffs().allFinite() ||
        std::abs(t.rotation.norm() - 1.0) > kMaxQuaternionNormError) {
      throw std::invalid_argument(
          StationField(s, "tracker qw/qx/qy/qz: not a unit quaternion (norm " +
                              std::to_string(t.rotation.norm()) + ")"));
    }
    std::set<int> markers;
    for (const MarkerObservation& m : s.markers) {
      if (!markers.insert(m.marker).second) {
        throw std::invalid_argument(StationField(s, "marker " + std::to_string(m.marker)) +
                                    ": measured twice");
      }
      if (!m.marker_in_optical.allFinite()) {
        throw std::invalid_argument(StationField(s, "marker " + std::to_string(m.marker)) +
                                    ": x/y/z not finite");
      }
    }
  }
}

// Working copy of the problem: dense marker indices and the parameter blocks.
struct Problem {
  std::vector<RegistrationStation> stations;  // usable stations, tracker quaternions normalised
  std::vector<int> marker_ids;                // index -> id
  std::map<int, int> marker_index;            // id -> index
  std::vector<int> marker_observations;       // per marker index
  int num_observations = 0;
};

// Rotation R0 of optical_from_transmitter from marker differences alone: for two markers j, k seen
// at station i, d = y_ij - y_ik = R0 R_i (r_j - r_k), so R_i^T R0^T d equals the same unknown
// e_jk = r_j - r_k at every station. Stacking R_i^T M d_ijk - e_jk = 0 gives a homogeneous linear
// system in (vec(M), e); its null vector is (vec(R0^T), e) up to scale. Needs stations with several
// orientations; returns false when the null space is not one-dimensional, with *why_not saying
// which way it failed.
bool RotationFromMarkerDifferences(const Problem& p, Eigen::Quaterniond* optical_from_transmitter,
                                   std::string* why_not) {
  std::map<std::pair<int, int>, int> pair_index;
  struct Row {
    Eigen::Matrix3d r_transpose;
    Eigen::Vector3d d;
    int pair;
  };
  std::vector<Row> rows;
  for (const RegistrationStation& s : p.stations) {
    const Eigen::Matrix3d rt =
        s.tracker_transmitter_from_receiver.rotation.toRotationMatrix().transpose();
    for (std::size_t a = 0; a < s.markers.size(); ++a) {
      for (std::size_t b = a + 1; b < s.markers.size(); ++b) {
        const MarkerObservation* ma = &s.markers[a];
        const MarkerObservation* mb = &s.markers[b];
        if (ma->marker > mb->marker) std::swap(ma, mb);
        const auto key = std::make_pair(ma->marker, mb->marker);
        auto it = pair_index.emplace(key, static_cast<int>(pair_index.size())).first;
        rows.push_back({rt, ma->marker_in_optical - mb->marker_in_optical, it->second});
      }
    }
  }
  const int num_unknowns = 9 + 3 * static_cast<int>(pair_index.size());
  const int num_rows = 3 * static_cast<int>(rows.size());
  if (num_rows < num_unknowns + 1) {
    *why_not = "too few marker pairs for the marker-difference rotation";
    return false;
  }
  Eigen::MatrixXd a = Eigen::MatrixXd::Zero(num_rows, num_unknowns);
  for (std::size_t r = 0; r < rows.size(); ++r) {
    // M d = sum_c d_c M.col(c) -> coefficient of vec(M) (column-major) is d_c * I.
    for (int c = 0; c < 3; ++c) {
      a.block<3, 3>(3 * r, 3 * c) = rows[r].d(c) * rows[r].r_transpose;
    }
    a.block<3, 3>(3 * r, 9 + 3 * rows[r].pair) = -Eigen::Matrix3d::Identity();
  }
  Eigen::BDCSVD<Eigen::MatrixXd> svd(a, Eigen::ComputeThinV);
  const Eigen::VectorXd& sv = svd.singularValues();
  const int n = num_unknowns;
  // The true solution makes the smallest singular value ~noise; a second small one means the
  // stations do not constrain the rotation (e.g. all with the same orientation); a smallest one
  // not well below the others means no rotation fits the differences.
  if (!(sv(n - 2) > 1e-3 * sv(0))) {
    *why_not = "stations lack orientation diversity";
    return false;
  }
  if (!(sv(n - 1) < 0.1 * sv(n - 2))) {
    *why_not =
        "marker differences inconsistent between stations: a mislabelled or moved marker, or "
        "optical noise large against the marker spacing";
    return false;
  }
  const Eigen::VectorXd z = svd.matrixV().col(n - 1);
  Eigen::Matrix3d m = Eigen::Map<const Eigen::Matrix3d>(z.data());
  if (m.norm() < 1e-6) {
    *why_not = "marker-difference rotation degenerate";
    return false;
  }
  if (m.determinant() < 0.0) m = -m;
  const Eigen::Matrix3d rotation = NearestRotation(m).transpose();
  *optical_from_transmitter = Eigen::Quaterniond(rotation).normalized();
  return true;
}

// Rotation R0 from receiver positions: the tracker's p_i against the centroid of the visible
// markers. The centroid is off by the marker offsets (centimetres), so this is only a start.
Eigen::Quaterniond RotationFromCentroids(const Problem& p) {
  std::vector<Eigen::Vector3d> from, to;
  for (const RegistrationStation& s : p.stations) {
    Eigen::Vector3d c = Eigen::Vector3d::Zero();
    for (const MarkerObservation& m : s.markers) c += m.marker_in_optical;
    from.push_back(s.tracker_transmitter_from_receiver.translation);
    to.push_back(c / static_cast<double>(s.markers.size()));
  }
  return AlignPoints(from, to).rotation;
}

// Given R0 and the tracker poses, R0^T y_ij = R_i r_j + c p_i + u is linear in the markers r_j,
// u = R0^T t0 and, if `with_scale`, the tracker scale c (else c = 1 and p_i moves to the right-hand
// side). Columns: 3 per marker, then c (if any), then u. Minimum-norm least squares solution.
Eigen::VectorXd SolveMarkerSystem(const Problem& p, const Eigen::Quaterniond& r0, bool with_scale) {
  const int nm = static_cast<int>(p.marker_ids.size());
  const int scale_columns = with_scale ? 1 : 0;
  Eigen::MatrixXd a = Eigen::MatrixXd::Zero(3 * p.num_observations, 3 * nm + scale_columns + 3);
  Eigen::VectorXd b(3 * p.num_observations);
  const Eigen::Matrix3d r0t = r0.toRotationMatrix().transpose();
  int row = 0;
  for (const RegistrationStation& s : p.stations) {
    const Rigid3d& x = s.tracker_transmitter_from_receiver;
    const Eigen::Matrix3d ri = x.rotation.toRotationMatrix();
    for (const MarkerObservation& m : s.markers) {
      a.block<3, 3>(row, 3 * p.marker_index.at(m.marker)) = ri;
      if (with_scale) a.block<3, 1>(row, 3 * nm) = x.translation;
      a.block<3, 3>(row, 3 * nm + scale_columns) = Eigen::Matrix3d::Identity();
      b.segment<3>(row) =
          r0t * m.marker_in_optical - (with_scale ? Eigen::Vector3d::Zero() : x.translation);
      row += 3;
    }
  }
  return a.completeOrthogonalDecomposition().solve(b);
}

void SolveMarkersAndTranslation(const Problem& p, const Eigen::Quaterniond& r0,
                                std::vector<Eigen::Vector3d>* markers, Eigen::Vector3d* t0) {
  const int nm = static_cast<int>(p.marker_ids.size());
  const Eigen::VectorXd z = SolveMarkerSystem(p, r0, /*with_scale=*/false);
  markers->resize(nm);
  for (int j = 0; j < nm; ++j) (*markers)[j] = z.segment<3>(3 * j);
  *t0 = r0 * Eigen::Vector3d(z.segment<3>(3 * nm));
}

// RMS distance of the tracker positions from their mean [m].
double PositionSpread(const Problem& p) {
  Eigen::Vector3d mean = Eigen::Vector3d::Zero();
  for (const RegistrationStation& s : p.stations)
    mean += s.tracker_transmitter_from_receiver.translation;
  mean /= static_cast<double>(p.stations.size());
  double sum_sq = 0.0;
  for (const RegistrationStation& s : p.stations) {
    sum_sq += (s.tracker_transmitter_from_receiver.translation - mean).squaredNorm();
  }
  return std::sqrt(sum_sq / static_cast<double>(p.stations.size()));
}

// How far the optical positions move per metre the tracker moves, given the marker-difference
// rotation R0: the scale c of SolveMarkerSystem. Right-handed frames in metres give c = 1. The
// marker differences fix R0 only up to sign (it is made proper), so an optical frame that is a
// mirror image of a right-handed one gives c = -1; millimetres give 1000, a tracker in inches
// 0.0254. The caller makes sure the positions vary (else c trades off with u).
double ScaleFromMarkerDifferenceRotation(const Problem& p, const Eigen::Quaterniond& r0) {
  return SolveMarkerSystem(p, r0, /*with_scale=*/true)(3 * static_cast<int>(p.marker_ids.size()));
}

// The same without orientation diversity: the visible markers' centroids against the tracker
// positions (Umeyama with reflections allowed; the centroids' offsets from the receiver, a few
// centimetres, only add noise). The sign tells a mirror image only when the positions spread in
// three dimensions; otherwise it is +.
double ScaleFromCentroids(const Problem& p) {
  Eigen::Vector3d mean_p = Eigen::Vector3d::Zero(), mean_c = Eigen::Vector3d::Zero();
  std::vector<Eigen::Vector3d> centroids;
  for (const RegistrationStation& s : p.stations) {
    Eigen::Vector3d c = Eigen::Vector3d::Zero();
    for (const MarkerObservation& m : s.markers) c += m.marker_in_optical;
    centroids.push_back(c / static_cast<double>(s.markers.size()));
    mean_c += centroids.back();
    mean_p += s.tracker_transmitter_from_receiver.translation;
  }
  const double n = static_cast<double>(p.stations.size());
  mean_p /= n;
  mean_c /= n;
  Eigen::Matrix3d cross = Eigen::Matrix3d::Zero();
  double variance = 0.0;
  for (std::size_t i = 0; i < p.stations.size(); ++i) {
    const Eigen::Vector3d dp = p.stations[i].tracker_transmitter_from_receiver.translation - mean_p;
    cross += (centroids[i] - mean_c) * dp.transpose();
    variance += dp.squaredNorm();
  }
  Eigen::JacobiSVD<Eigen::Matrix3d> svd(cross, Eigen::ComputeFullU | Eigen::ComputeFullV);
  const Eigen::Vector3d sv = svd.singularValues();
  const double scale = sv.sum() / variance;
  const bool mirrored = (svd.matrixU() * svd.matrixV().transpose()).determinant() < 0.0;
  return mirrored && sv(2) > 0.1 * sv(0) ? -scale : scale;
}

// RMS distance of the stations' marker centroids from their mean over the RMS distance of the
// visible markers from their station's centroid, both in optical units (so millimetres or a mirror
// leave it unchanged). ScaleFromCentroids takes the centroids for the receiver positions; the
// centroids' offsets from the receiver change from station to station with the visible markers
// and the orientation by up to the body's size, so below a spread of a few body sizes they, not
// the units, set the scale it finds.
double CentroidSpreadInBodySizes(const Problem& p) {
  std::vector<Eigen::Vector3d> centroids;
  Eigen::Vector3d mean = Eigen::Vector3d::Zero();
  double body_sq = 0.0;
  int num_markers = 0;
  for (const RegistrationStation& s : p.stations) {
    Eigen::Vector3d c = Eigen::Vector3d::Zero();
    for (const MarkerObservation& m : s.markers) c += m.marker_in_optical;
    c /= static_cast<double>(s.markers.size());
    for (const MarkerObservation& m : s.markers) body_sq += (m.marker_in_optical - c).squaredNorm();
    num_markers += static_cast<int>(s.markers.size());
    centroids.push_back(c);
    mean += c;
  }
  mean /= static_cast<double>(centroids.size());
  double spread_sq = 0.0;
  for (const Eigen::Vector3d& c : centroids) spread_sq += (c - mean).squaredNorm();
  const double spread = std::sqrt(spread_sq / static_cast<double>(centroids.size()));
  const double body = std::sqrt(body_sq / static_cast<double>(num_markers));
  return body > 0.0 ? spread / body : std::numeric_limits<double>::infinity();
}

// Throws if the optical positions do not move like the tracker's between stations (units or a
// left-handed optical frame): no rigid transform can then explain them, and the fit would only
// return a huge chi-square without saying why.
void CheckOpticalScale(const Problem& p, const Eigen::Quaterniond* marker_difference_rotation,
                       double tracker_position_noise_m) {
  // Positions spread over many times their noise determine the scale to a few per cent.
  constexpr double kMinSpreadInNoise = 10.0;
  // Without the marker-difference rotation the scale comes from the marker centroids, which need
  // the stations to spread over several marker-body sizes (see CentroidSpreadInBodySizes).
  constexpr double kMinCentroidSpreadInBodySizes = 1.0;
  // Units differ by 10 (cm), 25.4 (in), 1000 (mm); a real tracker's scale error is a few per cent.
  constexpr double kMaxScaleFactor = 2.0;
  if (PositionSpread(p) < kMinSpreadInNoise * tracker_position_noise_m) return;
  if (marker_difference_rotation == nullptr &&
      CentroidSpreadInBodySizes(p) < kMinCentroidSpreadInBodySizes) {
    return;
  }
  auto scale_of = [&](const Problem& q) {
    return marker_difference_rotation != nullptr
               ? ScaleFromMarkerDifferenceRotation(q, *marker_difference_rotation)
               : ScaleFromCentroids(q);
  };
  auto plausible = [&](double s) { return s > 1.0 / kMaxScaleFactor && s < kMaxScaleFactor; };
  const double scale = scale_of(p);
  if (plausible(scale)) return;
  // Units or handedness move every station alike; one tracker reading far off (a hemisphere
  // flip, a reading of another station) pulls the least-squares scale alone, and the units advice
  // below would then be wrong. If the scale is plausible without one station, name that station.
  // Not for a negative scale: a mirror image is the likelier cause, and without the marker-
  // difference rotation the centroids' sign is only trusted for a 3-D spread, which leaving a
  // station out can lose (a mirrored capture at one orientation then looked plausible).
  constexpr int kMinStationsForLeaveOneOut = 4;
  if (scale > 0.0 && static_cast<int>(p.stations.size()) >= kMinStationsForLeaveOneOut) {
    int culprit = -1;
    double culprit_scale = 0.0;
    for (std::size_t i = 0; i < p.stations.size(); ++i) {
      Problem without = p;
      without.num_observations -= static_cast<int>(p.stations[i].markers.size());
      without.stations.erase(without.stations.begin() + static_cast<std::ptrdiff_t>(i));
      const double s = scale_of(without);
      if (plausible(s) &&
          (culprit < 0 || std::abs(std::log(s)) < std::abs(std::log(culprit_scale)))) {
        culprit = static_cast<int>(i);
        culprit_scale = s;
      }
    }
    if (culprit >= 0) {
      throw std::invalid_argument(
          StationField(p.stations[culprit], "tracker x/y/z") +
          ": the reading disagrees with its markers: with this station the optical positions "
          "move " +
          Fmt("%.4g", scale) +
          " times as far as the tracker positions between stations, without it " +
          Fmt("%.4g", culprit_scale) +
          " (expected 1): a hemisphere flip, or the reading of another station? Remove or fix "
          "this station");
    }
  }
  if (scale < -1.0 / kMaxScaleFactor && scale > -kMaxScaleFactor) {
    throw std::invalid_argument(
        "registration: markers x/y/z: the optical positions move as a mirror image of the "
        "tracker positions (scale " +
        Fmt("%.3g", scale) +
        ", expected 1): the optical frame is left-handed; negate one of its axes");
  }
  throw std::invalid_argument(
      "registration: markers x/y/z: the optical positions move " + Fmt("%.4g", scale) +
      " times as far as the tracker positions between stations (expected 1): both must be in "
      "metres (optical millimetres give 1000, tracker inches 0.0254)" +
      (scale < 0.0 ? "; the sign also says the optical frame is left-handed" : ""));
}

// optical_from_transmitter aligning the markers placed by the tracker poses with their
// measurements: the optical least-squares transform for given markers and exact tracker poses.
Rigid3d AlignMarkers(const Problem& p, const std::vector<Eigen::Vector3d>& markers) {
  std::vector<Eigen::Vector3d> in_transmitter, in_optical;
  for (const RegistrationStation& s : p.stations) {
    for (const MarkerObservation& m : s.markers) {
      in_transmitter.push_back(s.tracker_transmitter_from_receiver *
                               markers[p.marker_index.at(m.marker)]);
      in_optical.push_back(m.marker_in_optical);
    }
  }
  return AlignPoints(in_transmitter, in_optical);
}

// Sum of squared optical residuals [m^2] with the tracker poses taken as exact.
double OpticalSumOfSquares(const Problem& p, const Eigen::Quaterniond& r0,
                           const Eigen::Vector3d& t0, const std::vector<Eigen::Vector3d>& markers) {
  const Rigid3d optical_from_transmitter(r0, t0);
  double sse = 0.0;
  for (const RegistrationStation& s : p.stations) {
    for (const MarkerObservation& m : s.markers) {
      const Eigen::Vector3d predicted =
          optical_from_transmitter *
          (s.tracker_transmitter_from_receiver * markers[p.marker_index.at(m.marker)]);
      sse += (predicted - m.marker_in_optical).squaredNorm();
    }
  }
  return sse;
}

ResidualStructure AnalyseResidualStructure(const std::vector<RegisteredStation>& stations) {
  ResidualStructure out;
  const int n = static_cast<int>(stations.size());
  out.trend_dof = 6 * 4;
  out.residual_dof = 6 * n - out.trend_dof;
  if (n <= 4) return out;
  Eigen::Vector3d centre = Eigen::Vector3d::Zero();
  for (const RegisteredStation& s : stations) centre += s.transmitter_from_receiver.translation;
  centre /= n;
  Eigen::MatrixXd x(n, 4);
  Eigen::MatrixXd y(n, 6);
  for (int i = 0; i < n; ++i) {
    x(i, 0) = 1.0;
    x.block<1, 3>(i, 1) = (stations[i].transmitter_from_receiver.translation - centre).transpose();
    y.row(i) = stations[i].tracker_residual_whitened.transpose();
  }
  const Eigen::MatrixXd fitted = x * x.colPivHouseholderQr().solve(y);
  const Eigen::MatrixXd rest = y - fitted;
  out.explained = fitted.squaredNorm();
  out.unexplained = rest.squaredNorm();
  for (int c = 0; c < 6; ++c) {
    const double total = y.col(c).squaredNorm();
    out.explained_fraction[c] = total > 0.0 ? fitted.col(c).squaredNorm() / total : 0.0;
  }
  if (out.unexplained > 0.0) {
    out.f_statistic = (out.explained / out.trend_dof) / (out.unexplained / out.residual_dof);
    out.p_value = FDistributionUpperTail(out.f_statistic, out.trend_dof, out.residual_dof);
  }
  return out;
}

// The registered marker body placed at a station by its own best optical fit (Horn alignment, no
// tracker reading): sets the station's marker_body_rms_m and marker_body_tail.
void FitMarkerBody(const RegistrationStation& station, const OpticalRegistration& registration,
                   double optical_noise_m, RegisteredStation* out) {
  std::vector<Eigen::Vector3d> in_receiver, in_optical;
  for (const MarkerObservation& m : station.markers) {
    in_receiver.push_back(registration.marker_in_receiver.at(m.marker));
    in_optical.push_back(m.marker_in_optical);
  }
  const int dof = 3 * static_cast<int>(in_receiver.size()) - 6;
  if (dof <= 0) return;  // two markers or fewer: any body fits
  const Rigid3d optical_from_receiver = AlignPoints(in_receiver, in_optical);
  double sum_sq = 0.0;
  for (std::size_t k = 0; k < in_receiver.size(); ++k) {
    sum_sq += (optical_from_receiver * in_receiver[k] - in_optical[k]).squaredNorm();
  }
  out->marker_body_rms_m = std::sqrt(sum_sq / static_cast<double>(in_receiver.size()));
  out->marker_body_tail = ChiSquareUpperTail(sum_sq / (optical_noise_m * optical_noise_m), dof);
}

// One solve of eq. 14 over the given stations (validated by the caller).
RegistrationResult SolveRegistration(const std::vector<RegistrationStation>& stations,
                                     const RegistrationOptions& options) {
  RegistrationResult result;
  Problem p;
  std::set<int> ids;
  for (const RegistrationStation& s : stations) {
    if (static_cast<int>(s.markers.size()) < options.min_markers_per_station) {
      result.skipped_stations.push_back(s.station);
      continue;
    }
    p.stations.push_back(s);
    p.stations.back().tracker_transmitter_from_receiver.rotation.normalize();
    for (const MarkerObservation& m : s.markers) ids.insert(m.marker);
    p.num_observations += static_cast<int>(s.markers.size());
  }
  if (static_cast<int>(p.stations.size()) < options.min_stations) {
    throw std::invalid_argument(
        "registration: " + std::to_string(p.stations.size()) + " station(s) with at least " +
        std::to_string(options.min_markers_per_station) + " visible markers, need at least " +
        std::to_string(options.min_stations));
  }
  for (int id : ids) {
    p.marker_index[id] = static_cast<int>(p.marker_ids.size());
    p.marker_ids.push_back(id);
  }
  p.marker_observations.assign(p.marker_ids.size(), 0);
  for (const RegistrationStation& s : p.stations) {
    for (const MarkerObservation& m : s.markers) ++p.marker_observations[p.marker_index[m.marker]];
  }
  const int nm = static_cast<int>(p.marker_ids.size());
  result.num_marker_observations = p.num_observations;
  result.num_parameters = 6 + 3 * nm;
  result.nu = 3.0 * p.num_observations - result.num_parameters;
  if (result.nu <= 0.0) {
    throw std::invalid_argument("registration: " + std::to_string(p.num_observations) +
                                " marker observations cannot determine " +
                                std::to_string(result.num_parameters) + " parameters");
  }
  result.chi_square_stddev = std::sqrt(2.0 * result.nu);

  // Closed-form start: candidate rotations, each completed with markers and translation by
  // linear least squares; the one that best explains the optical data (tracker poses fixed) wins,
  // so a marker-difference rotation spoiled by noise cannot beat a cruder but sound one.
  struct Start {
    std::string name;
    Eigen::Quaterniond r0;
    std::vector<Eigen::Vector3d> markers;
    Eigen::Vector3d t0;
    double sse = 0.0;
  };
  std::vector<Start> starts;
  Eigen::Quaterniond candidate;
  std::string no_difference_rotation;
  const bool have_difference_rotation =
      RotationFromMarkerDifferences(p, &candidate, &no_difference_rotation);
  CheckOpticalScale(p, have_difference_rotation ? &candidate : nullptr,
                    options.tracker_position_noise_m);
  if (have_difference_rotation) {
    starts.push_back({"rotation from marker differences", candidate, {}, {}, 0.0});
  }
  starts.push_back({"rotation from marker centroids", RotationFromCentroids(p), {}, {}, 0.0});
  for (Start& start : starts) {
    SolveMarkersAndTranslation(p, start.r0, &start.markers, &start.t0);
    // A few alternations of two exact partial minimisers (rotation and translation by Horn
    // alignment given the markers, markers and translation given the rotation) polish the start.
    for (int k = 0; k < kInitialAlternations; ++k) {
      start.r0 = AlignMarkers(p, start.markers).rotation;
      SolveMarkersAndTranslation(p, start.r0, &start.markers, &start.t0);
    }
    start.sse = OpticalSumOfSquares(p, start.r0, start.t0, start.markers);
  }
  const Start& best = *std::min_element(
      starts.begin(), starts.end(), [](const Start& a, const Start& b) { return a.sse < b.sse; });
  result.initialisation = best.name +
                          (starts.size() == 1 ? " (" + no_difference_rotation + ")" : "") +
                          ", markers and translation by linear least squares";
  const Eigen::Quaterniond r0 = best.r0;
  const std::vector<Eigen::Vector3d> markers = best.markers;
  Eigen::Vector3d t0 = best.t0;

  // Parameter blocks.
  double q0[4];
  QuaternionToXyzwArray(r0, q0);
  std::vector<double> marker_blocks(3 * nm);
  for (int j = 0; j < nm; ++j)
    std::copy(markers[j].data(), markers[j].data() + 3, &marker_blocks[3 * j]);
  const int ns = static_cast<int>(p.stations.size());
  std::vector<double> pose_q(4 * ns), pose_t(3 * ns);
  for (int i = 0; i < ns; ++i) {
    const Rigid3d& x = p.stations[i].tracker_transmitter_from_receiver;
    QuaternionToXyzwArray(x.rotation.normalized(), &pose_q[4 * i]);
    std::copy(x.translation.data(), x.translation.data() + 3, &pose_t[3 * i]);
  }

  ceres::Problem problem;
  SetQuaternionManifold(&problem, q0);
  problem.AddParameterBlock(t0.data(), 3);
  const auto optical_sqrt_info = IsotropicSqrtInformation<3>(options.optical_noise_m);
  Eigen::Matrix<double, 6, 1> prior_sigmas;
  prior_sigmas << Eigen::Vector3d::Constant(options.tracker_position_noise_m),
      Eigen::Vector3d::Constant(options.tracker_orientation_noise_rad);
  const auto prior_sqrt_info = DiagonalSqrtInformation<6>(prior_sigmas);
  std::vector<std::vector<ceres::ResidualBlockId>> station_residuals(ns);
  for (int i = 0; i < ns; ++i) {
    double* q = &pose_q[4 * i];
    double* t = &pose_t[3 * i];
    SetQuaternionManifold(&problem, q);
    station_residuals[i].push_back(problem.AddResidualBlock(
        Whitened<PosePriorCost>::Create(prior_sqrt_info,
                                        p.stations[i].tracker_transmitter_from_receiver),
        nullptr, q, t));
    for (const MarkerObservation& m : p.stations[i].markers) {
      double* r = &marker_blocks[3 * p.marker_index[m.marker]];
      station_residuals[i].push_back(problem.AddResidualBlock(
          Whitened<MarkerPositionCost>::Create(optical_sqrt_info, m.marker_in_optical), nullptr, q0,
          t0.data(), q, t, r));
    }
  }

  ceres::Solver::Options solver_options;
  solver_options.linear_solver_type = ceres::SPARSE_NORMAL_CHOLESKY;
  solver_options.max_num_iterations = options.max_num_iterations;
  solver_options.function_tolerance = options.function_tolerance;
  solver_options.parameter_tolerance = options.parameter_tolerance;
  solver_options.gradient_tolerance = 1e-14;
  solver_options.num_threads = options.num_threads;
  solver_options.logging_type = ceres::SILENT;
  ceres::Solver::Summary summary;
  ceres::Solve(solver_options, &problem, &summary);
  result.converged = summary.termination_type == ceres::CONVERGENCE;
  result.solver_report = summary.BriefReport();
  result.num_iterations = static_cast<int>(summary.iterations.size()) - 1;
  result.chi_square = 2.0 * summary.final_cost;

  // Covariance of the transform and the markers.
  std::vector<CovarianceBlock> blocks;
  blocks.push_back({q0,
                    "optical_from_transmitter.rotation",
                    {"rx", "ry", "rz"},
                    kQuaternionTangentToRotationVector,
                    options.max_rotation_stddev_rad});
  blocks.push_back({t0.data(),
                    "optical_from_transmitter.translation",
                    {"x", "y", "z"},
                    1.0,
                    options.max_translation_stddev_m});
  for (int j = 0; j < nm; ++j) {
    blocks.push_back({&marker_blocks[3 * j],
                      "marker_" + std::to_string(p.marker_ids[j]),
                      {"x", "y", "z"},
                      1.0,
                      options.max_marker_stddev_m});
  }
  const std::size_t first_station_block = blocks.size();
  for (int i = 0; i < ns; ++i) {
    const std::string name = "station_" + std::to_string(p.stations[i].station);
    // Receiver poses are nuisance parameters here: own covariance only, never flagged.
    blocks.push_back({&pose_q[4 * i],
                      name + ".rotation",
                      {"rx", "ry", "rz"},
                      kQuaternionTangentToRotationVector,
                      std::numeric_limits<double>::infinity(),
                      /*cross_covariance=*/false});
    blocks.push_back({&pose_t[3 * i],
                      name + ".position",
                      {"x", "y", "z"},
                      1.0,
                      std::numeric_limits<double>::infinity(),
                      /*cross_covariance=*/false});
  }
  result.covariance = ComputeCovariance(&problem, blocks, options.covariance);
  if (result.covariance.success) {
    result.optical_from_transmitter_covariance = result.covariance.covariance.topLeftCorner<6, 6>();
    result.optical_from_transmitter_stddev = result.covariance.stddev.head<6>();
  }
  bool transform_flagged = false;
  for (const IdentifiabilityFlag& f : result.covariance.flags) {
    if (f.coordinate.rfind("optical_from_transmitter", 0) == 0) transform_flagged = true;
  }
  result.identifiable =
      result.covariance.success && !result.covariance.rank_deficient && !transform_flagged;

  // Outputs.
  result.registration.optical_from_transmitter =
      Rigid3d(QuaternionFromXyzwArray(q0).normalized(), t0);
  for (int j = 0; j < nm; ++j) {
    RegisteredMarker m;
    m.marker = p.marker_ids[j];
    m.marker_in_receiver = Eigen::Map<const Eigen::Vector3d>(&marker_blocks[3 * j]);
    if (result.covariance.success) {
      m.stddev = result.covariance.stddev.segment<3>(result.covariance.block_offsets[2 + j]);
    }
    m.num_observations = p.marker_observations[j];
    result.registration.marker_in_receiver[m.marker] = m.marker_in_receiver;
    result.markers.push_back(m);
  }
  for (int i = 0; i < ns; ++i) {
    RegisteredStation s;
    s.station = p.stations[i].station;
    s.transmitter_from_receiver = Rigid3d(QuaternionFromXyzwArray(&pose_q[4 * i]).normalized(),
                                          Eigen::Map<const Eigen::Vector3d>(&pose_t[3 * i]));
    s.num_markers = static_cast<int>(p.stations[i].markers.size());
    if (result.covariance.success) {
      const int rotation = result.covariance.block_offsets[first_station_block + 2 * i];
      const int position = result.covariance.block_offsets[first_station_block + 2 * i + 1];
      s.stddev << result.covariance.stddev.segment<3>(rotation),
          result.covariance.stddev.segment<3>(position);
    }
    double sum_sq = 0.0;
    for (const MarkerObservation& m : p.stations[i].markers) {
      const Eigen::Vector3d predicted =
          result.registration.optical_from_transmitter *
          (s.transmitter_from_receiver * result.registration.marker_in_receiver.at(m.marker));
      sum_sq += (predicted - m.marker_in_optical).squaredNorm();
    }
    s.marker_rms_m = std::sqrt(sum_sq / s.num_markers);
    const Rigid3d& reading = p.stations[i].tracker_transmitter_from_receiver;
    s.tracker_position_residual_m = PositionErrorNorm(s.transmitter_from_receiver, reading);
    s.tracker_orientation_residual_rad =
        OrientationErrorAngle(s.transmitter_from_receiver, reading);
    s.tracker_residual_whitened << (s.transmitter_from_receiver.translation - reading.translation) /
                                       options.tracker_position_noise_m,
        RotationVectorBetween<double>(s.transmitter_from_receiver.rotation, reading.rotation) /
            options.tracker_orientation_noise_rad;
    for (ceres::ResidualBlockId id : station_residuals[i]) {
      double cost = 0.0;
      problem.EvaluateResidualBlock(id, /*apply_loss_function=*/true, &cost, nullptr, nullptr);
      s.chi_square += 2.0 * cost;
    }
    FitMarkerBody(p.stations[i], result.registration, options.optical_noise_m, &s);
    result.stations.push_back(s);
  }
  result.residual_structure = AnalyseResidualStructure(result.stations);
  return result;
}

// Does this station's marker set misfit the marker body beyond both of the options' tests?
bool MisfitsMarkerBody(const RegisteredStation& s, const RegistrationOptions& options) {
  return s.marker_body_rms_m > options.max_station_marker_rms_m &&
         s.marker_body_tail < options.station_false_alarm;
}

// Is this station's tracker reading far off the registration of the stations (see
// RegistrationOptions::max_tracker_residual_ratio)? median_norm: the median over the stations of
// the whitened tracker residual's norm.
bool TrackerReadingFarOff(const RegisteredStation& s, double median_norm,
                          const RegistrationOptions& options) {
  const double norm = s.tracker_residual_whitened.norm();
  return norm > options.max_tracker_residual_ratio * median_norm &&
         ChiSquareUpperTail(norm * norm, 6) < options.station_false_alarm;
}

double MedianTrackerResidualNorm(const std::vector<RegisteredStation>& stations) {
  std::vector<double> norms;
  for (const RegisteredStation& s : stations) norms.push_back(s.tracker_residual_whitened.norm());
  if (norms.empty()) return 0.0;
  std::sort(norms.begin(), norms.end());
  const std::size_t n = norms.size();
  return n % 2 == 1 ? norms[n / 2] : 0.5 * (norms[n / 2 - 1] + norms[n / 2]);
}

}  // namespace

RegistrationResult RegisterOpticalToTransmitter(const std::vector<RegistrationStation>& stations,
                                                const RegistrationOptions& options) {
  if (!options.Check()) throw std::invalid_argument("RegistrationOptions: invalid options");
  ValidateStations(stations);
  std::vector<RegistrationStation> kept = stations;
  std::vector<RejectedStation> rejected;
  RegistrationResult result = SolveRegistration(kept, options);
  while (true) {
    const int num_used = static_cast<int>(result.stations.size());
    const int max_rejected = static_cast<int>(std::floor(
        options.max_rejected_fraction * static_cast<double>(num_used + rejected.size())));
    if (!options.reject_bad_stations || static_cast<int>(rejected.size()) >= max_rejected ||
        num_used - 1 < options.min_stations) {
      return result;
    }
    // The worst first: one misfitting station pulls the marker body towards itself, which can
    // push a sound neighbour over the line until it is gone. Worst by the station's chi-square,
    // not by its body misfit: a swap at a station seeing three of the paper's markers (an
    // equilateral triangle) fits the body by itself, and in the solve that keeps it sound stations
    // misfitted the body as much (7.33 mm against its 7.32) while it held 97 % of chi-square; by
    // body misfit four sound stations were left out instead and the transform was 3-10 deg off.
    const RegisteredStation* worst = nullptr;
    for (const RegisteredStation& s : result.stations) {
      if (MisfitsMarkerBody(s, options) && (worst == nullptr || s.chi_square > worst->chi_square)) {
        worst = &s;
      }
    }
    std::string reason = "marker_body";
    if (worst == nullptr) {  // then the tracker reading farthest off, if it is
      const double median = MedianTrackerResidualNorm(result.stations);
      for (const RegisteredStation& s : result.stations) {
        if (TrackerReadingFarOff(s, median, options) &&
            (worst == nullptr ||
             s.tracker_residual_whitened.norm() > worst->tracker_residual_whitened.norm())) {
          worst = &s;
        }
      }
      reason = "tracker_reading";
    }
    if (worst == nullptr) return result;
    const int id = worst->station;
    std::vector<RegistrationStation> fewer;
    for (const RegistrationStation& s : kept) {
      if (s.station != id) fewer.push_back(s);
    }
    RegistrationResult next;
    try {
      next = SolveRegistration(fewer, options);
    } catch (const std::invalid_argument&) {
      // The rest no longer determine the parameters (or fail the unit check): keep the station
      // and the solve that had it rather than fail a registration that was solved.
      return result;
    }
    rejected.push_back({worst->station, worst->num_markers, worst->marker_body_rms_m,
                        worst->marker_body_tail, reason, worst->tracker_position_residual_m,
                        worst->tracker_orientation_residual_rad});
    next.rejected_stations = rejected;
    result = std::move(next);
    kept = std::move(fewer);
  }
}

std::string RejectedStation::Why() const {
  if (reason == "tracker_reading") {
    return "its tracker reading is " + Fmt("%.1f", tracker_position_residual_m * 1e3) + " mm and " +
           Fmt("%.2f", tracker_orientation_residual_rad * kDegPerRad) +
           " deg off the pose its markers give, many times the other stations' residuals: a "
           "hemisphere flip, metal near the receiver, or another station's reading?";
  }
  return "its " + std::to_string(num_markers) + " markers misfit the marker body by " +
         Fmt("%.2f", marker_body_rms_m * 1e3) + " mm RMS (chi-square tail " +
         Fmt("%.2g", marker_body_tail) + "): a swapped or misidentified marker?";
}

std::string RegistrationResult::ToString() const {
  std::ostringstream out;
  const Rigid3d& t = registration.optical_from_transmitter;
  out << "optical_from_transmitter: " << t.ToString() << "\n";
  out << "  rotation std [deg]: " << Fmt("%.4f", optical_from_transmitter_stddev(0) * kDegPerRad)
      << " " << Fmt("%.4f", optical_from_transmitter_stddev(1) * kDegPerRad) << " "
      << Fmt("%.4f", optical_from_transmitter_stddev(2) * kDegPerRad)
      << "  translation std [mm]: " << Fmt("%.3f", optical_from_transmitter_stddev(3) * 1e3) << " "
      << Fmt("%.3f", optical_from_transmitter_stddev(4) * 1e3) << " "
      << Fmt("%.3f", optical_from_transmitter_stddev(5) * 1e3) << "\n";
  for (const RegisteredMarker& m : markers) {
    out << "  marker " << m.marker
        << " in receiver [mm]: " << Fmt("%.3f", m.marker_in_receiver.x() * 1e3) << " "
        << Fmt("%.3f", m.marker_in_receiver.y() * 1e3) << " "
        << Fmt("%.3f", m.marker_in_receiver.z() * 1e3)
        << "  std [mm]: " << Fmt("%.3f", m.stddev.x() * 1e3) << " "
        << Fmt("%.3f", m.stddev.y() * 1e3) << " " << Fmt("%.3f", m.stddev.z() * 1e3) << "  ("
        << m.num_observations << " stations)\n";
  }
  out << "chi-square " << Fmt("%.2f", chi_square) << ", expected nu = " << Fmt("%.0f", nu) << " +- "
      << Fmt("%.2f", chi_square_stddev) << " (z = " << Fmt("%.2f", ChiSquareZ()) << ")\n";
  const ResidualStructure& rs = residual_structure;
  out << "tracker residual trend over station position: F = " << Fmt("%.2f", rs.f_statistic) << " ("
      << rs.trend_dof << ", " << rs.residual_dof << " dof), p = " << Fmt("%.2g", rs.p_value)
      << (rs.Flagged() ? "  DISTORTED: the tracker residuals vary smoothly over the stations"
                       : "")
      << "\n";
  out << "stations used " << stations.size() << ", skipped " << skipped_stations.size()
      << ", left out " << rejected_stations.size() << ", marker observations "
      << num_marker_observations << "\n";
  for (const RejectedStation& r : rejected_stations) {
    out << "  left out station " << r.station << ": " << r.Why() << "\n";
  }
  out << "solver: " << solver_report << (converged ? "" : " (NOT CONVERGED)") << "\n";
  out << "initialisation: " << initialisation << "\n";
  out << (identifiable ? "identifiable" : "NOT IDENTIFIABLE") << "; " << covariance.ToString();
  return out.str();
}

}  // namespace trackcal::fit

namespace trackcal::fit {
namespace {
nlohmann::json Vec(const Eigen::VectorXd& v) {
  nlohmann::json out = nlohmann::json::array();
  for (Eigen::Index i = 0; i < v.size(); ++i) out.push_back(v[i]);
  return out;
}
}  // namespace

nlohmann::json RegistrationResult::ToJson() const {
  const Rigid3d& t = registration.optical_from_transmitter;
  nlohmann::json covariance_rows = nlohmann::json::array();
  for (int r = 0; r < 6; ++r) covariance_rows.push_back(Vec(optical_from_transmitter_covariance.row(r).transpose()));
  nlohmann::json marker_list = nlohmann::json::array();
  for (const RegisteredMarker& m : markers) {
    marker_list.push_back({{"marker", m.marker},
                           {"marker_in_receiver", Vec(m.marker_in_receiver)},
                           {"stddev", Vec(m.stddev)},
                           {"num_observations", m.num_observations}});
  }
  nlohmann::json station_list = nlohmann::json::array();
  for (const RegisteredStation& s : stations) {
    station_list.push_back(
        {{"station", s.station},
         {"num_markers", s.num_markers},
         {"chi_square", s.chi_square},
         {"marker_rms_mm", s.marker_rms_m * 1e3},
         {"marker_body_rms_mm", s.marker_body_rms_m * 1e3},
         {"marker_body_tail", s.marker_body_tail},
         {"tracker_position_residual_mm", s.tracker_position_residual_m * 1e3},
         {"tracker_orientation_residual_deg", s.tracker_orientation_residual_rad * kDegPerRad},
         {"tracker_residual_whitened", Vec(s.tracker_residual_whitened)}});
  }
  nlohmann::json rejected_list = nlohmann::json::array();
  for (const RejectedStation& r : rejected_stations) {
    rejected_list.push_back(
        {{"station", r.station},
         {"num_markers", r.num_markers},
         {"marker_body_rms_mm", r.marker_body_rms_m * 1e3},
         {"marker_body_tail", r.marker_body_tail},
         {"reason", r.reason},
         {"tracker_position_residual_mm", r.tracker_position_residual_m * 1e3},
         {"tracker_orientation_residual_deg", r.tracker_orientation_residual_rad * kDegPerRad},
         {"message", r.Why()}});
  }
  const ResidualStructure& rs = residual_structure;
  nlohmann::json flags = nlohmann::json::array();
  for (const IdentifiabilityFlag& f : covariance.flags) {
    flags.push_back({{"coordinate", f.coordinate}, {"reason", f.reason}});
  }
  return {{"optical_from_transmitter",
           {{"rotation_xyzw", {t.rotation.x(), t.rotation.y(), t.rotation.z(), t.rotation.w()}},
            {"translation", Vec(t.translation)},
            {"covariance_order", "rotation vector (rad, optical-frame axes), translation (m)"},
            {"covariance", covariance_rows},
            {"stddev", Vec(optical_from_transmitter_stddev)}}},
          {"markers", marker_list},
          {"stations", station_list},
          {"skipped_stations", skipped_stations},
          {"rejected_stations", rejected_list},
          {"num_marker_observations", num_marker_observations},
          {"num_parameters", num_parameters},
          {"chi_square", chi_square},
          {"nu", nu},
          {"chi_square_z", ChiSquareZ()},
          {"residual_structure",
           {{"f_statistic", rs.f_statistic},
            {"trend_dof", rs.trend_dof},
            {"residual_dof", rs.residual_dof},
            {"p_value", rs.p_value},
            {"explained_fraction", Vec(rs.explained_fraction)},
            {"flagged", rs.Flagged()}}},
          {"converged", converged},
          {"identifiable", identifiable},
          {"identifiability_flags", flags},
          {"initialisation", initialisation},
          {"solver_report", solver_report},
          {"num_iterations", num_iterations}};
}

}  // namespace trackcal::fit
