#include "fit/registration_io.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>

#include "fit/synthetic_registration.h"
#include "tests/test_utils.h"

namespace trackcal::fit {
namespace {

using testing::TestRng;

// markers.csv / tracker.csv records of a synthetic capture.
void ToRecords(const SyntheticRegistration& data, int sensor, MarkerCapture* markers,
               TrackerCapture* tracker) {
  for (const RegistrationStation& s : data.stations) {
    TrackerRecord t;
    t.station = s.station;
    t.sensor = sensor;
    t.transmitter_from_receiver = s.tracker_transmitter_from_receiver;
    tracker->records.push_back(t);
    for (const MarkerObservation& m : s.markers) {
      MarkerRecord r;
      r.station = s.station;
      r.marker = m.marker;
      r.position_in_optical = m.marker_in_optical;
      markers->records.push_back(r);
    }
  }
}

TEST(RegistrationIo, Nominal) {
  // Files -> stations -> registration -> poses -> poses.csv -> read back.
  SyntheticRegistrationOptions s;
  s.optical_noise_m = 1.5e-4;
  s.tracker_position_noise_m = 8e-4;
  s.tracker_orientation_noise_rad = 0.15 * kRadPerDeg;
  const SyntheticRegistration data = MakeSyntheticRegistration(s, &TestRng());
  MarkerCapture markers;
  TrackerCapture tracker;
  ToRecords(data, /*sensor=*/2, &markers, &tracker);
  // A second receiver's rows must be ignored.
  TrackerRecord other = tracker.records.front();
  other.sensor = 1;
  other.transmitter_from_receiver.translation.x() += 1.0;
  tracker.records.push_back(other);

  const auto dir = testing::MakeTempDir("registration_io");
  WriteMarkers(dir / kMarkersCsv, markers);
  WriteTracker(dir / kTrackerCsv, tracker);
  const std::vector<RegistrationStation> stations =
      ReadRegistrationStations(dir / kMarkersCsv, dir / kTrackerCsv, /*sensor=*/2);
  ASSERT_EQ(stations.size(), data.stations.size());
  for (std::size_t i = 0; i < stations.size(); ++i) {
    EXPECT_EQ(stations[i].station, data.stations[i].station);
    EXPECT_EQ(stations[i].markers.size(), data.stations[i].markers.size());
    // The CSV writer round-trips doubles exactly; the reader normalises quaternions (1 ulp).
    EXPECT_TRUE(testing::PosesNear(data.stations[i].tracker_transmitter_from_receiver,
                                   stations[i].tracker_transmitter_from_receiver, 0.0, 1e-15));
  }

  RegistrationOptions ro;
  ro.optical_noise_m = s.optical_noise_m;
  ro.tracker_position_noise_m = s.tracker_position_noise_m;
  ro.tracker_orientation_noise_rad = s.tracker_orientation_noise_rad;
  const RegistrationResult reg = RegisterOpticalToTransmitter(stations, ro);
  ASSERT_TRUE(reg.identifiable) << reg.ToString();
  const std::vector<ExtractedPose> poses = ExtractPoses(stations, reg.registration);
  std::map<int, double> times = {{stations[0].station, 12.5}};
  const PoseRecords records = MakePoseRecords(stations, poses, times, {"reg", 2});
  EXPECT_TRUE(records.left_out.empty());
  WritePoses(dir / kPosesCsv, records.capture);
  EXPECT_THROW(WritePoses(dir / kPosesCsv, records.capture), std::runtime_error);  // no overwrite

  const PoseCapture back = ReadPoses(dir / kPosesCsv);
  ASSERT_EQ(back.records.size(), stations.size());
  EXPECT_EQ(back.records[0].time, 12.5);
  EXPECT_EQ(back.records[1].time, 0.0);
  for (std::size_t i = 0; i < back.records.size(); ++i) {
    const PoseRecord& r = back.records[i];
    EXPECT_EQ(r.set, "reg");
    EXPECT_EQ(r.sensor, 2);
    EXPECT_TRUE(
        testing::PosesNear(stations[i].tracker_transmitter_from_receiver, r.reported, 0.0, 1e-15));
    // Reference = extracted pose; against the truth within optical + registration error (see
    // pose_extraction_test: 1 mm and 0.6 deg are about four standard deviations).
    EXPECT_TRUE(testing::PosesNear(data.true_transmitter_from_receiver[i], r.reference, 1e-3,
                                   0.6 * kRadPerDeg));
  }
}

TEST(RegistrationIo, PairingErrorsNameFileStationAndField) {
  const SyntheticRegistration data = MakeSyntheticRegistration({}, &TestRng());
  MarkerCapture markers;
  TrackerCapture tracker;
  ToRecords(data, 1, &markers, &tracker);
  auto expect_message = [](const MarkerCapture& m, const TrackerCapture& t,
                           const std::string& needle) {
    try {
      PairRegistrationRecords(m, t);
      ADD_FAILURE() << "expected std::invalid_argument containing " << needle;
    } catch (const std::invalid_argument& e) {
      EXPECT_NE(std::string(e.what()).find(needle), std::string::npos) << e.what();
    }
  };
  TrackerCapture missing = tracker;
  missing.records.erase(missing.records.begin() + 3);
  expect_message(markers, missing, "markers.csv: column station: station 4 (marker");
  // Read from files, the message names the line of the first marker row without a tracker row.
  const auto dir = testing::MakeTempDir("registration_io_errors");
  WriteMarkers(dir / kMarkersCsv, markers);
  WriteTracker(dir / kTrackerCsv, missing);
  int line = 0;
  for (const MarkerRecord& m : ReadMarkers(dir / kMarkersCsv).records) {
    if (m.station == 4 && line == 0) line = m.line;
  }
  EXPECT_GT(line, 1);  // below the header
  try {
    ReadRegistrationStations(dir / kMarkersCsv, dir / kTrackerCsv);
    ADD_FAILURE() << "expected an error for station 4";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find((dir / kMarkersCsv).string() + ":" + std::to_string(line) +
                                         ": column station: station 4"),
              std::string::npos)
        << e.what();
  }
  TrackerCapture twice = tracker;
  twice.records.push_back(twice.records[5]);
  expect_message(markers, twice, "tracker.csv: station 6, sensor 1: more than one row");
  MarkerCapture duplicate = markers;
  duplicate.records.push_back(duplicate.records[0]);
  // In the form of every other capture error (it named the station before the column).
  expect_message(duplicate, tracker,
                 "markers.csv: column marker: marker " + std::to_string(markers.records[0].marker) +
                     " appears twice at station 1");

