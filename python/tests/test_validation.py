"""Validation statistics against hand-computed values, capture loading (extra columns, errors naming
file/line/column) and cross-validation on simulated data."""

import math
import pathlib
import types

import numpy as np
import pytest

import trackcal
from trackcal import captures, validation
from understand_support import quat_about_z_xyzw, simulate, write_poses


def hand_capture(tmp_path):
    """Four stations: reported 1, 2, 3, 4 mm short along x and rotated 1, 2, 3, 4 degrees about z
    from the reference; two calib, two valid."""
    n = 4
    ref_p = np.array([[0.3, 0.0, 0.2], [0.4, 0.1, 0.2], [0.5, -0.1, 0.3], [0.6, 0.2, 0.4]])
    rep_p = ref_p - np.array([[1e-3 * (i + 1), 0, 0] for i in range(n)])
    ref_q = np.tile([0.0, 0.0, 0.0, 1.0], (n, 1))
    rep_q = quat_about_z_xyzw(-np.radians([1.0, 2.0, 3.0, 4.0]))
    cap = types.SimpleNamespace(station=np.arange(1, n + 1), set=["calib", "calib", "valid", "valid"],
                                sensor=np.ones(n, int), time=np.arange(n, dtype=float), reported_positions=rep_p,
                                reported_quaternions_xyzw=rep_q, reference_positions=ref_p,
                                reference_quaternions_xyzw=ref_q)
    return write_poses(tmp_path / "poses.csv", cap, extra={"temperature": [20.0, 21.0, 22.0, 23.5]})


def test_table1_hand_computed(tmp_path):
    cap = captures.load_poses(hand_capture(tmp_path))
    assert cap.extra_columns == ["temperature"]
    np.testing.assert_array_equal(cap.column("temperature"), [20.0, 21.0, 22.0, 23.5])
    # A constant correction of +1 mm along x (degree-0 polynomial): errors become 0, 1, 2, 3 mm.
    poly = trackcal.PolynomialCorrection(0, [[1e-3, 0.0, 0.0]], [[0.0, 0.0, 0.0]])
    cal = trackcal.Calibration([poly], (-1, -1, -1), (1, 1, 1))
    v = validation.validate(cap, cal, analyse_covariates=False)
    tables = {t.set_name: t for t in v.tables}
    # Hand values (1e-9 mm: float rounding of mm-sized differences of ~0.5 m coordinates).
    tol = 1e-9
    allt = tables["all"]
    assert allt.before_position_mm["count"] == 4
    assert allt.before_position_mm["mean"] == pytest.approx(2.5, abs=tol)
    assert allt.before_position_mm["std"] == pytest.approx(math.sqrt(5.0 / 3.0), abs=tol)
    assert allt.before_position_mm["max"] == pytest.approx(4.0, abs=tol)
    assert allt.after_position_mm["mean"] == pytest.approx(1.5, abs=tol)
    assert allt.after_position_mm["max"] == pytest.approx(3.0, abs=tol)
    # Orientation: 1..4 degrees, the correction leaves orientation alone (1e-9 deg: acos-free angle).
    assert allt.before_orientation_deg["mean"] == pytest.approx(2.5, abs=1e-9)
    assert allt.after_orientation_deg["max"] == pytest.approx(4.0, abs=1e-9)
    assert tables["calib"].before_position_mm["mean"] == pytest.approx(1.5, abs=tol)
    assert tables["valid"].after_position_mm["mean"] == pytest.approx(2.5, abs=tol)
    text = tables["valid"].format()
    assert "valid set (2 poses)" in text and "Position error (mm)" in text
    # Error vectors: p_ref - p_rep along +x; orientation vector part sin(angle/2) about +z.
    np.testing.assert_allclose(v.before.position[:, 0], [1e-3, 2e-3, 3e-3, 4e-3], atol=1e-15)
    np.testing.assert_allclose(v.before.orientation[:, 2], np.sin(np.radians([1, 2, 3, 4]) / 2), atol=1e-12)
    assert v.worst[0]["station"] == 4 and v.worst[0]["position_mm"] == pytest.approx(3.0, abs=tol)
    assert not v.extrapolated.any()
    # A polynomial has no model inverse: every station's correction status is converged.
    assert v.status_counts == {"converged": 4, "ambiguous": 0, "not_converged": 0}
    assert v.worst[0]["status"] == "converged"


