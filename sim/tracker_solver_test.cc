#include "core/tracker_solver.h"

#include <gtest/gtest.h>

#include <cmath>
#include <vector>

#include "core/field.h"
#include "sim/random.h"
#include "sim/scene.h"
#include "sim/simulator.h"
#include "tests/test_utils.h"

namespace trackcal::sim {
namespace {

using testing::PosesNear;
using testing::RandomRotation;
using testing::TestRng;

Eigen::Matrix3d FreeSpaceSignal(const Rigid3d& pose, double k = 1.0) {
  return SignalMatrix<double>(Eigen::Matrix3d::Identity(), pose.rotation.toRotationMatrix(),
                              k * DipoleCoupling<double>(pose.translation));
}

Rigid3d RandomPoseInHemisphere(const Eigen::Vector3d& h, double r_min, double r_max) {
  std::uniform_real_distribution<double> u(-1, 1);
  std::uniform_real_distribution<double> ur(r_min, r_max);
  Eigen::Vector3d dir;
  do {
    dir = Eigen::Vector3d(u(TestRng()), u(TestRng()), u(TestRng()));
  } while (dir.norm() > 1 || dir.norm() < 0.1 || std::abs(dir.normalized().dot(h)) < 0.05);
  dir.normalize();
  if (dir.dot(h) < 0) dir = -dir;
  return Rigid3d(RandomRotation(TestRng()), ur(TestRng()) * dir);
}

TEST(SolveFreeSpacePose, Nominal) {
  TrackerSolverOptions options;
  options.field_constant = 2.5;
  for (int i = 0; i < 200; ++i) {
    const Rigid3d truth = RandomPoseInHemisphere(Eigen::Vector3d::UnitX(), 0.05, 3.0);
    const TrackerSolution s = SolveFreeSpacePose(FreeSpaceSignal(truth, 2.5), options);
    EXPECT_TRUE(s.converged);
    // The requirement: the truth to 1e-9 without distortion or noise.
    EXPECT_TRUE(PosesNear(truth, s.transmitter_from_receiver, 1e-9, 1e-9));
    // The closed form alone is already exact on free-space data (rounding only).
    EXPECT_TRUE(PosesNear(truth, s.closed_form, 1e-9, 1e-9));
  }
}

TEST(SolveFreeSpacePose, HemisphereChoice) {
  const Rigid3d truth(RandomRotation(TestRng()), Eigen::Vector3d(-0.4, 0.2, 0.3));
  // Default H1,0,0: a receiver at -x is reported at -p with the right orientation.
  const TrackerSolution plus_x = SolveFreeSpacePose(FreeSpaceSignal(truth));
  EXPECT_TRUE(PosesNear(Rigid3d(truth.rotation, -truth.translation),
                        plus_x.transmitter_from_receiver, 1e-9, 1e-9));
  TrackerSolverOptions minus_x;
  minus_x.hemisphere_in_transmitter = Eigen::Vector3d(-1, 0, 0);
  EXPECT_TRUE(PosesNear(
      truth, SolveFreeSpacePose(FreeSpaceSignal(truth), minus_x).transmitter_from_receiver, 1e-9,
      1e-9));
  // Any hemisphere vector: up (-z in a Fastrak frame) keeps z <= 0.
  TrackerSolverOptions up;
  up.hemisphere_in_transmitter = Eigen::Vector3d(0.1, 0, -1);
  for (int i = 0; i < 50; ++i) {
    const Rigid3d t = RandomPoseInHemisphere(up.hemisphere_in_transmitter.normalized(), 0.1, 2.0);
    const Rigid3d mirrored(t.rotation, -t.translation);
    EXPECT_TRUE(
        PosesNear(t, SolveFreeSpacePose(FreeSpaceSignal(mirrored), up).transmitter_from_receiver,
                  1e-9, 1e-9));
  }
}

TEST(SolveFreeSpacePose, ExactInEveryOctantOnTheAxesAndFromCentimetresTo100Metres) {
  // Every octant, exactly on each axis (where two eigenvalues of S^T S coincide) and just off it,
  // from 1 cm to 100 m (the signal spans 18 orders of magnitude), for three hemispheres: the report
  // is the truth or, outside the hemisphere, its mirror -p with the same orientation (D(-p) =
  // D(p)).
  std::uniform_real_distribution<double> u(0.05, 1.0);
  const std::vector<Eigen::Vector3d> hemispheres = {
      Eigen::Vector3d::UnitX(), Eigen::Vector3d(0, 0, -1), Eigen::Vector3d(0.3, -1, 0.2)};
  for (const double r : {0.01, 0.2, 1.0, 3.0, 100.0}) {
    for (int octant = 0; octant < 8; ++octant) {
      for (int axis = -1; axis < 3; ++axis) {
        for (int variant = 0; variant < 2; ++variant) {
          Eigen::Vector3d d(u(TestRng()), u(TestRng()), u(TestRng()));
          if (axis >= 0) {
            d = Eigen::Vector3d::Unit(axis);
            if (variant == 1) d += 1e-6 * Eigen::Vector3d(u(TestRng()), u(TestRng()), u(TestRng()));
          }
          for (int i = 0; i < 3; ++i) {
            if ((octant >> i) & 1) d(i) = -d(i);
          }
          const Rigid3d truth(RandomRotation(TestRng()), r * d.normalized());
          for (const Eigen::Vector3d& h : hemispheres) {
            // On the hemisphere's plane the two solutions are equally valid.
            if (std::abs(truth.translation.dot(h.normalized())) < 1e-3 * r) continue;
            TrackerSolverOptions options;
            options.hemisphere_in_transmitter = h;
            const TrackerSolution s = SolveFreeSpacePose(FreeSpaceSignal(truth), options);
            EXPECT_TRUE(s.converged);
            const Rigid3d expected(truth.rotation, truth.translation.dot(h) >= 0
                                                       ? truth.translation
                                                       : Eigen::Vector3d(-truth.translation));
            // Relative to the range: the closed form is exact to rounding (measured 1e-15).
            EXPECT_TRUE(PosesNear(expected, s.transmitter_from_receiver, 1e-12 * r, 1e-12))
                << "r " << r << " octant " << octant << " axis " << axis;
          }
        }
      }
    }
  }
}

TEST(SolveFreeSpacePose, DegenerateSignalIsNotConverged) {
  EXPECT_FALSE(SolveFreeSpacePose(Eigen::Matrix3d::Zero()).converged);
  Eigen::Matrix3d nan = Eigen::Matrix3d::Identity();
  nan(1, 2) = std::nan("");
  EXPECT_FALSE(SolveFreeSpacePose(nan).converged);
  TrackerSolverOptions bad;
  bad.hemisphere_in_transmitter = Eigen::Vector3d::Zero();
  EXPECT_THROW(SolveFreeSpacePose(Eigen::Matrix3d::Identity(), bad), std::invalid_argument);
}

TEST(SolveFreeSpacePose, RefinementFitsDistortedSignalBetterThanClosedForm) {
  // With a receiver gain error the closed form is only approximate; the refined pose is the
  // least-squares free-space explanation of S, so its residual is never larger.
  Eigen::Matrix3d g = Eigen::Matrix3d::Identity();
  g(0, 0) = 1.05;
  g(1, 2) = 0.03;
  for (int i = 0; i < 20; ++i) {
    const Rigid3d truth = RandomPoseInHemisphere(Eigen::Vector3d::UnitX(), 0.2, 1.5);
    const Eigen::Matrix3d s = SignalMatrix<double>(g, truth.rotation.toRotationMatrix(),
                                                   DipoleCoupling<double>(truth.translation));
    const TrackerSolution sol = SolveFreeSpacePose(s);
    const auto residual = [&](const Rigid3d& p) {
      return (s - p.rotation.toRotationMatrix().transpose() * DipoleCoupling<double>(p.translation))
          .norm();
    };
    EXPECT_TRUE(sol.converged);
    EXPECT_LE(residual(sol.transmitter_from_receiver), residual(sol.closed_form) + 1e-15);
    EXPECT_NEAR(sol.residual_norm, residual(sol.transmitter_from_receiver), 1e-12);
  }
}

TEST(TrackerModel, PositionJitterGrowsAsRToTheFourth) {
  // Constant noise on S: dS/dp ~ 3k / r^4, so position jitter ~ sigma r^4 / (3k).
  const TrackerModel tracker(FieldModel{}, Eigen::Matrix3d::Identity(), 1e-4, {});
  Rng rng(7, "jitter");
  const std::vector<double> radii = {0.3, 0.6, 1.2};
  std::vector<double> jitter;
  const Eigen::Quaterniond q = RandomRotation(TestRng());
  for (double r : radii) {
    const Rigid3d truth(q, r * Eigen::Vector3d(1, 1, 0.5).normalized());
    double sum2 = 0;
    const int n = 2000;
    for (int i = 0; i < n; ++i) {
      sum2 +=
          (tracker.Report(truth, 1, &rng).transmitter_from_receiver.translation - truth.translation)
              .squaredNorm();
    }
    jitter.push_back(std::sqrt(sum2 / n));
  }
  const double slope =
      std::log(jitter.back() / jitter.front()) / std::log(radii.back() / radii.front());
  // An RMS from 2000 samples is within ~2% (1/sqrt(2n)); over a factor 4 in r that moves the slope
  // by about 0.03. 0.15 leaves room and still rejects r^3 or r^5.
  EXPECT_NEAR(slope, 4.0, 0.15);
  const double mid_slope = std::log(jitter[1] / jitter[0]) / std::log(2.0);
  EXPECT_NEAR(mid_slope, 4.0, 0.2);
}

}  // namespace
}  // namespace trackcal::sim

