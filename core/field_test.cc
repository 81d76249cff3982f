#include "core/field.h"

#include <ceres/jet.h>
#include <gtest/gtest.h>

#include <Eigen/LU>

#include <numbers>

#include "tests/test_utils.h"

namespace trackcal {
namespace {

using testing::TestRng;

Eigen::Vector3d RandomPoint(double lo, double hi) {
  std::uniform_real_distribution<double> u(lo, hi);
  return Eigen::Vector3d(u(TestRng()), u(TestRng()), u(TestRng()));
}

// Textbook field of a point dipole m at `source`, at x (mu0/4pi = 1).
Eigen::Vector3d DipoleFieldAt(const Eigen::Vector3d& m, const Eigen::Vector3d& source,
                              const Eigen::Vector3d& x) {
  const Eigen::Vector3d d = x - source;
  const double r = d.norm();
  const Eigen::Vector3d u = d / r;
  return (3.0 * m.dot(u) * u - m) / (r * r * r);
}

TEST(DipoleCoupling, Nominal) {
  // On the axis of a unit dipole the field is 2 / r^3 along it, on its equator -1 / r^3.
  const double r = 0.7;
  const Matrix3<double> on_axis = DipoleCoupling<double>(Eigen::Vector3d(r, 0, 0));
  EXPECT_NEAR(on_axis(0, 0), 2.0 / (r * r * r), 1e-12);
  EXPECT_NEAR(on_axis(1, 1), -1.0 / (r * r * r), 1e-12);
  for (int i = 0; i < 20; ++i) {
    const Eigen::Vector3d x = RandomPoint(-2, 2);
    const Matrix3<double> d = DipoleCoupling<double>(x);
    for (int j = 0; j < 3; ++j) {
      EXPECT_TRUE(d.col(j).isApprox(
          DipoleFieldAt(Eigen::Vector3d::Unit(j), Eigen::Vector3d::Zero(), x), 1e-12));
    }
  }
}

TEST(PlaneImageField, MatchesImageDipoleClosedForm) {
  for (int trial = 0; trial < 20; ++trial) {
    const Eigen::Vector3d n = RandomPoint(-1, 1).normalized();
    const Eigen::Vector3d point = n * 0.8 + RandomPoint(-0.5, 0.5).cross(n);
    const double attenuation = std::uniform_real_distribution<double>(-1, 1)(TestRng());
    const Eigen::Vector3d x = RandomPoint(-1, 1);
    // Closed form: mirror point of the origin and moment alpha (m - 2 (m.n) n).
    const Eigen::Vector3d mirror = 2.0 * point.dot(n) * n;
    const Matrix3<double> b = PlaneImageField<double>(
        1.0, point, 3.0 * n /* not normalised on purpose */, attenuation, x);
    for (int j = 0; j < 3; ++j) {
      const Eigen::Vector3d m = Eigen::Vector3d::Unit(j);
      const Eigen::Vector3d image_moment = attenuation * (m - 2.0 * m.dot(n) * n);
      EXPECT_TRUE(b.col(j).isApprox(DipoleFieldAt(image_moment, mirror, x), 1e-12));
    }
  }
}

TEST(PlaneImageField, PerfectConductorCancelsNormalField) {
  // A perfect conductor (attenuation 1): the normal field vanishes on the plane; a perfect
  // ferromagnet (attenuation -1): the tangential field does.
  const Eigen::Vector3d n = Eigen::Vector3d(0.2, -0.3, 1.0).normalized();
  const Eigen::Vector3d point = 0.8 * n;
  const Eigen::Vector3d k_zero = Eigen::Vector3d::Zero();
  for (int trial = 0; trial < 20; ++trial) {
    const Eigen::Vector3d on_plane = point + RandomPoint(-2, 2).cross(n);
    const Matrix3<double> free = TransmitterField<double>(1.0, k_zero, on_plane);
    const Matrix3<double> conductor = free + PlaneImageField<double>(1.0, point, n, 1.0, on_plane);
    const Matrix3<double> ferro = free + PlaneImageField<double>(1.0, point, n, -1.0, on_plane);
    for (int j = 0; j < 3; ++j) {
      // Relative to the free field, rounding only.
      const double scale = free.col(j).norm();
      EXPECT_NEAR(conductor.col(j).dot(n), 0.0, 1e-12 * scale);
      EXPECT_NEAR((ferro.col(j) - ferro.col(j).dot(n) * n).norm(), 0.0, 1e-12 * scale);
    }
  }
}

TEST(InducedDipoleField, MatchesInducedMomentClosedForm) {
  for (int trial = 0; trial < 20; ++trial) {
    const Eigen::Vector3d location = RandomPoint(-2, 2);
    const Eigen::Vector3d x = RandomPoint(-2, 2);
    const double k = 1.7;
    const double chi = 0.02;
    const Matrix3<double> b = InducedDipoleField<double>(k, location, chi, x);
    for (int j = 0; j < 3; ++j) {
      const Eigen::Vector3d field_at_object =
          k * DipoleFieldAt(Eigen::Vector3d::Unit(j), Eigen::Vector3d::Zero(), location);
      EXPECT_TRUE(b.col(j).isApprox(DipoleFieldAt(chi * field_at_object, location, x), 1e-12));
    }
  }
}

// Biot-Savart field of a circular loop of radius a about axis e_j at the origin, scaled so its
// dipole moment is 1 (I pi a^2 = 1, mu0 / 4pi = 1).
Eigen::Vector3d LoopField(int axis, double a, const Eigen::Vector3d& x) {
  const Eigen::Vector3d e = Eigen::Vector3d::Unit(axis);
  const Eigen::Vector3d e1 = Eigen::Vector3d::Unit((axis + 1) % 3);
  const Eigen::Vector3d e2 = e.cross(e1);
  const int segments = 4000;
  const double current = 1.0 / (std::numbers::pi * a * a);
  Eigen::Vector3d b = Eigen::Vector3d::Zero();
  for (int s = 0; s < segments; ++s) {
    // Midpoint rule on a smooth periodic integrand: spectrally accurate.
    const double phi = 2.0 * std::numbers::pi * (s + 0.5) / segments;
    const Eigen::Vector3d y = a * (std::cos(phi) * e1 + std::sin(phi) * e2);
    const Eigen::Vector3d dl =
        (2.0 * std::numbers::pi * a / segments) * (-std::sin(phi) * e1 + std::cos(phi) * e2);
    const Eigen::Vector3d d = x - y;
    b += current * dl.cross(d) / std::pow(d.norm(), 3);
  }
  return b;
}

TEST(TransmitterField, OctupoleTermMatchesFiniteLoop) {
  const double a = 0.05;
  const Eigen::Vector3d loop_octupole = Eigen::Vector3d::Constant(-0.75 * a * a);
  for (int trial = 0; trial < 10; ++trial) {
    const Eigen::Vector3d x = RandomPoint(-1, 1).normalized() * (0.25 + 0.1 * trial);
    const Matrix3<double> dipole = TransmitterField<double>(1.0, Eigen::Vector3d::Zero(), x);
    const Matrix3<double> with_octupole = TransmitterField<double>(1.0, loop_octupole, x);
    for (int j = 0; j < 3; ++j) {
      const Eigen::Vector3d exact = LoopField(j, a, x);
      const double dipole_error = (dipole.col(j) - exact).norm();
      const double octupole_error = (with_octupole.col(j) - exact).norm();
      // The dipole misses O((a/r)^2) (>= 2e-3 relative here); the octupole leaves O((a/r)^4).
      const double r = x.norm();
      EXPECT_GT(dipole_error, 0.5 * std::pow(a / r, 2) * exact.norm());
      EXPECT_LT(octupole_error, 3.0 * std::pow(a / r, 4) * exact.norm());
    }
  }
}

TEST(FieldModel, SumOfSourcesAndAutodiff) {
  FieldModel model;
  model.field_constant = 1.3;
  model.transmitter_octupole_m2 = Eigen::Vector3d(-1e-3, -2e-3, 0.5e-3);
  model.planes.push_back({"floor", Eigen::Vector3d(0, 0, 0.8), Eigen::Vector3d(0, 0, 1), 0.4});
  model.planes.push_back({"door", Eigen::Vector3d(0, -2.1, 0), Eigen::Vector3d(0, 1, 0), 0.5});
  model.objects.push_back({"monitor", Eigen::Vector3d(1.5, 1.0, -0.3), 0.03});
  model.Check();
  const Eigen::Vector3d x(0.4, -0.3, -0.5);
  Matrix3<double> expected = TransmitterField<double>(1.3, model.transmitter_octupole_m2, x);
  for (const auto& p : model.planes) {
    expected += PlaneImageField<double>(1.3, p.point_in_transmitter, p.normal_in_transmitter,
                                        p.attenuation, x);
  }
  expected += InducedDipoleField<double>(1.3, model.objects[0].location_in_transmitter, 0.03, x);
  EXPECT_TRUE(model.Field<double>(x).isApprox(expected, 1e-14));

  // Jets through the whole model agree with central differences.
  using Jet = ceres::Jet<double, 3>;
  Vector3<Jet> xj;
  for (int i = 0; i < 3; ++i) xj(i) = Jet(x(i), i);
  const Matrix3<Jet> bj = model.Field<Jet>(xj);
  const double h = 1e-6;
  for (int i = 0; i < 3; ++i) {
    const Eigen::Vector3d dx = h * Eigen::Vector3d::Unit(i);
    const Matrix3<double> numeric =
        (model.Field<double>(x + dx) - model.Field<double>(x - dx)) / (2 * h);
    for (int r = 0; r < 3; ++r) {
      for (int c = 0; c < 3; ++c) {
        // Central differences: truncation O(h^2 f''') ~ 1e-10 against derivatives of order 10.
        EXPECT_NEAR(bj(r, c).v(i), numeric(r, c), 1e-6 * std::max(1.0, std::abs(numeric(r, c))));
      }
    }
  }
}

TEST(FieldModel, CheckNamesTheField) {
  FieldModel model;
  model.planes.push_back({"floor", Eigen::Vector3d(0, 0, 0), Eigen::Vector3d(0, 0, 1), 0.4});
  try {
    model.Check();
    FAIL() << "a plane through the transmitter must be rejected";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("planes[0].point_in_transmitter"), std::string::npos)
        << e.what();
  }
}

TEST(BackgroundBasis, CurlAndDivergenceFreeAndIndependent) {
  // A field between sources is the gradient of a harmonic potential: its Jacobian is symmetric
  // (no curl) and traceless (no divergence). Checked by autodiff at random points, and the basis
  // is independent: its 15 fields sampled at 10 points (30 rows) have full column rank.
  using Jet = ceres::Jet<double, 3>;
  constexpr int n = BackgroundBasisSize(kMaxBackgroundDegree);
  static_assert(BackgroundBasisSize(0) == 3 && BackgroundBasisSize(1) == 8 && n == 15);
  Eigen::MatrixXd samples(30, n);
  for (int s = 0; s < 10; ++s) {
    const Eigen::Vector3d x = RandomPoint(-1.0, 1.0);
    Vector3<Jet> xj;
    for (int i = 0; i < 3; ++i) xj(i) = Jet(x(i), i);
    const auto basis = BackgroundBasis<Jet>(kMaxBackgroundDegree, xj);
    for (int k = 0; k < n; ++k) {
      Eigen::Matrix3d jacobian;  // d field_r / d x_i
      for (int r = 0; r < 3; ++r) jacobian.row(r) = basis(r, k).v.transpose();
      // Polynomials of degree <= 2 in coordinates <= 1: exact up to rounding (1e-15 x 10).
      EXPECT_NEAR(jacobian.trace(), 0.0, 1e-13) << "basis field " << k;
      EXPECT_LT((jacobian - jacobian.transpose()).norm(), 1e-13) << "basis field " << k;
      for (int r = 0; r < 3; ++r) samples(3 * s + r, k) = basis(r, k).a;
    }
  }
  EXPECT_EQ(Eigen::FullPivLU<Eigen::MatrixXd>(samples).rank(), n);
  // A lower degree is the leading part of the higher one's basis; unused columns are zero.
  const Eigen::Vector3d x(0.3, -0.2, -0.6);
  const auto low = BackgroundBasis<double>(1, x);
  const auto high = BackgroundBasis<double>(2, x);
  EXPECT_TRUE(low.leftCols(8).isApprox(high.leftCols(8)));
  EXPECT_TRUE(low.rightCols(n - 8).isZero(0.0));
}

TEST(FieldModel, BackgroundAddsItsExpansion) {
  // Coil j's background column is sum_k c_jk grad h_k: with one coefficient set per coil the
  // field matrix is the basis columns side by side.
  FieldModel model;
  model.background.degree = 1;
  model.background.coefficients.assign(24, 0.0);
  model.background.coefficients[0 * 8 + 0] = 2e-3;   // coil x: uniform field along x
  model.background.coefficients[1 * 8 + 4] = -1e-3;  // coil y: grad(yz) = (0, z, y)
  model.background.coefficients[2 * 8 + 7] = 5e-4;   // coil z: grad(2z^2 - x^2 - y^2)
  model.Check();
  const Eigen::Vector3d x(0.4, -0.3, -0.5);
  Matrix3<double> expected = model.FreeSpaceField<double>(x);
  expected.col(0) += Eigen::Vector3d(2e-3, 0, 0);
  expected.col(1) += -1e-3 * Eigen::Vector3d(0, x.z(), x.y());
  expected.col(2) += 5e-4 * Eigen::Vector3d(-2 * x.x(), -2 * x.y(), 4 * x.z());
  EXPECT_TRUE(model.Field<double>(x).isApprox(expected, 1e-14));
  model.background.coefficients.pop_back();
  try {
    model.Check();
    FAIL() << "23 coefficients for degree 1 must be rejected";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("background.coefficients"), std::string::npos) << e.what();
  }
}

