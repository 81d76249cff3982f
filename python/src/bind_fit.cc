// Bindings of fit/: the fitting engine (fit/fit_engine.h), the optical registration
// (fit/registration_io.h) and stream pairing (fit/stream_pairing.h), in process.
//
// trackcal._core.fit() does exactly what `trackcal-fit fit` does, through the same library function
// (fit/fit_run.h, also used by fit/fit_main.cc): the same data
// resolution (poses.csv, a folder with poses.csv, or a folder with streams paired with the model's
// time offset), the same fit of the `calib` set, the same Table 1 rows (calib, then valid, or
// k-fold cross-validation), the same calibration file contents, and a to_dict() equal to the CLI's
// --json document; the numbers are the same because the code is the same. Everything after the
// input conversion runs with the GIL released; the progress callback re-acquires it. Bad input
// raises ValueError with the C++ message (file, line, column and field).
#include <pybind11/functional.h>
#include <pybind11/numpy.h>
#include <pybind11/stl.h>
#include <pybind11/stl/filesystem.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <exception>
#include <filesystem>
#include <future>
#include <limits>
#include <map>
#include <mutex>
#include <optional>
#include <sstream>
#include <string>
#include <vector>

#include "core/calibration_file.h"
#include "core/capture.h"
#include "core/file_util.h"
#include "fit/fit_engine.h"
#include "fit/fit_run.h"
#include "fit/model_file.h"
#include "fit/pose_extraction.h"
#include "fit/registration.h"
#include "fit/registration_io.h"
#include "fit/stream_pairing.h"
#include "python/src/bindings.h"

// The candidate ranking (fit/candidates.h) is bound when the engine has it.
#if __has_include("fit/candidates.h")
#include "fit/candidates.h"
#define TRACKCAL_HAVE_CANDIDATES 1
#endif

namespace py = pybind11;
namespace fs = std::filesystem;

