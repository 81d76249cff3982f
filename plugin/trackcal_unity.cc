// The C ABI of trackcal_unity.h over VrpnTrackerClient: a background thread per handle keeps the
// latest pose per sensor; every entry point catches everything, since an exception must not cross
// into Unity's runtime.
#include "plugin/trackcal_unity.h"

#include <algorithm>
#include <chrono>
#include <cstring>
#include <exception>
#include <map>
#include <memory>
#include <mutex>
#include <stdexcept>
#include <string>

#include "plugin/unity_axes.h"
#ifdef _WIN32
#include "vrpn_server/net/socket_compat.h"  // windows.h, after winsock2.h
#endif
#include "vrpn_server/client/tracker_client.h"
#include "vrpn_server/protocol/payloads.h"

namespace {

using trackcal::Rigid3d;
using SteadyClock = std::chrono::steady_clock;

thread_local std::string last_error;

int32_t Fail(int32_t code, std::string why) {
  last_error = std::move(why);
  return code;
}

struct SensorState {
  Rigid3d transmitter_from_receiver;
  trackcal::unity::UnityPose unity;
  double time_s = 0;
  SteadyClock::time_point arrived;
  std::uint64_t reports = 0;
};

// Runs body (returning a status code); an exception becomes an error code and last_error, so none
// crosses the C ABI into Unity's runtime (undefined behaviour, in practice a crash of the player).
template <typename Body>
int32_t Guarded(const char* function, Body&& body) {
  try {
    return body();
  } catch (const std::invalid_argument& e) {
    return Fail(TRACKCAL_UNITY_ERROR_ARGUMENT, std::string(function) + ": " + e.what());
  } catch (const std::exception& e) {
    return Fail(TRACKCAL_UNITY_ERROR_INTERNAL, std::string(function) + ": " + e.what());
  } catch (...) {
    return Fail(TRACKCAL_UNITY_ERROR_INTERNAL, std::string(function) + ": unknown failure");
  }
}

// TRACKCAL_UNITY_OK, or the error for a sensor or button index outside 0..MAX_SENSOR.
int32_t CheckIndex(const char* function, const char* what, int32_t index) {
  if (index >= 0 && index <= TRACKCAL_UNITY_MAX_SENSOR) return TRACKCAL_UNITY_OK;
  return Fail(TRACKCAL_UNITY_ERROR_ARGUMENT, std::string(function) + ": " + what + " " +
                                                 std::to_string(index) + " is outside 0.." +
                                                 std::to_string(TRACKCAL_UNITY_MAX_SENSOR));
}

trackcal::unity::AxisMap AxesOrDefault(const char* axes) {
  return trackcal::unity::ParseAxisMap(
      axes == nullptr || axes[0] == '\0' ? trackcal::unity::kDefaultAxes : std::string_view(axes));
}

// A client's host-name lookup runs on a detached thread that can outlive trackcal_unity_close; the
// library must then stay mapped. Linux: linked with -z nodelete (plugin/CMakeLists.txt,
// standalone/CMakeLists.txt). Windows: pinned here, once, from the first open.
void PinThisLibrary() {
#ifdef _WIN32
  static const bool pinned = [] {
    HMODULE module = nullptr;
    return ::GetModuleHandleExW(
               GET_MODULE_HANDLE_EX_FLAG_FROM_ADDRESS | GET_MODULE_HANDLE_EX_FLAG_PIN,
               reinterpret_cast<LPCWSTR>(&trackcal_unity_open), &module) != 0;
  }();
  (void)pinned;
#endif
}

}  // namespace

struct TrackcalUnityTracker {
  trackcal::unity::AxisMap axes;
  std::mutex mutex;
  std::map<int, SensorState> sensors;  // guarded by mutex
  std::string text;                    // guarded by mutex
  int32_t text_severity = 0;           // guarded by mutex
  std::uint64_t texts = 0;             // guarded by mutex
  struct Button {
    bool pressed = false;
    std::uint64_t presses = 0;
    // client->connections() when the server last said something about it: a state from an
    // earlier connection is stale (the button may have been released while the link was down).
    std::uint64_t connection = 0;
  };
  // The button's entry, its state dropped if it is from an earlier connection. Under mutex.
  Button& CurrentButton(int index) {
    Button& b = buttons[index];
    const std::uint64_t now = client->connections();
    if (b.connection != now) {
      b.pressed = false;
      b.connection = now;
    }
    return b;
  }
  std::map<int, Button> buttons;  // guarded by mutex
  // Last: destroyed first, so its thread is joined before the state its callbacks touch goes.
  std::unique_ptr<trackcal::vrpn::VrpnTrackerClient> client;
};

