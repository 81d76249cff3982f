// Drives a GameObject's local pose from one sensor of a VRPN tracker, in Unity's axes. Put the
// object under a parent that places the tracker's source (transmitter) in the scene: the plugin's
// poses are the receiver in the source's frame. Objects reading the same tracker name and axes share
// one connection.
#if UNITY_5_3_OR_NEWER
using System;
using UnityEngine;

namespace Trackcal
{
    public class TrackcalTrackedObject : MonoBehaviour
    {
        [Tooltip("VRPN name: Tracker0@host, Tracker0@host:port or Tracker0@tcp://host:port. A trackcal " +
                 "server serves the corrected tracker under its configured name and the raw one under raw=.")]
#if UNITY_5_4_OR_NEWER
        [Delayed]  // a change made while playing takes effect on Enter, not on every keystroke
#endif
        public string trackerName = "Tracker0@localhost";

        [Tooltip("Sensor index (a Fastrak's stations 1-4 are sensors 0-3).")]
        public int sensor = 0;

        [Tooltip("Unity's x, y, z as tracker axes. y,-z,x: the Polhemus source frame " +
                 "(x forward, y right, z down).")]
#if UNITY_5_4_OR_NEWER
        [Delayed]
#endif
        public string axes = TrackcalTracker.DefaultAxes;

        public bool applyPosition = true;
        public bool applyRotation = true;

        [Tooltip("A pose older than this is not applied (the object holds its last pose) and " +
                 "IsTracking is false.")]
        public float maxAgeSeconds = 0.5f;

        public bool IsTracking { get; private set; }
        public TrackcalPose LastPose { get; private set; }

        private TrackcalTracker tracker;
        // The name and axes the tracker was acquired for: changed while playing, they are reopened.
        private string acquiredName, acquiredAxes;

        // Open connections (TrackcalConnections.Count), for status displays and tests.
        public static int SharedConnections
        {
            get { return TrackcalConnections.Count; }
        }

        // TRACKCAL_UNITY_MAX_SENSOR: the plugin refuses a larger index.
        public const int MaxSensor = 255;

        private bool SensorValid()
        {
            return TrackcalComponents.IndexValid(this, "sensor", sensor);
        }

        private void OnEnable()
        {
            if (!SensorValid()) return;
            acquiredName = trackerName;
            acquiredAxes = axes;
            tracker = TrackcalComponents.Acquire(this, trackerName, axes);
        }

        private void OnDisable()
        {
            IsTracking = false;
            TrackcalConnections.Release(tracker);
            tracker = null;
        }

        private void Update()
        {
            IsTracking = false;
            if (tracker == null) return;
            // Changed in the Inspector while playing: an exception every frame otherwise.
            if (!SensorValid()) return;
            // trackerName or axes changed in the Inspector (or by a script) while playing: the object
            // kept following the old tracker and mapping while the Inspector showed the new ones.
            // String equality, no allocation per frame; a bad new value disables the component.
            if (trackerName != acquiredName || axes != acquiredAxes)
            {
                TrackcalTracker old = tracker;
                tracker = null;  // OnDisable, after a bad new value, has nothing more to release
                acquiredName = trackerName;
                acquiredAxes = axes;
                // Acquired before the old one is released: the same mapping spelt differently
                // keeps its connection rather than reconnecting.
                TrackcalTracker renewed = TrackcalComponents.Acquire(this, trackerName, axes);
                TrackcalConnections.Release(old);
                tracker = renewed;
                if (tracker == null) return;
            }
            // A script disposed the shared tracker: ObjectDisposedException every frame otherwise.
            tracker = TrackcalConnections.Renew(tracker);
            TrackcalPose pose;
            if (!tracker.TryGetPose(sensor, out pose)) return;
            LastPose = pose;
            if (pose.AgeSeconds > maxAgeSeconds) return;
            IsTracking = true;
            if (applyPosition)
                transform.localPosition = new Vector3((float)pose.UnityPx, (float)pose.UnityPy,
                                                      (float)pose.UnityPz);
            if (applyRotation)
                transform.localRotation = new Quaternion((float)pose.UnityQx, (float)pose.UnityQy,
                                                         (float)pose.UnityQz, (float)pose.UnityQw);
        }
    }

    // What TrackcalTrackedObject and TrackcalButton share: each failure is logged once and disables
    // the component, rather than an exception every frame.
    internal static class TrackcalComponents
    {
        internal static bool IndexValid(Behaviour owner, string what, int index)
        {
            if (index >= 0 && index <= TrackcalTrackedObject.MaxSensor) return true;
            Debug.LogError("trackcal: " + owner.name + ": " + what + " " + index + " is outside 0.." +
                           TrackcalTrackedObject.MaxSensor);
            owner.enabled = false;
            return false;
        }

        // The shared connection (TrackcalConnections), or null after a bad name or axes.
        internal static TrackcalTracker Acquire(Behaviour owner, string vrpnName, string axes)
        {
            try
            {
                return TrackcalConnections.Acquire(vrpnName, axes);
            }
            catch (Exception e)
            {
                Debug.LogError("trackcal: " + owner.name + ": " + e.Message);
                owner.enabled = false;
                return null;
            }
        }
    }
}
#endif
