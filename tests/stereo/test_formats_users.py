"""Users' files (issue 29), block side: COLMAP text models, ODM's gcp_list.txt and geo.txt, Metashape XML.

Samples are written here in the tools' documented layouts with our own values, no file of the tools
copied: COLMAP's text model layout (doc/format.rst, COLMAP is BSD-3-Clause), ODM's gcp_list.txt and
geo.txt layouts (OpenDroneMap docs, map-accuracy.rst, CC BY-SA / AGPL-3.0 project), and Metashape's
cameras/markers XML layout (Agisoft's XML export as documented by its manual's camera model, the
appendix on frame cameras). The COLMAP round trip through pycolmap (the ``bench`` extra) also reads a
model pycolmap itself wrote; it is skipped when pycolmap is not installed.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pyproj
import pytest
from numpy.testing import assert_allclose, assert_array_equal

from rectify import errors
from rectify.geometry.camera import Camera
from rectify.geometry.crs import transform_xyz
from rectify.geometry.geodesy import enu_rotation
from rectify.geometry.mapframe import grid_from_enu
from rectify.geometry.rotation import matrix_from_angles
from stereo.block.types import Pose, Tracks, project_pixel
from stereo.formats import colmap, metashape, odm

FLIP = np.diag([1.0, -1.0, -1.0])


def _write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


# ------------------------------------------------------------------ COLMAP
def _cameras() -> dict[str, Camera]:
    base = {"width": 4000, "height": 3000, "principal_point_px": [2001.25, 1498.5]}
    return {
        "1": Camera.from_dict({**base, "focal_length_px": 3300.125}),                                  # SIMPLE_PINHOLE
        "2": Camera.from_dict({**base, "focal_length_px": 3300.5, "distortion": {"k1": -0.05}}),       # SIMPLE_RADIAL
        "3": Camera.from_dict({**base, "focal_length_px": 3301.0, "distortion": {"k1": -0.05, "k2": 0.01}}),  # RADIAL
        "4": Camera.from_dict({**base, "fx_px": 3301.5, "fy_px": 3302.25}),                            # PINHOLE
        "dmc": Camera.from_dict({**base, "focal_length_px": 3302.0,                                      # OPENCV
                                 "distortion": {"k1": -0.05, "k2": 0.01, "p1": 1e-4, "p2": -2e-4}}),
        "full": Camera.from_dict({**base, "focal_length_px": 3303.0,                                     # FULL_OPENCV
                                  "distortion": {"k1": -0.05, "k2": 0.01, "k3": 1e-3, "p1": 1e-4}}),
    }


def _block() -> tuple[dict[str, Camera], list[Pose], Tracks, np.ndarray]:
    cams = _cameras()
    rng = np.random.default_rng(29)
    poses = [Pose(f"IMG_{i:04d}.JPG", cid, [300000.0 + 150.0 * i, 6270000.0 + rng.uniform(-5, 5), 500.0],
                  matrix_from_angles(*rng.uniform(-0.05, 0.05, 2), rng.uniform(-3, 3)))
             for i, cid in enumerate(cams)]
    pts = np.column_stack([rng.uniform(299900, 301000, 8), rng.uniform(6269800, 6270200, 8), rng.uniform(0, 30, 8)])
    o_pt, o_im, o_px = [], [], []
    for j in range(len(pts)):
        for k in rng.choice(len(poses), 3, replace=False):
            o_pt.append(j)
            o_im.append(k)
            o_px.append(rng.uniform(0, 3000, 2))
    tracks = Tracks(tuple(p.image for p in poses), tuple(f"tie{j}" for j in range(len(pts))), o_pt, o_im, o_px)
    return cams, poses, tracks, pts


def _ulps(p: Pose) -> float:
    """The file's precision for a position: C = -R^T t carries rounding of the largest coordinate (a few ulps)."""
    return 4 * float(np.spacing(np.abs(p.position).max()))


def _same_pose(a: Pose, b: Pose) -> None:
    assert a.image == b.image and a.camera == b.camera
    assert_allclose(b.position, a.position, rtol=0, atol=_ulps(a))
    assert_allclose(b.rotation, a.rotation, rtol=0, atol=1e-15)


