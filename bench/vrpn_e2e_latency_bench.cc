// End-to-end latency through the whole trackcal-server path: the Fastrak emulator writes a binary
// record to its pseudo-terminal, the Fastrak driver reads and parses it, the correction runs, the
// server sends it, and a VRPN client decodes the Pos_Quat. The emulator's pose source numbers its
// records in the position (x = 0.1 m + 0.5 mm * (n mod 1200), z = 0.2 m + 0.5 mm * (n / 1200), far
// coarser than the record's float precision) and notes when each was generated. The emulator runs
// unpaced (baud 0), so each record is written to the pty at once: the figures are the software
// path's, without the 2.8 ms a 32-byte record spends on a 115200 baud line (the paced emulator
// releases a record's bytes as they complete on the line, as a real unit does).
//
// The clients run in a separate process (bench/vrpn_bench_clients.h), each with its own thread, as
// separate client programs would. 4 stations (a Fastrak's 120 records/s shared, 30 Hz each); 1, 8
// and 32 clients over lob/UDP and direct TCP; each model kind a calibration file holds, against
// pass-through (no calibration) in the same run: a degree-4 polynomial and a 21^3 trilinear LUT
// with zero position terms (so the record number survives), and a physical model of the paper room
// (the emulator then reports what a tracker in that room reports for the numbered pose, and the
// server's inverse must recover it to within 0.25 mm, else the row receives nothing and the program
// exits 1). Prints p50/p99/max and the p50 as a ratio to pass-through's row, missing reports
// (records generated in the window that a client never decoded), the server's own share (srv_*:
// from the driver's hand-over to the last client's send() returning) and the records per fan-out
// (how many records one serial read delivered). Then the correction's own cost per pose, and the
// recovery figures: unplug, power cycle and stall of the emulated unit with the default (reference)
// timings -> first report after the unit answers again; exit status 1 if one takes 2 s or more (the
// issue's requirement).
//
//   vrpn_e2e_latency_bench [seconds_per_configuration=5] [realtime_priority=0] [skip_recovery=0]

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <ctime>
#include <map>
#include <mutex>
#include <string_view>
#include <thread>
#include <vector>

#include "bench/paper_room.h"
#include "bench/vrpn_bench_clients.h"
#include "core/calibration_file.h"
#include "core/field.h"
#include "core/file_util.h"
#include "core/lut.h"
#include "core/physical_correction.h"
#include "core/polynomial.h"
#include "core/tracker_solver.h"
#include "sim/emulator/emulator.h"
#include "vrpn_server/app/app.h"
#include "vrpn_server/app/calibration_corrector.h"
#include "vrpn_server/app/fastrak_source.h"
#include "vrpn_server/fastrak/driver.h"

namespace trackcal::vrpn {
namespace {

using bench::Clock;
constexpr std::size_t kMaxRecords = 1 << 22;
// z < 0: inside the physical kind's room (bench/bench_physical.cc's region of reports), 0.5 m or
// more from the transmitter and 0.8 m from its nearest object.
constexpr double kBaseX = 0.1, kBaseZ = -0.5, kStep = 5e-4;
constexpr std::int64_t kPerRow = 1200;

// Numbers every generated record and notes when it was generated (in the table shared with the
// client process).
class NumberedSource : public emulator::PoseSource {
 public:
  explicit NumberedSource(bench::ClientProcess* clients) : clients_(clients) {}
  Rigid3d TruePose(int station, double /*t_s*/) override {
    const std::int64_t n = next_.load();
    clients_->sent_ns(static_cast<std::size_t>(n)) = bench::NowNs();
    next_.store(n + 1);
    return Rigid3d(Eigen::Quaterniond::Identity(),
                   Eigen::Vector3d(kBaseX + kStep * static_cast<double>(n % kPerRow), 0.05 * station,
                                   kBaseZ + kStep * static_cast<double>(n / kPerRow)));
  }
  // The number the next record will get.
  std::int64_t next() const { return next_.load(); }

