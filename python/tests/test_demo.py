"""The README's main job, run as a script would: --no-serve, and a short serve; the model-file edits
of its loop."""

import json
import shutil
import socket
from pathlib import Path

import numpy as np
import pytest

from trackcal import demo

import test_workflow as workflow  # the workflow tests' rule for spurious terms

ROOT = Path(__file__).resolve().parents[2]
SMALL_SCENE = ROOT / "tests" / "data" / "workflow" / "paper_small.yaml"

tools = pytest.mark.skipif(shutil.which("trackcal-simulate") is None,
                           reason="command-line tools not installed (run scripts/build.sh)")


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# ---- the base model on few heights ----

def _grid_poses(path: Path, heights: int, jitter: float = 0.002) -> Path:
    """A poses.csv of an 8 x 6 grid at `heights` heights 0.15 m apart (positions jittered by up to
    `jitter` m, as stations placed by hand are), plus scattered validation stations."""
    rng = np.random.default_rng(4)
    rows = ["station,set,sensor,time,rep_x,rep_y,rep_z,rep_qw,rep_qx,rep_qy,rep_qz,"
            "ref_x,ref_y,ref_z,ref_qw,ref_qx,ref_qy,ref_qz"]
    points = [("calib", np.array([0.15 * i, 0.15 * j, -0.35 - 0.15 * k]) + rng.uniform(-jitter, jitter, 3))
              for i in range(8) for j in range(6) for k in range(heights)]
    points += [("valid", rng.uniform([0, 0, -1.0], [1.05, 0.75, -0.3])) for _ in range(20)]
    for n, (set_name, p) in enumerate(points, start=1):
        xyz = ",".join(f"{v:.6f}" for v in p)
        rows.append(f"{n},{set_name},1,{n},{xyz},1,0,0,0,{xyz},1,0,0,0")
    path.write_text("\n".join(rows) + "\n")
    return path


def test_grid_layers_counts_a_grid_s_heights_and_no_layers_in_scattered_stations():
    rng = np.random.default_rng(1)
    for seed in range(20):  # a wide gap in scattered stations splits them into two thick halves
        assert demo.grid_layers(np.random.default_rng(seed).uniform(size=300)) == 0, seed
    heights = np.repeat([-0.8, -0.65, -0.5, -0.35], 48) + rng.uniform(-0.002, 0.002, 192)
    assert demo.grid_layers(heights) == 4, "hand-placed stations 2 mm off their heights"
    assert demo.grid_layers(np.full(10, 0.3)) == 1
    assert demo.grid_layers([0.1, 0.2]) == 0, "too few to tell"


def test_the_base_shrinks_the_polynomial_only_on_fewer_heights_than_its_degree_needs(tmp_path):
    text, why = demo.base_model_for(_grid_poses(tmp_path / "four.csv", 4))
    assert text == demo.PAPER_MODEL_FEW_HEIGHTS and "ridge: auto" in text
    assert why == ("the calibration stations lie on 4 layers along z, fewer than the 5 a degree-4 "
                   "polynomial needs: its base gets ridge: auto")
    assert demo.base_model_for(_grid_poses(tmp_path / "five.csv", 5)) == (demo.PAPER_MODEL, None)
    # The same polynomial otherwise: the edits of the loop see the same items.
    assert demo.PAPER_MODEL_FEW_HEIGHTS.replace("    ridge: auto\n", "").endswith(
        demo.PAPER_MODEL[demo.PAPER_MODEL.index("terms:"):])


# ---- model-file edits (contract B's model_change / insert_index) ----

def test_apply_model_change_inserts_a_term_before_the_given_index():
    text = demo.apply_model_change(
        demo.PAPER_MODEL, "- type: dipole\n  location_in_transmitter: [0.6, 0.95, -0.5]\n", 0)
    lines = text.splitlines()
    i = lines.index("  - type: dipole")
    assert lines[i + 1] == "    location_in_transmitter: [0.6, 0.95, -0.5]"
    assert lines[i + 2] == "  - type: polynomial", "the physical term goes before the polynomial"
    assert text.startswith("# The paper's method"), "comments are kept"
    text = demo.apply_model_change(text, "- type: plane\n", 1)
    assert [l.strip() for l in text.splitlines() if "- type:" in l] == \
        ["- type: dipole", "- type: plane", "- type: polynomial"]
    end = demo.apply_model_change(text, "- type: lut\n  cell_size_mm: 100\n", None)
    assert end.rstrip().endswith("  - type: lut\n    cell_size_mm: 100")