def test_colmap_round_trip(tmp_path):
    cams, poses, tracks, pts = _block()
    rgb = np.arange(24).reshape(8, 3)
    colmap.write_colmap(tmp_path, cams, poses, points=pts, tracks=tracks, colors=rgb, errors=np.full(8, 0.25))
    models = [ln.split()[1] for ln in (tmp_path / "cameras.txt").read_text().splitlines() if not ln.startswith("#")]
    assert models == ["SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL", "PINHOLE", "OPENCV", "FULL_OPENCV"]
    assert colmap.detect_colmap(tmp_path) and colmap.detect_colmap(tmp_path / "images.txt")
    m = colmap.read_colmap(tmp_path)
    assert list(m.cameras) == list(cams)  # names kept through the comment lines
    for k, c in cams.items():
        assert_allclose(m.cameras[k].K, c.K, rtol=1e-15, atol=1e-12)
        assert m.cameras[k].distortion == c.distortion
    for a, b in zip(poses, m.poses, strict=True):
        _same_pose(a, b)
    assert m.point_ids == tracks.point_ids
    assert_array_equal(m.points, pts)
    assert_array_equal(m.colors, rgb)
    assert_array_equal(m.errors, 0.25)
    assert m.tracks is not None
    assert_array_equal(m.tracks.obs_point, tracks.obs_point)
    assert_array_equal(m.tracks.obs_image, tracks.obs_image)
    assert_allclose(m.tracks.obs_pixel, tracks.obs_pixel, rtol=0, atol=1e-12)


COLMAP_CAMERAS = """# Camera list with one line of data per camera:
#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]
# Number of cameras: 2
1 SIMPLE_PINHOLE 3072 2304 2559.81 1536 1152
2 SIMPLE_RADIAL 3072 2304 2559.69 1536 1152 -0.0218531
"""
COLMAP_IMAGES = """# Image list with two lines of data per image:
#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME
#   POINTS2D[] as (X, Y, POINT3D_ID)
# Number of images: 2, mean observations per image: 2
1 1 0 0 0 -10 20 30 1 P1180141.JPG
2362.39 248.498 7 1784.7 268.254 -1
2 0 1 0 0 5 6 7 2 P1180142.JPG

"""
COLMAP_POINTS = """# 3D point list with one line of data per point:
#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)
# Number of points: 1, mean track length: 1
7 1.67241 0.292931 0.609726 115 121 122 1.33927 1 0
"""


def test_colmap_sample_known_values(tmp_path):
    for name, text in zip(colmap.COLMAP_FILES, (COLMAP_CAMERAS, COLMAP_IMAGES, COLMAP_POINTS), strict=True):
        _write(tmp_path / name, text)
    m = colmap.read_colmap(tmp_path / "images.txt")
    c1, c2 = m.cameras["1"], m.cameras["2"]
    assert c1.focal_px == pytest.approx(2559.81, rel=1e-13)
    assert_allclose(c1.principal_point_px, [1535.5, 1151.5], atol=1e-9)  # COLMAP's corner origin -> our centres
    assert c2.distortion["k1"] == -0.0218531
    a, b = m.poses
    assert a.camera == "1" and b.camera == "2" and b.image == "P1180142.JPG"
    assert_allclose(a.rotation, FLIP, atol=1e-15)  # identity R_cw: camera looks along +z with y down
    assert_allclose(a.position, [10.0, -20.0, -30.0], atol=1e-12)  # C = -R_cw^T t
    assert_allclose(b.rotation, np.diag([1.0, -1.0, -1.0]) @ FLIP, atol=1e-15)  # 180 deg about x
    assert_allclose(b.position, [-5.0, 6.0, 7.0], atol=1e-12)
    assert m.point_ids == ("7",) and m.tracks is not None
    assert_allclose(m.tracks.obs_pixel, [[2361.89, 247.998]], atol=1e-12)
    assert tuple(m.colors[0]) == (115, 121, 122) and m.errors[0] == 1.33927


