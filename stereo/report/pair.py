"""Stereo-specific QA figures, built on :mod:`rectify.report.builder`.

- relative orientation: vertical-parallax residuals over the left image and the
  correlation matrix of the five elements as a heat map;
- absolute orientation: plan residual vectors (dX, dY) at the ground positions of
  the control points and the height residuals dZ as bars.

:func:`write_stereo_report` gathers them and calls
:func:`rectify.report.builder.write_report`, so a stereo run writes the same CSV, JSON,
PNG, GeoJSON and HTML files as every other command. This module is the one stereo
report builder: :func:`write_orient_report` (``stereo orient``), :func:`write_pair_report`
(``stereo model``, ``stereo run``, ``stereo demo``) and :func:`write_resect_report`
(``stereo resect``).
"""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from matplotlib.figure import Figure
from numpy.typing import ArrayLike

from rectify.errors import InvalidInputError, ShapeError
from rectify.geometry.camera import Camera
from rectify.geometry.geodesy import map_from_enu
from rectify.geometry.residuals import ResidualTable
from rectify.raster import io as rio
from rectify.report.builder import write_report
from rectify.report.figures import (
    correlation_heatmap_figure,
    height_bars_figure,
    height_difference_map_figure,
    pair_matches_figure,
    residual_vector_figure,
)
from stereo.pair.resection import ExteriorOrientation
from stereo.relative import RelativeOrientation

if TYPE_CHECKING:  # type hints only: stereo.pair.model does not depend on the report
    from stereo.pair.model import StereoModel

logger = logging.getLogger(__name__)

__all__ = ["absolute_orientation_figures", "relative_orientation_figures", "write_orient_report",
           "write_pair_report", "write_resect_report", "write_stereo_report", "absolute_table_in_ground",
           "pair_figures"]


def relative_orientation_figures(correlation_names: Sequence[str], correlation_matrix: ArrayLike, *,
                                 table: ResidualTable | None = None, image_shape: Sequence[int] | None = None,
                                 background: ArrayLike | None = None) -> dict[str, Figure]:
    """Figures of a relative orientation.

    Parameters
    ----------
    correlation_names : sequence of str, length m
        Names of the estimated elements (e.g. ``["tau", "nu", "alpha2", "omega2", "kappa2"]``).
    correlation_matrix : (m, m) array_like
        Their correlation coefficients (unitless), as in the RO JSON ``correlation``.
    table : ResidualTable, optional
        Vertical-parallax residuals (one component, usually mm) with ``position_px``
        on the left image; adds the "vertical parallax over the left image" figure.
    image_shape, background : optional
        Left image size / pixels for that figure.

    Returns
    -------
    dict name -> Figure
        ``"RO correlation of elements"`` and, with a table having positions,
        ``"RO vertical parallax over the left image"``.

    Raises
    ------
    ShapeError, InvalidInputError
        From :func:`rectify.report.figures.correlation_heatmap_figure` for a bad matrix.
    """
    figs = {"RO correlation of elements": correlation_heatmap_figure(
        correlation_names, correlation_matrix, title="Relative orientation: correlation of the elements")}
    if table is not None and table.position_px is not None and table.n:
        figs["RO vertical parallax over the left image"] = residual_vector_figure(
            table, image_shape=image_shape, background=background,
            title=f"{table.step}: residual vertical parallax {table.components[0]} ({table.units}), "
                  "drawn vertically at the left-image points")
    return figs


