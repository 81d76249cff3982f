"""The fit history of a work folder: ``history.jsonl``, one JSON object per line, one line per fit.

Each entry: ``time_utc``, ``label`` (what changed), ``model`` (path and SHA-256 of the model or
calibration file; for a model-file fit also ``copy``, the model text kept in ``models/<sha>.yaml``
of the work folder, so every earlier model can be recovered), ``data`` (a list of {path, role,
sha256} of the captures used) and ``scores`` ({set name: {"position_mm": {mean, std, max, ...},
"orientation_deg": {...}}}). Fits of a model file (``trackcal fit --workdir``) add ``terms`` (term
names of the model), ``calibration`` ({path, sha256} of the file written, and ``copy``, the same bytes
kept in ``models/<sha>.json``: a later fit may replace the file), ``fit`` (converged,
chi2_per_dof, free parameters, outliers) and ``sensor`` (the receiver fitted, from 1; ``trackcal
validate --workdir`` rows record the receiver validated). The file is rewritten atomically on every record, so an
interrupted write never loses earlier fits, under a lock (``.history.lock`` beside it), so two fits
recording at once (two terminals, parallel scripts) both keep their entry.
"""

from __future__ import annotations

import contextlib
import datetime
import hashlib
import json
import math
import os
import pathlib
import warnings
from typing import Callable, Dict, List, Optional, Sequence, Tuple, Union

from trackcal import _core
from trackcal._files import replace_atomically, write_new

HISTORY_FILE = "history.jsonl"
_LOCK_FILE = ".history.lock"

try:
    import fcntl
except ImportError:  # not POSIX: records are not serialised between processes
    fcntl = None