def test_colmap_through_pycolmap(tmp_path):
    pycolmap = pytest.importorskip("pycolmap")
    cams, poses, tracks, pts = _block()
    (tmp_path / "ours").mkdir()
    colmap.write_colmap(tmp_path / "ours", cams, poses, points=pts, tracks=tracks)
    rec = pycolmap.Reconstruction(str(tmp_path / "ours"))
    assert rec.num_images() == len(poses) and rec.num_points3D() == len(pts)
    by_name = {im.name: im for im in rec.images.values()}
    for p in poses:
        im = by_name[p.image]
        assert_allclose(im.projection_center(), p.position, rtol=0, atol=_ulps(p))
        assert_allclose(im.cam_from_world().rotation.matrix(), FLIP @ p.rotation.T, atol=1e-15)
        cam = rec.cameras[im.camera_id]
        K = cams[p.camera].K
        assert_allclose(cam.calibration_matrix(), K + [[0, 0, 0.5], [0, 0, 0.5], [0, 0, 0]], rtol=1e-15)
    (tmp_path / "theirs").mkdir()
    rec.write_text(str(tmp_path / "theirs"))  # a model as pycolmap writes it
    m = colmap.read_colmap(tmp_path / "theirs")
    got = {p.image: p for p in m.poses}
    for p in poses:
        assert_allclose(got[p.image].position, p.position, rtol=0, atol=_ulps(p))
        assert_allclose(got[p.image].rotation, p.rotation, atol=1e-15)
    assert m.tracks is not None and m.tracks.n_obs == tracks.n_obs


@pytest.mark.parametrize("file, text, match", [
    ("cameras.txt", "1 OPENCV_FISHEYE 640 480 500 500 320 240 0 0 0 0\n",
     r"line 1: camera model 'OPENCV_FISHEYE' is not in the frame camera model"),
    ("cameras.txt", "1 WEIRD 640 480 500 320 240\n", r"unknown camera model 'WEIRD'"),
    ("cameras.txt", "1 PINHOLE 640 480 500 320 240\n", r"PINHOLE takes 4 parameters"),
    ("cameras.txt", "1 SIMPLE_PINHOLE 640 480 5x0 320 240\n", r"SIMPLE_PINHOLE parameter 'f' is not a number: '5x0'"),
    ("cameras.txt", "1 FULL_OPENCV 640 480 500 500 320 240 0 0 0 0 0 0.1 0 0\n", r"FULL_OPENCV k4 = 0.1"),
    ("images.txt", "1 1 0 0 0 0 0 0 9 a.jpg\n\n", r"names CAMERA_ID 9, which cameras.txt lacks"),
    ("images.txt", "1 2 0 0 0 0 0 0 1 a.jpg\n\n", r"is not a unit quaternion"),
    ("images.txt", "1 1 0 0 0 0 0 0 1\n\n", r"expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME"),
    ("images.txt", "1 1 0 0 0 0 0 0 1 a.jpg\n10 20\n", r"POINTS2D must be triples"),
    ("points3D.txt", "1 0 0 0 1 2 3 0.5 4 0\n", r"track names IMAGE_ID 4, which images.txt lacks"),
    ("points3D.txt", "1 0 0 0 1 2 3 0.5 1 5\n", r"POINT2D_IDX 5 of image 'a.jpg', which has 1 2D points"),
    ("points3D.txt", "1 0 0 0 300 2 3 0.5\n", r"colour \[300, 2, 3\] is not 0..255"),
])
def test_colmap_bad_input(tmp_path, file, text, match):
    good = {"cameras.txt": "1 SIMPLE_PINHOLE 640 480 500 320 240\n", "images.txt": "1 1 0 0 0 0 0 0 1 a.jpg\n1 2 -1\n",
            "points3D.txt": ""}
    good[file] = text
    for name, body in good.items():
        _write(tmp_path / name, body)
    with pytest.raises(errors.InvalidInputError, match=match) as e:
        colmap.read_colmap(tmp_path)
    assert file in str(e.value) and "\n" not in str(e.value)


