#include "fit/alignment.h"

#include <gtest/gtest.h>

#include "tests/test_utils.h"

namespace trackcal::fit {
namespace {

TEST(AlignPoints, Nominal) {
  const Rigid3d b_from_a(testing::RandomRotation(testing::TestRng()), Eigen::Vector3d(1, -2, 3));
  std::vector<Eigen::Vector3d> from, to;
  for (int i = 0; i < 5; ++i) {
    from.push_back(Eigen::Vector3d::Random());
    to.push_back(b_from_a * from.back());
  }
  // Noise-free: exact up to rounding in the SVD.
  EXPECT_TRUE(testing::PosesNear(b_from_a, AlignPoints(from, to), 1e-12, 1e-12));
}

TEST(AlignPoints, ThreePointsAndWeights) {
  const Rigid3d b_from_a(testing::RandomRotation(testing::TestRng()), Eigen::Vector3d(0, 0.5, 0));
  std::vector<Eigen::Vector3d> from = {{0.05, 0, 0}, {0, 0.06, 0}, {0, 0, -0.07}, {0.1, 0.1, 0.1}};
  std::vector<Eigen::Vector3d> to;
  for (const auto& p : from) to.push_back(b_from_a * p);
  to[3] += Eigen::Vector3d(0.5, 0, 0);  // outlier, removed by a zero weight
  EXPECT_TRUE(testing::PosesNear(b_from_a, AlignPoints(from, to, {1, 1, 1, 0}), 1e-12, 1e-10));
  EXPECT_THROW(AlignPoints(from, {to[0]}), std::invalid_argument);
}

TEST(NearestRotation, ReflectionIsNotReturned) {
  const Eigen::Matrix3d reflection = Eigen::Vector3d(1, 1, -1).asDiagonal();
  const Eigen::Matrix3d r = NearestRotation(reflection);
  EXPECT_NEAR(r.determinant(), 1.0, 1e-12);
  const Eigen::Matrix3d rot = testing::RandomRotation(testing::TestRng()).toRotationMatrix();
  EXPECT_TRUE(NearestRotation(2.0 * rot).isApprox(rot, 1e-12));
}

}  // namespace
}  // namespace trackcal::fit
