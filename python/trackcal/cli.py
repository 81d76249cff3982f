"""The ``trackcal`` command: fit, validate, diagnose, report, history, record (docs/understand.md).

Colour and progress bars only when the stream is a terminal. User errors exit with status 2 and a
one-line message naming the file, line and column (from the C++ readers). Ctrl-C exits with status
130 (``record`` first saves what it recorded).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import pathlib
import sys
import time
import warnings
from typing import Callable, List, Optional

import numpy as np

from trackcal._format import fixed


class Terminal:
    """ANSI colour and a progress bar on a TTY, plain text otherwise."""

    def __init__(self, out=None, err=None):
        self.out = out or sys.stdout
        self.err = err or sys.stderr
        # no-color.org: NO_COLOR set and not empty turns colour off (NO_COLOR= leaves it on). A
        # dumb terminal (TERM=dumb: Emacs' shell) prints escape codes as text.
        dumb = os.environ.get("TERM") == "dumb"
        no_color = bool(os.environ.get("NO_COLOR")) or dumb
        self.colour = self.out.isatty() and not no_color
        # Each stream by itself: `2> errors.log` from a terminal must get plain text.
        self.err_colour = self.err.isatty() and not no_color
        self.progress_enabled = self.err.isatty()
        self._t0 = None
        self._line_open = False  # a bar or a message drawn on stderr, its line not ended yet
        # Clearing that line: the erase-line code, or on a dumb terminal (which prints it as text)
        # blanks as wide as the widest text drawn on it.
        self._erase = not dumb
        self._line_width = 0

    def c(self, text: str, code: str) -> str:
        """``text`` in colour for stdout (when it is a terminal)."""
        return f"\033[{code}m{text}\033[0m" if self.colour else text

    def ce(self, text: str, code: str) -> str:
        """``text`` in colour for stderr (when it is a terminal)."""
        return f"\033[{code}m{text}\033[0m" if self.err_colour else text

    def progress(self, label: str) -> Callable[[float, float], None]:
        """A callback (done, total) drawing a bar on stderr, only after work has run for 1 s."""
        start = time.monotonic()

        def update(done, total):
            if not self.progress_enabled or time.monotonic() - start < 1.0:
                return
            frac = min(1.0, done / total) if total else 1.0
            bar = "#" * int(30 * frac)
            text = f"{label} [{bar:<30}] {100 * frac:5.1f}%"
            self.err.write(f"\r{text}")
            self._line_open = frac < 1.0
            self._line_width = max(self._line_width, len(text)) if self._line_open else 0
            if frac >= 1.0:
                self.err.write("\n")
            self.err.flush()
        return update

    def stage_progress(self) -> Callable[[str, int, int], None]:
        """A trackcal.fit progress callback (stage, done, total): one bar per stage."""
        bars = {}

        def update(stage, done, total):
            if stage not in bars:
                bars[stage] = self.progress(stage)
            bars[stage](done, total)
        return update


    def message_progress(self) -> Callable[[str], None]:
        """A callback showing the latest progress message on stderr (on a terminal only, after work
        has run for 1 s, as the bars)."""
        start = time.monotonic()

        def update(message):
            if self.progress_enabled and time.monotonic() - start >= 1.0:
                text = str(message)[:120]
                self.err.write(self._clear_line() + text)
                self.err.flush()
                self._line_open = True
                self._line_width = max(self._line_width, len(text))
        return update

    def end_progress(self) -> None:
        """Clears a bar or a message left part-drawn (an error or a warning then starts its own
        line, not after "... 25.0%")."""
        if self.progress_enabled and self._line_open:
            self.err.write(self._clear_line())
            self.err.flush()
        self._line_open = False
        self._line_width = 0

    def _clear_line(self) -> str:
        """Back to the start of the line, what was drawn on it cleared."""
        if self._erase:
            return "\r\033[K"
        return "\r" + " " * self._line_width + "\r" if self._line_width else "\r"


def _time_offset(args, cal, fit_report=None):
    """The clock offset to pair a stream capture at, and where it comes from: --time-offset, else
    the one the model's fit used, else the calibration's (fit_statistics.time_offset_s); (None,
    "estimated"): estimate it. With the fit's or the calibration's offset, the clock drift its
    pairing corrected (fit_statistics.clock_drift, about clock_drift_origin_s): that offset holds at
    that tracker time only, and without the drift the stream's ends were paired half the drift over
    the stream off. Returns (offset, source, {clock_drift, clock_drift_origin_s} or {})."""
    def drift_of(calibration):
        s = getattr(calibration, "fit_statistics", None) or {}
        if s.get("clock_drift") and s.get("clock_drift_origin_s") is not None:
            return {"clock_drift": float(s["clock_drift"]),
                    "clock_drift_origin_s": float(s["clock_drift_origin_s"])}
        return {}
    if getattr(args, "time_offset", None) is not None:
        return args.time_offset, "--time-offset", {}
    if fit_report is not None and fit_report.time_offset_s is not None:
        return float(fit_report.time_offset_s), "the model's fit", drift_of(fit_report.calibration)
    if cal is not None:
        t = (cal.fit_statistics or {}).get("time_offset_s")
        if t is not None:
            return float(t), "the calibration", drift_of(cal)
    return None, "estimated", {}


def _load(args, fit_report=None):
    """The calibration (-c) and the capture: poses.csv, streams (paired) or raw markers
    (registered), trackcal.captures.load."""
    from trackcal import Calibration
    from trackcal.captures import load
    cal = Calibration.load(args.calibration) if args.calibration else None
    if cal is None and fit_report is not None:
        cal = fit_report.calibration
    offset, source, drift = _time_offset(args, cal, fit_report)
    capture = load(args.capture, time_offset=offset, register_markers=getattr(args, "register_markers", False),
                   sensor=getattr(args, "sensor", None), **drift)
    _require_one_sensor(capture)
    if (capture.origin or {}).get("kind") == "streams":
        capture.origin["time_offset_source"] = source
    return capture, cal


def _require_one_sensor(capture) -> None:
    """A capture of several receivers is refused, naming them and --sensor: each receiver has its
    own calibration (sensor offset, coil gains), and tables over all of them mixed the receivers."""
    import numpy as np
    sensors = sorted(int(s) for s in np.unique(capture.sensor))
    if len(sensors) > 1:
        names = ", ".join(map(str, sensors))
        raise ValueError(f"{capture.path}: stations of sensors {names} (the sensor column): each receiver "
                         f"has its own calibration; choose one with --sensor N, N one of {names}")


def _capture_files(capture) -> List[str]:
    """The files the stations were read from (for the history and the report's input guard)."""
    o = capture.origin or {}
    return list(o.get("files") or ([str(capture.path)] if capture.path is not None else []))


def _print_origin(term, capture) -> None:
    from trackcal.captures import describe_origin
    line = describe_origin(capture)
    if line:
        print(term.c(line, "2"))


def _print_outside(term, v, limit: int = 20) -> None:
    n_out = int(v.extrapolated.sum())
    msg = v.outside_line(limit)
    print(term.c(msg, "33") if n_out else msg)
    flipped = v.flipped_stations
    if flipped:
        n = len(flipped)
        print(term.c(f"hemisphere flips left out of the statistics (reported in the other hemisphere than "
                     f"their reference): {n}: " + " ".join(str(i) for i in flipped[:limit])
                     + (f" ... ({n - limit} more)" if n > limit else ""), "33"))


def _write_residuals(args, v) -> None:
    if getattr(args, "residuals", None):
        inputs = _capture_files(v.capture) + [args.calibration, getattr(args, "model", None)]
        path = v.write_residuals(args.residuals, inputs=inputs)
        print(f"wrote the residuals of {len(v.capture)} {v.points} to {path}", file=sys.stderr)


def _fmt_rows(rows: List[dict], cols: List[str]) -> str:
    if not rows:
        return "  (none)"
    widths = {c: max(len(c), *(len(_cell(r.get(c))) for r in rows)) for c in cols}
    lines = ["  " + "  ".join(c.rjust(widths[c]) for c in cols)]
    for r in rows:
        lines.append("  " + "  ".join(_cell(r.get(c)).rjust(widths[c]) for c in cols))
    return "\n".join(lines)


def _cell(v) -> str:
    if isinstance(v, (float, np.floating)):
        return fixed(v)
    return "" if v is None else str(v)


def _validation(args, term, covariates: bool):
    from trackcal.validation import cross_validate, validate
    from trackcal import sha256_file
    # The files as they were read, for the history: hashed when it records, after the validation,
    # a calibration (or capture) another fit replaced meanwhile got these scores.
    args.calibration_sha256 = args.calibration_bytes = None
    if args.calibration and getattr(args, "workdir", None):  # kept in WORK/models/ as scored
        args.calibration_bytes = pathlib.Path(args.calibration).read_bytes()
        args.calibration_sha256 = hashlib.sha256(args.calibration_bytes).hexdigest()
    elif args.calibration:
        args.calibration_sha256 = sha256_file(pathlib.Path(args.calibration))
    capture, cal = _load(args)
    args.capture_sha256 = {f: sha256_file(pathlib.Path(f)) for f in _capture_files(capture)}
    v = validate(capture, cal, analyse_covariates=covariates,
                 covariate_options={"n_permutations": args.permutations, "seed": args.seed} if covariates else None,
                 progress=term.progress("covariates") if covariates else None)
    if getattr(args, "cross_validate", 0):
        v.tables.append(cross_validate(capture, folds=args.cross_validate))
    return capture, cal, v


def _record_history(args, v) -> Optional[dict]:
    """Records a validation in --workdir's history; the entry recorded (None without --workdir)."""
    if not getattr(args, "workdir", None) or getattr(args, "command", "") != "validate":
        return None
    from trackcal.history import record_fit, scores_from_validation
    if not args.calibration:
        raise ValueError("--workdir records a fit: give its calibration with -c")
    # Resolved, as the capture files and `trackcal fit`'s model and calibration are: a path relative
    # to wherever validate ran names no file once the history is read from elsewhere.
    files = _capture_files(v.capture)
    hashes = getattr(args, "capture_sha256", None) or {}
    fields = {}
    if getattr(args, "calibration_sha256", None):  # as validated (_validation), not as it is now
        fields["model"] = {"sha256": args.calibration_sha256}
    if getattr(args, "calibration_bytes", None) is not None:
        # A copy by content, as trackcal fit keeps its calibration's: a later fit to the same file
        # must not take away the calibration this row scored.
        from trackcal.history import _keep_copy
        models = pathlib.Path(args.workdir) / "models"
        models.mkdir(parents=True, exist_ok=True)
        copy = models / f"{args.calibration_sha256[:16]}.json"
        _keep_copy(copy, args.calibration_bytes)
        fields["model"]["copy"] = str(copy.relative_to(args.workdir))
    if all(f in hashes for f in files):
        fields["data"] = [{"path": str(pathlib.Path(f).resolve()), "role": "validation_capture",
                           "sha256": hashes[f]} for f in files]
    # The receiver validated, as fit rows record it: validations of two receivers of one capture
    # share its files but not its stations, so their errors are no step of one loop.
    column = getattr(v.capture, "sensor", None)
    sensors = np.unique(column) if column is not None else []
    if len(sensors) == 1:
        fields["sensor"] = int(sensors[0])
    return record_fit(args.workdir, model=pathlib.Path(args.calibration).resolve(),
                      data=[(pathlib.Path(f).resolve(), "validation_capture") for f in files],
                      scores=scores_from_validation(v), label=args.label or pathlib.Path(args.calibration).name,
                      fields=fields)


def _has_valid_set(data, sensor: Optional[int] = None) -> bool:
    """Whether the poses.csv of ``data`` has validation stations of ``sensor`` (None: of any): the
    receiver fitted (--sensor) decides, since another receiver's valid stations do not hold its
    calibration out (before, sensor 2's fit on a capture whose valid stations were sensor 1's got
    neither a valid table nor a cross-validation: its only table was in-sample)."""
    p = pathlib.Path(data)
    poses = p / "poses.csv" if p.is_dir() else p
    if not poses.is_file():
        return False
    from trackcal.captures import load_poses
    capture = load_poses(poses)
    if sensor is not None:
        capture = capture.subset(capture.sensor == int(sensor))
    return "valid" in capture.sets


def _colour_table(term, t, held_out: bool) -> str:
    """Table 1 text with improvements green (better) or red (worse) and the held-out title bold."""
    import re
    text = t.format()
    if not term.colour:
        return text

    def paint(m):
        return term.c(m.group(0), "32" if float(m.group(1)) > 0 else "31")
    lines = [re.sub(r"(-?\d+(?:\.\d+)?) %$", paint, line) for line in text.splitlines()]
    if held_out and lines:
        lines[0] = term.c(lines[0], "1")
    return "\n".join(lines) + ("\n" if text.endswith("\n") else "")


def _markers_capture(path, sensor=None):
    """A folder of raw optical markers (markers.csv + tracker.csv, no poses.csv or streams) as its
    registered stations (trackcal.captures.load: every station registers), since the fit engine
    reads only poses.csv and streams; None for any other capture."""
    from trackcal import captures
    return captures.load(path, sensor=sensor) if captures.capture_kind(path) == "markers" else None


def cmd_fit(args, term) -> int:
    import trackcal
    from trackcal import history
    out = pathlib.Path(args.output).resolve()
    for given in (args.data, args.model):  # a bad -o fails now, not after the fit
        if pathlib.Path(given).is_file() and pathlib.Path(given).resolve() == out:
            raise ValueError(f"{args.output}: output would overwrite the input {given}")
    # A calibration in the work folder's models/ would replace an earlier fit's kept copy.
    if args.workdir and out.parent == (pathlib.Path(args.workdir) / "models").resolve():
        raise ValueError(f"{args.output}: inside the work folder's models/, where the history keeps "
                         "its copies of fitted models and calibrations; write it elsewhere")
    trackcal._core.check_calibration_output(args.output)
    if args.workdir:  # a malformed history fails now, not after the fit and its calibration file
        history.load_history(args.workdir)
    # Raw markers are registered first, as validate, diagnose and report do (docs/understand.md,
    # "Captures"); the engine alone said "<folder>/poses.csv: cannot open file". After the output
    # checks, so a bad -o does not wait for the registration.
    markers = _markers_capture(args.data, args.sensor)
    data = markers if markers is not None else args.data
    folds = args.folds if args.folds is not None else (
        (0 if "valid" in markers.sets else 5) if markers is not None else
        (0 if _has_valid_set(args.data, args.sensor) else 5))
    report = trackcal.fit(data, args.model, folds=folds, progress=term.stage_progress(),
                          sensor=args.sensor)
    if report.pairing_warning:  # on stderr, so --json stays one document
        data = pathlib.Path(args.data)
        print(f"warning: {data / 'tracker_stream.csv'}, {data / 'reference_stream.csv'}: "
              f"{report.pairing_warning}", file=sys.stderr)
    report.save(args.output, command_line="trackcal " + " ".join(sys.argv[1:]))
    entry = None
    if args.workdir:
        entry = history.record_model_fit(args.workdir, report, model=args.model, data=data,
                                         calibration=args.output, label=args.label)
    if args.json:
        print(json.dumps(report.to_dict(), indent=2))
        return 0
    held = report.held_out()
    if markers is not None:
        _print_origin(term, markers)
    if report.time_offset_s is not None:
        print(f"streams paired at a clock offset of {fixed(report.time_offset_s * 1e3)} ms (reference minus "
              "tracker; the model's fitted offset where it frees one)")
    for t in report.tables:
        print(_colour_table(term, t, t is held))
    chi = f"{report.chi2_per_dof:.3g}" if report.chi2_per_dof is not None else "n/a"
    solver = report.solver_status()
    status = term.c(solver, "32") if report.converged else term.c(solver, "31")
    print(f"Fit: {status} in {report.seconds * 1e3:.3g} ms; chi2/dof {chi}")
    if report.outliers:
        from trackcal.fitting import format_outliers
        print(term.c(format_outliers(report.outliers, report.num_calib_stations), "33"))
    from trackcal.fitting import format_parameters
    print(format_parameters(report.parameters))
    if report.covariance_estimator:  # which covariance the stds are from, as trackcal-fit says
        print(f"  (standard deviations from the {report.covariance_estimator} covariance; docs/fit.md, "
              "\"Standard deviations\")")
    if report.identifiability_flags:
        print(term.c(f"Poorly identified ({len(report.identifiability_flags)}):", "33"))
        for f in report.identifiability_flags[:10]:
            print(f"  {f['coordinate']}: {f['reason']}")
    print(f"Wrote {args.output}")
    if entry is not None:
        entries = history.load_history(args.workdir)
        # Its own row, not the last: a fit from another terminal may have recorded since.
        number = history.entry_number(entries, entry)
        print(f"Recorded fit #{number} in {pathlib.Path(args.workdir) / history.HISTORY_FILE}")
        if number > 1:
            print(history.history_table(entries[number - 2:number], first=number - 1))
    return 0


def _unresolved_line(v) -> str:
    """How many stations a physical term's model inverse could not resolve (correction status)."""
    c = v.status_counts
    n = c["ambiguous"] + c["not_converged"]
    return (f"{v.points} the model inverse does not resolve: {n} of {len(v.extrapolated)} "
            f"(ambiguous {c['ambiguous']}, not converged {c['not_converged']})")


def cmd_validate(args, term) -> int:
    _, _, v = _validation(args, term, covariates=False)
    entry = _record_history(args, v)
    _write_residuals(args, v)
    if args.json:  # one document on stdout, nothing else (as diagnose and fit), for scripts
        from trackcal.diagnosis import _finite
        print(json.dumps(_finite({
            "command": "validate", "capture": str(args.capture), "calibration": args.calibration,
            "capture_origin": v.capture.origin, "tables": [t.to_dict() for t in v.tables],
            "outside_volume": {"count": int(v.extrapolated.sum()), "of": int(len(v.extrapolated)),
                               "stations": v.outside_stations},
            "hemisphere_flips": v.flipped_stations,
            "model_inverse": v.status_counts}), indent=2, allow_nan=False))
        return 0
    _print_origin(term, v.capture)
    for t in v.tables:
        print(term.c(t.format(), "1") if t.set_name == "valid" else t.format())
    _print_outside(term, v)
    print(_unresolved_line(v))
    if getattr(args, "workdir", None):  # as trackcal fit says where it recorded its fit
        from trackcal import history
        number = history.entry_number(history.load_history(args.workdir), entry)
        print(f"Recorded validation #{number} in {pathlib.Path(args.workdir) / history.HISTORY_FILE}")
    return 0


def _diagnosis(args, term):
    """Runs everything diagnose and report show: the validation with covariates, the model's fit when
    no calibration is given, the candidate ranking (with --model) and the verdict."""
    import trackcal
    from trackcal import captures, diagnosis
    from trackcal.validation import OtherReceiverWarning, other_receiver_text, validate
    model = getattr(args, "model", None)
    fit_report = None
    # Registered markers: the model is fitted and ranked on the references they give, the ones the
    # statistics use, not on a labelling poses.csv's (streams are paired at the fit's offset below).
    registered = (_load(args) if getattr(args, "register_markers", False)
                  or captures.capture_kind(args.capture) == "markers" else None)
    data = registered[0] if registered else args.capture
    if model and not args.calibration:
        # Without a validation set the "after" errors are in-sample: the fit's cross-validation
        # gives the held-out table, as `trackcal fit` does (unless --cross-validate asks for one).
        # Not on streams: the ranking's held-out errors, over the same blocks of time as the fit's
        # cross-validation of a stream (docs/fit.md), stand.
        has_valid = ("valid" in registered[0].sets if registered
                     else _has_valid_set(args.capture, args.sensor))
        streams = not registered and captures.capture_kind(args.capture) == "streams"
        # On the ranking's folds (--folds): a receiver of 4 stations said "give fewer folds" when
        # --folds 2 had been given, since this cross-validation kept 5.
        held_out = 0 if getattr(args, "cross_validate", 0) or has_valid or streams else (args.folds or 5)
        fit_report = trackcal.fit(data, model, folds=held_out, progress=term.stage_progress(),
                                  sensor=args.sensor)
    if registered:
        capture, cal = registered[0], registered[1] or (fit_report.calibration if fit_report else None)
    else:
        capture, cal = _load(args, fit_report)
    covariates = not getattr(args, "no_covariates", False)
    with warnings.catch_warnings():
        # Said as a note instead (first of them): the report's page carries the notes, and a reader
        # of the page had no word of a calibration fitted for another receiver.
        warnings.simplefilter("ignore", OtherReceiverWarning)
        v = validate(capture, cal, analyse_covariates=covariates,
                     covariate_options={"n_permutations": args.permutations, "seed": args.seed} if covariates else None,
                     progress=term.progress("covariates") if covariates else None)
    if fit_report is not None:
        v.tables.extend(t for t in fit_report.tables if t.set_name.startswith("cross-validation"))
    if getattr(args, "cross_validate", 0):
        from trackcal.validation import cross_validate
        v.tables.append(cross_validate(capture, model=model, folds=args.cross_validate))
    doc = None
    notes = [n for n in (other_receiver_text(capture, cal),) if n]
    if model:
        if diagnosis.candidates_available():
            effects = [e.strip() for e in args.effects.split(",") if e.strip()] if args.effects else None
            doc = diagnosis.diagnose_candidates(data, model, folds=args.folds, effects=effects,
                                                sensor=args.sensor,
                                                cross_validate_top=args.cross_validate_top,
                                                progress=term.message_progress())
            term.end_progress()
        else:
            notes.append("candidate effects not ranked: this build has no fit/candidates.h")
    else:
        notes.append("catalog effects not tested: give --model to rank them")
    if (fit_report is not None and not registered and captures.capture_kind(args.capture) == "streams"
            and not getattr(args, "cross_validate", 0)):
        # The model's fit skipped its cross-validation on streams (above): the ranking's base is that
        # cross-validation (the same blocks of time and name, fit/fit_engine.h CrossValidationFolds),
        # and its table is shown, else a stream's only table was the in-sample fit (0.92 mm against
        # 2.26 held out, paper seed 1, degree 4) and nothing said so.
        base = ((doc or {}).get("base") or {}).get("table1")
        if base:
            from trackcal.fitting import _table1
            v.tables.append(_table1(base))
        else:
            notes.append("the table above is the model's fit to every sample (in-sample): no held-out "
                         "table without the candidate ranking; give --cross-validate K for one")
    notes += diagnosis.validation_notes(v)  # outside the volume; regions the correction makes worse
    if fit_report is not None and "valid" not in set(capture.sets):
        # Figures 4 and 5 drew these "after" points as the correction's errors, with nothing to say
        # the fit had seen every one (a polynomial of degree 6: 0.64 mm in-sample, 0.85 held out).
        held = [name for name, there in (
            ("the cross-validation table", any(t.set_name.startswith("cross-validation") for t in v.tables)),
            ("the candidate table's model alone", bool(doc and (doc.get("base") or {}).get("cv_position_mm_mean"))))
            if there]
        notes.append(f"the model was fitted to these {v.points} and the capture has no validation set: the errors "
                     f"after (Table 1, figures 4, 5 and 7, the residual maps) are in-sample, lower than on "
                     f"{v.points} the fit did not see"
                     + (f"; {' and '.join(held)} give{'' if len(held) > 1 else 's'} the held-out error"
                        if held else ""))
    if fit_report is not None:  # the diagnosed calibration is the model's fit to the calib stations
        gap = diagnosis.set_gap_note(v.tables, doc)
        if gap:
            notes.append(gap)
    if model and getattr(args, "calibration", None):
        mismatch = _model_mismatch_note(args.calibration, model)
        if mismatch:
            notes.append(mismatch)
    verdict = diagnosis.verdict(doc, v.covariate_effects, v.covariates_tested)
    verdict = diagnosis.verdict_with_regions(verdict, v)
    change = None
    # (A removal's change is empty: the item named by insert_index and replaces goes.)
    if verdict["source"] == "candidate" and (verdict.get("model_change") or verdict.get("replaces")):
        info = trackcal._core.parse_model(model)
        name = pathlib.Path(model).name if info["source"] != "<string>" else "model.yaml"
        try:
            diagnosis.check_model_text_is_utf8(info["text"])
            new_text = diagnosis.apply_model_change(info["text"], verdict["model_change"],
                                                    verdict.get("insert_index"),
                                                    verdict.get("replaces"))
        except ValueError as e:  # e.g. a flow-style terms: list: the change is made by hand
            new_text = None
            notes.append(f"the model-file change is not applied to {name}: {e}")
        change = {"effect": verdict["effect"], "yaml": verdict["model_change"],
                  "insert_index": verdict.get("insert_index"), "replaces": verdict.get("replaces"),
                  "place": diagnosis.change_place(verdict["model_change"], verdict.get("insert_index"),
                                                  verdict.get("replaces")),
                  "model_text": new_text,
                  "diff": diagnosis.model_diff(info["text"], new_text, name) if new_text else None}
    return capture, cal, v, fit_report, doc, verdict, change, notes


def _model_mismatch_note(calibration, model) -> Optional[str]:
    """With -c and --model: the tables are the calibration's, while the ranking refits --model; say
    so when the calibration records another model file (its provenance's model_file input) than
    --model, else a user reads the candidates as the calibration's (a sensor offset 'missing' from a
    calibration that has one)."""
    import hashlib
    if not os.path.isfile(model):
        return None  # model text: nothing to compare
    try:
        with open(calibration, "rb") as f:
            inputs = (json.loads(f.read()).get("provenance") or {}).get("inputs") or []
        with open(model, "rb") as f:
            sha = hashlib.sha256(f.read()).hexdigest()
    except (OSError, ValueError, AttributeError):
        return None  # the calibration loaded already: its own reader reports what is wrong
    models = [i for i in inputs if isinstance(i, dict) and i.get("role") == "model_file"]
    if not models or any(i.get("sha256") == sha for i in models):
        return None
    return (f"{calibration} was fitted from another model file ({models[0].get('path')}) than --model "
            f"{model}: the tables and covariates above are the calibration's, the candidate ranking and the "
            f"verdict are about {model} refitted to this capture")


def cmd_diagnose(args, term) -> int:
    from trackcal import diagnosis, validation
    capture, cal, v, fit_report, doc, verdict, change, notes = _diagnosis(args, term)
    _write_residuals(args, v)
    if args.json:
        print(json.dumps(diagnosis.diagnosis_document(
            v, capture=args.capture, calibration=args.calibration, model=args.model, fit_report=fit_report,
            candidates_doc=doc, verdict_=verdict, model_change=change, notes=notes), indent=2,
            allow_nan=False))
        return 0
    _print_origin(term, v.capture)
    for t in v.tables:
        print(t.format())
    _print_outside(term, v)
    msg = _unresolved_line(v)
    print(term.c(msg, "33") if v.status_counts["converged"] < len(v.extrapolated) else msg)
    cols = ["label", "count", "before_position_mm", "before_orientation_deg"]
    if v.after is not None:
        cols += ["after_position_mm", "after_orientation_deg"]
    print("\n" + term.c("By distance from the transmitter", "1"))
    print(_fmt_rows(v.by_distance, cols))
    print("\n" + term.c("By region (octants around the volume centre)", "1"))
    print(_fmt_rows(v.by_region, cols))
    print("\n" + term.c(v.worst_heading, "1")
          + " (x, y, z, distance: reported position in the transmitter frame [m])")
    moments = v.worst_separation_s is not None  # stream samples: the time says which moment
    print(_fmt_rows(v.worst_rows(), [v.point, "time" if moments else "set", "sensor", "x", "y", "z", "distance",
                              "position_mm", "orientation_deg", "extrapolated"]))
    method = validation.COVARIATE_METHOD_SERIAL if validation.serial_samples(v.capture) else validation.COVARIATE_METHOD
    print("\n" + term.c(f"Residual structure ({method})", "1"))
    # Findings that stand on their own first (not explained away by another covariate).
    sig = sorted((e for e in v.covariate_effects if e.significant),
                 key=lambda e: (e.confounded_with is not None, -e.r2))
    for name, why in v.covariates_left_out.items():  # not a finding: why it is not in the table
        print(term.c(f"  {name} left out: {why}", "2"))
    if not v.covariates_tested:  # too few stations or permutations: not a clean bill
        print(term.c(f"  not tested: {v.covariates_note}", "33"))
    elif not sig:
        print("  no covariate explains the residuals beyond noise")
    for e in sig[:args.top]:
        print("  " + term.c(f"{e.covariate:<24}", "31") + f" {e.target:<20} R²={e.r2:.3f}  p={e.p_value:.3g}"
              + (f"  (explained by {e.confounded_with})" if e.confounded_with else "")
              + (f"\n  {'':<24} each label's mean error from the mean of all: {diagnosis.levels_phrase(e.levels)}" if e.levels else ""))
    if doc is not None:
        from trackcal.report import _number
        base = doc.get("base", {})
        print("\n" + term.c("Candidate effects", "1") +
              f" (the model alone: held-out {_number(base.get('cv_position_mm_mean'))} mm, "
              f"{_number(base.get('cv_orientation_deg_mean'))} deg)")
        if diagnosis.unresolved_note(doc):
            print("  " + diagnosis.unresolved_note(doc))
        rows = diagnosis.candidate_rows(doc)
        print(_fmt_rows(rows, ["rank", "effect", "cv_pos_mm", "cv_ori_deg", "drop_pos_%",
                               "drop_ori_%", "delta_BIC", "p", "significant"]))
        for r in rows:  # what each fit says about the room, and why it is (not) claimed
            print(f"  {r['rank']:>2} {r['effect']}: " + (r["statement"] or "(no physical statement)"))
            if r["reason"]:
                print(term.c(f"     {r['reason']}", "2"))
        for f in doc.get("flexible_fallback") or []:  # structure in position no effect has
            drop = (f.get("cv_drop_percent") or {}).get("position")
            cv = f.get("cv_position_mm_mean")
            if not isinstance(cv, (int, float)):
                why = f.get("reason") or "not fitted"
                print(term.c(f"  flexible {f.get('effect')} (not an effect): {why}", "2"))
                continue
            print(f"  flexible {f.get('effect')} (not an effect): held-out {cv:.3f} mm"
                  + ((f", {'falls' if drop >= 0 else 'rises'} {abs(drop):.1f} %")
                     if isinstance(drop, (int, float)) else "")
                  + (", significant" if f.get("significant") else ", not significant")
                  + (f"; {f['reason']}" if f.get("reason") else ""))
        if doc.get("skipped"):
            print(term.c("  not tested: " + "; ".join(doc["skipped"]), "2"))
    for n in notes:
        print("\n" + term.c("note: ", "33") + n)
    colour = {None: "32", "unidentified": "33"}.get(verdict["source"], "31")  # red: something to add
    print("\n" + term.c("Verdict: ", "1") + term.c(verdict["text"], colour))
    if change is not None:
        print("\n" + term.c("Model-file change", "1") +
              f" ({change['place']}):")
        print(change["diff"] if change["diff"] else change["yaml"])
    return 0


def cmd_report(args, term) -> int:
    from trackcal.history import load_history
    from trackcal.report import write_report
    # Read first: a malformed history fails now, not after the fit and the covariate tests.
    hist = load_history(args.workdir) if args.workdir else None
    capture, cal, v, fit_report, doc, verdict, change, notes = _diagnosis(args, term)
    _write_residuals(args, v)
    inputs = [args.capture, args.calibration, args.model if args.model and os.path.exists(args.model) else None]
    inputs += _capture_files(capture)
    if args.workdir and not hist:  # asked for, but there is none to show
        notes.append(f"{pathlib.Path(args.workdir) / 'history.jsonl'}: no fits recorded: the report "
                     "has no history")
    if hist:  # the history's rows are of their captures as fitted: say which are no longer
        from trackcal.history import data_changed_notes
        notes += [f"history: {n}" for n in data_changed_notes(hist)]
    for n in notes:
        print(term.c("note: ", "33") + n)
    # Only an earlier trackcal report is ever replaced (any other file is refused): say so, the
    # earlier page and its figures are gone.
    replaced = (pathlib.Path(args.output) / "report.html").exists()
    path = write_report(v, args.output, inputs=inputs, history_entries=hist, candidates=doc,
                        verdict=verdict, model_change=change, progress=term.progress("figures"),
                        notes=notes)
    print(f"wrote {path}" + (" (replaced the earlier trackcal report there, and its figures)" if replaced else ""))
    return 0


def cmd_history(args, term) -> int:
    from trackcal import history
    from trackcal.history import history_table, load_history
    entries = load_history(args.workdir)
    if not entries:
        if args.plot:  # a script that asked for the figure must not find it missing after exit 0
            raise ValueError(f"--plot {args.plot}: not written: {args.workdir}: no fits recorded "
                             "(history.jsonl)")
        print(f"{args.workdir}: no fits recorded (history.jsonl)")
        return 0
    print(history_table(entries))
    for n in history.data_changed_notes(entries):
        print(term.c("note: ", "33") + n)
    if args.plot:
        from trackcal import figures
        work = pathlib.Path(args.workdir)
        inputs = [work / history.HISTORY_FILE]  # and every file the fits name: never drawn over
        for e in entries:
            m = e.get("model") or {}
            names = [m.get("path"), (e.get("calibration") or {}).get("path")]
            names += [d.get("path") for d in e.get("data") or [] if isinstance(d, dict)]
            inputs += [p for p in names if isinstance(p, str)]
            if isinstance(m.get("copy"), str):
                inputs.append(work / m["copy"])
        import matplotlib.pyplot as plt
        fig = figures.history_plot(entries)
        try:
            figures.save_png(fig, args.plot, inputs=inputs)
        finally:  # main() also runs in-process (scripts, tests): leave no figure in pyplot's registry
            plt.close(fig)
        print(f"wrote {args.plot}")
    return 0


def cmd_record(args, term) -> int:
    from trackcal.record import NoFirstReport, UnknownHost, record_streams
    devices = {}
    for spec in args.device:
        if "=" not in spec:
            raise ValueError(f"--device {spec!r}: expected LABEL=Tracker0@tcp://host:port")
        label, name = spec.split("=", 1)
        if label in devices:
            raise ValueError(f"--device {spec!r}: label {label!r} is given twice (each recording is "
                             f"<label>_tracker_stream.csv: one label per device)")
        devices[label] = name
    try:
        out = record_streams(devices, args.output, args.duration, connect_timeout_s=args.connect_timeout,
                             progress=term.progress("recording"))
    except UnknownHost as e:  # waiting longer would not help
        raise RuntimeError(str(e)) from None
    except NoFirstReport as e:  # a server still starting (a Fastrak reset) may need longer
        raise RuntimeError(f"{e} (--connect-timeout S to wait longer)") from None
    if out.interrupted:
        term.end_progress()
    for label, p in out.items():
        print(f"{label}: wrote {p}")
    if not out.interrupted:
        return 0
    for label in out.empty:
        print(f"{label}: no report before the interruption, nothing written")
    started = bool(out or out.empty)
    print("recording interrupted (Ctrl-C)"
          + ("" if started else " before every device had connected: nothing recorded"), file=sys.stderr)
    return 130


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="trackcal", description="Validate, diagnose and report tracker calibrations.")
    sub = p.add_subparsers(dest="command", required=True)

    def common(sp, covariates=True, model=True):
        sp.add_argument("capture", help="capture folder (poses.csv; or tracker_stream.csv + reference_stream.csv, "
                                        "paired; or markers.csv + tracker.csv, registered) or a poses.csv")
        sp.add_argument("-c", "--calibration", help="calibration file (docs/calibration-file.md)")
        # validate has no --model: its cross-validation always refits the paper's polynomial.
        sp.add_argument("--cross-validate", type=int, default=0, metavar="K",
                        help="also K-fold cross-validate a model with the fit engine ("
                             + ("--model, else " if model else "") + "the paper's degree-3 polynomial)")
        sp.add_argument("--time-offset", type=float, default=None, metavar="S",
                        help="streams: pair at this clock offset t_reference - t_tracker [s] (default: the "
                             "model fit's or the calibration's, else estimated)")
        sp.add_argument("--register-markers", action="store_true",
                        help="derive the reference poses from the folder's markers.csv + tracker.csv (registered "
                             "with the reg stations of its poses.csv, if any) instead of reading poses.csv")
        sp.add_argument("--sensor", type=int, default=None, metavar="N",
                        help="receiver whose stations are used (the capture's sensor column, from 1; VRPN "
                             "sensor N-1): needed when the capture holds several receivers")
        sp.add_argument("--residuals", metavar="CSV",
                        help="write every station's residuals (before/after, vectors, outside flag) to this "
                             "new CSV file")
        if covariates:
            sp.add_argument("--permutations", type=int, default=199,
                            help="permutations per covariate test (0 or more; below 99 no test can be significant, "
                                 "so the covariates count as not tested)")
            sp.add_argument("--seed", type=int, default=0)

    sp = sub.add_parser("validate", help="Table 1 before/after for the calibration and validation sets")
    common(sp, covariates=False, model=False)
    sp.add_argument("--json", action="store_true",
                    help="print one JSON document (tables, outside-volume stations, capture origin) instead of text")
    sp.add_argument("--workdir", help="record this calibration's scores in WORKDIR/history.jsonl (not the "
                                      "--cross-validate table: that is another fit's)")
    sp.add_argument("--label", help="what changed in this fit (history label; default: file name)")
    def model_args(sp):
        sp.add_argument("--model", help="model file (docs/model-file.md): fitted when no -c is given, "
                                        "and the catalog effects it lacks are ranked")
        # Defaults None: given without --model (no ranking) they are refused, not silently ignored.
        sp.add_argument("--folds", type=int, default=None,
                        help="cross-validation folds of the candidate ranking (default 5; with --model)")
        sp.add_argument("--effects", help="comma-separated catalog effects to try (default: all; with --model)")
        sp.add_argument("--cross-validate-top", type=int, default=None, metavar="N",
                        help="cross-validate only the N candidates with the best BIC; the others are "
                             "reported screened out, never significant (0: every one; default 3; "
                             "with --model)")

    sp = sub.add_parser("diagnose", help="compare and see where it fails: breakdowns, worst stations, covariates, "
                                         "candidate effects and the verdict")
    common(sp)
    model_args(sp)
    sp.add_argument("--top", type=int, default=15, help="significant covariates to list")
    sp.add_argument("--json", action="store_true", help="print the whole diagnosis as one JSON document")
    sp = sub.add_parser("report", help="write a self-contained HTML report and PNG figures")
    common(sp)
    model_args(sp)
    sp.add_argument("-o", "--output", required=True, help="output folder")
    sp.add_argument("--workdir", help="work folder whose history.jsonl to plot")
    sp.add_argument("--no-covariates", action="store_true")
    sp = sub.add_parser("fit", help="fit a model file with the fit engine, write the calibration, record the history")
    sp.add_argument("--data", required=True, help="capture folder or poses.csv")
    sp.add_argument("--model", required=True, help="model file (docs/model-file.md)")
    sp.add_argument("-o", "--output", required=True, help="calibration file to write (never over an input)")
    sp.add_argument("--folds", type=int, default=None,
                    help="K-fold cross-validation (default: 5 when the capture has no validation set)")
    sp.add_argument("--sensor", type=int, default=None,
                    help="receiver whose stations are fitted (the capture's sensor column, from 1); "
                         "needed when the capture holds several")
    sp.add_argument("--workdir", help="record the fit in WORKDIR/history.jsonl (model copy, data hashes, scores)")
    sp.add_argument("--label", help="what changed (history label; default: the terms added or removed)")
    sp.add_argument("--json", action="store_true", help="print trackcal-fit's --json document instead of text")
    sp = sub.add_parser("history", help="error after each recorded fit of a work folder")
    sp.add_argument("workdir")
    sp.add_argument("--plot", help="write the history plot to this PNG (replaces only a .png file, never "
                                   "the history or a file it names)")
    sp = sub.add_parser("record", help="record live raw and corrected streams from a VRPN server",
                        description="Record live raw and corrected streams from a VRPN server. Ctrl-C ends "
                                    "the recording early: what was recorded is saved and the exit status is "
                                    "130.")
    sp.add_argument("--device", action="append", required=True,
                    help="LABEL=Tracker0@tcp://host:port (repeat: e.g. raw=... corrected=...)")
    sp.add_argument("--duration", type=float, required=True, help="seconds")
    sp.add_argument("--connect-timeout", type=float, default=10.0, metavar="S",
                    help="seconds to wait for every device's first report before giving up (default 10); "
                         "the recording starts when all have sent one")
    sp.add_argument("-o", "--output", required=True, help="output folder")
    return p


