// Parameter uncertainty and identifiability of a solved ceres::Problem.
//
// With whitened residuals (fit/cost_functor.h), the a-posteriori covariance of the parameters is
// the inverse of the information matrix H = J^T J at the solution, J taken in the tangent spaces of
// the manifolds. ComputeCovariance
//   - analyses H densely (eigen-decomposition, one per group of columns that share no residual
//     with the others, since H is block diagonal over them) when the problem is small enough: its numerical
//     rank, and the weak directions (eigenvalues below weak_direction_ratio * largest), named by
//     the coordinates they move most; a well-conditioned H is inverted from that decomposition;
//   - otherwise inverts H by a Schur complement on its few global columns when the others fall
//     into independent groups that are band matrices in column order (a LUT after physical terms,
//     also with whitened stations coupling a node's position and orientation), forming only the
//     entries asked for, or asks ceres::Covariance for the joint covariance of the requested
//     blocks;
//   - falls back to the pseudo-inverse of H (dropping the null space) when Ceres reports a
//     rank-deficient Jacobian, so a degenerate problem still yields standard deviations for the
//     coordinates that are determined, and flags the ones that are not (their std is infinite);
//   - flags every coordinate whose standard deviation exceeds the scale the caller gives for it, or
//     which a weak direction moves.
// Standard deviations are in physical units: each block's tangent coordinates are multiplied by
// its tangent_scale (2 for EigenQuaternionManifold blocks, giving rotation vectors in radians).
//
// Two estimators (CovarianceOptions::estimator):
//   - kModel: H^-1. Exact when every residual is whitened by its true noise. The fit engine whitens
//     by the model file's `noise:`, constant by default, while an EM tracker's noise grows about as
//     r^4 with range, so on real-shaped data H^-1 is wrong (too small or too large, depending on
//     which stations carry the estimate).
//   - kSandwich: the cluster-robust ("heteroscedasticity-consistent") covariance
//     H^-1 (sum_g J_g^T u_g u_g^T J_g + J_o^T J_o) H^-1. Each cluster g is one residual block (a
//     station's 6 residuals, which share the station's noise and may be correlated), or a group
//     of them (cluster_groups: neighbouring stations, which share the model's misfit); u_g is its
//     residual at the solution, corrected for its leverage A_g = J_g H^-1 J_g^T as
//     u_g = (I - A_g)^-1/2 r_g (Bell and McCaffrey's CR2: unbiased when the noise model happens to
//     be right), or, when that costs too much, r_g scaled by G/(G-1) (N-1)/(N-K) (CR1). Residual
//     blocks that are not clusters (priors, regularisers) enter with their model information J_o^T
//     J_o; those whose weights are relative to the noise model (CovarianceOptions::noise_relative:
//     a ridge or smoothness prior of w c / sigma) with that information scaled by the clusters'
//     estimated noise variance s^2 (the mean square of the corrected residuals u_g), as the prior
//     is stated in units of the same sigma. It needs no noise model, only independent clusters and
//     a correct model (a misfit adds to it, as it should). It needs the dense analysis and at most
//     max_sandwich_dimension tangent coordinates; otherwise the model covariance is used and
//     CovarianceResult::estimator says so.

#pragma once

#include <ceres/problem.h>
#include <ceres/types.h>

#include <Eigen/Core>
#include <limits>
#include <string>
#include <vector>

