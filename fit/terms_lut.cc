#include "fit/terms_lut.h"

#include <ceres/autodiff_cost_function.h>
#include <ceres/jet.h>

#include <Eigen/SparseCholesky>
#include <Eigen/SparseCore>
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <stdexcept>
#include <string>

namespace trackcal::fit {

void LutTermOptions::Check() const {
  if (nodes) {
    long total = 1;
    for (int n : *nodes) {
      if (n < 2 || n > kMaxLutNodesPerAxis) {
        throw std::invalid_argument("lut: nodes must be 2 .. " +
                                    std::to_string(kMaxLutNodesPerAxis) + " per axis");
      }
      total *= n;
    }
    if (total > kMaxLutNodes) {
      throw std::invalid_argument("lut: nodes: " + std::to_string(total) + " nodes, at most " +
                                  std::to_string(kMaxLutNodes));
    }
  } else if (!(cell_size > 0.0) || !std::isfinite(cell_size)) {
    throw std::invalid_argument("lut: cell_size_mm must be > 0");
  }
  if (!(ridge >= 0.0) || !std::isfinite(ridge)) throw std::invalid_argument("lut: ridge must be >= 0");
  if (!(smoothness >= 0.0) || !std::isfinite(smoothness)) {
    throw std::invalid_argument("lut: smoothness must be >= 0");
  }
}

LutTerm::LutTerm(const LutTermOptions& options) : options_(options) { options_.Check(); }

std::unique_ptr<ModelTerm> LutTerm::FromYaml(const YamlMapReader& reader) {
  LutTermOptions options;
  if (reader.Has("cell_size_mm")) options.cell_size = reader.GetDouble("cell_size_mm") * 1e-3;
  if (reader.Has("nodes")) {
    // Both given: the node counts were used and the cell size dropped without a word.
    if (reader.node()["cell_size_mm"].IsDefined()) {
      reader.Fail("nodes", "give nodes or cell_size_mm, not both");
    }
    const auto n = reader.GetDoubleList("nodes");
    if (n.size() != 3) reader.Fail("nodes", "expected 3 node counts [nx, ny, nz]");
    std::array<int, 3> counts;
    for (size_t k = 0; k < 3; ++k) {
      // The range before the conversion: a double beyond int's range does not convert.
      if (!(n[k] >= 2 && n[k] <= kMaxLutNodesPerAxis) || n[k] != std::floor(n[k])) {
        reader.Fail("nodes",
                    "node counts must be integers 2 .. " + std::to_string(kMaxLutNodesPerAxis));
      }
      counts[k] = static_cast<int>(n[k]);
    }
    options.nodes = counts;
  }
  options.smoothness = reader.GetDoubleOr("smoothness", options.smoothness);
  options.ridge = reader.GetDoubleOr("ridge", options.ridge);
  options.smoothness_by_place = !reader.Has("smoothness");
  options.ridge_by_place = !reader.Has("ridge");
  try {
    options.Check();
  } catch (const std::invalid_argument& e) {
    // Blame the key the check is about (a negative ridge was blamed on cell_size_mm).
    const std::string what = e.what();
    reader.Fail(what.find("ridge") != std::string::npos        ? "ridge"
                : what.find("smoothness") != std::string::npos ? "smoothness"
                : what.find("nodes") != std::string::npos      ? "nodes"
                                                               : "cell_size_mm",
                what);
  }
  return std::make_unique<LutTerm>(options);
}

nlohmann::json LutTerm::PreparedState() const {
  if (!grid_) return nullptr;
  return {{"axes", {grid_->axis(0), grid_->axis(1), grid_->axis(2)}}};
}

bool LutTerm::AdoptPreparedState(const nlohmann::json& state) {
  adopted_axes_.reset();  // an earlier start's grid does not outlive it
  if (state.is_null()) return true;
  if (!state.is_object() || !state.contains("axes")) return false;
  std::array<std::vector<double>, 3> axes;
  // A start document edited by hand: named here, not by the grid as "LUT axis x: ...".
  const nlohmann::json& a = state.at("axes");
  for (size_t k = 0; k < 3; ++k) {
    bool ok = a.is_array() && a.size() == 3 && a[k].is_array() && a[k].size() >= 2 &&
              a[k].size() <= static_cast<size_t>(kMaxLutNodesPerAxis);
    for (size_t i = 0; ok && i < a[k].size(); ++i) {
      ok = a[k][i].is_number() && std::isfinite(a[k][i].get<double>());
      if (ok) axes[k].push_back(a[k][i].get<double>());
      ok = ok && (i == 0 || axes[k][i] > axes[k][i - 1]);
    }
    if (!ok) {
      throw std::invalid_argument("lut: prepared state: axes: expected 3 lists of 2 .. " +
                                  std::to_string(kMaxLutNodesPerAxis) +
                                  " strictly increasing finite numbers");
    }
  }
  if (options_.nodes) {
    for (size_t k = 0; k < 3; ++k) {
      if (static_cast<int>(axes[k].size()) != (*options_.nodes)[k]) return false;
    }
  }
  adopted_axes_ = std::move(axes);
  return true;
}

void LutTerm::Prepare(const std::vector<FitStation>& inputs) {
  if (inputs.empty()) throw std::invalid_argument("lut: no calibration stations");
  Eigen::Vector3d lo = inputs[0].reported.translation, hi = lo;
  for (const auto& s : inputs) {
    lo = lo.cwiseMin(s.reported.translation);
    hi = hi.cwiseMax(s.reported.translation);
  }
  std::array<int, 3> counts;
  double total = 1.0;
  for (int k = 0; k < 3; ++k) {
    if (!(hi[k] > lo[k])) {  // flat data: a thin slab around it
      lo[k] -= 1e-3;
      hi[k] += 1e-3;
    }
    // In double first: a small cell over a large box is beyond int's range.
    const double n =
        options_.nodes
            ? (*options_.nodes)[static_cast<size_t>(k)]
            : std::max(2.0, std::ceil((hi[k] - lo[k]) / options_.cell_size - 1e-9) + 1.0);
    total *= n;
    if (n > kMaxLutNodesPerAxis || total > static_cast<double>(kMaxLutNodes)) {
      char what[200];
      std::snprintf(what, sizeof(what),
                    "lut: cell_size_mm %g over the stations' box (%.3g x %.3g x %.3g m) gives more "
                    "than %ld nodes or %d per axis; use a larger cell",
                    options_.cell_size * 1e3, hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2],
                    kMaxLutNodes, kMaxLutNodesPerAxis);
      throw std::invalid_argument(what);
    }
    counts[static_cast<size_t>(k)] = static_cast<int>(n);
  }
  std::array<std::vector<double>, 3> axes;
  for (int k = 0; k < 3; ++k) {
    const int n = counts[static_cast<size_t>(k)];
    for (int i = 0; i < n; ++i) axes[static_cast<size_t>(k)].push_back(lo[k] + (hi[k] - lo[k]) * i / (n - 1));
    // lo + (hi - lo) rounds below hi for some boxes: the station at the maximum would be outside.
    axes[static_cast<size_t>(k)].back() = hi[k];
  }
  grid_.emplace(adopted_axes_ ? *adopted_axes_ : axes);
  blocks_.clear();
  blocks_.reserve(grid_->num_nodes());
  for (int ix = 0; ix < grid_->size(0); ++ix) {
    for (int iy = 0; iy < grid_->size(1); ++iy) {
      for (int iz = 0; iz < grid_->size(2); ++iz) {
        ParameterBlock block;
        const std::string node = "[" + std::to_string(ix) + "," + std::to_string(iy) + "," +
                                 std::to_string(iz) + "]";
        block.name = "node_values" + node;
        block.values.assign(6, 0.0);
        block.unit = "m | 1";
        for (const char* c : {"px", "py", "pz", "qx", "qy", "qz"}) block.coordinate_names.push_back(std::string(c) + node);
        blocks_.push_back(std::move(block));
      }
    }
  }
}

