"""Test support of the image side (not part of the library).

- :func:`verify_report`: every number shown in a report's ``report.html`` equals its CSV and JSON values.
- :func:`tiff_ifds`, :func:`cog_problems`: the TIFF directory chain and the Cloud Optimized GeoTIFF layout.
"""

from __future__ import annotations

import csv
import json
import math
import os
import re
import struct
from dataclasses import dataclass
from html.parser import HTMLParser
from pathlib import Path
from typing import Any

from rectify.errors import RasterIOError
from rectify.report.builder import _flatten, format_number

__all__ = ["verify_report", "tiff_ifds", "cog_problems", "TiffIfd"]


# --------------------------------------------------------------------------- report check
class _Cells(HTMLParser):
    """Collect every element with ``data-key``: (scope, key) -> list of (data-value, data-json, text)."""

    def __init__(self) -> None:
        super().__init__(convert_charrefs=True)
        self.cells: dict[tuple[str, str], list[tuple[str | None, str | None, str]]] = {}
        self._open: tuple[str, str, str | None, str | None] | None = None
        self._text: list[str] = []

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        a = dict(attrs)
        if "data-key" in a:
            self._open = (a.get("data-scope") or "", a["data-key"] or "", a.get("data-value"), a.get("data-json"))
            self._text = []

    def handle_data(self, data: str) -> None:
        if self._open is not None:
            self._text.append(data)

    def handle_endtag(self, tag: str) -> None:
        if tag == "td" and self._open is not None:
            scope, key, value, js = self._open
            self.cells.setdefault((scope, key), []).append((value, js, "".join(self._text).strip()))
            self._open = None


def _same_number(cell: tuple[str | None, str | None, str], expected: Any) -> bool:
    value, _, text = cell
    if expected is None or (isinstance(expected, float) and not math.isfinite(expected)):
        return value in ("", None) and text == "n/a"
    if value in ("", None):
        return False
    num: Any = int(value) if re.fullmatch(r"-?\d+", value) else float(value)
    return float(num) == float(expected) and text == format_number(num)


def verify_report(out_dir: str | os.PathLike) -> list[str]:
    """Check that every number shown in ``report.html`` equals the CSV and ``report.json`` values.

    Compares each summary cell with ``report.json``, each residual-row cell with
    the table's CSV (exact value in ``data-value``, shown text = 4 significant
    digits) and reports number-bearing cells that correspond to nothing.

    Returns
    -------
    list of str
        Discrepancies; empty when the page agrees with the files.

    Raises
    ------
    RasterIOError
        If the report files cannot be read.
    """
    root = Path(out_dir)
    try:
        doc = json.loads((root / "report.json").read_text())
        page = (root / "report.html").read_text(encoding="utf-8")
    except (OSError, ValueError) as err:
        raise RasterIOError(f"cannot read the report in {str(root)!r}: {err}") from err
    parser = _Cells()
    parser.feed(page)
    cells = parser.cells
    problems: list[str] = []
    seen: set[tuple[str, str]] = set()

    def check(key: tuple[str, str], expected: Any) -> None:
        seen.add(key)
        if key not in cells:
            problems.append(f"{key}: missing from the HTML (expected {expected!r})")
            return
        for cell in cells[key]:
            if not _same_number(cell, expected):
                problems.append(f"{key}: HTML shows {cell[2]!r} (data-value {cell[0]!r}), files say {expected!r}")

    for t in doc.get("tables", []):
        slug = t["slug"]
        for key, val in _flatten(t["summary"]):
            if key in ("step", "units"):
                continue
            if isinstance(val, str):
                seen.add((slug, key))
                if [c[2] for c in cells.get((slug, key), [])] != [val] * len(cells.get((slug, key), [1])):
                    problems.append(f"{(slug, key)}: text differs from {val!r}")
            elif isinstance(val, bool):
                seen.add((slug, key))
                if any(c[2] != format_number(val) for c in cells.get((slug, key), [])):
                    problems.append(f"{(slug, key)}: HTML differs from {val!r}")
            elif isinstance(val, (list, dict)):
                seen.add((slug, key))
            else:
                check((slug, key), val)
        seen.add((slug, "units"))
        try:
            lines = [ln for ln in (root / t["files"]["csv"]).read_text().splitlines() if not ln.startswith("#")]
        except OSError as err:
            raise RasterIOError(f"cannot read {t['files']['csv']!r}: {err}") from err
        for i, row in enumerate(csv.DictReader(lines)):
            for col, val in row.items():
                key = (f"{slug}#{i}", col)
                if col == "id" or key not in cells:
                    continue  # rows beyond html_max_rows are only in the CSV
                num = None if val in ("nan", "") else (int(val) if re.fullmatch(r"-?\d+", val) else float(val))
                check(key, num)
    for key, val in _flatten(doc.get("summary") or {}):
        k = ("summary", key)
        seen.add(k)
        got = cells.get(k)
        if got is None:
            problems.append(f"{k}: missing from the HTML")
        elif isinstance(val, list):
            if any(c[1] is None or json.loads(c[1]) != val for c in got):
                problems.append(f"{k}: HTML list differs from {val!r}")
        elif isinstance(val, str):
            if any(c[2] != val for c in got):
                problems.append(f"{k}: HTML text differs from {val!r}")
        elif isinstance(val, bool):
            if any(c[2] != format_number(val) for c in got):
                problems.append(f"{k}: HTML shows {got[0][2]!r}, files say {val!r}")
        else:
            check(k, val)
    extra = sorted(k for k in cells if k not in seen)
    problems += [f"{k}: number in the HTML with no counterpart in the CSV/JSON" for k in extra]
    return problems


