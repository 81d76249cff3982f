#include "fit/terms_polynomial.h"

#include <ceres/cost_function.h>
#include <ceres/jet.h>
#include <ceres/problem.h>

#include <Eigen/Cholesky>
#include <Eigen/Eigenvalues>
#include <Eigen/QR>
#include <Eigen/SVD>
#include <algorithm>
#include <array>
#include <cmath>
#include <limits>
#include <sstream>
#include <stdexcept>

namespace trackcal::fit {

void PolynomialTermOptions::Check() const {
  CheckPolynomialDegree(degree);
  if (!position && !orientation) {
    throw std::invalid_argument("polynomial: at least one of position, orientation must be enabled");
  }
  if (!(ridge >= 0.0) || !std::isfinite(ridge)) {
    throw std::invalid_argument("polynomial: ridge must be a number >= 0 or auto");
  }
  if (!(max_amplification == 0.0 || max_amplification >= 1.0) ||
      !std::isfinite(max_amplification)) {
    throw std::invalid_argument("polynomial: max_amplification must be 0 (no limit) or >= 1");
  }
}

namespace {

// Moves a term-major (basis x 3) coefficient block only within span(U) for each of its 3 columns:
// x + B delta with B = U (x) I_3 in the block's layout (values[j * 3 + k], basis j, output k).
class CoefficientSubspaceManifold : public ceres::Manifold {
 public:
  explicit CoefficientSubspaceManifold(Eigen::MatrixXd b)
      : b_(std::move(b)),
        b_pinv_((b_.transpose() * b_).ldlt().solve(b_.transpose())) {}
  int AmbientSize() const override { return static_cast<int>(b_.rows()); }
  int TangentSize() const override { return static_cast<int>(b_.cols()); }
  bool Plus(const double* x, const double* delta, double* x_plus_delta) const override {
    Eigen::Map<Eigen::VectorXd>(x_plus_delta, b_.rows()) =
        Eigen::Map<const Eigen::VectorXd>(x, b_.rows()) +
        b_ * Eigen::Map<const Eigen::VectorXd>(delta, b_.cols());
    return true;
  }
  bool PlusJacobian(const double* /*x*/, double* jacobian) const override {
    Eigen::Map<Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>>(
        jacobian, b_.rows(), b_.cols()) = b_;
    return true;
  }
  bool Minus(const double* y, const double* x, double* y_minus_x) const override {
    Eigen::Map<Eigen::VectorXd>(y_minus_x, b_.cols()) =
        b_pinv_ * (Eigen::Map<const Eigen::VectorXd>(y, b_.rows()) -
                   Eigen::Map<const Eigen::VectorXd>(x, b_.rows()));
    return true;
  }
  bool MinusJacobian(const double* /*x*/, double* jacobian) const override {
    Eigen::Map<Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>>(
        jacobian, b_.cols(), b_.rows()) = b_pinv_;
    return true;
  }

