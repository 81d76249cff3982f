#include "fit/terms_polynomial.h"

#include <ceres/jet.h>

#include <Eigen/QR>
#include <cmath>
#include <limits>
#include <stdexcept>

namespace trackcal::fit {

void PolynomialTermOptions::Check() const {
  CheckPolynomialDegree(degree);
  if (!position && !orientation) {
    throw std::invalid_argument("polynomial: at least one of position, orientation must be enabled");
  }
}

PolynomialTerm::PolynomialTerm(const PolynomialTermOptions& options) : options_(options) {
  options_.Check();
  num_terms_ = NumPolynomialTerms(options_.degree);
  const auto exponents = PolynomialTermExponents(options_.degree);
  auto make_block = [&](const std::string& name, const char* axis_prefix, const std::string& unit) {
    ParameterBlock block;
    block.name = name;
    block.values.assign(static_cast<size_t>(num_terms_) * 3, 0.0);
    block.unit = unit;
    for (int j = 0; j < num_terms_; ++j) {
      for (int k = 0; k < 3; ++k) {
        block.coordinate_names.push_back(std::string(axis_prefix) + "xyz"[k] + "[" +
                                         PolynomialTermName(exponents[static_cast<size_t>(j)]) +
                                         "]");
      }
    }
    blocks_.push_back(std::move(block));
    return static_cast<int>(blocks_.size()) - 1;
  };
  if (options_.position) position_block_ = make_block("position_coefficients", "p", "m");
  if (options_.orientation) orientation_block_ = make_block("orientation_coefficients", "q", "1");
}

std::unique_ptr<ModelTerm> PolynomialTerm::FromYaml(const YamlMapReader& reader) {
  PolynomialTermOptions options;
  options.degree = reader.GetIntOr("degree", options.degree);
  options.position = reader.GetBoolOr("position", options.position);
  options.orientation = reader.GetBoolOr("orientation", options.orientation);
  try {
    options.Check();
  } catch (const std::invalid_argument& e) {
    reader.Fail("degree", e.what());
  }
  return std::make_unique<PolynomialTerm>(options);
}

void PolynomialTerm::Prepare(const std::vector<FitStation>& inputs) {
  if (!std::isnan(options_.input_offset[0]) && !std::isnan(options_.input_scale[0])) return;
  if (inputs.empty()) throw std::invalid_argument("polynomial: no calibration stations");
  Eigen::Vector3d lo = inputs[0].reported.translation, hi = lo;
  for (const auto& s : inputs) {
    lo = lo.cwiseMin(s.reported.translation);
    hi = hi.cwiseMax(s.reported.translation);
  }
  options_.input_offset = 0.5 * (lo + hi);
  // Half the extent maps the box to [-1, 1]; a flat axis keeps scale 1 m (its powers are constant).
  options_.input_scale = (0.5 * (hi - lo)).unaryExpr([](double v) { return v > 1e-9 ? v : 1.0; });
}

bool PolynomialTerm::InitializeLinear(const std::vector<FitStation>& inputs,
                                      const Eigen::Vector2d& /*noise_sigmas*/) {
  const int n = static_cast<int>(inputs.size());
  if (n < num_terms_) return false;
  Eigen::MatrixXd a(n, num_terms_);
  Eigen::MatrixXd b_position(n, 3), b_orientation(n, 3);
  std::vector<double> monomials(static_cast<size_t>(num_terms_));
  for (int i = 0; i < n; ++i) {
    const FitStation& s = inputs[static_cast<size_t>(i)];
    double u[3];
    NormalizePolynomialInput(s.reported.translation.data(), options_.input_offset,
                             options_.input_scale, u);
    EvaluateMonomials(options_.degree, u, monomials.data());
    for (int j = 0; j < num_terms_; ++j) a(i, j) = monomials[static_cast<size_t>(j)];
    const PoseError e = ComputePoseError(s.reported, s.reference);
    b_position.row(i) = e.position.transpose();
    b_orientation.row(i) = e.orientation.transpose();
  }
  // Column-pivoting QR on the normalised basis: the paper's eq. 9 without forming A^T A (squaring
  // the condition number).
  const Eigen::ColPivHouseholderQR<Eigen::MatrixXd> qr(a);
  if (qr.rank() < num_terms_) return false;
  auto store = [&](int block_index, const Eigen::MatrixXd& b) {
    if (block_index < 0 || blocks_[static_cast<size_t>(block_index)].fixed) return;
    const Eigen::MatrixXd c = qr.solve(b);  // num_terms x 3
    auto& values = blocks_[static_cast<size_t>(block_index)].values;
    for (int j = 0; j < num_terms_; ++j) {
      for (int k = 0; k < 3; ++k) values[static_cast<size_t>(j * 3 + k)] = c(j, k);
    }
  };
  store(position_block_, b_position);
  store(orientation_block_, b_orientation);
  // diag((A^T A)^-1) = diag(P R^-1 R^-T P^T): row norms of R^-1, permuted.
  const Eigen::MatrixXd r = qr.matrixR().topLeftCorner(num_terms_, num_terms_).triangularView<Eigen::Upper>();
  const Eigen::MatrixXd r_inverse =
      r.triangularView<Eigen::Upper>().solve(Eigen::MatrixXd::Identity(num_terms_, num_terms_));
  const Eigen::VectorXd d = r_inverse.rowwise().squaredNorm();
  inverse_normal_diagonal_ = qr.colsPermutation() * d;
  return true;
}

bool PolynomialTerm::LinearCovariance(const Eigen::Vector2d& noise_sigmas) {
  if (inverse_normal_diagonal_.size() != num_terms_) return false;
  auto fill = [&](int block_index, double sigma) {
    if (block_index < 0) return;
    auto& block = blocks_[static_cast<size_t>(block_index)];
    block.stddev.assign(block.values.size(), std::numeric_limits<double>::quiet_NaN());
    if (block.fixed) return;
    for (int j = 0; j < num_terms_; ++j) {
      for (int k = 0; k < 3; ++k) {
        block.stddev[static_cast<size_t>(j * 3 + k)] = sigma * std::sqrt(inverse_normal_diagonal_[j]);
      }
    }
  };
  fill(position_block_, noise_sigmas[0]);
  fill(orientation_block_, noise_sigmas[1]);
  return true;
}

bool PolynomialTerm::Evaluate(const StationBinding& binding, const double* const* block_values,
                              const AmbientPose& input, bool jacobians,
                              TermEvaluation* result) const {
  if (!jacobians) return Apply<double>(binding, block_values, input.data(), result->output.data());
  using J3 = ceres::Jet<double, 3>;
  using J7 = ceres::Jet<double, 7>;
  J3 p[3], u[3];
  for (int k = 0; k < 3; ++k) p[k] = J3(input[k], k);
  NormalizePolynomialInput(p, options_.input_offset, options_.input_scale, u);
  std::vector<J3> monomials(static_cast<size_t>(num_terms_));
  EvaluateMonomials(options_.degree, u, monomials.data());
  J3 e_p[3], e_o[3];
  auto sum = [&](int block, J3* out) {
    for (int k = 0; k < 3; ++k) out[k] = J3(0.0);
    if (block < 0) return;
    const double* c = block_values[block];
    for (int j = 0; j < num_terms_; ++j) {
      for (int k = 0; k < 3; ++k) out[k] += monomials[static_cast<size_t>(j)] * c[j * 3 + k];
    }
  };
  sum(position_block_, e_p);
  sum(orientation_block_, e_o);
  // q_out = Q(e_o) * q_in with derivatives over (e_o, q_in).
  Vector3<J7> e_o7;
  for (int k = 0; k < 3; ++k) e_o7[k] = J7(e_o[k].a, k);
  J7 q_in[4];
  for (int k = 0; k < 4; ++k) q_in[k] = J7(input[3 + k], 3 + k);
  const Eigen::Quaternion<J7> q_out =
      QuaternionFromVectorPart<J7>(e_o7) * QuaternionFromXyzwArray(q_in);
  J7 q_out_xyzw[4];
  QuaternionToXyzwArray(q_out, q_out_xyzw);
  Eigen::Matrix<double, 4, 3> dq_deo;
  auto& d_in = result->d_output_d_input;
  d_in.setZero();
  for (int k = 0; k < 3; ++k) {
    result->output[k] = input[k] + e_p[k].a;
    d_in.block<1, 3>(k, 0) = e_p[k].v.transpose();
    d_in(k, k) += 1.0;
  }
  Eigen::Matrix<double, 3, 3> deo_dp;
  for (int k = 0; k < 3; ++k) deo_dp.row(k) = e_o[k].v.transpose();
  for (int r = 0; r < 4; ++r) {
    result->output[3 + r] = q_out_xyzw[r].a;
    dq_deo.row(r) = q_out_xyzw[r].v.head<3>().transpose();
    d_in.block<1, 4>(3 + r, 3) = q_out_xyzw[r].v.tail<4>().transpose();
  }
  d_in.block<4, 3>(3, 0) = dq_deo * deo_dp;
  result->d_output_d_blocks.resize(binding.blocks.size());
  for (size_t b = 0; b < binding.blocks.size(); ++b) {
    const int index = binding.blocks[b];
    auto& d = result->d_output_d_blocks[b];
    d.setZero(kAmbientPoseSize, num_terms_ * 3);
    for (int j = 0; j < num_terms_; ++j) {
      const double m = monomials[static_cast<size_t>(j)].a;
      for (int k = 0; k < 3; ++k) {
        if (index == position_block_) {
          d(k, j * 3 + k) = m;
        } else {
          d.block<4, 1>(3, j * 3 + k) = m * dq_deo.col(k);
        }
      }
    }
  }
  return true;
}

std::vector<double> PolynomialTerm::PositionCoefficients() const {
  return position_block_ >= 0 ? blocks_[static_cast<size_t>(position_block_)].values
                              : std::vector<double>(static_cast<size_t>(num_terms_) * 3, 0.0);
}

std::vector<double> PolynomialTerm::OrientationCoefficients() const {
  return orientation_block_ >= 0 ? blocks_[static_cast<size_t>(orientation_block_)].values
                                 : std::vector<double>(static_cast<size_t>(num_terms_) * 3, 0.0);
}

std::unique_ptr<Correction> PolynomialTerm::ToCorrection() const {
  return PolynomialCorrection::FromPositionAndOrientation(
      options_.degree, options_.input_offset, options_.input_scale, PositionCoefficients(),
      OrientationCoefficients());
}

nlohmann::json PolynomialTerm::Describe() const {
  return {{"degree", options_.degree},
          {"num_terms", num_terms_},
          {"position", options_.position},
          {"orientation", options_.orientation},
          {"input_offset", {options_.input_offset[0], options_.input_offset[1], options_.input_offset[2]}},
          {"input_scale", {options_.input_scale[0], options_.input_scale[1], options_.input_scale[2]}}};
}

}  // namespace trackcal::fit