def _check_folder(path, option: str, write: bool) -> None:
    """``path`` must be a folder, or (written) one that can be made: checked before the work."""
    p = pathlib.Path(path)
    if p.exists() and not p.is_dir():
        raise ValueError(f"{option} {p}: exists and is not a folder")
    if not write:
        return
    base = p
    while not base.exists():  # the nearest existing folder the missing ones are made in
        base = base.parent
    if not base.is_dir():
        raise ValueError(f"{option} {p}: {base} is not a folder")
    if not os.access(base, os.W_OK | os.X_OK):
        raise ValueError(f"{option} {p}: {base} is not writable")


def _check_args(args) -> None:
    """What can be refused before any work (a long fit, a covariate analysis, a recording)."""
    if getattr(args, "permutations", 0) < 0:  # would make p-values negative: everything significant
        raise ValueError(f"--permutations {args.permutations}: must be 0 or more")
    if args.command in ("diagnose", "report"):
        # The ranking's options do nothing without a model to rank the catalog effects against.
        given = [o for o, v in (("--folds", args.folds), ("--effects", args.effects),
                                ("--cross-validate-top", args.cross_validate_top)) if v is not None]
        if given and not args.model:
            raise ValueError(f"{', '.join(given)}: options of the candidate ranking, which needs --model "
                             "(the model file whose missing effects are ranked)")
        args.folds = 5 if args.folds is None else args.folds
        args.cross_validate_top = 3 if args.cross_validate_top is None else args.cross_validate_top
    if getattr(args, "cross_validate_top", 0) < 0:
        raise ValueError(f"--cross-validate-top {args.cross_validate_top}: must be 0 or more")
    if getattr(args, "top", 0) < 0:
        raise ValueError(f"--top {args.top}: must be 0 or more")
    if args.command == "record" and not (args.duration > 0 and math.isfinite(args.duration)):
        raise ValueError(f"--duration {args.duration}: must be a positive number of seconds")
    if args.command == "record" and not (args.connect_timeout > 0 and math.isfinite(args.connect_timeout)):
        raise ValueError(f"--connect-timeout {args.connect_timeout}: must be a positive number of seconds")
    if args.command == "validate" and args.workdir and not args.calibration:
        # Refused after the covariate tests (minutes) otherwise: a history records a calibration.
        raise ValueError("--workdir records a fit: give its calibration with -c")
    if args.command == "history" and not pathlib.Path(args.workdir).is_dir():
        # A mistyped folder is not an empty history.
        raise ValueError(f"{args.workdir}: no such work folder")
    if args.command == "report" and args.workdir and not pathlib.Path(args.workdir).is_dir():
        # Read only: a mistyped folder gave a report without its history, and no word of it.
        raise ValueError(f"--workdir {args.workdir}: no such work folder")
    if args.command in ("diagnose", "report") and getattr(args, "model", None) and args.folds < 2:
        raise ValueError(f"--folds {args.folds}: must be 2 or more")
    if args.command in ("report", "record"):
        _check_folder(args.output, "-o", write=True)
    # Outputs refused anyway once the work is done (the covariate tests, a model fit, the candidate
    # ranking: minutes): refused now instead.
    residuals = getattr(args, "residuals", None)
    if residuals and os.path.lexists(residuals):
        raise ValueError(f"{residuals}: exists; residuals are never written over an existing file")
    if args.command == "report":
        from trackcal.report import _check_replaceable
        _check_replaceable(pathlib.Path(args.output) / "report.html",
                           [pathlib.Path(p) for p in (args.capture, args.calibration, args.model) if p])
    if getattr(args, "workdir", None):
        _check_folder(args.workdir, "--workdir" if args.command != "history" else "work folder",
                      write=args.command in ("fit", "validate"))