def test_repr_of_a_capture_and_a_validation_says_what_they_are(tmp_path):
    """The dataclass reprs printed every array: 18 kB (257 lines) for the paper's 480 stations and
    84 kB for their validation, in a notebook cell that wanted to know which capture this is. They
    now name the file, the rows per set, the sensor and the Table 1 means, on one line."""
    n = 300
    cap = captures.load_poses(hand_capture(tmp_path))
    big = cap.subset(np.arange(n) % len(cap))  # 300 rows: enough for numpy to print all of them
    text = repr(big)
    assert "\n" not in text and len(text) < 200, text
    assert str(tmp_path / "poses.csv") in text and f"{n} rows (calib 150, valid 150)" in text, text
    assert "sensor 1" in text and "extra_columns=['temperature']" in text, text
    poly = trackcal.PolynomialCorrection(0, [[1e-3, 0.0, 0.0]], [[0.0, 0.0, 0.0]])
    cal = trackcal.Calibration([poly], (-1, -1, -1), (1, 1, 1))
    v = validation.validate(big, cal, analyse_covariates=False)
    text = repr(v)
    assert "\n" not in text and len(text) < 400, text
    valid = v.tables[[t.set_name for t in v.tables].index("valid")]
    assert f"valid: {valid.after_position_mm['mean']:.3f} mm" in text, text
    assert repr(cal) in text and "0 outside the calibrated volume" in text, text


def test_extrapolated_stations_flagged(tmp_path):
    cap = captures.load_poses(hand_capture(tmp_path))
    poly = trackcal.PolynomialCorrection(0, [[0.0, 0.0, 0.0]], [[0.0, 0.0, 0.0]])
    cal = trackcal.Calibration([poly], (0.0, -1, -1), (0.45, 1, 1))  # stations 3, 4 lie beyond x = 0.45
    v = validation.validate(cap, cal, analyse_covariates=False)
    assert v.extrapolated.tolist() == [False, False, True, True]


def test_breakdowns_partition_the_stations(tmp_path):
    cap = captures.load_poses(simulate(tmp_path / "sim", seed=11))
    cal = validation.fit_polynomial(cap.select_set("calib"), degree=3)
    v = validation.validate(cap, cal, analyse_covariates=False)
    n = len(v.capture)
    assert sum(r["count"] for r in v.by_distance) == n
    assert sum(r["count"] for r in v.by_region) == n
    # Band means recombine to the overall mean (same numbers, weighted by counts; 1e-9 rounding).
    total = sum(r["count"] * r["after_position_mm"] for r in v.by_distance) / n
    assert total == pytest.approx(v.after.position_mm.mean(), rel=1e-9)
    assert "reg" not in set(v.capture.set)
    tables = {t.set_name: t for t in v.tables}
    # The paper's degree-3 polynomial removes most of the simulated distortion on held-out stations.
    assert tables["valid"].after_position_mm["mean"] < 0.5 * tables["valid"].before_position_mm["mean"]


def test_distance_bands_hold_a_station_on_a_band_edge():
    """A station exactly at a multiple of the band width (here the farthest, at 0.5 m) was left out
    of every band: the bands ran up to ceil(max / step) * step, exclusive."""
    distance = np.array([0.1, 0.25, 0.3, 0.5])
    r = validation.Residuals(np.zeros((4, 3)), np.zeros((4, 3)), np.array([1.0, 2.0, 3.0, 4.0]), np.zeros(4))
    rows = validation.distance_breakdown(distance, r, None)
    assert [(row["label"], row["count"]) for row in rows] == [
        ("0.00-0.25 m", 1), ("0.25-0.50 m", 2), ("0.50-0.75 m", 1)]
    assert [row["before_position_mm"] for row in rows] == [1.0, 2.5, 4.0]
    # Bands of 0.1 m, whose edges are not exact in binary: still one band per station.
    d = np.linspace(0.0, 1.0, 11)
    r = validation.Residuals(np.zeros((11, 3)), np.zeros((11, 3)), np.ones(11), np.zeros(11))
    assert sum(row["count"] for row in validation.distance_breakdown(d, r, None, step_m=0.1)) == 11


