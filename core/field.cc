#include "core/field.h"

#include <cmath>
#include <stdexcept>

namespace trackcal {

namespace {
void Require(bool ok, const std::string& field, const std::string& what) {
  if (!ok) throw std::invalid_argument("field model: " + field + ": " + what);
}
bool Finite(const Eigen::Vector3d& v) { return v.allFinite(); }
}  // namespace

void FieldModel::Check() const {
  Require(std::isfinite(field_constant) && field_constant > 0, "field_constant",
          "must be a positive number");
  Require(Finite(transmitter_octupole_m2), "transmitter.octupole_m2", "must be finite");
  for (size_t i = 0; i < planes.size(); ++i) {
    const std::string f = "planes[" + std::to_string(i) + "]";
    const ConductingPlane& p = planes[i];
    Require(Finite(p.point_in_transmitter), f + ".point_in_transmitter", "must be finite");
    Require(Finite(p.normal_in_transmitter) && p.normal_in_transmitter.norm() > 1e-9,
            f + ".normal_in_transmitter", "must be a non-zero vector");
    Require(std::isfinite(p.attenuation) && std::abs(p.attenuation) <= 1.0, f + ".attenuation",
            "must be in [-1, 1]");
    // The transmitter must not sit on the plane: its image would coincide with it.
    Require(std::abs(p.point_in_transmitter.dot(p.normal_in_transmitter.normalized())) > 1e-3,
            f + ".point_in_transmitter", "plane passes through the transmitter");
  }
  for (size_t i = 0; i < objects.size(); ++i) {
    const std::string f = "objects[" + std::to_string(i) + "]";
    const InducedDipole& o = objects[i];
    Require(Finite(o.location_in_transmitter) && o.location_in_transmitter.norm() > 1e-3,
            f + ".location_in_transmitter", "must be finite and away from the transmitter");
    Require(std::isfinite(o.polarisability_m3), f + ".polarisability_m3", "must be finite");
  }
  if (background.present()) {
    Require(background.degree <= kMaxBackgroundDegree, "background.degree",
            "must be 0 .. " + std::to_string(kMaxBackgroundDegree));
    const size_t n = 3 * static_cast<size_t>(BackgroundBasisSize(background.degree));
    Require(background.coefficients.size() == n, "background.coefficients",
            "expected " + std::to_string(n) + " numbers for degree " +
                std::to_string(background.degree));
    for (double c : background.coefficients) {
      Require(std::isfinite(c), "background.coefficients", "must be finite");
    }
  }
}

}  // namespace trackcal
