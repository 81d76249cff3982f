"""Figures of a validation (matplotlib, Agg backend, no display needed). Each function returns a
matplotlib Figure; ``save_png`` writes it atomically.

- ``error_vs_distance``: error magnitude against distance from the transmitter, before and after
  (the paper's figures 4 and 5 for position and orientation).
- ``orientation_vectors_slice``: orientation error vectors of the stations in a z-slab (figure 7).
- ``distortion_field``: the fitted position correction on a z-slice as arrows over its magnitude
  (figure 6), computed from a calibration.
- ``residual_map``: stations coloured by their residual, seen from above and from the side.
- ``covariate_bars``: share of the residual variance each covariate explains.
- ``candidate_bars``: held-out error of the model alone and with each candidate effect.
- ``history_plot``: error after each fit of a work folder.
"""

from __future__ import annotations

import io
import pathlib
from typing import List, Optional, Sequence

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402


# The PNG text chunk every figure carries ("Software" keyword), by which an existing file is known
# to be an earlier trackcal figure that may be replaced.
PNG_SOFTWARE = "trackcal"


def is_trackcal_png(path) -> bool:
    """Whether ``path`` is a PNG that trackcal wrote (its Software text chunk names trackcal)."""
    try:
        with open(path, "rb") as f:
            head = f.read(1 << 16)
    except OSError:
        return False
    return head.startswith(b"\x89PNG\r\n\x1a\n") and b"tEXtSoftware\x00" + PNG_SOFTWARE.encode() in head


def save_png(fig, path, dpi: int = 110, inputs: Sequence = ()) -> pathlib.Path:
    """Writes fig as PNG atomically (temporary file in the same folder, then rename). Replaces only
    an earlier trackcal figure (``is_trackcal_png``): refuses any other existing file (a capture, a
    history, a user's picture) and any of ``inputs``, as the report does."""
    path = pathlib.Path(path)
    for p in inputs:
        if p is not None and pathlib.Path(p).resolve() == path.resolve():
            raise ValueError(f"{path}: refusing to overwrite an input")
    if path.is_dir():
        raise ValueError(f"{path}: is a folder; give the PNG file to write")
    if not path.parent.is_dir():  # else the error would name the temporary file
        raise ValueError(f"{path}: {path.parent} is not an existing folder")
    if path.suffix.lower() != ".png" or (path.exists() and not is_trackcal_png(path)):
        # Never replaced, even if it appears while the figure is drawn.
        from trackcal._files import write_new
        return write_new(path, png_bytes(fig, dpi),
                         "exists and is not a figure trackcal wrote; a figure replaces only an earlier "
                         "trackcal figure (give another file name, or remove the file)")
    from trackcal._files import replace_atomically
    return replace_atomically(path, png_bytes(fig, dpi))


def png_bytes(fig, dpi: int = 110) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi, metadata={"Software": PNG_SOFTWARE})
    return buf.getvalue()


# Errors before and after whose medians are this many times apart go on a logarithmic axis (as the
# history plot's): on a linear one the smaller lie within a pixel of zero.
_LOG_AXIS_FACTOR = 20.0


def _far_apart(before, after) -> bool:
    """Whether the median error before is more than _LOG_AXIS_FACTOR times the one after (finite
    positive values; those are the ones a log axis shows)."""
    b, a = np.asarray(before, dtype=float), np.asarray(after, dtype=float)
    b, a = b[np.isfinite(b) & (b > 0)], a[np.isfinite(a) & (a > 0)]
    return bool(len(a) and len(b) and np.median(b) > _LOG_AXIS_FACTOR * np.median(a))


def _binned(x, y, n=12):
    if len(x) < 2:
        return np.array([]), np.array([])
    edges = np.linspace(x.min(), x.max(), n + 1)
    ids = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, n - 1)
    cnt = np.bincount(ids, minlength=n)
    mean = np.bincount(ids, weights=y, minlength=n) / np.maximum(cnt, 1)
    centre = 0.5 * (edges[:-1] + edges[1:])
    return centre[cnt > 0], mean[cnt > 0]


