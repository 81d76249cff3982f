// One Bind<Module>() per C++ folder; module.cc calls them in layer order.
#pragma once

#include <pybind11/pybind11.h>

namespace trackcal::python {

void BindCore(pybind11::module_& m);
void BindCapture(pybind11::module_& m);
void BindVrpn(pybind11::module_& m);

}  // namespace trackcal::python
