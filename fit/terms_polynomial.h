// The paper's global correction (Ikits et al. 2001, eq. 7-9) as a model term: complete degree-r
// polynomials of the normalised reported position (core/polynomial.h) predicting the position error
// [m] and the vector part of the orientation error q_e; either part may be disabled (held at zero).
//
// Blocks: "position_coefficients" and "orientation_coefficients", NumPolynomialTerms(r) x 3 each,
// term-major in core's canonical order. InitializeLinear() is the paper's linear least-squares fit
// (QR on the normalised basis), exact when the polynomial is the only term.
#pragma once

#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "core/polynomial.h"
#include "fit/model.h"
#include "fit/model_file.h"

namespace trackcal::fit {

struct PolynomialTermOptions {
  int degree = 4;              // r, 0 .. kMaxPolynomialDegree
  bool position = true;        // fit the position part
  bool orientation = true;     // fit the orientation part
  // Tikhonov (ridge) prior on the coefficients of degree >= 2 (the constant and linear ones are
  // never shrunk): whitened residuals ridge * c / sigma per coefficient, sigma the model's position or
  // orientation noise, i.e. a Gaussian prior N(0, (sigma / ridge)^2) on each. It removes the
  // near-null directions a grid leaves (on the paper preset's 4 heights, z^4 equals a cubic at the
  // stations), which a polynomial chained after a physical term otherwise fits to noise. 0: none.
  double ridge = 0.0;
  // ridge: auto: chosen per part at initialisation over RidgeGrid() by a cross-validation of the
  // term's linear least squares (ridge_selection).
  bool ridge_auto = false;
  // How ridge: auto scores a weight. kBlocked (the default): spatially blocked folds, so that
  // held-out stations lie between or beyond the training stations as validation stations do
  // (BlockedRidgeCv); kLeaveOneOut: leave-one-out by the hat matrix with the one-standard-error
  // rule (blind to extrapolation: a station's neighbours are always in the training set).
  enum class RidgeSelection { kBlocked, kLeaveOneOut };
  RidgeSelection ridge_selection = RidgeSelection::kBlocked;
  // Largest amplification of a fitted direction (0: no limit). Without a ridge, a direction of the
  // coefficients whose RMS over the stations' box is more than this many times its RMS at the
  // stations is not fitted (taken out of the highest-degree coefficients; FindDeterminedSubspace).
  // With a grid of L layers a polynomial of degree >= L has such directions, (z - z1)...(z - zL)
  // times lower powers: at stations that sit on their layers to within delta they are
  // ~h / (6 delta) times smaller than between the layers (h the spacing), so a polynomial chained
  // after an accurate physical correction fits them to noise and blows that up between the
  // layers. Measured: the paper
  // preset's 4 layers at the true positions (degree 4): 681, every other direction at most 1.4; on
  // the raw reports at most 2.9; 5 layers at most 1.5; random stations, degree 8, 480-545
  // stations: at most 14 (kept). docs/model-file.md, "Undetermined directions".
  double max_amplification = 20.0;
  // Normalisation of the input (NaN: from the bounding box of the data in Prepare()).
  Eigen::Vector3d input_offset = Eigen::Vector3d::Constant(NAN);
  Eigen::Vector3d input_scale = Eigen::Vector3d::Constant(NAN);
  void Check() const;  // throws std::invalid_argument
};

class PolynomialTerm : public AutoDiffModelTerm<PolynomialTerm> {
 public:
  static constexpr const char* kType = "polynomial";
  explicit PolynomialTerm(const PolynomialTermOptions& options);
  static std::unique_ptr<ModelTerm> FromYaml(const YamlMapReader& reader);

