// The magnetic field model of an AC electromagnetic tracker (Polhemus Fastrak and relatives).
//
// The transmitter is three orthogonal coils at the origin of the transmitter frame, coil j driven
// along axis e_j. A field matrix B(p) (3 x 3) holds in column j the field of coil j at the point p
// (transmitter frame). In free space each coil is a magnetic dipole:
//
//   B_free(p) = k D(p),   D(d) = (3 u u^T - I) / |d|^3,  u = d / |d|,
//
// with k the field constant (field units times m^3; the simulator uses k = 1, so fields are in
// units of "field of a coil at 1 m on its equator"). Distortion adds, to first order (sources do
// not see each other's fields):
//
// - ConductingPlane (floor reinforcement, a metal door, a wall): the eddy currents of a perfectly
//   conducting plane make the normal field vanish on it, which is the field of an image dipole at
//   the transmitter's mirror point with moment M m, M = I - 2 n n^T. A real plane is imperfect and
//   finite: its image is scaled by `attenuation`; a negative attenuation gives the image of a
//   high-permeability (ferromagnetic) plane, whose tangential field vanishes instead (moment -M m).
// - InducedDipole (a monitor, a steel cabinet, a tool): a small object in the transmitter field B_c
//   becomes a dipole of moment `polarisability` * B_c. Polarisability is in m^3: a^3 for a
//   ferromagnetic sphere of radius a, -a^3/2 for a perfectly conducting one.
// - Finite transmitter coils: a coil of finite size adds the next multipole of its axially
// symmetric
//   field. Its scalar potential is k [ (e.x) / r^3 + c P3(e.u) / r^4 ]; c = `octupole_m2` per coil,
//   c = -3/4 a^2 for a circular loop of radius a. The error it causes falls as 1/r^2 relative to
//   the dipole, so it matters only near the source.
//
// The receiver is three orthogonal coils with orientation R (= transmitter_from_receiver rotation);
// it measures the signal matrix S = G R^T B(p): row i is receiver coil i, column j transmitter coil
// j. G holds the receiver coil gains and non-orthogonality (identity for an ideal receiver).
//
// Every function is templated on the scalar type so fit/ can differentiate it with Ceres autodiff
// (ceres::Jet) and core/ can invert it per pose; none allocates and none branches on values. A
// receiver at a source point (|d| = 0) is outside the model's domain.

#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <string>
#include <vector>

#include "core/pose.h"

