#include "sim/simulator.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <map>
#include <numbers>
#include <stdexcept>

#include "core/file_util.h"

namespace trackcal::sim {

namespace {

nlohmann::json PoseJson(const Rigid3d& p) {
  return {{"rotation_xyzw", {p.rotation.x(), p.rotation.y(), p.rotation.z(), p.rotation.w()}},
          {"translation", {p.translation.x(), p.translation.y(), p.translation.z()}}};
}
nlohmann::json VecJson(const Eigen::Vector3d& v) { return {v.x(), v.y(), v.z()}; }
nlohmann::json MatJson(const Eigen::Matrix3d& m) {
  nlohmann::json rows = nlohmann::json::array();
  for (int r = 0; r < 3; ++r) rows.push_back({m(r, 0), m(r, 1), m(r, 2)});
  return rows;
}

nlohmann::json FieldModelJson(const FieldModel& f) {
  nlohmann::json planes = nlohmann::json::array();
  for (const auto& p : f.planes) {
    planes.push_back({{"name", p.name},
                      {"point_in_transmitter", VecJson(p.point_in_transmitter)},
                      {"normal_in_transmitter", VecJson(p.normal_in_transmitter)},
                      {"attenuation", p.attenuation}});
  }
  nlohmann::json objects = nlohmann::json::array();
  for (const auto& o : f.objects) {
    objects.push_back({{"name", o.name},
                       {"location_in_transmitter", VecJson(o.location_in_transmitter)},
                       {"polarisability_m3", o.polarisability_m3}});
  }
  return {{"field_constant", f.field_constant},
          {"transmitter_octupole_m2", VecJson(f.transmitter_octupole_m2)},
          {"planes", planes},
          {"objects", objects}};
}

}  // namespace

// ---------------------------------------------------------------------------------------------
TrackerModel::TrackerModel(FieldModel field, const Eigen::Matrix3d& receiver_gain_matrix,
                           double signal_noise, const TrackerSolverOptions& solver)
    : field_(std::move(field)),
      receiver_gain_matrix_(receiver_gain_matrix),
      signal_noise_(signal_noise),
      solver_(solver) {
  field_.Check();
  solver_.Check();
  if (!(signal_noise_ >= 0))
    throw std::invalid_argument("tracker model: signal_noise must be >= 0");
}

Eigen::Matrix3d TrackerModel::Signal(const Rigid3d& transmitter_from_receiver) const {
  return SignalMatrix<double>(receiver_gain_matrix_,
                              transmitter_from_receiver.rotation.toRotationMatrix(),
                              field_.Field<double>(transmitter_from_receiver.translation));
}

TrackerSolution TrackerModel::Report(const Rigid3d& transmitter_from_receiver, int samples,
                                     Rng* rng) const {
  if (samples < 1) throw std::invalid_argument("tracker model: samples must be >= 1");
  Eigen::Matrix3d s = Signal(transmitter_from_receiver);
  if (rng != nullptr && signal_noise_ > 0) {
    const double sigma = signal_noise_ / std::sqrt(static_cast<double>(samples));
    for (int c = 0; c < 3; ++c) {
      for (int r = 0; r < 3; ++r) s(r, c) += sigma * rng->Normal();
    }
  }
  return SolveFreeSpacePose(s, solver_);
}

// ---------------------------------------------------------------------------------------------
namespace {
nlohmann::json ErrorSummaryJson(const ErrorSummary& e) {
  return {{"mean", e.mean}, {"std", e.std},       {"max", e.max},
          {"rms", e.rms},   {"median", e.median}, {"p95", e.p95}};
}
}  // namespace

nlohmann::json SummaryToJson(const PoseErrorSummary& summary) {
  return {{"count", summary.position_mm.count},
          {"position_mm", ErrorSummaryJson(summary.position_mm)},
          {"orientation_deg", ErrorSummaryJson(summary.orientation_deg)}};
}

PoseErrorSummary UncorrectedSummary(const PoseCapture& poses, const std::string& set) {
  std::vector<Rigid3d> reported, reference;
  for (const PoseRecord& r : poses.records) {
    if (r.set != set) continue;
    reported.push_back(r.reported);
    reference.push_back(r.reference);
  }
  return SummarizePoseErrors(reported, reference);
}

// ---------------------------------------------------------------------------------------------
namespace {

FieldModel EffectiveField(const Scene& scene) {
  FieldModel field = scene.environment;
  if (scene.hidden.ferromagnetic_object) {
    InducedDipole object = scene.hidden.object;
    if (object.name.empty()) object.name = "hidden_ferromagnetic_object";
    field.objects.push_back(object);
  }
  if (scene.hidden.finite_transmitter_coils) {
    field.transmitter_octupole_m2 += scene.hidden.octupole_m2;
  }
  return field;
}

TrackerSolverOptions SolverOptions(const Scene& scene) {
  TrackerSolverOptions o;
  o.field_constant = scene.environment.field_constant;
  o.hemisphere_in_transmitter = scene.tracker.hemisphere_in_transmitter;
  return o;
}

// A receiver at the transmitter or at an induced dipole has no signal (the field is singular
// there) and so no report: the tracker's solver would return an unconverged identity pose, which
// would go into the capture as if measured. `what` names the station or sample.
void RequireSignal(const TrackerModel& tracker, const Rigid3d& pose, const std::string& what) {
  if (tracker.Signal(pose).allFinite()) return;
  const Eigen::Vector3d& p = pose.translation;
  throw std::invalid_argument("scene: " + what + " at [" + FormatNumber(p.x()) + ", " +
                              FormatNumber(p.y()) + ", " + FormatNumber(p.z()) +
                              "] m is at the transmitter or an object, where the field is "
                              "singular");
}

Scene Checked(Scene scene) {
  scene.Check();
  return scene;
}

// The markers the camera (at the optical origin) sees on a body: those facing it, and always the
// three facing it best; each averaged marker gets noise sigma per axis. Noise is drawn for every
// marker so visibility never shifts the random stream.
void AppendMarkers(int station, const Rigid3d& optical_from_body, const ReferenceConfig& reference,
                   double sigma, Rng* noise, MarkerCapture* out) {
  const Eigen::Vector3d camera_in_optical = Eigen::Vector3d::Zero();
  const auto& markers = reference.markers_in_body;
  std::vector<std::pair<double, size_t>> ranked;
  for (size_t m = 0; m < markers.size(); ++m) {
    const Eigen::Vector3d x = optical_from_body * markers[m];
    const Eigen::Vector3d outward = optical_from_body.rotation * markers[m].normalized();
    ranked.push_back({outward.dot((camera_in_optical - x).normalized()), m});
  }
  std::sort(ranked.begin(), ranked.end(),
            [](const auto& a, const auto& b) { return a.first > b.first; });
  std::vector<bool> visible(markers.size(), false);
  for (size_t r = 0; r < ranked.size(); ++r) {
    visible[ranked[r].second] = r < 3 || ranked[r].first > reference.visibility_cos_min;
  }
  for (size_t m = 0; m < markers.size(); ++m) {
    const Eigen::Vector3d n = sigma * noise->Normal3();
    if (!visible[m]) continue;
    MarkerRecord mr;
    mr.station = station;
    mr.marker = static_cast<int>(m) + 1;
    mr.position_in_optical = optical_from_body * markers[m] + n;
    out->records.push_back(mr);
  }
}

}  // namespace

Simulator::Simulator(Scene scene)
    : scene_(Checked(std::move(scene))),
      tracker_(EffectiveField(scene_),
               scene_.hidden.receiver_gains ? scene_.hidden.receiver_gain_matrix
                                            : scene_.tracker.receiver_gain_matrix,
               scene_.tracker.signal_noise, SolverOptions(scene_)),
      receiver_from_body_(scene_.hidden.sensor_offset ? scene_.hidden.receiver_from_body
                                                      : Rigid3d()) {
  for (int r = 0; r < kMaxReceivers; ++r) {
    Rng rng(scene_.seed, r == 0 ? std::string("trajectory") : "trajectory_" + std::to_string(r));
    Trajectory t;
    for (int i = 0; i < 3; ++i) t.phase(i) = rng.Uniform(0.0, 2.0 * std::numbers::pi);
    for (int i = 0; i < 3; ++i) t.rotation_phase(i) = rng.Uniform(0.0, 2.0 * std::numbers::pi);
    t.base_rotation = rng.UniformRotation();
    trajectories_.push_back(t);
  }
}

Rigid3d Simulator::TruePoseAt(double time_s, int receiver) const {
  if (receiver < 0 || receiver >= kMaxReceivers) {
    throw std::invalid_argument("TruePoseAt: receiver " + std::to_string(receiver) +
                                " is not in [0, " + std::to_string(kMaxReceivers) + ")");
  }
  const Trajectory& tr = trajectories_[receiver];
  const StreamConfig& s = scene_.capture.stream;
  const double two_pi = 2.0 * std::numbers::pi;
  Eigen::Vector3d p = s.center_in_transmitter;
  Eigen::Vector3d w;
  // Incommensurate rotation periods so the orientation does not repeat with the position.
  const Eigen::Vector3d rot_periods = s.rotation_period_s * Eigen::Vector3d(1.0, 1.37, 0.81);
  for (int i = 0; i < 3; ++i) {
    p(i) += s.amplitude_m(i) * std::sin(two_pi * time_s / s.period_s(i) + tr.phase(i));
    w(i) = s.rotation_amplitude_rad *
           std::sin(two_pi * time_s / rot_periods(i) + tr.rotation_phase(i));
  }
  const double angle = w.norm();
  const Eigen::Quaterniond dq = angle > 0 ? Eigen::Quaterniond(Eigen::AngleAxisd(angle, w / angle))
                                          : Eigen::Quaterniond::Identity();
  return Rigid3d((tr.base_rotation * dq).normalized(), p);
}

SimulatedCapture Simulator::Generate() const {
  const Scene& sc = scene_;
  const CaptureProtocol& cp = sc.capture;
  SimulatedCapture out;

  // ---- Station plan: calibration grid (snake order), validation, registration. ----
  struct Planned {
    std::string set;
    Rigid3d pose;
  };
  std::vector<Planned> plan;
  {
    Rng orient(sc.seed, "calibration_orientations");
    const Eigen::Vector3i n = cp.calibration.counts;
    int row = 0;
    for (int k = 0; k < n.z(); ++k) {
      for (int jj = 0; jj < n.y(); ++jj, ++row) {
        const int j = (k % 2 == 0) ? jj : n.y() - 1 - jj;
        for (int ii = 0; ii < n.x(); ++ii) {
          const int i = (row % 2 == 0) ? ii : n.x() - 1 - ii;
          const Eigen::Vector3d p = cp.calibration.origin_in_transmitter +
                                    cp.calibration.spacing_m * Eigen::Vector3d(i, j, k);
          plan.push_back({"calib", Rigid3d(orient.UniformRotation(), p)});
        }
      }
    }
    auto random = [&](const RandomStations& r, const std::string& set, const char* stream) {
      Rng rng(sc.seed, stream);
      for (int s = 0; s < r.count; ++s) {
        Eigen::Vector3d p;
        for (int i = 0; i < 3; ++i)
          p(i) = rng.Uniform(r.min_in_transmitter(i), r.max_in_transmitter(i));
        plan.push_back({set, Rigid3d(rng.UniformRotation(), p)});
      }
    };
    random(cp.validation, "valid", "validation_stations");
    random(cp.registration, "reg", "registration_stations");
  }

  // ---- Hemisphere flips among calibration and validation stations. ----
  std::vector<bool> flipped(plan.size(), false);
  std::vector<int> flipped_ids;
  if (sc.hidden.hemisphere_flips && sc.hidden.flip_count > 0) {
    std::vector<size_t> candidates;
    for (size_t i = 0; i < plan.size(); ++i) {
      if (plan[i].set != "reg") candidates.push_back(i);
    }
    Rng rng(sc.seed, "hemisphere_flips");
    const size_t count = std::min(candidates.size(), static_cast<size_t>(sc.hidden.flip_count));
    for (size_t i = 0; i < count; ++i) {
      const size_t j =
          i + static_cast<size_t>(rng.Uniform() * static_cast<double>(candidates.size() - i));
      std::swap(candidates[i], candidates[std::min(j, candidates.size() - 1)]);
      flipped[candidates[i]] = true;
    }
  }

  // ---- Static stations. ----
  Rng tracker_noise(sc.seed, "tracker_noise");
  Rng reference_noise(sc.seed, "reference_noise");
  Rng marker_noise(sc.seed, "marker_noise");
  Rng station_marker_noise(sc.seed, "station_marker_noise");
  const double ref_n = std::sqrt(static_cast<double>(sc.reference.samples_per_station));
  const double sigma_ref_p = sc.reference.position_noise_m / ref_n;
  const double sigma_ref_q = sc.reference.orientation_noise_rad / ref_n;
  const double sigma_marker = sc.reference.marker_noise_m / ref_n;
  const Rigid3d& optical_from_transmitter = sc.reference.optical_from_transmitter;

  std::map<std::string, std::pair<std::vector<double>, std::vector<double>>> floor_errors;
  for (size_t i = 0; i < plan.size(); ++i) {
    const int id = static_cast<int>(i) + 1;
    const double time = static_cast<double>(i) * cp.station_period_s;
    StationTruth truth;
    truth.station = id;
    truth.set = plan[i].set;
    truth.time = time;
    truth.transmitter_from_receiver = plan[i].pose;
    truth.transmitter_from_body = plan[i].pose * receiver_from_body_;
    truth.hemisphere_flipped = flipped[i];
    RequireSignal(tracker_, plan[i].pose,
                  "capture: station " + std::to_string(id) + " (" + truth.set + ")");
    truth.reported_noise_free = tracker_.Report(plan[i].pose).transmitter_from_receiver;
    Rigid3d reported = tracker_.Report(plan[i].pose, sc.tracker.samples_per_station, &tracker_noise)
                           .transmitter_from_receiver;
    if (flipped[i]) {
      truth.reported_noise_free.translation = -truth.reported_noise_free.translation;
      reported.translation = -reported.translation;
      flipped_ids.push_back(id);
    }
    Rigid3d reference = truth.transmitter_from_body;
    reference.translation += sigma_ref_p * reference_noise.Normal3();
    reference.rotation =
        (reference_noise.SmallRotation(sigma_ref_q) * reference.rotation).normalized();

    PoseRecord rec;
    rec.station = id;
    rec.set = truth.set;
    rec.sensor = sc.tracker.sensor;
    rec.time = time;
    rec.reported = reported;
    rec.reference = reference;
    out.poses.records.push_back(rec);

    // The error a perfect model of this scene would leave: tracker and reference noise only
    // (mm and degrees, like every summary).
    const Eigen::Vector3d floor_p =
        (reference.translation - reported.translation) -
        (truth.transmitter_from_body.translation - truth.reported_noise_free.translation);
    const Eigen::Quaterniond e_capture = reference.rotation * reported.rotation.conjugate();
    const Eigen::Quaterniond e_model =
        truth.transmitter_from_body.rotation * truth.reported_noise_free.rotation.conjugate();
    floor_errors[truth.set].first.push_back(1e3 * floor_p.norm());
    floor_errors[truth.set].second.push_back(kDegPerRad * AngularDistance(e_capture, e_model));

    // Every station is seen by both systems, as in a session (paper section 3): the tracker's
    // reading (tracker.csv) and the markers facing the camera (markers.csv). The registration
    // stations draw their marker noise from "marker_noise" as before this change (their files
    // are unchanged), the others from "station_marker_noise".
    TrackerRecord tr;
    tr.station = id;
    tr.sensor = sc.tracker.sensor;
    tr.transmitter_from_receiver = reported;
    out.tracker.records.push_back(tr);
    AppendMarkers(id, optical_from_transmitter * truth.transmitter_from_body, sc.reference,
                  sigma_marker, truth.set == "reg" ? &marker_noise : &station_marker_noise,
                  &out.markers);
    out.stations.push_back(truth);
  }

  // ---- Streams on independent clocks. ----
  const StreamConfig& st = cp.stream;
  const double offset = sc.hidden.clock_offset ? sc.hidden.reference_minus_tracker_s : 0.0;
  const double drift = sc.hidden.clock_offset ? sc.hidden.reference_clock_drift : 0.0;
  if (st.duration_s > 0) {
    Rng stream_tracker(sc.seed, "stream_tracker_noise");
    const double dt = 1.0 / sc.tracker.update_rate_hz;
    for (int k = 0;; ++k) {
      const double t = k * dt;
      if (t > st.duration_s) break;
      TrackerStreamSample s;
      s.time = t;
      s.sensor = sc.tracker.sensor;
      const Rigid3d truth = TruePoseAt(t);
      RequireSignal(tracker_, truth,
                    "capture.stream: the receiver at t = " + FormatNumber(t) + " s");
      s.transmitter_from_receiver =
          tracker_.Report(truth, 1, &stream_tracker).transmitter_from_receiver;
      out.tracker_stream.records.push_back(s);
    }
    Rng stream_reference(sc.seed, "stream_reference_noise");
    const double dr = 1.0 / sc.reference.update_rate_hz;
    // The reference clock starts at an arbitrary phase of its own sample period.
    const double phase = Rng(sc.seed, "stream_reference_phase").Uniform(0.0, dr);
    for (int k = 0;; ++k) {
      const double t = phase + k * dr;
      if (t > st.duration_s) break;
      Rigid3d body = TruePoseAt(t) * receiver_from_body_;
      body.translation += sc.reference.position_noise_m * stream_reference.Normal3();
      body.rotation =
          (stream_reference.SmallRotation(sc.reference.orientation_noise_rad) * body.rotation)
              .normalized();
      ReferenceStreamSample s;
      s.time = t + offset + drift * t;
      s.transmitter_from_body = body;
      out.reference_stream.records.push_back(s);
    }
  }

  // ---- truth.json ----
  nlohmann::json stats = nlohmann::json::object();
  for (const std::string set : {"calib", "valid", "reg"}) {
    const auto it = floor_errors.find(set);
    if (it == floor_errors.end()) continue;
    const PoseErrorSummary floor{SummarizeErrors(it->second.first),
                                 SummarizeErrors(it->second.second)};
    out.uncorrected[set] = UncorrectedSummary(out.poses, set);
    out.noise_floor[set] = floor;
    stats[set] = {{"uncorrected", SummaryToJson(out.uncorrected[set])},
                  {"noise_floor", SummaryToJson(floor)}};
  }
  nlohmann::json stations = nlohmann::json::array();
  for (const StationTruth& t : out.stations) {
    stations.push_back({{"station", t.station},
                        {"set", t.set},
                        {"time", t.time},
                        {"transmitter_from_receiver", PoseJson(t.transmitter_from_receiver)},
                        {"transmitter_from_body", PoseJson(t.transmitter_from_body)},
                        {"reported_noise_free", PoseJson(t.reported_noise_free)},
                        {"hemisphere_flipped", t.hemisphere_flipped}});
  }
  nlohmann::json markers = nlohmann::json::array();
  for (const auto& m : sc.reference.markers_in_body) markers.push_back(VecJson(m));
  out.truth = {
      {"format", "trackcal-truth 1"},
      {"scene", SceneToJson(sc)},
      {"hidden_effects_enabled", sc.hidden.EnabledNames()},
      {"effective",
       {{"field_model", FieldModelJson(tracker_.field())},
        {"receiver_gain_matrix", MatJson(tracker_.receiver_gain_matrix())},
        {"signal_noise_per_sample", tracker_.signal_noise()},
        {"tracker_hemisphere_in_transmitter", VecJson(sc.tracker.hemisphere_in_transmitter)},
        {"receiver_from_body", PoseJson(receiver_from_body_)},
        {"optical_from_transmitter", PoseJson(sc.reference.optical_from_transmitter)},
        {"markers_in_body", markers},
        {"reference_minus_tracker_s", offset},
        {"reference_clock_drift", drift},
        {"hemisphere_flipped_stations", flipped_ids},
        {"station_noise",
         {{"reference_position_m", sigma_ref_p},
          {"reference_orientation_rad", sigma_ref_q},
          {"marker_m", sigma_marker},
          {"signal", sc.tracker.signal_noise /
                         std::sqrt(static_cast<double>(sc.tracker.samples_per_station))}}}}},
      {"statistics", stats},
      {"stations", stations}};
  return out;
}

namespace {
template <typename Table>
Table RowsOfSet(const Table& table, const std::vector<StationTruth>& stations,
                const std::string& set) {
  std::map<int, std::string> set_of;
  for (const StationTruth& t : stations) set_of[t.station] = t.set;
  Table out;
  out.extra_columns = table.extra_columns;
  out.extra_labels = table.extra_labels;
  for (const auto& r : table.records) {
    const auto it = set_of.find(r.station);
    if (it != set_of.end() && it->second == set) out.records.push_back(r);
  }
  return out;
}
}  // namespace

MarkerCapture SimulatedCapture::MarkersOfSet(const std::string& set) const {
  return RowsOfSet(markers, stations, set);
}

TrackerCapture SimulatedCapture::TrackerOfSet(const std::string& set) const {
  return RowsOfSet(tracker, stations, set);
}

// ---------------------------------------------------------------------------------------------
void WriteCaptureFolder(const Simulator& simulator, const SimulatedCapture& capture,
                        const std::filesystem::path& dir) {
  namespace fs = std::filesystem;
  std::error_code ec;
  if (fs::exists(dir, ec) && !(fs::is_directory(dir, ec) && fs::is_empty(dir, ec))) {
    throw std::runtime_error(dir.string() +
                             ": exists and is not an empty folder; refusing to "
                             "overwrite a capture");
  }
  // "out/" and "out" are the same folder: drop a trailing separator before taking the name.
  fs::path absolute = fs::absolute(dir).lexically_normal();
  if (absolute.filename().empty()) absolute = absolute.parent_path();
  const fs::path parent = absolute.parent_path();
  fs::create_directories(parent);
  std::string tmpl;
  if (!CreateTemporaryFolderBeside(absolute, &tmpl)) {
    throw std::runtime_error(dir.string() + ": cannot create a temporary folder in " +
                             parent.string());
  }
  const fs::path tmp(tmpl);
  try {
    WritePoses(tmp / kPosesCsv, capture.poses);
    WriteMarkers(tmp / kMarkersCsv, capture.markers);
    WriteTracker(tmp / kTrackerCsv, capture.tracker);
    if (!capture.tracker_stream.records.empty() || !capture.reference_stream.records.empty()) {
      WriteTrackerStream(tmp / kTrackerStreamCsv, capture.tracker_stream);
      WriteReferenceStream(tmp / kReferenceStreamCsv, capture.reference_stream);
    }
    WriteFileAtomically(tmp / "truth.json", capture.truth.dump(2) + "\n", false);
    WriteFileAtomically(tmp / "scene.yaml", SceneToYaml(simulator.scene()), false);
    // rename() replaces only an empty folder, so a capture that appeared meanwhile survives.
    if (std::rename(tmp.c_str(), absolute.c_str()) != 0) {
      throw std::runtime_error(dir.string() +
                               ": cannot move the capture into place (exists and "
                               "not empty?)");
    }
  } catch (...) {
    fs::remove_all(tmp, ec);
    throw;
  }
}

}  // namespace trackcal::sim