  std::string type() const override { return kType; }
  void Prepare(const std::vector<FitStation>& inputs) override;
  bool InitializeLinear(const std::vector<FitStation>& inputs,
                        const Eigen::Vector2d& noise_sigmas) override;
  std::unique_ptr<Correction> ToCorrection() const override;
  nlohmann::json Describe() const override;
  // Without a ridge the linear least squares is the fit; with one the engine solves (the prior).
  bool SolvesAloneLinearly() const override { return options_.ridge == 0.0 && !options_.ridge_auto; }
  // The ridge residuals (options().ridge or the chosen one) on the free parts.
  int AddExtraResiduals(ceres::Problem* problem, const std::vector<FitStation>& inputs) override;
  bool ExtraResidualsRelativeToNoise() const override { return true; }  // w c / sigma
  // The ridge weights in use per part (position, orientation): the option, or the chosen ones.
  const Eigen::Vector2d& ridge_used() const { return ridge_used_; }
  // The normalisation box and the ridge weights in use; adopting them makes Prepare() keep the box
  // and InitializeLinear() use the weights instead of choosing (a fit from another's optimum; a
  // state without "ridge_used" leaves `ridge: auto` to choose, at the start).
  nlohmann::json PreparedState() const override;
  bool AdoptPreparedState(const nlohmann::json& state) override;
  // Candidate weights of ridge: auto (0, then 1e-4 .. 1e2 in steps of 10^0.5).
  static std::vector<double> RidgeGrid();
  // The blocked cross-validation of ridge: auto (docs/model-file.md, "Polynomial ridge"). Folds:
  // per axis of the normalised inputs `u` (n x 3), up to kBlockedSlabsPerAxis slabs of about equal
  // station count, each boundary moved to the widest gap between consecutive coordinates near its
  // quantile (so a grid's layers stay whole); each slab is held out in turn. A held-out station is
  // predicted the way the runtime applies an explicit term outside the calibrated volume
  // (core/correction.h): from the nearest point of the training stations' box, continued to first
  // order out to `linear_reach` [m] (the `linear` policy; `input_scale` [m per unit of u] converts
  // the distance) and held beyond; linear_reach = 0 is the `clamp` policy. Closed form per fold and
  // weight on the normal equations: (A^T A - A_F^T A_F + lambda^2 D) c = A^T b - A_F^T b_F, D = 1 on
  // the `shrunk` columns. Returns the summed squared held-out error per weight of `grid`
  // (infinity where a fold's system is singular). `row_weight` (optional, n): rows of `a` and `b`
  // already carry these per-station weights (whitening), so the held-out prediction rows get them too.
  static constexpr int kBlockedSlabsPerAxis = 6;
  static std::vector<double> BlockedRidgeCv(int degree, const Eigen::MatrixXd& u,
                                            const Eigen::MatrixXd& a, const Eigen::MatrixXd& b,
                                            const std::vector<bool>& shrunk,
                                            const std::vector<double>& grid,
                                            int slabs_per_axis = kBlockedSlabsPerAxis,
                                            const Eigen::Vector3d& input_scale =
                                                Eigen::Vector3d::Ones(),
                                            double linear_reach = 0.0,
                                            const Eigen::VectorXd* row_weight = nullptr);
  // The folds of BlockedRidgeCv: fold index per station (each axis's slabs are a partition; the
  // result holds the 3 axes' partitions in turn, -1 for an axis with a single slab).
  static std::vector<std::vector<int>> BlockedFolds(const Eigen::MatrixXd& u,
                                                   int slabs_per_axis = kBlockedSlabsPerAxis);
  // Degree >= 1 with a free position part: e_p = (s - 1) p is linear in p.
  bool AbsorbsIsotropicScaling() const override {
    return options_.degree >= 1 && position_block_ >= 0 &&
           !blocks_[static_cast<size_t>(position_block_)].fixed;
  }
  // sigma^2 (A^T A)^-1 per part from the QR of the monomial matrix A (for the orientation part, of
  // the paper's linear model of the vector part of q_e).
  bool LinearCovariance(const Eigen::Vector2d& noise_sigmas) override;
  // Analytic in the coefficients (the output is linear in them); Jets of size 3 and 7 only for the
  // monomials' and the quaternion product's derivatives: ~30x faster than AutoDiffModelTerm's.
  bool Evaluate(const StationBinding& binding, const double* const* block_values,
                const AmbientPose& input, bool jacobians, TermEvaluation* result) const override;

  template <typename T>
  bool Apply(const StationBinding& binding, const T* const* block_values, const T* input7,
             T* output7) const;

  const PolynomialTermOptions& options() const { return options_; }

