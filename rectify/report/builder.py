"""One QA report for every step: residual CSVs, plots, ``report.json``, a self-contained HTML page.

Every command's ``--report DIR`` and the ``demo`` runs call :func:`write_report`
with the :class:`~rectify.geometry.residuals.ResidualTable` objects their estimators
return. For each table the report holds

- ``<step>.csv``: id, observed, adjusted, residual components, |v| (``norm``),
  normalised residual, weight, outlier flag, check flag (``ResidualTable.to_csv``);
- ``<step>_vectors.png``: residual vectors over the image at ``position_px``
  (arrows scaled, scale arrow, coloured by normalised residual, outliers marked);
- ``<step>_distribution.png``: histogram of normalised residuals + normal Q-Q plot;
- ``<step>_radial.png``: residual against distance from the principal point;
- ``<step>.geojson``: the residual vectors in the ground CRS (when ``crs`` and
  ``ground_xy`` are given), for QGIS;

plus the caller's extra ``figures`` (PNG), ``report.json`` (per-table summary:
counts, RMSE and sigma0 with units, the caller's ``summary``, the file list) and
``report.html``, one page with every image embedded as a base64 data URI (no
external resource; it works offline). Every number shown in the HTML sits in an
element carrying ``data-value`` (the exact ``repr`` of the number also written to
the CSV and JSON) so tests and scripts can check the page against the files.

The report is built in a temporary folder beside ``out_dir`` and moved into
place only when every file was written, so an error never leaves a half-written
report; existing report files are replaced only with ``overwrite=True``.
"""

from __future__ import annotations

import base64
import contextlib
import datetime as _dt
import html
import json
import logging
import math
import os
import re
import shutil
import tempfile
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from matplotlib.figure import Figure
from numpy.typing import ArrayLike, NDArray

from rectify.atomic import current_umask, write_failure_reason
from rectify.errors import InvalidInputError, RasterIOError, RectifyError, ShapeError
from rectify.formats.report import REPORT_VERSION, read_report, report_json_text
from rectify.geometry.accuracy import check_point_statement
from rectify.geometry.crs import crs_to_string, parse_crs
from rectify.geometry.points import GcpTable
from rectify.geometry.residuals import ResidualTable
from rectify.raster.io import read_overview, to_uint8
from rectify.report.figures import (
    correlation_heatmap_figure,
    height_bars_figure,
    histogram_qq_figure,
    match_figures,
    radial_figure,
    residual_vector_figure,
)

if TYPE_CHECKING:  # annotations only: the matcher and the warp engine (OpenCV, GDAL) are not needed to report
    from rectify.features import MatchResult
    from rectify.geometry.transforms import FitResult
    from rectify.raster.georectify import GeoRectification

logger = logging.getLogger(__name__)

__all__ = [
    "REPORT_VERSION",
    "correlation_heatmap_figure",
    "format_number",
    "height_bars_figure",
    "histogram_qq_figure",
    "json_safe",
    "radial_figure",
    "residual_geojson",
    "residual_vector_figure",
    "slugify",
    "write_fit_report",
    "write_match_report",
    "write_report",
    "write_warp_report",
]

#: Linear units in which residual components can be taken as ground-frame vectors.
GROUND_UNITS = {"m", "metre", "meter", "metres", "meters", "ft", "us-ft", "foot", "feet", "km"}
_DPI = 110


# --------------------------------------------------------------------------- helpers
def slugify(text: str) -> str:
    """A file-name-safe, lower-case slug of ``text`` (``[a-z0-9_-]``, never empty).

    >>> slugify("GCP fit (homography)")
    'gcp_fit_homography'
    >>> slugify("  ")
    'table'
    """
    s = re.sub(r"[^a-z0-9]+", "_", text.lower()).strip("_")
    return s[:60] or "table"


def json_safe(obj: Any) -> Any:
    """Convert numpy scalars/arrays, tuples, paths to JSON types; NaN and inf become None.

    >>> json_safe({"a": np.float64("nan"), "b": np.arange(2), "c": (1, 2.5)})
    {'a': None, 'b': [0, 1], 'c': [1, 2.5]}
    """
    if obj is None or isinstance(obj, (bool, str)):
        return obj
    if isinstance(obj, np.bool_):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        f = float(obj)
        return f if math.isfinite(f) else None
    if isinstance(obj, np.ndarray):
        return json_safe(obj.tolist())
    if isinstance(obj, Mapping):
        return {str(k): json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple, set, frozenset)):
        return [json_safe(v) for v in obj]
    if isinstance(obj, Path):
        return str(obj)
    return str(obj)


def format_number(x: Any) -> str:
    """Text shown in the HTML for a number: 4 significant digits, ints as is, ``n/a`` for None/NaN.

    >>> format_number(0.123456), format_number(12), format_number(None), format_number(True)
    ('0.1235', '12', 'n/a', 'yes')
    """
    if x is None:
        return "n/a"
    if isinstance(x, (bool, np.bool_)):
        return "yes" if x else "no"
    if isinstance(x, (int, np.integer)):
        return str(int(x))
    f = float(x)
    if not math.isfinite(f):
        return "n/a"
    return f"{f:.4g}"


