#include "fit/fit_engine.h"

#include <ceres/ceres.h>
#include <ceres/normal_prior.h>

#include <Eigen/Cholesky>
#include <Eigen/Eigenvalues>
#include <Eigen/SVD>
#include <algorithm>
#include <chrono>
#include <cmath>
#include <exception>
#include <limits>
#include <map>
#include <memory>
#include <numeric>
#include <optional>
#include <set>
#include <stdexcept>
#include <utility>

#include "core/json_reader.h"
#include "fit/pose_metric.h"
#include "fit/terms_time_offset.h"

namespace trackcal::fit {
namespace {

// One bound block of one term for one station.
struct BoundTerm {
  const ModelTerm* term;
  StationBinding binding;
};


// The pose at the input of terms[from..] that they map to `target` (`parameters` from term
// `from` on): a fixed number of fixed-point steps z <- z - (F(z) - target) (world-frame rotation
// error for the orientation) from z = target. No convergence test and no branch, so the result is
// a smooth function of the values; the terms after a physical group are corrections close to the
// identity (a polynomial, a LUT: |dF/dz - I| of order 1e-2), so each step gains about two digits.
// False if a term cannot be evaluated.
constexpr int kPullBackSteps = 3;
bool PullBack(const std::vector<BoundTerm>& terms, size_t from, double const* const* parameters,
              const AmbientPose& target, AmbientPose* out) {
  AmbientPose z = target;
  const Eigen::Quaterniond q_target = QuaternionFromXyzwArray(target.data() + 3).normalized();
  TermEvaluation eval;
  for (int step = 0; step < kPullBackSteps; ++step) {
    AmbientPose pose = z;
    size_t p = 0;
    for (size_t k = from; k < terms.size(); ++k) {
      if (!terms[k].term->Evaluate(terms[k].binding, parameters + p, pose, false, &eval)) {
        return false;
      }
      pose = eval.output;
      p += terms[k].binding.blocks.size();
    }
    z.head<3>() -= pose.head<3>() - target.head<3>();
    const Eigen::Quaterniond q_out = QuaternionFromXyzwArray(pose.data() + 3).normalized();
    const Eigen::Quaterniond q_z = QuaternionFromXyzwArray(z.data() + 3).normalized();
    const Eigen::Quaterniond q_next = (q_target * q_out.conjugate() * q_z).normalized();
    z.segment<4>(3) << q_next.x(), q_next.y(), q_next.z(), q_next.w();
  }
  *out = z;
  return z.allFinite();
}

using JacobianBlocks = std::vector<Eigen::Matrix<double, 7, Eigen::Dynamic, Eigen::RowMajor>>;


// Maps `input` through terms[from..], a term that UsesTarget() toward the pose the rest of the
// chain maps to `target` (PullBack; `target` itself for the last term): a physical group then gives
// a residual continuous in its values (ModelTerm::EvaluateToward, fit/terms_physical.h).
// `parameters` holds the bound blocks' values from term `from` on. With `want`, fills d output / d
// block for every bound block (7 x size each) by the chain rule, `d_output_d_input` and
// `d_output_d_target` if given.
//
// A group's output depends on its target, and so on the blocks of the terms after it, which pull
// the target back: with G the terms after the group (output = G(z)) and target_k their pull-back
// of `target` (G(target_k) = target), d target_k = (T G_z B)^-1 T (d target - G_phi d phi) on
// target_k's tangent (B: its chart, T: the target's tangent map), G_z and G_phi evaluated at
// target_k by the rest of the chain. A later block's column gains G_z(output of the group)
// d_output_d_target d target_k / d phi.
bool EvaluateChainFrom(const std::vector<BoundTerm>& terms, size_t from,
                       double const* const* parameters, const AmbientPose& input,
                       const AmbientPose& target, bool want, AmbientPose* output,
                       JacobianBlocks* d_pose,
                       Eigen::Matrix<double, 7, 7>* d_output_d_input = nullptr,
                       Eigen::Matrix<double, 7, 7>* d_output_d_target = nullptr) {
  using Matrix7 = Eigen::Matrix<double, 7, 7>;
  // A group evaluated toward a pulled-back target: its later blocks' extra columns, completed when
  // the chain's end is reached. A model has one physical group, its first term (ModelSpec): the
  // terms after it do not use a target, so the pull-back's derivative needs no term of theirs.
  struct Pending {
    size_t first_block;                   // in d_pose: the first block after the group
    Eigen::Matrix<double, 7, 6> t_chart;  // d group output / d target_k's tangent
    Eigen::Matrix<double, 6, 7> pull;     // (T G_z B)^-1 T
    JacobianBlocks g_phi;                 // d G / d later block at target_k
    Matrix7 after = Matrix7::Identity();  // d chain output / d group output
  };
  std::vector<Pending> pending;
  Matrix7 last_group_d_target = Matrix7::Zero();
  AmbientPose pose = input;
  if (d_output_d_input != nullptr) d_output_d_input->setIdentity();
  TermEvaluation eval;
  size_t p = 0;
  for (size_t k = from; k < terms.size(); ++k) {
    const BoundTerm& t = terms[k];
    const size_t count = t.binding.blocks.size();
    bool ok = false;
    std::optional<Pending> group;
    // The input derivative multiplies the derivatives gathered so far; the first term's (a
    // constant report) is not read unless the caller asks for the chain's.
    eval.want_d_output_d_input =
        want && (d_output_d_input != nullptr || !d_pose->empty() || !pending.empty());
    if (!t.term->UsesTarget()) {
      ok = t.term->Evaluate(t.binding, parameters + p, pose, want, &eval);
    } else if (k + 1 == terms.size()) {
      ok = t.term->EvaluateToward(t.binding, parameters + p, pose, target, want, &eval);
      if (ok && want) last_group_d_target = eval.d_output_d_target;
    } else {
      AmbientPose target_k;
      ok = PullBack(terms, k + 1, parameters + p + count, target, &target_k) &&
           t.term->EvaluateToward(t.binding, parameters + p, pose, target_k, want, &eval);
      if (ok && want) {
        group.emplace();
        AmbientPose unused;
        Matrix7 g_z;
        if (!EvaluateChainFrom(terms, k + 1, parameters + p + count, target_k, target, true,
                               &unused, &group->g_phi, &g_z)) {
          return false;
        }
        // On the tangents: d target = G_z B d target_k, so d target_k = (T G_z B)^-1 T d target
        // (T = TangentOfAmbient(target), B = AmbientOfTangent(target_k)).
        const Eigen::Matrix<double, 7, 6> chart = AmbientOfTangent(target_k);
        const Eigen::Matrix<double, 6, 7> tangent = TangentOfAmbient(target);
        group->pull = (tangent * g_z * chart).partialPivLu().solve(tangent);
        group->t_chart = eval.d_output_d_target * chart;
      }
    }
    if (!ok) return false;
    if (want) {
      for (auto& d : *d_pose) d = eval.d_output_d_input * d;
      for (auto& g : pending) g.after = eval.d_output_d_input * g.after;
      for (size_t b = 0; b < count; ++b) d_pose->push_back(eval.d_output_d_blocks[b]);
      if (d_output_d_input != nullptr) *d_output_d_input = eval.d_output_d_input * *d_output_d_input;
      if (group) {
        group->first_block = d_pose->size();
        pending.push_back(std::move(*group));
      }
    }
    pose = eval.output;
    p += count;
  }
  if (want) {
    Matrix7 e = last_group_d_target;
    for (const Pending& g : pending) {
      const Eigen::Matrix<double, 7, 7> via_target = g.after * g.t_chart * g.pull;
      for (size_t i = 0; i < g.g_phi.size(); ++i) {
        auto& d = (*d_pose)[g.first_block + i];
        d = (d - via_target * g.g_phi[i]).eval();
      }
      e += via_target;
    }
    if (d_output_d_target != nullptr) *d_output_d_target = e;
  }
  *output = pose;
  return true;
}

bool EvaluateChain(const std::vector<BoundTerm>& terms, double const* const* parameters,
                   const AmbientPose& input, const AmbientPose& target, bool want,
                   AmbientPose* output, JacobianBlocks* d_pose,
                   Eigen::Matrix<double, 7, 7>* d_output_d_target) {
  return EvaluateChainFrom(terms, 0, parameters, input, target, want, output, d_pose, nullptr,
                           d_output_d_target);
}

// Chains the terms: forward through them, Jacobians composed by the chain rule. With a
// pose `metric` K (PoseMetricOf, fit/pose_metric.h) the residual and its Jacobians are K times
// those of StationResidual.
class StationCost : public ceres::CostFunction {
 public:
  // With `time_offset0` set, the last parameter block is the clock offset dt (size 1) and the
  // reference moves by the station's velocity times dt - *time_offset0 (fit/terms_time_offset.h).
  StationCost(std::vector<BoundTerm> terms, const FitStation& station, double sigma_p,
              double sigma_o, std::optional<double> time_offset0 = std::nullopt,
              std::optional<Matrix6> metric = std::nullopt)
      : terms_(std::move(terms)),
        station_(station),
        sigma_p_(sigma_p),
        sigma_o_(sigma_o),
        time_offset0_(time_offset0),
        metric_(metric) {
    set_num_residuals(6);
    for (const auto& t : terms_) {
      for (int b : t.binding.blocks) {
        mutable_parameter_block_sizes()->push_back(t.term->blocks()[static_cast<size_t>(b)].size());
      }
    }
    if (time_offset0_) mutable_parameter_block_sizes()->push_back(1);
  }

  bool Evaluate(double const* const* parameters, double* residuals,
                double** jacobians) const override {
    if (!EvaluateUnweighted(parameters, residuals, jacobians)) return false;
    if (!metric_) return true;
    const Matrix6& w = *metric_;
    Eigen::Map<Eigen::Matrix<double, 6, 1>> r(residuals);
    r = (w * r).eval();
    if (jacobians != nullptr) {
      const std::vector<int32_t>& sizes = parameter_block_sizes();
      for (size_t b = 0; b < sizes.size(); ++b) {
        if (jacobians[b] == nullptr) continue;
        Eigen::Map<Eigen::Matrix<double, 6, Eigen::Dynamic, Eigen::RowMajor>> j(jacobians[b], 6,
                                                                                sizes[b]);
        j = (w * j).eval();
      }
    }
    return true;
  }

 private:
  bool EvaluateUnweighted(double const* const* parameters, double* residuals,
                          double** jacobians) const {
    const bool want = jacobians != nullptr;
    size_t p = 0;
    for (const auto& t : terms_) p += t.binding.blocks.size();
    Rigid3d reference = station_.reference;
    const double dt = time_offset0_ ? parameters[p][0] - *time_offset0_ : 0.0;
    if (time_offset0_) {
      ShiftReference<double>(station_.reference, station_.reference_velocity,
                             station_.reference_angular_velocity, dt, &reference.translation,
                             &reference.rotation);
    }
    AmbientPose pose = ToAmbient(station_.reported);
    // d pose / d block for every block so far (7 x size, row-major).
    std::vector<Eigen::Matrix<double, 7, Eigen::Dynamic, Eigen::RowMajor>> d_pose;
    Eigen::Matrix<double, 7, 7> d_pose_d_target;
    if (!EvaluateChain(terms_, parameters, pose, ToAmbient(reference), want, &pose, &d_pose,
                       &d_pose_d_target)) {
      return false;
    }
    if (!want) {
      StationResidual<double>(pose.data(), reference, sigma_p_, sigma_o_, residuals);
      return true;
    }
    using Jet = ceres::Jet<double, 7>;
    Jet pose_jet[7];
    for (int k = 0; k < 7; ++k) pose_jet[k] = Jet(pose[k], k);
    Jet r[6];
    StationResidual<Jet>(pose_jet, reference, sigma_p_, sigma_o_, r);
    Eigen::Matrix<double, 6, 7, Eigen::RowMajor> d_r;
    for (int i = 0; i < 6; ++i) {
      residuals[i] = r[i].a;
      d_r.row(i) = r[i].v.transpose();
    }
    if (time_offset0_ && jacobians[p] != nullptr) {
      // The clock offset moves the reference, and with it the pose a physical group is evaluated
      // toward (EvaluateChain's d_output_d_target).
      using Jet1 = ceres::Jet<double, 1>;
      Vector3<Jet1> p_ref;
      Eigen::Quaternion<Jet1> q_ref;
      ShiftReference<Jet1>(station_.reference, station_.reference_velocity,
                           station_.reference_angular_velocity, Jet1(dt, 0), &p_ref, &q_ref);
      Jet1 pose_const[7], r1[6];
      for (int k = 0; k < 7; ++k) pose_const[k] = Jet1(pose[k]);
      StationResidual<Jet1>(pose_const, p_ref, q_ref, sigma_p_, sigma_o_, r1);
      const Jet1 ref[7] = {p_ref(0),  p_ref(1),  p_ref(2), q_ref.x(),
                           q_ref.y(), q_ref.z(), q_ref.w()};
      Eigen::Matrix<double, 7, 1> d_ref_d_dt;
      for (int k = 0; k < 7; ++k) d_ref_d_dt(k) = ref[k].v[0];
      const Eigen::Matrix<double, 6, 1> via_pose = d_r * (d_pose_d_target * d_ref_d_dt);
      for (int i = 0; i < 6; ++i) jacobians[p][i] = r1[i].v[0] + via_pose(i);
    }
    for (size_t b = 0; b < d_pose.size(); ++b) {
      if (jacobians[b] == nullptr) continue;
      Eigen::Map<Eigen::Matrix<double, 6, Eigen::Dynamic, Eigen::RowMajor>> j(
          jacobians[b], 6, d_pose[b].cols());
      j.noalias() = d_r * d_pose[b];
    }
    return true;
  }

