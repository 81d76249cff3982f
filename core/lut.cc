#include "core/lut.h"

#include <cmath>
#include <stdexcept>

namespace trackcal {

namespace {

constexpr const char* kAxisNames[3] = {"x", "y", "z"};

// Relative tolerance on node positions for treating an axis as uniform: node i must be within
// 1e-9 of the axis span of first + i * step. Spacings written with 17 significant digits (or
// computed as first + i * step) are exact to ~1e-15; a real rectilinear grid differs by far more.
constexpr double kUniformTolerance = 1e-9;

// Returns an empty string if the axis is valid, else the problem (with the offending index).
std::string AxisProblem(const std::vector<double>& a, size_t* bad_index) {
  *bad_index = 0;
  if (a.size() < 2) return "an axis needs at least 2 nodes, got " + std::to_string(a.size());
  for (size_t i = 0; i < a.size(); ++i) {
    if (!std::isfinite(a[i])) {
      *bad_index = i;
      return "axis values must be finite";
    }
    if (i > 0 && !(a[i] > a[i - 1])) {
      *bad_index = i;
      // Shortest round-trip form, as the value is written in the file.
      return "axis values must be strictly increasing: " + nlohmann::json(a[i]).dump() +
             " at index " + std::to_string(i) + " follows " + nlohmann::json(a[i - 1]).dump();
    }
  }
  return "";
}

}  // namespace

LutGrid::LutGrid(std::array<std::vector<double>, 3> axes) : axes_(std::move(axes)) {
  for (int k = 0; k < 3; ++k) {
    size_t bad = 0;
    const std::string problem = AxisProblem(axes_[k], &bad);
    if (!problem.empty()) {
      throw std::invalid_argument(std::string("LUT axis ") + kAxisNames[k] + ": " + problem);
    }
    const std::vector<double>& a = axes_[k];
    const double span = a.back() - a.front();
    const double step = span / static_cast<double>(a.size() - 1);
    bool uniform = true;
    for (size_t i = 0; i < a.size() && uniform; ++i) {
      uniform = std::abs(a[i] - (a.front() + static_cast<double>(i) * step)) <=
                kUniformTolerance * span;
    }
    uniform_[k] = uniform;
    inverse_step_[k] = 1.0 / step;
  }
}

TrilinearLutCorrection::TrilinearLutCorrection(LutGrid grid, std::vector<double> node_values)
    : grid_(std::move(grid)), node_values_(std::move(node_values)) {
  if (node_values_.size() != 6 * grid_.num_nodes()) {
    throw std::invalid_argument("trilinear_lut: a " + std::to_string(grid_.size(0)) + " x " +
                                std::to_string(grid_.size(1)) + " x " +
                                std::to_string(grid_.size(2)) + " grid needs " +
                                std::to_string(grid_.num_nodes()) + " x 6 node values, got " +
                                std::to_string(node_values_.size()));
  }
  for (size_t i = 0; i < node_values_.size(); ++i) {
    if (!std::isfinite(node_values_[i])) {
      throw std::invalid_argument("trilinear_lut: node value " + std::to_string(i) +
                                  " is not finite");
    }
  }
}

std::unique_ptr<TrilinearLutCorrection> TrilinearLutCorrection::FromPositionAndOrientation(
    LutGrid grid, const std::vector<double>& position_error,
    const std::vector<double>& orientation_error) {
  const size_t n = grid.num_nodes();
  for (const auto* v : {&position_error, &orientation_error}) {
    if (v->size() != 3 * n) {
      throw std::invalid_argument(
          std::string("trilinear_lut: a ") + std::to_string(grid.size(0)) + " x " +
          std::to_string(grid.size(1)) + " x " + std::to_string(grid.size(2)) + " grid needs " +
          std::to_string(n) + " x 3 " + (v == &position_error ? "position" : "orientation") +
          " error values, got " + std::to_string(v->size()));
    }
  }
  std::vector<double> combined(6 * n);
  for (size_t i = 0; i < n; ++i) {
    for (size_t k = 0; k < 3; ++k) {
      combined[6 * i + k] = position_error[3 * i + k];
      combined[6 * i + 3 + k] = orientation_error[3 * i + k];
    }
  }
  return std::make_unique<TrilinearLutCorrection>(std::move(grid), std::move(combined));
}

std::unique_ptr<Correction> TrilinearLutCorrection::FromJson(const JsonObjectReader& reader) {
  reader.Enum("type", {kTypeName});
  reader.Enum("node_order", {kNodeOrderName});
  const JsonObjectReader axes_reader = reader.Object("axes");
  std::array<std::vector<double>, 3> axes;
  for (int k = 0; k < 3; ++k) {
    axes[k] = axes_reader.NumberArray(kAxisNames[k]);
    size_t bad = 0;
    const std::string problem = AxisProblem(axes[k], &bad);
    if (!problem.empty()) {
      if (axes[k].size() < 2) axes_reader.Fail(kAxisNames[k], problem);
      ThrowJsonError(reader.source(), JsonIndexPath(axes_reader.PathOf(kAxisNames[k]), bad),
                     problem);
    }
  }
  axes_reader.CheckNoUnknownKeys();
  LutGrid grid(std::move(axes));
  const std::string what = "a " + std::to_string(grid.size(0)) + " x " +
                           std::to_string(grid.size(1)) + " x " + std::to_string(grid.size(2)) +
                           " grid";
  const std::vector<double> position =
      reader.Vector3Array("position_error", grid.num_nodes(), what);
  const std::vector<double> orientation =
      reader.Vector3Array("orientation_error", grid.num_nodes(), what);
  return FromPositionAndOrientation(std::move(grid), position, orientation);
}

CorrectedPose TrilinearLutCorrection::Apply(const Rigid3d& reported) const {
  double e[6];
  const bool inside = EvaluateError(reported.translation.data(), e);
  CorrectedPose out{reported, !inside};
  ApplyPoseError<double>(Eigen::Vector3d(e[0], e[1], e[2]), Eigen::Vector3d(e[3], e[4], e[5]),
                         &out.pose.translation, &out.pose.rotation);
  return out;
}

void TrilinearLutCorrection::ApplyBatch(size_t n, const double* positions,
                                        const double* quaternions_xyzw, double* out_positions,
                                        double* out_quaternions_xyzw,
                                        uint8_t* extrapolated) const {
  for (size_t i = 0; i < n; ++i) {
    double e[6];
    const bool inside = EvaluateError(positions + 3 * i, e);
    const Eigen::Quaterniond q =
        QuaternionFromVectorPart<double>(Eigen::Vector3d(e[3], e[4], e[5])) *
        QuaternionFromXyzwArray(quaternions_xyzw + 4 * i);
    for (int k = 0; k < 3; ++k) out_positions[3 * i + k] = positions[3 * i + k] + e[k];
    QuaternionToXyzwArray(q, out_quaternions_xyzw + 4 * i);
    if (extrapolated != nullptr) extrapolated[i] = inside ? 0 : 1;
  }
}

nlohmann::json TrilinearLutCorrection::ToJson() const {
  nlohmann::json position = nlohmann::json::array();
  nlohmann::json orientation = nlohmann::json::array();
  for (size_t i = 0; i < grid_.num_nodes(); ++i) {
    const double* v = node_values_.data() + 6 * i;
    position.push_back({v[0], v[1], v[2]});
    orientation.push_back({v[3], v[4], v[5]});
  }
  nlohmann::json j;
  j["type"] = kTypeName;
  j["node_order"] = kNodeOrderName;
  j["axes"] = {{"x", grid_.axis(0)}, {"y", grid_.axis(1)}, {"z", grid_.axis(2)}};
  j["position_error"] = std::move(position);
  j["orientation_error"] = std::move(orientation);
  return j;
}

std::unique_ptr<Correction> TrilinearLutCorrection::Clone() const {
  return std::make_unique<TrilinearLutCorrection>(*this);
}

}  // namespace trackcal
