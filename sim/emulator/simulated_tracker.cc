#include "sim/emulator/simulated_tracker.h"

#include <stdexcept>
#include <string>

namespace trackcal::emulator {

SceneTrajectorySource::SceneTrajectorySource(std::shared_ptr<const sim::Simulator> simulator)
    : simulator_(std::move(simulator)) {
  if (!simulator_) throw std::invalid_argument("SceneTrajectorySource: simulator is null");
}

Rigid3d SceneTrajectorySource::TruePose(int station, double t_s) {
  if (station < 1 || station > sim::Simulator::kMaxReceivers) {
    throw std::out_of_range("SceneTrajectorySource: no station " + std::to_string(station));
  }
  return simulator_->TruePoseAt(t_s, station - 1);
}

SimulatedTracker::SimulatedTracker(std::shared_ptr<const sim::Simulator> simulator, uint64_t seed,
                                   bool add_noise)
    : simulator_(std::move(simulator)), rng_(seed, "emulator_signal_noise"), add_noise_(add_noise) {
  if (!simulator_) throw std::invalid_argument("SimulatedTracker: simulator is null");
}

Rigid3d SimulatedTracker::Reported(int /*station*/, const Rigid3d& true_pose, double /*t_s*/) {
  return simulator_->tracker()
      .Report(true_pose, /*samples=*/1, add_noise_ ? &rng_ : nullptr)
      .transmitter_from_receiver;
}

}  // namespace trackcal::emulator
