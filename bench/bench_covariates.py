#!/usr/bin/env python3
"""Time of the covariate permutation tests on a long stream capture, new code against the old.

    .venv/bin/python bench/bench_covariates.py [--duration 600] [--repeats 1] [--profile FILE]

Simulates the paper scene with a stream of ``--duration`` seconds (trackcal-simulate, fixed seed),
fits a degree-3 polynomial to its calibration stations, validates the paired streams with it
without covariates, and then times ``validation.covariate_analysis`` on the corrected residuals as
``trackcal diagnose`` and ``trackcal report`` run it (serial samples, 199 permutations, seed 0),
alternately by the code in use and by the code it replaced (``validation._SLOW_REFERENCE``), best of
``--repeats`` each. Prints both times, the new/old ratio, and whether the two gave the same effects
bit for bit (R^2, p-values, findings); exits 1 if they did not.
"""

from __future__ import annotations

import cProfile
import dataclasses
import pathlib
import sys
import time

from trackcal import validation

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
from bench_report_figures import stream_arguments, validated_stream  # noqa: E402  (the same capture)


def covariate_inputs(v):
    """What validate() hands covariate_analysis for a paired stream capture."""
    kept = ~v.flipped
    analysed = v.capture.subset(kept) if v.flipped.any() else v.capture
    covs, labels = validation.covariates_and_labels(analysed)
    serial = analysed.time if validation.serial_samples(analysed) else None
    return validation._sub(v.final, kept), covs, dict(serial_time=serial, labels=labels)


def run(inputs, reference: bool):
    res, covs, kwargs = inputs
    validation._SLOW_REFERENCE = reference
    try:
        start = time.perf_counter()
        effects = validation.covariate_analysis(res, covs, **kwargs)
        return time.perf_counter() - start, effects
    finally:
        validation._SLOW_REFERENCE = False


def main() -> int:
    args = stream_arguments(__doc__.splitlines()[0], repeats=1).parse_args()
    v = validated_stream(args.duration, args.seed)
    inputs = covariate_inputs(v)
    print(f"{len(inputs[0].position_mm)} paired stream samples ({args.duration:g} s), "
          f"{len(inputs[1])} covariates, best of {args.repeats}:")
    best = {"new": float("inf"), "old": float("inf")}
    same = True
    for _ in range(args.repeats):  # alternately, so that both see the same machine load
        t_new, new = run(inputs, reference=False)
        t_old, old = run(inputs, reference=True)
        best["new"], best["old"] = min(best["new"], t_new), min(best["old"], t_old)
        same &= [dataclasses.astuple(e) for e in new] == [dataclasses.astuple(e) for e in old]
    print(f"  new (validation._cv_r2_targets)          {best['new']:7.2f} s")
    print(f"  old (validation._cv_r2_rows_reference)   {best['old']:7.2f} s")
    print(f"  new/old {best['new'] / best['old']:.3f}; effects bit for bit the same: {'yes' if same else 'NO'}")
    if args.profile:
        res, covs, kwargs = inputs
        cProfile.runctx("validation.covariate_analysis(res, covs, **kwargs)", globals(),
                        {"res": res, "covs": covs, "kwargs": kwargs}, args.profile)
        print(f"profile written to {args.profile}")
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
