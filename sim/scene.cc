#include "sim/scene.h"

#include <yaml-cpp/yaml.h>

#include <algorithm>
#include <cerrno>
#include <charconv>
#include <cmath>
#include <fstream>
#include <functional>
#include <set>
#include <sstream>
#include <stdexcept>
#include <string>
#include <vector>

#include "core/capture.h"
#include "core/file_util.h"
#include "sim/presets.h"
#include "sim/scene_visit.h"

namespace trackcal::sim {

namespace {

void Require(bool ok, const std::string& field, const std::string& what) {
  if (!ok) throw std::invalid_argument("scene: " + field + ": " + what);
}
// Largest capture a scene may ask for (docs/scene.md).
constexpr double kMaxStations = 1e6;
constexpr double kMaxStreamSamples = 1e7;
bool Positive(double x) { return std::isfinite(x) && x > 0; }
bool NonNegative(double x) { return std::isfinite(x) && x >= 0; }
// 1-based line of a node in its document (0 if it has none).
int LineOf(const YAML::Node& node) { return node.Mark().line >= 0 ? node.Mark().line + 1 : 0; }

// ---- YAML reader: applies the keys present in a document to a Scene. ----
class YamlReader {
 public:
  YamlReader(const YAML::Node& root, std::string source) : source_(std::move(source)) {
    frames_.push_back(Frame{root, "", {}});
  }

  void Finish() { CheckUnknownKeys(frames_.back()); }

  template <typename T>
  void Field(const char* key, T& value) {
    Frame& f = frames_.back();
    f.seen.insert(key);
    const YAML::Node node = f.node[key];
    if (!node) return;
    Parse(node, Join(f.path, key), value);
  }

  template <typename F>
  void Object(const char* key, F visit) {
    Frame& f = frames_.back();
    f.seen.insert(key);
    const YAML::Node node = f.node[key];
    if (!node) return;
    const std::string path = Join(f.path, key);
    if (!node.IsMap()) Fail(node, path, "expected a mapping");
    frames_.push_back(Frame{node, path, {}});
    visit();
    CheckUnknownKeys(frames_.back());
    frames_.pop_back();
  }

  template <typename E, typename F>
  void List(const char* key, std::vector<E>& items, F visit) {
    Frame& f = frames_.back();
    f.seen.insert(key);
    const YAML::Node node = f.node[key];
    if (!node) return;
    const std::string path = Join(f.path, key);
    if (node.IsNull()) {
      items.clear();
      return;
    }
    if (!node.IsSequence()) Fail(node, path, "expected a list");
    items.assign(node.size(), E{});
    for (size_t i = 0; i < node.size(); ++i) {
      const std::string item_path = path + "[" + std::to_string(i) + "]";
      if (!node[i].IsMap()) Fail(node[i], item_path, "expected a mapping");
      frames_.push_back(Frame{node[i], item_path, {}});
      visit(items[i]);
      CheckMissingKeys(frames_.back());
      CheckUnknownKeys(frames_.back());
      frames_.pop_back();
    }
  }

  [[noreturn]] void Fail(const YAML::Node& node, const std::string& path,
                         const std::string& what) const {
    throw std::invalid_argument(source_ + ":" + std::to_string(LineOf(node)) + ": " + path + ": " +
                                what);
  }

 private:
  struct Frame {
    YAML::Node node;
    std::string path;
    std::set<std::string> seen;
  };

  static std::string Join(const std::string& path, const char* key) {
    return path.empty() ? std::string(key) : path + "." + key;
  }

  // A list item starts from the type's defaults, not from the base scene's item: a key left out
  // took a default that silently disabled the item (a plane without `attenuation` has 0, an object
  // without `polarisability_m3` has 0: sources that distort nothing). Every key but `name` is
  // required.
  void CheckMissingKeys(const Frame& f) const {
    for (const std::string& key : f.seen) {
      if (key != "name" && !f.node[key]) {
        Fail(f.node, Join(f.path, key.c_str()),
             "missing (a list item does not inherit from the base; give every key but name)");
      }
    }
  }

  void CheckUnknownKeys(const Frame& f) const {
    if (!f.node.IsMap()) return;
    std::set<std::string> keys;
    for (const auto& kv : f.node) {
      const std::string key = KeyOf(kv.first, f.path, &keys);
      if (f.path.empty() && key == "base") continue;
      if (!f.seen.count(key)) Fail(kv.first, Join(f.path, key.c_str()), "unknown key");
    }
  }

  // The text of a mapping key. A key that is not a plain value, or one already in `keys` (the
  // mapping's keys so far), is an error: yaml-cpp looks up the first of two equal keys, so a
  // repeated key (an override appended below the original) would be silently ignored.
  std::string KeyOf(const YAML::Node& key_node, const std::string& path,
                    std::set<std::string>* keys) const {
    if (!key_node.IsScalar()) {
      Fail(key_node, path.empty() ? "(top level)" : path, "keys must be names");
    }
    const std::string key = key_node.Scalar();
    if (!keys->insert(key).second) {
      Fail(key_node, Join(path, key.c_str()), "duplicate key (each key may appear once)");
    }
    return key;
  }