def test_colmap_refusals(tmp_path):
    _write(tmp_path / "cameras.bin", "")
    with pytest.raises(errors.InvalidInputError, match="binary COLMAP model.*model_converter"):
        colmap.read_colmap(tmp_path)
    with pytest.raises(errors.InvalidInputError, match="is not a COLMAP text model"):
        colmap.read_colmap(_write(tmp_path / "x.json", "{}"))
    cam = {"c": Camera.from_dict({"fx_px": 500.0, "fy_px": 500.0, "skew_px": 1.5, "principal_point_px": [3, 2],
                                  "width": 8, "height": 6})}
    pose = Pose("a b.jpg", "c", [0, 0, 0], np.eye(3))
    with pytest.raises(errors.InvalidInputError, match="has white space"):
        colmap.colmap_texts({"c": Camera.from_dict({"focal_length_px": 5.0, "principal_point_px": [3, 2], "width": 8,
                                                    "height": 6})}, [pose])
    with pytest.raises(errors.InvalidInputError, match="skew 1.5 px"):
        colmap.colmap_texts(cam, [Pose("a.jpg", "c", [0, 0, 0], np.eye(3))])
    with pytest.raises(errors.InvalidInputError, match="names camera 'x'"):
        colmap.colmap_texts(cam, [Pose("a.jpg", "x", [0, 0, 0], np.eye(3))])


# ------------------------------------------------------------------ ODM gcp_list.txt and geo.txt
GCP_LIST = """+proj=utm +zone=10 +ellps=WGS84 +datum=WGS84 +units=m +no_defs
544256.7 5320919.9 5 3044 2622 IMG_0525.jpg
544157.7 5320899.2 5 4193 1552 IMG_0585.jpg
544256.7 5320919.9 5 1001.5 2000.25 IMG_0585.jpg
544033.4 5320876.0 NaN 1606 2763 IMG_0690.jpg
"""


def test_odm_gcp_list_known_values(tmp_path):
    g = odm.read_odm_gcps(_write(tmp_path / "gcp_list.txt", GCP_LIST))
    assert g.crs == g.file_crs and pyproj.CRS(g.crs).utm_zone == "10N"
    assert g.ids == ("gcp1", "gcp2", "gcp3")  # unnamed: one point per coordinate triple, as ODM groups them
    assert_array_equal(g.xyz[:2], [[544256.7, 5320919.9, 5.0], [544157.7, 5320899.2, 5.0]])
    assert math.isnan(g.xyz[2, 2])
    assert g.meas_id == ("gcp1", "gcp2", "gcp1", "gcp3") and g.images == ("IMG_0525.jpg", "IMG_0585.jpg",
                                                                           "IMG_0690.jpg")
    assert_array_equal(g.meas_pixel[2], [1001.5, 2000.25])  # OpenSfM's pixel centres are ours: unchanged
    t = g.gcp_table("IMG_0585.jpg")
    assert t.ids == ("gcp2", "gcp1") and t.crs == g.crs
    assert_array_equal(t.pixel, [[4193.0, 1552.0], [1001.5, 2000.25]])
    assert_array_equal(t.z, [5.0, 5.0])
    c = g.control_table()
    assert c.kind == ("full", "full", "plan") and c.crs == g.crs and len(c.meas_id) == 4
    assert odm.detect_odm_gcps(tmp_path / "gcp_list.txt") and not odm.detect_odm_geo(tmp_path / "gcp_list.txt")


def test_odm_gcp_list_round_trip_through_lonlat(tmp_path):
    """Ours -> an EPSG:4326 gcp_list.txt (lon lat order, named points) -> ours, in the UTM zone ODM picks."""
    utm = "EPSG:32734"
    xyz = np.array([[301000.25, 6270000.5, 101.25], [301500.0, 6270400.0, 99.5]])
    lonlat = transform_xyz(utm, "EPSG:4326", xyz).tolist()
    lines = ["EPSG:4326"] + [f"{lo!r} {la!r} {h!r} {10.5 + i} {20.25 + i} img_{i}.tif gcp{i}_name extra"
                             for i, (lo, la, h) in enumerate(lonlat)]
    g = odm.read_odm_gcps(_write(tmp_path / "gcp_list.txt", "\n".join(lines) + "\n"))
    assert g.crs == utm and g.ids == ("gcp0_name", "gcp1_name")
    assert_allclose(g.xyz, xyz, rtol=0, atol=1e-6)
    assert_allclose(odm.read_odm_gcps(tmp_path / "gcp_list.txt", crs=utm).xyz, xyz, atol=1e-6)
    w = odm.read_odm_gcps(_write(tmp_path / "utm.txt", GCP_LIST.replace(GCP_LIST.splitlines()[0], "WGS84 UTM 10N")))
    assert w.crs == "EPSG:32610"