bool LutTerm::InitializeLinear(const std::vector<FitStation>& inputs,
                               const Eigen::Vector2d& noise_sigmas) {
  sigmas_ = noise_sigmas;  // for the smoothness residuals
  // The node values that map each station's input to its reference, with the other terms held, by
  // linear least squares (the engine then starts the joint solve from there instead of zero: the
  // LUT chain's solve, docs/benchmarks.md). The output is linear in the node values for the
  // position and, to first order in the error, for the orientation (q_e = Exp(e) ~ (e, 1)), so
  // the six components are six problems with one matrix: the stations' trilinear weights, the
  // smoothness and the ridge rows, each whitened by the component's sigma, which cancels.
  if (has_following_terms_) return false;  // see SetFollowingTerms
  for (const auto& block : blocks_) {
    if (block.fixed || !block.prior_mean.empty() || !block.lower.empty() || !block.upper.empty()) {
      return false;  // settings the unconstrained solve below would ignore: start from zero
    }
  }
  const int num_nodes = static_cast<int>(blocks_.size());
  // Each station's target error (position [m], orientation vector part) and its whitened size.
  std::vector<Eigen::Matrix<double, 6, 1>> target(inputs.size());
  std::vector<double> size(inputs.size());
  for (size_t i = 0; i < inputs.size(); ++i) {
    const PoseError e = ComputePoseError(inputs[i].reported, inputs[i].reference);
    target[i] << e.position, e.orientation;
    size[i] = std::hypot(e.position.norm() / noise_sigmas[0], e.orientation.norm() / noise_sigmas[1]);
  }
  // Gross outliers (a hemisphere flip's -p, metres off) are left out, so that a robust loss still
  // sees them as outliers from the first iteration: beyond 20 times the median station's whitened
  // error (and 20 sigma). The limit only decides where the solve starts: a station left out here
  // still enters the fit.
  std::vector<double> sorted = size;
  std::nth_element(sorted.begin(), sorted.begin() + static_cast<long>(sorted.size() / 2), sorted.end());
  const double limit = 20.0 * std::max(sorted[sorted.size() / 2], 1.0);
  std::vector<Eigen::Triplet<double>> triplets;
  Eigen::MatrixXd rhs = Eigen::MatrixXd::Zero(num_nodes, 6);
  for (size_t i = 0; i < inputs.size(); ++i) {
    if (!(size[i] <= limit)) continue;
    const AmbientPose pose = ToAmbient(inputs[i].reported);
    const StationBinding binding = Bind(pose);
    const int nz = grid_->size(2), ny = grid_->size(1);
    const int cell[3] = {static_cast<int>(binding.tag / (ny * nz)),
                         static_cast<int>((binding.tag / nz) % ny), static_cast<int>(binding.tag % nz)};
    double t[3];
    for (int k = 0; k < 3; ++k) {
      const double x0 = grid_->axis(k)[static_cast<size_t>(cell[k])];
      const double x1 = grid_->axis(k)[static_cast<size_t>(cell[k] + 1)];
      t[k] = (HeldToGrid(k, pose[k]) - x0) / (x1 - x0);
    }
    double w[8];
    for (int n = 0; n < 8; ++n) {
      const int a = n / 4, b = (n / 2) % 2, c = n % 2;
      w[n] = (a ? t[0] : 1.0 - t[0]) * (b ? t[1] : 1.0 - t[1]) * (c ? t[2] : 1.0 - t[2]);
    }
    for (int n = 0; n < 8; ++n) {
      const int node = binding.blocks[static_cast<size_t>(n)];
      rhs.row(node) += w[n] * target[i].transpose();
      for (int m = 0; m < 8; ++m) triplets.emplace_back(node, binding.blocks[static_cast<size_t>(m)], w[n] * w[m]);
    }
  }
  const int n[3] = {grid_->size(0), grid_->size(1), grid_->size(2)};
  const double s2 = options_.smoothness * options_.smoothness;
  for (int ix = 0; ix < n[0]; ++ix) {
    for (int iy = 0; iy < n[1]; ++iy) {
      for (int iz = 0; iz < n[2]; ++iz) {
        const int idx[3] = {ix, iy, iz};
        const int self = static_cast<int>(grid_->NodeIndex(ix, iy, iz));
        triplets.emplace_back(self, self, options_.ridge * options_.ridge);
        for (int axis = 0; axis < 3 && s2 > 0.0; ++axis) {
          if (idx[axis] == 0 || idx[axis] == n[axis] - 1) continue;
          int lo[3] = {ix, iy, iz}, hi[3] = {ix, iy, iz};
          --lo[axis];
          ++hi[axis];
          const int row[3] = {static_cast<int>(grid_->NodeIndex(lo[0], lo[1], lo[2])), self,
                              static_cast<int>(grid_->NodeIndex(hi[0], hi[1], hi[2]))};
          const double coefficient[3] = {1.0, -2.0, 1.0};
          for (int a = 0; a < 3; ++a) {
            for (int b = 0; b < 3; ++b) triplets.emplace_back(row[a], row[b], s2 * coefficient[a] * coefficient[b]);
          }
        }
      }
    }
  }
  Eigen::SparseMatrix<double> normal(num_nodes, num_nodes);
  normal.setFromTriplets(triplets.begin(), triplets.end());
  const Eigen::SimplicialLDLT<Eigen::SparseMatrix<double>> ldlt(normal);
  if (ldlt.info() != Eigen::Success) return false;
  const Eigen::MatrixXd values = ldlt.solve(rhs);
  if (ldlt.info() != Eigen::Success || !values.allFinite()) return false;
  for (int node = 0; node < num_nodes; ++node) {
    for (int k = 0; k < 6; ++k) blocks_[static_cast<size_t>(node)].values[static_cast<size_t>(k)] = values(node, k);
  }
  return true;
}

