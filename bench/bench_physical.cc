// Cost of correcting one pose with the physical model ("type": "physical",
// core/physical_correction.h) against the degree-4 polynomial correction in the same binary (the
// baseline). The physical model is the paper room (two planes, four induced dipoles) plus finite
// transmitter coils, a fifth object and a skewed receiver, with a sensor offset: every term the
// runtime inverse evaluates. Poses are noise-free reports of true poses in the paper's volume,
// cycled so the inputs are not constant. Target: at most 10 us per pose (the issue); report the
// ratio to BM_Polynomial4.
//
//   build/bench/bench_physical --benchmark_min_time=0.5
#include <benchmark/benchmark.h>

#include <random>
#include <vector>

#include "core/physical_correction.h"
#include "core/polynomial.h"
#include "core/tracker_solver.h"

namespace trackcal {
namespace {

constexpr size_t kNumPoses = 1024;

FieldModel RoomField() {
  FieldModel field;
  field.transmitter_octupole_m2 = Eigen::Vector3d(-0.000675, -0.0006, -0.00075);
  field.planes.push_back({"floor", Eigen::Vector3d(0, 0, 0.8), Eigen::Vector3d(0, 0, 1), 0.27});
  field.planes.push_back({"door", Eigen::Vector3d(0, -2.1, 0), Eigen::Vector3d(0, 1, 0), 0.18});
  field.objects.push_back({"crt1", Eigen::Vector3d(1.6, 1.0, -0.5), 0.04});
  field.objects.push_back({"crt2", Eigen::Vector3d(0.5, 1.8, -0.5), 0.04});
  field.objects.push_back({"crt3", Eigen::Vector3d(-1.5, 1.2, -0.4), 0.04});
  field.objects.push_back({"frame", Eigen::Vector3d(0.5, 0.0, 0.35), -0.009});
  field.objects.push_back({"toolbox", Eigen::Vector3d(0.6, 0.95, -0.5), 0.002});
  return field;
}

Eigen::Matrix3d Gain() {
  Eigen::Matrix3d g;
  g << 1.03, 0.01, -0.02, 0.0, 0.97, 0.015, 0.01, -0.01, 1.01;
  return g;
}

const std::vector<Rigid3d>& Reports() {
  static const std::vector<Rigid3d> reports = [] {
    std::vector<Rigid3d> out;
    std::mt19937_64 rng(5);
    std::uniform_real_distribution<double> x(-0.8, 0.8), y(-0.6, 0.6), z(-0.8, -0.35);
    std::normal_distribution<double> n(0.0, 1.0);
    TrackerSolverOptions solver;
    solver.hemisphere_in_transmitter = Eigen::Vector3d(0, 0, -1);
    const FieldModel field = RoomField();
    while (out.size() < kNumPoses) {
      const Eigen::Quaterniond q = QuaternionFromXyzw(n(rng), n(rng), n(rng), n(rng)).normalized();
      const Eigen::Vector3d p(x(rng), y(rng), z(rng));
      const TrackerSolution s = SolveFreeSpacePose(
          SignalMatrix<double>(Gain(), q.toRotationMatrix(), field.Field<double>(p)), solver);
      if (s.converged) out.push_back(s.transmitter_from_receiver);
    }
    return out;
  }();
  return reports;
}

template <typename C>
void RunPerPose(benchmark::State& state, const C& correction) {
  const std::vector<Rigid3d>& reports = Reports();
  size_t i = 0;
  for (auto _ : state) {
    benchmark::DoNotOptimize(correction.Apply(reports[i]));
    i = (i + 1) % reports.size();
  }
}

void BM_Polynomial4(benchmark::State& state) {  // baseline
  std::mt19937_64 rng(11);
  std::normal_distribution<double> n(0.0, 0.005);
  std::vector<double> c(6 * NumPolynomialTerms(4));
  for (double& v : c) v = n(rng);
  const PolynomialCorrection poly(4, Eigen::Vector3d(0, 0, -0.55), Eigen::Vector3d(0.9, 0.8, 0.3),
                                  c);
  RunPerPose(state, poly);
}
BENCHMARK(BM_Polynomial4);

void BM_PhysicalPaperRoom(benchmark::State& state) {
  const PhysicalCorrection physical(
      RoomField(), Gain(),
      Rigid3d(Eigen::Quaterniond(Eigen::AngleAxisd(0.05, Eigen::Vector3d::UnitX())),
              Eigen::Vector3d(0.01, 0.0, 0.02)));
  RunPerPose(state, physical);
  double iterations = 0;
  for (const Rigid3d& reported : Reports()) {
    Rigid3d x;
    int n = 0;
    physical.InvertReport(reported, &x, &n);
    iterations += n;
  }
  state.counters["newton_steps"] = iterations / Reports().size();  // mean steps per pose
}
BENCHMARK(BM_PhysicalPaperRoom);

void BM_PhysicalFreeSpace(benchmark::State& state) {  // the inverse's fixed cost
  const PhysicalCorrection physical(FieldModel{}, Eigen::Matrix3d::Identity());
  RunPerPose(state, physical);
}
BENCHMARK(BM_PhysicalFreeSpace);

}  // namespace
}  // namespace trackcal

BENCHMARK_MAIN();
