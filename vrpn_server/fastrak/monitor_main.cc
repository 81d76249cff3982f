// trackcal-fastrak-monitor: runs the Fastrak driver on a serial port and prints every report as CSV,
// to check a unit, a cable or an emulator without a VRPN server. Usage: see kUsage.

#include <csignal>
#include <cstdio>
#include <cstdlib>
#include <iostream>
#include <mutex>
#include <optional>
#include <stdexcept>
#include <string>
#include <thread>
#include <vector>

#include "core/printable_text.h"
#include "vrpn_server/config.h"
#include "vrpn_server/fastrak/driver.h"
#include "vrpn_server/fastrak/from_config.h"

namespace {

constexpr const char* kUsage =
    "usage: trackcal-fastrak-monitor PORT [options]\n"
    "       trackcal-fastrak-monitor --config vrpn.cfg --tracker NAME [options]\n"
    "Drives a Polhemus Fastrak and prints its reports as CSV on stdout:\n"
    "  host_time_s,sensor,x,y,z,qw,qx,qy,qz,status,stylus   (metres, transmitter frame)\n"
    "Driver texts go to stderr.\n"
    "options:\n"
    "  --baud N            line speed (default 115200)\n"
    "  --units in|cm       unit to put the tracker in (default in)\n"
    "  --no-force-units    do not send U/u (exact reference bytes; trust the tracker's state)\n"
    "  --extra CMD         extra reset command (repeatable; *N waits N s)\n"
    "  --stylus SENSOR     0-based sensor with a stylus (repeatable)\n"
    "  --stations N        stations to configure (default 4)\n"
    "  --fast              short reset waits (emulators on a pty)\n"
    "  --seconds S         stop after S seconds (default: until Ctrl-C)\n";

volatile std::sig_atomic_t g_stop = 0;
void OnSignal(int) { g_stop = 1; }

[[noreturn]] void UsageError(const std::string& message) {
  std::cerr << "trackcal-fastrak-monitor: " << trackcal::PrintableForLog(message) << "\n" << kUsage;
  std::exit(2);
}

int ParseInt(const std::string& flag, const std::string& value) {
  try {
    size_t end = 0;
    const int v = std::stoi(value, &end);
    if (end != value.size()) throw std::invalid_argument(value);
    return v;
  } catch (const std::exception&) {
    UsageError(flag + ": expected an integer, got '" + value + "'");
  }
}

}  // namespace

