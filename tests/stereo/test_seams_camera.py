"""Issue 24, item 11: the camera with fx, fy and skew in every step.

``stereo calibrate`` writes ``fx_px`` and ``fy_px`` by default; every step that reads a camera must
take it: the projective interior orientation of seed 003 (1.2, eq. 1.4),
``K = [[fx, s, cx], [0, fy, cy], [0, 0, 1]]``. The truth here is computed from ``K`` directly
(OpenCV's Brown-Conrady distortion on the normalised coordinates, then ``K``), not through
:class:`rectify.geometry.camera.Camera`, with fx = 1000 px, fy = 1012 px and a skew of 0.8 px.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import rasterio
from click.testing import CliRunner

from rectify.actions.ortho import ortho_from_files
from rectify.errors import CalibrationError
from rectify.formats.camera import camera_document, intrinsics_document, read_camera, write_camera
from rectify.geometry.camera import Camera
from rectify.geometry.rotation import matrix_from_angles
from rectify.geometry.sensors import FrameModel
from rectify.raster.ortho import OrthoOptions
from stereo.actions.block import BlockOptions, run_block
from stereo.actions.calibrate import calibrate_points
from stereo.actions.orient import orient
from stereo.actions.scene import make_scene, render
from stereo.block.bundle.adjust import BundleOptions, adjust_bundle
from stereo.block.bundle.model import interior_from_camera, project, rotation_axes, rotations
from stereo.block.types import BlockControl, GnssObservations, Pose, project_pixel
from stereo.calibration.model import Intrinsics
from stereo.cli.main import cli as stereo_cli
from stereo.dense.epipolar import rectify_pair
from stereo.formats.calibration import camera_from_dict
from stereo.formats.orientation import read_relative, write_exterior
from tests.rectify.test_ortho import E0, N0, geolocation_error, hills, surface, write_dem, write_image
from tests.support.block_synthetic import make_block
from tests.support.calibration_synthetic import board_scene

OLD = Path(__file__).resolve().parents[1] / "data" / "release_0_1_0"

W, H = 1280, 960
FX, FY, SKEW = 1000.0, 1012.0, 0.8
DIST = {"k1": -0.08, "k2": 0.02, "k3": 0.0, "p1": 3e-4, "p2": -2e-4}
CAM = {"fx_px": FX, "fy_px": FY, "skew_px": SKEW, "principal_point_px": [652.3, 471.9], "width": W, "height": H}


#: with and without skew: ``stereo calibrate`` writes fx_px and fy_px (no skew_px)
SKEWS = pytest.mark.parametrize("skew", [SKEW, 0.0], ids=["fx_fy_skew", "fx_fy"])


def cam_dict(skew: float = SKEW, *, distortion: bool = True, **over) -> dict:
    d = {**CAM, **({"distortion": DIST} if distortion else {}), **over}
    if skew:
        d["skew_px"] = skew
    else:
        d.pop("skew_px", None)
    return d


def camera_json(path: Path, skew: float = SKEW, *, distortion: bool = True, **over) -> Path:
    d = cam_dict(skew, distortion=distortion, **over)
    path.write_text(json.dumps({"format": "rectify-stereo/camera", "version": 2, **d}))
    return path


# ------------------------------------------------------------------ the truth, from K itself
def _k(d: dict) -> np.ndarray:
    cx, cy = d["principal_point_px"]
    return np.array([[d["fx_px"], d.get("skew_px", 0.0), cx], [0.0, d["fy_px"], cy], [0.0, 0.0, 1.0]])


def _distort(n: np.ndarray, dist: dict) -> np.ndarray:
    k = {"k1": 0.0, "k2": 0.0, "k3": 0.0, "p1": 0.0, "p2": 0.0, **dist}
    x, y = n[:, 0], n[:, 1]
    r2 = x * x + y * y
    rad = 1 + k["k1"] * r2 + k["k2"] * r2 ** 2 + k["k3"] * r2 ** 3
    return np.column_stack([x * rad + 2 * k["p1"] * x * y + k["p2"] * (r2 + 2 * x * x),
                            y * rad + k["p1"] * (r2 + 2 * y * y) + 2 * k["p2"] * x * y])


def k_project(d: dict, R: np.ndarray, C: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Pixels (N, 2) of ground points X (N, 3): camera axes x right, y down, z forward = diag(1, -1, -1) R^T (X - C)."""
    p = (np.asarray(X, float) - C) @ R  # R^T (X - C): photo frame (y up, z back)
    n = np.column_stack([p[:, 0] / -p[:, 2], -p[:, 1] / -p[:, 2]])
    nd = _distort(n, d.get("distortion", {}))
    q = np.column_stack([nd, np.ones(len(nd))]) @ _k(d).T
    return q[:, :2]