def test_apply_model_change_adds_or_replaces_a_top_level_key():
    text = demo.apply_model_change(demo.PAPER_MODEL, "loss:\n  type: cauchy\n  scale: 3\n", None)
    lines = text.splitlines()
    assert lines.index("loss:") < lines.index("terms:")
    assert "  scale: 3" in lines
    text = demo.apply_model_change(text, "loss:\n  type: huber\n", None)
    assert text.count("loss:") == 1 and "  type: huber" in text and "cauchy" not in text


@pytest.mark.parametrize("change,index,message", [
    ("- type: dipole\n", 5, "outside"),
    ("   \n", 0, "empty"),
    ("[1, 2]\n", None, "neither"),
])
def test_apply_model_change_rejects_what_it_cannot_place(change, index, message):
    with pytest.raises(ValueError, match=message):
        demo.apply_model_change(demo.PAPER_MODEL, change, index)


_TWO_DIPOLES = """terms:
  - type: sensor_offset
  - type: dipole
    location_in_transmitter: [0.455, 0.001, 0.415]
    polarisability_m3: -0.0134
  # the floor's mirror image?
  - type: dipole
    location_in_transmitter: [-0.038, -0.260, 1.326]
    polarisability_m3: -0.257

  - type: polynomial
    degree: 4
"""


def test_apply_model_change_replaces_the_named_term_in_place():
    plane = "- type: plane\n  normal_in_transmitter: [0, 0, 1]\n  attenuation: 0.26\n"
    text = demo.apply_model_change(_TWO_DIPOLES, plane, 2, "dipole_2")
    assert [l.strip() for l in text.splitlines() if "- type:" in l] == \
        ["- type: sensor_offset", "- type: dipole", "- type: plane", "- type: polynomial"]
    assert "1.326" not in text and "-0.257" not in text, "the replaced dipole is gone"
    assert "0.415" in text, "the other dipole stays"
    assert "  # the floor's mirror image?" in text, "comments between items stay"
    assert "    attenuation: 0.26" in text
    named = _TWO_DIPOLES.replace("  - type: dipole\n    location_in_transmitter: [-0.038",
                                 "  - type: dipole\n    name: image\n    location_in_transmitter: [-0.038")
    assert "1.326" not in demo.apply_model_change(named, plane, 2, "image")
    # Names as the model file gives them, whatever the item's layout: a one-line flow item and keys
    # indented further than usual (a nested `name:` is not the term's).
    odd = "terms:\n  - {type: dipole, name: a}\n  -   type: dipole\n      parameters:\n" \
          "        polarisability_m3: {name: x}\n  - type: dipole\n"
    assert [l.strip() for l in demo.apply_model_change(odd, "- type: plane\n", 2, "dipole_2")
            .splitlines()][1:] == ["- {type: dipole, name: a}", "-   type: dipole", "parameters:",
                                   "polarisability_m3: {name: x}", "- type: plane"]


def test_a_replacement_keeps_the_comments_of_its_neighbours_where_they_were():
    text = demo.apply_model_change(_TWO_DIPOLES.replace("polarisability_m3: -0.0134\n",
                                                        "polarisability_m3: -0.0134\n    # fixed: true\n"),
                                   "- type: plane\n", 1, "dipole")
    assert text.splitlines() == [
        "terms:", "  - type: sensor_offset", "  - type: plane", "  # the floor's mirror image?",
        "  - type: dipole", "    location_in_transmitter: [-0.038, -0.260, 1.326]",
        "    polarisability_m3: -0.257", "", "  - type: polynomial", "    degree: 4"], \
        "the item's own commented-out key goes with it; the comment before the next item stays there"