def error_vs_distance(distance, before, after=None, *, quantity: str = "position", unit: str = "mm",
                      title: Optional[str] = None, held_out=None, outside=None):
    """Figures 4 (position) and 5 (orientation): magnitude against distance, with binned means.

    ``held_out`` (a boolean mask, optional) marks the validation set, which a fit on this capture
    does not see: its errors after are the ones that tell, as in the paper's Table 1 (the
    calibration set's are in-sample). When both sets are present, the calibration set is drawn
    hollow after the correction and the binned mean after is of the validation set only.
    ``outside`` (a boolean mask, optional) marks stations outside the calibrated volume, crossed
    after the correction: there the correction is extrapolated."""
    distance = np.asarray(distance, dtype=float)
    # The legend in rows of its own under the axes (constrained layout makes room), so it hides no
    # point. Inside at loc "best", matplotlib counted every point under each candidate place: 4 s a
    # figure of a 10-minute stream (72000 samples), a third of the report's figure time.
    fig, ax = plt.subplots(figsize=(6.4, 4.8), layout="constrained")
    ax.scatter(distance, before, s=8, alpha=0.45, color="tab:red", label="before")
    xb, yb = _binned(distance, before)
    ax.plot(xb, yb, color="darkred", lw=2, label="before (binned mean)")
    if after is not None:
        after = np.asarray(after, dtype=float)
        split = held_out is not None and 0 < int(np.sum(held_out)) < len(after)
        if split:
            held_out = np.asarray(held_out, dtype=bool)
            ax.scatter(distance[~held_out], after[~held_out], s=8, alpha=0.45, facecolors="none",
                       edgecolors="tab:blue", linewidths=0.6, label="after, calib set")
            ax.scatter(distance[held_out], after[held_out], s=8, alpha=0.6, color="tab:blue",
                       label="after, valid set")
            xa, ya = _binned(distance[held_out], after[held_out])
            ax.plot(xa, ya, color="navy", lw=2, label="after, valid set (binned mean)")
        else:
            ax.scatter(distance, after, s=8, alpha=0.45, color="tab:blue", label="after")
            xa, ya = _binned(distance, after)
            ax.plot(xa, ya, color="navy", lw=2, label="after (binned mean)")
        if outside is not None and np.any(outside):
            # Small light-grey crosses under the after points (zorder below the scatters' 1): on a
            # stream, 22741 black crosses (s=16) were drawn over the after points and hid them; a
            # cross still shows around the point it marks.
            outside = np.asarray(outside, dtype=bool)
            ax.scatter(distance[outside], after[outside], marker="x", s=8, color="0.45", alpha=0.5,
                       linewidths=0.5, zorder=0.9,
                       label=f"after, outside the calibrated volume ({int(outside.sum())})")
    ax.set_xlabel("distance from transmitter [m]")
    ax.set_ylabel(f"{quantity} error [{unit}]")
    if after is not None and _far_apart(before, after[held_out] if split else after):
        # A correction to near the noise (32 mm before, 0.07 mm after): on a linear axis every
        # after point lay on the zero line, and the figure said nothing of the error after it.
        ax.set_yscale("log")
        ax.set_ylabel(f"{quantity} error [{unit}], log scale")
    ax.set_title(title or f"{quantity.capitalize()} error vs distance")
    ax.grid(alpha=0.3)
    fig.legend(fontsize=8, loc="outside lower center", ncol=3)
    return fig


def _slab(positions, z: Optional[float], thickness: Optional[float]):
    zs = positions[:, 2]
    if z is None:
        # Through the station height nearest the median, not the median itself: of a grid with an
        # even number of layers the median lies midway between two, and the slab held no station.
        finite = zs[np.isfinite(zs)]
        z = float(finite[np.argmin(np.abs(finite - np.median(finite)))]) if len(finite) else 0.0
    if thickness is None:
        thickness = max(0.1, 0.25 * float(np.ptp(zs))) if len(zs) else 0.1
    return z, thickness, np.abs(zs - z) <= 0.5 * thickness


def _spread(p: np.ndarray, count: int) -> np.ndarray:
    """Indices of at most about ``count`` of the points ``p`` (N, 2), one per cell of a square grid
    over their extent: a stream's thousands of samples drawn as arrows are one smear."""
    if len(p) <= count:
        return np.arange(len(p))
    lo, span = p.min(axis=0), np.ptp(p, axis=0)
    cell = max(float(np.sqrt(span[0] * span[1] / count)), float(span.max()) / count, 1e-9)
    while True:
        keys = np.floor((p - lo) / cell).astype(np.int64)
        _, first = np.unique(keys[:, 0] * (1 << 31) + keys[:, 1], return_index=True)
        if len(first) <= count:
            return np.sort(first)
        cell *= 1.25


