// Complete degree-r vector polynomials of the reported position (Ikits et al. 2001, eq. 7), the
// paper's global correction model, evaluated in normalised coordinates.
//
// Normalisation: the polynomial variable is u = (p - input_offset) / input_scale (per axis), not the
// raw position in metres as in the paper. With u in about [-1, 1] over the calibrated volume, the
// monomials of degree 0..r all have comparable magnitude, so the least-squares fit stays well
// conditioned at high degree (raw coordinates in metres make x^8 ~ 1e-3 next to 1) and coefficients
// are comparable across terms. input_offset and input_scale are stored in the calibration file.
//
// Canonical term order (the order of coefficients everywhere: in memory, in the file, in fit/):
// graded by total degree d = 0..r; within a degree, descending power of x, then descending power of y
// (z takes the rest). For r = 2: 1, x, y, z, x^2, xy, xz, y^2, yz, z^2; r = 4 has 35 terms. Here x, y, z
// stand for the components of u. PolynomialTermExponents() lists the (x, y, z) powers in this order.
//
// Coefficient layout: term-major; for a K-vector polynomial coefficient (j, k) is at j * K + k. The
// correction's 6-vector error is (position error x, y, z [m], vector part of q_e x, y, z), K = 6.
//
// Everything templated on T is used with ceres::Jet by fit/ (no value-dependent branches).
#pragma once

#include <Eigen/Core>
#include <array>
#include <memory>
#include <string>
#include <type_traits>
#include <vector>

#include "core/correction.h"

namespace trackcal {

// Highest supported degree: 455 terms, still well conditioned in normalised coordinates.
inline constexpr int kMaxPolynomialDegree = 12;

// R = (r+1)(r+2)(r+3)/6 (paper, after eq. 7).
constexpr int NumPolynomialTerms(int degree) {
  return (degree + 1) * (degree + 2) * (degree + 3) / 6;
}

inline constexpr int kMaxPolynomialTerms = NumPolynomialTerms(kMaxPolynomialDegree);

// The (x, y, z) powers of every term in canonical order; throws for degrees outside [0, kMax].
std::vector<std::array<int, 3>> PolynomialTermExponents(int degree);
// "1", "x", "x^2*y", ... for documentation and reports.
std::string PolynomialTermName(const std::array<int, 3>& exponents);

// Throws std::invalid_argument unless 0 <= degree <= kMaxPolynomialDegree.
void CheckPolynomialDegree(int degree);

// Writes the NumPolynomialTerms(degree) monomials of u (3 values) in canonical order to out. One
// multiplication per term: the block of degree d is x * (block d-1), then y * (the x-free tail of block
// d-1), then z * z^(d-1).
template <typename T>
void EvaluateMonomials(int degree, const T* u, T* out) {
  out[0] = T(1);
  int prev_start = 0;  // first index of the block of degree d-1
  int prev_size = 1;   // its size, d (d+1) / 2
  int pos = 1;
  for (int d = 1; d <= degree; ++d) {
    for (int i = 0; i < prev_size; ++i) out[pos++] = u[0] * out[prev_start + i];
    // The x-free terms of block d-1 are its last d entries (y^(d-1), ..., z^(d-1)).
    for (int i = prev_size - d; i < prev_size; ++i) out[pos++] = u[1] * out[prev_start + i];
    out[pos++] = u[2] * out[prev_start + prev_size - 1];
    prev_start += prev_size;
    prev_size += d + 1;
  }
}

// out[k] = sum_j monomial_j(u) * coefficients[j * kDim + k], k < kDim.
template <typename T, int kDim>
void EvaluateVectorPolynomial(int degree, const T* coefficients, const T* u, T* out) {
  const int num_terms = NumPolynomialTerms(degree);
  auto accumulate = [&](const T* monomials) {
    for (int k = 0; k < kDim; ++k) out[k] = T(0);
    for (int j = 0; j < num_terms; ++j) {
      for (int k = 0; k < kDim; ++k) out[k] += monomials[j] * coefficients[j * kDim + k];
    }
  };
  if constexpr (std::is_arithmetic_v<T>) {
    T monomials[kMaxPolynomialTerms];
    EvaluateMonomials(degree, u, monomials);
    accumulate(monomials);
  } else {
    // Jets can be large; keep them off the stack.
    std::vector<T> monomials(static_cast<size_t>(num_terms));
    EvaluateMonomials(degree, u, monomials.data());
    accumulate(monomials.data());
  }
}

// u = (p - input_offset) / input_scale, per axis.
template <typename T>
void NormalizePolynomialInput(const T* p, const Eigen::Vector3d& input_offset,
                              const Eigen::Vector3d& input_scale, T* u) {
  for (int k = 0; k < 3; ++k) u[k] = (p[k] - T(input_offset[k])) / T(input_scale[k]);
}

// The 6-vector error (position error [m], vector part of q_e) of a polynomial correction at reported
// position p: coefficients are NumPolynomialTerms(degree) x 6, term-major.
template <typename T>
void EvaluatePolynomialError(int degree, const T* coefficients, const Eigen::Vector3d& input_offset,
                             const Eigen::Vector3d& input_scale, const T* p, T* error6) {
  T u[3];
  NormalizePolynomialInput(p, input_offset, input_scale, u);
  EvaluateVectorPolynomial<T, 6>(degree, coefficients, u, error6);
}

namespace internal {
// Tests only: make PolynomialCorrection::ApplyBatch use the baseline-ISA kernel even on a CPU with
// AVX2 + FMA, so both kernels are exercised on one machine.
void ForceBaselinePolynomialKernel(bool force);
}  // namespace internal

class PolynomialCorrection : public Correction {
 public:
  static constexpr const char* kTypeName = "polynomial";
  // Value of the file's "term_order" field naming the canonical order above.
  static constexpr const char* kTermOrderName = "graded_x_y_z";

