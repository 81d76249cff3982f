// Local distortion as a model term: a trilinear lookup table (core/lut.h) over the bounding box of the
// data's input positions, whose node values (6 per node: position error [m], vector part of q_e) are
// fitted jointly with the other terms, regularised by a smoothness penalty on second differences.
//
// Grid: per axis, nodes spaced at most cell_size apart from the data's minimum to its maximum (at least
// 2 nodes), or an explicit node count per axis. One parameter block per node, named
// "node_values[ix,iy,iz]" (a model file's `parameters: {node_values: ...}` applies to all of them), so
// each station's residual touches only the 8 nodes of its cell and the problem stays sparse.
//
// Smoothness: for every node with neighbours on both sides along an axis, a residual
// smoothness * (v[i-1] - 2 v[i] + v[i+1]) / sigma per component (sigma: the model's position or
// orientation noise), i.e. whitened like the station residuals. It also fixes nodes without data.
// A weak ridge (LutTermOptions::ridge) removes the LUT/polynomial gauge freedom.
#pragma once

#include <algorithm>
#include <array>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "core/lut.h"
#include "core/scalar.h"
#include "fit/model.h"
#include "fit/model_file.h"

namespace trackcal::fit {

// Largest grid a LUT term builds: per axis and in all (six parameters per node; 40^3 nodes of 25
// mm span a metre cube, so this leaves room for any grid the stations of a capture can support).
inline constexpr int kMaxLutNodesPerAxis = 1000;
inline constexpr long kMaxLutNodes = 200000;

// Default weights of a LUT in a chain without a polynomial or another LUT (alone, or with physical
// terms only: none reproduces the multilinear fields it does): the held-out optimum on the paper
// preset over 100-200 mm cells (docs/model-file.md, "LUT regularisation"). ridge 1, smoothness 1
// held every node to about one noise sigma and left 34 mm of a 40 mm distortion with 100 mm cells.
// With a polynomial in the chain it keeps 1 and 1: with the weak ridge the gauge directions are
// nearly flat and the solver did not converge in its iterations.
inline constexpr double kLoneLutSmoothness = 0.1;
inline constexpr double kLoneLutRidge = 0.01;

struct LutTermOptions {
  double cell_size = 0.1;              // [m] largest node spacing (used unless nodes is set)
  std::optional<std::array<int, 3>> nodes;  // explicit node count per axis (2 .. 1000 each)
  // Weight of the second-difference residuals (>= 0): a prior sigma of noise sigma / smoothness on
  // each node's second difference. It fills nodes without stations and limits overfitting between
  // stations.
  double smoothness = 1.0;
  // Weight of residuals ridge * v / sigma pulling every node value to zero (>= 0). Multilinear fields
  // (1, x, y, z, xy, xz, yz, xyz) are reproduced exactly by both a LUT and a polynomial and have no
  // second differences, so with a polynomial in the chain they are otherwise unidentifiable; the
  // ridge hands them to the polynomial.
  double ridge = 1.0;
  // True: the fit chooses the weight by the LUT's place in the chain (LutTerm::SetPrecedingTerms):
  // kLoneLutSmoothness / kLoneLutRidge for a LUT in a chain without a polynomial or another LUT,
  // the values above with one. FromYaml sets it for a weight the model file does not set; false
  // keeps the value above wherever the LUT is.
  bool smoothness_by_place = false;
  bool ridge_by_place = false;
  void Check() const;                  // throws std::invalid_argument
};

class LutTerm : public AutoDiffModelTerm<LutTerm> {
 public:
  static constexpr const char* kType = "lut";
  explicit LutTerm(const LutTermOptions& options);
  static std::unique_ptr<ModelTerm> FromYaml(const YamlMapReader& reader);

  std::string type() const override { return kType; }
  void Prepare(const std::vector<FitStation>& inputs) override;
  bool InitializeLinear(const std::vector<FitStation>& inputs,
                        const Eigen::Vector2d& noise_sigmas) override;
  StationBinding Bind(const AmbientPose& input) const override;
  // Analytic Jacobians: the output is linear in the node values (weight of the node times d output
  // / d error), so one forward pass over the input pose and the interpolated error (13 derivatives)
  // replaces the 55-derivative autodiff of Apply (7 passes of 8): the LUT chain's Jacobian
  // evaluation (docs/benchmarks.md, bench_fit.py). Equal to EvaluateAutoDiff to rounding.
  bool Evaluate(const StationBinding& binding, const double* const* block_values,
                const AmbientPose& input, bool jacobians, TermEvaluation* result) const override;
  // The generic autodiff of Apply (AutoDiffModelTerm), the reference the analytic Evaluate is
  // tested against.
  bool EvaluateAutoDiff(const StationBinding& binding, const double* const* block_values,
                        const AmbientPose& input, bool jacobians, TermEvaluation* result) const {
    return AutoDiffModelTerm<LutTerm>::Evaluate(binding, block_values, input, jacobians, result);
  }
  // Trilinear interpolation reproduces a linear field exactly (unless every node is fixed).
  bool AbsorbsIsotropicScaling() const override {
    bool any_free = blocks_.empty();  // before Prepare(): free unless the settings fix them
    for (const auto& b : blocks_) any_free = any_free || !b.fixed;
    return any_free;
  }
  // A LUT followed by other terms starts from zero (InitializeLinear fits the whole remaining
  // error, which would hide it from the later terms' initialisation, a physical term's search).
  void SetFollowingTerms(const std::vector<const ModelTerm*>& later) override {
    has_following_terms_ = !later.empty();
    shares_gauge_after_ = SharesGauge(later);
    ChooseWeightsByPlace();
  }
  // A LUT in a chain without another term that reproduces multilinear fields (a polynomial, another
  // LUT) before or after it takes the lone defaults for the weights chosen by place
  // (LutTermOptions::smoothness_by_place, ridge_by_place); physical terms share no such gauge with
  // it. With 1 and 1 after a physical term the paper preset's held-out mean was 23-25 mm (plane,
  // receiver_gain, sensor_offset, near_field) against 0.4-2.4 mm with the lone weights, and
  // diagnose compared a lone LUT base with candidates whose LUT had other weights; a polynomial
  // after a lone LUT (diagnose's flexible fallback) took 38.6 s with the lone weights
  // (docs/model-file.md).
  void SetPrecedingTerms(const std::vector<const ModelTerm*>& earlier) override {
    shares_gauge_before_ = SharesGauge(earlier);
    ChooseWeightsByPlace();
  }
  int AddExtraResiduals(ceres::Problem* problem, const std::vector<FitStation>& inputs) override;
  // Ridge and smoothness are weighted by 1 / sigma of the noise model.
  bool ExtraResidualsRelativeToNoise() const override { return true; }
  std::unique_ptr<Correction> ToCorrection() const override;
  nlohmann::json Describe() const override;

