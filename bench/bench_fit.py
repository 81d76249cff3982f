#!/usr/bin/env python3
"""Fit time of trackcal's degree-4 polynomial next to a plain numpy least-squares implementation of
the paper's method (Ikits et al. 2001, eq. 7-9), in the same run, on the same simulated capture;
and of a chain of two physical terms and a LUT on the same capture.

    .venv/bin/python bench/bench_fit.py --build build [--repeat 5] [--before-fit OTHER/trackcal-fit]

(the project's venv: numpy is not in the system python).

Runs trackcal-simulate --scene paper, then `trackcal-fit fit --json` (its reported solve time:
linear initialisation + Ceres refinement, and the covariance time separately) and the numpy fit
(monomials on normalised coordinates, np.linalg.lstsq), and prints both times and the validation
improvements of both. Then the chain model CHAIN_MODEL (a plane and a dipole without start values,
found by the search, then a 150 mm LUT; issue target: fit <= 5 s) is fitted the same way; its wall
time (trackcal-fit's own `seconds`) and the CPU time of the trackcal-fit process (user + system, from
getrusage: on a shared machine the wall time includes waiting for a core) are printed with their
ratios to the numpy baseline.
"""
import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time

# Physical terms first (the plane and the dipole start from the search), then a LUT for what they do
# not explain. Covariance off: the LUT's 4290-parameter covariance alone costs minutes (see
# docs/model-file.md, solver.covariance). function_tolerance 1e-6: on this capture the cost is ~5000,
# so the solve stops when an iteration changes it by < 0.005, far below the 0.5 of a 1-sigma move
# of any parameter (the default 1e-12 spends ~25 more sparse factorisations changing the validation
# error by < 0.001 mm).
# The LUT's weights are pinned to 1 and 1, what every LUT had when the figures in docs/benchmarks.md
# and docs/physical-model.md were measured; the defaults of a LUT without a polynomial in its chain
# are 0.01 / 0.1 since session 41 (docs/model-file.md, "LUT regularisation"), which on this chain
# took 139 iterations (49.5 s CPU) to 4.90 mm instead of 6 iterations to 3.19 mm.
CHAIN_MODEL = """noise: {position_mm: 1.0, orientation_deg: 0.2}
solver: {covariance: false, function_tolerance: 1.0e-6}
terms:
  - type: plane
  - type: dipole
  - type: lut
    cell_size_mm: 150
    ridge: 1
    smoothness: 1
"""
# The chain as a user writes it, without the settings above.
CHAIN_MODEL_DEFAULTS = """noise: {position_mm: 1.0, orientation_deg: 0.2}
terms:
  - type: plane
  - type: dipole
  - type: lut
    cell_size_mm: 150
"""

# fit/best_chain_sim_test's chain.
RIDGE_CHAIN_MODEL = """noise: {position_mm: 1.0, orientation_deg: 0.2}
terms:
  - type: plane
  - type: dipole
  - type: polynomial
    degree: 8
    ridge: 0.25
"""


def run_timed(cmd):
    """Runs cmd; returns (stdout, CPU seconds of the child: user + system)."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    out = subprocess.run(cmd, check=True, capture_output=True, text=True)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return out.stdout, cpu

# One BLAS thread: the comparison is single-threaded on both sides (Ceres runs with 1 thread).
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402


def monomials(u, degree):
    """Complete monomials of u (n x 3) in core/polynomial.h's canonical order."""
    cols = [np.ones(len(u))]
    prev = [np.ones(len(u))]
    for d in range(1, degree + 1):
        block = [u[:, 0] * m for m in prev]
        block += [u[:, 1] * m for m in prev[len(prev) - d:]]
        block.append(u[:, 2] * prev[-1])
        cols += block
        prev = block
    return np.stack(cols, axis=1)


def quat_mul(a, b):  # (w, x, y, z)
    w1, x1, y1, z1 = a.T
    w2, x2, y2, z2 = b.T
    return np.stack([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                     w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2], 1)


def conj(q):
    return q * np.array([1, -1, -1, -1])


def angle_deg(q):
    return np.degrees(2 * np.arctan2(np.linalg.norm(q[:, 1:], axis=1), np.abs(q[:, 0])))


def numpy_paper_fit(rep_p, rep_q, ref_p, ref_q, degree=4):
    lo, hi = rep_p.min(0), rep_p.max(0)
    offset, scale = (lo + hi) / 2, (hi - lo) / 2
    a = monomials((rep_p - offset) / scale, degree)
    qe = quat_mul(ref_q, conj(rep_q))
    qe *= np.sign(qe[:, :1])
    b = np.hstack([ref_p - rep_p, qe[:, 1:]])
    coef, *_ = np.linalg.lstsq(a, b, rcond=None)
    return offset, scale, coef