 private:
  Eigen::MatrixXd b_;
  Eigen::MatrixXd b_pinv_;
};

}  // namespace

Eigen::MatrixXd PolynomialTerm::BoxGram(int degree, const Eigen::Vector3d& lo,
                                        const Eigen::Vector3d& hi) {
  // E[u^a] over the uniform interval [lo, hi] per axis: (hi^(a+1) - lo^(a+1)) / ((a+1)(hi - lo));
  // [-1, 1]: 1 / (a + 1) for even a, 0 for odd a.
  auto moment = [&](int k, int a) {
    const double l = lo[k], h = hi[k];
    if (!(h - l > 1e-12)) return std::pow(l, a);
    return (std::pow(h, a + 1) - std::pow(l, a + 1)) / ((a + 1) * (h - l));
  };
  const auto exponents = PolynomialTermExponents(degree);
  const auto n = static_cast<Eigen::Index>(exponents.size());
  Eigen::MatrixXd g(n, n);
  for (Eigen::Index i = 0; i < n; ++i) {
    for (Eigen::Index j = 0; j < n; ++j) {
      double m = 1.0;
      for (int k = 0; k < 3; ++k) {
        m *= moment(k, exponents[static_cast<size_t>(i)][k] + exponents[static_cast<size_t>(j)][k]);
      }
      g(i, j) = m;
    }
  }
  return g;
}

std::vector<bool> PolynomialTerm::IsolatedStations(const Eigen::MatrixXd& u) {
  const auto n = static_cast<size_t>(u.rows());
  std::vector<bool> isolated(n, false);
  // O(n^2): beyond kMaxIsolationStations (long streams) nothing is flagged.
  if (n < 10 || n > kMaxIsolationStations) return isolated;
  std::vector<double> nearest(n, std::numeric_limits<double>::infinity());
  for (size_t i = 0; i < n; ++i) {
    for (size_t j = i + 1; j < n; ++j) {
      const double d = (u.row(static_cast<Eigen::Index>(i)) - u.row(static_cast<Eigen::Index>(j)))
                           .squaredNorm();
      nearest[i] = std::min(nearest[i], d);
      nearest[j] = std::min(nearest[j], d);
    }
  }
  std::vector<double> sorted = nearest;
  std::nth_element(sorted.begin(), sorted.begin() + static_cast<std::ptrdiff_t>(n / 2),
                   sorted.end());
  const double median = sorted[n / 2];  // squared
  // 4 times the median distance, and at least an eighth of the normalised range (2): with half the
  // stations in tight clusters (pauses of a stream, repeated stations) the median alone is the
  // clusters' spacing and would flag every other station (review: 1401 of 3600 samples).
  const double limit = std::max(16.0 * median, 0.25 * 0.25);
  size_t count = 0;
  for (size_t i = 0; i < n; ++i) {
    isolated[i] = nearest[i] > limit;
    count += isolated[i] ? 1 : 0;
  }
  // Gross outliers are few: when more would be flagged, the stations are merely uneven.
  if (static_cast<double>(count) > std::max(3.0, 0.05 * static_cast<double>(n))) {
    std::fill(isolated.begin(), isolated.end(), false);
  }
  return isolated;
}

PolynomialTerm::DeterminedSubspace PolynomialTerm::FindDeterminedSubspace(
    const Eigen::MatrixXd& a, int degree, double max_amplification, const Eigen::MatrixXd* u) {
  // The volume: the box of the stations that are not isolated (u given), else [-1, 1]^3. A station
  // whose nearest neighbour is more than 4 times the median nearest-neighbour distance away (a
  // hemisphere flip reports -p, on the far side of the transmitter) would otherwise stretch the
  // box over empty space, where every polynomial is undetermined (measured, workflow capture,
  // hemisphere_flips seed 1: 3 directions held in every fit, and the loop stopped before the
  // workbench frame).
  DeterminedSubspace out;
  Eigen::Vector3d lo = -Eigen::Vector3d::Ones(), hi = Eigen::Vector3d::Ones();
  std::vector<Eigen::Index> rows;
  if (u != nullptr && u->rows() == a.rows()) {
    const std::vector<bool> isolated = IsolatedStations(*u);
    lo = Eigen::Vector3d::Constant(std::numeric_limits<double>::infinity());
    hi = -lo;
    for (Eigen::Index i = 0; i < a.rows(); ++i) {
      if (isolated[static_cast<size_t>(i)]) {
        ++out.isolated_stations;
        continue;
      }
      rows.push_back(i);
      lo = lo.cwiseMin(u->row(i).transpose());
      hi = hi.cwiseMax(u->row(i).transpose());
    }
    // A box much thinner than the normalisation's makes its Gram matrix numerically singular (a
    // condition number ~1e14 for a slab 0.02 wide, review): then, as for a flat axis, the
    // normalised box and every station.
    bool thin = false;
    for (int k = 0; k < 3; ++k) thin = thin || !(hi[k] - lo[k] > 0.5);
    if (thin) {
      lo = -Eigen::Vector3d::Ones();
      hi = Eigen::Vector3d::Ones();
      rows.clear();
      out.isolated_stations = 0;
    }
  }
  if (rows.empty()) {
    for (Eigen::Index i = 0; i < a.rows(); ++i) rows.push_back(i);
  }
  Eigen::MatrixXd kept_rows(static_cast<Eigen::Index>(rows.size()), a.cols());
  for (size_t i = 0; i < rows.size(); ++i) {
    kept_rows.row(static_cast<Eigen::Index>(i)) = a.row(rows[i]);
  }
  // Gs c = mu Gv c (Gv positive definite): the eigenvectors are Gv-orthonormal, and a direction's
  // RMS over the box is 1 / sqrt(mu) times its RMS at the stations.
  const Eigen::MatrixXd gs = kept_rows.transpose() * kept_rows /
                             static_cast<double>(std::max<Eigen::Index>(1, kept_rows.rows()));
  const Eigen::MatrixXd gv = BoxGram(degree, lo, hi);
  const Eigen::GeneralizedSelfAdjointEigenSolver<Eigen::MatrixXd> solver(gs, gv);
  const Eigen::VectorXd& mu = solver.eigenvalues();  // ascending
  const double mu_min = 1.0 / (max_amplification * max_amplification);
  std::vector<Eigen::Index> dropped;
  for (Eigen::Index i = 0; i < mu.size(); ++i) {
    const double amplification =
        mu[i] > 0 ? 1.0 / std::sqrt(mu[i]) : std::numeric_limits<double>::infinity();
    if (mu[i] >= mu_min) {
      out.max_kept_amplification = std::max(out.max_kept_amplification, amplification);
    } else {
      dropped.push_back(i);
      out.dropped_amplifications.push_back(amplification);  // largest first (mu ascending)
    }
  }
  const Eigen::Index n = a.cols();
  const auto m = static_cast<Eigen::Index>(dropped.size());
  if (m == 0) {
    out.basis = Eigen::MatrixXd::Identity(n, n);
    return out;
  }
  // Which solution of the stations' equations to keep: each dropped direction v is nearly zero
  // at the stations, so c and c + t v fit them alike. Holding t at zero in the eigenbasis would
  // keep the solution smallest over the box, which is not the smooth one (a quadratic error field
  // has a component along (z - z1)...(z - z4) in that sense and would lose it). Instead the
  // directions are taken out of the highest-degree coefficients: the kept coefficients c satisfy
  // V_T^T c_T = 0, T the monomials of degree >= d0 with d0 the highest degree for which the
  // subspace this leaves meets the limit. A polynomial of degree < d0 satisfies it, so it is
  // fitted without bias.
  const auto exponents = PolynomialTermExponents(degree);
  Eigen::MatrixXd v(n, m);
  for (Eigen::Index j = 0; j < m; ++j) {
    v.col(j) = solver.eigenvectors().col(dropped[static_cast<size_t>(j)]);
  }
  // The null space of the constraint (the last n - m columns of the complete Q of K^T), accepted
  // only when every direction left in it meets the limit (the restricted eigenproblem): a rank
  // test on the top-degree rows passes near-dependent ones (degree 5 on 4 layers) and leaves an
  // undetermined direction inside (review, numpy: 1095 left of 1167).
  for (int d0 = degree; d0 >= 0; --d0) {
    Eigen::MatrixXd constraint = Eigen::MatrixXd::Zero(m, n);
    for (Eigen::Index j = 0; j < n; ++j) {
      const auto& e = exponents[static_cast<size_t>(j)];
      if (e[0] + e[1] + e[2] >= d0) constraint.col(j) = v.row(j).transpose();
    }
    const Eigen::HouseholderQR<Eigen::MatrixXd> qr(constraint.transpose());
    const Eigen::MatrixXd q = qr.householderQ() * Eigen::MatrixXd::Identity(n, n);
    const Eigen::MatrixXd u = q.rightCols(n - m);
    const Eigen::GeneralizedSelfAdjointEigenSolver<Eigen::MatrixXd> kept(
        u.transpose() * gs * u, u.transpose() * gv * u, Eigen::EigenvaluesOnly);
    if (kept.eigenvalues().minCoeff() >= mu_min) {
      out.basis = u;
      return out;
    }
  }
  // No degree split works: the eigenvectors that meet the limit (smallest over the box among the
  // solutions; a low-degree field may then lose its component along the held directions).
  Eigen::MatrixXd x(n, n - m);
  Eigen::Index col = 0;
  for (Eigen::Index i = 0; i < mu.size(); ++i) {
    if (mu[i] >= mu_min) x.col(col++) = solver.eigenvectors().col(i);
  }
  const Eigen::HouseholderQR<Eigen::MatrixXd> orth(x);
  out.basis = orth.householderQ() * Eigen::MatrixXd::Identity(n, n - m);
  return out;
}

std::vector<double> PolynomialTerm::RidgeGrid() {
  std::vector<double> grid = {0.0};
  for (int k = -8; k <= 4; ++k) grid.push_back(std::pow(10.0, 0.5 * k));
  return grid;
}

PolynomialTerm::PolynomialTerm(const PolynomialTermOptions& options) : options_(options) {
  options_.Check();
  num_terms_ = NumPolynomialTerms(options_.degree);
  const auto exponents = PolynomialTermExponents(options_.degree);
  auto make_block = [&](const std::string& name, const char* axis_prefix, const std::string& unit) {
    ParameterBlock block;
    block.name = name;
    block.values.assign(static_cast<size_t>(num_terms_) * 3, 0.0);
    block.unit = unit;
    for (int j = 0; j < num_terms_; ++j) {
      for (int k = 0; k < 3; ++k) {
        block.coordinate_names.push_back(std::string(axis_prefix) + "xyz"[k] + "[" +
                                         PolynomialTermName(exponents[static_cast<size_t>(j)]) +
                                         "]");
      }
    }
    blocks_.push_back(std::move(block));
    return static_cast<int>(blocks_.size()) - 1;
  };
  if (options_.position) position_block_ = make_block("position_coefficients", "p", "m");
  if (options_.orientation) orientation_block_ = make_block("orientation_coefficients", "q", "1");
}

std::unique_ptr<ModelTerm> PolynomialTerm::FromYaml(const YamlMapReader& reader) {
  PolynomialTermOptions options;
  options.degree = reader.GetIntOr("degree", options.degree);
  options.position = reader.GetBoolOr("position", options.position);
  options.orientation = reader.GetBoolOr("orientation", options.orientation);
  options.max_amplification = reader.GetDoubleOr("max_amplification", options.max_amplification);
  if (reader.Has("ridge")) {
    const YAML::Node node = reader.node()["ridge"];
    if (node.IsScalar() && node.Scalar() == "auto") {
      options.ridge_auto = true;
      reader.MarkRead("ridge");
      if (reader.Has("ridge_cv")) {
        const std::string cv = reader.GetString("ridge_cv");
        if (cv == "blocked") {
          options.ridge_selection = PolynomialTermOptions::RidgeSelection::kBlocked;
        } else if (cv == "leave_one_out") {
          options.ridge_selection = PolynomialTermOptions::RidgeSelection::kLeaveOneOut;
        } else {
          reader.Fail("ridge_cv", "expected blocked or leave_one_out, got '" + cv + "'");
        }
      }
    } else {
      options.ridge = reader.GetDouble("ridge");
    }
  }
  if (!options.ridge_auto && reader.node()["ridge_cv"].IsDefined()) {
    reader.Fail("ridge_cv", "only with ridge: auto (it says how the weight is chosen)");
  }
  try {
    options.Check();
  } catch (const std::invalid_argument& e) {
    const std::string what = e.what();
    // Blame the key the check is about ("position, orientation" was blamed on `degree`).
    reader.Fail(what.find("ridge") != std::string::npos               ? "ridge"
                : what.find("max_amplification") != std::string::npos ? "max_amplification"
                : what.find("orientation") != std::string::npos       ? "orientation"
                                                                      : "degree",
                what);
  }
  return std::make_unique<PolynomialTerm>(options);
}

nlohmann::json PolynomialTerm::PreparedState() const {
  if (std::isnan(options_.input_offset[0]) || std::isnan(options_.input_scale[0])) return nullptr;
  const Eigen::Vector3d& o = options_.input_offset;
  const Eigen::Vector3d& c = options_.input_scale;
  return {{"degree", options_.degree},
          {"input_offset", {o[0], o[1], o[2]}},
          {"input_scale", {c[0], c[1], c[2]}},
          {"ridge_used", {ridge_used_[0], ridge_used_[1]}}};
}

bool PolynomialTerm::AdoptPreparedState(const nlohmann::json& state) {
  adopted_ridge_.reset();  // an earlier start's weight does not outlive it
  if (state.is_null()) return true;
  if (!state.is_object() || state.value("degree", -1) != options_.degree) return false;
  // A start document edited by hand (or not a fit's): a zero scale crashed the fit (SIGSEGV).
  // lower: the values must be at least it (strictly above it when `strict`).
  auto numbers = [&](const char* key, size_t n, double lower, bool strict) {
    const nlohmann::json v = state.contains(key) ? state.at(key) : nlohmann::json();
    Eigen::VectorXd out(static_cast<Eigen::Index>(n));
    bool ok = v.is_array() && v.size() == n;
    for (size_t k = 0; ok && k < n; ++k) {
      const double x = v[k].is_number() ? v[k].get<double>() : std::nan("");
      ok = std::isfinite(x) && (strict ? x > lower : x >= lower);
      out[static_cast<Eigen::Index>(k)] = x;
    }
    if (!ok) {
      throw std::invalid_argument(std::string("polynomial: prepared state: ") + key +
                                  ": expected " + std::to_string(n) + " finite numbers" +
                                  (strict              ? " > 0"
                                   : lower > -HUGE_VAL ? " >= 0"
                                                       : ""));
    }
    return out;
  };
  const Eigen::VectorXd offset = numbers("input_offset", 3, -HUGE_VAL, false);
  const Eigen::VectorXd scale = numbers("input_scale", 3, 0.0, true);
  options_.input_offset = offset;
  options_.input_scale = scale;
  // A fixed weight stays the file's; `ridge: auto` takes the weight the other fit chose, if the
  // state gives it (without it the weight is chosen again, at the start).
  if (options_.ridge_auto && state.contains("ridge_used")) {
    const Eigen::VectorXd r = numbers("ridge_used", 2, 0.0, false);
    adopted_ridge_ = Eigen::Vector2d(r[0], r[1]);
  }
  return true;
}

void PolynomialTerm::Prepare(const std::vector<FitStation>& inputs) {
  if (!std::isnan(options_.input_offset[0]) && !std::isnan(options_.input_scale[0])) return;
  if (inputs.empty()) throw std::invalid_argument("polynomial: no calibration stations");
  Eigen::Vector3d lo = inputs[0].reported.translation, hi = lo;
  for (const auto& s : inputs) {
    lo = lo.cwiseMin(s.reported.translation);
    hi = hi.cwiseMax(s.reported.translation);
  }
  options_.input_offset = 0.5 * (lo + hi);
  // Half the extent maps the box to [-1, 1]; a flat axis keeps scale 1 m (its powers are constant).
  options_.input_scale = (0.5 * (hi - lo)).unaryExpr([](double v) { return v > 1e-9 ? v : 1.0; });
}

namespace {

// Ridge regression of the columns `shrunk` of `a` (the others free) for every right-hand side of b,
// at weight lambda: returns the coefficients (a.cols() x b.cols()) and, in *loo, each station's
// squared leave-one-out residual summed over b's columns, (e_i / (1 - H_ii))^2 by the hat matrix H.
// Free columns are projected out (Q0), the shrunk ones solved by the SVD of what remains. The free
// columns may be dependent (stations on a plane: a flat axis's column is zero, a tilted plane's
// z = a x + b y + c); Q0 spans their range and the free coefficients are the minimum-norm solution
// (the undetermined ones zero), not the inverse of a singular R (non-finite coefficients).
struct RidgeSolver {
  Eigen::MatrixXd q0, a0, a1;  // orthonormal basis of the free columns' range; the columns
  Eigen::CompleteOrthogonalDecomposition<Eigen::MatrixXd> cod0;  // of a0
  Eigen::MatrixXd u, v;            // SVD of (I - Q0 Q0^T) A1
  Eigen::VectorXd s;
  std::vector<int> free_cols, shrunk_cols;

