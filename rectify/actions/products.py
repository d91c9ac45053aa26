"""The STAC Item every product command writes beside its output, in the step's transaction.

A product command (``rectify warp``, ``ortho``, ``mosaic``; ``stereo dense``, ``dense-rpc`` and
``block``) writes its main output through :func:`staged` (a temporary file inside the workspace's
transaction), then :func:`write_stac` builds the Item of :mod:`rectify.formats.stac` from the staged
bytes and stages it too: the product and its Item are renamed into place together, or neither is
(``docs/formats.md``, "STAC Items").

The Item's path is :func:`stac_path` (``<output stem>.stac.json`` beside a file; ``item.stac.json`` in
an output folder); it is planned with the product, so an existing Item is refused before any work
unless ``--overwrite``.
"""

from __future__ import annotations

import contextlib
import dataclasses
import re
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

from rectify.actions.workspace import StrPath, Workspace
from rectify.errors import RectifyError
from rectify.formats.stac import RasterGrid, StacAsset, StacProduct, stac_item_text
from rectify.raster.io import raster_info

__all__ = ["STAC_SUFFIX", "FOLDER_ITEM", "stac_path", "staged", "raster_grid", "raster_roles", "input_files",
           "options_of", "residual_accuracy", "stac_text", "write_stac"]

#: the suffix of the Item beside a product file
STAC_SUFFIX = ".stac.json"
#: the Item's name inside a product folder
FOLDER_ITEM = "item.stac.json"


def stac_path(product: StrPath, *, folder: bool = False) -> Path:
    """Where the Item of ``product`` goes: ``<stem>.stac.json`` beside a file, ``item.stac.json`` in a folder."""
    p = Path(product)
    if folder:
        return p / FOLDER_ITEM
    return p.with_name(p.stem + STAC_SUFFIX) if p.suffix else p.with_name(p.name + STAC_SUFFIX)


@contextlib.contextmanager
def staged(ws: Workspace, dst: StrPath) -> Iterator[Path]:
    """A transaction with ``dst`` staged: yields the temporary path to write the product to (writers called
    with it need ``overwrite=True``: the file exists, empty); everything staged in the block is renamed
    into place at its end, or removed on any error. An error naming the temporary file (or one beside
    it, ``<tmp>.body.tif``...) names ``dst`` instead."""
    with ws.transaction(), ws.output(dst) as tmp:
        try:
            yield tmp
        except RectifyError as err:
            msg = str(err)
            if str(tmp) not in msg:
                raise
            named = re.sub(re.escape(str(tmp)) + r"[^'\"]*", str(dst), msg)
            try:
                renamed = type(err)(named)
            except TypeError:  # an error class that needs more than a message: keep it as it is
                raise err from None
            raise renamed from err


def raster_grid(path: StrPath) -> RasterGrid | None:
    """The grid of a raster (None when it has no CRS)."""
    info = raster_info(Path(path))
    if info.crs is None:
        return None
    a, b, c, d, e, f = tuple(info.transform)[:6]
    return RasterGrid(info.crs, (a, b, c, d, e, f), info.width, info.height)


def raster_roles(path: StrPath) -> tuple[str, ...]:
    """STAC roles of a raster product: ``data``, and ``visual`` for 8-bit images of 1, 3 or 4 bands."""
    info = raster_info(Path(path))
    return ("data", "visual") if info.dtype == "uint8" and info.count in (1, 3, 4) else ("data",)


def residual_accuracy(table: Any, prefix: str) -> dict[str, float]:
    """The RMSE of a residual table (:class:`rectify.geometry.residuals.ResidualTable`) as accuracy figures named
    with its units: ``<prefix>_rmse_<units>``, ``<prefix>_check_rmse_<units>``, ``<prefix>_count``."""
    if table is None:
        return {}
    sm = table.summary()
    unit = "".join(c if c.isalnum() else "_" for c in str(sm.get("units") or "units")).strip("_")
    out = {f"{prefix}_count": float(sm["n_points"])}
    if sm.get("n_fit"):
        out[f"{prefix}_rmse_{unit}"] = sm["rmse"]
    if sm.get("rmse_check") is not None:
        out[f"{prefix}_check_rmse_{unit}"] = sm["rmse_check"]
    return out


def input_files(*paths: StrPath | None) -> list[Path]:
    """The files of the inputs: each file, and the files of a folder input (a COLMAP model), in order."""
    out: list[Path] = []
    for p in paths:
        if p is None:
            continue
        q = Path(p)
        if q.is_dir():
            out += sorted(f for f in q.iterdir() if f.is_file())
        elif q.is_file() and q not in out:
            out.append(q)
    return out


def options_of(*objs: Any, **extra: Any) -> dict[str, Any]:
    """The options of a run as one dict: dataclass fields (nested ones as dicts), then ``extra``."""
    out: dict[str, Any] = {}
    for o in objs:
        if o is not None and dataclasses.is_dataclass(o) and not isinstance(o, type):
            out.update(dataclasses.asdict(o))
    out.update({k: v for k, v in extra.items() if v is not None})
    return out


def stac_text(item: StrPath, *, item_id: str, assets: Mapping[str, StacAsset], grid: RasterGrid | None = None,
              footprint: tuple[str, tuple[float, float, float, float]] | None = None,
              accuracy: Mapping[str, float] | None = None, command: str, options: Mapping[str, Any] | None = None,
              inputs: Sequence[StrPath | None] = ()) -> str:
    """The text of the Item :func:`write_stac` stages (for a job that stages the Item's file itself)."""
    product = StacProduct(item_id=item_id, assets=dict(assets), grid=grid, footprint=footprint,
                          accuracy=dict(accuracy or {}), command=command, options=dict(options or {}),
                          inputs=input_files(*inputs), unlocated=grid is None and footprint is None)
    return stac_item_text(product, item)


def write_stac(ws: Workspace, item: StrPath, *, item_id: str, assets: Mapping[str, StacAsset],
               grid: RasterGrid | None = None, footprint: tuple[str, tuple[float, float, float, float]] | None = None,
               accuracy: Mapping[str, float] | None = None, command: str, options: Mapping[str, Any] | None = None,
               inputs: Sequence[StrPath | None] = ()) -> Path:
    """Stage the STAC Item of a product at ``item`` (inside the workspace's transaction).

    Parameters
    ----------
    item : path
        The Item file (:func:`stac_path`).
    assets : dict of str -> StacAsset
        The product's files at their final paths; ``source`` the staged file when it is not there yet.
    grid, footprint
        Where the product lies (a raster's grid, or a CRS and bounds); neither: in no map frame (a
        null geometry).
    accuracy : dict, optional
        The product's accuracy figures (units in the names).
    command : str
        ``rectify ortho``, ...
    options : dict, optional
    inputs : paths
        The input files (hashed; folders by their files).

    Raises
    ------
    RasterIOError, InvalidInputError, CRSError
        An unreadable file, no asset or extent, a CRS PROJ cannot place in WGS 84: the transaction
        then writes nothing.
    """
    return ws.write_text(item, stac_text(item, item_id=item_id, assets=assets, grid=grid, footprint=footprint,
                                         accuracy=accuracy, command=command, options=options, inputs=inputs))
