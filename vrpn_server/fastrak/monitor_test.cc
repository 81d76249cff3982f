// trackcal-fastrak-monitor end to end: the installed tool against the scripted pty Fastrak.

#include <gtest/gtest.h>

#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <sstream>
#include <string>

#include "tests/test_utils.h"
#include "vrpn_server/fastrak/fake_fastrak.h"

namespace trackcal::fastrak {
namespace {

std::string RunCommand(const std::string& command) {
  FILE* pipe = ::popen(command.c_str(), "r");
  EXPECT_NE(pipe, nullptr);
  std::string out;
  char buffer[4096];
  size_t n;
  while ((n = std::fread(buffer, 1, sizeof(buffer), pipe)) > 0) out.append(buffer, n);
  EXPECT_EQ(::pclose(pipe), 0) << command;
  return out;
}

TEST(FastrakMonitor, Nominal) {
  const char* binary_dir = std::getenv("TRACKCAL_BINARY_DIR");
  ASSERT_NE(binary_dir, nullptr);
  const auto dir = trackcal::testing::MakeTempDir("fastrak_monitor");
  testing::FakeFastrak fake(dir / "tty", testing::FakeFastrakOptions{});
  const std::string out = RunCommand(std::string(binary_dir) +
                                     "/vrpn_server/fastrak/trackcal-fastrak-monitor " +
                                     (dir / "tty").string() + " --fast --units cm --seconds 1 2>/dev/null");
  std::istringstream lines(out);
  std::string line;
  ASSERT_TRUE(std::getline(lines, line));
  EXPECT_EQ(line, "host_time_s,sensor,x,y,z,qw,qx,qy,qz,status,stylus");
  int sensor0 = 0;
  while (std::getline(lines, line)) {
    double t, x, y, z, qw, qx, qy, qz;
    int sensor;
    ASSERT_EQ(std::sscanf(line.c_str(), "%lf,%d,%lf,%lf,%lf,%lf,%lf,%lf,%lf", &t, &sensor, &x, &y, &z,
                          &qw, &qx, &qy, &qz), 9) << line;
    if (sensor != 0) continue;
    ++sensor0;
    // %.7g printing: 7 significant digits.
    EXPECT_NEAR(x, 0.254, 1e-6);
    EXPECT_NEAR(y, -0.127, 1e-6);
    EXPECT_NEAR(z, 0.508, 1e-6);
    EXPECT_NEAR(qw, 4 / std::sqrt(30.0), 1e-6);
  }
  EXPECT_GT(sensor0, 10);
  EXPECT_TRUE(fake.metric());  // --units cm was sent as `u`
}

TEST(FastrakMonitor, SecondsThatIsNotANumberIsAUsageError) {
  // strtod reads "nan", and NaN < 0 is false: the monitor accepted it and, as no time compares
  // >= NaN, ran until killed instead of saying what is wrong.
  const char* binary_dir = std::getenv("TRACKCAL_BINARY_DIR");
  ASSERT_NE(binary_dir, nullptr);
  const auto dir = trackcal::testing::MakeTempDir("fastrak_monitor");
  const std::string out = RunCommand(
      "timeout 10 " + std::string(binary_dir) + "/vrpn_server/fastrak/trackcal-fastrak-monitor " +
      (dir / "tty").string() + " --fast --seconds nan 2>&1; echo rc=$?");
  EXPECT_NE(out.find("--seconds: bad value 'nan'"), std::string::npos) << out;
  EXPECT_NE(out.find("rc=2"), std::string::npos) << out;
}

TEST(FastrakMonitor, PrintsTheBytesOfItsArgumentsAndVrpnCfgEscaped) {
  // A tracker name with an escape sequence (ESC [ 2 J clears the screen) reached the terminal raw
  // in the fatal error ("no vrpn_Tracker_Fastrak named ..."), as trackcal-server's once did.
  const char* binary_dir = std::getenv("TRACKCAL_BINARY_DIR");
  ASSERT_NE(binary_dir, nullptr);
  const auto dir = trackcal::testing::MakeTempDir("fastrak_monitor");
  {
    std::ofstream cfg(dir / "vrpn.cfg");
    cfg << "vrpn_Tracker_Fastrak Tracker0 /dev/ttyS0 115200\n";
  }
  const std::string out = RunCommand("timeout 10 " + std::string(binary_dir) +
                                     "/vrpn_server/fastrak/trackcal-fastrak-monitor --config " +
                                     (dir / "vrpn.cfg").string() +
                                     " --tracker \"$(printf 'T\\033[2J')\" 2>&1; echo rc=$?");
  EXPECT_NE(out.find("no vrpn_Tracker_Fastrak named 'T\\x1b[2J'"), std::string::npos) << out;
  EXPECT_EQ(out.find('\x1b'), std::string::npos) << out;
  EXPECT_NE(out.find("rc=1"), std::string::npos) << out;
}

}  // namespace
}  // namespace trackcal::fastrak
