#include "plugin/unity_axes.h"

#include <array>
#include <cctype>
#include <cmath>
#include <stdexcept>

namespace trackcal::unity {
namespace {

std::string Trim(std::string_view s) {
  std::size_t b = 0, e = s.size();
  while (b < e && std::isspace(static_cast<unsigned char>(s[b]))) ++b;
  while (e > b && std::isspace(static_cast<unsigned char>(s[e - 1]))) --e;
  return std::string(s.substr(b, e - b));
}

[[noreturn]] void Fail(std::string_view spec, const std::string& why) {
  throw std::invalid_argument("axes \"" + std::string(spec) + "\": " + why +
                              " (expected three tracker axes for Unity's x, y, z, e.g. \"" +
                              std::string(kDefaultAxes) + "\")");
}

}  // namespace

AxisMap ParseAxisMap(std::string_view spec) {
  std::array<std::string, 3> items;
  std::size_t count = 0, start = 0;
  for (std::size_t i = 0; i <= spec.size(); ++i) {
    if (i == spec.size() || spec[i] == ',') {
      if (count == 3) Fail(spec, "more than three items");
      items[count++] = Trim(spec.substr(start, i - start));
      start = i + 1;
    }
  }
  if (count != 3) Fail(spec, "fewer than three items");
  AxisMap out;
  out.unity_from_tracker.setZero();
  std::array<bool, 3> used{false, false, false};
  static constexpr std::array<const char*, 3> kUnityAxis = {"x", "y", "z"};
  for (int row = 0; row < 3; ++row) {
    std::string item = items[row];
    double sign = 1.0;
    if (!item.empty() && (item[0] == '-' || item[0] == '+')) {
      sign = item[0] == '-' ? -1.0 : 1.0;
      item = Trim(std::string_view(item).substr(1));
    }
    const char c = item.size() == 1
                       ? static_cast<char>(std::tolower(static_cast<unsigned char>(item[0])))
                       : '\0';
    if (c < 'x' || c > 'z') {
      Fail(spec,
           std::string("Unity ") + kUnityAxis[row] + " is \"" + items[row] + "\", not x, y or z");
    }
    const int col = c - 'x';
    if (used[col]) Fail(spec, std::string("tracker axis ") + c + " is used twice");
    used[col] = true;
    out.unity_from_tracker(row, col) = sign;
    if (row > 0) out.spec += ",";
    if (sign < 0) out.spec += '-';
    out.spec += c;
  }
  if (out.unity_from_tracker.determinant() > 0) {
    Fail(
        spec,
        "keeps handedness, so the scene would be mirrored (Unity is left-handed; negate one axis)");
  }
  return out;
}

UnityPose ToUnity(const AxisMap& axes, const Rigid3d& transmitter_from_receiver) {
  const Eigen::Matrix3d& m = axes.unity_from_tracker;
  const Eigen::Quaterniond& q = transmitter_from_receiver.rotation;
  UnityPose out;
  out.position = m * transmitter_from_receiver.translation;
  // det(M) = -1 (ParseAxisMap): the rotation axis is a pseudovector, so it maps to -M * axis.
  const Eigen::Vector3d v = -(m * q.vec());
  out.rotation = QuaternionFromXyzw(v.x(), v.y(), v.z(), q.w());
  // A server that sends an unnormalised quaternion (not the Fastrak's: float32, unit to ~1e-7)
  // would hand Unity a rotation it rejects; the position is not scaled with it.
  const double norm = out.rotation.norm();
  if (!std::isfinite(norm) || !std::isfinite(out.position.squaredNorm()) || norm == 0.0) {
    throw std::invalid_argument("pose " + transmitter_from_receiver.ToString() +
                                ": not a rotation and a position");
  }
  if (std::abs(norm - 1.0) > kUnitQuaternionTolerance) out.rotation.coeffs() /= norm;
  return out;
}

}  // namespace trackcal::unity