def k_rays(d: dict, R: np.ndarray, px: np.ndarray) -> np.ndarray:
    """Ground directions (N, 3) of pixels: K^-1, then the distortion inverted by Newton iteration."""
    nd = (np.column_stack([px, np.ones(len(px))]) @ np.linalg.inv(_k(d)).T)[:, :2]
    n = nd.copy()
    dist = d.get("distortion", {})
    for _ in range(30):
        e = 1e-7
        f0 = _distort(n, dist) - nd
        jx = (_distort(n + [e, 0], dist) - _distort(n - [e, 0], dist)) / (2 * e)
        jy = (_distort(n + [0, e], dist) - _distort(n - [0, e], dist)) / (2 * e)
        det = jx[:, 0] * jy[:, 1] - jy[:, 0] * jx[:, 1]
        n = n - np.column_stack([jy[:, 1] * f0[:, 0] - jy[:, 0] * f0[:, 1],
                                 -jx[:, 1] * f0[:, 0] + jx[:, 0] * f0[:, 1]]) / det[:, None]
    return np.column_stack([n[:, 0], -n[:, 1], -np.ones(len(n))]) @ R.T


def _angle(R1: np.ndarray, R2: np.ndarray) -> float:
    return float(np.arccos(np.clip((np.trace(R1.T @ R2) - 1) / 2, -1, 1)))


def _scene(rng, n=60, *, C=(0.0, 0.0, 1500.0), angles=(0.03, -0.02, 0.4), relief=80.0, d=None):
    """Ground points (n, 3) seen inside the frame of the camera at C with these angles."""
    d = d or {**CAM, "distortion": DIST}
    R = matrix_from_angles(*angles)
    C = np.asarray(C, float)
    px = np.column_stack([rng.uniform(30, d["width"] - 30, n), rng.uniform(30, d["height"] - 30, n)])
    ray = k_rays(d, R, px)
    z = rng.uniform(-relief / 2, relief / 2, n)
    X = C + ((z - C[2]) / ray[:, 2])[:, None] * ray
    return R, C, X, px


