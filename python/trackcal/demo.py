"""The main job (README's first command, ``scripts/demo.sh``) on the embedded default.

The loop a lab runs, with the Fastrak emulator and the physics simulator standing in for the
hardware and the optical reference:

1. simulate a paper-protocol capture (the room of sim/ preset ``paper``, a five-height grid:
   ``DEFAULT_SCENE``) with an effect the paper's polynomial model lacks (``--hidden``, default a
   2.5 cm / 3.1 deg sensor offset);
2. fit the base model (``--base``; default the paper's degree-4 polynomial, with ``ridge: auto``
   when the calibration stations lie on 2-4 layers along an axis: ``base_model_for``) with
   ``trackcal-fit``;
3. diagnose: rank the catalog effects the model lacks (``trackcal.diagnose_candidates`` in
   process, cross-validating the ``--cross-validate-top N`` best by BIC; ``trackcal-fit diagnose
   --json`` when the package has no ranking), name the top significant one and show the
   model-file change; write the changed model as a new file, refit, and repeat until nothing
   significant is left (at most ``--max-steps`` changes);
4. show the error after every change (validation set, against the simulator's noise floor), record
   every fit in the work folder's ``history.jsonl`` and write the HTML report of the final model;
5. serve: start the Fastrak emulator on a pseudo-terminal (same scene, same hidden effect) and
   ``trackcal-server`` with a vrpn.cfg that attaches the final calibration, so any VRPN client gets
   ``Tracker0@localhost`` (corrected) and ``Tracker0_raw@localhost`` until interrupted.

Every run writes into a fresh work folder (never over an earlier one); every model and calibration
is a new file. ``--no-serve`` stops before serving, for scripts.

The loop itself is :func:`follow_diagnosis`, used by the workflow tests (python/tests/test_workflow.py).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import datetime as _dt
import inspect
import json
import math
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Callable, Dict, List, Optional, Sequence, Tuple

from trackcal._signals import signals_deferred
# The model-file edit of every step; trackcal diagnose makes the same one.
from trackcal.diagnosis import apply_model_change

DEFAULT_HIDDEN = "sensor_offset"
DEFAULT_MAX_STEPS = 8
# The diagnosis fits every candidate once and cross-validates only the best 2 by BIC (trackcal-fit
# diagnose --cross-validate-top): about half the time of cross-validating all of them; the others
# are reported as screened out, never significant.
DEFAULT_CROSS_VALIDATE_TOP = 2
# The ranking's own default (fit/candidates.h CandidateOptions::cross_validate_top, and
# trackcal-fit diagnose's): what the workflow loops use.
RANKING_CROSS_VALIDATE_TOP = 3

# The embedded default scene: the paper's room, tracker and protocol (base: paper) with a capture
# of five heights (the paper's text: a 12 x 10 x 5 grid), here 8 x 6 x 5 at the paper's 0.15 m
# over the middle 1.05 x 0.75 x 0.6 m and 60 validation stations in the same box. Five heights,
# because on the preset's four a degree-4 polynomial after a physical correction is nearly
# singular along z (measured: the validation error of the paper preset rose from 4.9 to 8.1 mm
# when the first physical term was added); the smaller grid keeps the loop to minutes. The stream
# keeps the preset's 30 s: on 20 s of this path the degree-4 polynomial mimics a time shift
# (docs/diagnose.md, Known limits). tests/data/workflow/paper_small.yaml is the same scene
# (test_demo checks it).
DEFAULT_SCENE = """\
base: paper
name: paper_small
capture:
  calibration:
    origin_in_transmitter: [-0.525, -0.375, -0.875]
    counts: [8, 6, 5]
    spacing_m: 0.15
  validation:
    count: 60
    min_in_transmitter: [-0.525, -0.375, -0.875]
    max_in_transmitter: [0.525, 0.375, -0.275]
  registration:
    count: 6
  stream:
    duration_s: 30
"""

PAPER_MODEL = """\
# The paper's method (Ikits et al. 2001, eq. 7-9) at degree 4: polynomials of the reported position
# for the position error and the vector part of the orientation error quaternion. (`trackcal
# validate --cross-validate` fits the same polynomial at degree 3: validation.polynomial_model.)
terms:
  - type: polynomial
    degree: 4
