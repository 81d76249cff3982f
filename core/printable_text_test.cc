#include "core/printable_text.h"

#include <gtest/gtest.h>

#include <string>

namespace trackcal {
namespace {

constexpr PrintableFor kBothUses[] = {PrintableFor::kMessage, PrintableFor::kLogLine};

// What both uses do alike: the UTF-8 walk and the escape of C0 controls other than tab and line
// feed, DEL and every byte that is not well-formed UTF-8.
TEST(Printable, BothUsesKeepPrintableUtf8AndEscapeTheRest) {
  for (const PrintableFor use : kBothUses) {
    SCOPED_TRACE(use == PrintableFor::kMessage ? "message" : "log line");
    EXPECT_EQ(Printable("poses.csv:3: column x: 'abc' is not a number", use),
              "poses.csv:3: column x: 'abc' is not a number");
    EXPECT_EQ(Printable("Tracker0@host:3883 ~", use), "Tracker0@host:3883 ~");
    // Two-, three- and four-byte characters stay, the smallest and largest of each length too.
    EXPECT_EQ(Printable("Jos\xc3\xa9 \xe2\x82\xac \xf0\x9f\x98\x80", use),
              "Jos\xc3\xa9 \xe2\x82\xac \xf0\x9f\x98\x80");
    EXPECT_EQ(Printable("J\xc3\xb6rg \xe2\x9c\x93", use), "J\xc3\xb6rg \xe2\x9c\x93");
    EXPECT_EQ(Printable("\xc2\xa0\xdf\xbf", use), "\xc2\xa0\xdf\xbf");  // U+00A0, U+07FF
    EXPECT_EQ(Printable("\xe0\xa0\x80\xed\x9f\xbf\xee\x80\x80", use),
              "\xe0\xa0\x80\xed\x9f\xbf\xee\x80\x80");  // U+0800, U+D7FF, U+E000
    EXPECT_EQ(Printable("\xf0\x90\x80\x80\xf4\x8f\xbf\xbf", use),
              "\xf0\x90\x80\x80\xf4\x8f\xbf\xbf");  // U+10000, U+10FFFF
    // C0 controls, CR, DEL.
    EXPECT_EQ(Printable(std::string("1.5\0x\r\x7f", 7), use), "1.5\\x00x\\x0d\\x7f");
    EXPECT_EQ(Printable(std::string("a\0b\x7f", 4), use), "a\\x00b\\x7f");
    EXPECT_EQ(Printable("x\x1b[2J", use), "x\\x1b[2J");
    // A Latin-1 byte, a lone continuation byte, truncated sequences, a lead byte followed by
    // ASCII, overlong forms ('/' in two bytes, U+07FF in three, U+FFFF in four), a UTF-16
    // surrogate, a code point above U+10FFFF, bytes that never occur in UTF-8.
    EXPECT_EQ(Printable("Jos\xe9", use), "Jos\\xe9");
    EXPECT_EQ(Printable("\x80", use), "\\x80");
    EXPECT_EQ(Printable("\xe2\x82", use), "\\xe2\\x82");
    EXPECT_EQ(Printable("\xe2\x9c", use), "\\xe2\\x9c");
    EXPECT_EQ(Printable("\xc3(", use), "\\xc3(");
    EXPECT_EQ(Printable("\xc0\xaf", use), "\\xc0\\xaf");
    EXPECT_EQ(Printable("\xe0\x9f\xbf", use), "\\xe0\\x9f\\xbf");
    EXPECT_EQ(Printable("\xf0\x8f\xbf\xbf", use), "\\xf0\\x8f\\xbf\\xbf");
    EXPECT_EQ(Printable("\xed\xa0\x80", use), "\\xed\\xa0\\x80");
    EXPECT_EQ(Printable("\xf4\x90\x80\x80", use), "\\xf4\\x90\\x80\\x80");
    EXPECT_EQ(Printable("\xf5\xff", use), "\\xf5\\xff");
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

}  // namespace
}  // namespace trackcal