# --------------------------------------------------------------------------- TIFF structure (COG checks)
_TAG_TILE_OFFSETS, _TAG_STRIP_OFFSETS, _TAG_SUBFILE = 324, 273, 254
_TAG_TILE_WIDTH, _TAG_IMAGE_WIDTH, _TAG_IMAGE_LENGTH = 322, 256, 257


@dataclass(frozen=True)
class TiffIfd:
    """One image file directory of a TIFF: where it sits and what it describes."""

    offset: int
    width: int
    height: int
    tiled: bool
    subfile_type: int
    data_offsets: tuple[int, ...]


def tiff_ifds(path: str | Path) -> list[TiffIfd]:
    """Parse the IFD chain of a (Big)TIFF: offsets, sizes, tiling and data offsets.

    Raises
    ------
    RasterIOError
        If the file is not a TIFF.
    """
    p = Path(path)
    with open(p, "rb") as f:
        head = f.read(16)
        if head[:2] not in (b"II", b"MM"):
            raise RasterIOError(f"{str(p)!r} is not a TIFF file")
        e = "<" if head[:2] == b"II" else ">"
        magic = struct.unpack(e + "H", head[2:4])[0]
        big = magic == 43
        if magic not in (42, 43):
            raise RasterIOError(f"{str(p)!r} has a bad TIFF magic number {magic}")
        off = struct.unpack(e + ("Q" if big else "I"), head[8:16] if big else head[4:8])[0]
        types = {1: 1, 2: 1, 3: 2, 4: 4, 5: 8, 6: 1, 7: 1, 8: 2, 9: 4, 10: 8, 11: 4, 12: 8, 16: 8, 17: 8, 18: 8}
        fmt = {1: "B", 3: "H", 4: "I", 16: "Q", 6: "b", 8: "h", 9: "i", 17: "q", 18: "Q"}
        out: list[TiffIfd] = []
        seen = set()
        while off and off not in seen:
            seen.add(off)
            f.seek(off)
            n = struct.unpack(e + ("Q" if big else "H"), f.read(8 if big else 2))[0]
            esz = 20 if big else 12
            raw = f.read(n * esz)
            tags: dict[int, tuple[int, ...]] = {}
            for i in range(n):
                ent = raw[i * esz:(i + 1) * esz]
                tag, typ = struct.unpack(e + "HH", ent[:4])
                cnt = struct.unpack(e + ("Q" if big else "I"), ent[4:12] if big else ent[4:8])[0]
                val = ent[12:20] if big else ent[8:12]
                if typ not in fmt or tag not in (_TAG_TILE_OFFSETS, _TAG_STRIP_OFFSETS, _TAG_SUBFILE,
                                                 _TAG_TILE_WIDTH, _TAG_IMAGE_WIDTH, _TAG_IMAGE_LENGTH):
                    continue
                size = types[typ] * cnt
                if size > len(val):
                    pos = f.tell()
                    f.seek(struct.unpack(e + ("Q" if big else "I"), val)[0])
                    data = f.read(size)
                    f.seek(pos)
                else:
                    data = val[:size]
                tags[tag] = struct.unpack(e + fmt[typ] * cnt, data)
            nxt = f.read(8 if big else 4)
            tiled = _TAG_TILE_WIDTH in tags
            out.append(TiffIfd(off, tags.get(_TAG_IMAGE_WIDTH, (0,))[0], tags.get(_TAG_IMAGE_LENGTH, (0,))[0],
                               tiled, tags.get(_TAG_SUBFILE, (0,))[0],
                               tags.get(_TAG_TILE_OFFSETS if tiled else _TAG_STRIP_OFFSETS, ())))
            off = struct.unpack(e + ("Q" if big else "I"), nxt)[0] if len(nxt) == (8 if big else 4) else 0
    return out


