#include "fit/model_file.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include "fit/fit_engine.h"
#include "fit/terms_polynomial.h"
#include "tests/test_utils.h"

namespace trackcal::fit {
namespace {

using ::testing::HasSubstr;

std::string ErrorOf(const std::string& text) {
  try {
    ParseModelYaml(text, "model.yaml");
  } catch (const std::invalid_argument& e) {
    return e.what();
  }
  return "";
}

TEST(ParseModelYaml, Nominal) {
  const ModelSpec spec = ParseModelYaml(R"(
noise: {position_mm: 2.0, orientation_deg: 0.5}
loss: {type: huber, scale: 4}
solver: {max_iterations: 20, covariance: false}
time_offset: {value: 0.01, fixed: false}
terms:
  - type: polynomial
    degree: 3
    orientation: false
    parameters:
      position_coefficients: {prior: {mean: 0, sigma: 1}}
)",
                                        "model.yaml");
  EXPECT_DOUBLE_EQ(spec.position_sigma, 2e-3);
  EXPECT_NEAR(spec.orientation_sigma, 0.5 * M_PI / 180.0, 1e-15);
  EXPECT_EQ(spec.loss.type, LossType::kHuber);
  EXPECT_DOUBLE_EQ(spec.loss.scale, 4.0);
  EXPECT_EQ(spec.max_iterations, 20);
  EXPECT_FALSE(spec.covariance);
  ASSERT_TRUE(spec.time_offset.has_value());
  EXPECT_FALSE(spec.time_offset->fixed);
  ASSERT_EQ(spec.terms.size(), 1u);
  const auto& poly = dynamic_cast<const PolynomialTerm&>(*spec.terms[0]);
  EXPECT_EQ(poly.options().degree, 3);
  EXPECT_FALSE(poly.options().orientation);
  ASSERT_EQ(poly.blocks().size(), 1u);
  EXPECT_EQ(poly.blocks()[0].values.size(), 20u * 3u);
  ASSERT_EQ(spec.block_settings[0].size(), 1u);
}

TEST(ParseModelYaml, RepeatedTermsAreNumbered) {
  const ModelSpec spec = ParseModelYaml(
      "terms:\n  - {type: polynomial, degree: 1}\n  - {type: polynomial, degree: 2}\n", "m");
  ASSERT_EQ(spec.terms.size(), 2u);
  EXPECT_EQ(spec.terms[0]->name(), "polynomial");
  EXPECT_EQ(spec.terms[1]->name(), "polynomial_2");
}

TEST(ParseModelYaml, ErrorsNameFileLineAndField) {
  EXPECT_THAT(ErrorOf("terms:\n  - type: polynomial\n    degre: 4\n"),
              HasSubstr("model.yaml:3:5: $.terms[0].degre: unknown key"));
  EXPECT_THAT(ErrorOf("terms:\n  - type: polynomial\n    degree: 99\n"),
              HasSubstr("model.yaml:3:13: $.terms[0].degree"));
  EXPECT_THAT(ErrorOf("terms:\n  - type: warp\n"),
              HasSubstr("model.yaml:2:11: $.terms[0].type: unknown term type 'warp'"));
  EXPECT_THAT(ErrorOf("terms: []\n"), HasSubstr("at least one correction term"));
  EXPECT_THAT(ErrorOf("noise: {position_mm: -1}\nterms: [{type: polynomial}]\n"),
              HasSubstr("model.yaml:1:22: $.noise.position_mm: must be > 0"));
  EXPECT_THAT(ErrorOf("terms: [{type: polynomial}]\nextra: 1\n"),
              HasSubstr("model.yaml:2:1: $.extra: unknown key"));
  EXPECT_THAT(ErrorOf("terms: [{type: polynomial\n"), HasSubstr("YAML syntax error"));
  // A key given twice: yaml-cpp would read the first and drop the second silently.
  EXPECT_THAT(ErrorOf("noise: {position_mm: 0.5}\nterms: [{type: polynomial}]\nnoise: {}\n"),
              HasSubstr("model.yaml:3:1: $.noise: given twice (also at line 1)"));
  EXPECT_THAT(ErrorOf("terms:\n  - {type: polynomial, degree: 2, degree: 4}\n"),
              HasSubstr("$.terms[0].degree: given twice"));
  EXPECT_THAT(ErrorOf("loss: {type: l1}\nterms: [{type: polynomial}]\n"),
              HasSubstr("$.loss.type: unknown loss 'l1'"));
  EXPECT_THAT(ErrorOf("noise: {amplification_threshold: 0.5}\nterms: [{type: polynomial}]\n"),
              HasSubstr("model.yaml:1:34: $.noise.amplification_threshold: must be finite and >= 1"));
  EXPECT_THAT(ErrorOf("solver: {stream_clusters: 4}\nterms: [{type: polynomial}]\n"),
              HasSubstr("model.yaml:1:27: $.solver.stream_clusters: must be 0"));
  EXPECT_EQ(ParseModelYaml("terms: [{type: polynomial}]\n", "m").stream_clusters, 32);
  EXPECT_EQ(
      ParseModelYaml("solver: {stream_clusters: 0}\nterms: [{type: polynomial}]\n", "m").stream_clusters,
      0);
}

// A number the parser does not take was named by its field only ("expected a finite number"):
// the value is shown, and a decimal comma is called one. A calibration file given as the model
// said "$.terms: missing required field".
TEST(ParseModelYaml, ErrorsShowTheValueAndNameACalibrationFile) {
  EXPECT_THAT(ErrorOf("noise:\n  position_mm: 1,5\nterms: [{type: polynomial}]\n"),
              HasSubstr("model.yaml:2:16: $.noise.position_mm: expected a finite number, got "
                        "'1,5' (write '.' as the decimal point)"));
  EXPECT_THAT(ErrorOf("noise:\n  position_mm: 1 mm\nterms: [{type: polynomial}]\n"),
              HasSubstr("$.noise.position_mm: expected a finite number, got '1 mm'"));
  EXPECT_THAT(ErrorOf("terms:\n  - type: polynomial\n    degree: 2.5\n"),
              HasSubstr("model.yaml:3:13: $.terms[0].degree: expected an integer, got '2.5'"));
  EXPECT_THAT(ErrorOf("noise: {position_mm: [1, 2]}\nterms: [{type: polynomial}]\n"),
              ::testing::EndsWith("$.noise.position_mm: expected a finite number"));
  EXPECT_THAT(
      ErrorOf("{\"format\": \"trackcal-calibration\", \"version\": 1, \"corrections\": []}\n"),
      HasSubstr("model.yaml: a calibration file (format trackcal-calibration), not a model "
                "file"));
}

// A misspelt key said "unknown key", and a misspelt required one "missing required field" at the
// top of its mapping (line 1 for `terms`): the error names the line of the key as written and the
// valid name it most likely meant.
TEST(ParseModelYaml, MisspeltKeysNameTheLineAndTheClosestValidName) {
  EXPECT_EQ(ErrorOf("noise: {position_mm: 1}\nterm:\n  - type: polynomial\n"),
            "model.yaml:2:1: $.term: unknown key; did you mean 'terms' (a required field)?");
  EXPECT_EQ(ErrorOf("terms:\n  - tpye: polynomial\n    degree: 4\n"),
            "model.yaml:2:5: $.terms[0].tpye: unknown key; did you mean 'type' (a required "
            "field)?");
  EXPECT_EQ(ErrorOf("terms:\n  - type: polynomial\n    degre: 4\n"),
            "model.yaml:3:5: $.terms[0].degre: unknown key; did you mean 'degree'?");
  EXPECT_EQ(ErrorOf("solver: {max_iteration: 5}\nterms: [{type: polynomial}]\n"),
            "model.yaml:1:10: $.solver.max_iteration: unknown key; did you mean "
            "'max_iterations'?");
  EXPECT_EQ(ErrorOf("terms:\n  - type: polynomal\n"),
            "model.yaml:2:11: $.terms[0].type: unknown term type 'polynomal'; did you mean "
            "'polynomial'? (known: polynomial, lut, sensor_offset, receiver_gain, dipole, plane, "
            "near_field, background_field, time_offset)");
  // Nothing near: no suggestion, and a missing field is still named where its mapping starts.
  EXPECT_EQ(ErrorOf("terms: [{type: polynomial}]\nextra: 1\n"),
            "model.yaml:2:1: $.extra: unknown key");
  EXPECT_EQ(ErrorOf("noise: {position_mm: 1}\n"),
            "model.yaml:1:1: $.terms: missing required field");
}

// A model file had no version: `version: 2` (a file written for a newer trackcal) said only
// "$.version: unknown key", as a typo would. Version 1 may be given; none means 1 (every file
// written so far); another is refused as the calibration file refuses one.
TEST(ParseModelYaml, VersionIsOneOrAbsentAndANewerOneIsNamed) {
  EXPECT_EQ(ErrorOf("version: 1\nterms: [{type: polynomial}]\n"), "");
  EXPECT_EQ(ErrorOf("terms: [{type: polynomial}]\n"), "");
  EXPECT_EQ(ErrorOf("version: 2\nterms: [{type: polynomial}]\n"),
            "model.yaml:1:10: $.version: model file version 2; this trackcal reads version 1 (a "
            "newer file needs a newer trackcal)");
  EXPECT_EQ(ErrorOf("version: 1.1\nterms: [{type: polynomial}]\n"),
            "model.yaml:1:10: $.version: expected an integer, got '1.1'");
  // Checked first: a newer file's unknown keys or term types are not what to report.
  EXPECT_EQ(ErrorOf("terms: [{type: spline}]\nversion: 3\n"),
            "model.yaml:2:10: $.version: model file version 3; this trackcal reads version 1 (a "
            "newer file needs a newer trackcal)");
  // build's settings file takes it too.
  EXPECT_NO_THROW(ParseModelSettingsYaml("version: 1\nnoise: {position_mm: 1}\n", "s.yaml"));
}

TEST(ParseModelYaml, ErrorsQuotingBytesThatAreNotUtf8ArePrintable) {
  // A key typed in a Latin-1 editor: the message quoted it raw, and in Python (trackcal.fit,
  // trackcal fit) it failed as it became a str, "'utf-8' codec can't decode byte 0xe9", naming no
  // file. A Latin-1 comment is no error.
  EXPECT_EQ(ErrorOf("terms:\n  - type: polynomial\n    degr\xe9"
                    "e: 4\n"),
            "model.yaml:3:5: $.terms[0].degr\\xe9e: unknown key; did you mean 'degree'?");
  EXPECT_EQ(ErrorOf("terms:\n  - type: polyn\xf4mial\n"),
            "model.yaml:2:11: $.terms[0].type: unknown term type 'polyn\\xf4mial'; did you mean "
            "'polynomial'? (known: polynomial, lut, sensor_offset, receiver_gain, dipole, plane, "
            "near_field, "
            "background_field, time_offset)");
  EXPECT_EQ(ErrorOf("# Kalibrierung f\xfcr Raum B\nterms:\n  - type: polynomial\n"), "");
}

TEST(ReadModelFile, AFileThatCannotBeReadSaysWhy) {
  // "cannot open model file" gave no reason, and a folder opened as a stream and read as an empty
  // model.
  auto error_of = [](const std::filesystem::path& path) {
    try {
      ReadModelFile(path);
    } catch (const std::invalid_argument& e) {
      return std::string(e.what());
    }
    return std::string();
  };
  EXPECT_EQ(error_of("/nonexistent/model.yaml"),
            "/nonexistent/model.yaml: cannot open model file: No such file or directory");
  const auto folder = trackcal::testing::MakeTempDir("model_file_test");
  EXPECT_EQ(error_of(folder), folder.string() + ": is a folder, not a model file");
}

TEST(ParseModelYaml, AFileThatIsNotYamlTextSaysSoWithItsLine) {
  const std::string text = "noise:\n  position_mm: 1\nterms:\n  - type: polynomial\n";
  // Notepad's "Unicode" save: yaml-cpp decoded the UTF-16 and the model was accepted without a
  // word, its text (hashed into the provenance) not UTF-8.
  std::string le = "\xFF\xFE", be = "\xFE\xFF";
  for (const char c : text) {
    le += std::string{c, '\0'};
    be += std::string{'\0', c};
  }
  const std::string utf16 =
      "model.yaml: UTF-16 text (a byte order mark FF FE or FE FF); save the model file as UTF-8";
  EXPECT_EQ(ErrorOf(le), utf16);
  EXPECT_EQ(ErrorOf(be), utf16);
  try {
    ParseModelSettingsYaml(le, "s.yaml");
    ADD_FAILURE() << "UTF-16 settings were read";
  } catch (const std::invalid_argument& e) {
    EXPECT_EQ(std::string(e.what()),
              "s.yaml: UTF-16 text (a byte order mark FF FE or FE FF); save the settings file as "
              "UTF-8");
  }
  // A binary file (an image, an archive): yaml-cpp's "unknown escape character: ", cut at the NUL.
  EXPECT_EQ(ErrorOf(std::string("\x89PNG\r\n\x1a\n\0\0\0\rIHDR", 16)),
            "model.yaml:3:1: a NUL byte: not a text file; the model file is YAML text");
  EXPECT_EQ(ErrorOf(std::string("PK\x03\x04\x14\0\x06\0", 8)),
            "model.yaml:1:6: a NUL byte: not a text file; the model file is YAML text");
  // An empty or comment-only file (or a lone byte order mark) has no line to name.
  const std::string no_entries =
      "model.yaml: no entries (the file is empty or only comments); the model file must be a "
      "mapping with 'terms'";
  EXPECT_EQ(ErrorOf(""), no_entries);
  EXPECT_EQ(ErrorOf("# terms to come\n\n# nothing yet\n"), no_entries);
  EXPECT_EQ(ErrorOf("\xEF\xBB\xBF"), no_entries);
  // What is there and is no mapping is named where it starts.
  EXPECT_EQ(ErrorOf("# a list\n- type: polynomial\n"),
            "model.yaml:2:1: the model file must be a mapping with 'terms'");
}

TEST(ParseModelYaml, ATabInTheIndentationIsNamed) {
  // An editor's tab indent: yaml-cpp said "illegal block entry" or "illegal map value".
  const std::string tabs =
      ": YAML syntax error: a tab in the indentation; YAML indents with spaces only (replace the "
      "tab with spaces)";
  EXPECT_EQ(ErrorOf("noise:\n  position_mm: 1\nterms:\n\t- type: polynomial\n\t  degree: 1\n"),
            "model.yaml:4:1" + tabs);
  EXPECT_EQ(ErrorOf("noise:\n\tposition_mm: 1\nterms:\n  - type: polynomial\n"),
            "model.yaml:2:1" + tabs);
  EXPECT_EQ(ErrorOf("terms:\n  - type: polynomial\n  \tdegree: 1\n"), "model.yaml:3:3" + tabs);
  // A tab elsewhere is no error (before a comment, between a key and its value), nor the cause of
  // a later syntax error.
  EXPECT_EQ(ErrorOf("\t# comment\nterms:\n  - type:\tpolynomial  \t# tab\n"), "");
  EXPECT_EQ(ErrorOf("\t# comment\nterms:\n  - type: polynomial\n  - [\n"),
            "model.yaml:5:1: YAML syntax error: end of sequence flow not found");
  // Tab-indented continuation lines of a flow mapping and of a block scalar are legal YAML (the
  // file parses without the last line): a typo further down is named, not the tab.
  const std::string legal_tabs =
      "noise: {position_mm: 1.0,\n\torientation_deg: 0.2}\nterms:\n  - type: polynomial\n"
      "    name: |\n      a\n      \tb\n";
  EXPECT_EQ(ErrorOf(legal_tabs), "");
  EXPECT_EQ(ErrorOf(legal_tabs + "  - type: [\n"),
            "model.yaml:9:1: YAML syntax error: end of sequence flow not found");
}

TEST(ParseModelYaml, RejectsASecondDocument) {
  // YAML::Load read the first document only: the noise after `---` was dropped.
  EXPECT_THAT(ErrorOf("terms: [{type: polynomial}]\n---\nnoise: {position_mm: 5}\n"),
              HasSubstr("model.yaml:3:1: a second YAML document"));
  EXPECT_NO_THROW(ParseModelYaml("terms: [{type: polynomial}]\n---\n", "m"));
}

TEST(ParseModelYaml, AKeyWithoutAValueIsAnError) {
  // A forgotten value took the default silently.
  EXPECT_THAT(ErrorOf("terms:\n  - type: polynomial\n    degree:\n"),
              HasSubstr("model.yaml:3:5: $.terms[0].degree: no value given"));
  EXPECT_THAT(ErrorOf("noise:\n  position_mm:\nterms: [{type: polynomial}]\n"),
              HasSubstr("model.yaml:2:3: $.noise.position_mm: no value given"));
  EXPECT_THAT(ErrorOf("noise: ~\nterms: [{type: polynomial}]\n"),
              HasSubstr("model.yaml:1:1: $.noise: no value given"));
  EXPECT_THAT(ErrorOf("terms:\n  - type: polynomial\n    parameters:\n"
                      "      position_coefficients: {fixed: }\n"),
              HasSubstr("$.terms[0].parameters.position_coefficients.fixed: no value given"));
}

TEST(ParseModelYaml, TopLevelTimeOffsetRejectsUnknownKeys) {
  EXPECT_THAT(ErrorOf("time_offset: {valu: 0.01}\nterms: [{type: polynomial}]\n"),
              HasSubstr("model.yaml:1:15: $.time_offset.valu: unknown key"));
}

TEST(ParseModelYaml, MergeKeysAreRejectedByName) {
  EXPECT_THAT(
      ErrorOf("base: &b {type: polynomial, degree: 2}\nterms:\n  - <<: *b\n    degree: 3\n"),
      HasSubstr("model.yaml:3:5: $.terms[0].<<: merge keys are not supported"));
}

TEST(ParseModelYaml, AListAsAKeyIsNamed) {
  EXPECT_THAT(ErrorOf("? [a, b]\n: 1\nterms: [{type: polynomial}]\n"),
              HasSubstr("model.yaml:1:3: $: a key must be a plain name"));
}

TEST(ParseModelYaml, RejectsAnEmptyTermName) {
  EXPECT_THAT(ErrorOf("terms:\n  - {type: polynomial, name: \"\"}\n"),
              HasSubstr("$.terms[0].name: must not be empty"));
}

TEST(ParseModelYaml, ASearchedBlockHeldFixedNeedsAStart) {
  // Held fixed, the search was skipped and the dipole stayed at its placeholder [0, 0, 1].
  EXPECT_THAT(ErrorOf("terms:\n  - type: dipole\n    parameters:\n"
                      "      location_in_transmitter: {fixed: true}\n"),
              HasSubstr("model.yaml:4:32: $.terms[0].parameters.location_in_transmitter.fixed: "
                        "term 'dipole' block 'location_in_transmitter' is held fixed but has no "
                        "start value"));
  EXPECT_THAT(ErrorOf("terms:\n  - type: plane\n    parameters:\n"
                      "      normal_in_transmitter: {fixed: true}\n"),
              HasSubstr("give normal_in_transmitter"));
  EXPECT_NO_THROW(
      ParseModelYaml("terms:\n  - type: dipole\n    location_in_transmitter: [1, 0, 0]\n"
                     "    parameters:\n      location_in_transmitter: {fixed: true}\n",
                     "m"));
  EXPECT_NO_THROW(
      ParseModelYaml("terms:\n  - type: plane\n    parameters:\n"
                     "      normal_in_transmitter: {fixed: true, value: [0, 0, 1]}\n",
                     "m"));
}

TEST(ParseModelYaml, TermOptionErrorsNameTheirKey) {
  EXPECT_THAT(ErrorOf("terms:\n  - {type: polynomial, position: false, orientation: false}\n"),
              HasSubstr("$.terms[0].orientation: polynomial: at least one of position"));
  EXPECT_THAT(ErrorOf("terms:\n  - type: lut\n    ridge: -1\n"),
              HasSubstr("model.yaml:3:12: $.terms[0].ridge: lut: ridge must be >= 0"));
  EXPECT_THAT(ErrorOf("terms:\n  - type: polynomial\n    ridge_cv: blocked\n"),
              HasSubstr("model.yaml:3:15: $.terms[0].ridge_cv: only with ridge: auto"));
}

// 1e300 was accepted; the fit then failed to evaluate its weights and still exited 0.
TEST(ParseModelYaml, RangeExponentsAreBounded) {
  EXPECT_THAT(ErrorOf("noise: {position_range_exponent: 1e300}\nterms: [{type: polynomial}]\n"),
              HasSubstr("$.noise.position_range_exponent: must be 0 .. 8"));
  EXPECT_THAT(ErrorOf("noise: {orientation_range_exponent: -1}\nterms: [{type: polynomial}]\n"),
              HasSubstr("$.noise.orientation_range_exponent: must be 0 .. 8"));
  // With 1e-100 m the weights became infinite and the fit wrote a calibration that fitted nothing.
  EXPECT_THAT(ErrorOf("noise: {position_range_exponent: 8, reference_range_m: 1e-100}\n"
                      "terms: [{type: polynomial}]\n"),
              HasSubstr("$.noise.reference_range_m: must be 0.01 .. 100"));
  EXPECT_EQ(ErrorOf("noise: {position_range_exponent: 4, orientation_range_exponent: 3}\n"
                    "terms: [{type: polynomial}]\n"),
            "");
}

// Both were accepted and the node counts used: `cell_size_mm: 50` was dropped without a word.
TEST(ParseModelYaml, LutTakesNodesOrCellSizeNotBoth) {
  EXPECT_THAT(ErrorOf("terms:\n  - type: lut\n    cell_size_mm: 50\n    nodes: [3, 3, 3]\n"),
              HasSubstr("model.yaml:4:12: $.terms[0].nodes: give nodes or cell_size_mm, not both"));
  EXPECT_EQ(ErrorOf("terms:\n  - type: lut\n    nodes: [3, 3, 3]\n"), "");
  EXPECT_EQ(ErrorOf("terms:\n  - type: lut\n    cell_size_mm: 50\n"), "");
}

// A list as a block name read as "$.terms[0].parameters: missing required field".
TEST(ParseModelYaml, AListAsABlockNameIsNamed) {
  EXPECT_THAT(
      ErrorOf("terms:\n  - type: polynomial\n    parameters:\n      [a]: {fixed: true}\n"),
      HasSubstr("model.yaml:4:7: $.terms[0].parameters: a block name must be a plain name"));
}

// Errors that only the stations reveal name the model file's entry too: a LUT cell too fine for
// the stations' box said "lut: cell_size_mm 0.001 over the stations' box ..." with no file or line.
TEST(ParseModelYaml, ErrorsFoundWithTheDataNameTheTerm) {
  ModelSpec spec = ParseModelYaml(
      "terms:\n  - type: polynomial\n    degree: 1\n  - type: lut\n    cell_size_mm: 0.001\n",
      "m.yaml");
  std::vector<FitStation> stations;
  for (int i = 0; i < 8; ++i) {
    FitStation s;
    s.reported.translation = Eigen::Vector3d(0.1 * (i % 2), 0.1 * (i / 2 % 2), 0.1 * (i / 4));
    s.reference = s.reported;
    s.station = i + 1;
    stations.push_back(s);
  }
  try {
    FitModel(stations, &spec);
    FAIL() << "expected an error";
  } catch (const std::invalid_argument& e) {
    EXPECT_THAT(e.what(), HasSubstr("m.yaml:4:5: $.terms[1]: lut: cell_size_mm 0.001"));
  }
}

// trackcal-fit build's settings: the builder appends `terms:` to their text, which a flow mapping
// (or JSON) or a document end marker turned into "a second YAML document".
TEST(ParseModelSettingsYaml, AcceptsAnyStyleAndRefusesTerms) {
  for (const std::string text :
       {"noise: {position_mm: 0.5}\n", "{noise: {position_mm: 0.5}}\n",
        "{\"noise\": {\"position_mm\": 0.5}}", "noise: {position_mm: 0.5}\n...\n",
        "---\nnoise: {position_mm: 0.5}\n---\n"}) {
    EXPECT_DOUBLE_EQ(ParseModelSettingsYaml(text, "s.yaml").position_sigma, 0.5e-3) << text;
    const std::string block = ModelSettingsBlockYaml(text, "s.yaml");
    const ModelSpec spec = ParseModelYaml(block + "terms: [{type: polynomial}]\n", "s.yaml");
    EXPECT_DOUBLE_EQ(spec.position_sigma, 0.5e-3) << text;
  }
  // Block style is kept as written (comments too).
  EXPECT_EQ(ModelSettingsBlockYaml("# mine\nsolver: {covariance: false}\n", "s.yaml"),
            "# mine\nsolver: {covariance: false}\n");
  EXPECT_EQ(ParseModelSettingsYaml("", "s.yaml").position_sigma, ModelSpec().position_sigma);
  try {
    ParseModelSettingsYaml("noise: {position_mm: 1}\nterms: [{type: polynomial}]\n", "s.yaml");
    FAIL() << "expected an error";
  } catch (const std::invalid_argument& e) {
    EXPECT_THAT(e.what(), HasSubstr("s.yaml:2:8: $.terms: build chooses the terms itself"));
  }
  EXPECT_THROW(ParseModelSettingsYaml("{noise: {position_mm: 1}, foo: 1}", "s.yaml"),
               std::invalid_argument);
  EXPECT_THROW(ParseModelSettingsYaml("- 1\n", "s.yaml"), std::invalid_argument);
}

TEST(ApplyBlockSettings, RejectsUnknownBlockAndWrongSizes) {
  ModelSpec spec = ParseModelYaml(R"(terms:
  - type: polynomial
    degree: 1
    parameters:
      nodes: {fixed: true}
)",
                                  "m.yaml");
  try {
    ApplyBlockSettings(spec.block_settings[0], spec.terms[0].get());
    FAIL() << "expected an error";
  } catch (const std::invalid_argument& e) {
    EXPECT_THAT(e.what(), HasSubstr("m.yaml:5:14"));
    EXPECT_THAT(e.what(), HasSubstr("no parameter block 'nodes'"));
  }
  spec = ParseModelYaml(
      "terms:\n  - type: polynomial\n    degree: 1\n    parameters:\n"
      "      position_coefficients: {value: [1, 2]}\n",
      "m.yaml");
  EXPECT_THROW(ApplyBlockSettings(spec.block_settings[0], spec.terms[0].get()),
               std::invalid_argument);
}

TEST(TermRegistry, RejectsDuplicateType) {
  EXPECT_TRUE(TermRegistry::Global().Contains("polynomial"));
  EXPECT_THROW(TermRegistry::Global().Register("polynomial", &PolynomialTerm::FromYaml),
               std::invalid_argument);
}

}  // namespace
}  // namespace trackcal::fit
