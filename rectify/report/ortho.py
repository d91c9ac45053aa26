"""The report of ``rectify ortho --report DIR``: summary JSON, GCP residuals and the relief-shift map.

``ortho_report.json`` (the run's summary lines, the DEM and its heights on the output, the relief
displacement the DEM removed, the GCP residual summary), ``residuals.csv`` (with GCPs) and
``relief_shift.tif`` (:func:`rectify.raster.ortho.relief_shift_map`, a coarse float32 GeoTIFF in the
output CRS, NaN outside the DEM).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from rectify.atomic import atomic_write_text
from rectify.errors import InvalidInputError
from rectify.geometry.residuals import ResidualTable
from rectify.geometry.sensors import SensorModel
from rectify.raster.dem import Dem
from rectify.raster.io import write_raster
from rectify.raster.ortho import OrthoResult, relief_shift_map

__all__ = ["write_ortho_report"]


def write_ortho_report(report_dir: str | Path, result: OrthoResult, residuals: ResidualTable | None,
                       summary: list[str], model: SensorModel, dem: Dem, *, overwrite: bool = False) -> list[Path]:
    """``ortho_report.json`` (summary, DEM, GCP residuals), ``residuals.csv`` and ``relief_shift.tif``.

    Each file is written atomically into ``report_dir`` (created when missing).

    Parameters
    ----------
    result : OrthoResult
        What :func:`rectify.raster.ortho.orthorectify` wrote.
    residuals : ResidualTable or None
        The GCP residuals (px), when GCPs were given.
    summary : list of str
        The run's summary lines (as printed by ``rectify ortho``).
    model, dem
        The sensor model and DEM of the run (for the relief-shift map).
    """
    d = Path(report_dir)
    if d.exists() and not d.is_dir():
        raise InvalidInputError(f"report folder {str(d)!r} is a file")
    d.mkdir(parents=True, exist_ok=True)
    r = result
    shift, tr = relief_shift_map(model, dem, r.grid)
    doc: dict[str, Any] = {
        "output": str(r.path), "model": r.model, "crs": r.grid.crs, "width": r.grid.width, "height": r.grid.height,
        "resolution": r.grid.resolution[0], "dem": {"path": r.dem_path, "undulation_m": dem.undulation,
                                                    "geoid": dem.geoid, "heights_on_output_m": list(r.dem_range)},
        "relief_shift_removed": {"max": float(np.nanmax(shift)) if np.isfinite(shift).any() else None,
                                 "mean": float(np.nanmean(shift)) if np.isfinite(shift).any() else None,
                                 "map": "relief_shift.tif"},
        "occluded_pixels": r.n_occluded, "seconds": r.seconds, "summary": summary}
    out = []
    if residuals is not None:
        doc["gcp_residuals"] = residuals.summary()
        out.append(atomic_write_text(d / "residuals.csv", residuals.to_csv(), overwrite=overwrite))
    out.append(write_raster(d / "relief_shift.tif", shift.astype(np.float32), tr, r.grid.crs, nodata=float("nan"),
                            valid=np.isfinite(shift), overwrite=overwrite))
    out.append(atomic_write_text(d / "ortho_report.json", json.dumps(doc, indent=2, default=str) + "\n",
                                 overwrite=overwrite))
    return out
