"""Users' files through the commands (issue 29): cameras, exteriors, GCPs, poses and control of other tools,
detected by content, give the results of the project's own files; the block in other tools' formats; STAC Items.

Files are written here in the tools' documented layouts (orthority's int_param/ext_param/CSV and GCP
GeoJSON, BSD-3; OpenCV's FileStorage calibration files, Apache-2.0; COLMAP's text model, BSD-3; ODM's
gcp_list.txt and geo.txt, AGPL-3.0 project / CC BY-SA docs; Metashape's XML export as its manual
describes it), with our own values, no file of the tools copied. The NGI frames in orthority's own files
(``../shared/data/ngi_strip05``, orthority's test data, BSD-3) are used when present (``shared``).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
from pathlib import Path

import cv2
import numpy as np
import pystac
import pytest
import rasterio
from click.testing import CliRunner
from numpy.testing import assert_allclose
from rasterio.control import GroundControlPoint
from scipy import ndimage

import rectify.actions.ortho as ortho_action
from rectify.cli.main import cli as rectify_cli
from rectify.errors import CRSError, InvalidInputError, RasterIOError
from rectify.formats.colmap import read_colmap_images
from rectify.formats.opencv import read_opencv_calibration, write_opencv_calibration
from rectify.formats.orthority import (
    ext_param_text,
    frame_csv_text,
    int_param_text,
    oty_gcps_text,
    read_ext_param,
    read_int_param,
)
from rectify.formats.stac import file_checksum
from rectify.formats.transform import read_transform
from rectify.geometry.camera import Camera
from rectify.geometry.crs import same_crs
from rectify.geometry.points import GcpTable
from rectify.geometry.rotation import angles_from_matrix, matrix_from_angles
from stereo.actions.scene import make_scene, render
from stereo.block.types import Pose, project_pixel
from stereo.cli.main import cli as stereo_cli
from stereo.formats.block import read_block_orientation
from stereo.formats.colmap import read_colmap, write_colmap
from stereo.formats.opensfm import opensfm_texts, read_opensfm, write_opensfm
from stereo.formats.orientation import write_exterior
from stereo.formats.poses import read_pose_csv
from tests.support.block_example import CAM, write_example_block
from tests.support.block_example import CRS as BLOCK_CRS
from tests.support.block_example import E0 as BE0
from tests.support.block_example import N0 as BN0
from tests.support.calibration_synthetic import field_scene

FLIP = np.diag([1.0, -1.0, -1.0])


def _run(cli, args):
    r = CliRunner().invoke(cli, [str(a) for a in args])
    assert "Traceback" not in r.output, r.output
    return r


def _ok(cli, args):
    r = _run(cli, args)
    assert r.exit_code == 0, r.output
    return r


def _hashes(paths):
    return {str(p): hashlib.sha256(Path(p).read_bytes()).hexdigest() for p in paths if Path(p).is_file()}


def _raster(path):
    with rasterio.open(path) as ds:
        return ds.read(), ds.transform, ds.crs


def _same_raster(a, b):
    da, ta, ca = _raster(a)
    db, tb, cb = _raster(b)
    assert ta == tb and same_crs(ca.to_wkt(), cb.to_wkt())
    return da, db


# ------------------------------------------------------------------ a small frame scene (rectify ortho)
E0, N0 = 500_000.0, 5_000_000.0
UTM = "EPSG:32632"
W, H = 80, 60
# a pixel camera whose numbers survive every format exactly (binary fractions)
PIXCAM = {"width": W, "height": H, "focal_length_px": 500.0, "principal_point_px": [39.5, 29.5],
          "distortion": {"k1": -0.0625, "k2": 0.0, "k3": 0.0, "p1": 0.0, "p2": 0.0}}
R0 = matrix_from_angles(0.03, -0.02, 0.2)
C0 = np.array([E0, N0, 600.0])


def _dem(path):
    n = 100
    yy, xx = np.mgrid[0:n, 0:n]
    z = 100 + 10 * np.sin(xx / 9.0) + 0.2 * yy
    with rasterio.open(path, "w", driver="GTiff", width=n, height=n, count=1, dtype="float32", crs=UTM,
                       transform=rasterio.Affine(4.0, 0, E0 - 200, 0, -4.0, N0 + 200)) as ds:
        ds.write(z.astype("float32"), 1)


def _image(path, gcps=None):
    rr, cc = np.mgrid[0:H, 0:W]
    img = (100 + 50 * np.sin(cc / 3.0) * np.cos(rr / 4.0)).astype(np.uint8)
    kw = {"gcps": gcps, "crs": UTM} if gcps else {}
    with rasterio.open(path, "w", driver="GTiff", width=W, height=H, count=1, dtype="uint8", **kw) as ds:
        ds.write(img[None])


@pytest.fixture()
def frame(tmp_path):
    _dem(tmp_path / "dem.tif")
    _image(tmp_path / "img.tif")
    (tmp_path / "cam.json").write_text(json.dumps(PIXCAM))
    (tmp_path / "eo.json").write_text(json.dumps({"position": C0.tolist(), "rotation": R0.tolist(), "crs": UTM}))
    return tmp_path


def _ortho(d, out, *args):
    return _ok(rectify_cli, ["ortho", d / "img.tif", "--dem", d / "dem.tif", "-o", out, "--resolution", "2", *args])


def test_ortho_reads_every_camera_and_exterior_format(frame):
    d = frame
    cam = Camera.from_dict(PIXCAM)
    _ortho(d, d / "ours.tif", "--camera", d / "cam.json", "--exterior", d / "eo.json")
    eos = {"img": {"position": np.array(C0), "rotation": R0, "camera": "cam1"}}
    (d / "int_param.yaml").write_text(int_param_text({"cam1": cam}))
    (d / "ext_param.geojson").write_text(ext_param_text(eos, UTM))
    (d / "xyz_opk.csv").write_text("# angles=rad\n" + frame_csv_text(eos, radians=True))
    (d / "xyz_opk.prj").write_text(UTM + "\n")
    write_opencv_calibration(d / "calib.yml", cam)
    (d / "colmap").mkdir()
    write_colmap(d / "colmap", {"1": cam}, [Pose("img.tif", "1", C0, R0)])
    runs = {"orthority": ["--camera", d / "int_param.yaml", "--exterior", d / "ext_param.geojson"],
            "orthority-csv": ["--camera", d / "int_param.yaml", "--exterior", d / "xyz_opk.csv"],
            "opencv": ["--camera", d / "calib.yml", "--exterior", d / "eo.json"],
            "colmap": ["--exterior", d / "colmap", "--eo-crs", UTM]}
    for name, args in runs.items():
        r = _ortho(d, d / f"{name}.tif", *args)
        assert "orientation:" in r.output
        a, b = _same_raster(d / "ours.tif", d / f"{name}.tif")
        if name == "colmap":  # the rotation went through a unit quaternion (1e-16): a DN at a rounding edge at most
            assert np.abs(a.astype(int) - b.astype(int)).max() <= 1 and (a != b).mean() < 0.01, name
        else:
            assert np.array_equal(a, b), name
    assert "camera 'cam1' of orthority interior parameters" in _ortho(d, d / "o2.tif", "--overwrite", *runs[
        "orthority"]).output


def _metashape_local(path, cameras, poses, markers=(), meas=()):
    """A Metashape XML of a local chunk (no chunk transform): sensors (pixel cameras, no distortion), aligned
    cameras (transform camera -> chunk = [R diag(1,-1,-1) | C]), markers (label, xyz) and measurements
    (label, image, pixel ours -> + 0.5)."""
    sensors = []
    for sid, c in cameras.items():
        K = np.asarray(c.K)
        f, cx, cy = float(K[1, 1]), float(K[0, 2]) - (c.width - 1) / 2, float(K[1, 2]) - (c.height - 1) / 2
        sensors.append(f'<sensor id="{sid}" label="s{sid}" type="frame"><resolution width="{c.width}" '
                       f'height="{c.height}"/><calibration type="frame" class="adjusted"><resolution '
                       f'width="{c.width}" height="{c.height}"/><f>{f!r}</f><cx>{cx!r}</cx><cy>{cy!r}</cy>'
                       f'</calibration></sensor>')
    ids = {}
    cams = []
    for i, p in enumerate(poses):
        M = np.eye(4)
        M[:3, :3] = p.rotation @ FLIP
        M[:3, 3] = p.position
        ids[p.image] = i
        cams.append(f'<camera id="{i}" sensor_id="{p.camera}" label="{p.image}"><transform>'
                    f'{" ".join(repr(float(v)) for v in M.ravel())}</transform></camera>')
    mk = "".join(f'<marker id="{k}" label="{lab}"><reference x="{float(x)!r}" y="{float(y)!r}" z="{float(z)!r}"/>'
                 f'</marker>' for k, (lab, (x, y, z)) in enumerate(markers))
    mid = {lab: k for k, (lab, _) in enumerate(markers)}
    fr = "".join(f'<marker marker_id="{mid[lab]}"><location camera_id="{ids[im]}" x="{float(px[0]) + 0.5!r}" '
                 f'y="{float(px[1]) + 0.5!r}"/></marker>' for lab, im, px in meas)
    Path(path).write_text(f'<?xml version="1.0"?><document version="2.0.0"><chunk label="c"><sensors>{"".join(sensors)}'
                          f'</sensors><cameras>{"".join(cams)}</cameras><markers>{mk}</markers><frames><frame id="0">'
                          f'<markers>{fr}</markers></frame></frames></chunk></document>')
    return Path(path)


def test_ortho_reads_metashape_cameras_and_a_camera_id(frame):
    d = frame
    cam = Camera.from_dict(PIXCAM)
    _ortho(d, d / "ours.tif", "--camera", d / "cam.json", "--exterior", d / "eo.json")
    # the lens k1 is not in this sample: a camera without distortion on both sides
    plain = Camera.from_dict({**PIXCAM, "distortion": {}})
    (d / "plain.json").write_text(json.dumps(plain.to_dict()))
    _ortho(d, d / "plain.tif", "--camera", d / "plain.json", "--exterior", d / "eo.json")
    xml = _metashape_local(d / "cameras.xml", {"0": plain, "1": cam}, [Pose("img.tif", "0", C0, R0)])
    r = _ortho(d, d / "ms.tif", "--exterior", xml, "--eo-crs", UTM)
    assert "camera '0' of the same file" in r.output
    a, b = _same_raster(d / "plain.tif", d / "ms.tif")
    assert np.abs(a.astype(int) - b.astype(int)).max() <= 1 and (a != b).mean() < 0.01
    # an int_param of two cameras: the exterior's camera, else --camera-id, else refused with the ids
    (d / "two.yaml").write_text(int_param_text({"a": cam, "b": plain}))
    (d / "eo_b.geojson").write_text(ext_param_text({"img": {"position": C0, "rotation": R0, "camera": "b"}}, UTM))
    _ortho(d, d / "b.tif", "--camera", d / "two.yaml", "--exterior", d / "eo_b.geojson")
    assert np.array_equal(*_same_raster(d / "plain.tif", d / "b.tif"))
    _ortho(d, d / "a.tif", "--camera", d / "two.yaml", "--camera-id", "a", "--exterior", d / "eo.json")
    assert np.array_equal(*_same_raster(d / "ours.tif", d / "a.tif"))
    r = _run(rectify_cli, ["ortho", d / "img.tif", "--dem", d / "dem.tif", "-o", d / "x.tif", "--camera",
                           d / "two.yaml", "--exterior", d / "eo.json"])
    assert r.exit_code == 1 and "holds 2 cameras ['a', 'b']; name one (--camera-id)" in r.output
    assert not (d / "x.tif").exists() and not (d / "x.stac.json").exists()


def test_ortho_gcps_of_other_tools_check_the_frame_model(frame):
    d = frame
    cam = Camera.from_dict(PIXCAM)
    pose = Pose("img.tif", "c", C0, R0)
    rng = np.random.default_rng(29)
    xy = np.column_stack([E0 + rng.uniform(-40, 40, 6), N0 + rng.uniform(-30, 30, 6)])
    ground = np.column_stack([xy, np.full(6, 110.0)])
    px = project_pixel(cam, pose, ground).tolist()
    ground = ground.tolist()
    ids = [f"g{i}" for i in range(6)]
    (d / "gcps.csv").write_text(f"# crs={UTM}\nid,col,row,x,y,z\n" + "".join(
        f"{i},{p[0]!r},{p[1]!r},{g[0]!r},{g[1]!r},{g[2]!r}\n" for i, p, g in zip(ids, px, ground, strict=True)))
    (d / "gcp_list.txt").write_text(f"{UTM}\n" + "".join(
        f"{g[0]!r} {g[1]!r} {g[2]!r} {p[0]!r} {p[1]!r} img.tif {i}\n" for i, p, g in zip(ids, px, ground, strict=True))
        + "".join(f"{g[0]!r} {g[1]!r} {g[2]!r} 1 2 other.tif {i}\n" for i, g in zip(ids, ground, strict=True)))
    base = ["--camera", d / "cam.json", "--exterior", d / "eo.json", "--gcp-heights", "dem"]
    ours = _ortho(d, d / "o1.tif", *base, "--gcps", d / "gcps.csv").output
    odm = _ortho(d, d / "o2.tif", *base, "--gcps", d / "gcp_list.txt").output
    assert "GCPs: OpenDroneMap gcp_list.txt" in odm and "image 'img.tif'" in odm
    line = [ln for ln in ours.splitlines() if ln.startswith("GCP check")][0]
    assert line in odm  # the same residuals, to the printed digits
    xml = _metashape_local(d / "markers.xml", {"0": cam}, [Pose("img.tif", "0", C0, R0)],
                           [(i, g) for i, g in zip(ids, ground, strict=True)],
                           [(i, "img.tif", p) for i, p in zip(ids, px, strict=True)])
    ms = _ortho(d, d / "o3.tif", *base, "--gcps", f"metashape:{xml}").output
    assert "Metashape markers XML" in ms
    ms_line = [ln for ln in ms.splitlines() if ln.startswith("GCP check")][0]
    # Metashape's pixels gain and lose 0.5: the residuals agree to the printed digits
    assert ms_line == line


def test_fit_and_warp_read_gcps_of_other_tools(tmp_path):
    rng = np.random.default_rng(12)
    Hm = np.array([[2.0, 0.1, 500000.0], [0.05, -2.0, 4400000.0], [1e-5, 2e-5, 1.0]])
    pix = rng.uniform(0, [W - 1, H - 1], (8, 2))
    q = np.c_[pix, np.ones(8)] @ Hm.T
    tgt = (q[:, :2] / q[:, 2:]).tolist()
    pix = pix.tolist()
    ids = [f"p{i}" for i in range(8)]
    _image(tmp_path / "src.tif")
    crs = "EPSG:32618"
    (tmp_path / "gcps.csv").write_text(f"# crs={crs}\nid,col,row,x,y\n" + "".join(
        f"{i},{p[0]!r},{p[1]!r},{t[0]!r},{t[1]!r}\n" for i, p, t in zip(ids, pix, tgt, strict=True)))
    (tmp_path / "gcp_list.txt").write_text(f"{crs}\n" + "".join(
        f"{t[0]!r} {t[1]!r} 0 {p[0]!r} {p[1]!r} src.tif {i}\n" for i, p, t in zip(ids, pix, tgt, strict=True)))
    xml = _metashape_local(tmp_path / "markers.xml", {"0": Camera.from_dict(PIXCAM)},
                           [Pose("src.tif", "0", C0, R0)], [(i, (t[0], t[1], 0.0)) for i, t in zip(ids, tgt,
                                                                                                     strict=True)],
                           [(i, "src.tif", p) for i, p in zip(ids, pix, strict=True)])
    fits = {}
    for name, args in {"ours": [tmp_path / "gcps.csv"], "odm": [tmp_path / "gcp_list.txt"],
                       "metashape": [xml, "--image", tmp_path / "src.tif"]}.items():
        _ok(rectify_cli, ["fit", *args, "-o", tmp_path / f"{name}.json", "--method", "affine"])
        fits[name] = np.asarray(read_transform(tmp_path / f"{name}.json").model.matrix)
    assert_allclose(fits["odm"], fits["ours"], rtol=0, atol=1e-9)
    # Metashape's pixels lose 0.5 on reading: x + 0.5 - 0.5 is exact to the last bit or two
    assert_allclose(fits["metashape"], fits["ours"], rtol=1e-12, atol=1e-9)
    r = _ok(rectify_cli, ["warp", tmp_path / "src.tif", tmp_path / "w.tif", "--gcps", tmp_path / "gcp_list.txt",
                          "--method", "affine"])
    assert "GCPs: OpenDroneMap gcp_list.txt" in r.output
    item = pystac.Item.from_file(str(tmp_path / "w.stac.json"))
    assert item.assets["image"].extra_fields["file:checksum"] == file_checksum(tmp_path / "w.tif")
    assert item.properties["rectify:accuracy"]["gcp_count"] == 8


def test_embedded_gcps_pixel_convention(tmp_path):
    """orthority writes GCPs at pixel centres (ours); GDAL's corner reading shifts them by half a pixel."""
    pix = np.array([[5.0, 5.0], [70.0, 8.0], [10.0, 50.0], [66.0, 52.0], [40.0, 30.0]])
    tgt = np.column_stack([E0 + 2.0 * pix[:, 0], N0 - 2.0 * pix[:, 1]])
    gcps = [GroundControlPoint(row=float(p[1]), col=float(p[0]), x=float(t[0]), y=float(t[1]), id=f"g{i}")
            for i, (p, t) in enumerate(zip(pix, tgt, strict=True))]
    _image(tmp_path / "src.tif", gcps=gcps)
    for conv in ("corner", "centre"):
        _ok(rectify_cli, ["fit", tmp_path / "src.tif", "-o", tmp_path / f"{conv}.json", "--method", "affine",
                          "--gcp-pixel", conv])
    a = {c: np.asarray(read_transform(tmp_path / f"{c}.json").model.matrix) for c in ("corner", "centre")}
    # centre: target = E0 + 2 col exactly; corner: the pixels lost 0.5, so the map moved by half a pixel (1 m)
    assert_allclose(a["centre"] @ [10.0, 20.0, 1.0], [E0 + 20.0, N0 - 40.0, 1.0], atol=1e-6)
    assert_allclose(a["corner"] @ [10.0, 20.0, 1.0], [E0 + 21.0, N0 - 41.0, 1.0], atol=1e-6)
    r = _run(rectify_cli, ["fit", tmp_path / "c.csv", "-o", tmp_path / "x.json", "--gcp-pixel", "centre"])
    (tmp_path / "c.csv").write_text("id,col,row,x,y\n")
    r = _run(rectify_cli, ["fit", tmp_path / "c.csv", "-o", tmp_path / "x.json", "--gcp-pixel", "centre"])
    assert r.exit_code == 1 and "--gcp-pixel centre applies to GCPs embedded in a GeoTIFF" in r.output
    assert not (tmp_path / "x.json").exists()


