#include "vrpn_server/config.h"

#include <algorithm>
#include <cctype>
#include <cerrno>
#include <charconv>
#include <cmath>
#include <cstring>
#include <fstream>
#include <map>
#include <set>
#include <sstream>
#include <stdexcept>
#include <utility>

#include "core/printable_text.h"

namespace trackcal::vrpn {
namespace {

constexpr std::string_view kWhitespace = " \t\r\f\v";
// TrackerSpec::Check allows up to 1024 sensors (0..1023).
constexpr int kMaxCalibrationSensor = 1024;

std::string_view TrimRight(std::string_view s) {
  const size_t end = s.find_last_not_of(kWhitespace);
  return end == std::string_view::npos ? std::string_view() : s.substr(0, end + 1);
}

std::string_view Trim(std::string_view s) {
  s = TrimRight(s);
  const size_t begin = s.find_first_not_of(kWhitespace);
  return begin == std::string_view::npos ? std::string_view() : s.substr(begin);
}

std::vector<std::string> Tokenize(std::string_view s) {
  std::vector<std::string> tokens;
  size_t i = 0;
  while (i < s.size()) {
    i = s.find_first_not_of(kWhitespace, i);
    if (i == std::string_view::npos) break;
    size_t end = s.find_first_of(kWhitespace, i);
    if (end == std::string_view::npos) end = s.size();
    tokens.emplace_back(s.substr(i, end - i));
    i = end;
  }
  return tokens;
}

[[noreturn]] void Fail(const ConfigLocation& where, std::string_view field, const std::string& what) {
  std::ostringstream msg;
  msg << where.ToString() << ": ";
  if (!field.empty()) msg << "field '" << field << "': ";
  msg << what;
  // The message quotes the file, and the server prints it on the operator's terminal.
  throw std::invalid_argument(PrintableForLog(msg.str()));
}

// Why a VRPN client could not address device `name` (empty if it can). Clients name a device as
// "Name@host" and the reference reads the name up to the first '@' (vrpn_copy_service_name); the
// name goes on the wire as a sender description of at most 95 characters and reaches client logs
// and GUIs: it must be printable (no C0/C1 control, no DEL; a name that is not UTF-8 is only
// warned of, NonUtf8NameWarning). Spaces cannot occur (they separate the tokens of a line).
std::string UnaddressableName(const std::string& name) {
  if (name.empty()) return "empty device name";
  if (name.size() > 95) {  // the longest name a VRPN description carries; refused at start-up
    return "device name '" + name + "' is over 95 characters";  // without a line
  }
  if (const size_t at = name.find('@'); at != std::string::npos) {
    return "device name '" + name +
           "' contains '@' (clients address a device as Name@host and "
           "read the name up to the first '@')";
  }
  for (size_t i = 0; i < name.size(); ++i) {
    const auto c = static_cast<unsigned char>(name[i]);
    const bool c1 = c == 0xc2 && i + 1 < name.size() &&
                    static_cast<unsigned char>(name[i + 1]) >= 0x80 &&
                    static_cast<unsigned char>(name[i + 1]) <= 0x9f;  // U+0080-U+009F in UTF-8
    if (c < 0x20 || c == 0x7f || c1) {
      return "device name '" + name +
             "' contains a control character (a name must be printable; control bytes reach "
             "clients' logs and terminals)";
    }
  }
  return "";
}

// A warning for a device name that is not UTF-8 (empty if it is). The reference serves any bytes,
// and a lab's vrpn.cfg saved as Latin-1 ("Ger\xe4t") worked with it and with clients that send
// those same bytes: served as it is, but a client typing the name in UTF-8 (C#, Python, a UTF-8
// terminal) sends other bytes and is not served.
std::string NonUtf8NameWarning(const std::string& name, std::string_view field) {
  const size_t bad = FirstNonUtf8Byte(name);
  if (bad == std::string::npos) return "";
  return "field '" + std::string(field) + "': device name '" + name + "' is not UTF-8 (byte " +
         PrintableForLog(name.substr(bad, 1)) + " at character " + std::to_string(bad + 1) +
         "; the file was saved in another encoding, e.g. Latin-1?): served under these bytes, "
         "which a client must send exactly; save vrpn.cfg as UTF-8 so that clients typing the "
         "name reach it";
}

int ParseInt(const std::string& token, const ConfigLocation& where, std::string_view field) {
  int value = 0;
  const auto [end, ec] = std::from_chars(token.data(), token.data() + token.size(), value);
  if (ec != std::errc() || end != token.data() + token.size()) {
    Fail(where, field, "expected an integer, got '" + token + "'");
  }
  return value;
}

double ParseDouble(const std::string& token, const ConfigLocation& where, std::string_view field) {
  // std::from_chars for double is available in GCC 11+, but strtod also accepts what C users expect.
  char* end = nullptr;
  const double value = std::strtod(token.c_str(), &end);
  if (token.empty() || end != token.c_str() + token.size() || !std::isfinite(value)) {
    Fail(where, field, "expected a number, got '" + token + "'");
  }
  return value;
}

// Whether a device type is in trackcal's namespace: it starts with "trackcal_" in any letter case.
bool IsTrackcalKeyword(std::string_view keyword) {
  constexpr std::string_view kPrefix = "trackcal_";
  if (keyword.size() <= kPrefix.size()) return false;
  for (size_t i = 0; i < kPrefix.size(); ++i) {
    if (std::tolower(static_cast<unsigned char>(keyword[i])) != kPrefix[i]) return false;
  }
  return true;
}

// A physical line of the file: text without the line end and trailing blanks, 1-based number.
struct Line {
  std::string_view text;
  int number = 0;
};

bool IsCommentOrBlank(std::string_view text) {
  const std::string_view t = Trim(text);
  return t.empty() || t.front() == '#';
}

// Continuation character of a (right-trimmed) line: '\\', '/' or 0.
char ContinuationOf(std::string_view text) {
  if (text.empty()) return 0;
  const char c = text.back();
  return (c == '\\' || c == '/') ? c : 0;
}

class Parser {
 public:
  Parser(std::string_view text, const std::string& file_name) : file_name_(file_name) {
    FindEncodingProblem(text);
    // A UTF-8 byte order mark (editors on Windows save one) would glue itself, invisible, to the
    // first keyword and drop that device as unknown.
    if (text.substr(0, 3) == "\xEF\xBB\xBF") text.remove_prefix(3);
    size_t start = 0;
    int number = 1;
    while (start < text.size()) {  // a final line end does not start another line
      size_t end = text.find('\n', start);
      if (end == std::string_view::npos) end = text.size();
      lines_.push_back({TrimRight(text.substr(start, end - start)), number++});
      start = end + 1;
    }
  }

