// trackcal-fit: fits a correction model to a capture, registers the optical frame, pairs streams.
//
//   trackcal-fit fit --data DIR|poses.csv --model model.yaml -o calib.json [--folds K]
//                    [--start fit.json] [--sensor N] [--json] [--quiet]
//   trackcal-fit register --markers markers.csv --tracker tracker.csv -o poses.csv
//                         [--set NAME | --poses poses.csv [--model model.yaml]] [--json] [--quiet]
//                         [--optical-noise-mm S] [--tracker-noise-mm S] [--tracker-noise-deg S]
//                         [--allow-unidentifiable] [--keep-all-stations] [--sensor N]
//   trackcal-fit diagnose --data DIR|poses.csv --model model.yaml [--folds K] [--effects LIST]
//                         [--cross-validate-top N] [--exact-cv] [--threads N] [--sensor N]
//                         [--json] [--quiet]
//   trackcal-fit pair --tracker tracker_stream.csv --reference reference_stream.csv
//                     [--time-offset S] [--estimate-time-offset [--search-range S]] [--set NAME]
//                     [--sensor N] -o poses.csv [--json]
//
// Human-readable output (Table 1 of the paper, parameters with standard deviations) goes to stdout,
// progress to stderr; with --json stdout carries exactly one JSON document. Bad input exits with 1
// and a message naming file, line and field; bad usage exits with 2. A registration that is not
// identifiable exits with 3 and writes no poses (unless --allow-unidentifiable).

#include <cmath>
#include <cstdio>
#include <filesystem>
#include <iomanip>
#include <iostream>
#include <map>
#include <memory>
#include <nlohmann/json.hpp>
#include <optional>
#include <sstream>
#include <string>
#include <vector>

#include "core/calibration_file.h"
#include "core/capture.h"
#include "core/file_util.h"
#include "core/json_reader.h"
#include "fit/candidates.h"
#include "fit/chain_builder.h"
#include "fit/fit_engine.h"
#include "fit/fit_run.h"
#include "fit/model_file.h"
#include "fit/pose_extraction.h"
#include "fit/registration.h"
#include "fit/registration_io.h"
#include "fit/registration_refinement.h"
#include "fit/stream_pairing.h"

namespace fs = std::filesystem;
using namespace trackcal;
using namespace trackcal::fit;