def _is_number(x: Any) -> bool:
    return isinstance(x, (int, float, np.integer, np.floating)) and not isinstance(x, (bool, np.bool_))


def _value_attr(x: Any) -> str:
    """Exact machine-readable value: repr of floats (as in the CSV), ints, '' for None/NaN."""
    if x is None:
        return ""
    if isinstance(x, (int, np.integer)) and not isinstance(x, (bool, np.bool_)):
        return str(int(x))
    f = float(x)
    return repr(f) if math.isfinite(f) else ""


def _flatten(d: Mapping[str, Any], prefix: str = "") -> list[tuple[str, Any]]:
    out: list[tuple[str, Any]] = []
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, Mapping):
            out.extend(_flatten(v, key + "."))
        else:
            out.append((key, v))
    return out


# --------------------------------------------------------------------------- GeoJSON
def _ground_vectors(table: ResidualTable, ground: NDArray[np.float64]) -> NDArray[np.float64] | None:
    """Residual vectors in the ground frame, (N, 2) in CRS units, or None when unknown."""
    k = table.residual.shape[1]
    if k < 2:
        return None
    if table.units.strip().lower() in GROUND_UNITS:
        return table.residual[:, :2].copy()
    if table.units.strip().lower() == "px" and table.position_px is not None:
        ok = np.all(np.isfinite(table.position_px), axis=1) & np.all(np.isfinite(ground), axis=1)
        if ok.sum() >= 3:
            a = np.column_stack([table.position_px[ok], np.ones(int(ok.sum()))])
            coef, _, rank, _ = np.linalg.lstsq(a, ground[ok], rcond=None)
            if rank == 3:
                lin = coef[:2].T  # (2, 2): ground d(X, Y) per pixel d(col, row)
                return table.residual[:, :2] @ lin.T
    return None


def residual_geojson(table: ResidualTable, ground_xy: ArrayLike, crs: Any, *,
                     exaggeration: float | None = None) -> dict[str, Any]:
    """Residual vectors of ``table`` as a GeoJSON FeatureCollection in ``crs``.

    Parameters
    ----------
    table : ResidualTable
    ground_xy : (N, 2) array_like
        Ground coordinates (x = easting, y = northing, CRS units) of each point.
    crs : str or CRS
        Ground CRS (``"EPSG:nnnn"`` or WKT); stored in the legacy ``crs`` member,
        which QGIS/GDAL read.
    exaggeration : float, optional
        Factor applied to the residual vectors drawn as lines; by default chosen so
        the 95th-percentile vector spans 5 % of the points' extent.

    Returns
    -------
    dict
        FeatureCollection of LineString features (from the point along the
        exaggerated residual) when the residual can be expressed in ground units
        (tables in metres/feet, or in pixels with ``position_px`` from which the
        local pixel-to-ground affine map is fitted), Point features otherwise.
        Properties: id, step, units, the components, norm, normalised, weight,
        outlier, check, and for lines ``v_ground_x``/``v_ground_y`` (CRS units)
        and ``exaggeration``.

    Raises
    ------
    ShapeError
        If ``ground_xy`` is not (N, 2).
    CRSError
        If ``crs`` is unknown.
    """

    g = np.asarray(ground_xy, dtype=np.float64)
    if g.shape != (table.n, 2):
        raise ShapeError(f"`ground_xy` for {table.step!r} must have shape ({table.n}, 2); got {g.shape}",
                         actual_shape=g.shape, expected_shape=(table.n, 2))
    c = parse_crs(crs)
    auth = c.to_authority(min_confidence=100)
    crs_name = f"urn:ogc:def:crs:{auth[0]}::{auth[1]}" if auth else c.to_wkt()
    vg = _ground_vectors(table, g)
    ex = None
    if vg is not None:
        lens = np.hypot(vg[:, 0], vg[:, 1])
        fin = np.isfinite(lens) & np.all(np.isfinite(g), axis=1)
        if exaggeration is None:
            ext = float(np.ptp(g[fin], axis=0).max()) if fin.sum() > 1 else 1.0
            ref = float(np.percentile(lens[fin], 95)) if fin.any() else 0.0
            ex = 0.05 * ext / ref if ref > 0 and ext > 0 else 1.0
        else:
            ex = float(exaggeration)
    v, nrm, nz = table.residual, table.norm, table.normalised
    weights, outlier, check = (np.asarray(a) for a in (table.weights, table.outlier, table.check))
    feats = []
    for i in range(table.n):
        props: dict[str, Any] = {"id": table.ids[i], "step": table.step, "units": table.units}
        for j, name in enumerate(table.components):
            props[name] = v[i, j]
        props.update(norm=nrm[i], normalised=nz[i], weight=weights[i],
                     outlier=bool(outlier[i]), check=bool(check[i]))
        x, y = float(g[i, 0]), float(g[i, 1])
        geom: dict[str, Any]
        if vg is not None and ex is not None and np.all(np.isfinite(vg[i])):
            props.update(v_ground_x=vg[i, 0], v_ground_y=vg[i, 1], exaggeration=ex)
            geom = {"type": "LineString",
                    "coordinates": [[x, y], [x + ex * float(vg[i, 0]), y + ex * float(vg[i, 1])]]}
        else:
            geom = {"type": "Point", "coordinates": [x, y]}
        feats.append({"type": "Feature", "geometry": geom, "properties": json_safe(props)})
    return {
        "type": "FeatureCollection",
        "name": slugify(table.step),
        "crs": {"type": "name", "properties": {"name": crs_name}},
        "rectify": json_safe({"step": table.step, "units": table.units, "crs": crs_to_string(c),
                              "exaggeration": ex,
                              "note": "lines run from the point along the residual v = adjusted - observed, "
                                      "multiplied by `exaggeration`"}),
        "features": feats,
    }


