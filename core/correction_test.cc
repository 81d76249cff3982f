#include "core/correction.h"

#include <gtest/gtest.h>

#include <limits>
#include <random>

#include "core/lut.h"
#include "core/polynomial.h"
#include "tests/test_utils.h"

namespace trackcal {
namespace {

using testing::RandomRotation;
using testing::TestRng;

// Degree-1 polynomial: position error = a + b * x (x in metres, offset 0, scale 1), no rotation.
std::unique_ptr<PolynomialCorrection> LinearInX(double a, double b) {
  std::vector<double> c(6 * 4, 0.0);
  c[0] = a;      // term 1, position x
  c[6 * 1] = b;  // term x, position x
  return std::make_unique<PolynomialCorrection>(1, Eigen::Vector3d::Zero(),
                                                Eigen::Vector3d::Ones(), c);
}

// A degree-2 polynomial with position and orientation parts, for the volume tests.
std::unique_ptr<PolynomialCorrection> Curved() {
  std::vector<double> c(6 * 10, 0.0);
  c[0] = 0.01;
  c[6 * 4 + 1] = 0.02;   // x^2 -> position y
  c[6 * 9 + 2] = -0.03;  // z^2 -> position z
  c[6 * 3 + 3] = 0.02;   // z -> orientation x
  c[6 * 5 + 5] = 0.01;   // xy -> orientation z
  return std::make_unique<PolynomialCorrection>(2, Eigen::Vector3d::Zero(),
                                                Eigen::Vector3d::Ones(), c);
}

CalibratedVolume UnitBox(ExtrapolationPolicy policy, double fade = 0.0) {
  CalibratedVolume v;
  v.min = Eigen::Vector3d(-0.5, -0.5, -0.5);
  v.max = Eigen::Vector3d(0.5, 0.5, 0.5);
  v.extrapolation = policy;
  v.fade_distance = fade;
  return v;
}

TEST(CorrectionChain, Nominal) {
  // Terms apply in order, each to the output of the previous one.
  CorrectionChain ab, ba;
  ab.Append(LinearInX(0.1, 0.0));
  ab.Append(LinearInX(0.0, 0.5));
  ba.Append(LinearInX(0.0, 0.5));
  ba.Append(LinearInX(0.1, 0.0));
  const Rigid3d reported(RandomRotation(TestRng()), Eigen::Vector3d(0.2, 0.3, 0.4));
  // a then b: x -> x + 0.1 -> (x + 0.1) * 1.5; b then a: x -> 1.5 x -> 1.5 x + 0.1.
  EXPECT_NEAR(ab.Apply(reported).pose.translation.x(), 0.45, 1e-15);
  EXPECT_NEAR(ba.Apply(reported).pose.translation.x(), 0.4, 1e-15);
  EXPECT_FALSE(ab.Apply(reported).extrapolated);
}

TEST(CorrectionChain, RotationsComposeInOrder) {
  const Eigen::Quaterniond qa(Eigen::AngleAxisd(0.1, Eigen::Vector3d::UnitX()));
  const Eigen::Quaterniond qb(Eigen::AngleAxisd(0.2, Eigen::Vector3d::UnitY()));
  auto constant = [](const Eigen::Quaterniond& q) {
    return std::make_unique<PolynomialCorrection>(
        0, Eigen::Vector3d::Zero(), Eigen::Vector3d::Ones(),
        std::vector<double>{0, 0, 0, q.x(), q.y(), q.z()});
  };
  CorrectionChain chain;
  chain.Append(constant(qa));
  chain.Append(constant(qb));
  const Rigid3d reported(RandomRotation(TestRng()), Eigen::Vector3d(0.1, 0.1, 0.1));
  EXPECT_TRUE(testing::RotationsNear(qb * qa * reported.rotation,
                                     chain.Apply(reported).pose.rotation, 1e-14));
  EXPECT_FALSE(testing::RotationsNear(qa * qb * reported.rotation,
                                      chain.Apply(reported).pose.rotation, 1e-3));
}

TEST(CorrectionChain, ClampHoldsBoundaryCorrection) {
  CorrectionChain chain;
  chain.Append(Curved());
  chain.SetVolume(UnitBox(ExtrapolationPolicy::kClamp));
  for (int i = 0; i < 50; ++i) {
    const Eigen::Quaterniond q = RandomRotation(TestRng());
    const Eigen::Vector3d inside(0.3, -0.2, 0.45);
    const CorrectedPose in = chain.Apply(Rigid3d(q, inside));
    EXPECT_FALSE(in.extrapolated);
    EXPECT_TRUE(testing::PosesNear(Curved()->Apply(Rigid3d(q, inside)).pose, in.pose, 0, 0));

    const Eigen::Vector3d outside(2.0, -0.2, -3.0);
    const Eigen::Vector3d nearest(0.5, -0.2, -0.5);
    const CorrectedPose out = chain.Apply(Rigid3d(q, outside));
    EXPECT_TRUE(out.extrapolated);
    const CorrectedPose at_boundary = Curved()->Apply(Rigid3d(q, nearest));
    // Same position offset and the same world-frame rotation as at the nearest point of the box.
    // Offsets of ~0.03 recovered by subtracting positions of ~3: rounding ~1e-15 absolute.
    EXPECT_LT(((out.pose.translation - outside) - (at_boundary.pose.translation - nearest)).norm(),
              2e-15);
    EXPECT_TRUE(testing::RotationsNear(at_boundary.pose.rotation, out.pose.rotation, 1e-14));
  }
}

// A degree-1 polynomial with every position and orientation coefficient set (~1e-2).
std::unique_ptr<PolynomialCorrection> Linear() {
  std::vector<double> c(6 * 4);
  std::normal_distribution<double> n(0.0, 0.01);
  std::mt19937_64 rng(7);
  for (double& v : c) v = n(rng);
  return std::make_unique<PolynomialCorrection>(1, Eigen::Vector3d::Zero(),
                                                Eigen::Vector3d::Ones(), c);
}

CalibratedVolume LinearBox(double reach) {
  CalibratedVolume v = UnitBox(ExtrapolationPolicy::kLinear);
  v.linear_reach = reach;
  return v;
}

TEST(CorrectionChain, LinearPolicyReproducesALinearDistortionOutsideTheBox) {
  // A linear distortion is its own first-order continuation: outside the box (on one, two or three
  // axes, up to 3 m out) the guarded chain equals the polynomial applied everywhere; clamp does not.
  CorrectionChain chain, clamped;
  chain.Append(Linear());
  chain.SetVolume(LinearBox(10.0));
  clamped.Append(Linear());
  clamped.SetVolume(UnitBox(ExtrapolationPolicy::kClamp));
  const auto unguarded = Linear();
  for (const Eigen::Vector3d& p :
       {Eigen::Vector3d(2.0, -0.2, -3.0), Eigen::Vector3d(0.8, 0.9, 0.1),
        Eigen::Vector3d(-0.7, 0.3, 0.2), Eigen::Vector3d(-1.5, -0.9, 0.6)}) {
    const Rigid3d reported(RandomRotation(TestRng()), p);
    const CorrectedPose out = chain.Apply(reported);
    const Rigid3d expected = unguarded->Apply(reported).pose;
    EXPECT_TRUE(out.extrapolated);
    // The slopes come from differences of ~1e-2 corrections over 2 mm: rounding ~1e-17 / 2e-3 per
    // metre, times a few metres out: ~1e-13; 1e-11 leaves room and is 1e-8 of the correction.
    EXPECT_LT((out.pose.translation - expected.translation).norm(), 1e-11) << p.transpose();
    EXPECT_TRUE(testing::RotationsNear(expected.rotation, out.pose.rotation, 1e-11))
        << p.transpose();
    // Holding the edge value is off by the slope (~1e-2) times the distance (>= 0.2 m): > 1 mm.
    EXPECT_GT((clamped.Apply(reported).pose.translation - expected.translation).norm(), 1e-3)
        << p.transpose();
  }
}

TEST(CorrectionChain, LinearPolicyContinuesTheTangentOfACurvedCorrection) {
  // Curved() out of the x = 0.5 face at (0.5 + d, y, z): the position correction's y part 0.02 x^2
  // continues as its tangent 0.02 (0.25 + d) (the one-sided second-order difference is exact for a
  // quadratic); the other parts are constant or linear in x and continue exactly.
  CorrectionChain chain;
  chain.Append(Curved());
  chain.SetVolume(LinearBox(10.0));
  const Eigen::Quaterniond q = RandomRotation(TestRng());
  const double y = -0.2, z = 0.3;
  for (double d : {1e-6, 0.01, 0.3, 2.0}) {
    const Eigen::Vector3d p(0.5 + d, y, z);
    const CorrectedPose out = chain.Apply(Rigid3d(q, p));
    EXPECT_TRUE(out.extrapolated);
    const Eigen::Vector3d expected_offset(0.01, 0.02 * (0.25 + d), -0.03 * z * z);
    // Rounding as above (~1e-13 at 2 m out).
    EXPECT_LT(((out.pose.translation - p) - expected_offset).norm(), 1e-12) << d;
    const Eigen::Vector3d expected_vector(0.02 * z, 0.0, 0.01 * (0.5 + d) * y);
    EXPECT_LT((VectorPart(out.pose.rotation * q.conjugate()) - expected_vector).norm(), 1e-12)
        << d;
  }
}

TEST(CorrectionChain, LinearPolicyHoldsBeyondItsReach) {
  // Beyond linear_reach the continuation stops growing: the correction is the one at the point
  // `reach` out along the way from the box, held.
  const double reach = 0.2;
  CorrectionChain chain;
  chain.Append(Linear());
  chain.SetVolume(LinearBox(reach));
  const auto unguarded = Linear();
  const Eigen::Quaterniond q = RandomRotation(TestRng());
  const Eigen::Vector3d p(1.3, -0.9, 0.1), box_point(0.5, -0.5, 0.1);
  const Eigen::Vector3d at_reach = box_point + reach * (p - box_point).normalized();
  const Rigid3d held = unguarded->Apply(Rigid3d(q, at_reach)).pose;
  const CorrectedPose out = chain.Apply(Rigid3d(q, p));
  // Rounding as above, within 0.2 m.
  EXPECT_LT(((out.pose.translation - p) - (held.translation - at_reach)).norm(), 1e-12);
  EXPECT_TRUE(testing::RotationsNear(held.rotation, out.pose.rotation, 1e-12));
  // Within the reach it is still the distortion itself.
  const Eigen::Vector3d near = box_point + 0.5 * reach * (p - box_point).normalized();
  EXPECT_TRUE(testing::PosesNear(unguarded->Apply(Rigid3d(q, near)).pose,
                                 chain.Apply(Rigid3d(q, near)).pose, 1e-12, 1e-12));
  // A zero reach is clamp.
  chain.SetVolume(LinearBox(0.0));
  CorrectionChain clamped;
  clamped.Append(Linear());
  clamped.SetVolume(UnitBox(ExtrapolationPolicy::kClamp));
  EXPECT_TRUE(testing::PosesNear(clamped.Apply(Rigid3d(q, p)).pose, chain.Apply(Rigid3d(q, p)).pose,
                                 1e-15, 1e-15));
}

TEST(CorrectionChain, LinearPolicyContinuesALutsLastCell) {
  // A trilinear LUT is linear along an axis within a cell: out of the grid it continues its last
  // cell's gradient (the 1 mm differences stay inside the 0.5 m cells). Grid = volume here.
  const LutGrid grid({std::vector<double>{-0.5, 0.0, 0.5}, std::vector<double>{-0.5, 0.5},
                      std::vector<double>{-0.5, 0.5}});
  std::vector<double> values(6 * grid.num_nodes());
  std::normal_distribution<double> noise(0.0, 0.005);
  for (double& v : values) v = noise(TestRng());
  const TrilinearLutCorrection lut(grid, values);
  CorrectionChain chain;
  chain.Append(lut.Clone());
  chain.SetVolume(LinearBox(10.0));
  const Eigen::Quaterniond q = RandomRotation(TestRng());
  const Eigen::Vector3d b(0.5, 0.1, -0.2);
  const Eigen::Vector3d e_b = lut.Apply(Rigid3d(q, b)).pose.translation - b;
  const Eigen::Vector3d inner(0.25, 0.1, -0.2);  // halfway into the last cell
  const Eigen::Vector3d e_inner = lut.Apply(Rigid3d(q, inner)).pose.translation - inner;
  const double d = 0.4;
  const Eigen::Vector3d p = b + Eigen::Vector3d(d, 0, 0);
  const Eigen::Vector3d expected = e_b + (e_b - e_inner) / 0.25 * d;
  // Rounding of ~5e-3 values over 2 mm differences, times 0.4 m: ~1e-14.
  EXPECT_LT(((chain.Apply(Rigid3d(q, p)).pose.translation - p) - expected).norm(), 1e-12);
  EXPECT_TRUE(chain.Apply(Rigid3d(q, p)).extrapolated);
}

TEST(CorrectionChain, FadeReachesIdentitySmoothly) {
  const double fade = 0.2;
  CorrectionChain chain;
  chain.Append(Curved());
  chain.SetVolume(UnitBox(ExtrapolationPolicy::kFade, fade));
  const Eigen::Quaterniond q = RandomRotation(TestRng());
  const Eigen::Vector3d boundary(0.5, 0.1, 0.2);
  const CorrectedPose at_boundary = chain.Apply(Rigid3d(q, boundary));
  const Eigen::Vector3d e_boundary = at_boundary.pose.translation - boundary;
  const double angle_boundary = AngularDistance(at_boundary.pose.rotation, q);
  ASSERT_GT(e_boundary.norm(), 1e-3);
  ASSERT_GT(angle_boundary, 1e-3);
  double previous = 1.0;
  for (double d : {1e-9, 0.05, 0.1, 0.15, 0.199}) {
    const Eigen::Vector3d p = boundary + Eigen::Vector3d(d, 0, 0);
    const CorrectedPose out = chain.Apply(Rigid3d(q, p));
    EXPECT_TRUE(out.extrapolated);
    const double s = d / fade;
    const double w = 1 - s * s * (3 - 2 * s);
    // Absolute tolerances: rounding of positions ~1 and of quaternion products, not relative to w.
    EXPECT_LT(((out.pose.translation - p) - w * e_boundary).norm(), 2e-15) << d;
    // The rotation's vector part is scaled by w.
    const Eigen::Quaterniond q_e = out.pose.rotation * q.conjugate();
    const Eigen::Quaterniond q_e_boundary = at_boundary.pose.rotation * q.conjugate();
    EXPECT_LT((VectorPart(q_e) - w * VectorPart(q_e_boundary)).norm(), 1e-15) << d;
    EXPECT_LE(w, previous);
    previous = w;
  }
  // Continuous at the box (1e-9 outside differs from the boundary by ~1e-9 only).
  const CorrectedPose just_outside =
      chain.Apply(Rigid3d(q, boundary + Eigen::Vector3d(1e-9, 0, 0)));
  EXPECT_NEAR((just_outside.pose.translation - boundary - e_boundary).norm(), 0.0, 2e-9);
  // Identity at and beyond fade_distance.
  for (double d : {0.2, 0.5, 100.0}) {
    const Eigen::Vector3d p = boundary + Eigen::Vector3d(0, 0, 0) + Eigen::Vector3d(d, 0, 0);
    const CorrectedPose out = chain.Apply(Rigid3d(q, p));
    EXPECT_TRUE(out.extrapolated);
    EXPECT_TRUE(testing::PosesNear(Rigid3d(q, p), out.pose, 0.0, 1e-15)) << d;
  }
}

TEST(CorrectionChain, BatchMatchesSingle) {
  CorrectionChain chain;
  chain.Append(Curved());
  chain.Append(LinearInX(0.01, 0.02));
  // A LUT grid narrower than the volume in z: poses above z = 0.4 are flagged by the LUT itself.
  const LutGrid grid({std::vector<double>{-0.5, 0.5}, std::vector<double>{-0.5, 0.5},
                      std::vector<double>{-0.5, 0.0, 0.4}});
  std::vector<double> values(6 * grid.num_nodes());
  std::normal_distribution<double> noise(0.0, 0.001);
  for (double& v : values) v = noise(TestRng());
  chain.Append(std::make_unique<TrilinearLutCorrection>(grid, values));
  chain.SetVolume(UnitBox(ExtrapolationPolicy::kFade, 0.3));
  // 600 poses = chunks of 256, 256, 88 in the batch path; only pose 300 is outside the volume, so
  // chunks 0 and 2 take the vectorised path and chunk 1 the per-pose path.
  const size_t n = 600;
  std::vector<double> pos(3 * n), quat(4 * n), out_pos(3 * n), out_quat(4 * n);
  std::vector<uint8_t> flags(n);
  std::uniform_real_distribution<double> u(-0.49, 0.49);
  for (size_t i = 0; i < n; ++i) {
    for (int k = 0; k < 3; ++k) pos[3 * i + k] = u(TestRng());
    QuaternionToXyzwArray(RandomRotation(TestRng()), &quat[4 * i]);
  }
  pos[3 * 300] = 0.7;
  chain.ApplyBatch(n, pos.data(), quat.data(), out_pos.data(), out_quat.data(), flags.data());
  int flagged = 0, flagged_by_lut = 0;
  for (size_t i = 0; i < n; ++i) {
    const Eigen::Vector3d p(pos[3 * i], pos[3 * i + 1], pos[3 * i + 2]);
    const CorrectedPose single = chain.Apply(Rigid3d(QuaternionFromXyzwArray(&quat[4 * i]), p));
    EXPECT_EQ(flags[i] != 0, single.extrapolated) << i;
    if (!chain.volume()->Contains(p)) {
      EXPECT_TRUE(single.extrapolated) << i;
    }
    // Inside the volume only the LUT flags, for poses the earlier terms left above its grid.
    if (chain.volume()->Contains(p) && flags[i]) ++flagged_by_lut;
    flagged += flags[i];
    // The batch kernel sums in another order (and may use FMA): rounding of values ~1.
    const Rigid3d batch(QuaternionFromXyzwArray(&out_quat[4 * i]),
                        Eigen::Vector3d(out_pos[3 * i], out_pos[3 * i + 1], out_pos[3 * i + 2]));
    EXPECT_TRUE(testing::PosesNear(single.pose, batch, 1e-15, 1e-15)) << i;
  }
  EXPECT_GT(flagged_by_lut, 0);
  EXPECT_TRUE(flags[300]);
  EXPECT_LT(flagged, static_cast<int>(n));
  // In place, and without flags.
  chain.ApplyBatch(n, pos.data(), quat.data(), pos.data(), quat.data(), nullptr);
  EXPECT_EQ(pos, out_pos);
  EXPECT_EQ(quat, out_quat);
}

TEST(CorrectionChain, LutOutsideItsGridFlagsEvenWithoutVolume) {
  const LutGrid grid({std::vector<double>{0, 1}, std::vector<double>{0, 1},
                      std::vector<double>{0, 1}});
  CorrectionChain chain;
  chain.Append(std::make_unique<TrilinearLutCorrection>(grid, std::vector<double>(48, 0.001)));
  EXPECT_FALSE(chain.Apply(Rigid3d(Eigen::Quaterniond::Identity(), Eigen::Vector3d(0.5, 0.5, 0.5)))
                   .extrapolated);
  EXPECT_TRUE(chain.Apply(Rigid3d(Eigen::Quaterniond::Identity(), Eigen::Vector3d(1.5, 0.5, 0.5)))
                  .extrapolated);
}

TEST(CalibratedVolume, RejectsEmptyAndBadFade) {
  CalibratedVolume v = UnitBox(ExtrapolationPolicy::kClamp);
  EXPECT_NO_THROW(v.Check());
  v.max.y() = v.min.y();
  EXPECT_THROW(v.Check(), std::invalid_argument);
  v = UnitBox(ExtrapolationPolicy::kFade, 0.0);
  EXPECT_THROW(v.Check(), std::invalid_argument);
  v.fade_distance = std::numeric_limits<double>::infinity();
  EXPECT_THROW(v.Check(), std::invalid_argument);
  CorrectionChain chain;
  EXPECT_THROW(chain.SetVolume(v), std::invalid_argument);
  EXPECT_EQ(ExtrapolationPolicyFromName("fade"), ExtrapolationPolicy::kFade);
  EXPECT_THROW(ExtrapolationPolicyFromName("hold"), std::invalid_argument);
}

TEST(CalibratedVolume, LinearIsTheDefaultAndItsReachIsChecked) {
  const CalibratedVolume defaults;
  EXPECT_EQ(defaults.extrapolation, ExtrapolationPolicy::kLinear);
  EXPECT_EQ(defaults.linear_reach, CalibratedVolume::kDefaultLinearReach);
  EXPECT_EQ(ExtrapolationPolicyFromName("linear"), ExtrapolationPolicy::kLinear);
  EXPECT_EQ(ExtrapolationPolicyName(ExtrapolationPolicy::kLinear), "linear");
  CalibratedVolume v = LinearBox(0.1);
  EXPECT_NO_THROW(v.Check());
  for (double bad : {-0.1, std::numeric_limits<double>::quiet_NaN(),
                     std::numeric_limits<double>::infinity()}) {
    v.linear_reach = bad;
    EXPECT_THROW(v.Check(), std::invalid_argument) << bad;
    CorrectionChain chain;
    EXPECT_THROW(chain.SetVolume(v), std::invalid_argument) << bad;
  }
}

// A term type added from outside core, the way fit/ adds physical models.
class ConstantShift : public Correction {
 public:
  explicit ConstantShift(const Eigen::Vector3d& shift) : shift_(shift) {}
  static std::unique_ptr<Correction> FromJson(const JsonObjectReader& r) {
    r.Get("type");
    return std::make_unique<ConstantShift>(r.Vector3("shift"));
  }
  std::string TypeName() const override { return "test_constant_shift"; }
  CorrectedPose Apply(const Rigid3d& in) const override {
    return {Rigid3d(in.rotation, in.translation + shift_), false};
  }
  nlohmann::json ToJson() const override {
    return {{"type", TypeName()}, {"shift", {shift_.x(), shift_.y(), shift_.z()}}};
  }
  std::unique_ptr<Correction> Clone() const override {
    return std::make_unique<ConstantShift>(*this);
  }

