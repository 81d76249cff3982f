"""Which physical effect is missing: the fit engine's ranking of candidate effects (contract B,
``trackcal-fit diagnose``), combined with the residual-vs-covariate analysis of
``trackcal.validation`` into one verdict, and the whole diagnosis as one JSON document.

- :func:`diagnose_candidates` fits the model, then the model plus each catalog effect it lacks, and
  ranks them by held-out error (the C++ ranking of fit/candidates.h, in process).
- :func:`verdict` combines the two analyses: the top significant candidate when there is one;
  otherwise, when a covariate explains residual structure, "no catalog effect explains the remaining
  structure; it follows covariate X (R^2 ..)"; otherwise the ranking's word on structure it
  finds but cannot place; otherwise "nothing significant remains".
- :func:`apply_model_change` applies a candidate's ``model_change`` to the model text (the exact
  model-file edit to make; used by ``trackcal diagnose`` and the main job's loop),
  :func:`diagnosis_document` assembles everything ``trackcal diagnose --json`` prints.
"""

from __future__ import annotations

import math
import re
from typing import Callable, Dict, List, Optional, Sequence

import numpy as np

from trackcal import _core
from trackcal._format import fixed

CandidatesDoc = Dict[str, object]


def candidates_available() -> bool:
    """True when this build has the engine's candidate ranking (fit/candidates.h)."""
    return hasattr(_core, "diagnose_candidates")


def diagnose_candidates(data, model, folds: int = 5, effects: Optional[Sequence[str]] = None,
                        progress: Optional[Callable[[str], None]] = None,
                        cross_validate_top: int = 3, sensor: Optional[int] = None) -> CandidatesDoc:
    """The ranking of candidate effects as a dict (the JSON document of ``trackcal-fit diagnose
    --json``): ``base`` (the model's own scores), ``candidates`` (best first: effect, model_change,
    insert_index, cross-validated errors, cv_drop_percent, delta_bic, p_value, significant, reason,
    parameters, statement) and ``verdict`` ({effect or None, text}).

    ``data``: capture folder, poses.csv or PoseCapture; ``model``: path or YAML text; ``effects``:
    restrict the catalog to these term types (None: all); ``progress(message)`` receives the
    ranking's progress messages ("fitting dipole (fold 3/5)"); ``cross_validate_top`` N > 0
    cross-validates only the N candidates with the best BIC (the others are reported screened
    out, never significant), 0 every one (docs/diagnose.md, Speed); ``sensor``: the receiver whose
    stations are ranked (None: the data must hold one sensor, as ``trackcal.fit``). Ctrl-C (or an exception from
    ``progress``) stops the ranking at its candidates' next stage and is raised."""
    if not candidates_available():
        raise NotImplementedError("this trackcal build has no candidate ranking (fit/candidates.h); "
                                  "the covariate analysis (trackcal diagnose) still works")
    from trackcal.fitting import _data_arg, _int_arg, _model_arg, _progress_arg, _sensor_arg
    data, model = _data_arg(data), _model_arg(model)
    folds, cross_validate_top = _int_arg(folds, "folds"), _int_arg(cross_validate_top, "cross_validate_top")
    if cross_validate_top < 0:
        raise ValueError("cross_validate_top must be >= 0")
    if effects is not None:
        effects = [effects] if isinstance(effects, str) else list(effects)
        if not effects:
            # An empty restriction would mean "no effect", but the native call reads an empty list
            # as "every effect": say so instead of ranking what was not asked for.
            raise ValueError("effects: an empty list restricts the catalog to nothing; pass None "
                             "for every effect")
    kwargs = {"folds": folds, "effects": effects,
              "cross_validate_top": cross_validate_top, "sensor": _sensor_arg(sensor)}
    if _progress_arg(progress) is not None:
        kwargs["progress"] = progress
    return _core.diagnose_candidates(data, model, **kwargs)


# ---------------------------------------------------------------------------------------------
# The verdict

TARGET_WORDS = {"position_mm": "position error magnitude", "position_vector": "position error vector",
                "orientation_deg": "orientation error angle", "orientation_vector": "orientation error vector"}
# The targets that carry a direction: a dependence there is a systematic error (a bin's mean error
# points somewhere); on the magnitudes alone it may be a scatter that changes size.
VECTOR_TARGETS = ("position_vector", "orientation_vector")


def covariate_findings(effects) -> List[dict]:
    """Significant covariates, one row each (its best residual target), strongest first."""
    best: Dict[str, object] = {}

    def rank(e):  # a finding that stands on its own before one another covariate explains away
        return (getattr(e, "confounded_with", None) is None, e.r2)

    for e in effects:
        if e.significant and (e.covariate not in best or rank(e) > rank(best[e.covariate])):
            best[e.covariate] = e
    rows = [{"covariate": e.covariate, "target": e.target, "r2": float(e.r2), "p_value": float(e.p_value),
             "count": int(e.count), "confounded_with": getattr(e, "confounded_with", None),
             "levels": getattr(e, "levels", None)}
            for e in best.values()]
    # A covariate another family explains away (time that position explains) goes after those
    # that stand on their own, whatever its R^2.
    rows.sort(key=lambda r: (r["confounded_with"] is not None, -r["r2"]))
    return rows


