#include "core/capture.h"

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <cctype>
#include <cerrno>
#include <charconv>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <iterator>
#include <limits>
#include <map>
#include <set>
#include <sstream>
#include <stdexcept>
#include <utility>

#include "core/file_util.h"
#include "core/printable_text.h"

namespace trackcal {

namespace {

std::string Trim(std::string_view s) {
  size_t b = 0;
  size_t e = s.size();
  while (b < e && (s[b] == ' ' || s[b] == '\t')) ++b;
  while (e > b && (s[e - 1] == ' ' || s[e - 1] == '\t' || s[e - 1] == '\r')) --e;
  return std::string(s.substr(b, e - b));
}

std::vector<std::string> Split(const std::string& line) {
  std::vector<std::string> out;
  size_t start = 0;
  while (true) {
    const size_t comma = line.find(',', start);
    out.push_back(Trim(std::string_view(line).substr(start, comma - start)));
    if (comma == std::string::npos) break;
    start = comma + 1;
  }
  return out;
}

// Whether a field reads as a number (nan and inf included: the caller decides what it accepts).
bool ParsesAsNumber(const std::string& s, double* value) {
  // from_chars takes no leading '+'; skip one, but not before a sign ("+-1" is no number).
  const char* begin = s.data() + (s.size() > 1 && s[0] == '+' && s[1] != '-' ? 1 : 0);
  const char* const last = s.data() + s.size();
  const auto [end, ec] = std::from_chars(begin, last, *value);
  if (s.empty() || end != last) return false;
  if (ec == std::errc()) return true;
  if (ec != std::errc::result_out_of_range) return false;
  // A number beyond a double's range ("1e999", "1e-400"): from_chars leaves the value unset, and
  // the field was called no number at all ("'1e999' is not a number"; in an extra column, a
  // label). Read it as strtod and Python do: infinite beyond the largest double (a standard column
  // then says "not a finite number"), zero below the smallest. Out of range, its magnitude is
  // beyond 1 exactly when its decimal exponent (of the first significant digit) is not negative.
  const bool negative = *begin == '-';
  const char* p = begin + (negative ? 1 : 0);
  long integer_digits = 0;  // of the mantissa before the point, leading zeros left out
  long fraction_zeros = 0;  // zeros after the point before the first significant digit
  bool significant = false, after_point = false;
  for (; p != last && *p != 'e' && *p != 'E'; ++p) {
    if (*p == '.') {
      after_point = true;
    } else if (!after_point) {
      if (*p != '0' || significant) ++integer_digits;
      significant |= *p != '0';
    } else if (!significant) {
      if (*p == '0') ++fraction_zeros;
      significant = *p != '0';
    }
  }
  const long exponent = integer_digits > 0 ? integer_digits - 1 : -(fraction_zeros + 1);
  long written = 0;  // the explicit exponent, saturated (it can have any number of digits)
  if (p != last) {
    ++p;
    const bool minus = *p == '-';
    if (*p == '-' || *p == '+') ++p;
    for (; p != last; ++p) written = std::min(written * 10 + (*p - '0'), 100000L);
    if (minus) written = -written;
  }
  const double magnitude =
      significant && exponent + written >= 0 ? std::numeric_limits<double>::infinity() : 0.0;
  *value = negative ? -magnitude : magnitude;
  return true;
}

// A field quoted for a message: '<field>', or its first 60 bytes and its length when it is longer
// than 80 (a file without its line ends, a corrupt export: a message quoted a field of megabytes in
// full).
std::string Quoted(const std::string& field) {
  constexpr size_t kLongest = 80;
  constexpr size_t kShown = 60;
  if (field.size() <= kLongest) return "'" + field + "'";
  size_t cut = kShown;  // not inside a UTF-8 character
  while (cut > 0 && (static_cast<unsigned char>(field[cut]) & 0xC0) == 0x80) --cut;
  return "'" + field.substr(0, cut) + "...' (a field of " + std::to_string(field.size()) +
         " bytes)";
}

// A missing extra value: an empty field or nan.
bool IsMissing(const std::string& s) {
  double value = 0;
  return s.empty() || (ParsesAsNumber(s, &value) && std::isnan(value));
}

// A parsed CSV file with named columns: the standard ones and the extras.
class CsvTable {
 public:
  // Errors name the file as the user gave it (folder included: "capA/poses.csv:3: ..." tells two
  // captures' poses.csv apart).
  CsvTable(const std::filesystem::path& path, const std::vector<std::string>& required)
      : name_(path.string()) {
    // A folder opens as a stream on Linux and then fails to read with a library message that names
    // no file ("basic_filebuf::underflow error reading the file: Is a directory"): say which path
    // (a capture folder given where its file was meant, `--markers DIR`).
    std::error_code ec;
    if (std::filesystem::is_directory(path, ec)) {
      throw std::runtime_error(path.string() + ": is a folder, not a CSV file");
    }
    // "cannot open file" alone left the user to guess why (no such file, permission denied).
    errno = 0;
    std::ifstream file(path, std::ios::binary);
    if (!file) {
      throw std::runtime_error(path.string() + ": cannot open file: " + SystemErrorText(errno));
    }
    std::string text;
    try {
      text.assign(std::istreambuf_iterator<char>(file), std::istreambuf_iterator<char>());
    } catch (const std::exception& e) {
      throw std::runtime_error(path.string() + ": cannot read file: " + e.what());
    }
    if (file.bad()) throw std::runtime_error(path.string() + ": cannot read file");
    // Excel's "Unicode text" save: every other byte of the header was NUL and the message said
    // "column station: missing from the header".
    const std::string utf16 = Utf16TextProblem(text, "CSV file");
    if (!utf16.empty()) Fail(1, "encoding", utf16);
    // A UTF-8 byte order mark (spreadsheet exports) opens the file, not the header line: removed
    // from the line it sat on, a blank line after it was read as a header whose one column had no
    // name.
    if (text.rfind("\xEF\xBB\xBF", 0) == 0) text.erase(0, 3);
    // Old Mac spreadsheets end lines with CR alone: read as lines, not as one header line whose
    // "columns" repeat.
    if (text.find('\n') == std::string::npos) std::replace(text.begin(), text.end(), '\r', '\n');
    // Where a control byte first is (not a tab or a line end): no text CSV holds one.
    const auto control = [](std::string_view s) {
      return static_cast<size_t>(std::find_if(s.begin(), s.end(),
                                              [](char c) {
                                                return static_cast<unsigned char>(c) < 0x20 &&
                                                       c != '\t' && c != '\r' && c != '\n';
                                              }) -
                                 s.begin());
    };
    const std::string head = text.substr(0, 1024);
    // Three bytes more than the head: a UTF-8 character the head's end cuts is no error.
    const std::string text_start = text.substr(0, head.size() + 3);
    std::istringstream in(std::move(text));
    std::string line;
    int line_number = 0;
    bool have_header = false;
    while (std::getline(in, line)) {
      ++line_number;
      // A binary file given as the capture (an .xlsx workbook, an image, an archive renamed
      // .csv): a CR among its bytes was called "mixed line ends", or its header "missing" a column.
      // Its header holds a control byte (a NUL, UTF-16 without a byte order mark), or bytes that
      // are not UTF-8 with a NUL soon after (a PNG's signature). A legacy code page's header
      // (Latin-1 "temp_\xb0C") is no binary file, even with a form feed or a DOS end-of-file
      // byte further on: it is read as before.
      if (!have_header && !Trim(line).empty()) {
        const size_t control_at = control(line);
        const size_t non_utf8_at = FirstNonUtf8Byte(line);
        const size_t at = std::min(control_at, std::min(non_utf8_at, line.size()));
        if (control_at < line.size() ||
            (non_utf8_at != std::string::npos && head.find('\0') != std::string::npos)) {
          Fail(line_number, "encoding",
               "the header is not text (byte " + PrintableForMessage(line.substr(at, 1)) +
                   " at column " + std::to_string(at + 1) +
                   "): not a text CSV file (an .xlsx workbook, an image or an archive, or UTF-16 "
                   "text without a byte order mark?); export the capture as CSV in UTF-8");
        }
        FailIfBinary(head, text_start);
      }
      const size_t cr = line.find('\r');
      if (cr != std::string::npos && line.find_first_not_of("\r \t", cr) != std::string::npos) {
        Fail(line_number, "line end",
             "a carriage return inside the line (mixed line ends); save the file with LF or CRLF "
             "line ends");
      }
      if (Trim(line).empty()) continue;
      if (!have_header) {
        header_line_ = line_number;
        header_ = Split(line);
        have_header = true;
        continue;
      }
      rows_.push_back({line_number, Split(line)});
    }
    if (!have_header) throw std::invalid_argument(name_ + ":1: empty file, expected a header");
    for (size_t i = 0; i < header_.size(); ++i) {
      if (header_[i].empty()) {
        // A spreadsheet's export often ends every line with ',': an empty last column.
        Fail(header_line_, "header",
             "column " + std::to_string(i + 1) + " has no name" +
                 (i + 1 == header_.size() && i > 0
                      ? " (the line ends with ','; remove the ',' at the end of each line)"
                      : ""));
      }
      if (!index_.emplace(header_[i], i).second) {
        Fail(header_line_, "column " + header_[i], "appears twice in the header");
      }
    }
    // A regional spreadsheet export (';' between fields, ',' as the decimal point) read as one
    // column said only "column station: missing from the header".
    for (const char separator : {';', '\t', '|'}) {
      if (header_.size() == 1 && header_[0].find(separator) != std::string::npos) {
        Fail(header_line_, "header",
             std::string("fields are separated by ',' but this header is separated by '") +
                 (separator == '\t' ? std::string("\\t") : std::string(1, separator)) +
                 "' (export with ',' between fields and '.' as the decimal point)");
      }
    }
    for (const std::string& r : required) {
      if (!index_.count(r)) {
        Fail(header_line_, "column " + r,
             "missing from the header" + MissingColumnHint(r, required));
      }
    }
    for (size_t i = 0; i < header_.size(); ++i) {
      bool standard = false;
      for (const std::string& r : required) standard |= (r == header_[i]);
      if (!standard) {
        extra_names_.push_back(header_[i]);
        extra_index_.push_back(i);
      }
    }
    for (const Row& row : rows_) {
      if (row.fields.size() != header_.size()) {
        Fail(row.line, "row",
             "expected " + std::to_string(header_.size()) + " fields, found " +
                 std::to_string(row.fields.size()) + FieldCountHint(row));
      }
    }
    ClassifyExtras();
  }

