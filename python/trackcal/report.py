"""Self-contained HTML report of a validation: every figure embedded as a base64 PNG (no external
resource, opens offline) and also written as a PNG file next to it. Files are written atomically and
the report never replaces one of its inputs (a capture, a calibration).

The page carries a small script that, once every image has loaded, writes
``data-figures-ok="<count>"`` (or ``data-figures-broken="<name> (<why>)|..."``: not decoded, not
fully decoded, blank) on <body>: headless browsers and tests read it.
"""

from __future__ import annotations

import base64
import datetime
import html
import json
import pathlib
from typing import Callable, List, Optional, Sequence

import numpy as np

from trackcal import figures as F
from trackcal._files import replace_atomically
from trackcal._format import fixed
from trackcal import validation


# Every figure file a report may write (build_figures). A report written over an earlier one removes
# the earlier one's figures it does not draw itself (a fig6 of a calibration the new report has not,
# a history.png of a report without --workdir): else they sat next to the new page as if its own.
FIGURE_NAMES = ("fig4_position_error_vs_distance.png", "fig5_orientation_error_vs_distance.png",
                "fig7_orientation_vectors_slice.png", "fig6_distortion_field.png",
                "residual_map_position.png", "residual_map_orientation.png",
                "covariates_position_mm.png", "covariates_orientation_deg.png", "candidates.png",
                "history.png")

# In every report's <head>: an existing report.html is replaced only when it carries this (an earlier
# trackcal report), never a page of the user's that happens to sit in the output folder.
GENERATOR_META = "<meta name='generator' content='trackcal report'>"


def _check_replaceable(path: pathlib.Path, inputs: Sequence[pathlib.Path], own_folder: bool = False) -> None:
    """ValueError unless ``path`` is new or an earlier report's page or figure, and not an input.
    A figure is an earlier report's when trackcal wrote it, or (``own_folder``) when the folder
    holds an earlier trackcal report (figures of reports older than the PNG tag)."""
    target = path.resolve()
    for p in inputs:
        if p is not None and pathlib.Path(p).resolve() == target:
            raise ValueError(f"{path}: refusing to overwrite an input of the report")
    if path.is_dir():
        raise ValueError(f"{path}: is a folder; the report writes a file of that name")
    if path.suffix.lower() == ".html" and path.exists():
        with open(path, "rb") as f:
            head = f.read(4096)
        # Reports written before the tag carry the report's own style sheet at the top.
        if GENERATOR_META.encode() not in head and f"<style>{STYLE}</style>".encode() not in head:
            raise ValueError(f"{path}: exists and is not a trackcal report; refusing to replace it "
                             "(give another output folder, or remove the file)")
    elif path.suffix.lower() != ".html" and path.exists() and (
            path.suffix.lower() != ".png" or not (own_folder or F.is_trackcal_png(path))):
        raise ValueError(f"{path}: exists and is not a figure of a trackcal report; refusing to replace it "
                         "(give another output folder, or remove the file)")


def _atomic_write(path: pathlib.Path, data: bytes, inputs: Sequence[pathlib.Path],
                  own_folder: bool = False) -> None:
    _check_replaceable(path, inputs, own_folder)
    replace_atomically(path, data)


def _table(rows: List[dict], columns: Optional[List[str]] = None, fmt: str = "{:.3f}") -> str:
    if not rows:
        return "<p><em>none</em></p>"
    columns = columns or list(rows[0].keys())
    out = ["<table><tr>" + "".join(f"<th>{html.escape(c)}</th>" for c in columns) + "</tr>"]
    for r in rows:
        cells = []
        for c in columns:
            v = r.get(c, "")
            if v is None:  # not computed (e.g. a candidate that was not cross-validated)
                v = ""
            elif isinstance(v, (float, np.floating)):
                v = fixed(v, fmt)
            cells.append(f"<td>{html.escape(str(v))}</td>")
        out.append("<tr>" + "".join(cells) + "</tr>")
    out.append("</table>")
    return "\n".join(out)


def _number(value, fmt: str = "{:.3f}") -> str:
    """A number as text; 'n/a' for None (null in the ranking document: a mean the engine could
    not compute) or NaN."""
    if isinstance(value, (int, float, np.floating)) and not isinstance(value, bool) and np.isfinite(value):
        return fixed(value, fmt)
    return "n/a"


