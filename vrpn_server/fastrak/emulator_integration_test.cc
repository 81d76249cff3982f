// FastrakDriver against the full Fastrak emulator (sim/emulator, BackgroundEmulator on a pty, output
// paced at 115200 baud): poses, units, stylus and the emulator's fault injections.

#include <fcntl.h>
#include <gtest/gtest.h>
#include <unistd.h>

#include <condition_variable>
#include <iostream>
#include <mutex>
#include <optional>
#include <thread>

#include "sim/emulator/emulator.h"
#include "sim/emulator/pose_source.h"
#include "tests/test_utils.h"
#include "vrpn_server/fastrak/driver.h"

namespace trackcal::fastrak {
namespace {

using SteadyClock = std::chrono::steady_clock;

// The poses of transcript 07, in metres.
std::vector<Rigid3d> TranscriptPoses() {
  const double s = std::sqrt(30.0);
  return {Rigid3d(QuaternionFromWxyz(4 / s, 1 / s, 2 / s, 3 / s), Eigen::Vector3d(0.254, -0.127, 0.508)),
          Rigid3d(Eigen::Quaterniond::Identity(), Eigen::Vector3d(0.0381, 0.0635, -0.0889))};
}

// The emulator converts metres to float32 inches or centimetres and the driver converts back:
// float32 spacing at 20 in is 2e-6 in = 5e-8 m, plus the double->float rounding of the pose:
// 1e-6 m and 1e-6 rad leave a wide margin while catching any unit or order mistake.
constexpr double kPositionTolM = 1e-6;
constexpr double kAngleTolRad = 1e-6;

class Collector {
 public:
  FastrakDriver::Callbacks Callbacks() {
    FastrakDriver::Callbacks c;
    c.on_report = [this](const FastrakReport& r) {
      std::lock_guard<std::mutex> lock(mutex_);
      reports_.push_back(r);
      times_.push_back(SteadyClock::now());
      cv_.notify_all();
    };
    c.on_button = [this](int sensor, bool pressed, std::chrono::system_clock::time_point) {
      std::lock_guard<std::mutex> lock(mutex_);
      buttons_.emplace_back(sensor, pressed);
      cv_.notify_all();
    };
    c.on_message = [](Severity severity, const std::string& text) {
      std::cerr << SeverityName(severity) << ": " << text << "\n";
    };
    c.on_log = [this](Severity, const std::string& text) {
      std::lock_guard<std::mutex> lock(mutex_);
      logs_.push_back(text);
      if (text.find("opened at") == std::string::npos) return;
      opened_.push_back(SteadyClock::now());
    };
    return c;
  }
  // Seconds from the last opening of the port before report `i` to that report.
  double SinceOpened(size_t i) const {
    std::lock_guard<std::mutex> lock(mutex_);
    std::optional<SteadyClock::time_point> opened;
    for (const SteadyClock::time_point t : opened_) {
      if (t <= times_.at(i)) opened = t;
    }
    return opened ? std::chrono::duration<double>(times_.at(i) - *opened).count() : -1.0;
  }
  // Index of the first report, from `from` on, that follows a silence of at least `gap_s`.
  std::optional<size_t> FirstIndexAfterGap(size_t from, double gap_s) const {
    std::lock_guard<std::mutex> lock(mutex_);
    for (size_t i = std::max<size_t>(from, 1); i < times_.size(); ++i) {
      if (times_[i] - times_[i - 1] >= std::chrono::duration<double>(gap_s)) return i;
    }
    return std::nullopt;
  }
  bool WaitForReports(size_t n, double timeout_s) {
    std::unique_lock<std::mutex> lock(mutex_);
    return cv_.wait_for(lock, std::chrono::duration<double>(timeout_s), [&] { return reports_.size() >= n; });
  }
  bool WaitForButton(bool pressed, double timeout_s) {
    std::unique_lock<std::mutex> lock(mutex_);
    return cv_.wait_for(lock, std::chrono::duration<double>(timeout_s), [&] {
      return !buttons_.empty() && buttons_.back().second == pressed;
    });
  }
  size_t size() const {
    std::lock_guard<std::mutex> lock(mutex_);
    return reports_.size();
  }
  // Every text the driver logged that contains `part`.
  std::vector<std::string> Logs(const std::string& part) const {
    std::lock_guard<std::mutex> lock(mutex_);
    std::vector<std::string> out;
    for (const std::string& t : logs_) {
      if (t.find(part) != std::string::npos) out.push_back(t);
    }
    return out;
  }
  std::vector<FastrakReport> reports() const {
    std::lock_guard<std::mutex> lock(mutex_);
    return reports_;
  }
  SteadyClock::time_point time(size_t i) const {
    std::lock_guard<std::mutex> lock(mutex_);
    return times_.at(i);
  }
  // Time of the first report, from index `from` on, that follows a silence of at least `gap_s`
  // (records already queued when a fault starts still arrive before the silence).
  std::optional<SteadyClock::time_point> FirstAfterGap(size_t from, double gap_s) const {
    std::lock_guard<std::mutex> lock(mutex_);
    for (size_t i = std::max<size_t>(from, 1); i < times_.size(); ++i) {
      if (times_[i] - times_[i - 1] >= std::chrono::duration<double>(gap_s)) return times_[i];
    }
    return std::nullopt;
  }

