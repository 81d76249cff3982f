#include "vrpn_server/app/calibration_corrector.h"

#include <stdexcept>

#include "core/calibration_file.h"
#include "core/capture.h"

namespace trackcal::vrpn {
namespace {

class CalibrationCorrector : public PoseCorrector {
 public:
  CalibrationCorrector(Calibration calibration, std::string description)
      : calibration_(std::move(calibration)), description_(std::move(description)) {}
  Rigid3d Correct(const Rigid3d& reported) const override { return calibration_.Apply(reported).pose; }
  CorrectionResult CorrectWithFlag(const Rigid3d& reported) const override {
    const CorrectedPose c = calibration_.Apply(reported);
    return {c.pose, c.extrapolated, c.status};
  }
  std::string Describe() const override { return description_; }
  int FittedSensor() const override { return calibration_.sensor; }
  std::optional<std::pair<Eigen::Vector3d, Eigen::Vector3d>> FittedBox() const override {
    return std::make_pair(calibration_.volume().min, calibration_.volume().max);
  }

 private:
  Calibration calibration_;
  std::string description_;
};

}  // namespace

std::shared_ptr<const PoseCorrector> LoadCalibrationCorrector(
    const std::filesystem::path& path, const std::optional<std::string>& outside,
    const std::optional<double>& fade_distance) {
  Calibration calibration = ReadCalibrationFile(path);
  if (outside || fade_distance) {
    CalibratedVolume volume = calibration.volume();
    if (outside) volume.extrapolation = ExtrapolationPolicyFromName(*outside);
    if (fade_distance) volume.fade_distance = *fade_distance;
    try {
      volume.Check();  // fade needs a positive fade_distance (the file's, or the override)
    } catch (const std::invalid_argument& e) {
      throw std::invalid_argument(path.string() + ": " + e.what() +
                                  (fade_distance ? "" : " (give fade_distance=<metres>)"));
    }
    if (fade_distance && volume.extrapolation != ExtrapolationPolicy::kFade) {
      // Otherwise ignored without a word: the lab believes the correction fades out.
      throw std::invalid_argument(
          path.string() + ": fade_distance=" + FormatNumber(*fade_distance) +
          " has no effect: outside the calibrated volume is '" +
          ExtrapolationPolicyName(volume.extrapolation) + "' (add outside=fade)");
    }
    calibration.chain.SetVolume(volume);
  }
  std::string terms;
  for (std::size_t i = 0; i < calibration.chain.size(); ++i) {
    if (i > 0) terms += '+';
    terms += calibration.chain.term(i).TypeName();
  }
  std::string description = path.string() + " (" + terms + ", outside the calibrated volume: " +
                            ExtrapolationPolicyName(calibration.volume().extrapolation);
  if (calibration.sensor != 0) {
    description += ", fitted for receiver " + std::to_string(calibration.sensor) +
                   " = VRPN sensor " + std::to_string(calibration.sensor - 1);
  }
  description += ")";
  return std::make_shared<CalibrationCorrector>(std::move(calibration), std::move(description));
}

}  // namespace trackcal::vrpn
