"""The fitting engine in process: ``trackcal.fit``, ``trackcal.register``, ``trackcal.pair``.

They run the C++ code of ``trackcal-fit`` (fit/fit_engine.h, fit/registration_io.h,
fit/stream_pairing.h) inside the Python process with the GIL released, so a fit gives the same
numbers as the command-line tool, and ``FitReport.to_dict()`` is the document ``trackcal-fit fit
--json`` prints. Bad input raises ``ValueError`` with the C++ message naming the file, line, column
and field (``model.yaml:3:5: terms[0].degree: ...``).

::

    report = trackcal.fit("capture/", "model.yaml", folds=5)
    print(report.format())                  # Table 1 rows: calib, valid, cross-validation
    report.save("calib.json")               # atomic; never over the model or the capture
    cal = report.calibration                # a trackcal.Calibration
"""

from __future__ import annotations

import copy
import dataclasses
import json
import numbers
import os
import pathlib
import warnings
from typing import Callable, Dict, List, Optional, Union

import numpy as np

from trackcal import _core
from trackcal.captures import PoseCapture, _ArrayFields, not_utf8_inputs

PathLike = Union[str, os.PathLike]
Progress = Callable[[str, int, int], None]


def _table1(d: dict):
    from trackcal.validation import Table1
    return Table1(d["set"], d["before"]["position_mm"], d["before"]["orientation_deg"],
                  d["after"]["position_mm"], d["after"]["orientation_deg"],
                  hemisphere_flips_left_out=int(d.get("hemisphere_flips_left_out", 0)))


def _capture_from_dict(d: dict, path=None) -> PoseCapture:
    return PoseCapture(path=pathlib.Path(path) if path is not None else None,
                       station=np.asarray(d["station"]), set=np.asarray(d["set"], dtype=object),
                       sensor=np.asarray(d["sensor"]), time=np.asarray(d["time"]),
                       reported_positions=d["reported_positions"],
                       reported_quaternions_xyzw=d["reported_quaternions_xyzw"],
                       reference_positions=d["reference_positions"],
                       reference_quaternions_xyzw=d["reference_quaternions_xyzw"],
                       extra_columns=list(d["extra_columns"]), extra=d["extra"],
                       extra_labels=dict(d.get("extra_labels", {})))


@dataclasses.dataclass(eq=False)
class Parameter(_ArrayFields):
    """One parameter block of a fitted term: values with standard deviations (NaN: none, as ``null``
    in ``to_dict()``: a fixed block, a coordinate the data leave undetermined (named in
    ``identifiability_flags``), or a manifold block, whose uncertainty is that of its tangent
    coordinates). A manifold block (a quaternion, a plane's unit normal) has ``tangent_names``
    (``rotation_vector.x``, ...), their ``tangent_stddev`` (NaN: none) and ``tangent_unit``
    (``rad``), as ``trackcal-fit fit`` prints them; empty for other blocks."""

    term: str
    block: str
    unit: str
    fixed: bool
    names: List[str]
    values: np.ndarray
    stddev: np.ndarray
    tangent_names: List[str] = dataclasses.field(default_factory=list)
    tangent_stddev: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))
    tangent_unit: str = ""


def _stddevs(entries) -> np.ndarray:
    return np.array([np.nan if v["stddev"] is None else v["stddev"] for v in entries], dtype=float)


def _parameter(p: dict) -> Parameter:
    tangent = p.get("tangent") or []
    return Parameter(p["term"], p["block"], p["unit"], p["fixed"], [v["name"] for v in p["values"]],
                     np.array([v["value"] for v in p["values"]], dtype=float), _stddevs(p["values"]),
                     [t["name"] for t in tangent], _stddevs(tangent), p.get("tangent_unit", ""))


