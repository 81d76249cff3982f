// The simulator: a scene in, a capture out, bit for bit reproducible from the scene (and its seed).
//
//   Simulator sim(LoadScene("paper"));           // hidden effects enabled in the scene apply
//   SimulatedCapture capture = sim.Generate();
//   WriteCaptureFolder(sim, capture, "out/");    // poses.csv, markers.csv, ..., truth.json
//
// For the emulator and other live users, TrackerModel answers "what does the tracker report for a
// receiver at this true pose", with or without noise, and Simulator::TruePoseAt gives the smooth
// trajectory the streams follow, one per receiver. An emulator station at time t:
//
//   const Simulator sim(LoadScene("paper"));
//   Rng noise(sim.scene().seed, "emulator");         // one stream per user; not thread-safe
//   const Rigid3d truth = sim.TruePoseAt(t, station - 1);
//   const Rigid3d reported = sim.tracker().Report(truth, /*samples=*/1, &noise)
//                                .transmitter_from_receiver;
//
// TrackerModel and Simulator are immutable after construction and safe to share between threads.

#pragma once

#include <filesystem>
#include <map>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "core/capture.h"
#include "core/error_statistics.h"
#include "core/pose.h"
#include "core/field.h"
#include "sim/random.h"
#include "sim/scene.h"
#include "core/tracker_solver.h"

namespace trackcal::sim {

// The physical tracker: true field, receiver, noise on S and the free-space solver.
class TrackerModel {
 public:
  TrackerModel(FieldModel field, const Eigen::Matrix3d& receiver_gain_matrix, double signal_noise,
               const TrackerSolverOptions& solver);

  // Noise-free signal matrix S = G R^T B(p) of a receiver at a true pose.
  Eigen::Matrix3d Signal(const Rigid3d& transmitter_from_receiver) const;

  // The tracker's report for a receiver at a true pose, averaging `samples` samples of S (noise of
  // std signal_noise / sqrt(samples) on every entry); noise-free when rng is null.
  TrackerSolution Report(const Rigid3d& transmitter_from_receiver, int samples = 1,
                         Rng* rng = nullptr) const;

  const FieldModel& field() const { return field_; }
  const Eigen::Matrix3d& receiver_gain_matrix() const { return receiver_gain_matrix_; }
  double signal_noise() const { return signal_noise_; }
  const TrackerSolverOptions& solver_options() const { return solver_; }

 private:
  FieldModel field_;
  Eigen::Matrix3d receiver_gain_matrix_;
  double signal_noise_;
  TrackerSolverOptions solver_;
};

// Uncorrected errors (|p_ref - p_rep| in mm, angle(q_ref conj(q_rep)) in deg) of one set's records.
PoseErrorSummary UncorrectedSummary(const PoseCapture& poses, const std::string& set);
// {"count", "position_mm": {mean, std, max, rms, median, p95}, "orientation_deg": {...}}.
nlohmann::json SummaryToJson(const PoseErrorSummary& summary);

// What the simulator knows about one static station.
struct StationTruth {
  int station = 0;
  std::string set;
  double time = 0.0;
  Rigid3d transmitter_from_receiver;  // true receiver coil pose
  Rigid3d transmitter_from_body;      // true reference body pose (= coil without sensor offset)
  Rigid3d reported_noise_free;        // what the tracker reports without noise (flips included)
  bool hemisphere_flipped = false;    // reported at -p by the hemisphere_flips effect
};

struct SimulatedCapture {
  PoseCapture poses;             // calib, valid and reg stations
  // Every static station (calib, valid, reg), as a session that tracks the marker body at each
  // station records them; the `set` of a station is in poses (and stations).
  MarkerCapture markers;         // visible markers, optical frame
  TrackerCapture tracker;        // the tracker's averaged reading (the same as poses' rep_*)
  TrackerStream tracker_stream;  // empty when the scene has no stream
  ReferenceStream reference_stream;
  std::vector<StationTruth> stations;  // truth per static station, same order as poses
  // Per set ("calib", "valid", "reg"): errors before correction, and the noise floor, the errors a
  // perfect model of the scene would leave (tracker and reference noise only). A fit cannot beat it.
  std::map<std::string, PoseErrorSummary> uncorrected;
  std::map<std::string, PoseErrorSummary> noise_floor;
  nlohmann::json truth;                // truth.json: scene, effective physics, stats, noise floor

  // The rows of markers / tracker whose station is in `set` ("reg": the registration stations).
  MarkerCapture MarkersOfSet(const std::string& set) const;
  TrackerCapture TrackerOfSet(const std::string& set) const;
};

class Simulator {
 public:
  // Checks the scene (throws std::invalid_argument naming the field) and applies its enabled
  // hidden effects to the physics.
  explicit Simulator(Scene scene);

  const Scene& scene() const { return scene_; }
  // The physical tracker with hidden effects applied.
  const TrackerModel& tracker() const { return tracker_; }
  // Reference body pose relative to the receiver coil (identity unless sensor_offset is on).
  const Rigid3d& receiver_from_body() const { return receiver_from_body_; }

  // True receiver pose on a smooth trajectory at time t (tracker clock) [s]. Receiver 0 follows
  // the trajectory of the capture's streams; receivers 1..kMaxReceivers-1 (the other stations of
  // a Fastrak) follow their own seeded trajectories of the same amplitudes around the same centre.
  static constexpr int kMaxReceivers = 4;
  Rigid3d TruePoseAt(double time_s, int receiver = 0) const;

  // Generates every file of a capture from the scene.
  SimulatedCapture Generate() const;

 private:
  Scene scene_;
  TrackerModel tracker_;
  Rigid3d receiver_from_body_;
  struct Trajectory {
    Eigen::Vector3d phase;             // per-axis position phase [rad]
    Eigen::Vector3d rotation_phase;    // per-axis rotation phase [rad]
    Eigen::Quaterniond base_rotation;  // orientation the rotation sinusoids perturb
  };
  std::vector<Trajectory> trajectories_;  // one per receiver
};

// Writes a capture folder: poses.csv, markers.csv, tracker.csv, tracker_stream.csv,
// reference_stream.csv (if the scene has streams), truth.json and scene.yaml (the effective scene,
// which regenerates the same capture). The folder is assembled under a temporary name and renamed
// into place; throws std::runtime_error if `dir` exists and is not empty.
void WriteCaptureFolder(const Simulator& simulator, const SimulatedCapture& capture,
                        const std::filesystem::path& dir);

}  // namespace trackcal::sim
