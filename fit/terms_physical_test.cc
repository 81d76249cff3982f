#include "fit/terms_physical.h"

#include <ceres/manifold.h>
#include <gtest/gtest.h>

#include <Eigen/Geometry>
#include <cmath>
#include <cstring>
#include <fstream>
#include <memory>
#include <string>
#include <vector>

#include "core/calibration_file.h"
#include "core/tracker_solver.h"
#include "fit/fit_engine.h"
#include "fit/model_file.h"
#include "tests/test_utils.h"

namespace trackcal::fit {
namespace {

// A physical model of the form the terms fit: field, receiver gains, sensor offset.
struct PhysicalTruth {
  FieldModel field;
  Eigen::Matrix3d gain = Eigen::Matrix3d::Identity();
  Rigid3d receiver_from_body;
};

// The paper room's effects (sim/scenes/paper.yaml, hidden section) without the simulator.
PhysicalTruth PaperLikeTruth() {
  PhysicalTruth t;
  t.field.transmitter_octupole_m2 = Eigen::Vector3d(-0.000675, -0.0006, -0.00075);
  t.field.planes.push_back({"floor", Eigen::Vector3d(0, 0, 0.8), Eigen::Vector3d(0, 0, 1), 0.27});
  t.field.objects.push_back({"toolbox", Eigen::Vector3d(0.6, 0.95, -0.5), 0.002});
  t.gain << 1.02, 0.01, 0, -0.005, 0.98, 0.015, 0, 0.008, 1.01;
  t.receiver_from_body = Rigid3d(QuaternionFromXyzw(0.02, -0.015, 0.01, 0.99966).normalized(),
                                 Eigen::Vector3d(0.012, -0.008, 0.02));
  return t;
}

// Noise-free stations: random receiver poses in the paper's volume (z down, 0.35 to 0.8 m above the
// transmitter), reported by the tracker's free-space solver from the signal of `truth`.
std::vector<FitStation> NoiseFreeStations(const PhysicalTruth& truth, int n) {
  std::mt19937_64& rng = trackcal::testing::TestRng();
  std::uniform_real_distribution<double> ux(-0.8, 0.8), uy(-0.65, 0.65), uz(-0.8, -0.35);
  TrackerSolverOptions solver;
  solver.hemisphere_in_transmitter = Eigen::Vector3d(0, 0, -1);
  std::vector<FitStation> out;
  for (int i = 0; i < n; ++i) {
    const Rigid3d x(trackcal::testing::RandomRotation(rng), Eigen::Vector3d(ux(rng), uy(rng), uz(rng)));
    const Eigen::Matrix3d s =
        SignalMatrix<double>(truth.gain, x.rotation.toRotationMatrix(), truth.field.Field(x.translation));
    const TrackerSolution report = SolveFreeSpacePose(s, solver);
    FitStation station;
    station.reported = report.transmitter_from_receiver;
    station.reference = x * truth.receiver_from_body;
    station.station = i;
    out.push_back(station);
  }
  return out;
}

const ParameterReport& Find(const FitResult& result, const std::string& term,
                            const std::string& block) {
  for (const auto& p : result.parameters) {
    if (p.term == term && p.block == block) return p;
  }
  throw std::runtime_error("no parameter " + term + "." + block);
}

TEST(PhysicalTerms, Nominal_ParsesAllFiveIntoOneGroup) {
  const ModelSpec spec = ParseModelYaml(R"(terms:
  - type: sensor_offset
  - type: receiver_gain
    receiver_gain_matrix: [[1.01, 0, 0], [0, 1, 0], [0, 0, 1]]
  - type: dipole
    location_in_transmitter: [0.6, 0.95, -0.5]
    polarisability_m3: 0.002
  - type: dipole
    name: cabinet
  - type: plane
    point_in_transmitter: [0, 0, 0.8]
    normal_in_transmitter: [0, 0, 2]
    attenuation: 0.2
    parameters:
      attenuation: {fixed: true}
  - type: near_field
  - type: polynomial
    degree: 2
)",
                                        "m.yaml");
  ASSERT_EQ(spec.terms.size(), 2u);  // one physical group, one polynomial
  ASSERT_EQ(spec.file_terms.size(), 7u);
  EXPECT_EQ(spec.file_terms[3].name, "cabinet");
  EXPECT_EQ(spec.file_terms[3].line, 8);
  EXPECT_EQ(spec.file_terms[6].model_term, 1);
  const auto& group = dynamic_cast<const PhysicalGroupTerm&>(*spec.terms[0]);
  ASSERT_EQ(group.effects().size(), 6u);
  EXPECT_EQ(group.effects()[2].name, "dipole");
  EXPECT_FALSE(group.effects()[2].search_location);
  EXPECT_TRUE(group.effects()[3].search_location);
  // Blocks keep the names of their effects; the plane's point becomes its distance along the normal.
  bool found_distance = false;
  for (const auto& b : group.blocks()) {
    EXPECT_FALSE(b.term.empty()) << b.name;
    if (b.name == "distance_m") {
      EXPECT_EQ(b.term, "plane");
      EXPECT_DOUBLE_EQ(b.values[0], 0.8);
      found_distance = true;
    }
  }
  EXPECT_TRUE(found_distance);
  ASSERT_EQ(spec.block_settings[0].size(), 1u);
  EXPECT_EQ(spec.block_settings[0][0].term, "plane");
}

// A manifold block's stds are its tangent coordinates times tangent_scale, stated in
// tangent_unit (rad): one tangent unit must turn the block by tangent_scale radians. The plane's
// normal (SphereManifold<3>, which turns by |delta| / 2) had scale 1, so its angle stds were twice
// the normal's angular uncertainty (and diagnose's normal test, 0.1 rad, twice as strict).
TEST(PhysicalTerms, ManifoldTangentScaleIsTheAngleTurnedPerTangentUnit) {
  const ModelSpec spec = ParseModelYaml(R"(terms:
  - type: sensor_offset
  - type: plane
    point_in_transmitter: [0, 0, 0.8]
    normal_in_transmitter: [0, 0.6, 0.8]
)",
                                        "m.yaml");
  int checked = 0;
  for (const auto& term : spec.terms) {
    for (const auto& b : term->blocks()) {
      if (!b.make_manifold || b.tangent_unit != "rad") continue;
      std::unique_ptr<ceres::Manifold> manifold(b.make_manifold());
      ASSERT_EQ(manifold->TangentSize(), static_cast<int>(b.tangent_names.size())) << b.name;
      for (int k = 0; k < manifold->TangentSize(); ++k) {
        std::vector<double> delta(static_cast<size_t>(manifold->TangentSize()), 0.0);
        delta[static_cast<size_t>(k)] = 1e-3;
        std::vector<double> moved(b.values.size());
        ASSERT_TRUE(manifold->Plus(b.values.data(), delta.data(), moved.data()));
        double angle = 0.0;
        if (b.values.size() == 4) {  // x, y, z, w: the rotation from the old to the new
          const Eigen::Quaterniond q0(b.values[3], b.values[0], b.values[1], b.values[2]);
          const Eigen::Quaterniond q1(moved[3], moved[0], moved[1], moved[2]);
          angle = q1.angularDistance(q0);
        } else {  // a unit vector: the angle between the old and the new
          const Eigen::Map<const Eigen::Vector3d> v0(b.values.data()), v1(moved.data());
          angle = std::atan2(v0.cross(v1).norm(), v0.dot(v1));
        }
        EXPECT_NEAR(angle, b.tangent_scale * 1e-3, 1e-9) << b.term << "." << b.name << " " << k;
        ++checked;
      }
    }
  }
  EXPECT_EQ(checked, 3 + 2);  // the sensor offset's rotation, the plane's normal
}