class _Detached:
    """What a result keeps of its native run (a C++ object, which does not pickle) when it is
    pickled: a process pool's worker returns a FitReport, Registration or Pairing to its parent.
    It answers what the wrappers ask of the native run (to_dict, summary, calibration, output,
    failure, save) from the run's document, calibration and poses, and save() refuses what the
    native one refuses (a failed fit, an input, an existing poses.csv or a file that is not a
    calibration)."""

    def __init__(self, native, kind: str):
        if isinstance(native, _Detached):  # pickled again
            self.__dict__.update(native.__dict__)
            return
        self.kind = kind
        self._doc = native.to_dict()
        self.output = native.output if kind == "fit" else (
            pathlib.Path(self._doc["output"]) if self._doc.get("output") else None)
        if kind == "fit":
            self._calibration = native.calibration
            self.failure = native.failure
            self._inputs = [str(p) for p in native.protected_paths]
        else:
            self._poses = _capture_from_dict(native.poses)
            self._inputs = [str(p) for p in native.inputs]
            self._summary = native.summary() if kind == "registration" else ""

    @property
    def calibration(self):
        return copy.deepcopy(self._calibration)  # a copy each time, as the native run gives

    def summary(self) -> str:
        return self._summary

    def to_dict(self) -> dict:
        doc = copy.deepcopy(self._doc)
        doc["output"] = str(self.output) if self.output is not None else None
        return doc

    def save(self, path, command_line: str = "") -> None:
        if self.kind != "fit":
            _core.write_poses(path, self._poses, self._inputs)
            self.output = pathlib.Path(path)
            return
        if self.failure:
            raise ValueError(self.failure)
        out = pathlib.Path(path)
        for given in self._inputs:  # as the native save's CheckNotAnInput
            try:
                same = out.exists() and os.path.samefile(out, given)
            except OSError:
                same = False
            if same:
                raise ValueError(f"{out}: output would overwrite the input {given}")
        doc = json.loads(self._calibration.to_json())
        doc["provenance"].pop("command_line", None)
        if command_line:
            doc["provenance"]["command_line"] = command_line
        _core.Calibration.from_json(json.dumps(doc), str(out)).save(out)
        self.output = out


