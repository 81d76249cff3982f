#include "fit/terms_lut.h"

#include <gmock/gmock.h>
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

// The linear initialisation: on noise-free stations of a LUT without regularisers it gives the
// node values (before, they started at zero and the joint solve found them).
TEST(LutTerm, InitializeLinearStartsAtTheLeastSquaresNodeValues) {
  std::mt19937 rng(22);
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
  // A hemisphere flip: metres off, left out of the start.
  stations[0].reference.translation = -stations[0].reported.translation;

  LutTerm lut(options);
  lut.Prepare(stations);
  ASSERT_TRUE(lut.InitializeLinear(stations, Eigen::Vector2d(1e-3, 3.5e-3)));
  for (size_t b = 0; b < truth.blocks().size(); ++b) {
    for (int i = 0; i < 6; ++i) {
      const double t = truth.blocks()[b].values[static_cast<size_t>(i)];
      // Noise-free: each station's target error (position, vector part of q_ref conj(q)) is the
      // interpolated error exactly, so the least squares recover the nodes up to rounding.
      EXPECT_NEAR(lut.blocks()[b].values[static_cast<size_t>(i)], t, 1e-9)
          << truth.blocks()[b].coordinate_names[static_cast<size_t>(i)];
    }
  }
  // A fixed node keeps the engine's zero start (the solve honours it; this one would not).
  LutTerm held(options);
  held.Prepare(stations);
  held.blocks()[0].fixed = true;
  EXPECT_FALSE(held.InitializeLinear(stations, Eigen::Vector2d(1e-3, 3.5e-3)));
  EXPECT_EQ(held.blocks()[1].values[0], 0.0);
  // So does a LUT with terms after it (their initialisation sees the error it leaves).
  LutTerm first(options);
  first.SetFollowingTerms({&truth});
  first.Prepare(stations);
  EXPECT_FALSE(first.InitializeLinear(stations, Eigen::Vector2d(1e-3, 3.5e-3)));
  EXPECT_EQ(first.blocks()[1].values[0], 0.0);
}

// Random node values: position errors of ~5 mm, error vector parts of ~0.05.
void FillRandomNodes(LutTerm* lut, std::mt19937* rng) {
  std::normal_distribution<double> normal;
  for (auto& block : lut->blocks()) {
    for (int i = 0; i < 6; ++i) {
      block.values[static_cast<size_t>(i)] = (i < 3 ? 0.005 : 0.05) * normal(*rng);
    }
  }
}

// The analytic Jacobians against the autodiff of Apply they replace, inside a cell and outside the
// grid (the cell at the edge, its boundary value held).
TEST(LutTerm, AnalyticJacobiansEqualAutoDiff) {
  std::mt19937 rng(23);
  auto stations = RandomStations(200, &rng);
  LutTermOptions options;
  options.nodes = std::array<int, 3>{5, 4, 3};
  LutTerm lut(options);
  lut.Prepare(stations);
  FillRandomNodes(&lut, &rng);
  std::vector<AmbientPose> inputs;
  for (int i = 0; i < 20; ++i) inputs.push_back(ToAmbient(stations[static_cast<size_t>(i)].reported));
  AmbientPose outside = inputs[0];
  outside[0] = 0.7;  // beyond the grid's x
  inputs.push_back(outside);
  for (const AmbientPose& input : inputs) {
    const StationBinding binding = lut.Bind(input);
    std::vector<const double*> values;
    for (int b : binding.blocks) values.push_back(lut.blocks()[static_cast<size_t>(b)].values.data());
    TermEvaluation analytic, autodiff;
    ASSERT_TRUE(lut.Evaluate(binding, values.data(), input, true, &analytic));
    ASSERT_TRUE(lut.EvaluateAutoDiff(binding, values.data(), input, true, &autodiff));
    // The same chain rule summed in another order: rounding, ~1e-16 of entries of order 1.
    EXPECT_LT((analytic.output - autodiff.output).cwiseAbs().maxCoeff(), 1e-14);
    EXPECT_LT((analytic.d_output_d_input - autodiff.d_output_d_input).cwiseAbs().maxCoeff(), 1e-12);
    ASSERT_EQ(analytic.d_output_d_blocks.size(), autodiff.d_output_d_blocks.size());
    for (size_t b = 0; b < analytic.d_output_d_blocks.size(); ++b) {
      EXPECT_LT((analytic.d_output_d_blocks[b] - autodiff.d_output_d_blocks[b]).cwiseAbs().maxCoeff(), 1e-14);
    }
    TermEvaluation plain;
    ASSERT_TRUE(lut.Evaluate(binding, values.data(), input, false, &plain));
    EXPECT_LT((plain.output - analytic.output).cwiseAbs().maxCoeff(), 1e-15);
  }
}