int main(int argc, char** argv) {
  using namespace trackcal;
  std::vector<std::string> args(argv + 1, argv + argc);
  fastrak::FastrakOptions options;
  std::optional<std::string> config_path, tracker_name;
  std::optional<double> seconds;
  bool fast = false;
  std::optional<int> baud, stations;
  std::optional<fastrak::Units> units;
  bool no_force_units = false;
  std::vector<std::string> extras;
  std::vector<int> stylus;
  std::string port;
  for (size_t i = 0; i < args.size(); ++i) {
    const std::string& a = args[i];
    auto value = [&]() -> std::string {
      if (i + 1 >= args.size()) UsageError(a + " needs a value");
      return args[++i];
    };
    if (a == "-h" || a == "--help") {
      std::cout << kUsage;
      return 0;
    } else if (a == "--baud") {
      baud = ParseInt(a, value());
    } else if (a == "--units") {
      const std::string u = value();
      if (u == "in") {
        units = fastrak::Units::kInches;
      } else if (u == "cm") {
        units = fastrak::Units::kCentimetres;
      } else {
        UsageError("--units: expected in or cm, got '" + u + "'");
      }
    } else if (a == "--no-force-units") {
      no_force_units = true;
    } else if (a == "--extra") {
      extras.push_back(value());
    } else if (a == "--stylus") {
      stylus.push_back(ParseInt(a, value()));
    } else if (a == "--stations") {
      stations = ParseInt(a, value());
    } else if (a == "--fast") {
      fast = true;
    } else if (a == "--seconds") {
      const std::string v = value();
      char* end = nullptr;
      seconds = std::strtod(v.c_str(), &end);
      if (end == v.c_str() || *end != '\0' || !(*seconds >= 0))
        UsageError("--seconds: bad value '" + v + "'");
    } else if (a == "--config") {
      config_path = value();
    } else if (a == "--tracker") {
      tracker_name = value();
    } else if (!a.empty() && a[0] == '-') {
      UsageError("unknown option " + a);
    } else if (port.empty()) {
      port = a;
    } else {
      UsageError("unexpected argument " + a);
    }
  }

  try {
    if (config_path) {
      if (!tracker_name) UsageError("--config needs --tracker NAME");
      const vrpn::VrpnConfig config = vrpn::ReadVrpnConfig(*config_path);
      for (const auto& w : config.warnings) std::cerr << w.ToString() << "\n";
      const vrpn::FastrakTrackerSpec* spec = nullptr;
      for (const auto& t : config.fastrak_trackers) {
        if (t.name == *tracker_name) spec = &t;
      }
      if (spec == nullptr) {
        throw std::invalid_argument(*config_path + ": no vrpn_Tracker_Fastrak named '" + *tracker_name + "'");
      }
      std::vector<vrpn::ConfigWarning> warnings;
      options = fastrak::FastrakOptionsFromSpec(*spec, &warnings);
      for (const auto& w : warnings) std::cerr << w.ToString() << "\n";
      if (!port.empty()) options.port = port;
    } else {
      if (port.empty()) UsageError("missing PORT");
      options.port = port;
    }
    if (baud) options.baud = *baud;
    if (stations) options.num_stations = *stations;
    if (units) options.units = *units;
    if (no_force_units) options.force_units = false;
    options.extra_commands.insert(options.extra_commands.end(), extras.begin(), extras.end());
    options.stylus_sensors.insert(options.stylus_sensors.end(), stylus.begin(), stylus.end());
    if (fast) options.timings = fastrak::FastrakTimings::Fast();

    std::mutex out_mutex;
    fastrak::FastrakDriver::Callbacks callbacks;
    callbacks.on_report = [&](const fastrak::FastrakReport& r) {
      const double t = std::chrono::duration<double>(r.time.time_since_epoch()).count();
      std::lock_guard<std::mutex> lock(out_mutex);
      std::printf("%.6f,%d,%.7g,%.7g,%.7g,%.7g,%.7g,%.7g,%.7g,%c,%s\n", t, r.sensor, r.position_m.x(),
                  r.position_m.y(), r.position_m.z(), r.rotation.w(), r.rotation.x(), r.rotation.y(),
                  r.rotation.z(), r.status,
                  r.stylus_pressed ? (*r.stylus_pressed ? "1" : "0") : "");
      std::fflush(stdout);
    };
    callbacks.on_message = [&](fastrak::Severity s, const std::string& text) {
      std::lock_guard<std::mutex> lock(out_mutex);
      std::cerr << fastrak::SeverityName(s) << ": " << PrintableForLog(text) << std::endl;
    };
    fastrak::FastrakDriver driver(options, callbacks);
    std::signal(SIGINT, OnSignal);
    std::signal(SIGTERM, OnSignal);
    std::printf("host_time_s,sensor,x,y,z,qw,qx,qy,qz,status,stylus\n");
    std::fflush(stdout);
    driver.Start();
    const auto start = std::chrono::steady_clock::now();
    while (!g_stop) {
      if (seconds && std::chrono::steady_clock::now() - start >= std::chrono::duration<double>(*seconds)) break;
      std::this_thread::sleep_for(std::chrono::milliseconds(20));
    }
    driver.Stop();
    const fastrak::DriverStats st = driver.stats();
    // Scripts parse this line: new counters go at its end.
    std::cerr << "records " << st.records << ", resets " << st.resets_completed << ", resumes "
              << st.resumes << ", watchdog timeouts " << st.watchdog_timeouts << ", port losses "
              << st.port_losses << ", discarded bytes " << st.discarded_bytes << ", quick restarts "
              << st.quick_restarts << "\n";
    return 0;
  } catch (const std::exception& e) {
    // The message may quote the command line or vrpn.cfg (a port or tracker name): escaped, as
    // trackcal-server prints its fatal error, so that no byte drives the terminal.
    std::cerr << "trackcal-fastrak-monitor: " << PrintableForLog(e.what()) << "\n";
    return 1;
  }
}
