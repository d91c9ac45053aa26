"""The report of ``rectify ortho --report DIR``: an HTML page, summary JSON, GCP residuals and the relief-shift map.

Through :func:`rectify.report.builder.write_report`: ``report.html`` (one self-contained page: the run's
facts, the GCP residual table with its figures, the relief-shift map), ``report.json`` and the table's
CSV and figures. Beside them: ``ortho_report.json`` (the run's summary lines, the heights and their
datums, the DEM and its heights on the output, the relief displacement the DEM removed, the GCP
residual summary), ``residuals.csv`` (with GCPs) and ``relief_shift.tif`` (the map of
:class:`rectify.raster.ortho.ReliefShift`, a coarse float32 GeoTIFF in the output CRS, NaN where the
orthophoto has no data). The relief figures are the ones printed on the console: both come from
``result.relief``.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure

from rectify.atomic import atomic_write_text
from rectify.errors import InvalidInputError
from rectify.geometry.residuals import ResidualTable
from rectify.raster.dem import Dem
from rectify.raster.io import write_raster
from rectify.raster.ortho import OrthoResult, ReliefShift
from rectify.report.builder import json_safe, write_report

__all__ = ["write_ortho_report", "relief_figure"]


def relief_figure(relief: ReliefShift) -> Figure:
    """The relief-shift map (m) over the output grid, with its colour bar and figures."""
    fig = Figure(figsize=(6.4, 5.2))
    ax = fig.add_subplot(1, 1, 1)
    m = relief.map
    t = relief.transform
    h, w = m.shape
    extent = (t.c, t.c + t.a * w, t.f + t.e * h, t.f)
    im = ax.imshow(np.ma.masked_invalid(m), extent=extent, cmap="viridis", interpolation="nearest")
    fig.colorbar(im, ax=ax, label="relief displacement removed (m)")
    ax.set_title(f"DEM vs a plane at {relief.h_ref:.1f} m: median {relief.median:.2f} m, max {relief.max:.2f} m"
                 if relief.n_cells else "no valid output cell", fontsize=9)
    ax.ticklabel_format(useOffset=False, style="plain")
    ax.set_xlabel("x (output CRS)")
    ax.set_ylabel("y (output CRS)")
    fig.tight_layout()
    return fig


def _num(v: Any) -> Any:
    return None if isinstance(v, float) and not math.isfinite(v) else v


def write_ortho_report(report_dir: str | Path, result: OrthoResult, residuals: ResidualTable | None,
                       summary: list[str], model: Any, dem: Dem, *, overwrite: bool = False,
                       heights: Mapping[str, Any] | None = None, gcp_ground: Mapping[str, Any] | None = None
                       ) -> list[Path]:
    """``report.html`` (with ``report.json``), ``ortho_report.json``, ``residuals.csv`` and ``relief_shift.tif``.

    Each file is written atomically into ``report_dir`` (created when missing).

    Parameters
    ----------
    result : OrthoResult
        What :func:`rectify.raster.ortho.orthorectify` wrote (its ``relief`` gives the map and figures).
    residuals : ResidualTable or None
        The GCP residuals (px), when GCPs were given.
    summary : list of str
        The run's summary lines (as printed by ``rectify ortho``).
    model, dem
        The sensor model and DEM of the run.
    heights : dict, optional
        The height datums of the run (DEM, GCPs, the model's heights), as statements.
    gcp_ground : dict, optional
        The GCP errors on the ground (m): leave-one-out and check point figures.
    """
    d = Path(report_dir)
    if d.exists() and not d.is_dir():
        raise InvalidInputError(f"report folder {str(d)!r} is a file")
    r = result
    relief = r.relief
    if relief is None:
        raise InvalidInputError("the orthophoto result has no relief figures (made by orthorectify)")
    rs: dict[str, Any] = {"max": _num(relief.max), "mean": _num(relief.mean), "map": "relief_shift.tif",
                          **relief.to_dict()}
    doc: dict[str, Any] = {
        "output": str(r.path), "model": r.model, "crs": r.grid.crs, "width": r.grid.width, "height": r.grid.height,
        "resolution": r.grid.resolution[0],
        "dem": {"path": r.dem_path, "datum": dem.datum, "undulation_m": dem.undulation, "geoid": dem.geoid,
                "declared_vertical": None if dem.declared is None else dem.declared.label,
                "heights_on_output_m": [_num(v) for v in r.dem_range]},
        "heights": dict(heights or {}),
        "relief_shift_removed": rs,
        "occluded_pixels": r.n_occluded, "seconds": r.seconds, "summary": summary}
    if residuals is not None:
        doc["gcp_residuals"] = residuals.summary()
    if gcp_ground:
        doc["gcp_ground_errors"] = dict(gcp_ground)
    facts: dict[str, Any] = {"output": str(r.path), "model": r.model, "crs": r.grid.crs,
                             "size_px": f"{r.grid.width} x {r.grid.height}", "resolution": r.grid.resolution[0],
                             "dem": r.dem_path, "dem_heights": dem.datum, **{f"heights_{k}": v for k, v in
                                                                             (heights or {}).items()},
                             "relief_shift": relief.summary_line(), "summary": " | ".join(summary)}
    fig = relief_figure(relief)
    out = [write_report(d, title=f"rectify ortho: {r.path.name}", tables=[] if residuals is None else [residuals],
                        figures={"relief_shift": fig}, summary=facts, overwrite=overwrite)]
    if residuals is not None:
        out.append(atomic_write_text(d / "residuals.csv", residuals.to_csv(), overwrite=overwrite))
    out.append(write_raster(d / "relief_shift.tif", relief.map.astype(np.float32), relief.transform, r.grid.crs,
                            nodata=float("nan"), valid=np.isfinite(relief.map), overwrite=overwrite))
    out.append(atomic_write_text(d / "ortho_report.json", json.dumps(json_safe(doc), indent=2, default=str) + "\n",
                                 overwrite=overwrite))
    return out
