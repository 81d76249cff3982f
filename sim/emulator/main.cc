// trackcal-emulate: a Polhemus Fastrak on a pseudo-terminal. See docs/emulator.md.

#include <unistd.h>

#include <algorithm>
#include <cmath>
#include <csignal>
#include <cstdint>
#include <cstdio>
#include <iostream>
#include <memory>
#include <optional>
#include <sstream>
#include <stdexcept>
#include <string>
#include <vector>

#include "sim/emulator/emulator.h"
#include "sim/emulator/simulated_tracker.h"

namespace {

using trackcal::Rigid3d;
using namespace trackcal::emulator;

Emulator* g_emulator = nullptr;

void OnSignal(int) {
  if (g_emulator) g_emulator->RequestStop();
}

const char kUsage[] =
    "usage: trackcal-emulate [options]\n"
    "Emulates a Polhemus Fastrak on a pseudo-terminal; prints the device path on stdout (again\n"
    "after each reconnect). Default: the 'paper' scene's physics and trajectories.\n"
    "  --scene NAME|FILE|none  physics of the tracker (sim/ scene preset or YAML file); none = a\n"
    "                          perfect tracker (default: paper)\n"
    "  --hidden EFFECT[,...]  physical effects switched on in the scene (as trackcal-simulate)\n"
    "  --stations N           receivers plugged in, 1-4 (default: from the pose source, else 2)\n"
    "  --pose S=x,y,z,qw,qx,qy,qz  static true pose of station S in metres (repeatable)\n"
    "  --trajectory FILE      CSV keyframes t,station,x,y,z,qw,qx,qy,qz[,button] (m, s)\n"
    "  --within XMIN,YMIN,ZMIN,XMAX,YMAX,ZMAX  keep the scene's trajectories inside this box\n"
    "                         (true receiver positions, transmitter frame, metres)\n"
    "  --loop                 repeat the trajectory\n"
    "  --link PATH            symlink to the device, replaced atomically, removed at exit\n"
    "  --control PATH         Unix socket for the control protocol (move, button, fault, status)\n"
    "  --rate HZ              measurement cycles per second (default: the scene's, else 120)\n"
    "  --baud BPS             serial line speed of the device (default 115200, 0 = unpaced)\n"
    "  --rate-per-station     every active station in every cycle instead of round robin\n"
    "  --binary --continuous --metric   power-up state (default ASCII, polled, inches)\n"
    "  --noise-mm MM --noise-deg DEG  extra white noise per axis on reported position/orientation\n"
    "  --seed N               seed of the noise and of the garbage-byte fault (default: scene's)\n"
    "  --duration SECONDS     exit after this time (default: run until SIGINT/SIGTERM)\n"
    "  --verbose              log commands and faults to stderr\n";

[[noreturn]] void UsageError(const std::string& message) {
  throw std::invalid_argument(message + "\n" + kUsage);
}

// A finite number: "nan" or "inf" (which std::stod accepts) would become a NaN pose or an endless
// run, so they are usage errors too.
double ParseDouble(const std::string& s, const std::string& option) {
  double v = 0;
  try {
    size_t used = 0;
    v = std::stod(s, &used);
    if (used != s.size()) throw std::invalid_argument("");
  } catch (const std::exception&) {
    UsageError(option + ": not a number: '" + s + "'");
  }
  if (!std::isfinite(v)) UsageError(option + ": not a finite number: '" + s + "'");
  return v;
}

// A whole number in [min, max] (stations, baud with 0 unpaced, seed): "2.5", "1e3" or "-1" are usage errors, not
// truncated or wrapped.
uint64_t ParseWhole(const std::string& s, const std::string& option, uint64_t min, uint64_t max) {
  const bool digits = !s.empty() && s.size() <= 20 &&
                      std::all_of(s.begin(), s.end(), [](char c) { return c >= '0' && c <= '9'; });
  uint64_t v = 0;
  bool in_range = digits;
  try {
    if (digits) v = std::stoull(s);
  } catch (const std::exception&) {
    in_range = false;  // beyond 2^64 - 1
  }
  if (!in_range || v < min || v > max) {
    UsageError(option + ": expected a whole number from " + std::to_string(min) + " to " +
               std::to_string(max) + ", got '" + s + "'");
  }
  return v;
}

// Comma-separated fields, empty ones kept: "1,2," is three fields, the last empty (a number
// missing), where std::getline would drop it.
std::vector<std::string> SplitCommas(const std::string& text) {
  std::vector<std::string> fields;
  for (size_t start = 0;;) {
    const size_t comma = text.find(',', start);
    fields.push_back(text.substr(start, comma - start));
    if (comma == std::string::npos) return fields;
    start = comma + 1;
  }
}

std::pair<int, Rigid3d> ParsePose(const std::string& text) {
  const size_t eq = text.find('=');
  if (eq == std::string::npos)
    UsageError("--pose: expected S=x,y,z,qw,qx,qy,qz, got '" + text + "'");
  const int station = static_cast<int>(ParseWhole(text.substr(0, eq), "--pose station", 1, 4));
  if (station < 1 || station > kMaxStations) UsageError("--pose: station must be 1 to 4");
  const std::vector<std::string> fields = SplitCommas(text.substr(eq + 1));
  if (fields.size() != 7)
    UsageError("--pose: expected 7 numbers after '=', got " + std::to_string(fields.size()) +
               " fields in '" + text + "'");
  std::vector<double> v;
  for (const std::string& field : fields) v.push_back(ParseDouble(field, "--pose"));
  const Eigen::Quaterniond q = trackcal::QuaternionFromWxyz(v[3], v[4], v[5], v[6]);
  if (q.norm() < 1e-9) UsageError("--pose: zero quaternion");
  return {station, Rigid3d(q.normalized(), Eigen::Vector3d(v[0], v[1], v[2]))};
}

// "xmin,ymin,zmin,xmax,ymax,zmax" [m].
std::pair<Eigen::Vector3d, Eigen::Vector3d> ParseBox(const std::string& text,
                                                     const std::string& option) {
  static const char* const kFields[] = {"xmin", "ymin", "zmin", "xmax", "ymax", "zmax"};
  const std::vector<std::string> fields = SplitCommas(text);
  if (fields.size() != 6) {
    UsageError(option + ": expected xmin,ymin,zmin,xmax,ymax,zmax (6 numbers, metres), got '" +
               text + "'");
  }
  std::vector<double> v;
  for (size_t i = 0; i < fields.size(); ++i) {
    v.push_back(ParseDouble(fields[i], option + " " + kFields[i]));
  }
  const Eigen::Vector3d lo(v[0], v[1], v[2]), hi(v[3], v[4], v[5]);
  for (int i = 0; i < 3; ++i) {
    if (!(hi(i) > lo(i))) {
      UsageError(option + ": " + kFields[3 + i] + " (" + std::to_string(hi(i)) +
                 ") must be above " + kFields[i] + " (" + std::to_string(lo(i)) + ")");
    }
  }
  return {lo, hi};
}

int Main(int argc, char** argv) {
  EmulatorOptions options;
  int stations = 0;
  std::vector<std::pair<int, Rigid3d>> poses;
  std::string trajectory;
  bool loop = false;
  bool verbose = false;
  double duration = -1;
  double noise_mm = 0;
  std::string scene_name;
  std::string hidden;
  bool seed_given = false;
  bool rate_given = false;
  double noise_deg = 0;
  std::optional<std::pair<Eigen::Vector3d, Eigen::Vector3d>> within;
  for (int i = 1; i < argc; ++i) {
    const std::string arg = argv[i];
    auto value = [&]() -> std::string {
      if (i + 1 >= argc) UsageError(arg + ": missing value");
      return argv[++i];
    };
    if (arg == "--help" || arg == "-h") {
      std::cout << kUsage;
      return 0;
    } else if (arg == "--scene") {
      scene_name = value();
    } else if (arg == "--hidden") {
      hidden = value();
    } else if (arg == "--stations") {
      stations = static_cast<int>(ParseWhole(value(), arg, 1, 4));
    } else if (arg == "--pose") {
      poses.push_back(ParsePose(value()));
    } else if (arg == "--trajectory") {
      trajectory = value();
    } else if (arg == "--within") {
      within = ParseBox(value(), arg);
    } else if (arg == "--loop") {
      loop = true;
    } else if (arg == "--link") {
      options.link_path = value();
    } else if (arg == "--control") {
      options.control_socket_path = value();
    } else if (arg == "--rate") {
      options.update_rate_hz = ParseDouble(value(), arg);
      rate_given = true;
    } else if (arg == "--baud") {
      options.baud = static_cast<int>(ParseWhole(value(), arg, 0, 4000000));
    } else if (arg == "--rate-per-station") {
      options.divide_rate_among_stations = false;
    } else if (arg == "--binary") {
      options.device.binary = true;
    } else if (arg == "--continuous") {
      options.device.continuous = true;
    } else if (arg == "--metric") {
      options.device.metric = true;
    } else if (arg == "--noise-mm") {
      noise_mm = ParseDouble(value(), arg);
    } else if (arg == "--noise-deg") {
      noise_deg = ParseDouble(value(), arg);
    } else if (arg == "--seed") {
      options.seed = ParseWhole(value(), arg, 0, UINT64_MAX);
      seed_given = true;
    } else if (arg == "--duration") {
      // Run time <= 0 means "until stopped" to the Emulator, not "exit after 0 s".
      duration = ParseDouble(value(), arg);
      if (!(duration > 0)) UsageError("--duration: must be more than 0 seconds");
    } else if (arg == "--verbose") {
      verbose = true;
    } else {
      UsageError("unknown option '" + arg + "'");
    }
  }
  if (!trajectory.empty() && !poses.empty()) UsageError("--pose and --trajectory are exclusive");

  // Physics: a sim/ scene unless "none"; the default when no poses are given is the paper scene.
  if (scene_name.empty() && trajectory.empty() && poses.empty()) scene_name = "paper";
  std::shared_ptr<const trackcal::sim::Simulator> simulator;
  if (!scene_name.empty() && scene_name != "none") {
    trackcal::sim::Scene scene = trackcal::sim::LoadScene(scene_name);
    std::stringstream effects(hidden);
    std::string effect;
    while (std::getline(effects, effect, ',')) {
      if (effect.empty()) continue;
      scene.hidden.Enable(effect);
      // These act on trackcal-simulate's captures only: the offset and the clock sit between the
      // receiver and the optical reference, which the emulator does not have, and the flips are
      // drawn per capture station. Accepted (the demo serves the scene it simulated), but said.
      if (effect == "sensor_offset" || effect == "clock_offset" || effect == "hemisphere_flips") {
        std::cerr << "trackcal-emulate: note: --hidden " << effect
                  << " changes simulated captures only, not the emulated tracker's reports\n";
      }
    }
    if (!seed_given) options.seed = scene.seed;
    if (!rate_given) options.update_rate_hz = scene.tracker.update_rate_hz;
    if (within) scene.capture.stream.KeepWithin(within->first, within->second, "--within");
    // The scene's hemisphere as the power-up `H` of every station (a lab's saved configuration).
    options.device.hemisphere = scene.tracker.hemisphere_in_transmitter;
    simulator = std::make_shared<const trackcal::sim::Simulator>(scene);
  } else if (!hidden.empty()) {
    UsageError("--hidden needs a --scene");
  }
  if (within && (!simulator || !trajectory.empty() || !poses.empty())) {
    UsageError(
        "--within applies to the scene's trajectories (not --pose, --trajectory or --scene none)");
  }

  std::unique_ptr<PoseSource> base;
  int source_stations = 0;
  if (!trajectory.empty()) {
    auto t = TrajectoryPoseSource::ReadCsv(trajectory, loop);
    source_stations = t->num_stations();
    base = std::move(t);
  } else if (poses.empty() && simulator) {
    base = std::make_unique<SceneTrajectorySource>(simulator);
    source_stations = kMaxStations;
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
  std::unique_ptr<MeasurementModel> tracker;
  if (simulator) tracker = std::make_unique<SimulatedTracker>(simulator, options.seed);
  // Extra white noise on top (none by default), from its own stream of numbers.
  NoisyMeasurement model(std::move(tracker), noise_mm * 1e-3, noise_deg * trackcal::kRadPerDeg,
                         options.seed ^ 0x9e3779b97f4a7c15ULL);
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
