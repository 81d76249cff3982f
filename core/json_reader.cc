#include "core/json_reader.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <set>
#include <string_view>
#include <vector>

#include "core/printable_text.h"

namespace trackcal {

namespace {

const char* TypeName(const nlohmann::json& v) { return v.type_name(); }

// Where the parser is, for the JSON path of a repeated key: per open object its current key, per
// open array the index of its current element, and per object the keys seen so far.
struct OpenContainer {
  bool is_object = false;
  std::string key;
  size_t index = 0;
  std::set<std::string> keys;
};

constexpr size_t kMaxJsonDepth = 64;

std::string PathOfOpen(const std::vector<OpenContainer>& open) {
  std::string path = "$";
  for (size_t i = 0; i + 1 < open.size(); ++i) {
    path = open[i].is_object ? JsonKeyPath(path, open[i].key) : JsonIndexPath(path, open[i].index);
  }
  return path;
}

// Offset of `literal` as a whole number token outside strings, npos if none. A plain find took
// the first occurrence anywhere: in a key or a string ("1e999" in a description), or inside a
// longer number, which put the error on the wrong line.
size_t FindNumberLiteral(const std::string& text, const std::string& literal) {
  const auto is_number_char = [](char c) {
    return std::isdigit(static_cast<unsigned char>(c)) || c == '.' || c == 'e' || c == 'E' ||
           c == '+' || c == '-';
  };
  bool in_string = false;
  for (size_t i = 0; i < text.size(); ++i) {
    const char c = text[i];
    if (in_string) {
      if (c == '\\') {
        ++i;  // the escaped character
      } else if (c == '"') {
        in_string = false;
      }
    } else if (c == '"') {
      in_string = true;
    } else if (text.compare(i, literal.size(), literal) == 0 &&
               (i == 0 || !is_number_char(text[i - 1])) &&
               (i + literal.size() == text.size() || !is_number_char(text[i + literal.size()]))) {
      return i;
    }
  }
  return std::string::npos;
}

// nlohmann's parse_error text without its id and position: "[json.exception.parse_error.101]
// parse error at line 3, column 0: syntax error while parsing value - invalid literal; last
// read: 'tru'" -> "invalid literal; last read: 'tru'".
std::string WithoutParserPrefix(std::string what) {
  if (what.rfind("[json.exception.", 0) == 0) {
    if (const size_t id_end = what.find("] "); id_end != std::string::npos) {
      what.erase(0, id_end + 2);
    }
  }
  if (what.rfind("parse error", 0) == 0) {
    if (const size_t colon = what.find(": "); colon != std::string::npos) what.erase(0, colon + 2);
  }
  for (const std::string_view lead : {"syntax error while parsing ", "parse error: "}) {
    if (what.rfind(lead, 0) == 0) {
      const size_t dash = what.find(" - ");
      what.erase(0, dash == std::string::npos ? lead.size() : dash + 3);
    }
  }
  return what;
}

// A scanner for LocateJsonPath: it walks only the containers on the way to the target path and
// skips everything else, so a large LUT costs one pass over the text. It trusts nothing: on text
// that is not JSON (a parse stopped early by a key given twice) it stops and keeps what it found.
class PathLocator {
 public:
  PathLocator(const std::string& text, const std::string& target) : text_(text), target_(target) {}

  std::optional<size_t> Locate() {
    pos_ = text_.rfind("\xEF\xBB\xBF", 0) == 0 ? 3 : 0;  // the parser skips a UTF-8 BOM too
    SkipSpace();
    if (pos_ >= text_.size()) return std::nullopt;
    best_ = pos_;
    Descend("$", 0);
    return best_;
  }

 private:
  // True if `path` is `target_` or the start of it up to a segment boundary.
  bool OnTheWay(const std::string& path) const {
    return target_.compare(0, path.size(), path) == 0 &&
           (target_.size() == path.size() || target_[path.size()] == '.' ||
            target_[path.size()] == '[');
  }

  void SkipSpace() {
    while (pos_ < text_.size() && (text_[pos_] == ' ' || text_[pos_] == '\t' ||
                                   text_[pos_] == '\n' || text_[pos_] == '\r')) {
      ++pos_;
    }
  }