  std::string Scalar(const YAML::Node& node, const std::string& path) const {
    if (!node.IsScalar()) Fail(node, path, "expected a single value");
    return node.Scalar();
  }

  void Parse(const YAML::Node& node, const std::string& path, std::string& out) const {
    out = Scalar(node, path);
  }
  void Parse(const YAML::Node& node, const std::string& path, bool& out) const {
    const std::string s = Scalar(node, path);
    if (s == "true") {
      out = true;
    } else if (s == "false") {
      out = false;
    } else {
      Fail(node, path, "expected true or false, got '" + s + "'");
    }
  }
  template <typename I>
  requires std::is_integral_v<I>
  void Parse(const YAML::Node& node, const std::string& path, I& out) const {
    const std::string s = Scalar(node, path);
    I value{};
    const auto [end, ec] = std::from_chars(s.data(), s.data() + s.size(), value);
    if (ec != std::errc() || end != s.data() + s.size()) {
      Fail(node, path, "expected an integer, got '" + s + "'");
    }
    out = value;
  }
  void Parse(const YAML::Node& node, const std::string& path, double& out) const {
    const std::string s = Scalar(node, path);
    const char* begin = s.data() + (s.size() > 1 && s[0] == '+' ? 1 : 0);
    double value = 0;
    const auto [end, ec] = std::from_chars(begin, s.data() + s.size(), value);
    if (ec != std::errc() || end != s.data() + s.size() || !std::isfinite(value)) {
      Fail(node, path, "expected a number, got '" + s + "'");
    }
    out = value;
  }
  template <int N>
  void ParseNumbers(const YAML::Node& node, const std::string& path, double* out) const {
    if (!node.IsSequence() || node.size() != N) {
      Fail(node, path, "expected a list of " + std::to_string(N) + " numbers");
    }
    for (int i = 0; i < N; ++i) {
      Parse(node[i], path + "[" + std::to_string(i) + "]", out[i]);
    }
  }
  void Parse(const YAML::Node& node, const std::string& path, Eigen::Vector3d& out) const {
    ParseNumbers<3>(node, path, out.data());
  }
  void Parse(const YAML::Node& node, const std::string& path, Eigen::Vector3i& out) const {
    if (!node.IsSequence() || node.size() != 3) Fail(node, path, "expected a list of 3 integers");
    for (int i = 0; i < 3; ++i) Parse(node[i], path + "[" + std::to_string(i) + "]", out(i));
  }
  void Parse(const YAML::Node& node, const std::string& path, Eigen::Matrix3d& out) const {
    if (!node.IsSequence() || node.size() != 3) {
      Fail(node, path, "expected 3 rows of 3 numbers");
    }
    for (int r = 0; r < 3; ++r) {
      double row[3];
      ParseNumbers<3>(node[r], path + "[" + std::to_string(r) + "]", row);
      for (int c = 0; c < 3; ++c) out(r, c) = row[c];
    }
  }
  void Parse(const YAML::Node& node, const std::string& path, Rigid3d& out) const {
    if (!node.IsMap()) Fail(node, path, "expected a mapping with rotation_xyzw and translation");
    std::set<std::string> keys;
    for (const auto& kv : node) {
      const std::string key = KeyOf(kv.first, path, &keys);
      if (key != "rotation_xyzw" && key != "translation") {
        Fail(kv.first, path + "." + key, "unknown key");
      }
    }
    if (const YAML::Node q = node["rotation_xyzw"]) {
      double xyzw[4];
      ParseNumbers<4>(q, path + ".rotation_xyzw", xyzw);
      Eigen::Quaterniond rotation = QuaternionFromXyzwArray(xyzw);
      // Hand-typed quaternions carry a few digits; anything further from unit is a mistake.
      if (std::abs(rotation.norm() - 1.0) > 1e-3) {
        Fail(q, path + ".rotation_xyzw",
             "not a unit quaternion (norm " + std::to_string(rotation.norm()) + ")");
      }
      // An exactly unit quaternion is kept as is, so a written scene reads back bit for bit.
      if (std::abs(rotation.norm() - 1.0) > 1e-12) rotation.normalize();
      out.rotation = rotation;
    }
    if (const YAML::Node t = node["translation"]) {
      Parse(t, path + ".translation", out.translation);
    }
  }
  void Parse(const YAML::Node& node, const std::string& path,
             std::vector<Eigen::Vector3d>& out) const {
    if (!node.IsSequence()) Fail(node, path, "expected a list of [x, y, z]");
    out.assign(node.size(), Eigen::Vector3d::Zero());
    for (size_t i = 0; i < node.size(); ++i) {
      Parse(node[i], path + "[" + std::to_string(i) + "]", out[i]);
    }
  }

