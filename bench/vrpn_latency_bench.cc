// End-to-end latency of the VRPN server: from the moment a device thread hands a report to the
// server (TrackerDevice::OnReport, where the Fastrak driver calls in) to the moment a client has
// decoded the Pos_Quat. Each report carries its sequence number in its header timestamp (seconds
// field; the correction changes the pose itself, never the timestamp), so every client matches its
// reports to the send times and counts the ones it never got.
//
// Runs 1, 8 and 32 clients (direct TCP and lob/UDP), 4 stations at 30 Hz each (a Fastrak's
// 120 records/s), correction off and on, in one process; prints p50/p99/max per configuration, the
// correction's added cost as a difference against the uncorrected run of the same process, and the
// network thread's CPU use while idle with 32 connected clients.
//
//   vrpn_latency_bench [seconds_per_configuration=5] [realtime_priority=0]
//
// The emulator's pty hop (serial write -> driver read) is not included here; see docs/vrpn.md.

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <memory>
#include <mutex>
#include <thread>
#include <vector>

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

double Percentile(std::vector<double> v, double q) {
  if (v.empty()) return NAN;
  std::sort(v.begin(), v.end());
  const std::size_t i = std::min(v.size() - 1, static_cast<std::size_t>(q * (v.size() - 1) + 0.5));
  return v[i];
}

struct Result {
  double p50_us, p99_us, max_us;
  double server_p50_us, server_p99_us;  // hand-over -> last client's send() returned
  std::uint64_t published, dropped;
};

Result RunConfiguration(int num_clients, bool correction, bool lob, double seconds,
                        std::vector<std::unique_ptr<VrpnTrackerClient>>* keep_clients = nullptr,
                        std::unique_ptr<VrpnServer>* keep_server = nullptr) {
  auto catalog = std::make_shared<ServerCatalog>();
  TrackerSpec spec;
  spec.name = "Tracker0";
  spec.num_sensors = 4;
  const int tracker = catalog->AddTracker(spec);
  ServerOptions options;
  options.bind_address = "127.0.0.1";
  options.port = 0;
  options.realtime_priority = g_realtime_priority;
  auto server = std::make_unique<VrpnServer>(catalog, options, [](const std::string&) {});
  server->Start();
  TrackerDevice device(server.get(), tracker, std::nullopt);
  if (correction) device.SetCorrector(std::make_shared<PolynomialCorrector>());

  const std::size_t max_reports = static_cast<std::size_t>(seconds * 120 * 1.2) + 1000;
  std::vector<std::atomic<std::int64_t>> sent_ns(max_reports);
  // One latency list per client (no shared lock on the clients' threads).
  std::vector<std::vector<double>> latencies(num_clients);
  std::vector<std::vector<char>> seen(num_clients, std::vector<char>(max_reports, 0));
  std::atomic<bool> measuring{false};

  std::vector<std::unique_ptr<VrpnTrackerClient>> clients;
  const std::string port = std::to_string(server->port());
  for (int c = 0; c < num_clients; ++c) {
    clients.push_back(std::make_unique<VrpnTrackerClient>(
        (lob ? "Tracker0@127.0.0.1:" : "Tracker0@tcp://127.0.0.1:") + port));
    clients.back()->SetPoseCallback([&, c](const TrackerReport& r) {
      const auto now = Clock::now().time_since_epoch();
      if (r.time.usec != kTagUsec || r.time.sec >= max_reports) return;  // warm-up reports
      const auto seq = static_cast<std::size_t>(r.time.sec);
      const double us = std::chrono::duration<double, std::micro>(
                            now - std::chrono::nanoseconds(sent_ns[seq].load())).count();
      seen[c][seq] = 1;
      if (measuring) latencies[c].push_back(us);
    });
    clients.back()->Start();
  }
  // Wait for every client (pong) and, in lob mode, for the UDP channel to carry reports.
  const auto deadline = Clock::now() + std::chrono::seconds(30);
  while (Clock::now() < deadline) {
    device.OnReport(0, Rigid3d(), Timestamp{0, 0});
    bool ready = true;
    for (auto& c : clients) ready = ready && c->pong_received() && (!lob || c->udp_active());
    if (ready) break;
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  std::this_thread::sleep_for(std::chrono::milliseconds(200));
  server->TakeFanoutMicros();
  measuring = true;
  std::uint64_t seq = 0;
  const auto period = std::chrono::microseconds(33333);  // 30 Hz per station
  auto next = Clock::now();
  const auto end = next + std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(seconds));
  while (Clock::now() < end && seq + 4 < max_reports) {
    for (int s = 0; s < 4; ++s, ++seq) {
      // A pose inside a typical calibrated volume, so the correction does its normal work.
      const Rigid3d pose(Eigen::Quaterniond::Identity(), Eigen::Vector3d(0.3 + 0.01 * s, 0.1, 0.2));
      sent_ns[seq] = std::chrono::duration_cast<std::chrono::nanoseconds>(Clock::now().time_since_epoch()).count();
      device.OnReport(s, pose, Timestamp{static_cast<std::uint32_t>(seq), kTagUsec});
    }
    next += period;
    std::this_thread::sleep_until(next);
  }
  std::this_thread::sleep_for(std::chrono::milliseconds(500));  // let the last reports arrive
  measuring = false;
  for (auto& c : clients) c->Stop();  // joins the client threads before reading their lists
  Result r{};
  r.published = seq;
  for (int c = 0; c < num_clients; ++c) {
    for (std::uint64_t i = 0; i < seq; ++i) r.dropped += seen[c][i] ? 0 : 1;
  }
  std::vector<double> all;
  for (const auto& l : latencies) all.insert(all.end(), l.begin(), l.end());
  r.p50_us = Percentile(all, 0.50);
  r.p99_us = Percentile(all, 0.99);
  r.max_us = all.empty() ? NAN : *std::max_element(all.begin(), all.end());
  const auto fanout = server->TakeFanoutMicros();
  const std::vector<double> fanout_d(fanout.begin(), fanout.end());
  r.server_p50_us = Percentile(fanout_d, 0.50);
  r.server_p99_us = Percentile(fanout_d, 0.99);
  if (keep_clients && keep_server) {
    for (auto& c : clients) {
      c->SetPoseCallback(nullptr);  // the lists above go out of scope
      c->Start();
    }
    *keep_clients = std::move(clients);
    *keep_server = std::move(server);
  }
  return r;
}

}  // namespace
}  // namespace trackcal::vrpn