# ------------------------------------------------------------------ collinearity
@SKEWS
def test_collinearity_projection_round_trip(tmp_path, skew):
    cam = read_camera(camera_json(tmp_path / "cam.json", skew))
    d = cam_dict(skew)
    np.testing.assert_allclose(cam.K, _k(d), atol=1e-9)
    rng = np.random.default_rng(0)
    R, C, X, px = _scene(rng, d=d)
    # collinearity (block poses, frame model of the orthophoto) lands on the pixels of K
    np.testing.assert_allclose(k_project(d, R, C, X), px, atol=1e-8)
    pose = Pose("a", "cam", C, R)
    np.testing.assert_allclose(project_pixel(cam, pose, X), px, atol=1e-8)
    np.testing.assert_allclose(FrameModel(cam, C, R, "EPSG:32632").project(X), px, atol=1e-8)
    # pixel -> photo -> pixel, and the rays point at the ground points
    np.testing.assert_allclose(cam.pixel_from_photo(cam.photo_from_pixel(px)), px, atol=1e-9)
    ray = cam.rays_from_pixel(px) @ R.T
    ray /= np.linalg.norm(ray, axis=1, keepdims=True)
    to = (X - C) / np.linalg.norm(X - C, axis=1, keepdims=True)
    assert np.abs(ray - to).max() < 1e-12
    # the bundle's own vectorised collinearity model and its analytic Jacobians
    m = len(X)
    ang = pose.angles[None]

    def model(ang, C, intr, X, jacobian=False):
        return project(np.repeat(rotations(ang), m, 0), np.repeat(C[None], m, 0), np.repeat(rotation_axes(ang), m, 0),
                       np.repeat(intr[None], m, 0), np.full(m, cam.pixel_size_mm),
                       np.repeat([[(W - 1) / 2, (H - 1) / 2]], m, 0), X, jacobian=jacobian)

    intr0 = interior_from_camera(cam)
    pix, _, Jpose, Jpt, Jint = model(ang, C, intr0, X, jacobian=True)
    np.testing.assert_allclose(pix, px, atol=1e-8)
    for k in range(3):
        e = np.zeros(3)
        e[k] = 1e-3
        num = (model(ang, C, intr0, X + e)[0] - model(ang, C, intr0, X - e)[0]) / 2e-3
        np.testing.assert_allclose(Jpt[:, :, k], num, rtol=1e-5, atol=1e-7)
        num = (model(ang, C + e, intr0, X)[0] - model(ang, C - e, intr0, X)[0]) / 2e-3
        np.testing.assert_allclose(Jpose[:, :, 3 + k], num, rtol=1e-5, atol=1e-7)
        a = np.zeros((1, 3))
        a[0, k] = 1e-7
        num = (model(ang + a, C, intr0, X)[0] - model(ang - a, C, intr0, X)[0]) / 2e-7
        np.testing.assert_allclose(Jpose[:, :, k], num, rtol=1e-5, atol=1e-3)
    for k, eps in enumerate((1e-6, 1e-7, 1e-7, 1e-7, 1e-7, 1e-7, 1e-8, 1e-8)):
        e = np.zeros(10)
        e[k] = eps
        num = (model(ang, C, intr0 + e, X)[0] - model(ang, C, intr0 - e, X)[0]) / (2 * eps)
        np.testing.assert_allclose(Jint[:, :, k], num, rtol=1e-4, atol=1e-3)


# ------------------------------------------------------------------ stereo orient
@SKEWS
def test_orient_recovers_the_relative_rotation(tmp_path, skew):
    rng = np.random.default_rng(1)
    d = cam_dict(skew)
    R1, C1, X, pl = _scene(rng, 80, C=(0.0, 0.0, 1500.0), angles=(0.02, -0.03, 0.1), relief=300.0, d=d)
    R2, C2 = matrix_from_angles(-0.04, 0.05, 0.12), np.array([500.0, 30.0, 1520.0])
    pr = k_project(d, R2, C2, X)
    inside = (pr[:, 0] > 5) & (pr[:, 0] < W - 5) & (pr[:, 1] > 5) & (pr[:, 1] < H - 5)
    assert inside.sum() >= 30
    lines = ["id,col_left,row_left,col_right,row_right"] + [
        f"p{i},{a[0]:.17g},{a[1]:.17g},{b[0]:.17g},{b[1]:.17g}"
        for i, (a, b) in enumerate(zip(pl[inside], pr[inside], strict=True))]
    (tmp_path / "m.csv").write_text("\n".join(lines) + "\n")
    res = orient(camera=camera_json(tmp_path / "cam.json", skew), output=tmp_path / "ro.json",
                 matches=tmp_path / "m.csv")
    ro = res.ro
    assert _angle(ro.relative_rotation, R1.T @ R2) < 1e-9
    b = R1.T @ (C2 - C1)
    np.testing.assert_allclose(ro.base_left, b / np.linalg.norm(b), atol=1e-9)
    assert res.ro.summary()["rms_parallax_px"] < 1e-6
    # the camera travels with the orientation, in pixels with fx, fy and skew
    cam = read_relative(tmp_path / "ro.json").raw["camera"]
    assert cam["fx_px"] == pytest.approx(FX, rel=1e-12) and cam["fy_px"] == pytest.approx(FY, rel=1e-12)
    assert cam.get("skew_px", 0.0) == pytest.approx(skew, rel=1e-9)


