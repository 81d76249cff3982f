"""The verdict of `trackcal diagnose` (candidate ranking + covariate analysis), the model-file change
it prints, and --json as one document with every part of the diagnosis."""

import json
import shutil
import subprocess
import sys

import numpy as np
import pytest

import trackcal
from trackcal import diagnosis
from trackcal.validation import CovariateEffect
from understand_support import simulate

MODEL = """noise: {position_mm: 1.0}
terms:
  # the paper's polynomial
  - type: polynomial
    degree: 3

solver:
  max_iterations: 50
"""


def contract_b_doc(significant: bool):
    """A ranking in the shape of trackcal-fit diagnose --json (docs/contract B)."""
    return {
        "command": "diagnose", "model": "model.yaml", "data": "cap", "folds": 5,
        "base": {"cv_position_mm_mean": 3.0, "cv_orientation_deg_mean": 0.3, "final_cost": 10.0,
                 "num_residuals": 2880, "num_free_parameters": 40, "bic": 300.0, "table1": {}},
        "candidates": [
            {"effect": "dipole", "model_change": "- type: dipole\n  polarisability_m3: 0.002\n",
             "insert_index": 0, "cv_position_mm_mean": 1.0 if significant else 2.98,
             "cv_orientation_deg_mean": 0.1, "cv_drop_percent": {"position": 66.7, "orientation": 66.7},
             "delta_bic": -500.0 if significant else 12.0, "p_value": 1e-9 if significant else 0.4,
             "significant": significant, "reason": "held-out error falls 66.7 %", "parameters": [],
             "statement": "an object near (0.6, 0.9, -0.5) m"},
            {"effect": "sensor_offset", "model_change": "- type: sensor_offset\n", "insert_index": 0,
             "cv_position_mm_mean": 2.99, "cv_orientation_deg_mean": 0.3,
             "cv_drop_percent": {"position": 0.3, "orientation": 0.0}, "delta_bic": 30.0, "p_value": 0.7,
             "significant": False, "reason": "no change", "parameters": [], "statement": ""},
        ],
        "verdict": {"effect": "dipole" if significant else None,
                    "text": "a ferromagnetic object explains the remaining structure" if significant else
                    "no catalog effect explains the remaining structure"},
    }


TEMPERATURE = [CovariateEffect("temperature", "position_mm", 0.41, 0.005, True, 600),
               CovariateEffect("temperature", "position_vector", 0.2, 0.005, True, 600),
               CovariateEffect("distance", "position_mm", 0.08, 0.005, True, 600),
               CovariateEffect("humidity", "position_mm", 0.001, 0.6, False, 600)]


def test_verdict_names_the_top_significant_candidate():
    v = diagnosis.verdict(contract_b_doc(True), TEMPERATURE)
    assert v["source"] == "candidate" and v["effect"] == "dipole"
    assert v["text"].startswith("a ferromagnetic object") and v["insert_index"] == 0
    assert v["model_change"].startswith("- type: dipole")


def test_verdict_and_rows_carry_a_replacement():
    doc = contract_b_doc(True)
    top = doc["candidates"][0]
    top.update(effect="plane", replaces="dipole_2", insert_index=1,
               model_change="- type: plane\n  attenuation: 0.26\n")
    doc["verdict"].update(effect="plane", replaces="dipole_2")
    v = diagnosis.verdict(doc, TEMPERATURE)
    assert v["effect"] == "plane" and v["replaces"] == "dipole_2" and v["insert_index"] == 1
    assert diagnosis.verdict(contract_b_doc(True), TEMPERATURE)["replaces"] is None
    rows = diagnosis.candidate_rows(doc)
    assert rows[0]["effect"] == "plane for dipole_2" and rows[1]["effect"] == "sensor_offset"
    assert "in place of item 1 (dipole_2)" in diagnosis.change_place(v["model_change"], 1, "dipole_2")
    text = "terms:\n  - type: dipole\n  - type: dipole\n    polarisability_m3: -0.26\n  - type: polynomial\n"
    new = diagnosis.apply_model_change(text, v["model_change"], v["insert_index"], v["replaces"])
    assert new == "terms:\n  - type: dipole\n  - type: plane\n    attenuation: 0.26\n  - type: polynomial\n"


