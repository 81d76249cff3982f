"""The trackcal package's calibration API: loading, correcting batches, building and saving, and the
error messages users see."""

import json
import math
import os
import pathlib

import numpy as np
import pytest

import trackcal
from trackcal import numpy_reference

REPO = pathlib.Path(__file__).resolve().parents[2]
EXAMPLE = REPO / "tests" / "data" / "calibration" / "example.json"


def random_poses(rng, n, half_extent=0.4, centre=(0.0, 0.0, 0.3)):
    positions = np.asarray(centre) + rng.uniform(-half_extent, half_extent, size=(n, 3))
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return positions, q


def degree4(rng):
    r = trackcal.num_polynomial_terms(4)
    pc = rng.normal(scale=0.005, size=(r, 3))
    oc = rng.normal(scale=0.003, size=(r, 3))
    return pc, oc


def rotation_angles(a, b):
    """Angles between rows of (N, 4) quaternion arrays, sign-invariant."""
    d = np.abs(np.sum(a * b, axis=1) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1)))
    return 2.0 * np.arccos(np.clip(d, -1.0, 1.0))


def test_load_example_nominal():
    cal = trackcal.Calibration.load(EXAMPLE)
    assert [c.type for c in cal.corrections] == ["polynomial", "trilinear_lut"]
    assert cal.extrapolation == "fade"
    assert cal.fade_distance == 0.15
    np.testing.assert_array_equal(cal.volume_max, [0.6, 0.5, 0.7])
    assert cal.fit_statistics["num_samples"] == 480
    assert cal.provenance["inputs"][0]["role"] == "model_file"
    poly = cal.corrections[0]
    assert poly.degree == 2
    assert poly.position_coefficients.shape == (10, 3)
    assert poly.position_coefficients[1, 0] == 0.0102
    lut = cal.corrections[1]
    assert lut.position_error.shape == (2, 2, 3, 3)
    assert [len(a) for a in lut.axes] == [2, 2, 3]
    # Node (ix=0, iy=1, iz=2) is entry (0 * 2 + 1) * 3 + 2 = 5 of the file's list.
    doc = json.loads(EXAMPLE.read_text())
    np.testing.assert_array_equal(lut.position_error[0, 1, 2], doc["corrections"][1]["position_error"][5])


def test_correct_matches_numpy_reference():
    rng = np.random.default_rng(1)
    pc, oc = degree4(rng)
    offset, scale = (0.0, 0.0, 0.3), (0.5, 0.5, 0.5)
    poly = trackcal.PolynomialCorrection(4, pc, oc, offset, scale)
    cal = trackcal.Calibration([poly], volume_min=(-0.5, -0.5, -0.2), volume_max=(0.5, 0.5, 0.8))
    positions, quats = random_poses(rng, 1000)
    p, q, extrapolated = cal.correct(positions, quats)
    assert p.shape == (1000, 3) and q.shape == (1000, 4) and extrapolated.dtype == np.bool_
    assert not extrapolated.any()
    p_ref, q_ref = numpy_reference.correct_polynomial(4, pc, oc, offset, scale, positions, quats)
    # Same polynomial, different summation order: rounding of sums of 35 terms of ~0.01.
    np.testing.assert_allclose(p, p_ref, rtol=0, atol=1e-15)
    assert rotation_angles(q, q_ref).max() < 1e-7  # arccos of |dot| near 1 resolves only ~1e-8
    np.testing.assert_allclose(q, q_ref, rtol=0, atol=1e-15)
    # Inputs are not modified.
    p2, _, _ = cal.correct(positions, quats)
    np.testing.assert_array_equal(p, p2)


def test_correct_flags_and_clamps_outside_volume():
    rng = np.random.default_rng(2)
    pc, oc = degree4(rng)
    poly = trackcal.PolynomialCorrection(4, pc, oc, (0, 0, 0), (0.5, 0.5, 0.5))
    cal = trackcal.Calibration([poly], (-0.5, -0.5, -0.5), (0.5, 0.5, 0.5), extrapolation="clamp")
    positions = np.array([[0.1, 0.2, 0.3], [3.0, 0.2, 0.3], [0.5, 0.2, 0.3]])
    quats = np.tile([0.0, 0.0, 0.0, 1.0], (3, 1))
    p, q, extrapolated = cal.correct(positions, quats)
    assert extrapolated.tolist() == [False, True, False]
    # Held boundary value: the outside pose gets the correction of the nearest box point.
    np.testing.assert_allclose(p[1] - positions[1], p[2] - positions[2], atol=1e-15)
    np.testing.assert_allclose(q[1], q[2], atol=1e-15)

    fade = trackcal.Calibration([poly], (-0.5, -0.5, -0.5), (0.5, 0.5, 0.5), extrapolation="fade",
                                fade_distance=0.5)
    p, q, extrapolated = fade.correct(positions, quats)
    assert extrapolated.tolist() == [False, True, False]
    np.testing.assert_array_equal(p[1], positions[1])  # 2.5 m beyond: identity
    np.testing.assert_array_equal(q[1], quats[1])


