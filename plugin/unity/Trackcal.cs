// trackcal's C# wrapper for Unity: reads VRPN trackers (a trackcal server's corrected ones, or any
// VRPN tracker) through the native plugin libtrackcal_unity (plugin/trackcal_unity.h), with poses
// in Unity's left-handed, y-up axes. No UnityEngine dependency here: TrackcalTrackedObject.cs is
// the MonoBehaviour. docs/unity.md says how to install and which axes to choose.
using System;
using System.Collections.Generic;
using System.Runtime.InteropServices;
using System.Text;

namespace Trackcal
{
    // One sensor's latest pose. The field layout is TrackcalUnityPose's in trackcal_unity.h.
    [StructLayout(LayoutKind.Sequential)]
    public struct TrackcalPose
    {
        public int Sensor;
        public int Valid;         // 1 once the sensor has reported
        public ulong Reports;     // reports received for this sensor
        // Unity's axes: metres; rotation x, y, z, w.
        public double UnityPx, UnityPy, UnityPz;
        public double UnityQx, UnityQy, UnityQz, UnityQw;
        // The tracker's frame, as served (right-handed): metres; rotation x, y, z, w.
        public double TrackerPx, TrackerPy, TrackerPz;
        public double TrackerQx, TrackerQy, TrackerQz, TrackerQw;
        public double TimeSeconds; // the server's timestamp (seconds since the Unix epoch)
        public double AgeSeconds;  // seconds since the report arrived, when it was read
    }

    // The layout of TrackcalUnityStatus.
    [StructLayout(LayoutKind.Sequential)]
    public struct TrackcalStatus
    {
        public int Connected;     // the VRPN connection is up
        public int DeviceServed;  // the server answered for this device name
        public int Udp;           // reports arrive over UDP
        public int Reserved;
        public ulong Reports;
        public ulong Connections; // TCP connections made, counted before the VRPN handshake
        public ulong Texts;
    }

    // The native handle. The marshaller AddRefs a SafeHandle for the duration of each call, so
    // neither Dispose on another thread nor the finalizer (which can run while a call on the
    // object is still in native code: `this` is dead once Handle() returned) can free the
    // tracker under a running trackcal_unity_get_pose; ReleaseHandle runs exactly once.
    internal sealed class TrackcalHandle : SafeHandle
    {
        private TrackcalHandle() : base(IntPtr.Zero, true) { }

        public override bool IsInvalid { get { return handle == IntPtr.Zero; } }

        protected override bool ReleaseHandle()
        {
            TrackcalNative.Close(handle);
            return true;
        }
    }

    // Every import is Cdecl, the C functions' convention: DllImport's default (Winapi) is stdcall on
    // 32-bit Windows, where the caller then expects the callee to pop the arguments and a cdecl
    // callee does not (an unbalanced stack). On x86_64 and Linux the two are the same.
    internal static class TrackcalNative
    {
        internal const string Library = "trackcal_unity";

        [DllImport(Library, EntryPoint = "trackcal_unity_abi_version",
                   CallingConvention = CallingConvention.Cdecl)]
        internal static extern int AbiVersion();

        // Strings cross as NUL-terminated UTF-8 byte arrays (Utf8): LPStr would use the ANSI code
        // page on Windows, and UTF-8 string marshalling is not on every Unity runtime.
        [DllImport(Library, EntryPoint = "trackcal_unity_open",
                   CallingConvention = CallingConvention.Cdecl)]
        internal static extern TrackcalHandle Open(byte[] vrpnNameUtf8, byte[] axesUtf8);

        [DllImport(Library, EntryPoint = "trackcal_unity_close",
                   CallingConvention = CallingConvention.Cdecl)]
        internal static extern void Close(IntPtr tracker);

        [DllImport(Library, EntryPoint = "trackcal_unity_get_pose",
                   CallingConvention = CallingConvention.Cdecl)]
        internal static extern int GetPose(TrackcalHandle tracker, int sensor, out TrackcalPose pose);

