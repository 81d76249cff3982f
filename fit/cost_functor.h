// Ceres cost-functor foundations shared by every model fitted in fit/.
//
// A residual is written once as a templated functor deriving from
//
//   struct MyCost : AutoDiffCostFunctor<MyCost, /*kNumResiduals=*/3, /*param sizes=*/4, 3> {
//     explicit MyCost(Eigen::Vector3d measured);
//     template <typename T> bool operator()(const T* q, const T* t, T* residuals) const;
//   };
//
// and gets `MyCost::Create(args...)`, an owning ceres::AutoDiffCostFunction whose sizes come from
// the base, so they are never repeated at the call site. Residuals must be whitened (divided by
// their noise) before they enter a problem whose chi-square or covariance is read:
//
//   problem.AddResidualBlock(Whitened<MyCost>::Create(sqrt_information, args...), nullptr, q, t);
//
// applies a square-root information matrix L (L^T L = covariance^-1) to MyCost's raw residuals.
// IsotropicSqrtInformation / DiagonalSqrtInformation / SqrtInformationFromCovariance build L.

#pragma once

#include <ceres/autodiff_cost_function.h>

#include <Eigen/Cholesky>
#include <Eigen/Core>
#include <cstddef>
#include <stdexcept>
#include <string>
#include <tuple>
#include <type_traits>
#include <utility>

namespace trackcal::fit {

namespace internal {
template <typename Functor, int... kParamSizes>
ceres::CostFunction* MakeAutoDiffCostFunction(std::integer_sequence<int, kParamSizes...>,
                                              Functor* functor) {
  return new ceres::AutoDiffCostFunction<Functor, Functor::kNumResiduals, kParamSizes...>(functor);
}
}  // namespace internal

// CRTP base: states the residual and parameter-block sizes once and provides Create().
template <typename Derived, int kNumResidualsT, int... kParamSizes>
class AutoDiffCostFunctor {
 public:
  static constexpr int kNumResiduals = kNumResidualsT;
  static constexpr int kNumParameterBlocks = sizeof...(kParamSizes);
  using ParameterSizes = std::integer_sequence<int, kParamSizes...>;

  // A new ceres::AutoDiffCostFunction owning `Derived(args...)`; the caller (usually a
  // ceres::Problem) takes ownership.
  template <typename... Args>
  static ceres::CostFunction* Create(Args&&... args) {
    return internal::MakeAutoDiffCostFunction(ParameterSizes{},
                                              new Derived(std::forward<Args>(args)...));
  }
};

// Applies a square-root information matrix to the residuals of any AutoDiffCostFunctor:
// whitened = sqrt_information * raw. With sqrt_information = L where L^T L = Sigma^-1, the squared
// norm of the whitened residual is the Mahalanobis distance of the raw one, so the problem's cost
// is chi-square / 2.
template <typename Functor>
class Whitened {
 public:
  static constexpr int kNumResiduals = Functor::kNumResiduals;
  using SqrtInformation = Eigen::Matrix<double, kNumResiduals, kNumResiduals>;
  using ParameterSizes = typename Functor::ParameterSizes;

  Whitened(const SqrtInformation& sqrt_information, Functor functor)
      : sqrt_information_(sqrt_information), functor_(std::move(functor)) {}

  template <typename... Args>
  static ceres::CostFunction* Create(const SqrtInformation& sqrt_information, Args&&... args) {
    return internal::MakeAutoDiffCostFunction(
        ParameterSizes{}, new Whitened(sqrt_information, Functor(std::forward<Args>(args)...)));
  }

  // Called by Ceres as (params..., residuals); forwards the parameters to the wrapped functor.
  template <typename... Args>
  bool operator()(Args... args) const {
    constexpr std::size_t kNumArgs = sizeof...(Args);
    static_assert(kNumArgs >= 1, "expected at least the residual pointer");
    auto all = std::forward_as_tuple(args...);
    auto* residuals = std::get<kNumArgs - 1>(all);
    using T = std::remove_pointer_t<decltype(residuals)>;
    Eigen::Matrix<T, kNumResiduals, 1> raw;
    if (!CallWrapped(all, raw.data(), std::make_index_sequence<kNumArgs - 1>())) return false;
    Eigen::Map<Eigen::Matrix<T, kNumResiduals, 1>> whitened(residuals);
    whitened = sqrt_information_.template cast<T>() * raw;
    return true;
  }

  const SqrtInformation& sqrt_information() const { return sqrt_information_; }
  const Functor& functor() const { return functor_; }

 private:
  template <typename Tuple, typename T, std::size_t... kIs>
  bool CallWrapped(const Tuple& all, T* raw, std::index_sequence<kIs...>) const {
    return functor_(std::get<kIs>(all)..., raw);
  }

  SqrtInformation sqrt_information_;
  Functor functor_;
};

// sqrt-information of N independent residuals with the same standard deviation sigma (> 0).
template <int N>
Eigen::Matrix<double, N, N> IsotropicSqrtInformation(double sigma) {
  if (!(sigma > 0.0)) throw std::invalid_argument("noise standard deviation must be > 0");
  return Eigen::Matrix<double, N, N>::Identity() / sigma;
}

// sqrt-information of independent residuals with standard deviations sigmas (all > 0).
template <int N>
Eigen::Matrix<double, N, N> DiagonalSqrtInformation(const Eigen::Matrix<double, N, 1>& sigmas) {
  if (!(sigmas.array() > 0.0).all()) {
    throw std::invalid_argument("noise standard deviations must be > 0");
  }
  return sigmas.cwiseInverse().asDiagonal();
}

// sqrt-information L with L^T L = covariance^-1 for a symmetric positive definite covariance.
template <int N>
Eigen::Matrix<double, N, N> SqrtInformationFromCovariance(
    const Eigen::Matrix<double, N, N>& covariance) {
  const Eigen::Matrix<double, N, N> information =
      covariance.inverse().eval().template selfadjointView<Eigen::Lower>();
  Eigen::LLT<Eigen::Matrix<double, N, N>> llt(information);
  if (llt.info() != Eigen::Success) {
    throw std::invalid_argument("noise covariance is not symmetric positive definite");
  }
  // information = U^T U with U = L_llt^T upper triangular, so U is a square root.
  return llt.matrixU();
}

}  // namespace trackcal::fit
