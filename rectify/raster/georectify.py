"""Georectification by GCPs or a saved transform: fit (or take) a planar model, then warp.

:func:`georectify` fits a model of :mod:`rectify.geometry.transforms` to GCPs (in a local frame: the
targets minus their rounded centroid, so map coordinates of 1e5..1e7 m do not spoil the conditioning)
and warps the source through its inverse onto the output grid the forward model suggests;
:func:`rectify_with_transform` does the same with a saved forward model, through pyproj when the output
CRS differs from the model's. Both return a :class:`GeoRectification` (the fit, the
:class:`rectify.raster.warp.WarpResult`, the CRS, notes). The resampling itself is
:func:`rectify.raster.warp.warp_raster`.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from rectify.errors import CRSError, InvalidInputError
from rectify.geometry.crs import crs_to_string, get_transformer, transform_xy
from rectify.geometry.points import GcpTable
from rectify.geometry.residuals import ResidualTable
from rectify.geometry.transforms import METHODS, FitResult, fit_gcps, method_of
from rectify.raster.georef import check_horizon, output_grid
from rectify.raster.io import raster_info
from rectify.raster.warp import WarpOptions, WarpResult, warp_raster

__all__ = ["GeoRectification", "georectify", "rectify_with_transform", "gcps_outside", "outside_note"]

logger = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class GeoRectification:
    """Result of :func:`georectify` / :func:`rectify_with_transform`.

    Attributes
    ----------
    fit : rectify.geometry.transforms.FitResult or None
        The forward model (source pixels -> target) and its residual table.
    warp : WarpResult
    crs : str or None
        Output CRS.
    method : str
    notes : tuple of str
        One-line notes for the user (GCPs outside the source image).
    """

    fit: Any
    warp: WarpResult
    crs: str | None
    method: str
    notes: tuple[str, ...] = ()


def gcps_outside(pixel: NDArray[np.float64], width: int, height: int) -> NDArray[np.bool_]:
    """(N,) mask of the GCPs whose source pixel lies outside the ``width`` x ``height`` image."""
    p = np.asarray(pixel, dtype=np.float64).reshape(-1, 2)
    return np.asarray((p[:, 0] < -0.5) | (p[:, 0] > width - 0.5) | (p[:, 1] < -0.5) | (p[:, 1] > height - 0.5))


def outside_note(pixel: NDArray[np.float64], ids, width: int, height: int) -> str | None:
    """A one-line note naming the GCPs outside the source image (used for the fit, as ``rectify fit`` does),
    or None when all are inside."""
    out = gcps_outside(pixel, width, height)
    if not out.any():
        return None
    i = int(np.flatnonzero(out)[0])
    return (f"note: {int(out.sum())} GCP(s) outside the {width} x {height} image, used for the fit; first is "
            f"{ids[i]!r} at (col, row) = {np.round(pixel[i], 3).tolist()}")


class _Inverse:
    """Callable wrapper exposing a model's inverse (and its matrix when it has one)."""

    def __init__(self, model):
        self._m = model
        if hasattr(model, "matrix"):
            self.matrix = np.asarray(model.matrix, dtype=np.float64)

    def __call__(self, pts):
        return self._m(pts)