namespace {

constexpr const char* kVersion = "0.1.0";

struct UsageError : std::runtime_error {
  using std::runtime_error::runtime_error;
};

void PrintUsage(std::ostream& out) {
  out << "usage:\n"
         "  trackcal-fit fit --data DIR|poses.csv --model model.yaml -o calib.json [--folds K] "
         "[--start fit.json]\n"
         "                   [--sensor N] [--json] [--quiet]\n"
         "  trackcal-fit build --data DIR|poses.csv --model settings.yaml -o calib.json "
         "[--model-out model.yaml]\n"
         "                     [--sources N] [--folds K] [--sensor N] [--json] [--quiet]\n"
         "  trackcal-fit diagnose --data DIR|poses.csv --model model.yaml [--folds K] "
         "[--effects LIST]\n"
         "                        [--cross-validate-top N] [--exact-cv] [--threads N] [--sensor N] "
         "[--json] [--quiet]\n"
         "  trackcal-fit register --markers markers.csv --tracker tracker.csv -o poses.csv\n"
         "                        [--set NAME | --poses poses.csv [--model model.yaml]] [--json] "
         "[--quiet]\n"
         "                        [--optical-noise-mm S] [--tracker-noise-mm S] "
         "[--tracker-noise-deg S]\n"
         "                        [--allow-unidentifiable] [--keep-all-stations] [--sensor N]\n"
         "  trackcal-fit pair --tracker tracker_stream.csv --reference reference_stream.csv\n"
         "                    [--time-offset S] [--estimate-time-offset [--search-range S]] [--set "
         "NAME] [--sensor N] "
         "-o poses.csv [--json]\n"
         "build chooses the terms itself (settings.yaml: noise, solver, loss; no terms:).\n"
         "Model file format: docs/model-file.md; tool reference: docs/fit.md; diagnose: "
         "docs/diagnose.md.\n";
}

// --key value options and --flags.
struct Args {
  std::map<std::string, std::string> values;
  std::map<std::string, bool> flags;
  std::string Get(const std::string& key) const {
    auto it = values.find(key);
    if (it == values.end()) throw UsageError("missing " + key);
    return it->second;
  }
  std::string GetOr(const std::string& key, const std::string& fallback) const {
    auto it = values.find(key);
    return it == values.end() ? fallback : it->second;
  }
  bool Flag(const std::string& key) const { return flags.count(key) > 0; }
};

Args ParseArgs(int argc, char** argv, const std::vector<std::string>& value_keys,
               const std::vector<std::string>& flag_keys) {
  Args args;
  for (int i = 2; i < argc; ++i) {
    const std::string a = argv[i];
    if (std::find(flag_keys.begin(), flag_keys.end(), a) != flag_keys.end()) {
      args.flags[a] = true;
    } else if (std::find(value_keys.begin(), value_keys.end(), a) != value_keys.end()) {
      if (i + 1 >= argc) throw UsageError(a + " needs a value");
      const std::string value = argv[++i];
      // `-o --json` (the file name forgotten) would write the calibration to a file named
      // "--json"; an empty value fails only when the output is written, after the whole fit.
      if (value.empty() ||
          std::find(flag_keys.begin(), flag_keys.end(), value) != flag_keys.end() ||
          std::find(value_keys.begin(), value_keys.end(), value) != value_keys.end()) {
        throw UsageError(a + " needs a value, got '" + value + "'");
      }
      // The last of two was taken silently: `-o a.json ... -o b.json` wrote b.json only.
      if (!args.values.emplace(a, value).second) throw UsageError(a + " given twice");
    } else {
      throw UsageError("unknown argument '" + a + "'");
    }
  }
  return args;
}

double ParseNumber(const std::string& option, const std::string& text) {
  size_t used = 0;
  double v = 0.0;
  try {
    v = std::stod(text, &used);
  } catch (const std::exception&) {
    used = 0;
  }
  if (used != text.size() || !std::isfinite(v)) throw UsageError(option + ": not a number: " + text);
  return v;
}

// A whole number option (--folds, --threads, ...): "2.5" was truncated to 2 without a word.
int ParseInteger(const std::string& option, const std::string& text) {
  const double v = ParseNumber(option, text);
  if (v != std::floor(v) || std::abs(v) > 1e9) {
    throw UsageError(option + ": expected a whole number, got " + text);
  }
  return static_cast<int>(v);
}

// Refuses to write over an input file.
// --set (default calib), checked before any work: a name no capture can hold.
std::string SetOption(const Args& args) {
  const std::string set = args.GetOr("--set", "calib");
  if (!IsKnownSet(set)) throw UsageError("--set '" + set + "' is not one of calib, valid, reg");
  return set;
}

// --sensor N (a receiver number), or `absent` when not given.
int SensorOption(const Args& args, int absent) {
  if (!args.values.count("--sensor")) return absent;
  const double sensor = ParseNumber("--sensor", args.Get("--sensor"));
  if (!(sensor >= 1 && sensor <= 64 && sensor == std::floor(sensor))) {
    throw UsageError("--sensor must be a receiver number (1, 2, ...)");
  }
  return static_cast<int>(sensor);
}

void CheckOutputIsNotInput(const fs::path& output, const std::vector<fs::path>& inputs) {
  std::error_code ec;
  for (const auto& in : inputs) {
    if (fs::exists(output, ec) && fs::equivalent(output, in, ec)) {
      throw std::invalid_argument(output.string() + ": output would overwrite the input " +
                                  in.string());
    }
  }
}

// The stream pairing's warning (an estimated clock offset the streams identify poorly), naming the
// streams as `pair` does. Not progress: printed with --quiet too.
void PrintPairingWarning(const fs::path& data, const LoadedFitData& loaded) {
  if (loaded.pairing_warning.empty()) return;
  std::cerr << "warning: " << (data / kTrackerStreamCsv).string() << ", "
            << (data / kReferenceStreamCsv).string() << ": " << loaded.pairing_warning << "\n";
}

void PrintParameters(const FitResult& result, std::ostream& out) {
  out << "Parameters (value +- standard deviation):\n";
  if (!result.covariance_estimator.empty()) {
    out << "  (standard deviations from the " << result.covariance_estimator
        << " covariance; docs/fit.md, \"Standard deviations\")\n";
  }
  for (const auto& p : result.parameters) {
    out << "  " << p.term << "." << p.block << " [" << p.unit << "]" << (p.fixed ? " (fixed)" : "")
        << ": " << p.values.size() << " values\n";
    const size_t shown = std::min<size_t>(p.values.size(), 12);
    for (size_t i = 0; i < shown; ++i) {
      out << "    " << std::left << std::setw(22)
          << (i < p.coordinate_names.size() ? p.coordinate_names[i] : std::to_string(i))
          << std::right << std::setw(14) << std::setprecision(6) << p.values[i];
      if (p.stddev_names.empty() && i < p.stddev.size() && std::isfinite(p.stddev[i])) {
        out << " +- " << p.stddev[i];
      }
      out << "\n";
    }
    // Manifold blocks (quaternion, unit normal): stds of the tangent coordinates.
    for (size_t i = 0; i < p.stddev_names.size() && i < p.stddev.size(); ++i) {
      if (!std::isfinite(p.stddev[i])) continue;
      out << "    " << std::left << std::setw(22) << p.stddev_names[i] << std::right
          << std::setw(14) << "std" << " " << p.stddev[i] << " " << p.stddev_unit << "\n";
    }
    if (shown < p.values.size()) out << "    ... (all values in --json and the calibration file)\n";
  }
  if (!result.identifiability_flags.empty()) {
    out << "Poorly identified (" << result.identifiability_flags.size() << "):\n";
    for (size_t i = 0; i < result.identifiability_flags.size() && i < 10; ++i) {
      out << "  " << result.identifiability_flags[i].coordinate << ": "
          << result.identifiability_flags[i].reason << "\n";
    }
  }
}

int RunFit(int argc, char** argv) {
  const Args args =
      ParseArgs(argc, argv, {"--data", "--model", "-o", "--folds", "--start", "--sensor"},
                {"--json", "--quiet"});
  const fs::path data = args.Get("--data");
  const fs::path model_path = args.Get("--model");
  const fs::path output = args.Get("-o");
  const int folds = ParseInteger("--folds", args.GetOr("--folds", "5"));
  if (folds < 2) throw UsageError("--folds must be at least 2");
  const bool json = args.Flag("--json");
  const bool quiet = args.Flag("--quiet");

  // The pipeline (data resolution, stream pairing, joint clock offset, Table 1, calibration
  // contents) is fit/fit_run.h, shared with the Python binding.
  const FitModelSource model{ReadFileToString(model_path), model_path.string(), model_path};
  LoadedFitData loaded = LoadFitData({data, std::nullopt, std::nullopt, SensorOption(args, 0)},
                                     ParseModelYaml(model.text, model.source_name));
  PrintPairingWarning(data, loaded);
  std::vector<fs::path> inputs = {model_path};
  inputs.insert(inputs.end(), loaded.protected_paths.begin(), loaded.protected_paths.end());
  if (args.values.count("--start")) inputs.push_back(args.Get("--start"));
  CheckOutputIsNotInput(output, inputs);
  CheckCalibrationOutput(output);  // before the fit, not after it

  FitRunOptions options;
  options.folds = folds;
  options.cross_validate_with_validation_set = false;  // the valid set is the held-out table
  if (args.values.count("--start")) {
    // A previous `fit --json` document (or its "fit"): the fit starts at that fit's optimum.
    const fs::path start_path = args.Get("--start");
    // The parser's raw text ("[json.exception.parse_error.101] parse error at line 1, column 2:
    // ...") named no usable place and did not say what --start takes; a model file or an empty
    // file given here (easy slips) now say so, and a syntax error names line and column.
    static constexpr char kTakes[] =
        "--start takes the JSON that `trackcal-fit fit --json` printed for an earlier fit";
    const std::string text = ReadFileToString(start_path);
    // After a UTF-8 byte order mark (the JSON parser skips one, as the calibration reader does).
    const size_t first =
        text.find_first_not_of(" \t\r\n", text.rfind("\xEF\xBB\xBF", 0) == 0 ? 3 : 0);
    if (first == std::string::npos) {
      throw std::invalid_argument(start_path.string() + ": empty file; " + kTakes);
    }
    if (text[first] != '{') {
      throw std::invalid_argument(start_path.string() +
                                  ": not a JSON document (it does not start with '{'; a model "
                                  "file or a calibration's YAML?); " +
                                  kTakes);
    }
    nlohmann::json doc;
    try {
      doc = ParseJsonText(text, start_path.string());
    } catch (const JsonInputError& e) {
      throw std::invalid_argument(std::string(e.what()) + "; " + kTakes);
    }
    // A `ridge: auto` polynomial keeps that fit's weight, as diagnose's candidates do: chosen
    // again at the start, with the previous coefficients, it was 31.6 instead of 1 on the full
    // paper capture (seed 1, the floor plane added after the frame and the toolbox), and the fit
    // ended at cost 2224 against 652, its validation error 3.20 mm against 0.71.
    const bool wrapped = doc.is_object() && doc.contains("fit");
    options.start = std::make_shared<const FitStart>(LocateJsonErrors(text, [&] {
      return FitStartFromJson(wrapped ? doc["fit"] : doc, start_path.string(),
                              wrapped ? "$.fit" : "$");
    }));
  }
  options.tool = "trackcal-fit";
  options.tool_version = kVersion;
  options.description_tool = "trackcal-fit";
  if (!quiet) {
    options.on_iteration = [](int iteration, double cost, int) {
      std::cerr << "trackcal-fit: iteration " << iteration << ", cost " << cost << "\n";
    };
    options.on_fold = [](int f, int n) {
      std::cerr << "trackcal-fit: cross-validation fold " << f + 1 << "/" << n << "\n";
    };
  }
  FitRunResult run = fit::RunFit(std::move(loaded), model, options);
  const FitResult& result = run.result;
  Calibration& calibration = run.calibration;
  {
    std::string cmd;
    for (int i = 0; i < argc; ++i) cmd += (i ? " " : "") + std::string(argv[i]);
    calibration.provenance.command_line = cmd;
  }
  if (!run.failure.empty()) {  // exits 1 with the report, and no calibration file
    if (json) std::cout << run.ToJson(std::nullopt).dump(2) << "\n";
    throw std::runtime_error(run.failure);
  }
  WriteCalibrationFile(output, calibration);

  if (json) {
    std::cout << run.ToJson(output).dump(2) << "\n";
    return 0;
  }
  for (const auto& t : run.tables) std::cout << FormatTable1(t) << "\n";
  // As python/trackcal/fitting.py words it (trackcal fit): a lone polynomial is solved in closed
  // form, which "converged after 0 iterations" misstated.
  std::cout << "Fit: "
            << (result.linear_least_squares ? std::string("solved by linear least squares")
                : result.converged
                    ? "converged after " + std::to_string(result.iterations) + " iterations"
                    : "NOT converged after " + std::to_string(result.iterations) + " iterations")
            << " in " << std::setprecision(3) << result.seconds * 1e3 << " ms; chi2/dof "
            << result.chi2_per_dof << "\n";
  if (!result.outliers.empty()) {
    // The first 20 ids (all are in --json): a model that does not fit flags most stations, and
    // a line of 400 ids said less than the count.
    constexpr std::size_t kListed = 20;
    const std::size_t n = result.outliers.size();
    std::cout << "Outlier stations (" << n << " of " << run.num_calib << "):";
    for (std::size_t i = 0; i < n && i < kListed; ++i)
      std::cout << " " << result.outliers[i].station;
    if (n > kListed) std::cout << " ... (" << n - kListed << " more)";
    std::cout << "\n";
    if (2 * n > static_cast<std::size_t>(run.num_calib)) {
      std::cout << "  (most stations are outliers: the model leaves far more than the noise; see "
                   "trackcal-fit diagnose)\n";
    }
  }
  if (!result.left_out.empty()) {
    std::cout << "Left out of the fit, unresolved by the model's inverse ("
              << result.left_out.size() << "):";
    for (int station : result.left_out) std::cout << " " << station;
    std::cout << "\n";
  } else if (!result.left_out_note.empty()) {
    std::cout << "Left out of the fit: " << result.left_out_note << "\n";
  }
  if (!result.report_form_stations.empty()) {
    // docs/fit.md, "The station residual through a physical group": the stations the model's
    // inverse did not resolve during the fit (every one at amplification_threshold >= 1e9).
    std::cout << "Residuals in report form: " << result.report_form_stations.size() << " of "
              << result.report_form.size() - result.left_out.size() << " fitted stations, "
              << result.noise_whitened.size() << " with a capped pose metric\n";
  }
  PrintParameters(result, std::cout);
  std::cout << "Wrote " << output.string() << "\n";
  return 0;
}

// build: the chain chosen by held-out error (fit/chain_builder.h, docs/model-file.md "Building a
// chain"), then fitted and written as `fit` does.
int RunBuild(int argc, char** argv) {
  const Args args = ParseArgs(
      argc, argv, {"--data", "--model", "-o", "--model-out", "--sources", "--folds", "--sensor"},
      {"--json", "--quiet"});
  const fs::path data = args.Get("--data");
  const fs::path settings_path = args.Get("--model");
  const fs::path output = args.Get("-o");
  const int folds = ParseInteger("--folds", args.GetOr("--folds", "5"));
  if (folds < 2) throw UsageError("--folds must be at least 2");
  ChainBuilderOptions builder;
  builder.max_sources =
      ParseInteger("--sources", args.GetOr("--sources", std::to_string(builder.max_sources)));
  if (builder.max_sources < 0) throw UsageError("--sources must be >= 0");
  const bool json = args.Flag("--json");
  const bool quiet = args.Flag("--quiet");

  // The settings checked as a model file without terms (errors name the file's own lines), and
  // kept as text the builder appends its terms to: a flow-style or JSON file
  // (`{noise: {position_mm: 1}}`) was refused as "a second YAML document" at a line it does not
  // have.
  const std::string settings_text = ReadFileToString(settings_path);
  const ModelSpec settings = ParseModelSettingsYaml(settings_text, settings_path.string());
  builder.settings_yaml = ModelSettingsBlockYaml(settings_text, settings_path.string());
  LoadedFitData loaded =
      LoadFitData({data, std::nullopt, std::nullopt, SensorOption(args, 0)}, settings);
  PrintPairingWarning(data, loaded);
  std::vector<fs::path> inputs = {settings_path};
  inputs.insert(inputs.end(), loaded.protected_paths.begin(), loaded.protected_paths.end());
  CheckOutputIsNotInput(output, inputs);
  CheckCalibrationOutput(output);
  const std::optional<fs::path> model_out =
      args.values.count("--model-out") ? std::optional<fs::path>(args.Get("--model-out"))
                                       : std::nullopt;
  if (model_out) {
    // A model file is the user's own text: never replaced (a hand-written model.yaml given here by
    // mistake would be lost), and checked before the chain is built, not after.
    CheckOutputIsNotInput(*model_out, inputs);
    std::error_code ec;
    // (weakly_canonical leaves a relative path without an existing prefix as it is.)
    if (fs::absolute(*model_out, ec).lexically_normal() ==
        fs::absolute(output, ec).lexically_normal()) {
      throw UsageError("--model-out and -o name the same file");
    }
    if (fs::exists(*model_out, ec)) {
      throw std::invalid_argument(model_out->string() +
                                  ": --model-out: refusing to overwrite an existing file");
    }
    const fs::path folder =
        model_out->parent_path().empty() ? fs::path(".") : model_out->parent_path();
    if (!fs::is_directory(folder, ec)) {
      throw std::invalid_argument(model_out->string() + ": --model-out: the folder " +
                                  folder.string() + " does not exist");
    }
  }

  const std::vector<FitStation> calib = StationsOfSet(loaded.poses, "calib");
  if (calib.empty()) throw std::invalid_argument(loaded.source + ": no calib stations");
  if (!quiet) std::cerr << "trackcal-fit: building the chain on " << calib.size() << " stations\n";
  FitOptions quick;
  quick.compute_covariance = false;
  const BuiltChain built = BuildChain(calib, builder, quick);
  if (model_out) WriteFileAtomically(*model_out, built.model_text, /*overwrite=*/false);

  FitRunOptions options;
  options.folds = folds;
  options.cross_validate_with_validation_set = false;
  options.tool = "trackcal-fit";
  options.tool_version = kVersion;
  options.description_tool = "trackcal-fit build";
  const FitModelSource model{built.model_text,
                             model_out ? model_out->string() : std::string("<built model>"),
                             std::nullopt};
  FitRunResult run = fit::RunFit(std::move(loaded), model, options);
  {
    std::string cmd;
    for (int i = 0; i < argc; ++i) cmd += (i ? " " : "") + std::string(argv[i]);
    run.calibration.provenance.command_line = cmd;
  }
  if (!run.failure.empty()) throw std::runtime_error(run.failure);
  WriteCalibrationFile(output, run.calibration);

  nlohmann::json steps = nlohmann::json::array();
  for (const auto& s : built.steps) {
    steps.push_back({{"round", s.round}, {"added", s.added.empty() ? "nothing" : s.added},
                     {"score", s.score}, {"degree", s.degree}, {"kept", s.kept},
                     {"seconds", s.seconds}});
  }
  if (json) {
    nlohmann::json doc = run.ToJson(output);
    doc["build"] = {{"steps", steps},
                    {"degree", built.degree},
                    {"ridge", {built.ridge[0], built.ridge[1]}},
                    {"score", built.score},
                    {"model", built.model_text},
                    {"seconds", built.seconds}};
    std::cout << doc.dump(2) << "\n";
    return 0;
  }
  std::cout << "Chain building (score: whitened held-out error per station of the explicit term "
               "after the sources):\n";
  for (const auto& s : built.steps) {
    std::cout << "  round " << s.round << "  +" << std::left << std::setw(12)
              << (s.added.empty() ? "nothing" : s.added) << std::right << std::setprecision(4)
              << std::setw(10) << s.score << "  degree " << s.degree << (s.kept ? "  kept" : "")
              << "\n";
  }
  std::cout << "Explicit term: degree " << built.degree << ", ridge " << built.ridge[0]
            << " (position) / " << built.ridge[1] << " (orientation)\n\n";
  for (const auto& t : run.tables) std::cout << FormatTable1(t) << "\n";
  std::cout << "Model:\n" << built.model_text;
  if (model_out) std::cout << "Wrote " << model_out->string() << "\n";
  std::cout << "Wrote " << output.string() << "\n";
  return 0;
}

// diagnose: which catalog effect is the model missing (fit/candidates.h, docs/diagnose.md).
int RunDiagnose(int argc, char** argv) {
  const Args args = ParseArgs(argc, argv,
                              {"--data", "--model", "--folds", "--effects", "--cross-validate-top",
                               "--threads", "--sensor"},
                              {"--json", "--quiet", "--exact-cv"});
  const fs::path data = args.Get("--data");
  const fs::path model_path = args.Get("--model");
  CandidateOptions options;
  options.folds = ParseInteger("--folds", args.GetOr("--folds", "5"));
  if (options.folds < 2) throw UsageError("--folds must be at least 2");
  options.cross_validate_top =
      ParseInteger("--cross-validate-top", args.GetOr("--cross-validate-top", "3"));
  if (options.cross_validate_top < 0) throw UsageError("--cross-validate-top must be >= 0");
  // Every fold fitted from scratch instead of refitted from the full fit (docs/diagnose.md, Speed).
  options.exact_cv = args.Flag("--exact-cv");
  options.num_threads = ParseInteger("--threads", args.GetOr("--threads", "0"));
  if (options.num_threads < 0) throw UsageError("--threads must be >= 0 (0: all cores)");
  if (args.values.count("--effects")) {
    std::stringstream list(args.Get("--effects"));
    for (std::string name; std::getline(list, name, ',');) {
      if (!name.empty()) options.effects.push_back(name);
    }
    try {
      options.Check();
    } catch (const std::invalid_argument& e) {
      throw UsageError(std::string("--effects: ") + e.what());
    }
  }
  const bool quiet = args.Flag("--quiet");
  if (!quiet) {
    options.progress = [](const std::string& message) {
      std::cerr << "trackcal-fit diagnose: " << message << "\n";
    };
  }
  const std::string model_text = ReadFileToString(model_path);
  const ModelSpec spec = ParseModelYaml(model_text, model_path.string());

  // Data resolved as `fit` resolves it (fit/fit_run.h); streams are paired with the model's
  // time_offset, at the offset `fit` estimates when the model frees it.
  LoadedFitData loaded =
      LoadFitData({data, std::nullopt, std::nullopt, SensorOption(args, 0)}, spec);
  PrintPairingWarning(data, loaded);
  if (!loaded.stream_stations.empty()) {
    if (options.progress) options.progress("fitting the model's clock offset, as fit does");
    loaded = PairAtFittedOffset(std::move(loaded), {model_text, model_path.string(), model_path});
    if (options.progress && loaded.time_offset) {
      std::ostringstream m;
      m << std::fixed << std::setprecision(3) << "streams paired at the fitted clock offset "
        << *loaded.time_offset * 1e3 << " ms";
      options.progress(m.str());
    }
  }
  // The time_offset candidate pairs them again, estimating the offset.
  options.pair_streams = StreamRepairing(loaded, spec);
  const auto calib = StationsOfSet(loaded.poses, "calib");
  if (calib.empty()) {
    throw std::invalid_argument(loaded.source + ": no stations with set 'calib'");
  }
  // Named with the receiver chosen out of several (its stations are the ones counted).
  const int sensor = SensorOption(args, 0);
  Diagnosis diagnosis = DiagnoseCandidates(
      calib, model_text, model_path.string(),
      data.string() + (sensor != 0 ? " (sensor " + std::to_string(sensor) + ")" : ""), options);
  diagnosis.time_offset_s = loaded.time_offset;
  if (args.Flag("--json")) {
    std::cout << diagnosis.ToJson().dump(2) << "\n";
  } else {
    std::cout << FormatDiagnosis(diagnosis);
    std::cout << "(" << std::setprecision(3) << diagnosis.seconds << " s)\n";
  }
  return 0;
}

int RunPair(int argc, char** argv) {
  const Args args = ParseArgs(
      argc, argv,
      {"--tracker", "--reference", "-o", "--time-offset", "--search-range", "--set", "--sensor"},
      {"--json", "--estimate-time-offset"});
  const fs::path tracker_path = args.Get("--tracker");
  const fs::path reference_path = args.Get("--reference");
  const fs::path output = args.Get("-o");
  CheckOutputIsNotInput(output, {tracker_path, reference_path});
  StreamPairingOptions options;
  options.time_offset = ParseNumber("--time-offset", args.GetOr("--time-offset", "0"));
  options.estimate_time_offset = args.Flag("--estimate-time-offset");
  // The warnings of an offset outside the search name this option; there was none to give.
  options.search_range = ParseNumber("--search-range", args.GetOr("--search-range", "0.5"));
  options.set = SetOption(args);
  options.sensor = SensorOption(args, 0);
  const TrackerStream tracker = ReadTrackerStream(tracker_path);
  const ReferenceStream reference = ReadReferenceStream(reference_path);
  const StreamPairingResult result =
      PairStreamsOfFiles(tracker, reference, options, tracker_path, reference_path);
  WritePoses(output, result.poses);
  if (!result.warning.empty()) {
    std::cerr << "warning: " << tracker_path.string() << ", " << reference_path.string() << ": "
              << result.warning << "\n";
  }
  if (args.Flag("--json")) {
    std::cout << PairingJson(result, options.estimate_time_offset, output).dump(2) << "\n";
  } else {
    std::cout << "Paired " << result.poses.records.size() << " samples (" << result.dropped
              << " without reference), time offset " << std::setprecision(6) << result.time_offset
              << " s";
    if (options.estimate_time_offset) {
      std::cout << " +- " << result.time_offset_stddev << " s (estimated, "
                << result.gauss_newton_steps << " Gauss-Newton steps)";
    }
    if (result.clock_drift_corrected) {
      std::cout << ", clock drift " << 1e6 * result.clock_drift_applied << " +- "
                << 1e6 * result.clock_drift_stddev << " ppm corrected (offset at tracker time "
                << std::setprecision(10) << result.clock_drift_origin << " s)";
    }
    std::cout << "\nWrote "
              << output.string() << "\n";
  }
  return 0;
}

int RunRegister(int argc, char** argv) {
  const Args args =
      ParseArgs(argc, argv,
                {"--markers", "--tracker", "-o", "--set", "--poses", "--model",
                 "--optical-noise-mm", "--tracker-noise-mm", "--tracker-noise-deg", "--sensor"},
                {"--json", "--quiet", "--allow-unidentifiable", "--keep-all-stations"});
  // Noise of the averaged readings (fit/registration.h); they set the weights and the covariance.
  RegistrationOptions registration_options;
  auto noise = [&](const std::string& key, double scale, double* out) {
    if (!args.values.count(key)) return;
    const double v = ParseNumber(key, args.Get(key));
    if (!(v > 0)) throw UsageError(key + " must be > 0");
    *out = v * scale;
  };
  noise("--optical-noise-mm", 1e-3, &registration_options.optical_noise_m);
  noise("--tracker-noise-mm", 1e-3, &registration_options.tracker_position_noise_m);
  noise("--tracker-noise-deg", kRadPerDeg, &registration_options.tracker_orientation_noise_rad);
  registration_options.reject_bad_stations = !args.Flag("--keep-all-stations");
  PoseExtractionOptions extraction_options;
  extraction_options.optical_noise_m = registration_options.optical_noise_m;
  const fs::path markers_path = args.Get("--markers");
  const fs::path tracker_path = args.Get("--tracker");
  const fs::path output = args.Get("-o");
  const bool refine = args.values.count("--model") > 0;
  const bool labelled = args.values.count("--poses") > 0;
  if (refine && !labelled) {
    throw UsageError("--model needs --poses: its set column tells the registration stations (reg) "
                     "from the calibration stations (calib) the correction is fitted to");
  }
  if (labelled && args.values.count("--set")) throw UsageError("--set and --poses exclude each other");
  std::vector<fs::path> inputs = {markers_path, tracker_path};
  if (labelled) inputs.push_back(args.Get("--poses"));
  if (refine) inputs.push_back(args.Get("--model"));
  CheckOutputIsNotInput(output, inputs);
  // The receiver that carries the markers (tracker.csv's sensor column); a capture whose marker
  // body is on receiver 2 could not be registered before this option (always sensor 1).
  const int sensor = SensorOption(args, 1);
  const std::vector<RegistrationStation> stations =
      ReadRegistrationStations(markers_path, tracker_path, sensor);

  // Set and time of each station: from --poses, else every station registers and gets --set.
  std::map<int, std::string> set_of;
  std::map<int, double> time_of;
  const std::string default_set = SetOption(args);
  PoseCapture labels;  // --poses: sets, times and extra columns per station
  if (labelled) {
    const fs::path poses_path = args.Get("--poses");
    labels = ReadPoses(poses_path);
    for (const PoseRecord& r : labels.records) {
      set_of[r.station] = r.set;
      time_of[r.station] = r.time;
    }
    for (const RegistrationStation& s : stations) {
      if (!set_of.count(s.station)) {
        throw std::invalid_argument(poses_path.string() + ": column station: no row for station " +
                                    std::to_string(s.station) + " of " +
                                    markers_path.filename().string());
      }
    }
  }
  std::vector<RegistrationStation> registration_stations, calibration_stations;
  for (const RegistrationStation& s : stations) {
    if (!labelled || set_of[s.station] == "reg") registration_stations.push_back(s);
    if (labelled && set_of[s.station] == "calib") calibration_stations.push_back(s);
  }
  if (registration_stations.empty()) {
    if (!labelled) {  // every station registers: none was read
      throw std::invalid_argument(markers_path.string() + ", " + tracker_path.string() +
                                  ": no station has both marker and tracker rows");
    }
    throw std::invalid_argument(args.Get("--poses") + ": no station of " +
                                markers_path.filename().string() + " has set 'reg'");
  }

  RegistrationResult registration;
  std::optional<RegistrationRefinementResult> refinement;
  if (refine) {
    const fs::path model_path = args.Get("--model");
    const std::string model_text = ReadFileToString(model_path);
    ParseModelYaml(model_text, model_path.string());  // errors before any work
    RegistrationRefinementOptions options;
    options.registration = registration_options;
    options.extraction = extraction_options;
    CorrectionFitter engine =
        MakeEngineFitter([model_text, model_path] { return ParseModelYaml(model_text, model_path.string()); });
    const bool quiet = args.Flag("--quiet");
    int round = 0;
    CorrectionFitter fitter = [&](const std::vector<FitStation>& fit_stations) {
      if (!quiet) std::cerr << "trackcal-fit: refinement round " << ++round << "\n";
      return engine(fit_stations);
    };
    refinement = RefineRegistration(registration_stations, calibration_stations, fitter, options);
    registration = refinement->refined;
  } else {
    registration = RegisterOpticalToTransmitter(registration_stations, registration_options);
  }

  for (const RejectedStation& r : registration.rejected_stations) {
    std::cerr << "trackcal-fit register: warning: station " << r.station
              << " left out of the registration: " << r.Why() << " --keep-all-stations keeps it\n";
  }
  // The reference poses inherit every undetermined direction of the transform: not written unless
  // asked for, so a script chaining register and fit stops here (exit 3), with the report printed.
  const bool write_unidentifiable = args.Flag("--allow-unidentifiable");
  if (!registration.identifiable && !write_unidentifiable) {
    if (args.Flag("--json")) {
      nlohmann::json doc = RegisterDocument(registration, std::nullopt, 0, {});
      if (refinement) doc["refinement"] = refinement->ToJson();
      std::cout << doc.dump(2) << "\n";
    } else {
      std::cout << (refinement ? refinement->ToString() : registration.ToString()) << "\n";
    }
    std::cerr << "trackcal-fit register: the registration is not identifiable (the report names "
                 "the poorly identified coordinates); "
              << output.string()
              << " not written. Add stations with other orientations and positions "
                 "(docs/registration.md, Identifiability), or pass --allow-unidentifiable to "
                 "write the poses anyway.\n";
    return 3;
  }
  const auto extracted =
      ExtractPoses(stations, registration.registration, extraction_options, markers_path.string());
  PoseCapture poses;
  std::vector<int> left_out;
  for (size_t i = 0; i < stations.size(); ++i) {
    PoseRecordOptions record_options;
    record_options.set = labelled ? set_of[stations[i].station] : default_set;
    record_options.sensor = sensor;
    const PoseRecords one = MakePoseRecords({stations[i]}, {extracted[i]}, time_of, record_options);
    poses.records.insert(poses.records.end(), one.capture.records.begin(), one.capture.records.end());
    left_out.insert(left_out.end(), one.left_out.begin(), one.left_out.end());
  }
  // Why stations give no pose, said: "Wrote 0 poses" was all a capture whose marker body is
  // collinear got (every station degenerate), exit 0, and fit then failed on the empty file.
  if (!left_out.empty()) {
    const std::string summary = NoPoseSummary(extracted, left_out);
    if (poses.records.empty()) {
      throw std::invalid_argument(markers_path.string() + ": no station gives a reference pose: " +
                                  summary + "; " + output.string() + " not written");
    }
    std::cerr << "trackcal-fit register: warning: " << markers_path.string() << ": "
              << left_out.size() << " of " << stations.size()
              << " stations give no reference pose: " << summary << "\n";
  }
  if (labelled) CopyExtraColumns(labels, &poses);
  WritePoses(output, poses);
  // Poses from markers symmetric enough that two labels swapped fit as well.
  const std::string symmetric = SymmetricMarkersWarning(extracted, extraction_options);
  if (!symmetric.empty()) {
    std::cerr << "trackcal-fit register: warning: " << markers_path.string() << ": " << symmetric
              << "\n";
  }
  if (args.Flag("--json")) {
    nlohmann::json doc = RegisterDocument(registration, output, poses.records.size(), left_out);
    if (refinement) doc["refinement"] = refinement->ToJson();
    std::cout << doc.dump(2) << "\n";
  } else {
    std::cout << (refinement ? refinement->ToString() : registration.ToString()) << "\nWrote "
              << poses.records.size() << " poses to " << output.string() << "\n";
  }
  if (!registration.identifiable) {
    std::cerr << "trackcal-fit register: warning: the registration is not identifiable; the poses "
                 "in "
              << output.string() << " carry its undetermined directions\n";
  }
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  if (argc < 2 || std::string(argv[1]) == "--help" || std::string(argv[1]) == "-h") {
    PrintUsage(argc < 2 ? std::cerr : std::cout);
    return argc < 2 ? 2 : 0;
  }
  const std::string command = argv[1];
  for (int i = 2; i < argc; ++i) {  // `trackcal-fit fit --help` asks, it is not a usage error
    if (std::string(argv[i]) == "--help" || std::string(argv[i]) == "-h") {
      PrintUsage(std::cout);
      return 0;
    }
  }
  try {
    if (command == "fit") return RunFit(argc, argv);
    if (command == "diagnose") return RunDiagnose(argc, argv);
    if (command == "build") return RunBuild(argc, argv);
    if (command == "pair") return RunPair(argc, argv);
    if (command == "register") return RunRegister(argc, argv);
    throw UsageError("unknown command '" + command + "'");
  } catch (const UsageError& e) {
    std::cerr << "trackcal-fit: " << e.what() << "\n";
    PrintUsage(std::cerr);
    return 2;
  } catch (const std::exception& e) {
    std::cerr << "trackcal-fit: error: " << e.what() << "\n";
    return 1;
  }
}
