"""A zoom camera (``stereo calibrate --zoom``) evaluated per image by ``stereo block``, ``stereo dense`` and
``rectify ortho``.

The synthetic block: 2 strips x 3 images (400 x 300 px) of a textured terrain with 8 m relief, each image
rendered with the camera of a zoom lens at its own focal setting (18, 20 or 22 mm; the zoom camera is a known
degree-1 polynomial in the setting: f = z / 0.05 mm px, the principal point drifting 1 px over the range), its
EXIF FocalLength written into the GeoTIFF tags as GDAL reads them. The truth is the zoom camera evaluated at
each setting, so each command with the zoom camera must give what it gives with the evaluated cameras.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import rasterio
from click.testing import CliRunner
from hypothesis import given, settings
from hypothesis import strategies as st

from rectify.cli.main import cli as rectify_cli
from rectify.errors import CalibrationError
from rectify.formats.camera import camera_document, zoom_camera_document
from rectify.geometry.rotation import angles_from_matrix
from rectify.geometry.zoom import ZoomCamera
from stereo.actions.block import BlockOptions, run_block
from stereo.actions.block_zoom import zoom_block
from stereo.block.types import Pose, project_pixel
from stereo.cli.main import cli
from stereo.formats.block import block_orientation_text, read_block_orientation
from tests.support.block_example import CAM, E0, GSD, H_FLY, N0, Z0
from tests.support.block_render import make_terrain, render_image, strip_poses

CRS = "EPSG:32633"
#: the focal setting (mm) of each image: strip 1 then strip 2 (flown back)
SETTINGS = (18.0, 20.0, 22.0, 22.0, 20.0, 18.0)
CHECKS = "C1,C6,C10"


def _zoom() -> ZoomCamera:
    """Calibrated 16..24 mm: f = z / 0.05 px, cx = 199.5 + u, cy = 149.5 - 0.5 u with u = (z - 20) / 4."""
    cov = np.diag([1e-4, 1e-4])
    return ZoomCamera(np.array([16.0, 18.0, 20.0, 22.0, 24.0]), 1, 20.0, 4.0,
                      {"f": np.array([400.0, 80.0]), "cx": np.array([199.5, 1.0]), "cy": np.array([149.5, -0.5])},
                      {"f": cov, "cx": cov, "cy": cov}, 400, 300, "mm")


def _tiff(path, img, focal):
    with rasterio.open(path, "w", driver="GTiff", width=img.shape[1], height=img.shape[0], count=1,
                       dtype="uint8") as dst:
        dst.write(img[None])
        if focal is not None:
            dst.update_tags(EXIF_FocalLength=f"({focal:g})")


def _id(z):
    return f"zoom_{z:g}mm"


@pytest.fixture(scope="module")
def zblock(tmp_path_factory):
    """The rendered zoom block and its inputs: zoom.json, poses.csv (5 cm, 0.5 deg off), poses_cam.csv (the same
    with a camera column naming each image's true camera), control.csv (0.2 px)."""
    d = tmp_path_factory.mktemp("zoomblock")
    zoom = _zoom()
    (d / "zoom.json").write_text(json.dumps(zoom_camera_document(zoom)))
    cams = {_id(z): zoom.camera(z) for z in sorted(set(SETTINGS))}
    w, h = CAM.width * GSD, CAM.height * GSD
    ext = (-w / 2 - 20, -(1 - 0.3) * h - h / 2 - 20, 2 * 0.4 * w + w / 2 + 20, h / 2 + 20)
    terrain = make_terrain(ext, cell_m=GSD, base_height_m=Z0 - 3.0, relief_m=8.0, seed=3)
    poses = [Pose(p.image, _id(z), p.position, p.rotation) for p, z in zip(
        strip_poses(CAM, n_strips=2, n_per_strip=3, flying_height_m=H_FLY, ground_z=Z0, alternate=True,
                    angle_sigma_rad=0.01, seed=1), SETTINGS, strict=True)]
    images = []
    for p, z in zip(poses, SETTINGS, strict=True):
        path = d / f"{p.image}.tif"
        _tiff(path, render_image(terrain, cams[p.camera], p), z)
        images.append(path)
    rng = np.random.default_rng(5)
    head = [f"# crs={CRS}", "# angles=deg"]
    rows, rows_cam = [], []
    for p, path in zip(poses, images, strict=True):
        pos = p.position + [E0, N0, 0.0] + rng.normal(0, 0.05, 3)
        a = np.degrees(angles_from_matrix(p.rotation)) + rng.normal(0, 0.5, 3)
        vals = [*(f"{v:.4f}" for v in pos), *(f"{v:.6f}" for v in a), "0.05", "0.05", "0.05"]
        rows.append(",".join([path.name, *vals]))
        rows_cam.append(",".join([path.name, p.camera, *vals]))
    cols = "x,y,z,omega,phi,kappa,sx,sy,sz"
    (d / "poses.csv").write_text("\n".join([*head, "image," + cols, *rows]) + "\n")
    (d / "poses_cam.csv").write_text("\n".join([*head, "image,camera," + cols, *rows_cam]) + "\n")
    x0, y0, x1, y1 = ext
    gx, gy = np.meshgrid(np.linspace(x0 + 40, x1 - 40, 4), np.linspace(y0 + 35, y1 - 35, 3))
    xy = np.column_stack([gx.ravel(), gy.ravel()])
    xyz = np.column_stack([xy, terrain.height(xy)])
    ctrl = [f"# crs={CRS}", "id,image,col,row,x,y,z"]
    for k, g in enumerate(xyz):
        for p, path in zip(poses, images, strict=True):
            px = project_pixel(cams[p.camera], p, g[None])[0]
            if np.isfinite(px).all() and 5 < px[0] < CAM.width - 6 and 5 < px[1] < CAM.height - 6:
                px = px + rng.normal(0, 0.2, 2)
                ctrl.append(f"C{k},{path.name},{px[0]:.3f},{px[1]:.3f},{g[0] + E0:.4f},{g[1] + N0:.4f},{g[2]:.4f}")
    (d / "control.csv").write_text("\n".join(ctrl) + "\n")
    return d, images, poses, cams, zoom


def _block_args(d, images, out, *extra):
    return ["block", *map(str, images), "--camera", str(d / "zoom.json"), "--poses", str(d / "poses.csv"),
            "--gnss-sigma", "0.05", "--control", str(d / "control.csv"), "--check", CHECKS, "--control-sigma", "0.01",
            "--no-report", "--no-stac", "-o", str(out), *map(str, extra)]


def _summary(out):
    return json.loads((out / "orientation.json").read_text())


# --------------------------------------------------------------------------- stereo block
def test_block_with_zoom_camera_equals_true_cameras(zblock, tmp_path):
    """``stereo block --camera zoom.json``: one camera per EXIF setting (3), each image naming its own, and the
    check-point RMSE per axis within 1 mm of the block given the true per-image cameras (the same cameras: the
    zoom camera evaluated at each setting; the two runs differ only in how the cameras reach the bundle);
    the errors within one ground pixel and a normalised RMS (error / predicted standard error) in 0.3..3."""
    d, images, poses, cams, _ = zblock
    out = tmp_path / "zoom"
    r = CliRunner().invoke(cli, _block_args(d, images, out))
    assert r.exit_code == 0, r.output
    assert ("evaluated at each image's focal setting (EXIF 6): 3 cameras zoom_18mm (2 images), zoom_20mm "
            "(2 images), zoom_22mm (2 images)") in r.output
    doc, o = _summary(out), read_block_orientation(out / "orientation.json")
    assert sorted(o.cameras) == ["zoom_18mm", "zoom_20mm", "zoom_22mm"]
    assert {q.image: q.camera for q in o.poses} == {f"{p.image}.tif": p.camera for p in poses}
    for cid, cam in cams.items():
        assert (out / f"camera_{cid}.json").is_file()
        assert o.cameras[cid].focal_px == pytest.approx(cam.focal_px, abs=1e-9)
        assert np.allclose(o.cameras[cid].K, cam.K, atol=1e-9)
    truth = run_block(images, out_dir=tmp_path / "true", camera=cams, poses=d / "poses_cam.csv",
                      control=d / "control.csv",
                      options=BlockOptions(gnss_sigma_m=(0.05, 0.05, 0.05), control_sigma_m=(0.01, 0.01, 0.01),
                                           check_ids=tuple(CHECKS.split(",")), report=False, stac=False))
    assert truth.n_check == 3
    rz, rt = np.array(doc["summary"]["check_rmse_xyz_m"]), np.array(_summary(tmp_path / "true")["summary"][
        "check_rmse_xyz_m"])
    assert np.all(np.abs(rz - rt) <= 0.001), (rz, rt)
    # against the truth: within one ground pixel (0.25 m) per axis and as the predicted standard errors say
    assert np.all(rz < GSD), rz
    assert 0.3 < doc["summary"]["check_normalised_rms"] < 3.0


def test_block_zoom_settings_csv_and_self_calibration(zblock, tmp_path):
    """``--focal-settings`` overrides EXIF (here every image at 20 mm: one camera); ``--self-calibrate`` on a zoom
    block calibrates each setting's camera on its own, said in the summary."""
    d, images, _, _, _ = zblock
    csv = tmp_path / "settings.csv"
    csv.write_text("image,setting\n" + "".join(f"{p.stem},20\n" for p in images))
    out = tmp_path / "o"
    r = CliRunner().invoke(cli, _block_args(d, images, out, "--focal-settings", csv, "--self-calibrate"))
    assert r.exit_code == 0, r.output
    assert "(--focal-settings 6): 1 camera zoom_20mm (6 images)" in r.output
    assert "--self-calibrate calibrates each setting's camera on its own" in r.output
    assert sorted(read_block_orientation(out / "orientation.json").cameras) == ["zoom_20mm"]


@pytest.mark.parametrize("case", ["outside", "no_exif", "unknown_image", "not_zoom", "projective"])
def test_block_zoom_bad_input(zblock, tmp_path, case):
    """One-line errors before any matching; nothing written."""
    d, images, _, cams, _ = zblock
    out = tmp_path / "o"
    imgs, extra = list(images), []
    if case == "outside":
        csv = tmp_path / "s.csv"
        csv.write_text(f"image,setting\n{images[0].name},30\n")
        extra = ["--focal-settings", csv]
        msg = (f"image '{images[0].name}' (--focal-settings): focal setting 30 mm is outside the zoom camera's "
               "calibrated range 16..24 mm (margin 0.08 mm)")
    elif case == "no_exif":
        bare = tmp_path / images[0].name
        with rasterio.open(images[0]) as src:
            _tiff(bare, src.read(1), None)
        imgs[0] = bare
        msg = (f"image '{images[0].name}' has no focal setting for the zoom camera '{d / 'zoom.json'}' (calibrated "
               "16..24 mm): it has no EXIF FocalLength; give its setting in --focal-settings CSV (image,setting)")
    elif case == "unknown_image":
        csv = tmp_path / "s.csv"
        csv.write_text("image,setting\nnope.tif,20\n")
        extra = ["--focal-settings", csv]
        msg = "names image(s) ['nope.tif'] that are not in the block"
    elif case == "not_zoom":
        cam = tmp_path / "cam.json"
        cam.write_text(json.dumps(camera_document(cams["zoom_20mm"])))
        csv = tmp_path / "s.csv"
        csv.write_text("image,setting\n")
        args = _block_args(d, imgs, out, "--focal-settings", csv)
        args[args.index("--camera") + 1] = str(cam)
        r = CliRunner().invoke(cli, args)
        assert r.exit_code != 0 and "goes with a zoom camera" in r.output and f"{str(cam)!r} is not one" in r.output
        assert not out.exists()
        return
    else:
        r = CliRunner().invoke(cli, ["block", *map(str, images), "--method", "projective", "--focal-settings",
                                     str(d / "poses.csv"), "-o", str(out)])
        assert r.exit_code != 0 and "--focal-settings goes with a zoom camera; --method projective" in r.output
        assert not out.exists()
        return
    r = CliRunner().invoke(cli, _block_args(d, imgs, out, *extra))
    assert r.exit_code != 0
    assert msg in r.output, r.output
    assert "Traceback" not in r.output and len(r.output.strip().splitlines()) == 1, r.output
    assert not out.exists()


@settings(max_examples=25, deadline=None)
@given(st.lists(st.floats(16.0 - 0.08, 24.0 + 0.08).map(lambda z: round(z, 2)), min_size=2, max_size=6),
       st.floats(0.0, 1.0), st.booleans())
def test_zoom_block_cameras_property(tmp_path_factory, zs, t, below):
    """:func:`zoom_block` from a settings CSV (no image files): every image's camera is the zoom camera at its
    setting, one camera per distinct setting; a setting beyond the range plus its margin is refused with
    that image, the setting and the range named."""
    d = tmp_path_factory.mktemp("zprop")
    zoom = _zoom()
    (d / "zoom.json").write_text(json.dumps(zoom_camera_document(zoom)))
    names = [f"im{k}.tif" for k in range(len(zs))]
    csv = d / "s.csv"
    csv.write_text("image,setting\n" + "".join(f"{Path(n).stem},{z!r}\n" for n, z in zip(names, zs, strict=True)))
    zb = zoom_block(d / "zoom.json", [], names, csv)
    assert zb is not None and len(zb.cameras) == len(set(zs)) and zb.settings == tuple(zs)
    for z, cid in zip(zs, zb.camera_of, strict=True):
        assert cid == f"zoom_{z:g}mm" and np.array_equal(zb.cameras[cid].K, zoom.camera(z).K)
    bad = (16.0 - 0.08 - 0.01 - 5 * t) if below else (24.0 + 0.08 + 0.01 + 5 * t)
    csv.write_text(f"image,setting\nim0,{bad!r}\n")
    with pytest.raises(CalibrationError, match=r"image 'im0.tif' \(--focal-settings\): focal setting .* is outside "
                       r"the zoom camera's calibrated range 16..24 mm"):
        zoom_block(d / "zoom.json", [], names, csv)


# --------------------------------------------------------------------------- rectify ortho
def _ortho(d, img, cam, out, *extra):
    return CliRunner().invoke(rectify_cli, ["ortho", str(img), "--dem-height", str(Z0), "--camera", str(cam),
                                            "--exterior", str(d / "poses.csv"), "--resolution", "0.5", "--no-stac",
                                            "-o", str(out), *map(str, extra)])


def _pixels(path):
    with rasterio.open(path) as src:
        return src.read(), src.transform


def test_ortho_zoom_camera_equals_evaluated_camera(zblock, tmp_path):
    """``rectify ortho --camera zoom.json`` on an image with EXIF 22 mm is pixel-identical (and on the same grid)
    to the orthophoto made with the zoom camera evaluated at 22 mm as a camera JSON; ``--focal-setting 22`` on
    the image gives it too; ``--focal-setting 18`` does not."""
    d, images, _, cams, zoom = zblock
    img = images[2]  # EXIF 22 mm
    cam22 = tmp_path / "cam22.json"
    cam22.write_text(json.dumps(camera_document(zoom.camera(22.0))))
    runs = {}
    for name, cam, extra in (("zoom", d / "zoom.json", ()), ("eval", cam22, ()),
                             ("given", d / "zoom.json", ("--focal-setting", "22")),
                             ("other", d / "zoom.json", ("--focal-setting", "18"))):
        r = _ortho(d, img, cam, tmp_path / f"{name}.tif", *extra)
        assert r.exit_code == 0, r.output
        runs[name] = _pixels(tmp_path / f"{name}.tif")
    a, ta = runs["zoom"]
    for k in ("eval", "given"):
        b, tb = runs[k]
        assert ta == tb and a.shape == b.shape and np.array_equal(a, b), k
    assert (a > 0).mean() > 0.5
    c, tc = runs["other"]
    assert tc != ta or not np.array_equal(a, c)


@pytest.mark.parametrize("case", ["outside", "no_exif", "not_zoom"])
def test_ortho_zoom_bad_input(zblock, tmp_path, case):
    d, images, _, cams, _ = zblock
    out = tmp_path / "o.tif"
    img, cam = images[0], d / "zoom.json"
    extra: tuple[str, ...] = ()
    if case == "outside":
        extra = ("--focal-setting", "40")
        msg = (f"image '{img}': zoom camera '{d / 'zoom.json'}': focal setting 40 mm is outside the zoom camera's "
               "calibrated range 16..24 mm")
    elif case == "no_exif":
        img = tmp_path / images[0].name
        with rasterio.open(images[0]) as src:
            _tiff(img, src.read(1), None)
        msg = f"is a zoom camera, but image '{img}' has no EXIF FocalLength: give its focal setting (--focal-setting)"
    else:
        cam = tmp_path / "cam.json"
        cam.write_text(json.dumps(camera_document(cams["zoom_20mm"])))
        extra = ("--focal-setting", "20")
        msg = f"--focal-setting 20 goes with a zoom camera (stereo calibrate --zoom); '{cam}' is not one"
    r = _ortho(d, img, cam, out, *extra)
    assert r.exit_code != 0 and msg in r.output, r.output
    assert "Traceback" not in r.output
    assert not out.exists()


# --------------------------------------------------------------------------- stereo dense
@pytest.fixture(scope="module")
def true_orientation(zblock, tmp_path_factory):
    """The block's true orientation as ``stereo block`` writes it (the true per-setting cameras in it)."""
    d, images, poses, cams, _ = zblock
    p = tmp_path_factory.mktemp("zoomdense") / "orientation.json"
    shifted = [Pose(f"{q.image}.tif", q.camera, q.position + [E0, N0, 0.0], q.rotation) for q in poses]
    p.write_text(block_orientation_text(cams, shifted, crs=CRS))
    return p


def _dense(o, left, right, out, *extra):
    return CliRunner().invoke(cli, ["dense", str(o), str(left), str(right), "-o", str(out), "--cloud", "none",
                                    "--no-stac", *map(str, extra)])


def test_dense_zoom_camera_equals_block_cameras(zblock, true_orientation, tmp_path):
    """``stereo dense`` of two block images at 18 and 20 mm with ``--camera zoom.json`` (each photo's camera at its
    EXIF setting) writes the DSM the block's own (true) cameras give, pixel-identical."""
    d, images, _, _, _ = zblock
    left, right = images[0], images[1]
    outs = {}
    for name, extra in (("zoom", ("--camera", d / "zoom.json")), ("block", ())):
        r = _dense(true_orientation, left, right, tmp_path / name, *extra)
        assert r.exit_code == 0, r.output
        with rasterio.open(tmp_path / name / "dsm.tif") as src:
            outs[name] = (src.read(), src.transform)
    (a, ta), (b, tb) = outs["zoom"], outs["block"]
    assert ta == tb and np.array_equal(a, b)
    assert np.isfinite(a[0]).mean() > 0.3


@pytest.mark.parametrize("case", ["outside", "no_exif", "not_zoom"])
def test_dense_zoom_bad_input(zblock, true_orientation, tmp_path, case):
    d, images, _, _, _ = zblock
    out = tmp_path / "o"
    left, right, extra = images[0], images[1], ["--camera", d / "zoom.json"]
    if case == "outside":
        extra += ["--focal-setting", "18,25"]
        msg = f"image '{right}': zoom camera '{d / 'zoom.json'}': focal setting 25 mm is outside"
    elif case == "no_exif":
        left = tmp_path / images[0].name
        with rasterio.open(images[0]) as src:
            _tiff(left, src.read(1), None)
        msg = f"image '{left}' has no EXIF FocalLength: give its focal setting (--focal-setting)"
    else:
        extra = ["--focal-setting", "20"]
        msg = "--focal-setting 20 goes with a zoom camera"
    r = _dense(true_orientation, left, right, out, *extra)
    assert r.exit_code != 0 and msg in r.output, r.output
    assert "Traceback" not in r.output
    assert not out.exists() or not any(out.iterdir())