  // coefficients: NumPolynomialTerms(degree) x 6, term-major (see above). Throws std::invalid_argument
  // on a bad degree, a non-positive or non-finite scale, a wrong size or non-finite coefficients.
  PolynomialCorrection(int degree, const Eigen::Vector3d& input_offset,
                       const Eigen::Vector3d& input_scale, std::vector<double> coefficients);
  // From separate NumPolynomialTerms(degree) x 3 term-major arrays for position [m] and orientation.
  static std::unique_ptr<PolynomialCorrection> FromPositionAndOrientation(
      int degree, const Eigen::Vector3d& input_offset, const Eigen::Vector3d& input_scale,
      const std::vector<double>& position_coefficients,
      const std::vector<double>& orientation_coefficients);
  // Parser registered under "polynomial".
  static std::unique_ptr<Correction> FromJson(const JsonObjectReader& reader);

  int degree() const { return degree_; }
  int num_terms() const { return num_terms_; }
  const Eigen::Vector3d& input_offset() const { return input_offset_; }
  const Eigen::Vector3d& input_scale() const { return input_scale_; }
  const std::vector<double>& coefficients() const { return coefficients_; }

  // The 6-vector error at reported position p (the fast double path).
  void EvaluateError(const double* p, double* error6) const;

  std::string TypeName() const override { return kTypeName; }
  CorrectedPose Apply(const Rigid3d& reported) const override;
  void ApplyBatch(size_t n, const double* positions, const double* quaternions_xyzw,
                  double* out_positions, double* out_quaternions_xyzw,
                  uint8_t* extrapolated) const override;
  nlohmann::json ToJson() const override;
  std::unique_ptr<Correction> Clone() const override;

 private:
  int degree_;
  int num_terms_;
  Eigen::Vector3d input_offset_;
  Eigen::Vector3d input_scale_;
  Eigen::Vector3d inverse_scale_;
  std::vector<double> coefficients_;
  // The fast path's copy, zero-padded to a multiple of 4 terms.
  int padded_terms_ = 0;
  std::vector<double> padded_coefficients_;
};

}  // namespace trackcal