# --------------------------------------------------------------------------- planning
@dataclass
class _TablePlan:
    table: ResidualTable
    slug: str
    files: dict[str, str] = field(default_factory=dict)


def _plan(tables: Sequence[ResidualTable], figures: Mapping[str, Figure], ground: Mapping[str, Any]
          ) -> tuple[list[_TablePlan], dict[str, str]]:
    used: set[str] = {"report"}
    plans = []

    def unique(base: str) -> str:
        s, i = base, 2
        while s in used:
            s, i = f"{base}_{i}", i + 1
        used.add(s)
        return s

    for t in tables:
        p = _TablePlan(t, unique(slugify(t.step)))
        p.files["csv"] = f"{p.slug}.csv"
        if t.n:
            p.files["distribution"] = f"{p.slug}_distribution.png"
            if t.position_px is not None:
                p.files["vectors"] = f"{p.slug}_vectors.png"
                p.files["radial"] = f"{p.slug}_radial.png"
        if t.step in ground:
            p.files["geojson"] = f"{p.slug}.geojson"
        plans.append(p)
    fig_files = {name: f"{unique('fig_' + slugify(name))}.png" for name in figures}
    return plans, fig_files


def _validate(out_dir: Any, title: Any, tables: Any, figures: Any, summary: Any, crs: Any,
              ground_xy: Any, backgrounds: Any, image_shapes: Any, principal_point_px: Any) -> Path:
    if not isinstance(title, str) or not title.strip():
        raise InvalidInputError(f"`title` must be a non-empty string; got {title!r}")
    if isinstance(tables, ResidualTable) or not isinstance(tables, (list, tuple)):
        raise InvalidInputError(f"`tables` must be a list of ResidualTable; got {type(tables).__name__}")
    for i, t in enumerate(tables):
        if not isinstance(t, ResidualTable):
            raise InvalidInputError(f"`tables[{i}]` must be a ResidualTable; got {type(t).__name__}")
    if figures is not None:
        if not isinstance(figures, Mapping):
            raise InvalidInputError(f"`figures` must be a dict name -> Figure; got {type(figures).__name__}")
        for k, f in figures.items():
            if not isinstance(k, str) or not k.strip():
                raise InvalidInputError(f"figure names must be non-empty strings; got {k!r}")
            if not isinstance(f, Figure):
                raise InvalidInputError(f"`figures[{k!r}]` must be a matplotlib Figure; got {type(f).__name__}")
    if not tables and not figures:
        raise InvalidInputError("nothing to report: `tables` and `figures` are both empty")
    if summary is not None and not isinstance(summary, Mapping):
        raise InvalidInputError(f"`summary` must be a dict; got {type(summary).__name__}")
    steps = [t.step for t in tables]
    if (crs is None) != (ground_xy is None):
        raise InvalidInputError("`crs` and `ground_xy` go together: got "
                                f"crs={crs!r} and ground_xy={'None' if ground_xy is None else 'a dict'}")
    for name, m in (("ground_xy", ground_xy), ("backgrounds", backgrounds), ("image_shapes", image_shapes)):
        if m is None:
            continue
        if not isinstance(m, Mapping):
            raise InvalidInputError(f"`{name}` must be a dict step -> value; got {type(m).__name__}")
        unknown = [k for k in m if k not in steps]
        if unknown:
            raise InvalidInputError(f"`{name}` names unknown steps {unknown}; tables are {steps}")
    if isinstance(principal_point_px, Mapping):
        unknown = [k for k in principal_point_px if k not in steps]
        if unknown:
            raise InvalidInputError(f"`principal_point_px` names unknown steps {unknown}; tables are {steps}")
    if ground_xy is not None:
        for t in tables:
            if t.step in ground_xy:
                g = np.asarray(ground_xy[t.step], dtype=np.float64)
                if g.shape != (t.n, 2):
                    raise ShapeError(f"`ground_xy[{t.step!r}]` must have shape ({t.n}, 2); got {g.shape}",
                                     actual_shape=g.shape, expected_shape=(t.n, 2))

        parse_crs(crs)
    if out_dir is None or (isinstance(out_dir, str) and not out_dir.strip()):
        raise InvalidInputError(f"`out_dir` must be a folder path; got {out_dir!r}")
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise InvalidInputError(f"report folder {str(out)!r} exists and is not a folder")
    return out


