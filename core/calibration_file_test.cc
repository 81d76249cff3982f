#include "core/calibration_file.h"

#include <gtest/gtest.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <fstream>
#include <functional>
#include <regex>

#include "core/file_util.h"
#include "core/json_reader.h"
#include "core/lut.h"
#include "core/polynomial.h"
#include "core/printable_text.h"
#include "tests/test_utils.h"

namespace trackcal {
namespace {

using testing::TestRng;

std::filesystem::path ExamplePath() {
  return testing::SourceDir() / "tests/data/calibration/example.json";
}

nlohmann::json ExampleJson() { return nlohmann::json::parse(ReadFileToString(ExamplePath())); }

// An error at a JSON path without its line and column ("calib.json:1:1913: $.format: ..." ->
// "calib.json: $.format: ..."): the tests of what each error says edit one-line dumps, where the
// column is a byte count no reader checks by eye. The locations have their own tests
// (ParseCalibrationJson.ErrorsNameLineAndColumn); syntax errors ("calib.json:27:18: invalid
// JSON: ...") are left as they are.
std::string WithoutPathLocation(const std::string& error) {
  static const std::regex located(R"(^calib\.json:[0-9]+:[0-9]+: \$)");
  return std::regex_replace(error, located, "calib.json: $$",
                            std::regex_constants::format_first_only);
}

// Parses the example after `edit` and returns the error message ("" if it parsed).
std::string ErrorAfterEdit(const std::function<void(nlohmann::json&)>& edit) {
  nlohmann::json j = ExampleJson();
  edit(j);
  try {
    ParseCalibrationJson(j.dump(), "calib.json");
  } catch (const JsonInputError& e) {
    return WithoutPathLocation(e.what());
  }
  return "";
}

std::string ErrorForText(const std::string& text) {
  try {
    ParseCalibrationJson(text, "calib.json");
  } catch (const JsonInputError& e) {
    return WithoutPathLocation(e.what());
  }
  return "";
}

// The error for the example's text with `from` (which must occur once) replaced by `to`, as a
// hand edit makes it: the file keeps its lines.
std::string ErrorForExampleEdit(const std::string& from, const std::string& to) {
  std::string text = ReadFileToString(ExamplePath());
  const size_t at = text.find(from);
  EXPECT_NE(at, std::string::npos) << from;
  EXPECT_EQ(text.find(from, at + 1), std::string::npos) << from;
  if (at == std::string::npos) return "";
  text.replace(at, from.size(), to);
  try {
    ParseCalibrationJson(text, "calib.json");
  } catch (const JsonInputError& e) {
    return e.what();
  }
  return "";
}

Calibration RandomCalibration() {
  std::normal_distribution<double> n(0.0, 0.01);
  const int r = 4;
  std::vector<double> c(6 * NumPolynomialTerms(r));
  for (double& v : c) v = n(TestRng());
  Calibration cal;
  cal.description = "random";
  cal.chain.Append(std::make_unique<PolynomialCorrection>(r, Eigen::Vector3d(0.01, -0.02, 0.3),
                                                          Eigen::Vector3d(0.7, 0.6, 0.5), c));
  LutGrid grid({std::vector<double>{-0.7, -0.2, 0.1, 0.7}, std::vector<double>{-0.6, 0.6},
                std::vector<double>{-0.2, 0.0, 0.3, 0.5, 0.8}});
  std::vector<double> values(6 * grid.num_nodes());
  for (double& v : values) v = n(TestRng()) / 3.0;  // not exactly representable in short decimal
  cal.chain.Append(std::make_unique<TrilinearLutCorrection>(std::move(grid), values));
  CalibratedVolume volume;
  volume.min = Eigen::Vector3d(-0.65, -0.55, -0.15);
  volume.max = Eigen::Vector3d(0.65, 0.55, 0.75);
  volume.extrapolation = ExtrapolationPolicy::kClamp;
  cal.chain.SetVolume(volume);
  cal.fit_statistics = {{"num_samples", 100}, {"position_residual_m", {{"rms", 0.0012}}}};
  cal.provenance.tool = "calibration_file_test";
  cal.provenance.tool_version = "0.1.0";
  cal.provenance.created_utc = "2026-11-21T12:00:00Z";
  cal.provenance.inputs.push_back({"capture.csv", Sha256Hex("capture"), "calibration_capture"});
  return cal;
}

TEST(ReadCalibrationFile, Nominal) {
  const Calibration cal = ReadCalibrationFile(ExamplePath());
  ASSERT_EQ(cal.chain.size(), 2u);
  EXPECT_EQ(cal.chain.term(0).TypeName(), "polynomial");
  EXPECT_EQ(cal.chain.term(1).TypeName(), "trilinear_lut");
  const auto& poly = dynamic_cast<const PolynomialCorrection&>(cal.chain.term(0));
  EXPECT_EQ(poly.degree(), 2);
  EXPECT_EQ(poly.input_offset(), Eigen::Vector3d(0.0, 0.0, 0.3));
  // Coefficient (term x, position x) and (term z, orientation x), from the file.
  EXPECT_EQ(poly.coefficients()[6 * 1 + 0], 0.0102);
  EXPECT_EQ(poly.coefficients()[6 * 3 + 3], 0.0009);
  const auto& lut = dynamic_cast<const TrilinearLutCorrection&>(cal.chain.term(1));
  EXPECT_EQ(lut.grid().size(2), 3);
  EXPECT_EQ(cal.volume().extrapolation, ExtrapolationPolicy::kFade);
  EXPECT_EQ(cal.volume().fade_distance, 0.15);
  EXPECT_EQ(cal.volume().max, Eigen::Vector3d(0.6, 0.5, 0.7));
  EXPECT_EQ(cal.fit_statistics.at("num_samples"), 480);
  ASSERT_EQ(cal.provenance.inputs.size(), 2u);
  EXPECT_EQ(cal.provenance.inputs[1].role, "calibration_capture");
  EXPECT_EQ(cal.provenance.tool, "trackcal-fit");
}

TEST(CalibrationDoc, ExampleInDocIsTheTestedExample) {
  // docs/calibration-file.md shows the example verbatim between these markers.
  const std::string doc = ReadFileToString(testing::SourceDir() / "docs/calibration-file.md");
  const std::string begin_marker = "<!-- example: tests/data/calibration/example.json -->\n```json\n";
  const size_t begin = doc.find(begin_marker);
  ASSERT_NE(begin, std::string::npos);
  const size_t start = begin + begin_marker.size();
  const size_t end = doc.find("```", start);
  ASSERT_NE(end, std::string::npos);
  EXPECT_EQ(doc.substr(start, end - start), ReadFileToString(ExamplePath()));
}

TEST(WriteCalibrationFile, RoundTripIsBitExact) {
  const Calibration cal = RandomCalibration();
  const auto dir = testing::MakeTempDir("calib");
  const auto path = dir / "out.json";
  WriteCalibrationFile(path, cal);
  const Calibration back = ReadCalibrationFile(path);
  EXPECT_EQ(CalibrationToJson(back), CalibrationToJson(cal));
  EXPECT_EQ(CalibrationToJsonText(back), ReadFileToString(path));
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  for (int i = 0; i < 200; ++i) {
    const Rigid3d reported(testing::RandomRotation(TestRng()),
                           Eigen::Vector3d(u(TestRng()), u(TestRng()), u(TestRng())));
    const CorrectedPose a = cal.Apply(reported);
    const CorrectedPose b = back.Apply(reported);
    EXPECT_EQ(a.pose.translation, b.pose.translation);
    EXPECT_EQ(a.pose.rotation.coeffs(), b.pose.rotation.coeffs());
    EXPECT_EQ(a.extrapolated, b.extrapolated);
  }
  // The example survives a parse/write cycle unchanged in content.
  const Calibration example = ReadCalibrationFile(ExamplePath());
  EXPECT_EQ(CalibrationToJson(ParseCalibrationJson(CalibrationToJsonText(example), "again")),
            ExampleJson());
}

TEST(WriteCalibrationFile, WritesStringsThatAreNotUtf8) {
  // Linux paths are bytes: a capture named in Latin-1 ("caf\xe9.csv") reaches the provenance
  // through the command line and the inputs. The writer used to throw nlohmann's type_error 316
  // ("invalid UTF-8 byte at index 17"), not naming the field, after the whole fit; now each bad
  // byte is written as U+FFFD and the file reads back.
  Calibration cal = RandomCalibration();
  cal.description = "lab \xe9";
  cal.provenance.command_line = "trackcal-fit caf\xe9.csv -o out.json";
  cal.provenance.inputs[0].path = "caf\xe9.csv";
  const auto dir = testing::MakeTempDir("calib");
  const auto path = dir / "out.json";
  ASSERT_NO_THROW(WriteCalibrationFile(path, cal));
  const Calibration back = ReadCalibrationFile(path);
  const std::string replacement = "\xEF\xBF\xBD";  // U+FFFD in UTF-8
  EXPECT_EQ(back.description, "lab " + replacement);
  EXPECT_EQ(back.provenance.command_line, "trackcal-fit caf" + replacement + ".csv -o out.json");
  EXPECT_EQ(back.provenance.inputs[0].path, "caf" + replacement + ".csv");
  EXPECT_EQ(back.provenance.inputs[0].sha256, cal.provenance.inputs[0].sha256);
}

TEST(ParseCalibrationJson, RejectsUnknownFormatAndVersion) {
  EXPECT_EQ(ErrorAfterEdit([](nlohmann::json& j) { j["format"] = "trackcal-capture"; }),
            "calib.json: $.format: unknown format \"trackcal-capture\"; expected "
            "\"trackcal-calibration\"");
  EXPECT_EQ(ErrorAfterEdit([](nlohmann::json& j) { j["version"] = 2; }),
            "calib.json: $.version: unsupported version 2; this reader supports version 1");
  EXPECT_EQ(ErrorAfterEdit([](nlohmann::json& j) { j["version"] = "1"; }),
            "calib.json: $.version: expected an integer, got string \"1\"");
  EXPECT_EQ(ErrorForText("[1, 2]"), "calib.json: $: expected an object, got array [1,2]");
  // 2^64 - 1 is an unsigned JSON integer, not version -1.
  EXPECT_EQ(ErrorAfterEdit([](nlohmann::json& j) { j["version"] = UINT64_MAX; }),
            "calib.json: $.version: integer out of range: 18446744073709551615");
  EXPECT_EQ(ErrorAfterEdit(
                [](nlohmann::json& j) { j["corrections"][0]["degree"] = UINT64_MAX - 4; }),
            "calib.json: $.corrections[0].degree: integer out of range: 18446744073709551611");
}

TEST(ParseCalibrationJson, RejectsMissingAndUnknownFields) {
  EXPECT_EQ(ErrorAfterEdit([](nlohmann::json& j) { j.erase("units"); }),
            "calib.json: $.units: missing required field");
  EXPECT_EQ(ErrorAfterEdit([](nlohmann::json& j) { j["corrections"][1].erase("axes"); }),
            "calib.json: $.corrections[1].axes: missing required field");
  EXPECT_EQ(ErrorAfterEdit([](nlohmann::json& j) { j["provenance"]["inputs"][1].erase("sha256"); }),
            "calib.json: $.provenance.inputs[1].sha256: missing required field");
  EXPECT_EQ(ErrorAfterEdit([](nlohmann::json& j) { j["colour"] = "red"; }),
            "calib.json: $.colour: unknown field");
  EXPECT_EQ(ErrorAfterEdit([](nlohmann::json& j) { j["corrections"][0]["degre"] = 4; }),
            "calib.json: $.corrections[0].degre: unknown field");
  EXPECT_EQ(ErrorAfterEdit([](nlohmann::json& j) { j["calibrated_volume"]["fade"] = 0.1; }),
            "calib.json: $.calibrated_volume.fade: unknown field");
  EXPECT_EQ(ErrorAfterEdit([](nlohmann::json& j) { j["corrections"][1]["axes"]["w"] = {0, 1}; }),
            "calib.json: $.corrections[1].axes.w: unknown field");
  EXPECT_EQ(ErrorAfterEdit([](nlohmann::json& j) { j["units"]["length"] = "mm"; }),
            "calib.json: $.units.length: unknown value \"mm\"; expected one of \"m\"");
  EXPECT_EQ(ErrorAfterEdit([](nlohmann::json& j) { j["corrections"][0]["type"] = "spline"; }),
            "calib.json: $.corrections[0].type: unknown correction type \"spline\"; known: "
            "\"polynomial\", \"trilinear_lut\", \"physical\"");
}

TEST(ParseCalibrationJson, RejectsWrongArraySizes) {
  // The issue's example: a degree-4 polynomial with 34 position coefficients.
  EXPECT_EQ(ErrorAfterEdit([](nlohmann::json& j) {
              auto& c = j["corrections"][0];
              c["degree"] = 4;
              c["position_coefficients"] = nlohmann::json::array();
              c["orientation_coefficients"] = nlohmann::json::array();
              for (int i = 0; i < 35; ++i) {
                if (i < 34) c["position_coefficients"].push_back({0.0, 0.0, 0.0});
                c["orientation_coefficients"].push_back({0.0, 0.0, 0.0});
              }
            }),
            "calib.json: $.corrections[0].position_coefficients: degree 4 needs 35 entries, got 34");
  EXPECT_EQ(ErrorAfterEdit([](nlohmann::json& j) {
              j["corrections"][0]["orientation_coefficients"][3] = {0.1, 0.2};
            }),
            "calib.json: $.corrections[0].orientation_coefficients[3]: expected 3 numbers [x, y, "
            "z], got [0.1,0.2]");
  EXPECT_EQ(ErrorAfterEdit([](nlohmann::json& j) {
              j["corrections"][1]["position_error"].erase(0);
            }),
            "calib.json: $.corrections[1].position_error: a 2 x 2 x 3 grid needs 12 entries, got 11");
  EXPECT_EQ(ErrorAfterEdit([](nlohmann::json& j) { j["calibrated_volume"]["min"] = {0, 0}; }),
            "calib.json: $.calibrated_volume.min: expected 3 numbers [x, y, z], got 2");
  EXPECT_EQ(ErrorAfterEdit([](nlohmann::json& j) { j["corrections"][0]["degree"] = 13; }),
            "calib.json: $.corrections[0].degree: must be in [0, 12], got 13");
}

TEST(ParseCalibrationJson, OverflowingNumberIsLocatedAtTheNumberNotAtTextThatContainsIt) {
  // The literal was located with a plain text search, which found it first in the description
  // (line 4) and reported that line and column instead of the number's.
  std::string text = ReadFileToString(ExamplePath());
  const std::string description = "Example: degree-2 polynomial";
  ASSERT_NE(text.find(description), std::string::npos);
  text.replace(text.find(description), description.size(), "Example: coefficients up to 1e999");
  const std::string needle = "[0.0102, 0.0007, -0.0011]";
  ASSERT_NE(text.find(needle), std::string::npos);
  text.replace(text.find(needle), needle.size(), "[0.0102, 1e999, -0.0011]");
  EXPECT_EQ(ErrorForText(text),
            "calib.json:27:18: invalid JSON: number 1e999 overflows a double; numbers must be "
            "finite");
  // Nor in a key (it was put at the key "1e999", line 2).
  EXPECT_EQ(
      ErrorForText("{\"a\": 0,\n \"1e999\": 0,\n \"c\": 1e999}"),
      "calib.json:3:7: invalid JSON: number 1e999 overflows a double; numbers must be finite");
}

TEST(ParseCalibrationJson, AnUnquotedWordIsNotCalledANonFiniteNumber) {
  // Any word starting with "nan" or "inf" was reported as NaN/Infinity: a forgotten pair of quotes
  // around `info` read "non-finite number (NaN or Infinity) is not allowed".
  std::string text = ReadFileToString(ExamplePath());
  const std::string role = "\"role\": \"calibration_capture\"";
  ASSERT_NE(text.find(role), std::string::npos);
  const size_t at = text.find(role);
  text.replace(at, role.size(), "\"role\": info");
  // The line of the replaced role, counted in the example (which may grow).
  const std::string line = std::to_string(1 + std::count(text.begin(), text.begin() + at, '\n'));
  const std::string error = ErrorForText(text);
  EXPECT_EQ(error.rfind("calib.json:" + line + ":17: invalid JSON: ", 0), 0u) << error;
  EXPECT_EQ(error.find("non-finite"), std::string::npos) << error;
  EXPECT_NE(error.find("invalid literal"), std::string::npos) << error;
  // The real literals still are.
  for (const char* word : {"NaN", "Infinity", "-Infinity", "nan", "inf"}) {
    const std::string e = ErrorForText(std::string("{\"a\": ") + word + "}");
    EXPECT_NE(e.find("non-finite number (NaN or Infinity) is not allowed"), std::string::npos)
        << word << ": " << e;
  }
}

TEST(ParseCalibrationJson, RejectsNonFiniteNumbers) {
  std::string text = ReadFileToString(ExamplePath());
  const std::string needle = "[0.0102, 0.0007, -0.0011]";
  ASSERT_NE(text.find(needle), std::string::npos);
  std::string nan_text = text;
  nan_text.replace(nan_text.find(needle), needle.size(), "[0.0102, NaN, -0.0011]");
  const std::string nan_error = ErrorForText(nan_text);
  EXPECT_EQ(nan_error.rfind("calib.json:27:18:", 0), 0u) << nan_error;  // line 27 of the example
  EXPECT_NE(nan_error.find("non-finite number (NaN or Infinity) is not allowed"), std::string::npos)
      << nan_error;
  std::string inf_text = text;
  inf_text.replace(inf_text.find(needle), needle.size(), "[0.0102, 1e999, -0.0011]");
  const std::string inf_error = ErrorForText(inf_text);
  EXPECT_EQ(inf_error,
            "calib.json:27:18: invalid JSON: number 1e999 overflows a double; numbers must be "
            "finite");
  // Free-form sections are checked too.
  std::string stats_text = text;
  stats_text.replace(stats_text.find("\"rms\": 0.0038"), 13, "\"rms\": -1e400");
  const std::string stats_error = ErrorForText(stats_text);
  EXPECT_NE(stats_error.find("invalid JSON: number -1e400 overflows a double"), std::string::npos)
      << stats_error;
  // The reader's own finiteness check (reachable for documents built in memory).
  nlohmann::json stats = {{"rms", std::numeric_limits<double>::infinity()}};
  try {
    CheckJsonNumbersFinite(stats, "calib.json", "$.fit_statistics");
    FAIL();
  } catch (const JsonInputError& e) {
    EXPECT_STREQ(e.what(), "calib.json: $.fit_statistics.rms: number must be finite, got Infinity");
  }
  // Without the parser's "[json.exception.parse_error.101] parse error at line 1, column 12:
  // syntax error while parsing value - " (jargon, and a second position that can disagree).
  EXPECT_EQ(ErrorForText("{\"format\": "),
            "calib.json:1:12: invalid JSON: unexpected end of input; expected '[', '{', or a "
            "literal");
  EXPECT_EQ(ErrorForText("{\"format\":\n tru\n}"),
            "calib.json:2:5: invalid JSON: invalid literal; last read: '\"format\":<U+000A> "
            "tru<U+000A>'");
}

TEST(ParseCalibrationJson, AFileThatIsNotJsonSaysWhatACalibrationFileIs) {
  // docs/understand.md's loop has model.yaml next to calib.json; given the model as -c (or in a
  // trackcal_Calibration line), the error was only the JSON parser's "invalid literal; last read:
  // 'te'".
  const std::string yaml = ErrorForText("terms:\n  - type: polynomial\n    degree: 4\n");
  EXPECT_EQ(yaml.rfind("calib.json:1:2: invalid JSON: ", 0), 0u) << yaml;
  EXPECT_NE(yaml.find("(not a calibration file: a calibration file is the JSON document that "
                      "trackcal fit -o or trackcal-fit fit -o writes, starting with '{'; is this a "
                      "model file or a capture?)"),
            std::string::npos)
      << yaml;
  const std::string csv = ErrorForText("\xEF\xBB\xBF station,set,sensor\n1,calib,1\n");
  EXPECT_NE(csv.find("(not a calibration file"), std::string::npos) << csv;
  // A JSON document that is broken keeps the parser's message alone.
  EXPECT_EQ(ErrorForText("  {\"format\": ").find("not a calibration file"), std::string::npos);
}

TEST(ParseCalibrationJson, AFileThatIsNotUtf8GetsAPrintableMessage) {
  // A description typed in a Latin-1 editor ("Kalibrierung f\xfcr Raum B"): the parser's message
  // quoted the byte raw, and in Python (Calibration.load, trackcal validate -c) it failed as it
  // became a str, "'utf-8' codec can't decode byte 0xfc", naming no file.
  std::string text = ReadFileToString(ExamplePath());
  const size_t at = text.find("Example");
  ASSERT_NE(at, std::string::npos);
  text.replace(at, 7, "f\xfcr lab");
  const std::string latin1 = ErrorForText(text);
  EXPECT_EQ(latin1.rfind("calib.json:4:20: invalid JSON: ", 0), 0u) << latin1;
  EXPECT_NE(latin1.find("ill-formed UTF-8 byte; last read: '\"f\\xfc'"), std::string::npos)
      << latin1;
  EXPECT_EQ(PrintableForMessage(latin1), latin1);  // nothing left to escape: valid UTF-8
  // Notepad's "Unicode" save: UTF-16 with a byte order mark, said as such, not "not a calibration
  // file".
  EXPECT_EQ(ErrorForText(std::string("\xFF\xFE{\0\"\0", 6)),
            "calib.json: UTF-16 text (a byte order mark FF FE or FE FF); save the calibration file "
            "as UTF-8");
}

TEST(ParseCalibrationJson, RejectsTermsThatOverflowInTheVolume) {
  // Every number is finite, but u = (x - offset) / 1e-200 makes the degree-2 terms infinite and
  // infinity times a coefficient NaN: the file would serve NaN for every pose in its own volume.
  std::vector<double> c(6 * NumPolynomialTerms(2), 0.001);
  const PolynomialCorrection tiny_scale(2, Eigen::Vector3d::Zero(),
                                        Eigen::Vector3d(1e-200, 0.5, 0.4), c);
  EXPECT_FALSE(
      tiny_scale.Apply(Rigid3d(Eigen::Quaterniond::Identity(), Eigen::Vector3d(0.1, 0.1, 0.1)))
          .pose.translation.allFinite());
  nlohmann::json j = ExampleJson();
  j["corrections"][0]["input_scale"] = {1e-200, 0.5, 0.4};
  EXPECT_EQ(ErrorForText(j.dump()),
            "calib.json: $.corrections[0]: gives a non-finite pose at [-0.6,-0.5,-0.1] of the "
            "calibrated volume (its numbers overflow a double there)");
  // The same for huge coefficients whose sum overflows.
  j = ExampleJson();
  j["corrections"][0]["position_coefficients"][1] = {1e308, 0.0, 0.0};
  j["corrections"][0]["position_coefficients"][4] = {1e308, 0.0, 0.0};
  EXPECT_NE(ErrorForText(j.dump()).find("calib.json: $.corrections[0]: gives a non-finite pose"),
            std::string::npos);
  // The example itself is finite everywhere.
  EXPECT_EQ(ErrorForText(ReadFileToString(ExamplePath())), "");
}

TEST(ParseCalibrationJson, RejectsDeepNesting) {
  // A calibration document is a few levels deep; the free-form fit_statistics are checked
  // recursively (each level copying its JSON path), so a pathologically nested one must be refused
  // while parsing, naming where, rather than exhausting the stack or memory.
  std::string text = ReadFileToString(ExamplePath());
  const std::string needle = "\"fit_statistics\": {";
  ASSERT_NE(text.find(needle), std::string::npos);
  constexpr int kDepth = 100000;
  text.insert(text.find(needle) + needle.size(),
              "\"deep\": " + std::string(kDepth, '[') + "0" + std::string(kDepth, ']') + ",");
  const std::string error = ErrorForText(text);
  EXPECT_EQ(
      error, "calib.json: $.fit_statistics.deep" + [] {
        std::string levels;
        for (int i = 0; i < 62; ++i) levels += "[0]";
        return levels;
      }() + ": nested more than 64 levels deep");
}

TEST(ParseCalibrationJson, ErrorsNameLineAndColumn) {
  // A hand editor of a file with a LUT of thousands of entries needs the line, not only the JSON
  // path: every error at a path names the line and column of its key (an object's field) or value
  // (an array entry) in the example's text, as syntax errors and the model file's errors do.
  // A misspelt field: at its key (line 16 of the example: `    "fade_distance": 0.15`).
  EXPECT_EQ(
      ErrorForExampleEdit("\"fade_distance\": 0.15", "\"fade_distance\": 0.15, \"outisde\": 1"),
      "calib.json:16:28: $.calibrated_volume.outisde: unknown field");
  // A wrong type, deep in the chain: the entry's line (27, the second coefficient row).
  EXPECT_EQ(ErrorForExampleEdit("[0.0102, 0.0007, -0.0011]", "[0.0102, \"0.0007\", -0.0011]"),
            "calib.json:27:18: $.corrections[0].position_coefficients[1][1]: expected a number, "
            "got string \"0.0007\"");
  // A non-monotonic LUT axis: at the offending value.
  EXPECT_EQ(ErrorForExampleEdit("\"z\": [-0.1, 0.2, 0.7]", "\"z\": [-0.1, 0.7, 0.2]"),
            "calib.json:56:26: $.corrections[1].axes.z[2]: axis values must be strictly "
            "increasing: 0.2 at index 2 follows 0.7");
  // A missing field: at the object that lacks it (the `{` of the first correction).
  EXPECT_EQ(ErrorForExampleEdit("\"term_order\": \"graded_x_y_z\",", ""),
            "calib.json:19:5: $.corrections[0].term_order: missing required field");
  // A future version.
  EXPECT_EQ(ErrorForExampleEdit("\"version\": 1", "\"version\": 2"),
            "calib.json:3:3: $.version: unsupported version 2; this reader supports version 1");
  // A key given twice: at the second one.
  EXPECT_EQ(ErrorForExampleEdit("\"role\": \"model_file\"",
                                "\"role\": \"model_file\",\n        \"role\": \"capture\""),
            "calib.json:108:9: $.provenance.inputs[0].role: given twice (a key may appear once per "
            "object)");
  // CRLF line ends (a file edited on Windows) count the same lines.
  std::string crlf;
  for (const char c : ReadFileToString(ExamplePath())) {
    if (c == '\n') crlf += '\r';
    crlf += c;
  }
  crlf.replace(crlf.find("\"version\": 1"), 12, "\"version\": 2");
  EXPECT_EQ(ErrorForText(crlf).rfind("calib.json: $.version: unsupported version 2", 0), 0u);
  try {
    ParseCalibrationJson(crlf, "calib.json");
  } catch (const JsonInputError& e) {
    EXPECT_EQ(std::string(e.what()).rfind("calib.json:3:3: $.version: ", 0), 0u) << e.what();
  }
}

TEST(ParseCalibrationJson, MisspeltFieldsNameTheirLineAndTheClosestValidName) {
  // A misspelt required field said "missing required field" at the `{` of its object, a misspelt
  // optional one "unknown field": the error is at the key as written and names the field meant.
  EXPECT_EQ(ErrorForExampleEdit("\"version\": 1", "\"verison\": 1"),
            "calib.json:3:3: $.verison: unknown field; did you mean \"version\" (a required "
            "field)?");
  EXPECT_EQ(ErrorForExampleEdit("\"term_order\"", "\"term_ordre\""),
            "calib.json:22:7: $.corrections[0].term_ordre: unknown field; did you mean "
            "\"term_order\" (a required field)?");
  EXPECT_EQ(ErrorForExampleEdit("\"description\"", "\"descripton\""),
            "calib.json:4:3: $.descripton: unknown field; did you mean \"description\"?");
  // Nothing near: as before.
  EXPECT_EQ(
      ErrorForExampleEdit("\"fade_distance\": 0.15", "\"fade_distance\": 0.15, \"outisde\": 1"),
      "calib.json:16:28: $.calibrated_volume.outisde: unknown field");
}

TEST(LocateJsonPath, FindsKeysPastStringsEscapesAndBom) {
  const auto at = [](const std::string& text, const std::string& path) {
    const std::optional<JsonTextPosition> p = LocateJsonPath(text, path);
    return p ? std::to_string(p->line) + ":" + std::to_string(p->column) : std::string("none");
  };
  // Brackets, braces and quotes inside strings are skipped; a key is matched decoded.
  const std::string text = "{\"a\": \"{[\\\"]}\", \"b\\u002ec\": [1, {\"d\": 2}],\n \"e\": {}}";
  EXPECT_EQ(at(text, "$.b.c[1].d"), "1:34");
  EXPECT_EQ(at(text, "$.b.c[1]"), "1:33");
  EXPECT_EQ(at(text, "$.e.missing"), "2:2");  // the deepest part that exists: "e"
  EXPECT_EQ(at(text, "$.a"), "1:2");
  EXPECT_EQ(at(text, "$"), "1:1");
  EXPECT_EQ(at("\xEF\xBB\xBF{\"a\": 1}", "$.a"), "1:5");  // bytes, the BOM's three included
  EXPECT_EQ(at("{\"a\": 1, \"a\": 2}", "$.a"), "1:10");   // a key given twice: the last
  EXPECT_EQ(at("", "$.a"), "none");
  EXPECT_EQ(at("{\"a\": [1, 2", "$.a[5]"), "1:2");  // text that ends early: what was found
}

TEST(ParseCalibrationJson, RejectsAKeyGivenTwice) {
  // A hand edit that adds a field instead of changing it: the JSON parser alone would keep the last
  // value without a word. Named by its JSON path, inside objects and array elements alike.
  const std::string text = ReadFileToString(ExamplePath());
  auto twice = [&](const std::string& field, const std::string& again) {
    std::string edited = text;
    const size_t at = edited.find(field);
    EXPECT_NE(at, std::string::npos) << field;
    edited.insert(at + field.size(), " " + again);
    return ErrorForText(edited);
  };
  EXPECT_EQ(twice("\"extrapolation\": \"fade\",", "\"fade_distance\": 0.5,"),
            "calib.json: $.calibrated_volume.fade_distance: given twice (a key may appear once per "
            "object)");
  EXPECT_EQ(twice("\"node_order\": \"x_slowest_z_fastest\",", "\"node_order\": 1,"),
            "calib.json: $.corrections[1].node_order: given twice (a key may appear once per "
            "object)");
  EXPECT_EQ(twice("\"version\": 1,", "\"version\": 1,"),
            "calib.json: $.version: given twice (a key may appear once per object)");
  // The same key in two objects is no repeat.
  EXPECT_EQ(ErrorForText(text), "");
}

TEST(ParseCalibrationJson, RejectsNonIncreasingAxesAndEmptyVolume) {
  EXPECT_EQ(ErrorAfterEdit([](nlohmann::json& j) {
              j["corrections"][1]["axes"]["z"] = {-0.1, 0.2, 0.2};
            }),
            "calib.json: $.corrections[1].axes.z[2]: axis values must be strictly increasing: 0.2 at index 2 follows 0.2");
  EXPECT_EQ(ErrorAfterEdit([](nlohmann::json& j) { j["corrections"][1]["axes"]["x"] = {0.5}; }),
            "calib.json: $.corrections[1].axes.x: an axis needs at least 2 nodes, got 1");
  EXPECT_EQ(ErrorAfterEdit([](nlohmann::json& j) { j["calibrated_volume"]["max"][1] = -0.5; }),
            "calib.json: $.calibrated_volume.max: empty volume: max.y = -0.5 is not above min.y = "
            "-0.5");
  EXPECT_EQ(ErrorAfterEdit([](nlohmann::json& j) { j["calibrated_volume"]["fade_distance"] = 0; }),
            "calib.json: $.calibrated_volume.fade_distance: must be positive for extrapolation "
            "\"fade\", got 0");
  EXPECT_EQ(ErrorAfterEdit([](nlohmann::json& j) {
              j["calibrated_volume"]["extrapolation"] = "hold";
            }),
            "calib.json: $.calibrated_volume.extrapolation: unknown value \"hold\"; expected one "
            "of \"clamp\", \"fade\", \"linear\"");
  EXPECT_EQ(ErrorAfterEdit([](nlohmann::json& j) { j["corrections"][0]["input_scale"][2] = 0; }),
            "calib.json: $.corrections[0].input_scale: entries must be positive, got [0.6,0.5,0]");
}

TEST(ParseCalibrationJson, LinearPolicyAndItsReach) {
  nlohmann::json j = ExampleJson();
  j["calibrated_volume"]["extrapolation"] = "linear";
  j["calibrated_volume"]["linear_reach"] = 0.05;
  const Calibration cal = ParseCalibrationJson(j.dump(), "calib.json");
  EXPECT_EQ(cal.volume().extrapolation, ExtrapolationPolicy::kLinear);
  EXPECT_EQ(cal.volume().linear_reach, 0.05);
  // Written back with its reach (bit-exact), and read again the same.
  const nlohmann::json written = CalibrationToJson(cal);
  EXPECT_EQ(written["calibrated_volume"]["linear_reach"], 0.05);
  EXPECT_EQ(CalibrationToJson(ParseCalibrationJson(written.dump(), "again")), written);
  // Optional: files written before the linear policy have no reach; the default applies.
  j["calibrated_volume"].erase("linear_reach");
  EXPECT_EQ(ParseCalibrationJson(j.dump(), "calib.json").volume().linear_reach,
            CalibratedVolume::kDefaultLinearReach);
  // Bad values name the file and the field.
  EXPECT_EQ(ErrorAfterEdit([](nlohmann::json& e) {
              e["calibrated_volume"]["extrapolation"] = "linear";
              e["calibrated_volume"]["linear_reach"] = -0.1;
            }),
            "calib.json: $.calibrated_volume.linear_reach: must not be negative, got -0.1");
  const std::string wrong_type = ErrorAfterEdit(
      [](nlohmann::json& e) { e["calibrated_volume"]["linear_reach"] = "far"; });
  EXPECT_EQ(wrong_type.rfind("calib.json: $.calibrated_volume.linear_reach: ", 0), 0u)
      << wrong_type;
}

// The receiver a calibration was fitted for (the capture's 1-based sensor column): written when
// known, read back, optional (the example and every file before the field have none: 0), and a
// bad value names the file and the field. Before, the file had no such field (unknown key).
TEST(ParseCalibrationJson, RecordsTheSensorItWasFittedFor) {
  EXPECT_EQ(ReadCalibrationFile(ExamplePath()).sensor, 0);
  nlohmann::json j = ExampleJson();
  j["sensor"] = 2;
  const Calibration cal = ParseCalibrationJson(j.dump(), "calib.json");
  EXPECT_EQ(cal.sensor, 2);
  EXPECT_EQ(CalibrationToJson(cal)["sensor"], 2);
  EXPECT_NE(CalibrationToJsonText(cal).find("\"description\": \"Example: degree-2 polynomial "
                                            "followed by a 2 x 2 x 3 residual LUT, Fastrak in lab "
                                            "B\",\n  \"sensor\": 2,\n"),
            std::string::npos)
      << CalibrationToJsonText(cal);
  EXPECT_FALSE(CalibrationToJson(ReadCalibrationFile(ExamplePath())).contains("sensor"));
  EXPECT_EQ(ErrorAfterEdit([](nlohmann::json& e) { e["sensor"] = 0; }),
            "calib.json: $.sensor: expected the capture's sensor number (1..64; Fastrak station n "
            "is sensor n), got 0");
  const std::string wrong_type = ErrorAfterEdit([](nlohmann::json& e) { e["sensor"] = "2"; });
  EXPECT_EQ(wrong_type.rfind("calib.json: $.sensor: ", 0), 0u) << wrong_type;
  Calibration bad = cal;
  bad.sensor = -1;
  EXPECT_THROW(CalibrationToJson(bad), std::invalid_argument);
}

TEST(ParseCalibrationJson, RejectsBadProvenance) {
  EXPECT_EQ(ErrorAfterEdit([](nlohmann::json& j) {
              j["provenance"]["inputs"][0]["sha256"] = "abc";
            }),
            "calib.json: $.provenance.inputs[0].sha256: expected 64 lower-case hexadecimal "
            "digits, got \"abc\"");
  EXPECT_EQ(ErrorAfterEdit([](nlohmann::json& j) { j["provenance"]["created_utc"] = "yesterday"; }),
            "calib.json: $.provenance.created_utc: expected an ISO 8601 UTC time "
            "\"YYYY-MM-DDTHH:MM:SSZ\", got \"yesterday\"");
  // The shape alone is not a time: each field is checked against its range.
  for (const char* bad : {"2026-13-01T00:00:00Z", "2026-00-10T00:00:00Z", "2026-02-29T00:00:00Z",
                          "2026-04-31T00:00:00Z", "2026-11-21T24:00:00Z", "2026-11-21T12:60:00Z",
                          "2026-11-21T12:00:61Z"}) {
    EXPECT_NE(ErrorAfterEdit([&](nlohmann::json& j) {
                j["provenance"]["created_utc"] = bad;
              }).find("$.provenance.created_utc: expected an ISO 8601 UTC time"),
              std::string::npos)
        << bad;
  }
  for (const char* good : {"2024-02-29T23:59:60Z", "2000-02-29T00:00:00.5Z"}) {
    EXPECT_EQ(ErrorAfterEdit([&](nlohmann::json& j) { j["provenance"]["created_utc"] = good; }), "")
        << good;
  }
}

TEST(ParseCalibrationJson, AnEmptyFileSaysSo) {
  // An empty file (an interrupted save) got the JSON parser's "syntax error while parsing value -
  // unexpected end of input" at its last line.
  const std::string tail =
      "; a calibration file is the JSON document that trackcal fit -o or trackcal-fit fit -o "
      "writes";
  EXPECT_EQ(ErrorForText(""), "calib.json: empty file" + tail);
  EXPECT_EQ(ErrorForText(" \n\r\n\t\n"), "calib.json: empty file (only white space)" + tail);
}

TEST(ReadCalibrationFile, MissingFileNamesPath) {
  try {
    ReadCalibrationFile("/nonexistent/calib.json");
    FAIL();
  } catch (const std::invalid_argument& e) {
    EXPECT_EQ(std::string(e.what()).rfind("/nonexistent/calib.json: cannot open", 0), 0u)
        << e.what();
  }
}

TEST(WriteCalibrationFile, NeverOverwritesAnInput) {
  const auto dir = testing::MakeTempDir("calib");
  Calibration cal = RandomCalibration();
  const auto capture = dir / "capture.csv";
  WriteFileAtomically(capture, "t,x,y,z\n0,1,2,3\n");
  cal.provenance.inputs = {{capture.string(), Sha256HexOfFile(capture), "calibration_capture"}};
  // Same path.
  EXPECT_THROW(WriteCalibrationFile(capture, cal), std::invalid_argument);
  // Same file through another spelling of the path.
  EXPECT_THROW(WriteCalibrationFile(dir / "." / "capture.csv", cal), std::invalid_argument);
  // A copy of an input (same digest) elsewhere.
  const auto copy = dir / "copy.json";
  WriteFileAtomically(copy, "t,x,y,z\n0,1,2,3\n");
  EXPECT_THROW(WriteCalibrationFile(copy, cal), std::invalid_argument);
  // Any existing non-calibration file.
  const auto notes = dir / "notes.json";
  WriteFileAtomically(notes, "{\"mine\": true}");
  EXPECT_THROW(WriteCalibrationFile(notes, cal), std::invalid_argument);
  EXPECT_EQ(ReadFileToString(capture), "t,x,y,z\n0,1,2,3\n");
  EXPECT_EQ(ReadFileToString(notes), "{\"mine\": true}");
  // An existing calibration output may be replaced.
  const auto out = dir / "calib.json";
  WriteCalibrationFile(out, cal);
  cal.description = "second";
  WriteCalibrationFile(out, cal);
  EXPECT_EQ(ReadCalibrationFile(out).description, "second");
}

// A calibration kept on purpose (chmod a-w) was replaced by the next fit written over it: a
// rename needs only the folder to be writable, whoever runs it. And a file replaced had the
// umask's mode, not its own.
TEST(WriteCalibrationFile, RefusesAReadOnlyFileAndKeepsTheModeOfOneItReplaces) {
  const auto dir = testing::MakeTempDir("calib");
  Calibration cal = RandomCalibration();
  const auto kept = dir / "kept.json";
  WriteCalibrationFile(kept, cal);
  const std::string before = ReadFileToString(kept);
  ASSERT_EQ(::chmod(kept.c_str(), 0444), 0);
  cal.description = "second";
  try {
    WriteCalibrationFile(kept, cal);
    ADD_FAILURE() << "a read-only calibration was replaced";
  } catch (const std::invalid_argument& e) {
    EXPECT_EQ(std::string(e.what()),
              kept.string() +
                  ": is read-only; refusing to replace it (make it writable to "
                  "replace it, or write the calibration to another file)");
  }
  EXPECT_THROW(CheckCalibrationOutput(kept), std::invalid_argument);  // before a long fit
  EXPECT_TRUE(ReadFileToString(kept) == before) << "the read-only file changed";
  // Writable by its group only (0460): not read-only.
  const auto shared = dir / "shared.json";
  WriteCalibrationFile(shared, cal);
  for (const std::filesystem::perms mode :
       {std::filesystem::perms(0664), std::filesystem::perms(0460)}) {
    std::filesystem::permissions(shared, mode);
    WriteCalibrationFile(shared, cal);
    EXPECT_EQ(std::filesystem::status(shared).permissions(), mode);
  }
}

// An output folder the user may not write in (a shared read-only folder, a read-only mount)
// passed the checks made before a fit, which then ran for minutes and failed at the end, its
// result lost: it is refused before the fit, naming the folder.
TEST(CheckCalibrationOutput, RefusesAFolderTheUserCannotWriteIn) {
  const auto dir = testing::MakeTempDir("calib_folder");
  const auto read_only = dir / "read_only";
  const auto writable = dir / "writable";
  std::filesystem::create_directory(read_only);
  std::filesystem::create_directory(writable);
  ASSERT_EQ(::chmod(dir.c_str(), 0755), 0);
  ASSERT_EQ(::chmod(read_only.c_str(), 0555), 0);
  ASSERT_EQ(::chmod(writable.c_str(), 0777), 0);
  // The outcome of the checks as the user "nobody" (root writes in any folder): 0 refused naming
  // the folder, 1 accepted, 2 refused for another reason.
  const auto outcome = [](const std::filesystem::path& out) {
    try {
      CheckCalibrationOutput(out);
      return 1;
    } catch (const std::invalid_argument& e) {
      const std::string expected = out.string() + ": cannot write here: the folder " +
                                   out.parent_path().string() + " is not writable";
      return std::string(e.what()).rfind(expected, 0) == 0 ? 0 : 2;
    }
  };
  const auto as_nobody = [&outcome](const std::filesystem::path& out) {
    if (::geteuid() != 0) return outcome(out);
    const pid_t child = ::fork();
    if (child == 0) {
      if (::setgid(65534) != 0 || ::setuid(65534) != 0) ::_exit(3);
      ::_exit(outcome(out));
    }
    int status = 0;
    ::waitpid(child, &status, 0);
    return WIFEXITED(status) ? WEXITSTATUS(status) : 4;
  };
  EXPECT_EQ(as_nobody(read_only / "calib.json"), 0);
  EXPECT_EQ(as_nobody(writable / "calib.json"), 1);
}

// A folder as the output said "read error: Is a directory" (the inputs' SHA-256 check read it)
// before CheckCalibrationOutput's plain sentence.
TEST(WriteCalibrationFile, AFolderIsNamedAsAFolder) {
  const auto dir = testing::MakeTempDir("calib");
  Calibration cal = RandomCalibration();
  const auto capture = dir / "capture.csv";
  WriteFileAtomically(capture, "t,x,y,z\n0,1,2,3\n");
  cal.provenance.inputs = {{capture.string(), Sha256HexOfFile(capture), "calibration_capture"}};
  std::filesystem::create_directory(dir / "out");
  try {
    WriteCalibrationFile(dir / "out", cal);
    ADD_FAILURE() << "a folder was accepted";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("out: is a folder; give a file name"), std::string::npos)
        << e.what();
  }
}

TEST(WriteCalibrationFile, RejectsIncompleteCalibration) {
  Calibration cal = RandomCalibration();
  cal.chain.ClearVolume();
  const auto dir = testing::MakeTempDir("calib");
  EXPECT_THROW(WriteCalibrationFile(dir / "x.json", cal), std::invalid_argument);
  EXPECT_FALSE(std::filesystem::exists(dir / "x.json"));
  cal = RandomCalibration();
  cal.provenance.inputs[0].sha256 = "nothex";
  EXPECT_THROW(WriteCalibrationFile(dir / "x.json", cal), std::invalid_argument);
  cal = RandomCalibration();
  cal.fit_statistics["bad"] = std::nan("");
  EXPECT_THROW(WriteCalibrationFile(dir / "x.json", cal), std::invalid_argument);
  // A term that overflows in the volume: the reader would refuse the file.
  cal = RandomCalibration();
  CorrectionChain chain;
  chain.Append(std::make_unique<PolynomialCorrection>(
      2, Eigen::Vector3d::Zero(), Eigen::Vector3d(1e-200, 1, 1),
      std::vector<double>(6 * NumPolynomialTerms(2), 0.001)));
  chain.SetVolume(cal.volume());
  cal.chain = chain;
  EXPECT_THROW(WriteCalibrationFile(dir / "x.json", cal), std::invalid_argument);
  EXPECT_FALSE(std::filesystem::exists(dir / "x.json"));
}

}  // namespace
}  // namespace trackcal
