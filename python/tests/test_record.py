"""Recording live raw and corrected streams from a trackcal-server serving a NULL tracker through a
calibration (raw= name), then validating the recording against the calibration."""

import pathlib
import shutil
import socket
import subprocess
import time

import numpy as np
import pytest

import trackcal
from trackcal import captures
from trackcal.record import record_streams

REPO = pathlib.Path(__file__).resolve().parents[2]
EXAMPLE = REPO / "tests" / "data" / "calibration" / "example.json"


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def server(tmp_path):
    exe = shutil.which("trackcal-server")
    assert exe, "trackcal-server must be on PATH (scripts/build.sh installs it)"
    shutil.copy(EXAMPLE, tmp_path / "cal.json")
    (tmp_path / "vrpn.cfg").write_text("vrpn_Tracker_NULL Tracker0 2 100.0\n"
                                       "trackcal_Calibration Tracker0 cal.json raw=Tracker0_raw\n")
    port = free_port()
    proc = subprocess.Popen([exe, "-f", str(tmp_path / "vrpn.cfg"), str(port), "--bind", "127.0.0.1"],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    time.sleep(0.3)
    yield port
    proc.terminate()
    try:
        proc.wait(timeout=10)
    except subprocess.TimeoutExpired:
        proc.kill()


def test_record_raw_and_corrected(server, tmp_path):
    port = server
    out = record_streams({"raw": f"Tracker0_raw@tcp://127.0.0.1:{port}",
                          "corrected": f"Tracker0@tcp://127.0.0.1:{port}"}, tmp_path / "rec", 0.6)
    raw = captures.load_tracker_stream(out["raw"])
    cor = captures.load_tracker_stream(out["corrected"])
    # 2 sensors at 100 Hz for 0.6 s: ~120 reports each; at least a third arrives on a loaded machine.
    assert len(raw) > 40 and len(cor) > 40
    assert set(raw.sensor) == {1, 2}
    # NULL trackers report the identity pose; the corrected device serves the calibration applied to it.
    cal = trackcal.Calibration.load(EXAMPLE)
    p, q, _ = cal.correct(raw.positions[:1], raw.quaternions_xyzw[:1])
    np.testing.assert_allclose(raw.positions, 0.0, atol=0)
    # Wire values are doubles: the corrected stream equals the C++ correction exactly (1e-12 m slack
    # for a different evaluation order is not needed, but guards against a float32 path).
    np.testing.assert_allclose(cor.positions, np.repeat(p, len(cor), axis=0), atol=1e-12)
    assert np.abs(cor.positions).max() > 1e-4  # the example calibration does move the origin
    with pytest.raises(ValueError, match="never overwritten"):
        record_streams({"raw": f"Tracker0_raw@tcp://127.0.0.1:{port}"}, tmp_path / "rec", 0.1)


def test_record_unserved_name_times_out(server, tmp_path):
    with pytest.raises(RuntimeError, match="no report within"):
        record_streams({"x": f"Nope@tcp://127.0.0.1:{server}"}, tmp_path / "rec", 0.1, connect_timeout_s=1.5)