def test_bad_shapes_raise_value_error_with_expected_shape():
    cal = trackcal.Calibration.load(EXAMPLE)
    with pytest.raises(ValueError, match=r"positions must have shape \(N, 3\), got \(4, 4\)"):
        cal.correct(np.zeros((4, 4)), np.zeros((4, 4)))
    with pytest.raises(ValueError, match=r"positions must have shape \(N, 3\), got \(3,\)"):
        cal.correct(np.zeros(3), np.zeros((1, 4)))
    with pytest.raises(ValueError,
                       match=r"quaternions_xyzw must have shape \(5, 4\) \(N = 5 rows like positions"
                             r".*got \(4, 4\)"):
        cal.correct(np.zeros((5, 3)), np.zeros((4, 4)))
    with pytest.raises(ValueError, match=r"positions must be a numeric array of shape \(N, 3\)"):
        cal.correct([["a", "b", "c"]], np.zeros((1, 4)))
    with pytest.raises(ValueError,
                       match=r"position_coefficients must have shape \(35, 3\) for degree 4, got \(34, 3\)"):
        trackcal.PolynomialCorrection(4, np.zeros((34, 3)), np.zeros((35, 3)))
    with pytest.raises(ValueError, match=r"position_error must have shape \(2, 3, 2, 3\)"):
        trackcal.TrilinearLutCorrection([0, 1], [0, 1, 2], [0, 1], np.zeros((2, 2, 3, 3)),
                                        np.zeros((2, 3, 2, 3)))


def test_accepts_other_dtypes_and_layouts():
    cal = trackcal.Calibration.load(EXAMPLE)
    rng = np.random.default_rng(3)
    positions, quats = random_poses(rng, 10)
    expected = cal.correct(positions, quats)
    got = cal.correct(np.asfortranarray(positions.astype(np.float32).astype(np.float64)),
                      quats.tolist())
    np.testing.assert_allclose(got[0], cal.correct(positions.astype(np.float32).astype(np.float64), quats)[0])
    np.testing.assert_allclose(got[1], expected[1], atol=1e-15)
    empty = cal.correct(np.zeros((0, 3)), np.zeros((0, 4)))
    assert empty[0].shape == (0, 3) and empty[1].shape == (0, 4) and empty[2].shape == (0,)


def test_values_that_are_not_real_numbers_are_a_type_error_naming_the_argument():
    """float64 conversion dropped a complex array's imaginary parts (with a ComplexWarning at most)
    and turned datetime64 / timedelta64 values into counts of their unit: a corrected pose or a
    fit from values that were never positions. Now a TypeError naming the argument and the dtype;
    real dtypes (int, float32, big-endian, object arrays of numbers) still convert."""
    cal = trackcal.Calibration.load(EXAMPLE)
    positions, quats = random_poses(np.random.default_rng(4), 6)
    expected = cal.correct(positions, quats)
    for bad in (positions + 1e-3j, positions.astype("M8[ns]"), positions.astype("m8[s]"),
                [[1 + 1j, 0, 0]] * 6):
        with pytest.raises(TypeError, match=r"positions must hold real numbers, got an array of dtype"):
            cal.correct(bad, quats)
    with pytest.raises(TypeError, match=r"quaternions_xyzw must hold real numbers.*complex128"):
        cal.correct(positions, quats.astype(complex))
    with pytest.raises(TypeError, match=r"a_xyzw must hold real numbers"):
        trackcal.angular_distance(np.array([0, 0, 0, 1], dtype=complex), [0, 0, 0, 1])
    for ok in (positions.astype(">f8"), positions.astype(object)):
        np.testing.assert_array_equal(cal.correct(ok, quats)[0], expected[0])


def test_repr_of_a_term_says_what_it_is():
    """A term's repr named only its address ("<trackcal._core.PolynomialCorrection object at
    0x7f...>"): cal.corrections in a notebook said nothing of the degree or the grid."""
    poly = trackcal.PolynomialCorrection(2, np.zeros((10, 3)), np.zeros((10, 3)),
                                         input_offset=(0.0, 0.0, 0.3), input_scale=(0.5, 0.5, 0.25))
    assert repr(poly) == "PolynomialCorrection(degree=2, input_offset=[0, 0, 0.3], input_scale=[0.5, 0.5, 0.25])"
    zeros = np.zeros((2, 3, 4, 3))
    lut = trackcal.TrilinearLutCorrection([0.1, 0.9], [-0.5, 0.0, 0.5], [0.0, 0.1, 0.2, 0.3], zeros, zeros)
    cal = trackcal.Calibration([poly, lut], (-1, -1, -1), (1, 1, 1))
    assert [repr(c) for c in cal.corrections] == [
        repr(poly), "TrilinearLutCorrection(2 x 3 x 4 nodes, x 0.1..0.9 m, y -0.5..0.5 m, z 0..0.3 m)"]


