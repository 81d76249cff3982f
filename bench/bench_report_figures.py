#!/usr/bin/env python3
"""Time of the HTML report's figures (drawing and PNG encoding) on a long stream capture.

    .venv/bin/python bench/bench_report_figures.py [--duration 600] [--repeats 3] [--profile FILE]

Simulates the paper scene with a stream of ``--duration`` seconds (trackcal-simulate, fixed seed),
fits a degree-3 polynomial to its calibration stations, validates the paired streams with it
(covariates off: their permutation tests are timed by `trackcal diagnose`, not here) and times
``report.build_figures`` and the PNG encoding of each figure, best of ``--repeats``, alternately as
the report draws them (new) and with the two slow paths the report left on 2026-11-30 put back
(old, ``slow_paths``): the legend of figures 4 and 5 inside the axes at loc "best", and the residual
maps' colour-mapped dots at area 14 with matplotlib's default edge. Everything else in the figures
is the same on both sides, so the ratio is what those two changes save in this run. Prints one line
per figure, new and old, the totals and new/old, in CPU time (wall beside it).
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

_SLOW_LEGENDS = ("fig4_position_error_vs_distance.png", "fig5_orientation_error_vs_distance.png")
_SLOW_DOTS = ("residual_map_position.png", "residual_map_orientation.png")


def slow_paths(figs) -> None:
    """Put back, in the figures build_figures made, the two paths 88a80dc took out of them: the
    legend of figures 4 and 5 inside the axes at loc "best" (matplotlib then counts every point under
    each candidate place when the figure is drawn), and the residual maps' colour-mapped dots at the
    scatter's default area 14 with its default edge (rcParams patch.linewidth in the face's colour,
    which Agg strokes marker by marker) instead of edgeless dots as large. Raises if a figure no
    longer has what is put back (the comparison would then time nothing)."""
    import matplotlib
    by_name = {name: fig for name, _, fig in figs}
    for name in _SLOW_LEGENDS:
        fig = by_name[name]
        if len(fig.legends) != 1 or fig.axes[0].get_legend() is not None:
            raise RuntimeError(f"{name}: expected one figure legend under the axes to move back inside")
        handles, labels = fig.axes[0].get_legend_handles_labels()
        fig.legends[0].remove()
        fig.axes[0].legend(handles, labels, fontsize=8, loc="best")
    for name in _SLOW_DOTS:
        for ax in by_name[name].axes[:2]:
            dots = ax.collections[0]
            if dots.get_array() is None or not (dots.get_linewidths() == 0).all():
                raise RuntimeError(f"{name}: expected edgeless colour-mapped dots to give an edge back")
            dots.set_sizes([14.0])
            dots.set_linewidths([matplotlib.rcParams["patch.linewidth"]])
            dots.set_edgecolor("face")


def time_figures(v, old: bool = False) -> dict:
    """CPU seconds (this process; matplotlib draws on one thread) of build_figures and of each
    figure's PNG encoding, their total, and the total's wall seconds ("total, wall")."""
    import matplotlib.pyplot as plt
    wall = time.perf_counter()
    start = time.process_time()
    figs = report.build_figures(v)
    if old:
        slow_paths(figs)
    times = {"(drawing every figure)": time.process_time() - start}
    for name, _, fig in figs:
        start = time.process_time()
        figures.png_bytes(fig)
        times[name] = time.process_time() - start
        plt.close(fig)
    times["total"] = sum(times.values())
    times["total, wall"] = time.perf_counter() - wall
    return times


def main() -> int:
    args = stream_arguments(__doc__.splitlines()[0], repeats=3).parse_args()
    v = validated_stream(args.duration, args.seed)
    print(f"{len(v.capture.station)} paired stream samples ({args.duration:g} s), best of {args.repeats}, "
          "new and old alternately (CPU seconds):")
    best: dict = {"new": {}, "old": {}}
    for _ in range(args.repeats):  # alternately, so that both see the same machine load
        for side in ("new", "old"):
            for name, t in time_figures(v, old=side == "old").items():
                best[side][name] = min(best[side].get(name, float("inf")), t)
    print(f"  {'':42s} {'new':>7s} {'old':>7s}")
    for name in best["new"]:
        print(f"  {name:42s} {best['new'][name]:7.2f} {best['old'][name]:7.2f}")
    print(f"  new/old {best['new']['total'] / best['old']['total']:.3f} CPU, "
          f"{best['new']['total, wall'] / best['old']['total, wall']:.3f} wall "
          "(old: legends at loc 'best', dots with their edge)")
    if args.profile:
        cProfile.runctx("time_figures(v)", globals(), {"v": v, "time_figures": time_figures}, args.profile)
        print(f"profile written to {args.profile}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
