"""The benchmark scripts of bench/ run on a machine set up by scripts/install-deps.sh alone: here
with stand-ins for the build's tools, so the scripts' own plumbing is tested in seconds."""

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]

_SIMULATE = """#!/bin/sh
# stand-in for trackcal-simulate: makes the -o folder
while [ $# -gt 0 ]; do [ "$1" = -o ] && mkdir -p "$2"; shift; done
"""

_DIAGNOSIS = {
    "base": {"cv_position_mm_mean": 1.0, "cv_orientation_deg_mean": 0.1},
    "candidates": [{"effect": "sensor_offset", "replaces": None, "cross_validated": True,
                    "significant": True, "cv_position_mm_mean": 0.5,
                    "cv_orientation_deg_mean": 0.05, "parameters": []}],
    "verdict": {"effect": "sensor_offset"},
}

_FIT = f"""#!{sys.executable}
# stand-in for trackcal-fit: fit and diagnose --json documents
import sys, time
# 0.1 s of CPU: well above the 10 ms tick of the CPU times, which the script divides by
while time.process_time() < 0.1:
    pass
if sys.argv[1] == "fit":
    print('{{"fit": {{"seconds": 0.01}}}}')
else:
    print({json.dumps(json.dumps(_DIAGNOSIS))})
"""

# What a fresh Debian bookworm has after scripts/install-deps.sh (coreutils, bash, python3), and not
# GNU time (Debian's `time` package, priority optional).
_TOOLS = ["bash", "sh", "env", "python3", "mktemp", "rm", "cut", "nproc", "ln", "cp", "mkdir",
          "cat", "dirname", "sleep"]


@pytest.mark.skipif(os.name != "posix" or shutil.which("bash") is None, reason="needs bash")
def test_bench_diagnose_runs_without_gnu_time(tmp_path):
    """Before: bench/bench_diagnose.sh timed its runs with `/usr/bin/env time -f ...` (GNU time),
    which scripts/install-deps.sh does not install: on a fresh machine every step failed with
    "env: 'time': No such file or directory"."""
    build = tmp_path / "build"
    for rel, text in (("sim/trackcal-simulate", _SIMULATE), ("fit/trackcal-fit", _FIT)):
        path = build / rel
        path.parent.mkdir(parents=True)
        path.write_text(text)
        path.chmod(0o755)
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    for tool in _TOOLS:
        found = shutil.which(tool)
        if found is None:
            pytest.skip(f"{tool} not installed")
        (bin_dir / tool).symlink_to(found)
    env = {"PATH": str(bin_dir), "HOME": str(tmp_path), "TMPDIR": str(tmp_path)}
    proc = subprocess.run(["bash", str(ROOT / "bench" / "bench_diagnose.sh"), str(build)],
                          env=env, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    for step in ("step1", "step2"):
        line = next(l for l in proc.stdout.splitlines() if l.startswith(step + ":"))
        assert "fast" in line and "exact" in line and "speed-up" in line, proc.stdout
    assert "verdict sensor_offset (exact: sensor_offset)" in proc.stdout, proc.stdout
    assert "same;" in proc.stdout, proc.stdout


def test_bench_python_batch_runs_and_prints_cpu_and_wall_ratios():
    """bench/bench_python_batch.py on a few poses: the same-answer check, the alternating rounds and
    the CPU / wall report (its figure is the CPU ratio; docs/benchmarks.md). No time is asserted."""
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1")
    proc = subprocess.run([sys.executable, str(ROOT / "bench" / "bench_python_batch.py"),
                           "--poses", "2000", "--repeats", "2"],
                          capture_output=True, text=True, env=env, timeout=120)
    assert proc.returncode == 0, proc.stderr
    ratio = [line for line in proc.stdout.splitlines() if "ratio numpy / trackcal" in line]
    assert len(ratio) == 1 and "x wall)" in ratio[0], proc.stdout
    assert "best of 2 (alternating)" in proc.stdout, proc.stdout


def test_bench_report_figures_reference_puts_the_two_slow_paths_back():
    """bench/bench_report_figures.py's old side (slow_paths): on the figures the report draws, the
    legend of figures 4 and 5 goes back inside the axes at loc "best" and the residual maps' dots get
    back area 14 and the default edge; everything else stays. On figures without them it raises
    rather than time two identical sides."""
    import matplotlib
    import matplotlib.pyplot as plt
    import numpy as np
    sys.path.insert(0, str(ROOT / "bench"))
    try:
        import bench_report_figures as bench
    finally:
        sys.path.remove(str(ROOT / "bench"))
    from trackcal import figures

    rng = np.random.default_rng(3)
    n = 300
    distance = rng.uniform(0.2, 1.2, n)
    figs = [(name, "", figures.error_vs_distance(distance, 30 * distance, 3 * distance,
                                                 held_out=rng.random(n) < 0.3))
            for name in bench._SLOW_LEGENDS]
    figs += [(name, "", figures.residual_map(rng.normal(size=(n, 3)), rng.uniform(0, 5, n)))
             for name in bench._SLOW_DOTS]
    labels_before = [sorted(t.get_text() for t in fig.legends[0].get_texts()) for _, _, fig in figs[:2]]
    try:
        bench.slow_paths(figs)
        for (_, _, fig), labels in zip(figs[:2], labels_before):
            legend = fig.axes[0].get_legend()
            assert not fig.legends and legend is not None
            assert legend._loc == 0  # "best"
            assert sorted(t.get_text() for t in legend.get_texts()) == labels
            fig.canvas.draw()  # the old figure still draws
        for _, _, fig in figs[2:]:
            for ax in fig.axes[:2]:
                dots = ax.collections[0]
                assert np.allclose(dots.get_sizes(), 14.0)
                assert np.allclose(dots.get_linewidths(), matplotlib.rcParams["patch.linewidth"])
                assert dots.get_array() is not None  # still colour-mapped
        # A second time there is nothing left to put back.
        with pytest.raises(RuntimeError, match="fig4_position_error_vs_distance"):
            bench.slow_paths(figs)
    finally:
        for _, _, fig in figs:
            plt.close(fig)
