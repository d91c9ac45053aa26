"""Figures of residuals: vectors over the image, histogram + Q-Q, radial trend, heat maps, bars;
the figures of a tie-point match (:func:`match_figures`) and of the cotangent vs homography study
(:func:`study_figures`).

Every function returns a new :class:`matplotlib.figure.Figure` built without
:mod:`matplotlib.pyplot` (no global state, no GUI backend), so they are safe in
libraries, threads and headless runs; save them with ``fig.savefig(...)`` or pass
them to :func:`rectify.report.builder.write_report` as ``figures``.

Conventions: positions are in the pixel frame (x = column right, y = row down,
pixel centres at integers), so image axes are drawn with y increasing downwards.
Residuals are ``v = adjusted - observed`` in the table's ``units``.
"""

from __future__ import annotations

import logging
import math
import textwrap
from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np
from matplotlib.colors import Normalize
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.ticker import FuncFormatter, MaxNLocator
from numpy.typing import ArrayLike, NDArray

from rectify.errors import InvalidInputError, ShapeError
from rectify.geometry.residuals import ResidualTable

if TYPE_CHECKING:  # annotations only: drawing needs neither the matcher (OpenCV) nor the study
    from rectify.features import MatchResult
    from rectify.geometry.transforms.study import StudyResults

logger = logging.getLogger(__name__)

__all__ = [
    "correlation_heatmap_figure",
    "height_bars_figure",
    "height_difference_map_figure",
    "pair_matches_figure",
    "readable_map_ticks",
    "histogram_qq_figure",
    "match_figures",
    "nice_number",
    "radial_figure",
    "residual_vector_figure",
    "standardised_components",
    "study_figures",
]

#: Largest background side (pixels) drawn; bigger images are subsampled for the plot only.
MAX_BACKGROUND_PX = 1600
#: Normalised residuals above this are drawn in the top colour (colour scale 0 .. NORM_CLIP).
NORM_CLIP = 4.0
_CMAP = "plasma"
_OUTLIER_COLOUR = "#d62728"
_CHECK_COLOUR = "#1f77b4"


def nice_number(x: float) -> float:
    """Round a positive number to 1, 2 or 5 times a power of ten (for scale bars).

    >>> nice_number(0.37), nice_number(7.2), nice_number(180.0)
    (0.5, 5.0, 200.0)
    """
    if not (x > 0 and math.isfinite(x)):
        return 1.0
    e = math.floor(math.log10(x))
    f = x / 10.0 ** e
    m = 1.0 if f < 1.5 else 2.0 if f < 3.5 else 5.0 if f < 7.5 else 10.0
    return float(m * 10.0 ** e)


def _new_figure(w: float, h: float) -> Figure:
    fig = Figure(figsize=(w, h), dpi=100, layout="constrained")
    return fig


def _wrap(text: str, fig: Figure, fontsize: float) -> str:
    """Wrap a title to the figure width (about 0.6 em per character)."""
    width_chars = max(20, int(fig.get_figwidth() * 72.0 / (0.6 * fontsize)) - 4)
    return "\n".join(textwrap.fill(part, width_chars) for part in text.split("\n"))


def _finite_or_nan(x: float | None) -> float:
    return float(x) if x is not None and math.isfinite(float(x)) else float("nan")


def standardised_components(table: ResidualTable) -> NDArray[np.float64]:
    """Signed residual components divided by their standard deviation, (N, k), unitless.

    With per-point ``std`` (standard deviation of |v|) each component is divided
    by ``std / sqrt(k)``; otherwise by ``sigma0 / sqrt(weight)``. Under the model
    each entry is approximately standard normal, so these feed the normal Q-Q plot.
    NaN where the divisor is zero or undefined.
    """
    v = table.residual
    k = v.shape[1]
    with np.errstate(divide="ignore", invalid="ignore"):
        if table.std is not None:
            s = table.std / math.sqrt(k)
        else:
            s0 = _finite_or_nan(table.sigma0)
            w = np.ones(table.n) if table.weights is None else table.weights
            s = np.where(w > 0, s0 / np.sqrt(w), np.nan)
        s = np.where(s > 0, s, np.nan)
        return v / s[:, None]


def _flags(a: NDArray[np.bool_] | None, n: int) -> NDArray[np.bool_]:
    """A per-point flag column of a table (``check``, ``outlier``), all False when absent."""
    return np.zeros(n, dtype=bool) if a is None else a


def _masks(table: ResidualTable) -> tuple[NDArray[np.bool_], NDArray[np.bool_], NDArray[np.bool_]]:
    out = _flags(table.outlier, table.n)
    return table.fit_mask, _flags(table.check, table.n) & ~out, out


def _subsample_background(background: NDArray) -> tuple[NDArray, int]:
    b = np.asarray(background)
    if b.ndim not in (2, 3) or (b.ndim == 3 and b.shape[2] not in (1, 3, 4)):
        raise ShapeError(f"`background` must have shape (H, W) or (H, W, 1|3|4); got {b.shape}",
                         actual_shape=b.shape)
    step = max(1, math.ceil(max(b.shape[:2]) / MAX_BACKGROUND_PX))
    b = b[::step, ::step]
    if b.ndim == 3 and b.shape[2] == 1:
        b = b[:, :, 0]
    if b.dtype != np.uint8:
        f = b.astype(np.float64)
        finite = np.isfinite(f)
        if finite.any():
            lo, hi = np.percentile(f[finite], [1, 99])
            hi = hi if hi > lo else lo + 1.0
            f = np.clip((f - lo) / (hi - lo), 0.0, 1.0)
        f[~finite] = 0.0
        b = f
    return b, step