def test_error_magnitudes_refuse_a_zero_quaternion():
    """The Table 1 errors (validation.residuals, _core.error_magnitudes): a zero quaternion stayed
    zero through normalisation and its orientation error came out 0 deg, a perfect station."""
    from trackcal import validation
    rng = np.random.default_rng(5)
    positions, quats = random_poses(rng, 4)
    ok = validation.residuals(positions, quats, positions, quats)
    np.testing.assert_array_equal(ok.orientation_deg, np.zeros(4))
    bad = quats.copy()
    bad[2] = 0.0
    with pytest.raises(ValueError, match=r"estimated_quaternions_xyzw: row 2 is zero, not a rotation"):
        validation.residuals(positions, bad, positions, quats)
    with pytest.raises(ValueError, match=r"reference_quaternions_xyzw: row 2 is zero, not a rotation"):
        validation.residuals(positions, quats, positions, bad)


def test_a_calibration_pickles_and_deep_copies_to_the_same_correction():
    """A validation script's process pool pickles the calibration it hands out; a Calibration was
    not picklable ("cannot pickle 'trackcal._core.Calibration' object")."""
    import copy
    import pickle
    cal = trackcal.Calibration.load(EXAMPLE)
    rng = np.random.default_rng(7)
    positions, quats = random_poses(rng, 20)
    for other in (pickle.loads(pickle.dumps(cal)), copy.deepcopy(cal)):
        assert other.to_json() == cal.to_json()
        for a, b in zip(other.correct(positions, quats), cal.correct(positions, quats)):
            np.testing.assert_array_equal(a, b)


def test_a_correction_term_pickles_to_the_same_term():
    """cal.corrections[0] did not pickle ("cannot pickle 'trackcal._core.PolynomialCorrection'
    object") while the Calibration holding it did; a term goes through its file entry, as the
    calibration through its file text, and comes back of its own class."""
    import copy
    import pickle
    cal = trackcal.Calibration.load(EXAMPLE)
    positions, quats = random_poses(np.random.default_rng(9), 20)
    for term in cal.corrections:
        for other in (pickle.loads(pickle.dumps(term)), copy.deepcopy(term)):
            assert type(other) is type(term) and other.to_json() == term.to_json()
            for a, b in zip(other.correct(positions, quats), term.correct(positions, quats)):
                np.testing.assert_array_equal(a, b)
    # A term of a class not bound by itself (a physical one) comes back as a Correction of its type.
    physical = {"type": "physical", "field_constant": 1.0, "fold_reach": 3.0, "max_correction_fraction": 0.5,
                "max_iterations": 50, "max_noise_gain": 10.0, "objects": [], "planes": [],
                "receiver_from_body": {"rotation_xyzw": [0, 0, 0, 1], "translation": [0.01, -0.02, 0.03]},
                "receiver_gain_matrix": np.eye(3).tolist(), "tolerance_m": 1e-12,
                "transmitter_octupole_m2": [0, 0, 0]}
    term = trackcal.Calibration.from_json(json.dumps({**json.loads(EXAMPLE.read_text()),
                                                      "corrections": [physical]})).corrections[0]
    other = pickle.loads(pickle.dumps(term))
    assert repr(other) == repr(term) == "Correction(type='physical')" and other.to_json() == term.to_json()
    for a, b in zip(other.correct(positions, quats), term.correct(positions, quats)):
        np.testing.assert_array_equal(a, b)


def test_assigning_a_sensor_outside_the_file_rules_is_refused_at_once(tmp_path):
    """cal.sensor = -3 (or 65) was accepted and refused only by a later save(), naming no
    assignment; the rule is the calibration file's (0: not recorded, or 1..64)."""
    cal = trackcal.Calibration.load(EXAMPLE)
    for bad in (-3, 65, 2**70):
        with pytest.raises(ValueError, match=r"^Calibration\.sensor must be 0 \(not recorded\) or 1\.\.64 "):
            cal.sensor = bad
        assert cal.sensor == 0  # unchanged
    for bad in (2.0, "2", True, None):
        with pytest.raises(TypeError, match=r"^Calibration\.sensor must be an integer"):
            cal.sensor = bad
    cal.sensor = np.int64(3)  # a capture's sensor column is numpy's
    assert cal.sensor == 3 and type(cal.sensor) is int
    cal.sensor = 64
    cal.save(tmp_path / "c.json")
    assert trackcal.Calibration.load(tmp_path / "c.json").sensor == 64


