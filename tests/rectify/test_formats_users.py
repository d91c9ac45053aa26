"""Users' files (issue 29), image side: orthority, OpenCV calibration files, STAC Items; the map grid frame.

Samples are written here in the tools' documented layouts with our own values (no file of the tools
is copied): orthority's interior/exterior/CSV/GCP layouts from its documentation
(docs/file_formats/*.rst, orthority is AGPL-3.0), OpenCV's ``cv::FileStorage`` calibration layout
(the calibration sample's output keys, OpenCV is Apache-2.0) and the ROS ``camera_info`` YAML
layout (BSD). orthority's own NGI files are read from ../shared/data (skipped when absent).
"""

from __future__ import annotations

import datetime as dt
import hashlib
import json
import math
from pathlib import Path

import numpy as np
import pyproj
import pystac
import pytest
import rasterio
from numpy.testing import assert_allclose, assert_array_equal
from rasterio.control import GroundControlPoint

from rectify import errors
from rectify.formats import opencv, orthority, stac
from rectify.formats.gcps import read_gcps_embedded
from rectify.geometry.camera import Camera
from rectify.geometry.crs import same_crs, transform_xyz
from rectify.geometry.mapframe import grid_from_enu, true_north_azimuth
from rectify.geometry.points import GcpTable
from rectify.geometry.rotation import angles_from_matrix, matrix_from_angles, rot_x, rot_y, rot_z

UTM34S = "EPSG:32734"
LO25 = "+proj=tmerc +lat_0=0 +lon_0=25 +k=1 +x_0=0 +y_0=0 +datum=WGS84 +units=m +no_defs"


def _write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


# ------------------------------------------------------------------ the map grid frame
@pytest.mark.parametrize("lon, lat", [(21.0, -33.0), (23.7, -33.7), (18.2, -29.0), (22.5, 10.0)])
def test_true_north_azimuth_is_pyprojs_meridian_convergence(lon, lat):
    crs = "EPSG:32734" if lat < 0 else "EPSG:32634"
    conv = pyproj.Proj(crs).get_factors(lon, lat).meridian_convergence  # true north -> grid north, clockwise
    assert math.degrees(true_north_azimuth(crs, lon, lat)) == pytest.approx(-conv, abs=1e-7)
    R = grid_from_enu(crs, lon, lat)
    assert_allclose(R @ R.T, np.eye(3), atol=1e-15)
    assert_allclose(R[2], [0, 0, 1])


def test_true_north_azimuth_refuses_bad_places():
    with pytest.raises(errors.CRSError, match="projected CRS"):
        true_north_azimuth("EPSG:4326", 21.0, 30.0)
    with pytest.raises(errors.InvalidInputError, match="poles"):
        true_north_azimuth("EPSG:32634", 21.0, 90.0)


# ------------------------------------------------------------------ orthority: interior parameters
INT_PARAM = """\
# orthority interior parameters, in the layout of orthority's documentation
Aerial camera:
    type: pinhole
    im_size: [640, 1152]
    focal_len: 120.                 # mm
    sensor_size: [92.16, 165.888]   # mm
    cx: -0.01
    cy: 0.02
Drone camera:
    type: brown
    im_size: [400, 300]
    focal_len: 0.8333               # normalised by the image width
    cx: -0.01
    cy: 0.02
    k1: -0.25
    k2: 0.2
    p1: 0.01
    p2: 0.005
    k3: -0.1
Full model:
    type: opencv
    im_size: [400, 300]
    focal_len: [310.0, 310.0]
    sensor_size: [400, 300]         # pixels: focal_len in pixels
    k1: 0.1
    k4: 0.0
    s1: 0.0
"""


def test_int_param_known_values(tmp_path):
    cams = orthority.read_int_param(_write(tmp_path / "int_param.yaml", INT_PARAM))
    assert list(cams) == ["Aerial camera", "Drone camera", "Full model"]
    a = cams["Aerial camera"]
    assert not a.pixel_camera
    assert a.focal_length_mm == 120.0 and a.pixel_size_mm == pytest.approx(0.144, rel=1e-15)
    # principal point: (w - 1)/2 + cx max(w, h), (h - 1)/2 + cy max(w, h) px
    assert_allclose(a.principal_point_px, [319.5 - 0.01 * 1152, 575.5 + 0.02 * 1152], atol=1e-9)
    d = cams["Drone camera"]
    assert d.pixel_camera
    assert d.focal_px == pytest.approx(0.8333 * 400, rel=1e-12)  # orthority multiplies by the width
    assert_allclose(d.principal_point_px, [199.5 - 4.0, 149.5 + 8.0], atol=1e-9)
    assert d.distortion == {"k1": -0.25, "k2": 0.2, "k3": -0.1, "p1": 0.01, "p2": 0.005}
    f = cams["Full model"]
    assert f.focal_px == pytest.approx(310.0, rel=1e-12) and f.distortion["k1"] == 0.1
    assert_allclose(f.principal_point_px, [199.5, 149.5], atol=1e-12)


