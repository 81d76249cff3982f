"""The workflow a user follows (issue #6), on simulated data with a hidden effect.

Start from the paper's degree-4 polynomial, diagnose, add the top significant candidate (or make
the replacement it proposes: docs/diagnose.md, "Replacements"), refit, and repeat until the
diagnosis finds nothing significant (``trackcal.demo.follow_diagnosis``, the
main job's loop). For every hidden effect of the simulator and three seeds, following it must

1. end by itself: the last diagnosis finds nothing significant (not the step cap);
2. add the term of the hidden effect, with every physical parameter within 3 standard deviations
   (the final fit's own standard deviations) of truth.json; for a combination of hidden effects
   (HIDDEN_COMBINATIONS), the term of each, compared in the fit's gauge where the effects share
   one (_truth_in_fit_gauge);
3. add no spurious physical term (rule below);
4. end within 1.5 times the noise floor on held-out data (position and orientation means);
5. record every fit in the work folder's history.

**Spurious** = a physical term of the final model that matches no true source of truth.json. The
true sources are the hidden effect *and the room's own* (the paper room's floor and door planes,
CRT monitors and workbench frame). The base model cannot reach the floor without the room:

- a degree-4 polynomial leaves 2.77 mm on the paper preset (31x the floor, seed 1); degree 6, 8,
  10 overfit and extrapolate worse (7.1, 29, 68 mm) and a 150 mm LUT after it still leaves 2.25 mm;
- on this file's capture it leaves 0.63 mm (10x); the room's true workbench frame and floor plane,
  held fixed before the polynomial, bring it to 1.18x (without the floor plane 1.76x, without the
  frame 9x; the monitors and the door, 1.9-2.1 m away, the polynomial absorbs: 1.03-1.11x);
  measured by correcting the reports with the true partial physical model and fitting the
  polynomial to the result.

So the loop must discover the room's near sources, and a term for a real plane or object is a true
finding. Matching (each true source matches at most one term):

- ``sensor_offset``, ``receiver_gain``, ``near_field``: the truth has that effect (offset not the
  identity, G not the identity, octupole not zero);
- ``dipole``: a true object within ``ROOM_MATCH_M`` of the fitted location, or the only true
  object within 3 sigma of it on every axis (a term whose uncertainty spans several sources
  represents none of them);
- ``plane``: a true plane whose normal is within ``ROOM_MATCH_DEG`` (sign-free) and whose offset
  from the transmitter along that normal is within ``ROOM_MATCH_M`` (signed: a plane on the other
  side of the transmitter is another plane), or within 3 sigma of the fitted distance when it is
  the only true plane so (a plane outside the volume trades its distance with its attenuation).

Types must agree: a plane never represents objects, a dipole never a plane. A plane through the two
CRT monitors (the sensor_offset loop, seed 1, before the search projected out the polynomial) or a
dipole at the floor's mirror image fits some of their field but says nothing true about them, so it
is spurious; the failure message names the nearest true source of the term's type, what is off,
and the sources of another type it stands in for.

The geometric tolerances are for the room's sources only, which share the volume with the
polynomial and other terms; the hidden effect's own term must pass the strict 3-sigma test of 2.

**Noise floor** = the error the true model leaves on the same data: truth.json's
``statistics.valid.noise_floor`` for static captures; for the clock offset (stream-only data) the
true physical model (a calibration file built from truth.json) applied to the streams paired at
the true clock offset. Flipped stations (hemisphere_flips) are left out of the final error: no
correction of a reported pose can undo the solver's hemisphere ambiguity (the robust loss keeps
them from biasing the fit), and the floor counts them as if they were known.

Capture: ``tests/data/workflow/paper_small.yaml``: the paper room with 240 calibration stations
(8 x 6 x 5 at 0.15 m over 1.05 x 0.75 x 0.6 m) and 60 validation stations instead of 480 + 120, so
18 loops fit the CI time.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from trackcal import demo
from understand_support import stream_only

ROOT = Path(__file__).resolve().parents[2]
SCENE = ROOT / "tests" / "data" / "workflow" / "paper_small.yaml"

# Room sources: a term within this distance of a true object's location (or of a true plane's
# distance along its normal) represents it. 0.15 m is a quarter of the distance from the nearest
# room source (the workbench frame) to the captured volume, and the room's true sources are more
# than 0.9 m apart, so a match cannot pick the wrong one.
ROOM_MATCH_M = 0.15
# Planes: the normal's direction, by the same principle: a quarter of the 90 deg between the room's
# two planes. (First set to 10 deg; a loop then fitted the floor plane 12.9 deg tilted, at 0.755 m
# +- 0.32 against the true 0.8 m, with no standard deviation reported for the normal.)
ROOM_MATCH_DEG = 22.5
# A background_field term (the smooth field of sources too far to place one by one) represents the
# true room sources no other term matched that lie at least this far from the box of the true
# station positions: in the workflow scene the paper room's CRT monitors are 1.24 to 1.43 m from it
# and its door 1.73 m, its nearest sources 0.52-0.55 m (the workbench frame) and 0.97-1.00 m (the
# floor; the box varies with the seed's stations), midway: 1.1 m. A background with no such source
# left is spurious.
FAR_SOURCE_M = 1.1
SIGMAS = 3.0           # the "within three standard deviations"
FLOOR_FACTOR = 1.5     # the "within 1.5 times the noise floor"

HIDDEN_EFFECTS = ["sensor_offset", "receiver_gains", "ferromagnetic_object",
                  "finite_transmitter_coils", "clock_offset", "hemisphere_flips"]
# Hidden effects together, "+"-joined (the simulator's --hidden list): a real receiver has an
# offset sensor and imperfect coils at once, and the two meet in a gauge (_truth_in_fit_gauge);
# every transmitter has coils of finite size. Measured (session 30, five loops at once on the 2
# cores, 18-34 min each): sensor_offset+receiver_gains goes offset, G, frame dipole, floor plane,
# background, then nothing, on seeds 1, 2, 3 and 5 (seed 4: a dipole at the floor's image before
# the background and the plane, then its removal), 1.09x-1.22x / 1.06x-1.13x the floor, nothing
# spurious, every parameter within 3 sigma in the fit's gauge on seeds 1 and 3-5, not on seed 2
# (_XFAIL); finite_transmitter_coils+receiver_gains goes G, near field, frame, floor, background,
# then nothing, on seeds 1-3, 1.03x-1.08x / 1.02x-1.12x the floor, and passes (seed 1 alone
# through pytest on a quiet machine: 350 s).
HIDDEN_COMBINATIONS = ["sensor_offset+receiver_gains", "finite_transmitter_coils+receiver_gains"]
SEEDS = [1, 2, 3]

# Which loops run: TRACKCAL_WORKFLOW_TESTS unset or "ci": CI_LOOPS (one seed per effect, what fits
# CI's budget, see LOOP_TIMES); "full": every effect on 3 seeds; "none": no loop; else a
# comma-separated list of effects or combinations (3 seeds each) or effect:seed items
# ("clock_offset:2", "sensor_offset+receiver_gains:1"; any seed, "sensor_offset:4" adds a loop on
# a seed outside SEEDS).
_SELECTED = os.environ.get("TRACKCAL_WORKFLOW_TESTS", "").strip() or "ci"
# Measured (branch `loops`, main with the chain clamping only explicit terms), wall time of one loop
# at a time under nice -n 5 on the 2 shared cores of the development machine, under a load of 10-17
# from other developers' builds and loops (a quiet machine takes roughly half):
#   hemisphere_flips          seed 1: 219 s, seed 2: ~300 s, seed 3: ~190 s (pass); on branch
#                             flips (session 5, load ~10): 180 s, 387 s, 266 s (pass: loss, frame
#                             dipole, floor plane; 1.10x, 1.22x, 1.22x the floor)
#   receiver_gains            seed 1: 166 s, seed 2: 85 s, seed 3: 110 s (then xfail: G 3.3-5.4
#                             sigma off); session 10 (with background_field, pass): 212, 175, 196 s
#   ferromagnetic_object      seed 1: 69 s (457 s when it went on to 4 fits), seed 2: 208 s (xfail)
#   finite_transmitter_coils  seed 1 and hemisphere_flips seed 1 together (the CI default): 391 s
#                             at load ~15, both pass
# and earlier (seed 1, main before the clamp change, load ~12):
#   finite_transmitter_coils 174 s (passes: near_field, frame, floor; 1.11x the floor)
#   sensor_offset             363 s (xfail: one spurious term, see _XFAIL)
#   clock_offset             1284 s (passes, 0.99x the floor). Not the pairing (the time_offset
#                            candidate, pairing included, takes 0.6 s): every candidate is fitted
#                            on the 2398 stream samples, 10x the static stations; the physical
#                            candidates' start searches and solves take the time (docs/diagnose.md,
#                            "Where the time goes on streams"). Session 6 (main adafed4, load
#                            10-14, seed 1): 3474 s wall, 696 s CPU, passes (time_offset, then the
#                            frame dipole; diagnoses 689 / 1407 / 1236 s wall, fits 0 / 5 / 133 s).
#                            Branch diagspeed (fold refits hold a bounded plane, two loops and
#                            builds at once, load 12-14): the same models and held-out errors step
#                            by step (1.3707 / 0.6235 / 0.4962 mm); diagnoses 840 / 691 / 667 s
#                            (step 1 2.0x: its plane's folds no longer go to the solver; steps 0
#                            and 2 the same work, the load differed); 2458 s wall, 630 s CPU
#                            (1.10x less CPU), passes. Seed 2 (branch only):
#                            diagnoses 1369 / 594 / 333 s, 2491 s wall, 654 s CPU: time_offset
#                            then the frame dipole (2.06 -> 0.79 -> 0.49 mm), nothing spurious, but
#                            FAILS: the offset 35.71 +- 0.26 ms against 37 (5.0 sigma). The joint
#                            fit's estimate (trackcal-fit fit), which this branch did not change;
#                            main was not run on seed 2 (not verified there).
# The split: CI (TRACKCAL_WORKFLOW_TESTS unset) runs three loops that pass, finite_transmitter_coils
# and hemisphere_flips on seed 1 (391 s for both at load ~15 here; session 3's whole pytest run with
# three loops, these two and sensor_offset, took 114 s on a quiet machine) and, since session 10,
# receiver_gains seed 1 (the distant sources' bias on G that background_field removes). The xfail
# loops (_XFAIL) and the other seeds run with TRACKCAL_WORKFLOW_TESTS=full (all 18 single effects, about 1.5 h there, and the combinations; clock_offset alone
# ~20 min on the 20 s stream; its 30 s stream since session 12 took 47-50 min per seed with three
# seeds and a CI run sharing the 2 cores). One pytest process: the diagnoses already use both cores (candidates in parallel
# threads), so pytest-xdist would not help. The xfail ones still must run to their assertions
# (xfail(raises=AssertionError): a crash fails the test).
CI_LOOPS = {("finite_transmitter_coils", 1), ("hemisphere_flips", 1), ("receiver_gains", 1)}
pytestmark = [
    pytest.mark.skipif(shutil.which("trackcal-simulate") is None or shutil.which("trackcal-fit") is None,
                       reason="command-line tools not installed (run scripts/build.sh)"),
]


def _selected(hidden: str, seed: int) -> bool:
    if _SELECTED == "ci":
        return (hidden, seed) in CI_LOOPS
    if _SELECTED in ("full", "none"):
        return _SELECTED == "full"
    items = [x.strip() for x in _SELECTED.split(",")]
    return hidden in items or f"{hidden}:{seed}" in items


# ----------------------------------------------------------------------------------------------
# Data


def _simulate(out: Path, hidden: str, seed: int) -> Path:
    subprocess.run(["trackcal-simulate", "--scene", str(SCENE), "--hidden", hidden.replace("+", ","),
                    "--seed", str(seed),
                    "-o", str(out)], check=True, capture_output=True, text=True)
    return out


# ----------------------------------------------------------------------------------------------
# Parameters of the final fit


def _blocks(fit_doc: dict) -> dict:
    """{term name: {block name: (values, stddevs)}} from trackcal-fit --json's fit.parameters
    (values as [{name, value, stddev}] or as contract B's parallel lists)."""
    out: dict = {}
    for b in fit_doc["fit"]["parameters"]:
        if isinstance(b.get("values"), list) and b["values"] and isinstance(b["values"][0], dict):
            vals = [v["value"] for v in b["values"]]
            sds = [v.get("stddev") for v in b["values"]]
        else:
            vals, sds = list(b["values"]), list(b.get("stddev") or [None] * len(b["values"]))
        if b.get("tangent"):  # manifold blocks: stddevs in the tangent space (rotation vector, angles)
            sds = [t.get("stddev") for t in b["tangent"]]
        sds = [math.nan if s is None else float(s) for s in sds]
        out.setdefault(b["term"], {})[b["block"]] = (np.asarray(vals, float), np.asarray(sds, float))
    return out


_BLOCK_KIND = {"location_in_transmitter": "dipole", "polarisability_m3": "dipole", "distance_m": "plane",
               "normal_in_transmitter": "plane", "attenuation": "plane", "gain_matrix": "receiver_gain",
               "octupole_m2": "near_field", "translation": "sensor_offset", "rotation": "sensor_offset",
               "coefficients": "background_field"}


def _physical_terms(fit_doc: dict) -> list:
    """[(kind, term name, blocks)] of the physical terms of a fit."""
    terms = []
    for name, blocks in _blocks(fit_doc).items():
        kinds = {_BLOCK_KIND[b] for b in blocks if b in _BLOCK_KIND}
        if kinds:
            assert len(kinds) == 1, f"term {name} mixes blocks of {kinds}"
            terms.append((kinds.pop(), name, blocks))
    return terms


def _rotation_vector_xyzw(q) -> np.ndarray:
    q = np.asarray(q, float)
    q = q / np.linalg.norm(q)
    if q[3] < 0:
        q = -q
    s = np.linalg.norm(q[:3])
    if s < 1e-15:
        return 2 * q[:3]
    return 2 * math.atan2(s, q[3]) * q[:3] / s


def _matrix_xyzw(q) -> np.ndarray:
    """The rotation matrix of a quaternion (x, y, z, w)."""
    x, y, z, w = np.asarray(q, float) / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def _rotation_vector_of(r) -> np.ndarray:
    """The rotation vector (axis times angle, rad) of a rotation matrix (angle below pi)."""
    w = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
    angle = math.acos(float(np.clip((np.trace(r) - 1) / 2, -1, 1)))
    return w / 2 if angle < 1e-12 else angle * w / (2 * math.sin(angle))


def _unit_mean_gain(fit_doc: dict) -> bool:
    """Whether the fit held trace G = 3 (gain_scale: the uniform gain is a gauge when a polynomial
    or LUT follows the physical group; trackcal-fit --json's effect description)."""
    return any(e.get("unit_mean_gain") for t in fit_doc.get("fit", {}).get("terms", [])
               for e in t.get("effects", []))


def _truth_in_fit_gauge(eff: dict, terms: list, unit_mean_gain: bool = False):
    """(G, receiver_from_body translation, rotation vector, length scale) of the truth as the fit
    can report it.

    The receiver measures G R_s R_b^T B(p) at p = t_b - R_b R_s^T t_s (core/field.h SignalMatrix;
    body pose (R_b, t_b), receiver_from_body (R_s, t_s)): only the product G R_s is seen. Beside a
    free sensor_offset the fit therefore holds G symmetric (docs/model-file.md), which picks one
    factorisation: G = P U with P = sqrt(G G^T) symmetric and U a rotation. The same signal and
    position then come from (P, U R_s, U t_s), and that is the truth the fit's values estimate.
    When the fit also holds the mean gain at 1 (unit_mean_gain), its lengths inside the physical
    group are the true ones times c^(-1/3), c = trace(P) / 3 (a uniform gain c scales a dipole
    field's positions so; the polynomial after the group undoes it for positions, and the group's
    other lengths are fitted in those units): the translation compared is c^(-1/3) U t_s, and the
    length scale c^(-1/3) is returned for the other terms (an octupole in m^2 scales by its
    square). G itself is compared as 3 G / trace(G) by the caller. Without both terms, or with a G
    the fit did not hold symmetric, the truth as it is (scaled as above when the mean gain was
    held)."""
    g = np.asarray(eff["receiver_gain_matrix"], float)
    rfb = eff["receiver_from_body"]
    r_s, t_s = _matrix_xyzw(rfb["rotation_xyzw"]), np.asarray(rfb["translation"], float)
    fitted = [b["gain_matrix"][0].reshape(3, 3) for k, _, b in terms if k == "receiver_gain"]
    if fitted and np.allclose(fitted[0], fitted[0].T, rtol=0, atol=1e-12) and \
            any(k == "sensor_offset" for k, _, _ in terms):
        w, v = np.linalg.eigh(g @ g.T)
        p = v @ np.diag(np.sqrt(w)) @ v.T
        u = np.linalg.solve(p, g)
        g, r_s, t_s = p, u @ r_s, u @ t_s
    scale = (np.trace(g) / 3.0) ** (-1.0 / 3.0) if fitted and unit_mean_gain else 1.0
    return g, scale * t_s, _rotation_vector_of(r_s), scale


def _within(values, sds, truth, what: str) -> list:
    """Failures of |value - truth| <= SIGMAS sd per coordinate."""
    values, sds, truth = (np.asarray(x, float).ravel() for x in (values, sds, truth))
    fails = []
    for i, (v, s, t) in enumerate(zip(values, sds, truth)):
        if not math.isfinite(s):
            fails.append(f"{what}[{i}] = {v:.6g}, truth {t:.6g}: no standard deviation reported")
        elif not (abs(v - t) <= SIGMAS * s):
            fails.append(f"{what}[{i}] = {v:.6g} +- {s:.3g}, truth {t:.6g} ({abs(v - t) / s:.1f} sigma)")
    return fails


def _normal_of(blocks) -> np.ndarray:
    n = np.asarray(blocks["normal_in_transmitter"][0], float)
    return n / np.linalg.norm(n)


# ----------------------------------------------------------------------------------------------
# Truth


def _truth(capture: Path) -> dict:
    return json.loads((capture / "truth.json").read_text())


def _true_sources(truth: dict) -> list:
    """[(kind, name, parameters)] of every true source: the room's and the hidden ones."""
    eff = truth["effective"]
    fm = eff["field_model"]
    out = [("dipole", o["name"], o) for o in fm["objects"]]
    out += [("plane", p["name"], p) for p in fm["planes"]]
    if np.any(np.abs(fm["transmitter_octupole_m2"]) > 0):
        out.append(("near_field", "octupole", fm["transmitter_octupole_m2"]))
    if not np.allclose(eff["receiver_gain_matrix"], np.eye(3)):
        out.append(("receiver_gain", "G", eff["receiver_gain_matrix"]))
    rfb = eff["receiver_from_body"]
    if np.any(np.abs(rfb["translation"]) > 0) or abs(abs(rfb["rotation_xyzw"][3]) - 1) > 0:
        out.append(("sensor_offset", "receiver_from_body", rfb))
    return out


def _close(kind: str, blocks: dict, source) -> bool:
    """Within ROOM_MATCH_M (planes: and ROOM_MATCH_DEG) of a true source of the same kind."""
    skind, _, p = source
    if skind != kind:
        return False
    if kind == "dipole":
        loc = blocks["location_in_transmitter"][0]
        return bool(np.linalg.norm(loc - np.asarray(p["location_in_transmitter"], float)) <= ROOM_MATCH_M)
    if kind == "plane":
        tn = np.asarray(p["normal_in_transmitter"], float)
        tn /= np.linalg.norm(tn)
        if math.degrees(math.acos(float(np.clip(abs(_normal_of(blocks) @ tn), 0, 1)))) > ROOM_MATCH_DEG:
            return False
        return abs(_signed_offset(blocks, tn) - float(np.asarray(p["point_in_transmitter"], float) @ tn)) \
            <= ROOM_MATCH_M
    return True  # sensor_offset, receiver_gain, near_field: the truth has the effect


def _signed_offset(blocks: dict, direction) -> float:
    """The fitted plane's offset along ``direction`` (a unit vector near its normal, either sign):
    the plane is {x: n.x = d} with d = distance_m along normal_in_transmitter, so a plane on the
    other side of the transmitter (the door at -2.1 m along y against a fit at +1.65 m) differs by
    the sum of the distances, not their difference."""
    n = _normal_of(blocks)
    return float(blocks["distance_m"][0][0]) * (1.0 if n @ direction >= 0 else -1.0)


def _within_sigmas(kind: str, blocks: dict, source) -> bool:
    """Dipoles: the true location within 3 sigma of the fitted one on every axis. Planes: the
    normal within ROOM_MATCH_DEG of the true one and the true plane's offset along it within 3
    sigma of the fitted distance (a plane outside the volume trades its distance with its
    attenuation: ferromagnetic_object seed 5's floor at 0.96 +- 0.08 m against 0.8)."""
    skind, _, p = source
    if skind != kind:
        return False
    if kind == "dipole":
        loc, sd = blocks["location_in_transmitter"]
        return bool(np.all(np.abs(loc - np.asarray(p["location_in_transmitter"], float)) <= SIGMAS * sd))
    if kind == "plane":
        tn = np.asarray(p["normal_in_transmitter"], float)
        tn = tn / np.linalg.norm(tn)
        if math.degrees(math.acos(float(np.clip(abs(_normal_of(blocks) @ tn), 0, 1)))) > ROOM_MATCH_DEG:
            return False
        sd = float(blocks["distance_m"][1][0])
        off = _signed_offset(blocks, tn) - float(np.asarray(p["point_in_transmitter"], float) @ tn)
        return math.isfinite(sd) and abs(off) <= SIGMAS * sd
    return False


def _match(kind: str, blocks: dict, sources: list, all_sources: list):
    """The true source a term represents, or None. Close (ROOM_MATCH_M) counts; so does 3 sigma,
    but only when exactly one true source lies within the 3-sigma box: a term whose uncertainty
    spans several sources (a dipole at 1.8 m +- 1.3 m standing in for the floor's image) says
    nothing about any of them."""
    close = [s for s in sources if _close(kind, blocks, s)]
    if close:
        return close[0]
    inside = [s for s in all_sources if _within_sigmas(kind, blocks, s)]
    if len(inside) == 1 and inside[0] in sources:
        return inside[0]
    return None


def _spurious_terms(fit_doc: dict, truth: dict) -> list:
    all_sources = _true_sources(truth)
    free = list(all_sources)
    spurious = []
    terms = _physical_terms(fit_doc)
    for kind, name, blocks in terms:
        if kind == "background_field":
            continue
        hit = _match(kind, blocks, free, all_sources)
        if hit is None:
            spurious.append(f"{name} ({kind}): {_describe(blocks)}; {_why_unmatched(kind, blocks, all_sources, free)}")
        else:
            free.remove(hit)
    # After the located terms: a background stands for the distant sources they leave.
    for kind, name, _ in terms:
        if kind != "background_field":
            continue
        far = [s[1] for s in free
               if s[0] in ("dipole", "plane") and _distance_to_stations(s, truth) >= FAR_SOURCE_M]
        if not far:
            left = ", ".join(f"{s[1]} {_distance_to_stations(s, truth):.2f} m" for s in free
                             if s[0] in ("dipole", "plane")) or "none"
            spurious.append(f"{name} ({kind}): no unmatched true source {FAR_SOURCE_M} m or more from "
                            f"the stations (unmatched room sources: {left})")
        for s in list(free):
            if s[1] in far:
                free.remove(s)
    return spurious


def _distance_to_stations(source, truth: dict) -> float:
    """How far a true dipole or plane is from the box of the true station positions (inf for the
    other kinds, which are not sources in the room: the caller keeps to dipoles and planes)."""
    p = np.array([s["transmitter_from_receiver"]["translation"] for s in truth["stations"]], float)
    lo, hi = p.min(axis=0), p.max(axis=0)
    kind, _, params = source
    if kind == "dipole":
        x = np.asarray(params["location_in_transmitter"], float)
        return float(np.linalg.norm(x - np.clip(x, lo, hi)))
    if kind == "plane":
        n = np.asarray(params["normal_in_transmitter"], float)
        n /= np.linalg.norm(n)
        d = float(np.asarray(params["point_in_transmitter"], float) @ n)
        corners = np.array([[a, b, c] for a in (lo[0], hi[0]) for b in (lo[1], hi[1]) for c in (lo[2], hi[2])])
        s = corners @ n - d
        return float(0.0 if s.min() <= 0 <= s.max() else np.abs(s).min())
    return math.inf


def _why_unmatched(kind: str, blocks: dict, all_sources: list, free: list) -> str:
    """Why a term matches no true source, in words: the nearest source of its own type and what is
    off, and the true sources of another type it sits on (a plane through two monitors stands in
    for them: a term of the wrong type represents none of them)."""
    notes = []
    same = [s for s in all_sources if s[0] == kind]
    if not same:
        notes.append(f"the truth has no {kind}")
    elif kind == "dipole":
        loc = blocks["location_in_transmitter"][0]
        dist = {s[1]: float(np.linalg.norm(loc - np.asarray(s[2]["location_in_transmitter"], float)))
                for s in same}
        near = min(dist, key=dist.get)
        taken = "" if any(s[1] == near for s in free) else ", already matched by another term"
        notes.append(f"nearest true object {near} {dist[near]:.2f} m away (match: {ROOM_MATCH_M} m or "
                     f"the only one within {SIGMAS:g} sigma{taken})")
    elif kind == "plane":
        for s in same:
            tn = np.asarray(s[2]["normal_in_transmitter"], float)
            tn = tn / np.linalg.norm(tn)
            angle = math.degrees(math.acos(float(np.clip(abs(_normal_of(blocks) @ tn), 0, 1))))
            off = _signed_offset(blocks, tn) - float(np.asarray(s[2]["point_in_transmitter"], float) @ tn)
            notes.append(f"true plane {s[1]}: normal {angle:.0f} deg off (match: {ROOM_MATCH_DEG} deg), "
                         f"offset {off:+.2f} m (match: {ROOM_MATCH_M} m or {SIGMAS:g} sigma)")
    else:
        notes.append(f"already matched by another {kind} term")
    # Sources of another type that the term sits on.
    on = []
    for s in all_sources:
        if s[0] == kind or s[0] not in ("dipole", "plane"):
            continue
        if kind == "plane" and s[0] == "dipole":
            x = np.asarray(s[2]["location_in_transmitter"], float)
            d = abs(float(_normal_of(blocks) @ x) - float(blocks["distance_m"][0][0]))
            if d <= 2 * ROOM_MATCH_M:  # a note, not a match: as for the mirror image below
                on.append(f"{s[1]} ({d:.2f} m from the plane)")
        elif kind == "dipole" and s[0] == "plane":
            tn = np.asarray(s[2]["normal_in_transmitter"], float)
            tn = tn / np.linalg.norm(tn)
            x = np.asarray(blocks["location_in_transmitter"][0], float)
            # The transmitter's mirror image in the plane, where a dipole fits much of the plane's
            # field (a note, not a match: twice the room tolerance, since the image dipole of a
            # fit that also has a polynomial sits short of the exact image, 1.43 against 1.6 m).
            image = 2 * float(np.asarray(s[2]["point_in_transmitter"], float) @ tn)
            d = float(np.linalg.norm(x - image * tn))
            if d <= 2 * ROOM_MATCH_M:
                on.append(f"{s[1]}'s mirror image of the transmitter ({d:.2f} m from it)")
    if on:
        notes.append("it stands in for " + ", ".join(on) + ", a source of another type")
    return "; ".join(notes)


def _describe(blocks: dict) -> str:
    return ", ".join(f"{b}={np.array2string(v, precision=4)}+-{np.array2string(s, precision=2)}"
                     for b, (v, s) in blocks.items())


def _hidden_term_failures(hidden: str, final: "demo.Step", truth: dict) -> list:
    """Why the hidden effect's term is missing or off (empty: present, within 3 sigma)."""
    if "+" in hidden:  # a combination: every effect's term
        return [f for part in hidden.split("+") for f in _hidden_term_failures(part, final, truth)]
    eff = truth["effective"]
    terms = _physical_terms(final.fit)
    true_g, true_t_s, true_r_s, length_scale = _truth_in_fit_gauge(eff, terms, _unit_mean_gain(final.fit))
    if hidden == "hemisphere_flips":
        text = final.model_path.read_text()
        return [] if any(line.startswith("loss:") for line in text.splitlines()) else \
            ["no robust loss in the final model"]
    if hidden == "clock_offset":
        # trackcal-fit fit --json: "time_offset_s" (the offset the streams were paired at, which is
        # the joint fit's estimate when the model frees it) and the joint fit's parameter block
        # time_offset.value with its standard deviation (fit/fit_engine.cc).
        if final.fit.get("time_offset_s") is None:
            return ["no estimated time offset in the final fit"]
        sd = final.fit.get("time_offset_stddev_s")
        joint = _blocks(final.fit).get("time_offset", {}).get("value")
        if sd is None and joint is not None and math.isfinite(joint[1][0]):
            return _within([joint[0][0]], [joint[1][0]], [eff["reference_minus_tracker_s"]], "time_offset")
        if sd is None:
            return [f"time offset {final.fit['time_offset_s']:.6f} s (truth "
                    f"{eff['reference_minus_tracker_s']} s) has no standard deviation to test it against"]
        return _within([final.fit["time_offset_s"]], [sd], [eff["reference_minus_tracker_s"]], "time_offset")
    if hidden == "sensor_offset":
        cands = [b for k, _, b in terms if k == "sensor_offset"]
        if not cands:
            return ["no sensor_offset term"]
        b = cands[0]
        rot_v, rot_s = b["rotation"]
        rot = _rotation_vector_xyzw(rot_v) if rot_v.size == 4 else rot_v
        return (_within(b["translation"][0], b["translation"][1], true_t_s, "translation")
                + _within(rot, rot_s, true_r_s, "rotation vector"))
    if hidden == "receiver_gains":
        cands = [b for k, _, b in terms if k == "receiver_gain"]
        if not cands:
            return ["no receiver_gain term"]
        v, s = cands[0]["gain_matrix"]
        # With a polynomial or LUT after the physical group the uniform gain is a gauge (it scales
        # positions isotropically, which the polynomial absorbs): the fit holds trace G = 3, the
        # mean coil gain at 1 (docs/model-file.md, gain_scale), so G is compared as 3 G / trace(G)
        # on both sides.
        fitted = np.asarray(v, float).reshape(3, 3)
        true = true_g
        fitted = 3.0 * fitted / np.trace(fitted)
        true = 3.0 * true / np.trace(true)
        return _within(fitted.ravel(), s, true.ravel(), "gain_matrix (mean gain 1)")
    if hidden == "finite_transmitter_coils":
        cands = [b for k, _, b in terms if k == "near_field"]
        if not cands:
            return ["no near_field term"]
        v, s = cands[0]["octupole_m2"]
        return _within(v, s, length_scale ** 2 * np.asarray(eff["field_model"]["transmitter_octupole_m2"]),
                       "octupole_m2")
    if hidden == "ferromagnetic_object":
        obj = next(o for o in eff["field_model"]["objects"]
                   if o["name"] == truth["scene"]["hidden"]["ferromagnetic_object"]["name"])
        best = None
        for k, _, b in terms:
            if k != "dipole":
                continue
            f = (_within(*b["location_in_transmitter"],
                         length_scale * np.asarray(obj["location_in_transmitter"]), "location")
                 + _within(*b["polarisability_m3"], [length_scale ** 3 * obj["polarisability_m3"]],
                           "polarisability"))
            if best is None or len(f) < len(best):
                best = f
        return ["no dipole term"] if best is None else best
    raise AssertionError(f"unknown hidden effect {hidden}")


# ----------------------------------------------------------------------------------------------
# Held-out error and the floor


def _true_calibration(truth: dict) -> dict:
    """The true model as a calibration file (core/physical_correction.h entry)."""
    eff = truth["effective"]
    fm = eff["field_model"]
    return {
        "format": "trackcal-calibration", "version": 1, "description": "truth of a simulated capture",
        "units": {"length": "m"},
        "frames": {"pose": "transmitter_from_receiver", "errors": "transmitter"},
        "calibrated_volume": {"min": [-5, -5, -5], "max": [5, 5, 5], "extrapolation": "clamp",
                              "fade_distance": 0.0},
        "corrections": [{
            "type": "physical", "field_constant": fm["field_constant"],
            "transmitter_octupole_m2": fm["transmitter_octupole_m2"],
            "planes": fm["planes"], "objects": fm["objects"],
            "receiver_gain_matrix": eff["receiver_gain_matrix"],
            "receiver_from_body": eff["receiver_from_body"]}],
        "fit_statistics": {},
        "provenance": {"tool": "test_workflow", "tool_version": "0", "created_utc": "2026-01-01T00:00:00Z",
                       "command_line": "", "inputs": []},
    }


def _errors(capture_poses, calibration_path: Path, keep=None):
    import trackcal
    from trackcal import validation
    cal = trackcal.Calibration.load(str(calibration_path))
    cap = capture_poses if keep is None else capture_poses.subset(keep)
    p, q, _ = cal.correct(cap.reported_positions, cap.reported_quaternions_xyzw)
    r = validation.residuals(p, q, cap.reference_positions, cap.reference_quaternions_xyzw)
    return float(np.mean(r.position_mm)), float(np.mean(r.orientation_deg))


def _floor_and_final(hidden: str, capture: Path, data: Path, final: "demo.Step", tmp: Path):
    """((floor pos mm, floor ori deg), (final pos mm, final ori deg)) on held-out data."""
    from trackcal import captures
    truth = _truth(capture)
    if hidden == "clock_offset":
        paired = tmp / "true_pairs.csv"
        subprocess.run(["trackcal-fit", "pair", "--tracker", str(capture / "tracker_stream.csv"),
                        "--reference", str(capture / "reference_stream.csv"), "--time-offset",
                        repr(truth["effective"]["reference_minus_tracker_s"]), "-o", str(paired)],
                       check=True, capture_output=True, text=True)
        true_cal = tmp / "truth_calibration.json"
        true_cal.write_text(json.dumps(_true_calibration(truth)))
        floor = _errors(captures.load_poses(str(paired)), true_cal)
        held = final.held_out["after"]  # cross-validation of the stream pairs
        return floor, (held["position_mm"]["mean"], held["orientation_deg"]["mean"])
    nf = truth["statistics"]["valid"]["noise_floor"]
    poses = captures.load_poses(str(capture))
    flipped = set(truth["effective"].get("hemisphere_flipped_stations", []))
    keep = (poses.set == "valid") & ~np.isin(poses.station, sorted(flipped))
    return (nf["position_mm"]["mean"], nf["orientation_deg"]["mean"]), \
        _errors(poses, final.calibration_path, keep)


# ----------------------------------------------------------------------------------------------


# Session 2, measured with the ranking of the `candidates` branch and the terms of `physterms` (seed 1, the
# loop stopped by a 25 min time limit during its 4th diagnosis): base 0.640 mm -> +dipole (the
# workbench frame: (0.499, -0.002, 0.348) m, -0.0088 m^3, truth (0.5, 0, 0.35), -0.009) 0.121 ->
# +dipole_2 (at (0.02, 0.08, 1.48) +- (0.74, 0.57, 1.57) m: the floor plane's image at (0, 0, 1.6),
# taken as a dipole; the plane candidate scored lower) 0.102 -> +plane (normal (0.50, 0.79, -0.35),
# 0.68 m, attenuation -0.004: its image sits at the hidden toolbox (0.6, 0.95, -0.5); the dipole
# candidate's search did not find the toolbox) 0.068 mm, floor 0.063 (1.08x). The error criterion
# holds, but the hidden object is explained by a plane and the floor by a dipole: no dipole term
# for the toolbox, two spurious terms.
# receiver_gains and sensor_offset, seed 1 (stopped during the 5th diagnosis, 35 min): the hidden
# term comes first and right, then the workbench frame (dipole) and the floor (plane), at 1.2-1.3x
# the floor; then every diagnosis still finds a "significant" 10-20 % held-out gain for a term it
# cannot place (a second plane 0.51 +- 0.42 m away with its normal +- 186 deg; a dipole at
# (0.4, -1.5, -3.6) +- (2.6, 3.1, 3.8) m), which the rule counts as spurious.
_XFAIL = {
    # Session 10 (background_field in the catalog; main, a ctest run alongside): every loop below goes
    # hidden term -> dipole (the workbench frame) -> plane (the floor) -> background_field (the
    # monitors and the door), then nothing. Held-out error over the floor (position / orientation):
    #   sensor_offset:3      423x -> 13.9x -> 3.27x -> 1.555x -> 1.159x / 1.102x (failed at 1.555x before)
    #   receiver_gains:1-3   1.031x, 1.082x, 1.082x; G within 3 sigma (before: 3.3-5.4 sigma off)
    #   ferromagnetic_object:1  0.999x / 1.021x; the toolbox within 3 sigma (before: x 4.0 sigma off)
    #   sensor_offset:1-2    1.066x, 1.128x (1.338x, 1.470x before)
    #   finite_transmitter_coils:1-3  0.998x, 1.092x, 1.072x; hemisphere_flips:1-3 pass (seed 3 1.071x)
    # 140-212 s per loop. clock_offset seed 1: time offset, frame dipole, then nothing (the background
    # buys 1.6 % after the dipole), passes, ~30 min under a CI run. Session 11 (seeds 2-3 together,
    # 28 min, a build alongside): both go time offset, frame dipole, nothing; seed 3 passes, seed 2
    # failed at 35.71 ms against 37 (its last diagnosis found the background significant held out,
    # -3.0 %, p = 9.5e-9, 4.1 sigma, but did not claim it). On that 20 s stream the degree-4
    # polynomial mimics a time shift (docs/diagnose.md, Known limits). Session 12, the capture's
    # stream at the paper preset's 30 s (and the time_offset candidate fitting the offset jointly):
    # seeds 1-3 each go time offset (36.84 +- 0.19 ms on seed 2 at step 0), frame dipole, nothing,
    # and pass: the final offset 36.943 +- 0.029, 36.996 +- 0.030, 37.007 +- 0.015 ms (-2.0, -0.1,
    # +0.4 sigma; variance inflation 3.7, 2.8, 4.6), held out 1.028x / 1.002x, 1.057x / 1.010x,
    # 1.020x / 1.003x the floor; 47-50 min each, the three at once with a CI run alongside. Again
    # with diagnose holding the offset at fit's joint estimate (PairAtFittedOffset): the same steps
    # and final models, the step-1 base 0.923 / 1.070 / 1.154 mm held out (0.925 / 1.076 / 1.161
    # at the search's offset), 41-50 min each, three at once.
    # The toolbox (seeds 2-3 below), Monte Carlo in session 11: the same room, 29 seeds, fitted with
    # the true monitors and door held fixed plus a background (a model that contains the truth):
    # (est - truth) / stddev has rms 1.18 / 1.25 / 1.16 (location x, y, z) and 1.33 (polarisability)
    # with seeds 2, 3 and 108 at -2.6 to -3.5 on the polarisability; the reported stddev scales with
    # the estimate (a toolbox fitted weaker and nearer gets a smaller one: 0.00023-0.00066 m^3
    # against an empirical 0.00049), so the low tail is long. The loop's final model (a degree-1
    # background instead of the true sources), 9 seeds: z of location z has mean -1.2 (range -3.75 to
    # +0.67). Seeds 2-3 sit in the tail of both.
    "ferromagnetic_object:2": "main (session 10): dipole (frame), dipole_2 (the toolbox), plane (floor), "
                              "background_field, then nothing; 1.086x / 1.121x the floor, nothing spurious, "
                              "but the toolbox's location z ends at -0.550 +- 0.015 m against -0.5 (3.4 "
                              "sigma); before the background, x was 0.635 +- 0.011 against 0.6 (3.1 sigma). "
                              "Refitting the final model with a degree-0 background: z 3.3 sigma and the "
                              "polarisability 4.0 sigma off; degree 2: the toolbox within 3 sigma but the "
                              "floor plane slides to 1.04 m (spurious). A weak object (0.002 m^3) 0.58 m "
                              "outside the volume: its location and strength trade. Session 28: the same "
                              "final model and z (-0.5505 +- 0.0148). Not a Wald interval too short for a "
                              "nonlinear term: the fit with z held at -0.5 / -0.52 / -0.535 (x, y and the "
                              "rest free) costs 184 / 64 / 17 more in chi2 scaled to its chi2/dof, a profile "
                              "interval of +- 0.004, and the sandwich's 0.015 is already 4x that (the "
                              "residual is structure the model lacks, not noise). The room's other sources "
                              "that the polynomial and the degree-1 background stand in for bias it",
    "sensor_offset+receiver_gains:2": "session 30: offset, G, frame dipole, floor plane, background, then "
                                      "nothing; 1.19x / 1.13x the floor, nothing spurious, the offset's "
                                      "rotation and translation within 3 sigma in the fit's gauge, but "
                                      "G_yy (mean gain 1) 0.976806 +- 9.17e-06 against 0.976778: 3.05 "
                                      "sigma (the other 8 entries of G within 3)",
    "ferromagnetic_object:3": "main (session 10): the same terms as seed 2 (10.23x -> 1.94x -> 1.34x -> "
                              "1.154x -> 1.066x / 1.051x the floor), nothing spurious, but the toolbox ends "
                              "at (0.599, 0.911, -0.537) +- 0.010 in z against (0.6, 0.95, -0.5), z 3.7 "
                              "sigma off, polarisability 0.00131 against 0.002: pulled towards the volume "
                              "and weaker, as on seed 2 (not measured before background_field)",
}


def _extra_seeds() -> list:
    """(hidden, seed) items of TRACKCAL_WORKFLOW_TESTS with a seed outside SEEDS ("sensor_offset:4"):
    the same loop and checks on a seed the tests do not fix."""
    out = []
    if _SELECTED in ("ci", "full", "none"):
        return out
    for item in (x.strip() for x in _SELECTED.split(",")):
        hidden, _, seed = item.partition(":")
        if hidden in HIDDEN_EFFECTS + HIDDEN_COMBINATIONS and seed.isdigit() and int(seed) not in SEEDS:
            out.append((hidden, int(seed)))
    return out


def _loop_params() -> list:
    """(hidden, seed) for every loop, marked xfail by _XFAIL's effect or "effect:seed" key, and the
    extra seeds a run asks for (_extra_seeds)."""
    out = []
    pairs = [(h, seed) for h in HIDDEN_EFFECTS + HIDDEN_COMBINATIONS for seed in SEEDS] + _extra_seeds()
    for h, seed in pairs:
        reason = _XFAIL.get(f"{h}:{seed}", _XFAIL.get(h))
        marks = [pytest.mark.xfail(reason=reason, strict=False, raises=AssertionError)] if reason else []
        out.append(pytest.param(h, seed, marks=marks, id=f"{h}-{seed}"))
    return out


@pytest.mark.parametrize("hidden,seed", _loop_params())
def test_following_the_diagnosis_finds_the_hidden_effect(hidden, seed, tmp_path):
    if not demo.diagnosis_available():
        pytest.skip("no candidate ranking in this build (trackcal-fit diagnose)")
    if not _selected(hidden, seed):
        pytest.skip("not in this run's loops (TRACKCAL_WORKFLOW_TESTS: unset/ci runs CI_LOOPS, "
                    "full runs them all, or a list of effects or effect:seed items)")
    capture = _simulate(tmp_path / "capture", hidden, seed)
    data = stream_only(capture, tmp_path / "streams") if hidden == "clock_offset" else capture
    work = tmp_path / "work"
    log = []
    steps = demo.follow_diagnosis(data, demo.PAPER_MODEL, work, say=log.append,
                                  cross_validate_top=demo.DEFAULT_CROSS_VALIDATE_TOP)
    final = steps[-1]
    story = "\n".join(log) + "\n" + demo.steps_table(steps)
    truth = _truth(capture)

    # 1. The loop ended because nothing significant was left, not at the cap.
    assert final.diagnosis is not None and demo.top_significant(final.diagnosis) is None, story
    # 5. One history entry per fit, in order.
    from trackcal import history
    entries = history.load_history(work)
    assert [e["label"] for e in entries] == [s.label for s in steps], story
    # 2. The hidden effect's term, within 3 sigma of the truth.
    failures = _hidden_term_failures(hidden, final, truth)
    assert not failures, f"{hidden} seed {seed}: " + "; ".join(failures) + "\n" + story
    # 3. No spurious physical term.
    spurious = _spurious_terms(final.fit, truth)
    assert not spurious, f"{hidden} seed {seed}: spurious " + "; ".join(spurious) + "\n" + story
    # 4. Within 1.5x the noise floor on held-out data.
    (fp, fo), (p, o) = _floor_and_final(hidden, capture, data, final, tmp_path)
    assert p <= FLOOR_FACTOR * fp and o <= FLOOR_FACTOR * fo, (
        f"{hidden} seed {seed}: final {p:.4f} mm / {o:.4f} deg, floor {fp:.4f} mm / {fo:.4f} deg "
        f"({p / fp:.2f}x / {o / fo:.2f}x)\n" + story)


# ----------------------------------------------------------------------------------------------
# The rules above, on hand-made fit documents (fast; no ranking needed)


def _fit_doc(*terms) -> dict:
    """A trackcal-fit --json document with the given (term name, {block: (values, stddevs)})."""
    params = []
    for name, blocks in terms:
        for block, (v, sd) in blocks.items():
            sd = list(sd) if len(sd) == len(v) else [None] * len(v)  # a normal: tangent stddevs only
            params.append({"term": name, "block": block, "fixed": False, "unit": "",
                           "values": [{"name": str(i), "value": a, "stddev": b}
                                      for i, (a, b) in enumerate(zip(v, sd))]})
    return {"fit": {"parameters": params}}


@pytest.fixture(scope="module")
def toolbox_truth(tmp_path_factory):
    return _truth(_simulate(tmp_path_factory.mktemp("truth") / "capture", "ferromagnetic_object", 1))


def test_a_selection_can_add_seeds_outside_the_fixed_ones(monkeypatch):
    import sys
    monkeypatch.setattr(sys.modules[__name__], "_SELECTED",
                        "sensor_offset:4, receiver_gains, clock_offset:2, bogus:7, ferromagnetic_object:x")
    assert _extra_seeds() == [("sensor_offset", 4)]
    assert ("sensor_offset", 4) in [tuple(p.values) for p in _loop_params()]
    monkeypatch.setattr(sys.modules[__name__], "_SELECTED", "ci")
    assert _extra_seeds() == [] and \
        len(_loop_params()) == (len(HIDDEN_EFFECTS) + len(HIDDEN_COMBINATIONS)) * len(SEEDS)


def test_room_sources_are_findings_and_each_is_matched_once(toolbox_truth):
    frame = ("dipole", {"location_in_transmitter": ([0.46, 0.0, 0.41], [0.03, 0.02, 0.02]),
                        "polarisability_m3": ([-0.0127], [0.002])})
    floor = ("plane", {"distance_m": ([0.78], [0.01]), "normal_in_transmitter": ([0.02, 0.0, 1.0], [0.01, 0.01]),
                       "attenuation": ([0.27], [0.01])})
    assert _spurious_terms(_fit_doc(frame, floor), toolbox_truth) == []
    twice = _spurious_terms(_fit_doc(frame, ("dipole_2", frame[1])), toolbox_truth)
    assert len(twice) == 1 and twice[0].startswith("dipole_2"), "one true source, one term"


def test_a_term_that_represents_no_true_source_is_spurious(toolbox_truth):
    # A dipole standing in for the floor's image: its 3-sigma box spans several true objects.
    vague = ("dipole", {"location_in_transmitter": ([-0.25, 0.04, 1.78], [0.74, 0.60, 1.27]),
                        "polarisability_m3": ([-1.7], [8.0])})
    tilted = ("plane", {"distance_m": ([0.69], [0.14]), "normal_in_transmitter": ([0.49, 0.80, -0.34], [0.7, 0.7]),
                        "attenuation": ([-0.004], [0.013])})
    offset = ("sensor_offset", {"translation": ([0.001, 0.0, 0.0], [0.001, 0.001, 0.001])})
    assert len(_spurious_terms(_fit_doc(vague, tilted, offset), toolbox_truth)) == 3


def test_a_plane_standing_in_for_two_monitors_is_spurious(toolbox_truth):
    # The sensor_offset loop's last term (seed 1): 1.65 m along (0.47, 0.85, 0.23), through
    # crt_monitor_1 and crt_monitor_2. Its normal is 32 deg from the door's and it lies on the other
    # side of the transmitter (the door is at -2.1 m along y): no true plane; the monitors are
    # objects, which a plane cannot represent.
    n = np.array([0.47, 0.85, 0.23])
    monitors = ("plane_2", {"distance_m": ([1.65], [0.05]), "normal_in_transmitter": (list(n / np.linalg.norm(n)), [0.02, 0.02]),
                            "attenuation": ([-0.30], [0.03])})
    spurious = _spurious_terms(_fit_doc(monitors), toolbox_truth)
    assert len(spurious) == 1 and spurious[0].startswith("plane_2")
    assert "metal_door" in spurious[0] and "crt_monitor_1" in spurious[0] and "crt_monitor_2" in spurious[0], spurious
    # The door itself, fitted on its side (normal -y at +2.1 m is the same plane), is a finding.
    door = ("plane", {"distance_m": ([2.05], [0.1]), "normal_in_transmitter": ([0.0, -1.0, 0.02], [0.02, 0.02]),
                      "attenuation": ([0.2], [0.05])})
    assert _spurious_terms(_fit_doc(door), toolbox_truth) == []
    mirrored = ("plane", {"distance_m": ([2.05], [0.1]), "normal_in_transmitter": ([0.0, 1.0, 0.02], [0.02, 0.02]),
                          "attenuation": ([0.2], [0.05])})
    assert len(_spurious_terms(_fit_doc(mirrored), toolbox_truth)) == 1, "the door's mirror across the transmitter"


def test_a_plane_matches_by_its_distance_within_three_sigma(toolbox_truth):
    # ferromagnetic_object seed 5's last fit: the floor (0.8 m along +z) at 0.96 +- 0.077 m, its
    # distance and attenuation trading: 0.16 m off, 2.1 sigma, is the floor.
    floor = {"distance_m": ([0.9624], [0.0774]), "normal_in_transmitter": ([0.048, 0.061, 0.997], [0.06, 0.08]),
             "attenuation": ([0.64], [0.16])}
    assert _spurious_terms(_fit_doc(("plane", floor)), toolbox_truth) == []
    # The same offset with a tight distance is not; nor is a tilted plane (the angle rule still holds).
    tight = dict(floor, distance_m=([0.9624], [0.02]))
    assert len(_spurious_terms(_fit_doc(("plane", tight)), toolbox_truth)) == 1
    tilted = dict(floor, normal_in_transmitter=([0.5, 0.0, 0.866], [0.06, 0.08]))
    assert len(_spurious_terms(_fit_doc(("plane", tilted)), toolbox_truth)) == 1


def test_a_background_field_stands_for_the_distant_sources_only(toolbox_truth):
    background = ("background_field", {"coefficients": ([1e-3] * 24, [1e-4] * 24)})
    # The room's monitors and door (1.2 m or more from the stations) are left to it: a finding.
    assert _spurious_terms(_fit_doc(background), toolbox_truth) == []
    # With every distant source placed by a term of its own, it represents nothing.
    truth = json.loads(json.dumps(toolbox_truth))
    fm = truth["effective"]["field_model"]
    fm["objects"] = [o for o in fm["objects"] if not o["name"].startswith("crt_monitor")]
    fm["planes"] = [p for p in fm["planes"] if p["name"] != "metal_door"]
    spurious = _spurious_terms(_fit_doc(background), truth)
    assert len(spurious) == 1 and spurious[0].startswith("background_field"), spurious
    assert "workbench_frame" in spurious[0] and "floor_reinforcement" in spurious[0], spurious
    # A hidden effect no term found is no distant source either.
    truth["effective"]["receiver_gain_matrix"] = [[1.02, 0.01, 0], [-0.005, 0.98, 0.015], [0, 0.008, 1.01]]
    assert len(_spurious_terms(_fit_doc(background), truth)) == 1


def test_the_hidden_term_must_be_within_three_sigma(toolbox_truth):
    def final(loc, sd):
        step = demo.Step(0, "x", Path("m.yaml"), Path("c.json"), _fit_doc(
            ("dipole", {"location_in_transmitter": (loc, [sd] * 3), "polarisability_m3": ([0.002], [0.0001])})))
        return _hidden_term_failures("ferromagnetic_object", step, toolbox_truth)
    assert final([0.6 + 0.02, 0.95, -0.5], 0.01) == []            # 2 sigma off
    assert "location[0]" in final([0.6 + 0.04, 0.95, -0.5], 0.01)[0]  # 4 sigma off


def _gain_offset_truth():
    """A receiver with non-orthogonal coils (G not symmetric) and a sensor offset."""
    g = np.array([[1.02, 0.01, -0.004], [-0.005, 0.99, 0.015], [0.006, 0.008, 1.01]])
    q = np.array([0.02, -0.015, 0.01, 1.0])
    return {"effective": {"receiver_gain_matrix": g.tolist(), "receiver_from_body": {
        "rotation_xyzw": (q / np.linalg.norm(q)).tolist(), "translation": [0.012, -0.007, 0.02]}}}


def test_the_gauge_of_gain_and_offset_keeps_signal_and_position():
    # The claim of _truth_in_fit_gauge, checked on poses: (P, U R_s, U t_s) gives every body pose
    # the same signal G R_s R_b^T B(p) and the same receiver position p as (G, R_s, t_s).
    eff = _gain_offset_truth()["effective"]
    sym = ("receiver_gain", "g", {"gain_matrix": (np.eye(3).ravel(), np.ones(9))})
    p_g, t_g, r_g, _ = _truth_in_fit_gauge(eff, [sym, ("sensor_offset", "o", {})])
    assert np.allclose(p_g, p_g.T) and np.all(np.linalg.eigvalsh(p_g) > 0)
    g = np.asarray(eff["receiver_gain_matrix"])
    r_s = _matrix_xyzw(eff["receiver_from_body"]["rotation_xyzw"])
    t_s = np.asarray(eff["receiver_from_body"]["translation"])
    angle = np.linalg.norm(r_g)
    k = np.array([[0, -r_g[2], r_g[1]], [r_g[2], 0, -r_g[0]], [-r_g[1], r_g[0], 0]]) / angle
    r_s_g = np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k  # Rodrigues
    rng = np.random.default_rng(7)
    for _ in range(5):
        r_b = _matrix_xyzw(rng.normal(size=4))
        t_b = rng.uniform(-0.5, 0.5, 3)
        field = rng.normal(size=(3, 3))  # B(p): any 3x3 (p is the same in both gauges, below)
        assert np.allclose(g @ r_s @ r_b.T @ field, p_g @ r_s_g @ r_b.T @ field, atol=1e-12)
        assert np.allclose(t_b - r_b @ r_s.T @ t_s, t_b - r_b @ r_s_g.T @ t_g, atol=1e-12)
    # With the mean gain held at 1 (unit_mean_gain) the group's lengths are c^(-1/3) the true ones,
    # c = trace(P) / 3: the transmitter's dipole field is homogeneous of degree -3, so P / c at the
    # scaled position measures what P measures at the true one.
    _, t_u, _, scale = _truth_in_fit_gauge(eff, [sym, ("sensor_offset", "o", {})], unit_mean_gain=True)
    c = np.trace(p_g) / 3

    def dipole(x):
        r = np.linalg.norm(x)
        return (3 * np.outer(x, x) / r ** 2 - np.eye(3)) / r ** 3

    x = np.array([0.3, -0.2, -0.5])
    assert abs(c - 1) > 1e-3 and np.allclose(p_g / c @ dipole(scale * x), p_g @ dipole(x), rtol=1e-12)
    assert np.allclose(t_u, scale * t_g, rtol=1e-12)
    # No gauge to change without a sensor_offset, or when the fit's G is not symmetric.
    free_g = ("receiver_gain", "g", {"gain_matrix": (g.ravel(), np.ones(9))})
    for terms in ([sym], [free_g, ("sensor_offset", "o", {})]):
        assert np.allclose(_truth_in_fit_gauge(eff, terms)[0], g)


def test_a_gain_and_an_offset_together_are_compared_in_the_fit_gauge():
    truth = _gain_offset_truth()
    eff = truth["effective"]
    sym = ("receiver_gain", "g", {"gain_matrix": (np.eye(3).ravel(), np.ones(9))})
    p_g, t_g, r_g, _ = _truth_in_fit_gauge(eff, [sym, ("sensor_offset", "o", {})])
    p_g = 3 * p_g / np.trace(p_g)  # the fit's mean-gain-1 scale (the polynomial absorbs the rest)

    def failures(gain, translation, rotation):
        sd = 1e-5  # the size of the two-effect loop's stddevs (seed 4: 5e-6 to 5e-5)
        step = demo.Step(0, "x", Path("m.yaml"), Path("c.json"), _fit_doc(
            ("receiver_gain", {"gain_matrix": (list(np.ravel(gain)), [sd] * 9)}),
            ("sensor_offset", {"translation": (list(translation), [sd] * 3),
                               "rotation": (list(rotation), [sd] * 3)})))
        return _hidden_term_failures("sensor_offset+receiver_gains", step, truth)

    assert failures(p_g, t_g, r_g) == []
    # The same truth not carried into the gauge: the rotation and the translation are off by G's
    # rotation part (about 0.5 deg here, hundreds of sigma), as session 26's loop measured.
    naive = failures(p_g, eff["receiver_from_body"]["translation"],
                     _rotation_vector_xyzw(eff["receiver_from_body"]["rotation_xyzw"]))
    assert any("rotation vector" in f for f in naive) and any("translation" in f for f in naive)
    # Each effect's term is required (and without the offset there is no gauge: the symmetric G
    # is compared with the truth's own G, and fails).
    step = demo.Step(0, "x", Path("m.yaml"), Path("c.json"), _fit_doc(
        ("receiver_gain", {"gain_matrix": (list(p_g.ravel()), [1e-5] * 9)})))
    alone = _hidden_term_failures("sensor_offset+receiver_gains", step, truth)
    assert alone[0] == "no sensor_offset term" and any("gain_matrix" in f for f in alone[1:])