def residual_vector_figure(table: ResidualTable, image_shape: Sequence[int] | None = None,
                           background: ArrayLike | None = None, *, positions: ArrayLike | None = None,
                           position_units: str = "px", y_down: bool = True,
                           components_y_up: bool = False, scale: float | None = None,
                           max_arrows: int = 1500, title: str | None = None) -> Figure:
    """Residual vectors drawn at their points, scaled, with a scale arrow, coloured by normalised residual.

    Parameters
    ----------
    table : ResidualTable
        Residuals; uses ``table.position_px`` unless ``positions`` is given.
        With one component (e.g. vertical parallax q) the arrows are vertical;
        with three or more (e.g. dX, dY, dZ) the first two are drawn (plan vectors).
    image_shape : (H, W) or (H, W, C), optional
        Image size in pixels; sets the axes limits to the image frame.
    background : (H, W) or (H, W, C) array, optional
        Image drawn under the vectors (subsampled to at most 1600 px a side for
        the plot only; non-uint8 data stretched between the 1st and 99th percentile).
    positions : (N, 2) array_like, optional
        Where to draw the vectors instead of ``table.position_px`` (e.g. ground
        X, Y for absolute orientation; then pass ``position_units="m"``, ``y_down=False``).
    position_units : str
        Units of the positions, for the axis labels.
    y_down : bool
        True for the image frame (y axis pointing down), False for map/ground axes.
    components_y_up : bool
        True when the second residual component points up (photo mm frame) while
        the plot is in the image frame: the arrow's y is then negated.
    scale : float, optional
        Plot units per residual unit (arrow exaggeration); chosen automatically so
        that the 95th-percentile arrow spans about 8 % of the plotted extent, or
        0.8 of the mean point spacing when that is shorter.
    max_arrows : int
        With more points than this, the arrows show the mean residual of the
        non-outlier points in each cell of a square grid (about max_arrows / 2
        cells) and are coloured by the cell's RMS normalised residual; every point,
        check point and outlier is still marked.
    title : str, optional
        Figure title; default names the step.

    Returns
    -------
    matplotlib.figure.Figure

    Raises
    ------
    InvalidInputError
        If there are no positions or no points.
    ShapeError
        If ``positions``, ``image_shape`` or ``background`` has a wrong shape.
    """
    if positions is None:
        if table.position_px is None:
            raise InvalidInputError(f"table {table.step!r} has no position_px; pass `positions`")
        pos = table.position_px
    else:
        pos = np.asarray(positions, dtype=np.float64)
        if pos.shape != (table.n, 2):
            raise ShapeError(f"`positions` must have shape ({table.n}, 2); got {pos.shape}",
                             actual_shape=pos.shape, expected_shape=(table.n, 2))
    if table.n == 0:
        raise InvalidInputError(f"table {table.step!r} has no points to draw")
    if max_arrows < 4:
        raise InvalidInputError(f"`max_arrows` must be >= 4; got {max_arrows}")
    v = table.residual
    if v.shape[1] == 1:
        u = np.zeros(table.n)
        w = v[:, 0].copy()
        comp_label = f"{table.components[0]} drawn vertically"
    else:
        u, w = v[:, 0].copy(), v[:, 1].copy()
        comp_label = f"({table.components[0]}, {table.components[1]})"
    if components_y_up:
        w = -w
    # matplotlib's quiver takes directions in data coordinates with angles="xy": a positive
    # w points towards increasing y, i.e. downwards on an inverted (image) axis, as wanted.
    extent_xy = None
    bg = None
    if background is not None:
        bg, step = _subsample_background(np.asarray(background))
        hh, ww = np.asarray(background).shape[:2]
        extent_xy = (ww, hh)
        if image_shape is None:
            image_shape = (hh, ww)
    if image_shape is not None:
        shp = tuple(int(s) for s in image_shape)
        if len(shp) not in (2, 3) or min(shp[:2]) <= 0:
            raise ShapeError(f"`image_shape` must be (H, W) or (H, W, C) with positive sizes; got {shp}",
                             actual_shape=shp)
        extent_xy = (shp[1], shp[0])
    finite = np.all(np.isfinite(pos), axis=1)
    if extent_xy is not None:
        x0, x1, y0, y1 = -0.5, extent_xy[0] - 0.5, -0.5, extent_xy[1] - 0.5
    elif finite.any():
        x0, x1 = float(pos[finite, 0].min()), float(pos[finite, 0].max())
        y0, y1 = float(pos[finite, 1].min()), float(pos[finite, 1].max())
        pad = 0.08 * max(x1 - x0, y1 - y0, 1e-9)
        x0, x1, y0, y1 = x0 - pad, x1 + pad, y0 - pad, y1 + pad
    else:
        x0, x1, y0, y1 = 0.0, 1.0, 0.0, 1.0
    span = max(x1 - x0, y1 - y0, 1e-12)
    aspect = abs(y1 - y0) / max(abs(x1 - x0), 1e-12)
    fig = _new_figure(8.0, 6.4) if aspect <= 1.1 else _new_figure(7.0, min(10.0, 1.6 + 5.4 * aspect))
    ax = fig.add_subplot()
    if bg is not None:
        ax.imshow(bg, cmap="gray" if bg.ndim == 2 else None, extent=(-0.5, ww - 0.5, hh - 0.5, -0.5),
                  interpolation="nearest" if step == 1 else "antialiased", zorder=0)
    fit, chk, out = _masks(table)
    nz = table.normalised
    n_pts = table.n
    gridded = n_pts > max_arrows
    if gridded:
        # too many arrows to read: mean residual of the non-outlier points per grid cell
        g = max(2, int(math.sqrt(max_arrows / 2.0)))
        use = ~_flags(table.outlier, table.n) & finite & np.isfinite(u) & np.isfinite(w)
        cx = np.clip(((pos[:, 0] - x0) / max(x1 - x0, 1e-12) * g).astype(np.int64), 0, g - 1)
        cy = np.clip(((pos[:, 1] - y0) / max(y1 - y0, 1e-12) * g).astype(np.int64), 0, g - 1)
        cell = (cy * g + cx)[use]
        cnt = np.bincount(cell, minlength=g * g).astype(np.float64)
        has = cnt > 0
        c = cnt[has]

        def mean_of(a: NDArray) -> NDArray:
            return np.bincount(cell, weights=a[use], minlength=g * g)[has] / c

        ax_pos = np.column_stack([mean_of(pos[:, 0]), mean_of(pos[:, 1])])
        au, aw = mean_of(u), mean_of(w)
        nzf = np.where(np.isfinite(nz), nz, 0.0)
        acol = np.sqrt(mean_of(nzf * nzf))
        cell_size = max(x1 - x0, y1 - y0) / g
        arrow_cap = 0.9 * cell_size
    else:
        ax_pos, au, aw = pos, u, w
        acol = np.where(np.isfinite(nz), nz, 0.0)
        arrow_cap = 0.8 * span / math.sqrt(max(n_pts, 1))
    length = np.hypot(au, aw)
    good = np.isfinite(length)
    ref = float(np.percentile(length[good], 95)) if good.any() else 0.0
    if scale is None:
        scale = min(0.08 * span, arrow_cap) / ref if ref > 0 else 1.0
    key_len = nice_number(ref if ref > 0 else 1.0)
    norm = Normalize(vmin=0.0, vmax=NORM_CLIP)
    dense = n_pts > 500
    q = ax.quiver(ax_pos[:, 0], ax_pos[:, 1], au * scale, aw * scale, acol, cmap=_CMAP, norm=norm,
                  angles="xy", scale_units="xy", scale=1.0, width=0.0025 if dense else 0.003,
                  headwidth=3.5, headlength=4.5, zorder=3)
    ax.scatter(pos[fit, 0], pos[fit, 1], s=1 if dense else 6, c="k", alpha=0.35 if dense else 1.0,
               linewidths=0, zorder=2 if dense else 4, label="fit point")
    if chk.any():
        ax.scatter(pos[chk, 0], pos[chk, 1], s=10 if dense else 40, marker="^", facecolors="none",
                   edgecolors=_CHECK_COLOUR, linewidths=0.6 if dense else 1.2, zorder=5, label="check point")
    if out.any():
        ax.scatter(pos[out, 0], pos[out, 1], s=14 if dense else 55, marker="x", c=_OUTLIER_COLOUR,
                   linewidths=0.8 if dense else 1.4, zorder=6, label="outlier")
    if gridded:
        comp_label += f" mean per cell of a {g}\u00d7{g} grid ({n_pts} points, outliers excluded)"
    qk = ax.quiverkey(q, 0.80, 1.015, key_len * scale, f"{key_len:g} {table.units}", labelpos="E",
                      coordinates="axes", color="k")
    qk.set_zorder(7)
    cb = fig.colorbar(q, ax=ax, shrink=0.85, extend="max")
    cb.set_label("normalised residual |v| / \u03c3  (unitless)" if not gridded
                 else "RMS normalised residual per cell (unitless)")
    ax.set_xlim(x0, x1)
    if y_down:
        ax.set_ylim(y1, y0)
    else:
        ax.set_ylim(y0, y1)
    ax.set_aspect("equal")
    ax.ticklabel_format(axis="both", style="plain", useOffset=False)  # full map coordinates
    if not y_down:
        readable_map_ticks(ax)
    xl, yl = ("column x", "row y") if position_units == "px" else ("X", "Y")
    ax.set_xlabel(f"{xl} ({position_units})")
    ax.set_ylabel(f"{yl} ({position_units})")
    ax.set_title(_wrap(title or f"{table.step}: residual vectors {comp_label}, arrows \u00d7{scale:.3g}",
                       fig, 10), fontsize=10, loc="left", pad=18)
    ax.legend(loc="lower left", fontsize=8, framealpha=0.85, markerscale=3.0 if dense else 1.0)
    ax.grid(True, alpha=0.25)
    return fig


