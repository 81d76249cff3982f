// BuildChain's option checks and its refusal of captures too small for the explicit term's
// cross-validation, on synthetic stations (no physical source: max_sources 0 where it runs). The
// builder's search on the paper preset is fit/best_chain_sim_test.cc.
#include "fit/chain_builder.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <stdexcept>
#include <vector>

#include "core/polynomial.h"

namespace trackcal::fit {
namespace {

// `n` stations scattered over a 0.6 x 0.6 x 0.5 m box below the transmitter; the report is
// off by a smooth position error (quadratic in position) and a small turn, no noise.
std::vector<FitStation> Stations(int n) {
  std::vector<FitStation> out;
  for (int i = 0; i < n; ++i) {
    const Eigen::Vector3d p(-0.3 + 0.6 * ((i * 7) % 11) / 10.0, -0.3 + 0.6 * ((i * 5) % 13) / 12.0,
                            -0.8 + 0.5 * ((i * 3) % 7) / 6.0);
    FitStation s;
    s.station = i + 1;
    s.reference = Rigid3d(Eigen::Quaterniond::Identity(), p);
    const Eigen::Vector3d error(0.002 * p.x() * p.y(), 0.001 * p.z() * p.z(), 0.003 * p.x());
    s.reported = Rigid3d(
        Eigen::Quaterniond(Eigen::AngleAxisd(0.002 * p.y(), Eigen::Vector3d::UnitZ())), p + error);
    out.push_back(s);
  }
  return out;
}

TEST(ChainBuilderOptions, Nominal_DefaultsPassAndEachSourceTypeOnce) {
  ChainBuilderOptions options;
  EXPECT_NO_THROW(options.Check());
  // A type listed twice was tried twice per round, and both steps were marked kept.
  options.source_types = {"dipole", "plane", "dipole"};
  EXPECT_THAT([&] { options.Check(); },
              ::testing::ThrowsMessage<std::invalid_argument>(
                  ::testing::HasSubstr("source_types: 'dipole' given twice")));
  options.source_types = {"dipole", "wall"};
  EXPECT_THROW(options.Check(), std::invalid_argument);
}

// A degree-2 polynomial has 10 coefficients per coordinate: its cross-validation needs 11 stations.
// With 10 every score was infinite and the model ended with a degree-0 polynomial at ridge 0 that
// was never scored; now the builder says why it cannot build.
TEST(BuildChain, TooFewStationsForTheExplicitTermThrow) {
  ChainBuilderOptions options;
  options.max_sources = 0;
  ASSERT_EQ(NumPolynomialTerms(options.min_degree), 10);
  EXPECT_THAT([&] { BuildChain(Stations(10), options); },
              ::testing::ThrowsMessage<std::invalid_argument>(
                  ::testing::AllOf(::testing::HasSubstr("10 stations are too few"),
                                   ::testing::HasSubstr("degree-2 polynomial (min_degree)"),
                                   ::testing::HasSubstr("at least 11 stations"))));
  // One more, and the explicit term is scored at a degree in [min_degree, max_degree].
  const BuiltChain built = BuildChain(Stations(11), options);
  EXPECT_GE(built.degree, options.min_degree);
  EXPECT_TRUE(std::isfinite(built.score));
  ASSERT_EQ(built.steps.size(), 1u);
  EXPECT_TRUE(built.steps[0].kept);
  EXPECT_THAT(built.model_text, ::testing::HasSubstr("degree: " + std::to_string(built.degree)));
}

}  // namespace
}  // namespace trackcal::fit