# ------------------------------------------------------------------ stereo block
BLOCK_CAM = {"fx_px": FX, "fy_px": FY, "skew_px": SKEW, "principal_point_px": [761.0, 493.5], "width": 1500,
             "height": 1000, "distortion": {"k1": -0.05, "k2": 0.01, "p1": 1e-4, "p2": -5e-5}}


@SKEWS
def test_block_recovers_poses_and_points(tmp_path, skew):
    block_cam = {**BLOCK_CAM, "skew_px": skew} if skew else {k: v for k, v in BLOCK_CAM.items() if k != "skew_px"}
    cam = Camera.from_dict(block_cam)
    blk = make_block(0, strips=2, images_per_strip=4, n_points=400, camera=cam, image_noise_px=0.0,
                     gnss_noise_m=0.0, control_noise_m=0.0)
    d = tmp_path / "in"
    d.mkdir()
    images = []
    for name in blk.tracks.images:
        (d / name).write_bytes(b"placeholder")
        images.append(d / name)
    (d / "camera.json").write_text(json.dumps(block_cam))
    rows = ["# crs=EPSG:32633", "# angles=rad", "image,x,y,z,omega,phi,kappa,sx,sy,sz"]
    for p, g in zip(blk.initial_poses, blk.gnss.position, strict=True):
        rows.append(",".join([p.image, *(repr(float(v)) for v in g), *(repr(float(v)) for v in p.angles),
                              "0.05", "0.05", "0.05"]))
    (d / "poses.csv").write_text("\n".join(rows) + "\n")
    res = run_block(images, out_dir=tmp_path / "out", camera=d / "camera.json", poses=d / "poses.csv",
                    tracks=blk.tracks, options=BlockOptions(report=False, bundle=BundleOptions(max_iterations=50),
                                                            frame="map"))  # a Cartesian synthetic block
    b = res.bundle
    assert b.converged
    truth = {p.image: p for p in blk.true_poses}
    assert max(np.abs(p.position - truth[p.image].position).max() for p in b.poses) < 1e-4  # m
    assert max(_angle(p.rotation, truth[p.image].rotation) for p in b.poses) < 1e-7  # rad
    assert b.sigma0 < 1e-3
    out = read_camera(tmp_path / "out" / "camera_camera.json")
    np.testing.assert_allclose(out.K, cam.K, atol=1e-9)


def test_bundle_self_calibrates_f_with_aspect_and_skew_held():
    cam = Camera.from_dict(BLOCK_CAM)
    blk = make_block(1, strips=2, images_per_strip=4, n_points=400, camera=cam, image_noise_px=0.0,
                     gnss_noise_m=0.0, control_noise_m=0.0)
    start = Camera.from_dict({**BLOCK_CAM, "fx_px": FX * 1.004, "fy_px": FY * 1.004, "skew_px": SKEW * 1.004})
    ctrl = BlockControl(blk.control.ids, blk.control.xyz, blk.control.kind, np.full_like(blk.control.xyz, 0.01),
                        blk.control.check)
    gn = GnssObservations(blk.gnss.images, blk.gnss.position, np.full((len(blk.gnss.images), 3), 0.05))
    r = adjust_bundle({"cam": start}, blk.initial_poses, blk.tracks, blk.initial_points, control=ctrl, gnss=gn,
                      options=BundleOptions(self_calibrate=("f",), max_iterations=50))
    assert r.converged
    c = r.cameras["cam"]
    assert c.focal_px == pytest.approx(FX, rel=1e-7)
    assert c.fy_px == pytest.approx(FY, rel=1e-7) and c.skew_px == pytest.approx(SKEW, rel=1e-6)