# ------------------------------------------------------------------ bad input through the commands
def _bad_int_param(d):
    (d / "bad.yaml").write_text("DMC:\n  type: pinhole\n  im_size: [80, 60]\n  focal_len: ten\n")
    return ["ortho", d / "img.tif", "--dem", d / "dem.tif", "-o", d / "o.tif", "--camera", d / "bad.yaml",
            "--exterior", d / "eo.json"], ["bad.yaml", "focal_len", "'ten'"]


def _bad_fisheye(d):
    (d / "fe.yaml").write_text("DMC:\n  type: fisheye\n  im_size: [80, 60]\n  focal_len: 1.0\n")
    return ["ortho", d / "img.tif", "--dem", d / "dem.tif", "-o", d / "o.tif", "--camera", d / "fe.yaml",
            "--exterior", d / "eo.json"], ["fe.yaml", "`type`", "'fisheye'"]


def _bad_opencv(d):
    (d / "cal.yml").write_text("%YAML:1.0\n---\nimage_width: 80\nimage_height: 60\n"
                               "camera_matrix: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n"
                               "   data: [ 500., 0., 39.5, 0., 500., 29.5, 0., 0., 1. ]\n"
                               "distortion_coefficients: !!opencv-matrix\n   rows: 8\n   cols: 1\n   dt: d\n"
                               "   data: [ 0., 0., 0., 0., 0., 0.25, 0., 0. ]\n")
    return ["ortho", d / "img.tif", "--dem", d / "dem.tif", "-o", d / "o.tif", "--camera", d / "cal.yml",
            "--exterior", d / "eo.json"], ["cal.yml", "distortion_coefficients", "'k4': 0.25"]