 private:
  Eigen::Vector3d shift_;
};

TEST(CorrectionRegistry, ExtensibleByName) {
  CorrectionRegistry& registry = CorrectionRegistry::Global();
  EXPECT_TRUE(registry.Contains("polynomial"));
  EXPECT_TRUE(registry.Contains("trilinear_lut"));
  if (!registry.Contains("test_constant_shift")) {
    registry.Register("test_constant_shift", &ConstantShift::FromJson);
  }
  EXPECT_THROW(registry.Register("test_constant_shift", &ConstantShift::FromJson),
               std::invalid_argument);
  const nlohmann::json j = {{"type", "test_constant_shift"}, {"shift", {0.1, 0.2, 0.3}}};
  const auto c = registry.Parse(j, "mem", "$.corrections[0]");
  EXPECT_EQ(c->TypeName(), "test_constant_shift");
  EXPECT_EQ(c->ToJson(), j);
  // The registry rejects fields the parser did not read.
  nlohmann::json extra = j;
  extra["sihft"] = 1;
  try {
    registry.Parse(extra, "mem", "$.corrections[0]");
    FAIL();
  } catch (const JsonInputError& e) {
    EXPECT_STREQ(e.what(), "mem: $.corrections[0].sihft: unknown field");
  }
  try {
    registry.Parse({{"type", "dipole_v9"}}, "mem", "$.corrections[2]");
    FAIL();
  } catch (const JsonInputError& e) {
    const std::string what = e.what();
    EXPECT_EQ(what.rfind("mem: $.corrections[2].type: unknown correction type \"dipole_v9\"", 0),
              0u)
        << what;
    EXPECT_NE(what.find("\"polynomial\""), std::string::npos) << what;
  }
}

// A term like a physical model: position-dependent, valid everywhere, so not guarded by the volume.
class UnguardedScale : public Correction {
 public:
  explicit UnguardedScale(double k) : k_(k) {}
  std::string TypeName() const override { return "test_unguarded_scale"; }
  CorrectedPose Apply(const Rigid3d& in) const override {
    return {Rigid3d(in.rotation, (1.0 + k_) * in.translation), false};
  }
  nlohmann::json ToJson() const override { return {{"type", TypeName()}, {"k", k_}}; }
  std::unique_ptr<Correction> Clone() const override {
    return std::make_unique<UnguardedScale>(*this);
  }
  bool GuardedByVolume() const override { return false; }