def test_correct_refuses_a_zero_quaternion():
    """Calibration.correct and Correction.correct of a zero quaternion returned a zero quaternion
    with status converged; NaN rows (dropped samples) still pass through as NaN."""
    cal = trackcal.Calibration.load(EXAMPLE)
    rng = np.random.default_rng(6)
    positions, quats = random_poses(rng, 3)
    bad = quats.copy()
    bad[1] = 0.0
    for target in (cal, cal.corrections[0]):
        with pytest.raises(ValueError, match=r"quaternions_xyzw: row 1 is zero, not a rotation"):
            target.correct(positions, bad, return_status=True)
    nan = quats.copy()
    nan[1] = np.nan
    _, q, _ = cal.correct(positions, nan)
    assert np.isnan(q[1]).all() and np.isfinite(q[[0, 2]]).all()


def test_correct_normalises_a_nearly_unit_quaternion_and_refuses_one_that_is_not():
    """The terms keep a quaternion's norm: [0, 0, 0, 2] came back with norm 2, and 1.0005 with
    1.0005. As a capture file is read (core/capture.cc): within 1e-3 of 1 the row is normalised,
    further it is no rotation (ValueError naming the row); unit rows are corrected bit for bit as
    before."""
    cal = trackcal.Calibration.load(EXAMPLE)
    positions, quats = random_poses(np.random.default_rng(8), 4)
    for target in (cal, cal.corrections[0]):
        for scale in (2.0, 0.5, 1.0 + 1.5e-3):
            bad = quats.copy()
            bad[2] *= scale
            with pytest.raises(ValueError, match=rf"^quaternions_xyzw: row 2 has norm {scale:g}, not 1"):
                target.correct(positions, bad)
        near = quats.copy()
        near[1] *= 1.0 + 9e-4
        near[3] *= 1.0 - 9e-4
        p_near, q_near, _ = target.correct(positions, near)
        p_unit, q_unit, _ = target.correct(positions, quats)
        # 1e-12: the rounding of the division by the norm, carried through one correction.
        np.testing.assert_allclose(np.linalg.norm(q_near, axis=1), 1.0, rtol=0, atol=1e-12)
        np.testing.assert_allclose(q_near, q_unit, rtol=0, atol=1e-12)
        np.testing.assert_allclose(p_near, p_unit, rtol=0, atol=1e-12)
        np.testing.assert_array_equal(q_near[[0, 2]], q_unit[[0, 2]])  # untouched rows: same bits


def test_correct_refuses_an_infinite_value():
    """[0, 0, 0, inf] came back as [-inf, -inf, -inf, inf] without a word; an infinite position
    came back infinite. Neither is a pose (a dropped sample is NaN)."""
    cal = trackcal.Calibration.load(EXAMPLE)
    positions, quats = random_poses(np.random.default_rng(7), 3)
    inf_q = quats.copy()
    inf_q[2] = [0.0, 0.0, 0.0, np.inf]
    inf_p = positions.copy()
    inf_p[0, 1] = -np.inf
    for target in (cal, cal.corrections[0]):
        with pytest.raises(ValueError, match=r"^quaternions_xyzw: row 2 holds an infinite value"):
            target.correct(positions, inf_q)
        with pytest.raises(ValueError, match=r"^positions: row 0 holds an infinite value"):
            target.correct(inf_p, quats)


def test_file_errors_are_value_errors_naming_path(tmp_path):
    doc = json.loads(EXAMPLE.read_text())
    doc["corrections"][0]["position_coefficients"].pop()
    bad = tmp_path / "calib.json"
    text = json.dumps(doc, indent=2)
    bad.write_text(text)
    with pytest.raises(ValueError) as info:
        trackcal.Calibration.load(bad)
    # The line and column of the field's key, as the C++ tools print them (one reader).
    before = text[:text.index('"position_coefficients"')]
    line, column = before.count("\n") + 1, len(before) - before.rfind("\n")
    assert str(info.value) == (f"{bad}:{line}:{column}: $.corrections[0].position_coefficients: degree 2 "
                               "needs 10 entries, got 9")
    with pytest.raises(ValueError, match=r"missing\.json: cannot open"):
        trackcal.Calibration.load(tmp_path / "missing.json")
    doc = json.loads(EXAMPLE.read_text())
    doc["version"] = 2
    with pytest.raises(ValueError, match=r"<string>:1:[0-9]+: \$\.version: unsupported version 2"):
        trackcal.Calibration.from_json(json.dumps(doc))
    # Python's json writes NaN literals; the reader names them.
    doc = json.loads(EXAMPLE.read_text())
    doc["calibrated_volume"]["fade_distance"] = float("nan")
    with pytest.raises(ValueError, match="non-finite number"):
        trackcal.Calibration.from_json(json.dumps(doc), "nan.json")