namespace trackcal::python {
namespace {

using fit::FitOptions;
using fit::FitResult;
using fit::FitStation;
using fit::ModelSpec;

py::object JsonToPython(const nlohmann::json& j) {
  return py::module_::import("json").attr("loads")(j.dump());
}

// bytes counts as a path here so that PathArgument refuses it by name.
bool IsPathLike(const py::handle& obj) {
  return py::isinstance<py::str>(obj) || py::isinstance<py::bytes>(obj) ||
         py::isinstance(obj, py::module_::import("os").attr("PathLike"));
}

// A model given as a path or as YAML text: a path object is a path; a string is a path when it
// names an existing file or looks like a file name, YAML text when it has a newline, a mapping's
// "key: " or starts a flow mapping '{'. A colon alone ("C:/models/m.yaml", "run:2/m.yaml") is no
// mapping in YAML: such a missing file is reported as missing, not as a malformed model.
struct ModelSource {
  std::string text;
  std::string source_name;       // file name or "<string>" for errors
  std::optional<fs::path> path;  // the file, if the model came from one
};

ModelSource ResolveModel(const py::handle& model) {
  ModelSource out;
  // A str that is not UTF-8 text (a file name with surrogates, from os.listdir) is a path.
  bool text_like = py::isinstance<py::str>(model);
  std::string s;
  if (text_like) {
    try {
      s = model.cast<std::string>();
    } catch (const py::cast_error&) {
      PyErr_Clear();
      text_like = false;
    }
  }
  if (text_like) {
    std::error_code ec;
    const size_t first = s.find_first_not_of(" \t");
    const bool looks_like_text =
        s.find('\n') != std::string::npos || s.find(": ") != std::string::npos ||
        (!s.empty() && s.back() == ':') || (first != std::string::npos && s[first] == '{');
    if (!(looks_like_text && !fs::is_regular_file(s, ec))) out.path = fs::path(s);
    if (!out.path) {
      out.text = s;
      out.source_name = "<string>";
      return out;
    }
  } else if (IsPathLike(model)) {
    out.path = PathArgument(model, "model");
  } else {
    throw py::value_error("model must be a model file path or its YAML text (docs/model-file.md)");
  }
  out.text = ReadFileToString(*out.path);
  out.source_name = out.path->string();
  return out;
}

// A quaternion from x, y, z, w, normalised only when it is not unit already (as the poses.csv
// reader does), so a capture read by the reader and passed back in memory gives the same fit bit
// for bit.
// A zero quaternion comes back NaN: Eigen's normalize() leaves it zero, which is finite and
// passed the check of PoseCaptureFromPython ("or a quaternion is zero") into the fit.
// A norm further from 1 than the reader allows (1e-3, core/capture.cc) is refused as the reader
// refuses it, naming the station, row and array: [0, 0, 0, 2] was normalised silently, so an
// in-memory capture fitted what its poses.csv could not even be read as.
Eigen::Quaterniond UnitQuaternion(double x, double y, double z, double w, const char* attr,
                                  int station, py::ssize_t row) {
  Eigen::Quaterniond q = QuaternionFromXyzw(x, y, z, w);
  if (q.norm() == 0.0) q.coeffs().setConstant(std::numeric_limits<double>::quiet_NaN());
  if (std::abs(q.norm() - 1.0) > 1e-3) {  // false for NaN: refused below as not finite
    std::ostringstream s;
    s.precision(6);
    s << "PoseCapture: station " << station << " (row " << row << "): " << attr << " [" << x << ", "
      << y << ", " << z << ", " << w << "] has norm " << q.norm()
      << ", not 1 (within 1e-3, as poses.csv)";
    throw py::value_error(s.str());
  }
  if (std::abs(q.norm() - 1.0) > 1e-12) q.normalize();
  return q;
}

// obj.<attr> as T; ValueError naming the attribute and what it must be otherwise (pybind11's
// cast_error would reach Python as RuntimeError "Unable to cast Python instance ...").
template <typename T>
T CastAttribute(const py::handle& obj, const char* attr, const char* expected) {
  try {
    return obj.attr(attr).cast<T>();
  } catch (const py::cast_error&) {
    throw py::value_error(std::string("PoseCapture: ") + attr + " must be " + expected + ", got " +
                          py::repr(obj.attr(attr)).cast<std::string>());
  }
}

// An integral id (station, sensor) of row i; ValueError naming it unless it is a whole number in
// the range of int (numpy's cast to an integer type truncated 1.5 to 1 and NaN to a huge number).
int IntegralId(double v, const char* name, py::ssize_t i) {
  if (!(std::isfinite(v) && v == std::trunc(v) && v >= std::numeric_limits<int>::min() &&
        v <= std::numeric_limits<int>::max())) {
    std::ostringstream s;
    s << "PoseCapture: row " << i << ": " << name << " " << v << " is not an integer";
    throw py::value_error(s.str());
  }
  return static_cast<int>(v);
}

// PoseCapture-like Python object (trackcal.captures.PoseCapture) -> C++ PoseCapture.
PoseCapture PoseCaptureFromPython(const py::handle& obj) {
  using DoubleArray = py::array_t<double, py::array::c_style | py::array::forcecast>;
  using IntArray = DoubleArray;  // ids are checked to be integers, not truncated
  for (const char* attr :
       {"station", "set", "sensor", "time", "reported_positions", "reported_quaternions_xyzw",
        "reference_positions", "reference_quaternions_xyzw"}) {
    if (!py::hasattr(obj, attr)) {
      throw py::value_error(std::string("data must be a capture folder, a poses.csv path or a "
                                        "trackcal.captures.PoseCapture (missing attribute '") +
                            attr + "')");
    }
  }
  // Each array read as float64 of the shape it must have, or a ValueError naming it: a 2-D station
  // column ((N, 1) from a DataFrame) was an IndexError "index dimension mismatch", and a
  // transposed (3, N) positions array was "every array needs one row per station", naming none.
  const auto array = [&obj](const char* attr, const char* what) {
    CheckRealNumbers(obj.attr(attr), std::string("PoseCapture: ") + attr);
    const DoubleArray a = DoubleArray::ensure(obj.attr(attr));
    if (!a) {
      PyErr_Clear();
      throw py::value_error(std::string("PoseCapture: ") + attr + " must be a numeric array " +
                            what + ", got " + py::repr(obj.attr(attr)).cast<std::string>());
    }
    return a;
  };
  const auto shape_string = [](const DoubleArray& a) {
    std::string s = "(";
    for (py::ssize_t k = 0; k < a.ndim(); ++k) s += (k ? ", " : "") + std::to_string(a.shape(k));
    return s + (a.ndim() == 1 ? ",)" : ")");
  };
  const IntArray station = array("station", "(N,)");
  if (station.ndim() != 1) {
    throw py::value_error("PoseCapture: station must have shape (N,), one id per station, got " +
                          shape_string(station));
  }
  const py::ssize_t n = station.shape(0);
  const auto shaped = [&](const char* attr, py::ssize_t cols, const char* what) {
    const DoubleArray a = array(attr, what);
    const bool ok = cols == 0 ? a.ndim() == 1 && a.shape(0) == n
                              : a.ndim() == 2 && a.shape(0) == n && a.shape(1) == cols;
    if (!ok) {
      throw py::value_error(std::string("PoseCapture: ") + attr + " must have shape " + what +
                            " with N = " + std::to_string(n) + " (one row per station), got " +
                            shape_string(a));
    }
    return a;
  };
  const IntArray sensor = shaped("sensor", 0, "(N,)");
  const DoubleArray time = shaped("time", 0, "(N,)");
  const DoubleArray rp = shaped("reported_positions", 3, "(N, 3)");
  const DoubleArray rq = shaped("reported_quaternions_xyzw", 4, "(N, 4) x, y, z, w");
  const DoubleArray fp = shaped("reference_positions", 3, "(N, 3)");
  const DoubleArray fq = shaped("reference_quaternions_xyzw", 4, "(N, 4) x, y, z, w");
  const py::sequence sets = py::reinterpret_borrow<py::sequence>(py::list(obj.attr("set")));
  if (static_cast<py::ssize_t>(sets.size()) != n) {
    throw py::value_error("PoseCapture: set needs one entry per station");
  }
  PoseCapture capture;
  py::ssize_t num_extra = 0;
  std::optional<DoubleArray> extra;
  if (py::hasattr(obj, "extra_columns") && !obj.attr("extra_columns").is_none()) {
    capture.extra_columns =
        CastAttribute<std::vector<std::string>>(obj, "extra_columns", "a list of column names");
    num_extra = static_cast<py::ssize_t>(capture.extra_columns.size());
    if (num_extra > 0) {
      CheckRealNumbers(obj.attr("extra"), "PoseCapture: extra");
      extra = DoubleArray::ensure(obj.attr("extra"));
      if (!*extra || extra->ndim() != 2 || extra->shape(0) != n || extra->shape(1) != num_extra) {
        PyErr_Clear();
        throw py::value_error("PoseCapture: extra must be (N, len(extra_columns))");
      }
    }
    // Labels columns ({column: labels}): their values are indices into the labels.
    if (py::hasattr(obj, "extra_labels") && !obj.attr("extra_labels").is_none()) {
      const auto labels = CastAttribute<std::map<std::string, std::vector<std::string>>>(
          obj, "extra_labels", "a dict {column name: list of label strings}");
      capture.extra_labels.resize(capture.extra_columns.size());
      for (const auto& [name, list] : labels) {
        const auto it = std::find(capture.extra_columns.begin(), capture.extra_columns.end(), name);
        if (it == capture.extra_columns.end()) {
          throw py::value_error("PoseCapture: extra_labels names " + name +
                                ", which is not in extra_columns");
        }
        capture.extra_labels[it - capture.extra_columns.begin()] = list;
      }
    }
  }
  capture.records.resize(static_cast<size_t>(n));
  for (py::ssize_t i = 0; i < n; ++i) {
    PoseRecord& r = capture.records[static_cast<size_t>(i)];
    r.station = IntegralId(station.at(i), "station", i);
    r.sensor = IntegralId(sensor.at(i), "sensor", i);
    r.time = time.at(i);
    // As the poses.csv reader ("column time: 'nan' is not a finite number"): a NaN time went into
    // the fit, whose sort of the stations by time (serial samples, time clusters) needs an order.
    if (!std::isfinite(r.time)) {
      std::ostringstream s;
      s << "PoseCapture: row " << i << ": time " << r.time << " is not finite";
      throw py::value_error(s.str());
    }
    r.set = py::str(sets[static_cast<size_t>(i)]).cast<std::string>();
    // As the poses.csv reader: a set of another name ("validation") was silently left out of the
    // fit and of every table.
    if (!IsKnownSet(r.set)) {
      throw py::value_error("PoseCapture: station " + std::to_string(r.station) + ": set '" +
                            r.set + "' is not one of calib, valid, reg");
    }
    r.reported.translation = Eigen::Vector3d(rp.at(i, 0), rp.at(i, 1), rp.at(i, 2));
    r.reported.rotation = UnitQuaternion(rq.at(i, 0), rq.at(i, 1), rq.at(i, 2), rq.at(i, 3),
                                         "reported_quaternions_xyzw", r.station, i);
    r.reference.translation = Eigen::Vector3d(fp.at(i, 0), fp.at(i, 1), fp.at(i, 2));
    r.reference.rotation = UnitQuaternion(fq.at(i, 0), fq.at(i, 1), fq.at(i, 2), fq.at(i, 3),
                                          "reference_quaternions_xyzw", r.station, i);
    for (py::ssize_t k = 0; k < num_extra; ++k) r.extra.push_back(extra->at(i, k));
    if (!r.reported.translation.allFinite() || !r.reference.translation.allFinite() ||
        !r.reported.rotation.coeffs().allFinite() || !r.reference.rotation.coeffs().allFinite()) {
      throw py::value_error("PoseCapture: station " + std::to_string(r.station) +
                            ": pose is not finite (or a quaternion is zero)");
    }
  }
  return capture;
}

// Where the stations come from: a file (listed in the provenance and protected from being
// overwritten) or an in-memory capture (its .path attribute protected, not hashed as input).
using DataSource = fit::FitData;

DataSource ResolveData(const py::handle& data, int sensor = 0) {
  if (sensor < 0) throw py::value_error("sensor must be a receiver number (1, 2, ...) or 0");
  DataSource out;
  out.sensor = sensor;
  if (IsPathLike(data)) {
    out.path = PathArgument(data, "data");
  } else {
    out.in_memory = PoseCaptureFromPython(data);
    if (py::hasattr(data, "path") && !data.attr("path").is_none()) {
      out.loaded_from = PathArgument(data.attr("path"), "PoseCapture.path");
    }
  }
  return out;
}

// One fit as `trackcal-fit fit` runs it (fit/fit_run.h), and where save() wrote it.
struct FitRun : fit::FitRunResult {
  std::optional<fs::path> output;  // set by save()
  // The document `trackcal-fit fit --json` prints ("output": null until saved).
  nlohmann::json ToJson() const { return fit::FitRunResult::ToJson(output); }
};

// Calls a Python progress callback from the fit, which runs without the GIL in the calling thread,
// and runs Python's signal handlers there (Ctrl-C: KeyboardInterrupt), with or without a callback.
// A Python exception raised by either is kept (later calls are skipped) and re-raised after the
// run; the run stops at its next solver iteration or cross-validation fold (failed()).
class ProgressRelay {
 public:
  explicit ProgressRelay(py::object callback) : callback_(std::move(callback)) {}
  bool enabled() const { return !callback_.is_none(); }
  void Call(const char* stage, int done, int total) {
    if (failed()) return;
    py::gil_scoped_acquire acquire;
    try {
      if (enabled()) callback_(stage, done, total);
      if (PyErr_CheckSignals() != 0) throw py::error_already_set();
    } catch (py::error_already_set& e) {
      error_ = std::make_unique<py::error_already_set>(std::move(e));
    }
  }
  bool failed() const { return error_ != nullptr; }
  void RethrowIfFailed() {
    if (error_) {
      std::unique_ptr<py::error_already_set> e = std::move(error_);
      throw std::move(*e);
    }
  }
  ~ProgressRelay() {
    if (error_) {
      py::gil_scoped_acquire acquire;
      error_.reset();
    }
  }