def _bad_ext_param(d):
    (d / "ext.geojson").write_text(json.dumps({"type": "FeatureCollection", "world_crs": UTM, "features": [
        {"type": "Feature", "properties": {"filename": "img", "xyz": [1, 2, "high"], "opk": [0, 0, 0]},
         "geometry": None}]}))
    return ["ortho", d / "img.tif", "--dem", d / "dem.tif", "-o", d / "o.tif", "--camera", d / "cam.json",
            "--exterior", d / "ext.geojson"], ["ext.geojson", "`xyz`", "'high'"]


def _bad_prj(d):
    (d / "opk.csv").write_text("# crs=EPSG:32633\nfilename,x,y,z,omega,phi,kappa\nimg,1,2,3,0,0,0\n")
    (d / "opk.prj").write_text(UTM + "\n")
    return ["ortho", d / "img.tif", "--dem", d / "dem.tif", "-o", d / "o.tif", "--camera", d / "cam.json",
            "--exterior", d / "opk.csv"], ["opk.csv", "EPSG:32633", "contradicts"]


def _bad_colmap(d):
    (d / "m").mkdir()
    (d / "m" / "cameras.txt").write_text("1 OPENCV_FISHEYE 80 60 500 500 40 30 0 0 0 0\n")
    (d / "m" / "images.txt").write_text("1 1 0 0 0 0 0 0 1 img.tif\n\n")
    return ["ortho", d / "img.tif", "--dem", d / "dem.tif", "-o", d / "o.tif", "--exterior", d / "m", "--eo-crs",
            UTM], ["cameras.txt", "line 1", "'OPENCV_FISHEYE'"]


