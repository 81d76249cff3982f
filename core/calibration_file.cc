#include "core/calibration_file.h"

#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <ctime>
#include <regex>
#include <stdexcept>
#include <system_error>

#include "core/file_util.h"
#include "core/json_reader.h"

namespace trackcal {

namespace {

constexpr const char* kUnitsLength = "m";
constexpr const char* kFramePose = "transmitter_from_receiver";
constexpr const char* kFrameErrors = "transmitter";

// Key order of the written file, so a human reads it top-down.
const std::vector<std::string>& CalibrationKeyOrder() {
  static const std::vector<std::string> order = {
      "format", "version", "description", "sensor", "units", "frames", "calibrated_volume",
      "corrections", "fit_statistics", "provenance",
      // volume
      "min", "max", "extrapolation", "fade_distance", "linear_reach",
      // corrections
      "type", "degree", "term_order", "input_offset", "input_scale", "node_order", "axes",
      "position_coefficients", "orientation_coefficients", "position_error", "orientation_error",
      // provenance
      "tool", "tool_version", "created_utc", "command_line", "inputs", "path", "sha256", "role"};
  return order;
}

bool IsScalar(const nlohmann::json& v) { return !v.is_object() && !v.is_array(); }

// A scalar or key as JSON text. Strings that are not valid UTF-8 (a file name or command line in a
// legacy 8-bit encoding: Linux paths are bytes) get U+FFFD for each bad byte instead of throwing
// nlohmann's type_error, which would lose the calibration at the very end of a fit.
std::string Dump(const nlohmann::json& v) {
  return v.dump(-1, ' ', false, nlohmann::json::error_handler_t::replace);
}

bool IsFlatArray(const nlohmann::json& v) {
  if (!v.is_array()) return false;
  for (const auto& e : v) {
    if (!IsScalar(e)) return false;
  }
  return true;
}

void Format(const nlohmann::json& v, const std::vector<std::string>& key_order, int indent,
            std::string* out) {
  const std::string pad(static_cast<size_t>(indent + 2), ' ');
  const std::string close_pad(static_cast<size_t>(indent), ' ');
  if (IsScalar(v)) {
    *out += Dump(v);
  } else if (v.is_array()) {
    if (v.empty()) {
      *out += "[]";
    } else if (IsFlatArray(v)) {
      *out += "[";
      for (size_t i = 0; i < v.size(); ++i) {
        if (i) *out += ", ";
        *out += Dump(v[i]);
      }
      *out += "]";
    } else {
      *out += "[\n";
      for (size_t i = 0; i < v.size(); ++i) {
        *out += pad;
        Format(v[i], key_order, indent + 2, out);
        *out += i + 1 < v.size() ? ",\n" : "\n";
      }
      *out += close_pad + "]";
    }
  } else {
    if (v.empty()) {
      *out += "{}";
      return;
    }
    std::vector<std::string> keys;
    for (const auto& [key, unused] : v.items()) keys.push_back(key);
    auto rank = [&](const std::string& k) {
      const auto it = std::find(key_order.begin(), key_order.end(), k);
      return static_cast<size_t>(it - key_order.begin());
    };
    std::stable_sort(keys.begin(), keys.end(), [&](const std::string& a, const std::string& b) {
      const size_t ra = rank(a), rb = rank(b);
      return ra != rb ? ra < rb : a < b;
    });
    *out += "{\n";
    for (size_t i = 0; i < keys.size(); ++i) {
      *out += pad + Dump(nlohmann::json(keys[i])) + ": ";
      Format(v.at(keys[i]), key_order, indent + 2, out);
      *out += i + 1 < keys.size() ? ",\n" : "\n";
    }
    *out += close_pad + "}";
  }
}

bool IsUtcTimestamp(const std::string& s) {
  static const std::regex pattern(R"((\d{4})-(\d{2})-(\d{2})T(\d{2}):(\d{2}):(\d{2})(\.\d+)?Z)");
  std::smatch m;
  if (!std::regex_match(s, m, pattern)) return false;
  // The fields in range too: a month 13 or an hour 25 is no time (a leap second's 60 is).
  const auto field = [&m](int i) { return std::stoi(m[i].str()); };
  const int year = field(1), month = field(2), day = field(3);
  if (month < 1 || month > 12 || day < 1) return false;
  static constexpr int kDays[12] = {31, 29, 31, 30, 31, 30, 31, 31, 30, 31, 30, 31};
  const bool leap = (year % 4 == 0 && year % 100 != 0) || year % 400 == 0;
  if (day > kDays[month - 1] || (month == 2 && day == 29 && !leap)) return false;
  return field(4) <= 23 && field(5) <= 59 && field(6) <= 60;
}

CalibratedVolume ParseVolume(const JsonObjectReader& r) {
  CalibratedVolume volume;
  volume.min = r.Vector3("min");
  volume.max = r.Vector3("max");
  static const char* kAxis[3] = {"x", "y", "z"};
  for (int k = 0; k < 3; ++k) {
    if (!(volume.min[k] < volume.max[k])) {
      r.Fail("max", std::string("empty volume: max.") + kAxis[k] + " = " +
                        nlohmann::json(volume.max[k]).dump() + " is not above min." + kAxis[k] +
                        " = " + nlohmann::json(volume.min[k]).dump());
    }
  }
  volume.extrapolation =
      ExtrapolationPolicyFromName(r.Enum("extrapolation", {"clamp", "fade", "linear"}));
  volume.fade_distance = r.Number("fade_distance");
  if (volume.extrapolation == ExtrapolationPolicy::kFade && !(volume.fade_distance > 0.0)) {
    r.Fail("fade_distance", "must be positive for extrapolation \"fade\", got " +
                                r.Get("fade_distance").dump());
  }
  if (volume.fade_distance < 0.0) {
    r.Fail("fade_distance", "must not be negative, got " + r.Get("fade_distance").dump());
  }
  // Optional (files before the linear policy do not have it); read whatever the policy so that a
  // bad value is reported rather than ignored.
  if (r.Has("linear_reach")) {
    volume.linear_reach = r.Number("linear_reach");
    if (volume.linear_reach < 0.0) {
      r.Fail("linear_reach", "must not be negative, got " + r.Get("linear_reach").dump());
    }
  }
  r.CheckNoUnknownKeys();
  return volume;
}

Provenance ParseProvenance(const JsonObjectReader& r) {
  Provenance p;
  p.tool = r.String("tool");
  p.tool_version = r.String("tool_version");
  p.created_utc = r.String("created_utc");
  if (!IsUtcTimestamp(p.created_utc)) {
    r.Fail("created_utc", "expected an ISO 8601 UTC time \"YYYY-MM-DDTHH:MM:SSZ\", got \"" +
                              p.created_utc + "\"");
  }
  if (r.Has("command_line")) p.command_line = r.String("command_line");
  const nlohmann::json& inputs = r.Get("inputs");
  if (!inputs.is_array()) r.Fail("inputs", "expected an array of {path, sha256, role}");
  for (size_t i = 0; i < inputs.size(); ++i) {
    const JsonObjectReader in(inputs[i], r.source(), JsonIndexPath(r.PathOf("inputs"), i));
    CalibrationInput input;
    input.path = in.String("path");
    if (input.path.empty()) in.Fail("path", "must not be empty");
    input.sha256 = in.String("sha256");
    if (!IsSha256Hex(input.sha256)) {
      in.Fail("sha256", "expected 64 lower-case hexadecimal digits, got \"" + input.sha256 + "\"");
    }
    input.role = in.String("role");
    in.CheckNoUnknownKeys();
    p.inputs.push_back(std::move(input));
  }
  r.CheckNoUnknownKeys();
  return p;
}

// Numbers that are finite in the file can still overflow when a term is evaluated (an input_scale
// of 1e-200 makes the polynomial's u^2 infinite, and infinity times a zero coefficient is NaN):
// such a file would serve NaN for every pose. Each term is applied, in chain order, at the corners
// and the centre of the calibrated volume; the first that gives a non-finite pose is the error.
void CheckFiniteInVolume(const CorrectionChain& chain, const CalibratedVolume& volume,
                         const std::string& source, const std::string& path) {
  for (int point = 0; point < 9; ++point) {
    Eigen::Vector3d p = 0.5 * (volume.min + volume.max);
    if (point < 8) {
      for (int k = 0; k < 3; ++k) p[k] = (point >> k) & 1 ? volume.max[k] : volume.min[k];
    }
    Rigid3d pose(Eigen::Quaterniond::Identity(), p);
    for (size_t i = 0; i < chain.size(); ++i) {
      pose = chain.term(i).Apply(pose).pose;
      if (!pose.translation.allFinite() || !pose.rotation.coeffs().allFinite()) {
        ThrowJsonError(source, JsonIndexPath(path, i),
                       "gives a non-finite pose at " +
                           nlohmann::json({p.x(), p.y(), p.z()}).dump() +
                           " of the calibrated volume (its numbers overflow a double there)");
      }
    }
  }
}

void CheckProvenance(const Provenance& p) {
  if (!p.created_utc.empty() && !IsUtcTimestamp(p.created_utc)) {
    throw std::invalid_argument("provenance.created_utc: expected \"YYYY-MM-DDTHH:MM:SSZ\", got \"" +
                                p.created_utc + "\"");
  }
  for (size_t i = 0; i < p.inputs.size(); ++i) {
    const std::string where = "provenance.inputs[" + std::to_string(i) + "]";
    if (p.inputs[i].path.empty()) throw std::invalid_argument(where + ".path: must not be empty");
    if (!IsSha256Hex(p.inputs[i].sha256)) {
      throw std::invalid_argument(where + ".sha256: expected 64 lower-case hex digits, got \"" +
                                  p.inputs[i].sha256 + "\"");
    }
  }
}

}  // namespace

void Calibration::Check() const {
  if (sensor < 0 || sensor > kMaxCalibrationSensor) {
    throw std::invalid_argument("calibration: sensor must be 0 (not recorded) or 1.." +
                                std::to_string(kMaxCalibrationSensor) + ", got " +
                                std::to_string(sensor));
  }
  if (!chain.volume().has_value()) {
    throw std::invalid_argument("calibration: the calibrated volume is not set");
  }
  chain.volume()->Check();
  CheckFiniteInVolume(chain, *chain.volume(), "calibration", "$.corrections");
  CheckProvenance(provenance);
  if (!fit_statistics.is_object()) {
    throw std::invalid_argument("calibration: fit_statistics must be a JSON object");
  }
  CheckJsonNumbersFinite(fit_statistics, "calibration", "$.fit_statistics");
}

const CalibratedVolume& Calibration::volume() const {
  if (!chain.volume().has_value()) {
    throw std::invalid_argument("calibration: the calibrated volume is not set");
  }
  return *chain.volume();
}

namespace {

Calibration ParseCalibrationJsonAtPaths(const std::string& text, const std::string& source_name) {
  nlohmann::json doc;
  try {
    doc = ParseJsonText(text, source_name);
  } catch (const JsonInputError& e) {
    // Notepad's "Unicode" (UTF-16) save of a hand-edited file read as "invalid literal" and "not a
    // calibration file"; JSON is UTF-8.
    const std::string utf16 = Utf16TextProblem(text, "calibration file");
    if (!utf16.empty()) throw JsonInputError(source_name + ": " + utf16);
    // A file that is not JSON at all (a model file's YAML, a capture's CSV given as the
    // calibration) got only the JSON parser's "invalid literal; last read: 'te'": say what a
    // calibration file is.
    size_t first = text.rfind("\xEF\xBB\xBF", 0) == 0 ? 3 : 0;
    first = text.find_first_not_of(" \t\r\n", first);
    // An empty file (a save interrupted, a file created but never written) got the parser's
    // "syntax error while parsing value - unexpected end of input" at its last line.
    if (first == std::string::npos) {
      throw JsonInputError(source_name + ": empty file" +
                           (text.empty() ? "" : " (only white space)") +
                           "; a calibration file is the JSON document that trackcal fit -o or "
                           "trackcal-fit fit -o writes");
    }
    if (text[first] == '{' || text[first] == '[') {
      throw;
    }
    throw JsonInputError(std::string(e.what()) +
                         " (not a calibration file: a calibration file is the JSON document "
                         "that trackcal fit -o or trackcal-fit fit -o writes, starting with '{'; "
                         "is this a model file or a capture?)");
  }
  const JsonObjectReader root(doc, source_name, "$");
  const std::string format = root.String("format");
  if (format != kCalibrationFormat) {
    root.Fail("format", "unknown format \"" + format + "\"; expected \"" + kCalibrationFormat +
                            "\"");
  }
  const int version = root.Integer("version");
  if (version != kCalibrationVersion) {
    root.Fail("version", "unsupported version " + std::to_string(version) +
                             "; this reader supports version " +
                             std::to_string(kCalibrationVersion));
  }
  Calibration cal;
  if (root.Has("description")) cal.description = root.String("description");
  // Optional (files before it do not have it): the receiver the file was fitted for.
  if (root.Has("sensor")) {
    cal.sensor = root.Integer("sensor");
    if (cal.sensor < 1 || cal.sensor > kMaxCalibrationSensor) {
      root.Fail("sensor", "expected the capture's sensor number (1.." +
                              std::to_string(kMaxCalibrationSensor) + "; Fastrak station n is " +
                              "sensor n), got " + std::to_string(cal.sensor));
    }
  }

  const JsonObjectReader units = root.Object("units");
  units.Enum("length", {kUnitsLength});
  units.CheckNoUnknownKeys();
  const JsonObjectReader frames = root.Object("frames");
  frames.Enum("pose", {kFramePose});
  frames.Enum("errors", {kFrameErrors});
  frames.CheckNoUnknownKeys();

  const CalibratedVolume volume = ParseVolume(root.Object("calibrated_volume"));

  const nlohmann::json& corrections = root.Get("corrections");
  if (!corrections.is_array()) root.Fail("corrections", "expected an array of corrections");
  const CorrectionRegistry& registry = CorrectionRegistry::Global();
  for (size_t i = 0; i < corrections.size(); ++i) {
    const std::string path = JsonIndexPath(root.PathOf("corrections"), i);
    try {
      cal.chain.Append(registry.Parse(corrections[i], source_name, path));
    } catch (const JsonInputError&) {
      throw;
    } catch (const std::invalid_argument& e) {
      // A constructor's own check: still say where.
      ThrowJsonError(source_name, path, e.what());
    }
  }
  cal.chain.SetVolume(volume);
  CheckFiniteInVolume(cal.chain, volume, source_name, root.PathOf("corrections"));

  cal.fit_statistics = root.Get("fit_statistics");
  if (!cal.fit_statistics.is_object()) root.Fail("fit_statistics", "expected an object");
  CheckJsonNumbersFinite(cal.fit_statistics, source_name, root.PathOf("fit_statistics"));

  cal.provenance = ParseProvenance(root.Object("provenance"));
  root.CheckNoUnknownKeys();
  return cal;
}

}  // namespace

Calibration ParseCalibrationJson(const std::string& text, const std::string& source_name) {
  // A JSON path alone ("$.corrections[1].position_error[417][2]") made a hand editor count
  // entries; the line and column take an editor there, as for a syntax error.
  return LocateJsonErrors(text, [&] { return ParseCalibrationJsonAtPaths(text, source_name); });
}

Calibration ReadCalibrationFile(const std::filesystem::path& path) {
  return ParseCalibrationJson(ReadFileToString(path), path.string());
}

nlohmann::json CalibrationToJson(const Calibration& calibration) {
  calibration.Check();
  const CalibratedVolume& v = calibration.volume();
  nlohmann::json doc;
  doc["format"] = kCalibrationFormat;
  doc["version"] = kCalibrationVersion;
  if (!calibration.description.empty()) doc["description"] = calibration.description;
  if (calibration.sensor != 0) doc["sensor"] = calibration.sensor;
  doc["units"] = {{"length", kUnitsLength}};
  doc["frames"] = {{"pose", kFramePose}, {"errors", kFrameErrors}};
  doc["calibrated_volume"] = {{"min", {v.min.x(), v.min.y(), v.min.z()}},
                              {"max", {v.max.x(), v.max.y(), v.max.z()}},
                              {"extrapolation", ExtrapolationPolicyName(v.extrapolation)},
                              {"fade_distance", v.fade_distance}};
  // Only where it is used (files of the other policies stay as they were).
  if (v.extrapolation == ExtrapolationPolicy::kLinear) {
    doc["calibrated_volume"]["linear_reach"] = v.linear_reach;
  }
  nlohmann::json corrections = nlohmann::json::array();
  for (size_t i = 0; i < calibration.chain.size(); ++i) {
    corrections.push_back(calibration.chain.term(i).ToJson());
  }
  doc["corrections"] = std::move(corrections);
  doc["fit_statistics"] = calibration.fit_statistics;
  const Provenance& p = calibration.provenance;
  nlohmann::json inputs = nlohmann::json::array();
  for (const CalibrationInput& in : p.inputs) {
    inputs.push_back({{"path", in.path}, {"sha256", in.sha256}, {"role", in.role}});
  }
  doc["provenance"] = {{"tool", p.tool},
                       {"tool_version", p.tool_version},
                       {"created_utc", p.created_utc.empty() ? CurrentUtcTimestamp() : p.created_utc},
                       {"inputs", std::move(inputs)}};
  if (!p.command_line.empty()) doc["provenance"]["command_line"] = p.command_line;
  return doc;
}

std::string CalibrationToJsonText(const Calibration& calibration) {
  return FormatJsonCompactArrays(CalibrationToJson(calibration), CalibrationKeyOrder()) + "\n";
}

void WriteCalibrationFile(const std::filesystem::path& path, const Calibration& calibration) {
  // Serialise first: a calibration that cannot be written must not touch the disk.
  const std::string text = CalibrationToJsonText(calibration);
  std::error_code ec;
  const bool exists = std::filesystem::exists(path, ec);
  if (exists && std::filesystem::is_directory(path, ec)) {
    CheckCalibrationOutput(path);  // names it a folder before the inputs' checks read it
  }
  for (const CalibrationInput& input : calibration.provenance.inputs) {
    const std::filesystem::path input_path(input.path);
    bool same = std::filesystem::weakly_canonical(path, ec) ==
                std::filesystem::weakly_canonical(input_path, ec);
    if (!same && exists && std::filesystem::exists(input_path, ec)) {
      same = std::filesystem::equivalent(path, input_path, ec);
    }
    if (same) {
      throw std::invalid_argument(path.string() + ": refusing to overwrite input file \"" +
                                  input.path + "\" (" + input.role + ")");
    }
  }
  if (exists) {
    // The target may be an input recorded under another path (a copy, another working directory).
    const std::string digest = Sha256HexOfFile(path);
    for (const CalibrationInput& input : calibration.provenance.inputs) {
      if (input.sha256 == digest) {
        throw std::invalid_argument(path.string() +
                                    ": refusing to overwrite a file whose contents are input \"" +
                                    input.path + "\" (same SHA-256)");
      }
    }
  }
  CheckCalibrationOutput(path);
  WriteFileAtomically(path, text);
}

void CheckCalibrationOutput(const std::filesystem::path& path) {
  std::error_code ec;
  const std::filesystem::path folder =
      path.parent_path().empty() ? std::filesystem::path(".") : path.parent_path();
  if (!std::filesystem::is_directory(folder, ec)) {
    throw std::invalid_argument(path.string() + ": cannot write here: the folder " +
                                folder.string() + " does not exist");
  }
  // The temporary file is made in the folder of the file written (through a link, the link's
  // target's): a folder the user may not write in failed only after the fit, its result lost.
  // access() is right here, unlike for the read-only file below: root may write in any folder,
  // except on a read-only mount, which access() reports too.
  std::filesystem::path written = path;
  if (std::filesystem::is_symlink(std::filesystem::symlink_status(path, ec))) {
    written = std::filesystem::weakly_canonical(path, ec);
  }
  const std::filesystem::path written_folder =
      written.parent_path().empty() ? std::filesystem::path(".") : written.parent_path();
  if (::access(written_folder.c_str(), W_OK | X_OK) != 0) {
    const int error = errno;
    throw std::invalid_argument(path.string() + ": cannot write here: the folder " +
                                written_folder.string() + " is not writable (" +
                                SystemErrorText(error) + ")");
  }
  if (!std::filesystem::exists(path, ec)) return;
  if (std::filesystem::is_directory(path, ec)) {
    throw std::invalid_argument(path.string() + ": is a folder; give a file name");
  }
  // A calibration made read-only (chmod a-w, to keep it) was replaced all the same: a rename needs
  // only the folder to be writable. Decided on the mode, not access(), which lets root write all.
  const std::filesystem::perms perms = std::filesystem::status(path, ec).permissions();
  if (!ec && (perms & (std::filesystem::perms::owner_write | std::filesystem::perms::group_write |
                       std::filesystem::perms::others_write)) == std::filesystem::perms::none) {
    throw std::invalid_argument(path.string() +
                                ": is read-only; refusing to replace it (make it writable to "
                                "replace it, or write the calibration to another file)");
  }
  bool is_calibration = false;
  try {
    const nlohmann::json existing = nlohmann::json::parse(ReadFileToString(path));
    is_calibration = existing.is_object() && existing.value("format", "") == kCalibrationFormat;
  } catch (const std::exception&) {
    is_calibration = false;
  }
  if (!is_calibration) {
    throw std::invalid_argument(path.string() +
                                ": refusing to overwrite an existing file that is not a "
                                "trackcal calibration file");
  }
}

Provenance ParseProvenanceJson(const nlohmann::json& value, const std::string& source,
                               const std::string& path) {
  return ParseProvenance(JsonObjectReader(value, source, path));
}

std::string CurrentUtcTimestamp() {
  const std::time_t now = std::time(nullptr);
  std::tm tm{};
  gmtime_r(&now, &tm);
  char buf[32];
  std::strftime(buf, sizeof(buf), "%Y-%m-%dT%H:%M:%SZ", &tm);
  return buf;
}

std::string FormatJsonCompactArrays(const nlohmann::json& value,
                                    const std::vector<std::string>& key_order) {
  std::string out;
  Format(value, key_order, 0, &out);
  return out;
}

}  // namespace trackcal
