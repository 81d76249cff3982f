"""Validation and diagnosis of every kind of capture a lab brings (docs/understand.md): a poses.csv, a
folder of streams (paired by time, with the receiver's speed as a covariate), and per-station
residuals (``--residuals`` and the ``stations`` of ``diagnose --json``)."""

import json
import pathlib
import re
import shutil
import subprocess
import sys

import numpy as np
import pytest

import trackcal
from trackcal import captures, validation
from understand_support import simulate, stream_only


def run_cli(*args, check=True):
    exe = shutil.which("trackcal")
    cmd = [exe] if exe else [sys.executable, "-m", "trackcal.cli"]
    r = subprocess.run(cmd + [str(a) for a in args], capture_output=True, text=True, timeout=600)
    if check:
        assert r.returncode == 0, r.stderr
    return r


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    """A paper capture (poses, markers and streams) and a folder holding its two streams only."""
    tmp = tmp_path_factory.mktemp("kinds")
    cap_dir = simulate(tmp / "capture", seed=51)
    streams = stream_only(cap_dir, tmp / "streams")
    cal = tmp / "cal.json"
    validation.fit_polynomial(captures.load_poses(cap_dir).select_set("calib"), degree=3).save(cal)
    return cap_dir, streams, cal


def test_load_pairs_streams_and_keeps_their_speed(sim):
    _, streams, _ = sim
    cap = captures.load(streams, time_offset=0.0)
    pairing = trackcal.pair(streams / "tracker_stream.csv", streams / "reference_stream.csv")
    assert cap.origin["kind"] == "streams" and cap.origin["time_offset_source"] == "given"
    assert len(cap) == len(pairing.poses) > 1000
    np.testing.assert_array_equal(cap.reported_positions, pairing.poses.reported_positions)
    # The simulated receiver moves smoothly at walking-hand speeds: 0 < v < 2 m/s at every sample.
    assert cap.speed.shape == (len(cap),) and 0 < np.median(cap.speed) < 2.0
    assert "speed" in validation.covariates(cap)
    # Without an offset it is estimated; the paper scene has no clock offset (|offset| < 5 ms, the
    # pairing's error on this scene is ~1 ms, docs/fit.md).
    est = captures.load(streams)
    assert est.origin["time_offset_source"] == "estimated" and abs(est.origin["time_offset_s"]) < 5e-3


def test_stream_extra_columns_become_covariates_of_the_paired_stations(sim, tmp_path):
    # A temperature logged beside every tracker sample: each paired station carries it at its time,
    # as a poses.csv's extra column would be.
    _, streams, _ = sim
    folder = tmp_path / "logged"
    folder.mkdir()
    shutil.copy(streams / "reference_stream.csv", folder / "reference_stream.csv")
    lines = (streams / "tracker_stream.csv").read_text().splitlines()
    time_col = lines[0].split(",").index("time")
    out = [lines[0] + ",temperature"]
    for line in lines[1:]:
        out.append(f"{line},{20.0 + 0.1 * float(line.split(',')[time_col]):.6f}")
    (folder / "tracker_stream.csv").write_text("\n".join(out) + "\n")
    cap = captures.load(folder, time_offset=0.0)
    assert cap.extra_columns == ["temperature"]
    # Paired samples are tracker samples: the value is the one logged at that time (linear in it).
    np.testing.assert_allclose(cap.extra[:, 0], 20.0 + 0.1 * cap.time, atol=1e-6)
    assert "temperature" in validation.covariates(cap)


def _with_columns(source, target, names: str, values) -> None:
    """Copies a stream CSV with columns `names` appended, `values(time)` giving each row's text."""
    lines = source.read_text().splitlines()
    time_col = lines[0].split(",").index("time")
    out = [lines[0] + "," + names] + [f"{line},{values(float(line.split(',')[time_col]))}" for line in lines[1:]]
    target.write_text("\n".join(out) + "\n")


def test_reference_stream_columns_and_labels_reach_the_paired_stations(sim, tmp_path):
    # The optical system logs a per-frame marker residual (numbers) and the tracking state (labels);
    # the tracker logs which operator held the probe (labels) and its own state under the same name.
    # Each paired station carries them at its instant: tracker columns at its time, reference ones at
    # time + offset on the reference clock (the offset here is 20 ms, set when pairing).
    _, streams, _ = sim
    folder = tmp_path / "logged"
    folder.mkdir()
    _with_columns(streams / "reference_stream.csv", folder / "reference_stream.csv", "marker_rms_mm,state",
                  lambda t: f"{0.1 + 0.01 * t:.9f},{'good' if int(t) % 2 == 0 else 'partial'}")
    _with_columns(streams / "tracker_stream.csv", folder / "tracker_stream.csv", "operator,state",
                  lambda t: f"{'alice' if t < 10 else 'bob'},ok")
    offset = 0.02
    cap = captures.load(folder, time_offset=offset)
    assert cap.extra_columns == ["operator", "state", "marker_rms_mm", "reference_state"]
    assert cap.extra_labels == {"operator": ["alice", "bob"], "state": ["ok"],
                                "reference_state": ["good", "partial"]}
    # Linear in reference time: interpolated at time + offset (not at the tracker time: 2e-4 apart).
    np.testing.assert_allclose(cap.column("marker_rms_mm"), 0.1 + 0.01 * (cap.time + offset), atol=1e-7)
    # Labels are those of the nearest sample (away from the switch instants, where nearest is ambiguous).
    away = np.abs((cap.time + offset) - np.round(cap.time + offset)) > 0.05
    expected = np.where(np.floor(cap.time + offset).astype(int) % 2 == 0, "good", "partial")
    assert list(cap.column("reference_state")[away]) == list(expected[away])
    assert set(cap.column("operator")[cap.time < 9.9]) == {"alice"}
    covs = validation.covariates(cap)
    assert {"operator", "marker_rms_mm", "reference_state"} <= set(covs)
    # The live-recording validation carries them the same way.
    v = validation.validate_recording(folder / "tracker_stream.csv", folder / "reference_stream.csv",
                                      time_offset=offset)
    assert v.capture.extra_columns == cap.extra_columns


def _drifting(streams, folder):
    """The streams with the reference clock 1000 ppm fast (as test_fit_binding's drift test), and
    a reference column frame_time holding the reference time itself."""
    folder.mkdir()
    shutil.copy(streams / "tracker_stream.csv", folder / "tracker_stream.csv")
    lines = (streams / "reference_stream.csv").read_text().splitlines()
    time_col = lines[0].split(",").index("time")
    t0 = float(lines[1].split(",")[time_col])
    out = [lines[0] + ",frame_time"]
    for line in lines[1:]:
        cells = line.split(",")
        t = t0 + (float(cells[time_col]) - t0) * 1.001
        cells[time_col] = repr(t)
        out.append(",".join(cells) + f",{t!r}")
    (folder / "reference_stream.csv").write_text("\n".join(out) + "\n")
    return folder


