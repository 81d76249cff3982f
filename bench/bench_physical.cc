// Cost of correcting one pose with the physical model ("type": "physical",
// core/physical_correction.h) against the degree-4 polynomial correction in the same binary (the
// baseline). The physical model is the paper room (two planes, four induced dipoles) plus finite
// transmitter coils, a fifth object and a skewed receiver, with a sensor offset: every term the
// runtime inverse evaluates. Poses are noise-free reports of true poses in the paper's volume,
// cycled so the inputs are not constant. Target: at most 10 us per pose (the issue); report the
// ratio to BM_Polynomial4, and the bounded inverse's ratio to BM_PreBoundedInverse: the plain
// Newton inverse as it was before the bounded inverse (no domain, trust region or status), kept
// here as the baseline of what bounding and the status cost.
//
//   build/bench/bench_physical --benchmark_min_time=0.5
#include <benchmark/benchmark.h>
#include <ceres/jet.h>

#include <Eigen/Eigenvalues>
#include <Eigen/LU>
#include <random>
#include <vector>

#include "bench/paper_room.h"
#include "core/physical_correction.h"
#include "core/polynomial.h"
#include "core/tracker_solver.h"

namespace trackcal {
namespace {

constexpr size_t kNumPoses = 1024;

const std::vector<Rigid3d>& Reports() {
  static const std::vector<Rigid3d> reports = [] {
    std::vector<Rigid3d> out;
    std::mt19937_64 rng(5);
    std::uniform_real_distribution<double> x(-0.8, 0.8), y(-0.6, 0.6), z(-0.8, -0.35);
    std::normal_distribution<double> n(0.0, 1.0);
    TrackerSolverOptions solver;
    solver.hemisphere_in_transmitter = Eigen::Vector3d(0, 0, -1);
    const FieldModel field = PaperRoomField();
    while (out.size() < kNumPoses) {
      const Eigen::Quaterniond q = QuaternionFromXyzw(n(rng), n(rng), n(rng), n(rng)).normalized();
      const Eigen::Vector3d p(x(rng), y(rng), z(rng));
      const TrackerSolution s = SolveFreeSpacePose(
          SignalMatrix<double>(PaperRoomGain(), q.toRotationMatrix(), field.Field<double>(p)),
          solver);
      if (s.converged) out.push_back(s.transmitter_from_receiver);
    }
    return out;
  }();
  return reports;
}

// The pre-bounded inverse (core/physical_correction.cc before the bounded inverse): Newton on the
// tracker's normal equations J_y^T (S(x) - S_free(y)) = 0 from x = y, full steps, no status. The
// same arithmetic as PhysicalCorrection::NormalEquations, so the two differ only by what bounding
// and the status add.
class PreBoundedInverse {
 public:
  PreBoundedInverse(const FieldModel& field, const Eigen::Matrix3d& gain,
                    const Rigid3d& receiver_from_body)
      : field_(field), gain_(gain), receiver_from_body_(receiver_from_body) {
    const double k = field.field_constant;
    for (const ConductingPlane& plane : field.planes) {
      const Eigen::Vector3d n = plane.normal_in_transmitter.normalized();
      Eigen::Matrix3d moment = -(2.0 * plane.attenuation) * (n * n.transpose());
      moment.diagonal().array() += plane.attenuation;
      sources_.push_back({(2.0 * plane.point_in_transmitter.dot(n)) * n, k * moment});
    }
    for (const InducedDipole& object : field.objects) {
      sources_.push_back({object.location_in_transmitter,
                          (k * object.polarisability_m3) *
                              DipoleCoupling<double>(object.location_in_transmitter)});
    }
  }