def test_hemisphere_flips_are_left_out_of_the_statistics_and_named(tmp_path):
    """The simulator's hemisphere_flips: a few stations reported at -p, 2 |p| off whatever the
    calibration. Both Table 1s (the fit's, C++, and validate's) leave them out of both columns and
    say so; the breakdowns and the worst stations leave them out; the station rows name them."""
    import json
    out = simulate(tmp_path / "sim", seed=3, hidden="hemisphere_flips")
    flipped = sorted(json.loads((out / "truth.json").read_text())["effective"]["hemisphere_flipped_stations"])
    assert flipped, "the simulator's hemisphere_flips flipped no station"
    cap = captures.load_poses(out)
    report = trackcal.fit(cap, validation.polynomial_model(3))
    v = validation.validate(cap, report.calibration, covariate_options={"n_permutations": 19})
    assert sorted(v.flipped_stations) == flipped
    # The covariate analysis ran on the stations left (each test counts them).
    assert v.covariate_effects and all(e.count == len(v.capture) - len(flipped) for e in v.covariate_effects)
    sets = {t.set_name: t for t in v.tables}
    left_out = 0
    for name in ("calib", "valid"):
        n_set = int((v.capture.set == name).sum())
        t = sets[name]
        assert t.before_position_mm["count"] + t.hemisphere_flips_left_out == n_set
        left_out += t.hemisphere_flips_left_out
        # A flip is at least 2 x 0.35 m off (the paper's volume starts 0.35 m above the
        # transmitter); the stations left are within centimetres before and millimetres after.
        assert t.before_position_mm["max"] < 150.0 and t.after_position_mm["max"] < 150.0
        assert ("more left out" in t.format()) == bool(t.hemisphere_flips_left_out)
        # The fit's own table (core/error_statistics.cc MakeTable1, the same rule) agrees.
        cpp = report.table(name)
        assert cpp.hemisphere_flips_left_out == t.hemisphere_flips_left_out
        assert cpp.after_position_mm["mean"] == pytest.approx(t.after_position_mm["mean"], rel=1e-9)
    assert left_out == len(flipped)
    assert sets["all"].hemisphere_flips_left_out == len(flipped)
    assert sets["all"].to_dict()["hemisphere_flips_left_out"] == len(flipped)  # trackcal-fit's JSON name
    assert sum(r["count"] for r in v.by_distance) == len(v.capture) - len(flipped)
    assert sum(r["count"] for r in v.by_region) == len(v.capture) - len(flipped)
    # The least-squares polynomial bends to the calibration set's flips, but the worst stations
    # are those of the others.
    assert len(v.worst) == 10 and not {w["station"] for w in v.worst} & set(flipped)
    rows = {r["station"]: r for r in v.station_rows()}
    assert sorted(s for s, r in rows.items() if r["flipped"]) == flipped


def test_most_reports_flipped_are_shown_not_left_out(tmp_path):
    """Every report in the other hemisphere (a wrong hemisphere setting): nothing is left out."""
    cap = captures.load_poses(hand_capture(tmp_path))
    cap.reported_positions = -cap.reported_positions
    v = validation.validate(cap, None, analyse_covariates=False)
    assert v.flipped_stations == [] and all(t.hemisphere_flips_left_out == 0 for t in v.tables)
    assert {t.set_name: t for t in v.tables}["all"].before_position_mm["count"] == 4


