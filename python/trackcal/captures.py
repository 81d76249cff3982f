"""Capture files (docs/captures.md) as numpy arrays, read and written by the one C++ implementation
(core/capture.h) so Python and the C++ tools agree on every rule and every error message.

Errors raise ``ValueError`` naming the file, line and column, e.g.
``poses.csv:17: column rep_qw: 'abc' is not a number``.
"""

from __future__ import annotations

import dataclasses
import os
import pathlib
from typing import Optional, Union

import numpy as np

from trackcal import _core

PathLike = Union[str, os.PathLike]


@dataclasses.dataclass
class PoseCapture:
    """Paired static stations of a poses.csv: the tracker's report and the reference, per row.

    Quaternions are (N, 4) ordered x, y, z, w; positions (N, 3) in metres, transmitter frame.
    ``extra`` holds every extra numeric column (``extra_columns`` names them), NaN where missing.
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

    def __len__(self) -> int:
        return len(self.station)

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
        """An extra column by name; KeyError listing the available ones otherwise."""
        if name not in self.extra_columns:
            raise KeyError(f"{self.path}: no extra column {name!r} (have: {', '.join(self.extra_columns) or 'none'})")
        return self.extra[:, self.extra_columns.index(name)]


def _resolve(path: PathLike, file_name: str) -> pathlib.Path:
    p = pathlib.Path(path)
    return p / file_name if p.is_dir() else p


def load_poses(path: PathLike) -> PoseCapture:
    """Reads a poses.csv (or the poses.csv of a capture folder)."""
    p = _resolve(path, "poses.csv")
    d = _core.read_poses(p)
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
    )


@dataclasses.dataclass
class TrackerStream:
    """Unaveraged tracker samples (tracker_stream.csv): time [s], sensor, poses."""

    time: np.ndarray
    sensor: np.ndarray
    positions: np.ndarray
    quaternions_xyzw: np.ndarray
    extra_columns: list = dataclasses.field(default_factory=list)
    extra: Optional[np.ndarray] = None

    def __len__(self) -> int:
        return len(self.time)

    def speed(self) -> np.ndarray:
        """Speed [m/s] per sample from central differences along each sensor's samples."""
        out = np.zeros(len(self.time))
        for s in np.unique(self.sensor):
            idx = np.flatnonzero(self.sensor == s)
            if len(idx) < 2:
                continue
            t, p = self.time[idx], self.positions[idx]
            dt = np.gradient(t)
            dp = np.gradient(p, axis=0)
            with np.errstate(divide="ignore", invalid="ignore"):
                v = np.linalg.norm(dp, axis=1) / dt
            out[idx] = np.where(np.isfinite(v), v, 0.0)
        return out


def load_tracker_stream(path: PathLike) -> TrackerStream:
    p = _resolve(path, "tracker_stream.csv")
    d = _core.read_tracker_stream(p)
    return TrackerStream(time=d["time"], sensor=d["sensor"], positions=d["positions"],
                         quaternions_xyzw=d["quaternions_xyzw"], extra_columns=list(d["extra_columns"]),
                         extra=d["extra"])


def save_tracker_stream(path: PathLike, stream: TrackerStream, overwrite: bool = False) -> None:
    """Writes tracker_stream.csv atomically; never replaces an existing file unless asked."""
    _core.write_tracker_stream(pathlib.Path(path), stream.time, stream.sensor, stream.positions,
                               stream.quaternions_xyzw, overwrite)