class FitReport:
    """The result of :func:`fit`.

    Attributes: ``tables`` (Table 1 rows as ``trackcal.validation.Table1``: calib, valid when the
    capture has one, cross-validation when ``folds`` >= 2), ``parameters`` (:class:`Parameter`),
    ``identifiability_flags`` ([{coordinate, reason}]), ``outliers`` ([{station, whitened_rms}]),
    ``converged``, ``termination_type``, ``failure`` (why a failed fit is not saved; "" when it
    did not fail), ``chi2_per_dof``, ``terms`` (each term's description), ``calibration`` (a
    ``trackcal.Calibration``), ``model`` ({source, text, sha256, terms}).
    """

    def __init__(self, native, model_info: dict):
        self._native = native
        self.model = model_info
        fit = native.fit
        self.fit = fit
        self.tables = [_table1(t) for t in native.tables]
        self.converged: bool = fit["converged"]
        # How the solve ended (Ceres' termination type: "CONVERGENCE", "NO_CONVERGENCE" at the
        # model's max_iterations, "FAILURE", ...; docs/fit.md) and, for a fit that failed, why
        # save() refuses it ("" otherwise).
        self.termination_type: str = fit.get("termination_type", "")
        self.failure: str = native.failure
        self.iterations: int = fit["iterations"]
        self.final_cost: float = fit["final_cost"]
        self.chi2_per_dof: Optional[float] = fit["chi2_per_dof"]
        self.num_residuals: int = fit["num_residuals"]
        self.num_free_parameters: int = fit["num_free_parameters"]
        self.rank_deficient: bool = fit["rank_deficient"]
        self.seconds: float = fit["seconds"]
        # Which covariance gave the standard deviations: "sandwich (CR2)", "sandwich (CR1)" (one
        # cluster per station), "sandwich (CR2, 32 clusters)" (stream samples in runs of time) or
        # "model" (docs/fit.md, "Standard deviations"); None without standard deviations.
        self.covariance_estimator: Optional[str] = fit.get("covariance_estimator")
        # The sandwich's number of clusters (0: the model covariance).
        self.covariance_clusters: int = fit.get("covariance_clusters", 0)
        self.identifiability_flags: List[dict] = fit["identifiability_flags"]
        self.outliers: List[dict] = fit["outliers"]
        self.terms: List[dict] = fit["terms"]
        self.parameters = [_parameter(p) for p in fit["parameters"]]
        self.time_offset_s: Optional[float] = native.time_offset_s
        # Streams paired at a poorly determined clock offset: what the pairing warns ("" otherwise).
        self.pairing_warning: str = native.pairing_warning
        self.num_calib_stations: int = native.num_calib_stations
        self.num_valid_stations: int = native.num_valid_stations

    @property
    def calibration(self):
        """The fitted correction chain with its calibrated volume (a ``trackcal.Calibration``)."""
        return self._native.calibration

    def __getstate__(self):
        # The native run does not pickle ("cannot pickle 'trackcal._core.NativeFitReport'
        # object"): a process pool's fit could not be returned. Its document, calibration and
        # what save() checks go instead.
        return {**self.__dict__, "_native": _Detached(self._native, "fit")}

    @property
    def output(self) -> Optional[pathlib.Path]:
        return self._native.output

    def table(self, name: str):
        """The Table 1 of a set by name prefix ('calib', 'valid', 'cross-validation')."""
        for t in self.tables:
            if t.set_name.startswith(name):
                return t
        raise KeyError(f"no table {name!r} (have: {', '.join(t.set_name for t in self.tables)})")

    def held_out(self):
        """The most telling Table 1: validation set, else cross-validation, else calib."""
        for key in ("valid", "cross-validation", "calib"):
            for t in self.tables:
                if t.set_name.startswith(key):
                    return t
        return self.tables[0]

    def scores(self) -> Dict[str, dict]:
        """{set name: {"position_mm": summary, "orientation_deg": summary}} of the corrected poses
        (the history's scores)."""
        return {t.set_name: {"position_mm": t.after_position_mm, "orientation_deg": t.after_orientation_deg,
                             "hemisphere_flips_left_out": t.hemisphere_flips_left_out}
                for t in self.tables}

    def save(self, path: PathLike, command_line: str = "") -> pathlib.Path:
        """Writes the calibration file atomically. Refuses (ValueError) a fit that failed
        (``failure``), and to overwrite the model file, the capture, or an existing file that is not
        a trackcal calibration."""
        p = pathlib.Path(path)
        self._native.save(p, command_line)
        return p

    def to_dict(self) -> dict:
        """The document ``trackcal-fit fit --json`` prints (``output``: the last save() path)."""
        return self._native.to_dict()

    def format(self) -> str:
        """Table 1 rows, the solver summary, outliers and parameters as text."""
        out = [t.format() for t in self.tables]
        chi = f"{self.chi2_per_dof:.3g}" if self.chi2_per_dof is not None else "n/a"
        out.append(f"Fit: {self.solver_status()} in {self.seconds * 1e3:.3g} ms; chi2/dof {chi}")
        if self.outliers:
            out.append(format_outliers(self.outliers, self.num_calib_stations))
        out.append(format_parameters(self.parameters))
        if self.covariance_estimator:
            out.append(f"  (standard deviations from the {self.covariance_estimator} covariance)")
        if self.identifiability_flags:
            out.append(f"Poorly identified ({len(self.identifiability_flags)}):")
            out += [f"  {f['coordinate']}: {f['reason']}" for f in self.identifiability_flags[:10]]
        return "\n".join(out)

    def solver_status(self) -> str:
        """'converged after 12 iterations', 'NOT converged after 100 iterations', or for a lone
        polynomial without a ridge (solved in closed form, paper eq. 9) 'solved by linear least
        squares'."""
        if self.failure:
            return f"FAILED ({self.fit.get('solver_message', '')}) after {self.iterations} iterations"
        if self.to_dict()["fit"].get("linear_least_squares"):
            return "solved by linear least squares"
        return f"{'converged' if self.converged else 'NOT converged'} after {self.iterations} iterations"

    def __repr__(self) -> str:
        t = self.held_out()
        return (f"FitReport(terms={self.model['terms']}, {t.set_name}: {t.after_position_mm['mean']:.3f} mm / {t.after_orientation_deg['mean']:.3f} deg)")


def format_outliers(outliers: List[dict], num_stations: int, limit: int = 20) -> str:
    """'Outlier stations (12 of 480): 3 17 ...' listing the first ``limit`` ids (all of them are in
    to_dict()). When most stations are outliers the model, not the stations, is what fails."""
    n = len(outliers)
    ids = " ".join(str(o["station"]) for o in outliers[:limit])
    line = f"Outlier stations ({n} of {num_stations}): {ids}" + (f" ... ({n - limit} more)" if n > limit else "")
    if num_stations and n > 0.5 * num_stations:
        line += ("\n  (most stations are outliers: the model leaves far more than the noise; "
                 "see trackcal diagnose)")
    return line


