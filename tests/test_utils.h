// Test support shared by every C++ test: deterministic randomness and pose comparisons.
#pragma once

#include <gtest/gtest.h>

#include <filesystem>
#include <random>
#include <string>

#include "core/pose.h"

namespace trackcal::testing {

// The RNG every test draws from; test_main.cc reseeds it with kTestSeed before each test so a test's
// numbers do not depend on which tests ran before it.
inline constexpr unsigned kTestSeed = 20010313;
std::mt19937_64& TestRng();

Eigen::Quaterniond RandomRotation(std::mt19937_64& rng);

// Source tree root (tests/data lives below it); from TRACKCAL_SOURCE_DIR set by ctest.
std::filesystem::path SourceDir();
// A fresh empty directory for one test, removed when the test binary exits.
std::filesystem::path MakeTempDir(const std::string& prefix);

// Rotations compared by angle, so q and -q are equal.
::testing::AssertionResult RotationsNear(const Eigen::Quaterniond& expected,
                                         const Eigen::Quaterniond& actual, double max_angle_rad);
::testing::AssertionResult PosesNear(const Rigid3d& expected, const Rigid3d& actual,
                                     double max_position_m, double max_angle_rad);

}  // namespace trackcal::testing