def test_each_set_decides_its_flips_and_every_statistic_leaves_out_the_same(tmp_path):
    """8 calibration stations with 1 flip (left out) and 4 validation stations with 3 (most of
    the set: a wrong setting, shown): the tables, the breakdowns and the worst stations agree."""
    rng = np.random.default_rng(3)
    n = 12
    ref_p = np.column_stack([rng.uniform(-0.4, 0.4, n), rng.uniform(-0.4, 0.4, n), rng.uniform(-0.8, -0.4, n)])
    rep_p = ref_p + rng.normal(0, 1e-3, (n, 3))
    flip = np.zeros(n, bool)
    flip[[2, 9, 10, 11]] = True
    rep_p[flip] = -rep_p[flip]
    q = np.tile([0.0, 0.0, 0.0, 1.0], (n, 1))
    cap = types.SimpleNamespace(station=np.arange(1, n + 1), set=["calib"] * 8 + ["valid"] * 4,
                                sensor=np.ones(n, int), time=np.arange(n, dtype=float), reported_positions=rep_p,
                                reported_quaternions_xyzw=q, reference_positions=ref_p, reference_quaternions_xyzw=q)
    cap = captures.load_poses(write_poses(tmp_path / "poses.csv", cap))
    assert validation.hemisphere_flips(rep_p[:8], ref_p[:8]).tolist() == flip[:8].tolist()
    assert not validation.hemisphere_flips(rep_p[8:], ref_p[8:]).any()
    v = validation.validate(cap, None, analyse_covariates=False)
    assert v.flipped_stations == [3]
    tables = {t.set_name: t for t in v.tables}
    assert (tables["calib"].before_position_mm["count"], tables["calib"].hemisphere_flips_left_out) == (7, 1)
    assert (tables["valid"].before_position_mm["count"], tables["valid"].hemisphere_flips_left_out) == (4, 0)
    assert (tables["all"].before_position_mm["count"], tables["all"].hemisphere_flips_left_out) == (11, 1)
    assert "1 more left out" in tables["calib"].format()  # the table without a correction says so too
    assert "left out" not in tables["valid"].format()
    assert sum(r["count"] for r in v.by_distance) == 11 and sum(r["count"] for r in v.by_region) == 11
    # The valid set's three flips are shown: they top the worst stations; the calib flip is not there.
    assert {w["station"] for w in v.worst[:3]} == {10, 11, 12} and 3 not in {w["station"] for w in v.worst}


def test_cross_validation_held_out_is_worse_than_in_sample(tmp_path):
    cap = captures.load_poses(simulate(tmp_path / "sim", seed=12))
    cv = validation.cross_validate(cap, folds=5)
    cal = validation.fit_polynomial(cap.subset(cap.set != "reg"), degree=3)
    v = validation.validate(cap, cal, analyse_covariates=False)
    in_sample = {t.set_name: t for t in v.tables}["all"].after_position_mm["mean"]
    assert cv.after_position_mm["mean"] > in_sample  # held-out error cannot beat in-sample
    assert cv.after_position_mm["mean"] < cv.before_position_mm["mean"]


def test_bad_capture_error_names_file_line_column(tmp_path):
    p = hand_capture(tmp_path)
    lines = p.read_text().splitlines()
    fields = lines[2].split(",")
    fields[7] = "abc"  # rep_qw of the second station (line 3)
    lines[2] = ",".join(fields)
    p.write_text("\n".join(lines) + "\n")
    with pytest.raises(ValueError, match=r"poses\.csv:3: column rep_qw: 'abc' is not a number"):
        captures.load_poses(p)


def test_repeated_station_and_sensor_error_names_both_lines(tmp_path):
    p = hand_capture(tmp_path)
    lines = p.read_text().splitlines()
    lines.append(lines[1])  # the first station's row again, on the last line
    p.write_text("\n".join(lines) + "\n")
    with pytest.raises(ValueError, match=rf"poses\.csv:{len(lines)}: columns station, sensor: "
                                         r"station \d+, sensor \d+ repeats line 2"):
        captures.load_poses(p)


