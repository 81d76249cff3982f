// The VRPN server serving many clients: per report, the time from the device thread's hand-over
// (TrackerDevice::OnReports, where the Fastrak driver calls in) until the last of N TCP clients has
// decoded it, as a ratio to the same with one client in the same round. The clients run in a
// separate process (bench/vrpn_bench_clients.h), one thread each, as separate client programs
// would; each report carries its sequence number in its header timestamp. 4 stations at 30 Hz (a
// Fastrak's 120 records/s), handed over in one burst per record cycle, no correction: what grows
// with N is the fan-out (one send per client) and the clients' share of the host's cores.
//
//   vrpn_fanout_bench [seconds_per_row=3] [rounds=2] [client counts=1,32,128]
//
// Each round runs every client count in turn, 1 first; each row's ratio is to that round's
// 1-client row, so a change of load between rounds falls on both. Prints per row: the last
// client's p50 / p99 (over the reports every client decoded), the pooled per-client p50, the
// server's own share (hand-over -> the last client's send() returned, per fan-out), and the
// (client, report) pairs never decoded. Exits 1 if a row decodes nothing. docs/benchmarks.md.

#include <cstdio>
#include <cstdlib>
#include <memory>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "bench/vrpn_bench_clients.h"
#include "vrpn_server/server/devices.h"
#include "vrpn_server/server/server.h"

namespace trackcal::vrpn {
namespace {

using bench::Clock;
constexpr std::uint32_t kTagUsec = 777777;  // marks measured reports; warm-up reports use 0
constexpr std::size_t kMaxReports = 1 << 22;

std::int64_t ReportNumber(const TrackerReport& r) {
  return r.time.usec == kTagUsec ? static_cast<std::int64_t>(r.time.sec) : -1;
}

struct Row {
  bench::ClientRunResult clients;
  double server_p50_us = NAN;
  std::uint64_t published = 0;
};

std::uint64_t g_next_seq = 0;  // sequence numbers never repeat within a run

Row RunClients(bench::ClientProcess& process, int num_clients, double seconds) {
  auto catalog = std::make_shared<ServerCatalog>();
  TrackerSpec spec;
  spec.name = "Tracker0";
  spec.num_sensors = 4;
  const int tracker = catalog->AddTracker(spec);
  ServerOptions options;
  options.bind_address = "127.0.0.1";
  options.port = 0;
  auto server = std::make_unique<VrpnServer>(catalog, options, [](const std::string&) {});
  server->Start();
  TrackerDevice device(server.get(), tracker, std::nullopt);

  // Warm-up reports (not measured) until every client is connected and streaming.
  std::atomic<bool> warming{true};
  std::thread warm([&] {
    while (warming) {
      device.OnReport(0, Rigid3d(), Timestamp{0, 0});
      std::this_thread::sleep_for(std::chrono::milliseconds(20));
    }
  });
  const bool ready = process.Connect(server->port(), num_clients, /*lob=*/false);
  warming = false;
  warm.join();
  if (!ready) std::printf("(%d clients not all ready within 30 s)\n", num_clients);
  std::this_thread::sleep_for(std::chrono::milliseconds(200));
  server->TakeFanoutMicros();
  const std::uint64_t begin = g_next_seq;
  std::uint64_t seq = begin;
  const auto period = std::chrono::microseconds(33333);  // 30 Hz per station
  auto next = Clock::now();
  const auto end =
      next + std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(seconds));
  std::vector<SensorReport> batch(4);
  while (Clock::now() < end && seq + 4 < kMaxReports) {
    const std::int64_t now = bench::NowNs();
    for (int s = 0; s < 4; ++s) {
      batch[s] = SensorReport{
          s, Rigid3d(Eigen::Quaterniond::Identity(), Eigen::Vector3d(0.3 + 0.01 * s, 0.1, 0.2)),
          Timestamp{static_cast<std::uint32_t>(seq + s), kTagUsec}};
      process.sent_ns(seq + s) = now;
    }
    device.OnReports(batch);
    seq += 4;
    next += period;
    std::this_thread::sleep_until(next);
  }
  g_next_seq = seq;
  std::this_thread::sleep_for(std::chrono::milliseconds(300));  // let the last reports arrive
  Row row;
  row.clients = process.Finish(static_cast<std::int64_t>(begin), static_cast<std::int64_t>(seq));
  row.published = seq - begin;
  const std::vector<float> fanout = server->TakeFanoutMicros();
  row.server_p50_us = bench::Percentile(std::vector<double>(fanout.begin(), fanout.end()), 0.50);
  return row;
}

std::vector<int> ParseCounts(const char* text) {
  std::vector<int> counts;
  std::stringstream in(text);
  std::string item;
  while (std::getline(in, item, ',')) counts.push_back(std::atoi(item.c_str()));
  return counts;
}

}  // namespace
}  // namespace trackcal::vrpn

int main(int argc, char** argv) {
  using namespace trackcal::vrpn;
  const double seconds = argc > 1 ? std::atof(argv[1]) : 3.0;
  const int rounds = argc > 2 ? std::atoi(argv[2]) : 2;
  std::vector<int> counts = argc > 3 ? ParseCounts(argv[3]) : std::vector<int>{1, 32, 128};
  if (argc > 4 || !(seconds > 0) || rounds < 1 || counts.empty() || counts.front() != 1) {
    std::fprintf(stderr,
                 "usage: vrpn_fanout_bench [seconds_per_row=3] [rounds=2] [client counts=1,32,128]"
                 " (comma-separated, starting with 1: the baseline)\n");
    return 2;
  }
  for (int n : counts) {
    if (n < 1) {
      std::fprintf(stderr, "vrpn_fanout_bench: a client count must be at least 1\n");
      return 2;
    }
  }
  // Forks the client process first, before any thread exists.
  bench::ClientProcess process(kMaxReports, ReportNumber);
  std::printf(
      "VRPN server fan-out, OnReports -> last client's decode (TCP clients in a separate process), "
      "loopback, 4 stations x 30 Hz in one burst, no correction, %.1f s per row, %d round(s)\n",
      seconds, rounds);
  std::printf("%-5s %-8s %12s %12s %9s %9s %12s %12s %9s %8s\n", "round", "clients", "last_p50[us]",
              "last_p99[us]", "ratio50", "ratio99", "all_p50[us]", "srv_p50[us]", "reports",
              "missing");
  bool decoded_everywhere = true;
  for (int round = 1; round <= rounds; ++round) {
    Row baseline;
    for (int n : counts) {
      const Row row = RunClients(process, n, seconds);
      if (n == 1) baseline = row;
      decoded_everywhere = decoded_everywhere && row.clients.complete > 0;
      std::printf("%-5d %-8d %12.1f %12.1f %9.2f %9.2f %12.1f %12.1f %9llu %8llu\n", round, n,
                  row.clients.last_p50_us, row.clients.last_p99_us,
                  row.clients.last_p50_us / baseline.clients.last_p50_us,
                  row.clients.last_p99_us / baseline.clients.last_p99_us, row.clients.p50_us,
                  row.server_p50_us, static_cast<unsigned long long>(row.published),
                  static_cast<unsigned long long>(row.clients.missing));
      std::fflush(stdout);
    }
  }
  if (!decoded_everywhere) {
    std::printf("a row had no report that every client decoded\n");
    return 1;
  }
  return 0;
}