def _table1_html(t, points: str = "stations") -> str:
    """One Table 1 with its heading: the set, how many ``points`` (stations or samples) it holds."""
    rows = []
    for title, b, a in (("Position error (mm)", t.before_position_mm, t.after_position_mm),
                        ("Orientation error (deg)", t.before_orientation_deg, t.after_orientation_deg)):
        for stat, name in (("mean", "Mean"), ("std", "Standard dev."), ("max", "Maximum"), ("p95", "95th percentile")):
            row = {"quantity": title, "statistic": name, "original": b[stat]}
            if a is not None:
                row["corrected"] = a[stat]
                row["improvement %"] = 100.0 * (b[stat] - a[stat]) / b[stat] if b[stat] > 0 else 0.0
            rows.append(row)
    n_flips = getattr(t, "hemisphere_flips_left_out", 0)
    flips = f", {n_flips} more left out: reported in the other hemisphere than their reference" if n_flips else ""
    return (f"<h3>{html.escape(t.set_name)} ({t.before_position_mm['count']} {points}{flips})</h3>"
            + _table(rows))


STYLE = """
body{font-family:sans-serif;max-width:1100px;margin:1em auto;color:#222}
table{border-collapse:collapse;margin:.5em 0 1em 0;font-size:90%}
td,th{border:1px solid #bbb;padding:2px 6px;text-align:right}th{background:#eee}
figure{display:inline-block;margin:.5em;vertical-align:top}figcaption{font-size:85%;max-width:640px}
img{max-width:100%;border:1px solid #ddd}.sig{color:#b35900;font-weight:bold}
"""

# Once the page has loaded, each image is drawn into a canvas and read back: a PNG cut short (a write
# or a copy cut short) keeps its size and decodes as far as it goes, so the browser marked it
# complete with its natural width and the check counted it as rendered; its undecoded rows are
# transparent, where every figure is opaque. A figure of one colour has nothing drawn. A data: image
# does not taint the canvas, so its pixels can be read back.
CHECK_SCRIPT = """
(function(){function drawn(img){var c=document.createElement('canvas');
c.width=img.naturalWidth;c.height=img.naturalHeight;var g=c.getContext('2d');g.drawImage(img,0,0);
var d=g.getImageData(0,0,c.width,c.height).data,same=true;
for(var i=0;i<d.length;i+=4){if(d[i+3]!==255){return 'not fully decoded';}
if(same&&(d[i]!==d[0]||d[i+1]!==d[1]||d[i+2]!==d[2])){same=false;}}
return same?'blank':'';}
function check(){var imgs=document.images,ok=0,bad=[];
for(var i=0;i<imgs.length;i++){var why=imgs[i].complete&&imgs[i].naturalWidth>0?drawn(imgs[i]):'not decoded';
if(why){bad.push(imgs[i].alt+' ('+why+')');}else{ok++;}}
if(bad.length){document.body.setAttribute('data-figures-broken',bad.join('|'));}
else{document.body.setAttribute('data-figures-ok',String(ok));}}
if(document.readyState==='complete'){check();}else{window.addEventListener('load',check);}})();
"""


def _sensors_text(capture) -> str:
    """" (sensor N)": the receiver whose stations the report is of. Reports of each receiver of one
    capture (--sensor 1, --sensor 2) had the same header, one page told from the other by nothing."""
    sensors = sorted(int(s) for s in np.unique(np.asarray(capture.sensor))) if len(capture) else []
    if not sensors:
        return ""
    return f" (sensor{'s' if len(sensors) > 1 else ''} {', '.join(map(str, sensors))})"


def _fitted_for_text(calibration) -> str:
    """" (fitted for sensor N)" when the calibration records its receiver (files before it do not)."""
    sensor = int(getattr(calibration, "sensor", 0) or 0) if calibration is not None else 0
    return f" (fitted for sensor {sensor})" if sensor else ""


def _sensor_offset_mm(calibration) -> float:
    """The length [mm] of the largest sensor offset (a physical term's receiver_from_body
    translation) in the calibration, 0 without one."""
    doc = json.loads(calibration.to_json())
    return max((1e3 * float(np.linalg.norm(c["receiver_from_body"]["translation"]))
                for c in doc.get("corrections", []) if c.get("receiver_from_body")), default=0.0)


