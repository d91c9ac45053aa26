"""Readers of RPC models (``docs/ortho.md``): ``_RPC.TXT``, ``.RPB``, DIMAP v2 and DigitalGlobe XML, GeoTIFF tags;
writers of ``_RPC.TXT`` and ``.RPB`` (:func:`rpc_txt_text`, :func:`rpb_text`); the tie-point and GCP CSVs of
``rectify rpc-adjust`` (:func:`read_rpc_ties`, :func:`read_rpc_gcps`; ``docs/rpc_adjust.md``).

:func:`read_rpc` reads any of them by suffix and content; :func:`rpc_from_raster` reads the RPC tags of a
raster (or the sidecar file GDAL finds beside it) through :func:`rectify.raster.io.raster_rpc_tags`. The
model they build is :class:`rectify.geometry.rpc.RPC` (its pixel convention: ``col = sample``,
``row = line``; DIMAP's 1-based offsets are reduced by 1 on reading).
"""

from __future__ import annotations

import math
import re
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from rectify.errors import InvalidInputError, RasterIOError
from rectify.formats.common import load_table, need_columns
from rectify.geometry.rpc import RPC, RPC_COEFFICIENTS
from rectify.raster.io import raster_rpc_tags

__all__ = ["RpcMeasurements", "read_rpc", "read_rpc_gcps", "read_rpc_ties", "rpb_text", "rpc_from_raster",
           "rpc_txt_text"]


def _num(text: str, what: str, source: str) -> float:
    m = re.match(r"\s*([-+]?(\d+\.?\d*|\.\d+)([eEdD][-+]?\d+)?)", text)
    if not m:
        raise InvalidInputError(f"RPC {source}: {what} is not a number: {text.strip()[:40]!r}")
    return float(m.group(1).replace("D", "E").replace("d", "e"))


def _from_txt(text: str, source: str) -> RPC:
    """IKONOS / Planet / SkySat ``KEY: value`` text (``_RPC.TXT``)."""
    vals: dict[str, str] = {}
    for line in text.splitlines():
        if ":" in line:
            k, v = line.split(":", 1)
            vals[k.strip().upper()] = v
    keys = {"line_off": "LINE_OFF", "samp_off": "SAMP_OFF", "lat_off": "LAT_OFF", "long_off": "LONG_OFF",
            "height_off": "HEIGHT_OFF", "line_scale": "LINE_SCALE", "samp_scale": "SAMP_SCALE",
            "lat_scale": "LAT_SCALE", "long_scale": "LONG_SCALE", "height_scale": "HEIGHT_SCALE"}
    d: dict[str, Any] = {}
    for k, key in keys.items():
        if key not in vals:
            raise InvalidInputError(f"RPC {source}: missing key {key}")
        d[k] = _num(vals[key], key, source)
    for k in RPC_COEFFICIENTS:
        c = []
        for i in range(1, 21):
            key = f"{k.upper()}_{i}"
            if key not in vals:
                raise InvalidInputError(f"RPC {source}: missing key {key}")
            c.append(_num(vals[key], key, source))
        d[k] = c
    for k, key in (("err_bias", "ERR_BIAS"), ("err_rand", "ERR_RAND")):
        d[k] = _num(vals[key], key, source) if key in vals else None
    return RPC.from_dict(d, source=source)


_RPB_KEYS = {"lineoffset": "line_off", "sampoffset": "samp_off", "latoffset": "lat_off",
             "longoffset": "long_off", "heightoffset": "height_off", "linescale": "line_scale",
             "sampscale": "samp_scale", "latscale": "lat_scale", "longscale": "long_scale",
             "heightscale": "height_scale", "linenumcoef": "line_num_coeff", "linedencoef": "line_den_coeff",
             "sampnumcoef": "samp_num_coeff", "sampdencoef": "samp_den_coeff", "errbias": "err_bias",
             "errrand": "err_rand"}


def _from_rpb(text: str, source: str) -> RPC:
    """DigitalGlobe / Maxar ``.RPB`` (``key = value;``, coefficient lists in parentheses)."""
    d: dict[str, Any] = {}
    for m in re.finditer(r"(\w+)\s*=\s*(\([^)]*\)|[^;\n]*);", text):
        key = _RPB_KEYS.get(m.group(1).lower())
        if key is None:
            continue
        v = m.group(2).strip()
        if v.startswith("("):
            d[key] = [_num(x, m.group(1), source) for x in v.strip("()").split(",") if x.strip()]
        else:
            d[key] = _num(v, m.group(1), source)
    return RPC.from_dict(d, source=source)