        [DllImport(Library, EntryPoint = "trackcal_unity_get_status",
                   CallingConvention = CallingConvention.Cdecl)]
        internal static extern int GetStatus(TrackcalHandle tracker, out TrackcalStatus status);

        [DllImport(Library, EntryPoint = "trackcal_unity_get_button",
                   CallingConvention = CallingConvention.Cdecl)]
        internal static extern int GetButton(TrackcalHandle tracker, int index, out int pressed,
                                             out ulong presses);

        [DllImport(Library, EntryPoint = "trackcal_unity_last_text",
                   CallingConvention = CallingConvention.Cdecl)]
        internal static extern int LastText(TrackcalHandle tracker, [Out] byte[] buffer, int bufferSize,
                                            out int severity);

        [DllImport(Library, EntryPoint = "trackcal_unity_convert",
                   CallingConvention = CallingConvention.Cdecl)]
        internal static extern int Convert(byte[] axesUtf8, double[] trackerP, double[] trackerQXyzw,
                                           [Out] double[] unityP, [Out] double[] unityQXyzw);

        [DllImport(Library, EntryPoint = "trackcal_unity_last_error",
                   CallingConvention = CallingConvention.Cdecl)]
        internal static extern IntPtr LastErrorPtr();

        // null stays null (the plugin's default axes).
        internal static byte[] Utf8(string text)
        {
            return text == null ? null : Encoding.UTF8.GetBytes(text + "\0");
        }

        internal static string LastError()
        {
            IntPtr p = LastErrorPtr();
            if (p == IntPtr.Zero) return "";
            int length = 0;
            while (Marshal.ReadByte(p, length) != 0) length++;
            byte[] bytes = new byte[length];
            Marshal.Copy(p, bytes, 0, length);
            return Encoding.UTF8.GetString(bytes);
        }
    }

    // One VRPN tracker ("Tracker0@host", "Tracker0@host:3883", "Tracker0@tcp://host:port"). The
    // plugin connects, reconnects and decodes on its own thread; TryGetPose never blocks.
    public sealed class TrackcalTracker : IDisposable
    {
        public const int AbiVersion = 1;               // TRACKCAL_UNITY_ABI_VERSION
        public const string DefaultAxes = "y,-z,x";    // the Polhemus source frame in Unity

        private readonly TrackcalHandle handle;
        private readonly object textLock = new object();
        private byte[] textBytes = new byte[512];      // LastText's read buffer, kept between calls
        private byte[] textDecoded = new byte[512];    // the bytes `text` was decoded from
        private int textDecodedLength = 0;
        private string text = "";

        public string VrpnName { get; private set; }
        public string Axes { get; private set; }

        // axes: Unity's x, y, z as tracker axes ("y,-z,x"); null for the default. Throws
        // ArgumentException with the plugin's reason (a bad name or axes), or
        // InvalidOperationException when the native library is of another ABI version.
        public TrackcalTracker(string vrpnName, string axes = DefaultAxes)
        {
            CheckAbi();
            handle = TrackcalNative.Open(TrackcalNative.Utf8(vrpnName), TrackcalNative.Utf8(axes));
            if (handle.IsInvalid)
                throw new ArgumentException(TrackcalNative.LastError());
            VrpnName = vrpnName;
            Axes = axes ?? DefaultAxes;
        }

        public static void CheckAbi()
        {
            int native = TrackcalNative.AbiVersion();
            if (native != AbiVersion)
                throw new InvalidOperationException("libtrackcal_unity has ABI version " + native +
                                                    ", this wrapper expects " + AbiVersion +
                                                    ": copy Trackcal.cs from the same trackcal build");
        }