  std::vector<BoundTerm> terms_;
  FitStation station_;
  double sigma_p_, sigma_o_;
  std::optional<double> time_offset0_;
  std::optional<Matrix6> metric_;
};

// The bound blocks' current values, term after term (a StationCost's parameters).
std::vector<const double*> BoundValues(const std::vector<BoundTerm>& terms) {
  std::vector<const double*> values;
  for (const auto& t : terms) {
    for (int b : t.binding.blocks) {
      values.push_back(t.term->blocks()[static_cast<size_t>(b)].values.data());
    }
  }
  return values;
}

// A station's ReportPerPose (fit/pose_metric.h) at the terms' current values, its reference moved
// by the clock offset dt (fit/terms_time_offset.h) as StationCost moves it. Null if a term cannot
// be evaluated.
std::optional<Matrix6> StationReportPerPose(const std::vector<BoundTerm>& terms,
                                            const FitStation& station, double sigma_p,
                                            double sigma_o, double dt) {
  Rigid3d reference = station.reference;
  if (dt != 0.0) {
    ShiftReference<double>(station.reference, station.reference_velocity,
                           station.reference_angular_velocity, dt, &reference.translation,
                           &reference.rotation);
  }
  AmbientPose pose;
  Eigen::Matrix<double, 7, 7> d_pose_d_target;
  JacobianBlocks unused;
  if (!EvaluateChain(terms, BoundValues(terms).data(), ToAmbient(station.reported),
                     ToAmbient(reference), true, &pose, &unused, &d_pose_d_target)) {
    return std::nullopt;
  }
  return ReportPerPose(pose, d_pose_d_target, reference, sigma_p, sigma_o);
}

// Each station's pose at the input of term `k` (terms 0..k-1 applied with their current values).
std::vector<FitStation> InputsOfTerm(const std::vector<FitStation>& stations,
                                     const ModelSpec& spec, size_t k) {
  std::vector<FitStation> out = stations;
  if (k == 0) return out;
  for (auto& s : out) {
    AmbientPose pose = ToAmbient(s.reported);
    TermEvaluation eval;
    for (size_t t = 0; t < k; ++t) {
      const ModelTerm& term = *spec.terms[t];
      const StationBinding binding = term.Bind(pose);
      std::vector<const double*> values;
      for (int b : binding.blocks) values.push_back(term.blocks()[static_cast<size_t>(b)].values.data());
      if (!term.Evaluate(binding, values.data(), pose, false, &eval)) {
        throw std::runtime_error("term '" + term.name() + "' cannot be evaluated at station " +
                                 std::to_string(s.station));
      }
      pose = eval.output;
    }
    s.reported = FromAmbient(pose);
  }
  return out;
}

// A robust loss that rejects a gross outlier outright: beyond kRejectScales times its scale (the
// station's whitened rms) the cost is constant, so the station pulls neither the fit nor the
// sandwich covariance. The Cauchy tail alone pulls with J / |r|, which is small only where the
// Jacobian is bounded: a hemisphere flip reports -p, next to the floor plane (z 0.3-0.9 m against
// the floor at 0.8 m), where a plane term's Jacobian is huge (measured, workflow capture,
// hemisphere_flips seed 1: the floor plane 0.85 +- 0.20 m, attenuation 0.37 +- 0.25 with the two
// flips, 0.72 +- 0.03 m, 0.256 +- 0.038 without them). At 30 scales a Cauchy station's weight is
// already ~1e-3 (no station the loss is meant to keep is near it).
class RejectingLoss : public ceres::LossFunction {
 public:
  static constexpr double kRejectScales = 30.0;
  RejectingLoss(ceres::LossFunction* inner, double scale)
      : inner_(inner), reject_sq_norm_(6.0 * std::pow(kRejectScales * scale, 2)) {}
  void Evaluate(double s, double rho[3]) const override {
    if (s > reject_sq_norm_) {
      inner_->Evaluate(reject_sq_norm_, rho);
      rho[1] = 0.0;  // no influence (Ceres' Tukey loss does the same beyond its scale)
      rho[2] = 0.0;
      return;
    }
    inner_->Evaluate(s, rho);
  }

 private:
  std::unique_ptr<ceres::LossFunction> inner_;
  double reject_sq_norm_;  // squared norm of a station's 6 whitened residuals
};

// The loss of a station's residual block. The scale is in sigmas of the station's whitened RMS
// (LossOptions; the outlier list, the rejection above and diagnose's mean-shift model read it so);
// Ceres' losses take theirs on the norm of the block's 6 residuals, sqrt(6) times the RMS. Given
// the scale as it is, a 3-sigma loss down-weighted stations from RMS 1.22 on, most of a right
// model's stations.
ceres::LossFunction* MakeLoss(const LossOptions& loss) {
  const double norm_scale = std::sqrt(6.0) * loss.scale;
  switch (loss.type) {
    case LossType::kNone: return nullptr;
    case LossType::kHuber:
      return new RejectingLoss(new ceres::HuberLoss(norm_scale), loss.scale);
    case LossType::kCauchy:
      return new RejectingLoss(new ceres::CauchyLoss(norm_scale), loss.scale);
  }
  return nullptr;
}

// Calls FitOptions::progress after each iteration. An exception it throws (the Python binding's
// stop on Ctrl-C) is kept and the solve aborted, then rethrown after ceres::Solve returns
// (SolveWithProgress): Ceres does not promise to be exception-safe through its callbacks.
class ProgressCallback : public ceres::IterationCallback {
 public:
  explicit ProgressCallback(std::function<void(int, double)> f) : f_(std::move(f)) {}
  ceres::CallbackReturnType operator()(const ceres::IterationSummary& s) override {
    try {
      f_(s.iteration, s.cost);
    } catch (...) {
      thrown_ = std::current_exception();
      return ceres::SOLVER_ABORT;
    }
    return ceres::SOLVER_CONTINUE;
  }
  void RethrowIfThrown() {
    if (thrown_) std::rethrow_exception(std::exchange(thrown_, nullptr));
  }

 private:
  std::function<void(int, double)> f_;
  std::exception_ptr thrown_;
};

void SolveWithProgress(const ceres::Solver::Options& options, ceres::Problem* problem,
                       ceres::Solver::Summary* summary, ProgressCallback* progress) {
  ceres::Solve(options, problem, summary);
  progress->RethrowIfThrown();
}

// Statistical convergence: stops the solver once a successful step lowers the cost (0.5 chi2) by
// less than `fraction` times the chi2 per degree of freedom at that point, i.e. when what is left
// to gain is a small fraction of one degree of freedom's share of the scatter: the parameters are
// then within ~0.1 of their standard deviation of the optimum (FoldRefitOptions uses the same
// rule). Ceres' function_tolerance is relative to the whole cost and, at its default 1e-12,
// spends tens of iterations of a large LUT chain moving parameters by far less than that
// (docs/benchmarks.md). Noise-free data (chi2/dof near 0) are left to Ceres' own tolerances.
class StatisticalConvergence : public ceres::IterationCallback {
 public:
  StatisticalConvergence(int dof, double fraction) : dof_(dof), fraction_(fraction) {}
  ceres::CallbackReturnType operator()(const ceres::IterationSummary& s) override {
    if (s.iteration == 0 || !s.step_is_successful || dof_ <= 0) return ceres::SOLVER_CONTINUE;
    const double chi2_per_dof = 2.0 * s.cost / dof_;
    return s.cost_change < fraction_ * chi2_per_dof ? ceres::SOLVER_TERMINATE_SUCCESSFULLY
                                                    : ceres::SOLVER_CONTINUE;
  }