  VrpnConfig Parse() {
    if (!encoding_problem_.empty()) {
      Fail({file_name_, encoding_problem_line_}, "", encoding_problem_);
    }
    while (next_ < lines_.size()) {
      const Line line = lines_[next_++];
      if (IsCommentOrBlank(line.text)) continue;
      const ConfigLocation where = Where(line);
      const std::vector<std::string> tokens = Tokenize(line.text);
      const std::string& keyword = tokens.front();
      if (std::optional<BlankLineEnd> blank = std::exchange(blank_line_end_, std::nullopt);
          blank && !StartsDeviceLine(Trim(line.text))) {
        // A command or device line of the block that the blank line ended: as an unknown device it
        // was dropped with a warning (a hemisphere command not sent, a stylus not served).
        Fail(where, "device type",
             "'" + keyword + "' is not a device line: it follows the continuation block of " +
                 blank->block + ", which the blank line at " + blank->location.ToString() +
                 " ended; remove the blank line to continue the block");
      }
      if (keyword == "vrpn_Tracker_Fastrak") {
        ParseFastrak(line);
      } else if (keyword == "vrpn_Tracker_NULL") {
        ParseNull(tokens, where);
      } else if (keyword == "trackcal_Calibration") {
        ParseCalibration(tokens, where);
      } else if (keyword == "trackcal_Tracker_Passthrough") {
        ParsePassthrough(tokens, where);
      } else if (IsTrackcalKeyword(keyword)) {
        // trackcal's own lines: no other software defines them, so an unknown one is a typo, and
        // as a warning a misspelt trackcal_Calibration served its tracker uncorrected.
        Fail(where, "device type",
             "unknown trackcal device type '" + keyword +
                 "' (trackcal's own lines are trackcal_Calibration and "
                 "trackcal_Tracker_Passthrough; names are case-sensitive)");
      } else {
        const int skipped = SkipContinuation(ContinuationOf(line.text), keyword);
        std::string message = "unknown device type '" + keyword + "'; line ignored";
        if (skipped > 0) {
          message += " with its " + std::to_string(skipped) + " continuation line(s)";
        }
        message += " (other devices are still served)";
        config_.warnings.push_back({where, message});
      }
    }
    CheckCalibrations();
    CheckLocalPassthroughs();
    return std::move(config_);
  }

 private:
  ConfigLocation Where(const Line& line) const { return {file_name_, line.number}; }

