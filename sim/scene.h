// A scene: everything the simulator needs to produce a capture, bit for bit.
//
// environment (transmitter and distortion sources) + tracker (receiver, noise, solver hemisphere) +
// reference (optical system, marker body, noise) + capture protocol (calibration grid, validation
// and registration stations, streams) + hidden effects (physics switched on top, for tests that
// need data whose cause the base model lacks) + seed. Scene files are YAML, documented in
// docs/scene.md; presets (sim/scenes/*.yaml) are compiled in and selected by name ("paper").

#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <filesystem>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "core/pose.h"
#include "core/field.h"

namespace trackcal::sim {

struct TrackerConfig {
  // G in S = G R^T B: receiver coil gains (diagonal) and non-orthogonality (off-diagonal).
  Eigen::Matrix3d receiver_gain_matrix = Eigen::Matrix3d::Identity();
  double signal_noise = 0.0;      // std of each entry of S, one sample [field units; k = 1 at 1 m]
  int samples_per_station = 120;  // samples averaged per static station (noise / sqrt(N))
  Eigen::Vector3d hemisphere_in_transmitter = Eigen::Vector3d::UnitX();  // Fastrak H command
  int sensor = 1;                 // station number written in the `sensor` column
  double update_rate_hz = 120.0;  // stream sample rate
  void Check() const;             // throws naming the field
};

struct ReferenceConfig {
  double position_noise_m = 0.0;       // optical receiver position noise, per axis, one sample
  double orientation_noise_rad = 0.0;  // optical orientation noise, per axis, one sample
  double marker_noise_m = 0.0;         // marker position noise, per axis, one sample
  int samples_per_station = 100;       // samples averaged per static station
  double update_rate_hz = 100.0;       // stream sample rate
  Rigid3d optical_from_transmitter;    // pose of the transmitter in the optical frame
  // Marker positions in the reference body frame; default: the paper's six, 6 cm along +-x, y, z.
  std::vector<Eigen::Vector3d> markers_in_body = {{0.06, 0, 0},  {-0.06, 0, 0}, {0, 0.06, 0},
                                                  {0, -0.06, 0}, {0, 0, 0.06},  {0, 0, -0.06}};
  double visibility_cos_min = 0.0;  // marker seen when cos(its outward axis, line to camera) > this
  void Check() const;
};

struct CalibrationGrid {
  Eigen::Vector3d origin_in_transmitter = Eigen::Vector3d::Zero();  // first grid node [m]
  Eigen::Vector3i counts = Eigen::Vector3i(12, 10, 4);              // nodes along x, y, z
  double spacing_m = 0.15;                                          // node spacing
};

struct RandomStations {
  int count = 0;                                                 // number of stations
  Eigen::Vector3d min_in_transmitter = Eigen::Vector3d::Zero();  // box, uniform positions [m]
  Eigen::Vector3d max_in_transmitter = Eigen::Vector3d::Zero();
};

struct StreamConfig {
  double duration_s = 0.0;                                          // 0 disables the streams
  Eigen::Vector3d center_in_transmitter = Eigen::Vector3d::Zero();  // trajectory centre [m]
  Eigen::Vector3d amplitude_m = Eigen::Vector3d::Zero();            // sinusoid amplitude per axis
  Eigen::Vector3d period_s = Eigen::Vector3d(7.0, 5.0, 11.0);       // sinusoid period per axis
  double rotation_amplitude_rad = 0.0;  // amplitude of each axis of the rotation vector
  double rotation_period_s = 6.0;       // period of the x rotation sinusoid (y: 1.37x, z: 0.81x)
  // Narrows the position sinusoids so the path stays inside the box [min, max] (transmitter
  // frame): per axis the part of [center - amplitude, center + amplitude] inside the box, or the
  // box's whole extent when the two do not overlap. Throws std::invalid_argument (naming `what`
  // and the field) for a non-finite or empty box.
  void KeepWithin(const Eigen::Vector3d& min_in_transmitter,
                  const Eigen::Vector3d& max_in_transmitter, const std::string& what);
};

struct CaptureProtocol {
  CalibrationGrid calibration;    // visited in snake order
  RandomStations validation;      // random positions and orientations
  RandomStations registration;    // near the transmitter, for the optical registration (markers)
  double station_period_s = 5.0;  // time between static stations
  StreamConfig stream;            // dynamic capture
  void Check() const;
};

// Physics switched on top of a scene; names are those of the --hidden option. The defaults are
// effects of a plausible size (the paper preset uses the same), so `--hidden NAME` on any scene
// produces a visible effect.
struct HiddenEffects {
  // "sensor_offset": the optical body is not at the receiver coil.
  bool sensor_offset = false;
  Rigid3d receiver_from_body = DefaultReceiverFromBody();
  // "receiver_gains": receiver coil gains and non-orthogonality G (replaces the tracker's G).
  bool receiver_gains = false;
  Eigen::Matrix3d receiver_gain_matrix = DefaultReceiverGainMatrix();
  // "ferromagnetic_object": an extra induced dipole near the workspace.
  bool ferromagnetic_object = false;
  InducedDipole object = {"steel_toolbox", Eigen::Vector3d(0.6, 0.95, -0.5), 0.002};
  // "finite_transmitter_coils": octupole term of each transmitter coil (added to the
  // environment's).
  bool finite_transmitter_coils = false;
  Eigen::Vector3d octupole_m2 = Eigen::Vector3d(-0.000675, -0.0006, -0.00075);
  // "clock_offset": reference stream time = tracker stream time + offset + drift * (tracker stream
  // time), the reference clock running (1 + drift) times as fast as the tracker's (1e-4: 100 ppm).
  bool clock_offset = false;
  double reference_minus_tracker_s = 0.037;
  double reference_clock_drift = 0.0;
  // "hemisphere_flips": this many calibration/validation stations are reported at -p.
  bool hemisphere_flips = false;
  int flip_count = 3;

  // Enables an effect by name; throws std::invalid_argument listing the names if unknown.
  void Enable(const std::string& name);
  static const std::vector<std::string>& Names();
  std::vector<std::string> EnabledNames() const;
  void Check() const;

  static Rigid3d DefaultReceiverFromBody();
  static Eigen::Matrix3d DefaultReceiverGainMatrix();
};

struct Scene {
  std::string name;          // label written to truth.json
  uint64_t seed = 20010313;  // master seed of every random stream
  FieldModel environment;    // transmitter and distortion sources
  TrackerConfig tracker;
  ReferenceConfig reference;
  CaptureProtocol capture;
  HiddenEffects hidden;
  void Check() const;  // throws std::invalid_argument naming the field
};

// Names of the compiled-in presets ("paper", ...).
std::vector<std::string> PresetNames();
// YAML text of a preset; throws std::invalid_argument listing the presets if unknown.
const std::string& PresetYaml(const std::string& name);

// Parses a scene from YAML text; `source` names it in errors ("scene.yaml:12: tracker.signal_noise:
// expected a number"). Keys absent from the text keep the value of `base` (or of a preset named by
// a top-level `base:` key); unknown keys are errors.
Scene ParseScene(const std::string& yaml_text, const std::string& source, const Scene& base = {});
// A preset by name, or a scene file by path (a path that exists wins).
Scene LoadScene(const std::string& preset_or_path);
// The scene as YAML that ParseScene reads back to the same scene, bit for bit.
std::string SceneToYaml(const Scene& scene);
// Every field of the scene as JSON (the same keys as the YAML), for truth.json.
nlohmann::json SceneToJson(const Scene& scene);

}  // namespace trackcal::sim
