#include "fit/covariance.h"

#include <ceres/covariance.h>
#include <ceres/cost_function.h>
#include <ceres/crs_matrix.h>

#include <Eigen/Eigenvalues>
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <Eigen/QR>
#include <map>
#include <numeric>
#include <set>
#include <sstream>
#include <tuple>
#include <limits>
#include <stdexcept>
#include <utility>

namespace trackcal::fit {

bool CovarianceOptions::Check() const {
  return rank_tolerance > 0.0 && rank_tolerance < 1.0 && weak_direction_ratio >= rank_tolerance &&
         weak_direction_ratio < 1.0 && weak_component_threshold > 0.0 &&
         weak_component_threshold <= 1.0 && max_dense_dimension >= 0 && num_threads >= 1 &&
         max_sandwich_dimension >= 0 && max_leverage_flops >= 0.0 &&
         (cluster_groups.empty() || cluster_groups.size() == clusters.size()) &&
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

// One group of columns that shares no residual row with the other groups: H is block diagonal over
// the groups, so each is analysed (and inverted) on its own. A lone polynomial splits into its
// position x, y and z coefficients (each row of a position residual touches one axis) and its
// orientation coefficients; a problem whose blocks all meet in some residual is one group.
struct Component {
  std::vector<int> columns;       // columns of the full tangent vector, ascending
  std::vector<int> rows;          // rows of the problem's residual vector that touch them
  Eigen::MatrixXd jacobian;       // those rows x those columns
  Eigen::VectorXd scale;          // D^-1/2: column scaling that makes diag(H) one (H without
                                  // hard constraints, DecomposeWithConstraints)
  Eigen::VectorXd eigenvalues;    // of the scaled information matrix, ascending
  Eigen::MatrixXd eigenvectors;   // columns, scaled coordinates
  int rank = 0;                   // eigenvalues above rank_tolerance * the largest of all groups
};

struct DenseAnalysis {
  bool done = false;
  int rank = 0;
  double reciprocal_condition = 0.0;
  double largest = 0.0;  // largest eigenvalue over all groups
  std::vector<Component> components;
  std::vector<int> component_of_column, local_of_column;
  std::vector<int> component_of_row, local_of_row;  // -1: a row without non-zeros
  // Weak eigen-directions as (group, eigen index), by ascending eigenvalue.
  std::vector<std::pair<int, int>> weak;
  // The whitened (loss-applied) residuals of every residual block of the problem, in the problem's
  // order, and each block's first row: the sandwich reuses them instead of evaluating the problem
  // again.
  std::vector<double> residuals;
  std::map<ceres::ResidualBlockId, int> first_row;

  // Component `e` of the unit eigenvector of weak direction `w` at full column `column`.
  double WeakComponent(const std::pair<int, int>& w, int column) const {
    if (component_of_column[static_cast<size_t>(column)] != w.first) return 0.0;
    return components[static_cast<size_t>(w.first)].eigenvectors(
        local_of_column[static_cast<size_t>(column)], w.second);
  }
  double Eigenvalue(const std::pair<int, int>& w) const {
    return components[static_cast<size_t>(w.first)].eigenvalues(w.second);
  }
};

// Groups of columns connected through the non-zeros of the rows (union-find).
std::vector<std::vector<int>> ConnectedColumns(const ceres::CRSMatrix& crs, bool split) {
  const int n = crs.num_cols;
  std::vector<int> parent(static_cast<size_t>(n));
  for (int i = 0; i < n; ++i) parent[static_cast<size_t>(i)] = split ? i : 0;
  auto find = [&](int i) {
    while (parent[static_cast<size_t>(i)] != i) {
      parent[static_cast<size_t>(i)] = parent[static_cast<size_t>(parent[static_cast<size_t>(i)])];
      i = parent[static_cast<size_t>(i)];
    }
    return i;
  };
  if (split) {
    for (int r = 0; r < crs.num_rows; ++r) {
      int first = -1;
      for (int k = crs.rows[r]; k < crs.rows[r + 1]; ++k) {
        if (crs.values[k] == 0.0) continue;  // an exact zero couples nothing
        if (first < 0) {
          first = find(crs.cols[k]);
          continue;
        }
        const int other = find(crs.cols[k]);
        if (other != first) parent[static_cast<size_t>(std::max(other, first))] = std::min(other, first);
        first = std::min(other, first);
      }
    }
  }
  std::map<int, int> index_of_root;
  std::vector<std::vector<int>> groups;
  for (int c = 0; c < n; ++c) {
    const int root = find(c);
    auto it = index_of_root.find(root);
    if (it == index_of_root.end()) {
      it = index_of_root.emplace(root, static_cast<int>(groups.size())).first;
      groups.emplace_back();
    }
    groups[static_cast<size_t>(it->second)].push_back(c);
  }
  return groups;
}

// The eigen-decomposition of a group whose rows include hard constraints
// (CovarianceOptions::hard_constraints: `stiff`, the group's local rows of them), in the limit of
// their weight: the Jacobi scaling is the other rows' (with the constraints in, a column's scale
// is the constraint's, the data's information in the directions the constraint leaves free is
// scaled down by its weight squared, 1e16, and those directions, the relative coil gains, fell below
// the rank tolerance and out of the pseudo-inverse: stds of 4e-9 on a 3.5 s stream where the gauge
// left free gives 0.02). The data's information is decomposed in the null space of the constraint
// rows, the constraints' own directions (their range) apart; these come last, with eigenvalues of
// the constraints' size, so the pseudo-inverse gives them no variance, and `largest` (which the
// rank and the weak directions are relative to) is the data's.
// False (and `c` to be analysed plainly) when the constraints leave nothing free or an eigen-solver
// fails.
bool DecomposeWithConstraints(const Eigen::MatrixXd& information,
                              const std::vector<Eigen::Index>& stiff, Component* c,
                              double* largest) {
  const Eigen::Index m = information.rows();
  std::vector<bool> is_stiff(static_cast<size_t>(c->jacobian.rows()), false);
  for (Eigen::Index r : stiff) is_stiff[static_cast<size_t>(r)] = true;
  Eigen::MatrixXd data_jacobian(c->jacobian.rows() - static_cast<Eigen::Index>(stiff.size()), m);
  Eigen::MatrixXd constraints(static_cast<Eigen::Index>(stiff.size()), m);
  for (Eigen::Index r = 0, d = 0, k = 0; r < c->jacobian.rows(); ++r) {
    if (is_stiff[static_cast<size_t>(r)]) {
      constraints.row(k++) = c->jacobian.row(r);
    } else {
      data_jacobian.row(d++) = c->jacobian.row(r);
    }
  }
  Eigen::MatrixXd data_information = Eigen::MatrixXd::Zero(m, m);
  data_information.selfadjointView<Eigen::Lower>().rankUpdate(data_jacobian.transpose());
  data_information.triangularView<Eigen::StrictlyUpper>() =
      data_information.transpose().triangularView<Eigen::StrictlyUpper>();
  c->scale = Eigen::VectorXd::Ones(m);
  for (Eigen::Index i = 0; i < m; ++i) {
    const double h = data_information(i, i) > 0.0 ? data_information(i, i) : information(i, i);
    if (h > 0.0) c->scale(i) = 1.0 / std::sqrt(h);
  }
  // The constraints' range and null space in scaled coordinates.
  const Eigen::MatrixXd scaled_constraints = constraints * c->scale.asDiagonal();
  Eigen::ColPivHouseholderQR<Eigen::MatrixXd> qr(scaled_constraints.transpose());
  const Eigen::Index k = qr.rank();
  const Eigen::MatrixXd q = qr.householderQ() * Eigen::MatrixXd::Identity(m, m);
  const Eigen::MatrixXd range = q.leftCols(k), null = q.rightCols(m - k);
  // Nothing left free (constraints that hold every column of the group): the plain analysis.
  if (m - k == 0) return false;
  const Eigen::MatrixXd scaled_data =
      c->scale.asDiagonal() * data_information * c->scale.asDiagonal();
  Eigen::SelfAdjointEigenSolver<Eigen::MatrixXd> free_part(null.transpose() * scaled_data * null);
  Eigen::MatrixXd scaled = information.selfadjointView<Eigen::Lower>();
  scaled = c->scale.asDiagonal() * scaled * c->scale.asDiagonal();
  Eigen::SelfAdjointEigenSolver<Eigen::MatrixXd> held_part(range.transpose() * scaled * range);
  if (free_part.info() != Eigen::Success || held_part.info() != Eigen::Success) return false;
  c->eigenvalues.resize(m);
  c->eigenvectors.resize(m, m);
  c->eigenvalues << free_part.eigenvalues(), held_part.eigenvalues();
  c->eigenvectors << null * free_part.eigenvectors(), range * held_part.eigenvectors();
  *largest = std::max(*largest, free_part.eigenvalues()(m - k - 1));
  // Ascending, as the rank count and GroupFactor expect (the held directions, at the constraints'
  // weight, normally lie above all of the data's already).
  std::vector<Eigen::Index> order(static_cast<size_t>(m));
  std::iota(order.begin(), order.end(), Eigen::Index{0});
  std::stable_sort(order.begin(), order.end(), [&](Eigen::Index x, Eigen::Index y) {
    return c->eigenvalues(x) < c->eigenvalues(y);
  });
  const Eigen::VectorXd values = c->eigenvalues;
  const Eigen::MatrixXd vectors = c->eigenvectors;
  for (Eigen::Index i = 0; i < m; ++i) {
    c->eigenvalues(i) = values(order[static_cast<size_t>(i)]);
    c->eigenvectors.col(i) = vectors.col(order[static_cast<size_t>(i)]);
  }
  return true;
}

// Information matrix of the whitened problem over `columns` blocks (tangent coordinates), group by
// group (Component), each eigen-decomposed after Jacobi scaling (so rank and weak directions do not
// depend on units).
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
  const std::set<ceres::ResidualBlockId> constraints(options.hard_constraints.begin(),
                                                     options.hard_constraints.end());
  std::set<int> constraint_rows;
  for (ceres::ResidualBlockId id : eval.residual_blocks) {
    a.first_row[id] = row;
    const int rows = problem->GetCostFunctionForResidualBlock(id)->num_residuals();
    if (constraints.count(id)) {
      for (int r = row; r < row + rows; ++r) constraint_rows.insert(r);
    }
    row += rows;
  }
  const std::vector<std::vector<int>> groups =
      ConnectedColumns(crs, options.split_independent_columns);
  a.component_of_column.assign(static_cast<size_t>(dimension), -1);
  a.local_of_column.assign(static_cast<size_t>(dimension), -1);
  a.component_of_row.assign(static_cast<size_t>(crs.num_rows), -1);
  a.local_of_row.assign(static_cast<size_t>(crs.num_rows), -1);
  a.components.resize(groups.size());
  for (size_t g = 0; g < groups.size(); ++g) {
    a.components[g].columns = groups[g];
    for (size_t i = 0; i < groups[g].size(); ++i) {
      a.component_of_column[static_cast<size_t>(groups[g][i])] = static_cast<int>(g);
      a.local_of_column[static_cast<size_t>(groups[g][i])] = static_cast<int>(i);
    }
  }
  for (int r = 0; r < crs.num_rows; ++r) {
    int g = -1;
    for (int k = crs.rows[r]; k < crs.rows[r + 1] && g < 0; ++k) {
      if (crs.values[k] != 0.0 || !options.split_independent_columns) {
        g = a.component_of_column[static_cast<size_t>(crs.cols[k])];
      }
    }
    if (g < 0) continue;
    Component& c = a.components[static_cast<size_t>(g)];
    a.component_of_row[static_cast<size_t>(r)] = g;
    a.local_of_row[static_cast<size_t>(r)] = static_cast<int>(c.rows.size());
    c.rows.push_back(r);
  }
  for (Component& c : a.components) {
    const int m = static_cast<int>(c.columns.size());
    c.jacobian = Eigen::MatrixXd::Zero(static_cast<Eigen::Index>(c.rows.size()), m);
    for (size_t i = 0; i < c.rows.size(); ++i) {
      const int r = c.rows[i];
      for (int k = crs.rows[r]; k < crs.rows[r + 1]; ++k) {
        const size_t column = static_cast<size_t>(crs.cols[k]);
        // A row's structural zeros may lie in another group's columns.
        if (a.component_of_column[column] != a.component_of_row[static_cast<size_t>(r)]) continue;
        c.jacobian(static_cast<Eigen::Index>(i), a.local_of_column[column]) = crs.values[k];
      }
    }
    // J^T J by a symmetric rank update (half the flops of the product); the eigen-solver below
    // reads the lower triangle only, the diagonal is used for the scaling.
    Eigen::MatrixXd information = Eigen::MatrixXd::Zero(m, m);
    information.selfadjointView<Eigen::Lower>().rankUpdate(c.jacobian.transpose());
    std::vector<Eigen::Index> stiff;
    for (size_t i = 0; i < c.rows.size(); ++i) {
      if (constraint_rows.count(c.rows[i])) stiff.push_back(static_cast<Eigen::Index>(i));
    }
    if (stiff.empty() || !DecomposeWithConstraints(information, stiff, &c, &a.largest)) {
      c.scale = Eigen::VectorXd::Ones(m);
      for (int i = 0; i < m; ++i) {
        if (information(i, i) > 0.0) c.scale(i) = 1.0 / std::sqrt(information(i, i));
      }
      const Eigen::MatrixXd scaled = c.scale.asDiagonal() * information * c.scale.asDiagonal();
      Eigen::SelfAdjointEigenSolver<Eigen::MatrixXd> eig(scaled);
      if (eig.info() != Eigen::Success) return a;
      c.eigenvalues = eig.eigenvalues();
      c.eigenvectors = eig.eigenvectors();
      if (m > 0) a.largest = std::max(a.largest, c.eigenvalues(m - 1));
    }
  }
  double smallest = std::numeric_limits<double>::infinity();
  std::vector<std::tuple<double, int, int>> weak;
  a.rank = 0;
  for (size_t g = 0; g < a.components.size(); ++g) {
    Component& c = a.components[g];
    c.rank = 0;
    for (int i = 0; i < c.eigenvalues.size(); ++i) {
      const double l = c.eigenvalues(i);
      smallest = std::min(smallest, l);
      if (l > options.rank_tolerance * a.largest) ++c.rank;
      if (l <= options.weak_direction_ratio * a.largest) weak.emplace_back(l, static_cast<int>(g), i);
    }
    a.rank += c.rank;
  }
  std::stable_sort(weak.begin(), weak.end(),
                   [](const auto& x, const auto& y) { return std::get<0>(x) < std::get<0>(y); });
  for (const auto& [l, g, i] : weak) a.weak.emplace_back(g, i);
  a.reciprocal_condition = a.largest > 0.0 ? std::max(0.0, smallest) / a.largest : 0.0;
  a.done = true;
  return a;
}

// H^+ = S V_r diag(1/l_r)^power V_r^T S of one group, from its `rank` largest eigenvalues, with
// power 1 (the pseudo-inverse) or, with half, the factor S V_r diag(l_r)^-1/2 whose outer product
// it is.
Eigen::MatrixXd GroupFactor(const Component& c) {
  const Eigen::VectorXd inv_sqrt = c.eigenvalues.tail(c.rank).cwiseInverse().cwiseSqrt();
  return c.scale.asDiagonal() * c.eigenvectors.rightCols(c.rank) * inv_sqrt.asDiagonal();
}

// The full (dimension x dimension, block diagonal over the groups) pseudo-inverse of H.
Eigen::MatrixXd PseudoInverse(const DenseAnalysis& dense, int dimension) {
  Eigen::MatrixXd h_inv = Eigen::MatrixXd::Zero(dimension, dimension);
  for (const Component& c : dense.components) {
    const Eigen::MatrixXd f = GroupFactor(c);
    const Eigen::MatrixXd block = f * f.transpose();
    for (size_t i = 0; i < c.columns.size(); ++i) {
      for (size_t j = 0; j < c.columns.size(); ++j) {
        h_inv(c.columns[i], c.columns[j]) =
            block(static_cast<Eigen::Index>(i), static_cast<Eigen::Index>(j));
      }
    }
  }
  return h_inv;
}

// The cluster-robust sandwich over all `columns` (see the header): H^+ M H^+ with H^+ the
// rank-aware pseudo-inverse of the dense analysis. False (and why) if it cannot be computed.
bool SandwichCovariance(ceres::Problem* problem, int dimension, const DenseAnalysis& dense,
                        const CovarianceOptions& options, Eigen::MatrixXd* full,
                        std::string* estimator, int* clusters, double* noise_variance_scale,
                        std::string* why) {
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
  const int num_groups = static_cast<int>(dense.components.size());

  // Residual blocks that are not clusters (priors, regularisers): their model information, group
  // by group (a row touches one group); [0] those in physical units, [1] those relative to the
  // noise (options.noise_relative), scaled below.
  std::vector<Eigen::MatrixXd> other_information[2];
  bool have_other = false;
  {
    const std::set<ceres::ResidualBlockId> clustered(options.clusters.begin(),
                                                     options.clusters.end());
    const std::set<ceres::ResidualBlockId> relative(options.noise_relative.begin(),
                                                    options.noise_relative.end());
    std::vector<std::vector<int>> other_local_rows[2];
    for (int kind = 0; kind < 2; ++kind) {
      other_information[kind].resize(static_cast<size_t>(num_groups));
      other_local_rows[kind].resize(static_cast<size_t>(num_groups));
    }
    std::vector<ceres::ResidualBlockId> all;
    problem->GetResidualBlocks(&all);
    for (ceres::ResidualBlockId id : all) {
      if (clustered.count(id)) continue;
      const int kind = relative.count(id) ? 1 : 0;
      const int first = dense.first_row.at(id);
      const int k = problem->GetCostFunctionForResidualBlock(id)->num_residuals();
      for (int r = first; r < first + k; ++r) {
        const int g = dense.component_of_row[static_cast<size_t>(r)];
        if (g >= 0) {
          other_local_rows[kind][static_cast<size_t>(g)].push_back(
              dense.local_of_row[static_cast<size_t>(r)]);
        }
      }
    }
    for (int kind = 0; kind < 2; ++kind) {
      for (int g = 0; g < num_groups; ++g) {
        const auto& rows = other_local_rows[kind][static_cast<size_t>(g)];
        if (rows.empty()) continue;
        const Component& c = dense.components[static_cast<size_t>(g)];
        Eigen::MatrixXd jo(static_cast<Eigen::Index>(rows.size()), c.jacobian.cols());
        for (size_t i = 0; i < rows.size(); ++i) {
          jo.row(static_cast<Eigen::Index>(i)) = c.jacobian.row(rows[i]);
        }
        other_information[kind][static_cast<size_t>(g)] = jo.transpose() * jo;
        have_other = true;
      }
    }
  }

  // The groups: clusters whose scores are summed before the outer product (cluster_groups), each
  // a list of (first row, rows) segments.
  std::vector<std::vector<std::pair<int, int>>> groups;
  if (options.cluster_groups.empty()) {
    for (size_t c = 0; c < cluster_rows.size(); ++c) groups.push_back({{cluster_rows[c], cluster_sizes[c]}});
  } else {
    std::map<int, size_t> index_of_group;
    for (size_t c = 0; c < cluster_rows.size(); ++c) {
      const auto [it, added] = index_of_group.emplace(options.cluster_groups[c], groups.size());
      if (added) groups.emplace_back();
      groups[it->second].emplace_back(cluster_rows[c], cluster_sizes[c]);
    }
  }
  const int num_clusters = static_cast<int>(groups.size());
  int num_rows = 0;
  for (int k : cluster_sizes) num_rows += k;
  // CR2 costs rows * dimension^2 for B, and per group of k rows the smaller of an eigen-
  // decomposition of the k x k I - A_g and one of B_g^T B_g after forming it (k dimension^2); a
  // symmetric eigen-decomposition with its vectors takes about 5 n^3 (below). Measured: 0.5 s for
  // the whole covariance of a 20 s stream's fit (time offset, a dipole, poly4) over 32 runs.
  double leverage_flops = static_cast<double>(num_rows) * dimension * dimension;
  for (const auto& segments : groups) {
    double k = 0;
    for (const auto& seg : segments) k += seg.second;
    const double d = dimension;
    leverage_flops += std::min(5.0 * k * k * k, k * d * d + 5.0 * d * d * d);
  }
  const bool leverage = leverage_flops <= options.max_leverage_flops;
  // Leverages A_g = J_g H^+ J_g^T = B_g B_g^T with B = J S V_r diag(l_r)^-1/2 per group (H^+ is
  // block diagonal): one product per group instead of one per cluster.
  std::vector<Eigen::MatrixXd> factors, b;
  for (const Component& c : dense.components) {
    factors.push_back(GroupFactor(c));
    if (leverage) b.push_back(c.jacobian * factors.back());
  }
  // Scores s_g = J_g^T u_g, premultiplied by H^+ group by group: T = H^+ S.
  Eigen::MatrixXd scores = Eigen::MatrixXd::Zero(dimension, num_clusters);
  std::vector<int> rows;
  double sum_sq_residual = 0.0;  // of the clusters' residuals u_g (corrected with CR2)
  for (int g = 0; g < num_clusters; ++g) {
    rows.clear();
    for (const auto& [first, count] : groups[static_cast<size_t>(g)]) {
      for (int r = first; r < first + count; ++r) rows.push_back(r);
    }
    const int k = static_cast<int>(rows.size());
    Eigen::VectorXd u(k);
    for (int i = 0; i < k; ++i) u(i) = dense.residuals[static_cast<size_t>(rows[static_cast<size_t>(i)])];
    if (leverage) {
      // u = (I - A)^-1/2 r with A = B_g B_g^T, block diagonal over the column groups. A group with
      // fewer rows than columns (a station) decomposes I - A itself; a longer one (a run of stream
      // samples) B_g^T B_g = V diag(s^2) V^T: I - A has eigenvalues 1 - s^2 on B_g's column space
      // and 1 elsewhere, so (I - A)^-1/2 u = u + B_g V diag(f(s^2)) V^T B_g^T u with
      // f(x) = ((1 - x)^-1/2 - 1) / x, which costs the rows times the columns^2, not rows^3. A
      // leverage near 1 (a cluster that alone determines a direction) is capped so its residual is
      // inflated at most 1000-fold.
      std::map<int, std::vector<int>> rows_of_component;  // positions in `rows`
      for (int i = 0; i < k; ++i) {
        const int gi = dense.component_of_row[static_cast<size_t>(rows[static_cast<size_t>(i)])];
        if (gi >= 0) rows_of_component[gi].push_back(i);
      }
      Eigen::VectorXd corrected = u;
      for (const auto& [gi, positions] : rows_of_component) {
        const Eigen::MatrixXd& bc = b[static_cast<size_t>(gi)];
        Eigen::MatrixXd bg(static_cast<Eigen::Index>(positions.size()), bc.cols());
        Eigen::VectorXd ug(bg.rows());
        for (size_t i = 0; i < positions.size(); ++i) {
          const int ri = rows[static_cast<size_t>(positions[i])];
          bg.row(static_cast<Eigen::Index>(i)) = bc.row(dense.local_of_row[static_cast<size_t>(ri)]);
          ug(static_cast<Eigen::Index>(i)) = u(positions[i]);
        }
        if (bg.rows() <= bg.cols()) {
          const Eigen::SelfAdjointEigenSolver<Eigen::MatrixXd> eig(
              Eigen::MatrixXd::Identity(bg.rows(), bg.rows()) - bg * bg.transpose());
          const Eigen::VectorXd scale = eig.eigenvalues().cwiseMax(1e-6).cwiseSqrt().cwiseInverse();
          const Eigen::VectorXd ui = eig.eigenvectors() * scale.cwiseProduct(eig.eigenvectors().transpose() * ug);
          for (size_t i = 0; i < positions.size(); ++i) corrected(positions[i]) = ui(static_cast<Eigen::Index>(i));
          continue;
        }
        const Eigen::SelfAdjointEigenSolver<Eigen::MatrixXd> eig(bg.transpose() * bg);
        Eigen::VectorXd f(eig.eigenvalues().size());
        for (Eigen::Index j = 0; j < f.size(); ++j) {
          const double x = std::clamp(eig.eigenvalues()(j), 0.0, 1.0);
          // f(x) -> 1/2 as x -> 0 (its series 1/2 + 3x/8 + ...).
          f(j) = x < 1e-8 ? 0.5 : (1.0 / std::sqrt(std::max(1.0 - x, 1e-6)) - 1.0) / x;
        }
        const Eigen::VectorXd w = eig.eigenvectors().transpose() * (bg.transpose() * ug);
        const Eigen::VectorXd delta = bg * (eig.eigenvectors() * f.cwiseProduct(w));
        for (size_t i = 0; i < positions.size(); ++i) {
          corrected(positions[i]) += delta(static_cast<Eigen::Index>(i));
        }
      }
      u = corrected;
    }
    sum_sq_residual += u.squaredNorm();
    for (int i = 0; i < k; ++i) {
      const int ri = rows[static_cast<size_t>(i)];
      const int gi = dense.component_of_row[static_cast<size_t>(ri)];
      if (gi < 0) continue;
      const Component& c = dense.components[static_cast<size_t>(gi)];
      const auto row = c.jacobian.row(dense.local_of_row[static_cast<size_t>(ri)]);
      for (size_t j = 0; j < c.columns.size(); ++j) {
        scores(c.columns[j], g) += row(static_cast<Eigen::Index>(j)) * u(i);
      }
    }
  }
  double factor = 1.0;
  if (!leverage) {
    const double g = num_clusters, n = num_rows, p = dense.rank;
    factor = g > 1 && n > p ? g / (g - 1.0) * (n - 1.0) / (n - p) : 1.0;
  }
  // s^2: the corrected residuals have the noise's variance (CR2); the raw ones lose the rank's
  // share of the degrees of freedom (CR1).
  *noise_variance_scale =
      leverage ? sum_sq_residual / std::max(num_rows, 1)
               : sum_sq_residual / std::max(1.0, static_cast<double>(num_rows) - dense.rank);
  // T = H^+ S, group by group; H^+ M H^+ = factor T T^T + H^+ M_other H^+.
  Eigen::MatrixXd t = Eigen::MatrixXd::Zero(dimension, num_clusters);
  for (int g = 0; g < num_groups; ++g) {
    const Component& c = dense.components[static_cast<size_t>(g)];
    const Eigen::MatrixXd& f = factors[static_cast<size_t>(g)];
    const Eigen::Index m = static_cast<Eigen::Index>(c.columns.size());
    Eigen::MatrixXd s(m, num_clusters);
    for (Eigen::Index j = 0; j < m; ++j) s.row(j) = scores.row(c.columns[static_cast<size_t>(j)]);
    const Eigen::MatrixXd tg = f * (f.transpose() * s);
    for (Eigen::Index j = 0; j < m; ++j) t.row(c.columns[static_cast<size_t>(j)]) = tg.row(j);
  }
  *full = Eigen::MatrixXd::Zero(dimension, dimension);
  full->selfadjointView<Eigen::Lower>().rankUpdate(t, factor);
  *full = full->selfadjointView<Eigen::Lower>();
  if (have_other) {
    Eigen::MatrixXd meat = Eigen::MatrixXd::Zero(dimension, dimension);
    for (int kind = 0; kind < 2; ++kind) {
      const double scale = kind == 1 ? *noise_variance_scale : 1.0;
      for (int g = 0; g < num_groups; ++g) {
        const Component& c = dense.components[static_cast<size_t>(g)];
        const Eigen::MatrixXd& m = other_information[kind][static_cast<size_t>(g)];
        if (m.size() == 0) continue;
        for (size_t i = 0; i < c.columns.size(); ++i) {
          for (size_t j = 0; j < c.columns.size(); ++j) {
            meat(c.columns[i], c.columns[j]) +=
                scale * m(static_cast<Eigen::Index>(i), static_cast<Eigen::Index>(j));
          }
        }
      }
    }
    const Eigen::MatrixXd h_inv = PseudoInverse(dense, dimension);
    *full += h_inv * meat * h_inv;
  }
  *clusters = num_clusters;
  *estimator = std::string("sandwich (") + (leverage ? "CR2" : "CR1") +
               (options.cluster_groups.empty() ? "" : ", " + std::to_string(num_clusters) + " clusters") + ")";
  return true;
}

// H^-1(i, global g) = -(X S^-1)(i, g) for a local column i (SchurInverse below).
double LocalGlobalEntry(int i, int g, const std::vector<int>& group_of,
                          const std::vector<int>& local_of, const std::vector<Eigen::MatrixXd>& y) {
  return -y[static_cast<size_t>(group_of[static_cast<size_t>(i)])](local_of[static_cast<size_t>(i)], g);
}

// A symmetric positive definite band matrix A (A(i, j) = 0 for |i - j| > width) and its Cholesky
// factor, both in LAPACK's lower band storage: band(d, j) = A(j + d, j), 0 <= d <= width. Factoring,
// solving and the band of A^-1 cost n width^2, n width per right-hand side and n width^2: a LUT's
// node values ordered node by node have width ~ one layer of the grid (ny nz nodes), far below n.
class BandCholesky {
 public:
  BandCholesky(int n, int width) : n_(n), width_(width), band_(Eigen::MatrixXd::Zero(width + 1, n)) {}
  int width() const { return width_; }
  // A(i, j), i >= j, i - j <= width (before Factor()).
  double& Lower(int i, int j) { return band_(i - j, j); }
  // A = L L^T in place; false if A is not (numerically) positive definite.
  bool Factor() {
    for (int j = 0; j < n_; ++j) {
      const double d = band_(0, j);
      if (!(d > 0.0) || !std::isfinite(d)) return false;
      const double l = std::sqrt(d);
      band_(0, j) = l;
      const int k = std::min(width_, n_ - 1 - j);
      band_.col(j).segment(1, k) /= l;
      for (int c = 1; c <= k; ++c) {
        band_.col(j + c).head(k - c + 1).noalias() -= band_(c, j) * band_.col(j).segment(c, k - c + 1);
      }
    }
    return true;
  }
  // x = A^-1 x (after Factor()).
  void Solve(Eigen::MatrixXd* x) const {
    for (int j = 0; j < n_; ++j) {
      x->row(j) /= band_(0, j);
      const int k = std::min(width_, n_ - 1 - j);
      if (k > 0) x->middleRows(j + 1, k).noalias() -= band_.col(j).segment(1, k) * x->row(j);
    }
    for (int j = n_ - 1; j >= 0; --j) {
      const int k = std::min(width_, n_ - 1 - j);
      if (k > 0) {
        x->row(j).noalias() -= band_.col(j).segment(1, k).transpose() * x->middleRows(j + 1, k);
      }
      x->row(j) /= band_(0, j);
    }
  }
  // The entries of A^-1 within the band, same storage (after Factor()): Z = A^-1 satisfies
  // Z L = L^-T, upper triangular with diagonal 1 / L(j, j), so column j of Z's band follows from
  // the columns right of it (Takahashi's recurrence), which stay within the band.
  Eigen::MatrixXd BandOfInverse() const {
    Eigen::MatrixXd z = Eigen::MatrixXd::Zero(width_ + 1, n_);
    Eigen::VectorXd acc(width_ + 1);
    for (int j = n_ - 1; j >= 0; --j) {
      const int k = std::min(width_, n_ - 1 - j);
      const double l = band_(0, j);
      // acc(i) = sum_d Z(j + i, j + d) L(j + d, j), i, d in 1..k.
      acc.setZero();
      for (int d = 1; d <= k; ++d) {  // rows i >= d from column j + d of Z's band
        acc.segment(d, k - d + 1).noalias() += band_(d, j) * z.col(j + d).head(k - d + 1);
      }
      for (int i = 1; i < k; ++i) {  // rows i < d: Z(j + i, j + d) = Z(j + d, j + i)
        acc(i) += z.col(j + i).segment(1, k - i).dot(band_.col(j).segment(i + 1, k - i));
      }
      z.col(j).segment(1, k) = -acc.segment(1, k) / l;
      z(0, j) = (1.0 / l - z.col(j).segment(1, k).dot(band_.col(j).segment(1, k))) / l;
    }
    return z;
  }