 private:
  bench::ClientProcess* clients_;
  std::atomic<std::int64_t> next_{0};
};

std::int64_t NumberOf(const Eigen::Vector3d& p) {
  const double k = std::round((p.x() - kBaseX) / kStep);
  const double m = std::round((p.z() - kBaseZ) / kStep);
  if (k < 0 || k >= kPerRow || m < 0) return -1;
  return static_cast<std::int64_t>(k) + kPerRow * static_cast<std::int64_t>(m);
}

std::int64_t RecordNumber(const TrackerReport& r) {
  return NumberOf(r.transmitter_from_receiver.translation);
}

// What a Fastrak in the room reports for a receiver truly at `true_pose` (its free-space solver on
// the distorted signal, no noise); the true pose itself while off. In the room the record's time
// is noted again after the solve: the emulator's physics (~15 us) is not the server's latency.
class RoomTracker : public emulator::MeasurementModel {
 public:
  explicit RoomTracker(bench::ClientProcess* clients) : clients_(clients) {}
  Rigid3d Reported(int /*station*/, const Rigid3d& true_pose, double /*t_s*/) override {
    if (!in_room_.load()) return true_pose;
    const Rigid3d reported = Measure(true_pose);
    const std::int64_t n = NumberOf(true_pose.translation);
    if (n >= 0) clients_->sent_ns(static_cast<std::size_t>(n)) = bench::NowNs();
    return reported;
  }
  static Rigid3d Measure(const Rigid3d& true_pose) {
    static const FieldModel field = PaperRoomField();
    const TrackerSolution s = SolveFreeSpacePose(
        SignalMatrix<double>(PaperRoomGain(), true_pose.rotation.toRotationMatrix(),
                             field.Field<double>(true_pose.translation)));
    return s.transmitter_from_receiver;
  }
  void set_in_room(bool in_room) { in_room_.store(in_room); }