TEST(PhysicalTerms, RejectsPhysicalTermAfterExplicitWithFileAndLine) {
  try {
    ParseModelYaml("terms:\n  - type: polynomial\n    degree: 2\n  - type: dipole\n", "m.yaml");
    FAIL() << "no error";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("m.yaml:4:"), std::string::npos) << e.what();
    EXPECT_NE(std::string(e.what()).find("physical terms must come first"), std::string::npos);
  }
}

TEST(PhysicalTerms, RejectsBadValuesWithFileAndLine) {
  const auto expect_error = [](const std::string& yaml, const std::string& where) {
    try {
      ParseModelYaml(yaml, "m.yaml");
      ADD_FAILURE() << "no error for " << yaml;
    } catch (const std::invalid_argument& e) {
      EXPECT_NE(std::string(e.what()).find(where), std::string::npos) << e.what();
    }
  };
  expect_error("terms:\n  - type: plane\n    normal_in_transmitter: [0, 0, 1]\n    attenuation: 1.5\n",
               "m.yaml:4:18: $.terms[0].attenuation");
  expect_error("terms:\n  - type: receiver_gain\n  - type: receiver_gain\n", "m.yaml:3:");
  expect_error("terms:\n  - type: receiver_gain\n    gain_scale: fixed\n",
               "m.yaml:3:17: $.terms[0].gain_scale");
  expect_error("terms:\n  - type: dipole\n    location_in_transmitter: [1, 2]\n", "m.yaml:3:");
  expect_error("terms:\n  - type: background_field\n    degree: 3\n", "m.yaml:3:13: $.terms[0].degree");
  expect_error("terms:\n  - type: background_field\n    coefficients: [0, 0, 0]\n",
               "m.yaml:3:19: $.terms[0].coefficients: expected 24 numbers");
  expect_error("terms:\n  - type: background_field\n  - type: background_field\n", "m.yaml:3:");
  expect_error("terms:\n  - type: dipole\n    parameters:\n      strength: {fixed: true}\n",
               "has no parameter block 'strength'");
  // A plane through the transmitter puts its image on the transmitter: caught at the file, not
  // after a fit whose every evaluation failed ("field model: planes[0]...", no file or line).
  expect_error(
      "terms:\n  - type: plane\n    point_in_transmitter: [0.3, -0.2, 0.0005]\n"
      "    normal_in_transmitter: [0, 0, 1]\n",
      "m.yaml:3:27: $.terms[0].point_in_transmitter: the plane passes through the transmitter");
}

// A start off the unit sphere of a quaternion or normal block (`parameters: {BLOCK: {value: ...}}`,
// applied when the fit starts): a zero one (`value: 0` for "no rotation") failed every evaluation
// and the fit ended in "receiver_from_body must be finite with a unit quaternion" / "plane: zero
// normal", naming no file or line; a quaternion of norm 2 was fitted and reported with norm 2.
TEST(PhysicalTerms, QuaternionAndNormalStartsMustBeUnitVectors) {
  const std::vector<FitStation> stations = NoiseFreeStations(PaperLikeTruth(), 20);
  const auto expect_error = [&](const std::string& yaml, const std::string& where) {
    ModelSpec spec = ParseModelYaml(yaml, "m.yaml");
    try {
      FitModel(stations, &spec, FitOptions());
      ADD_FAILURE() << "no error for " << yaml;
    } catch (const std::invalid_argument& e) {
      EXPECT_NE(std::string(e.what()).find(where), std::string::npos) << e.what();
      EXPECT_NE(std::string(e.what()).find("must be a unit vector"), std::string::npos) << e.what();
    }
  };
  expect_error("terms:\n  - type: sensor_offset\n    parameters:\n      rotation: {value: 0}\n",
               "m.yaml:4:17: $.terms[0].parameters.rotation: ");
  expect_error(
      "terms:\n  - type: plane\n    parameters:\n      normal_in_transmitter: {value: 0}\n"
      "      distance_m: {value: 0.8}\n",
      "m.yaml:4:30: $.terms[0].parameters.normal_in_transmitter: ");
  expect_error(
      "terms:\n  - type: sensor_offset\n    parameters:\n      rotation: {value: [0, 0, 0, 2]}\n",
      "|value| = 2");
}

