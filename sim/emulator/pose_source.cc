#include "sim/emulator/pose_source.h"

#include <algorithm>
#include <cerrno>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <map>
#include <sstream>
#include <stdexcept>

#include "core/file_util.h"

namespace trackcal::emulator {
namespace {

void CheckStation(int station, size_t count, const char* where) {
  if (station < 1 || static_cast<size_t>(station) > count) {
    throw std::out_of_range(std::string(where) + ": no station " + std::to_string(station));
  }
}

std::string TrimCell(const std::string& s) {
  size_t b = 0, e = s.size();
  while (b < e && std::isspace(static_cast<unsigned char>(s[b]))) ++b;
  while (e > b && std::isspace(static_cast<unsigned char>(s[e - 1]))) --e;
  return s.substr(b, e - b);
}

std::vector<std::string> SplitCsvLine(const std::string& line) {
  std::vector<std::string> cells;
  std::stringstream ss(line);
  std::string cell;
  while (std::getline(ss, cell, ',')) cells.push_back(TrimCell(cell));
  if (!line.empty() && line.back() == ',') cells.push_back("");
  return cells;
}

}  // namespace

NoisyMeasurement::NoisyMeasurement(std::unique_ptr<MeasurementModel> base, double position_std_m,
                                   double orientation_std_rad, uint64_t seed)
    : base_(base ? std::move(base) : std::make_unique<PerfectMeasurement>()),
      position_std_m_(position_std_m),
      orientation_std_rad_(orientation_std_rad),
      rng_(seed, "emulator_measurement_noise") {
  if (!(position_std_m >= 0 && std::isfinite(position_std_m))) {
    throw std::invalid_argument("NoisyMeasurement.position_std_m: must be finite and >= 0");
  }
  if (!(orientation_std_rad >= 0 && std::isfinite(orientation_std_rad))) {
    throw std::invalid_argument("NoisyMeasurement.orientation_std_rad: must be finite and >= 0");
  }
}

Rigid3d NoisyMeasurement::Reported(int station, const Rigid3d& true_pose, double t_s) {
  Rigid3d reported = base_->Reported(station, true_pose, t_s);
  const Eigen::Vector3d dp = position_std_m_ * rng_.Normal3();
  const Eigen::Vector3d w = orientation_std_rad_ * rng_.Normal3();
  reported.translation += dp;
  const double angle = w.norm();
  if (angle > 0) {
    reported.rotation =
        (Eigen::Quaterniond(Eigen::AngleAxisd(angle, w / angle)) * reported.rotation).normalized();
  }
  return reported;
}

StaticPoseSource::StaticPoseSource(std::vector<Rigid3d> poses) : poses_(std::move(poses)) {
  if (poses_.empty() || poses_.size() > kMaxStations) {
    throw std::invalid_argument("StaticPoseSource: 1 to 4 station poses required");
  }
}

Rigid3d StaticPoseSource::TruePose(int station, double /*t_s*/) {
  CheckStation(station, poses_.size(), "StaticPoseSource");
  return poses_[station - 1];
}

TrajectoryPoseSource::TrajectoryPoseSource(std::vector<std::vector<TrajectoryKeyframe>> keyframes,
                                           bool loop)
    : keyframes_(std::move(keyframes)), loop_(loop) {
  if (keyframes_.empty() || keyframes_.size() > kMaxStations) {
    throw std::invalid_argument("TrajectoryPoseSource: 1 to 4 stations required");
  }
  for (size_t i = 0; i < keyframes_.size(); ++i) {
    if (keyframes_[i].empty()) {
      throw std::invalid_argument("TrajectoryPoseSource: station " + std::to_string(i + 1) +
                                  " has no keyframe");
    }
    for (size_t k = 1; k < keyframes_[i].size(); ++k) {
      if (!(keyframes_[i][k].t_s > keyframes_[i][k - 1].t_s)) {
        throw std::invalid_argument("TrajectoryPoseSource: station " + std::to_string(i + 1) +
                                    " keyframe times must increase strictly");
      }
    }
  }
}

std::unique_ptr<TrajectoryPoseSource> TrajectoryPoseSource::ReadCsv(
    const std::filesystem::path& path, bool loop) {
  std::error_code ec;
  if (std::filesystem::is_directory(path, ec)) {
    throw std::invalid_argument(path.string() + ": is a folder, not a trajectory file");
  }
  errno = 0;
  std::ifstream in(path);
  if (!in) {
    throw std::invalid_argument(path.string() +
                                ": cannot open trajectory file: " + SystemErrorText(errno));
  }
  const std::vector<std::string> required = {"t", "station", "x", "y", "z", "qw", "qx", "qy", "qz"};
  std::map<std::string, size_t> column;
  std::map<int, std::vector<TrajectoryKeyframe>> by_station;
  std::string line;
  int line_number = 0;
  bool have_header = false;
  while (std::getline(in, line)) {
    ++line_number;
    if (!line.empty() && line.back() == '\r') line.pop_back();
    const std::string trimmed = TrimCell(line);
    if (trimmed.empty() || trimmed[0] == '#') continue;
    const std::vector<std::string> cells = SplitCsvLine(line);
    const std::string where = path.string() + ":" + std::to_string(line_number);
    if (!have_header) {
      for (size_t i = 0; i < cells.size(); ++i) {
        if (!column.emplace(cells[i], i).second) {
          throw std::invalid_argument(where + ": duplicate column '" + cells[i] + "'");
        }
      }
      for (const std::string& name : required) {
        if (!column.count(name))
          throw std::invalid_argument(where + ": missing column '" + name + "'");
      }
      have_header = true;
      continue;
    }
    if (cells.size() != column.size()) {
      throw std::invalid_argument(where + ": expected " + std::to_string(column.size()) +
                                  " fields, got " + std::to_string(cells.size()));
    }
    auto number = [&](const std::string& name) {
      const std::string& cell = cells[column.at(name)];
      char* end = nullptr;
      const double v = std::strtod(cell.c_str(), &end);
      if (cell.empty() || *end != '\0' || !std::isfinite(v)) {
        throw std::invalid_argument(where + ": field '" + name + "': not a finite number: '" +
                                    cell + "'");
      }
      return v;
    };
    const double station_value = number("station");
    const int station = static_cast<int>(station_value);
    if (station_value != station || station < 1 || station > kMaxStations) {
      throw std::invalid_argument(where + ": field 'station': must be 1 to 4");
    }
    TrajectoryKeyframe k;
    k.t_s = number("t");
    k.transmitter_from_receiver.translation =
        Eigen::Vector3d(number("x"), number("y"), number("z"));
    Eigen::Quaterniond q =
        QuaternionFromWxyz(number("qw"), number("qx"), number("qy"), number("qz"));
    if (q.norm() < 1e-9) throw std::invalid_argument(where + ": fields 'qw..qz': zero quaternion");
    k.transmitter_from_receiver.rotation = q.normalized();
    if (column.count("button")) {
      const double b = number("button");
      if (b != 0 && b != 1) throw std::invalid_argument(where + ": field 'button': must be 0 or 1");
      k.stylus_button = b != 0;
    }
    std::vector<TrajectoryKeyframe>& frames = by_station[station];
    if (!frames.empty() && !(k.t_s > frames.back().t_s)) {
      throw std::invalid_argument(where + ": field 't': times of station " +
                                  std::to_string(station) + " must increase strictly");
    }
    frames.push_back(k);
  }
  if (!have_header) throw std::invalid_argument(path.string() + ": empty trajectory file");
  if (by_station.empty()) throw std::invalid_argument(path.string() + ": no keyframes");
  const int num_stations = by_station.rbegin()->first;
  std::vector<std::vector<TrajectoryKeyframe>> keyframes(num_stations);
  for (int s = 1; s <= num_stations; ++s) {
    if (!by_station.count(s)) {
      throw std::invalid_argument(path.string() + ": station " + std::to_string(s) +
                                  " has no keyframe (stations must be 1..n without gaps)");
    }
    keyframes[s - 1] = std::move(by_station[s]);
  }
  return std::make_unique<TrajectoryPoseSource>(std::move(keyframes), loop);
}

double TrajectoryPoseSource::LocalTime(int station, double t_s) const {
  const std::vector<TrajectoryKeyframe>& frames = keyframes_[station - 1];
  if (!loop_ || frames.size() < 2) return t_s;
  const double t0 = frames.front().t_s;
  const double period = frames.back().t_s - t0;
  return t0 + std::fmod(std::fmod(t_s - t0, period) + period, period);
}

Rigid3d TrajectoryPoseSource::TruePose(int station, double t_s) {
  CheckStation(station, keyframes_.size(), "TrajectoryPoseSource");
  const std::vector<TrajectoryKeyframe>& frames = keyframes_[station - 1];
  const double t = LocalTime(station, t_s);
  if (t <= frames.front().t_s) return frames.front().transmitter_from_receiver;
  if (t >= frames.back().t_s) return frames.back().transmitter_from_receiver;
  const auto next =
      std::upper_bound(frames.begin(), frames.end(), t,
                       [](double v, const TrajectoryKeyframe& k) { return v < k.t_s; });
  const TrajectoryKeyframe& b = *next;
  const TrajectoryKeyframe& a = *(next - 1);
  const double u = (t - a.t_s) / (b.t_s - a.t_s);
  Rigid3d pose;
  pose.translation = (1 - u) * a.transmitter_from_receiver.translation +
                     u * b.transmitter_from_receiver.translation;
  pose.rotation =
      a.transmitter_from_receiver.rotation.slerp(u, b.transmitter_from_receiver.rotation);
  return pose;
}

bool TrajectoryPoseSource::StylusButton(int station, double t_s) {
  CheckStation(station, keyframes_.size(), "TrajectoryPoseSource");
  const std::vector<TrajectoryKeyframe>& frames = keyframes_[station - 1];
  const double t = LocalTime(station, t_s);
  const auto next =
      std::upper_bound(frames.begin(), frames.end(), t,
                       [](double v, const TrajectoryKeyframe& k) { return v < k.t_s; });
  if (next == frames.begin()) return frames.front().stylus_button;
  return (next - 1)->stylus_button;
}

ControlledPoseSource::ControlledPoseSource(std::unique_ptr<PoseSource> base)
    : base_(std::move(base)) {
  if (!base_) throw std::invalid_argument("ControlledPoseSource: base source is null");
}

void ControlledPoseSource::Move(int station, const Rigid3d& transmitter_from_receiver) {
  CheckStation(station, kMaxStations, "ControlledPoseSource::Move");
  std::lock_guard<std::mutex> lock(mutex_);
  moved_[station - 1] = transmitter_from_receiver;
}

void ControlledPoseSource::Release(int station) {
  CheckStation(station, kMaxStations, "ControlledPoseSource::Release");
  std::lock_guard<std::mutex> lock(mutex_);
  moved_[station - 1].reset();
  button_[station - 1].reset();
}

void ControlledPoseSource::SetButton(int station, bool pressed) {
  CheckStation(station, kMaxStations, "ControlledPoseSource::SetButton");
  std::lock_guard<std::mutex> lock(mutex_);
  button_[station - 1] = pressed;
}

Rigid3d ControlledPoseSource::TruePose(int station, double t_s) {
  CheckStation(station, kMaxStations, "ControlledPoseSource");
  {
    std::lock_guard<std::mutex> lock(mutex_);
    if (moved_[station - 1]) return *moved_[station - 1];
  }
  return base_->TruePose(station, t_s);
}

bool ControlledPoseSource::StylusButton(int station, double t_s) {
  CheckStation(station, kMaxStations, "ControlledPoseSource");
  {
    std::lock_guard<std::mutex> lock(mutex_);
    if (button_[station - 1]) return *button_[station - 1];
  }
  return base_->StylusButton(station, t_s);
}

StationMeasurement Measure(PoseSource& source, MeasurementModel& model, int station, double t_s) {
  StationMeasurement m;
  m.transmitter_from_receiver = model.Reported(station, source.TruePose(station, t_s), t_s);
  m.stylus_button = source.StylusButton(station, t_s);
  return m;
}

}  // namespace trackcal::emulator
