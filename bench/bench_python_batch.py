#!/usr/bin/env python3
"""Batch correction throughput: 1M poses through trackcal's native batch path and through a plain
numpy implementation of the same degree-4 polynomial (trackcal.numpy_reference), in the same run.

    .venv/bin/python bench/bench_python_batch.py [--poses 1000000] [--repeats 5]

Prints the best-of-repeats CPU time per pose of each (the two alternating) and their ratio, with
the wall times in brackets. Pin to one core for the
single-core figure: `taskset -c 0 .venv/bin/python bench/bench_python_batch.py`.
"""

from __future__ import annotations

import argparse
import os
import time

# One BLAS thread, set before numpy loads OpenBLAS: the native path is single-threaded, and numpy's
# matrix products would otherwise start a thread per core, which on a shared machine made the numpy
# side 2-3.5x slower unpinned (ratios of 53-94x instead of 25-27x in the same minute).
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402

import trackcal  # noqa: E402
from trackcal import numpy_reference  # noqa: E402


def best_times(fns, repeats: int) -> list[tuple[float, float]]:
    """Best (CPU seconds, wall seconds) of each function over `repeats` rounds, the functions
    alternating within a round so that both sides see the same machine load. CPU time is the
    figure: on a shared, loaded machine the wall time of the slower side (seconds per call) is
    preempted more often than the faster side's, which inflated the ratio (2026-12-02, load average
    9 on 2 cores, pinned: 50.1x by the wall-time best of 5 of each side in turn, then 23.8x CPU and
    27.5x wall alternating, a minute apart). With more than one BLAS thread CPU time sums them."""
    best = [(float("inf"), float("inf")) for _ in fns]
    for _ in range(repeats):
        for i, fn in enumerate(fns):
            cpu, wall = time.process_time(), time.perf_counter()
            fn()
            cpu, wall = time.process_time() - cpu, time.perf_counter() - wall
            best[i] = (min(best[i][0], cpu), min(best[i][1], wall))
    return best


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--poses", type=int, default=1_000_000)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--degree", type=int, default=4)
    args = parser.parse_args()

    rng = np.random.default_rng(20010313)
    n = args.poses
    r = trackcal.num_polynomial_terms(args.degree)
    pc = rng.normal(scale=0.005, size=(r, 3))
    oc = rng.normal(scale=0.003, size=(r, 3))
    offset, scale = (0.0, 0.0, 0.3), (0.5, 0.5, 0.5)
    positions = np.asarray(offset) + rng.uniform(-0.45, 0.45, size=(n, 3))
    quats = rng.normal(size=(n, 4))
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)

    poly = trackcal.PolynomialCorrection(args.degree, pc, oc, offset, scale)
    cal = trackcal.Calibration([poly], (-0.5, -0.5, -0.2), (0.5, 0.5, 0.8))

    # Same answer first: the benchmark compares equal work.
    p_native, q_native, _ = cal.correct(positions[:1000], quats[:1000])
    p_np, q_np = numpy_reference.correct_polynomial(args.degree, pc, oc, offset, scale,
                                                    positions[:1000], quats[:1000])
    assert np.abs(p_native - p_np).max() < 1e-14 and np.abs(q_native - q_np).max() < 1e-14

    (c_native, w_native), (c_numpy, w_numpy) = best_times(
        [lambda: cal.correct(positions, quats),
         lambda: numpy_reference.correct_polynomial(args.degree, pc, oc, offset, scale, positions,
                                                    quats)],
        args.repeats)
    affinity = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else "?"
    print(f"degree-{args.degree} polynomial, position + orientation, {n} poses, best of "
          f"{args.repeats} (alternating), {affinity} CPU(s) allowed, OPENBLAS_NUM_THREADS="
          f"{os.environ['OPENBLAS_NUM_THREADS']}; CPU time (wall in brackets)")
    print(f"  trackcal Calibration.correct: {c_native * 1e3:9.1f} ms  {c_native / n * 1e9:7.1f} ns/pose"
          f"  ({w_native / n * 1e9:.1f} ns/pose wall)")
    print(f"  numpy reference             : {c_numpy * 1e3:9.1f} ms  {c_numpy / n * 1e9:7.1f} ns/pose"
          f"  ({w_numpy / n * 1e9:.1f} ns/pose wall)")
    print(f"  ratio numpy / trackcal      : {c_numpy / c_native:9.1f} x  ({w_numpy / w_native:.1f} x wall)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