extern "C" {

int32_t trackcal_unity_abi_version(void) { return TRACKCAL_UNITY_ABI_VERSION; }

TrackcalUnityTracker* trackcal_unity_open(const char* vrpn_name, const char* axes) {
  last_error.clear();
  if (vrpn_name == nullptr) {
    Fail(TRACKCAL_UNITY_ERROR_ARGUMENT, "trackcal_unity_open: the VRPN name is null");
    return nullptr;
  }
  TrackcalUnityTracker* opened = nullptr;
  Guarded("trackcal_unity_open", [&]() -> int32_t {
    PinThisLibrary();
    auto tracker = std::make_unique<TrackcalUnityTracker>();
    tracker->axes = AxesOrDefault(axes);
    // Parse first: the client's constructor names a bad "Device@host" string.
    tracker->client = std::make_unique<trackcal::vrpn::VrpnTrackerClient>(vrpn_name);
    TrackcalUnityTracker* t = tracker.get();
    // The callbacks run on the client's std::thread: an exception leaving them would reach
    // std::terminate and take the whole Unity process down. A report that cannot be stored
    // (bad_alloc, a failed lock) or shown (a zero quaternion, ToUnity) is dropped instead.
    t->client->SetPoseCallback([t](const trackcal::vrpn::TrackerReport& r) noexcept {
      if (r.sensor < 0 || r.sensor > TRACKCAL_UNITY_MAX_SENSOR) return;
      try {
        const auto unity = trackcal::unity::ToUnity(t->axes, r.transmitter_from_receiver);
        std::lock_guard lock(t->mutex);
        SensorState& s = t->sensors[r.sensor];
        s.transmitter_from_receiver = r.transmitter_from_receiver;
        s.unity = unity;
        s.time_s = r.time.Seconds();
        s.arrived = SteadyClock::now();
        ++s.reports;
      } catch (...) {
      }
    });
    t->client->SetMessageCallback([t](const trackcal::vrpn::ReceivedMessage& m) noexcept {
      try {
        if (m.type == trackcal::vrpn::kTextType) {
          const auto text = trackcal::vrpn::DecodeText(m.payload);
          if (!text) return;
          std::lock_guard lock(t->mutex);
          t->text = text->text;
          t->text_severity = static_cast<int32_t>(text->severity);
          ++t->texts;
        } else if (m.type == trackcal::vrpn::kButtonChangeType) {
          const auto change = trackcal::vrpn::DecodeButtonChange(m.payload);
          if (!change || change->button < 0 || change->button > TRACKCAL_UNITY_MAX_SENSOR) return;
          std::lock_guard lock(t->mutex);
          auto& b = t->CurrentButton(change->button);
          if (change->state != 0 && !b.pressed) ++b.presses;
          b.pressed = change->state != 0;
        } else if (m.type == trackcal::vrpn::kButtonStatesType) {
          // Sent on connect: the states as they are, not presses seen.
          const auto states = trackcal::vrpn::DecodeButtonStates(m.payload);
          if (!states) return;
          std::lock_guard lock(t->mutex);
          for (std::size_t i = 0; i < states->size() && i <= TRACKCAL_UNITY_MAX_SENSOR; ++i) {
            t->CurrentButton(static_cast<int>(i)).pressed = (*states)[i] != 0;
          }
        }
      } catch (...) {
      }
    });
    t->client->Start();
    opened = tracker.release();
    return TRACKCAL_UNITY_OK;
  });
  return opened;
}

void trackcal_unity_close(TrackcalUnityTracker* tracker) {
  last_error.clear();
  if (tracker == nullptr) return;
  try {
    tracker->client->Stop();
  } catch (...) {
    // The thread is joined or was never started; nothing else to undo.
  }
  delete tracker;
}

int32_t trackcal_unity_get_pose(TrackcalUnityTracker* tracker, int32_t sensor,
                                TrackcalUnityPose* out) {
  last_error.clear();
  if (tracker == nullptr || out == nullptr) {
    return Fail(TRACKCAL_UNITY_ERROR_ARGUMENT, "trackcal_unity_get_pose: null handle or output");
  }
  std::memset(out, 0, sizeof(*out));
  out->sensor = sensor;
  return Guarded("trackcal_unity_get_pose", [&]() -> int32_t {
    if (const int32_t rc = CheckIndex("trackcal_unity_get_pose", "sensor", sensor); rc != 0) {
      return rc;
    }
    std::lock_guard lock(tracker->mutex);
    const auto it = tracker->sensors.find(sensor);
    if (it == tracker->sensors.end()) return TRACKCAL_UNITY_NO_POSE;
    const SensorState& s = it->second;
    out->valid = 1;
    out->reports = s.reports;
    out->unity_px = s.unity.position.x();
    out->unity_py = s.unity.position.y();
    out->unity_pz = s.unity.position.z();
    out->unity_qx = s.unity.rotation.x();
    out->unity_qy = s.unity.rotation.y();
    out->unity_qz = s.unity.rotation.z();
    out->unity_qw = s.unity.rotation.w();
    out->tracker_px = s.transmitter_from_receiver.translation.x();
    out->tracker_py = s.transmitter_from_receiver.translation.y();
    out->tracker_pz = s.transmitter_from_receiver.translation.z();
    out->tracker_qx = s.transmitter_from_receiver.rotation.x();
    out->tracker_qy = s.transmitter_from_receiver.rotation.y();
    out->tracker_qz = s.transmitter_from_receiver.rotation.z();
    out->tracker_qw = s.transmitter_from_receiver.rotation.w();
    out->time_s = s.time_s;
    out->age_s = std::chrono::duration<double>(SteadyClock::now() - s.arrived).count();
    return TRACKCAL_UNITY_OK;
  });
}

int32_t trackcal_unity_get_status(TrackcalUnityTracker* tracker, TrackcalUnityStatus* out) {
  last_error.clear();
  if (tracker == nullptr || out == nullptr) {
    return Fail(TRACKCAL_UNITY_ERROR_ARGUMENT, "trackcal_unity_get_status: null handle or output");
  }
  std::memset(out, 0, sizeof(*out));
  return Guarded("trackcal_unity_get_status", [&]() -> int32_t {
    out->connected = tracker->client->connected() ? 1 : 0;
    out->device_served = tracker->client->pong_received() ? 1 : 0;
    out->udp = tracker->client->udp_active() ? 1 : 0;
    out->reports = tracker->client->reports();
    out->connections = tracker->client->connections();
    std::lock_guard lock(tracker->mutex);
    out->texts = tracker->texts;
    return TRACKCAL_UNITY_OK;
  });
}

int32_t trackcal_unity_get_button(TrackcalUnityTracker* tracker, int32_t index, int32_t* pressed,
                                  uint64_t* presses) {
  last_error.clear();
  if (tracker == nullptr || pressed == nullptr || presses == nullptr) {
    return Fail(TRACKCAL_UNITY_ERROR_ARGUMENT, "trackcal_unity_get_button: null handle or output");
  }
  *pressed = 0;
  *presses = 0;
  return Guarded("trackcal_unity_get_button", [&]() -> int32_t {
    if (const int32_t rc = CheckIndex("trackcal_unity_get_button", "button", index); rc != 0) {
      return rc;
    }
    std::lock_guard lock(tracker->mutex);
    const auto it = tracker->buttons.find(index);
    if (it == tracker->buttons.end()) return TRACKCAL_UNITY_NO_BUTTON;
    // Not pressed while the connection is down or before this connection's states arrived: a
    // stylus held when the link dropped would otherwise stay pressed until a reconnect.
    const bool current =
        tracker->client->connected() && it->second.connection == tracker->client->connections();
    *pressed = current && it->second.pressed ? 1 : 0;
    *presses = it->second.presses;
    return TRACKCAL_UNITY_OK;
  });
}

int32_t trackcal_unity_last_text(TrackcalUnityTracker* tracker, char* buffer, int32_t buffer_size,
                                 int32_t* severity) {
  last_error.clear();
  if (tracker == nullptr || (buffer == nullptr && buffer_size > 0) || buffer_size < 0) {
    return Fail(TRACKCAL_UNITY_ERROR_ARGUMENT,
                "trackcal_unity_last_text: null handle or bad buffer");
  }
  return Guarded("trackcal_unity_last_text", [&]() -> int32_t {
    std::lock_guard lock(tracker->mutex);
    if (buffer_size > 0) {
      std::size_t n = std::min(tracker->text.size(), static_cast<std::size_t>(buffer_size - 1));
      // A cut backs off to the start of a UTF-8 character, so the caller never decodes half of one.
      if (n < tracker->text.size()) {
        while (n > 0 && (static_cast<unsigned char>(tracker->text[n]) & 0xc0) == 0x80) --n;
      }
      std::memcpy(buffer, tracker->text.data(), n);
      buffer[n] = '\0';
    }
    if (severity != nullptr) *severity = tracker->text_severity;
    return static_cast<int32_t>(std::min<std::size_t>(tracker->text.size(), INT32_MAX));
  });
}

int32_t trackcal_unity_convert(const char* axes, const double tracker_p[3],
                               const double tracker_q_xyzw[4], double unity_p[3],
                               double unity_q_xyzw[4]) {
  last_error.clear();
  if (tracker_p == nullptr || tracker_q_xyzw == nullptr || unity_p == nullptr ||
      unity_q_xyzw == nullptr) {
    return Fail(TRACKCAL_UNITY_ERROR_ARGUMENT, "trackcal_unity_convert: null array");
  }
  return Guarded("trackcal_unity_convert", [&]() -> int32_t {
    const Rigid3d pose(trackcal::QuaternionFromXyzwArray(tracker_q_xyzw),
                       Eigen::Vector3d(tracker_p[0], tracker_p[1], tracker_p[2]));
    const auto unity = trackcal::unity::ToUnity(AxesOrDefault(axes), pose);
    for (int i = 0; i < 3; ++i) unity_p[i] = unity.position[i];
    unity_q_xyzw[0] = unity.rotation.x();
    unity_q_xyzw[1] = unity.rotation.y();
    unity_q_xyzw[2] = unity.rotation.z();
    unity_q_xyzw[3] = unity.rotation.w();
    return TRACKCAL_UNITY_OK;
  });
}

const char* trackcal_unity_last_error(void) { return last_error.c_str(); }

}  // extern "C"