"""

# The base on a calibration grid with fewer heights than the polynomial's degree + 1: the same
# polynomial with ridge: auto (docs/understand.md, "Four heights").
PAPER_MODEL_FEW_HEIGHTS = PAPER_MODEL.replace(
    "terms:\n",
    "# ridge: auto: the calibration stations lie on fewer layers along an axis than the degree + 1,\n"
    "# so once physical terms before it put the reports onto the grid, an unshrunk polynomial swings\n"
    "# between and beyond the layers; its coefficients of degree >= 2 are shrunk by the weight that\n"
    "# best predicts held-out layers (docs/model-file.md, \"Polynomial ridge\").\n"
    "terms:\n").replace("    degree: 4\n", "    degree: 4\n    ridge: auto\n")


def grid_layers(values) -> int:
    """How many layers the coordinates `values` of a calibration grid fall into: a gap wider than 10
    times the median gap between neighbouring sorted values and a quarter of the widest starts a new
    one (the rule of the polynomial's blocked cross-validation, fit/terms_polynomial.h), and every
    layer must be thinner than half the narrowest gap between layers (scattered stations split at
    an unusually wide gap give two thick "layers": 0). 0 also when fewer than 3 values are given."""
    import numpy as np
    v = np.sort(np.asarray(values, dtype=float))
    if v.size < 3:
        return 0
    gaps = np.diff(v)
    if not np.any(gaps > 0):
        return 1
    threshold = max(10.0 * float(np.median(gaps)), 0.25 * float(gaps.max()))
    cuts = np.flatnonzero((gaps > threshold) & (gaps > 0))
    if cuts.size == 0:
        return 0
    layers = np.split(v, cuts + 1)
    thickest = max(float(layer[-1] - layer[0]) for layer in layers)
    return len(layers) if thickest < 0.5 * float(gaps[cuts].min()) else 0


def base_model_for(capture: Path) -> Tuple[str, Optional[str]]:
    """The loop's default base model for `capture` and why it differs from PAPER_MODEL (None when
    it does not): on calibration stations in fewer layers than the degree + 1 along some axis, the
    polynomial gets ridge: auto."""
    degree = 4  # PAPER_MODEL's
    from trackcal import captures
    poses = captures.load_poses(capture)
    calib = poses.reference_positions[poses.set == "calib"]
    if len(calib) == 0:
        calib = poses.reference_positions
    for axis, name in enumerate("xyz"):
        n = grid_layers(calib[:, axis])
        if 2 <= n < degree + 1:
            return PAPER_MODEL_FEW_HEIGHTS, (
                f"the calibration stations lie on {n} layers along {name}, fewer than the {degree + 1} "
                f"a degree-{degree} polynomial needs: its base gets ridge: auto")
    return PAPER_MODEL, None


# ----------------------------------------------------------------------------------------------
# Small helpers


def _tool(name: str) -> str:
    path = shutil.which(name)
    if path is None:
        raise SystemExit(
            f"trackcal demo: '{name}' is not on PATH; run ./scripts/demo.sh (it builds and installs it)")
    return path


def _run(cmd: List[str], log: Optional[Path] = None, echo: bool = True) -> str:
    if echo:
        print("$ " + " ".join(cmd), flush=True)
    proc = subprocess.run(cmd, text=True, capture_output=True)
    if log is not None:
        _write_new(log, proc.stdout + proc.stderr)
    if proc.returncode != 0:
        sys.stderr.write(proc.stdout + proc.stderr)
        raise SystemExit(f"trackcal demo: {Path(cmd[0]).name} failed with exit code {proc.returncode}")
    return proc.stdout


def _write_new(path: Path, text: str) -> Path:
    """Writes a new file atomically (temporary file + link): refuses to replace an existing file."""
    from trackcal._files import write_new
    try:
        return write_new(Path(path), text.encode("utf-8"), "exists; not overwriting it")
    except ValueError as e:
        raise SystemExit(f"trackcal demo: {e}") from None


def _fresh_work_dir(base: Path) -> Path:
    stamp = _dt.datetime.now(_dt.timezone.utc).strftime("%Y%m%dT%H%M%SZ")
    for i in range(1000):
        candidate = base / (stamp if i == 0 else f"{stamp}-{i}")
        try:
            candidate.mkdir(parents=True)
            return candidate
        except FileExistsError:
            continue
        except OSError as e:  # --work a file, or a folder that cannot be written
            raise SystemExit(f"trackcal demo: --work {base}: cannot make a work folder there: "
                             f"{e.strerror or e}") from None
    raise SystemExit(f"trackcal demo: cannot make a fresh work folder under {base}")


# ----------------------------------------------------------------------------------------------
# The engine: fits through trackcal-fit (it writes the calibration file), diagnosis in process
# (contract C) when the Python package has it, else through `trackcal-fit diagnose --json` (B).


def diagnosis_available() -> bool:
    """True when a candidate ranking can be run (Python API or trackcal-fit diagnose)."""
    return _python_diagnose() is not None or _cli_diagnose_available()


def _python_diagnose() -> Optional[Callable]:
    try:
        import trackcal
    except ImportError:  # pragma: no cover - the package is what runs this
        return None
    f = getattr(trackcal, "diagnose_candidates", None)
    available = getattr(getattr(trackcal, "diagnosis", None), "candidates_available", None)
    if f is None or (available is not None and not available()):
        return None
    return f


_cli_diagnose_cache: Dict[str, bool] = {}


def _cli_diagnose_available() -> bool:
    exe = shutil.which("trackcal-fit")
    if exe is None:
        return False
    if exe not in _cli_diagnose_cache:
        # The usage text (printed on bad usage) lists the commands this build has.
        proc = subprocess.run([exe], text=True, capture_output=True)
        _cli_diagnose_cache[exe] = "trackcal-fit diagnose" in proc.stdout + proc.stderr
    return _cli_diagnose_cache[exe]


def run_fit(data: Path, model: Path, calibration: Path, log: Path, folds: int = 5,
            start: Optional[Path] = None) -> dict:
    """trackcal-fit fit --json: returns its JSON document (tables, fit). ``start``: a previous
    fit's document (``trackcal-fit fit --start``), whose optimum the fit starts from."""
    cmd = [_tool("trackcal-fit"), "fit", "--data", str(data), "--model", str(model), "-o",
           str(calibration), "--folds", str(folds), "--json", "--quiet"]
    if start is not None:
        cmd += ["--start", str(start)]
    return json.loads(_run(cmd, log=log, echo=False))