@pytest.mark.parametrize("layout,names", [
    ("terms:\n  -\n    type: dipole\n  - type: dipole\n", ["dipole", "dipole_2"]),
    ("terms:\n  - {type: dipole}  # the frame\n  - type: dipole\n", ["dipole", "dipole_2"]),
    ("terms:\n  - {type: dipole,\n     name: a}\n  - type: dipole\n", ["a", "dipole"]),
    ("terms:\n  -  # the frame\n    type: plane\n    name: b  # floor\n  - type: plane\n", ["b", "plane"]),
])
def test_a_replacement_reads_the_names_of_every_layout(layout, names):
    # Each item is found under the name the model file gives it, whatever its layout, and only that
    # item is replaced (the other keeps its lines).
    other = "lut"
    for i, name in enumerate(names):
        new = demo.apply_model_change(layout, f"- type: {other}\n", i, name)
        items = [l for l in new.splitlines() if l.startswith("  -")]
        assert len(items) == 2 and items[i] == f"  - type: {other}", new
        with pytest.raises(ValueError, match="replaces"):
            demo.apply_model_change(layout, f"- type: {other}\n", i, name + "_9")


@pytest.mark.parametrize("change", ["loss:\n  type: cauchy\n", "- type: plane\n- type: plane\n"])
def test_a_replacement_must_be_one_term(change):
    with pytest.raises(ValueError, match="one terms: item"):
        demo.apply_model_change(_TWO_DIPOLES, change, 2, "dipole_2")


@pytest.mark.parametrize("index,replaces", [(1, "dipole_2"), (2, "dipole_3"), (0, "sensor_offset"),
                                            (4, "dipole_2")])
def test_apply_model_change_refuses_to_replace_another_term(index, replaces):
    # The item at the index must be the dipole or plane the diagnosis named: a model file edited
    # since the diagnosis must not lose a different term.
    with pytest.raises(ValueError, match="replaces"):
        demo.apply_model_change(_TWO_DIPOLES, "- type: plane\n", index, replaces)


def test_apply_model_change_needs_a_terms_list():
    with pytest.raises(ValueError, match="terms"):
        demo.apply_model_change("noise:\n  position_mm: 1\n", "- type: plane\n", 0)


def test_top_significant_takes_the_verdicts_candidate():
    doc = {"candidates": [{"effect": "plane", "significant": False},
                          {"effect": "dipole", "significant": True},
                          {"effect": "near_field", "significant": True}],
           "verdict": {"effect": "dipole"}}
    assert demo.top_significant(doc)["effect"] == "dipole"
    doc["candidates"][1]["significant"] = doc["candidates"][2]["significant"] = False
    doc["verdict"] = {"effect": None}
    assert demo.top_significant(doc) is None


def test_write_new_never_overwrites(tmp_path):
    p = demo._write_new(tmp_path / "m.yaml", "a\n")
    with pytest.raises(SystemExit, match="not overwriting"):
        demo._write_new(p, "b\n")
    assert p.read_text() == "a\n"
    assert [x.name for x in tmp_path.iterdir()] == ["m.yaml"], "no temporary file left behind"


# ---- the main job ----

@tools
def test_demo_without_serving_writes_a_fresh_work_folder(tmp_path, capsys):
    args = ["--work", str(tmp_path), "--no-serve", "--seed", "7", "--scene", str(SMALL_SCENE)]
    assert demo.main(args + ["--max-steps", "0"]) == 0
    # One change only: a diagnosis costs a minute or more (the whole loop: docs/understand.md).
    assert demo.main(args + ["--max-steps", "1"]) == 0
    runs = sorted(p for p in tmp_path.iterdir() if p.is_dir())
    assert len(runs) == 2, "a second run must not reuse the first run's folder"
    for run in runs:
        assert (run / "capture" / "poses.csv").is_file()
        assert (run / "report" / "report.html").is_file()
    out = capsys.readouterr().out
    if demo.diagnosis_available():
        first, second = (json.loads(l) for l in
                         ((r / "history.jsonl").read_text().splitlines()[-1] for r in runs))
        assert first["label"] == "base"
        models = sorted((runs[1] / "models").glob("step*.yaml"))
        assert len(models) == 2, "the loop added the top candidate and refitted"
        assert "missing effect:" in out and "model-file change:" in out
        assert "noise floor (truth)" in out, "the table compares with the simulator's floor"
        # --max-steps stopped both loops before they diagnosed the final model: the page said
        # "catalog effects not tested: give --model to rank them" right after the loop ranked them.
        pages = [(r / "report" / "report.html").read_text() for r in runs]
        assert not any("give --model" in p for p in pages)
        assert "--max-steps 0 stopped the loop before any diagnosis" in pages[0]
        assert ("catalog effects last ranked for the model of step 0" in pages[1]
                and "the final model (step 1) was not ranked again: --max-steps 1" in pages[1]), pages[1]
    else:
        for run in runs:
            assert (run / "paper_polynomial.json").is_file()
        assert "validation, uncorrected" in out


