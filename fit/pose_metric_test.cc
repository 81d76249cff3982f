#include "fit/pose_metric.h"

#include <gtest/gtest.h>

#include <Eigen/SVD>
#include <cmath>
#include <random>

#include "fit/fit_engine.h"
#include "fit/model_file.h"

namespace trackcal::fit {
namespace {

// A = U diag(s) V^T with random orthogonal U, V (deterministic seed).
Matrix6 WithSingularValues(const Eigen::Matrix<double, 6, 1>& s, std::mt19937* rng) {
  std::normal_distribution<double> normal;
  auto orthogonal = [&] {
    Matrix6 m;
    for (int i = 0; i < 36; ++i) m(i) = normal(*rng);
    return Matrix6(Eigen::JacobiSVD<Matrix6>(m, Eigen::ComputeFullU).matrixU());
  };
  return orthogonal() * s.asDiagonal() * orthogonal().transpose();
}

TEST(PoseMetricOf, InvertsAWhereTheAmplificationIsBelowTheThreshold) {
  std::mt19937 rng(3);
  Eigen::Matrix<double, 6, 1> s;
  s << 1.6, 1.2, 1.0, 0.9, 0.7, 0.55;  // amplifications 1 / s up to 1.82 < 2
  const Matrix6 a = WithSingularValues(s, &rng);
  const PoseMetric m = PoseMetricOf(a, 2.0);
  ASSERT_TRUE(m.k.has_value());
  EXPECT_NEAR(m.gain, 1.0 / 0.55, 1e-12);
  // Rounding of a 6 x 6 SVD: 1e-12.
  EXPECT_LT((*m.k * a - Matrix6::Identity()).norm(), 1e-12);
}

TEST(PoseMetricOf, CapsTheAmplificationAtTheThreshold) {
  std::mt19937 rng(4);
  Eigen::Matrix<double, 6, 1> s;
  s << 1.3, 1.0, 0.8, 0.1, 0.02, 0.0;  // amplifications 10, 50 and unbounded (no root)
  const Matrix6 a = WithSingularValues(s, &rng);
  const PoseMetric m = PoseMetricOf(a, 2.0);
  ASSERT_TRUE(m.k.has_value());
  EXPECT_GT(m.gain, 1e12);  // unbounded: the SVD's rounding of the zero singular value
  // K's singular values are min(1 / s, 2): 2, 2, 2, 1.25, 1, 1 / 1.3.
  const Eigen::Matrix<double, 6, 1> k = Eigen::JacobiSVD<Matrix6>(*m.k).singularValues();
  const Eigen::Matrix<double, 6, 1> expected =
      (Eigen::Matrix<double, 6, 1>() << 2, 2, 2, 1.25, 1.0, 1.0 / 1.3).finished();
  EXPECT_LT((k - expected).norm(), 1e-12) << k.transpose();
  EXPECT_TRUE(m.k->allFinite());
  // Null A (a station that could not be evaluated): no metric, gain NaN.
  const PoseMetric none = PoseMetricOf(std::nullopt, 2.0);
  EXPECT_FALSE(none.k.has_value());
  EXPECT_TRUE(std::isnan(none.gain));
}

// What the metric is for: at a station whose report the model's inverse resolves, K = A^-1 maps
// the fit's report-space residual onto the residual of the pose the runtime inverse finds (the
// pose error a calibration is judged by), to first order in the misfit. Here the reference is 1 mm
// and 0.1 deg off that pose, 0.33 m from a strong object, so the two residuals differ (A is far
// from I) and agree after K.
TEST(ReportPerPose, MapsTheReportResidualOntoThePoseResidual) {
  ModelSpec spec = ParseModelYaml(R"(noise: {position_mm: 0.5, orientation_deg: 0.1}
terms:
  - type: sensor_offset
    receiver_from_body:
      rotation_xyzw: [0.1, -0.05, 0.02, 0.99369]
      translation: [0.02, 0.01, -0.03]
  - type: dipole
    location_in_transmitter: [0.55, 0.05, -0.6]
    polarisability_m3: 0.002
)",
                                  "metric.yaml");
  FitStation station;
  station.reported = Rigid3d(
      Eigen::Quaterniond(Eigen::AngleAxisd(0.6, Eigen::Vector3d(1, -2, 1).normalized())),
      Eigen::Vector3d(0.3, -0.15, -0.5));
  spec.terms[0]->Prepare({station});
  const CorrectedPose runtime = spec.terms[0]->ToCorrection()->Apply(station.reported);
  ASSERT_EQ(runtime.status, CorrectionStatus::kConverged);
  const Eigen::Vector3d dp(0.0006, -0.0005, 0.0006);
  const Eigen::Quaterniond dq(
      Eigen::AngleAxisd(0.1 * M_PI / 180, Eigen::Vector3d(0, 1, 1).normalized()));
  station.reference = Rigid3d(runtime.pose.rotation * dq, runtime.pose.translation + dp);
  Eigen::Matrix<double, 6, 1> r;
  std::vector<Eigen::MatrixXd> unused;
  std::optional<Matrix6> a;
  ASSERT_TRUE(EvaluateStationResidual(spec, station, std::nullopt, &r, &unused, &a));
  ASSERT_TRUE(a.has_value());
  // The pose residual of the runtime's pose, as the fit's StationResidual.
  const AmbientPose pose = ToAmbient(runtime.pose);
  Eigen::Matrix<double, 6, 1> r_pose;
  StationResidual<double>(pose.data(), station.reference, 0.0005, 0.1 * M_PI / 180,
                          r_pose.data());
  const Eigen::Matrix<double, 6, 1> mapped = a->inverse() * r;
  // First order in a 1 mm misfit 0.33 m from the object: the second-order terms measured 0.4 %
  // relative (the raw residual 19 %).
  EXPECT_LT((mapped - r_pose).norm(), 0.02 * r_pose.norm())
      << "A^-1 r " << mapped.transpose() << "\nr_pose " << r_pose.transpose();
  // The test can fail: without the metric the two differ.
  EXPECT_GT((r - r_pose).norm(), 0.1 * r_pose.norm()) << "r " << r.transpose();
}

}  // namespace
}  // namespace trackcal::fit