TEST(FieldModel, EverySourceScalesWithTheFieldConstant) {
  // k is the transmitter's strength: every distorting source (an image, an induced dipole, the
  // smooth field of distant sources) is driven by the transmitter, so B(p) is k times the field of
  // the same model at k = 1. That is what lets the fit hold k = 1 (docs/physical-model.md): k then
  // cancels between the measured signal and the free-space signal the tracker's solver assumes.
  FieldModel unit;
  unit.transmitter_octupole_m2 = Eigen::Vector3d(-6e-4, -7e-4, -5e-4);
  unit.planes.push_back({"floor", Eigen::Vector3d(0, 0, 0.8), Eigen::Vector3d(0, 0, 1), 0.27});
  unit.objects.push_back({"toolbox", Eigen::Vector3d(0.6, 0.95, -0.5), 0.002});
  unit.background.degree = 2;
  std::uniform_real_distribution<double> c(-1e-3, 1e-3);
  for (int i = 0; i < 3 * BackgroundBasisSize(2); ++i) {
    unit.background.coefficients.push_back(c(TestRng()));
  }
  FieldModel strong = unit;
  strong.field_constant = 2.5;
  for (int trial = 0; trial < 20; ++trial) {
    const Eigen::Vector3d x = RandomPoint(-0.8, 0.8);
    // Rounding only: the same sums, each term multiplied by k once.
    EXPECT_TRUE(strong.Field<double>(x).isApprox(2.5 * unit.Field<double>(x), 1e-13));
  }
}