def top_candidate(doc: Optional[CandidatesDoc]) -> Optional[dict]:
    """The best significant candidate of a ranking (ranked best first), or None."""
    if not doc:
        return None
    for c in doc.get("candidates", []):
        if c.get("significant"):
            return c
    return None


def levels_phrase(levels: Optional[List[dict]], most: int = 4, say_rest: bool = True) -> str:
    """"bob 2.35 mm along (+2.33, -0.01, -0.27), 198 stations; carol ...": how far each label's mean
    error sits from the mean over all labels (``validation._levels``), largest first, each label's
    count in its own noun (a stream's: samples); empty for a numeric covariate."""
    if not levels:
        return ""

    def one(r):
        off = r["offset"]
        if isinstance(off, list):
            return (f"{r['label']} {r['size']:.3g} {r['unit']} along ("
                    + ", ".join(f"{v:+.2f}" for v in off) + f"), {r['count']} {r.get('points', 'stations')}")
        return f"{r['label']} {off:+.3g} {r['unit']}, {r['count']} {r.get('points', 'stations')}"

    text = "; ".join(one(r) for r in levels[:most])
    return text + (f"; {len(levels) - most} more" if say_rest and len(levels) > most else "")


def _covariate_phrase(rows: List[dict]) -> str:
    head = rows[0]
    by_label = levels_phrase(head.get("levels"))
    text = (f"it follows covariate {head['covariate']} (R^2 {head['r2']:.2f} of the "
            f"{TARGET_WORDS.get(head['target'], head['target'])}"
            + (f"; each {head['covariate']}'s mean error from the mean of all: {by_label}" if by_label else "")
            + ")")
    if head.get("confounded_with") is not None:
        # Every finding is explained away by the other family (no finding stands on its own).
        text += (f", which {head['confounded_with']} explains as well: on this capture time and position go "
                 "together, so it cannot tell a drift from a place (visit the stations again in another "
                 "order to separate them)")
        return text
    if len(rows) > 1:
        text += "; also " + ", ".join(
            f"{r['covariate']} (R^2 {r['r2']:.2f}"
            + (f", explained by {r['confounded_with']}" if r.get("confounded_with") else "")
            + (f"; most off: {levels_phrase(r['levels'], most=1, say_rest=False)}" if r.get("levels") else "") + ")"
            for r in rows[1:4])
    return text


def _untested(candidates_doc: Optional[dict]):
    """(names of the candidates the ranking did not test on held-out data, how many it did): screened
    out by --cross-validate-top, refused by the physical conditions on the fit to all stations, or
    not fitted. A replacement is named with the term it would replace ("plane in place of
    dipole_1"): its effect's addition may have been tested."""
    cands = (candidates_doc or {}).get("candidates") or []
    names = []
    for c in cands:
        if c.get("cross_validated", True) or c.get("kind") == "removal":  # explains no structure
            continue
        name = _candidate_name(c, " in place of ")
        if name not in names:
            names.append(name)
    return names, sum(1 for c in cands if c.get("cross_validated", True) and c.get("kind") != "removal")


def _candidate_name(c: dict, between: str) -> str:
    """A candidate's name: its effect; a replacement's with the term it replaces ("plane for
    dipole_2", ``between`` " for "); a removal's "remove dipole_2"."""
    effect = c.get("effect", "?")
    if not c.get("replaces"):
        return effect
    return f"{effect} {c['replaces']}" if c.get("kind") == "removal" else f"{effect}{between}{c['replaces']}"


def _no_catalog_effect(candidates_doc: Optional[dict]) -> str:
    """"no catalog effect explains the remaining structure", narrowed to the candidates tested on
    held-out data when some were not (_untested): the claim covers only what was tested."""
    untested, tested = _untested(candidates_doc)
    if not untested:
        return "no catalog effect explains the remaining structure"
    shown = ", ".join(untested[:6]) + (f" and {len(untested) - 6} more" if len(untested) > 6 else "")
    if tested == 0:
        return f"no candidate was tested on held-out data (not tested: {shown})"
    return (f"none of the {tested} candidate{'s' if tested != 1 else ''} tested on held-out data explains "
            f"the remaining structure (not tested there: {shown})")


