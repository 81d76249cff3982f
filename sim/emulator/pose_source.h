// Where the emulator's stations are: a PoseSource gives the true pose of each receiver over time
// (static, scripted trajectory, or moved through the control socket), and a MeasurementModel turns
// a true pose into what the tracker reports (perfect by default; the physics simulator plugs in
// here: reported = tracker solver applied to the distorted field at the true pose, plus noise).
//
// Poses are transmitter_from_receiver in metres; time is seconds since the emulator started.
// Stations are numbered 1..4 like the Fastrak's.

#pragma once

#include <array>
#include <filesystem>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <vector>

#include "core/pose.h"
#include "sim/emulator/fastrak_device.h"
#include "sim/random.h"

namespace trackcal::emulator {

class PoseSource {
 public:
  virtual ~PoseSource() = default;
  // Ground-truth pose of the receiver on `station` at time t_s.
  virtual Rigid3d TruePose(int station, double t_s) = 0;
  // Stylus switch on `station` at time t_s.
  virtual bool StylusButton(int /*station*/, double /*t_s*/) { return false; }
};

class MeasurementModel {
 public:
  virtual ~MeasurementModel() = default;
  // What the tracker reports for a receiver truly at `true_pose` (transmitter_from_receiver).
  virtual Rigid3d Reported(int station, const Rigid3d& true_pose, double t_s) = 0;
};

// An undistorted, noise-free tracker: reports the true pose.
class PerfectMeasurement final : public MeasurementModel {
 public:
  Rigid3d Reported(int /*station*/, const Rigid3d& true_pose, double /*t_s*/) override {
    return true_pose;
  }
};

// Another model's report plus white noise: isotropic Gaussian position noise and a rotation by a
// Gaussian rotation vector (per axis std), from the named stream "emulator_measurement_noise" of
// sim/random.h, so a seed gives the same numbers with every compiler and standard library.
class NoisyMeasurement final : public MeasurementModel {
 public:
  // `base` null = PerfectMeasurement. Throws std::invalid_argument for negative or non-finite std.
  NoisyMeasurement(std::unique_ptr<MeasurementModel> base, double position_std_m,
                   double orientation_std_rad, uint64_t seed);
  Rigid3d Reported(int station, const Rigid3d& true_pose, double t_s) override;

 private:
  std::unique_ptr<MeasurementModel> base_;
  double position_std_m_;
  double orientation_std_rad_;
  sim::Rng rng_;
};

// Every station at a fixed pose.
class StaticPoseSource final : public PoseSource {
 public:
  // poses[i] is station i + 1 (1 to 4 poses).
  explicit StaticPoseSource(std::vector<Rigid3d> poses);
  Rigid3d TruePose(int station, double t_s) override;

 private:
  std::vector<Rigid3d> poses_;
};

// One keyframe of a scripted trajectory.
struct TrajectoryKeyframe {
  double t_s = 0;
  Rigid3d transmitter_from_receiver;
  bool stylus_button = false;
};

// Keyframes per station, interpolated linearly in position and by slerp in rotation; held constant
// before the first and after the last keyframe, or repeated with `loop`.
//
// CSV file format (docs/emulator.md): a header naming the columns, read by name in any order:
//   t,station,x,y,z,qw,qx,qy,qz[,button]
// t in seconds, station 1..4, position in metres, quaternion scalar first (normalised on reading),
// button 0/1 (optional, held until the next keyframe). '#' starts a comment line; blank lines are
// skipped. Times of one station must increase strictly.
class TrajectoryPoseSource final : public PoseSource {
 public:
  // keyframes[i] is station i + 1; each station needs at least one keyframe.
  TrajectoryPoseSource(std::vector<std::vector<TrajectoryKeyframe>> keyframes, bool loop);
  // Throws std::invalid_argument naming the file, line and column of the first error.
  static std::unique_ptr<TrajectoryPoseSource> ReadCsv(const std::filesystem::path& path,
                                                       bool loop);

  Rigid3d TruePose(int station, double t_s) override;
  bool StylusButton(int station, double t_s) override;
  int num_stations() const { return static_cast<int>(keyframes_.size()); }

 private:
  double LocalTime(int station, double t_s) const;
  std::vector<std::vector<TrajectoryKeyframe>> keyframes_;
  bool loop_ = false;
};

// Wraps a base source; the control socket moves stations (the override holds until released) and
// presses stylus buttons. Thread-safe.
class ControlledPoseSource final : public PoseSource {
 public:
  explicit ControlledPoseSource(std::unique_ptr<PoseSource> base);
  void Move(int station, const Rigid3d& transmitter_from_receiver);
  void Release(int station);
  void SetButton(int station, bool pressed);
  Rigid3d TruePose(int station, double t_s) override;
  bool StylusButton(int station, double t_s) override;

 private:
  std::unique_ptr<PoseSource> base_;
  std::mutex mutex_;
  std::array<std::optional<Rigid3d>, kMaxStations> moved_;
  std::array<std::optional<bool>, kMaxStations> button_;
};

// Samples what the device measures: the model applied to the source's true pose.
StationMeasurement Measure(PoseSource& source, MeasurementModel& model, int station, double t_s);

}  // namespace trackcal::emulator