@pytest.fixture(scope="module")
def main_job(tmp_path_factory):
    """The main job's whole loop as ``./scripts/demo.sh --no-serve`` runs it (DEFAULT_SCENE, the
    default hidden sensor offset and seed), run once for the tests below: (capture, floor, steps,
    story). About 3 min of diagnoses on 2 shared cores."""
    if shutil.which("trackcal-simulate") is None:
        pytest.skip("command-line tools not installed (run scripts/build.sh)")
    if not demo.diagnosis_available():
        pytest.skip("no candidate ranking in this build")
    tmp_path = tmp_path_factory.mktemp("main_job")
    scene = demo._write_new(tmp_path / "scene.yaml", demo.DEFAULT_SCENE)
    capture = demo.simulate(tmp_path, demo.DEFAULT_HIDDEN, None, str(scene))
    floor = demo.noise_floor(capture)
    log = []
    steps = demo.follow_diagnosis(capture, demo.PAPER_MODEL, tmp_path / "work",
                                  max_steps=demo.DEFAULT_MAX_STEPS, say=log.append, record=False,
                                  cross_validate_top=demo.DEFAULT_CROSS_VALIDATE_TOP)
    story = "\n".join(log) + "\n" + demo.steps_table(steps, floor)
    return capture, floor, steps, story


def test_the_main_job_names_the_sensor_offset_first_and_ends_within_1_5_times_the_floor(main_job):
    """The first change is the hidden effect, and the loop ends within the issue's 1.5 times the
    noise floor on the validation set, position and orientation. Measured (branch farsrc): 1.498x /
    1.136x after sensor offset, workbench frame and floor plane, the far CRT monitors (1.9 m) left
    to the polynomial: not identified by this capture, and not claimed (before: 1.29x / 1.11x with
    a spurious plane standing in for the +y monitors; earlier 3.24x / 1.85x when the floor plane's
    search ran off)."""
    capture, floor, steps, story = main_job
    assert len(steps) >= 2 and steps[1].label == "+sensor_offset", story
    final = steps[-1]
    assert final.held_out.get("set") == "valid", story
    assert final.position_mm <= 1.5 * floor["position_mm"]["mean"], story
    assert final.orientation_deg <= 1.5 * floor["orientation_deg"]["mean"], story


def test_the_main_job_adds_no_spurious_term(main_job):
    """Every physical term of the final model is one of the scene's sources: the hidden sensor
    offset or the room's (workbench frame, floor, monitors, door), as test_workflow.py's rule
    judges it (a plane never represents objects). Measured (branch farsrc): sensor offset,
    workbench frame, floor plane, then nothing. Before, a fourth term, plane_2, 1.70 m along
    (0.46, 0.84, 0.28) with its normal open by 19.9 deg, stood in for crt_monitor_1 and
    crt_monitor_2; a plane whose normal is not determined is no longer claimed (docs/diagnose.md,
    condition 5), and the verdict names the +y structure as not identified."""
    capture, floor, steps, story = main_job
    spurious = workflow._spurious_terms(steps[-1].fit, workflow._truth(capture))
    assert not spurious, "spurious " + "; ".join(spurious) + "\n" + story