 private:
  double k_;
};

TEST(CorrectionChain, OutsideTheVolumeOnlyGuardedTermsAreClamped) {
  const UnguardedScale physical(0.01);
  CorrectionChain chain;
  chain.Append(physical.Clone());
  chain.Append(Curved());
  chain.SetVolume(UnitBox(ExtrapolationPolicy::kClamp));
  const Eigen::Quaterniond q = RandomRotation(TestRng());
  const Rigid3d reported(q, Eigen::Vector3d(2.0, -0.2, -3.0));
  const CorrectedPose out = chain.Apply(reported);
  EXPECT_TRUE(out.extrapolated);
  // The physical term at the actual pose (not at the box: that would give a 1 cm shift of the
  // boundary point instead of 3.6 cm), then the polynomial's correction held from the nearest point
  // of the box to its input.
  const Rigid3d after_physical = physical.Apply(reported).pose;
  const Eigen::Vector3d nearest = chain.volume()->Nearest(after_physical.translation);
  const CorrectedPose at_boundary = Curved()->Apply(Rigid3d(q, nearest));
  const Eigen::Vector3d expected =
      after_physical.translation + (at_boundary.pose.translation - nearest);
  // Positions ~3 m: rounding ~1e-15 absolute.
  EXPECT_LT((out.pose.translation - expected).norm(), 4e-15);
  EXPECT_TRUE(testing::RotationsNear(at_boundary.pose.rotation, out.pose.rotation, 1e-14));

  // Far beyond a fade, the guarded term has faded to nothing while the physical one still applies.
  chain.SetVolume(UnitBox(ExtrapolationPolicy::kFade, 0.2));
  const CorrectedPose faded = chain.Apply(reported);
  EXPECT_TRUE(faded.extrapolated);
  EXPECT_TRUE(testing::PosesNear(after_physical, faded.pose, 1e-15, 1e-15));
  // Linear: the physical term still at the actual pose, the polynomial continued to first order
  // from the nearest point of the box to its own input. Curved()'s parts are linear along the way
  // out except the quadratics 0.02 x^2 (position y) and -0.03 z^2 (position z), whose tangents
  // leave 0.02 dx^2 and -0.03 dz^2 (dx, dz: how far out the input is on x and z).
  chain.SetVolume(LinearBox(10.0));
  const CorrectedPose linear = chain.Apply(reported);
  EXPECT_TRUE(linear.extrapolated);
  const Rigid3d curved_everywhere = Curved()->Apply(after_physical).pose;
  const Eigen::Vector3d out_by = after_physical.translation - nearest;
  const Eigen::Vector3d second_order(0.0, 0.02 * out_by.x() * out_by.x(),
                                     -0.03 * out_by.z() * out_by.z());
  // Rounding as in LinearPolicyReproducesALinearDistortionOutsideTheBox, ~3 m out.
  EXPECT_LT((linear.pose.translation - (curved_everywhere.translation - second_order)).norm(),
            1e-11);
  EXPECT_TRUE(testing::RotationsNear(curved_everywhere.rotation, linear.pose.rotation, 1e-11));

  // Inside the box the chain is unchanged by the volume.
  const Rigid3d inside(q, Eigen::Vector3d(0.3, -0.2, 0.4));
  CorrectionChain unguarded_chain;
  unguarded_chain.Append(physical.Clone());
  unguarded_chain.Append(Curved());
  EXPECT_TRUE(testing::PosesNear(unguarded_chain.Apply(inside).pose, chain.Apply(inside).pose, 0, 0));
}

TEST(CorrectionChain, CopyIsDeep) {
  CorrectionChain chain;
  chain.Append(LinearInX(0.1, 0.0));
  chain.SetVolume(UnitBox(ExtrapolationPolicy::kClamp));
  CorrectionChain copy = chain;
  chain.Append(LinearInX(0.1, 0.0));
  EXPECT_EQ(copy.size(), 1u);
  EXPECT_EQ(chain.size(), 2u);
  EXPECT_TRUE(copy.volume().has_value());
}

}  // namespace
}  // namespace trackcal
