"""The step's measurements read from its files, as the JSON the page draws (docs/view.md lists each answer).

Everything is read from the documented files (docs/formats.md), never through the code that wrote them
(``rectify`` does not import ``stereo``): a block's ``observations.csv``, ``orientation.json`` and
``points.csv``; every report folder's ``report.json`` and its residual table CSVs; ``dense.json``,
``dense_rpc.json`` and ``ortho_report.json``. Files are read once, on the first request that needs them,
and kept (a block of 500 photos and 150 000 observations takes about 20 MB).

Conventions of the answers: pixels x = column right, y = row down, centre of the top-left pixel at
(0, 0); residuals adjusted - observed (the files' sign); the *standardised residual* of an image
observation is ``|v| / sigma_px`` (its residual in units of its a-priori standard deviation); a
residual table's is its ``normalised`` column. NaN is ``null``.
"""

from __future__ import annotations

import math
import threading
import zlib
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import Any

import numpy as np
from numpy.typing import NDArray

from rectify.atomic import read_json
from rectify.errors import InvalidInputError, RectifyError
from rectify.formats.common import TableReader
from rectify.geometry.camera import Camera
from rectify.raster.viewtiles import TILE, TileSource, max_level_for
from rectify.view.folder import FolderContents, RasterEntry, find_photo

MAX_OBSERVATIONS = 20_000_000
MAX_TABLE_ROWS = 2_000_000
#: tracks per bucket file of ``api/tracks/<b>.json`` (about)
TRACKS_PER_BUCKET = 256
#: points of the plan view of the layout (a regular subsample beyond)
MAX_PLAN_POINTS = 20_000
#: first words of band descriptions shown as a coloured band of their own (a DSM's sigma_Z, a difference to a
#: reference DEM, a disparity's confidence)
BAND_WORDS = frozenset({"sigma", "sigma_z", "std", "std_z", "difference", "diff", "dz", "confidence",
                        "disparity", "count"})


def _num(v: float) -> float | None:
    return None if not math.isfinite(v) else float(v)


def _cell(text: str) -> float | str | None:
    t = text.strip()
    if t == "" or t.lower() == "nan":
        return None
    try:
        v = float(t)
    except ValueError:
        return t
    return v if math.isfinite(v) else None


def bucket_of(ident: str, n_buckets: int) -> int:
    """The track bucket of a point id: ``crc32(utf-8 id) % n_buckets`` (the page computes the same).

    >>> bucket_of("t1", 1), bucket_of("t1", 7)
    (0, 2)
    """
    return zlib.crc32(ident.encode("utf-8")) % max(1, int(n_buckets))


