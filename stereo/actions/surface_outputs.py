"""The products of ``stereo surface`` beside the DSM: the true orthomosaic, the point cloud, the check points.

Each works on the fused ``dsm.tif`` (band 1 height, 2 sigma_Z, 3 count, 4 provenance; nodata -9999) as
:func:`stereo.actions.surface.run_surface` stages it, and writes through paths the caller stages (the
caller's workspace transaction renames everything into place at the end, or nothing):

- :func:`write_orthophotos`: the true orthophoto of every image of the block over the DSM
  (:func:`rectify.raster.ortho.orthorectify`: the frame model of each image read from the block
  orientation by :func:`rectify.formats.detect.read_frame_source_any`, z-buffer visibility), on grids
  aligned to whole multiples of the pixel size;
- :func:`write_orthomosaic`: one mosaic of them (:func:`rectify.raster.mosaic.mosaic`) with the seams of the
  least-transformed image (``seams="normal"`` with the DSM), balancing and feathering as ``rectify mosaic``'s
  defaults unless given, a provenance raster, a COG with overviews;
- :func:`write_cloud`: one point per valid DSM cell (the cell centre, the fused height) with the extra
  dimensions ``sigma_z`` (m, float32), ``pair`` (the provenance pair's index in ``pairs.json``, uint16)
  and ``count`` (agreeing pairs, uint16) (:class:`stereo.formats.cloud.LasWriter`), streamed by rows, as
  ``points.laz``, ``points.las`` or ``points.copc.laz`` (:func:`cloud_output` names it);
- :func:`check_points_accuracy`: the DSM height at check points (bilinear over the 4 cells about each
  point; a point with a cell of no height among them is counted as outside) against their surveyed
  height: :meth:`rectify.geometry.accuracy.AccuracyStatement.vertical`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from rectify.atomic import write_failure_reason
from rectify.errors import InvalidInputError, RasterIOError
from rectify.formats.common import TableReader, need_columns
from rectify.formats.detect import read_frame_source_any
from rectify.geometry.accuracy import AccuracyStatement
from rectify.raster.dem import Dem
from rectify.raster.io import WindowReader, gdal_wkt, raster_info
from rectify.raster.mosaic import MosaicOptions, MosaicResult, mosaic
from rectify.raster.ortho import OrthoOptions, orthorectify
from stereo.dense.dsm import DSM_NODATA
from stereo.formats.cloud import CLOUD_FORMATS, LasWriter, copc_available, laz_available

__all__ = ["CLOUD_DIMS", "CLOUD_FORMATS", "CheckPoints", "check_points_accuracy", "cloud_output", "heights_at",
           "read_check_points", "save_grid", "write_cloud", "write_orthomosaic", "write_orthophotos"]

StrPath = str | Path
#: the extra dimensions of the point cloud (``points.laz``, ``points.las``, ``points.copc.laz``)
CLOUD_DIMS = ("sigma_z", "pair", "count")
#: the cloud's file name per format
CLOUD_NAMES = {"las": "points.las", "laz": "points.laz", "copc": "points.copc.laz"}
#: DSM rows per chunk of the point cloud
CLOUD_ROWS = 256


# --------------------------------------------------------------------------- orthophotos and mosaic
def write_orthophotos(orientation: Path, names: list[str], images: list[Path], dsm: Path, folder: Path,
                      resolution: float, *, compress: str = "zstd",
                      progress: Callable[[str, int, int], None] | None = None) -> list[Path]:
    """The true orthophoto ``folder/<image stem>.tif`` of every image over the DSM; their paths.

    ``names``: the images' names in the block orientation; ``images``: their files; ``resolution``: the
    orthophotos' pixel size (ground units). Areas without a DSM height stay nodata. Lossless ``compress``
    only (the visibility band must stay exact; the mosaic may be JPEG).
    """
    dem = Dem.from_path(dsm)
    out: list[Path] = []
    seen: set[str] = set()
    for name, img in zip(names, images, strict=True):
        if progress is not None:
            progress("orthophotos", len(out), len(names))
        stem = Path(name).stem
        k, base = 1, stem
        while stem in seen:  # two images of one stem in different folders
            k += 1
            stem = f"{base}_{k}"
        seen.add(stem)
        fs = read_frame_source_any(None, orientation, image_id=name, image_path=img)
        dst = folder / f"{stem}.tif"
        orthorectify(img, dst, fs.model, dem, resolution=resolution, overwrite=True,
                     options=OrthoOptions(true_ortho=True, compress=compress, min_valid_share=0.0))
        out.append(dst)
    return out


def write_orthomosaic(orthos: list[Path], dsm: Path, dst: Path, provenance: Path, *, balance: str = "none",
                      feather_px: float = 16.0, compress: str = "zstd", cog: bool = True) -> MosaicResult:
    """One mosaic of the orthophotos: seams of the least-transformed image over the DSM (``seams="normal"``),
    ``balance`` (``none``, ``mean``, ``reference``), feathering ``feather_px`` output pixels, ``compress``
    (``jpeg``: JPEG-in-TIFF with a mask), a COG with overviews; the provenance raster (1-based number of the
    orthophoto per pixel, 0 none) at ``provenance``."""
    opts = MosaicOptions(feather_px=feather_px, compress=compress, cog=cog, seams="normal", dsm=str(dsm),
                         balance=balance)
    return mosaic([str(p) for p in orthos], dst, options=opts, overwrite=True, provenance=provenance)


# --------------------------------------------------------------------------- the point cloud
def cloud_output(fmt: str) -> tuple[str, str]:
    """The cloud's format and file name for the option ``fmt`` (:data:`CLOUD_FORMATS`): ``laz`` ->
    ``points.laz`` (``las``, ``points.las``, when laspy has no LAZ backend), ``las`` -> ``points.las``,
    ``copc`` -> ``points.copc.laz``; a COPC without ``copclib`` installed is refused in one line (before
    any work)."""
    if fmt not in CLOUD_FORMATS:
        raise InvalidInputError(f"`cloud_format` must be one of {list(CLOUD_FORMATS)}; got {fmt!r}")
    if fmt == "laz" and not laz_available():
        fmt = "las"
    if fmt == "copc" and not copc_available():
        raise InvalidInputError("--cloud-format copc needs the copclib package, not installed (pip install copclib, "
                                "or the rectify-stereo[copc] extra); choose laz or las")
    return fmt, CLOUD_NAMES[fmt]


def save_grid(path: Path, values: NDArray) -> None:
    """``np.save`` to a scratch file; a failed write (a full disk) is a one-line :class:`RasterIOError`
    naming the file and the reason, and the partial file is removed."""
    try:
        np.save(path, values)
    except OSError as err:   # numpy's own "N requested and M written" carries no errno
        path.unlink(missing_ok=True)
        raise RasterIOError(f"cannot write {str(path)!r}: {write_failure_reason(err, path)}") from err


def write_cloud(dsm: Path, dst: Path, fmt: str, crs: str | None) -> int:
    """One point per valid DSM cell (cell centre x, y; height z) with ``sigma_z``, ``pair`` and ``count``;
    written to ``dst`` as ``fmt`` (``las``, ``laz`` or ``copc``), by blocks of :data:`CLOUD_ROWS` rows.
    Returns the number of points.

    LAS and LAZ stream straight to ``dst``; a COPC is staged as a hidden LAS beside ``dst`` and built at
    the end (:class:`stereo.formats.cloud.LasWriter`: about 60 bytes of memory per point up to
    :data:`stereo.formats.cloud.COPC_BATCH` points, by batches of whole octree nodes beyond). On any
    error the staging file is removed (``dst`` is the caller's to remove); a failed write is a one-line
    :class:`RasterIOError` naming ``dst`` and the reason.
    """
    info = raster_info(dsm)
    t = info.transform
    rd = WindowReader(dsm)
    try:
        offset = (t.c + 0.5 * t.a * info.width, t.f + 0.5 * t.e * info.height, 0.0)
        with LasWriter(dst, offset, crs_wkt=gdal_wkt(crs) if crs else None, fmt=fmt,
                       extra_dims=list(CLOUD_DIMS)) as wr:
            for r0 in range(0, info.height, CLOUD_ROWS):
                a, _ = rd.read(0, r0, info.width, min(CLOUD_ROWS, info.height - r0))
                z, s, n, p = (a[:, :, k].astype(np.float64) for k in range(4))
                ok = (z != DSM_NODATA) & np.isfinite(z) & (p >= 0)
                if not ok.any():
                    continue
                rr, cc = np.nonzero(ok)
                x = t.c + t.a * (cc + 0.5)
                y = t.f + t.e * (rr + r0 + 0.5)
                wr.write(np.column_stack([x, y, z[ok]]),
                         extra={"sigma_z": s[ok], "pair": p[ok], "count": n[ok]})
        return int(wr.count)
    finally:
        rd.close()


# --------------------------------------------------------------------------- check points
@dataclass(frozen=True, eq=False)
class CheckPoints:
    """Check points against the DSM: ``ids``, ``xyz`` (N, 3) surveyed, ``dsm_z`` (N,) the DSM height (NaN
    outside), the vertical statement of those inside (None when none is)."""

    path: Path
    ids: tuple[str, ...]
    xyz: NDArray[np.float64]
    dsm_z: NDArray[np.float64]
    statement: AccuracyStatement | None

    @property
    def n_outside(self) -> int:
        return int((~np.isfinite(self.dsm_z)).sum())

    def summary_lines(self) -> list[str]:
        head = (f"check points {self.path.name}: {len(self.ids)}, {len(self.ids) - self.n_outside} on the DSM"
                + (f" ({self.n_outside} outside it or on a cell of no height)" if self.n_outside else ""))
        if self.statement is None:
            return [head + "; no accuracy statement"]
        return [head + "; DSM height minus check point height:", *self.statement.lines()]

    def to_dict(self) -> dict[str, Any]:
        return {"file": str(self.path), "n": len(self.ids), "outside": self.n_outside,
                "points": [{"id": i, "x": float(p[0]), "y": float(p[1]), "z": float(p[2]),
                            "dsm_z": None if not math.isfinite(d) else float(d)}
                           for i, p, d in zip(self.ids, self.xyz, self.dsm_z, strict=True)],
                "statement": None if self.statement is None else self.statement.to_dict()}


def read_check_points(path: StrPath, ids: tuple[str, ...] = ()) -> tuple[tuple[str, ...], NDArray[np.float64]]:
    """Check points of a CSV with the columns ``id, x, y, z`` (a plain table, or the block control CSV whose
    ids repeat per image measurement: each id once; rows of empty x, y, z, tie points, skipped). Ids whose
    rows differ in x, y, z are refused. ``ids``: only these (all of them must be in the file; default all).
    Returns (ids, xyz (N, 3))."""
    p = Path(path)
    if not p.is_file():
        raise InvalidInputError(f"check points file not found: {str(path)!r}")
    with TableReader(p) as t:
        need_columns(list(t.fields), ("id", "x", "y", "z"), p)
        cols = t.read("rows", numbers=("x", "y", "z"), texts=("id",), empty=("x", "y", "z"))
    xyz = np.column_stack([cols.numbers["x"], cols.numbers["y"], cols.numbers["z"]])
    first: dict[str, int] = {}
    for k, i in enumerate(cols.texts["id"]):
        if not np.isfinite(xyz[k]).all():     # a tie point of a control file (empty x, y, z)
            continue
        j = first.setdefault(i, k)
        if j != k and not np.allclose(xyz[j], xyz[k], rtol=0, atol=1e-6):
            raise InvalidInputError(f"{str(path)!r}: check point {i!r} has two positions {xyz[j].tolist()} and "
                                    f"{xyz[k].tolist()}")
    if ids:
        missing = [i for i in ids if i not in first]
        if missing:
            raise InvalidInputError(f"{str(path)!r}: check point(s) {missing} not in the file (with x, y, z)")
        first = {i: first[i] for i in ids}
    if not first:
        raise InvalidInputError(f"{str(path)!r} holds no check point")
    keep = list(first.values())
    return tuple(first), xyz[keep]


def heights_at(dsm: StrPath, xy: NDArray[np.float64]) -> NDArray[np.float64]:
    """The DSM height (band 1) at ground points ``xy`` (N, 2), bilinear between the 4 cell centres about each
    point; NaN outside the grid or where one of the 4 has no height."""
    info = raster_info(dsm)
    inv = ~info.transform
    out = np.full(len(xy), np.nan)
    rd = WindowReader(dsm)
    try:
        for k, (x, y) in enumerate(np.asarray(xy, np.float64)):
            c, r = inv * (float(x), float(y))
            c, r = c - 0.5, r - 0.5                       # cell centres at integers
            c0, r0 = math.floor(c), math.floor(r)
            if not (0 <= c0 and c0 + 1 < info.width and 0 <= r0 and r0 + 1 < info.height):
                continue
            a, _ = rd.read(c0, r0, 2, 2)
            z = a[:, :, 0].astype(np.float64)
            if (z == DSM_NODATA).any() or not np.isfinite(z).all():
                continue
            fc, fr = c - c0, r - r0
            out[k] = ((1 - fr) * ((1 - fc) * z[0, 0] + fc * z[0, 1]) + fr * ((1 - fc) * z[1, 0] + fc * z[1, 1]))
    finally:
        rd.close()
    return out


def check_points_accuracy(dsm: StrPath, path: StrPath, units: str = "m", ids: tuple[str, ...] = ()) -> CheckPoints:
    """The DSM against the check points of ``path`` (:func:`read_check_points`; ``ids``: only these)."""
    ids, xyz = read_check_points(path, ids)
    z = heights_at(dsm, xyz[:, :2])
    ok = np.isfinite(z)
    st = AccuracyStatement.vertical(z[ok] - xyz[ok, 2], units=units) if ok.any() else None
    return CheckPoints(Path(path), ids, xyz, z, st)
