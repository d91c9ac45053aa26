"""Block files: the block control CSV, the observations CSV and the block orientation JSON."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rectify.errors import InvalidInputError, RasterIOError
from rectify.geometry.camera import Camera
from rectify.geometry.rotation import matrix_from_angles
from stereo.block.types import Pose, Tracks
from stereo.formats.block import (
    BLOCK_FORMAT,
    block_orientation_text,
    observations_text,
    read_block_control,
    read_block_orientation,
)

CAM = Camera(focal_length_mm=100.0, pixel_size_mm=0.01, width=2000, height=1500)


def _write(tmp_path, text, name="control.csv"):
    p = tmp_path / name
    p.write_text(text, encoding="utf-8")
    return p


def test_control_kinds_repeated_and_single_ground_rows(tmp_path):
    p = _write(tmp_path, "\ufeff# crs=EPSG:32633\n"
               "id,image,col,row,x,y,z,sx,sy,sz\n"
               "A,img1.tif,10.5,20.25,500000.0,5000000.0,250.0,0.02,0.02,0.05\n"
               "A,img2.tif,11.0,21.0,500000.0,5000000.0,250.0,,,\n"
               "H,img1.tif,100,200,,,310.5,,,\n"
               "H,img2.tif,101,201,,,,,,\n"
               "P,,,,500100.0,5000100.0,,,,\n"
               "P,img2.tif,300,400,,,,,,\n"
               "P,img3.tif,301,401,,,,,,\n"
               "T,img1.tif,5,6,,,,,,\n"
               "T,img3.tif,7,8,,,,,,\n")
    c = read_block_control(p)
    assert c.ids == ("A", "H", "P", "T")
    assert c.kind == ("full", "height", "plan", "tie")
    assert c.crs == "EPSG:32633"
    np.testing.assert_array_equal(c.xyz[0], [500000.0, 5000000.0, 250.0])
    assert math.isnan(c.xyz[1, 0]) and c.xyz[1, 2] == 310.5
    assert c.xyz[2, :2].tolist() == [500100.0, 5000100.0] and math.isnan(c.xyz[2, 2])
    assert np.isnan(c.xyz[3]).all()
    np.testing.assert_array_equal(c.sigma_m[0], [0.02, 0.02, 0.05])
    assert np.isnan(c.sigma_m[1]).all()
    assert c.meas_id == ("A", "A", "H", "H", "P", "P", "T", "T")
    assert c.meas_image[4:6] == ("img2.tif", "img3.tif")
    np.testing.assert_array_equal(c.meas_pixel[0], [10.5, 20.25])


@pytest.mark.parametrize("body, message", [
    ("id,image,col,row,x,y\nA,i,1,2,3,4\n", "missing column"),
    ("id,image,col,row,x,y,z\nA,i,1,abc,3,4,5\n", "line 2: column 'row' is not a number: 'abc'"),
    ("id,image,col,row,x,y,z\nA,i,1,2,3,4,5\nA,j,1,2,3,4,6\n", "has ground coordinates"),
    ("id,image,col,row,x,y,z\nA,i,1,2,3,,5\n", "x and y must be both given"),
    ("id,image,col,row,x,y,z\nA,i,1,2,3,4,5\nA,i,3,4,,,\n", "measured twice in image 'i'"),
    ("id,image,col,row,x,y,z,sx,sy,sz\nA,i,1,2,3,4,5,0,1,1\n", "standard deviations must be > 0"),
    ("id,image,col,row,x,y,z\nA,,1,2,3,4,5\n", "col/row given without an image"),
    ("id,image,col,row,x,y,z\n,i,1,2,3,4,5\n", "empty id"),
    ("id,image,col,row,x,y,z\n", "has a header but no rows"),
])
def test_control_bad_input(tmp_path, body, message):
    p = _write(tmp_path, body)
    before = p.read_bytes()
    with pytest.raises(InvalidInputError, match=message):
        read_block_control(p)
    assert p.read_bytes() == before


def test_control_missing_file(tmp_path):
    with pytest.raises(RasterIOError, match="file not found"):
        read_block_control(tmp_path / "nope.csv")


def _poses(n=3, seed=0):
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        a = rng.normal(0, 0.05, 3)
        a[2] += math.pi * (i % 2)
        out.append(Pose(f"img{i}.tif", "cam", rng.normal(0, 100, 3) + [500000.0, 5e6, 1500.0],
                        matrix_from_angles(*a)))
    return out


def test_orientation_round_trip(tmp_path):
    poses = _poses()
    std = np.abs(np.random.default_rng(1).normal(0, 0.01, (3, 6)))
    std[1, 2] = np.nan
    text = block_orientation_text({"cam": CAM}, poses, std_errors=std, crs="EPSG:32633",
                                  sigma0={"all": 0.98, "image": 1.01}, datum=["control: 4 full points"],
                                  summary={"images": 3})
    p = tmp_path / "orientation.json"
    p.write_text(text)
    doc = json.loads(text)
    assert doc["format"] == BLOCK_FORMAT and doc["version"] == 1
    b = read_block_orientation(p)
    assert [q.image for q in b.poses] == [q.image for q in poses]
    for q, r in zip(poses, b.poses, strict=True):
        np.testing.assert_array_equal(q.position, r.position)
        np.testing.assert_allclose(q.rotation, r.rotation, atol=1e-15)
    np.testing.assert_allclose(b.std_errors[~np.isnan(std)], std[~np.isnan(std)])
    assert np.isnan(b.std_errors[1, 2])
    assert b.crs == "EPSG:32633" and b.sigma0["image"] == 1.01 and b.datum == ["control: 4 full points"]
    assert b.cameras["cam"].focal_length_mm == 100.0
    assert b.pose("img1.tif").image == "img1.tif"
    with pytest.raises(InvalidInputError, match="'nope' is not in the block"):
        b.pose("nope")


@pytest.mark.parametrize("edit, message", [
    (lambda d: d.update(format="rectify-stereo/relative-orientation"), "has format"),
    (lambda d: d.update(version=99), "version 99"),
    (lambda d: d.update(cameras={}), "`cameras` must be a non-empty object"),
    (lambda d: d.update(images=[]), "`images` must be a non-empty list"),
    (lambda d: d["images"][0].update(camera="other"), "names camera 'other'"),
    (lambda d: d["images"][0].update(position=[1, 2]), "position"),
    (lambda d: d["images"][0].update(std_errors=[1, 2]), "`std_errors` must be an object"),
    (lambda d: d["cameras"].update(cam=[1, 2]), "camera 'cam' must be an object"),
])
def test_orientation_bad_files(tmp_path, edit, message):
    d = json.loads(block_orientation_text({"cam": CAM}, _poses()))
    edit(d)
    p = tmp_path / "o.json"
    p.write_text(json.dumps(d))
    with pytest.raises(InvalidInputError, match=message):
        read_block_orientation(p)


def test_orientation_file_without_format_is_refused(tmp_path):
    d = json.loads(block_orientation_text({"cam": CAM}, _poses()))
    del d["format"]
    p = tmp_path / "o.json"
    p.write_text(json.dumps(d))
    with pytest.raises(InvalidInputError, match="not a block orientation file"):
        read_block_orientation(p)


def test_observations_csv_rows():
    t = Tracks(("a", "b"), ("p1", "p2"), [0, 0, 1, 1], [0, 1, 0, 1],
               [[1.0, 2.0], [3.0, 4.0], [5.0, 6.0], [7.0, 8.0]], [1.0, 1.0, 0.5, 0.5])
    text = observations_text(t, np.array([[0.1, -0.2], [0.0, 0.0], [np.nan, np.nan], [1.0, 2.0]]),
                             np.array([1.0, 1.0, 0.0, 0.5]), np.array([False, False, True, False]))
    lines = text.splitlines()
    assert lines[0] == "image,id,col,row,sigma_px,residual_x_px,residual_y_px,weight,flagged"
    assert lines[1] == "a,p1,1.0000,2.0000,1,0.10000,-0.20000,1.0000,0"
    assert lines[3] == "a,p2,5.0000,6.0000,0.5,,,0.0000,1"
    assert len(lines) == 5


@settings(max_examples=40, deadline=None)
@given(st.lists(st.tuples(st.floats(-3.1, 3.1), st.floats(-1.5, 1.5), st.floats(-3.1, 3.1),
                          st.floats(-1e6, 1e6), st.floats(-1e6, 1e6), st.floats(-1e4, 1e4)),
                min_size=1, max_size=5))
def test_orientation_json_round_trip_property(tmp_path_factory, rows):
    poses = [Pose(f"i{k}", "cam", r[3:], matrix_from_angles(*r[:3])) for k, r in enumerate(rows)]
    p = tmp_path_factory.mktemp("o") / "o.json"
    p.write_text(block_orientation_text({"cam": CAM}, poses))
    back = read_block_orientation(p)
    for q, r in zip(poses, back.poses, strict=True):
        np.testing.assert_array_equal(q.position, r.position)
        np.testing.assert_allclose(q.rotation, r.rotation, atol=1e-15)
