#include "fit/registration.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <iostream>
#include <map>
#include <random>

#include "fit/rotation.h"
#include "fit/synthetic_registration.h"
#include "tests/test_utils.h"

namespace trackcal::fit {
namespace {

using testing::TestRng;

// Error of an estimated optical_from_transmitter as the 6-vector of the reported covariance:
// [rotation vector of estimate * conj(truth) (rad), translation difference (m)].
Eigen::Matrix<double, 6, 1> TransformError(const Rigid3d& estimate, const Rigid3d& truth) {
  Eigen::Matrix<double, 6, 1> e;
  e << RotationVectorBetween<double>(estimate.rotation, truth.rotation),
      estimate.translation - truth.translation;
  return e;
}

SyntheticRegistrationOptions NoisyOptions() {
  SyntheticRegistrationOptions o;
  o.optical_noise_m = 1.5e-4;         // Optotrak-like, paper section 3.1
  o.tracker_position_noise_m = 8e-4;  // Fastrak static accuracy, ~0.03 in
  o.tracker_orientation_noise_rad = 0.15 * kRadPerDeg;
  return o;
}

RegistrationOptions MatchingOptions(const SyntheticRegistrationOptions& s) {
  RegistrationOptions o;
  o.optical_noise_m = s.optical_noise_m;
  o.tracker_position_noise_m = s.tracker_position_noise_m;
  o.tracker_orientation_noise_rad = s.tracker_orientation_noise_rad;
  return o;
}

TEST(RegisterOpticalToTransmitter, Nominal) {
  // Noise-free data; the noise options only weight the residuals.
  for (int trial = 0; trial < 5; ++trial) {
    const SyntheticRegistration data = MakeSyntheticRegistration({}, &TestRng());
    const RegistrationResult r = RegisterOpticalToTransmitter(data.stations);
    ASSERT_TRUE(r.converged) << r.ToString();
    EXPECT_TRUE(r.identifiable) << r.ToString();
    EXPECT_TRUE(r.skipped_stations.empty());
    // Exact data: limited by the solver's tolerances and rounding, 1e-8 m / rad is ample.
    EXPECT_TRUE(testing::PosesNear(data.optical_from_transmitter,
                                   r.registration.optical_from_transmitter, 1e-8, 1e-8))
        << r.ToString();
    ASSERT_EQ(r.markers.size(), data.marker_in_receiver.size());
    for (const RegisteredMarker& m : r.markers) {
      EXPECT_LT((m.marker_in_receiver - data.marker_in_receiver.at(m.marker)).norm(), 1e-8);
    }
    for (std::size_t i = 0; i < r.stations.size(); ++i) {
      EXPECT_TRUE(testing::PosesNear(data.true_transmitter_from_receiver[i],
                                     r.stations[i].transmitter_from_receiver, 1e-8, 1e-8));
    }
    EXPECT_LT(r.chi_square, 1e-10);
    EXPECT_EQ(r.num_parameters, 6 + 3 * 6);
    EXPECT_DOUBLE_EQ(r.nu, 3.0 * r.num_marker_observations - 24.0);
    EXPECT_NE(r.initialisation.find("marker differences"), std::string::npos);
  }
}

TEST(RegisterOpticalToTransmitter, NoisyChiSquareAndCovarianceAreConsistent) {
  // Over many independent captures: chi-square is near nu, and the transform error's Mahalanobis
  // distance under the reported covariance behaves like chi-square with 6 degrees of freedom.
  const int kTrials = 30;
  double sum_d2 = 0.0, sum_z = 0.0, sum_station_z2 = 0.0;
  int num_station_z = 0;
  for (int trial = 0; trial < kTrials; ++trial) {
    const SyntheticRegistrationOptions s = NoisyOptions();
    const SyntheticRegistration data = MakeSyntheticRegistration(s, &TestRng());
    const RegistrationResult r = RegisterOpticalToTransmitter(data.stations, MatchingOptions(s));
    ASSERT_TRUE(r.converged) << r.ToString();
    ASSERT_TRUE(r.identifiable) << r.ToString();
    EXPECT_TRUE(r.rejected_stations.empty()) << r.ToString();  // sound markers stay in
    // |z| < 5: a 5-sigma band of the chi-square distribution (nu ~ 250, nearly Gaussian).
    EXPECT_LT(std::abs(r.ChiSquareZ()), 5.0) << r.ToString();
    const Eigen::Matrix<double, 6, 1> e =
        TransformError(r.registration.optical_from_transmitter, data.optical_from_transmitter);
    const double d2 = e.dot(r.optical_from_transmitter_covariance.ldlt().solve(e));
    // 99.99 % quantile of chi-square(6) is 27.86: a single trial beyond it means the covariance
    // is too optimistic.
    EXPECT_LT(d2, 27.86) << "trial " << trial << "\n" << r.ToString();
    sum_d2 += d2;
    sum_z += r.ChiSquareZ();
    for (std::size_t i = 0; i < r.stations.size(); ++i) {
      const Rigid3d& truth = data.true_transmitter_from_receiver[i];
      const Rigid3d& estimate = r.stations[i].transmitter_from_receiver;
      Eigen::Matrix<double, 6, 1> es;
      es << RotationVectorBetween<double>(estimate.rotation, truth.rotation),
          estimate.translation - truth.translation;
      sum_station_z2 += es.cwiseQuotient(r.stations[i].stddev).squaredNorm();
      num_station_z += 6;
    }
  }
  std::cout << "mean Mahalanobis^2 of the transform error " << sum_d2 / kTrials
            << " (expected 6), mean chi-square z " << sum_z / kTrials
            << " (expected 0), station pose mean squared z " << sum_station_z2 / num_station_z
            << " (expected 1)\n";
  // Mean of 30 chi-square(6) draws: 6 +- sqrt(12 / 30) = 0.63; 4 sigma band.
  EXPECT_NEAR(sum_d2 / kTrials, 6.0, 4 * 0.63);
  // Mean of 30 standard z values: 0 +- 0.18; 4 sigma band.
  EXPECT_NEAR(sum_z / kTrials, 0.0, 4 * 0.18);
  // Station pose errors in units of their reported std: mean square 1. The 3600 values are
  // correlated within a station, so the band is wider than 4 sqrt(2 / 3600) = 0.09: 0.2.
  EXPECT_NEAR(sum_station_z2 / num_station_z, 1.0, 0.2);
}

TEST(RegisterOpticalToTransmitter, TiltedPlatformConvergesFromClosedForm) {
  // A platform only tilted up to 30 degrees around one orientation: less diversity for the
  // marker-difference rotation, still a unique solution.
  for (int trial = 0; trial < 5; ++trial) {
    SyntheticRegistrationOptions s = NoisyOptions();
    s.max_rotation_from_nominal_rad = 30.0 * kRadPerDeg;
    const SyntheticRegistration data = MakeSyntheticRegistration(s, &TestRng());
    const RegistrationResult r = RegisterOpticalToTransmitter(data.stations, MatchingOptions(s));
    ASSERT_TRUE(r.converged) << r.ToString();
    EXPECT_LT(std::abs(r.ChiSquareZ()), 5.0) << r.ToString();  // 5 sigma, as above
    const Eigen::Matrix<double, 6, 1> e =
        TransformError(r.registration.optical_from_transmitter, data.optical_from_transmitter);
    // 99.99 % quantile of chi-square(6), as above.
    EXPECT_LT(e.dot(r.optical_from_transmitter_covariance.ldlt().solve(e)), 27.86) << r.ToString();
  }
}

TEST(RegisterOpticalToTransmitter, StationsAtNearlyOnePositionStillRegister) {
  // Receiver rotated in place (positions within +-2 cm): the centroid start is poor (centroid
  // offsets are as large as the station spread), so the marker-difference rotation must be the
  // start chosen, and the fit must still be statistically sound.
  for (int trial = 0; trial < 5; ++trial) {
    SyntheticRegistrationOptions s = NoisyOptions();
    s.station_half_size_m = 0.02;
    const SyntheticRegistration data = MakeSyntheticRegistration(s, &TestRng());
    const RegistrationResult r = RegisterOpticalToTransmitter(data.stations, MatchingOptions(s));
    ASSERT_TRUE(r.converged) << r.ToString();
    EXPECT_NE(r.initialisation.find("marker differences"), std::string::npos) << r.initialisation;
    EXPECT_LT(std::abs(r.ChiSquareZ()), 5.0) << r.ToString();  // 5 sigma, as above
    const Eigen::Matrix<double, 6, 1> e =
        TransformError(r.registration.optical_from_transmitter, data.optical_from_transmitter);
    EXPECT_LT(e.dot(r.optical_from_transmitter_covariance.ldlt().solve(e)), 27.86) << r.ToString();
  }
}

TEST(RegisterOpticalToTransmitter, DisplacedMarkerStandsOutInItsStation) {
  SyntheticRegistrationOptions s = NoisyOptions();
  SyntheticRegistration data = MakeSyntheticRegistration(s, &TestRng());
  data.stations[6].markers[0].marker_in_optical += Eigen::Vector3d(0.0, 0.003, 0.0);  // 3 mm
  RegistrationOptions o = MatchingOptions(s);
  o.reject_bad_stations = false;  // the diagnosis when the station stays in
  const RegistrationResult r = RegisterOpticalToTransmitter(data.stations, o);
  ASSERT_TRUE(r.converged);
  // 3 mm is 20 optical sigmas: the whole fit fails the chi-square test...
  EXPECT_GT(r.ChiSquareZ(), 5.0) << r.ToString();
  // ...and the displaced station carries the largest share of chi-square.
  const auto worst = std::max_element(r.stations.begin(), r.stations.end(),
                                      [](const RegisteredStation& a, const RegisteredStation& b) {
                                        return a.chi_square < b.chi_square;
                                      });
  EXPECT_EQ(worst->station, data.stations[6].station);
}

TEST(RegisterOpticalToTransmitter, MislabelledMarkerIsNotBlamedOnOrientations) {
  // Two labels swapped at one station of 20 with random orientations: the marker differences no
  // longer share one rotation, so the centroid start is used. The initialisation must say why
  // (it used to claim that the stations lack orientation diversity), and the swapped station must
  // carry the largest chi-square.
  SyntheticRegistrationOptions s = NoisyOptions();
  SyntheticRegistration data = MakeSyntheticRegistration(s, &TestRng());
  std::swap(data.stations[3].markers[0].marker, data.stations[3].markers[1].marker);
  RegistrationOptions o = MatchingOptions(s);
  o.reject_bad_stations = false;  // the diagnosis when the station stays in
  const RegistrationResult r = RegisterOpticalToTransmitter(data.stations, o);
  EXPECT_EQ(r.initialisation.find("orientation diversity"), std::string::npos) << r.initialisation;
  EXPECT_NE(r.initialisation.find("mislabelled"), std::string::npos) << r.initialisation;
  const auto worst = std::max_element(r.stations.begin(), r.stations.end(),
                                      [](const RegisteredStation& a, const RegisteredStation& b) {
                                        return a.chi_square < b.chi_square;
                                      });
  EXPECT_EQ(worst->station, data.stations[3].station);
}

// Swaps the labels of two markers at a station (the commonest optical capture error).
void SwapTwoLabels(RegistrationStation* station) {
  std::swap(station->markers[0].marker, station->markers[1].marker);
}

TEST(RegisterOpticalToTransmitter, StationWithSwappedLabelsIsLeftOut) {
  // One station of 20 with two labels swapped, 4-6 markers in view. Kept in, it pulls the
  // transform beyond its 99.99 % bound in about half of such captures; left out, every transform
  // is within it, and the station is named.
  const int kTrials = 12;
  int beyond_bound_when_kept = 0;
  for (int trial = 0; trial < kTrials; ++trial) {
    SyntheticRegistrationOptions s = NoisyOptions();
    s.min_visible = 4;
    SyntheticRegistration data = MakeSyntheticRegistration(s, &TestRng());
    const int bad = trial % static_cast<int>(data.stations.size());
    SwapTwoLabels(&data.stations[bad]);
    const RegistrationResult r = RegisterOpticalToTransmitter(data.stations, MatchingOptions(s));
    ASSERT_EQ(r.rejected_stations.size(), 1u) << "trial " << trial << "\n" << r.ToString();
    EXPECT_EQ(r.rejected_stations[0].station, data.stations[bad].station);
    EXPECT_GT(r.rejected_stations[0].marker_body_rms_m, 1e-3);
    EXPECT_EQ(r.stations.size(), data.stations.size() - 1);
    EXPECT_NE(r.ToString().find("left out station " + std::to_string(data.stations[bad].station)),
              std::string::npos);
    EXPECT_EQ(r.ToJson()["rejected_stations"][0]["station"], data.stations[bad].station);
    const Eigen::Matrix<double, 6, 1> e =
        TransformError(r.registration.optical_from_transmitter, data.optical_from_transmitter);
    // 99.99 % quantile of chi-square(6), as above.
    EXPECT_LT(e.dot(r.optical_from_transmitter_covariance.ldlt().solve(e)), 27.86)
        << "trial " << trial << "\n"
        << r.ToString();

    RegistrationOptions keep = MatchingOptions(s);
    keep.reject_bad_stations = false;
    const RegistrationResult kept = RegisterOpticalToTransmitter(data.stations, keep);
    const Eigen::Matrix<double, 6, 1> e_kept =
        TransformError(kept.registration.optical_from_transmitter, data.optical_from_transmitter);
    if (e_kept.dot(kept.optical_from_transmitter_covariance.ldlt().solve(e_kept)) > 27.86) {
      ++beyond_bound_when_kept;
    }
  }
  // The motivation, so that this test cannot pass on captures where a swap does no harm.
  EXPECT_GE(beyond_bound_when_kept, 3);
}

TEST(RegisterOpticalToTransmitter, StationWithTrackerReadingFarOffIsLeftOut) {
  // One station of 20 whose tracker reading is 0.5 m off (metal near the receiver) or whose
  // position is negated (a hemisphere flip). Kept in, it moved the transform far beyond its
  // 99.99 % bound with no message (paper scene: 2.6 deg and 34 mm); now it is left out and named.
  for (int trial = 0; trial < 4; ++trial) {
    SyntheticRegistration data = MakeSyntheticRegistration(NoisyOptions(), &TestRng());
    const int bad = 3 + 5 * trial;
    Rigid3d& reading = data.stations[bad].tracker_transmitter_from_receiver;
    if (trial % 2 == 0) {
      reading.translation.x() += 0.5;
    } else {
      reading.translation = -reading.translation;
    }
    const RegistrationOptions o = MatchingOptions(NoisyOptions());
    const RegistrationResult r = RegisterOpticalToTransmitter(data.stations, o);
    ASSERT_EQ(r.rejected_stations.size(), 1u) << "trial " << trial << "\n" << r.ToString();
    EXPECT_EQ(r.rejected_stations[0].station, data.stations[bad].station);
    EXPECT_EQ(r.rejected_stations[0].reason, "tracker_reading");
    EXPECT_GT(r.rejected_stations[0].tracker_position_residual_m, 0.1);
    EXPECT_NE(r.ToString().find("its tracker reading is"), std::string::npos) << r.ToString();
    EXPECT_EQ(r.ToJson()["rejected_stations"][0]["reason"], "tracker_reading");
    const Eigen::Matrix<double, 6, 1> e =
        TransformError(r.registration.optical_from_transmitter, data.optical_from_transmitter);
    EXPECT_LT(e.dot(r.optical_from_transmitter_covariance.ldlt().solve(e)), 27.86)  // 99.99 %
        << "trial " << trial << "\n"
        << r.ToString();

    RegistrationOptions keep = o;  // the motivation: kept in, the transform is far off
    keep.reject_bad_stations = false;
    const RegistrationResult kept = RegisterOpticalToTransmitter(data.stations, keep);
    const Eigen::Matrix<double, 6, 1> e_kept =
        TransformError(kept.registration.optical_from_transmitter, data.optical_from_transmitter);
    EXPECT_GT(e_kept.dot(kept.optical_from_transmitter_covariance.ldlt().solve(e_kept)), 1000.0)
        << "trial " << trial;
  }
}

TEST(RegisterOpticalToTransmitter, DistortedTrackerReadingsLeaveNoStationOut) {
  // A distorted field moves the tracker's readings by centimetres and degrees, and the prior then
  // pulls the station poses off the optical data by up to millimetres: the whole marker body
  // moves, and its shape still fits, so no station is left out.
  SyntheticRegistrationOptions s = NoisyOptions();
  SyntheticRegistration data = MakeSyntheticRegistration(s, &TestRng());
  for (std::size_t i = 0; i < data.stations.size(); ++i) {
    Rigid3d& reading = data.stations[i].tracker_transmitter_from_receiver;
    const double scale = static_cast<double>(i) / static_cast<double>(data.stations.size());
    reading.translation += Eigen::Vector3d(0.04, -0.02, 0.03) * scale;  // up to 5 cm
    reading.rotation = (Eigen::Quaterniond(Eigen::AngleAxisd(
                            0.05 * scale, Eigen::Vector3d(1, 1, 0).normalized())) *
                        reading.rotation)
                           .normalized();  // up to 2.9 degrees
  }
  const RegistrationResult r = RegisterOpticalToTransmitter(data.stations, MatchingOptions(s));
  EXPECT_GT(r.ChiSquareZ(), 5.0) << r.ToString();  // the distortion shows in chi-square...
  EXPECT_TRUE(r.rejected_stations.empty()) << r.ToString();  // ...but not as bad marker sets
}

TEST(RegisterOpticalToTransmitter, LeavesOutAtMostTheConfiguredFraction) {
  // Six of 20 stations swapped: 20 % of 20 is 4, the worst four are left out and the result says
  // what remains. With the option off, none is.
  SyntheticRegistrationOptions s = NoisyOptions();
  s.min_visible = 4;
  SyntheticRegistration data = MakeSyntheticRegistration(s, &TestRng());
  for (int i = 0; i < 6; ++i) SwapTwoLabels(&data.stations[3 * i]);
  RegistrationOptions o = MatchingOptions(s);
  const RegistrationResult r = RegisterOpticalToTransmitter(data.stations, o);
  EXPECT_EQ(r.rejected_stations.size(), 4u) << r.ToString();
  EXPECT_EQ(r.stations.size(), data.stations.size() - 4);
  for (const RejectedStation& rejected : r.rejected_stations) {
    EXPECT_EQ((rejected.station - data.stations[0].station) % 3, 0) << r.ToString();
  }
  o.reject_bad_stations = false;
  EXPECT_TRUE(RegisterOpticalToTransmitter(data.stations, o).rejected_stations.empty());
  o.reject_bad_stations = true;
  o.max_rejected_fraction = 1.0;  // not a fraction of the stations that can be left out
  EXPECT_THROW(RegisterOpticalToTransmitter(data.stations, o), std::invalid_argument);
}

TEST(RegisterOpticalToTransmitter, KeepsTheStationWhenTheRestCannotBeSolved) {
  // Five stations see three markers each, twelve markers in all: 45 coordinates for 42
  // parameters. Station 5 sees markers 1, 4 and 7 (with 1 and 4 swapped), which the others also
  // see: without it, 36 coordinates cannot determine 42 parameters. Leaving it out used to throw
  // and fail a registration that had been solved; it now stays in.
  std::mt19937_64& rng = TestRng();
  std::uniform_real_distribution<double> unit(-1.0, 1.0);
  std::map<int, Eigen::Vector3d> body;
  for (int id = 1; id <= 12; ++id)
    body[id] = 0.08 * Eigen::Vector3d(unit(rng), unit(rng), unit(rng));
  const Rigid3d optical_from_transmitter(QuaternionFromWxyz(0.9, 0.1, -0.3, 0.2).normalized(),
                                         Eigen::Vector3d(1.5, -0.4, 1.2));
  const std::vector<std::vector<int>> seen = {
      {1, 2, 3}, {4, 5, 6}, {7, 8, 9}, {10, 11, 12}, {1, 4, 7}};
  std::vector<RegistrationStation> stations;
  for (int i = 0; i < 5; ++i) {
    RegistrationStation s;
    s.station = i + 1;
    s.tracker_transmitter_from_receiver = Rigid3d(
        QuaternionFromWxyz(1.0, unit(rng), unit(rng), unit(rng)).normalized(),
        Eigen::Vector3d(0.3, 0.0, 0.2) + 0.25 * Eigen::Vector3d(unit(rng), unit(rng), unit(rng)));
    for (int id : seen[i]) {
      const int label = i == 4 && id == 1 ? 4 : i == 4 && id == 4 ? 1 : id;  // the swap
      s.markers.push_back(
          {label, optical_from_transmitter * (s.tracker_transmitter_from_receiver * body.at(id))});
    }
    stations.push_back(s);
  }
  RegistrationOptions o;
  // Exact readings: a tight tracker prior keeps the poses from absorbing the swap.
  o.tracker_position_noise_m = 5e-5;
  o.tracker_orientation_noise_rad = 5e-5;
  const RegistrationResult kept = RegisterOpticalToTransmitter(stations, o);
  EXPECT_TRUE(kept.rejected_stations.empty()) << kept.ToString();
  EXPECT_EQ(kept.stations.size(), 5u);
  // The station does misfit: with the test's limit at the same station count it would go.
  const auto worst = std::max_element(kept.stations.begin(), kept.stations.end(),
                                      [](const RegisteredStation& a, const RegisteredStation& b) {
                                        return a.marker_body_rms_m < b.marker_body_rms_m;
                                      });
  EXPECT_EQ(worst->station, 5);
  EXPECT_GT(worst->marker_body_rms_m, o.max_station_marker_rms_m) << kept.ToString();
}

TEST(RegisterOpticalToTransmitter, UnderestimatedNoiseShowsInChiSquare) {
  SyntheticRegistrationOptions s = NoisyOptions();
  s.optical_noise_m = 3 * 1.5e-4;
  const SyntheticRegistration data = MakeSyntheticRegistration(s, &TestRng());
  RegistrationOptions o = MatchingOptions(s);
  o.optical_noise_m = 1.5e-4;  // three times too small
  const RegistrationResult r = RegisterOpticalToTransmitter(data.stations, o);
  ASSERT_TRUE(r.converged);
  // chi-square ~ 9 nu: z ~ 8 nu / sqrt(2 nu) ~ 90 for nu ~ 250; 20 is far outside any noise.
  EXPECT_GT(r.ChiSquareZ(), 20.0) << r.ToString();
}

TEST(RegisterOpticalToTransmitter, StationsWithTooFewMarkersAreSkipped) {
  SyntheticRegistration data = MakeSyntheticRegistration({}, &TestRng());
  data.stations[4].markers.resize(2);
  data.stations[7].markers.clear();
  const RegistrationResult r = RegisterOpticalToTransmitter(data.stations);
  EXPECT_EQ(r.skipped_stations,
            (std::vector<int>{data.stations[4].station, data.stations[7].station}));
  EXPECT_EQ(r.stations.size(), data.stations.size() - 2);
  EXPECT_TRUE(testing::PosesNear(data.optical_from_transmitter,
                                 r.registration.optical_from_transmitter, 1e-8, 1e-8));

  for (auto& station : data.stations) {
    if (station.markers.size() > 2) station.markers.resize(2);
  }
  try {
    RegisterOpticalToTransmitter(data.stations);
    FAIL() << "expected std::invalid_argument";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("need at least"), std::string::npos) << e.what();
  }
}

TEST(RegisterOpticalToTransmitter, IdenticalStationsAreNotIdentifiable) {
  SyntheticRegistrationOptions s;
  s.identical_stations = true;
  s.min_visible = 6;
  const SyntheticRegistration data = MakeSyntheticRegistration(s, &TestRng());
  const RegistrationResult r = RegisterOpticalToTransmitter(data.stations);
  EXPECT_FALSE(r.identifiable);
  EXPECT_TRUE(r.covariance.rank_deficient) << r.ToString();
  EXPECT_FALSE(r.covariance.flags.empty());
  EXPECT_NE(r.ToString().find("NOT IDENTIFIABLE"), std::string::npos);
}

TEST(RegisterOpticalToTransmitter, SingleOrientationFallsBackAndFlagsTranslation) {
  // Without orientation diversity the rotation still follows from the station positions, but the
  // translation trades off against the marker offsets (t0 + R0 R r_j): a 3-dimensional null space.
  SyntheticRegistrationOptions s;
  s.random_orientations = false;
  const SyntheticRegistration data = MakeSyntheticRegistration(s, &TestRng());
  const RegistrationResult r = RegisterOpticalToTransmitter(data.stations);
  EXPECT_NE(r.initialisation.find("centroids (stations lack orientation diversity)"),
            std::string::npos)
      << r.initialisation;
  EXPECT_FALSE(r.identifiable);
  EXPECT_EQ(r.covariance.rank, r.covariance.tangent_dimension - 3) << r.ToString();
  EXPECT_TRUE(testing::RotationsNear(data.optical_from_transmitter.rotation,
                                     r.registration.optical_from_transmitter.rotation, 1e-8));
  bool translation_flagged = false;
  for (const auto& f : r.covariance.flags) {
    if (f.coordinate.find("optical_from_transmitter.translation") == 0) translation_flagged = true;
  }
  EXPECT_TRUE(translation_flagged) << r.ToString();
}

TEST(RegisterOpticalToTransmitter, OpticalUnitsOrHandednessUnlikeTheTrackerThrow) {
  // An optical system that reports millimetres, a tracker in inches or a left-handed optical
  // frame: no rigid transform explains the markers, and without the check the fit returned a
  // chi-square z of ~1e10 (mm, not converged) or ~3e5 (mirror, "identifiable") with no reason.
  for (const bool random_orientations : {true, false}) {  // both closed-form starts
    SyntheticRegistrationOptions s = NoisyOptions();
    s.random_orientations = random_orientations;
    const SyntheticRegistration data = MakeSyntheticRegistration(s, &TestRng());
    const RegistrationOptions o = MatchingOptions(s);
    auto expect_message = [&](const std::vector<RegistrationStation>& stations,
                              const std::string& needle) {
      try {
        RegisterOpticalToTransmitter(stations, o);
        ADD_FAILURE() << "expected std::invalid_argument containing " << needle;
      } catch (const std::invalid_argument& e) {
        EXPECT_NE(std::string(e.what()).find(needle), std::string::npos) << e.what();
      }
    };
    auto millimetres = data.stations;
    for (auto& station : millimetres) {
      for (auto& m : station.markers) m.marker_in_optical *= 1e3;
    }
    expect_message(millimetres, "optical millimetres give 1000");
    auto inches = data.stations;
    for (auto& station : inches) station.tracker_transmitter_from_receiver.translation /= 0.0254;
    expect_message(inches, "tracker inches 0.0254");
    auto mirrored = data.stations;
    for (auto& station : mirrored) {
      for (auto& m : station.markers) m.marker_in_optical.y() *= -1.0;
    }
    expect_message(mirrored, "left-handed");
    // A real tracker's scale error of a few per cent is not a unit error.
    auto scaled = data.stations;
    for (auto& station : scaled) station.tracker_transmitter_from_receiver.translation *= 1.05;
    EXPECT_NO_THROW(RegisterOpticalToTransmitter(scaled, o));
  }
}

// One tracker reading far off (the Fastrak's hemisphere ambiguity negates the position) pulls the
// least-squares scale of the unit check to 0.47 on seed 2, and the registration refused metric,
// right-handed data with "both must be in metres (optical millimetres give 1000, tracker inches
// 0.0254)": advice that sends the user after a unit error there is not. The error now names the
// station and the field. Seeds 0-9: whenever the check refuses the capture, it must blame station
// 4 and never the units; seed 2 (and others) must be refused.
TEST(RegisterOpticalToTransmitter, OneFarTrackerReadingIsNamedNotTakenForUnits) {
  int refused = 0;
  for (int seed = 0; seed < 10; ++seed) {
    const SyntheticRegistrationOptions s = NoisyOptions();
    std::mt19937_64 rng(seed);
    SyntheticRegistration data = MakeSyntheticRegistration(s, &rng);
    ASSERT_EQ(data.stations[3].station, 4);
    data.stations[3].tracker_transmitter_from_receiver.translation *= -1.0;  // hemisphere flip
    try {
      RegisterOpticalToTransmitter(data.stations, MatchingOptions(s));
    } catch (const std::invalid_argument& e) {
      ++refused;
      const std::string what = e.what();
      EXPECT_NE(what.find("registration station 4, tracker x/y/z"), std::string::npos)
          << "seed " << seed << ": " << what;
      EXPECT_EQ(what.find("millimetres"), std::string::npos) << "seed " << seed << ": " << what;
      EXPECT_EQ(what.find("left-handed"), std::string::npos) << "seed " << seed << ": " << what;
    }
  }
  EXPECT_GT(refused, 0);
  // A mirrored optical frame moves every station alike and must keep its message: at one
  // orientation with 6 stations, leaving a station out can lose the 3-D spread the centroids' sign
  // needs, and a first version of the check then blamed a station in 19 of 30 seeds.
  for (int seed = 0; seed < 30; ++seed) {
    SyntheticRegistrationOptions s = NoisyOptions();
    s.num_stations = 6;
    s.random_orientations = false;
    std::mt19937_64 rng(seed);
    SyntheticRegistration data = MakeSyntheticRegistration(s, &rng);
    for (auto& station : data.stations) {
      for (auto& m : station.markers) m.marker_in_optical.y() *= -1.0;
    }
    try {
      RegisterOpticalToTransmitter(data.stations, MatchingOptions(s));
    } catch (const std::invalid_argument& e) {
      EXPECT_EQ(std::string(e.what()).find("tracker x/y/z"), std::string::npos)
          << "seed " << seed << ": " << e.what();
    }
  }
}

// One orientation and positions within +-1 cm: the scale then comes from the marker centroids,
// whose offsets from the receiver (the visible markers change from station to station) are as
// large as the spread. Metric, right-handed data were refused in 3-15 of 100 such captures as
// "the optical frame is left-handed; negate one of its axes" (scale -0.85) or "2.03 times as far":
// advice that would have corrupted good data. Five seeds that threw before (5 and 20 stations).
TEST(RegisterOpticalToTransmitter, ScaleCheckDoesNotMistakeMarkerOffsetsForUnits) {
  const std::vector<std::pair<int, int>> cases = {{5, 0}, {5, 4}, {5, 14}, {5, 28}, {20, 11}};
  for (const auto& [num_stations, seed] : cases) {
    SyntheticRegistrationOptions s = NoisyOptions();
    s.random_orientations = false;
    s.station_half_size_m = 0.01;
    s.num_stations = num_stations;
    std::mt19937_64 rng(seed);
    const SyntheticRegistration data = MakeSyntheticRegistration(s, &rng);
    EXPECT_NO_THROW(RegisterOpticalToTransmitter(data.stations, MatchingOptions(s)))
        << num_stations << " stations, seed " << seed;
  }
}

TEST(RegisterOpticalToTransmitter, InvalidInputThrowsNamingStationAndField) {
  SyntheticRegistration data = MakeSyntheticRegistration({}, &TestRng());
  auto expect_message = [](const std::vector<RegistrationStation>& stations,
                           const std::string& needle) {
    try {
      RegisterOpticalToTransmitter(stations);
      ADD_FAILURE() << "expected std::invalid_argument containing " << needle;
    } catch (const std::invalid_argument& e) {
      EXPECT_NE(std::string(e.what()).find(needle), std::string::npos) << e.what();
    }
  };
  auto duplicate = data.stations;
  duplicate[2].markers.push_back(duplicate[2].markers.front());
  expect_message(duplicate, "station 3, marker");
  auto not_unit = data.stations;
  not_unit[5].tracker_transmitter_from_receiver.rotation.coeffs() *= 1.5;
  expect_message(not_unit, "station 6, tracker qw/qx/qy/qz");
  // Rounded readings (a Fastrak prints 4-5 decimals) are accepted and normalised.
  auto rounded = data.stations;
  rounded[5].tracker_transmitter_from_receiver.rotation.coeffs() *= 1.0 + 5e-5;
  EXPECT_NO_THROW(RegisterOpticalToTransmitter(rounded));
  auto nan = data.stations;
  nan[0].markers[0].marker_in_optical.x() = std::nan("");
  expect_message(nan, "station 1, marker");
  auto same_id = data.stations;
  same_id[1].station = same_id[0].station;
  expect_message(same_id, "duplicate station id");
  RegistrationOptions bad;
  bad.optical_noise_m = 0.0;
  EXPECT_THROW(RegisterOpticalToTransmitter(data.stations, bad), std::invalid_argument);
}

}  // namespace
}  // namespace trackcal::fit