def _os_error_text(e: OSError) -> str:
    """'<file>: <reason>' of an OSError (PermissionError, IsADirectoryError, ...)."""
    if e.filename is None or not e.strerror:
        return str(e)
    names = f"{e.filename}" + (f" -> {e.filename2}" if e.filename2 is not None else "")
    return f"{names}: {e.strerror}"


COMMANDS = {"fit": cmd_fit, "validate": cmd_validate, "diagnose": cmd_diagnose, "report": cmd_report,
            "history": cmd_history, "record": cmd_record}


def main(argv: Optional[List[str]] = None) -> int:
    args = build_parser().parse_args(argv)
    term = Terminal()
    try:
        with warnings.catch_warnings():
            from trackcal.history import HistoryWarning
            from trackcal.validation import OtherReceiverWarning
            _show = warnings.showwarning

            def show(message, category, *rest, **kw):
                if issubclass(category, (HistoryWarning, OtherReceiverWarning)):  # one line, like the errors
                    term.end_progress()
                    print(term.ce("warning: ", "33") + str(message), file=sys.stderr)
                else:
                    _show(message, category, *rest, **kw)
            warnings.showwarning = show
            warnings.simplefilter("always", HistoryWarning)
            _check_args(args)
            return COMMANDS[args.command](args, term)
    except (ValueError, KeyError, RuntimeError, NotImplementedError) as e:
        msg = e.args[0] if isinstance(e, KeyError) and e.args else str(e)
        term.end_progress()
        print(term.ce("error: ", "31") + str(msg), file=sys.stderr)
        return 2
    except BrokenPipeError:  # output piped into head & co.
        sys.stderr.close()
        return 0
    except OSError as e:  # a file the system refuses (missing, a folder, no permission): one line
        term.end_progress()
        print(term.ce("error: ", "31") + _os_error_text(e), file=sys.stderr)
        return 2
    except KeyboardInterrupt:  # Ctrl-C: no traceback (record saves what it recorded first)
        term.end_progress()
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