def extrapolation_note(v) -> Optional[str]:
    """A note when stations outside the calibrated volume carry errors well beyond those inside:
    the correction extrapolates there, which no covariate or candidate explains (the covariate
    analysis and the ranking look at the structure inside). None when there is no calibration,
    no such station, or their errors are not larger than twice the inside ones."""
    if getattr(v, "after", None) is None or v.calibration is None:
        return None
    kept = ~np.asarray(v.flipped, bool) if getattr(v, "flipped", None) is not None else np.ones(len(v.extrapolated), bool)
    out = np.asarray(v.extrapolated, bool) & kept
    inside = ~np.asarray(v.extrapolated, bool) & kept
    if out.any() and not inside.any():
        # No station to compare with: the worst case (another room's capture, a wrong calibration
        # file) said nothing, where every table and figure measured an extrapolation.
        points, _ = _points_words(v)
        lo, hi = getattr(v.calibration, "volume_min", None), getattr(v.calibration, "volume_max", None)
        box = (" (" + ", ".join(f"{a} {fixed(l, '{:.2f}')} to {fixed(h, '{:.2f}')}"
                                for a, l, h in zip("xyz", lo, hi)) + " m)") if lo is not None and hi is not None else ""
        return (f"all {int(out.sum())} {points} lie outside the calibrated volume{box}: the correction "
                "extrapolates at every one, so the errors after measure no part of the volume it was fitted "
                "over; check that the capture and the calibration belong together")
    if not out.any() or not inside.any():
        return None
    e_out = float(np.mean(v.after.position_mm[out]))
    e_in = float(np.mean(v.after.position_mm[inside]))
    if not e_out > 2.0 * e_in:
        return None
    points, worst = _points_words(v)
    return (f"{int(out.sum())} of {int((out | inside).sum())} {points} lie outside the calibrated volume, where "
            f"the correction extrapolates: their mean position error is {e_out:.3f} mm against {e_in:.3f} mm "
            f"inside (by distance and worst {worst} above); calibrate over the volume they use rather than "
            "look for an effect there")


def _points_words(v) -> tuple:
    """(the noun for the validation's rows, for its worst list's rows): ("samples", "moments") of
    a stream, ("stations", "stations") of stations (``validation.points_word``; a validation-like
    object without a capture or a worst list is one of stations)."""
    from trackcal.validation import points_word, worst_word
    return points_word(getattr(v, "capture", None)), worst_word(getattr(v, "worst_separation_s", None))



# A region counts as made worse by the correction when its corrected mean error is more than
# WORSE_FACTOR times its uncorrected one AND above it by a margin of several noise floors (the
# paper room's simulated floor is 0.08 mm, 0.02 deg), on at least WORSE_MIN_SAMPLES stations: a
# region already at the noise floor (0.05 mm -> 0.09 mm) is not news. Measured on a 300 s
# paper-room stream corrected by a degree-4 polynomial fitted to poses.csv: 0-0.25 m from the
# transmitter went from 0.566 mm, 0.218 deg to 4.372 mm, 1.609 deg on 121 samples, and only the
# by-distance table showed it.
WORSE_FACTOR = 1.5
WORSE_MARGIN_MM = 0.5
WORSE_MARGIN_DEG = 0.05
WORSE_MIN_SAMPLES = 20


def worse_regions(v) -> List[dict]:
    """The regions where the corrected errors are clearly above the uncorrected ones (WORSE_*):
    distance bands, octants and the stations outside the calibrated volume, each as a breakdown
    row ({"label", "count", "before_position_mm", ...}) with "where" naming it. [] without a
    correction."""
    if getattr(v, "after", None) is None:
        return []
    rows = [dict(r, where=f"{r['label']} from the transmitter") for r in v.by_distance]
    rows += [dict(r, where=f"octant {r['label']}") for r in v.by_region]
    kept = ~np.asarray(v.flipped, bool) if getattr(v, "flipped", None) is not None else np.ones(len(v.extrapolated), bool)
    out = np.asarray(v.extrapolated, bool) & kept
    if out.any():
        from trackcal.validation import _summary_row
        rows.append(dict(_summary_row("outside", out, v.before, v.after),
                         where="outside the calibrated volume"))
    worse = []
    for r in rows:
        if r["count"] < WORSE_MIN_SAMPLES:
            continue
        bp, ap = r["before_position_mm"], r["after_position_mm"]
        bo, ao = r["before_orientation_deg"], r["after_orientation_deg"]
        if (ap > WORSE_FACTOR * bp and ap - bp > WORSE_MARGIN_MM) or \
                (ao > WORSE_FACTOR * bo and ao - bo > WORSE_MARGIN_DEG):
            worse.append(r)
    return worse


def worse_regions_note(v) -> Optional[str]:
    """A note naming the regions the correction makes worse than uncorrected (worse_regions), with
    their errors before and after; None when there is none."""
    worse = worse_regions(v)
    if not worse:
        return None
    points, _ = _points_words(v)
    parts = [f"{r['where']} ({r['count']} {points}: position {r['before_position_mm']:.3f} -> "
             f"{r['after_position_mm']:.3f} mm, orientation {r['before_orientation_deg']:.3f} -> "
             f"{r['after_orientation_deg']:.3f} deg)" for r in worse]
    return ("the correction makes the errors worse than uncorrected in " + "; ".join(parts)
            + " (by distance and by region above): do not use it there, or calibrate over that region")


