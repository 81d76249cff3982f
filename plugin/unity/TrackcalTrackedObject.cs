// Drives a GameObject's local pose from one sensor of a VRPN tracker, in Unity's axes. Put the
// object under a parent that places the tracker's source (transmitter) in the scene: the plugin's
// poses are the receiver in the source's frame. Objects reading the same tracker name and axes share
// one connection.
#if UNITY_5_3_OR_NEWER
using System;
using System.Collections.Generic;
using UnityEngine;

namespace Trackcal
{
    public class TrackcalTrackedObject : MonoBehaviour
    {
        [Tooltip("VRPN name: Tracker0@host, Tracker0@host:port or Tracker0@tcp://host:port. A trackcal " +
                 "server serves the corrected tracker under its configured name and the raw one under raw=.")]
        public string trackerName = "Tracker0@localhost";

        [Tooltip("Sensor index (a Fastrak's stations 1-4 are sensors 0-3).")]
        public int sensor = 0;

        [Tooltip("Unity's x, y, z as tracker axes. y,-z,x: the Polhemus source frame " +
                 "(x forward, y right, z down).")]
        public string axes = TrackcalTracker.DefaultAxes;

        public bool applyPosition = true;
        public bool applyRotation = true;

        [Tooltip("A pose older than this is not applied (the object holds its last pose) and " +
                 "IsTracking is false.")]
        public float maxAgeSeconds = 0.5f;

        public bool IsTracking { get; private set; }
        public TrackcalPose LastPose { get; private set; }

        private sealed class Shared
        {
            public TrackcalTracker Tracker;
            public int Users;
        }

        private static readonly Dictionary<string, Shared> shared = new Dictionary<string, Shared>();
        private Shared connection;
        private string key;

        // Open connections (tracker name and axes), for status displays and tests.
        public static int SharedConnections
        {
            get { lock (shared) return shared.Count; }
        }

        // TRACKCAL_UNITY_MAX_SENSOR: the plugin refuses a larger index.
        public const int MaxSensor = 255;

        // "Y, -Z, +x" and "y,-z,x" (and "" and null, the default) are one mapping: one connection.
        private static string NormalizedAxes(string axes)
        {
            if (string.IsNullOrEmpty(axes) || axes.Trim().Length == 0) return TrackcalTracker.DefaultAxes;
            var sb = new System.Text.StringBuilder();
            foreach (char c in axes)
                if (!char.IsWhiteSpace(c) && c != '+') sb.Append(char.ToLowerInvariant(c));
            return sb.ToString();
        }

        private bool SensorValid()
        {
            if (sensor >= 0 && sensor <= MaxSensor) return true;
            Debug.LogError("trackcal: " + name + ": sensor " + sensor + " is outside 0.." + MaxSensor);
            enabled = false;
            return false;
        }

        private void OnEnable()
        {
            if (!SensorValid()) return;
            string normalized = NormalizedAxes(axes);
            key = trackerName + "\n" + normalized;
            lock (shared)
            {
                if (!shared.TryGetValue(key, out connection))
                {
                    try
                    {
                        connection = new Shared { Tracker = new TrackcalTracker(trackerName, normalized) };
                    }
                    catch (Exception e)
                    {
                        Debug.LogError("trackcal: " + name + ": " + e.Message);
                        connection = null;
                        enabled = false;
                        return;
                    }
                    shared[key] = connection;
                }
                connection.Users++;
            }
        }

        private void OnDisable()
        {
            IsTracking = false;
            if (connection == null) return;
            lock (shared)
            {
                if (--connection.Users == 0)
                {
                    connection.Tracker.Dispose();
                    shared.Remove(key);
                }
            }
            connection = null;
        }

        private void Update()
        {
            IsTracking = false;
            if (connection == null) return;
            // Changed in the Inspector while playing: an exception every frame otherwise.
            if (!SensorValid()) return;
            TrackcalPose pose;
            if (!connection.Tracker.TryGetPose(sensor, out pose)) return;
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
}
#endif