namespace trackcal::sim {
namespace {

TEST(SolvePoseInField, InvertsTheDistortedModel) {
  // The paper room: the free-space solver is centimetres off, the full model recovers the truth.
  const Scene paper = LoadScene("paper");
  Eigen::Matrix3d g = Eigen::Matrix3d::Identity();
  g(0, 1) = 0.01;
  g(2, 2) = 0.98;
  const TrackerModel tracker(
      paper.environment, g, 0.0,
      {.hemisphere_in_transmitter = paper.tracker.hemisphere_in_transmitter});
  double worst_free = 0;
  double worst_reconstructed = 0;
  int max_iterations = 0;
  for (int i = 0; i < 50; ++i) {
    const Rigid3d truth = RandomPoseInHemisphere(Eigen::Vector3d(0, 0, -1), 0.3, 1.3);
    const Eigen::Matrix3d s = tracker.Signal(truth);
    const TrackerSolution reported = SolveFreeSpacePose(s, tracker.solver_options());
    worst_free = std::max(worst_free, PositionErrorNorm(truth, reported.transmitter_from_receiver));
    const TrackerSolution inverted =
        SolvePoseInField(s, paper.environment, g, reported.transmitter_from_receiver);
    EXPECT_TRUE(inverted.converged);
    // Exact data, exact model: the truth to rounding through a well-conditioned 6x6 solve.
    EXPECT_TRUE(PosesNear(truth, inverted.transmitter_from_receiver, 1e-9, 1e-9));
    // A runtime correction only has the report, not S: rebuilding S from the report as a
    // free-space signal drops the free-space fit residual, so the inverse is approximate.
    const Rigid3d& rep = reported.transmitter_from_receiver;
    const Eigen::Matrix3d s_rep =
        rep.rotation.toRotationMatrix().transpose() * DipoleCoupling<double>(rep.translation);
    const TrackerSolution approx = SolvePoseInField(s_rep, paper.environment, g, rep);
    worst_reconstructed =
        std::max(worst_reconstructed, PositionErrorNorm(truth, approx.transmitter_from_receiver));
    // The exact inverse of the report.
    const TrackerSolution exact =
        InvertReportedPose(rep, paper.environment, g, tracker.solver_options());
    EXPECT_TRUE(exact.converged);
    // Fixed point to 1e-12 per step; the 1e-9 of the round trip bounds the rest.
    EXPECT_TRUE(PosesNear(truth, exact.transmitter_from_receiver, 1e-9, 1e-9)) << exact.iterations;
    max_iterations = std::max(max_iterations, exact.iterations);
  }
  EXPECT_GT(worst_free, 0.01);  // the distortion is real (centimetres)
  // Rebuilding S from the report is not a correction (documented in InvertReportedPose).
  EXPECT_GT(worst_reconstructed, 0.005);
  std::printf(
      "free-space worst %.2f mm, S rebuilt from the report worst %.3f mm, exact inverse in <= %d "
      "iterations\n",
      1e3 * worst_free, 1e3 * worst_reconstructed, max_iterations);
}

}  // namespace
}  // namespace trackcal::sim