// A group with every effect but the background: a sensor offset, receiver gains, a dipole at
// `location` (YAML list) of `polarisability` m^3, the floor plane and the transmitter's octupole.
std::string GroupYaml(const std::string& location, double polarisability) {
  return R"(terms:
  - type: sensor_offset
    receiver_from_body:
      rotation_xyzw: [0.1, -0.05, 0.02, 0.99369]
      translation: [0.02, 0.01, -0.03]
  - type: receiver_gain
    receiver_gain_matrix: [[1.02, 0.01, 0], [-0.005, 0.98, 0.015], [0, 0.008, 1.01]]
  - type: dipole
    location_in_transmitter: )" +
         location + "\n    polarisability_m3: " + std::to_string(polarisability) + R"(
  - type: plane
    point_in_transmitter: [0, 0, 0.8]
    normal_in_transmitter: [0.1, 0, 1]
    attenuation: 0.27
  - type: near_field
    octupole_m2: [-0.001, -0.0006, -0.0008]
)";
}

// d output / d blocks and d output / d input against central differences.
TEST(PhysicalGroupTerm, JacobiansMatchNumericDifferentiation) {
  ModelSpec spec = ParseModelYaml(GroupYaml("[0.6, 0.95, -0.5]", 0.02) + R"(  - type: background_field
    degree: 2
    coefficients: [1e-3, -2e-3, 5e-4, 1e-3, 0, 2e-3, -1e-3, 5e-4, 0, 1e-3, -5e-4, 2e-4, 0, 3e-4, -1e-3,
                   2e-3, 1e-3, 0, -5e-4, 1e-3, 0, 2e-4, -3e-4, 1e-3, 5e-4, 0, -2e-3, 1e-3, 0, 4e-4,
                   -1e-3, 0, 2e-3, 5e-4, -5e-4, 1e-3, 0, 3e-4, -2e-4, 1e-3, 0, -1e-3, 5e-4, 2e-4, 0]
)",
                                  "m.yaml");
  const ModelTerm& term = *spec.terms[0];
  const Rigid3d reported(Eigen::Quaterniond(Eigen::AngleAxisd(0.7, Eigen::Vector3d(1, 2, 3).normalized())),
                         Eigen::Vector3d(0.3, -0.2, -0.5));
  const AmbientPose input = ToAmbient(reported);
  const StationBinding binding = term.Bind(input);
  ASSERT_EQ(binding.blocks.size(), term.blocks().size());  // nothing fixed: all bound
  std::vector<std::vector<double>> values;
  for (const auto& b : term.blocks()) values.push_back(b.values);
  auto evaluate = [&](const AmbientPose& in, bool jacobians, TermEvaluation* out) {
    std::vector<const double*> ptrs;
    for (const auto& v : values) ptrs.push_back(v.data());
    return term.Evaluate(binding, ptrs.data(), in, jacobians, out);
  };
  TermEvaluation analytic;
  ASSERT_TRUE(evaluate(input, true, &analytic));
  // Central differences: h = 1e-6 gives truncation ~1e-12 and rounding ~1e-10 on O(1) outputs;
  // tolerance 1e-6 absolute on entries of O(1) (the inverse converges to ~1e-12).
  const double h = 1e-6, tolerance = 1e-6;
  for (size_t b = 0; b < values.size(); ++b) {
    for (size_t c = 0; c < values[b].size(); ++c) {
      TermEvaluation plus, minus;
      const double saved = values[b][c];
      values[b][c] = saved + h;
      ASSERT_TRUE(evaluate(input, false, &plus));
      values[b][c] = saved - h;
      ASSERT_TRUE(evaluate(input, false, &minus));
      values[b][c] = saved;
      const AmbientPose numeric = (plus.output - minus.output) / (2 * h);
      for (int r = 0; r < 7; ++r) {
        EXPECT_NEAR(analytic.d_output_d_blocks[b](r, static_cast<int>(c)), numeric[r], tolerance)
            << term.blocks()[b].term << "." << term.blocks()[b].name << "[" << c << "] row " << r;
      }
    }
  }
  for (int c = 0; c < 7; ++c) {
    AmbientPose in_plus = input, in_minus = input;
    in_plus[c] += h;
    in_minus[c] -= h;
    TermEvaluation plus, minus;
    ASSERT_TRUE(evaluate(in_plus, false, &plus));
    ASSERT_TRUE(evaluate(in_minus, false, &minus));
    const AmbientPose numeric = (plus.output - minus.output) / (2 * h);
    for (int r = 0; r < 7; ++r) {
      EXPECT_NEAR(analytic.d_output_d_input(r, c), numeric[r], tolerance) << "input " << c << " row " << r;
    }
  }
}