@pytest.mark.parametrize("text, err, match", [
    ("UTM 10N\n1 2 3 4 5 a.jpg\n", errors.CRSError, r"line 1: unknown CRS header 'UTM 10N'"),
    ("EPSG:99999999\n1 2 3 4 5 a.jpg\n", errors.CRSError, r"line 1: unknown CRS 'EPSG:99999999'"),
    ("EPSG:32610\n1 2 3 4 5\n", errors.InvalidInputError, r"line 2: expected geo_x geo_y geo_z im_x im_y image_name"),
    ("EPSG:32610\n1 2 3 4 five a.jpg\n", errors.InvalidInputError, r"line 2: im_y is not a number: 'five'"),
    ("EPSG:32610\n1 2 3 4 5 a.jpg g1\n1 2 4 4 5 b.jpg g1\n", errors.InvalidInputError,
     r"line 3: GCP 'g1' has coordinates \[1.0, 2.0, 4.0\] here and \[1.0, 2.0, 3.0\] on line 2"),
    ("EPSG:32610\n1 2 3 4 5 a.jpg\n1 2 3 6 7 a.jpg\n", errors.InvalidInputError,
     r"line 3: GCP 'gcp1' is measured twice in image 'a.jpg'"),
    ("EPSG:32610\n", errors.InvalidInputError, "no GCP lines"),
    ("", errors.InvalidInputError, "is empty"),
])
def test_odm_gcp_list_bad_input(tmp_path, text, err, match):
    with pytest.raises(err, match=match) as e:
        odm.read_odm_gcps(_write(tmp_path / "gcp_list.txt", text))
    assert "gcp_list.txt" in str(e.value) and "\n" not in str(e.value)


GEO_TXT = """EPSG:4326
DJI_0028.JPG    -91.9942096111111   46.84252125 198.609
DJI_0032.JPG    -91.9938293055556   46.8424584444444    198.609 12.5 -0.5 1.0 0.02 0.05 label-b
DJI_0040.JPG    -91.9938 46.8424
"""


def test_odm_geo_known_values(tmp_path):
    g = odm.read_odm_geo(_write(tmp_path / "geo.txt", GEO_TXT))
    assert g.crs == "EPSG:32615" and g.file_crs == "EPSG:4326"  # the UTM zone of the first image, as ODM
    expect = pyproj.Transformer.from_crs("EPSG:4326", "EPSG:32615", always_xy=True).transform(
        -91.9942096111111, 46.84252125)
    assert_allclose(g.position[0, :2], expect, atol=1e-6)
    assert g.position[0, 2] == 198.609 and math.isnan(g.position[2, 2])
    assert_allclose(g.ypr_rad[1], np.radians([12.5, -0.5, 1.0]))
    assert np.isnan(g.ypr_rad[0]).all()
    assert_array_equal(g.sigma_m[1], [0.02, 0.02, 0.05])
    assert g.extras == ("", "label-b", "")
    assert odm.detect_odm_geo(tmp_path / "geo.txt") and not odm.detect_odm_gcps(tmp_path / "geo.txt")
    with pytest.raises(errors.InvalidInputError, match=r"without height.*DJI_0040.JPG"):
        g.gnss(default_sigma_m=1.0)
    two = odm.read_odm_geo(_write(tmp_path / "geo2.txt", "\n".join(GEO_TXT.splitlines()[:3]) + "\n"))
    with pytest.raises(errors.InvalidInputError, match=r"no accuracy for \['DJI_0028.JPG'\]"):
        two.gnss()
    obs = two.gnss(default_sigma_m=3.0)
    assert_array_equal(obs.sigma_m, [[3.0, 3.0, 3.0], [0.02, 0.02, 0.05]])
    assert obs.images == ("DJI_0028.JPG", "DJI_0032.JPG")