// The fit evaluates the term as the runtime's TrilinearLutCorrection does, also where a station's
// input lies outside the grid (the grid is built on the inputs at the start; a term before the LUT
// moves them while the fit runs, and a start's adopted grid need not cover them): the boundary
// value held, not the edge cell continued. Before, the fit extrapolated linearly while the served
// correction held: 1.5 to 4.6 mm apart (position) 0.1 m beyond a face here.
TEST(LutTerm, OutsideTheGridTheFitEvaluatesWhatTheRuntimeServes) {
  std::mt19937 rng(24);
  auto stations = RandomStations(200, &rng);
  LutTermOptions options;
  options.nodes = std::array<int, 3>{5, 4, 3};
  LutTerm lut(options);
  lut.Prepare(stations);
  FillRandomNodes(&lut, &rng);
  const auto correction = lut.ToCorrection();
  const LutGrid& grid = lut.grid();
  std::vector<AmbientPose> inputs;
  for (int i = 0; i < 6; ++i) {
    AmbientPose pose = ToAmbient(stations[static_cast<size_t>(i)].reported);
    const int k = i % 3;
    pose[k] = i < 3 ? grid.axis(k).back() + 0.1 : grid.axis(k).front() - 0.1;
    inputs.push_back(pose);
  }
  AmbientPose corner = inputs[0];  // outside on all three axes
  for (int k = 0; k < 3; ++k) corner[k] = grid.axis(k).back() + 0.05;
  inputs.push_back(corner);
  for (const AmbientPose& input : inputs) {
    const StationBinding binding = lut.Bind(input);
    std::vector<const double*> values;
    for (int b : binding.blocks)
      values.push_back(lut.blocks()[static_cast<size_t>(b)].values.data());
    TermEvaluation plain, analytic, autodiff;
    ASSERT_TRUE(lut.Evaluate(binding, values.data(), input, false, &plain));
    ASSERT_TRUE(lut.Evaluate(binding, values.data(), input, true, &analytic));
    ASSERT_TRUE(lut.EvaluateAutoDiff(binding, values.data(), input, true, &autodiff));
    const CorrectedPose served = correction->Apply(FromAmbient(input));
    EXPECT_TRUE(served.extrapolated);
    const AmbientPose expected = ToAmbient(served.pose);
    // The same interpolation in another order: rounding of values of order 1.
    EXPECT_LT((plain.output - expected).cwiseAbs().maxCoeff(), 1e-14) << input.transpose();
    EXPECT_LT((analytic.output - expected).cwiseAbs().maxCoeff(), 1e-14) << input.transpose();
    EXPECT_LT((autodiff.output - expected).cwiseAbs().maxCoeff(), 1e-14) << input.transpose();
    // The held value does not move with the input along an axis outside the grid.
    EXPECT_LT((analytic.d_output_d_input - autodiff.d_output_d_input).cwiseAbs().maxCoeff(), 1e-12);
    for (int k = 0; k < 3; ++k) {
      if (input[k] > grid.axis(k).front() && input[k] < grid.axis(k).back()) continue;
      Eigen::Matrix<double, 7, 1> column = analytic.d_output_d_input.col(k);
      column[k] -= 1.0;  // the position passes through
      EXPECT_LT(column.cwiseAbs().maxCoeff(), 1e-15) << "axis " << k;
    }
  }
}

// The grid spans the stations' box exactly: its last node was lo + (hi - lo) * (n - 1) / (n - 1),
// which rounds below hi for about 3 % of boxes (here -0.99 .. 0.85 with 4 nodes:
// 0.8499999999999999), so the station at the maximum was outside the grid and its served correction
// flagged extrapolated.
TEST(LutTerm, GridEndsAtTheStationsMaximum) {
  std::mt19937 rng(25);
  auto stations = RandomStations(50, &rng);
  stations[0].reported.translation = Eigen::Vector3d(-0.99, -0.99, -0.99);
  stations[1].reported.translation = Eigen::Vector3d(0.85, 0.85, 0.85);
  LutTermOptions options;
  options.nodes = std::array<int, 3>{4, 4, 4};
  LutTerm lut(options);
  lut.Prepare(stations);
  for (int k = 0; k < 3; ++k) {
    EXPECT_EQ(lut.grid().axis(k).front(), -0.99);
    EXPECT_EQ(lut.grid().axis(k).back(), 0.85);
  }
  const auto correction = lut.ToCorrection();
  for (const auto& s : stations)
    EXPECT_FALSE(correction->Apply(s.reported).extrapolated) << s.station;
}

TEST(LutTerm, ModelFileErrors) {
  EXPECT_THROW(ParseModelYaml("terms: [{type: lut, cell_size_mm: 0}]", "m"), std::invalid_argument);
  EXPECT_THROW(ParseModelYaml("terms: [{type: lut, nodes: [2, 2]}]", "m"), std::invalid_argument);
  EXPECT_THROW(ParseModelYaml("terms: [{type: lut, smoothness: -1}]", "m"), std::invalid_argument);
}

