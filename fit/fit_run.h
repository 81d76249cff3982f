// One fit as `trackcal-fit fit` (fit/fit_main.cc) and trackcal.fit (python/src/bind_fit.cc) run it,
// so both give the same numbers by construction:
//
//   const ModelSpec spec = ParseModelYaml(text, "model.yaml");
//   LoadedFitData data = LoadFitData({.path = "capture/"}, spec);   // poses.csv or streams
//   FitRunResult run = RunFit(std::move(data), {text, "model.yaml", "model.yaml"}, options);
//   run.tables;        // Table 1: calib, then valid and/or k-fold cross-validation
//   run.calibration;   // the calibration file's contents (provenance without the command line)
//   run.ToJson(out);   // the document `trackcal-fit fit --json` prints
//
// Data resolution: a poses.csv, a folder with poses.csv, or a folder with only the streams
// (tracker_stream.csv, reference_stream.csv), which are paired with the model file's time_offset
// (docs/fit.md, "Streams and the clock offset in the fit"); or a capture in memory. With streams
// and a free time_offset the offset is fitted jointly with the terms and the streams are re-paired
// at the estimate while it moves by more than 1 ms (at most 3 times).

#pragma once

#include <filesystem>
#include <functional>
#include <memory>
#include <nlohmann/json.hpp>
#include <optional>
#include <string>
#include <vector>

#include "core/calibration_file.h"
#include "core/capture.h"
#include "core/error_statistics.h"
#include "fit/candidates.h"
#include "fit/fit_engine.h"
#include "fit/model_file.h"
#include "fit/registration.h"
#include "fit/stream_pairing.h"

namespace trackcal::fit {

// The stations of one set (`calib`, `valid`, `reg`) of a capture, in file order.
std::vector<FitStation> StationsOfSet(const PoseCapture& poses, const std::string& set);

// Stream pairing as the model file's time_offset asks (default pairing without one).
StreamPairingOptions PairingOf(const ModelSpec& spec);

// True for a folder that holds the streams and no poses.csv (its stations are paired).
bool IsStreamFolder(const std::filesystem::path& data);

// Where the stations come from: a file or folder, or a capture in memory.
struct FitData {
  std::optional<std::filesystem::path> path;         // capture folder or poses.csv
  std::optional<PoseCapture> in_memory;              // used when path is not set
  std::optional<std::filesystem::path> loaded_from;  // in_memory's file (protected, not hashed)
  // The receiver (capture `sensor` column, 1-based) whose stations are fitted; 0: the data must
  // hold one sensor only. A calibration is one receiver's (its sensor offset and coil gains), so
  // stations of several sensors are refused rather than fitted as one receiver. With streams, the
  // tracker stream's sensor paired (0: the lowest, with a pairing warning when there are several).
  int sensor = 0;
};

// The stations of a FitData, resolved as described in the file comment.
struct LoadedFitData {
  PoseCapture poses;
  // Short name for the description ("poses.csv", the folder, "in-memory capture").
  std::string name;
  std::string source;                                  // for messages: the path read, or `name`
  std::vector<CalibrationInput> inputs;                // files read, with SHA-256 (provenance)
  std::vector<std::filesystem::path> protected_paths;  // never to be written over
  std::optional<double> time_offset;                   // when streams were paired
  // With streams: the clock drift they were paired with (StreamPairingResult::clock_drift_applied,
  // 0 when none was corrected) and the tracker time at which time_offset holds with it.
  double clock_drift = 0.0;
  double clock_drift_origin = 0.0;
  // The pairing's warning (StreamPairingResult::warning: an estimated offset poorly identified by
  // these streams), without the stream files' names; empty when none or no streams.
  std::string pairing_warning;
  // Streams paired with a free time offset: kept for the joint fit (fit/terms_time_offset.h).
  std::shared_ptr<TrackerStream> tracker_stream;
  std::shared_ptr<ReferenceStream> reference_stream;
  std::optional<StreamPairingOptions> pairing;
  std::vector<FitStation> stream_stations;  // the pairing's calib stations with velocities
  int stream_sensor = 0;  // with streams: the tracker sensor paired (FitData::sensor, 0: lowest)
};

// Throws std::invalid_argument / std::runtime_error (file, line, column) for unreadable data, and
// std::invalid_argument naming the sensors for stations of several sensors without
// FitData::sensor, or a FitData::sensor the data do not have.
LoadedFitData LoadFitData(const FitData& data, const ModelSpec& spec);

// The time_offset candidate's pairing (CandidateOptions::pair_streams) of `data`'s streams: pairs
// them at the setting's offset (searched around it unless fixed) and returns the calib stations as
// `trackcal-fit fit` fits them, with the reference's velocities, so the candidate's fit estimates
// a free offset jointly with the model (its standard deviation, and whether the model can mimic a
// time shift: FitResult::time_offset_variance_inflation). An empty function without streams.
std::function<PairedStations(const TimeOffsetSpec&)> StreamRepairing(const LoadedFitData& data,
                                                                     const ModelSpec& spec);

// The model file as text, its name for messages, and its file (provenance, protected) if any.
struct FitModelSource {
  std::string text;
  std::string source_name;                    // "model.yaml" or "<string>"
  std::optional<std::filesystem::path> path;  // the file the text came from
};

struct FitRunOptions {
  // k-fold cross-validation (>= 2) adds a "cross-validation (k-fold)" table ("cross-validation
  // (k-fold, blocks of time)" for stream samples, CrossValidate); 0: none.
  int folds = 0;
  // false: cross-validate only when the capture has no `valid` set (the command line).
  bool cross_validate_with_validation_set = true;
  // Called after each solver iteration: (iteration, cost, the model's max_iterations).
  std::function<void(int, double, int)> on_iteration;
  // Called before cross-validation fold f (0-based) of `folds`; may throw to stop the run.
  std::function<void(int, int)> on_fold;
  // Provenance and description of the calibration file.
  std::string tool = "trackcal-fit";
  std::string tool_version = "0.1.0";
  std::string description_tool = "trackcal-fit";  // "fitted by <this> from <data> with model <m>"
  // The fit on the calibration set starts here (FitOptions::start; null: the model file's
  // starts). The cross-validation folds start from the model file.
  std::shared_ptr<const FitStart> start;
  bool Check() const { return folds == 0 || folds >= 2; }
};

// One fit and what it produced.
struct FitRunResult {
  FitResult result;
  std::vector<Table1> tables;         // calib, then valid and/or cross-validation
  Calibration calibration;            // chain, statistics, provenance (no command line)
  std::optional<double> time_offset;  // the clock offset used (paired or fitted), with streams
  // The clock drift the streams were paired with and its origin (LoadedFitData::clock_drift): the
  // reference at t + time_offset + clock_drift (t - clock_drift_origin). 0 when none.
  double clock_drift = 0.0;
  double clock_drift_origin = 0.0;
  std::string pairing_warning;        // LoadedFitData::pairing_warning of the data fitted
  int num_calib = 0;
  int num_valid = 0;
  std::vector<std::filesystem::path> protected_paths;  // model file and data files
  // Why the calibration must not be written, naming the model, the data and what failed: the fit
  // failed (FitResult::Failed(): the solver's FAILURE, or a cost that is not finite). Empty when
  // the fit may be written (converged, or stopped at max_iterations: FitResult::termination_type
  // NO_CONVERGENCE, which the calibration's fit_statistics.converged records as false).
  std::string failure;

