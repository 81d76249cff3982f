#include "core/polynomial.h"

#include <algorithm>
#include <atomic>
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
  padded_terms_ = (num_terms_ + 3) / 4 * 4;
  padded_coefficients_ = coefficients_;
  padded_coefficients_.resize(static_cast<size_t>(6 * padded_terms_), 0.0);
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
  // Padded to a multiple of 4 terms with zero monomials so the accumulation below needs no tail.
  double monomials[kMaxPolynomialTerms + 4];
  EvaluateMonomials(degree_, u, monomials);
  for (int j = num_terms_; j < padded_terms_; ++j) monomials[j] = 0.0;
  // Four interleaved partial sums: the additions of one sum depend on each other, so a single
  // accumulator makes the loop latency-bound; four independent chains keep the FPU busy.
  double acc[4][6] = {};
  const double* c = padded_coefficients_.data();
  for (int j = 0; j < padded_terms_; j += 4, c += 24) {
    for (int s = 0; s < 4; ++s) {
      const double m = monomials[j + s];
      for (int k = 0; k < 6; ++k) acc[s][k] += m * c[6 * s + k];
    }
  }
  for (int k = 0; k < 6; ++k) error6[k] = (acc[0][k] + acc[1][k]) + (acc[2][k] + acc[3][k]);
}