 private:
  int dof_;
  double fraction_;
};

// The calibrated volume of `chain`: the box of the stations' reported positions. Outside it the
// explicit terms continue to first order (linear) when they follow a physical term, whose residual
// they model (paper preset's best chain, validation over the floor: 2.03-3.73x against 2.34-4.59x
// clamped), and are clamped when they model the whole distortion alone. That choice was made on a
// range-weighted degree-4 polynomial (111-118x clamped, 124-143x linear); the paper's unweighted
// fit measures 29.6-31.5x clamped, 26.6-31.3x linear (fit/best_chain_sim_test.cc, seeds 1-3), so
// linear would not be worse there: open (docs/calibration-file.md).
CalibratedVolume VolumeOf(const std::vector<FitStation>& stations, const CorrectionChain& chain) {
  CalibratedVolume volume;
  volume.extrapolation = ExtrapolationPolicy::kClamp;
  for (size_t t = 0; t < chain.size(); ++t) {
    if (!chain.term(t).GuardedByVolume()) volume.extrapolation = ExtrapolationPolicy::kLinear;
  }
  volume.min = volume.max = stations[0].reported.translation;
  for (const auto& s : stations) {
    volume.min = volume.min.cwiseMin(s.reported.translation);
    volume.max = volume.max.cwiseMax(s.reported.translation);
  }
  // A flat axis (all stations in one plane) still needs a non-empty box.
  for (int k = 0; k < 3; ++k) {
    if (volume.max[k] <= volume.min[k]) {
      volume.min[k] -= 1e-3;
      volume.max[k] += 1e-3;
    }
  }
  return volume;
}

// Parameter reports, term descriptions, the chain with its calibrated volume, timing.
void FinishResult(const std::vector<FitStation>& stations, ModelSpec* spec,
                  std::chrono::steady_clock::time_point start, FitResult* out) {
  FitResult& result = *out;
  // Ceres reports CONVERGENCE for a cost that is infinite from the start (its relative change is
  // NaN, which passes its function tolerance): a model whose noise is so small that the whitened
  // residuals overflow was "converged" at its start values, and its calibration written.
  if (!std::isfinite(result.final_cost)) {
    result.converged = false;
    result.termination_type = "FAILURE";
    result.solver_message += std::string(result.solver_message.empty() ? "" : "; ") +
                             "the final cost is not finite (" + std::to_string(result.final_cost) +
                             "): the whitened residuals overflow or cannot be evaluated";
  }
  // A term's own note explains what the covariance's per-coordinate flags show (thousands of
  // them for an undetermined polynomial), so the notes come first.
  std::vector<IdentifiabilityFlag> notes;
  for (const auto& term : spec->terms) {
    for (const auto& block : term->blocks()) {
      if (!block.identifiability_note.empty() && !block.fixed) {
        notes.push_back({(block.term.empty() ? term->name() : block.term) + "." + block.name,
                         block.identifiability_note});
      }
    }
  }
  result.identifiability_flags.insert(result.identifiability_flags.begin(), notes.begin(),
                                      notes.end());
  for (const auto& term : spec->terms) {
    for (const auto& block : term->blocks()) {
      ParameterReport r;
      r.term = block.term.empty() ? term->name() : block.term;
      r.block = block.name;
      r.unit = block.unit;
      r.fixed = block.fixed;
      r.coordinate_names = block.coordinate_names;
      r.values = block.values;
      r.stddev = block.stddev;
      r.covariance = block.covariance;
      if (block.stddev.size() != block.values.size()) {  // a manifold block: tangent stds
        r.stddev_names = block.tangent_names;
        r.stddev_unit = block.tangent_unit;
      }
      result.parameters.push_back(std::move(r));
    }
    nlohmann::json d = term->Describe();
    d["name"] = term->name();
    d["type"] = term->type();
    d["prepared"] = term->PreparedState();  // for a later fit's start (FitStartFromJson)
    result.terms.push_back(d);
  }

  result.chain = ModelToChain(spec->terms);
  result.chain.SetVolume(VolumeOf(stations, result.chain));
  // Stations whose physical inverse is not converged or ambiguous under the fitted model: their
  // corrected pose is a bounded best guess or one of several, so their residual says little.
  for (const auto& s : stations) {
    const CorrectionStatus status = result.chain.Apply(s.reported).status;
    if (status != CorrectionStatus::kConverged) result.unresolved.push_back({s.station, status});
  }
  result.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
}

// The stations the chain at `spec`'s current values does not resolve (its physical inverse finds
// an ambiguous root or none), as ModelSpec::leave_out_unresolved sees them; `count` gets how many.
std::vector<bool> UnresolvedStations(const std::vector<FitStation>& stations, const ModelSpec& spec,
                                     size_t* count) {
  CorrectionChain chain = ModelToChain(spec.terms);
  chain.SetVolume(VolumeOf(stations, chain));
  std::vector<bool> out(stations.size(), false);
  *count = 0;
  for (size_t i = 0; i < stations.size(); ++i) {
    out[i] = chain.Apply(stations[i].reported).status != CorrectionStatus::kConverged;
    *count += out[i] ? 1 : 0;
  }
  return out;
}

bool WithinLeftOutLimit(size_t count, size_t total) {
  return static_cast<double>(count) <= kMaxLeftOutFraction * static_cast<double>(total);
}

// The joint problem of FitModel's step (2) over `stations`, with the terms' current values (no
// preparation or initialisation: FitModel has done it, or a fold refit reuses the full fit's).
// `time_offset` (with time_offset0 its reference value) is the clock offset block when it is fitted.
struct BuiltProblem {
  std::unique_ptr<ceres::Problem> problem;
  std::vector<ceres::ResidualBlockId> station_blocks;  // one per station, in station order
  int num_free = 0;  // tangent size of the free term blocks (the time offset not counted)
  // Per station: its report-noise amplification at the values the problem was built with, and
  // whether the threshold capped it (PoseMetricOf).
  std::vector<double> noise_gain;
  std::vector<bool> noise_whitened;
  std::vector<std::optional<Matrix6>> noise_metric;  // each station's K (PoseMetricOf)
  // Per station: its residual through a physical group is in report form (StationBinding::
  // pose_form false), weighed by noise_metric.
  std::vector<bool> report_form;
  // The terms' extra residual blocks weighted relative to the noise sigma
  // (ModelTerm::ExtraResidualsRelativeToNoise): the sandwich scales their information.
  std::vector<ceres::ResidualBlockId> noise_relative_blocks;
  // The others: gauge constraints (CovarianceOptions::hard_constraints).
  std::vector<ceres::ResidualBlockId> constraint_blocks;
};

// noise.amplification_threshold at or above which no station gets a pose metric: each residual
// through a physical group is then in report form, its report's misfit as it is
// (docs/model-file.md).
constexpr double kNoPoseMetric = 1e9;

// The terms' bindings for one station at their current values (a LUT cell per station).
std::vector<BoundTerm> BindStation(const ModelSpec& spec, const FitStation& station) {
  std::vector<BoundTerm> bound;
  AmbientPose pose = ToAmbient(station.reported);
  TermEvaluation eval;
  for (const auto& term : spec.terms) {
    BoundTerm b{term.get(), term->Bind(pose)};
    term->Evaluate(b.binding, BoundValues({b}).data(), pose, false, &eval);
    pose = eval.output;
    bound.push_back(std::move(b));
  }
  return bound;
}

// The residual form of a station through a physical group. Where the group's runtime inverse
// resolves the report, the pose form: the root Newton reaches from the reference, the residual the
// runtime's pose error is, exact (the report form agrees with it to first order only: O(d^2 /
// range) and K held between passes; measured on the workflow capture, hidden toolbox seed 1, the
// report form everywhere left a background candidate's held-out error 0.7 % lower where the pose
// form had 11.9 %, and the loop stopped without it). Elsewhere (no root or an ambiguous one, next
// to a strong object) the report form under the capped metric K, defined and differentiated
// exactly where the pose form's Newton steps reach no root and Levenberg-Marquardt stalled
// (docs/fit.md). The amplification does not choose the form: K follows the values, and a fit that
// could move stations into the capped report form by raising their amplification did (paper
// capture, toolbox, step-3 model plus a background: 192 stations, validation 1.097 mm mean against
// 0.890 with the form chosen by the inverse alone). A station once in report form stays in it for
// the fit's later passes (`report_before`), so the passes end. `held_forms` (one per station): the
// forms as given, none chosen (a fold refit keeps the full fit's).
BuiltProblem BuildProblem(const std::vector<FitStation>& stations, ModelSpec* spec,
                          double* time_offset, std::optional<double> time_offset0,
                          const std::vector<bool>* report_before = nullptr,
                          const std::vector<bool>* held_forms = nullptr) {
  CHECK(!held_forms || held_forms->size() == stations.size());
  BuiltProblem out;
  out.problem = std::make_unique<ceres::Problem>();
  ceres::Problem& problem = *out.problem;
  int& num_free = out.num_free;
  std::vector<ceres::ResidualBlockId>& station_blocks = out.station_blocks;
  for (auto& term : spec->terms) {
    for (auto& block : term->blocks()) {
      if (block.values.empty()) continue;
      problem.AddParameterBlock(block.values.data(), block.size());
      if (block.make_manifold) problem.SetManifold(block.values.data(), block.make_manifold());
    }
  }
  {
    // The bindings are fixed at the initial values (a LUT cell per station).
    std::vector<std::vector<BoundTerm>> bound(stations.size());
    for (size_t i = 0; i < stations.size(); ++i) bound[i] = BindStation(*spec, stations[i]);
    // The group's runtime inverse at the current values (the model file allows one group, first).
    // Held forms (a fold refit) decide every station's form without it.
    std::unique_ptr<Correction> group_correction;
    if (!held_forms && !spec->terms.empty() && spec->terms[0]->UsesTarget()) {
      try {
        group_correction = spec->terms[0]->ToCorrection();
      } catch (const std::exception&) {
        group_correction.reset();  // off the model's domain: every station in report form
      }
    }
    for (size_t i = 0; i < stations.size(); ++i) {
      std::vector<double*> blocks;
      for (const auto& b : bound[i]) {
        for (int j : b.binding.blocks) {
          blocks.push_back(const_cast<ModelTerm*>(b.term)->blocks()[static_cast<size_t>(j)].values.data());
        }
      }
      if (time_offset) blocks.push_back(time_offset);
      const Eigen::Vector2d station_sigmas = spec->StationSigmas(stations[i].reported);
      const bool group = std::any_of(bound[i].begin(), bound[i].end(),
                                     [](const BoundTerm& b) { return b.term->UsesTarget(); });
      const bool metric_used = group && spec->amplification_threshold < kNoPoseMetric;
      bool report = group;
      // A report in the other hemisphere than its reference (a Fastrak flip, -p) is a bad report,
      // not a fold of the model: in pose form it stays 2 |p| off, for a robust loss to reject. The
      // report form compares it with the mirrored pose's signal, which a fit can bend to (measured,
      // workflow capture, hemisphere flips seed 3: from the previous step's optimum, the frame,
      // floor plane and background fitted with the 3 flips in report form ended at cost 44
      // against 117, the plane 0.34 m away and 42 deg off, validation 0.153 mm against 0.062).
      const bool flipped =
          IsHemisphereFlip(stations[i].reported.translation, stations[i].reference.translation);
      if (metric_used && held_forms) {
        report = (*held_forms)[i];
      } else if (metric_used && flipped) {
        report = false;
      } else if (metric_used && !(report_before && i < report_before->size() &&
                                  (*report_before)[i]) && group_correction) {
        const CorrectedPose runtime = group_correction->Apply(stations[i].reported);
        if (runtime.status == CorrectionStatus::kConverged) report = false;
      }
      // The pose metric of a station in report form (PoseMetricOf); a chain without a physical
      // group, and a station in pose form, is fitted exactly as its residual is.
      PoseMetric metric;
      if (metric_used && report) {
        const double dt = time_offset && time_offset0 ? *time_offset - *time_offset0 : 0.0;
        metric = PoseMetricOf(StationReportPerPose(bound[i], stations[i], station_sigmas[0],
                                                   station_sigmas[1], dt),
                              spec->amplification_threshold);
      } else if (metric_used) {
        for (auto& b : bound[i]) {
          if (b.term->UsesTarget()) b.binding.pose_form = true;
        }
      }
      out.report_form.push_back(report);
      out.noise_gain.push_back(metric.gain);
      out.noise_metric.push_back(metric.k);
      out.noise_whitened.push_back(report && metric.gain > spec->amplification_threshold);
      station_blocks.push_back(
          problem.AddResidualBlock(new StationCost(bound[i], stations[i], station_sigmas[0],
                                                   station_sigmas[1], time_offset0, metric.k),
                                   MakeLoss(spec->loss), blocks));
    }
  }
  for (size_t k = 0; k < spec->terms.size(); ++k) {
    const bool relative = spec->terms[k]->ExtraResidualsRelativeToNoise();
    std::vector<ceres::ResidualBlockId> before;
    problem.GetResidualBlocks(&before);
    spec->terms[k]->AddExtraResiduals(&problem, InputsOfTerm(stations, *spec, k));
    std::vector<ceres::ResidualBlockId> after;
    problem.GetResidualBlocks(&after);
    if (after.size() == before.size()) continue;  // none added (most terms)
    const std::set<ceres::ResidualBlockId> old(before.begin(), before.end());
    for (ceres::ResidualBlockId id : after) {
      if (old.count(id)) continue;
      (relative ? out.noise_relative_blocks : out.constraint_blocks).push_back(id);
    }
  }
  for (auto& term : spec->terms) {
    for (auto& block : term->blocks()) {
      if (block.values.empty() || !problem.HasParameterBlock(block.values.data())) continue;
      double* data = block.values.data();
      if (block.fixed) {
        problem.SetParameterBlockConstant(data);
        continue;
      }
      num_free += problem.ParameterBlockTangentSize(data);
      for (int i = 0; i < block.size(); ++i) {
        if (!block.lower.empty() && std::isfinite(block.lower[static_cast<size_t>(i)])) {
          problem.SetParameterLowerBound(data, i, block.lower[static_cast<size_t>(i)]);
        }
        if (!block.upper.empty() && std::isfinite(block.upper[static_cast<size_t>(i)])) {
          problem.SetParameterUpperBound(data, i, block.upper[static_cast<size_t>(i)]);
        }
      }
      if (!block.prior_mean.empty()) {
        Eigen::MatrixXd a = Eigen::MatrixXd::Zero(block.size(), block.size());
        Eigen::VectorXd b(block.size());
        for (int i = 0; i < block.size(); ++i) {
          a(i, i) = 1.0 / block.prior_sigma[static_cast<size_t>(i)];
          b[i] = block.prior_mean[static_cast<size_t>(i)];
        }
        problem.AddResidualBlock(new ceres::NormalPrior(a, b), nullptr, data);
      }
    }
  }

  return out;
}

// Passes of FitModel's solve with the stations' pose metrics (PoseMetricOf) rebuilt at the
// solution (IRLS), while one changes by more than kMetricChange (relative, Frobenius norm; the
// metric's directions move, not only its largest amplification). Measured on the paper capture
// (seed 2): the demo's step-3 model, with and without a background field, settles in 2-3.
constexpr int kMaxMetricPasses = 8;
constexpr double kMetricChange = 0.05;
// Solves of ModelSpec::leave_out_unresolved after the first, each without the stations the
// previous solution left unresolved.
constexpr int kMaxLeaveOutPasses = 3;

// True if any station's pose metric in `after` differs from `before`'s by more than kMetricChange
// (or one of them could not be evaluated): worth another solve.
bool MetricChanged(const BuiltProblem& before, const BuiltProblem& after) {
  // A station that left the pose form changed its residual, with or without a metric (a null K:
  // its A could not be evaluated).
  if (before.report_form != after.report_form) return true;
  for (size_t i = 0; i < before.noise_metric.size(); ++i) {
    const auto& a = before.noise_metric[i];
    const auto& b = after.noise_metric[i];
    if (a.has_value() != b.has_value()) return true;
    if (!a) continue;
    if (!((*b - *a).norm() <= kMetricChange * a->norm())) return true;
  }
  return false;
}

// The linear solver for the normal equations of `problem` (num_free tangent coordinates). Small
// problems and problems whose J^T J is mostly filled (a polynomial's coefficient blocks and the
// physical blocks are shared by every station) get dense Cholesky: a sparse factorisation of a
// dense matrix pays the sparse bookkeeping (block outer products, supernode analysis) for no
// saving. Problems with many local blocks (a LUT's nodes: each station touches the 8 of its cell)
// stay sparse; above kMaxDenseNormal coordinates the dense matrix alone would cost too much memory
// and O(n^3) time.
// Above this many free coordinates the normal equations are sparse (72 MB of dense normal matrix).
constexpr int kMaxDenseNormal = 3000;
// The statistical stop's default above kMaxDenseNormal (the fold refits' rule, StatisticalConvergence).
constexpr double kLargeProblemStatisticalTolerance = 5e-3;

ceres::LinearSolverType ChooseLinearSolver(const ceres::Problem& problem, int num_free) {
  constexpr int kAlwaysDense = 400;      // dense below this size whatever the structure
  constexpr double kDenseFill = 0.25;  // fraction of J^T J's entries that are structurally non-zero
  if (num_free <= kAlwaysDense) return ceres::DENSE_NORMAL_CHOLESKY;
  if (num_free > kMaxDenseNormal) return ceres::SPARSE_NORMAL_CHOLESKY;
  // Structural non-zeros of J^T J: every pair of free blocks that share a residual block.
  std::vector<ceres::ResidualBlockId> residual_blocks;
  problem.GetResidualBlocks(&residual_blocks);
  std::set<std::pair<const double*, const double*>> pairs;
  double nonzeros = 0.0;
  std::vector<double*> used;
  for (ceres::ResidualBlockId id : residual_blocks) {
    problem.GetParameterBlocksForResidualBlock(id, &used);
    for (double* a : used) {
      if (problem.IsParameterBlockConstant(a)) continue;
      for (double* b : used) {
        if (problem.IsParameterBlockConstant(b) || !pairs.emplace(a, b).second) continue;
        nonzeros += static_cast<double>(problem.ParameterBlockTangentSize(a)) *
                    problem.ParameterBlockTangentSize(b);
      }
    }
  }
  const double n = num_free;
  return nonzeros >= kDenseFill * n * n ? ceres::DENSE_NORMAL_CHOLESKY
                                        : ceres::SPARSE_NORMAL_CHOLESKY;
}

// Why stream samples got the model covariance instead of the sandwich (covariance_message).
std::string StreamModelCovarianceMessage(int num_samples, int max_clusters) {
  return "stream samples (serially correlated): model covariance instead of the sandwich, " +
         (max_clusters == 0 ? std::string("as solver.stream_clusters is 0")
                            : std::to_string(num_samples) + " samples are too few for " +
                                  std::to_string(max_clusters) + " time runs of 5") +
         "; ";
}

}  // namespace

// True for stations that are samples of a stream rather than static stations: most of them
// less than 0.5 s after the previous one of the same sensor (a static station averages a second or
// more of samples; several sensors sample at the same times). Stations without distinct times (all
// 0) count as static.
bool SerialSamples(const std::vector<FitStation>& stations) {
  std::map<int, std::vector<double>> times_of_sensor;
  for (const auto& s : stations) times_of_sensor[s.sensor].push_back(s.time);
  int close = 0, distinct = 0;
  for (auto& [sensor, times] : times_of_sensor) {
    std::sort(times.begin(), times.end());
    for (size_t i = 1; i < times.size(); ++i) {
      const double dt = times[i] - times[i - 1];
      if (dt > 0.0) {
        ++distinct;
        if (dt < 0.5) ++close;
      }
    }
  }
  return distinct > 0 && 2 * distinct >= static_cast<int>(stations.size()) && 2 * close > distinct;
}

// The sandwich's clusters for stream samples (ModelSpec::stream_clusters): the cluster of each
// sample, contiguous runs of about equal count in time, or empty (the model covariance) when
// `max_clusters` is 0 or there are fewer than 5 samples per run. The model's misfit is smooth
// along the path, so neighbouring samples' scores are correlated, and a sandwich over single
// samples understates how far that shared misfit moves the estimates (docs/fit.md, "Standard
// deviations"). Samples that share a time stay in one run (several sensors).
std::vector<int> TimeClusters(const std::vector<FitStation>& stations, int max_clusters,
                              int min_per_cluster) {
  const int n = static_cast<int>(stations.size());
  if (max_clusters <= 0 || n < std::max(1, min_per_cluster) * max_clusters) return {};
  std::vector<int> order(static_cast<size_t>(n));
  std::iota(order.begin(), order.end(), 0);
  auto time = [&](int k) { return stations[static_cast<size_t>(order[static_cast<size_t>(k)])].time; };
  std::stable_sort(order.begin(), order.end(), [&](int a, int b) {
    return stations[static_cast<size_t>(a)].time < stations[static_cast<size_t>(b)].time;
  });
  std::vector<int> cluster(static_cast<size_t>(n), 0);
  int run = 0;
  for (int k = 0; k < n; ++k) {
    const int wanted = static_cast<int>(static_cast<long>(k) * max_clusters / n);
    if (wanted > run && time(k) != time(k - 1)) run = wanted;
    cluster[static_cast<size_t>(order[static_cast<size_t>(k)])] = run;
  }
  return cluster;
}

std::vector<int> SerialTestBlocks(const std::vector<FitStation>& stations, int serial_blocks,
                                  int folds) {
  if (serial_blocks <= 0 || !SerialSamples(stations)) return {};
  const int n = static_cast<int>(stations.size());
  double first = std::numeric_limits<double>::infinity(), last = -first;
  for (const auto& s : stations) {
    if (!std::isfinite(s.time)) continue;
    first = std::min(first, s.time);
    last = std::max(last, s.time);
  }
  const double duration = last > first ? last - first : 0.0;
  int blocks = std::min({serial_blocks, n / kSerialBlockMinSamples,
                         static_cast<int>(std::floor(duration / kSerialBlockMinSeconds))});
  // Never fewer blocks than folds, nor back to per-sample folds and tests: a short stream gets
  // `folds` blocks, whose test cannot reach a small p (5 blocks: 1/32), which is what it can show.
  blocks = std::max(blocks, folds);
  if (n < blocks) return {};
  std::vector<int> block = TimeClusters(stations, blocks, /*min_per_cluster=*/1);
  // Numbered densely (samples sharing a time stay together and can skip a number).
  std::map<int, int> dense;
  for (int b : block) dense.emplace(b, 0);
  int next = 0;
  for (auto& [b, d] : dense) d = next++;
  for (int& b : block) b = dense[b];
  return block;
}

std::vector<int> CrossValidationFolds(const std::vector<FitStation>& stations, int folds,
                                      int serial_blocks, bool* by_blocks) {
  const std::vector<int> block = SerialTestBlocks(stations, serial_blocks, folds);
  if (by_blocks) *by_blocks = !block.empty();
  std::vector<int> fold_of(stations.size());
  for (size_t i = 0; i < stations.size(); ++i) {
    fold_of[i] =
        block.empty() ? static_cast<int>(i % static_cast<size_t>(folds)) : block[i] % folds;
  }
  return fold_of;
}

std::string CrossValidationTableName(int folds, bool by_blocks) {
  return "cross-validation (" + std::to_string(folds) + "-fold" +
         (by_blocks ? ", blocks of time" : "") + ")";
}

std::string TimeOffsetMimicryNote(double variance_inflation) {
  auto fixed1 = [](double v) {
    char buf[32];
    std::snprintf(buf, sizeof(buf), "%.1f", v);
    return std::string(buf);
  };
  return "shares " + fixed1(100.0 * (1.0 - 1.0 / variance_inflation)) +
         " % of its information with the other parameters (variance inflation " +
         fixed1(variance_inflation) +
         "): along this stream's path they can mimic a time shift, so the offset and its stddev "
         "are not reliable; record a longer or more varied stream, or fit the offset with a lower "
         "polynomial degree";
}

namespace {

// The model-file term (type, name) a block belongs to.
std::pair<std::string, std::string> BlockOwner(const ModelSpec& spec, const ModelTerm& term,
                                               const ParameterBlock& block) {
  if (block.term.empty()) return {term.type(), term.name()};
  for (const auto& f : spec.file_terms) {
    if (f.name == block.term) return {f.type, f.name};
  }
  return {term.type(), block.term};
}

// "FILE:LINE:COLUMN: PATH" of the model file's `parameters:` setting of `block` of the spec's term
// k, else of the file entries the term holds; empty without either (a spec not from a file).
std::string WhereInModelFile(const ModelSpec& spec, size_t k, const ParameterBlock& block) {
  if (k < spec.block_settings.size()) {
    const std::string family = block.name.substr(0, block.name.find('['));
    for (const BlockSettings& s : spec.block_settings[k]) {
      if ((s.term.empty() || s.term == block.term) &&
          (s.block == block.name || s.block == family) && !s.where.empty()) {
        return s.where;
      }
    }
  }
  std::string where;
  for (const ModelFileTerm& f : spec.file_terms) {
    if (f.model_term != static_cast<int>(k) || f.where.empty()) continue;
    if (!block.term.empty() && f.name != block.term) continue;
    where += (where.empty() ? "" : ", ") + f.where;
  }
  return where;
}

// FitOptions::start for one prepared and initialised term: its free blocks that `start` holds
// take its values. When any does, or when a later term is held (`precedes_held`), the term's
// other free blocks (an effect added to a physical group, or a group added before the
// polynomial) go back to `before`, their values before the term's initialisation: the model
// file's starts, which the group's own refinement (without the terms after it) moved away.
void StartBlocksFrom(const FitStart& start, const ModelSpec& spec,
                     const std::vector<std::vector<double>>& before, bool precedes_held,
                     ModelTerm* term) {
  // Finite values within the block's bounds (those of a search included).
  auto admissible = [](const ParameterBlock& block, const std::vector<double>& v) {
    for (size_t i = 0; i < v.size(); ++i) {
      if (!std::isfinite(v[i]) || (!block.lower.empty() && v[i] < block.lower[i]) ||
          (!block.upper.empty() && v[i] > block.upper[i])) {
        return false;
      }
    }
    return true;
  };
  std::vector<bool> taken(term->blocks().size(), false);
  for (size_t k = 0; k < term->blocks().size(); ++k) {
    ParameterBlock& block = term->blocks()[k];
    if (block.fixed) continue;
    const auto t = start.terms.find(BlockOwner(spec, *term, block));
    if (t == start.terms.end()) continue;
    const auto b = t->second.blocks.find(block.name);
    if (b == t->second.blocks.end() || b->second.size() != block.values.size() ||
        !admissible(block, b->second)) {
      continue;
    }
    std::copy(b->second.begin(), b->second.end(), block.values.begin());
    taken[k] = true;
  }
  if (!precedes_held && std::find(taken.begin(), taken.end(), true) == taken.end()) return;
  for (size_t k = 0; k < term->blocks().size(); ++k) {
    ParameterBlock& block = term->blocks()[k];
    if (taken[k] || block.fixed || k >= before.size() || before[k].size() != block.values.size()) {
      continue;
    }
    if (admissible(block, before[k])) block.values = before[k];
  }
  // A block that moves only within a subspace (a polynomial's determined directions) keeps the
  // component of its start outside it for the whole fit: a start from a fit that determined more
  // directions (another station set, `max_amplification: 0`) would freeze its share of the
  // undetermined ones. Projected onto the subspace, as the term's own initialisation lies.
  for (ParameterBlock& block : term->blocks()) {
    if (block.fixed || block.ambient_from_tangent.size() == 0) continue;
    const Eigen::MatrixXd& b = block.ambient_from_tangent;
    Eigen::Map<Eigen::VectorXd> v(block.values.data(), block.size());
    const Eigen::VectorXd projected = b * (b.transpose() * b).ldlt().solve(b.transpose() * v);
    v = projected;
  }
}

}  // namespace

bool EvaluateStationResidual(const ModelSpec& spec, const FitStation& station,
                             std::optional<double> time_offset,
                             Eigen::Matrix<double, 6, 1>* residual,
                             std::vector<Eigen::MatrixXd>* jacobians,
                             std::optional<Eigen::Matrix<double, 6, 6>>* report_per_pose) {
  const Eigen::Vector2d sigmas = spec.StationSigmas(station.reported);
  const std::vector<BoundTerm> bound = BindStation(spec, station);
  const StationCost cost(bound, station, sigmas[0], sigmas[1],
                         time_offset ? std::optional<double>(0.0) : std::nullopt);
  std::vector<const double*> values = BoundValues(bound);
  std::vector<double*> jacobian_ptrs;
  const std::vector<int32_t>& sizes = cost.parameter_block_sizes();
  jacobians->clear();
  for (int32_t size : sizes) jacobians->push_back(Eigen::MatrixXd(6, size));
  std::vector<Eigen::Matrix<double, 6, Eigen::Dynamic, Eigen::RowMajor>> row_major(sizes.size());
  for (size_t b = 0; b < sizes.size(); ++b) {
    row_major[b].resize(6, sizes[b]);
    jacobian_ptrs.push_back(row_major[b].data());
  }
  if (time_offset) values.push_back(&*time_offset);
  if (values.size() != sizes.size()) return false;
  if (!cost.Evaluate(values.data(), residual->data(), jacobian_ptrs.data())) return false;
  for (size_t b = 0; b < sizes.size(); ++b) (*jacobians)[b] = row_major[b];
  if (report_per_pose != nullptr) {
    *report_per_pose =
        StationReportPerPose(bound, station, sigmas[0], sigmas[1], time_offset.value_or(0.0));
  }
  return true;
}

FitStart TakeFitStart(const ModelSpec& fitted) {
  FitStart start;
  if (fitted.time_offset && !fitted.time_offset->fixed) {
    start.time_offset = fitted.time_offset->value;
  }
  for (const auto& term : fitted.terms) {
    start.terms[{term->type(), term->name()}].prepared = term->PreparedState();
    for (const auto& block : term->blocks()) {
      start.terms[BlockOwner(fitted, *term, block)].blocks[block.name] = block.values;
    }
  }
  return start;
}

FitStart FitStartFromJson(const nlohmann::json& fit, const std::string& source,
                          const std::string& json_path) {
  // `field`: the path below `fit` ("" for fit itself, ".terms[0]").
  auto fail = [&](const std::string& field, const std::string& what) {
    throw JsonInputError(source, json_path + field,
                         what + " (expected the \"fit\" of trackcal-fit fit --json)");
  };
  if (!fit.is_object()) fail("", "not an object");
  if (!fit.contains("terms") || !fit["terms"].is_array()) fail(".terms", "missing");
  if (!fit.contains("parameters") || !fit["parameters"].is_array()) {
    fail(".parameters", "missing");
  }
  FitStart start;
  start.source = source;
  std::map<std::string, std::string> type_of;  // model-file term name -> type
  for (size_t i = 0; i < fit["terms"].size(); ++i) {
    const nlohmann::json& t = fit["terms"][i];
    const std::string at = ".terms[" + std::to_string(i) + "]";
    if (!t.is_object() || !t.contains("name") || !t["name"].is_string() || !t.contains("type") ||
        !t["type"].is_string()) {
      fail(at, "needs a name and a type");
    }
    const std::string name = t["name"].get<std::string>(), type = t["type"].get<std::string>();
    start.terms[{type, name}].prepared = t.value("prepared", nlohmann::json());
    type_of[name] = type;
    if (t.contains("effects") && t["effects"].is_array()) {
      for (const auto& e : t["effects"]) {
        if (e.is_object() && e.contains("name") && e["name"].is_string() && e.contains("type") &&
            e["type"].is_string()) {
          type_of[e["name"].get<std::string>()] = e["type"].get<std::string>();
        }
      }
    }
  }
  for (size_t i = 0; i < fit["parameters"].size(); ++i) {
    const nlohmann::json& p = fit["parameters"][i];
    const std::string at = ".parameters[" + std::to_string(i) + "]";
    if (!p.is_object() || !p.contains("term") || !p["term"].is_string() || !p.contains("block") ||
        !p["block"].is_string() || !p.contains("values") || !p["values"].is_array()) {
      fail(at, "needs a term, a block and values");
    }
    const std::string term = p["term"].get<std::string>();
    if (term == "time_offset") {  // the clock offset the fit estimated (not a model term)
      const auto& v = p["values"];
      if (v.size() != 1 || !v[0].is_object() || !v[0].contains("value") ||
          !v[0]["value"].is_number()) {
        fail(at + ".values", "a clock offset needs one numeric value");
      }
      start.time_offset = v[0]["value"].get<double>();
      continue;
    }
    const auto type = type_of.find(term);
    if (type == type_of.end()) fail(at + ".term", "'" + term + "' is not among fit.terms");
    std::vector<double> values;
    for (const auto& v : p["values"]) {
      if (!v.is_object() || !v.contains("value") || !v["value"].is_number()) {
        fail(at + ".values", "each needs a numeric value");
      }
      values.push_back(v["value"].get<double>());
    }
    start.terms[{type->second, term}].blocks[p["block"].get<std::string>()] = std::move(values);
  }
  return start;
}

FitResult FitModel(const std::vector<FitStation>& stations, ModelSpec* spec,
                   const FitOptions& options) {
  if (!options.Check()) throw std::invalid_argument("FitOptions: num_threads must be >= 1");
  if (spec->terms.empty()) throw std::invalid_argument("model has no terms");
  if (stations.empty()) throw std::invalid_argument("no calibration stations");
  const auto start = std::chrono::steady_clock::now();
  const Eigen::Vector2d sigmas(spec->position_sigma, spec->orientation_sigma);

  for (size_t k = 0; k < spec->terms.size(); ++k) {
    std::vector<const ModelTerm*> later;
    for (size_t j = k + 1; j < spec->terms.size(); ++j) later.push_back(spec->terms[j].get());
    spec->terms[k]->SetFollowingTerms(later);
    std::vector<const ModelTerm*> earlier;
    for (size_t j = 0; j < k; ++j) earlier.push_back(spec->terms[j].get());
    spec->terms[k]->SetPrecedingTerms(earlier);
  }

  // (1) prepare and initialise term by term.
  std::vector<bool> linear_ok;
  for (size_t k = 0; k < spec->terms.size(); ++k) {
    ModelTerm& term = *spec->terms[k];
    bool from_start = false;
    if (options.start) {
      const auto t = options.start->terms.find({term.type(), term.name()});
      try {
        from_start =
            term.AdoptPreparedState(t != options.start->terms.end() ? t->second.prepared : nullptr);
      } catch (const std::exception& e) {  // also nlohmann's, whose messages name nothing
        throw std::invalid_argument(
            (options.start->source.empty() ? std::string("start") : options.start->source) +
            ": fit.terms: '" + term.name() + "' prepared: " + e.what());
      }
    }
    const std::vector<FitStation> inputs = InputsOfTerm(stations, *spec, k);
    try {
      term.Prepare(inputs);
    } catch (const std::invalid_argument& e) {
      // What only the data reveal (a LUT cell too fine for the stations' box) names the entry
      // of the model file, as the parser's errors do.
      std::string where;
      for (const ModelFileTerm& f : spec->file_terms) {
        if (f.model_term != static_cast<int>(k) || f.where.empty()) continue;
        where += (where.empty() ? "" : ", ") + f.where;
      }
      if (where.empty()) throw;
      throw std::invalid_argument(where + ": " + e.what());
    }
    if (k < spec->block_settings.size()) ApplyBlockSettings(spec->block_settings[k], &term);
    std::vector<std::vector<double>> before;  // the file's starts, for FitOptions::start
    if (from_start) {
      for (const auto& block : term.blocks()) before.push_back(block.values);
    }
    linear_ok.push_back(term.InitializeLinear(inputs, sigmas));
    if (spec->loss.type != LossType::kNone && term.SolvesAloneLinearly()) {
      // With a robust loss a linear term starts from zero, not from its least-squares solution:
      // that bends to an isolated gross outlier (a hemisphere flip reports -p, where no other
      // station constrains a polynomial) and the loss then keeps that basin (measured, workflow
      // capture, hemisphere_flips seed 1: the two flips fitted to within 3 sigma, the other
      // stations' held-out error 1.96 mm instead of ~0.6). From zero, an outlier's residual is far
      // beyond the loss scale from the first iteration and the loss ignores it.
      // (Within a block's bounds: zero on them when they exclude it.)
      for (auto& block : term.blocks()) {
        if (block.fixed) continue;
        for (size_t i = 0; i < block.values.size(); ++i) {
          double v = 0.0;
          if (!block.lower.empty()) v = std::max(v, block.lower[i]);
          if (!block.upper.empty()) v = std::min(v, block.upper[i]);
          block.values[i] = v;
        }
      }
    }
    // (A lone linear term's fit is its initialisation: nothing to start from.)
    if (from_start && !(spec->terms.size() == 1 && term.SolvesAloneLinearly())) {
      bool precedes_held = false;
      for (size_t j = k + 1; j < spec->terms.size(); ++j) {
        const auto t = options.start->terms.find({spec->terms[j]->type(), spec->terms[j]->name()});
        precedes_held =
            precedes_held || (t != options.start->terms.end() && !t->second.blocks.empty());
      }
      StartBlocksFrom(*options.start, *spec, before, precedes_held, &term);
    }
    // A start refused here (the values an initialisation left) names the block's settings in the
    // model file, or the term's entry, as the parser's errors do.
    for (const auto& block : term.blocks()) {
      try {
        block.Check(term.name());
      } catch (const std::invalid_argument& e) {
        const std::string where = WhereInModelFile(*spec, k, block);
        if (where.empty()) throw;
        throw std::invalid_argument(where + ": " + e.what());
      }
    }
  }

  const double seconds_initialize =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();

  // A clock offset fitted with the model: streams whose stations carry reference velocities and a
  // model file whose time_offset is not fixed (fit/terms_time_offset.h).
  bool moving = false;
  for (const auto& s : stations) {
    moving = moving || !s.reference_velocity.isZero() || !s.reference_angular_velocity.isZero();
  }
  const bool fit_time_offset = moving && spec->time_offset && !spec->time_offset->fixed;
  double time_offset = fit_time_offset ? spec->time_offset->value : 0.0;
  if (fit_time_offset && options.start && options.start->time_offset &&
      std::isfinite(*options.start->time_offset)) {
    time_offset = *options.start->time_offset;  // the stations stay paired at the file's value
  }
  const std::optional<double> time_offset0 =
      fit_time_offset ? std::optional<double>(spec->time_offset->value) : std::nullopt;

  // Fast path: a lone linear term (the paper's method) is solved by its linear least squares. Its
  // model covariance is the term's own; a sandwich needs the station residual blocks, so then the
  // problem below is built at the linear solution (not solved again) for the covariance alone.
  std::optional<FitResult> linear_solution;
  if (spec->terms.size() == 1 && linear_ok[0] && spec->terms[0]->SolvesAloneLinearly() &&
      spec->loss.type == LossType::kNone && spec->position_range_exponent == 0.0 &&
      spec->orientation_range_exponent == 0.0 && !fit_time_offset) {
    bool plain = true;
    for (const auto& block : spec->terms[0]->blocks()) {
      plain = plain && block.lower.empty() && block.upper.empty() && block.prior_mean.empty();
    }
    if (plain) {
      FitResult result;
      ModelTerm& term = *spec->terms[0];
      result.converged = true;
      result.termination_type = "CONVERGENCE";
      result.solver_message = "linear least squares (paper eq. 9)";
      result.linear_least_squares = true;
      const auto correction = term.ToCorrection();
      const double limit = 5.0;
      for (const auto& s : stations) {
        const Rigid3d c = correction->Apply(s.reported).pose;
        const AmbientPose a = ToAmbient(c);
        double r[6];
        StationResidual<double>(a.data(), s.reference, spec->position_sigma,
                                spec->orientation_sigma, r);
        double s2 = 0.0;
        for (double v : r) s2 += v * v;
        result.final_cost += 0.5 * s2;
        if (std::sqrt(s2 / 6.0) > limit) result.outliers.push_back({s.station, std::sqrt(s2 / 6.0)});
      }
      result.initial_cost = result.final_cost;
      result.num_residuals = 6 * static_cast<int>(stations.size());
      for (auto& block : term.blocks()) {
        block.stddev.assign(block.values.size(), std::numeric_limits<double>::quiet_NaN());
        if (!block.fixed) result.num_free_parameters += block.free_size();
      }
      const int dof = result.num_residuals - result.num_free_parameters;
      result.chi2_per_dof =
          dof > 0 ? 2.0 * result.final_cost / dof : std::numeric_limits<double>::quiet_NaN();
      // (None of a fit that failed: FinishResult.)
      const bool covariance =
          options.compute_covariance && spec->covariance && std::isfinite(result.final_cost);
      if (options.compute_covariance && spec->covariance && !covariance) {
        result.covariance_message = "not computed: the fit failed";
      }
      // Stream samples without time runs keep the model covariance (see the covariance section
      // below).
      const bool stream_samples =
          (moving || SerialSamples(stations)) && TimeClusters(stations, spec->stream_clusters).empty();
      if (!covariance || spec->covariance_estimator == CovarianceEstimator::kModel ||
          stream_samples) {
        const auto covariance_start = std::chrono::steady_clock::now();
        result.seconds_solve = std::chrono::duration<double>(covariance_start - start).count();
        result.seconds_initialize = seconds_initialize;
        if (covariance) {
          if (term.LinearCovariance(sigmas)) {
            result.covariance_estimator = "model";
            result.covariance_method = "linear";
            if (stream_samples && spec->covariance_estimator == CovarianceEstimator::kSandwich) {
              result.covariance_message = StreamModelCovarianceMessage(
                  static_cast<int>(stations.size()), spec->stream_clusters);
            }
          } else {
            result.covariance_message = "linear covariance unavailable";
          }
        }
        result.seconds_covariance = std::chrono::duration<double>(
                                        std::chrono::steady_clock::now() - covariance_start)
                                        .count();
        FinishResult(stations, spec, start, &result);
        return result;
      }
      linear_solution = std::move(result);
    }
  }

  // (2) the joint problem.
  FitResult result;
  BuiltProblem built =
      BuildProblem(stations, spec, fit_time_offset ? &time_offset : nullptr, time_offset0);
  int num_free = built.num_free;

  if (fit_time_offset) num_free += 1;
  ceres::Solver::Options solver_options;
  solver_options.max_num_iterations = spec->max_iterations;
  solver_options.function_tolerance = spec->function_tolerance;
  solver_options.gradient_tolerance = 1e-14;
  solver_options.parameter_tolerance = 1e-12;
  solver_options.num_threads = options.num_threads;
  solver_options.linear_solver_type =
      options.linear_solver ? *options.linear_solver : ChooseLinearSolver(*built.problem, num_free);
  ProgressCallback callback(options.progress ? options.progress : [](int, double) {});
  if (options.progress) {
    solver_options.callbacks.push_back(&callback);
    solver_options.update_state_every_iteration = false;
  }
  // The statistical stop is the default where every iteration costs a sparse factorisation (above
  // kMaxDenseNormal free coordinates: a LUT chain). Measured on bench_fit.py's plane + dipole +
  // 150 mm LUT (3608 coordinates): 21 -> 9 iterations, 6.8 -> 4.6 s CPU; the cost 0.5 chi2 higher
  // by 1.5e-4 (every parameter within ~0.02 sigma of the tight solution), validation mean +3e-6 mm.
  // Below it the file's setting alone (the fast/exact cross-validation of small candidates moved
  // by 6 % with it, docs/benchmarks.md).
  const double statistical_tolerance =
      spec->statistical_tolerance > 0.0 ? spec->statistical_tolerance
      : num_free > kMaxDenseNormal      ? kLargeProblemStatisticalTolerance
                                        : 0.0;
  StatisticalConvergence statistical(built.problem->NumResiduals() - num_free,
                                     statistical_tolerance);
  if (statistical_tolerance > 0.0) solver_options.callbacks.push_back(&statistical);
  ceres::Solver::Summary summary;
  if (linear_solution) {
    // Solved linearly above; the problem is only the covariance's.
    result = std::move(*linear_solution);
  }
  double first_initial_cost = 0.0;
  if (!linear_solution && num_free > 0) {
    SolveWithProgress(solver_options, built.problem.get(), &summary, &callback);
    result.linear_solver = ceres::LinearSolverTypeToString(solver_options.linear_solver_type);
    first_initial_cost = summary.initial_cost >= 0.0 ? summary.initial_cost
                                                     : std::numeric_limits<double>::quiet_NaN();
    result.iterations = static_cast<int>(summary.iterations.size()) - 1;
    result.whitening_passes = 1;
    // The pose metrics and the residual forms depend on the values (a station's amplification
    // follows the fitted object): rebuilt at the solution and solved again while they change, as
    // iteratively reweighted least squares (a station leaves the pose form at most once). A chain
    // without a physical group has none and is solved once.
    for (; result.whitening_passes < kMaxMetricPasses; ++result.whitening_passes) {
      BuiltProblem next = BuildProblem(stations, spec, fit_time_offset ? &time_offset : nullptr,
                                       time_offset0, &built.report_form);
      if (!MetricChanged(built, next)) break;
      built = std::move(next);
      SolveWithProgress(solver_options, built.problem.get(), &summary, &callback);
      result.iterations += static_cast<int>(summary.iterations.size()) - 1;
    }
  }
  // ModelSpec::leave_out_unresolved: solved again without the static stations the solution does
  // not resolve, while that set changes (a station resolved again comes back).
  std::vector<FitStation> kept_stations;
  const std::vector<FitStation>* fitted = &stations;
  std::vector<bool> left_out_mask(stations.size(), false);  // `built` is of the others
  if (spec->leave_out_unresolved && !linear_solution && num_free > 0 && !fit_time_offset) {
    std::vector<bool> left(stations.size(), false);
    for (int pass = 0; pass < kMaxLeaveOutPasses; ++pass) {
      size_t count = 0;
      const std::vector<bool> now = UnresolvedStations(stations, *spec, &count);
      if (!WithinLeftOutLimit(count, stations.size())) {
        result.left_out_note = std::to_string(count) + " of " + std::to_string(stations.size()) +
                               " stations unresolved, more than " +
                               std::to_string(std::lround(100 * kMaxLeftOutFraction)) +
                               " %: none left out";
        if (std::find(left.begin(), left.end(), true) != left.end()) {
          // An earlier pass left some out: solved again on every station, as the note says.
          left.assign(stations.size(), false);
          fitted = &stations;
          built = BuildProblem(stations, spec, nullptr, time_offset0);
          num_free = built.num_free;
          SolveWithProgress(solver_options, built.problem.get(), &summary, &callback);
          result.iterations += static_cast<int>(summary.iterations.size()) - 1;
        }
        break;
      }
      if (now == left) break;
      left = now;
      kept_stations.clear();
      for (size_t i = 0; i < stations.size(); ++i) {
        if (!left[i]) kept_stations.push_back(stations[i]);
      }
      fitted = &kept_stations;
      built = BuildProblem(*fitted, spec, nullptr, time_offset0);
      num_free = built.num_free;
      SolveWithProgress(solver_options, built.problem.get(), &summary, &callback);
      result.iterations += static_cast<int>(summary.iterations.size()) - 1;
    }
    for (size_t i = 0; i < stations.size(); ++i) {
      if (left[i]) result.left_out.push_back(stations[i].station);
    }
    if (result.left_out.empty()) fitted = &stations;
    left_out_mask = left;
  }
  ceres::Problem& problem = *built.problem;
  const std::vector<ceres::ResidualBlockId>& station_blocks = built.station_blocks;
  if (!spec->terms.empty() && spec->terms[0]->UsesTarget()) {
    CHECK_EQ(built.report_form.size(), fitted->size());
    result.report_form.assign(stations.size(), true);
    for (size_t i = 0, k = 0; i < stations.size(); ++i) {
      if (!left_out_mask[i]) result.report_form[i] = built.report_form[k++];
      if (!left_out_mask[i] && result.report_form[i]) {
        result.report_form_stations.push_back(stations[i].station);
      }
    }
  }
  for (size_t i = 0; i < fitted->size(); ++i) {
    if (built.noise_whitened[i]) {
      result.noise_whitened.push_back({(*fitted)[i].station, built.noise_gain[i]});
    }
  }
  if (!linear_solution) {
    result.converged = num_free == 0 || summary.termination_type == ceres::CONVERGENCE ||
                       summary.termination_type == ceres::USER_SUCCESS;
    result.termination_type =
        num_free == 0 ? "CONVERGENCE" : ceres::TerminationTypeToString(summary.termination_type);
    result.solver_message = num_free == 0 ? "no free parameters" : summary.message;
    // A solve that failed before its first iteration has none (Ceres' count is then 0, not 1).
    result.iterations = std::max(result.iterations, 0);
    result.num_residuals = problem.NumResiduals();
    result.num_free_parameters = num_free;
    {
      // A problem that cannot be evaluated has no cost (it read 0, a perfect fit, with chi2/dof 0).
      double cost = 0.0;
      if (!problem.Evaluate(ceres::Problem::EvaluateOptions(), &cost, nullptr, nullptr, nullptr)) {
        cost = std::numeric_limits<double>::quiet_NaN();
      }
      result.final_cost = cost;
      result.initial_cost = num_free == 0 ? cost : first_initial_cost;
    }
    const int dof = result.num_residuals - num_free;
    result.chi2_per_dof = dof > 0 ? 2.0 * result.final_cost / dof : std::numeric_limits<double>::quiet_NaN();

    // Outliers: the raw (un-robustified) whitened station residual.
    {
      ceres::Problem::EvaluateOptions eo;
      eo.residual_blocks = station_blocks;
      eo.apply_loss_function = false;
      std::vector<double> residuals;
      problem.Evaluate(eo, nullptr, &residuals, nullptr, nullptr);
      const double limit = spec->loss.type == LossType::kNone ? 5.0 : spec->loss.scale;
      for (size_t i = 0; i < fitted->size(); ++i) {
        double s2 = 0.0;
        for (int k = 0; k < 6; ++k) s2 += residuals[i * 6 + static_cast<size_t>(k)] * residuals[i * 6 + static_cast<size_t>(k)];
        const double rms = std::sqrt(s2 / 6.0);
        if (rms > limit) result.outliers.push_back({(*fitted)[i].station, rms});
      }
    }
  }

  // (3) covariance.
  const auto covariance_start = std::chrono::steady_clock::now();
  result.seconds_solve = std::chrono::duration<double>(covariance_start - start).count();
  result.seconds_initialize = seconds_initialize;
  std::vector<CovarianceBlock> cov_blocks;
  std::vector<std::pair<size_t, size_t>> cov_index;  // (term, block) of each requested block
  for (size_t t = 0; t < spec->terms.size(); ++t) {
    auto& blocks = spec->terms[t]->blocks();
    for (size_t b = 0; b < blocks.size(); ++b) {
      blocks[b].stddev.assign(blocks[b].values.size(), std::numeric_limits<double>::quiet_NaN());
      blocks[b].covariance.clear();
      if (blocks[b].fixed || blocks[b].values.empty()) continue;
      CovarianceBlock cb;
      cb.values = blocks[b].values.data();
      cb.name = (blocks[b].term.empty() ? spec->terms[t]->name() : blocks[b].term) + "." +
                blocks[b].name;
      cb.coordinate_names = blocks[b].coordinate_names;
      if (blocks[b].make_manifold) {
        cb.coordinate_names = blocks[b].tangent_names;
        cb.tangent_scale = blocks[b].tangent_scale;
      }
      cb.max_stddev = blocks[b].identifiability_scale;
      // Only each block's own covariance is kept below: cross-covariances would cost a LUT chain
      // a solve per coordinate (fit/covariance.h).
      cb.cross_covariance = false;
      cov_blocks.push_back(cb);
      cov_index.emplace_back(t, b);
    }
  }
  if (fit_time_offset) {
    CovarianceBlock cb;
    cb.values = &time_offset;
    cb.name = "time_offset";
    cb.coordinate_names = {"dt"};
    cov_blocks.push_back(cb);
  }
  double time_offset_stddev = std::numeric_limits<double>::quiet_NaN();
  // None of a fit that failed (a final cost that is not finite, FinishResult): its Jacobian is
  // not finite either, and diagnose's candidate fits crashed in the covariance's eigensolver.
  const bool finite_cost = std::isfinite(result.final_cost);
  if (!finite_cost && options.compute_covariance && spec->covariance) {
    result.covariance_message = "not computed: the fit failed";
  }
  if (options.compute_covariance && spec->covariance && !cov_blocks.empty() && finite_cost) {
    CovarianceOptions co;
    co.num_threads = options.num_threads;
    // One cluster per static station: its 6 residuals share the station's noise. Stream samples
    // are not independent (the model's misfit is smooth along the path): runs of them in time
    // (TimeClusters), or, when there are too few (or stream_clusters is 0), the model covariance
    // (a per-sample sandwich would be optimistic).
    co.estimator = spec->covariance_estimator;
    co.clusters = station_blocks;
    co.noise_relative = built.noise_relative_blocks;
    co.hard_constraints = built.constraint_blocks;
    const bool stream_samples = moving || SerialSamples(*fitted);
    if (stream_samples) {
      co.cluster_groups = TimeClusters(*fitted, spec->stream_clusters);
      if (co.cluster_groups.empty()) co.estimator = CovarianceEstimator::kModel;
    }
    const CovarianceResult cov = ComputeCovariance(&problem, cov_blocks, co);
    result.covariance_message = cov.message;
    if (co.estimator != spec->covariance_estimator) {
      result.covariance_message +=
          StreamModelCovarianceMessage(static_cast<int>(fitted->size()), spec->stream_clusters);
    }
    if (cov.success) {
      result.covariance_estimator = cov.estimator;
      result.covariance_clusters = cov.num_clusters;
      result.covariance_method = cov.method;
    }
    result.rank_deficient = cov.rank_deficient;
    result.identifiability_flags = cov.flags;
    if (cov.success) {
      // With the model estimator the stds assume the model's sigmas (chi2_per_dof tells whether
      // they fit); the sandwich estimator does not (fit/covariance.h).
      if (fit_time_offset) {
        const int t = cov.block_offsets[cov_index.size()];
        time_offset_stddev = cov.stddev[t];
        if (cov.variance_inflation.size() > t) {
          result.time_offset_variance_inflation = cov.variance_inflation(t);
          const double vif = result.time_offset_variance_inflation;
          if (vif > kMaxTimeOffsetVarianceInflation) {
            result.identifiability_flags.push_back(
                {"time_offset.dt", TimeOffsetMimicryNote(vif) +
                                       " (docs/diagnose.md, Known limits)"});
          }
        }
      }
      for (size_t i = 0; i < cov_index.size(); ++i) {
        auto& block = spec->terms[cov_index[i].first]->blocks()[cov_index[i].second];
        const int offset = cov.block_offsets[i];
        const int tangent = problem.ParameterBlockTangentSize(block.values.data());
        if (block.ambient_from_tangent.size() > 0) {
          // A linear subspace: the values' own covariance, B C B^T.
          const Eigen::MatrixXd& b = block.ambient_from_tangent;
          const Eigen::MatrixXd c = b * cov.covariance.block(offset, offset, tangent, tangent) *
                                    b.transpose();
          const auto n = static_cast<size_t>(c.rows());
          block.stddev.resize(n);
          block.covariance.resize(n * n);
          for (size_t r = 0; r < n; ++r) {
            block.stddev[r] = std::sqrt(std::max(0.0, c(static_cast<Eigen::Index>(r),
                                                          static_cast<Eigen::Index>(r))));
            for (size_t k = 0; k < n; ++k) {
              block.covariance[r * n + k] =
                  c(static_cast<Eigen::Index>(r), static_cast<Eigen::Index>(k));
            }
          }
          continue;
        }
        // Manifold blocks: one std per tangent coordinate (tangent_names, tangent_unit).
        block.stddev.resize(static_cast<size_t>(tangent));
        for (int k = 0; k < tangent; ++k) block.stddev[static_cast<size_t>(k)] = cov.stddev[offset + k];
        block.covariance.resize(static_cast<size_t>(tangent * tangent));
        for (int r = 0; r < tangent; ++r) {
          for (int k = 0; k < tangent; ++k) {
            block.covariance[static_cast<size_t>(r * tangent + k)] = cov.covariance(offset + r, offset + k);
          }
        }
      }
    }
  }
  result.seconds_covariance =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - covariance_start).count();
  FinishResult(stations, spec, start, &result);
  if (fit_time_offset) {
    spec->time_offset->value = time_offset;
    ParameterReport r;
    r.term = "time_offset";
    r.block = "value";
    r.unit = "s";
    r.coordinate_names = {"dt"};
    r.values = {time_offset};
    r.stddev = {time_offset_stddev};
    result.parameters.push_back(std::move(r));
  }
  return result;
}

