"""What a lab engineer reads on the terminal: the candidates' physical statements in the text of
``trackcal diagnose``, a readable outlier line from ``trackcal fit``, and a history whose last
changes stay visible (log axes) and say which set's error they show."""

import shutil
import subprocess
import sys

import pytest

from trackcal import figures, history
from understand_support import simulate

MODEL = "terms:\n  - type: polynomial\n    degree: 3\n"


def run_cli(*args):
    exe = shutil.which("trackcal")
    cmd = [exe] if exe else [sys.executable, "-m", "trackcal.cli"]
    r = subprocess.run(cmd + [str(a) for a in args], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    return r


@pytest.fixture(scope="module")
def capture_dir(tmp_path_factory):
    return simulate(tmp_path_factory.mktemp("clitext") / "capture", seed=73, hidden="sensor_offset")


def test_diagnose_text_states_every_candidate_physically(capture_dir, tmp_path):
    model = tmp_path / "model.yaml"
    model.write_text(MODEL)
    r = run_cli("diagnose", capture_dir, "--model", model, "--permutations", "9", "--effects", "sensor_offset",
                "--folds", "2")
    text = r.stdout
    table = text[text.index("Candidate effects"):text.index("Verdict")]
    # Under the ranking table, each candidate's fit in physical words (the engine's statement) and
    # the reason it is or is not claimed.
    assert "1 sensor_offset: a sensor offset of (" in table
    assert "held-out error falls" in table
    # The flexible fallback's row says why it was not fitted (a catalog effect is significant).
    assert "flexible polynomial_3 (not an effect): not fitted: a catalog effect is significant" in table
    # The change, headed by where it goes (a term: into terms:, before the polynomial).
    assert "Model-file change (in terms:, as item 0 counting from 0):" in text
    assert "+  - type: sensor_offset" in text[text.index("Model-file change"):]


def test_fit_lists_a_readable_number_of_outliers(capture_dir, tmp_path):
    model = tmp_path / "model.yaml"
    # A degree-1 polynomial leaves most stations far beyond the noise in the paper room with an
    # offset sensor: nearly all are outliers.
    model.write_text("terms:\n  - type: polynomial\n    degree: 1\n")
    r = run_cli("fit", "--data", capture_dir, "--model", model, "-o", tmp_path / "c.json")
    line = next(l for l in r.stdout.splitlines() if l.startswith("Outlier stations"))
    assert " of 480): " in line  # out of the calib stations
    assert len(line.split(":", 1)[1].split()) <= 23  # 20 ids and "... (N more)"
    assert "most stations are outliers" in r.stdout
    # Solved in closed form (paper eq. 9), not "converged after 0 iterations".
    assert "Fit: solved by linear least squares in " in r.stdout


def entry(label, pos, ori, set_name="valid"):
    return {"label": label, "scores": {"calib": {"position_mm": {"mean": pos / 2}, "orientation_deg": {"mean": ori / 2}},
                                       set_name: {"position_mm": {"mean": pos}, "orientation_deg": {"mean": ori}}}}


def test_history_plot_keeps_the_last_changes_visible():
    # The main job's loop: 25.9 mm -> 0.09 mm. On a linear axis the last two changes are flat.
    entries = [entry("base", 25.866, 3.227), entry("+sensor_offset", 0.877, 0.160),
               entry("+dipole", 0.194, 0.036), entry("+plane", 0.090, 0.022)]
    import matplotlib.pyplot as plt
    fig = figures.history_plot(entries)
    left, right = fig.axes
    assert left.get_yscale() == "log" and right.get_yscale() == "log"
    assert "(valid)" in left.get_title()
    # One legend names both lines (the two y axes' colours alone did).
    legend = left.get_legend()
    assert legend is not None
    assert [t.get_text() for t in legend.get_texts()] == ["position mean [mm]", "orientation mean [deg]"]
    plt.close(fig)
    # Errors within a factor of 20 stay linear.
    fig = figures.history_plot([entry("a", 2.0, 0.2), entry("b", 1.5, 0.15)])
    assert fig.axes[0].get_yscale() == "linear"
    plt.close(fig)


def test_history_plot_joins_only_comparable_rows():
    # Rows 1-2 on one capture, row 3 on another: the table says "other data", the plot must not
    # draw the step from 2 to 3 as a change.
    rows = [entry("a", 2.0, 0.2), entry("b", 1.5, 0.15), entry("c", 9.0, 0.9)]
    for r, sha in zip(rows, ["1", "1", "2"]):
        r["data"] = [{"sha256": sha}]
    import matplotlib.pyplot as plt
    fig = figures.history_plot(rows)
    left, right = fig.axes
    for axis in (left, right):
        assert [len(line.get_xdata()) for line in axis.get_lines()] == [2, 1]
    assert [h.get_label() for h in left.get_legend_handles_labels()[0]] == ["position mean [mm]"]
    plt.close(fig)


def test_history_plot_says_why_a_row_is_not_joined_to_the_one_before():
    # A work folder of fits on two captures and of two sets: the table says "other data" and
    # "other set", but the plot only broke the line, so a reader of the report's figure took the
    # fall from row 3 to row 4 for a change of the model (measured on a work folder: 29.0 mm with
    # a LUT on capture 1, then 4.7 mm with a sensor offset on capture 2).
    rows = [entry("a", 25.6, 3.2), entry("b", 4.1, 0.6), entry("c", 29.0, 3.8), entry("d", 4.7, 0.7),
            entry("e", 4.0, 0.5, "cross-validation (5-fold)")]
    for r, sha in zip(rows, ["1", "1", "1", "2", "2"]):
        r["data"] = [{"sha256": sha}]
    import matplotlib.pyplot as plt
    fig = figures.history_plot(rows)
    fig.canvas.draw()
    left = fig.axes[0]
    flags = {t.get_text(): t for t in left.texts}
    assert set(flags) == {"other data", "other set"}, list(flags)
    # Each at the break it names, between the two rows (in data coordinates along x).
    assert 3 < flags["other data"].get_position()[0] < 4
    assert 4 < flags["other set"].get_position()[0] < 5
    dividers = [seg[0][0] for c in left.collections for seg in c.get_segments() if seg[0][0] == seg[1][0]]
    assert sorted(dividers) == [3.5, 4.5]  # a divider at each
    plt.close(fig)


def test_history_plot_legend_hides_no_point():
    # Row 3 is the highest on both axes, at the right: the legend (upper right, inside the axes)
    # was drawn over its markers.
    rows = [entry("a", 25.6, 3.2), entry("b", 4.1, 0.6), entry("c", 29.0, 3.8), entry("d", 4.7, 0.7)]
    import matplotlib.pyplot as plt
    fig = figures.history_plot(rows)
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    legends = [a.get_legend() for a in fig.axes if a.get_legend()] + list(fig.legends)
    assert len(legends) == 1
    box = legends[0].get_window_extent(renderer)
    for axis in fig.axes:
        for line in axis.get_lines():
            for x, y in axis.transData.transform(line.get_xydata()):
                # 6 px: the largest marker's half-width at the figure's 100 dpi (9 pt squares).
                assert not (box.x0 - 6 < x < box.x1 + 6 and box.y0 - 6 < y < box.y1 + 6), (x, y, box)
    plt.close(fig)


def test_history_table_shows_the_median_fall_that_gross_errors_hide_from_the_mean():
    # Measured, workflow loop with hidden hemisphere flips (seed 2): the validation set holds
    # flipped reports, 2 |p| off whatever the calibration, so the mean rose 16.0 -> 19.4 mm when the
    # robust loss stopped the fit from bending towards them while the median fell 1.83 -> 0.48 mm.
    base, loss = entry("base", 16.035, 0.5), entry("+robust_loss", 19.446, 0.4)
    base["scores"]["valid"]["position_mm"]["median"] = 1.8252
    loss["scores"]["valid"]["position_mm"]["median"] = 0.4828
    lines = history.history_table([base, loss]).splitlines()
    assert "median mm" in lines[0]
    assert "1.825" in lines[1] and "+21.3%" in lines[2]
    assert "0.483" in lines[2] and "-73.5%" in lines[2]
    # A record without a median (older files) leaves the column blank instead of failing.
    lines = history.history_table([entry("a", 2.0, 0.2), entry("b", 1.0, 0.1)]).splitlines()
    assert "-50.0%" in lines[2] and "nan" not in lines[2]


def test_history_table_names_the_set_of_each_row():
    rows = history.history_table([entry("base", 2.0, 0.2, "cross-validation (5-fold)"), entry("+x", 1.0, 0.1)])
    lines = rows.splitlines()
    assert " set " in lines[0]
    assert "cross-valida" in lines[1] and "valid " in lines[2]


def test_history_labels_name_the_effect_added(capture_dir, tmp_path):
    """`trackcal fit --workdir` labels each fit by the effects added, as the user wrote them in the
    model file (not the engine's internal 'physical' chain), and counts a second dipole as a change."""
    assert history.term_change(["dipole", "polynomial"], ["dipole", "dipole", "polynomial"]) == "+dipole"
    work = tmp_path / "work"
    first, second = tmp_path / "m1.yaml", tmp_path / "m2.yaml"
    first.write_text(MODEL)
    second.write_text("terms:\n  - type: sensor_offset\n" + MODEL.split("\n", 1)[1])
    run_cli("fit", "--data", capture_dir, "--model", first, "-o", tmp_path / "c1.json", "--workdir", work)
    run_cli("fit", "--data", capture_dir, "--model", second, "-o", tmp_path / "c2.json", "--workdir", work)
    entries = history.load_history(work)
    assert [e["label"] for e in entries] == ["polynomial", "+sensor_offset"]
    assert entries[1]["terms"] == ["sensor_offset", "polynomial"]


def test_history_table_compares_only_rows_on_the_same_data_and_set():
    # A reviewer's work folder: a fit on another capture showed "+362.7%" against the previous row,
    # and a cross-validation figure was compared with a validation-set one.
    a, b, c, d = (entry("base", 2.0, 0.2), entry("+x", 1.0, 0.1), entry("+x", 9.0, 0.3),
                  entry("+y", 0.5, 0.05, "cross-validation (5-fold)"))
    for e, sha in ((a, "aa"), (b, "aa"), (c, "bb"), (d, "bb")):
        e["data"] = [{"path": "poses.csv", "role": "calibration_capture", "sha256": sha}]
    lines = history.history_table([a, b, c, d]).splitlines()
    assert "-50.0%" in lines[2]
    assert "other data" in lines[3] and "%" not in lines[3]
    assert "other set" in lines[4] and "%" not in lines[4]
    assert "cross-validation (5-fold)" in lines[4]  # the set's whole name


def test_history_table_of_the_last_rows_keeps_their_numbers():
    # trackcal fit --workdir prints the last two rows of the history: fit #7 is not "#2".
    lines = history.history_table([entry("a", 2.0, 0.2), entry("b", 1.0, 0.1)], first=6).splitlines()
    assert lines[1].split()[0] == "6" and lines[2].split()[0] == "7"
    assert "-50.0%" in lines[2] and lines[1].split()[1] == "a"


def test_error_vs_distance_tells_the_in_sample_and_the_extrapolated_stations_apart():
    # Calib stations fitted to 0.1 mm, valid stations at 1 mm: the binned mean after must be the
    # valid set's (as Table 1's), not a mix pulled down by the in-sample errors.
    import numpy as np
    import matplotlib.pyplot as plt
    distance = np.tile(np.linspace(0.3, 1.5, 40), 2)
    held_out = np.repeat([False, True], 40)
    after = np.where(held_out, 1.0, 0.1)
    fig = figures.error_vs_distance(distance, np.full(80, 20.0), after, held_out=held_out)
    ax = fig.axes[0]
    labels = [h.get_label() for h in ax.get_legend_handles_labels()[0]]
    assert "after, calib set" in labels and "after, valid set" in labels
    line = next(l for l in ax.get_lines() if l.get_label() == "after, valid set (binned mean)")
    assert np.allclose(line.get_ydata(), 1.0)
    plt.close(fig)
    # One set only: drawn as before.
    fig = figures.error_vs_distance(distance, np.full(80, 20.0), after, held_out=np.zeros(80, bool))
    assert "after (binned mean)" in [l.get_label() for l in fig.axes[0].get_lines()]
    plt.close(fig)
    # Stations outside the calibrated volume are crossed, and counted in the legend.
    outside = distance > 1.45
    fig = figures.error_vs_distance(distance, np.full(80, 20.0), after, outside=outside)
    labels = [h.get_label() for h in fig.axes[0].get_legend_handles_labels()[0]]
    assert f"after, outside the calibrated volume ({int(outside.sum())})" in labels
    plt.close(fig)


def test_error_vs_distance_after_a_correction_to_near_the_noise_is_on_a_log_axis():
    # The demo's final calibration: 32 mm before, 0.072 mm after on the valid set. On a linear
    # axis to 90 mm every after point and its binned mean lay on the zero line, 0.3 px above it at
    # 110 dpi: figures 4 and 5 said nothing of the error after. Logarithmic beyond a factor of 20
    # between the medians (as the history plot); a correction that halves the error stays linear.
    import numpy as np
    import matplotlib.pyplot as plt
    rng = np.random.default_rng(3)
    distance = rng.uniform(0.3, 1.1, 300)
    before = 20.0 + 40.0 * rng.random(300)
    held_out = np.arange(300) % 5 == 0
    for after, scale in ((0.07 * (1.0 + rng.random(300)), "log"), (0.5 * before, "linear")):
        fig = figures.error_vs_distance(distance, before, after, held_out=held_out)
        try:
            ax = fig.axes[0]
            assert ax.get_yscale() == scale
            if scale == "log":
                lo, hi = ax.get_ylim()
                assert lo < 0.07 and hi > before.max()  # every point, before and after, on the axes
                assert "log" in ax.get_ylabel()
        finally:
            plt.close(fig)


def test_error_vs_distance_draws_the_outside_crosses_under_the_after_points():
    # A stream with 22741 samples outside the volume: black crosses (s=16) drawn last buried every
    # after point beneath them. They go under the after points, smaller and lighter.
    import numpy as np
    import matplotlib.pyplot as plt
    from matplotlib.colors import to_rgba
    distance = np.linspace(0.3, 1.5, 400)
    outside = distance > 0.5
    fig = figures.error_vs_distance(distance, np.full(400, 20.0), np.full(400, 1.0), outside=outside)
    try:
        cols = {c.get_label(): c for c in fig.axes[0].collections}
        crosses = cols[f"after, outside the calibrated volume ({int(outside.sum())})"]
        after = cols["after"]
        assert crosses.get_zorder() < after.get_zorder()
        assert max(crosses.get_sizes()) <= max(after.get_sizes())
        rgba = crosses.get_edgecolor()[0]
        assert rgba[3] <= 0.5 and min(rgba[:3]) >= 0.3, rgba  # light grey, half transparent
    finally:
        plt.close(fig)


def test_numbers_that_round_to_zero_are_printed_without_a_minus():
    # A stream paired at a clock offset of -4 us printed "a time offset of -0.00 ms": a measured
    # negative offset to the reader. The report's tables (a coordinate of -0.0002 m) likewise.
    from trackcal import captures, report
    from trackcal._format import fixed
    assert fixed(-0.004, "{:.2f}") == "0.00" and fixed(-0.006, "{:.2f}") == "-0.01"
    assert fixed(-0.0, "{:.3f}") == "0.000" and fixed(float("-inf"), "{:.1f}") == "-inf"
    cap = captures.PoseCapture.__new__(captures.PoseCapture)
    cap.origin = {"kind": "streams", "time_offset_s": -4e-6, "time_offset_source": "estimated",
                  "paired": 10, "sensor": 1, "dropped": 0}
    assert "time offset of 0.00 ms" in captures.describe_origin(cap)
    assert "<td>0.000</td>" in report._table([{"x": -0.0002}]) and "-0.000" not in report._table([{"x": -0.0002}])
    from trackcal.cli import _cell
    assert _cell(-0.0004) == "0.000"
