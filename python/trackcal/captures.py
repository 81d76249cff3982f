"""Capture files (docs/captures.md) as numpy arrays, read and written by the one C++ implementation
(core/capture.h) so Python and the C++ tools agree on every rule and every error message.

Errors raise ``ValueError`` naming the file, line and column, e.g.
``poses.csv:17: column rep_qw: 'abc' is not a number``.
"""

from __future__ import annotations

import dataclasses
import os
import pathlib
import warnings
from typing import List, Optional, Tuple, Union

import numpy as np

from trackcal import _core

PathLike = Union[str, os.PathLike]


def _capture_summary(capture) -> str:
    """"path='.../poses.csv', 480 rows (calib 300, valid 180), sensor 1, extra_columns=[...]"."""
    n = len(capture.station)
    sets = [str(s) for s in np.asarray(capture.set, dtype=object).ravel()]
    counts = {}
    for name in sets:
        counts[name] = counts.get(name, 0) + 1
    parts = [f"path={str(capture.path)!r}" if capture.path is not None else "path=None",
             f"{n} rows" + (f" ({', '.join(f'{k} {v}' for k, v in counts.items())})" if counts else "")]
    try:
        sensors = sorted({int(v) for v in np.asarray(capture.sensor).ravel()})
        parts.append(f"sensor{'s' if len(sensors) != 1 else ''} {', '.join(map(str, sensors))}")
    except (TypeError, ValueError):  # a hand-built capture not checked yet: not repr's to refuse
        parts.append(f"sensor {np.asarray(capture.sensor)!r}")
    if capture.extra_columns:
        parts.append(f"extra_columns={list(capture.extra_columns)!r}")
    return ", ".join(parts)


def _same_values(a, b) -> bool:
    """Whether two field values are equal: arrays of the same shape element by element, NaN equal
    to NaN (an extra column's missing value, a summary of one station), objects with ``equals``
    (a Validation's capture and residuals) by it, dataclasses, dicts, lists and tuples field by
    field and item by item, a calibration by its file text, anything else by ==."""
    if isinstance(a, _ArrayFields) or isinstance(b, _ArrayFields):
        return isinstance(a, _ArrayFields) and a.equals(b)
    if dataclasses.is_dataclass(a) and not isinstance(a, type):
        return type(a) is type(b) and all(_same_values(getattr(a, f.name), getattr(b, f.name))
                                          for f in dataclasses.fields(a))
    if isinstance(a, dict):
        return isinstance(b, dict) and a.keys() == b.keys() and all(_same_values(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)):
        return (type(a) is type(b) and len(a) == len(b)
                and all(_same_values(x, y) for x, y in zip(a, b)))
    if isinstance(a, _core.Calibration):  # compares by identity: by the file it would write
        return isinstance(b, _core.Calibration) and a.to_json() == b.to_json()
    if isinstance(a, float) and isinstance(b, float) and a != a and b != b:
        return True
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        if a is None or b is None:
            return False
        a, b = np.asarray(a), np.asarray(b)
        if a.shape != b.shape:
            return False
        nan_aware = a.dtype.kind in "fc" and b.dtype.kind in "fc"
        return bool(np.array_equal(a, b, equal_nan=nan_aware))
    return bool(a == b)


class _ArrayFields:
    """Equality of a dataclass that holds numpy arrays. ``==`` is refused with a hint: the
    dataclass's == compared tuples of arrays and failed with numpy's "The truth value of an array
    with more than one element is ambiguous", and an element-wise answer has no meaning for a whole
    capture; ``equals(other)`` says whether every compared field holds the same values, as pandas'
    and xarray's ``equals`` do."""

    _not_compared: tuple = ()

    def equals(self, other) -> bool:
        """True when ``other`` is of the same class and every field holds the same values (arrays
        element by element, NaN equal to NaN)."""
        if type(other) is not type(self):
            return False
        return all(_same_values(getattr(self, f.name), getattr(other, f.name))
                   for f in dataclasses.fields(self) if f.name not in self._not_compared)

    def __eq__(self, other):
        if not isinstance(other, _ArrayFields):
            return NotImplemented
        raise TypeError(f"{type(self).__name__} == {type(other).__name__} is not defined (they hold numpy "
                        "arrays): use a.equals(b) for whether they hold the same values, or compare "
                        "their arrays, e.g. np.array_equal(a.time, b.time)")

    __hash__ = None  # mutable arrays, as the dataclass had it