def run_diagnose(data: Path, model: Path, log: Path, folds: int = 5,
                 cross_validate_top: int = RANKING_CROSS_VALIDATE_TOP) -> dict:
    """The ranked candidates (contract B's JSON document as a dict). ``cross_validate_top`` N > 0
    cross-validates only the N candidates with the best BIC (the others cannot be significant), 0
    every one; 3 is the ranking's own default."""
    f = _python_diagnose()
    if f is not None:
        kwargs = {"folds": folds}
        try:
            params = inspect.signature(f).parameters
        except (TypeError, ValueError):
            params = {}
        if "cross_validate_top" in params:
            kwargs["cross_validate_top"] = cross_validate_top
        elif cross_validate_top != RANKING_CROSS_VALIDATE_TOP:
            f = None  # this in-process ranking cannot take the option: the command line can
        if f is not None:
            doc = f(str(data), str(model), **kwargs)
            _write_new(log, json.dumps(doc, indent=1, default=str) + "\n")
            return doc
    cmd = [_tool("trackcal-fit"), "diagnose", "--data", str(data), "--model", str(model),
           "--folds", str(folds), "--json", "--quiet"]
    cmd += ["--cross-validate-top", str(cross_validate_top)]
    out = _run(cmd, echo=False)
    _write_new(log, out)
    return json.loads(out)


# ----------------------------------------------------------------------------------------------
# Scores


def held_out_table(fit_doc: dict) -> dict:
    """The held-out table of a trackcal-fit document: the validation set, else cross-validation."""
    tables = fit_doc.get("tables", [])
    for want in ("valid", "cross"):
        for t in tables:
            if str(t.get("set", "")).startswith(want):
                return t
    if not tables:
        raise ValueError("trackcal-fit printed no error table")
    return tables[-1]


def _mean(stats: dict, key: str) -> float:
    return float(stats[key]["mean"])


def noise_floor(capture: Path) -> Optional[dict]:
    """The simulator's noise floor of the validation set (truth.json), or None for real data."""
    truth = Path(capture) / "truth.json"
    if not truth.is_file():
        return None
    stats = json.loads(truth.read_text()).get("statistics", {}).get("valid", {})
    return stats.get("noise_floor")


@dataclasses.dataclass
class Step:
    """One fit of the loop and what the diagnosis said after it."""
    index: int
    label: str                      # what changed ("base" for the first fit)
    model_path: Path
    calibration_path: Path
    fit: dict                       # trackcal-fit fit --json document
    diagnosis: Optional[dict] = None
    added: Optional[dict] = None    # the candidate added after this fit (its JSON object)

    @property
    def held_out(self) -> dict:
        return held_out_table(self.fit)

    @property
    def position_mm(self) -> float:
        return _mean(self.held_out["after"], "position_mm")

    @property
    def orientation_deg(self) -> float:
        return _mean(self.held_out["after"], "orientation_deg")


def top_significant(diagnosis: dict) -> Optional[dict]:
    """The best candidate the diagnosis calls significant, or None."""
    verdict = diagnosis.get("verdict") or {}
    cands = diagnosis.get("candidates") or []
    sig = [c for c in cands if c.get("significant")]
    if not sig:
        return None
    want = verdict.get("effect")
    for c in sig:  # the verdict names the top significant effect; take that row
        if want is None or c.get("effect") == want:
            return c
    return sig[0]


def _data_files(capture: Path) -> List[tuple]:
    capture = Path(capture)
    if capture.is_file():
        return [(capture, "calib+valid")]
    files = [(capture / "poses.csv", "poses")] if (capture / "poses.csv").is_file() else []
    if not files:
        files = [(p, "stream") for p in sorted(capture.glob("*_stream.csv"))]
    return files


def _record(work: Path, step: Step, data: Path) -> None:
    from trackcal import history
    scores = {}
    for t in step.fit.get("tables", []):
        scores[str(t["set"])] = {"position_mm": t["after"]["position_mm"],
                                 "orientation_deg": t["after"]["orientation_deg"],
                                 "hemisphere_flips_left_out": int(t.get("hemisphere_flips_left_out", 0))}
    history.record_fit(work, model=step.model_path, data=_data_files(data), scores=scores,
                       label=step.label,
                       extra={"calibration": str(step.calibration_path),
                              "calibration_sha256": _sha(step.calibration_path),
                              "step": step.index})


def _sha(path: Path) -> str:
    from trackcal import _core
    return _core.sha256_file(Path(path))