@pytest.mark.parametrize("text, match", [
    ("EPSG:4326\nDJI.JPG -91.9\n", r"line 2: expected image_name geo_x geo_y"),
    ("EPSG:4326\nDJI.JPG -91.9 4x.8\n", r"line 2: geo_y is not a number: '4x.8'"),
    ("EPSG:4326\nDJI.JPG -91.9 46.8 100 0 0 0 -1 2\n", r"line 2: accuracies must be > 0; got -1.0, 2.0"),
    ("EPSG:4326\nA.JPG -91.9 46.8\nA.JPG -91.9 46.8\n", r"line 3: image 'A.JPG' is listed twice"),
])
def test_odm_geo_bad_input(tmp_path, text, match):
    with pytest.raises(errors.InvalidInputError, match=match) as e:
        odm.read_odm_geo(_write(tmp_path / "geo.txt", text))
    assert "geo.txt" in str(e.value)


# ------------------------------------------------------------------ Metashape XML
WGS84_WKT = pyproj.CRS("EPSG:4326").to_wkt("WKT1_GDAL")
UTM = "EPSG:32734"
W, H = 5280, 3956
CAL = {"f": 3705.4728792737214, "cx": 11.6738523909, "cy": -27.7497969199, "k1": -0.0919367147,
       "k2": -0.0762807468, "k3": 0.1162639394, "p1": -0.0003134847, "p2": 0.0001164035}


def _metashape_pixel(Xc: np.ndarray, cal: dict) -> np.ndarray:
    """Metashape's frame camera projection (its manual's appendix): corner origin, P1/P2 as Metashape has them."""
    x, y = Xc[0] / Xc[2], Xc[1] / Xc[2]
    r2 = x * x + y * y
    rad = 1 + cal["k1"] * r2 + cal["k2"] * r2 ** 2 + cal["k3"] * r2 ** 3
    xd = x * rad + cal["p1"] * (r2 + 2 * x * x) + 2 * cal["p2"] * x * y
    yd = y * rad + cal["p2"] * (r2 + 2 * y * y) + 2 * cal["p1"] * x * y
    b1, b2 = cal.get("b1", 0.0), cal.get("b2", 0.0)
    return np.array([W * 0.5 + cal["cx"] + xd * (cal["f"] + b1) + yd * b2, H * 0.5 + cal["cy"] + yd * cal["f"]])