namespace {

// The batch kernel: poses are processed in tiles of kTile in structure-of-arrays form, so every
// arithmetic loop runs across poses (independent, vectorisable, no dependency chain longer than the
// number of terms), and the coefficients are broadcast. Compiled twice: for the baseline ISA and, on
// x86-64, for AVX2 + FMA, chosen at run time (results differ only by FMA rounding).
constexpr int kTile = 8;

struct PolynomialKernelArgs {
  int degree;
  int num_terms;
  const double* coefficients;  // num_terms x 6, term-major
  double offset[3];
  double inverse_scale[3];
};

// Four doubles; in the AVX2 clone one ymm register, in the baseline two SSE2 registers.
typedef double Vec4 __attribute__((vector_size(32)));
constexpr int kTileVecs = kTile / 4;

template <bool kFma>
[[gnu::always_inline]] inline void CorrectTile(const PolynomialKernelArgs& a, int count,
                                               const double* p_in, const double* q_in,
                                               double* p_out, double* q_out) {
  Vec4 m[kMaxPolynomialTerms][kTileVecs];
  Vec4 u[3][kTileVecs] = {};
  for (int k = 0; k < 3; ++k) {
    for (int v = 0; v < kTileVecs; ++v) {
      for (int l = 0; l < 4; ++l) {
        const int t = 4 * v + l;
        u[k][v][l] = t < count ? (p_in[3 * t + k] - a.offset[k]) * a.inverse_scale[k] : 0.0;
      }
    }
  }
  // Monomials by the recurrence of EvaluateMonomials, one tile row at a time.
  for (int v = 0; v < kTileVecs; ++v) m[0][v] = Vec4{1.0, 1.0, 1.0, 1.0};
  int prev_start = 0, prev_size = 1, pos = 1;
  for (int d = 1; d <= a.degree; ++d) {
    for (int i = 0; i < prev_size; ++i, ++pos) {
      for (int v = 0; v < kTileVecs; ++v) m[pos][v] = u[0][v] * m[prev_start + i][v];
    }
    for (int i = prev_size - d; i < prev_size; ++i, ++pos) {
      for (int v = 0; v < kTileVecs; ++v) m[pos][v] = u[1][v] * m[prev_start + i][v];
    }
    for (int v = 0; v < kTileVecs; ++v) m[pos][v] = u[2][v] * m[prev_start + prev_size - 1][v];
    ++pos;
    prev_start += prev_size;
    prev_size += d + 1;
  }
  // 6 x kTileVecs accumulators stay in registers; each coefficient is broadcast once.
  Vec4 e[6][kTileVecs] = {};
  for (int j = 0; j < a.num_terms; ++j) {
    const double* c = a.coefficients + 6 * j;
    for (int k = 0; k < 6; ++k) {
      const Vec4 ck = {c[k], c[k], c[k], c[k]};
      for (int v = 0; v < kTileVecs; ++v) e[k][v] += ck * m[j][v];  // contracted to FMA if kFma
    }
  }
  // q_e from its vector part (as QuaternionFromVectorPart), then q_e * q and p + e_p.
  for (int t = 0; t < count; ++t) {
    const int v = t / 4, l = t % 4;
    const double vx = e[3][v][l], vy = e[4][v][l], vz = e[5][v][l];
    const double n2 = vx * vx + vy * vy + vz * vz;
    double ex, ey, ez, ew;
    if (n2 < 1.0) {
      ex = vx;
      ey = vy;
      ez = vz;
      ew = std::sqrt(1.0 - n2);
    } else {
      const double inv = 1.0 / std::sqrt(n2);
      ex = vx * inv;
      ey = vy * inv;
      ez = vz * inv;
      ew = 0.0;
    }
    const double qx = q_in[4 * t], qy = q_in[4 * t + 1], qz = q_in[4 * t + 2],
                 qw = q_in[4 * t + 3];
    q_out[4 * t] = ew * qx + ex * qw + ey * qz - ez * qy;
    q_out[4 * t + 1] = ew * qy - ex * qz + ey * qw + ez * qx;
    q_out[4 * t + 2] = ew * qz + ex * qy - ey * qx + ez * qw;
    q_out[4 * t + 3] = ew * qw - ex * qx - ey * qy - ez * qz;
    for (int k = 0; k < 3; ++k) p_out[3 * t + k] = p_in[3 * t + k] + e[k][v][l];
  }
}

template <bool kFma>
[[gnu::always_inline]] inline void CorrectBatchTiles(const PolynomialKernelArgs& a, size_t n,
                                                     const double* p_in, const double* q_in,
                                                     double* p_out, double* q_out) {
  for (size_t i = 0; i < n; i += kTile) {
    const int count = static_cast<int>(std::min<size_t>(kTile, n - i));
    CorrectTile<kFma>(a, count, p_in + 3 * i, q_in + 4 * i, p_out + 3 * i, q_out + 4 * i);
  }
}

void CorrectBatchBaseline(const PolynomialKernelArgs& a, size_t n, const double* p_in,
                          const double* q_in, double* p_out, double* q_out) {
  CorrectBatchTiles<false>(a, n, p_in, q_in, p_out, q_out);
}

std::atomic<bool> force_baseline_kernel{false};

#if defined(__x86_64__) && defined(__GNUC__)
#define TRACKCAL_HAVE_AVX2_KERNEL 1
__attribute__((target("avx2,fma"))) void CorrectBatchAvx2Fma(const PolynomialKernelArgs& a,
                                                             size_t n, const double* p_in,
                                                             const double* q_in, double* p_out,
                                                             double* q_out) {
  CorrectBatchTiles<true>(a, n, p_in, q_in, p_out, q_out);
}

bool CpuHasAvx2Fma() {
  static const bool has = [] {
    __builtin_cpu_init();
    return __builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma");
  }();
  return has;
}
#endif

}  // namespace

void internal::ForceBaselinePolynomialKernel(bool force) { force_baseline_kernel = force; }

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
  PolynomialKernelArgs args{degree_, num_terms_, coefficients_.data(), {}, {}};
  for (int k = 0; k < 3; ++k) {
    args.offset[k] = input_offset_[k];
    args.inverse_scale[k] = inverse_scale_[k];
  }
#ifdef TRACKCAL_HAVE_AVX2_KERNEL
  if (CpuHasAvx2Fma() && !force_baseline_kernel.load(std::memory_order_relaxed)) {
    CorrectBatchAvx2Fma(args, n, positions, quaternions_xyzw, out_positions,
                        out_quaternions_xyzw);
  } else {
    CorrectBatchBaseline(args, n, positions, quaternions_xyzw, out_positions,
                         out_quaternions_xyzw);
  }
#else
  CorrectBatchBaseline(args, n, positions, quaternions_xyzw, out_positions, out_quaternions_xyzw);
#endif
  if (extrapolated != nullptr) std::fill(extrapolated, extrapolated + n, uint8_t{0});
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