def cog_problems(path: str | Path) -> list[str]:
    """Check the Cloud Optimized GeoTIFF layout, as GDAL's ``validate_cloud_optimized_geotiff.py``.

    Checks: the main image is tiled; overviews exist when the image is larger
    than a tile (512 px); every overview and mask is tiled; the overviews come
    in decreasing size; all IFDs precede the image data; the full-resolution
    image's data come after the overviews' data (smallest overview first).

    Returns
    -------
    list of str
        Problems found (empty for a valid COG).
    """
    ifds = tiff_ifds(path)
    errs: list[str] = []
    if not ifds:
        return ["no IFD"]
    main = ifds[0]
    if not main.tiled:
        errs.append("the main image is not tiled")
    images = [d for d in ifds if not d.subfile_type & 4]  # bit 2: transparency mask
    ovr = images[1:]
    if max(main.width, main.height) > 512 and not ovr:
        errs.append(f"no overviews for a {main.width} x {main.height} image")
    for i, d in enumerate(ifds[1:], 1):
        if not d.tiled:
            errs.append(f"IFD {i} ({d.width} x {d.height}) is not tiled")
    for a, b in zip(images, images[1:], strict=False):
        if not (b.width < a.width and b.height <= a.height):
            errs.append(f"overviews are not in decreasing size: {a.width} then {b.width}")
    first_data = min((min(o) for d in ifds for o in [[x for x in d.data_offsets if x > 0]] if o), default=None)
    last_ifd = max(d.offset for d in ifds)
    if first_data is not None and last_ifd > first_data:
        errs.append(f"an IFD (at {last_ifd}) comes after image data (first at {first_data})")
    main_data = [x for x in main.data_offsets if x > 0]
    for d in ovr:
        od = [x for x in d.data_offsets if x > 0]
        if od and main_data and min(main_data) < max(od):
            errs.append(f"full-resolution data (from {min(main_data)}) precede the data of the "
                        f"{d.width} x {d.height} overview (up to {max(od)})")
            break
    for a, b in zip(ovr, ovr[1:], strict=False):
        da, db = [x for x in a.data_offsets if x > 0], [x for x in b.data_offsets if x > 0]
        if da and db and min(da) < max(db):
            errs.append(f"overview {a.width} x {a.height} data precede those of the smaller {b.width} overview")
    return errs