def histogram_qq_figure(table: ResidualTable, *, title: str | None = None) -> Figure:
    """Histogram of normalised residuals |v|/sigma and a normal Q-Q plot of standardised components.

    The left panel is the histogram of the table's normalised residuals (the
    ``normalised`` CSV column) for fit and check points, with the chi density
    of k degrees of freedom that it follows under the model. The right panel is
    the normal Q-Q plot of the signed standardised components
    (:func:`standardised_components`) with the 1:1 line; outliers in red.

    Raises
    ------
    InvalidInputError
        If the table has no points.
    """
    if table.n == 0:
        raise InvalidInputError(f"table {table.step!r} has no points to plot")
    # local import: scipy.stats takes about 1.4 s to import, which every command would pay at start-up
    from scipy import stats

    fig = _new_figure(10.0, 4.2)
    ax1, ax2 = fig.subplots(1, 2)
    nz = table.normalised
    fit, chk, out = _masks(table)
    k = table.residual.shape[1]
    finite = np.isfinite(nz)
    data = [nz[fit & finite], nz[chk & finite], nz[out & finite]]
    labels = ["fit points", "check points", "outliers"]
    colours = ["#7f7f7f", _CHECK_COLOUR, _OUTLIER_COLOUR]
    allv = nz[finite]
    if allv.size:
        ref_vals = nz[fit & finite] if (fit & finite).any() else allv
        top = max(1.2 * float(np.percentile(ref_vals, 99.5)), 3.0)
        bins = np.linspace(0.0, top, max(10, min(60, int(np.sqrt(allv.size)) + 5)))
        keep = [(d, lab, c) for d, lab, c in zip(data, labels, colours, strict=True) if d.size]
        ax1.hist([np.clip(d, 0, top) for d, _, _ in keep], bins=bins, stacked=True, density=True,
                 color=[c for _, _, c in keep], label=[f"{lab} ({d.size})" for d, lab, _ in keep],
                 edgecolor="white", linewidth=0.5)
        xs = np.linspace(0.0, top, 200)
        ax1.plot(xs, stats.chi.pdf(xs, k), "k--", lw=1.2, label=f"\u03c7 density, {k} dof")
        ax1.legend(fontsize=8, loc="upper right")
    else:
        ax1.text(0.5, 0.5, "no finite normalised residuals\n(sigma undefined)", ha="center",
                 va="center", transform=ax1.transAxes)
    ax1.set_xlabel("normalised residual |v| / \u03c3  (unitless; larger values in the last bin)")
    ax1.set_ylabel("density (1 / unit)")
    ax1.set_title("Histogram of normalised residuals", fontsize=10)
    ax1.grid(True, alpha=0.25)

    z = standardised_components(table)
    groups = [(fit, "fit", "#444444", "o"), (chk, "check", _CHECK_COLOUR, "^"), (out, "outlier", _OUTLIER_COLOUR, "x")]
    zall = z[np.isfinite(z)]
    if zall.size:
        order_vals = np.sort(zall)
        n = order_vals.size
        theo = stats.norm.ppf((np.arange(1, n + 1) - 0.5) / n)
        # colour each sorted value by the group of the point it came from
        flat_group = np.repeat(np.select([out, chk], [2, 1], 0), k)[np.isfinite(z).reshape(-1)]
        idx = np.argsort(z[np.isfinite(z)], kind="stable")
        g_sorted = flat_group[idx]
        for gi, (_, lab, col, mk) in enumerate(groups):
            m = g_sorted == gi
            if m.any():
                ax2.scatter(theo[m], order_vals[m], s=8 if mk != "x" else 20, c=col, marker=mk,
                            linewidths=0.8 if mk == "x" else 0, label=f"{lab} ({int(m.sum())} comp.)")
        lim = float(max(np.abs(theo).max(), np.abs(order_vals[np.isfinite(order_vals)]).max()))
        lim = min(lim, 20.0) * 1.05
        ax2.plot([-lim, lim], [-lim, lim], "k--", lw=1, label="1:1 (normal)")
        ax2.set_xlim(-lim, lim)
        ax2.set_ylim(-lim, lim)
        ax2.legend(fontsize=8, loc="upper left")
    else:
        ax2.text(0.5, 0.5, "no finite standardised residuals", ha="center", va="center",
                 transform=ax2.transAxes)
    ax2.set_xlabel("standard normal quantile (unitless)")
    ax2.set_ylabel("standardised residual component v\u00b7\u221aw / \u03c3\u2080  (unitless)")
    ax2.set_title("Normal Q-Q plot of residual components", fontsize=10)
    ax2.grid(True, alpha=0.25)
    fig.suptitle(_wrap(title or f"{table.step}: distribution of residuals", fig, 11), fontsize=11)
    return fig