def validation_notes(v) -> List[str]:
    """The notes a validation alone calls for (extrapolation_note, worse_regions_note), as
    diagnose, report and the demo's report print them."""
    return [n for n in (extrapolation_note(v), worse_regions_note(v)) if n]


def verdict_with_regions(verdict_: dict, v) -> dict:
    """The verdict with a clause naming the regions the correction makes worse (worse_regions):
    whatever the remaining structure, a region the correction harms is the reader's first concern."""
    worse = worse_regions(v)
    if not worse:
        return verdict_
    names = ", ".join(r["where"] for r in worse)
    text = verdict_["text"]
    # A verdict of whole sentences (the engine's: "... add the top one, then diagnose again.")
    # takes a sentence of its own: "; and" after its full stop read "diagnose again.; and the ...".
    if text.rstrip().endswith("."):
        return dict(verdict_, text=f"{text.rstrip()} Also, the correction makes {names} worse than "
                                   "uncorrected (note).")
    return dict(verdict_, text=f"{text}; and the correction makes {names} worse than uncorrected (note)")


# The validation set's corrected mean may be this many times the calibration stations' held-out
# mean before a note says the calibration does not carry over. Both are held-out errors over the
# same box; on captures of the ideal room with hidden effects (240 + 60 stations; sensor offset +
# toolbox, receiver gains + a tilted plate, none) their ratio was 0.62-0.97 at every step of the
# loop (7 diagnoses); a reference drifting 1 mm along x over the capture made it 6.2.
SET_GAP_FACTOR = 2.0


def set_gap_note(tables, candidates_doc: Optional[CandidatesDoc]) -> Optional[str]:
    """A note when the validation set's corrected position error is far above the held-out error
    of the calibration stations (the ranking's cross-validation of the same model, ``base``): the
    calibration does not carry over to the validation stations. The covariate analysis centres
    each set and the ranking cross-validates within the calibration set, so neither can see a
    difference between the sets (a drift over the capture: the paper protocol visits the
    validation stations last). None without a ranking, a validation set or such a gap."""
    base = ((candidates_doc or {}).get("base") or {}).get("cv_position_mm_mean")
    valid = next((t for t in tables or [] if t.set_name == "valid" and t.after_position_mm), None)
    if valid is None or not isinstance(base, (int, float)) or not math.isfinite(base) or base <= 0:
        return None
    after = valid.after_position_mm.get("mean")
    if not isinstance(after, (int, float)) or not after > SET_GAP_FACTOR * base:
        return None
    return (f"the validation stations' corrected position error (mean {after:.3f} mm) is {after / base:.1f} "
            f"times the calibration stations' held-out error ({base:.3f} mm, the ranking's cross-validation "
            "of the model): the calibration does not carry over to the validation stations. The covariate "
            "analysis and the candidate ranking look inside each set, so they cannot see a difference "
            "between the sets, and the covariate they name may only echo it: look for what changed between "
            "the two sets (a drift over the capture, since the validation stations are visited last; an "
            "object moved; another registration)")


def verdict(candidates_doc: Optional[CandidatesDoc], covariate_effects, covariates_tested: bool = True) -> dict:
    """Combines the candidate ranking (None: not run) and the covariate analysis
    (``covariates_tested`` False: not run, as ``validate(analyse_covariates=False)``; a verdict of
    nothing significant then says the covariates were not tested instead of calling them clean).

    Without a significant candidate or covariate, a significant flexible fallback of the ranking
    (a polynomial appended to the model: structure in position that no catalog effect has) is named.

    Without those either, the engine's verdict when it finds held-out structure that no candidate
    identifies (``verdict.unexplained_structure``: a term that fits it without placing its
    source, a flexible term's held-out gain) is kept as it is, source "unidentified".

    Returns {"source": "candidate" | "covariate" | "flexible" | "unidentified" | None, "effect",
    "covariate", "text", "model_change", "insert_index", "replaces"} ("replaces": the term a
    replacement takes the place of, else None)."""
    out = _verdict(candidates_doc, covariate_effects, covariates_tested)
    # The model's own source terms the data no longer identify (the engine's note): said whatever
    # the verdict, since removing one is a change the user can test.
    engine = (candidates_doc or {}).get("verdict") or {}
    # And when the paired test cannot reach the threshold on these data (a short stream, few
    # stations): "nothing significant" then says nothing about the data, whatever the verdict.
    for note in (engine.get("unsupported_note"), engine.get("test_power_note")):
        if note and note not in out["text"]:
            out["text"] = out["text"].rstrip(".") + ". " + note
    return out


def _is_geometric(covariate: str) -> bool:
    """Whether a covariate says where the receiver is or how it is turned (what a scatter that
    grows with range follows), not when it was measured or a column of the capture."""
    return covariate in ("x", "y", "z", "distance") or covariate.startswith(
        ("rx_x_axis_in_tx.", "rx_z_axis_in_tx.", "tx_direction_in_rx."))


