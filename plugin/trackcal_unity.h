/* trackcal's native plugin for Unity: a C ABI over trackcal's VRPN tracker client.
 *
 * One handle per VRPN tracker name ("Tracker0@host", "Tracker0@host:3883",
 * "Tracker0@tcp://host:port"). The handle connects, reconnects after a lost server and decodes
 * Pos_Quat reports on its own thread; trackcal_unity_get_pose() copies the latest pose of a sensor,
 * so Unity's main thread never blocks on the network. Poses come in two frames: the tracker's, as
 * served (metres, right-handed), and Unity's (metres, left-handed, y up), converted by the axis
 * mapping given to trackcal_unity_open() (plugin/unity_axes.h, docs/unity.md).
 *
 * A trackcal server serves the corrected tracker under its configured name and, when the config
 * asks for it, the raw one under a second name: open both to compare them live.
 *
 * Every function is safe to call from any thread; one handle may be shared, except that
 * trackcal_unity_close() must not overlap another call on the same handle (it frees it). No
 * function throws or aborts on bad input: it returns an error code and trackcal_unity_last_error()
 * says why. */
#ifndef TRACKCAL_PLUGIN_TRACKCAL_UNITY_H_
#define TRACKCAL_PLUGIN_TRACKCAL_UNITY_H_

#include <stdint.h>

#if defined(_WIN32)
#define TRACKCAL_UNITY_API __declspec(dllexport)
#else
#define TRACKCAL_UNITY_API __attribute__((visibility("default")))
#endif

#ifdef __cplusplus
extern "C" {
#endif

/* Bumped when a struct layout or a signature changes; the C# wrapper checks it. */
#define TRACKCAL_UNITY_ABI_VERSION 1

/* Largest sensor index a handle keeps (a Fastrak has 4 stations, served as sensors 0-3). */
#define TRACKCAL_UNITY_MAX_SENSOR 255

typedef struct TrackcalUnityTracker TrackcalUnityTracker;

/* Plain fields only (no arrays), so C# marshals it as a blittable struct of the same layout. */
typedef struct TrackcalUnityPose {
  int32_t sensor;
  int32_t valid;    /* 1 once this sensor has reported; the fields below are 0 before */
  uint64_t reports; /* reports received for this sensor since the handle was opened */
  /* Unity's axes: metres; rotation x, y, z, w. */
  double unity_px, unity_py, unity_pz;
  double unity_qx, unity_qy, unity_qz, unity_qw;
  /* The tracker's frame, as served: transmitter_from_receiver, metres; rotation x, y, z, w. */
  double tracker_px, tracker_py, tracker_pz;
  double tracker_qx, tracker_qy, tracker_qz, tracker_qw;
  double time_s; /* the server's timestamp of the report (seconds since the Unix epoch) */
  double age_s;  /* seconds since the report arrived here, at the time of the call */
} TrackcalUnityPose;

typedef struct TrackcalUnityStatus {
  int32_t connected;     /* the VRPN connection is up (cookie exchanged) */
  int32_t device_served; /* the server answered a ping for this device name */
  int32_t udp;           /* reports arrive over the UDP data channel */
  int32_t reserved;
  uint64_t reports;     /* Pos_Quat reports received, every sensor */
  /* TCP connections made (1 after the first, more after reconnects), counted before the VRPN
   * handshake: a peer that accepts and never completes it (a stopped server) adds one per attempt
   * while connected stays 0. */
  uint64_t connections;
  uint64_t texts;       /* text messages the server sent for this device */
} TrackcalUnityStatus;

enum {
  TRACKCAL_UNITY_OK = 0,
  TRACKCAL_UNITY_NO_POSE = 1,         /* trackcal_unity_get_pose: nothing from this sensor yet */
  TRACKCAL_UNITY_NO_BUTTON = 1,       /* trackcal_unity_get_button: nothing about this button yet */
  TRACKCAL_UNITY_ERROR_ARGUMENT = -1, /* a null pointer, a bad name, axes or sensor index */
  TRACKCAL_UNITY_ERROR_INTERNAL =
      -2 /* an unexpected failure; trackcal_unity_last_error() says it */
};

TRACKCAL_UNITY_API int32_t trackcal_unity_abi_version(void);

/* Axes: Unity's x, y, z as tracker axes, e.g. "y,-z,x"; NULL or "" takes that default (the
 * Polhemus source frame, x forward, y right, z down). Returns NULL on error. */
TRACKCAL_UNITY_API TrackcalUnityTracker* trackcal_unity_open(const char* vrpn_name,
                                                             const char* axes);

/* Stops the network thread and frees the handle. NULL is allowed. Returns at once (the thread is
 * woken from its wait; well under a frame): a host-name lookup still in progress finishes on its
 * own thread. */
TRACKCAL_UNITY_API void trackcal_unity_close(TrackcalUnityTracker* tracker);

/* TRACKCAL_UNITY_OK and *out filled, TRACKCAL_UNITY_NO_POSE (out->valid = 0), or an error. */
TRACKCAL_UNITY_API int32_t trackcal_unity_get_pose(TrackcalUnityTracker* tracker, int32_t sensor,
                                                   TrackcalUnityPose* out);

TRACKCAL_UNITY_API int32_t trackcal_unity_get_status(TrackcalUnityTracker* tracker,
                                                     TrackcalUnityStatus* out);

/* The last text message the server sent for this device ("resetting the tracker", ...), written
 * NUL-terminated and cut to at most buffer_size bytes (never inside a UTF-8 character). Returns its
 * full length in bytes (0: none yet), or an error. *severity: 0 normal, 1 warning, 2 error. */
TRACKCAL_UNITY_API int32_t trackcal_unity_last_text(TrackcalUnityTracker* tracker, char* buffer,
                                                    int32_t buffer_size, int32_t* severity);

/* A button of a VRPN button device, opened like a tracker: a Fastrak stylus is served as a device
 * of its own (vrpn.cfg's stylus line, e.g. "Stylus0@host"). *pressed: 1 pressed, 0 released or
 * the connection down (a state from an earlier connection is not reported);
 * *presses: presses seen since the handle was opened, so a press and release between two frames is
 * not lost. TRACKCAL_UNITY_OK, TRACKCAL_UNITY_NO_BUTTON (nothing about it yet: *pressed = 0,
 * *presses = 0), or an error (an index outside 0..TRACKCAL_UNITY_MAX_SENSOR). */
TRACKCAL_UNITY_API int32_t trackcal_unity_get_button(TrackcalUnityTracker* tracker, int32_t index,
                                                     int32_t* pressed, uint64_t* presses);

/* Converts one pose as trackcal_unity_get_pose() does (tests, tools, poses from elsewhere). */
TRACKCAL_UNITY_API int32_t trackcal_unity_convert(const char* axes, const double tracker_p[3],
                                                  const double tracker_q_xyzw[4], double unity_p[3],
                                                  double unity_q_xyzw[4]);

/* Why the last failing call on this thread failed (empty after a success). Valid until the
 * thread's next call. */
TRACKCAL_UNITY_API const char* trackcal_unity_last_error(void);

#ifdef __cplusplus
}
#endif

#endif /* TRACKCAL_PLUGIN_TRACKCAL_UNITY_H_ */