  struct Row {
    int line;
    std::vector<std::string> fields;
  };

  // A binary file whose first line reads as text: a PDF document ("%PDF-1.7", then compressed
  // streams, often without a NUL in its first kilobyte) said "column station: missing from the
  // header". A text file holds no control byte but a tab, a line end, a form feed or vertical
  // tab, or DOS's end-of-file byte; a legacy code page's text (Latin-1 "temp_\xb0C") is not UTF-8
  // but holds none either, so both together (in `head`, the file's first kilobyte; `text_start` is
  // a few bytes more of it) tell a binary file apart.
  void FailIfBinary(const std::string& head, const std::string& text_start) const {
    static constexpr char kExport[] = "export the capture as CSV in UTF-8";
    if (head.rfind("%PDF-", 0) == 0) {
      Fail(1, "encoding",
           std::string("a PDF document (the file starts with %PDF-), not a text CSV file; ") +
               kExport);
    }
    const auto binary = std::find_if(head.begin(), head.end(), [](char c) {
      const auto byte = static_cast<unsigned char>(c);
      return byte < 0x20 && c != '\t' && c != '\n' && c != '\v' && c != '\f' && c != '\r' &&
             c != '\x1a';
    });
    if (binary == head.end() || FirstNonUtf8Byte(text_start) >= head.size()) return;
    const size_t at = static_cast<size_t>(binary - head.begin());
    const size_t line_start =
        head.rfind('\n', at) == std::string::npos ? 0 : head.rfind('\n', at) + 1;
    Fail(1 + static_cast<int>(std::count(head.begin(), binary, '\n')), "encoding",
         "byte " + PrintableForMessage(std::string_view(head).substr(at, 1)) + " at column " +
             std::to_string(at - line_start + 1) +
             " is not text, and the file is not UTF-8: not a text CSV file (a PDF document, an "
             ".xlsx workbook, an image or an archive?); " +
             kExport);
  }
  const std::vector<Row>& rows() const { return rows_; }
  const std::vector<std::string>& extra_columns() const { return extra_names_; }
  const std::vector<std::vector<std::string>>& extra_labels() const { return extra_labels_; }