# A source the loop adds is grown from this fraction of its strength when the fit from the change's
# values ends above the cost of the model without it (fit/candidates.cc does the same per candidate).
GROW_FROM_FRACTION = 1e-3
_STRENGTH = re.compile(r"^([ \t]*(?:-[ \t]+)?(?:polarisability_m3|attenuation):[ \t]*)"
                       r"([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)([ \t]*(?:#.*)?)$", re.M)
_SOURCE_ITEM = re.compile(r"^-[ \t]+(?:\{[ \t]*)?type:[ \t]*(dipole|plane)\b", re.M)


def grown_change(change: str) -> Optional[str]:
    """``change`` (a candidate's ``model_change``: block-style ``terms:`` items) with every dipole's
    polarisability and plane's attenuation at GROW_FROM_FRACTION of its value, where it was placed;
    None when it adds no dipole or plane, or when not every one's strength is a plain value there."""
    count = 0

    def scale(m: "re.Match") -> str:
        nonlocal count
        count += 1
        return f"{m.group(1)}{float(m.group(2)) * GROW_FROM_FRACTION:.4g}{m.group(3)}"

    out = _STRENGTH.sub(scale, change)
    sources = len(_SOURCE_ITEM.findall(change))
    return out if sources and count == sources else None


def _final_cost(doc: dict) -> float:
    cost = (doc.get("fit") or {}).get("final_cost")
    return float(cost) if isinstance(cost, (int, float)) else math.inf


def follow_diagnosis(data: Path, base_model: str, work: Path, *, max_steps: int = DEFAULT_MAX_STEPS,
                     folds: int = 5, cross_validate_top: int = RANKING_CROSS_VALIDATE_TOP,
                     record: bool = True,
                     say: Callable[[str], None] = print) -> List[Step]:
    """The workflow of docs/understand.md, "The main job": fit the base model, diagnose, add the
    top significant candidate to the model file, refit, and repeat until the diagnosis finds nothing
    significant or ``max_steps`` changes were made. Every model and calibration is a new file in
    ``work/models``; every fit is recorded in ``work/history.jsonl`` when ``record``."""
    if not diagnosis_available():
        raise RuntimeError("no candidate ranking: neither trackcal.diagnose_candidates nor "
                           "'trackcal-fit diagnose' is installed")
    work = Path(work)
    models = work / "models"
    models.mkdir(parents=True, exist_ok=True)
    steps: List[Step] = []
    text, label = base_model, "base"
    grown_text = None  # the last change with its sources grown from near zero (grown_change)
    seen_changes = set()
    # Each fit after the first starts at the previous step's optimum (its fit document, written as
    # stepN.start.json): the model with the added term holds the one before it, so the refit
    # continues from there instead of from the model file's starts, where the polynomial and its
    # `ridge: auto` weight are chosen afresh (the path diagnose's candidates take as well; the
    # weight is kept: trackcal-fit fit --start, docs/fit.md).
    start = None
    replacing = False  # this step's change replaces a term
    for i in range(max_steps + 1):
        model = _write_new(models / f"step{i}.yaml", text)
        calib = models / f"step{i}.json"
        t0 = time.monotonic()
        # A replacement removes a term the previous optimum was fitted with (the polynomial's
        # coefficients hold the replaced source's share), so its fit starts from the model file
        # (measured, full paper capture, seed 1: the floor plane replaced by a dipole at its image
        # ended at cost 1108 from the previous optimum, validation 1.39 mm, against 515 and
        # 0.49 mm before the swap; from the model file at 358 and 0.77 mm).
        if replacing:
            start = None
        doc = run_fit(data, model, calib, models / f"step{i}.fit.log", folds=folds, start=start)
        if grown_text is not None and _final_cost(doc) > _final_cost(steps[-1].fit):
            # The model with the added source fits worse than the model without it: its fit from
            # the change's values left the last optimum for a worse one. Grow the source from near
            # zero instead and keep the fit that ends lower (measured, full paper capture,
            # ferromagnetic_object seed 2: a dipole at the floor's image added after the frame and
            # the toolbox, cost 909 before, 1603 from the change's values, 439 grown). The costs
            # are the fits' objectives, a polynomial's ridge prior included: both fits start at
            # the previous step's optimum and keep its `ridge: auto` weight, so the costs are of
            # one objective.
            grown_model = _write_new(models / f"step{i}.grown.yaml", grown_text)
            grown_calib = models / f"step{i}.grown.json"
            try:
                grown = run_fit(data, grown_model, grown_calib, models / f"step{i}.grown.fit.log",
                                folds=folds, start=start)
            except SystemExit as e:  # keep the first fit
                say(f"  growing the added source from near zero failed: {e}")
                grown = {}
            keep = _final_cost(grown) < _final_cost(doc)
            say(f"  the fit from the change's values ended at cost {_final_cost(doc):.6g}, above "
                f"the {_final_cost(steps[-1].fit):.6g} before the change; grown from "
                f"{GROW_FROM_FRACTION:g} of its strength: {_final_cost(grown):.6g} "
                f"({'kept: ' + grown_model.name if keep else 'not kept'})")
            if record and grown:  # every fit is recorded: the one not kept first
                other = (Step(i, f"{label} (first attempt, not kept)", model, calib, doc) if keep
                         else Step(i, f"{label} (grown, not kept)", grown_model, grown_calib, grown))
                _record(work, other, data)
            if keep:
                model, calib, doc, text = grown_model, grown_calib, grown, grown_text
        step = Step(i, label, model, calib, doc)
        steps.append(step)
        if doc.get("fit"):
            start = _write_new(models / f"step{i}.start.json",
                               json.dumps({"fit": doc["fit"]}) + "\n")
        if record:
            _record(work, step, data)
        say(f"step {i} ({label}): fitted in {time.monotonic() - t0:.1f} s; held-out error "
            f"{step.position_mm:.3f} mm, {step.orientation_deg:.4f} deg")
        if i == max_steps:
            say(f"stopping after {max_steps} changes (--max-steps)")
            break
        t0 = time.monotonic()
        step.diagnosis = run_diagnose(data, model, models / f"step{i}.diagnose.json", folds=folds,
                                      cross_validate_top=cross_validate_top)
        best = top_significant(step.diagnosis)
        say(f"  diagnosed in {time.monotonic() - t0:.1f} s")
        if best is None:
            verdict = (step.diagnosis.get("verdict") or {}).get("text") or \
                "no candidate effect is significant"
            say("  diagnosis: " + verdict)
            break
        # (A removal's change is empty: the model it is made on tells one removal from another of a
        # later term that took the same name.)
        key = (best.get("effect"), best.get("replaces"), best.get("model_change"),
               text if best.get("kind") == "removal" else None)
        if key in seen_changes:  # the same change again means the ranking is not converging
            say(f"  diagnosis proposes {best.get('effect')} again with the same change; stopping")
            break
        seen_changes.add(key)
        step.added = best
        removal = best.get("kind") == "removal"  # a term the data no longer identify, removed
        if removal:
            say(f"  {best['replaces']} is no longer identified by these data: "
                f"{best.get('statement') or ''}".rstrip(": "))
        elif best.get("replaces"):
            say(f"  {best['replaces']} is better explained as {best.get('effect')}: "
                f"{best.get('statement') or ''}".rstrip(": "))
        else:
            say(f"  missing effect: {best.get('effect')}: {best.get('statement') or ''}".rstrip(": "))
        if best.get("reason"):
            say(f"  because {best['reason']}")
        where = (f" (replaces terms: item {best.get('insert_index')}, {best['replaces']})"
                 if best.get("replaces") else "")
        if removal:
            say(f"  model-file change: remove terms: item {best.get('insert_index')} "
                f"({best['replaces']})")
        else:
            say(f"  model-file change{where}:\n" + "\n".join(
                "    + " + l for l in str(best.get("model_change", "")).rstrip().splitlines()))
        previous = text
        replacing = bool(best.get("replaces"))
        text = apply_model_change(previous, best["model_change"], best.get("insert_index"),
                                  best.get("replaces"))
        grown = None if best.get("replaces") else grown_change(str(best.get("model_change", "")))
        grown_text = (apply_model_change(previous, grown, best.get("insert_index"), None)
                      if grown else None)
        label = (f"-{best['replaces']}" if removal
                 else f"{best['replaces']} -> {best.get('effect')}" if best.get("replaces")
                 else f"+{best.get('effect')}")
    return steps