namespace {

// A free parameter block of a problem, in the order of the Jacobian's columns.
struct FreeBlock {
  double* values = nullptr;
  int size = 0;
  int tangent = 0;
  int offset = 0;                             // first column
  const ceres::Manifold* manifold = nullptr;  // null: Euclidean
  const ParameterBlock* block = nullptr;      // bounds
};

// Cost, residuals and dense Jacobian (columns: the free blocks' tangent spaces) of `blocks`.
// False if a term cannot be evaluated at the current values.
bool EvaluateDense(ceres::Problem* problem, const std::vector<ceres::ResidualBlockId>& blocks,
                   const std::vector<double*>& parameters, int columns, double* cost,
                   Eigen::VectorXd* residuals, Eigen::MatrixXd* jacobian) {
  ceres::Problem::EvaluateOptions eo;
  eo.residual_blocks = blocks;
  eo.parameter_blocks = parameters;
  std::vector<double> r;
  ceres::CRSMatrix crs;
  if (!problem->Evaluate(eo, cost, residuals ? &r : nullptr, nullptr, jacobian ? &crs : nullptr)) {
    return false;
  }
  if (!std::isfinite(*cost)) return false;
  if (residuals)
    *residuals = Eigen::Map<const Eigen::VectorXd>(r.data(), static_cast<Eigen::Index>(r.size()));
  if (jacobian) {
    jacobian->setZero(crs.num_rows, columns);
    for (int row = 0; row < crs.num_rows; ++row) {
      for (int k = crs.rows[static_cast<size_t>(row)]; k < crs.rows[static_cast<size_t>(row) + 1];
           ++k) {
        (*jacobian)(row, crs.cols[static_cast<size_t>(k)]) = crs.values[static_cast<size_t>(k)];
      }
    }
  }
  return true;
}

// Copies the lower triangle (where rankUpdate writes) to the upper one.
void Symmetrize(Eigen::MatrixXd* h) { *h = Eigen::MatrixXd(h->selfadjointView<Eigen::Lower>()); }

// Steps of the normal equations H delta = -g for any Levenberg-Marquardt damping lambda from one
// eigendecomposition of the Jacobi-scaled H (D H D, D = diag(H)^-1/2): delta(lambda) =
// -D V (Lambda + lambda)^-1 V^T D g, i.e. (H + lambda diag(H)) delta = -g, so trying another
// damping costs no factorisation. Eigenvalues below 1e-10 of the largest are dropped (pseudo-
// inverse): directions the data do not determine (a coil gain the polynomial's linear term absorbs)
// keep their values instead of taking huge steps that cancel only to first order; 1e-10 because
// J^T J squares J's condition number, so smaller eigenvalues of the scaled matrix are rounding.
class DampedSteps {
 public:
  DampedSteps(const Eigen::MatrixXd& h, const Eigen::VectorXd& g) { Init(h, g); }
  // With the coordinates `held` removed from the normal equations (their steps are 0).
  DampedSteps(Eigen::MatrixXd h, Eigen::VectorXd g, const std::vector<Eigen::Index>& held) {
    for (Eigen::Index c : held) {
      h.row(c).setZero();
      h.col(c).setZero();
      g[c] = 0.0;
    }
    Init(h, g);
  }
  double max_eigenvalue() const { return max_lambda_; }
  // The step for damping `mu` (in units of the scaled matrix) and the decrease of the quadratic
  // model it predicts, -(g^T delta + delta^T H delta / 2).
  Eigen::VectorXd Step(double mu, double* predicted) const {
    Eigen::VectorXd y = Eigen::VectorXd::Zero(b_.size());
    double p = 0.0;
    for (Eigen::Index k = 0; k < b_.size(); ++k) {
      if (!(lambda_[k] > 1e-10 * max_lambda_)) continue;
      const double denominator = lambda_[k] + mu;
      y[k] = -b_[k] / denominator;
      p += b_[k] * b_[k] / denominator - 0.5 * lambda_[k] * y[k] * y[k];
    }
    *predicted = p;
    return d_.asDiagonal() * (v_ * y);
  }

