"""One call per CLI use: detect or read the target, calibrate, write the camera JSON and the report.

The output plan (the camera JSON, the report files) is checked against every input before any
detection (:class:`rectify.actions.workspace.Workspace`: an output that is an input, through a
symlink, ``..`` or a hard link, is refused even with ``overwrite``); the camera JSON and the report
are written in one transaction, so a full disk or SIGTERM leaves neither.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rectify.actions.workspace import Workspace
from rectify.errors import CalibrationError, InvalidInputError
from rectify.formats.common import unstamped
from rectify.formats.opencv import opencv_calibration_text
from rectify.geometry.camera import Camera
from rectify.raster.exif import exif_focal_length
from stereo.calibration.result import Calibration
from stereo.calibration.rig import RigCalibration
from stereo.calibration.views import TargetView
from stereo.calibration.zoom import HeldOut, ZoomModel, held_out_checks, min_settings
from stereo.features.targets import (
    CORNER_METHODS,
    Chessboard,
    ChessboardDetection,
    RejectedCorner,
    find_chessboards,
    parse_pattern,
    parse_square,
)
from stereo.formats.calibration import views_from_csv
from stereo.formats.zoom import observation_settings, read_settings_csv, setting_for
from stereo.report.calibration import write_calibration_report

logger = logging.getLogger(__name__)

__all__ = ["CORNER_METHODS", "OPENCV_OUTPUT_SUFFIXES", "CalibrationRun", "RigRun", "ZoomRun", "calibrate_images",
           "calibrate_points", "calibrate_rig_images", "calibrate_zoom", "parse_size"]


@dataclass(frozen=True, eq=False)
class CalibrationRun:
    """What a calibration run did: the calibration, the files written, the views left out."""

    calibration: Calibration
    output: Path
    missing: tuple[str, ...]
    n_images: int
    report: Path | None
    units: str
    source: str
    detection: ChessboardDetection | None = None

    @property
    def rejected(self) -> tuple[RejectedCorner, ...]:
        """Chessboard corners left out because their refinement failed."""
        return tuple(self.detection.rejected) if self.detection is not None else ()

    def summary_lines(self) -> list[str]:
        out = [self.source]
        if self.missing:
            out.append(f"board not found in {len(self.missing)} of {self.n_images} images: "
                       f"{', '.join(self.missing)} (left out)")
        if self.detection is not None:
            out += self.detection.summary_lines()
        out += self.calibration.summary_lines()
        if self.rejected:
            n = len(self.rejected)
            out.append(f"(RMS and sigma0 over the {self.calibration.n_points} kept corners; the {n} rejected "
                       f"corner{'s are' if n > 1 else ' is'} not in the fit)")
        out.append(f"wrote {self.output} ({self.units} camera)")
        if self.report is not None:
            out.append(f"report: {self.report}")
        return out


@dataclass(frozen=True, eq=False)
class RigRun:
    """What a rig calibration did: the rig, the file written, the pairs left out."""

    rig: Any
    output: Path
    missing: tuple[str, ...]
    n_pairs: int
    source: str
    detections: tuple[ChessboardDetection, ...] = ()

    @property
    def rejected(self) -> tuple[RejectedCorner, ...]:
        """Chessboard corners (left and right images) left out because their refinement failed."""
        return tuple(r for d in self.detections for r in d.rejected)

    def summary_lines(self) -> list[str]:
        out = [self.source]
        if self.missing:
            out.append(f"board not found in {len(self.missing)} of {self.n_pairs} pairs: {', '.join(self.missing)} "
                       "(left out)")
        for side, d in zip(("left", "right"), self.detections, strict=False):
            out += [f"{side} {line}" if k == 0 else line for k, line in enumerate(d.summary_lines())]
        out += self.rig.summary_lines()
        out.append(f"wrote {self.output} (rig: left and right cameras, relative orientation)")
        return out


def parse_size(text: str) -> tuple[int, int]:
    """``"640x480"`` -> (640, 480)."""
    try:
        w, h = parse_pattern(text)
    except InvalidInputError:
        raise InvalidInputError(f"image size must look like 640x480 (width x height, px); got {text!r}") from None
    if w < 2 or h < 2:
        raise InvalidInputError(f"image size must be at least 2 x 2 px; got {text!r}")
    return w, h


#: suffixes of ``-o`` written as an OpenCV calibration file (``.json`` is the camera JSON)
OPENCV_OUTPUT_SUFFIXES = (".yml", ".yaml", ".xml")
#: files of the calibration report planned before any work (the commit checks every file it writes again)
_REPORT_FILES = ("calibration.json", "report.json", "report.html")


def _plan(output: str | Path, inputs: Sequence[str | Path | None], *, report_dir: str | Path | None = None,
          overwrite: bool) -> Workspace:
    """The workspace of a calibration: the camera JSON and the report files checked against every input
    (resolved: symlinks, ``..``, hard links) and the overwrite policy, before any detection."""
    ws = Workspace(overwrite=overwrite, inputs=[p for p in inputs if p is not None], report_dir=report_dir)
    ws.check_report_dir()
    ws.plan(output, *((Path(report_dir) / n for n in _REPORT_FILES) if report_dir is not None else ()))
    return ws


def _finish(ws: Workspace, cal: Calibration, output: str | Path, *, pixel_size_mm: float | None,
            detection: ChessboardDetection | None = None) -> tuple[Path, Path | None]:
    """Write the camera JSON and the report in one transaction: both or neither (a full disk, SIGTERM)."""
    d = cal.camera_dict(pixel_size_mm=pixel_size_mm)
    text = json.dumps(d, indent=2) + "\n"
    suffix = Path(output).suffix.lower()
    if suffix in OPENCV_OUTPUT_SUFFIXES:  # an OpenCV calibration file (.yml, .yaml, .xml): K, distortion, size
        if d.get("point_of_symmetry_px") is not None or d.get("point_of_symmetry_mm") is not None:
            raise InvalidInputError(f"{str(output)!r}: an OpenCV calibration file has no separate point of symmetry "
                                    "of distortion (--symmetry); write a camera JSON (.json)")
        text = opencv_calibration_text(Camera.from_dict(unstamped(d)), fmt=suffix)
    rep = None
    with ws.transaction():
        ws.write_text(output, text)
        if ws.report_dir is not None:
            corners = None
            if detection is not None:
                corners = {"method": detection.method, "found": detection.n_corners,
                           "kept": detection.n_corners - len(detection.rejected),
                           "rejected": [r.as_dict() for r in detection.rejected]}
            with ws.report_folder() as stage:
                page = write_calibration_report(stage, cal, overwrite=True, corners=corners)
            rep = ws.report_dir / Path(page).relative_to(stage)
    return Path(output), rep


def _model_kwargs(kw: dict[str, Any], pixel_size_mm: float | None) -> dict[str, Any]:
    out = dict(kw)
    if pixel_size_mm is not None:
        out["equal_focal"] = True  # a millimetre camera has square pixels: one focal length
    return out


def calibrate_images(images: Sequence[str | Path], *, pattern: str, square: str = "1", output: str | Path,
                     report_dir: str | Path | None = None, overwrite: bool = False,
                     pixel_size_mm: float | None = None, corners: str = "symmetry", **model: Any) -> CalibrationRun:
    """Calibrate from chessboard images.

    Parameters
    ----------
    images : sequence of paths
    pattern : str
        Inner corners, ``"9x6"``.
    square : str
        Square size, e.g. ``"25mm"`` (object units only; the interior orientation does not depend on it).
    output : path
        Camera JSON to write (checked before any work).
    pixel_size_mm : float, optional
        Write a millimetre camera.
    corners : {"symmetry", "opencv"}
        Corner refinement (:func:`stereo.features.targets.refine_corners`); corners whose refinement
        failed are left out, named in the summary and the report.
    **model
        Keywords of :meth:`Calibration.from_views` (``equal_focal``, ``distortion``, ``symmetry``, ``robust``).

    Raises
    ------
    InvalidInputError, CalibrationError, RasterIOError
    """
    ws = _plan(output, list(images), report_dir=report_dir, overwrite=overwrite)
    if not images:
        raise InvalidInputError("no images given")
    cols, rows = parse_pattern(pattern)
    sq, unit = parse_square(square)
    board = Chessboard(cols, rows, sq)
    det = find_chessboards(images, board, method=corners)
    views, missing, (w, h) = det.views, det.missing, det.size
    if len(views) < 3 and missing:
        raise CalibrationError(f"chessboard {cols}x{rows} found in only {len(views)} of {len(images)} images "
                               f"(not found: {', '.join(missing)}); at least 3 views needed")
    if len(views) < 3:
        raise CalibrationError(f"too few views: {len(views)} images of the chessboard {cols}x{rows}, at least 3 needed")
    cal = Calibration.from_views(views, w, h, **_model_kwargs(model, pixel_size_mm))
    out, rep = _finish(ws, cal, output, pixel_size_mm=pixel_size_mm, detection=det)
    src = (f"chessboard {cols}x{rows} (square {sq:g} {unit}) found in {len(views)} of {len(images)} images, "
           f"{w} x {h} px")
    return CalibrationRun(cal, out, tuple(missing), len(images), rep, "mm" if pixel_size_mm else "pixel", src, det)


def calibrate_points(points: str | Path, *, field: str | Path | None, size: str, output: str | Path,
                     report_dir: str | Path | None = None, overwrite: bool = False,
                     pixel_size_mm: float | None = None, **model: Any) -> CalibrationRun:
    """Calibrate from measured image points (observation CSV) of a plane or 3D target (field CSV).

    See :mod:`.targets` for the CSV formats; ``size`` is ``"640x480"``.
    """
    ws = _plan(output, [points, field], report_dir=report_dir, overwrite=overwrite)
    w, h = parse_size(size)
    views = views_from_csv(points, field)
    cal = Calibration.from_views(views, w, h, **_model_kwargs(model, pixel_size_mm))
    out, rep = _finish(ws, cal, output, pixel_size_mm=pixel_size_mm)
    kind = "plane target" if all(v.is_planar for v in views) else "3D test field"
    src = f"{kind}: {sum(v.n for v in views)} measured points in {len(views)} views, {w} x {h} px"
    return CalibrationRun(cal, out, (), len(views), rep, "mm" if pixel_size_mm else "pixel", src)


def calibrate_rig_images(left: Sequence[str | Path], right: Sequence[str | Path], *, pattern: str, square: str = "1",
                         output: str | Path, overwrite: bool = False, pixel_size_mm: float | None = None,
                         corners: str = "symmetry", **model: Any) -> RigRun:
    """Calibrate a two-camera rig from synchronous chessboard images (``left[i]`` with ``right[i]``).

    Pairs where the board is missing in either image are left out (named); chessboard corners whose
    refinement failed (``corners``: ``symmetry`` or ``opencv``) are left out and named in the summary.
    Writes the rig JSON (:meth:`.rig.RigCalibration.to_dict`).

    Raises
    ------
    InvalidInputError
        Different numbers of left and right images.
    CalibrationError
        Fewer than 3 complete pairs, or as :meth:`Calibration.from_views`.
    """
    ws = _plan(output, [*left, *right], overwrite=overwrite)
    if len(left) != len(right):
        raise InvalidInputError(f"{len(left)} left images but {len(right)} right images")
    if not left:
        raise InvalidInputError("no images given")
    cols, rows = parse_pattern(pattern)
    sq, unit = parse_square(square)
    board = Chessboard(cols, rows, sq)
    ldet = find_chessboards(left, board, method=corners)
    rdet = find_chessboards(right, board, method=corners)
    lv, lsize, rv, rsize = ldet.views, ldet.size, rdet.views, rdet.size
    lnames = [Path(p).name for p in left]
    rnames = [Path(p).name for p in right]
    by_l = {v.name: v for v in lv}
    by_r = {v.name: v for v in rv}
    pairs, missing = [], []
    for a, b in zip(lnames, rnames, strict=True):
        if a in by_l and b in by_r:
            pairs.append((by_l[a], by_r[b]))
        else:
            missing.append(f"{a}/{b}")
    if len(pairs) < 3:
        raise CalibrationError(f"chessboard {cols}x{rows} found in both images of only {len(pairs)} of {len(left)} "
                               f"pairs (not found: {', '.join(missing) or 'none'}); at least 3 pairs needed")
    kw = _model_kwargs(model, pixel_size_mm)
    kw.pop("robust", None)
    rig = RigCalibration.from_views([p[0] for p in pairs], [p[1] for p in pairs], *lsize, right_size=rsize, **kw)
    with ws.transaction():
        ws.write_text(output, json.dumps(rig.to_dict(pixel_size_mm=pixel_size_mm), indent=2) + "\n")
    src = (f"rig: chessboard {cols}x{rows} (square {sq:g} {unit}) in {len(pairs)} of {len(left)} pairs, "
           f"left {lsize[0]} x {lsize[1]} px, right {rsize[0]} x {rsize[1]} px")
    return RigRun(rig, Path(output), tuple(missing), len(left), src, (ldet, rdet))


# ------------------------------------------------------------------------------------------- zoom lenses
@dataclass(frozen=True, eq=False)
class ZoomRun:
    """What a zoom calibration did: the calibration of each setting, the zoom model, the leave-one-out checks."""

    model: ZoomModel
    calibrations: tuple[Calibration, ...]
    n_views: tuple[int, ...]
    held_out: tuple[HeldOut, ...]
    output: Path
    unit: str
    source: str
    missing: tuple[str, ...] = ()

    def summary_lines(self) -> list[str]:
        m, u = self.model, (f" {self.unit}" if self.unit else "")
        out = [self.source]
        if self.missing:
            out.append(f"board not found in {len(self.missing)} images: {', '.join(self.missing)} (left out)")
        for z, c, n in zip(m.settings, self.calibrations, self.n_views, strict=True):
            f = "f" if "f" in c.names else "fx"
            out.append(f"setting {z:g}{u}: {n} views, {c.n_points} points, {f} {c.value(f):.3f} +- "
                       f"{c.std_errors[f]:.3f} px, cx {c.value('cx'):.3f}, cy {c.value('cy'):.3f} px, "
                       f"sigma0 {c.sigma0_px:.4f} px")
        out.append(f"zoom model: degree {m.degree} over {len(m.settings)} settings {m.settings.min():g}.."
                   f"{m.settings.max():g}{u}; chi2/dof " + ", ".join(
                       f"{n} {v:.2f}" for n, v in m.chi2_dof.items()))
        for h in self.held_out:
            name, worst = h.worst
            out.append(f"held out {h.setting:g}{u} (predicted from the other settings): RMS "
                       f"{h.rms:.2f} standard errors over {len(h.z)} elements, worst {name} {worst:+.2f}")
        zc = m.zoom_camera(self.unit)
        out.append(f"wrote {self.output} (zoom camera: evaluated at an image's focal setting within "
                   f"{zc.low:g}..{zc.high:g}{u}, margin {zc.margin:.3g}{u})")
        return out


def _group_settings(names: Sequence[str], table: dict[str, float] | None, fallback: Any, what: str,
                    hint: str) -> list[float]:
    """The setting of each view (the settings file first, then ``fallback(name)``); missing ones named."""
    out: list[float | None] = []
    for n in names:
        z = setting_for(n, table) if table is not None else None
        out.append(z if z is not None else fallback(n))
    missing = [n for n, z in zip(names, out, strict=True) if z is None]
    if missing:
        more = " ..." if len(missing) > 5 else ""
        raise InvalidInputError(f"no focal setting for {len(missing)} {what}: {', '.join(missing[:5])}{more} "
                                f"({hint})")
    return [float(z) for z in out if z is not None]


def _check_enough(settings: Sequence[float], degree: int) -> list[float]:
    zs = sorted(set(settings))
    need = min_settings(degree)
    if len(zs) < need:
        raise CalibrationError(f"a zoom model of degree {degree} needs views at {need} focal settings at least; "
                               f"got {len(zs)} ({', '.join(f'{z:g}' for z in zs)})")
    return zs


def calibrate_zoom(*, output: str | Path, degree: int = 2, images: Sequence[str | Path] = (),
                   pattern: str | None = None, square: str = "1", corners: str = "symmetry",
                   points: str | Path | None = None, field: str | Path | None = None, size: str | None = None,
                   settings: str | Path | None = None, overwrite: bool = False, **model: Any) -> ZoomRun:
    """Calibrate a zoom lens: each focal setting on its own views, then the zoom model over the settings.

    Views come from chessboard ``images`` (``pattern``) or an observation CSV ``points`` (``field``,
    ``size``). The focal setting of a view is read from the ``settings`` CSV (``view,setting``), else a
    ``setting`` column of ``points``, else an image's EXIF FocalLength (mm) (:mod:`stereo.formats.zoom`).
    Views of one setting make one calibration (:meth:`Calibration.from_views`, ``model`` keywords);
    :class:`ZoomModel` of ``degree`` is fitted over them and written as the zoom camera JSON
    (:func:`rectify.formats.camera.zoom_camera_document`) in one transaction.

    Raises
    ------
    InvalidInputError
        Views without a focal setting (named), an output that is not ``.json``, bad options.
    CalibrationError
        Fewer settings than ``degree + 1`` (the minimum named); a setting whose calibration fails (named).
    """
    if Path(output).suffix.lower() != ".json":
        raise InvalidInputError(f"-o {str(output)!r}: a zoom camera is written as a zoom camera JSON (.json)")
    if model.get("symmetry"):
        raise InvalidInputError("--symmetry is not available with --zoom (the zoom model holds no point of symmetry)")
    model = {k: v for k, v in model.items() if k != "symmetry"}
    if isinstance(degree, bool) or not isinstance(degree, int) or degree < 0:
        raise InvalidInputError(f"zoom degree must be an integer >= 0; got {degree!r}")
    ws = _plan(output, [*images, points, field, settings], overwrite=overwrite)
    table = read_settings_csv(settings) if settings is not None else None
    missing: tuple[str, ...] = ()
    views: list[TargetView]
    if points is not None:
        if images or pattern:
            raise InvalidInputError("give either IMAGES with --chessboard or --points, not both")
        if not size:
            raise InvalidInputError("--points needs --size WxH (the image size in pixels)")
        w, h = parse_size(size)
        views = views_from_csv(points, field)
        obs = observation_settings(points) or {}
        zs = _group_settings([v.name for v in views], table, obs.get, "views",
                             "give a `setting` column in the observation CSV, or --settings view,setting")
        _check_enough(zs, degree)
        unit, by = "", dict(zip([v.name for v in views], zs, strict=True))
        src = f"zoom: {sum(v.n for v in views)} measured points in {len(views)} views, {w} x {h} px"
    else:
        if not images:
            raise InvalidInputError("no input: give IMAGES with --chessboard 9x6, or --points obs.csv")
        if not pattern:
            raise InvalidInputError("IMAGES need --chessboard COLSxROWS (inner corners, e.g. 9x6)")
        names = [Path(p).name for p in images]
        exif = {Path(p).name: p for p in images}
        zs = _group_settings(names, table, lambda n: exif_focal_length(exif[n]), "images",
                             "no EXIF FocalLength; give --settings image,setting")
        _check_enough(zs, degree)
        unit = "" if table is not None else "mm"
        cols, rows = parse_pattern(pattern)
        sq, _ = parse_square(square)
        board = Chessboard(cols, rows, sq)
        det = find_chessboards(images, board, method=corners)
        views, missing, (w, h) = list(det.views), tuple(det.missing), det.size
        by = dict(zip(names, zs, strict=True))
        src = (f"zoom: chessboard {board.cols}x{board.rows} found in {len(views)} of {len(images)} images, "
               f"{w} x {h} px")
    groups: dict[float, list[TargetView]] = {}
    for v in views:
        groups.setdefault(by[v.name], []).append(v)
    settings_used = _check_enough(list(groups), degree)
    least = 3 if points is None else 1
    cals = []
    for z in settings_used:
        g = groups[z]
        if len(g) < least:
            raise CalibrationError(f"focal setting {z:g}: the chessboard was found in only {len(g)} images; "
                                   f"at least {least} needed")
        try:
            cals.append(Calibration.from_views(g, w, h, **model))
        except (CalibrationError, InvalidInputError) as err:
            raise type(err)(f"focal setting {z:g}: {err}") from None
    zm = ZoomModel.from_calibrations(settings_used, cals, degree=degree)
    held = held_out_checks(settings_used, cals, degree=degree)
    per = [{"setting": z, "views": len(groups[z]), "points": c.n_points, "sigma0_px": c.sigma0_px,
            "values": {n: c.value(n) for n in c.names}, "std_errors": dict(c.std_errors)}
           for z, c in zip(settings_used, cals, strict=True)]
    doc = zm.to_dict(unit, calibrations=per)
    with ws.transaction():
        ws.write_text(output, json.dumps(doc, indent=2) + "\n")
    return ZoomRun(zm, tuple(cals), tuple(len(groups[z]) for z in settings_used), tuple(held), Path(output), unit,
                   src, missing)