  CorrectedPose Apply(const Rigid3d& reported) const {
    using Jet6 = ceres::Jet<double, 6>;
    using Jet3 = ceres::Jet<double, 3>;
    using Matrix6 = Eigen::Matrix<double, 6, 6>;
    using Vector6 = Eigen::Matrix<double, 6, 1>;
    using Vector9 = Eigen::Matrix<double, 9, 1>;
    using Matrix96 = Eigen::Matrix<double, 9, 6>;
    const double k = field_.field_constant;
    const Eigen::Matrix3d rotation_y = reported.rotation.normalized().toRotationMatrix();
    // S_free(y) and its Jacobian by a 6-slot Jet (position slots 0..2, rotation 3..5).
    Vector3<Jet6> pj;
    for (int i = 0; i < 3; ++i) pj(i) = Jet6(reported.translation(i), i);
    Matrix3<Jet6> exp_minus_w = Matrix3<Jet6>::Identity();
    const Jet6 w0(0.0, 3), w1(0.0, 4), w2(0.0, 5);
    exp_minus_w(0, 1) = w2;
    exp_minus_w(0, 2) = -w1;
    exp_minus_w(1, 0) = -w2;
    exp_minus_w(1, 2) = w0;
    exp_minus_w(2, 0) = w1;
    exp_minus_w(2, 1) = -w0;
    const Matrix3<Jet6> s_free_jet =
        exp_minus_w * rotation_y.transpose().cast<Jet6>() * (Jet6(k) * DipoleCoupling<Jet6>(pj));
    Vector9 s_free;
    Matrix96 j_free;
    for (int c = 0; c < 3; ++c) {
      for (int r = 0; r < 3; ++r) {
        s_free(3 * c + r) = s_free_jet(r, c).a;
        j_free.row(3 * c + r) = s_free_jet(r, c).v.transpose();
      }
    }
    const Eigen::Matrix<double, 6, 9> j_free_t = j_free.transpose();
    Eigen::Vector3d p = reported.translation;
    Eigen::Matrix3d rotation = rotation_y;
    for (int it = 0; it < 8; ++it) {
      Vector3<Jet3> pj3;
      for (int i = 0; i < 3; ++i) pj3(i) = Jet3(p(i), i);
      Matrix3<Jet3> b =
          TransmitterField<Jet3>(Jet3(k), field_.transmitter_octupole_m2.cast<Jet3>(), pj3);
      for (const Source& source : sources_) {
        const Matrix3<Jet3> d = DipoleCoupling<Jet3>(pj3 - source.center.cast<Jet3>());
        for (int c = 0; c < 3; ++c) {
          for (int r = 0; r < 3; ++r) {
            b(r, c) += d(r, 0) * source.moment(0, c) + d(r, 1) * source.moment(1, c) +
                       d(r, 2) * source.moment(2, c);
          }
        }
      }
      const Eigen::Matrix3d gain_rt = gain_ * rotation.transpose();
      Eigen::Matrix3d b_value, db[3];
      for (int c = 0; c < 3; ++c) {
        for (int r = 0; r < 3; ++r) {
          b_value(r, c) = b(r, c).a;
          for (int i = 0; i < 3; ++i) db[i](r, c) = b(r, c).v(i);
        }
      }
      const Eigen::Matrix3d rt_b = rotation.transpose() * b_value;
      const Eigen::Matrix3d s_value = gain_ * rt_b;
      Eigen::Matrix3d ds[6];
      for (int i = 0; i < 3; ++i) {
        ds[i] = gain_rt * db[i];
        Eigen::Matrix3d e_cross = Eigen::Matrix3d::Zero();
        e_cross((i + 2) % 3, (i + 1) % 3) = 1.0;
        e_cross((i + 1) % 3, (i + 2) % 3) = -1.0;
        ds[3 + i] = -gain_ * (e_cross * rt_b);
      }
      Vector9 s;
      Matrix96 j_s;
      for (int c = 0; c < 3; ++c) {
        for (int r = 0; r < 3; ++r) {
          s(3 * c + r) = s_value(r, c);
          for (int i = 0; i < 6; ++i) j_s(3 * c + r, i) = ds[i](r, c);
        }
      }
      const Vector6 g = j_free_t * (s - s_free);
      const Matrix6 h = j_free_t * j_s;
      const Vector6 step = -h.partialPivLu().solve(g);
      p += step.head<3>();
      const double angle = step.tail<3>().norm();
      if (angle > 0) {
        rotation = rotation * Eigen::AngleAxisd(angle, step.tail<3>() / angle).toRotationMatrix();
      }
      const double size = std::max(step.head<3>().norm(), angle);
      if (size * size < 1e-12) break;
    }
    Eigen::Quaterniond q(rotation);
    q.normalize();
    return CorrectedPose{Rigid3d(q, p) * receiver_from_body_, false, CorrectionStatus::kConverged};
  }