  std::string source_;
  std::vector<Frame> frames_;
};

// ---- YAML writer. ----
class YamlWriter {
 public:
  YamlWriter() { out_ << YAML::BeginMap; }
  std::string Finish() {
    out_ << YAML::EndMap;
    return std::string(out_.c_str()) + "\n";
  }
  template <typename T>
  void Field(const char* key, T& value) {
    out_ << YAML::Key << key << YAML::Value;
    Write(value);
  }
  template <typename F>
  void Object(const char* key, F visit) {
    out_ << YAML::Key << key << YAML::Value << YAML::BeginMap;
    visit();
    out_ << YAML::EndMap;
  }
  template <typename E, typename F>
  void List(const char* key, std::vector<E>& items, F visit) {
    out_ << YAML::Key << key << YAML::Value;
    if (items.empty()) {
      out_ << YAML::Flow << YAML::BeginSeq << YAML::EndSeq;
      return;
    }
    out_ << YAML::BeginSeq;
    for (E& item : items) {
      out_ << YAML::BeginMap;
      visit(item);
      out_ << YAML::EndMap;
    }
    out_ << YAML::EndSeq;
  }

 private:
  void Write(const std::string& s) { out_ << YAML::DoubleQuoted << s; }
  void Write(bool b) { out_ << (b ? "true" : "false"); }
  void Write(int i) { out_ << i; }
  void Write(uint64_t i) { out_ << i; }
  // Shortest round-trip text: readable, and ParseScene reads back the same double.
  void Write(double d) { out_ << FormatNumber(d); }
  void Write(const Eigen::Vector3d& v) {
    out_ << YAML::Flow << YAML::BeginSeq << FormatNumber(v.x()) << FormatNumber(v.y())
         << FormatNumber(v.z()) << YAML::EndSeq;
  }
  void Write(const Eigen::Vector3i& v) {
    out_ << YAML::Flow << YAML::BeginSeq << v.x() << v.y() << v.z() << YAML::EndSeq;
  }
  void Write(const Eigen::Matrix3d& m) {
    out_ << YAML::BeginSeq;
    for (int r = 0; r < 3; ++r) {
      out_ << YAML::Flow << YAML::BeginSeq << FormatNumber(m(r, 0)) << FormatNumber(m(r, 1))
           << FormatNumber(m(r, 2)) << YAML::EndSeq;
    }
    out_ << YAML::EndSeq;
  }
  void Write(const Rigid3d& pose) {
    out_ << YAML::BeginMap << YAML::Key << "rotation_xyzw" << YAML::Value << YAML::Flow
         << YAML::BeginSeq << FormatNumber(pose.rotation.x()) << FormatNumber(pose.rotation.y())
         << FormatNumber(pose.rotation.z()) << FormatNumber(pose.rotation.w()) << YAML::EndSeq
         << YAML::Key << "translation" << YAML::Value;
    Write(pose.translation);
    out_ << YAML::EndMap;
  }
  void Write(const std::vector<Eigen::Vector3d>& vs) {
    out_ << YAML::BeginSeq;
    for (const Eigen::Vector3d& v : vs) Write(v);
    out_ << YAML::EndSeq;
  }

  YAML::Emitter out_;
};

// ---- JSON writer. ----
class JsonWriter {
 public:
  nlohmann::json Finish() { return root_; }
  template <typename T>
  void Field(const char* key, T& value) {
    (*current_)[key] = ToJson(value);
  }
  template <typename F>
  void Object(const char* key, F visit) {
    nlohmann::json* parent = current_;
    (*parent)[key] = nlohmann::json::object();
    current_ = &(*parent)[key];
    visit();
    current_ = parent;
  }
  template <typename E, typename F>
  void List(const char* key, std::vector<E>& items, F visit) {
    nlohmann::json* parent = current_;
    nlohmann::json list = nlohmann::json::array();
    for (E& item : items) {
      nlohmann::json element = nlohmann::json::object();
      current_ = &element;
      visit(item);
      list.push_back(element);
    }
    current_ = parent;
    (*parent)[key] = list;
  }

 private:
  static nlohmann::json ToJson(const std::string& s) { return s; }
  static nlohmann::json ToJson(bool b) { return b; }
  static nlohmann::json ToJson(int i) { return i; }
  static nlohmann::json ToJson(uint64_t i) { return i; }
  static nlohmann::json ToJson(double d) { return d; }
  static nlohmann::json ToJson(const Eigen::Vector3d& v) { return {v.x(), v.y(), v.z()}; }
  static nlohmann::json ToJson(const Eigen::Vector3i& v) { return {v.x(), v.y(), v.z()}; }
  static nlohmann::json ToJson(const Eigen::Matrix3d& m) {
    nlohmann::json rows = nlohmann::json::array();
    for (int r = 0; r < 3; ++r) rows.push_back({m(r, 0), m(r, 1), m(r, 2)});
    return rows;
  }
  static nlohmann::json ToJson(const Rigid3d& p) {
    return {{"rotation_xyzw", {p.rotation.x(), p.rotation.y(), p.rotation.z(), p.rotation.w()}},
            {"translation", ToJson(p.translation)}};
  }
  static nlohmann::json ToJson(const std::vector<Eigen::Vector3d>& vs) {
    nlohmann::json list = nlohmann::json::array();
    for (const auto& v : vs) list.push_back(ToJson(v));
    return list;
  }