def orientation_vectors_slice(positions, orientation_vectors, *, z: Optional[float] = None,
                              thickness: Optional[float] = None, after_vectors=None, max_arrows: int = 200,
                              points: str = "stations"):
    """Figure 7: the x, y components of the orientation error vectors (vector part of q_e, shown as
    twice it, i.e. the small-angle rotation vector in degrees) of stations in a z-slab. Of more
    than ``max_arrows`` stations (a stream capture), one per cell of a grid gets its arrows.
    ``points``: what the positions are, for the title ("stations", or a stream's "samples")."""
    z, thickness, sel = _slab(positions, z, thickness)
    fig, ax = plt.subplots(figsize=(6.4, 5.4))
    deg = 2.0 * 180.0 / np.pi
    p = positions[sel]
    ax.scatter(p[:, 0], p[:, 1], s=6, color="gray")
    in_slab = len(p)
    sel = np.flatnonzero(sel)[_spread(p[:, :2], max_arrows)]
    p = positions[sel]
    v = orientation_vectors[sel] * deg
    if len(p):
        # One scale for before and after (so arrow lengths compare): the largest vector, before or
        # after, is drawn 0.1 m long, with a key arrow giving the scale in degrees. Scaled by the
        # before-vectors alone, a calibration that makes things worse drew its after-arrows metres
        # long, across the whole frame (measured: 0.04 deg before, 8 deg after: 20 m arrows).
        a = after_vectors[sel] * deg if after_vectors is not None else np.zeros((0, 3))
        lengths = np.linalg.norm(np.concatenate([v[:, :2], a[:, :2]]), axis=1)
        lengths = lengths[np.isfinite(lengths)]  # a NaN vector made the scale (and every arrow) NaN
        vmax = float(lengths.max()) if len(lengths) and lengths.max() > 0 else 1.0
        scale = vmax / 0.1
        kw = dict(angles="xy", scale_units="xy", scale=scale, width=0.004)
        q = ax.quiver(p[:, 0], p[:, 1], v[:, 0], v[:, 1], color="tab:red", label="before", **kw)
        if after_vectors is not None:
            ax.quiver(p[:, 0], p[:, 1], a[:, 0], a[:, 1], color="tab:blue", label="after", **kw)
        # The limits hold every arrow's tip, not only the stations (autoscaling sees a quiver's
        # tails alone): an arrow at the slab's edge pointing out was cut at the axes (measured: tips
        # 0.046 m past the y limits of a 1 m slab).
        tips = np.concatenate([p[:, :2] + v[:, :2] / scale, p[:, :2] + a[:, :2] / scale if len(a) else p[:, :2]])
        ax.update_datalim(tips[np.all(np.isfinite(tips), axis=1)])
        ax.autoscale_view()
        key = float(f"{vmax / 2:.1g}")
        ax.quiverkey(q, 0.02, -0.1, key, f"{key:g} deg", labelpos="E", coordinates="axes")
        # Under the axes, in line with the key arrow: inside (lower right) it hid the arrows there.
        ax.legend(fontsize=8, loc="upper right", bbox_to_anchor=(1.0, -0.06), ncol=2)
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_aspect("equal", adjustable="datalim")
    shown = f", {len(sel)} with arrows" if len(sel) < in_slab else ""
    ax.set_title(f"Orientation error vectors, z = {z:.2f} ± {thickness / 2:.2f} m ({in_slab} {points}{shown})",
                 fontsize=10 if shown else None)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    return fig