 private:
  void Init(const Eigen::MatrixXd& h, const Eigen::VectorXd& g) {
    const Eigen::Index n = h.rows();
    d_.resize(n);
    for (Eigen::Index i = 0; i < n; ++i) d_[i] = h(i, i) > 0 ? 1.0 / std::sqrt(h(i, i)) : 1.0;
    const Eigen::MatrixXd a = d_.asDiagonal() * h * d_.asDiagonal();
    const Eigen::SelfAdjointEigenSolver<Eigen::MatrixXd> es(a);
    lambda_ = es.eigenvalues();
    v_ = es.eigenvectors();
    max_lambda_ = std::max(lambda_.maxCoeff(), std::numeric_limits<double>::min());
    b_ = v_.transpose() * (d_.asDiagonal() * g);
  }

  Eigen::VectorXd d_, lambda_, b_;
  Eigen::MatrixXd v_;
  double max_lambda_ = 0.0;
};

// A free coordinate with bounds (blocks without a manifold: the step is in the ambient coordinate).
struct BoundedCoordinate {
  Eigen::Index column = 0;
  const double* value = nullptr;  // the current value
  double lower = -std::numeric_limits<double>::infinity();
  double upper = std::numeric_limits<double>::infinity();
};

// The coordinates on one of their bounds whose Gauss-Newton step (of H delta = -g with the others
// held) points out of it. On a bound means within 1e-12 of it relative to max(1, |bound|): the
// solver's projected steps leave a value exactly on it.
std::vector<Eigen::Index> HeldAtBound(const std::vector<BoundedCoordinate>& bounded,
                                      const Eigen::MatrixXd& h, const Eigen::VectorXd& g) {
  std::vector<std::pair<Eigen::Index, int>> on_bound;  // (column, -1 lower / +1 upper)
  for (const auto& b : bounded) {
    const double v = *b.value;
    if (std::isfinite(b.lower) && v <= b.lower + 1e-12 * std::max(1.0, std::abs(b.lower))) {
      on_bound.emplace_back(b.column, -1);
    } else if (std::isfinite(b.upper) && v >= b.upper - 1e-12 * std::max(1.0, std::abs(b.upper))) {
      on_bound.emplace_back(b.column, +1);
    }
  }
  std::vector<Eigen::Index> held;
  if (on_bound.empty()) return held;
  // Release one at a time is the exact active-set rule; one pass (hold those whose step points
  // out, given the others free) is enough for the one or two bounds a physical term has.
  double unused = 0.0;
  const Eigen::VectorXd step = DampedSteps(h, g).Step(0.0, &unused);
  for (const auto& [column, side] : on_bound) {
    if (side * step[column] > 0.0) held.push_back(column);
  }
  return held;
}

}  // namespace

