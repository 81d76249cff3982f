// Cost of correcting one pose: trackcal's degree-4 polynomial and trilinear LUT against naive
// baselines in the same binary (a std::pow-per-term polynomial with per-component coefficient
// vectors, as a direct transcription of the paper's eq. 7 would be; a LUT with binary search and
// nested vectors). Report figures as ratios of these (docs: the paper needed 18 us per pose).
//
//   build/bench/bench_correction --benchmark_min_time=0.5
//
// BM_Calibration_*: the server's per-report path (chain and calibrated volume) inside the volume,
// and outside it under `clamp` and `linear` (report the outside cases as ratios to the inside one).
// BM_ServerReport_*: the server's whole per-report path (unit quaternion, finiteness checks,
// correction, Pos_Quat message), with and without the normalisation, as ratios to BM_Calibration_*.
#include <benchmark/benchmark.h>

#include <algorithm>
#include <cmath>
#include <random>
#include <vector>

#include "core/calibration_file.h"
#include "core/lut.h"
#include "core/polynomial.h"
#include "vrpn_server/protocol/payloads.h"
#include "vrpn_server/protocol/wire.h"
#include "vrpn_server/server/devices.h"

namespace trackcal {
namespace {

constexpr int kDegree = 4;
constexpr size_t kNumPoses = 4096;  // cycled through so the inputs are not constant

struct Poses {
  std::vector<Eigen::Vector3d> positions;
  std::vector<Eigen::Quaterniond> rotations;
};

const Poses& TestPoses() {
  static const Poses poses = [] {
    Poses p;
    std::mt19937_64 rng(7);
    std::uniform_real_distribution<double> u(-0.45, 0.45);
    std::normal_distribution<double> n(0.0, 1.0);
    for (size_t i = 0; i < kNumPoses; ++i) {
      p.positions.emplace_back(u(rng), u(rng), 0.3 + u(rng));
      p.rotations.push_back(QuaternionFromXyzw(n(rng), n(rng), n(rng), n(rng)).normalized());
    }
    return p;
  }();
  return poses;
}

std::vector<double> RandomCoefficients(size_t count) {
  std::mt19937_64 rng(11);
  std::normal_distribution<double> n(0.0, 0.005);
  std::vector<double> c(count);
  for (double& v : c) v = n(rng);
  return c;
}

const PolynomialCorrection& Degree4() {
  static const PolynomialCorrection poly(kDegree, Eigen::Vector3d(0, 0, 0.3),
                                         Eigen::Vector3d(0.5, 0.5, 0.5),
                                         RandomCoefficients(6 * NumPolynomialTerms(kDegree)));
  return poly;
}

// The naive baseline: exponents looked up per term, std::pow for each power, one coefficient vector
// per error component, a heap-allocated result.
struct NaivePolynomial {
  std::vector<std::array<int, 3>> exponents = PolynomialTermExponents(kDegree);
  std::vector<std::vector<double>> coefficients;  // [component][term]
  Eigen::Vector3d offset{0, 0, 0.3};
  Eigen::Vector3d scale{0.5, 0.5, 0.5};

  NaivePolynomial() {
    const PolynomialCorrection& p = Degree4();
    coefficients.assign(6, std::vector<double>(exponents.size()));
    for (size_t j = 0; j < exponents.size(); ++j) {
      for (int k = 0; k < 6; ++k) coefficients[k][j] = p.coefficients()[6 * j + k];
    }
  }

  Rigid3d Apply(const Rigid3d& reported) const {
    const Eigen::Vector3d u = (reported.translation - offset).cwiseQuotient(scale);
    std::vector<double> e(6, 0.0);
    for (int k = 0; k < 6; ++k) {
      for (size_t j = 0; j < exponents.size(); ++j) {
        e[k] += coefficients[k][j] * std::pow(u.x(), exponents[j][0]) *
                std::pow(u.y(), exponents[j][1]) * std::pow(u.z(), exponents[j][2]);
      }
    }
    const double w = std::sqrt(std::max(0.0, 1.0 - e[3] * e[3] - e[4] * e[4] - e[5] * e[5]));
    const Eigen::Quaterniond q_e = QuaternionFromXyzw(e[3], e[4], e[5], w);
    return Rigid3d((q_e * reported.rotation).normalized(),
                   reported.translation + Eigen::Vector3d(e[0], e[1], e[2]));
  }
};

std::vector<double> Axis(double first, double last, int n) {
  std::vector<double> a(n);
  for (int i = 0; i < n; ++i) a[i] = first + (last - first) * i / (n - 1);
  return a;
}

const TrilinearLutCorrection& Lut() {
  static const TrilinearLutCorrection lut = [] {
    LutGrid grid({Axis(-0.5, 0.5, 21), Axis(-0.5, 0.5, 21), Axis(-0.2, 0.8, 21)});
    std::vector<double> values = RandomCoefficients(6 * grid.num_nodes());
    return TrilinearLutCorrection(std::move(grid), std::move(values));
  }();
  return lut;
}

// Naive LUT: binary search on each axis, values in nested vectors [ix][iy][iz][component].
struct NaiveLut {
  std::array<std::vector<double>, 3> axes;
  std::vector<std::vector<std::vector<std::vector<double>>>> values;

