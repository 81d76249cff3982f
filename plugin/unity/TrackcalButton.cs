// A button of a VRPN button device (a Fastrak stylus: "Stylus0@host", its own device on the
// server) for scripts to poll: IsPressed, and PressedThisFrame, which also sees a press and release
// that both fell between two frames. Shares the connection with other components reading the same
// device (TrackcalConnections).
#if UNITY_5_3_OR_NEWER
using UnityEngine;

namespace Trackcal
{
    public class TrackcalButton : MonoBehaviour
    {
        [Tooltip("VRPN button device: Stylus0@host, Stylus0@host:port or Stylus0@tcp://host:port.")]
#if UNITY_5_4_OR_NEWER
        [Delayed]  // a change made while playing takes effect on Enter, not on every keystroke
#endif
        public string deviceName = "Stylus0@localhost";

        [Tooltip("Button index on the device (0 for the Fastrak stylus's switch).")]
        public int button = 0;

        public bool IsPressed { get; private set; }
        // At least one press since the previous frame.
        public bool PressedThisFrame { get; private set; }
        // Presses since the component was enabled.
        public ulong Presses { get; private set; }
        // False until the server has sent this button's state.
        public bool IsKnown { get; private set; }

        private TrackcalTracker device;
        // The name the device was acquired for: changed while playing, it is reopened.
        private string acquiredName;
        private ulong pressesAtEnable;
        private bool firstRead;
        private ulong pressesCarried;
        private int buttonRead;  // the index pressesAtEnable counts

        private void OnEnable()
        {
            if (!TrackcalComponents.IndexValid(this, "button", button)) return;
            acquiredName = deviceName;
            // Axes do not matter to buttons; the default keeps one connection per device.
            device = TrackcalComponents.Acquire(this, deviceName, null);
            if (device == null) return;
            firstRead = true;
            pressesCarried = 0;
            Presses = 0;
        }

        private void OnDisable()
        {
            IsPressed = PressedThisFrame = IsKnown = false;
            TrackcalConnections.Release(device);
            device = null;
        }

        private void Update()
        {
            PressedThisFrame = false;
            if (device == null) return;
            // Changed in the Inspector while playing: an exception every frame otherwise.
            if (!TrackcalComponents.IndexValid(this, "button", button)) return;
            // deviceName changed in the Inspector (or by a script) while playing: the component kept
            // reading the old device while the Inspector showed the new one. String equality, no
            // allocation per frame; a bad new name disables the component.
            if (deviceName != acquiredName)
            {
                TrackcalTracker old = device;
                device = null;  // OnDisable, after a bad new name, has nothing more to release
                acquiredName = deviceName;
                // Acquired before the old one is released, as TrackcalTrackedObject does.
                TrackcalTracker renewed = TrackcalComponents.Acquire(this, deviceName, null);
                TrackcalConnections.Release(old);
                if (renewed == null) return;
                device = renewed;
                // Another connection's count (names are its key): carry ours over, as for a
                // renewed handle below.
                pressesCarried = Presses;
                firstRead = true;
            }
            TrackcalTracker current = TrackcalConnections.Renew(device);
            if (current != device || button != buttonRead)
            {
                // A new handle counts presses from 0, and another button (the index changed in the
                // Inspector) has a count of its own: carry ours over rather than subtract a
                // baseline of another count (an underflow: billions of presses).
                device = current;
                pressesCarried = Presses;
                firstRead = true;
            }
            bool pressed;
            ulong presses;
            IsKnown = device.TryGetButton(button, out pressed, out presses);
            if (firstRead)
            {
                // The connection may be older than this component: count from here.
                pressesAtEnable = presses;
                buttonRead = button;
                firstRead = false;
            }
            ulong since = pressesCarried + (presses - pressesAtEnable);
            PressedThisFrame = since > Presses;
            Presses = since;
            IsPressed = pressed;
        }
    }
}
#endif