 private:
  struct Source {
    Eigen::Vector3d center;
    Eigen::Matrix3d moment;
  };
  FieldModel field_;
  Eigen::Matrix3d gain_;
  Rigid3d receiver_from_body_;
  std::vector<Source> sources_;
};

Rigid3d SensorOffset() {
  return Rigid3d(Eigen::Quaterniond(Eigen::AngleAxisd(0.05, Eigen::Vector3d::UnitX())),
                 Eigen::Vector3d(0.01, 0.0, 0.02));
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

void BM_PreBoundedInverse(benchmark::State& state) {  // baseline of the bounded inverse
  const PreBoundedInverse baseline(PaperRoomField(), PaperRoomGain(), SensorOffset());
  RunPerPose(state, baseline);
}
BENCHMARK(BM_PreBoundedInverse);

void BM_PhysicalPaperRoom(benchmark::State& state) {
  const PhysicalCorrection physical(PaperRoomField(), PaperRoomGain(), SensorOffset());
  RunPerPose(state, physical);
  const PreBoundedInverse baseline(PaperRoomField(), PaperRoomGain(), SensorOffset());
  double iterations = 0, ambiguous = 0, max_difference = 0;
  for (const Rigid3d& reported : Reports()) {
    const PhysicalCorrection::Inverse inverse = physical.Invert(reported);
    iterations += inverse.iterations;
    ambiguous += inverse.status != CorrectionStatus::kConverged ? 1 : 0;
    if (inverse.status != CorrectionStatus::kConverged) continue;
    max_difference = std::max(max_difference, (physical.Apply(reported).pose.translation -
                                               baseline.Apply(reported).pose.translation)
                                                  .norm());
  }
  const double n = static_cast<double>(Reports().size());
  state.counters["newton_steps"] = iterations / n;  // mean steps per pose
  state.counters["unresolved"] = ambiguous / n;     // fraction not converged or ambiguous
  // Largest distance to the baseline's pose where the bounded inverse converged [m]: the same
  // roots.
  state.counters["max_vs_baseline_m"] = max_difference;
}
BENCHMARK(BM_PhysicalPaperRoom);

// With the 50 Newton steps fitted calibration files carry since the fit and the runtime share
// them (fit/terms_physical.h InverseOptions): only poses unconverged after 8 take more. Its ratio
// to BM_PhysicalPaperRoom is what that costs per pose in the server.
void BM_PhysicalPaperRoomFitSteps(benchmark::State& state) {
  PhysicalCorrectionOptions options;
  options.max_iterations = 50;
  const PhysicalCorrection physical(PaperRoomField(), PaperRoomGain(), SensorOffset(), options);
  RunPerPose(state, physical);
  double unresolved = 0;
  for (const Rigid3d& reported : Reports()) {
    unresolved += physical.Invert(reported).status != CorrectionStatus::kConverged ? 1 : 0;
  }
  state.counters["unresolved"] = unresolved / static_cast<double>(Reports().size());
}
BENCHMARK(BM_PhysicalPaperRoomFitSteps);

// Without the second-root search near objects (fold_reach 0): what that search costs.
void BM_PhysicalPaperRoomNoFoldSearch(benchmark::State& state) {
  PhysicalCorrectionOptions options;
  options.fold_reach = 0.0;
  const PhysicalCorrection physical(PaperRoomField(), PaperRoomGain(), SensorOffset(), options);
  RunPerPose(state, physical);
}
BENCHMARK(BM_PhysicalPaperRoomNoFoldSearch);

// The inverse as the fit calls it, per station evaluation (InvertReport: Classify::kRootOnly, the
// root or none, without the noise-gain check and the second-root search) against the full Invert()
// on the same reports, both with the fit's 50 Newton steps (fit/terms_physical.h InverseOptions).
// Their ratio is what the fit saves per evaluation; the poses are bitwise the same
// (core/physical_correction_test, RootOnlyInverseIsTheFullInverseWithoutClassifying).
PhysicalCorrection FitInverse() {
  PhysicalCorrectionOptions options;
  options.max_iterations = 50;
  return PhysicalCorrection(PaperRoomField(), PaperRoomGain(), SensorOffset(), options);
}

void BM_InvertFull(benchmark::State& state) {
  const PhysicalCorrection physical = FitInverse();
  const std::vector<Rigid3d>& reports = Reports();
  size_t i = 0;
  for (auto _ : state) {
    benchmark::DoNotOptimize(physical.Invert(reports[i]));
    i = (i + 1) % reports.size();
  }
}
BENCHMARK(BM_InvertFull);

void BM_InvertReportRootOnly(benchmark::State& state) {
  const PhysicalCorrection physical = FitInverse();
  const std::vector<Rigid3d>& reports = Reports();
  size_t i = 0;
  Rigid3d x;
  for (auto _ : state) {
    benchmark::DoNotOptimize(physical.InvertReport(reports[i], &x));
    benchmark::DoNotOptimize(x);
    i = (i + 1) % reports.size();
  }
}
BENCHMARK(BM_InvertReportRootOnly);

// The workflow's final models: the near sources (frame, toolbox, floor) with the distant ones as a
// background_field (core/field.h, degree 1, 24 coefficients) instead of three dipoles and a plane.
// Its ratio to BM_PhysicalPaperRoom is what the background costs per pose (the poses are the
// room's reports; the correction is a different model of them, so only the cost is compared).
void BM_PhysicalNearRoomWithBackground(benchmark::State& state) {
  FieldModel field = PaperRoomField();
  field.planes.resize(1);                                          // the floor
  field.objects.erase(field.objects.begin(), field.objects.begin() + 3);  // frame, toolbox
  field.background.degree = 1;
  for (int k = 0; k < 24; ++k) field.background.coefficients.push_back(1e-3 * ((k % 5) - 2));
  const PhysicalCorrection physical(field, PaperRoomGain(), SensorOffset());
  RunPerPose(state, physical);
}
BENCHMARK(BM_PhysicalNearRoomWithBackground);

// The noise-gain step alone at a root, as it was (dy/dx = A^-1 h with A^-1 per pose, eigen-solve of
// its normal matrix, determinant) and as it is (LU of h, dx/dy = h^-1 A, Frobenius bound; the
// eigen-solve only above max_noise_gain): matrices like the paper room's (h = A (I + E), |E| ~
// 0.1).
struct NoiseGainInputs {
  std::vector<Eigen::Matrix<double, 6, 6>> a, h;
};
const NoiseGainInputs& GainInputs() {
  static const NoiseGainInputs inputs = [] {
    NoiseGainInputs out;
    std::mt19937_64 rng(7);
    std::normal_distribution<double> n(0.0, 1.0);
    for (int i = 0; i < 256; ++i) {
      Eigen::Matrix<double, 6, 6> j;
      for (int k = 0; k < 36; ++k) j(k) = n(rng);
      Eigen::Matrix<double, 6, 6> e;
      for (int k = 0; k < 36; ++k) e(k) = 0.1 * n(rng);
      const Eigen::Matrix<double, 6, 6> a = j.transpose() * j;
      out.a.push_back(a);
      out.h.push_back(a * (Eigen::Matrix<double, 6, 6>::Identity() + e));
    }
    return out;
  }();
  return inputs;
}

void BM_NoiseGainEigenSolve(benchmark::State& state) {  // before
  const NoiseGainInputs& in = GainInputs();
  size_t i = 0;
  for (auto _ : state) {
    Eigen::Matrix<double, 6, 6> m = in.a[i].inverse() * in.h[i];
    m.topRightCorner<3, 3>() /= 0.7;
    m.bottomLeftCorner<3, 3>() *= 0.7;
    const Eigen::SelfAdjointEigenSolver<Eigen::Matrix<double, 6, 6>> eig(m.transpose() * m,
                                                                         Eigen::EigenvaluesOnly);
    benchmark::DoNotOptimize(eig.eigenvalues()(0));
    benchmark::DoNotOptimize(m.determinant());
    i = (i + 1) % in.a.size();
  }
}
BENCHMARK(BM_NoiseGainEigenSolve);

void BM_NoiseGainFrobeniusBound(benchmark::State& state) {  // now (the bound decides)
  const NoiseGainInputs& in = GainInputs();
  size_t i = 0;
  for (auto _ : state) {
    const Eigen::PartialPivLU<Eigen::Matrix<double, 6, 6>> lu(in.h[i]);
    benchmark::DoNotOptimize(lu.determinant());
    Eigen::Matrix<double, 6, 6> dx_dy = lu.solve(in.a[i]);
    dx_dy.topRightCorner<3, 3>() /= 0.7;
    dx_dy.bottomLeftCorner<3, 3>() *= 0.7;
    benchmark::DoNotOptimize(dx_dy.norm());
    i = (i + 1) % in.a.size();
  }
}
BENCHMARK(BM_NoiseGainFrobeniusBound);

void BM_PhysicalFreeSpace(benchmark::State& state) {  // the inverse's fixed cost
  const PhysicalCorrection physical(FieldModel{}, Eigen::Matrix3d::Identity());
  RunPerPose(state, physical);
}
BENCHMARK(BM_PhysicalFreeSpace);

}  // namespace
}  // namespace trackcal

BENCHMARK_MAIN();
