// Bindings of core/: pose helpers, corrections and the calibration file. Batches of poses cross the
// boundary as numpy arrays (N x 3 positions, N x 4 x, y, z, w quaternions) and are corrected in C++
// with the GIL released; user errors (bad shapes, bad files) raise ValueError naming the problem.
#include <pybind11/eigen.h>
#include <pybind11/numpy.h>
#include <pybind11/stl.h>
#include <pybind11/stl/filesystem.h>

#include <sstream>

#include "core/calibration_file.h"
#include "core/file_util.h"
#include "core/lut.h"
#include "core/polynomial.h"
#include "core/pose.h"
#include "python/src/bindings.h"

namespace py = pybind11;

namespace trackcal::python {

namespace {

using DoubleArray = py::array_t<double, py::array::c_style | py::array::forcecast>;

// How far from 1 a quaternion's norm may be, as the capture readers allow (core/capture.cc).
constexpr double kQuaternionNormTolerance = 1e-3;

std::string ShapeString(const py::array& a) {
  std::ostringstream s;
  s << "(";
  for (py::ssize_t i = 0; i < a.ndim(); ++i) {
    if (i) s << ", ";
    s << a.shape(i);
  }
  if (a.ndim() == 1) s << ",";
  s << ")";
  return s.str();
}

std::string ExpectedShape(const std::vector<py::ssize_t>& shape) {
  std::ostringstream s;
  s << "(";
  for (size_t i = 0; i < shape.size(); ++i) {
    if (i) s << ", ";
    if (shape[i] < 0) {
      s << "N";
    } else {
      s << shape[i];
    }
  }
  if (shape.size() == 1) s << ",";
  s << ")";
  return s.str();
}

// A C-contiguous float64 view of `obj` with the given shape (-1: any length); ValueError otherwise
// (TypeError for values that are not real numbers).
DoubleArray AsArray(const py::handle& obj, const std::string& name,
                    const std::vector<py::ssize_t>& shape, const std::string& note = "") {
  CheckRealNumbers(obj, name);
  DoubleArray a = DoubleArray::ensure(obj);
  if (!a) {
    PyErr_Clear();
    throw py::value_error(name + " must be a numeric array of shape " + ExpectedShape(shape) +
                          note);
  }
  bool ok = a.ndim() == static_cast<py::ssize_t>(shape.size());
  for (size_t i = 0; ok && i < shape.size(); ++i) ok = shape[i] < 0 || a.shape(i) == shape[i];
  if (!ok) {
    throw py::value_error(name + " must have shape " + ExpectedShape(shape) + note + ", got " +
                          ShapeString(a));
  }
  return a;
}

Eigen::Vector3d AsVector3(const py::handle& obj, const std::string& name) {
  const DoubleArray a = AsArray(obj, name, {3});
  return Eigen::Vector3d(a.at(0), a.at(1), a.at(2));
}

std::vector<double> Flatten(const DoubleArray& a) {
  return std::vector<double>(a.data(), a.data() + a.size());
}

py::array_t<double> ToArray(const std::vector<double>& v, std::vector<py::ssize_t> shape) {
  py::array_t<double> a(shape);
  std::copy(v.begin(), v.end(), a.mutable_data());
  return a;
}

py::array_t<double> ToArray(const Eigen::Vector3d& v) {
  return ToArray(std::vector<double>{v.x(), v.y(), v.z()}, {3});
}

// Splits a (n x 6) node-major array into its position (first 3) or orientation (last 3) columns.
std::vector<double> Columns(const std::vector<double>& v, int first) {
  std::vector<double> out;
  out.reserve(v.size() / 2);
  for (size_t i = 0; i < v.size(); i += 6) {
    for (int k = 0; k < 3; ++k) out.push_back(v[i + first + k]);
  }
  return out;
}

// Corrects a batch through `apply` (a Correction's or a chain's ApplyBatchWithStatus) with the GIL
// released. Returns (positions, quaternions, extrapolated) and, with `with_status`, the per-pose
// CorrectionStatus as a uint8 array (0 converged, 1 ambiguous, 2 not_converged).
template <typename Apply>
py::tuple CorrectBatch(const py::handle& positions_obj, const py::handle& quaternions_obj,
                       bool with_status, const Apply& apply) {
  const DoubleArray positions = AsArray(positions_obj, "positions", {-1, 3});
  const py::ssize_t n = positions.shape(0);
  const DoubleArray quaternions =
      AsArray(quaternions_obj, "quaternions_xyzw", {n, 4},
              " (N = " + std::to_string(n) + " rows like positions, columns x, y, z, w)");
  // A zero quaternion is no orientation: it came back zero, with status converged. NaN rows
  // (dropped samples) still give NaN out, as numpy does.
  // An infinite value is no pose either: [0, 0, 0, inf] came back as [-inf, -inf, -inf, inf].
  // A quaternion's norm is 1 within the capture readers' tolerance (core/capture.cc: a few digits
  // of a hand-edited or low-precision file), and such a row is normalised as they normalise it;
  // further from 1 it is no rotation and refused: the terms keep the norm, so [0, 0, 0, 2] came
  // back with norm 2 and 1.0005 with norm 1.0005.
  std::vector<double> normalised;  // a copy of the quaternions, made when a row needs it
  for (py::ssize_t i = 0; i < n; ++i) {
    const double* q = quaternions.data() + 4 * i;
    if (q[0] == 0.0 && q[1] == 0.0 && q[2] == 0.0 && q[3] == 0.0) {
      throw py::value_error("quaternions_xyzw: row " + std::to_string(i) +
                            " is zero, not a rotation");
    }
    const double* p = positions.data() + 3 * i;
    const bool bad_q = std::any_of(q, q + 4, [](double v) { return std::isinf(v); });
    if (bad_q || std::any_of(p, p + 3, [](double v) { return std::isinf(v); })) {
      throw py::value_error(std::string(bad_q ? "quaternions_xyzw" : "positions") + ": row " +
                            std::to_string(i) +
                            " holds an infinite value (a dropped sample is NaN, which comes "
                            "back NaN)");
    }
    const double norm = std::sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
    if (std::abs(norm - 1.0) > kQuaternionNormTolerance) {  // false for a NaN row
      std::ostringstream s;
      s.precision(6);
      s << "quaternions_xyzw: row " << i << " has norm " << norm
        << ", not 1 (a rotation's quaternion x, y, z, w is unit; within "
        << kQuaternionNormTolerance << " it is normalised, as a capture file's)";
      throw py::value_error(s.str());
    }
    if (std::abs(norm - 1.0) > 1e-12) {  // unit rows are kept bit for bit, as the readers do
      if (normalised.empty()) normalised.assign(quaternions.data(), quaternions.data() + 4 * n);
      for (int k = 0; k < 4; ++k) normalised[4 * i + k] = q[k] / norm;
    }
  }
  py::array_t<double> out_positions({n, py::ssize_t{3}});
  py::array_t<double> out_quaternions({n, py::ssize_t{4}});
  py::array_t<bool> extrapolated(n);
  py::array_t<uint8_t> status(with_status ? n : py::ssize_t{0});
  static_assert(sizeof(bool) == sizeof(uint8_t));
  static_assert(sizeof(CorrectionStatus) == sizeof(uint8_t));
  {
    const double* p = positions.data();
    const double* q = normalised.empty() ? quaternions.data() : normalised.data();
    double* po = out_positions.mutable_data();
    double* qo = out_quaternions.mutable_data();
    auto* flags = reinterpret_cast<uint8_t*>(extrapolated.mutable_data());
    auto* statuses =
        with_status ? reinterpret_cast<CorrectionStatus*>(status.mutable_data()) : nullptr;
    py::gil_scoped_release release;
    apply(static_cast<size_t>(n), p, q, po, qo, flags, statuses);
  }
  if (with_status) return py::make_tuple(out_positions, out_quaternions, extrapolated, status);
  return py::make_tuple(out_positions, out_quaternions, extrapolated);
}

// The docstring tail shared by both correct() methods.
constexpr const char* kStatusDoc =
    " With return_status=True a fourth array, status (N,) uint8, says how each pose's model "
    "inverse (a physical term) arrived at it: 0 converged, 1 ambiguous (another true pose explains "
    "the same report, or report noise is amplified more than max_noise_gain times: next to a "
    "strong object), 2 not_converged (a bounded best guess); trackcal.correction_status_names "
    "names them and trackcal.status_counts(status) counts them. Terms without an inverse always "
    "report 0.";

py::object JsonToPython(const nlohmann::json& j) {
  return py::module_::import("json").attr("loads")(j.dump());
}

nlohmann::json PythonToJson(const py::handle& obj, const std::string& name) {
  std::string text;
  try {
    text = py::module_::import("json").attr("dumps")(obj, py::arg("allow_nan") = false).cast<std::string>();
  } catch (const py::error_already_set& e) {
    throw py::value_error(name + " must be JSON-serialisable with finite numbers: " +
                          std::string(e.what()));
  }
  return nlohmann::json::parse(text);
}

Calibration MakeCalibration(const std::vector<std::shared_ptr<Correction>>& corrections,
                            const py::handle& volume_min, const py::handle& volume_max,
                            const std::string& extrapolation, double fade_distance,
                            const std::string& description, const py::object& fit_statistics,
                            const py::object& provenance) {
  Calibration cal;
  cal.description = description;
  for (const auto& c : corrections) {
    if (!c) throw py::value_error("corrections must not contain None");
    cal.chain.Append(c->Clone());
  }
  CalibratedVolume volume;
  volume.min = AsVector3(volume_min, "volume_min");
  volume.max = AsVector3(volume_max, "volume_max");
  volume.extrapolation = ExtrapolationPolicyFromName(extrapolation);
  volume.fade_distance = fade_distance;
  cal.chain.SetVolume(volume);
  if (!fit_statistics.is_none()) {
    cal.fit_statistics = PythonToJson(fit_statistics, "fit_statistics");
    if (!cal.fit_statistics.is_object()) throw py::value_error("fit_statistics must be a dict");
  }
  if (provenance.is_none()) {
    cal.provenance.tool = "trackcal-python";
    cal.provenance.tool_version = TRACKCAL_VERSION;
    cal.provenance.created_utc = CurrentUtcTimestamp();
  } else {
    cal.provenance = ParseProvenanceJson(PythonToJson(provenance, "provenance"), "provenance", "$");
  }
  cal.Check();
  return cal;
}

// "PolynomialCorrection(degree=4, input_offset=[0, 0, 0.3], input_scale=[0.5, 0.5, 0.5])",
// "TrilinearLutCorrection(5 x 6 x 4 nodes, x 0.1..0.9 m, y ..., z ...)",
// "Correction(type='physical')".
std::string CorrectionRepr(const Correction& c) {
  std::ostringstream s;
  s.precision(6);
  const auto vec = [&s](const Eigen::Vector3d& v) {
    s << "[" << v.x() << ", " << v.y() << ", " << v.z() << "]";
  };
  if (const auto* p = dynamic_cast<const PolynomialCorrection*>(&c)) {
    s << "PolynomialCorrection(degree=" << p->degree() << ", input_offset=";
    vec(p->input_offset());
    s << ", input_scale=";
    vec(p->input_scale());
    s << ")";
  } else if (const auto* l = dynamic_cast<const TrilinearLutCorrection*>(&c)) {
    const LutGrid& g = l->grid();
    s << "TrilinearLutCorrection(" << g.size(0) << " x " << g.size(1) << " x " << g.size(2)
      << " nodes";
    for (int k = 0; k < 3; ++k) {
      s << ", "
        << "xyz"[k] << " " << g.axis(k).front() << ".." << g.axis(k).back() << " m";
    }
    s << ")";
  } else {
    s << "Correction(type='" << c.TypeName() << "')";
  }
  return s.str();
}

// A term pickles through its entry of the file's corrections array, read back by the registry
// as a calibration file's terms are: "cannot pickle 'trackcal._core.PolynomialCorrection'
// object" while the Calibration holding it pickled.
template <typename T>
std::shared_ptr<T> CorrectionFromPickle(const std::string& text) {
  std::shared_ptr<Correction> c =
      CorrectionRegistry::Global().Parse(nlohmann::json::parse(text), "<pickle>", "$");
  std::shared_ptr<T> out = std::dynamic_pointer_cast<T>(c);
  if (!out) throw py::value_error("<pickle>: the term is a '" + c->TypeName() + "'");
  return out;
}

std::string CorrectionToPickle(const Correction& c) { return c.ToJson().dump(); }

}  // namespace

std::filesystem::path PathArgument(const py::handle& obj, const std::string& name) {
  const bool path_like = py::isinstance<py::str>(obj) || py::isinstance<py::bytes>(obj) ||
                         py::isinstance(obj, py::module_::import("os").attr("PathLike"));
  if (!path_like) {
    throw py::type_error(name + " must be a path (str or os.PathLike such as pathlib.Path), got " +
                         std::string(py::str(py::type::of(obj).attr("__name__"))));
  }
  const py::object fspath = py::module_::import("os").attr("fspath")(obj);
  if (py::isinstance<py::bytes>(fspath)) {
    throw py::type_error(name + " must be a str or os.PathLike path, got bytes " +
                         py::repr(fspath).cast<std::string>() + ": decode it with os.fsdecode()");
  }
  return fspath.cast<std::filesystem::path>();
}

void CheckRealNumbers(const py::handle& obj, const std::string& name) {
  const py::array raw = py::array::ensure(obj);  // no cast: the dtype numpy gives the values
  if (!raw) {
    PyErr_Clear();  // not an array at all: the float64 conversion names it
    return;
  }
  const char kind = raw.dtype().kind();
  if (kind == 'c' || kind == 'M' || kind == 'm' || kind == 'V') {
    throw py::type_error(name + " must hold real numbers, got an array of dtype " +
                         py::str(raw.dtype()).cast<std::string>());
  }
}

void BindCore(py::module_& m) {
  m.def(
      "angular_distance",
      [](const py::handle& a_obj, const py::handle& b_obj) {
        // A zero quaternion is no rotation: Eigen's normalized() leaves it zero and the angle came
        // out 0 (a zero quaternion "equal" to every rotation); a wrong length was a TypeError.
        const auto rotation = [](const py::handle& obj, const std::string& name) {
          const DoubleArray a = AsArray(obj, name, {4}, " (x, y, z, w)");
          Eigen::Quaterniond q = QuaternionFromXyzwArray(a.data());
          const double largest = q.coeffs().cwiseAbs().maxCoeff();
          if (!q.coeffs().allFinite() || largest == 0.0) {
            throw py::value_error(name + " must be a finite, non-zero quaternion (x, y, z, w)");
          }
          // Scaled before normalising: the norm of (0, 0, 0, 1e300) overflowed to inf and
          // normalized() made it zero, 0 rad from every rotation; (0, 0, 0, 1e-300) underflowed to
          // a norm of 0 and was refused as zero.
          q.coeffs() /= largest;
          return q.normalized();
        };
        return AngularDistance(rotation(a_obj, "a_xyzw"), rotation(b_obj, "b_xyzw"));
      },
      py::arg("a_xyzw"), py::arg("b_xyzw"),
      "Angle in radians between two rotations given as x, y, z, w quaternions; q and -q are equal. "
      "ValueError for a zero or non-finite quaternion.");

  m.def(
      "num_polynomial_terms",
      [](int degree) {
        CheckPolynomialDegree(degree);  // -5 gave -4 terms; the other polynomial calls refuse it
        return NumPolynomialTerms(degree);
      },
      py::arg("degree"),
      "Number of terms (r+1)(r+2)(r+3)/6 of a complete degree-r polynomial in x, y, z; ValueError "
      "for a degree outside [0, 12].");
  m.def(
      "polynomial_term_exponents",
      [](int degree) {
        const auto terms = PolynomialTermExponents(degree);
        py::array_t<int> out({static_cast<py::ssize_t>(terms.size()), py::ssize_t{3}});
        auto r = out.mutable_unchecked<2>();
        for (size_t j = 0; j < terms.size(); ++j) {
          for (int k = 0; k < 3; ++k) r(j, k) = terms[j][k];
        }
        return out;
      },
      py::arg("degree"),
      "(R, 3) powers of x, y, z of every term in the canonical order (graded by total degree, then "
      "descending power of x, then of y).");
  m.def(
      "sha256_file",
      [](const py::handle& path) { return Sha256HexOfFile(PathArgument(path, "path")); },
      py::arg("path"), "Lower-case hex SHA-256 of a file (for provenance inputs).");
  m.def(
      "check_calibration_output",
      [](const py::handle& path) { CheckCalibrationOutput(PathArgument(path, "path")); },
      py::arg("path"),
      "Raises ValueError unless a calibration file can be written at path: its folder exists "
      "and an existing file there is a trackcal calibration (checked before a long fit).");

  // pybind11 copies docstrings; these outlive the definitions anyway.
  const std::string term_correct_doc =
      std::string(
          "Applies this term alone (no calibrated volume): (positions, quaternions, "
          "extrapolated).") +
      kStatusDoc;
  const std::string calibration_correct_doc =
      std::string(
          "Corrects N reported poses: positions (N, 3) [m] and quaternions (N, 4) ordered "
          "x, y, z, w. Returns (positions (N, 3), quaternions (N, 4), extrapolated (N,) "
          "bool).") +
      kStatusDoc;
  m.attr("correction_status_names") =
      py::make_tuple(CorrectionStatusName(CorrectionStatus::kConverged),
                     CorrectionStatusName(CorrectionStatus::kAmbiguous),
                     CorrectionStatusName(CorrectionStatus::kNotConverged));
  py::class_<Correction, std::shared_ptr<Correction>>(
      m, "Correction",
      "One correction term (polynomial, LUT, ...): reported pose -> corrected pose.")
      .def_property_readonly("type", &Correction::TypeName, "The term's \"type\" in the file.")
      .def(
          "to_json", [](const Correction& c) { return c.ToJson().dump(2); },
          "The term's entry of the file's corrections array, as JSON text.")
      .def(
          "correct",
          [](const Correction& c, const py::handle& positions, const py::handle& quaternions,
             bool return_status) {
            return CorrectBatch(
                positions, quaternions, return_status,
                [&c](size_t n, const double* p, const double* q, double* po, double* qo, uint8_t* f,
                     CorrectionStatus* st) { c.ApplyBatchWithStatus(n, p, q, po, qo, f, st); });
          },
          py::arg("positions"), py::arg("quaternions_xyzw"), py::arg("return_status") = false,
          term_correct_doc.c_str())
      // The default repr named only the address ("<trackcal._core.PolynomialCorrection object at
      // 0x7f...>"), in cal.corrections of a notebook.
      .def("__repr__", [](const Correction& c) { return CorrectionRepr(c); })
      .def(py::pickle(&CorrectionToPickle, &CorrectionFromPickle<Correction>));

  py::class_<PolynomialCorrection, Correction, std::shared_ptr<PolynomialCorrection>>(
      m, "PolynomialCorrection",
      "Complete degree-r vector polynomial of the normalised reported position u = (p - "
      "input_offset) / input_scale (Ikits et al. 2001, eq. 7), for the position error [m] and the "
      "vector part of the world-frame error quaternion q_e = q_ref * conj(q_reported).")
      .def(py::init([](int degree, const py::handle& position_coefficients,
                       const py::handle& orientation_coefficients, const py::handle& input_offset,
                       const py::handle& input_scale) {
             CheckPolynomialDegree(degree);
             const py::ssize_t r = NumPolynomialTerms(degree);
             const std::string note = " for degree " + std::to_string(degree);
             const DoubleArray pc = AsArray(position_coefficients, "position_coefficients", {r, 3}, note);
             const DoubleArray oc =
                 AsArray(orientation_coefficients, "orientation_coefficients", {r, 3}, note);
             return std::shared_ptr<PolynomialCorrection>(
                 PolynomialCorrection::FromPositionAndOrientation(
                     degree, AsVector3(input_offset, "input_offset"),
                     AsVector3(input_scale, "input_scale"), Flatten(pc), Flatten(oc)));
           }),
           py::arg("degree"), py::arg("position_coefficients"), py::arg("orientation_coefficients"),
           py::arg("input_offset") = py::make_tuple(0.0, 0.0, 0.0),
           py::arg("input_scale") = py::make_tuple(1.0, 1.0, 1.0),
           "Coefficients are (R, 3) arrays in the canonical term order "
           "(polynomial_term_exponents).")
      .def(py::pickle(&CorrectionToPickle, &CorrectionFromPickle<PolynomialCorrection>))
      .def_property_readonly("degree", &PolynomialCorrection::degree)
      .def_property_readonly(
          "input_offset", [](const PolynomialCorrection& p) { return ToArray(p.input_offset()); })
      .def_property_readonly("input_scale",
                             [](const PolynomialCorrection& p) { return ToArray(p.input_scale()); })
      .def_property_readonly("position_coefficients",
                             [](const PolynomialCorrection& p) {
                               return ToArray(Columns(p.coefficients(), 0), {p.num_terms(), 3});
                             })
      .def_property_readonly("orientation_coefficients", [](const PolynomialCorrection& p) {
        return ToArray(Columns(p.coefficients(), 3), {p.num_terms(), 3});
      });

  py::class_<TrilinearLutCorrection, Correction, std::shared_ptr<TrilinearLutCorrection>>(
      m, "TrilinearLutCorrection",
      "Trilinear lookup table over a grid of reported positions holding the position error [m] "
      "and the vector part of q_e at each node.")
      .def(py::init([](const py::handle& x, const py::handle& y, const py::handle& z,
                       const py::handle& position_error, const py::handle& orientation_error) {
             std::array<std::vector<double>, 3> axes = {
                 Flatten(AsArray(x, "x", {-1})), Flatten(AsArray(y, "y", {-1})),
                 Flatten(AsArray(z, "z", {-1}))};
             const std::vector<py::ssize_t> shape = {static_cast<py::ssize_t>(axes[0].size()),
                                                     static_cast<py::ssize_t>(axes[1].size()),
                                                     static_cast<py::ssize_t>(axes[2].size()), 3};
             const std::string note = " = (len(x), len(y), len(z), 3)";
             const DoubleArray pe = AsArray(position_error, "position_error", shape, note);
             const DoubleArray oe = AsArray(orientation_error, "orientation_error", shape, note);
             return std::shared_ptr<TrilinearLutCorrection>(
                 TrilinearLutCorrection::FromPositionAndOrientation(LutGrid(std::move(axes)),
                                                                    Flatten(pe), Flatten(oe)));
           }),
           py::arg("x"), py::arg("y"), py::arg("z"), py::arg("position_error"),
           py::arg("orientation_error"),
           "Axes: strictly increasing node coordinates [m]; errors: (nx, ny, nz, 3) arrays.")
      .def(py::pickle(&CorrectionToPickle, &CorrectionFromPickle<TrilinearLutCorrection>))
      .def_property_readonly("axes",
                             [](const TrilinearLutCorrection& l) {
                               py::list axes;
                               for (int k = 0; k < 3; ++k) {
                                 axes.append(ToArray(l.grid().axis(k), {l.grid().size(k)}));
                               }
                               return py::tuple(axes);
                             })
      .def_property_readonly("position_error",
                             [](const TrilinearLutCorrection& l) {
                               const LutGrid& g = l.grid();
                               return ToArray(Columns(l.node_values(), 0),
                                              {g.size(0), g.size(1), g.size(2), 3});
                             })
      .def_property_readonly("orientation_error", [](const TrilinearLutCorrection& l) {
        const LutGrid& g = l.grid();
        return ToArray(Columns(l.node_values(), 3), {g.size(0), g.size(1), g.size(2), 3});
      });

  py::class_<Calibration>(
      m, "Calibration",
      "A calibration: a chain of corrections guarded by the calibrated volume, with fit statistics "
      "and provenance (docs/calibration-file.md).")
      .def(py::init(&MakeCalibration), py::arg("corrections"), py::arg("volume_min"),
           py::arg("volume_max"), py::arg("extrapolation") = "clamp",
           py::arg("fade_distance") = 0.0, py::arg("description") = "",
           py::arg("fit_statistics") = py::none(), py::arg("provenance") = py::none(),
           "Builds a calibration from correction terms (applied in order) and the box of reported "
           "positions they are valid in; extrapolation is 'clamp' or 'fade'.")
      .def_static(
          "load",
          [](const py::handle& path) { return ReadCalibrationFile(PathArgument(path, "path")); },
          py::arg("path"), "Reads a calibration file; errors name the file and the JSON path.")
      .def_static("from_json", &ParseCalibrationJson, py::arg("text"),
                  py::arg("source_name") = "<string>",
                  "Parses a calibration file's text; errors (ValueError) name source_name and the "
                  "JSON path.")
      .def(
          "save",
          [](const Calibration& c, const py::handle& path) {
            WriteCalibrationFile(PathArgument(path, "path"), c);
          },
          py::arg("path"),
          "Writes atomically; refuses to overwrite an input listed in the provenance or an "
          "existing file that is not a trackcal calibration (ValueError).")
      .def("to_json", &CalibrationToJsonText, "The calibration file's text (JSON).")
      // Through its file text (which reads back to the same file, core/calibration_file_test.cc):
      // a validation script's process pool, copy.deepcopy.
      .def(py::pickle(
          [](const Calibration& c) { return CalibrationToJsonText(c); },
          [](const std::string& text) { return ParseCalibrationJson(text, "<pickle>"); }))
      .def(
          "correct",
          [](const Calibration& c, const py::handle& positions, const py::handle& quaternions,
             bool return_status) {
            return CorrectBatch(positions, quaternions, return_status,
                                [&c](size_t n, const double* p, const double* q, double* po,
                                     double* qo, uint8_t* f, CorrectionStatus* st) {
                                  c.chain.ApplyBatchWithStatus(n, p, q, po, qo, f, st);
                                });
          },
          py::arg("positions"), py::arg("quaternions_xyzw"), py::arg("return_status") = false,
          calibration_correct_doc.c_str())
      .def_property_readonly("corrections",
                             [](const Calibration& c) {
                               std::vector<std::shared_ptr<Correction>> out;
                               for (size_t i = 0; i < c.chain.size(); ++i) {
                                 out.emplace_back(c.chain.term(i).Clone());
                               }
                               return out;
                             })
      .def_property_readonly("volume_min",
                             [](const Calibration& c) { return ToArray(c.volume().min); })
      .def_property_readonly("volume_max",
                             [](const Calibration& c) { return ToArray(c.volume().max); })
      .def_property_readonly(
          "extrapolation",
          [](const Calibration& c) { return ExtrapolationPolicyName(c.volume().extrapolation); })
      .def_property_readonly("fade_distance",
                             [](const Calibration& c) { return c.volume().fade_distance; })
      .def_readwrite("description", &Calibration::description)
      // Checked on assignment, as Calibration::Check() checks it: cal.sensor = -3 was accepted and
      // refused only by a later save() ("calibration: sensor must be ..."), far from the mistake.
      .def_property(
          "sensor", [](const Calibration& c) { return c.sensor; },
          [](Calibration& c, const py::handle& value) {
            const std::string range =
                "0 (not recorded) or 1.." + std::to_string(kMaxCalibrationSensor);
            // Any integer (a numpy one too, capture.sensor[0]); not a bool, not a float.
            PyObject* index =
                py::isinstance<py::bool_>(value) ? nullptr : PyNumber_Index(value.ptr());
            if (index == nullptr) {
              PyErr_Clear();
              throw py::type_error("Calibration.sensor must be an integer, " + range + ", got " +
                                   py::repr(value).cast<std::string>());
            }
            const py::int_ as_int = py::reinterpret_steal<py::int_>(index);
            int overflow = 0;  // beyond long long: out of range like -3
            const long long sensor = PyLong_AsLongLongAndOverflow(as_int.ptr(), &overflow);
            if (overflow != 0 || sensor < 0 || sensor > kMaxCalibrationSensor) {
              throw py::value_error("Calibration.sensor must be " + range +
                                    " (the capture's sensor column), got " +
                                    py::repr(value).cast<std::string>());
            }
            c.sensor = static_cast<int>(sensor);
          },
          "The receiver the calibration was fitted for: the capture's 1-based sensor "
          "column (Fastrak station n; VRPN sensor n - 1); 0 when not recorded. Assigning "
          "anything else raises ValueError (TypeError for a value that is not an integer).")
      .def_property_readonly("fit_statistics",
                             [](const Calibration& c) { return JsonToPython(c.fit_statistics); })
      .def_property_readonly(
          "provenance",
          [](const Calibration& c) { return JsonToPython(CalibrationToJson(c).at("provenance")); })
      .def("__repr__", [](const Calibration& c) {
        std::string terms;
        for (size_t i = 0; i < c.chain.size(); ++i) {
          if (i) terms += ", ";
          terms += c.chain.term(i).TypeName();
        }
        return "Calibration(corrections=[" + terms + "], extrapolation='" +
               ExtrapolationPolicyName(c.volume().extrapolation) + "'" +
               (c.sensor != 0 ? ", sensor=" + std::to_string(c.sensor) : std::string()) + ")";
      });
}

}  // namespace trackcal::python