  // Notepad's "Unicode" save (UTF-16) warned "unknown device type '\xff\xfev\x00r...'" on every
  // line, then "no device trackcal-server can serve"; a PDF or another binary file warned on each
  // of its lines. Not UTF-8 text: one error, saying what the file is.
  void FindEncodingProblem(std::string_view text) {
    static constexpr char kSave[] = "; save the VRPN configuration file as UTF-8";
    using namespace std::string_view_literals;
    if (std::string utf16 = Utf16TextProblem(text, "VRPN configuration file"); !utf16.empty()) {
      encoding_problem_ = std::move(utf16);
    } else if (text.substr(0, 5) == "%PDF-"sv) {
      encoding_problem_ =
          "a PDF document (the file starts with %PDF-), not a VRPN configuration file";
    } else if (const size_t nul = text.find('\0'); nul != std::string_view::npos) {
      encoding_problem_line_ =
          1 + static_cast<int>(std::count(text.begin(), text.begin() + nul, '\n'));
      encoding_problem_ =
          "a NUL byte: not a text file (UTF-16 without a byte order mark, or a "
          "binary file?)" +
          std::string(kSave);
    }
  }

  // Why NextContinuationLine returned no line.
  enum class BlockEnd {
    kEndOfFile,            // nothing after the line that continues (the caller decides)
    kCommentsToEndOfFile,  // only comment lines up to the end of the file (warned)
    kDeviceLine,           // at a line that starts with a device type (warned, left for Parse)
    kBlankLine,            // a blank line ended the block (warned, consumed)
  };

  // Next line of the continuation block of `block` (what it continues, for the warning) that is
  // not a comment (comments are allowed inside continuation blocks), or null (`end` says why):
  // - at a line that starts with a device type (see StartsDeviceLine): that line is left for the
  //   main loop, since a block whose last line was commented out ("#u" below "H1,1,0,0\") is
  //   otherwise still open and would swallow the next device line, while the reference, which
  //   sends the comment as a command, ends the block there;
  // - at the end of the file after comment lines only: the same block, at the end of the file
  //   (warned; it used to end without a word, or as "the file ends before the command line");
  // - at a blank line, which ends the block (the reference sends it as an empty command and ends
  //   the block, or misreads it as a device line): warned, and a line after it that does not
  //   start a device is an error in Parse (it was meant to continue the block).
  const Line* NextContinuationLine(std::string_view block, BlockEnd* end = nullptr) {
    BlockEnd ignored;
    if (end == nullptr) end = &ignored;
    std::optional<ConfigLocation> first_comment;
    while (next_ < lines_.size()) {
      const Line& line = lines_[next_];
      const std::string_view t = Trim(line.text);
      if (!t.empty() && t.front() == '#') {
        if (!first_comment) first_comment = Where(line);
        ++next_;
        continue;
      }
      if (t.empty()) {
        *end = BlockEnd::kBlankLine;
        config_.warnings.push_back(
            {Where(line), "a blank line ends the continuation block of " + std::string(block) +
                              " (the line before it ends with '\\' or '/'); a line after it "
                              "is read as a device line"});
        blank_line_end_ = BlankLineEnd{std::string(block), Where(line)};
        ++next_;
        return nullptr;
      }
      if (StartsDeviceLine(t)) {
        const std::string keyword(t.substr(0, t.find_first_of(kWhitespace)));
        config_.warnings.push_back(
            {Where(line), "'" + keyword +
                              "' starts a device line inside the continuation block of " +
                              std::string(block) +
                              " (its last line that is not a comment ends with '\\' or '/'; was "
                              "the block's last line commented out?): the block ends before this "
                              "line, which is read as a device line"});
        *end = BlockEnd::kDeviceLine;
        return nullptr;
      }
      ++next_;
      return &line;
    }
    *end = BlockEnd::kEndOfFile;
    if (first_comment) {
      *end = BlockEnd::kCommentsToEndOfFile;
      config_.warnings.push_back(
          {*first_comment, "the continuation block of " + std::string(block) +
                               " has only comment lines from here to the end of the file (its "
                               "last line that is not a comment ends with '\\' or '/'; was the "
                               "block's last line commented out?): the block ends here"});
    }
    return nullptr;
  }

  // Whether the trimmed line starts with a device type: the reference's all start with "vrpn_",
  // trackcal's with "trackcal_". No tracker command, button line (FTStylus, Stylus, Wand) or
  // continuation line of another device does.
  static bool StartsDeviceLine(std::string_view trimmed) {
    const std::string_view keyword = trimmed.substr(0, trimmed.find_first_of(kWhitespace));
    return keyword.substr(0, 5) == "vrpn_" || IsTrackcalKeyword(keyword);
  }

  int SkipContinuation(char continuation, std::string_view keyword) {
    int skipped = 0;
    while (continuation != 0) {
      const Line* line = NextContinuationLine("the ignored '" + std::string(keyword) + "' line");
      if (line == nullptr) break;
      ++skipped;
      continuation = ContinuationOf(line->text);
    }
    return skipped;
  }