def _from_xml(text: str, source: str) -> RPC:
    try:
        root = ET.fromstring(text.encode() if text.lstrip().startswith("<?xml") else text)
    except ET.ParseError as err:
        raise InvalidInputError(f"RPC {source}: not valid XML: {err}") from None
    if root.tag == "Dimap_Document" or root.find(".//Rational_Function_Model") is not None:
        return _from_dimap(root, source)
    rpb = root.find(".//RPB/IMAGE")
    if rpb is not None:
        return _from_isd(rpb, source)
    raise InvalidInputError(f"RPC {source}: XML has neither a DIMAP Rational_Function_Model nor an RPB/IMAGE block")


def _text(el, tag: str, source: str) -> str:
    x = el.find(f".//{tag}")
    if x is None or x.text is None:
        raise InvalidInputError(f"RPC {source}: missing XML element {tag}")
    return x.text


def _from_dimap(root, source: str) -> RPC:
    """DIMAP v2 (Pleiades, SPOT 6/7): Inverse_Model is ground -> image; 1-based pixels (offsets - 1)."""
    inv = root.find(".//Inverse_Model")
    val = root.find(".//RFM_Validity")
    if inv is None or val is None:
        raise InvalidInputError(f"RPC {source}: DIMAP file lacks Inverse_Model or RFM_Validity")
    d: dict[str, Any] = {}
    for k, tag in (("samp_num_coeff", "SAMP_NUM_COEFF"), ("samp_den_coeff", "SAMP_DEN_COEFF"),
                   ("line_num_coeff", "LINE_NUM_COEFF"), ("line_den_coeff", "LINE_DEN_COEFF")):
        d[k] = [_num(_text(inv, f"{tag}_{i}", source), f"{tag}_{i}", source) for i in range(1, 21)]
    for k, tag in (("long_scale", "LONG_SCALE"), ("long_off", "LONG_OFF"), ("lat_scale", "LAT_SCALE"),
                   ("lat_off", "LAT_OFF"), ("height_scale", "HEIGHT_SCALE"), ("height_off", "HEIGHT_OFF"),
                   ("samp_scale", "SAMP_SCALE"), ("samp_off", "SAMP_OFF"), ("line_scale", "LINE_SCALE"),
                   ("line_off", "LINE_OFF")):
        d[k] = _num(_text(val, tag, source), tag, source)
    d["samp_off"] -= 1.0
    d["line_off"] -= 1.0
    return RPC.from_dict(d, source=source)


def _from_isd(img, source: str) -> RPC:
    """DigitalGlobe ISD XML (``<RPB><IMAGE>``): the same fields as ``.RPB``."""
    d: dict[str, Any] = {}
    for tag, k in (("LINEOFFSET", "line_off"), ("SAMPOFFSET", "samp_off"), ("LATOFFSET", "lat_off"),
                   ("LONGOFFSET", "long_off"), ("HEIGHTOFFSET", "height_off"), ("LINESCALE", "line_scale"),
                   ("SAMPSCALE", "samp_scale"), ("LATSCALE", "lat_scale"), ("LONGSCALE", "long_scale"),
                   ("HEIGHTSCALE", "height_scale")):
        d[k] = _num(_text(img, tag, source), tag, source)
    for tag, k in (("LINENUMCOEF", "line_num_coeff"), ("LINEDENCOEF", "line_den_coeff"),
                   ("SAMPNUMCOEF", "samp_num_coeff"), ("SAMPDENCOEF", "samp_den_coeff")):
        d[k] = [_num(x, tag, source) for x in _text(img, tag, source).split()]
    for tag, k in (("ERRBIAS", "err_bias"), ("ERRRAND", "err_rand")):
        x = img.find(tag)
        d[k] = _num(x.text, tag, source) if x is not None and x.text else None
    return RPC.from_dict(d, source=source)


def rpc_from_raster(path: str | Path) -> RPC:
    """The RPC of a raster (GeoTIFF RPC tags, or a sidecar ``_RPC.TXT``/``.RPB`` GDAL finds).

    Raises
    ------
    RasterIOError
        Unreadable raster.
    InvalidInputError
        The raster has no RPC.
    """
    tags = raster_rpc_tags(path)
    if tags is None:
        raise InvalidInputError(f"raster {str(path)!r} has no RPC (no RPC tags and no _RPC.TXT/.RPB beside it)")
    return RPC.from_dict(tags, source=str(path))


