#!/usr/bin/env python3
"""Time of the HTML report's figures (drawing and PNG encoding) on a long stream capture.

    .venv/bin/python bench/bench_report_figures.py [--duration 600] [--repeats 3] [--profile FILE]

Simulates the paper scene with a stream of ``--duration`` seconds (trackcal-simulate, fixed seed),
fits a degree-3 polynomial to its calibration stations, validates the paired streams with it
(covariates off: their permutation tests are timed by `trackcal diagnose`, not here) and times
``report.build_figures`` and the PNG encoding of each figure, best of ``--repeats``. Prints one line
per figure and the total. For a before/after ratio, run it on both checkouts in the same minute
(docs/benchmarks.md).
"""

from __future__ import annotations

import argparse
import cProfile
import pathlib
import re
import shutil
import subprocess
import sys
import tempfile
import time

from trackcal import captures, figures, report, validation


def simulate(folder: pathlib.Path, duration_s: float, seed: int) -> pathlib.Path:
    exe = shutil.which("trackcal-simulate")
    if exe is None:
        sys.exit("trackcal-simulate must be on PATH (scripts/build.sh installs it into the venv)")
    scene = pathlib.Path(__file__).resolve().parents[1] / "sim" / "scenes" / "paper.yaml"
    text, n = re.subn(r"(\n\s*duration_s:\s*)[0-9.]+", rf"\g<1>{duration_s:g}", scene.read_text())
    if n != 1:
        sys.exit(f"{scene}: expected one stream duration_s to replace, found {n}")
    (folder / "scene.yaml").write_text(text)
    subprocess.run([exe, "--scene", str(folder / "scene.yaml"), "--seed", str(seed), "-o", str(folder / "capture")],
                   check=True, capture_output=True)
    streams = folder / "streams"
    streams.mkdir()
    for name in ("tracker_stream.csv", "reference_stream.csv"):
        shutil.copy(folder / "capture" / name, streams / name)
    return folder



def stream_arguments(description: str, repeats: int) -> argparse.ArgumentParser:
    """The options both long-stream benchmarks take (this one and bench_covariates.py)."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--duration", type=float, default=600.0, help="stream length [s] (default 600)")
    parser.add_argument("--repeats", type=int, default=repeats)
    parser.add_argument("--seed", type=int, default=5)
    parser.add_argument("--profile", help="also write a cProfile of one more run to this file")
    return parser


def validated_stream(duration_s: float, seed: int):
    """The paired streams of a simulated paper capture validated, covariates off, with a degree-3
    polynomial fitted to its calibration stations."""
    with tempfile.TemporaryDirectory(prefix="bench_stream_") as tmp:
        folder = simulate(pathlib.Path(tmp), duration_s, seed)
        cal = validation.fit_polynomial(captures.load_poses(folder / "capture").select_set("calib"), degree=3)
        cap = captures.load(folder / "streams")
        return validation.validate(cap, cal, analyse_covariates=False)

def time_figures(v) -> dict:
    import matplotlib.pyplot as plt
    start = time.perf_counter()
    figs = report.build_figures(v)
    drawn = time.perf_counter() - start
    times = {"(drawing every figure)": drawn}
    for name, _, fig in figs:
        start = time.perf_counter()
        figures.png_bytes(fig)
        times[name] = time.perf_counter() - start
        plt.close(fig)
    times["total"] = sum(times.values())
    return times


def main() -> int:
    args = stream_arguments(__doc__.splitlines()[0], repeats=3).parse_args()
    v = validated_stream(args.duration, args.seed)
    print(f"{len(v.capture.station)} paired stream samples ({args.duration:g} s), best of {args.repeats}:")
    best: dict = {}
    for _ in range(args.repeats):
        for name, t in time_figures(v).items():
            best[name] = min(best.get(name, float("inf")), t)
    for name, t in best.items():
        print(f"  {name:42s} {t:7.2f} s")
    if args.profile:
        cProfile.runctx("time_figures(v)", globals(), {"v": v, "time_figures": time_figures}, args.profile)
        print(f"profile written to {args.profile}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