StationBinding LutTerm::Bind(const AmbientPose& input) const {
  int cell[3];
  for (int k = 0; k < 3; ++k) cell[k] = grid_->FindCell(k, input[k]);
  StationBinding binding;
  const int ny = grid_->size(1), nz = grid_->size(2);
  binding.tag = (static_cast<long>(cell[0]) * ny + cell[1]) * nz + cell[2];
  for (int a = 0; a < 2; ++a) {
    for (int b = 0; b < 2; ++b) {
      for (int c = 0; c < 2; ++c) {
        binding.blocks.push_back(static_cast<int>(grid_->NodeIndex(cell[0] + a, cell[1] + b, cell[2] + c)));
      }
    }
  }
  return binding;
}

bool LutTerm::Evaluate(const StationBinding& binding, const double* const* block_values,
                       const AmbientPose& input, bool jacobians, TermEvaluation* result) const {
  if (!jacobians) return Apply(binding, block_values, input.data(), result->output.data());
  // As Apply: trilinear weights w_abc(t) of the cell's corners, t_k = (x_k - x0_k) / (x1_k - x0_k).
  const int nz = grid_->size(2), ny = grid_->size(1);
  const int cell[3] = {static_cast<int>(binding.tag / (ny * nz)),
                       static_cast<int>((binding.tag / nz) % ny), static_cast<int>(binding.tag % nz)};
  // Outside the grid the boundary value is held (HeldToGrid): no slope along k.
  double t[3], inv_width[3];
  for (int k = 0; k < 3; ++k) {
    const double x0 = grid_->axis(k)[static_cast<size_t>(cell[k])];
    const double x1 = grid_->axis(k)[static_cast<size_t>(cell[k] + 1)];
    const double x = HeldToGrid(k, input[k]);
    inv_width[k] = x != input[k] ? 0.0 : 1.0 / (x1 - x0);
    t[k] = (x - x0) / (x1 - x0);
  }
  // e = sum_n w_n v_n and de / dx_k = sum_n (dw_n / dt_k) v_n / width_k.
  Eigen::Matrix<double, 6, 1> e = Eigen::Matrix<double, 6, 1>::Zero();
  Eigen::Matrix<double, 6, 3> de_dx = Eigen::Matrix<double, 6, 3>::Zero();
  double weight[8];
  for (int a = 0; a < 2; ++a) {
    const double wa = a ? t[0] : 1.0 - t[0], da = a ? 1.0 : -1.0;
    for (int b = 0; b < 2; ++b) {
      const double wb = b ? t[1] : 1.0 - t[1], db = b ? 1.0 : -1.0;
      for (int c = 0; c < 2; ++c) {
        const double wc = c ? t[2] : 1.0 - t[2], dc = c ? 1.0 : -1.0;
        const int n = a * 4 + b * 2 + c;
        weight[n] = wa * wb * wc;
        const Eigen::Map<const Eigen::Matrix<double, 6, 1>> v(block_values[n]);
        e.noalias() += weight[n] * v;
        de_dx.col(0).noalias() += (da * wb * wc * inv_width[0]) * v;
        de_dx.col(1).noalias() += (wa * db * wc * inv_width[1]) * v;
        de_dx.col(2).noalias() += (wa * wb * dc * inv_width[2]) * v;
      }
    }
  }
  // One forward pass of the pose error's application over (input pose, e).
  using Jet = ceres::Jet<double, 13>;
  Vector3<Jet> position, e_p, e_o;
  for (int k = 0; k < 3; ++k) {
    position[k] = Jet(input[k], k);
    e_p[k] = Jet(e[k], 7 + k);
    e_o[k] = Jet(e[3 + k], 10 + k);
  }
  Eigen::Quaternion<Jet> rotation = QuaternionFromXyzw<Jet>(Jet(input[3], 3), Jet(input[4], 4),
                                                            Jet(input[5], 5), Jet(input[6], 6));
  ApplyPoseError<Jet>(e_p, e_o, &position, &rotation);
  Jet out[7];
  for (int k = 0; k < 3; ++k) out[k] = position[k];
  QuaternionToXyzwArray(rotation, out + 3);
  Eigen::Matrix<double, 7, 7> d_input;
  Eigen::Matrix<double, 7, 6> d_error;
  for (int i = 0; i < 7; ++i) {
    result->output[i] = out[i].a;
    d_input.row(i) = out[i].v.head<7>().transpose();
    d_error.row(i) = out[i].v.tail<6>().transpose();
  }
  d_input.leftCols<3>().noalias() += d_error * de_dx;
  result->d_output_d_input = d_input;
  result->d_output_d_blocks.resize(binding.blocks.size());
  for (size_t n = 0; n < binding.blocks.size(); ++n) {
    result->d_output_d_blocks[n] = weight[n] * d_error;
  }
  return true;
}

