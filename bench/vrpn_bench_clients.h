// VRPN latency benchmarks: the clients run in a separate process, so decoding in 32 clients does
// not share the server's threads and locks (it still shares the host's cores; docs/vrpn.md).
//
// ClientProcess forks at construction (call it before any thread is started: the child must not
// inherit locked mutexes). The child waits for commands on a pipe: connect N clients (TCP or lob)
// to a port, record what they decode, and at the end report latency percentiles and missing
// reports for a range of sequence numbers. Send times live in a table shared by both processes
// (MAP_SHARED), indexed by the report's sequence number; the clocks are CLOCK_MONOTONIC
// (steady_clock), which both processes share.

#pragma once

#include <sys/mman.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <functional>
#include <memory>
#include <mutex>
#include <stdexcept>
#include <string>
#include <thread>
#include <vector>

#include "vrpn_server/client/tracker_client.h"

namespace trackcal::vrpn::bench {

using Clock = std::chrono::steady_clock;

inline std::int64_t NowNs() {
  return std::chrono::duration_cast<std::chrono::nanoseconds>(Clock::now().time_since_epoch())
      .count();
}

inline double Percentile(std::vector<double> v, double q) {
  if (v.empty()) return NAN;
  std::sort(v.begin(), v.end());
  return v[std::min(v.size() - 1,
                    static_cast<std::size_t>(q * static_cast<double>(v.size() - 1) + 0.5))];
}

struct ClientRunResult {
  double p50_us = NAN;
  double p99_us = NAN;
  double max_us = NAN;
  std::uint64_t received = 0;  // reports with a sequence number in the range, over all clients
  std::uint64_t missing = 0;   // (client, sequence number in the range) pairs never decoded
  std::int32_t ready = 0;      // all clients connected (and on UDP in lob mode) in time
  // Per report: the time until the last client had decoded it (the slowest client's latency), over
  // the reports in the range that every client decoded (`complete` of them).
  double last_p50_us = NAN;
  double last_p99_us = NAN;
  std::uint64_t complete = 0;
};

class ClientProcess {
 public:
  // Sequence number of a decoded report, or -1 for reports that are not measured.
  using SeqFunction = std::function<std::int64_t(const TrackerReport&)>;

  ClientProcess(std::size_t table_size, SeqFunction seq)
      : table_size_(table_size), seq_(std::move(seq)) {
    void* mem = ::mmap(nullptr, table_size * sizeof(std::atomic<std::int64_t>),
                       PROT_READ | PROT_WRITE, MAP_SHARED | MAP_ANONYMOUS, -1, 0);
    if (mem == MAP_FAILED) throw std::runtime_error("mmap failed");
    table_ = static_cast<std::atomic<std::int64_t>*>(mem);
    int to_child[2], to_parent[2];
    if (::pipe(to_child) != 0 || ::pipe(to_parent) != 0) throw std::runtime_error("pipe failed");
    pid_ = ::fork();
    if (pid_ < 0) throw std::runtime_error("fork failed");
    if (pid_ == 0) {
      ::close(to_child[1]);
      ::close(to_parent[0]);
      ChildLoop(to_child[0], to_parent[1]);
      ::_exit(0);
    }
    ::close(to_child[0]);
    ::close(to_parent[1]);
    cmd_fd_ = to_child[1];
    reply_fd_ = to_parent[0];
  }

  ~ClientProcess() {
    Command c{};
    c.type = Command::kExit;
    Send(c);
    ::close(cmd_fd_);
    ::close(reply_fd_);
    int status = 0;
    ::waitpid(pid_, &status, 0);
    ::munmap(table_, table_size_ * sizeof(std::atomic<std::int64_t>));
  }

  // Send time [steady ns] of sequence number i; written by the parent before the report leaves.
  std::atomic<std::int64_t>& sent_ns(std::size_t i) { return table_[i % table_size_]; }
  std::size_t table_size() const { return table_size_; }

  // Connects n clients and waits (at most 30 s) until each has had its pong and a report (over
  // UDP in lob mode); reports must be flowing. Returns false if they did not all get there.
  bool Connect(int port, int n, bool lob) {
    Command c{};
    c.type = Command::kConnect;
    c.port = port;
    c.clients = n;
    c.lob = lob ? 1 : 0;
    Send(c);
    std::int32_t ok = 0;
    Read(&ok, sizeof(ok));
    return ok != 0;
  }

  // Stats over the reports with sequence numbers in [begin, end); disconnects the clients.
  ClientRunResult Finish(std::int64_t begin, std::int64_t end) {
    Command c{};
    c.type = Command::kFinish;
    c.begin = begin;
    c.end = end;
    Send(c);
    ClientRunResult r;
    Read(&r, sizeof(r));
    return r;
  }

