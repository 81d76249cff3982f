#include "fit/model_file.h"

#include <algorithm>
#include <cerrno>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <map>
#include <sstream>
#include <stdexcept>
#include <string_view>

#include "core/file_util.h"
#include "core/printable_text.h"
#include "fit/terms_physical.h"

namespace trackcal::fit {
namespace {

std::string MarkString(const std::string& source, const YAML::Mark& mark) {
  if (mark.is_null()) return source;
  return source + ":" + std::to_string(mark.line + 1) + ":" + std::to_string(mark.column + 1);
}

}  // namespace

YamlMapReader::YamlMapReader(YAML::Node node, std::string source, std::string path)
    : node_(std::move(node)), source_(std::move(source)), path_(std::move(path)) {
  if (!node_.IsMap()) {
    throw std::invalid_argument(MarkString(source_, node_.Mark()) + ": " + path_ +
                                ": expected a mapping");
  }
  // yaml-cpp keeps every duplicate and answers node[key] with the first, so a second `noise:` or
  // `terms:` would be dropped without a word.
  std::map<std::string, YAML::Mark> seen;
  for (const auto& item : node_) {
    if (!item.first.IsScalar()) continue;
    // yaml-cpp does not implement YAML 1.1 merge keys: `<<: *base` would be a key named "<<" and
    // the anchored keys would go missing (the error then blamed a missing `type`).
    if (item.first.Scalar() == "<<") {
      throw std::invalid_argument(MarkString(source_, item.first.Mark()) + ": " + path_ +
                                  ".<<: merge keys are not supported; write the keys out");
    }
    const auto [it, inserted] = seen.emplace(item.first.Scalar(), item.first.Mark());
    if (!inserted) {
      throw std::invalid_argument(MarkString(source_, item.first.Mark()) + ": " + path_ + "." +
                                  item.first.Scalar() + ": given twice (also at line " +
                                  std::to_string(it->second.line + 1) + ")");
    }
  }
}

void YamlMapReader::Fail(const std::string& key, const std::string& message) const {
  YAML::Mark mark = node_.Mark();
  std::string field = path_;
  if (!key.empty()) {
    field += "." + key;
    const YAML::Node value = node_[key];
    if (value.IsDefined()) mark = value.Mark();
    // An empty value's mark is wherever the next token starts (often the next line): name the key.
    if (value.IsDefined() && value.IsNull()) {
      for (const auto& item : node_) {
        if (item.first.IsScalar() && item.first.Scalar() == key) mark = item.first.Mark();
      }
    }
  }
  throw std::invalid_argument(MarkString(source_, mark) + ": " + field + ": " + message);
}

namespace {

// ", got '1,5'" for a scalar that is not the number asked for (a decimal comma, a unit after the
// number, "1_000"): the message named the field but not what it held. Empty for a list or a map.
std::string Got(const YAML::Node& value) {
  if (!value.IsScalar()) return "";
  const std::string& s = value.Scalar();
  return ", got '" + (s.size() > 40 ? s.substr(0, 37) + "..." : s) + "'" +
         (s.find(',') != std::string::npos ? " (write '.' as the decimal point)" : "");
}

}  // namespace

// A key written without a value (`degree:`, `noise: ~`) counts as given: its typed read fails,
// rather than the default standing in silently for a value the author forgot.
bool YamlMapReader::Has(const std::string& key) const {
  read_.insert(key);
  return node_[key].IsDefined();
}

void YamlMapReader::FailMissing(const std::string& key) const {
  // Keys given and not read yet: one of them may be the required key misspelt.
  for (const auto& item : node_) {
    if (!item.first.IsScalar() || read_.count(item.first.Scalar())) continue;
    if (ClosestName(item.first.Scalar(), {key}) == key) {
      throw std::invalid_argument(MarkString(source_, item.first.Mark()) + ": " + path_ + "." +
                                  item.first.Scalar() + ": unknown key; did you mean '" + key +
                                  "' (a required field)?");
    }
  }
  Fail(key, "missing required field");
}

YAML::Node YamlMapReader::Get(const std::string& key) const {
  read_.insert(key);
  const YAML::Node value = node_[key];
  if (!value.IsDefined()) FailMissing(key);
  if (value.IsNull()) Fail(key, "no value given (write one, or leave the key out for the default)");
  return value;
}

double YamlMapReader::GetDouble(const std::string& key) const {
  const YAML::Node value = Get(key);
  double out = 0.0;
  if (!value.IsScalar() || !YAML::convert<double>::decode(value, out) || !std::isfinite(out)) {
    Fail(key, "expected a finite number" + Got(value));
  }
  return out;
}

double YamlMapReader::GetDoubleOr(const std::string& key, double fallback) const {
  return Has(key) ? GetDouble(key) : fallback;
}

int YamlMapReader::GetInt(const std::string& key) const {
  const YAML::Node value = Get(key);
  int out = 0;
  if (!value.IsScalar() || !YAML::convert<int>::decode(value, out)) {
    Fail(key, "expected an integer" + Got(value));
  }
  return out;
}

int YamlMapReader::GetIntOr(const std::string& key, int fallback) const {
  return Has(key) ? GetInt(key) : fallback;
}

bool YamlMapReader::GetBoolOr(const std::string& key, bool fallback) const {
  if (!Has(key)) return fallback;
  const YAML::Node value = Get(key);
  bool out = false;
  if (!value.IsScalar() || !YAML::convert<bool>::decode(value, out)) {
    Fail(key, "expected true or false");
  }
  return out;
}

std::string YamlMapReader::GetString(const std::string& key) const {
  const YAML::Node value = Get(key);
  if (!value.IsScalar()) Fail(key, "expected a string");
  return value.Scalar();
}

std::string YamlMapReader::GetStringOr(const std::string& key, const std::string& fallback) const {
  return Has(key) ? GetString(key) : fallback;
}

std::vector<double> YamlMapReader::GetDoubleList(const std::string& key) const {
  const YAML::Node value = Get(key);
  std::vector<double> out;
  auto decode = [&](const YAML::Node& item) {
    double v = 0.0;
    if (!item.IsScalar() || !YAML::convert<double>::decode(item, v) || !std::isfinite(v)) {
      Fail(key, "expected a finite number or a list of finite numbers" + Got(item));
    }
    out.push_back(v);
  };
  if (value.IsSequence()) {
    for (const auto& item : value) decode(item);
  } else {
    decode(value);
  }
  return out;
}

YamlMapReader YamlMapReader::GetMap(const std::string& key) const {
  const YAML::Node value = Get(key);
  if (!value.IsMap()) Fail(key, "expected a mapping");
  return YamlMapReader(value, source_, path_ + "." + key);
}

void YamlMapReader::Finish() const {
  for (const auto& item : node_) {
    // `? [a, b]`: its Scalar() is "", which read as "$.: unknown key".
    if (!item.first.IsScalar()) {
      throw std::invalid_argument(MarkString(source_, item.first.Mark()) + ": " + path_ +
                                  ": a key must be a plain name, not a list or mapping");
    }
    const std::string key = item.first.Scalar();
    if (!read_.count(key)) {
      // The keys this mapping takes that it does not hold: a misspelt key meant one of them.
      std::vector<std::string> absent;
      for (const std::string& known : read_) {
        if (!node_[known].IsDefined()) absent.push_back(known);
      }
      const std::string meant = ClosestName(key, absent);
      throw std::invalid_argument(MarkString(source_, item.first.Mark()) + ": " + path_ + "." +
                                  key + ": unknown key" +
                                  (meant.empty() ? "" : "; did you mean '" + meant + "'?"));
    }
  }
}

// --- registry -------------------------------------------------------------------------------

void RegisterBuiltinTerms(TermRegistry* registry);  // fit/terms_builtin.cc

TermRegistry& TermRegistry::Global() {
  static TermRegistry* registry = [] {
    auto* r = new TermRegistry();
    RegisterBuiltinTerms(r);
    return r;
  }();
  return *registry;
}

void TermRegistry::Register(const std::string& type, TermFactory factory) {
  std::lock_guard<std::mutex> lock(mutex_);
  if (type.empty()) throw std::invalid_argument("TermRegistry: empty term type");
  for (const auto& [name, f] : factories_) {
    if (name == type) throw std::invalid_argument("TermRegistry: term type '" + type + "' taken");
  }
  factories_.emplace_back(type, std::move(factory));
}

bool TermRegistry::Contains(const std::string& type) const {
  std::lock_guard<std::mutex> lock(mutex_);
  return std::any_of(factories_.begin(), factories_.end(),
                     [&](const auto& f) { return f.first == type; });
}

std::vector<std::string> TermRegistry::Types() const {
  std::lock_guard<std::mutex> lock(mutex_);
  std::vector<std::string> out;
  for (const auto& f : factories_) out.push_back(f.first);
  return out;
}

std::unique_ptr<ModelTerm> TermRegistry::Create(const std::string& type,
                                                const YamlMapReader& reader) const {
  TermFactory factory;
  {
    std::lock_guard<std::mutex> lock(mutex_);
    for (const auto& f : factories_) {
      if (f.first == type) factory = f.second;
    }
  }
  if (!factory) {
    std::vector<std::string> types = Types();
    types.push_back("time_offset");
    std::string known;
    for (const auto& t : types) known += (known.empty() ? "" : ", ") + t;
    const std::string meant = ClosestName(type, types);
    reader.Fail("type", "unknown term type '" + type + "'" +
                            (meant.empty() ? "" : "; did you mean '" + meant + "'?") +
                            " (known: " + known + ")");
  }
  return factory(reader);
}

// --- parser ---------------------------------------------------------------------------------

std::string LossTypeName(LossType type) {
  switch (type) {
    case LossType::kNone: return "none";
    case LossType::kHuber: return "huber";
    case LossType::kCauchy: return "cauchy";
  }
  return "none";
}

namespace {

std::vector<BlockSettings> ParseBlockSettings(const YamlMapReader& parameters) {
  std::vector<BlockSettings> out;
  for (const auto& item : parameters.node()) {
    // `[a]: {...}`: its Scalar() is "", which read as "parameters: missing required field".
    if (!item.first.IsScalar()) {
      throw std::invalid_argument(MarkString(parameters.source(), item.first.Mark()) + ": " +
                                  parameters.path() +
                                  ": a block name must be a plain name, not a list or mapping");
    }
    const std::string block = item.first.Scalar();
    const YamlMapReader r = parameters.GetMap(block);
    BlockSettings s;
    s.block = block;
    s.where = MarkString(r.source(), r.node().Mark()) + ": " + r.path();
    if (r.Has("value")) s.value = r.GetDoubleList("value");
    if (r.Has("fixed")) s.fixed = r.GetBoolOr("fixed", false);
    if (r.Has("lower")) s.lower = r.GetDoubleList("lower");
    if (r.Has("upper")) s.upper = r.GetDoubleList("upper");
    if (r.Has("prior")) {
      const YamlMapReader p = r.GetMap("prior");
      s.prior_mean = p.GetDoubleList("mean");
      s.prior_sigma = p.GetDoubleList("sigma");
      for (double sigma : *s.prior_sigma) {
        if (!(sigma > 0.0)) p.Fail("sigma", "must be > 0");
      }
      p.Finish();
    }
    r.Finish();
    out.push_back(std::move(s));
  }
  return out;
}

}  // namespace

void ApplyBlockSettings(const std::vector<BlockSettings>& settings, ModelTerm* term) {
  for (const BlockSettings& s : settings) {
    ParameterBlock* block = nullptr;
    std::string known;
    std::vector<ParameterBlock*> matched;
    for (auto& b : term->blocks()) {
      if (!s.term.empty() && b.term != s.term) continue;  // another effect of a physical group
      // "node_values" names every "node_values[...]" block of a LUT.
      const std::string family = b.name.substr(0, b.name.find('['));
      if (known.find(family) == std::string::npos) known += (known.empty() ? "" : ", ") + family;
      if (b.name == s.block || family == s.block) matched.push_back(&b);
    }
    if (!matched.empty()) block = matched.front();
    if (block == nullptr) {
      throw std::invalid_argument(s.where + ": term '" + (s.term.empty() ? term->name() : s.term) +
                                  "' has no parameter block '" + s.block + "' (blocks: " + known +
                                  ")");
    }
    for (ParameterBlock* target : matched) {
    block = target;
    const size_t n = block->values.size();
    auto expand = [&](const std::vector<double>& v, const char* field) {
      if (v.size() == 1) return std::vector<double>(n, v[0]);
      if (v.size() != n) {
        throw std::invalid_argument(s.where + "." + field + ": expected 1 or " +
                                    std::to_string(n) + " values, got " +
                                    std::to_string(v.size()));
      }
      return v;
    };
    if (s.value) block->values = expand(*s.value, "value");
    if (s.fixed) block->fixed = *s.fixed;
    if (s.lower) block->lower = expand(*s.lower, "lower");
    if (s.upper) block->upper = expand(*s.upper, "upper");
    if (s.prior_mean) {
      block->prior_mean = expand(*s.prior_mean, "prior.mean");
      block->prior_sigma = expand(*s.prior_sigma, "prior.sigma");
    }
    try {
      block->Check(term->name());
    } catch (const std::invalid_argument& e) {
      throw std::invalid_argument(s.where + ": " + e.what());
    }
    }
  }
}

namespace {

// settings_only: `trackcal-fit build`'s settings file (noise, solver, loss; no terms).
ModelSpec ParseModel(const std::string& text, const std::string& source_name, bool settings_only) {
  const char* const kind = settings_only ? "settings file" : "model file";
  // yaml-cpp reads UTF-16 (Notepad's "Unicode" save) as it reads UTF-8: the model was accepted
  // without a word, but its text (hashed into the calibration's provenance, returned by
  // trackcal.parse_model) is not the UTF-8 every other trackcal file is.
  const std::string utf16 = Utf16TextProblem(text, kind);
  if (!utf16.empty()) throw std::invalid_argument(source_name + ": " + utf16);
  // A binary file (an image, an archive, a workbook) given as the model: yaml-cpp stops at its
  // first NUL with "unknown escape character: " and a message cut at that NUL. No YAML text
  // holds a NUL.
  const size_t nul = text.find('\0');
  if (nul != std::string::npos) {
    const size_t line_start = text.rfind('\n', nul) + 1;  // npos + 1 == 0: the first line
    throw std::invalid_argument(
        source_name + ":" + std::to_string(std::count(text.begin(), text.begin() + nul, '\n') + 1) +
        ":" + std::to_string(nul - line_start + 1) + ": a NUL byte: not a text file; the " + kind +
        " is YAML text");
  }
  YAML::Node root;
  std::vector<YAML::Node> documents;
  try {
    documents = YAML::LoadAll(text);
  } catch (const YAML::Exception& e) {
    // A tab-indented file (an editor's default) got yaml-cpp's "illegal block entry" or "illegal
    // map value": name the line indented with a tab where the error is. yaml-cpp reports a tab
    // indent on that line itself; a tab-indented line before it is legal YAML (a flow list's or a
    // block scalar's continuation) and not the cause of a later error.
    std::string_view rest(text);
    for (int line = 1; !rest.empty() && (e.mark.is_null() || line <= e.mark.line + 1); ++line) {
      const std::string_view row = rest.substr(0, rest.find('\n'));
      const size_t content = row.find_first_not_of(" \t");
      const size_t tab = row.find('\t');
      if ((e.mark.is_null() || line == e.mark.line + 1) && content != std::string_view::npos &&
          tab < content && row[content] != '\r' && row[content] != '#') {
        throw std::invalid_argument(source_name + ":" + std::to_string(line) + ":" +
                                    std::to_string(tab + 1) +
                                    ": YAML syntax error: a tab in the indentation; YAML indents "
                                    "with spaces only (replace the tab with spaces)");
      }
      rest.remove_prefix(std::min(row.size() + 1, rest.size()));
    }
    throw std::invalid_argument(MarkString(source_name, e.mark) + ": YAML syntax error: " + e.msg);
  }
  if (!documents.empty()) root = documents.front();
  // YAML::Load reads the first document only: a model continued after a `---` lost its second part.
  for (size_t i = 1; i < documents.size(); ++i) {
    if (documents[i].IsNull()) continue;  // a trailing `---` with nothing after it
    throw std::invalid_argument(MarkString(source_name, documents[i].Mark()) +
                                ": a second YAML document (after ---); the model file holds one");
  }
  if (settings_only && root.IsNull()) {  // an empty settings file: every default
    ModelSpec defaults;
    defaults.source = source_name;
    return defaults;
  }
  if (!root.IsMap()) {
    // An empty or comment-only file has no line to name: say it has no entries. Anything else
    // (a list, a lone word) is named where it starts.
    throw std::invalid_argument(
        (root.IsNull() ? source_name + ": no entries (the file is empty or only comments); "
                       : MarkString(source_name, root.Mark()) + ": ") +
        (settings_only ? "the settings file must be a mapping (noise, solver, loss)"
                       : "the model file must be a mapping with 'terms'"));
  }
  const YamlMapReader top(root, source_name, "$");
  // Before anything else: a newer file's keys and term types are not the error to report.
  // Optional, 1 when absent (every model file written before it existed).
  if (top.Has("version")) {
    const int version = top.GetInt("version");
    if (version != kModelFileVersion) {
      top.Fail("version", "model file version " + std::to_string(version) +
                              "; this trackcal reads version " + std::to_string(kModelFileVersion) +
                              " (a newer file needs a newer trackcal)");
    }
  }
  ModelSpec spec;
  spec.source = source_name;
  if (top.Has("noise")) {
    const YamlMapReader noise = top.GetMap("noise");
    const double p = noise.GetDoubleOr("position_mm", spec.position_sigma * 1e3);
    const double o = noise.GetDoubleOr("orientation_deg", spec.orientation_sigma * 180.0 / M_PI);
    if (!(p > 0.0)) noise.Fail("position_mm", "must be > 0");
    if (!(o > 0.0)) noise.Fail("orientation_deg", "must be > 0");
    spec.position_sigma = p * 1e-3;
    spec.orientation_sigma = o * M_PI / 180.0;
    spec.position_range_exponent = noise.GetDoubleOr("position_range_exponent", 0.0);
    spec.orientation_range_exponent = noise.GetDoubleOr("orientation_range_exponent", 0.0);
    // An EM tracker's noise grows as r^4 (position) and r^3 (orientation); beyond 8 the weights
    // of a capture's near and far stations differ by more than double precision keeps apart.
    for (const char* key : {"position_range_exponent", "orientation_range_exponent"}) {
      const double e = std::string(key) == "position_range_exponent"
                           ? spec.position_range_exponent
                           : spec.orientation_range_exponent;
      if (!(e >= 0.0 && e <= 8.0)) noise.Fail(key, "must be 0 .. 8 (an EM tracker: 4 and 3)");
    }
    spec.noise_reference_range_m = noise.GetDoubleOr("reference_range_m", 1.0);
    // Ranges are clamped to 1 cm below (StationSigmas); a tracker reaches a few metres.
    if (!(spec.noise_reference_range_m >= 0.01 && spec.noise_reference_range_m <= 100.0)) {
      noise.Fail("reference_range_m", "must be 0.01 .. 100 [m]");
    }
    spec.amplification_threshold = noise.GetDoubleOr("amplification_threshold", 2.0);
    if (!(spec.amplification_threshold >= 1.0) || !std::isfinite(spec.amplification_threshold)) {
      noise.Fail("amplification_threshold", "must be finite and >= 1 (1e9: no pose metric)");
    }
    noise.Finish();
  }
  if (top.Has("loss")) {
    const YamlMapReader loss = top.GetMap("loss");
    const std::string type = loss.GetString("type");
    if (type == "none") {
      spec.loss.type = LossType::kNone;
    } else if (type == "huber") {
      spec.loss.type = LossType::kHuber;
    } else if (type == "cauchy") {
      spec.loss.type = LossType::kCauchy;
    } else {
      loss.Fail("type", "unknown loss '" + type + "' (known: none, huber, cauchy)");
    }
    spec.loss.scale = loss.GetDoubleOr("scale", spec.loss.scale);
    if (!(spec.loss.scale > 0.0)) loss.Fail("scale", "must be > 0");
    loss.Finish();
  }
  if (top.Has("solver")) {
    const YamlMapReader solver = top.GetMap("solver");
    spec.max_iterations = solver.GetIntOr("max_iterations", spec.max_iterations);
    if (spec.max_iterations < 1) solver.Fail("max_iterations", "must be >= 1");
    spec.function_tolerance = solver.GetDoubleOr("function_tolerance", spec.function_tolerance);
    if (!(spec.function_tolerance > 0.0)) solver.Fail("function_tolerance", "must be > 0");
    spec.statistical_tolerance =
        solver.GetDoubleOr("statistical_tolerance", spec.statistical_tolerance);
    if (!(spec.statistical_tolerance >= 0.0) || !std::isfinite(spec.statistical_tolerance)) {
      solver.Fail("statistical_tolerance", "must be a number >= 0");
    }
    spec.covariance = solver.GetBoolOr("covariance", spec.covariance);
    if (solver.Has("covariance_estimator")) {
      const std::string estimator = solver.GetString("covariance_estimator");
      if (estimator == "sandwich") {
        spec.covariance_estimator = CovarianceEstimator::kSandwich;
      } else if (estimator == "model") {
        spec.covariance_estimator = CovarianceEstimator::kModel;
      } else {
        solver.Fail("covariance_estimator",
                    "unknown estimator '" + estimator + "' (known: sandwich, model)");
      }
    }
    spec.leave_out_unresolved =
        solver.GetBoolOr("leave_out_unresolved", spec.leave_out_unresolved);
    spec.stream_clusters = solver.GetIntOr("stream_clusters", spec.stream_clusters);
    if (spec.stream_clusters != 0 && spec.stream_clusters < 8) {
      solver.Fail("stream_clusters",
                  "must be 0 (the model covariance for streams) or >= 8 (fewer clusters give a "
                  "sandwich too noisy to use)");
    }
    solver.Finish();
  }
  auto parse_time_offset = [&](const YamlMapReader& r) {
    TimeOffsetSpec t;
    t.value = r.GetDoubleOr("value", 0.0);
    t.fixed = r.GetBoolOr("fixed", true);
    t.search_range = r.GetDoubleOr("search_range", t.search_range);
    if (!(t.search_range > 0.0)) r.Fail("search_range", "must be > 0");
    if (spec.time_offset) r.Fail("", "time_offset given twice");
    spec.time_offset = t;
  };
  if (top.Has("time_offset")) {
    const YamlMapReader r = top.GetMap("time_offset");
    parse_time_offset(r);
    r.Finish();
  }

  const YAML::Node terms = root["terms"];
  top.MarkRead("terms");
  if (settings_only) {
    if (terms.IsDefined()) {
      top.Fail("terms", "build chooses the terms itself; give only noise, solver and loss");
    }
    top.Finish();
    return spec;
  }
  // A calibration file (JSON is YAML) given as the model said "$.terms: missing required field".
  const YAML::Node format = root["format"];
  if (!terms.IsDefined() && format.IsDefined() && format.IsScalar() &&
      format.Scalar() == "trackcal-calibration") {
    throw std::invalid_argument(
        source_name +
        ": a calibration file (format trackcal-calibration), not a model file: the model is the "
        "YAML file that lists the terms (docs/model-file.md); trackcal-fit fit --start takes a "
        "calibration to start from");
  }
  if (!terms.IsDefined() || !terms.IsSequence()) {
    if (!terms.IsDefined()) top.FailMissing("terms");
    top.Fail("terms", "expected a list of terms");
  }
  std::set<std::string> names;
  bool saw_explicit = false;  // physical terms must come before polynomial / LUT terms
  for (size_t i = 0; i < terms.size(); ++i) {
    const YamlMapReader r(terms[i], source_name, "$.terms[" + std::to_string(i) + "]");
    const std::string type = r.GetString("type");
    if (type == "time_offset") {
      parse_time_offset(r);
      r.Finish();
      continue;
    }
    std::unique_ptr<ModelTerm> term = TermRegistry::Global().Create(type, r);
    std::string name = r.GetStringOr("name", type);
    // Reports address blocks as NAME.BLOCK: an empty name would leave ".attenuation".
    if (name.empty()) r.Fail("name", "must not be empty");
    if (names.count(name)) {
      // Repeated types (several dipoles) are numbered unless named.
      if (r.Has("name")) r.Fail("name", "duplicate term name '" + name + "'");
      int k = 2;
      while (names.count(type + "_" + std::to_string(k))) ++k;
      name = type + "_" + std::to_string(k);
    }
    names.insert(name);
    term->set_name(name);
    std::vector<BlockSettings> settings;
    if (r.Has("parameters")) settings = ParseBlockSettings(r.GetMap("parameters"));
    r.Finish();
    const int line = terms[i].Mark().is_null() ? 0 : terms[i].Mark().line + 1;
    spec.file_terms.push_back({type, name, line, static_cast<int>(spec.terms.size()),
                               MarkString(source_name, terms[i].Mark()) + ": " + r.path()});
    // Consecutive physical terms form one forward field model: one PhysicalGroupTerm.
    if (auto* group = dynamic_cast<PhysicalGroupTerm*>(term.get())) {
      if (saw_explicit) {
        r.Fail("type", "physical term '" + type +
                           "' after an explicit term (polynomial, lut): physical terms must come "
                           "first, they correct the raw report");
      }
      group->SetEffectName(name, line);
      for (BlockSettings& setting : settings) {
        setting.term = name;
        std::string known;
        bool exists = false;
        for (const auto& b : group->blocks()) {
          known += (known.empty() ? "" : ", ") + b.name;
          exists = exists || b.name == setting.block;
        }
        if (!exists) {  // physical blocks exist before Prepare(): check them at once
          throw std::invalid_argument(setting.where + ": term '" + name +
                                      "' has no parameter block '" + setting.block +
                                      "' (blocks: " + known + ")");
        }
        if (setting.value) group->MarkStartGiven(name, setting.block);
      }
      // A searched block that is held fixed skips its search and keeps the placeholder start (a
      // dipole at [0, 0, 1], a plane's normal along z): fixed needs a start from the file.
      const PhysicalGroupTerm::Effect& effect = group->effects().front();
      for (const BlockSettings& setting : settings) {
        if (!setting.fixed.value_or(false) || setting.value) continue;
        const std::string& b = setting.block;
        const char* key = nullptr;
        if (effect.kind == PhysicalEffect::kDipole) {
          if (b == "location_in_transmitter" && effect.search_location)
            key = "location_in_transmitter";
          if (b == "polarisability_m3" && !effect.strength_given) key = "polarisability_m3";
        } else if (effect.kind == PhysicalEffect::kPlane) {
          if (b == "distance_m" && effect.search_plane) key = "point_in_transmitter";
          if (b == "normal_in_transmitter" && !effect.normal_given) key = "normal_in_transmitter";
          if (b == "attenuation" && !effect.strength_given) key = "attenuation";
        }
        if (key != nullptr) {
          throw std::invalid_argument(setting.where + ".fixed: term '" + name + "' block '" + b +
                                      "' is held fixed but has no start value (it would be "
                                      "searched): give " +
                                      key + " or a value");
        }
      }
      auto* previous =
          spec.terms.empty() ? nullptr : dynamic_cast<PhysicalGroupTerm*>(spec.terms.back().get());
      if (previous != nullptr) {
        try {
          previous->Absorb(std::move(*group));
        } catch (const std::invalid_argument& e) {
          r.Fail("type", e.what());
        }
        spec.file_terms.back().model_term = static_cast<int>(spec.terms.size()) - 1;
        for (BlockSettings& setting : settings) spec.block_settings.back().push_back(setting);
        continue;
      }
      std::string group_name = PhysicalGroupTerm::kType;
      while (names.count(group_name)) group_name += "_group";
      names.insert(group_name);
      term->set_name(group_name);
    } else {
      saw_explicit = true;
    }
    spec.terms.push_back(std::move(term));
    spec.block_settings.push_back(std::move(settings));
  }
  if (spec.terms.empty()) top.Fail("terms", "the model needs at least one correction term");
  top.Finish();
  return spec;
}

// ParseModel, its errors made printable: they quote the file (an unknown key, a value, a term
// type), and a Latin-1 key (`degr\xe9e`) or a NUL came through raw, cutting the message at the NUL
// and failing in Python as it became a str (UnicodeDecodeError naming no file).
ModelSpec ParseModelPrintably(const std::string& text, const std::string& source_name,
                              bool settings_only) {
  try {
    return ParseModel(text, source_name, settings_only);
  } catch (const std::invalid_argument& e) {
    std::string printable = PrintableForMessage(e.what());
    if (printable == e.what()) throw;
    throw std::invalid_argument(std::move(printable));
  }
}

}  // namespace

ModelSpec ParseModelYaml(const std::string& text, const std::string& source_name) {
  return ParseModelPrintably(text, source_name, /*settings_only=*/false);
}

ModelSpec ParseModelSettingsYaml(const std::string& text, const std::string& source_name) {
  return ParseModelPrintably(text, source_name, /*settings_only=*/true);
}

std::string ModelSettingsBlockYaml(const std::string& text, const std::string& source_name) {
  ParseModelSettingsYaml(text, source_name);
  const std::string probe = "\nterms:\n  - type: polynomial\n    degree: 0\n";
  try {
    ParseModelYaml(text + probe, source_name);
    return text;  // as written, comments and all
  } catch (const std::invalid_argument&) {
  }
  // Flow style (`{noise: ...}`, a JSON file) or document markers (`...`, a trailing `---`): the
  // terms appended after them were a second document or a syntax error. Written out in block style.
  YAML::Node root = YAML::LoadAll(text).front();
  root.SetStyle(YAML::EmitterStyle::Block);
  YAML::Emitter out;
  out << root;
  std::string block = std::string(out.c_str()) + "\n";
  ParseModelYaml(block + probe, source_name);
  return block;
}

Eigen::Vector2d ModelSpec::StationSigmas(const Rigid3d& reported) const {
  Eigen::Vector2d sigmas(position_sigma, orientation_sigma);
  if (position_range_exponent == 0.0 && orientation_range_exponent == 0.0) return sigmas;
  // A station at the transmitter would get zero noise: 1 cm is closer than any tracker works.
  const double range = std::max(reported.translation.norm(), 0.01) / noise_reference_range_m;
  sigmas[0] *= std::pow(range, position_range_exponent);
  sigmas[1] *= std::pow(range, orientation_range_exponent);
  return sigmas;
}

ModelSpec ReadModelFile(const std::filesystem::path& path) {
  // A folder opened as a stream and read as an empty model; "cannot open model file" gave no
  // reason (no such file, permission denied).
  std::error_code ec;
  if (std::filesystem::is_directory(path, ec)) {
    throw std::invalid_argument(path.string() + ": is a folder, not a model file");
  }
  errno = 0;
  std::ifstream in(path);
  if (!in) {
    throw std::invalid_argument(path.string() +
                                ": cannot open model file: " + SystemErrorText(errno));
  }
  std::stringstream buffer;
  buffer << in.rdbuf();
  if (in.bad()) throw std::invalid_argument(path.string() + ": read error");
  return ParseModelYaml(buffer.str(), path.string());
}

}  // namespace trackcal::fit
