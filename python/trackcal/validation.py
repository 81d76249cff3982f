"""Validation and diagnosis of a calibration against a capture: the paper's Table 1 before and after
(computed by the C++ statistics of core/error_statistics.h), per-station residuals, breakdowns by
distance from the transmitter and by region of the volume, the worst stations, stations outside the
calibrated volume, and which covariates explain the residuals (``covariate_analysis``).

Conventions (docs/developing.md): position error ``p_ref - p``, orientation error the vector part of
``q_ref * conj(q)`` in the transmitter frame (paper eq. 1, 3, 6); magnitudes in mm and degrees.
"""

from __future__ import annotations

import dataclasses
import os
import pathlib
import warnings
from typing import Callable, Dict, List, Optional, Sequence

import numpy as np

from trackcal import _core
from trackcal._core import correction_status_names
from trackcal.captures import PoseCapture, _ArrayFields, _same_values
from trackcal.numpy_reference import quaternion_multiply_xyzw


# ---------------------------------------------------------------------------------------------
# Quaternion helpers (x, y, z, w arrays)

def conjugate_xyzw(q: np.ndarray) -> np.ndarray:
    return q * np.array([-1.0, -1.0, -1.0, 1.0])


def orientation_error_vectors(q_reference: np.ndarray, q_estimated: np.ndarray) -> np.ndarray:
    """(N, 3) vector part of q_ref * conj(q) with the sign that makes w >= 0 (eq. 3, 6)."""
    e = quaternion_multiply_xyzw(q_reference, conjugate_xyzw(q_estimated))
    e = e / np.linalg.norm(e, axis=1, keepdims=True)
    return np.where(e[:, 3:4] < 0, -e[:, :3], e[:, :3])


def rotation_matrices(q: np.ndarray) -> np.ndarray:
    """(N, 3, 3) active rotation matrices of (N, 4) x, y, z, w quaternions."""
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    x, y, z, w = q.T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], axis=-1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], axis=-1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], axis=-1),
    ], axis=1)


# ---------------------------------------------------------------------------------------------
# Residuals and Table 1

@dataclasses.dataclass(eq=False)
class Residuals(_ArrayFields):
    """Per-station errors of an estimate against the reference. ``a.equals(b)`` compares them
    (``==`` is a TypeError saying so, as for a PoseCapture)."""

    position: np.ndarray      # (N, 3) p_ref - p [m]
    orientation: np.ndarray   # (N, 3) vector part of q_ref conj(q)
    position_mm: np.ndarray   # (N,) |position| [mm]
    orientation_deg: np.ndarray  # (N,) rotation angle of q_ref conj(q) [deg]


def residuals(positions, quaternions_xyzw, reference_positions, reference_quaternions_xyzw) -> Residuals:
    pos_mm, ori_deg = _core.error_magnitudes(positions, quaternions_xyzw, reference_positions,
                                             reference_quaternions_xyzw)
    return Residuals(position=np.asarray(reference_positions) - np.asarray(positions),
                     orientation=orientation_error_vectors(np.asarray(reference_quaternions_xyzw),
                                                           np.asarray(quaternions_xyzw)),
                     position_mm=pos_mm, orientation_deg=ori_deg)


class _NanEqual:
    """== field by field with NaN equal to NaN (captures._same_values): a summary of an empty set
    or a covariate's undefined p-value is NaN, and the dataclass == said a result differed from
    its own copy."""

    def __eq__(self, other):
        if type(other) is not type(self):
            return NotImplemented
        return _same_values(self, other)

    __hash__ = None


@dataclasses.dataclass(eq=False)
class Table1(_NanEqual):
    """The paper's Table 1 for one set: summaries (count, mean, std, max, rms, median, p95)."""

    set_name: str
    before_position_mm: dict
    before_orientation_deg: dict
    after_position_mm: Optional[dict] = None
    after_orientation_deg: Optional[dict] = None
    # Hemisphere flips left out of every column (core/error_statistics.h HemisphereFlipsToLeaveOut;
    # the same name as in trackcal-fit's JSON).
    hemisphere_flips_left_out: int = 0

    def format(self) -> str:
        """The paper's layout (core/error_statistics.h FormatTable1); without a correction only the
        original errors."""
        if self.after_position_mm is not None and self.after_orientation_deg is not None:
            return _core.format_table1(self.set_name, self.before_position_mm, self.before_orientation_deg,
                                       self.after_position_mm, self.after_orientation_deg,
                                       flips_left_out=self.hemisphere_flips_left_out)
        lines = [f"{self.set_name} set ({self.before_position_mm['count']} poses), no correction"]
        if self.hemisphere_flips_left_out:
            lines.append(f"  {self.hemisphere_flips_left_out} more left out: reported in the other "
                         "hemisphere than their reference (hemisphere flips)")
        for title, s in (("Position error (mm)", self.before_position_mm),
                         ("Orientation error (deg)", self.before_orientation_deg)):
            lines.append(f"{title:<22} {'Original':>10}")
            for name, key in (("Mean", "mean"), ("Standard dev.", "std"), ("Maximum", "max")):
                lines.append(f"  {name:<20} {s[key]:10.3f}")
        return "\n".join(lines) + "\n"

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


def hemisphere_flips(reported_positions, reference_positions) -> np.ndarray:
    """(N,) bool: the reports in the other hemisphere than their reference (a Fastrak's -p), when
    they are fewer than half; all False otherwise, since most reports flipped is a wrong hemisphere
    setting or registration that the statistics must show (core/error_statistics.h
    HemisphereFlipsToLeaveOut)."""
    reported_positions = np.asarray(reported_positions, dtype=float)
    out = np.zeros(len(reported_positions), bool)
    out[_core.hemisphere_flips_to_leave_out(reported_positions, reference_positions)] = True
    return out


def table1(set_name: str, before: Residuals, after: Optional[Residuals] = None,
           flipped: Optional[np.ndarray] = None) -> Table1:
    """Table 1 of one set; the stations ``flipped`` marks (hemisphere_flips) are left out of both
    columns and counted."""
    if flipped is not None and np.any(flipped):
        keep = ~np.asarray(flipped, bool)
        before = _sub(before, keep)
        after = _sub(after, keep) if after is not None else None
    t = Table1(set_name, _core.summarize_errors(before.position_mm),
               _core.summarize_errors(before.orientation_deg),
               hemisphere_flips_left_out=int(np.count_nonzero(flipped)) if flipped is not None else 0)
    if after is not None:
        t.after_position_mm = _core.summarize_errors(after.position_mm)
        t.after_orientation_deg = _core.summarize_errors(after.orientation_deg)
    return t


# ---------------------------------------------------------------------------------------------
# Covariates and the residual-vs-covariate analysis

def covariates(capture: PoseCapture, stream_speed: Optional[np.ndarray] = None) -> Dict[str, np.ndarray]:
    """Every covariate the capture offers, per station.

    Position (reported, transmitter frame), distance from the transmitter, the receiver's x and z
    axes in the transmitter frame (its orientation as the transmitter sees it), the direction of the
    transmitter in the receiver frame (the field direction the coils see: separates receiver-side
    effects such as coil gains from transmitter-side ones, paper section 2.1), time, visiting order,
    sensor, the receiver's speed for stations paired from streams (``stream_speed``, default the
    capture's own ``speed``; of them visiting order only when it is not time's order:
    ``left_out_covariates``), and every extra column (a column of labels as its label indices:
    ``covariates_and_labels`` names those that are categories). An extra column named like a derived
    covariate (``x``, ``distance``, ``speed``...) is ``extra_<name>``: both are tested.
    """
    return covariates_and_labels(capture, stream_speed)[0]


def covariates_and_labels(capture: PoseCapture, stream_speed: Optional[np.ndarray] = None):
    """(``covariates``, {covariate name: labels} for the capture's labels columns): what
    ``covariate_analysis`` takes as ``covs`` and ``labels``."""
    p = capture.reported_positions
    r = rotation_matrices(capture.reported_quaternions_xyzw)
    dist = np.linalg.norm(p, axis=1)
    to_tx_in_rx = np.einsum("nji,nj->ni", r, -p / np.maximum(dist, 1e-12)[:, None])
    cov = {
        "x": p[:, 0], "y": p[:, 1], "z": p[:, 2], "distance": dist,
        "rx_x_axis_in_tx.x": r[:, 0, 0], "rx_x_axis_in_tx.y": r[:, 1, 0], "rx_x_axis_in_tx.z": r[:, 2, 0],
        "rx_z_axis_in_tx.x": r[:, 0, 2], "rx_z_axis_in_tx.y": r[:, 1, 2], "rx_z_axis_in_tx.z": r[:, 2, 2],
        "tx_direction_in_rx.x": to_tx_in_rx[:, 0], "tx_direction_in_rx.y": to_tx_in_rx[:, 1],
        "tx_direction_in_rx.z": to_tx_in_rx[:, 2],
        "time": capture.time.astype(float),
        "visiting_order": np.argsort(np.argsort(capture.time, kind="stable"), kind="stable").astype(float),
        "sensor": capture.sensor.astype(float),
    }
    if stream_speed is None:
        stream_speed = getattr(capture, "speed", None)
    if stream_speed is not None:
        cov["speed"] = np.asarray(stream_speed, dtype=float)
    taken = set(cov) | set(capture.extra_columns)
    labels = {}
    for k, name in enumerate(capture.extra_columns):
        key = name
        if name in cov:  # a derived covariate's name: the user's column is extra_<name>
            key = "extra_" + name
            while key in taken:
                key = "extra_" + key
            taken.add(key)
        cov[key] = capture.extra[:, k].astype(float)
        if name in (capture.extra_labels or {}):
            labels[key] = capture.extra_labels[name]
    # After the extra columns are named, so a user's column "visiting_order" stays extra_visiting_order.
    for name in left_out_covariates(capture):
        del cov[name]
    return cov, labels


