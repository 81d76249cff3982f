// Run by plugin/foreign_clients_test, which serves known poses on loopback:
//   mono TrackcalCsharpTest.exe <vrpn name> <sensor,px,py,pz,qx,qy,qz,qw>...
// Checks, in C#, what a Unity scene relies on: the P/Invoke signatures and struct layouts against
// the native library, the poses as served, the handedness conversion (computed here independently
// of the plugin) and TrackcalTrackedObject driving a transform. Exit code 0: every check passed.
using System;
using System.Collections.Generic;
using System.Globalization;
using System.Reflection;
using System.Threading;
using Trackcal;
using UnityEngine;

public static class TrackcalCsharpTest
{
    static int failures = 0;

    static void Check(bool ok, string what)
    {
        if (!ok)
        {
            failures++;
            Console.WriteLine("FAIL: " + what);
        }
    }

    // The default axes "y,-z,x" written out: Unity (x, y, z) = (tracker y, -tracker z, tracker x).
    static double[] MapVector(double x, double y, double z) { return new[] { y, -z, x }; }

    static void Invoke(object target, string method)
    {
        target.GetType().GetMethod(method, BindingFlags.Instance | BindingFlags.NonPublic)
            .Invoke(target, null);
    }

    public static int Main(string[] args)
    {
        if (args.Length < 2)
        {
            Console.WriteLine("usage: TrackcalCsharpTest.exe <vrpn name> <sensor,px,py,pz,qx,qy,qz,qw>...");
            return 2;
        }
        string name = args[0];
        var expected = new Dictionary<int, double[]>();
        for (int i = 1; i < args.Length; i++)
        {
            string[] f = args[i].Split(',');
            var v = new double[7];
            for (int k = 0; k < 7; k++) v[k] = double.Parse(f[k + 1], CultureInfo.InvariantCulture);
            expected[int.Parse(f[0], CultureInfo.InvariantCulture)] = v;
        }

        TrackcalTracker.CheckAbi();
        // The C functions are cdecl; DllImport's default is stdcall on 32-bit Windows.
        foreach (MethodInfo m in typeof(TrackcalNative).GetMethods(BindingFlags.Static |
                                                                    BindingFlags.NonPublic))
        {
            var import = (System.Runtime.InteropServices.DllImportAttribute)Attribute.GetCustomAttribute(
                m, typeof(System.Runtime.InteropServices.DllImportAttribute));
            if (import == null) continue;
            Check(import.CallingConvention == System.Runtime.InteropServices.CallingConvention.Cdecl,
                  m.Name + ": calling convention " + import.CallingConvention + ", not Cdecl");
        }
        Check(Marshal_SizeOf<TrackcalPose>() == 16 + 16 * 8, "TrackcalPose is 144 bytes as in C");
        Check(Marshal_SizeOf<TrackcalStatus>() == 16 + 3 * 8, "TrackcalStatus is 40 bytes as in C");

        // A bad mapping is refused with the plugin's reason.
        try
        {
            new TrackcalTracker(name, "x,y,z").Dispose();
            Check(false, "axes x,y,z (a mirrored scene) accepted");
        }
        catch (ArgumentException e)
        {
            Check(e.Message.Contains("mirrored"), "the axes error says why: " + e.Message);
        }

        // The components' way in (TrackcalConnections) refuses what the plugin refuses, and the
        // error quotes the axes as typed: a '+' that is not an axis's sign ("x+", "+-x") is not
        // dropped into a valid mapping, and "X, Y, Z" is not reported as "x,y,z".
        foreach (string typed in new[] { "x+,y,-z", "+-x,y,z", "y,-z,x+", "X, Y, Z" })
        {
            try
            {
                TrackcalConnections.Release(TrackcalConnections.Acquire(name, typed));
                Check(false, "axes \"" + typed + "\" accepted by TrackcalConnections");
            }
            catch (ArgumentException e)
            {
                Check(e.Message.Contains("axes \"" + typed + "\""),
                      "the axes error quotes \"" + typed + "\": " + e.Message);
            }
        }
        Check(TrackcalConnections.Count == 0, "refused axes open no connection");
        // Spellings the plugin accepts still share one connection ("+ x": a sign, then the axis).
        TrackcalTracker spelt = TrackcalConnections.Acquire(name, " Y, - Z, + X ");
        Check(TrackcalConnections.Acquire(name, "y,-z,x") == spelt &&
              TrackcalConnections.Acquire(name, "  ") == spelt && TrackcalConnections.Count == 1,
              "equivalent spellings share one connection");
        for (int i = 0; i < 3; i++) TrackcalConnections.Release(spelt);
        Check(TrackcalConnections.Count == 0 && spelt.IsDisposed, "the spelt tracker released");

        // Text crosses as UTF-8 both ways: the name in the plugin's error is the one given.
        try
        {
            new TrackcalTracker("Tracker\u00e9\u4e00", null).Dispose();
            Check(false, "a name without @host accepted");
        }
        catch (ArgumentException e)
        {
            Check(e.Message.Contains("'Tracker\u00e9\u4e00'"),
                  "the name error quotes the name: " + e.Message);
        }

        // Convert: the common z-flip rule, (x, y, -z) and (-qx, -qy, qz, qw).
        var up = new double[3];
        var uq = new double[4];
        TrackcalTracker.Convert("x,y,-z", new[] { 1.0, 2.0, 3.0 },
                                new[] { 0.1, 0.2, 0.3, Math.Sqrt(1 - 0.14) }, up, uq);
        Check(up[0] == 1 && up[1] == 2 && up[2] == -3, "convert position");
        Check(uq[0] == -0.1 && uq[1] == -0.2 && uq[2] == 0.3, "convert rotation");
        try
        {
            TrackcalTracker.Convert("x,y,-z", new[] { 1.0, 2.0 }, new double[4], up, uq);
            Check(false, "a 2-value position accepted (the plugin would read past it)");
        }
        catch (ArgumentException) { }

        using (var tracker = new TrackcalTracker(name))
        {
            var got = new Dictionary<int, TrackcalPose>();
            DateTime end = DateTime.UtcNow.AddSeconds(20);
            while (got.Count < expected.Count && DateTime.UtcNow < end)
            {
                foreach (int s in expected.Keys)
                {
                    TrackcalPose p;
                    if (tracker.TryGetPose(s, out p)) got[s] = p;
                }
                Thread.Sleep(10);
            }
            // No text yet: "" with severity 0, and the same string each call (nothing allocated
            // per frame while the text is unchanged).
            int severity;
            string first = tracker.LastText(out severity);
            Check(first == "" && severity == 0, "no text yet: \"" + first + "\", severity " + severity);
            Check(ReferenceEquals(tracker.LastText(out severity), first), "LastText reuses its string");
            Check(got.Count == expected.Count, "poses of every sensor within 20 s (" + got.Count + " of " +
                                                   expected.Count + ")");
            foreach (var kv in got)
            {
                double[] e = expected[kv.Key];
                TrackcalPose p = kv.Value;
                string who = "sensor " + kv.Key + ": ";
                Check(p.Sensor == kv.Key && p.Valid == 1 && p.Reports >= 1, who + "header fields");
                // Doubles on the wire and through the struct: exact.
                Check(p.TrackerPx == e[0] && p.TrackerPy == e[1] && p.TrackerPz == e[2],
                      who + "tracker position");
                Check(p.TrackerQx == e[3] && p.TrackerQy == e[4] && p.TrackerQz == e[5] &&
                      p.TrackerQw == e[6], who + "tracker rotation");
                double[] mp = MapVector(e[0], e[1], e[2]);
                Check(p.UnityPx == mp[0] && p.UnityPy == mp[1] && p.UnityPz == mp[2], who + "Unity position");
                // The rotation axis is a pseudovector: det(M) = -1 negates its image.
                double[] mv = MapVector(e[3], e[4], e[5]);
                Check(p.UnityQx == -mv[0] && p.UnityQy == -mv[1] && p.UnityQz == -mv[2] && p.UnityQw == e[6],
                      who + "Unity rotation");
                Check(p.AgeSeconds >= 0 && p.AgeSeconds < 20, who + "age " + p.AgeSeconds);
            }
            TrackcalStatus status = tracker.Status;
            Check(status.Connected == 1 && status.DeviceServed == 1 &&
                  status.Reports >= (ulong)expected.Count, "status");
            TrackcalPose none;
            Check(!tracker.TryGetPose(200, out none) && none.Valid == 0, "a silent sensor has no pose");
            try
            {
                tracker.TryGetPose(-1, out none);
                Check(false, "sensor -1 accepted");
            }
            catch (ArgumentException e)
            {
                Check(e.Message.Contains("sensor -1"), "the sensor error says why: " + e.Message);
            }
            tracker.Dispose();  // and again by using: closing twice is harmless
            try
            {
                tracker.TryGetPose(0, out none);
                Check(false, "a disposed tracker answered");
            }
            catch (ObjectDisposedException) { }
        }

        // The MonoBehaviour, two objects on one tracker: one shared connection; the transform gets
        // the pose, and Unity's own rotation rule maps the receiver's points where the tracker does.
        int sensor = 0;
        foreach (int s in expected.Keys) { sensor = s; break; }
        var a = new TrackcalTrackedObject { trackerName = name, sensor = sensor, maxAgeSeconds = 5 };
        // The same mapping spelt differently is the same connection.
        var b = new TrackcalTrackedObject { trackerName = name, sensor = sensor, maxAgeSeconds = 5,
                                            axes = " Y, -Z, +x" };
        Invoke(a, "OnEnable");
        Invoke(b, "OnEnable");
        Check(TrackcalTrackedObject.SharedConnections == 1, "one connection for two objects on one tracker");
        DateTime until = DateTime.UtcNow.AddSeconds(20);
        while (!a.IsTracking && DateTime.UtcNow < until)
        {
            Invoke(a, "Update");
            Thread.Sleep(10);
        }
        Check(a.IsTracking, "the behaviour tracks within 20 s");
        if (a.IsTracking)
        {
            double[] e = expected[sensor];
            double[] t = MapVector(e[0], e[1], e[2]);
            Vector3 pos = a.transform.localPosition;
            Check(pos.x == (float)t[0] && pos.y == (float)t[1] && pos.z == (float)t[2],
                  "transform position " + pos);
            // A point of the receiver's body, 0.1 m along its tracker x: where the tracker puts it,
            // in Unity's axes, and where Unity puts it from the transform. Float math: 1e-5 m.
            double qx = e[3], qy = e[4], qz = e[5], qw = e[6];
            double[] body = { 0.1, -0.05, 0.02 };
            double cx = qy * body[2] - qz * body[1], cy = qz * body[0] - qx * body[2];
            double cz = qx * body[1] - qy * body[0];
            double dx = qy * cz - qz * cy, dy = qz * cx - qx * cz, dz = qx * cy - qy * cx;
            double[] world = { body[0] + 2 * (qw * cx + dx) + e[0], body[1] + 2 * (qw * cy + dy) + e[1],
                               body[2] + 2 * (qw * cz + dz) + e[2] };
            double[] expect = MapVector(world[0], world[1], world[2]);
            double[] mb = MapVector(body[0], body[1], body[2]);
            Vector3 r = a.transform.localRotation * new Vector3((float)mb[0], (float)mb[1], (float)mb[2]);
            double err = Math.Abs(r.x + pos.x - expect[0]) + Math.Abs(r.y + pos.y - expect[1]) +
                         Math.Abs(r.z + pos.z - expect[2]);
            Check(err < 1e-5, "Unity's rotation of a receiver point is the tracker's (error " + err + " m)");
        }
        // A pose older than maxAgeSeconds is not applied.
        a.maxAgeSeconds = -1;
        a.transform.localPosition = new Vector3(7, 7, 7);
        Invoke(a, "Update");
        Check(!a.IsTracking && a.transform.localPosition.x == 7, "a stale pose is not applied");
        // The mapping changed in the Inspector while playing: the object follows the new one (it
        // kept the old mapping, and Unity showed the new text), on a connection of its own.
        a.maxAgeSeconds = 5;
        a.axes = "x,y,-z";
        until = DateTime.UtcNow.AddSeconds(20);
        do
        {
            Invoke(a, "Update");
            Thread.Sleep(10);
        } while (!a.IsTracking && DateTime.UtcNow < until);
        {
            double[] e = expected[sensor];
            Vector3 pos = a.transform.localPosition;
            Check(a.IsTracking && pos.x == (float)e[0] && pos.y == (float)e[1] && pos.z == (float)-e[2],
                  "axes changed while playing are applied: " + pos);
            Check(TrackcalTrackedObject.SharedConnections == 2,
                  "the changed object has a connection of its own, b keeps the old one");
        }
        // Respelt, the same mapping keeps its connection: still tracking on the next frame.
        a.axes = " X, Y, -Z";
        Invoke(a, "Update");
        Check(a.IsTracking && TrackcalTrackedObject.SharedConnections == 2,
              "axes respelt while playing keep the connection");
        // A mirrored mapping typed while playing: logged once and the object disabled, its
        // connection released.
        int errorsBefore = UnityEngine.Debug.Errors.Count;
        a.axes = "x,y,z";
        Invoke(a, "Update");
        Check(!a.enabled && UnityEngine.Debug.Errors.Count == errorsBefore + 1 &&
              TrackcalTrackedObject.SharedConnections == 1,
              "bad axes typed while playing disable the object and log");
        UnityEngine.Debug.Errors.Clear();  // the checks below count from none
        Invoke(a, "OnDisable");
        Check(TrackcalTrackedObject.SharedConnections == 1, "the connection stays while an object uses it");
        Invoke(b, "OnDisable");
        Check(TrackcalTrackedObject.SharedConnections == 0, "the last object closes the connection");

        // The stylus beside the tracker: button 1 goes down and up about every 0.1 s, button 0 stays up.
        string stylusName = name.Replace("Tracker0", "Stylus0");
        var stylus = new TrackcalButton { deviceName = stylusName, button = 1 };
        var other = new TrackcalButton { deviceName = stylusName, button = 0 };
        Invoke(stylus, "OnEnable");
        Invoke(other, "OnEnable");
        Check(TrackcalTrackedObject.SharedConnections == 1, "two buttons of one device share a connection");
        int framesPressed = 0;
        DateTime stop = DateTime.UtcNow.AddSeconds(20);
        while (stylus.Presses < 2 && DateTime.UtcNow < stop)
        {
            Invoke(stylus, "Update");
            Invoke(other, "Update");
            if (stylus.PressedThisFrame) framesPressed++;
            Thread.Sleep(5);
        }
        Check(stylus.IsKnown && stylus.Presses >= 2, "stylus presses seen: " + stylus.Presses);
        Check(framesPressed >= 1 && (ulong)framesPressed <= stylus.Presses,
              "PressedThisFrame in " + framesPressed + " frames for " + stylus.Presses + " presses");
        Check(other.IsKnown && !other.IsPressed && other.Presses == 0, "button 0 known and up");
        // A script disposes the shared tracker under both components: each acquires a new one on
        // its next Update (one connection again), and the presses seen so far are kept.
        ulong before = stylus.Presses;
        TrackcalTracker held = TrackcalConnections.Acquire(stylusName, null);
        held.Dispose();
        TrackcalConnections.Release(held);
        Invoke(stylus, "Update");
        Invoke(other, "Update");
        Check(TrackcalTrackedObject.SharedConnections == 1 && stylus.Presses >= before,
              "a disposed shared tracker is replaced: " + TrackcalTrackedObject.SharedConnections +
              " connection(s), presses " + before + " -> " + stylus.Presses);
        Invoke(stylus, "OnDisable");
        Invoke(other, "OnDisable");
        Check(TrackcalTrackedObject.SharedConnections == 0, "the buttons' connection closed");
        using (var direct = new TrackcalTracker(stylusName))
        {
            bool pressed;
            ulong presses;
            try
            {
                direct.TryGetButton(256, out pressed, out presses);
                Check(false, "button 256 accepted");
            }
            catch (ArgumentException e)
            {
                Check(e.Message.Contains("button 256"), "the button error says why: " + e.Message);
            }
        }

        var bad = new TrackcalTrackedObject { trackerName = "no host name", sensor = 0 };
        Invoke(bad, "OnEnable");
        Check(!bad.enabled && UnityEngine.Debug.Errors.Count == 1,
              "a bad tracker name disables the object and logs");
        var badSensor = new TrackcalTrackedObject { trackerName = name, sensor = -1 };
        Invoke(badSensor, "OnEnable");
        Check(!badSensor.enabled && UnityEngine.Debug.Errors.Count == 2 &&
              TrackcalTrackedObject.SharedConnections == 0,
              "a sensor outside 0..255 disables the object and logs, opening nothing");

        // A button index changed to one outside 0..255 while playing (the Inspector): logged once
        // and the component disabled, as for a sensor, not an exception every frame.
        var changed = new TrackcalButton { deviceName = stylusName, button = 1 };
        Invoke(changed, "OnEnable");
        Invoke(changed, "Update");
        changed.button = 256;
        try
        {
            Invoke(changed, "Update");
            Check(!changed.enabled && UnityEngine.Debug.Errors.Count == 3,
                  "a button index changed to 256 disables the component and logs");
        }
        catch (TargetInvocationException e)
        {
            Check(false, "a button index changed to 256 throws from Update: " + e.InnerException.Message);
        }
        Invoke(changed, "OnDisable");
        Check(TrackcalTrackedObject.SharedConnections == 0, "the changed button's connection closed");

        // The index changed in the Inspector to a valid one while playing: the presses so far are
        // kept and the other button's count is not read against this one's baseline. The component
        // is enabled on a connection that has already seen presses (a baseline above 0), then
        // switched to button 0, which has none.
        var keeper = new TrackcalButton { deviceName = stylusName, button = 1 };
        Invoke(keeper, "OnEnable");
        DateTime keepUntil = DateTime.UtcNow.AddSeconds(20);
        while (keeper.Presses < 1 && DateTime.UtcNow < keepUntil)
        {
            Invoke(keeper, "Update");
            Thread.Sleep(5);
        }
        var switched = new TrackcalButton { deviceName = stylusName, button = 1 };
        Invoke(switched, "OnEnable");
        Invoke(switched, "Update");
        ulong presses1 = switched.Presses;
        switched.button = 0;
        Invoke(switched, "Update");
        Check(keeper.Presses >= 1 && switched.Presses == presses1 && !switched.PressedThisFrame,
              "a button index changed to 0 keeps the presses: " + presses1 + " -> " +
              switched.Presses + ", PressedThisFrame " + switched.PressedThisFrame);
        // The device changed in the Inspector while playing (the same server spelt by host name):
        // the component reads a connection of its own (it kept the old one, and Unity showed the
        // new name), keeper keeps the old one, and the presses so far are carried over rather than
        // read against the old connection's baseline (above 0: keeper's connection has seen a
        // press) on the new connection, which counts from 0 (an underflow: billions of presses).
        string respelt = stylusName.Replace("127.0.0.1", "localhost");
        Check(respelt != stylusName, "the test's device name has 127.0.0.1 to respell: " + stylusName);
        var renamed = new TrackcalButton { deviceName = stylusName, button = 1 };
        Invoke(renamed, "OnEnable");
        Invoke(renamed, "Update");
        ulong pressesBefore = renamed.Presses;
        renamed.deviceName = respelt;
        Invoke(renamed, "Update");
        Check(TrackcalTrackedObject.SharedConnections == 2 && renamed.Presses == pressesBefore &&
              !renamed.PressedThisFrame,
              "a device renamed while playing: " + TrackcalTrackedObject.SharedConnections +
              " connection(s) (2: its own and keeper's), presses " + pressesBefore + " -> " +
              renamed.Presses);
        // 20 s: the server's button changes about every 0.1 s; a new connection needs well under 1 s.
        DateTime renamedUntil = DateTime.UtcNow.AddSeconds(20);
        while (renamed.Presses < pressesBefore + 2 && DateTime.UtcNow < renamedUntil)
        {
            Invoke(renamed, "Update");
            Thread.Sleep(5);
        }
        // 20 s at 10 presses a second is at most a few hundred; an underflow about 2^64.
        Check(renamed.IsKnown && renamed.Presses >= pressesBefore + 2 &&
              renamed.Presses < pressesBefore + 1000,
              "presses on the renamed device continue from " + pressesBefore + ": " + renamed.Presses);
        // A bad name typed while playing: logged once and the component disabled, its connection
        // released (keeper's stays).
        int renameErrors = UnityEngine.Debug.Errors.Count;
        renamed.deviceName = "no host name";
        Invoke(renamed, "Update");
        Check(!renamed.enabled && UnityEngine.Debug.Errors.Count == renameErrors + 1 &&
              TrackcalTrackedObject.SharedConnections == 1,
              "a bad device name typed while playing disables the component and logs: " +
              TrackcalTrackedObject.SharedConnections + " connection(s)");
        Invoke(renamed, "OnDisable");
        Invoke(switched, "OnDisable");
        Invoke(keeper, "OnDisable");
        Check(TrackcalTrackedObject.SharedConnections == 0, "the switched button's connection closed");

        Console.WriteLine(failures == 0 ? "PASS" : failures + " check(s) failed");
        return failures == 0 ? 0 : 1;
    }

    static int Marshal_SizeOf<T>()
    {
        return System.Runtime.InteropServices.Marshal.SizeOf(typeof(T));
    }
}