@dataclasses.dataclass(repr=False, eq=False)
class PoseCapture(_ArrayFields):
    """Paired static stations of a poses.csv: the tracker's report and the reference, per row.

    Quaternions are (N, 4) ordered x, y, z, w; positions (N, 3) in metres, transmitter frame.
    ``extra`` holds every extra column (``extra_columns`` names them), NaN where missing. A column of
    labels (text: an operator, a room, a tracker's serial number) holds each station's label index
    into ``extra_labels[name]``; ``column(name)`` gives the labels themselves.
    """

    path: Optional[pathlib.Path]
    station: np.ndarray
    set: np.ndarray
    sensor: np.ndarray
    time: np.ndarray
    reported_positions: np.ndarray
    reported_quaternions_xyzw: np.ndarray
    reference_positions: np.ndarray
    reference_quaternions_xyzw: np.ndarray
    extra_columns: list
    extra: np.ndarray
    # Per station: the receiver's speed [m/s] when the stations were paired from streams (a
    # covariate of the diagnosis), else None.
    speed: Optional[np.ndarray] = None
    # How the stations were obtained (``load``): {"kind": "poses" | "streams" | "markers", ...}.
    origin: Optional[dict] = None
    # {column: sorted labels} for the extra columns that hold labels rather than numbers.
    extra_labels: dict = dataclasses.field(default_factory=dict)

    # Where the stations came from, not what they are: equals() leaves them out.
    _not_compared = ("path", "origin")

    def __len__(self) -> int:
        return len(self.station)

    def __repr__(self) -> str:
        # The dataclass repr printed every array: 18 kB and 257 lines for the paper's 480 stations,
        # in a notebook cell or a log line that wanted to know which capture this is.
        return f"PoseCapture({_capture_summary(self)})"

    def subset(self, mask) -> "PoseCapture":
        """Rows selected by a boolean mask or index array (same file)."""
        mask = np.asarray(mask)
        fields = {}
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            fields[f.name] = v[mask] if isinstance(v, np.ndarray) else v
        return PoseCapture(**fields)

    def select_set(self, name: str) -> "PoseCapture":
        return self.subset(self.set == name)

    @property
    def sets(self) -> list:
        """Set names present, in order of first appearance."""
        seen = []
        for s in self.set:
            if s not in seen:
                seen.append(str(s))
        return seen

    def column(self, name: str) -> np.ndarray:
        """An extra column by name: numbers (NaN where missing), or for a column of labels an object
        array of labels (None where missing); KeyError listing the available ones otherwise."""
        return _column(self, name)


def _column(table, name: str) -> np.ndarray:
    if name not in table.extra_columns:
        raise KeyError(f"{getattr(table, 'path', None)}: no extra column {name!r} "
                       f"(have: {', '.join(table.extra_columns) or 'none'})")
    values = table.extra[:, table.extra_columns.index(name)]
    labels = (table.extra_labels or {}).get(name)
    if labels is None:
        return values
    return np.array([None if np.isnan(v) else labels[int(v)] for v in values], dtype=object)


def _user_errors(function, *args):
    """Calls a C++ reader or writer of core/capture.h. Its std::runtime_error (a file that cannot be
    opened, an output that exists) arrives as RuntimeError; like its format errors it is the
    user's input, so it is raised as ValueError (the message names the file)."""
    try:
        return function(*args)
    except RuntimeError as e:
        raise ValueError(str(e)) from None
    except UnicodeDecodeError:
        # The C++ reader takes any bytes; a label or column name that is not UTF-8 (a spreadsheet's
        # Latin-1 or Windows-1252 export: an operator "José") failed only when it became a Python
        # str, as "'utf-8' codec can't decode byte 0xe9 in position 3" naming no file.
        raise ValueError(not_utf8_message(args[0])) from None


def not_utf8_inputs(function, *args, inputs=()):
    """Calls function(*args); a UnicodeDecodeError (a label of one of the CSV files ``inputs`` that
    is not UTF-8 text) becomes a ValueError naming the first such file, line and column."""
    try:
        return function(*args)
    except UnicodeDecodeError:
        for path in inputs:
            if path is not None and pathlib.Path(path).is_file():
                try:
                    pathlib.Path(path).read_bytes().decode("utf-8")
                except UnicodeDecodeError:
                    raise ValueError(not_utf8_message(path)) from None
        raise


