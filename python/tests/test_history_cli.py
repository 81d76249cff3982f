"""History round trip, the trackcal command (validate/diagnose/report/history) and its errors."""

import json
import os
import pathlib
import shutil
import subprocess
import sys

import numpy as np
import pytest

import trackcal
from trackcal import captures, history, validation
from understand_support import simulate


def run_cli(*args, check=True):
    exe = shutil.which("trackcal")
    cmd = [exe] if exe else [sys.executable, "-m", "trackcal.cli"]
    r = subprocess.run(cmd + [str(a) for a in args], capture_output=True, text=True, timeout=300)
    if check:
        assert r.returncode == 0, r.stderr
    return r


def _record_many(args):
    work, model, data, label, count = args
    scores = {"valid": {"position_mm": {"mean": 1.0}, "orientation_deg": {"mean": 0.1}}}
    for i in range(count):
        history.record_fit(work, model=model, data=[(data, "calibration_capture")], scores=scores,
                           label=f"{label} {i}")


def test_fits_recorded_at_once_all_keep_their_entry(tmp_path):
    """Two processes recording into one work folder: each record reads the file and rewrites it, so
    without a lock one could drop the other's entry (a lab running two fits from two terminals)."""
    import multiprocessing
    data = tmp_path / "poses.csv"
    data.write_text("x\n")
    model = tmp_path / "model.json"
    model.write_text("{}\n")
    work = tmp_path / "work"
    work.mkdir()
    count = 60
    with multiprocessing.get_context("fork").Pool(2) as pool:
        pool.map(_record_many, [(work, model, data, name, count) for name in ("a", "b")])
    labels = [e["label"] for e in history.load_history(work)]
    assert sorted(labels) == sorted([f"{n} {i}" for n in ("a", "b") for i in range(count)])


def test_a_label_of_the_previous_entries_is_worked_out_under_the_lock(tmp_path):
    """record_model_fit's default label ("+dipole") is the change from the previous entry: worked
    out before taking the lock, a fit recorded meanwhile by another process was not its previous."""
    import threading
    data = tmp_path / "poses.csv"
    data.write_text("x\n")
    work = tmp_path / "work"
    scores = {"valid": {"position_mm": {"mean": 1.0}, "orientation_deg": {"mean": 0.1}}}
    record = dict(model=None, data=[(data, "calibration_capture")], scores=scores)
    history.record_fit(work, label="first", **record)
    with history._history_lock(work):  # another process, in the middle of its record
        t = threading.Thread(target=history.record_fit, args=(work,),
                             kwargs=dict(label=lambda entries: f"after {entries[-1]['label']}", **record))
        t.start()
        t.join(0.5)  # blocked on the lock: it must not have read the history yet
        assert t.is_alive()
        path = work / history.HISTORY_FILE
        other = json.loads(path.read_text().splitlines()[0])
        other["label"] = "second"
        path.write_text(path.read_text() + json.dumps(other) + "\n")
    t.join(10)
    assert [e["label"] for e in history.load_history(work)] == ["first", "second", "after second"]


def test_a_fit_of_a_loaded_capture_records_its_files(tmp_path):
    """record_model_fit of a fit given a loaded capture (trackcal.fit(captures.load(...), ...), the
    Python example of docs/understand.md) recorded no capture file at all: its rows carried no data
    hashes, so the history compared fits on other captures as steps of one loop instead of saying
    "other data"."""
    import types
    cap_a = captures.load(simulate(tmp_path / "a", seed=3))
    cap_b = captures.load(simulate(tmp_path / "b", seed=4))
    work = tmp_path / "work"

    def report(pos):
        text = "terms:\n  - type: polynomial\n    degree: 2\n"
        s = {"valid": {"position_mm": {"mean": pos}, "orientation_deg": {"mean": 0.1}}}
        return types.SimpleNamespace(
            model={"text": text, "sha256": "ab" * 32, "source": "<string>", "terms": ["polynomial"]},
            terms=[{"type": "polynomial"}], converged=True, chi2_per_dof=1.0, num_free_parameters=60,
            outliers=[], iterations=3, scores=lambda: s)
    history.record_model_fit(work, report(3.0), model=None, data=cap_a)
    history.record_model_fit(work, report(2.0), model=None, data=cap_b)
    e1, e2 = history.load_history(work)
    poses = (tmp_path / "a" / "poses.csv").resolve()
    assert e1["data"] == [{"path": str(poses), "role": "calibration_capture",
                           "sha256": trackcal._core.sha256_file(poses)}]
    assert e2["data"][0]["path"] == str((tmp_path / "b" / "poses.csv").resolve())
    row2 = history.history_table([e1, e2]).splitlines()[2]
    assert "other data" in row2 and "%" not in row2, row2


def test_fits_of_two_receivers_of_one_capture_are_not_compared(tmp_path):
    """trackcal fit --sensor 1 and --sensor 2 of one two-receiver capture read the same files: the
    history recorded no receiver, so the second row showed a change from the first (a "-40 %" that
    was another receiver's stations). Rows record the calibration's sensor; another receiver's row
    says so instead of a change, and rows written before the field still compare."""
    import types
    data = tmp_path / "poses.csv"
    data.write_text("x\n")
    work = tmp_path / "work"

    def report(pos, sensor):
        text = "terms:\n  - type: polynomial\n    degree: 2\n"
        s = {"valid": {"position_mm": {"mean": pos}, "orientation_deg": {"mean": 0.1}}}
        ns = types.SimpleNamespace(
            model={"text": text, "sha256": "ab" * 32, "source": "<string>", "terms": ["polynomial"]},
            terms=[{"type": "polynomial"}], converged=True, chi2_per_dof=1.0, num_free_parameters=60,
            outliers=[], iterations=3, scores=lambda: s)
        if sensor is not None:
            ns.calibration = types.SimpleNamespace(sensor=sensor)
        return ns
    history.record_model_fit(work, report(5.0, 1), model=None, data=data)
    history.record_model_fit(work, report(3.0, 2), model=None, data=data)
    history.record_model_fit(work, report(2.0, 2), model=None, data=data)
    history.record_model_fit(work, report(1.0, None), model=None, data=data)  # an older row's shape
    entries = history.load_history(work)
    assert [e.get("sensor") for e in entries] == [1, 2, 2, None]
    rows = history.history_table(entries).splitlines()
    assert "sensor 2" in rows[2] and "%" not in rows[2], rows[2]
    assert "-33.3%" in rows[3], rows[3]
    assert "-50.0%" in rows[4], rows[4]