def _verdict(candidates_doc: Optional[CandidatesDoc], covariate_effects, covariates_tested: bool) -> dict:
    rows = covariate_findings(covariate_effects)
    top = top_candidate(candidates_doc)
    out = {"source": None, "effect": None, "covariate": rows[0]["covariate"] if rows else None,
           "text": "", "model_change": None, "insert_index": None, "replaces": None}
    if top is not None:
        engine_text = ((candidates_doc or {}).get("verdict") or {}).get("text")
        text = engine_text or f"{top['effect']} explains the remaining structure: {top.get('reason', '')}"
        if top.get("statement") and top.get("kind") != "removal":  # (its verdict names the test)
            text += f" ({top['statement']})" if top["statement"] not in text else ""
        out.update(source="candidate", effect=top["effect"], text=text,
                   model_change=top.get("model_change"), insert_index=top.get("insert_index"),
                   replaces=top.get("replaces"))
        return out
    if rows:
        # A scatter that grows with range follows where the receiver is (position, distance, its
        # orientation seen from the transmitter), not time or a column of the capture: a receiver
        # gain drifting over the capture (ideal room, paper_small grid, seed 61, gains 1.8 % / 0.6 %
        # / 1.2 % apart from start to end) left 1.85 mm held out, 30x the noise floor, whose size
        # followed time (R^2 0.11) and was called noise that grows with range.
        geometric = all(_is_geometric(r["covariate"]) for r in rows)
        if geometric and not any(e.significant and e.target in VECTOR_TARGETS for e in covariate_effects):
            # Only the size of the error follows a covariate, never its direction: a scatter that
            # grows with range does that (an EM tracker's position noise grows as r^4), so it is
            # no sign of a missing effect on its own. Measured (ideal room, no hidden effect, a
            # degree-4 polynomial that holds the truth, at the noise floor): distance R^2 0.17 of
            # the position error magnitude, called "the remaining structure" before.
            lead = (_no_catalog_effect(candidates_doc).replace("the remaining structure", "what remains")
                    if candidates_doc is not None else "catalog effects not tested")
            out.update(source="covariate",
                       text=lead + "; only the size of the remaining error follows a covariate, not its direction: "
                            + _covariate_phrase(rows)[len("it follows covariate "):]
                            + ". A scatter that grows with range (a tracker's noise does, as r^4) does this, so it "
                              "is no sign of a missing effect by itself")
            return out
        lead = (_no_catalog_effect(candidates_doc) + "; " if candidates_doc is not None
                else "the remaining structure is not noise (catalog effects not tested); ")
        out.update(source="covariate", text=lead + _covariate_phrase(rows))
        return out
    flexible = next((f for f in (candidates_doc or {}).get("flexible_fallback", []) if f.get("significant")), None)
    if flexible is not None:
        drop = (flexible.get("cv_drop_percent") or {}).get("position")
        out.update(source="flexible",
                   text=_no_catalog_effect(candidates_doc) + "; it follows position (a flexible "
                        f"{flexible.get('effect', 'term')} lowers the held-out error"
                        + (f" by {drop:.1f} %" if isinstance(drop, (int, float)) else "") + ")",
                   model_change=flexible.get("model_change"), insert_index=flexible.get("insert_index"))
        return out
    engine = (candidates_doc or {}).get("verdict") or {}
    if engine.get("unexplained_structure") and engine.get("text"):
        # Held-out data show structure no candidate identifies (a term that fits it without
        # placing its source, a flexible term's held-out gain BIC does not pay for): the engine's
        # verdict says what and where; "nothing" would hide it.
        out.update(source="unidentified", text=engine["text"])
        return out
    # Nothing found: what was tested decides the words (untested covariates are not called clean).
    ranked = "not ranked" if candidates_doc is None else "partly" if _untested(candidates_doc)[0] else "all"
    text = {
        (True, "not ranked"): "nothing significant remains in the covariates (catalog effects not tested)",
        (True, "partly"): "nothing significant remains in the covariates; ",
        (True, "all"): "nothing significant remains",
        (False, "not ranked"): "nothing tested: covariates not tested and catalog effects not ranked",
        (False, "partly"): "covariates not tested; ",
        (False, "all"): "no catalog effect is significant (covariates not tested)",
    }[(bool(covariates_tested), ranked)]
    out["text"] = text + (_no_catalog_effect(candidates_doc) if ranked == "partly" else "")
    return out


def candidate_rows(doc: Optional[CandidatesDoc]) -> List[dict]:
    """One table row per ranked candidate (rank, effect, held-out errors, drops, delta BIC, p,
    significant, the fitted parameters stated physically, and why it is or is not claimed)."""
    rows = []
    for i, c in enumerate((doc or {}).get("candidates", []), 1):
        drop = c.get("cv_drop_percent") or {}
        effect = _candidate_name(c, " for ")  # a replacement shares its effect with the addition
        rows.append({"rank": i, "effect": effect, "cv_pos_mm": c.get("cv_position_mm_mean"),
                     "cv_ori_deg": c.get("cv_orientation_deg_mean"), "drop_pos_%": drop.get("position"),
                     "drop_ori_%": drop.get("orientation"), "delta_BIC": c.get("delta_bic"),
                     "p": f"{c['p_value']:.2g}" if isinstance(c.get("p_value"), (int, float)) else "",
                     "significant": "yes" if c.get("significant") else "",
                     "statement": c.get("statement", ""), "reason": c.get("reason", "")})
    return rows