def _bad_metashape(d):
    (d / "ms.xml").write_text('<document><chunk><sensors><sensor id="0" type="frame"><resolution width="80" '
                              'height="60"/><calibration type="frame" class="adjusted"><resolution width="80" '
                              'height="60"/><f>500</f></calibration></sensor></sensors><cameras><camera id="0" '
                              'sensor_id="0" label="img.tif"><transform>1 0 0</transform></camera></cameras>'
                              '</chunk></document>')
    return ["ortho", d / "img.tif", "--dem", d / "dem.tif", "-o", d / "o.tif", "--exterior", d / "ms.xml",
            "--eo-crs", UTM], ["ms.xml", "`transform`", "16 numbers"]


def _bad_oty_gcps(d):
    (d / "g.geojson").write_text(json.dumps({"type": "FeatureCollection", "features": [
        {"type": "Feature", "properties": {"filename": "img.tif", "ji": [1, "x"], "id": "a"},
         "geometry": {"type": "Point", "coordinates": [9.0, 45.0, 100.0]}}]}))
    return ["ortho", d / "img.tif", "--dem", d / "dem.tif", "-o", d / "o.tif", "--camera", d / "cam.json",
            "--exterior", d / "eo.json", "--gcps", d / "g.geojson"], ["g.geojson", "`ji`", "'x'"]


def _bad_odm_gcps(d):
    (d / "gcp_list.txt").write_text("EPSG:32632\n500000 5000000 100 10 twenty img.tif g1\n")
    return ["fit", d / "gcp_list.txt", "-o", d / "t.json"], ["gcp_list.txt", "line 2", "im_y", "'twenty'"]


def _bad_odm_header(d):
    (d / "gcp_list.txt").write_text("UTM 32N\n500000 5000000 100 10 20 img.tif g1\n")
    return ["warp", d / "img.tif", d / "o.tif", "--gcps", "odm:" + str(d / "gcp_list.txt")], \
        ["gcp_list.txt", "line 1", "'UTM 32N'"]


def _ambiguous(d):
    (d / "both.json").write_text(json.dumps({"DMC": {"type": "pinhole", "im_size": [80, 60], "focal_len": 1.0},
                                             "camera_matrix": [[1, 0, 0], [0, 1, 0], [0, 0, 1]],
                                             "image_width": 80}))
    return ["ortho", d / "img.tif", "--dem", d / "dem.tif", "-o", d / "o.tif", "--camera", d / "both.json",
            "--exterior", d / "eo.json"], ["both.json", "could be read as any of", "orthority", "opencv",
                                            "choices: orthority, opencv", "orthority:"]


def _no_image_entry(d):
    (d / "ext.geojson").write_text(ext_param_text({"other": {"position": C0, "rotation": R0}}, UTM))
    return ["ortho", d / "img.tif", "--dem", d / "dem.tif", "-o", d / "o.tif", "--camera", d / "cam.json",
            "--exterior", d / "ext.geojson"], ["ext.geojson", "'img.tif' has no entry", "['other']"]


def _several_images(d):
    t = GcpTable(("a", "b", "c", "d"), np.zeros((4, 2)) + np.arange(4)[:, None], np.full((4, 2), 9.0) +
                 np.arange(4)[:, None], np.full(4, 100.0), np.zeros(4, bool), "EPSG:4979")
    (d / "g.geojson").write_text(oty_gcps_text({"one.tif": t, "two.tif": t}))
    return ["fit", d / "g.geojson", "-o", d / "t.json"], ["g.geojson", "holds 2 images", "--image"]