int main(int argc, char** argv) {
  using namespace trackcal::vrpn;
  const double seconds = argc > 1 ? std::atof(argv[1]) : 5.0;
  g_realtime_priority = argc > 2 ? std::atoi(argv[2]) : 0;
  std::printf("VRPN end-to-end latency, OnReport -> client decode, loopback, 4 stations x 30 Hz, %.0f s each, "
              "network thread real-time priority %d\n", seconds, g_realtime_priority);
  std::printf("%-8s %-5s %-10s %10s %10s %10s %10s %8s %12s %12s\n", "clients", "mode", "correction",
              "p50[us]", "p99[us]", "max[us]", "reports", "dropped", "srv_p50[us]", "srv_p99[us]");
  for (bool lob : {false, true}) {
    for (int n : {1, 8, 32}) {
      double p50_off = 0;
      for (bool corr : {false, true}) {
        const Result r = RunConfiguration(n, corr, lob, seconds);
        std::printf("%-8d %-5s %-10s %10.1f %10.1f %10.1f %10llu %8llu %12.1f %12.1f", n, lob ? "lob" : "tcp",
                    corr ? "on" : "off", r.p50_us, r.p99_us, r.max_us,
                    static_cast<unsigned long long>(r.published), static_cast<unsigned long long>(r.dropped),
                    r.server_p50_us, r.server_p99_us);
        if (corr) std::printf("   correction adds %.1f us at p50", r.p50_us - p50_off);
        std::printf("\n");
        p50_off = r.p50_us;
      }
    }
  }
  // The correction's own cost, per call, against the device hand-over without correction.
  {
    PolynomialCorrector corrector;
    trackcal::Rigid3d pose(Eigen::Quaterniond::Identity(), Eigen::Vector3d(0.3, 0.1, 0.2));
    const int n = 200000;
    const auto t0 = std::chrono::steady_clock::now();
    double sink = 0;
    for (int i = 0; i < n; ++i) {
      pose.translation.x() = 0.3 + 1e-7 * i;
      sink += corrector.Correct(pose).translation.y();
    }
    const auto t1 = std::chrono::steady_clock::now();
    std::printf("correction (%s): %.2f us per pose (checksum %.3g)\n", corrector.Describe().c_str(),
                std::chrono::duration<double, std::micro>(t1 - t0).count() / n, sink);
  }
  // Idle: 32 connected clients, no reports.
  std::vector<std::unique_ptr<VrpnTrackerClient>> clients;
  std::unique_ptr<VrpnServer> server;
  RunConfiguration(32, false, false, 0.5, &clients, &server);
  const double cpu0 = server->NetworkThreadCpuSeconds();
  std::this_thread::sleep_for(std::chrono::seconds(3));
  const double cpu1 = server->NetworkThreadCpuSeconds();
  std::printf("idle, 32 clients connected: network thread CPU %.3f %% over 3 s\n", 100.0 * (cpu1 - cpu0) / 3.0);
  for (auto& c : clients) c->Stop();
  return 0;
}
