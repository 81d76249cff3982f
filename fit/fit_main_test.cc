// End to end: trackcal-simulate -> trackcal-fit fit -> the calibration file loads with core/ and
// corrects the validation stations as the tool's table says.
#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <algorithm>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <map>
#include <nlohmann/json.hpp>
#include <regex>
#include <set>
#include <sstream>

#include "core/calibration_file.h"
#include "core/capture.h"
#include "core/error_statistics.h"
#include "core/file_util.h"

namespace trackcal {
namespace {

namespace fs = std::filesystem;

fs::path BinaryDir() {
  const char* dir = std::getenv("TRACKCAL_BINARY_DIR");
  return dir ? fs::path(dir) : fs::current_path().parent_path();
}

int RunCommand(const std::string& command) {
  const int status = std::system(command.c_str());
  return WEXITSTATUS(status);
}

class FitCliTest : public ::testing::Test {
 protected:
  void SetUp() override {
    dir_ = fs::temp_directory_path() /
           ("trackcal_fit_cli_" + std::to_string(::getpid()) + "_" +
            ::testing::UnitTest::GetInstance()->current_test_info()->name());
    fs::remove_all(dir_);
    fs::create_directories(dir_);
    fit_ = (BinaryDir() / "fit" / "trackcal-fit").string();
    ASSERT_EQ(RunCommand((BinaryDir() / "sim" / "trackcal-simulate").string() + " --scene paper -o " +
                  (dir_ / "cap").string() + " > /dev/null"),
              0);
    std::ofstream(dir_ / "model.yaml") << "terms:\n  - type: polynomial\n    degree: 4\n";
  }
  void TearDown() override { fs::remove_all(dir_); }
  fs::path dir_;
  std::string fit_;
};

TEST_F(FitCliTest, Nominal_SimulateFitLoadCorrect) {
  const fs::path out = dir_ / "calib.json";
  const fs::path json = dir_ / "out.json";
  ASSERT_EQ(RunCommand(fit_ + " fit --data " + (dir_ / "cap").string() + " --model " +
                (dir_ / "model.yaml").string() + " -o " + out.string() + " --json --quiet > " +
                json.string()),
            0);
  const auto doc = nlohmann::json::parse(ReadFileToString(json));  // exactly one JSON document
  ASSERT_EQ(doc["tables"].size(), 2u);
  EXPECT_EQ(doc["tables"][1]["set"], "valid");
  EXPECT_FALSE(doc["fit"]["parameters"][0]["values"][0]["stddev"].is_null());

  const Calibration calibration = ReadCalibrationFile(out);
  ASSERT_EQ(calibration.chain.size(), 1u);
  EXPECT_EQ(calibration.provenance.inputs.size(), 2u);
  EXPECT_EQ(calibration.provenance.inputs[1].sha256, Sha256HexOfFile(dir_ / "cap" / "poses.csv"));
  // Correct the validation set with the loaded file: same mean as the tool reported.
  const PoseCapture poses = ReadPoses(dir_ / "cap" / "poses.csv");
  std::vector<Rigid3d> corrected, reference;
  for (const auto& r : poses.records) {
    if (r.set != "valid") continue;
    corrected.push_back(calibration.Apply(r.reported).pose);
    reference.push_back(r.reference);
  }
  const PoseErrorSummary after = SummarizePoseErrors(corrected, reference);
  EXPECT_NEAR(after.position_mm.mean,
              doc["tables"][1]["after"]["position_mm"]["mean"].get<double>(), 1e-9);
  EXPECT_GE(doc["tables"][1]["improvement_percent"]["position_mean"].get<double>(), 88.6);
}

// A lone polynomial is solved in closed form: the text said "converged after 0 iterations". A
// degree-1 polynomial leaves most of the paper room's stations beyond 5 sigma: the outlier line
// listed all 406 ids and nothing said that the model, not the stations, fails.
TEST_F(FitCliTest, TextSaysHowTheFitWasSolvedAndWhenMostStationsAreOutliers) {
  std::ofstream(dir_ / "linear.yaml") << "terms:\n  - type: polynomial\n    degree: 1\n";
  const fs::path text = dir_ / "out.txt";
  ASSERT_EQ(RunCommand(fit_ + " fit --data " + (dir_ / "cap").string() + " --model " +
                       (dir_ / "linear.yaml").string() + " -o " + (dir_ / "c.json").string() +
                       " --quiet > " + text.string()),
            0);
  const std::string out = ReadFileToString(text);
  EXPECT_THAT(out, ::testing::HasSubstr("Fit: solved by linear least squares in "));
  const auto at = out.find("Outlier stations (");
  ASSERT_NE(at, std::string::npos) << out;
  const std::string line = out.substr(at, out.find('\n', at) - at);
  EXPECT_THAT(line, ::testing::HasSubstr(" of 480): "));  // out of the calib stations
  std::istringstream ids(line.substr(line.find("): ") + 3));
  int listed = 0;
  for (std::string id; ids >> id && id != "...";) ++listed;
  EXPECT_EQ(listed, 20) << line;
  EXPECT_THAT(line, ::testing::EndsWith(" more)"));
  EXPECT_THAT(out, ::testing::HasSubstr("most stations are outliers"));
  std::ofstream(dir_ / "lm.yaml")
      << "terms:\n  - type: sensor_offset\n  - type: polynomial\n    degree: 1\n";
  ASSERT_EQ(RunCommand(fit_ + " fit --data " + (dir_ / "cap").string() + " --model " +
                       (dir_ / "lm.yaml").string() + " -o " + (dir_ / "c2.json").string() +
                       " --quiet > " + text.string()),
            0);
  EXPECT_THAT(ReadFileToString(text),
              ::testing::ContainsRegex("Fit: converged after [1-9][0-9]* iterations in "));
}

TEST_F(FitCliTest, BadInputExitsNonZeroNamingTheFile) {
  std::ofstream(dir_ / "bad.yaml") << "terms:\n  - type: polynomial\n    degre: 4\n";
  const fs::path err = dir_ / "err.txt";
  EXPECT_EQ(RunCommand(fit_ + " fit --data " + (dir_ / "cap").string() + " --model " +
                (dir_ / "bad.yaml").string() + " -o " + (dir_ / "c.json").string() + " 2> " +
                err.string()),
            1);
  EXPECT_THAT(ReadFileToString(err), ::testing::HasSubstr("bad.yaml:3:5: $.terms[0].degre: unknown key"));
  EXPECT_FALSE(fs::exists(dir_ / "c.json"));
  // Never overwrites an input.
  EXPECT_EQ(RunCommand(fit_ + " fit --data " + (dir_ / "cap").string() + " --model " +
                (dir_ / "model.yaml").string() + " -o " + (dir_ / "cap" / "poses.csv").string() +
                " --quiet 2> /dev/null"),
            1);
  EXPECT_EQ(RunCommand(fit_ + " frobnicate 2> /dev/null"), 2);
  // The output is checked before the fit: a missing folder, an existing file that is not a
  // calibration (left as it was).
  const std::string fit_to = fit_ + " fit --data " + (dir_ / "cap").string() + " --model " +
                             (dir_ / "model.yaml").string() + " --quiet -o ";
  EXPECT_EQ(RunCommand(fit_to + (dir_ / "no" / "c.json").string() + " 2> " + err.string()), 1);
  EXPECT_THAT(ReadFileToString(err), ::testing::HasSubstr("c.json: cannot write here: the folder"));
  std::ofstream(dir_ / "notes.txt") << "my notes\n";
  EXPECT_EQ(RunCommand(fit_to + (dir_ / "notes.txt").string() + " 2> " + err.string()), 1);
  EXPECT_THAT(ReadFileToString(err),
              ::testing::HasSubstr("notes.txt: refusing to overwrite an existing file that is not "
                                   "a trackcal calibration file"));
  EXPECT_EQ(ReadFileToString(dir_ / "notes.txt"), "my notes\n");
  // A set name no capture can hold is a usage error before any work.
  EXPECT_EQ(RunCommand(fit_ + " pair --tracker a.csv --reference b.csv -o p.csv --set foo 2> " +
                       err.string()),
            2);
  EXPECT_THAT(ReadFileToString(err), ::testing::HasSubstr("--set 'foo' is not one of"));
  for (const char* sensor : {"0", "1.5", "x"}) {
    EXPECT_EQ(RunCommand(fit_ + " pair --tracker a.csv --reference b.csv -o p.csv --sensor " +
                         sensor + " 2> " + err.string()),
              2)
        << sensor;
    EXPECT_THAT(ReadFileToString(err), ::testing::HasSubstr("--sensor")) << sensor;
  }
  // The pairing's own errors name the streams: a tracker stream with a header only.
  std::ofstream(dir_ / "empty_stream.csv") << "time,sensor,x,y,z,qw,qx,qy,qz\n";
  const fs::path reference = dir_ / "cap" / "reference_stream.csv";
  EXPECT_EQ(RunCommand(fit_ + " pair --tracker " + (dir_ / "empty_stream.csv").string() +
                       " --reference " + reference.string() + " -o " + (dir_ / "p.csv").string() +
                       " 2> " + err.string()),
            1);
  EXPECT_THAT(ReadFileToString(err),
              ::testing::HasSubstr("empty_stream.csv, " + reference.string() +
                                   ": tracker stream has fewer than 2 samples"));
  EXPECT_FALSE(fs::exists(dir_ / "p.csv"));
  // So do they when fit pairs a stream folder itself.
  fs::create_directories(dir_ / "empty_streams");
  fs::copy_file(dir_ / "empty_stream.csv", dir_ / "empty_streams" / "tracker_stream.csv");
  fs::copy_file(reference, dir_ / "empty_streams" / "reference_stream.csv");
  EXPECT_EQ(RunCommand(fit_ + " fit --data " + (dir_ / "empty_streams").string() + " --model " +
                       (dir_ / "model.yaml").string() + " --quiet -o " +
                       (dir_ / "c.json").string() + " 2> " + err.string()),
            1);
  EXPECT_THAT(ReadFileToString(err),
              ::testing::HasSubstr("empty_streams/tracker_stream.csv, " +
                                   (dir_ / "empty_streams" / "reference_stream.csv").string() +
                                   ": tracker stream has fewer than 2 samples"));
}

// A --data folder without poses.csv said "DIR/poses.csv: cannot open file" (raw markers, or
// nothing) or "DIR/reference_stream.csv: cannot open file" (a tracker stream alone), where Python's
// trackcal.load names what a capture folder holds.
TEST_F(FitCliTest, DataFolderWithoutACaptureSaysWhatACaptureFolderHolds) {
  const fs::path err = dir_ / "err.txt";
  const auto fit_error = [&](const fs::path& data) {
    EXPECT_EQ(RunCommand(fit_ + " fit --data " + data.string() + " --model " +
                         (dir_ / "model.yaml").string() + " --quiet -o " +
                         (dir_ / "c.json").string() + " 2> " + err.string()),
              1)
        << data;
    EXPECT_FALSE(fs::exists(dir_ / "c.json"));
    return ReadFileToString(err);
  };
  const std::string what =
      ": not a capture folder (no poses.csv, no tracker_stream.csv + reference_stream.csv, no "
      "markers.csv + tracker.csv)";
  fs::create_directories(dir_ / "empty");
  EXPECT_EQ(fit_error(dir_ / "empty"),
            "trackcal-fit: error: " + (dir_ / "empty").string() + what + "\n");
  fs::create_directories(dir_ / "half");
  fs::copy_file(dir_ / "cap" / "tracker_stream.csv", dir_ / "half" / "tracker_stream.csv");
  EXPECT_EQ(fit_error(dir_ / "half"),
            "trackcal-fit: error: " + (dir_ / "half").string() + what +
                "; tracker_stream.csv has no reference_stream.csv beside it to be paired with\n");
  fs::create_directories(dir_ / "raw");
  fs::copy_file(dir_ / "cap" / "markers.csv", dir_ / "raw" / "markers.csv");
  fs::copy_file(dir_ / "cap" / "tracker.csv", dir_ / "raw" / "tracker.csv");
  EXPECT_THAT(fit_error(dir_ / "raw"),
              ::testing::HasSubstr(": raw markers (markers.csv + tracker.csv, no poses.csv): "
                                   "register them first, trackcal-fit register --markers " +
                                   (dir_ / "raw" / "markers.csv").string()));
  // The command it suggests makes a folder trackcal-fit fits.
  EXPECT_EQ(RunCommand(fit_ + " register --markers " + (dir_ / "raw" / "markers.csv").string() +
                       " --tracker " + (dir_ / "raw" / "tracker.csv").string() + " -o " +
                       (dir_ / "raw" / "poses.csv").string() + " > /dev/null"),
            0);
  EXPECT_EQ(RunCommand(fit_ + " fit --data " + (dir_ / "raw").string() + " --model " +
                       (dir_ / "model.yaml").string() + " --quiet -o " +
                       (dir_ / "c.json").string() + " > /dev/null"),
            0);
}

// A fit that failed (the whitened residuals overflow: position noise 1e-160 mm, an infinite cost
// that Ceres called converged) exited 0 and wrote its start values as the calibration, over the
// user's earlier good one. Now: exit 1 naming the model, the data and what failed; the earlier
// calibration is left as it was; with --json the report (termination_type FAILURE) is printed.
TEST_F(FitCliTest, AFailedFitExitsNonZeroAndWritesNoCalibration) {
  std::ofstream(dir_ / "overflow.yaml")
      << "noise:\n  position_mm: 1e-160\nterms:\n  - type: sensor_offset\n  - type: polynomial\n"
         "    degree: 1\n";
  const fs::path out = dir_ / "calib.json";
  ASSERT_EQ(
      RunCommand(fit_ + " fit --data " + (dir_ / "cap").string() + " --model " +
                 (dir_ / "model.yaml").string() + " -o " + out.string() + " --quiet > /dev/null"),
      0);
  const std::string good = ReadFileToString(out);
  const fs::path err = dir_ / "err.txt";
  const fs::path json = dir_ / "out.json";
  for (const std::string command : {"fit", "fit --json"}) {
    SCOPED_TRACE(command);
    EXPECT_EQ(RunCommand(fit_ + " " + command + " --data " + (dir_ / "cap").string() + " --model " +
                         (dir_ / "overflow.yaml").string() + " -o " + out.string() + " --quiet > " +
                         json.string() + " 2> " + err.string()),
              1);
    const std::string message = ReadFileToString(err);
    EXPECT_THAT(message, ::testing::HasSubstr("overflow.yaml: the fit to "));
    EXPECT_THAT(message, ::testing::HasSubstr("poses.csv failed (FAILURE: "));
    EXPECT_THAT(message, ::testing::HasSubstr("no calibration is written"));
    EXPECT_EQ(ReadFileToString(out), good);  // the earlier calibration is kept
  }
  const auto doc = nlohmann::json::parse(ReadFileToString(json));
  EXPECT_EQ(doc["fit"]["termination_type"], "FAILURE");
  EXPECT_FALSE(doc["fit"]["converged"].get<bool>());
  EXPECT_TRUE(doc["output"].is_null());
  // diagnose ranked candidates against that failed base (its start values: "held-out error
  // 21.2 mm ... chi2/dof inf", exit 0); with every effect it crashed (SIGSEGV) in a candidate's
  // covariance.
  EXPECT_EQ(RunCommand(fit_ + " diagnose --data " + (dir_ / "cap").string() + " --model " +
                       (dir_ / "overflow.yaml").string() + " --effects dipole --quiet > " +
                       json.string() + " 2> " + err.string()),
            1);
  EXPECT_THAT(ReadFileToString(err),
              ::testing::HasSubstr("overflow.yaml: the model's own fit to " +
                                   (dir_ / "cap").string() + " failed (FAILURE: "));
}

// An option given twice took the last value without a word (`-o a.json -o b.json` wrote b.json),
// `-o --json` wrote the calibration to a file named "--json", and `--folds 2.5` ran 2 folds.
TEST_F(FitCliTest, AmbiguousOptionsAreUsageErrors) {
  const fs::path err = dir_ / "err.txt";
  const std::string fit = fit_ + " fit --data " + (dir_ / "cap").string() + " --model " +
                          (dir_ / "model.yaml").string() + " --quiet ";
  const fs::path a = dir_ / "a.json", b = dir_ / "b.json";
  EXPECT_EQ(RunCommand(fit + "-o " + a.string() + " -o " + b.string() + " 2> " + err.string()), 2);
  EXPECT_THAT(ReadFileToString(err), ::testing::HasSubstr("-o given twice"));
  EXPECT_FALSE(fs::exists(a));
  EXPECT_FALSE(fs::exists(b));
  EXPECT_EQ(RunCommand(fit + "--data " + (dir_ / "cap").string() + " -o " + a.string() + " 2> " +
                       err.string()),
            2);
  EXPECT_THAT(ReadFileToString(err), ::testing::HasSubstr("--data given twice"));
  EXPECT_EQ(RunCommand("cd " + dir_.string() + " && " + fit + "-o --json 2> " + err.string()), 2);
  EXPECT_THAT(ReadFileToString(err), ::testing::HasSubstr("-o needs a value, got '--json'"));
  EXPECT_FALSE(fs::exists(dir_ / "--json"));
  EXPECT_EQ(RunCommand(fit + "-o '' 2> " + err.string()), 2);
  EXPECT_THAT(ReadFileToString(err), ::testing::HasSubstr("-o needs a value, got ''"));
  EXPECT_EQ(RunCommand(fit + "-o " + a.string() + " --folds 2.5 2> " + err.string()), 2);
  EXPECT_THAT(ReadFileToString(err),
              ::testing::HasSubstr("--folds: expected a whole number, got 2.5"));
  EXPECT_FALSE(fs::exists(a));
}

// More folds than calibration stations: the fit ran to its end and the cross-validation refused
// the folds only then (minutes on a large model), naming neither the data nor the remedy.
TEST_F(FitCliTest, MoreFoldsThanStationsAreRefusedBeforeTheFit) {
  std::ifstream in(dir_ / "cap" / "poses.csv");
  std::ofstream few(dir_ / "few.csv");
  std::string line;
  std::getline(in, line);
  few << line << "\n";
  int kept = 0;
  while (kept < 12 && std::getline(in, line)) {
    if (line.find(",calib,") == std::string::npos) continue;
    few << line << "\n";
    ++kept;
  }
  few.close();
  ASSERT_EQ(kept, 12);
  std::ofstream(dir_ / "linear.yaml") << "terms:\n  - type: polynomial\n    degree: 1\n";
  const fs::path err = dir_ / "err.txt", out = dir_ / "out.json";
  EXPECT_EQ(RunCommand(fit_ + " fit --data " + (dir_ / "few.csv").string() + " --model " +
                       (dir_ / "linear.yaml").string() + " --folds 20 -o " + out.string() +
                       " --quiet 2> " + err.string()),
            1);
  const std::string text = ReadFileToString(err);
  EXPECT_THAT(text, ::testing::HasSubstr("few.csv: 12 calibration stations cannot be split into "
                                         "20 cross-validation folds"));
  EXPECT_FALSE(fs::exists(out));
}

// In a capture of several receivers, the refusals about too few stations name the receiver they
// counted (--sensor): "few.csv: 12 calibration stations" left the user to guess which, while the
// file holds 24.
TEST_F(FitCliTest, TooFewStationsOfOneReceiverNameIt) {
  std::ifstream in(dir_ / "cap" / "poses.csv");
  std::ofstream few(dir_ / "two.csv");
  std::string line;
  std::getline(in, line);
  ASSERT_EQ(line.rfind("station,set,sensor,", 0), 0u) << line;
  few << line << "\n";
  std::vector<std::string> rows;
  while (rows.size() < 12 && std::getline(in, line)) {
    if (line.find(",calib,1,") != std::string::npos) rows.push_back(line);
  }
  ASSERT_EQ(rows.size(), 12u);
  for (const std::string& r : rows) few << r << "\n";
  for (const std::string& r : rows) {  // the same poses as receiver 2, stations 100000 + id
    few << "100000" << r.substr(0, r.find(",calib,1,")) << ",calib,2,"
        << r.substr(r.find(",calib,1,") + 9) << "\n";
  }
  few.close();
  std::ofstream(dir_ / "linear.yaml") << "terms:\n  - type: polynomial\n    degree: 1\n";
  const fs::path err = dir_ / "err.txt", out = dir_ / "out.json";
  const std::string data = " --data " + (dir_ / "two.csv").string() + " --model " +
                           (dir_ / "linear.yaml").string() + " --sensor 2";
  EXPECT_EQ(RunCommand(fit_ + " fit" + data + " --folds 20 -o " + out.string() + " --quiet 2> " +
                       err.string()),
            1);
  EXPECT_THAT(ReadFileToString(err),
              ::testing::HasSubstr("two.csv (sensor 2): 12 calibration stations cannot be split "
                                   "into 20 cross-validation folds"));
  EXPECT_EQ(RunCommand(fit_ + " diagnose" + data + " --folds 7 --quiet 2> " + err.string()), 1);
  EXPECT_THAT(ReadFileToString(err),
              ::testing::HasSubstr("two.csv (sensor 2): diagnose needs at least 14 calibration "
                                   "stations, got 12"));
}

// --start: a fit of a model with an added term starts at a previous fit's optimum (its --json
// document), so its first cost is that fit's final cost; a file that is not one is refused by name.
TEST_F(FitCliTest, StartFromAPreviousFit) {
  const std::string head =
      "noise: {amplification_threshold: 1e9}\nterms:\n  - type: sensor_offset\n";
  std::ofstream(dir_ / "base.yaml") << head << "  - {type: polynomial, degree: 3}\n";
  std::ofstream(dir_ / "more.yaml") << head << "  - type: receiver_gain\n"
                                     << "  - {type: polynomial, degree: 3}\n";
  const std::string data = " --data " + (dir_ / "cap").string();
  ASSERT_EQ(RunCommand(fit_ + " fit" + data + " --model " + (dir_ / "base.yaml").string() +
                       " -o " + (dir_ / "base.json").string() + " --json --quiet > " +
                       (dir_ / "base.out").string()),
            0);
  ASSERT_EQ(RunCommand(fit_ + " fit" + data + " --model " + (dir_ / "more.yaml").string() +
                       " -o " + (dir_ / "more.json").string() + " --start " +
                       (dir_ / "base.out").string() + " --json --quiet > " +
                       (dir_ / "more.out").string()),
            0);
  const auto base = nlohmann::json::parse(ReadFileToString(dir_ / "base.out"));
  const auto more = nlohmann::json::parse(ReadFileToString(dir_ / "more.out"));
  const double cost = base["fit"]["final_cost"].get<double>();
  // Receiver gains at the identity leave the base's chain; 1e-6 relative is the physical group's
  // iterative inverse (fit/fit_engine_test.cc, StartAddsAnEffectBeforeTheHeldPolynomial).
  EXPECT_NEAR(more["fit"]["initial_cost"].get<double>(), cost, 1e-6 * cost);
  EXPECT_LE(more["fit"]["final_cost"].get<double>(), cost * (1 + 1e-6));
  // The same document saved with a UTF-8 byte order mark (PowerShell's Out-File -Encoding utf8,
  // Notepad): JSON readers skip it, as the calibration reader does. The check for a model file
  // given here ("does not start with '{'") refused it.
  std::ofstream(dir_ / "bom.out") << "\xEF\xBB\xBF" << ReadFileToString(dir_ / "base.out");
  EXPECT_EQ(RunCommand(fit_ + " fit" + data + " --model " + (dir_ / "more.yaml").string() + " -o " +
                       (dir_ / "bom.json").string() + " --start " + (dir_ / "bom.out").string() +
                       " --json --quiet > " + (dir_ / "bom_more.out").string()),
            0);
  EXPECT_EQ(nlohmann::json::parse(ReadFileToString(dir_ / "bom_more.out"))["fit"]["initial_cost"],
            more["fit"]["initial_cost"]);

  std::ofstream(dir_ / "not_a_fit.json") << "{\"fit\": {\"terms\": 3}}\n";
  const fs::path err = dir_ / "err.txt";
  EXPECT_EQ(RunCommand(fit_ + " fit" + data + " --model " + (dir_ / "more.yaml").string() +
                       " -o " + (dir_ / "x.json").string() + " --start " +
                       (dir_ / "not_a_fit.json").string() + " --quiet 2> " + err.string()),
            1);
  // An error in the document names its line and column, as the calibration file's do (it said
  // "not_a_fit.json: fit.terms: missing", leaving a hand editor to search a long document).
  EXPECT_THAT(ReadFileToString(err),
              ::testing::HasSubstr("not_a_fit.json:1:10: $.fit.terms: missing"));
  EXPECT_FALSE(fs::exists(dir_ / "x.json"));
  std::ofstream(dir_ / "bad_value.json")
      << "{\"fit\": {\"terms\": [{\"name\": \"polynomial\", \"type\": \"polynomial\"}],\n"
      << "  \"parameters\": [{\"term\": \"polynomial\", \"block\": \"position_coefficients\",\n"
      << "    \"values\": [{\"value\": \"x\"}]}]}}\n";
  std::ofstream(dir_ / "bare_fit.json") << "{\"terms\": 3}\n";  // the "fit" alone
  for (const auto& [start, message] : std::vector<std::pair<std::string, std::string>>{
           {"bad_value.json", ":3:5: $.fit.parameters[0].values: each needs a numeric value"},
           {"bare_fit.json", ":1:2: $.terms: missing"}}) {
    EXPECT_EQ(RunCommand(fit_ + " fit" + data + " --model " + (dir_ / "more.yaml").string() +
                         " -o " + (dir_ / "x.json").string() + " --start " +
                         (dir_ / start).string() + " --quiet 2> " + err.string()),
              1)
        << start;
    EXPECT_THAT(ReadFileToString(err), ::testing::HasSubstr((dir_ / start).string() + message));
  }

  // A model file, an empty file and a cut document: the parser's raw text ("[json.exception.
  // parse_error.101] parse error at line 1, column 2") named no line:column and not what --start
  // takes.
  std::ofstream(dir_ / "empty.json") << "\n";
  std::ofstream(dir_ / "cut.json") << "{\"fit\": {\n  \"final_cost\": tru\n";
  const std::string takes =
      "; --start takes the JSON that `trackcal-fit fit --json` printed for an earlier fit";
  for (const auto& [start, message] : std::vector<std::pair<std::string, std::string>>{
           {"more.yaml",
            ": not a JSON document (it does not start with '{'; a model file or a calibration's "
            "YAML?)"},
           {"empty.json", ": empty file"},
           {"cut.json", ":2:"}}) {
    EXPECT_EQ(RunCommand(fit_ + " fit" + data + " --model " + (dir_ / "more.yaml").string() +
                         " -o " + (dir_ / "x.json").string() + " --start " +
                         (dir_ / start).string() + " --quiet 2> " + err.string()),
              1)
        << start;
    const std::string text = ReadFileToString(err);
    EXPECT_THAT(text, ::testing::HasSubstr((dir_ / start).string() + message)) << start;
    EXPECT_THAT(text, ::testing::HasSubstr(takes)) << start;
    EXPECT_THAT(text, ::testing::Not(::testing::HasSubstr("json.exception"))) << start;
  }
  EXPECT_FALSE(fs::exists(dir_ / "x.json"));
}

// A start document whose prepared state is not a fit's: a polynomial's zero input_scale crashed
// the fit (SIGSEGV, exit 139), a LUT's unordered axes were blamed on "LUT axis x" without a file.
TEST_F(FitCliTest, ABrokenStartIsNamedNotACrash) {
  const fs::path err = dir_ / "err.txt";
  const std::string data = " --data " + (dir_ / "cap").string();
  std::ofstream(dir_ / "lut.yaml") << "terms:\n  - {type: lut, cell_size_mm: 500}\n";
  for (const std::string model : {"model", "lut"}) {
    const fs::path yaml = dir_ / (model + ".yaml");
    ASSERT_EQ(RunCommand(fit_ + " fit" + data + " --model " + yaml.string() + " -o " +
                         (dir_ / (model + ".json")).string() + " --json --quiet > " +
                         (dir_ / "start.out").string()),
              0);
    auto doc = nlohmann::json::parse(ReadFileToString(dir_ / "start.out"));
    nlohmann::json& prepared = doc["fit"]["terms"][0]["prepared"];
    if (model == "model") {
      prepared["input_scale"] = {0.0, 0.0, 0.0};
    } else {
      prepared["axes"][0] = {1.0, 0.0};
    }
    std::ofstream(dir_ / "broken.json") << doc.dump();
    EXPECT_EQ(RunCommand(fit_ + " fit" + data + " --model " + yaml.string() + " -o " +
                         (dir_ / "x.json").string() + " --start " +
                         (dir_ / "broken.json").string() + " --quiet 2> " + err.string()),
              1)
        << model;
    EXPECT_THAT(
        ReadFileToString(err),
        ::testing::HasSubstr("broken.json: fit.terms: '" +
                             std::string(model == "model" ? "polynomial" : "lut") + "' prepared: " +
                             (model == "model"
                                  ? "polynomial: prepared state: input_scale: expected 3 finite "
                                    "numbers > 0"
                                  : "lut: prepared state: axes: expected 3 lists")))
        << model;
    EXPECT_FALSE(fs::exists(dir_ / "x.json"));
  }
}

TEST_F(FitCliTest, HelpAfterACommandPrintsTheUsageAndSucceeds) {
  const fs::path out = dir_ / "help.txt";
  EXPECT_EQ(RunCommand(fit_ + " diagnose --help > " + out.string()), 0);
  EXPECT_THAT(ReadFileToString(out), ::testing::HasSubstr("trackcal-fit diagnose --data"));
}

TEST_F(FitCliTest, RegisterWritesReferencePoses) {
  const fs::path json = dir_ / "reg.json";
  ASSERT_EQ(RunCommand(fit_ + " register --markers " + (dir_ / "cap" / "markers.csv").string() +
                       " --tracker " + (dir_ / "cap" / "tracker.csv").string() + " -o " +
                       (dir_ / "reg_poses.csv").string() + " --json > " + json.string()),
            0);
  const auto doc = nlohmann::json::parse(ReadFileToString(json));
  EXPECT_TRUE(doc["converged"].get<bool>());
  const PoseCapture poses = ReadPoses(dir_ / "reg_poses.csv");
  EXPECT_EQ(static_cast<int>(poses.records.size()), doc["num_poses"].get<int>());
  EXPECT_GT(poses.records.size(), 0u);
}

// diagnose: one JSON document with the contract's keys (docs/diagnose.md); a robust-loss candidate
// is never claimed for a hemisphere-flip-free capture; the text output ends with the verdict.
TEST_F(FitCliTest, DiagnoseJsonAndText) {
  const fs::path json = dir_ / "diagnose.json";
  ASSERT_EQ(RunCommand(fit_ + " diagnose --data " + (dir_ / "cap").string() + " --model " +
                       (dir_ / "model.yaml").string() +
                       " --folds 3 --effects robust_loss --json --quiet > " + json.string()),
            0);
  const auto doc = nlohmann::json::parse(ReadFileToString(json));  // exactly one document
  EXPECT_EQ(doc["command"], "diagnose");
  EXPECT_EQ(doc["folds"], 3);
  EXPECT_EQ(doc["num_stations"], 480);
  EXPECT_TRUE(doc["base"]["cv_position_mm_mean"].is_number());
  EXPECT_EQ(doc["base"]["table1"]["set"], "cross-validation (3-fold)");
  ASSERT_EQ(doc["candidates"].size(), 1u);
  EXPECT_EQ(doc["candidates"][0]["effect"], "robust_loss");
  EXPECT_TRUE(doc["candidates"][0]["insert_index"].is_null());
  EXPECT_FALSE(doc["candidates"][0]["significant"].get<bool>());
  EXPECT_TRUE(doc["verdict"]["effect"].is_null());

  const fs::path text = dir_ / "diagnose.txt";
  ASSERT_EQ(RunCommand(fit_ + " diagnose --data " + (dir_ / "cap").string() + " --model " +
                       (dir_ / "model.yaml").string() + " --folds 3 --effects robust_loss > " +
                       text.string() + " 2> /dev/null"),
            0);
  EXPECT_THAT(ReadFileToString(text), ::testing::HasSubstr("Verdict: No catalog effect explains"));
  EXPECT_EQ(RunCommand(fit_ + " diagnose --data " + (dir_ / "cap").string() + " --model " +
                       (dir_ / "model.yaml").string() + " --effects teleportation 2> /dev/null"),
            2);
}

// build: the builder's chain (fit/chain_builder.h) on the paper capture, two sources at most (the
// CLI's plumbing; the builder's figures are fit/best_chain_sim_test's): it writes the model it built,
// which fits again, and a calibration file; a settings file with terms is refused naming the file.
TEST_F(FitCliTest, BuildWritesTheChainAndTheModel) {
  std::ofstream(dir_ / "settings.yaml")
      << "noise: {position_mm: 0.25, orientation_deg: 0.04, position_range_exponent: 4, "
         "orientation_range_exponent: 3}\nsolver: {covariance: false}\n";
  const fs::path out = dir_ / "calib.json", model = dir_ / "built.yaml", json = dir_ / "build.json";
  ASSERT_EQ(RunCommand(fit_ + " build --data " + (dir_ / "cap").string() + " --model " +
                       (dir_ / "settings.yaml").string() + " --sources 2 -o " + out.string() +
                       " --model-out " + model.string() + " --json --quiet > " + json.string()),
            0);
  const auto doc = nlohmann::json::parse(ReadFileToString(json));
  ASSERT_TRUE(doc["build"].is_object());
  // The start (no source), then the first round's four candidates (dipole + plane, dipole, plane,
  // dipole pair).
  ASSERT_GE(doc["build"]["steps"].size(), 5u);
  EXPECT_EQ(doc["build"]["steps"][0]["added"], "nothing");
  EXPECT_EQ(doc["build"]["steps"][1]["added"], "dipole_plane");
  EXPECT_EQ(doc["build"]["model"], ReadFileToString(model));
  // The paper preset's uncorrected validation error is ~40 mm; the chain's is below a millimetre
  // (the degree-4 polynomial alone leaves ~3 mm).
  const auto& valid = doc["tables"][1];
  EXPECT_EQ(valid["set"], "valid");
  EXPECT_LT(valid["after"]["position_mm"]["mean"].get<double>(), 1.0);
  const Calibration cal = ReadCalibrationFile(out);
  EXPECT_EQ(cal.chain.term(0).TypeName(), "physical");
  // The model written fits again.
  EXPECT_EQ(RunCommand(fit_ + " fit --data " + (dir_ / "cap").string() + " --model " +
                       model.string() + " -o " + (dir_ / "again.json").string() +
                       " --quiet > /dev/null"),
            0);

  std::ofstream(dir_ / "with_terms.yaml") << "terms:\n  - type: polynomial\n    degree: 2\n";
  const fs::path err = dir_ / "err.txt";
  EXPECT_EQ(RunCommand(fit_ + " build --data " + (dir_ / "cap").string() + " --model " +
                       (dir_ / "with_terms.yaml").string() + " -o " + out.string() + " 2> " +
                       err.string()),
            1);
  EXPECT_THAT(ReadFileToString(err),
              ::testing::HasSubstr("with_terms.yaml:2:3: $.terms: build chooses the terms itself"));
  // --model-out never replaces a file (a hand-written model given by mistake would be lost).
  const std::string built_text = ReadFileToString(model);
  EXPECT_EQ(RunCommand(fit_ + " build --data " + (dir_ / "cap").string() + " --model " +
                       (dir_ / "settings.yaml").string() + " -o " + out.string() +
                       " --model-out " + model.string() + " --quiet 2> " + err.string()),
            1);
  EXPECT_THAT(ReadFileToString(err),
              ::testing::HasSubstr("--model-out: refusing to overwrite an existing file"));
  EXPECT_EQ(ReadFileToString(model), built_text);
  // One file for both outputs is refused before the chain is built (it was found only after the
  // fit, with the model written where the calibration was to go).
  EXPECT_EQ(RunCommand("cd " + dir_.string() + " && " + fit_ + " build --data cap --model " +
                       "settings.yaml -o ./same.json --model-out same.json --quiet 2> " +
                       err.string()),
            2);
  EXPECT_THAT(ReadFileToString(err), ::testing::HasSubstr("--model-out and -o name the same file"));
  EXPECT_FALSE(fs::exists(dir_ / "same.json"));
  // A syntax error in the settings names the file and line.
  std::ofstream(dir_ / "broken.yaml") << "noise: {position_mm: 0.25\nsolver: {}\n";
  EXPECT_EQ(RunCommand(fit_ + " build --data " + (dir_ / "cap").string() + " --model " +
                       (dir_ / "broken.yaml").string() + " -o " + out.string() + " 2> " +
                       err.string()),
            1);
  EXPECT_THAT(ReadFileToString(err), ::testing::HasSubstr("broken.yaml:"));
  EXPECT_THAT(ReadFileToString(err), ::testing::HasSubstr("YAML syntax error"));
}

// A settings file in flow style or JSON was refused as "a second YAML document (after ---)" at a
// line the file does not have: the builder appended its `terms:` to the text.
TEST_F(FitCliTest, BuildTakesJsonSettings) {
  std::ofstream(dir_ / "settings.json")
      << "{\"noise\": {\"position_mm\": 0.25, \"orientation_deg\": 0.04}, "
         "\"solver\": {\"covariance\": false}}\n";
  const fs::path model = dir_ / "built.yaml", err = dir_ / "err.txt";
  ASSERT_EQ(RunCommand(fit_ + " build --data " + (dir_ / "cap").string() + " --model " +
                       (dir_ / "settings.json").string() + " --sources 0 -o " +
                       (dir_ / "calib.json").string() + " --model-out " + model.string() +
                       " --quiet > /dev/null 2> " + err.string()),
            0)
      << ReadFileToString(err);
  EXPECT_THAT(ReadFileToString(model), ::testing::HasSubstr("position_mm: 0.25"));
  EXPECT_EQ(
      RunCommand(fit_ + " fit --data " + (dir_ / "cap").string() + " --model " + model.string() +
                 " -o " + (dir_ / "again.json").string() + " --quiet > /dev/null"),
      0);
}

TEST_F(FitCliTest, PairJson) {
  const fs::path json = dir_ / "pair.json";
  ASSERT_EQ(RunCommand((BinaryDir() / "sim" / "trackcal-simulate").string() +
                       " --scene paper --hidden clock_offset -o " + (dir_ / "cap2").string() +
                       " > /dev/null"),
            0);
  ASSERT_EQ(RunCommand(fit_ + " pair --tracker " + (dir_ / "cap2" / "tracker_stream.csv").string() +
                " --reference " + (dir_ / "cap2" / "reference_stream.csv").string() +
                " --estimate-time-offset -o " + (dir_ / "paired.csv").string() + " --json > " +
                json.string()),
            0);
  const auto doc = nlohmann::json::parse(ReadFileToString(json));
  // The scene's clock_offset effect: reference clock = tracker clock + 37 ms, recovered within
  // 3 sigma of the reported standard deviation (~0.3 ms; fit/stream_pairing_sim_test).
  const double stddev = doc["time_offset_stddev_s"].get<double>();
  EXPECT_GT(stddev, 0.0);
  EXPECT_LT(stddev, 1e-3);
  EXPECT_NEAR(doc["time_offset_s"].get<double>(), 0.037, 3.0 * stddev);
  EXPECT_GT(ReadPoses(dir_ / "paired.csv").records.size(), 100u);
}

TEST_F(FitCliTest, PairSaysWhenTheOffsetIsOutsideTheSearchAndTakesAWiderOne) {
  // A reference clock 3 s behind: the default search (0 +- 0.5 s) paired poses of unrelated times
  // without a warning, and pair had no option to search further.
  ASSERT_EQ(RunCommand((BinaryDir() / "sim" / "trackcal-simulate").string() +
                       " --scene paper --hidden clock_offset -o " + (dir_ / "cap3").string() +
                       " > /dev/null"),
            0);
  const fs::path reference = dir_ / "cap3" / "reference_stream.csv";
  ReferenceStream shifted = ReadReferenceStream(reference);
  for (auto& r : shifted.records) r.time -= 3.0;
  const fs::path moved = dir_ / "shifted_reference.csv";
  WriteReferenceStream(moved, shifted);
  const std::string pair = fit_ + " pair --tracker " +
                           (dir_ / "cap3" / "tracker_stream.csv").string() + " --reference " +
                           moved.string() + " --estimate-time-offset --json";
  const fs::path err = dir_ / "pair3.err";
  ASSERT_EQ(
      RunCommand(pair + " -o " + (dir_ / "p1.csv").string() + " > /dev/null 2> " + err.string()),
      0);
  EXPECT_THAT(
      ReadFileToString(err),
      ::testing::HasSubstr("no clock offset in the searched 0 +- 500 ms pairs the streams"));
  const fs::path json = dir_ / "pair3.json";
  ASSERT_EQ(RunCommand(pair + " --search-range 4 -o " + (dir_ / "p2.csv").string() + " > " +
                       json.string() + " 2> " + err.string()),
            0);
  const auto doc = nlohmann::json::parse(ReadFileToString(json));
  EXPECT_NEAR(doc["time_offset_s"].get<double>(), 0.037 - 3.0,
              3.0 * doc["time_offset_stddev_s"].get<double>());
  EXPECT_EQ(doc["warning"].get<std::string>(), "");
  EXPECT_EQ(ReadFileToString(err), "");
}

TEST_F(FitCliTest, FitStreamsEstimatesTheClockOffsetWithTheModel) {
  ASSERT_EQ(RunCommand((BinaryDir() / "sim" / "trackcal-simulate").string() +
                       " --scene paper --hidden clock_offset -o " + (dir_ / "streams").string() +
                       " > /dev/null"),
            0);
  fs::remove(dir_ / "streams" / "poses.csv");  // streams only: the fit pairs them
  std::ofstream(dir_ / "joint.yaml") << "time_offset: {value: 0, fixed: false}\n"
                                        "terms:\n  - type: polynomial\n    degree: 3\n";
  const fs::path json = dir_ / "joint.json";
  ASSERT_EQ(RunCommand(fit_ + " fit --data " + (dir_ / "streams").string() + " --model " +
                       (dir_ / "joint.yaml").string() + " -o " + (dir_ / "joint_calib.json").string() +
                       " --folds 2 --quiet --json > " + json.string()),
            0);
  const auto doc = nlohmann::json::parse(ReadFileToString(json));
  const auto& last = doc["fit"]["parameters"].back();
  ASSERT_EQ(last["term"], "time_offset");
  const double dt = last["values"][0]["value"].get<double>();
  const double stddev = last["values"][0]["stddev"].get<double>();
  EXPECT_NEAR(dt, 0.037, 3.0 * stddev);
  EXPECT_DOUBLE_EQ(doc["time_offset_s"].get<double>(), dt);
  // 30 s identify the offset at degree 3 (docs/fit.md, "Short streams"): nothing to warn of.
  EXPECT_EQ(doc.value("pairing_warning", std::string("(missing)")), "");
}

// A 10 s stream lets the pairing's degree-3 error model mimic a time shift (variance inflation
// 122-135 on the paper preset, limit 10; docs/fit.md, "Short streams"), so the pairing lowers the
// degree and warns. `fit` on the folder tells the user as `pair` does: on stderr naming both
// streams (with --quiet too: it is not progress), in --json and in the calibration's statistics.
TEST_F(FitCliTest, FitStreamsRepeatsThePairingWarning) {
  std::ofstream(dir_ / "short.yaml") << "base: paper\ncapture:\n  stream:\n    duration_s: 10\n";
  const fs::path streams = dir_ / "short_streams";
  ASSERT_EQ(RunCommand((BinaryDir() / "sim" / "trackcal-simulate").string() + " --scene " +
                       (dir_ / "short.yaml").string() + " --hidden clock_offset -o " +
                       streams.string() + " > /dev/null"),
            0);
  fs::remove(streams / "poses.csv");  // streams only: the fit pairs them
  std::ofstream(dir_ / "joint.yaml") << "time_offset: {value: 0, fixed: false}\n"
                                        "terms:\n  - type: polynomial\n    degree: 3\n";
  const fs::path json = dir_ / "joint.json", err = dir_ / "err.txt", out = dir_ / "calib.json";
  ASSERT_EQ(RunCommand(fit_ + " fit --data " + streams.string() + " --model " +
                       (dir_ / "joint.yaml").string() + " -o " + out.string() +
                       " --folds 2 --quiet --json > " + json.string() + " 2> " + err.string()),
            0);
  const std::string expected = "warning: " + (streams / "tracker_stream.csv").string() + ", " +
                               (streams / "reference_stream.csv").string() +
                               ": the clock offset is poorly identified with a degree-3";
  EXPECT_THAT(ReadFileToString(err), ::testing::HasSubstr(expected));
  const auto doc = nlohmann::json::parse(ReadFileToString(json));  // stdout: the document only
  ASSERT_TRUE(doc.contains("pairing_warning"));
  const std::string warning = doc["pairing_warning"].get<std::string>();
  EXPECT_THAT(warning, ::testing::StartsWith("the clock offset is poorly identified"));
  EXPECT_EQ(ReadCalibrationFile(out).fit_statistics.value("pairing_warning", std::string()),
            warning);
}

TEST_F(FitCliTest, RegisterRefusesToWritePosesOfAnUnidentifiableRegistration) {
  // Ten copies of one station: the transform trades off against the marker positions (rank
  // deficient, docs/registration.md "Identifiability"), so the reference poses would be arbitrary.
  const MarkerCapture markers = ReadMarkers(dir_ / "cap" / "markers.csv");
  const TrackerCapture tracker = ReadTracker(dir_ / "cap" / "tracker.csv");
  std::map<int, int> markers_at;
  for (const MarkerRecord& m : markers.records) ++markers_at[m.station];
  const int station = std::max_element(markers_at.begin(), markers_at.end(), [](auto& a, auto& b) {
                        return a.second < b.second;
                      })->first;
  MarkerCapture same_markers;
  TrackerCapture same_tracker;
  for (int copy = 1; copy <= 10; ++copy) {
    for (MarkerRecord m : markers.records) {
      if (m.station != station) continue;
      m.station = copy;
      same_markers.records.push_back(m);
    }
    for (TrackerRecord t : tracker.records) {
      if (t.station != station) continue;
      t.station = copy;
      same_tracker.records.push_back(t);
    }
  }
  WriteMarkers(dir_ / "same_markers.csv", same_markers);
  WriteTracker(dir_ / "same_tracker.csv", same_tracker);
  const std::string command = fit_ + " register --markers " + (dir_ / "same_markers.csv").string() +
                              " --tracker " + (dir_ / "same_tracker.csv").string() + " -o " +
                              (dir_ / "same_poses.csv").string() + " --json > " +
                              (dir_ / "same.json").string() + " 2> " + (dir_ / "err.txt").string();
  EXPECT_EQ(RunCommand(command), 3);
  EXPECT_FALSE(fs::exists(dir_ / "same_poses.csv"));
  const auto doc = nlohmann::json::parse(ReadFileToString(dir_ / "same.json"));
  EXPECT_FALSE(doc["identifiable"].get<bool>());
  EXPECT_TRUE(doc["output"].is_null());
  EXPECT_THAT(ReadFileToString(dir_ / "err.txt"), ::testing::HasSubstr("--allow-unidentifiable"));
  // Asked for, the poses are written, with a warning.
  EXPECT_EQ(RunCommand(command + " --allow-unidentifiable"), 0);
  EXPECT_EQ(ReadPoses(dir_ / "same_poses.csv").records.size(), 10u);
  EXPECT_THAT(ReadFileToString(dir_ / "err.txt"), ::testing::HasSubstr("not identifiable"));
}

// The marker body on receiver 2 (a scene with tracker.sensor: 2 writes such a capture): register
// read sensor 1 only, had no option to choose, and failed with "station 1 (marker 2) has no row in
// tracker.csv for sensor 1"; its poses.csv rows were always written as sensor 1.
TEST_F(FitCliTest, RegisterPairsTheReceiverThatCarriesTheMarkers) {
  TrackerCapture tracker = ReadTracker(dir_ / "cap" / "tracker.csv");
  for (TrackerRecord& t : tracker.records) t.sensor = 2;
  WriteTracker(dir_ / "tracker2.csv", tracker);
  PoseCapture labels = ReadPoses(dir_ / "cap" / "poses.csv");
  for (PoseRecord& r : labels.records) r.sensor = 2;
  WritePoses(dir_ / "poses2.csv", labels);
  const std::string base = fit_ + " register --markers " + (dir_ / "cap" / "markers.csv").string() +
                           " --tracker " + (dir_ / "tracker2.csv").string() + " --poses " +
                           (dir_ / "poses2.csv").string();
  const fs::path err = dir_ / "err.txt";
  EXPECT_EQ(RunCommand(base + " -o " + (dir_ / "x.csv").string() + " 2> " + err.string()), 1);
  EXPECT_THAT(ReadFileToString(err),
              ::testing::HasSubstr("for sensor 1 (it has rows for sensor 2 there"));
  EXPECT_FALSE(fs::exists(dir_ / "x.csv"));
  ASSERT_EQ(RunCommand(base + " --sensor 2 -o " + (dir_ / "reg2.csv").string() + " > /dev/null"),
            0);
  const PoseCapture registered = ReadPoses(dir_ / "reg2.csv");
  EXPECT_EQ(registered.records.size(), labels.records.size());
  for (const PoseRecord& r : registered.records) EXPECT_EQ(r.sensor, 2);
  EXPECT_EQ(RunCommand(base + " --sensor 0 -o " + (dir_ / "y.csv").string() + " 2> /dev/null"), 2);
}

// A poses.csv of two receivers (the sensor column holds 1 and 2) was fitted as one receiver without
// a word: two simulated receivers whose bodies sit 6 cm apart gave 31.5 mm mean corrected error
// (3.9 mm each alone). fit, build and diagnose refuse the mixture naming the sensors and --sensor;
// --sensor N fits that receiver's stations alone, as a file of them alone.
TEST_F(FitCliTest, SeveralReceiversAreRefusedOrFittedOneAtATime) {
  const PoseCapture one = ReadPoses(dir_ / "cap" / "poses.csv");
  PoseCapture mixed = one, second = one;
  for (PoseRecord& r : second.records) {
    r.sensor = 2;
    r.reference.translation += Eigen::Vector3d(0.03, -0.02, 0.01);  // another body offset
  }
  mixed.records.insert(mixed.records.end(), second.records.begin(), second.records.end());
  WritePoses(dir_ / "mixed.csv", mixed);
  WritePoses(dir_ / "second.csv", second);
  const fs::path err = dir_ / "err.txt";
  const std::string model = " --model " + (dir_ / "model.yaml").string();
  const std::string mixed_data = " --data " + (dir_ / "mixed.csv").string();
  std::ofstream(dir_ / "settings.yaml") << "noise:\n  position_mm: 1\n";
  for (const std::string& command :
       {fit_ + " fit" + mixed_data + model + " -o " + (dir_ / "m.json").string(),
        fit_ + " build" + mixed_data + " --model " + (dir_ / "settings.yaml").string() + " -o " +
            (dir_ / "b.json").string(),
        fit_ + " diagnose" + mixed_data + model}) {
    SCOPED_TRACE(command);
    EXPECT_EQ(RunCommand(command + " --quiet > /dev/null 2> " + err.string()), 1);
    const std::string message = ReadFileToString(err);
    EXPECT_THAT(message, ::testing::HasSubstr("mixed.csv: stations of sensors 1, 2"));
    EXPECT_THAT(message, ::testing::HasSubstr("--sensor N"));
  }
  EXPECT_FALSE(fs::exists(dir_ / "m.json"));
  EXPECT_FALSE(fs::exists(dir_ / "b.json"));

  const fs::path picked = dir_ / "picked.json", alone = dir_ / "alone.json";
  ASSERT_EQ(RunCommand(fit_ + " fit" + mixed_data + model + " --sensor 2 -o " +
                       (dir_ / "p.json").string() + " --json --quiet > " + picked.string()),
            0);
  ASSERT_EQ(RunCommand(fit_ + " fit --data " + (dir_ / "second.csv").string() + model + " -o " +
                       (dir_ / "a.json").string() + " --json --quiet > " + alone.string()),
            0);
  const auto p = nlohmann::json::parse(ReadFileToString(picked));
  const auto a = nlohmann::json::parse(ReadFileToString(alone));
  EXPECT_EQ(p["tables"], a["tables"]);  // the same stations, in the same order: the same numbers
  // The file records the receiver it was fitted for (picked with --sensor, or the file's only one),
  // so a server can refuse it on another receiver's sensor= line; it recorded nothing before.
  EXPECT_EQ(ReadCalibrationFile(dir_ / "p.json").sensor, 2);
  EXPECT_EQ(ReadCalibrationFile(dir_ / "a.json").sensor, 2);
  EXPECT_THAT(ReadFileToString(dir_ / "a.json"), ::testing::HasSubstr("\"sensor\": 2,"));
  EXPECT_EQ(RunCommand(fit_ + " fit" + mixed_data + model + " --sensor 3 -o " +
                       (dir_ / "x.json").string() + " --quiet 2> " + err.string()),
            1);
  EXPECT_THAT(ReadFileToString(err),
              ::testing::HasSubstr("no station of sensor 3 (the sensor column has 1, 2)"));
}

// A marker no registration station saw (another body's, or mislabelled) at a calibration station
// stopped the extraction with "station N, marker M: marker id not in the registration", naming
// neither the file nor its line.
TEST_F(FitCliTest, RegisterNamesTheLineOfAMarkerTheRegistrationNeverSaw) {
  std::set<int> reg_stations;
  int calib_station = 0;
  for (const PoseRecord& r : ReadPoses(dir_ / "cap" / "poses.csv").records) {
    if (r.set == "reg") reg_stations.insert(r.station);
    if (r.set == "calib" && calib_station == 0) calib_station = r.station;
  }
  ASSERT_NE(calib_station, 0);
  MarkerCapture markers = ReadMarkers(dir_ / "cap" / "markers.csv");
  MarkerRecord stray = markers.records.back();
  for (const MarkerRecord& m : markers.records) {
    if (m.station == calib_station) stray = m;
  }
  stray.marker = 99;
  // Inserted after the station's last row, so its line is that row's + 1 (+1 for the header).
  size_t at = 0;
  for (size_t i = 0; i < markers.records.size(); ++i) {
    if (markers.records[i].station == calib_station) at = i + 1;
  }
  markers.records.insert(markers.records.begin() + static_cast<std::ptrdiff_t>(at), stray);
  WriteMarkers(dir_ / "stray.csv", markers);
  const fs::path err = dir_ / "err.txt", out = dir_ / "stray_poses.csv";
  EXPECT_EQ(RunCommand(fit_ + " register --markers " + (dir_ / "stray.csv").string() +
                       " --tracker " + (dir_ / "cap" / "tracker.csv").string() + " --poses " +
                       (dir_ / "cap" / "poses.csv").string() + " -o " + out.string() +
                       " --quiet 2> " + err.string()),
            1);
  EXPECT_THAT(ReadFileToString(err),
              ::testing::HasSubstr("stray.csv:" + std::to_string(at + 2) +
                                   ": column marker: station " + std::to_string(calib_station) +
                                   ", marker 99: marker id not in the registration"));
  EXPECT_FALSE(fs::exists(out));
}

TEST_F(FitCliTest, RegisterWithPosesLabelsAndFlagsTheDistortion) {
  const fs::path json = dir_ / "reg.json";
  const std::string base = fit_ + " register --markers " + (dir_ / "cap" / "markers.csv").string() +
                           " --tracker " + (dir_ / "cap" / "tracker.csv").string() + " --poses " +
                           (dir_ / "cap" / "poses.csv").string();
  const fs::path warnings = dir_ / "reg_warnings.txt";
  ASSERT_EQ(RunCommand(base + " -o " + (dir_ / "reg_poses.csv").string() + " --json > " +
                       json.string() + " 2> " + warnings.string()),
            0);
  const auto doc = nlohmann::json::parse(ReadFileToString(json));
  // Any three of the paper's six markers (+-60 mm on the receiver axes) are symmetric: a label
  // swapped there gives a pose 180 deg off with a perfect fit. It was not said.
  EXPECT_THAT(ReadFileToString(warnings),
              ::testing::HasSubstr("poses come from markers in view so symmetric that two labels "
                                   "swapped would fit as well"));
  // The paper scene's workbench frame distorts the registration stations (docs/registration.md).
  EXPECT_TRUE(doc["registration"]["residual_structure"]["flagged"].get<bool>());
  EXPECT_EQ(doc["registration"]["optical_from_transmitter"]["covariance"].size(), 6u);
  EXPECT_EQ(doc["registration"]["stations"].size(), 20u);
  // Every station has markers: each gets its pose, with its set and time from --poses.
  std::map<int, const PoseRecord*> labelled;
  const PoseCapture input = ReadPoses(dir_ / "cap" / "poses.csv");
  for (const PoseRecord& r : input.records) labelled[r.station] = &r;
  const PoseCapture registered = ReadPoses(dir_ / "reg_poses.csv");
  EXPECT_EQ(registered.records.size(), input.records.size());
  for (const PoseRecord& r : registered.records) {
    ASSERT_TRUE(labelled.count(r.station)) << r.station;
    EXPECT_EQ(r.set, labelled[r.station]->set);
    EXPECT_EQ(r.time, labelled[r.station]->time);
  }
  // --model needs calibration stations with markers. The simulator writes markers at every
  // station (fit/session_sim_test refines its folders); a capture with markers at the
  // registration stations only cannot be refined (exit 1, message says why).
  std::set<int> reg_stations;
  for (const PoseRecord& r : ReadPoses(dir_ / "cap" / "poses.csv").records) {
    if (r.set == "reg") reg_stations.insert(r.station);
  }
  MarkerCapture reg_only;
  for (const MarkerRecord& m : ReadMarkers(dir_ / "cap" / "markers.csv").records) {
    if (reg_stations.count(m.station)) reg_only.records.push_back(m);
  }
  WriteMarkers(dir_ / "reg_markers.csv", reg_only);
  const fs::path err = dir_ / "err.txt";
  EXPECT_EQ(RunCommand(fit_ + " register --markers " + (dir_ / "reg_markers.csv").string() +
                       " --tracker " + (dir_ / "cap" / "tracker.csv").string() + " --poses " +
                       (dir_ / "cap" / "poses.csv").string() + " --model " +
                       (dir_ / "model.yaml").string() + " -o " + (dir_ / "refined.csv").string() +
                       " --quiet 2> " + err.string()),
            1);
  EXPECT_THAT(ReadFileToString(err), ::testing::HasSubstr("calibration station"));
  EXPECT_FALSE(fs::exists(dir_ / "refined.csv"));
  // --model without --poses is a usage error.
  EXPECT_EQ(RunCommand(fit_ + " register --markers " + (dir_ / "cap" / "markers.csv").string() +
                       " --tracker " + (dir_ / "cap" / "tracker.csv").string() + " --model " +
                       (dir_ / "model.yaml").string() + " -o " + (dir_ / "x.csv").string() +
                       " 2> /dev/null"),
            2);
}

// Stations that give no reference pose are counted with why on stderr; when none gives one the
// command fails without writing. A marker body on one line registers (the tracker gives each
// station's orientation) but every station's pose is degenerate: that used to be "Wrote 0 poses",
// exit 0, a header-only poses.csv and nothing saying why.
TEST_F(FitCliTest, RegisterSaysWhyStationsGiveNoPose) {
  std::ofstream(dir_ / "collinear.yaml") << "base: ideal\nreference:\n  markers_in_body:\n"
                                            "    - [0.06, 0, 0]\n    - [-0.06, 0, 0]\n"
                                            "    - [0.03, 0, 0]\n    - [-0.03, 0, 0]\n";
  ASSERT_EQ(RunCommand((BinaryDir() / "sim" / "trackcal-simulate").string() + " --scene " +
                       (dir_ / "collinear.yaml").string() + " -o " + (dir_ / "collinear").string() +
                       " > /dev/null"),
            0);
  const fs::path err = dir_ / "err.txt", out = dir_ / "collinear_poses.csv";
  const fs::path cap = dir_ / "collinear";
  EXPECT_EQ(
      RunCommand(fit_ + " register --markers " + (cap / "markers.csv").string() + " --tracker " +
                 (cap / "tracker.csv").string() + " --poses " + (cap / "poses.csv").string() +
                 " -o " + out.string() + " > /dev/null 2> " + err.string()),
      1);
  EXPECT_THAT(ReadFileToString(err),
              ::testing::HasSubstr("markers.csv: no station gives a reference pose: 620 "
                                   "degenerate (e.g. station 1, line 2: visible markers nearly "
                                   "collinear"));
  EXPECT_FALSE(fs::exists(out));

  // One calibration station of the paper capture down to two markers: its pose is missing, and
  // the warning says so.
  MarkerCapture markers = ReadMarkers(dir_ / "cap" / "markers.csv");
  const int station = markers.records.front().station;
  int seen = 0;
  std::erase_if(markers.records,
                [&](const MarkerRecord& m) { return m.station == station && ++seen > 2; });
  WriteMarkers(dir_ / "two.csv", markers);
  // The station's first marker row (after the header) is the line the message points at.
  const auto first_row = std::find_if(markers.records.begin(), markers.records.end(),
                                      [&](const MarkerRecord& m) { return m.station == station; });
  const int line = static_cast<int>(first_row - markers.records.begin()) + 2;
  EXPECT_EQ(RunCommand(fit_ + " register --markers " + (dir_ / "two.csv").string() + " --tracker " +
                       (dir_ / "cap" / "tracker.csv").string() + " --poses " +
                       (dir_ / "cap" / "poses.csv").string() + " -o " +
                       (dir_ / "two_poses.csv").string() + " > /dev/null 2> " + err.string()),
            0);
  EXPECT_THAT(ReadFileToString(err),
              ::testing::HasSubstr("two.csv: 1 of 620 stations give no reference pose: 1 "
                                   "too_few_markers (e.g. station " +
                                   std::to_string(station) + ", line " + std::to_string(line) +
                                   ": 2 marker(s) visible, need 3)"));
  EXPECT_EQ(ReadPoses(dir_ / "two_poses.csv").records.size(), 619u);
}

// The options of each command in `trackcal-fit --help` and in the synopsis that opens docs/fit.md
// (the block a user copies) are the same: a user reads one or the other, and an option the usage
// leaves out (diagnose's --sensor was) looks like one the command does not take.
std::map<std::string, std::set<std::string>> OptionsPerCommand(const std::string& usage) {
  std::map<std::string, std::set<std::string>> options;
  const std::regex command_line(R"(^\s*trackcal-fit (\w+) )");
  const std::regex option(R"((--[a-z][a-z0-9-]*|-o\b))");
  std::string command;
  std::istringstream lines(usage);
  for (std::string line; std::getline(lines, line);) {
    std::smatch match;
    if (std::regex_search(line, match, command_line)) {
      command = match[1];
    } else if (line.rfind(' ', 0) != 0) {
      command.clear();  // the text after the synopsis
    }
    if (command.empty()) continue;
    for (auto it = std::sregex_iterator(line.begin(), line.end(), option);
         it != std::sregex_iterator(); ++it) {
      options[command].insert(it->str());
    }
  }
  return options;
}

TEST(FitCliUsage, HelpListsTheOptionsTheDocsListForEachCommand) {
  const char* source = std::getenv("TRACKCAL_SOURCE_DIR");
  ASSERT_NE(source, nullptr) << "run through ctest (TRACKCAL_SOURCE_DIR)";
  const std::string doc = ReadFileToString(fs::path(source) / "docs" / "fit.md");
  const size_t begin = doc.find("```\n");
  const size_t end = doc.find("```", begin + 4);
  ASSERT_NE(end, std::string::npos);
  const auto documented = OptionsPerCommand(doc.substr(begin + 4, end - begin - 4));

  const fs::path out =
      fs::temp_directory_path() / ("trackcal_fit_usage_" + std::to_string(::getpid()));
  ASSERT_EQ(
      RunCommand((BinaryDir() / "fit" / "trackcal-fit").string() + " --help > " + out.string()), 0);
  const auto printed = OptionsPerCommand(ReadFileToString(out));
  fs::remove(out);

  ASSERT_EQ(documented.size(), 5u);
  for (const auto& [command, options] : documented) {
    ASSERT_TRUE(printed.count(command)) << command;
    EXPECT_EQ(printed.at(command), options) << "trackcal-fit " << command;
  }
}

}  // namespace
}  // namespace trackcal
