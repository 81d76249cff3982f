#include "fit/cost_functor.h"

#include <ceres/ceres.h>
#include <gtest/gtest.h>

#include "fit/marker_model.h"
#include "tests/test_utils.h"

namespace trackcal::fit {
namespace {

// r = [a0 + 2 a1 - m0, a0 * b - m1]: two parameter blocks of different sizes.
struct TwoBlockCost : AutoDiffCostFunctor<TwoBlockCost, 2, 2, 1> {
  explicit TwoBlockCost(Eigen::Vector2d measured) : measured(std::move(measured)) {}
  template <typename T>
  bool operator()(const T* a, const T* b, T* r) const {
    r[0] = a[0] + T(2) * a[1] - T(measured(0));
    r[1] = a[0] * b[0] - T(measured(1));
    return true;
  }
  Eigen::Vector2d measured;
};

void Evaluate(const ceres::CostFunction& f, const double* a, const double* b, double* residuals,
              double* ja, double* jb) {
  const double* params[2] = {a, b};
  double* jacobians[2] = {ja, jb};
  ASSERT_TRUE(f.Evaluate(params, residuals, jacobians));
}

TEST(AutoDiffCostFunctor, Nominal) {
  std::unique_ptr<ceres::CostFunction> f(TwoBlockCost::Create(Eigen::Vector2d(1.0, 2.0)));
  EXPECT_EQ(f->num_residuals(), 2);
  ASSERT_EQ(f->parameter_block_sizes().size(), 2u);
  EXPECT_EQ(f->parameter_block_sizes()[0], 2);
  EXPECT_EQ(f->parameter_block_sizes()[1], 1);
  const double a[2] = {3.0, 0.5}, b[1] = {4.0};
  double r[2], ja[4], jb[2];
  Evaluate(*f, a, b, r, ja, jb);
  EXPECT_DOUBLE_EQ(r[0], 3.0 + 1.0 - 1.0);
  EXPECT_DOUBLE_EQ(r[1], 12.0 - 2.0);
  // Row-major jacobians: d r1 / d a0 = b, d r1 / d b = a0.
  EXPECT_DOUBLE_EQ(ja[2], 4.0);
  EXPECT_DOUBLE_EQ(jb[1], 3.0);
}

TEST(Whitened, AppliesSqrtInformationToResidualsAndJacobians) {
  Eigen::Matrix2d l;
  l << 2.0, 0.5, 0.0, 3.0;
  const Eigen::Vector2d measured(1.0, 2.0);
  std::unique_ptr<ceres::CostFunction> raw(TwoBlockCost::Create(measured));
  std::unique_ptr<ceres::CostFunction> whitened(Whitened<TwoBlockCost>::Create(l, measured));
  EXPECT_EQ(whitened->num_residuals(), 2);
  EXPECT_EQ(whitened->parameter_block_sizes(), raw->parameter_block_sizes());
  const double a[2] = {0.3, -1.2}, b[1] = {2.5};
  Eigen::Vector2d r_raw, r_w;
  Eigen::Matrix<double, 2, 2, Eigen::RowMajor> ja_raw, ja_w;
  Eigen::Vector2d jb_raw, jb_w;
  Evaluate(*raw, a, b, r_raw.data(), ja_raw.data(), jb_raw.data());
  Evaluate(*whitened, a, b, r_w.data(), ja_w.data(), jb_w.data());
  // Exact arithmetic up to one rounding per product: 1e-14 relative.
  EXPECT_TRUE(r_w.isApprox(l * r_raw, 1e-14));
  EXPECT_TRUE(ja_w.isApprox(l * ja_raw, 1e-14));
  EXPECT_TRUE(jb_w.isApprox(l * jb_raw, 1e-14));
}

TEST(SqrtInformation, SquaresToInverseCovariance) {
  Eigen::Matrix3d a = Eigen::Matrix3d::Random();
  const Eigen::Matrix3d covariance = a * a.transpose() + 0.1 * Eigen::Matrix3d::Identity();
  const Eigen::Matrix3d l = SqrtInformationFromCovariance<3>(covariance);
  EXPECT_TRUE((l.transpose() * l).isApprox(covariance.inverse(), 1e-10));
  EXPECT_TRUE(IsotropicSqrtInformation<3>(0.5).isApprox(2.0 * Eigen::Matrix3d::Identity()));
  EXPECT_TRUE(DiagonalSqrtInformation<2>(Eigen::Vector2d(0.5, 4.0))
                  .isApprox(Eigen::Vector2d(2.0, 0.25).asDiagonal().toDenseMatrix()));
  EXPECT_THROW(IsotropicSqrtInformation<3>(0.0), std::invalid_argument);
  EXPECT_THROW(SqrtInformationFromCovariance<2>(-Eigen::Matrix2d::Identity()),
               std::invalid_argument);
}

TEST(MarkerPositionCost, MatchesRigidComposition) {
  const Rigid3d optical_from_transmitter(testing::RandomRotation(testing::TestRng()),
                                         Eigen::Vector3d(1.0, -2.0, 0.5));
  const Rigid3d transmitter_from_receiver(testing::RandomRotation(testing::TestRng()),
                                          Eigen::Vector3d(0.3, 0.1, -0.2));
  const Eigen::Vector3d r(0.05, -0.02, 0.07);
  const Eigen::Vector3d expected = optical_from_transmitter * (transmitter_from_receiver * r);
  double q0[4], q[4];
  QuaternionToXyzwArray(optical_from_transmitter.rotation, q0);
  QuaternionToXyzwArray(transmitter_from_receiver.rotation, q);
  const Eigen::Vector3d predicted =
      PredictMarkerInOptical(q0, optical_from_transmitter.translation.data(), q,
                             transmitter_from_receiver.translation.data(), r.data());
  EXPECT_TRUE(predicted.isApprox(expected, 1e-14));

  // Autodiff Jacobian against central differences (no analytic Jacobian exists to compare).
  std::unique_ptr<ceres::CostFunction> f(MarkerPositionCost::Create(expected));
  const double* params[5] = {q0, optical_from_transmitter.translation.data(), q,
                             transmitter_from_receiver.translation.data(), r.data()};
  Eigen::Matrix<double, 3, 3, Eigen::RowMajor> j_r;
  double* jacobians[5] = {nullptr, nullptr, nullptr, nullptr, j_r.data()};
  Eigen::Vector3d residual;
  ASSERT_TRUE(f->Evaluate(params, residual.data(), jacobians));
  EXPECT_LT(residual.norm(), 1e-14);
  // Residual is linear in r with slope R0 R.
  const Eigen::Matrix3d slope =
      (optical_from_transmitter.rotation * transmitter_from_receiver.rotation).toRotationMatrix();
  EXPECT_TRUE(Eigen::Matrix3d(j_r).isApprox(slope, 1e-14));
}

}  // namespace
}  // namespace trackcal::fit