  nlohmann::json TablesJson() const;
  // The document `trackcal-fit fit --json` prints ("output": null without a path; with streams
  // "time_offset_s" and "pairing_warning", "" when the pairing warned of nothing).
  nlohmann::json ToJson(const std::optional<std::filesystem::path>& output) const;
};

// Fits the model to the `calib` set of the data and evaluates Table 1. Throws
// std::invalid_argument for invalid options, no `calib` stations, or what FitModel rejects. A fit
// that fails is returned with FitRunResult::failure set: the callers write no calibration of it.
FitRunResult RunFit(LoadedFitData data, const FitModelSource& model,
                    const FitRunOptions& options = {});

// For trackcal-fit diagnose: when `data` holds streams and the model estimates the clock offset,
// the offset as RunFit estimates it (jointly with the model, re-paired while it moves) and the
// streams paired again there, so the diagnosis holds the offset `fit` would report rather than the
// pairing search's. Other data are returned unchanged. `fitted_offset_s` (optional) gets the offset.
// Throws what RunFit throws, std::invalid_argument prefixed "fitting the model's clock offset: ".
LoadedFitData PairAtFittedOffset(LoadedFitData data, const FitModelSource& model,
                                 double* fitted_offset_s = nullptr);

// The `register` document of `trackcal-fit register --json` and of Python's
// `trackcal.register(...).to_dict()`: the output file (null when none was written), the number of
// poses extracted, the stations left without a pose, and the registration. The CLI adds
// "refinement" when it refined the registration.
nlohmann::json RegisterDocument(const RegistrationResult& registration,
                                const std::optional<std::filesystem::path>& output,
                                size_t num_poses, const std::vector<int>& stations_left_out);

}  // namespace trackcal::fit
