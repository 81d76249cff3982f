// The physics simulator (sim/simulator.h) behind the emulator: receivers follow the scene's smooth
// trajectories, and the device reports what the tracker's own free-space solver makes of the
// distorted field at the true pose, with the scene's signal noise (one sample of S per record, as a
// Fastrak measures each record once).

#pragma once

#include <memory>

#include "sim/emulator/pose_source.h"
#include "sim/random.h"
#include "sim/simulator.h"

namespace trackcal::emulator {

// Station n follows the simulator's receiver n - 1 trajectory (TruePoseAt).
class SceneTrajectorySource final : public PoseSource {
 public:
  explicit SceneTrajectorySource(std::shared_ptr<const sim::Simulator> simulator);
  Rigid3d TruePose(int station, double t_s) override;

 private:
  std::shared_ptr<const sim::Simulator> simulator_;
};

// reported = the scene tracker's solver applied to the signal at the true pose (+ signal noise).
class SimulatedTracker final : public MeasurementModel {
 public:
  // `seed` seeds the noise stream (named "emulator_signal_noise"); `add_noise` false gives the
  // noise-free report (what the tracker reports on average).
  SimulatedTracker(std::shared_ptr<const sim::Simulator> simulator, uint64_t seed,
                   bool add_noise = true);
  Rigid3d Reported(int station, const Rigid3d& true_pose, double t_s) override;

 private:
  std::shared_ptr<const sim::Simulator> simulator_;
  sim::Rng rng_;
  bool add_noise_;
};

}  // namespace trackcal::emulator
