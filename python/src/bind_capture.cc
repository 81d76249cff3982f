// Bindings of core/capture.h and core/error_statistics.h: the one CSV reader/writer and the one
// implementation of the paper's Table 1 statistics, so Python and C++ tools agree to the bit.
// Captures cross the boundary as dicts of numpy arrays (positions (N, 3), quaternions (N, 4) ordered
// x, y, z, w); reader errors keep the C++ text "file:line: column name: problem" (ValueError).
#include <pybind11/numpy.h>
#include <pybind11/stl.h>
#include <pybind11/stl/filesystem.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <map>
#include <sstream>
#include <stdexcept>
#include <string>
#include <vector>

#include "core/capture.h"
#include "core/error_statistics.h"
#include "python/src/bindings.h"

namespace py = pybind11;

namespace trackcal::python {
namespace {

using DoubleArray = py::array_t<double, py::array::c_style | py::array::forcecast>;

py::array_t<double> Positions(size_t n, const auto& get) {
  py::array_t<double> a({static_cast<py::ssize_t>(n), py::ssize_t{3}});
  auto r = a.mutable_unchecked<2>();
  for (size_t i = 0; i < n; ++i) {
    const Eigen::Vector3d& p = get(i).translation;
    for (int k = 0; k < 3; ++k) r(i, k) = p[k];
  }
  return a;
}

py::array_t<double> Quaternions(size_t n, const auto& get) {
  py::array_t<double> a({static_cast<py::ssize_t>(n), py::ssize_t{4}});
  auto r = a.mutable_unchecked<2>();
  for (size_t i = 0; i < n; ++i) {
    double xyzw[4];
    QuaternionToXyzwArray(get(i).rotation, xyzw);
    for (int k = 0; k < 4; ++k) r(i, k) = xyzw[k];
  }
  return a;
}

template <typename Record>
py::array_t<double> Extra(const CaptureTable<Record>& table) {
  const size_t n = table.records.size(), m = table.extra_columns.size();
  py::array_t<double> a({static_cast<py::ssize_t>(n), static_cast<py::ssize_t>(m)});
  auto r = a.mutable_unchecked<2>();
  for (size_t i = 0; i < n; ++i) {
    for (size_t k = 0; k < m; ++k) r(i, k) = table.records[i].extra[k];
  }
  return a;
}

// {column: labels} for the extra columns that hold labels (their `extra` values index the list).
template <typename Record>
py::dict ExtraLabels(const CaptureTable<Record>& table) {
  py::dict d;
  for (size_t k = 0; k < table.extra_columns.size(); ++k) {
    if (const std::vector<std::string>* labels = table.LabelsOf(k)) {
      d[py::str(table.extra_columns[k])] = *labels;
    }
  }
  return d;
}

// A stream as a dict: time, positions, quaternions_xyzw (of pose_of(record)) and the extras.
template <typename Record, typename PoseOf>
py::dict StreamToDict(const CaptureTable<Record>& c, const PoseOf& pose_of) {
  const size_t n = c.records.size();
  py::dict d;
  py::array_t<double> time(n);
  for (size_t i = 0; i < n; ++i) time.mutable_at(i) = c.records[i].time;
  d["time"] = time;
  auto get = [&](size_t i) -> const Rigid3d& { return pose_of(c.records[i]); };
  d["positions"] = Positions(n, get);
  d["quaternions_xyzw"] = Quaternions(n, get);
  d["extra_columns"] = c.extra_columns;
  d["extra"] = Extra(c);
  d["extra_labels"] = ExtraLabels(c);
  return d;
}

// Reads an (N, 3) and an (N, 4) array into poses; ValueError naming the arrays otherwise. A
// quaternion within 1e-12 of unit is kept bit for bit (a loaded stream saves as it was read: it
// was normalised, changing last digits); one further than the readers' 1e-3 is normalised only
// with `normalize_any`, else kept for the writer to refuse naming its record (any norm, (0, 0, 0,
// 2), was written as a rotation).
// `prefix` + "positions" / "quaternions_xyzw" are the arguments' names in the errors
// ("estimated_"): "estimated: positions must be (N, 3) and quaternions (N, 4)" named neither array
// nor its shape.
std::vector<Rigid3d> ToPoses(const py::handle& positions_obj, const py::handle& quaternions_obj,
                             const std::string& name, bool normalize_any = true,
                             const std::string& prefix = "") {
  const auto shape_of = [](const py::handle& obj) {
    const DoubleArray a = DoubleArray::ensure(obj);
    if (!a) {
      PyErr_Clear();
      return "no numeric array: " + py::repr(obj).cast<std::string>().substr(0, 80);
    }
    std::string s = "(";
    for (py::ssize_t k = 0; k < a.ndim(); ++k) s += (k ? ", " : "") + std::to_string(a.shape(k));
    return s + (a.ndim() == 1 ? ",)" : ")");
  };
  const DoubleArray p = DoubleArray::ensure(positions_obj);
  if (!p) PyErr_Clear();
  if (!p || p.ndim() != 2 || p.shape(1) != 3) {
    throw py::value_error(name + ": " + prefix + "positions must have shape (N, 3), got " +
                          shape_of(positions_obj));
  }
  const DoubleArray q = DoubleArray::ensure(quaternions_obj);
  if (!q) PyErr_Clear();
  if (!q || q.ndim() != 2 || q.shape(1) != 4 || q.shape(0) != p.shape(0)) {
    throw py::value_error(name + ": " + prefix +
                          "quaternions_xyzw must have shape (N, 4) x, y, z, w with N = " +
                          std::to_string(p.shape(0)) + " like " + prefix + "positions, got " +
                          shape_of(quaternions_obj));
  }
  std::vector<Rigid3d> poses(p.shape(0));
  for (py::ssize_t i = 0; i < p.shape(0); ++i) {
    poses[i].translation = Eigen::Vector3d(p.at(i, 0), p.at(i, 1), p.at(i, 2));
    Eigen::Quaterniond rotation =
        QuaternionFromXyzw(q.at(i, 0), q.at(i, 1), q.at(i, 2), q.at(i, 3));
    const double off = std::abs(rotation.norm() - 1.0);
    if (off > 1e-12 && (normalize_any || off <= 1e-3)) rotation.normalize();
    poses[i].rotation = rotation;
  }
  return poses;
}

// Reads an (N, 3) array of positions; ValueError naming it otherwise.
std::vector<Eigen::Vector3d> ToPositions(const py::handle& positions_obj, const std::string& name) {
  const DoubleArray p = DoubleArray::ensure(positions_obj);
  if (!p || p.ndim() != 2 || p.shape(1) != 3) {
    PyErr_Clear();
    throw py::value_error(name + ": positions must be (N, 3)");
  }
  std::vector<Eigen::Vector3d> out(p.shape(0));
  for (py::ssize_t i = 0; i < p.shape(0); ++i) out[i] = {p.at(i, 0), p.at(i, 1), p.at(i, 2)};
  return out;
}

py::dict SummaryToDict(const ErrorSummary& s) {
  py::dict d;
  d["count"] = s.count;
  d["mean"] = s.mean;
  d["std"] = s.std;
  d["max"] = s.max;
  d["rms"] = s.rms;
  d["median"] = s.median;
  d["p95"] = s.p95;
  return d;
}

ErrorSummary SummaryFromDict(const py::dict& d) {
  ErrorSummary s;
  s.count = d["count"].cast<int>();
  s.mean = d["mean"].cast<double>();
  s.std = d["std"].cast<double>();
  s.max = d["max"].cast<double>();
  return s;
}

// The stream the arrays describe, for write_tracker_stream and format_tracker_stream (`function`
// in shape errors, `name` for the file in value errors).
TrackerStream ToTrackerStream(const std::string& function, const std::string& name,
                              const py::handle& time_obj, const py::handle& sensor_obj,
                              const py::handle& positions, const py::handle& quaternions,
                              const std::vector<std::string>& extra_columns,
                              const py::handle& extra_obj,
                              const std::map<std::string, std::vector<std::string>>& extra_labels) {
  const std::vector<Rigid3d> poses = ToPoses(positions, quaternions, function,
                                             /*normalize_any=*/false);
  const py::ssize_t n = static_cast<py::ssize_t>(poses.size());
  const DoubleArray time = DoubleArray::ensure(time_obj);
  // Read as numbers and checked: the int cast truncated a sensor of 1.7 to 1.
  const DoubleArray sensor = DoubleArray::ensure(sensor_obj);
  if (!time || !sensor || time.ndim() != 1 || sensor.ndim() != 1 || time.shape(0) != n ||
      sensor.shape(0) != n) {
    PyErr_Clear();
    throw py::value_error(function + ": time and sensor must be (N,) like positions");
  }
  // The extra columns (a temperature, an operator's label) were dropped without a word.
  TrackerStream s;
  s.extra_columns = extra_columns;
  const py::ssize_t num_extra = static_cast<py::ssize_t>(extra_columns.size());
  DoubleArray extra;
  if (num_extra > 0) {
    extra = DoubleArray::ensure(extra_obj);
    if (!extra || extra.ndim() != 2 || extra.shape(0) != n || extra.shape(1) != num_extra) {
      PyErr_Clear();
      throw py::value_error(function + ": extra must be (N, len(extra_columns))");
    }
  }
  if (!extra_labels.empty()) s.extra_labels.resize(extra_columns.size());
  for (const auto& [column, labels] : extra_labels) {
    const auto it = std::find(extra_columns.begin(), extra_columns.end(), column);
    if (it == extra_columns.end()) {
      throw py::value_error(function + ": extra_labels names " + column +
                            ", which is not in extra_columns");
    }
    s.extra_labels[it - extra_columns.begin()] = labels;
  }
  s.records.resize(poses.size());
  for (size_t i = 0; i < poses.size(); ++i) {
    const double id = sensor.at(i);
    if (!(std::isfinite(id) && id == std::trunc(id) && id >= std::numeric_limits<int>::min() &&
          id <= std::numeric_limits<int>::max())) {
      std::ostringstream message;
      message << name << ": record " << i << ": column sensor: " << id << " is not an integer";
      throw py::value_error(message.str());
    }
    s.records[i].time = time.at(i);
    s.records[i].sensor = static_cast<int>(id);
    s.records[i].transmitter_from_receiver = poses[i];
    for (py::ssize_t k = 0; k < num_extra; ++k) s.records[i].extra.push_back(extra.at(i, k));
  }
  return s;
}

}  // namespace

py::dict PoseCaptureToDict(const PoseCapture& c) {
  const size_t n = c.records.size();
  py::dict d;
  py::array_t<int> station(n), sensor(n);
  py::array_t<double> time(n);
  py::list sets;
  for (size_t i = 0; i < n; ++i) {
    station.mutable_at(i) = c.records[i].station;
    sensor.mutable_at(i) = c.records[i].sensor;
    time.mutable_at(i) = c.records[i].time;
    sets.append(c.records[i].set);
  }
  d["station"] = station;
  d["set"] = sets;
  d["sensor"] = sensor;
  d["time"] = time;
  d["reported_positions"] = Positions(n, [&](size_t i) -> const Rigid3d& { return c.records[i].reported; });
  d["reported_quaternions_xyzw"] = Quaternions(n, [&](size_t i) -> const Rigid3d& { return c.records[i].reported; });
  d["reference_positions"] = Positions(n, [&](size_t i) -> const Rigid3d& { return c.records[i].reference; });
  d["reference_quaternions_xyzw"] = Quaternions(n, [&](size_t i) -> const Rigid3d& { return c.records[i].reference; });
  d["extra_columns"] = c.extra_columns;
  d["extra"] = Extra(c);
  d["extra_labels"] = ExtraLabels(c);
  return d;
}

void BindCapture(py::module_& m) {
  m.def(
      "read_poses",
      [](const py::handle& path) {
        return PoseCaptureToDict(ReadPoses(PathArgument(path, "path")));
      },
      py::arg("path"),
      "Reads poses.csv (core/capture.h) into a dict of arrays: station, set (list), sensor, time, "
      "reported_/reference_positions (N, 3) [m], reported_/reference_quaternions_xyzw (N, 4), "
      "extra_columns (list), extra (N, K) and extra_labels ({column: labels} for the columns that "
      "hold labels; their values index the labels, NaN where missing). Errors: ValueError "
      "'file:line: column c: problem'.");

  m.def(
      "read_tracker_stream",
      [](const py::handle& path) {
        const TrackerStream c = ReadTrackerStream(PathArgument(path, "path"));
        py::dict d = StreamToDict(c, [](const TrackerStreamSample& r) -> const Rigid3d& {
          return r.transmitter_from_receiver;
        });
        py::array_t<int> sensor(c.records.size());
        for (size_t i = 0; i < c.records.size(); ++i) sensor.mutable_at(i) = c.records[i].sensor;
        d["sensor"] = sensor;
        return d;
      },
      py::arg("path"),
      "Reads tracker_stream.csv into time, sensor, positions, quaternions_xyzw, extra.");

  m.def(
      "read_reference_stream",
      [](const py::handle& path) {
        return StreamToDict(ReadReferenceStream(PathArgument(path, "path")),
                            [](const ReferenceStreamSample& r) -> const Rigid3d& {
                              return r.transmitter_from_body;
                            });
      },
      py::arg("path"),
      "Reads reference_stream.csv (reference clock) into time, positions, quaternions_xyzw, "
      "extra.");

  m.def(
      "write_tracker_stream",
      [](const py::handle& path_obj, const py::handle& time_obj, const py::handle& sensor_obj,
         const py::handle& positions, const py::handle& quaternions, bool overwrite,
         const std::vector<std::string>& extra_columns, const py::handle& extra_obj,
         const std::map<std::string, std::vector<std::string>>& extra_labels) {
        const std::filesystem::path path = PathArgument(path_obj, "path");
        const TrackerStream s =
            ToTrackerStream("write_tracker_stream", path.string(), time_obj, sensor_obj, positions,
                            quaternions, extra_columns, extra_obj, extra_labels);
        WriteTrackerStream(path, s, CaptureWriteOptions{.overwrite = overwrite});
      },
      py::arg("path"), py::arg("time"), py::arg("sensor"), py::arg("positions"),
      py::arg("quaternions_xyzw"), py::arg("overwrite") = false,
      py::arg("extra_columns") = std::vector<std::string>{}, py::arg("extra") = py::none(),
      py::arg("extra_labels") = std::map<std::string, std::vector<std::string>>{},
      "Writes tracker_stream.csv atomically; refuses to replace an existing file unless overwrite. "
      "extra (N, K) holds the extra columns extra_columns names; a column of labels holds indices "
      "into extra_labels[name] (as read_tracker_stream gives them).");

  m.def(
      "format_tracker_stream",
      [](const py::handle& time_obj, const py::handle& sensor_obj, const py::handle& positions,
         const py::handle& quaternions, const std::string& name, bool header,
         const std::vector<std::string>& extra_columns, const py::handle& extra_obj,
         const std::map<std::string, std::vector<std::string>>& extra_labels) {
        const TrackerStream s =
            ToTrackerStream("format_tracker_stream", name, time_obj, sensor_obj, positions,
                            quaternions, extra_columns, extra_obj, extra_labels);
        return py::bytes(FormatTrackerStream(s, name, header));
      },
      py::arg("time"), py::arg("sensor"), py::arg("positions"), py::arg("quaternions_xyzw"),
      py::kw_only(), py::arg("name"), py::arg("header") = true,
      py::arg("extra_columns") = std::vector<std::string>{}, py::arg("extra") = py::none(),
      py::arg("extra_labels") = std::map<std::string, std::vector<std::string>>{},
      "The bytes write_tracker_stream writes, without a file (name stands for it in the errors, "
      "which are the writer's); the rows alone when not header, to append to a file that has it.");

  m.def(
      "summarize_errors",
      [](const py::handle& values) {
        const DoubleArray v = DoubleArray::ensure(values);
        if (!v || v.ndim() != 1) {
          PyErr_Clear();
          throw py::value_error("values must be a 1-D numeric array");
        }
        return SummaryToDict(SummarizeErrors(std::span<const double>(v.data(), v.size())));
      },
      py::arg("values"),
      "count, mean, std (n - 1), max, rms, median, p95 of error magnitudes (core/error_statistics.h).");

  m.def(
      "error_magnitudes",
      [](const py::handle& est_p, const py::handle& est_q, const py::handle& ref_p,
         const py::handle& ref_q) {
        const auto est = ToPoses(est_p, est_q, "error_magnitudes", true, "estimated_");
        const auto ref = ToPoses(ref_p, ref_q, "error_magnitudes", true, "reference_");
        // A zero quaternion stays zero through normalized() and its error angle came out 0: a
        // station without a rotation counted as a perfect one in Table 1. (NaN stays NaN.)
        for (const auto* poses : {&est, &ref}) {
          for (size_t i = 0; i < poses->size(); ++i) {
            if ((*poses)[i].rotation.coeffs().isZero(0.0)) {
              throw py::value_error(std::string(poses == &est ? "estimated" : "reference") +
                                    "_quaternions_xyzw: row " + std::to_string(i) +
                                    " is zero, not a rotation");
            }
          }
        }
        std::vector<double> pos_mm, ori_deg;
        ComputeErrorMagnitudes(est, ref, &pos_mm, &ori_deg);
        return py::make_tuple(py::array_t<double>(pos_mm.size(), pos_mm.data()),
                              py::array_t<double>(ori_deg.size(), ori_deg.data()));
      },
      py::arg("estimated_positions"), py::arg("estimated_quaternions_xyzw"),
      py::arg("reference_positions"), py::arg("reference_quaternions_xyzw"),
      "Per-pose position error [mm] and orientation error angle [deg] (paper eq. 1, 3).");

  m.def("improvement_percent", &ImprovementPercent, py::arg("before"), py::arg("after"));

  m.def(
      "hemisphere_flips_to_leave_out",
      [](const py::handle& reported, const py::handle& reference) {
        const auto rep = ToPositions(reported, "reported");
        const auto ref = ToPositions(reference, "reference");
        if (rep.size() != ref.size()) {
          throw py::value_error("hemisphere_flips_to_leave_out: " + std::to_string(rep.size()) +
                                " reported but " + std::to_string(ref.size()) +
                                " reference positions");
        }
        const std::vector<int> flips = HemisphereFlipsToLeaveOut(rep, ref);
        return py::array_t<int>(flips.size(), flips.data());
      },
      py::arg("reported_positions"), py::arg("reference_positions"),
      "Indices of the reports in the other hemisphere than their reference, when fewer than half "
      "(core/error_statistics.h HemisphereFlipsToLeaveOut); empty otherwise.");

  m.def(
      "format_table1",
      [](const std::string& set_name, const py::dict& before_pos, const py::dict& before_ori,
         const py::dict& after_pos, const py::dict& after_ori, int flips_left_out) {
        Table1 t;
        t.set_name = set_name;
        t.flips_left_out = flips_left_out;
        t.before.position_mm = SummaryFromDict(before_pos);
        t.before.orientation_deg = SummaryFromDict(before_ori);
        t.after.position_mm = SummaryFromDict(after_pos);
        t.after.orientation_deg = SummaryFromDict(after_ori);
        return FormatTable1(t);
      },
      py::arg("set_name"), py::arg("before_position_mm"), py::arg("before_orientation_deg"),
      py::arg("after_position_mm"), py::arg("after_orientation_deg"),
      py::arg("flips_left_out") = 0,
      "The paper's Table 1 layout from summarize_errors dicts; `flips_left_out` hemisphere flips "
      "left out of them.");
}

}  // namespace trackcal::python