def not_utf8_message(path: PathLike) -> str:
    """'<file>:<line>: column <name>: <field> is not UTF-8 text ...' for the first field of a CSV
    file that is not UTF-8 (its line numbered as the C++ reader numbers them)."""
    p = pathlib.Path(path)
    data = p.read_bytes()
    if data.startswith(b"\xef\xbb\xbf"):
        data = data[3:]
    lines = data.split(b"\n") if b"\n" in data else data.split(b"\r")
    header = None
    for number, raw in enumerate(lines, start=1):
        fields = [f.strip(b" \t\r") for f in raw.split(b",")]
        if header is None and any(fields):
            header = fields
        for k, field in enumerate(fields):
            try:
                field.decode("utf-8")
            except UnicodeDecodeError:
                if fields is header:
                    where = f"header: column {k + 1}"
                else:
                    name = header[k].decode("utf-8", "replace") if k < len(header) else f"{k + 1}"
                    where = f"column {name}"
                text = field.decode("utf-8", "backslashreplace")
                return f"{p}:{number}: {where}: '{text}' is not UTF-8 text (save the file as UTF-8)"
    return f"{p}: not UTF-8 text (save the file as UTF-8)"


def _path_arg(path, name: str = "path") -> pathlib.Path:
    """A path argument as pathlib.Path. Another type was Python's "expected str, bytes or
    os.PathLike object, not int", naming no argument: a TypeError naming it, in the words of the
    C++ functions' (bytes too: pathlib refuses it)."""
    if isinstance(path, bytes):
        raise TypeError(f"{name} must be a str or os.PathLike path, got bytes {path!r:.80}: decode it "
                        "with os.fsdecode()")
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"{name} must be a path (str or os.PathLike such as pathlib.Path), got "
                        f"{type(path).__name__}")
    return pathlib.Path(path)


def _resolve(path: PathLike, file_name: str) -> pathlib.Path:
    p = _path_arg(path)
    return p / file_name if p.is_dir() else p


def load_poses(path: PathLike) -> PoseCapture:
    """Reads a poses.csv (or the poses.csv of a capture folder); ValueError naming the file (and
    line and column) when it cannot be read."""
    p = _resolve(path, "poses.csv")
    d = _user_errors(_core.read_poses, p)
    return PoseCapture(
        path=p,
        station=np.asarray(d["station"]),
        set=np.asarray(d["set"], dtype=object),
        sensor=np.asarray(d["sensor"]),
        time=np.asarray(d["time"]),
        reported_positions=d["reported_positions"],
        reported_quaternions_xyzw=d["reported_quaternions_xyzw"],
        reference_positions=d["reference_positions"],
        reference_quaternions_xyzw=d["reference_quaternions_xyzw"],
        extra_columns=list(d["extra_columns"]),
        extra=d["extra"],
        extra_labels=dict(d["extra_labels"]),
    )


STREAM_FILES = ("tracker_stream.csv", "reference_stream.csv")
MARKER_FILES = ("markers.csv", "tracker.csv")


def capture_kind(path: PathLike) -> str:
    """What a capture path holds, in the order ``load`` uses it: "poses" (a file, or a folder with
    poses.csv), "streams" (tracker_stream.csv and reference_stream.csv) or "markers" (markers.csv
    and tracker.csv). ValueError naming the path and the files looked for otherwise."""
    p = pathlib.Path(path)
    if not p.is_dir():
        if not p.exists():
            raise ValueError(f"{p}: no such file or folder")
        return "poses"
    if (p / "poses.csv").is_file():
        return "poses"
    if all((p / n).is_file() for n in STREAM_FILES):
        return "streams"
    if all((p / n).is_file() for n in MARKER_FILES):
        return "markers"
    # One stream without the other (as trackcal-fit --data and trackcal.fit say it).
    halves = [n for n in STREAM_FILES if (p / n).is_file()]
    if len(halves) == 1:
        other = STREAM_FILES[1 - STREAM_FILES.index(halves[0])]
        half = f"; {halves[0]} has no {other} beside it to be paired with"
    else:
        half = ""
    # A `trackcal record` folder (LABEL_tracker_stream.csv per device) is a recording, validated
    # against its reference stream by trackcal.validation.validate_recording, not a capture: say so.
    recorded = sorted(f.name for f in p.glob("*_tracker_stream.csv") if f.is_file())
    hint = (f"; {', '.join(recorded)}: a recording (trackcal record): validate it against the "
            "reference stream with trackcal.validation.validate_recording (docs/understand.md)"
            if recorded else "")
    raise ValueError(f"{p}: not a capture folder (no poses.csv, no {' + '.join(STREAM_FILES)}, "
                     f"no {' + '.join(MARKER_FILES)}){half}{hint}")