        // False until the sensor has reported. Throws ArgumentException for a bad sensor index.
        public bool TryGetPose(int sensor, out TrackcalPose pose)
        {
            int rc = TrackcalNative.GetPose(Handle(), sensor, out pose);
            if (rc < 0) throw new ArgumentException(TrackcalNative.LastError());
            return rc == 0;
        }

        public TrackcalStatus Status
        {
            get
            {
                TrackcalStatus status;
                if (TrackcalNative.GetStatus(Handle(), out status) < 0)
                    throw new InvalidOperationException(TrackcalNative.LastError());
                return status;
            }
        }

        // A button of a button device opened like a tracker ("Stylus0@host": a Fastrak stylus is
        // served as a device of its own). False until the server has said anything about it.
        // presses counts presses since this tracker was opened (across reconnects; a shared tracker
        // may be older than its reader), so a press shorter than a frame is not lost. pressed is
        // false while the connection is down. Throws ArgumentException for an index outside 0..255.
        public bool TryGetButton(int index, out bool pressed, out ulong presses)
        {
            int state;
            int rc = TrackcalNative.GetButton(Handle(), index, out state, out presses);
            if (rc < 0) throw new ArgumentException(TrackcalNative.LastError());
            pressed = state != 0;
            return rc == 0;
        }

        // The server's last text for this device ("" if none); severity 0 normal, 1 warning, 2 error.
        // Called every frame, it allocates nothing while the text is unchanged: the bytes are read
        // into a buffer kept between calls and the string is decoded only when they change.
        public string LastText(out int severity)
        {
            lock (textLock)
            {
                int length = TrackcalNative.LastText(Handle(), textBytes, textBytes.Length, out severity);
                if (length < 0) throw new InvalidOperationException(TrackcalNative.LastError());
                if (length >= textBytes.Length)
                {
                    textBytes = new byte[length + 1];
                    length = TrackcalNative.LastText(Handle(), textBytes, textBytes.Length, out severity);
                    if (length < 0) throw new InvalidOperationException(TrackcalNative.LastError());
                }
                // A text that grew between the two calls comes cut at a character boundary, so
                // shorter than its length: it ends at its NUL.
                length = Math.Min(length, textBytes.Length - 1);
                int nul = Array.IndexOf(textBytes, (byte)0, 0, length);
                if (nul >= 0) length = nul;
                if (!SameBytes(textBytes, length, textDecoded))
                {
                    if (textDecoded.Length < length) textDecoded = new byte[textBytes.Length];
                    Buffer.BlockCopy(textBytes, 0, textDecoded, 0, length);
                    textDecodedLength = length;
                    text = Encoding.UTF8.GetString(textBytes, 0, length);
                }
                return text;
            }
        }

        private bool SameBytes(byte[] bytes, int length, byte[] decoded)
        {
            if (length != textDecodedLength) return false;
            for (int i = 0; i < length; i++)
            {
                if (bytes[i] != decoded[i]) return false;
            }
            return true;
        }

        // A tracker-frame pose in Unity's axes, as TryGetPose converts it.
        public static void Convert(string axes, double[] trackerP, double[] trackerQXyzw,
                                   double[] unityP, double[] unityQXyzw)
        {
            // The native side reads 3 and 4 doubles and writes as many: a shorter array is memory
            // corruption, not an error code.
            CheckLength(trackerP, 3, "trackerP");
            CheckLength(trackerQXyzw, 4, "trackerQXyzw");
            CheckLength(unityP, 3, "unityP");
            CheckLength(unityQXyzw, 4, "unityQXyzw");
            if (TrackcalNative.Convert(TrackcalNative.Utf8(axes), trackerP, trackerQXyzw, unityP,
                                       unityQXyzw) < 0)
                throw new ArgumentException(TrackcalNative.LastError());
        }

        private static void CheckLength(double[] a, int n, string name)
        {
            if (a == null || a.Length < n)
                throw new ArgumentException(name + ": " + n + " values expected", name);
        }

