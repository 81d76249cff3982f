// Latency of the VRPN server alone: from the moment a device thread hands a report to the server
// (TrackerDevice::OnReport / OnReports, where the Fastrak driver calls in) to the moment a client
// has decoded the Pos_Quat. Each report carries its sequence number in its header timestamp
// (seconds field; the correction changes the pose itself, never the timestamp), so every client
// matches its reports to the send times and counts the ones it never got.
//
// The clients run in a separate process (bench/vrpn_bench_clients.h), one thread each, as separate
// client programs would. 1, 8 and 32 clients (direct TCP and lob/UDP), 4 stations at 30 Hz each (a
// Fastrak's 120 records/s) handed over in two ways in the same run:
//   per-report: the 4 stations' reports one by one (OnReport x 4: 4 fan-outs, 4 sends per client),
//   batched:    the 4 reports at once (OnReports: 1 fan-out, 1 send per client),
// i.e. a record burst of 4 stations; correction off and on. Prints p50/p99/max, dropped reports,
// the server's own share (srv_*), the ratios batched / per-report, the correction's cost per
// pose, and the network thread's CPU use while idle with 32 connected clients.
//
//   vrpn_latency_bench [seconds_per_configuration=5] [realtime_priority=0] [direct_fanout=1] [clients]
//
// The emulator's pty hop (serial write -> driver read) is not included here; see
// vrpn_e2e_latency_bench and docs/vrpn.md.

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <ctime>
#include <memory>
#include <mutex>
#include <thread>
#include <vector>

#include "bench/vrpn_bench_clients.h"
#include "core/correction.h"
#include "core/polynomial.h"
#include "vrpn_server/client/tracker_client.h"
#include "vrpn_server/server/devices.h"
#include "vrpn_server/server/server.h"

namespace trackcal::vrpn {
namespace {

using Clock = std::chrono::steady_clock;
// Marks measured reports (header usec field); warm-up reports use 0.
constexpr std::uint32_t kTagUsec = 777777;
int g_realtime_priority = 0;
bool g_direct_fanout = true;
std::vector<int> g_client_counts = {1, 8, 32};

// The runtime correction of a calibration file: core's degree-4 polynomial (35 terms x 6 outputs),
// with small coefficients as a fit produces, inside a calibrated volume.
class PolynomialCorrector : public PoseCorrector {
 public:
  PolynomialCorrector() {
    const int degree = 4;
    std::vector<double> c(6 * NumPolynomialTerms(degree));
    for (std::size_t i = 0; i < c.size(); ++i) c[i] = 1e-4 * std::sin(0.7 * static_cast<double>(i));
    chain_.Append(std::make_unique<PolynomialCorrection>(degree, Eigen::Vector3d(0, 0, 0.2),
                                                         Eigen::Vector3d(0.6, 0.6, 0.6), c));
    CalibratedVolume volume;
    volume.min = Eigen::Vector3d(-0.6, -0.6, -0.4);
    volume.max = Eigen::Vector3d(0.6, 0.6, 0.8);
    chain_.SetVolume(volume);
  }
  Rigid3d Correct(const Rigid3d& reported) const override { return chain_.Apply(reported).pose; }
  std::string Describe() const override { return "core polynomial degree 4 in a calibrated volume"; }