def _metashape_xml(local: bool = False, components: bool = False, cal: dict | None = None) -> tuple[str, dict]:
    """A cameras + markers XML of two aligned cameras, one unaligned, two markers (one reference, one tie)."""
    cal = dict(CAL if cal is None else cal)
    rng = np.random.default_rng(7)
    Rc = matrix_from_angles(*rng.uniform(-np.pi, np.pi, 3))
    s = 12.354192447331316
    truth = {"poses": {"DJI_0001.JPG": ([301000.0, 6270000.0, 850.0], matrix_from_angles(0.02, -0.01, 2.9)),
                       "DJI_0002.JPG": ([301120.0, 6270010.0, 851.0], matrix_from_angles(-0.015, 0.02, 2.95))},
             "marker": [301060.0, 6270100.0, 120.0]}
    if local:
        T = np.array([100.0, -50.0, 20.0])

        def to_world(p):  # local frame: the chunk transform leads straight into it
            return np.asarray(p, float)

        ref_text = 'LOCAL_CS["Local Coordinates (m)",LOCAL_DATUM["Local Datum",0],UNIT["metre",1]]'
        world_R = {k: v[1] @ FLIP for k, v in truth["poses"].items()}
        marker_ref = truth["marker"]
    else:
        lon0, lat0, _ = transform_xyz(UTM, "EPSG:4979", [truth["poses"]["DJI_0001.JPG"][0]])[0]
        T = transform_xyz("EPSG:4979", "EPSG:4978", [[lon0, lat0, 0.0]])[0]

        def to_world(p):
            return transform_xyz(UTM, "EPSG:4978", [p])[0]

        ref_text = WGS84_WKT
        world_R = {}
        for k, (c, R) in truth["poses"].items():
            lon, lat, _ = transform_xyz(UTM, "EPSG:4979", [c])[0]
            world_R[k] = enu_rotation(lon, lat).T @ grid_from_enu(UTM, lon, lat).T @ R @ FLIP
        marker_ref = transform_xyz(UTM, "EPSG:4979", [truth["marker"]])[0].tolist()

    def internal(X):
        return Rc.T @ (np.asarray(X) - T) / s

    cams_xml, locs = [], []
    for i, (k, (c, _)) in enumerate(truth["poses"].items()):
        M = np.eye(4)
        M[:3, :3] = Rc.T @ world_R[k]
        M[:3, 3] = internal(to_world(c))
        comp = ' component_id="0"' if components else ""
        cams_xml.append(f'<camera id="{i}" sensor_id="0"{comp} label="{k}"><transform>'
                        f'{" ".join(repr(float(v)) for v in M.ravel())}</transform>'
                        f'<orientation>1</orientation></camera>')
        Xc = np.linalg.inv(M) @ np.append(internal(to_world(truth["marker"])), 1.0)
        u, v = (float(c) for c in _metashape_pixel(Xc[:3], cal))
        locs.append(f'<location camera_id="{i}" pinned="true" x="{u!r}" y="{v!r}"/>')
        truth.setdefault("pixels", {})[k] = (u, v)
    transform = (f'<transform><rotation locked="true">{" ".join(repr(float(v)) for v in Rc.ravel())}</rotation>'
                 f'<translation locked="true">{" ".join(repr(float(v)) for v in T)}</translation>'
                 f'<scale locked="true">{s!r}</scale></transform>')
    cal_xml = "".join(f"<{k}>{v!r}</{k}>" for k, v in cal.items())
    xml = f"""<?xml version="1.0" encoding="UTF-8"?>
<document version="2.0.0">
  <chunk label="Chunk 1" enabled="true">
    <sensors next_id="1">
      <sensor id="0" label="M3M (12.29mm)" type="frame">
        <resolution width="{W}" height="{H}"/>
        <property name="pixel_width" value="0.00335820"/>
        <calibration type="frame" class="initial"><resolution width="{W}" height="{H}"/><f>3600</f></calibration>
        <calibration type="frame" class="adjusted"><resolution width="{W}" height="{H}"/>{cal_xml}</calibration>
      </sensor>
    </sensors>
    {f'<components next_id="1" active_id="0"><component id="0" label="Component 1">{transform}</component></components>'
     if components else ""}
    <cameras next_id="3" next_group_id="1">
      <group id="0" label="Group 1" type="folder">{"".join(cams_xml)}</group>
      <camera id="2" sensor_id="0" label="DJI_0003.JPG"><orientation>1</orientation></camera>
    </cameras>
    <markers next_id="2">
      <marker id="0" label="point 1" reference="true">
        <reference x="{marker_ref[0]!r}" y="{marker_ref[1]!r}" z="{marker_ref[2]!r}" enabled="true"/>
      </marker>
      <marker id="1" label="tie 1"/>
    </markers>
    <frames next_id="1"><frame id="0"><markers>
      <marker marker_id="0">{"".join(locs)}</marker>
      <marker marker_id="1"><location camera_id="0" pinned="true" x="100.5" y="200.5"/></marker>
    </markers></frame></frames>
    <reference>{ref_text}</reference>
    {"" if components else transform}
  </chunk>
</document>
"""
    return xml, truth


@pytest.mark.parametrize("components", [False, True])
def test_metashape_georeferenced_chunk(tmp_path, components):
    xml, truth = _metashape_xml(components=components)
    p = _write(tmp_path / "cameras.xml", xml)
    assert metashape.detect_metashape(p)
    doc = metashape.read_metashape(p, crs=UTM)
    assert doc.crs == UTM and doc.reference_crs == "EPSG:4326"
    assert doc.unaligned == ("DJI_0003.JPG",) and doc.sensor_labels == {"0": "M3M (12.29mm)"}
    cam = doc.cameras["0"]
    assert cam.focal_px == pytest.approx(CAL["f"], rel=1e-14)
    assert_allclose(cam.principal_point_px, [(W - 1) / 2 + CAL["cx"], (H - 1) / 2 + CAL["cy"]], atol=1e-9)
    assert cam.distortion == {"k1": CAL["k1"], "k2": CAL["k2"], "k3": CAL["k3"], "p1": CAL["p2"], "p2": CAL["p1"]}
    for pose in doc.poses:
        c, R = truth["poses"][pose.image]
        assert pose.camera == "0"
        assert_allclose(pose.position, c, rtol=0, atol=1e-6)
        assert_allclose(pose.rotation, R, atol=1e-9)
    assert doc.marker_ids == ("point 1", "tie 1")
    assert_allclose(doc.marker_xyz[0], truth["marker"], atol=1e-6)
    assert np.isnan(doc.marker_xyz[1]).all()
    ctl = doc.control_table()
    assert ctl.kind == ("full", "tie") and ctl.crs == UTM
    t = doc.gcp_table("DJI_0002.JPG")
    assert t.ids == ("point 1",)
    assert_allclose(t.pixel[0], np.array(truth["pixels"]["DJI_0002.JPG"]) - 0.5, atol=1e-9)
    auto = metashape.read_metashape(p)  # no crs: the UTM zone of the cameras
    assert auto.crs == UTM