def distortion_field(calibration, *, z: Optional[float] = None, n: int = 25, streamlines: bool = True):
    """Figure 6: the calibration's position correction (corrected - reported) on a z-slice of its
    volume, arrows (or streamlines) of the x, y components over a map of the full magnitude [mm].
    The figure's ``unresolved_points`` is (points the model inverse does not resolve, grid points):
    those are left blank over a hatched background."""
    lo, hi = np.asarray(calibration.volume_min), np.asarray(calibration.volume_max)
    if z is None:
        z = 0.5 * (lo[2] + hi[2])
    xs, ys = np.linspace(lo[0], hi[0], n), np.linspace(lo[1], hi[1], n)
    gx, gy = np.meshgrid(xs, ys)
    pts = np.column_stack([gx.ravel(), gy.ravel(), np.full(gx.size, z)])
    quats = np.tile([0.0, 0.0, 0.0, 1.0], (len(pts), 1))
    cp, _, _, status = calibration.correct(pts, quats, return_status=True)
    d = (cp - pts) * 1e3
    # Where a physical term's model inverse does not resolve the pose (status not 0: ambiguous or
    # not converged) the correction is not the field's: it was drawn as a dark band of ~0 mm with
    # streamlines through it, as if the volume there were undistorted. Left blank (hatched) instead.
    unresolved = np.asarray(status) != 0
    d[unresolved] = np.nan
    mag = np.linalg.norm(d, axis=1).reshape(gx.shape)
    fig, ax = plt.subplots(figsize=(6.4, 5.4))
    if unresolved.any():
        ax.add_patch(plt.Rectangle((0, 0), 1, 1, transform=ax.transAxes, facecolor="none",
                                   edgecolor="lightgray", hatch="//", zorder=0))
    im = ax.pcolormesh(gx, gy, np.ma.masked_invalid(mag), shading="auto", cmap="viridis")
    fig.colorbar(im, ax=ax, label="|correction| [mm]")
    u, v = d[:, 0].reshape(gx.shape), d[:, 1].reshape(gx.shape)
    if streamlines and np.nanmax(np.hypot(u, v), initial=0.0) > 0:
        ax.streamplot(xs, ys, u, v, color="white", density=1.0, linewidth=0.8)
    else:
        ax.quiver(gx, gy, u, v, color="white")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_aspect("equal", adjustable="box")
    note = (f"\nhatched: {int(unresolved.sum())} of {unresolved.size} points the model inverse does not resolve"
            if unresolved.any() else "")
    ax.set_title(f"Fitted distortion (position correction), z = {z:.2f} m{note}", fontsize=10 if note else None)
    fig.tight_layout()
    fig.unresolved_points = (int(unresolved.sum()), int(unresolved.size))  # for the report's caption
    return fig


def _edgeless_area(area: float) -> float:
    """Area [pt^2] of an edgeless scatter marker as large as one of ``area`` with matplotlib's
    default edge (rcParams patch.linewidth, 1 pt, in the face's colour): diameter sqrt(area) + edge."""
    return (np.sqrt(area) + float(matplotlib.rcParams["patch.linewidth"])) ** 2


def residual_map(positions, values, *, label: str = "position error [mm]", title: str = "Residual map"):
    """Stations coloured by a residual: top view (x, y) and side view (x, z)."""
    # Constrained layout: with the colorbar taken from both axes, the fixed subplot spacing put the
    # side view's "z [m]" label over the top view's frame (8 px into it at 110 dpi on the paper stream).
    fig, axes = plt.subplots(1, 2, figsize=(10, 4.4), layout="constrained")
    values = np.asarray(values, dtype=float)
    # The colour scale from the finite values: one NaN made the 98th percentile NaN and every
    # station one colour. Stations without a value are drawn as grey crosses.
    finite = np.isfinite(values)
    vmax = float(np.percentile(values[finite], 98)) if finite.any() else 1.0
    for ax, (i, j, names) in zip(axes, [(0, 1, ("x", "y")), (0, 2, ("x", "z"))]):
        # Markers without an edge, as large as the default's face plus its edge of the face's colour:
        # the same dots, but Agg strokes each colour-mapped marker's edge separately, and of a
        # 10-minute stream (72000 samples) that took 2.2 s of the figure's 2.5 s.
        sc = ax.scatter(positions[finite, i], positions[finite, j], c=values[finite], s=_edgeless_area(14.0),
                        linewidths=0, cmap="magma_r", vmin=0, vmax=max(vmax, 1e-12))
        if not finite.all():
            ax.scatter(positions[~finite, i], positions[~finite, j], marker="x", s=14, color="gray",
                       label=f"no value ({int((~finite).sum())})")
        ax.set_xlabel(f"{names[0]} [m]")
        ax.set_ylabel(f"{names[1]} [m]")
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(alpha=0.3)
    fig.colorbar(sc, ax=axes, label=label)
    if not finite.all():
        # One legend for both views, in a row under them: at loc "best" inside each view matplotlib
        # counted every point under each candidate place (slow on a stream) and put it wherever
        # that count was lowest, over some of the dots.
        fig.legend(*axes[0].get_legend_handles_labels(), fontsize=8, loc="outside lower center")
    fig.suptitle(title)
    return fig