def _limit_to_fit(ax, y: NDArray, keep: NDArray[np.bool_], *, zero_floor: bool) -> None:
    """Scale the y axis to the non-outlier values; say how many points lie beyond."""
    vals = y[keep & np.isfinite(y)]
    if vals.size < 2:
        return
    lo, hi = np.percentile(vals, [0.0, 100.0])
    pad = 0.1 * max(hi - lo, abs(hi), 1e-12)
    lo = 0.0 if zero_floor else lo - pad
    hi = hi + pad
    beyond = int(np.sum(np.isfinite(y) & ((y > hi) | (y < lo))))
    if beyond:
        ax.set_ylim(lo, hi)
        ax.text(0.99, 0.01, f"{beyond} outlier(s) beyond the plotted range", transform=ax.transAxes,
                ha="right", va="bottom", fontsize=8, color=_OUTLIER_COLOUR,
                bbox={"facecolor": "white", "alpha": 0.85, "edgecolor": "none", "pad": 2})


def radial_figure(table: ResidualTable, principal_point_px: ArrayLike, *,
                  components_y_up: bool = False, n_bins: int = 10, title: str | None = None) -> Figure:
    """Residual against radial distance from the principal point.

    Left: |v| against r with the RMS per radial bin. Right (two or more
    components): the radial component v . r_hat (positive outwards), whose
    systematic trend with r reveals uncorrected radial distortion.

    Parameters
    ----------
    table : ResidualTable
        Needs ``position_px``.
    principal_point_px : (2,) array_like
        Principal point (x, y) in the pixel frame.
    components_y_up : bool
        True when the second residual component points up (photo mm frame).
    n_bins : int
        Number of radial bins for the RMS / mean curves.

    Raises
    ------
    InvalidInputError
        If the table has no positions or no points, or ``n_bins`` < 1.
    ShapeError
        If ``principal_point_px`` is not two numbers.
    """
    if table.position_px is None:
        raise InvalidInputError(f"table {table.step!r} has no position_px for a radial plot")
    if table.n == 0:
        raise InvalidInputError(f"table {table.step!r} has no points to plot")
    if n_bins < 1:
        raise InvalidInputError(f"`n_bins` must be >= 1; got {n_bins}")
    pp = np.asarray(principal_point_px, dtype=np.float64).reshape(-1)
    if pp.shape != (2,) or not np.all(np.isfinite(pp)):
        raise ShapeError(f"`principal_point_px` must be two finite numbers (x, y); got {pp.tolist()}",
                         actual_shape=pp.shape, expected_shape=(2,))
    d = table.position_px - pp
    r = np.hypot(d[:, 0], d[:, 1])
    v = table.residual
    k = v.shape[1]
    fit, chk, out = _masks(table)
    two = k >= 2
    fig = _new_figure(10.0 if two else 6.0, 4.2)
    axes = fig.subplots(1, 2) if two else [fig.add_subplot()]
    series = [("|v|", table.norm, "RMS")]
    if two:
        vx, vy = v[:, 0], (-v[:, 1] if components_y_up else v[:, 1])
        with np.errstate(invalid="ignore", divide="ignore"):
            vr = np.where(r > 0, (vx * d[:, 0] + vy * d[:, 1]) / r, 0.0)
        series.append(("radial component v\u00b7r\u0302 (outwards +)", vr, "mean"))
    rmax = float(np.nanmax(r)) if np.isfinite(r).any() else 1.0
    edges = np.linspace(0.0, rmax if rmax > 0 else 1.0, n_bins + 1)
    for ax, (lab, y, stat_name) in zip(axes, series, strict=True):
        ax.scatter(r[fit], y[fit], s=6, c="#555555", linewidths=0, alpha=0.6, label="fit point")
        if chk.any():
            ax.scatter(r[chk], y[chk], s=25, marker="^", facecolors="none", edgecolors=_CHECK_COLOUR,
                       label="check point")
        if out.any():
            ax.scatter(r[out], y[out], s=25, marker="x", c=_OUTLIER_COLOUR, label="outlier")
        which = np.clip(np.digitize(r, edges) - 1, 0, n_bins - 1)
        centres, vals = [], []
        for b in range(n_bins):
            m = fit & (which == b) & np.isfinite(y)
            if m.any():
                centres.append(0.5 * (edges[b] + edges[b + 1]))
                vals.append(float(np.sqrt(np.mean(y[m] ** 2))) if stat_name == "RMS" else float(np.mean(y[m])))
        if centres:
            ax.plot(centres, vals, "-o", color="#ff7f0e", lw=2, ms=4, label=f"{stat_name} per radial bin")
        if stat_name == "mean":
            ax.axhline(0.0, color="k", lw=0.8)
        _limit_to_fit(ax, y, fit | chk, zero_floor=stat_name == "RMS")
        ax.set_xlim(left=0.0)
        ax.set_xlabel("radial distance from principal point r (px)")
        ax.set_ylabel(f"{lab} ({table.units})")
        ax.grid(True, alpha=0.25)
        ax.legend(fontsize=8, loc="upper left")
    axes[0].set_title("Residual length vs radius", fontsize=10)
    if two:
        axes[1].set_title("Radial component vs radius (distortion signature)", fontsize=10)
    fig.suptitle(_wrap(title or f"{table.step}: residuals vs distance from principal point "
                       f"({pp[0]:.1f}, {pp[1]:.1f}) px", fig, 11), fontsize=11)
    return fig