def build_figures(v, history_entries: Optional[Sequence[dict]] = None,
                  candidates: Optional[dict] = None) -> List[tuple]:
    """[(file name, caption, Figure)] for a Validation."""
    import matplotlib.pyplot as plt  # noqa: F401  (figures configures Agg)
    from trackcal.validation import _sub
    # Hemisphere flips (reported at -p, 2 |p| off) are left out of the figures as of the tables.
    kept = ~v.flipped if v.flipped is not None else np.ones(len(v.capture), bool)
    data = v.capture.subset(kept)
    dist = np.linalg.norm(data.reported_positions, axis=1)
    before = _sub(v.before, kept)
    after = _sub(v.after, kept) if v.after is not None else None
    held_out = np.asarray(data.set) == "valid"
    outside = np.asarray(v.extrapolated, dtype=bool)[kept] if after is not None else None
    split = after is not None and 0 < int(held_out.sum()) < len(held_out)
    after_text = (" and after (blue; hollow: the calib set, filled: the valid set, which a fit on this "
                  "capture does not see, and whose binned mean is drawn)" if split else
                  " and after (blue)" if after is not None else "")
    points = v.points  # "samples" of a stream, "stations" else
    crossed = (f" Crossed: {points} outside the calibrated volume, where the correction is extrapolated."
               if outside is not None and outside.any() else "")
    figs = [
        ("fig4_position_error_vs_distance.png",
         f"Figure 4: position error magnitude against distance from the transmitter, before (red){after_text} "
         f"the correction, with binned means.{crossed}",
         F.error_vs_distance(dist, before.position_mm, after.position_mm if after else None,
                             quantity="position", unit="mm", held_out=held_out, outside=outside)),
        ("fig5_orientation_error_vs_distance.png",
         f"Figure 5: orientation error angle against distance from the transmitter, before (red){after_text} "
         f"the correction.{crossed}",
         F.error_vs_distance(dist, before.orientation_deg, after.orientation_deg if after else None,
                             quantity="orientation", unit="deg", held_out=held_out, outside=outside)),
        ("fig7_orientation_vectors_slice.png",
         "Figure 7: orientation error vectors (x, y components of the small-angle rotation, degrees) of "
         f"the {points} in a horizontal slab through the {v.point} height nearest the median (of "
         "more than 200, arrows at a few spread over the slab).",
         F.orientation_vectors_slice(data.reported_positions, before.orientation,
                                     after_vectors=after.orientation if after else None, points=points)),
    ]
    if v.calibration is not None:
        field = F.distortion_field(v.calibration)
        # The hatching only when there is some (a polynomial or LUT resolves every point): the caption
        # described hatched points under every figure 6, as if some part of the field were missing.
        n_unresolved, n_points = field.unresolved_points
        hatched = (f"; hatched (blank): {n_unresolved} of its {n_points} grid points, where a physical term's "
                   "model inverse does not resolve the pose" if n_unresolved else "")
        # Drawn for a receiver at the transmitter's orientation: a sensor offset (the body point a
        # physical term reports, not the coil centre) is part of every arrow there, and turns with the
        # receiver; a reader took its 36 mm for field distortion.
        offset_mm = _sensor_offset_mm(v.calibration)
        offset = (f"; drawn for a receiver at the transmitter's orientation, so it includes the "
                  f"calibration's sensor offset ({offset_mm:.1f} mm), which turns with the receiver"
                  if offset_mm >= 0.05 else "")
        figs.append(("fig6_distortion_field.png",
                     "Figure 6: the calibration's position correction on the horizontal mid-plane of its "
                     f"volume: magnitude as colour, x-y direction as streamlines{hatched}{offset}.", field))
    final = after if after is not None else before
    figs.append(("residual_map_position.png",
                 f"Residual map: remaining position error per {v.point} (top and side views).",
                 F.residual_map(data.reported_positions, final.position_mm, title="Position residuals")))
    figs.append(("residual_map_orientation.png",
                 f"Residual map: remaining orientation error per {v.point}.",
                 F.residual_map(data.reported_positions, final.orientation_deg, label="orientation error [deg]",
                                title="Orientation residuals")))
    if v.covariate_effects:
        for target in ("position_mm", "orientation_deg"):
            figs.append((f"covariates_{target}.png",
                         f"Residual structure: cross-validated share of the {target} variance each covariate "
                         "explains; orange bars pass the permutation test, pale hatched ones pass it but "
                         "another covariate family explains them (time that the positions explain), as "
                         "diagnose says.",
                         F.covariate_bars(v.covariate_effects, target=target)))
    if candidates and candidates.get("candidates"):
        figs.append(("candidates.png",
                     "Candidate effects: held-out (cross-validated) mean position error of the model alone and "
                     "with each catalog effect added; significant candidates in orange.",
                     F.candidate_bars(candidates)))
    if history_entries:
        figs.append(("history.png", "Error after each recorded fit of the work folder.",
                     F.history_plot(history_entries)))
    return figs


