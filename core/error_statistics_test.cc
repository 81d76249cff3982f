#include "core/error_statistics.h"

#include <gtest/gtest.h>

#include <cmath>
#include <limits>
#include <vector>

#include "tests/test_utils.h"

namespace trackcal {
namespace {

TEST(SummarizeErrors, Nominal) {
  const std::vector<double> v = {1.0, 2.0, 3.0, 4.0};
  const ErrorSummary s = SummarizeErrors(v);
  EXPECT_EQ(s.count, 4);
  EXPECT_DOUBLE_EQ(s.mean, 2.5);
  EXPECT_DOUBLE_EQ(s.std, std::sqrt(5.0 / 3.0));  // sample std of 1..4
  EXPECT_DOUBLE_EQ(s.max, 4.0);
  EXPECT_DOUBLE_EQ(s.median, 2.5);
  EXPECT_DOUBLE_EQ(s.rms, std::sqrt(7.5));
  EXPECT_DOUBLE_EQ(s.p95, 3.85);
}

TEST(SummarizeErrors, EmptyAndSingle) {
  EXPECT_EQ(SummarizeErrors({}).count, 0);
  const std::vector<double> one = {7.0};
  const ErrorSummary s = SummarizeErrors(one);
  EXPECT_EQ(s.std, 0.0);
  EXPECT_EQ(s.max, 7.0);
}

TEST(SummarizeErrors, AnUnknownValueMakesEveryStatisticUnknown) {
  // NaN last and first: std::max skipped it in one order, and the sort's order was undefined.
  for (const std::vector<double>& values :
       {std::vector<double>{1.0, 2.0, std::nan("")}, std::vector<double>{std::nan(""), 5.0, 1.0}}) {
    const ErrorSummary s = SummarizeErrors(values);
    EXPECT_EQ(s.count, 3);
    for (double v : {s.mean, s.std, s.max, s.rms, s.median, s.p95}) EXPECT_TRUE(std::isnan(v));
  }
}

TEST(SummarizePoseErrors, UnitsAreMillimetresAndDegrees) {
  const Rigid3d reference(Eigen::Quaterniond::Identity(), Eigen::Vector3d(0.5, 0.0, 0.0));
  const Rigid3d reported(Eigen::Quaterniond(Eigen::AngleAxisd(3.0 * kRadPerDeg, Eigen::Vector3d::UnitY())),
                         Eigen::Vector3d(0.5, 0.0, 0.042));
  const std::vector<Rigid3d> est = {reported}, ref = {reference};
  const PoseErrorSummary s = SummarizePoseErrors(est, ref);
  EXPECT_NEAR(s.position_mm.mean, 42.0, 1e-9);
  EXPECT_NEAR(s.orientation_deg.mean, 3.0, 1e-9);
}

TEST(SummarizePoseErrors, SizeMismatchThrows) {
  const std::vector<Rigid3d> est(2), ref(3);
  EXPECT_THROW(SummarizePoseErrors(est, ref), std::invalid_argument);
}

TEST(FormatTable1, PaperNumbers) {
  Table1 t;
  t.set_name = "valid";
  t.before.position_mm = {120, 42.3, 26.3, 97.5};
  t.after.position_mm = {120, 4.82, 4.04, 22.8};
  const std::string s = FormatTable1(t);
  EXPECT_NE(s.find("88.6 %"), std::string::npos) << s;  // the paper's mean improvement
  EXPECT_NE(s.find("76.6 %"), std::string::npos) << s;  // and its maximum
}

TEST(ImprovementPercent, UnknownOrNewErrorsAreNotReportedAsNoChange) {
  EXPECT_DOUBLE_EQ(ImprovementPercent(42.3, 4.82), 100.0 * (42.3 - 4.82) / 42.3);
  EXPECT_DOUBLE_EQ(ImprovementPercent(2.0, 3.0), -50.0);
  EXPECT_EQ(ImprovementPercent(0.0, 0.0), 0.0);
  // Both used to be 0: a correction that adds an error to a perfect set read as "no change", and
  // a NaN (unknown) original error read as a known 0 % next to "nan" in the table.
  EXPECT_EQ(ImprovementPercent(0.0, 1.0), -std::numeric_limits<double>::infinity());
  EXPECT_TRUE(std::isnan(ImprovementPercent(std::nan(""), 1.0)));
  EXPECT_TRUE(std::isnan(ImprovementPercent(1.0, std::nan(""))));
  // The table of a set with a NaN original error shows no improvement figure for it.
  Table1 t;
  t.set_name = "valid";
  t.before.position_mm = {3, std::nan(""), std::nan(""), std::nan("")};
  t.after.position_mm = {3, 1.0, 0.5, 2.0};
  t.before.orientation_deg = {3, 2.0, 1.0, 4.0};
  t.after.orientation_deg = {3, 1.0, 0.5, 2.0};
  const std::string s = FormatTable1(t);
  EXPECT_EQ(s.find(" 0.0 %"), std::string::npos) << s;
  EXPECT_NE(s.find("50.0 %"), std::string::npos) << s;
}

std::vector<Rigid3d> Positions(const std::vector<Eigen::Vector3d>& p) {
  std::vector<Rigid3d> out;
  for (const auto& x : p) out.emplace_back(Eigen::Quaterniond::Identity(), x);
  return out;
}

// Three stations 0.5 m above the transmitter (z down) with 1 mm errors, and a hemisphere flip: the
// report of the fourth is -p (1 m off), as a Fastrak gives when the receiver crosses the
// hemisphere's plane.
TEST(MakeTable1, LeavesOutHemisphereFlipsFromBothColumns) {
  const auto reference = Positions({{0.1, 0, -0.5}, {0, 0.1, -0.5}, {-0.1, 0, -0.5}, {0, 0, -0.5}});
  const auto reported =
      Positions({{0.1, 0, -0.501}, {0, 0.1, -0.501}, {-0.1, 0, -0.501}, {0, 0, 0.5}});
  const auto corrected = Positions({{0.1, 0, -0.5005}, {0, 0.1, -0.5005}, {-0.1, 0, -0.5005},
                                    {0, 0, 0.5}});
  const Table1 t = MakeTable1("valid", reported, corrected, reference);
  EXPECT_EQ(t.flips_left_out, 1);
  EXPECT_EQ(t.before.position_mm.count, 3);
  EXPECT_EQ(t.after.position_mm.count, 3);
  EXPECT_NEAR(t.before.position_mm.max, 1.0, 1e-9);  // the flip's 1000 mm is not the maximum
  EXPECT_NEAR(t.after.position_mm.mean, 0.5, 1e-9);
  const std::string s = FormatTable1(t);
  EXPECT_NE(s.find("valid set (3 poses)"), std::string::npos) << s;
  EXPECT_NE(s.find("1 more left out"), std::string::npos) << s;
}

TEST(MakeTable1, MostReportsFlippedAreShownNotLeftOut) {
  // Every report in the other hemisphere: a wrong hemisphere setting, which the table must show.
  const auto reference = Positions({{0.1, 0, -0.5}, {0, 0.1, -0.5}});
  const auto reported = Positions({{-0.1, 0, 0.5}, {0, -0.1, 0.5}});
  const Table1 t = MakeTable1("valid", reported, reported, reference);
  EXPECT_EQ(t.flips_left_out, 0);
  EXPECT_EQ(t.before.position_mm.count, 2);
  EXPECT_NEAR(t.before.position_mm.mean, 2e3 * std::sqrt(0.26), 1e-9);  // 2 |p| each
  EXPECT_EQ(FormatTable1(t).find("left out"), std::string::npos);
  // Exactly half is not a minority either.
  const std::vector<Eigen::Vector3d> half_reported = {{0.1, 0, -0.5}, {0, -0.1, 0.5}};
  const std::vector<Eigen::Vector3d> half_reference = {{0.1, 0, -0.5}, {0, 0.1, -0.5}};
  EXPECT_TRUE(HemisphereFlipsToLeaveOut(half_reported, half_reference).empty());
  EXPECT_THROW(MakeTable1("valid", reported, reported, Positions({{0, 0, -0.5}})),
               std::invalid_argument);
}

}  // namespace
}  // namespace trackcal
