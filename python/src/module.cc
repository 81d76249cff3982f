#include <pybind11/pybind11.h>

#include "python/src/bindings.h"

PYBIND11_MODULE(_core, m) {
  m.doc() = "trackcal native core: pose math, runtime corrections, captures and the fitting engine";
  m.attr("__version__") = TRACKCAL_VERSION;
  trackcal::python::BindCore(m);
  trackcal::python::BindCapture(m);
  trackcal::python::BindFit(m);
  trackcal::python::BindVrpn(m);
}