// A caller that does not read d_output_d_input (the chain's first term, on the constant report)
// may skip it: the output and every other derivative stay the same bits in all three forms (the
// report's inverse, toward a target from the report, toward a target by Newton from the pose
// behind it), and the skipped matrix is NaN, so a caller that read it would see it at once.
TEST(PhysicalGroupTerm, SkippingTheInputDerivativeChangesNothingElse) {
  ModelSpec spec = ParseModelYaml(GroupYaml("[0.6, 0.95, -0.5]", 0.02), "m.yaml");
  const auto& term = dynamic_cast<const PhysicalGroupTerm&>(*spec.terms[0]);
  std::vector<const double*> values;
  for (const auto& b : term.blocks()) values.push_back(b.values.data());
  const Rigid3d body(
      Eigen::Quaterniond(Eigen::AngleAxisd(0.7, Eigen::Vector3d(1, 2, 3).normalized())),
      Eigen::Vector3d(0.3, -0.2, -0.5));
  const Rigid3d reported(
      body.rotation * Eigen::Quaterniond(Eigen::AngleAxisd(0.03, Eigen::Vector3d::UnitX())),
      body.translation + Eigen::Vector3d(0.01, -0.02, 0.005));
  const AmbientPose input = ToAmbient(reported), target = ToAmbient(body);
  for (int form = 0; form < 3; ++form) {
    SCOPED_TRACE("form " + std::to_string(form));
    StationBinding binding = term.Bind(input);
    binding.pose_form = form == 2;
    TermEvaluation full, skipped;
    skipped.want_d_output_d_input = false;
    const auto evaluate = [&](TermEvaluation* out) {
      return form == 0 ? term.Evaluate(binding, values.data(), input, true, out)
                       : term.EvaluateToward(binding, values.data(), input, target, true, out);
    };
    ASSERT_TRUE(evaluate(&full));
    ASSERT_TRUE(evaluate(&skipped));
    EXPECT_TRUE(full.d_output_d_input.allFinite());
    EXPECT_TRUE(skipped.d_output_d_input.array().isNaN().all());
    EXPECT_EQ(skipped.output, full.output);
    EXPECT_EQ(skipped.d_output_d_target, full.d_output_d_target);
    ASSERT_EQ(skipped.d_output_d_blocks.size(), full.d_output_d_blocks.size());
    for (size_t b = 0; b < full.d_output_d_blocks.size(); ++b) {
      EXPECT_EQ(skipped.d_output_d_blocks[b], full.d_output_d_blocks[b]) << "block " << b;
    }
  }
}

// The runtime correction (the calibration file's, ToCorrection()) is the inverse the fit evaluates
// (Evaluate(): the group's output from the report, on which the later terms are bound and
// initialised): the same pose for every report, also where Newton needs many steps. A strong room
// (a 0.004 m^3 object 0.6 m from the transmitter, a plane at 0.6 m with attenuation 0.5) on a grid
// of reports from 0.1 m to 1.4 m, on the axes, at identity and half-turn orientations. Before the
// runtime used the fit's Newton step limit, 166 of these 5910 reports came out differently, by up
// to 0.46 m; 20 of them the fit's inverse resolved in 9-23 steps where the runtime stopped,
// unconverged, at its default 8.
TEST(PhysicalGroupTerm, RuntimeCorrectionIsTheFittedInverse) {
  ModelSpec spec = ParseModelYaml(R"(terms:
  - type: sensor_offset
    receiver_from_body: {rotation_xyzw: [0.1, -0.05, 0.02, 0.99369], translation: [0.02, 0.01, -0.03]}
  - type: receiver_gain
    receiver_gain_matrix: [[1.02, 0.01, 0], [-0.005, 0.98, 0.015], [0, 0.008, 1.01]]
  - type: dipole
    location_in_transmitter: [0.5, 0.1, 0.3]
    polarisability_m3: 0.004
  - type: plane
    point_in_transmitter: [0, 0, 0.6]
    normal_in_transmitter: [0, 0, 1]
    attenuation: 0.5
  - type: near_field
    octupole_m2: [-0.001, -0.0006, -0.0008]
)",
                                  "m.yaml");
  const ModelTerm& term = *spec.terms[0];
  const std::unique_ptr<Correction> runtime = term.ToCorrection();
  const StationBinding binding = term.Bind(AmbientPose::Zero());
  std::vector<const double*> values;
  for (int b : binding.blocks)
    values.push_back(term.blocks()[static_cast<size_t>(b)].values.data());
  const std::vector<Eigen::Quaterniond> rotations = {
      Eigen::Quaterniond::Identity(),
      Eigen::Quaterniond(Eigen::AngleAxisd(M_PI, Eigen::Vector3d::UnitX())),
      Eigen::Quaterniond(Eigen::AngleAxisd(M_PI, Eigen::Vector3d(1, 1, 0).normalized())),
      Eigen::Quaterniond(Eigen::AngleAxisd(M_PI / 2, Eigen::Vector3d::UnitZ())),
      Eigen::Quaterniond(Eigen::AngleAxisd(2.0, Eigen::Vector3d(1, -2, 3).normalized()))};
  int count = 0, differ = 0, ambiguous = 0;
  for (int i = -6; i <= 6; ++i) {
    for (int j = -6; j <= 6; ++j) {
      for (int k = -3; k <= 3; ++k) {
        const Eigen::Vector3d p(0.15 * i, 0.15 * j, 0.15 * k);
        if (p.norm() < 0.1) continue;
        for (const Eigen::Quaterniond& q : rotations) {
          const Rigid3d reported(q, p);
          TermEvaluation fitted;
          ASSERT_TRUE(term.Evaluate(binding, values.data(), ToAmbient(reported), false, &fitted));
          const CorrectedPose corrected = runtime->Apply(reported);
          const AmbientPose applied = ToAmbient(corrected.pose);
          ++count;
          if (corrected.status == CorrectionStatus::kAmbiguous) ++ambiguous;
          // The same Newton run on the same numbers, the same offset composition: bit for bit
          // (the fit's InvertReport skips only the classification Apply runs after it).
          if (std::memcmp(fitted.output.data(), applied.data(), sizeof(applied)) != 0) {
            ++differ;
            ADD_FAILURE() << "report at " << p.transpose() << ": fit " << fitted.output.transpose()
                          << ", runtime " << applied.transpose();
            if (differ > 5) return;
          }
        }
      }
    }
  }
  EXPECT_EQ(count, 5910);
  // Reports where the runtime's classification (noise gain, second-root search) found a fold
  // are among them.
  EXPECT_GT(ambiguous, 0);
}