@contextlib.contextmanager
def _history_lock(workdir: pathlib.Path):
    """Holds an exclusive lock of the work folder's history while it is read and rewritten."""
    if fcntl is None:
        yield
        return
    with open(workdir / _LOCK_FILE, "a") as lock:
        fcntl.flock(lock.fileno(), fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(lock.fileno(), fcntl.LOCK_UN)


def _sha(path) -> str:
    return _core.sha256_file(pathlib.Path(path))


class HistoryWarning(UserWarning):
    """A history.jsonl whose last line is cut short (a write interrupted by a crash or a full disk,
    by a tool that appends): the line is left out, every entry before it is kept."""


def _truncated_tail(data: bytes) -> int:
    """Length of an unterminated last line of ``data`` that is not a whole JSON value (a write cut
    short), else 0. An entry is a JSON object, so a prefix of one never parses, and it starts with
    '{': a line that does not (notes a person or a tool put there) is not a cut write, and is left
    for the reader to refuse by its line rather than dropped."""
    if not data or data.endswith(b"\n"):
        return 0
    tail = data[data.rfind(b"\n") + 1:]
    if not tail.strip() or not tail.lstrip().startswith(b"{"):
        return 0
    try:
        json.loads(tail.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError):
        return len(tail)
    return 0


def _without_truncated_tail(path: pathlib.Path, data: bytes, outcome: str) -> bytes:
    """``data`` without a last line cut short, with a ``HistoryWarning`` saying what became of it
    (pointing at the caller of the public function)."""
    cut = _truncated_tail(data)
    if not cut:
        return data
    lineno = data.count(b"\n") + 1
    warnings.warn(f"{path}:{lineno}: last line is incomplete ({cut} bytes, no newline: "
                  f"a write cut short); {outcome}, the entries before it are kept", HistoryWarning,
                  stacklevel=3)
    return data[:-cut]


def load_history(workdir) -> List[dict]:
    """Entries of a work folder's history.jsonl ([] if there is none). Errors name file, line and
    field: every entry is checked for the shape the history table, plot and labels read. A last
    line without its newline that is not JSON (a write cut short) is left out with a
    ``HistoryWarning``: the entries before it are kept."""
    path = pathlib.Path(workdir) / HISTORY_FILE
    if not path.exists():
        return []
    return _parse_entries(path, _without_truncated_tail(path, path.read_bytes(), "left out"))


def _parse_entries(path: pathlib.Path, data: bytes) -> List[dict]:
    """The entries of history.jsonl's contents ``data``; errors name ``path``, line and field."""
    entries = []
    for lineno, raw in enumerate(data.split(b"\n"), 1):
        try:
            line = raw.decode("utf-8")
        except UnicodeDecodeError as err:
            raise ValueError(f"{path}:{lineno}: column {err.start + 1}: not UTF-8 text "
                             f"(byte 0x{raw[err.start]:02x})") from None
        if not line.strip():
            continue
        try:
            e = json.loads(line)
        except json.JSONDecodeError as err:
            raise ValueError(f"{path}:{lineno}: column {err.colno}: not JSON: {err.msg}") from None
        problem = _entry_problem(e)
        if problem:
            raise ValueError(f"{path}:{lineno}: field {problem[0]}: {problem[1]}")
        entries.append(e)
    return entries


def _kind(value) -> str:
    if value is None:
        return "null"
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, (int, float)):
        return "a number"
    return {str: "a string", list: "a list", dict: "an object"}.get(type(value), type(value).__name__)


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _entry_problem(e) -> Optional[Tuple[str, str]]:
    """(field, what is wrong) when a history entry lacks what its readers use, else None: scores
    {set: {position_mm: {mean, median?}, orientation_deg: {mean}}}, model {path, sha256, copy}
    when present, terms (names), time_utc, calibration and data."""
    if not isinstance(e, dict) or "scores" not in e:
        return "scores", "missing (not a fit record)"
    scores = e["scores"]
    if not isinstance(scores, dict):
        return "scores", f"expected an object of sets, got {_kind(scores)}"
    for name, s in scores.items():
        if not isinstance(s, dict):
            return f"scores.{name}", ("expected an object with position_mm and orientation_deg, "
                                      f"got {_kind(s)}")
        for quantity in ("position_mm", "orientation_deg"):
            field = f"scores.{name}.{quantity}"
            summary = s.get(quantity)
            if not isinstance(summary, dict):
                return field, ("missing" if quantity not in s
                               else f"expected an object with mean, std, max, ..., got {_kind(summary)}")
            if not _is_number(summary.get("mean")):
                return f"{field}.mean", ("missing" if "mean" not in summary
                                         else f"expected a number, got {_kind(summary['mean'])}")
            median = summary.get("median")
            if median is not None and not _is_number(median):
                return f"{field}.median", f"expected a number, got {_kind(median)}"
    model = e.get("model")
    if model is not None:
        if not isinstance(model, dict):
            return "model", f"expected an object (path, sha256) or null, got {_kind(model)}"
        for key in ("path", "sha256", "copy"):
            if key in model and not isinstance(model[key], str):
                return f"model.{key}", f"expected a string, got {_kind(model[key])}"
    terms = e.get("terms")
    if "terms" in e and not (isinstance(terms, list) and all(isinstance(t, str) for t in terms)):
        return "terms", "expected a list of term names"
    if "label" in e and not isinstance(e["label"], str):
        return "label", f"expected a string, got {_kind(e['label'])}"
    sensor = e.get("sensor")
    # Any whole number: a capture's sensor column may count from 0, and validate records it as is.
    if "sensor" in e and not (_is_number(sensor) and math.isfinite(sensor) and sensor == int(sensor)):
        return "sensor", f"expected the receiver's whole number, got {_kind(sensor)}"
    if "time_utc" in e and not isinstance(e["time_utc"], str):
        return "time_utc", f"expected a string, got {_kind(e['time_utc'])}"
    if "calibration" in e and not isinstance(e["calibration"], dict):
        return "calibration", f"expected an object (path, sha256), got {_kind(e['calibration'])}"
    if "data" in e and not isinstance(e["data"], list):
        return "data", f"expected a list of files, got {_kind(e['data'])}"
    return None


