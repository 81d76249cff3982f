// The emulator against the project's own Fastrak driver (vrpn_server/fastrak, run as the
// trackcal-fastrak-monitor process): the driver resets the emulated tracker and streams its
// records, and every injected fault is seen by the driver as the fault it is. Only the monitor's
// final summary line ("records N, resets N, resumes N, watchdog timeouts N, port losses N,
// discarded bytes N") is read, so the two modules share no code.

#include <fcntl.h>
#include <gtest/gtest.h>
#include <spawn.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <fstream>
#include <iterator>
#include <regex>
#include <thread>

#include "sim/emulator/emulator.h"
#include "tests/test_utils.h"

namespace trackcal::emulator {
namespace {

struct DriverSummary {
  long records = -1, resets = -1, resumes = -1, watchdog_timeouts = -1, port_losses = -1,
       discarded_bytes = -1;
};

DriverSummary ParseSummary(const std::string& text) {
  DriverSummary s;
  std::smatch m;
  const std::regex re(
      R"(records (\d+), resets (\d+), resumes (\d+), watchdog timeouts (\d+), port losses (\d+), discarded bytes (\d+))");
  if (std::regex_search(text, m, re)) {
    s.records = std::stol(m[1]);
    s.resets = std::stol(m[2]);
    s.resumes = std::stol(m[3]);
    s.watchdog_timeouts = std::stol(m[4]);
    s.port_losses = std::stol(m[5]);
    s.discarded_bytes = std::stol(m[6]);
  }
  return s;
}

void Sleep(double seconds) { std::this_thread::sleep_for(std::chrono::duration<double>(seconds)); }

TEST(DriverEndToEnd, EveryFaultIsObserved) {
  const std::filesystem::path dir = testing::MakeTempDir("driver_e2e");
  EmulatorOptions options;
  options.link_path = (dir / "fastrak").string();
  options.device.num_stations = 2;
  BackgroundEmulator emulator(options,
                              std::make_unique<StaticPoseSource>(std::vector<Rigid3d>{
                                  Rigid3d(Eigen::Quaterniond::Identity(), {0.25, 0.0, 0.1}),
                                  Rigid3d(Eigen::Quaterniond::Identity(), {0.35, 0.1, 0.1})}));

  const std::string monitor = TRACKCAL_FASTRAK_MONITOR;
  const std::string err_path = (dir / "monitor_err.txt").string();
  std::vector<std::string> args = {monitor, options.link_path, "--fast", "--seconds", "11"};
  std::vector<char*> argv;
  for (std::string& a : args) argv.push_back(a.data());
  argv.push_back(nullptr);
  posix_spawn_file_actions_t actions;
  posix_spawn_file_actions_init(&actions);
  posix_spawn_file_actions_addopen(&actions, 1, "/dev/null", O_WRONLY, 0);
  posix_spawn_file_actions_addopen(&actions, 2, err_path.c_str(), O_WRONLY | O_CREAT | O_TRUNC,
                                   0644);
  pid_t pid = 0;
  ASSERT_EQ(posix_spawn(&pid, monitor.c_str(), &actions, nullptr, argv.data(), environ), 0);
  posix_spawn_file_actions_destroy(&actions);

  // The driver's reset takes well under a second with --fast; faults follow at a pace that lets it
  // recover from each (watchdog 2 s).
  Sleep(2.0);
  EXPECT_EQ(emulator.Control("fault garbage 50"), "ok");
  Sleep(1.0);
  EXPECT_EQ(emulator.Control("fault truncate"), "ok");  // 32-byte record cut to 16
  Sleep(1.0);
  EXPECT_EQ(emulator.Control("fault stall 3"), "ok");  // beyond the driver's 2 s watchdog
  Sleep(4.0);
  EXPECT_EQ(emulator.Control("fault disconnect 1"), "ok");

  int status = 0;
  ASSERT_EQ(waitpid(pid, &status, 0), pid);
  EXPECT_TRUE(WIFEXITED(status) && WEXITSTATUS(status) == 0) << status;
  std::ifstream in(err_path);
  const std::string err((std::istreambuf_iterator<char>(in)), {});
  const DriverSummary s = ParseSummary(err);
  ASSERT_GE(s.records, 0) << "no summary line from the monitor:\n" << err;
  // 11 s at 120 Hz minus ~6 s of faults and recoveries: several hundred records.
  EXPECT_GT(s.records, 300) << err;
  // The injected garbage and the truncated half record were discarded. While the driver recovers
  // from the stall, the stalled device's late answers to its reset (a status record, a partial
  // record) may be discarded too: at most a couple of those (2 x 55 + 32 bytes).
  EXPECT_GE(s.discarded_bytes, 50 + 16) << err;
  EXPECT_LE(s.discarded_bytes, 50 + 16 + 2 * 55 + 32) << err;
  EXPECT_GE(s.watchdog_timeouts, 1) << err;   // the stall
  EXPECT_GE(s.port_losses, 1) << err;         // the unplugged cable
  EXPECT_GE(s.resets + s.resumes, 2) << err;  // start-up, and back after each loss
}

}  // namespace
}  // namespace trackcal::emulator