def test_residuals_never_replace_a_file_that_appears_while_they_are_written(tmp_path, monkeypatch):
    """The last check before publishing cannot close the window before a rename: the file is
    published by a link, which fails on any file there, however late it came."""
    import errno
    import os
    cap = captures.load_poses(hand_capture(tmp_path))
    v = validation.validate(cap, None, analyse_covariates=False)
    out = tmp_path / "residuals.csv"
    out.write_text("someone else's file\n")
    real_exists = pathlib.Path.exists
    # The file appears after every existence check the writer may make.
    monkeypatch.setattr(pathlib.Path, "exists",
                        lambda self, *a, **k: False if self == out else real_exists(self))
    with pytest.raises(ValueError, match="residuals.csv: exists; residuals are never written over"):
        v.write_residuals(out)
    monkeypatch.undo()
    assert out.read_text() == "someone else's file\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["poses.csv", "residuals.csv"]  # no temporary left
    # A file system without hard links: a clear error, nothing written, no temporary left.

    def no_links(src, dst, *a, **k):
        raise OSError(errno.EPERM, "Operation not permitted")
    monkeypatch.setattr(os, "link", no_links)
    with pytest.raises(ValueError, match="new.csv: not written: the file system .* has no hard links"):
        v.write_residuals(tmp_path / "new.csv")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["poses.csv", "residuals.csv"]
    monkeypatch.undo()
    with pytest.raises(ValueError, match=f"r.csv: {tmp_path / 'none'} is not an existing folder"):
        v.write_residuals(tmp_path / "none" / "r.csv")
    v.write_residuals(tmp_path / "new.csv")
    assert (tmp_path / "new.csv").read_text().startswith("station,set,sensor,")


def test_corrected_poses_of_the_wrong_count_are_a_value_error(tmp_path):
    """One corrected pose per station of the capture: another count is the caller's error, named
    (it was an IndexError from the boolean mask of the registration stations)."""
    cap = captures.load_poses(hand_capture(tmp_path))
    with pytest.raises(ValueError, match=r"corrected_poses: expected \(4, 3\) positions and \(4, 4\) quaternions"):
        validation.validate(cap, None, analyse_covariates=False,
                            corrected_poses=(cap.reference_positions[:3], cap.reference_quaternions_xyzw[:3]))


@pytest.mark.parametrize("field", ["position", "quaternion"])
def test_corrected_poses_that_are_not_poses_are_refused_naming_the_station(tmp_path, field):
    """A NaN corrected position made the means NaN while the maximum and the worst stations left it
    out without a word; a zero quaternion was scored as a perfect 0 degree orientation."""
    cap = captures.load_poses(hand_capture(tmp_path))
    p, q = cap.reference_positions.copy(), cap.reference_quaternions_xyzw.copy()
    if field == "position":
        p[2, 1] = np.nan
    else:
        q[2] = 0.0
    with pytest.raises(ValueError, match=rf"corrected_poses: station 3: {field}"):
        validation.validate(cap, None, analyse_covariates=False, corrected_poses=(p, q))
    # Unit quaternions, q or -q, are accepted and equal.
    v = validation.validate(cap, None, analyse_covariates=False,
                            corrected_poses=(cap.reference_positions, -cap.reference_quaternions_xyzw))
    np.testing.assert_allclose(v.after.orientation_deg, 0.0, atol=1e-9)


