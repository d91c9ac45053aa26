"""Known poses in: position/angle CSV, OpenSfM reconstruction.json, GNSS/INS navigation angles."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.testing import assert_allclose, assert_array_equal
from scipy.spatial.transform import Rotation

from rectify.errors import CRSError, InvalidInputError, RasterIOError, ShapeError
from rectify.geometry.camera import Camera
from rectify.geometry.geodesy import enu_from_body
from rectify.geometry.rotation import angles_from_matrix, matrix_from_angles, rodrigues, rot_x, rot_y, rot_z
from stereo.block.navigation import body_rotation, navigation_from_rotation, rotation_from_navigation
from stereo.block.types import Pose, project_pixel
from stereo.formats.opensfm import OpenSfMReconstruction, read_opensfm
from stereo.formats.poses import DEFAULT_CAMERA_ID, PoseTable, pose_csv_text, read_pose_csv, write_pose_csv

DATA = Path(__file__).resolve().parents[1] / "data" / "block"
D = np.deg2rad
EAST, NORTH, UP = np.eye(3)


# =========================================================================== navigation angles
@pytest.mark.parametrize("convention", ["seed004", "euler"])
def test_zero_angles_nadir_camera_looks_down_image_top_north(convention):
    R = rotation_from_navigation(0.0, 0.0, 0.0, convention=convention)
    assert_allclose(R, np.eye(3), atol=1e-15)
    assert_allclose(R @ [0.0, 0.0, -1.0], -UP, atol=1e-15)  # viewing direction (0, 0, -f): straight down


@pytest.mark.parametrize("convention", ["seed004", "euler"])
@pytest.mark.parametrize(("heading_deg", "forward", "image_x"), [
    (0.0, NORTH, EAST), (90.0, EAST, -NORTH), (180.0, -NORTH, -EAST), (270.0, -EAST, NORTH), (45.0,
     (EAST + NORTH) / math.sqrt(2), (EAST - NORTH) / math.sqrt(2))])
def test_heading_clockwise_from_grid_north(convention, heading_deg, forward, image_x):
    R = rotation_from_navigation(D(heading_deg), 0.0, 0.0, convention=convention)
    assert_allclose(R @ [0.0, 1.0, 0.0], forward, atol=1e-15)  # top of the image = flight direction
    assert_allclose(R @ [1.0, 0.0, 0.0], image_x, atol=1e-15)  # image x = right wing
    assert_allclose(R @ [0.0, 0.0, -1.0], -UP, atol=1e-15)
    assert_allclose(angles_from_matrix(R)[2], -D(heading_deg) if heading_deg <= 180 else D(360 - heading_deg),
                    atol=1e-14)  # kappa = -heading


@pytest.mark.parametrize("convention", ["seed004", "euler"])
def test_pitch_nose_up_and_roll_right_wing_down(convention):
    p = D(10.0)
    R = rotation_from_navigation(0.0, p, 0.0, convention=convention)
    assert_allclose(R @ [0.0, 1.0, 0.0], [0.0, math.cos(p), math.sin(p)], atol=1e-15)  # nose up
    assert_allclose(R @ [0.0, 0.0, -1.0], [0.0, math.sin(p), -math.cos(p)], atol=1e-15)  # belly swings forward
    r = D(5.0)
    R = rotation_from_navigation(0.0, 0.0, r, convention=convention)
    assert_allclose(R @ [1.0, 0.0, 0.0], [math.cos(r), 0.0, -math.sin(r)], atol=1e-15)  # right wing down
    assert_allclose(R @ [0.0, 0.0, -1.0], [-math.sin(r), 0.0, -math.cos(r)], atol=1e-15)  # looks left of track
    # flying east, right wing down: the right wing (south) dips
    R = rotation_from_navigation(D(90.0), 0.0, r, convention=convention)
    assert_allclose(R @ [1.0, 0.0, 0.0], [0.0, -math.cos(r), -math.sin(r)], atol=1e-15)


def test_seed004_matrix_is_geodesy_navigation_matrix_with_roll_sign_reversed():
    """Seed 004 eqs. (6)-(10), as coded independently in rectify.geometry.geodesy (its roll raises the Y' axis)."""
    rng = np.random.default_rng(4)
    for h, p, r in zip(rng.uniform(0, 2 * np.pi, 20), rng.uniform(-0.6, 0.6, 20), rng.uniform(-0.6, 0.6, 20),
                       strict=True):
        assert_allclose(rotation_from_navigation(h, p, r), enu_from_body(h, p, -r), atol=1e-14)


def test_seed004_hand_computed_large_angles():
    """heading 0, pitch 30, roll 30 deg: gamma = arccos(tan 30 tan 30) = arccos(1/3) (seed eq. 7)."""
    p = r = D(30.0)
    g = math.acos(1.0 / 3.0)
    R = rotation_from_navigation(0.0, p, r)
    right = [math.cos(r) * math.sin(g), math.cos(r) * math.cos(g), -math.sin(r)]
    fwd = [0.0, math.cos(p), math.sin(p)]
    assert_allclose(R[:, 0], right, atol=1e-15)
    assert_allclose(R[:, 1], fwd, atol=1e-15)
    assert_allclose(R[:, 2], np.cross(right, fwd), atol=1e-15)
    assert_allclose(R @ R.T, np.eye(3), atol=1e-15)
    # the right-wing axis is 30 deg below the horizon (great-circle roll) ...
    assert math.degrees(math.asin(-R[2, 0])) == pytest.approx(30.0, abs=1e-12)
    # ... which a Tait-Bryan roll reaches only with sin(r_euler) = sin(r) / cos(p)
    re = math.asin(math.sin(r) / math.cos(p))
    assert_allclose(rotation_from_navigation(0.0, p, re, convention="euler"), R, atol=1e-14)


def test_euler_convention_is_yaw_pitch_roll_product():
    h, p, r = 0.7, -0.2, 0.3
    assert_allclose(rotation_from_navigation(h, p, r, convention="euler"), rot_z(-h) @ rot_x(p) @ rot_y(r),
                    atol=1e-15)
    # with pitch or roll zero both definitions agree
    assert_allclose(rotation_from_navigation(h, 0.0, r, convention="euler"), rotation_from_navigation(h, 0.0, r),
                    atol=1e-15)
    assert_allclose(rotation_from_navigation(h, p, 0.0, convention="euler"), rotation_from_navigation(h, p, 0.0),
                    atol=1e-15)
    assert not np.allclose(rotation_from_navigation(h, p, r, convention="euler"), rotation_from_navigation(h, p, r),
                           atol=1e-6)


@pytest.mark.parametrize("convention", ["seed004", "euler"])
@pytest.mark.parametrize("heading_deg", [0.0, 30.0, 90.0, 200.0, 315.0])
def test_small_angles_agree_with_omega_phi_kappa(convention, heading_deg):
    """Near nadir: kappa = -heading; (omega, phi) = Rz(-heading) (pitch, roll), to second order in the angles."""
    h, p, r = D(heading_deg), 1e-3, -2e-3
    tol = (abs(p) + abs(r)) ** 2  # 9e-6 rad
    opk = angles_from_matrix(rotation_from_navigation(h, p, r, convention=convention))
    assert opk[0] == pytest.approx(p * math.cos(h) + r * math.sin(h), abs=tol)
    assert opk[1] == pytest.approx(-p * math.sin(h) + r * math.cos(h), abs=tol)
    assert math.remainder(opk[2] + h, 2 * math.pi) == pytest.approx(0.0, abs=tol)


def test_boresight_is_applied_after_the_body_rotation():
    h, p, r = 1.0, 0.05, -0.03
    b = [0.002, -0.004, 0.01]
    R = rotation_from_navigation(h, p, r, boresight_rad=b)
    assert_allclose(R, body_rotation(h, p, r) @ matrix_from_angles(b[0], b[1], b[2]), atol=1e-15)
    assert_allclose(navigation_from_rotation(R, boresight_rad=b), [h, p, r], atol=1e-12)
    # without the boresight the camera angles are off by about its size
    assert np.abs(navigation_from_rotation(R) - [h, p, r]).max() > 1e-3


def test_vectorised_and_broadcast():
    h = np.array([0.0, 0.5, 1.0, 6.0])
    R = rotation_from_navigation(h, 0.01, np.array([[0.0], [0.02]]))
    assert R.shape == (2, 4, 3, 3)
    for i in range(2):
        for j in range(4):
            assert_allclose(R[i, j], rotation_from_navigation(h[j], 0.01, [0.0, 0.02][i]), atol=0)
    back = navigation_from_rotation(R)
    assert back.shape == (2, 4, 3)
    assert_allclose(back[..., 0], np.broadcast_to(h, (2, 4)), atol=1e-14)
    assert rotation_from_navigation(0.1, 0.0, 0.0).shape == (3, 3)


angle = st.floats(-1.2, 1.2, allow_nan=False)


@settings(max_examples=200, deadline=None)
@given(h=st.floats(0.0, 2 * np.pi - 1e-9), p=angle, r=angle, conv=st.sampled_from(["seed004", "euler"]),
       b=st.lists(st.floats(-0.1, 0.1), min_size=3, max_size=3))
def test_navigation_round_trip(h, p, r, conv, b):
    if conv == "seed004" and abs(math.tan(p) * math.tan(r)) > 0.99:
        return  # outside seed 004's domain (tested below)
    R = rotation_from_navigation(h, p, r, boresight_rad=b, convention=conv)
    assert_allclose(R @ R.T, np.eye(3), atol=1e-14)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-14)
    hb, pb, rb = navigation_from_rotation(R, boresight_rad=b, convention=conv)
    assert math.remainder(hb - h, 2 * math.pi) == pytest.approx(0.0, abs=1e-9)
    assert pb == pytest.approx(p, abs=1e-9)
    assert rb == pytest.approx(r, abs=1e-9)
    assert 0.0 <= hb < 2 * np.pi
    assert_allclose(rotation_from_navigation(hb, pb, rb, boresight_rad=b, convention=conv), R, atol=1e-12)