# ------------------------------------------------------------------ stereo dense
@SKEWS
@pytest.mark.parametrize("distortion", [False, True])
def test_dense_epipolar_rectification_has_no_vertical_parallax(tmp_path, distortion, skew):
    d = cam_dict(skew, distortion=distortion)
    cam = read_camera(camera_json(tmp_path / "cam.json", skew, distortion=distortion))
    rng = np.random.default_rng(2)
    R1, C1, X, pl = _scene(rng, 200, C=(0.0, 0.0, 1500.0), angles=(0.02, -0.03, 0.1), relief=300.0, d=d)
    R2, C2 = matrix_from_angles(-0.04, 0.05, 0.12), np.array([500.0, 30.0, 1520.0])
    pr = k_project(d, R2, C2, X)
    rect = rectify_pair(cam, cam, rotation_left=R1, rotation_right=R2, base=C2 - C1, centre_left=C1)
    ql = rect.rectified_from_original("left", pl)
    qr = rect.rectified_from_original("right", pr)
    assert np.abs(ql[:, 1] - qr[:, 1]).max() < 1e-7  # px: zero vertical parallax
    # the resampling map (the homography without distortion) goes back to the same pixels
    np.testing.assert_allclose(rect.original_from_rectified("left", ql), pl, atol=1e-6)
    np.testing.assert_allclose(rect.original_from_rectified("right", qr), pr, atol=1e-6)
    r0 = np.floor(ql[:3]).astype(int)
    mx, my = rect.source_maps("left", int(r0[0, 0]), int(r0[0, 1]), 2, 2)
    grid = np.array([[r0[0, 0], r0[0, 1]], [r0[0, 0] + 1, r0[0, 1]], [r0[0, 0], r0[0, 1] + 1],
                     [r0[0, 0] + 1, r0[0, 1] + 1]], float)
    want = rect.original_from_rectified("left", grid)
    np.testing.assert_allclose(np.column_stack([mx.ravel(), my.ravel()]), want, atol=2e-3)


@SKEWS
def test_dense_command_surface_matches_the_truth(tmp_path, skew):
    """``stereo dense`` end to end on a rendered 160 px pair whose camera has fx != fy (and skew).

    The camera is the one above scaled to the small photos (fx 250, fy 253, skew 0.2 px); the
    photos are rendered through it, the DSM is compared with the scene's true surface.
    """
    sc = make_scene(3, size_px=160)
    cam = Camera.from_dict({"fx_px": FX / 4, "fy_px": FY / 4, **({"skew_px": skew / 4} if skew else {}),
                            "principal_point_px": [81.3, 78.6], "width": 160, "height": 160})
    f = cam.focal_length_mm
    sc = dataclasses.replace(sc, camera=cam, left=dataclasses.replace(sc.left, focal_length_mm=f),
                             right=dataclasses.replace(sc.right, focal_length_mm=f))
    cv2.imwrite(str(tmp_path / "l.png"), render(sc, "left"))
    cv2.imwrite(str(tmp_path / "r.png"), render(sc, "right"))
    doc = cam.to_dict()
    assert ("skew_px" in doc) == bool(skew) and doc["fy_px"] == pytest.approx(FY / 4, rel=1e-12)
    for name, eo in (("l", sc.left), ("r", sc.right)):
        write_exterior(tmp_path / f"{name}.json", dataclasses.replace(eo, sigma0=0.0, crs=sc.crs), camera=doc)
    g = sc.random_ground_points(40, np.random.default_rng(0), margin_px=10.0)
    pl, pr = sc.pixel_from_ground(sc.left, g), sc.pixel_from_ground(sc.right, g)
    (tmp_path / "m.csv").write_text("id,col_left,row_left,col_right,row_right\n" + "".join(
        f"{i},{a[0]},{a[1]},{b[0]},{b[1]}\n" for i, (a, b) in enumerate(zip(pl, pr, strict=True))))
    out = tmp_path / "out"
    r = CliRunner().invoke(stereo_cli, ["dense", str(tmp_path / "l.json"), str(tmp_path / "l.png"),
                                        str(tmp_path / "r.png"), "-o", str(out), "--right-orientation",
                                        str(tmp_path / "r.json"), "--matches", str(tmp_path / "m.csv")])
    assert r.exit_code == 0, r.output
    summary = json.loads((out / "dense.json").read_text())
    with rasterio.open(out / "dsm.tif") as ds:
        h = ds.read(1)
        rr, cc = np.nonzero(h != ds.nodata)
        x, y = rasterio.transform.xy(ds.transform, rr, cc)
    dz = h[rr, cc] - sc.height(np.column_stack([x, y]))
    dz = dz[np.isfinite(dz)]
    gsd = summary["dsm_cell"]
    assert dz.size > 1000 and abs(np.median(dz)) < 0.2 * gsd and np.sqrt(np.mean(dz ** 2)) < gsd, \
        (np.median(dz), np.sqrt(np.mean(dz ** 2)), gsd)