  // What stations with monomial matrix `a` (stations x terms, inputs normalised to the box
  // [-1, 1]^3) determine. The undetermined directions are the generalized eigenvectors of
  // (A^T A / n, the box's Gram matrix) whose RMS over the box is more than `max_amplification`
  // times their RMS at the stations (`dropped_amplifications`, largest first). `basis` (terms x k,
  // orthonormal) spans the coefficients fitted instead: those with no component of the
  // undetermined directions in their highest-degree monomials (so a polynomial of lower degree
  // than those is fitted without bias); the identity when nothing is dropped.
  // With `u` (stations x 3, the normalised inputs), the box is that of the stations that are not
  // isolated (IsolatedStations), and only they enter A^T A; without, [-1, 1]^3 and every station.
  struct DeterminedSubspace {
    Eigen::MatrixXd basis;
    std::vector<double> dropped_amplifications;
    double max_kept_amplification = 0.0;
    int isolated_stations = 0;  // left out of the volume and of A^T A
  };
  static DeterminedSubspace FindDeterminedSubspace(const Eigen::MatrixXd& a, int degree,
                                                   double max_amplification,
                                                   const Eigen::MatrixXd* u = nullptr);
  // E[m_i m_j] over the uniform box [lo, hi] (default [-1, 1]^3) for the monomials of `degree`
  // (canonical order); a flat axis (lo = hi) contributes its value's powers.
  static Eigen::MatrixXd BoxGram(int degree, const Eigen::Vector3d& lo = -Eigen::Vector3d::Ones(),
                                 const Eigen::Vector3d& hi = Eigen::Vector3d::Ones());
  // Stations whose nearest neighbour (in `u`) is more than 4 times the median nearest-neighbour
  // distance and more than 0.25 (an eighth of the normalised range) away; none when fewer than 10
  // or more than kMaxIsolationStations stations, or when more than max(3, 5 %) would be flagged.
  static constexpr size_t kMaxIsolationStations = 5000;
  static std::vector<bool> IsolatedStations(const Eigen::MatrixXd& u);
  // The last InitializeLinear()'s subspace when it held directions (else empty).
  const DeterminedSubspace& undetermined() const { return undetermined_; }
  // Coefficients (R x 3, term-major) of each part; zeros for a disabled part.
  std::vector<double> PositionCoefficients() const;
  std::vector<double> OrientationCoefficients() const;

 private:
  PolynomialTermOptions options_;
  int num_terms_ = 0;
  int position_block_ = -1;     // index in blocks_, -1 if disabled
  int orientation_block_ = -1;  // index in blocks_, -1 if disabled
  Eigen::VectorXd inverse_normal_diagonal_;  // diag((A^T A)^-1) of the last InitializeLinear()
  Eigen::Vector2d ridge_used_ = Eigen::Vector2d::Zero();
  std::optional<Eigen::Vector2d> adopted_ridge_;  // AdoptPreparedState(): not chosen again
  Eigen::Vector2d sigmas_ = Eigen::Vector2d(1e-3, 3.5e-3);  // the model's noise (ridge whitening)
  Eigen::Vector2d loo_rms_ = Eigen::Vector2d::Constant(NAN);  // leave-one-out RMS at the chosen ridge
  DeterminedSubspace undetermined_;
  bool InitializeInSubspace(const Eigen::MatrixXd& a, const Eigen::MatrixXd& b_position,
                            const Eigen::MatrixXd& b_orientation);
};

template <typename T>
bool PolynomialTerm::Apply(const StationBinding& /*binding*/, const T* const* block_values,
                           const T* input7, T* output7) const {
  T u[3];
  NormalizePolynomialInput(input7, options_.input_offset, options_.input_scale, u);
  Vector3<T> position_error = Vector3<T>::Zero();
  Vector3<T> orientation_error = Vector3<T>::Zero();
  if (position_block_ >= 0) {
    EvaluateVectorPolynomial<T, 3>(options_.degree, block_values[position_block_], u,
                                   position_error.data());
  }
  if (orientation_block_ >= 0) {
    EvaluateVectorPolynomial<T, 3>(options_.degree, block_values[orientation_block_], u,
                                   orientation_error.data());
  }
  Vector3<T> position(input7[0], input7[1], input7[2]);
  Eigen::Quaternion<T> rotation = QuaternionFromXyzwArray(input7 + 3);
  ApplyPoseError<T>(position_error, orientation_error, &position, &rotation);
  for (int k = 0; k < 3; ++k) output7[k] = position[k];
  QuaternionToXyzwArray(rotation, output7 + 3);
  return true;
}

}  // namespace trackcal::fit
