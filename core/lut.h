// Trilinear lookup table (LUT) over a grid of reported positions: the paper's local correction model
// (§1, "local interpolation"). Each node holds the 6-vector error (position error x, y, z [m], vector
// part of q_e x, y, z); a query is trilinearly interpolated from the 8 nodes of its cell.
//
// The grid has explicit strictly increasing axes per dimension (at least 2 nodes each). Uniformly
// spaced axes are detected and looked up in O(1); other (rectilinear) axes by binary search.
// Node order: x slowest, z fastest, i.e. node (ix, iy, iz) is at (ix * ny + iy) * nz + iz, the C order
// of a numpy array of shape (nx, ny, nz, 6). Outside the grid the boundary value is held (each local
// cell coordinate is clamped to [0, 1]) and the pose is flagged extrapolated.
//
// InterpolateTrilinear is templated on the scalar type for both the query position and the node
// values, so fit/ can optimise node values (and differentiate through the query) with ceres::Jet.
#pragma once

#include <algorithm>
#include <array>
#include <memory>
#include <string>
#include <vector>

#include "core/correction.h"
#include "core/scalar.h"

namespace trackcal {

class LutGrid {
 public:
  // Throws std::invalid_argument naming the axis and index: fewer than 2 nodes, non-finite values,
  // values not strictly increasing.
  explicit LutGrid(std::array<std::vector<double>, 3> axes);

  const std::vector<double>& axis(int k) const { return axes_[k]; }
  int size(int k) const { return static_cast<int>(axes_[k].size()); }
  size_t num_nodes() const { return axes_[0].size() * axes_[1].size() * axes_[2].size(); }
  bool uniform(int k) const { return uniform_[k]; }
  size_t NodeIndex(int ix, int iy, int iz) const {
    return (static_cast<size_t>(ix) * axes_[1].size() + static_cast<size_t>(iy)) *
               axes_[2].size() +
           static_cast<size_t>(iz);
  }
  bool Contains(const double* p) const {
    for (int k = 0; k < 3; ++k) {
      if (!(p[k] >= axes_[k].front() && p[k] <= axes_[k].back())) return false;
    }
    return true;
  }
  // Index i in [0, size(k) - 2] of the cell of axis k containing v (the first or last cell outside).
  int FindCell(int k, double v) const {
    const std::vector<double>& a = axes_[k];
    const int last_cell = static_cast<int>(a.size()) - 2;
    int i;
    if (uniform_[k]) {
      const double s = (v - a.front()) * inverse_step_[k];
      // Compare as double first: casting a huge or NaN value to int is undefined.
      if (!(s > 0.0)) return 0;
      if (s >= last_cell) return last_cell;
      i = static_cast<int>(s);
    } else {
      i = static_cast<int>(std::upper_bound(a.begin(), a.end(), v) - a.begin()) - 1;
    }
    return i < 0 ? 0 : (i > last_cell ? last_cell : i);
  }

 private:
  std::array<std::vector<double>, 3> axes_;
  std::array<bool, 3> uniform_{};
  std::array<double, 3> inverse_step_{};
};

// out = trilinear interpolation at p of node_values (grid.num_nodes() x kDim, node-major). Returns
// whether p was inside the grid (outside, the boundary value is held; a NaN coordinate is outside and
// gives NaN).
template <typename T, int kDim = 6>
bool InterpolateTrilinear(const LutGrid& grid, const T* node_values, const T* p, T* out) {
  int cell[3];
  T t[3];
  bool inside = true;
  for (int k = 0; k < 3; ++k) {
    const double v = ScalarValue(p[k]);
    cell[k] = grid.FindCell(k, v);
    const double x0 = grid.axis(k)[cell[k]];
    const double x1 = grid.axis(k)[cell[k] + 1];
    if (v < grid.axis(k).front()) {
      t[k] = T(0);
      inside = false;
    } else if (v > grid.axis(k).back()) {
      t[k] = T(1);
      inside = false;
    } else if (!(v == v)) {  // NaN: propagate it rather than hold a boundary value
      t[k] = p[k];
      inside = false;  // in no cell: flagged like any query outside the grid
    } else {
      t[k] = (p[k] - T(x0)) / T(x1 - x0);
    }
  }
  const T* c000 = node_values + kDim * grid.NodeIndex(cell[0], cell[1], cell[2]);
  const size_t sz = static_cast<size_t>(kDim);
  const size_t dz = sz;
  const size_t dy = sz * static_cast<size_t>(grid.size(2));
  const size_t dx = dy * static_cast<size_t>(grid.size(1));
  const T one(1);
  const T wx[2] = {one - t[0], t[0]};
  const T wy[2] = {one - t[1], t[1]};
  const T wz[2] = {one - t[2], t[2]};
  for (int k = 0; k < kDim; ++k) out[k] = T(0);
  for (int a = 0; a < 2; ++a) {
    for (int b = 0; b < 2; ++b) {
      const T wab = wx[a] * wy[b];
      const T* row = c000 + a * dx + b * dy;
      const T w0 = wab * wz[0];
      const T w1 = wab * wz[1];
      for (int k = 0; k < kDim; ++k) out[k] += w0 * row[k] + w1 * row[dz + k];
    }
  }
  return inside;
}

class TrilinearLutCorrection : public Correction {
 public:
  static constexpr const char* kTypeName = "trilinear_lut";
  // Value of the file's "node_order" field naming the order above.
  static constexpr const char* kNodeOrderName = "x_slowest_z_fastest";

  // node_values: grid.num_nodes() x 6 (position error [m], orientation vector part). Throws
  // std::invalid_argument on a wrong size or non-finite values.
  TrilinearLutCorrection(LutGrid grid, std::vector<double> node_values);
  // From separate num_nodes x 3 arrays.
  static std::unique_ptr<TrilinearLutCorrection> FromPositionAndOrientation(
      LutGrid grid, const std::vector<double>& position_error,
      const std::vector<double>& orientation_error);
  // Parser registered under "trilinear_lut".
  static std::unique_ptr<Correction> FromJson(const JsonObjectReader& reader);

  const LutGrid& grid() const { return grid_; }
  const std::vector<double>& node_values() const { return node_values_; }

  // The interpolated 6-vector error at p; returns whether p was inside the grid.
  bool EvaluateError(const double* p, double* error6) const {
    return InterpolateTrilinear<double, 6>(grid_, node_values_.data(), p, error6);
  }

  std::string TypeName() const override { return kTypeName; }
  CorrectedPose Apply(const Rigid3d& reported) const override;
  void ApplyBatch(size_t n, const double* positions, const double* quaternions_xyzw,
                  double* out_positions, double* out_quaternions_xyzw,
                  uint8_t* extrapolated) const override;
  nlohmann::json ToJson() const override;
  std::unique_ptr<Correction> Clone() const override;

 private:
  LutGrid grid_;
  std::vector<double> node_values_;
};

}  // namespace trackcal
