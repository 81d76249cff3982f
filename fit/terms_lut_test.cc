#include "fit/terms_lut.h"

#include <gtest/gtest.h>

#include <random>

#include "fit/fit_engine.h"

namespace trackcal::fit {
namespace {

std::vector<FitStation> RandomStations(int n, std::mt19937* rng) {
  std::uniform_real_distribution<double> pos(-0.5, 0.5);
  std::normal_distribution<double> normal;
  std::vector<FitStation> out;
  for (int i = 0; i < n; ++i) {
    FitStation s;
    s.station = i;
    s.reported.translation = Eigen::Vector3d(pos(*rng), pos(*rng), 0.5 * pos(*rng));
    s.reported.rotation =
        Eigen::Quaterniond(normal(*rng), normal(*rng), normal(*rng), normal(*rng)).normalized();
    out.push_back(s);
  }
  return out;
}

TEST(LutTerm, Nominal_RecoversNoiseFreeNodeValues) {
  std::mt19937 rng(21);
  auto stations = RandomStations(1500, &rng);
  LutTermOptions options;
  options.nodes = std::array<int, 3>{4, 4, 3};
  options.smoothness = 0.0;
  options.ridge = 0.0;
  LutTerm truth(options);
  truth.Prepare(stations);
  std::normal_distribution<double> normal;
  for (auto& block : truth.blocks()) {
    for (int i = 0; i < 6; ++i) block.values[static_cast<size_t>(i)] = (i < 3 ? 0.005 : 0.01) * normal(rng);
  }
  const auto correction = truth.ToCorrection();
  for (auto& s : stations) s.reference = correction->Apply(s.reported).pose;

  ModelSpec spec;
  spec.terms.push_back(std::make_unique<LutTerm>(options));
  const FitResult result = FitModel(stations, &spec);
  EXPECT_TRUE(result.converged) << result.solver_message;
  ASSERT_EQ(spec.terms[0]->blocks().size(), truth.blocks().size());
  // Noise-free, same model form and ~40 stations per cell: node values to 1e-6 relative.
  for (size_t b = 0; b < truth.blocks().size(); ++b) {
    for (int i = 0; i < 6; ++i) {
      const double t = truth.blocks()[b].values[static_cast<size_t>(i)];
      EXPECT_NEAR(spec.terms[0]->blocks()[b].values[static_cast<size_t>(i)], t, 1e-6 * 0.02)
          << truth.blocks()[b].coordinate_names[static_cast<size_t>(i)];
    }
  }
}

TEST(LutTerm, SmoothnessFillsEmptyCellsAndGridFollowsCellSize) {
  std::mt19937 rng(4);
  auto stations = RandomStations(400, &rng);
  // A smooth (linear) distortion: second differences vanish, so smoothing does not bias it.
  for (auto& s : stations) {
    s.reference = s.reported;
    s.reference.translation += 0.01 * s.reported.translation;
  }
  ModelSpec spec = ParseModelYaml("terms: [{type: lut, cell_size_mm: 300, smoothness: 10, ridge: 0}]", "m");
  const FitResult result = FitModel(stations, &spec);
  const auto& lut = dynamic_cast<const LutTerm&>(*spec.terms[0]);
  EXPECT_EQ(lut.grid().size(0), 5);  // ~1 m / 0.3 m -> 4 cells
  EXPECT_EQ(lut.grid().size(2), 3);  // ~0.5 m / 0.3 m -> 2 cells
  double worst = 0.0;
  for (const auto& s : stations) {
    worst = std::max(worst, PositionErrorNorm(result.chain.Apply(s.reported).pose, s.reference));
  }
  EXPECT_LT(worst, 1e-7);  // linear field: reproduced to solver tolerance
}

TEST(LutTerm, ModelFileErrors) {
  EXPECT_THROW(ParseModelYaml("terms: [{type: lut, cell_size_mm: 0}]", "m"), std::invalid_argument);
  EXPECT_THROW(ParseModelYaml("terms: [{type: lut, nodes: [2, 2]}]", "m"), std::invalid_argument);
  EXPECT_THROW(ParseModelYaml("terms: [{type: lut, smoothness: -1}]", "m"), std::invalid_argument);
}

}  // namespace
}  // namespace trackcal::fit