def test_reference_stream_columns_follow_a_corrected_clock_drift(sim, tmp_path):
    # The pairing corrects the drift, pairing the sample at t with the reference at t + offset +
    # drift (t - origin). The reference's own columns were still taken at t + offset: frame_time
    # was up to 14.5 ms (drift * span / 2) off the instant the pose was paired at.
    _, streams, _ = sim
    folder = _drifting(streams, tmp_path / "drifting")
    with pytest.warns(UserWarning, match="the clocks drift: .*; corrected"):
        pairing = trackcal.pair(folder / "tracker_stream.csv", folder / "reference_stream.csv",
                                estimate_time_offset=True)
    assert pairing.clock_drift_corrected
    paired_at = (pairing.poses.time + pairing.time_offset_s
                 + pairing.clock_drift_applied * (pairing.poses.time - pairing.clock_drift_origin_s))
    cap = captures.load(folder)
    np.testing.assert_array_equal(cap.time, pairing.poses.time)
    # frame_time is linear in the reference time: interpolated exactly where the pose was paired.
    np.testing.assert_allclose(cap.column("frame_time"), paired_at, rtol=0, atol=1e-9)
    v = validation.validate_recording(folder / "tracker_stream.csv", folder / "reference_stream.csv")
    np.testing.assert_allclose(v.capture.column("frame_time"), paired_at, rtol=0, atol=1e-9)