  RidgeSolver(const Eigen::MatrixXd& a, const std::vector<bool>& shrunk) {
    for (int j = 0; j < a.cols(); ++j) (shrunk[static_cast<size_t>(j)] ? shrunk_cols : free_cols).push_back(j);
    a0.resize(a.rows(), static_cast<Eigen::Index>(free_cols.size()));
    a1.resize(a.rows(), static_cast<Eigen::Index>(shrunk_cols.size()));
    for (size_t j = 0; j < free_cols.size(); ++j) a0.col(static_cast<Eigen::Index>(j)) = a.col(free_cols[j]);
    for (size_t j = 0; j < shrunk_cols.size(); ++j) a1.col(static_cast<Eigen::Index>(j)) = a.col(shrunk_cols[j]);
    cod0.compute(a0);
    q0 = cod0.householderQ() * Eigen::MatrixXd::Identity(a.rows(), cod0.rank());
    if (shrunk_cols.empty()) {
      // Degree <= 1: nothing to shrink, the ridge is plain least squares (Eigen's SVD of an
      // n x 0 matrix reads past its storage: a degree-1 polynomial with a ridge crashed the fit).
      u.setZero(a.rows(), 0);
      v.setZero(0, 0);
      s.resize(0);
      return;
    }
    const Eigen::MatrixXd p1 = a1 - q0 * (q0.transpose() * a1);
    const Eigen::BDCSVD<Eigen::MatrixXd> svd(p1, Eigen::ComputeThinU | Eigen::ComputeThinV);
    u = svd.matrixU();
    v = svd.matrixV();
    s = svd.singularValues();
  }

