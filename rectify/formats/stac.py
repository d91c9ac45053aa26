"""A STAC Item beside a product: its files, where it lies, how accurate it is and how it was made.

:func:`write_stac_item` (the product commands' call) writes ``<name>.stac.json``, a STAC 1.x Item
built with pystac from a :class:`StacProduct`:

- **assets** (:class:`StacAsset`): each product file with its roles (``data``, ``metadata``,
  ``overview``, ``visual`` ...), media type and the file extension's ``file:size`` and
  ``file:checksum`` (a SHA-256 multihash); hrefs are relative to the Item, so the folder can move;
- **where**: the projection extension (``proj:code``/``proj:epsg`` or ``proj:wkt2``, ``proj:shape``,
  ``proj:transform`` in rasterio/GDAL order, ``proj:bbox``) from the product's grid, and the
  Item's geometry and bbox: the grid's outline (ten points per edge) in WGS 84 longitude/latitude
  as STAC requires;
- **accuracy**: ``rectify:accuracy``, the product's figures as the command computed them
  (name -> number, units in the names: ``gcp_rmse_m``, ``check_rmse_px``, ...);
- **provenance**: the processing extension's ``processing:software`` (``{"rectify-stereo":
  version}``), ``processing:lineage`` (the command) and ``processing:datetime``, and
  ``rectify:options`` (the options, JSON-safe) and ``rectify:inputs`` (each input's path, size
  and SHA-256 multihash).

STAC needs a ``datetime``: the acquisition time when the product knows it, else the processing
time (``rectify:datetime_source`` says which). QGIS's STAC browser and STAC catalogues read such
Items as they are.
"""

from __future__ import annotations

import datetime as dt
import hashlib
import json
import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pystac
from pystac.extensions.file import FileExtension
from pystac.extensions.projection import ProjectionExtension

from rectify import __version__
from rectify.atomic import atomic_write_text
from rectify.errors import InvalidInputError, RasterIOError
from rectify.formats.common import StrPath
from rectify.geometry.crs import crs_to_string, parse_crs, transform_xy

__all__ = ["PROCESSING_SCHEMA", "SOFTWARE", "RasterGrid", "StacAsset", "StacProduct", "stac_item",
           "stac_item_text", "write_stac_item", "file_checksum", "MEDIA_TYPES"]

#: schema of the STAC processing extension (its fields are written by hand: pystac has no class for it)
PROCESSING_SCHEMA = "https://stac-extensions.github.io/processing/v1.2.0/schema.json"
#: the software named in ``processing:software``
SOFTWARE = "rectify-stereo"
#: media type by suffix (assets that name none)
MEDIA_TYPES = {".tif": "image/tiff; application=geotiff", ".tiff": "image/tiff; application=geotiff",
               ".las": "application/vnd.las", ".laz": "application/vnd.laszip", ".ply": "application/octet-stream",
               ".json": "application/json", ".geojson": "application/geo+json", ".csv": "text/csv",
               ".html": "text/html", ".png": "image/png", ".jpg": "image/jpeg", ".txt": "text/plain"}
_EDGE_POINTS = 10
_CHUNK = 1 << 20


@dataclass(frozen=True)
class RasterGrid:
    """A raster's grid: CRS, affine transform and size.

    Parameters
    ----------
    crs : str
        ``EPSG:nnnn`` or WKT.
    transform : 6 floats
        (a, b, c, d, e, f), rasterio's and STAC's order: x = a col + b row + c, y = d col + e row + f
        with (col, row) the corner of a pixel (0, 0 the image's top-left corner).
    width, height : int
    """

    crs: str
    transform: tuple[float, float, float, float, float, float]
    width: int
    height: int

    def __post_init__(self) -> None:
        t = tuple(float(v) for v in self.transform)
        if len(t) != 6 or not all(math.isfinite(v) for v in t):
            raise InvalidInputError(f"grid `transform` must be 6 finite numbers (a, b, c, d, e, f); "
                                    f"got {self.transform!r}")
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise InvalidInputError(f"grid size must be positive; got {self.width!r} x {self.height!r}")
        object.__setattr__(self, "transform", t)
        object.__setattr__(self, "crs", crs_to_string(parse_crs(self.crs)))

    def outline(self) -> np.ndarray:
        """The grid's outline, (4 * 10, 2) map coordinates, corners included."""
        a, b, c, d, e, f = self.transform
        s = np.linspace(0.0, 1.0, _EDGE_POINTS, endpoint=False)
        w, h = float(self.width), float(self.height)
        cr = np.concatenate([np.column_stack([s * w, np.zeros_like(s)]), np.column_stack([np.full_like(s, w), s * h]),
                             np.column_stack([w - s * w, np.full_like(s, h)]), np.column_stack([np.zeros_like(s),
                                                                                                h - s * h])])
        return np.column_stack([a * cr[:, 0] + b * cr[:, 1] + c, d * cr[:, 0] + e * cr[:, 1] + f])

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """(xmin, ymin, xmax, ymax) in the grid's CRS."""
        o = self.outline()
        return float(o[:, 0].min()), float(o[:, 1].min()), float(o[:, 0].max()), float(o[:, 1].max())


