// The calibration file (docs/calibration-file.md): a versioned, self-describing JSON document holding
// the chain of corrections, the calibrated volume, units and frames, fit statistics and provenance.
// The reader is strict: unknown format or version, missing or unknown fields, wrong array sizes,
// non-finite numbers, non-increasing grid axes and empty volumes are errors that name the source and
// the JSON path, e.g. "calib.json: $.corrections[0].position_coefficients: degree 4 needs 35 entries,
// got 34". The writer writes atomically and never overwrites an input listed in the provenance.
#pragma once

#include <filesystem>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "core/correction.h"

namespace trackcal {

inline constexpr const char* kCalibrationFormat = "trackcal-calibration";
inline constexpr int kCalibrationVersion = 1;
// Largest receiver number a calibration file may record (trackcal-fit's --sensor takes 1..64).
inline constexpr int kMaxCalibrationSensor = 64;

// One input file a calibration was computed from.
struct CalibrationInput {
  std::string path;    // as given to the tool (relative to its working directory, or absolute)
  std::string sha256;  // lower-case hex SHA-256 of the file's contents
  std::string role;    // what the file was used for, e.g. "calibration_capture", "validation_capture"
};

struct Provenance {
  std::string tool = "trackcal";        // program that wrote the file
  std::string tool_version;             // its version (trackcal's project version)
  std::string created_utc;              // ISO 8601 UTC time, "YYYY-MM-DDTHH:MM:SSZ"
  std::string command_line;             // optional: how the tool was invoked ("" if not recorded)
  std::vector<CalibrationInput> inputs; // input files with their digests
};

struct Calibration {
  std::string description;  // optional free text
  // The receiver the calibration was fitted for: the capture's `sensor` column (1-based, the
  // Fastrak station; served on vrpn.cfg's sensor=<sensor - 1>). 0: not recorded (files written
  // before the field, or data of no single sensor). A receiver's sensor offset and coil gains are
  // its own, so a server refuses a file on another sensor's line (docs/vrpn-config.md).
  int sensor = 0;
  // The corrections in order; its volume (required in a file) is the calibrated volume.
  CorrectionChain chain;
  // Free-form fit statistics (objects, arrays, strings, finite numbers); see the doc for the keys
  // trackcal's tools write. Not interpreted by the runtime.
  nlohmann::json fit_statistics = nlohmann::json::object();
  Provenance provenance;

  // Throws std::invalid_argument if the chain has no volume, a term gives a non-finite pose in it
  // (as the reader) or the provenance is malformed.
  void Check() const;
  const CalibratedVolume& volume() const;

  CorrectedPose Apply(const Rigid3d& reported) const { return chain.Apply(reported); }
  void ApplyBatch(size_t n, const double* positions, const double* quaternions_xyzw,
                  double* out_positions, double* out_quaternions_xyzw,
                  uint8_t* extrapolated) const {
    chain.ApplyBatch(n, positions, quaternions_xyzw, out_positions, out_quaternions_xyzw,
                     extrapolated);
  }
};

// Parses a calibration document; `source_name` (usually the path) prefixes every error message.
// Throws JsonInputError (a std::invalid_argument).
Calibration ParseCalibrationJson(const std::string& text, const std::string& source_name);
Calibration ReadCalibrationFile(const std::filesystem::path& path);

// The document as a JSON value, and as text (2-space indentation, arrays of numbers on one line,
// numbers in shortest round-trip form so a read-back is bit-exact).
nlohmann::json CalibrationToJson(const Calibration& calibration);
std::string CalibrationToJsonText(const Calibration& calibration);

// Writes atomically. Refuses (std::invalid_argument) to overwrite a file listed in
// provenance.inputs (same file, or same contents as a listed digest) or an existing file that is not a
// trackcal calibration file.
void WriteCalibrationFile(const std::filesystem::path& path, const Calibration& calibration);

// The checks WriteCalibrationFile can make before the calibration exists, for tools to call before
// a long fit (so a bad -o fails in a second, not after the fit): the folder exists and the user may
// write in it (access(); the link target's folder for a symbolic link), and an existing
// file at `path` is a trackcal calibration file that is not read-only (no write permission for
// anyone: a file kept on purpose). Throws std::invalid_argument naming the path. A file replaced
// keeps its mode (WriteFileAtomically).
void CheckCalibrationOutput(const std::filesystem::path& path);

// Reads a "provenance" object (as in the file) with errors naming `source` and `path`.
Provenance ParseProvenanceJson(const nlohmann::json& value, const std::string& source,
                               const std::string& path);

// Current UTC time as "YYYY-MM-DDTHH:MM:SSZ" for provenance.created_utc.
std::string CurrentUtcTimestamp();

// Pretty-prints JSON like CalibrationToJsonText (reused by other JSON writers of the project): keys in
// the order of `key_order` first, the rest alphabetically; arrays of scalars on one line.
std::string FormatJsonCompactArrays(const nlohmann::json& value,
                                    const std::vector<std::string>& key_order);

}  // namespace trackcal