@dataclass(frozen=True)
class Observations:
    """A block's ``observations.csv`` as arrays, sorted by image then file order.

    ``image`` (N,) int: index into ``names``; ``ids`` (N,) int: index into ``id_names``; ``col, row, vx,
    vy, sigma, weight`` (N,) float64 px; ``flag`` (N,) bool; ``starts`` (n_images + 1,) the slice of each
    image; ``redundancy`` (N,) the observations' redundancy numbers when the file has a ``redundancy``
    column (no step writes one yet), else None.
    """

    names: tuple[str, ...]
    id_names: tuple[str, ...]
    image: NDArray[np.int64]
    ids: NDArray[np.int64]
    col: NDArray[np.float64]
    row: NDArray[np.float64]
    vx: NDArray[np.float64]
    vy: NDArray[np.float64]
    sigma: NDArray[np.float64]
    weight: NDArray[np.float64]
    flag: NDArray[np.bool_]
    starts: NDArray[np.int64]
    redundancy: NDArray[np.float64] | None = None

    @classmethod
    def read(cls, path: Path, order: tuple[str, ...] = ()) -> Observations:
        """Read ``observations.csv``; ``order`` lists image names first (the orientation's order)."""
        with TableReader(path) as t:
            c = t.read("observation rows", numbers=("col", "row", "sigma_px", "residual_x_px", "residual_y_px",
                                                    "weight", "flagged", "redundancy"),
                       texts=("image", "id"), empty=("weight", "flagged", "sigma_px", "redundancy"),
                       max_rows=MAX_OBSERVATIONS)
        missing = [k for k in ("image", "id", "col", "row", "residual_x_px", "residual_y_px") if k not in c.fields]
        if missing:
            raise InvalidInputError(f"{str(path)!r} is not an observations CSV: no column(s) {missing}")
        names = list(order)
        known = set(names)
        for n in dict.fromkeys(c.texts["image"]):
            if n not in known:
                names.append(n)
                known.add(n)
        pos = {n: i for i, n in enumerate(names)}
        img = np.fromiter((pos[n] for n in c.texts["image"]), np.int64, len(c.texts["image"]))
        id_names, ids = np.unique(np.array(c.texts["id"], dtype=object), return_inverse=True)
        o = np.argsort(img, kind="stable")
        num = c.numbers
        starts = np.searchsorted(img[o], np.arange(len(names) + 1))
        sig = num["sigma_px"]
        return cls(tuple(names), tuple(str(s) for s in id_names), img[o], ids.astype(np.int64)[o],
                   num["col"][o], num["row"][o], num["residual_x_px"][o], num["residual_y_px"][o],
                   np.where(np.isfinite(sig), sig, np.nan)[o], np.nan_to_num(num["weight"], nan=1.0)[o],
                   (np.nan_to_num(num["flagged"]) > 0)[o], starts.astype(np.int64),
                   num["redundancy"][o] if "redundancy" in c.fields else None)

    @property
    def standardised(self) -> NDArray[np.float64]:
        """``|v| / sigma_px`` of every observation (NaN where sigma is missing)."""
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.hypot(self.vx, self.vy) / self.sigma