namespace trackcal::fit {

// A parameter block whose uncertainty is wanted.
struct CovarianceBlock {
  const double* values = nullptr;  // the block as added to the problem
  std::string name;  // used in flags and reports, e.g. "optical_from_transmitter.rotation"
  std::vector<std::string> coordinate_names;  // one per tangent coordinate; default "<name>[i]"
  double tangent_scale = 1.0;                 // physical units per tangent unit (2 for quaternions)
  double max_stddev = std::numeric_limits<double>::infinity();  // larger std => poorly identified
  // false: only this block's own covariance is computed; its cross-covariances with the other
  // requested blocks are left zero (keeps many per-station blocks cheap).
  bool cross_covariance = true;
};

enum class CovarianceEstimator {
  kModel,     // H^-1 with the residuals' whitening taken as the truth
  kSandwich,  // cluster-robust sandwich over `clusters` (see the file comment)
};

// "model" or "sandwich".
std::string CovarianceEstimatorName(CovarianceEstimator estimator);

struct CovarianceOptions {
  CovarianceEstimator estimator = CovarianceEstimator::kModel;
  // kSandwich: the residual blocks that are independent observations, one cluster each (a
  // station's residual block). Other residual blocks count as model information.
  std::vector<ceres::ResidualBlockId> clusters;
  // kSandwich: the group of each entry of `clusters` (empty, or as many entries): blocks of one
  // group are one cluster, their rows corrected for leverage together and their scores summed
  // (stations that share the model's smooth misfit). The small-sample factor of CR1 counts groups.
  std::vector<int> cluster_groups;
  // kSandwich: residual blocks that are not clusters and whose weights are relative to the noise
  // sigma of the stations (a polynomial's or a LUT's ridge, a LUT's smoothness). Their information
  // enters the meat scaled by s^2, the clusters' noise variance relative to the whitening: with a
  // model file whose noise is 25 times the stations' real scatter (s^2 ~ 0.0016) the unscaled prior
  // information dominated the data's and widened the physical terms' stds about 4-fold. Blocks not
  // listed (a block prior in physical units, gauge constraints) enter unscaled. One s^2 for all
  // rows: a file whose position and orientation sigmas are off by different factors gets a
  // compromise for both parts' priors (a scale per part would need each prior row tagged with its
  // part; not done).
  std::vector<ceres::ResidualBlockId> noise_relative;
  // Residual blocks that are hard constraints of a gauge (the unit-mean gain, trace G = 3, held by
  // a residual of weight 1e8): the dense analysis takes them in the limit of their weight, leaving
  // them out of the Jacobi scaling and of the largest eigenvalue that rank and weak directions are
  // relative to. Given as ordinary rows, such a weight scales the data's information in the
  // directions the constraint leaves free by 1e-16, below the rank tolerance (fit/covariance.cc,
  // DecomposeWithConstraints). Not for priors, whose sigma is a variance the covariance keeps.
  std::vector<ceres::ResidualBlockId> hard_constraints;
  // kSandwich only up to this many tangent coordinates (its dense products cost dimension^3;
  // larger problems, such as fine LUTs, get the model covariance and a message saying so).
  int max_sandwich_dimension = 800;
  // kSandwich: the CR2 leverage correction costs about residual rows * dimension^2 flops; above
  // this the CR1 scaling is used instead.
  double max_leverage_flops = 4e9;
  // Eigenvalues of H below this fraction of the largest count as null space (rank deficiency).
  double rank_tolerance = 1e-12;
  // Eigen-directions below this fraction of the largest eigenvalue are reported as weak.
  double weak_direction_ratio = 1e-9;
  // A coordinate is "moved" by a weak direction when its share of that unit eigenvector exceeds
  // this.
  double weak_component_threshold = 0.1;
  // Dense analysis (rank, weak directions, fallback) only up to this many tangent coordinates.
  int max_dense_dimension = 3000;
  // kModel: H^-1 is taken from the dense analysis' eigen-decomposition when its reciprocal
  // condition is at least this (relative error about 1e-16 / 1e-6 = 1e-10), instead of factoring
  // the Jacobian again with Ceres' sparse QR. Above 1: always Ceres.
  double min_reciprocal_condition_dense_inverse = 1e-6;
  // Analyse the groups of columns that share no residual row (H block diagonal: a lone polynomial's
  // position x, y, z and orientation coefficients) one by one: the same covariance, rank and weak
  // directions (up to rounding) for a fraction of the dense products. false: one group (tests).
  bool split_independent_columns = true;
  // Above max_dense_dimension: H^-1 by a Schur complement on the few columns most rows touch, the
  // others in independent band groups (a LUT after physical terms), before Ceres' sparse QR.
  // false: Ceres only (tests).
  bool schur_large_problems = true;
  // Threads for ceres::Covariance.
  int num_threads = 1;
  bool Check() const;
};

// One poorly identified coordinate and why.
struct IdentifiabilityFlag {
  std::string coordinate;  // "<block>.<coordinate>"
  std::string reason;  // "std 3.2e-03 > 1.0e-03" or "in weak direction 1 (eigenvalue ratio 1e-17)"
};

struct CovarianceResult {
  bool success = false;         // a covariance (full or pseudo-inverse) was computed
  // "dense_inverse", "schur_banded_groups", "ceres_sparse_qr", "dense_pseudo_inverse", "dense_sandwich" or
  // "dense_pseudo_inverse_sandwich"
  std::string method;
  // The estimator used: "model", "sandwich (CR2)" or "sandwich (CR1)", with ", N clusters" inside
  // the parentheses when blocks were grouped; a sandwich that was asked for but could not be
  // computed gives "model" and says why in `message`.
  std::string estimator = "model";
  int num_clusters = 0;  // the sandwich's clusters (0: the model covariance)
  // The sandwich's s^2 (CovarianceOptions::noise_relative): the clusters' noise variance over the
  // whitening's, 1 when the model file's noise is the stations' (NaN: not computed).
  double noise_variance_scale = std::numeric_limits<double>::quiet_NaN();
  int tangent_dimension = 0;    // tangent coordinates of all non-constant blocks in the problem
  int rank = -1;                // numerical rank of H (-1: dense analysis skipped)
  // Groups of columns sharing no residual row, analysed one by one (0: dense analysis skipped).
  int num_groups = 0;
  bool rank_deficient = false;  // rank < tangent_dimension (or Ceres refused the inverse)
  double reciprocal_condition = 0.0;  // smallest / largest eigenvalue of H (dense analysis only)
  // Joint covariance of the requested blocks in physical tangent units, blocks in request order
  // (cross terms of blocks with cross_covariance = false are zero).
  Eigen::MatrixXd covariance;
  // sqrt(diag(covariance)); +infinity for a coordinate the null space of H moves (rank deficient:
  // `covariance` is the pseudo-inverse's, which leaves that direction out), flagged.
  Eigen::VectorXd stddev;
  // Per requested coordinate, its variance inflation factor H_jj (H^+)_jj >= 1: how much the
  // freedom of the other coordinates widens its variance (1: it shares no information with them;
  // 20: 95 % of its information is shared, what is left rests on 5 %). From the dense analysis
  // (empty when that was skipped; NaN for a coordinate no residual touches).
  Eigen::VectorXd variance_inflation;
  std::vector<int> block_offsets;             // first row of each requested block in covariance
  std::vector<std::string> coordinate_names;  // one per row of covariance
  std::vector<IdentifiabilityFlag> flags;     // poorly identified coordinates
  std::string message;                        // failure reason or notes

  // Multi-line human-readable summary: method, rank, flags.
  std::string ToString() const;
};

// Covariance of `blocks` at the current parameter values of a solved problem whose residuals are
// whitened. Throws std::invalid_argument if a block is not in the problem or is constant.
CovarianceResult ComputeCovariance(ceres::Problem* problem,
                                   const std::vector<CovarianceBlock>& blocks,
                                   const CovarianceOptions& options = {});

}  // namespace trackcal::fit