@dataclass(frozen=True)
class StacAsset:
    """One file of a product.

    Parameters
    ----------
    path : path
        The file (it must exist when the Item is written).
    roles : tuple of str
        STAC roles: ``data``, ``metadata``, ``overview``, ``visual``, ``thumbnail`` ...
    title : str, optional
    media_type : str, optional
        Default from the suffix (:data:`MEDIA_TYPES`).
    grid : RasterGrid, optional
        The asset's own grid when it differs from the product's (an overview, a residual raster).
    source : path, optional
        The file whose bytes are described when it is not yet at ``path`` (the staged temporary file
        of a transaction that renames it there); default ``path``.
    """

    path: StrPath
    roles: tuple[str, ...] = ("data",)
    title: str | None = None
    media_type: str | None = None
    grid: RasterGrid | None = None
    source: StrPath | None = None


@dataclass(frozen=True)
class StacProduct:
    """What a product command knows about its output, for :func:`stac_item`.

    Parameters
    ----------
    item_id : str
        The Item's id (the product's file stem).
    assets : dict of str -> StacAsset
        Asset key -> file.
    grid : RasterGrid, optional
        The product's grid (projection extension and footprint).
    footprint : (crs, (xmin, ymin, xmax, ymax)), optional
        The extent of a product without a grid (a point cloud).
    acquired : datetime, optional
        Acquisition time of the images (timezone-aware, else taken as UTC).
    accuracy : dict of str -> float
        The accuracy figures written for the product (units in the names).
    command : str
        The command line or command name (``rectify ortho``).
    options : dict
        The options it ran with.
    inputs : sequence of path
        Its input files (hashed).
    created : datetime, optional
        Processing time (default: now, UTC).
    unlocated : bool
        The product is in no map frame (an image rectified onto another image's pixels): the Item's
        geometry and bbox are null, as STAC allows, and ``rectify:frame`` says ``pixel``.
    """

    item_id: str
    assets: Mapping[str, StacAsset]
    grid: RasterGrid | None = None
    footprint: tuple[str, tuple[float, float, float, float]] | None = None
    acquired: dt.datetime | None = None
    accuracy: Mapping[str, float] = field(default_factory=dict)
    command: str = ""
    options: Mapping[str, Any] = field(default_factory=dict)
    inputs: Sequence[StrPath] = ()
    created: dt.datetime | None = None
    unlocated: bool = False


def file_checksum(path: StrPath) -> str:
    """SHA-256 of a file as a multihash in hex (``1220`` + digest), the STAC file extension's ``file:checksum``.

    Raises
    ------
    RasterIOError
        The file is missing or unreadable.
    """
    h = hashlib.sha256()
    try:
        with open(path, "rb") as fh:
            for block in iter(lambda: fh.read(_CHUNK), b""):
                h.update(block)
    except OSError as err:
        raise RasterIOError(f"cannot read {str(path)!r} to hash it: {err.strerror or err}") from err
    return "1220" + h.hexdigest()


def _utc(t: dt.datetime) -> dt.datetime:
    return t if t.tzinfo is not None else t.replace(tzinfo=dt.timezone.utc)


def _json_safe(v: Any) -> Any:
    if isinstance(v, Mapping):
        return {str(k): _json_safe(x) for k, x in v.items()}
    if isinstance(v, (list, tuple, set)):
        return [_json_safe(x) for x in v]
    if isinstance(v, np.ndarray):
        return _json_safe(v.tolist())
    if isinstance(v, (np.integer, np.floating, np.bool_)):
        v = v.item()
    if isinstance(v, float) and not math.isfinite(v):
        return None
    if isinstance(v, (str, int, float, bool)) or v is None:
        return v
    if isinstance(v, os.PathLike):
        return os.fspath(v)
    if isinstance(v, (dt.datetime, dt.date)):
        return v.isoformat()
    return str(v)