  // The 8 bound blocks are the corners of the cell in `binding.tag`, (a, b, c) in {0,1}^3, c
  // fastest. Outside the grid (an input moved by an earlier term while the fit runs, or a start's
  // adopted grid) the boundary value is held, as core/lut.h's runtime interpolation holds it.
  template <typename T>
  bool Apply(const StationBinding& binding, const T* const* block_values, const T* input7,
             T* output7) const;

  const LutGrid& grid() const { return *grid_; }
  // The grid's axes; adopting them makes Prepare() build that grid instead of the data's.
  nlohmann::json PreparedState() const override;
  bool AdoptPreparedState(const nlohmann::json& state) override;

 private:
  // `value` of input axis k held to the grid: outside it the boundary value is held (no slope),
  // as the runtime's InterpolateTrilinear holds it; the edge cell continued linearly is not what
  // the calibration file serves.
  double HeldToGrid(int k, double value) const {
    return std::clamp(value, grid_->axis(k).front(), grid_->axis(k).back());
  }

  LutTermOptions options_;
  std::optional<LutGrid> grid_;
  std::optional<std::array<std::vector<double>, 3>> adopted_axes_;  // AdoptPreparedState()
  Eigen::Vector2d sigmas_ = Eigen::Vector2d(1e-3, 3.5e-3);
  bool has_following_terms_ = false;
  // A polynomial or another LUT before / after this one in the chain (SetPrecedingTerms,
  // SetFollowingTerms): the multilinear gauge the ridge must hold.
  bool shares_gauge_before_ = false;
  bool shares_gauge_after_ = false;
  static bool SharesGauge(const std::vector<const ModelTerm*>& terms) {
    return std::any_of(terms.begin(), terms.end(), [](const ModelTerm* t) {
      return t->type() == kType || t->type() == "polynomial";
    });
  }
  void ChooseWeightsByPlace() {
    const bool lone = !shares_gauge_before_ && !shares_gauge_after_;
    if (options_.smoothness_by_place) {
      options_.smoothness = lone ? kLoneLutSmoothness : LutTermOptions().smoothness;
    }
    if (options_.ridge_by_place) options_.ridge = lone ? kLoneLutRidge : LutTermOptions().ridge;
  }
};

template <typename T>
bool LutTerm::Apply(const StationBinding& binding, const T* const* block_values, const T* input7,
                    T* output7) const {
  const int nz = grid_->size(2), ny = grid_->size(1);
  const int cell[3] = {static_cast<int>(binding.tag / (ny * nz)),
                       static_cast<int>((binding.tag / nz) % ny), static_cast<int>(binding.tag % nz)};
  T t[3];
  for (int k = 0; k < 3; ++k) {
    const double x0 = grid_->axis(k)[static_cast<size_t>(cell[k])];
    const double x1 = grid_->axis(k)[static_cast<size_t>(cell[k] + 1)];
    const double v = ScalarValue(input7[k]), held = HeldToGrid(k, v);
    const T x = held != v ? T(held) : input7[k];
    t[k] = (x - T(x0)) / T(x1 - x0);
  }
  T e[6];
  for (int i = 0; i < 6; ++i) e[i] = T(0);
  for (int a = 0; a < 2; ++a) {
    const T wa = a ? t[0] : T(1) - t[0];
    for (int b = 0; b < 2; ++b) {
      const T wb = b ? t[1] : T(1) - t[1];
      for (int c = 0; c < 2; ++c) {
        const T w = wa * wb * (c ? t[2] : T(1) - t[2]);
        const T* v = block_values[a * 4 + b * 2 + c];
        for (int i = 0; i < 6; ++i) e[i] += w * v[i];
      }
    }
  }
  Vector3<T> position(input7[0], input7[1], input7[2]);
  Eigen::Quaternion<T> rotation = QuaternionFromXyzwArray(input7 + 3);
  ApplyPoseError<T>(Vector3<T>(e[0], e[1], e[2]), Vector3<T>(e[3], e[4], e[5]), &position, &rotation);
  for (int k = 0; k < 3; ++k) output7[k] = position[k];
  QuaternionToXyzwArray(rotation, output7 + 3);
  return true;
}

}  // namespace trackcal::fit
