// Capture files: what a calibration session records and every other part of trackcal reads.
// Formats documented in docs/captures.md.
//
//   poses.csv            station,set,sensor,time,rep_x..rep_qz,ref_x..ref_qz  paired static poses
//   markers.csv          station,marker,x,y,z                                optical markers (reg.)
//   tracker.csv          station,sensor,x,y,z,qw,qx,qy,qz                    tracker at reg.
//   stations tracker_stream.csv   time,sensor,x,y,z,qw,qx,qy,qz                       tracker
//   stream reference_stream.csv time,x,y,z,qw,qx,qy,qz                              reference
//   stream
//
// Metres and seconds; poses are transmitter_from_receiver (reference: transmitter_from_body) in the
// transmitter frame, markers in the optical frame. Columns are found by name in any order; any
// other column is kept (`extra_columns`, `extra` per record) and written back after the standard
// ones. An extra column holds numbers (nan or an empty field: missing) or labels (text such as an
// operator's name or a room; an empty field: missing), never both: a labels column's records
// hold the index of their label in `extra_labels`. Errors name file, line and column:
//   poses.csv:17: column rep_qw: 'abc' is not a number
// Writers are atomic (temporary file + rename) and refuse to replace an existing file unless
// `overwrite` is set.

#pragma once

#include <filesystem>
#include <string>
#include <vector>

#include "core/file_util.h"  // WriteFileAtomically, used with the writers below
#include "core/pose.h"

namespace trackcal {

// True for the sets a capture's set column may name: calib, valid, reg.
bool IsKnownSet(const std::string& set);

// One paired static station: the tracker's report and the optical reference, both averaged.
struct PoseRecord {
  int station = 0;            // station id, unique per capture
  std::string set;            // "calib", "valid" or "reg"
  int sensor = 1;             // tracker station (receiver) number
  double time = 0.0;          // station time on the tracker clock [s]
  Rigid3d reported;           // transmitter_from_receiver reported by the tracker
  Rigid3d reference;          // transmitter_from_receiver measured by the reference
  std::vector<double> extra;  // values of the extra columns, in extra_columns order
};

// One optical marker reading (registration stations).
struct MarkerRecord {
  int station = 0;                                                // station id
  int marker = 0;                                                 // marker id on the body
  Eigen::Vector3d position_in_optical = Eigen::Vector3d::Zero();  // [m]
  std::vector<double> extra;
  int line = 0;  // line of markers.csv it was read from (0: made in memory), for messages
};

// The tracker's report at a registration station.
struct TrackerRecord {
  int station = 0;
  int sensor = 1;
  Rigid3d transmitter_from_receiver;
  std::vector<double> extra;
};

// A tracker stream sample (tracker clock).
struct TrackerStreamSample {
  double time = 0.0;  // [s]
  int sensor = 1;
  Rigid3d transmitter_from_receiver;
  std::vector<double> extra;
};

// A reference stream sample (reference clock), registered into the transmitter frame.
struct ReferenceStreamSample {
  double time = 0.0;  // [s]
  Rigid3d transmitter_from_body;
  std::vector<double> extra;
};

// A whole file: the records and the names of the extra columns they carry.
template <typename Record>
struct CaptureTable {
  std::vector<std::string> extra_columns;
  // Per extra column, the sorted labels of a labels column (its records' values are indices into
  // them, NaN where missing); empty for a numeric column. Empty altogether: every column numeric.
  std::vector<std::vector<std::string>> extra_labels;
  std::vector<Record> records;

  // The labels of extra column k, or nullptr when it holds numbers.
  const std::vector<std::string>* LabelsOf(size_t k) const {
    return k < extra_labels.size() && !extra_labels[k].empty() ? &extra_labels[k] : nullptr;
  }
};

using PoseCapture = CaptureTable<PoseRecord>;
using MarkerCapture = CaptureTable<MarkerRecord>;
using TrackerCapture = CaptureTable<TrackerRecord>;
using TrackerStream = CaptureTable<TrackerStreamSample>;
using ReferenceStream = CaptureTable<ReferenceStreamSample>;

struct CaptureWriteOptions {
  bool overwrite = false;  // replace an existing file (never the default: captures are precious)
};

// The standard file names of a capture folder.
inline constexpr const char* kPosesCsv = "poses.csv";
inline constexpr const char* kMarkersCsv = "markers.csv";
inline constexpr const char* kTrackerCsv = "tracker.csv";
inline constexpr const char* kTrackerStreamCsv = "tracker_stream.csv";
inline constexpr const char* kReferenceStreamCsv = "reference_stream.csv";

// Readers throw std::invalid_argument "file:line: column name: problem" on bad input and
// std::runtime_error when the file cannot be read.
PoseCapture ReadPoses(const std::filesystem::path& path);
MarkerCapture ReadMarkers(const std::filesystem::path& path);
TrackerCapture ReadTracker(const std::filesystem::path& path);
TrackerStream ReadTrackerStream(const std::filesystem::path& path);
ReferenceStream ReadReferenceStream(const std::filesystem::path& path);

// Writers throw std::invalid_argument, before anything is written, on records the readers would
// refuse (extra values not matching extra_columns, unknown set, a non-finite number other than an
// extra's nan, a quaternion whose norm is not 1 within 1e-3, a repeated key: station and sensor,
// station and marker, a tracker stream's sensor and time), and std::runtime_error when the file
// exists (without overwrite) or cannot be written. Numbers are written in shortest round-trip
// form, so read(write(x)) == x.
void WritePoses(const std::filesystem::path& path, const PoseCapture& capture,
                const CaptureWriteOptions& options = {});
void WriteMarkers(const std::filesystem::path& path, const MarkerCapture& capture,
                  const CaptureWriteOptions& options = {});
void WriteTracker(const std::filesystem::path& path, const TrackerCapture& capture,
                  const CaptureWriteOptions& options = {});
void WriteTrackerStream(const std::filesystem::path& path, const TrackerStream& capture,
                        const CaptureWriteOptions& options = {});
void WriteReferenceStream(const std::filesystem::path& path, const ReferenceStream& capture,
                          const CaptureWriteOptions& options = {});

// The text WriteTrackerStream writes for `capture` (the header line, then one line per record),
// refusing what it refuses with the same std::invalid_argument, `name` standing for the file
// ("name: record 2: column x: ..."). Without the header when !header: the rows to append to a
// file that has it (a live recording), byte for byte the file one write of all the rows gives.
std::string FormatTrackerStream(const TrackerStream& capture, const std::string& name,
                                bool header = true);

// Shortest decimal text that reads back to exactly `value`.
std::string FormatNumber(double value);

}  // namespace trackcal