def _principal_point(t: ResidualTable, pp: Any, shape: Sequence[int] | None) -> tuple[NDArray, str]:
    if isinstance(pp, Mapping):
        pp = pp.get(t.step)
    if pp is not None:
        return np.asarray(pp, dtype=np.float64).reshape(-1), "principal point"
    if shape is not None:
        h, w = int(shape[0]), int(shape[1])
        return np.array([(w - 1) / 2.0, (h - 1) / 2.0]), "image centre (assumed principal point)"
    pp_all = np.asarray(t.position_px, dtype=np.float64).reshape(-1, 2)
    pos = pp_all[np.all(np.isfinite(pp_all), axis=1)]
    if len(pos):
        return 0.5 * (pos.min(axis=0) + pos.max(axis=0)), "centre of the points' extent (assumed principal point)"
    return np.zeros(2), "origin"


def _in_ground_units(t: ResidualTable) -> bool:
    return t.units.strip().lower() in GROUND_UNITS and t.residual.shape[1] >= 2


def _vector_figure(t: ResidualTable, shape: Sequence[int] | None, bg: Any, ground: Any, crs: Any) -> Figure:
    """The standard vector plot: image frame, or map frame for ground-unit residuals with ground positions.

    Residuals in ground units (m, ft) are map-frame components (x east, y north). With the points'
    ground coordinates they are drawn at those positions on north-up map axes, which is exact;
    without them they are drawn over the image with the second component pointing up
    (an approximately north-up image is assumed, and the title says so).
    """
    if not _in_ground_units(t):
        return residual_vector_figure(t, image_shape=shape, background=bg)
    if ground is not None:

        axis = parse_crs(crs).axis_info
        unit = axis[0].unit_name if axis else t.units
        unit = {"metre": "m", "meter": "m", "US survey foot": "us-ft", "foot": "ft"}.get(unit, unit)
        return residual_vector_figure(
            t, positions=np.asarray(ground, dtype=np.float64), position_units=unit, y_down=False,
            title=f"{t.step}: residual vectors ({t.components[0]}, {t.components[1]}) at the ground positions")
    return residual_vector_figure(
        t, image_shape=shape, background=bg, components_y_up=True,
        title=f"{t.step}: map-frame residuals ({t.components[0]} east, {t.components[1]} north) over the image "
              "(north assumed up)")


def _save(fig: Figure, path: Path) -> None:
    fig.savefig(path, dpi=_DPI, format="png")


# --------------------------------------------------------------------------- HTML
_CSS = """
body{font-family:-apple-system,Segoe UI,Helvetica,Arial,sans-serif;margin:0;color:#222;background:#fafafa}
header{background:#243447;color:#fff;padding:16px 28px}
header h1{margin:0 0 4px 0;font-size:22px} header p{margin:2px 0;font-size:13px;color:#cfd8e3}
nav{padding:8px 28px;background:#e8edf3;font-size:13px} nav a{margin-right:14px;color:#243447}
main{padding:8px 28px 40px 28px;max-width:1200px}
section{background:#fff;border:1px solid #dde3ea;border-radius:6px;padding:12px 18px;margin:16px 0}
h2{font-size:18px;margin:4px 0 10px 0;color:#243447} h3{font-size:15px;margin:14px 0 6px 0}
table{border-collapse:collapse;font-size:12.5px;margin:6px 0}
th,td{border:1px solid #d5dbe2;padding:3px 8px;text-align:right} th{background:#f0f3f7}
td.l,th.l{text-align:left}
tr.outlier td{background:#fde2e2} tr.check td{background:#e3eefb}
figure{margin:10px 0} figure img{max-width:100%;height:auto;border:1px solid #e3e7ec}
figcaption{font-size:12px;color:#555}
.defs{font-size:12.5px;color:#444;background:#f6f8fa;padding:6px 10px;border-left:3px solid #8aa1bd}
.warn{background:#fff3cd;border:1px solid #e0c46c;padding:8px 12px;display:none}
.scroll{max-height:520px;overflow:auto}
"""

_SCRIPT = """
(function(){
  function check(){
    var imgs=document.querySelectorAll('img'), ok=0, bad=[];
    for(var i=0;i<imgs.length;i++){
      if(imgs[i].complete && imgs[i].naturalWidth>0){ok++;} else {bad.push(imgs[i].getAttribute('data-file'));}
    }
    document.body.setAttribute('data-images-total', String(imgs.length));
    document.body.setAttribute('data-images-decoded', String(ok));
    var secs=document.querySelectorAll('section[data-section]');
    for(var j=0;j<secs.length;j++){
      var r=secs[j].getBoundingClientRect();
      secs[j].setAttribute('data-rendered', (r.height>0 && r.width>0) ? 'yes' : 'no');
    }
    if(bad.length){
      var w=document.getElementById('render-warning');
      w.style.display='block'; w.textContent='Images that failed to decode: '+bad.join(', ');
      console.error('report: images failed to decode: '+bad.join(', '));
    }
    document.body.setAttribute('data-render-check','done');
  }
  if(document.readyState==='complete'){check();} else {window.addEventListener('load', check);}
})();
"""