@tools
def test_demo_serves_with_the_emulator_until_told_to_stop(tmp_path):
    port = _free_port()
    assert demo.main(["--work", str(tmp_path), "--serve-seconds", "3", "--port", str(port),
                      "--max-steps", "0", "--scene", str(SMALL_SCENE)]) == 0
    run = next(p for p in tmp_path.iterdir() if p.is_dir())
    cfg = (run / "vrpn.cfg").read_text()
    assert "vrpn_Tracker_Fastrak Tracker0" in cfg
    assert "trackcal_Calibration Tracker0" in cfg and "raw=Tracker0_raw" in cfg
    assert "opened at 115200 baud" in (run / "server.log").read_text()


@tools
def _small_capture(tmp_path: Path) -> Path:
    """The workflow tests' scene, seed 3, simulated into tmp_path / "capture"."""
    import subprocess
    capture = tmp_path / "capture"
    subprocess.run(["trackcal-simulate", "--scene", str(SMALL_SCENE), "--seed", "3", "-o", str(capture)],
                   check=True, capture_output=True)
    return capture


def _one_change_ranking(calls: list, candidate: dict):
    """A stand-in for run_diagnose that proposes ``candidate`` once and then nothing; each call's
    model text goes to ``calls``."""
    def ranking(data, model, log, folds=5, cross_validate_top=0):
        calls.append(Path(model).read_text())
        significant = len(calls) == 1
        doc = {"candidates": [dict(candidate, significant=significant, reason="stand-in")],
               "verdict": {"effect": candidate["effect"] if significant else None,
                           "text": None if significant else "nothing significant (stand-in)"}}
        demo._write_new(log, json.dumps(doc))
        return doc
    return ranking


def test_the_loop_adds_the_proposed_change_refits_and_records_every_fit(tmp_path, monkeypatch):
    """The loop's mechanics with a stand-in ranking that proposes one change (a LUT after the
    polynomial, a term every build accepts) and then nothing: a new model file per step, one
    history entry per fit, the error after each change."""
    capture = _small_capture(tmp_path)
    calls = []
    ranking = _one_change_ranking(calls, {"effect": "lut", "insert_index": None,
                                          "model_change": "- type: lut\n  cell_size_mm: 300\n",
                                          "statement": "a coarse lookup table"})

    monkeypatch.setattr(demo, "diagnosis_available", lambda: True)
    monkeypatch.setattr(demo, "run_diagnose", ranking)
    said = []
    steps = demo.follow_diagnosis(capture, demo.PAPER_MODEL, tmp_path / "work", say=said.append)
    assert [s.label for s in steps] == ["base", "+lut"]
    assert steps[0].added["effect"] == "lut" and steps[1].added is None
    assert "type: lut" not in calls[0] and "  - type: lut\n    cell_size_mm: 300" in calls[1]
    assert calls[1] == steps[1].model_path.read_text()
    assert steps[0].model_path.read_text() == demo.PAPER_MODEL, "earlier model files stay as they were"
    for s in steps:
        assert s.calibration_path.is_file() and s.position_mm > 0
    from trackcal import history
    entries = history.load_history(tmp_path / "work")
    assert [e["label"] for e in entries] == ["base", "+lut"]
    assert entries[1]["model"]["path"] == str(steps[1].model_path)
    assert entries[1]["data"][0]["sha256"] == history._sha(capture / "poses.csv")
    assert "nothing significant (stand-in)" in "\n".join(said)
    table = demo.steps_table(steps, demo.noise_floor(capture))
    assert "+lut" in table and "noise floor (truth)" in table and "uncorrected" in table
    # Run again on the same work folder: the model files of the first run are never overwritten.
    with pytest.raises(SystemExit, match="not overwriting"):
        demo.follow_diagnosis(capture, demo.PAPER_MODEL, tmp_path / "work", say=said.append)