def load(path: PathLike, *, time_offset: Optional[float] = None, search_range: float = 0.5,
         register_markers: bool = False, register_options: Optional[dict] = None,
         sensor: Optional[int] = None, clock_drift: float = 0.0,
         clock_drift_origin_s: Optional[float] = None) -> PoseCapture:
    """Any capture as paired stations (docs/captures.md), whatever the folder holds:

    - ``poses.csv`` (or a folder with one): read as it is;
    - ``tracker_stream.csv`` + ``reference_stream.csv``: paired by time (``trackcal.pair``, lowest
      sensor of the stream) at ``time_offset`` [s] (t_reference - t_tracker), or, when it is None,
      at an offset estimated within +-``search_range`` s (a given offset with the clock drift
      ``clock_drift`` about the tracker time ``clock_drift_origin_s``, as a fit that corrected a
      drift records them: ``trackcal.pair``); every paired sample is a station of set
      ``calib`` and carries its speed (``speed``, a covariate of the diagnosis) and the tracker
      stream's extra columns at its time;
    - ``markers.csv`` + ``tracker.csv`` (raw optical markers): registered (``trackcal.register``,
      paper section 3; ``register_options`` are its keyword options) and every station's reference
      pose extracted. With ``register_markers`` this is done even when the folder has a poses.csv,
      whose ``set`` column then says which stations register (``reg``) and which set each station
      is in; without a poses.csv every station registers and is set ``calib``.

    ``sensor`` (the ``sensor`` column, from 1) keeps that receiver's stations: a poses.csv's rows
    of it, the tracker stream's samples of it paired, the markers registered with its tracker.csv
    rows; ``ValueError`` when the capture has none. None keeps every station (the lowest sensor of
    streams, sensor 1 of markers).

    ``origin`` says which, with the offset used (and its source) or the registration's chi-square.
    """
    from trackcal.fitting import pair, register
    p = _path_arg(path)
    kind = capture_kind(p)
    labels = None
    if register_markers:
        if not (p.is_dir() and all((p / n).is_file() for n in MARKER_FILES)):
            raise ValueError(f"{p}: register_markers needs a folder with {' and '.join(MARKER_FILES)}")
        labels = p / "poses.csv" if (p / "poses.csv").is_file() else None
        kind = "markers"
    if sensor is not None and (isinstance(sensor, bool) or int(sensor) != sensor or sensor < 1):
        raise ValueError(f"sensor must be a receiver number (1, 2, ...), got {sensor!r}")
    if kind == "poses":
        cap = load_poses(p)
        cap.origin = {"kind": "poses", "files": [str(cap.path)]}
        if sensor is not None:
            have = sorted(int(s) for s in np.unique(cap.sensor))
            if sensor not in have:
                raise ValueError(f"{cap.path}: no station of sensor {sensor} (the sensor column has "
                                 f"{', '.join(map(str, have)) or 'none'})")
            origin = cap.origin
            cap = cap.subset(cap.sensor == sensor)
            cap.origin = origin
        return cap
    if kind == "streams":
        estimate = time_offset is None
        with warnings.catch_warnings():  # its warning goes in origin, printed with the pairing line
            warnings.simplefilter("ignore", UserWarning)
            result = pair(p / STREAM_FILES[0], p / STREAM_FILES[1],
                          time_offset=0.0 if estimate else float(time_offset),
                          estimate_time_offset=estimate, search_range=search_range,
                          sensor=int(sensor or 0), clock_drift=0.0 if estimate else float(clock_drift),
                          clock_drift_origin_s=None if estimate else clock_drift_origin_s)
        cap = result.poses
        first = carry_stream_columns(cap, p / STREAM_FILES[0], p / STREAM_FILES[1], result.time_offset_s,
                                     result.clock_drift_applied, result.clock_drift_origin_s)
        cap.path = p / STREAM_FILES[0]
        warning = with_gaps(result.warning, p / STREAM_FILES[0], first)
        cap.origin = {"kind": "streams", "files": [str(p / n) for n in STREAM_FILES],
                      "time_offset_s": float(result.time_offset_s),
                      "clock_drift": float(result.clock_drift_applied),
                      "time_offset_source": "estimated" if estimate else "given",
                      "paired": len(cap), "dropped": int(result.dropped), "sensor": first,
                      "warning": warning}
        return cap
    options = dict(register_options or {})
    if sensor is not None:
        options["sensor"] = int(sensor)
    result = register(p / MARKER_FILES[0], p / MARKER_FILES[1], poses=labels, **options)
    cap = result.poses
    cap.path = p / MARKER_FILES[1]
    cap.origin = {"kind": "markers", "files": [str(p / n) for n in MARKER_FILES] + ([str(labels)] if labels else []),
                  "registered_with": "the reg stations of poses.csv" if labels else "every station",
                  "registered": len(cap), "left_out": [int(s) for s in result.left_out],
                  "converged": bool(result.converged), "chi_square": float(result.chi_square),
                  "nu": float(result.nu)}
    return cap