def correlation_heatmap_figure(names: Sequence[str], matrix: ArrayLike, *,
                               title: str = "Correlation of estimated elements") -> Figure:
    """Correlation matrix as an annotated heat map (-1 blue .. +1 red).

    Parameters
    ----------
    names : sequence of str, length m
        Element names (e.g. the five relative-orientation elements).
    matrix : (m, m) array_like
        Correlation coefficients, unitless, in [-1, 1].

    Raises
    ------
    ShapeError
        If ``matrix`` is not (m, m) for m = len(names).
    InvalidInputError
        If it holds values outside [-1, 1] (beyond rounding) or NaN.
    """
    names = [str(n) for n in names]
    c = np.asarray(matrix, dtype=np.float64)
    m = len(names)
    if c.shape != (m, m) or m == 0:
        raise ShapeError(f"`matrix` must have shape ({m}, {m}) for {m} names; got {c.shape}",
                         actual_shape=c.shape, expected_shape=(m, m))
    if not np.all(np.isfinite(c)) or np.abs(c).max() > 1.0 + 1e-9:
        bad = c[~np.isfinite(c) | (np.abs(c) > 1.0 + 1e-9)]
        raise InvalidInputError(f"correlations must be finite and in [-1, 1]; got {bad[:3].tolist()}")
    size = max(4.5, 0.8 * m + 2.0)
    fig = _new_figure(size + 1.0, size)
    ax = fig.add_subplot()
    im = ax.imshow(c, cmap="RdBu_r", vmin=-1.0, vmax=1.0)
    ax.set_xticks(range(m), names, rotation=45, ha="right")
    ax.set_yticks(range(m), names)
    ax.set_xlabel("element")
    ax.set_ylabel("element")
    for i in range(m):
        for j in range(m):
            ax.text(j, i, f"{c[i, j]:+.2f}", ha="center", va="center", fontsize=9,
                    color="white" if abs(c[i, j]) > 0.6 else "black")
    cb = fig.colorbar(im, ax=ax, shrink=0.85)
    cb.set_label("correlation coefficient (unitless)")
    ax.set_title(_wrap(title, fig, 11), fontsize=11)
    return fig


