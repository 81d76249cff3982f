// Internal: one walk over every field of a Scene, shared by the YAML reader and writer and the JSON
// writer of truth.json, so a field cannot be read but not written (or the reverse).
//
// A visitor V provides:
//   Field(const char* key, T& value) for std::string, uint64_t, int, bool, double, Eigen::Vector3d,
//     Eigen::Vector3i, Eigen::Matrix3d, Rigid3d, std::vector<Eigen::Vector3d>;
//   Object(const char* key, F visit_members);
//   List(const char* key, std::vector<E>& items, F visit_item).
#pragma once

#include "sim/scene.h"

namespace trackcal::sim::internal {

template <typename V>
void VisitScene(V& v, Scene& s) {
  v.Field("name", s.name);
  v.Field("seed", s.seed);
  v.Object("environment", [&] {
    FieldModel& e = s.environment;
    v.Field("field_constant", e.field_constant);
    v.Field("transmitter_octupole_m2", e.transmitter_octupole_m2);
    v.List("planes", e.planes, [&](ConductingPlane& p) {
      v.Field("name", p.name);
      v.Field("point_in_transmitter", p.point_in_transmitter);
      v.Field("normal_in_transmitter", p.normal_in_transmitter);
      v.Field("attenuation", p.attenuation);
    });
    v.List("objects", e.objects, [&](InducedDipole& o) {
      v.Field("name", o.name);
      v.Field("location_in_transmitter", o.location_in_transmitter);
      v.Field("polarisability_m3", o.polarisability_m3);
    });
  });
  v.Object("tracker", [&] {
    TrackerConfig& t = s.tracker;
    v.Field("receiver_gain_matrix", t.receiver_gain_matrix);
    v.Field("signal_noise", t.signal_noise);
    v.Field("samples_per_station", t.samples_per_station);
    v.Field("hemisphere_in_transmitter", t.hemisphere_in_transmitter);
    v.Field("sensor", t.sensor);
    v.Field("update_rate_hz", t.update_rate_hz);
  });
  v.Object("reference", [&] {
    ReferenceConfig& r = s.reference;
    v.Field("position_noise_m", r.position_noise_m);
    v.Field("orientation_noise_rad", r.orientation_noise_rad);
    v.Field("marker_noise_m", r.marker_noise_m);
    v.Field("samples_per_station", r.samples_per_station);
    v.Field("update_rate_hz", r.update_rate_hz);
    v.Field("optical_from_transmitter", r.optical_from_transmitter);
    v.Field("markers_in_body", r.markers_in_body);
    v.Field("visibility_cos_min", r.visibility_cos_min);
  });
  v.Object("capture", [&] {
    CaptureProtocol& c = s.capture;
    v.Object("calibration", [&] {
      v.Field("origin_in_transmitter", c.calibration.origin_in_transmitter);
      v.Field("counts", c.calibration.counts);
      v.Field("spacing_m", c.calibration.spacing_m);
    });
    auto random = [&](const char* key, RandomStations& r) {
      v.Object(key, [&] {
        v.Field("count", r.count);
        v.Field("min_in_transmitter", r.min_in_transmitter);
        v.Field("max_in_transmitter", r.max_in_transmitter);
      });
    };
    random("validation", c.validation);
    random("registration", c.registration);
    v.Field("station_period_s", c.station_period_s);
    v.Object("stream", [&] {
      v.Field("duration_s", c.stream.duration_s);
      v.Field("center_in_transmitter", c.stream.center_in_transmitter);
      v.Field("amplitude_m", c.stream.amplitude_m);
      v.Field("period_s", c.stream.period_s);
      v.Field("rotation_amplitude_rad", c.stream.rotation_amplitude_rad);
      v.Field("rotation_period_s", c.stream.rotation_period_s);
    });
  });
  v.Object("hidden", [&] {
    HiddenEffects& h = s.hidden;
    v.Object("sensor_offset", [&] {
      v.Field("enabled", h.sensor_offset);
      v.Field("receiver_from_body", h.receiver_from_body);
    });
    v.Object("receiver_gains", [&] {
      v.Field("enabled", h.receiver_gains);
      v.Field("receiver_gain_matrix", h.receiver_gain_matrix);
    });
    v.Object("ferromagnetic_object", [&] {
      v.Field("enabled", h.ferromagnetic_object);
      v.Field("name", h.object.name);
      v.Field("location_in_transmitter", h.object.location_in_transmitter);
      v.Field("polarisability_m3", h.object.polarisability_m3);
    });
    v.Object("finite_transmitter_coils", [&] {
      v.Field("enabled", h.finite_transmitter_coils);
      v.Field("octupole_m2", h.octupole_m2);
    });
    v.Object("clock_offset", [&] {
      v.Field("enabled", h.clock_offset);
      v.Field("reference_minus_tracker_s", h.reference_minus_tracker_s);
      v.Field("reference_clock_drift", h.reference_clock_drift);
    });
    v.Object("hemisphere_flips", [&] {
      v.Field("enabled", h.hemisphere_flips);
      v.Field("count", h.flip_count);
    });
  });
}

}  // namespace trackcal::sim::internal