 private:
  bench::ClientProcess* clients_;
  std::atomic<bool> in_room_{false};
};

// A model kind the server may serve: no calibration (pass-through, the baseline) or one file.
enum class Kind { kPassThrough, kPolynomial4, kLut21, kPhysical };
const char* KindName(Kind kind) {
  switch (kind) {
    case Kind::kPassThrough:
      return "off";
    case Kind::kPolynomial4:
      return "poly4";
    case Kind::kLut21:
      return "lut21";
    case Kind::kPhysical:
      return "physical";
  }
  return "?";
}

std::vector<double> Axis(double first, double last, int n) {
  std::vector<double> a(n);
  for (int i = 0; i < n; ++i) a[i] = first + (last - first) * i / (n - 1);
  return a;
}

void WriteCalibration(const std::filesystem::path& path, Kind kind) {
  Calibration cal;
  if (kind == Kind::kPolynomial4) {
    const int degree = 4;
    const int terms = NumPolynomialTerms(degree);
    std::vector<double> position(3 * terms, 0.0), orientation(3 * terms);
    for (int i = 0; i < 3 * terms; ++i) orientation[i] = 1e-4 * std::sin(0.37 * i);
    cal.chain.Append(PolynomialCorrection::FromPositionAndOrientation(
        degree, Eigen::Vector3d::Zero(), Eigen::Vector3d::Ones(), position, orientation));
  } else if (kind == Kind::kLut21) {
    // 21 nodes per axis around the numbered poses, as bench/bench_correction.cc's BM_Lut21.
    LutGrid grid({Axis(-0.1, 0.9, 21), Axis(-0.5, 0.5, 21), Axis(-0.8, 0.2, 21)});
    const std::size_t nodes = static_cast<std::size_t>(grid.num_nodes());
    std::vector<double> position(3 * nodes, 0.0), orientation(3 * nodes);
    for (std::size_t i = 0; i < orientation.size(); ++i) orientation[i] = 1e-4 * std::sin(0.37 * i);
    cal.chain.Append(
        TrilinearLutCorrection::FromPositionAndOrientation(std::move(grid), position, orientation));
  } else if (kind == Kind::kPhysical) {
    cal.chain.Append(PhysicalCorrection(PaperRoomField(), PaperRoomGain()).Clone());
  }
  CalibratedVolume volume;
  volume.min = Eigen::Vector3d(-1, -1, -1);
  volume.max = Eigen::Vector3d(1, 1, 1);
  cal.chain.SetVolume(volume);
  cal.provenance.tool = "vrpn_e2e_latency_bench";
  cal.provenance.tool_version = "0";
  cal.provenance.created_utc = CurrentUtcTimestamp();
  cal.provenance.inputs.push_back({"none", Sha256Hex("bench"), "calibration_capture"});
  std::filesystem::remove(path);
  WriteCalibrationFile(path, cal);
}

// Fault `fault` of `seconds` on an emulated unit driven with the default (reference) timings;
// returns the time from the unit answering again (port back, power on, stall over) to the first
// report after the silence.
double RecoverySeconds(emulator::BackgroundEmulator& emu, const std::string& port, const std::string& fault,
                       double seconds) {
  std::mutex mutex;
  std::vector<Clock::time_point> times;
  fastrak::FastrakOptions fo;
  fo.port = port;
  fo.timings = fastrak::FastrakTimings::Reference();
  fastrak::FastrakDriver::Callbacks cb;
  cb.on_report = [&](const fastrak::FastrakReport&) {
    std::lock_guard<std::mutex> lock(mutex);
    times.push_back(Clock::now());
  };
  fastrak::FastrakDriver driver(fo, cb);
  driver.Start();
  auto count = [&] {
    std::lock_guard<std::mutex> lock(mutex);
    return times.size();
  };
  const auto start_deadline = Clock::now() + std::chrono::seconds(30);
  while (count() < 10 && Clock::now() < start_deadline) std::this_thread::sleep_for(std::chrono::milliseconds(20));
  const std::size_t before = count();
  const auto t_fault = Clock::now();
  emu.Control("fault " + fault + " " + std::to_string(seconds));
  const auto back = t_fault + std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(seconds));
  const auto deadline = back + std::chrono::seconds(60);
  double result = NAN;
  while (std::isnan(result) && Clock::now() < deadline) {
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
    std::lock_guard<std::mutex> lock(mutex);
    for (std::size_t i = std::max<std::size_t>(before, 1); i < times.size(); ++i) {
      if (times[i] - times[i - 1] >= std::chrono::seconds(1)) {
        result = std::chrono::duration<double>(times[i] - back).count();
        break;
      }
    }
  }
  driver.Stop();
  return result;
}

}  // namespace
}  // namespace trackcal::vrpn

