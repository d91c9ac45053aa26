"""``stereo calibrate``: camera calibration from chessboard images or measured target points."""

from __future__ import annotations

import glob
from pathlib import Path

import click

from rectify.cli.options import echo, handle_errors, overwrite_opt, report_opt
from rectify.errors import InvalidInputError
from stereo.actions.calibrate import (
    CORNER_METHODS,
    OPENCV_OUTPUT_SUFFIXES,
    calibrate_images,
    calibrate_points,
    calibrate_rig_images,
    calibrate_zoom,
)


@click.command(short_help="Camera calibration: chessboard images or measured points of a plane/3D target.")
@click.argument("images", nargs=-1, type=click.Path(exists=True, dir_okay=False))
@click.option("--chessboard", "pattern", default=None, help="Inner corners of the chessboard, e.g. 9x6.")
@click.option("--square", default="1", show_default=True, help="Chessboard square size, e.g. 25mm (object units).")
@click.option("--points", "points_path", type=click.Path(exists=True, dir_okay=False), default=None,
              help="Observation CSV view,point,col,row[,x,y,z] (instead of images).")
@click.option("--field", "field_path", type=click.Path(exists=True, dir_okay=False), default=None,
              help="Field CSV point,x,y,z: object coordinates of the target points (plane or 3D).")
@click.option("--right", "right_glob", default=None,
              help="Rig: right-camera images as a quoted glob pattern ('right*.jpg'); IMAGES are the left images, "
                   "paired in sorted order. Writes the rig JSON (both cameras, relative orientation).")
@click.option("--zoom", is_flag=True, default=False,
              help="Zoom lens: calibrate each focal setting on its views, fit the interior orientation as polynomials "
                   "of the setting and write a zoom camera JSON (other commands evaluate it at an image's focal "
                   "setting). Settings: --settings, else a `setting` column of --points, else EXIF FocalLength.")
@click.option("--zoom-degree", type=click.IntRange(min=0), default=2, show_default=True,
              help="Degree of the zoom polynomials (needs views at degree + 1 focal settings at least).")
@click.option("--settings", "settings_path", type=click.Path(exists=True, dir_okay=False), default=None,
              help="With --zoom: CSV view,setting giving the focal setting of each view or image (name or stem).")
@click.option("--corners", "corners", type=click.Choice(list(CORNER_METHODS)), default="symmetry", show_default=True,
              help="Chessboard corner refinement: 'symmetry' (the centre of point symmetry of each corner's "
                   "neighbourhood) or 'opencv' (cornerSubPix). Corners whose refinement fails are left out, by name.")
@click.option("--size", default=None, help="Image size WxH in pixels (with --points), e.g. 640x480.")
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False),
              help="Camera JSON to write (.json), or an OpenCV calibration file (.yml, .yaml, .xml: camera_matrix, "
                   "distortion_coefficients, image size; a rig writes JSON only).")
@click.option("--pixel-size", "pixel_size_mm", type=float, default=None,
              help="Pixel size in mm: write a millimetre camera (one focal length).")
@click.option("--equal-focal", is_flag=True, default=False, help="One principal distance (square pixels).")
@click.option("--distortion", default="k1,k2,k3,p1,p2", show_default=True,
              help="Free distortion coefficients (comma separated; 'none' for none).")
@click.option("--symmetry", is_flag=True, default=False,
              help="Estimate the point of symmetry of distortion separately from the principal point.")
@click.option("--robust", type=click.Choice(["none", "huber", "tukey", "hampel", "andrews"]), default="none",
              show_default=True, help="Robust weights (M-estimator).")
@report_opt
@overwrite_opt
@handle_errors
def calibrate(images, pattern, square, points_path, field_path, right_glob, zoom, zoom_degree, settings_path, corners,
              size, output, pixel_size_mm, equal_focal, distortion, symmetry, robust, report_dir, overwrite):
    """Calibrate a camera: interior orientation (f or fx/fy, principal point, Brown k1..k3, p1, p2) with standard
    errors, by a least-squares adjustment of all views. IMAGES with --chessboard, or --points [--field] --size."""
    dist = () if distortion.strip().lower() == "none" else tuple(d.strip() for d in distortion.split(",") if d.strip())
    model = {"equal_focal": equal_focal, "distortion": dist, "symmetry": symmetry,
             "robust": None if robust == "none" else robust}
    if settings_path and not zoom:
        raise InvalidInputError("--settings gives the focal settings of a zoom calibration: add --zoom")
    if zoom:
        for flag, given in (("--right", right_glob), ("--report", report_dir), ("--pixel-size", pixel_size_mm)):
            if given:
                raise InvalidInputError(f"{flag} is not available with --zoom (a zoom camera is written in pixels)"
                                        if flag == "--pixel-size" else f"{flag} is not available with --zoom")
        zoom_run = calibrate_zoom(output=output, degree=zoom_degree, images=images, pattern=pattern, square=square,
                                  corners=corners, points=points_path, field=field_path, size=size,
                                  settings=settings_path, overwrite=overwrite, **model)
        for line in zoom_run.summary_lines():
            echo(line)
        return
    if Path(output).suffix.lower() in OPENCV_OUTPUT_SUFFIXES:  # refused before any detection
        if symmetry:
            raise InvalidInputError(f"-o {output!r}: an OpenCV calibration file has no separate point of symmetry "
                                    "(--symmetry); write a camera JSON (.json)")
        if right_glob:
            raise InvalidInputError(f"-o {output!r}: a rig is written as a rig JSON (.json)")
    if points_path:
        if images or pattern:
            raise InvalidInputError("give either IMAGES with --chessboard or --points, not both")
        if not size:
            raise InvalidInputError("--points needs --size WxH (the image size in pixels)")
        run = calibrate_points(points_path, field=field_path, size=size, output=output, report_dir=report_dir,
                               overwrite=overwrite, pixel_size_mm=pixel_size_mm, **model)
    elif right_glob:
        right = sorted(glob.glob(right_glob))
        if not right:
            raise InvalidInputError(f"--right {right_glob!r} matches no files")
        if not pattern:
            raise InvalidInputError("a rig needs --chessboard COLSxROWS (inner corners, e.g. 9x6)")
        if report_dir:
            raise InvalidInputError("--report is not available for rigs yet")
        rig_run = calibrate_rig_images(sorted(images), right, pattern=pattern, square=square, output=output,
                                       overwrite=overwrite, pixel_size_mm=pixel_size_mm, corners=corners, **model)
        for line in rig_run.summary_lines():
            echo(line)
        return
    else:
        if not images:
            raise InvalidInputError("no input: give IMAGES with --chessboard 9x6, or --points obs.csv")
        if not pattern:
            raise InvalidInputError("IMAGES need --chessboard COLSxROWS (inner corners, e.g. 9x6)")
        run = calibrate_images(images, pattern=pattern, square=square, output=output, report_dir=report_dir,
                               overwrite=overwrite, pixel_size_mm=pixel_size_mm, corners=corners, **model)
    for line in run.summary_lines():
        echo(line)