def test_verdict_rows_and_change_carry_a_removal():
    """A removal (kind "removal": the model's own source the data no longer identify) has an empty
    change; the verdict keeps the item and the term, the row reads "remove dipole_2", and applying it
    removes that item with its indented lines and comments, nothing else."""
    doc = contract_b_doc(True)
    top = doc["candidates"][0]
    top.update(effect="remove", kind="removal", replaces="dipole_2", insert_index=1, model_change="")
    doc["verdict"].update(effect="remove")
    v = diagnosis.verdict(doc, TEMPERATURE)
    assert v["effect"] == "remove" and v["replaces"] == "dipole_2" and v["insert_index"] == 1
    rows = diagnosis.candidate_rows(doc)
    assert rows[0]["effect"] == "remove dipole_2"
    assert diagnosis.change_place("", 1, "dipole_2") == "in terms:, remove item 1 (dipole_2) counting from 0"
    text = ("terms:\n  - type: dipole\n  - type: dipole  # stood in for the floor\n"
            "    polarisability_m3: -0.26\n    # location searched\n  - type: polynomial\n")
    new = diagnosis.apply_model_change(text, "", 1, "dipole_2")
    assert new == "terms:\n  - type: dipole\n  - type: polynomial\n"
    with pytest.raises(ValueError, match="dipole_2.*is 'polynomial'"):
        diagnosis.apply_model_change(text, "", 2, "dipole_2")  # the file changed since
    with pytest.raises(ValueError, match="empty model change"):
        diagnosis.apply_model_change(text, "", 1)
    with pytest.raises(ValueError, match="insert_index"):
        diagnosis.apply_model_change(text, "", None, "dipole_2")
    with pytest.raises(ValueError, match="leave terms: empty"):
        diagnosis.apply_model_change("terms:\n  - type: dipole\n", "", 0, "dipole")
    # Not shown as untested: a removal explains no structure, tested or not.
    doc["candidates"][0].update(cross_validated=False, significant=False)
    assert "remove" not in diagnosis._untested(doc)[0]


def test_candidate_figure_gives_a_replacement_its_own_bar():
    """A replacement shares its effect name with the matching addition: labelled by effect alone,
    matplotlib's categorical axis drew both at one position, one bar hiding the other."""
    from trackcal import figures
    doc = contract_b_doc(True)
    replacement = dict(doc["candidates"][0], replaces="dipole_2", cv_position_mm_mean=1.5, significant=False)
    doc["candidates"].insert(1, replacement)
    fig = figures.candidate_bars(doc)
    fig.canvas.draw()
    ax = fig.axes[0]
    labels = [t.get_text() for t in ax.get_yticklabels()]
    assert sorted(labels) == sorted(["model alone", "dipole", "dipole for dipole_2", "sensor_offset"])
    bars = {round(b.get_y() + b.get_height() / 2, 6): b.get_width() for b in ax.patches}
    assert len(bars) == 4
    # Each label sits at its own bar, with its own value.
    at = {t.get_text(): bars[round(y, 6)] for t, y in zip(ax.get_yticklabels(), ax.get_yticks())}
    assert at == {"model alone": 3.0, "dipole": 1.0, "dipole for dipole_2": 1.5, "sensor_offset": 2.99}
    import matplotlib.pyplot as plt
    plt.close(fig)

def test_the_note_on_stations_left_out_of_the_comparison():
    doc = contract_b_doc(True)
    assert diagnosis.unresolved_note(doc) == ""
    doc["candidates"][0].update(kind="loss", cv_unresolved_left_out=3)  # a robust loss keeps them
    assert diagnosis.unresolved_note(doc) == ""
    doc["candidates"][1].update(kind="term", cv_unresolved_left_out=25, cv_base_position_mm_mean=0.992,
                                cv_base_orientation_deg_mean=0.0966)
    assert diagnosis.unresolved_note(doc) == (
        "Held-out means and drops without 25 stations where a runtime inverse finds no root or an "
        "ambiguous one; the model alone over the others: 0.992 mm, 0.097 deg.")


def test_verdict_falls_back_to_the_covariate():
    v = diagnosis.verdict(contract_b_doc(False), TEMPERATURE)
    assert v["source"] == "covariate" and v["effect"] is None and v["covariate"] == "temperature"
    assert v["text"].startswith("no catalog effect explains the remaining structure; it follows covariate "
                                "temperature (R^2 0.41 of the position error magnitude)")
    assert "distance (R^2 0.08)" in v["text"] and "humidity" not in v["text"]


def test_verdict_does_not_call_a_growing_scatter_structure():
    # A model that holds the truth, at the noise floor (ideal room, no hidden effect, a degree-4
    # polynomial; 240 + 60 stations 0.28-0.88 m from the transmitter): the tracker's noise grows as
    # r^4, so the size of the residual follows distance (R^2 0.17, z 0.08) while no covariate
    # predicts its direction. "it follows covariate distance" sent the user looking for an effect.
    scatter = [CovariateEffect("distance", "position_mm", 0.17, 0.0002, True, 300),
               CovariateEffect("z", "position_mm", 0.08, 0.0002, True, 300),
               CovariateEffect("distance", "position_vector", 0.003, 0.4, False, 300)]
    v = diagnosis.verdict(contract_b_doc(False), scatter)
    assert v["source"] == "covariate" and v["covariate"] == "distance" and v["model_change"] is None
    assert "remaining structure" not in v["text"], v["text"]
    assert v["text"].startswith("no catalog effect explains what remains; only the size of the remaining "
                                "error follows a covariate, not its direction: distance (R^2 0.17 of the "
                                "position error magnitude); also z (R^2 0.08). A scatter that grows with "
                                "range"), v["text"]
    assert "no sign of a missing effect" in v["text"]
    # A direction that follows a covariate is a systematic error, said as before.
    v = diagnosis.verdict(contract_b_doc(False), scatter + [
        CovariateEffect("x", "position_vector", 0.05, 0.0002, True, 300)])
    assert v["text"].startswith("no catalog effect explains the remaining structure; it follows covariate "
                                "distance"), v["text"]
    assert "scatter" not in v["text"]