def steps_table(steps: List[Step], floor: Optional[dict] = None) -> str:
    """Before/after table: the held-out error after every change (and against the noise floor)."""
    fp = _mean(floor, "position_mm") if floor else None
    fo = _mean(floor, "orientation_deg") if floor else None
    head = f"{'step':>4}  {'change':<22} {'pos mean mm':>11} {'change':>8} {'ori mean deg':>12} {'change':>8}"
    if fp:
        head += f" {'x floor':>8}"
    lines = [head]
    first = steps[0].held_out
    lines.append(f"{'':>4}  {'uncorrected':<22} {_mean(first['before'], 'position_mm'):>11.3f} {'':>8} "
                 f"{_mean(first['before'], 'orientation_deg'):>12.4f} {'':>8}"
                 + (f" {_mean(first['before'], 'position_mm') / fp:>8.1f}" if fp else ""))
    prev = None
    for s in steps:
        p, o = s.position_mm, s.orientation_deg
        dp = f"{100 * (p - prev[0]) / prev[0]:+.1f}%" if prev else ""
        do = f"{100 * (o - prev[1]) / prev[1]:+.1f}%" if prev else ""
        row = f"{s.index:>4}  {s.label[:22]:<22} {p:>11.3f} {dp:>8} {o:>12.4f} {do:>8}"
        if fp:
            row += f" {p / fp:>8.2f}"
        lines.append(row)
        prev = (p, o)
    if fp:
        lines.append(f"{'':>4}  {'noise floor (truth)':<22} {fp:>11.3f} {'':>8} {fo:>12.4f} {'':>8} {1.0:>8.2f}")
    return "\n".join(lines)


# ----------------------------------------------------------------------------------------------
# The main job