def unresolved_note(doc: Optional[CandidatesDoc]) -> str:
    """When the candidates were compared without the stations the base's runtime inverse does not
    resolve (no root, or an ambiguous one next to a strong object; docs/diagnose.md), one sentence
    that says how many and gives the model alone over the others; else ""."""
    for c in (doc or {}).get("candidates", []):
        n = c.get("cv_unresolved_left_out") or 0
        if n > 0 and c.get("kind") != "loss":
            p, o = c.get("cv_base_position_mm_mean"), c.get("cv_base_orientation_deg_mean")
            there = (f"; the model alone over the others: {p:.3f} mm, {o:.3f} deg"
                     if isinstance(p, (int, float)) and isinstance(o, (int, float)) else "")
            return (f"Held-out means and drops without {n} station{'s' if n != 1 else ''} where a "
                    f"runtime inverse finds no root or an ambiguous one{there}.")
    return ""


# ---------------------------------------------------------------------------------------------
# The model-file change

_TOP_KEY_RE = re.compile(r"^([A-Za-z_][A-Za-z0-9_]*)\s*:")


def _is_item(text: str) -> bool:
    return text == "-" or text.startswith("- ")


def _is_filler(line: str) -> bool:
    """A blank or comment line."""
    return not line.strip() or line.lstrip().startswith("#")


def change_is_term(change: str) -> bool:
    """True when a candidate's ``model_change`` is a ``terms:`` list item (``- type: ...``), False
    when it is a top-level key (``loss: ...``, ``time_offset: ...``)."""
    first = next((l for l in change.splitlines() if not _is_filler(l)), "")
    return _is_item(first.strip())


def check_model_text_is_utf8(model_text: str) -> None:
    """ValueError naming the line and column of the first byte that is not UTF-8 in a model text
    from ``_core.parse_model`` (decoded with surrogateescape: a Latin-1 comment parses). A change
    applied to such a text would carry those bytes into the JSON document and the printed diff,
    where they are not text, and would not parse again from Python: it is shown, not applied."""
    for number, line in enumerate(model_text.splitlines(), start=1):
        for column, ch in enumerate(line, start=1):
            if 0xDC80 <= ord(ch) <= 0xDCFF:
                raise ValueError(f"line {number}, column {column}: byte \\x{ord(ch) - 0xDC00:02x} is "
                                 "not UTF-8 text (save the model file as UTF-8)")