def _lonlat_geometry(crs: str, outline: np.ndarray) -> tuple[dict[str, Any], list[float]]:
    ll = transform_xy(crs, "EPSG:4326", outline)
    x, y = ll[:, 0], ll[:, 1]
    if np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y) < 0:  # RFC 7946: exterior rings counter-clockwise
        ll = ll[::-1]
    ring = [[float(x), float(y)] for x, y in ll] + [[float(ll[0, 0]), float(ll[0, 1])]]
    bbox = [float(ll[:, 0].min()), float(ll[:, 1].min()), float(ll[:, 0].max()), float(ll[:, 1].max())]
    return {"type": "Polygon", "coordinates": [ring]}, bbox


def _apply_grid(ext: Any, grid: RasterGrid) -> None:
    code = crs_to_string(grid.crs)
    epsg = int(code[5:]) if code.startswith("EPSG:") else None
    ext.apply(epsg=epsg, wkt2=None if epsg else parse_crs(grid.crs).to_wkt(), bbox=list(grid.bounds),
              shape=[grid.height, grid.width], transform=list(grid.transform))


def stac_item(product: StacProduct, href: StrPath) -> pystac.Item:
    """The STAC Item of ``product``, to be written at ``href`` (asset hrefs relative to its folder).

    Raises
    ------
    InvalidInputError
        No asset, neither ``grid`` nor ``footprint``.
    RasterIOError
        An asset or input file that cannot be read (named).
    CRSError
        A CRS PROJ cannot place in WGS 84.
    """
    if not product.assets:
        raise InvalidInputError(f"STAC Item {product.item_id!r} needs at least one asset")
    geometry: dict[str, Any] | None
    bbox: list[float] | None
    if product.grid is not None:
        geometry, bbox = _lonlat_geometry(product.grid.crs, product.grid.outline())
    elif product.footprint is not None:
        crs, (x0, y0, x1, y1) = product.footprint
        g = RasterGrid(crs, (x1 - x0, 0.0, x0, 0.0, y0 - y1, y1), 1, 1)
        geometry, bbox = _lonlat_geometry(g.crs, g.outline())
    elif product.unlocated:
        geometry = bbox = None
    else:
        raise InvalidInputError(f"STAC Item {product.item_id!r} needs a grid or a footprint (where the product lies)")
    created = _utc(product.created or dt.datetime.now(dt.timezone.utc))
    when = _utc(product.acquired) if product.acquired is not None else created
    folder = Path(href).resolve().parent
    inputs = [{"href": os.fspath(p), "file:size": _size(p), "file:checksum": file_checksum(p)} for p in product.inputs]
    props: dict[str, Any] = {
        "processing:software": {SOFTWARE: __version__},
        "processing:lineage": product.command or SOFTWARE,
        "processing:datetime": created.isoformat().replace("+00:00", "Z"),
        "rectify:datetime_source": "acquisition" if product.acquired is not None else "processing",
        "rectify:accuracy": _json_safe(dict(product.accuracy)),
        "rectify:options": _json_safe(dict(product.options)),
        "rectify:inputs": inputs,
    }
    if geometry is None:
        props["rectify:frame"] = "pixel"
    item = pystac.Item(id=product.item_id, geometry=geometry, bbox=bbox, datetime=when, properties=props,
                       stac_extensions=[PROCESSING_SCHEMA])
    if product.grid is not None:
        _apply_grid(ProjectionExtension.ext(item, add_if_missing=True), product.grid)
    FileExtension.add_to(item)
    for key, a in product.assets.items():
        p = Path(a.path)
        rel = os.path.relpath(p.resolve(), folder)
        asset = pystac.Asset(href=Path(rel).as_posix(), title=a.title,
                             media_type=a.media_type or MEDIA_TYPES.get(p.suffix.lower()), roles=list(a.roles))
        item.add_asset(key, asset)
        data = a.source if a.source is not None else p
        FileExtension.ext(asset).apply(size=_size(data), checksum=file_checksum(data))
        if a.grid is not None:
            _apply_grid(ProjectionExtension.ext(asset, add_if_missing=True), a.grid)
    return item


def _size(path: StrPath) -> int:
    try:
        return os.stat(path).st_size
    except OSError as err:
        raise RasterIOError(f"cannot read {str(path)!r}: {err.strerror or err}") from err


def stac_item_text(product: StacProduct, href: StrPath) -> str:
    """The Item of :func:`stac_item` as JSON text (no self link: the file can move with its assets)."""
    return json.dumps(stac_item(product, href).to_dict(include_self_link=False), indent=2) + "\n"


def write_stac_item(path: StrPath, product: StacProduct, *, overwrite: bool = False) -> Path:
    """Write the STAC Item of ``product`` at ``path`` (``<product>.stac.json`` by convention) atomically."""
    return atomic_write_text(path, stac_item_text(product, path), overwrite=overwrite)