def record_fit(workdir, *, model, data: Sequence[Tuple[str, str]], scores: Dict[str, dict],
               label: Union[str, Callable[[List[dict]], str]] = "", extra: Optional[dict] = None,
               fields: Optional[dict] = None) -> dict:
    """Appends a fit to the work folder's history. ``data`` is [(path, role)]; ``scores`` maps a set
    name to Table 1 summaries ({"position_mm": {...}, "orientation_deg": {...}}); ``fields`` are
    merged into the entry (``model`` keys included). A callable ``label`` is given the entries
    already recorded, read under the history's lock, so two fits recorded at once are each labelled
    against the entry truly before them."""
    workdir = pathlib.Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    entry = {
        "time_utc": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "label": "" if callable(label) else label,
        "model": {"path": str(model), "sha256": _sha(model)} if model is not None else None,
        "data": [{"path": str(p), "role": role, "sha256": _sha(p)} for p, role in data],
        "scores": scores,
    }
    if extra:
        entry["extra"] = extra
    for k, v in (fields or {}).items():
        if k == "model" and isinstance(v, dict) and entry["model"]:
            entry["model"].update(v)
        else:
            entry[k] = v
    json.dumps(entry, allow_nan=False)  # refuse NaN before touching the file
    path = workdir / HISTORY_FILE
    with _history_lock(workdir):
        old = path.read_bytes() if path.exists() else b""
        # A line cut short by an earlier crash: kept, it would sit between two entries and make
        # every later read of the history fail.
        old = _without_truncated_tail(path, old, "replaced by this fit's entry")
        if callable(label):
            entry["label"] = str(label(_parse_entries(path, old)))
        if old and not old.endswith(b"\n"):
            old += b"\n"
        replace_atomically(path, old + (json.dumps(entry, sort_keys=True) + "\n").encode())
        _remove_stale_temporaries(path)
    return entry


def _remove_stale_temporaries(path: pathlib.Path) -> None:
    """Removes the temporary copies of history.jsonl (``.history.jsonl.tmp-*``) that writers killed
    mid-write (SIGKILL, a power cut) left: each is a whole copy of the history, and they piled up
    (3 of 6 records killed at random left 2-4.5 MB each). Called under the lock, which every writer
    holds while its temporary exists, so none of them is in use; without fcntl none is touched."""
    if fcntl is None:
        return
    for stale in path.parent.glob(f".{path.name}.tmp-*"):
        with contextlib.suppress(OSError):
            stale.unlink()


def entry_number(entries: Sequence[dict], entry: dict) -> int:
    """The 1-based row of ``entry`` (as record_fit returned it) in ``entries`` (the history read
    after it was recorded): the last row equal to it. Not the history's length: another fit may
    have been recorded since (two terminals, parallel scripts). len(entries) when it is not there
    (the history rewritten meanwhile)."""
    recorded = json.loads(json.dumps(entry))  # as read back: tuples become lists
    return next((i for i in range(len(entries), 0, -1) if entries[i - 1] == recorded), len(entries))


def _data_files(data) -> List[Tuple[pathlib.Path, str]]:
    """The capture files a fit read from ``data`` (folder or poses.csv)."""
    p = pathlib.Path(data).resolve()
    if p.is_dir():
        if (p / "poses.csv").is_file():
            return [(p / "poses.csv", "calibration_capture")]
        return [(p / n, "calibration_capture") for n in ("tracker_stream.csv", "reference_stream.csv")
                if (p / n).is_file()]
    return [(p, "calibration_capture")]


def _capture_data_files(capture) -> List[Tuple[pathlib.Path, str]]:
    """The files a loaded capture (trackcal.captures.PoseCapture) was read from: its origin's files
    (poses.csv, both streams, or the markers and tracker files), else its path; [] for stations
    made in memory."""
    origin = getattr(capture, "origin", None) or {}
    names = origin.get("files") or ([capture.path] if getattr(capture, "path", None) is not None else [])
    return [(pathlib.Path(f).resolve(), "calibration_capture") for f in names]


def term_change(previous: Optional[Sequence[str]], terms: Sequence[str]) -> str:
    """'+dipole -lut' between two term lists, counted as multisets ('' when equal; the list itself
    for the first fit)."""
    if previous is None:
        return " + ".join(terms)
    from collections import Counter
    # As multisets: a second dipole is a change too.
    added = list((Counter(terms) - Counter(previous)).elements())
    removed = list((Counter(previous) - Counter(terms)).elements())
    return " ".join([f"+{t}" for t in added] + [f"-{t}" for t in removed])