class ViewData:
    """The answers of one result folder (thread-safe; files read on first use).

    Parameters
    ----------
    contents : FolderContents
        What :func:`rectify.view.folder.scan` found.
    max_open : int
        The most rasters kept open at once (each keeps its preview, up to 2048 x 2048 pixels); the least
        recently used is dropped beyond.
    """

    def __init__(self, contents: FolderContents, *, max_open: int = 8) -> None:
        self.contents = contents
        self._lock = threading.RLock()
        self._cache: dict[str, Any] = {}
        self._sources: OrderedDict[int, TileSource] = OrderedDict()
        self._max_open = max(1, int(max_open))

    def source(self, k: int) -> TileSource:
        """The tile source of raster ``k`` of the manifest (opened on first use, kept in a small LRU)."""
        entries = self.rasters()
        if not 0 <= k < len(entries):
            raise InvalidInputError(f"no raster number {k}")
        with self._lock:
            src = self._sources.pop(k, None)
            if src is None:
                e = entries[k]
                src = TileSource(str(e.path), mode=e.mode, band=e.band)
            self._sources[k] = src
            while len(self._sources) > self._max_open:
                self._sources.popitem(last=False)  # dropped, closed by the collector when no request holds it
            return src

    def _describe(self, k: int) -> dict[str, Any]:
        lay = self.source(k).layout
        return {"width": lay.width, "height": lay.height, "count": lay.count, "max_level": lay.max_level,
                "tile": lay.tile, "crs": lay.crs, "transform": list(lay.transform),
                "descriptions": list(lay.descriptions)}

    # ---------------------------------------------------------------- files
    def _once(self, key: str, make: Callable[[], Any]) -> Any:
        with self._lock:
            if key not in self._cache:
                self._cache[key] = make()
            return self._cache[key]

    def orientation(self) -> dict[str, Any] | None:
        """The block's ``orientation.json`` (or None).

        Raises
        ------
        InvalidInputError
            ``images`` is not a list of objects with an ``image`` name, or ``cameras`` not an object.
        """
        rel = self.contents.block_orientation

        def make() -> dict[str, Any] | None:
            if rel is None:
                return None
            doc = read_json(self.contents.root / rel, "block orientation")
            ims = doc.get("images") if isinstance(doc, dict) else None
            if not isinstance(ims, list) or not all(isinstance(im, dict) and "image" in im for im in ims):
                raise InvalidInputError(f"{str(self.contents.root / rel)!r}: 'images' must be a list of objects "
                                        "with an 'image' name")
            if not isinstance(doc.get("cameras", {}), dict):
                raise InvalidInputError(f"{str(self.contents.root / rel)!r}: 'cameras' must be an object")
            return doc

        return self._once("orientation", make)

    def observations(self) -> Observations | None:
        """The block's ``observations.csv`` (or None)."""
        rel = self.contents.observations

        def make() -> Observations | None:
            if rel is None:
                return None
            o = self.orientation()
            order = tuple(str(im.get("image")) for im in o.get("images", [])) if o else ()
            return Observations.read(self.contents.root / rel, order)

        return self._once("observations", make)

    def points(self) -> dict[str, Any] | None:
        """``points.csv``: ids and columns x, y, z, residual_mm, std_x, std_y, std_z (NaN where absent)."""
        rel = self.contents.points

        def make() -> dict[str, Any] | None:
            if rel is None:
                return None
            cols = ("x", "y", "z", "residual_mm", "std_x", "std_y", "std_z")
            with TableReader(self.contents.root / rel) as t:
                c = t.read("point rows", numbers=cols, texts=("id",), empty=cols, max_rows=MAX_OBSERVATIONS)
            out: dict[str, Any] = {k: c.numbers[k] for k in cols}
            out["id"] = c.texts["id"]
            out["index"] = {s: i for i, s in enumerate(c.texts["id"])}
            out["crs"] = c.crs
            return out

        return self._once("points", make)

    def reports(self) -> list[dict[str, Any]]:
        """Every ``report.json`` of the folder: ``{"dir": rel, "doc": report}`` (unreadable ones skipped)."""
        def make() -> list[dict[str, Any]]:
            out = []
            for rel in self.contents.reports:
                try:
                    doc = read_json(self.contents.root / rel, "report JSON")
                except RectifyError:
                    continue
                if isinstance(doc, dict):
                    out.append({"dir": PurePosixPath(rel).parent.as_posix(), "doc": doc})
            return out

        return self._once("reports", make)

    def tables(self) -> list[dict[str, Any]]:
        """The residual tables of every report: step, slug, units, components, CSV path and figures."""
        def make() -> list[dict[str, Any]]:
            out: list[dict[str, Any]] = []
            for rep in self.reports():
                base = "" if rep["dir"] in ("", ".") else rep["dir"] + "/"
                for t in rep["doc"].get("tables", []) or []:
                    files = t.get("files") or {}
                    csv = files.get("csv")
                    if not isinstance(csv, str) or (base + csv) not in self.contents.files:
                        continue
                    out.append({"t": len(out), "step": str(t.get("step", "")), "slug": str(t.get("slug", "")),
                                "units": str(t.get("units", "")), "components": list(t.get("components") or []),
                                "csv": base + csv, "summary": _jsonable(t.get("summary") or {}),
                                "figures": {k: base + v for k, v in files.items()
                                            if isinstance(v, str) and (base + v) in self.contents.files
                                            and k != "csv"}})
            return out

        return self._once("tables", make)

    def match_positions(self) -> dict[str, tuple[float, float]]:
        """The left-image pixel of every tie point of the folder's matches CSV (``matches.csv`` of ``stereo
        run`` / ``rectify match``: ``id,col_left,row_left,...``), by id; empty when there is none."""
        def make() -> dict[str, tuple[float, float]]:
            for rel in self.contents.files:
                if not PurePosixPath(rel).name.endswith("matches.csv"):
                    continue
                try:
                    with TableReader(self.contents.root / rel) as t:
                        if not {"id", "col_left", "row_left"} <= set(t.fields):
                            continue
                        c = t.read("match rows", numbers=("col_left", "row_left"), texts=("id",),
                                   max_rows=MAX_OBSERVATIONS)
                except RectifyError:
                    continue
                return {i: (float(x), float(y)) for i, x, y in zip(c.texts["id"], c.numbers["col_left"],
                                                                   c.numbers["row_left"], strict=True)}
            return {}

        return self._once("matches", make)

    def point_kinds(self) -> dict[str, str]:
        """Control and check point ids (from the reports' control and check tables): id -> kind."""
        def make() -> dict[str, str]:
            kinds: dict[str, str] = {}
            for t in self.tables():
                step = t["step"].lower()
                kind = "check" if "check" in step else "control" if "control" in step else None
                if kind is None:
                    continue
                for row in self.table(t["t"])["rows"]:
                    kinds.setdefault(str(row[0]), kind)
            return kinds

        return self._once("kinds", make)

    # ---------------------------------------------------------------- rasters
    def rasters(self) -> list[RasterEntry]:
        """The rasters of the manifest, by number: the folder's result rasters, then the block's photos."""
        def make() -> list[RasterEntry]:
            out = []
            root = self.contents.root
            for rel in self.contents.rasters:
                name = PurePosixPath(rel).name.lower()
                try:
                    with TileSource(str(root / rel)) as src:
                        desc = src.layout.descriptions
                except RectifyError:
                    continue  # not a raster GDAL reads: not shown
                is_dsm = "dsm" in name or (desc and desc[0].lower().startswith("height"))
                role, mode = ("dsm", "hillshade") if is_dsm else ("raster", "image")
                if name.startswith(("disparity", "confidence", "disp")) or (
                        not is_dsm and len(desc) and desc[0].split(":")[0].strip().lower() in BAND_WORDS):
                    role, mode = "band", "ramp"
                out.append(RasterEntry(root / rel, rel, role, mode, 1))
                for b, d in enumerate(desc[1:], start=2):
                    word = d.split(":")[0].strip().lower()
                    if is_dsm and word in BAND_WORDS:
                        out.append(RasterEntry(root / rel, f"{rel} band {b} ({word})", "band", "ramp", b))
            for name in self.photo_names():
                p = find_photo(name, self.contents.image_dirs)
                if p is not None:
                    out.append(RasterEntry(p, name, "photo", "image", 1))
            return out

        return self._once("rasters", make)

    def photo_names(self) -> tuple[str, ...]:
        """The block's image names (orientation order, then any only in the observations)."""
        o = self.orientation()
        names = [str(im.get("image")) for im in o.get("images", [])] if o else []
        obs = self.observations()
        if obs is not None:
            names += [n for n in obs.names if n not in set(names)]
        return tuple(names)

    def cameras(self) -> dict[str, Camera]:
        """The block's cameras (from ``orientation.json``; unreadable ones left out)."""
        def make() -> dict[str, Camera]:
            o = self.orientation() or {}
            out = {}
            for k, d in (o.get("cameras") or {}).items():
                try:
                    out[str(k)] = Camera.from_dict(dict(d))
                except (RectifyError, TypeError, ValueError):
                    continue
            return out

        return self._once("cameras", make)

    # ---------------------------------------------------------------- answers
    def manifest(self) -> dict[str, Any]:
        """What the folder holds: rasters (with their tile layout), block images, tables, figures, notes."""
        c = self.contents
        rasters: list[dict[str, Any]] = []
        photo_raster: dict[str, int] = {}
        for k, e in enumerate(self.rasters()):
            d = {"id": k, "label": e.label, "role": e.role, "mode": e.mode}
            if e.role == "photo":
                photo_raster[e.label] = k
            else:
                d.update(self._describe(k), band=e.band)
            rasters.append(d)
        images = []
        obs = self.observations()
        o = self.orientation() or {}
        cams = self.cameras()
        by_name = {str(im.get("image")): im for im in o.get("images", [])}
        for i, name in enumerate(self.photo_names()):
            cam = cams.get(str(by_name.get(name, {}).get("camera")))
            w: int | None = None
            h: int | None = None
            if cam is not None:
                w, h = cam.width, cam.height
            n = nf = 0
            if obs is not None and i < len(obs.names) and obs.names[i] == name:
                s0, s1 = int(obs.starts[i]), int(obs.starts[i + 1])
                n, nf = s1 - s0, int(obs.flag[s0:s1].sum())
                if w is None and n:
                    w = int(math.ceil(obs.col[s0:s1].max() + 1))
                    h = int(math.ceil(obs.row[s0:s1].max() + 1))
            kr = photo_raster.get(name)
            if kr is not None and w is not None and h is not None:
                rasters[kr].update(width=w, height=h, max_level=max_level_for(w, h), tile=TILE)
            elif kr is not None:
                rasters[kr].update(self._describe(kr))
                w, h = int(rasters[kr]["width"]), int(rasters[kr]["height"])
            images.append({"i": i, "name": name, "n_obs": n, "n_flagged": nf, "width": w, "height": h,
                           "raster": kr})
        figures = []
        html = []
        for rep in self.reports():
            base = "" if rep["dir"] in ("", ".") else rep["dir"] + "/"
            for title, f in (rep["doc"].get("figures") or {}).items():
                if isinstance(f, str) and base + f in c.files:
                    figures.append({"title": str(title), "href": base + f})
            if base + "report.html" in c.files:
                html.append({"title": str(rep["doc"].get("title", "report")), "href": base + "report.html"})
        notes = []
        for rel in c.dense:
            try:
                doc = read_json(c.root / rel, "result summary")
            except RectifyError:
                continue
            notes.append({"file": rel, "summary": _jsonable(_short(doc))})
        obs_n = len(obs.id_names) if obs is not None else 0
        kind = ("block" if c.block_orientation or c.observations else "pair" if c.pair_orientation
                else "dense" if any(r["role"] == "dsm" for r in rasters) else "rasters" if rasters else "tables")
        summary = _jsonable(o.get("summary") or {}) if o else {}
        return {"format": "rectify-stereo/view-manifest", "version": 1, "title": c.root.name, "kind": kind,
                "rasters": rasters, "images": images, "tables": self.tables(), "figures": figures,
                "reports": html, "notes": notes, "block_summary": summary,
                "datum": [str(s) for s in (o.get("datum") or [])] if o else [],
                "n_buckets": max(1, math.ceil(obs_n / TRACKS_PER_BUCKET)), "truncated": c.truncated,
                "static": None}

    def warm_up(self, limit: int | None = None) -> None:
        """Read the previews of the result rasters (at most ``limit``, default: as many as are kept open), so
        that the first coarse tiles are ready by the time the browser asks for them. Errors are left for the
        requests to report."""
        n = self._max_open if limit is None else limit
        for k, e in enumerate(self.rasters()[:n]):
            if e.role == "photo":
                break
            try:
                self.source(k).preview()
            except RectifyError:
                continue

    def raster_info(self, k: int) -> dict[str, Any]:
        """Raster ``k``'s rendering for the legend: mode, band, its description and the stretch limits (the
        2nd and 98th percentile of its preview; read on first use)."""
        e = self.rasters()[k] if 0 <= k < len(self.rasters()) else None
        if e is None or e.role == "photo":
            raise InvalidInputError(f"no result raster number {k}")
        src = self.source(k)
        desc = src.layout.descriptions[e.band - 1] if e.band <= len(src.layout.descriptions) else ""
        lo, hi = (0.0, 255.0) if e.mode == "image" and src.dtype == "uint8" else src.limits()  # uint8: as stored
        return {"id": k, "label": e.label, "mode": e.mode, "band": e.band, "description": desc,
                "limits": [_num(lo), _num(hi)], "dtype": src.dtype}

    def image_observations(self, i: int) -> dict[str, Any]:
        """The observations of block image ``i``: columns id, col, row, vx, vy, sigma, weight, flag, z, kind."""
        obs = self.observations()
        if obs is None or not 0 <= i < len(obs.names):
            raise InvalidInputError(f"no block image number {i}")
        s0, s1 = int(obs.starts[i]), int(obs.starts[i + 1])
        kinds = self.point_kinds()
        ids = [obs.id_names[j] for j in obs.ids[s0:s1]]
        z = obs.standardised[s0:s1]
        return {"image": obs.names[i], "i": i, "id": ids,
                "col": _list(obs.col[s0:s1]), "row": _list(obs.row[s0:s1]),
                "vx": _list(obs.vx[s0:s1]), "vy": _list(obs.vy[s0:s1]), "sigma": _list(obs.sigma[s0:s1]),
                "weight": _list(obs.weight[s0:s1]), "flag": [int(f) for f in obs.flag[s0:s1]],
                "z": _list(z), "kind": [kinds.get(s, "tie") for s in ids],
                **({"redundancy": _list(obs.redundancy[s0:s1])} if obs.redundancy is not None else {})}

    def track_bucket(self, b: int, n_buckets: int) -> dict[str, Any]:
        """The tracks of bucket ``b``: id -> its observations in every image, its ground point and kind."""
        obs = self.observations()
        if obs is None or not 0 <= b < n_buckets:
            raise InvalidInputError(f"no track bucket {b}")
        key = f"buckets{n_buckets}"

        def make() -> NDArray[np.int64]:
            return np.fromiter((bucket_of(s, n_buckets) for s in obs.id_names), np.int64, len(obs.id_names))

        of_id = self._once(key, make)
        sel = np.flatnonzero(of_id[obs.ids] == b)
        pts = self.points()
        kinds = self.point_kinds()
        z = obs.standardised
        out: dict[str, Any] = {}
        for j in sel:
            ident = obs.id_names[obs.ids[j]]
            tr = out.setdefault(ident, {"kind": kinds.get(ident, "tie"), "obs": [], "point": None})
            tr["obs"].append([int(obs.image[j]), _num(obs.col[j]), _num(obs.row[j]), _num(obs.vx[j]),
                              _num(obs.vy[j]), _num(obs.sigma[j]), _num(obs.weight[j]), int(obs.flag[j]),
                              _num(z[j])])
        if pts is not None:
            for ident, tr in out.items():
                k = pts["index"].get(ident)
                if k is not None:
                    tr["point"] = {c: _num(pts[c][k]) for c in ("x", "y", "z", "residual_mm", "std_x", "std_y",
                                                               "std_z")}
        return {"bucket": b, "n_buckets": n_buckets, "columns": ["image", "col", "row", "vx", "vy", "sigma",
                                                                 "weight", "flag", "z"], "tracks": out}

    def table(self, t: int) -> dict[str, Any]:
        """Residual table ``t`` of the manifest: its columns and rows (numbers, or text; NaN null)."""
        tabs = self.tables()
        if not 0 <= t < len(tabs):
            raise InvalidInputError(f"no residual table number {t}")
        rel = tabs[t]["csv"]

        def make() -> dict[str, Any]:
            with TableReader(self.contents.root / rel) as r:
                fields = r.fields
                c = r.read("residual rows", texts=fields, max_rows=MAX_TABLE_ROWS)
            cols = [c.texts[f] for f in fields]
            rows = [[cells[0], *(_cell(v) for v in cells[1:])] for cells in zip(*cols, strict=True)]
            names = list(fields)
            pos = self.match_positions() if "observed_1" not in names else None
            if pos:  # a one-component table (a pair's y-parallax): placed at the tie points of the left image
                names += ["col_left", "row_left"]
                rows = [[*r, *pos.get(str(r[0]), (None, None))] for r in rows]
            return {**{k: tabs[t][k] for k in ("t", "step", "units", "components", "csv")},
                    "columns": names, "rows": rows}

        return self._once(f"table{t}", make)

    def layout(self) -> dict[str, Any]:
        """The block in plan: projection centres with standard errors, footprints on the mean ground height,
        a subsample of the points, control and check points with their residuals."""
        o = self.orientation()
        if o is None:
            raise InvalidInputError("the folder holds no block orientation (orientation.json of stereo block)")
        pts = self.points()
        cams = self.cameras()
        z0 = None
        if pts is not None and np.isfinite(pts["z"]).any():
            z0 = float(np.nanmedian(pts["z"]))
        images = []
        for i, im in enumerate(o.get("images", [])):
            pos = np.asarray(im.get("position", [math.nan] * 3), float)
            rot = np.asarray(im.get("rotation", np.eye(3)), float)
            cam = cams.get(str(im.get("camera")))
            foot = footprint(cam, pos, rot, z0) if cam is not None and z0 is not None else None
            images.append({"i": i, "name": str(im.get("image")), "position": _list(pos),
                           "std": {k: _num(float(v)) for k, v in (im.get("std_errors") or {}).items()},
                           "footprint": foot})
        plan = None
        if pts is not None:
            n = len(pts["id"])
            step = max(1, math.ceil(n / MAX_PLAN_POINTS))
            sel = slice(0, n, step)
            plan = {"id": pts["id"][sel], "x": _list(pts["x"][sel]), "y": _list(pts["y"][sel]),
                    "z": _list(pts["z"][sel]), "residual_mm": _list(pts["residual_mm"][sel]), "every": step,
                    "n": n}
        marks = []
        for t in self.tables():
            step = t["step"].lower()
            kind = "check" if "check" in step else "control" if "control" in step else None
            if kind is None:
                continue
            tab = self.table(t["t"])
            f = tab["columns"]
            for row in tab["rows"]:
                r = dict(zip(f, row, strict=True))
                comps = t["components"] or [c for c in f if c.startswith("d")][:3]
                marks.append({"id": r["id"], "kind": kind, "table": t["t"], "x": r.get("observed_0"),
                              "y": r.get("observed_1"), "v": [r.get(c) for c in comps],
                              "normalised": r.get("normalised"), "outlier": r.get("outlier")})
        return {"crs": o.get("crs"), "frame": o.get("frame"), "ground_height": z0, "images": images,
                "points": plan, "marks": marks}