def carry_stream_columns(cap: PoseCapture, tracker_stream: PathLike, reference_stream: PathLike,
                         time_offset_s: float, clock_drift: float = 0.0,
                         clock_drift_origin_s: float = 0.0) -> int:
    """Gives stations paired from streams (``trackcal.pair``; lowest sensor) what the streams logged
    beside the poses, for the diagnosis to test as covariates as it does a poses.csv's columns: the
    receiver's ``speed`` at each station's time, the tracker stream's extra columns at that time,
    and the reference stream's at the same instant on its own clock (time + ``time_offset_s`` +
    ``clock_drift`` (time - ``clock_drift_origin_s``), where the pairing took the pose: a corrected
    drift is the Pairing's ``clock_drift_applied``; an optical system's per-frame residual or marker
    count). Numbers are interpolated, labels are
    those of the nearest sample; a reference column whose name the tracker's already has is named
    reference_<name>. Returns the sensor whose samples were paired."""
    stream = load_tracker_stream(tracker_stream)
    sensor = int(cap.sensor[0]) if len(cap) else int(stream.sensor[0]) if len(stream) else 1
    # The sensor's samples in time order: the tracker stream reader does not require it (several
    # receivers interleave), the pairing takes each sample alone, and np.interp and
    # nearest_samples need increasing times (out of order they silently gave another sample's
    # speed and columns).
    own = np.flatnonzero(stream.sensor == sensor)
    own = own[np.argsort(stream.time[own], kind="stable")]
    cap.speed = (np.interp(cap.time, stream.time[own], stream.speed()[own]) if len(own)
                 else np.zeros(len(cap)))
    if not len(cap):
        return sensor
    reference = load_reference_stream(reference_stream)
    names = list(cap.extra_columns)
    columns = [cap.extra[:, k] for k in range(len(cap.extra_columns))]
    for table, rows, at, prefix in ((stream, own, cap.time, ""),
                                    (reference, np.arange(len(reference)),
                                     cap.time + time_offset_s + clock_drift * (cap.time - clock_drift_origin_s),
                                     "reference_")):
        if not len(rows):
            continue
        t = table.time[rows]
        for k, name in enumerate(table.extra_columns):
            out = name
            if out in names:
                if not prefix:
                    continue  # the paired poses already carry it
                out = prefix + name
                if out in names:
                    continue
            v = table.extra[rows, k]
            if name in table.extra_labels:
                columns.append(v[nearest_samples(t, at)])
                cap.extra_labels[out] = list(table.extra_labels[name])
            else:
                columns.append(np.interp(at, t, v))
            names.append(out)
    if len(names) > len(cap.extra_columns):
        cap.extra_columns = names
        cap.extra = np.column_stack(columns).astype(float)
    return sensor


def describe_origin(capture: PoseCapture) -> Optional[str]:
    """One line saying how stations that were not read from a poses.csv were obtained."""
    o = capture.origin or {}
    if o.get("kind") in ("streams", "recording"):
        drift = o.get("clock_drift") or 0.0
        from trackcal._format import fixed
        return (f"streams paired at a time offset of {fixed(1e3 * o['time_offset_s'], '{:.2f}')} ms"
                + (f" and a clock drift of {1e6 * drift:.1f} ppm" if drift else "") + f" ({o['time_offset_source']}): "
                f"{o['paired']} samples of sensor {o['sensor']}, {o['dropped']} dropped"
                + (f"\nwarning: {', '.join(o['files'])}: {o['warning']}" if o.get("warning") else ""))
    if o.get("kind") == "markers":
        return (f"raw markers registered (paper section 3) with {o['registered_with']}: {o['registered']} stations, "
                f"{len(o['left_out'])} left out, chi-square {o['chi_square']:.1f} for {o['nu']:.0f} degrees of freedom")
    return None


