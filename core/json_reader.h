// Strict reading of JSON documents with errors that name the source and the JSON path of the problem,
// e.g. "calib.json: $.corrections[0].degree: expected an integer, got \"four\"". Every object read
// through a JsonObjectReader must have all its keys consumed; CheckNoUnknownKeys() names the first
// key nobody read, so a misspelt optional field is an error instead of being silently ignored.
#pragma once

#include <Eigen/Core>
#include <cstddef>
#include <nlohmann/json.hpp>
#include <optional>
#include <set>
#include <stdexcept>
#include <string>
#include <vector>

namespace trackcal {

// Thrown for malformed user input; derives from std::invalid_argument so Python sees ValueError.
class JsonInputError : public std::invalid_argument {
 public:
  using std::invalid_argument::invalid_argument;
  // An error at a JSON path (ThrowJsonError): "<source>: <json_path>: <problem>", with its parts
  // kept so that a reader holding the text can say where the path is (LocateJsonErrors).
  JsonInputError(const std::string& source, const std::string& json_path,
                 const std::string& problem);

  // Empty for an error that is not at a JSON path (a syntax error, which has its line already).
  const std::string& source() const { return source_; }
  const std::string& json_path() const { return json_path_; }
  const std::string& problem() const { return problem_; }

 private:
  std::string source_;
  std::string json_path_;
  std::string problem_;
};

// Parses JSON text; a syntax error names the source, line and column. NaN/Infinity literals are
// reported as such (they are not JSON, but Python's json module writes them). A key given twice in
// one object is an error naming its JSON path (the parser alone would keep the last value), and so
// is nesting deeper than 64 objects and arrays (the recursive checks would exhaust the stack).
nlohmann::json ParseJsonText(const std::string& text, const std::string& source_name);

// Where the element at `json_path` (as the readers write paths: "$.corrections[1].axes.z[2]") is
// in `text`: 1-based line and byte column of its key for an object member, of its value for an
// array element or the root. For a path that does not exist (a missing field) the deepest element
// of it that does; of a key given twice, its last occurrence. nullopt if nothing of the path is
// found (text that is not JSON).
struct JsonTextPosition {
  size_t line = 0;
  size_t column = 0;
};
std::optional<JsonTextPosition> LocateJsonPath(const std::string& text,
                                               const std::string& json_path);

// Runs `read` (which parses `text`); a JsonInputError at a JSON path is rethrown with the path's
// line and column: "<source>:<line>:<column>: <json_path>: <problem>", as a syntax error and the
// model file's errors are, so that a hand editor can jump to it.
template <typename Read>
auto LocateJsonErrors(const std::string& text, Read&& read) -> decltype(read());

// "$.a.b" + "[3]" style path helpers.
std::string JsonIndexPath(const std::string& path, size_t index);
std::string JsonKeyPath(const std::string& path, const std::string& key);

// Throws JsonInputError("<source>: <path>: <message>").
[[noreturn]] void ThrowJsonError(const std::string& source, const std::string& path,
                                 const std::string& message);

// Short rendering of a JSON value for error messages (truncated).
std::string JsonSnippet(const nlohmann::json& value);

// A finite number at `path` (integers accepted); throws otherwise.
double JsonFiniteNumber(const nlohmann::json& value, const std::string& source,
                        const std::string& path);

// Checks that every number anywhere below `value` is finite (for free-form sections).
void CheckJsonNumbersFinite(const nlohmann::json& value, const std::string& source,
                            const std::string& path);

class JsonObjectReader {
 public:
  // Throws if `value` is not an object. `value` must outlive the reader.
  JsonObjectReader(const nlohmann::json& value, std::string source, std::string path);

  const std::string& source() const { return source_; }
  const std::string& path() const { return path_; }
  std::string PathOf(const std::string& key) const { return JsonKeyPath(path_, key); }

  // Error at this object (key empty) or at one of its keys.
  [[noreturn]] void Fail(const std::string& key, const std::string& message) const;

  // Whether the object holds `key`; the key is then one the object takes (for CheckNoUnknownKeys's
  // suggestion of the field a misspelt key meant).
  bool Has(const std::string& key) const;
  // The raw value of a required key (marks it read). Absent, the error is at a key of the object
  // that misspells it ("unknown field; did you mean \"key\" (a required field)?") if there is one.
  const nlohmann::json& Get(const std::string& key) const;
  JsonObjectReader Object(const std::string& key) const;
  std::string String(const std::string& key) const;
  // A string that must be one of `allowed`.
  std::string Enum(const std::string& key, const std::vector<std::string>& allowed) const;
  double Number(const std::string& key) const;
  double PositiveNumber(const std::string& key) const;
  int Integer(const std::string& key) const;
  Eigen::Vector3d Vector3(const std::string& key) const;
  std::vector<double> NumberArray(const std::string& key) const;
  // An array of `expected_count` 3-vectors, flattened; `what` explains the count in the error
  // ("degree 4 needs 35 entries").
  std::vector<double> Vector3Array(const std::string& key, size_t expected_count,
                                   const std::string& what) const;

  // Throws naming the first key that was never read, and the absent key asked for (Has, Get) that
  // it most likely misspells.
  void CheckNoUnknownKeys() const;

 private:
  const nlohmann::json& value_;
  std::string source_;
  std::string path_;
  mutable std::set<std::string> read_keys_;
  mutable std::set<std::string> asked_keys_;  // by Has() or Get(), present or not
};

template <typename Read>
auto LocateJsonErrors(const std::string& text, Read&& read) -> decltype(read()) {
  try {
    return read();
  } catch (const JsonInputError& e) {
    if (e.json_path().empty()) throw;
    const std::optional<JsonTextPosition> at = LocateJsonPath(text, e.json_path());
    if (!at) throw;
    throw JsonInputError(e.source() + ":" + std::to_string(at->line) + ":" +
                         std::to_string(at->column) + ": " + e.json_path() + ": " + e.problem());
  }
}

}  // namespace trackcal