def test_navigation_bad_input():
    with pytest.raises(InvalidInputError, match=r"pitch 1.2 and roll 1.2 rad admit no orthogonal platform axes"):
        rotation_from_navigation(0.0, 1.2, 1.2)
    with pytest.raises(InvalidInputError, match=r"pitch 1.5707963267948966 and roll 0.0"):
        rotation_from_navigation(0.0, math.pi / 2, 0.0)
    with pytest.raises(InvalidInputError, match=r"navigation angles must be finite; got heading \[nan\]"):
        rotation_from_navigation([float("nan")], 0.0, 0.0)
    with pytest.raises(InvalidInputError, match=r"unknown navigation convention 'ned'; expected one of "
                                                r"\['seed004', 'euler'\]"):
        rotation_from_navigation(0.0, 0.0, 0.0, convention="ned")
    with pytest.raises(InvalidInputError, match=r"unknown navigation convention 'x'"):
        navigation_from_rotation(np.eye(3), convention="x")
    with pytest.raises(InvalidInputError, match=r"boresight_rad must be 3 finite angles .* got \[0.0, 0.0\]"):
        rotation_from_navigation(0.0, 0.0, 0.0, boresight_rad=[0.0, 0.0])
    with pytest.raises(InvalidInputError, match=r"boresight_rad must be small angles .* got \[0.0, 0.0, 0.5\]: "
                                                r"were degrees given\?"):
        rotation_from_navigation(0.0, 0.0, 0.0, boresight_rad=[0.0, 0.0, 0.5])
    with pytest.raises(ShapeError, match=r"`R` must have shape \(\.\.\., 3, 3\); got \(3, 2\)"):
        navigation_from_rotation(np.zeros((3, 2)))