def test_a_file_that_is_not_utf8_is_a_value_error_naming_it(tmp_path):
    """A description typed in a Latin-1 editor, or Notepad's "Unicode" (UTF-16) save: the parser's
    message quoted the raw byte and became a UnicodeDecodeError on its way to Python, "'utf-8' codec
    can't decode byte 0xfc in position 191", naming no file (trackcal validate -c printed just that)."""
    text = EXAMPLE.read_text().replace("Example", "f\u00fcr lab")
    latin1 = tmp_path / "latin1.json"
    latin1.write_bytes(text.encode("latin-1"))
    with pytest.raises(ValueError) as info:
        trackcal.Calibration.load(latin1)
    assert type(info.value) is ValueError  # not its subclass UnicodeDecodeError
    assert str(info.value).startswith(f"{latin1}:4:20: invalid JSON: ")
    assert "ill-formed UTF-8 byte; last read: '\"f\\xfc'" in str(info.value)
    utf16 = tmp_path / "utf16.json"
    utf16.write_bytes(("\ufeff" + EXAMPLE.read_text()).encode("utf-16-le"))
    with pytest.raises(ValueError) as info:
        trackcal.Calibration.load(utf16)
    assert str(info.value) == f"{utf16}: UTF-16 text (a byte order mark FF FE or FE FF); save the calibration file as UTF-8"


def test_an_empty_calibration_file_is_a_value_error_saying_so(tmp_path):
    """An empty file (an interrupted save) got the JSON parser's "unexpected end of input"."""
    for name, data in (("empty.json", b""), ("blank.json", b"\n  \n")):
        path = tmp_path / name
        path.write_bytes(data)
        with pytest.raises(ValueError) as info:
            trackcal.Calibration.load(path)
        assert str(info.value).startswith(f"{path}: empty file")
        assert "unexpected end of input" not in str(info.value)


def test_build_save_load_round_trip(tmp_path):
    rng = np.random.default_rng(4)
    pc, oc = degree4(rng)
    poly = trackcal.PolynomialCorrection(4, pc, oc, (0, 0, 0.3), (0.5, 0.5, 0.5))
    x = np.linspace(-0.5, 0.5, 5)
    y = np.array([-0.5, -0.1, 0.0, 0.5])
    z = np.linspace(-0.2, 0.8, 3)
    pe = rng.normal(scale=0.001, size=(5, 4, 3, 3))
    oe = rng.normal(scale=0.001, size=(5, 4, 3, 3))
    lut = trackcal.TrilinearLutCorrection(x, y, z, pe, oe)
    np.testing.assert_array_equal(lut.position_error, pe)
    capture = tmp_path / "capture.csv"
    capture.write_text("t,x\n0,1\n")
    provenance = {
        "tool": "pytest",
        "tool_version": trackcal.__version__,
        "created_utc": "2026-11-21T12:00:00Z",
        "inputs": [{"path": str(capture), "sha256": trackcal.sha256_file(capture),
                    "role": "calibration_capture"}],
    }
    cal = trackcal.Calibration([poly, lut], (-0.5, -0.5, -0.2), (0.5, 0.5, 0.8), "fade", 0.1,
                               description="round trip", fit_statistics={"num_samples": 12},
                               provenance=provenance)
    out = tmp_path / "calib.json"
    cal.save(out)
    back = trackcal.Calibration.load(out)
    assert back.to_json() == cal.to_json() == out.read_text()
    assert back.description == "round trip"
    positions, quats = random_poses(rng, 500, half_extent=0.7)
    a = cal.correct(positions, quats)
    b = back.correct(positions, quats)
    for x_a, x_b in zip(a, b):
        np.testing.assert_array_equal(x_a, x_b)
    assert a[2].any() and not a[2].all()
    # The chain applies the polynomial, then the LUT to its output.
    p1, q1, _ = poly.correct(positions, quats)
    p2, q2, _ = lut.correct(p1, q1)
    inside = ~a[2]
    np.testing.assert_allclose(a[0][inside], p2[inside], atol=1e-15)
    # Never overwrites an input.
    with pytest.raises(ValueError, match="refusing to overwrite input file"):
        cal.save(capture)
    assert capture.read_text() == "t,x\n0,1\n"


