#include "core/lut.h"

#include <ceres/jet.h>
#include <gtest/gtest.h>

#include <cmath>

#include "tests/test_utils.h"

namespace trackcal {
namespace {

using testing::TestRng;

std::vector<double> UniformAxis(double first, double last, int n) {
  std::vector<double> a(n);
  for (int i = 0; i < n; ++i) a[i] = first + (last - first) * i / (n - 1);
  return a;
}

LutGrid UniformGrid() {
  return LutGrid({UniformAxis(-0.5, 0.5, 6), UniformAxis(-0.4, 0.4, 5), UniformAxis(0.0, 0.6, 4)});
}

LutGrid RectilinearGrid() {
  return LutGrid({std::vector<double>{-0.5, -0.3, 0.0, 0.05, 0.5},
                  std::vector<double>{-0.4, 0.1, 0.15, 0.4},
                  std::vector<double>{0.0, 0.2, 0.25, 0.6}});
}

// A function that is trilinear in (x, y, z): interpolation must reproduce it exactly everywhere.
void Trilinear(const double* p, double* out) {
  const double x = p[0], y = p[1], z = p[2];
  for (int k = 0; k < 6; ++k) {
    const double s = 0.001 * (k + 1);
    out[k] = s * (1.0 + 2 * x - 3 * y + 0.5 * z + 4 * x * y - x * z + 2 * y * z - 3 * x * y * z);
  }
}

std::vector<double> NodeValues(const LutGrid& grid, void (*f)(const double*, double*)) {
  std::vector<double> v(6 * grid.num_nodes());
  for (int i = 0; i < grid.size(0); ++i) {
    for (int j = 0; j < grid.size(1); ++j) {
      for (int k = 0; k < grid.size(2); ++k) {
        const double p[3] = {grid.axis(0)[i], grid.axis(1)[j], grid.axis(2)[k]};
        f(p, &v[6 * grid.NodeIndex(i, j, k)]);
      }
    }
  }
  return v;
}

Eigen::Vector3d RandomInside(const LutGrid& g) {
  Eigen::Vector3d p;
  for (int k = 0; k < 3; ++k) {
    std::uniform_real_distribution<double> u(g.axis(k).front(), g.axis(k).back());
    p[k] = u(TestRng());
  }
  return p;
}

TEST(TrilinearLut, Nominal) {
  // Exact at nodes: random node values are returned bit-exactly at every node.
  for (const LutGrid& grid : {UniformGrid(), RectilinearGrid()}) {
    std::vector<double> values(6 * grid.num_nodes());
    std::normal_distribution<double> n(0.0, 0.01);
    for (double& v : values) v = n(TestRng());
    for (int i = 0; i < grid.size(0); ++i) {
      for (int j = 0; j < grid.size(1); ++j) {
        for (int k = 0; k < grid.size(2); ++k) {
          const double p[3] = {grid.axis(0)[i], grid.axis(1)[j], grid.axis(2)[k]};
          double out[6];
          EXPECT_TRUE((InterpolateTrilinear<double, 6>(grid, values.data(), p, out)));
          for (int c = 0; c < 6; ++c) {
            EXPECT_EQ(out[c], values[6 * grid.NodeIndex(i, j, k) + c]) << i << j << k << c;
          }
        }
      }
    }
  }
}

TEST(TrilinearLut, ReproducesTrilinearFunctionsInsideCells) {
  for (const LutGrid& grid : {UniformGrid(), RectilinearGrid()}) {
    const std::vector<double> values = NodeValues(grid, Trilinear);
    for (int i = 0; i < 500; ++i) {
      const Eigen::Vector3d p = RandomInside(grid);
      double out[6], expected[6];
      InterpolateTrilinear<double, 6>(grid, values.data(), p.data(), out);
      Trilinear(p.data(), expected);
      // Same trilinear function, different arithmetic: rounding of values <= 0.1.
      for (int k = 0; k < 6; ++k) EXPECT_NEAR(out[k], expected[k], 1e-15);
    }
  }
}

TEST(TrilinearLut, LinearAlongEachAxisWithinACell) {
  const LutGrid grid = RectilinearGrid();
  std::vector<double> values(6 * grid.num_nodes());
  std::normal_distribution<double> n(0.0, 0.01);
  for (double& v : values) v = n(TestRng());
  for (int trial = 0; trial < 100; ++trial) {
    const Eigen::Vector3d p = RandomInside(grid);
    for (int axis = 0; axis < 3; ++axis) {
      const int cell = grid.FindCell(axis, p[axis]);
      Eigen::Vector3d a = p, b = p, m = p;
      a[axis] = grid.axis(axis)[cell];
      b[axis] = grid.axis(axis)[cell + 1];
      const double s = 0.3;
      m[axis] = a[axis] + s * (b[axis] - a[axis]);
      double ea[6], eb[6], em[6];
      InterpolateTrilinear<double, 6>(grid, values.data(), a.data(), ea);
      InterpolateTrilinear<double, 6>(grid, values.data(), b.data(), eb);
      InterpolateTrilinear<double, 6>(grid, values.data(), m.data(), em);
      for (int k = 0; k < 6; ++k) EXPECT_NEAR(em[k], ea[k] + s * (eb[k] - ea[k]), 1e-16);
    }
  }
}

TEST(LutGrid, UniformLookupMatchesBinarySearch) {
  const LutGrid uniform = UniformGrid();
  for (int k = 0; k < 3; ++k) EXPECT_TRUE(uniform.uniform(k));
  const LutGrid rect = RectilinearGrid();
  for (int k = 0; k < 3; ++k) EXPECT_FALSE(rect.uniform(k));
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  for (int i = 0; i < 2000; ++i) {
    const double v = u(TestRng());
    const auto& a = uniform.axis(0);
    int expected = static_cast<int>(std::upper_bound(a.begin(), a.end(), v) - a.begin()) - 1;
    expected = std::clamp(expected, 0, static_cast<int>(a.size()) - 2);
    const int cell = uniform.FindCell(0, v);
    // Off by one only at a node, where both cells give the same value.
    if (cell != expected) {
      EXPECT_NEAR(v, a[std::max(cell, expected)], 1e-15);
    }
  }
  EXPECT_EQ(uniform.FindCell(0, 1e300), uniform.size(0) - 2);
  EXPECT_EQ(uniform.FindCell(0, -1e300), 0);
}

TEST(LutGrid, RejectsBadAxes) {
  EXPECT_THROW(LutGrid({std::vector<double>{0.0}, UniformAxis(0, 1, 2), UniformAxis(0, 1, 2)}),
               std::invalid_argument);
  EXPECT_THROW(LutGrid({UniformAxis(0, 1, 2), std::vector<double>{0.0, 0.5, 0.5},
                        UniformAxis(0, 1, 2)}),
               std::invalid_argument);
  EXPECT_THROW(LutGrid({UniformAxis(0, 1, 2), UniformAxis(0, 1, 2),
                        std::vector<double>{0.0, std::nan(""), 1.0}}),
               std::invalid_argument);
  try {
    LutGrid({UniformAxis(0, 1, 3), std::vector<double>{0.0, 0.6, 0.5}, UniformAxis(0, 1, 2)});
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("axis y"), std::string::npos) << e.what();
  }
}

TEST(TrilinearLutCorrection, HoldsBoundaryValueOutsideAndFlags) {
  const LutGrid grid = UniformGrid();
  const TrilinearLutCorrection lut(grid, NodeValues(grid, Trilinear));
  const Eigen::Quaterniond q = testing::RandomRotation(TestRng());
  const Eigen::Vector3d inside(0.2, -0.1, 0.3);
  const Eigen::Vector3d outside(0.9, -0.1, -2.0);  // beyond x max and z min
  const Eigen::Vector3d boundary(0.5, -0.1, 0.0);
  const CorrectedPose in = lut.Apply(Rigid3d(q, inside));
  EXPECT_FALSE(in.extrapolated);
  const CorrectedPose out = lut.Apply(Rigid3d(q, outside));
  EXPECT_TRUE(out.extrapolated);
  double e_boundary[6], e_outside[6];
  lut.EvaluateError(boundary.data(), e_boundary);
  EXPECT_FALSE(lut.EvaluateError(outside.data(), e_outside));
  for (int k = 0; k < 6; ++k) EXPECT_EQ(e_outside[k], e_boundary[k]);
  EXPECT_TRUE(out.pose.translation.isApprox(
      outside + Eigen::Vector3d(e_boundary[0], e_boundary[1], e_boundary[2]), 1e-15));
  // Apply composes q_e on the left (transmitter frame).
  const Eigen::Vector3d v(e_boundary[3], e_boundary[4], e_boundary[5]);
  EXPECT_TRUE(testing::RotationsNear(QuaternionFromVectorPart<double>(v) * q, out.pose.rotation,
                                     1e-15));
  // A NaN position is in no cell: NaN out, flagged like any other query outside the grid.
  const CorrectedPose nan = lut.Apply(Rigid3d(q, Eigen::Vector3d(0.2, NAN, 0.3)));
  EXPECT_TRUE(nan.extrapolated);
  EXPECT_TRUE(std::isnan(nan.pose.translation.x()));
  uint8_t flag = 0;
  const double p_nan[3] = {0.2, NAN, 0.3};
  const double q_identity[4] = {0, 0, 0, 1};
  double p_out[3], q_out[4];
  lut.ApplyBatch(1, p_nan, q_identity, p_out, q_out, &flag);
  EXPECT_EQ(flag, 1);
}

TEST(InterpolateTrilinear, AutodiffThroughNodeValuesAndPosition) {
  using Jet = ceres::Jet<double, 4>;
  const LutGrid grid = RectilinearGrid();
  const std::vector<double> values = NodeValues(grid, Trilinear);
  const Eigen::Vector3d p(0.01, 0.12, 0.22);  // cell (2, 1, 1)
  std::vector<Jet> v_jet(values.begin(), values.end());
  // Seed component 0 of the 8 corners' first corner and the position.
  const size_t corner = grid.NodeIndex(2, 1, 1);
  v_jet[6 * corner] = Jet(values[6 * corner], 3);
  Jet p_jet[3] = {Jet(p.x(), 0), Jet(p.y(), 1), Jet(p.z(), 2)};
  Jet out[6];
  InterpolateTrilinear<Jet, 6>(grid, v_jet.data(), p_jet, out);
  // Weight of corner (2,1,1) is the product of (1 - t) on each axis.
  const double tx = (p.x() - 0.0) / 0.05, ty = (p.y() - 0.1) / 0.05, tz = (p.z() - 0.2) / 0.05;
  EXPECT_NEAR(out[0].v[3], (1 - tx) * (1 - ty) * (1 - tz), 1e-14);
  // The function is trilinear, so d/dp of the interpolation equals its analytic gradient.
  const double x = p.x(), y = p.y(), z = p.z();
  const double s = 0.001;
  EXPECT_NEAR(out[0].v[0], s * (2 + 4 * y - z - 3 * y * z), 1e-13);
  EXPECT_NEAR(out[0].v[1], s * (-3 + 4 * x + 2 * z - 3 * x * z), 1e-13);
  EXPECT_NEAR(out[0].v[2], s * (0.5 - x + 2 * y - 3 * x * y), 1e-13);
}

}  // namespace
}  // namespace trackcal