def read_rpc(path: str | Path) -> RPC:
    """Read an RPC model from a GeoTIFF (tags), ``_RPC.TXT``, ``.RPB``, DIMAP v2 XML or DigitalGlobe XML.

    Raises
    ------
    RasterIOError
        The file is missing or unreadable.
    InvalidInputError
        The file is not an RPC model (the message names the missing key).
    """
    p = Path(path)
    if not p.is_file():
        raise RasterIOError(f"RPC file not found: {str(p)!r}")
    suffix = p.suffix.lower()
    if suffix in (".tif", ".tiff", ".ntf", ".jp2", ".vrt", ".img"):
        return rpc_from_raster(p)
    try:
        text = p.read_text(errors="replace")
    except OSError as err:
        raise RasterIOError(f"cannot read RPC file {str(p)!r}: {err}") from err
    stripped = text.lstrip()
    if stripped.startswith("<"):
        return _from_xml(stripped, str(p))
    if suffix == ".rpb" or re.search(r"lineNumCoef\s*=", text, re.IGNORECASE):
        return _from_rpb(text, str(p))
    if re.search(r"LINE_NUM_COEFF_1\s*:", text, re.IGNORECASE):
        return _from_txt(text, str(p))
    raise InvalidInputError(f"{str(p)!r} is not an RPC file (_RPC.TXT, .RPB, DIMAP or DigitalGlobe XML)")


# =========================================================================== writers
def rpc_txt_text(rpc: RPC) -> str:
    """The model as an ``_RPC.TXT`` text (``KEY: value``; the keys GDAL's ``GDALLoadRPCFile`` reads), in the
    RPC00B pixel frame (``col = sample``, ``row = line``)."""
    return rpc.to_rpc_txt()


def rpb_text(rpc: RPC, *, sat_id: str = "rectify", band_id: str = "P") -> str:
    """The model as a DigitalGlobe ``.RPB`` text (the ``BEGIN_GROUP = IMAGE`` block GDAL's ``GDALLoadRPBFile``
    reads), every number written with 17 significant digits."""
    def num(v: float) -> str:
        return f"{float(v):+.16E}"

    def coef(c: Any) -> str:
        return "(\n" + ",\n".join(f"\t\t\t{num(v)}" for v in c) + ")"
    fields = [("errBias", rpc.err_bias if rpc.err_bias is not None else -1.0),
              ("errRand", rpc.err_rand if rpc.err_rand is not None else -1.0),
              ("lineOffset", rpc.line_off), ("sampOffset", rpc.samp_off), ("latOffset", rpc.lat_off),
              ("longOffset", rpc.long_off), ("heightOffset", rpc.height_off), ("lineScale", rpc.line_scale),
              ("sampScale", rpc.samp_scale), ("latScale", rpc.lat_scale), ("longScale", rpc.long_scale),
              ("heightScale", rpc.height_scale)]
    lines = [f'satId = "{sat_id}";', f'bandId = "{band_id}";', 'SpecId = "RPC00B";', "BEGIN_GROUP = IMAGE"]
    lines += [f"\t{k} = {num(v)};" for k, v in fields]
    for key, k in (("lineNumCoef", "line_num_coeff"), ("lineDenCoef", "line_den_coeff"),
                   ("sampNumCoef", "samp_num_coeff"), ("sampDenCoef", "samp_den_coeff")):
        lines.append(f"\t{key} = {coef(getattr(rpc, k))};")
    lines += ["END_GROUP = IMAGE", "END;"]
    return "\n".join(lines) + "\n"


# =========================================================================== rpc-adjust tables
@dataclass(frozen=True, eq=False)
class RpcMeasurements:
    """Image measurements read from a CSV: image index (into the image list), point id, (col, row), sigma.

    Attributes
    ----------
    image : (M,) int64
    ids : tuple of str (M,)
    pixels : (M, 2) float64
        (col, row), px, pixel centres at integers.
    sigma : (M,) float64
        px; NaN where the file has none.
    """

    image: NDArray[np.int64]
    ids: tuple[str, ...]
    pixels: NDArray[np.float64]
    sigma: NDArray[np.float64]


def _image_index(name: str, images: Sequence[str | Path], path: str | Path, line: int) -> int:
    """The image a CSV cell names: the path as given, its file name or its stem."""
    hits = [j for j, im in enumerate(images) if name in (str(im), Path(im).name, Path(im).stem)]
    if len(set(hits)) == 1:
        return hits[0]
    if not hits:
        raise InvalidInputError(f"{str(path)!r} line {line}: image {name!r} is not one of the images "
                                f"{[Path(i).name for i in images]}")
    raise InvalidInputError(f"{str(path)!r} line {line}: image {name!r} names more than one image")