def test_int_param_json_flat_and_legacy_forms(tmp_path):
    one = {"type": "pinhole", "im_size": [100, 80], "focal_len": 50.0, "sensor_size": [10.0, 8.0]}
    cams = orthority.read_int_param(_write(tmp_path / "c.json", json.dumps({"cam": one})))
    assert cams["cam"].focal_length_mm == 50.0 and cams["cam"].pixel_size_mm == pytest.approx(0.1)
    flat = orthority.read_int_param(_write(tmp_path / "flat.yaml", json.dumps({**one, "name": "solo"})))
    assert list(flat) == ["solo"]
    legacy = orthority.read_int_param(_write(tmp_path / "config.yaml", json.dumps({"camera": {**one, "name": "x"}})))
    assert list(legacy) == ["x"]


@pytest.mark.parametrize("cam", [
    Camera(focal_length_mm=120.0, pixel_size_mm=0.012, width=640, height=1152, principal_point_mm=(0.03, -0.05),
           distortion={"k1": 1e-5, "p2": 2e-6}),
    Camera.from_dict({"focal_length_px": 3000.5, "principal_point_px": [2011.25, 1499.75], "width": 4000,
                      "height": 3000, "distortion": {"k1": -0.1, "k2": 0.02, "k3": 0.001, "p1": 1e-4, "p2": -2e-4}}),
])
def test_int_param_round_trip(tmp_path, cam):
    p = orthority.write_int_param(tmp_path / "int_param.yaml", {"c": cam})
    back = orthority.read_int_param(p)["c"]
    assert back.pixel_camera == cam.pixel_camera
    assert_allclose(back.K, cam.K, rtol=1e-14, atol=1e-9)
    assert back.distortion == pytest.approx(cam.distortion, rel=1e-15)
    if not cam.pixel_camera:
        assert back.focal_length_mm == cam.focal_length_mm
        assert back.pixel_size_mm == pytest.approx(cam.pixel_size_mm, rel=1e-15)
    assert orthority.detect_int_param(p)


@pytest.mark.parametrize("body, match", [
    ("c: {type: fisheye, im_size: [4, 3], focal_len: 1.0}", r"'c'.*`type` 'fisheye' is not a frame camera"),
    ("c: {type: kannala, im_size: [4, 3], focal_len: 1.0}", r"unknown `type` 'kannala'"),
    ("c: {type: pinhole, focal_len: 1.0}", r"'c' lacks \['im_size'\]"),
    ("c: {type: pinhole, im_size: [4, 3], focal_len: big}", r"`focal_len` must be a finite number; got 'big'"),
    ("c: {type: pinhole, im_size: [4.5, 3], focal_len: 1.0}", r"`im_size` must be \[width, height\]"),
    ("c: {type: opencv, im_size: [4, 3], focal_len: 1.0, k4: 0.5}", r"`k4` = 0.5"),
    ("c: {type: pinhole, im_size: [4, 3], focal_len: 1.0, k1: 0.1}", r"unknown parameter\(s\) \['k1'\]"),
    ("c: {type: pinhole, im_size: [4, 3], focal_len: 1.0, sensor_size: [1, -2]}", r"`sensor_size` must be > 0"),
    ("[1, 2, 3]", "must be a mapping of camera id"),
    ("c: {type: [pinhole", "not valid YAML or JSON"),
])
def test_int_param_bad_input(tmp_path, body, match):
    p = _write(tmp_path / "bad.yaml", body)
    with pytest.raises(errors.InvalidInputError, match=match) as e:
        orthority.read_int_param(p)
    assert "bad.yaml" in str(e.value) and "\n" not in str(e.value)


def test_single_camera(tmp_path):
    cams = orthority.read_int_param(_write(tmp_path / "int_param.yaml", INT_PARAM))
    assert orthority.single_camera(cams, "x", "Drone camera") is cams["Drone camera"]
    with pytest.raises(errors.InvalidInputError, match=r"holds 3 cameras"):
        orthority.single_camera(cams, "int_param.yaml")
    with pytest.raises(errors.InvalidInputError, match=r"no camera 'nope'"):
        orthority.single_camera(cams, "int_param.yaml", "nope")


# ------------------------------------------------------------------ orthority: exterior parameters
def _exteriors() -> dict[str, dict]:
    return {"img_a": {"position": np.array([301234.567, 6270000.125, 1200.5]),
                      "rotation": matrix_from_angles(0.01, -0.02, 1.5), "camera": "Drone camera"},
            "img_b.tif": {"position": np.array([301434.5, 6270020.0, 1201.0]),
                          "rotation": matrix_from_angles(-0.015, 0.03, -1.6), "camera": None}}