def test_rodrigues_matches_scipy():
    rng = np.random.default_rng(7)
    for v in [*rng.normal(size=(10, 3)), np.zeros(3), np.array([1e-14, 0.0, 0.0]), np.array([np.pi, 0, 0])]:
        assert_allclose(rodrigues(v)[0], Rotation.from_rotvec(v).as_matrix(), atol=1e-14)


# =========================================================================== position/angle CSV
def _pose(name: str, xyz, opk_deg, camera: str = "cam") -> Pose:
    return Pose(name, camera, np.asarray(xyz, float), matrix_from_angles(*np.radians(opk_deg)))


def test_read_sample_opk_csv():
    t = read_pose_csv(DATA / "poses_opk.csv")
    assert isinstance(t, PoseTable)
    assert t.images == ("img_001.tif", "img_002.tif") and len(t) == 2
    assert t.crs == "EPSG:32633" and t.angle_unit == "deg" and t.angle_system == "omega-phi-kappa"
    assert t.source == DATA / "poses_opk.csv"
    a, b = t.poses
    assert a.camera == b.camera == "dji"
    assert_array_equal(b.position, [500060.0, 5000000.0, 1101.5])
    assert_allclose(a.rotation, np.eye(3), atol=0)
    assert_allclose(b.rotation, rot_x(D(1.5)) @ rot_y(D(-2.0)) @ rot_z(D(90.0)), atol=1e-15)
    assert t.sigma is not None
    assert_allclose(t.sigma[0], [0.05, 0.05, 0.1, D(0.01), D(0.01), D(0.02)], rtol=1e-15)
    assert_allclose(t.sigma[1, :3], [0.05, 0.05, 0.1])
    assert np.isnan(t.sigma[1, 3:]).all()
    assert not t.sigma.flags.writeable


def test_read_sample_navigation_csv_with_bom_and_lever_arm():
    lever = [0.1, -0.2, 0.5]
    t = read_pose_csv(DATA / "poses_nav.csv", camera="ins-cam", lever_arm_m=lever)
    assert t.angle_system == "navigation" and t.crs == "EPSG:32633" and t.images[0] == "img_001.tif"
    a, b = t.poses
    assert a.camera == "ins-cam"
    # heading 90 deg: body right wing = south, forward = east, up = up
    assert_allclose(a.rotation, [[0, 1, 0], [-1, 0, 0], [0, 0, 1]], atol=1e-15)
    # R_body @ lever = (lever_y, -lever_x, lever_z) = (-0.2, -0.1, 0.5); C = A - R_body @ lever
    assert_allclose(a.position, [500000.2, 5000000.1, 1099.5], atol=1e-9)
    Rb = rotation_from_navigation(D(270.0), D(2.0), D(-1.0))
    assert_allclose(b.rotation, Rb, atol=1e-15)
    assert_allclose(b.position, np.array([500060.0, 5000000.0, 1100.0]) - Rb @ lever, atol=1e-9)
    assert t.sigma is not None
    assert_allclose(t.sigma[:, :3], [[0.03, 0.03, 0.05]] * 2)
    assert np.isnan(t.sigma[:, 3:]).all()


def test_lever_arm_sign_antenna_forward_of_camera(tmp_path):
    """Antenna 1 m forward of the projection centre, flying east: the camera is 1 m west of it."""
    text = "image,x,y,z,heading,pitch,roll\na,100.0,200.0,50.0,90,0,0\n"
    p = tmp_path / "p.csv"
    p.write_text(text)
    t = read_pose_csv(p, lever_arm_m=[0.0, 1.0, 0.0])
    assert_allclose(t.poses[0].position, [99.0, 200.0, 50.0], atol=1e-12)


def test_boresight_in_csv(tmp_path):
    p = tmp_path / "nav.csv"
    p.write_text("# angles=rad\nimage,x,y,z,heading,pitch,roll\na,0,0,100,0.5,0.01,-0.02\n")
    b = [0.001, 0.002, -0.003]
    t = read_pose_csv(p, boresight_rad=b, convention="euler")
    assert t.angle_unit == "rad" and t.sigma is None and t.crs is None
    assert t.poses[0].camera == DEFAULT_CAMERA_ID
    assert_allclose(t.poses[0].rotation, rotation_from_navigation(0.5, 0.01, -0.02, boresight_rad=b,
                                                                  convention="euler"), atol=1e-15)


def test_angles_default_deg_and_rad(tmp_path):
    p = tmp_path / "a.csv"
    p.write_text("image,x,y,z,omega,phi,kappa\na,1,2,3,0,0,90\n")
    t = read_pose_csv(p)
    assert t.angle_unit == "deg"
    assert_allclose(t.poses[0].angles, [0, 0, math.pi / 2], atol=1e-15)
    p.write_text("# Angles = RAD\nimage,x,y,z,omega,phi,kappa\na,1,2,3,0,0,1.5\n")
    t = read_pose_csv(p)
    assert t.angle_unit == "rad"
    assert_allclose(t.poses[0].angles, [0, 0, 1.5], atol=1e-15)