def left_out_covariates(capture: PoseCapture) -> Dict[str, str]:
    """{covariate: why} for the derived covariates ``covariates_and_labels`` leaves out.

    ``visiting_order`` is the rank of ``time``; when every time is finite and distinct it is a
    strictly monotonic function of time, with the same quantile bins, so the same R^2 (0.153 of the
    orientation error, both, uncorrected, on the 3598 samples of the stream simulated with seed 51;
    0.1947 of the orientation vector on a 620-station capture), and tested twice it counted one
    covariate twice in the Bonferroni family (alpha over covariates x targets: 64 tests there, 60
    without it). With shared times (samples of several sensors at one time, a capture without
    times) the row order splits them, so it stays. The same rule for stations and stream samples.
    """
    t = np.asarray(capture.time, dtype=float)
    if t.size > 1 and np.all(np.isfinite(t)) and np.unique(t).size == t.size:
        return {"visiting_order": "the same order as time (every time distinct: the same bins and R²)"}
    return {}


CATEGORICAL = {"sensor"}


def _is_categorical(name: str, x: np.ndarray, n_bins: int, labels: Dict[str, list]) -> bool:
    """Whether a covariate's values are categories (a sensor, an operator, few distinct values)
    rather than a quantity to bin by quantiles."""
    return name in CATEGORICAL or name in labels or np.unique(x).size <= n_bins


def _bin_ids(x: np.ndarray, n_bins: int, categorical: bool) -> np.ndarray:
    """Bin index of every value: categories, or quantile bins of x. The bins use x alone (never the
    residual), so computing them on all stations leaks nothing into the cross-validation."""
    if categorical:
        return np.unique(x, return_inverse=True)[1].ravel()
    edges = np.unique(np.quantile(x, np.linspace(0, 1, n_bins + 1))[1:-1])
    return np.searchsorted(edges, x, side="right")


@dataclasses.dataclass(eq=False)
class CovariateEffect(_NanEqual):
    covariate: str
    target: str           # which residual: position_mm, position_vector, orientation_deg, orientation_vector
    r2: float             # cross-validated share of the residual variance the covariate explains
    p_value: float        # permutation p-value of r2
    significant: bool     # p below the Bonferroni-corrected level and r2 above min_r2
    count: int
    # Significant, but the dependence goes once the other family is accounted for: "position" for
    # time or visiting order that the stations' positions explain (a protocol that visits the
    # volume in order makes a spatial effect look like a drift), "time" for a position covariate
    # that time explains (a drift looks like a spatial effect). None: not confounded, or not tested.
    confounded_with: Optional[str] = None
    # For a covariate of labels (``labels`` of covariate_analysis): per label, its stations and how far
    # their mean error sits from the mean over all labels (``_levels``), largest first.
    levels: Optional[List[dict]] = None


def serial_samples(capture: PoseCapture) -> bool:
    """Whether the stations were paired from streams (they carry the receiver's speed): their
    samples are serially correlated and ``covariate_analysis`` tests them along time."""
    return getattr(capture, "speed", None) is not None


def points_word(capture) -> str:
    """The noun for a capture's rows in text: "samples" when they were paired from streams
    (``serial_samples``: thousands of them along a path, milliseconds apart), else "stations".
    ``capture`` None (a validation-like object without one) is a capture of stations."""
    return "samples" if capture is not None and serial_samples(capture) else "stations"


def worst_word(worst_separation_s: Optional[float]) -> str:
    """What one row of a worst list is: a "moment" of a stream (its worst samples at least
    ``worst_separation_s`` apart), else a station (None)."""
    return "moments" if worst_separation_s is not None else "stations"


def id_runs(ids: Sequence[int]) -> List[tuple]:
    """[(first, last)] index ranges into ``ids`` of its runs of consecutive ids (each one more
    than the one before it), in the given order."""
    ids = np.asarray(ids, dtype=np.int64)
    if len(ids) == 0:
        return []
    breaks = np.flatnonzero(np.diff(ids) != 1) + 1
    starts = np.r_[0, breaks]
    ends = np.r_[breaks - 1, len(ids) - 1]
    return list(zip(starts.tolist(), ends.tolist()))


def id_ranges_text(ids: Sequence[int], limit: int) -> str:
    """The ids as "12 15-19 40", consecutive ids as one range, at most ``limit`` items and then
    "... (k more in m ranges)" ("... (k more)" when none of them is a range)."""
    runs = id_runs(ids)
    items = [str(ids[a]) if a == b else f"{ids[a]}-{ids[b]}" for a, b in runs[:limit]]
    rest = runs[limit:]
    if rest:
        n = sum(b - a + 1 for a, b in rest)
        items.append(f"... ({n} more)" if n == len(rest) else f"... ({n} more in {len(rest)} ranges)")
    return " ".join(items)


COVARIATE_METHOD = "cross-validated R², permutation test"
COVARIATE_METHOD_SERIAL = ("stream samples: folds are stretches of time, the null shifts the covariate "
                           "along time")