def nearest_samples(t: np.ndarray, at: np.ndarray) -> np.ndarray:
    """Index into the increasing times t of the sample nearest each of ``at`` (the later on a tie)."""
    idx = np.clip(np.searchsorted(t, at), 0, len(t) - 1)
    prev = np.clip(idx - 1, 0, len(t) - 1)
    return np.where(np.abs(t[prev] - at) < np.abs(t[idx] - at), prev, idx)


class _StreamColumns:
    """What the two streams share: a sample count and their extra columns by name."""

    def __len__(self) -> int:
        return len(self.time)

    def column(self, name: str) -> np.ndarray:
        """An extra column by name, as ``PoseCapture.column``."""
        return _column(self, name)


@dataclasses.dataclass(eq=False)
class TrackerStream(_StreamColumns, _ArrayFields):
    """Unaveraged tracker samples (tracker_stream.csv): time [s], sensor, poses."""

    time: np.ndarray
    sensor: np.ndarray
    positions: np.ndarray
    quaternions_xyzw: np.ndarray
    extra_columns: list = dataclasses.field(default_factory=list)
    extra: Optional[np.ndarray] = None
    extra_labels: dict = dataclasses.field(default_factory=dict)  # as PoseCapture's

    def speed(self) -> np.ndarray:
        """Speed [m/s] per sample from central differences along each sensor's samples in time
        order; at a gap (``gaps``) from the step on the sample's own side only (a central difference
        across a 1 s dropout gave 0.069 m/s on either side of it, 0.097 and 0.030 true), and NaN for
        a sample with a gap on both sides."""
        out = np.zeros(len(self.time))
        for s in np.unique(self.sensor):
            idx = np.flatnonzero(self.sensor == s)
            idx = idx[np.argsort(self.time[idx], kind="stable")]  # neighbours in time, not in the file
            if len(idx) < 2:
                continue
            t, p = self.time[idx], self.positions[idx]
            step = np.diff(t)
            # Per step: its speed, unless it spans a gap (the reader refuses a repeated time).
            with np.errstate(divide="ignore", invalid="ignore"):
                v_step = np.linalg.norm(np.diff(p, axis=0), axis=1) / step
            ok = ~_gap_steps(step)
            before, after = np.r_[False, ok], np.r_[ok, False]  # the steps into and out of sample i
            with np.errstate(divide="ignore", invalid="ignore"):
                central = np.linalg.norm(np.gradient(p, axis=0), axis=1) / np.gradient(t)
            v = np.full(len(t), np.nan)
            v[after] = np.r_[v_step, np.nan][after]  # forward (the first sample; before a gap)
            v[before] = np.r_[np.nan, v_step][before]  # backward (the last sample; after a gap)
            v[before & after] = central[before & after]
            out[idx] = v
        return out

    def gaps(self) -> List[Tuple[int, float, float]]:
        """(sensor, time of the last sample before, duration [s]) of every gap in each sensor's
        samples: a step longer than both GAP_MIN_S and GAP_FACTOR times the sensor's median step."""
        found = []
        for s in np.unique(self.sensor):
            t = np.sort(self.time[self.sensor == s])
            step = np.diff(t)
            for k in np.flatnonzero(_gap_steps(step)):
                found.append((int(s), float(t[k]), float(step[k])))
        return found


# A step of a sensor's samples longer than both of these is a gap (a dropout, a paused recording):
# the pairing's longest reference step interpolated across (trackcal.pair max_gap_s), and ten of
# the sensor's median steps (a slow tracker's regular steps are no gap).
GAP_MIN_S = 0.1
GAP_FACTOR = 10.0


def _gap_steps(step: np.ndarray) -> np.ndarray:
    """Which of a sensor's time steps (increasing times) are gaps."""
    if not len(step):
        return np.zeros(0, bool)
    return (step > GAP_MIN_S) & (step > GAP_FACTOR * float(np.median(step)))


