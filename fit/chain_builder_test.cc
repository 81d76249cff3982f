// BuildChain's option checks. The builder's search on the paper preset is
// fit/best_chain_sim_test.cc.
#include "fit/chain_builder.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <stdexcept>
#include <vector>

namespace trackcal::fit {
namespace {

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

}  // namespace
}  // namespace trackcal::fit