def write_report(capture: Path, calibration: Path, diagnosis_doc: Optional[dict], work: Path, out: Path,
                 notes: Sequence[str] = ()) -> Path:
    """The HTML report of the final calibration with the last diagnosis (candidate table, verdict;
    None: the final model was not diagnosed, ``notes`` say why) and the work folder's history plot,
    without ranking the candidates again; with the notes `trackcal report` gives a validation."""
    import trackcal
    from trackcal import captures, diagnosis, history, report, validation
    v = validation.validate(captures.load_poses(str(capture)), trackcal.Calibration.load(str(calibration)))
    verdict = diagnosis.verdict_with_regions(
        diagnosis.verdict(diagnosis_doc, v.covariate_effects, v.covariates_tested), v)
    path = report.write_report(v, out, inputs=[capture, calibration],
                               history_entries=history.load_history(work), candidates=diagnosis_doc,
                               verdict=verdict, notes=list(notes) + diagnosis.validation_notes(v))
    print(f"wrote {path}")
    return path



def unranked_final_note(steps: Sequence[Step], max_steps: int, capture: Path) -> str:
    """What the demo's report says of the catalog effects when --max-steps stopped the loop before
    it diagnosed the final model: which step's model was ranked last, and how to rank the final
    one. (`trackcal report` without --model said "give --model to rank them" right after the loop
    had ranked them.)"""
    final = steps[-1]
    ranked = [s for s in steps if s.diagnosis is not None]
    how = f"trackcal diagnose {capture} --model {final.model_path} ranks them"
    if not ranked:
        return (f"catalog effects not tested: --max-steps {max_steps} stopped the loop before any "
                f"diagnosis; {how}")
    return (f"catalog effects last ranked for the model of step {ranked[-1].index} (the history below); "
            f"the final model (step {final.index}) was not ranked again: --max-steps {max_steps} stopped "
            f"the loop; {how}")


def simulate(work: Path, hidden: str, seed: Optional[int], scene: str = "paper") -> Path:
    capture = work / "capture"
    cmd = [_tool("trackcal-simulate"), "--scene", scene, "-o", str(capture)]
    if hidden:
        cmd += ["--hidden", hidden]
    if seed is not None:
        cmd += ["--seed", str(seed)]
    print(_run(cmd), end="")
    return capture


def fit(work: Path, capture: Path, model_text: str, name: str) -> Path:
    """One fit with trackcal-fit, its Table 1 printed (the main job without a candidate ranking)."""
    model = _write_new(work / f"{name}.yaml", model_text)
    calib = work / f"{name}.json"
    out = _run([_tool("trackcal-fit"), "fit", "--data", str(capture), "--model", str(model), "-o",
                str(calib)], log=work / f"{name}.log")
    print(out, end="")
    return calib


# How far inside the calibrated volume the emulated receivers stay while serving [m]. The volume is
# the box of *reported* positions the fit saw, the emulator's box is of true positions: reported and
# true differ by the room's distortion and the sensor offset (a few cm in the paper room), so
# without a margin the poses near the faces are served extrapolated.
SERVE_MARGIN_M = 0.05


def serving_box(calibration: Path, margin_m: float = SERVE_MARGIN_M):
    """The calibration's calibrated_volume shrunk by ``margin_m`` (at most a quarter of its extent
    per axis), as (min, max) lists in metres, or None when the file has no volume."""
    volume = json.loads(Path(calibration).read_text()).get("calibrated_volume")
    if not volume:
        return None
    lo, hi = [float(v) for v in volume["min"]], [float(v) for v in volume["max"]]
    m = [min(margin_m, (b - a) / 4.0) for a, b in zip(lo, hi)]
    return [a + d for a, d in zip(lo, m)], [b - d for b, d in zip(hi, m)]


def port_unavailable(port: int) -> Optional[str]:
    """Why trackcal-server could not serve on ``port`` (TCP listener and UDP socket on every
    address, SO_REUSEADDR, as vrpn_server/server/server.cc binds them), or None when it could."""
    import socket
    for kind, name in ((socket.SOCK_STREAM, "TCP"), (socket.SOCK_DGRAM, "UDP")):
        with socket.socket(socket.AF_INET, kind) as s:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                s.bind(("0.0.0.0", port))
                if kind == socket.SOCK_STREAM:
                    s.listen()
            except OSError as e:
                return f"cannot bind {name} port {port}: {e.strerror or e}"
    return None


_STATUS_COUNTS = re.compile(r"(\S+): (\d+) corrected, (\d+) extrapolated")


def served_counts(server_log: Path, tracker: str = "Tracker0"):
    """(corrected, extrapolated) from the last status line the server logged for ``tracker``, or
    None when it logged none (it logs one at stop)."""
    if not server_log.exists():
        return None
    counts = None
    for line in server_log.read_text(errors="replace").splitlines():
        if "status:" not in line:
            continue
        for name, corrected, extrapolated in _STATUS_COUNTS.findall(line):
            if name == tracker:
                counts = (int(corrected), int(extrapolated))
    return counts