def test_ext_param_round_trip(tmp_path):
    eo = _exteriors()
    p = orthority.write_ext_param(tmp_path / "ext_param.geojson", eo, UTM34S)
    doc = json.loads(p.read_text())
    assert doc["world_crs"] == UTM34S and doc["features"][0]["properties"]["filename"] == "img_a"
    lon, lat, h = doc["features"][0]["geometry"]["coordinates"]
    assert_allclose(transform_xyz("EPSG:4979", UTM34S, [[lon, lat, h]])[0], eo["img_a"]["position"], atol=1e-6)
    back = orthority.read_ext_param(p)
    assert orthority.detect_ext_param(p) and not orthority.detect_oty_gcps(p)
    for k, v in eo.items():
        assert_array_equal(back[k]["position"], v["position"])
        assert_allclose(back[k]["rotation"], v["rotation"], atol=1e-15)
        assert back[k]["crs"] == UTM34S and back[k]["camera"] == v["camera"]


def _ext_doc(**props) -> dict:
    p = {"filename": "a", "camera": None, "xyz": [1.0, 2.0, 3.0], "opk": [0.0, 0.0, 0.0], **props}
    return {"type": "FeatureCollection", "world_crs": UTM34S,
            "features": [{"type": "Feature", "properties": p, "geometry": {"type": "Point", "coordinates": [0, 0]}}]}


@pytest.mark.parametrize("doc, err, match", [
    ({**_ext_doc(), "world_crs": None}, errors.InvalidInputError, r"`world_crs` must be a CRS string"),
    ({k: v for k, v in _ext_doc().items() if k != "world_crs"}, errors.InvalidInputError, "lacks 'world_crs'"),
    ({**_ext_doc(), "world_crs": "EPSG:4326"}, errors.CRSError, "must be a projected CRS"),
    ({**_ext_doc(), "world_crs": "EPSG:99999999"}, errors.CRSError, r"`world_crs`: unknown CRS 'EPSG:99999999'"),
    (_ext_doc(xyz=[1.0, "2", 3.0]), errors.InvalidInputError, r"\('a'\): `xyz` must be a finite number; got '2'"),
    (_ext_doc(opk=[0.0, 0.0]), errors.InvalidInputError, r"`opk` must be a list of 3 numbers; got \[0.0, 0.0\]"),
    (_ext_doc(camera=3), errors.InvalidInputError, r"`camera` must be a string or null; got 3"),
    (_ext_doc(filename=""), errors.InvalidInputError, r"`filename` must be a non-empty string"),
    ({**_ext_doc(), "type": "Feature"}, errors.InvalidInputError, r"FeatureCollection.*got type 'Feature'"),
])
def test_ext_param_bad_input(tmp_path, doc, err, match):
    p = _write(tmp_path / "ext.geojson", json.dumps(doc))
    with pytest.raises(err, match=match) as e:
        orthority.read_ext_param(p)
    assert "ext.geojson" in str(e.value)


def test_ext_param_refuses_a_duplicate_filename(tmp_path):
    doc = _ext_doc()
    doc["features"] *= 2
    with pytest.raises(errors.InvalidInputError, match="filename 'a' appears twice"):
        orthority.read_ext_param(_write(tmp_path / "e.geojson", json.dumps(doc)))


# ------------------------------------------------------------------ orthority: CSV exterior parameters
@pytest.mark.parametrize("radians", [False, True])
def test_frame_csv_round_trip(tmp_path, radians):
    eo = _exteriors()
    p = orthority.write_frame_csv(tmp_path / "xyz_opk.csv", eo, crs=UTM34S, radians=radians)
    assert (tmp_path / "xyz_opk.prj").is_file() and orthority.detect_frame_csv(p)
    back = orthority.read_frame_csv(p, radians=radians)
    for k, v in eo.items():
        assert_array_equal(back[k]["position"], v["position"])
        assert_allclose(back[k]["rotation"], v["rotation"], atol=1e-15)
        assert same_crs(back[k]["crs"], UTM34S) and back[k]["camera"] == v["camera"]


def test_frame_csv_dialects_and_legacy_order(tmp_path):
    spaced = ("'filename' 'x' 'y' 'z' 'omega' 'phi' 'kappa' 'camera'\n"
              "'img 1' 292710.217 2731048.771 186.446 28.831 0.94 1.782 'dji fc6310r'\n")
    a = orthority.read_frame_csv(_write(tmp_path / "spaced.csv", spaced), crs="EPSG:32651")
    assert_allclose(a["img 1"]["position"], [292710.217, 2731048.771, 186.446])
    assert_allclose(angles_from_matrix(a["img 1"]["rotation"]), np.radians([28.831, 0.94, 1.782]), atol=1e-15)
    assert a["img 1"]["camera"] == "dji fc6310r"
    legacy = "img_2 292746.19 2731093.469 186.56 -2.728 -30.083 -93.729\n"
    b = orthority.read_frame_csv(_write(tmp_path / "legacy.txt", legacy))
    assert b["img_2"]["crs"] is None and b["img_2"]["camera"] is None
    assert_allclose(angles_from_matrix(b["img_2"]["rotation"]), np.radians([-2.728, -30.083, -93.729]), atol=1e-14)
    rad = "# angles=rad\n# crs=EPSG:32651\nfilename;x;y;z;omega;phi;kappa\nc;1;2;3;0.1;0.2;0.3\n"
    c = orthority.read_frame_csv(_write(tmp_path / "semi.csv", rad))
    assert_allclose(angles_from_matrix(c["c"]["rotation"]), [0.1, 0.2, 0.3], atol=1e-15)
    assert c["c"]["crs"] == "EPSG:32651"


