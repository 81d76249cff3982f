"""The README's main job, run as a script would: --no-serve, and a short serve."""

import shutil
import socket

import pytest

from trackcal import demo

pytestmark = pytest.mark.skipif(shutil.which("trackcal-simulate") is None,
                                reason="command-line tools not installed (run scripts/build.sh)")


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_demo_without_serving_writes_a_fresh_work_folder(tmp_path, capsys):
    assert demo.main(["--work", str(tmp_path), "--no-serve", "--seed", "7"]) == 0
    assert demo.main(["--work", str(tmp_path), "--no-serve", "--seed", "7"]) == 0
    runs = sorted(p for p in tmp_path.iterdir() if p.is_dir())
    assert len(runs) == 2, "a second run must not reuse the first run's folder"
    for run in runs:
        assert (run / "capture" / "poses.csv").is_file()
        assert (run / "paper_polynomial.json").is_file()
    out = capsys.readouterr().out
    assert "validation, uncorrected" in out
    assert "Position error" in out or "position" in out.lower()


def test_demo_serves_with_the_emulator_until_told_to_stop(tmp_path):
    port = _free_port()
    assert demo.main(["--work", str(tmp_path), "--serve-seconds", "3", "--port", str(port)]) == 0
    run = next(p for p in tmp_path.iterdir() if p.is_dir())
    cfg = (run / "vrpn.cfg").read_text()
    assert "vrpn_Tracker_Fastrak Tracker0" in cfg
    assert "trackcal_Calibration Tracker0" in cfg and "raw=Tracker0_raw" in cfg
    assert "opened at 115200 baud" in (run / "server.log").read_text()