 private:
  py::object callback_;
  std::unique_ptr<py::error_already_set> error_;
};

struct StoppedByCallback : std::exception {};

// The fit of fit/fit_run.h (the pipeline of `trackcal-fit fit`), with Python's progress callback
// and provenance; cross-validation whenever folds >= 2.
std::shared_ptr<FitRun> RunFit(const DataSource& data, const ModelSource& model, int folds,
                               ProgressRelay* relay) {
  fit::FitRunOptions options;
  options.folds = folds;
  if (!options.Check()) {
    throw std::invalid_argument("folds must be 0 (no cross-validation) or at least 2, got " +
                                std::to_string(folds));
  }
  options.cross_validate_with_validation_set = true;
  options.tool = "trackcal-python";
  options.tool_version = TRACKCAL_VERSION;
  options.description_tool = "trackcal.fit";
  // Always installed, so that Ctrl-C stops the solve at its next iteration without a callback
  // too (Python runs signal handlers only in its own code: without a callback a KeyboardInterrupt
  // waited for the whole run, 5 s of a 5-fold LUT fit, minutes of a large one). The iteration
  // callback only reads the solver's summary: the fit is the same.
  options.on_iteration = [relay](int iteration, double, int max_iterations) {
    if (relay->failed()) throw StoppedByCallback();
    relay->Call("fit", iteration, max_iterations);
    if (relay->failed()) throw StoppedByCallback();
  };
  options.on_fold = [relay](int f, int n) {
    if (relay->failed()) throw StoppedByCallback();
    relay->Call("cross-validation", f + 1, n);
    if (relay->failed()) throw StoppedByCallback();
  };
  const ModelSpec spec = fit::ParseModelYaml(model.text, model.source_name);
  auto run = std::make_shared<FitRun>();
  static_cast<fit::FitRunResult&>(*run) =
      fit::RunFit(fit::LoadFitData(data, spec), {model.text, model.source_name, model.path}, options);
  return run;
}

// Refuses to write over one of the files a result was computed from.
void CheckNotAnInput(const fs::path& output, const std::vector<fs::path>& inputs) {
  std::error_code ec;
  if (!fs::exists(output, ec)) return;
  for (const auto& in : inputs) {
    if (fs::equivalent(output, in, ec)) {
      throw std::invalid_argument(output.string() + ": output would overwrite the input " +
                                  in.string());
    }
  }
}

py::dict PoseCaptureDict(const PoseCapture& c) { return PoseCaptureToDict(c); }

// Runs f, turning the C++ library's std::runtime_error (a file that cannot be read, an output that
// exists) into ValueError like its std::invalid_argument: both are the user's input.
template <typename F>
auto ValueErrors(F&& f) -> decltype(f()) {
  try {
    return f();
  } catch (const py::builtin_exception&) {
    throw;  // already the Python exception it must be (a TypeError stays one)
  } catch (const std::runtime_error& e) {
    throw py::value_error(e.what());
  }
}

// --- registration --------------------------------------------------------------------------

struct RegistrationRun {
  fit::RegistrationResult registration;
  std::vector<fit::ExtractedPose> extracted;
  PoseCapture poses;
  std::vector<int> left_out;
  std::vector<fs::path> inputs;
  std::optional<fs::path> output;
  nlohmann::json ToJson() const {
    return fit::RegisterDocument(registration, output, poses.records.size(), left_out);
  }
};

struct PairRun {
  fit::StreamPairingResult result;
  bool estimated = false;
  std::vector<fs::path> inputs;
  std::optional<fs::path> output;
  nlohmann::json ToJson() const { return fit::PairingJson(result, estimated, output); }
};

py::array_t<double> Vec(const Eigen::VectorXd& v) {
  py::array_t<double> a(v.size());
  std::copy(v.data(), v.data() + v.size(), a.mutable_data());
  return a;
}

py::dict RigidDict(const Rigid3d& t) {
  py::dict d;
  py::array_t<double> q(4), p(3);
  QuaternionToXyzwArray(t.rotation, q.mutable_data());
  std::copy(t.translation.data(), t.translation.data() + 3, p.mutable_data());
  d["rotation_xyzw"] = q;
  d["translation"] = p;
  return d;
}

void WritePosesChecked(const fs::path& path, const PoseCapture& poses,
                       const std::vector<fs::path>& inputs) {
  CheckNotAnInput(path, inputs);
  WritePoses(path, poses);  // atomic; refuses an existing file
}

#ifdef TRACKCAL_HAVE_CANDIDATES
// Thrown from the ranking's progress hook to stop it: not a std::exception, so the ranking's own
// handlers (a candidate's failed fit) let it through to the caller.
struct RankingStopped {};

// Progress messages of the ranking ("fitting dipole (fold 3/5)") for a Python callback. A Python
// exception from the callback, or a signal (Ctrl-C: KeyboardInterrupt, or a handler's exception),
// stops the ranking at its next progress message (each worker's candidate at its next stage,
// seconds) and is raised. The ranking runs on its own thread while this (the main) thread waits
// without the GIL and runs Python's signal handlers every 0.1 s: the ranking's workers are not the
// main thread, where alone Python runs signal handlers.
nlohmann::json DiagnoseCandidatesJson(const DataSource& data, const ModelSource& model, int folds,
                                      const std::vector<std::string>& effects,
                                      int cross_validate_top, const py::object& progress) {
  fit::CandidateOptions options;
  options.folds = folds;
  options.effects = effects;
  if (cross_validate_top < 0) throw py::value_error("cross_validate_top must be >= 0");
  options.cross_validate_top = cross_validate_top;
  std::mutex error_mutex;
  std::unique_ptr<py::error_already_set> error;  // the first Python exception (callback or signal)
  std::atomic<bool> stop{false};
  const auto keep = [&](py::error_already_set&& e) {  // with the GIL held
    std::lock_guard<std::mutex> lock(error_mutex);
    if (!error) error = std::make_unique<py::error_already_set>(std::move(e));
    stop = true;
  };
  options.progress = [&](const std::string& message) {
    if (stop) throw RankingStopped{};
    if (progress.is_none()) return;
    py::gil_scoped_acquire acquire;
    try {
      progress(message);
    } catch (py::error_already_set& e) {
      keep(std::move(e));
      throw RankingStopped{};
    }
  };
  options.Check();
  nlohmann::json doc;
  {
    py::gil_scoped_release release;
    std::future<void> ranking = std::async(std::launch::async, [&] {
      ValueErrors([&] {
        const ModelSpec spec = fit::ParseModelYaml(model.text, model.source_name);
        // Streams are paired at the offset `fit` estimates when the model frees it.
        const fit::LoadedFitData loaded = fit::PairAtFittedOffset(
            fit::LoadFitData(data, spec), {model.text, model.source_name, model.path});
        const auto calib = fit::StationsOfSet(loaded.poses, "calib");
        if (calib.empty())
          throw std::invalid_argument(loaded.name + ": no stations with set 'calib'");
        // Named with the receiver chosen out of several (its stations are the ones counted).
        const std::string data_name =
            (data.path ? data.path->string() : loaded.name) +
            (data.sensor != 0 ? " (sensor " + std::to_string(data.sensor) + ")" : "");
        // The time_offset candidate pairs the streams again with its own offset setting.
        options.pair_streams = fit::StreamRepairing(loaded, spec);
        fit::Diagnosis d =
            fit::DiagnoseCandidates(calib, model.text, model.source_name, data_name, options);
        d.time_offset_s = loaded.time_offset;
        doc = d.ToJson();
      });
    });
    while (ranking.wait_for(std::chrono::milliseconds(100)) != std::future_status::ready) {
      if (stop) continue;
      py::gil_scoped_acquire acquire;
      if (PyErr_CheckSignals() != 0) keep(py::error_already_set());
    }
    try {
      ranking.get();
    } catch (const RankingStopped&) {
      // the kept Python exception is raised below
    }
  }
  if (error) throw std::move(*error);
  return doc;
}
#endif

}  // namespace

void BindFit(py::module_& m) {
  py::class_<FitRun, std::shared_ptr<FitRun>>(
      m, "NativeFitReport",
      "Result of trackcal._core.fit (wrapped by trackcal.FitReport): tables, fit, calibration.")
      .def(
          "to_dict", [](const FitRun& r) { return JsonToPython(r.ToJson()); },
          "The document `trackcal-fit fit --json` prints (output: the path of the last save()).")
      .def_property_readonly("tables", [](const FitRun& r) { return JsonToPython(r.TablesJson()); })
      .def_property_readonly("fit", [](const FitRun& r) { return JsonToPython(r.result.ToJson()); })
      .def_property_readonly(
          "calibration", [](const FitRun& r) { return r.calibration; },
          "A copy of the fitted calibration (trackcal.Calibration).")
      .def_property_readonly("time_offset_s", [](const FitRun& r) { return r.time_offset; })
      .def_property_readonly("pairing_warning", [](const FitRun& r) { return r.pairing_warning; })
      .def_property_readonly("num_calib_stations", [](const FitRun& r) { return r.num_calib; })
      .def_property_readonly("num_valid_stations", [](const FitRun& r) { return r.num_valid; })
      .def_property_readonly("protected_paths", [](const FitRun& r) { return r.protected_paths; })
      .def_property_readonly("output", [](const FitRun& r) { return r.output; })
      .def_property_readonly(
          "failure", [](const FitRun& r) { return r.failure; },
          "Why the fit may not be saved (the solver failed), naming model and data; '' otherwise.")
      .def(
          "save",
          [](FitRun& r, const py::handle& path_obj, const std::string& command_line) {
            const fs::path path = PathArgument(path_obj, "path");
            ValueErrors([&] {
              if (!r.failure.empty()) throw std::runtime_error(r.failure);
              CheckNotAnInput(path, r.protected_paths);
              Calibration cal = r.calibration;
              cal.provenance.command_line = command_line;
              WriteCalibrationFile(path, cal);
            });
            r.output = path;
          },
          py::arg("path"), py::arg("command_line") = "",
          "Writes the calibration file atomically; refuses to overwrite any input (model, "
          "capture), and refuses a fit that failed (failure).");

  m.def(
      "fit",
      [](const py::object& data, const py::object& model, int folds, const py::object& progress,
         int sensor) {
        const DataSource source = ResolveData(data, sensor);
        const ModelSource model_source = ValueErrors([&] { return ResolveModel(model); });
        ProgressRelay relay(progress);
        std::shared_ptr<FitRun> run;
        try {
          py::gil_scoped_release release;
          run = ValueErrors([&] { return RunFit(source, model_source, folds, &relay); });
        } catch (const StoppedByCallback&) {
        }
        relay.RethrowIfFailed();
        return run;
      },
      py::arg("data"), py::arg("model"), py::kw_only(), py::arg("folds") = 0,
      py::arg("progress") = py::none(), py::arg("sensor") = 0,
      "Fits a model file to the calib set of a capture, as `trackcal-fit fit` does. data: capture "
      "folder, poses.csv path or PoseCapture; model: path or YAML text; folds >= 2 adds k-fold "
      "cross-validation; progress(stage, done, total) is called per solver iteration and fold; "
      "sensor: the receiver whose stations are fitted (0: the data must hold one sensor).");

#ifdef TRACKCAL_HAVE_CANDIDATES
  m.def(
      "diagnose_candidates",
      [](const py::object& data, const py::object& model, int folds,
         const std::optional<std::vector<std::string>>& effects, int cross_validate_top,
         const py::object& progress, int sensor) {
        const DataSource source = ResolveData(data, sensor);
        const ModelSource model_source = ValueErrors([&] { return ResolveModel(model); });
        return JsonToPython(DiagnoseCandidatesJson(source, model_source, folds,
                                                   effects.value_or(std::vector<std::string>{}),
                                                   cross_validate_top, progress));
      },
      py::arg("data"), py::arg("model"), py::kw_only(), py::arg("folds") = 5,
      py::arg("effects") = py::none(),
      py::arg("cross_validate_top") = fit::CandidateOptions().cross_validate_top,
      py::arg("progress") = py::none(), py::arg("sensor") = 0,
      "Ranks the catalog effects the model lacks (fit/candidates.h): the document of "
      "`trackcal-fit diagnose --json` as a dict. cross_validate_top N > 0 cross-validates only "
      "the N candidates with the best BIC (0: every one). progress(message) gets the ranking's "
      "messages.");
#endif

  // What save() of a registration or a pairing does, for one that was pickled (its native run
  // does not pickle; trackcal.fitting keeps its poses as a PoseCapture).
  m.def(
      "write_poses",
      [](const py::handle& path, const py::handle& capture, const py::handle& inputs) {
        const fs::path out = PathArgument(path, "path");
        const PoseCapture poses = PoseCaptureFromPython(capture);
        std::vector<fs::path> protected_paths;
        for (const py::handle& in : inputs) protected_paths.push_back(PathArgument(in, "inputs"));
        ValueErrors([&] { WritePosesChecked(out, poses, protected_paths); });
      },
      py::arg("path"), py::arg("capture"), py::arg("inputs"),
      "Writes a PoseCapture as poses.csv atomically; never over an existing file or an input.");

  m.def(
      "parse_model",
      [](const py::object& model) {
        const ModelSource source = ValueErrors([&] { return ResolveModel(model); });
        const ModelSpec spec = fit::ParseModelYaml(source.text, source.source_name);
        py::list types;
        for (const auto& t : spec.terms) types.append(t->name());
        py::dict d;
        d["source"] = source.source_name;
        // A model file's bytes need not be UTF-8 (a Latin-1 comment parses); the text decodes with
        // surrogateescape so that .encode("utf-8", "surrogateescape") gives the file's bytes back.
        d["text"] = py::reinterpret_steal<py::str>(PyUnicode_DecodeUTF8(
            source.text.data(), static_cast<Py_ssize_t>(source.text.size()), "surrogateescape"));
        d["sha256"] = Sha256Hex(source.text);
        d["terms"] = types;
        return d;
      },
      py::arg("model"),
      "Checks a model (path or YAML text): {source, text, sha256, terms: term names}; ValueError "
      "naming file, line, column and field otherwise. text is the file's bytes decoded as UTF-8 "
      "with surrogateescape (bytes that are not UTF-8 survive a round trip).");

  py::class_<RegistrationRun, std::shared_ptr<RegistrationRun>>(
      m, "NativeRegistration", "Result of trackcal._core.register (wrapped by trackcal.register).")
      .def("to_dict", [](const RegistrationRun& r) { return JsonToPython(r.ToJson()); })
      .def_property_readonly("poses",
                             [](const RegistrationRun& r) { return PoseCaptureDict(r.poses); })
      .def_property_readonly("left_out", [](const RegistrationRun& r) { return r.left_out; })
      .def_property_readonly(
          "symmetry_warning",
          [](const RegistrationRun& r) { return fit::SymmetricMarkersWarning(r.extracted); })
      .def_property_readonly(
          "no_pose_summary",
          [](const RegistrationRun& r) { return fit::NoPoseSummary(r.extracted, r.left_out); },
          "\"\" or why the stations in left_out give no pose, counted per status.")
      .def_property_readonly("converged",
                             [](const RegistrationRun& r) { return r.registration.converged; })
      .def_property_readonly("identifiable",
                             [](const RegistrationRun& r) { return r.registration.identifiable; })
      .def_property_readonly("chi_square",
                             [](const RegistrationRun& r) { return r.registration.chi_square; })
      .def_property_readonly("nu", [](const RegistrationRun& r) { return r.registration.nu; })
      .def_property_readonly(
          "optical_from_transmitter",
          [](const RegistrationRun& r) {
            return RigidDict(r.registration.registration.optical_from_transmitter);
          })
      .def_property_readonly(
          "optical_from_transmitter_stddev",
          [](const RegistrationRun& r) {
            return Vec(r.registration.optical_from_transmitter_stddev);
          },
          "[rotation vector (rad, optical axes); translation (m)].")
      .def_property_readonly("markers",
                             [](const RegistrationRun& r) {
                               py::list out;
                               for (const auto& mk : r.registration.markers) {
                                 py::dict d;
                                 d["marker"] = mk.marker;
                                 d["marker_in_receiver"] = Vec(mk.marker_in_receiver);
                                 d["stddev"] = Vec(mk.stddev);
                                 d["num_observations"] = mk.num_observations;
                                 out.append(d);
                               }
                               return out;
                             })
      .def_property_readonly("identifiability_flags",
                             [](const RegistrationRun& r) {
                               py::list out;
                               for (const auto& f : r.registration.covariance.flags) {
                                 out.append(py::dict(py::arg("coordinate") = f.coordinate,
                                                     py::arg("reason") = f.reason));
                               }
                               return out;
                             })
      .def("summary", [](const RegistrationRun& r) { return r.registration.ToString(); })
      .def_property_readonly(
          "inputs", [](const RegistrationRun& r) { return r.inputs; },
          "The files read (markers.csv, tracker.csv, poses.csv): save() never writes over one.")
      .def(
          "save",
          [](RegistrationRun& r, const py::handle& path_obj) {
            const fs::path path = PathArgument(path_obj, "path");
            ValueErrors([&] { WritePosesChecked(path, r.poses, r.inputs); });
            r.output = path;
          },
          py::arg("path"), "Writes poses.csv atomically; never over an existing file or an input.");

  m.def(
      "register",
      [](const py::object& markers, const py::object& tracker, int sensor, const std::string& set,
         double optical_noise_m, double tracker_position_noise_m,
         double tracker_orientation_noise_deg, int min_markers_per_station, const py::object& poses,
         bool reject_bad_stations) {
        auto run = std::make_shared<RegistrationRun>();
        const fs::path markers_path = PathArgument(markers, "markers");
        const fs::path tracker_path = PathArgument(tracker, "tracker");
        run->inputs = {markers_path, tracker_path};
        const bool labelled = !poses.is_none();
        const fs::path poses_path = labelled ? PathArgument(poses, "poses") : fs::path();
        if (labelled) run->inputs.push_back(poses_path);
        fit::RegistrationOptions options;
        options.optical_noise_m = optical_noise_m;
        options.tracker_position_noise_m = tracker_position_noise_m;
        options.tracker_orientation_noise_rad = tracker_orientation_noise_deg * kRadPerDeg;
        options.min_markers_per_station = min_markers_per_station;
        options.reject_bad_stations = reject_bad_stations;
        // Each option named: a bad min_markers_per_station was reported as "noise must be > 0".
        const auto require = [](bool ok, const std::string& what, double value) {
          if (!ok) {
            std::ostringstream s;
            s << "register: " << what << ", got " << value;
            throw py::value_error(s.str());
          }
        };
        require(std::isfinite(optical_noise_m) && optical_noise_m > 0.0,
                "optical_noise_m must be positive and finite", optical_noise_m);
        require(std::isfinite(tracker_position_noise_m) && tracker_position_noise_m > 0.0,
                "tracker_position_noise_m must be positive and finite", tracker_position_noise_m);
        require(std::isfinite(tracker_orientation_noise_deg) && tracker_orientation_noise_deg > 0.0,
                "tracker_orientation_noise_deg must be positive and finite",
                tracker_orientation_noise_deg);
        require(min_markers_per_station >= 1, "min_markers_per_station must be at least 1",
                min_markers_per_station);
        if (!options.Check()) throw py::value_error("register: invalid options");
        fit::PoseRecordOptions record_options;
        record_options.set = set;
        record_options.sensor = sensor;
        if (!record_options.Check())
          throw py::value_error("register: set must be calib, valid or reg");
        py::gil_scoped_release release;
        ValueErrors([&] {
          const auto stations = fit::ReadRegistrationStations(markers_path, tracker_path, sensor);
          // With a poses.csv, as `trackcal-fit register --poses`: its `reg` stations register, and
          // every station keeps its set and time; without, every station registers.
          std::map<int, std::string> set_of;
          std::map<int, double> time_of;
          PoseCapture labels;
          if (labelled) {
            labels = ReadPoses(poses_path);
            for (const PoseRecord& r : labels.records) {
              set_of[r.station] = r.set;
              time_of[r.station] = r.time;
            }
            for (const fit::RegistrationStation& st : stations) {
              if (!set_of.count(st.station)) {
                throw std::invalid_argument(poses_path.string() + ": column station: no row for station " +
                                            std::to_string(st.station) + " of " +
                                            markers_path.filename().string());
              }
            }
          }
          std::vector<fit::RegistrationStation> registering;
          for (const fit::RegistrationStation& st : stations) {
            if (!labelled || set_of[st.station] == "reg") registering.push_back(st);
          }
          if (registering.empty()) {
            throw std::invalid_argument(poses_path.string() + ": no station of " +
                                        markers_path.filename().string() + " has set 'reg'");
          }
          run->registration = fit::RegisterOpticalToTransmitter(registering, options);
          fit::PoseExtractionOptions extraction;
          extraction.optical_noise_m = optical_noise_m;
          run->extracted = fit::ExtractPoses(stations, run->registration.registration, extraction,
                                             markers_path.string());
          for (size_t i = 0; i < stations.size(); ++i) {
            fit::PoseRecordOptions one_options = record_options;
            if (labelled) one_options.set = set_of[stations[i].station];
            fit::PoseRecords one =
                fit::MakePoseRecords({stations[i]}, {run->extracted[i]}, time_of, one_options);
            run->poses.records.insert(run->poses.records.end(), one.capture.records.begin(),
                                      one.capture.records.end());
            run->left_out.insert(run->left_out.end(), one.left_out.begin(), one.left_out.end());
          }
          if (labelled) fit::CopyExtraColumns(labels, &run->poses);
        });
        return run;
      },
      py::arg("markers"), py::arg("tracker"), py::kw_only(), py::arg("sensor") = 1,
      py::arg("set") = "calib", py::arg("optical_noise_m") = 1.5e-4,
      py::arg("tracker_position_noise_m") = 8e-4, py::arg("tracker_orientation_noise_deg") = 0.15,
      py::arg("min_markers_per_station") = 3, py::arg("poses") = py::none(),
      py::arg("reject_bad_stations") = true,
      "Registers the optical frame to the transmitter from markers.csv and tracker.csv and "
      "extracts each station's reference pose, as `trackcal-fit register` does; with `poses` (a "
      "poses.csv) only its `reg` stations register and every station keeps its set and time, as "
      "`trackcal-fit register --poses`.");

  py::class_<PairRun, std::shared_ptr<PairRun>>(
      m, "NativePairing", "Result of trackcal._core.pair (wrapped by trackcal.pair).")
      .def("to_dict", [](const PairRun& r) { return JsonToPython(r.ToJson()); })
      .def_property_readonly("poses",
                             [](const PairRun& r) { return PoseCaptureDict(r.result.poses); })
      .def_property_readonly("time_offset_s", [](const PairRun& r) { return r.result.time_offset; })
      .def_property_readonly("dropped", [](const PairRun& r) { return r.result.dropped; })
      .def_property_readonly("cost", [](const PairRun& r) { return r.result.cost; })
      .def_property_readonly(
          "inputs", [](const PairRun& r) { return r.inputs; },
          "The streams read: save() never writes over one.")
      .def(
          "save",
          [](PairRun& r, const py::handle& path_obj) {
            const fs::path path = PathArgument(path_obj, "path");
            ValueErrors([&] { WritePosesChecked(path, r.result.poses, r.inputs); });
            r.output = path;
          },
          py::arg("path"), "Writes poses.csv atomically; never over an existing file or an input.");

  m.def(
      "pair",
      [](const py::object& tracker, const py::object& reference, double time_offset,
         bool estimate_time_offset, double search_range, double max_gap_s, int sensor,
         const std::string& set, int decimate, double clock_drift,
         std::optional<double> clock_drift_origin) {
        auto run = std::make_shared<PairRun>();
        const fs::path tracker_path = PathArgument(tracker, "tracker");
        const fs::path reference_path = PathArgument(reference, "reference");
        run->inputs = {tracker_path, reference_path};
        fit::StreamPairingOptions options;
        options.time_offset = time_offset;
        options.estimate_time_offset = estimate_time_offset;
        options.search_range = search_range;
        options.max_gap_s = max_gap_s;
        options.sensor = sensor;
        options.set = set;
        options.decimate = decimate;
        options.clock_drift = clock_drift;
        if (clock_drift_origin) options.clock_drift_origin = *clock_drift_origin;
        run->estimated = estimate_time_offset;
        // Checked before the work, as register() does: an unknown set paired every sample and
        // then save() refused the poses ("p.csv: record 0: set 'x' ...", naming the output).
        if (!IsKnownSet(set)) {
          throw py::value_error("pair: set must be calib, valid or reg, got '" + set + "'");
        }
        py::gil_scoped_release release;
        ValueErrors([&] {
          run->result = fit::PairStreamsOfFiles(ReadTrackerStream(tracker_path),
                                                ReadReferenceStream(reference_path), options,
                                                tracker_path, reference_path);
        });
        return run;
      },
      py::arg("tracker"), py::arg("reference"), py::kw_only(), py::arg("time_offset") = 0.0,
      py::arg("estimate_time_offset") = false, py::arg("search_range") = 0.5,
      py::arg("max_gap_s") = 0.1, py::arg("sensor") = 0, py::arg("set") = "calib",
      py::arg("decimate") = 1, py::arg("clock_drift") = 0.0,
      py::arg("clock_drift_origin") = py::none(),
      "Pairs tracker_stream.csv with reference_stream.csv by time, as `trackcal-fit pair` does.");
}

}  // namespace trackcal::python