def test_opk_lever_arm_in_camera_frame(tmp_path):
    p = tmp_path / "a.csv"
    p.write_text("image,x,y,z,omega,phi,kappa\na,10,20,30,0,0,90\n")
    t = read_pose_csv(p, lever_arm_m=[1.0, 0.0, 0.0])  # antenna on the image x axis, kappa 90: x -> north
    assert_allclose(t.poses[0].position, [10.0, 19.0, 30.0], atol=1e-12)


@pytest.mark.parametrize("angles", ["deg", "rad"])
def test_write_read_round_trip(tmp_path, angles):
    rng = np.random.default_rng(11)
    poses = [_pose(f"IMG {i:03d}.jpg", rng.uniform(-1e6, 1e6, 3), rng.uniform(-170, 170, 3) * [0.5, 0.5, 1],
                   camera=f"c{i % 2}") for i in range(7)]
    std = rng.uniform(0, 1, (7, 6))
    std[2, 4] = np.nan
    out = write_pose_csv(tmp_path / "poses.csv", poses, crs="EPSG:25833", angles=angles, std=std)
    assert out == tmp_path / "poses.csv"
    t = read_pose_csv(out)
    assert t.crs == "EPSG:25833" and t.angle_unit == angles
    for a, b in zip(poses, t.poses, strict=True):
        assert (a.image, a.camera) == (b.image, b.camera)
        assert_array_equal(a.position, b.position)  # repr: exact
        assert_allclose(b.rotation, a.rotation, atol=2e-15)
        assert_allclose(b.angles, a.angles, atol=1e-14)
    assert t.sigma is not None
    assert_allclose(t.sigma, std, rtol=1e-15, atol=0)
    # written text carries angles to 17 significant digits (far below 1e-10 deg)
    text = out.read_text()
    assert f"# angles={angles}" in text and text.startswith("# crs=EPSG:25833\n")
    value = float(text.splitlines()[4].split(",")[5])
    assert value == pytest.approx(np.degrees(poses[0].angles[0]) if angles == "deg" else poses[0].angles[0],
                                  abs=1e-13)


def test_pose_csv_text_exact_layout():
    text = pose_csv_text([_pose("a", [1.0, 2.5, 3.0], [0, 0, 90])], crs=None, angles="deg")
    assert text.splitlines() == [
        "# angles=deg",
        "# R = Rx(omega) Ry(phi) Rz(kappa) takes the photo vector (x, y, -f) into the ground frame",
        "image,camera,x,y,z,omega,phi,kappa",
        "a,cam,1.0,2.5,3.0,0.0,0.0,90.0",
    ]


def test_write_refuses_overwrite_and_is_atomic(tmp_path):
    poses = [_pose("a", [1, 2, 3], [0, 0, 0])]
    out = tmp_path / "p.csv"
    write_pose_csv(out, poses, crs=None)
    before = out.read_text()
    with pytest.raises(InvalidInputError, match=r"output '.*p\.csv' exists; pass --overwrite to replace it"):
        write_pose_csv(out, [_pose("b", [4, 5, 6], [0, 0, 0])], crs=None)
    assert out.read_text() == before
    write_pose_csv(out, [_pose("b", [4, 5, 6], [0, 0, 0])], crs=None, overwrite=True)
    assert read_pose_csv(out).images == ("b",)
    with pytest.raises(CRSError, match=r"unknown CRS 'EPSG:99999999'"):
        write_pose_csv(tmp_path / "q.csv", poses, crs="EPSG:99999999")
    assert sorted(x.name for x in tmp_path.iterdir()) == ["p.csv"]  # nothing left behind


def test_write_bad_input(tmp_path):
    poses = [_pose("a", [1, 2, 3], [0, 0, 0]), _pose("b", [1, 2, 3], [0, 0, 0])]
    with pytest.raises(InvalidInputError, match=r"unknown angle unit 'grad'; expected one of \['deg', 'rad'\]"):
        pose_csv_text(poses, crs=None, angles="grad")
    with pytest.raises(ShapeError, match=r"std must have shape \(2, 6\); got \(2, 3\)"):
        pose_csv_text(poses, crs=None, std=np.ones((2, 3)))
    with pytest.raises(InvalidInputError, match=r"std must be >= 0 and finite"):
        pose_csv_text(poses, crs=None, std=-np.ones((2, 6)))
    with pytest.raises(InvalidInputError, match=r"duplicate image name\(s\) \['a'\]"):
        pose_csv_text([poses[0], poses[0]], crs=None)
    with pytest.raises(InvalidInputError, match=r"image name 'x,y' / camera id 'cam' cannot be written"):
        pose_csv_text([_pose("x,y", [1, 2, 3], [0, 0, 0])], crs=None)
    with pytest.raises(InvalidInputError, match=r"poses must be a sequence of stereo.block.types.Pose"):
        pose_csv_text([1], crs=None)  # type: ignore[list-item]


def _bad(tmp_path: Path, text: str, name: str = "bad.csv") -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


HEAD = "image,x,y,z,omega,phi,kappa\n"