  // Moves past the string token at pos_ (the opening quote); false if there is none.
  bool SkipString() {
    if (pos_ >= text_.size() || text_[pos_] != '"') return false;
    for (++pos_; pos_ < text_.size(); ++pos_) {
      if (text_[pos_] == '\\') {
        ++pos_;
      } else if (text_[pos_] == '"') {
        ++pos_;
        return true;
      }
    }
    return false;
  }

  // The string token at pos_, decoded (a key may hold escapes); nullopt if it is not one.
  std::optional<std::string> ReadString() {
    const size_t start = pos_;
    if (!SkipString()) return std::nullopt;
    try {
      return nlohmann::json::parse(text_.substr(start, pos_ - start)).get<std::string>();
    } catch (const nlohmann::json::exception&) {
      return std::nullopt;
    }
  }

  // Skips the value at pos_; false if the text ends or is not JSON there.
  bool SkipValue() {
    if (pos_ >= text_.size()) return false;
    if (text_[pos_] == '"') return SkipString();
    if (text_[pos_] != '{' && text_[pos_] != '[') {
      while (pos_ < text_.size() &&
             std::string_view(",]} \t\r\n").find(text_[pos_]) == std::string_view::npos) {
        ++pos_;
      }
      return true;
    }
    size_t depth = 0;
    while (pos_ < text_.size()) {
      const char c = text_[pos_];
      if (c == '"') {
        if (!SkipString()) return false;
        continue;
      }
      ++pos_;
      if (c == '{' || c == '[') {
        ++depth;
      } else if ((c == '}' || c == ']') && --depth == 0) {
        return true;
      }
    }
    return false;
  }

  // At the value (pos_) of the element at `path`, which is on the way: looks inside it.
  void Descend(const std::string& path, size_t depth) {
    if (path.size() >= target_.size() || depth > kMaxJsonDepth) return;
    const bool object = text_[pos_] == '{';
    if (!object && text_[pos_] != '[') return;
    ++pos_;
    for (size_t index = 0;; ++index) {
      SkipSpace();
      if (pos_ >= text_.size() || text_[pos_] == '}' || text_[pos_] == ']') return;
      const size_t element_start = pos_;
      std::string child;
      if (object) {
        const std::optional<std::string> key = ReadString();
        if (!key) return;
        SkipSpace();
        if (pos_ >= text_.size() || text_[pos_] != ':') return;
        ++pos_;
        SkipSpace();
        child = JsonKeyPath(path, *key);
      } else {
        child = JsonIndexPath(path, index);
      }
      if (pos_ >= text_.size()) return;
      if (OnTheWay(child)) {
        best_ = element_start;
        const size_t value_start = pos_;
        Descend(child, depth + 1);
        // Of a key given twice, the last: keep looking in this object (the reader fails at the
        // second occurrence, and a document without repeats has only one).
        pos_ = value_start;
        if (!object) return;
      }
      if (!SkipValue()) return;
      SkipSpace();
      if (pos_ >= text_.size() || text_[pos_] != ',') return;
      ++pos_;
    }
  }