  Eigen::MatrixXd Solve(const Eigen::MatrixXd& b, double lambda, Eigen::VectorXd* loo) const {
    const Eigen::VectorXd f = s.array().square() / (s.array().square() + lambda * lambda);
    const Eigen::VectorXd g =
        (s.array() > 0).select(s.array() / (s.array().square() + lambda * lambda), 0.0);
    const Eigen::MatrixXd b1 = b - q0 * (q0.transpose() * b);
    const Eigen::MatrixXd c1 = v * (g.asDiagonal() * (u.transpose() * b1));
    const Eigen::MatrixXd c0 = cod0.solve(b - a1 * c1);
    Eigen::MatrixXd c(static_cast<Eigen::Index>(free_cols.size() + shrunk_cols.size()), b.cols());
    for (size_t j = 0; j < free_cols.size(); ++j) c.row(free_cols[j]) = c0.row(static_cast<Eigen::Index>(j));
    for (size_t j = 0; j < shrunk_cols.size(); ++j) c.row(shrunk_cols[j]) = c1.row(static_cast<Eigen::Index>(j));
    if (loo != nullptr) {
      const Eigen::VectorXd h =
          q0.rowwise().squaredNorm() + u.array().square().matrix() * f;
      const Eigen::MatrixXd e = b - a0 * c0 - a1 * c1;
      *loo = (e.array().colwise() / (1.0 - h.array().min(1.0 - 1e-9))).square().rowwise().sum();
    }
    return c;
  }
};

// Least-squares coefficients c (num_terms x 3) into `block` (values[j * 3 + k] = c(j, k)). The
// linear solve does not see a block's bounds (`parameters: {lower, upper}`): a coefficient beyond
// one is put on it, a start inside them from which the joint solve (which keeps the bounds) goes
// on. Kept as solved, it was refused as the fit's start: a constant offset bounded to >= 1 mm
// (`lower: [0.001, -1, -1]`) on stations with none failed with "value 0.000002 outside its bounds"
// (fit/fit_engine_test.cc ABoundedPolynomialCoefficientStartsWithinItsBounds).
void StoreCoefficients(const Eigen::MatrixXd& c, ParameterBlock* block) {
  for (Eigen::Index j = 0; j < c.rows(); ++j) {
    for (Eigen::Index k = 0; k < 3; ++k) {
      const size_t i = static_cast<size_t>(j * 3 + k);
      double v = c(j, k);
      if (!block->lower.empty()) v = std::max(v, block->lower[i]);
      if (!block->upper.empty()) v = std::min(v, block->upper[i]);
      block->values[i] = v;
    }
  }
}

}  // namespace

std::vector<std::vector<int>> PolynomialTerm::BlockedFolds(const Eigen::MatrixXd& u,
                                                           int slabs_per_axis) {
  const int n = static_cast<int>(u.rows());
  std::vector<std::vector<int>> folds(3, std::vector<int>(static_cast<size_t>(n), -1));
  const int m = std::min(slabs_per_axis, n);
  if (m < 2) return folds;
  for (int k = 0; k < 3; ++k) {
    std::vector<int> order(static_cast<size_t>(n));
    for (int i = 0; i < n; ++i) order[static_cast<size_t>(i)] = i;
    std::stable_sort(order.begin(), order.end(), [&](int i, int j) { return u(i, k) < u(j, k); });
    auto value = [&](int rank) { return u(order[static_cast<size_t>(rank)], k); };
    // Layers: a gap wider than 10 times the median gap between neighbouring coordinates and a
    // quarter of the widest starts a new one (a grid's layers, however wobbly: their gaps are all
    // about the spacing, a layer's own stragglers far less; uniform random data has almost no such
    // gap).
    std::vector<double> gaps;
    for (int r = 1; r < n; ++r) gaps.push_back(value(r) - value(r - 1));
    std::vector<double> sorted_gaps = gaps;
    std::nth_element(sorted_gaps.begin(), sorted_gaps.begin() + (n - 1) / 2, sorted_gaps.end());
    const double threshold = std::max(10.0 * sorted_gaps[static_cast<size_t>((n - 1) / 2)],
                                      0.25 * *std::max_element(gaps.begin(), gaps.end()));
    std::vector<int> layer_starts;  // ranks where a layer starts (after rank 0)
    for (int r = 1; r < n; ++r) {
      const double gap = gaps[static_cast<size_t>(r - 1)];
      if (gap > threshold && gap > 0.0) layer_starts.push_back(r);
    }
    // Cuts: every layer boundary when there are at most m layers; otherwise the layer boundary
    // nearest each quantile j n / m; without layers, the quantiles themselves (ties kept together).
    std::vector<int> bounds;
    if (!layer_starts.empty() && static_cast<int>(layer_starts.size()) + 1 <= m) {
      bounds = layer_starts;
    } else {
      for (int j = 1; j < m; ++j) {
        int q = j * n / m;
        if (!layer_starts.empty()) {
          q = *std::min_element(layer_starts.begin(), layer_starts.end(),
                                [&](int x, int y) { return std::abs(x - q) < std::abs(y - q); });
        } else {
          while (q < n && value(q) == value(q - 1)) ++q;
          if (q >= n) continue;
        }
        if (bounds.empty() || q > bounds.back()) bounds.push_back(q);
      }
    }
    if (bounds.empty()) continue;  // a flat axis: no slabs
    size_t slab = 0;
    for (int r = 0; r < n; ++r) {
      while (slab < bounds.size() && r >= bounds[slab]) ++slab;
      folds[static_cast<size_t>(k)][static_cast<size_t>(order[static_cast<size_t>(r)])] =
          static_cast<int>(slab);
    }
  }
  return folds;
}

std::vector<double> PolynomialTerm::BlockedRidgeCv(int degree, const Eigen::MatrixXd& u,
                                                   const Eigen::MatrixXd& a,
                                                   const Eigen::MatrixXd& b,
                                                   const std::vector<bool>& shrunk,
                                                   const std::vector<double>& grid,
                                                   int slabs_per_axis,
                                                   const Eigen::Vector3d& input_scale,
                                                   double linear_reach,
                                                   const Eigen::VectorXd* row_weight) {
  const Eigen::Index n = a.rows(), r = a.cols();
  const std::vector<std::array<int, 3>> exponents = PolynomialTermExponents(degree);
  std::vector<double> error(grid.size(), 0.0);
  const Eigen::MatrixXd normal = a.transpose() * a;
  const Eigen::MatrixXd rhs = a.transpose() * b;
  Eigen::VectorXd d(r);
  for (Eigen::Index j = 0; j < r; ++j) d[j] = shrunk[static_cast<size_t>(j)] ? 1.0 : 0.0;
  // A relative 1e-12 on the diagonal keeps lambda = 0 solvable where a fold leaves a direction
  // unsampled (its held-out error is then what such a fit does there).
  const double jitter = 1e-12 * normal.diagonal().maxCoeff();
  std::vector<double> monomials(static_cast<size_t>(r));
  for (const std::vector<int>& fold_of : BlockedFolds(u, slabs_per_axis)) {
    int folds = 0;
    for (int f : fold_of) folds = std::max(folds, f + 1);
    if (folds < 2) continue;
    for (int f = 0; f < folds; ++f) {
      std::vector<Eigen::Index> held, kept;
      for (Eigen::Index i = 0; i < n; ++i) {
        (fold_of[static_cast<size_t>(i)] == f ? held : kept).push_back(i);
      }
      if (held.empty() || kept.empty()) continue;
      Eigen::Vector3d lo = u.row(kept[0]).transpose(), hi = lo;
      for (Eigen::Index i : kept) {
        lo = lo.cwiseMin(u.row(i).transpose());
        hi = hi.cwiseMax(u.row(i).transpose());
      }
      const Eigen::Index h = static_cast<Eigen::Index>(held.size());
      Eigen::MatrixXd a_held(h, r), a_clamped(h, r), b_held(h, b.cols());
      for (Eigen::Index i = 0; i < h; ++i) {
        a_held.row(i) = a.row(held[static_cast<size_t>(i)]);
        b_held.row(i) = b.row(held[static_cast<size_t>(i)]);
        const Eigen::Vector3d ui = u.row(held[static_cast<size_t>(i)]).transpose();
        const Eigen::Vector3d uc = ui.cwiseMax(lo).cwiseMin(hi);
        EvaluateMonomials(degree, uc.data(), monomials.data());
        for (Eigen::Index j = 0; j < r; ++j) a_clamped(i, j) = monomials[static_cast<size_t>(j)];
        // The linear policy: plus the monomials' derivatives at uc times the step out, the step
        // capped at linear_reach metres (exact derivatives; the runtime's one-sided differences
        // agree to O(h^2)).
        const Eigen::Vector3d step = ui - uc;
        const double metres = step.cwiseProduct(input_scale).norm();
        if (linear_reach > 0.0 && metres > 0.0) {
          const double scale = std::min(1.0, linear_reach / metres);
          for (Eigen::Index j = 0; j < r; ++j) {
            const std::array<int, 3>& e = exponents[static_cast<size_t>(j)];
            double derivative = 0.0;
            for (int k = 0; k < 3; ++k) {
              if (e[k] == 0 || step[k] == 0.0) continue;
              double d = e[k];
              for (int m = 0; m < 3; ++m) d *= std::pow(uc[m], e[m] - (m == k ? 1 : 0));
              derivative += d * step[k];
            }
            a_clamped(i, j) += scale * derivative;
          }
        }
        if (row_weight != nullptr) a_clamped.row(i) *= (*row_weight)[held[static_cast<size_t>(i)]];
      }
      const Eigen::MatrixXd normal_kept = normal - a_held.transpose() * a_held;
      const Eigen::MatrixXd rhs_kept = rhs - a_held.transpose() * b_held;
      for (size_t g = 0; g < grid.size(); ++g) {
        Eigen::MatrixXd m = normal_kept;
        m.diagonal() += (grid[g] * grid[g]) * d + Eigen::VectorXd::Constant(r, jitter);
        const Eigen::LDLT<Eigen::MatrixXd> ldlt(m);
        const Eigen::MatrixXd c = ldlt.solve(rhs_kept);
        const double e = (b_held - a_clamped * c).squaredNorm();
        error[g] += (ldlt.info() == Eigen::Success && std::isfinite(e))
                        ? e
                        : std::numeric_limits<double>::infinity();
      }
    }
  }
  return error;
}

bool PolynomialTerm::InitializeLinear(const std::vector<FitStation>& inputs,
                                      const Eigen::Vector2d& noise_sigmas) {
  sigmas_ = noise_sigmas;
  // No subspace from an earlier call survives (FindDeterminedSubspace below sets a new one).
  undetermined_ = {};
  for (int index : {position_block_, orientation_block_}) {
    if (index < 0) continue;
    auto& block = blocks_[static_cast<size_t>(index)];
    block.make_manifold = nullptr;
    block.ambient_from_tangent.resize(0, 0);
    block.tangent_names.clear();
    block.identifiability_note.clear();
  }
  const int n = static_cast<int>(inputs.size());
  if (n == 0) return false;
  Eigen::MatrixXd a(n, num_terms_), u(n, 3);
  Eigen::MatrixXd b_position(n, 3), b_orientation(n, 3);
  std::vector<double> monomials(static_cast<size_t>(num_terms_));
  for (int i = 0; i < n; ++i) {
    const FitStation& s = inputs[static_cast<size_t>(i)];
    double ui[3];
    NormalizePolynomialInput(s.reported.translation.data(), options_.input_offset,
                             options_.input_scale, ui);
    EvaluateMonomials(options_.degree, ui, monomials.data());
    for (int k = 0; k < 3; ++k) u(i, k) = ui[k];
    for (int j = 0; j < num_terms_; ++j) a(i, j) = monomials[static_cast<size_t>(j)];
    const PoseError e = ComputePoseError(s.reported, s.reference);
    b_position.row(i) = e.position.transpose();
    b_orientation.row(i) = e.orientation.transpose();
  }
  if (options_.ridge > 0.0 || options_.ridge_auto) {
    // Ridge on the coefficients of degree >= 2; ridge: auto picks the weight by leave-one-out.
    const auto exponents = PolynomialTermExponents(options_.degree);
    std::vector<bool> shrunk;
    for (const auto& e : exponents) shrunk.push_back(e[0] + e[1] + e[2] >= 2);
    const RidgeSolver solver(a, shrunk);
    auto fit = [&](int block_index, const Eigen::MatrixXd& b, int part) {
      if (block_index < 0 || blocks_[static_cast<size_t>(block_index)].fixed) return;
      double lambda = options_.ridge;
      Eigen::VectorXd loo;
      if (adopted_ridge_) {
        lambda = (*adopted_ridge_)[part];
      } else if (options_.ridge_auto &&
          options_.ridge_selection == PolynomialTermOptions::RidgeSelection::kBlocked) {
        // The weight with the smallest blocked cross-validation error.
        const std::vector<double> grid = RidgeGrid();
        // Held-out stations predicted with the box value held (linear_reach 0), although the
        // runtime's default now continues to first order: predicting as the runtime does picks
        // weaker weights on the paper preset (seed 2: 0.1 instead of 0.32 for position), and the
        // joint fit then trades the physical terms for polynomial coefficients (12.9x the floor
        // instead of 3.2x; seed 3: 5.2x instead of 2.9x; docs/model-file.md). The weight is chosen on what the physical group
        // alone leaves, which is the deeper problem.
        const std::vector<double> cv = BlockedRidgeCv(options_.degree, u, a, b, shrunk, grid);
        lambda = grid[static_cast<size_t>(std::min_element(cv.begin(), cv.end()) - cv.begin())];
      } else if (options_.ridge_auto) {
        // One-standard-error rule over the grid: mean and standard error of the per-station
        // leave-one-out errors; the largest weight within one SE of the best.
        std::vector<double> grid = RidgeGrid(), mean, se;
        for (double l : grid) {
          if (l == 0.0 && n <= num_terms_) {
            // Unshrunk with no more stations than terms, every station fits itself (leverage 1):
            // its leave-one-out error is undefined, and the hat matrix's formula read it as ~0.
            mean.push_back(std::numeric_limits<double>::infinity());
            se.push_back(0.0);
            continue;
          }
          solver.Solve(b, l, &loo);
          const double m = loo.mean();
          mean.push_back(m);
          se.push_back(std::sqrt((loo.array() - m).square().sum() / std::max(1, n - 1) / n));
        }
        size_t best = 0;
        for (size_t k = 1; k < grid.size(); ++k) {
          if (mean[k] < mean[best]) best = k;
        }
        lambda = grid[best];
        for (size_t k = best + 1; k < grid.size(); ++k) {
          if (mean[k] <= mean[best] + se[best]) lambda = grid[k];
        }
      }
      StoreCoefficients(solver.Solve(b, lambda, &loo), &blocks_[static_cast<size_t>(block_index)]);
      ridge_used_[part] = lambda;
      loo_rms_[part] = std::sqrt(loo.mean() / 3.0);
    };
    fit(position_block_, b_position, 0);
    fit(orientation_block_, b_orientation, 1);
    inverse_normal_diagonal_.resize(0);  // no linear covariance: the engine's covariance serves
    return true;
  }
  // Without a ridge, fewer stations than terms leave eq. 8 under-determined (the paper: N > R).
  // With one, the shrunk coefficients are determined by the prior, so the check comes after it.
  if (n <= num_terms_) {
    // The fit still runs (a cross-validation fold may hit this), but its report says it first.
    const std::string note =
        std::to_string(n) + " stations for " + std::to_string(num_terms_) + " terms (degree " +
        std::to_string(options_.degree) +
        "): the polynomial passes through every station, noise included, and is not determined "
        "between them (eq. 8 needs more stations than terms); use ridge: auto or a lower degree "
        "(docs/model-file.md)";
    for (int index : {position_block_, orientation_block_}) {
      if (index >= 0) blocks_[static_cast<size_t>(index)].identifiability_note = note;
    }
    if (n < num_terms_) return false;
  }
  // The directions the stations determine (FindDeterminedSubspace): when some are not, the
  // coefficients are the least-squares solution within the fitted subspace, and the fit moves
  // them only within it. Bounds would act after the manifold's step and leave the subspace: a
  // bound on either block makes the term fit every direction of both.
  bool bounded = false;
  for (int index : {position_block_, orientation_block_}) {
    if (index >= 0) bounded = bounded || !blocks_[static_cast<size_t>(index)].lower.empty() ||
                              !blocks_[static_cast<size_t>(index)].upper.empty();
  }
  if (options_.max_amplification > 0 && !bounded) {
    DeterminedSubspace subspace = FindDeterminedSubspace(a, options_.degree,
                                                         options_.max_amplification, &u);
    if (!subspace.dropped_amplifications.empty()) {
      undetermined_ = subspace;
      if (InitializeInSubspace(a, b_position, b_orientation)) return true;
      undetermined_ = {};
      return false;
    }
  }
  // Column-pivoting QR on the normalised basis: the paper's eq. 9 without forming A^T A (squaring
  // the condition number).
  const Eigen::ColPivHouseholderQR<Eigen::MatrixXd> qr(a);
  if (qr.rank() < num_terms_) return false;
  auto store = [&](int block_index, const Eigen::MatrixXd& b) {
    if (block_index < 0 || blocks_[static_cast<size_t>(block_index)].fixed) return;
    StoreCoefficients(qr.solve(b), &blocks_[static_cast<size_t>(block_index)]);
  };
  store(position_block_, b_position);
  store(orientation_block_, b_orientation);
  // diag((A^T A)^-1) = diag(P R^-1 R^-T P^T): row norms of R^-1, permuted.
  const Eigen::MatrixXd r = qr.matrixR().topLeftCorner(num_terms_, num_terms_).triangularView<Eigen::Upper>();
  const Eigen::MatrixXd r_inverse =
      r.triangularView<Eigen::Upper>().solve(Eigen::MatrixXd::Identity(num_terms_, num_terms_));
  const Eigen::VectorXd d = r_inverse.rowwise().squaredNorm();
  inverse_normal_diagonal_ = qr.colsPermutation() * d;
  return true;
}

bool PolynomialTerm::InitializeInSubspace(const Eigen::MatrixXd& a,
                                          const Eigen::MatrixXd& b_position,
                                          const Eigen::MatrixXd& b_orientation) {
  const Eigen::MatrixXd& u = undetermined_.basis;  // num_terms x k
  const auto k = u.cols();
  const Eigen::MatrixXd a_sub = a * u;
  const Eigen::ColPivHouseholderQR<Eigen::MatrixXd> qr(a_sub);
  if (k == 0 || qr.rank() < k) return false;
  // B = U (x) I_3 in the block's term-major layout.
  Eigen::MatrixXd b = Eigen::MatrixXd::Zero(3 * num_terms_, 3 * k);
  for (int j = 0; j < num_terms_; ++j) {
    for (Eigen::Index i = 0; i < k; ++i) {
      for (int c = 0; c < 3; ++c) b(3 * j + c, 3 * i + c) = u(j, i);
    }
  }
  const auto make = [b]() -> ceres::Manifold* { return new CoefficientSubspaceManifold(b); };
  std::ostringstream note;
  const double largest = undetermined_.dropped_amplifications.front();
  note << undetermined_.dropped_amplifications.size() << " of its " << num_terms_
       << " directions not determined by the stations (over their box it would be "
       << (std::isfinite(largest) && largest < 1e12
               ? std::to_string(static_cast<long>(std::lround(largest))) + " times"
               : std::string("unboundedly"))
       << " as large as at them; e.g. degree " << options_.degree << " on a grid of fewer than "
       << options_.degree + 1
       << " layers): taken out of its highest-degree coefficients, the rest fitted "
          "(docs/model-file.md, \"Undetermined directions\")";
  auto store = [&](int block_index, const Eigen::MatrixXd& rhs) {
    if (block_index < 0) return;
    auto& block = blocks_[static_cast<size_t>(block_index)];
    if (block.fixed) return;
    const Eigen::MatrixXd c = u * qr.solve(rhs);  // num_terms x 3
    for (int j = 0; j < num_terms_; ++j) {
      for (int m = 0; m < 3; ++m) block.values[static_cast<size_t>(j * 3 + m)] = c(j, m);
    }
    block.make_manifold = make;
    block.ambient_from_tangent = b;
    block.tangent_names.clear();
    for (Eigen::Index i = 0; i < k; ++i) {
      for (int m = 0; m < 3; ++m) {
        block.tangent_names.push_back("determined_direction[" + std::to_string(i) + "]." +
                                      "xyz"[m]);
      }
    }
    block.tangent_unit = block.unit;
    // After the note of a fit with no more stations than terms, when there is one.
    block.identifiability_note += (block.identifiability_note.empty() ? "" : "; ") + note.str();
  };
  store(position_block_, b_position);
  store(orientation_block_, b_orientation);
  // diag((A^T A)^-1) restricted to the subspace: diag(U (A_s^T A_s)^-1 U^T), the squared row
  // norms of U P R^-1.
  const Eigen::MatrixXd r = qr.matrixR().topLeftCorner(k, k).triangularView<Eigen::Upper>();
  const Eigen::MatrixXd r_inverse =
      r.triangularView<Eigen::Upper>().solve(Eigen::MatrixXd::Identity(k, k));
  const Eigen::MatrixXd w = u * (qr.colsPermutation() * r_inverse);
  inverse_normal_diagonal_ = w.rowwise().squaredNorm();
  return true;
}

bool PolynomialTerm::LinearCovariance(const Eigen::Vector2d& noise_sigmas) {
  if (inverse_normal_diagonal_.size() != num_terms_) return false;
  auto fill = [&](int block_index, double sigma) {
    if (block_index < 0) return;
    auto& block = blocks_[static_cast<size_t>(block_index)];
    block.stddev.assign(block.values.size(), std::numeric_limits<double>::quiet_NaN());
    if (block.fixed) return;
    for (int j = 0; j < num_terms_; ++j) {
      for (int k = 0; k < 3; ++k) {
        block.stddev[static_cast<size_t>(j * 3 + k)] = sigma * std::sqrt(inverse_normal_diagonal_[j]);
      }
    }
  };
  fill(position_block_, noise_sigmas[0]);
  fill(orientation_block_, noise_sigmas[1]);
  return true;
}

bool PolynomialTerm::Evaluate(const StationBinding& binding, const double* const* block_values,
                              const AmbientPose& input, bool jacobians,
                              TermEvaluation* result) const {
  if (!jacobians) return Apply<double>(binding, block_values, input.data(), result->output.data());
  using J3 = ceres::Jet<double, 3>;
  using J7 = ceres::Jet<double, 7>;
  J3 p[3], u[3];
  for (int k = 0; k < 3; ++k) p[k] = J3(input[k], k);
  NormalizePolynomialInput(p, options_.input_offset, options_.input_scale, u);
  std::vector<J3> monomials(static_cast<size_t>(num_terms_));
  EvaluateMonomials(options_.degree, u, monomials.data());
  J3 e_p[3], e_o[3];
  auto sum = [&](int block, J3* out) {
    for (int k = 0; k < 3; ++k) out[k] = J3(0.0);
    if (block < 0) return;
    const double* c = block_values[block];
    for (int j = 0; j < num_terms_; ++j) {
      for (int k = 0; k < 3; ++k) out[k] += monomials[static_cast<size_t>(j)] * c[j * 3 + k];
    }
  };
  sum(position_block_, e_p);
  sum(orientation_block_, e_o);
  // q_out = Q(e_o) * q_in with derivatives over (e_o, q_in).
  Vector3<J7> e_o7;
  for (int k = 0; k < 3; ++k) e_o7[k] = J7(e_o[k].a, k);
  J7 q_in[4];
  for (int k = 0; k < 4; ++k) q_in[k] = J7(input[3 + k], 3 + k);
  const Eigen::Quaternion<J7> q_out =
      QuaternionFromVectorPart<J7>(e_o7) * QuaternionFromXyzwArray(q_in);
  J7 q_out_xyzw[4];
  QuaternionToXyzwArray(q_out, q_out_xyzw);
  Eigen::Matrix<double, 4, 3> dq_deo;
  auto& d_in = result->d_output_d_input;
  d_in.setZero();
  for (int k = 0; k < 3; ++k) {
    result->output[k] = input[k] + e_p[k].a;
    d_in.block<1, 3>(k, 0) = e_p[k].v.transpose();
    d_in(k, k) += 1.0;
  }
  Eigen::Matrix<double, 3, 3> deo_dp;
  for (int k = 0; k < 3; ++k) deo_dp.row(k) = e_o[k].v.transpose();
  for (int r = 0; r < 4; ++r) {
    result->output[3 + r] = q_out_xyzw[r].a;
    dq_deo.row(r) = q_out_xyzw[r].v.head<3>().transpose();
    d_in.block<1, 4>(3 + r, 3) = q_out_xyzw[r].v.tail<4>().transpose();
  }
  d_in.block<4, 3>(3, 0) = dq_deo * deo_dp;
  result->d_output_d_blocks.resize(binding.blocks.size());
  for (size_t b = 0; b < binding.blocks.size(); ++b) {
    const int index = binding.blocks[b];
    auto& d = result->d_output_d_blocks[b];
    d.setZero(kAmbientPoseSize, num_terms_ * 3);
    for (int j = 0; j < num_terms_; ++j) {
      const double m = monomials[static_cast<size_t>(j)].a;
      for (int k = 0; k < 3; ++k) {
        if (index == position_block_) {
          d(k, j * 3 + k) = m;
        } else {
          d.block<4, 1>(3, j * 3 + k) = m * dq_deo.col(k);
        }
      }
    }
  }
  return true;
}

namespace {
// ridge * c / sigma on the coefficients of degree >= 2 of one part (`mask` 1 where shrunk).
struct PolynomialRidge {
  Eigen::VectorXd weight;  // per coefficient: ridge / sigma, 0 where not shrunk
  bool operator()(double const* const* c, double* r, double** jacobians) const {
    const Eigen::Index m = weight.size();
    for (Eigen::Index i = 0; i < m; ++i) r[i] = weight[i] * c[0][i];
    if (jacobians != nullptr && jacobians[0] != nullptr) {
      Eigen::Map<Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>> j(
          jacobians[0], m, m);
      j.setZero();
      j.diagonal() = weight;
    }
    return true;
  }
};
class PolynomialRidgeCost : public ceres::CostFunction {
 public:
  explicit PolynomialRidgeCost(Eigen::VectorXd weight) : ridge_{std::move(weight)} {
    set_num_residuals(static_cast<int>(ridge_.weight.size()));
    mutable_parameter_block_sizes()->push_back(static_cast<int>(ridge_.weight.size()));
  }
  bool Evaluate(double const* const* p, double* r, double** j) const override { return ridge_(p, r, j); }