 private:
  mutable std::mutex mutex_;
  std::condition_variable cv_;
  std::vector<FastrakReport> reports_;
  std::vector<SteadyClock::time_point> times_;
  std::vector<SteadyClock::time_point> opened_;
  std::vector<std::string> logs_;
  std::vector<std::pair<int, bool>> buttons_;
};

template <typename Pred>
bool WaitUntil(Pred pred, double timeout_s) {
  const auto deadline = SteadyClock::now() + std::chrono::duration<double>(timeout_s);
  while (!pred()) {
    if (SteadyClock::now() > deadline) return false;
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  }
  return true;
}

void ExpectPoses(const std::vector<FastrakReport>& reports) {
  const std::vector<Rigid3d> poses = TranscriptPoses();
  for (const FastrakReport& r : reports) {
    ASSERT_GE(r.sensor, 0);
    ASSERT_LT(r.sensor, 2);
    EXPECT_LT((r.position_m - poses[r.sensor].translation).norm(), kPositionTolM)
        << "sensor " << r.sensor << ": " << r.position_m.transpose();
    EXPECT_LT(AngularDistance(r.rotation, poses[r.sensor].rotation), kAngleTolRad);
  }
}

struct Fixture {
  explicit Fixture(const std::string& name, int baud = 115200,
                   const Eigen::Vector3d& hemisphere = Eigen::Vector3d::UnitX())
      : dir(trackcal::testing::MakeTempDir(name)), baud(baud) {
    emulator::EmulatorOptions options;
    options.device.hemisphere = hemisphere;  // power-up `H` of every station
    options.link_path = (dir / "fastrak").string();
    options.baud = baud;
    emulator = std::make_unique<emulator::BackgroundEmulator>(
        options, std::make_unique<emulator::StaticPoseSource>(TranscriptPoses()));
  }
  FastrakOptions DriverOptions() const {
    FastrakOptions o;
    o.port = (dir / "fastrak").string();
    o.baud = baud;
    o.timings = FastrakTimings::Fast();
    return o;
  }
  std::filesystem::path dir;
  int baud;
  std::unique_ptr<emulator::BackgroundEmulator> emulator;
};

TEST(FastrakDriverWithEmulator, Nominal) {
  Fixture f("fastrak_emulator");
  for (Units units : {Units::kInches, Units::kCentimetres}) {
    SCOPED_TRACE(UnitsName(units));
    Collector collector;
    FastrakOptions options = f.DriverOptions();
    options.units = units;
    FastrakDriver driver(options, collector.Callbacks());
    driver.Start();
    ASSERT_TRUE(collector.WaitForReports(30, 15.0));
    driver.Stop();
    ExpectPoses(collector.reports());
    EXPECT_EQ(driver.stats().discarded_bytes, 0u);
  }
}

TEST(FastrakDriverWithEmulator, Stylus) {
  Fixture f("fastrak_emulator");
  Collector collector;
  FastrakOptions options = f.DriverOptions();
  options.stylus_sensors = {0};
  FastrakDriver driver(options, collector.Callbacks());
  driver.Start();
  ASSERT_TRUE(collector.WaitForReports(10, 15.0));
  ASSERT_TRUE(collector.WaitForButton(false, 20.0));
  f.emulator->Control("button 1 1");
  EXPECT_TRUE(collector.WaitForButton(true, 20.0));
  f.emulator->Control("button 1 0");
  EXPECT_TRUE(collector.WaitForButton(false, 20.0));
  driver.Stop();
  ExpectPoses(collector.reports());
}

TEST(FastrakDriverWithEmulator, DisconnectGarbageTruncationAndStall) {
  Fixture f("fastrak_emulator");
  Collector collector;
  FastrakOptions options = f.DriverOptions();
  FastrakDriver driver(options, collector.Callbacks());
  driver.Start();
  ASSERT_TRUE(collector.WaitForReports(10, 15.0));

  // Unplug for 1 s: the emulator keeps its state, so the driver resumes without a reset.
  size_t n = collector.size();
  auto t_fault = SteadyClock::now();
  f.emulator->Control("fault disconnect 1.0");
  ASSERT_TRUE(WaitUntil([&] { return collector.FirstAfterGap(n, 0.5).has_value(); }, 10.0));
  // Back 1 s after the fault; reports must follow within 2 s of that.
  double since_back =
      std::chrono::duration<double>(*collector.FirstAfterGap(n, 0.5) - t_fault).count() - 1.0;
  // Timing figure: printed, not asserted (host load; benchmarks measure it).
  std::cout << "disconnect 1 s: reports resumed " << since_back << " s after the device came back, "
            << collector.SinceOpened(*collector.FirstIndexAfterGap(n, 0.5))
            << " s after the port was reopened\n";
  EXPECT_GE(driver.stats().port_losses, 1u);
  // The unit was still streaming: stopped and configured again, without the full reset.
  EXPECT_EQ(driver.stats().resumes, 1u);
  EXPECT_EQ(driver.stats().resets_started, 1u);
  EXPECT_EQ(driver.stats().resets_completed, 2u);

  n = collector.size();
  const DriverStats before_garbage = driver.stats();
  f.emulator->Control("fault garbage 200");
  f.emulator->Control("fault truncate");
  ASSERT_TRUE(collector.WaitForReports(n + 20, 30.0));
  const DriverStats after_garbage = driver.stats();
  if (after_garbage.watchdog_timeouts == before_garbage.watchdog_timeouts &&
      after_garbage.port_losses == before_garbage.port_losses) {
    // Streaming throughout: the garbage went through the parser, which must have skipped it.
    EXPECT_GT(after_garbage.discarded_bytes, before_garbage.discarded_bytes);
  } else {
    // A load-induced watchdog reopen flushed the input instead; the poses are still checked below.
    std::cout << "garbage arrived while the driver was reopening (host under load)\n";
  }

  // 3 s of silence: watchdog, probe, reset attempts; streaming resumes after the stall.
  n = collector.size();
  t_fault = SteadyClock::now();
  f.emulator->Control("fault stall 3");
  ASSERT_TRUE(WaitUntil([&] { return collector.FirstAfterGap(n, 2.0).has_value(); }, 20.0));
  since_back = std::chrono::duration<double>(*collector.FirstAfterGap(n, 2.0) - t_fault).count() - 3.0;
  std::cout << "stall 3 s: reports resumed " << since_back << " s after the device came back\n";
  EXPECT_GE(driver.stats().watchdog_timeouts, 1u);
  driver.Stop();
  ExpectPoses(collector.reports());
}

TEST(FastrakDriverWithEmulator, ReferenceTimingsStartAndUnplug) {
  // The default profile (the reference's waits, meant for real units) against the emulator, which
  // paces its output like a 115200 baud line: start-up, then a 2 s unplug of the port.
  Fixture f("fastrak_emulator");
  Collector collector;
  FastrakOptions options = f.DriverOptions();
  options.timings = FastrakTimings::Reference();
  FastrakDriver driver(options, collector.Callbacks());
  const auto started = SteadyClock::now();
  driver.Start();
  ASSERT_TRUE(collector.WaitForReports(10, 20.0));
  // c, 2 s, flush, 2 s, S, lists 0.2 s, x, v, S (confirmed at the reply instead of the
  // reference's 2 x 1 s): about 4.2 s (the status waits end at their LF).
  const double startup_s = std::chrono::duration<double>(collector.time(0) - started).count();
  std::cout << "reference timings: first report " << startup_s << " s after Start\n";
  // The reference's preamble waits are really made (a lower bound: load can only lengthen them);
  // how much longer start-up takes is a timing figure, not asserted.
  EXPECT_GT(startup_s, 4.0);

  const size_t n = collector.size();
  const auto t_fault = SteadyClock::now();
  f.emulator->Control("fault disconnect 2.0");
  ASSERT_TRUE(WaitUntil([&] { return collector.FirstAfterGap(n, 1.0).has_value(); }, 10.0));
  const double since_back =
      std::chrono::duration<double>(*collector.FirstAfterGap(n, 1.0) - t_fault).count() - 2.0;
  std::cout << "reference timings, disconnect 2 s: reports resumed " << since_back
            << " s after the device came back, "
            << collector.SinceOpened(*collector.FirstIndexAfterGap(n, 1.0))
            << " s after the port was reopened\n";
  EXPECT_EQ(driver.stats().resets_started, 1u);  // configured again, without the full reset
  EXPECT_EQ(driver.stats().resets_completed, 2u);
  EXPECT_EQ(driver.stats().resumes, 1u);
  driver.Stop();
  ExpectPoses(collector.reports());
}

// The requirement: after the port disappears and comes back, or the unit stalls or loses
// power, reports resume within 2 s of the device answering (the reference took 40 s after a 5 s
// unplug). Default (reference) timings, as a real unit gets them; the emulator's output is paced
// like a 115200 baud line. Expected here: about 0.5-1 s (back-off cap 1 s / status poll 0.5 s,
// plus the configuration: 4 output lists 50 ms apart and a status round trip).
TEST(FastrakDriverWithEmulator, ReportsResumeWithin2sOfTheDeviceAnswering) {
  Fixture f("fastrak_emulator");
  Collector collector;
  FastrakOptions options = f.DriverOptions();
  options.timings = FastrakTimings::Reference();
  FastrakDriver driver(options, collector.Callbacks());
  driver.Start();
  ASSERT_TRUE(collector.WaitForReports(10, 20.0));
  struct Case {
    const char* fault;
    double seconds;  // the device answers again this long after the fault starts
  };
  // disconnect: the port vanishes and comes back with the unit still streaming (probe resume);
  // powercycle: the unit comes back unconfigured (short path: status, configure); stall: the unit
  // is silent (commands queue up) and answers them when it wakes (short path).
  for (const Case c : {Case{"disconnect", 5.0}, Case{"powercycle", 5.0}, Case{"stall", 6.0}}) {
    SCOPED_TRACE(c.fault);
    const size_t n = collector.size();
    const auto t_fault = SteadyClock::now();
    f.emulator->Control(std::string("fault ") + c.fault + " " + std::to_string(c.seconds));
    ASSERT_TRUE(WaitUntil([&] { return collector.FirstAfterGap(n, 1.0).has_value(); }, 30.0));
    const double since_back =
        std::chrono::duration<double>(*collector.FirstAfterGap(n, 1.0) - t_fault).count() - c.seconds;
    std::cout << c.fault << " " << c.seconds << " s: reports resumed " << since_back
              << " s after the device came back\n";
    // 2 s is the requirement; the margin over the expected 0.5-1 s covers a loaded host.
    EXPECT_LT(since_back, 2.0);
    ASSERT_TRUE(collector.WaitForReports(collector.size() + 10, 10.0));
  }
  const DriverStats stats = driver.stats();
  EXPECT_GE(stats.resumes, 1u);
  EXPECT_GE(stats.quick_restarts, 2u);
  driver.Stop();
  ExpectPoses(collector.reports());
}

// A unit that lost power while its port was away (an unplugged or re-enumerating USB adapter) and
// powers up in a configuration a lab saved with ^K: continuous binary output with VRPN's output
// list 2,11,0, but centimetres and the -x hemisphere. Its records cannot be told from the ones the
// driver configured (inches, +x from the vrpn.cfg extra commands). The driver used to resume them
// without a reset and served every position -2.54 times the true one (station 1: 2.06 m off); it
// must stop the unit and configure it again before reporting.
TEST(FastrakDriverWithEmulator, PowerCycledUnitWithSavedSettingsIsReconfigured) {
  Fixture f("fastrak_emulator");
  {
    // The lab's setup and ^K, written on the pty before the driver opens it.
    const std::string link = (f.dir / "fastrak").string();
    const int fd = ::open(link.c_str(), O_WRONLY | O_NOCTTY);
    ASSERT_GE(fd, 0) << link;
    const std::string setup = "O1,2,11,0\rO2,2,11,0\rH1,-1,0,0\rH2,-1,0,0\rufC\x0b";
    ASSERT_EQ(::write(fd, setup.data(), setup.size()), static_cast<ssize_t>(setup.size()));
    ::close(fd);
    ASSERT_TRUE(WaitUntil(
        [&] { return f.emulator->Control("status").find(" saved=1") != std::string::npos; }, 10.0));
  }
  Collector collector;
  FastrakOptions options = f.DriverOptions();
  options.extra_commands = {"H1,1,0,0", "H2,1,0,0"};  // vrpn.cfg: the +x hemisphere
  FastrakDriver driver(options, collector.Callbacks());
  driver.Start();
  ASSERT_TRUE(collector.WaitForReports(10, 15.0));
  ExpectPoses(collector.reports());

  // Unplugged for 1 s; meanwhile the unit is off for 0.3 s and powers up in its saved
  // configuration.
  const size_t n = collector.size();
  const auto t_fault = SteadyClock::now();
  ASSERT_EQ(f.emulator->Control("fault disconnect 1.0"), "ok");
  ASSERT_EQ(f.emulator->Control("fault powercycle 0.3"), "ok");
  ASSERT_TRUE(WaitUntil([&] { return collector.FirstAfterGap(n, 0.5).has_value(); }, 15.0));
  const double since_back =
      std::chrono::duration<double>(*collector.FirstAfterGap(n, 0.5) - t_fault).count() - 1.0;
  std::cout << "disconnect 1 s with a power cycle to saved settings: reports resumed " << since_back
            << " s after the device came back, "
            << collector.SinceOpened(*collector.FirstIndexAfterGap(n, 0.5))
            << " s after the port was reopened\n";
  EXPECT_EQ(driver.stats().resumes, 1u);  // the probe found the saved configuration's stream
  ASSERT_TRUE(collector.WaitForReports(collector.size() + 20, 10.0));
  driver.Stop();
  const std::vector<FastrakReport> reports = collector.reports();
  const std::vector<Rigid3d> poses = TranscriptPoses();
  double worst_m = 0.0;
  size_t wrong = 0;
  for (size_t i = n; i < reports.size(); ++i) {
    const double error_m = (reports[i].position_m - poses[reports[i].sensor].translation).norm();
    worst_m = std::max(worst_m, error_m);
    if (error_m >= kPositionTolM) ++wrong;
  }
  std::cout << "after the power cycle: " << wrong << " of " << reports.size() - n
            << " reports wrong, the largest position error " << worst_m << " m\n";
  EXPECT_EQ(wrong, 0u);
  if (wrong == 0) ExpectPoses(reports);  // (else the count above says it: not one line each)
  EXPECT_NE(f.emulator->Control("status").find("units=inches"), std::string::npos);
}

// The reference waits extras_settle_s (2 s) after the extra commands, in every reset and now in
// every re-configuration of a unit found streaming (above). The unit answers `S` after it has read
// them, so the driver continues at the reply. Here extras_settle_s is 5 s: the first report must
// come well before it (fast timings start in about 0.2 s; 4 s leaves the rest for a loaded host).
// The unit powers up in the -x hemisphere, so right poses show the `H` extras took effect before
// streaming.
TEST(FastrakDriverWithEmulator, ExtraCommandsAreConfirmedByAStatusRoundTrip) {
  Fixture f("fastrak_emulator", 115200, -Eigen::Vector3d::UnitX());
  Collector collector;
  FastrakOptions options = f.DriverOptions();
  options.extra_commands = {"H1,1,0,0", "H2,1,0,0"};
  options.timings.extras_settle_s = 5.0;
  FastrakDriver driver(options, collector.Callbacks());
  const auto started = SteadyClock::now();
  driver.Start();
  ASSERT_TRUE(collector.WaitForReports(10, 15.0));
  driver.Stop();
  const double startup_s = std::chrono::duration<double>(collector.time(0) - started).count();
  std::cout << "extra commands confirmed: first report " << startup_s << " s after Start\n";
  EXPECT_LT(startup_s, 4.0);
  ExpectPoses(collector.reports());
}

// An extra command the unit answers (`P`: one record per active station, in ASCII at power-up,
// since `f` comes after the extras) puts its reply before the reply to the driver's `S`. Those
// replies must be skipped and the status still confirm the extras: taking the first reply would
// refuse it (it is a record, not a status) and wait extras_settle_s (5 s here) with a warning.
// Twice, so the second reset also runs with the unit in binary (records that may hold LF bytes):
// the port is reopened by an unplug. No byte of the replies may reach the record parser.
TEST(FastrakDriverWithEmulator, RepliesToQueryExtraCommandsAreSkipped) {
  Fixture f("fastrak_emulator", 115200, -Eigen::Vector3d::UnitX());
  Collector collector;
  FastrakOptions options = f.DriverOptions();
  options.extra_commands = {"H1,1,0,0", "P", "H2,1,0,0", "P"};
  options.timings.extras_settle_s = 5.0;
  FastrakDriver driver(options, collector.Callbacks());
  const auto started = SteadyClock::now();
  driver.Start();
  ASSERT_TRUE(collector.WaitForReports(10, 15.0));
  const double startup_s = std::chrono::duration<double>(collector.time(0) - started).count();
  std::cout << "query extra commands: first report " << startup_s << " s after Start\n";
  // Fast timings start in about 0.2 s; 4 s leaves the rest of the 5 s wait for a loaded host.
  EXPECT_LT(startup_s, 4.0);

  // Unplugged for 0.5 s: the unit is still streaming binary when the port comes back, so it is
  // configured again (resume) and the `P` replies are binary records.
  const size_t n = collector.size();
  ASSERT_EQ(f.emulator->Control("fault disconnect 0.5"), "ok");
  ASSERT_TRUE(WaitUntil([&] { return collector.FirstIndexAfterGap(n, 0.3).has_value(); }, 15.0));
  const double reopened_s = collector.SinceOpened(*collector.FirstIndexAfterGap(n, 0.3));
  std::cout << "query extra commands: reopen to first report " << reopened_s << " s\n";
  EXPECT_LT(reopened_s, 4.0);
  EXPECT_EQ(driver.stats().resumes, 1u);
  EXPECT_TRUE(collector.Logs("after the extra commands").empty())
      << collector.Logs("after the extra commands").front();
  EXPECT_EQ(driver.stats().discarded_bytes, 0u);
  driver.Stop();
  ExpectPoses(collector.reports());
}

// At 300 baud the status reply takes 1.83 s on the line and a record 1.07 s. The short restart
// after a loss polled every restart_poll_s (0.5 s) and read the reply only until the next poll, so
// it never saw a whole one at <= 1200 baud, and its 0.02-0.1 s settle after `c` let the rest of a
// record in flight precede the reply: every stall became a full reset (quick_restarts 0). Now the
// settle covers a record and the poll the reply (FastrakTimings::RestartSettle, RestartPoll).
TEST(FastrakDriverWithEmulator, ShortRestartAtALowBaudRate) {
  Fixture f("fastrak_emulator", 300);
  Collector collector;
  FastrakDriver driver(f.DriverOptions(), collector.Callbacks());
  driver.Start();
  ASSERT_TRUE(collector.WaitForReports(3, 30.0));
  const size_t n = collector.size();
  f.emulator->Control("fault stall 3");
  // Watchdog (2 s), probe (1 s), one poll: settle 2.3 s, the reply 1.8 s, then a record 1.1 s.
  ASSERT_TRUE(WaitUntil([&] { return collector.FirstAfterGap(n, 2.0).has_value(); }, 40.0));
  const DriverStats stats = driver.stats();
  driver.Stop();
  EXPECT_EQ(stats.watchdog_timeouts, 1u);
  EXPECT_EQ(stats.quick_restarts, 1u);
  EXPECT_EQ(stats.resets_started, 1u) << "the stall needed a full reset";
  ExpectPoses(collector.reports());
}

TEST(FastrakTimings, ShortRestartWaitsCoverARecordAndTheReplyAtTheLineRate) {
  const FastrakTimings reference = FastrakTimings::Reference();
  // At 115200 and 9600 baud the configured values hold (a record and a reply take < 0.1 s).
  EXPECT_EQ(reference.RestartSettle(115200), reference.restart_settle_s);
  EXPECT_EQ(reference.RestartPoll(115200), reference.restart_poll_s);
  EXPECT_EQ(reference.RestartSettle(9600), reference.restart_settle_s);
  EXPECT_EQ(reference.RestartPoll(9600), reference.restart_poll_s);
  // 1200 baud: two 34-byte records 0.567 s, plus two 55-byte replies 0.917 s.
  EXPECT_NEAR(reference.RestartSettle(1200), 2 * 340 / 1200.0, 1e-12);
  EXPECT_NEAR(reference.RestartPoll(1200), (2 * 340 + 2 * 550) / 1200.0, 1e-12);
}

}  // namespace
}  // namespace trackcal::fastrak