def test_a_capture_of_the_wrong_shape_or_not_finite_is_refused_naming_the_field(tmp_path):
    """validate() checks an in-memory capture's per-station fields as trackcal.fit does. Before: a
    transposed (3, N) positions array was an IndexError of a boolean mask and an (N, 1) station
    column a TypeError; a list field was kept whole by subset() while the arrays beside it lost the
    registration stations ("estimated: positions must be (N, 3) ...", naming no field); an
    infinite reported position was silently left out of every table as a hemisphere flip."""
    import dataclasses
    cap = captures.load_poses(hand_capture(tmp_path))
    cap = dataclasses.replace(cap, set=np.array(["reg", "calib", "valid", "valid"], dtype=object))
    base = validation.validate(cap, None, analyse_covariates=False)
    for change, message in [
        (dict(reported_positions=cap.reported_positions.T), r"reported_positions must have shape \(N, 3\) with N = 4 "
                                                             r"\(one row per station\), got \(3, 4\)"),
        (dict(station=cap.station[:, None]), r"station must have shape \(N,\), one id per station, got \(4, 1\)"),
        (dict(reference_quaternions_xyzw=cap.reference_quaternions_xyzw[:3]),
         r"reference_quaternions_xyzw must have shape \(N, 4\) with N = 4 .*got \(3, 4\)"),
    ]:
        with pytest.raises(ValueError, match="PoseCapture: " + message):
            validation.validate(dataclasses.replace(cap, **change), None, analyse_covariates=False)
    p = cap.reported_positions.copy()
    p[1, 0] = -np.inf  # x of every reference is positive: was a "hemisphere flip", left out
    with pytest.raises(ValueError, match=r"PoseCapture: station 2: reported_positions \[-inf, .*\] is not finite"):
        validation.validate(dataclasses.replace(cap, reported_positions=p), None, analyse_covariates=False)
    # Lists and Fortran-ordered arrays are the same numbers as the contiguous arrays.
    same = dataclasses.replace(cap, set=list(cap.set), reported_positions=cap.reported_positions.tolist(),
                               reference_positions=np.asfortranarray(cap.reference_positions))
    v = validation.validate(same, None, analyse_covariates=False)
    assert v.tables == base.tables


def test_a_capture_quaternion_that_is_not_unit_is_refused_naming_station_and_field(tmp_path):
    """As poses.csv is read and trackcal.fit checks a capture: a norm within 1e-3 of 1 is
    normalised, further it is refused. validate() normalised [0, 0, 0, 2] silently without a
    calibration, and with one the error came from correct(), naming a row index only."""
    import dataclasses
    cap = captures.load_poses(hand_capture(tmp_path))
    cal = trackcal.Calibration([trackcal.PolynomialCorrection(0, np.zeros((1, 3)), np.zeros((1, 3)))],
                               [-2, -2, -2], [2, 2, 2])
    for calibration in (None, cal):
        q = cap.reference_quaternions_xyzw.copy()
        q[2] *= 2.0
        with pytest.raises(ValueError, match=r"^PoseCapture: station 3 \(row 2\): reference_quaternions_xyzw "
                                             r"\[.*\] has norm 2, not 1"):
            validation.validate(dataclasses.replace(cap, reference_quaternions_xyzw=q), calibration,
                                analyse_covariates=False)
        q = cap.reported_quaternions_xyzw.copy()
        q[1] *= 1.0 + 5e-4  # within the readers' tolerance: normalised, the same tables
        near = validation.validate(dataclasses.replace(cap, reported_quaternions_xyzw=q), calibration,
                                   analyse_covariates=False)
        unit = validation.validate(cap, calibration, analyse_covariates=False)
        # 1e-9 deg: the rounding of the normalisation through an angle of a few degrees.
        assert near.tables[0].before_orientation_deg["mean"] == pytest.approx(
            unit.tables[0].before_orientation_deg["mean"], abs=1e-9)


def test_residuals_of_arrays_of_the_wrong_shape_name_the_array_and_its_shape():
    """validation.residuals (the C++ error_magnitudes) said "estimated: positions must be (N, 3)
    and quaternions (N, 4) x, y, z, w" for any wrong array: not which one, nor the shape it had."""
    p = np.array([[0.3, 0.0, 0.2], [0.4, 0.1, 0.2]])
    q = np.tile([0.0, 0.0, 0.0, 1.0], (2, 1))
    for args, message in [
        ((p.T, q, p, q), r"error_magnitudes: estimated_positions must have shape \(N, 3\), got \(3, 2\)"),
        ((p, q, p, q.T), r"error_magnitudes: reference_quaternions_xyzw must have shape \(N, 4\) x, y, z, w with "
                         r"N = 2 like reference_positions, got \(4, 2\)"),
        ((p, q[:1], p, q), r"estimated_quaternions_xyzw must have shape .* got \(1, 4\)"),
        ((p, q, "abc", q), r"reference_positions must have shape \(N, 3\), got no numeric array: .abc."),
    ]:
        with pytest.raises(ValueError, match=message):
            validation.residuals(*args)
    r = validation.residuals(p.tolist(), np.asfortranarray(q), p[::-1][::-1], q)
    np.testing.assert_array_equal(r.position_mm, [0.0, 0.0])