def format_parameters(parameters: List[Parameter], max_values: int = 12) -> str:
    lines = ["Parameters (value +- standard deviation):"]
    for p in parameters:
        lines.append(f"  {p.term}.{p.block} [{p.unit}]{' (fixed)' if p.fixed else ''}: {len(p.values)} values")
        for name, v, s in list(zip(p.names, p.values, p.stddev))[:max_values]:
            lines.append(f"    {name:<22}{v:14.6g}" + (f" +- {s:.3g}" if np.isfinite(s) else ""))
        # A manifold block's uncertainty is that of its tangent coordinates (trackcal-fit prints
        # them too): without these lines a sensor offset's rotation or a plane's normal showed no
        # standard deviation at all.
        for name, s in zip(p.tangent_names, p.tangent_stddev):
            if np.isfinite(s):
                lines.append(f"    {name:<22}{'std':>14} {s:.3g} {p.tangent_unit}")
        if len(p.values) > max_values:
            lines.append("    ... (all values in to_dict() and the calibration file)")
    return "\n".join(lines)


def _data_arg(data):
    if isinstance(data, (str, bytes, os.PathLike)):  # bytes: refused by name in C++, as everywhere
        return data
    if isinstance(data, PoseCapture) or hasattr(data, "reported_positions"):
        return data
    # A ValueError said nothing of the type the argument had.
    raise TypeError("data must be a capture folder or a poses.csv path (str or os.PathLike) or a "
                    f"trackcal.captures.PoseCapture, got {type(data).__name__}")


def _model_arg(model):
    """``model`` of fit/diagnose_candidates: a path or the YAML text (bytes: refused by name in C++)."""
    if isinstance(model, (str, bytes, os.PathLike)):
        return model
    raise TypeError("model must be a model file's path (str or os.PathLike) or its YAML text "
                    f"(docs/model-file.md), got {type(model).__name__}")