def test_grown_change_scales_every_source_strength_and_nothing_else():
    change = ("- type: dipole\n  name: dipole_3\n  location_in_transmitter: [-0.1229, -0.4802, 1.3828]\n"
              "  polarisability_m3: -0.3189\n- type: plane\n  point_in_transmitter: [0, 0, 0.7]\n"
              "  normal_in_transmitter: [0, 0, 1]\n  attenuation: 0.2526\n")
    assert demo.grown_change(change) == change.replace("-0.3189", "-0.0003189").replace(
        "0.2526", "0.0002526")
    assert demo.grown_change("- type: background_field\n") is None
    assert demo.grown_change("- type: sensor_offset\n  translation: [0.01, 0, 0]\n") is None
    # A comment after the value stays; an exponent is read.
    assert demo.grown_change("- type: dipole\n  polarisability_m3: 2.5e-3  # toolbox\n") == \
        "- type: dipole\n  polarisability_m3: 2.5e-06  # toolbox\n"
    # Not every source's strength is a plain value (a flow item): nothing is grown.
    assert demo.grown_change("- type: dipole\n  polarisability_m3: 0.01\n"
                             "- {type: plane, attenuation: 0.2}\n") is None


def test_a_replacement_is_fitted_from_the_model_file(tmp_path, monkeypatch):
    """A change that replaces a term does not start at the previous optimum (fitted with the term
    it removes); an addition does (the grown test below)."""
    capture = _small_capture(tmp_path)
    calls = []
    ranking = _one_change_ranking(calls, {"effect": "plane", "insert_index": 0,
                                          "replaces": "dipole",
                                          "model_change": "- type: plane\n  point_in_transmitter: "
                                                          "[0, 0, 0.8]\n  normal_in_transmitter: "
                                                          "[0, 0, 1]\n  attenuation: 0.2\n",
                                          "statement": "the floor"})
    base = ("terms:\n  - type: dipole\n    location_in_transmitter: [0.5, 0.0, 0.35]\n"
            "    polarisability_m3: -0.009\n  - type: polynomial\n    degree: 4\n")
    real_fit = demo.run_fit
    starts = {}

    def fit(data, model, calibration, log, folds=5, start=None):
        starts[Path(model).name] = start
        return real_fit(data, model, calibration, log, folds=folds, start=start)

    monkeypatch.setattr(demo, "diagnosis_available", lambda: True)
    monkeypatch.setattr(demo, "run_diagnose", ranking)
    monkeypatch.setattr(demo, "run_fit", fit)
    steps = demo.follow_diagnosis(capture, base, tmp_path / "work", say=lambda _: None)
    assert [s.label for s in steps] == ["base", "dipole -> plane"]
    assert "type: plane" in steps[1].model_path.read_text()
    assert "type: dipole" not in steps[1].model_path.read_text()
    assert starts == {"step0.yaml": None, "step1.yaml": None}


