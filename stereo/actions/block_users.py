"""``stereo block`` and the users' other tools: what their files add to a block, and the block in their formats.

Inputs (read by :mod:`stereo.formats.detect`; used here):

- :func:`geo_gnss`: ODM ``geo.txt`` positions as GNSS observations of the block's images (its
  accuracies, else ``--gnss-sigma``); they also bring the independent models to the ground;
- :func:`block_tracks`: a COLMAP model's tracks on the block's images, a start that spares the
  matching (``--rematch`` matches anyway).

Outputs, staged in the block's transaction with its other files:

- :class:`BlockExports`: the adjusted block as a COLMAP text model (``--colmap DIR``), an OpenSfM
  ``reconstruction.json`` and ``camera_models.json`` (``--opensfm DIR``), orthority's
  ``int_param.yaml`` and ``ext_param.geojson`` (``--orthority DIR``; ``xyz_opk.csv`` without a
  projected CRS); each checked before any work (:func:`check_exports`);
- :func:`block_stac`: the STAC Item of the point cloud (``OUTDIR/item.stac.json``).
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from rectify.actions.products import FOLDER_ITEM, write_stac
from rectify.actions.workspace import StrPath, Workspace
from rectify.errors import InvalidInputError, RasterIOError
from rectify.formats.orthority import ext_param_text, frame_csv_text, int_param_text
from rectify.formats.stac import StacAsset
from rectify.geometry.camera import Camera
from rectify.geometry.crs import is_geographic, parse_crs
from stereo.block.types import GnssObservations, Pose, Tracks
from stereo.formats.colmap import COLMAP_FILES, colmap_texts
from stereo.formats.odm import OdmGeo
from stereo.formats.opensfm import OPENSFM_FILES, opensfm_texts

__all__ = ["BlockExports", "check_exports", "plan_exports", "export_folders", "write_exports", "geo_gnss",
           "block_tracks", "block_stac", "FOLDER_ITEM"]


@dataclass(frozen=True)
class BlockExports:
    """Folders to write the adjusted block into, in other tools' formats (None: not written).

    Attributes
    ----------
    colmap : path, optional
        COLMAP text model (``cameras.txt``, ``images.txt``, ``points3D.txt``).
    opensfm : path, optional
        OpenSfM ``reconstruction.json`` and ``camera_models.json``.
    orthority : path, optional
        orthority ``int_param.yaml`` and ``ext_param.geojson`` (``xyz_opk.csv`` when the block has no
        projected CRS).
    """

    colmap: StrPath | None = None
    opensfm: StrPath | None = None
    orthority: StrPath | None = None

    def files(self, crs: str | None) -> list[Path]:
        """Every file the exports write."""
        out: list[Path] = []
        if self.colmap is not None:
            out += [Path(self.colmap) / n for n in COLMAP_FILES]
        if self.opensfm is not None:
            out += [Path(self.opensfm) / n for n in OPENSFM_FILES]
        if self.orthority is not None:
            d = Path(self.orthority)
            out += [d / "int_param.yaml", d / ("ext_param.geojson" if _projected(crs) else "xyz_opk.csv")]
        return out


def _projected(crs: str | None) -> bool:
    return crs is not None and parse_crs(crs).is_projected


def check_exports(exports: BlockExports, cameras: Mapping[str, Camera], names: Sequence[str],
                  crs: str | None) -> None:
    """Refuse, before any work, a block the requested formats cannot hold, and a folder that is a file.

    Raises
    ------
    InvalidInputError
        A camera with skew (COLMAP, OpenSfM and orthority have none), an image name with white space
        (COLMAP), a geographic CRS (OpenSfM's topocentric frame needs a projected one), an export
        folder that is a file.
    """
    wanted = {k: v for k, v in (("colmap", exports.colmap), ("opensfm", exports.opensfm),
                                ("orthority", exports.orthority)) if v is not None}
    for key, folder in wanted.items():
        if Path(folder).exists() and not Path(folder).is_dir():
            raise InvalidInputError(f"--{key} {str(folder)!r} is a file; give a folder")
    if not wanted:
        return
    for cid, cam in cameras.items():
        skew = float(np.asarray(cam.K)[0, 1])
        if skew != 0.0:
            raise InvalidInputError(f"camera {cid!r} has skew {skew!r} px, which {', '.join(wanted)} cannot hold")
    if "colmap" in wanted:
        spaced = [n for n in names if any(c.isspace() for c in n)]
        if spaced:
            raise InvalidInputError(f"image name(s) {spaced[:3]} hold white space, which COLMAP's images.txt cannot "
                                    "hold; rename them or drop --colmap")
    if "opensfm" in wanted and crs is not None and is_geographic(crs):
        raise InvalidInputError(f"the block's CRS {crs!r} is geographic: OpenSfM's topocentric frame needs a "
                                "projected one (--opensfm)")


def plan_exports(ws: Workspace, files: Sequence[Path]) -> None:
    """Check the export files before any work: in an existing folder as any output (:meth:`Workspace.plan`), in a
    folder to be made only against the inputs and for an ancestor that is a writable folder."""
    for f in files:
        if f.parent.exists():
            ws.plan(f)
            continue
        ws.check_not_input(f)
        probe = next((p for p in f.parent.parents if p.exists()), Path("."))
        if not probe.is_dir():
            raise InvalidInputError(f"export folder {str(f.parent)!r} cannot be created: {str(probe)!r} is a file")
        if not os.access(probe, os.W_OK | os.X_OK):
            raise RasterIOError(f"export folder {str(f.parent)!r} cannot be created: {str(probe)!r} is not "
                                "writable")


@contextlib.contextmanager
def export_folders(exports: BlockExports) -> Iterator[None]:
    """Create the export folders that do not exist; remove them again (when left empty) on any error."""
    made: list[Path] = []
    try:
        for folder in (exports.colmap, exports.opensfm, exports.orthority):
            if folder is None:
                continue
            d = Path(folder)
            missing = [p for p in (d, *d.parents) if not p.exists()]
            try:
                d.mkdir(parents=True, exist_ok=True)
            except OSError as err:
                raise RasterIOError(f"cannot create the export folder {str(d)!r}: {err.strerror or err}") from err
            made += missing
        yield
    except BaseException:
        for d in made:  # innermost first
            with contextlib.suppress(OSError):
                d.rmdir()
        raise


def write_exports(ws: Workspace, exports: BlockExports, cameras: Mapping[str, Camera], poses: Sequence[Pose],
                  crs: str | None, tracks: Tracks, point_ids: Sequence[str], points: NDArray[np.float64]) -> list[Path]:
    """Stage the requested exports in the open transaction; return the files.

    ``point_ids``/``points``: the determined points (P, 3) in the block's frame; their observations
    are taken from ``tracks`` (pixels in our convention: each writer converts them).
    """
    out: list[Path] = []
    if exports.colmap is not None:
        where = {p: k for k, p in enumerate(point_ids)}
        keep = np.array([tracks.point_ids[i] in where for i in tracks.obs_point], dtype=bool)
        sub = tracks.subset(keep)
        xyz = points[[where[p] for p in sub.point_ids]].reshape(-1, 3)
        for name, text in colmap_texts(cameras, poses, points=xyz, tracks=sub).items():
            out.append(ws.write_text(Path(exports.colmap) / name, text))
    if exports.opensfm is not None:
        texts = opensfm_texts(cameras, poses, crs=crs, points=points, point_ids=point_ids)
        for name, text in texts.items():
            out.append(ws.write_text(Path(exports.opensfm) / name, text))
    if exports.orthority is not None:
        d = Path(exports.orthority)
        out.append(ws.write_text(d / "int_param.yaml", int_param_text(cameras)))
        eos = {p.image: {"position": p.position, "rotation": p.rotation, "camera": p.camera} for p in poses}
        if _projected(crs):
            assert crs is not None
            out.append(ws.write_text(d / "ext_param.geojson", ext_param_text(eos, crs)))
        else:
            out.append(ws.write_text(d / "xyz_opk.csv", frame_csv_text(eos)))
    return out


def geo_gnss(geo: OdmGeo, names: Sequence[str], source: str,
             default_sigma_m: tuple[float, float, float] | None) -> tuple[GnssObservations | None, str]:
    """ODM ``geo.txt`` positions of the block's images (matched by name or stem) as GNSS observations.

    Raises
    ------
    InvalidInputError
        A position without height, or without accuracy and no ``default_sigma_m`` (images named).
    """
    by = {im: k for k, im in enumerate(geo.images)}
    by_stem = {Path(im).stem: k for k, im in enumerate(geo.images)}
    rows, imgs = [], []
    for n in names:
        k = by.get(n, by_stem.get(Path(n).stem))
        if k is not None:
            rows.append(k)
            imgs.append(n)
    if not rows:
        return None, f"{source} names none of the block's images"
    sub = OdmGeo(tuple(imgs), geo.position[rows], geo.ypr_rad[rows], geo.sigma_m[rows],
                 tuple(geo.extras[k] for k in rows), geo.crs, geo.file_crs)
    g = sub.gnss(default_sigma_m=default_sigma_m)
    given = np.isfinite(sub.sigma_m).all(axis=1)
    how = ("sigma from its accuracies" if given.all() else "sigma from --gnss-sigma" if not given.any()
           else "sigma from its accuracies, else --gnss-sigma")
    return g, f"the positions of {len(rows)} of {len(names)} images in {source} (ODM geo.txt, {how})"


def block_tracks(t: Tracks, names: tuple[str, ...]) -> Tracks | None:
    """A pose file's tracks (a COLMAP model's) on the block's images (by name or stem; rays of other images
    dropped, then tracks of fewer than two rays), point ids prefixed ``colmap``; None when none is left."""
    index = {n: k for k, n in enumerate(names)}
    stems = {Path(n).stem: k for k, n in enumerate(names)}
    img = np.array([index.get(im, stems.get(Path(im).stem, -1)) for im in t.images], dtype=np.int64)
    new = img[t.obs_image] if t.n_obs else np.zeros(0, dtype=np.int64)
    keep = new >= 0
    if not keep.any():
        return None
    tr = Tracks(names, tuple(f"colmap{p}" for p in t.point_ids), t.obs_point[keep], new[keep], t.obs_pixel[keep],
                t.obs_sigma_px[keep]).subset(np.ones(int(keep.sum()), dtype=bool))
    return tr if tr.n_points else None


def block_stac(ws: Workspace, root: Path, assets: Mapping[str, tuple[Path, Path]], points: NDArray[np.float64],
               crs: str | None, accuracy: Mapping[str, float], options: Mapping[str, Any],
               inputs: Sequence[StrPath | None]) -> Path:
    """Stage ``OUTDIR/item.stac.json``: the point cloud's files (``assets``: key -> (final, staged)), its extent
    (the points' bounds in ``crs``; a null geometry without a CRS), accuracy, options and inputs."""
    footprint = None
    if crs is not None and len(points):
        lo, hi = points[:, :2].min(axis=0), points[:, :2].max(axis=0)
        footprint = (crs, (float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])))
    item = root / FOLDER_ITEM
    write_stac(ws, item, item_id=root.name or "block", footprint=footprint, accuracy=accuracy,
               command="stereo block", options=options, inputs=inputs,
               assets={k: StacAsset(final, ("data",), f"block points ({final.suffix[1:].upper()})", source=staged)
                       for k, (final, staged) in assets.items()})
    return item