std::vector<FoldRefit> RefitFoldsFromFull(const std::vector<FitStation>& stations, ModelSpec* spec,
                                          const std::vector<int>& fold_of, int folds,
                                          const FoldRefitOptions& options) {
  if (!options.Check()) throw std::invalid_argument("FoldRefitOptions: invalid settings");
  if (folds < 2) throw std::invalid_argument("fold refits need at least 2 folds");
  if (fold_of.size() != stations.size()) {
    throw std::invalid_argument("fold refits: one fold index per station needed");
  }
  std::vector<size_t> training_count(static_cast<size_t>(folds), 0);
  for (int f : fold_of) {
    if (f < 0 || f >= folds) throw std::invalid_argument("fold refits: fold index out of range");
  }
  for (int f = 0; f < folds; ++f) {
    for (int g : fold_of) training_count[static_cast<size_t>(f)] += g != f ? 1 : 0;
    if (training_count[static_cast<size_t>(f)] == 0) {
      throw std::invalid_argument("fold refits: fold " + std::to_string(f) + " leaves no stations");
    }
  }
  for (const auto& s : stations) {
    if ((!s.reference_velocity.isZero() || !s.reference_angular_velocity.isZero()) &&
        spec->time_offset && !spec->time_offset->fixed) {
      // FitModel shifts the reference relative to the offset the streams were paired with, which
      // the fitted spec no longer holds.
      throw std::invalid_argument("fold refits: a fitted clock offset needs full refits");
    }
  }

  // The full fit's left-out stations (FoldRefitOptions::left_out) train no fold.
  const std::set<int> left_out(options.left_out.begin(), options.left_out.end());
  std::vector<bool> excluded(stations.size(), false);
  for (size_t i = 0; i < stations.size(); ++i) excluded[i] = left_out.count(stations[i].station);

  if (!options.report_form.empty() && options.report_form.size() != stations.size()) {
    throw std::invalid_argument("fold refits: one residual form per station needed");
  }
  const std::vector<bool>* held_forms =
      options.report_form.empty() ? nullptr : &options.report_form;
  BuiltProblem built = BuildProblem(stations, spec, nullptr, std::nullopt, nullptr, held_forms);
  ceres::Problem& problem = *built.problem;
  std::vector<FreeBlock> free;
  std::vector<double*> parameters;
  int n = 0;
  for (auto& term : spec->terms) {
    for (auto& block : term->blocks()) {
      double* data = block.values.data();
      if (block.values.empty() || !problem.HasParameterBlock(data) ||
          problem.IsParameterBlockConstant(data)) {
        continue;
      }
      FreeBlock fb;
      fb.values = data;
      fb.size = block.size();
      fb.tangent = problem.ParameterBlockTangentSize(data);
      fb.offset = n;
      fb.manifold = problem.GetManifold(data);
      fb.block = &block;
      n += fb.tangent;
      free.push_back(fb);
      parameters.push_back(data);
    }
  }
  std::vector<BoundedCoordinate> free_bounds;
  for (const auto& fb : free) {
    const ParameterBlock& pb = *fb.block;
    if (fb.manifold || (pb.lower.empty() && pb.upper.empty())) continue;
    for (int k = 0; k < fb.size; ++k) {
      BoundedCoordinate c;
      c.column = fb.offset + k;
      c.value = fb.values + k;
      if (!pb.lower.empty()) c.lower = pb.lower[static_cast<size_t>(k)];
      if (!pb.upper.empty()) c.upper = pb.upper[static_cast<size_t>(k)];
      free_bounds.push_back(c);
    }
  }
  std::vector<std::vector<double>> full_values;
  for (const auto& fb : free) full_values.emplace_back(fb.values, fb.values + fb.size);
  auto set_values = [&](const std::vector<std::vector<double>>& v) {
    for (size_t b = 0; b < free.size(); ++b) std::copy(v[b].begin(), v[b].end(), free[b].values);
  };
  auto current_values = [&] {
    std::vector<std::vector<double>> v;
    for (const auto& fb : free) v.emplace_back(fb.values, fb.values + fb.size);
    return v;
  };
  // theta (+) delta; false if a value leaves its bounds or the manifold refuses the step.
  auto plus = [&](const std::vector<std::vector<double>>& theta, const Eigen::VectorXd& delta) {
    for (size_t b = 0; b < free.size(); ++b) {
      const FreeBlock& fb = free[b];
      if (fb.manifold) {
        if (!fb.manifold->Plus(theta[b].data(), delta.data() + fb.offset, fb.values)) return false;
      } else {
        for (int k = 0; k < fb.size; ++k)
          fb.values[k] = theta[b][static_cast<size_t>(k)] + delta[fb.offset + k];
      }
      const ParameterBlock& pb = *fb.block;
      for (int k = 0; k < fb.size; ++k) {
        const size_t kk = static_cast<size_t>(k);
        if (!pb.lower.empty() && fb.values[k] < pb.lower[kk]) return false;
        if (!pb.upper.empty() && fb.values[k] > pb.upper[kk]) return false;
      }
    }
    return true;
  };

  std::vector<ceres::ResidualBlockId> all_blocks, others;
  problem.GetResidualBlocks(&all_blocks);
  {
    std::set<ceres::ResidualBlockId> station_set(built.station_blocks.begin(),
                                                 built.station_blocks.end());
    for (auto id : all_blocks) {
      if (!station_set.count(id)) others.push_back(id);
    }
  }
  auto training_blocks = [&](int f) {
    std::vector<ceres::ResidualBlockId> blocks;
    for (size_t i = 0; i < stations.size(); ++i) {
      if (fold_of[i] != f && !excluded[i]) blocks.push_back(built.station_blocks[i]);
    }
    blocks.insert(blocks.end(), others.begin(), others.end());
    return blocks;
  };
  auto training_stations = [&](int f, std::vector<bool>* forms) {
    std::vector<FitStation> train;
    for (size_t i = 0; i < stations.size(); ++i) {
      if (fold_of[i] != f) {
        train.push_back(stations[i]);
        if (held_forms) forms->push_back((*held_forms)[i]);
      }
    }
    return train;
  };
  auto finish = [&](const std::vector<FitStation>& train, FoldRefit* out) {
    out->stayed_at_full_fit = n > 0 && current_values() == full_values;
    out->chain = ModelToChain(spec->terms);
    out->chain.SetVolume(VolumeOf(train, out->chain));
  };
  // The fallback: the solver on the fold's stations, from the current values (as FitModel's (2));
  // `train` holds every training station (the calibrated volume's, as FitModel's), the left-out
  // ones are not solved for.
  // `train_forms`: their held forms (empty: chosen afresh).
  auto solver_refit = [&](const std::vector<FitStation>& train,
                          const std::vector<bool>& train_forms, FoldRefit* out) {
    out->solver_refit = true;
    std::vector<FitStation> solved;
    std::vector<bool> solved_forms;
    for (size_t j = 0; j < train.size(); ++j) {
      if (left_out.count(train[j].station)) continue;
      solved.push_back(train[j]);
      if (!train_forms.empty()) solved_forms.push_back(train_forms[j]);
    }
    BuiltProblem fold = BuildProblem(solved, spec, nullptr, std::nullopt, nullptr,
                                     train_forms.empty() ? nullptr : &solved_forms);
    if (fold.num_free > 0) {
      ceres::Solver::Options so;
      so.max_num_iterations = spec->max_iterations;
      so.function_tolerance = spec->function_tolerance;
      so.gradient_tolerance = 1e-14;
      so.parameter_tolerance = 1e-12;
      so.linear_solver_type = ChooseLinearSolver(*fold.problem, fold.num_free);
      ceres::Solver::Summary summary;
      ceres::Solve(so, fold.problem.get(), &summary);
    }
    finish(train, out);
  };

  std::vector<FoldRefit> out(static_cast<size_t>(folds));
  double full_cost = 0.0;
  Eigen::VectorXd full_r;
  Eigen::MatrixXd full_j;
  std::vector<ceres::ResidualBlockId> ordered = built.station_blocks;  // station i: rows 6i..6i+5
  ordered.insert(ordered.end(), others.begin(), others.end());
  const bool dense = n > 0 && n <= options.max_dense_parameters &&
                     EvaluateDense(&problem, ordered, parameters, n, &full_cost, &full_r, &full_j);
  Eigen::MatrixXd full_h;
  Eigen::VectorXd full_g;
  if (dense) {
    // Left-out stations' rows contribute nothing (their residuals are in `ordered` only to keep
    // station i at rows 6i..6i+5).
    for (size_t i = 0; i < stations.size(); ++i) {
      if (!excluded[i]) continue;
      full_j.middleRows(static_cast<Eigen::Index>(6 * i), 6).setZero();
      full_r.segment(static_cast<Eigen::Index>(6 * i), 6).setZero();
    }
    full_h = Eigen::MatrixXd::Zero(n, n);
    full_h.selfadjointView<Eigen::Lower>().rankUpdate(full_j.transpose());
    Symmetrize(&full_h);
    full_g = full_j.transpose() * full_r;
  }
  // The tolerance in units of the scatter the full fit leaves: the parameters' real uncertainty is
  // sqrt(chi2/dof) times the whitening's, and so is a negligible step, in both directions. A model
  // file whose noise overstates the stations' scatter (the default 1 mm / 0.2 deg against a
  // Fastrak's ~0.06 mm: chi2/dof ~ 0.001) made a fixed 5e-3 larger than any fold's whole change,
  // so every fold stopped at the full fit's values: its held-out predictions were in-sample, and
  // nonlinear candidates beat a linearly solved base by that leak (a dipole's "held-out" drop of
  // 3.6 %, p 4e-14, on data with no dipole; -1.3 % with exact folds).
  double tolerance = options.cost_tolerance;
  const Eigen::Index fitted_rows =
      full_r.size() - 6 * std::count(excluded.begin(), excluded.end(), true);
  if (dense && fitted_rows > n) {
    tolerance *= full_r.squaredNorm() / static_cast<double>(fitted_rows - n);
  }
  for (int f = 0; f < folds; ++f) {
    FoldRefit& result = out[static_cast<size_t>(f)];
    const auto fold_start = std::chrono::steady_clock::now();
    set_values(full_values);
    std::vector<bool> train_forms;
    const std::vector<FitStation> train = training_stations(f, &train_forms);
    if (n == 0) {
      finish(train, &result);
      continue;
    }
    if (!dense) {
      solver_refit(train, train_forms, &result);
      continue;
    }
    const std::vector<ceres::ResidualBlockId> blocks = training_blocks(f);
    // First linearisation: the full fit's, with the fold's station rows removed.
    Eigen::Index held = 0;
    for (int g : fold_of) held += g == f ? 6 : 0;
    Eigen::MatrixXd jf(held, n);
    Eigen::VectorXd rf(held);
    {
      Eigen::Index row = 0;
      for (size_t i = 0; i < stations.size(); ++i) {
        if (fold_of[i] != f) continue;
        jf.middleRows(row, 6) = full_j.middleRows(static_cast<Eigen::Index>(6 * i), 6);
        rf.segment(row, 6) = full_r.segment(static_cast<Eigen::Index>(6 * i), 6);
        row += 6;
      }
    }
    Eigen::MatrixXd h = full_h;
    h.selfadjointView<Eigen::Lower>().rankUpdate(jf.transpose(), -1.0);
    Symmetrize(&h);
    Eigen::VectorXd g = full_g - jf.transpose() * rf;
    double cost = 0.0;
    bool ok = EvaluateDense(&problem, blocks, parameters, n, &cost, nullptr, nullptr);
    bool converged = false;
    std::vector<std::vector<double>> theta = full_values;
    double mu = 0.0;  // damping: 0 is the Gauss-Newton step
    for (int step = 0; ok && step < options.max_steps; ++step) {
      if (step > 0) {
        Eigen::VectorXd r;
        Eigen::MatrixXd j;
        ++result.jacobian_evaluations;
        if (!EvaluateDense(&problem, blocks, parameters, n, &cost, &r, &j)) {
          ok = false;
          break;
        }
        h.setZero();
        h.selfadjointView<Eigen::Lower>().rankUpdate(j.transpose());
        Symmetrize(&h);
        g = j.transpose() * r;
      }
      // Coordinates the full fit left on a bound, where the step would leave it, stay there (as the
      // solver's projected steps keep them): stepped, every damped step was refused, and the fold
      // went to the solver (measured, the clock_offset loop's second diagnosis: a plane on its
      // distance bound sent 3 of 5 folds to the solver, 224 s of cross-validation; held, 36 s).
      const std::vector<Eigen::Index> held_at_bound = HeldAtBound(free_bounds, h, g);
      if (!held_at_bound.empty()) ++result.bound_steps;
      const DampedSteps steps = held_at_bound.empty() ? DampedSteps(h, g)
                                                      : DampedSteps(h, g, held_at_bound);
      double gauss_newton_decrease = 0.0;
      steps.Step(0.0, &gauss_newton_decrease);
      if (!std::isfinite(gauss_newton_decrease)) {
        ok = false;
        break;
      }
      // At the fold's optimum, to the tolerance (or to rounding, on a fit that leaves no scatter).
      if (gauss_newton_decrease < tolerance || gauss_newton_decrease <= 1e-13 * (1.0 + cost)) {
        converged = true;
        break;
      }
      // Levenberg-Marquardt: raise the damping until the fold's cost falls (a physical term is not
      // quadratic far from the full fit's values), lower it after steps the model predicted well.
      bool accepted = false;
      double predicted = 0.0, new_cost = cost;
      for (int tries = 0; tries < 12 && !accepted; ++tries) {
        Eigen::VectorXd delta = steps.Step(mu, &predicted);
        for (Eigen::Index c : held_at_bound) delta[c] = 0.0;
        set_values(theta);
        accepted = delta.allFinite() && plus(theta, delta) &&
                   EvaluateDense(&problem, blocks, parameters, n, &new_cost, nullptr, nullptr) &&
                   new_cost < cost;
        if (!accepted) mu = mu > 0 ? 4.0 * mu : 1e-4 * steps.max_eigenvalue();
      }
      if (!accepted) {
        set_values(theta);
        ok = false;
        break;
      }
      theta = current_values();
      ++result.steps;
      const double actual = cost - new_cost;
      cost = new_cost;
      const double ratio = actual / predicted;
      const bool undamped = mu == 0.0;
      if (ratio > 0.75) mu = mu < 1e-8 * steps.max_eigenvalue() ? 0.0 : mu / 4.0;
      if (ratio < 0.25) mu = std::max(4.0 * mu, 1e-4 * steps.max_eigenvalue());
      // Converged: the cost no longer falls by the tolerance (as the solver's function
      // tolerance), or a Gauss-Newton step whose quadratic model was right to within it landed at
      // the optimum (one step for a model linear in its parameters).
      if (actual < tolerance || (undamped && std::abs(actual - predicted) < tolerance)) {
        converged = true;
        break;
      }
    }
    set_values(theta);
    result.converged = converged;
    if (ok) {
      finish(train, &result);  // converged, or the best values after max_steps
    } else {
      // A step that could not lower the cost: the solver decides.
      solver_refit(train, train_forms, &result);
    }
    result.seconds =
        std::chrono::duration<double>(std::chrono::steady_clock::now() - fold_start).count();
  }
  set_values(full_values);
  return out;
}