def test_verdict_nothing_significant():
    quiet = [CovariateEffect("x", "position_mm", 0.01, 0.3, False, 600)]
    assert diagnosis.verdict(contract_b_doc(False), quiet)["text"] == "nothing significant remains"
    assert diagnosis.verdict(None, quiet)["text"].startswith("nothing significant remains")
    assert "(catalog effects not tested); it follows covariate temperature" in \
        diagnosis.verdict(None, TEMPERATURE)["text"]


def test_verdict_without_covariate_tests_does_not_call_them_clean():
    # (validate(analyse_covariates=False): an empty list of effects is then no finding.)
    assert diagnosis.verdict(contract_b_doc(False), [], covariates_tested=False)["text"] == \
        "no catalog effect is significant (covariates not tested)"
    untested = diagnosis.verdict(None, [], covariates_tested=False)["text"]
    assert untested.startswith("nothing tested") and "in the covariates" not in untested


def test_verdict_names_a_source_the_data_no_longer_identify_whatever_it_says():
    note = ("Already in the model but not identified by these data: dipole_2 (`terms:` item 3, "
            "polarisability_m3 0.0 sigma from its null value; location undetermined). A term added after it "
            "may explain the same structure: fit the model without it and keep the change if the held-out "
            "error does not rise (trackcal history).")
    doc = contract_b_doc(False)
    doc["verdict"]["unsupported_note"] = note
    quiet = [CovariateEffect("x", "position_mm", 0.01, 0.3, False, 600)]
    assert diagnosis.verdict(doc, quiet)["text"] == "nothing significant remains. " + note
    covariate = diagnosis.verdict(doc, TEMPERATURE)
    assert covariate["source"] == "covariate" and covariate["text"].endswith(". " + note)
    # The engine's own verdict already carries it: not said twice.
    doc["verdict"]["text"] = "No catalog effect explains the remaining structure. " + note
    doc["verdict"]["unexplained_structure"] = True
    assert diagnosis.verdict(doc, quiet)["text"].count("Already in the model") == 1


def test_verdict_says_when_the_paired_test_cannot_reach_its_threshold():
    # A short stream: "nothing significant remains" alone would read as a clean bill of health.
    note = ("The paired test has 6 blocks of time (at least 0.5 s and 5 samples each) on this stream: its "
            "smallest p (every one favouring a candidate) is 0.018, not below the threshold 0.0033 for 3 "
            "candidates, so no candidate can be claimed on these data (robust_loss aside: its outliers have "
            "their own test), whatever they show. Record a longer stream (10 blocks: at least 5.0 s and 50 "
            "samples) or test fewer effects (--effects).")
    doc = contract_b_doc(False)
    doc["verdict"]["test_power_note"] = note
    quiet = [CovariateEffect("x", "position_mm", 0.01, 0.3, False, 600)]
    assert diagnosis.verdict(doc, quiet)["text"] == "nothing significant remains. " + note
    assert diagnosis.verdict(doc, TEMPERATURE)["text"].endswith(". " + note)
    doc["verdict"]["test_power_note"] = ""
    assert diagnosis.verdict(doc, quiet)["text"] == "nothing significant remains"


def test_verdict_keeps_the_rankings_word_on_structure_it_cannot_place():
    # The engine found held-out structure no candidate identifies: "nothing significant remains"
    # would hide it, so its verdict is kept (and a covariate finding still comes first).
    quiet = [CovariateEffect("x", "position_mm", 0.01, 0.3, False, 600)]
    doc = contract_b_doc(False)
    text = ("No catalog effect explains the remaining structure. A dipole_pair term fits structure "
            "that is there (held-out position error falls 12.9 %, delta BIC -40.2), but its fit "
            "does not identify the source (...), so it is not claimed: source not identified. ")
    doc["verdict"] = {"effect": None, "replaces": None, "text": text, "unexplained_structure": True}
    v = diagnosis.verdict(doc, quiet)
    assert v["source"] == "unidentified" and v["effect"] is None and v["model_change"] is None
    assert v["text"] == text
    assert diagnosis.verdict(doc, TEMPERATURE)["source"] == "covariate"
    doc["verdict"]["unexplained_structure"] = False
    assert diagnosis.verdict(doc, quiet)["text"] == "nothing significant remains"


def test_verdict_claims_only_over_the_effects_tested_held_out():
    # A candidate screened out of cross-validation (--cross-validate-top) or refused on the fit to
    # all stations was never tested on held-out data: "no catalog effect" would claim too much.
    doc = contract_b_doc(False)
    doc["candidates"][1]["cross_validated"] = False
    v = diagnosis.verdict(doc, TEMPERATURE)
    assert v["text"].startswith("none of the 1 candidate tested on held-out data explains the remaining "
                                "structure (not tested there: sensor_offset); it follows covariate temperature")
    # A replacement is named with the term it would replace (its effect's addition was tested).
    doc["candidates"][1].update(effect="dipole", replaces="dipole_1")
    assert "(not tested there: dipole in place of dipole_1)" in diagnosis.verdict(doc, TEMPERATURE)["text"]
    # Nothing tested held out: said so, and the quiet verdict does not say "nothing remains" alone.
    doc["candidates"][0]["cross_validated"] = False
    assert diagnosis.verdict(doc, TEMPERATURE)["text"].startswith(
        "no candidate was tested on held-out data (not tested: dipole, dipole in place of dipole_1)")
    doc["candidates"][0]["significant"] = False
    quiet = diagnosis.verdict(doc, [])
    assert quiet["text"] == ("nothing significant remains in the covariates; no candidate was tested on "
                             "held-out data (not tested: dipole, dipole in place of dipole_1)")
    for c in doc["candidates"]:
        c["cross_validated"] = True
    assert diagnosis.verdict(doc, TEMPERATURE)["text"].startswith("no catalog effect explains")


