#include "vrpn_server/app/calibration_corrector.h"

#include "core/calibration_file.h"

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

 private:
  Calibration calibration_;
  std::string description_;
};

}  // namespace

std::shared_ptr<const PoseCorrector> LoadCalibrationCorrector(const std::filesystem::path& path,
                                                              const std::optional<std::string>& outside) {
  Calibration calibration = ReadCalibrationFile(path);
  if (outside) {
    CalibratedVolume volume = calibration.volume();
    volume.extrapolation = ExtrapolationPolicyFromName(*outside);
    volume.Check();  // fade needs the file's fade_distance
    calibration.chain.SetVolume(volume);
  }
  std::string terms;
  for (std::size_t i = 0; i < calibration.chain.size(); ++i) {
    if (i > 0) terms += '+';
    terms += calibration.chain.term(i).TypeName();
  }
  std::string description = path.string() + " (" + terms + ", outside the calibrated volume: " +
                            ExtrapolationPolicyName(calibration.volume().extrapolation) + ")";
  return std::make_shared<CalibrationCorrector>(std::move(calibration), std::move(description));
}

}  // namespace trackcal::vrpn