def test_residual_rows_keep_every_extra_column_whatever_its_name(tmp_path):
    """An extra column named like a derived column (x) is written as extra_x; a column the user
    named extra_x was then overwritten by x's values (one column lost without a word). Both are
    kept, named as the covariate analysis names them."""
    base = captures.load_poses(hand_capture(tmp_path))
    cap = types.SimpleNamespace(station=base.station, set=list(base.set), sensor=base.sensor, time=base.time,
                                reported_positions=base.reported_positions,
                                reported_quaternions_xyzw=base.reported_quaternions_xyzw,
                                reference_positions=base.reference_positions,
                                reference_quaternions_xyzw=base.reference_quaternions_xyzw)
    (tmp_path / "named").mkdir()
    path = write_poses(tmp_path / "named" / "poses.csv", cap,
                       extra={"extra_x": [101.0, 102.0, 103.0, 104.0], "x": [1.0, 2.0, 3.0, 4.0]})
    v = validation.validate(captures.load_poses(path), None, analyse_covariates=False)
    rows = v.station_rows()
    assert [r["extra_x"] for r in rows] == [101.0, 102.0, 103.0, 104.0]
    assert [r["extra_extra_x"] for r in rows] == [1.0, 2.0, 3.0, 4.0]
    assert rows[0]["x"] == pytest.approx(base.reported_positions[0, 0])
    covs = validation.covariates(v.capture)
    np.testing.assert_array_equal(covs["extra_x"], [101.0, 102.0, 103.0, 104.0])
    np.testing.assert_array_equal(covs["extra_extra_x"], [1.0, 2.0, 3.0, 4.0])
    out = v.write_residuals(tmp_path / "residuals.csv")
    header = out.read_text().splitlines()[0].split(",")
    assert header.count("extra_x") == 1 and "extra_extra_x" in header


def test_a_degree_that_is_not_whole_and_a_negative_worst_count_are_refused(tmp_path):
    """fit_polynomial(capture, 2.7) fitted a degree-2 polynomial without a word (int() truncated
    it), and validate(worst_count=-1) listed every station but one as the worst (a [:-1] slice)."""
    cap = captures.load_poses(hand_capture(tmp_path))
    for degree in (2.7, "3", True, float("nan")):
        with pytest.raises(ValueError, match=r"polynomial degree .*: must be a whole number"):
            validation.polynomial_model(degree)
    with pytest.raises(ValueError, match=r"polynomial degree 2\.7: must be a whole number"):
        validation.fit_polynomial(cap, 2.7)
    assert "degree: 2\n" in validation.polynomial_model(2.0) and "degree: 3\n" in validation.polynomial_model(np.int64(3))
    with pytest.raises(ValueError, match=r"worst_count -1: must be 0 or more"):
        validation.validate(cap, None, worst_count=-1, analyse_covariates=False)
    assert validation.validate(cap, None, worst_count=0, analyse_covariates=False).worst == []
    # A fractional count: worst_count=2.5 raised TypeError from a slice, folds=2.5 a TypeError from
    # inside the fit binding; both name the argument now.
    with pytest.raises(ValueError, match=r"worst_count 2\.5: must be a whole number"):
        validation.validate(cap, None, worst_count=2.5, analyse_covariates=False)
    with pytest.raises(ValueError, match=r"cross-validation folds 2\.5: must be a whole number"):
        validation.cross_validate(cap, folds=2.5)