 private:
  CorrectionChain chain_;
};

using bench::Clock;
constexpr std::size_t kMaxReports = 1 << 22;

struct Result {
  bench::ClientRunResult clients;
  double server_p50_us, server_p99_us;  // hand-over -> last client's send() returned
  std::uint64_t published;
};

std::int64_t ReportNumber(const TrackerReport& r) {
  return r.time.usec == kTagUsec ? static_cast<std::int64_t>(r.time.sec) : -1;  // warm-up: not measured
}

std::uint64_t g_next_seq = 0;  // sequence numbers never repeat within a run

Result RunConfiguration(bench::ClientProcess& process, int num_clients, bool correction, bool lob, bool batched,
                        double seconds, std::unique_ptr<VrpnServer>* keep_server = nullptr) {
  auto catalog = std::make_shared<ServerCatalog>();
  TrackerSpec spec;
  spec.name = "Tracker0";
  spec.num_sensors = 4;
  const int tracker = catalog->AddTracker(spec);
  ServerOptions options;
  options.bind_address = "127.0.0.1";
  options.port = 0;
  options.realtime_priority = g_realtime_priority;
  options.direct_fanout = g_direct_fanout;
  auto server = std::make_unique<VrpnServer>(catalog, options, [](const std::string&) {});
  server->Start();
  TrackerDevice device(server.get(), tracker, std::nullopt);
  if (correction) device.SetCorrector(std::make_shared<PolynomialCorrector>());

  // Warm-up reports (not measured) until every client is connected and streaming.
  std::atomic<bool> warming{true};
  std::thread warm([&] {
    while (warming) {
      device.OnReport(0, Rigid3d(), Timestamp{0, 0});
      std::this_thread::sleep_for(std::chrono::milliseconds(20));
    }
  });
  const bool ready = process.Connect(server->port(), num_clients, lob);
  warming = false;
  warm.join();
  if (!ready) std::printf("(clients not all ready within 30 s)\n");
  std::this_thread::sleep_for(std::chrono::milliseconds(200));
  server->TakeFanoutMicros();
  const std::uint64_t begin = g_next_seq;
  std::uint64_t seq = begin;
  const auto period = std::chrono::microseconds(33333);  // 30 Hz per station
  auto next = Clock::now();
  const auto end = next + std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(seconds));
  std::vector<SensorReport> batch(4);
  while (Clock::now() < end && seq + 4 < kMaxReports) {
    const std::int64_t now = bench::NowNs();
    for (int s = 0; s < 4; ++s) {
      // A pose inside a typical calibrated volume, so the correction does its normal work.
      batch[s] = SensorReport{s, Rigid3d(Eigen::Quaterniond::Identity(), Eigen::Vector3d(0.3 + 0.01 * s, 0.1, 0.2)),
                              Timestamp{static_cast<std::uint32_t>(seq + s), kTagUsec}};
      process.sent_ns(seq + s) = now;
    }
    if (batched) {
      device.OnReports(batch);
    } else {
      for (const SensorReport& r : batch) device.OnReport(r.sensor, r.transmitter_from_receiver, r.time);
    }
    seq += 4;
    next += period;
    std::this_thread::sleep_until(next);
  }
  g_next_seq = seq;
  std::this_thread::sleep_for(std::chrono::milliseconds(300));  // let the last reports arrive
  Result r{};
  r.clients = process.Finish(static_cast<std::int64_t>(begin), static_cast<std::int64_t>(seq));
  r.published = seq - begin;
  const auto fanout = server->TakeFanoutMicros();
  const std::vector<double> fanout_d(fanout.begin(), fanout.end());
  r.server_p50_us = bench::Percentile(fanout_d, 0.50);
  r.server_p99_us = bench::Percentile(fanout_d, 0.99);
  if (keep_server) *keep_server = std::move(server);
  return r;
}

}  // namespace
}  // namespace trackcal::vrpn

