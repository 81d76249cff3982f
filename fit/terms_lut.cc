#include "fit/terms_lut.h"

#include <ceres/autodiff_cost_function.h>

#include <cmath>
#include <stdexcept>

namespace trackcal::fit {

void LutTermOptions::Check() const {
  if (nodes) {
    for (int n : *nodes) {
      if (n < 2) throw std::invalid_argument("lut: nodes must be at least 2 per axis");
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
    const auto n = reader.GetDoubleList("nodes");
    if (n.size() != 3) reader.Fail("nodes", "expected 3 node counts [nx, ny, nz]");
    std::array<int, 3> counts;
    for (int k = 0; k < 3; ++k) {
      counts[static_cast<size_t>(k)] = static_cast<int>(n[static_cast<size_t>(k)]);
      if (counts[static_cast<size_t>(k)] != n[static_cast<size_t>(k)] || counts[static_cast<size_t>(k)] < 2) {
        reader.Fail("nodes", "node counts must be integers >= 2");
      }
    }
    options.nodes = counts;
  }
  options.smoothness = reader.GetDoubleOr("smoothness", options.smoothness);
  options.ridge = reader.GetDoubleOr("ridge", options.ridge);
  try {
    options.Check();
  } catch (const std::invalid_argument& e) {
    reader.Fail(reader.Has("smoothness") ? "smoothness" : "cell_size_mm", e.what());
  }
  return std::make_unique<LutTerm>(options);
}

void LutTerm::Prepare(const std::vector<FitStation>& inputs) {
  if (inputs.empty()) throw std::invalid_argument("lut: no calibration stations");
  Eigen::Vector3d lo = inputs[0].reported.translation, hi = lo;
  for (const auto& s : inputs) {
    lo = lo.cwiseMin(s.reported.translation);
    hi = hi.cwiseMax(s.reported.translation);
  }
  std::array<std::vector<double>, 3> axes;
  for (int k = 0; k < 3; ++k) {
    if (!(hi[k] > lo[k])) {  // flat data: a thin slab around it
      lo[k] -= 1e-3;
      hi[k] += 1e-3;
    }
    const int n = options_.nodes ? (*options_.nodes)[static_cast<size_t>(k)]
                                 : std::max(2, static_cast<int>(std::ceil((hi[k] - lo[k]) / options_.cell_size - 1e-9)) + 1);
    for (int i = 0; i < n; ++i) axes[static_cast<size_t>(k)].push_back(lo[k] + (hi[k] - lo[k]) * i / (n - 1));
  }
  grid_.emplace(axes);
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

bool LutTerm::InitializeLinear(const std::vector<FitStation>& /*inputs*/,
                               const Eigen::Vector2d& noise_sigmas) {
  sigmas_ = noise_sigmas;  // for the smoothness residuals
  return false;            // node values start at zero; the problem is linear in them
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
