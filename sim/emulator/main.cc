// trackcal-emulate: a Polhemus Fastrak on a pseudo-terminal. See docs/emulator.md.

#include <unistd.h>

#include <algorithm>
#include <cmath>
#include <csignal>
#include <cstdio>
#include <iostream>
#include <memory>
#include <sstream>
#include <stdexcept>
#include <string>
#include <vector>

#include "sim/emulator/emulator.h"

namespace {

using trackcal::Rigid3d;
using namespace trackcal::emulator;

Emulator* g_emulator = nullptr;

void OnSignal(int) {
  if (g_emulator) g_emulator->RequestStop();
}

const char kUsage[] =
    "usage: trackcal-emulate [options]\n"
    "Emulates a Polhemus Fastrak on a pseudo-terminal; prints the device path on stdout (again "
    "after\n"
    "each reconnect).\n"
    "  --stations N           receivers plugged in, 1-4 (default: from the pose source, else 2)\n"
    "  --pose S=x,y,z,qw,qx,qy,qz  static pose of station S in metres (repeatable)\n"
    "  --trajectory FILE      CSV keyframes t,station,x,y,z,qw,qx,qy,qz[,button] (metres, "
    "seconds)\n"
    "  --loop                 repeat the trajectory\n"
    "  --link PATH            symlink to the device, replaced atomically, removed at exit\n"
    "  --control PATH         Unix socket for the control protocol (move, button, fault, status)\n"
    "  --rate HZ              measurement cycles per second (default 120, shared among stations)\n"
    "  --baud BPS             serial line speed of the device, paces output (default 115200, 0 = "
    "off)\n"
    "  --rate-per-station     every active station in every cycle instead of round robin\n"
    "  --binary --continuous --metric   power-up state (default ASCII, polled, inches)\n"
    "  --seed N               seed of the garbage-byte fault\n"
    "  --duration SECONDS     exit after this time (default: run until SIGINT/SIGTERM)\n"
    "  --verbose              log commands and faults to stderr\n";

[[noreturn]] void UsageError(const std::string& message) {
  throw std::invalid_argument(message + "\n" + kUsage);
}

double ParseDouble(const std::string& s, const std::string& option) {
  try {
    size_t used = 0;
    const double v = std::stod(s, &used);
    if (used != s.size()) throw std::invalid_argument("");
    return v;
  } catch (const std::exception&) {
    UsageError(option + ": not a number: '" + s + "'");
  }
}

std::pair<int, Rigid3d> ParsePose(const std::string& text) {
  const size_t eq = text.find('=');
  if (eq == std::string::npos)
    UsageError("--pose: expected S=x,y,z,qw,qx,qy,qz, got '" + text + "'");
  const int station = static_cast<int>(ParseDouble(text.substr(0, eq), "--pose station"));
  if (station < 1 || station > kMaxStations) UsageError("--pose: station must be 1 to 4");
  std::vector<double> v;
  std::stringstream ss(text.substr(eq + 1));
  std::string item;
  while (std::getline(ss, item, ',')) v.push_back(ParseDouble(item, "--pose"));
  if (v.size() != 7)
    UsageError("--pose: expected 7 numbers after '=', got " + std::to_string(v.size()));
  const Eigen::Quaterniond q = trackcal::QuaternionFromWxyz(v[3], v[4], v[5], v[6]);
  if (q.norm() < 1e-9) UsageError("--pose: zero quaternion");
  return {station, Rigid3d(q.normalized(), Eigen::Vector3d(v[0], v[1], v[2]))};
}

int Main(int argc, char** argv) {
  EmulatorOptions options;
  int stations = 0;
  std::vector<std::pair<int, Rigid3d>> poses;
  std::string trajectory;
  bool loop = false;
  bool verbose = false;
  double duration = -1;
  for (int i = 1; i < argc; ++i) {
    const std::string arg = argv[i];
    auto value = [&]() -> std::string {
      if (i + 1 >= argc) UsageError(arg + ": missing value");
      return argv[++i];
    };
    if (arg == "--help" || arg == "-h") {
      std::cout << kUsage;
      return 0;
    } else if (arg == "--stations") {
      stations = static_cast<int>(ParseDouble(value(), arg));
    } else if (arg == "--pose") {
      poses.push_back(ParsePose(value()));
    } else if (arg == "--trajectory") {
      trajectory = value();
    } else if (arg == "--loop") {
      loop = true;
    } else if (arg == "--link") {
      options.link_path = value();
    } else if (arg == "--control") {
      options.control_socket_path = value();
    } else if (arg == "--rate") {
      options.update_rate_hz = ParseDouble(value(), arg);
    } else if (arg == "--baud") {
      options.baud = static_cast<int>(ParseDouble(value(), arg));
    } else if (arg == "--rate-per-station") {
      options.divide_rate_among_stations = false;
    } else if (arg == "--binary") {
      options.device.binary = true;
    } else if (arg == "--continuous") {
      options.device.continuous = true;
    } else if (arg == "--metric") {
      options.device.metric = true;
    } else if (arg == "--seed") {
      options.seed = static_cast<uint64_t>(ParseDouble(value(), arg));
    } else if (arg == "--duration") {
      duration = ParseDouble(value(), arg);
    } else if (arg == "--verbose") {
      verbose = true;
    } else {
      UsageError("unknown option '" + arg + "'");
    }
  }
  if (!trajectory.empty() && !poses.empty()) UsageError("--pose and --trajectory are exclusive");

  std::unique_ptr<PoseSource> base;
  int source_stations = 0;
  if (!trajectory.empty()) {
    auto t = TrajectoryPoseSource::ReadCsv(trajectory, loop);
    source_stations = t->num_stations();
    base = std::move(t);
  } else {
    // Unspecified stations sit 30 cm in front of the transmitter, 10 cm apart, in the +x
    // hemisphere.
    std::vector<Rigid3d> fixed(kMaxStations);
    for (int s = 0; s < kMaxStations; ++s) {
      fixed[s].translation = Eigen::Vector3d(0.3, 0.1 * s - 0.15, 0.1);
    }
    int highest = 0;
    for (const auto& [s, pose] : poses) {
      fixed[s - 1] = pose;
      highest = std::max(highest, s);
    }
    source_stations = poses.empty() ? kMaxStations : highest;
    fixed.resize(source_stations);
    base = std::make_unique<StaticPoseSource>(fixed);
  }
  if (stations == 0) stations = (trajectory.empty() && poses.empty()) ? 2 : source_stations;
  if (stations > source_stations) {
    UsageError("--stations " + std::to_string(stations) + ": the pose source defines only " +
               std::to_string(source_stations));
  }
  options.device.num_stations = stations;
  options.run_seconds = duration;
  options.Check();

  ControlledPoseSource source(std::move(base));
  PerfectMeasurement model;
  Emulator emulator(options, &source, &model);
  emulator.on_device_path = [](const std::string& path) { std::cout << path << std::endl; };
  if (verbose) emulator.on_log = [](const std::string& line) { std::cerr << line << std::endl; };
  g_emulator = &emulator;
  struct sigaction sa {};
  sa.sa_handler = OnSignal;
  sigemptyset(&sa.sa_mask);
  sigaction(SIGINT, &sa, nullptr);
  sigaction(SIGTERM, &sa, nullptr);
  std::signal(SIGPIPE, SIG_IGN);
  emulator.Start();
  emulator.Run();
  g_emulator = nullptr;
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  try {
    return Main(argc, argv);
  } catch (const std::exception& e) {
    std::cerr << "trackcal-emulate: " << e.what() << std::endl;
    return 2;
  }
}
