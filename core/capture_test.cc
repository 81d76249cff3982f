#include "core/capture.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstring>
#include <fstream>
#include <functional>
#include <limits>
#include <sstream>

#include "tests/test_utils.h"

namespace trackcal {
namespace {

using testing::MakeTempDir;
using testing::RandomRotation;
using testing::TestRng;

std::string ReadText(const std::filesystem::path& p) {
  std::ifstream in(p);
  std::stringstream s;
  s << in.rdbuf();
  return s.str();
}

void WriteText(const std::filesystem::path& p, const std::string& text) {
  std::ofstream(p) << text;
}

// The error message with the test's temporary folder cut from the file it names ("poses.csv:3:
// ..." for "/tmp/.../poses.csv:3: ...").
std::string ErrorOf(const std::function<void()>& f) {
  try {
    f();
  } catch (const std::exception& e) {
    std::string message = e.what();
    const size_t colon = message.find(':');
    const size_t slash = colon == std::string::npos ? std::string::npos : message.rfind('/', colon);
    return slash == std::string::npos ? message : message.substr(slash + 1);
  }
  return "";
}

// The standard columns of poses.csv, as a header line.
const char kPosesHeader[] =
    "station,set,sensor,time,rep_x,rep_y,rep_z,rep_qw,rep_qx,rep_qy,rep_qz,ref_x,ref_y,ref_z,"
    "ref_qw,ref_qx,ref_qy,ref_qz\n";

PoseCapture RandomPoses() {
  PoseCapture c;
  c.extra_columns = {"temperature_c"};
  const char* sets[] = {"calib", "valid", "reg"};
  for (int i = 0; i < 30; ++i) {
    PoseRecord r;
    r.station = i + 1;
    r.set = sets[i % 3];
    r.sensor = 1 + i % 2;
    r.time = 0.1 * i + 1.0 / 3.0;
    r.reported = Rigid3d(RandomRotation(TestRng()), Eigen::Vector3d(0.1 * i, -1.0 / 7, 2e-9));
    r.reference = Rigid3d(RandomRotation(TestRng()), Eigen::Vector3d(1.0 / 3, 0.25, -0.75 * i));
    r.extra = {20.0 + i / 9.0};
    c.records.push_back(r);
  }
  return c;
}

TEST(PosesCsv, Nominal) {
  const auto dir = MakeTempDir("capture_test");
  const PoseCapture written = RandomPoses();
  WritePoses(dir / "poses.csv", written);
  const std::string text = ReadText(dir / "poses.csv");
  EXPECT_EQ(
      text.substr(0, text.find('\n')),
      "station,set,sensor,time,rep_x,rep_y,rep_z,rep_qw,rep_qx,rep_qy,rep_qz,ref_x,ref_y,ref_z,"
      "ref_qw,ref_qx,ref_qy,ref_qz,temperature_c");
  const PoseCapture read = ReadPoses(dir / "poses.csv");
  ASSERT_EQ(read.records.size(), written.records.size());
  EXPECT_EQ(read.extra_columns, written.extra_columns);
  for (size_t i = 0; i < read.records.size(); ++i) {
    const PoseRecord& a = written.records[i];
    const PoseRecord& b = read.records[i];
    EXPECT_EQ(a.station, b.station);
    EXPECT_EQ(a.set, b.set);
    EXPECT_EQ(a.sensor, b.sensor);
    // Shortest round-trip formatting: every number reads back bit for bit.
    EXPECT_EQ(a.time, b.time);
    EXPECT_EQ(a.reported.translation, b.reported.translation);
    EXPECT_EQ(a.reported.rotation.coeffs(), b.reported.rotation.coeffs());
    EXPECT_EQ(a.reference.translation, b.reference.translation);
    EXPECT_EQ(a.reference.rotation.coeffs(), b.reference.rotation.coeffs());
    EXPECT_EQ(a.extra, b.extra);
  }
  // Writing what was read reproduces the file byte for byte.
  WritePoses(dir / "again.csv", read);
  EXPECT_EQ(ReadText(dir / "again.csv"), text);
}

TEST(PosesCsv, ColumnsByNameInAnyOrderWithExtras) {
  const auto dir = MakeTempDir("capture_test");
  WriteText(
      dir / "poses.csv",
      "ref_qz,ref_qy,ref_qx,ref_qw,ref_z,ref_y,ref_x,humidity,rep_qw,rep_qx,rep_qy,rep_qz,rep_x,"
      "rep_y,rep_z,time,sensor,set,station\r\n"
      "0,0,0,1,0.3,0.2,0.1,45.5,0,1,0,0,1.5,2.5,3.5,12.25,2,valid,7\r\n"
      "\n");
  const PoseCapture c = ReadPoses(dir / "poses.csv");
  ASSERT_EQ(c.records.size(), 1u);
  // A spreadsheet's byte order mark before the header is ignored.
  WriteText(dir / "bom.csv", "\xEF\xBB\xBF" + ReadText(dir / "poses.csv"));
  EXPECT_EQ(ReadPoses(dir / "bom.csv").records.size(), 1u);
  // Also before blank lines (a sheet whose first row is empty): the header is the first non-empty
  // line, the mark is not a line of its own. It was read as a header of one unnamed column.
  WriteText(dir / "bom_blank.csv", "\xEF\xBB\xBF\r\n\r\n" + ReadText(dir / "poses.csv"));
  EXPECT_EQ(ReadPoses(dir / "bom_blank.csv").records.size(), 1u);
  WriteText(dir / "bom_only.csv", "\xEF\xBB\xBF\n");
  EXPECT_EQ(ErrorOf([&] { ReadPoses(dir / "bom_only.csv"); }),
            "bom_only.csv:1: empty file, expected a header");
  // Old Mac spreadsheets end lines with CR alone; a bare CR inside a line is refused, naming it.
  std::string cr_only = ReadText(dir / "poses.csv");
  cr_only.erase(std::remove(cr_only.begin(), cr_only.end(), '\n'), cr_only.end());
  WriteText(dir / "mac.csv", cr_only);
  const PoseCapture mac = ReadPoses(dir / "mac.csv");
  ASSERT_EQ(mac.records.size(), 1u);
  EXPECT_EQ(mac.records[0].reported.translation, c.records[0].reported.translation);
  EXPECT_EQ(mac.records[0].set, "valid");
  WriteText(dir / "mixed.csv", ReadText(dir / "poses.csv") + "1,2\r3\n");
  try {
    ReadPoses(dir / "mixed.csv");
    ADD_FAILURE() << "a bare CR inside a line was accepted";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("mixed.csv:4: line end: a carriage return inside"),
              std::string::npos)
        << e.what();
  }
  const PoseRecord& r = c.records[0];
  EXPECT_EQ(r.station, 7);
  EXPECT_EQ(r.set, "valid");
  EXPECT_EQ(r.sensor, 2);
  EXPECT_EQ(r.time, 12.25);
  EXPECT_EQ(r.reported.translation, Eigen::Vector3d(1.5, 2.5, 3.5));
  EXPECT_EQ(r.reported.rotation.x(), 1.0);
  EXPECT_EQ(r.reference.translation, Eigen::Vector3d(0.1, 0.2, 0.3));
  EXPECT_EQ(c.extra_columns, std::vector<std::string>{"humidity"});
  EXPECT_EQ(r.extra, std::vector<double>{45.5});
}

TEST(PosesCsv, TextColumnsAreLabels) {
  const auto dir = MakeTempDir("capture_test");
  const std::string header = kPosesHeader;
  const std::string pose = "0,0.1,0.2,0.3,1,0,0,0,0.1,0.2,0.3,1,0,0,0";
  WriteText(dir / "poses.csv", header.substr(0, header.size() - 1) + ",operator,temp\n" +
                                   "1,calib,1," + pose + ",bob,21.5\n" +    //
                                   "2,calib,1," + pose + ",alice,\n" +      // temp missing
                                   "3,valid,1," + pose + ",,nan\n" +        // both missing
                                   "4,valid,1," + pose + ",bob,22\n");
  const PoseCapture c = ReadPoses(dir / "poses.csv");
  ASSERT_EQ(c.extra_columns, (std::vector<std::string>{"operator", "temp"}));
  // Labels are sorted, so an index does not depend on which row came first.
  ASSERT_NE(c.LabelsOf(0), nullptr);
  EXPECT_EQ(*c.LabelsOf(0), (std::vector<std::string>{"alice", "bob"}));
  EXPECT_EQ(c.LabelsOf(1), nullptr);
  ASSERT_EQ(c.records.size(), 4u);
  EXPECT_EQ(c.records[0].extra, (std::vector<double>{1, 21.5}));
  EXPECT_EQ(c.records[1].extra[0], 0);
  EXPECT_TRUE(std::isnan(c.records[1].extra[1]));
  EXPECT_TRUE(std::isnan(c.records[2].extra[0]) && std::isnan(c.records[2].extra[1]));

  // Written back as labels (a missing one as an empty field) and read back the same.
  WritePoses(dir / "copy.csv", c);
  const std::string text = ReadText(dir / "copy.csv");
  EXPECT_NE(text.find(",bob,21.5\n"), std::string::npos) << text;
  EXPECT_NE(text.find(",,nan\n"), std::string::npos) << text;
  const PoseCapture back = ReadPoses(dir / "copy.csv");
  EXPECT_EQ(back.extra_labels, c.extra_labels);
  EXPECT_EQ(back.records[3].extra, c.records[3].extra);

  // A label index out of range, or a label that would read back as a number, is refused.
  PoseCapture bad = c;
  bad.records[0].extra[0] = 2;
  EXPECT_NE(ErrorOf([&] { WritePoses(dir / "bad.csv", bad); })
                .find("record 0: extra column 1: 2 is not the index of one of its 2 labels"),
            std::string::npos);
  bad = c;
  bad.extra_labels[0] = {"alice", "7"};
  EXPECT_NE(ErrorOf([&] { WritePoses(dir / "bad.csv", bad); })
                .find("extra column operator: label '7' is not a valid label"),
            std::string::npos);
  EXPECT_FALSE(std::filesystem::exists(dir / "bad.csv"));
}

TEST(PosesCsv, ErrorsNameFileLineAndColumn) {
  const auto dir = MakeTempDir("capture_test");
  const std::string header = kPosesHeader;
  const std::string good = "1,calib,1,0,0.1,0.2,0.3,1,0,0,0,0.1,0.2,0.3,1,0,0,0\n";
  const auto path = dir / "poses.csv";
  auto error_for = [&](const std::string& text) {
    WriteText(path, text);
    return ErrorOf([&] { ReadPoses(path); });
  };
  EXPECT_EQ(error_for(header + good + "2,calib,1,0,0.1,0.2,0.3,abc,0,0,0,0.1,0.2,0.3,1,0,0,0\n"),
            "poses.csv:3: column rep_qw: 'abc' is not a number");
  // The message names the file with its folder, as given.
  try {
    ReadPoses(path);
    ADD_FAILURE() << "no error";
  } catch (const std::exception& e) {
    EXPECT_EQ(std::string(e.what()), path.string() + ":3: column rep_qw: 'abc' is not a number");
  }
  EXPECT_EQ(error_for(header + good + "2,calib,1,0,0.1,0.2,0.3,1,0,0,0,0.1,0.2,0.3,1,0,0\n"),
            "poses.csv:3: row: expected 18 fields, found 17");
  // A NUL in a field (a corrupt export, a binary file) is shown as \x00: what() is a C string, and
  // the message ended at the NUL, without its problem ("column rep_qw: '1").
  EXPECT_EQ(error_for(header + good +
                      std::string("2,calib,1,0,0.1,0.2,0.3,1\0,0,0,0,0.1,0.2,0.3,1,0,0,0\n", 53)),
            "poses.csv:3: column rep_qw: '1\\x00' is not a number");
  // A Latin-1 byte in a standard column: the message is UTF-8 text (a str in Python).
  EXPECT_EQ(error_for(header + good +
                      "2,calib,1,0,0.1,0.2,0.3,\xb1"
                      "1,0,0,0,0.1,0.2,0.3,1,0,0,0\n"),
            "poses.csv:3: column rep_qw: '\\xb11' is not a number");
  // A regional spreadsheet export: ';' between fields, ',' as the decimal point.
  std::string semicolons = header + good;
  std::replace(semicolons.begin(), semicolons.end(), ',', ';');
  EXPECT_EQ(error_for(semicolons),
            "poses.csv:1: header: fields are separated by ',' but this header is separated by "
            "';' (export with ',' between fields and '.' as the decimal point)");
  std::string tabs = header + good;
  std::replace(tabs.begin(), tabs.end(), ',', '\t');
  EXPECT_NE(error_for(tabs).find("this header is separated by '\\t'"), std::string::npos)
      << error_for(tabs);
  EXPECT_EQ(error_for(header + "1,train,1,0,0.1,0.2,0.3,1,0,0,0,0.1,0.2,0.3,1,0,0,0\n"),
            "poses.csv:2: column set: 'train' is not one of calib, valid, reg");
  EXPECT_EQ(error_for(header + "x1,calib,1,0,0.1,0.2,0.3,1,0,0,0,0.1,0.2,0.3,1,0,0,0\n"),
            "poses.csv:2: column station: 'x1' is not an integer");
  EXPECT_EQ(error_for(header + "1,calib,1,0,0.1,0.2,0.3,0.5,0,0,0,0.1,0.2,0.3,1,0,0,0\n"),
            "poses.csv:2: columns rep_qw, rep_qx, rep_qy, rep_qz: quaternion norm 0.5 is not 1");
  EXPECT_EQ(error_for(header + "1,calib,1,inf,0.1,0.2,0.3,1,0,0,0,0.1,0.2,0.3,1,0,0,0\n"),
            "poses.csv:2: column time: 'inf' is not a finite number");
  // One sign: "+-0.5" (a typo) is not -0.5, though "+0.5" is 0.5.
  EXPECT_EQ(error_for(header + "1,calib,1,+-0.5,0.1,0.2,0.3,1,0,0,0,0.1,0.2,0.3,1,0,0,0\n"),
            "poses.csv:2: column time: '+-0.5' is not a number");
  WriteText(path, header + "1,calib,1,+0.5,0.1,0.2,0.3,1,0,0,0,0.1,0.2,0.3,1,0,0,0\n");
  EXPECT_EQ(ReadPoses(path).records[0].time, 0.5);
  // A number beyond a double's range is a number (it was "'1e999' is not a number", and in an
  // extra column a label): too large is infinite, too small is zero, as strtod and Python read it.
  EXPECT_EQ(error_for(header + "1,calib,1,1e999,0.1,0.2,0.3,1,0,0,0,0.1,0.2,0.3,1,0,0,0\n"),
            "poses.csv:2: column time: '1e999' is not a finite number");
  EXPECT_EQ(
      error_for(header + "1,calib,1,0,0.1,0.2,-12345e99999999999,1,0,0,0,0.1,0.2,0.3,1,0,0,0\n"),
      "poses.csv:2: column rep_z: '-12345e99999999999' is not a finite number");
  EXPECT_EQ(error_for(header.substr(0, header.size() - 1) + ",temp\n" +
                      "1,calib,1,0,0.1,0.2,0.3,1,0,0,0,0.1,0.2,0.3,1,0,0,0,21.5\n" +
                      "2,calib,1,0,0.1,0.2,0.3,1,0,0,0,0.1,0.2,0.3,1,0,0,0,1e999\n"),
            "poses.csv:3: column temp: '1e999' is not a finite number");
  WriteText(path, header + "1,calib,1,1e-400,-0.000001e-999,0.2,0.3,1,0,0,0,0.1,0.2,0.3,1,0,0,0\n");
  EXPECT_EQ(ReadPoses(path).records[0].time, 0.0);
  EXPECT_EQ(ReadPoses(path).records[0].reported.translation.x(), 0.0);
  EXPECT_TRUE(std::signbit(ReadPoses(path).records[0].reported.translation.x()));
  EXPECT_EQ(error_for("station,set\n1,calib\n"),
            "poses.csv:1: column sensor: missing from the header");
  EXPECT_EQ(error_for(""), "poses.csv:1: empty file, expected a header");
  // A column holds numbers or labels: a label among numbers (a typo in a temperature log) is
  // an error, not a silent change of the column's kind.
  EXPECT_EQ(error_for(header.substr(0, header.size() - 1) + ",temp\n" +
                      "1,calib,1,0,0.1,0.2,0.3,1,0,0,0,0.1,0.2,0.3,1,0,0,0,21.5\n" +
                      "2,calib,1,0,0.1,0.2,0.3,1,0,0,0,0.1,0.2,0.3,1,0,0,0,warm\n"),
            "poses.csv:3: column temp: 'warm' is not a number, but line 2 holds the number 21.5 (a "
            "column holds numbers or labels, not both)");
  EXPECT_EQ(error_for(header.substr(0, header.size() - 1) + ",operator\n" +
                      "1,calib,1,0,0.1,0.2,0.3,1,0,0,0,0.1,0.2,0.3,1,0,0,0,alice\n" +
                      "2,calib,1,0,0.1,0.2,0.3,1,0,0,0,0.1,0.2,0.3,1,0,0,0,3\n"),
            "poses.csv:3: column operator: '3' is a number, but line 2 holds the label 'alice' (a "
            "column holds numbers or labels, not both)");
  EXPECT_EQ(error_for("station,station\n"),
            "poses.csv:1: column station: appears twice in the header");
}

// A lab's export names the columns in ways the reader does not take: the error said only
// "column station: missing from the header" of a header that visibly held "station".
TEST(PosesCsv, HeaderAsLabSoftwareExportsItSaysWhatToChange) {
  const auto dir = MakeTempDir("capture_test");
  const std::string header = kPosesHeader;
  const std::string good = "1,calib,1,0,0.1,0.2,0.3,1,0,0,0,0.1,0.2,0.3,1,0,0,0\n";
  const auto path = dir / "poses.csv";
  auto error_for = [&](const std::string& text) {
    WriteText(path, text);
    return ErrorOf([&] { ReadPoses(path); });
  };
  auto replaced = [](std::string s, const std::string& from, const std::string& to) {
    return s.replace(s.find(from), from.size(), to);
  };
  // Quoted names (a spreadsheet's "save with quotes").
  std::string quoted = "\"" + replaced(header, "\n", "") + "\"\n";
  for (size_t at = quoted.find(','); at != std::string::npos; at = quoted.find(',', at + 3)) {
    quoted.replace(at, 1, "\",\"");
  }
  EXPECT_EQ(error_for(quoted + good),
            "poses.csv:1: column station: missing from the header (the header names it "
            "\"station\", in quotes: fields are read without quoting; save the file without "
            "quotes)");
  // A unit in the name.
  EXPECT_EQ(error_for(replaced(header, "rep_x", "rep_x (m)") + good),
            "poses.csv:1: column rep_x: missing from the header (the header has 'rep_x (m)': "
            "name it rep_x alone; values are read in metres and seconds)");
  EXPECT_EQ(error_for(replaced(header, "time", "time [s]") + good),
            "poses.csv:1: column time: missing from the header (the header has 'time [s]': name "
            "it time alone; values are read in metres and seconds)");
  // Another letter case.
  EXPECT_EQ(error_for(replaced(header, "station", "Station") + good),
            "poses.csv:1: column station: missing from the header (the header has 'Station': "
            "names are case-sensitive; rename it station)");
  // A commented-out header, and metadata lines above the header (a Motive export).
  EXPECT_EQ(error_for("# " + header + good),
            "poses.csv:1: column station: missing from the header (the header names it '# "
            "station': remove the '#')");
  EXPECT_EQ(error_for("Format Version,1.23,Take Name,Take 2024-05-01\n\n" + header + good),
            "poses.csv:1: column station: missing from the header (line 3 names the columns: "
            "remove the lines above it, which were read as the header)");
  EXPECT_EQ(error_for("# exported by lab software\n" + header + good),
            "poses.csv:1: column station: missing from the header (line 2 names the columns: "
            "remove the lines above it, which were read as the header)");
  // Every line ending with ',' (an empty last column).
  EXPECT_EQ(error_for(replaced(header, "\n", ",\n") + replaced(good, "\n", ",\n")),
            "poses.csv:1: header: column 19 has no name (the line ends with ','; remove the ',' "
            "at the end of each line)");
  EXPECT_EQ(error_for(header + replaced(good, "\n", ",\n")),
            "poses.csv:2: row: expected 18 fields, found 19 (the line ends with ','; remove it)");
  // ',' as the decimal point in a file separated by ','.
  EXPECT_EQ(error_for(header + "1,calib,1,0,0,1,0,2,0,3,1,0,0,0,0,1,0,2,0,3,1,0,0,0\n"),
            "poses.csv:2: row: expected 18 fields, found 24 (no '.' in the line: is ',' its "
            "decimal point? export with '.' as the decimal point)");
  // A misspelt name (the letters of a quaternion column swapped, a letter left out).
  EXPECT_EQ(error_for(replaced(header, "rep_qx", "rep_xq") + good),
            "poses.csv:1: column rep_qx: missing from the header (the header has 'rep_xq': is it "
            "rep_qx misspelt? rename it rep_qx)");
  EXPECT_EQ(error_for(replaced(header, "station", "staion") + good),
            "poses.csv:1: column station: missing from the header (the header has 'staion': is it "
            "station misspelt? rename it station)");
  // No hint where nothing explains the missing column.
  EXPECT_EQ(error_for("station,set\n1,calib\n"),
            "poses.csv:1: column sensor: missing from the header");
  // What the hints recognise is still refused when the header is right: a field in quotes.
  EXPECT_EQ(error_for(header + replaced(good, "calib", "\"calib\"")),
            "poses.csv:2: column set: '\"calib\"' is not one of calib, valid, reg");
}

TEST(PosesCsv, AFileThatIsNotUtf8TextSaysSo) {
  const auto dir = MakeTempDir("capture_test");
  const auto path = dir / "poses.csv";
  const std::string text =
      std::string(kPosesHeader) + "1,calib,1,0,0.1,0.2,0.3,1,0,0,0,0.1,0.2,0.3,1,0,0,0\n";
  auto error_for = [&](const std::string& bytes) {
    WriteText(path, bytes);
    return ErrorOf([&] { ReadPoses(path); });
  };
  // Excel's "Unicode text" save (UTF-16 with a byte order mark, either byte order) said "column
  // station: missing from the header".
  std::string le = "\xFF\xFE", be = "\xFE\xFF";
  for (const char c : text) {
    le += std::string{c, '\0'};
    be += std::string{'\0', c};
  }
  const std::string utf16 =
      "poses.csv:1: encoding: UTF-16 text (a byte order mark FF FE or FE FF); save the CSV file as "
      "UTF-8";
  EXPECT_EQ(error_for(le), utf16);
  EXPECT_EQ(error_for(be), utf16);
  // UTF-32 (its little-endian mark FF FE 00 00 starts with UTF-16's) was called UTF-16.
  std::string le32("\xFF\xFE\0\0", 4), be32("\0\0\xFE\xFF", 4);
  for (const char c : text) {
    le32 += std::string{c, '\0', '\0', '\0'};
    be32 += std::string{'\0', '\0', '\0', c};
  }
  const std::string utf32 =
      "poses.csv:1: encoding: UTF-32 text (a byte order mark FF FE 00 00 or 00 00 FE FF); save the "
      "CSV file as UTF-8";
  EXPECT_EQ(error_for(le32), utf32);
  EXPECT_EQ(error_for(be32), utf32);
  // A PNG renamed .csv: the CR of its signature was called "mixed line ends" (line 3).
  const std::string hint =
      "): not a text CSV file (an .xlsx workbook, an image or an archive, or UTF-16 text without a "
      "byte order mark?); export the capture as CSV in UTF-8";
  EXPECT_EQ(error_for(std::string("\x89PNG\r\n\x1a\n\0\0\0\rIHDR\0\0\0\x10", 20)),
            "poses.csv:1: encoding: the header is not text (byte \\x89 at column 1" + hint);
  // A gzip archive (1f 8b) and an .xlsx workbook (a zip: "PK\3\4") said "column station: missing
  // from the header"; so did UTF-16 without a byte order mark, after blank lines.
  EXPECT_EQ(error_for(std::string("\x1f\x8b\x08\0\0\0\0\0", 8)),
            "poses.csv:1: encoding: the header is not text (byte \\x1f at column 1" + hint);
  EXPECT_EQ(error_for(std::string("PK\x03\x04\x14\0\x06\0", 8)),
            "poses.csv:1: encoding: the header is not text (byte \\x03 at column 3" + hint);
  EXPECT_EQ(error_for("\n\n" + le.substr(2)),
            "poses.csv:3: encoding: the header is not text (byte \\x00 at column 2" + hint);
  // A legacy code page's column name (Latin-1 "temp_\xb0C") is text: read as before (Python names
  // its column as it fails to become a str), as in UTF-8 after a UTF-8 byte order mark.
  const std::string columns(kPosesHeader, strlen(kPosesHeader) - 1);
  const std::string row = "1,calib,1,0,0.1,0.2,0.3,1,0,0,0,0.1,0.2,0.3,1,0,0,0,20\n";
  EXPECT_EQ(error_for(columns +
                      ",temp_\xb0"
                      "C\n" +
                      row),
            "");
  EXPECT_EQ(error_for("\xEF\xBB\xBF" + columns +
                      ",temp_\xc2\xb0"
                      "C\n" +
                      row),
            "");
  // Such a header with a form feed further on (a page break in an extra column) was called "not a
  // text CSV file" because of the control byte; a binary file's NUL is what tells it apart.
  EXPECT_EQ(error_for(columns +
                      ",temp_\xb0"
                      "C\n" +
                      row.substr(0, row.size() - 3) + "2\f0\n"),
            "");
}

TEST(PosesCsv, ABinaryFileWhoseFirstLineIsTextSaysSo) {
  const auto dir = MakeTempDir("capture_test");
  const auto path = dir / "poses.csv";
  auto error_for = [&](const std::string& bytes) {
    WriteText(path, bytes);
    return ErrorOf([&] { ReadPoses(path); });
  };
  // A PDF document renamed poses.csv: its first line "%PDF-1.7" reads as a header, and it said
  // "column station: missing from the header". Its compressed stream (no NUL in its first bytes)
  // follows a few text lines.
  const std::string stream("x\x9c\xed\x5d\xdb\x8e\xe3\x36\x12\x7d\xef\xaf\xd0\xe3\x02\x33", 16);
  const std::string pdf_body =
      "%\xe2\xe3\xcf\xd3\n1 0 obj\n<< /Length 16 /Filter /FlateDecode >>\nstream\n" + stream +
      "\nendstream\nendobj\n";
  EXPECT_EQ(error_for("%PDF-1.7\n" + pdf_body),
            "poses.csv:1: encoding: a PDF document (the file starts with %PDF-), not a text CSV "
            "file; export the capture as CSV in UTF-8");
  // Any such binary file (here the same without its signature): its first control byte named.
  EXPECT_EQ(
      error_for("PDF export\n" + pdf_body),
      "poses.csv:6: encoding: byte \\x12 at column 9 is not text, and the file is not UTF-8: "
      "not a text CSV file (a PDF document, an .xlsx workbook, an image or an archive?); export "
      "the capture as CSV in UTF-8");
  // A legacy code page's text with a form feed, a vertical tab or a DOS end-of-file byte is text,
  // and so is UTF-8 with a control byte in a label: read as before.
  const std::string columns(kPosesHeader, strlen(kPosesHeader) - 1);
  const std::string row = "1,calib,1,0,0.1,0.2,0.3,1,0,0,0,0.1,0.2,0.3,1,0,0,0,";
  EXPECT_EQ(error_for(columns + ",note\n" + row + "caf\xe9\f\v\x1a\n"), "");
  EXPECT_EQ(error_for(columns + ",note\n" + row + "caf\xc3\xa9\x01\n"), "");
  // A multi-byte UTF-8 character that the first kilobyte's end cuts is no encoding error.
  std::string long_row =
      row + "\x01" + std::string(1023 - columns.size() - 6 - row.size() - 1, 'a');
  long_row += "\xc3\xa9\n";
  ASSERT_EQ((columns + ",note\n" + long_row).find("\xc3"), 1023u);
  EXPECT_EQ(error_for(columns + ",note\n" + long_row), "");
}

TEST(PosesCsv, AHugeFieldIsQuotedShortened) {
  // A field of megabytes (a corrupt export, a file that lost its line ends) was quoted in full.
  const auto dir = MakeTempDir("capture_test");
  const auto path = dir / "poses.csv";
  const std::string rest = ",0.2,0.3,1,0,0,0,0.1,0.2,0.3,1,0,0,0\n";
  WriteText(path,
            std::string(kPosesHeader) + "1,calib,1,0," + std::string(1'000'000, '9') + "x" + rest);
  EXPECT_EQ(ErrorOf([&] { ReadPoses(path); }),
            "poses.csv:2: column rep_x: '" + std::string(60, '9') +
                "...' (a field of 1000001 bytes) is not a number");
  // Not cut inside a UTF-8 character (which would be quoted as \xNN bytes); a field of 80 bytes
  // is quoted whole.
  WriteText(path, std::string(kPosesHeader) + "1,calib,1,0," + std::string(59, 'a') + "\xc3\xa9" +
                      std::string(100, 'b') + rest);
  EXPECT_EQ(ErrorOf([&] { ReadPoses(path); }), "poses.csv:2: column rep_x: '" +
                                                   std::string(59, 'a') +
                                                   "...' (a field of 161 bytes) is not a number");
  WriteText(path, std::string(kPosesHeader) + "1," + std::string(80, 'c') + ",1,0,0.1" + rest);
  EXPECT_EQ(ErrorOf([&] { ReadPoses(path); }), "poses.csv:2: column set: '" + std::string(80, 'c') +
                                                   "' is not one of calib, valid, reg");
}

TEST(CaptureReaders, AFileThatCannotBeOpenedSaysWhy) {
  // "cannot open file" gave no reason: a missing file, a folder on the way, a symbolic-link loop.
  const auto dir = MakeTempDir("capture_test");
  EXPECT_EQ(ErrorOf([&] { ReadPoses(dir / "nothing.csv"); }),
            "nothing.csv: cannot open file: No such file or directory");
  WriteText(dir / "file", "station\n");
  EXPECT_EQ(ErrorOf([&] { ReadMarkers(dir / "file" / "markers.csv"); }),
            "markers.csv: cannot open file: Not a directory");
  std::filesystem::create_symlink("loop.csv", dir / "loop.csv");
  EXPECT_EQ(ErrorOf([&] { ReadTrackerStream(dir / "loop.csv"); }),
            "loop.csv: cannot open file: Too many levels of symbolic links");
}

TEST(CaptureReaders, FolderInsteadOfFileIsAnErrorNamingIt) {
  // A capture folder given where one of its files was meant (trackcal-fit register --markers DIR):
  // the folder opens as a stream and failed to read with the library's "basic_filebuf::underflow
  // error reading the file: Is a directory", naming no file.
  const auto dir = MakeTempDir("capture_test");
  std::filesystem::create_directory(dir / "capA");
  const std::vector<std::function<void()>> readers = {
      [&] { ReadPoses(dir / "capA"); }, [&] { ReadMarkers(dir / "capA"); },
      [&] { ReadTracker(dir / "capA"); }, [&] { ReadTrackerStream(dir / "capA"); },
      [&] { ReadReferenceStream(dir / "capA"); }};
  for (const auto& read : readers) {
    try {
      read();
      ADD_FAILURE() << "a folder was read as a file";
    } catch (const std::runtime_error& e) {
      EXPECT_EQ(std::string(e.what()), (dir / "capA").string() + ": is a folder, not a CSV file");
    }
  }
}

TEST(PosesCsv, RepeatedStationAndSensorIsAnErrorNamingBothLines) {
  const auto dir = MakeTempDir("capture_test");
  const std::string header = kPosesHeader;
  const std::string rest = ",0,0.1,0.2,0.3,1,0,0,0,0.1,0.2,0.3,1,0,0,0\n";
  const auto path = dir / "poses.csv";
  // A station may carry several sensors: (1, 1) and (1, 2) are two records.
  WriteText(path, header + "1,calib,1" + rest + "1,calib,2" + rest + "2,valid,1" + rest);
  EXPECT_EQ(ReadPoses(path).records.size(), 3u);
  // The same station and sensor twice, even in another set, is ambiguous.
  WriteText(path, header + "1,calib,1" + rest + "2,calib,1" + rest + "\n1,valid,1" + rest);
  EXPECT_EQ(ErrorOf([&] { ReadPoses(path); }),
            "poses.csv:5: columns station, sensor: station 1, sensor 1 repeats line 2 (one row "
            "per station and sensor)");
}

TEST(CaptureWriters, RefuseToOverwrite) {
  const auto dir = MakeTempDir("capture_test");
  const PoseCapture c = RandomPoses();
  WritePoses(dir / "poses.csv", c);
  const std::string before = ReadText(dir / "poses.csv");
  PoseCapture other = c;
  other.records.resize(1);
  EXPECT_NE(ErrorOf([&] { WritePoses(dir / "poses.csv", other); }).find("refusing to overwrite"),
            std::string::npos);
  EXPECT_EQ(ReadText(dir / "poses.csv"), before);
  WritePoses(dir / "poses.csv", other, {.overwrite = true});
  EXPECT_EQ(ReadPoses(dir / "poses.csv").records.size(), 1u);
  // No temporary files are left behind.
  int files = 0;
  for (const auto& e : std::filesystem::directory_iterator(dir)) {
    (void)e;
    ++files;
  }
  EXPECT_EQ(files, 1);
  // Inconsistent records are rejected before anything is written.
  other.records[0].extra.clear();
  EXPECT_THROW(WritePoses(dir / "bad.csv", other), std::invalid_argument);
  EXPECT_FALSE(std::filesystem::exists(dir / "bad.csv"));
}

TEST(CaptureWriters, RefuseWhatTheReadersRefuse) {
  // A file the readers refuse is no capture: a non-finite number in a standard column, an infinite
  // extra value or a quaternion that is not unit is an error naming the record and the column, and
  // nothing is written. An extra column's nan (a missing value) is written and read back.
  const auto dir = MakeTempDir("capture_test");
  const auto path = dir / "poses.csv";
  const double nan = std::numeric_limits<double>::quiet_NaN();
  const double inf = std::numeric_limits<double>::infinity();
  auto error_for = [&](const std::function<void(PoseCapture&)>& edit) {
    PoseCapture c = RandomPoses();
    edit(c);
    const std::string error = ErrorOf([&] { WritePoses(path, c); });
    EXPECT_FALSE(std::filesystem::exists(path)) << error;
    return error;
  };
  EXPECT_EQ(error_for([&](PoseCapture& c) { c.records[3].time = nan; }),
            "poses.csv: record 3: column time: nan is not a finite number");
  EXPECT_EQ(error_for([&](PoseCapture& c) { c.records[0].reference.translation.y() = -inf; }),
            "poses.csv: record 0: column ref_y: -inf is not a finite number");
  EXPECT_EQ(error_for([&](PoseCapture& c) { c.records[2].extra[0] = inf; }),
            "poses.csv: record 2: column temperature_c: inf is not a finite number");
  EXPECT_EQ(
      error_for(
          [&](PoseCapture& c) { c.records[1].reported.rotation = Eigen::Quaterniond(0, 0, 0, 0); }),
      "poses.csv: record 1: columns rep_qw, rep_qx, rep_qy, rep_qz: quaternion norm 0 is not 1");
  EXPECT_EQ(error_for([&](PoseCapture& c) { c.records[1].reference.rotation.coeffs() *= 1.01; }),
            "poses.csv: record 1: columns ref_qw, ref_qx, ref_qy, ref_qz: quaternion norm 1.01 is "
            "not 1");
  EXPECT_EQ(error_for([&](PoseCapture& c) { c.records[1].reference.rotation.x() = nan; }),
            "poses.csv: record 1: column ref_qx: nan is not a finite number");
  // Named with its folder, as the other writer errors (it gave the file name alone).
  try {
    PoseCapture c = RandomPoses();
    c.records[2].set = "train";
    WritePoses(path, c);
    ADD_FAILURE() << "no error";
  } catch (const std::exception& e) {
    EXPECT_EQ(std::string(e.what()),
              path.string() + ": record 2: column set: 'train' is not one of calib, valid, reg");
  }
  EXPECT_FALSE(std::filesystem::exists(path));
  // The streams' writers share the check.
  TrackerStream stream;
  stream.records.resize(2);
  stream.records[1].time = 0.01;
  stream.records[1].transmitter_from_receiver.translation.z() = nan;
  EXPECT_EQ(ErrorOf([&] { WriteTrackerStream(dir / kTrackerStreamCsv, stream); }),
            std::string(kTrackerStreamCsv) + ": record 1: column z: nan is not a finite number");
  EXPECT_FALSE(std::filesystem::exists(dir / kTrackerStreamCsv));

  PoseCapture missing = RandomPoses();
  missing.records[4].extra[0] = nan;
  WritePoses(path, missing);
  EXPECT_TRUE(std::isnan(ReadPoses(path).records[4].extra[0]));
}

TEST(CaptureWriters, RefuseFilesTheReadersRefuse) {
  // What a reader refuses beyond single values: a repeated key, a reference time that does not
  // increase, an extra column given twice or named with spaces the reader trims. Refused when
  // writing, naming the record, and nothing is written.
  const auto dir = MakeTempDir("capture_test");
  const auto path = dir / "poses.csv";
  PoseCapture poses = RandomPoses();
  poses.records[7].station = poses.records[5].station;
  poses.records[7].sensor = poses.records[5].sensor;
  EXPECT_EQ(ErrorOf([&] { WritePoses(path, poses); }),
            "poses.csv: record 7: columns station, sensor: station 6, sensor 2 repeats record 5 "
            "(one record per station and sensor)");
  EXPECT_FALSE(std::filesystem::exists(path));

  MarkerCapture markers;
  markers.records.push_back({1, 2, Eigen::Vector3d::Zero(), {}});
  markers.records.push_back({1, 2, Eigen::Vector3d::Ones(), {}});
  EXPECT_EQ(ErrorOf([&] { WriteMarkers(dir / kMarkersCsv, markers); }),
            std::string(kMarkersCsv) +
                ": record 1: columns station, marker: station 1, marker 2 repeats record 0 (one "
                "record per station and marker)");
  EXPECT_FALSE(std::filesystem::exists(dir / kMarkersCsv));

  TrackerCapture tracker;
  tracker.records.resize(2);  // both station 0, sensor 1
  EXPECT_NE(ErrorOf([&] { WriteTracker(dir / kTrackerCsv, tracker); }).find("repeats record 0"),
            std::string::npos);
  EXPECT_FALSE(std::filesystem::exists(dir / kTrackerCsv));

  ReferenceStream stream;
  stream.records.resize(3);
  stream.records[0].time = 0.01;
  stream.records[1].time = 0.02;
  stream.records[2].time = 0.02;
  EXPECT_EQ(ErrorOf([&] { WriteReferenceStream(dir / kReferenceStreamCsv, stream); }),
            std::string(kReferenceStreamCsv) +
                ": record 2: column time: 0.02 is not after the previous record's 0.02 (times "
                "must increase)");
  EXPECT_FALSE(std::filesystem::exists(dir / kReferenceStreamCsv));

  // One sensor's time twice: ReadTrackerStream refuses it, so the writer does (it saved a live
  // recording that then failed to load). Another sensor at that time, or an earlier time, is fine.
  TrackerStream samples;
  samples.records.resize(4);
  samples.records[0].time = 0.02;
  samples.records[1].time = 0.02;
  samples.records[1].sensor = 2;  // the others are sensor 1
  samples.records[2].time = 0.01;
  samples.records[3].time = 0.02;
  const std::string repeat =
      ": record 3: columns time, sensor: time 0.02 of sensor 1 repeats record 0 (one sample per "
      "sensor and time)";
  EXPECT_EQ(ErrorOf([&] { WriteTrackerStream(dir / kTrackerStreamCsv, samples); }),
            std::string(kTrackerStreamCsv) + repeat);
  EXPECT_FALSE(std::filesystem::exists(dir / kTrackerStreamCsv));
  EXPECT_EQ(ErrorOf([&] { FormatTrackerStream(samples, "live.csv.partial", false); }),
            "live.csv.partial" + repeat);
  samples.records.pop_back();
  WriteTrackerStream(dir / kTrackerStreamCsv, samples);
  EXPECT_EQ(ReadTrackerStream(dir / kTrackerStreamCsv).records.size(), 3u);

  for (const std::vector<std::string>& columns :
       std::vector<std::vector<std::string>>{{"temperature_c", "temperature_c"}, {" room"}}) {
    PoseCapture c = RandomPoses();
    c.extra_columns = columns;
    for (PoseRecord& r : c.records) r.extra.assign(columns.size(), 1.0);
    EXPECT_THROW(WritePoses(path, c), std::invalid_argument) << columns[0];
    EXPECT_FALSE(std::filesystem::exists(path)) << columns[0];
  }
}

TEST(OtherCaptureFiles, RoundTrip) {
  const auto dir = MakeTempDir("capture_test");
  MarkerCapture markers;
  TrackerCapture tracker;
  TrackerStream tracker_stream;
  ReferenceStream reference_stream;
  reference_stream.extra_columns = {"frame"};
  for (int i = 0; i < 10; ++i) {
    markers.records.push_back({i / 3 + 1, i % 6 + 1, Eigen::Vector3d(0.1 * i, 1.0 / 3, -2.0), {}});
    tracker.records.push_back(
        {i + 1, 1, Rigid3d(RandomRotation(TestRng()), Eigen::Vector3d(i, 0, 1)), {}});
    tracker_stream.records.push_back(
        {i / 120.0, 2, Rigid3d(RandomRotation(TestRng()), Eigen::Vector3d(0, i, 1)), {}});
    reference_stream.records.push_back(
        {0.037 + i / 100.0,
         Rigid3d(RandomRotation(TestRng()), Eigen::Vector3d(1, 0, i)),
         {double(i)}});
  }
  WriteMarkers(dir / kMarkersCsv, markers);
  WriteTracker(dir / kTrackerCsv, tracker);
  WriteTrackerStream(dir / kTrackerStreamCsv, tracker_stream);
  WriteReferenceStream(dir / kReferenceStreamCsv, reference_stream);
  EXPECT_EQ(ReadText(dir / kMarkersCsv).substr(0, 21), "station,marker,x,y,z\n");
  const MarkerCapture m = ReadMarkers(dir / kMarkersCsv);
  const TrackerCapture t = ReadTracker(dir / kTrackerCsv);
  const TrackerStream ts = ReadTrackerStream(dir / kTrackerStreamCsv);
  const ReferenceStream rs = ReadReferenceStream(dir / kReferenceStreamCsv);
  ASSERT_EQ(m.records.size(), 10u);
  ASSERT_EQ(rs.records.size(), 10u);
  for (int i = 0; i < 10; ++i) {
    EXPECT_EQ(m.records[i].position_in_optical, markers.records[i].position_in_optical);
    EXPECT_EQ(m.records[i].marker, markers.records[i].marker);
    EXPECT_EQ(t.records[i].transmitter_from_receiver.rotation.coeffs(),
              tracker.records[i].transmitter_from_receiver.rotation.coeffs());
    EXPECT_EQ(ts.records[i].time, tracker_stream.records[i].time);
    EXPECT_EQ(ts.records[i].sensor, 2);
    EXPECT_EQ(rs.records[i].time, reference_stream.records[i].time);
    EXPECT_EQ(rs.records[i].transmitter_from_body.translation,
              reference_stream.records[i].transmitter_from_body.translation);
    EXPECT_EQ(rs.records[i].extra, reference_stream.records[i].extra);
  }
}

TEST(OtherCaptureFiles, RepeatedKeyIsAnErrorNamingBothLines) {
  const auto dir = MakeTempDir("capture_test");
  WriteText(dir / kMarkersCsv, "station,marker,x,y,z\n1,1,0,0,0\n1,2,0,0,0\n2,1,0,0,0\n1,2,1,1,1\n");
  EXPECT_EQ(ErrorOf([&] { ReadMarkers(dir / kMarkersCsv); }),
            std::string(kMarkersCsv) +
                ":5: columns station, marker: station 1, marker 2 repeats line 3 (one row per "
                "station and marker)");
  WriteText(dir / kTrackerCsv,
            "station,sensor,x,y,z,qw,qx,qy,qz\n3,1,0,0,0,1,0,0,0\n3,2,0,0,0,1,0,0,0\n"
            "3,1,0,0,0,1,0,0,0\n");
  EXPECT_EQ(ErrorOf([&] { ReadTracker(dir / kTrackerCsv); }),
            std::string(kTrackerCsv) +
                ":4: columns station, sensor: station 3, sensor 1 repeats line 2 (one row per "
                "station and sensor)");
}

TEST(OtherCaptureFiles, ReferenceStreamTimesMustIncrease) {
  // A frame written twice: named by its line and column when read, not later by sample index.
  const auto dir = MakeTempDir("capture_test");
  WriteText(dir / kReferenceStreamCsv,
            "time,x,y,z,qw,qx,qy,qz\n0.01,0,0,0,1,0,0,0\n\n0.02,0,0,0,1,0,0,0\n"
            "0.02,0,0,0,1,0,0,0\n");
  EXPECT_EQ(ErrorOf([&] { ReadReferenceStream(dir / kReferenceStreamCsv); }),
            std::string(kReferenceStreamCsv) +
                ":5: column time: 0.02 is not after the previous sample's 0.02 (times must "
                "increase)");
}

TEST(FormatTrackerStream, Nominal) {
  // The text is the file WriteTrackerStream writes, and the rows alone are it without the header:
  // a recording appended a chunk at a time is byte for byte the file of one write.
  const auto dir = MakeTempDir("capture_test");
  TrackerStream stream;
  for (int i = 0; i < 20; ++i) {
    stream.records.push_back({1796098746.0 + i / 120.0,
                              1 + i % 2,
                              Rigid3d(RandomRotation(TestRng()), Eigen::Vector3d(1.0 / 3, -0.2, i)),
                              {}});
  }
  WriteTrackerStream(dir / kTrackerStreamCsv, stream);
  const std::string file = ReadText(dir / kTrackerStreamCsv);
  EXPECT_EQ(FormatTrackerStream(stream, "rec"), file);
  TrackerStream first = stream, second = stream;
  first.records.resize(7);
  second.records.erase(second.records.begin(), second.records.begin() + 7);
  EXPECT_EQ(FormatTrackerStream(first, "rec") + FormatTrackerStream(second, "rec", false), file);
  EXPECT_EQ(FormatTrackerStream(TrackerStream{}, "rec"), "time,sensor,x,y,z,qw,qx,qy,qz\n");
  EXPECT_EQ(FormatTrackerStream(TrackerStream{}, "rec", false), "");
}

TEST(FormatTrackerStream, RefusesWhatTheWriterRefusesNamingTheText) {
  TrackerStream stream;
  stream.records.resize(3);
  for (size_t i = 0; i < stream.records.size(); ++i) stream.records[i].time = 0.01 * i;
  stream.records[2].transmitter_from_receiver.rotation.coeffs() << 0.0, 0.0, 0.0, 2.0;
  EXPECT_EQ(ErrorOf([&] { FormatTrackerStream(stream, "raw.partial", false); }),
            "raw.partial: record 2: columns qw, qx, qy, qz: quaternion norm 2 is not 1");
}

TEST(OtherCaptureFiles, TrackerStreamTimeRepeatedForOneSensorIsAnErrorNamingBothLines) {
  // Receivers interleave (one frame's sensors share its time) and rows may come out of time order
  // (the pairing and the speed take each sensor's samples in time order), but one sensor's time
  // twice is a frame written twice or a clock that did not tick: two poses at one instant, paired
  // with one reference pose, and a speed from a zero time step. Named by both lines when read.
  const auto dir = MakeTempDir("capture_test");
  const std::string header = "time,sensor,x,y,z,qw,qx,qy,qz\n";
  const std::string pose = ",0,0,0,1,0,0,0\n";
  WriteText(dir / kTrackerStreamCsv, header + "0.02,1" + pose + "0.02,2" + pose + "0.01,1" + pose +
                                         "0.01,2" + pose + "0.03,1" + pose);
  EXPECT_EQ(ReadTrackerStream(dir / kTrackerStreamCsv).records.size(), 5u);
  WriteText(dir / kTrackerStreamCsv, header + "0.01,1" + pose + "0.02,1" + pose + "0.02,2" + pose +
                                         "\n0.03,1" + pose + "0.02,1" + pose);
  EXPECT_EQ(ErrorOf([&] { ReadTrackerStream(dir / kTrackerStreamCsv); }),
            std::string(kTrackerStreamCsv) +
                ":7: columns time, sensor: time 0.02 of sensor 1 repeats line 3 (one sample per "
                "sensor and time)");
}

TEST(FormatNumber, ShortestRoundTrip) {
  EXPECT_EQ(FormatNumber(0.1), "0.1");
  EXPECT_EQ(FormatNumber(-2.5e-7), "-2.5e-07");
  const double third = 1.0 / 3.0;
  EXPECT_EQ(std::stod(FormatNumber(third)), third);
}

}  // namespace
}  // namespace trackcal
