// The one escaper for text that quotes bytes trackcal did not write (a user's file, a vrpn.cfg
// line, a VRPN client's names and messages) before it reaches an exception message, a terminal or a
// log. A library of its own (trackcal_text, no dependencies) so that the VRPN server, which does
// not link trackcal_core, uses the same code as the file readers.
#pragma once

#include <cstddef>
#include <string>
#include <string_view>
#include <vector>

namespace trackcal {

// Which characters, besides the ones every use escapes, are written as \xNN.
enum class PrintableFor {
  // An exception message (C++ what(), a Python ValueError): tab and line feed stay (a message may
  // have several lines), and so do C1 controls encoded as UTF-8 (a Python str holds them).
  kMessage,
  // One line of a log or of a terminal: tab, line feed and the C1 controls U+0080-U+009F are
  // escaped too (a newline would forge a log line; U+009B is CSI on terminals that take C1).
  kLogLine,
  // Bytes a device sent (a serial line's replies and binary records), which are not text: every
  // byte outside printable ASCII, and the backslash (so that the quote reads back unambiguously),
  // is escaped; no UTF-8 sequence is kept.
  kDeviceBytes,
};

// `text` with every byte that is not well-formed UTF-8 (RFC 3629: no overlong forms, no surrogates,
// nothing above U+10FFFF; a lone, stray or truncated byte) and every C0 control and DEL (but what
// `use` keeps) written as \xNN with lower-case hex, as Python's "backslashreplace" writes it;
// printable ASCII and other UTF-8 stay. A NUL kept raw would cut what() short (a C string), an
// invalid byte would fail Python's conversion to str ("'utf-8' codec can't decode byte 0xe9",
// naming no file), and an escape byte could drive the operator's terminal.
// Idempotent: its output has no byte it would change.
std::string Printable(std::string_view text, PrintableFor use);

// The offset of the first byte of `text` that is not part of well-formed UTF-8 (as Printable judges
// it; C1 controls count as UTF-8), or std::string_view::npos if it is all UTF-8.
size_t FirstNonUtf8Byte(std::string_view text);

// "UTF-16 text (a byte order mark FF FE or FE FF); save the <kind> as UTF-8" if `text` starts with
// a UTF-16 byte order mark (Notepad's "Unicode" and Excel's "Unicode text" saves), "UTF-32 text (a
// byte order mark FF FE 00 00 or 00 00 FE FF); ..." for UTF-32's, else "". The readers of UTF-8
// files read such a file as gibberish: "not a calibration file", "column station: missing from the
// header", or a model parsed without a word.
std::string Utf16TextProblem(std::string_view text, std::string_view kind);

// The one of `candidates` that `word` most likely misspells, for a "did you mean" hint in an error
// about an unknown key, a missing field or a missing column: the nearest by edit distance
// (inserting, deleting or replacing a letter, or swapping two neighbours, count 1 each; letter case
// is ignored), if it is within 0 edits of a name of 1-2 characters, 1 of 3-5 and 2 of longer ones
// (short names are a letter apart from many others: "min" is no misspelt "max"). The first of
// equally near ones; "" if none is near enough. `word` itself is never suggested.
std::string ClosestName(std::string_view word, const std::vector<std::string>& candidates);

// Printable(text, PrintableFor::kMessage).
inline std::string PrintableForMessage(std::string_view text) {
  return Printable(text, PrintableFor::kMessage);
}

// Printable(text, PrintableFor::kLogLine).
inline std::string PrintableForLog(std::string_view text) {
  return Printable(text, PrintableFor::kLogLine);
}

}  // namespace trackcal