 private:
  PolynomialRidge ridge_;
};
}  // namespace

int PolynomialTerm::AddExtraResiduals(ceres::Problem* problem,
                                      const std::vector<FitStation>& /*inputs*/) {
  int added = 0;
  const auto exponents = PolynomialTermExponents(options_.degree);
  for (int part = 0; part < 2; ++part) {
    const int index = part == 0 ? position_block_ : orientation_block_;
    const double lambda = options_.ridge_auto ? ridge_used_[part] : options_.ridge;
    if (index < 0 || lambda <= 0.0) continue;
    auto& block = blocks_[static_cast<size_t>(index)];
    if (block.fixed) continue;
    Eigen::VectorXd weight = Eigen::VectorXd::Zero(num_terms_ * 3);
    for (int j = 0; j < num_terms_; ++j) {
      const auto& e = exponents[static_cast<size_t>(j)];
      if (e[0] + e[1] + e[2] < 2) continue;
      for (int k = 0; k < 3; ++k) weight[j * 3 + k] = lambda / sigmas_[part];
    }
    problem->AddResidualBlock(new PolynomialRidgeCost(weight), nullptr, block.values.data());
    ++added;
  }
  return added;
}

std::vector<double> PolynomialTerm::PositionCoefficients() const {
  return position_block_ >= 0 ? blocks_[static_cast<size_t>(position_block_)].values
                              : std::vector<double>(static_cast<size_t>(num_terms_) * 3, 0.0);
}

std::vector<double> PolynomialTerm::OrientationCoefficients() const {
  return orientation_block_ >= 0 ? blocks_[static_cast<size_t>(orientation_block_)].values
                                 : std::vector<double>(static_cast<size_t>(num_terms_) * 3, 0.0);
}

std::unique_ptr<Correction> PolynomialTerm::ToCorrection() const {
  return PolynomialCorrection::FromPositionAndOrientation(
      options_.degree, options_.input_offset, options_.input_scale, PositionCoefficients(),
      OrientationCoefficients());
}

nlohmann::json PolynomialTerm::Describe() const {
  return {{"degree", options_.degree},
          {"num_terms", num_terms_},
          {"position", options_.position},
          {"orientation", options_.orientation},
          {"ridge", options_.ridge_auto ? nlohmann::json("auto") : nlohmann::json(options_.ridge)},
          {"ridge_used", {ridge_used_[0], ridge_used_[1]}},
          {"ridge_cv", !options_.ridge_auto ? nlohmann::json()
                       : options_.ridge_selection ==
                               PolynomialTermOptions::RidgeSelection::kBlocked
                           ? nlohmann::json("blocked")
                           : nlohmann::json("leave_one_out")},
          {"max_amplification", options_.max_amplification},
          {"undetermined_directions", undetermined_.dropped_amplifications.size()},
          {"undetermined_isolated_stations", undetermined_.isolated_stations},
          {"undetermined_amplification", [this] {
             nlohmann::json a = nlohmann::json::array();  // null: unbounded (no station sees it)
             for (double v : undetermined_.dropped_amplifications) {
               a.push_back(std::isfinite(v) ? nlohmann::json(v) : nlohmann::json());
             }
             return a;
           }()},
          {"input_offset", {options_.input_offset[0], options_.input_offset[1], options_.input_offset[2]}},
          {"input_scale", {options_.input_scale[0], options_.input_scale[1], options_.input_scale[2]}}};
}

}  // namespace trackcal::fit