@pytest.mark.parametrize(("text", "kwargs", "error", "pattern"), [
    ("image,x,y,omega,phi,kappa\na,1,2,0,0,0\n", {}, InvalidInputError,
     r"'.*bad\.csv': missing column\(s\) \['z'\]; header is \['image', 'x', 'y', 'omega', 'phi', 'kappa'\]"),
    ("image,x,y,z\na,1,2,3\n", {}, InvalidInputError, r"missing column\(s\) \['omega', 'phi', 'kappa'\]"),
    ("image,x,y,z,omega,phi,kappa,heading,pitch,roll\na,1,2,3,0,0,0,0,0,0\n", {}, InvalidInputError,
     r"give either omega,phi,kappa or heading,pitch,roll, not both"),
    ("# crs=EPSG:32633\n" + HEAD + "a,1,2,3,0,0,0\nb,1,two,3,0,0,0\n", {}, InvalidInputError,
     r"'.*bad\.csv' line 4: column 'y' is not a number: 'two'"),
    (HEAD + "a,1,2,3,0,nan,0\n", {}, InvalidInputError, r"line 2: column 'phi' is not finite: 'nan'"),
    (HEAD + "a,1,2,3,0,0,\n", {}, InvalidInputError, r"line 2: column 'kappa' is not a number: ''"),
    (HEAD + "a,1,2,3,0,0,0\nb,1,2,3,0,0,0\na,4,5,6,0,0,0\n", {}, InvalidInputError,
     r"'.*bad\.csv': duplicate image name\(s\) \['a'\]"),
    (HEAD + ",1,2,3,0,0,0\n", {}, InvalidInputError, r"line 2: empty image name"),
    ("# angles=grad\n" + HEAD + "a,1,2,3,0,0,0\n", {}, InvalidInputError,
     r"'.*bad\.csv' line 1: unknown angle unit 'grad'; expected one of \['deg', 'rad'\]"),
    ("# angles=deg\n# angles=rad\n" + HEAD + "a,1,2,3,0,0,0\n", {}, InvalidInputError,
     r"line 2: second angle unit 'rad' contradicts 'deg' of line 1"),
    ("# angles=rad\n# crs=EPSG:99999999\n" + HEAD + "a,1,2,3,0,0,0\n", {}, CRSError,
     r"'.*bad\.csv' line 2: unknown CRS 'EPSG:99999999'"),
    ("image,x,y,z,omega,phi,kappa,sigma_x\na,1,2,3,0,0,0,1\n", {}, InvalidInputError,
     r"unknown column\(s\) \['sigma_x'\]; allowed are \["),
    ("image,x,y,z,omega,phi,kappa,sx\na,1,2,3,0,0,0,-0.1\n", {}, InvalidInputError,
     r"line 2: standard deviation 'sx' must be >= 0; got '-0.1'"),
    (HEAD + "a,1,2,3,0,0,0\n", {"boresight_rad": [0, 0, 0]}, InvalidInputError,
     r"boresight_rad applies to heading,pitch,roll files only"),
    ("image,x,y,z,heading,pitch,roll\na,1,2,3,0,0,0\nb,1,2,3,0,60,60\n", {}, InvalidInputError,
     r"'.*bad\.csv' line 3: pitch 1.047.* and roll 1.047.* rad admit no orthogonal platform axes"),
    (HEAD, {}, InvalidInputError, r"has a header but no pose rows"),
    ("# crs=EPSG:32633\n", {}, InvalidInputError, r"has no header and no rows"),
    (HEAD + "a,1,2,3,0,0,0\n", {"camera": ""}, InvalidInputError, r"camera must be a non-empty camera id; got ''"),
    (HEAD + "a,1,2,3,0,0,0\n", {"lever_arm_m": [1, 2]}, InvalidInputError,
     r"lever_arm_m must be 3 finite numbers \(metres, body frame\); got \[1, 2\]"),
    (HEAD + "a,1,2,3,0,0,0\n", {"convention": "ned"}, InvalidInputError, r"unknown navigation convention 'ned'"),
])
def test_read_pose_csv_bad_input(tmp_path, text, kwargs, error, pattern):
    with pytest.raises(error, match=pattern):
        read_pose_csv(_bad(tmp_path, text), **kwargs)


def test_read_pose_csv_missing_file(tmp_path):
    with pytest.raises(RasterIOError, match=r"file not found: '.*nothing\.csv'"):
        read_pose_csv(tmp_path / "nothing.csv")


def test_read_pose_csv_bom_and_camera_cells(tmp_path):
    p = tmp_path / "bom.csv"
    p.write_bytes("\ufeffimage,camera,x,y,z,omega,phi,kappa\r\na,,1,2,3,0,0,0\r\nb,wide,1,2,3,0,0,0\r\n"
                  .encode("utf-8"))
    t = read_pose_csv(p, camera="nadir")
    assert [q.camera for q in t.poses] == ["nadir", "wide"]


# =========================================================================== OpenSfM
FLIP = np.diag([1.0, -1.0, -1.0])


