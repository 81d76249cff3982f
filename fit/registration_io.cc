#include "fit/registration_io.h"

#include <algorithm>
#include <limits>
#include <map>
#include <set>
#include <stdexcept>

namespace trackcal::fit {

namespace {

// " (it has rows for sensor 2, ...)" when the tracker has the station for other receivers: the
// markers are on another receiver than the one asked for.
std::string OtherSensors(const std::map<int, std::set<int>>& sensors_at, int station) {
  const auto it = sensors_at.find(station);
  if (it == sensors_at.end()) return "";
  std::string list;
  for (const int s : it->second) list += (list.empty() ? "" : ", ") + std::to_string(s);
  return " (it has rows for sensor " + list +
         " there: choose the receiver that carries the markers, trackcal-fit register --sensor N, "
         "Python trackcal.register(..., sensor=N))";
}

}  // namespace

bool IsDropout(const Eigen::Vector3d& position_in_optical) {
  return position_in_optical.x() == 0.0 && position_in_optical.y() == 0.0 &&
         position_in_optical.z() == 0.0;
}

std::vector<RegistrationStation> PairRegistrationRecords(const MarkerCapture& markers,
                                                         const TrackerCapture& tracker, int sensor,
                                                         const std::string& markers_name,
                                                         const std::string& tracker_name) {
  std::map<int, RegistrationStation> stations;
  std::map<int, std::set<int>> sensors_at;  // station -> every sensor with a row, for messages
  for (const TrackerRecord& t : tracker.records) {
    sensors_at[t.station].insert(t.sensor);
    if (t.sensor != sensor) continue;
    RegistrationStation s;
    s.station = t.station;
    s.tracker_transmitter_from_receiver = t.transmitter_from_receiver;
    if (!stations.emplace(t.station, s).second) {
      throw std::invalid_argument(tracker_name + ": station " + std::to_string(t.station) +
                                  ", sensor " + std::to_string(sensor) +
                                  ": more than one row for this station and sensor");
    }
  }
  std::set<std::pair<int, int>> seen;
  for (const MarkerRecord& m : markers.records) {
    const auto it = stations.find(m.station);
    if (it == stations.end()) {
      throw std::invalid_argument(markers_name + (m.line > 0 ? ":" + std::to_string(m.line) : "") +
                                  ": column station: station " + std::to_string(m.station) +
                                  " (marker " + std::to_string(m.marker) + ") has no row in " +
                                  tracker_name + " for sensor " + std::to_string(sensor) +
                                  OtherSensors(sensors_at, m.station));
    }
    if (!seen.emplace(m.station, m.marker).second) {
      throw std::invalid_argument(markers_name + (m.line > 0 ? ":" + std::to_string(m.line) : "") +
                                  ": column marker: marker " + std::to_string(m.marker) +
                                  " appears twice at station " + std::to_string(m.station));
    }
    // Optical systems (Vicon, OptiTrack exports) write an occluded marker as 0,0,0. Read as a
    // position it misfits the marker body by the optical origin's distance: the station was left
    // out as "a swapped marker" (a 4-marker station lost for 3 good markers), a calibration
    // station's pose was dropped as a bad fit, and with a dropout at 5 of 20 registration
    // stations the transform came out 11 deg and 72 mm off. A real marker exactly at the optical
    // origin is implausible, so exactly (0,0,0) is a marker not seen.
    if (IsDropout(m.position_in_optical)) continue;
    it->second.markers.push_back({m.marker, m.position_in_optical, m.line});
  }
  std::vector<RegistrationStation> out;
  out.reserve(stations.size());
  for (auto& [id, s] : stations) out.push_back(std::move(s));
  return out;
}

std::vector<RegistrationStation> ReadRegistrationStations(const std::filesystem::path& markers_csv,
                                                          const std::filesystem::path& tracker_csv,
                                                          int sensor) {
  return PairRegistrationRecords(ReadMarkers(markers_csv), ReadTracker(tracker_csv), sensor,
                                 markers_csv.string(), tracker_csv.string());
}

bool PoseRecordOptions::Check() const { return set == "calib" || set == "valid" || set == "reg"; }

PoseRecords MakePoseRecords(const std::vector<RegistrationStation>& stations,
                            const std::vector<ExtractedPose>& poses,
                            const std::map<int, double>& station_times,
                            const PoseRecordOptions& options) {
  if (!options.Check()) {
    throw std::invalid_argument("PoseRecordOptions: set '" + options.set +
                                "' is not one of calib, valid, reg");
  }
  if (stations.size() != poses.size()) {
    throw std::invalid_argument("MakePoseRecords: " + std::to_string(stations.size()) +
                                " stations but " + std::to_string(poses.size()) + " poses");
  }
  PoseRecords out;
  for (std::size_t i = 0; i < stations.size(); ++i) {
    if (stations[i].station != poses[i].station) {
      throw std::invalid_argument(
          "MakePoseRecords: station " + std::to_string(stations[i].station) +
          " paired with the pose of station " + std::to_string(poses[i].station));
    }
    const bool usable = poses[i].status == PoseStatus::kOk ||
                        (options.include_bad_fit && poses[i].status == PoseStatus::kBadFit);
    if (!usable) {
      out.left_out.push_back(stations[i].station);
      continue;
    }
    PoseRecord r;
    r.station = stations[i].station;
    r.set = options.set;
    r.sensor = options.sensor;
    const auto t = station_times.find(r.station);
    r.time = t == station_times.end() ? 0.0 : t->second;
    r.reported = stations[i].tracker_transmitter_from_receiver;
    r.reference = poses[i].transmitter_from_receiver;
    out.capture.records.push_back(r);
  }
  return out;
}

void CopyExtraColumns(const PoseCapture& labels, PoseCapture* registered) {
  std::map<std::pair<int, int>, const std::vector<double>*> extra_of;
  for (const PoseRecord& r : labels.records) extra_of[{r.station, r.sensor}] = &r.extra;
  registered->extra_columns = labels.extra_columns;
  registered->extra_labels = labels.extra_labels;
  for (PoseRecord& r : registered->records) {
    const auto it = extra_of.find({r.station, r.sensor});
    r.extra = it != extra_of.end()
                  ? *it->second
                  : std::vector<double>(labels.extra_columns.size(),
                                        std::numeric_limits<double>::quiet_NaN());
  }
}

}  // namespace trackcal::fit