def footprint(cam: Camera, position: NDArray[np.float64], rotation: NDArray[np.float64], z0: float
              ) -> list[list[float]] | None:
    """The photo's outline on the plane Z = ``z0``: (8, 2) ground x, y of its corners and edge midpoints
    (pixel corners), or None when a ray does not reach the plane (a photo looking at the horizon).

    ``rotation`` takes the photo vector (x, y, -f) into the ground frame; ``position`` (3,) the projection centre.
    """
    w, h = cam.width - 0.5, cam.height - 0.5
    px = np.array([[-0.5, -0.5], [w / 2, -0.5], [w, -0.5], [w, h / 2], [w, h], [w / 2, h], [-0.5, h],
                   [-0.5, h / 2]])
    rays = cam.rays_from_pixel(px) @ np.asarray(rotation, float).T
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (z0 - position[2]) / rays[:, 2]
    if not np.all(np.isfinite(t)) or np.any(t <= 0):
        return None
    g = position[None, :2] + t[:, None] * rays[:, :2]
    return [[float(a), float(b)] for a, b in g]


def _list(a: NDArray) -> list[float | None]:
    return [None if not math.isfinite(v) else float(v) for v in np.asarray(a, float).tolist()]


def _jsonable(v: Any) -> Any:
    if isinstance(v, dict):
        return {str(k): _jsonable(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_jsonable(x) for x in v]
    if isinstance(v, float):
        return v if math.isfinite(v) else None
    if v is None or isinstance(v, (str, int, bool)):
        return v
    return str(v)


def _short(doc: Any) -> Any:
    """A summary JSON without its long lists (tiles, per-window tables): the keys the page prints."""
    if not isinstance(doc, dict):
        return doc
    return {k: v for k, v in doc.items() if not (isinstance(v, list) and len(v) > 20) and k not in ("tiles",)}