def absolute_orientation_figures(table: ResidualTable, ground_xy: ArrayLike, *,
                                 position_units: str | None = None) -> dict[str, Figure]:
    """Plan residual vectors over the ground and height-residual bars of an absolute orientation.

    Parameters
    ----------
    table : ResidualTable
        Residuals with three components (dX, dY, dZ) in ground units.
    ground_xy : (N, 2) array_like
        Ground plan coordinates (X easting, Y northing) of the control points.
    position_units : str, optional
        Units of ``ground_xy`` for the axis labels (default the table's units).

    Returns
    -------
    dict name -> Figure
        ``"AO plan residuals"`` and ``"AO height residuals"``.

    Raises
    ------
    InvalidInputError
        If the table does not have three components.
    ShapeError
        If ``ground_xy`` is not (N, 2).
    """
    if table.residual.shape[1] != 3:
        raise InvalidInputError(f"absolute orientation residuals need 3 components (dX, dY, dZ); "
                                f"table {table.step!r} has {table.components}")
    g = np.asarray(ground_xy, dtype=np.float64)
    if g.shape != (table.n, 2):
        raise ShapeError(f"`ground_xy` must have shape ({table.n}, 2); got {g.shape}",
                         actual_shape=g.shape, expected_shape=(table.n, 2))
    units = position_units or table.units
    return {
        "AO plan residuals": residual_vector_figure(
            table, positions=g, position_units=units, y_down=False,
            title=f"{table.step}: plan residuals ({table.components[0]}, {table.components[1]}) "
                  f"at the control points"),
        "AO height residuals": height_bars_figure(table, component=2),
    }


def write_stereo_report(out_dir: str | os.PathLike, *, title: str,
                        relative: ResidualTable | None = None,
                        correlation: tuple[Sequence[str], ArrayLike] | None = None,
                        absolute: ResidualTable | None = None, absolute_ground_xy: ArrayLike | None = None,
                        tables: Sequence[ResidualTable] = (), figures: dict[str, Figure] | None = None,
                        summary: dict | None = None, crs: str | None = None,
                        left_image_shape: Sequence[int] | None = None, left_image: ArrayLike | None = None,
                        principal_point_px: ArrayLike | None = None, overwrite: bool = False) -> Path:
    """Write the QA report of a stereo run (relative + absolute orientation) with :func:`write_report`.

    Parameters
    ----------
    out_dir : path
        Report folder.
    title : str
        Page title.
    relative : ResidualTable, optional
        Vertical-parallax residuals of the relative orientation (positions on the left image).
    correlation : (names, matrix), optional
        Correlation of the relative-orientation elements (heat map).
    absolute : ResidualTable, optional
        Control-point residuals (dX, dY, dZ) of the absolute orientation, ground units.
    absolute_ground_xy : (N, 2) array_like, optional
        Ground X, Y of those points; required with ``absolute``. With ``crs`` the
        plan vectors are also written as GeoJSON.
    tables : sequence of ResidualTable
        Further tables (tie points, check points, resection, ...).
    figures, summary, overwrite : as in :func:`rectify.report.builder.write_report`.
    crs : str, optional
        Ground CRS of ``absolute_ground_xy``.
    left_image_shape, left_image : optional
        Left image size / pixels, drawn under the relative-orientation residuals.
    principal_point_px : (2,), optional
        Principal point of the left image (pixels) for the radial plot.

    Returns
    -------
    pathlib.Path
        Path of ``report.html``.

    Raises
    ------
    InvalidInputError
        If ``absolute`` is given without ``absolute_ground_xy``, or as in
        :func:`write_report`.
    """
    all_tables: list[ResidualTable] = []
    figs: dict[str, Figure] = {}
    backgrounds: dict[str, Any] = {}
    shapes: dict[str, Sequence[int]] = {}
    pps: dict[str, Any] = {}
    ground: dict[str, Any] | None = None
    if relative is not None:
        all_tables.append(relative)
        if left_image is not None:
            backgrounds[relative.step] = left_image
        if left_image_shape is not None:
            shapes[relative.step] = left_image_shape
        if principal_point_px is not None:
            pps[relative.step] = principal_point_px
    if correlation is not None:
        names, matrix = correlation
        figs.update(relative_orientation_figures(names, matrix))
    if absolute is not None:
        if absolute_ground_xy is None:
            raise InvalidInputError("`absolute_ground_xy` (N, 2) is required with `absolute`")
        all_tables.append(absolute)
        figs.update(absolute_orientation_figures(absolute, absolute_ground_xy))
        if crs is not None:
            ground = {absolute.step: np.asarray(absolute_ground_xy, dtype=np.float64)}
    all_tables.extend(tables)
    figs.update(figures or {})
    return write_report(out_dir, title=title, tables=all_tables, figures=figs, summary=summary,
                        crs=crs if ground else None, ground_xy=ground, overwrite=overwrite,
                        backgrounds=backgrounds or None, image_shapes=shapes or None,
                        principal_point_px=pps or None)


