// End-to-end latency through the whole trackcal-server path: the Fastrak emulator writes a binary
// record to its pseudo-terminal, the Fastrak driver reads and parses it, the correction runs, the
// server sends it, and a VRPN client decodes the Pos_Quat. The emulator's pose source numbers its
// records in position x (x = 0.1 m + 0.5 mm * n, far coarser than the record's float precision)
// and notes when each was generated (it is written to the pty at once; a 32-byte record at
// 115200 baud then keeps the emulated line busy for 2.8 ms, which paces the next one, not this one).
//
// 4 stations (a Fastrak's 120 records/s shared, 30 Hz each); 1, 8 and 32 clients over lob/UDP and
// direct TCP; correction off and on (a degree-4 polynomial from a calibration file, with zero
// position terms so the record number survives). Prints p50/p99/max and missing reports, and the
// server's own share (srv_*: from the driver's hand-over to the last client's send() returning).
//
//   vrpn_e2e_latency_bench [seconds_per_configuration=5] [realtime_priority=0]

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <mutex>
#include <thread>
#include <vector>

#include "core/calibration_file.h"
#include "core/file_util.h"
#include "core/polynomial.h"
#include "sim/emulator/emulator.h"
#include "vrpn_server/app/app.h"
#include "vrpn_server/app/calibration_corrector.h"
#include "vrpn_server/app/fastrak_source.h"

namespace trackcal::vrpn {
namespace {

using Clock = std::chrono::steady_clock;
constexpr std::size_t kMaxRecords = 1 << 20;
constexpr double kBaseX = 0.1, kStepX = 5e-4;

// Numbers every generated record and notes when it was generated.
class NumberedSource : public emulator::PoseSource {
 public:
  explicit NumberedSource(std::vector<std::atomic<std::int64_t>>* generated_ns) : generated_ns_(generated_ns) {}
  Rigid3d TruePose(int station, double /*t_s*/) override {
    const std::size_t n = next_++ % 1200;  // x stays below 0.7 m; numbers wrap every 10 s
    (*generated_ns_)[n] = Clock::now().time_since_epoch().count();
    return Rigid3d(Eigen::Quaterniond::Identity(),
                   Eigen::Vector3d(kBaseX + kStepX * static_cast<double>(n), 0.05 * station, 0.2));
  }

 private:
  std::vector<std::atomic<std::int64_t>>* generated_ns_;
  std::size_t next_ = 0;
};

void WriteCalibration(const std::filesystem::path& path) {
  const int degree = 4;
  const int terms = NumPolynomialTerms(degree);
  std::vector<double> position(3 * terms, 0.0), orientation(3 * terms);
  for (int i = 0; i < 3 * terms; ++i) orientation[i] = 1e-4 * std::sin(0.37 * i);
  Calibration cal;
  cal.chain.Append(PolynomialCorrection::FromPositionAndOrientation(
      degree, Eigen::Vector3d::Zero(), Eigen::Vector3d::Ones(), position, orientation));
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

double Percentile(std::vector<double> v, double q) {
  if (v.empty()) return NAN;
  std::sort(v.begin(), v.end());
  return v[std::min(v.size() - 1, static_cast<std::size_t>(q * (v.size() - 1) + 0.5))];
}

}  // namespace
}  // namespace trackcal::vrpn

int main(int argc, char** argv) {
  using namespace trackcal;
  using namespace trackcal::vrpn;
  const double seconds = argc > 1 ? std::atof(argv[1]) : 5.0;
  const int rt = argc > 2 ? std::atoi(argv[2]) : 0;
  const auto dir = std::filesystem::temp_directory_path() / ("vrpn_e2e_bench_" + std::to_string(::getpid()));
  std::filesystem::create_directories(dir);
  WriteCalibration(dir / "calib.json");

  std::vector<std::atomic<std::int64_t>> generated_ns(kMaxRecords);
  emulator::EmulatorOptions eo;
  eo.device.num_stations = 4;
  emulator::BackgroundEmulator emu(eo, std::make_unique<NumberedSource>(&generated_ns));

  std::printf("emulator record -> client decode, 4 stations x 30 Hz, %.0f s per row, network thread RT priority %d\n",
              seconds, rt);
  std::printf("%-8s %-5s %-10s %10s %10s %10s %9s %8s %12s %12s\n", "clients", "mode", "correction", "p50[us]",
              "p99[us]", "max[us]", "received", "missing", "srv_p50[us]", "srv_p99[us]");
  for (bool correction : {false, true}) {
    TrackerSetup setup;
    setup.name = "Tracker0";
    setup.num_sensors = 4;
    setup.origin = "bench";
    if (correction) setup.calibration = dir / "calib.json";
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
        std::vector<std::vector<double>> lat(n);
        std::vector<std::vector<std::size_t>> got(n);
        std::atomic<bool> measuring{false};
        std::vector<std::unique_ptr<VrpnTrackerClient>> clients;
        for (int c = 0; c < n; ++c) {
          clients.push_back(std::make_unique<VrpnTrackerClient>(
              std::string("Tracker0@") + (lob ? "" : "tcp://") + "127.0.0.1:" + std::to_string(app.port())));
          clients.back()->SetPoseCallback([&, c](const TrackerReport& r) {
            const auto now = Clock::now().time_since_epoch().count();
            if (!measuring) return;
            const double k = std::round((r.transmitter_from_receiver.translation.x() - kBaseX) / kStepX);
            if (k < 0 || k >= 1200) return;
            const auto idx = static_cast<std::size_t>(k);
            lat[c].push_back((now - generated_ns[idx].load()) / 1000.0);
            got[c].push_back(idx);
          });
          clients.back()->Start();
        }
        const auto ready_by = Clock::now() + std::chrono::seconds(30);
        while (Clock::now() < ready_by) {
          bool ready = true;
          for (auto& c : clients) ready = ready && c->pong_received() && c->reports() > 0 && (!lob || c->udp_active());
          if (ready) break;
          std::this_thread::sleep_for(std::chrono::milliseconds(20));
        }
        app.server().TakeFanoutMicros();
        measuring = true;
        std::this_thread::sleep_for(std::chrono::duration<double>(std::min(seconds, 9.0)));
        measuring = false;
        std::this_thread::sleep_for(std::chrono::milliseconds(100));
        for (auto& c : clients) c->Stop();
        const auto fanout = app.server().TakeFanoutMicros();
        const std::vector<double> fanout_d(fanout.begin(), fanout.end());
        // Missing: per client, gaps in the record numbers it received (records come in order).
        std::uint64_t missing = 0, received = 0;
        std::vector<double> all;
        for (int c = 0; c < n; ++c) {
          all.insert(all.end(), lat[c].begin(), lat[c].end());
          received += got[c].size();
          for (std::size_t i = 1; i < got[c].size(); ++i) {
            missing += (got[c][i] + 1200 - got[c][i - 1] - 1) % 1200;
          }
        }
        std::printf("%-8d %-5s %-10s %10.1f %10.1f %10.1f %9llu %8llu %12.1f %12.1f\n", n, lob ? "lob" : "tcp",
                    correction ? "on" : "off", Percentile(all, 0.5), Percentile(all, 0.99),
                    all.empty() ? NAN : *std::max_element(all.begin(), all.end()),
                    static_cast<unsigned long long>(received), static_cast<unsigned long long>(missing),
                    Percentile(fanout_d, 0.5), Percentile(fanout_d, 0.99));
      }
    }
    app.Stop();
  }
  std::filesystem::remove_all(dir);
  return 0;
}