def test_verdict_names_a_flexible_fallback_when_no_covariate_explains():
    doc = contract_b_doc(False)
    doc["flexible_fallback"] = [{"effect": "polynomial", "significant": True, "model_change": "- type: polynomial\n",
                                 "insert_index": 1, "cv_drop_percent": {"position": 22.5}}]
    quiet = [CovariateEffect("x", "position_mm", 0.01, 0.3, False, 600)]
    v = diagnosis.verdict(doc, quiet)
    assert v["source"] == "flexible" and "held-out error by 22.5 %" in v["text"]
    assert v["text"].startswith("no catalog effect explains the remaining structure")
    # A covariate, when there is one, says more than the flexible term.
    assert diagnosis.verdict(doc, TEMPERATURE)["source"] == "covariate"


def test_model_change_is_inserted_where_the_candidate_says():
    change = "- type: dipole\n  location_in_transmitter: [0.6, 0.9, -0.5]\n"
    new = diagnosis.apply_model_change(MODEL, change, 0)
    assert new.count("- type: dipole") == 1
    assert new.index("- type: dipole") < new.index("- type: polynomial")
    assert "  - type: dipole\n    location_in_transmitter: [0.6, 0.9, -0.5]\n  # the paper" not in new
    assert "  - type: dipole\n    location_in_transmitter: [0.6, 0.9, -0.5]\n  - type: polynomial" in new
    appended = diagnosis.apply_model_change(MODEL, "- type: lut\n  cell_size_mm: 200\n", None)
    assert "    degree: 3\n  - type: lut\n    cell_size_mm: 200\n\nsolver:" in appended
    # The result is a model file the engine accepts, with the new term at its place.
    assert trackcal._core.parse_model(appended)["terms"] == ["polynomial", "lut"]
    with pytest.raises(ValueError, match="flow style"):
        diagnosis.apply_model_change("terms: [{type: polynomial}]\n", change, 0)
    with pytest.raises(ValueError, match="no top-level 'terms:'"):
        diagnosis.apply_model_change("noise: {position_mm: 1.0}\n", change, 0)
    assert "+  - type: lut" in diagnosis.model_diff(MODEL, appended)


def _top_level(text):
    """{key: the key's lines} of a model text's unindented keys, in order."""
    out = {}
    for line in text.splitlines():
        if line[:1].isalpha():
            out[line.split(":", 1)[0]] = [line]
        elif out and line.strip() and not line.lstrip().startswith("#"):
            out[list(out)[-1]].append(line)
    return out


def test_term_and_top_level_changes_give_a_model_with_the_change_in_its_place():
    # A term (dipole) goes into terms: before the item the engine names.
    term = diagnosis.apply_model_change(MODEL, "- type: dipole\n  polarisability_m3: 0.002\n", 0)
    assert trackcal._core.parse_model(term)["terms"] == ["physical", "polynomial"]  # the chain, then the rest
    assert _top_level(term)["terms"][1:3] == ["  - type: dipole", "    polarisability_m3: 0.002"]
    # robust_loss's change is a top-level key (insert_index null): it goes beside terms:, not in it.
    loss = diagnosis.apply_model_change(MODEL, "loss:\n  type: cauchy\n  scale: 3\n", None)
    assert trackcal._core.parse_model(loss)["terms"] == ["polynomial"]  # parses: the YAML is valid
    keys = _top_level(loss)
    assert list(keys) == ["noise", "loss", "terms", "solver"]
    assert keys["loss"] == ["loss:", "  type: cauchy", "  scale: 3"]
    assert keys["terms"] == ["terms:", "  - type: polynomial", "    degree: 3"]
    # The same key again replaces it; so does time_offset's change for a model with a fixed offset.
    huber = diagnosis.apply_model_change(loss, "loss:\n  type: huber\n  scale: 2\n", None)
    assert _top_level(huber)["loss"] == ["loss:", "  type: huber", "  scale: 2"]
    assert huber.count("loss:") == 1 and "cauchy" not in huber
    fixed = MODEL + "time_offset: {value: 0.0, fixed: true}\n"
    freed = diagnosis.apply_model_change(fixed, "time_offset:\n  value: 0.037\n  fixed: false\n", None)
    assert _top_level(freed)["time_offset"] == ["time_offset:", "  value: 0.037", "  fixed: false"]
    assert freed.count("time_offset:") == 1
    trackcal._core.parse_model(freed)
    # Where each goes, in the words trackcal diagnose prints above the diff.
    assert diagnosis.change_place("- type: dipole\n", 0) == "in terms:, as item 0 counting from 0"
    assert diagnosis.change_place("- type: lut\n", None) == "in terms:, at the end"
    assert diagnosis.change_place("loss:\n  type: cauchy\n", None) == "top-level key 'loss:', not in terms:"