def test_frame_csv_lla_rpy_at_and_off_the_central_meridian(tmp_path):
    """A nadir camera (roll = pitch = 0) heading yaw: kappa = -(yaw + a), a the grid azimuth of true north."""
    text = ("filename latitude longitude altitude roll pitch yaw\n"
            "on -33.5 21.0 1500.0 0.0 0.0 90.0\n"
            "off -33.5 23.2 1500.0 0.0 0.0 30.0\n")
    eo = orthority.read_frame_csv(_write(tmp_path / "lla_rpy.csv", text), crs=UTM34S)
    on, off = eo["on"], eo["off"]
    assert_allclose(on["position"], transform_xyz("EPSG:4979", UTM34S, [[21.0, -33.5, 1500.0]])[0], atol=1e-9)
    assert on["position"][2] == 1500.0  # ellipsoidal height kept in a 2D CRS
    assert_allclose(on["rotation"], rot_z(math.radians(-90.0)), atol=1e-12)
    a = true_north_azimuth(UTM34S, 23.2, -33.5)
    assert a > 0  # south of the equator, east of the central meridian: true north lies east of grid north
    assert_allclose(off["rotation"], rot_z(-(math.radians(30.0) + a)), atol=1e-12)
    auto = orthority.read_frame_csv(_write(tmp_path / "auto.csv", text))  # no CRS: the UTM zone of the positions
    assert auto["on"]["crs"] == UTM34S


def test_frame_csv_rpy_follows_pix4ds_definition(tmp_path):
    """Pitch and roll: C = G E_ned Rz(yaw) Ry(pitch) Rx(roll) B (Pix4D's conversion, orthority's reading)."""
    roll, pitch, yaw = 3.0, -7.0, 125.0
    text = f"# crs={UTM34S}\nfilename,x,y,z,roll,pitch,yaw\nimg,250000.0,6290000.0,900.0,{roll},{pitch},{yaw}\n"
    eo = orthority.read_frame_csv(_write(tmp_path / "xyz_rpy.csv", text))["img"]
    lon, lat, _ = transform_xyz(UTM34S, "EPSG:4979", [eo["position"]])[0]
    body = np.array([[0, 1, 0], [1, 0, 0], [0, 0, -1.0]])
    ned = np.array([[0, 1, 0], [1, 0, 0], [0, 0, -1.0]])
    r, p, y = np.radians([roll, pitch, yaw])
    expected = grid_from_enu(UTM34S, lon, lat) @ ned @ rot_z(y) @ rot_y(p) @ rot_x(r) @ body
    assert_allclose(eo["rotation"], expected, atol=1e-14)


def test_prj_contradicting_the_crs_line_is_refused(tmp_path):
    p = _write(tmp_path / "poses.csv", "# crs=EPSG:32734\nfilename,x,y,z,omega,phi,kappa\na,1,2,3,0,0,0\n")
    _write(tmp_path / "poses.prj", "EPSG:32735")
    with pytest.raises(errors.CRSError) as e:
        orthority.read_frame_csv(p)
    msg = str(e.value)
    assert "poses.prj" in msg and "EPSG:32735" in msg and "EPSG:32734" in msg and "contradicts" in msg
    _write(tmp_path / "poses.prj", pyproj.CRS("EPSG:32734").to_wkt())  # the same CRS as WKT: accepted
    assert orthority.read_frame_csv(p)["a"]["crs"] == "EPSG:32734"
    with pytest.raises(errors.CRSError, match="the `crs` argument"):
        orthority.read_frame_csv(p, crs="EPSG:32733")


