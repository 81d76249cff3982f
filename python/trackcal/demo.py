"""The main job (README's first command, ``scripts/demo.sh``) on the embedded default.

The loop a lab runs, with the Fastrak emulator and the physics simulator standing in for the
hardware and the optical reference:

1. simulate a paper-protocol capture (sim/ preset ``paper``) in a room with an effect the paper's
   polynomial model lacks (``--hidden``, default a ferromagnetic object near the volume);
2. fit the paper's degree-4 polynomial with ``trackcal-fit`` and show Table 1 before and after;
   write the HTML report (figures 4-7 of the paper, residual structure against every covariate);
3. serve: start the Fastrak emulator on a pseudo-terminal (same scene, same hidden effect) and
   ``trackcal-server`` with a vrpn.cfg that attaches the calibration, so any VRPN client gets
   ``Tracker0@localhost`` (corrected) and ``Tracker0_raw@localhost`` until interrupted.

Every run writes into a fresh work folder (never over an earlier one). ``--no-serve`` stops after
the fit, for scripts.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

DEFAULT_HIDDEN = "ferromagnetic_object"


def _tool(name: str) -> str:
    path = shutil.which(name)
    if path is None:
        raise SystemExit(
            f"trackcal demo: '{name}' is not on PATH; run ./scripts/demo.sh (it builds and installs it)")
    return path


def _run(cmd: list[str], log: Path | None = None) -> str:
    print("$ " + " ".join(cmd), flush=True)
    proc = subprocess.run(cmd, text=True, capture_output=True)
    if log is not None:
        log.write_text(proc.stdout + proc.stderr)
    if proc.returncode != 0:
        sys.stderr.write(proc.stdout + proc.stderr)
        raise SystemExit(f"trackcal demo: {Path(cmd[0]).name} failed with exit code {proc.returncode}")
    return proc.stdout


def _fresh_work_dir(base: Path) -> Path:
    stamp = _dt.datetime.now(_dt.timezone.utc).strftime("%Y%m%dT%H%M%SZ")
    for i in range(1000):
        candidate = base / (stamp if i == 0 else f"{stamp}-{i}")
        try:
            candidate.mkdir(parents=True)
            return candidate
        except FileExistsError:
            continue
    raise SystemExit(f"trackcal demo: cannot make a fresh work folder under {base}")


PAPER_MODEL = """\
# The paper's method (Ikits et al. 2001, eq. 7-9): degree-4 polynomials of the reported position
# for the position error and the vector part of the orientation error quaternion.
terms:
  - type: polynomial
    degree: 4
"""


def simulate(work: Path, hidden: str, seed: int | None) -> Path:
    capture = work / "capture"
    cmd = [_tool("trackcal-simulate"), "--scene", "paper", "-o", str(capture)]
    if hidden:
        cmd += ["--hidden", hidden]
    if seed is not None:
        cmd += ["--seed", str(seed)]
    print(_run(cmd), end="")
    return capture


def fit(work: Path, capture: Path, model_text: str, name: str) -> Path:
    model = work / f"{name}.yaml"
    model.write_text(model_text)
    calib = work / f"{name}.json"
    out = _run([_tool("trackcal-fit"), "fit", "--data", str(capture), "--model", str(model), "-o",
                str(calib)], log=work / f"{name}.log")
    print(out, end="")
    return calib


def serve(work: Path, calib: Path | None, hidden: str, seed: int | None, port: int,
          seconds: float | None) -> None:
    device = work / "fastrak"
    emulate_cmd = [_tool("trackcal-emulate"), "--scene", "paper", "--link", str(device), "--binary",
                   "--continuous"]
    if hidden:
        emulate_cmd += ["--hidden", hidden]
    if seed is not None:
        emulate_cmd += ["--seed", str(seed)]
    cfg = work / "vrpn.cfg"
    lines = [
        "# Written by the trackcal demo: the emulated Fastrak, corrected by the fitted calibration.",
        f"vrpn_Tracker_Fastrak Tracker0 {device} 115200",
    ]
    if calib is not None:
        lines.append(f"trackcal_Calibration Tracker0 {calib} raw=Tracker0_raw")
    cfg.write_text("\n".join(lines) + "\n")
    procs: list[subprocess.Popen] = []
    try:
        print("$ " + " ".join(emulate_cmd), flush=True)
        procs.append(subprocess.Popen(emulate_cmd, stdout=subprocess.DEVNULL,
                                      stderr=open(work / "emulator.log", "w")))
        deadline = time.monotonic() + 10.0
        while not device.exists():
            if procs[0].poll() is not None or time.monotonic() > deadline:
                raise SystemExit(f"trackcal demo: the emulator did not start; see {work / 'emulator.log'}")
            time.sleep(0.05)
        server_cmd = [_tool("trackcal-server"), "-f", str(cfg), str(port)]
        print("$ " + " ".join(server_cmd), flush=True)
        procs.append(subprocess.Popen(server_cmd, stdout=open(work / "server.log", "w"),
                                      stderr=subprocess.STDOUT))
        print(f"\nServing on port {port}: Tracker0@localhost:{port} (corrected)"
              + (f", Tracker0_raw@localhost:{port} (raw)" if calib is not None else "")
              + f". Logs in {work}.")
        print("Press Ctrl-C to stop." if seconds is None else f"Stopping after {seconds:g} s.",
              flush=True)
        end = None if seconds is None else time.monotonic() + seconds
        while end is None or time.monotonic() < end:
            for p in procs:
                if p.poll() is not None:
                    raise SystemExit(f"trackcal demo: {Path(p.args[0]).name} exited with code "
                                     f"{p.returncode}; see the logs in {work}")
            time.sleep(0.2)
    except KeyboardInterrupt:
        print("\nstopping")
    finally:
        for p in reversed(procs):
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
        for p in reversed(procs):
            try:
                p.wait(timeout=5)
            except subprocess.TimeoutExpired:
                p.kill()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="trackcal demo", description=__doc__.split("\n\n")[0])
    parser.add_argument("--work", type=Path, default=Path("demo-runs"),
                        help="folder under which a fresh, timestamped work folder is made")
    parser.add_argument("--hidden", default=DEFAULT_HIDDEN,
                        help="effect the base model lacks, as trackcal-simulate --hidden ('' for none)")
    parser.add_argument("--seed", type=int, default=None, help="simulation seed (default: the scene's)")
    parser.add_argument("--port", type=int, default=3883, help="VRPN port of the server")
    parser.add_argument("--no-serve", action="store_true", help="stop after the fit (for scripts)")
    parser.add_argument("--serve-seconds", type=float, default=None,
                        help="serve this long, then stop (default: until Ctrl-C)")
    args = parser.parse_args(argv)

    work = _fresh_work_dir(args.work)
    print(f"trackcal demo: work folder {work}")
    capture = simulate(work, args.hidden, args.seed)
    calib = fit(work, capture, PAPER_MODEL, "paper_polynomial")
    report = work / "report"
    print(_run([_tool("trackcal"), "report", str(capture), "-c", str(calib), "-o", str(report)],
               log=work / "report.log"), end="")
    print(f"Report: {report / 'report.html'}")
    if not args.no_serve:
        serve(work, calib, args.hidden, args.seed, args.port, args.serve_seconds)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