def effect_names(report) -> List[str]:
    """The model's terms as a user wrote them: the physical chain's effects by type (sensor_offset,
    dipole, plane, ...), then the other terms (polynomial, lut)."""
    names = []
    for t in getattr(report, "terms", None) or []:
        effects = t.get("effects") if isinstance(t, dict) else None
        if effects:
            names += [str(e.get("type") or e.get("name")) for e in effects]
        elif isinstance(t, dict):
            names.append(str(t.get("type") or t.get("name")))
    return names or list(report.model["terms"])


def _keep_copy(path: pathlib.Path, data: bytes) -> None:
    """Writes a file named by its content once. One written at the same moment is the same, so on a
    file system without hard links (write_new refuses there) a rename over it is harmless."""
    if path.exists():
        return
    try:
        write_new(path, data)
    except ValueError:
        if not path.exists():
            replace_atomically(path, data)


def record_model_fit(workdir, report, *, model, data, calibration=None, label: Optional[str] = None) -> dict:
    """Records a trackcal.fit FitReport: a copy of the model text (``models/<sha256[:16]>.yaml``,
    written once), the SHA-256 of the model and of every capture file, the Table 1 scores, the term
    names, the calibration written (and a copy of it, ``models/<sha256[:16]>.json``) and fit figures. The label defaults to the term change from the
    previous model-file fit ("+dipole"; "settings" when only settings changed). ``data`` is what
    the fit was given: a capture folder or poses.csv, or a loaded capture (trackcal.captures),
    whose files are hashed."""
    workdir = pathlib.Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    text, sha = report.model["text"], report.model["sha256"]
    models = workdir / "models"
    models.mkdir(exist_ok=True)
    copy = models / f"{sha[:16]}.yaml"
    _keep_copy(copy, text.encode("utf-8", "surrogateescape"))  # the file's bytes, as hashed
    terms = effect_names(report)

    def default_label(entries: List[dict]) -> str:  # against the previous model-file fit
        previous = next((e for e in reversed(entries) if "terms" in e), None)
        if previous is None:
            return term_change(None, terms)
        if (previous.get("model") or {}).get("sha256") == sha:
            return "same model"
        return term_change(previous["terms"], terms) or "settings"
    model_path = (pathlib.Path(model).resolve()
                  if isinstance(model, (str, os.PathLike)) and report.model["source"] != "<string>" else None)
    fields = {"model": {"sha256": sha, "copy": str(copy.relative_to(workdir)), "terms": terms},
              "terms": terms,
              "fit": {"converged": report.converged, "chi2_per_dof": report.chi2_per_dof,
                      "num_free_parameters": report.num_free_parameters, "num_outliers": len(report.outliers),
                      "iterations": report.iterations}}
    if model_path is None:  # model given as text: the copy is the model file
        fields["model"]["path"] = str(copy.relative_to(workdir))
    # The receiver fitted (the capture's sensor column): fits of two receivers of one capture share
    # its files but not its stations, so their errors are no step of one loop.
    sensor = getattr(getattr(report, "calibration", None), "sensor", 0)
    if sensor:
        fields["sensor"] = int(sensor)
    if calibration is not None:
        # A copy by content beside the model's: `trackcal fit -o cal.json` may replace cal.json by a
        # later fit, and the history must still lead to the calibration each row scored.
        cal_bytes = pathlib.Path(calibration).read_bytes()
        cal_sha = hashlib.sha256(cal_bytes).hexdigest()
        cal_copy = models / f"{cal_sha[:16]}.json"
        _keep_copy(cal_copy, cal_bytes)
        fields["calibration"] = {"path": str(pathlib.Path(calibration).resolve()), "sha256": cal_sha,
                                 "copy": str(cal_copy.relative_to(workdir))}
    files = _data_files(data) if isinstance(data, (str, os.PathLike)) else _capture_data_files(data)
    # The capture as the fit read it: the engine hashes each file when it reads it (the calibration
    # file's provenance). Hashed again now, after a fit of minutes, a capture re-exported meanwhile
    # lent its SHA-256 to the old stations' scores.
    read = _fitted_capture_hashes(report)
    if files and all(str(p) in read for p, _ in files):
        fields["data"] = [{"path": str(p), "role": role, "sha256": read[str(p)]} for p, role in files]
    return record_fit(workdir, model=model_path, data=files, scores=report.scores(),
                      label=default_label if label is None else label, fields=fields)