BAD = {f.__name__[1:]: f for f in (_bad_int_param, _bad_fisheye, _bad_opencv, _bad_ext_param, _bad_prj, _bad_colmap,
                                    _bad_metashape, _bad_oty_gcps, _bad_odm_gcps, _bad_odm_header, _ambiguous,
                                    _no_image_entry, _several_images)}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_input_of_every_reader_through_the_commands(frame, case):
    d = frame
    args, expect = BAD[case](d)
    before = _hashes(p for p in d.rglob("*"))
    r = _run(rectify_cli, args)
    assert r.exit_code == 1, r.output
    msg = r.output.strip()
    assert msg.count("\n") == 0, msg  # one line
    for e in expect:
        assert e in msg, (e, msg)
    assert _hashes(p for p in d.rglob("*")) == before  # inputs untouched, no output left
    assert not any(p.name.startswith(("o.", "t.")) for p in d.iterdir())


def test_an_ambiguous_file_is_read_with_the_kind_named(frame):
    d = frame
    _ambiguous(d)
    cam = Camera.from_dict(PIXCAM)
    write_opencv_calibration(d / "calib.json", cam)
    doc = json.loads((d / "calib.json").read_text())
    doc["DMC"] = {"type": "pinhole", "im_size": [W, H], "focal_len": 500.0, "sensor_size": [W, H]}
    (d / "both2.json").write_text(json.dumps(doc))
    r = _run(rectify_cli, ["ortho", d / "img.tif", "--dem", d / "dem.tif", "-o", d / "o.tif", "--camera",
                           d / "both2.json", "--exterior", d / "eo.json"])
    assert r.exit_code == 1 and "could be read as any of" in r.output
    _ortho(d, d / "ours.tif", "--camera", d / "cam.json", "--exterior", d / "eo.json")
    _ortho(d, d / "cv.tif", "--camera", f"opencv:{d / 'both2.json'}", "--exterior", d / "eo.json")
    assert np.array_equal(*_same_raster(d / "ours.tif", d / "cv.tif"))
    r = _run(rectify_cli, ["ortho", d / "img.tif", "--dem", d / "dem.tif", "-o", d / "o.tif", "--camera",
                           f"nosuch:{d / 'cam.json'}", "--exterior", d / "eo.json"])
    assert r.exit_code == 1 and "unknown file kind 'nosuch'" in r.output


# ------------------------------------------------------------------ STAC Items, all or nothing
def test_products_write_a_stac_item_in_their_transaction(frame, monkeypatch):
    d = frame
    _ortho(d, d / "o.tif", "--camera", d / "cam.json", "--exterior", d / "eo.json")
    item = pystac.Item.from_file(str(d / "o.stac.json"))
    a = item.assets["ortho"]
    assert a.href == "o.tif" and "data" in (a.roles or [])
    assert a.extra_fields["file:checksum"] == file_checksum(d / "o.tif")
    assert item.properties["proj:code"] == UTM and item.properties["proj:shape"][0] > 0
    assert item.properties["processing:software"]["rectify-stereo"]
    hrefs = {Path(i["href"]).name for i in item.properties["rectify:inputs"]}
    assert hrefs == {"img.tif", "dem.tif", "cam.json", "eo.json"}
    assert "max_relief_shift_m" in item.properties["rectify:accuracy"]
    _ok(rectify_cli, ["mosaic", d / "o.tif", "-o", d / "m.tif"])
    assert pystac.Item.from_file(str(d / "m.stac.json")).assets["mosaic"].href == "m.tif"
    _ortho(d, d / "n.tif", "--camera", d / "cam.json", "--exterior", d / "eo.json", "--no-stac")
    assert not (d / "n.stac.json").exists()
    # an Item that exists is refused before any work; a failing Item leaves neither file
    (d / "p.stac.json").write_text("{}")
    r = _run(rectify_cli, ["ortho", d / "img.tif", "--dem", d / "dem.tif", "-o", d / "p.tif", "--camera",
                           d / "cam.json", "--exterior", d / "eo.json"])
    assert r.exit_code == 1 and "p.stac.json" in r.output and "exists" in r.output and not (d / "p.tif").exists()
    def fail(*args, **kwargs):
        raise RasterIOError("cannot write 'q.stac.json': disk full (injected)")

    monkeypatch.setattr(ortho_action, "write_stac", fail)
    r = _run(rectify_cli, ["ortho", d / "img.tif", "--dem", d / "dem.tif", "-o", d / "q.tif", "--camera",
                           d / "cam.json", "--exterior", d / "eo.json"])
    assert r.exit_code == 1 and "injected" in r.output
    assert not any(p.name.startswith((".q", "q.")) for p in d.iterdir())


def test_dense_writes_the_stac_item_of_its_dsm_and_cloud(tmp_path):
    sc = make_scene(3, size_px=160)
    cv2.imwrite(str(tmp_path / "l.png"), render(sc, "left"))
    cv2.imwrite(str(tmp_path / "r.png"), render(sc, "right"))
    for side, eo in (("l", sc.left), ("r", sc.right)):
        write_exterior(tmp_path / f"{side}.json", dataclasses.replace(eo, sigma0=0.0, crs=sc.crs),
                       camera=sc.camera.to_dict())
    args = ["dense", tmp_path / "l.json", tmp_path / "l.png", tmp_path / "r.png", "--right-orientation",
            tmp_path / "r.json", "--cloud", "ply"]
    _ok(stereo_cli, [*args, "-o", tmp_path / "out"])
    item = pystac.Item.from_file(str(tmp_path / "out" / "item.stac.json"))
    assert {k: a.href for k, a in item.assets.items()} == {"dsm": "dsm.tif", "metadata": "dense.json",
                                                            "points": "points.ply"}
    for a in item.assets.values():
        assert a.extra_fields["file:checksum"] == file_checksum(tmp_path / "out" / a.href)
    with rasterio.open(tmp_path / "out" / "dsm.tif") as ds:
        assert item.properties["proj:shape"] == [ds.height, ds.width]
        assert item.properties["proj:transform"] == list(ds.transform)[:6]
    assert item.properties["rectify:accuracy"]["vertical_parallax_rms_px"] >= 0
    _ok(stereo_cli, [*args, "-o", tmp_path / "out2", "--no-stac"])
    assert not (tmp_path / "out2" / "item.stac.json").exists()