@pytest.mark.parametrize("grown_is_lower", [True, False])
def test_a_source_that_fits_worse_than_the_model_without_it_is_grown_from_near_zero(
        tmp_path, monkeypatch, grown_is_lower):
    """When the refit with an added source ends above the cost before the change (a worse optimum:
    the model without it is inside the new one), the loop refits with the source grown from near
    zero and keeps the lower fit; the first attempt's files stay."""
    capture = _small_capture(tmp_path)
    calls = []
    ranking = _one_change_ranking(calls, {"effect": "dipole", "insert_index": 0,
                                          "model_change": "- type: dipole\n  location_in_transmitter: "
                                                          "[0.5, 0.0, 0.35]\n  polarisability_m3: -0.009\n",
                                          "statement": "the workbench frame"})

    real_fit = demo.run_fit
    starts = {}

    def fit(data, model, calibration, log, folds=5, start=None):
        starts[Path(model).name] = start
        doc = real_fit(data, model, calibration, log, folds=folds, start=start)
        if Path(model).name == "step1.yaml":  # stand-in for a fit that ended in a worse optimum
            doc["fit"]["final_cost"] = 1e12
        if Path(model).name == "step1.grown.yaml" and not grown_is_lower:
            doc["fit"]["final_cost"] = 2e12
        return doc

    monkeypatch.setattr(demo, "diagnosis_available", lambda: True)
    monkeypatch.setattr(demo, "run_diagnose", ranking)
    monkeypatch.setattr(demo, "run_fit", fit)
    said = []
    steps = demo.follow_diagnosis(capture, demo.PAPER_MODEL, tmp_path / "work", say=said.append)
    assert [s.label for s in steps] == ["base", "+dipole"]
    # Both refits of step 1 start at step 0's optimum (trackcal-fit fit --start); the base does not.
    models = tmp_path / "work" / "models"
    assert starts == {"step0.yaml": None, "step1.yaml": models / "step0.start.json",
                      "step1.grown.yaml": models / "step0.start.json"}
    assert json.loads((models / "step0.start.json").read_text())["fit"] == steps[0].fit["fit"]
    from trackcal import history
    other = "+dipole (first attempt, not kept)" if grown_is_lower else "+dipole (grown, not kept)"
    assert [e["label"] for e in history.load_history(tmp_path / "work")] == \
        ["base", other, "+dipole"], "every fit is recorded, the one kept last"
    assert (models / "step1.grown.yaml").is_file() and (models / "step1.grown.json").is_file()
    assert "polarisability_m3: -9e-06" in (models / "step1.grown.yaml").read_text()
    assert "polarisability_m3: -0.009" in (models / "step1.yaml").read_text()
    assert (models / "step1.json").is_file(), "the first attempt's files stay"
    assert calls[1] == steps[1].model_path.read_text(), "the next diagnosis reads the kept model"
    if grown_is_lower:
        assert steps[1].model_path.name == "step1.grown.yaml"
        assert steps[1].calibration_path.name == "step1.grown.json"
        assert steps[1].fit["fit"]["final_cost"] < 1e12
        assert any("(kept: step1.grown.yaml)" in line for line in said)
    else:
        assert steps[1].model_path.name == "step1.yaml"
        assert steps[1].fit["fit"]["final_cost"] == 1e12
        assert any("(not kept)" in line for line in said)


def test_the_default_scene_is_the_workflow_tests_scene():
    """demo.DEFAULT_SCENE and tests/data/workflow/paper_small.yaml are one scene (comments aside)."""
    def keys(text):
        return [l.rstrip() for l in text.splitlines() if l.strip() and not l.lstrip().startswith("#")]
    assert keys(demo.DEFAULT_SCENE) == keys(SMALL_SCENE.read_text())


def test_ctrl_c_before_serving_exits_130_without_a_traceback(tmp_path, monkeypatch, capsys):
    """Ctrl-C while the loop simulates, fits or diagnoses (minutes): a one-line message and the
    shell's 130, not a KeyboardInterrupt traceback."""
    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt
    monkeypatch.setattr(demo, "simulate", interrupted)
    assert demo.main(["--work", str(tmp_path), "--no-serve"]) == 130
    err = capsys.readouterr().err
    assert "trackcal demo: interrupted" in err and "Traceback" not in err
    # The last line names the work folder (its first line has scrolled away after minutes of fits).
    work = next(p for p in tmp_path.iterdir() if p.is_dir())
    assert err.strip().splitlines()[-1].endswith(f"what it wrote is in {work}"), err


@pytest.mark.parametrize("bad", ["missing_base", "folder_base", "work_is_a_file"])
def test_bad_base_or_work_folder_is_a_one_line_error(tmp_path, capsys, bad):
    """A mistyped --base or a --work that is a file: a message naming it, exit status 2 or a
    SystemExit message, not a FileNotFoundError / NotADirectoryError traceback."""
    (tmp_path / "afile").write_text("x")
    argv = {"missing_base": ["--base", str(tmp_path / "nope.yaml"), "--work", str(tmp_path / "w")],
            "folder_base": ["--base", str(tmp_path), "--work", str(tmp_path / "w")],
            "work_is_a_file": ["--work", str(tmp_path / "afile")]}[bad]
    with pytest.raises(SystemExit) as e:
        demo.main(argv + ["--no-serve"])
    text = str(e.value.code) + capsys.readouterr().err
    name = "afile" if bad == "work_is_a_file" else "--base"
    assert name in text, text