def _td(x: Any, *, scope: str, key: str, cls: str = "") -> str:
    c = f' class="{cls}"' if cls else ""
    if _is_number(x) or x is None:
        return (f'<td{c} data-scope="{html.escape(scope)}" data-key="{html.escape(key)}" '
                f'data-value="{_value_attr(x)}">{format_number(x)}</td>')
    if isinstance(x, (bool, np.bool_)):
        return f'<td{c} data-scope="{html.escape(scope)}" data-key="{html.escape(key)}">{format_number(x)}</td>'
    return f'<td class="l" data-scope="{html.escape(scope)}" data-key="{html.escape(key)}">{html.escape(str(x))}</td>'


def _img(path: Path, name: str, caption: str) -> str:
    data = base64.b64encode(path.read_bytes()).decode("ascii")
    return (f'<figure><img alt="{html.escape(caption)}" data-file="{html.escape(name)}" '
            f'src="data:image/png;base64,{data}"><figcaption>{html.escape(caption)} '
            f'(<code>{html.escape(name)}</code>)</figcaption></figure>')


_SUMMARY_COLS = [
    ("n_points", "points"), ("n_fit", "fit"), ("n_check", "check"), ("n_outliers", "outliers"),
    ("n_params", "parameters"), ("rmse", "RMSE fit"), ("rmse_check", "RMSE check"),
    ("sigma0", "sigma0"), ("max_abs", "max |v| fit"),
]
_CAPTIONS = {
    "vectors": "Residual vectors over the image (arrow scale in the key; colour = normalised residual; "
               "x = outlier, triangle = check point)",
    "distribution": "Histogram of normalised residuals and normal Q-Q plot of standardised components",
    "radial": "Residuals against radial distance from the principal point",
}
_DEFS = ("<p class='defs'><b>RMSE</b> = sqrt(mean |v|&sup2;) over the fit points (check points and outliers "
         "excluded; <b>RMSE check</b> over the check points), in the table's units. "
         "<b>sigma0</b> = sqrt(v&#7488;Pv / (n&middot;k &minus; u)), the a-posteriori standard deviation of "
         "unit weight (n fit points, k components, u parameters), in the same units when the weights are 1. "
         "Residual v = adjusted &minus; observed. <b>Normalised residual</b> = |v| / &sigma; "
         "(&sigma; = the point's standard deviation, or sigma0).</p>")