  // Warns that tokens[first..] are ignored (text the reference's sscanf never reads).
  void WarnIgnoredTokens(const std::vector<std::string>& tokens, size_t first,
                         const ConfigLocation& where, const std::string& after) {
    if (tokens.size() <= first) return;
    std::string text;
    for (size_t i = first; i < tokens.size(); ++i) text += (i == first ? "" : " ") + tokens[i];
    config_.warnings.push_back({where, "text after " + after + " ignored: '" + text + "'"});
  }

  void RegisterName(const std::string& name, const ConfigLocation& where, std::string_view field,
                    std::string_view hint = {}) {
    if (const std::string why = UnaddressableName(name); !why.empty()) Fail(where, field, why);
    if (std::string warning = NonUtf8NameWarning(name, field); !warning.empty()) {
      config_.warnings.push_back({where, std::move(warning)});
    }
    const auto [it, inserted] = names_.emplace(name, NameUse{where, std::nullopt});
    if (!inserted) {
      Fail(where, field,
           "device name '" + name + "' is already used at " + it->second.location.ToString() +
               std::string(hint));
    }
  }

  // A button device may take the name of the tracker it is attached to: the reference then serves
  // a tracker and a button server under one sender, their messages told apart by type. Any other
  // reuse (a second button of that name, another device's name) is an error, as two devices of one
  // type under one name would mix their messages in the reference.
  void RegisterButtonName(const std::string& name, const std::string& tracker,
                          const ConfigLocation& where) {
    if (!name.empty() && name == tracker) {
      NameUse& use = names_.at(tracker);  // registered before its device lines are read
      if (use.button) {
        Fail(where, "button name",
             "button device name '" + name + "' is already used at " + use.button->ToString());
      }
      use.button = where;
      return;
    }
    RegisterName(name, where, "button name",
                 " (a button may share only the name of the tracker it is attached to)");
  }

  // Two drivers on one serial port each read part of the other's bytes (and reset the unit under
  // the other), so neither is served: an error naming both lines. The port is compared by its
  // canonical path when it exists (a symbolic link such as /dev/serial/by-id/..., or
  // /dev/./ttyUSB0, names the same device as /dev/ttyUSB0), else by its lexically normal form.
  void RegisterSerialPort(const std::string& tracker, const std::string& port,
                          const ConfigLocation& where) {
    std::error_code ec;
    std::filesystem::path key = std::filesystem::canonical(port, ec);
    if (ec) key = std::filesystem::path(port).lexically_normal();
    const auto [it, inserted] = ports_.emplace(key.string(), PortUse{tracker, port, where});
    if (inserted) return;
    const PortUse& first = it->second;
    std::string same = "'" + port + "'";
    if (first.port != port) same += " (the same device as '" + first.port + "')";
    Fail(where, "serial_port",
         "serial port " + same + " is already opened by tracker '" + first.tracker + "' at " +
             first.location.ToString() +
             "; two drivers on one port read each other's bytes (one line per unit)");
  }