def test_save_refuses_a_read_only_file_and_keeps_the_mode_of_one_it_replaces(tmp_path):
    """A calibration kept with chmod a-w was replaced by the next save over it (a rename needs only
    the folder to be writable), and a file replaced got the umask's mode (0664 became 0644)."""
    cal = trackcal.Calibration.load(EXAMPLE)
    kept = tmp_path / "kept.json"
    cal.save(kept)
    before = kept.read_bytes()
    kept.chmod(0o444)
    with pytest.raises(ValueError, match=r"kept\.json: is read-only; refusing to replace it"):
        cal.save(kept)
    assert kept.read_bytes() == before
    with pytest.raises(ValueError, match="is read-only"):
        trackcal._core.check_calibration_output(kept)  # what trackcal fit -o checks before fitting
    shared = tmp_path / "shared.json"
    cal.save(shared)
    for mode in (0o664, 0o600):
        shared.chmod(mode)
        cal.save(shared)
        assert shared.stat().st_mode & 0o7777 == mode


def test_constructor_errors():
    poly = trackcal.PolynomialCorrection(0, np.zeros((1, 3)), np.zeros((1, 3)))
    with pytest.raises(ValueError, match="empty volume"):
        trackcal.Calibration([poly], (0, 0, 0), (1, 0, 1))
    with pytest.raises(ValueError, match="unknown policy \"hold\""):
        trackcal.Calibration([poly], (0, 0, 0), (1, 1, 1), extrapolation="hold")
    with pytest.raises(ValueError, match="fade_distance must be positive"):
        trackcal.Calibration([poly], (0, 0, 0), (1, 1, 1), extrapolation="fade")
    with pytest.raises(ValueError, match="polynomial degree must be in"):
        trackcal.PolynomialCorrection(13, np.zeros((1, 3)), np.zeros((1, 3)))
    with pytest.raises(ValueError, match="input_scale must be positive"):
        trackcal.PolynomialCorrection(0, np.zeros((1, 3)), np.zeros((1, 3)), input_scale=(1, 0, 1))
    with pytest.raises(ValueError, match="strictly increasing"):
        trackcal.TrilinearLutCorrection([0, 1], [1, 0], [0, 1], np.zeros((2, 2, 2, 3)),
                                        np.zeros((2, 2, 2, 3)))
    with pytest.raises(ValueError, match="fit_statistics must be JSON-serialisable"):
        trackcal.Calibration([poly], (0, 0, 0), (1, 1, 1), fit_statistics={"rms": math.nan})
    with pytest.raises(ValueError, match=r"provenance: \$\.tool_version: missing required field"):
        trackcal.Calibration([poly], (0, 0, 0), (1, 1, 1),
                             provenance={"tool": "x", "created_utc": "2026-01-01T00:00:00Z",
                                         "inputs": []})


def test_term_exponents_match_reference_order():
    for r in range(0, 9):
        np.testing.assert_array_equal(trackcal.polynomial_term_exponents(r),
                                      numpy_reference.term_exponents(r))
        assert trackcal.num_polynomial_terms(r) == (r + 1) * (r + 2) * (r + 3) // 6
    for bad in (-1, -5, 13):  # -5 gave -4 terms: the degrees polynomial_term_exponents refuses
        with pytest.raises(ValueError, match="degree must be in"):
            trackcal.num_polynomial_terms(bad)


def test_lut_exact_at_nodes_and_flags_outside_grid():
    rng = np.random.default_rng(5)
    x, y, z = np.linspace(-0.5, 0.5, 4), np.array([-0.3, 0.0, 0.4]), np.linspace(0.0, 0.6, 3)
    pe = rng.normal(scale=0.01, size=(4, 3, 3, 3))
    oe = rng.normal(scale=0.01, size=(4, 3, 3, 3))
    lut = trackcal.TrilinearLutCorrection(x, y, z, pe, oe)
    grid = np.stack(np.meshgrid(x, y, z, indexing="ij"), axis=-1).reshape(-1, 3)
    identity = np.tile([0.0, 0.0, 0.0, 1.0], (len(grid), 1))
    p, q, flags = lut.correct(grid, identity)
    # Node weights are exactly 0 and 1; only the addition p + e and its subtraction round.
    np.testing.assert_allclose(p - grid, pe.reshape(-1, 3), rtol=0, atol=1e-16)
    np.testing.assert_allclose(q[:, :3], oe.reshape(-1, 3), atol=1e-17)
    assert not flags.any()
    _, _, flags = lut.correct([[0.0, 0.0, 0.7], [0.0, 0.0, 0.3]], [[0, 0, 0, 1]] * 2)
    assert flags.tolist() == [True, False]


