#include "fit/chain_builder.h"

#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <iomanip>
#include <limits>
#include <optional>
#include <sstream>
#include <stdexcept>

#include "core/polynomial.h"
#include "fit/model_file.h"
#include "fit/terms_physical.h"
#include "fit/terms_polynomial.h"

namespace trackcal::fit {
namespace {

using Clock = std::chrono::steady_clock;

double SecondsSince(Clock::time_point start) {
  return std::chrono::duration<double>(Clock::now() - start).count();
}

std::string Number(double v) {
  std::ostringstream out;
  out << std::setprecision(17) << v;
  return out.str();
}

std::string Vector(const double* v) {
  return "[" + Number(v[0]) + ", " + Number(v[1]) + ", " + Number(v[2]) + "]";
}

// The group's sources (dipoles and planes) as model-file term items with their current values as
// start values (free: refined again with the next source).
std::string SourcesYaml(const PhysicalGroupTerm& group) {
  std::ostringstream out;
  for (const auto& e : group.effects()) {
    const auto& b = group.blocks();
    if (e.kind == PhysicalEffect::kDipole) {
      const auto& location = b[static_cast<size_t>(e.first_block)].values;
      const auto& strength = b[static_cast<size_t>(e.first_block + 1)].values;
      out << "  - type: dipole\n    location_in_transmitter: " << Vector(location.data())
          << "\n    polarisability_m3: " << Number(strength[0]) << "\n";
    } else if (e.kind == PhysicalEffect::kPlane) {
      const double distance = b[static_cast<size_t>(e.first_block)].values[0];
      const auto& n = b[static_cast<size_t>(e.first_block + 1)].values;
      const Eigen::Vector3d normal = Eigen::Vector3d(n[0], n[1], n[2]).normalized();
      const Eigen::Vector3d point = distance * normal;
      out << "  - type: plane\n    point_in_transmitter: " << Vector(point.data())
          << "\n    normal_in_transmitter: " << Vector(normal.data())
          << "\n    attenuation: " << Number(b[static_cast<size_t>(e.first_block + 2)].values[0])
          << "\n";
    } else {
      throw std::logic_error("chain builder: unexpected physical effect");
    }
  }
  return out.str();
}

// The new source's term items.
std::string SearchedYaml(const std::string& type) {
  if (type == "dipole_pair") return "  - type: dipole\n  - type: dipole\n";
  if (type == "dipole_plane") return "  - type: dipole\n  - type: plane\n";
  return "  - type: " + type + "\n";
}

std::string PolynomialYaml(int degree, const std::string& ridge, const std::string& parts) {
  std::string out = "  - type: polynomial\n    degree: " + std::to_string(degree) +
                    "\n    ridge: " + ridge + "\n";
  if (parts == "position") out += "    orientation: false\n";
  if (parts == "orientation") out += "    position: false\n";
  return out;
}

// The physical group of `sources_yaml` initialised as FitModel does before its joint solve (the
// searches of sources without start values, then the group's refinement), with a degree
// `search_degree` polynomial after it. Null when the text has no physical term.
struct InitialisedGroup {
  ModelSpec spec;
  PhysicalGroupTerm* group = nullptr;
};
InitialisedGroup InitialiseGroup(const std::vector<FitStation>& stations,
                                 const ChainBuilderOptions& options,
                                 const std::string& sources_yaml) {
  InitialisedGroup out;
  out.spec = ParseModelYaml(options.settings_yaml + "\nterms:\n" + sources_yaml +
                                PolynomialYaml(options.search_degree, "auto", "both"),
                            "chain builder");
  if (out.spec.terms.size() < 2) return out;
  out.group = dynamic_cast<PhysicalGroupTerm*>(out.spec.terms[0].get());
  if (out.group == nullptr) throw std::logic_error("chain builder: the first term is not physical");
  std::vector<const ModelTerm*> later;
  for (size_t j = 1; j < out.spec.terms.size(); ++j) later.push_back(out.spec.terms[j].get());
  out.group->SetFollowingTerms(later);
  out.group->Prepare(stations);
  if (!out.spec.block_settings.empty()) ApplyBlockSettings(out.spec.block_settings[0], out.group);
  const Eigen::Vector2d sigmas(out.spec.position_sigma, out.spec.orientation_sigma);
  out.group->InitializeLinear(stations, sigmas);
  return out;
}

}  // namespace

void ChainBuilderOptions::Check() const {
  if (source_types.empty() && max_sources > 0) {
    throw std::invalid_argument("chain builder: source_types is empty");
  }
  for (size_t i = 0; i < source_types.size(); ++i) {
    const std::string& t = source_types[i];
    if (t != "dipole" && t != "plane" && t != "dipole_pair" && t != "dipole_plane") {
      throw std::invalid_argument("chain builder: source_types: expected dipole, plane, "
                                  "dipole_pair or dipole_plane, got '" + t + "'");
    }
    // A type listed twice is tried twice per round with the same result, and both steps would be
    // marked kept.
    if (std::find(source_types.begin(), source_types.begin() + static_cast<std::ptrdiff_t>(i), t) !=
        source_types.begin() + static_cast<std::ptrdiff_t>(i)) {
      throw std::invalid_argument("chain builder: source_types: '" + t + "' given twice");
    }
  }
  if (max_sources < 0) throw std::invalid_argument("chain builder: max_sources must be >= 0");
  if (!(min_relative_gain >= 0.0 && min_relative_gain < 1.0)) {
    throw std::invalid_argument("chain builder: min_relative_gain must be in [0, 1)");
  }
  if (min_degree < 0 || max_degree < min_degree || max_degree > kMaxPolynomialDegree) {
    throw std::invalid_argument("chain builder: need 0 <= min_degree <= max_degree <= " +
                                std::to_string(kMaxPolynomialDegree));
  }
  if (search_degree < 0 || search_degree > kMaxPolynomialDegree) {
    throw std::invalid_argument("chain builder: search_degree out of range");
  }
  if (!(cv_linear_reach >= 0.0)) {
    throw std::invalid_argument("chain builder: cv_linear_reach must be >= 0");
  }
}

ExplicitCv ExplicitTermCv(const Correction* group, const std::vector<FitStation>& stations,
                          const ModelSpec& noise, int min_degree, int max_degree,
                          double linear_reach) {
  const int n = static_cast<int>(stations.size());
  Eigen::MatrixXd b_position(n, 3), b_orientation(n, 3), p(n, 3);
  Eigen::VectorXd w_position(n), w_orientation(n);
  for (int i = 0; i < n; ++i) {
    const FitStation& s = stations[static_cast<size_t>(i)];
    const Rigid3d input = group != nullptr ? group->Apply(s.reported).pose : s.reported;
    const PoseError e = ComputePoseError(input, s.reference);
    // The fit's whitening relative to the model's sigmas (range-dependent noise).
    const Eigen::Vector2d sigma = noise.StationSigmas(s.reported);
    w_position[i] = noise.position_sigma / sigma[0];
    w_orientation[i] = noise.orientation_sigma / sigma[1];
    b_position.row(i) = w_position[i] * e.position.transpose();
    b_orientation.row(i) = w_orientation[i] * e.orientation.transpose();
    p.row(i) = input.translation.transpose();
  }
  // The polynomial's normalisation: the inputs' box onto [-1, 1] (PolynomialTerm::Prepare).
  const Eigen::RowVector3d lo = p.colwise().minCoeff(), hi = p.colwise().maxCoeff();
  const Eigen::RowVector3d half = (0.5 * (hi - lo)).cwiseMax(1e-9);
  const Eigen::MatrixXd u = (p.rowwise() - 0.5 * (lo + hi)).array().rowwise() / half.array();
  const std::vector<double> grid = PolynomialTerm::RidgeGrid();
  ExplicitCv out;
  out.best = std::numeric_limits<double>::infinity();
  for (int degree = min_degree; degree <= max_degree; ++degree) {
    const int r = NumPolynomialTerms(degree);
    if (r >= n) break;
    Eigen::MatrixXd a(n, r);
    std::vector<double> monomials(static_cast<size_t>(r));
    for (int i = 0; i < n; ++i) {
      const Eigen::Vector3d ui = u.row(i).transpose();
      EvaluateMonomials(degree, ui.data(), monomials.data());
      for (int j = 0; j < r; ++j) a(i, j) = monomials[static_cast<size_t>(j)];
    }
    std::vector<bool> shrunk;
    for (const auto& e : PolynomialTermExponents(degree)) shrunk.push_back(e[0] + e[1] + e[2] >= 2);
    const Eigen::Vector3d scale = half.transpose();
    const Eigen::MatrixXd a_position = w_position.asDiagonal() * a;
    const Eigen::MatrixXd a_orientation = w_orientation.asDiagonal() * a;
    // Rows whitened like the fit's normal equations for a `ridge: lambda` polynomial; held-out
    // stations predicted as the runtime's `linear` policy does (PolynomialTerm::BlockedRidgeCv).
    const int slabs = PolynomialTerm::kBlockedSlabsPerAxis;
    const std::vector<double> cv_p = PolynomialTerm::BlockedRidgeCv(
        degree, u, a_position, b_position, shrunk, grid, slabs, scale, linear_reach, &w_position);
    const std::vector<double> cv_o =
        PolynomialTerm::BlockedRidgeCv(degree, u, a_orientation, b_orientation, shrunk, grid, slabs,
                                       scale, linear_reach, &w_orientation);
    const size_t ip = static_cast<size_t>(std::min_element(cv_p.begin(), cv_p.end()) - cv_p.begin());
    const size_t io = static_cast<size_t>(std::min_element(cv_o.begin(), cv_o.end()) - cv_o.begin());
    // Whitened as the fit's station residual: position / sigma_p, the vector part of q_e / sigma_o.
    const double score = (cv_p[ip] / (noise.position_sigma * noise.position_sigma) +
                          cv_o[io] / (noise.orientation_sigma * noise.orientation_sigma)) /
                         static_cast<double>(n);
    out.score.push_back(score);
    if (score < out.best) {
      out.best = score;
      out.degree = degree;
      out.ridge = Eigen::Vector2d(grid[ip], grid[io]);
    }
  }
  return out;
}

BuiltChain BuildChain(const std::vector<FitStation>& stations, const ChainBuilderOptions& options,
                      const FitOptions& fit_options) {
  options.Check();
  // The explicit term's cross-validation skips the degrees with as many coefficients as stations
  // (ExplicitTermCv): with min_degree among them every score would be infinite, no source could be
  // kept, and the model would end with a degree-0 polynomial that was never scored.
  const int coefficients = NumPolynomialTerms(options.min_degree);
  if (static_cast<int>(stations.size()) <= coefficients) {
    throw std::invalid_argument(
        "chain builder: " + std::to_string(stations.size()) +
        " stations are too few to cross-validate the explicit term: a degree-" +
        std::to_string(options.min_degree) + " polynomial (min_degree) has " +
        std::to_string(coefficients) + " coefficients per coordinate, so at least " +
        std::to_string(coefficients + 1) + " stations are needed");
  }
  const auto start = Clock::now();
  // The settings alone, for the sigmas.
  const ModelSpec settings = ParseModelYaml(
      options.settings_yaml + "\nterms:\n" + PolynomialYaml(0, "0", "both"), "chain builder");
  BuiltChain out;

  // The start: no source.
  std::string sources;
  ExplicitCv current = ExplicitTermCv(nullptr, stations, settings, options.min_degree,
                                      options.max_degree, options.cv_linear_reach);
  out.steps.push_back({0, "", current.best, current.degree, true, "", SecondsSince(start)});
  int count = 0;
  for (int round = 1; count < options.max_sources; ++round) {
    struct Tried {
      std::string type, sources;
      ExplicitCv cv;
    };
    std::optional<Tried> best;
    for (const std::string& type : options.source_types) {
      const int adds = type == "dipole_pair" || type == "dipole_plane" ? 2 : 1;
      if (count + adds > options.max_sources) continue;
      const auto t0 = Clock::now();
      ChainBuilderStep step{round, type, std::numeric_limits<double>::infinity(), 0, false, "", 0};
      try {
        InitialisedGroup g = InitialiseGroup(stations, options, sources + SearchedYaml(type));
        const auto correction = g.group->ToCorrection();
        const ExplicitCv cv = ExplicitTermCv(correction.get(), stations, settings,
                                             options.min_degree, options.max_degree,
                                             options.cv_linear_reach);
        step.score = cv.best;
        step.degree = cv.degree;
        step.sources = SourcesYaml(*g.group);
        if (std::isfinite(cv.best) && (!best || cv.best < best->cv.best)) {
          best = Tried{type, step.sources, cv};
        }
      } catch (const std::invalid_argument&) {
        // A candidate whose group leaves the model's domain is not kept (score infinite).
      }
      step.seconds = SecondsSince(t0);
      out.steps.push_back(step);
    }
    if (!best || best->cv.best > (1.0 - options.min_relative_gain) * current.best) break;
    for (auto it = out.steps.rbegin(); it != out.steps.rend() && it->round == round; ++it) {
      if (it->added == best->type) it->kept = true;
    }
    sources = best->sources;
    current = best->cv;
    count += best->type == "dipole_pair" || best->type == "dipole_plane" ? 2 : 1;
  }

  // The explicit term after the final group: the cross-validation's degree and weights.
  out.degree = current.degree;
  out.ridge = current.ridge;
  out.score = current.best;
  out.sources = sources;
  std::string group_yaml = sources;
  if (!options.refit_group && !sources.empty()) {
    // Held at the values found: every source block fixed.
    std::string held;
    std::istringstream in(sources);
    for (std::string line; std::getline(in, line);) {
      held += line + "\n";
      if (line.rfind("  - type: dipole", 0) == 0) {
        held += "    parameters: {location_in_transmitter: {fixed: true}, polarisability_m3: "
                "{fixed: true}}\n";
      } else if (line.rfind("  - type: plane", 0) == 0) {
        held += "    parameters: {distance_m: {fixed: true}, normal_in_transmitter: {fixed: "
                "true}, attenuation: {fixed: true}}\n";
      }
    }
    group_yaml = held;
  }
  out.model_text = options.settings_yaml + "\nterms:\n" + group_yaml +
                   PolynomialYaml(out.degree, Number(out.ridge[0]), "position") +
                   PolynomialYaml(out.degree, Number(out.ridge[1]), "orientation");
  ModelSpec spec = ParseModelYaml(out.model_text, "chain builder (final)");
  out.fit = FitModel(stations, &spec, fit_options);
  out.seconds = SecondsSince(start);
  return out;
}

}  // namespace trackcal::fit