  void ParseFastrak(const Line& line) {
    const ConfigLocation where = Where(line);
    std::string_view body = line.text;
    char continuation = ContinuationOf(body);
    if (continuation != 0) body = TrimRight(body.substr(0, body.size() - 1));
    std::vector<std::string> tokens = Tokenize(body);
    // The reference also accepts the continuation character as a separate token before the end.
    if (tokens.size() > 4 && (tokens.back() == "\\" || tokens.back() == "/")) tokens.pop_back();
    if (tokens.size() < 4) {
      static constexpr const char* kFields[] = {"", "name", "serial_port", "baud"};
      Fail(where, kFields[tokens.size()],
           "missing; expected 'vrpn_Tracker_Fastrak <name> <serial_port> <baud> [IS900time]'");
    }
    FastrakTrackerSpec spec;
    spec.location = where;
    spec.name = tokens[1];
    spec.port = tokens[2];
    spec.baud = ParseInt(tokens[3], where, "baud");
    if (!IsSupportedBaudRate(spec.baud)) {
      Fail(where, "baud",
           std::to_string(spec.baud) +
               " is not a supported rate (300, 1200, 2400, 4800, 9600, 19200, 38400, 57600, 115200)");
    }
    // The reference reads one optional token (sscanf "%s%s%d%s"): IS900time (compared as a prefix)
    // or a lone "/" or backslash, and never looks at what follows (warned here). A lone
    // continuation character with text after it does not continue the line, so the command or
    // device lines meant to follow would be misread: that is an error.
    if (tokens.size() > 4) {
      const std::string& option = tokens[4];
      if (option == "/" || option == "\\") {
        if (tokens.size() > 5) {
          Fail(where, "option",
               "text after '" + option + "': a continuation character must end the line");
        }
      } else if (option.rfind("IS900time", 0) == 0) {
        spec.is900_time = true;
        WarnIgnoredTokens(tokens, 5, where, "the baud rate and option");
      } else {
        Fail(where, "option",
             "unexpected token '" + option + "' (only IS900time, \\ or / may follow the baud rate)");
      }
    }
    RegisterName(spec.name, where, "name");
    RegisterSerialPort(spec.name, spec.port, where);

    // '\' lines: extra reset commands; the last one may end with '/' to start device lines.
    const std::string commands_of = "'" + spec.name + "' (extra commands)";
    const std::string devices_of = "'" + spec.name + "' (device lines)";
    while (continuation == '\\') {
      BlockEnd end;
      const Line* cmd_line = NextContinuationLine(commands_of, &end);
      if (cmd_line == nullptr && end == BlockEnd::kEndOfFile) {
        Fail(where, "extra commands",
             "the line ends with '\\' but the file ends before the command line");
      }
      if (cmd_line == nullptr) {  // a device line, a blank line or comments to the end (warned)
        continuation = 0;
        break;
      }
      const ConfigLocation cmd_where = Where(*cmd_line);
      std::string_view text = cmd_line->text;
      continuation = ContinuationOf(text);
      if (continuation != 0) text.remove_suffix(1);
      const std::string command(Trim(text));
      if (command.empty()) {
        config_.warnings.push_back({cmd_where, "empty extra command line ignored"});
        continue;
      }
      if (command.front() == '*') {
        const double seconds = ParseDouble(command.substr(1), cmd_where, "sleep");
        if (seconds < 0.0) Fail(cmd_where, "sleep", "a '*N' sleep must not be negative");
      }
      // Only whole lines are comments: the reference sends this one as it is, and a unit may refuse
      // the whole command (the emulator does: a hemisphere line silently not set).
      if (command.find('#') != std::string::npos) {
        config_.warnings.push_back(
            {cmd_where,
             "extra command '" + command +
                 "' contains '#': it is sent to the tracker as it is, comment included "
                 "(as by the reference; vrpn.cfg has whole-line comments only), and the "
                 "tracker may refuse the command; put the comment on a line of its own"});
      }
      spec.extra_commands.push_back(command);
    }

    // '/' lines: button devices on this tracker's sensors.
    while (continuation == '/') {
      BlockEnd end;
      const Line* dev_line = NextContinuationLine(devices_of, &end);
      if (dev_line == nullptr && end == BlockEnd::kEndOfFile) {
        Fail(where, "device line", "a line ends with '/' but the file ends before the device line");
      }
      if (dev_line == nullptr)
        break;  // a device line, a blank line or comments to the end (warned)
      const ConfigLocation dev_where = Where(*dev_line);
      std::string_view text = dev_line->text;
      continuation = ContinuationOf(text);
      if (continuation == '\\') {
        Fail(dev_where, "device line", "a device line cannot be followed by '\\' command lines");
      }
      if (continuation != 0) text.remove_suffix(1);
      spec.buttons.push_back(ParseButton(Tokenize(text), dev_where, spec.name));
    }
    config_.fastrak_trackers.push_back(std::move(spec));
  }

  ButtonDeviceSpec ParseButton(const std::vector<std::string>& tokens, const ConfigLocation& where,
                               const std::string& tracker) {
    if (tokens.empty()) Fail(where, "device line", "empty device line after '/'");
    ButtonDeviceSpec button;
    button.location = where;
    size_t expected = 3;
    if (tokens[0] == "FTStylus") {
      button.kind = ButtonDeviceKind::kFastrakStylus;
    } else if (tokens[0] == "Stylus") {
      button.kind = ButtonDeviceKind::kIs900Stylus;
    } else if (tokens[0] == "Wand") {
      button.kind = ButtonDeviceKind::kIs900Wand;
      expected = 11;
    } else {
      Fail(where, "device line",
           "unknown device '" + tokens[0] + "' after '/' (expected FTStylus, Stylus or Wand)");
    }
    if (tokens.size() < expected) {
      Fail(where, tokens[0],
           "expected " + std::to_string(expected - 1) + " values after '" + tokens[0] + "', got " +
               std::to_string(tokens.size() - 1));
    }
    // The reference reads these lines with sscanf and ignores what follows the last field.
    WarnIgnoredTokens(tokens, expected, where, "the " + tokens[0] + " fields");
    button.name = tokens[1];
    button.sensor = ParseInt(tokens[2], where, "sensor");
    if (button.sensor < 0 || button.sensor > 3) {
      Fail(where, "sensor", "must be 0..3 (Fastrak stations 1..4), got " + tokens[2]);
    }
    if (button.kind == ButtonDeviceKind::kFastrakStylus && button.sensor != 0) {
      config_.warnings.push_back(
          {where, "FTStylus on sensor " + tokens[2] +
                      ": the Fastrak reads the stylus switch on station 1 (sensor 0) only, so "
                      "this button never reports a press (the stylus still tracks)"});
    }
    for (size_t i = 3; i < expected; ++i) {
      button.wand_ranges[i - 3] = ParseDouble(tokens[i], where, "wand range");
    }
    RegisterButtonName(button.name, tracker, where);
    return button;
  }

