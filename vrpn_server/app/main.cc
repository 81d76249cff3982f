// trackcal-server: a drop-in for vrpn_server that serves corrected (and, on request, raw) tracker
// poses. Usage: see kUsage below and docs/vrpn.md.

#include <arpa/inet.h>
#include <netdb.h>
#include <poll.h>
#include <signal.h>
#include <sys/inotify.h>
#include <sys/signalfd.h>
#include <unistd.h>

#include <charconv>
#include <chrono>
#include <cstring>
#include <filesystem>
#include <iostream>
#include <set>
#include <stdexcept>
#include <string>
#include <vector>

#include "core/printable_text.h"
#include "vrpn_server/app/app.h"
#include "vrpn_server/app/calibration_corrector.h"
#include "vrpn_server/app/config_setup.h"
#include "vrpn_server/config.h"
#include "vrpn_server/net/socket_util.h"

namespace trackcal::vrpn {
namespace {

// How long a stopping server waits for its queued log lines to reach stderr.
constexpr std::chrono::milliseconds kLogFlushTimeout{2000};

constexpr const char* kUsage = R"(usage: trackcal-server [-f vrpn.cfg] [port] [options]

Serves the trackers of a vrpn.cfg over VRPN (TCP and UDP on one port, default 3883), corrected by
the calibration files attached with trackcal_Calibration lines (docs/vrpn.md, docs/vrpn-config.md).