def _fitted_capture_hashes(report) -> Dict[str, str]:
    """{resolved path: SHA-256} of the capture files the fit engine read (its provenance inputs);
    {} for a report without them (a capture loaded in Python, a report made by hand)."""
    provenance = getattr(getattr(report, "calibration", None), "provenance", None) or {}
    return {str(pathlib.Path(i["path"]).resolve()): i["sha256"] for i in provenance.get("inputs") or []
            if isinstance(i, dict) and i.get("role") == "calibration_capture"
            and isinstance(i.get("path"), str) and isinstance(i.get("sha256"), str)}


def scores_from_validation(validation) -> Dict[str, dict]:
    """Table 1 summaries of a trackcal.validation.Validation, keyed by set (the 'after' numbers
    when it has a calibration, else the 'before' ones). A cross-validation table appended to it
    (``trackcal validate --cross-validate``) is left out: trackcal.validation.cross_validate refits
    a model (by default the polynomial), so its errors are not this calibration's, and the history
    would show them first (``headline_set`` prefers held-out sets)."""
    out = {}
    for t in validation.tables:
        if t.set_name.startswith("cross-validation"):
            continue
        out[t.set_name] = {"position_mm": t.after_position_mm or t.before_position_mm,
                           "orientation_deg": t.after_orientation_deg or t.before_orientation_deg,
                           "hemisphere_flips_left_out": t.hemisphere_flips_left_out}
    return out


def headline_set(entry: dict) -> Optional[str]:
    """The set whose errors ``headline_scores`` reports: held-out first (valid, cross-validation),
    then all, then calib."""
    scores = entry.get("scores", {})
    for key in ("valid", "cross-validation", "all", "calib"):
        for name in scores:
            if name.startswith(key):
                return name
    return next(iter(scores), None)


def headline_scores(entry: dict) -> Tuple[float, float]:
    """(position mean mm, orientation mean deg) of the most telling set: held-out first."""
    name = headline_set(entry)
    if name is None:
        return math.nan, math.nan
    s = entry["scores"][name]
    return float(s["position_mm"]["mean"]), float(s["orientation_deg"]["mean"])


def headline_median_mm(entry: dict) -> float:
    """The position median [mm] of the headline set (NaN when the record has none)."""
    name = headline_set(entry)
    if name is None:
        return math.nan
    value = entry["scores"][name]["position_mm"].get("median")
    return float(value) if value is not None else math.nan


def _rows_text(rows: Sequence[int]) -> str:
    """'row 4', 'rows 2, 3', 'rows 1-60, 62' of sorted 1-based row numbers."""
    runs = []
    for r in rows:
        if runs and r == runs[-1][1] + 1:
            runs[-1][1] = r
        else:
            runs.append([r, r])
    parts = [f"{a}" if a == b else f"{a}, {b}" if b == a + 1 else f"{a}-{b}" for a, b in runs]
    return f"row{'s' if len(rows) > 1 else ''} {', '.join(parts)}"


