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
  ``points.laz``, ``points.las`` or ``points.copc.laz`` (:func:`cloud_output` names it); its RGB from the
  orthomosaic (the nearest pixel to the cell centre) or, without one, from the left image of the point's
  provenance pair (the point projected with the block's camera model, bilinear): :class:`PairView`;
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
from rectify.geometry.camera import Camera
from rectify.raster.dem import Dem
from rectify.raster.io import WindowReader, gdal_wkt, ignore_not_georeferenced, raster_info
from rectify.raster.mosaic import MosaicOptions, MosaicResult, mosaic
from rectify.raster.ortho import OrthoOptions, orthorectify
from stereo.block.types import Pose
from stereo.dense.dsm import DSM_NODATA
from stereo.formats.cloud import CLOUD_FORMATS, LasWriter, copc_available, laz_available

__all__ = ["CLOUD_DIMS", "CLOUD_FORMATS", "CheckPoints", "CloudWritten", "PairView", "check_points_accuracy",
           "cloud_output", "heights_at", "read_check_points", "save_grid", "write_cloud", "write_orthomosaic",
           "write_orthophotos"]

StrPath = str | Path
#: the extra dimensions of the point cloud (``points.laz``, ``points.las``, ``points.copc.laz``)
CLOUD_DIMS = ("sigma_z", "pair", "count")
#: the cloud's file name per format
CLOUD_NAMES = {"las": "points.las", "laz": "points.laz", "copc": "points.copc.laz"}
#: DSM rows per chunk of the point cloud
CLOUD_ROWS = 256
#: pixels of one window read to colour the points (a band of whole rows: bounds the colours' memory)
COLOR_WINDOW_PIXELS = 1 << 22
#: images kept open at once to colour the points (the least recently opened is closed beyond)
COLOR_OPEN_IMAGES = 16
#: how a point's colour is sampled, per source
COLOR_SAMPLING = {"orthomosaic": "nearest", "images": "bilinear"}


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


@dataclass(frozen=True)
class PairView:
    """The left image of one stereo pair, to colour its points when no orthomosaic is made: the image file,
    its camera and pose in the block (:meth:`stereo.block.types.Pose.pixel_from_ground`)."""

    image: Path
    camera: Camera
    pose: Pose


@dataclass(frozen=True)
class CloudWritten:
    """What :func:`write_cloud` wrote: ``points``; the colours' ``source`` (``orthomosaic``, ``images`` or
    ``none``); ``uncolored``: points whose colour is unknown (nodata in the mosaic, outside the image), RGB 0;
    ``bits``: the source's depth (8: scaled x 257 to LAS's 16 bits; 16: as read; 0 without colours)."""

    points: int
    source: str = "none"
    uncolored: int = 0
    bits: int = 0

    def note(self) -> str:
        """The colours in one phrase of the summary."""
        if self.source == "none":
            return "no colours (RGB 0)"
        how = ("the orthomosaic (nearest pixel)" if self.source == "orthomosaic"
               else "the left image of each point's pair (bilinear)")
        return f"RGB from {how}, {self.uncolored} without a colour (RGB 0)"

    def to_dict(self) -> dict[str, Any]:
        return {"source": self.source, "sampling": COLOR_SAMPLING.get(self.source), "bits": self.bits or None,
                "uncolored": self.uncolored}


class _Colors:
    """The colours of one raster at pixel positions (x = column, y = row, pixel centres at integers), read by
    bands of whole rows of at most :data:`COLOR_WINDOW_PIXELS` pixels. RGB from bands 1-3 (an alpha band left
    out); a raster of one or two bands gives grey (band 1) to R = G = B. Values on LAS's 16-bit scale: uint8
    x 257, other types rounded and clipped to 0..65535 by the writer."""

    def __init__(self, path: Path):
        with ignore_not_georeferenced():   # a frame image has no georeference
            self.rd = WindowReader(path)
        pol = self.rd.policy
        bands = [k for k in range(self.rd.count) if not (pol.kind == "alpha" and k == pol.alpha_band)]
        self.bands = bands[:3] if len(bands) >= 3 else [bands[0]] * 3
        self.bits = 8 if self.rd.dtype == np.uint8 else 16

    def close(self) -> None:
        self.rd.close()

    def sample(self, x: NDArray[np.float64], y: NDArray[np.float64], bilinear: bool
               ) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
        """(rgb (N, 3) on the 16-bit scale, 0 where unknown; known (N,) bool) at ``x``, ``y`` (N,).

        ``bilinear``: between the 4 pixel centres about each position (the image edge replicated); where one
        of them is invalid, the nearest pixel. Else the nearest pixel. Unknown: outside the raster, or an
        invalid (nodata, masked) nearest pixel."""
        W, H = self.rd.width, self.rd.height
        out, known = np.zeros((len(x), 3)), np.zeros(len(x), bool)
        inside = np.isfinite(x) & np.isfinite(y) & (x >= -0.5) & (x < W - 0.5) & (y >= -0.5) & (y < H - 0.5)
        idx = np.flatnonzero(inside)
        if not idx.size:
            return out, known
        rows = max(1, COLOR_WINDOW_PIXELS // W - 2)
        part_of = np.clip(np.floor(y[idx] + 0.5), 0, H - 1).astype(np.int64) // rows
        order = np.argsort(part_of, kind="stable")
        idx, part_of = idx[order], part_of[order]
        for sel in np.split(idx, np.flatnonzero(np.diff(part_of)) + 1):
            xs, ys = x[sel], y[sel]
            c0, r0 = max(0, int(np.floor(xs.min()))), max(0, int(np.floor(ys.min())))
            c1, r1 = min(W, int(np.floor(xs.max())) + 2), min(H, int(np.floor(ys.max())) + 2)
            a, valid = self.rd.read(c0, r0, c1 - c0, r1 - r0)
            a = a[:, :, self.bands].astype(np.float64) * (257.0 if self.bits == 8 else 1.0)
            ok = np.ones(a.shape[:2], bool) if valid is None else valid
            cn = np.clip(np.floor(xs + 0.5), 0, W - 1).astype(np.int64) - c0
            rn = np.clip(np.floor(ys + 0.5), 0, H - 1).astype(np.int64) - r0
            v, k = a[rn, cn], ok[rn, cn]
            if bilinear:
                xc, yc = np.clip(xs, 0, W - 1), np.clip(ys, 0, H - 1)
                xa, ya = np.floor(xc).astype(np.int64), np.floor(yc).astype(np.int64)
                xb, yb = np.minimum(xa + 1, W - 1), np.minimum(ya + 1, H - 1)
                fx, fy = (xc - xa)[:, None], (yc - ya)[:, None]
                xa, xb, ya, yb = xa - c0, xb - c0, ya - r0, yb - r0
                four = ok[ya, xa] & ok[ya, xb] & ok[yb, xa] & ok[yb, xb]
                bl = (1 - fy) * ((1 - fx) * a[ya, xa] + fx * a[ya, xb]) + fy * ((1 - fx) * a[yb, xa] + fx * a[yb, xb])
                v = np.where(four[:, None], bl, v)
                k = k | four
            out[sel] = np.where(k[:, None], v, 0.0)
            known[sel] = k
        return out, known


def write_cloud(dsm: Path, dst: Path, fmt: str, crs: str | None, *, mosaic: Path | None = None,
                views: list[PairView] | None = None) -> CloudWritten:
    """One point per valid DSM cell (cell centre x, y; height z) with ``sigma_z``, ``pair`` and ``count``;
    written to ``dst`` as ``fmt`` (``las``, ``laz`` or ``copc``), by blocks of :data:`CLOUD_ROWS` rows.

    Colours (LAS RGB, 16 bits; :class:`_Colors`): from the orthomosaic ``mosaic`` when given, its pixel
    nearest to the cell centre (the DSM and the mosaic grids lie on whole multiples of their cells, so at
    the default cell a cell centre is a pixel centre); else from ``views`` (one per pair of ``pairs.json``,
    indexed by the DSM's provenance band): the cell's point projected into the left image of its pair,
    bilinear; else none (RGB 0). Memory: one block of DSM rows and one colour window at a time.

    LAS and LAZ stream straight to ``dst``; a COPC is staged as a hidden LAS beside ``dst`` and built at
    the end (:class:`stereo.formats.cloud.LasWriter`: about 60 bytes of memory per point up to
    :data:`stereo.formats.cloud.COPC_BATCH` points, by batches of whole octree nodes beyond). On any
    error the staging file is removed (``dst`` is the caller's to remove); a failed write is a one-line
    :class:`RasterIOError` naming ``dst`` and the reason.
    """
    info = raster_info(dsm)
    t = info.transform
    rd = WindowReader(dsm)
    source = "orthomosaic" if mosaic is not None else "images" if views else "none"
    readers: dict[Path, _Colors] = {}
    unknown = 0
    bits: set[int] = set()
    inv = None
    try:
        if mosaic is not None:
            readers[mosaic] = _Colors(mosaic)
            inv = ~raster_info(mosaic).transform
        offset = (t.c + 0.5 * t.a * info.width, t.f + 0.5 * t.e * info.height, 0.0)
        with LasWriter(dst, offset, crs_wkt=gdal_wkt(crs) if crs else None, fmt=fmt,
                       extra_dims=list(CLOUD_DIMS), color_bits=16) as wr:
            for r0 in range(0, info.height, CLOUD_ROWS):
                a, _ = rd.read(0, r0, info.width, min(CLOUD_ROWS, info.height - r0))
                z, s, n, p = (a[:, :, k].astype(np.float64) for k in range(4))
                ok = (z != DSM_NODATA) & np.isfinite(z) & (p >= 0)
                if not ok.any():
                    continue
                rr, cc = np.nonzero(ok)
                x = t.c + t.a * (cc + 0.5)
                y = t.f + t.e * (rr + r0 + 0.5)
                xyz = np.column_stack([x, y, z[ok]])
                rgb = None
                if source != "none":
                    rgb, known = _point_colors(xyz, p[ok], mosaic, inv, views, readers, bits)
                    unknown += int((~known).sum())
                wr.write(xyz, rgb, extra={"sigma_z": s[ok], "pair": p[ok], "count": n[ok]})
        bits.update(c.bits for c in readers.values())
        return CloudWritten(int(wr.count), source, unknown if source != "none" else 0, max(bits, default=0))
    finally:
        rd.close()
        for c in readers.values():
            c.close()


def _point_colors(xyz: NDArray[np.float64], pair: NDArray[np.float64], mosaic: Path | None, inv: Any,
                  views: list[PairView] | None, readers: dict[Path, _Colors], bits: set[int]
                  ) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """The colours of the points ``xyz`` (N, 3) of :func:`write_cloud` (``pair``: their provenance pairs) and
    whether each is known; the rasters open in ``readers`` (at most :data:`COLOR_OPEN_IMAGES` images: the
    first opened is closed beyond, its depth kept in ``bits``)."""
    if mosaic is not None:
        c, r = inv * (xyz[:, 0], xyz[:, 1])
        return readers[mosaic].sample(np.asarray(c) - 0.5, np.asarray(r) - 0.5, bilinear=False)
    assert views is not None
    rgb, known = np.zeros((len(xyz), 3)), np.zeros(len(xyz), bool)
    pk = pair.astype(np.int64)
    for k in np.unique(pk):
        if not 0 <= k < len(views):
            continue
        sel = pk == k
        v = views[k]
        if v.image not in readers:
            if len(readers) >= COLOR_OPEN_IMAGES:
                old = readers.pop(next(iter(readers)))
                bits.add(old.bits)
                old.close()
            readers[v.image] = _Colors(v.image)
        px = v.pose.pixel_from_ground(v.camera, xyz[sel])
        rgb[sel], known[sel] = readers[v.image].sample(px[:, 0], px[:, 1], bilinear=True)
    return rgb, known


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