 private:
  struct Command {
    enum Type : std::int32_t { kConnect, kFinish, kExit } type;
    std::int32_t port, clients, lob;
    std::int64_t begin, end;
  };
  struct Sample {
    std::int64_t seq;
    float us;
  };

  void Send(const Command& c) { [[maybe_unused]] auto n = ::write(cmd_fd_, &c, sizeof(c)); }
  void Read(void* p, std::size_t size) {
    auto* bytes = static_cast<char*>(p);
    std::size_t got = 0;
    while (got < size) {
      const ssize_t n = ::read(reply_fd_, bytes + got, size - got);
      if (n <= 0) throw std::runtime_error("client process died");
      got += static_cast<std::size_t>(n);
    }
  }

  void ChildLoop(int in, int out) {
    std::vector<std::unique_ptr<VrpnTrackerClient>> clients;
    std::vector<std::vector<Sample>> samples;
    std::vector<std::unique_ptr<std::mutex>> locks;
    while (true) {
      Command c{};
      if (::read(in, &c, sizeof(c)) != static_cast<ssize_t>(sizeof(c)) || c.type == Command::kExit)
        return;
      if (c.type == Command::kConnect) {
        samples.assign(static_cast<std::size_t>(c.clients), {});
        for (auto& s : samples) s.reserve(1 << 16);
        locks.clear();
        for (int i = 0; i < c.clients; ++i) locks.push_back(std::make_unique<std::mutex>());
        for (int i = 0; i < c.clients; ++i) {
          clients.push_back(std::make_unique<VrpnTrackerClient>(
              std::string("Tracker0@") + (c.lob ? "" : "tcp://") +
              "127.0.0.1:" + std::to_string(c.port)));
          clients.back()->SetPoseCallback([this, i, &samples, &locks](const TrackerReport& r) {
            const std::int64_t now = NowNs();
            const std::int64_t seq = seq_(r);
            if (seq < 0) return;
            const float us = static_cast<float>(
                static_cast<double>(now - sent_ns(static_cast<std::size_t>(seq)).load()) / 1000.0);
            std::lock_guard<std::mutex> lock(*locks[i]);
            samples[i].push_back(Sample{seq, us});
          });
          clients.back()->Start();
        }
        const auto deadline = Clock::now() + std::chrono::seconds(30);
        bool ready = false;
        while (!ready && Clock::now() < deadline) {
          ready = true;
          for (auto& cl : clients)
            ready =
                ready && cl->pong_received() && cl->reports() > 0 && (!c.lob || cl->udp_active());
          if (!ready) std::this_thread::sleep_for(std::chrono::milliseconds(20));
        }
        const std::int32_t ok = ready ? 1 : 0;
        [[maybe_unused]] auto n = ::write(out, &ok, sizeof(ok));
      } else if (c.type == Command::kFinish) {
        for (auto& cl : clients) cl->Stop();  // joins the client threads
        ClientRunResult r;
        r.ready = 1;
        std::vector<double> all;
        const auto range = static_cast<std::size_t>(std::max<std::int64_t>(c.end - c.begin, 0));
        std::vector<float> last_us(range, -1.0f);  // per report: the slowest client so far
        std::vector<std::uint32_t> clients_seen(range, 0);
        for (auto& s : samples) {
          std::vector<char> seen(range, 0);
          for (const Sample& x : s) {
            if (x.seq < c.begin || x.seq >= c.end) continue;
            all.push_back(x.us);
            const auto k = static_cast<std::size_t>(x.seq - c.begin);
            if (!seen[k]) ++clients_seen[k];
            seen[k] = 1;
            last_us[k] = std::max(last_us[k], x.us);
          }
          for (char v : seen) r.missing += v ? 0 : 1;
        }
        r.received = all.size();
        r.p50_us = Percentile(all, 0.50);
        r.p99_us = Percentile(all, 0.99);
        r.max_us = all.empty() ? NAN : *std::max_element(all.begin(), all.end());
        std::vector<double> last;
        for (std::size_t k = 0; k < range; ++k) {
          if (clients_seen[k] == samples.size()) last.push_back(last_us[k]);
        }
        r.complete = last.size();
        r.last_p50_us = Percentile(last, 0.50);
        r.last_p99_us = Percentile(last, 0.99);
        clients.clear();
        [[maybe_unused]] auto n = ::write(out, &r, sizeof(r));
      }
    }
  }

  std::size_t table_size_;
  SeqFunction seq_;
  std::atomic<std::int64_t>* table_ = nullptr;
  pid_t pid_ = -1;
  int cmd_fd_ = -1;
  int reply_fd_ = -1;
};

}  // namespace trackcal::vrpn::bench