namespace trackcal {

template <typename T>
using Matrix3 = Eigen::Matrix<T, 3, 3>;

// Unit dipole coupling D(d) = (3 u u^T - I) / |d|^3: column j is the field at offset d of a unit
// dipole along e_j (times mu0/4pi).
template <typename T>
Matrix3<T> DipoleCoupling(const Vector3<T>& d) {
  using std::sqrt;
  const T r2 = d.squaredNorm();
  const T r = sqrt(r2);
  const T inv_r3 = T(1) / (r2 * r);
  const T inv_r5 = inv_r3 / r2;
  Matrix3<T> m = (T(3) * inv_r5) * (d * d.transpose());
  m.diagonal().array() -= inv_r3;
  return m;
}

// Free-space field matrix of the transmitter, including the finite-coil (octupole) term of each
// coil. `octupole_m2(j)` is the octupole coefficient c_j of coil j [m^2]; zero gives the ideal
// dipoles.
template <typename T>
Matrix3<T> TransmitterField(const T& field_constant, const Vector3<T>& octupole_m2,
                            const Vector3<T>& p_in_transmitter) {
  using std::sqrt;
  Matrix3<T> b = DipoleCoupling<T>(p_in_transmitter);
  const T r2 = p_in_transmitter.squaredNorm();
  const T r = sqrt(r2);
  const Vector3<T> u = p_in_transmitter / r;
  const T inv_r5 = T(1) / (r2 * r2 * r);
  for (int j = 0; j < 3; ++j) {
    // B = -grad(c P3(cos) / r^4) = -c / r^5 [P3'(cos) (e - cos u) - 4 P3(cos) u], cos = e.u.
    const T c = u(j);
    const T p3 = T(0.5) * (T(5) * c * c * c - T(3) * c);
    const T dp3 = T(0.5) * (T(15) * c * c - T(3));
    Vector3<T> grad = (-dp3 * c - T(4) * p3) * u;
    grad(j) += dp3;
    b.col(j) -= (octupole_m2(j) * inv_r5) * grad;
  }
  return field_constant * b;
}

// Field matrix of the image of the transmitter in a conducting plane through `plane_point` with
// normal `plane_normal` (normalised here; either sign), scaled by `attenuation` (see file comment).
template <typename T>
Matrix3<T> PlaneImageField(const T& field_constant, const Vector3<T>& plane_point_in_transmitter,
                           const Vector3<T>& plane_normal_in_transmitter, const T& attenuation,
                           const Vector3<T>& p_in_transmitter) {
  const Vector3<T> n = plane_normal_in_transmitter.normalized();
  // Mirror of the transmitter (at the origin) through the plane.
  const Vector3<T> image_in_transmitter = (T(2) * plane_point_in_transmitter.dot(n)) * n;
  Matrix3<T> image_moments = -(T(2) * attenuation) * (n * n.transpose());
  image_moments.diagonal().array() += attenuation;
  return field_constant * DipoleCoupling<T>(p_in_transmitter - image_in_transmitter) *
         image_moments;
}

// Field matrix of the dipole induced in a small object at `location` with scalar polarisability
// [m^3] by the transmitter's free-space dipole field.
template <typename T>
Matrix3<T> InducedDipoleField(const T& field_constant, const Vector3<T>& location_in_transmitter,
                              const T& polarisability_m3, const Vector3<T>& p_in_transmitter) {
  return (field_constant * polarisability_m3) *
         (DipoleCoupling<T>(p_in_transmitter - location_in_transmitter) *
          DipoleCoupling<T>(location_in_transmitter));
}

// Background field: the field of sources too far, too many or too large to locate one by one (CRT
// monitors across the room, a door, the building's steel), which over the tracked volume is smooth.
// Between sources the field of each transmitter coil is curl- and divergence-free, the gradient of
// a harmonic potential; column j of the background is therefore expanded as
//
//   B_bg(p)_j = sum_k c_jk grad h_k(p / 1 m),
//
// over the regular solid harmonics h_k of degrees 1 .. L + 1 (a field of polynomial degree L):
// 3 + 5 + 7 = 15 per coil for L = 2, 8 for L = 1, 3 (a uniform field) for L = 0. The harmonic
// polynomials of bounded degree are closed under translation, so the expansion about the
// transmitter spans the same fields as one about the data's centre. Coefficients are in units of
// the field constant k (k m^-3, the field of distant sources the transmitter drives):
// FieldModel::Field multiplies them by k like every other source, so k cancels between S and the
// tracker's free-space signal. Coefficient c_jk is element j * BackgroundBasisSize(L) + k.
constexpr int kMaxBackgroundDegree = 2;
constexpr int BackgroundBasisSize(int degree) { return (degree + 1) * (degree + 3); }

// The basis fields grad h_k at p (column k), k < BackgroundBasisSize(degree), for 0 <= degree <= 2.
template <typename T>
Eigen::Matrix<T, 3, BackgroundBasisSize(kMaxBackgroundDegree)> BackgroundBasis(
    int degree, const Vector3<T>& p) {
  Eigen::Matrix<T, 3, BackgroundBasisSize(kMaxBackgroundDegree)> g;
  g.setZero();
  const T& x = p(0);
  const T& y = p(1);
  const T& z = p(2);
  const T zero(0), one(1);
  // Degree 1: x, y, z (a uniform field).
  g.col(0) << one, zero, zero;
  g.col(1) << zero, one, zero;
  g.col(2) << zero, zero, one;
  if (degree < 1) return g;
  // Degree 2: xy, yz, zx, x^2 - y^2, 2z^2 - x^2 - y^2 (a uniform gradient).
  g.col(3) << y, x, zero;
  g.col(4) << zero, z, y;
  g.col(5) << z, zero, x;
  g.col(6) << T(2) * x, T(-2) * y, zero;
  g.col(7) << T(-2) * x, T(-2) * y, T(4) * z;
  if (degree < 2) return g;
  // Degree 3: x^3 - 3xy^2, 3x^2y - y^3, xyz, z(x^2 - y^2), x(4z^2 - x^2 - y^2),
  // y(4z^2 - x^2 - y^2), z(2z^2 - 3x^2 - 3y^2).
  const T xx = x * x, yy = y * y, zz = z * z;
  g.col(8) << T(3) * (xx - yy), T(-6) * x * y, zero;
  g.col(9) << T(6) * x * y, T(3) * (xx - yy), zero;
  g.col(10) << y * z, x * z, x * y;
  g.col(11) << T(2) * x * z, T(-2) * y * z, xx - yy;
  g.col(12) << T(4) * zz - T(3) * xx - yy, T(-2) * x * y, T(8) * x * z;
  g.col(13) << T(-2) * x * y, T(4) * zz - xx - T(3) * yy, T(8) * y * z;
  g.col(14) << T(-6) * x * z, T(-6) * y * z, T(6) * zz - T(3) * (xx + yy);
  return g;
}

// The background field matrix at p: coefficients of type T, BackgroundBasisSize(degree) per coil.
template <typename T, typename C>
Matrix3<T> BackgroundFieldMatrix(int degree, const C* coefficients, const Vector3<T>& p) {
  const auto basis = BackgroundBasis<T>(degree, p);
  const int n = BackgroundBasisSize(degree);
  Matrix3<T> b = Matrix3<T>::Zero();
  for (int j = 0; j < 3; ++j) {
    for (int k = 0; k < n; ++k) b.col(j) += basis.col(k) * T(coefficients[j * n + k]);
  }
  return b;
}

// Signal matrix S = G R^T B measured by a receiver with orientation `transmitter_from_receiver`.
template <typename T>
Matrix3<T> SignalMatrix(const Matrix3<T>& receiver_gain_matrix,
                        const Matrix3<T>& transmitter_from_receiver_rotation,
                        const Matrix3<T>& field) {
  return receiver_gain_matrix * (transmitter_from_receiver_rotation.transpose() * field);
}

// A conducting (or, with negative attenuation, ferromagnetic) plane.
struct ConductingPlane {
  std::string name;                                                  // label in scenes and reports
  Eigen::Vector3d point_in_transmitter = Eigen::Vector3d::Zero();    // any point of the plane [m]
  Eigen::Vector3d normal_in_transmitter = Eigen::Vector3d::UnitZ();  // plane normal (any sign)
  double attenuation = 0.0;  // image strength: 1 perfect conductor, < 0 ferromagnetic, 0 none
};

// The smooth field of distant sources (BackgroundBasis above); degree < 0: none.
struct BackgroundField {
  int degree = -1;                  // polynomial degree of the field, 0 .. kMaxBackgroundDegree
  std::vector<double> coefficients;  // 3 * BackgroundBasisSize(degree) [k m^-3]
  bool present() const { return degree >= 0; }
};

// A small object polarised by the transmitter field.
struct InducedDipole {
  std::string name;                                                   // label
  Eigen::Vector3d location_in_transmitter = Eigen::Vector3d::Zero();  // object centre [m]
  double polarisability_m3 = 0.0;  // > 0 ferromagnetic, < 0 conducting (eddy currents) [m^3]
};

// Everything that shapes the field the receiver sits in: transmitter and distortion sources.
struct FieldModel {
  double field_constant = 1.0;                                        // k [field units m^3]
  Eigen::Vector3d transmitter_octupole_m2 = Eigen::Vector3d::Zero();  // finite-coil term per coil
  std::vector<ConductingPlane> planes;                                // image dipoles
  std::vector<InducedDipole> objects;                                 // induced dipoles
  BackgroundField background;                                         // distant sources

