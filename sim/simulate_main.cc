// trackcal-simulate: writes a simulated capture folder from a scene.
//
//   trackcal-simulate --scene paper|FILE [--hidden EFFECT[,EFFECT]] [--seed N] -o DIR
//
// DIR gets poses.csv, markers.csv and tracker.csv (every station: calib, valid and reg; the set of
// each is in poses.csv), tracker_stream.csv, reference_stream.csv, truth.json and scene.yaml (the effective scene: rerunning with --scene DIR/scene.yaml reproduces
// the capture bit for bit). An existing non-empty DIR is never overwritten.

#include <charconv>
#include <cstdio>
#include <exception>
#include <iostream>
#include <string>

#include "sim/scene.h"
#include "sim/simulator.h"

namespace {

void PrintUsage(std::ostream& out) {
  out << "usage: trackcal-simulate --scene PRESET|FILE [--hidden EFFECT[,EFFECT...]] [--seed N] -o "
         "DIR\n"
         "  --scene   a preset (";
  const auto presets = trackcal::sim::PresetNames();
  for (size_t i = 0; i < presets.size(); ++i) out << (i ? ", " : "") << presets[i];
  out << ") or a scene file (docs/scene.md)\n"
         "  --hidden  physical effects switched on top of the scene, repeatable (";
  const auto& names = trackcal::sim::HiddenEffects::Names();
  for (size_t i = 0; i < names.size(); ++i) out << (i ? ", " : "") << names[i];
  out << ")\n"
         "  --seed    master seed (default: the scene's)\n"
         "  -o DIR    output capture folder (must not exist or be empty)\n";
}

}  // namespace

int main(int argc, char** argv) {
  std::string scene_arg, out_dir, hidden, seed_text;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    auto value = [&](std::string* dst) {
      if (i + 1 >= argc) {
        std::cerr << "trackcal-simulate: " << a << " needs a value\n";
        std::exit(2);
      }
      // An empty value ("--seed $SEED" with SEED unset) was taken as no option at all: the run
      // used the scene's seed and succeeded. An empty value also escaped the check below, so a
      // second value replaced it.
      if (argv[i + 1][0] == '\0') {
        std::cerr << "trackcal-simulate: " << a << " needs a value, got an empty one\n";
        std::exit(2);
      }
      // A second value would silently replace the first (a second -o, a second --scene).
      if (!dst->empty()) {
        std::cerr << "trackcal-simulate: " << a << " given twice\n";
        std::exit(2);
      }
      *dst = argv[++i];
    };
    if (a == "--scene") {
      value(&scene_arg);
    } else if (a == "--hidden") {
      // Repeatable: --hidden A --hidden B is --hidden A,B.
      std::string more;
      value(&more);
      hidden += (hidden.empty() ? "" : ",") + more;
    } else if (a == "--seed") {
      value(&seed_text);
    } else if (a == "-o" || a == "--output") {
      value(&out_dir);
    } else if (a == "-h" || a == "--help") {
      PrintUsage(std::cout);
      return 0;
    } else {
      std::cerr << "trackcal-simulate: unknown argument '" << a << "'\n";
      PrintUsage(std::cerr);
      return 2;
    }
  }
  if (scene_arg.empty() || out_dir.empty()) {
    PrintUsage(std::cerr);
    return 2;
  }
  try {
    trackcal::sim::Scene scene = trackcal::sim::LoadScene(scene_arg);
    if (!seed_text.empty()) {
      uint64_t seed = 0;
      const auto [end, ec] =
          std::from_chars(seed_text.data(), seed_text.data() + seed_text.size(), seed);
      if (ec != std::errc() || end != seed_text.data() + seed_text.size()) {
        throw std::invalid_argument("--seed: '" + seed_text + "' is not a non-negative integer");
      }
      scene.seed = seed;
    }
    size_t start = 0;
    while (start <= hidden.size() && !hidden.empty()) {
      const size_t comma = hidden.find(',', start);
      const std::string name = hidden.substr(start, comma - start);
      if (!name.empty()) scene.hidden.Enable(name);
      if (comma == std::string::npos) break;
      start = comma + 1;
    }
    const trackcal::sim::Simulator simulator(scene);
    const trackcal::sim::SimulatedCapture capture = simulator.Generate();
    trackcal::sim::WriteCaptureFolder(simulator, capture, out_dir);
    const auto& stats = capture.truth["statistics"];
    std::cout << "wrote " << out_dir << ": " << capture.poses.records.size() << " stations, "
              << capture.markers.records.size() << " marker readings, "
              << capture.tracker_stream.records.size() << " tracker and "
              << capture.reference_stream.records.size() << " reference stream samples\n";
    if (stats.contains("valid")) {
      const auto& u = stats["valid"]["uncorrected"];
      const auto& f = stats["valid"]["noise_floor"];
      std::printf(
          "validation, uncorrected: position mean %.1f std %.1f max %.1f mm; orientation mean "
          "%.2f std %.2f max %.2f deg\n"
          "validation, noise floor: position mean %.2f mm; orientation mean %.3f deg\n",
          u["position_mm"]["mean"].get<double>(), u["position_mm"]["std"].get<double>(),
          u["position_mm"]["max"].get<double>(), u["orientation_deg"]["mean"].get<double>(),
          u["orientation_deg"]["std"].get<double>(), u["orientation_deg"]["max"].get<double>(),
          f["position_mm"]["mean"].get<double>(), f["orientation_deg"]["mean"].get<double>());
    }
  } catch (const std::exception& e) {
    std::cerr << "trackcal-simulate: " << e.what() << "\n";
    return 1;
  }
  return 0;
}