TEST(SignalMatrix, IsGRTransposeB) {
  const Eigen::Matrix3d rotation = testing::RandomRotation(TestRng()).toRotationMatrix();
  Eigen::Matrix3d g = Eigen::Matrix3d::Identity();
  g(0, 1) = 0.01;
  g(2, 2) = 1.02;
  const Eigen::Matrix3d b = DipoleCoupling<double>(Eigen::Vector3d(0.3, 0.2, -0.5));
  EXPECT_TRUE(SignalMatrix<double>(g, rotation, b).isApprox(g * rotation.transpose() * b, 1e-15));
}

}  // namespace
}  // namespace trackcal

namespace trackcal {
namespace {

// Every physical parameter can be a Ceres Jet (fit/ fits them): derivatives against central
// differences for plane point/normal/attenuation, object location/polarisability, octupole, k.
TEST(FieldFunctions, DifferentiableInEveryParameter) {
  using Jet = ceres::Jet<double, 14>;
  // Parameters: k, plane point (3), plane normal (3), attenuation, object location (3),
  // polarisability, octupole x, octupole z.
  const double params[14] = {1.1, 0.1, -0.2, 0.8,  0.1,  0.05,  1.0,
                             0.4, 1.5, 1.0,  -0.3, 0.03, -1e-3, -2e-3};
  const Eigen::Vector3d x(0.3, 0.2, -0.5);
  const auto field = [&x](const auto* q) {
    using T = std::remove_const_t<std::remove_pointer_t<decltype(q)>>;
    const Vector3<T> p = x.cast<T>();
    const Vector3<T> octupole(q[12], T(0.0), q[13]);
    return Matrix3<T>(TransmitterField<T>(q[0], octupole, p) +
                      PlaneImageField<T>(q[0], Vector3<T>(q[1], q[2], q[3]),
                                         Vector3<T>(q[4], q[5], q[6]), q[7], p) +
                      InducedDipoleField<T>(q[0], Vector3<T>(q[8], q[9], q[10]), q[11], p));
  };
  Jet jets[14];
  for (int i = 0; i < 14; ++i) jets[i] = Jet(params[i], i);
  const Matrix3<Jet> b = field(static_cast<const Jet*>(jets));
  for (int i = 0; i < 14; ++i) {
    double plus[14], minus[14];
    std::copy(params, params + 14, plus);
    std::copy(params, params + 14, minus);
    const double h = 1e-6 * std::max(1e-3, std::abs(params[i]));
    plus[i] += h;
    minus[i] -= h;
    const Matrix3<double> numeric =
        (field(static_cast<const double*>(plus)) - field(static_cast<const double*>(minus))) /
        (2 * h);
    for (int r = 0; r < 3; ++r) {
      for (int c = 0; c < 3; ++c) {
        // Central differences with relative step 1e-6: truncation ~1e-12, rounding ~1e-10 / h.
        EXPECT_NEAR(b(r, c).v(i), numeric(r, c), 1e-5 * std::max(1.0, std::abs(numeric(r, c))))
            << "parameter " << i;
      }
    }
  }
}

}  // namespace
}  // namespace trackcal