  const std::string& Text(const Row& row, const std::string& column) const {
    return row.fields[index_.at(column)];
  }

  double Number(const Row& row, const std::string& column) const {
    return ParseNumber(row, column, Text(row, column));
  }

  int Integer(const Row& row, const std::string& column) const {
    const std::string& s = Text(row, column);
    int value = 0;
    const auto [end, ec] = std::from_chars(s.data(), s.data() + s.size(), value);
    if (s.empty() || ec != std::errc() || end != s.data() + s.size()) {
      Fail(row.line, "column " + column, Quoted(s) + " is not an integer");
    }
    return value;
  }

  Eigen::Vector3d Vector(const Row& row, const std::string& prefix) const {
    return Eigen::Vector3d(Number(row, prefix + "x"), Number(row, prefix + "y"),
                           Number(row, prefix + "z"));
  }

  Eigen::Quaterniond Quaternion(const Row& row, const std::string& prefix) const {
    const double w = Number(row, prefix + "qw");
    const double x = Number(row, prefix + "qx");
    const double y = Number(row, prefix + "qy");
    const double z = Number(row, prefix + "qz");
    Eigen::Quaterniond q = QuaternionFromWxyz(w, x, y, z);
    // Hand-edited or low-precision files carry a few digits; anything further from unit is an
    // error.
    if (std::abs(q.norm() - 1.0) > 1e-3) {
      char buf[64];
      std::snprintf(buf, sizeof(buf), "%.6g", q.norm());
      Fail(row.line,
           "columns " + prefix + "qw, " + prefix + "qx, " + prefix + "qy, " + prefix + "qz",
           std::string("quaternion norm ") + buf + " is not 1");
    }
    if (std::abs(q.norm() - 1.0) > 1e-12) q.normalize();  // keep written values bit for bit
    return q;
  }

  Rigid3d Pose(const Row& row, const std::string& prefix) const {
    return Rigid3d(Quaternion(row, prefix), Vector(row, prefix));
  }