int main(int argc, char** argv) {
  using namespace trackcal::vrpn;
  const double seconds = argc > 1 ? std::atof(argv[1]) : 5.0;
  g_realtime_priority = argc > 2 ? std::atoi(argv[2]) : 0;
  g_direct_fanout = argc > 3 ? std::atoi(argv[3]) != 0 : true;
  if (argc > 4) g_client_counts = {std::atoi(argv[4])};
  // Forks the client process first, before any thread exists.
  bench::ClientProcess process(kMaxReports, ReportNumber);
  std::printf("VRPN server latency, OnReport(s) -> client decode (clients in a separate process), loopback, "
              "4 stations x 30 Hz, %.0f s each, network thread real-time priority %d, direct fan-out %d\n",
              seconds, g_realtime_priority, g_direct_fanout ? 1 : 0);
  std::printf("%-8s %-5s %-5s %-11s %10s %10s %10s %9s %8s %12s %12s\n", "clients", "mode", "corr", "hand-over",
              "p50[us]", "p99[us]", "max[us]", "reports", "dropped", "srv_p50[us]", "srv_p99[us]");
  for (bool lob : {false, true}) {
    for (int n : g_client_counts) {
      for (bool corr : {false, true}) {
        Result per[2];
        for (bool batched : {false, true}) {
          const Result r = RunConfiguration(process, n, corr, lob, batched, seconds);
          per[batched] = r;
          std::printf("%-8d %-5s %-5s %-11s %10.1f %10.1f %10.1f %9llu %8llu %12.1f %12.1f\n", n,
                      lob ? "lob" : "tcp", corr ? "on" : "off", batched ? "batched" : "per-report", r.clients.p50_us,
                      r.clients.p99_us, r.clients.max_us, static_cast<unsigned long long>(r.published),
                      static_cast<unsigned long long>(r.clients.missing), r.server_p50_us, r.server_p99_us);
        }
        // Client latencies are both counted from the burst's hand-over, so their ratio compares
        // the two; srv_* are per fan-out (one report per-report, four batched): no ratio.
        std::printf("%-8d %-5s %-5s %-11s %10.2f %10.2f\n", n, lob ? "lob" : "tcp", corr ? "on" : "off",
                    "ratio b/p", per[1].clients.p50_us / per[0].clients.p50_us,
                    per[1].clients.p99_us / per[0].clients.p99_us);
        std::fflush(stdout);
      }
    }
  }
  // The correction's own cost, per call, against the same loop without it, in this thread's CPU
  // time: after the forked clients' rows on a loaded machine, wall time read 1.02 us per pose where
  // the CPU time was a fifth of it (2026-12-02, load average 10 on 2 cores).
  {
    PolynomialCorrector corrector;
    trackcal::Rigid3d pose(Eigen::Quaterniond::Identity(), Eigen::Vector3d(0.3, 0.1, 0.2));
    const int n = 200000;
    double sink = 0;
    auto cpu_us = [] {
      timespec ts{};
      ::clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts);
      return 1e6 * static_cast<double>(ts.tv_sec) + 1e-3 * static_cast<double>(ts.tv_nsec);
    };
    const auto w0 = std::chrono::steady_clock::now();
    const double t0 = cpu_us();
    for (int i = 0; i < n; ++i) {
      pose.translation.x() = 0.3 + 1e-7 * i;
      sink += pose.translation.x();
    }
    const double t1 = cpu_us();
    const auto w1 = std::chrono::steady_clock::now();
    for (int i = 0; i < n; ++i) {
      pose.translation.x() = 0.3 + 1e-7 * i;
      sink += corrector.Correct(pose).translation.y();
    }
    const double t2 = cpu_us();
    const auto w2 = std::chrono::steady_clock::now();
    std::printf(
        "correction (%s): %.3f us CPU per pose (loop without it %.3f us; wall %.3f and %.3f "
        "us; checksum %.3g)\n",
        corrector.Describe().c_str(), (t2 - t1) / n, (t1 - t0) / n,
        std::chrono::duration<double, std::micro>(w2 - w1).count() / n,
        std::chrono::duration<double, std::micro>(w1 - w0).count() / n, sink);
  }
  // Idle: 32 connected clients, no reports.
  {
    std::unique_ptr<VrpnServer> server;
    auto catalog = std::make_shared<ServerCatalog>();
    TrackerSpec spec;
    spec.name = "Tracker0";
    spec.num_sensors = 4;
    const int tracker = catalog->AddTracker(spec);
    ServerOptions options;
    options.bind_address = "127.0.0.1";
    options.port = 0;
    server = std::make_unique<VrpnServer>(catalog, options, [](const std::string&) {});
    server->Start();
    TrackerDevice device(server.get(), tracker, std::nullopt);
    std::atomic<bool> warming{true};
    std::thread warm([&] {
      while (warming) {
        device.OnReport(0, trackcal::Rigid3d(), Timestamp{0, 0});
        std::this_thread::sleep_for(std::chrono::milliseconds(20));
      }
    });
    process.Connect(server->port(), 32, false);
    warming = false;
    warm.join();
    std::this_thread::sleep_for(std::chrono::milliseconds(200));
    const double cpu0 = server->NetworkThreadCpuSeconds();
    std::this_thread::sleep_for(std::chrono::seconds(3));
    const double cpu1 = server->NetworkThreadCpuSeconds();
    std::printf("idle, 32 clients connected: network thread CPU %.3f %% over 3 s\n", 100.0 * (cpu1 - cpu0) / 3.0);
    process.Finish(0, 0);
  }
  return 0;
}
