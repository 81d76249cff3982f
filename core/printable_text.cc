#include "core/printable_text.h"

#include <algorithm>
#include <cctype>
#include <cstddef>

namespace trackcal {
namespace {

// The length of the well-formed UTF-8 sequence at text[i] (i < text.size()), 0 if none starts
// there: its length from the lead byte, then continuation bytes 10xxxxxx, in the ranges that
// exclude overlong forms, surrogates and code points above U+10FFFF (RFC 3629). 1 for an ASCII
// byte. `c1_is_invalid`: U+0080-U+009F count as no sequence (a log line escapes the C1 controls).
size_t Utf8SequenceLength(std::string_view text, size_t i, bool c1_is_invalid) {
  const auto byte = [&text](size_t k) { return static_cast<unsigned char>(text[k]); };
  const unsigned char c = byte(i);
  if (c < 0x80) return 1;
  size_t length = 0;
  unsigned char low = 0x80, high = 0xbf;  // allowed range of the second byte
  if (c >= 0xc2 && c <= 0xdf) {
    length = 2;
    if (c == 0xc2 && c1_is_invalid) low = 0xa0;
  } else if (c >= 0xe0 && c <= 0xef) {
    length = 3;
    if (c == 0xe0) low = 0xa0;
    if (c == 0xed) high = 0x9f;
  } else if (c >= 0xf0 && c <= 0xf4) {
    length = 4;
    if (c == 0xf0) low = 0x90;
    if (c == 0xf4) high = 0x8f;
  }
  if (length == 0 || i + length > text.size()) return 0;
  for (size_t k = 1; k < length; ++k) {
    const unsigned char b = byte(i + k);
    if (k == 1 ? (b < low || b > high) : (b < 0x80 || b > 0xbf)) return 0;
  }
  return length;
}

}  // namespace

std::string Printable(std::string_view text, PrintableFor use) {
  const bool log_line = use == PrintableFor::kLogLine;
  const bool device_bytes = use == PrintableFor::kDeviceBytes;
  std::string out;
  out.reserve(text.size());
  const auto byte = [&text](size_t i) { return static_cast<unsigned char>(text[i]); };
  const auto escape = [&out](unsigned char c) {
    static constexpr char kHex[] = "0123456789abcdef";
    out += "\\x";
    out += kHex[c >> 4];
    out += kHex[c & 15];
  };
  for (size_t i = 0; i < text.size();) {
    const unsigned char c = byte(i);
    if (c < 0x80) {
      const bool kept_layout = use == PrintableFor::kMessage && (c == '\t' || c == '\n');
      if ((c < 0x20 && !kept_layout) || c == 0x7f || (device_bytes && c == '\\')) {
        escape(c);
      } else {
        out += static_cast<char>(c);
      }
      ++i;
      continue;
    }
    const size_t length =
        device_bytes ? 0 : Utf8SequenceLength(text, i, /*c1_is_invalid=*/log_line);
    if (length > 0) {
      out.append(text.substr(i, length));
      i += length;
    } else {
      // The lead byte alone; the bytes after it are looked at again (a continuation byte is then
      // escaped as a lone one, a new lead byte may start a valid sequence).
      escape(c);
      ++i;
    }
  }
  return out;
}

size_t FirstNonUtf8Byte(std::string_view text) {
  for (size_t i = 0; i < text.size();) {
    const size_t length = Utf8SequenceLength(text, i, /*c1_is_invalid=*/false);
    if (length == 0) return i;
    i += length;
  }
  return std::string_view::npos;
}

std::string Utf16TextProblem(std::string_view text, std::string_view kind) {
  const std::string save = "; save the " + std::string(kind) + " as UTF-8";
  // UTF-32's little-endian mark starts with UTF-16's: a UTF-32 file was called UTF-16. (UTF-16
  // text does not start with U+0000 after its mark.)
  using namespace std::string_view_literals;
  if (text.substr(0, 4) == "\xFF\xFE\0\0"sv || text.substr(0, 4) == "\0\0\xFE\xFF"sv) {
    return "UTF-32 text (a byte order mark FF FE 00 00 or 00 00 FE FF)" + save;
  }
  if (text.substr(0, 2) != "\xFF\xFE" && text.substr(0, 2) != "\xFE\xFF") return "";
  return "UTF-16 text (a byte order mark FF FE or FE FF)" + save;
}

std::string ClosestName(std::string_view word, const std::vector<std::string>& candidates) {
  const auto lower = [](std::string_view s) {
    std::string out(s);
    for (char& c : out) c = static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
    return out;
  };
  const std::string a = lower(word);
  std::string best;
  size_t best_distance = std::string::npos;
  for (const std::string& candidate : candidates) {
    if (candidate == word || word.empty()) continue;
    const std::string b = lower(candidate);
    const size_t allowed = b.size() <= 2 ? 0 : b.size() <= 5 ? 1 : 2;
    if (a.size() > b.size() + allowed || b.size() > a.size() + allowed) continue;
    // Optimal string alignment distance (Damerau-Levenshtein without repeated edits of a
    // substring), three rows.
    std::vector<size_t> before(b.size() + 1), previous(b.size() + 1), current(b.size() + 1);
    for (size_t j = 0; j <= b.size(); ++j) previous[j] = j;
    for (size_t i = 1; i <= a.size(); ++i) {
      current[0] = i;
      for (size_t j = 1; j <= b.size(); ++j) {
        const size_t cost = a[i - 1] == b[j - 1] ? 0 : 1;
        current[j] = std::min({previous[j] + 1, current[j - 1] + 1, previous[j - 1] + cost});
        if (i > 1 && j > 1 && a[i - 1] == b[j - 2] && a[i - 2] == b[j - 1]) {
          current[j] = std::min(current[j], before[j - 2] + 1);
        }
      }
      before.swap(previous);
      previous.swap(current);
    }
    const size_t distance = previous[b.size()];
    if (distance <= allowed && distance < best_distance) {
      best = candidate;
      best_distance = distance;
    }
  }
  return best;
}

}  // namespace trackcal