def test_a_calibration_given_as_a_path_is_loaded_and_anything_else_is_named(tmp_path):
    """validate(capture, "calib.json") was an AttributeError ("'str' object has no attribute
    'correct'") from deep inside; a path (str or pathlib) is loaded as trackcal.Calibration.load does,
    and gives the same tables as the loaded calibration."""
    example = pathlib.Path(__file__).resolve().parents[2] / "tests" / "data" / "calibration" / "example.json"
    cap = captures.load_poses(hand_capture(tmp_path))
    loaded = validation.validate(cap, trackcal.Calibration.load(str(example)), analyse_covariates=False)
    for given in (str(example), example):
        v = validation.validate(cap, given, analyse_covariates=False)
        np.testing.assert_array_equal(v.corrected_positions, loaded.corrected_positions)
        np.testing.assert_array_equal(v.corrected_quaternions_xyzw, loaded.corrected_quaternions_xyzw)
    with pytest.raises(TypeError, match="calibration: expected a trackcal.Calibration.*got int"):
        validation.validate(cap, 3, analyse_covariates=False)
    with pytest.raises(ValueError, match="missing.json"):
        validation.validate(cap, str(tmp_path / "missing.json"), analyse_covariates=False)


def test_validation_and_residuals_compare_with_equals_and_refuse_equality_with_a_hint(tmp_path):
    """Validation and Residuals hold numpy arrays, as PoseCapture and Parameter do, but kept the
    dataclass ==: it failed with numpy's "The truth value of an array with more than one element is
    ambiguous", naming neither class. They now have equals() (every field, arrays element by
    element, NaN equal to NaN, the capture and calibration by their contents) and == is a TypeError
    pointing to it."""
    path = hand_capture(tmp_path)
    poly = trackcal.PolynomialCorrection(0, [[1e-3, 0.0, 0.0]], [[0.0, 0.0, 0.0]])
    cal = trackcal.Calibration([poly], (-1, -1, -1), (1, 1, 1))
    a = validation.validate(captures.load_poses(path), cal, analyse_covariates=False)
    b = validation.validate(captures.load_poses(path), trackcal.Calibration.from_json(cal.to_json(), "c"),
                            analyse_covariates=False)
    assert a.equals(b) and b.equals(a) and a.before.equals(b.before) and a.after.equals(b.after)
    other = trackcal.Calibration([trackcal.PolynomialCorrection(0, [[2e-3, 0.0, 0.0]], [[0.0, 0.0, 0.0]])],
                                 (-1, -1, -1), (1, 1, 1))
    c = validation.validate(captures.load_poses(path), other, analyse_covariates=False)
    assert not a.equals(c) and not a.after.equals(c.after) and a.before.equals(c.before)
    assert not a.equals(None) and not a.before.equals(a) and not a.equals(a.before)
    for x, y, name in ((a, b, "Validation"), (a.before, b.before, "Residuals")):
        with pytest.raises(TypeError, match=rf"{name} == {name} is not defined \(they hold numpy arrays\): "
                                            r"use a\.equals\(b\)"):
            x == y  # noqa: B015
    # A NaN in a summary (the std of one station) is equal to itself, as in the arrays.
    one = captures.load_poses(path).subset([0])
    assert validation.validate(one, cal, analyse_covariates=False).equals(
        validation.validate(one, cal, analyse_covariates=False))


def test_table1_and_covariate_effects_with_nan_equal_their_copies():
    """A summary of no stations and an untested covariate hold NaN; == compares field by field with
    NaN equal to NaN, so a result equals one computed again (the dataclass == said it did not: two
    NaN objects are not ==)."""
    from trackcal.validation import CovariateEffect, Table1

    def empty():
        nan = float("nan")  # a new NaN object each time, as a second computation makes
        return {"count": 0, "mean": nan, "std": nan, "max": nan, "rms": nan, "median": nan, "p95": nan}

    def table(mean):
        return Table1("valid", empty(), dict(empty(), count=3, mean=mean))
    assert table(1.5) == table(1.5)
    assert table(1.5) != table(1.6)
    assert table(1.5) != "valid"

    def effect(count):
        return CovariateEffect("temperature", "position_mm", float("nan"), float("nan"), False, count,
                               levels=[{"label": "a", "offset": float("nan")}])
    assert effect(12) == effect(12)
    assert effect(12) != effect(13)