def covariate_bars(effects, *, target: str = "position_mm", top: int = 15):
    """Cross-validated R^2 of each covariate for one residual target: significant ones orange, those
    diagnose marks explained by another covariate family (``confounded_with``: time that the
    positions explain) in a paler hatched colour, the rest grey; a legend says which is which."""
    from matplotlib.patches import Patch
    rows = [e for e in effects if e.target == target][:top]
    # The legend in a row of its own under the axes (constrained layout makes room): inside, it hid
    # the ends of bars of equal length.
    fig, ax = plt.subplots(figsize=(6.4, 0.3 * max(len(rows), 3) + 1.5), layout="constrained")
    names = [e.covariate for e in rows][::-1]
    vals = [max(e.r2, 0.0) for e in rows][::-1]
    # An explained-away finding was as orange as one that stands on its own, where diagnose and the
    # table say "(explained by position)".
    kinds = {"finding": dict(color="tab:orange", label="significant"),
             "explained": dict(color="navajowhite", hatch="//", edgecolor="tab:orange",
                               label="significant, explained by {}"),
             "none": dict(color="lightgray", label="not significant")}

    def kind(e):
        return "none" if not e.significant else "explained" if e.confounded_with else "finding"

    bars = ax.barh(names, vals, color=[kinds[kind(e)]["color"] for e in rows][::-1])
    for bar, e in zip(bars, rows[::-1]):
        if kind(e) == "explained":
            bar.set_hatch(kinds["explained"]["hatch"])
            bar.set_edgecolor(kinds["explained"]["edgecolor"])
    handles = []
    for k in ("finding", "explained", "none"):
        of_kind = [e for e in rows if kind(e) == k]
        if not of_kind:
            continue
        style = {a: b for a, b in kinds[k].items() if a != "label"}
        others = sorted({str(e.confounded_with) for e in of_kind})
        handles.append(Patch(facecolor=style.pop("color"), **style,
                             label=kinds[k]["label"].format(" or ".join(others))))
    if handles:
        fig.legend(handles=handles, fontsize=8, loc="outside lower center", ncol=len(handles))
    ax.set_xlabel("share of residual variance explained (cross-validated R²)")
    ax.set_title(f"Residual structure: {target}")
    ax.grid(alpha=0.3, axis="x")
    return fig


# Beyond this many fits the history plot's ticks are fit numbers: rotated labels overlap (measured:
# 200 fits of 30-character labels made a band taller than the axes on the 6.4 inch figure).
_MAX_LABELLED_FITS = 20


