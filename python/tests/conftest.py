"""Fixtures shared by test modules: trackcal-server on the Fastrak emulator."""

import shutil
import subprocess
import time

import numpy as np
import pytest

from trackcal import captures
from understand_support import free_port


@pytest.fixture
def emulated_server(tmp_path):
    """The Fastrak emulator (paper room physics, one receiver held still at a known true pose)
    attached to trackcal-server with a calibration fitted in the same room; yields (port, the true
    pose (position, quaternion xyzw), the calibration path)."""
    from trackcal import validation
    from understand_support import simulate
    cap = captures.load_poses(simulate(tmp_path / "capture", seed=81))
    cal = tmp_path / "cal.json"
    validation.fit_polynomial(cap.select_set("calib"), degree=3).save(cal)
    position, q_wxyz = (0.30, 0.20, -0.50), (1.0, 0.0, 0.0, 0.0)
    device = tmp_path / "fastrak"
    emulator = subprocess.Popen([shutil.which("trackcal-emulate"), "--scene", "paper", "--stations", "1",
                                 "--pose", "1=" + ",".join(str(v) for v in position + q_wxyz),
                                 "--link", str(device), "--binary", "--continuous"],
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    procs = [emulator]
    try:
        deadline = time.monotonic() + 10
        while not device.exists():
            assert emulator.poll() is None and time.monotonic() < deadline, "the emulator did not start"
            time.sleep(0.05)
        (tmp_path / "vrpn.cfg").write_text(f"vrpn_Tracker_Fastrak Tracker0 {device} 115200\n"
                                           f"trackcal_Calibration Tracker0 {cal} raw=Tracker0_raw\n")
        port = free_port()
        procs.append(subprocess.Popen([shutil.which("trackcal-server"), "-f", str(tmp_path / "vrpn.cfg"), str(port),
                                       "--bind", "127.0.0.1"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
        yield port, (np.array(position), np.array([*q_wxyz[1:], q_wxyz[0]])), cal
    finally:
        for p in reversed(procs):
            p.terminate()
            try:
                p.wait(timeout=10)
            except subprocess.TimeoutExpired:
                p.kill()