def absolute_table_in_ground(model: StereoModel) -> ResidualTable | None:
    """The absolute orientation's residual table with coordinates in the ground CRS.

    Estimated in the topocentric frame, the table holds local ENU offsets; here ``observed`` and
    ``adjusted`` are taken back to the control CRS (so the report shows map coordinates and the
    residuals dX, dY, dZ are map-frame differences). Each row gets the standard deviation of its
    residual (``std``, so that the normalised residuals and the Q-Q plot are unitless and standard
    normal under the model): for check points the predicted ground standard error (their error is
    the estimate's), for control points that times the square root of the average redundancy
    ``(n - 7) / n`` (a fitted point's residual is smaller than its error).
    """
    if model.absolute is None or model.ground is None:
        return None
    t = model.absolute.residuals
    obs, adj = t.observed, t.adjusted
    origin = (model.frame or {}).get("origin_lon_lat_h")
    if model.frame.get("name") == "topocentric" and model.crs and origin is not None:
        obs, adj = map_from_enu(obs, model.crs, origin), map_from_enu(adj, model.crs, origin)
    std = None
    if model.ground_std is not None:
        rows = [model.ids.index(i) for i in t.ids]
        var = np.sum(np.square(model.ground_std[rows]), axis=1)
        n_obs = int(t.extra.get("n_equations", 3 * t.n))
        red = max(n_obs - t.n_params, 1) / max(n_obs, 1)
        std = np.sqrt(np.where(np.asarray(t.check, dtype=bool), var, var * red))
    units = model.summary.get("ground_unit", t.units)
    return ResidualTable(step=t.step, ids=t.ids, observed=obs, adjusted=adj, units=units, components=t.components,
                         weights=t.weights, outlier=t.outlier, check=t.check, std=std, n_params=t.n_params,
                         sigma0=t.sigma0, extra=dict(t.extra, coordinates="ground CRS"))


def pair_figures(model: StereoModel, ro: Any = None, *, camera: Camera | None = None,
                 left_image: Any = None, right_image: Any = None) -> dict[str, Figure]:
    """The pair's extra figures: the tie points over both images (with ``ro`` and ``camera``) and the
    height-difference map at the check points (with an absolute orientation and check points)."""
    figs: dict[str, Figure] = {}
    if ro is not None and camera is not None and len(ro.left_mm):
        pl = camera.pixel_from_photo(ro.left_mm)
        pr = camera.pixel_from_photo(ro.right_mm)
        figs["tie points over the images"] = pair_matches_figure(
            left_image, right_image, pl, pr, outlier=ro.outlier,
            shapes=((camera.height, camera.width), (camera.height, camera.width)))
    t = absolute_table_in_ground(model)
    if t is not None and np.asarray(t.check, dtype=bool).any():
        c = np.asarray(t.check, dtype=bool)
        rows = [model.ids.index(i) for i, k in zip(t.ids, c, strict=True) if k]
        sd = None if model.ground_std is None else model.ground_std[rows, 2]
        figs["height differences at check points"] = height_difference_map_figure(
            t.observed[c, :2], t.residual[c, 2], [i for i, k in zip(t.ids, c, strict=True) if k], units=t.units,
            std=sd)
    return figs