def physical_calibration(volume_min=(-0.8, -0.6, -0.8), volume_max=(0.8, 0.6, -0.35)):
    """A calibration whose only term is a physical model: the paper room's floor and its toolbox
    (a ferromagnetic object 0.126 m in radius at (0.6, 0.95, -0.5) m)."""
    doc = json.loads(EXAMPLE.read_text())
    doc["calibrated_volume"] = {"min": list(volume_min), "max": list(volume_max), "extrapolation": "clamp",
                               "fade_distance": 0.0}
    doc["corrections"] = [{
        "type": "physical", "field_constant": 1.0, "transmitter_octupole_m2": [0, 0, 0],
        "planes": [{"name": "floor", "point_in_transmitter": [0, 0, 0.8], "normal_in_transmitter": [0, 0, 1],
                    "attenuation": 0.27}],
        "objects": [{"name": "toolbox", "location_in_transmitter": [0.6, 0.95, -0.5], "polarisability_m3": 0.002}],
        "receiver_gain_matrix": [[1, 0, 0], [0, 1, 0], [0, 0, 1]]}]
    return trackcal.Calibration.from_json(json.dumps(doc))


def test_correct_reports_the_status_of_the_model_inverse():
    cal = physical_calibration()
    toolbox = np.array([0.6, 0.95, -0.5])
    # Reports away from the object (the volume's far corner and centre), on the object (no true pose:
    # the receiver would be inside it), and along a line towards it through its fold zone, where a
    # report has a second true pose or its noise is amplified more than 10 times.
    positions = [[-0.6, -0.4, -0.5], [0.0, 0.0, -0.6], toolbox.tolist()]
    positions += [(toolbox - d * np.array([0.0, 1.0, 0.0])).tolist() for d in np.linspace(0.13, 0.4, 28)]
    positions = np.array(positions)
    quats = np.tile([0.0, 0.0, 0.0, 1.0], (len(positions), 1))
    p, q, extrapolated, status = cal.correct(positions, quats, return_status=True)
    assert status.dtype == np.uint8 and status.shape == (len(positions),)
    names = [trackcal.correction_status_names[s] for s in status]
    assert names[:3] == ["converged", "converged", "not_converged"]
    assert "ambiguous" in names[3:]
    counts = trackcal.status_counts(status)
    assert sum(counts.values()) == len(positions)
    assert counts == {n: names.count(n) for n in trackcal.correction_status_names}
    # The default call keeps its three arrays and the same poses.
    p3, q3, e3 = cal.correct(positions, quats)
    np.testing.assert_array_equal(p3, p)
    np.testing.assert_array_equal(e3, extrapolated)
    # The term alone (no volume) and the chain's per-pose path for poses outside the volume (every
    # pose here but the first two is outside it) agree with the batch path.
    _, _, _, term_status = cal.corrections[0].correct(positions, quats, return_status=True)
    np.testing.assert_array_equal(term_status, status)
    inside = physical_calibration(volume_min=(-1.0, -1.0, -1.0), volume_max=(1.0, 1.0, 0.0))
    np.testing.assert_array_equal(inside.correct(positions, quats, return_status=True)[3], status)


def test_status_of_terms_without_an_inverse_is_converged():
    cal = trackcal.Calibration.load(EXAMPLE)
    rng = np.random.default_rng(4)
    positions, quats = random_poses(rng, 50)
    _, _, _, status = cal.correct(positions, quats, return_status=True)
    assert trackcal.status_counts(status) == {"converged": 50, "ambiguous": 0, "not_converged": 0}
    with pytest.raises(ValueError, match="status codes"):
        trackcal.status_counts([0, 3])


@pytest.mark.parametrize("bad", [[0.5, 1.7], [np.nan], ["ambiguous"]])
def test_status_counts_refuses_codes_that_are_not_status_codes(bad):
    """1.7 was truncated and counted as ambiguous, NaN failed inside bincount ('no negative
    elements') and text with a numpy type error: each is an unknown code, named."""
    with pytest.raises(ValueError, match=r"status code .*: status codes must be 0\.\.2"):
        trackcal.status_counts(bad)
    assert trackcal.status_counts(np.array([0.0, 2.0])) == {"converged": 1, "ambiguous": 0, "not_converged": 1}


def test_status_counts_takes_an_object_array_of_codes():
    """An object array of valid codes (as pandas gives) raised StopIteration from the check."""
    counts = trackcal.status_counts(np.array([0, 1, 1], dtype=object))
    assert counts == {"converged": 1, "ambiguous": 2, "not_converged": 0}


