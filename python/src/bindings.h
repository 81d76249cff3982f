// One Bind<Module>() per C++ folder; module.cc calls them in layer order.
#pragma once

#include <pybind11/pybind11.h>

#include <filesystem>
#include <string>

#include "core/capture.h"

namespace trackcal::python {

void BindCore(pybind11::module_& m);
void BindCapture(pybind11::module_& m);
void BindFit(pybind11::module_& m);
void BindVrpn(pybind11::module_& m);

// TypeError naming `name` unless `obj` (an array or what numpy makes one of) holds real numbers:
// forcecast to float64 dropped a complex array's imaginary parts (a ComplexWarning at most) and
// turned datetime64 / timedelta64 values into counts of their unit, silently.
void CheckRealNumbers(const pybind11::handle& obj, const std::string& name);

// A path argument of the API, a str or an os.PathLike (pathlib.Path), as a std::filesystem::path
// through pybind11's caster (the file system encoding: a file name that is not UTF-8, a str with
// surrogates from os.listdir, names that file). bytes, or a PathLike giving bytes, is a TypeError
// naming `name`, as pathlib and the Python modules refuse it (Calibration.load took bytes and
// fit() did not; register() and pair() read b'/x/m.csv' as the file "b'/x/m.csv'").
std::filesystem::path PathArgument(const pybind11::handle& obj, const std::string& name);

// A poses.csv capture as the dict of arrays trackcal.captures.PoseCapture is built from (station,
// set, sensor, time, reported_/reference_positions, ..._quaternions_xyzw, extra_columns, extra).
pybind11::dict PoseCaptureToDict(const PoseCapture& capture);

}  // namespace trackcal::python