  std::vector<double> Extras(const Row& row) const {
    std::vector<double> out;
    out.reserve(extra_index_.size());
    for (size_t i = 0; i < extra_index_.size(); ++i) {
      const std::string& s = row.fields[extra_index_[i]];
      const std::vector<std::string>& labels = extra_labels_[i];
      if (IsMissing(s)) {
        out.push_back(std::numeric_limits<double>::quiet_NaN());
      } else if (!labels.empty()) {
        const auto it = std::lower_bound(labels.begin(), labels.end(), s);
        if (it == labels.end() || *it != s) throw std::logic_error("label missing from its column");
        out.push_back(static_cast<double>(it - labels.begin()));
      } else {
        out.push_back(ParseNumber(row, extra_names_[i], s, true));
      }
    }
    return out;
  }

  // Rows are keyed by two integer columns (station and sensor, station and marker): a key seen
  // twice is an error naming both lines, since which row to keep is the user's call, not ours.
  void RequireUniqueKey(const Row& row, const std::string& first, int first_value,
                        const std::string& second, int second_value,
                        std::map<std::pair<int, int>, int>* seen) const {
    const auto [it, inserted] = seen->emplace(std::make_pair(first_value, second_value), row.line);
    if (!inserted) {
      Fail(row.line, "columns " + first + ", " + second,
           first + " " + std::to_string(first_value) + ", " + second + " " +
               std::to_string(second_value) + " repeats line " + std::to_string(it->second) +
               " (one row per " + first + " and " + second + ")");
    }
  }

  // Why a standard column is missing when the file does name it, the way lab software exports:
  // in quotes ("station"), with its unit (rep_x (m)), in other letter case (Station), after a
  // '#', or on a line below the first (a Motive or Vicon export's metadata lines, a comment
  // line, became the header). The message said only "missing from the header" for a header that
  // visibly held the name. Empty when nothing explains it.
  std::string MissingColumnHint(const std::string& column,
                                const std::vector<std::string>& required) const {
    const auto lower = [](std::string s) {
      for (char& c : s) c = static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
      return s;
    };
    for (const std::string& name : header_) {
      const char q = name.empty() ? '\0' : name.front();
      if (name.size() >= 2 && (q == '"' || q == '\'') && name.back() == q &&
          Trim(std::string_view(name).substr(1, name.size() - 2)) == column) {
        return " (the header names it " + name +
               ", in quotes: fields are read without quoting; save the file without quotes)";
      }
      if (name.size() > 1 && name[0] == '#' && Trim(std::string_view(name).substr(1)) == column) {
        return " (the header names it '" + name + "': remove the '#')";
      }
      if (name != column && lower(name) == lower(column)) {
        return " (the header has '" + name + "': names are case-sensitive; rename it " + column +
               ")";
      }
      if (name.size() > column.size() && name.compare(0, column.size(), column) == 0 &&
          (name[column.size()] == ' ' || name[column.size()] == '(' ||
           name[column.size()] == '[')) {
        return " (the header has '" + name + "': name it " + column +
               " alone; values are read in metres and seconds)";
      }
    }
    // A misspelt name (rep_xq, staion): a column the file has that no standard one is, near it.
    for (const std::string& name : header_) {
      if (std::find(required.begin(), required.end(), name) == required.end() &&
          ClosestName(name, {column}) == column) {
        return " (the header has '" + name + "': is it " + column + " misspelt? rename it " +
               column + ")";
      }
    }
    // Metadata or comment lines above the header: a later line names every standard column.
    for (size_t i = 0; i < rows_.size() && i < 50; ++i) {
      const std::vector<std::string>& fields = rows_[i].fields;
      bool all = true;
      for (const std::string& r : required) {
        all = all && std::find(fields.begin(), fields.end(), r) != fields.end();
      }
      if (all) {
        return " (line " + std::to_string(rows_[i].line) +
               " names the columns: remove the lines above it, which were read as the header)";
      }
    }
    return "";
  }

  // What a row of the wrong length most likely is.
  std::string FieldCountHint(const Row& row) const {
    if (row.fields.size() == header_.size() + 1 && row.fields.back().empty()) {
      return " (the line ends with ','; remove it)";
    }
    if (row.fields.size() > header_.size()) {
      bool point = false, digit = false;
      for (const std::string& f : row.fields) {
        point = point || f.find('.') != std::string::npos;
        digit = digit || f.find_first_of("0123456789") != std::string::npos;
      }
      if (digit && !point) {
        return " (no '.' in the line: is ',' its decimal point? export with '.' as the decimal "
               "point)";
      }
    }
    return "";
  }

  // The message quotes fields as read: a NUL (a binary file, a corrupt export) or a byte that is
  // not UTF-8 is written as \xNN, since what() is a C string that ended at the NUL, dropping the
  // problem ("column rep_y: '1.5" and nothing more).
  [[noreturn]] void Fail(int line, const std::string& what, const std::string& problem) const {
    throw std::invalid_argument(
        PrintableForMessage(name_ + ":" + std::to_string(line) + ": " + what + ": " + problem));
  }

