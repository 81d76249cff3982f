#include <pybind11/eigen.h>
#include <pybind11/stl.h>

#include "core/pose.h"
#include "python/src/bindings.h"

namespace py = pybind11;

namespace trackcal::python {

void BindCore(py::module_& m) {
  m.def(
      "angular_distance",
      [](const Eigen::Vector4d& a_xyzw, const Eigen::Vector4d& b_xyzw) {
        return AngularDistance(QuaternionFromXyzwArray(a_xyzw.data()).normalized(),
                               QuaternionFromXyzwArray(b_xyzw.data()).normalized());
      },
      py::arg("a_xyzw"), py::arg("b_xyzw"),
      "Angle in radians between two rotations given as x, y, z, w quaternions; q and -q are equal.");
}

}  // namespace trackcal::python
