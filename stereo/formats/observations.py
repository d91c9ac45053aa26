"""Image measurements as input: the observations CSV that ``stereo block`` writes, read back as tie tracks.

``stereo block --observations obs.csv --camera CAM --poses POSES -o OUT`` adjusts a block from
measurements made elsewhere (a photogrammetric workstation, an earlier run), without the images.

Format (``docs/formats.md``, "Observations CSV")
    Header with at least ``image,id,col,row``; optional ``sigma_px`` (the a-priori standard
    deviation of both coordinates, pixels; an empty cell takes the default). The other columns
    ``stereo block`` writes (``residual_x_px,residual_y_px,weight,flagged``) and any column this
    reader does not know are ignored: every row is a measurement (the earlier run's blunder flags
    are not applied; the new adjustment judges again). One row per image measurement: ``col,row``
    pixel coordinates (x = column right, y = row down, pixel centres at integers) in the image
    named by ``image``; ``id`` names the ground point. Comment lines start with ``#``.

Checks (one-line errors naming the file, line and value): missing columns, empty image or id,
non-numeric or non-finite numbers, ``sigma_px`` <= 0, an image the pose file does not name, the
same (image, id) twice, a measurement outside its image (beyond -0.5 .. width - 0.5 or
-0.5 .. height - 0.5 px, the edges of the edge pixels), an image with no measurement. A point
measured in one image only cannot be intersected: its row is dropped and counted
(:attr:`ObservationTable.n_single`).
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rectify.errors import InvalidInputError
from rectify.formats.common import TableReader, need_columns
from stereo.block.types import Tracks

__all__ = ["OBSERVATION_COLUMNS", "ObservationTable", "read_observations"]

StrPath = str | os.PathLike[str]

#: the columns an observations CSV must have
OBSERVATION_COLUMNS = ("image", "id", "col", "row")
#: the most rows an observations CSV may have
MAX_OBSERVATION_ROWS = 20_000_000


@dataclass(frozen=True, eq=False)
class ObservationTable:
    """An observations CSV read as tie tracks.

    Attributes
    ----------
    tracks : Tracks
        On ``images`` (the pose file's order); points measured in two images or more.
    n_rows : int
        Rows read.
    n_single : int
        Rows dropped because their point is measured in that one image only.
    n_flagged : int
        Rows the earlier run had flagged as blunders (``flagged`` = 1; kept).
    source : Path
    """

    tracks: Tracks
    n_rows: int
    n_single: int
    n_flagged: int
    source: Path

    def summary_line(self) -> str:
        """``observations: N rows of obs.csv, P points ...``."""
        t = self.tracks
        extra = []
        if self.n_single:
            extra.append(f"{self.n_single} rows of points seen in one image only dropped")
        if self.n_flagged:
            extra.append(f"{self.n_flagged} rows flagged by the earlier run kept (judged again)")
        return (f"observations: {self.n_rows} rows of {self.source.name}: {t.n_points} points, {t.n_obs} image "
                f"measurements in {len(t.images)} images (no matching)" + (f"; {'; '.join(extra)}" if extra else ""))


def read_observations(path: StrPath, images: Sequence[str], sizes: Mapping[str, tuple[int, int]], *,
                      default_sigma_px: float = 1.0) -> ObservationTable:
    """Read an observations CSV (module docstring) into tracks on the block's ``images``.

    Parameters
    ----------
    path : str or path-like
        The CSV.
    images : sequence of str
        The block's image names (the pose file's), in block order. A row's ``image`` matches a
        name or its stem (``img1`` for ``img1.tif``).
    sizes : mapping image name -> (width, height)
        Each image's size in pixels (from its camera).
    default_sigma_px : float
        Standard deviation of rows without ``sigma_px``, pixels.

    Returns
    -------
    ObservationTable

    Raises
    ------
    RasterIOError
        The file is missing or unreadable.
    InvalidInputError
        As listed in the module docstring.
    """
    p = Path(path)
    if not (isinstance(default_sigma_px, (int, float)) and math.isfinite(default_sigma_px) and default_sigma_px > 0):
        raise InvalidInputError(f"default_sigma_px must be a finite number > 0; got {default_sigma_px!r}")
    names = tuple(str(n) for n in images)
    missing_size = [n for n in names if n not in sizes]
    if missing_size:
        raise InvalidInputError(f"no image size for {missing_size[:5]}")
    with TableReader(p) as t:
        fields = list(t.fields)
        need_columns(fields, OBSERVATION_COLUMNS, p)
        has_sigma = "sigma_px" in fields
        has_flag = "flagged" in fields
        cols = t.read("observation rows", numbers=("col", "row", *(("sigma_px",) if has_sigma else ())),
                      texts=("image", "id", *(("flagged",) if has_flag else ())),
                      empty=("sigma_px",) if has_sigma else (), max_rows=MAX_OBSERVATION_ROWS)
    lines = cols.lines
    img_txt, ids = cols.texts["image"], cols.texts["id"]
    n = len(cols)
    for what, vals in (("image", img_txt), ("id", ids)):
        empty = next((i for i, v in enumerate(vals) if not v), None)
        if empty is not None:
            raise InvalidInputError(f"{str(p)!r} line {lines[empty]}: empty {what}")
    where = {nm: k for k, nm in enumerate(names)}
    stem = {Path(nm).stem: k for k, nm in enumerate(names)}
    im = np.array([where.get(v, stem.get(v, stem.get(Path(v).stem, -1))) for v in img_txt], dtype=np.int64)
    if (im < 0).any():
        bad = sorted({img_txt[i] for i in np.flatnonzero(im < 0)})
        i0 = int(np.flatnonzero(im < 0)[0])
        raise InvalidInputError(f"{str(p)!r} line {lines[i0]}: image {img_txt[i0]!r} is not in the pose file "
                                f"({len(bad)} unknown image name(s): {bad[:5]}; the pose file names {list(names)[:3]}"
                                f"{' ...' if len(names) > 3 else ''})")
    px = np.column_stack([cols.numbers["col"], cols.numbers["row"]])
    sig = np.full(n, float(default_sigma_px))
    if has_sigma:
        s = cols.numbers["sigma_px"]
        given = np.isfinite(s)
        bad_s = np.flatnonzero(given & (s <= 0))
        if bad_s.size:
            i = int(bad_s[0])
            raise InvalidInputError(f"{str(p)!r} line {lines[i]}: sigma_px must be > 0; got {float(s[i])!r}")
        sig = np.where(given, s, sig)
    wh = np.array([sizes[nm] for nm in names], dtype=np.float64).reshape(-1, 2)[im]
    out = (px[:, 0] < -0.5) | (px[:, 1] < -0.5) | (px[:, 0] > wh[:, 0] - 0.5) | (px[:, 1] > wh[:, 1] - 0.5)
    if out.any():
        i = int(np.flatnonzero(out)[0])
        raise InvalidInputError(f"{str(p)!r} line {lines[i]}: measurement of {ids[i]!r} at col {px[i, 0]:g}, row "
                                f"{px[i, 1]:g} lies outside image {names[im[i]]!r} ({int(wh[i, 0])} x {int(wh[i, 1])} "
                                f"px from the camera; {int(out.sum())} such row(s)): wrong camera, or measured on "
                                "another image size")
    uid, pt = np.unique(np.asarray(ids, dtype=object), return_inverse=True)
    pt = np.asarray(pt, dtype=np.int64).reshape(-1)
    key = pt * len(names) + im
    order = np.argsort(key, kind="stable")
    dup = np.flatnonzero(key[order][1:] == key[order][:-1])
    if dup.size:
        a, b = sorted((int(order[dup[0]]), int(order[dup[0] + 1])))
        raise InvalidInputError(f"{str(p)!r} lines {lines[a]} and {lines[b]}: point {ids[a]!r} is measured twice in "
                                f"image {names[im[a]]!r} ({dup.size} duplicate (image, id) row(s))")
    counts = np.bincount(pt, minlength=len(uid))
    keep = counts[pt] >= 2
    per_image = np.bincount(im[keep], minlength=len(names))
    if (per_image == 0).any():
        empty_imgs = [names[k] for k in np.flatnonzero(per_image == 0)]
        raise InvalidInputError(f"{str(p)!r}: image(s) {empty_imgs[:5]} of the pose file have no measurement of a "
                                "point seen in two images or more: leave them out of the pose file, or measure them")
    used = np.unique(pt[keep])
    remap = np.full(len(uid), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    n_flag = 0
    if has_flag:
        n_flag = sum(1 for v in cols.texts["flagged"] if v.strip() not in ("", "0", "false", "False"))
    tracks = Tracks(names, tuple(str(uid[i]) for i in used), remap[pt[keep]], im[keep], px[keep], sig[keep])
    return ObservationTable(tracks, n, int((~keep).sum()), n_flag, p)