// EvaluateToward() (the fit's form): the report's misfit carried to the pose behind the target
// by the free-space inverse's chord, with no inverse of the model, so its derivatives by the
// blocks, the target and the input match central differences at any report: here 0.15 m from a
// strong object, at reports some of which the model's inverse cannot reach (no root). (The form
// it replaced, Newton steps on the model's normal equations with implicit-function derivatives,
// disagreed with its own value there by O(1): the fit stalled on the paper capture next to the
// toolbox.)
TEST(PhysicalGroupTerm, TowardJacobiansMatchNumericDifferentiationWhereTheInverseHasNoRoot) {
  ModelSpec spec = ParseModelYaml(GroupYaml("[0.38, -0.11, -0.40]", 0.002), "m.yaml");
  const auto& term = dynamic_cast<const PhysicalGroupTerm&>(*spec.terms[0]);
  const StationBinding binding = term.Bind(AmbientPose::Zero());
  ASSERT_EQ(binding.blocks.size(), term.blocks().size());  // nothing fixed: all bound
  std::vector<std::vector<double>> values;
  for (const auto& b : term.blocks()) values.push_back(b.values);
  const auto pointers = [&] {
    std::vector<const double*> ptrs;
    for (const auto& v : values) ptrs.push_back(v.data());
    return ptrs;
  };
  const Rigid3d body(
      Eigen::Quaterniond(Eigen::AngleAxisd(0.7, Eigen::Vector3d(1, 2, 3).normalized())),
      Eigen::Vector3d(0.3, -0.2, -0.5));
  const PhysicalCorrection model = term.MakeCorrection(pointers().data());
  std::vector<Rigid3d> reports;
  for (const Eigen::Vector3d& misfit :
       {Eigen::Vector3d(0.02, 0, 0), Eigen::Vector3d(0, -0.03, 0.01),
        Eigen::Vector3d(0.04, 0.04, -0.04), Eigen::Vector3d(-0.05, 0.02, 0.03),
        Eigen::Vector3d(0.08, -0.02, 0.05)}) {
    reports.emplace_back(
        body.rotation * Eigen::Quaterniond(Eigen::AngleAxisd(0.05, misfit.normalized())),
        body.translation + misfit);
  }
  // A hemisphere flip (reported at -p): the form starts from the mirrored pose.
  reports.emplace_back(body.rotation, -(body.translation + Eigen::Vector3d(0.01, 0.0, 0.01)));
  int no_root = 0;
  for (size_t n = 0; n < reports.size(); ++n) {
    SCOPED_TRACE("report " + std::to_string(n));
    const Rigid3d& reported = reports[n];
    Rigid3d x;
    if (!model.InvertReport(reported, &x)) ++no_root;
    const AmbientPose input = ToAmbient(reported), target = ToAmbient(body);
    auto evaluate = [&](const AmbientPose& in, const AmbientPose& to, bool jacobians,
                        TermEvaluation* out) {
      return term.EvaluateToward(binding, pointers().data(), in, to, jacobians, out);
    };
    TermEvaluation analytic;
    ASSERT_TRUE(evaluate(input, target, true, &analytic));
    // Central differences, h = 1e-6: truncation ~1e-12 times the third derivative, rounding ~1e-10,
    // against entries up to ~10 here (a strength's); 1e-6 relative to max(1, entry) holds both.
    const double h = 1e-6;
    const auto expect_column = [&](const Eigen::Matrix<double, 7, 1>& analytic_column,
                                   const AmbientPose& plus, const AmbientPose& minus,
                                   const std::string& what) {
      const AmbientPose numeric = (plus - minus) / (2 * h);
      for (int r = 0; r < 7; ++r) {
        EXPECT_NEAR(analytic_column[r], numeric[r], 1e-6 * std::max(1.0, std::abs(numeric[r])))
            << what << " row " << r;
      }
    };
    for (size_t b = 0; b < values.size(); ++b) {
      for (size_t c = 0; c < values[b].size(); ++c) {
        TermEvaluation plus, minus;
        const double saved = values[b][c];
        values[b][c] = saved + h;
        ASSERT_TRUE(evaluate(input, target, false, &plus));
        values[b][c] = saved - h;
        ASSERT_TRUE(evaluate(input, target, false, &minus));
        values[b][c] = saved;
        expect_column(analytic.d_output_d_blocks[b].col(static_cast<Eigen::Index>(c)), plus.output,
                      minus.output, term.blocks()[b].term + "." + term.blocks()[b].name + "[" +
                                        std::to_string(c) + "]");
      }
    }
    for (int c = 0; c < 7; ++c) {
      AmbientPose plus_in = input, minus_in = input, plus_to = target, minus_to = target;
      plus_in[c] += h;
      minus_in[c] -= h;
      plus_to[c] += h;
      minus_to[c] -= h;
      TermEvaluation plus, minus;
      ASSERT_TRUE(evaluate(plus_in, target, false, &plus));
      ASSERT_TRUE(evaluate(minus_in, target, false, &minus));
      expect_column(analytic.d_output_d_input.col(c), plus.output, minus.output,
                    "input " + std::to_string(c));
      ASSERT_TRUE(evaluate(input, plus_to, false, &plus));
      ASSERT_TRUE(evaluate(input, minus_to, false, &minus));
      expect_column(analytic.d_output_d_target.col(c), plus.output, minus.output,
                    "target " + std::to_string(c));
    }
  }
  // The regime the form is for: at least one of the reports has no root of the model's inverse.
  EXPECT_GE(no_root, 1);
}