Table1 EvaluateTable1(const CorrectionChain& chain, const std::vector<FitStation>& stations,
                      const std::string& set_name) {
  std::vector<Rigid3d> reported, corrected, reference;
  for (const auto& s : stations) {
    reported.push_back(s.reported);
    corrected.push_back(chain.Apply(s.reported).pose);
    reference.push_back(s.reference);
  }
  return MakeTable1(set_name, reported, corrected, reference);
}

Table1 CrossValidate(const std::vector<FitStation>& stations,
                     const std::function<ModelSpec()>& make_spec, int folds,
                     const std::function<void(int)>& on_fold, int serial_blocks) {
  if (folds < 2) throw std::invalid_argument("cross-validation needs at least 2 folds");
  if (static_cast<int>(stations.size()) < folds) {
    throw std::invalid_argument("cross-validation: fewer stations (" +
                                std::to_string(stations.size()) + ") than folds (" +
                                std::to_string(folds) + ")");
  }
  // Stream samples by blocks of time: with folds i % k every held-out sample's neighbours, a few
  // ms away and sharing its misfit, were trained on, and the "held-out" error was the in-sample
  // one (paper room, 30 s stream, sensor offset + degree-4 polynomial: 0.917 mm against 0.913 mm
  // in-sample, while a second stream of the same room was corrected to 1.46 mm; by blocks 2.33 mm,
  // docs/fit.md "Cross-validation of a stream").
  bool by_blocks = false;
  const std::vector<int> fold_of = CrossValidationFolds(stations, folds, serial_blocks, &by_blocks);
  std::vector<Rigid3d> reported, corrected, reference;
  for (int f = 0; f < folds; ++f) {
    if (on_fold) on_fold(f);
    std::vector<FitStation> train, test;
    for (size_t i = 0; i < stations.size(); ++i) {
      (fold_of[i] == f ? test : train).push_back(stations[i]);
    }
    ModelSpec spec = make_spec();
    FitOptions options;
    options.compute_covariance = false;
    const FitResult fit = FitModel(train, &spec, options);
    // A failed fold's chain holds its start values: its "held-out error" is not the model's.
    if (fit.Failed()) {
      throw std::runtime_error("cross-validation fold " + std::to_string(f + 1) + " of " +
                               std::to_string(folds) + ": the fit failed (" + fit.termination_type +
                               ": " + fit.solver_message + ")");
    }
    for (const auto& s : test) {
      reported.push_back(s.reported);
      corrected.push_back(fit.chain.Apply(s.reported).pose);
      reference.push_back(s.reference);
    }
  }
  return MakeTable1(CrossValidationTableName(folds, by_blocks), reported, corrected, reference);
}