def height_bars_figure(table: ResidualTable, *, component: int | str = -1,
                       title: str | None = None) -> Figure:
    """Bar chart of one residual component per point (e.g. the height residual dZ).

    Bars are ordered as in the table, red for outliers, hatched for check points,
    with +-RMSE of the fit points as dashed lines.

    Parameters
    ----------
    table : ResidualTable
    component : int or str
        Index or name of the component (default the last, e.g. ``"dz"``).

    Raises
    ------
    InvalidInputError
        If the table is empty or the component is unknown.
    """
    if table.n == 0:
        raise InvalidInputError(f"table {table.step!r} has no points to plot")
    comps = list(table.components)
    if isinstance(component, str):
        if component not in comps:
            raise InvalidInputError(f"unknown component {component!r}; table has {comps}")
        j = comps.index(component)
    else:
        j = int(component)
        if not -len(comps) <= j < len(comps):
            raise InvalidInputError(f"component index {component} out of range for {comps}")
        j %= len(comps)
    y = table.residual[:, j]
    fit, chk, out = _masks(table)
    n = table.n
    fig = _new_figure(min(14.0, max(6.0, 0.25 * n + 2.0)), 4.2)
    ax = fig.add_subplot()
    x = np.arange(n)
    colours = np.where(out, _OUTLIER_COLOUR, np.where(chk, _CHECK_COLOUR, "#4c72b0"))
    bars = ax.bar(x, y, color=colours, edgecolor="k", linewidth=0.4)
    for b, c in zip(bars, chk, strict=True):
        if c:
            b.set_hatch("//")
    rmse = float(np.sqrt(np.mean(y[fit] ** 2))) if fit.any() else float("nan")
    if math.isfinite(rmse):
        ax.axhline(rmse, color="k", ls="--", lw=0.9)
        ax.axhline(-rmse, color="k", ls="--", lw=0.9)
    ax.axhline(0.0, color="k", lw=0.8)
    if n <= 60:
        ax.set_xticks(x, list(table.ids), rotation=90, fontsize=7)
    else:
        ax.set_xlabel("point index")
    if n <= 60:
        ax.set_xlabel("point id")
    ax.set_ylabel(f"{comps[j]} ({table.units})")
    handles = [Line2D([], [], color="#4c72b0", lw=6, label="fit point"),
               Line2D([], [], color="k", ls="--", label=f"\u00b1RMSE {rmse:.3g} {table.units}")]
    if chk.any():
        handles.append(Line2D([], [], color=_CHECK_COLOUR, lw=6, label="check point"))
    if out.any():
        handles.append(Line2D([], [], color=_OUTLIER_COLOUR, lw=6, label="outlier"))
    ax.legend(handles=handles, fontsize=8, loc="upper right")
    ax.grid(True, axis="y", alpha=0.25)
    ax.set_title(_wrap(title or f"{table.step}: {comps[j]} residual per point", fig, 11), fontsize=11)
    return fig


# --------------------------------------------------------------------------- tie points
def match_figures(result: MatchResult, left_preview: tuple[NDArray, float] | None = None,
                  right_preview: tuple[NDArray, float] | None = None) -> dict[str, Figure]:
    """Figures for the report: inliers/outliers side by side, and match density.

    Parameters
    ----------
    result : MatchResult
    left_preview, right_preview : (image (h, w[, C]), scale), optional
        Downsampled images and their scale (full-resolution px per preview px),
        e.g. from :func:`rectify.raster.io.read_overview`.

    Returns
    -------
    dict name -> matplotlib Figure (``"matches"``, ``"density"``)
    """
    (hl, wl), _ = result.image_shapes
    fig = Figure(figsize=(11, 6), layout="constrained")
    axes = fig.subplots(1, 2)
    pts = [result.candidates_left, result.candidates_right]
    inl = result.candidate_inlier
    for ax, prev, (h, w), p, name in zip(axes, (left_preview, right_preview), result.image_shapes, pts,
                                         ("left", "right"), strict=True):
        if prev is not None:
            img, _scale = prev
            a = np.asarray(img, dtype=np.float64)
            a = a.mean(axis=2) if a.ndim == 3 else a
            ax.imshow(a, cmap="gray", extent=(-0.5, w - 0.5, h - 0.5, -0.5))
        sub = np.random.default_rng(0).permutation(len(p))[:20000]
        ax.scatter(p[sub][~inl[sub], 0], p[sub][~inl[sub], 1], s=2, c="tab:red", label="rejected")
        ax.scatter(p[sub][inl[sub], 0], p[sub][inl[sub], 1], s=2, c="tab:green", label="verified")
        ax.set_xlim(-0.5, w - 0.5)
        ax.set_ylim(h - 0.5, -0.5)
        ax.set_title(f"{name} image ({w} x {h} px)")
        ax.set_aspect("equal")
    axes[0].legend(loc="upper right", markerscale=4)
    fig.suptitle(f"{int(inl.sum())} verified / {len(inl)} candidate matches ({result.verification.method})")
    dens = Figure(figsize=(6, 6), layout="constrained")
    ax = dens.subplots()
    pl = result.matches.left
    nb = 32
    cell = max(hl, wl) / nb
    hist, _, _ = np.histogram2d(pl[:, 1], pl[:, 0], bins=(max(1, int(np.ceil(hl / cell))),
                                                         max(1, int(np.ceil(wl / cell)))),
                                range=((-0.5, hl - 0.5), (-0.5, wl - 0.5)))
    im = ax.imshow(hist, extent=(-0.5, wl - 0.5, hl - 0.5, -0.5), cmap="viridis", interpolation="nearest")
    dens.colorbar(im, ax=ax, label=f"matches per {cell:.0f} x {cell:.0f} px cell")
    ax.set_title(f"match density, left image ({len(pl)} matches)")
    return {"matches": fig, "density": dens}