@pytest.mark.parametrize("text, kw, err, match", [
    ("filename,x,y,z,omega,phi,kappa\na,1,2,three,0,0,0\n", {}, errors.InvalidInputError,
     r"line 2: column 'z' is not a number: 'three'"),
    ("filename,x,y,omega,phi,kappa\na,1,2,0,0,0\n", {}, errors.InvalidInputError, r"needs columns filename"),
    ("filename,x,y,z,omega,phi,kappa\na,1,2,3,0,0\n", {}, errors.InvalidInputError, r"line 2: 6 cells for 7 columns"),
    ("filename,x,y,z,omega,phi,kappa\na,1,2,3,0,0,0\na,1,2,3,0,0,0\n", {}, errors.InvalidInputError,
     r"duplicate filename\(s\) \['a'\]"),
    ("filename,latitude,longitude,altitude,omega,phi,kappa\na,-33,21,3,0,0,0\n", {}, errors.CRSError,
     r"\(lla_opk\) needs the world CRS"),
    ("filename,x,y,z,roll,pitch,yaw\na,1,2,3,0,0,0\n", {}, errors.CRSError, r"\(xyz_rpy\) needs the world CRS"),
    ("# angles=grad\nfilename,x,y,z,omega,phi,kappa\na,1,2,3,0,0,0\n", {}, errors.InvalidInputError,
     r"line 1: `angles` must be 'deg' or 'rad'; got 'grad'"),
    ("# angles=deg\nfilename,x,y,z,omega,phi,kappa\na,1,2,3,0,0,0\n", {"radians": True}, errors.InvalidInputError,
     r"'# angles=deg' contradicts radians=True"),
    ("filename,x,y,z,omega,phi,kappa\na,1,2,3,0,0,0\n", {"crs": "EPSG:4326"}, errors.CRSError,
     "must be a projected CRS"),
    ("filename,x,y,z,omega,phi,kappa\n", {}, errors.InvalidInputError, "a header but no rows"),
])
def test_frame_csv_bad_input(tmp_path, text, kw, err, match):
    with pytest.raises(err, match=match) as e:
        orthority.read_frame_csv(_write(tmp_path / "bad.csv", text), **kw)
    assert "\n" not in str(e.value)


# ------------------------------------------------------------------ orthority: GCPs
def test_oty_gcps_round_trip_and_known_values(tmp_path):
    t = GcpTable(("p1", "p2"), np.array([[821.3001696660183, 62.303697728645055], [10.0, 20.5]]),
                 np.array([[24.41948061951812, -33.65426900104435], [24.44, -33.649]]),
                 np.array([214.75143153141929, 208.5]), np.zeros(2, bool), "EPSG:4979")
    p = _write(tmp_path / "gcps.geojson", orthority.oty_gcps_text({"qb2.tif": t, "other.tif": t}))
    assert orthority.detect_oty_gcps(p) and not orthority.detect_ext_param(p)
    back = orthority.read_oty_gcps(p)
    assert sorted(back) == ["other.tif", "qb2.tif"]
    b = back["qb2.tif"]
    assert b.ids == ("p1", "p2") and b.crs == "EPSG:4979"
    assert_array_equal(b.pixel, t.pixel)  # orthority's ji are our pixel centres: unchanged
    assert_array_equal(b.target, t.target)
    assert_array_equal(b.z, t.z)


def test_oty_gcps_from_a_map_crs_are_written_in_wgs84(tmp_path):
    xyz = np.array([[301000.0, 6270000.0, 100.0]])
    t = GcpTable(("g",), np.array([[5.0, 6.0]]), xyz[:, :2], xyz[:, 2], np.zeros(1, bool), UTM34S)
    back = orthority.read_oty_gcps(_write(tmp_path / "g.geojson", orthority.oty_gcps_text({"a": t})))["a"]
    assert_allclose(transform_xyz("EPSG:4979", UTM34S, np.column_stack([back.target, back.z])), xyz, atol=1e-6)
    with pytest.raises(errors.InvalidInputError, match="need heights"):
        orthority.oty_gcps_text({"a": GcpTable(("g",), t.pixel, t.target, None, t.check, UTM34S)})


def _gcp_doc(props: dict, coords=(24.4, -33.6, 200.0)) -> dict:
    return {"type": "FeatureCollection", "features": [
        {"type": "Feature", "properties": props, "geometry": {"type": "Point", "coordinates": list(coords)}}]}


@pytest.mark.parametrize("doc, match", [
    (_gcp_doc({"filename": "a.tif"}), r"feature 0: lacks `ji`"),
    (_gcp_doc({"filename": "a.tif", "ji": ["1", 2]}), r"feature 0: `ji` must be a finite number; got '1'"),
    (_gcp_doc({"filename": "a.tif", "ji": [1, 2]}, (24.4, -33.6)), r"Point `coordinates` \[lon, lat, h\] must be"),
    (_gcp_doc({"ji": [1, 2]}), r"`filename` must be a non-empty string; got None"),
    ({"type": "FeatureCollection", "features": []}, r"`features` must be a non-empty list"),
])
def test_oty_gcps_bad_input(tmp_path, doc, match):
    with pytest.raises(errors.InvalidInputError, match=match) as e:
        orthority.read_oty_gcps(_write(tmp_path / "gcps.geojson", json.dumps(doc)))
    assert "gcps.geojson" in str(e.value)


def test_oty_gcps_refuse_an_id_twice_in_one_image(tmp_path):
    doc = _gcp_doc({"filename": "a.tif", "ji": [1, 2], "id": "x"})
    doc["features"] *= 2
    with pytest.raises(errors.InvalidInputError, match=r"GCP id\(s\) \['x'\] repeated in image 'a.tif'"):
        orthority.read_oty_gcps(_write(tmp_path / "g.geojson", json.dumps(doc)))