def _run_correction_xyzw(doc, positions, quats):
    """(N, 6) correction (e_p, vector part of q_e) of the example's explicit chain (polynomial, then
    trilinear LUT) at positions inside its box, from the formulas of docs/calibration-file.md."""
    poly, lut = doc["corrections"]
    p, q = numpy_reference.correct_polynomial(
        poly["degree"], np.array(poly["position_coefficients"]),
        np.array(poly["orientation_coefficients"]), poly["input_offset"], poly["input_scale"],
        positions, quats)
    axes = [np.array(lut["axes"][k]) for k in "xyz"]
    shape = tuple(len(a) for a in axes) + (3,)
    nodes = [np.array(lut["position_error"]).reshape(shape), np.array(lut["orientation_error"]).reshape(shape)]
    e_p, v = np.zeros_like(p), np.zeros_like(p)
    for n, x in enumerate(p):
        x = np.clip(x, [a[0] for a in axes], [a[-1] for a in axes])  # outside the grid: held
        cell = [min(np.searchsorted(a, c, side="right") - 1, len(a) - 2) for a, c in zip(axes, x)]
        frac = [(c - a[i]) / (a[i + 1] - a[i]) for a, c, i in zip(axes, x, cell)]
        for corner in np.ndindex(2, 2, 2):
            w = np.prod([f if b else 1.0 - f for f, b in zip(frac, corner)])
            index = tuple(i + b for i, b in zip(cell, corner))
            e_p[n] += w * nodes[0][index]
            v[n] += w * nodes[1][index]
    p = p + e_p
    q = numpy_reference.quaternion_multiply_xyzw(numpy_reference.quaternion_from_vector_part(v), q)
    return np.concatenate([p - positions, numpy_reference.orientation_error_vectors(q, quats)], axis=1)


def test_linear_extrapolation_follows_the_documented_formula_on_low_and_high_faces():
    # docs/calibration-file.md, `linear`: c(p) = c(p_b) + sum_k dc/dx_k (p_k - p_b,k) min(1, reach/d)
    # with the one-sided derivative from inside the box. Its first writing took the outward
    # difference for dc/dx_k, which turns the continuation around on the low faces (35 mm and
    # 3 degrees off the served pose for a degree-4 fit): checked here on both sides of every axis.
    doc = json.loads(EXAMPLE.read_text())
    doc["calibrated_volume"].update(extrapolation="linear", linear_reach=0.1)
    cal = trackcal.Calibration.from_json(json.dumps(doc))
    lo, hi = np.array(doc["calibrated_volume"]["min"]), np.array(doc["calibrated_volume"]["max"])
    rng = np.random.default_rng(7)
    inside, quats = lo + (hi - lo) * rng.uniform(size=(60, 3)), random_poses(rng, 60)[1]
    positions = inside.copy()
    for n in range(60):  # out through a low or a high face (or two), 0 .. 0.3 m
        axis, side = n % 3, (n // 3) % 2
        positions[n, axis] = (hi if side else lo)[axis] + (1 if side else -1) * rng.uniform(0.0, 0.3)
        if n % 4 == 0:
            positions[n, (axis + 1) % 3] = lo[(axis + 1) % 3] - rng.uniform(0.0, 0.05)
    p_b = np.clip(positions, lo, hi)
    d = np.linalg.norm(positions - p_b, axis=1)
    c0 = _run_correction_xyzw(doc, p_b, quats)
    c = c0.copy()
    h = np.minimum(1e-3, (hi - lo) / 10.0)
    for k in range(3):
        s = np.sign(positions[:, k] - p_b[:, k])  # outward sign, 0 where inside on k
        e = np.zeros(3)
        e[k] = 1.0
        c1 = _run_correction_xyzw(doc, p_b - (s * h[k])[:, None] * e, quats)
        c2 = _run_correction_xyzw(doc, p_b - (2.0 * s * h[k])[:, None] * e, quats)
        dc_dx = s[:, None] * (3.0 * c0 - 4.0 * c1 + c2) / (2.0 * h[k])  # s = 1 / s: d/dx_k itself
        c = c + dc_dx * ((positions[:, k] - p_b[:, k]) * np.minimum(1.0, 0.1 / np.maximum(d, 1e-300)))[:, None]
    p_doc = positions + c[:, :3]
    q_doc = numpy_reference.quaternion_multiply_xyzw(numpy_reference.quaternion_from_vector_part(c[:, 3:]), quats)
    p, q, extrapolated = cal.correct(positions, quats)
    assert extrapolated.all()
    # Same formulas, other summation orders: rounding of ~1e-3 corrections, amplified by 1 / 2h
    # (h = 1 mm) in the derivatives: ~1e-16 / 1e-3 * 0.1 m.
    np.testing.assert_allclose(p, p_doc, rtol=0, atol=1e-12)
    assert rotation_angles(q, q_doc).max() < 1e-7  # arccos of |dot| near 1 resolves only ~1e-8