def covariate_analysis(residuals_: Residuals, covs: Dict[str, np.ndarray], *, n_bins: int = 8,
                       n_folds: int = 5, n_permutations: int = 199, alpha: float = 0.01,
                       min_r2: float = 0.02, seed: int = 0,
                       progress: Optional[Callable[[int, int], None]] = None,
                       serial_time: Optional[np.ndarray] = None,
                       groups: Optional[np.ndarray] = None,
                       labels: Optional[Dict[str, list]] = None) -> List[CovariateEffect]:
    """How much of the residuals each covariate explains, with a permutation test.

    For every covariate and every target (position error magnitude and vector, orientation error
    magnitude and angle vector), the cross-validated R^2 of the binned-means predictor is compared
    with the same statistic after shuffling the covariate (the null of no dependence). A dependence
    is reported as significant when its permutation p-value is below ``alpha`` divided by the number
    of tests (Bonferroni) and it explains at least ``min_r2`` of the variance, so noise is not
    reported as structure. Results are sorted by r2, largest first.

    ``serial_time``: the samples' times when they are serially correlated (stations paired from
    streams: neighbours in time share their misfit). Random folds and shuffles would then make any
    slowly varying covariate (time, visiting order, speed) look predictive: a test sample's
    neighbours sit in the training folds, while shuffling breaks the serial structure that the null
    must keep. So the folds are ``n_folds`` contiguous stretches of time, and the null shifts the
    covariate circularly along time against the residuals (by 10-90 % of the samples), which keeps
    both series' serial structure and breaks only their alignment.

    ``groups``: a label per station whose level differences are not structure to explain, such as
    the set of each station when the residuals are after a fit to the calibration set (in-sample
    there, held-out on the validation set, which the paper protocol visits last: time and visiting
    order would "explain" that difference). Each target is centred within its group, and the null
    shuffles the covariate within groups, so only dependence inside the groups counts. Not used
    with ``serial_time``.

    ``labels``: {covariate: labels} for covariates whose values index labels (the capture's text
    columns, ``PoseCapture.extra_labels``): tested as categories, each effect listing its labels'
    mean errors (``levels``).
    """
    labels = dict(labels or {})
    n_permutations = _whole_number(n_permutations, "n_permutations")
    if n_permutations < 0:  # p = (1 + count) / (n_permutations + 1) would be negative: all significant
        raise ValueError(f"n_permutations {n_permutations}: must be 0 or more")
    # One fold or one bin made every R^2 NaN or 0: nothing significant, whatever the data.
    n_folds, n_bins = _whole_number(n_folds, "n_folds"), _whole_number(n_bins, "n_bins")
    if n_folds < 2:
        raise ValueError(f"n_folds {n_folds}: must be 2 or more")
    if n_bins < 2:
        raise ValueError(f"n_bins {n_bins}: must be 2 or more")
    if not 0.0 < alpha < 1.0:
        raise ValueError(f"alpha {alpha!r}: must be between 0 and 1")
    n = len(residuals_.position_mm)
    # One value per station, numbers: a covariate of another length failed as a bare IndexError
    # deep in the test, without its name.
    checked = {}
    for name, x in covs.items():
        try:
            checked[name] = np.asarray(x, dtype=float)
        except (TypeError, ValueError):
            raise ValueError(f"covariate {name!r}: not numbers (a column of labels goes in as label "
                             "indices, its labels in `labels`)") from None
        if checked[name].shape != (n,):
            raise ValueError(f"covariate {name!r}: {checked[name].shape} values, expected one per "
                             f"station ({n})")
    covs = checked
    for what, a in (("serial_time", serial_time), ("groups", groups)):
        if a is not None and np.shape(a) != (n,):
            raise ValueError(f"{what}: {np.shape(a)} values, expected one per station ({n})")
    targets = {
        "position_mm": residuals_.position_mm[:, None],
        "position_vector": residuals_.position * 1e3,
        "orientation_deg": residuals_.orientation_deg[:, None],
        "orientation_vector": residuals_.orientation * (2.0 * 180.0 / np.pi),
    }
    rng = np.random.default_rng(seed)
    # One random fold per station for every covariate: the covariates' R^2 are compared with each
    # other (the verdict names the largest), so they must not differ by their folds' luck.
    station_folds = rng.permutation(np.arange(n) % n_folds)
    usable = {}
    for name, x in covs.items():
        x = np.asarray(x, dtype=float)
        ok = np.isfinite(x)
        if ok.sum() >= max(20, 2 * n_folds) and np.unique(x[ok]).size >= 2:
            usable[name] = x
    n_tests = max(1, len(usable) * len(targets))
    # The smallest reachable p is 1 / (n_permutations + 1): with the default 199 permutations and
    # 4 targets x ~20 covariates, Bonferroni at alpha = 0.01 needs p <= 1.25e-4, which a finite
    # permutation count cannot reach; so a covariate whose observed r2 beats every permutation is
    # also checked against a normal approximation of the permutation distribution (z-score), when
    # there are at least 99 permutations to estimate its spread, and one that passes is confirmed
    # by more shuffles (_confirm; stream samples keep the approximation: too few circular shifts).
    level = alpha / n_tests
    from statistics import NormalDist
    z_needed = NormalDist().inv_cdf(1.0 - level)
    effects = []
    total = len(usable) * len(targets)
    done = 0
    for name, x in usable.items():
        ok = np.isfinite(x)
        xs = x[ok]
        categorical = _is_categorical(name, xs, n_bins, labels)
        m = int(ok.sum())
        ids = _bin_ids(xs, n_bins, categorical)
        gs = None
        if serial_time is None and groups is not None:
            gs = np.unique(np.asarray(groups)[ok], return_inverse=True)[1].ravel()
            if gs.max() == 0:
                gs = None
        if serial_time is None:
            folds = station_folds[ok]
            if gs is None:
                perms = [rng.permutation(ids) for _ in range(n_permutations)]
            else:
                members = [np.flatnonzero(gs == g) for g in range(int(gs.max()) + 1)]
                perms = []
                for _ in range(n_permutations):
                    pid = ids.copy()
                    for idx in members:
                        pid[idx] = ids[rng.permutation(idx)]
                    perms.append(pid)
        else:
            by_time = np.argsort(np.asarray(serial_time, dtype=float)[ok], kind="stable")
            folds = np.empty(m, dtype=int)
            folds[by_time] = np.arange(m) * n_folds // m
            shifts = rng.integers(max(1, m // 10), max(2, m - m // 10), size=n_permutations)
            perms = []
            for k in shifts:
                shifted = np.empty_like(ids)
                shifted[by_time] = np.roll(ids[by_time], int(k))
                perms.append(shifted)
        ys_all = [_centred_within(y[ok], gs) if gs is not None else y[ok] for y in targets.values()]
        # Every target at once: they share the bins, folds and shuffles (_permutation_tests).
        tests = _permutation_tests(ids, ys_all, folds, n_folds, perms, n_permutations, level, z_needed)
        for (tname, y), ys, (obs, p, z_ok) in zip(targets.items(), ys_all, tests):
            if z_ok and p > level and serial_time is None and obs >= min_r2:
                # The normal approximation is a screen, not the test: the null of a binned-means
                # R^2 has heavier tails than a normal (pure noise beyond mean + 3.6 sd: 9e-4 of
                # permutations for 8 bins, 2.7e-3 for 3 categories, against 1.6e-4), so a finding it
                # passes is confirmed by as many more shuffles as the level needs.
                p = _confirm(ids, ys, folds, n_folds, obs, n_permutations, level, rng, gs)
                z_ok = False
            sig = bool(obs >= min_r2 and (p <= level or z_ok))
            effects.append(CovariateEffect(name, tname, float(obs), float(p), sig, int(ok.sum()),
                                           levels=_levels(y[ok], tname, xs, labels[name],
                                                          "samples" if serial_time is not None else "stations")
                                           if name in labels else None))
            done += 1
            if progress:
                progress(done, total)
    if serial_time is None:
        _mark_confounded(effects, targets, usable, groups, n_bins, n_folds, n_permutations, alpha,
                         station_folds, rng, labels)
    effects.sort(key=lambda e: -e.r2)
    return effects


def permutations_can_reach(n_permutations: int, n_tests: int, alpha: float = 0.01) -> bool:
    """Whether covariate_analysis with this many permutations can call any of ``n_tests`` tests
    significant: the smallest permutation p is 1 / (n_permutations + 1), and the normal
    approximation that reaches below it needs 99 permutations or more. Below that, every test
    comes out not significant whatever the residuals, which is not evidence of their absence."""
    return n_permutations >= 99 or 1.0 / (n_permutations + 1.0) <= alpha / max(1, n_tests)


def _levels(y: np.ndarray, target: str, codes: np.ndarray, names: list, points: str = "stations") -> List[dict]:
    """Per label of a covariate: its stations and how far their mean of the target y (N, d) sits
    from the mean over every label (``offset``: the vector in the transmitter frame for a vector
    target, mm or the rotation vector in degrees; the signed difference for a magnitude), largest
    ``size`` first. ``points`` ("stations", or "samples" of a stream) names what ``count`` counts,
    for the text."""
    position = target.startswith("position")
    overall = y.mean(axis=0)
    rows = []
    for code in np.unique(codes):
        idx = codes == code
        offset = y[idx].mean(axis=0) - overall
        rows.append({"label": str(names[int(code)]), "count": int(idx.sum()),
                     "offset": [float(v) for v in offset] if len(offset) > 1 else float(offset[0]),
                     "size": float(np.linalg.norm(offset)), "unit": "mm" if position else "deg",
                     "points": points})
    rows.sort(key=lambda r: -r["size"])
    return rows


TIME_COVARIATES = ("time", "visiting_order")
POSITION_COVARIATES = ("x", "y", "z", "distance")


def _centred_within(y: np.ndarray, gs: np.ndarray) -> np.ndarray:
    """y (N, d) less its mean within each group gs (labels 0..G-1)."""
    means = np.stack([np.bincount(gs, weights=y[:, d]) / np.bincount(gs) for d in range(y.shape[1])], axis=1)
    return y - means[gs]


# The covariate tests' R^2 by the code they had before _cv_r2_targets (_cv_r2_rows_reference, target
# by target): for the tests and bench/bench_covariates.py, which check that both give the same bits.
_SLOW_REFERENCE = False


def _cv_r2_rows(rows: np.ndarray, y: np.ndarray, folds: np.ndarray, n_folds: int) -> np.ndarray:
    """Cross-validated R^2 of predicting y (N, d) by the mean of y in the station's bin, for every
    row of bin ids (P, N) at once: bin means from the training folds (the training mean for a bin
    without training stations); SST around the training mean, so a covariate that explains
    nothing scores about 0 or below (``_cv_r2_targets`` for one target)."""
    return _cv_r2_targets(rows, [y], folds, n_folds)[0]


def _cv_r2_targets(rows: np.ndarray, ys: Sequence[np.ndarray], folds: np.ndarray, n_folds: int) -> List[np.ndarray]:
    """``[_cv_r2_rows_reference(rows, y, folds, n_folds) for y in ys]``, bit for bit, at a fraction of
    its cost: what depends on the rows alone (the folds' bin ids, training counts, test lookups) is
    done once for every target; the bin sums are per row (np.bincount, whose plain loop adds a bin's
    values in station order, as it did over the rows' concatenation) without tiling y per row; and
    each squared error is summed over the test stations in their order, as the reference's
    column-ordered (P, N_test) sum did (np.sum along axis 1 of such an array adds the columns one by
    one; a row-ordered array would be summed pairwise, to other last bits)."""
    rows = np.asarray(rows)
    n_rows = rows.shape[0]
    nb = int(rows.max()) + 1
    offsets = np.arange(n_rows) * nb
    cols = [np.ascontiguousarray(y[:, d]) for y in ys for d in range(y.shape[1])]
    sse = [np.zeros(n_rows) for _ in ys]
    sst = [0.0 for _ in ys]
    by_station = rows.T  # (N, P): a fold's test stations taken from it are a row-ordered (N_test, P)
    for f in range(n_folds):
        test = folds == f
        train = ~test
        rows_train = rows.compress(train, axis=1)  # row-ordered (P, N_train): each row contiguous
        counts = np.empty((n_rows, nb))
        sums = np.empty((len(cols), n_rows, nb))
        train_cols = [c[train] for c in cols]
        for p in range(n_rows):
            r = rows_train[p]
            counts[p] = np.bincount(r, minlength=nb)
            for c, w in enumerate(train_cols):
                sums[c, p] = np.bincount(r, weights=w, minlength=nb)
        filled = counts > 0
        safe = np.maximum(counts, 1)
        # (N_test, P) row-ordered: the memory layout of the reference's column-ordered (P, N_test).
        at_test = by_station[test] + offsets
        squared = np.empty(at_test.shape)
        c = 0
        for t, y in enumerate(ys):
            mean_all = y[train].mean(axis=0)
            for d in range(y.shape[1]):
                table = np.where(filled, sums[c] / safe, mean_all[d]).ravel()
                np.take(table, at_test, out=squared)
                np.subtract(y[test, d][:, None], squared, out=squared)
                np.square(squared, out=squared)
                sse[t] += np.sum(squared, axis=0)
                c += 1
            sst[t] += float(np.sum((y[test] - mean_all) ** 2))
    return [1.0 - e / s if s > 0 else np.zeros(n_rows) for e, s in zip(sse, sst)]


def _cv_r2_rows_reference(rows: np.ndarray, y: np.ndarray, folds: np.ndarray, n_folds: int) -> np.ndarray:
    """_cv_r2_rows as it was before _cv_r2_targets, kept to check that one against it
    (_SLOW_REFERENCE)."""
    n_rows = rows.shape[0]
    nb = int(rows.max()) + 1
    offsets = (np.arange(n_rows) * nb)[:, None]
    sse = np.zeros(n_rows)
    sst = 0.0
    for f in range(n_folds):
        test = folds == f
        train = ~test
        it = (rows[:, train] + offsets).ravel()
        counts = np.bincount(it, minlength=n_rows * nb).astype(float)
        mean_all = y[train].mean(axis=0)
        at_test = rows[:, test] + offsets
        for d in range(y.shape[1]):
            sums = np.bincount(it, weights=np.tile(y[train, d], n_rows), minlength=n_rows * nb)
            table = np.where(counts > 0, sums / np.maximum(counts, 1), mean_all[d])
            sse += np.sum((y[test, d][None, :] - table[at_test]) ** 2, axis=1)
        sst += float(np.sum((y[test] - mean_all) ** 2))
    return 1.0 - sse / sst if sst > 0 else np.zeros(n_rows)


def _confirm(ids, ys, folds, n_folds, obs, n_permutations, level, rng, gs=None, batch: int = 1024) -> float:
    """Permutation p-value of ``obs`` over the first ``n_permutations`` shuffles (all below it) and
    more, shuffled as the first (within the groups ``gs``), until p can reach ``level``; stops at
    the first shuffle at or above ``obs``."""
    total = int(np.ceil(1.0 / level)) - 1
    done, count = n_permutations, 0
    members = None if gs is None else [np.flatnonzero(gs == g) for g in range(int(gs.max()) + 1)]
    while done < total and count == 0:
        k = min(batch, total - done)
        rows = np.tile(ids, (k, 1))
        if members is None:
            rows = rng.permuted(rows, axis=1)
        else:
            for idx in members:
                rows[:, idx] = rng.permuted(rows[:, idx], axis=1)
        cv = _cv_r2_rows_reference if _SLOW_REFERENCE else _cv_r2_rows
        count += int(np.sum(cv(rows, ys, folds, n_folds) >= obs))
        done += k
    return (1.0 + count) / (done + 1.0)


def _permutation_tests(ids, ys_all, folds, n_folds, perms, n_permutations, level, z_needed) -> list:
    """``[_permutation_test(ids, ys, ...) for ys in ys_all]``, bit for bit: the targets share the bin
    ids, folds and shuffles, so their R^2 are computed together (_cv_r2_targets)."""
    if _SLOW_REFERENCE:
        return [_permutation_test(ids, ys, folds, n_folds, perms, n_permutations, level, z_needed) for ys in ys_all]
    # The observed R^2 on its own row, as _permutation_test computes it: one row's squared errors
    # are summed pairwise, a batch's column by column (_cv_r2_targets), which differs in the last bits.
    obs = [float(r[0]) for r in _cv_r2_targets(ids[None, :], ys_all, folds, n_folds)]
    nulls = (_cv_r2_targets(np.asarray(perms), ys_all, folds, n_folds) if len(perms)
             else [np.empty(0) for _ in ys_all])
    return [_null_verdict(o, null, n_permutations, z_needed) for o, null in zip(obs, nulls)]


def _permutation_test(ids, ys, folds, n_folds, perms, n_permutations, level, z_needed):
    """(cv R^2, permutation p, whether the normal approximation of the null reaches the level)."""
    # All at once (_cv_r2_rows), the observed R^2 too. (Not summed alike, though: a single row's
    # squared errors are summed pairwise, a batch's column by column; kept, for identical results.)
    cv = _cv_r2_rows_reference if _SLOW_REFERENCE else _cv_r2_rows
    obs = float(cv(ids[None, :], ys, folds, n_folds)[0])
    null = cv(np.asarray(perms), ys, folds, n_folds) if len(perms) else np.empty(0)
    return _null_verdict(obs, null, n_permutations, z_needed)


def _null_verdict(obs: float, null: np.ndarray, n_permutations: int, z_needed: float):
    """(obs, permutation p, whether the normal approximation of the null reaches the level)."""
    p = (1.0 + np.sum(null >= obs)) / (n_permutations + 1.0)
    sd = null.std() if len(null) else 0.0
    z = (obs - null.mean()) / sd if sd > 0 else (np.inf if len(null) and obs > null.mean() else 0.0)
    z_ok = n_permutations >= 99 and bool(np.all(null < obs)) and z >= z_needed
    return obs, p, z_ok


def _mark_confounded(effects, targets, usable, groups, n_bins, n_folds, n_permutations, alpha,
                     station_folds, rng, labels) -> None:
    """Time against position, each given the other (stations, not streams).

    The paper's protocol visits the volume in order, so time and visiting order correlate with a
    coordinate (0.97 with z on the snake grid): a purely spatial residual made "visiting_order" the
    verdict's covariate as often as z. For a target where a time covariate T and a position
    covariate P are both significant, T is tested again on the target less its bin means over P
    (the same bins as the marginal tests, the same folds, a fresh permutation null at ``alpha``
    without the Bonferroni factor: a follow-up of a finding already made, where a lack of power
    would wrongly call it explained): when nothing is left, T gets ``confounded_with`` "position".
    When every T survives every P, each P is tested on the target less its bin means over T and
    gets "time" when nothing is left (a drift seen through a protocol that visits the volume in
    order)."""
    by_target: Dict[str, List[CovariateEffect]] = {}
    for e in effects:
        if e.significant:
            by_target.setdefault(e.target, []).append(e)
    from statistics import NormalDist
    z_alpha = NormalDist().inv_cdf(1.0 - alpha)

    def explained_away(tname, e, other) -> bool:
        """Whether e's dependence goes once the target's bin means over `other` are removed."""
        ok = np.isfinite(usable[e.covariate]) & np.isfinite(usable[other.covariate])
        if ok.sum() < max(20, 2 * n_folds):
            return False
        y = targets[tname][ok].astype(float)
        if groups is not None:  # as the marginal test: only dependence within the groups
            gs = np.unique(np.asarray(groups)[ok], return_inverse=True)[1].ravel()
            y = _centred_within(y, gs)

        def bins(name):  # as the marginal test bins it
            x = usable[name][ok]
            return _bin_ids(x, n_bins, _is_categorical(name, x, n_bins, labels))

        ids, o = bins(e.covariate), bins(other.covariate)
        o = np.unique(o, return_inverse=True)[1].ravel()
        counts = np.bincount(o).astype(float)
        left = y - np.stack([np.bincount(o, weights=y[:, d]) / counts for d in range(y.shape[1])], axis=1)[o]
        perms = [rng.permutation(ids) for _ in range(n_permutations)]
        _, p, z_ok = _permutation_test(ids, left, station_folds[ok], n_folds, perms, n_permutations, alpha,
                                       z_alpha)
        return not (p <= alpha or z_ok)

    for tname, es in by_target.items():
        time_es = [e for e in es if e.covariate in TIME_COVARIATES]
        pos_es = [e for e in es if e.covariate in POSITION_COVARIATES]
        pairs = [(te, pe) for te in time_es for pe in pos_es]
        for te, pe in pairs:
            if te.confounded_with is None and explained_away(tname, te, pe):
                te.confounded_with = "position"
        # Time explained away by a place: the place stands (on a grid visited layer by layer a
        # coordinate is a function of time, so the place is always "explained" by time too, and the
        # simpler account is the place). Only when every time covariate survives every place can
        # time take a place's finding from it.
        if any(te.confounded_with is not None for te in time_es):
            continue
        for te, pe in pairs:
            if pe.confounded_with is None and explained_away(tname, pe, te):
                pe.confounded_with = "time"


# ---------------------------------------------------------------------------------------------
# Breakdowns

def _summary_row(label: str, idx: np.ndarray, before: Residuals, after: Optional[Residuals]) -> dict:
    row = {"label": label, "count": int(idx.sum()),
           "before_position_mm": float(before.position_mm[idx].mean()) if idx.any() else float("nan"),
           "before_orientation_deg": float(before.orientation_deg[idx].mean()) if idx.any() else float("nan")}
    if after is not None:
        row["after_position_mm"] = float(after.position_mm[idx].mean()) if idx.any() else float("nan")
        row["after_orientation_deg"] = float(after.orientation_deg[idx].mean()) if idx.any() else float("nan")
    return row


def distance_breakdown(distance: np.ndarray, before: Residuals, after: Optional[Residuals],
                       step_m: float = 0.25) -> List[dict]:
    """Mean errors per distance band of width ``step_m`` from the transmitter (band k holds
    k * step_m <= distance < (k + 1) * step_m; every station is in exactly one band)."""
    rows = []
    if len(distance) == 0:
        return rows
    # Band index per station: bands [lo, lo + step) built by adding step missed a station at
    # exactly the farthest band's upper edge (0.5 m with 0.25 m bands), and float sums can leave
    # gaps between bands.
    band = np.floor(np.asarray(distance, dtype=float) / step_m).astype(np.int64)
    for k in np.unique(band):
        lo = k * step_m
        rows.append(_summary_row(f"{lo:.2f}-{lo + step_m:.2f} m", band == k, before, after))
    return rows


def region_breakdown(positions: np.ndarray, before: Residuals, after: Optional[Residuals],
                     centre: Optional[np.ndarray] = None) -> List[dict]:
    """Mean errors per octant of the volume around ``centre`` (default: median station position)."""
    c = np.median(positions, axis=0) if centre is None else np.asarray(centre)
    rows = []
    for sx in "-+":
        for sy in "-+":
            for sz in "-+":
                idx = np.ones(len(positions), bool)
                for k, s in enumerate((sx, sy, sz)):
                    idx &= (positions[:, k] >= c[k]) if s == "+" else (positions[:, k] < c[k])
                if idx.any():
                    rows.append(_summary_row(f"x{sx} y{sy} z{sz}", idx, before, after))
    return rows


# ---------------------------------------------------------------------------------------------
# The whole validation

@dataclasses.dataclass(repr=False, eq=False)
class Validation(_ArrayFields):
    """A validation run (``validate``). ``a.equals(b)``: the same capture, calibration (its file
    text) and results, arrays element by element; ``==`` is a TypeError saying so."""

    capture: PoseCapture
    calibration: Optional[object]
    corrected_positions: Optional[np.ndarray]
    corrected_quaternions_xyzw: Optional[np.ndarray]
    extrapolated: np.ndarray
    before: Residuals
    after: Optional[Residuals]
    tables: List[Table1]
    by_distance: List[dict]
    by_region: List[dict]
    worst: List[dict]
    covariate_effects: List[CovariateEffect] = dataclasses.field(default_factory=list)
    # Whether the covariate analysis ran (validate(analyse_covariates=True)) and tested at least
    # one covariate (none is on fewer than 20 stations): False means no covariate was tested, not
    # that none follows the residuals.
    covariates_tested: bool = False
    # Why covariates_tested is False although the analysis ran ("" when it is True): too few
    # stations, or too few permutations for any test to reach its significance level.
    covariates_note: str = ""
    # {covariate: why} for derived covariates not tested on this capture (left_out_covariates):
    # visiting_order of stream samples, which repeats time.
    covariates_left_out: Dict[str, str] = dataclasses.field(default_factory=dict)
    # Per station: how the calibration's model inverse arrived at the corrected pose (uint8: 0
    # converged, 1 ambiguous, 2 not_converged; trackcal.correction_status_names); all 0 without a
    # calibration or without a physical term.
    status: Optional[np.ndarray] = None
    # Per station: reported in the other hemisphere than its reference (hemisphere_flips within its
    # set). Left out of every table, the breakdowns, the worst stations, the covariate analysis
    # and the report's figures.
    flipped: Optional[np.ndarray] = None
    # Samples paired from streams: the worst list holds the worst sample of distinct moments, at
    # least this many seconds apart per sensor (None: static stations, the worst ones as they are).
    worst_separation_s: Optional[float] = None

    def __repr__(self) -> str:
        # The dataclass repr printed the capture's and every residual's arrays: 84 kB for the
        # paper's 480 stations.
        tables = "; ".join(
            f"{t.set_name}: {t.after_position_mm['mean']:.3f} mm / {t.after_orientation_deg['mean']:.3f} deg"
            if t.after_position_mm is not None else
            f"{t.set_name}: {t.before_position_mm['mean']:.3f} mm / {t.before_orientation_deg['mean']:.3f} deg uncorrected"
            for t in self.tables)
        return (f"Validation({len(self.extrapolated)} {self.points} of {self.capture.path}, "
                f"calibration={self.calibration!r}, {tables}, "
                f"{int(np.sum(self.extrapolated))} outside the calibrated volume)")

    @property
    def points(self) -> str:
        """The noun for the capture's rows in text (``points_word``): "samples" or "stations"."""
        return points_word(self.capture)

    @property
    def point(self) -> str:
        """One of ``points``: "sample" or "station"."""
        return self.points[:-1]

    @property
    def worst_points(self) -> str:
        """What one row of the worst list is (``worst_word``): "moments" or "stations"."""
        return worst_word(self.worst_separation_s)

    def outside_line(self, limit: int) -> str:
        """"stations outside the calibrated volume: n of N: ids" for text and the report, the ids
        as ranges (``id_ranges_text``, at most ``limit`` items). Of samples paired from streams,
        the stretches of the tracker's time they lie in, with their sample ids: a stream leaves
        the volume for a while, and its thousands of ids in a row said nothing."""
        n_out = int(self.extrapolated.sum())
        head = f"{self.points} outside the calibrated volume: {n_out} of {len(self.extrapolated)}"
        if not n_out:
            return head
        ids = self.outside_stations
        if self.points != "samples":
            return f"{head}: {id_ranges_text(ids, limit)}"
        t = np.asarray(self.capture.time, dtype=float)[self.extrapolated]
        runs = id_runs(ids)
        spans = [f"{t[a]:.2f}-{t[b]:.2f} s (samples {ids[a]}-{ids[b]})" if a != b else
                 f"{t[a]:.2f} s (sample {ids[a]})" for a, b in runs[:limit]]
        total = float(sum(t[b] - t[a] for a, b in runs))
        text = (f"{head}, {len(runs)} stretch{'es' if len(runs) != 1 else ''} of the stream "
                f"({total:.1f} s in all; time: the tracker's [s]): " + ", ".join(spans))
        if len(runs) > limit:
            text += f" ... ({len(runs) - limit} more)"
        return text

    def worst_rows(self) -> List[dict]:
        """The worst list as the text and the report show it: a stream's rows name their id
        "sample" (``points``), not "station" (the key in ``worst`` and the JSON documents)."""
        return [{(self.point if k == "station" else k): x for k, x in r.items()} for r in self.worst]

    @property
    def worst_heading(self) -> str:
        """What the worst list holds, for the report and the text output."""
        if self.worst_separation_s is None:
            return f"Worst {len(self.worst)} stations"
        return (f"Worst {len(self.worst)} moments of the stream (the worst sample of each, at least "
                f"{self.worst_separation_s:g} s apart; time: the tracker's [s])")

    @property
    def flipped_stations(self) -> List[int]:
        """Station ids reported in the other hemisphere than their reference (left out)."""
        if self.flipped is None:
            return []
        return [int(s) for s in self.capture.station[self.flipped]]

    @property
    def status_counts(self) -> dict:
        """{"converged": n, "ambiguous": n, "not_converged": n} over the stations."""
        from trackcal import status_counts
        return status_counts(self.status if self.status is not None else np.zeros(len(self.extrapolated), np.uint8))

    @property
    def final(self) -> Residuals:
        """The residuals left: after the calibration if there is one, else before."""
        return self.after if self.after is not None else self.before

    @property
    def outside_stations(self) -> List[int]:
        """Station ids outside the calibrated volume (the correction extrapolates there)."""
        return [int(s) for s in self.capture.station[self.extrapolated]]

    def station_rows(self) -> List[dict]:
        """The residuals of every station, one dict each: station, set, sensor, time, reported
        position x, y, z [m] and distance, the error before (and after the calibration) as
        magnitudes (position mm, orientation deg) and vectors (position p_ref - p in mm,
        orientation the small-angle rotation vector of q_ref conj(q) in deg, transmitter frame),
        outside (the calibrated volume), flipped (reported in the other hemisphere than its
        reference), status (of a physical term's model inverse), then the capture's extra columns
        (labels as text, None or NaN where missing; named extra_<name> where a name is taken)."""
        c = self.capture
        deg = 2.0 * 180.0 / np.pi
        distance = np.linalg.norm(c.reported_positions, axis=1)
        extras = [(name, c.column(name)) for name in c.extra_columns]
        rows = []
        for i in range(len(c)):
            row = {"station": int(c.station[i]), "set": str(c.set[i]), "sensor": int(c.sensor[i]),
                   "time": float(c.time[i]), "x": float(c.reported_positions[i, 0]),
                   "y": float(c.reported_positions[i, 1]), "z": float(c.reported_positions[i, 2]),
                   "distance": float(distance[i])}
            for name, r in (("before", self.before), ("after", self.after)):
                if r is None:
                    continue
                row[f"{name}_position_mm"] = float(r.position_mm[i])
                row[f"{name}_orientation_deg"] = float(r.orientation_deg[i])
                for k, axis in enumerate("xyz"):
                    row[f"{name}_dp{axis}_mm"] = float(r.position[i, k] * 1e3)
                for k, axis in enumerate("xyz"):
                    row[f"{name}_dr{axis}_deg"] = float(r.orientation[i, k] * deg)
            row["outside"] = bool(self.extrapolated[i])
            row["flipped"] = bool(self.flipped[i]) if self.flipped is not None else False
            row["status"] = correction_status_names[int(self.status[i])] if self.status is not None else "converged"
            if i == 0:
                keys = _extra_keys(row, c.extra_columns)
            for (name, values), key in zip(extras, keys):
                value = values[i]
                row[key] = value if value is None or isinstance(value, str) else float(value)
            rows.append(row)
        return rows

    def write_residuals(self, path, inputs: Sequence = ()) -> "pathlib.Path":
        """Writes ``station_rows()`` as CSV atomically. Refuses an existing file (a capture is never
        overwritten), also one created while the rows are computed, and any of ``inputs``."""
        import csv
        import io
        import pathlib
        from trackcal._files import write_new
        path = pathlib.Path(path)
        if path.exists():
            raise ValueError(f"{path}: exists; residuals are never written over an existing file")
        for p in inputs:
            if p is not None and pathlib.Path(p).resolve() == path.resolve():
                raise ValueError(f"{path}: refusing to overwrite an input")
        rows = self.station_rows()
        buf = io.StringIO()
        w = csv.DictWriter(buf, fieldnames=list(rows[0].keys()) if rows else ["station"], lineterminator="\n")
        w.writeheader()
        for r in rows:
            w.writerow({k: (repr(v) if isinstance(v, float) else v) for k, v in r.items()})
        return write_new(path, buf.getvalue().encode("utf-8"),
                         "exists; residuals are never written over an existing file")

    def summary_text(self) -> str:
        out = [t.format() for t in self.tables]
        return "\n".join(out)


def _extra_keys(row: dict, extra_columns: Sequence[str]) -> List[str]:
    """The key of each extra column in a station row: its name, or extra_<name> (extra_extra_<name>
    ...) when the row or another extra column has that name already, as ``covariates_and_labels``
    names them. extra_<name> alone overwrote a user's own column extra_<name> with <name>'s values."""
    taken = set(row) | set(extra_columns)
    keys = []
    for name in extra_columns:
        key = name
        if name in row:
            key = "extra_" + name
            while key in taken:
                key = "extra_" + key
            taken.add(key)
        keys.append(key)
    return keys


def _sub(r: Residuals, idx) -> Residuals:
    return Residuals(r.position[idx], r.orientation[idx], r.position_mm[idx], r.orientation_deg[idx])


def _check_corrected_poses(data: PoseCapture, positions: np.ndarray, quaternions_xyzw: np.ndarray) -> None:
    """ValueError naming the first station whose corrected pose is not finite or whose quaternion is
    not a unit quaternion (norm 1 within 1e-3, as a capture file's; docs/captures.md). A NaN
    made every mean NaN while the maximum and the worst stations silently left it out, and a zero
    quaternion was normalised to nothing and counted as a perfect 0 degree orientation."""
    bad_p = ~np.all(np.isfinite(positions), axis=1)
    norm = np.linalg.norm(quaternions_xyzw, axis=1)
    with np.errstate(invalid="ignore"):
        bad_q = ~(np.abs(norm - 1.0) <= 1e-3)
    for i in np.flatnonzero(bad_p | bad_q):
        where = f"corrected_poses: station {int(data.station[i])}"
        if bad_p[i]:
            raise ValueError(f"{where}: position {positions[i].tolist()} is not finite")
        raise ValueError(f"{where}: quaternion x, y, z, w {quaternions_xyzw[i].tolist()}: norm {norm[i]:g} is not 1")


def _as_calibration(calibration):
    """``calibration`` as a trackcal.Calibration: None stays None, a path (str or os.PathLike) is
    loaded (trackcal.Calibration.load), a Calibration is used as it is. A path was an
    AttributeError ("'str' object has no attribute 'correct'") from deep in validate()."""
    if calibration is None or callable(getattr(calibration, "correct", None)):
        return calibration
    if isinstance(calibration, (str, os.PathLike)):
        return _core.Calibration.load(os.fspath(calibration))
    raise TypeError(f"calibration: expected a trackcal.Calibration, a calibration file's path or None, "
                    f"got {type(calibration).__name__}")


class OtherReceiverWarning(UserWarning):
    """The capture's stations are another receiver's than the calibration was fitted for
    (``other_receiver_text``): the commands print it as a note, and the report shows it."""


def other_receiver_text(capture: PoseCapture, calibration) -> Optional[str]:
    """What to say when the calibration records the receiver it was fitted for (Calibration.sensor,
    the capture's 1-based sensor column) and the capture's stations are another receiver's: every
    receiver has its own sensor offset and coil gains, so the tables would measure a correction
    meant for another receiver (deliberate in a comparison, a mix-up otherwise). None else."""
    fitted_for = int(getattr(calibration, "sensor", 0) or 0)
    if calibration is None or fitted_for == 0 or len(capture) == 0:
        return None
    others = sorted(int(s) for s in np.unique(capture.sensor) if int(s) != fitted_for)
    if not others:
        return None
    return (f"{capture.path or 'the capture'}: stations of sensor {', '.join(map(str, others))}, but the calibration "
            f"was fitted for sensor {fitted_for} (receiver {fitted_for}): its correction is "
            f"another receiver's there; validate each receiver with its own calibration "
            f"(trackcal validate --sensor N)")


def _warn_other_receiver(capture: PoseCapture, calibration) -> None:
    """Warns (OtherReceiverWarning) with ``other_receiver_text``, if there is something to say."""
    text = other_receiver_text(capture, calibration)
    if text:
        warnings.warn(text, OtherReceiverWarning, stacklevel=3)


def _checked_capture(capture: PoseCapture) -> PoseCapture:
    """The capture with its per-station fields as numpy arrays of the shapes they must have and
    finite poses, else a ValueError naming the field (as trackcal.fit checks an in-memory capture).
    A transposed (3, N) positions array or an (N, 1) station column was an IndexError of a boolean
    mask deep in validate(); a list was kept whole by subset() while the arrays beside it lost the
    registration stations ("estimated: positions must be (N, 3) ...", naming none of the capture's
    fields); an infinite reported position was silently left out as a hemisphere flip and a NaN one
    made every mean NaN."""
    # Anything else (a number, a poses.csv's path) was an AttributeError deep in the checks.
    if not all(hasattr(capture, f) for f in ("station", "set", "reported_positions")):
        raise TypeError("capture must be a trackcal.captures.PoseCapture (captures.load(path) reads "
                        f"one), got {type(capture).__name__}")
    n = np.shape(capture.station)
    if len(n) != 1:
        raise ValueError(f"PoseCapture: station must have shape (N,), one id per station, got {n}")
    n = n[0]
    fields = {}
    for name, cols in (("station", 0), ("set", 0), ("sensor", 0), ("time", 0), ("reported_positions", 3),
                       ("reported_quaternions_xyzw", 4), ("reference_positions", 3),
                       ("reference_quaternions_xyzw", 4)):
        value = getattr(capture, name)
        try:
            a = np.asarray(value, dtype=object if name == "set" else None)
            if cols:
                a = a.astype(float)
        except (TypeError, ValueError):
            raise ValueError(f"PoseCapture: {name} must be a numeric array, got {value!r:.80}") from None
        shape = (n, cols) if cols else (n,)
        if a.shape != shape:
            what = f"({'N, ' + str(cols) if cols else 'N,'})"
            raise ValueError(f"PoseCapture: {name} must have shape {what} with N = {n} (one row per station), "
                             f"got {a.shape}")
        if cols:
            bad = np.flatnonzero(~np.all(np.isfinite(a), axis=1))
            if len(bad):
                i = bad[0]
                raise ValueError(f"PoseCapture: station {capture.station[i]}: {name} {a[i].tolist()} is not finite")
        if cols == 4:
            # As poses.csv is read and trackcal.fit checks a capture: norm 1 within 1e-3 (normalised
            # by the readers). [0, 0, 0, 2] was normalised silently without a calibration, and with
            # one refused by correct() naming a row index, not the station or the array.
            norm = np.linalg.norm(a, axis=1)
            bad = np.flatnonzero(np.abs(norm - 1.0) > 1e-3)
            if len(bad):
                i = bad[0]
                raise ValueError(f"PoseCapture: station {capture.station[i]} (row {i}): {name} {a[i].tolist()} "
                                 f"has norm {norm[i]:g}, not 1 (within 1e-3, as poses.csv)")
        fields[name] = a
    return dataclasses.replace(capture, **fields)


# Stream samples are milliseconds apart (120 Hz on a Fastrak): the 10 worst were neighbouring
# samples of two moments (a 300 s paper-room stream: samples 6137-6147 and 27149-27168). The worst
# list keeps the worst sample of moments at least this far apart, about the pairing's correlation
# window (0.5 s, docs/diagnose.md), so each row is another pass through a bad place.
WORST_SEPARATION_S = 0.5


def _distinct_moments(order: Sequence[int], time: np.ndarray, sensor: np.ndarray, count: int,
                      separation: Optional[float]) -> List[int]:
    """The first ``count`` of ``order`` (station indices, worst first), skipping a station within
    ``separation`` seconds of one already taken of the same sensor (None: no skipping)."""
    if separation is None:
        return list(order[:count])
    taken: List[int] = []
    for i in order:
        if len(taken) >= count:
            break
        if all(sensor[j] != sensor[i] or abs(time[i] - time[j]) >= separation for j in taken):
            taken.append(i)
    return taken


def validate(capture: PoseCapture, calibration=None, *, sets: Sequence[str] = ("calib", "valid"),
             worst_count: int = 10, analyse_covariates: bool = True, covariate_options: Optional[dict] = None,
             progress: Optional[Callable[[int, int], None]] = None,
             corrected_poses: Optional[tuple] = None) -> Validation:
    """Applies ``calibration`` (a trackcal.Calibration, a calibration file's path, or None) to the capture's reported poses and
    computes everything ``trackcal diagnose`` shows. Registration stations (set 'reg') are left out
    of the breakdowns and the covariate analysis (they are not calibration data). Hemisphere flips
    (``hemisphere_flips``, decided within each set) are left out of the tables, the breakdowns, the
    worst stations and the covariate analysis, and named in ``flipped_stations``.

    ``corrected_poses`` = (positions (N, 3), quaternions_xyzw (N, 4)), one per station of the
    capture, are corrected poses obtained elsewhere (a server's corrected stream): they are
    validated as they are, and the calibration, if any, only flags the stations outside its volume."""
    worst_count = _whole_number(worst_count, "worst_count")
    if worst_count < 0:  # the slice [:-1] listed every station but one as the "worst"
        raise ValueError(f"worst_count {worst_count}: must be 0 or more")
    capture = _checked_capture(capture)
    calibration = _as_calibration(calibration)
    if calibration is not None:
        _warn_other_receiver(capture, calibration)
    data = capture.subset(capture.set != "reg") if "reg" in capture.sets else capture
    if len(data) == 0:
        raise ValueError(f"{capture.path}: no calibration or validation stations")
    before = residuals(data.reported_positions, data.reported_quaternions_xyzw,
                       data.reference_positions, data.reference_quaternions_xyzw)
    after = None
    cp = cq = None
    extrapolated = np.zeros(len(data), bool)
    status = np.zeros(len(data), np.uint8)
    if calibration is not None:
        cp, cq, extrapolated, status = calibration.correct(data.reported_positions, data.reported_quaternions_xyzw,
                                                           return_status=True)
    if corrected_poses is not None:
        keep = capture.set != "reg" if "reg" in capture.sets else np.ones(len(capture), bool)
        cp, cq = (np.asarray(a, dtype=float) for a in corrected_poses)
        # One row per station of the capture, checked before the registration stations are
        # dropped: a wrong count made the boolean mask an IndexError instead of this message.
        if cp.shape != (len(capture), 3) or cq.shape != (len(capture), 4):
            raise ValueError(f"corrected_poses: expected ({len(capture)}, 3) positions and ({len(capture)}, 4) "
                             f"quaternions x, y, z, w (one per station of the capture), got {cp.shape} and "
                             f"{cq.shape}")
        cp, cq = cp[keep], cq[keep]
        _check_corrected_poses(data, cp, cq)
    if cp is not None:
        after = residuals(cp, cq, data.reference_positions, data.reference_quaternions_xyzw)
    # A hemisphere flip (-p) stays 2 |p| off whatever the calibration. Each set decides its own
    # (fewer than half of it, as trackcal-fit's tables do); every table, the breakdowns, the worst
    # stations and the covariate analysis leave out the same stations (named: flipped_stations).
    flipped = np.zeros(len(data), bool)
    for name in np.unique(data.set.astype(str)):
        idx = data.set == name
        flipped[idx] = hemisphere_flips(data.reported_positions[idx], data.reference_positions[idx])
    # Samples paired from streams (or a recording) carry the set label the pairing gave every one
    # of them ("calib"), not a set of the user's: their table repeated the "all" one under a name
    # that reads as the calibration's in-sample stations (of a fit often made on poses.csv). One
    # table, "all", for them.
    paired = (getattr(capture, "origin", None) or {}).get("kind") in ("streams", "recording")
    tables = []
    for s in sets:
        idx = data.set == s
        if idx.any() and not (paired and idx.all()):
            tables.append(table1(s, _sub(before, idx), _sub(after, idx) if after is not None else None,
                                 flipped[idx]))
    tables.append(table1("all", before, after, flipped))
    final = after if after is not None else before
    distance = np.linalg.norm(data.reported_positions, axis=1)
    kept = ~flipped
    order = [i for i in np.argsort(-final.position_mm) if kept[i]]
    separation = WORST_SEPARATION_S if serial_samples(data) else None
    order = _distinct_moments(order, data.time, data.sensor, worst_count, separation)
    # (A stream sample's time in place of its set: the pairing's label, the same for every one.)
    worst = [{"station": int(data.station[i]),
              **({"set": str(data.set[i])} if separation is None else {"time": float(data.time[i])}),
              "sensor": int(data.sensor[i]),
              "x": float(data.reported_positions[i, 0]), "y": float(data.reported_positions[i, 1]),
              "z": float(data.reported_positions[i, 2]), "distance": float(distance[i]),
              "position_mm": float(final.position_mm[i]), "orientation_deg": float(final.orientation_deg[i]),
              "extrapolated": bool(extrapolated[i]),
              "status": correction_status_names[int(status[i])]} for i in order]
    centre = None
    if calibration is not None:
        centre = 0.5 * (np.asarray(calibration.volume_min) + np.asarray(calibration.volume_max))
    v = Validation(capture=data, calibration=calibration, corrected_positions=cp, corrected_quaternions_xyzw=cq,
                   extrapolated=np.asarray(extrapolated, bool), before=before, after=after, tables=tables,
                   by_distance=distance_breakdown(distance[kept], _sub(before, kept),
                                                  _sub(after, kept) if after is not None else None),
                   by_region=region_breakdown(data.reported_positions[kept], _sub(before, kept),
                                              _sub(after, kept) if after is not None else None, centre),
                   worst=worst, status=np.asarray(status, np.uint8), flipped=flipped,
                   worst_separation_s=separation)
    if analyse_covariates:
        # Stations paired from streams carry their speed: their samples are serially correlated.
        analysed = data.subset(kept) if flipped.any() else data
        serial = analysed.time if serial_samples(analysed) else None
        # After a fit, calib residuals are in-sample and valid ones held out: a level difference
        # between the sets, not structure a covariate explains (the sets are visited in turn).
        by_set = analysed.set if after is not None and len(np.unique(analysed.set)) > 1 else None
        covs, labels = covariates_and_labels(analysed)
        v.covariates_left_out = left_out_covariates(analysed)
        v.covariate_effects = covariate_analysis(_sub(final, kept), covs, progress=progress,
                                                 serial_time=serial, groups=by_set, labels=labels,
                                                 **(covariate_options or {}))
        # A covariate is tested only with values at 20 stations or more (covariate_analysis): on
        # fewer, none is, and the verdict said "nothing significant remains in the covariates" of
        # residuals it never looked at. Likewise with too few permutations (--permutations 9 to
        # save time): no test can reach its level, and "no covariate explains the residuals beyond
        # noise" was printed over an x that explained 29 % of the orientation error.
        options = covariate_options or {}
        n_permutations = options.get("n_permutations", 199)
        alpha = options.get("alpha", 0.01)
        if not v.covariate_effects:
            v.covariates_note = "a covariate needs values at 20 stations or more"
        elif not permutations_can_reach(n_permutations, len(v.covariate_effects), alpha):
            v.covariates_note = (f"{n_permutations} permutations cannot reach the significance level "
                                 f"(p <= {alpha / len(v.covariate_effects):.2g}: alpha {alpha:g} over "
                                 f"{len(v.covariate_effects)} tests); give 99 or more (--permutations)")
        v.covariates_tested = not v.covariates_note
    return v


def validate_recording(raw, reference, *, corrected=None, calibration=None, time_offset: Optional[float] = None,
                       search_range: float = 0.5, analyse_covariates: bool = False,
                       covariate_options: Optional[dict] = None, sensor: Optional[int] = None,
                       estimate_time_offset: Optional[bool] = None) -> Validation:
    """Validates a live recording (``trackcal record``, ``trackcal.record.record_streams`` or
    ``trackcal-server --record``) against the reference (optical) stream recorded beside it.

    ``raw``: the raw tracker_stream.csv; ``reference``: reference_stream.csv, on its own clock;
    ``corrected``: the server's corrected tracker_stream.csv of the same run (its reports carry the
    raw ones' times); ``calibration``: a trackcal.Calibration (or a calibration file's path), applied to the raw poses when no
    corrected stream is given (else it only flags stations outside its volume); ``sensor``: the
    receiver the reference tracks (numbered from 1 as in the recording), default the lowest sensor
    number of the raw recording (not the sensor of its first row: a live recording's first report
    comes from whichever receiver the server sent first). The raw stream of that sensor is paired
    with the reference (``trackcal.pair``) at ``time_offset`` [s] (t_reference - t_tracker), or at
    an offset estimated within +-``search_range`` s around 0 when it is None;
    ``estimate_time_offset=True`` estimates it around a given ``time_offset`` (a rough one: clocks
    of different epochs, an optical clock counting from its own start), as trackcal.pair does
    (default: estimated only when no offset is given). The corrected reports are matched to the
    paired raw samples by sensor and time.
    Returns a Validation (Table 1 before and after, breakdowns, worst samples, ``capture.origin``
    with the offset); ValueError if no corrected report matches a raw one."""
    import pathlib
    from trackcal.captures import carry_stream_columns, load_tracker_stream, nearest_samples, with_gaps
    from trackcal.fitting import pair
    if estimate_time_offset is None:
        estimate = time_offset is None
    elif not isinstance(estimate_time_offset, (bool, np.bool_)):
        raise ValueError(f"estimate_time_offset {estimate_time_offset!r}: must be True, False or None")
    else:
        estimate = bool(estimate_time_offset)
        if not estimate and time_offset is None:
            raise ValueError("estimate_time_offset=False needs a time_offset [s] (t_reference - t_tracker)")
    sensors = np.unique(load_tracker_stream(raw).sensor)
    if sensor is None:
        if len(sensors) == 0:
            raise ValueError(f"{raw}: no tracker reports")
        sensor = int(sensors[0])
    elif _whole_number(sensor, "sensor") not in sensors:
        raise ValueError(f"{raw}: no report of sensor {sensor} (have: {', '.join(str(int(s)) for s in sensors)})")
    with warnings.catch_warnings():  # its warning goes in origin, printed with the pairing line
        warnings.simplefilter("ignore", UserWarning)
        pairing = pair(raw, reference, time_offset=0.0 if time_offset is None else float(time_offset),
                       estimate_time_offset=estimate, search_range=search_range, sensor=int(sensor))
    cap = pairing.poses
    sensor = carry_stream_columns(cap, raw, reference, pairing.time_offset_s, pairing.clock_drift_applied,
                                  pairing.clock_drift_origin_s)
    cap.path = pathlib.Path(raw)
    cap.origin = {"kind": "recording", "files": [str(raw), str(reference)] + ([str(corrected)] if corrected else []),
                  "time_offset_s": float(pairing.time_offset_s),
                  "time_offset_source": "estimated" if estimate else "given",
                  "paired": len(cap), "dropped": int(pairing.dropped), "sensor": sensor,
                  "warning": with_gaps(pairing.warning, raw, sensor)}
    corrected_poses = None
    if corrected is not None:
        stream = load_tracker_stream(corrected)
        mine = stream.sensor == sensor
        t, p, q = stream.time[mine], stream.positions[mine], stream.quaternions_xyzw[mine]
        if len(t) == 0:
            raise ValueError(f"{corrected}: no report of sensor {sensor}")
        order = np.argsort(t, kind="stable")
        t, p, q = t[order], p[order], q[order]
        idx = nearest_samples(t, cap.time)
        # Both reports of a record are stamped with the same time; 1 us allows for a text round trip.
        ok = np.abs(t[idx] - cap.time) <= 1e-6
        if not ok.any():
            raise ValueError(f"{corrected}: no report matches a raw report of {raw} in time (sensor {sensor}): "
                             "record the raw and corrected trackers of the same server together")
        cap = cap.subset(ok)
        cap.origin["matched_corrected"] = int(ok.sum())
        corrected_poses = (p[idx[ok]], q[idx[ok]])
    return validate(cap, calibration, analyse_covariates=analyse_covariates, covariate_options=covariate_options,
                    corrected_poses=corrected_poses)


# ---------------------------------------------------------------------------------------------
# Fits and cross-validation through the fit engine (trackcal.fit, fit/fit_engine.h)

def _whole_number(value, what: str) -> int:
    """``value`` as an int when it is a whole number (2.0 is, 2.5, True and "2" are not), else a
    ValueError naming ``what``: a fraction was silently truncated (a degree 2.7 fitted degree 2) or
    failed far from the argument (folds=2.5 as a TypeError inside the fit)."""
    try:
        whole = not isinstance(value, (bool, np.bool_, str, bytes)) and int(value) == value
    except (TypeError, ValueError, OverflowError):
        whole = False
    if not whole:
        raise ValueError(f"{what} {value!r}: must be a whole number")
    return int(value)


def polynomial_model(degree: int = 3) -> str:
    """The model file text of the paper's eq. 7 polynomial of the given degree (a whole number)."""
    degree = _whole_number(degree, "polynomial degree")
    return f"terms:\n  - type: polynomial\n    degree: {degree}\n"


def _as_calibration_set(capture: PoseCapture) -> PoseCapture:
    """Every non-registration station of the capture labelled 'calib' (the set the engine fits)."""
    data = capture.subset(capture.set != "reg")
    if len(data) == 0:
        raise ValueError(f"{capture.path}: no calibration or validation stations")
    relabelled = dataclasses.replace(data, set=np.full(len(data), "calib", dtype=object))
    return relabelled


def fit_polynomial(capture: PoseCapture, degree: int = 3):
    """The paper's eq. 7 polynomial of the given degree fitted by the engine (linear least squares
    for a lone polynomial) to every non-registration station of ``capture``. Returns a
    trackcal.Calibration valid over the stations' bounding box."""
    from trackcal.fitting import fit
    return fit(_as_calibration_set(capture), polynomial_model(degree)).calibration


def cross_validate(capture: PoseCapture, model=None, folds: int = 5) -> Table1:
    """k-fold cross-validation of a model (path or YAML text; default: degree-3 polynomial) on the
    non-registration stations, by the engine: station i is corrected by the model fitted on the
    stations of the other folds (fold i mod k; stream samples by blocks of time, docs/fit.md). Returns
    the Table 1 of the held-out corrections, its set named by the model ("cross-validation (5-fold,
    degree-3 polynomial)"; "cross-validation (5-fold, blocks of time, degree-3 polynomial)")."""
    from trackcal.fitting import fit
    folds = _whole_number(folds, "cross-validation folds")
    if folds < 2:
        raise ValueError(f"cross-validation needs at least 2 folds, got {folds}")
    report = fit(_as_calibration_set(capture), model if model is not None else polynomial_model(3), folds=folds)
    table = report.table("cross-validation")
    # Named by the model it refits, which is not the calibration whose tables it stands beside.
    if model is None:
        what = "degree-3 polynomial"
    elif isinstance(model, (str, os.PathLike)) and os.path.isfile(model):
        what = pathlib.Path(model).name
    else:
        what = "the model text"
    name = table.set_name[:-1] + f", {what})" if table.set_name.endswith(")") else f"{table.set_name} ({what})"
    return dataclasses.replace(table, set_name=name)