# ------------------------------------------------------------------ rectify ortho
@SKEWS
def test_ortho_frame_model_puts_ground_points_on_the_right_pixels(tmp_path, skew):
    w, h = 240, 200
    d = cam_dict(skew, principal_point_px=[121.7, 97.2], width=w, height=h)
    R = matrix_from_angles(0.06, -0.05, 0.35)
    C = np.array([E0, N0, 800.0])
    write_dem(tmp_path / "dem.tif", hills)
    surf = surface(tmp_path / "dem.tif")
    cc, rr = np.meshgrid(np.arange(w), np.arange(h))
    px = np.column_stack([cc.ravel(), rr.ravel()]).astype(float)
    ray = k_rays(d, R, px)
    lo, hi = np.full(len(px), 0.0), np.full(len(px), 200.0)  # heights below and above the hills, m
    for _ in range(60):  # bisection on the height where the ray meets the surface
        mid = 0.5 * (lo + hi)
        g = C + ((mid - C[2]) / ray[:, 2])[:, None] * ray
        above = g[:, 2] > surf(g[:, :2])
        hi, lo = np.where(above, mid, hi), np.where(above, lo, mid)
    g = C + ((0.5 * (lo + hi) - C[2]) / ray[:, 2])[:, None] * ray
    write_image(tmp_path / "frame.tif", g[:, :2], (h, w))
    (tmp_path / "cam.json").write_text(json.dumps(d))
    (tmp_path / "eo.json").write_text(json.dumps({"position": C.tolist(), "rotation": R.tolist(),
                                                  "crs": "EPSG:32632"}))
    run = ortho_from_files(tmp_path / "frame.tif", tmp_path / "ortho.tif", tmp_path / "dem.tif",
                           camera=tmp_path / "cam.json", exterior=tmp_path / "eo.json", resolution=1.0,
                           options=OrthoOptions(tile_px=64, threads=1))
    assert run.model_kind == "FrameModel"
    err, _a, _ = geolocation_error(tmp_path / "ortho.tif")
    ok = np.isfinite(err)
    assert ok.mean() > 0.3
    assert np.percentile(err[ok], 99.9) < 0.1, np.percentile(err[ok], [50, 99, 99.9, 100])  # output px
    with rasterio.open(tmp_path / "ortho.tif") as ds:
        assert ds.tags()["ORTHO_MODEL"] == "FrameModel"