@tools
def test_serving_from_a_relative_work_folder_finds_the_calibration(tmp_path, monkeypatch):
    """The default --work demo-runs is relative; trackcal-server reads vrpn.cfg's paths from the
    file's folder, so relative ones there named a calibration (and device) that does not exist
    and the server exited at the end of the main job."""
    import shutil as _shutil
    monkeypatch.chdir(tmp_path)
    work = Path("demo-runs") / "run"
    work.mkdir(parents=True)
    _shutil.copy(ROOT / "tests" / "data" / "calibration" / "example.json", work / "cal.json")
    demo.serve(work, work / "cal.json", "", 1, _free_port(), 3.0, "paper")  # SystemExit if the server exits
    log = (work / "server.log").read_text()
    # The calibration was found and loaded. (Not "no 'error' in the log": the emulator stops before
    # the server, which then logs the port's "error condition" while it stops.)
    assert "cannot open" not in log, log
    assert "Tracker0: correction " + str((tmp_path / work / "cal.json")) in log, log


def _no_work(*args, **kwargs):
    raise AssertionError("the job started its work before refusing the option")


@pytest.mark.parametrize("argv,name", [
    (["--folds", "1"], "--folds 1"),
    (["--folds", "0", "--no-serve"], "--folds 0"),
    (["--cross-validate-top", "-1"], "--cross-validate-top -1"),
    (["--port", "0"], "--port 0"),
    (["--port", "70000"], "--port 70000"),
    (["--serve-seconds", "-1"], "--serve-seconds -1"),
    (["--serve-seconds", "nan"], "--serve-seconds nan"),
])
def test_bad_options_are_refused_before_any_work(tmp_path, monkeypatch, capsys, argv, name):
    """Before: --folds 1 and --cross-validate-top -1 failed after the simulation and the first fit
    (a trackcal-fit usage dump; a ValueError traceback), --port 70000 after the whole loop (minutes:
    the server could not bind), each leaving a work folder of wasted work."""
    monkeypatch.setattr(demo, "simulate", _no_work)
    with pytest.raises(SystemExit) as e:
        demo.main(["--work", str(tmp_path / "w")] + argv)
    assert e.value.code == 2
    assert name in capsys.readouterr().err
    assert not (tmp_path / "w").exists(), "no work folder for a run that cannot run"


def test_a_busy_port_is_refused_before_the_loop(tmp_path, monkeypatch, capsys):
    """The default port 3883 is VRPN's: on a lab machine another server may hold it. Before, the
    loop ran for minutes, then 'Serving on port' was printed and the server exited at once."""
    monkeypatch.setattr(demo, "simulate", _no_work)
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as holder:
        holder.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        holder.bind(("0.0.0.0", 0))
        holder.listen()
        port = holder.getsockname()[1]
        assert demo.port_unavailable(port).startswith(f"cannot bind TCP port {port}")
        with pytest.raises(SystemExit) as e:
            demo.main(["--work", str(tmp_path / "w"), "--port", str(port)])
        assert e.value.code == 2
        assert f"--port {port}: cannot bind TCP port {port}" in capsys.readouterr().err
        # --no-serve does not serve: the port does not matter.
        with pytest.raises(AssertionError, match="started its work"):
            demo.main(["--work", str(tmp_path / "w2"), "--port", str(port), "--no-serve"])
    assert demo.port_unavailable(_free_port()) is None


@tools
def test_a_server_that_exits_is_reported_with_its_error(tmp_path):
    """The server's own reason is in the demo's message, not only in server.log."""
    import shutil as _shutil
    _shutil.copy(ROOT / "tests" / "data" / "calibration" / "example.json", tmp_path / "cal.json")
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as holder:
        holder.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        holder.bind(("0.0.0.0", 0))
        holder.listen()
        port = holder.getsockname()[1]
        with pytest.raises(SystemExit) as e:
            demo.serve(tmp_path, tmp_path / "cal.json", "", 1, port, 20.0, "paper")
    message = str(e.value)
    assert "trackcal-server exited with code" in message, message
    assert f"cannot bind TCP 0.0.0.0:{port}" in message, message
    assert str(tmp_path / "server.log") in message, message
