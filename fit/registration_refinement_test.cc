// Registration refined with a fitted correction, on the paper preset of the physics simulator,
// whose workbench frame (a conducting dipole 0.35 m from the transmitter) biases the registration
// stations' tracker readings by ~2 mm and ~0.5 deg.

#include "fit/registration_refinement.h"

#include <gtest/gtest.h>

#include <cmath>
#include <iostream>
#include <sstream>

#include "fit/registration_io.h"
#include "fit/rotation.h"
#include "sim/random.h"
#include "sim/simulator.h"
#include "tests/test_utils.h"

namespace trackcal::fit {
namespace {

// A capture as a session that measures markers at every station records it: the simulator's
// registration stations (markers.csv + tracker.csv), and its calibration stations with the
// tracker's averaged reading (poses.csv rep_*) and the markers the optical system sees on the true
// body pose (the simulator writes markers for registration stations only; these follow its rules:
// markers facing the camera, at least the best three, averaged noise).
struct Capture {
  sim::Scene scene;
  std::vector<RegistrationStation> registration;
  std::vector<RegistrationStation> calibration;
  FieldModel field;
};

Capture MakeCapture(const sim::Scene& scene) {
  const sim::Simulator simulator(scene);
  const sim::SimulatedCapture capture = simulator.Generate();
  Capture c;
  c.scene = scene;
  c.field = simulator.tracker().field();
  c.registration = PairRegistrationRecords(capture.markers, capture.tracker, scene.tracker.sensor);
  sim::Rng noise(scene.seed, "refinement_test_markers");
  const double sigma = scene.reference.marker_noise_m /
                       std::sqrt(static_cast<double>(scene.reference.samples_per_station));
  const Rigid3d& optical_from_transmitter = scene.reference.optical_from_transmitter;
  const auto& markers = scene.reference.markers_in_body;
  for (size_t i = 0; i < capture.stations.size(); ++i) {
    const sim::StationTruth& truth = capture.stations[i];
    if (truth.set != "calib") continue;
    RegistrationStation s;
    s.station = truth.station;
    s.tracker_transmitter_from_receiver = capture.poses.records[i].reported;
    const Rigid3d optical_from_body = optical_from_transmitter * truth.transmitter_from_body;
    std::vector<std::pair<double, int>> facing;
    for (size_t m = 0; m < markers.size(); ++m) {
      const Eigen::Vector3d x = optical_from_body * markers[m];
      const Eigen::Vector3d outward = optical_from_body.rotation * markers[m].normalized();
      facing.push_back({outward.dot((-x).normalized()), static_cast<int>(m)});
    }
    std::sort(facing.rbegin(), facing.rend());
    for (size_t r = 0; r < facing.size(); ++r) {
      const Eigen::Vector3d n = sigma * noise.Normal3();
      if (r >= 3 && facing[r].first <= scene.reference.visibility_cos_min) continue;
      const int m = facing[r].second;
      s.markers.push_back({m + 1, optical_from_body * markers[static_cast<size_t>(m)] + n});
    }
    c.calibration.push_back(s);
  }
  return c;
}

RegistrationOptions NoiseOf(const sim::Scene& scene) {
  RegistrationOptions o;
  o.optical_noise_m =
      scene.reference.marker_noise_m / std::sqrt(double(scene.reference.samples_per_station));
  // The tracker's noise at 0.2-0.45 m from the transmitter with 120 averaged samples (truth.json
  // noise floor of the reg set): what the readings would scatter by without distortion.
  o.tracker_position_noise_m = 5e-5;
  o.tracker_orientation_noise_rad = 0.01 * kRadPerDeg;
  return o;
}

double Mahalanobis2(const RegistrationResult& r, const Rigid3d& truth) {
  Eigen::Matrix<double, 6, 1> e;
  e << RotationVectorBetween<double>(r.registration.optical_from_transmitter.rotation,
                                     truth.rotation),
      r.registration.optical_from_transmitter.translation - truth.translation;
  return e.dot(r.optical_from_transmitter_covariance.ldlt().solve(e));
}

// A physical model file of the room: the far sources (floor, door, monitors) at the values a
// previous calibration found (here: the truth), fixed; the workbench frame (a dipole) and the
// floor's plane free, started 10 cm and 40 % (frame) and 5 cm (floor) away from the truth.
std::string Vec3(const Eigen::Vector3d& v) {
  std::ostringstream out;
  out.precision(17);
  out << "[" << v.x() << ", " << v.y() << ", " << v.z() << "]";
  return out.str();
}

std::string PhysicalModelYaml(const FieldModel& truth) {
  std::ostringstream y;
  y.precision(17);
  y << "noise: {position_mm: 0.1, orientation_deg: 0.02}\nterms:\n";
  for (size_t i = 0; i < truth.planes.size(); ++i) {
    const ConductingPlane& p = truth.planes[i];
    const bool free = i == 0;
    y << "  - type: plane\n    name: " << (p.name.empty() ? "plane" + std::to_string(i) : p.name)
      << "\n    point_in_transmitter: "
      << Vec3(p.point_in_transmitter + (free ? Eigen::Vector3d(0, 0, 0.05) : Eigen::Vector3d::Zero()))
      << "\n    normal_in_transmitter: " << Vec3(p.normal_in_transmitter)
      << "\n    attenuation: " << p.attenuation << "\n";
    if (!free) {
      y << "    parameters:\n      distance_m: {fixed: true}\n      normal_in_transmitter: {fixed: "
           "true}\n      attenuation: {fixed: true}\n";
    }
  }
  for (size_t i = 0; i < truth.objects.size(); ++i) {
    const InducedDipole& o = truth.objects[i];
    const bool free = o.name == "workbench_frame";
    y << "  - type: dipole\n    name: " << o.name << "\n    location_in_transmitter: "
      << Vec3(o.location_in_transmitter +
              (free ? Eigen::Vector3d(0.08, -0.05, 0.05) : Eigen::Vector3d::Zero()))
      << "\n    polarisability_m3: " << o.polarisability_m3 * (free ? 0.6 : 1.0) << "\n";
    if (!free) {
      y << "    parameters:\n      location_in_transmitter: {fixed: true}\n      "
           "polarisability_m3: {fixed: true}\n";
    }
  }
  return y.str();
}

CorrectionFitter PhysicalFitter(const FieldModel& truth) {
  const std::string yaml = PhysicalModelYaml(truth);
  return MakeEngineFitter([yaml] { return ParseModelYaml(yaml, "room.yaml"); });
}

// 99.7 % quantile of chi-square with 6 degrees of freedom.
constexpr double kChiSquare6Dof997 = 20.06;

TEST(RefineRegistration, Nominal_PaperScenePhysicalModelRemovesTheBias) {
  for (uint64_t seed : {20010313ull, 1ull, 2ull}) {
    sim::Scene scene = sim::LoadScene("paper");
    scene.seed = seed;
    const Capture c = MakeCapture(scene);
    RegistrationRefinementOptions options;
    options.registration = NoiseOf(scene);
    const RegistrationRefinementResult r =
        RefineRegistration(c.registration, c.calibration, PhysicalFitter(c.field), options);
    const Rigid3d& truth = scene.reference.optical_from_transmitter;
    const double before = Mahalanobis2(r.initial, truth);
    const double after = Mahalanobis2(r.refined, truth);
    std::cout << "seed " << seed << ": Mahalanobis^2 " << before << " -> " << after << " in "
              << r.rounds.size() << " rounds; trend p " << r.initial.residual_structure.p_value
              << " -> " << r.refined.residual_structure.p_value << "\n";
    ASSERT_TRUE(r.converged) << r.ToString();
    ASSERT_TRUE(r.refined.converged);
    // The paper's registration is biased far beyond its covariance (measured 1e4-5e4) ...
    EXPECT_GT(before, kChiSquare6Dof997);
    // ... and both the chi-square (with the tracker's real noise) and the noise-free trend test
    // say so (measured z 440-490, p 1e-12 - 1e-9).
    EXPECT_GT(r.initial.ChiSquareZ(), 5.0);
    EXPECT_TRUE(r.initial.residual_structure.Flagged());
    // Refined: within its covariance (measured 0.5-1.3: the inflated tracker noise is
    // conservative).
    EXPECT_LT(after, kChiSquare6Dof997) << r.ToString();
    EXPECT_FALSE(r.refined.residual_structure.Flagged()) << r.ToString();
    // Converged in a few rounds (measured 5); the last step is below the tolerance.
    EXPECT_LE(r.rounds.size(), 10u);
    // Every calibration station has its reference (6 markers, 3-6 visible).
    EXPECT_EQ(r.rounds.back().num_calibration_stations, static_cast<int>(c.calibration.size()));
  }
}

TEST(RefineRegistration, PolynomialDivergesAndTheInitialRegistrationIsKept) {
  // A degree-4 polynomial can represent a rigid change of frame, so it cannot tell the distortion
  // from a rotated frame; fitted on the calibration grid it also extrapolates to the registration
  // stations nearer the transmitter (measured: 8 mm and 1.6 deg there in round 1, 1.5 deg moved,
  // more in round 2). The loop notices that it does not contract and keeps the initial result.
  sim::Scene scene = sim::LoadScene("paper");
  const Capture c = MakeCapture(scene);
  RegistrationRefinementOptions options;
  options.registration = NoiseOf(scene);
  const CorrectionFitter fitter = MakeEngineFitter(
      [] { return ParseModelYaml("terms:\n  - type: polynomial\n    degree: 4\n", "model.yaml"); });
  const RegistrationRefinementResult r =
      RefineRegistration(c.registration, c.calibration, fitter, options);
  EXPECT_TRUE(r.diverged) << r.ToString();
  EXPECT_FALSE(r.converged);
  EXPECT_EQ(r.rounds.size(), 2u);
  EXPECT_EQ(AngularDistance(r.refined.registration.optical_from_transmitter.rotation,
                            r.initial.registration.optical_from_transmitter.rotation),
            0.0);
}

TEST(RefineRegistration, TooFewCalibrationStationsThrows) {
  sim::Scene scene = sim::LoadScene("paper");
  const Capture c = MakeCapture(scene);
  const std::vector<RegistrationStation> few(c.calibration.begin(), c.calibration.begin() + 5);
  RegistrationRefinementOptions options;
  options.registration = NoiseOf(scene);
  EXPECT_THROW(RefineRegistration(c.registration, few, PhysicalFitter(c.field), options),
               std::invalid_argument);
  options.max_iterations = 0;
  EXPECT_THROW(RefineRegistration(c.registration, c.calibration, PhysicalFitter(c.field), options),
               std::invalid_argument);
}

}  // namespace
}  // namespace trackcal::fit