# ------------------------------------------------------------------ the camera JSON
def test_camera_json_fx_fy_skew_round_trip_and_old_files_unchanged(tmp_path):
    cam = read_camera(camera_json(tmp_path / "cam.json"))
    assert (cam.focal_px, cam.fy_px, cam.skew_px) == (pytest.approx(FX, rel=1e-12), pytest.approx(FY, rel=1e-12),
                                                       pytest.approx(SKEW, rel=1e-12))
    back = read_camera(write_camera(tmp_path / "back.json", cam))
    doc = json.loads((tmp_path / "back.json").read_text())
    assert list(doc)[:5] == ["format", "version", "fx_px", "fy_px", "skew_px"] and "focal_length_px" not in doc
    np.testing.assert_allclose(back.K, cam.K, rtol=1e-12)
    assert back.distortion == cam.distortion
    # no skew: fx_px and fy_px only; fx == fy and no skew: focal_length_px, as before
    no_skew = Camera.from_dict({**CAM, "skew_px": 0.0}).to_dict()
    assert "skew_px" not in no_skew and no_skew["fy_px"] == pytest.approx(FY, rel=1e-12)
    square = Camera.from_dict({**CAM, "fy_px": FX, "skew_px": 0.0})
    assert square.square and "focal_length_px" in square.to_dict() and "fx_px" not in square.to_dict()
    # files of release 0.1.0 and square pixel cameras are written byte for byte as before
    old = read_camera(OLD / "camera.json")
    assert json.dumps(camera_document(old), indent=2) == (
        '{\n  "format": "rectify-stereo/camera",\n  "version": 2,\n  "focal_length_mm": 120.0,\n'
        '  "pixel_size_mm": 0.192,\n  "width": 480,\n  "height": 480\n}')
    px = Camera.from_dict({"focal_length_px": 812.5, "principal_point_px": [321.25, 238.75], "width": 640,
                           "height": 480, "distortion": {"k1": -0.21}})
    assert json.dumps(px.to_dict()) == (
        '{"focal_length_px": 812.5, "principal_point_px": [321.25, 238.75], "width": 640, "height": 480, '
        '"distortion": {"k1": -0.21, "k2": 0.0, "k3": 0.0, "p1": 0.0, "p2": 0.0}}')


def test_calibrate_default_output_is_read_by_the_other_steps(tmp_path):
    """``stereo calibrate`` (fx and fy free, its default) -> a camera every other step reads."""
    truth = Intrinsics(fx=FX, fy=FY, cx=652.3, cy=471.9, width=W, height=H, k1=-0.08, k2=0.02)
    sc = board_scene(np.random.default_rng(4), n_views=6, camera=truth, noise_px=0.0)
    obs = ["view,point,col,row,x,y,z"] + [f"{v.name},{p},{c:.17g},{r:.17g},{x:.17g},{y:.17g},{z:.17g}" for v in sc.views
                                          for p, (c, r), (x, y, z) in zip(v.ids, v.pixel, v.object_xyz, strict=True)]
    (tmp_path / "obs.csv").write_text("\n".join(obs) + "\n")
    run = calibrate_points(tmp_path / "obs.csv", field=None, size=f"{W}x{H}", output=tmp_path / "cam.json",
                           distortion=("k1", "k2"))
    doc = json.loads(run.output.read_text())
    assert "fx_px" in doc and "fy_px" in doc
    cam = read_camera(run.output)  # refused before: "calibrate with a single f"
    np.testing.assert_allclose(cam.K, truth.K, atol=1e-6)
    assert camera_from_dict(doc).intrinsics.fy == pytest.approx(FY, rel=1e-9)
    # the calibration's own writer and the camera's agree
    again = intrinsics_document(Intrinsics(fx=FX, fy=FY, cx=652.3, cy=471.9, width=W, height=H))
    assert Camera.from_dict({k: v for k, v in again.items() if k not in ("format", "version")}).to_dict()[
        "fy_px"] == pytest.approx(FY, rel=1e-12)


@pytest.mark.parametrize("bad, message", [
    ({"fy_px": None}, "`fx_px` 1000.0 without `fy_px`"),
    ({"fy_px": -3.0}, "`fy_px` must be a finite number > 0"),
    ({"skew_px": "0.8"}, "`skew_px` must be a finite number"),
    ({"focal_length_px": 999.0}, "contradicts"),
])
def test_bad_fx_fy_skew_refused_by_name(bad, message):
    d = {**CAM, **bad}
    d = {k: v for k, v in d.items() if v is not None}
    with pytest.raises(CalibrationError, match=message):
        Camera.from_dict(d)