def _html(title: str, created: str, crs: str | None, plans: list[_TablePlan], summaries: list[dict],
          fig_files: dict[str, str], caller_summary: Mapping[str, Any] | None, tmp: Path,
          files: list[str], max_rows: int) -> str:
    e = html.escape
    parts = [("<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'>"
              "<meta name='viewport' content='width=device-width, initial-scale=1'>"
              f"<title>{e(title)}</title><style>{_CSS}</style></head>"
              f"<body data-report-version='{REPORT_VERSION}'>")]
    parts.append(f"<header><h1>{e(title)}</h1><p>Residual QA report, created {e(created)} UTC"
                 + (f" &middot; ground CRS <code>{e(crs)}</code>" if crs else "") + "</p></header>")
    nav = ["<a href='#overview'>Overview</a>"]
    nav += [f"<a href='#t-{p.slug}'>{e(p.table.step)}</a>" for p in plans]
    if fig_files:
        nav.append("<a href='#figures'>Figures</a>")
    if caller_summary:
        nav.append("<a href='#summary'>Summary</a>")
    nav.append("<a href='#files'>Files</a>")
    parts.append("<nav>" + "".join(nav) + "</nav><main><div id='render-warning' class='warn'></div>")

    # overview
    parts.append("<section id='overview' data-section='overview'><h2>Overview</h2>")
    if plans:
        parts.append("<table class='overview'><thead><tr><th class='l'>step</th><th class='l'>units</th>"
                     + "".join(f"<th>{e(lab)}</th>" for _, lab in _SUMMARY_COLS) + "</tr></thead><tbody>")
        for p, s in zip(plans, summaries, strict=True):
            parts.append(f"<tr data-step='{p.slug}'><td class='l'><a href='#t-{p.slug}'>{e(p.table.step)}</a></td>"
                         f"<td class='l' data-scope='{p.slug}' data-key='units'>{e(p.table.units)}</td>"
                         + "".join(_td(s.get(k), scope=p.slug, key=k) for k, _ in _SUMMARY_COLS) + "</tr>")
        parts.append("</tbody></table>")
    else:
        parts.append("<p>No residual tables in this report.</p>")
    parts.append(_DEFS + "</section>")

    # per table
    for p, s in zip(plans, summaries, strict=True):
        t = p.table
        parts.append(f"<section id='t-{p.slug}' data-section='table-{p.slug}'><h2>{e(t.step)}</h2>")
        parts.append(f"<p>Residual v = adjusted &minus; observed, in <b>{e(t.units)}</b>; components "
                     f"{e(', '.join(t.components))}. Full table: <a href='{e(p.files['csv'])}'>"
                     f"{e(p.files['csv'])}</a>.</p>")
        unit_keys = {"rmse", "rmse_check", "sigma0", "max_abs"} | {f"rmse_{c}" for c in t.components}
        rows = []
        for k, v in _flatten(s):
            if k in ("step", "units"):
                continue
            label = f"{k} ({t.units})" if k in unit_keys else k
            rows.append(f"<tr><th class='l'>{e(label)}</th>{_td(v, scope=p.slug, key=k)}</tr>")
        parts.append("<h3>Summary</h3><table class='summary'>" + "".join(rows) + "</table>")
        for kind in ("vectors", "distribution", "radial"):
            if kind in p.files:
                parts.append(_img(tmp / p.files[kind], p.files[kind], _CAPTIONS[kind]))
        # residual rows, worst first
        nrows = t.n
        order = np.argsort(-np.nan_to_num(t.normalised, nan=-1.0), kind="stable")[:max_rows]
        table_rows = t.rows()
        cols = list(table_rows[0]) if table_rows else []
        parts.append(f"<h3>Residuals ({min(nrows, max_rows)} of {nrows} rows, largest normalised residual "
                     f"first)</h3><div class='scroll'><table class='residuals' data-step='{p.slug}'><thead><tr>"
                     + "".join(f"<th{' class=l' if c == 'id' else ''}>{e(c)}</th>" for c in cols)
                     + "</tr></thead><tbody>")
        for i in order:
            r = table_rows[int(i)]
            cls = "outlier" if r["outlier"] else ("check" if r["check"] else "")
            cells = []
            for c in cols:
                if c == "id":
                    cells.append(f"<td class='l'>{e(str(r[c]))}</td>")
                else:
                    cells.append(_td(r[c], scope=f"{p.slug}#{int(i)}", key=c))
            parts.append(f"<tr data-row='{int(i)}' data-id='{e(str(r['id']))}'"
                         + (f" class='{cls}'" if cls else "") + ">" + "".join(cells) + "</tr>")
        parts.append("</tbody></table></div>")
        if "geojson" in p.files:
            parts.append(f"<p>Residual vectors for QGIS: <a href='{e(p.files['geojson'])}'>"
                         f"{e(p.files['geojson'])}</a> (ground CRS {e(crs or '')}).</p>")
        parts.append("</section>")

    if fig_files:
        parts.append("<section id='figures' data-section='figures'><h2>Figures</h2>")
        for name, fn in fig_files.items():
            parts.append(_img(tmp / fn, fn, name))
        parts.append("</section>")
    if caller_summary:
        parts.append("<section id='summary' data-section='summary'><h2>Summary</h2><table class='caller'>")
        for k, v in _flatten(json_safe(caller_summary)):
            if isinstance(v, list):
                cell = (f"<td class='l' data-scope='summary' data-key='{e(k)}' "
                        f"data-json='{e(json.dumps(v))}'>{e(json.dumps(v))}</td>")
            else:
                cell = _td(v, scope="summary", key=k)
            parts.append(f"<tr><th class='l'>{e(k)}</th>{cell}</tr>")
        parts.append("</table></section>")
    parts.append("<section id='files' data-section='files'><h2>Files</h2><ul>"
                 + "".join(f"<li><a href='{e(f)}'>{e(f)}</a></li>" for f in files)
                 + "</ul></section>")
    parts.append(f"</main><script>{_SCRIPT}</script></body></html>")
    return "\n".join(parts)