def write_report(v, out_dir, *, title: str = "trackcal report", inputs: Sequence = (),
                 history_entries: Optional[Sequence[dict]] = None,
                 candidates: Optional[dict] = None, verdict: Optional[dict] = None,
                 model_change: Optional[dict] = None,
                 progress: Optional[Callable[[int, int], None]] = None,
                 notes: Sequence[str] = ()) -> pathlib.Path:
    """Writes out_dir/report.html and one PNG per figure; returns the HTML path.

    ``candidates`` (optional) is the fit engine's ranking of missing effects
    (``trackcal.diagnose_candidates``), shown as the "Candidate effects" table and figure;
    ``verdict`` (``trackcal.diagnosis.verdict``) and ``model_change`` (the edit for the top
    candidate) are shown with it; ``history_entries`` gives the history table and plot."""
    from trackcal import diagnosis
    from trackcal.history import history_table
    import matplotlib.pyplot as plt
    out_dir = pathlib.Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise ValueError(f"{out_dir}: exists and is not a folder; the report writes a folder")
    input_paths = [pathlib.Path(p) for p in inputs if p is not None]
    if v.capture.path is not None:
        input_paths.append(pathlib.Path(v.capture.path))
    _check_replaceable(out_dir / "report.html", input_paths)  # before any folder or figure is made
    out_dir.mkdir(parents=True, exist_ok=True)
    figs = build_figures(v, history_entries, candidates)
    parts = [f"<!DOCTYPE html><html><head><meta charset='utf-8'>{GENERATOR_META}<title>{html.escape(title)}</title>"
             f"<style>{STYLE}</style></head><body>",
             f"<h1>{html.escape(title)}</h1>",
             f"<p>Generated {datetime.datetime.now(datetime.timezone.utc).strftime('%Y-%m-%d %H:%M UTC')}. "
             f"Capture: {html.escape(str(v.capture.path))}{_sensors_text(v.capture)}; calibration: "
             f"{html.escape(str(getattr(v.calibration, 'description', None) or ('none' if v.calibration is None else 'yes')))}"
             f"{_fitted_for_text(v.calibration)}.</p>",
             "<h2>Table 1: errors before and after</h2>"]
    from trackcal.captures import describe_origin
    origin = describe_origin(v.capture)
    if origin:  # streams paired, markers registered: say how, with the offset or the chi-square
        parts.insert(-1, f"<p>{v.points.capitalize()}: {html.escape(origin)}.</p>")
    parts += [_table1_html(t, v.points) for t in v.tables]
    outside = v.outside_line(50)
    parts.append(f"<p>{html.escape(outside[:1].upper() + outside[1:])}.</p>")
    flipped = v.flipped_stations
    if flipped:
        parts.append(f"<p>Hemisphere flips (reported in the other hemisphere than their reference, 2 |p| off "
                     f"whatever the calibration; left out of the statistics): <b>{len(flipped)}</b>: "
                     f"{html.escape(' '.join(str(i) for i in flipped[:50]))}"
                     f"{f' ... ({len(flipped) - 50} more)' if len(flipped) > 50 else ''}.</p>")
    parts.append("<h2>By distance from the transmitter</h2>" + _table(v.by_distance))
    parts.append("<h2>By region of the volume (octants)</h2>" + _table(v.by_region))
    parts.append(f"<h2>{html.escape(v.worst_heading)}</h2><p>x, y, z and distance: the reported position "
                 "in the transmitter frame [m].</p>" + _table(v.worst_rows()))
    if v.covariate_effects:
        # As diagnose lists them: a finding another covariate family explains away (time that the
        # positions explain) is marked so and goes after those that stand on their own; the table
        # called it plainly significant. p with its digits: a permutation p of 0.000167 read "0.000".
        shown = sorted((e for e in v.covariate_effects if e.significant or e.r2 > 0.01),
                       key=lambda e: (not e.significant, e.confounded_with is not None, -e.r2))
        rows = [{"covariate": e.covariate, "residual": e.target, "R² (cv)": e.r2, "p": f"{e.p_value:.3g}",
                 "significant": ("yes" + (f" (explained by {e.confounded_with})" if e.confounded_with else ""))
                 if e.significant else "",
                 **({"each label's mean error from the mean of all": diagnosis.levels_phrase(e.levels)}
                    if any(x.levels for x in v.covariate_effects) else {})} for e in shown][:40]
        parts.append("<h2>Residual structure (covariates)</h2>"
                     "<p>Share of the remaining residual variance each covariate explains (binned means, "
                     "5-fold cross-validated), with a permutation test; only significant or R² &gt; 0.01 shown."
                     + (" Stream samples: the folds are contiguous stretches of time and the null shifts "
                        "the covariate along time, since neighbouring samples share their misfit."
                        if validation.serial_samples(v.capture) else "")
                     + (f" Not tested: {html.escape(v.covariates_note)}." if v.covariates_note else "")
                     + "".join(f" {html.escape(name)} left out: {html.escape(why)}."
                               for name, why in (getattr(v, "covariates_left_out", None) or {}).items())
                     + "</p>" + _table(rows))
    if candidates is not None:
        base = candidates.get("base", {})
        parts.append("<h2>Candidate effects</h2>"
                     "<p>The model refitted with each catalog effect it lacks, ranked by held-out error "
                     f"({html.escape(str(candidates.get('folds', '')))}-fold cross-validation). The model alone: "
                     f"{_number(base.get('cv_position_mm_mean'))} mm, "
                     f"{_number(base.get('cv_orientation_deg_mean'))} deg. "
                     f"{html.escape(diagnosis.unresolved_note(candidates))}</p>"
                     + _table(diagnosis.candidate_rows(candidates)))
    if verdict is None and (candidates is not None or v.covariate_effects):
        verdict = diagnosis.verdict(candidates, v.covariate_effects, v.covariates_tested)
    for n in notes:  # what the reader must know to read the tables and the verdict
        parts.append(f"<p><b>Note:</b> {html.escape(n)}</p>")
    if verdict is not None:
        parts.append(f"<h2>Verdict</h2><p class='sig'>{html.escape(verdict['text'])}</p>")
    if model_change is not None:
        parts.append("<h3>Model-file change</h3><pre>"
                     + html.escape(model_change.get("diff") or model_change.get("yaml") or "") + "</pre>")
    if history_entries:
        parts.append("<h2>History of fits</h2><pre>" + html.escape(history_table(history_entries)) + "</pre>")
    parts.append("<h2>Figures</h2>")
    # Every figure's file is checked before any is written: a refusal leaves the folder as it was.
    own_folder = (out_dir / "report.html").exists()  # checked above: an earlier trackcal report
    try:
        for name, _, _ in figs:
            _check_replaceable(out_dir / name, input_paths, own_folder)
        for i, (name, caption, fig) in enumerate(figs):
            data = F.png_bytes(fig)
            plt.close(fig)
            _atomic_write(out_dir / name, data, input_paths, own_folder)
            b64 = base64.b64encode(data).decode("ascii")
            parts.append(f"<figure><img alt='{html.escape(name)}' src='data:image/png;base64,{b64}'>"
                         f"<figcaption>{html.escape(caption)}</figcaption></figure>")
            if progress:
                progress(i + 1, len(figs))
    finally:
        # A refused file leaves the figures drawn: close them, or a script's loop of reports keeps
        # every one in pyplot's registry (matplotlib's "more than 20 figures" warning in the tests).
        for _, _, fig in figs:
            plt.close(fig)
    parts.append(f"<script>{CHECK_SCRIPT}</script></body></html>")
    path = out_dir / "report.html"
    _atomic_write(path, "\n".join(parts).encode("utf-8"), input_paths)
    # The earlier report's figures this one did not draw, once the new page is in place: only in a
    # folder that held an earlier report, only files trackcal's PNG tag says it wrote (a user's own
    # history.png there is left, where the figure guard would let a drawn figure replace it), and
    # never an input.
    drawn = {name for name, _, _ in figs}
    for name in FIGURE_NAMES if own_folder else ():
        stale = out_dir / name
        if name in drawn or not stale.is_file() or not F.is_trackcal_png(stale):
            continue
        try:
            _check_replaceable(stale, input_paths, own_folder)
        except ValueError:
            continue
        stale.unlink()
    return path