// Step-1 acceptance on noise-free data: sensor offset and receiver gains of the same form are
// recovered through FitModel from a model file (the field known: free space).
TEST(PhysicalTerms, NoiseFreeSensorOffsetAndGainRecovered) {
  PhysicalTruth truth = PaperLikeTruth();
  truth.field = FieldModel();  // free space: only the receiver-side effects
  // With a sensor offset, G's rotation part is the offset's rotation (a gauge the term fixes by
  // holding G symmetric): the truth's G is symmetric.
  truth.gain = 0.5 * (truth.gain + truth.gain.transpose()).eval();
  const auto stations = NoiseFreeStations(truth, 200);
  ModelSpec spec = ParseModelYaml(R"(noise: {position_mm: 0.1, orientation_deg: 0.01}
terms:
  - type: sensor_offset
  - type: receiver_gain
)",
                                  "m.yaml");
  const FitResult result = FitModel(stations, &spec);
  ASSERT_TRUE(result.converged) << result.solver_message;
  const auto& gain = Find(result, "receiver_gain", "gain_matrix");
  for (int k = 0; k < 9; ++k) {
    // Noise-free: the fit reaches the truth up to the inverse's and solver's tolerances (1e-12);
    // 1e-6 relative to the largest entry.
    EXPECT_NEAR(gain.values[static_cast<size_t>(k)], truth.gain(k / 3, k % 3), 1e-6) << k;
    EXPECT_TRUE(std::isfinite(gain.stddev[static_cast<size_t>(k)]));
  }
  const auto& rotation = Find(result, "sensor_offset", "rotation");
  const Eigen::Quaterniond q = QuaternionFromXyzwArray(rotation.values.data());
  EXPECT_LT(AngularDistance(q, truth.receiver_from_body.rotation), 1e-6);
  // Manifold block: one std per tangent coordinate (rotation vector, rad).
  ASSERT_EQ(rotation.stddev.size(), 3u);
  EXPECT_EQ(rotation.stddev_names[0], "rotation_vector.x");
  for (double s : rotation.stddev) EXPECT_TRUE(std::isfinite(s) && s > 0);
  const auto& translation = Find(result, "sensor_offset", "translation");
  for (int k = 0; k < 3; ++k) {
    EXPECT_NEAR(translation.values[static_cast<size_t>(k)], truth.receiver_from_body.translation(k),
                1e-6 * truth.receiver_from_body.translation.norm());
  }
}

// Acceptance (a): noise-free data generated by a physical model of the same form (all five
// effects); every parameter recovered to 1e-6 relative through FitModel from a model file, from
// starts 10 cm / a factor 2 / 5 degrees away.
TEST(PhysicalTerms, NoiseFreeAllFiveRecoveredTo1e6Relative) {
  PhysicalTruth truth = PaperLikeTruth();
  truth.gain = 0.5 * (truth.gain + truth.gain.transpose()).eval();  // the gauge, see above
  const auto stations = NoiseFreeStations(truth, 300);
  ModelSpec spec = ParseModelYaml(R"(noise: {position_mm: 0.1, orientation_deg: 0.01}
terms:
  - type: sensor_offset
  - type: receiver_gain
  - type: near_field
  - type: plane
    point_in_transmitter: [0, 0, 0.9]
    normal_in_transmitter: [0.08, 0, 1]
    attenuation: 0.15
  - type: dipole
    location_in_transmitter: [0.7, 0.85, -0.45]
    polarisability_m3: 0.001
)",
                                  "m.yaml");
  const FitResult result = FitModel(stations, &spec);
  ASSERT_TRUE(result.converged) << result.solver_message;
  EXPECT_FALSE(result.rank_deficient) << result.covariance_message;
  // 1e-6 relative to each block's magnitude: the inverse converges to 1e-12 and the solver to a
  // relative cost change of 1e-12, so noise-free parameters are exact to ~1e-9.
  auto expect_block = [&](const std::string& term, const std::string& block,
                          const Eigen::VectorXd& expected) {
    const auto& p = Find(result, term, block);
    ASSERT_EQ(p.values.size(), static_cast<size_t>(expected.size()));
    const double scale = expected.cwiseAbs().maxCoeff();
    for (int k = 0; k < expected.size(); ++k) {
      EXPECT_NEAR(p.values[static_cast<size_t>(k)], expected[k], 1e-6 * scale)
          << term << "." << block << "[" << k << "]";
    }
  };
  expect_block("receiver_gain", "gain_matrix",
               Eigen::Map<const Eigen::Matrix<double, 9, 1>>(
                   Eigen::Matrix<double, 3, 3, Eigen::RowMajor>(truth.gain).data()));
  expect_block("sensor_offset", "translation", truth.receiver_from_body.translation);
  expect_block("near_field", "octupole_m2", truth.field.transmitter_octupole_m2);
  expect_block("plane", "distance_m", Eigen::VectorXd::Constant(1, 0.8));
  expect_block("plane", "normal_in_transmitter", Eigen::Vector3d(0, 0, 1));
  expect_block("plane", "attenuation", Eigen::VectorXd::Constant(1, 0.27));
  expect_block("dipole", "location_in_transmitter", truth.field.objects[0].location_in_transmitter);
  expect_block("dipole", "polarisability_m3", Eigen::VectorXd::Constant(1, 0.002));
  const auto& rotation = Find(result, "sensor_offset", "rotation");
  EXPECT_LT(AngularDistance(QuaternionFromXyzwArray(rotation.values.data()),
                            truth.receiver_from_body.rotation),
            1e-6 * RotationAngle(truth.receiver_from_body.rotation));
  // Manifold blocks report tangent stds: 2 angles for the normal.
  const auto& normal = Find(result, "plane", "normal_in_transmitter");
  ASSERT_EQ(normal.stddev.size(), 2u);
  EXPECT_EQ(normal.stddev_unit, "rad");
  EXPECT_TRUE(std::isfinite(normal.stddev[0]));
  // --json: every block with its term's name; manifold blocks carry their tangent stds.
  const nlohmann::json json = result.ToJson();
  bool found = false;
  for (const auto& p : json["parameters"]) {
    if (p["term"] == "sensor_offset" && p["block"] == "rotation") {
      found = true;
      ASSERT_EQ(p["tangent"].size(), 3u);
      EXPECT_EQ(p["tangent"][0]["name"], "rotation_vector.x");
      EXPECT_TRUE(p["tangent"][0]["stddev"].is_number()) << p.dump();
      EXPECT_EQ(p["tangent_unit"], "rad");
      EXPECT_TRUE(p["values"][0]["stddev"].is_null());  // no std per quaternion component
    }
  }
  EXPECT_TRUE(found);
}