def _number(row: dict[str, str], key: str, line: int, path: str | Path) -> float:
    try:
        v = float(row[key])
    except ValueError:
        raise InvalidInputError(f"{str(path)!r} line {line}: {key} is not a number: {row[key]!r}") from None
    if not math.isfinite(v):
        raise InvalidInputError(f"{str(path)!r} line {line}: {key} is not finite: {row[key]!r}")
    return v


def _measurements(rows: list[dict[str, str]], lines: list[int], images: Sequence[str | Path],
                  path: str | Path) -> RpcMeasurements:
    im, ids, px, sg = [], [], [], []
    seen: set[tuple[int, str]] = set()
    for row, no in zip(rows, lines, strict=True):
        j = _image_index(row["image"], images, path, no)
        pid = row["id"]
        if not pid:
            raise InvalidInputError(f"{str(path)!r} line {no}: empty id")
        if (j, pid) in seen:
            raise InvalidInputError(f"{str(path)!r} line {no}: point {pid!r} is measured twice in image "
                                    f"{row['image']!r}")
        seen.add((j, pid))
        im.append(j)
        ids.append(pid)
        px.append((_number(row, "col", no, path), _number(row, "row", no, path)))
        s = row.get("sigma", "")
        sv = _number(row, "sigma", no, path) if s else float("nan")
        if s and not sv > 0:
            raise InvalidInputError(f"{str(path)!r} line {no}: sigma must be > 0 px; got {s!r}")
        sg.append(sv)
    return RpcMeasurements(np.array(im, np.int64), tuple(ids), np.array(px, np.float64).reshape(-1, 2),
                           np.array(sg, np.float64))


def read_rpc_ties(path: str | Path, images: Sequence[str | Path]) -> RpcMeasurements:
    """A tie-point CSV ``image,id,col,row[,sigma]``: one row per measurement; rows of one id in several images
    are one ground point. ``image`` is an image's path as given, its file name or its stem.

    Raises
    ------
    RasterIOError
        Missing or unreadable file.
    InvalidInputError
        Missing columns, an unknown image, a bad number, a point measured twice in one image.
    """
    rows, lines, _crs, fields = load_table(path, "tie-point rows")
    need_columns(fields, ("image", "id", "col", "row"), path)
    return _measurements(rows, lines, images, path)


def read_rpc_gcps(path: str | Path, images: Sequence[str | Path], *, sigma_xy: float = 0.5, sigma_h: float = 1.0
                  ) -> tuple[RpcMeasurements, dict[str, tuple[tuple[float, float, float], tuple[float, float]]]]:
    """A GCP CSV ``id,image,col,row,lon,lat,h[,sigma_xy,sigma_h,sigma]``: one row per image measurement of a
    GCP (lon, lat in WGS 84 degrees, h metres above the ellipsoid; sigma_xy / sigma_h its ground standard
    deviations in metres, default ``sigma_xy`` / ``sigma_h``; sigma the measurement's px). The rows of one
    id must give the same ground coordinates.

    Returns
    -------
    (RpcMeasurements, {id: ((lon, lat, h), (sigma_xy, sigma_h))})

    Raises
    ------
    InvalidInputError
        Missing columns, a bad number or sigma, a latitude outside [-90, 90], one id with two ground positions.
    """
    rows, lines, _crs, fields = load_table(path, "GCP rows")
    need_columns(fields, ("id", "image", "col", "row", "lon", "lat", "h"), path)
    ground: dict[str, tuple[tuple[float, float, float], tuple[float, float]]] = {}
    for row, no in zip(rows, lines, strict=True):
        g = (_number(row, "lon", no, path), _number(row, "lat", no, path), _number(row, "h", no, path))
        if not -90 <= g[1] <= 90:
            raise InvalidInputError(f"{str(path)!r} line {no}: lat {g[1]!r} is outside [-90, 90] degrees")
        sx = _number(row, "sigma_xy", no, path) if row.get("sigma_xy") else sigma_xy
        sh = _number(row, "sigma_h", no, path) if row.get("sigma_h") else sigma_h
        if not (sx > 0 and sh > 0):
            raise InvalidInputError(f"{str(path)!r} line {no}: GCP sigmas must be > 0 m; got {sx!r}, {sh!r}")
        pid = row["id"]
        if pid in ground and not np.allclose(ground[pid][0], g, rtol=0, atol=1e-9):
            raise InvalidInputError(f"{str(path)!r} line {no}: GCP {pid!r} has two ground positions "
                                    f"{list(ground[pid][0])} and {list(g)}")
        ground[pid] = (g, (sx, sh))
    return _measurements(rows, lines, images, path), ground