def numpy_apply(model, p, q, degree=4):
    offset, scale, coef = model
    e = monomials((p - offset) / scale, degree) @ coef
    v = e[:, 3:]
    w = np.sqrt(np.clip(1 - (v * v).sum(1), 0, None))
    return p + e[:, :3], quat_mul(np.hstack([w[:, None], v]), q)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--build", default="build", help="CMake build folder")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--ridge-chain", action="store_true",
                    help="also fit plane + dipole + a degree-8 polynomial with ridge 0.25 (slow)")
    ap.add_argument("--skip-default-chain", action="store_true",
                    help="skip the chain fitted with the default solver settings and covariance")
    ap.add_argument("--before-fit", default=None,
                    help="another trackcal-fit binary (e.g. main's) to fit the default chain with in "
                         "the same run, for before/after ratios")
    args = ap.parse_args()
    sim = os.path.join(args.build, "sim", "trackcal-simulate")
    fit = os.path.join(args.build, "fit", "trackcal-fit")
    with tempfile.TemporaryDirectory() as tmp:
        cap = os.path.join(tmp, "cap")
        subprocess.run([sim, "--scene", "paper", "-o", cap], check=True, stdout=subprocess.DEVNULL)
        model = os.path.join(tmp, "model.yaml")
        with open(model, "w") as f:
            f.write("terms:\n  - type: polynomial\n    degree: 4\n")
        import csv
        with open(os.path.join(cap, "poses.csv")) as f:
            rows = [r for r in csv.DictReader(f)]
        def arr(rows, cols):
            return np.array([[float(r[c]) for c in cols] for r in rows])
        sets = {}
        for name in ("calib", "valid"):
            rs = [r for r in rows if r["set"] == name]
            sets[name] = (arr(rs, ["rep_x", "rep_y", "rep_z"]), arr(rs, ["rep_qw", "rep_qx", "rep_qy", "rep_qz"]),
                          arr(rs, ["ref_x", "ref_y", "ref_z"]), arr(rs, ["ref_qw", "ref_qx", "ref_qy", "ref_qz"]))
        np_times, tc_solve, tc_cov, tc_total = [], [], [], []
        # One untimed numpy fit first: the first call pays numpy's one-time set-up (about 1.5 ms,
        # 4-5x a fit), which with --repeat 1 was the baseline of every ratio below.
        numpy_paper_fit(*sets["calib"])
        for i in range(args.repeat):
            t0 = time.perf_counter()
            model_np = numpy_paper_fit(*sets["calib"])
            np_times.append(time.perf_counter() - t0)
            out = subprocess.run([fit, "fit", "--data", cap, "--model", model, "-o",
                                  os.path.join(tmp, f"calib{i}.json"), "--json", "--quiet"],
                                 check=True, capture_output=True, text=True)
            doc = json.loads(out.stdout)
            tc_solve.append(doc["fit"]["seconds_solve"])
            tc_cov.append(doc["fit"]["seconds_covariance"])
            tc_total.append(doc["fit"]["seconds"])
        p, q, rp, rq = sets["valid"]
        cp, cq = numpy_apply(model_np, p, q)
        before_p = np.linalg.norm(rp - p, axis=1).mean()
        after_p = np.linalg.norm(rp - cp, axis=1).mean()
        before_o = angle_deg(quat_mul(rq, conj(q))).mean()
        after_o = angle_deg(quat_mul(rq, conj(cq))).mean()
        valid = doc["tables"][1]
        # numpy applies its polynomial everywhere; trackcal's file also clamps to the calibrated volume,
        # so the validation figures differ slightly at stations outside the calibration box.
        print(f"numpy lstsq (paper method) : fit {1e3 * min(np_times):7.2f} ms (best of {args.repeat}); "
              f"valid improvement position {100 * (1 - after_p / before_p):.1f} %, "
              f"orientation {100 * (1 - after_o / before_o):.1f} %")
        print(f"trackcal degree-4 fit      : fit {1e3 * min(tc_solve):7.2f} ms (best of {args.repeat}; "
              f"+ covariance {1e3 * min(tc_cov):.1f} ms ({doc['fit'].get('covariance_method')}), "
              f"total {1e3 * min(tc_total):.1f} ms); "
              f"valid improvement position {valid['improvement_percent']['position_mean']:.1f} %, "
              f"orientation {valid['improvement_percent']['orientation_mean']:.1f} %")
        base = min(np_times)
        print(f"ratio to numpy lstsq       : degree-4 solve {min(tc_solve) / base:.1f}x, "
              f"with covariance {min(tc_total) / base:.1f}x")
        # The "fit time" is what `trackcal-fit fit` spends fitting: initialisation, solve and
        # the standard deviations it reports by default (reading and writing files excluded).
        ok = min(tc_total) <= 0.050
        print("degree-4 fit time target (<= 50 ms, with covariance):", "met" if ok else "NOT met")

        def run_chain(name, text, repeats, fit=fit):
            """Fits the chain `repeats` times; returns (last JSON document, wall list, CPU list)."""
            chain_model = os.path.join(tmp, f"{name}.yaml")
            with open(chain_model, "w") as f:
                f.write(text)
            walls, cpus = [], []
            for i in range(repeats):
                stdout, cpu = run_timed([fit, "fit", "--data", cap, "--model", chain_model, "-o",
                                         os.path.join(tmp, f"{name}{i}.json"), "--json", "--quiet"])
                doc = json.loads(stdout)
                walls.append(doc["fit"]["seconds"])
                cpus.append(cpu)
            return doc, walls, cpus

        def print_chain(label, doc, walls, cpus, target=True):
            valid = doc["tables"][1]
            blocks = {(p["term"], p["block"]): p for p in doc["fit"]["parameters"]}
            plane = blocks.get(("plane", "distance_m"))
            plane_d = plane["values"][0]["value"] if plane else float("nan")
            print(f"{label:27s}: fit {min(walls):7.2f} s wall, {min(cpus):.2f} s CPU "
                  f"(best of {len(walls)}; covariance {doc['fit']['seconds_covariance']:.2f} s wall"
                  f" ({doc['fit'].get('covariance_method')}); "
                  f"{doc['fit']['iterations']} iterations, "
                  f"{doc['fit']['num_free_parameters']} parameters); valid position mean "
                  f"{valid['after']['position_mm']['mean']:.2f} mm (improvement "
                  f"{valid['improvement_percent']['position_mean']:.1f} %), orientation "
                  f"{valid['after']['orientation_deg']['mean']:.3f} deg; searched plane distance "
                  f"{plane_d:.3f} m")
            print(f"ratio to numpy lstsq       : chain wall {min(walls) / base:.0f}x, "
                  f"chain CPU {min(cpus) / base:.0f}x")
            if target:  # the target is for a chain with a LUT and two physical terms
                print("chain fit time target (<= 5 s CPU):", "met" if min(cpus) <= 5.0 else "NOT met")

        doc, walls, cpus = run_chain("chain", CHAIN_MODEL, max(1, min(args.repeat, 3)))
        print_chain("trackcal plane+dipole+LUT", doc, walls, cpus)
        if args.ridge_chain:
            # The best chain of fit/best_chain_sim_test (a ridge polynomial after the physical terms):
            # ~1000 parameters whose normal matrix is dense (docs/model-file.md, solver).
            doc, walls, cpus = run_chain("ridge_chain", RIDGE_CHAIN_MODEL, 1)
            print_chain("plane+dipole+ridge deg. 8", doc, walls, cpus, target=False)
        if not args.skip_default_chain:
            # The same chain as a user writes it: the default solver tolerance and the default
            # standard deviations (sandwich, which a LUT's size turns into the model covariance).
            doc, walls, cpus = run_chain("chain_defaults", CHAIN_MODEL_DEFAULTS, max(1, min(args.repeat, 3)))
            print_chain("  the same, solver defaults", doc, walls, cpus)
            if args.before_fit:
                doc_b, walls_b, cpus_b = run_chain("chain_defaults_before", CHAIN_MODEL_DEFAULTS,
                                                   max(1, min(args.repeat, 3)), fit=args.before_fit)
                print_chain("  the same, --before-fit", doc_b, walls_b, cpus_b, target=False)
                print(f"after / before (defaults)  : CPU {min(cpus) / min(cpus_b):.2f}x, "
                      f"wall {min(walls) / min(walls_b):.2f}x")
                # The fast path against the reference: the same fitted values to well below their
                # standard deviations, the same standard deviations.
                after = {(p["term"], p["block"]): p for p in doc["fit"]["parameters"]}
                worst_value, worst_std = 0.0, 0.0
                for p in doc_b["fit"]["parameters"]:
                    q = after[(p["term"], p["block"])]
                    for v, w in zip(p["values"], q["values"]):
                        if not isinstance(v, dict) or not isinstance(w, dict):
                            continue
                        sb, sa = v.get("stddev"), w.get("stddev")
                        v, w = v["value"], w["value"]
                        if sb is not None and sa is not None and sb == sb and sb > 0:
                            worst_value = max(worst_value, abs(v - w) / sb)
                            worst_std = max(worst_std, abs(sa - sb) / sb)
                print(f"after vs before (defaults) : largest value change {worst_value:.2g} sigma, "
                      f"largest relative stddev change {worst_std:.2g}; valid position mean "
                      f"{doc_b['tables'][1]['after']['position_mm']['mean']:.6f} -> "
                      f"{doc['tables'][1]['after']['position_mm']['mean']:.6f} mm")
        return 0


if __name__ == "__main__":
    sys.exit(main())