def serve(work: Path, calib: Optional[Path], hidden: str, seed: Optional[int], port: int,
          seconds: Optional[float], scene: str = "paper") -> None:
    # Absolute paths: trackcal-server reads a relative path in vrpn.cfg from the file's folder, so
    # the default --work demo-runs (relative) named demo-runs/<run>/demo-runs/<run>/models/... there.
    work = Path(work).resolve()
    calib = Path(calib).resolve() if calib is not None else None
    device = work / "fastrak"
    emulate_cmd = [_tool("trackcal-emulate"), "--scene", scene, "--link", str(device), "--binary",
                   "--continuous"]
    box = serving_box(calib) if calib is not None else None
    if box is not None:
        # Serve where the calibration was measured: poses outside its volume are extrapolated.
        emulate_cmd += ["--within", ",".join(f"{v:.4f}" for v in box[0] + box[1])]
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
    _write_new(cfg, "\n".join(lines) + "\n")
    procs: List[subprocess.Popen] = []
    logs = contextlib.ExitStack()  # the children's log files, closed once they are stopped
    try:
        print("$ " + " ".join(emulate_cmd), flush=True)
        procs.append(subprocess.Popen(emulate_cmd, stdout=subprocess.DEVNULL,
                                      stderr=logs.enter_context(open(work / "emulator.log", "w"))))
        deadline = time.monotonic() + 10.0
        while not device.exists():
            if procs[0].poll() is not None or time.monotonic() > deadline:
                raise SystemExit(f"trackcal demo: the emulator did not start; see {work / 'emulator.log'}")
            time.sleep(0.05)
        server_cmd = [_tool("trackcal-server"), "-f", str(cfg), str(port)]
        print("$ " + " ".join(server_cmd), flush=True)
        procs.append(subprocess.Popen(server_cmd, stdout=logs.enter_context(open(work / "server.log", "w")),
                                      stderr=subprocess.STDOUT))
        print(f"\nServing on port {port}: Tracker0@localhost:{port} (corrected)"
              + (f", Tracker0_raw@localhost:{port} (raw)" if calib is not None else "")
              + f". Logs in {work}.")
        print("Press Ctrl-C to stop." if seconds is None else f"Stopping after {seconds:g} s.",
              flush=True)
        end = None if seconds is None else time.monotonic() + seconds
        while end is None or time.monotonic() < end:
            for p, log in zip(procs, ("emulator.log", "server.log")):
                if p.poll() is not None:
                    why = _last_error(work / log)
                    raise SystemExit(f"trackcal demo: {Path(p.args[0]).name} exited with code "
                                     f"{p.returncode}" + (f" ({why})" if why else "")
                                     + f"; see {work / log}")
            time.sleep(0.2)
    except KeyboardInterrupt:
        print("\nstopping")
    finally:
        # A second Ctrl-C (or a SIGTERM) while the children stop must not leave them running:
        # the signals wait until they are stopped, then the first one's exit stands.
        with signals_deferred((signal.SIGINT, signal.SIGTERM, signal.SIGHUP)):
            for p in reversed(procs):
                if p.poll() is None:
                    p.send_signal(signal.SIGTERM)
            for p in reversed(procs):
                try:
                    p.wait(timeout=5)
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait()
            logs.close()
        counts = served_counts(work / "server.log") if calib is not None else None
        if counts is not None and counts[0] > 0:
            print(f"Served {counts[0]} corrected poses; {counts[1]} "
                  f"({100.0 * counts[1] / counts[0]:.1f} %) extrapolated outside the calibrated volume.",
                  flush=True)


def _last_error(log: Path) -> Optional[str]:
    """The last line of a child's log that says "error" (stripped), or None."""
    try:
        lines = log.read_text(errors="replace").splitlines()
    except OSError:
        return None
    errors = [l.strip() for l in lines if "error" in l.lower()]
    return errors[-1] if errors else None


class Stopped(Exception):
    """SIGTERM or SIGHUP arrived: unwinds the job so the children it started are stopped."""

    def __init__(self, signum: int):
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


def _raise_stopped(signum, _frame):
    raise Stopped(signum)


def main(argv: Optional[List[str]] = None) -> int:
    """The main job; SIGTERM and SIGHUP stop it like Ctrl-C does, children included, and it exits
    with 128 + the signal's number (143, 129), as a shell reports a process the signal ended; Ctrl-C
    before serving exits with 130 (while serving it stops the emulator and the server, status 0)."""
    handled = (signal.SIGTERM, signal.SIGHUP)
    previous = {s: signal.getsignal(s) for s in handled}
    for s in handled:
        signal.signal(s, _raise_stopped)
    made = []  # the work folder once made: the last line names it (its first line scrolled away)
    try:
        return _main(argv, made)
    except Stopped as e:
        print(f"\ntrackcal demo: stopped by {e}{_kept(made)}", file=sys.stderr, flush=True)
        return 128 + e.signum
    except KeyboardInterrupt:  # Ctrl-C before serving (simulating, fitting, diagnosing): no traceback
        print(f"\ntrackcal demo: interrupted{_kept(made)}", file=sys.stderr, flush=True)
        return 130
    finally:
        for s, h in previous.items():
            signal.signal(s, h)