def _opensfm_project(cam: dict, rotvec, translation, X) -> np.ndarray:
    """OpenSfM's own model (doc/source/geometry.rst, camera_distortions_functions.h), written from its docs:
    camera coordinates x_c = R_cw X + t (x right, y down, z forward), x_n = x/z, distortion, affine in
    normalised units, then pixel = s * u - 0.5 + w / 2 (features.denormalized_image_coordinates)."""
    R_cw = Rotation.from_rotvec(rotvec).as_matrix()
    xc = np.asarray(X) @ R_cw.T + np.asarray(translation)
    xn, yn = xc[:, 0] / xc[:, 2], xc[:, 1] / xc[:, 2]
    r2 = xn * xn + yn * yn
    g = cam.get
    pt = cam["projection_type"]
    if pt == "perspective":
        d = 1 + g("k1", 0.0) * r2 + g("k2", 0.0) * r2 * r2
        u, v = cam["focal"] * d * xn, cam["focal"] * d * yn
    else:
        k1, k2, k3, p1, p2 = (g(k, 0.0) for k in ("k1", "k2", "k3", "p1", "p2"))
        dr = 1 + k1 * r2 + k2 * r2 ** 2 + k3 * r2 ** 3
        xd = dr * xn + 2 * p1 * xn * yn + p2 * (r2 + 2 * xn * xn)
        yd = dr * yn + 2 * p2 * xn * yn + p1 * (r2 + 2 * yn * yn)
        u = cam["focal_x"] * xd + g("c_x", 0.0)
        v = cam["focal_y"] * yd + g("c_y", 0.0)
    w, h = cam["width"], cam["height"]
    s = max(w, h)
    return np.column_stack([u * s - 0.5 + w / 2.0, v * s - 0.5 + h / 2.0])