def test_embedded_gcps_with_orthoritys_pixel_centres(tmp_path):
    path = tmp_path / "gcps.tif"
    gcps = [GroundControlPoint(row=20.0, col=10.0, x=24.41, y=-33.65, z=210.0, id="a"),
            GroundControlPoint(row=300.5, col=400.25, x=24.45, y=-33.60, z=190.0, id="b")]
    with rasterio.open(path, "w", driver="GTiff", width=500, height=400, count=1, dtype="uint8") as ds:
        ds.gcps = (gcps, rasterio.crs.CRS.from_epsg(4979))
    centre = orthority.read_embedded_gcps_centre(path)
    assert centre.ids == ("1", "2") and centre.crs == "EPSG:4979"  # GeoTIFF tie points carry no ids
    assert_array_equal(centre.pixel, [[10.0, 20.0], [400.25, 300.5]])
    assert_array_equal(centre.z, [210.0, 190.0])
    corner = read_gcps_embedded(path)  # GDAL's corner reading of the same tags: half a pixel apart
    assert_allclose(corner.pixel, centre.pixel - 0.5)
    assert_array_equal(orthority.pixel_from_embedded(centre.pixel, "corner"), corner.pixel)


def test_embedded_gcps_centre_refuses_a_raster_without_gcps(tmp_path):
    path = tmp_path / "plain.tif"
    with rasterio.open(path, "w", driver="GTiff", width=4, height=4, count=1, dtype="uint8") as ds:
        ds.write(np.zeros((1, 4, 4), np.uint8))
    with pytest.raises(errors.InvalidInputError, match="plain.tif' carries no embedded GCPs"):
        orthority.read_embedded_gcps_centre(path)


def test_match_image():
    m = {"3324c_0182_RGB": 1, "b.tif": 2}
    assert orthority.match_image(m, "/data/3324c_0182_RGB.tif") == 1
    assert orthority.match_image(m, "b.tif") == 2 and orthority.match_image(m, "b.jpg") == 2
    with pytest.raises(errors.InvalidInputError, match="image 'c.tif' has no entry"):
        orthority.match_image(m, "c.tif")


# ------------------------------------------------------------------ orthority's own NGI files (shared data)
NGI_EO = {"3324c_2015_1004_05_0182_RGB": (-55094.504480, -3727407.037480, 5258.307930, -0.349216, 0.298484,
                                          -179.086702),
          "3324c_2015_1004_05_0184_RGB": (-57710.435280, -3727433.893020, 5256.764790, 0.269761, -0.281937,
                                          -179.027883)}


@pytest.mark.shared
def test_orthoritys_ngi_files(ngi_pair):
    d = ngi_pair
    if not (d / "orthority_int_param.yaml").is_file():
        pytest.skip("orthority's NGI files are not in the shared data")
    cam = orthority.single_camera(orthority.read_int_param(d / "orthority_int_param.yaml"), "int_param")
    ours = Camera(focal_length_mm=120.0, pixel_size_mm=0.144, width=640, height=1152)  # tests/stereo/test_block_ngi
    assert cam.focal_length_mm == 120.0 and cam.pixel_size_mm == pytest.approx(0.144, rel=1e-12)
    assert_allclose(cam.K, ours.K, rtol=1e-12)
    assert not cam.has_distortion
    geo = orthority.read_ext_param(d / "orthority_ext_param.geojson")
    csv = orthority.read_frame_csv(d / "orthority_xyz_opk.csv")
    assert sorted(geo) == sorted(csv) == sorted(NGI_EO)
    for name, v in NGI_EO.items():
        g, c = geo[name], csv[name]
        assert_allclose(g["position"], v[:3], atol=1e-9)
        assert_allclose(np.degrees(angles_from_matrix(g["rotation"])), v[3:], atol=1e-6)
        assert g["camera"] == "Integraph DMC"
        assert same_crs(g["crs"], LO25) and same_crs(c["crs"], LO25)  # world_crs WKT and the .prj PROJ string
        assert_allclose(c["position"], v[:3], atol=5e-4)  # the CSV has 3 decimals (mm, 0.001 deg)
        assert_allclose(c["rotation"], g["rotation"], atol=2e-5)


# ------------------------------------------------------------------ OpenCV calibration files
OPENCV_SAMPLE = """%YAML:1.0
---
calibration_time: "Tue 01 Jan 2019 00:00:00"
nr_of_frames: 14
image_width: 640
image_height: 480
board_width: 9
board_height: 6
square_size: 2.5e-02
flags: 0
camera_matrix: !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: [ 5.3591573396163199e+02, 0., 3.4228315473308373e+02, 0.,
       5.3591573396163199e+02, 2.3557082909788173e+02, 0., 0., 1. ]
distortion_coefficients: !!opencv-matrix
   rows: 5
   cols: 1
   dt: d
   data: [ -2.6637260909660682e-01, -3.8588898922304653e-02,
       1.7831947042852964e-03, -2.8122100441115472e-04,
       2.3839153080878486e-01 ]
avg_reprojection_error: 3.9259098975581364e-01
"""