namespace {
nlohmann::json SummaryToJson(const ErrorSummary& s) {
  return {{"count", s.count}, {"mean", s.mean}, {"std", s.std},     {"max", s.max},
          {"rms", s.rms},     {"median", s.median}, {"p95", s.p95}};
}
nlohmann::json PoseSummaryToJson(const PoseErrorSummary& s) {
  return {{"position_mm", SummaryToJson(s.position_mm)},
          {"orientation_deg", SummaryToJson(s.orientation_deg)}};
}
nlohmann::json NumberOrNull(double v) { return std::isfinite(v) ? nlohmann::json(v) : nlohmann::json(); }
}  // namespace

nlohmann::json Table1ToJson(const Table1& table) {
  return {
      {"set", table.set_name},
      {"hemisphere_flips_left_out", table.flips_left_out},
      {"before", PoseSummaryToJson(table.before)},
      {"after", PoseSummaryToJson(table.after)},
      // null where undefined (an error where there was none, an unknown mean): the calibration
      // file holds finite numbers only, and -inf made a fit on error-free data unsavable.
      {"improvement_percent",
       {{"position_mean", NumberOrNull(ImprovementPercent(table.before.position_mm.mean,
                                                          table.after.position_mm.mean))},
        {"orientation_mean", NumberOrNull(ImprovementPercent(table.before.orientation_deg.mean,
                                                             table.after.orientation_deg.mean))}}}};
}

nlohmann::json FitResult::ToJson() const {
  nlohmann::json params = nlohmann::json::array();
  for (const auto& p : parameters) {
    nlohmann::json values = nlohmann::json::array();
    for (size_t i = 0; i < p.values.size(); ++i) {
      values.push_back({{"name", i < p.coordinate_names.size() ? p.coordinate_names[i]
                                                               : p.block + "[" + std::to_string(i) + "]"},
                        {"value", p.values[i]},
                        {"stddev", NumberOrNull(p.stddev_names.empty() && i < p.stddev.size()
                                                    ? p.stddev[i]
                                                    : NAN)}});
    }
    nlohmann::json entry = {{"term", p.term}, {"block", p.block}, {"unit", p.unit},
                            {"fixed", p.fixed}, {"values", values}};
    if (!p.stddev_names.empty()) {
      // A manifold block: the stds are of its tangent coordinates, not of its values.
      nlohmann::json tangent = nlohmann::json::array();
      for (size_t i = 0; i < p.stddev_names.size(); ++i) {
        tangent.push_back({{"name", p.stddev_names[i]},
                           {"stddev", NumberOrNull(i < p.stddev.size() ? p.stddev[i] : NAN)}});
      }
      entry["tangent"] = tangent;
      entry["tangent_unit"] = p.stddev_unit;
    }
    params.push_back(entry);
  }
  nlohmann::json flags = nlohmann::json::array();
  for (const auto& f : identifiability_flags) flags.push_back({{"coordinate", f.coordinate}, {"reason", f.reason}});
  nlohmann::json out_flags = nlohmann::json::array();
  for (const auto& o : outliers) out_flags.push_back({{"station", o.station}, {"whitened_rms", o.whitened_rms}});
  nlohmann::json unresolved_json = nlohmann::json::array();
  for (const auto& u : unresolved) {
    unresolved_json.push_back({{"station", u.station}, {"status", CorrectionStatusName(u.status)}});
  }
  nlohmann::json amplified_json = nlohmann::json::array();
  for (const auto& a : noise_whitened) {
    amplified_json.push_back({{"station", a.station}, {"gain", NumberOrNull(a.gain)}});
  }
  return {{"converged", converged},
          {"termination_type", termination_type},
          {"linear_least_squares", linear_least_squares},
          {"solver_message", solver_message},
          {"linear_solver", linear_solver},
          {"iterations", iterations},
          {"initial_cost", initial_cost},
          {"final_cost", final_cost},
          {"num_residuals", num_residuals},
          {"num_free_parameters", num_free_parameters},
          {"chi2_per_dof", NumberOrNull(chi2_per_dof)},
          {"seconds", seconds},
          {"seconds_solve", seconds_solve},  // (seconds_initialize: progress messages only)
          {"seconds_covariance", seconds_covariance},
          {"rank_deficient", rank_deficient},
          {"covariance_message", covariance_message},
          {"covariance_estimator",
           covariance_estimator.empty() ? nlohmann::json() : nlohmann::json(covariance_estimator)},
          {"covariance_clusters", covariance_clusters},
          {"time_offset_variance_inflation", NumberOrNull(time_offset_variance_inflation)},
          {"covariance_method",
           covariance_method.empty() ? nlohmann::json() : nlohmann::json(covariance_method)},
          {"identifiability_flags", flags},
          {"outliers", out_flags},
          {"unresolved", unresolved_json},
          {"left_out", left_out},
          {"left_out_note", left_out_note},
          {"noise_amplified", amplified_json},
          {"report_form", report_form_stations},
          {"whitening_passes", whitening_passes},
          {"terms", terms},
          {"parameters", params}};
}

}  // namespace trackcal::fit
