"""The view written as a static folder (``rectify view OUTDIR --static DIR``) that any web server can serve.

The folder holds the page and, under the same names the live server answers (:mod:`rectify.view.server`),
every answer: ``api/manifest.json``, ``api/layout.json``, ``api/obs/<i>.json``, ``api/tracks/<b>.json``,
``api/table/<t>.json``, ``api/raster/<r>.json``, copies of the report figures, pages and tables
(``files/...``) and the tiles of each raster from level 0 up to the deepest level whose tiles still fit
the tile budget (``max_tiles`` over all rasters, shared equally). What a static folder lacks, said in
its manifest (``static.note``) and on the page: beyond that level a raster shows no finer detail (the
live server reads any level on demand), so a large orthophoto or a large block's photos are not at full resolution.

The folder is built beside ``DIR`` under a hidden name and renamed into place at the end: an error leaves
nothing at ``DIR``.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import uuid
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from rectify.errors import InvalidInputError, RasterIOError
from rectify.view.server import Response, ViewApp

#: default budget of tiles in a static folder (all rasters together)
MAX_STATIC_TILES = 4000


@dataclass(frozen=True)
class StaticExport:
    """What :func:`write_static` wrote: the folder, its files and tiles, and each raster's deepest level."""

    path: Path
    files: int
    tiles: int
    levels: dict[int, int]
    bytes: int


def _tiles_to(width: int, height: int, tile: int, max_level: int, level: int) -> int:
    s = 2 ** (max_level - level)
    return math.ceil(width / (tile * s)) * math.ceil(height / (tile * s))


def static_levels(rasters: list[dict], max_tiles: int) -> dict[int, int]:
    """The deepest level of each raster whose tiles (levels 0..L together) fit its share of ``max_tiles``
    (level 0 always).

    >>> static_levels([{"id": 0, "width": 10000, "height": 10000, "tile": 256, "max_level": 6}], 100)
    {0: 3}
    """
    if not rasters:
        return {}
    share = max(1, int(max_tiles) // len(rasters))
    out = {}
    for r in rasters:
        total, best = 0, 0
        for lv in range(0, int(r["max_level"]) + 1):
            total += _tiles_to(int(r["width"]), int(r["height"]), int(r["tile"]), int(r["max_level"]), lv)
            if total > share and lv > 0:
                break
            best = lv
        out[int(r["id"])] = best
    return out


def write_static(app: ViewApp, dest: str | Path, *, overwrite: bool = False, max_tiles: int = MAX_STATIC_TILES,
                 progress: Callable[[int, int], None] | None = None) -> StaticExport:
    """Write the whole view of ``app``'s folder into ``dest`` (see the module docstring).

    Raises
    ------
    InvalidInputError
        ``dest`` exists (without ``overwrite``), is the result folder or lies inside it.
    RasterIOError
        A write failed (nothing is left at ``dest``).
    """
    out = Path(dest)
    root = app.data.contents.root
    target = out.resolve()
    if target == root or target.is_relative_to(root):
        raise InvalidInputError(f"--static {str(dest)!r} lies inside the result folder {str(root)!r}: "
                                "choose a folder outside it")
    if out.exists() and not overwrite:
        raise InvalidInputError(f"{str(dest)!r} exists; pass --overwrite to replace it")
    if out.exists() and not out.is_dir():
        raise InvalidInputError(f"--static {str(dest)!r} exists and is not a folder")
    manifest = dict(app.manifest())
    rasters = [r for r in manifest["rasters"] if "max_level" in r]
    levels = static_levels(rasters, max_tiles)
    lacking = [f"{r['label']}: levels 0..{levels[r['id']]} of 0..{r['max_level']}" for r in rasters
               if levels[r["id"]] < r["max_level"]]
    note = ("a static folder: every answer precomputed; " + (
        "rasters not at full resolution (tile budget " + str(max_tiles) + "): " + "; ".join(lacking)
        if lacking else "every raster at full resolution"))
    manifest["static"] = {"levels": {str(k): v for k, v in levels.items()}, "max_tiles": max_tiles, "note": note}
    out.parent.mkdir(parents=True, exist_ok=True)
    stage = out.parent / f".{out.name}.{uuid.uuid4().hex[:8]}.part"
    n_files = n_tiles = size = 0

    def put(rel: str, body: bytes) -> None:
        nonlocal n_files, size
        p = stage / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_bytes(body)
        n_files += 1
        size += len(body)

    def answer(rel: str) -> bytes:
        res: Response = app.respond("/" + rel)
        if res.status != 200:
            raise InvalidInputError(f"static view: {rel}: {res.body.decode(errors='replace').strip()}")
        return res.body

    try:
        stage.mkdir()
        put("index.html", app.static["index.html"])
        for name, body in app.static.items():
            put(f"static/{name}", body)
        put("api/manifest.json", json.dumps(manifest, separators=(",", ":")).encode())
        if manifest["kind"] == "block" and app.data.orientation() is not None:
            put("api/layout.json", answer("api/layout.json"))
        if app.data.observations() is not None:
            for im in manifest["images"]:
                put(f"api/obs/{im['i']}.json", answer(f"api/obs/{im['i']}.json"))
            for b in range(manifest["n_buckets"]):
                put(f"api/tracks/{b}.json", answer(f"api/tracks/{b}.json"))
        for r in manifest["rasters"]:
            if r["role"] != "photo":
                put(f"api/raster/{r['id']}.json", answer(f"api/raster/{r['id']}.json"))
        for t in manifest["tables"]:
            put(f"api/table/{t['t']}.json", answer(f"api/table/{t['t']}.json"))
            put(f"files/{t['csv']}", answer(f"files/{t['csv']}"))
            for f in t["figures"].values():
                if not (stage / "files" / f).exists():
                    put(f"files/{f}", answer(f"files/{f}"))
        for f in [*manifest["figures"], *manifest["reports"]]:
            if not (stage / "files" / f["href"]).exists():
                put(f"files/{f['href']}", answer(f"files/{f['href']}"))
        total = sum(sum(_tiles_to(r["width"], r["height"], r["tile"], r["max_level"], lv)
                        for lv in range(levels[r["id"]] + 1)) for r in rasters)
        for r in rasters:
            for lv in range(levels[r["id"]] + 1):
                s = 2 ** (r["max_level"] - lv)
                for ty in range(math.ceil(r["height"] / (r["tile"] * s))):
                    for tx in range(math.ceil(r["width"] / (r["tile"] * s))):
                        put(f"tiles/{r['id']}/{lv}/{tx}_{ty}.png", answer(f"tiles/{r['id']}/{lv}/{tx}_{ty}.png"))
                        n_tiles += 1
                        if progress is not None:
                            progress(n_tiles, total)
        if out.exists():
            shutil.rmtree(out)
        os.replace(stage, out)
    except OSError as err:
        shutil.rmtree(stage, ignore_errors=True)
        raise RasterIOError(f"cannot write the static view {str(dest)!r}: {err.strerror or err}") from None
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        raise
    return StaticExport(out, n_files, n_tiles, levels, size)