ROS_SAMPLE = """image_width: 640
image_height: 480
camera_name: narrow_stereo
camera_matrix:
  rows: 3
  cols: 3
  data: [420.5, 0.0, 319.25, 0.0, 421.0, 241.5, 0.0, 0.0, 1.0]
distortion_model: plumb_bob
distortion_coefficients:
  rows: 1
  cols: 5
  data: [-0.3, 0.1, 0.001, -0.002, 0.0]
rectification_matrix:
  rows: 3
  cols: 3
  data: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
"""


def test_opencv_sample_known_values(tmp_path):
    cam = opencv.read_opencv_calibration(_write(tmp_path / "out_camera_data.yml", OPENCV_SAMPLE))
    assert (cam.width, cam.height) == (640, 480) and cam.pixel_camera
    assert cam.focal_px == 5.3591573396163199e02
    assert_allclose(cam.principal_point_px, [3.4228315473308373e02, 2.3557082909788173e02], rtol=1e-15)
    assert cam.distortion == {"k1": -2.6637260909660682e-01, "k2": -3.8588898922304653e-02,
                              "p1": 1.7831947042852964e-03, "p2": -2.8122100441115472e-04,
                              "k3": 2.3839153080878486e-01}
    ros = opencv.read_opencv_calibration(_write(tmp_path / "camera_info.yaml", ROS_SAMPLE))
    assert_allclose(ros.K, [[420.5, 0, 319.25], [0, 421.0, 241.5], [0, 0, 1]], rtol=1e-14)
    assert ros.distortion["p2"] == -0.002
    assert opencv.detect_opencv_calibration(tmp_path / "camera_info.yaml")


@pytest.mark.parametrize("suffix", [".yml", ".yaml", ".xml", ".json"])
def test_opencv_round_trip(tmp_path, suffix):
    cam = Camera.from_dict({"focal_length_px": 1234.5678901234567, "principal_point_px": [1023.75, 767.125],
                            "width": 2048, "height": 1536,
                            "distortion": {"k1": -0.123456789, "k2": 0.0123, "k3": -1e-4, "p1": 3e-4, "p2": -7e-5}})
    p = opencv.write_opencv_calibration(tmp_path / f"cal{suffix}", cam)
    back = opencv.read_opencv_calibration(p)
    assert_array_equal(back.K, cam.K)
    assert back.distortion == cam.distortion


@pytest.mark.parametrize("text, match", [
    ("%YAML:1.0\n---\nimage_width: 640\nimage_height: 480\n", "lacks `camera_matrix`"),
    ("%YAML:1.0\n---\nimage_width: 640\ncamera_matrix: !!opencv-matrix\n   rows: 2\n   cols: 2\n   dt: d\n"
     "   data: [1., 0., 0., 1.]\n", r"`camera_matrix` must be 3 x 3"),
    ("%YAML:1.0\n---\nimage_width: 640\nimage_height: 480\ncamera_matrix: !!opencv-matrix\n   rows: 3\n   cols: 3\n"
     "   dt: d\n   data: [500., 0., 320., 0., 500., 240., 0., 0., 1.]\ndistortion_coefficients: !!opencv-matrix\n"
     "   rows: 8\n   cols: 1\n   dt: d\n   data: [0., 0., 0., 0., 0., 0.5, 0., 0.]\n", r"nonzero \{'k4': 0.5\}"),
    ("%YAML:1.0\n---\nimage_width: 640\nimage_height: 480\ncamera_matrix: !!opencv-matrix\n   rows: 3\n   cols: 3\n"
     "   dt: d\n   data: [500., 0., 320., 0., 500., 240., 0., 0., 1.]\ndistortion_coefficients: !!opencv-matrix\n"
     "   rows: 3\n   cols: 1\n   dt: d\n   data: [0., 0., 0.]\n", r"4, 5, 8, 12 or 14 finite numbers"),
    ("%YAML:1.0\n---\nimage_width: wide\nimage_height: 480\ncamera_matrix: !!opencv-matrix\n   rows: 3\n   cols: 3\n"
     "   dt: d\n   data: [500., 0., 320., 0., 500., 240., 0., 0., 1.]\n", r"`image_width` must be a positive integer; "
                                                                          r"got 'wide'"),
    (ROS_SAMPLE.replace("plumb_bob", "equidistant"), r"`distortion_model` 'equidistant' \(fisheye\)"),
    (ROS_SAMPLE.replace("[420.5, 0.0, 319.25", "[420.5, 0.0, 'x'"), r"`camera_matrix` element 2 is not a number"),
    ("camera_matrix: [1, 2", "is not an OpenCV FileStorage file"),
])
def test_opencv_bad_input(tmp_path, text, match):
    with pytest.raises(errors.InvalidInputError, match=match) as e:
        opencv.read_opencv_calibration(_write(tmp_path / "bad.yml", text))
    assert "bad.yml" in str(e.value) and "\n" not in str(e.value)