# --------------------------------------------------------------------------- projective study
def study_figures(results: StudyResults) -> dict[str, Figure]:
    """Figures of the cotangent vs homography study (:func:`rectify.geometry.transforms.study.run_study`), one per part.

    Returns
    -------
    dict name -> Figure: ``agreement`` (histogram of the largest difference on
    exact data, log10 of the image size), ``noise`` (check-point RMSE against
    the control-point noise, px), ``propagation`` (predicted against Monte
    Carlo RMSE, px), ``conditioning`` (noise gain near degeneracy) and
    ``speed`` (million points per second).
    """

    figs: dict[str, Figure] = {}
    raw = results.raw
    # 1. agreement histogram
    fig = Figure(figsize=(6, 4))
    ax = fig.add_subplot()
    d = np.asarray(raw.get("agreement_rel", []))
    d = d[d > 0]
    if d.size:
        ax.hist(np.log10(d), bins=40, color="tab:blue")
    ax.axvline(-8, color="r", ls="--", label="1e-8 of image size")
    ax.set_xlabel("log10(max |cotangent - homography| / image size)")
    ax.set_ylabel("configurations")
    ax.set_title("1. Agreement on exact data")
    ax.legend()
    figs["agreement"] = fig
    # 2. RMSE vs sigma
    fig = Figure(figsize=(7, 4))
    ax = fig.add_subplot()
    for cam in dict.fromkeys(r["camera"] for r in results.noise):
        rows = [r for r in results.noise if r["camera"] == cam]
        sg = [r["sigma_px"] for r in rows]
        short = cam.split(" (")[0]
        ax.plot(sg, [r["rmse_cotangent"] for r in rows], "o-", label=f"{short}: cotangent (4)")
        ax.plot(sg, [r["rmse_homography4"] for r in rows], "x--", label=f"{short}: homography (4)")
        ax.plot(sg, [r["rmse_homography_lsq"] for r in rows], "s-", label=f"{short}: homography LSQ")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("control-point noise sigma [px]")
    ax.set_ylabel("RMSE at check points [px]")
    ax.set_title("2. Accuracy under noise (Monte Carlo)")
    ax.legend(fontsize=7)
    figs["noise"] = fig
    # 3. predicted vs MC
    fig = Figure(figsize=(5, 5))
    ax = fig.add_subplot()
    for m, mk in (("cotangent (4)", "o"), ("homography (4)", "x"), ("homography LSQ", "s")):
        rows = [r for r in results.propagation if r["method"] == m]
        ax.plot([r["monte_carlo"] for r in rows], [r["predicted"] for r in rows], mk, label=m)
    allv = [r["monte_carlo"] for r in results.propagation] + [r["predicted"] for r in results.propagation]
    if allv:
        lo, hi = min(allv), max(allv)
        ax.plot([lo, hi], [lo, hi], "k:", label="y = x")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("Monte Carlo RMSE [px]")
    ax.set_ylabel("first-order predicted RMSE [px]")
    ax.set_title("3. Error propagation vs Monte Carlo")
    ax.legend(fontsize=8)
    figs["propagation"] = fig
    # 4. conditioning
    fig = Figure(figsize=(7, 4))
    ax = fig.add_subplot()
    cond = [r for r in results.conditioning if "error" not in r]
    eps = [r["eps"] for r in cond]
    ax.plot(eps, [r["gain_cotangent"] for r in cond], "o-", label="noise gain, cotangent (4)")
    ax.plot(eps, [r["gain_homography"] for r in cond], "x--", label="noise gain, homography (4)")
    ax.plot(eps, [max(r["max_diff_rel"], 1e-17) for r in cond], "s-",
            label="max |cot - H| / size (exact)")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("eps (distance of point 3 from line 2-4 / side)")
    ax.set_title("4. Conditioning near degeneracy")
    ax.legend(fontsize=8)
    figs["conditioning"] = fig
    # 5. speed
    fig = Figure(figsize=(5, 3.5))
    ax = fig.add_subplot()
    s = results.speed
    ax.bar(["homography", "cotangent"], [s["homography_pts_per_s"] / 1e6, s["cotangent_pts_per_s"] / 1e6],
           color=["tab:gray", "tab:blue"])
    ax.set_ylabel("million points / s")
    ax.set_title(f"5. Speed ({s['n_points']:,} points, ratio {s['ratio']:.2f})")
    figs["speed"] = fig
    return figs


# --------------------------------------------------------------------------- map ticks, pair figures (issue 12)
def _coordinate_label(v: float, _pos: int | None = None) -> str:
    """A map coordinate for a tick: thin-space thousands groups for large values (500 200, 4 399 800)."""
    if abs(v) >= 1e4:
        return f"{v:,.0f}".replace(",", "\u2009")
    return f"{v:.6g}"


def readable_map_ticks(ax) -> None:
    """Full map coordinates on at most 6 ticks per axis, thousands grouped, x labels turned 30 degrees."""

    for axis in (ax.xaxis, ax.yaxis):
        axis.set_major_locator(MaxNLocator(nbins=6))
        axis.set_major_formatter(FuncFormatter(_coordinate_label))
    ax.tick_params(axis="x", labelrotation=30)
    for label in ax.get_xticklabels():
        label.set_horizontalalignment("right")