  -f FILE          device configuration (default: vrpn.cfg)
  port             TCP/UDP port (default 3883)
  --bind ADDR      listen on this IPv4 address, or the host name's, only (default 0.0.0.0;
                   vrpn_server's -NIC ADDR too)
  --allow CIDR     accept clients from this network only; repeatable (default: everyone)
  --record DIR     record raw and corrected streams of every tracker to DIR as CSV (DIR is
                   made if missing, like mkdir; earlier recordings are never overwritten)
  --max-clients N  refuse connections beyond N (default 256)
  --max-total-output MIB
                   past MIB MiB of output waiting for all clients together, drop the client
                   with the most waiting (default 64)
  --realtime-priority P
                   run the network thread SCHED_FIFO at priority P (1-99; needs CAP_SYS_NICE)
  -h, --help       this text

Signals: SIGHUP reloads every calibration file (a changed file is also reloaded on its own);
a bad new file is rejected with a logged reason and the previous correction stays active.
Accepted and ignored for vrpn_server compatibility: -warn, -v, -q, -millisleep N, -li F, -lo F.
)";

struct Args {
  std::string config = "vrpn.cfg";
  AppOptions app;
};

// A --bind / -NIC value as a dotted IPv4 address: vrpn_server also takes the name of one of the
// host's interfaces (-NIC myhost.lab), which is looked up here, once, at start.
std::string BindAddress(const std::string& flag, const std::string& text) {
  if (ParseIpv4(text)) return text;
  addrinfo hints{};
  hints.ai_family = AF_INET;
  hints.ai_socktype = SOCK_STREAM;
  addrinfo* found = nullptr;
  const int rc = ::getaddrinfo(text.c_str(), nullptr, &hints, &found);
  if (rc != 0 || found == nullptr) {
    throw std::invalid_argument(flag + " '" + text +
                                "': not an IPv4 address, and the name does not resolve to one (" +
                                ::gai_strerror(rc) + ")");
  }
  char dotted[INET_ADDRSTRLEN] = {};
  const auto* in = reinterpret_cast<const sockaddr_in*>(found->ai_addr);
  ::inet_ntop(AF_INET, &in->sin_addr, dotted, sizeof(dotted));
  ::freeaddrinfo(found);
  std::cerr << "trackcal-server: " << flag << " " << text << ": listening on " << dotted << "\n";
  return dotted;
}

int ParseInt(const std::string& text, const std::string& what, int lo, int hi) {
  int v = 0;
  auto [ptr, ec] = std::from_chars(text.data(), text.data() + text.size(), v);
  if (ec != std::errc() || ptr != text.data() + text.size() || v < lo || v > hi) {
    throw std::invalid_argument(what + " '" + text + "': expected an integer in [" +
                                std::to_string(lo) + ", " + std::to_string(hi) + "]");
  }
  return v;
}

Args ParseArgs(int argc, char** argv) {
  Args a;
  a.app.server.port = kDefaultPort;
  bool port_given = false;
  for (int i = 1; i < argc; ++i) {
    const std::string arg = argv[i];
    auto value = [&](const std::string& name) -> std::string {
      if (i + 1 >= argc) throw std::invalid_argument(name + ": missing value");
      return argv[++i];
    };
    if (arg == "-h" || arg == "--help") {
      std::cout << kUsage;
      std::exit(0);
    } else if (arg == "-f") {
      a.config = value(arg);
    } else if (arg == "--bind" || arg == "-NIC") {
      a.app.server.bind_address = BindAddress(arg, value(arg));
    } else if (arg == "--allow") {
      a.app.server.allow.push_back(value(arg));
    } else if (arg == "--record") {
      a.app.record_dir = value(arg);
    } else if (arg == "--max-clients") {
      a.app.server.max_clients = ParseInt(value(arg), arg, 1, 100000);
    } else if (arg == "--max-total-output") {
      a.app.server.max_total_output_bytes =
          static_cast<std::size_t>(ParseInt(value(arg), arg, 1, 65536)) << 20;
    } else if (arg == "--realtime-priority") {
      a.app.server.realtime_priority = ParseInt(value(arg), arg, 1, 99);
    } else if (arg == "-warn" || arg == "-v" || arg == "-q") {
      std::cerr << "trackcal-server: note: " << arg << " ignored\n";
    } else if (arg == "-millisleep" || arg == "-li" || arg == "-lo") {
      value(arg);
      std::cerr << "trackcal-server: note: " << arg << " ignored (event-driven server, no logging)\n";
    } else if (!arg.empty() && arg[0] != '-' && !port_given) {
      a.app.server.port = ParseInt(arg, "port", 1, 65535);
      port_given = true;
    } else {
      throw std::invalid_argument("unknown argument '" + arg + "' (see --help)");
    }
  }
  a.app.server.Check();
  return a;
}

int Run(int argc, char** argv) {
  Args args = ParseArgs(argc, argv);
  const VrpnConfig config = ReadVrpnConfig(args.config);
  const std::string self_host =
      args.app.server.bind_address == "0.0.0.0" ? "127.0.0.1" : args.app.server.bind_address;
  ConfigSetup setup = SetupFromConfig(config, self_host + ":" + std::to_string(args.app.server.port));
  for (const auto& w : setup.warnings) LogToStderr(w);
  // A same-server pass-through connects from self_host to self_host: without this entry an
  // allow-list of the lab's network refuses it and it waits for ever.
  if (setup.reads_this_server && !args.app.server.allow.empty()) {
    args.app.server.allow.push_back(self_host + "/32");
    LogToStderr("allow-list: admitting " + self_host +
                " for the pass-through of this server's own tracker");
  }
  if (setup.trackers.empty()) {
    throw std::invalid_argument(args.config + ": no device trackcal-server can serve");
  }

  // Signals are handled by the main thread through a signalfd; every thread inherits the mask.
  sigset_t signals;
  sigemptyset(&signals);
  sigaddset(&signals, SIGHUP);
  sigaddset(&signals, SIGUSR1);
  sigaddset(&signals, SIGINT);
  sigaddset(&signals, SIGTERM);
  sigaddset(&signals, SIGPIPE);
  pthread_sigmask(SIG_BLOCK, &signals, nullptr);
  const int sfd = ::signalfd(-1, &signals, SFD_CLOEXEC);

  TrackcalServerApp app(std::move(setup.trackers), args.app, LoadCalibrationCorrector);
  app.Start();

  const int ifd = ::inotify_init1(IN_NONBLOCK | IN_CLOEXEC);
  // Again after every reload: a symbolic link re-pointed into another directory (calib.json ->
  // ../releases/v2/lab.json) has its new target there, which must be watched from then on. Adding a
  // watch that exists is a no-op; a directory that cannot be watched is logged once. Returns
  // whether a directory was added, so that a change made there before its watch is looked for.
  std::set<std::filesystem::path> watched, unwatchable;
  auto watch_calibration_directories = [&] {
    bool added = false;
    for (const auto& dir : app.CalibrationDirectories()) {
      if (::inotify_add_watch(ifd, dir.c_str(), IN_CLOSE_WRITE | IN_MOVED_TO | IN_CREATE) >= 0) {
        unwatchable.erase(dir);
        added = watched.insert(dir).second || added;
      } else if (unwatchable.insert(dir).second) {
        LogToStderr("cannot watch " + dir.string() + " for calibration changes: " +
                    std::strerror(errno) + " (SIGHUP still reloads)");
      }
    }
    return added;
  };
  watch_calibration_directories();
  for (;;) {
    pollfd fds[2] = {{sfd, POLLIN, 0}, {ifd, POLLIN, 0}};
    if (::poll(fds, 2, -1) < 0) {
      if (errno == EINTR) continue;
      throw std::runtime_error(std::string("poll: ") + std::strerror(errno));
    }
    if (fds[1].revents & POLLIN) {
      alignas(inotify_event) char buf[4096];
      while (::read(ifd, buf, sizeof(buf)) > 0) {
      }
      app.ReloadChangedCalibrations();
      if (watch_calibration_directories()) app.ReloadChangedCalibrations();
    }
    if (fds[0].revents & POLLIN) {
      signalfd_siginfo info{};
      if (::read(sfd, &info, sizeof(info)) != sizeof(info)) continue;
      if (info.ssi_signo == SIGHUP) {
        LogToStderr("SIGHUP: reloading calibrations");
        app.ReloadCalibrations();
        if (watch_calibration_directories()) app.ReloadChangedCalibrations();
      } else if (info.ssi_signo == SIGUSR1) {
        LogToStderr(app.StatusLine());
      } else if (info.ssi_signo == SIGINT || info.ssi_signo == SIGTERM) {
        LogToStderr(app.StatusLine());
        LogToStderr("stopping");
        break;
      }
    }
  }
  app.Stop();
  // Bounded: a stderr nobody reads must not keep a stopped server from exiting.
  FlushStderrLog(kLogFlushTimeout);
  return 0;
}

}  // namespace
}  // namespace trackcal::vrpn

int main(int argc, char** argv) {
  try {
    return trackcal::vrpn::Run(argc, argv);
  } catch (const std::exception& e) {
    // After the lines queued before it (config warnings). The message may quote vrpn.cfg or a
    // calibration file (a device name, a token).
    trackcal::vrpn::FlushStderrLog(trackcal::vrpn::kLogFlushTimeout);
    std::cerr << "trackcal-server: error: " << trackcal::PrintableForLog(e.what()) << "\n";
    return 1;
  }
}