# --------------------------------------------------------------------------- main entry
def write_report(out_dir: str | os.PathLike, *, title: str, tables: list[ResidualTable],
                 figures: dict[str, Figure] | None = None, summary: dict | None = None,
                 crs: str | None = None, ground_xy: Mapping[str, ArrayLike] | None = None,
                 overwrite: bool = False, backgrounds: dict[str, ArrayLike] | None = None,
                 image_shapes: dict[str, Sequence[int]] | None = None,
                 principal_point_px: ArrayLike | dict[str, ArrayLike] | None = None,
                 html_max_rows: int = 500) -> Path:
    """Write the QA report of a run into ``out_dir``; return the path of ``report.html``.

    Parameters
    ----------
    out_dir : path
        Report folder; created (with parents) when absent. Existing report files
        in it are replaced only with ``overwrite``.
    title : str
        Page title, e.g. ``"rectify demo: Landsat GCP fit"``.
    tables : list of ResidualTable
        One per estimation step; their ``step`` names must be unique (file names
        are slugs of them, de-duplicated).
    figures : dict name -> matplotlib Figure, optional
        Extra figures (e.g. a correlation heat map), saved as ``fig_<name>.png``
        and embedded. They are not closed.
    summary : dict, optional
        Run-level facts (parameters, timings, transform) added to ``report.json``
        under ``"summary"`` and shown as a table; numpy values are converted.
    crs : str, optional
        Ground CRS (``"EPSG:nnnn"`` or WKT); with ``ground_xy`` it makes one
        GeoJSON per listed table.
    ground_xy : dict step -> (N, 2) array_like, optional
        Ground coordinates (x, y in ``crs`` units) of each point of that table.
    overwrite : bool
        Replace existing report files.
    backgrounds : dict step -> image array, optional
        Image drawn under that table's residual vectors.
    image_shapes : dict step -> (H, W), optional
        Image size for the vector plot frame and the default principal point.
    principal_point_px : (2,) array_like or dict step -> (2,), optional
        Principal point (x, y) in pixels for the radial plot; default the image
        centre when the image size is known, else the centre of the points' extent.
    html_max_rows : int
        Residual rows shown per table in the HTML (largest normalised first);
        the CSV always holds all rows.

    Returns
    -------
    pathlib.Path
        ``out_dir / "report.html"``.

    Raises
    ------
    InvalidInputError
        Bad arguments, or report files exist in ``out_dir`` and ``overwrite`` is false.
    ShapeError
        A ``ground_xy`` entry is not (N, 2).
    CRSError
        ``crs`` is unknown.
    RasterIOError
        The folder cannot be created or written.
    """
    out = _validate(out_dir, title, tables, figures, summary, crs, ground_xy, backgrounds, image_shapes,
                    principal_point_px)
    if not isinstance(html_max_rows, (int, np.integer)) or html_max_rows < 0:
        raise InvalidInputError(f"`html_max_rows` must be a non-negative integer; got {html_max_rows!r}")
    tables = list(tables)
    figures = dict(figures or {})
    ground = dict(ground_xy or {})
    backgrounds = dict(backgrounds or {})
    image_shapes = dict(image_shapes or {})
    plans, fig_files = _plan(tables, figures, ground)
    files = [f for p in plans for f in p.files.values()] + list(fig_files.values()) + ["report.json", "report.html"]
    previous: list[str] = []
    if out.is_dir():
        clash = sorted(f for f in files if (out / f).exists())
        if clash and not overwrite:
            raise InvalidInputError(f"report folder {str(out)!r} already holds {clash[:5]}"
                                    f"{' ...' if len(clash) > 5 else ''}; pass overwrite=True (--overwrite)")
        with contextlib.suppress(OSError, ValueError, TypeError, AttributeError, KeyError):
            previous = [str(f) for f in read_report(out)["files"]]
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".part", dir=out.parent))
        os.chmod(tmp, 0o777 & ~current_umask())  # mkdtemp makes it private; the report folder is an ordinary one
    except OSError as err:
        raise RasterIOError(f"cannot create report folder beside {str(out)!r}: {err}") from err
    created = _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%d %H:%M:%S")
    crs_text = None
    try:
        if crs is not None:

            crs_text = crs_to_string(crs)
        summaries = []
        for p in plans:
            t = p.table
            (tmp / p.files["csv"]).write_text(t.to_csv())
            shape = image_shapes.get(t.step)
            bg = backgrounds.get(t.step)
            if bg is not None and shape is None:
                shape = np.asarray(bg).shape[:2]
            if "vectors" in p.files:
                _save(_vector_figure(t, shape, bg, ground.get(t.step), crs), tmp / p.files["vectors"])
            if "distribution" in p.files:
                _save(histogram_qq_figure(t), tmp / p.files["distribution"])
            if "radial" in p.files:
                pp, what = _principal_point(t, principal_point_px, shape)
                title = f"{t.step}: residuals vs distance from the {what} ({pp[0]:.1f}, {pp[1]:.1f}) px"
                _save(radial_figure(t, pp, components_y_up=_in_ground_units(t), title=title), tmp / p.files["radial"])
            if "geojson" in p.files:
                gj = residual_geojson(t, ground[t.step], crs)
                (tmp / p.files["geojson"]).write_text(json.dumps(gj, allow_nan=False))
            summaries.append(json_safe(t.summary()))
        for name, fn in fig_files.items():
            _save(figures[name], tmp / fn)
        caller = json_safe(summary) if summary else {}
        doc = {
            "title": title,
            "created_utc": created,
            "crs": crs_text,
            "tables": [{"step": p.table.step, "slug": p.slug, "units": p.table.units,
                        "components": list(p.table.components), "summary": s, "files": p.files}
                       for p, s in zip(plans, summaries, strict=True)],
            "figures": fig_files,
            "summary": caller,
            "files": files,
        }
        (tmp / "report.json").write_text(report_json_text(doc))
        (tmp / "report.html").write_text(_html(title, created, crs_text, plans, summaries, fig_files,
                                               caller, tmp, files, int(html_max_rows)), encoding="utf-8")
        _commit(tmp, out, files, previous, overwrite)
    except OSError as err:
        shutil.rmtree(tmp, ignore_errors=True)
        if isinstance(err, RectifyError):
            raise
        raise RasterIOError(f"cannot write the report {str(out)!r}: {write_failure_reason(err, out)}") from err
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    logger.info("report written to %s (%d tables, %d figures)", out, len(plans), len(fig_files))
    return out / "report.html"