def height_difference_map_figure(xy: ArrayLike, dz: ArrayLike, ids: Sequence[str], *, units: str = "m",
                                 std: ArrayLike | None = None, title: str | None = None) -> Figure:
    """Map of height differences at check points: dZ = estimated - reference at the points' ground X, Y,
    coloured on a symmetric diverging scale, each labelled with its value (and dZ / predicted std)."""
    p = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    d = np.asarray(dz, dtype=np.float64).reshape(-1)
    if len(p) != len(d) or len(ids) != len(d):
        raise ShapeError(f"`xy`, `dz` and `ids` must have one row per point; got {len(p)}, {len(d)}, {len(ids)}")
    if len(d) == 0:
        raise InvalidInputError("no check points for the height-difference map")
    fig = _new_figure(8.0, 6.4)
    ax = fig.add_subplot()
    lim = float(np.nanmax(np.abs(d))) if np.isfinite(d).any() else 1.0
    lim = lim if lim > 0 else 1.0
    sc = ax.scatter(p[:, 0], p[:, 1], c=d, cmap="RdBu_r", vmin=-lim, vmax=lim, s=70, edgecolors="k", linewidths=0.5)
    sd = None if std is None else np.asarray(std, dtype=np.float64).reshape(-1)
    for i in range(len(d)):
        txt = f"{ids[i]}: {d[i]:+.3g}"
        if sd is not None and np.isfinite(sd[i]) and sd[i] > 0:
            txt += f" ({d[i] / sd[i]:+.1f}\u03c3)"
        ax.annotate(txt, (p[i, 0], p[i, 1]), textcoords="offset points", xytext=(5, 4), fontsize=7)
    cb = fig.colorbar(sc, ax=ax, shrink=0.85)
    cb.set_label(f"dZ = estimated - reference ({units})")
    ax.set_aspect("equal", adjustable="datalim")
    readable_map_ticks(ax)
    ax.set_xlabel(f"X ({units})")
    ax.set_ylabel(f"Y ({units})")
    rms_txt = float(np.sqrt(np.nanmean(d ** 2)))
    ax.set_title(_wrap(title or f"Height differences at {len(d)} check points (RMS {rms_txt:.3g} {units}, "
                       f"mean {float(np.nanmean(d)):+.3g} {units})", fig, 10), fontsize=10, loc="left")
    ax.grid(True, alpha=0.25)
    return fig


def pair_matches_figure(left: NDArray | None, right: NDArray | None, left_px: ArrayLike, right_px: ArrayLike, *,
                        outlier: ArrayLike | None = None, shapes: Sequence[Sequence[int]] | None = None,
                        max_lines: int = 300, title: str | None = None) -> Figure:
    """The tie points over the two images side by side: kept points green, rejected red, and lines joining
    an even sample of at most ``max_lines`` pairs. Images may be None (frames only; give ``shapes``)."""
    pl = np.asarray(left_px, dtype=np.float64).reshape(-1, 2)
    pr = np.asarray(right_px, dtype=np.float64).reshape(-1, 2)
    if pl.shape != pr.shape:
        raise ShapeError(f"left and right points differ in shape: {pl.shape} and {pr.shape}")
    out = np.zeros(len(pl), bool) if outlier is None else np.asarray(outlier, dtype=bool).reshape(-1)
    imgs = [left, right]
    hw = []
    for k, im in enumerate(imgs):
        if im is not None:
            hw.append(tuple(np.asarray(im).shape[:2]))
        elif shapes is not None:
            hw.append(tuple(int(v) for v in shapes[k][:2]))
        else:
            pts = pl if k == 0 else pr
            hw.append((int(np.nanmax(pts[:, 1])) + 1, int(np.nanmax(pts[:, 0])) + 1) if len(pts) else (1, 1))
    (h1, w1), (h2, w2) = hw
    gap = 0.03 * max(w1, w2)
    fig = _new_figure(11.0, 11.0 * max(h1, h2) / (w1 + w2 + gap) + 1.2)
    ax = fig.add_subplot()
    for k, (im, off) in enumerate(((imgs[0], 0.0), (imgs[1], w1 + gap))):
        h, w = hw[k]
        if im is not None:
            a = np.asarray(im)
            step = max(1, int(math.ceil(max(a.shape[:2]) / MAX_BACKGROUND_PX)))
            ax.imshow(a[::step, ::step], cmap="gray" if a.ndim == 2 else None,
                      extent=(off - 0.5, off + w - 0.5, h - 0.5, -0.5))
        ax.plot([off - 0.5, off + w - 0.5, off + w - 0.5, off - 0.5, off - 0.5],
                [-0.5, -0.5, h - 0.5, h - 0.5, -0.5], "k-", lw=0.8)
    q = pr + [w1 + gap, 0.0]
    idx = np.flatnonzero(~out)
    if len(idx) > max_lines:
        idx = idx[np.linspace(0, len(idx) - 1, max_lines).round().astype(int)]
    for i in idx:
        ax.plot([pl[i, 0], q[i, 0]], [pl[i, 1], q[i, 1]], "-", color="#2ca02c", lw=0.4, alpha=0.5)
    for pts in (pl, q):
        ax.scatter(pts[~out, 0], pts[~out, 1], s=4, c="#2ca02c")
        if out.any():
            ax.scatter(pts[out, 0], pts[out, 1], s=10, c=_OUTLIER_COLOUR, marker="x", linewidths=0.7)
    ax.set_xlim(-0.5 - gap / 2, w1 + gap + w2)
    ax.set_ylim(max(h1, h2) - 0.5, -0.5)
    ax.set_aspect("equal")
    ax.set_axis_off()
    handles = [Line2D([], [], marker="o", ls="", color="#2ca02c", label=f"kept ({int((~out).sum())})")]
    if out.any():
        handles.append(Line2D([], [], marker="x", ls="", color=_OUTLIER_COLOUR, label=f"rejected ({int(out.sum())})"))
    ax.legend(handles=handles, loc="lower center", bbox_to_anchor=(0.5, -0.06), ncol=2, fontsize=8)
    ax.set_title(_wrap(title or f"{len(pl)} tie points over the left and right images "
                       f"(lines: {len(idx)} of the kept pairs)", fig, 11), fontsize=11)
    return fig
