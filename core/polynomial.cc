#include "core/polynomial.h"

#include <cmath>
#include <stdexcept>

namespace trackcal {

void CheckPolynomialDegree(int degree) {
  if (degree < 0 || degree > kMaxPolynomialDegree) {
    throw std::invalid_argument("polynomial degree must be in [0, " +
                                std::to_string(kMaxPolynomialDegree) + "], got " +
                                std::to_string(degree));
  }
}

std::vector<std::array<int, 3>> PolynomialTermExponents(int degree) {
  CheckPolynomialDegree(degree);
  std::vector<std::array<int, 3>> terms;
  for (int d = 0; d <= degree; ++d) {
    for (int a = d; a >= 0; --a) {
      for (int b = d - a; b >= 0; --b) terms.push_back({a, b, d - a - b});
    }
  }
  return terms;
}

std::string PolynomialTermName(const std::array<int, 3>& exponents) {
  static const char* kVar[3] = {"x", "y", "z"};
  std::string name;
  for (int k = 0; k < 3; ++k) {
    if (exponents[k] == 0) continue;
    if (!name.empty()) name += "*";
    name += kVar[k];
    if (exponents[k] > 1) {
      name += '^';
      name += std::to_string(exponents[k]);
    }
  }
  return name.empty() ? "1" : name;
}

PolynomialCorrection::PolynomialCorrection(int degree, const Eigen::Vector3d& input_offset,
                                           const Eigen::Vector3d& input_scale,
                                           std::vector<double> coefficients)
    : degree_(degree),
      num_terms_(0),
      input_offset_(input_offset),
      input_scale_(input_scale),
      coefficients_(std::move(coefficients)) {
  CheckPolynomialDegree(degree);
  num_terms_ = NumPolynomialTerms(degree);
  if (!input_offset_.allFinite()) {
    throw std::invalid_argument("polynomial: input_offset must be finite");
  }
  for (int k = 0; k < 3; ++k) {
    if (!(std::isfinite(input_scale_[k]) && input_scale_[k] > 0.0)) {
      throw std::invalid_argument("polynomial: input_scale must be positive and finite, got " +
                                  std::to_string(input_scale_[k]) + " on axis " +
                                  std::to_string(k));
    }
  }
  inverse_scale_ = input_scale_.cwiseInverse();
  if (coefficients_.size() != static_cast<size_t>(6 * num_terms_)) {
    throw std::invalid_argument("polynomial: degree " + std::to_string(degree) + " needs " +
                                std::to_string(num_terms_) + " x 6 = " +
                                std::to_string(6 * num_terms_) + " coefficients, got " +
                                std::to_string(coefficients_.size()));
  }
  for (size_t i = 0; i < coefficients_.size(); ++i) {
    if (!std::isfinite(coefficients_[i])) {
      throw std::invalid_argument("polynomial: coefficient " + std::to_string(i) +
                                  " is not finite");
    }
  }
}

std::unique_ptr<PolynomialCorrection> PolynomialCorrection::FromPositionAndOrientation(
    int degree, const Eigen::Vector3d& input_offset, const Eigen::Vector3d& input_scale,
    const std::vector<double>& position_coefficients,
    const std::vector<double>& orientation_coefficients) {
  CheckPolynomialDegree(degree);
  const size_t r = static_cast<size_t>(NumPolynomialTerms(degree));
  for (const auto* c : {&position_coefficients, &orientation_coefficients}) {
    if (c->size() != 3 * r) {
      throw std::invalid_argument(
          std::string("polynomial: degree ") + std::to_string(degree) + " needs " +
          std::to_string(r) + " x 3 " +
          (c == &position_coefficients ? "position" : "orientation") + " coefficients, got " +
          std::to_string(c->size()));
    }
  }
  std::vector<double> combined(6 * r);
  for (size_t j = 0; j < r; ++j) {
    for (size_t k = 0; k < 3; ++k) {
      combined[6 * j + k] = position_coefficients[3 * j + k];
      combined[6 * j + 3 + k] = orientation_coefficients[3 * j + k];
    }
  }
  return std::make_unique<PolynomialCorrection>(degree, input_offset, input_scale,
                                                std::move(combined));
}

std::unique_ptr<Correction> PolynomialCorrection::FromJson(const JsonObjectReader& reader) {
  reader.Enum("type", {kTypeName});
  const int degree = reader.Integer("degree");
  if (degree < 0 || degree > kMaxPolynomialDegree) {
    reader.Fail("degree", "must be in [0, " + std::to_string(kMaxPolynomialDegree) + "], got " +
                              std::to_string(degree));
  }
  reader.Enum("term_order", {kTermOrderName});
  const Eigen::Vector3d offset = reader.Vector3("input_offset");
  const Eigen::Vector3d scale = reader.Vector3("input_scale");
  for (int k = 0; k < 3; ++k) {
    if (!(scale[k] > 0.0)) {
      reader.Fail("input_scale", "entries must be positive, got " + reader.Get("input_scale").dump());
    }
  }
  const size_t r = static_cast<size_t>(NumPolynomialTerms(degree));
  const std::string what = "degree " + std::to_string(degree);
  const std::vector<double> position = reader.Vector3Array("position_coefficients", r, what);
  const std::vector<double> orientation = reader.Vector3Array("orientation_coefficients", r, what);
  return FromPositionAndOrientation(degree, offset, scale, position, orientation);
}

void PolynomialCorrection::EvaluateError(const double* p, double* error6) const {
  const double u[3] = {(p[0] - input_offset_[0]) * inverse_scale_[0],
                       (p[1] - input_offset_[1]) * inverse_scale_[1],
                       (p[2] - input_offset_[2]) * inverse_scale_[2]};
  double monomials[kMaxPolynomialTerms];
  EvaluateMonomials(degree_, u, monomials);
  double acc[6] = {0, 0, 0, 0, 0, 0};
  const double* c = coefficients_.data();
  for (int j = 0; j < num_terms_; ++j, c += 6) {
    const double m = monomials[j];
    for (int k = 0; k < 6; ++k) acc[k] += m * c[k];
  }
  for (int k = 0; k < 6; ++k) error6[k] = acc[k];
}

namespace {

// p += e[0..2]; q = q_e(e[3..5]) * q, on raw arrays (the batch path).
inline void ApplyErrorToArrays(const double* error6, const double* p_in, const double* q_in,
                               double* p_out, double* q_out) {
  const Eigen::Quaterniond q_e =
      QuaternionFromVectorPart<double>(Eigen::Vector3d(error6[3], error6[4], error6[5]));
  const Eigen::Quaterniond q = q_e * QuaternionFromXyzwArray(q_in);
  p_out[0] = p_in[0] + error6[0];
  p_out[1] = p_in[1] + error6[1];
  p_out[2] = p_in[2] + error6[2];
  QuaternionToXyzwArray(q, q_out);
}

}  // namespace

CorrectedPose PolynomialCorrection::Apply(const Rigid3d& reported) const {
  double e[6];
  EvaluateError(reported.translation.data(), e);
  CorrectedPose out{reported, false};
  ApplyPoseError<double>(Eigen::Vector3d(e[0], e[1], e[2]), Eigen::Vector3d(e[3], e[4], e[5]),
                         &out.pose.translation, &out.pose.rotation);
  return out;
}

void PolynomialCorrection::ApplyBatch(size_t n, const double* positions,
                                      const double* quaternions_xyzw, double* out_positions,
                                      double* out_quaternions_xyzw, uint8_t* extrapolated) const {
  for (size_t i = 0; i < n; ++i) {
    double e[6];
    EvaluateError(positions + 3 * i, e);
    ApplyErrorToArrays(e, positions + 3 * i, quaternions_xyzw + 4 * i, out_positions + 3 * i,
                       out_quaternions_xyzw + 4 * i);
    if (extrapolated != nullptr) extrapolated[i] = 0;
  }
}

nlohmann::json PolynomialCorrection::ToJson() const {
  nlohmann::json position = nlohmann::json::array();
  nlohmann::json orientation = nlohmann::json::array();
  for (int j = 0; j < num_terms_; ++j) {
    const double* c = coefficients_.data() + 6 * j;
    position.push_back({c[0], c[1], c[2]});
    orientation.push_back({c[3], c[4], c[5]});
  }
  nlohmann::json j;
  j["type"] = kTypeName;
  j["degree"] = degree_;
  j["term_order"] = kTermOrderName;
  j["input_offset"] = {input_offset_.x(), input_offset_.y(), input_offset_.z()};
  j["input_scale"] = {input_scale_.x(), input_scale_.y(), input_scale_.z()};
  j["position_coefficients"] = std::move(position);
  j["orientation_coefficients"] = std::move(orientation);
  return j;
}

std::unique_ptr<Correction> PolynomialCorrection::Clone() const {
  return std::make_unique<PolynomialCorrection>(*this);
}

}  // namespace trackcal