def _commit(tmp: Path, out: Path, files: list[str], previous: list[str], overwrite: bool) -> None:
    """Move the finished report from ``tmp`` into ``out`` (one rename when ``out`` is new)."""
    try:
        if not out.exists():
            os.rename(tmp, out)
            return
        clash = [f for f in files if (out / f).exists()]
        if clash and not overwrite:
            raise InvalidInputError(f"report files {clash[:5]} appeared in {str(out)!r} while writing; "
                                    "pass overwrite=True (--overwrite)")
        # report.html last: a reader never sees a page whose files are missing
        for f in sorted(files, key=lambda f: f == "report.html"):
            os.replace(tmp / f, out / f)
        for f in previous:
            if f not in files and "/" not in f and not f.startswith("."):
                with contextlib.suppress(OSError):
                    (out / f).unlink()
        tmp.rmdir()
    except OSError as err:
        raise RasterIOError(f"cannot move the report into {str(out)!r}: {err}") from err


# --------------------------------------------------------------------------- the reports of the rectify steps
def write_match_report(report_dir: str | os.PathLike, result: MatchResult, left: str | os.PathLike,
                       right: str | os.PathLike, *, overwrite: bool = False) -> Path:
    """The report of ``rectify match``: verification residuals, matches over both images, match density.

    Parameters
    ----------
    report_dir : path
    result : rectify.features.MatchResult
    left, right : path
        The matched rasters; overviews of at most 1024 px are drawn under the matches.

    Returns
    -------
    Path of ``report.html``.
    """
    previews = []
    for p in (left, right):
        data, valid, scale = read_overview(os.fspath(p), 1024)
        previews.append((to_uint8(data, valid), scale))
    figs = match_figures(result, previews[0], previews[1])
    tables = [result.verification.table] if result.verification.table is not None else []
    return write_report(report_dir, title=f"rectify match: {left} / {right}", tables=tables, figures=figs,
                        summary={**result.summary(), "left": str(left), "right": str(right)}, overwrite=overwrite,
                        image_shapes={t.step: result.image_shapes[0] for t in tables})


def write_fit_report(report_dir: str | os.PathLike, result: FitResult, gcps: GcpTable, *,
                     gcps_path: str | os.PathLike, transform_path: str | os.PathLike,
                     overwrite: bool = False) -> Path:
    """The report of ``rectify fit``: the GCP residual table (target units), with GeoJSON when the GCPs have a CRS.

    Returns
    -------
    Path of ``report.html``.
    """
    table = result.table
    s = table.summary()
    ground = {table.step: gcps.target} if gcps.crs else None
    acc = check_point_statement(table)
    extra = {} if acc is None else {"accuracy_statement": acc.to_dict()}
    return write_report(report_dir, title=f"rectify fit: {result.method} on {gcps_path}", tables=[table],
                        summary={"method": result.method, "gcps": str(gcps_path), "transform": str(transform_path),
                                 **{k: v for k, v in s.items() if k != "step"}, **extra},
                        crs=gcps.crs, ground_xy=ground, overwrite=overwrite)


def write_warp_report(report_dir: str | os.PathLike, result: GeoRectification, *, source_shape: tuple[int, int],
                      title: str = "rectify warp", summary: dict | None = None, background: ArrayLike | None = None,
                      overwrite: bool = False) -> Path:
    """The report of ``rectify warp --gcps`` and the demo: GCP residual table, vectors over the image, grid.

    Parameters
    ----------
    report_dir : path
    result : rectify.raster.georectify.GeoRectification
        With a ``fit`` (GCP runs); check points are reported separately by the table.
    source_shape : (H, W)
        Source image size, for the residual-vector plot frame.
    summary : dict, optional
        More run-level facts.
    background : (H, W[, C]) array, optional
        Image drawn under the vectors (e.g. a decimated source).

    Returns
    -------
    Path of ``report.html``.
    """
    if result.fit is None:
        raise InvalidInputError("a report needs a GCP fit (use --gcps)")
    t = result.fit.table
    fig = residual_vector_figure(t, source_shape, background, title=f"GCP residuals ({result.method}), {t.units}")
    info = {"method": result.method, "output": str(result.warp.path), "crs": result.crs,
            "grid_width": result.warp.grid.width, "grid_height": result.warp.grid.height,
            "resolution": result.warp.grid.resolution[0], "seconds": round(result.warp.seconds, 3),
            "invalid_pixels_as": result.warp.policy}
    info.update(summary or {})
    return write_report(report_dir, title=title, tables=[t], figures={"gcp_residual_vectors": fig},
                        summary=info, crs=result.crs, ground_xy={t.step: t.observed} if result.crs else None,
                        overwrite=overwrite)
