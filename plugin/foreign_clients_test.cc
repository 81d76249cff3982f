// The plugin as foreign clients use it, against known poses served on loopback: the C# wrapper
// under Mono, and the Windows DLL under Wine. CMake passes the tools' paths.
#include <gtest/gtest.h>
#include <sys/wait.h>

#include <atomic>
#include <cstdio>
#include <cstdlib>
#include <map>
#include <string>
#include <thread>

#include "core/pose.h"
#include "tests/test_utils.h"
#include "vrpn_server/server/server.h"

namespace trackcal {
namespace {

std::string Number(double v) {
  char buf[40];
  std::snprintf(buf, sizeof(buf), "%.17g", v);  // round-trips a double
  return buf;
}

// Serves two sensors' known poses and a stylus ("Stylus0", button 1 pressed about every 0.1 s) on
// loopback while `command` (followed by the VRPN name and the
// poses as "sensor,px,py,pz,qx,qy,qz,qw") runs; returns its exit status and output.
struct Run {
  int status = -1;
  std::string output;
  std::string command;
};

Run RunAgainstServedPoses(const std::string& command_prefix) {
  auto catalog = std::make_shared<vrpn::ServerCatalog>();
  vrpn::TrackerSpec spec;
  spec.name = "Tracker0";
  spec.num_sensors = 4;
  catalog->AddTracker(spec);
  catalog->AddButton(vrpn::ButtonSpec{"Stylus0", 2});  // read as "Stylus0@..." by the programs
  vrpn::ServerOptions options;
  options.bind_address = "127.0.0.1";
  options.port = 0;
  vrpn::VrpnServer server(catalog, options, [](const std::string&) {});
  server.Start();

  auto& rng = testing::TestRng();
  std::map<int, Rigid3d> poses = {
      {0, Rigid3d(testing::RandomRotation(rng), Eigen::Vector3d(0.31, -0.22, 0.47))},
      {3, Rigid3d(testing::RandomRotation(rng), Eigen::Vector3d(-0.12, 0.26, 0.61))}};
  std::atomic<bool> stop{false};
  std::thread publisher([&] {
    for (int i = 0; !stop; ++i) {
      for (const auto& [sensor, pose] : poses) {
        server.PublishPose(0, sensor, pose, vrpn::Timestamp::Now());
      }
      // The stylus's button 1 goes down and up every 0.1 s; button 0 stays up.
      if (i % 5 == 0) server.PublishButton(0, 1, (i / 5) % 2 == 0, vrpn::Timestamp::Now());
      std::this_thread::sleep_for(std::chrono::milliseconds(10));
    }
  });

  Run run;
  run.command = command_prefix + " Tracker0@tcp://127.0.0.1:" + std::to_string(server.port());
  for (const auto& [sensor, pose] : poses) {
    run.command += ' ';
    run.command += std::to_string(sensor);
    for (double v : {pose.translation.x(), pose.translation.y(), pose.translation.z(),
                     pose.rotation.x(), pose.rotation.y(), pose.rotation.z(), pose.rotation.w()}) {
      run.command += ',';
      run.command += Number(v);
    }
  }
  run.command += " 2>&1";
  FILE* pipe = popen(run.command.c_str(), "r");
  if (pipe != nullptr) {
    char buf[512];
    while (std::fgets(buf, sizeof(buf), pipe) != nullptr) run.output += buf;
    run.status = pclose(pipe);
  }
  stop = true;
  publisher.join();
  return run;
}

void ExpectPass(const Run& run) {
  ASSERT_TRUE(WIFEXITED(run.status)) << run.command << "\n" << run.output;
  EXPECT_EQ(WEXITSTATUS(run.status), 0) << run.command << "\n" << run.output;
  EXPECT_NE(run.output.find("PASS"), std::string::npos) << run.output;
}

// The C# wrapper compiled with mcs (against a UnityEngine stub) and run with mono against the
// Linux library (unity/tests/TrackcalCsharpTest.cs has the checks).
TEST(UnityCsharp, TheWrapperReadsServedPosesInUnityAxes) {
  const std::string mono = TRACKCAL_MONO;
  ASSERT_FALSE(mono.empty()) << "mono and mcs are needed: apt-get install mono-mcs mono-runtime "
                                "(scripts/install-deps.sh does), then re-run cmake";
  ExpectPass(RunAgainstServedPoses("LD_LIBRARY_PATH=" TRACKCAL_UNITY_LIBRARY_DIR " " + mono +
                                   " " TRACKCAL_CSHARP_TEST_EXE));
}

// The Windows DLL (plugin/standalone, cross-compiled with MinGW-w64) and its smoke program
// (windows_smoke.cc) under Wine, against the same server: Winsock, the exports, the struct layout.
TEST(UnityWindows, TheDllReadsServedPosesUnderWine) {
  const std::string wine = TRACKCAL_WINE;
  ASSERT_FALSE(wine.empty()) << "MinGW-w64 and Wine are needed: apt-get install "
                                "g++-mingw-w64-x86-64-posix wine64 (scripts/install-deps.sh does), "
                                "then re-run cmake";
  // A prefix of the build tree's own (made on first use, ~10 s), quiet.
  ExpectPass(RunAgainstServedPoses("WINEPREFIX=" TRACKCAL_WINE_PREFIX " WINEDEBUG=-all " + wine +
                                   " " TRACKCAL_WINDOWS_SMOKE_EXE));
}

}  // namespace
}  // namespace trackcal