  nlohmann::json root_ = nlohmann::json::object();
  nlohmann::json* current_ = &root_;
};

// 1-based line of the deepest node below `node` on steps[i..] (map keys, or list indices where
// `is_index`); the line of `node` itself if steps[i] is not in the document.
int LineOfSteps(const YAML::Node& node, const std::vector<std::string>& steps,
                const std::vector<bool>& is_index, size_t i) {
  if (i == steps.size()) return LineOf(node);
  const std::string& step = steps[i];
  if (is_index[i]) {
    size_t index = 0;
    const auto [end, ec] = std::from_chars(step.data(), step.data() + step.size(), index);
    if (ec != std::errc() || end != step.data() + step.size() || !node.IsSequence() ||
        index >= node.size()) {
      return LineOf(node);
    }
    return LineOfSteps(node[index], steps, is_index, i + 1);
  }
  if (!node.IsMap() || !node[step]) return LineOf(node);
  return LineOfSteps(node[step], steps, is_index, i + 1);
}

// 1-based line of the deepest key of `root` on a field path such as
// "environment.planes[1].attenuation"; 0 if the path's first key is not in the document.
int LineOfField(const YAML::Node& root, const std::string& path) {
  std::vector<std::string> steps;
  std::vector<bool> is_index;
  std::string token;
  auto flush = [&](bool index) {
    if (!token.empty()) {
      steps.push_back(token);
      is_index.push_back(index);
    }
    token.clear();
  };
  for (const char c : path) {
    if (c == '.' || c == '[') {
      flush(false);
    } else if (c == ']') {
      flush(true);
    } else {
      token += c;
    }
  }
  flush(false);
  if (steps.empty() || !root.IsMap() || !root[steps[0]]) return 0;
  return LineOfSteps(root[steps[0]], steps, is_index, 1);
}

}  // namespace

void TrackerConfig::Check() const {
  Require(receiver_gain_matrix.allFinite() && std::abs(receiver_gain_matrix.determinant()) > 1e-6,
          "tracker.receiver_gain_matrix", "must be finite and invertible");
  Require(NonNegative(signal_noise), "tracker.signal_noise", "must be >= 0");
  Require(samples_per_station >= 1, "tracker.samples_per_station", "must be >= 1");
  Require(hemisphere_in_transmitter.allFinite() && hemisphere_in_transmitter.norm() > 1e-9,
          "tracker.hemisphere_in_transmitter", "must be a non-zero vector");
  Require(sensor >= 1, "tracker.sensor", "must be >= 1");
  Require(Positive(update_rate_hz), "tracker.update_rate_hz", "must be > 0");
}

void ReferenceConfig::Check() const {
  Require(NonNegative(position_noise_m), "reference.position_noise_m", "must be >= 0");
  Require(NonNegative(orientation_noise_rad), "reference.orientation_noise_rad", "must be >= 0");
  Require(NonNegative(marker_noise_m), "reference.marker_noise_m", "must be >= 0");
  Require(samples_per_station >= 1, "reference.samples_per_station", "must be >= 1");
  Require(Positive(update_rate_hz), "reference.update_rate_hz", "must be > 0");
  Require(optical_from_transmitter.translation.allFinite() &&
              std::abs(optical_from_transmitter.rotation.norm() - 1.0) < 1e-9,
          "reference.optical_from_transmitter", "must be a finite rigid transform");
  Require(markers_in_body.size() >= 3, "reference.markers_in_body", "needs at least 3 markers");
  for (size_t i = 0; i < markers_in_body.size(); ++i) {
    Require(markers_in_body[i].allFinite() && markers_in_body[i].norm() > 1e-6,
            "reference.markers_in_body[" + std::to_string(i) + "]",
            "must be finite and away from the body origin");
  }
  Require(std::isfinite(visibility_cos_min) && visibility_cos_min <= 0.0,
          "reference.visibility_cos_min",
          "must be <= 0 (markers around the receiver then keep at least 3 visible)");
}

void StreamConfig::KeepWithin(const Eigen::Vector3d& min_in_transmitter,
                              const Eigen::Vector3d& max_in_transmitter, const std::string& what) {
  static const char* const kAxes[] = {"x", "y", "z"};
  for (int i = 0; i < 3; ++i) {
    const double lo = min_in_transmitter(i), hi = max_in_transmitter(i);
    if (!std::isfinite(lo) || !std::isfinite(hi)) {
      throw std::invalid_argument(what + ": " + kAxes[i] + " bounds must be finite");
    }
    if (!(hi > lo)) {
      throw std::invalid_argument(what + ": max " + kAxes[i] + " (" + std::to_string(hi) +
                                  ") must be above min " + kAxes[i] + " (" + std::to_string(lo) +
                                  ")");
    }
    const double a = std::abs(amplitude_m(i));
    double from = std::max(center_in_transmitter(i) - a, lo);
    double to = std::min(center_in_transmitter(i) + a, hi);
    if (from > to) from = lo, to = hi;  // the path lies beside the box: sweep the box instead
    center_in_transmitter(i) = 0.5 * (from + to);
    amplitude_m(i) = 0.5 * (to - from);
  }
}

void CaptureProtocol::Check() const {
  Require((calibration.counts.array() >= 1).all(), "capture.calibration.counts", "must be >= 1");
  Require(calibration.origin_in_transmitter.allFinite(),
          "capture.calibration.origin_in_transmitter", "must be finite");
  Require(Positive(calibration.spacing_m), "capture.calibration.spacing_m", "must be > 0");
  auto check_random = [](const RandomStations& r, const std::string& name) {
    Require(r.count >= 0, "capture." + name + ".count", "must be >= 0");
    Require(r.min_in_transmitter.allFinite() && r.max_in_transmitter.allFinite() &&
                (r.min_in_transmitter.array() <= r.max_in_transmitter.array()).all(),
            "capture." + name + ".max_in_transmitter", "must be finite and >= min_in_transmitter");
  };
  check_random(validation, "validation");
  check_random(registration, "registration");
  Require(Positive(station_period_s), "capture.station_period_s", "must be > 0");
  Require(NonNegative(stream.duration_s), "capture.stream.duration_s", "must be >= 0");
  Require(stream.center_in_transmitter.allFinite() && stream.amplitude_m.allFinite(),
          "capture.stream.center_in_transmitter", "must be finite");
  Require((stream.period_s.array() > 0).all() && stream.period_s.allFinite(),
          "capture.stream.period_s", "must be > 0");
  Require(NonNegative(stream.rotation_amplitude_rad), "capture.stream.rotation_amplitude_rad",
          "must be >= 0");
  Require(Positive(stream.rotation_period_s), "capture.stream.rotation_period_s", "must be > 0");
}

const std::vector<std::string>& HiddenEffects::Names() {
  static const std::vector<std::string> names = {"sensor_offset",        "receiver_gains",
                                                 "ferromagnetic_object", "finite_transmitter_coils",
                                                 "clock_offset",         "hemisphere_flips"};
  return names;
}

void HiddenEffects::Enable(const std::string& name) {
  bool* flags[] = {&sensor_offset,        &receiver_gains,
                   &ferromagnetic_object, &finite_transmitter_coils,
                   &clock_offset,         &hemisphere_flips};
  for (size_t i = 0; i < Names().size(); ++i) {
    if (Names()[i] == name) {
      *flags[i] = true;
      return;
    }
  }
  std::string known;
  for (const auto& n : Names()) known += (known.empty() ? "" : ", ") + n;
  throw std::invalid_argument("unknown hidden effect '" + name + "' (known: " + known + ")");
}

std::vector<std::string> HiddenEffects::EnabledNames() const {
  const bool flags[] = {sensor_offset,        receiver_gains,
                        ferromagnetic_object, finite_transmitter_coils,
                        clock_offset,         hemisphere_flips};
  std::vector<std::string> out;
  for (size_t i = 0; i < Names().size(); ++i) {
    if (flags[i]) out.push_back(Names()[i]);
  }
  return out;
}

Rigid3d HiddenEffects::DefaultReceiverFromBody() {
  // About 3.1 degrees and 2.5 cm: a marker body glued on slightly askew.
  return Rigid3d(QuaternionFromXyzw(0.02, -0.015, 0.01, 0.99966).normalized(),
                 Eigen::Vector3d(0.012, -0.008, 0.02));
}

Eigen::Matrix3d HiddenEffects::DefaultReceiverGainMatrix() {
  // Gains within 2% and coil axes about 1 degree off orthogonal.
  Eigen::Matrix3d g;
  g << 1.02, 0.01, 0.0, -0.005, 0.98, 0.015, 0.0, 0.008, 1.01;
  return g;
}

void HiddenEffects::Check() const {
  Require(receiver_from_body.translation.allFinite(), "hidden.sensor_offset.receiver_from_body",
          "must be finite");
  Require(receiver_gain_matrix.allFinite() && std::abs(receiver_gain_matrix.determinant()) > 1e-6,
          "hidden.receiver_gains.receiver_gain_matrix", "must be finite and invertible");
  Require(
      object.location_in_transmitter.allFinite() && object.location_in_transmitter.norm() > 1e-3,
      "hidden.ferromagnetic_object.location_in_transmitter",
      "must be finite and away from the transmitter");
  Require(std::isfinite(object.polarisability_m3), "hidden.ferromagnetic_object.polarisability_m3",
          "must be finite");
  Require(octupole_m2.allFinite(), "hidden.finite_transmitter_coils.octupole_m2", "must be finite");
  Require(std::isfinite(reference_minus_tracker_s), "hidden.clock_offset.reference_minus_tracker_s",
          "must be finite");
  Require(std::isfinite(reference_clock_drift) && std::abs(reference_clock_drift) < 0.1,
          "hidden.clock_offset.reference_clock_drift", "must be finite and within +-0.1");
  Require(flip_count >= 0, "hidden.hemisphere_flips.count", "must be >= 0");
}

namespace {
void CheckCalibrationGridAvoidsSources(const Scene& scene) {
  // The field is singular at the transmitter and at every induced dipole: a receiver there has no
  // report (the tracker's solver returns nothing), so the capture would hold a made-up pose. The
  // grid node nearest each source, per axis the rounded and clamped index, is checked.
  std::vector<std::pair<std::string, Eigen::Vector3d>> sources = {
      {"the transmitter", Eigen::Vector3d::Zero()}};
  for (const InducedDipole& o : scene.environment.objects) {
    sources.push_back({"object '" + o.name + "'", o.location_in_transmitter});
  }
  if (scene.hidden.ferromagnetic_object) {
    sources.push_back({"the hidden object '" + scene.hidden.object.name + "'",
                       scene.hidden.object.location_in_transmitter});
  }
  const CalibrationGrid& g = scene.capture.calibration;
  for (const auto& [what, at] : sources) {
    Eigen::Vector3d node;
    for (int i = 0; i < 3; ++i) {
      const double index =
          std::clamp(std::round((at(i) - g.origin_in_transmitter(i)) / g.spacing_m), 0.0,
                     static_cast<double>(g.counts(i) - 1));
      node(i) = g.origin_in_transmitter(i) + g.spacing_m * index;
    }
    Require((node - at).norm() > 1e-3, "capture.calibration.origin_in_transmitter",
            "the grid node at [" + FormatNumber(node.x()) + ", " + FormatNumber(node.y()) + ", " +
                FormatNumber(node.z()) + "] is within 1 mm of " + what +
                ", where the field is singular");
  }
}
// The regions a capture visits, each a box [lo, hi] named by its scene field: the calibration
// grid, the validation and registration boxes with stations, the streams' box.
struct CaptureRegion {
  std::string field;
  Eigen::Vector3d lo, hi;
};
std::vector<CaptureRegion> CaptureRegions(const CaptureProtocol& c) {
  std::vector<CaptureRegion> regions;
  const CalibrationGrid& g = c.calibration;
  regions.push_back(
      {"capture.calibration", g.origin_in_transmitter,
       g.origin_in_transmitter + g.spacing_m * (g.counts.cast<double>().array() - 1).matrix()});
  if (c.validation.count > 0) {
    regions.push_back(
        {"capture.validation", c.validation.min_in_transmitter, c.validation.max_in_transmitter});
  }
  if (c.registration.count > 0) {
    regions.push_back({"capture.registration", c.registration.min_in_transmitter,
                       c.registration.max_in_transmitter});
  }
  if (c.stream.duration_s > 0) {
    const Eigen::Vector3d a = c.stream.amplitude_m.cwiseAbs();
    regions.push_back(
        {"capture.stream", c.stream.center_in_transmitter - a, c.stream.center_in_transmitter + a});
  }
  return regions;
}
Eigen::Vector3d Corner(const CaptureRegion& r, int corner) {
  Eigen::Vector3d x;
  for (int a = 0; a < 3; ++a) x(a) = (corner >> a) & 1 ? r.hi(a) : r.lo(a);
  return x;
}
// The image of the transmitter in a plane is its field on the transmitter's side only: behind a
// conducting plane the field is screened, not the sum of the transmitter and its image. (A plane
// with the sign of its point flipped, e.g. a floor placed above a z-down transmitter, puts the
// capture behind it.) Every region a capture visits is a box, so its 8 corners are checked.
void CheckCaptureOnTheTransmitterSideOfPlanes(const Scene& scene) {
  const std::vector<CaptureRegion> regions = CaptureRegions(scene.capture);
  const auto& planes = scene.environment.planes;
  for (size_t i = 0; i < planes.size(); ++i) {
    const Eigen::Vector3d n = planes[i].normal_in_transmitter.normalized();
    const Eigen::Vector3d& q = planes[i].point_in_transmitter;
    for (const CaptureRegion& r : regions) {
      for (int corner = 0; corner < 8; ++corner) {
        const Eigen::Vector3d x = Corner(r, corner);
        // On the transmitter's side, (x - q).n has the sign of (0 - q).n.
        Require((x - q).dot(n) * q.dot(n) < 0.0, r.field,
                "the capture reaches [" + FormatNumber(x.x()) + ", " + FormatNumber(x.y()) + ", " +
                    FormatNumber(x.z()) + "], on or beyond plane '" + planes[i].name +
                    "' (environment.planes[" + std::to_string(i) +
                    "]) from the transmitter, where its image model does not hold");
      }
    }
  }
}
// The tracker's solver reports, of the two dipole solutions +-p, the one with p . h >= 0: a
// receiver on the other side of the hemisphere plane is reported at its mirror image -p. A capture
// reaching there (the Fastrak's power-up hemisphere +x on a workspace above a z-down transmitter,
// or a box drawn across the plane) was simulated without complaint, with position errors of about
// twice the range (paper preset with h = +x: validation mean 836 mm instead of 43 mm) that no
// correction can learn. The hidden effect hemisphere_flips is the way to ask for flipped reports.
// The stream's box is not checked: the emulator walks it (trackcal-emulate --within the served
// calibration's volume), and a device moved outside its hemisphere reports mirror images, as a
// real Fastrak does; refusing it stopped the emulator (the demo serving a calibration measured on
// the other side of the plane).
void CheckCaptureInTheTrackerHemisphere(const Scene& scene) {
  const Eigen::Vector3d& h = scene.tracker.hemisphere_in_transmitter;
  for (const CaptureRegion& r : CaptureRegions(scene.capture)) {
    if (r.field == "capture.stream") continue;
    for (int corner = 0; corner < 8; ++corner) {
      const Eigen::Vector3d x = Corner(r, corner);
      Require(x.dot(h) > 0.0, r.field,
              "the capture reaches [" + FormatNumber(x.x()) + ", " + FormatNumber(x.y()) + ", " +
                  FormatNumber(x.z()) + "], outside the tracker's hemisphere " +
                  "(tracker.hemisphere_in_transmitter [" + FormatNumber(h.x()) + ", " +
                  FormatNumber(h.y()) + ", " + FormatNumber(h.z()) +
                  "]: positions p with p . h > 0), where it reports the mirror image -p");
    }
  }
}
}  // namespace

void Scene::Check() const {
  try {
    environment.Check();
  } catch (const std::invalid_argument& e) {
    // FieldModel names its fields from its own root ("field model: planes[0].attenuation"); a scene
    // holds it under `environment`, with the octupole under its YAML key.
    std::string what = e.what();
    const std::string prefix = "field model: ";
    if (what.rfind(prefix, 0) == 0) what.erase(0, prefix.size());
    const std::string octupole = "transmitter.octupole_m2";
    if (what.rfind(octupole, 0) == 0) what.replace(0, octupole.size(), "transmitter_octupole_m2");
    throw std::invalid_argument("scene: environment." + what);
  }
  tracker.Check();
  reference.Check();
  capture.Check();
  hidden.Check();
  // Sizes the simulator holds in memory and counts with int ids: beyond them a typo (an extra
  // zero in counts, a duration in ms) ran out of memory after minutes, or looped without end on
  // an overflowing sample index.
  const CaptureProtocol& c = capture;
  const double grid = c.calibration.counts.cast<double>().prod();
  const double stations = grid + c.validation.count + c.registration.count;
  // Named by the largest part.
  const std::string stations_field =
      grid >= std::max(c.validation.count, c.registration.count) ? "capture.calibration.counts"
      : c.validation.count >= c.registration.count               ? "capture.validation.count"
                                                                 : "capture.registration.count";
  Require(stations <= kMaxStations, stations_field,
          "the capture would have " + FormatNumber(stations) + " static stations, more than " +
              std::to_string(static_cast<long>(kMaxStations)));
  const double rate = std::max(tracker.update_rate_hz, reference.update_rate_hz);
  Require(c.stream.duration_s * rate <= kMaxStreamSamples, "capture.stream.duration_s",
          "the streams would have " + FormatNumber(c.stream.duration_s * rate) +
              " samples, more than " + std::to_string(static_cast<long>(kMaxStreamSamples)));
  CheckCalibrationGridAvoidsSources(*this);
  CheckCaptureOnTheTransmitterSideOfPlanes(*this);
  CheckCaptureInTheTrackerHemisphere(*this);
}

std::vector<std::string> PresetNames() {
  std::vector<std::string> names;
  for (const auto& p : internal::Presets()) names.push_back(p.name);
  return names;
}

const std::string& PresetYaml(const std::string& name) {
  for (const auto& p : internal::Presets()) {
    if (p.name == name) return p.yaml;
  }
  std::string known;
  for (const auto& n : PresetNames()) known += (known.empty() ? "" : ", ") + n;
  throw std::invalid_argument("unknown scene preset '" + name + "' (presets: " + known + ")");
}

Scene ParseScene(const std::string& yaml_text, const std::string& source, const Scene& base) {
  // A PDF (docs/scene.md printed to PDF, or saved under .yaml) gave "YAML syntax error: unknown
  // escape character" followed by a raw byte. yaml-cpp itself reads UTF-16 and UTF-32 scenes.
  if (yaml_text.rfind("%PDF-", 0) == 0) {
    throw std::invalid_argument(source +
                                ":1: a PDF document (the file starts with %PDF-), not a scene "
                                "file (YAML text, docs/scene.md)");
  }
  YAML::Node root;
  try {
    // Every document, not the first only: YAML::Load stopped at a "---" line, so the keys of a
    // second document (an override appended below one) were silently ignored.
    const std::vector<YAML::Node> documents = YAML::LoadAll(yaml_text);
    if (!documents.empty()) root = documents.front();
    for (size_t i = 1; i < documents.size(); ++i) {
      if (documents[i].IsNull()) continue;  // a trailing "---" or comment
      throw std::invalid_argument(source + ":" + std::to_string(LineOf(documents[i])) +
                                  ": a scene is one YAML document; a second one starts here (after "
                                  "a '---' line), its keys would be ignored");
    }
  } catch (const YAML::Exception& e) {
    throw std::invalid_argument(source + ":" + std::to_string(e.mark.line + 1) +
                                ": YAML syntax error: " + e.msg);
  }
  // An empty file (or one of comments only) said "a scene must be a YAML mapping", which reads as
  // a syntax problem to someone who saved nothing.
  if (!root.IsDefined() || root.IsNull()) {
    throw std::invalid_argument(source +
                                ":1: the scene has no keys (an empty file, or comments only); "
                                "start from a preset with 'base: paper' (docs/scene.md)");
  }
  if (!root.IsMap()) {
    throw std::invalid_argument(source + ":" + std::to_string(root.Mark().line + 1) +
                                ": a scene must be a YAML mapping (key: value lines), not " +
                                (root.IsSequence() ? "a list" : "a single value"));
  }
  Scene scene = base;
  if (const YAML::Node b = root["base"]) {
    if (!b.IsScalar()) {
      throw std::invalid_argument(source + ":" + std::to_string(b.Mark().line + 1) +
                                  ": base: expected a preset name");
    }
    try {
      scene = ParseScene(PresetYaml(b.Scalar()), "preset " + b.Scalar());
    } catch (const std::invalid_argument& e) {
      throw std::invalid_argument(source + ":" + std::to_string(b.Mark().line + 1) +
                                  ": base: " + e.what());
    }
  }
  YamlReader reader(root, source);
  internal::VisitScene(reader, scene);
  reader.Finish();
  try {
    scene.Check();
  } catch (const std::invalid_argument& e) {
    // "scene: capture.validation.max_in_transmitter: must be ..." -> the line of that key in this
    // file, or of its closest enclosing key here (the value itself may come from `base`).
    std::string what = e.what();
    const std::string prefix = "scene: ";
    if (what.rfind(prefix, 0) == 0) what.erase(0, prefix.size());
    const int line = LineOfField(root, what.substr(0, what.find(": ")));
    throw std::invalid_argument(source + (line > 0 ? ":" + std::to_string(line) : "") + ": " +
                                what);
  }
  return scene;
}

Scene LoadScene(const std::string& preset_or_path) {
  const std::filesystem::path path(preset_or_path);
  std::error_code ec;
  const std::filesystem::file_status status = std::filesystem::status(path, ec);
  // A folder was "neither a scene file nor a preset", as was a pipe (`--scene <(...)`), which is
  // read as a file is; a file that could not be opened gave no reason.
  if (std::filesystem::is_directory(status)) {
    throw std::invalid_argument(preset_or_path + ": is a folder, not a scene file");
  }
  if (std::filesystem::exists(status)) {
    errno = 0;
    std::ifstream in(path);
    if (!in) {
      throw std::invalid_argument(preset_or_path +
                                  ": cannot open scene file: " + SystemErrorText(errno));
    }
    std::stringstream text;
    text << in.rdbuf();
    if (in.bad()) throw std::invalid_argument(preset_or_path + ": read error");
    return ParseScene(text.str(), path.string());
  }
  for (const auto& name : PresetNames()) {
    if (name == preset_or_path) return ParseScene(PresetYaml(name), "preset " + name);
  }
  std::string known;
  for (const auto& n : PresetNames()) known += (known.empty() ? "" : ", ") + n;
  throw std::invalid_argument("scene '" + preset_or_path + "' is neither a scene file" +
                              (ec ? " (" + ec.message() + ")" : std::string()) +
                              " nor a preset (presets: " + known + ")");
}

std::string SceneToYaml(const Scene& scene) {
  Scene copy = scene;
  YamlWriter writer;
  internal::VisitScene(writer, copy);
  return "# trackcal scene (docs/scene.md)\n" + writer.Finish();
}

nlohmann::json SceneToJson(const Scene& scene) {
  Scene copy = scene;
  JsonWriter writer;
  internal::VisitScene(writer, copy);
  return writer.Finish();
}

}  // namespace trackcal::sim