def _overview(path: str | os.PathLike | None) -> Any:
    if path is None:
        return None
    data, valid, _ = rio.read_overview(Path(path), 2048)
    return rio.to_uint8(data, valid)


def write_pair_report(model: StereoModel, out_dir: str | os.PathLike, *, title: str, ro: Any = None,
                      left_image: str | os.PathLike | None = None, camera: Camera | None = None,
                      overwrite: bool = False, right_image: str | os.PathLike | None = None) -> Path:
    """QA report of a pair run with :func:`stereo.report.pair.write_stereo_report`.

    Relative orientation: vertical-parallax table over the left image (drawn on
    the photo when ``left_image`` can be read) and the correlation heat map of
    its elements; absolute orientation: residual table, plan vectors at the
    control points' ground positions (GeoJSON too when the model has a CRS,
    EPSG code or WKT) and height bars; the intersection table. ``model.tables``
    must start with ``ro.residual_table()`` when ``ro`` is given.

    Issue 12: the absolute-orientation table is in the ground CRS with per-point residual standard
    deviations (:func:`absolute_table_in_ground`), map axes have readable ticks, and
    :func:`pair_figures` adds the tie points over both images and the height-difference map at the
    check points.
    """
    tables = list(model.tables)
    rel = corr = None
    if ro is not None:
        rel = tables.pop(0)
        c = ro.correlation
        if c is not None and np.isfinite(c).all():
            corr = (list(ro.names), c)
    absolute = gxy = None
    if model.absolute is not None and model.ground is not None:
        tables = [t for t in tables if t is not model.absolute.residuals]
        absolute = absolute_table_in_ground(model)
        assert absolute is not None
        rows = [model.ids.index(i) for i in absolute.ids]
        gxy = model.ground[rows, :2]
    img = shape = pp = None
    if camera is not None:
        shape = (camera.height, camera.width)
        pp = camera.pixel_from_photo(np.zeros((1, 2)))[0]
    # bounded overviews for the plot backgrounds (drawn over the full-resolution extent)
    img = _overview(left_image)
    figs = pair_figures(model, ro, camera=camera, left_image=img, right_image=_overview(right_image))
    return write_stereo_report(out_dir, title=title, relative=rel, correlation=corr, absolute=absolute,
                               absolute_ground_xy=gxy, tables=tables, summary=model.summary,
                               crs=model.crs or None, left_image_shape=shape, left_image=img,
                               principal_point_px=pp, overwrite=overwrite, figures=figs)


def write_orient_report(ro: RelativeOrientation, camera: Camera, out_dir: str | os.PathLike, *, title: str,
                        overwrite: bool = False) -> Path:
    """QA report of ``stereo orient``: vertical-parallax table over the left image frame, the correlation
    heat map of the elements and the summary (with the elements in radians)."""
    corr = ro.correlation
    return write_stereo_report(
        out_dir, title=title, relative=ro.residual_table(),
        correlation=None if corr is None else (list(ro.names), corr),
        summary={**ro.summary(), "elements_rad": ro.element_dict,
                 # one sigma0 in console and report: that of the parallax table
                 # (stereo.actions.common.parallax_sigma0_mm)
                 "sigma0_mm": ro.residual_table(units="mm").sigma0, "sigma0_coordinate_mm": ro.sigma0_mm},
        left_image_shape=(camera.height, camera.width), principal_point_px=camera.principal_point_px,
        overwrite=overwrite)


def write_resect_report(eo: ExteriorOrientation, out_dir: str | os.PathLike, *, summary: dict[str, Any],
                        title: str = "stereo resect", overwrite: bool = False) -> Path:
    """QA report of ``stereo resect``: the photo residual table (mm) and ``summary`` (the EO JSON)."""
    if eo.residuals is None:
        raise InvalidInputError("the exterior orientation has no residual table to report")
    return write_report(out_dir, title=title, tables=[eo.residuals], summary=summary, overwrite=overwrite)
