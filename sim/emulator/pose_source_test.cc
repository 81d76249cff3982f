#include "sim/emulator/pose_source.h"

#include <gtest/gtest.h>

#include <fstream>

#include "sim/random.h"
#include "tests/test_utils.h"

namespace trackcal::emulator {
namespace {

std::filesystem::path WriteFile(const std::string& name, const std::string& text) {
  const std::filesystem::path path = testing::MakeTempDir("pose_source") / name;
  std::ofstream(path) << text;
  return path;
}

std::string ErrorOf(const std::filesystem::path& path) {
  try {
    TrajectoryPoseSource::ReadCsv(path, false);
  } catch (const std::invalid_argument& e) {
    return e.what();
  }
  return "";
}

TEST(TrajectoryPoseSource, Nominal) {
  const auto path = WriteFile("traj.csv",
                              "# two keyframes for station 1, one for station 2\n"
                              "qz, qy, qx, qw, z, y, x, station, t, button\n"
                              "0,0,0,1, 0,0,0.3, 1, 0.0, 0\n"
                              "0.7071067811865476,0,0,0.7071067811865476, 0,0.2,0.3, 1, 2.0, 1\n"
                              "\n"
                              "0,0,0,1, 0.1,0.1,0.1, 2, 0.5, 0\n");
  auto source = TrajectoryPoseSource::ReadCsv(path, false);
  ASSERT_EQ(source->num_stations(), 2);
  // Before the first keyframe: held.
  EXPECT_TRUE(testing::PosesNear(Rigid3d(Eigen::Quaterniond::Identity(), {0.3, 0, 0}),
                                 source->TruePose(1, -1.0), 1e-12, 1e-12));
  // Halfway: linear position, slerp rotation (45 degrees of the 90 about z).
  const Rigid3d mid = source->TruePose(1, 1.0);
  const Rigid3d expected(Eigen::Quaterniond(Eigen::AngleAxisd(M_PI / 4, Eigen::Vector3d::UnitZ())),
                         {0.3, 0.1, 0});
  // Exact arithmetic up to rounding of the 1/sqrt(2) inputs (1e-12).
  EXPECT_TRUE(testing::PosesNear(expected, mid, 1e-12, 1e-12));
  EXPECT_FALSE(source->StylusButton(1, 1.0));
  EXPECT_TRUE(source->StylusButton(1, 2.0));
  EXPECT_TRUE(source->StylusButton(1, 5.0));
  EXPECT_TRUE(testing::PosesNear(Rigid3d(Eigen::Quaterniond::Identity(), {0.1, 0.1, 0.1}),
                                 source->TruePose(2, 100.0), 1e-12, 1e-12));
}

TEST(TrajectoryPoseSource, Loop) {
  std::vector<std::vector<TrajectoryKeyframe>> frames(1);
  frames[0].resize(2);
  frames[0][0].t_s = 1.0;
  frames[0][1].t_s = 3.0;
  frames[0][1].transmitter_from_receiver.translation = {0.2, 0, 0};
  TrajectoryPoseSource source(frames, /*loop=*/true);
  // Period 2 s starting at t = 1: t = 6 is 1 s into a cycle.
  EXPECT_NEAR(source.TruePose(1, 6.0).translation.x(), 0.1, 1e-12);
  EXPECT_NEAR(source.TruePose(1, 0.5).translation.x(), 0.15, 1e-12);
}

TEST(TrajectoryPoseSource, ErrorsNameFileLineField) {
  EXPECT_NE(ErrorOf(WriteFile("a.csv", "t,station,x,y,z,qw,qx,qy\n")).find("missing column 'qz'"),
            std::string::npos);
  const std::string bad_number = ErrorOf(
      WriteFile("b.csv", "t,station,x,y,z,qw,qx,qy,qz\n0,1,0,0,0,1,0,0,0\n1,1,abc,0,0,1,0,0,0\n"));
  EXPECT_NE(bad_number.find("b.csv:3"), std::string::npos) << bad_number;
  EXPECT_NE(bad_number.find("'x'"), std::string::npos) << bad_number;
  const std::string bad_time = ErrorOf(
      WriteFile("c.csv", "t,station,x,y,z,qw,qx,qy,qz\n1,1,0,0,0,1,0,0,0\n1,1,0,0,0,1,0,0,0\n"));
  EXPECT_NE(bad_time.find("c.csv:3: field 't'"), std::string::npos) << bad_time;
  const std::string bad_station =
      ErrorOf(WriteFile("d.csv", "t,station,x,y,z,qw,qx,qy,qz\n1,5,0,0,0,1,0,0,0\n"));
  EXPECT_NE(bad_station.find("field 'station'"), std::string::npos) << bad_station;
  const std::string gap =
      ErrorOf(WriteFile("e.csv", "t,station,x,y,z,qw,qx,qy,qz\n1,2,0,0,0,1,0,0,0\n"));
  EXPECT_NE(gap.find("station 1 has no keyframe"), std::string::npos) << gap;
  const std::string zero_q =
      ErrorOf(WriteFile("f.csv", "t,station,x,y,z,qw,qx,qy,qz\n1,1,0,0,0,0,0,0,0\n"));
  EXPECT_NE(zero_q.find("zero quaternion"), std::string::npos) << zero_q;
  const std::string short_row =
      ErrorOf(WriteFile("g.csv", "t,station,x,y,z,qw,qx,qy,qz\n1,1,0,0\n"));
  EXPECT_NE(short_row.find("g.csv:2: expected 9 fields"), std::string::npos) << short_row;
  // The system's reason, and a folder named as one (it opened as a stream and read as a file
  // without a header).
  EXPECT_EQ(ErrorOf("/nonexistent/traj.csv"),
            "/nonexistent/traj.csv: cannot open trajectory file: No such file or directory");
  const auto folder = testing::MakeTempDir("pose_source");
  EXPECT_EQ(ErrorOf(folder), folder.string() + ": is a folder, not a trajectory file");
}

TEST(ControlledPoseSource, MoveOverridesUntilReleased) {
  const Rigid3d base_pose(Eigen::Quaterniond::Identity(), {0.3, 0, 0});
  ControlledPoseSource source(std::make_unique<StaticPoseSource>(std::vector<Rigid3d>{base_pose}));
  const Rigid3d moved(testing::RandomRotation(testing::TestRng()), {0.1, 0.2, -0.1});
  source.Move(1, moved);
  source.SetButton(1, true);
  EXPECT_TRUE(testing::PosesNear(moved, source.TruePose(1, 0), 0, 0));
  EXPECT_TRUE(source.StylusButton(1, 0));
  source.Release(1);
  EXPECT_TRUE(testing::PosesNear(base_pose, source.TruePose(1, 0), 0, 0));
  EXPECT_FALSE(source.StylusButton(1, 0));
  EXPECT_THROW(source.Move(5, moved), std::out_of_range);
}

TEST(NoisyMeasurement, Statistics) {
  NoisyMeasurement model(nullptr, 0.001, 0.002, /*seed=*/7);
  const Rigid3d truth(testing::RandomRotation(testing::TestRng()), {0.3, 0.1, -0.2});
  constexpr int kSamples = 20000;
  Eigen::Vector3d sum = Eigen::Vector3d::Zero();
  double sum_sq = 0, angle_sq = 0;
  for (int i = 0; i < kSamples; ++i) {
    const Rigid3d r = model.Reported(1, truth, 0.0);
    const Eigen::Vector3d d = r.translation - truth.translation;
    sum += d;
    sum_sq += d.squaredNorm();
    angle_sq += std::pow(AngularDistance(r.rotation, truth.rotation), 2);
  }
  // Mean ~0 (std of the mean 1e-3/sqrt(2e4) = 7e-6 m per axis; 5 sigma); per-axis variance 1e-6 m^2
  // and per-axis rotation variance 4e-6 rad^2 within 3 % (the variance estimate's relative std is
  // sqrt(2/(3*2e4)) = 0.6 %).
  EXPECT_LT(sum.norm() / kSamples, 3.5e-5);
  EXPECT_NEAR(sum_sq / kSamples / 3, 1e-6, 3e-8);
  EXPECT_NEAR(angle_sq / kSamples / 3, 4e-6, 1.2e-7);
  // Same seed, same numbers.
  NoisyMeasurement a(nullptr, 0.001, 0.002, 9), b(nullptr, 0.001, 0.002, 9);
  EXPECT_TRUE(testing::PosesNear(a.Reported(1, truth, 0), b.Reported(1, truth, 0), 0, 0));
  EXPECT_THROW(NoisyMeasurement(nullptr, -1, 0, 1), std::invalid_argument);
}

// --seed promises reproducible streams: the extra noise comes from the portable named streams of
// sim/random.h (std::normal_distribution differs between standard libraries), so the numbers are
// the same with every compiler.
TEST(NoisyMeasurement, DrawsFromThePortableSeededStream) {
  NoisyMeasurement model(nullptr, 0.001, 0.002, /*seed=*/9);
  const Rigid3d truth(QuaternionFromWxyz(0.9, 0.1, -0.3, 0.2).normalized(), {0.3, 0.1, -0.2});
  sim::Rng rng(9, "emulator_measurement_noise");
  for (int i = 0; i < 3; ++i) {
    const Eigen::Vector3d dp = 0.001 * rng.Normal3();
    const Eigen::Vector3d w = 0.002 * rng.Normal3();
    Rigid3d expected = truth;
    expected.translation += dp;
    expected.rotation =
        (Eigen::Quaterniond(Eigen::AngleAxisd(w.norm(), w.normalized())) * truth.rotation)
            .normalized();
    EXPECT_TRUE(testing::PosesNear(expected, model.Reported(1, truth, 0.0), 1e-15, 1e-15)) << i;
  }
}

TEST(Measure, AppliesModelToTruePose) {
  struct Offset final : MeasurementModel {
    Rigid3d Reported(int station, const Rigid3d& true_pose, double t_s) override {
      Rigid3d r = true_pose;
      r.translation.x() += 0.01 * station + t_s;
      return r;
    }
  } model;
  StaticPoseSource source({Rigid3d(), Rigid3d()});
  const StationMeasurement m = Measure(source, model, 2, 0.5);
  EXPECT_DOUBLE_EQ(m.transmitter_from_receiver.translation.x(), 0.52);
}

}  // namespace
}  // namespace trackcal::emulator