def test_validate_pairs_at_the_fitted_offset_with_the_corrected_drift(sim, tmp_path, capsys):
    # A fit of drifting streams with a fitted clock offset pairs them with the drift corrected, and
    # its calibration records the offset at the middle of the stream (fit_statistics.time_offset_s).
    # trackcal validate -c paired the same streams at that offset without the drift: the stream's
    # ends 15 ms off, the calibration's corrected error 4.6 mm mean instead of 1.9 mm (seed 51).
    from trackcal import cli
    _, streams, _ = sim
    folder = _drifting(streams, tmp_path / "drifting")
    report = trackcal.fit(folder, "time_offset: {value: 0.0, fixed: false}\n"
                                  "terms:\n  - type: polynomial\n    degree: 3\n")
    stats = report.calibration.fit_statistics
    assert stats["time_offset_s"] == pytest.approx(0.015, abs=1e-3)
    assert stats["clock_drift"] == pytest.approx(1e-3, abs=5e-5)
    cal = tmp_path / "cal.json"
    report.calibration.save(cal)
    assert cli.main(["validate", str(folder), "-c", str(cal), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    at_calibration = doc["tables"][0]["after_position_mm"]["mean"]
    # The reference paired where the fit paired it: as an estimated pairing (which corrects the
    # drift itself) gives, to the offset's difference (0.1 ms at ~1 m/s: 0.1 mm).
    v = validation.validate(captures.load(folder), report.calibration, analyse_covariates=False)
    estimated = v.tables[0].after_position_mm["mean"]
    assert at_calibration == pytest.approx(estimated, abs=0.2), (at_calibration, estimated)
    cap = captures.load(folder, time_offset=stats["time_offset_s"], clock_drift=stats["clock_drift"],
                        clock_drift_origin_s=stats["clock_drift_origin_s"])
    # Another capture of the same clocks holds the fit's offset at the fit's origin, not at its own
    # middle: the origin given is used.
    at_zero = captures.load(folder, time_offset=0.001, clock_drift=1e-3, clock_drift_origin_s=0.0)
    np.testing.assert_allclose(at_zero.column("frame_time"), at_zero.time + 0.001 + 1e-3 * at_zero.time,
                               rtol=0, atol=1e-9)
    assert re.search(r"time offset of 14\.\d\d ms and a clock drift of 9\d\d\.\d ppm \(given\)",
                     captures.describe_origin(cap)), captures.describe_origin(cap)


def test_capture_folder_without_any_capture_names_what_it_looked_for(tmp_path):
    with pytest.raises(ValueError, match="not a capture folder .*tracker_stream.csv"):
        captures.load(tmp_path)
    r = run_cli("validate", tmp_path, check=False)
    assert r.returncode == 2 and "not a capture folder" in r.stderr
    assert "trackcal record" not in r.stderr


def test_a_folder_with_one_stream_says_so_in_python_and_in_the_fit_engine(tmp_path):
    # trackcal.load said "not a capture folder" and trackcal.fit (the C++ LoadFitData, as
    # trackcal-fit --data) "reference_stream.csv: cannot open file" of the same folder.
    (tmp_path / "tracker_stream.csv").write_text("time,sensor,x,y,z,qw,qx,qy,qz\n0,1,0,0,0,1,0,0,0\n")
    expected = (f"{tmp_path}: not a capture folder (no poses.csv, no tracker_stream.csv + "
                "reference_stream.csv, no markers.csv + tracker.csv); tracker_stream.csv has no "
                "reference_stream.csv beside it to be paired with")
    with pytest.raises(ValueError) as loaded:
        captures.load(tmp_path)
    assert str(loaded.value) == expected
    with pytest.raises(ValueError) as fitted:
        trackcal.fit(tmp_path, "terms:\n  - type: polynomial\n    degree: 1\n")
    assert str(fitted.value) == expected


def test_a_recording_folder_given_as_a_capture_says_how_to_validate_it(tmp_path):
    # `trackcal record -o run1` writes LABEL_tracker_stream.csv per device; `trackcal validate run1`
    # (with the reference stream beside them) said only "not a capture folder", leaving the user
    # to find validate_recording in the docs.
    for label in ("raw", "corrected"):
        (tmp_path / f"{label}_tracker_stream.csv").write_text("time,sensor,x,y,z,qw,qx,qy,qz\n")
    (tmp_path / "reference_stream.csv").write_text("time,x,y,z,qw,qx,qy,qz\n")
    r = run_cli("validate", tmp_path, check=False)
    assert r.returncode == 2 and "not a capture folder" in r.stderr
    assert ("corrected_tracker_stream.csv, raw_tracker_stream.csv: a recording (trackcal record): "
            "validate it against the reference stream with trackcal.validation.validate_recording") in r.stderr


def test_unreadable_capture_files_and_existing_outputs_are_value_errors(tmp_path):
    """docs/python.md: files that cannot be read and outputs that exist are ValueError, like the
    format errors, so a script's `except ValueError` handles every mistake in its input; the C++
    readers' RuntimeError came through for a missing file and an existing recording."""
    missing = tmp_path / "nothing.csv"
    for read in (captures.load_poses, captures.load_tracker_stream, captures.load_reference_stream):
        with pytest.raises(ValueError, match=r"nothing\.csv: cannot open file"):
            read(missing)
    with pytest.raises(ValueError, match=r"poses\.csv: cannot open file"):
        captures.load_poses(tmp_path)  # a folder without poses.csv
    stream = captures.TrackerStream(np.array([0.0]), np.array([1]), np.zeros((1, 3)), np.array([[0.0, 0, 0, 1]]))
    out = tmp_path / "tracker_stream.csv"
    captures.save_tracker_stream(out, stream)
    before = out.read_bytes()
    with pytest.raises(ValueError, match="exists"):
        captures.save_tracker_stream(out, stream)
    assert out.read_bytes() == before


def test_a_pdf_or_utf32_poses_file_or_one_that_cannot_be_opened_says_why(tmp_path):
    """A PDF renamed poses.csv said "column station: missing from the header" (its first line is
    text); UTF-32 was called UTF-16; a file that cannot be opened gave no reason."""
    pdf = tmp_path / "pdf" / "poses.csv"
    pdf.parent.mkdir()
    pdf.write_bytes(b"%PDF-1.7\n%\xe2\xe3\xcf\xd3\n1 0 obj\n<< /Filter /FlateDecode >>\nstream\n"
                    b"x\x9c\xed\x5d\xdb\x8e\xe3\x36\x12\nendstream\n")
    with pytest.raises(ValueError) as info:
        captures.load_poses(pdf.parent)
    assert str(info.value) == (f"{pdf}:1: encoding: a PDF document (the file starts with %PDF-), not a text "
                               "CSV file; export the capture as CSV in UTF-8")
    utf32 = tmp_path / "utf32.csv"
    utf32.write_bytes("\ufeffstation,set\n".encode("utf-32-le"))
    with pytest.raises(ValueError) as info:
        captures.load_poses(utf32)
    assert str(info.value) == (f"{utf32}:1: encoding: UTF-32 text (a byte order mark FF FE 00 00 or "
                               "00 00 FE FF); save the CSV file as UTF-8")
    with pytest.raises(ValueError) as info:
        captures.load_poses(tmp_path / "missing.csv")
    assert str(info.value) == f"{tmp_path / 'missing.csv'}: cannot open file: No such file or directory"


def test_a_poses_file_that_is_not_utf8_text_is_a_value_error_naming_it(tmp_path):
    """Excel's "Unicode text" save said "column station: missing from the header"; a PNG renamed
    poses.csv was "mixed line ends" on line 3."""
    header = "station,set,sensor,time,rep_x,rep_y,rep_z,rep_qw,rep_qx,rep_qy,rep_qz,ref_x,ref_y,ref_z,ref_qw,ref_qx,ref_qy,ref_qz\n"
    utf16 = tmp_path / "utf16" / "poses.csv"
    utf16.parent.mkdir()
    utf16.write_bytes(("\ufeff" + header + "1,calib,1,0,0,0,0.3,1,0,0,0,0,0,0.3,1,0,0,0\n").encode("utf-16-le"))
    with pytest.raises(ValueError) as info:
        captures.load_poses(utf16)
    assert str(info.value) == (f"{utf16}:1: encoding: UTF-16 text (a byte order mark FF FE or FE FF); "
                               "save the CSV file as UTF-8")
    png = tmp_path / "png" / "poses.csv"
    png.parent.mkdir()
    png.write_bytes(b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR\x00\x00\x00\x10")
    with pytest.raises(ValueError) as info:
        captures.load_poses(png.parent)
    assert str(info.value).startswith(f"{png}:1: encoding: the header is not text (byte \\x89 at column 1): "
                                      "not a text CSV file")


def test_saved_tracker_stream_keeps_its_extra_columns_and_refuses_a_fractional_sensor(tmp_path):
    """save_tracker_stream wrote time, sensor and pose only: a stream's extra columns (a
    temperature, an operator's label: the covariates of the diagnosis) were dropped without a word,
    and a sensor of 1.5 was written as 1."""
    original = tmp_path / "in.csv"
    original.write_text("time,sensor,x,y,z,qw,qx,qy,qz,temperature_c,operator\n"
                        "0,1,0.1,0.2,0.3,1,0,0,0,21.5,ann\n"
                        "0.01,1,0.1,0.2,0.3,1,0,0,0,,bob\n"
                        "0.02,2,0.4,0.5,0.6,0,1,0,0,22.25,\n")
    stream = captures.load_tracker_stream(original)
    out = tmp_path / "out.csv"
    captures.save_tracker_stream(out, stream)
    again = captures.load_tracker_stream(out)
    assert again.extra_columns == ["temperature_c", "operator"]
    np.testing.assert_array_equal(again.column("temperature_c"), [21.5, np.nan, 22.25])
    assert list(again.column("operator")) == ["ann", "bob", None]
    np.testing.assert_array_equal(again.positions, stream.positions)
    np.testing.assert_array_equal(again.quaternions_xyzw, stream.quaternions_xyzw)
    np.testing.assert_array_equal(again.sensor, [1, 1, 2])

    stream.sensor = np.array([1.0, 1.5, 2.0])
    with pytest.raises(ValueError, match=r"bad\.csv: record 1: column sensor: 1\.5 is not an integer"):
        captures.save_tracker_stream(tmp_path / "bad.csv", stream)
    assert not (tmp_path / "bad.csv").exists()


def test_saved_tracker_stream_keeps_quaternions_bit_for_bit_and_refuses_a_non_unit_one(tmp_path):
    """save_tracker_stream normalised every quaternion, so a loaded stream saved back changed in the
    last digits, and it wrote any norm ((0, 0, 0, 2)) as a rotation where the C++ writer and the
    readers refuse one further than 1e-3 from unit."""
    original = tmp_path / "in.csv"
    # The first row's norm is 0.9999999999999999 (a normalised random rotation): kept as read; the
    # second is 5e-6 from unit, within the readers' tolerance, and normalised by the reader.
    text = ("time,sensor,x,y,z,qw,qx,qy,qz\n"
            "0,1,0.1,0.2,0.3,-0.8078898754434873,0.21424427007839494,0.5093606231982167,"
            "0.20485384406841473\n"
            "0.01,1,0.1,0.2,0.3,0.5,0.5,0.5,0.50001\n")
    original.write_text(text)
    stream = captures.load_tracker_stream(original)
    out = tmp_path / "out.csv"
    captures.save_tracker_stream(out, stream)
    np.testing.assert_array_equal(captures.load_tracker_stream(out).quaternions_xyzw,
                                  stream.quaternions_xyzw)
    assert out.read_text().splitlines()[1] == text.splitlines()[1]
    stream.quaternions_xyzw = np.array([[0.0, 0.0, 0.0, 2.0], [0.0, 0.0, 0.0, 1.0]])
    with pytest.raises(ValueError, match=r"bad\.csv: record 0: columns qw, qx, qy, qz: quaternion norm 2 is not 1"):
        captures.save_tracker_stream(tmp_path / "bad.csv", stream)
    assert not (tmp_path / "bad.csv").exists()


def test_validate_and_diagnose_a_stream_capture(sim, tmp_path):
    _, streams, cal = sim
    r = run_cli("validate", streams, "-c", cal)
    assert "streams paired at a time offset of" in r.stdout and "(estimated)" in r.stdout
    # One table: every paired sample carries the pairing's "calib", not a set of the user's.
    assert "all set (" in r.stdout and "calib set (" not in r.stdout and "Corrected" in r.stdout
    r = run_cli("validate", streams, "-c", cal, "--time-offset", "0.02")
    assert "time offset of 20.00 ms (--time-offset)" in r.stdout
    r = run_cli("diagnose", streams, "-c", cal, "--permutations", "9", "--json")
    doc = json.loads(r.stdout)
    assert doc["capture_origin"]["kind"] == "streams"
    assert "speed" in {c["covariate"] for c in doc["covariates"]}
    # visiting_order repeats time on a stream (the same R^2): tested once, and the document says why.
    tested = [c["covariate"] for c in doc["covariates"]]
    assert "visiting_order" not in tested and tested.count("time") == 4, tested
    assert list(doc["covariates_left_out"]) == ["visiting_order"]
    assert len(doc["stations"]) == doc["capture_origin"]["paired"]
    run_cli("report", streams, "-c", cal, "--permutations", "9", "-o", tmp_path / "report")
    page = (tmp_path / "report" / "report.html").read_text()
    assert "Samples: streams paired at a time offset of" in page


def test_diagnose_model_on_a_stream_shows_the_fits_held_out_table(sim, tmp_path):
    # trackcal diagnose --model on a stream skips the fit's cross-validation (the ranking holds out
    # the same blocks of time), but then showed only the in-sample table of the fit ("all set",
    # paper seed 1, degree 4: 0.92 mm corrected against 2.26 mm held out) and nothing said so; the
    # ranking named its held-out table "cross-validation (5-fold)" while trackcal fit names the
    # same folds "cross-validation (5-fold, blocks of time)". Now the ranking's base table is shown
    # under the fit's name and equals trackcal fit's table: a polynomial is linear, its folds are
    # fitted exactly on the same blocks, so the means agree to the solver's precision (1e-9 rel).
    _, streams, _ = sim
    model = tmp_path / "model.yaml"
    model.write_text("terms:\n  - type: polynomial\n    degree: 2\n")
    fitted = json.loads(run_cli("fit", "--data", streams, "--model", model, "-o", tmp_path / "cal.json",
                                "--json").stdout)
    held_out = next(t for t in fitted["tables"] if t["set"].startswith("cross-validation"))
    assert held_out["set"] == "cross-validation (5-fold, blocks of time)"
    common = ("--model", model, "--effects", "sensor_offset", "--permutations", "9")
    doc = json.loads(run_cli("diagnose", streams, *common, "--json").stdout)
    assert doc["candidates"]["base"]["table1"]["set"] == held_out["set"]
    shown = [t for t in doc["tables"] if t["set_name"] == held_out["set"]]
    assert len(shown) == 1, [t["set_name"] for t in doc["tables"]]
    for key in ("position_mm", "orientation_deg"):
        assert shown[0]["after_" + key]["count"] == held_out["after"][key]["count"]
        assert shown[0]["after_" + key]["mean"] == pytest.approx(held_out["after"][key]["mean"], rel=1e-9)
    text = run_cli("diagnose", streams, *common).stdout
    assert f"{held_out['set']} set (" in text, text
    assert f"{held_out['after']['position_mm']['mean']:.3f}" in text, text


def test_diagnose_json_and_residuals_give_every_station(sim, tmp_path):
    cap_dir, _, cal = sim
    out = tmp_path / "residuals.csv"
    r = run_cli("diagnose", cap_dir, "-c", cal, "--permutations", "9", "--json", "--residuals", out)
    doc = json.loads(r.stdout)  # still one JSON document on stdout
    cap = captures.load_poses(cap_dir)
    v = validation.validate(cap, trackcal.Calibration.load(cal), analyse_covariates=False)
    rows = doc["stations"]
    assert len(rows) == len(v.capture) == 600  # 480 calib + 120 valid; reg stations left out
    assert [r["station"] for r in rows] == v.capture.station.tolist()
    np.testing.assert_allclose([r["after_position_mm"] for r in rows], v.after.position_mm, rtol=1e-12)
    # The vector columns are the magnitudes' components (mm), so they recombine to the magnitude.
    vec = np.array([[r[f"after_dp{a}_mm"] for a in "xyz"] for r in rows])
    np.testing.assert_allclose(np.linalg.norm(vec, axis=1), v.after.position_mm, rtol=1e-9)
    assert doc["outside_volume"]["stations"] == [r["station"] for r in rows if r["outside"]]
    assert doc["outside_volume"]["count"] == len(doc["outside_volume"]["stations"])
    text = out.read_text().splitlines()
    assert text[0].startswith("station,set,sensor,time,x,y,z,distance,before_position_mm")
    assert len(text) == 601
    # A second run never writes over the file.
    before = out.read_bytes()
    r = run_cli("validate", cap_dir, "-c", cal, "--residuals", out, check=False)
    assert r.returncode == 2 and "exists" in r.stderr and out.read_bytes() == before


def test_diagnose_fits_the_model_to_the_registered_references(sim, tmp_path):
    # With --register-markers the statistics use the references extracted from the markers; the
    # model must be fitted to those too, not to the labelling poses.csv's (6 mm apart here).
    cap_dir, _, _ = sim
    folder = tmp_path / "markers"
    folder.mkdir()
    for name in ("markers.csv", "tracker.csv", "poses.csv"):
        shutil.copy(cap_dir / name, folder / name)
    model = tmp_path / "model.yaml"
    model.write_text("terms:\n  - type: polynomial\n    degree: 2\n")
    doc = json.loads(run_cli("diagnose", folder, "--register-markers", "--model", model, "--json",
                             "--permutations", "9", "--effects", "sensor_offset", "--folds", "2").stdout)
    fitted = next(t for t in doc["fit"]["tables"] if t["set_name"] == "calib")
    shown = next(t for t in doc["tables"] if t["set_name"] == "calib")
    # The same stations and references: the uncorrected errors agree to rounding.
    assert fitted["before_position_mm"]["mean"] == pytest.approx(shown["before_position_mm"]["mean"], rel=1e-9)
    assert fitted["before_position_mm"]["count"] == shown["before_position_mm"]["count"]


def test_fit_and_diagnose_register_a_folder_of_raw_markers(sim, tmp_path):
    # docs/understand.md: every command that takes a capture (fit --data too) accepts a folder of
    # markers.csv + tracker.csv and registers it. validate did; fit and diagnose --model handed the
    # folder to the engine, which said "<folder>/poses.csv: cannot open file".
    cap_dir, _, _ = sim
    folder = tmp_path / "markers"
    folder.mkdir()
    for name in ("markers.csv", "tracker.csv"):
        shutil.copy(cap_dir / name, folder / name)
    model = tmp_path / "model.yaml"
    model.write_text("terms:\n  - type: polynomial\n    degree: 2\n")
    registered = captures.load(folder)
    r = run_cli("fit", "--data", folder, "--model", model, "-o", tmp_path / "cal.json", "--workdir",
                tmp_path / "work", check=False)
    assert r.returncode == 0, r.stderr
    assert "raw markers registered (paper section 3) with every station" in r.stdout
    # Every station registers and is fitted (no validation set: cross-validated).
    assert f"calib set ({len(registered)} poses)" in r.stdout and "cross-validation (5-fold)" in r.stdout
    entry = json.loads((tmp_path / "work" / "history.jsonl").read_text().splitlines()[-1])
    assert sorted(pathlib.Path(d["path"]).name for d in entry["data"]) == ["markers.csv", "tracker.csv"]
    doc = json.loads(run_cli("diagnose", folder, "--model", model, "--json", "--permutations", "9",
                             "--effects", "sensor_offset", "--folds", "2").stdout)
    fitted = next(t for t in doc["fit"]["tables"] if t["set_name"] == "calib")
    shown = next(t for t in doc["tables"] if t["set_name"] == "calib")
    assert doc["capture_origin"]["kind"] == "markers"
    assert fitted["before_position_mm"]["count"] == shown["before_position_mm"]["count"] == len(registered)
    assert fitted["before_position_mm"]["mean"] == pytest.approx(shown["before_position_mm"]["mean"], rel=1e-9)


def test_outside_stations_are_listed(sim):
    cap_dir, _, cal = sim
    v = validation.validate(captures.load_poses(cap_dir), trackcal.Calibration.load(cal), analyse_covariates=False)
    r = run_cli("validate", cap_dir, "-c", cal)
    n = int(v.extrapolated.sum())
    assert n > 0  # validation stations extend beyond the calib grid's bounding box
    line = next(l for l in r.stdout.splitlines() if l.startswith("stations outside the calibrated volume"))
    listed = [int(w) for w in line.split(": ", 2)[2].split() if w.isdigit()]
    assert not any(b == a + 1 for a, b in zip(listed, listed[1:])), line  # a row of ids is one range
    assert line == f"stations outside the calibrated volume: {n} of 600: " + validation.id_ranges_text(
        v.outside_stations, 20)


def test_ids_in_a_row_are_listed_as_ranges():
    # A stream's 1229 samples outside the volume were listed one id after the other, 20 of them
    # (50 in the report) and "... (1209 more)": consecutive ids are one range now.
    assert validation.id_ranges_text([3, 4, 5, 6, 9, 12, 13], 20) == "3-6 9 12-13"
    assert validation.id_ranges_text([3, 4, 5, 6, 9, 12, 13, 20], 2) == "3-6 9 ... (3 more in 2 ranges)"
    assert validation.id_ranges_text([1, 3, 5, 7], 2) == "1 3 ... (2 more)"
    assert validation.id_ranges_text([7, 6, 5], 5) == "7 6 5"  # in the order given: no range backwards
    assert validation.id_ranges_text([], 5) == ""


def test_diagnose_text_of_a_stream_says_samples_and_gives_stretches_of_time(sim):
    # trackcal diagnose of a stream printed "stations outside the calibrated volume: 1229 of 3599:
    # 610 611 612 ... (1209 more)", "stations the model inverse does not resolve", a worst table with
    # a "station" column under "Worst 10 moments" and "(41 stations: ...)" in its note. Now samples,
    # and the stretches of the stream's time outside the volume with their sample ids.
    _, streams, cal = sim
    r = run_cli("diagnose", streams, "-c", cal, "--permutations", "19")
    assert "station" not in r.stdout.lower(), r.stdout
    assert "visiting_order left out: the same order as time" in r.stdout, r.stdout
    v = validation.validate(captures.load(streams), trackcal.Calibration.load(cal), analyse_covariates=False)
    n_out, n = int(v.extrapolated.sum()), len(v.extrapolated)
    assert n_out > 0  # the stream leaves the calibration grid's box
    line = next(l for l in r.stdout.splitlines() if l.startswith("samples outside the calibrated volume"))
    assert not re.search(r"\b(\d+) (\d+) (\d+)\b", line), line  # no wall of sample ids
    runs = validation.id_runs(v.outside_stations)
    assert 0 < len(runs) < 20 and len(runs) < n_out / 10  # a few passes out of the box, each many samples
    t, ids = v.capture.time[v.extrapolated], v.outside_stations
    assert line.startswith(f"samples outside the calibrated volume: {n_out} of {n}, {len(runs)} stretch")
    for a, b in runs:
        assert f"{t[a]:.2f}-{t[b]:.2f} s (samples {ids[a]}-{ids[b]})" in line, line
    assert re.search(r"^ +sample +time +sensor", r.stdout, re.M), r.stdout
    assert "samples the model inverse does not resolve" in r.stdout


def test_raw_markers_register_with_the_reg_stations_like_trackcal_fit(sim, tmp_path):
    """A folder of raw markers (markers.csv, tracker.csv) with the poses.csv that labels the sets:
    the Python loader registers with the `reg` stations only and extracts every station's reference
    pose, exactly as `trackcal-fit register --poses` does."""
    cap_dir, _, cal = sim
    folder = tmp_path / "markers"
    folder.mkdir()
    for name in ("markers.csv", "tracker.csv", "poses.csv"):
        shutil.copy(cap_dir / name, folder / name)
    # A temperature logged per station in the labelling poses.csv stays with its station.
    lines = (folder / "poses.csv").read_text().splitlines()
    station_col = lines[0].split(",").index("station")
    temperature = {}
    rows = [lines[0] + ",temperature"]
    for line in lines[1:]:
        station = int(line.split(",")[station_col])
        temperature[station] = 20.0 + 0.01 * station
        rows.append(f"{line},{temperature[station]}")
    (folder / "poses.csv").write_text("\n".join(rows) + "\n")
    cap = captures.load(folder, register_markers=True)
    assert cap.origin["kind"] == "markers" and cap.origin["registered_with"].startswith("the reg stations")
    assert cap.extra_columns == ["temperature"]
    assert cap.column("temperature").tolist() == [temperature[int(s)] for s in cap.station]
    out = tmp_path / "registered.csv"
    subprocess.run([shutil.which("trackcal-fit"), "register", "--markers", folder / "markers.csv", "--tracker",
                    folder / "tracker.csv", "--poses", folder / "poses.csv", "-o", out], check=True,
                   capture_output=True)
    cli = captures.load_poses(out)
    assert cap.station.tolist() == cli.station.tolist() and cap.set.tolist() == cli.set.tolist()
    assert cli.column("temperature").tolist() == cap.column("temperature").tolist()
    # Same code on the same input; the CSV round trip is exact (shortest round-trip printing).
    np.testing.assert_array_equal(cap.reference_positions, cli.reference_positions)
    # Registering with every station (no labels) lets the far, distorted stations bias it: the
    # references move away from the simulator's (which are registered with the true transform).
    sim_refs = captures.load_poses(cap_dir)
    index = {s: i for i, s in enumerate(sim_refs.station)}
    rows = [index[s] for s in cap.station]

    def mean_mm(c):
        return 1e3 * np.linalg.norm(c.reference_positions - sim_refs.reference_positions[rows], axis=1).mean()
    r = run_cli("validate", folder, "-c", cal, "--register-markers")
    assert "raw markers registered (paper section 3) with the reg stations of poses.csv" in r.stdout
    (folder / "poses.csv").unlink()
    everything = captures.load(folder)
    assert everything.origin["registered_with"] == "every station" and set(everything.set) == {"calib"}
    # Measured on seed 5 of the paper preset: 6.0 mm with the reg stations, 33.5 mm with all.
    assert mean_mm(cap) < 0.5 * mean_mm(everything)
    # And the CLI validates such a folder directly.
    r = run_cli("validate", folder, "-c", cal)
    assert "raw markers registered (paper section 3) with every station" in r.stdout


def test_validate_records_stream_files_by_absolute_path(sim, tmp_path, monkeypatch):
    """A history entry must find its data again from another folder: both stream files, absolute."""
    from trackcal import cli, history
    _, streams, cal = sim
    monkeypatch.chdir(streams.parent)
    assert cli.main(["validate", streams.name, "-c", str(cal), "--workdir", str(tmp_path / "work")]) == 0
    data = history.load_history(tmp_path / "work")[0]["data"]
    assert [d["path"] for d in data] == [str(streams / "tracker_stream.csv"), str(streams / "reference_stream.csv")]


def test_stream_rows_out_of_time_order_give_each_station_its_own_speed_and_columns(tmp_path):
    """The tracker stream reader and the pairing accept rows in any order (receivers interleave;
    streams get merged), but the speed and the extra columns were interpolated along the file's
    order: a stream written out of time order gave stations another sample's speed (0.2 m/s off on
    a 0.1 m/s motion) and column values. They must not depend on the order of the rows."""
    n = 200
    t = 100.0 + 0.01 * np.arange(n)
    p = np.column_stack([0.3 + 0.1 * np.sin(t), np.full(n, 0.2), np.full(n, -0.5)])  # speed 0.1 |cos t|
    frame = np.arange(n, dtype=float)
    t, p, frame = t.tolist(), p.tolist(), frame.tolist()  # floats that print as numbers

    def write(folder, order):
        folder.mkdir()
        rows = ["time,sensor,x,y,z,qw,qx,qy,qz,frame"] + [
            f"{t[i]!r},1,{p[i][0]!r},{p[i][1]!r},{p[i][2]!r},1,0,0,0,{frame[i]!r}" for i in order]
        (folder / "tracker_stream.csv").write_text("\n".join(rows) + "\n")
        rows = ["time,x,y,z,qw,qx,qy,qz"] + [f"{t[i]!r},{p[i][0]!r},{p[i][1]!r},{p[i][2]!r},1,0,0,0"
                                             for i in range(n)]
        (folder / "reference_stream.csv").write_text("\n".join(rows) + "\n")
        cap = captures.load(folder, time_offset=0.0)
        by_time = np.argsort(cap.time)
        notes.append(captures.describe_origin(cap))
        return cap.time[by_time], cap.speed[by_time], cap.column("frame")[by_time]

    notes = []
    t_sorted, speed_sorted, frame_sorted = write(tmp_path / "sorted", np.arange(n))
    t_mixed, speed_mixed, frame_mixed = write(tmp_path / "mixed", np.random.default_rng(3).permutation(n))
    # Taken in time order, and said so: two recordings concatenated into one file interleave.
    assert "warning" not in notes[0], notes[0]
    assert "sensor 1's samples are not in time order in the file" in notes[1], notes[1]
    assert "taken in time order" in notes[1], notes[1]
    np.testing.assert_array_equal(t_mixed, t_sorted)
    np.testing.assert_allclose(speed_sorted, 0.1 * np.abs(np.cos(t_sorted)), atol=1e-3)
    np.testing.assert_allclose(speed_mixed, speed_sorted, atol=1e-12)
    np.testing.assert_array_equal(frame_mixed, frame_sorted)
    np.testing.assert_array_equal(frame_sorted, np.round((t_sorted - 100.0) / 0.01))


def test_a_capture_folder_given_to_pair_register_or_a_recording_names_its_files(sim, tmp_path):
    """A folder given where a file is expected is read as its capture file, as captures.load_* do;
    the C++ readers failed on it with 'basic_filebuf::underflow error reading the file: Is a
    directory', naming no file (and validate_recording read its raw folder one way and paired it
    the other)."""
    cap_dir, streams, _ = sim
    from_files = trackcal.pair(streams / "tracker_stream.csv", streams / "reference_stream.csv", time_offset=0.0)
    from_folder = trackcal.pair(streams, streams, time_offset=0.0)
    np.testing.assert_array_equal(from_folder.poses.reported_positions, from_files.poses.reported_positions)
    v = validation.validate_recording(streams, streams, time_offset=0.0)
    assert len(v.capture) == len(from_files.poses)
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(ValueError, match=r"empty/tracker_stream\.csv: cannot open file"):
        trackcal.pair(empty, streams)
    with pytest.raises(ValueError, match=r"empty/markers\.csv: cannot open file"):
        trackcal.register(empty, cap_dir / "tracker.csv")


def test_a_label_that_is_not_utf8_names_its_file_line_and_column(sim, tmp_path):
    """A spreadsheet's Latin-1 (Windows-1252) export of an operator "José": the C++ reader takes the
    bytes, and the label failed only as it became a Python str, as "'utf-8' codec can't decode byte
    0xe9 in position 3: unexpected end of data", naming no file, line or column (from load_poses,
    load_tracker_stream, load of a stream folder, register with a poses.csv)."""
    cap_dir, _, _ = sim
    lines = (cap_dir / "poses.csv").read_text().splitlines()
    utf8 = tmp_path / "utf8"
    utf8.mkdir()
    (utf8 / "poses.csv").write_bytes(("\r\n".join([lines[0] + ",operator"] + [line + ",José" for line in lines[1:]])
                                      + "\r\n").encode("utf-8"))
    assert set(captures.load_poses(utf8).column("operator")) == {"José"}  # UTF-8 text is fine
    latin1 = tmp_path / "latin1"
    latin1.mkdir()
    rows = [lines[0] + ",operator", lines[1] + ",Anna", lines[2] + ",José"] + [line + ",Anna" for line in lines[3:]]
    (latin1 / "poses.csv").write_bytes(("\r\n".join(rows) + "\r\n").encode("latin-1"))
    message = r"latin1/poses\.csv:3: column operator: 'Jos\\xe9' is not UTF-8 text \(save the file as UTF-8\)"
    with pytest.raises(ValueError, match=message):
        captures.load_poses(latin1)
    for name in ("markers.csv", "tracker.csv"):
        shutil.copy(cap_dir / name, latin1 / name)
    with pytest.raises(ValueError, match=message):
        captures.load(latin1, register_markers=True)
    streams = tmp_path / "streams"
    streams.mkdir()
    shutil.copy(cap_dir / "reference_stream.csv", streams)
    t = (cap_dir / "tracker_stream.csv").read_text().splitlines()
    (streams / "tracker_stream.csv").write_bytes(
        ("\n".join([t[0] + ",room\xb0"] + [line + ",1" for line in t[1:]]) + "\n").encode("latin-1"))
    header = r"streams/tracker_stream\.csv:1: header: column 10: 'room\\xb0' is not UTF-8 text"
    with pytest.raises(ValueError, match=header):
        captures.load_tracker_stream(streams)
    with pytest.raises(ValueError, match=header):
        captures.load(streams, time_offset=0.0)


def test_captures_and_streams_compare_with_equals_and_refuse_equality_with_a_hint(sim):
    """capture == capture raised numpy's "The truth value of an array with more than one element is
    ambiguous" (the dataclass compared tuples of arrays), as did TrackerStream, ReferenceStream and
    FitReport.parameters' Parameter. == is now a TypeError pointing to equals(), which compares
    every array (NaN equal to NaN: a missing extra value) and leaves out where a capture came from
    (path, origin)."""
    import copy
    cap_dir, streams, _ = sim
    a = captures.load_poses(cap_dir)
    b = captures.load(cap_dir)  # origin set
    assert a.equals(b) and b.equals(a) and a.equals(a.subset(np.arange(len(a))))
    assert not a.equals(a.select_set("calib")) and not a.equals(None) and not a.equals("poses.csv")
    c = copy.deepcopy(a)
    c.reported_positions[5, 1] += 1e-9
    assert not a.equals(c)
    c = copy.deepcopy(a)
    c.set[0] = "valid" if c.set[0] != "valid" else "calib"
    assert not a.equals(c)
    with_nan = copy.deepcopy(a)
    with_nan.extra_columns = ["operator_height"]
    with_nan.extra = np.full((len(a), 1), np.nan)
    assert with_nan.equals(copy.deepcopy(with_nan)) and not with_nan.equals(a)
    tracker = captures.load_tracker_stream(streams)
    reference = captures.load_reference_stream(streams)
    assert tracker.equals(captures.load_tracker_stream(streams)) and not tracker.equals(a)
    assert reference.equals(captures.load_reference_stream(streams))
    for x, y in ((a, b), (tracker, tracker), (reference, captures.load_reference_stream(streams))):
        with pytest.raises(TypeError, match=r"== .* is not defined \(they hold numpy arrays\): use a\.equals\(b\)"):
            x == y  # noqa: B015
        with pytest.raises(TypeError, match=r"use a\.equals\(b\)"):
            x != y  # noqa: B015
    # Identity still finds a capture in a list; other types compare unequal, as before.
    assert a in [a] and a != 3 and not (a == None)  # noqa: E711
    param = trackcal.fit(cap_dir, "terms:\n  - type: polynomial\n    degree: 1\n").parameters[0]
    assert param.equals(copy.deepcopy(param))
    with pytest.raises(TypeError, match=r"Parameter == Parameter is not defined"):
        param == copy.deepcopy(param)  # noqa: B015


def test_registration_and_pairing_have_one_line_reprs(sim):
    """Their repr was the default "<trackcal.fitting.Registration object at 0x7f...>", beside the
    one-line reprs of FitReport, PoseCapture and Calibration."""
    import warnings
    cap_dir, streams, _ = sim
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        reg = trackcal.register(cap_dir, cap_dir)
        paired = trackcal.pair(streams, streams, estimate_time_offset=True)
    text = repr(reg)
    assert re.fullmatch(r"Registration\(\d+ poses, \d+ left out, \d+ rejected, chi-square [\d.]+ for \d+ "
                        r"degrees of freedom, (NOT )?converged, (NOT )?identifiable\)", text), text
    assert f"Registration({len(reg.poses)} poses, {len(reg.left_out)} left out" in text
    text = repr(paired)
    assert re.fullmatch(r"Pairing\(\d+ poses of sensor \d+, time offset -?[\d.]+ ms \(estimated, \+- [\d.e-]+ ms\)"
                        r"(, clock drift -?[\d.]+ ppm)?, \d+ dropped(, warning)?\)", text), text
    assert text.startswith(f"Pairing({len(paired.poses)} poses") and "\n" not in text
    given = trackcal.pair(streams, streams, time_offset=0.0125)
    assert re.fullmatch(r"Pairing\(\d+ poses of sensor \d+, time offset 12\.500 ms, \d+ dropped(, warning)?\)",
                        repr(given)), repr(given)


def _fit_in_a_worker(cap_dir):
    return trackcal.fit(cap_dir, "terms:\n  - type: polynomial\n    degree: 2\n")


def test_fit_reports_registrations_and_pairings_pickle_for_process_pools(sim, tmp_path):
    """A process pool's worker could not return a fit: "cannot pickle
    'trackcal._core.NativeFitReport' object" (nor a Registration or a Pairing), while
    report.calibration pickled. They pickle now with their document, calibration and poses, and a
    pickled one saves the same file as the original and refuses what it refuses."""
    import concurrent.futures
    import multiprocessing
    import pickle
    import warnings
    cap_dir, streams, _ = sim
    with concurrent.futures.ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn")) as pool:
        pooled = pool.submit(_fit_in_a_worker, cap_dir).result(timeout=300)
    report = _fit_in_a_worker(cap_dir)
    copy_ = pickle.loads(pickle.dumps(pickle.loads(pickle.dumps(report))))  # twice: a copy pickles too
    for other in (pooled, copy_):
        assert repr(other) == repr(report) and other.format().split("Fit:")[0] == report.format().split("Fit:")[0]
        assert other.calibration.to_json().split('"provenance"')[0] == report.calibration.to_json().split('"provenance"')[0]
        assert other.to_dict()["fit"]["parameters"] == report.to_dict()["fit"]["parameters"]
    assert copy_.to_dict() == report.to_dict()
    a = report.save(tmp_path / "a.json", "trackcal fit x")
    b = copy_.save(tmp_path / "b.json", "trackcal fit x")
    assert json.loads(a.read_text()) == json.loads(b.read_text())
    assert copy_.output == b and copy_.to_dict()["output"] == str(b)
    assert report.to_dict()["output"] == str(a)
    assert pickle.loads(pickle.dumps(copy_)).to_dict()["output"] == str(b)
    with pytest.raises(ValueError, match="output would overwrite the input"):
        copy_.save(cap_dir / "poses.csv")
    (tmp_path / "notes.txt").write_text("mine")
    with pytest.raises(ValueError, match="notes.txt"):
        copy_.save(tmp_path / "notes.txt")
    assert (tmp_path / "notes.txt").read_text() == "mine"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        results = [trackcal.register(cap_dir, cap_dir), trackcal.pair(streams, streams, estimate_time_offset=True)]
    for k, result in enumerate(results):
        copied = pickle.loads(pickle.dumps(result))
        assert repr(copied) == repr(result) and copied.to_dict() == result.to_dict()
        assert copied.poses.equals(result.poses)
        if k == 0:
            assert copied.summary() == result.summary()
        native_file = result.save(tmp_path / f"native{k}.csv")
        copied_file = copied.save(tmp_path / f"copied{k}.csv")
        assert native_file.read_bytes() == copied_file.read_bytes()
        assert copied.to_dict()["output"] == str(copied_file)
        with pytest.raises(ValueError, match="exists"):
            copied.save(copied_file)
        with pytest.raises(ValueError, match="output would overwrite the input"):
            copied.save((cap_dir / "markers.csv") if k == 0 else (streams / "tracker_stream.csv"))


def _write_streams(folder, t_tracker, p_tracker, t_reference, p_reference):
    """A tracker stream of sensor 1 and a reference stream, identity orientations."""
    folder.mkdir()
    rows = ["time,sensor,x,y,z,qw,qx,qy,qz"] + [f"{a!r},1,{b[0]!r},{b[1]!r},{b[2]!r},1,0,0,0"
                                              for a, b in zip(t_tracker.tolist(), p_tracker.tolist())]
    (folder / "tracker_stream.csv").write_text("\n".join(rows) + "\n")
    rows = ["time,x,y,z,qw,qx,qy,qz"] + [f"{a!r},{b[0]!r},{b[1]!r},{b[2]!r},1,0,0,0"
                                         for a, b in zip(t_reference.tolist(), p_reference.tolist())]
    (folder / "reference_stream.csv").write_text("\n".join(rows) + "\n")
    return folder


def test_a_repeated_tracker_time_is_an_error_naming_its_lines(tmp_path):
    """One sensor's time twice (a frame written twice, a clock that did not tick) was paired twice
    with one reference pose and gave the next sample a speed of 0.067 m/s on a 0.100 m/s motion."""
    n = 200
    t = 100.0 + 0.01 * np.arange(n)
    p = np.column_stack([0.3 + 0.1 * np.sin(t), np.full(n, 0.2), np.full(n, -0.5)])
    repeated = t.copy()
    repeated[50] = repeated[49]  # rows 51 and 52 of the file (after the header)
    folder = _write_streams(tmp_path / "repeated", repeated, p, t, p)
    with pytest.raises(ValueError, match=r"tracker_stream\.csv:52: columns time, sensor: time 100\.49 of "
                                         r"sensor 1 repeats line 51"):
        captures.load(folder, time_offset=0.0)


def test_a_gap_in_the_tracker_stream_is_named_and_no_speed_is_taken_across_it(tmp_path):
    """A tracker stream without samples for 1 s (a dropout): the speed covariate of the samples on
    either side came from a central difference across the gap (0.069 m/s against 0.097 before it,
    0.069 against 0.030 after it), and nothing said there was a gap."""
    n = 200
    t = 100.0 + 0.01 * np.arange(n)
    p = np.column_stack([0.3 + 0.1 * np.sin(t), np.full(n, 0.2), np.full(n, -0.5)])  # speed 0.1 |cos t|
    keep = np.r_[0:80, 180:n]  # no tracker sample between 100.79 and 101.80: a step of 1.01 s
    cap = captures.load(_write_streams(tmp_path / "gap", t[keep], p[keep], t, p), time_offset=0.0)
    order = np.argsort(cap.time)
    # One-sided differences over one 10 ms step: within 1e-3 m/s of the true speed (the motion's
    # acceleration 0.1 m/s^2 times half a step is 5e-4 m/s).
    np.testing.assert_allclose(cap.speed[order], 0.1 * np.abs(np.cos(cap.time[order])), atol=1e-3)
    line = captures.describe_origin(cap)
    assert "1 gap " in line and "sensor 1: no sample from t = 100.790 to 101.800 s (1.010 s)" in line, line
