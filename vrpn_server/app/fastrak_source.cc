#include "vrpn_server/app/fastrak_source.h"

#include <chrono>
#include <vector>

namespace trackcal::vrpn {
namespace {

Timestamp ToTimestamp(std::chrono::system_clock::time_point t) {
  const auto us =
      std::chrono::duration_cast<std::chrono::microseconds>(t.time_since_epoch()).count();
  return Timestamp{static_cast<std::uint32_t>(us / 1000000), static_cast<std::uint32_t>(us % 1000000)};
}

TextSeverity ToTextSeverity(fastrak::Severity s) {
  switch (s) {
    case fastrak::Severity::kInfo:
      return TextSeverity::kNormal;
    case fastrak::Severity::kWarning:
      return TextSeverity::kWarning;
    case fastrak::Severity::kError:
      return TextSeverity::kError;
  }
  return TextSeverity::kError;
}

class FastrakSource : public ReportSource {
 public:
  explicit FastrakSource(fastrak::FastrakOptions options) : options_(std::move(options)) {
    options_.Check();
  }
  void Start(SourceCallbacks callbacks) override {
    callbacks_ = std::move(callbacks);
    fastrak::FastrakDriver::Callbacks cb;
    if (callbacks_.on_poses) {
      // The records of one serial read go out as one batch (one send per client).
      cb.on_reports = [this](std::span<const fastrak::FastrakReport> reports) {
        batch_.clear();
        for (const fastrak::FastrakReport& r : reports) {
          batch_.push_back(SensorReport{r.sensor, Rigid3d(r.rotation, r.position_m), ToTimestamp(r.time)});
        }
        callbacks_.on_poses(batch_);
      };
    } else {
      cb.on_report = [this](const fastrak::FastrakReport& r) {
        callbacks_.on_pose(r.sensor, Rigid3d(r.rotation, r.position_m), ToTimestamp(r.time));
      };
    }
    cb.on_button = [this](int sensor, bool pressed, std::chrono::system_clock::time_point time) {
      if (callbacks_.on_button) callbacks_.on_button(sensor, pressed, ToTimestamp(time));
    };
    cb.on_message = [this](fastrak::Severity severity, const std::string& text) {
      if (callbacks_.on_text) callbacks_.on_text(ToTextSeverity(severity), text);
    };
    driver_ = std::make_unique<fastrak::FastrakDriver>(options_, std::move(cb));
    driver_->Start();
  }
  void SetRealtimePriority(int priority) override {
    options_.realtime_priority = priority;
    options_.Check();
  }
  void Stop() override {
    if (driver_) driver_->Stop();
  }
  std::string Describe() const override {
    return "Fastrak on " + options_.port + " at " + std::to_string(options_.baud) + " baud";
  }

 private:
  fastrak::FastrakOptions options_;
  SourceCallbacks callbacks_;
  std::unique_ptr<fastrak::FastrakDriver> driver_;
  std::vector<SensorReport> batch_;  // driver thread only
};

}  // namespace

std::unique_ptr<ReportSource> MakeFastrakSource(fastrak::FastrakOptions options) {
  return std::make_unique<FastrakSource>(std::move(options));
}

}  // namespace trackcal::vrpn