  // Throws std::invalid_argument naming the offending field.
  void Check() const;

  // True field matrix B(p) (columns: transmitter coils) at a point; T may be a ceres::Jet so the
  // pose can be differentiated (the model's parameters stay double here).
  template <typename T>
  Matrix3<T> Field(const Vector3<T>& p_in_transmitter) const {
    const T k(field_constant);
    Matrix3<T> b = TransmitterField<T>(k, transmitter_octupole_m2.cast<T>(), p_in_transmitter);
    for (const ConductingPlane& plane : planes) {
      b += PlaneImageField<T>(k, plane.point_in_transmitter.cast<T>(),
                              plane.normal_in_transmitter.cast<T>(), T(plane.attenuation),
                              p_in_transmitter);
    }
    for (const InducedDipole& object : objects) {
      b += InducedDipoleField<T>(k, object.location_in_transmitter.cast<T>(),
                                 T(object.polarisability_m3), p_in_transmitter);
    }
    if (background.present()) {
      // Driven by the transmitter like every other source: the coefficients are in units of k.
      b += k * BackgroundFieldMatrix<T>(background.degree, background.coefficients.data(),
                                        p_in_transmitter);
    }
    return b;
  }

  // The free-space field the tracker's own solver assumes (ideal dipoles, same k).
  template <typename T>
  Matrix3<T> FreeSpaceField(const Vector3<T>& p_in_transmitter) const {
    return T(field_constant) * DipoleCoupling<T>(p_in_transmitter);
  }
};

}  // namespace trackcal