 private:
  int n_, width_;
  Eigen::MatrixXd band_;
};

// The model covariance H^-1 of a problem too large for the dense analysis, when its columns are a
// few "global" ones that many rows touch (a physical term's parameters, in every station's
// residual) and local ones that fall into independent groups once the global columns are set
// aside, each a band matrix in column order (a LUT's node values: position x, y, z and orientation
// node by node, each coupled to its cell's neighbours only; one group of all six when the
// amplification whitening mixes a station's position and orientation rows). With
// H = [[A, B], [B^T, C]], A block diagonal over the groups,
//   H^-1 = [[A^-1 + X S^-1 X^T, -X S^-1], [-S^-1 X^T, S^-1]],  X = A^-1 B,  S = C - B^T X:
// one band Cholesky per group and one dense of S. Only the entries `wanted` asks for are formed
// (the requested blocks' own covariances and the cross-covariances asked for): A^-1 within the
// band from the band of the inverse, outside it by a solve per column. Fills `covariance`
// (requested coordinates `full_index`). False when the structure does not fit (too many global
// columns, bands too wide) or a factorisation fails (H not positive definite: the caller falls back
// to Ceres, which detects the rank deficiency).
template <typename WantedFn>
bool SchurInverse(ceres::Problem* problem, const std::vector<double*>& columns, int dimension,
                  const std::vector<int>& full_index, const WantedFn& wanted,
                  const std::vector<int>& sizes, const std::vector<int>& offsets,
                  Eigen::MatrixXd* covariance, int* num_groups) {
  ceres::Problem::EvaluateOptions eval;
  eval.parameter_blocks = columns;
  eval.apply_loss_function = true;
  ceres::CRSMatrix crs;
  if (!problem->Evaluate(eval, nullptr, nullptr, nullptr, &crs)) return false;
  if (crs.num_cols != dimension || dimension == 0) return false;
  // Global columns: touched by many more rows than a typical column.
  std::vector<int> count(static_cast<size_t>(dimension), 0);
  for (size_t k = 0; k < crs.values.size(); ++k) {
    if (crs.values[k] != 0.0) ++count[static_cast<size_t>(crs.cols[k])];
  }
  std::vector<int> sorted = count;
  std::nth_element(sorted.begin(), sorted.begin() + dimension / 2, sorted.end());
  const int median = std::max(1, sorted[static_cast<size_t>(dimension / 2)]);
  constexpr int kGlobalFactor = 16;  // a LUT node sees ~20 rows, a physical parameter thousands
  constexpr int kMaxGlobal = 200;    // S is dense: global^2 memory, global^3 flops
  // Band factorisations above this many flops (sum of n width^2) are left to Ceres: ~1 s.
  constexpr double kMaxBandFlops = 2e9;
  std::vector<int> global_index(static_cast<size_t>(dimension), -1);
  std::vector<int> global_columns;
  for (int c = 0; c < dimension; ++c) {
    if (count[static_cast<size_t>(c)] > kGlobalFactor * median) {
      global_index[static_cast<size_t>(c)] = static_cast<int>(global_columns.size());
      global_columns.push_back(c);
    }
  }
  if (static_cast<int>(global_columns.size()) > kMaxGlobal) return false;
  // Groups of the local columns (union-find over the rows' local non-zeros).
  std::vector<int> parent(static_cast<size_t>(dimension));
  for (int i = 0; i < dimension; ++i) parent[static_cast<size_t>(i)] = i;
  auto find = [&](int i) {
    while (parent[static_cast<size_t>(i)] != i) {
      parent[static_cast<size_t>(i)] = parent[static_cast<size_t>(parent[static_cast<size_t>(i)])];
      i = parent[static_cast<size_t>(i)];
    }
    return i;
  };
  for (int r = 0; r < crs.num_rows; ++r) {
    int root = -1;
    for (int k = crs.rows[r]; k < crs.rows[r + 1]; ++k) {
      const int c = crs.cols[k];
      if (crs.values[k] == 0.0 || global_index[static_cast<size_t>(c)] >= 0) continue;
      const int other = find(c);
      if (root < 0) {
        root = other;
      } else if (other != root) {
        parent[static_cast<size_t>(std::max(other, root))] = std::min(other, root);
        root = std::min(other, root);
      }
    }
  }
  // Each group's columns in ascending order: position `local_of` in the group's band matrix.
  std::vector<int> group_of(static_cast<size_t>(dimension), -1), local_of(static_cast<size_t>(dimension), -1);
  std::vector<std::vector<int>> groups;
  {
    std::map<int, int> index_of_root;
    for (int c = 0; c < dimension; ++c) {
      if (global_index[static_cast<size_t>(c)] >= 0) continue;
      const auto it = index_of_root.emplace(find(c), static_cast<int>(groups.size())).first;
      if (it->second == static_cast<int>(groups.size())) groups.emplace_back();
      group_of[static_cast<size_t>(c)] = it->second;
      local_of[static_cast<size_t>(c)] = static_cast<int>(groups[static_cast<size_t>(it->second)].size());
      groups[static_cast<size_t>(it->second)].push_back(c);
    }
  }
  // Band widths: the largest distance of two local non-zeros of a row (all in one group).
  std::vector<int> width(groups.size(), 0);
  for (int r = 0; r < crs.num_rows; ++r) {
    int lo = std::numeric_limits<int>::max(), hi = -1, g = -1;
    for (int k = crs.rows[r]; k < crs.rows[r + 1]; ++k) {
      const size_t c = static_cast<size_t>(crs.cols[k]);
      if (crs.values[k] == 0.0 || global_index[c] >= 0) continue;
      g = group_of[c];
      lo = std::min(lo, local_of[c]);
      hi = std::max(hi, local_of[c]);
    }
    if (g >= 0) width[static_cast<size_t>(g)] = std::max(width[static_cast<size_t>(g)], hi - lo);
  }
  double flops = 0.0;
  for (size_t g = 0; g < groups.size(); ++g) {
    flops += static_cast<double>(groups[g].size()) * (width[g] + 1.0) * (width[g] + 1.0);
  }
  if (flops > kMaxBandFlops) return false;
  // H's blocks, row by row: A's band per group, B per group, C.
  const int ng = static_cast<int>(global_columns.size());
  std::vector<BandCholesky> a;
  std::vector<Eigen::MatrixXd> b(groups.size());
  for (size_t g = 0; g < groups.size(); ++g) {
    a.emplace_back(static_cast<int>(groups[g].size()), width[g]);
    b[g] = Eigen::MatrixXd::Zero(static_cast<Eigen::Index>(groups[g].size()), ng);
  }
  Eigen::MatrixXd c = Eigen::MatrixXd::Zero(ng, ng);
  for (int r = 0; r < crs.num_rows; ++r) {
    for (int i = crs.rows[r]; i < crs.rows[r + 1]; ++i) {
      const double vi = crs.values[i];
      if (vi == 0.0) continue;
      const size_t ci = static_cast<size_t>(crs.cols[i]);
      for (int j = crs.rows[r]; j < crs.rows[r + 1]; ++j) {
        const double vj = crs.values[j];
        if (vj == 0.0) continue;
        const size_t cj = static_cast<size_t>(crs.cols[j]);
        if (global_index[ci] >= 0) {
          if (global_index[cj] >= 0) c(global_index[ci], global_index[cj]) += vi * vj;
        } else if (global_index[cj] >= 0) {
          b[static_cast<size_t>(group_of[ci])](local_of[ci], global_index[cj]) += vi * vj;
        } else if (local_of[ci] >= local_of[cj]) {
          a[static_cast<size_t>(group_of[ci])].Lower(local_of[ci], local_of[cj]) += vi * vj;
        }
      }
    }
  }
  // X = A^-1 B and S = C - B^T X per group; Y = X S^-1.
  std::vector<Eigen::MatrixXd> x(groups.size()), y(groups.size()), z(groups.size());
  Eigen::MatrixXd s = c;
  for (size_t g = 0; g < groups.size(); ++g) {
    if (!a[g].Factor()) return false;
    x[g] = b[g];
    a[g].Solve(&x[g]);
    s.noalias() -= b[g].transpose() * x[g];
    z[g] = a[g].BandOfInverse();
    if (!z[g].allFinite()) return false;
  }
  Eigen::MatrixXd s_inv = Eigen::MatrixXd::Zero(ng, ng);
  if (ng > 0) {
    const Eigen::LLT<Eigen::MatrixXd> llt(s);
    if (llt.info() != Eigen::Success) return false;
    s_inv = llt.solve(Eigen::MatrixXd::Identity(ng, ng));
    if (!s_inv.allFinite()) return false;
  }
  for (size_t g = 0; g < groups.size(); ++g) y[g] = x[g] * s_inv;
  // Columns of A^-1 outside the band, solved when first asked for.
  std::map<int, Eigen::VectorXd> solved;  // by full column
  auto a_inverse = [&](int i, int j) -> double {  // A^-1(i, j), i and j local, one group
    const size_t g = static_cast<size_t>(group_of[static_cast<size_t>(i)]);
    const int li = local_of[static_cast<size_t>(i)], lj = local_of[static_cast<size_t>(j)];
    if (std::abs(li - lj) <= width[g]) return z[g](std::abs(li - lj), std::min(li, lj));
    auto it = solved.find(j);
    if (it == solved.end()) {
      Eigen::MatrixXd e = Eigen::MatrixXd::Zero(static_cast<Eigen::Index>(groups[g].size()), 1);
      e(lj, 0) = 1.0;
      a[g].Solve(&e);
      it = solved.emplace(j, e.col(0)).first;
    }
    return it->second(li);
  };
  auto entry = [&](int i, int j) -> double {  // H^-1(i, j), full columns
    const int gi = global_index[static_cast<size_t>(i)], gj = global_index[static_cast<size_t>(j)];
    if (gi >= 0 && gj >= 0) return s_inv(gi, gj);
    if (gi >= 0) return LocalGlobalEntry(j, gi, group_of, local_of, y);
    if (gj >= 0) return LocalGlobalEntry(i, gj, group_of, local_of, y);
    const size_t g = static_cast<size_t>(group_of[static_cast<size_t>(i)]);
    const size_t h = static_cast<size_t>(group_of[static_cast<size_t>(j)]);
    double v = ng > 0 ? x[g].row(local_of[static_cast<size_t>(i)]).dot(y[h].row(local_of[static_cast<size_t>(j)]))
                      : 0.0;
    if (g == h) v += a_inverse(i, j);
    return v;
  };
  const int n = static_cast<int>(full_index.size());
  *covariance = Eigen::MatrixXd::Zero(n, n);
  for (size_t bi = 0; bi < sizes.size(); ++bi) {
    for (size_t bj = bi; bj < sizes.size(); ++bj) {
      if (!wanted(bi, bj)) continue;
      for (int p = 0; p < sizes[bi]; ++p) {
        for (int q = 0; q < sizes[bj]; ++q) {
          const int ra = offsets[bi] + p, rb = offsets[bj] + q;
          const double v = entry(full_index[static_cast<size_t>(ra)], full_index[static_cast<size_t>(rb)]);
          (*covariance)(ra, rb) = v;
          (*covariance)(rb, ra) = v;
        }
      }
    }
  }
  *num_groups = static_cast<int>(groups.size()) + (ng > 0 ? 1 : 0);
  return true;
}

// (Pseudo-)inverse over the requested rows `full_index`, from each group's eigenvalues above the
// rank threshold: H^+ = S V_r diag(1/l_r) V_r^T S; pairs of blocks not `wanted` are zero.
template <typename WantedFn>
Eigen::MatrixXd DenseInverse(const DenseAnalysis& dense, int dimension,
                             const std::vector<int>& full_index, const WantedFn& wanted,
                             const std::vector<CovarianceBlock>& blocks,
                             const std::vector<int>& sizes, const std::vector<int>& offsets) {
  const int n = static_cast<int>(full_index.size());
  const Eigen::MatrixXd h_inv = PseudoInverse(dense, dimension);
  Eigen::MatrixXd covariance(n, n);
  for (int i = 0; i < n; ++i) {
    for (int j = 0; j < n; ++j) covariance(i, j) = h_inv(full_index[i], full_index[j]);
  }
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
    result.num_groups = static_cast<int>(dense.components.size());
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

  // Variance inflation of each requested coordinate, H_jj (H^+)_jj: H_jj = 1 / scale_j^2 and
  // (H^+)_jj = |row j of the group's factor|^2 (GroupFactor).
  if (dense.done) {
    result.variance_inflation =
        Eigen::VectorXd::Constant(n, std::numeric_limits<double>::quiet_NaN());
    std::map<int, Eigen::MatrixXd> factor_of_group;
    for (int i = 0; i < n; ++i) {
      const size_t column = static_cast<size_t>(full_index[static_cast<size_t>(i)]);
      const int g = dense.component_of_column[column];
      if (g < 0) continue;
      const Component& c = dense.components[static_cast<size_t>(g)];
      auto it = factor_of_group.find(g);
      if (it == factor_of_group.end()) it = factor_of_group.emplace(g, GroupFactor(c)).first;
      const int local = dense.local_of_column[column];
      const double scale = c.scale(local);
      if (scale > 0.0) {
        result.variance_inflation(i) = it->second.row(local).squaredNorm() / (scale * scale);
      }
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
    } else if (options.clusters.size() < 2 ||
               (!options.cluster_groups.empty() &&
                std::set<int>(options.cluster_groups.begin(), options.cluster_groups.end()).size() < 2)) {
      why = "fewer than 2 clusters";
    } else {
      Eigen::MatrixXd full;
      std::string estimator;
      int clusters = 0;
      double noise_variance_scale = std::numeric_limits<double>::quiet_NaN();
      if (SandwichCovariance(problem, result.tangent_dimension, dense, options, &full,
                             &estimator, &clusters, &noise_variance_scale, &why)) {
        result.noise_variance_scale = noise_variance_scale;
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
        result.num_clusters = clusters;
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
    result.covariance = DenseInverse(dense, result.tangent_dimension, full_index, Wanted, blocks,
                                     sizes, result.block_offsets);
    result.method = "dense_inverse";
    have_covariance = true;
  }
  if (!have_covariance && !result.rank_deficient && !dense.done && options.schur_large_problems) {
    int groups = 0;
    if (SchurInverse(problem, columns, result.tangent_dimension, full_index, Wanted, sizes,
                     result.block_offsets, &result.covariance, &groups)) {
      result.method = "schur_banded_groups";
      result.num_groups = groups;
      have_covariance = true;
    }
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
    result.covariance = DenseInverse(dense, result.tangent_dimension, full_index, Wanted, blocks,
                                     sizes, result.block_offsets);
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
    const double largest = dense.largest;
    for (std::size_t w = 0; w < dense.weak.size(); ++w) {
      const double ratio =
          largest > 0.0 ? std::max(0.0, dense.Eigenvalue(dense.weak[w])) / largest : 0.0;
      for (int k = 0; k < n; ++k) {
        if (std::abs(dense.WeakComponent(dense.weak[w], full_index[k])) >
            options.weak_component_threshold) {
          result.flags.push_back({result.coordinate_names[k],
                                  "moved by weak direction " + std::to_string(w) +
                                      " (eigenvalue ratio " + Format("%.2g", ratio) + ")"});
        }
      }
    }
    if (!dense.weak.empty()) {
      result.message += std::to_string(dense.weak.size()) + " weak direction(s) in the problem";
    }
    // A coordinate the null space of H moves is not determined by the data at all: the
    // pseudo-inverse leaves that direction out and gave it the variance of its determined part
    // (0.125 for each of two offsets of which only the sum is seen; 0 for a coordinate no residual
    // touches), which reads as a measurement. Its standard deviation is infinite. Shares of the
    // null space below 1e-6 (components of 1e-3) are taken as rounding.
    constexpr double kNullShare = 1e-6;
    for (int k = 0; k < n; ++k) {
      const size_t column = static_cast<size_t>(full_index[static_cast<size_t>(k)]);
      const Component& c = dense.components[static_cast<size_t>(dense.component_of_column[column])];
      const Eigen::Index null = c.eigenvalues.size() - c.rank;  // ascending: the first ones
      if (null <= 0) continue;
      const double share =
          c.eigenvectors.row(dense.local_of_column[column]).head(null).squaredNorm();
      if (!(share > kNullShare)) continue;
      result.stddev(k) = std::numeric_limits<double>::infinity();
      const bool flagged =
          std::any_of(result.flags.begin(), result.flags.end(), [&](const IdentifiabilityFlag& f) {
            return f.coordinate == result.coordinate_names[static_cast<size_t>(k)];
          });
      if (!flagged) {
        result.flags.push_back({result.coordinate_names[static_cast<size_t>(k)],
                                "not determined (null space share " + Format("%.2g", share) + ")"});
      }
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