// Distant sources with receiver gains, noise-free, in free space otherwise: the group recovers both
// (no polynomial after it, so the background's position-only part is identified as well).
TEST(PhysicalTerms, NoiseFreeBackgroundFieldAndGainRecovered) {
  PhysicalTruth truth = PaperLikeTruth();
  truth.field = FieldModel();
  truth.receiver_from_body = Rigid3d();
  truth.field.background.degree = 1;
  std::uniform_real_distribution<double> c(-2e-3, 2e-3);
  for (int k = 0; k < 24; ++k) truth.field.background.coefficients.push_back(c(trackcal::testing::TestRng()));
  const auto stations = NoiseFreeStations(truth, 200);
  ModelSpec spec = ParseModelYaml(R"(noise: {position_mm: 0.1, orientation_deg: 0.01}
terms:
  - type: receiver_gain
    gain_scale: free
  - type: background_field
)",
                                  "m.yaml");
  const FitResult result = FitModel(stations, &spec);
  ASSERT_TRUE(result.converged) << result.solver_message;
  EXPECT_FALSE(result.rank_deficient) << result.covariance_message;
  const auto& gain = Find(result, "receiver_gain", "gain_matrix");
  const auto& background = Find(result, "background_field", "coefficients");
  ASSERT_EQ(background.values.size(), 24u);
  EXPECT_EQ(background.coordinate_names[8], "coil_y.0");
  for (int k = 0; k < 9; ++k) {
    // Noise-free: exact to the solver's tolerances (see above); 1e-6.
    EXPECT_NEAR(gain.values[static_cast<size_t>(k)], truth.gain(k / 3, k % 3), 1e-6) << k;
  }
  for (size_t k = 0; k < 24; ++k) {
    // 1e-6 relative to the largest coefficient (2e-3): 2e-9 field units.
    EXPECT_NEAR(background.values[k], truth.field.background.coefficients[k], 2e-9) << k;
  }
  // The calibration file carries it, and the fitted chain takes a report back to the truth.
  ASSERT_EQ(result.chain.size(), 1u);
  EXPECT_TRUE(result.chain.term(0).ToJson().contains("background"));
  CorrectionChain chain = result.chain;
  chain.ClearVolume();
  for (size_t i = 0; i < 5; ++i) {
    // The solvers' tolerances (1e-12) with the noise-free fit's: 1e-8 m, 1e-8 rad.
    EXPECT_TRUE(trackcal::testing::PosesNear(chain.Apply(stations[i].reported).pose,
                                             stations[i].reference, 1e-8, 1e-8));
  }
}

// The calibration file written from a fit holds the whole chain (physical, then polynomial) and
// core's reader applies it exactly as the fit's chain.
TEST(PhysicalTerms, CalibrationFileRoundTripWithPolynomial) {
  PhysicalTruth truth = PaperLikeTruth();
  truth.gain = 0.5 * (truth.gain + truth.gain.transpose()).eval();
  const auto stations = NoiseFreeStations(truth, 150);
  ModelSpec spec = ParseModelYaml(R"(terms:
  - type: receiver_gain
  - type: dipole
    location_in_transmitter: [0.6, 0.95, -0.5]
    polarisability_m3: 0.002
  - type: polynomial
    degree: 2
)",
                                  "m.yaml");
  const FitResult result = FitModel(stations, &spec);
  ASSERT_EQ(result.chain.size(), 2u);
  EXPECT_EQ(result.chain.term(0).TypeName(), "physical");
  EXPECT_EQ(result.chain.term(1).TypeName(), "polynomial");
  Calibration calibration;
  calibration.chain = result.chain;
  calibration.provenance.tool_version = "test";
  calibration.provenance.created_utc = CurrentUtcTimestamp();
  const auto path = trackcal::testing::MakeTempDir("physical_calib") / "calib.json";
  WriteCalibrationFile(path, calibration);
  const Calibration read = ReadCalibrationFile(path);
  ASSERT_EQ(read.chain.size(), 2u);
  const auto& physical = dynamic_cast<const PhysicalCorrection&>(read.chain.term(0));
  ASSERT_EQ(physical.field().objects.size(), 1u);
  EXPECT_EQ(physical.field().objects[0].name, "dipole");
  for (const auto& s : stations) {
    // Same poses as the fit's chain up to the file's number formatting (17 digits).
    EXPECT_TRUE(trackcal::testing::PosesNear(result.chain.Apply(s.reported).pose,
                                             read.Apply(s.reported).pose, 1e-9, 1e-9));
  }
}