        // Disposed (closed): TrackcalConnections hands out a new tracker for its name instead.
        public bool IsDisposed
        {
            get { return handle.IsClosed; }
        }

        private TrackcalHandle Handle()
        {
            if (handle.IsClosed) throw new ObjectDisposedException("TrackcalTracker " + VrpnName);
            return handle;
        }

        // Closes the connection (joins the plugin's network thread). The SafeHandle's own finalizer
        // closes a tracker that was never disposed.
        public void Dispose()
        {
            handle.Dispose();
        }
    }

    // One TrackcalTracker per (VRPN name, axes) for every component that reads it: two objects on
    // the sensors of one tracker, or a stylus button beside them, share a connection. Acquire and
    // Release pair up; the last Release disposes the tracker. Do not Dispose an acquired tracker
    // (Release it): if a script does, the next Acquire opens a new one, and the components holding
    // the old one acquire again (Renew).
    public static class TrackcalConnections
    {
        private sealed class Shared
        {
            public TrackcalTracker Tracker;
            public int Users;
        }

        private static readonly Dictionary<string, Shared> shared = new Dictionary<string, Shared>();

        // Open connections, for status displays and tests.
        public static int Count
        {
            get { lock (shared) return shared.Count; }
        }

        // "Y, -Z, +x" and "y,-z,x" (and "" and null, the default) are one mapping: one connection.
        // A '+' is dropped only as an item's sign before an axis, as the plugin reads it: "x+" or
        // "+-x" stays as typed, so it cannot share (or open) a connection the plugin would refuse.
        public static string NormalizedAxes(string axes)
        {
            if (IsBlank(axes)) return TrackcalTracker.DefaultAxes;
            var sb = new StringBuilder();
            foreach (char c in axes)
                if (!char.IsWhiteSpace(c)) sb.Append(char.ToLowerInvariant(c));
            for (int i = sb.Length - 2; i >= 0; i--)
            {
                bool itemStart = i == 0 || sb[i - 1] == ',';
                char next = sb[i + 1];
                if (sb[i] == '+' && itemStart && next >= 'x' && next <= 'z') sb.Remove(i, 1);
            }
            return sb.ToString();
        }

        private static bool IsBlank(string axes)
        {
            return axes == null || axes.Trim().Length == 0;
        }

        // Throws what TrackcalTracker's constructor throws (a bad name or axes).
        public static TrackcalTracker Acquire(string vrpnName, string axes)
        {
            string normalized = NormalizedAxes(axes);
            string key = vrpnName + "\n" + normalized;
            lock (shared)
            {
                Shared s;
                // A tracker disposed by a script while held is replaced; its holders' Releases no
                // longer match it and are ignored.
                if (!shared.TryGetValue(key, out s) || s.Tracker.IsDisposed)
                {
                    // The text as typed: the plugin's error then quotes what the user wrote.
                    s = new Shared { Tracker = new TrackcalTracker(vrpnName,
                                                                   IsBlank(axes) ? null : axes) };
                    shared[key] = s;
                }
                s.Users++;
                return s.Tracker;
            }
        }

        // The tracker itself while it is open; else releases it and acquires a new one for the
        // same name and axes (a script disposed the shared tracker).
        public static TrackcalTracker Renew(TrackcalTracker tracker)
        {
            if (tracker == null || !tracker.IsDisposed) return tracker;
            Release(tracker);
            return Acquire(tracker.VrpnName, tracker.Axes);
        }

        public static void Release(TrackcalTracker tracker)
        {
            if (tracker == null) return;
            lock (shared)
            {
                string key = tracker.VrpnName + "\n" + NormalizedAxes(tracker.Axes);
                Shared s;
                if (!shared.TryGetValue(key, out s) || s.Tracker != tracker) return;
                if (--s.Users == 0)
                {
                    s.Tracker.Dispose();
                    shared.Remove(key);
                }
            }
        }
    }
}
