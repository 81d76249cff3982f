#include "tests/test_utils.h"

#include <cstdlib>
#include <vector>

namespace trackcal::testing {

std::mt19937_64& TestRng() {
  static std::mt19937_64 rng(kTestSeed);
  return rng;
}

Eigen::Quaterniond RandomRotation(std::mt19937_64& rng) {
  // Uniform on SO(3): a normalised 4-D Gaussian.
  std::normal_distribution<double> n(0.0, 1.0);
  Eigen::Quaterniond q = QuaternionFromXyzw(n(rng), n(rng), n(rng), n(rng));
  q.normalize();
  return q;
}

std::filesystem::path SourceDir() {
  if (const char* dir = std::getenv("TRACKCAL_SOURCE_DIR")) return dir;
  return std::filesystem::path(__FILE__).parent_path().parent_path();
}

namespace {
struct TempDirs {
  std::vector<std::filesystem::path> dirs;
  ~TempDirs() {
    std::error_code ec;
    for (const auto& d : dirs) std::filesystem::remove_all(d, ec);
  }
};
TempDirs& AllTempDirs() {
  static TempDirs dirs;
  return dirs;
}
}  // namespace

std::filesystem::path MakeTempDir(const std::string& prefix) {
  std::string templ = (std::filesystem::temp_directory_path() / (prefix + "-XXXXXX")).string();
  char* made = mkdtemp(templ.data());
  if (made == nullptr) throw std::runtime_error("mkdtemp failed for " + templ);
  AllTempDirs().dirs.emplace_back(made);
  return made;
}

::testing::AssertionResult RotationsNear(const Eigen::Quaterniond& expected,
                                         const Eigen::Quaterniond& actual, double max_angle_rad) {
  const double angle = AngularDistance(expected, actual);
  if (angle <= max_angle_rad) return ::testing::AssertionSuccess();
  return ::testing::AssertionFailure()
         << "rotations differ by " << angle << " rad (max " << max_angle_rad << "): expected xyzw ["
         << expected.coeffs().transpose() << "], actual [" << actual.coeffs().transpose() << "]";
}

::testing::AssertionResult PosesNear(const Rigid3d& expected, const Rigid3d& actual,
                                     double max_position_m, double max_angle_rad) {
  const double dp = (expected.translation - actual.translation).norm();
  const double angle = AngularDistance(expected.rotation, actual.rotation);
  if (dp <= max_position_m && angle <= max_angle_rad) return ::testing::AssertionSuccess();
  return ::testing::AssertionFailure() << "poses differ by " << dp << " m and " << angle
                                       << " rad (max " << max_position_m << " m, " << max_angle_rad
                                       << " rad): expected " << expected.ToString() << ", actual "
                                       << actual.ToString();
}

}  // namespace trackcal::testing