 private:
  double ParseNumber(const Row& row, const std::string& column, const std::string& s,
                     bool allow_nan = false) const {
    double value = 0;
    if (!ParsesAsNumber(s, &value))
      Fail(row.line, "column " + column, Quoted(s) + " is not a number");
    // Extra columns may mark a missing reading with nan; standard columns must be finite.
    if (!std::isfinite(value) && !(allow_nan && std::isnan(value))) {
      Fail(row.line, "column " + column, Quoted(s) + " is not a finite number");
    }
    return value;
  }

  // Decides whether each extra column holds numbers or labels and collects its labels (sorted, so
  // a label's index does not depend on the row order). A column holding both is the file's error,
  // named at the first value whose kind differs from the column's first value.
  void ClassifyExtras() {
    extra_labels_.assign(extra_index_.size(), {});
    for (size_t k = 0; k < extra_index_.size(); ++k) {
      const size_t column = extra_index_[k];
      const Row* first = nullptr;
      bool first_is_number = false;
      std::set<std::string> labels;
      for (const Row& row : rows_) {
        const std::string& s = row.fields[column];
        if (IsMissing(s)) continue;
        double value = 0;
        const bool number = ParsesAsNumber(s, &value);
        if (first == nullptr) {
          first = &row;
          first_is_number = number;
        } else if (number != first_is_number) {
          const std::string& f = first->fields[column];
          const std::string where = ", but line " + std::to_string(first->line) + " holds ";
          const std::string why = " (a column holds numbers or labels, not both)";
          Fail(row.line, "column " + extra_names_[k],
               number ? Quoted(s) + " is a number" + where + "the label " + Quoted(f) + why
                      : Quoted(s) + " is not a number" + where + "the number " + f + why);
        }
        if (!number) labels.insert(s);
      }
      extra_labels_[k].assign(labels.begin(), labels.end());
    }
  }