int main(int argc, char** argv) {
  using namespace trackcal;
  using namespace trackcal::vrpn;
  // `--help` (or any word) was read by atof as 0 s per row: every row failed after a full run.
  const char* usage =
      "usage: vrpn_e2e_latency_bench [SECONDS_PER_ROW (default 5)] [RT_PRIORITY (default 0)] "
      "[SKIP_RECOVERY 0|1]\n";
  char* end = nullptr;
  const double seconds = argc > 1 ? std::strtod(argv[1], &end) : 5.0;
  if (argc > 4 || (argc > 1 && (end == argv[1] || *end != '\0' || !(seconds > 0.0) ||
                                !std::isfinite(seconds)))) {
    std::fputs(usage, argc > 1 && std::string_view(argv[1]) == "--help" ? stdout : stderr);
    return argc > 1 && std::string_view(argv[1]) == "--help" ? 0 : 2;
  }
  const int rt = argc > 2 ? std::atoi(argv[2]) : 0;
  const bool skip_recovery = argc > 3 && std::atoi(argv[3]) != 0;
  // Forks the client process first, before any thread exists.
  bench::ClientProcess client_process(kMaxRecords, RecordNumber);
  const auto dir = std::filesystem::temp_directory_path() / ("vrpn_e2e_bench_" + std::to_string(::getpid()));
  std::filesystem::create_directories(dir);
  const std::vector<Kind> kinds = {Kind::kPassThrough, Kind::kPolynomial4, Kind::kLut21,
                                   Kind::kPhysical};
  for (Kind kind : kinds) {
    if (kind != Kind::kPassThrough)
      WriteCalibration(dir / (std::string(KindName(kind)) + ".json"), kind);
  }

  auto source = std::make_unique<NumberedSource>(&client_process);
  NumberedSource* numbered = source.get();
  auto room_model = std::make_unique<RoomTracker>(&client_process);
  RoomTracker* room = room_model.get();
  emulator::EmulatorOptions eo;
  eo.device.num_stations = 4;
  eo.baud = 0;  // records written whole at once: software latency only (see the top comment)
  emulator::BackgroundEmulator emu(eo, std::move(source), std::move(room_model));

  std::printf(
      "emulator record -> client decode (clients in a separate process), 4 stations x 30 Hz, %.0f "
      "s per "
      "row, network thread RT priority %d; ratio = p50 / pass-through's p50 (correction off) of "
      "the same "
      "clients and mode in this run\n",
      seconds, rt);
  std::printf("%-8s %-5s %-10s %10s %10s %10s %7s %9s %8s %12s %12s %10s\n", "clients", "mode",
              "correction", "p50[us]", "p99[us]", "max[us]", "ratio", "received", "missing",
              "srv_p50[us]", "srv_p99[us]", "per_fanout");
  int status = 0;
  std::map<std::pair<bool, int>, double> pass_through_p50;
  for (Kind kind : kinds) {
    TrackerSetup setup;
    setup.name = "Tracker0";
    setup.num_sensors = 4;
    setup.origin = "bench";
    if (kind != Kind::kPassThrough)
      setup.calibration = dir / (std::string(KindName(kind)) + ".json");
    room->set_in_room(kind == Kind::kPhysical);
    fastrak::FastrakOptions fo;
    fo.port = emu.initial_device_path();
    fo.timings = fastrak::FastrakTimings::Fast();
    setup.make_source = [fo] { return MakeFastrakSource(fo); };
    AppOptions ao;
    ao.server.bind_address = "127.0.0.1";
    ao.server.port = 0;
    ao.server.realtime_priority = rt;
    TrackcalServerApp app({setup}, ao, LoadCalibrationCorrector, [](const std::string&) {});
    app.Start();
    for (bool lob : {true, false}) {
      for (int n : {1, 8, 32}) {
        if (!client_process.Connect(app.port(), n, lob)) {
          std::printf("%-8d %-5s clients not ready within 30 s\n", n, lob ? "lob" : "tcp");
        }
        std::this_thread::sleep_for(std::chrono::milliseconds(200));
        app.server().TakeFanoutMicros();
        const std::uint64_t published0 = app.server().stats().reports_published;
        const std::int64_t begin = numbered->next();
        std::this_thread::sleep_for(std::chrono::duration<double>(seconds));
        const std::int64_t end = numbered->next();
        std::this_thread::sleep_for(std::chrono::milliseconds(300));  // records in flight arrive
        const auto fanout = app.server().TakeFanoutMicros();
        const std::uint64_t published = app.server().stats().reports_published - published0;
        const bench::ClientRunResult r = client_process.Finish(begin, end);
        const std::vector<double> fanout_d(fanout.begin(), fanout.end());
        if (kind == Kind::kPassThrough) pass_through_p50[{lob, n}] = r.p50_us;
        const double ratio = r.p50_us / pass_through_p50[{lob, n}];
        std::printf(
            "%-8d %-5s %-10s %10.1f %10.1f %10.1f %7.2f %9llu %8llu %12.1f %12.1f %10.2f\n", n,
            lob ? "lob" : "tcp", KindName(kind), r.p50_us, r.p99_us, r.max_us, ratio,
            static_cast<unsigned long long>(r.received), static_cast<unsigned long long>(r.missing),
            bench::Percentile(fanout_d, 0.5), bench::Percentile(fanout_d, 0.99),
            fanout.empty() ? NAN
                           : static_cast<double>(published) / static_cast<double>(fanout.size()));
        std::fflush(stdout);
        if (r.received == 0) {
          // Nothing decoded carried its record's number: the correction did not give back the
          // numbered pose (or nothing was served).
          std::printf("  FAILED: no report of this row carried its record's number\n");
          status = 1;
        }
      }
    }
    app.Stop();
  }
  room->set_in_room(false);

  // Each kind's own cost per pose through the server's corrector (LoadCalibrationCorrector, what
  // TrackerDevice::OnReports calls per report), on the reports the emulator sends for numbered
  // poses, against the same loop without correction and as a ratio to the polynomial's.
  {
    std::vector<Rigid3d> plain, in_room;
    for (int i = 0; i < 1200; ++i) {
      const Rigid3d pose(Eigen::Quaterniond::Identity(),
                         Eigen::Vector3d(kBaseX + 5e-4 * i, 0.05 * (1 + i % 4), kBaseZ));
      plain.push_back(pose);
      in_room.push_back(RoomTracker::Measure(pose));
    }
    const int n = 200000;
    double sink = 0;
    // Thread CPU time: on a shared machine the wall time of such a loop varied 2x between runs.
    auto cpu_now = [] {
      timespec ts{};
      ::clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts);
      return 1e6 * static_cast<double>(ts.tv_sec) + 1e-3 * static_cast<double>(ts.tv_nsec);
    };
    auto time_loop = [&](const std::vector<Rigid3d>& reports, const PoseCorrector* corrector) {
      const double t0 = cpu_now();
      for (int i = 0; i < n; ++i) {
        const Rigid3d& r = reports[static_cast<std::size_t>(i) % reports.size()];
        sink += corrector ? corrector->CorrectWithFlag(r).pose.rotation.x() : r.rotation.x();
      }
      return (cpu_now() - t0) / n;
    };
    const double loop_us = time_loop(plain, nullptr);
    double poly_us = NAN;
    for (Kind kind : kinds) {
      if (kind == Kind::kPassThrough) continue;
      const auto corrector =
          LoadCalibrationCorrector(dir / (std::string(KindName(kind)) + ".json"), std::nullopt);
      const double us = time_loop(kind == Kind::kPhysical ? in_room : plain, corrector.get());
      if (kind == Kind::kPolynomial4) poly_us = us;
      std::printf(
          "correction per pose, %-8s: %.3f us CPU (%.2fx the polynomial's; loop without it: %.3f "
          "us)\n",
          KindName(kind), us, us / poly_us, loop_us);
    }
    std::printf("(checksum %.3g)\n", sink);
  }
  if (!skip_recovery) {
    emulator::EmulatorOptions ro;
    ro.device.num_stations = 2;
    ro.link_path = (dir / "fastrak").string();
    emulator::BackgroundEmulator recovery_emu(ro, std::make_unique<emulator::StaticPoseSource>(std::vector<Rigid3d>{
                                                      Rigid3d(), Rigid3d()}));
    std::printf("recovery with the default (reference) timings: first report after the unit answers again "
                "(requirement < 2 s; the reference: 40 s after a 5 s unplug)\n");
    for (const auto& [fault, s] : std::vector<std::pair<std::string, double>>{
             {"disconnect", 5.0}, {"powercycle", 5.0}, {"stall", 6.0}}) {
      const double t = RecoverySeconds(recovery_emu, ro.link_path, fault, s);
      const bool ok = t < 2.0;
      std::printf("  %-10s %.0f s: %.2f s %s\n", fault.c_str(), s, t, ok ? "ok" : "FAILED (>= 2 s)");
      if (!ok) status = 1;
    }
  }
  std::filesystem::remove_all(dir);
  return status;
}