  void ParseNull(const std::vector<std::string>& tokens, const ConfigLocation& where) {
    if (tokens.size() != 4) {
      Fail(where, "vrpn_Tracker_NULL", "expected 'vrpn_Tracker_NULL <name> <sensors> <rate_hz>'");
    }
    NullTrackerSpec spec;
    spec.location = where;
    spec.name = tokens[1];
    spec.sensors = ParseInt(tokens[2], where, "sensors");
    if (spec.sensors < 1) Fail(where, "sensors", "must be at least 1");
    spec.rate_hz = ParseDouble(tokens[3], where, "rate");
    if (spec.rate_hz < 0.0) Fail(where, "rate", "must not be negative");
    RegisterName(spec.name, where, "name");
    config_.null_trackers.push_back(std::move(spec));
  }

  void ParseCalibration(const std::vector<std::string>& tokens, const ConfigLocation& where) {
    if (tokens.size() < 3) {
      Fail(where, tokens.size() < 2 ? "tracker" : "calibration_file",
           "missing; expected 'trackcal_Calibration <tracker> <calibration_file> [raw=<name>] "
           "[outside=clamp|fade|linear] [fade_distance=<metres>] [sensor=<n>]'");
    }
    CalibrationSpec spec;
    spec.location = where;
    spec.tracker = tokens[1];
    spec.file = tokens[2];
    if (spec.file.is_relative()) {
      spec.file = std::filesystem::path(file_name_).parent_path() / spec.file;
    }
    std::set<std::string> given;
    for (size_t i = 3; i < tokens.size(); ++i) {
      const std::string& option = tokens[i];
      const size_t eq = option.find('=');
      const std::string key = option.substr(0, eq);
      const std::string value = eq == std::string::npos ? std::string() : option.substr(eq + 1);
      if (eq == std::string::npos || value.empty()) {
        Fail(where, key, "expected key=value, got '" + option + "'");
      }
      // outside=clamp ... outside=fade would otherwise serve the last one silently.
      if (!given.insert(key).second) Fail(where, key, "given twice");
      if (key == "raw") {
        RegisterName(value, where, "raw");
        spec.raw_name = value;
      } else if (key == "outside") {
        if (value == "clamp") {
          spec.outside = OutsidePolicy::kClamp;
        } else if (value == "fade") {
          spec.outside = OutsidePolicy::kFade;
        } else if (value == "linear") {
          spec.outside = OutsidePolicy::kLinear;
        } else {
          Fail(where, "outside", "expected clamp, fade or linear, got '" + value + "'");
        }
      } else if (key == "fade_distance") {
        const double d = ParseDouble(value, where, "fade_distance");
        if (!(d > 0.0)) Fail(where, "fade_distance", "must be a positive distance in metres");
        spec.fade_distance_m = d;
      } else if (key == "sensor") {
        const int sensor = ParseInt(value, where, "sensor");
        if (sensor < 0 || sensor >= kMaxCalibrationSensor) {
          Fail(where, "sensor",
               "must be 0.." + std::to_string(kMaxCalibrationSensor - 1) +
                   " (the VRPN sensor number: Fastrak station n is sensor n-1), got " + value);
        }
        spec.sensor = sensor;
      } else {
        Fail(where, key,
             "unknown option (expected raw=<name>, outside=clamp|fade|linear, "
             "fade_distance=<metres> "
             "or sensor=<n>)");
      }
    }
    config_.calibrations.push_back(std::move(spec));
  }