def georectify(src: str | Path, dst: str | Path, gcps, *, method: str = "homography",
               gcp_crs: str | None = None, dst_crs: str | None = None, resolution: float | None = None,
               options: WarpOptions | None = None, overwrite: bool = False,
               progress: Callable[[int, int], None] | None = None) -> GeoRectification:
    """Fit a transform to GCPs and warp the source into a georeferenced GeoTIFF.

    Parameters
    ----------
    src, dst : path
    gcps : rectify.geometry.points.GcpTable
        ``pixel`` = source (col, row), ``target`` = map coordinates in
        ``gcp_crs`` (or the table's CRS), or target pixels without a CRS.
    method : str
        ``homography``, ``cotangent``, ``affine``, ``poly2`` or ``poly3``.
    gcp_crs, dst_crs : str, optional
        The GCP CRS (overrides the file's) and the output CRS (default: the GCP
        CRS). When they differ the GCP coordinates are transformed with pyproj
        and the model is fitted in the output CRS.
    resolution : float, optional
        Output pixel size (output CRS units); default as GDAL suggests.

    Returns
    -------
    GeoRectification

    Raises
    ------
    EstimationError
        Too few or degenerate GCPs.
    InvalidInputError
        Unknown method, existing output. GCPs outside the image are used (as by ``rectify fit``) and
        named in ``notes``.
    CRSError
        Unknown CRS, or an output CRS without a GCP CRS.
    """
    m = METHODS.get(method)
    if m is None:
        raise InvalidInputError(f"unknown method {method!r}; expected one of {sorted(METHODS)}")
    info = raster_info(src)
    g_crs = gcp_crs or gcps.crs
    g_crs = crs_to_string(g_crs) if g_crs else None
    out_crs = crs_to_string(dst_crs) if dst_crs else g_crs
    if out_crs is not None and g_crs is None:
        raise CRSError("an output CRS needs the GCP CRS (a '# crs=' line in the GCP file or --gcp-crs)")
    note = outside_note(gcps.pixel, gcps.ids, info.width, info.height)
    if note is not None:  # accepted, as by 'rectify fit' (e.g. GCPs read off a larger scan); the summary says so
        logger.info(note)
    target = gcps.target
    if g_crs is not None and out_crs is not None and g_crs != out_crs:
        target = transform_xy(g_crs, out_crs, gcps.target)
    # fit in a local frame (targets minus their rounded centroid): map coordinates of
    # 1e5..1e7 m would otherwise dominate the conditioning of the normal equations
    fit_rows = ~gcps.check
    offset = np.round(target[fit_rows].mean(axis=0)) if fit_rows.any() else np.zeros(2)
    local = GcpTable(gcps.ids, gcps.pixel, target - offset, gcps.z, gcps.check, out_crs)
    fit_local = fit_gcps(local, method)  # residuals in the output CRS's unit (px without a CRS)
    if method in ("poly2", "poly3"):
        mask = fit_local.table.fit_mask
        inverse_local = m.from_points(local.target[mask], local.pixel[mask])
    else:
        inverse_local = fit_local.model.inverse
    forward = _Shifted(fit_local.model, offset, after=True)
    inverse = _Shifted(inverse_local, offset, after=False)
    t = fit_local.table
    table_out = ResidualTable(step=t.step, ids=t.ids, observed=t.observed + offset, adjusted=t.adjusted + offset,
                              units=t.units, weights=t.weights, outlier=t.outlier,
                              check=t.check, position_px=t.position_px, n_params=t.n_params,
                              extra=dict(t.extra, fit_offset=offset.tolist()))
    fit = FitResult(forward, table_out, method)  # type: ignore[arg-type]  # maps like the model, shifted
    opts = options or WarpOptions()
    grid = output_grid(forward, info.width, info.height, resolution=resolution, crs=out_crs,
                       y_up=out_crs is not None, max_pixels=opts.max_pixels)
    res = warp_raster(src, dst, inverse, grid, options=opts, overwrite=overwrite, progress=progress)
    return GeoRectification(fit, res, out_crs, method, notes=(note,) if note else ())


class _Shifted:
    """A model followed (``after``) or preceded by a translation of the target frame.

    ``after=True``: p -> model(p) + offset (forward, source -> target).
    ``after=False``: w -> model(w - offset) (inverse, target -> source).
    Exposes ``matrix`` (3, 3) when the model has one, and ``model``/``offset``.
    """

    def __init__(self, model, offset: NDArray[np.float64], *, after: bool):
        self.model, self.offset, self.after = model, np.asarray(offset, dtype=np.float64), after
        m = getattr(model, "matrix", None)
        if m is not None:
            T = np.eye(3)
            T[:2, 2] = self.offset if after else -self.offset
            mm = T @ np.asarray(m) if after else np.asarray(m) @ T
            self.matrix = mm / mm[2, 2] if abs(mm[2, 2]) > 1e-300 else mm

    def __call__(self, pts):
        p = np.asarray(pts, dtype=np.float64)
        if self.after:
            return np.asarray(self.model(p)) + self.offset
        return np.asarray(self.model(p - self.offset))


def rectify_with_transform(src: str | Path, dst: str | Path, model, *, model_crs: str | None = None,
                           dst_crs: str | None = None, resolution: float | None = None,
                           options: WarpOptions | None = None, overwrite: bool = False,
                           progress: Callable[[int, int], None] | None = None) -> GeoRectification:
    """Warp with a saved forward model (source pixels -> target in ``model_crs``).

    With ``dst_crs`` different from ``model_crs`` the output grid is computed
    from the footprint transformed through pyproj, and every output pixel is
    mapped back through pyproj (sparse, interpolated) and the model's inverse.
    """
    info = raster_info(src)
    m_crs = crs_to_string(model_crs) if model_crs else None
    out_crs = crs_to_string(dst_crs) if dst_crs else m_crs
    if out_crs is not None and m_crs is None:
        raise CRSError("an output CRS needs the transform's CRS ('crs' in transform.json or --gcp-crs)")
    inverse = model.inverse
    if m_crs is not None and out_crs != m_crs:
        t = get_transformer(m_crs, out_crs)

        def forward(p):
            w = np.asarray(model(p))
            x, y = t.transform(w[:, 0], w[:, 1])
            return np.column_stack([x, y])
        world_crs = m_crs
    else:
        forward, world_crs = model, None
    model_matrix = getattr(model, "matrix", None)
    if model_matrix is not None:
        check_horizon(model_matrix, info.width, info.height)
    grid = output_grid(forward, info.width, info.height, resolution=resolution, crs=out_crs,
                       y_up=out_crs is not None, max_pixels=(options or WarpOptions()).max_pixels)
    res = warp_raster(src, dst, _Inverse(inverse), grid, world_crs=world_crs, options=options,
                      overwrite=overwrite, progress=progress)
    try:
        name = method_of(model)
    except InvalidInputError:
        name = type(model).__name__
    return GeoRectification(None, res, out_crs, name)
