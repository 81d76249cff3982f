"""The main job stops cleanly on SIGTERM and SIGHUP while serving: its emulator and server are
stopped with it, and it exits 128 + the signal's number as a shell reports it."""
import os
import re
import signal
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
SMALL_SCENE = ROOT / "tests" / "data" / "workflow" / "paper_small.yaml"

pytestmark = pytest.mark.skipif(
    shutil.which("trackcal-simulate") is None or shutil.which("trackcal-server") is None,
    reason="command-line tools not installed (run scripts/build.sh)")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _children(pid: int):
    try:
        text = Path(f"/proc/{pid}/task/{pid}/children").read_text()
    except OSError:
        return []
    return [int(c) for c in text.split()]


def _alive(pid: int) -> bool:
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"  # a zombie has exited


@pytest.mark.parametrize("signum, code", [(signal.SIGTERM, 143), (signal.SIGHUP, 129)])
def test_a_signal_stops_the_demo_and_its_children(tmp_path, signum, code):
    proc = subprocess.Popen(
        [sys.executable, "-m", "trackcal.demo", "--work", str(tmp_path), "--max-steps", "0",
         "--scene", str(SMALL_SCENE), "--port", str(_free_port())],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    out, children = [], []
    try:
        # The fit and one diagnosis come first (about a minute on a loaded 2-core machine).
        deadline = time.monotonic() + 600
        for line in proc.stdout:
            out.append(line)
            if line.startswith("Serving on port") or time.monotonic() > deadline:
                break
        assert any(l.startswith("Serving on port") for l in out), "".join(out)
        children = _children(proc.pid)
        assert len(children) == 2, f"expected the emulator and the server, got {children}"
        # Wait until the server has corrected poses (the Fastrak's reset and set-up take seconds):
        # SIGUSR1 makes it log its status line.
        log = next(p for p in tmp_path.iterdir() if p.is_dir()) / "server.log"
        # Right after the start a child's /proc cmdline can still read empty: ask again.
        server, deadline = None, time.monotonic() + 10
        while server is None and time.monotonic() < deadline:
            cmdlines = {c: Path(f"/proc/{c}/cmdline").read_bytes() for c in children}
            server = next((c for c, cmd in cmdlines.items() if b"trackcal-server" in cmd), None)
            time.sleep(0.1)
        assert server is not None, f"no trackcal-server among the children: {cmdlines}"
        deadline = time.monotonic() + 60
        while not re.search(r"Tracker0: [1-9]\d* corrected", log.read_text() if log.exists() else ""):
            assert time.monotonic() < deadline, "the server served no corrected pose in 60 s"
            os.kill(server, signal.SIGUSR1)
            time.sleep(0.5)
        proc.send_signal(signum)
        rest, _ = proc.communicate(timeout=30)
        out.append(rest)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        leftover = [c for c in children if _alive(c)]
        for c in leftover:  # a failed test must not leave an emulator and a server running
            os.kill(c, signal.SIGKILL)
    text = "".join(out)
    assert proc.returncode == code, text
    assert f"stopped by {signal.Signals(signum).name}" in text, text
    # The server logged its status at stop, and the demo reports the extrapolated share.
    assert "corrected poses;" in text and "extrapolated outside the calibrated volume" in text, text
    assert not leftover, f"children still running after the demo exited: {leftover}\n{text}"


def test_signals_during_the_childrens_stop_are_ignored():
    # serve() stops the emulator and the server inside this block: a second Ctrl-C (or a SIGTERM)
    # there must not unwind past the wait and leave them unreaped, a traceback printed.
    from trackcal._signals import signals_deferred
    before = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)}
    with signals_deferred(tuple(before)) as arrived:
        for s in before:
            os.kill(os.getpid(), s)
        time.sleep(0.05)  # the handlers run between bytecodes: give them the chance to
    assert arrived == set(before)  # remembered, for a caller that acts on them afterwards
    assert {s: signal.getsignal(s) for s in before} == before