// Node counts beyond int's range used to be converted before their check (undefined behaviour),
// and a tiny cell over the stations' box built grids beyond memory: both are errors naming the key
// or the cell size.
TEST(LutTerm, GridSizeIsBounded) {
  auto error_of = [](const std::string& yaml) -> std::string {
    try {
      ParseModelYaml(yaml, "m.yaml");
    } catch (const std::invalid_argument& e) {
      return e.what();
    }
    return "";
  };
  EXPECT_THAT(error_of("terms: [{type: lut, nodes: [1e12, 4, 4]}]"),
              ::testing::HasSubstr("nodes: node counts must be integers 2 .. 1000"));
  EXPECT_THAT(error_of("terms: [{type: lut, nodes: [2.5, 4, 4]}]"),
              ::testing::HasSubstr("nodes: node counts must be integers"));
  EXPECT_THAT(error_of("terms: [{type: lut, nodes: [100, 100, 100]}]"),
              ::testing::HasSubstr("$.terms[0].nodes: lut: nodes: 1000000 nodes, at most 200000"));
  EXPECT_EQ(error_of("terms: [{type: lut, nodes: [100, 100, 20]}]"), "");

  std::mt19937 rng(4);
  auto stations = RandomStations(50, &rng);  // about a metre wide
  for (auto& s : stations) s.reference = s.reported;
  ModelSpec spec = ParseModelYaml("terms: [{type: lut, cell_size_mm: 0.001}]", "m");
  try {
    FitModel(stations, &spec);
    ADD_FAILURE() << "a 1 um cell over a metre was accepted";
  } catch (const std::invalid_argument& e) {
    EXPECT_THAT(e.what(), ::testing::HasSubstr("lut: cell_size_mm 0.001 over the stations' box"));
  }
}

// The weights a model file does not set follow the LUT's place in the chain: the lone defaults for
// a LUT after no polynomial or LUT, 1 and 1 after one (whose gauge the ridge must hold firmly
// enough for the solver to converge); a weight the file sets is kept wherever the LUT is.
TEST(LutTerm, UnsetWeightsFollowThePlaceInTheChain) {
  auto weights = [](const std::string& yaml, bool first) {
    ModelSpec spec = ParseModelYaml(yaml, "m");
    ModelTerm& lut = *spec.terms.back();
    const std::vector<const ModelTerm*> earlier =
        first ? std::vector<const ModelTerm*>{}
              : std::vector<const ModelTerm*>{spec.terms[0].get()};
    lut.SetPrecedingTerms(earlier);
    const nlohmann::json d = lut.Describe();
    return std::make_pair(d.at("smoothness").get<double>(), d.at("ridge").get<double>());
  };
  EXPECT_EQ(weights("terms: [{type: lut}]", true),
            std::make_pair(kLoneLutSmoothness, kLoneLutRidge));
  const std::string chain = "terms: [{type: polynomial, degree: 2}, {type: lut}]";
  EXPECT_EQ(weights(chain, false), std::make_pair(1.0, 1.0));
  EXPECT_EQ(weights("terms: [{type: lut}, {type: lut}]", false), std::make_pair(1.0, 1.0));
  // A physical term shares no multilinear gauge with the LUT: the lone weights stay, so that a
  // diagnose candidate adding one in front of a lone LUT changes nothing else (with 1 and 1 the
  // paper preset's held-out mean after a plane was 2.9 mm, after a receiver_gain 25 mm).
  for (const std::string physical : {"plane", "receiver_gain", "dipole"}) {
    EXPECT_EQ(weights("terms: [{type: " + physical + "}, {type: lut}]", false),
              std::make_pair(kLoneLutSmoothness, kLoneLutRidge))
        << physical;
  }
  // A polynomial after the LUT (diagnose's flexible fallback after a lone-LUT base) shares the
  // gauge as much as one before it.
  {
    ModelSpec spec = ParseModelYaml("terms: [{type: lut}, {type: polynomial, degree: 3}]", "m");
    spec.terms[0]->SetFollowingTerms({spec.terms[1].get()});
    spec.terms[0]->SetPrecedingTerms({});
    const nlohmann::json d = spec.terms[0]->Describe();
    EXPECT_EQ(d.at("smoothness").get<double>(), 1.0);
    EXPECT_EQ(d.at("ridge").get<double>(), 1.0);
  }
  EXPECT_EQ(weights("terms: [{type: lut, ridge: 0.5}]", true),
            std::make_pair(kLoneLutSmoothness, 0.5));
  EXPECT_EQ(weights("terms: [{type: polynomial, degree: 2}, {type: lut, smoothness: 3}]", false),
            std::make_pair(3.0, 1.0));
}

}  // namespace
}  // namespace trackcal::fit
