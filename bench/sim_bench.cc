// Cost of the physics per pose, as ratios against the free-space dipole field in the same run:
// the paper room's full field model (what fit/ differentiates, core/ inverts), the tracker's
// free-space solve (what the simulator and emulator run per sample), and the exact inverse of a
// report (what a physical-model correction runs per pose).
#include <benchmark/benchmark.h>

#include "sim/field.h"
#include "sim/scene.h"
#include "sim/simulator.h"
#include "sim/tracker_solver.h"

namespace {

using trackcal::Rigid3d;
namespace sim = trackcal::sim;

const Eigen::Vector3d kPoint(0.4, -0.3, -0.6);

void BM_FreeSpaceField(benchmark::State& state) {  // baseline
  Eigen::Vector3d p = kPoint;
  for (auto _ : state) {
    benchmark::DoNotOptimize(p);
    benchmark::DoNotOptimize(sim::DipoleCoupling<double>(p));
  }
}
BENCHMARK(BM_FreeSpaceField);

void BM_PaperRoomField(benchmark::State& state) {
  const sim::FieldModel model = sim::LoadScene("paper").environment;
  Eigen::Vector3d p = kPoint;
  for (auto _ : state) {
    benchmark::DoNotOptimize(p);
    benchmark::DoNotOptimize(model.Field<double>(p));
  }
}
BENCHMARK(BM_PaperRoomField);

void BM_FreeSpaceSolve(benchmark::State& state) {
  const sim::Simulator simulator(sim::LoadScene("paper"));
  const Rigid3d truth(
      Eigen::Quaterniond(Eigen::AngleAxisd(0.7, Eigen::Vector3d(1, 2, 3).normalized())), kPoint);
  const Eigen::Matrix3d s = simulator.tracker().Signal(truth);
  for (auto _ : state) {
    benchmark::DoNotOptimize(sim::SolveFreeSpacePose(s, simulator.tracker().solver_options()));
  }
}
BENCHMARK(BM_FreeSpaceSolve);

void BM_InvertReportedPose(benchmark::State& state) {
  const sim::Simulator simulator(sim::LoadScene("paper"));
  const Rigid3d truth(
      Eigen::Quaterniond(Eigen::AngleAxisd(0.7, Eigen::Vector3d(1, 2, 3).normalized())), kPoint);
  const Rigid3d reported = simulator.tracker().Report(truth).transmitter_from_receiver;
  for (auto _ : state) {
    benchmark::DoNotOptimize(sim::InvertReportedPose(reported, simulator.tracker().field(),
                                                     simulator.tracker().receiver_gain_matrix(),
                                                     simulator.tracker().solver_options()));
  }
}
BENCHMARK(BM_InvertReportedPose);

}  // namespace

BENCHMARK_MAIN();