def apply_model_change(model_text: str, change: str, insert_index: Optional[int],
                       replaces: Optional[str] = None) -> str:
    """The model text with a candidate's ``model_change`` applied (contract B), nothing else changed.

    A change that is a list item (``- type: dipole ...``) goes into the block-style ``terms:`` list
    before item ``insert_index`` (counting from 0; None: at the end). A replacement (``replaces``:
    the candidate's ``replaces``, the name of the term it takes the place of) first removes item
    ``insert_index`` (comment lines around it stay); the item must be a ``dipole`` or ``plane``
    whose term name is ``replaces`` (its ``name:``, else its type, numbered as the model file numbers
    repeats: the second unnamed dipole is ``dipole_2``). An empty change with ``replaces`` is a
    removal (a candidate of kind ``removal``): item ``insert_index`` is removed, nothing goes in
    its place. A change that is a top-level
    key (``loss:``, ``time_offset:``; its ``insert_index`` is None) replaces that key's block when
    the model has one, else goes directly before ``terms:`` (at the end when there is no
    ``terms:``). Comments and blank lines are kept. Raises ValueError for an empty change, a change
    that is neither, a term change to a model without a block-style ``terms:`` list (flow style
    must be edited by hand) and an index outside the list."""
    change_lines = (change or "").rstrip("\n").splitlines()
    removing = not any(l.strip() for l in change_lines)
    if removing and replaces is None:
        raise ValueError("empty model change")
    if removing and insert_index is None:
        raise ValueError(f"removing {replaces!r}: the change needs the item's insert_index")
    lines = model_text.splitlines()
    # The file's own line ending (a model written on Windows keeps CRLF, so the diff shows only the
    # change, not every line rewritten).
    eol = "\r\n" if "\r\n" in model_text else "\n"
    keys = {}  # top-level key -> line index (the first occurrence)
    for i, l in enumerate(lines):
        m = _TOP_KEY_RE.match(l)
        if m:
            keys.setdefault(m.group(1), i)
    if replaces is not None and not removing and not change_is_term(change):
        raise ValueError(f"replaces {replaces!r}: the change must be one terms: item, got {change!r}")
    if removing or change_is_term(change):
        start = keys.get("terms")
        if start is None:
            raise ValueError("model has no top-level 'terms:' list")
        if not _is_filler(lines[start].split(":", 1)[1]):
            raise ValueError("model's 'terms:' is written inline (flow style); expected a block list "
                             "(make the change by hand)")
        items, indent, end = [], None, len(lines)
        for i in range(start + 1, len(lines)):
            if _is_filler(lines[i]):
                continue
            text = lines[i].strip()
            lead = len(lines[i]) - len(lines[i].lstrip())
            if indent is None and not _is_item(text):
                if lead > 0:
                    raise ValueError("model's 'terms:' is not a block list of '- ' items")
                end = i  # an empty list
                break
            if indent is None:
                indent = lead
            if _is_item(text) and lead == indent:
                items.append(i)
            elif lead <= indent:
                end = i  # the next key after the list
                break
        # Blank and comment lines before the next key stay after the list.
        while end > start + 1 and _is_filler(lines[end - 1]):
            end -= 1
        n = len(items)
        idx = n if insert_index is None else int(insert_index)
        if not 0 <= idx <= n:
            raise ValueError(f"insert_index {idx} is outside the {n} terms")
        if replaces is not None:
            if idx >= n:
                raise ValueError(f"replaces {replaces!r}: insert_index {idx} names no term")
            if not removing and sum(_is_item(l.strip()) for l in change_lines
                                    if len(l) - len(l.lstrip()) == 0) != 1:
                raise ValueError(f"replaces {replaces!r}: the change must be one terms: item")
            # Each item's lines; blank lines and comments at the list's column after it belong to
            # what follows (a comment indented under the item, a commented-out key, is the item's).
            bounds = []
            for k in range(n):
                stop = items[k + 1] if k + 1 < n else end
                while stop > items[k] + 1 and (
                        not lines[stop - 1].strip() or
                        (_is_filler(lines[stop - 1]) and
                         len(lines[stop - 1]) - len(lines[stop - 1].lstrip()) <= indent)):
                    stop -= 1
                bounds.append((items[k], stop))
            names = _term_names([_item_fields(lines[a:b], indent) for a, b in bounds])
            typ = _item_fields(lines[bounds[idx][0]:bounds[idx][1]], indent)[0]
            if typ not in ("dipole", "plane") or names[idx] != replaces:
                raise ValueError(f"replaces {replaces!r}, but terms: item {idx} is {names[idx]!r} "
                                 f"(type {typ!r}): the model file changed since the diagnosis")
            stop = bounds[idx][1]
            replaced_at = bounds[idx][0]
            lines = lines[:items[idx]] + lines[stop:]
            removed = stop - items[idx]
            items = items[:idx] + [i - removed for i in items[idx + 1:]]
            end -= removed
            n -= 1
            if removing and n == 0:
                raise ValueError(f"removing {replaces!r} would leave terms: empty; a model needs one "
                                 "correction term")
        pad = " " * (2 if indent is None else indent)
        block = [] if removing else [pad + l if l.strip() else l for l in change_lines]
        at = items[idx] if idx < n else end
        if replaces is not None:
            at = replaced_at  # where the removed item began: what followed it stays after
    else:
        m = _TOP_KEY_RE.match(next((l for l in change_lines if not _is_filler(l)), ""))
        if not m:
            raise ValueError(f"model change is neither a term nor a top-level key: {change!r}")
        block = change_lines
        old = keys.get(m.group(1))
        if old is not None:  # replace the key's block, up to the next top-level key
            stop = next((i for i in range(old + 1, len(lines)) if _TOP_KEY_RE.match(lines[i])), len(lines))
            while stop > old + 1 and _is_filler(lines[stop - 1]):
                stop -= 1
            return eol.join(lines[:old] + block + lines[stop:]) + eol
        at = keys.get("terms", len(lines))
    return eol.join(lines[:at] + block + lines[at:]) + eol


def _item_fields(item_lines: List[str], indent: int) -> tuple:
    """(type, name) of a block-style ``terms:`` item (None where absent): the keys at the column of
    the item's first key (``-   type: dipole`` puts it 4 columns in; after a bare ``-``, the next
    line's), not a nested block's, and the keys of a flow item (``- {type: dipole, name: a}``, on
    one or several lines)."""
    fields = {}
    key_col = None
    dash_seen = False
    flow = None  # the text of a flow item while it is read
    for line in item_lines:
        if _is_filler(line):
            continue
        body = re.sub(r"\s+#.*$", "", line.rstrip())  # a trailing comment
        col = len(body) - len(body.lstrip())
        body = body.strip()
        if flow is not None:
            flow += " " + body
        elif not dash_seen and body.startswith("-"):
            dash_seen = True
            rest = body[1:]
            col += 1 + len(rest) - len(rest.lstrip())
            body = rest.strip()
            if not body:
                continue  # a bare '-': the keys start on the next line
            if body.startswith("{"):
                flow = body
            else:
                key_col = col
        elif key_col is None:
            key_col = col
        if flow is not None:
            if flow.endswith("}"):
                for part in flow.strip("{}").split(","):
                    k, _, v = part.partition(":")
                    fields.setdefault(k.strip(), v.strip().strip("'\""))
                break
            continue
        if col != key_col:
            continue
        m = re.match(r"^(type|name)\s*:\s*(.*?)\s*$", body)
        if m:
            fields.setdefault(m.group(1), m.group(2).strip("'\""))
    return fields.get("type"), fields.get("name")


