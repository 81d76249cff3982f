"""The HTML report renders in headless Chromium with every figure loaded; the check itself fails
on a broken figure."""

import base64
import os
import pathlib
import re
import shutil
import stat
import subprocess

import numpy as np
import pytest

import trackcal
from trackcal import figures, captures, report, validation
from trackcal.history import record_fit, load_history, scores_from_validation
from understand_support import simulate, stream_only

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"


def dump_dom(html_path: pathlib.Path, profile: pathlib.Path) -> str:
    if not os.path.exists(CHROMIUM):
        pytest.fail("chromium is required (scripts/install-deps.sh installs it)")
    cmd = [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
           "--disable-background-networking", "--disable-component-update", "--disable-sync",
           f"--user-data-dir={profile}", "--virtual-time-budget=5000", "--dump-dom", html_path.as_uri()]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    return r.stdout


@pytest.fixture(scope="module")
def written_report(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("report")
    cap_dir = simulate(tmp / "capture", seed=31)
    cap = captures.load_poses(cap_dir)
    cal = validation.fit_polynomial(cap.select_set("calib"), degree=3)
    cal_path = tmp / "calibration.json"
    cal.save(cal_path)
    work = tmp / "work"
    v = validation.validate(cap, cal, covariate_options={"n_permutations": 49})
    record_fit(work, model=cal_path, data=[(cap_dir / "poses.csv", "calibration_capture")],
               scores=scores_from_validation(validation.validate(cap, None, analyse_covariates=False)),
               label="uncorrected")
    record_fit(work, model=cal_path, data=[(cap_dir / "poses.csv", "calibration_capture")],
               scores=scores_from_validation(v), label="polynomial r=3")
    out = tmp / "out"
    ranking = {"folds": 5, "base": {"cv_position_mm_mean": 2.0, "cv_orientation_deg_mean": 0.2},
               "candidates": [{"effect": "sensor_offset", "cv_position_mm_mean": 1.2, "cv_orientation_deg_mean": 0.1,
                               "cv_drop_percent": {"position": 40.0, "orientation": 50.0}, "delta_bic": -90.0,
                               "p_value": 1e-6, "significant": True, "reason": "held-out error falls 40 %",
                               "model_change": "- type: sensor_offset\n", "insert_index": 0},
                              {"effect": "robust_loss", "cv_position_mm_mean": None, "cv_orientation_deg_mean": None,
                               "cv_drop_percent": None, "delta_bic": 661.5, "p_value": None, "significant": False,
                               "reason": "not cross-validated: its fit rejects no station as a gross outlier"}],
               "verdict": {"effect": "sensor_offset", "text": "a sensor offset explains the remaining structure"}}
    html = report.write_report(v, out, inputs=[cap_dir / "poses.csv", cal_path],
                               history_entries=load_history(work), candidates=ranking,
                               model_change={"yaml": "- type: sensor_offset\n", "diff": None})
    return html


def test_report_renders_every_figure(written_report, tmp_path):
    text = written_report.read_text()
    n_img = text.count("<img ")
    # fig 4, 5, 7, 6, two residual maps, two covariate charts, candidates, history.
    assert n_img == 10
    assert "http://" not in text and "https://" not in text  # self-contained, opens offline
    assert "Candidate effects" in text and "sensor_offset" in text
    assert "<td>None</td>" not in text  # a candidate without held-out scores shows empty cells
    assert "a sensor offset explains the remaining structure" in text  # the verdict
    assert "History of fits" in text and "polynomial r=3" in text
    pngs = sorted(p.name for p in written_report.parent.glob("*.png"))
    assert len(pngs) == n_img and "fig6_distortion_field.png" in pngs
    dom = dump_dom(written_report, tmp_path / "profile")
    m = re.search(r'<body[^>]*\sdata-figures-ok="(\d+)"', dom)
    assert m and int(m.group(1)) == n_img, dom[:500]
    assert not re.search(r"<body[^>]*data-figures-broken", dom)


def _blank_png() -> bytes:
    import matplotlib.pyplot as plt
    fig = plt.figure(figsize=(2, 2))  # nothing drawn: one colour
    try:
        return figures.png_bytes(fig)
    finally:
        plt.close(fig)


# A figure that does not render, three ways. A cut PNG (its header and the first third of its
# data: a write or a copy cut short) has its size and decodes as far as it goes, so Chromium
# marks it complete with its natural width, and the check counted it as rendered (measured: a
# page with figure 4 cut so gave data-figures-ok="10"). A figure with nothing drawn is one colour.
@pytest.mark.parametrize("breakage,why", [("not a png", "not decoded"), ("cut short", "not fully decoded"),
                                          ("nothing drawn", "blank")])
def test_render_check_detects_a_broken_figure(written_report, tmp_path, breakage, why):
    text = written_report.read_text()
    first = re.search(r"src='data:image/png;base64,([A-Za-z0-9+/=]+)'", text)
    data = base64.b64decode(first.group(1))
    bad = {"not a png": b"not a png", "cut short": data[:len(data) // 3], "nothing drawn": _blank_png()}[breakage]
    broken = text.replace(first.group(1), base64.b64encode(bad).decode(), 1)
    page = tmp_path / "broken.html"
    page.write_text(broken)
    dom = dump_dom(page, tmp_path / "profile")
    m = re.search(r'<body[^>]*\sdata-figures-broken="([^"]*)"', dom)
    assert m and m.group(1) == f"fig4_position_error_vs_distance.png ({why})", dom[:300]
    assert not re.search(r"<body[^>]*data-figures-ok", dom)


def test_report_refuses_to_overwrite_an_input(tmp_path):
    cap_dir = simulate(tmp_path / "capture", seed=32)
    cap = captures.load_poses(cap_dir)
    v = validation.validate(cap, None, analyse_covariates=False)
    # Pretend the capture itself is named like the report: it must not be replaced.
    fake = tmp_path / "out" / "report.html"
    fake.parent.mkdir()
    fake.write_text("precious")
    with pytest.raises(ValueError, match="refusing to overwrite an input"):
        report.write_report(v, tmp_path / "out", inputs=[fake])
    assert fake.read_text() == "precious"
    # An output "folder" that is a file: a ValueError naming it, the file untouched.
    with pytest.raises(ValueError, match="is not a folder"):
        report.write_report(v, fake)
    assert fake.read_text() == "precious"


def test_report_replaces_only_an_earlier_report_and_files_get_the_umask_mode(tmp_path):
    cap_dir = simulate(tmp_path / "capture", seed=33)
    cap = captures.load_poses(cap_dir)
    v = validation.validate(cap, None, analyse_covariates=False)
    out = tmp_path / "out"
    out.mkdir()
    mine = out / "report.html"
    mine.write_text("<html>my notes</html>")
    with pytest.raises(ValueError, match="not a trackcal report"):
        report.write_report(v, out)
    assert mine.read_text() == "<html>my notes</html>"
    assert list(out.iterdir()) == [mine]  # refused before any figure was written
    mine.unlink()
    old_umask = os.umask(0o022)
    try:
        first = report.write_report(v, out)
        again = report.write_report(v, out)  # an earlier report is replaced
    finally:
        os.umask(old_umask)
    assert first == again and "trackcal report" in again.read_text()[:4096]
    # mkstemp makes files 0600; outputs are shared like any other new file (umask 022: 0644).
    for f in out.iterdir():
        assert stat.S_IMODE(f.stat().st_mode) == 0o644, f


def test_report_never_replaces_a_users_file_named_like_a_figure(tmp_path):
    cap = captures.load_poses(simulate(tmp_path / "capture", seed=35))
    v = validation.validate(cap, None, analyse_covariates=False)
    out = tmp_path / "out"
    out.mkdir()
    mine = out / "fig4_position_error_vs_distance.png"  # a user's picture, in a folder with no report
    mine.write_bytes(b"\x89PNG\r\n\x1a\n" + b"mine" * 8)
    import matplotlib.pyplot as plt
    open_before = set(plt.get_fignums())
    with pytest.raises(ValueError, match="not a figure of a trackcal report"):
        report.write_report(v, out)
    assert mine.read_bytes() == b"\x89PNG\r\n\x1a\n" + b"mine" * 8
    assert list(out.iterdir()) == [mine]  # refused before any figure was written
    assert set(plt.get_fignums()) == open_before  # and the figures it drew are closed
    mine.unlink()
    page = report.write_report(v, out)
    # Its own figures carry the tag and are replaced by the next report into the folder; so are
    # those of a report written before the tag (the folder holds that report).
    assert figures.is_trackcal_png(mine) and report.write_report(v, out) == page
    mine.write_bytes(b"\x89PNG\r\n\x1a\n" + b"old figure" * 4)
    assert report.write_report(v, out) == page and figures.is_trackcal_png(mine)


def test_report_replaces_a_report_written_before_the_generator_tag(tmp_path):
    cap = captures.load_poses(simulate(tmp_path / "capture", seed=34))
    v = validation.validate(cap, None, analyse_covariates=False)
    out = tmp_path / "out"
    page = report.write_report(v, out)
    old = page.read_text().replace(report.GENERATOR_META, "")  # as an earlier version wrote it
    page.write_text(old)
    assert report.write_report(v, out) == page and report.GENERATOR_META in page.read_text()


@pytest.fixture(scope="module")
def uncorrected(tmp_path_factory):
    cap = captures.load_poses(simulate(tmp_path_factory.mktemp("edge") / "capture", seed=36))
    return validation.validate(cap, None, analyse_covariates=False)


def test_report_of_a_ranking_whose_base_has_no_held_out_mean(uncorrected, tmp_path):
    # The engine writes a mean it could not compute (NaN) as null: the page says n/a instead of
    # failing with a TypeError traceback after the whole diagnosis.
    doc = {"folds": 5, "base": {"cv_position_mm_mean": None, "cv_orientation_deg_mean": None},
           "candidates": [{"effect": "dipole", "cv_position_mm_mean": None, "cv_orientation_deg_mean": None,
                           "cv_drop_percent": None, "delta_bic": 3.0, "p_value": None, "significant": False,
                           "reason": "not cross-validated"}]}
    text = report.write_report(uncorrected, tmp_path / "out", candidates=doc).read_text()
    assert "The model alone: n/a mm, n/a deg." in text


def test_report_of_a_validation_without_covariate_tests_does_not_call_them_clean(uncorrected, tmp_path):
    # validate(analyse_covariates=False) tested no covariate: the verdict of a ranking that finds
    # nothing must say so instead of "nothing significant remains in the covariates".
    doc = {"folds": 5, "base": {"cv_position_mm_mean": 1.0, "cv_orientation_deg_mean": 0.1},
           "candidates": [{"effect": "dipole", "cv_position_mm_mean": 1.0, "cv_orientation_deg_mean": 0.1,
                           "cv_drop_percent": {"position": 0.1, "orientation": 0.0}, "delta_bic": 3.0,
                           "p_value": 0.4, "significant": False, "reason": "no held-out gain"}]}
    assert not uncorrected.covariates_tested
    page = report.write_report(uncorrected, tmp_path / "out", candidates=doc).read_text()
    verdict = page.split("<h2>Verdict</h2>", 1)[1].split("</p>", 1)[0]
    assert "in the covariates" not in verdict and "covariates not tested" in verdict, verdict


def test_residual_map_colour_scale_ignores_a_station_without_value():
    import matplotlib.pyplot as plt
    rng = np.random.default_rng(0)
    pos, val = rng.normal(size=(50, 3)), rng.uniform(1.0, 5.0, 50)
    val[3] = np.nan
    fig = figures.residual_map(pos, val)
    try:
        norm = fig.axes[0].collections[0].norm
        assert norm.vmax == pytest.approx(np.nanpercentile(val, 98))  # not NaN: one colour for all
        assert len(fig.axes[0].collections[1].get_offsets()) == 1  # the NaN station, drawn apart
    finally:
        plt.close(fig)


def test_orientation_slice_scale_ignores_a_station_without_value():
    import matplotlib.pyplot as plt
    rng = np.random.default_rng(1)
    pos = rng.uniform(-0.5, 0.5, size=(40, 3))
    pos[:, 2] = 0.0
    vec = rng.normal(scale=0.01, size=(40, 3))
    vec[0] = np.nan
    fig = figures.orientation_vectors_slice(pos, vec)
    try:
        q = next(c for c in fig.axes[0].collections if hasattr(c, "scale"))
        assert np.isfinite(q.scale) and q.scale > 0
    finally:
        plt.close(fig)


def test_orientation_slice_of_a_stream_draws_arrows_spread_over_the_slab():
    # A stream capture: thousands of samples along a path. Every sample's arrow overlapped the next
    # (688 of them in the measured stream capture's slab: one red smear).
    import matplotlib.pyplot as plt
    t = np.linspace(0.0, 2 * np.pi, 3000)
    pos = np.column_stack([0.6 * np.cos(t), 0.5 * np.sin(2 * t), np.zeros_like(t)])
    vec = np.column_stack([0.01 * np.cos(t), 0.01 * np.sin(t), np.zeros_like(t)])
    fig = figures.orientation_vectors_slice(pos, vec, after_vectors=vec / 4)
    try:
        arrows = [c for c in fig.axes[0].collections if hasattr(c, "scale")]
        assert len(arrows) == 2 and all(20 <= len(a.get_offsets()) <= 200 for a in arrows)
        assert "3000 stations," in fig.axes[0].get_title() and "with arrows" in fig.axes[0].get_title()
        assert len(fig.axes[0].collections[0].get_offsets()) == 3000  # every sample still a dot
    finally:
        plt.close(fig)
    fig = figures.orientation_vectors_slice(pos[:150], vec[:150])  # a station capture: every arrow
    try:
        assert len(next(c for c in fig.axes[0].collections if hasattr(c, "scale")).get_offsets()) == 150
    finally:
        plt.close(fig)


def test_orientation_slice_of_a_grid_with_an_even_number_of_layers_is_not_empty():
    # A calibration grid of 4 layers 0.15 m apart (the paper preset's, a capture with no validation
    # set): the median height falls between layers 2 and 3, 0.075 m from each, and the slab of
    # +-0.056 m around it held no station: figure 7 was an empty frame ("0 stations").
    import matplotlib.pyplot as plt
    g = np.meshgrid(np.arange(12) * 0.15, np.arange(10) * 0.15, -0.8 + np.arange(4) * 0.15, indexing="ij")
    pos = np.column_stack([a.ravel() for a in g])
    vec = np.tile([0.01, 0.0, 0.0], (len(pos), 1))
    fig = figures.orientation_vectors_slice(pos, vec, after_vectors=vec / 2)
    try:
        title = fig.axes[0].get_title()
        assert "(120 stations" in title, title  # one whole layer of 12 x 10
        arrows = [c for c in fig.axes[0].collections if hasattr(c, "scale")]
        assert len(arrows) == 2 and all(len(a.get_offsets()) == 120 for a in arrows)
    finally:
        plt.close(fig)


def test_report_over_an_earlier_one_leaves_none_of_its_figures_it_does_not_draw(tmp_path):
    # A report with a calibration and a history, then one without either into the same folder:
    # the first one's fig6 and history.png stayed beside the new page, as if they were its figures.
    cap = captures.load_poses(simulate(tmp_path / "capture", seed=37))
    cal = validation.fit_polynomial(cap.select_set("calib"), degree=2)
    with_cal = validation.validate(cap, cal, analyse_covariates=False)
    cal_path = tmp_path / "calibration.json"
    cal.save(cal_path)
    record_fit(tmp_path / "work", model=cal_path, data=[(tmp_path / "capture" / "poses.csv", "calibration_capture")],
               scores=scores_from_validation(with_cal), label="polynomial r=2")
    out = tmp_path / "out"
    report.write_report(with_cal, out, history_entries=load_history(tmp_path / "work"))
    assert {"fig6_distortion_field.png", "history.png"} <= {p.name for p in out.iterdir()}
    (out / "notes.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"mine" * 8)  # not a figure's name: kept
    # A user's own picture under a figure's name the new report does not draw, without trackcal's
    # PNG tag: kept too (removing it would lose the user's file).
    (out / "candidates.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"mine" * 8)
    page = report.write_report(validation.validate(cap, None, analyse_covariates=False), out)
    drawn = set(re.findall(r"<img alt='([^']+)'", page.read_text()))
    assert {p.name for p in out.glob("*.png")} == drawn | {"notes.png", "candidates.png"}
    assert (out / "candidates.png").read_bytes().endswith(b"mine")
    assert "fig6_distortion_field.png" not in drawn and "history.png" not in drawn
    assert drawn <= set(report.FIGURE_NAMES)


def test_orientation_slice_of_a_calibration_that_makes_things_worse_keeps_its_arrows_short():
    # Before 0.04 deg, after 8 deg (a calibration applied to another setup): scaled by the
    # before-vectors alone, every after-arrow was drawn about 20 m long across the 1 m slab.
    import matplotlib.pyplot as plt
    rng = np.random.default_rng(2)
    pos = rng.uniform(-0.5, 0.5, size=(60, 3))
    pos[:, 2] = 0.0
    before = rng.normal(scale=3e-4, size=(60, 3))
    after = 200.0 * before
    fig = figures.orientation_vectors_slice(pos, before, after_vectors=after)
    try:
        arrows = [c for c in fig.axes[0].collections if hasattr(c, "scale")]
        deg = 2.0 * 180.0 / np.pi
        for q, vec in zip(arrows, (before, after)):
            drawn_m = np.linalg.norm(vec[:, :2] * deg, axis=1) / q.scale  # scale_units "xy": data units
            assert drawn_m.max() <= 0.1 + 1e-9  # the longest arrow, after, 0.1 m (the frame ~1 m)
        assert np.linalg.norm(after[:, :2] * deg, axis=1).max() / arrows[1].scale == pytest.approx(0.1)
    finally:
        plt.close(fig)


def test_report_covariate_table_says_what_diagnose_says_of_a_confounded_covariate(uncorrected, tmp_path):
    # diagnose prints "time ... (explained by position)" after the findings that stand on their
    # own; the report's table called time plainly significant, before z, with p "0.000".
    import dataclasses
    effects = [validation.CovariateEffect("time", "orientation_deg", 0.21, 1.0 / 6000, True, 480,
                                          confounded_with="position"),
               validation.CovariateEffect("z", "orientation_deg", 0.20, 1.0 / 6000, True, 480)]
    v = dataclasses.replace(uncorrected, covariate_effects=effects, covariates_tested=True)
    page = report.write_report(v, tmp_path / "out").read_text()
    table = page.split("<h2>Residual structure (covariates)</h2>", 1)[1].split("</table>", 1)[0]
    rows = re.findall(r"<tr><td>(\w+)</td><td>orientation_deg</td><td>[^<]*</td><td>([^<]*)</td><td>([^<]*)</td>",
                      table)
    assert rows == [("z", "0.000167", "yes"), ("time", "0.000167", "yes (explained by position)")], rows


def test_report_says_which_covariate_was_left_out_as_diagnose_does(uncorrected, tmp_path):
    # diagnose's text and JSON said "visiting_order left out: the same order as time ..."; the
    # report's covariate section did not, so its table looked as if visiting_order had been tested.
    import dataclasses
    why = "the same order as time (every time distinct: the same bins and R²)"
    effects = [validation.CovariateEffect("time", "orientation_deg", 0.21, 1.0 / 6000, True, 480)]
    v = dataclasses.replace(uncorrected, covariate_effects=effects, covariates_tested=True,
                            covariates_left_out={"visiting_order": why})
    page = report.write_report(v, tmp_path / "out").read_text()
    section = page.split("<h2>Residual structure (covariates)</h2>", 1)[1].split("</p>", 1)[0]
    assert f"visiting_order left out: {why}." in section, section


def test_distortion_field_leaves_blank_where_the_model_inverse_does_not_resolve(tmp_path):
    # A fitted floor plane that cuts the calibrated volume (measured: the paper capture fitted with
    # sensor_offset, receiver_gain, plane and dipole; 50 of its 600 stations not converged): beyond
    # the plane the inverse does not converge and the "correction" there is ~0.15 mm, drawn as a
    # dark band with streamlines through it, as if that part of the volume were undistorted.
    import matplotlib.pyplot as plt
    _, cal = _capture_and_calibration_the_inverse_does_not_resolve_everywhere(tmp_path)
    # The figure's grid: 25 x 25 over the volume's x, y on its mid-plane.
    lo, hi = np.asarray(cal.volume_min), np.asarray(cal.volume_max)
    gx, gy = np.meshgrid(np.linspace(lo[0], hi[0], 25), np.linspace(lo[1], hi[1], 25))
    pts = np.column_stack([gx.ravel(), gy.ravel(), np.full(gx.size, 0.5 * (lo[2] + hi[2]))])
    _, _, _, status = cal.correct(pts, np.tile([0.0, 0.0, 0.0, 1.0], (len(pts), 1)), return_status=True)
    unresolved = status != 0
    assert 0 < unresolved.sum() < len(pts)  # the case this test is about
    fig = figures.distortion_field(cal)
    try:
        mesh = next(c for c in fig.axes[0].collections if hasattr(c, "get_array") and c.get_array() is not None
                    and np.size(c.get_array()) == len(pts))
        shown = np.ma.getmaskarray(mesh.get_array()).ravel()
        assert np.array_equal(shown, unresolved)  # blank exactly there, not a ~0 mm value
        assert f"hatched: {int(unresolved.sum())} of {len(pts)}" in fig.axes[0].get_title()
    finally:
        plt.close(fig)


def _capture_and_calibration_the_inverse_does_not_resolve_everywhere(tmp_path):
    """A paper capture and a physical calibration whose fitted floor plane cuts the calibrated
    volume: beyond the plane its model inverse does not converge (figure 6's hatched points)."""
    import json
    cap = captures.load_poses(simulate(tmp_path / "capture", seed=38))
    validation.fit_polynomial(cap.select_set("calib"), degree=1).save(tmp_path / "poly.json")
    doc = json.loads((tmp_path / "poly.json").read_text())  # a valid file; its correction replaced
    doc["calibrated_volume"].update({"min": [-0.85, -0.75, -0.8], "max": [0.88, 0.71, -0.27]})
    doc["corrections"] = [{
        "type": "physical", "field_constant": 1.0, "transmitter_octupole_m2": [0, 0, 0], "objects": [],
        "planes": [{"name": "floor", "point_in_transmitter": [0.262, 0.011, 0.195],
                    "normal_in_transmitter": [0.8, 0.033, 0.6], "attenuation": 0.07}],
        "receiver_from_body": {"rotation_xyzw": [0, 0, 0, 1], "translation": [0, 0, 0]},
        "receiver_gain_matrix": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "tolerance_m": 1e-12,
        "max_iterations": 50, "fold_reach": 3.0, "max_correction_fraction": 0.5, "max_noise_gain": 10.0}]
    (tmp_path / "physical.json").write_text(json.dumps(doc))
    return cap, trackcal.Calibration.load(str(tmp_path / "physical.json"))


def test_report_mentions_hatched_points_of_figure_6_only_when_there_are_some(tmp_path):
    # Every figure 6 caption said "hatched (blank) where a physical term's model inverse does not
    # resolve the pose", also under a polynomial's field, which resolves every point: a reader looked
    # for a missing part of the field. Said only when some points are hatched, with their count.
    import matplotlib.pyplot as plt
    cap, physical = _capture_and_calibration_the_inverse_does_not_resolve_everywhere(tmp_path)
    polynomial = validation.fit_polynomial(cap.select_set("calib"), degree=2)
    captions = {}
    for name, cal in (("polynomial", polynomial), ("physical", physical)):
        figs = report.build_figures(validation.validate(cap, cal, analyse_covariates=False))
        try:
            (captions[name], fig), = [(c, f) for n, c, f in figs if n == "fig6_distortion_field.png"]
            title = fig.axes[0].get_title()
        finally:
            for _, _, f in figs:
                plt.close(f)
        if name == "polynomial":
            assert "hatched" not in captions[name] and "hatched" not in title, captions[name]
        else:  # the count the figure's title gives (test_distortion_field_leaves_blank_...)
            n, total = map(int, re.search(r"hatched: (\d+) of (\d+)", title).groups())
            assert 0 < n < total == 625
            assert f"hatched (blank): {n} of its {total} grid points" in captions[name], captions[name]


def test_orientation_slice_limits_hold_every_arrow_tip():
    # Autoscaling sees a quiver's tails (the stations) only: arrows at the slab's edge pointing out
    # left the axes (measured with these stations: before-tips 0.046 m past the y limits).
    import matplotlib.pyplot as plt
    rng = np.random.default_rng(3)
    pos = rng.uniform(-0.5, 0.5, size=(60, 3))
    pos[:, 2] = 0.0
    vec = np.zeros((60, 3))
    vec[:, :2] = 0.01 * pos[:, :2]  # pointing away from the middle, longest at the corners
    vec[5] = np.nan  # a station without a value draws no arrow and moves no limit
    fig = figures.orientation_vectors_slice(pos, vec, after_vectors=-vec / 2)
    try:
        fig.canvas.draw()  # the limits the PNG has (the equal aspect adjusts them when drawn)
        ax = fig.axes[0]
        (x0, x1), (y0, y1) = ax.get_xlim(), ax.get_ylim()
        arrows = [c for c in ax.collections if hasattr(c, "scale")]
        assert len(arrows) == 2
        for q in arrows:  # angles and scale_units "xy": the tip is the tail + (U, V) / scale
            tips = q.get_offsets() + np.column_stack([q.U, q.V]) / q.scale
            tips = tips[~np.broadcast_to(np.asarray(q.Umask, dtype=bool), len(tips))]  # NaN: masked, no arrow
            assert len(tips) == 59
            assert x0 < tips[:, 0].min() and tips[:, 0].max() < x1 and y0 < tips[:, 1].min() and tips[:, 1].max() < y1
        assert np.all(np.isfinite([x0, x1, y0, y1]))
    finally:
        plt.close(fig)


def test_covariate_bars_set_a_finding_explained_by_another_family_apart():
    # diagnose and the table say "time ... (explained by position)"; the chart drew time as orange as
    # z, a finding that stands on its own, and its legend (the title) said "orange = significant".
    import matplotlib.colors as mcolors
    import matplotlib.pyplot as plt
    effects = [validation.CovariateEffect("z", "orientation_deg", 0.21, 1.0 / 6000, True, 480),
               validation.CovariateEffect("time", "orientation_deg", 0.20, 1.0 / 6000, True, 480,
                                          confounded_with="position"),
               validation.CovariateEffect("speed", "orientation_deg", 0.02, 0.3, False, 480)]
    fig = figures.covariate_bars(effects, target="orientation_deg")
    try:
        ax = fig.axes[0]
        bars = dict(zip([t.get_text() for t in ax.get_yticklabels()], ax.patches))
        colour = {name: mcolors.to_hex(bar.get_facecolor()) for name, bar in bars.items()}
        assert len(set(colour.values())) == 3, colour  # finding, explained finding, not significant
        legend = fig.legends + [ax.get_legend()] if ax.get_legend() else fig.legends
        entries = {t.get_text(): mcolors.to_hex(h.get_facecolor())
                   for lg in legend for t, h in zip(lg.get_texts(), lg.legend_handles)}
        assert entries == {"significant": colour["z"], "significant, explained by position": colour["time"],
                           "not significant": colour["speed"]}, entries
    finally:
        plt.close(fig)


def test_figures_of_a_long_stream_place_legends_and_draw_dots_without_the_slow_paths():
    # A 10-minute stream (72000 samples): at loc "best" the legend of figures 4 and 5 counted every
    # point under each candidate place (4 s a figure), and the residual map's colour-mapped dots
    # each had their edge stroked apart (2.2 s of its 2.5 s). bench/bench_report_figures.py times it.
    import matplotlib.pyplot as plt
    rng = np.random.default_rng(4)
    n = 3000
    distance = rng.uniform(0.2, 1.2, n)
    fig = figures.error_vs_distance(distance, 30 * distance, 3 * distance, held_out=rng.random(n) < 0.3)
    try:
        fig.canvas.draw()
        assert fig.axes[0].get_legend() is None and len(fig.legends) == 1
        legend = fig.legends[0]
        assert legend._loc != 0  # not "best": a fixed place, found without counting points
        # ... under the axes, so it hides no point (the room made by the layout, not over the data).
        box, axes_box = legend.get_window_extent(), fig.axes[0].get_window_extent()
        assert box.y1 < axes_box.y0 and box.y0 >= 0
        assert {t.get_text() for t in legend.get_texts()} >= {"before", "after, valid set (binned mean)"}
    finally:
        plt.close(fig)
    fig = figures.residual_map(rng.normal(size=(n, 3)), rng.uniform(0, 5, n))
    try:
        for ax in fig.axes[:2]:
            dots = ax.collections[0]
            assert np.all(dots.get_linewidths() == 0)
            # As large as the dots were: the area 14 pt^2 plus the default edge (1 pt) around it.
            import matplotlib
            assert matplotlib.rcParams["patch.linewidth"] == 1.0
            assert np.allclose(np.sqrt(dots.get_sizes()), np.sqrt(14.0) + 1.0)
    finally:
        plt.close(fig)


def test_orientation_slice_legend_hides_no_arrow():
    # The legend sat inside the axes (lower right), over the arrows of the slab's corner: measured on
    # a 10-minute stream's figure 7, where the largest arrows are in that corner.
    import matplotlib.pyplot as plt
    rng = np.random.default_rng(5)
    pos = rng.uniform(-0.5, 0.5, size=(80, 3))
    pos[:, 2] = 0.0
    vec = rng.normal(scale=0.01, size=(80, 3))
    fig = figures.orientation_vectors_slice(pos, vec, after_vectors=vec / 3)
    try:
        fig.canvas.draw()
        ax = fig.axes[0]
        legend, box = ax.get_legend(), ax.get_window_extent()
        assert legend is not None and {t.get_text() for t in legend.get_texts()} == {"before", "after"}
        shown = legend.get_window_extent()
        assert shown.y1 <= box.y0 and shown.y0 >= 0 and shown.x1 <= fig.bbox.x1  # under the axes, on the page
    finally:
        plt.close(fig)


@pytest.fixture(scope="module")
def stream_validation(tmp_path_factory):
    """The paper room's 30 s stream (trackcal-simulate, seed 5) validated with a degree-3 polynomial
    fitted to the same simulation's calibration stations (poses.csv), as a lab validates a
    calibration on a stream."""
    root = tmp_path_factory.mktemp("stream")
    sim = simulate(root / "capture", seed=5)
    streams = stream_only(sim, root / "streams")
    cal = validation.fit_polynomial(captures.load_poses(sim).select_set("calib"), degree=3)
    return validation.validate(captures.load(streams), cal, analyse_covariates=False)


def test_stream_report_has_one_table_and_lists_distinct_moments(stream_validation, tmp_path):
    # Every paired sample carries the pairing's label "calib": the page printed a "calib" table
    # equal to the "all" one, as if the samples were the fit's in-sample stations, and the worst
    # list was ten neighbouring samples of one moment (milliseconds apart).
    v = stream_validation
    assert [t.set_name for t in v.tables] == ["all"]
    assert len(v.worst) == 10 and all("set" not in w for w in v.worst)
    times = np.array([w["time"] for w in v.worst])
    gaps = np.abs(times[:, None] - times[None, :])[~np.eye(len(times), dtype=bool)]
    assert gaps.min() >= validation.WORST_SEPARATION_S
    errors = [w["position_mm"] for w in v.worst]
    assert errors == sorted(errors, reverse=True)
    final = v.after.position_mm[~v.flipped]
    assert errors[0] == pytest.approx(final.max())  # the worst sample of all heads the list
    page = report.write_report(v, tmp_path / "out").read_text()
    assert "<h3>calib (" not in page and "<h3>all (" in page
    assert f"Worst 10 moments of the stream (the worst sample of each, at least " \
           f"{validation.WORST_SEPARATION_S:g} s apart" in page


def test_a_region_the_correction_makes_worse_is_named_in_a_note_and_the_verdict(uncorrected):
    # On a stream the correction took 0-0.25 m from the transmitter from 0.57 mm to 4.4 mm and only
    # the by-distance table showed it. Here: the nearest distance band's corrected errors are 3
    # times the uncorrected ones, every other station's a twentieth of them.
    from trackcal import diagnosis
    cap = uncorrected.capture
    band = np.floor(np.linalg.norm(cap.reported_positions, axis=1) / 0.25).astype(int)
    counts = {b: int((band == b).sum()) for b in np.unique(band)}
    near = band == min(b for b, n in counts.items() if n >= diagnosis.WORSE_MIN_SAMPLES)
    err = cap.reported_positions - cap.reference_positions
    pos = cap.reference_positions + np.where(near[:, None], 3.0, 0.05) * err
    # Orientation as reference (unchanged in every region): the position alone must trigger it.
    v = validation.validate(cap, None, corrected_poses=(pos, cap.reference_quaternions_xyzw),
                            analyse_covariates=False)
    row = next(r for r in v.by_distance if r["count"] == int(near.sum()))
    note = diagnosis.worse_regions_note(v)
    assert note is not None and f"{row['label']} from the transmitter ({row['count']} stations: position " \
        f"{row['before_position_mm']:.3f} -> {row['after_position_mm']:.3f} mm" in note, note
    others = [r["label"] for r in v.by_distance if r is not row]
    assert not any(f"{label} from the transmitter" in note for label in others), note
    text = diagnosis.verdict_with_regions(diagnosis.verdict(None, [], False), v)["text"]
    assert f"the correction makes {row['label']} from the transmitter" in text, text
    # Every region better after: no note, the verdict as it was.
    good = validation.validate(cap, None, corrected_poses=(cap.reference_positions + 0.05 * err,
                                                           cap.reference_quaternions_xyzw),
                               analyse_covariates=False)
    assert diagnosis.worse_regions_note(good) is None
    plain = diagnosis.verdict(None, [], False)
    assert diagnosis.verdict_with_regions(plain, good) == plain


def test_figure_6_caption_says_a_sensor_offset_is_part_of_the_arrows(tmp_path):
    # Figure 6 corrects grid points at the identity orientation: a physical term's sensor offset
    # (36.3 mm here) is part of every arrow and turns with the receiver, and the caption called it
    # all distortion. Said only when the calibration has an offset (the zero one has none to say).
    import json
    import matplotlib.pyplot as plt
    cap, _ = _capture_and_calibration_the_inverse_does_not_resolve_everywhere(tmp_path)
    doc = json.loads((tmp_path / "physical.json").read_text())
    doc["corrections"][0]["receiver_from_body"]["translation"] = [0.018, 0.006, 0.031]
    (tmp_path / "offset.json").write_text(json.dumps(doc))
    captions = {}
    for name in ("physical", "offset"):
        cal = trackcal.Calibration.load(str(tmp_path / f"{name}.json"))
        figs = report.build_figures(validation.validate(cap, cal, analyse_covariates=False))
        try:
            (captions[name],) = [c for n, c, _ in figs if n == "fig6_distortion_field.png"]
        finally:
            for _, _, f in figs:
                plt.close(f)
    assert "sensor offset" not in captions["physical"], captions["physical"]
    assert "includes the calibration's sensor offset (36.3 mm)" in captions["offset"], captions["offset"]


def _stream_path(n=3600):
    """Positions [m] along a stream's Lissajous path through the paper room's volume (as the
    simulator's stream: x +-0.6, y +-0.5, z -0.6 to -0.2 m)."""
    t = np.linspace(0.0, 30.0, n)
    return np.column_stack([0.6 * np.sin(t), 0.5 * np.sin(1.3 * t), -0.4 + 0.2 * np.sin(0.7 * t)])


def test_residual_map_side_view_label_clears_the_top_view():
    # The side view's "z [m]" label sat over the top view's frame (fixed subplot spacing, with the
    # colour bar taken from both views): 8 px into it at the report's 110 dpi on the paper stream.
    import matplotlib.pyplot as plt
    rng = np.random.default_rng(6)
    fig = figures.residual_map(_stream_path(), rng.uniform(0, 10, 3600))
    try:
        fig.canvas.draw()
        renderer = fig.canvas.get_renderer()
        top, side = fig.axes[0], fig.axes[1]
        label = side.yaxis.label.get_window_extent(renderer)
        assert label.x0 >= top.get_window_extent(renderer).x1, (label, top.get_window_extent(renderer))
        # Nor over the top view's tick labels (its tight box holds them) or the side view's own.
        assert label.x0 >= top.get_tightbbox(renderer).x1
        ticks = [t.get_window_extent(renderer) for t in side.get_yticklabels() if t.get_text()]
        assert all(label.x1 <= t.x0 for t in ticks)
    finally:
        plt.close(fig)


def test_residual_map_legend_of_values_missing_has_a_fixed_place_under_the_views():
    # The legend of the stations without a value sat at loc "best" in each view: matplotlib counted
    # every point under each candidate place (slow on a stream) and moved it wherever that count was
    # lowest, over some of the dots. One legend now, in a row under both views.
    import matplotlib.pyplot as plt
    rng = np.random.default_rng(7)
    values = rng.uniform(0, 10, 3600)
    values[:40] = np.nan
    fig = figures.residual_map(_stream_path(), values)
    try:
        fig.canvas.draw()
        assert all(ax.get_legend() is None for ax in fig.axes)
        (legend,) = fig.legends
        assert legend._loc != 0  # not "best"
        assert [t.get_text() for t in legend.get_texts()] == ["no value (40)"]
        box = legend.get_window_extent()
        assert box.y0 >= 0 and all(box.y1 <= ax.get_window_extent().y0 for ax in fig.axes[:2])
    finally:
        plt.close(fig)


def test_stream_report_counts_samples_and_moments_not_stations(stream_validation, written_report, tmp_path):
    # A stream's samples were "stations" all over the page: the table's heading, the outside line,
    # the worst table's id column, the notes, figure 7's title and the captions, under a worst list
    # headed "moments". One noun (Validation.points) for every one of them.
    import matplotlib.pyplot as plt
    from trackcal import diagnosis
    v = stream_validation
    notes = diagnosis.validation_notes(v)
    assert notes  # the paper stream's nearest band is made worse (a note that counts its samples)
    page = report.write_report(v, tmp_path / "out", notes=notes).read_text()
    text = re.sub(r"<[^>]+>", " ", page.split("<script>")[0])
    assert "station" not in text.lower(), [m.group(0) for m in re.finditer(r".{60}station.{20}", text, re.I)]
    n = len(v.capture)
    assert f"all ({n} samples)" in text and f"Samples outside the calibrated volume: {int(v.extrapolated.sum())} of {n}" in text
    assert "<th>sample</th>" in page and "samples:" in " ".join(notes)
    assert "Crossed: samples outside the calibrated volume" in text and "error per sample" in text
    figs = report.build_figures(v)
    try:
        (fig7,) = [f for name, _, f in figs if name == "fig7_orientation_vectors_slice.png"]
        assert " samples" in fig7.axes[0].get_title() and "station" not in fig7.axes[0].get_title()
    finally:
        for _, _, f in figs:
            plt.close(f)
    # A capture of stations keeps its noun.
    station_page = written_report.read_text()
    assert re.search(r"<h3>calib \(\d+ stations\)</h3>", station_page) and "<th>station</th>" in station_page
    assert "Stations outside the calibrated volume" in station_page and "error per station" in station_page
    assert v.points == "samples" and v.point == "sample" and v.worst_points == "moments"


def test_report_names_the_receiver_it_is_of_and_a_calibration_fitted_for_another(tmp_path, capsys):
    """A colleague reads the page, not the terminal: the sensor the report is of, and a
    calibration fitted for another receiver (validate's warning), are on the page. Before, two
    reports of a two-receiver capture (--sensor 1, --sensor 2) had the same header, and the other
    receiver's calibration was a Python warning with a source line on stderr alone."""
    from trackcal import cli
    from understand_support import two_receivers, write_poses
    mixed, _ = two_receivers(simulate(tmp_path / "capture", seed=37))
    both = write_poses(tmp_path / "both.csv", mixed)
    cal = validation.fit_polynomial(mixed.subset((mixed.sensor == 1) & (mixed.set == "calib")), degree=2)
    cal.sensor = 1
    cal_path = tmp_path / "cal1.json"
    cal.save(cal_path)
    common = [str(both), "-c", str(cal_path), "--no-covariates"]
    assert cli.main(["report", *common, "--sensor", "1", "-o", str(tmp_path / "own")]) == 0
    own = (tmp_path / "own" / "report.html").read_text()
    assert "(sensor 1)" in own and "fitted for sensor 1" in own
    assert "fitted for sensor 1 (receiver 1)" not in own  # its own receiver: no note
    capsys.readouterr()
    assert cli.main(["report", *common, "--sensor", "2", "-o", str(tmp_path / "other")]) == 0
    printed = capsys.readouterr()
    other = (tmp_path / "other" / "report.html").read_text()
    assert "(sensor 2)" in other
    note = "stations of sensor 2, but the calibration was fitted for sensor 1"
    assert re.search(r"<p><b>Note:</b> [^<]*" + note, other), other[:3000]
    # A note on the terminal, as the others: no "UserWarning" and no source line.
    assert f"note: {both}: {note}" in printed.out, printed.out
    assert "UserWarning" not in printed.err and "v = validate(" not in printed.err, printed.err


def test_report_of_a_model_fitted_to_a_capture_without_validation_set_says_the_errors_after_are_in_sample(
        tmp_path):
    # --model without -c on calibration stations alone: Table 1's "corrected" and figures 4 and 5
    # are the fit's own stations (a degree-6 polynomial: 0.64 mm in-sample, 0.85 mm held out on a
    # paper capture); the page said nothing of it.
    from trackcal import cli
    from understand_support import write_poses
    cap = captures.load_poses(simulate(tmp_path / "capture", seed=38))
    calib = write_poses(tmp_path / "calib.csv", cap.select_set("calib"))
    model = tmp_path / "poly.yaml"
    model.write_text("terms:\n  - type: polynomial\n    degree: 3\n")
    assert cli.main(["report", str(calib), "--model", str(model), "--effects", "sensor_offset", "--folds", "2",
                     "--no-covariates", "-o", str(tmp_path / "out")]) == 0
    page = (tmp_path / "out" / "report.html").read_text()
    assert re.search(r"<p><b>Note:</b> the model was fitted to these stations and the capture has no "
                     r"validation set: the errors after [^<]* are in-sample", page), page[:3000]
    assert "the cross-validation table" in page.split("are in-sample", 1)[1].split("</p>", 1)[0]
    # With a validation set the tables and figures tell the sets apart: no such note.
    assert cli.main(["report", str(tmp_path / "capture"), "--model", str(model), "--effects", "sensor_offset", "--folds", "2",
                     "--no-covariates", "-o", str(tmp_path / "both")]) == 0
    assert "are in-sample" not in (tmp_path / "both" / "report.html").read_text()