def test_opensfm_writer_round_trip_and_refusals(tmp_path):
    cam = Camera.from_dict({"width": 4000, "height": 3000, "focal_length_px": 3300.0,
                            "principal_point_px": [2001.25, 1498.5],
                            "distortion": {"k1": -0.05, "k2": 0.01, "k3": 1e-3, "p1": 1e-4, "p2": -2e-4}})
    rng = np.random.default_rng(4)
    poses = []
    for i in range(3):
        om, ph = rng.uniform(-0.1, 0.1, 2)
        poses.append(Pose(f"I{i}.JPG", "c", rng.uniform(-50, 50, 3), matrix_from_angles(om, ph, rng.uniform(-3, 3))))
    pts = rng.uniform(-20, 20, (5, 3))
    (tmp_path / "local").mkdir()
    write_opensfm(tmp_path / "local", {"c": cam}, poses, points=pts)  # no CRS: its own frame, no reference_lla
    rec = read_opensfm(tmp_path / "local" / "reconstruction.json")
    assert rec.crs is None and rec.reference_lonlat_h is None
    _close({p.image: p for p in rec.poses}, {p.image: p for p in poses}, 1e-12, 1e-13)
    assert_allclose(rec.points, pts, rtol=0, atol=0)
    assert_allclose(np.asarray(rec.cameras["c"].K), np.asarray(cam.K), rtol=1e-15)
    assert rec.cameras["c"].distortion == pytest.approx(cam.distortion, rel=1e-15)
    skew = Camera.from_dict({"width": 40, "height": 30, "fx_px": 30.0, "fy_px": 30.0, "skew_px": 0.5,
                             "principal_point_px": [19.5, 14.5]})
    with pytest.raises(InvalidInputError, match="skew 0.5"):
        opensfm_texts({"c": skew}, poses)
    with pytest.raises(InvalidInputError, match="names camera 'c'"):
        opensfm_texts({"d": cam}, poses)
    with pytest.raises(CRSError, match="must be projected"):
        opensfm_texts({"c": cam}, poses, crs="EPSG:4326")


# ------------------------------------------------------------------ stereo calibrate -o *.yml
def test_calibrate_writes_an_opencv_file(tmp_path):
    sc = field_scene(np.random.default_rng(3), n_views=2, n_points=40, noise_px=0.2)
    (tmp_path / "obs.csv").write_text("view,point,col,row\n" + "".join(
        f"{v.name},{p},{c!r},{r!r}\n" for v in sc.views for p, (c, r) in zip(v.ids, v.pixel.tolist(), strict=True)))
    v0 = sc.views[0]
    (tmp_path / "field.csv").write_text("point,x,y,z\n" + "".join(
        f"{p},{x!r},{y!r},{z!r}\n" for p, (x, y, z) in zip(v0.ids, v0.object_xyz.tolist(), strict=True)))
    base = ["calibrate", "--points", tmp_path / "obs.csv", "--field", tmp_path / "field.csv", "--size", "640x480"]
    _ok(stereo_cli, [*base, "-o", tmp_path / "cam.json"])
    for suffix in (".yml", ".xml"):
        r = _ok(stereo_cli, [*base, "-o", tmp_path / f"cam{suffix}"])
        assert f"cam{suffix}" in r.output
        cv = read_opencv_calibration(tmp_path / f"cam{suffix}")
        ours = Camera.from_dict({k: v for k, v in json.loads((tmp_path / "cam.json").read_text()).items()
                                 if k not in ("format", "version")})
        assert_allclose(np.asarray(cv.K), np.asarray(ours.K), rtol=1e-15)
        assert cv.distortion == pytest.approx(ours.distortion, rel=1e-15, abs=1e-300)
    # what an OpenCV file cannot hold is refused before any work
    r = _run(stereo_cli, [*base, "--symmetry", "-o", tmp_path / "sym.yml"])
    assert r.exit_code == 1 and "no separate point of symmetry" in r.output and not (tmp_path / "sym.yml").exists()


# ------------------------------------------------------------------ the rendered block (stereo block)
@pytest.fixture(scope="module")
def block(tmp_path_factory):
    d = tmp_path_factory.mktemp("users_block")
    images, poses, xyz = write_example_block(d)
    out = d / "ref"
    _ok(stereo_cli, ["block", *images, "--camera", d / "camera.json", "--poses", d / "poses.csv", "--gnss-sigma",
                     "0.05", "--control", d / "control.csv", "--no-report", "-o", out, "--colmap", d / "colmap",
                     "--opensfm", d / "opensfm", "--orthority", d / "orthority"])
    return d, images, poses, out


def _poses_of(out):
    return {q.image: q for q in read_block_orientation(out / "orientation.json").poses}


def _close(a, b, pos_m, rot):
    assert a.keys() == b.keys()
    for k in a:
        assert np.abs(a[k].position - b[k].position).max() < pos_m, (k, a[k].position - b[k].position)
        assert np.abs(angles_from_matrix(a[k].rotation.T @ b[k].rotation)).max() < rot, k


def test_block_exports_read_back(block):
    d, images, _poses, out = block
    ref = read_block_orientation(out / "orientation.json")
    poses = {q.image: q for q in ref.poses}
    # COLMAP: exact to the rounding of C = -R^T t (1e-15 of 5e6 m coordinates) and of the quaternion; its points
    # with their tracks
    m = read_colmap(d / "colmap")
    _close({p.image: p for p in m.poses}, poses, 1e-8, 1e-12)
    assert m.tracks is not None and m.tracks.n_points > 100
    cam = next(iter(ref.cameras.values()))
    assert_allclose(np.asarray(m.cameras["camera"].K), np.asarray(cam.K), rtol=0, atol=1e-9)
    # OpenSfM: topocentric about the mean centre, back through PROJ
    rec = read_opensfm(d / "opensfm" / "reconstruction.json").to_crs(BLOCK_CRS)
    _close({p.image: p for p in rec.poses}, poses, 1e-6, 1e-8)
    assert json.loads((d / "opensfm" / "camera_models.json").read_text())["camera"]["projection_type"] == "brown"
    # orthority: the camera and the poses as written (JSON numbers: exact)
    oc = read_int_param(d / "orthority" / "int_param.yaml")["camera"]
    assert_allclose(np.asarray(oc.K), np.asarray(cam.K), rtol=1e-15)
    eos = read_ext_param(d / "orthority" / "ext_param.geojson")
    for k, q in poses.items():
        assert np.array_equal(eos[k]["position"], q.position)
        assert_allclose(eos[k]["rotation"], q.rotation, rtol=0, atol=1e-15)
    item = pystac.Item.from_file(str(out / "item.stac.json"))
    assert {a.href for a in item.assets.values()} == {"points.las", "points.ply"}
    assert item.properties["rectify:accuracy"]["sigma0"] > 0 and item.bbox is not None


