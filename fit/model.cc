#include "fit/model.h"

#include <cmath>
#include <iomanip>
#include <sstream>
#include <stdexcept>

namespace trackcal::fit {

AmbientPose ToAmbient(const Rigid3d& pose) {
  AmbientPose a;
  a.head<3>() = pose.translation;
  a[3] = pose.rotation.x();
  a[4] = pose.rotation.y();
  a[5] = pose.rotation.z();
  a[6] = pose.rotation.w();
  return a;
}

Rigid3d FromAmbient(const AmbientPose& a) {
  Rigid3d pose;
  pose.translation = a.head<3>();
  pose.rotation = Eigen::Quaterniond(a[6], a[3], a[4], a[5]).normalized();
  return pose;
}

void ParameterBlock::Check(const std::string& term_name) const {
  const std::string where = term_name + "." + name;
  const size_t n = values.size();
  auto fail = [&](const std::string& message) {
    throw std::invalid_argument("parameter block " + where + ": " + message);
  };
  if (!coordinate_names.empty() && coordinate_names.size() != n) fail("wrong number of names");
  if (!lower.empty() && lower.size() != n) fail("lower bound needs one value per coordinate");
  if (!upper.empty() && upper.size() != n) fail("upper bound needs one value per coordinate");
  if (prior_mean.size() != prior_sigma.size()) fail("prior needs both mean and sigma");
  if (!prior_mean.empty() && prior_mean.size() != n) fail("prior needs one value per coordinate");
  for (size_t i = 0; i < n; ++i) {
    if (!std::isfinite(values[i])) fail("value " + std::to_string(i) + " is not finite");
    const double lo = lower.empty() ? -INFINITY : lower[i];
    const double hi = upper.empty() ? INFINITY : upper[i];
    if (lo > hi) fail("lower bound above upper bound at " + std::to_string(i));
    if (values[i] < lo || values[i] > hi) {
      // In the block's own unit, the model file's; digits enough to tell a value from a bound
      // (std::to_string printed 0.000002 against a bound of 0.001).
      std::ostringstream m;
      m << std::setprecision(9) << "value " << values[i] << " at " << i;
      if (!coordinate_names.empty()) m << " (" << coordinate_names[i] << ")";
      m << " outside its bounds [" << lo << ", " << hi << "]";
      if (!unit.empty()) m << " " << unit;
      fail(m.str());
    }
    if (!prior_sigma.empty() && !(prior_sigma[i] > 0.0)) fail("prior sigma must be > 0");
  }
  if (unit_norm) {
    // Its manifold moves it on the sphere of its start's radius: a zero start stays zero (every
    // evaluation fails) and another radius is reported as the fitted value.
    double norm2 = 0.0;
    for (double v : values) norm2 += v * v;
    if (!(std::abs(std::sqrt(norm2) - 1.0) <= 1e-3)) {
      fail(
          "must be a unit vector (|value| = 1, e.g. [0, 0, 0, 1] for no rotation), got |value| = " +
          std::to_string(std::sqrt(norm2)));
    }
  }
}

void ModelTerm::Prepare(const std::vector<FitStation>& /*inputs*/) {}

bool ModelTerm::InitializeLinear(const std::vector<FitStation>& /*inputs*/,
                                 const Eigen::Vector2d& /*noise_sigmas*/) {
  return false;
}

bool ModelTerm::LinearCovariance(const Eigen::Vector2d& /*noise_sigmas*/) { return false; }

StationBinding ModelTerm::Bind(const AmbientPose& /*input*/) const {
  StationBinding binding;
  for (size_t i = 0; i < blocks_.size(); ++i) binding.blocks.push_back(static_cast<int>(i));
  return binding;
}

int ModelTerm::AddExtraResiduals(ceres::Problem* /*problem*/,
                                 const std::vector<FitStation>& /*inputs*/) {
  return 0;
}

nlohmann::json ModelTerm::Describe() const { return nlohmann::json::object(); }

CorrectionChain ModelToChain(const std::vector<std::unique_ptr<ModelTerm>>& terms) {
  CorrectionChain chain;
  for (const auto& term : terms) chain.Append(term->ToCorrection());
  return chain;
}

}  // namespace trackcal::fit