  std::string name_;
  int header_line_ = 1;
  std::vector<std::string> header_;
  std::map<std::string, size_t> index_;
  std::vector<std::string> extra_names_;
  std::vector<size_t> extra_index_;
  std::vector<std::vector<std::string>> extra_labels_;
  std::vector<Row> rows_;
};

const std::vector<std::string> kPoseColumns = {
    "station", "set",    "sensor", "time",  "rep_x", "rep_y",  "rep_z",  "rep_qw", "rep_qx",
    "rep_qy",  "rep_qz", "ref_x",  "ref_y", "ref_z", "ref_qw", "ref_qx", "ref_qy", "ref_qz"};
const std::vector<std::string> kMarkerColumns = {"station", "marker", "x", "y", "z"};
const std::vector<std::string> kTrackerColumns = {"station", "sensor", "x",  "y", "z",
                                                  "qw",      "qx",     "qy", "qz"};
const std::vector<std::string> kTrackerStreamColumns = {"time", "sensor", "x",  "y", "z",
                                                        "qw",   "qx",     "qy", "qz"};
const std::vector<std::string> kReferenceStreamColumns = {"time", "x",  "y",  "z",
                                                          "qw",   "qx", "qy", "qz"};

// ---- Writing. ----
class CsvWriter {
 public:
  CsvWriter(const std::filesystem::path& path, const std::vector<std::string>& columns,
            const std::vector<std::string>& extra_columns,
            const std::vector<std::vector<std::string>>& extra_labels)
      : name_(path.string()),
        standard_count_(columns.size()),
        extra_count_(extra_columns.size()),
        extra_labels_(extra_labels) {
    if (!extra_labels_.empty() && extra_labels_.size() != extra_count_) {
      throw std::invalid_argument(name_ + ": " + std::to_string(extra_labels_.size()) +
                                  " label lists for " + std::to_string(extra_count_) +
                                  " extra columns");
    }
    extra_labels_.resize(extra_count_);
    for (size_t k = 0; k < extra_count_; ++k) {
      // Labels must read back as the same labels: text, one field, each once.
      std::set<std::string> seen;
      for (const std::string& label : extra_labels_[k]) {
        double value = 0;
        if (label.empty() || label != Trim(label) ||
            label.find_first_of(",\n\r") != std::string::npos || ParsesAsNumber(label, &value) ||
            !seen.insert(label).second) {
          throw std::invalid_argument(name_ + ": extra column " + extra_columns[k] + ": label '" +
                                      label + "' is not a valid label (text, no comma, once)");
        }
      }
    }
    for (size_t k = 0; k < extra_columns.size(); ++k) {
      const std::string& e = extra_columns[k];
      for (const std::string& c : columns) {
        if (e == c)
          throw std::invalid_argument(name_ + ": extra column " + e + " is a standard column");
      }
      // The reader trims header names and refuses a name given twice: a name it would read
      // differently, or a repeated one, makes a file it refuses.
      if (e.empty() || e != Trim(e) || e.find_first_of(",\n\r") != std::string::npos) {
        throw std::invalid_argument(name_ + ": extra column name '" + e + "' is not a valid name");
      }
      if (std::find(extra_columns.begin(), extra_columns.begin() + k, e) !=
          extra_columns.begin() + k) {
        throw std::invalid_argument(name_ + ": extra column " + e + " is given twice");
      }
    }
    names_ = columns;
    names_.insert(names_.end(), extra_columns.begin(), extra_columns.end());
    for (size_t i = 0; i < names_.size(); ++i) out_ << (i ? "," : "") << names_[i];
    out_ << '\n';
    header_size_ = static_cast<size_t>(out_.tellp());
  }
  CsvWriter& Int(int v) {
    Sep();
    out_ << v;
    return *this;
  }
  CsvWriter& Text(const std::string& s) {
    Sep();
    out_ << s;
    return *this;
  }
  // What the readers refuse is refused here, before anything is written: a capture the tools
  // cannot read back is no capture. Standard columns need finite numbers; an extra column's nan
  // marks a missing value.
  CsvWriter& Num(double v) {
    if (!std::isfinite(v) && !(field_ >= standard_count_ && std::isnan(v))) {
      Fail("column " + names_[field_], FormatNumber(v) + " is not a finite number");
    }
    Sep();
    out_ << FormatNumber(v);
    return *this;
  }
  CsvWriter& Vec(const Eigen::Vector3d& v) { return Num(v.x()).Num(v.y()).Num(v.z()); }
  CsvWriter& Pose(const Rigid3d& p) {
    const Eigen::Quaterniond& q = p.rotation;
    Vec(p.translation);
    if (std::abs(q.norm() - 1.0) > 1e-3) {  // the readers' tolerance
      char norm[64];
      std::snprintf(norm, sizeof(norm), "%.6g", q.norm());
      Fail("columns " + names_[field_] + ", " + names_[field_ + 1] + ", " + names_[field_ + 2] +
               ", " + names_[field_ + 3],
           std::string("quaternion norm ") + norm + " is not 1");
    }
    return Num(q.w()).Num(q.x()).Num(q.y()).Num(q.z());
  }
  void End(const std::vector<double>& extra, size_t record) {
    if (extra.size() != extra_count_) {
      throw std::invalid_argument(name_ + ": record " + std::to_string(record) + " has " +
                                  std::to_string(extra.size()) + " extra values, expected " +
                                  std::to_string(extra_count_));
    }
    for (size_t k = 0; k < extra_count_; ++k) {
      const double v = extra[k];
      const std::vector<std::string>& labels = extra_labels_[k];
      if (labels.empty()) {
        Num(v);
      } else if (std::isnan(v)) {
        Text("");
      } else if (v >= 0 && v < static_cast<double>(labels.size()) && v == std::floor(v)) {
        Text(labels[static_cast<size_t>(v)]);
      } else {
        throw std::invalid_argument(name_ + ": record " + std::to_string(record) +
                                    ": extra column " + std::to_string(k + 1) + ": " +
                                    FormatNumber(v) + " is not the index of one of its " +
                                    std::to_string(labels.size()) + " labels");
      }
    }
    out_ << '\n';
    field_ = 0;
    ++record_;
  }
  // As the readers: one record per pair of key columns (station and sensor, station and marker).
  void RequireUniqueKey(const std::string& first, int first_value, const std::string& second,
                        int second_value) {
    const auto [it, inserted] = keys_.emplace(std::make_pair(first_value, second_value), record_);
    if (!inserted) {
      Fail("columns " + first + ", " + second,
           first + " " + std::to_string(first_value) + ", " + second + " " +
               std::to_string(second_value) + " repeats record " + std::to_string(it->second) +
               " (one record per " + first + " and " + second + ")");
    }
  }
  // As ReadTrackerStream: one record per sensor and time. After the time's Num(), so a non-finite
  // time is named as such (and never compared).
  void RequireUniqueSensorTime(int sensor, double time) {
    const auto [it, inserted] = sensor_times_.emplace(std::make_pair(sensor, time), record_);
    if (!inserted) {
      Fail("columns time, sensor", "time " + FormatNumber(time) + " of sensor " +
                                       std::to_string(sensor) + " repeats record " +
                                       std::to_string(it->second) +
                                       " (one sample per sensor and time)");
    }
  }
  // As ReadReferenceStream: times must increase from record to record.
  void RequireIncreasingTime(double time) {
    if (record_ > 0 && !(time > previous_time_)) {
      Fail("column time", FormatNumber(time) + " is not after the previous record's " +
                              FormatNumber(previous_time_) + " (times must increase)");
    }
    previous_time_ = time;
  }
  void Commit(const std::filesystem::path& path, const CaptureWriteOptions& options) {
    WriteFileAtomically(path, out_.str(), options.overwrite);
  }
  // The text so far, with or without the header line.
  std::string Contents(bool header) const {
    std::string text = out_.str();
    return header ? text : text.substr(header_size_);
  }