def test_block_from_a_colmap_model_reuses_its_tracks(block, tmp_path):
    d, images, _poses, out = block
    r = _ok(stereo_cli, ["block", *images, "--camera", d / "camera.json", "--poses", d / "colmap", "--gnss-sigma",
                         "0.05", "--control", d / "control.csv", "--no-report", "-o", tmp_path / "c"])
    assert "tracks of colmap" in r.output and "matching skipped" in r.output
    # the same block from its own adjusted result and written points: the adjustment lands where it started
    # (measured: 4.3e-6 m, 2.5e-6 rad; the tracks are the written points only, a few dozen fewer)
    _close(_poses_of(tmp_path / "c"), _poses_of(out), 1e-4, 2e-5)


def test_block_through_pycolmap(block, tmp_path):
    pycolmap = pytest.importorskip("pycolmap")
    d, images, _poses, out = block
    rec = pycolmap.Reconstruction(str(d / "colmap"))
    tracks = read_colmap(d / "colmap").tracks
    assert tracks is not None and rec.num_images() == len(images) and rec.num_points3D() == tracks.n_points
    (tmp_path / "pc").mkdir()
    rec.write_text(str(tmp_path / "pc"))
    again = read_colmap_images(tmp_path / "pc")
    ours = read_colmap_images(d / "colmap")
    order = {n: k for k, n in enumerate(ours.images)}
    for n, p in zip(again.images, again.positions, strict=True):
        assert np.abs(p - ours.positions[order[n]]).max() < 1e-6
    r = _ok(stereo_cli, ["block", *images, "--poses", tmp_path / "pc", "--gnss-sigma", "0.05", "--control",
                         d / "control.csv", "--no-report", "-o", tmp_path / "b"])
    assert "matching skipped" in r.output
    _close(_poses_of(tmp_path / "b"), _poses_of(out), 1e-4, 2e-5)


def test_block_control_from_odm_and_metashape(block, tmp_path):
    d, images, poses, _out = block
    lines = [ln.split(",") for ln in (d / "control.csv").read_text().splitlines()[2:]]
    (tmp_path / "gcp_list.txt").write_text(f"{BLOCK_CRS}\n" + "".join(
        f"{x} {y} {z} {c} {r} {im} {i}\n" for i, im, c, r, x, y, z in lines))
    meas = [(i, im, (float(c), float(r))) for i, im, c, r, *_ in lines]
    marks = {i: (float(x), float(y), float(z)) for i, _im, _c, _r, x, y, z in lines}
    cams = {"camera": Camera.from_dict(json.loads((d / "camera.json").read_text()))}
    read = read_pose_csv(d / "poses.csv")
    xml = _metashape_local(tmp_path / "markers.xml", cams, [Pose(p.image, "camera", p.position, p.rotation)
                                                           for p in read.poses], list(marks.items()), meas)
    base = ["block", *images, "--camera", d / "camera.json", "--poses", d / "poses.csv", "--gnss-sigma", "0.05",
            "--no-report"]
    _ok(stereo_cli, [*base, "--control", d / "control.csv", "-o", tmp_path / "csv"])
    r = _ok(stereo_cli, [*base, "--control", tmp_path / "gcp_list.txt", "-o", tmp_path / "odm"])
    assert "OpenDroneMap gcp_list.txt" in r.output
    _close(_poses_of(tmp_path / "odm"), _poses_of(tmp_path / "csv"), 1e-9, 1e-12)
    r = _ok(stereo_cli, [*base, "--control", xml, "-o", tmp_path / "ms"])
    assert "markers of" in r.output
    _close(_poses_of(tmp_path / "ms"), _poses_of(tmp_path / "csv"), 1e-7, 1e-10)
    # the Metashape cameras as poses (a local chunk: the control's CRS names its frame)
    r = _ok(stereo_cli, ["block", *images, "--camera", d / "camera.json", "--poses", xml, "--gnss-sigma", "0.05",
                         "--control", d / "control.csv", "--no-report", "-o", tmp_path / "msp"])
    _close(_poses_of(tmp_path / "msp"), _poses_of(tmp_path / "csv"), 1e-6, 1e-9)


def test_block_gnss_from_odm_geo_txt(block, tmp_path):
    d, images, poses, _out = block
    read = read_pose_csv(d / "poses.csv")
    (tmp_path / "geo.txt").write_text(f"{BLOCK_CRS}\n" + "".join(
        f"{p.image} {' '.join(map(repr, p.position.tolist()))} 0 0 0 0.05 0.05\n" for p in read.poses))
    r = _ok(stereo_cli, ["block", *images, "--camera", d / "camera.json", "--poses", tmp_path / "geo.txt",
                         "--control", d / "control.csv", "--no-report", "-o", tmp_path / "g"])
    assert "ODM geo.txt, sigma from its accuracies" in r.output and "GNSS positions" in r.output
    truth = {path.name: p for p, path in zip(poses, images, strict=True)}
    for k, q in _poses_of(tmp_path / "g").items():
        assert np.abs(q.position - truth[k].position - [BE0, BN0, 0.0]).max() < 0.1


def test_block_bad_input_of_the_readers(block, tmp_path):
    d, images, _poses, _out = block
    (tmp_path / "geo.txt").write_text(f"{BLOCK_CRS}\n{images[0].name} 1 2 3 0 0 0 0.05 -1\n")
    (tmp_path / "gcp_list.txt").write_text("UTM 33N\n1 2 3 4 5 a.tif g\n")
    (tmp_path / "ext.geojson").write_text(json.dumps({"type": "FeatureCollection", "world_crs": "EPSG:4326",
                                                      "features": []}))
    cases = {"geo": (["--poses", tmp_path / "geo.txt"], ["geo.txt", "line 2", "accuracies must be > 0", "-1"]),
             "odm": (["--control", tmp_path / "gcp_list.txt"], ["gcp_list.txt", "line 1", "'UTM 33N'"]),
             "ext": (["--poses", tmp_path / "ext.geojson"], ["ext.geojson", "world_crs", "projected"]),
             "colmap_skew": (["--colmap", tmp_path / "cm", "--camera", tmp_path / "skew.json", "--poses",
                              d / "poses.csv"],
                             ["skew", "colmap"])}
    (tmp_path / "skew.json").write_text(json.dumps({"width": CAM.width, "height": CAM.height, "fx_px": 400.0,
                                                    "fy_px": 400.0, "skew_px": 0.5,
                                                    "principal_point_px": [199.5, 149.5]}))
    for name, (args, expect) in cases.items():
        base = ["block", *images, "--camera", d / "camera.json", "--gnss-sigma", "0.05", "-o", tmp_path / name]
        r = _run(stereo_cli, [*base, *args])
        assert r.exit_code == 1, (name, r.output)
        assert r.output.strip().count("\n") == 0, r.output
        for e in expect:
            assert e in r.output, (name, e, r.output)
        assert not (tmp_path / name).exists() and not (tmp_path / "cm").exists()


