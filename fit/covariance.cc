#include "fit/covariance.h"

#include <ceres/covariance.h>
#include <ceres/cost_function.h>
#include <ceres/crs_matrix.h>

#include <Eigen/Eigenvalues>
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <map>
#include <set>
#include <sstream>
#include <stdexcept>
#include <utility>

namespace trackcal::fit {

bool CovarianceOptions::Check() const {
  return rank_tolerance > 0.0 && rank_tolerance < 1.0 && weak_direction_ratio >= rank_tolerance &&
         weak_direction_ratio < 1.0 && weak_component_threshold > 0.0 &&
         weak_component_threshold <= 1.0 && max_dense_dimension >= 0 && num_threads >= 1 &&
         max_sandwich_dimension >= 0 && max_leverage_flops >= 0.0 &&
         min_reciprocal_condition_dense_inverse >= 0.0;
}

std::string CovarianceEstimatorName(CovarianceEstimator estimator) {
  return estimator == CovarianceEstimator::kSandwich ? "sandwich" : "model";
}

namespace {

std::string Format(const char* fmt, double value) {
  char buf[64];
  std::snprintf(buf, sizeof(buf), fmt, value);
  return buf;
}

Eigen::MatrixXd DenseJacobian(const ceres::CRSMatrix& crs) {
  Eigen::MatrixXd jacobian = Eigen::MatrixXd::Zero(crs.num_rows, crs.num_cols);
  for (int r = 0; r < crs.num_rows; ++r) {
    for (int k = crs.rows[r]; k < crs.rows[r + 1]; ++k) jacobian(r, crs.cols[k]) = crs.values[k];
  }
  return jacobian;
}

struct DenseAnalysis {
  bool done = false;
  int rank = 0;
  double reciprocal_condition = 0.0;
  Eigen::VectorXd scale;         // D^-1/2: column scaling that makes diag(H) one
  Eigen::VectorXd eigenvalues;   // of the scaled information matrix, ascending
  Eigen::MatrixXd eigenvectors;  // columns, scaled coordinates
  std::vector<int> weak;         // indices of weak eigen-directions
  // The whitened (loss-applied) Jacobian and residuals of every residual block of the problem, in
  // the problem's order, and each block's first row: the sandwich reuses them instead of evaluating
  // the problem again.
  Eigen::MatrixXd jacobian;
  std::vector<double> residuals;
  std::map<ceres::ResidualBlockId, int> first_row;
};

// Information matrix of the whitened problem over `columns` blocks (tangent coordinates), its
// eigen-decomposition after Jacobi scaling (so rank and weak directions do not depend on units).
DenseAnalysis AnalyseDense(ceres::Problem* problem, const std::vector<double*>& columns,
                           int dimension, const CovarianceOptions& options) {
  DenseAnalysis a;
  ceres::Problem::EvaluateOptions eval;
  eval.parameter_blocks = columns;
  eval.apply_loss_function = true;
  eval.num_threads = options.num_threads;
  problem->GetResidualBlocks(&eval.residual_blocks);  // all, in order, to know each block's rows
  ceres::CRSMatrix crs;
  double cost = 0.0;
  if (!problem->Evaluate(eval, &cost, &a.residuals, nullptr, &crs)) return a;
  if (crs.num_cols != dimension) return a;
  int row = 0;
  for (ceres::ResidualBlockId id : eval.residual_blocks) {
    a.first_row[id] = row;
    row += problem->GetCostFunctionForResidualBlock(id)->num_residuals();
  }
  a.jacobian = DenseJacobian(crs);
  // J^T J by a symmetric rank update (half the flops of the product); the eigen-solver below reads
  // the lower triangle only, the diagonal is used for the scaling.
  Eigen::MatrixXd information = Eigen::MatrixXd::Zero(dimension, dimension);
  information.selfadjointView<Eigen::Lower>().rankUpdate(a.jacobian.transpose());
  a.scale = Eigen::VectorXd::Ones(dimension);
  for (int i = 0; i < dimension; ++i) {
    if (information(i, i) > 0.0) a.scale(i) = 1.0 / std::sqrt(information(i, i));
  }
  const Eigen::MatrixXd scaled = a.scale.asDiagonal() * information * a.scale.asDiagonal();
  Eigen::SelfAdjointEigenSolver<Eigen::MatrixXd> eig(scaled);
  if (eig.info() != Eigen::Success) return a;
  a.eigenvalues = eig.eigenvalues();
  a.eigenvectors = eig.eigenvectors();
  const double largest = dimension > 0 ? a.eigenvalues(dimension - 1) : 0.0;
  a.rank = 0;
  for (int i = 0; i < dimension; ++i) {
    if (a.eigenvalues(i) > options.rank_tolerance * largest) ++a.rank;
    if (a.eigenvalues(i) <= options.weak_direction_ratio * largest) a.weak.push_back(i);
  }
  a.reciprocal_condition = largest > 0.0 ? std::max(0.0, a.eigenvalues(0)) / largest : 0.0;
  a.done = true;
  return a;
}

// The cluster-robust sandwich over all `columns` (see the header): H^+ M H^+ with H^+ the
// rank-aware pseudo-inverse of the dense analysis. False (and why) if it cannot be computed.
bool SandwichCovariance(ceres::Problem* problem, const std::vector<double*>& columns,
                        int dimension, const DenseAnalysis& dense,
                        const CovarianceOptions& options, Eigen::MatrixXd* full,
                        std::string* estimator, std::string* why) {
  const int rank = dense.rank;
  const Eigen::MatrixXd sv = dense.scale.asDiagonal() * dense.eigenvectors.rightCols(rank);
  const Eigen::VectorXd inv = dense.eigenvalues.tail(rank).cwiseInverse();
  const Eigen::MatrixXd h_inv = sv * inv.asDiagonal() * sv.transpose();

  // The clusters' rows and the other residual blocks' rows of the analysis' Jacobian (evaluated
  // once for both, with the loss applied as the solver saw it).
  std::vector<int> cluster_rows, cluster_sizes;
  for (ceres::ResidualBlockId id : options.clusters) {
    const auto it = dense.first_row.find(id);
    if (it == dense.first_row.end()) {
      *why = "a cluster is not a residual block of the problem";
      return false;
    }
    cluster_rows.push_back(it->second);
    cluster_sizes.push_back(problem->GetCostFunctionForResidualBlock(id)->num_residuals());
  }
  Eigen::MatrixXd meat = Eigen::MatrixXd::Zero(dimension, dimension);

  // Residual blocks that are not clusters (priors, regularisers): their model information.
  {
    const std::set<ceres::ResidualBlockId> clustered(options.clusters.begin(),
                                                     options.clusters.end());
    std::vector<std::pair<int, int>> other_rows;  // (first row, rows) in the problem's order
    int num_other_rows = 0;
    std::vector<ceres::ResidualBlockId> all;
    problem->GetResidualBlocks(&all);
    for (ceres::ResidualBlockId id : all) {
      if (clustered.count(id)) continue;
      const int k = problem->GetCostFunctionForResidualBlock(id)->num_residuals();
      other_rows.emplace_back(dense.first_row.at(id), k);
      num_other_rows += k;
    }
    if (num_other_rows > 0) {
      Eigen::MatrixXd jo(num_other_rows, dimension);
      int row = 0;
      for (const auto& [first, k] : other_rows) {
        jo.middleRows(row, k) = dense.jacobian.middleRows(first, k);
        row += k;
      }
      meat.noalias() += jo.transpose() * jo;
    }
  }

  const int num_clusters = static_cast<int>(options.clusters.size());
  int num_rows = 0;
  for (int k : cluster_sizes) num_rows += k;
  const bool leverage =
      static_cast<double>(num_rows) * dimension * dimension <= options.max_leverage_flops;
  // Leverages A_g = J_g H^+ J_g^T = B_g B_g^T with B = J S V_r diag(l_r)^-1/2: one product for all
  // clusters instead of one (k x dimension) (dimension x dimension) product per cluster.
  Eigen::MatrixXd b;
  if (leverage) {
    const Eigen::MatrixXd half = sv * inv.cwiseSqrt().asDiagonal();
    b = dense.jacobian * half;
  }
  Eigen::MatrixXd scores(dimension, num_clusters);
  for (int g = 0; g < num_clusters; ++g) {
    const int k = cluster_sizes[static_cast<size_t>(g)];
    const int first = cluster_rows[static_cast<size_t>(g)];
    const auto jg = dense.jacobian.middleRows(first, k);
    Eigen::VectorXd u = Eigen::Map<const Eigen::VectorXd>(dense.residuals.data() + first, k);
    if (leverage) {
      // u = (I - A)^-1/2 r; a leverage near 1 (a cluster that alone determines a direction) is
      // capped so its residual is inflated at most 1000-fold.
      const auto bg = b.middleRows(first, k);
      const Eigen::MatrixXd a = bg * bg.transpose();
      Eigen::SelfAdjointEigenSolver<Eigen::MatrixXd> eig(Eigen::MatrixXd::Identity(k, k) - a);
      const Eigen::VectorXd scale =
          eig.eigenvalues().cwiseMax(1e-6).cwiseSqrt().cwiseInverse();
      u = eig.eigenvectors() * scale.asDiagonal() * eig.eigenvectors().transpose() * u;
    }
    scores.col(g) = jg.transpose() * u;
  }
  double factor = 1.0;
  if (!leverage) {
    const double g = num_clusters, n = num_rows, p = rank;
    factor = g > 1 && n > p ? g / (g - 1.0) * (n - 1.0) / (n - p) : 1.0;
  }
  meat.noalias() += factor * scores * scores.transpose();
  *full = h_inv * meat * h_inv;
  *estimator = leverage ? "sandwich (CR2)" : "sandwich (CR1)";
  return true;
}

// (Pseudo-)inverse in the scaled coordinates over the requested rows `full_index`, from the `rank`
// largest eigenvalues: H^+ = S V_r diag(1/l_r) V_r^T S; pairs of blocks not `wanted` are zero.
template <typename WantedFn>
Eigen::MatrixXd DenseInverse(const DenseAnalysis& dense, const std::vector<int>& full_index,
                             int rank, const WantedFn& wanted,
                             const std::vector<CovarianceBlock>& blocks,
                             const std::vector<int>& sizes, const std::vector<int>& offsets) {
  const int n = static_cast<int>(full_index.size());
  const Eigen::MatrixXd v = dense.eigenvectors.rightCols(rank);
  const Eigen::VectorXd inv = dense.eigenvalues.tail(rank).cwiseInverse();
  Eigen::MatrixXd rows(n, rank);
  for (int k = 0; k < n; ++k) rows.row(k) = dense.scale(full_index[k]) * v.row(full_index[k]);
  Eigen::MatrixXd covariance = rows * inv.asDiagonal() * rows.transpose();
  for (std::size_t i = 0; i < blocks.size(); ++i) {
    for (std::size_t j = 0; j < blocks.size(); ++j) {
      if (wanted(i, j)) continue;
      covariance.block(offsets[i], offsets[j], sizes[i], sizes[j]).setZero();
    }
  }
  return covariance;
}

}  // namespace

CovarianceResult ComputeCovariance(ceres::Problem* problem,
                                   const std::vector<CovarianceBlock>& blocks,
                                   const CovarianceOptions& options) {
  if (!options.Check()) throw std::invalid_argument("CovarianceOptions: invalid options");
  CovarianceResult result;

  // Requested blocks: sizes and names.
  std::vector<int> sizes;
  for (const CovarianceBlock& b : blocks) {
    if (b.values == nullptr || !problem->HasParameterBlock(b.values)) {
      throw std::invalid_argument("ComputeCovariance: block '" + b.name +
                                  "' is not in the problem");
    }
    if (problem->IsParameterBlockConstant(b.values)) {
      throw std::invalid_argument("ComputeCovariance: block '" + b.name + "' is constant");
    }
    const int size = problem->ParameterBlockTangentSize(b.values);
    if (!b.coordinate_names.empty() && static_cast<int>(b.coordinate_names.size()) != size) {
      throw std::invalid_argument("ComputeCovariance: block '" + b.name + "' has " +
                                  std::to_string(b.coordinate_names.size()) +
                                  " coordinate names for a tangent size of " +
                                  std::to_string(size));
    }
    if (!(b.tangent_scale > 0.0)) {
      throw std::invalid_argument("ComputeCovariance: block '" + b.name +
                                  "' needs tangent_scale > 0");
    }
    result.block_offsets.push_back(static_cast<int>(result.coordinate_names.size()));
    for (int i = 0; i < size; ++i) {
      result.coordinate_names.push_back(
          b.name + "." +
          (b.coordinate_names.empty() ? "[" + std::to_string(i) + "]" : b.coordinate_names[i]));
    }
    sizes.push_back(size);
  }
  const int n = static_cast<int>(result.coordinate_names.size());

  // All free blocks of the problem, in a fixed column order: the requested blocks, then the others
  // as the residual blocks (kept in insertion order) use them. Problem::GetParameterBlocks lists
  // them by address, which differs between runs and would change the last bits of every sum.
  std::vector<double*> all_blocks;
  {
    std::set<const double*> seen;
    auto add = [&](double* block) {
      if (seen.insert(block).second) all_blocks.push_back(block);
    };
    for (const CovarianceBlock& b : blocks) add(const_cast<double*>(b.values));
    std::vector<ceres::ResidualBlockId> residual_blocks;
    problem->GetResidualBlocks(&residual_blocks);
    for (ceres::ResidualBlockId id : residual_blocks) {
      std::vector<double*> used;
      problem->GetParameterBlocksForResidualBlock(id, &used);
      for (double* block : used) add(block);
    }
    std::vector<double*> by_address;
    problem->GetParameterBlocks(&by_address);
    for (double* block : by_address) add(block);  // blocks without residuals
  }
  std::vector<double*> columns;
  std::map<const double*, int> column_offset;
  for (double* block : all_blocks) {
    if (problem->IsParameterBlockConstant(block)) continue;
    column_offset[block] = result.tangent_dimension;
    columns.push_back(block);
    result.tangent_dimension += problem->ParameterBlockTangentSize(block);
  }

  DenseAnalysis dense;
  if (result.tangent_dimension <= options.max_dense_dimension) {
    dense = AnalyseDense(problem, columns, result.tangent_dimension, options);
  }
  if (dense.done) {
    result.rank = dense.rank;
    result.rank_deficient = dense.rank < result.tangent_dimension;
    result.reciprocal_condition = dense.reciprocal_condition;
  }

  // Row in the full tangent vector of each requested coordinate.
  std::vector<int> full_index(n);
  for (std::size_t b = 0; b < blocks.size(); ++b) {
    for (int i = 0; i < sizes[b]; ++i) {
      full_index[result.block_offsets[b] + i] = column_offset.at(blocks[b].values) + i;
    }
  }

  auto Wanted = [&](std::size_t i, std::size_t j) {
    return i == j || (blocks[i].cross_covariance && blocks[j].cross_covariance);
  };
  bool have_covariance = false;
  if (options.estimator == CovarianceEstimator::kSandwich) {
    std::string why;
    if (result.tangent_dimension > options.max_sandwich_dimension) {
      why = "tangent dimension " + std::to_string(result.tangent_dimension) +
            " is above max_sandwich_dimension " + std::to_string(options.max_sandwich_dimension);
    } else if (!dense.done) {
      why = "the dense analysis was not possible";
    } else if (options.clusters.size() < 2) {
      why = "fewer than 2 clusters";
    } else {
      Eigen::MatrixXd full;
      std::string estimator;
      if (SandwichCovariance(problem, columns, result.tangent_dimension, dense, options, &full,
                             &estimator, &why)) {
        result.covariance = Eigen::MatrixXd::Zero(n, n);
        for (std::size_t i = 0; i < blocks.size(); ++i) {
          for (std::size_t j = 0; j < blocks.size(); ++j) {
            if (!Wanted(i, j)) continue;
            for (int a = 0; a < sizes[i]; ++a) {
              for (int b = 0; b < sizes[j]; ++b) {
                const int ra = result.block_offsets[i] + a, rb = result.block_offsets[j] + b;
                result.covariance(ra, rb) = full(full_index[ra], full_index[rb]);
              }
            }
          }
        }
        result.method = dense.rank < result.tangent_dimension ? "dense_pseudo_inverse_sandwich"
                                                              : "dense_sandwich";
        result.estimator = estimator;
        have_covariance = true;
      }
    }
    if (!have_covariance) {
      result.message += "sandwich covariance unavailable (" + why + "), model covariance used; ";
    }
  }
  // The model covariance H^-1 from the dense analysis' eigen-decomposition when H is well enough
  // conditioned for it (relative error ~ machine epsilon / reciprocal condition); Ceres' sparse QR
  // would factor the same Jacobian a second time.
  if (!have_covariance && !result.rank_deficient && dense.done &&
      dense.reciprocal_condition >= options.min_reciprocal_condition_dense_inverse) {
    result.covariance =
        DenseInverse(dense, full_index, dense.rank, Wanted, blocks, sizes, result.block_offsets);
    result.method = "dense_inverse";
    have_covariance = true;
  }
  if (!have_covariance && !result.rank_deficient) {
    ceres::Covariance::Options copt;
    copt.algorithm_type = ceres::SPARSE_QR;
    copt.num_threads = options.num_threads;
    copt.apply_loss_function = true;
    ceres::Covariance covariance(copt);
    std::vector<std::pair<const double*, const double*>> pairs;
    for (std::size_t i = 0; i < blocks.size(); ++i) {
      for (std::size_t j = i; j < blocks.size(); ++j) {
        if (Wanted(i, j)) pairs.emplace_back(blocks[i].values, blocks[j].values);
      }
    }
    if (covariance.Compute(pairs, problem)) {
      result.covariance = Eigen::MatrixXd::Zero(n, n);
      have_covariance = true;
      for (std::size_t i = 0; i < blocks.size() && have_covariance; ++i) {
        for (std::size_t j = i; j < blocks.size(); ++j) {
          if (!Wanted(i, j)) continue;
          Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor> c(sizes[i],
                                                                                   sizes[j]);
          if (!covariance.GetCovarianceBlockInTangentSpace(blocks[i].values, blocks[j].values,
                                                           c.data())) {
            have_covariance = false;
            break;
          }
          result.covariance.block(result.block_offsets[i], result.block_offsets[j], sizes[i],
                                  sizes[j]) = c;
          result.covariance.block(result.block_offsets[j], result.block_offsets[i], sizes[j],
                                  sizes[i]) = c.transpose();
        }
      }
      if (have_covariance) result.method = "ceres_sparse_qr";
    } else {
      result.rank_deficient = true;
      result.message = "ceres::Covariance refused the Jacobian (rank deficient); ";
    }
  }

  if (!have_covariance && dense.done) {
    result.covariance =
        DenseInverse(dense, full_index, dense.rank, Wanted, blocks, sizes, result.block_offsets);
    result.method = "dense_pseudo_inverse";
    have_covariance = true;
  }

  if (!have_covariance) {
    result.message +=
        "no covariance: Ceres failed and the problem is too large for the dense "
        "fallback (max_dense_dimension)";
    return result;
  }

  // Physical units.
  Eigen::VectorXd unit(n);
  for (std::size_t b = 0; b < blocks.size(); ++b) {
    unit.segment(result.block_offsets[b], sizes[b]).setConstant(blocks[b].tangent_scale);
  }
  result.covariance = unit.asDiagonal() * result.covariance * unit.asDiagonal();
  result.stddev = result.covariance.diagonal().cwiseMax(0.0).cwiseSqrt();
  result.success = true;

  // Flags: large standard deviations, then coordinates moved by weak directions.
  for (std::size_t b = 0; b < blocks.size(); ++b) {
    for (int i = 0; i < sizes[b]; ++i) {
      const int k = result.block_offsets[b] + i;
      if (result.stddev(k) > blocks[b].max_stddev) {
        result.flags.push_back(
            {result.coordinate_names[k], "std " + Format("%.3g", result.stddev(k)) + " > " +
                                             Format("%.3g", blocks[b].max_stddev)});
      }
    }
  }
  if (dense.done) {
    const double largest = dense.eigenvalues(result.tangent_dimension - 1);
    for (std::size_t w = 0; w < dense.weak.size(); ++w) {
      const int e = dense.weak[w];
      const double ratio = largest > 0.0 ? std::max(0.0, dense.eigenvalues(e)) / largest : 0.0;
      for (int k = 0; k < n; ++k) {
        if (std::abs(dense.eigenvectors(full_index[k], e)) > options.weak_component_threshold) {
          result.flags.push_back({result.coordinate_names[k],
                                  "moved by weak direction " + std::to_string(w) +
                                      " (eigenvalue ratio " + Format("%.2g", ratio) + ")"});
        }
      }
    }
    if (!dense.weak.empty()) {
      result.message += std::to_string(dense.weak.size()) + " weak direction(s) in the problem";
    }
  }
  return result;
}

std::string CovarianceResult::ToString() const {
  std::ostringstream out;
  out << "covariance: " << (success ? method + ", estimator " + estimator : "FAILED")
      << ", tangent dimension "
      << tangent_dimension;
  if (rank >= 0) {
    out << ", rank " << rank << (rank_deficient ? " (RANK DEFICIENT)" : "")
        << ", reciprocal condition " << Format("%.3g", reciprocal_condition);
  }
  out << "\n";
  if (!message.empty()) out << "  " << message << "\n";
  // One line per coordinate, all its reasons together.
  std::vector<std::pair<std::string, std::string>> grouped;
  for (const IdentifiabilityFlag& f : flags) {
    auto it = std::find_if(grouped.begin(), grouped.end(),
                           [&](const auto& g) { return g.first == f.coordinate; });
    if (it == grouped.end()) {
      grouped.emplace_back(f.coordinate, f.reason);
    } else {
      it->second += "; " + f.reason;
    }
  }
  for (const auto& [coordinate, reasons] : grouped) {
    out << "  poorly identified: " << coordinate << ": " << reasons << "\n";
  }
  return out.str();
}

}  // namespace trackcal::fit