def test_history_round_trip(tmp_path):
    data = tmp_path / "poses.csv"
    data.write_text("x\n")
    model = tmp_path / "model.json"
    model.write_text("{}\n")
    s1 = {"valid": {"position_mm": {"mean": 10.0}, "orientation_deg": {"mean": 2.0}}}
    s2 = {"valid": {"position_mm": {"mean": 4.0}, "orientation_deg": {"mean": 1.5}}}
    history.record_fit(tmp_path / "work", model=model, data=[(data, "calibration_capture")], scores=s1,
                       label="polynomial")
    model.write_text('{"changed": true}\n')
    history.record_fit(tmp_path / "work", model=model, data=[(data, "calibration_capture")], scores=s2,
                       label="+ sensor offset")
    entries = history.load_history(tmp_path / "work")
    assert [e["label"] for e in entries] == ["polynomial", "+ sensor offset"]
    assert entries[0]["model"]["sha256"] != entries[1]["model"]["sha256"]
    assert entries[0]["data"][0]["sha256"] == entries[1]["data"][0]["sha256"]
    assert entries[1]["scores"] == s2
    table = history.history_table(entries)
    assert "-60.0%" in table and "-25.0%" in table  # 10 -> 4 mm, 2 -> 1.5 deg
    r = run_cli("history", tmp_path / "work", "--plot", tmp_path / "h.png")
    assert "+ sensor offset" in r.stdout
    assert (tmp_path / "h.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_history_says_which_captures_were_changed_or_deleted_since_their_fits(tmp_path):
    # A row's scores are of the capture as it was fitted (its SHA-256). Re-exported or deleted
    # since, nothing said so: a user refitting "the same capture" got other numbers, or could not
    # find the file the rows name.
    kept, changed, gone = (tmp_path / f"{n}.csv" for n in ("kept", "changed", "gone"))
    for f in (kept, changed, gone):
        f.write_text(f"{f.name}\n")
    scores = {"valid": {"position_mm": {"mean": 1.0}, "orientation_deg": {"mean": 0.1}}}
    work = tmp_path / "work"
    for data in (kept, changed, changed, gone, kept):
        history.record_fit(work, model=None, data=[(data, "calibration_capture")], scores=scores)
    changed.write_text("re-exported\n")
    gone.unlink()
    entries = history.load_history(work)
    assert history.data_changed_notes(entries) == [
        f"{changed} (rows 2, 3): changed since it was fitted; the rows' scores are of the file as it was",
        f"{gone} (row 4): deleted since it was fitted; the row's scores are of the file as it was"]
    r = run_cli("history", work)
    assert r.stdout.splitlines()[-2:] == [f"note: {n}" for n in history.data_changed_notes(entries)]
    assert f"{kept} " not in r.stdout


def test_report_with_a_history_of_captures_changed_since_says_so(tmp_path, monkeypatch, capsys):
    # The report's history table and plot show the rows as recorded: its notes say which rows'
    # captures are no longer what they fitted, as `trackcal history` does.
    import types
    from trackcal import cli, report
    gone = tmp_path / "gone.csv"
    gone.write_text("x\n")
    history.record_fit(tmp_path / "work", model=None, data=[(gone, "calibration_capture")],
                       scores={"valid": {"position_mm": {"mean": 1.0}, "orientation_deg": {"mean": 0.1}}})
    gone.unlink()
    (tmp_path / "poses.csv").write_text("station\n")
    monkeypatch.setattr(cli, "_diagnosis", lambda args, term: (
        types.SimpleNamespace(origin=None, path=None), None, object(), None, None, None, None, []))
    written = {}

    def write_report(v, out_dir, **kw):
        written.update(kw)
        return pathlib.Path(out_dir) / "report.html"
    monkeypatch.setattr(report, "write_report", write_report)
    assert cli.main(["report", str(tmp_path / "poses.csv"), "-o", str(tmp_path / "out"),
                     "--workdir", str(tmp_path / "work")]) == 0
    note = f"history: {gone} (row 1): deleted since it was fitted; the row's scores are of the file as it was"
    assert note in written["notes"], written["notes"]
    assert f"note: {note}" in capsys.readouterr().out


def test_history_bad_line_names_file_and_line(tmp_path):
    (tmp_path / "history.jsonl").write_text('{"scores": {}}\n{"scores": \n')
    with pytest.raises(ValueError, match=r"history\.jsonl:2: column \d+: not JSON"):
        history.load_history(tmp_path)
    r = run_cli("history", tmp_path, check=False)
    assert r.returncode == 2 and "history.jsonl:2:" in r.stderr


def test_cli_validate_diagnose_report(tmp_path):
    cap_dir = simulate(tmp_path / "capture", seed=41)
    cap = captures.load_poses(cap_dir)
    cal_path = tmp_path / "cal.json"
    validation.fit_polynomial(cap.select_set("calib"), degree=3).save(cal_path)
    r = run_cli("validate", cap_dir, "-c", cal_path, "--cross-validate", "5")
    # The cross-validation table refits the default polynomial, not cal.json: its name says so.
    assert "valid set (120 poses)" in r.stdout and "cross-validation (5-fold, degree-3 polynomial)" in r.stdout
    # --json: one document a script can parse, nothing else on stdout.
    doc = json.loads(run_cli("validate", cap_dir, "-c", cal_path, "--cross-validate", "5", "--json").stdout)
    assert [t["set_name"] for t in doc["tables"]] == ["calib", "valid", "all",
                                                      "cross-validation (5-fold, degree-3 polynomial)"]
    assert doc["outside_volume"]["count"] == len(doc["outside_volume"]["stations"])
    assert "\033[" not in r.stdout  # not a terminal: no colour codes
    r = run_cli("diagnose", cap_dir, "-c", cal_path, "--permutations", "19")
    for heading in ("By distance from the transmitter", "By region", "Worst 10 stations", "Residual structure"):
        assert heading in r.stdout
    # The worst stations' coordinates carry their unit (the table's other columns name theirs).
    assert "reported position in the transmitter frame [m]" in r.stdout
    r = run_cli("report", cap_dir, "-c", cal_path, "-o", tmp_path / "rep", "--permutations", "19")
    assert (tmp_path / "rep" / "report.html").exists()
    assert "reported position in the transmitter frame [m]" in (tmp_path / "rep" / "report.html").read_text()
    assert (tmp_path / "rep" / "fig4_position_error_vs_distance.png").exists()


def test_diagnose_says_when_the_calibration_is_not_the_model_it_ranks(tmp_path):
    """-c cal.json --model other.yaml: the tables are cal.json's, the ranking refits other.yaml; a
    calibration fitted from another model file is named, in the text, the JSON and the report."""
    cap_dir = simulate(tmp_path / "capture", seed=45)
    m1, m2 = tmp_path / "m1.yaml", tmp_path / "m2.yaml"
    m1.write_text("terms:\n  - type: polynomial\n    degree: 2\n")
    m2.write_text("terms:\n  - type: polynomial\n    degree: 1\n")
    cal = tmp_path / "cal.json"
    assert run_cli("fit", "--data", cap_dir, "--model", m1, "-o", cal).returncode == 0
    args = ("diagnose", cap_dir, "-c", cal, "--effects", "sensor_offset", "--permutations", "0")
    same = run_cli(*args, "--model", m1)
    assert "was fitted from another model file" not in same.stdout
    other = run_cli(*args, "--model", m2)
    assert f"{cal} was fitted from another model file ({m1}) than --model {m2}" in other.stdout
    doc = json.loads(run_cli(*args, "--model", m2, "--json").stdout)
    assert any("was fitted from another model file" in n for n in doc["notes"])
    rep = run_cli("report", cap_dir, "-c", cal, "--model", m2, "--effects", "sensor_offset", "--no-covariates",
                  "-o", tmp_path / "rep")
    assert "was fitted from another model file" in (tmp_path / "rep" / "report.html").read_text()


def test_cli_errors_name_file_line_column(tmp_path):
    p = tmp_path / "poses.csv"
    header = ("station,set,sensor,time,rep_x,rep_y,rep_z,rep_qw,rep_qx,rep_qy,rep_qz,"
              "ref_x,ref_y,ref_z,ref_qw,ref_qx,ref_qy,ref_qz")
    good = "1,calib,1,0,0.1,0.2,0.3,1,0,0,0,0.1,0.2,0.3,1,0,0,0"
    bad = "2,calib,1,1,0.1,0.2,0.3,1,0,0,0,0.1,zz,0.3,1,0,0,0"
    p.write_text("\n".join([header, good, bad]) + "\n")
    r = run_cli("validate", p, check=False)
    assert r.returncode == 2
    assert "poses.csv:3: column ref_y: 'zz' is not a number" in r.stderr
    r = run_cli("validate", tmp_path / "missing.csv", check=False)
    assert r.returncode == 2 and "missing.csv" in r.stderr


def test_cli_colour_only_on_a_terminal(tmp_path):
    """On a pseudo-terminal the output is coloured; without one (the other tests) it is plain."""
    import pty
    cap_dir = simulate(tmp_path / "capture", seed=42)
    exe = shutil.which("trackcal")
    cmd = [exe] if exe else [sys.executable, "-m", "trackcal.cli"]
    out = bytearray()

    def read(fd):
        data = os.read(fd, 65536)
        out.extend(data)
        return data

    env_before = os.environ.pop("NO_COLOR", None)
    try:
        status = pty.spawn(cmd + ["diagnose", str(cap_dir), "--permutations", "9"], read)
    finally:
        if env_before is not None:
            os.environ["NO_COLOR"] = env_before
    assert os.waitstatus_to_exitcode(status) == 0
    text = out.decode(errors="replace")
    assert "\033[1mBy distance from the transmitter" in text
    assert "all set (600 poses), no correction" in text


def test_validate_records_history(tmp_path, capsys):
    from trackcal import cli
    cap_dir = simulate(tmp_path / "capture", seed=43)
    cap = captures.load_poses(cap_dir)
    cal1, cal3 = tmp_path / "r1.json", tmp_path / "r3.json"
    validation.fit_polynomial(cap.select_set("calib"), degree=1).save(cal1)
    validation.fit_polynomial(cap.select_set("calib"), degree=3).save(cal3)
    work = tmp_path / "work"
    assert cli.main(["validate", str(cap_dir), "-c", str(cal1), "--workdir", str(work), "--label", "r=1"]) == 0
    assert cli.main(["validate", str(cap_dir), "-c", str(cal3), "--workdir", str(work), "--label", "r=3"]) == 0
    # Says where it recorded, as trackcal fit does (it recorded silently).
    assert f"Recorded validation #2 in {work / 'history.jsonl'}" in capsys.readouterr().out
    entries = history.load_history(work)
    assert [e["label"] for e in entries] == ["r=1", "r=3"]
    # The higher degree lowers the validation error: the history shows the fall.
    assert history.headline_scores(entries[1])[0] < history.headline_scores(entries[0])[0]
    assert entries[0]["data"][0]["sha256"] == trackcal_sha(cap_dir / "poses.csv")
    # Each row keeps its calibration by content, as trackcal fit does: replacing r1.json (a later
    # fit to the same -o) does not take away the calibration row 1 scored.
    kept = work / entries[0]["model"]["copy"]
    assert kept.read_bytes() == cal1.read_bytes()
    assert trackcal_sha(kept) == entries[0]["model"]["sha256"]
    assert (work / entries[1]["model"]["copy"]).read_bytes() == cal3.read_bytes()


def test_validate_rows_of_two_receivers_of_one_capture_are_not_compared(tmp_path, capsys):
    """trackcal validate --sensor 1 and --sensor 2 of one two-receiver capture read the same file:
    validate rows recorded no receiver (fit rows do), so receiver 2's row showed a change from
    receiver 1's, another receiver's stations. Its row records the sensor and says so instead."""
    from trackcal import cli
    from understand_support import two_receivers, write_poses
    mixed, _ = two_receivers(simulate(tmp_path / "capture", seed=43))
    (tmp_path / "mixed").mkdir()
    data = write_poses(tmp_path / "mixed" / "poses.csv", mixed)
    work = tmp_path / "work"
    for n in (1, 2):
        cal = tmp_path / f"r{n}.json"
        validation.fit_polynomial(mixed.subset((mixed.sensor == n) & (mixed.set == "calib")),
                                  degree=2).save(cal)
        assert cli.main(["validate", str(data), "-c", str(cal), "--sensor", str(n), "--workdir",
                         str(work), "--label", f"receiver {n}"]) == 0
    entries = history.load_history(work)
    assert [e.get("sensor") for e in entries] == [1, 2]
    row = history.history_table(entries).splitlines()[2]
    assert "sensor 2" in row and "%" not in row, row


def trackcal_sha(path):
    import hashlib
    return hashlib.sha256(pathlib.Path(path).read_bytes()).hexdigest()


def test_validate_history_leaves_out_the_cross_validation_of_another_model(tmp_path):
    """`validate -c cal.json --cross-validate K --workdir W` cross-validates the default polynomial,
    not cal.json: on a capture without a valid set that table must not become cal.json's headline."""
    from trackcal import cli
    sim = simulate(tmp_path / "sim", seed=44)
    cap_dir = tmp_path / "capture"
    cap_dir.mkdir()
    lines = (sim / "poses.csv").read_text().splitlines(keepends=True)
    (cap_dir / "poses.csv").write_text("".join(l for l in lines if ",valid," not in l))
    cap = captures.load_poses(cap_dir)
    assert "valid" not in cap.sets
    cal = tmp_path / "r1.json"
    validation.fit_polynomial(cap.select_set("calib"), degree=1).save(cal)
    work = tmp_path / "work"
    assert cli.main(["validate", str(cap_dir), "-c", str(cal), "--workdir", str(work),
                     "--cross-validate", "2"]) == 0
    (e,) = history.load_history(work)
    assert sorted(e["scores"]) == ["all", "calib"]
    assert history.headline_set(e) == "all"
    v = validation.validate(cap, trackcal.Calibration.load(cal), analyse_covariates=False)
    expected = {t.set_name: t for t in v.tables}["all"].after_position_mm["mean"]
    assert history.headline_scores(e)[0] == pytest.approx(expected)


def test_history_plot_never_draws_over_the_history_or_a_capture(tmp_path, capsys):
    from trackcal import cli
    cap = tmp_path / "capture"
    cap.mkdir()
    data = cap / "poses.csv"
    data.write_text("x\n")
    model = tmp_path / "model.json"
    model.write_text("{}\n")
    work = tmp_path / "work"
    s = {"valid": {"position_mm": {"mean": 10.0}, "orientation_deg": {"mean": 2.0}}}
    history.record_fit(work, model=model, data=[(data, "calibration_capture")], scores=s, label="a")
    hist = (work / "history.jsonl").read_bytes()
    other = tmp_path / "notes.txt"
    other.write_text("mine\n")
    # A picture of the user's named .png (a PNG trackcal did not write) is not an earlier figure.
    picture = tmp_path / "setup.png"
    picture.write_bytes(b"\x89PNG\r\n\x1a\n" + b"\x00" * 32)
    capsys.readouterr()
    import matplotlib.pyplot as plt
    open_before = set(plt.get_fignums())
    for target, why in ((work / "history.jsonl", "refusing to overwrite an input"),
                        (data, "refusing to overwrite an input"),
                        (model, "refusing to overwrite an input"),
                        (other, "exists and is not a figure trackcal wrote"),
                        (picture, "exists and is not a figure trackcal wrote"),
                        (tmp_path, "is a folder"),
                        (tmp_path / "none" / "h.png", f"{tmp_path / 'none'} is not an existing folder")):
        assert cli.main(["history", str(work), "--plot", str(target)]) == 2, target
        err = capsys.readouterr().err
        assert err.startswith(f"error: {target}: {why}"), err
    assert (work / "history.jsonl").read_bytes() == hist
    assert data.read_text() == "x\n" and model.read_text() == "{}\n" and other.read_text() == "mine\n"
    assert picture.read_bytes() == b"\x89PNG\r\n\x1a\n" + b"\x00" * 32
    # A new file, and an earlier figure (a .png) replaced.
    for target in (tmp_path / "plot", tmp_path / "h.png", tmp_path / "h.png"):
        assert cli.main(["history", str(work), "--plot", str(target)]) == 0
        assert target.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # In-process (a script's loop), refused or written, no plot stays open in pyplot's registry.
    assert set(plt.get_fignums()) == open_before


def test_cli_refuses_unusable_outputs_up_front_in_one_line(tmp_path, capsys):
    """An output that cannot be written is refused before the work (the capture here does not even
    exist: the output is checked first), and a file the system refuses is one 'error:' line."""
    from trackcal import cli
    afile = tmp_path / "afile"
    afile.write_text("mine\n")
    missing = tmp_path / "no-capture"
    cases = [(["report", missing, "-o", afile], f"error: -o {afile}: exists and is not a folder"),
             (["report", missing, "-o", afile / "sub"],
              f"error: -o {afile / 'sub'}: {afile} is not a folder"),
             (["record", "--device", "raw=Nope@tcp://127.0.0.1:9", "--duration", "1", "-o", afile],
              f"error: -o {afile}: exists and is not a folder"),
             (["validate", missing, "-c", missing, "--workdir", afile],
              f"error: --workdir {afile}: exists and is not a folder"),
             (["diagnose", missing, "--permutations", "-1"], "error: --permutations -1: must be 0 or more"),
             (["report", missing, "-o", tmp_path / "r", "--permutations", "-5"],
              "error: --permutations -5: must be 0 or more"),
             (["diagnose", missing, "--top", "-1"], "error: --top -1: must be 0 or more"),
             # The ranking's options without --model were silently ignored.
             (["diagnose", missing, "-c", missing, "--effects", "dipole", "--folds", "3"],
              "error: --folds, --effects: options of the candidate ranking, which needs --model "
              "(the model file whose missing effects are ranked)"),
             (["report", missing, "-o", tmp_path / "r", "--cross-validate-top", "0"],
              "error: --cross-validate-top: options of the candidate ranking, which needs --model "
              "(the model file whose missing effects are ranked)"),
             (["record", "--device", "raw=Nope@tcp://127.0.0.1:9", "--duration", "-1", "-o", tmp_path / "rec"],
              "error: --duration -1.0: must be a positive number of seconds"),
             (["history", tmp_path / "no-work"], f"error: {tmp_path / 'no-work'}: no such work folder")]
    (tmp_path / "work" / "history.jsonl").mkdir(parents=True)  # an OSError: a folder where a file goes
    cases.append((["history", tmp_path / "work"],
                  f"error: {tmp_path / 'work' / 'history.jsonl'}: Is a directory"))
    for argv, line in cases:
        assert cli.main([str(a) for a in argv]) == 2, argv
        err = capsys.readouterr().err
        assert err == line + "\n", (argv, err)
    assert afile.read_text() == "mine\n" and not (tmp_path / "r").exists() and not (tmp_path / "rec").exists()
    p, q = np.zeros((30, 3)), np.tile([0.0, 0.0, 0.0, 1.0], (30, 1))
    with pytest.raises(ValueError, match="n_permutations -1: must be 0 or more"):
        validation.covariate_analysis(validation.residuals(p, q, p, q), {"x": np.arange(30.0)},
                                      n_permutations=-1)


GOOD = {"valid": {"position_mm": {"mean": 1.0}, "orientation_deg": {"mean": 0.1}}}


@pytest.mark.parametrize("line, field, what", [
    ('{"scores": []}', "scores", "expected an object of sets, got a list"),
    ('{"scores": {"valid": 3}}', "scores.valid", "expected an object with position_mm"),
    ('{"scores": {"valid": {"orientation_deg": {"mean": 1}}}}', "scores.valid.position_mm", "missing"),
    ('{"scores": {"valid": {"position_mm": [1], "orientation_deg": {"mean": 1}}}}',
     "scores.valid.position_mm", "expected an object with mean"),
    ('{"scores": {"valid": {"position_mm": {"std": 1}, "orientation_deg": {"mean": 1}}}}',
     "scores.valid.position_mm.mean", "missing"),
    ('{"scores": {"valid": {"position_mm": {"mean": "1.2"}, "orientation_deg": {"mean": 1}}}}',
     "scores.valid.position_mm.mean", "expected a number, got a string"),
    ('{"scores": {"valid": {"position_mm": {"mean": 1, "median": "x"}, "orientation_deg": {"mean": 1}}}}',
     "scores.valid.position_mm.median", "expected a number, got a string"),
    ('{"scores": {"all": {"position_mm": {"mean": 1}, "orientation_deg": {"mean": true}}}}',
     "scores.all.orientation_deg.mean", "expected a number, got true"),
    ('{"scores": {}, "model": "m.yaml"}', "model", "expected an object (path, sha256) or null, got a string"),
    ('{"scores": {}, "model": {"path": "m.yaml", "sha256": 5}}', "model.sha256",
     "expected a string, got a number"),
    ('{"scores": {}, "terms": "polynomial"}', "terms", "expected a list of term names"),
    ('{"scores": {}, "time_utc": null}', "time_utc", "expected a string, got null"),
    ('{"scores": {}, "data": 3}', "data", "expected a list of files, got a number"),
    # Shown in the table and the plot: a hand-edited null label was printed "None".
    ('{"scores": {}, "label": null}', "label", "expected a string, got null"),
    ('{"scores": {}, "label": ["+dipole"]}', "label", "expected a string, got a list"),
    # Compared between rows ("sensor N"): "2" and 2 were two receivers.
    ('{"scores": {}, "sensor": "2"}', "sensor", "expected the receiver's whole number, got a string"),
    ('{"scores": {}, "sensor": 1.5}', "sensor", "expected the receiver's whole number, got a number"),
    ('{"scores": {}, "sensor": NaN}', "sensor", "expected the receiver's whole number, got a number"),
])
def test_history_malformed_entry_names_file_line_and_field(tmp_path, capsys, line, field, what):
    from trackcal import cli
    path = tmp_path / "history.jsonl"
    path.write_text(json.dumps({"label": "ok", "scores": GOOD, "model": None}) + "\n" + line + "\n")
    with pytest.raises(ValueError) as err:
        history.load_history(tmp_path)
    assert str(err.value).startswith(f"{path}:2: field {field}: {what}")
    assert cli.main(["history", str(tmp_path)]) == 2
    assert capsys.readouterr().err == f"error: {err.value}\n"


def test_history_not_utf8_names_file_line_and_column(tmp_path):
    (tmp_path / "history.jsonl").write_bytes(b'{"scores": {}}\n{"scores": {}, "label": "caf\xe9"}\n')
    with pytest.raises(ValueError, match=r"history\.jsonl:2: column 29: not UTF-8 text \(byte 0xe9\)"):
        history.load_history(tmp_path)


def test_history_older_records_still_load(tmp_path):
    """Records of earlier versions: scores without median or flips, model null, no terms."""
    lines = [{"time_utc": "2024-01-01T00:00:00Z", "label": "first", "model": None, "data": [],
              "scores": GOOD},
             {"label": "flips", "model": {"path": "/m.json", "sha256": "ab" * 32}, "scores": {
                 "calib": {"position_mm": {"mean": 2, "std": 1, "max": 3, "median": 1.5},
                           "orientation_deg": {"mean": 0.2}, "hemisphere_flips_left_out": 0}}},
             {"scores": {}}]
    (tmp_path / "history.jsonl").write_text("".join(json.dumps(e) + "\n" for e in lines))
    entries = history.load_history(tmp_path)
    assert entries == lines
    assert "first" in history.history_table(entries)


def test_work_folder_copies_are_written_without_hard_links(tmp_path, monkeypatch):
    """On a file system without hard links (FAT, some network mounts) the content-named copies of a
    work folder are still written (by rename: replacing one is harmless), so the fit's row is kept."""
    import errno
    import os as os_module

    def no_link(src, dst):
        raise OSError(errno.EPERM, "Operation not permitted", src, None, dst)

    monkeypatch.setattr(os_module, "link", no_link)
    path = tmp_path / "models" / "0123456789abcdef.json"
    path.parent.mkdir()
    history._keep_copy(path, b"{}\n")
    assert path.read_bytes() == b"{}\n"


def test_history_truncated_last_line_keeps_earlier_entries(tmp_path, capsys):
    """A last line cut short (a crash or a full disk during a write, a script appending) loses only
    itself: `trackcal history` shows the fits before it with a warning, and the next fit's record
    takes its place instead of burying it between two entries (every later read would fail)."""
    from trackcal import cli
    path = tmp_path / "history.jsonl"
    whole = json.dumps({"label": "first", "scores": GOOD, "model": None}) + "\n"
    cut = json.dumps({"label": "second", "scores": GOOD, "model": None})[:25]
    path.write_text(whole + cut)
    with pytest.warns(history.HistoryWarning, match=r"history\.jsonl:2: last line is incomplete"):
        entries = history.load_history(tmp_path)
    assert [e["label"] for e in entries] == ["first"]
    assert cli.main(["history", str(tmp_path)]) == 0
    out, err = capsys.readouterr()
    assert "first" in out and err.startswith(f"warning: {path}:2: last line is incomplete")
    model = tmp_path / "m.json"
    model.write_text("{}")
    with pytest.warns(history.HistoryWarning, match=r"history\.jsonl:2: .*replaced by this fit's entry"):
        history.record_fit(tmp_path, model=model, data=[], scores=GOOD, label="third")
    assert [e["label"] for e in history.load_history(tmp_path)] == ["first", "third"]
    # A whole last line without its newline is an entry, not a cut.
    path.write_text(whole + whole.rstrip("\n"))
    assert len(history.load_history(tmp_path)) == 2


def test_history_last_line_that_no_write_began_is_an_error_not_dropped(tmp_path):
    """Only a line that starts as an entry (a JSON object, '{') can be a write cut short: any
    other unterminated last line (a file a tool or a person put there) is an error naming it, and
    recording a fit keeps it instead of replacing it."""
    path = tmp_path / "history.jsonl"
    whole = json.dumps({"label": "first", "scores": GOOD, "model": None}) + "\n"
    junk = "notes: refit after moving the cart"
    path.write_text(whole + junk)
    with pytest.raises(ValueError, match=r"history\.jsonl:2: column 1: not JSON"):
        history.load_history(tmp_path)
    model = tmp_path / "m.json"
    model.write_text("{}")
    with pytest.raises(ValueError, match=r"history\.jsonl:2: column 1: not JSON"):
        history.record_fit(tmp_path, model=model, data=[], scores=GOOD, label=lambda entries: "x")
    assert path.read_text() == whole + junk


def test_malformed_history_fails_before_the_work(tmp_path, monkeypatch, capsys):
    """report --workdir and fit --workdir read the history before the diagnosis or the fit: a
    malformed one fails at once, and fit writes no calibration it then cannot record."""
    from trackcal import cli
    work = tmp_path / "work"
    work.mkdir()
    (work / "history.jsonl").write_text('{"scores": []}\n')

    def no_work(*a, **k):
        raise AssertionError("the work ran before the history was read")
    monkeypatch.setattr(cli, "_diagnosis", no_work)
    monkeypatch.setattr(trackcal, "fit", no_work)
    (tmp_path / "poses.csv").write_text("station\n")
    (tmp_path / "m.yaml").write_text("terms: []\n")
    assert cli.main(["report", str(tmp_path / "poses.csv"), "-o", str(tmp_path / "out"),
                     "--workdir", str(work)]) == 2
    assert "history.jsonl:1: field scores" in capsys.readouterr().err
    assert cli.main(["fit", "--data", str(tmp_path / "poses.csv"), "--model", str(tmp_path / "m.yaml"),
                     "-o", str(tmp_path / "cal.json"), "--folds", "5", "--workdir", str(work)]) == 2
    assert "history.jsonl:1: field scores" in capsys.readouterr().err
    assert not (tmp_path / "cal.json").exists()


def test_report_workdir_without_a_history_is_not_silently_ignored(tmp_path, monkeypatch, capsys):
    """report --workdir names a folder whose history the report shows: a mistyped folder was read as
    an empty history, and the report came out without one and without a word (exit status 0). It is
    refused before the work, as `trackcal history` refuses it; a folder with no fits recorded yet
    gives a report with a note saying so."""
    import types
    from trackcal import cli, report
    (tmp_path / "poses.csv").write_text("station\n")
    calls = []

    def diagnosis(args, term):
        calls.append(args.workdir)
        capture = types.SimpleNamespace(origin=None, path=None)
        return capture, None, object(), None, None, None, None, []
    monkeypatch.setattr(cli, "_diagnosis", diagnosis)
    written = {}

    def write_report(v, out_dir, **kw):
        written.update(kw)
        return pathlib.Path(out_dir) / "report.html"
    monkeypatch.setattr(report, "write_report", write_report)
    out = tmp_path / "out"
    assert cli.main(["report", str(tmp_path / "poses.csv"), "-o", str(out),
                     "--workdir", str(tmp_path / "wrok")]) == 2
    assert f"--workdir {tmp_path / 'wrok'}: no such work folder" in capsys.readouterr().err
    assert calls == [] and not out.exists()
    work = tmp_path / "work"
    work.mkdir()
    assert cli.main(["report", str(tmp_path / "poses.csv"), "-o", str(out), "--workdir", str(work)]) == 0
    assert calls == [str(work)]
    assert any("history.jsonl: no fits recorded" in n for n in written["notes"]), written["notes"]
    assert "no fits recorded" in capsys.readouterr().out


def test_report_over_an_earlier_one_says_it_replaced_it(tmp_path, monkeypatch, capsys):
    # An earlier trackcal report in -o is replaced (a user's page there is refused): the command
    # said only "wrote out/report.html", as for a new folder, and the earlier page was gone.
    import types
    from trackcal import cli, report
    (tmp_path / "poses.csv").write_text("station\n")
    monkeypatch.setattr(cli, "_diagnosis", lambda args, term: (
        types.SimpleNamespace(origin=None, path=None), None, object(), None, None, None, None, []))

    def write_report(v, out_dir, **kw):
        (pathlib.Path(out_dir) / "report.html").write_text(f"<html><head>{report.GENERATOR_META}</head></html>")
        return pathlib.Path(out_dir) / "report.html"
    monkeypatch.setattr(report, "write_report", write_report)
    out = tmp_path / "out"
    out.mkdir()
    argv = ["report", str(tmp_path / "poses.csv"), "-o", str(out)]
    assert cli.main(argv) == 0
    assert capsys.readouterr().out.splitlines()[-1] == f"wrote {out / 'report.html'}"
    assert cli.main(argv) == 0
    assert capsys.readouterr().out.splitlines()[-1] == (
        f"wrote {out / 'report.html'} (replaced the earlier trackcal report there, and its figures)")


def test_validate_records_the_calibration_by_its_full_path(tmp_path, monkeypatch):
    """validate --workdir recorded -c as given: a relative path ("cal.json") named a file only from
    the folder validate ran in, while the capture files beside it and trackcal fit's rows carry
    full paths."""
    import types
    from trackcal import cli
    run = tmp_path / "run"
    run.mkdir()
    (run / "cal.json").write_text("{}\n")
    (run / "poses.csv").write_text("station\n")
    monkeypatch.chdir(run)
    v = types.SimpleNamespace(tables=[], capture=types.SimpleNamespace(
        origin={"files": ["poses.csv"]}, path=pathlib.Path("poses.csv")))
    args = types.SimpleNamespace(command="validate", workdir=str(tmp_path / "work"), calibration="cal.json",
                                 label=None)
    cli._record_history(args, v)
    entry, = history.load_history(tmp_path / "work")
    assert entry["model"]["path"] == str(run / "cal.json")
    assert entry["data"][0]["path"] == str(run / "poses.csv")
    assert entry["label"] == "cal.json"


def test_outputs_that_would_be_refused_are_refused_before_the_work(tmp_path, monkeypatch, capsys):
    """An existing --residuals file, or a report.html in -o that is not a trackcal report, is
    refused: it was refused only after the covariate tests, the model's fit and the candidate
    ranking had run (minutes), with nothing to show for them."""
    from trackcal import cli

    def no_work(*a, **k):
        raise AssertionError("the work ran before the outputs were checked")
    monkeypatch.setattr(cli, "_diagnosis", no_work)
    monkeypatch.setattr(cli, "_validation", no_work)
    poses = tmp_path / "poses.csv"
    poses.write_text("station\n")
    mine = tmp_path / "mine.csv"
    mine.write_text("precious\n")
    for command in (["validate"], ["diagnose"], ["report", "-o", str(tmp_path / "out")]):
        assert cli.main(command + [str(poses), "--residuals", str(mine)]) == 2, command
        assert f"{mine}: exists; residuals are never written" in capsys.readouterr().err
    out = tmp_path / "rep"
    out.mkdir()
    (out / "report.html").write_text("<html>my notes</html>")
    assert cli.main(["report", str(poses), "-o", str(out)]) == 2
    assert "report.html: exists and is not a trackcal report" in capsys.readouterr().err
    assert mine.read_text() == "precious\n" and list(out.iterdir()) == [out / "report.html"]


def test_report_without_covariates_does_not_call_them_clean(tmp_path):
    """report --no-covariates skips the covariate tests: its verdict must not say "nothing
    significant remains in the covariates" (it tested none)."""
    cap_dir = simulate(tmp_path / "capture", seed=46)
    model = tmp_path / "m.yaml"
    model.write_text("terms:\n  - type: polynomial\n    degree: 2\n")
    cal = tmp_path / "cal.json"
    run_cli("fit", "--data", cap_dir, "--model", model, "-o", cal)
    run_cli("report", cap_dir, "-c", cal, "--no-covariates", "-o", tmp_path / "rep")
    page = (tmp_path / "rep" / "report.html").read_text()
    verdict = page.split("<h2>Verdict</h2>", 1)[1].split("</p>", 1)[0]
    assert "in the covariates" not in verdict, verdict
    assert "covariates not tested" in verdict, verdict


def test_history_plot_of_an_empty_history_is_an_error(tmp_path, capsys):
    """`trackcal history W --plot P` with no fits recorded exited 0 without writing P: a script that
    asked for the figure found it missing only later."""
    from trackcal import cli
    work = tmp_path / "work"
    work.mkdir()
    plot = tmp_path / "h.png"
    assert cli.main(["history", str(work), "--plot", str(plot)]) == 2
    err = capsys.readouterr().err
    assert f"--plot {plot}: not written" in err and "no fits recorded" in err, err
    assert not plot.exists()
    assert cli.main(["history", str(work)]) == 0  # the table alone: an empty history is no error
    assert "no fits recorded" in capsys.readouterr().out


def test_validate_workdir_without_calibration_is_refused_before_the_work(tmp_path, capsys, monkeypatch):
    """`validate CAPTURE --workdir W` without -c was refused only after the validation and its
    covariate tests (minutes on a real capture)."""
    from trackcal import cli
    cap_dir = simulate(tmp_path / "capture", seed=45)
    called = []

    def validate(*args, **kwargs):
        called.append(args)
        raise AssertionError("the validation ran")
    import trackcal.validation as tv
    monkeypatch.setattr(tv, "validate", validate)
    assert cli.main(["validate", str(cap_dir), "--workdir", str(tmp_path / "work")]) == 2
    err = capsys.readouterr().err
    assert "--workdir records a fit: give its calibration with -c" in err, err
    assert not called
    assert not (tmp_path / "work" / "history.jsonl").exists()


def test_errors_on_a_redirected_stderr_are_plain_text(tmp_path, monkeypatch):
    """`trackcal history work 2> errors.log` from a terminal: stdout is a terminal, stderr a file.
    The error line was coloured by whether stdout is a terminal, so the log got escape codes
    ("\\033[31merror: \\033[0m..."); the warning of a history cut short too."""
    import io
    from trackcal import cli

    class Tty(io.StringIO):
        def isatty(self):
            return True
    monkeypatch.delenv("NO_COLOR", raising=False)
    err = io.StringIO()
    monkeypatch.setattr(sys, "stdout", Tty())
    monkeypatch.setattr(sys, "stderr", err)
    assert cli.main(["history", str(tmp_path / "missing")]) == 2
    assert err.getvalue() == f"error: {tmp_path / 'missing'}: no such work folder\n"
    work = tmp_path / "work"
    data = tmp_path / "poses.csv"
    data.write_text("x\n")
    history.record_fit(work, model=None, data=[(data, "calibration_capture")], label="one",
                       scores={"valid": {"position_mm": {"mean": 1.0}, "orientation_deg": {"mean": 0.1}}})
    with open(work / history.HISTORY_FILE, "ab") as f:
        f.write(b'{"scores": {"val')  # a write cut short
    err.seek(0)
    err.truncate()
    assert cli.main(["history", str(work)]) == 0
    assert err.getvalue().startswith("warning: ") and "\033" not in err.getvalue()
    # And the other way round: stderr a terminal, stdout piped: the error is coloured there.
    tty_err = Tty()
    monkeypatch.setattr(sys, "stdout", io.StringIO())
    monkeypatch.setattr(sys, "stderr", tty_err)
    assert cli.main(["history", str(tmp_path / "missing")]) == 2
    assert tty_err.getvalue().startswith("\033[31merror: \033[0m")


def test_validate_records_the_calibration_it_scored_not_one_written_meanwhile(tmp_path, monkeypatch):
    """`validate -c cal.json --workdir W` hashed cal.json when it recorded, after the validation:
    a `trackcal fit -o cal.json` finishing meanwhile (another terminal; `--cross-validate K` refits
    for a while) gave the new calibration's SHA-256 to the old calibration's scores."""
    from trackcal import cli
    cap_dir = simulate(tmp_path / "capture", seed=45)
    cap = captures.load_poses(cap_dir)
    cal, other = tmp_path / "cal.json", tmp_path / "other.json"
    validation.fit_polynomial(cap.select_set("calib"), degree=1).save(cal)
    validation.fit_polynomial(cap.select_set("calib"), degree=2).save(other)
    scored = trackcal_sha(cal)
    real_validate = validation.validate

    def validate_then_refit(*args, **kwargs):
        v = real_validate(*args, **kwargs)
        shutil.copyfile(other, cal)  # the other fit replaces cal.json while this one runs
        return v
    monkeypatch.setattr(validation, "validate", validate_then_refit)
    work = tmp_path / "work"
    assert cli.main(["validate", str(cap_dir), "-c", str(cal), "--workdir", str(work)]) == 0
    (e,) = history.load_history(work)
    assert trackcal_sha(cal) != scored
    assert e["model"]["sha256"] == scored
    assert e["data"][0]["sha256"] == trackcal_sha(cap_dir / "poses.csv")


def test_fit_output_into_the_kept_copies_is_refused(tmp_path, monkeypatch, capsys):
    """`trackcal fit -o WORK/models/<sha>.json --workdir WORK` replaced an earlier fit's kept copy of
    its calibration (the copy then held the new fit under the old file's hash name), so the history
    no longer led to the calibration that row scored."""
    from trackcal import cli

    def no_fit(*a, **k):
        raise AssertionError("the fit ran before the output was checked")
    monkeypatch.setattr(trackcal, "fit", no_fit)
    work = tmp_path / "work"
    (work / "models").mkdir(parents=True)
    # A kept copy is a calibration file, which check_calibration_output alone would let -o replace.
    example = pathlib.Path(__file__).resolve().parents[2] / "tests" / "data" / "calibration" / "example.json"
    kept = work / "models" / "0123456789abcdef.json"
    shutil.copy(example, kept)
    model = tmp_path / "m.yaml"
    model.write_text("terms:\n  - type: polynomial\n    degree: 1\n")
    for output in (kept, work / "models" / "new.json"):
        assert cli.main(["fit", "--data", str(tmp_path), "--model", str(model), "-o", str(output),
                         "--workdir", str(work)]) == 2
        assert "inside the work folder's models/" in capsys.readouterr().err
    assert kept.read_bytes() == example.read_bytes() and sorted(p.name for p in (work / "models").iterdir()) == [kept.name]


def test_fit_records_the_capture_it_fitted_not_one_changed_meanwhile(tmp_path, monkeypatch):
    """`trackcal fit --workdir W` hashed the capture when it recorded, after the fit (minutes for a
    physical model): a poses.csv re-exported meanwhile lent its SHA-256 to the scores of the old
    stations, while the calibration file's provenance named the old one, and the next fit on the
    new file was compared with this row as a step of one loop instead of "other data"."""
    from trackcal import cli
    cap_dir = simulate(tmp_path / "capture", seed=46)
    poses = cap_dir / "poses.csv"
    fitted = trackcal_sha(poses)
    model = tmp_path / "m.yaml"
    model.write_text("terms:\n  - type: polynomial\n    degree: 1\n")
    real_fit = trackcal.fit

    def fit_then_change_the_capture(*args, **kwargs):
        report = real_fit(*args, **kwargs)
        with open(poses, "a") as f:  # the capture re-exported while the fit ran
            f.write(poses.read_text().splitlines()[-1] + "\n")
        return report
    monkeypatch.setattr(trackcal, "fit", fit_then_change_the_capture)
    work, cal = tmp_path / "work", tmp_path / "cal.json"
    assert cli.main(["fit", "--data", str(cap_dir), "--model", str(model), "-o", str(cal),
                     "--workdir", str(work)]) == 0
    (e,) = history.load_history(work)
    assert trackcal_sha(poses) != fitted
    assert e["data"] == [{"path": str(poses.resolve()), "role": "calibration_capture", "sha256": fitted}]
    provenance = json.loads(cal.read_text())["provenance"]["inputs"]
    assert fitted in [i["sha256"] for i in provenance if i["role"] == "calibration_capture"]


def test_fit_says_which_row_is_its_own_when_another_fit_records_meanwhile(tmp_path, monkeypatch, capsys):
    """`trackcal fit --workdir W` numbered its fit by the history's length read after recording,
    and printed the last two rows as its own and the one before: a fit from another terminal
    recorded in between made it say "Recorded fit #3" of fit #2 and show the other fit's row."""
    from trackcal import cli
    cap_dir = simulate(tmp_path / "capture", seed=47)
    model = tmp_path / "m.yaml"
    work = tmp_path / "work"
    args = ["--data", str(cap_dir), "--model", str(model), "--workdir", str(work)]
    model.write_text("terms:\n  - type: polynomial\n    degree: 1\n")
    assert cli.main(["fit", *args, "-o", str(tmp_path / "c1.json")]) == 0
    real_record = history.record_model_fit

    def record_then_another_fit_records(*a, **k):
        entry = real_record(*a, **k)
        s = {"valid": {"position_mm": {"mean": 99.0}, "orientation_deg": {"mean": 9.0}}}
        history.record_fit(work, model=None, data=[(cap_dir / "poses.csv", "calibration_capture")],
                           scores=s, label="other terminal")
        return entry
    monkeypatch.setattr(history, "record_model_fit", record_then_another_fit_records)
    model.write_text("terms:\n  - type: polynomial\n    degree: 2\n")
    capsys.readouterr()
    assert cli.main(["fit", *args, "-o", str(tmp_path / "c2.json"), "--label", "mine"]) == 0
    out = capsys.readouterr().out
    assert [e["label"] for e in history.load_history(work)] == ["polynomial", "mine", "other terminal"]
    assert "Recorded fit #2 in" in out, out
    table = out[out.index("Recorded fit"):].splitlines()[2:]
    assert [r.split()[0] for r in table] == ["1", "2"] and "mine" in table[1] and "other terminal" not in out


def test_history_plot_of_many_fits_stays_readable(tmp_path):
    """A work folder of 200 fits drew 200 rotated labels under the plot: they overlapped into a
    black band taller than the axes, and one grid line per fit. Beyond 20 fits the ticks are the
    fits' numbers (the table's #), a readable few."""
    import matplotlib.pyplot as plt
    from trackcal import figures
    data = tmp_path / "poses.csv"
    data.write_text("x\n")

    def entries(n):
        return [{"label": f"+dipole step {i} of a long loop", "data": [{"path": str(data), "sha256": "ab"}],
                 "scores": {"valid": {"position_mm": {"mean": 30 * 0.98 ** i},
                                      "orientation_deg": {"mean": 3 * 0.98 ** i}}}} for i in range(n)]
    fig = figures.history_plot(entries(200))
    try:
        ax = fig.axes[0]
        fig.canvas.draw()
        lo, hi = ax.get_xlim()
        ticks = [t for t in ax.get_xticks() if lo <= t <= hi]
        assert 2 <= len(ticks) <= 20, ticks
        assert all(float(t).is_integer() and 1 <= t <= 200 for t in ticks), ticks
        assert "#" in ax.get_xlabel()
        # The tick labels fit below the axes: no taller than a fifth of the figure.
        renderer = fig.canvas.get_renderer()
        heights = [t.get_window_extent(renderer).height for t in ax.get_xticklabels() if t.get_text()]
        assert max(heights) < fig.bbox.height / 5
    finally:
        plt.close(fig)
    fig = figures.history_plot(entries(5))  # a short loop keeps its labels
    try:
        assert [t.get_text() for t in fig.axes[0].get_xticklabels()] == [e["label"] for e in entries(5)]
    finally:
        plt.close(fig)


def test_validate_says_which_row_is_its_own_when_another_fit_records_meanwhile(tmp_path, monkeypatch, capsys):
    """`trackcal validate --workdir W` numbered its row by the history's length, as fit did."""
    from trackcal import cli
    cap_dir = simulate(tmp_path / "capture", seed=48)
    cal = tmp_path / "cal.json"
    validation.fit_polynomial(captures.load_poses(cap_dir).select_set("calib"), degree=1).save(cal)
    work = tmp_path / "work"
    real_record = history.record_fit

    def record_then_another_fit_records(*a, **k):
        entry = real_record(*a, **k)
        real_record(work, model=None, data=[], label="other terminal",
                    scores={"valid": {"position_mm": {"mean": 9.0}, "orientation_deg": {"mean": 1.0}}})
        return entry
    monkeypatch.setattr(history, "record_fit", record_then_another_fit_records)
    capsys.readouterr()
    assert cli.main(["validate", str(cap_dir), "-c", str(cal), "--workdir", str(work), "--label", "mine"]) == 0
    assert [e["label"] for e in history.load_history(work)] == ["mine", "other terminal"]
    assert "Recorded validation #1 in" in capsys.readouterr().out


def test_a_record_removes_the_temporaries_of_writers_killed_mid_write(tmp_path):
    """history.jsonl is rewritten through a temporary copy renamed over it; a writer killed with
    SIGKILL between the two left its copy, a whole history, in the work folder for good (3 of 6
    records killed at random left 2-4.5 MB each). The next record, holding the lock every writer
    holds while its copy exists, removes them; other files are left alone."""
    work = tmp_path / "work"
    s = {"valid": {"position_mm": {"mean": 1.0}, "orientation_deg": {"mean": 0.1}}}
    history.record_fit(work, model=None, data=[], scores=s, label="a")
    killed = work / ".history.jsonl.tmp-0badf00d"
    killed.write_bytes((work / "history.jsonl").read_bytes())  # what a killed writer leaves
    others = [work / ".poses.csv.tmp-0badf00d", work / "history.jsonl.tmp-notes"]
    for o in others:
        o.write_text("mine\n")
    history.record_fit(work, model=None, data=[], scores=s, label="b")
    assert not killed.exists()
    assert all(o.read_text() == "mine\n" for o in others)
    assert [e["label"] for e in history.load_history(work)] == ["a", "b"]