def data_changed_notes(entries: Sequence[dict], first: int = 1) -> List[str]:
    """One note per capture file a row names that is no longer what the row fitted: changed since
    (its SHA-256 now differs from the row's) or deleted, with the rows (numbered from ``first``).
    A row's scores are of the file as it was: a refit of "the same capture" gives other numbers.
    Each file is hashed once."""
    rows: Dict[str, List[Tuple[int, str]]] = {}
    for i, e in enumerate(entries, first):
        for d in e.get("data") or []:
            if isinstance(d, dict) and isinstance(d.get("path"), str) and isinstance(d.get("sha256"), str):
                rows.setdefault(d["path"], []).append((i, d["sha256"]))
    notes = []
    for path, recorded in rows.items():
        now, what = None, "deleted"
        if os.path.lexists(path):
            try:
                now, what = _sha(path), "changed"
            except (OSError, ValueError, RuntimeError) as err:  # a folder, no permission: say why
                what = f"not readable now ({err})"
        stale = sorted({i for i, sha in recorded if sha != now})
        if not stale:
            continue
        whose = "rows'" if len(stale) > 1 else "row's"
        notes.append(f"{path} ({_rows_text(stale)}): {what} since it was fitted; the {whose} scores are of "
                     "the file as it was")
    return notes


def _change(now: float, before: Optional[float]) -> str:
    if before is None or not before or math.isnan(before) or math.isnan(now):
        return ""
    return f"{100 * (now - before) / before:+.1f}%"


def comparable_key(e: dict):
    """What two rows must share for their errors to be compared: the capture files' contents, the
    set the headline is taken from, and the receiver (``sensor``; None in rows without it)."""
    data = tuple(sorted(str(d.get("sha256")) for d in e.get("data") or [] if isinstance(d, dict)))
    return data, headline_set(e), e.get("sensor")


def comparable(key, previous) -> bool:
    """Two comparable_key values whose rows' errors may be compared: same data and set, and the same
    receiver when both rows record one (rows written before the field are taken as the same)."""
    return (key[:2] == previous[:2]
            and (key[2] is None or previous[2] is None or key[2] == previous[2]))


def comparison_break(key, previous) -> str:
    """'' when rows of comparable_key ``key`` and ``previous`` may be compared, else what differs, as
    the history's table and plot say it: "other data", "other set" or "sensor N"."""
    if comparable(key, previous):
        return ""
    return "other data" if key[0] != previous[0] else "other set" if key[1] != previous[1] else f"sensor {key[2]}"


def history_table(entries: Sequence[dict], first: int = 1) -> str:
    """Plain-text table: one row per fit with the headline error (``set``: which set's, held-out
    first) and its change from the previous. The position median beside the mean: a few gross
    errors no calibration can remove hold the mean up while the median falls (hemisphere flips are
    left out of the scores since session 23; records written before kept them). A row whose capture
    files (their SHA-256) or headline set differ from the previous row's shows "other data" or
    "other set" instead of a change, and one of another receiver (both rows recording their
    ``sensor``) "sensor N": errors on different stations are not a step of the loop.
    ``first`` numbers the first row (the last rows of a history keep their numbers)."""
    sets = [headline_set(e) or "" for e in entries]
    width = max([3] + [len(x) for x in sets])
    lines = [f"{'#':>3}  {'time (UTC)':<20}  {'label':<28} {'pos mean mm':>12} {'change':>10} "
             f"{'median mm':>10} {'change':>10} {'ori mean deg':>13} {'change':>10}  {'set':<{width}}  model"]
    prev = None
    prev_key = None
    for i, e in enumerate(entries, first):
        p, o = headline_scores(e)
        med = headline_median_mm(e)
        key = comparable_key(e)
        if prev is None or comparable(key, prev_key):
            dp = _change(p, prev[0] if prev else None)
            dm = _change(med, prev[1] if prev else None)
            do = _change(o, prev[2] if prev else None)
        else:
            dp = dm = do = comparison_break(key, prev_key)
        med_text = "" if math.isnan(med) else f"{med:.3f}"
        m = e.get("model") or {}
        model = pathlib.Path(m.get("path", "")).name + (f" @{m['sha256'][:8]}" if m.get("sha256") else "")
        lines.append(f"{i:>3}  {e.get('time_utc', ''):<20}  {str(e.get('label', ''))[:28]:<28} {p:>12.3f} "
                     f"{dp:>10} {med_text:>10} {dm:>10} {o:>13.3f} {do:>10}  "
                     f"{sets[i - first]:<{width}}  {model}")
        prev = (p, med, o)
        prev_key = key
    return "\n".join(lines)