def _int_arg(value, name: str) -> int:
    """An integer argument (a whole float, a numpy integer too) as the engine takes it. Another type
    was pybind11's "incompatible function arguments" listing the C++ signature, naming no argument:
    a TypeError naming it; a fraction a ValueError."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real):
        raise TypeError(f"{name} must be a whole number, got {type(value).__name__} {value!r:.40}")
    if not float(value).is_integer():
        raise ValueError(f"{name} {value!r}: must be a whole number")
    return int(value)


def _float_arg(value, name: str, optional: bool = False):
    """A real-number argument (None too when ``optional``), as ``_int_arg``."""
    if optional and value is None:
        return None
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real):
        raise TypeError(f"{name} must be a number{' or None' if optional else ''}, got "
                        f"{type(value).__name__} {value!r:.40}")
    return float(value)


def _sensor_arg(sensor) -> int:
    """``sensor`` of fit/diagnose_candidates as the engine takes it (0: none given)."""
    if sensor is None:
        return 0
    # A string ("1", from argv) failed inside the comparison: "'<' not supported between instances
    # of 'str' and 'int'", naming no argument.
    if not isinstance(sensor, numbers.Real):
        raise TypeError(f"sensor must be a receiver number (1, 2, ...) or None, got {sensor!r}")
    if isinstance(sensor, bool) or not float(sensor).is_integer() or sensor < 1:
        raise ValueError(f"sensor must be a receiver number (1, 2, ...), got {sensor!r}")
    return int(sensor)


def _progress_arg(progress):
    """``progress`` of fit/diagnose_candidates: None or a callable. Anything else was accepted and
    failed only when first called, if ever (a fit solved in closed form returned as if it had
    been a callback)."""
    if progress is not None and not callable(progress):
        raise TypeError(f"progress must be a callable or None, got {progress!r}")
    return progress


def fit(data, model, *, folds: int = 0, progress: Optional[Progress] = None,
        sensor: Optional[int] = None) -> FitReport:
    """Fits a model file (docs/model-file.md) to the ``calib`` stations of a capture.

    ``data``: capture folder (poses.csv, or tracker/reference streams paired with the model's
    time offset), poses.csv path, or a :class:`trackcal.captures.PoseCapture`. ``model``: model
    file path or its YAML text. ``folds`` >= 2 adds a k-fold cross-validation table (station i in
    fold i mod k; stream samples by blocks of time, "cross-validation (k-fold, blocks of time)", as
    ``trackcal-fit``); the validation set, when present, is always evaluated.
    ``progress(stage, done, total)`` is called after each solver iteration (stage "fit") and
    cross-validation fold (stage "cross-validation"); an exception it raises stops the run.
    ``sensor``: the receiver (the capture's ``sensor`` column, from 1) whose stations are fitted;
    None: the data must hold one sensor (a calibration is one receiver's: stations of several are
    refused, naming them, as ``trackcal-fit fit --sensor N``).
    """
    data, model = _data_arg(data), _model_arg(model)
    folds = _int_arg(folds, "folds")
    info = _core.parse_model(model)
    native = _core.fit(data, model, folds=folds, progress=_progress_arg(progress),
                       sensor=_sensor_arg(sensor))
    return FitReport(native, info)


class Registration:
    """The result of :func:`register`: the registration and the extracted reference poses."""

    def __init__(self, native):
        self._native = native
        self.poses: PoseCapture = _capture_from_dict(native.poses)
        self.left_out: List[int] = list(native.left_out)
        self.converged: bool = native.converged
        self.identifiable: bool = native.identifiable
        self.chi_square: float = native.chi_square
        self.nu: float = native.nu
        self.optical_from_transmitter: dict = native.optical_from_transmitter
        self.optical_from_transmitter_stddev: np.ndarray = native.optical_from_transmitter_stddev
        self.markers: List[dict] = native.markers
        self.identifiability_flags: List[dict] = native.identifiability_flags
        # Stations left out: markers misfit the marker body, or tracker reading far off (docs/registration.md).
        self.rejected_stations: List[dict] = native.to_dict()["registration"]["rejected_stations"]
        # "" or what trackcal-fit register warns: how many poses come from markers in view so
        # symmetric that two labels swapped fit as well (any three of the paper's six markers), a
        # pose up to 180 deg off that no check catches (docs/registration.md, Pose extraction).
        self.symmetry_warning: str = native.symmetry_warning

    def summary(self) -> str:
        return self._native.summary()

    def __repr__(self) -> str:
        # The default named only the address ("<trackcal.fitting.Registration object at 0x7f...>").
        state = ", ".join(("converged" if self.converged else "NOT converged",
                           "identifiable" if self.identifiable else "NOT identifiable"))
        return (f"Registration({len(self.poses)} poses, {len(self.left_out)} left out, "
                f"{len(self.rejected_stations)} rejected, chi-square {self.chi_square:.1f} for "
                f"{self.nu:.0f} degrees of freedom, {state})")

    def save(self, path: PathLike) -> pathlib.Path:
        """Writes poses.csv atomically; refuses an existing file or an input."""
        p = pathlib.Path(path)
        self._native.save(p)
        return p

    def to_dict(self) -> dict:
        """The document ``trackcal-fit register --json`` prints."""
        return self._native.to_dict()

    def __getstate__(self):  # as FitReport's: the native run does not pickle
        return {**self.__dict__, "_native": _Detached(self._native, "registration")}


def _input_file(path, file_name: str):
    """``path``, or ``path/file_name`` when it is a folder, as ``trackcal.captures.load_*`` read a
    capture folder: given a folder, the C++ readers failed with "basic_filebuf::underflow error
    reading the file: Is a directory", a ValueError that names no file."""
    # bytes is passed on to be refused by name (TypeError), as every path argument refuses it.
    if path is None or not isinstance(path, (str, os.PathLike)) or isinstance(os.fspath(path), bytes):
        return path
    if not os.path.isdir(path):
        return path
    return pathlib.Path(path) / file_name


def register(markers: PathLike, tracker: PathLike, *, sensor: int = 1, set: str = "calib",
             optical_noise_m: float = 1.5e-4, tracker_position_noise_m: float = 8e-4,
             tracker_orientation_noise_deg: float = 0.15, min_markers_per_station: int = 3,
             poses: Optional[PathLike] = None, reject_bad_stations: bool = True) -> Registration:
    """Optical-to-transmitter registration (paper section 3) from markers.csv and tracker.csv, and
    the reference pose of every station from its markers, as ``trackcal-fit register``.

    A folder stands for its markers.csv, tracker.csv or poses.csv. Without ``poses`` every station
    registers and gets set ``set``. With ``poses`` (a poses.csv
    whose ``set`` column labels every station of markers.csv), only its ``reg`` stations register
    (the paper's ~20 stations near the transmitter, where the distortion is small) and every station
    keeps its set and time, as ``trackcal-fit register --poses``: registering with distorted
    stations biases the registration by their distortion.

    A registration that is not identifiable (``identifiable`` False: the stations leave directions
    of the transform undetermined, ``identifiability_flags`` names them) warns: its poses inherit
    those directions, and ``trackcal-fit register`` refuses to write them.

    A station whose markers no rigid placement of the marker body explains (a swapped or
    misidentified label), or whose tracker reading is far off the others' (a hemisphere flip, a
    reading metres off near metal), is left out of the registration, at most 20 % of them, with a
    warning naming it and why (``rejected_stations``, ``reason``); ``reject_bad_stations=False`` keeps every station, as
    ``--keep-all-stations``. Stations that give no reference pose (``left_out``) warn with how many
    per reason (too few markers, degenerate, bad fit) and an example, as ``trackcal-fit register``
    says on stderr."""
    markers, tracker = _input_file(markers, "markers.csv"), _input_file(tracker, "tracker.csv")
    poses = _input_file(poses, "poses.csv")
    native = _core.register(markers, tracker, sensor=sensor, set=set, optical_noise_m=optical_noise_m,
                            tracker_position_noise_m=tracker_position_noise_m,
                            tracker_orientation_noise_deg=tracker_orientation_noise_deg,
                            min_markers_per_station=min_markers_per_station,
                            poses=poses, reject_bad_stations=reject_bad_stations)
    # A poses.csv label that is not UTF-8 fails as it becomes a Python str: name its file and line.
    result = not_utf8_inputs(Registration, native, inputs=(poses, markers, tracker))
    for left_out in result.rejected_stations:
        warnings.warn(f"{markers}: station {left_out['station']} left out of the registration: "
                      f"{left_out['message']}", UserWarning, stacklevel=2)
    if result.left_out:
        # As trackcal-fit register says on stderr (which refuses to write when no station has a
        # pose: a marker body on one line makes every station degenerate).
        total = len(result.left_out) + len(result.poses.station)
        warnings.warn(f"{markers}: {len(result.left_out)} of {total} stations give no reference pose: "
                      f"{native.no_pose_summary}", UserWarning, stacklevel=2)
    if not result.identifiable:
        flagged = ", ".join(f["coordinate"] for f in result.identifiability_flags) or "none named"
        warnings.warn(f"{markers}: the registration is not identifiable (poorly identified: {flagged}); "
                      "the extracted poses carry its undetermined directions", UserWarning, stacklevel=2)
    return result


def _number_or_nan(value) -> float:
    """A JSON number of a native document, NaN for its null (a NaN in C++)."""
    return float("nan") if value is None else float(value)


class Pairing:
    """The result of :func:`pair`: paired poses, the clock offset used, dropped samples, and what
    the pairing warns (``warning``, "" when nothing)."""

    def __init__(self, native):
        self._native = native
        self.poses: PoseCapture = _capture_from_dict(native.poses)
        self.time_offset_s: float = native.time_offset_s
        self.dropped: int = native.dropped
        self.cost: float = native.cost
        doc = native.to_dict()
        # Of an estimated offset (0 when given).
        self.time_offset_stddev_s: float = float(doc["time_offset_stddev_s"])
        # Of an estimated offset (NaN when given or not determined): the reference clock's rate
        # relative to the tracker's minus 1 (1e-4: 100 ppm fast) with its standard deviation, and
        # the paired residual's RMS over the tracker path's spread (above 0.1: no searched offset
        # pairs the streams). docs/fit.md.
        self.clock_drift: float = _number_or_nan(doc.get("clock_drift"))
        self.clock_drift_stddev: float = _number_or_nan(doc.get("clock_drift_stddev"))
        self.residual_to_path_ratio: float = _number_or_nan(doc.get("residual_to_path_ratio"))
        # Whether that drift was significant and corrected: the reference is then paired at
        # t + time_offset_s + clock_drift_applied * (t - clock_drift_origin_s) (tracker time t;
        # clock_drift_applied 0 when not corrected).
        self.clock_drift_corrected: bool = bool(doc.get("clock_drift_corrected", False))
        self.clock_drift_applied: float = float(doc.get("clock_drift_applied", 0.0))
        self.clock_drift_origin_s: float = float(doc.get("clock_drift_origin_s", 0.0))
        # An estimated offset the streams identify poorly, or the sensor chosen among several:
        # what ``trackcal-fit pair`` prints on stderr.
        self.warning: str = str(doc["warning"])
        # Whether time_offset_s was estimated (else given).
        self.estimated: bool = bool(doc.get("estimated", False))

    def __repr__(self) -> str:
        # The default named only the address ("<trackcal.fitting.Pairing object at 0x7f...>").
        from trackcal._format import fixed
        offset = f"time offset {fixed(1e3 * self.time_offset_s, '{:.3f}')} ms"
        if self.estimated:
            offset += f" (estimated, +- {1e3 * self.time_offset_stddev_s:.3g} ms)"
        if self.clock_drift_applied:
            offset += f", clock drift {1e6 * self.clock_drift_applied:.1f} ppm"
        sensor = f" of sensor {int(self.poses.sensor[0])}" if len(self.poses) else ""
        return (f"Pairing({len(self.poses)} poses{sensor}, {offset}, {self.dropped} dropped"
                + (", warning" if self.warning else "") + ")")

    def save(self, path: PathLike) -> pathlib.Path:
        p = pathlib.Path(path)
        self._native.save(p)
        return p

    def to_dict(self) -> dict:
        """The document ``trackcal-fit pair --json`` prints."""
        return self._native.to_dict()

    def __getstate__(self):  # as FitReport's: the native run does not pickle
        return {**self.__dict__, "_native": _Detached(self._native, "pairing")}


def pair(tracker: PathLike, reference: PathLike, *, time_offset: float = 0.0,
         estimate_time_offset: bool = False, search_range: float = 0.5, max_gap_s: float = 0.1,
         sensor: int = 0, set: str = "calib", decimate: int = 1, clock_drift: float = 0.0,
         clock_drift_origin_s: Optional[float] = None) -> Pairing:
    """Pairs tracker_stream.csv with reference_stream.csv by time (reference pose interpolated at
    t + time_offset), estimating the offset if asked, as ``trackcal-fit pair``. A folder stands for
    its tracker_stream.csv (``tracker``) or reference_stream.csv (``reference``).

    A given offset may come with a clock drift (``clock_drift``, a fit's ``clock_drift`` statistic):
    the reference is then taken at t + time_offset + clock_drift (t - ``clock_drift_origin_s``), the
    origin being the tracker time at which the offset holds (None: the middle of the samples)."""
    tracker = _input_file(tracker, "tracker_stream.csv")
    reference = _input_file(reference, "reference_stream.csv")
    time_offset, search_range = _float_arg(time_offset, "time_offset"), _float_arg(search_range, "search_range")
    max_gap_s, clock_drift = _float_arg(max_gap_s, "max_gap_s"), _float_arg(clock_drift, "clock_drift")
    clock_drift_origin_s = _float_arg(clock_drift_origin_s, "clock_drift_origin_s", optional=True)
    sensor, decimate = _int_arg(sensor, "sensor"), _int_arg(decimate, "decimate")
    native = _core.pair(tracker, reference, time_offset=time_offset,
                        estimate_time_offset=estimate_time_offset, search_range=search_range,
                        max_gap_s=max_gap_s, sensor=sensor, set=set, decimate=decimate,
                        clock_drift=clock_drift, clock_drift_origin=clock_drift_origin_s)
    result = not_utf8_inputs(Pairing, native, inputs=(tracker, reference))
    # As trackcal-fit pair on stderr (it reached only to_dict()["warning"]: a poorly identified
    # offset was returned with nothing said).
    if result.warning:
        warnings.warn(f"{tracker}, {reference}: {result.warning}", UserWarning, stacklevel=2)
    return result