def history_plot(entries: Sequence[dict]):
    """Error after each recorded fit (mean position mm and orientation deg of the held-out or
    validation set when recorded, else the calibration set). When the errors span more than a
    factor of 20 (a loop that starts at the uncorrected error and ends near the noise floor) the
    axes are logarithmic, so the last changes stay visible. Rows on other capture files or another
    set are not joined to the previous one."""
    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    x = np.arange(1, len(entries) + 1)
    from trackcal.history import comparable_key, comparison_break, headline_scores, headline_set
    pos = [headline_scores(e)[0] for e in entries]
    ori = [headline_scores(e)[1] for e in entries]
    # A line joins only rows the table compares (same capture files, same headline set): a step to
    # other data is not a step of the loop.
    keys = [comparable_key(e) for e in entries]
    breaks = {i: comparison_break(keys[i], keys[i - 1]) for i in range(1, len(entries))}
    starts = [0] + [i for i, why in breaks.items() if why]
    # Each break is a divider between the two rows, named as the table names it: the broken line
    # alone was read as a change of the model (29.0 mm with a LUT on one capture, 4.7 mm with a
    # sensor offset on another, drawn side by side).
    for i in starts[1:]:
        ax.vlines(i + 0.5, 0, 1, transform=ax.get_xaxis_transform(), colors="0.5", linestyles=":", lw=1)
        ax.text(i + 0.5, 0.98, breaks[i], transform=ax.get_xaxis_transform(), rotation=90, ha="right",
                va="top", fontsize=7, color="0.35")
    runs = list(zip(starts, starts[1:] + [len(entries)]))
    many = len(entries) > _MAX_LABELLED_FITS  # smaller markers: 200 hollow squares hid the lines
    for k, (a, b) in enumerate(runs):
        ax.plot(x[a:b], pos[a:b], "o-", color="tab:blue", markersize=3 if many else 6,
                label="position mean [mm]" if k == 0 else None)
    ax.set_ylabel("position error mean [mm]", color="tab:blue")
    ax2 = ax.twinx()
    for k, (a, b) in enumerate(runs):
        # Hollow and larger: where the two axes put a point at the same height (a single fit is
        # in the middle of both) the position marker stays visible inside the square.
        ax2.plot(x[a:b], ori[a:b], "s--", color="tab:red", markerfacecolor="none",
                 markersize=4 if many else 9, label="orientation mean [deg]" if k == 0 else None)
    ax2.set_ylabel("orientation error mean [deg]", color="tab:red")
    for axis, values in ((ax, pos), (ax2, ori)):
        v = np.asarray([y for y in values if np.isfinite(y) and y > 0])
        if len(v) >= 2 and v.max() > 20 * v.min():
            axis.set_yscale("log")
    if len(entries) <= _MAX_LABELLED_FITS:
        ax.set_xticks(x)
        ax.set_xticklabels([str(e.get("label") or i) for i, e in zip(x, entries)], rotation=30, ha="right",
                           fontsize=8)
        ax.set_xlabel("fit (label)")  # the ticks are the fits' labels, in recorded order
    else:
        # 200 rotated labels overlapped into a band taller than the axes: a few fit numbers instead,
        # the rows of `trackcal history`, whose table names each fit's label.
        from matplotlib.ticker import MaxNLocator
        ax.xaxis.set_major_locator(MaxNLocator(nbins=12, integer=True, min_n_ticks=2))
        ax.set_xlim(0.5, len(entries) + 0.5)
        ax.set_xlabel("fit # (the row of `trackcal history`, which gives its label)")
    sets = sorted({headline_set(e) for e in entries} - {None})
    # One legend for the two axes' lines (only the axis labels' colours told them apart), in a row
    # between the title and the axes: inside (upper right) it hid the markers of a high last fit.
    handles = ax.get_legend_handles_labels()[0] + ax2.get_legend_handles_labels()[0]
    if handles:
        ax.legend(handles=handles, loc="lower center", bbox_to_anchor=(0.5, 1.0), ncol=2, fontsize=8,
                  frameon=False)
    ax.set_title("Error after each change" + (f" ({', '.join(sets)})" if sets else ""), pad=20 if handles else 6)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    return fig


def candidate_bars(doc: dict, *, top: int = 12):
    """Held-out mean position error of the model alone and with each candidate effect (contract B
    document of trackcal.diagnose_candidates); significant candidates in orange. Bars carry the
    labels of the candidate table ("dipole for polynomial" for a replacement), so a replacement
    and the addition of the same effect get one bar each."""
    from trackcal.diagnosis import candidate_rows
    cands = list(doc.get("candidates", []))[:top]
    base = doc.get("base", {}).get("cv_position_mm_mean")
    names = ["model alone"] + [str(r["effect"]) for r in candidate_rows(doc)[:top]]
    vals = [base] + [c.get("cv_position_mm_mean") for c in cands]
    vals = [float("nan") if x is None else float(x) for x in vals]
    colors = ["tab:gray"] + ["tab:orange" if c.get("significant") else "lightsteelblue" for c in cands]
    fig, ax = plt.subplots(figsize=(6.4, 0.32 * len(names) + 1.4))
    ys = np.arange(len(names))[::-1]  # one position per bar even if two labels were equal
    ax.barh(ys, vals, color=colors)
    ax.set_yticks(ys)
    ax.set_yticklabels(names)
    if base is not None:
        ax.axvline(float(base), color="k", lw=1, ls="--")
    ax.set_xlabel("held-out mean position error [mm]")
    # A pale bar can have a tiny p-value (a located source BIC does not prefer, a stand-in): the
    # table gives the reason, which the title points to.
    ax.set_title("Candidate effects\n(orange = significant; the table says why a pale bar is not)",
                 fontsize=10)
    ax.grid(alpha=0.3, axis="x")
    fig.tight_layout()
    return fig
