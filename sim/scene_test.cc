#include "sim/scene.h"

#include <fcntl.h>
#include <gtest/gtest.h>
#include <sys/stat.h>
#include <unistd.h>

#include <fstream>
#include <thread>

#include "tests/test_utils.h"

namespace trackcal::sim {
namespace {

std::string ErrorOf(const std::string& yaml) {
  try {
    ParseScene(yaml, "bad.yaml");
  } catch (const std::invalid_argument& e) {
    return e.what();
  }
  return "";
}

TEST(LoadScene, Nominal) {
  const Scene paper = LoadScene("paper");
  EXPECT_EQ(paper.name, "paper");
  // 480 calibration stations (the paper's count; see the preset on its "12 x 10 x 5 grid").
  EXPECT_EQ(paper.capture.calibration.counts, Eigen::Vector3i(12, 10, 4));
  EXPECT_EQ(paper.capture.calibration.spacing_m, 0.15);
  EXPECT_EQ(paper.capture.validation.count, 120);
  EXPECT_EQ(paper.capture.registration.count, 20);
  EXPECT_EQ(paper.reference.markers_in_body.size(), 6u);
  EXPECT_GE(paper.environment.planes.size(), 2u);
  EXPECT_FALSE(paper.hidden.sensor_offset);
  // The distortion sources of the paper's room, at the distances it gives.
  bool floor = false, door = false;
  for (const auto& p : paper.environment.planes) {
    const double distance =
        std::abs(p.point_in_transmitter.dot(p.normal_in_transmitter.normalized()));
    floor |= p.name.find("floor") != std::string::npos && std::abs(distance - 0.8) < 1e-12;
    door |= p.name.find("door") != std::string::npos && std::abs(distance - 2.1) < 1e-12;
  }
  EXPECT_TRUE(floor);
  EXPECT_TRUE(door);
  for (const auto& o : paper.environment.objects) {
    if (o.name.find("monitor") != std::string::npos) {
      EXPECT_GE(o.location_in_transmitter.norm(), 1.8) << o.name;
    }
  }
  EXPECT_NE(std::find(PresetNames().begin(), PresetNames().end(), "paper"), PresetNames().end());
}

TEST(SceneToYaml, RoundTripIsBitExact) {
  Scene scene = LoadScene("paper");
  scene.seed = 12345678901234ULL;
  scene.hidden.Enable("sensor_offset");
  scene.environment.objects.push_back(
      {"odd", Eigen::Vector3d(0.1 / 3, 2.0 / 7, -1e-17 + 1), 1.0 / 3});
  const Scene again = ParseScene(SceneToYaml(scene), "written.yaml");
  EXPECT_EQ(SceneToJson(scene).dump(), SceneToJson(again).dump());
  EXPECT_EQ(again.environment.objects.back().polarisability_m3, 1.0 / 3);
}

TEST(ParseScene, BaseAndOverrides) {
  const Scene s = ParseScene(
      "base: paper\n"
      "seed: 5\n"
      "environment:\n"
      "  objects: []\n"
      "tracker:\n"
      "  signal_noise: 0\n",
      "override.yaml");
  const Scene paper = LoadScene("paper");
  EXPECT_EQ(s.seed, 5u);
  EXPECT_TRUE(s.environment.objects.empty());
  EXPECT_EQ(s.tracker.signal_noise, 0.0);
  EXPECT_EQ(s.environment.planes.size(), paper.environment.planes.size());
  EXPECT_EQ(s.capture.validation.count, paper.capture.validation.count);
}

TEST(ParseScene, ErrorsNameFileLineAndField) {
  EXPECT_EQ(ErrorOf("base: paper\ntracker:\n  signal_noise: abc\n"),
            "bad.yaml:3: tracker.signal_noise: expected a number, got 'abc'");
  EXPECT_EQ(ErrorOf("base: paper\ntracker:\n  signal_nois: 1\n"),
            "bad.yaml:3: tracker.signal_nois: unknown key");
  EXPECT_EQ(
      ErrorOf("base: paper\nenvironment:\n  planes:\n    - name: x\n      attenuation: [1]\n"),
      "bad.yaml:5: environment.planes[0].attenuation: expected a single value");
  EXPECT_EQ(ErrorOf("base: paper\ncapture:\n  calibration:\n    counts: [1, 2]\n"),
            "bad.yaml:4: capture.calibration.counts: expected a list of 3 integers");
  EXPECT_EQ(ErrorOf("base: nowhere\n").rfind("bad.yaml:1: base: unknown scene preset 'nowhere'", 0),
            0u);
  // Semantic checks name the file, the line of the key (or of its closest enclosing key in this
  // file when the value comes from the base preset) and the field as it is spelled in the file.
  EXPECT_EQ(ErrorOf("base: paper\ntracker:\n  samples_per_station: 0\n"),
            "bad.yaml:3: tracker.samples_per_station: must be >= 1");
  EXPECT_EQ(
      ErrorOf("base: paper\nreference:\n  markers_in_body:\n    - [0.1, 0, 0]\n"
              "    - [0.1, 0, 0]\n    - [0, 0, 0]\n"),
      "bad.yaml:6: reference.markers_in_body[2]: must be finite and away from the body origin");
  EXPECT_EQ(ErrorOf("base: paper\ncapture:\n  validation:\n    min_in_transmitter: [1, 1, 1]\n"),
            "bad.yaml:4: capture.validation.max_in_transmitter: must be finite and >= "
            "min_in_transmitter");
  // The environment's checks (core's FieldModel) are named by their scene keys too.
  EXPECT_EQ(
      ErrorOf("base: paper\nenvironment:\n  planes:\n    - name: x\n"
              "      point_in_transmitter: [0, 0, 1]\n      normal_in_transmitter: [0, 0, 1]\n"
              "      attenuation: 2\n"),
      "bad.yaml:7: environment.planes[0].attenuation: must be in [-1, 1]");
  // A list item does not inherit from the base: a key left out took the type's default, and an
  // object without polarisability_m3 (0) or a plane without attenuation (0) distorted nothing.
  EXPECT_EQ(ErrorOf("base: paper\nenvironment:\n  objects:\n    - name: desk\n"
                    "      location_in_transmitter: [0.5, 0, 0.3]\n"),
            "bad.yaml:4: environment.objects[0].polarisability_m3: missing (a list item does not "
            "inherit from the base; give every key but name)");
  EXPECT_EQ(
      ErrorOf("base: paper\nenvironment:\n  planes:\n    - name: wall\n"
              "      point_in_transmitter: [0, 0, 1]\n      normal_in_transmitter: [0, 0, 1]\n"
              "    - point_in_transmitter: [0, 2, 0]\n      normal_in_transmitter: [0, 1, 0]\n"
              "      attenuation: 0.5\n"),
      "bad.yaml:4: environment.planes[0].attenuation: missing (a list item does not inherit "
      "from the base; give every key but name)");
  EXPECT_EQ(ErrorOf("base: paper\nenvironment:\n  field_constant: 0\n"),
            "bad.yaml:3: environment.field_constant: must be a positive number");
  EXPECT_NE(ErrorOf("tracker: [\n").find("bad.yaml:"), std::string::npos);
}

TEST(ParseScene, EmptyScenesPdfsAndNonMappingsSayWhatTheFileIs) {
  // An empty file and a comment-only one said "a scene must be a YAML mapping"; a PDF gave
  // "YAML syntax error: unknown escape character" and a raw byte.
  EXPECT_EQ(ErrorOf(""),
            "bad.yaml:1: the scene has no keys (an empty file, or comments only); start from a "
            "preset with 'base: paper' (docs/scene.md)");
  EXPECT_EQ(ErrorOf("# nothing yet\n\n"), ErrorOf(""));
  EXPECT_EQ(ErrorOf("%PDF-1.7\n%\xe2\xe3\xcf\xd3\n1 0 obj\n<< /Type /Catalog >>\n\x01\x02"),
            "bad.yaml:1: a PDF document (the file starts with %PDF-), not a scene file (YAML "
            "text, docs/scene.md)");
  EXPECT_EQ(ErrorOf("# a list\n- base: paper\n"),
            "bad.yaml:2: a scene must be a YAML mapping (key: value lines), not a list");
  EXPECT_EQ(ErrorOf("paper\n"),
            "bad.yaml:1: a scene must be a YAML mapping (key: value lines), not a single value");
}

TEST(ParseScene, RepeatedKeysAreErrors) {
  // yaml-cpp looks up the first of two equal keys: an override appended below the original was
  // silently ignored (signal_noise stayed 0.1).
  EXPECT_EQ(ErrorOf("base: paper\ntracker:\n  signal_noise: 0.1\n  signal_noise: 0.2\n"),
            "bad.yaml:4: tracker.signal_noise: duplicate key (each key may appear once)");
  EXPECT_EQ(ErrorOf("base: paper\nseed: 1\nname: a\nseed: 2\n"),
            "bad.yaml:4: seed: duplicate key (each key may appear once)");
  EXPECT_EQ(ErrorOf("base: paper\nhidden:\n  sensor_offset:\n    receiver_from_body:\n"
                    "      translation: [0, 0, 0]\n      translation: [0, 0, 1]\n"),
            "bad.yaml:6: hidden.sensor_offset.receiver_from_body.translation: duplicate key (each "
            "key may appear once)");
  // A key that is not a name is a user error naming the file and line (it escaped as yaml-cpp's
  // "bad conversion", without either).
  EXPECT_EQ(ErrorOf("base: paper\n? [a, b]\n: 1\n"), "bad.yaml:2: (top level): keys must be names");
}

TEST(ParseScene, OneDocumentOnly) {
  // The keys after a "---" line (a second YAML document) were ignored: seed stayed 20010313 and
  // signal_noise 0.001, and the capture was written without a word.
  EXPECT_EQ(ErrorOf("base: paper\nname: a\n---\nseed: 5\ntracker:\n  signal_noise: 0\n"),
            "bad.yaml:4: a scene is one YAML document; a second one starts here (after a '---' "
            "line), its keys would be ignored");
  // A leading or trailing document marker is no second document.
  EXPECT_EQ(ErrorOf("---\nbase: paper\nseed: 5\n---\n# the end\n"), "");
  EXPECT_EQ(ParseScene("---\nbase: paper\nseed: 5\n...\n", "ok.yaml").seed, 5u);
}

TEST(ParseScene, CalibrationGridMustAvoidTheSingularPoints) {
  // A grid through the transmitter: the station there has no signal, and the capture got an
  // unconverged identity pose at the origin as its report.
  EXPECT_EQ(
      ErrorOf("base: paper\ncapture:\n  calibration:\n    origin_in_transmitter: [0, 0, 0]\n"),
      "bad.yaml:4: capture.calibration.origin_in_transmitter: the grid node at [0, 0, 0] is "
      "within 1 mm of the transmitter, where the field is singular");
  // A node (index (2, 2, 2)) on the paper room's workbench frame at [0.5, 0, 0.35].
  const std::string on_object = ErrorOf(
      "base: paper\ncapture:\n  calibration:\n    origin_in_transmitter: [0.2, -0.3, 0.05]\n");
  EXPECT_EQ(
      on_object.rfind("bad.yaml:4: capture.calibration.origin_in_transmitter: the grid node at "
                      "[0.5, 0, 0.35",
                      0),
      0u)
      << on_object;
  EXPECT_NE(on_object.find("within 1 mm of object 'workbench_frame'"), std::string::npos)
      << on_object;
  // Near is fine: the field is finite 2 mm away (the node [0, 0, -0.002], in the hemisphere).
  EXPECT_EQ(ErrorOf("base: paper\ncapture:\n  calibration:\n"
                    "    origin_in_transmitter: [-0.75, -0.6, -0.452]\n"),
            "");
  // The hidden object counts once it is enabled.
  Scene scene = LoadScene("paper");
  scene.capture.calibration.origin_in_transmitter =
      scene.hidden.object.location_in_transmitter - Eigen::Vector3d(0.15, 0.3, 0.45);
  EXPECT_NO_THROW(scene.Check());
  scene.hidden.Enable("ferromagnetic_object");
  EXPECT_THROW(scene.Check(), std::invalid_argument);
}

TEST(ParseScene, CaptureMustStayOnTheTransmitterSideOfEveryPlane) {
  // The floor 0.8 m "below" with z taken as up: the plane is at the grid's top layer and the
  // validation box reaches past it, where a conducting plane screens the field instead of adding
  // its image. The capture was simulated with the image model there all the same.
  EXPECT_EQ(
      ErrorOf("base: paper\nenvironment:\n  planes:\n    - name: floor\n"
              "      point_in_transmitter: [0, 0, -0.8]\n      normal_in_transmitter: [0, 0, 1]\n"
              "      attenuation: 0.27\n"),
      "bad.yaml: capture.calibration: the capture reaches [-0.825, -0.675, -0.8], on or "
      "beyond plane 'floor' (environment.planes[0]) from the transmitter, where its image "
      "model does not hold");
  const std::string validation = ErrorOf(
      "base: paper\nenvironment:\n  planes:\n    - name: floor\n"
      "      point_in_transmitter: [0, 0, -0.85]\n      normal_in_transmitter: [0, 0, -2]\n"
      "      attenuation: 0.27\n");
  EXPECT_EQ(validation.rfind(
                "bad.yaml: capture.validation: the capture reaches [-0.9, -0.75, -0.875]", 0),
            0u)
      << validation;
  // The stream's box counts, and the registration box; a box on the plane's far side is named.
  const std::string stream =
      ErrorOf("base: paper\ncapture:\n  stream:\n    amplitude_m: [0.6, 2.5, 0.2]\n");
  EXPECT_EQ(
      stream.rfind(
          "bad.yaml:4: capture.stream: the capture reaches [-0.6, -2.5, -0.6000000000000001], "
          "on or beyond plane 'metal_door'",
          0),
      0u)
      << stream;
  EXPECT_NE(
      ErrorOf("base: paper\ncapture:\n  registration:\n    min_in_transmitter: [-0.2, -0.2, 0.7]\n"
              "    max_in_transmitter: [0.2, 0.2, 0.9]\n")
          .find("capture.registration: the capture reaches"),
      std::string::npos);
  // With no stations in a box, the box is not visited.
  EXPECT_EQ(
      ErrorOf(
          "base: paper\ncapture:\n  registration:\n    count: 0\n"
          "    min_in_transmitter: [-0.2, -0.2, 0.7]\n    max_in_transmitter: [0.2, 0.2, 0.9]\n"),
      "");
}

TEST(ParseScene, CaptureMustLieInTheTrackerHemisphere) {
  // The Fastrak's power-up hemisphere (+x) on the paper's workspace above a z-down transmitter:
  // half the stations were reported at their mirror image -p (validation position error mean 836
  // mm instead of 43 mm), silently.
  EXPECT_EQ(ErrorOf("base: paper\ntracker:\n  hemisphere_in_transmitter: [1, 0, 0]\n"),
            "bad.yaml: capture.calibration: the capture reaches [-0.825, -0.675, -0.8], outside "
            "the tracker's hemisphere (tracker.hemisphere_in_transmitter [1, 0, 0]: positions p "
            "with p . h > 0), where it reports the mirror image -p");
  // A box drawn across the hemisphere plane is named with the line of its key.
  EXPECT_EQ(
      ErrorOf("base: paper\ncapture:\n  validation:\n    max_in_transmitter: [0.9, 0.75, 0.1]\n")
          .rfind("bad.yaml:4: capture.validation: the capture reaches [-0.9, -0.75, 0.1], "
                 "outside the tracker's hemisphere",
                 0),
      0u);
  // Not the stream's box: the emulator walks it, and a device outside its hemisphere reports the
  // mirror image as a real one does.
  EXPECT_EQ(ErrorOf("base: paper\ncapture:\n  stream:\n    center_in_transmitter: [0, 0, -0.1]\n"),
            "");
  // A tilted hemisphere that still holds the whole capture is fine.
  EXPECT_EQ(ErrorOf("base: paper\ntracker:\n  hemisphere_in_transmitter: [0.1, 0, -1]\n"), "");
}

TEST(ParseScene, CaptureSizeIsBounded) {
  // An extra zero in each count (8e9 stations) ran out of memory after minutes; a stream of 1e300 s
  // looped without end (its int sample index overflowed).
  EXPECT_EQ(ErrorOf("base: paper\ncapture:\n  calibration:\n    counts: [2000, 2000, 2000]\n"),
            "bad.yaml:4: capture.calibration.counts: the capture would have 8000000140 static "
            "stations, more than 1000000");
  EXPECT_EQ(ErrorOf("base: paper\ncapture:\n  validation:\n    count: 2000000\n"),
            "bad.yaml:4: capture.validation.count: the capture would have 2000500 static "
            "stations, more than 1000000");
  EXPECT_EQ(ErrorOf("base: paper\ncapture:\n  stream:\n    duration_s: 1e300\n"),
            "bad.yaml:4: capture.stream.duration_s: the streams would have 1.2e+302 samples, more "
            "than 10000000");
  // A day of streams at the paper's 120 Hz is not refused.
  EXPECT_EQ(ErrorOf("base: paper\ncapture:\n  stream:\n    duration_s: 80000\n"), "");
}

TEST(LoadScene, IdealPresetHasNoDistortion) {
  const Scene ideal = LoadScene("ideal");
  const Scene paper = LoadScene("paper");
  EXPECT_EQ(ideal.name, "ideal");
  EXPECT_TRUE(ideal.environment.planes.empty());
  EXPECT_TRUE(ideal.environment.objects.empty());
  EXPECT_EQ(ideal.tracker.signal_noise, paper.tracker.signal_noise);
  EXPECT_EQ(ideal.capture.validation.count, paper.capture.validation.count);
}

TEST(LoadScene, FileAndUnknownName) {
  const auto dir = testing::MakeTempDir("scene_test");
  const auto path = dir / "mine.yaml";
  std::ofstream(path) << "base: paper\nseed: 9\n";
  EXPECT_EQ(LoadScene(path.string()).seed, 9u);
  EXPECT_THROW(LoadScene("no_such_preset"), std::invalid_argument);
}

TEST(LoadScene, AFolderAPipeAndAMissingFileAreNamedAsSuch) {
  auto error_of = [](const std::string& arg) {
    try {
      LoadScene(arg);
    } catch (const std::invalid_argument& e) {
      return std::string(e.what());
    }
    return std::string();
  };
  // A folder was "neither a scene file nor a preset"; a missing file gave no reason.
  const auto dir = testing::MakeTempDir("scene_test");
  EXPECT_EQ(error_of(dir.string()), dir.string() + ": is a folder, not a scene file");
  EXPECT_EQ(error_of((dir / "mine.yaml").string()),
            "scene '" + (dir / "mine.yaml").string() +
                "' is neither a scene file (No such file or directory) nor a preset (presets: "
                "ideal, paper)");
  // A pipe (`--scene <(generate_scene)`) is read as a file is.
  const auto fifo = dir / "scene.fifo";
  ASSERT_EQ(::mkfifo(fifo.c_str(), 0600), 0);
  std::thread writer([&] { std::ofstream(fifo) << "base: paper\nseed: 11\n"; });
  Scene scene;
  EXPECT_NO_THROW(scene = LoadScene(fifo.string()));
  // Should the pipe not have been read, the writer waits for a reader: release it.
  const int reader = ::open(fifo.c_str(), O_RDONLY | O_NONBLOCK);
  writer.join();
  if (reader >= 0) ::close(reader);
  EXPECT_EQ(scene.seed, 11u);
}

TEST(HiddenEffects, EnableByName) {
  HiddenEffects h;
  for (const auto& name : HiddenEffects::Names()) h.Enable(name);
  EXPECT_EQ(h.EnabledNames(), HiddenEffects::Names());
  EXPECT_THROW(h.Enable("latency"), std::invalid_argument);
}

}  // namespace
}  // namespace trackcal::sim

namespace trackcal::sim {
namespace {

TEST(HiddenEffects, DefaultsMatchThePaperPresetAndAreVisible) {
  // A scene without a hidden section still gets effects of a plausible size.
  const HiddenEffects defaults;
  const Scene paper = LoadScene("paper");
  Scene with_defaults;
  with_defaults.hidden = defaults;
  Scene with_paper;
  with_paper.hidden = paper.hidden;
  EXPECT_EQ(SceneToJson(with_defaults)["hidden"].dump(), SceneToJson(with_paper)["hidden"].dump());
  EXPECT_GT(defaults.receiver_from_body.translation.norm(), 0.01);
  EXPECT_GT((defaults.receiver_gain_matrix - Eigen::Matrix3d::Identity()).norm(), 0.01);
  EXPECT_GT(defaults.flip_count, 0);
  EXPECT_NE(defaults.reference_minus_tracker_s, 0.0);
}

}  // namespace
}  // namespace trackcal::sim