# ------------------------------------------------------------------ STAC Items
def test_stac_item_of_an_orthophoto(tmp_path):
    (tmp_path / "out").mkdir()
    ortho = _write(tmp_path / "out" / "ortho.tif", "pixels")
    report = _write(tmp_path / "out" / "ortho_report.json", "{}")
    src = _write(tmp_path / "photo.tif", "raw photo")
    grid = stac.RasterGrid(UTM34S, (0.5, 0.0, 300000.0, 0.0, -0.5, 6270000.0), 400, 200)
    product = stac.StacProduct(
        "ortho", {"ortho": stac.StacAsset(ortho, ("data", "visual"), "Orthophoto"),
                  "report": stac.StacAsset(report, ("metadata",))},
        grid=grid, accuracy={"check_rmse_m": 0.42, "n_check": 5}, command="rectify ortho photo.tif -o out",
        options={"resolution_m": 0.5, "dem": Path("dem.tif"), "nodata": float("nan")}, inputs=[src])
    p = stac.write_stac_item(tmp_path / "out" / "ortho.stac.json", product)
    d = json.loads(p.read_text())
    assert d["type"] == "Feature" and d["id"] == "ortho" and "links" in d
    assert stac.PROCESSING_SCHEMA in d["stac_extensions"]
    assert any("projection" in s for s in d["stac_extensions"]) and any("/file/" in s for s in d["stac_extensions"])
    props = d["properties"]
    assert props.get("proj:code", f"EPSG:{props.get('proj:epsg')}") == UTM34S
    assert props["proj:shape"] == [200, 400] and props["proj:transform"][:6] == list(grid.transform)
    assert props["processing:software"]["rectify-stereo"]
    assert props["rectify:accuracy"] == {"check_rmse_m": 0.42, "n_check": 5}
    assert props["rectify:options"] == {"resolution_m": 0.5, "dem": "dem.tif", "nodata": None}
    assert props["rectify:inputs"][0]["file:checksum"] == stac.file_checksum(src)
    assert props["rectify:inputs"][0]["file:size"] == len("raw photo")
    assert props["rectify:datetime_source"] == "processing"
    a = d["assets"]["ortho"]
    assert a["href"] == "ortho.tif" and a["roles"] == ["data", "visual"] and a["title"] == "Orthophoto"
    assert a["type"].startswith("image/tiff") and a["file:size"] == len("pixels")
    assert a["file:checksum"] == "1220" + hashlib.sha256(b"pixels").hexdigest()
    # the footprint in WGS 84, counter-clockwise, around the grid's centre
    ring = np.array(d["geometry"]["coordinates"][0])
    x, y = ring[:-1, 0], ring[:-1, 1]
    assert np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y) > 0
    cx, cy = transform_xyz(UTM34S, "EPSG:4979", [[300100.0, 6269950.0, 0.0]])[0][:2]
    assert d["bbox"][0] < cx < d["bbox"][2] and d["bbox"][1] < cy < d["bbox"][3]
    item = pystac.Item.from_file(str(p))
    assert Path(item.assets["ortho"].get_absolute_href()) == ortho.resolve()


def test_stac_item_of_a_point_cloud_and_bad_products(tmp_path):
    las = _write(tmp_path / "points.las", "LASF")
    when = dt.datetime(2015, 10, 4, 9, 30)
    product = stac.StacProduct("points", {"points": stac.StacAsset(las)}, acquired=when,
                               footprint=(UTM34S, (300000.0, 6269000.0, 301000.0, 6270000.0)))
    d = json.loads(stac.stac_item_text(product, tmp_path / "points.stac.json"))
    assert d["properties"]["datetime"].startswith("2015-10-04T09:30:00")
    assert d["properties"]["rectify:datetime_source"] == "acquisition"
    assert d["assets"]["points"]["type"] == "application/vnd.las"
    with pytest.raises(errors.InvalidInputError, match="needs a grid or a footprint"):
        stac.stac_item(stac.StacProduct("x", {"points": stac.StacAsset(las)}), tmp_path / "x.json")
    with pytest.raises(errors.InvalidInputError, match="at least one asset"):
        stac.stac_item(stac.StacProduct("x", {}, footprint=product.footprint), tmp_path / "x.json")
    with pytest.raises(errors.RasterIOError, match="missing.tif"):
        stac.stac_item(stac.StacProduct("x", {"a": stac.StacAsset(tmp_path / "missing.tif")},
                                        footprint=product.footprint), tmp_path / "x.json")
    with pytest.raises(errors.InvalidInputError, match="6 finite numbers"):
        stac.RasterGrid(UTM34S, (1.0, 0.0, 0.0, 0.0, -1.0), 4, 4)  # type: ignore[arg-type]
