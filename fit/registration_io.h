// Capture glue of the registration: markers.csv + tracker.csv in (core/capture.h readers), the
// stations RegisterOpticalToTransmitter and ExtractPoses take, and poses.csv records out.
//
//   auto stations = ReadRegistrationStations(dir / kMarkersCsv, dir / kTrackerCsv);
//   RegistrationResult reg = RegisterOpticalToTransmitter(stations, options);
//   auto poses = ExtractPoses(stations, reg.registration);
//   WritePoses(out / kPosesCsv, MakePoseRecords(stations, poses).capture);  // atomic, no overwrite

#pragma once

#include <filesystem>
#include <map>
#include <string>
#include <vector>

#include "core/capture.h"
#include "fit/pose_extraction.h"
#include "fit/registration.h"

namespace trackcal::fit {

// True for a marker position of exactly (0,0,0): how optical systems export an occluded marker.
bool IsDropout(const Eigen::Vector3d& position_in_optical);

// Pairs markers.csv and tracker.csv records by station id, keeping the tracker rows of `sensor`
// (the receiver that carries the markers). A marker at exactly (0,0,0) is a dropout (IsDropout):
// not visible at that station. A tracker row without markers gives a station with no markers (the
// registration skips and lists it). Throws std::invalid_argument naming the file,
// station and field for a station with markers but no tracker row, two tracker rows for one
// station, or a marker listed twice at one station. Stations come out sorted by id.
std::vector<RegistrationStation> PairRegistrationRecords(
    const MarkerCapture& markers, const TrackerCapture& tracker, int sensor = 1,
    const std::string& markers_name = kMarkersCsv, const std::string& tracker_name = kTrackerCsv);

// ReadMarkers + ReadTracker + PairRegistrationRecords (file errors carry file:line:column).
std::vector<RegistrationStation> ReadRegistrationStations(const std::filesystem::path& markers_csv,
                                                          const std::filesystem::path& tracker_csv,
                                                          int sensor = 1);

struct PoseRecordOptions {
  std::string set = "reg";       // poses.csv `set` of every row: calib, valid or reg
  int sensor = 1;                // poses.csv `sensor` of every row
  bool include_bad_fit = false;  // also write stations whose marker residuals exceed the limit
  bool Check() const;
};

struct PoseRecords {
  PoseCapture capture;        // one row per station with a usable pose
  std::vector<int> left_out;  // stations without a pose (or with a bad fit, unless included)
};

// poses.csv rows: rep_* = the tracker reading, ref_* = the pose extracted from the markers (both
// transmitter_from_receiver). `time` comes from station_times (e.g. an existing poses.csv); a
// station missing there gets time 0, because tracker.csv carries no time. Throws
// std::invalid_argument if stations and poses do not correspond one to one.
PoseRecords MakePoseRecords(const std::vector<RegistrationStation>& stations,
                            const std::vector<ExtractedPose>& poses,
                            const std::map<int, double>& station_times = {},
                            const PoseRecordOptions& options = {});

// Copies the extra columns of a labelling poses.csv (`trackcal-fit register --poses`) to the
// registered records of the same station and sensor, so a value logged per station (a
// temperature) stays a covariate of the diagnosis; NaN where the labels have no such row.
void CopyExtraColumns(const PoseCapture& labels, PoseCapture* registered);

}  // namespace trackcal::fit