  void ParsePassthrough(const std::vector<std::string>& tokens, const ConfigLocation& where) {
    if (tokens.size() != 3) {
      Fail(where, tokens.size() < 2 ? "name" : (tokens.size() < 3 ? "source" : "source"),
           "expected 'trackcal_Tracker_Passthrough <name> <source>' with source "
           "Device@host[:port] or *Device");
    }
    PassthroughSpec spec;
    spec.location = where;
    spec.name = tokens[1];
    spec.source = tokens[2];
    std::string_view s = spec.source;
    const bool star = !s.empty() && s.front() == '*';
    if (star) s.remove_prefix(1);
    // The text before the last '@' is taken as the device so that a device holding '@' is refused
    // as such below (VRPN clients read the device up to the first '@' and never reach it).
    const size_t at = s.rfind('@');
    spec.source_device = std::string(s.substr(0, at));
    if (spec.source_device.empty()) Fail(where, "source", "missing device name in '" + spec.source + "'");
    if (const std::string why = UnaddressableName(spec.source_device); !why.empty()) {
      Fail(where, "source", why);
    }
    if (std::string warning = NonUtf8NameWarning(spec.source_device, "source"); !warning.empty()) {
      config_.warnings.push_back({where, std::move(warning)});
    }
    if (at == std::string_view::npos) {
      if (!star) {
        Fail(where, "source",
             "'" + spec.source + "' names no server; write Device@host[:port], or *Device for a "
             "device of this server");
      }
      if (spec.source_device == spec.name) {
        Fail(where, "source", "a pass-through cannot read its own name");
      }
    } else {
      std::string_view host = s.substr(at + 1);
      // The connection part as VRPN clients (and VrpnTrackerClient) read it: "tcp:" anywhere asks
      // for TCP only, and a "tcp://", "x-vrpn://" or "tcp:" prefix is not part of the host.
      spec.source_tcp_only = host.find("tcp:") != std::string_view::npos;
      for (const std::string_view prefix : {"tcp://", "x-vrpn://", "tcp:"}) {
        if (host.substr(0, prefix.size()) == prefix) {
          host.remove_prefix(prefix.size());
          break;
        }
      }
      const size_t colon = host.rfind(':');
      if (colon != std::string_view::npos) {
        const std::string port(host.substr(colon + 1));
        spec.source_port = ParseInt(port, where, "source port");
        if (spec.source_port < 1 || spec.source_port > 65535) {
          Fail(where, "source port", "must be 1..65535, got " + port);
        }
        host = host.substr(0, colon);
      }
      if (host.empty()) Fail(where, "source", "missing host after '@' in '" + spec.source + "'");
      // A host name or an IPv4 address, checked here so the error names this line (the client
      // would refuse anything else at start, naming no line).
      for (const char c : host) {
        if (!std::isalnum(static_cast<unsigned char>(c)) && c != '.' && c != '-' && c != '_') {
          Fail(where, "source",
               "host '" + std::string(host) + "' in '" + spec.source +
                   "' is not a host name or IPv4 address (write Device@host[:port], "
                   "Device@tcp://host[:port]; IPv6 is not supported)");
        }
      }
      spec.source_host = std::string(host);
    }
    RegisterName(spec.name, where, "name");
    config_.passthroughs.push_back(std::move(spec));
  }

  void CheckCalibrations() {
    // Per tracker: the calibration for every sensor, or the one of each listed sensor, and the
    // line that gave raw=.
    std::map<std::string, const CalibrationSpec*> all_sensors, raw_line;
    std::map<std::pair<std::string, int>, const CalibrationSpec*> per_sensor;
    std::map<std::string, const CalibrationSpec*> any_sensor;
    for (const CalibrationSpec& c : config_.calibrations) {
      bool is_tracker = false;
      for (const auto& t : config_.fastrak_trackers) is_tracker |= t.name == c.tracker;
      for (const auto& t : config_.null_trackers) is_tracker |= t.name == c.tracker;
      for (const auto& t : config_.passthroughs) is_tracker |= t.name == c.tracker;
      if (!is_tracker) {
        Fail(c.location, "tracker", "no tracker named '" + c.tracker + "' is defined in this file");
      }
      // One pose cannot be corrected twice: a line for every sensor excludes any other line of
      // that tracker, and a sensor= line excludes another one for the same sensor.
      if (auto it = all_sensors.find(c.tracker); it != all_sensors.end()) {
        Fail(c.location, c.sensor ? "sensor" : "tracker",
             "tracker '" + c.tracker + "' already has a calibration at " +
                 it->second->location.ToString() + " (for every sensor)");
      }
      if (!c.sensor) {
        if (auto it = any_sensor.find(c.tracker); it != any_sensor.end()) {
          Fail(c.location, "tracker",
               "tracker '" + c.tracker + "' already has a calibration for sensor " +
                   std::to_string(*it->second->sensor) + " at " + it->second->location.ToString() +
                   " (give sensor=<n> on every calibration line of a tracker, or on none)");
        }
        all_sensors.emplace(c.tracker, &c);
      } else {
        const auto [it, inserted] = per_sensor.emplace(std::make_pair(c.tracker, *c.sensor), &c);
        if (!inserted) {
          Fail(c.location, "sensor",
               "sensor " + std::to_string(*c.sensor) + " of tracker '" + c.tracker +
                   "' already has a calibration at " + it->second->location.ToString());
        }
        any_sensor.emplace(c.tracker, &c);
      }
      if (c.raw_name) {
        const auto [it, inserted] = raw_line.emplace(c.tracker, &c);
        if (!inserted) {
          Fail(c.location, "raw",
               "tracker '" + c.tracker + "' already serves its raw reports as '" +
                   *it->second->raw_name + "' (" + it->second->location.ToString() + ")");
        }
      }
    }
  }