namespace {
struct Ridge {
  Eigen::Matrix<double, 6, 1> weight;  // ridge / sigma per component
  template <typename T>
  bool operator()(const T* v, T* r) const {
    for (int i = 0; i < 6; ++i) r[i] = T(weight[i]) * v[i];
    return true;
  }
};

struct SecondDifference {
  Eigen::Matrix<double, 6, 1> weight;  // smoothness / sigma per component
  template <typename T>
  bool operator()(const T* a, const T* b, const T* c, T* r) const {
    for (int i = 0; i < 6; ++i) r[i] = T(weight[i]) * (a[i] - T(2) * b[i] + c[i]);
    return true;
  }
};
}  // namespace

int LutTerm::AddExtraResiduals(ceres::Problem* problem, const std::vector<FitStation>& /*inputs*/) {
  int added = 0;
  if (options_.ridge > 0.0) {
    Ridge ridge;
    for (int i = 0; i < 6; ++i) ridge.weight[i] = options_.ridge / sigmas_[i < 3 ? 0 : 1];
    for (auto& block : blocks_) {
      problem->AddResidualBlock(new ceres::AutoDiffCostFunction<Ridge, 6, 6>(new Ridge(ridge)),
                                nullptr, block.values.data());
      ++added;
    }
  }
  if (options_.smoothness == 0.0) return added;
  SecondDifference functor;
  for (int i = 0; i < 6; ++i) functor.weight[i] = options_.smoothness / sigmas_[i < 3 ? 0 : 1];
  const int n[3] = {grid_->size(0), grid_->size(1), grid_->size(2)};
  for (int ix = 0; ix < n[0]; ++ix) {
    for (int iy = 0; iy < n[1]; ++iy) {
      for (int iz = 0; iz < n[2]; ++iz) {
        const int idx[3] = {ix, iy, iz};
        for (int axis = 0; axis < 3; ++axis) {
          if (idx[axis] == 0 || idx[axis] == n[axis] - 1) continue;
          int lo[3] = {ix, iy, iz}, hi[3] = {ix, iy, iz};
          --lo[axis];
          ++hi[axis];
          double* a = blocks_[grid_->NodeIndex(lo[0], lo[1], lo[2])].values.data();
          double* b = blocks_[grid_->NodeIndex(ix, iy, iz)].values.data();
          double* c = blocks_[grid_->NodeIndex(hi[0], hi[1], hi[2])].values.data();
          problem->AddResidualBlock(
              new ceres::AutoDiffCostFunction<SecondDifference, 6, 6, 6, 6>(new SecondDifference(functor)),
              nullptr, a, b, c);
          ++added;
        }
      }
    }
  }
  return added;
}

std::unique_ptr<Correction> LutTerm::ToCorrection() const {
  std::vector<double> values;
  values.reserve(grid_->num_nodes() * 6);
  for (const auto& block : blocks_) values.insert(values.end(), block.values.begin(), block.values.end());
  return std::make_unique<TrilinearLutCorrection>(*grid_, std::move(values));
}

nlohmann::json LutTerm::Describe() const {
  nlohmann::json d = {{"smoothness", options_.smoothness}, {"ridge", options_.ridge}};
  if (grid_) {
    d["nodes"] = {grid_->size(0), grid_->size(1), grid_->size(2)};
    d["min"] = {grid_->axis(0).front(), grid_->axis(1).front(), grid_->axis(2).front()};
    d["max"] = {grid_->axis(0).back(), grid_->axis(1).back(), grid_->axis(2).back()};
  }
  return d;
}

}  // namespace trackcal::fit