# ------------------------------------------------------------------ the NGI frames in orthority's own files
def _ngi_files(d, tmp):
    """Our camera JSON, EO JSONs and poses CSVs of the NGI frames, with the values of orthority's files."""
    ext = json.loads((d / "orthority_ext_param.geojson").read_text())
    (tmp / "cam.json").write_text(json.dumps({"focal_length_mm": 120.0, "pixel_size_mm": 0.144, "width": 640,
                                              "height": 1152}))
    rows = ["# angles=rad", f"# crs={ext['world_crs']}", "image,x,y,z,omega,phi,kappa"]
    for f in ext["features"]:
        p = f["properties"]
        (tmp / f"eo_{p['filename']}.json").write_text(json.dumps({
            "position": p["xyz"], "rotation": matrix_from_angles(*p["opk"]).tolist(), "crs": ext["world_crs"]}))
        rows.append(",".join([p["filename"] + ".tif", *map(repr, p["xyz"]), *map(repr, p["opk"])]))
    (tmp / "poses_rad.csv").write_text("\n".join(rows) + "\n")
    prj = (d / "orthority_xyz_opk.prj").read_text().strip()
    lines = (d / "orthority_xyz_opk.csv").read_text().splitlines()
    deg = ["# angles=deg", f"# crs={prj}", "image,x,y,z,omega,phi,kappa"]
    deg += [f"{ln.split(',')[0]}.tif," + ",".join(ln.split(",")[1:]) for ln in lines[1:]]
    (tmp / "poses_deg.csv").write_text("\n".join(deg) + "\n")
    return ext


@pytest.mark.shared
def test_ngi_ortho_with_orthoritys_files_is_ours(ngi_pair, tmp_path):
    d = ngi_pair
    ext = _ngi_files(d, tmp_path)
    for f in ext["features"]:
        name = f["properties"]["filename"]
        img = d / f"{name}.tif"
        base = ["ortho", img, "--dem", d / "dem.tif", "--resolution", "6"]
        _ok(rectify_cli, [*base, "-o", tmp_path / f"ours_{name}.tif", "--camera", tmp_path / "cam.json",
                          "--exterior", tmp_path / f"eo_{name}.json"])
        _ok(rectify_cli, [*base, "-o", tmp_path / f"oty_{name}.tif", "--camera", d / "orthority_int_param.yaml",
                          "--exterior", d / "orthority_ext_param.geojson"])
        a, b = _same_raster(tmp_path / f"ours_{name}.tif", tmp_path / f"oty_{name}.tif")
        assert np.array_equal(a, b)  # identical orthophotos
        # the CSV (degrees to 3 decimals, CRS in the .prj) against our poses.csv of the same numbers
        _ok(rectify_cli, [*base, "-o", tmp_path / f"csv_{name}.tif", "--camera", tmp_path / "cam.json",
                          "--exterior", tmp_path / "poses_deg.csv"])
        _ok(rectify_cli, [*base, "-o", tmp_path / f"otycsv_{name}.tif", "--camera", d / "orthority_int_param.yaml",
                          "--exterior", d / "orthority_xyz_opk.csv"])
        a, b = _same_raster(tmp_path / f"csv_{name}.tif", tmp_path / f"otycsv_{name}.tif")
        assert np.array_equal(a, b)


def _ngi_control(d, tmp):
    """8 DEM points projected into both frames with the aero-triangulation (as tests/stereo/test_block_ngi.py)."""
    ext = json.loads((d / "orthority_ext_param.geojson").read_text())
    cam = Camera(focal_length_mm=120.0, pixel_size_mm=0.144, width=640, height=1152)
    poses = [Pose(f["properties"]["filename"] + ".tif", "c", f["properties"]["xyz"],
                  matrix_from_angles(*f["properties"]["opk"])) for f in ext["features"]]
    with rasterio.open(d / "dem.tif") as src:
        dem, T = src.read(1).astype(float), src.transform
    rng = np.random.default_rng(0)
    rows = [f"# crs={ext['world_crs']}", "id,image,col,row,x,y,z"]
    k = 0
    while k < 8:
        c = (poses[0].position[:2] + poses[1].position[:2]) / 2 + rng.uniform(-2500, 2500, 2) * [0.6, 1.0]
        col, row = ~T * (c[0], c[1])
        z = ndimage.map_coordinates(dem, [[row - 0.5], [col - 0.5]], order=1, cval=np.nan)[0]
        g = np.array([c[0], c[1], z])
        px = [project_pixel(cam, p, g[None])[0] for p in poses]
        if math.isfinite(z) and all(30 < q[0] < 610 and 30 < q[1] < 1122 for q in px):
            for p, q in zip(poses, px, strict=True):
                rows.append(",".join([f"dem{k}", p.image, *map(repr, q.tolist()), *map(repr, g.tolist())]))
            k += 1
    (tmp / "control.csv").write_text("\n".join(rows) + "\n")


@pytest.mark.shared
def test_ngi_block_with_orthoritys_files_is_ours(ngi_pair, tmp_path):
    d = ngi_pair
    _ngi_files(d, tmp_path)
    _ngi_control(d, tmp_path)
    images = [d / "3324c_2015_1004_05_0182_RGB.tif", d / "3324c_2015_1004_05_0184_RGB.tif"]
    base = ["block", *images, "--control", tmp_path / "control.csv", "--control-sigma", "0.5",
            "--control-sigma-px", "0.5", "--no-report"]
    runs = {"ours": ["--camera", tmp_path / "cam.json", "--poses", tmp_path / "poses_rad.csv"],
            "oty": ["--camera", d / "orthority_int_param.yaml", "--poses", d / "orthority_ext_param.geojson"],
            "ours_deg": ["--camera", tmp_path / "cam.json", "--poses", tmp_path / "poses_deg.csv"],
            "oty_csv": ["--camera", d / "orthority_int_param.yaml", "--poses", d / "orthority_xyz_opk.csv"]}
    for name, args in runs.items():
        _ok(stereo_cli, [*base, *args, "-o", tmp_path / name])
    _close(_poses_of(tmp_path / "oty"), _poses_of(tmp_path / "ours"), 1e-9, 1e-9)
    _close(_poses_of(tmp_path / "oty_csv"), _poses_of(tmp_path / "ours_deg"), 1e-9, 1e-9)
