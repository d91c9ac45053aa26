"""``stereo orient``: relative orientation of a photo pair from matches or images."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

from rectify.errors import InvalidInputError
from rectify.features import MatcherConfig
from rectify.formats.detect import is_zoom_camera, read_one_camera
from rectify.geometry.camera import Camera
from stereo.actions.common import PathArg, given, pair_tie_points, sigma0_text
from stereo.actions.orient_projective import ProjectiveOrientResult, orient_projective
from stereo.actions.workspace import PairWorkspace
from stereo.relative import RelativeOrientation
from stereo.relative.degenerate import check_base
from stereo.report.pair import write_orient_report


@dataclass(frozen=True)
class OrientOptions:
    """Options of ``stereo orient``.

    Attributes
    ----------
    system : str
        System of elements (:data:`stereo.relative.SYSTEMS`).
    robust : str
        :data:`rectify.geometry.robust.ROBUST_METHODS`; ``"none"`` is plain least squares.
    initial : str
        :data:`stereo.relative.INITIAL_METHODS`.
    """

    system: str = "left-image"
    robust: str = "none"
    initial: str = "auto"


@dataclass(frozen=True, eq=False)
class OrientResult:
    """Result of :func:`orient`: the relative orientation and the files written."""

    ro: RelativeOrientation
    camera: Camera
    output: Path
    options: OrientOptions
    n_matched: int | None = None
    match_rmse_px: float | None = None
    report: Path | None = None

    def summary_lines(self) -> list[str]:
        ro, cam, o = self.ro, self.camera, self.options
        out = []
        if self.n_matched is not None:
            out.append(f"matched {self.n_matched} tie points (verification RMSE {self.match_rmse_px:.3g} px)")
        s = ro.summary()
        out.append(f"relative orientation ({o.system}), {s['n_used']} of {s['n_points']} points used, "
                   f"{s['n_outliers']} outliers, {s['iterations']} iterations"
                   + (f" + {s['irls_iterations']} reweightings ({o.robust})" if o.robust != "none" else "")
                   + f", start: {s['initial']}")
        out.append(f"residual vertical parallax: RMSE {s['rms_parallax_px']:.3f} px "
                   f"({s['rms_parallax_mm'] * 1000:.2f} um); sigma0 {sigma0_text(ro, cam.pixel_size_mm)}; "
                   f"condition number {ro.condition_number:.3g}")
        std = ro.std_errors
        for i, name in enumerate(ro.names):
            se = "" if std is None else f" +- {math.degrees(std[i]):.5f}"
            out.append(f"  {name:>7} = {math.degrees(ro.elements[i]):11.5f}{se} deg")
        if ro.method_figures:  # system projective: the fundamental-matrix stage (seed 003, 3.2.2)
            mf = ro.method_figures
            s0 = "n/a" if mf.get("sampson_sigma0_px") is None else f"{mf['sampson_sigma0_px']:.3f} px"
            out.append(f"fundamental matrix: Sampson RMSE {mf['sampson_rms_px']:.3f} px, sigma0 {s0} "
                       f"(redundancy {mf['redundancy']}); elements from it, then the coplanarity adjustment")
        wf = ro.western()
        out.append(f"  relative omega, phi, kappa = {math.degrees(wf.omega):.5f}, {math.degrees(wf.phi):.5f}, "
                   f"{math.degrees(wf.kappa):.5f} deg; base (1, {wf.by:.5f}, {wf.bz:.5f})")
        out.append(f"wrote {self.output}")
        if self.report is not None:
            out.append(f"report: {self.report}")
        return out


def parse_focal_settings(text: str | None) -> tuple[float | None, float | None]:
    """``--focal-setting``: ``"Z"`` (both images) or ``"ZLEFT,ZRIGHT"`` -> (left, right); None -> (None, None).

    Raises
    ------
    InvalidInputError
        Not one or two finite numbers (the text named).
    """
    if text is None:
        return None, None
    parts = [p.strip() for p in str(text).split(",")]
    try:
        vals = [float(p) for p in parts]
    except ValueError:
        vals = []
    if len(vals) not in (1, 2) or not all(math.isfinite(v) for v in vals):
        raise InvalidInputError(f"--focal-setting must be Z or ZLEFT,ZRIGHT (numbers); got {text!r}")
    return (vals[0], vals[-1])


def orient(*, camera: PathArg | None, output: PathArg, matches: PathArg | None = None,
           images: tuple[PathArg, PathArg] | None = None, camera_right: PathArg | None = None,
           matches_out: PathArg | None = None, report_dir: PathArg | None = None, overwrite: bool = False,
           options: OrientOptions | None = None, matcher: MatcherConfig | None = None,
           focal_settings: tuple[float | None, float | None] = (None, None)
           ) -> OrientResult | ProjectiveOrientResult:
    """``stereo orient``: relative orientation from a matches CSV or from matching two images.

    Parameters
    ----------
    camera, camera_right : path
        Camera JSON of both images (or the left one) and of the right image when it differs. ``camera``
        None: only system ``projective`` (:func:`stereo.actions.orient_projective.orient_projective`,
        the fundamental matrix and a projective pair JSON; no metric elements).
    output : path
        Relative orientation JSON to write (the cameras are stored in it).
    matches : path, optional
        Matches CSV (pixels). Exactly one of ``matches`` and ``images``.
    images : (left, right), optional
        Photos to match first; ``matches_out`` also writes the matches.
    report_dir : path, optional
        QA report folder.
    matcher : MatcherConfig, optional
        Matcher options with ``images`` (default :data:`ORIENT_MATCHER`, fundamental-matrix verification).
    focal_settings : (left, right)
        Focal settings of the images for a zoom camera (``--focal-setting``); None: the image's EXIF
        FocalLength (:func:`rectify.formats.detect.read_one_camera`). Ignored by other cameras.

    Raises
    ------
    InvalidInputError
        Neither or both of ``matches`` and ``images``; no tie points; an output exists without
        ``overwrite`` or equals an input; and as :meth:`RelativeOrientation.from_pixels`.
    """
    opts = options or OrientOptions()
    if camera is None:
        if camera_right is not None:
            raise InvalidInputError("--camera-right needs --camera")
        return orient_projective(output=output, system=opts.system, matches=matches, images=images,
                                 matches_out=matches_out, report_dir=report_dir, overwrite=overwrite, matcher=matcher)
    if (matches is None) == (images is None):
        raise InvalidInputError("give either a matches CSV or the two images LEFT RIGHT")
    ws = PairWorkspace(overwrite=overwrite, inputs=given(camera, camera_right, matches, *(images or ())),
                       report_dir=report_dir)
    ws.plan(output, matches_out)
    ws.check_report_dir()
    # any camera file (camera JSON, orthority, OpenCV, COLMAP, Metashape); a zoom camera at each image's setting
    img_l, img_r = images if images is not None else (None, None)
    cam = read_one_camera(camera, focal_setting=focal_settings[0], image=img_l)
    cam_r = read_one_camera(camera_right or camera, focal_setting=focal_settings[1], image=img_r) \
        if camera_right or is_zoom_camera(camera) else None
    if images is not None:  # check the cameras against the photos before matching
        ws.check_camera_image(cam, images[0], "left")
        ws.check_camera_image(cam_r or cam, images[1], "right")
    m, n_matched, rmse = pair_tie_points(images, matches, ws.load_matches, matcher)
    ws.check_points_in_frame(cam, m.left, m.ids, "left tie points")
    ws.check_points_in_frame(cam_r or cam, m.right, m.ids, "right tie points")
    cam2 = cam_r or cam
    check_base(cam.photo_from_pixel(m.left), cam2.photo_from_pixel(m.right),
               (cam.focal_length_mm, cam2.focal_length_mm), cam.pixel_size_mm)
    # each match by its own precision: an unrefined match (raw keypoints) never weighs as a refined one
    ro = RelativeOrientation.from_pixels(m.left, m.right, cam, camera_right=cam_r, system=opts.system,
                                         robust=opts.robust, initial=opts.initial, ids=m.ids, weights=m.weights())
    # the cameras travel with the orientation, so `stereo model` needs no --camera
    cams = {"camera": cam.to_dict(), **({"camera_right": cam_r.to_dict()} if cam_r else {})}
    report = None
    with ws.transaction():
        if matches_out is not None:
            ws.save_matches(matches_out, m)
        ws.save_relative(output, ro, extra=cams)
        if report_dir is not None:
            report = write_orient_report(ro, cam, report_dir, title=f"stereo orient: relative orientation "
                                         f"({opts.system})", overwrite=overwrite)
    return OrientResult(ro, cam, Path(output), opts, n_matched, rmse, report)