def _kept(made: List[Path]) -> str:
    """"; what it wrote is in <work folder>" once the work folder exists, else ""."""
    return f"; what it wrote is in {made[0]}" if made else ""


def _main(argv: Optional[List[str]] = None, made: Optional[List[Path]] = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m trackcal.demo", description=__doc__.split("\n\n")[0])
    parser.add_argument("--work", type=Path, default=Path("demo-runs"),
                        help="folder under which a fresh, timestamped work folder is made")
    parser.add_argument("--scene", default=None,
                        help="scene preset or file (trackcal-simulate --scene); default: the paper room "
                             "with a five-height capture (DEFAULT_SCENE)")
    parser.add_argument("--hidden", default=DEFAULT_HIDDEN,
                        help="effect the base model lacks, as trackcal-simulate --hidden ('' for none)")
    parser.add_argument("--seed", type=int, default=None, help="simulation seed (default: the scene's)")
    parser.add_argument("--base", type=Path, default=None,
                        help="base model file (default: the paper's degree-4 polynomial, with "
                             "ridge: auto on a grid of 2-4 layers along an axis)")
    parser.add_argument("--max-steps", type=int, default=DEFAULT_MAX_STEPS,
                        help="at most this many model changes")
    parser.add_argument("--folds", type=int, default=5, help="cross-validation folds of the diagnosis")
    parser.add_argument("--cross-validate-top", type=int, default=DEFAULT_CROSS_VALIDATE_TOP,
                        help="cross-validate only the N candidates with the best BIC (0: all)")
    parser.add_argument("--port", type=int, default=3883, help="VRPN port of the server")
    parser.add_argument("--no-serve", action="store_true", help="stop after the report (for scripts)")
    parser.add_argument("--serve-seconds", type=float, default=None,
                        help="serve this long, then stop (default: until Ctrl-C)")
    args = parser.parse_args(argv)
    # Every option is checked before any work: a bad one found by trackcal-fit, the ranking or the
    # server failed only after the simulation, or after the whole loop (minutes) for the serving ones.
    if args.max_steps < 0:
        parser.error("--max-steps must be >= 0")
    if args.folds < 2:
        parser.error(f"--folds {args.folds}: must be at least 2 (the fits cross-validate)")
    if args.cross_validate_top < 0:
        parser.error(f"--cross-validate-top {args.cross_validate_top}: must be >= 0 (0: every candidate)")
    if not args.no_serve:
        if not 1 <= args.port <= 65535:
            parser.error(f"--port {args.port}: must be 1-65535")
        if args.serve_seconds is not None and not (math.isfinite(args.serve_seconds)
                                                   and args.serve_seconds > 0):
            parser.error(f"--serve-seconds {args.serve_seconds:g}: must be a positive number of seconds")
        busy = port_unavailable(args.port)
        if busy:
            parser.error(f"--port {args.port}: {busy}; the server could not serve there after the "
                         f"loop (another VRPN server? give another --port, or --no-serve)")

    try:
        base_text = None if args.base is None else args.base.read_text()
    except (OSError, UnicodeDecodeError) as e:  # missing, a folder, not text: before any work
        parser.error(f"--base {args.base}: {getattr(e, 'strerror', None) or e}")
    work = _fresh_work_dir(args.work)
    if made is not None:
        made.append(work)
    print(f"trackcal demo: work folder {work}")
    if args.scene is None:
        args.scene = str(_write_new(work / "scene.yaml", DEFAULT_SCENE))
    capture = simulate(work, args.hidden, args.seed, args.scene)
    if base_text is None:
        base_text, why = base_model_for(capture)
        if why:
            print(f"base model: {why}")
    floor = noise_floor(capture)
    final = None
    if diagnosis_available():
        print("\nThe loop: fit, diagnose, add the missing effect, refit.")
        steps = follow_diagnosis(capture, base_text, work, max_steps=args.max_steps, folds=args.folds,
                                 cross_validate_top=args.cross_validate_top)
        final = steps[-1]
        print("\nHeld-out error after each change (" + str(final.held_out.get("set")) + " set):")
        print(steps_table(steps, floor))
        print(f"\nFinal model: {final.model_path}\nFinal calibration: {final.calibration_path}")
        calib = final.calibration_path
    else:
        print("\ntrackcal demo: no candidate ranking installed (trackcal-fit diagnose); fitting the "
              "base model only")
        calib = fit(work, capture, base_text, "paper_polynomial")
    report = work / "report"
    if final is not None and final.diagnosis is not None:
        write_report(capture, calib, final.diagnosis, work, report)
    elif final is not None:  # --max-steps stopped the loop before it diagnosed the final model
        write_report(capture, calib, None, work, report,
                     notes=[unranked_final_note(steps, args.max_steps, capture)])
    else:
        print(_run([_tool("trackcal"), "report", str(capture), "-c", str(calib), "-o", str(report),
                    "--workdir", str(work)], log=work / "report.log"), end="")
    print(f"Report: {report / 'report.html'}")
    print(f"History: trackcal history {work}")
    if not args.no_serve:
        serve(work, calib, args.hidden, args.seed, args.port, args.serve_seconds, args.scene)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