@pytest.mark.parametrize("change,index,message", [
    ("- type: dipole\n", 2, "outside the 1 terms"),
    ("\n", None, "empty"),
    ("[1, 2]\n", None, "neither"),
])
def test_model_change_that_cannot_be_placed_is_a_value_error(change, index, message):
    with pytest.raises(ValueError, match=message):
        diagnosis.apply_model_change(MODEL, change, index)


def run_cli(*args):
    exe = shutil.which("trackcal")
    cmd = [exe] if exe else [sys.executable, "-m", "trackcal.cli"]
    r = subprocess.run(cmd + [str(a) for a in args], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    return r


def test_diagnose_prints_and_applies_a_top_level_change_at_the_top_level(tmp_path):
    # Hemisphere flips: robust_loss wins, and its change is a loss: block beside terms:.
    cap = simulate(tmp_path / "capture", seed=73, hidden="hemisphere_flips")
    model = tmp_path / "model.yaml"
    model.write_text(MODEL)
    args = ("diagnose", cap, "--model", model, "--permutations", "9", "--effects", "robust_loss", "--folds", "2")
    if not diagnosis.candidates_available():
        pytest.skip("this build has no candidate ranking")
    doc = json.loads(run_cli(*args, "--json").stdout)
    change = doc["model_change"]
    assert doc["verdict"]["effect"] == "robust_loss" and change["insert_index"] is None
    assert change["place"] == "top-level key 'loss:', not in terms:"
    assert trackcal._core.parse_model(change["model_text"])["terms"] == ["polynomial"]
    assert list(_top_level(change["model_text"])) == ["noise", "loss", "terms", "solver"]
    text = run_cli(*args).stdout
    assert "Model-file change (top-level key 'loss:', not in terms:):" in text
    assert "\n+loss:\n+  type: cauchy\n" in text and "index None" not in text


def test_diagnose_json_carries_the_notes_the_text_prints(tmp_path):
    # Without --model no catalog effect is tested: the text says so, and so must --json.
    cap = simulate(tmp_path / "capture", seed=71)
    args = ("diagnose", cap, "--permutations", "9")
    doc = json.loads(run_cli(*args, "--json").stdout)
    assert doc["candidates"] is None
    assert doc["notes"] == ["catalog effects not tested: give --model to rank them"]
    assert "catalog effects not tested: give --model to rank them" in run_cli(*args).stdout


def test_diagnose_without_a_validation_set_shows_the_fits_held_out_table(tmp_path):
    # Every station calib: the calibration's "after" is in-sample, so the model's fit is
    # cross-validated (as `trackcal fit` does) and its held-out table shown.
    cap = simulate(tmp_path / "capture", seed=71)
    poses = cap / "poses.csv" if cap.is_dir() else cap
    lines = poses.read_text().splitlines()
    col = lines[0].split(",").index("set")
    rows = [line.split(",") for line in lines[1:]]
    for r in rows:
        r[col] = "calib" if r[col] == "valid" else r[col]
    only = tmp_path / "calib_only.csv"
    only.write_text("\n".join([lines[0]] + [",".join(r) for r in rows]) + "\n")
    model = tmp_path / "model.yaml"
    model.write_text(MODEL)
    doc = json.loads(run_cli("diagnose", only, "--model", model, "--json", "--permutations", "9",
                             "--effects", "sensor_offset", "--folds", "2").stdout)
    names = [t["set_name"] for t in doc["tables"]]
    assert names[0] == "calib" and "valid" not in names
    assert any(n.startswith("cross-validation") for n in names), names


@pytest.mark.skipif(not diagnosis.candidates_available(), reason="no candidate ranking in this build")
def test_cross_validate_top_zero_cross_validates_every_candidate(tmp_path):
    # The in-process ranking takes the option (the demo's "--cross-validate-top 0: all" relied on
    # it and got the default 3): four effects, every one cross-validated at 0, not at 1.
    cap = simulate(tmp_path / "capture", seed=71)
    effects = ["sensor_offset", "receiver_gain", "robust_loss", "near_field"]
    every = diagnosis.diagnose_candidates(cap, MODEL, folds=2, effects=effects, cross_validate_top=0)
    assert len(every["candidates"]) == 4
    assert all(c["cross_validated"] for c in every["candidates"])
    one = diagnosis.diagnose_candidates(cap, MODEL, folds=2, effects=effects, cross_validate_top=1)
    assert not all(c["cross_validated"] for c in one["candidates"])
    with pytest.raises(ValueError, match="cross_validate_top"):
        diagnosis.diagnose_candidates(cap, MODEL, effects=effects, cross_validate_top=-1)
    # An empty restriction is refused (it used to rank every effect), and one name given as a
    # string is one effect, not its letters.
    with pytest.raises(ValueError, match="effects: an empty list"):
        diagnosis.diagnose_candidates(cap, MODEL, effects=[])
    single = diagnosis.diagnose_candidates(cap, MODEL, folds=2, effects="sensor_offset",
                                           cross_validate_top=0)
    assert [c["effect"] for c in single["candidates"]] == ["sensor_offset"]


def test_diagnose_json_is_one_document_with_everything(tmp_path):
    cap = simulate(tmp_path / "capture", seed=71)
    model = tmp_path / "model.yaml"
    model.write_text(MODEL)
    r = run_cli("diagnose", cap, "--model", model, "--json", "--permutations", "19", "--effects", "sensor_offset",
                "--folds", "2")
    doc = json.loads(r.stdout)
    for key in ("tables", "outside_volume", "by_distance", "by_region", "worst", "covariates",
                "covariate_findings", "candidates", "verdict", "fit", "notes"):
        assert key in doc, key
    assert doc["command"] == "diagnose" and doc["model"] == str(model)
    # The simulated stations have distinct times: visiting_order (their rank) repeats time, left out
    # and said why; time stays.
    assert list(doc["covariates_left_out"]) == ["visiting_order"]
    assert "visiting_order" not in {c["covariate"] for c in doc["covariates"]}
    assert "time" in {c["covariate"] for c in doc["covariates"]}
    assert [t["set_name"] for t in doc["tables"]] == ["calib", "valid", "all"]
    assert doc["fit"]["converged"] is True  # the model was fitted (no -c given)
    assert doc["fit"]["parameters"][0]["term"] and doc["fit"]["parameters"][0]["values"]
    assert set(doc["model_inverse"]) >= {"ambiguous", "not_converged"}
    assert len(doc["worst"]) == 10 and doc["verdict"]["text"]
    if diagnosis.candidates_available():
        assert doc["candidates"]["command"] == "diagnose"
        assert {c["effect"] for c in doc["candidates"]["candidates"]} <= {"sensor_offset"}
    else:
        assert doc["candidates"] is None


def test_extrapolated_stations_are_named_in_a_note():
    # 29 stations outside the calibrated volume with 60-177 mm errors against 0.4 mm inside (a
    # reviewer's capture): the covariates and the ranking do not explain extrapolation; say so.
    from types import SimpleNamespace
    n_in, n_out = 60, 29
    after = SimpleNamespace(position_mm=np.r_[np.full(n_in, 0.4), np.linspace(60, 177, n_out)])
    v = SimpleNamespace(after=after, calibration=object(), flipped=np.zeros(n_in + n_out, bool),
                        extrapolated=np.r_[np.zeros(n_in, bool), np.ones(n_out, bool)])
    note = diagnosis.extrapolation_note(v)
    assert note.startswith("29 of 89 stations lie outside the calibrated volume") and "0.400 mm inside" in note
    # Outside but no worse than inside (twice), or no calibration: nothing to say.
    after.position_mm[n_in:] = 0.7
    assert diagnosis.extrapolation_note(v) is None
    after.position_mm[n_in:] = 50.0
    v.calibration = None
    assert diagnosis.extrapolation_note(v) is None


def test_a_capture_wholly_outside_the_calibrated_volume_is_named_in_a_note():
    # A capture 5 m from the calibrated volume (another room's, a wrong calibration file): the
    # report listed "600 of 600" outside and a worse-regions note, but no note said that no
    # station lies inside, since the note compared the outside error with an inside one.
    from types import SimpleNamespace
    n = 40
    v = SimpleNamespace(after=SimpleNamespace(position_mm=np.full(n, 80.0)), calibration=object(),
                        flipped=np.zeros(n, bool), extrapolated=np.ones(n, bool))
    note = diagnosis.extrapolation_note(v)
    assert note and note.startswith("all 40 stations lie outside the calibrated volume"), note
    # A hemisphere flip left out is not counted, as in the tables.
    v.flipped[0] = True
    assert diagnosis.extrapolation_note(v).startswith("all 39 stations"), diagnosis.extrapolation_note(v)


def test_a_crlf_model_keeps_its_line_endings():
    # A model file written on Windows: the change adds its lines with CRLF, the diff shows only them.
    text = "terms:\r\n  - type: polynomial\r\n    degree: 3\r\n"
    new = diagnosis.apply_model_change(text, "- type: sensor_offset\n", 0)
    assert new == "terms:\r\n  - type: sensor_offset\r\n  - type: polynomial\r\n    degree: 3\r\n"
    diff = diagnosis.model_diff(text, new)
    assert [l for l in diff.splitlines() if l.startswith(("+", "-")) and not l.startswith(("+++", "---"))] == [
        "+  - type: sensor_offset"]


def test_a_covariate_keeps_the_finding_that_stands_on_its_own():
    # Time explained by position on the position error, but a drift of its own on the orientation
    # error: the finding is the drift, not the confounded one with the larger R^2.
    effects = [CovariateEffect("time", "position_mm", 0.3, 0.005, True, 600, confounded_with="position"),
               CovariateEffect("time", "orientation_deg", 0.1, 0.005, True, 600),
               CovariateEffect("z", "position_mm", 0.35, 0.005, True, 600)]
    rows = {r["covariate"]: r for r in diagnosis.covariate_findings(effects)}
    assert rows["time"]["target"] == "orientation_deg" and rows["time"]["confounded_with"] is None


@pytest.mark.skipif(not diagnosis.candidates_available(), reason="no candidate ranking in this build")
def test_ctrl_c_stops_the_in_process_ranking(tmp_path):
    # The ranking runs for seconds to minutes (the demo's first diagnosis). Ctrl-C was handled only
    # after it had finished: it runs with the GIL released, and its workers are not Python's main
    # thread, where alone signal handlers run. Now the main thread runs them every 0.1 s while it
    # waits, and every worker stops at its candidate's next stage.
    import os
    import signal
    import time
    cap = simulate(tmp_path / "capture", seed=71)
    # Effects whose stages are short (~1 s each here), so a stop at the next stage is quick.
    effects = ["sensor_offset", "receiver_gain", "near_field", "background_field", "robust_loss"]
    start = time.monotonic()
    diagnosis.diagnose_candidates(cap, MODEL, folds=5, effects=effects, cross_validate_top=0)
    full = time.monotonic() - start
    killed = []

    def progress(message):
        if not killed and "fit on" in message:  # the base's fit: the ranking's first stage
            killed.append(time.monotonic())
            os.kill(os.getpid(), signal.SIGINT)  # as a terminal's Ctrl-C

    # Python's own Ctrl-C handler for the test: started from a non-interactive shell's background
    # job (nohup, `cmd &`), Python inherits SIGINT ignored, installs none, and the signal is lost.
    handler = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with pytest.raises(KeyboardInterrupt):
            diagnosis.diagnose_candidates(cap, MODEL, folds=5, effects=effects, cross_validate_top=0,
                                          progress=progress)
    finally:
        signal.signal(signal.SIGINT, handler)
    stopped = time.monotonic() - killed[0]
    # Measured: full 3.9 s, stopped 1.0 s after the signal (the stages in flight end). Before: the
    # whole ranking ran first (stopped ~ full). Half of the same run's full time holds both on a
    # loaded machine, as both runs see the same load.
    assert stopped < 0.5 * full, (stopped, full)


SMALL_IDEAL_SCENE = """\
base: ideal
name: small_ideal
capture:
  calibration:
    origin_in_transmitter: [-0.45, -0.3, -0.8]
    counts: [6, 4, 4]
    spacing_m: 0.15
  validation:
    count: 40
    min_in_transmitter: [-0.45, -0.3, -0.8]
    max_in_transmitter: [0.3, 0.15, -0.35]
  registration:
    count: 4
  stream:
    duration_s: 0
"""


def _drifted(src, out, drift_m):
    """A copy of the capture src whose reference positions drift along x by drift_m over the
    capture (linearly in time): an effect outside the catalog."""
    import csv
    rows = list(csv.DictReader(open(src / "poses.csv", newline="")))
    end = max(float(r["time"]) for r in rows)
    out.mkdir()
    with open(out / "poses.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        for r in rows:
            r["ref_x"] = repr(float(r["ref_x"]) + drift_m * float(r["time"]) / end)
            w.writerow(r)
    return out


def test_diagnose_notes_a_calibration_that_does_not_carry_over_to_the_validation_set(tmp_path):
    # The ideal room, no hidden effect, a reference drifting 1 mm along x over the capture. The paper
    # protocol visits the calibration grid layer by layer (time follows z), then the validation
    # stations: the polynomial absorbs the drift in the calibration set as a function of z, and the
    # validation stations, visited last, keep 0.5 mm (the ranking's held-out error on the
    # calibration stations: 0.08 mm). The covariate analysis (centred per set) then named z, the
    # ranking nothing, and no line said that the calibration does not carry over (measured on 240 +
    # 60 stations: validation 0.487 mm against 0.078 held out, 6.2x).
    if not diagnosis.candidates_available():
        pytest.skip("this build has no candidate ranking")
    exe = shutil.which("trackcal-simulate")
    scene = tmp_path / "scene.yaml"
    scene.write_text(SMALL_IDEAL_SCENE)
    clean = tmp_path / "clean"
    subprocess.run([exe, "--scene", scene, "--seed", "3", "-o", clean], check=True, capture_output=True)
    model = tmp_path / "model.yaml"
    model.write_text("terms:\n  - type: polynomial\n    degree: 3\n")
    common = ("--model", model, "--permutations", "9", "--effects", "sensor_offset", "--json")

    def gap_notes(cap):
        doc = json.loads(run_cli("diagnose", cap, *common).stdout)
        base = doc["candidates"]["base"]["cv_position_mm_mean"]
        valid = next(t for t in doc["tables"] if t["set_name"] == "valid")["after_position_mm"]["mean"]
        return [n for n in doc["notes"] if "does not carry over" in n], valid / base

    notes, ratio = gap_notes(clean)
    assert not notes and ratio < 1.5, (notes, ratio)  # no drift: no note (measured 0.81)
    notes, ratio = gap_notes(_drifted(clean, tmp_path / "drifted", 0.001))
    assert ratio > 3 and len(notes) == 1, (notes, ratio)  # measured 5.3 (0.463 / 0.088 mm)
    assert notes[0].startswith("the validation stations' corrected position error (mean "), notes
    assert "a drift over the capture" in notes[0]


def test_a_size_that_follows_time_is_not_called_a_growing_scatter():
    # A receiver gain drifting over the capture (ideal room, paper_small grid, seed 61; after a
    # constant receiver_gain, 1.85 mm held out, 30x the noise floor): only the size of the residual
    # followed a covariate, time among them, and the verdict called it a scatter that grows with
    # range, "no sign of a missing effect". Range does not follow time.
    drift = [CovariateEffect("z", "orientation_deg", 0.16, 0.0002, True, 300),
             CovariateEffect("time", "position_mm", 0.11, 0.0002, True, 300),
             CovariateEffect("time", "position_vector", 0.004, 0.3, False, 300)]
    v = diagnosis.verdict(contract_b_doc(False), drift)
    assert v["source"] == "covariate" and v["model_change"] is None
    assert "no sign of a missing effect" not in v["text"], v["text"]
    assert "grows with range" not in v["text"], v["text"]
    assert "time (R^2 0.11" in v["text"], v["text"]


def test_extrapolation_note_of_a_stream_counts_samples_and_points_at_the_worst_moments():
    # On a stream the note said "stations lie outside ... (by distance and worst stations above)"
    # where the list above is headed "Worst 10 moments of the stream".
    from types import SimpleNamespace
    n_in, n_out = 60, 29
    after = SimpleNamespace(position_mm=np.r_[np.full(n_in, 0.4), np.linspace(60, 177, n_out)])
    v = SimpleNamespace(after=after, calibration=object(), flipped=np.zeros(n_in + n_out, bool),
                        extrapolated=np.r_[np.zeros(n_in, bool), np.ones(n_out, bool)],
                        capture=SimpleNamespace(speed=np.zeros(n_in + n_out)), worst_separation_s=0.5)
    note = diagnosis.extrapolation_note(v)
    assert note.startswith("29 of 89 samples lie outside the calibrated volume"), note
    assert "(by distance and worst moments above)" in note and "station" not in note, note
    # Stations (no speed, no separation of the worst list) keep their words.
    v.capture, v.worst_separation_s = SimpleNamespace(speed=None), None
    note = diagnosis.extrapolation_note(v)
    assert note.startswith("29 of 89 stations lie outside") and "worst stations above" in note, note


def test_a_verdict_of_sentences_takes_the_worse_region_as_a_sentence_of_its_own():
    # The engine's verdict ends with a full stop ("... add the top one, then diagnose again."): the
    # worse-region clause was glued to it as "diagnose again.; and the correction makes ...".
    from types import SimpleNamespace
    n = 40
    v = SimpleNamespace(after=SimpleNamespace(position_mm=np.full(n, 6.0), orientation_deg=np.full(n, 1.8)),
                        extrapolated=np.zeros(n, bool), flipped=np.zeros(n, bool),
                        by_distance=[{"label": "0.00-0.25 m", "count": n, "before_position_mm": 0.5,
                                      "before_orientation_deg": 0.2, "after_position_mm": 6.0,
                                      "after_orientation_deg": 1.8}], by_region=[])
    sentences = {"source": "candidate", "text": "A dipole explains the remaining structure. 1 other candidate "
                 "is also significant: add the top one, then diagnose again."}
    text = diagnosis.verdict_with_regions(sentences, v)["text"]
    assert ".;" not in text and text.endswith("diagnose again. Also, the correction makes 0.00-0.25 m from "
                                              "the transmitter worse than uncorrected (note)."), text
    clause = diagnosis.verdict_with_regions({"source": None, "text": "nothing significant remains"}, v)["text"]
    assert clause == ("nothing significant remains; and the correction makes 0.00-0.25 m from the transmitter "
                      "worse than uncorrected (note)"), clause


def test_a_label_covariate_of_a_stream_counts_its_samples():
    # Labels logged beside a stream (the operator holding the probe): "bob 2.1 mm along (...), 1800
    # stations" counted the stream's samples as stations, in the diagnose text, the report's table
    # and the verdict. A stream's (serial_time given) count samples; stations' stay stations.
    from trackcal import validation
    rng = np.random.default_rng(3)
    n = 600
    time = np.arange(n) / 120.0
    operator = (time >= 2.5).astype(float)  # codes into the labels: alice, then bob
    err = rng.normal(scale=1e-4, size=(n, 3))
    err[operator == 1, 0] += 2e-3
    res = validation.Residuals(position=err, orientation=np.zeros((n, 3)),
                               position_mm=np.linalg.norm(err, axis=1) * 1e3, orientation_deg=np.zeros(n))
    phrases = {}
    for name, serial in (("stream", time), ("stations", None)):
        effects = validation.covariate_analysis(res, {"operator": operator}, n_permutations=19,
                                                serial_time=serial, labels={"operator": ["alice", "bob"]})
        e = next(e for e in effects if e.target == "position_vector")
        phrases[name] = diagnosis.levels_phrase(e.levels)
    assert "samples" in phrases["stream"] and "station" not in phrases["stream"], phrases
    assert f"{int((operator == 1).sum())} samples" in phrases["stream"], phrases
    assert "stations" in phrases["stations"] and "samples" not in phrases["stations"], phrases