  // The markers on receiver 2: asking for sensor 1 (trackcal-fit register could ask for nothing
  // else) said only "no row for sensor 1"; the message now names the sensors there are and how to
  // choose one.
  TrackerCapture on_two = tracker;
  for (TrackerRecord& t : on_two.records) t.sensor = 2;
  expect_message(markers, on_two,
                 "for sensor 1 (it has rows for sensor 2 there: choose the receiver that carries "
                 "the markers, trackcal-fit register --sensor N");
  EXPECT_EQ(PairRegistrationRecords(markers, on_two, /*sensor=*/2).size(), data.stations.size());

  // A tracker row without markers is a station with none: the registration skips it.
  MarkerCapture fewer;
  for (const MarkerRecord& m : markers.records) {
    if (m.station != 2) fewer.records.push_back(m);
  }
  const auto stations = PairRegistrationRecords(fewer, tracker);
  ASSERT_EQ(stations.size(), data.stations.size());
  EXPECT_TRUE(stations[1].markers.empty());
  EXPECT_EQ(RegisterOpticalToTransmitter(stations).skipped_stations, std::vector<int>{2});
}

TEST(RegistrationIo, MarkerAtZeroIsADropout) {
  // Vicon and OptiTrack exports write an occluded marker as 0,0,0. Read as a position, at 6 of 20
  // registration stations (more than the 20 % the marker-body test may leave out), it put the
  // transform 16 deg and 25 mm off with a chi-square z of 1e7, and 2 poses were left out;
  // read as a dropout, the stations keep their other markers and the transform is as without.
  SyntheticRegistrationOptions s;
  s.optical_noise_m = 1.5e-4;
  s.tracker_position_noise_m = 8e-4;
  s.tracker_orientation_noise_rad = 0.15 * kRadPerDeg;
  s.min_visible = 3;
  s.max_visible = 5;  // a marker to drop out at every station
  const SyntheticRegistration data = MakeSyntheticRegistration(s, &TestRng());
  MarkerCapture markers;
  TrackerCapture tracker;
  ToRecords(data, 1, &markers, &tracker);
  for (int i = 0; i < 6; ++i) {
    const RegistrationStation& st = data.stations[i];
    int hidden = 1;
    while (std::any_of(st.markers.begin(), st.markers.end(),
                       [&](const MarkerObservation& m) { return m.marker == hidden; })) {
      ++hidden;
    }
    MarkerRecord dropout;
    dropout.station = st.station;
    dropout.marker = hidden;  // position_in_optical 0,0,0
    markers.records.push_back(dropout);
  }
  const auto dir = testing::MakeTempDir("registration_io_dropout");
  WriteMarkers(dir / kMarkersCsv, markers);
  WriteTracker(dir / kTrackerCsv, tracker);
  const std::vector<RegistrationStation> stations =
      ReadRegistrationStations(dir / kMarkersCsv, dir / kTrackerCsv);
  ASSERT_EQ(stations.size(), data.stations.size());
  for (std::size_t i = 0; i < stations.size(); ++i) {
    EXPECT_EQ(stations[i].markers.size(), data.stations[i].markers.size()) << "station " << i + 1;
  }
  RegistrationOptions ro;
  ro.optical_noise_m = s.optical_noise_m;
  ro.tracker_position_noise_m = s.tracker_position_noise_m;
  ro.tracker_orientation_noise_rad = s.tracker_orientation_noise_rad;
  const RegistrationResult reg = RegisterOpticalToTransmitter(stations, ro);
  EXPECT_TRUE(reg.rejected_stations.empty()) << reg.ToString();
  // About 30 standard deviations of the transform (0.02 deg, 0.3 mm): the registration as if
  // the dropout rows were not in the file, far from the degrees it was off.
  EXPECT_TRUE(testing::PosesNear(data.optical_from_transmitter,
                                 reg.registration.optical_from_transmitter, 1e-2, 0.5 * kRadPerDeg))
      << reg.ToString();
  // A pose is extracted at every station, none left out as a bad fit.
  const PoseRecords records = MakePoseRecords(stations, ExtractPoses(stations, reg.registration));
  EXPECT_TRUE(records.left_out.empty());
}

TEST(CopyExtraColumns, ByStationAndSensorWithNanForMissingRows) {
  PoseCapture labels;
  labels.extra_columns = {"temperature"};
  labels.records.push_back({3, "calib", 1, 0.0, {}, {}, {21.5}});
  labels.records.push_back({3, "calib", 2, 0.0, {}, {}, {22.5}});
  labels.records.push_back({4, "reg", 1, 0.0, {}, {}, {23.0}});
  PoseCapture registered;
  registered.records.push_back({4, "reg", 1, 0.0, {}, {}, {}});
  registered.records.push_back({3, "calib", 2, 0.0, {}, {}, {}});
  registered.records.push_back({5, "calib", 1, 0.0, {}, {}, {}});  // not in the labels
  CopyExtraColumns(labels, &registered);
  EXPECT_EQ(registered.extra_columns, labels.extra_columns);
  EXPECT_EQ(registered.records[0].extra, std::vector<double>{23.0});
  EXPECT_EQ(registered.records[1].extra, std::vector<double>{22.5});
  ASSERT_EQ(registered.records[2].extra.size(), 1u);
  EXPECT_TRUE(std::isnan(registered.records[2].extra[0]));
}

TEST(MakePoseRecords, LeavesOutStationsWithoutAPose) {
  const SyntheticRegistration data = MakeSyntheticRegistration({}, &TestRng());
  std::vector<RegistrationStation> stations(data.stations.begin(), data.stations.begin() + 3);
  stations[1].markers.resize(2);
  const OpticalRegistration truth{data.optical_from_transmitter, data.marker_in_receiver};
  const std::vector<ExtractedPose> poses = ExtractPoses(stations, truth);
  const PoseRecords records = MakePoseRecords(stations, poses);
  EXPECT_EQ(records.capture.records.size(), 2u);
  EXPECT_EQ(records.left_out, std::vector<int>{stations[1].station});
  EXPECT_THROW(MakePoseRecords(stations, {poses[0]}), std::invalid_argument);
  PoseRecordOptions bad;
  bad.set = "calibration";
  EXPECT_THROW(MakePoseRecords(stations, poses, {}, bad), std::invalid_argument);
}

}  // namespace
}  // namespace trackcal::fit