def _term_names(fields: List[tuple]) -> List[str]:
    """The term names the model file gives the items (fit/model_file.cc): ``name:``, else the type,
    numbered ``type_2``, ``type_3``, ... when taken."""
    taken, out = set(), []
    for typ, name in fields:
        if name is None:
            name = str(typ)
            if name in taken:
                k = 2
                while f"{typ}_{k}" in taken:
                    k += 1
                name = f"{typ}_{k}"
        taken.add(name)
        out.append(name)
    return out


def change_place(change: str, insert_index: Optional[int], replaces: Optional[str] = None) -> str:
    """Where ``apply_model_change`` puts a change, in words."""
    if replaces is not None and insert_index is not None and not (change or "").strip():
        return f"in terms:, remove item {insert_index} ({replaces}) counting from 0"
    if replaces is not None and insert_index is not None:
        return f"in terms:, in place of item {insert_index} ({replaces}) counting from 0"
    if not change_is_term(change):
        m = _TOP_KEY_RE.match(next((l for l in change.splitlines() if not _is_filler(l)), ""))
        return f"top-level key '{m.group(1)}:', not in terms:" if m else "top level"
    if insert_index is None:
        return "in terms:, at the end"
    return f"in terms:, as item {insert_index} counting from 0"


def model_diff(model_text: str, new_text: str, name: str = "model.yaml") -> str:
    import difflib
    return "".join(difflib.unified_diff(model_text.splitlines(True), new_text.splitlines(True),
                                        fromfile=name, tofile=name + " (with the change)"))


# ---------------------------------------------------------------------------------------------
# The whole diagnosis as one document

def _finite(x):
    if isinstance(x, dict):
        return {k: _finite(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_finite(v) for v in x]
    if isinstance(x, (np.floating, float)):
        return float(x) if math.isfinite(x) else None
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, np.bool_):
        return bool(x)
    return x


def diagnosis_document(v, *, capture=None, calibration=None, model=None, fit_report=None,
                       candidates_doc: Optional[CandidatesDoc] = None, verdict_: Optional[dict] = None,
                       model_change: Optional[dict] = None, notes=()) -> dict:
    """Everything ``trackcal diagnose`` shows, as one JSON-serialisable dict: how the stations were
    obtained (``capture_origin``), Table 1 per set, stations outside the calibrated volume (ids), breakdowns by distance and region, worst stations,
    every covariate test and the significant findings, the candidate ranking (contract B, or None
    when no model was given), the verdict, the model-file change, the notes the text output prints
    (why something was not done) and every station's residuals (``stations``, the rows of
    ``Validation.station_rows``)."""
    doc = {
        "command": "diagnose",
        "capture": None if capture is None else str(capture),
        "calibration": None if calibration is None else str(calibration),
        "model": model,
        "tables": [t.to_dict() for t in v.tables],
        "capture_origin": getattr(v.capture, "origin", None),
        "outside_volume": {"count": int(v.extrapolated.sum()), "of": int(len(v.extrapolated)),
                           "stations": v.outside_stations},
        "hemisphere_flips": v.flipped_stations,
        "model_inverse": v.status_counts,
        "by_distance": v.by_distance,
        "by_region": v.by_region,
        "worst": v.worst,
        "covariates": [{"covariate": e.covariate, "target": e.target, "r2": e.r2, "p_value": e.p_value,
                        "significant": e.significant, "count": e.count,
                        "confounded_with": getattr(e, "confounded_with", None),
                        "levels": getattr(e, "levels", None)} for e in v.covariate_effects],
        "covariate_findings": covariate_findings(v.covariate_effects),
        "covariates_left_out": dict(getattr(v, "covariates_left_out", {}) or {}),
        "fit": None if fit_report is None else {"tables": [t.to_dict() for t in fit_report.tables],
                                                "converged": fit_report.converged,
                                                "chi2_per_dof": fit_report.chi2_per_dof,
                                                "parameters": (fit_report.to_dict().get("fit") or {})
                                                .get("parameters")},
        "candidates": candidates_doc,
        "verdict": verdict_ if verdict_ is not None else verdict(candidates_doc, v.covariate_effects,
                                                                     v.covariates_tested),
        "model_change": model_change,
        "notes": list(notes),
        "stations": v.station_rows(),
    }
    return _finite(doc)
