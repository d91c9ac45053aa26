"""What a result folder holds, and the one check of every path the page asks for.

:func:`resolve_inside` is the only way a requested path becomes a file: it refuses absolute paths, ``..``,
hidden names (temporaries ``.*.part`` included), back-slashes and NUL, a path whose resolved target
(symlinks followed) leaves the folder, and any kind of file not in :data:`SERVED_SUFFIXES`. Rasters are
never served as files: the page gets their tiles by number (:class:`RasterEntry`), so no raster path is
ever taken from a request.

:func:`scan` walks the folder (at most :data:`MAX_DEPTH` levels, :data:`MAX_FILES` files; hidden names
skipped) and sorts what it finds: rasters (orthophotos, DSMs and their bands), report folders
(``report.json``), a block's ``orientation.json`` / ``observations.csv`` / ``points.csv``, a pair's
orientation, ``dense.json``. The block's photos are inputs, not results: they are looked up by name in
the folders given with ``--images`` (each name resolved inside its folder, as above), and shown as tiles.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath

from rectify.atomic import read_json
from rectify.errors import InvalidInputError, RectifyError

#: the kinds of file the page may fetch whole (figures, pages, tables, JSON)
SERVED_SUFFIXES = frozenset({".png", ".jpg", ".jpeg", ".svg", ".html", ".json", ".csv", ".geojson", ".md", ".txt"})
#: result rasters shown as tiles
RASTER_SUFFIXES = frozenset({".tif", ".tiff"})
#: photos of a block looked up in ``--images`` folders
PHOTO_SUFFIXES = frozenset({".tif", ".tiff", ".png", ".jpg", ".jpeg", ".jp2", ".bmp"})
MAX_DEPTH = 3
MAX_FILES = 20_000


class Refused(InvalidInputError):
    """A request the server refuses: ``status`` 403 (outside the folder, a hidden or unserved kind) or 404."""

    def __init__(self, status: int, reason: str) -> None:
        super().__init__(reason)
        self.status = status


def safe_parts(rel: str) -> tuple[str, ...]:
    """The segments of a request path relative to the folder, or :class:`Refused` (403).

    ``rel`` is already percent-decoded once (the server decodes the URL path once; a ``%2e%2e`` left
    after that is a literal name, which then does not exist).

    >>> safe_parts("report/fig.png")
    ('report', 'fig.png')
    >>> safe_parts("../etc/passwd")
    Traceback (most recent call last):
    ...
    rectify.view.folder.Refused: '..' in the path '../etc/passwd'
    """
    if "\x00" in rel or "\\" in rel:
        raise Refused(403, f"a NUL or back-slash in the path {rel!r}")
    if rel.startswith("/") or PurePosixPath(rel).is_absolute() or (len(rel) > 1 and rel[1] == ":"):
        raise Refused(403, f"an absolute path {rel!r}")
    parts = tuple(p for p in rel.split("/") if p != "")
    if not parts:
        raise Refused(404, "an empty path")
    for p in parts:
        if p in ("..", "."):
            raise Refused(403, f"{p!r} in the path {rel!r}")
        if p.startswith("."):
            raise Refused(403, f"a hidden name {p!r} in the path {rel!r}")
    return parts


def resolve_inside(root: Path, rel: str, suffixes: frozenset[str] = SERVED_SUFFIXES) -> Path:
    """The file ``root/rel`` if it is a served kind and, symlinks followed, inside ``root``.

    Raises
    ------
    Refused
        403: an absolute path, ``..``, a hidden name, a target outside ``root``, a kind not in
        ``suffixes``; 404: no such file.
    """
    parts = safe_parts(rel)
    cand = root.joinpath(*parts)
    try:
        real = cand.resolve(strict=True)
    except (OSError, RuntimeError):
        raise Refused(404, f"no file {rel!r}") from None
    if not real.is_relative_to(root):
        raise Refused(403, f"{rel!r} points outside the folder")
    if real.suffix.lower() not in suffixes or cand.suffix.lower() not in suffixes:
        raise Refused(403, f"{rel!r} is not a kind of result the view serves")
    if not real.is_file():
        raise Refused(404, f"no file {rel!r}")
    return real


@dataclass(frozen=True)
class RasterEntry:
    """A raster the page may show as tiles, by its number in the manifest.

    Attributes
    ----------
    path : Path
        Resolved path (inside the folder, or inside an ``--images`` folder for a photo).
    label : str
        What the page calls it (path relative to its folder).
    role : str
        ``raster`` (an orthophoto or any result image), ``dsm``, ``band`` (one band of a result, e.g.
        sigma_Z), ``photo`` (a block's photo).
    mode, band : str, int
        The tile rendering (:class:`rectify.raster.viewtiles.TileSource`).
    """

    path: Path
    label: str
    role: str
    mode: str = "image"
    band: int = 1


@dataclass(frozen=True)
class FolderContents:
    """What :func:`scan` found in a result folder (paths relative to ``root``, POSIX)."""

    root: Path
    files: tuple[str, ...]
    rasters: tuple[str, ...]
    reports: tuple[str, ...]
    block_orientation: str | None = None
    observations: str | None = None
    points: str | None = None
    pair_orientation: str | None = None
    dense: tuple[str, ...] = ()
    image_dirs: tuple[Path, ...] = field(default_factory=tuple)
    truncated: bool = False


def _json_format(path: Path) -> str | None:
    try:
        if path.stat().st_size > 50 * 2**20:
            return None
        doc = read_json(path, "result JSON")
    except RectifyError:
        return None
    return doc.get("format") if isinstance(doc, dict) and isinstance(doc.get("format"), str) else None


def scan(root: str | Path, image_dirs: tuple[str | Path, ...] = ()) -> FolderContents:
    """Walk a result folder and sort its files (see the module docstring).

    Raises
    ------
    InvalidInputError
        ``root`` or an ``image_dirs`` entry is not a folder.
    """
    r = Path(root)
    if not r.is_dir():
        raise InvalidInputError(f"not a folder: {str(root)!r}")
    rr = r.resolve()
    dirs = []
    for d in image_dirs:
        if not Path(d).is_dir():
            raise InvalidInputError(f"--images: not a folder: {str(d)!r}")
        dirs.append(Path(d).resolve())
    files: list[str] = []
    truncated = False
    for cur, subdirs, names in os.walk(rr):
        here = Path(cur)
        depth = len(here.relative_to(rr).parts)
        subdirs[:] = sorted(d for d in subdirs if not d.startswith(".") and depth < MAX_DEPTH
                            and (here / d).resolve().is_relative_to(rr))
        for n in sorted(names):
            if n.startswith("."):
                continue
            p = here / n
            if not p.resolve().is_relative_to(rr):
                continue
            files.append(p.relative_to(rr).as_posix())
            if len(files) >= MAX_FILES:
                truncated = True
                break
        if truncated:
            break
    rasters = tuple(f for f in files if PurePosixPath(f).suffix.lower() in RASTER_SUFFIXES)
    reports = tuple(f for f in files if PurePosixPath(f).name == "report.json")
    block = obs = pts = pair = None
    dense = []
    for f in files:
        name = PurePosixPath(f).name
        if name.endswith("orientation.json"):
            fmt = _json_format(rr / f)
            if fmt == "rectify-stereo/block-orientation" and block is None:
                block = f
            elif fmt == "rectify-stereo/model-orientation" and pair is None:
                pair = f
        elif name == "observations.csv" and obs is None:
            obs = f
        elif name == "points.csv" and pts is None:
            pts = f
        elif name in ("dense.json", "dense_rpc.json", "ortho_report.json"):
            dense.append(f)
    return FolderContents(rr, tuple(files), rasters, reports, block, obs, pts, pair, tuple(dense), tuple(dirs),
                          truncated)


def find_photo(name: str, dirs: tuple[Path, ...]) -> Path | None:
    """The photo ``name`` (a block's image name) in the first of ``dirs`` that has it, resolved inside that
    folder; None if none has it or the name would leave the folder."""
    try:
        parts = safe_parts(name)
    except Refused:
        return None
    if PurePosixPath(name).suffix.lower() not in PHOTO_SUFFIXES:
        return None
    for d in dirs:
        cand = d.joinpath(*parts)
        try:
            real = cand.resolve(strict=True)
        except (OSError, RuntimeError):
            continue
        if real.is_relative_to(d) and real.is_file():
            return real
    return None