def test_metashape_local_chunk_reprojects_markers_exactly(tmp_path):
    """In a local frame the conversion is rigid: our camera and pose put each marker on its measured pixel."""
    xml, truth = _metashape_xml(local=True)
    doc = metashape.read_metashape(_write(tmp_path / "cameras.xml", xml))
    assert doc.crs is None and doc.reference_crs is None and "local" in doc.frame
    for pose in doc.poses:
        c, R = truth["poses"][pose.image]
        assert_allclose(pose.position, c, atol=1e-9)
        assert_allclose(pose.rotation, R, atol=1e-12)
        px = project_pixel(doc.cameras[pose.camera], pose, [truth["marker"]])[0]
        assert_allclose(px, np.array(truth["pixels"][pose.image]) - 0.5, atol=1e-6)
    with pytest.raises(errors.CRSError, match="local coordinate system"):
        metashape.read_metashape(tmp_path / "cameras.xml", crs=UTM)


def test_metashape_affinity_and_skew(tmp_path):
    cal = {**CAL, "b1": 0.5262024073, "b2": -0.3058334293}
    xml, truth = _metashape_xml(local=True, cal=cal)
    doc = metashape.read_metashape(_write(tmp_path / "cameras.xml", xml))
    K = doc.cameras["0"].K
    assert_allclose([K[0, 0], K[1, 1], K[0, 1]], [cal["f"] + cal["b1"], cal["f"], cal["b2"]], rtol=1e-12)
    for pose in doc.poses:
        px = project_pixel(doc.cameras[pose.camera], pose, [truth["marker"]])[0]
        assert_allclose(px, np.array(truth["pixels"][pose.image]) - 0.5, atol=1e-6)


@pytest.mark.parametrize("edit, err, match", [
    (lambda x: x.replace('type="frame">', 'type="fisheye">', 1), errors.InvalidInputError,
     r"sensor 0 \('M3M \(12.29mm\)'\) has type 'fisheye'"),
    (lambda x: x.replace("<k3>", "<k4>0.5</k4><k3>"), errors.InvalidInputError, r"has \{'k4': 0.5\}"),
    (lambda x: x.replace("<f>3705", "<f>x3705"), errors.InvalidInputError, r"calibration \(adjusted\): `f` is not a "
                                                                           r"number: 'x3705"),
    (lambda x: x.replace('<transform>', '<transform>1 2 ', 1), errors.InvalidInputError, r"`transform` must hold 16"),
    (lambda x: x.replace('sensor_id="0" label="DJI_0001', 'sensor_id="5" label="DJI_0001'), errors.InvalidInputError,
     r"camera 0 \('DJI_0001.JPG'\) is aligned but its sensor '5' has no calibration"),
    (lambda x: x.replace('camera_id="0" pinned="true" x="100.5"', 'camera_id="9" pinned="true" x="100.5"'),
     errors.InvalidInputError, r"marker 'tie 1' is measured in camera_id '9'"),
    (lambda x: x.replace("<document", "<doc").replace("</document>", "</doc>"), errors.InvalidInputError,
     "not a Metashape XML export"),
    (lambda x: x[:200], errors.InvalidInputError, "is not valid XML"),
    (lambda x: x.replace(WGS84_WKT, 'GEOGCS["nonsense"]'), errors.CRSError, r"`reference`"),
])
def test_metashape_bad_input(tmp_path, edit, err, match):
    xml, _ = _metashape_xml()
    with pytest.raises(err, match=match) as e:
        metashape.read_metashape(_write(tmp_path / "cameras.xml", edit(xml)))
    assert "cameras.xml" in str(e.value) and "\n" not in str(e.value)