  NaiveLut() {
    const LutGrid& g = Lut().grid();
    for (int k = 0; k < 3; ++k) axes[k] = g.axis(k);
    values.assign(g.size(0), std::vector<std::vector<std::vector<double>>>(
                                 g.size(1), std::vector<std::vector<double>>(g.size(2))));
    for (int i = 0; i < g.size(0); ++i) {
      for (int j = 0; j < g.size(1); ++j) {
        for (int k = 0; k < g.size(2); ++k) {
          const double* v = Lut().node_values().data() + 6 * g.NodeIndex(i, j, k);
          values[i][j][k].assign(v, v + 6);
        }
      }
    }
  }

  Rigid3d Apply(const Rigid3d& reported) const {
    int cell[3];
    double t[3];
    for (int k = 0; k < 3; ++k) {
      const auto& a = axes[k];
      const double v = std::clamp(reported.translation[k], a.front(), a.back());
      int i = static_cast<int>(std::upper_bound(a.begin(), a.end(), v) - a.begin()) - 1;
      i = std::clamp(i, 0, static_cast<int>(a.size()) - 2);
      cell[k] = i;
      t[k] = (v - a[i]) / (a[i + 1] - a[i]);
    }
    std::vector<double> e(6, 0.0);
    for (int a = 0; a < 2; ++a) {
      for (int b = 0; b < 2; ++b) {
        for (int c = 0; c < 2; ++c) {
          const double w = (a ? t[0] : 1 - t[0]) * (b ? t[1] : 1 - t[1]) * (c ? t[2] : 1 - t[2]);
          for (int k = 0; k < 6; ++k) {
            e[k] += w * values[cell[0] + a][cell[1] + b][cell[2] + c][k];
          }
        }
      }
    }
    const double w = std::sqrt(std::max(0.0, 1.0 - e[3] * e[3] - e[4] * e[4] - e[5] * e[5]));
    const Eigen::Quaterniond q_e = QuaternionFromXyzw(e[3], e[4], e[5], w);
    return Rigid3d((q_e * reported.rotation).normalized(),
                   reported.translation + Eigen::Vector3d(e[0], e[1], e[2]));
  }
};

template <typename Apply>
void RunPerPose(benchmark::State& state, const Apply& apply) {
  const Poses& poses = TestPoses();
  size_t i = 0;
  for (auto _ : state) {
    const Rigid3d reported(poses.rotations[i], poses.positions[i]);
    auto out = apply(reported);
    benchmark::DoNotOptimize(out);
    i = (i + 1) % kNumPoses;
  }
  state.SetItemsProcessed(state.iterations());
}

void BM_Polynomial4_Trackcal(benchmark::State& state) {
  RunPerPose(state, [](const Rigid3d& r) { return Degree4().Apply(r); });
}
BENCHMARK(BM_Polynomial4_Trackcal);

void BM_Polynomial4_NaivePow(benchmark::State& state) {
  static const NaivePolynomial naive;
  RunPerPose(state, [](const Rigid3d& r) { return naive.Apply(r); });
}
BENCHMARK(BM_Polynomial4_NaivePow);

void BM_Lut21_Trackcal(benchmark::State& state) {
  RunPerPose(state, [](const Rigid3d& r) { return Lut().Apply(r); });
}
BENCHMARK(BM_Lut21_Trackcal);

void BM_Lut21_NaiveBinarySearch(benchmark::State& state) {
  static const NaiveLut naive;
  RunPerPose(state, [](const Rigid3d& r) { return naive.Apply(r); });
}
BENCHMARK(BM_Lut21_NaiveBinarySearch);

// What the server runs: the calibration (chain + volume check) around the degree-4 polynomial.
void BM_Calibration_Polynomial4(benchmark::State& state) {
  static const Calibration cal = [] {
    Calibration c;
    c.chain.Append(Degree4().Clone());
    CalibratedVolume v;
    v.min = Eigen::Vector3d(-0.5, -0.5, -0.2);
    v.max = Eigen::Vector3d(0.5, 0.5, 0.8);
    c.chain.SetVolume(v);
    return c;
  }();
  RunPerPose(state, [](const Rigid3d& r) { return cal.Apply(r); });
}
BENCHMARK(BM_Calibration_Polynomial4);

// The server's per-report path outside the calibrated volume, as a ratio to the inside case above
// (the same calibration, every report inside): `clamp` evaluates the chain at the nearest box point,
// `linear` (what trackcal-fit writes for chains with a physical term) adds the explicit terms'
// one-sided derivatives there times the distance out (a few extra term evaluations per axis out).
// The reports lie 0-0.15 m beyond the box (beyond linear_reach for a third), every other one
// outside two faces.
const std::vector<Rigid3d>& OutsideReports() {
  static const std::vector<Rigid3d> reports = [] {
    std::vector<Rigid3d> r;
    const Poses& poses = TestPoses();
    for (size_t i = 0; i < kNumPoses; ++i) {
      Eigen::Vector3d p = poses.positions[i];
      p.x() = 0.5 + 0.15 * (p.x() + 0.45) / 0.9;
      if (i % 2 == 1) p.y() = -0.5 - 0.15 * (p.y() + 0.45) / 0.9;
      r.emplace_back(poses.rotations[i], p);
    }
    return r;
  }();
  return reports;
}

Calibration CalibrationOf(const Correction& term, ExtrapolationPolicy policy) {
  Calibration c;
  c.chain.Append(term.Clone());
  CalibratedVolume v;
  v.min = Eigen::Vector3d(-0.5, -0.5, -0.2);
  v.max = Eigen::Vector3d(0.5, 0.5, 0.8);
  v.extrapolation = policy;
  c.chain.SetVolume(v);
  return c;
}

void RunOutside(benchmark::State& state, const Calibration& cal) {
  const std::vector<Rigid3d>& reports = OutsideReports();
  size_t i = 0;
  for (auto _ : state) {
    auto out = cal.Apply(reports[i]);
    benchmark::DoNotOptimize(out);
    i = (i + 1) % kNumPoses;
  }
  state.SetItemsProcessed(state.iterations());
}

void BM_Calibration_Polynomial4_OutsideClamp(benchmark::State& state) {
  static const Calibration cal = CalibrationOf(Degree4(), ExtrapolationPolicy::kClamp);
  RunOutside(state, cal);
}
BENCHMARK(BM_Calibration_Polynomial4_OutsideClamp);

void BM_Calibration_Polynomial4_OutsideLinear(benchmark::State& state) {
  static const Calibration cal = CalibrationOf(Degree4(), ExtrapolationPolicy::kLinear);
  RunOutside(state, cal);
}
BENCHMARK(BM_Calibration_Polynomial4_OutsideLinear);

// The same three cases for the 21^3 LUT.
void BM_Calibration_Lut21(benchmark::State& state) {
  static const Calibration cal = CalibrationOf(Lut(), ExtrapolationPolicy::kLinear);
  RunPerPose(state, [](const Rigid3d& r) { return cal.Apply(r); });
}
BENCHMARK(BM_Calibration_Lut21);

void BM_Calibration_Lut21_OutsideClamp(benchmark::State& state) {
  static const Calibration cal = CalibrationOf(Lut(), ExtrapolationPolicy::kClamp);
  RunOutside(state, cal);
}
BENCHMARK(BM_Calibration_Lut21_OutsideClamp);

void BM_Calibration_Lut21_OutsideLinear(benchmark::State& state) {
  static const Calibration cal = CalibrationOf(Lut(), ExtrapolationPolicy::kLinear);
  RunOutside(state, cal);
}
BENCHMARK(BM_Calibration_Lut21_OutsideLinear);

// The server's per-report path as TrackerDevice::OnReports and the network thread run it, on
// reports as the Fastrak driver hands them over (the quaternion printed with 4 decimals, so |q| is
// off by up to ~1e-4 and the normalisation does its division): the report scaled to a unit
// quaternion and checked finite, corrected, the corrected pose scaled and checked again, then
// encoded as a Pos_Quat message into a reused buffer. `normalise` false drops the two
// WithUnitRotation calls (the path before the server served unit quaternions): the ratio of the two
// is what the normalisation costs per report, the ratio to BM_Calibration_* what the server adds
// to the correction.
const std::vector<Rigid3d>& DriverReports() {
  static const std::vector<Rigid3d> reports = [] {
    std::vector<Rigid3d> r;
    const Poses& poses = TestPoses();
    for (size_t i = 0; i < kNumPoses; ++i) {
      Eigen::Vector4d q = poses.rotations[i].coeffs();
      for (int k = 0; k < 4; ++k) q[k] = std::round(q[k] * 1e4) * 1e-4;
      r.emplace_back(Eigen::Quaterniond(q), poses.positions[i]);
    }
    return r;
  }();
  return reports;
}

void RunServerReport(benchmark::State& state, const Calibration& cal, bool normalise) {
  const std::vector<Rigid3d>& reports = DriverReports();
  std::vector<uint8_t> message;
  message.reserve(256);
  size_t i = 0;
  int64_t not_served = 0;
  for (auto _ : state) {
    message.clear();
    Rigid3d reported = reports[i];
    if (normalise) reported = vrpn::WithUnitRotation(reported);
    i = (i + 1) % kNumPoses;
    if (!vrpn::IsFinite(reported)) {
      ++not_served;
      continue;
    }
    Rigid3d corrected = cal.Apply(reported).pose;
    if (normalise) corrected = vrpn::WithUnitRotation(corrected);
    if (!vrpn::IsFinite(corrected)) {
      ++not_served;
      continue;
    }
    uint8_t payload[vrpn::kPosQuatSize];
    vrpn::EncodePosQuatInto(vrpn::PosQuat{0, corrected}, payload);
    vrpn::AppendMessage(&message, vrpn::Timestamp{1, static_cast<uint32_t>(i)}, 0, 2, 0, payload);
    benchmark::DoNotOptimize(message.data());
    benchmark::ClobberMemory();
  }
  state.SetItemsProcessed(state.iterations());
  // 0 here (every report finite): otherwise the loop timed less than the whole path.
  state.counters["not_served"] = static_cast<double>(not_served);
}

void BM_ServerReport_Polynomial4(benchmark::State& state) {
  static const Calibration cal = CalibrationOf(Degree4(), ExtrapolationPolicy::kLinear);
  RunServerReport(state, cal, true);
}
BENCHMARK(BM_ServerReport_Polynomial4);

void BM_ServerReport_Polynomial4_NoNormalise(benchmark::State& state) {
  static const Calibration cal = CalibrationOf(Degree4(), ExtrapolationPolicy::kLinear);
  RunServerReport(state, cal, false);
}
BENCHMARK(BM_ServerReport_Polynomial4_NoNormalise);

void BM_ServerReport_Lut21(benchmark::State& state) {
  static const Calibration cal = CalibrationOf(Lut(), ExtrapolationPolicy::kLinear);
  RunServerReport(state, cal, true);
}
BENCHMARK(BM_ServerReport_Lut21);

void BM_ServerReport_Lut21_NoNormalise(benchmark::State& state) {
  static const Calibration cal = CalibrationOf(Lut(), ExtrapolationPolicy::kLinear);
  RunServerReport(state, cal, false);
}
BENCHMARK(BM_ServerReport_Lut21_NoNormalise);

// Batch path on raw arrays (what the Python binding calls), per pose.
void BM_Polynomial4_Batch(benchmark::State& state) {
  const Poses& poses = TestPoses();
  std::vector<double> pos(3 * kNumPoses), quat(4 * kNumPoses), out_pos(3 * kNumPoses),
      out_quat(4 * kNumPoses);
  std::vector<uint8_t> flags(kNumPoses);
  for (size_t i = 0; i < kNumPoses; ++i) {
    for (int k = 0; k < 3; ++k) pos[3 * i + k] = poses.positions[i][k];
    QuaternionToXyzwArray(poses.rotations[i], &quat[4 * i]);
  }
  for (auto _ : state) {
    Degree4().ApplyBatch(kNumPoses, pos.data(), quat.data(), out_pos.data(), out_quat.data(),
                         flags.data());
    benchmark::DoNotOptimize(out_pos.data());
    benchmark::DoNotOptimize(out_quat.data());
    benchmark::ClobberMemory();
  }
  state.SetItemsProcessed(state.iterations() * kNumPoses);
}
BENCHMARK(BM_Polynomial4_Batch);

}  // namespace
}  // namespace trackcal

BENCHMARK_MAIN();
