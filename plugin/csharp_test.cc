// Serves known poses on loopback and runs the C# wrapper's test program under Mono against the
// plugin (unity/tests/TrackcalCsharpTest.cs has the checks). CMake passes the paths.
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

TEST(UnityCsharp, TheWrapperReadsServedPosesInUnityAxes) {
  const std::string mono = TRACKCAL_MONO;
  ASSERT_FALSE(mono.empty())
      << "mono and mcs are needed for this test: apt-get install mono-mcs mono-runtime "
         "(scripts/install-deps.sh does), then re-run cmake";
  auto catalog = std::make_shared<vrpn::ServerCatalog>();
  vrpn::TrackerSpec spec;
  spec.name = "Tracker0";
  spec.num_sensors = 4;
  catalog->AddTracker(spec);
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
    while (!stop) {
      for (const auto& [sensor, pose] : poses)
        server.PublishPose(0, sensor, pose, vrpn::Timestamp::Now());
      std::this_thread::sleep_for(std::chrono::milliseconds(10));
    }
  });

  std::string command = "LD_LIBRARY_PATH=" TRACKCAL_UNITY_LIBRARY_DIR " " + mono +
                        " " TRACKCAL_CSHARP_TEST_EXE +
                        " Tracker0@tcp://127.0.0.1:" + std::to_string(server.port());
  for (const auto& [sensor, pose] : poses) {
    command += ' ';
    command += std::to_string(sensor);
    for (double v : {pose.translation.x(), pose.translation.y(), pose.translation.z(),
                     pose.rotation.x(), pose.rotation.y(), pose.rotation.z(), pose.rotation.w()}) {
      command += ',';
      command += Number(v);
    }
  }
  command += " 2>&1";
  std::string output;
  FILE* pipe = popen(command.c_str(), "r");
  ASSERT_NE(pipe, nullptr) << command;
  char buf[512];
  while (std::fgets(buf, sizeof(buf), pipe) != nullptr) output += buf;
  const int status = pclose(pipe);
  stop = true;
  publisher.join();
  ASSERT_TRUE(WIFEXITED(status)) << command << "\n" << output;
  EXPECT_EQ(WEXITSTATUS(status), 0) << command << "\n" << output;
  EXPECT_NE(output.find("PASS"), std::string::npos) << output;
}

}  // namespace
}  // namespace trackcal