def with_gaps(warning: str, tracker_stream: PathLike, sensor: int) -> str:
    """A pairing's warning with what the tracker stream's samples of ``sensor`` hold that the pairing
    does not say: rows out of time order (taken in time order; two recordings concatenated into
    one file interleave) and gaps (the pairing takes every sample alone, but the speed covariate
    and a reader of the tables need to know the stream has holes)."""
    stream = load_tracker_stream(tracker_stream)
    t = stream.time[stream.sensor == sensor]
    back = np.flatnonzero(np.diff(t) < 0)
    order = (f"sensor {sensor}'s samples are not in time order in the file ({len(back)} go back in "
             f"time, the first t = {t[back[0] + 1]:.3f} s after t = {t[back[0]]:.3f} s): taken in time "
             f"order (a file of two recordings interleaves them)") if len(back) else ""
    gaps = [g for g in stream.gaps() if g[0] == sensor]
    return "; ".join(w for w in (warning, order, gaps_text(gaps) if gaps else "") if w)


def gaps_text(gaps: List[Tuple[int, float, float]], limit: int = 5) -> str:
    """The gaps of TrackerStream.gaps in words, for the pairing's line."""
    words = [f"sensor {s}: no sample from t = {t:.3f} to {t + d:.3f} s ({d:.3f} s)" for s, t, d in gaps[:limit]]
    more = f" and {len(gaps) - limit} more" if len(gaps) > limit else ""
    return (f"the tracker stream has {len(gaps)} gap{'s' if len(gaps) != 1 else ''} (steps over "
            f"{GAP_MIN_S:g} s and {GAP_FACTOR:g} median steps): " + "; ".join(words) + more
            + "; no speed is taken across a gap")


def load_tracker_stream(path: PathLike) -> TrackerStream:
    p = _resolve(path, "tracker_stream.csv")
    d = _user_errors(_core.read_tracker_stream, p)
    return TrackerStream(time=d["time"], sensor=d["sensor"], positions=d["positions"],
                         quaternions_xyzw=d["quaternions_xyzw"], extra_columns=list(d["extra_columns"]),
                         extra=d["extra"], extra_labels=dict(d["extra_labels"]))


@dataclasses.dataclass(eq=False)
class ReferenceStream(_StreamColumns, _ArrayFields):
    """Unaveraged reference samples (reference_stream.csv) on the reference clock: time [s], poses
    (transmitter_from_body, registered into the transmitter frame)."""

    time: np.ndarray
    positions: np.ndarray
    quaternions_xyzw: np.ndarray
    extra_columns: list = dataclasses.field(default_factory=list)
    extra: Optional[np.ndarray] = None
    extra_labels: dict = dataclasses.field(default_factory=dict)  # as PoseCapture's


def load_reference_stream(path: PathLike) -> ReferenceStream:
    p = _resolve(path, "reference_stream.csv")
    d = _user_errors(_core.read_reference_stream, p)
    return ReferenceStream(time=d["time"], positions=d["positions"], quaternions_xyzw=d["quaternions_xyzw"],
                           extra_columns=list(d["extra_columns"]), extra=d["extra"],
                           extra_labels=dict(d["extra_labels"]))


def save_tracker_stream(path: PathLike, stream: TrackerStream, overwrite: bool = False) -> None:
    """Writes tracker_stream.csv atomically, with its extra columns; never replaces an existing
    file unless asked (ValueError naming it)."""
    extra_columns = list(stream.extra_columns or [])
    _user_errors(_core.write_tracker_stream, pathlib.Path(path), stream.time, stream.sensor, stream.positions,
                 stream.quaternions_xyzw, overwrite, extra_columns,
                 stream.extra if extra_columns else None, dict(stream.extra_labels or {}))


def format_tracker_stream(stream: TrackerStream, *, name: str = "tracker_stream.csv", header: bool = True) -> bytes:
    """The bytes save_tracker_stream writes for the stream, without a file (in memory, in C++):
    refused as it refuses, ValueError naming ``name`` where it names the file. Without the header
    line when not ``header``: the rows to append to a file that has it, which then holds the bytes
    one write of all the rows gives (a live recording, trackcal.record)."""
    extra_columns = list(stream.extra_columns or [])
    return _core.format_tracker_stream(stream.time, stream.sensor, stream.positions, stream.quaternions_xyzw,
                                       name=str(name), header=header, extra_columns=extra_columns,
                                       extra=stream.extra if extra_columns else None,
                                       extra_labels=dict(stream.extra_labels or {}))