  const std::string& text_;
  const std::string& target_;
  size_t pos_ = 0;
  size_t best_ = 0;
};

}  // namespace

JsonInputError::JsonInputError(const std::string& source, const std::string& json_path,
                               const std::string& problem)
    : std::invalid_argument(source + ": " + json_path + ": " + problem),
      source_(source),
      json_path_(json_path),
      problem_(problem) {}

std::optional<JsonTextPosition> LocateJsonPath(const std::string& text,
                                               const std::string& json_path) {
  if (json_path.rfind('$', 0) != 0) return std::nullopt;
  const std::optional<size_t> offset = PathLocator(text, json_path).Locate();
  if (!offset) return std::nullopt;
  const size_t line_start = text.rfind('\n', *offset == 0 ? 0 : *offset - 1);
  JsonTextPosition at;
  at.line = 1 + static_cast<size_t>(std::count(text.begin(), text.begin() + *offset, '\n'));
  at.column = line_start == std::string::npos || *offset == 0 ? *offset + 1 : *offset - line_start;
  return at;
}

nlohmann::json ParseJsonText(const std::string& text, const std::string& source_name) {
  // nlohmann keeps the last of two values of a key: a key given twice (a hand edit that added a
  // field instead of changing it) is an error, as in the model file, not a silent choice.
  std::vector<OpenContainer> open;
  const auto element_done = [&open] {
    if (!open.empty() && !open.back().is_object) ++open.back().index;
  };
  const nlohmann::json::parser_callback_t check_keys =
      [&](int /*depth*/, nlohmann::json::parse_event_t event, nlohmann::json& parsed) {
        using Event = nlohmann::json::parse_event_t;
        switch (event) {
          case Event::object_start:
          case Event::array_start:
            open.push_back({event == Event::object_start, "", 0, {}});
            // The readers walk documents recursively (each level copying its path): a document
            // nested thousands deep would exhaust the stack. Ours are a few levels deep.
            if (open.size() > kMaxJsonDepth) {
              ThrowJsonError(source_name, PathOfOpen(open),
                             "nested more than " + std::to_string(kMaxJsonDepth) + " levels deep");
            }
            break;
          case Event::key: {
            OpenContainer& object = open.back();
            object.key = parsed.get<std::string>();
            if (!object.keys.insert(object.key).second) {
              ThrowJsonError(source_name, JsonKeyPath(PathOfOpen(open), object.key),
                             "given twice (a key may appear once per object)");
            }
            break;
          }
          case Event::object_end:
          case Event::array_end:
            open.pop_back();
            element_done();
            break;
          case Event::value:
            element_done();
            break;
        }
        return true;
      };
  try {
    return nlohmann::json::parse(text, check_keys);
  } catch (const nlohmann::json::parse_error& e) {
    // e.byte is the 1-based position of the offending byte; turn it into line and column.
    const size_t byte = e.byte == 0 ? 0 : std::min<size_t>(e.byte - 1, text.size());
    size_t line = 1, column = 1;
    for (size_t i = 0; i < byte && i < text.size(); ++i) {
      if (text[i] == '\n') {
        ++line;
        column = 1;
      } else {
        ++column;
      }
    }
    // The word that failed, to recognise NaN / Infinity. The whole word: a prefix test called an
    // unquoted string such as `info` or `nanometre` a non-finite number.
    const auto is_alpha = [&text](size_t i) {
      return i < text.size() && std::isalpha(static_cast<unsigned char>(text[i]));
    };
    size_t token_start = byte;
    while (token_start > 0 && is_alpha(token_start - 1)) --token_start;
    size_t token_end = token_start;
    while (is_alpha(token_end)) ++token_end;
    const std::string token = text.substr(token_start, token_end - token_start);
    // The parser quotes what it last read: a byte that is not UTF-8 (a Latin-1 description) came
    // through raw, and the message failed in Python as it became a str, naming no file.
    // Without nlohmann's prefix ("[json.exception.parse_error.101] parse error at line 1, column
    // 12: syntax error while parsing value - "): library jargon, and a second line:column that
    // disagrees with ours (the parser counts columns from 0 and puts an error at a line's end on
    // the next line).
    std::string what = PrintableForMessage(WithoutParserPrefix(e.what()));
    if (token == "NaN" || token == "Infinity" || token == "nan" || token == "inf" ||
        token == "infinity") {
      what = "non-finite number (NaN or Infinity) is not allowed";
    }
    throw JsonInputError(source_name + ":" + std::to_string(line) + ":" + std::to_string(column) +
                         ": invalid JSON: " + what);
  } catch (const nlohmann::json::out_of_range& e) {
    // Number overflow ("number overflow parsing '1e999'"): locate the literal for line and column.
    const std::string what = e.what();
    const size_t q0 = what.find('\'');
    const size_t q1 = q0 == std::string::npos ? q0 : what.find('\'', q0 + 1);
    std::string where = source_name;
    std::string literal;
    if (q1 != std::string::npos) {
      literal = what.substr(q0 + 1, q1 - q0 - 1);
      const size_t at = FindNumberLiteral(text, literal);
      if (at != std::string::npos) {
        const size_t line = 1 + static_cast<size_t>(std::count(text.begin(), text.begin() + at, '\n'));
        const size_t line_start = text.rfind('\n', at);
        const size_t column = line_start == std::string::npos ? at + 1 : at - line_start;
        where += ":" + std::to_string(line) + ":" + std::to_string(column);
      }
    }
    throw JsonInputError(where + ": invalid JSON: number " + literal +
                         " overflows a double; numbers must be finite");
  }
}

std::string JsonIndexPath(const std::string& path, size_t index) {
  return path + "[" + std::to_string(index) + "]";
}

std::string JsonKeyPath(const std::string& path, const std::string& key) {
  return path + "." + key;
}

void ThrowJsonError(const std::string& source, const std::string& path,
                    const std::string& message) {
  throw JsonInputError(source, path, message);
}

std::string JsonSnippet(const nlohmann::json& value) {
  std::string s = value.dump();
  if (s.size() > 40) s = s.substr(0, 37) + "...";
  return s;
}

double JsonFiniteNumber(const nlohmann::json& value, const std::string& source,
                        const std::string& path) {
  if (!value.is_number()) {
    ThrowJsonError(source, path,
                   std::string("expected a number, got ") + TypeName(value) + " " +
                       JsonSnippet(value));
  }
  const double v = value.get<double>();
  if (!std::isfinite(v)) {
    ThrowJsonError(source, path,
                   std::string("number must be finite, got ") +
                       (std::isnan(v) ? "NaN" : (v > 0 ? "Infinity" : "-Infinity")));
  }
  return v;
}

void CheckJsonNumbersFinite(const nlohmann::json& value, const std::string& source,
                            const std::string& path) {
  if (value.is_number()) {
    JsonFiniteNumber(value, source, path);
  } else if (value.is_array()) {
    for (size_t i = 0; i < value.size(); ++i) {
      CheckJsonNumbersFinite(value[i], source, JsonIndexPath(path, i));
    }
  } else if (value.is_object()) {
    for (const auto& [key, item] : value.items()) {
      CheckJsonNumbersFinite(item, source, JsonKeyPath(path, key));
    }
  }
}

JsonObjectReader::JsonObjectReader(const nlohmann::json& value, std::string source,
                                   std::string path)
    : value_(value), source_(std::move(source)), path_(std::move(path)) {
  if (!value_.is_object()) {
    ThrowJsonError(source_, path_,
                   std::string("expected an object, got ") + TypeName(value_) + " " +
                       JsonSnippet(value_));
  }
}

void JsonObjectReader::Fail(const std::string& key, const std::string& message) const {
  ThrowJsonError(source_, key.empty() ? path_ : PathOf(key), message);
}

bool JsonObjectReader::Has(const std::string& key) const {
  asked_keys_.insert(key);
  return value_.contains(key);
}

const nlohmann::json& JsonObjectReader::Get(const std::string& key) const {
  asked_keys_.insert(key);
  const auto it = value_.find(key);
  if (it == value_.end()) {
    // A key given and not read: the required one misspelt ("verison").
    for (const auto& [given, unused] : value_.items()) {
      if (read_keys_.count(given) == 0 && ClosestName(given, {key}) == key) {
        Fail(given, "unknown field; did you mean \"" + key + "\" (a required field)?");
      }
    }
    Fail(key, "missing required field");
  }
  read_keys_.insert(key);
  return *it;
}

JsonObjectReader JsonObjectReader::Object(const std::string& key) const {
  return JsonObjectReader(Get(key), source_, PathOf(key));
}

std::string JsonObjectReader::String(const std::string& key) const {
  const nlohmann::json& v = Get(key);
  if (!v.is_string()) {
    Fail(key, std::string("expected a string, got ") + TypeName(v) + " " + JsonSnippet(v));
  }
  return v.get<std::string>();
}

std::string JsonObjectReader::Enum(const std::string& key,
                                   const std::vector<std::string>& allowed) const {
  const std::string s = String(key);
  for (const auto& a : allowed) {
    if (s == a) return s;
  }
  std::string list;
  for (size_t i = 0; i < allowed.size(); ++i) list += (i ? ", \"" : "\"") + allowed[i] + "\"";
  Fail(key, "unknown value \"" + s + "\"; expected one of " + list);
}

double JsonObjectReader::Number(const std::string& key) const {
  return JsonFiniteNumber(Get(key), source_, PathOf(key));
}

double JsonObjectReader::PositiveNumber(const std::string& key) const {
  const double v = Number(key);
  if (!(v > 0.0)) Fail(key, "must be positive, got " + Get(key).dump());
  return v;
}

int JsonObjectReader::Integer(const std::string& key) const {
  const nlohmann::json& v = Get(key);
  if (!v.is_number_integer()) {
    Fail(key, std::string("expected an integer, got ") + TypeName(v) + " " + JsonSnippet(v));
  }
  // An unsigned literal above INT64_MAX would wrap to a negative int64_t (2^64 - 1 reads as -1).
  const bool above_int64 =
      v.is_number_unsigned() &&
      v.get<uint64_t>() > static_cast<uint64_t>(std::numeric_limits<int64_t>::max());
  const int64_t i = above_int64 ? std::numeric_limits<int64_t>::max() : v.get<int64_t>();
  if (i < std::numeric_limits<int>::min() || i > std::numeric_limits<int>::max()) {
    Fail(key, "integer out of range: " + v.dump());
  }
  return static_cast<int>(i);
}

std::vector<double> JsonObjectReader::NumberArray(const std::string& key) const {
  const nlohmann::json& v = Get(key);
  if (!v.is_array()) {
    Fail(key, std::string("expected an array of numbers, got ") + TypeName(v) + " " +
                  JsonSnippet(v));
  }
  std::vector<double> out;
  out.reserve(v.size());
  for (size_t i = 0; i < v.size(); ++i) {
    out.push_back(JsonFiniteNumber(v[i], source_, JsonIndexPath(PathOf(key), i)));
  }
  return out;
}

Eigen::Vector3d JsonObjectReader::Vector3(const std::string& key) const {
  const std::vector<double> v = NumberArray(key);
  if (v.size() != 3) Fail(key, "expected 3 numbers [x, y, z], got " + std::to_string(v.size()));
  return Eigen::Vector3d(v[0], v[1], v[2]);
}

std::vector<double> JsonObjectReader::Vector3Array(const std::string& key, size_t expected_count,
                                                   const std::string& what) const {
  const nlohmann::json& v = Get(key);
  if (!v.is_array()) {
    Fail(key, std::string("expected an array of [x, y, z] entries, got ") + TypeName(v) + " " +
                  JsonSnippet(v));
  }
  if (v.size() != expected_count) {
    Fail(key, what + " needs " + std::to_string(expected_count) + " entries, got " +
                  std::to_string(v.size()));
  }
  std::vector<double> out;
  out.reserve(3 * v.size());
  for (size_t i = 0; i < v.size(); ++i) {
    const std::string item_path = JsonIndexPath(PathOf(key), i);
    if (!v[i].is_array() || v[i].size() != 3) {
      ThrowJsonError(source_, item_path, "expected 3 numbers [x, y, z], got " + JsonSnippet(v[i]));
    }
    for (size_t k = 0; k < 3; ++k) {
      out.push_back(JsonFiniteNumber(v[i][k], source_, JsonIndexPath(item_path, k)));
    }
  }
  return out;
}

void JsonObjectReader::CheckNoUnknownKeys() const {
  for (const auto& [key, unused] : value_.items()) {
    if (read_keys_.count(key) != 0) continue;
    std::vector<std::string> absent;
    for (const std::string& known : asked_keys_) {
      if (!value_.contains(known)) absent.push_back(known);
    }
    const std::string meant = ClosestName(key, absent);
    Fail(key, "unknown field" + (meant.empty() ? "" : "; did you mean \"" + meant + "\"?"));
  }
}

}  // namespace trackcal