def _synthetic_block(seed: int = 3):
    """A 2 x 3 block of near-nadir shots over a hilly patch; OpenSfM's rotations and translations."""
    rng = np.random.default_rng(seed)
    cams = {
        "brown cam": {"projection_type": "brown", "width": 640, "height": 480, "focal_x": 0.85, "focal_y": 0.85,
                      "c_x": 0.012, "c_y": -0.008, "k1": -0.08, "k2": 0.02, "k3": -0.004, "p1": 0.0012,
                      "p2": -0.0007},
        "persp cam": {"projection_type": "perspective", "width": 400, "height": 600, "focal": 1.1, "k1": -0.05,
                      "k2": 0.01},
        "radial cam": {"projection_type": "radial", "width": 500, "height": 500, "focal_x": 0.9, "focal_y": 0.9,
                       "c_x": -0.01, "c_y": 0.02, "k1": 0.03, "k2": -0.01},
        "simple cam": {"projection_type": "simple_radial", "width": 300, "height": 200, "focal_x": 0.7,
                       "focal_y": 0.7, "c_x": 0.0, "c_y": 0.01, "k1": -0.02},
    }
    shots = {}
    names = list(cams)
    for i in range(6):
        C = np.array([40.0 * (i % 3), 50.0 * (i // 3), 120.0]) + rng.normal(0, 2, 3)
        # world -> camera: a nadir camera (x_c = x_w, y_c = -y_w, z_c = -z_w) tilted by a few degrees
        R_cw = Rotation.from_rotvec(rng.normal(0, 0.05, 3)).as_matrix() @ FLIP
        shots[f"IMG_{i:04d}.JPG"] = {"rotation": Rotation.from_matrix(R_cw).as_rotvec().tolist(),
                                     "translation": (-R_cw @ C).tolist(), "camera": names[i % len(names)]}
    X = np.column_stack([rng.uniform(0, 80, 40), rng.uniform(0, 50, 40), rng.uniform(-10, 15, 40)])
    points = {str(100 + k): {"coordinates": X[k].tolist(), "color": rng.integers(0, 256, 3).astype(float).tolist()}
              for k in range(len(X))}
    return {"cameras": cams, "shots": shots, "points": points}, X


def test_opensfm_projection_matches_opensfm_model(tmp_path):
    rec, X = _synthetic_block()
    small = {"cameras": {"c": rec["cameras"]["brown cam"]},
             "shots": {"x.jpg": {**rec["shots"]["IMG_0000.JPG"], "camera": "c"}}}
    path = tmp_path / "reconstruction.json"
    path.write_text(json.dumps([small, rec]))
    r = read_opensfm(path)
    assert isinstance(r, OpenSfMReconstruction)
    assert r.index == 1 and r.n_reconstructions == 2  # the largest
    assert r.reference_lonlat_h is None and "not georeferenced" in r.frame
    assert [p.image for p in r.poses] == sorted(rec["shots"])
    assert set(r.cameras) == set(rec["cameras"]) and all(c.pixel_camera for c in r.cameras.values())
    checked = 0
    for pose in r.poses:
        shot = rec["shots"][pose.image]
        cam = rec["cameras"][shot["camera"]]
        want = _opensfm_project(cam, shot["rotation"], shot["translation"], X)
        got = project_pixel(r.cameras[pose.camera], pose, X)
        assert_allclose(got, want, atol=1e-6, rtol=0)
        checked += len(X)
        R_cw = Rotation.from_rotvec(shot["rotation"]).as_matrix()
        assert_allclose(pose.position, -R_cw.T @ shot["translation"], atol=1e-9)
        assert_allclose(pose.rotation, R_cw.T @ FLIP, atol=1e-14)
    assert checked == 6 * 40
    order = np.argsort([str(100 + k) for k in range(40)])
    assert r.point_ids == tuple(sorted(str(100 + k) for k in range(40)))
    assert_allclose(r.points, X[order], atol=0)
    want_rgb = np.array([rec["points"][k]["color"] for k in r.point_ids])
    assert r.colors is not None and r.colors.dtype == np.uint8
    assert_array_equal(r.colors, want_rgb.astype(np.uint8))
    assert np.isnan(r.gps_position).all() and np.isnan(r.gps_dop).all()
    # index chooses explicitly
    assert [p.image for p in read_opensfm(path, index=0).poses] == ["x.jpg"]


def test_opensfm_camera_conversion_values(tmp_path):
    """Brown camera in OpenSfM units -> pixels: f = s focal, principal point = s c + (w - 1) / 2."""
    rec, _ = _synthetic_block()
    path = tmp_path / "reconstruction.json"
    path.write_text(json.dumps([rec]))
    cam = read_opensfm(path).cameras["brown cam"]
    assert cam.focal_px == pytest.approx(0.85 * 640, rel=1e-15)
    assert_allclose(cam.principal_point_px, [0.012 * 640 + 319.5, -0.008 * 640 + 239.5], atol=1e-12)
    assert cam.distortion == {"k1": -0.08, "k2": 0.02, "k3": -0.004, "p1": 0.0012, "p2": -0.0007}
    assert (cam.width, cam.height) == (640, 480)
    persp = read_opensfm(path).cameras["persp cam"]
    assert persp.focal_px == pytest.approx(1.1 * 600) and persp.distortion["k3"] == 0.0
    assert_allclose(persp.principal_point_px, [199.5, 299.5], atol=1e-12)


def test_opensfm_sample_file_hand_checked():
    """tests/data/block/opensfm: nadir shots at 100 m; ground point (10, 20, 0) -> pixel (239.5, 69.5)."""
    r = read_opensfm(DATA / "opensfm" / "reconstruction.json")
    assert r.index == 0 and r.n_reconstructions == 2
    assert r.reference_lonlat_h is not None
    assert_allclose(r.reference_lonlat_h, [14.5, 46.05, 300.0])
    assert r.frame.startswith("topocentric east-north-up")
    a, b = r.poses
    assert_allclose(a.position, [0.0, 0.0, 100.0], atol=1e-12)
    assert_allclose(b.position, [50.0, 0.0, 100.0], atol=1e-12)
    assert_allclose(a.rotation, np.eye(3), atol=1e-15)  # nadir, image top = north
    cam = r.cameras[a.camera]
    assert_allclose(project_pixel(cam, a, [[0, 0, 0], [10, 20, 0]]), [[199.5, 149.5], [239.5, 69.5]], atol=1e-9)
    assert_allclose(project_pixel(cam, b, [[50, 0, 0]]), [[199.5, 149.5]], atol=1e-9)
    assert_array_equal(r.colors, [[255, 128, 0], [0, 0, 0]])
    assert_allclose(r.gps_position[0], [0.5, 0.0, 100.0])
    assert np.isnan(r.gps_position[1]).all()
    assert_allclose(r.gps_dop, [5.0, np.nan])
    assert not r.points.flags.writeable


def test_opensfm_reference_in_data_wins_and_single_object(tmp_path):
    rec = json.loads((DATA / "opensfm" / "reconstruction.json").read_text())[0]
    rec["reference_lla"] = {"latitude": -33.9, "longitude": 18.4, "altitude": 12.0}
    p = tmp_path / "reconstruction.json"
    p.write_text(json.dumps(rec))  # a bare object is read as a one-element list
    r = read_opensfm(p)
    assert r.reference_lonlat_h is not None
    assert_allclose(r.reference_lonlat_h, [18.4, -33.9, 12.0])


def test_opensfm_focal_mean_within_tolerance(tmp_path):
    rec, _ = _synthetic_block()
    cam = rec["cameras"]["brown cam"]
    cam["focal_y"] = cam["focal_x"] * (1 + 5e-4)
    p = tmp_path / "r.json"
    p.write_text(json.dumps([rec]))
    assert read_opensfm(p).cameras["brown cam"].focal_px == pytest.approx(640 * 0.85 * (1 + 2.5e-4), rel=1e-12)


def _with(rec: dict, mutate) -> list:
    rec = json.loads(json.dumps(rec))
    mutate(rec)
    return [rec]


def _cam(rec, **kw):
    rec["cameras"]["brown cam"].update(kw)


@pytest.mark.parametrize(("doc", "kwargs", "pattern"), [
    ({"a": 1}, {}, r"is not an OpenSfM reconstruction file .* got dict"),
    ([], {}, r"is not an OpenSfM reconstruction file"),
    ([1, 2], {}, r"\(a non-empty JSON list of reconstructions\); got list"),
    ("BLOCK", {"index": 1}, r"reconstruction index 1 out of range 0\.\.0"),
    ([{"shots": {}}], {}, r"reconstruction 0 lacks the 'cameras' object"),
    ("fisheye", {}, r"camera 'brown cam' has projection_type 'fisheye', which the frame camera model cannot "
                    r"represent; supported: \['perspective', 'brown', 'radial', 'simple_radial'\]"),
    ("spherical", {}, r"projection_type 'spherical'"),
    ("equirectangular", {}, r"projection_type 'equirectangular'"),
    ("aspect", {}, r"camera 'brown cam' has focal_x 0\.85 and focal_y 0\.86; the frame camera model needs square "
                   r"pixels"),
    ("nowidth", {}, r"camera 'brown cam' needs positive integer width and height .* got 0, 480"),
    ("nofocal", {}, r"camera 'brown cam' \(brown\) lacks \['focal_y'\]"),
    ("badk1", {}, r"camera 'brown cam' k1 must be a finite number; got 'x'"),
    ("unknowncam", {}, r"shot 'IMG_0000\.JPG' names camera 'nope', which is not in the reconstruction"),
    ("badrot", {}, r"shot 'IMG_0001\.JPG' rotation must be a list of 3 numbers; got \[0, 1\]"),
    ("nanrot", {}, r"shot 'IMG_0001\.JPG' rotation must be a finite number; got nan"),
    ("notrans", {}, r"shot 'IMG_0002\.JPG' lacks rotation/translation"),
    ("badpoint", {}, r"point '100' lacks coordinates"),
    ("BLOCK", {"index": True}, r"reconstruction index True out of range"),
    ("camnotdict", {}, r"camera 'brown cam' must be an object; got 3"),
    ("perspnofocal", {}, r"camera 'persp cam' \(perspective\) lacks 'focal'"),
    ("perspzero", {}, r"camera 'persp cam' focal must be > 0; got 0\.0"),
    ("negfocal", {}, r"camera 'brown cam' focal_x and focal_y must be > 0; got -0\.85, -0\.85"),
    ("emptyname", {}, r"shot '': a pose needs a non-empty image name"),
    ("badgps", {}, r"shot 'IMG_0003\.JPG' gps_position must be a list of 3 numbers; got 'here'"),
    ("baddop", {}, r"shot 'IMG_0003\.JPG' gps_dop must be a finite number; got 'x'"),
    ("pointsnotdict", {}, r"reconstruction 0 'points' must be an object"),
    ("badref", {}, r"reference_lla must hold latitude, longitude and altitude; got \{'latitude': 1\.0\}"),
    ("farref", {}, r"reference_lla latitude 91\.0 / longitude 14\.0 out of range"),
])
def test_opensfm_bad_input(tmp_path, doc, kwargs, pattern):
    rec, _ = _synthetic_block()
    mutations = {
        "BLOCK": lambda r: None,
        "fisheye": lambda r: _cam(r, projection_type="fisheye", focal=0.8),
        "spherical": lambda r: _cam(r, projection_type="spherical"),
        "equirectangular": lambda r: _cam(r, projection_type="equirectangular"),
        "aspect": lambda r: _cam(r, focal_y=0.86),
        "nowidth": lambda r: _cam(r, width=0),
        "nofocal": lambda r: r["cameras"]["brown cam"].pop("focal_y"),
        "badk1": lambda r: _cam(r, k1="x"),
        "unknowncam": lambda r: r["shots"]["IMG_0000.JPG"].update(camera="nope"),
        "badrot": lambda r: r["shots"]["IMG_0001.JPG"].update(rotation=[0, 1]),
        "nanrot": lambda r: r["shots"]["IMG_0001.JPG"].update(rotation=[0, float("nan"), 1]),
        "notrans": lambda r: r["shots"]["IMG_0002.JPG"].pop("translation"),
        "badpoint": lambda r: r["points"]["100"].pop("coordinates"),
        "camnotdict": lambda r: r["cameras"].update({"brown cam": 3}),
        "perspnofocal": lambda r: r["cameras"]["persp cam"].pop("focal"),
        "perspzero": lambda r: r["cameras"]["persp cam"].update(focal=0.0),
        "negfocal": lambda r: _cam(r, focal_x=-0.85, focal_y=-0.85),
        "emptyname": lambda r: r["shots"].update({"": r["shots"]["IMG_0000.JPG"]}),
        "badgps": lambda r: r["shots"]["IMG_0003.JPG"].update(gps_position="here"),
        "baddop": lambda r: r["shots"]["IMG_0003.JPG"].update(gps_dop="x"),
        "pointsnotdict": lambda r: r.update(points=[1, 2]),
        "badref": lambda r: r.update(reference_lla={"latitude": 1.0}),
        "farref": lambda r: r.update(reference_lla={"latitude": 91.0, "longitude": 14.0, "altitude": 0.0}),
    }
    if isinstance(doc, str):
        doc = _with(rec, mutations[doc])
    p = tmp_path / "reconstruction.json"
    p.write_text(json.dumps(doc))
    with pytest.raises(InvalidInputError, match=r"'.*reconstruction\.json'.*" + pattern):
        read_opensfm(p, **kwargs)


def test_opensfm_unreadable(tmp_path):
    with pytest.raises(RasterIOError, match=r"cannot read OpenSfM reconstruction '.*missing\.json': file not found"):
        read_opensfm(tmp_path / "missing.json")
    p = tmp_path / "broken.json"
    p.write_text("[{")
    with pytest.raises(InvalidInputError, match=r"OpenSfM reconstruction '.*broken\.json' is not valid JSON"):
        read_opensfm(p)
    q = tmp_path / "reconstruction.json"
    q.write_text((DATA / "opensfm" / "reconstruction.json").read_text())
    (tmp_path / "reference_lla.json").write_text('{"latitude": 1.0}')
    with pytest.raises(InvalidInputError, match=r"'.*reference_lla\.json': the reference must hold latitude, "
                                                r"longitude and altitude"):
        read_opensfm(q)


def test_opensfm_partial_colours_and_no_points(tmp_path):
    rec, _ = _synthetic_block()
    del rec["points"]["105"]["color"]
    p = tmp_path / "r.json"
    p.write_text(json.dumps([rec]))
    r = read_opensfm(p)
    assert r.colors is None and r.points.shape == (40, 3)
    del rec["points"]
    p.write_text(json.dumps([rec]))
    r = read_opensfm(p)
    assert r.points.shape == (0, 3) and r.point_ids == () and r.colors is None


def test_pose_table_checks_sigma_shape():
    with pytest.raises(ShapeError, match=r"sigma must have shape \(1, 6\); got \(2, 6\)"):
        PoseTable((_pose("a", [0, 0, 0], [0, 0, 0]),), None, np.zeros((2, 6)), "deg", "omega-phi-kappa")


def test_camera_type_is_rectify_camera():
    r = read_opensfm(DATA / "opensfm" / "reconstruction.json")
    assert all(isinstance(c, Camera) for c in r.cameras.values())