  // A pass-through of this server's own device ("*Device") must name a tracker served here;
  // otherwise it connects to this server and waits for reports that never come.
  void CheckLocalPassthroughs() {
    std::map<std::string, const PassthroughSpec*> local;  // pass-through name -> spec
    std::set<std::string> trackers;
    for (const auto& t : config_.fastrak_trackers) trackers.insert(t.name);
    for (const auto& t : config_.null_trackers) trackers.insert(t.name);
    for (const auto& c : config_.calibrations) {
      if (c.raw_name) trackers.insert(*c.raw_name);
    }
    for (const auto& p : config_.passthroughs) {
      trackers.insert(p.name);
      if (p.source_host.empty()) local.emplace(p.name, &p);
    }
    for (const auto& [name, p] : local) {
      if (trackers.count(p->source_device) == 0) {
        bool is_button = false;
        for (const auto& t : config_.fastrak_trackers) {
          for (const auto& b : t.buttons) is_button |= b.name == p->source_device;
        }
        Fail(p->location, "source",
             is_button ? "'" + p->source_device + "' is a button of this server, not a tracker"
                       : "no tracker named '" + p->source_device +
                             "' is served by this file; write " + p->source_device +
                             "@host[:port] for a device of another server");
      }
      // Pass-throughs reading each other in a circle have no report to pass on.
      std::string chain = name;
      const PassthroughSpec* at = p;
      for (size_t steps = 0; steps <= local.size(); ++steps) {
        chain += " -> " + at->source_device;
        const auto next = local.find(at->source_device);
        if (next == local.end()) break;
        if (next->first == name) {
          Fail(p->location, "source", "pass-throughs read each other in a circle (" + chain + ")");
        }
        at = next->second;
      }
    }
  }

  std::string file_name_;
  std::vector<Line> lines_;
  std::string encoding_problem_;  // "" for text
  int encoding_problem_line_ = 1;
  size_t next_ = 0;
  // Every device name of the file: where it was first used and, for a tracker name that a button
  // of that tracker shares, where the button was declared.
  struct NameUse {
    ConfigLocation location;
    std::optional<ConfigLocation> button;
  };
  std::map<std::string, NameUse> names_;
  // Serial ports of the Fastrak lines, by canonical path (RegisterSerialPort).
  struct PortUse {
    std::string tracker;
    std::string port;  // as written
    ConfigLocation location;
  };
  std::map<std::string, PortUse> ports_;
  // The continuation block that a blank line ended, until the next line that is not a comment.
  struct BlankLineEnd {
    std::string block;
    ConfigLocation location;  // of the blank line
  };
  std::optional<BlankLineEnd> blank_line_end_;
  VrpnConfig config_;
};

}  // namespace

std::string ConfigLocation::ToString() const { return file + ":" + std::to_string(line); }

std::string ConfigWarning::ToString() const {
  // The message quotes the file (an unknown device type, ignored tokens), and this line is printed
  // on the operator's terminal.
  return PrintableForLog(location.ToString() + ": warning: " + message);
}

const CalibrationSpec* VrpnConfig::FindCalibration(std::string_view name) const {
  for (const CalibrationSpec& c : calibrations) {
    if (c.tracker == name) return &c;
  }
  return nullptr;
}

bool IsSupportedBaudRate(int baud) {
  for (int b : {300, 1200, 2400, 4800, 9600, 19200, 38400, 57600, 115200}) {
    if (baud == b) return true;
  }
  return false;
}

VrpnConfig ParseVrpnConfig(std::string_view text, const std::string& file_name) {
  return Parser(text, file_name).Parse();
}

VrpnConfig ReadVrpnConfig(const std::filesystem::path& path) {
  // A folder opens as a stream and reads as an empty file: "no device trackcal-server can serve".
  std::error_code ec;
  if (std::filesystem::is_directory(path, ec)) {
    throw std::runtime_error(path.string() +
                             ": is a folder, not a VRPN configuration file (give -f the vrpn.cfg)");
  }
  errno = 0;
  std::ifstream in(path, std::ios::binary);
  if (!in) {
    throw std::runtime_error(path.string() + ": cannot open the VRPN configuration file: " +
                             (errno != 0 ? std::strerror(errno) : "unknown error"));
  }
  std::ostringstream text;
  text << in.rdbuf();
  if (in.bad()) throw std::runtime_error(path.string() + ": read error");
  return ParseVrpnConfig(text.str(), path.string());
}

}  // namespace trackcal::vrpn
