#include "core/printable_text.h"

#include <gtest/gtest.h>

#include <string>

namespace trackcal {
namespace {

constexpr PrintableFor kBothUses[] = {PrintableFor::kMessage, PrintableFor::kLogLine};

// What both uses do alike: the UTF-8 walk and the escape of C0 controls other than tab and line
// feed, DEL and every byte that is not well-formed UTF-8.
TEST(Printable, BothUsesKeepPrintableUtf8AndEscapeTheRest) {
  struct Case {
    std::string text;
    std::string printable;
  };
  const Case kCases[] = {
      {"poses.csv:3: column x: 'abc' is not a number",
       "poses.csv:3: column x: 'abc' is not a number"},
      {"Tracker0@host:3883 ~", "Tracker0@host:3883 ~"},
      // Two-, three- and four-byte characters stay, the smallest and largest of each length too.
      {"Jos\xc3\xa9 \xe2\x82\xac \xf0\x9f\x98\x80", "Jos\xc3\xa9 \xe2\x82\xac \xf0\x9f\x98\x80"},
      {"J\xc3\xb6rg \xe2\x9c\x93", "J\xc3\xb6rg \xe2\x9c\x93"},
      {"\xc2\xa0\xdf\xbf", "\xc2\xa0\xdf\xbf"},  // U+00A0, U+07FF
      {"\xe0\xa0\x80\xed\x9f\xbf\xee\x80\x80",
       "\xe0\xa0\x80\xed\x9f\xbf\xee\x80\x80"},  // U+0800, U+D7FF, U+E000
      {"\xf0\x90\x80\x80\xf4\x8f\xbf\xbf",
       "\xf0\x90\x80\x80\xf4\x8f\xbf\xbf"},  // U+10000, U+10FFFF
      // C0 controls, CR, DEL.
      {std::string("1.5\0x\r\x7f", 7), "1.5\\x00x\\x0d\\x7f"},
      {std::string("a\0b\x7f", 4), "a\\x00b\\x7f"},
      {"x\x1b[2J", "x\\x1b[2J"},
      // A Latin-1 byte, a lone continuation byte, truncated sequences, a lead byte followed by
      // ASCII, overlong forms ('/' in two bytes, U+07FF in three, U+FFFF in four), a UTF-16
      // surrogate, a code point above U+10FFFF, bytes that never occur in UTF-8.
      {"Jos\xe9", "Jos\\xe9"},
      {"\x80", "\\x80"},
      {"\xe2\x82", "\\xe2\\x82"},
      {"\xe2\x9c", "\\xe2\\x9c"},
      {"\xc3(", "\\xc3("},
      {"\xc0\xaf", "\\xc0\\xaf"},
      {"\xe0\x9f\xbf", "\\xe0\\x9f\\xbf"},
      {"\xf0\x8f\xbf\xbf", "\\xf0\\x8f\\xbf\\xbf"},
      {"\xed\xa0\x80", "\\xed\\xa0\\x80"},
      {"\xf4\x90\x80\x80", "\\xf4\\x90\\x80\\x80"},
      {"\xf5\xff", "\\xf5\\xff"},
  };
  for (const PrintableFor use : kBothUses) {
    SCOPED_TRACE(use == PrintableFor::kMessage ? "message" : "log line");
    for (const Case& c : kCases) EXPECT_EQ(Printable(c.text, use), c.printable);
    // Idempotent: the output has no byte it would change (a backslash is kept as it is).
    for (const std::string& text :
         {std::string("x\x1b\xff\n\t\xc2\x9b\\x41"), std::string("\xe2\x82\xac\x00\xc3", 6)}) {
      const std::string once = Printable(text, use);
      EXPECT_EQ(Printable(once, use), once);
    }
  }
}

TEST(Printable, AMessageKeepsTabLineFeedAndC1) {
  // A message may have several lines, and a Python str holds a C1 control.
  EXPECT_EQ(PrintableForMessage("a\tb\nc"), "a\tb\nc");
  EXPECT_EQ(PrintableForMessage("\xc2\x80\xc2\x9b\xc2\x9f"), "\xc2\x80\xc2\x9b\xc2\x9f");
}

TEST(Printable, ALogLineEscapesTabLineFeedAndC1) {
  // A newline would forge a log line; U+009B is CSI on terminals that take C1 controls.
  EXPECT_EQ(PrintableForLog("a\tb\nc"), "a\\x09b\\x0ac");
  EXPECT_EQ(PrintableForLog("\xc2\x9b"), "\\xc2\\x9b");
  EXPECT_EQ(PrintableForLog("\xc2\x80\xc2\x9f\xc2\xa0"), "\\xc2\\x80\\xc2\\x9f\xc2\xa0");
}

TEST(Printable, DeviceBytesEscapeEverythingButPrintableAscii) {
  // A serial reply quoted in a warning: binary record bytes are not UTF-8 text, and an escaped
  // backslash keeps the quote unambiguous.
  EXPECT_EQ(Printable("21S0A \\ ok", PrintableFor::kDeviceBytes), "21S0A \\x5c ok");
  EXPECT_EQ(Printable(std::string("\r\n\t\0\x7f", 5), PrintableFor::kDeviceBytes),
            "\\x0d\\x0a\\x09\\x00\\x7f");
  EXPECT_EQ(Printable("\xc3\xa9\xc2\x9b\xff", PrintableFor::kDeviceBytes),
            "\\xc3\\xa9\\xc2\\x9b\\xff");
}

TEST(FirstNonUtf8Byte, IsWherePrintableEscapesTheFirstByteAboveAscii) {
  EXPECT_EQ(FirstNonUtf8Byte(""), std::string_view::npos);
  EXPECT_EQ(FirstNonUtf8Byte("Jos\xc3\xa9 \xe2\x82\xac \xf0\x9f\x98\x80"), std::string_view::npos);
  EXPECT_EQ(FirstNonUtf8Byte(std::string("a\0b\r", 4)), std::string_view::npos);  // text bytes
  EXPECT_EQ(FirstNonUtf8Byte("\xc2\x9b"), std::string_view::npos);  // a C1 control is UTF-8
  EXPECT_EQ(FirstNonUtf8Byte("Jos\xe9"), 3u);
  EXPECT_EQ(FirstNonUtf8Byte("\x89PNG"), 0u);
  EXPECT_EQ(FirstNonUtf8Byte("ab\xe2\x82"), 2u);        // truncated
  EXPECT_EQ(FirstNonUtf8Byte("\xc3\xa9\xc0\xaf"), 2u);  // overlong
  EXPECT_EQ(FirstNonUtf8Byte("x\xed\xa0\x80"), 1u);     // surrogate
  EXPECT_EQ(FirstNonUtf8Byte("\xf4\x90\x80\x80"), 0u);  // above U+10FFFF
}

TEST(ClosestName, Nominal) {
  // A key, field or column misspelt by one or two letters names the one meant.
  EXPECT_EQ(ClosestName("verison", {"format", "version", "description"}), "version");  // swap
  EXPECT_EQ(ClosestName("term", {"noise", "terms", "loss"}), "terms");                 // dropped
  EXPECT_EQ(ClosestName("rep_xq", {"station", "rep_qx", "rep_qy"}), "rep_qx");
  EXPECT_EQ(ClosestName("Degree", {"degree", "ridge"}), "degree");  // letter case alone
}

TEST(ClosestName, NothingNearEnoughIsNoSuggestion) {
  EXPECT_EQ(ClosestName("temperature", {"station", "set", "sensor"}), "");
  EXPECT_EQ(ClosestName("", {"a", "b"}), "");
  EXPECT_EQ(ClosestName("x", {}), "");
  // Short names are one edit apart from many others: "min" is not a misspelt "max", nor "y" "x".
  EXPECT_EQ(ClosestName("min", {"max"}), "");
  EXPECT_EQ(ClosestName("y", {"x", "z"}), "");
  EXPECT_EQ(ClosestName("Y", {"y"}), "y");
  // A name is not its own suggestion.
  EXPECT_EQ(ClosestName("terms", {"terms"}), "");
}

TEST(ClosestName, NearestWinsAndTiesGoToTheFirst) {
  EXPECT_EQ(ClosestName("degre", {"degrees", "degree"}), "degree");  // 1 edit before 2
  EXPECT_EQ(ClosestName("rep_q", {"rep_qx", "rep_qy"}), "rep_qx");
}

}  // namespace
}  // namespace trackcal