// Acceptance (c): a dipole given without a start is found by the search (the room's floor given as
// a fixed plane), then refined by the joint fit to the truth.
TEST(PhysicalTerms, DipoleWithoutStartIsFoundBySearch) {
  PhysicalTruth truth;
  truth.field.planes.push_back({"floor", Eigen::Vector3d(0, 0, 0.8), Eigen::Vector3d(0, 0, 1), 0.27});
  truth.field.objects.push_back({"toolbox", Eigen::Vector3d(0.6, 0.95, -0.5), 0.002});
  const auto stations = NoiseFreeStations(truth, 480);
  ModelSpec spec = ParseModelYaml(R"(noise: {position_mm: 0.1, orientation_deg: 0.01}
terms:
  - type: plane
    name: floor
    point_in_transmitter: [0, 0, 0.8]
    normal_in_transmitter: [0, 0, 1]
    attenuation: 0.27
    parameters:
      distance_m: {fixed: true}
      normal_in_transmitter: {fixed: true}
      attenuation: {fixed: true}
  - type: dipole
)",
                                  "m.yaml");
  // The search alone (before the joint fit) lands near the object: within one grid spacing.
  {
    ModelSpec search_only = ParseModelYaml(R"(terms:
  - type: plane
    point_in_transmitter: [0, 0, 0.8]
    normal_in_transmitter: [0, 0, 1]
    attenuation: 0.27
    parameters: {distance_m: {fixed: true}, normal_in_transmitter: {fixed: true}, attenuation: {fixed: true}}
  - type: dipole
)",
                                           "m.yaml");
    ModelTerm& term = *search_only.terms[0];
    term.Prepare(stations);
    ApplyBlockSettings(search_only.block_settings[0], &term);
    term.InitializeLinear(stations, Eigen::Vector2d(1e-4, 1.745e-4));
    const auto& location = term.blocks()[3].values;
    ASSERT_EQ(term.blocks()[3].name, "location_in_transmitter");
    EXPECT_LT((Eigen::Vector3d(location[0], location[1], location[2]) -
               truth.field.objects[0].location_in_transmitter)
                  .norm(),
              0.15);
  }
  const FitResult result = FitModel(stations, &spec);
  ASSERT_TRUE(result.converged) << result.solver_message;
  const auto& location = Find(result, "dipole", "location_in_transmitter");
  for (int k = 0; k < 3; ++k) {
    // Noise-free: exact to the solver's tolerance (see the recovery test above).
    EXPECT_NEAR(location.values[static_cast<size_t>(k)],
                truth.field.objects[0].location_in_transmitter(k), 1e-6);
  }
  EXPECT_NEAR(Find(result, "dipole", "polarisability_m3").values[0], 0.002, 1e-9);
  // Stations near the toolbox have a second true pose in its fold zone (core/physical_correction.h):
  // the fit names them, and only them (within 3 fold radii, 0.75 m, of the object).
  EXPECT_FALSE(result.unresolved.empty());
  for (const UnresolvedStation& u : result.unresolved) {
    const FitStation& s = stations[static_cast<size_t>(u.station)];
    ASSERT_EQ(s.station, u.station);
    EXPECT_LT((s.reference.translation - truth.field.objects[0].location_in_transmitter).norm(), 0.75)
        << u.station << " " << CorrectionStatusName(u.status);
  }
  EXPECT_EQ(result.ToJson()["unresolved"].size(), result.unresolved.size());
  // The fixed floor is reported with its values and no std.
  const auto& floor = Find(result, "floor", "attenuation");
  EXPECT_TRUE(floor.fixed);
  EXPECT_TRUE(std::isnan(floor.stddev[0]));
}

// A plane given without point and normal is found by the search over normals and distances.
TEST(PhysicalTerms, PlaneWithoutStartIsFoundBySearch) {
  PhysicalTruth truth;
  truth.field.planes.push_back(
      {"wall", Eigen::Vector3d(0, -1.6, 0), Eigen::Vector3d(0.1, 1, 0).normalized(), 0.3});
  const auto stations = NoiseFreeStations(truth, 300);
  ModelSpec spec = ParseModelYaml(R"(noise: {position_mm: 0.1, orientation_deg: 0.01}
terms:
  - type: plane
)",
                                  "m.yaml");
  const FitResult result = FitModel(stations, &spec);
  ASSERT_TRUE(result.converged) << result.solver_message;
  const auto& n = Find(result, "plane", "normal_in_transmitter").values;
  const double d = Find(result, "plane", "distance_m").values[0];
  const Eigen::Vector3d normal(n[0], n[1], n[2]);
  const Eigen::Vector3d n_true = truth.field.planes[0].normal_in_transmitter;
  // (d, n) and (-d, -n) are the same plane.
  const double sign = normal.dot(n_true) > 0 ? 1.0 : -1.0;
  EXPECT_LT((sign * normal - n_true).norm(), 1e-6);
  EXPECT_NEAR(sign * d, truth.field.planes[0].point_in_transmitter.dot(n_true), 1e-6);
  EXPECT_NEAR(Find(result, "plane", "attenuation").values[0], 0.3, 1e-6);
}

// A dipole far outside the data: its location and strength trade, and the fit says so.
TEST(PhysicalTerms, FarDipoleIsFlaggedAsPoorlyIdentified) {
  PhysicalTruth truth;
  truth.field.objects.push_back({"far", Eigen::Vector3d(6.0, 4.0, -0.5), 0.2});
  auto stations = NoiseFreeStations(truth, 200);
  // 0.1 mm / 0.01 deg noise, so the fit has an uncertainty to speak of.
  std::normal_distribution<double> noise(0.0, 1e-4);
  for (auto& s : stations) {
    for (int k = 0; k < 3; ++k) s.reference.translation(k) += noise(trackcal::testing::TestRng());
  }
  ModelSpec spec = ParseModelYaml(R"(noise: {position_mm: 0.1, orientation_deg: 0.01}
terms:
  - type: dipole
    location_in_transmitter: [6.0, 4.0, -0.5]
    polarisability_m3: 0.2
)",
                                  "m.yaml");
  const FitResult result = FitModel(stations, &spec);
  bool location_flagged = false;
  for (const auto& f : result.identifiability_flags) {
    location_flagged = location_flagged || f.coordinate.find("dipole.location_in_transmitter") == 0;
  }
  EXPECT_TRUE(location_flagged) << result.ToJson().dump();
}

}  // namespace
}  // namespace trackcal::fit
