#include "fit/fit_run.h"

#include <algorithm>
#include <cmath>
#include <set>
#include <stdexcept>

#include "core/file_util.h"

namespace trackcal::fit {

namespace fs = std::filesystem;

std::vector<FitStation> StationsOfSet(const PoseCapture& poses, const std::string& set) {
  std::vector<FitStation> out;
  for (const auto& r : poses.records) {
    if (r.set == set) out.push_back({r.reported, r.reference, r.time, r.sensor, r.station});
  }
  return out;
}

StreamPairingOptions PairingOf(const ModelSpec& spec) {
  StreamPairingOptions pairing;
  if (spec.time_offset) {
    pairing.time_offset = spec.time_offset->value;
    pairing.estimate_time_offset = !spec.time_offset->fixed;
    pairing.search_range = spec.time_offset->search_range;
  }
  return pairing;
}

bool IsStreamFolder(const fs::path& data) {
  return fs::is_directory(data) && !fs::exists(data / kPosesCsv) &&
         fs::exists(data / kTrackerStreamCsv) && fs::exists(data / kReferenceStreamCsv);
}

// Keeps the stations of `sensor` (0: requires that every station has the same sensor). A fit of
// two receivers' stations as one receiver fitted neither: their sensor offsets and coil gains
// differ (two simulated paper-room receivers, body offsets 6 cm apart, sensor offset and a degree-3
// polynomial: 31.5 mm mean corrected error on the mixture, 3.9 mm on each receiver alone).
void SelectSensor(PoseCapture* poses, int sensor, const std::string& source) {
  std::set<int> sensors;
  for (const auto& r : poses->records) sensors.insert(r.sensor);
  std::string list;
  for (const int s : sensors) list += (list.empty() ? "" : ", ") + std::to_string(s);
  if (sensor == 0) {
    if (sensors.size() <= 1) return;
    throw std::invalid_argument(
        source + ": stations of sensors " + list +
        " (the sensor column): a calibration is fitted from one receiver's stations (each "
        "receiver has its own sensor offset and coil gains); fit each receiver on its own with "
        "--sensor N, N one of " +
        list +
        " (trackcal-fit fit/build/diagnose, trackcal fit/validate/diagnose/report; Python: " +
        "trackcal.fit(..., sensor=N)), and serve each file on VRPN sensor N-1 " +
        "(trackcal_Calibration ... sensor=<N-1>, docs/vrpn-config.md)");
  }
  if (sensors.count(sensor) == 0) {
    throw std::invalid_argument(source + ": no station of sensor " + std::to_string(sensor) +
                                " (the sensor column has " + (list.empty() ? "none" : list) + ")");
  }
  std::erase_if(poses->records, [sensor](const PoseRecord& r) { return r.sensor != sensor; });
}

namespace {

LoadedFitData LoadFitDataOfFiles(const FitData& data, const ModelSpec& spec) {
  if (data.sensor < 0) throw std::invalid_argument("sensor must be 0 (the only one) or >= 1");
  LoadedFitData out;
  out.name = "in-memory capture";
  if (!data.path) {
    if (!data.in_memory) throw std::invalid_argument("LoadFitData: no data given");
    out.poses = *data.in_memory;
    if (data.loaded_from) {
      out.protected_paths.push_back(*data.loaded_from);
      out.name = data.loaded_from->filename().string() + " (in memory)";
    }
    out.source = out.name;
    SelectSensor(&out.poses, data.sensor, out.source);
    return out;
  }
  if (IsStreamFolder(*data.path)) {
    StreamPairingOptions pairing = PairingOf(spec);
    pairing.sensor = data.sensor;
    out.stream_sensor = data.sensor;
    const fs::path tracker = *data.path / kTrackerStreamCsv;
    const fs::path reference = *data.path / kReferenceStreamCsv;
    out.tracker_stream = std::make_shared<TrackerStream>(ReadTrackerStream(tracker));
    out.reference_stream = std::make_shared<ReferenceStream>(ReadReferenceStream(reference));
    const StreamPairingResult paired =
        PairStreamsOfFiles(*out.tracker_stream, *out.reference_stream, pairing, tracker, reference);
    out.poses = paired.poses;
    out.time_offset = paired.time_offset;
    out.clock_drift = paired.clock_drift_applied;
    out.clock_drift_origin = paired.clock_drift_origin;
    out.pairing_warning = paired.warning;
    if (spec.time_offset && !spec.time_offset->fixed) {
      out.pairing = pairing;
      // Re-pairing at a fitted offset keeps a corrected drift.
      out.pairing->clock_drift = paired.clock_drift_applied;
      out.stream_stations = FitStationsOfPairing(paired, "calib");
    }
    for (const auto& p : {tracker, reference}) {
      out.inputs.push_back({p.string(), Sha256HexOfFile(p), "calibration_capture"});
      out.protected_paths.push_back(p);
    }
    out.name = data.path->filename().string();
    out.source = data.path->string();
    return out;
  }
  if (fs::is_directory(*data.path) && !fs::exists(*data.path / kPosesCsv)) {
    // A folder without poses.csv said only "DIR/poses.csv: cannot open file" (raw markers), or
    // "DIR/reference_stream.csv: cannot open file" (a tracker stream alone), where Python's
    // trackcal.load says what a capture folder holds: the same words here.
    const fs::path& dir = *data.path;
    std::string message = dir.string() + ": not a capture folder (no " + kPosesCsv + ", no " +
                          kTrackerStreamCsv + " + " + kReferenceStreamCsv + ", no " + kMarkersCsv +
                          " + " + kTrackerCsv + ")";
    if (fs::exists(dir / kTrackerStreamCsv) != fs::exists(dir / kReferenceStreamCsv)) {
      const bool tracker = fs::exists(dir / kTrackerStreamCsv);
      message += std::string("; ") + (tracker ? kTrackerStreamCsv : kReferenceStreamCsv) +
                 " has no " + (tracker ? kReferenceStreamCsv : kTrackerStreamCsv) +
                 " beside it to be paired with";
    } else if (fs::exists(dir / kMarkersCsv) && fs::exists(dir / kTrackerCsv)) {
      message = dir.string() + ": raw markers (" + kMarkersCsv + " + " + kTrackerCsv + ", no " +
                kPosesCsv + "): register them first, trackcal-fit register --markers " +
                (dir / kMarkersCsv).string() + " --tracker " + (dir / kTrackerCsv).string() +
                " -o " + (dir / kPosesCsv).string() +
                " (the trackcal command registers such a folder itself: trackcal fit; Python: "
                "trackcal.fit(trackcal.captures.load(folder), model))";
    }
    throw std::invalid_argument(message);
  }
  const fs::path poses_path = fs::is_directory(*data.path) ? *data.path / kPosesCsv : *data.path;
  out.poses = ReadPoses(poses_path);
  out.inputs.push_back({poses_path.string(), Sha256HexOfFile(poses_path), "calibration_capture"});
  out.protected_paths.push_back(poses_path);
  out.name = poses_path.filename().string();
  out.source = poses_path.string();
  SelectSensor(&out.poses, data.sensor, out.source);
  return out;
}

}  // namespace

LoadedFitData LoadFitData(const FitData& data, const ModelSpec& spec) {
  LoadedFitData out = LoadFitDataOfFiles(data, spec);
  // The receiver chosen out of several: a refusal about its stations ("12 calibration stations
  // cannot be split into 20 cross-validation folds") named only the file, which holds every
  // receiver's stations.
  if (data.sensor != 0) out.source += " (sensor " + std::to_string(data.sensor) + ")";
  return out;
}

std::function<PairedStations(const TimeOffsetSpec&)> StreamRepairing(const LoadedFitData& data,
                                                                     const ModelSpec& spec) {
  if (!data.tracker_stream || !data.reference_stream) return {};
  // A drift the first pairing corrected is kept at a fixed offset (an estimated one estimates it).
  return [tracker = data.tracker_stream, reference = data.reference_stream,
          pairing = PairingOf(spec), sensor = data.stream_sensor,
          drift = data.pairing ? data.pairing->clock_drift : 0.0](const TimeOffsetSpec& t) {
    StreamPairingOptions o = pairing;
    o.sensor = sensor;
    o.clock_drift = drift;
    o.time_offset = t.value;
    o.estimate_time_offset = !t.fixed;
    o.search_range = t.search_range;
    const StreamPairingResult r = PairStreams(*tracker, *reference, o);
    return PairedStations{FitStationsOfPairing(r, "calib"), r.time_offset};
  };
}

nlohmann::json FitRunResult::TablesJson() const {
  nlohmann::json t = nlohmann::json::array();
  for (const auto& table : tables) t.push_back(Table1ToJson(table));
  return t;
}

nlohmann::json FitRunResult::ToJson(const std::optional<fs::path>& output) const {
  nlohmann::json doc = {{"command", "fit"},
                        {"output", output ? nlohmann::json(output->string()) : nlohmann::json()},
                        {"tables", TablesJson()},
                        {"fit", result.ToJson()}};
  if (time_offset) {
    doc["time_offset_s"] = *time_offset;
    doc["clock_drift"] = clock_drift;
    doc["clock_drift_origin_s"] = clock_drift_origin;
    doc["pairing_warning"] = pairing_warning;
  }
  return doc;
}

FitRunResult RunFit(LoadedFitData data, const FitModelSource& model, const FitRunOptions& options) {
  if (!options.Check()) {
    throw std::invalid_argument("folds must be 0 (no cross-validation) or at least 2, got " +
                                std::to_string(options.folds));
  }
  auto make_spec = [&] { return ParseModelYaml(model.text, model.source_name); };
  ModelSpec spec = make_spec();
  FitRunResult run;
  std::vector<CalibrationInput> inputs;
  if (model.path) {
    inputs.push_back({model.path->string(), Sha256HexOfFile(*model.path), "model_file"});
    run.protected_paths.push_back(*model.path);
  } else {
    inputs.push_back({"<model text>", Sha256Hex(model.text), "model_text"});
  }
  inputs.insert(inputs.end(), data.inputs.begin(), data.inputs.end());
  run.protected_paths.insert(run.protected_paths.end(), data.protected_paths.begin(),
                             data.protected_paths.end());
  run.time_offset = data.time_offset;
  run.clock_drift = data.clock_drift;
  run.clock_drift_origin = data.clock_drift_origin;
  run.pairing_warning = data.pairing_warning;
  PoseCapture& poses = data.poses;
  if (!data.stream_stations.empty()) spec.time_offset->value = *data.time_offset;
  auto calib = StationsOfSet(poses, "calib");
  const auto valid = StationsOfSet(poses, "valid");
  if (calib.empty()) throw std::invalid_argument(data.source + ": no stations with set 'calib'");
  // Refused before the fit, not after it (CrossValidate would refuse the same).
  const size_t fit_stations =
      data.stream_stations.empty() ? calib.size() : data.stream_stations.size();
  if (options.folds >= 2 && (options.cross_validate_with_validation_set || valid.empty()) &&
      fit_stations < static_cast<size_t>(options.folds)) {
    throw std::invalid_argument(data.source + ": " + std::to_string(fit_stations) +
                                " calibration stations cannot be split into " +
                                std::to_string(options.folds) +
                                " cross-validation folds (give fewer folds)");
  }

  FitOptions fit_options;
  fit_options.start = options.start.get();
  if (options.on_iteration) {
    const int max_iterations = spec.max_iterations;
    fit_options.progress = [&options, max_iterations](int iteration, double cost) {
      options.on_iteration(iteration, cost, max_iterations);
    };
  }
  if (data.stream_stations.empty()) {
    run.result = FitModel(calib, &spec, fit_options);
  } else {
    // Joint fit of the terms and the clock offset; re-pair at the estimate while it moves by more
    // than the linearisation allows (1 ms: a 1 m/s^2 acceleration then errs by 0.5 um).
    std::vector<FitStation> stations = data.stream_stations;
    for (int round = 0;; ++round) {
      const double paired_at = spec.time_offset->value;
      run.result = FitModel(stations, &spec, fit_options);
      if (std::abs(spec.time_offset->value - paired_at) < 1e-3 || round == 3) break;
      StreamPairingOptions again = *data.pairing;
      again.time_offset = spec.time_offset->value;
      again.estimate_time_offset = false;
      const auto repaired = PairStreams(*data.tracker_stream, *data.reference_stream, again);
      poses = repaired.poses;
      stations = FitStationsOfPairing(repaired, "calib");
      ModelSpec fresh = make_spec();
      fresh.time_offset->value = again.time_offset;
      spec = std::move(fresh);
    }
    run.time_offset = spec.time_offset->value;
    calib = StationsOfSet(poses, "calib");
  }
  if (run.result.Failed()) {
    run.failure = model.source_name + ": the fit to " + data.source + " failed (" +
                  run.result.termination_type + ": " + run.result.solver_message +
                  "); no calibration is written";
  }
  run.num_calib = static_cast<int>(calib.size());
  run.num_valid = static_cast<int>(valid.size());
  run.tables.push_back(EvaluateTable1(run.result.chain, calib, "calib"));
  if (!valid.empty()) run.tables.push_back(EvaluateTable1(run.result.chain, valid, "valid"));
  // (Not after a failed fit: its folds would fail too, and the error would name a fold.)
  if (options.folds >= 2 && (options.cross_validate_with_validation_set || valid.empty()) &&
      run.failure.empty()) {
    run.tables.push_back(CrossValidate(calib, make_spec, options.folds, [&](int f) {
      if (options.on_fold) options.on_fold(f, options.folds);
    }));
  }

  Calibration& cal = run.calibration;
  cal.description = "fitted by " + options.description_tool + " from " + data.name +
                    " with model " +
                    (model.path ? model.path->filename().string() : std::string("<model text>"));
  cal.chain = run.result.chain;
  // The receiver fitted (the data hold one sensor's stations after LoadFitData): a server can then
  // refuse the file on another receiver's line.
  {
    std::set<int> sensors;
    for (const auto& r : poses.records) sensors.insert(r.sensor);
    if (sensors.size() == 1 && *sensors.begin() >= 1 && *sensors.begin() <= kMaxCalibrationSensor) {
      cal.sensor = *sensors.begin();
    }
  }
  nlohmann::json stats = nlohmann::json::object();
  stats["tables"] = run.TablesJson();
  stats["chi2_per_dof"] = std::isfinite(run.result.chi2_per_dof)
                              ? nlohmann::json(run.result.chi2_per_dof)
                              : nlohmann::json();
  stats["num_calib_stations"] = calib.size();
  stats["num_valid_stations"] = valid.size();
  stats["converged"] = run.result.converged;
  stats["num_outliers"] = run.result.outliers.size();
  // Stations not fitted (solver.leave_out_unresolved): a reader sees the calibration did not use
  // every station it lists.
  stats["num_left_out"] = run.result.left_out.size();
  stats["num_poorly_identified"] = run.result.identifiability_flags.size();
  if (!run.result.covariance_estimator.empty()) {
    stats["covariance_estimator"] = run.result.covariance_estimator;
  }
  if (run.time_offset) stats["time_offset_s"] = *run.time_offset;
  // A corrected clock drift: time_offset_s holds at clock_drift_origin_s (tracker time) only, and
  // pairing these streams (trackcal validate -c) at it without the drift puts the stream's ends
  // half the drift over the stream off.
  if (run.time_offset && run.clock_drift != 0.0) {
    stats["clock_drift"] = run.clock_drift;
    stats["clock_drift_origin_s"] = run.clock_drift_origin;
  }
  // The calibration keeps why its offset may be poorly identified (the re-pairings at the fitted
  // offset do not estimate it, so they cannot warn).
  if (!run.pairing_warning.empty()) stats["pairing_warning"] = run.pairing_warning;
  cal.fit_statistics = stats;
  cal.provenance.tool = options.tool;
  cal.provenance.tool_version = options.tool_version;
  cal.provenance.created_utc = CurrentUtcTimestamp();
  cal.provenance.inputs = inputs;
  return run;
}

LoadedFitData PairAtFittedOffset(LoadedFitData data, const FitModelSource& model,
                                 double* fitted_offset_s) {
  if (data.stream_stations.empty() || !data.pairing || !data.tracker_stream ||
      !data.reference_stream) {
    return data;
  }
  std::optional<double> offset;
  try {
    offset = RunFit(data, model, {}).time_offset;  // no cross-validation
  } catch (const std::invalid_argument& e) {
    throw std::invalid_argument(std::string("fitting the model's clock offset: ") + e.what());
  }
  if (!offset) return data;
  StreamPairingOptions again = *data.pairing;
  again.time_offset = *offset;
  again.estimate_time_offset = false;
  const StreamPairingResult paired =
      PairStreams(*data.tracker_stream, *data.reference_stream, again);
  data.poses = paired.poses;
  data.time_offset = paired.time_offset;
  data.stream_stations = FitStationsOfPairing(paired, "calib");
  if (fitted_offset_s) *fitted_offset_s = *offset;
  return data;
}

nlohmann::json RegisterDocument(const RegistrationResult& registration,
                                const std::optional<std::filesystem::path>& output,
                                size_t num_poses, const std::vector<int>& stations_left_out) {
  return {{"command", "register"},
          {"output", output ? nlohmann::json(output->string()) : nlohmann::json()},
          {"num_poses", num_poses},
          {"stations_without_pose", stations_left_out.size()},
          {"stations_left_out", stations_left_out},
          {"converged", registration.converged},
          {"identifiable", registration.identifiable},
          {"chi_square", registration.chi_square},
          {"nu", registration.nu},
          {"registration", registration.ToJson()}};
}

}  // namespace trackcal::fit