 private:
  void Sep() {
    if (field_ > 0) out_ << ',';
    ++field_;
  }
  [[noreturn]] void Fail(const std::string& what, const std::string& problem) const {
    throw std::invalid_argument(name_ + ": record " + std::to_string(record_) + ": " + what + ": " +
                                problem);
  }
  std::string name_;
  size_t standard_count_;
  std::vector<std::string> names_;  // standard columns, then extras
  size_t extra_count_;
  std::vector<std::vector<std::string>> extra_labels_;
  std::ostringstream out_;
  size_t header_size_ = 0;  // length of the header line in out_
  size_t field_ = 0;   // fields written of the current record
  size_t record_ = 0;  // index of the current record
  std::map<std::pair<int, int>, size_t> keys_;  // key columns' values -> first record
  std::map<std::pair<int, double>, size_t> sensor_times_;  // (sensor, time) -> first record
  double previous_time_ = 0.0;
};

}  // namespace

bool IsKnownSet(const std::string& set) {
  return set == "calib" || set == "valid" || set == "reg";
}

std::string FormatNumber(double value) {
  std::array<char, 64> buf;
  const auto [end, ec] = std::to_chars(buf.data(), buf.data() + buf.size(), value);
  if (ec != std::errc()) throw std::runtime_error("cannot format number");
  return std::string(buf.data(), end);
}

PoseCapture ReadPoses(const std::filesystem::path& path) {
  CsvTable t(path, kPoseColumns);
  PoseCapture c;
  c.extra_columns = t.extra_columns();
  c.extra_labels = t.extra_labels();
  std::map<std::pair<int, int>, int> seen;
  for (const auto& row : t.rows()) {
    PoseRecord r;
    r.station = t.Integer(row, "station");
    r.set = t.Text(row, "set");
    if (!IsKnownSet(r.set)) {
      t.Fail(row.line, "column set", Quoted(r.set) + " is not one of calib, valid, reg");
    }
    r.sensor = t.Integer(row, "sensor");
    t.RequireUniqueKey(row, "station", r.station, "sensor", r.sensor, &seen);
    r.time = t.Number(row, "time");
    r.reported = t.Pose(row, "rep_");
    r.reference = t.Pose(row, "ref_");
    r.extra = t.Extras(row);
    c.records.push_back(std::move(r));
  }
  return c;
}

MarkerCapture ReadMarkers(const std::filesystem::path& path) {
  CsvTable t(path, kMarkerColumns);
  MarkerCapture c;
  c.extra_columns = t.extra_columns();
  c.extra_labels = t.extra_labels();
  std::map<std::pair<int, int>, int> seen;
  for (const auto& row : t.rows()) {
    MarkerRecord r;
    r.line = row.line;
    r.station = t.Integer(row, "station");
    r.marker = t.Integer(row, "marker");
    t.RequireUniqueKey(row, "station", r.station, "marker", r.marker, &seen);
    r.position_in_optical = t.Vector(row, "");
    r.extra = t.Extras(row);
    c.records.push_back(std::move(r));
  }
  return c;
}

TrackerCapture ReadTracker(const std::filesystem::path& path) {
  CsvTable t(path, kTrackerColumns);
  TrackerCapture c;
  c.extra_columns = t.extra_columns();
  c.extra_labels = t.extra_labels();
  std::map<std::pair<int, int>, int> seen;
  for (const auto& row : t.rows()) {
    TrackerRecord r;
    r.station = t.Integer(row, "station");
    r.sensor = t.Integer(row, "sensor");
    t.RequireUniqueKey(row, "station", r.station, "sensor", r.sensor, &seen);
    r.transmitter_from_receiver = t.Pose(row, "");
    r.extra = t.Extras(row);
    c.records.push_back(std::move(r));
  }
  return c;
}

TrackerStream ReadTrackerStream(const std::filesystem::path& path) {
  CsvTable t(path, kTrackerStreamColumns);
  TrackerStream c;
  c.extra_columns = t.extra_columns();
  c.extra_labels = t.extra_labels();
  // Rows may come in any order (receivers interleave, streams get merged): the pairing and the
  // speed take each sensor's samples in time order. One sensor's time twice is a frame written
  // twice or a clock that did not tick, two poses at one instant: silently it paired both with one
  // reference pose and gave a speed from a zero time step, so it is the file's error.
  std::map<std::pair<int, double>, int> seen;  // (sensor, time) -> line
  for (const auto& row : t.rows()) {
    TrackerStreamSample r;
    r.time = t.Number(row, "time");
    r.sensor = t.Integer(row, "sensor");
    const auto [it, inserted] = seen.emplace(std::make_pair(r.sensor, r.time), row.line);
    if (!inserted) {
      t.Fail(row.line, "columns time, sensor",
             "time " + FormatNumber(r.time) + " of sensor " + std::to_string(r.sensor) +
                 " repeats line " + std::to_string(it->second) +
                 " (one sample per sensor and time)");
    }
    r.transmitter_from_receiver = t.Pose(row, "");
    r.extra = t.Extras(row);
    c.records.push_back(std::move(r));
  }
  return c;
}

ReferenceStream ReadReferenceStream(const std::filesystem::path& path) {
  CsvTable t(path, kReferenceStreamColumns);
  ReferenceStream c;
  c.extra_columns = t.extra_columns();
  c.extra_labels = t.extra_labels();
  for (const auto& row : t.rows()) {
    ReferenceStreamSample r;
    r.time = t.Number(row, "time");
    r.transmitter_from_body = t.Pose(row, "");
    r.extra = t.Extras(row);
    // Pairing interpolates between neighbouring samples: a repeated or earlier time (a frame
    // written twice, streams concatenated) is the file's error, named here by line.
    if (!c.records.empty() && !(r.time > c.records.back().time)) {
      t.Fail(row.line, "column time",
             FormatNumber(r.time) + " is not after the previous sample's " +
                 FormatNumber(c.records.back().time) + " (times must increase)");
    }
    c.records.push_back(std::move(r));
  }
  return c;
}

void WritePoses(const std::filesystem::path& path, const PoseCapture& capture,
                const CaptureWriteOptions& options) {
  CsvWriter w(path, kPoseColumns, capture.extra_columns, capture.extra_labels);
  for (size_t i = 0; i < capture.records.size(); ++i) {
    const PoseRecord& r = capture.records[i];
    if (!IsKnownSet(r.set)) {
      throw std::invalid_argument(path.string() + ": record " + std::to_string(i) +
                                  ": column set: '" + r.set + "' is not one of calib, valid, reg");
    }
    w.RequireUniqueKey("station", r.station, "sensor", r.sensor);
    w.Int(r.station).Text(r.set).Int(r.sensor).Num(r.time).Pose(r.reported).Pose(r.reference);
    w.End(r.extra, i);
  }
  w.Commit(path, options);
}

void WriteMarkers(const std::filesystem::path& path, const MarkerCapture& capture,
                  const CaptureWriteOptions& options) {
  CsvWriter w(path, kMarkerColumns, capture.extra_columns, capture.extra_labels);
  for (size_t i = 0; i < capture.records.size(); ++i) {
    const MarkerRecord& r = capture.records[i];
    w.RequireUniqueKey("station", r.station, "marker", r.marker);
    w.Int(r.station).Int(r.marker).Vec(r.position_in_optical);
    w.End(r.extra, i);
  }
  w.Commit(path, options);
}

void WriteTracker(const std::filesystem::path& path, const TrackerCapture& capture,
                  const CaptureWriteOptions& options) {
  CsvWriter w(path, kTrackerColumns, capture.extra_columns, capture.extra_labels);
  for (size_t i = 0; i < capture.records.size(); ++i) {
    const TrackerRecord& r = capture.records[i];
    w.RequireUniqueKey("station", r.station, "sensor", r.sensor);
    w.Int(r.station).Int(r.sensor).Pose(r.transmitter_from_receiver);
    w.End(r.extra, i);
  }
  w.Commit(path, options);
}

namespace {

void AddTrackerStream(const TrackerStream& capture, CsvWriter& w) {
  for (size_t i = 0; i < capture.records.size(); ++i) {
    const TrackerStreamSample& r = capture.records[i];
    w.Num(r.time).Int(r.sensor);
    w.RequireUniqueSensorTime(r.sensor, r.time);
    w.Pose(r.transmitter_from_receiver);
    w.End(r.extra, i);
  }
}

}  // namespace

void WriteTrackerStream(const std::filesystem::path& path, const TrackerStream& capture,
                        const CaptureWriteOptions& options) {
  CsvWriter w(path, kTrackerStreamColumns, capture.extra_columns, capture.extra_labels);
  AddTrackerStream(capture, w);
  w.Commit(path, options);
}

std::string FormatTrackerStream(const TrackerStream& capture, const std::string& name,
                                bool header) {
  CsvWriter w(name, kTrackerStreamColumns, capture.extra_columns, capture.extra_labels);
  AddTrackerStream(capture, w);
  return w.Contents(header);
}

void WriteReferenceStream(const std::filesystem::path& path, const ReferenceStream& capture,
                          const CaptureWriteOptions& options) {
  CsvWriter w(path, kReferenceStreamColumns, capture.extra_columns, capture.extra_labels);
  for (size_t i = 0; i < capture.records.size(); ++i) {
    const ReferenceStreamSample& r = capture.records[i];
    w.Num(r.time);  // a non-finite time is named as such first
    w.RequireIncreasingTime(r.time);
    w.Pose(r.transmitter_from_body);
    w.End(r.extra, i);
  }
  w.Commit(path, options);
}

}  // namespace trackcal
