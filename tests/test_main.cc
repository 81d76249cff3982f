// gtest main for every trackcal test: reseeds the shared RNG before each test.
#include <gtest/gtest.h>

#include "tests/test_utils.h"

namespace {
class ReseedListener : public ::testing::EmptyTestEventListener {
  void OnTestStart(const ::testing::TestInfo&) override {
    trackcal::testing::TestRng().seed(trackcal::testing::kTestSeed);
  }
};
}  // namespace

int main(int argc, char** argv) {
  ::testing::InitGoogleTest(&argc, argv);
  ::testing::UnitTest::GetInstance()->listeners().Append(new ReseedListener);
  return RUN_ALL_TESTS();
}
