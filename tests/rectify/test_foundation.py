"""Errors, point validation, camera, rotations, residual tables, tables, atomic files."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.testing import assert_allclose

from rectify import errors
from rectify.atomic import atomic_output, atomic_write_text, check_output
from rectify.formats.camera import read_camera
from rectify.formats.gcps import read_gcps, write_gcps
from rectify.formats.tables import read_control, read_matches, write_matches
from rectify.geometry.camera import Camera
from rectify.geometry.points import (
    Matches,
    as_pair,
    as_points,
    check_distinct,
    check_no_three_collinear,
    check_not_collinear,
)
from rectify.geometry.residuals import ResidualTable
from rectify.geometry.rotation import (
    ORDERS,
    angles_from_matrix,
    check_rotation,
    matrix_from_angles,
    rot_x,
    rot_y,
    rot_z,
)

angle = st.floats(-3.0, 3.0)
mid_angle = st.floats(-1.5, 1.5)


# ------------------------------------------------------------------ errors
def test_error_tree_mixes_builtins():
    assert issubclass(errors.InvalidInputError, ValueError)
    assert issubclass(errors.ShapeError, errors.InvalidInputError)
    assert issubclass(errors.RasterIOError, OSError)
    assert issubclass(errors.CRSError, ValueError)
    assert issubclass(errors.ConvergenceError, errors.EstimationError)
    assert issubclass(errors.CalibrationError, errors.StereoError)
    for name in errors.__all__:
        cls = getattr(errors, name)
        assert issubclass(cls, (errors.RectifyError, errors.RectifyWarning))


# ------------------------------------------------------------------ points
def test_as_points_copies_and_validates():
    a = np.array([[1, 2], [3, 4]], dtype=np.int32)
    p = as_points(a)
    assert p.dtype == np.float64 and p.flags.c_contiguous
    p[0, 0] = 99
    assert a[0, 0] == 1
    assert as_points([5.0, 6.0]).shape == (1, 2)
    assert as_points([]).shape == (0, 2)


@pytest.mark.parametrize("bad, exc, text", [
    (np.zeros((5, 3)), errors.ShapeError, "(N, 2); got (5, 3)"),
    (np.zeros((2, 2, 2)), errors.ShapeError, "got (2, 2, 2)"),
    ([[1.0, np.nan]], errors.InvalidInputError, "non-finite"),
    ([[1.0, np.inf], [0, 0]], errors.InvalidInputError, "row 0"),
    ([["a", "b"]], errors.InvalidInputError, "numeric"),
])
def test_as_points_rejects(bad, exc, text):
    with pytest.raises(exc, match=None) as ei:
        as_points(bad, "src")
    assert text in str(ei.value)


def test_as_points_empty_not_allowed():
    with pytest.raises(errors.InvalidInputError, match="empty"):
        as_points(np.zeros((0, 2)), allow_empty=False)


def test_as_pair_length_mismatch():
    with pytest.raises(errors.ShapeError, match="same number of points; got 3 and 2"):
        as_pair(np.zeros((3, 2)), np.zeros((2, 2)))


def test_degeneracy_checks():
    with pytest.raises(errors.EstimationError, match="duplicate"):
        check_distinct(np.array([[0.0, 0], [1, 1], [0, 0]]))
    with pytest.raises(errors.EstimationError, match="collinear"):
        check_not_collinear(np.array([[0.0, 0], [1, 1], [2, 2], [3, 3]]))
    with pytest.raises(errors.EstimationError, match="rows 0, 1, 2"):
        check_no_three_collinear(np.array([[0.0, 0], [1, 1], [2, 2], [0, 5]]))
    check_no_three_collinear(np.array([[0.0, 0], [10, 0], [10, 10], [0, 10]]))


# ------------------------------------------------------------------ camera
NGI = dict(focal_length_mm=120.0, pixel_size_mm=0.144, width=640, height=1152)


def test_camera_centre_is_principal_point():
    cam = Camera(**NGI)
    assert_allclose(cam.photo_from_pixel([[319.5, 575.5]]), [[0.0, 0.0]], atol=1e-12)
    # top-left pixel centre: left (x < 0) and up (y > 0)
    assert_allclose(cam.photo_from_pixel([[0.0, 0.0]]), [[-319.5 * 0.144, 575.5 * 0.144]])


def test_camera_matches_ngi_projection_formula():
    # ../shared/data README: col = (W-1)/2 + x_mm/0.144 ; row = (H-1)/2 - y_mm/0.144
    cam = Camera(**NGI)
    mm = np.array([[10.0, -20.0], [-30.5, 44.0]])
    px = cam.pixel_from_photo(mm)
    assert_allclose(px[:, 0], 319.5 + mm[:, 0] / 0.144)
    assert_allclose(px[:, 1], 575.5 - mm[:, 1] / 0.144)


def test_camera_principal_point_offset():
    cam = Camera(**NGI, principal_point_mm=(0.144, -0.288))
    assert_allclose(cam.principal_point_px, [320.5, 577.5])
    assert_allclose(cam.photo_from_pixel(cam.principal_point_px), [[0, 0]], atol=1e-12)


def test_camera_distortion_matches_opencv_and_round_trips():
    import cv2
    cam = Camera(**NGI, distortion={"k1": -0.05, "k2": 0.01, "p1": 1e-3, "p2": -5e-4, "k3": 0.001})
    rng = np.random.default_rng(1)
    mm = rng.uniform([-40, -80], [40, 80], size=(50, 2))
    px = cam.pixel_from_photo(mm)
    # OpenCV projects ideal normalised points with the same coefficients
    n = np.column_stack([mm[:, 0], -mm[:, 1], np.full(50, 120.0)]) / 120.0
    ref, _ = cv2.projectPoints(n, np.zeros(3), np.zeros(3), cam.K, cam.dist_coeffs)
    assert_allclose(px, ref.reshape(-1, 2), atol=1e-6)
    assert_allclose(cam.photo_from_pixel(px), mm, atol=1e-9)


def test_camera_rays():
    cam = Camera(**NGI)
    r = cam.rays_from_pixel([[319.5, 575.5]])
    assert_allclose(r, [[0, 0, -120.0]])


@pytest.mark.parametrize("kw, text", [
    (dict(focal_length_mm=-1), "focal_length_mm"),
    (dict(pixel_size_mm=float("nan")), "pixel_size_mm"),
    (dict(width=0), "width"),
    (dict(height=2.5), "height"),
    (dict(distortion={"k9": 1.0}), "k9"),
    (dict(principal_point_mm=(1.0,)), "principal_point_mm"),
])
def test_camera_rejects_bad_values(kw, text):
    with pytest.raises(errors.CalibrationError, match=text):
        Camera(**{**NGI, **kw})


def test_camera_json_round_trip(tmp_path):
    cam = Camera(**NGI, principal_point_mm=(0.01, -0.02), distortion={"k1": 0.1})
    p = tmp_path / "cam.json"
    p.write_text(json.dumps(cam.to_dict()))
    back = read_camera(p)
    assert back.to_dict() == cam.to_dict()
    p.write_text('{"focal_length_mm": 1}')
    with pytest.raises(errors.CalibrationError, match="lacks required"):
        read_camera(p)
    p.write_text("{not json")
    with pytest.raises(errors.InvalidInputError, match="not valid JSON"):
        read_camera(p)
    with pytest.raises(errors.RasterIOError, match="cannot read"):
        read_camera(tmp_path / "missing.json")


# ---------------------------------------------------------------- rotation
def test_elementary_rotations_are_right_handed():
    assert_allclose(rot_z(np.pi / 2) @ [1, 0, 0], [0, 1, 0], atol=1e-15)
    assert_allclose(rot_x(np.pi / 2) @ [0, 1, 0], [0, 0, 1], atol=1e-15)
    assert_allclose(rot_y(np.pi / 2) @ [0, 0, 1], [1, 0, 0], atol=1e-15)


def test_seed000_eq1_element_by_element():
    # seed 000, eq. (1): a1 = cos(alpha) cos(chi), a2 = -cos(alpha) sin(chi), a3 = sin(alpha),
    # c3 = cos(omega) cos(alpha)
    om, al, ch = 0.11, -0.23, 0.37
    R = matrix_from_angles(om, al, ch, "omega-alpha-chi")
    assert_allclose(R[0], [np.cos(al) * np.cos(ch), -np.cos(al) * np.sin(ch), np.sin(al)])
    assert_allclose(R[2, 2], np.cos(om) * np.cos(al))
    assert_allclose(R[1, 2], -np.sin(om) * np.cos(al))
    assert_allclose(R, matrix_from_angles(om, al, ch, "omega-phi-kappa"))


def test_phi_omega_kappa_product():
    R = matrix_from_angles(0.2, 0.1, -0.4, "phi-omega-kappa")
    assert_allclose(R, rot_y(0.2) @ rot_x(0.1) @ rot_z(-0.4))


@settings(max_examples=200, deadline=None)
@given(a=angle, b=mid_angle, c=angle, order=st.sampled_from(sorted(ORDERS)))
def test_angles_round_trip(a, b, c, order):
    R = matrix_from_angles(a, b, c, order)
    assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    back = angles_from_matrix(R, order)
    assert_allclose(matrix_from_angles(*back, order), R, atol=1e-10)
    assert_allclose(back, [a, b, c], atol=1e-7)


def test_rotation_vectorised_and_checks():
    a = np.linspace(-1, 1, 7)
    R = matrix_from_angles(a, a / 2, -a, "omega-phi-kappa")
    assert R.shape == (7, 3, 3)
    assert_allclose(angles_from_matrix(R)[:, 0], a)
    with pytest.raises(errors.ShapeError):
        angles_from_matrix(np.eye(2))
    with pytest.raises(errors.InvalidInputError, match="not a proper rotation"):
        check_rotation(np.diag([1.0, 1.0, -1.0]))
    with pytest.raises(errors.InvalidInputError, match="unknown rotation order"):
        matrix_from_angles(0, 0, 0, "xyz")


# ----------------------------------------------------------- residual table
def test_residual_table_summary():
    obs = np.zeros((5, 2))
    adj = np.array([[3.0, 4.0], [0, 0], [0, 0], [0, 0], [6.0, 8.0]])
    t = ResidualTable("fit", ["a", "b", "c", "d", "e"], obs, adj, "px", n_params=2,
                      check=[False, False, False, False, True])
    s = t.summary()
    assert s["n_fit"] == 4 and s["n_check"] == 1
    assert s["rmse"] == pytest.approx(np.sqrt(25 / 4))
    assert s["rmse_check"] == pytest.approx(10.0)
    # sigma0 = sqrt(v'v / (8 - 2))
    assert t.sigma0 == pytest.approx(np.sqrt(25 / 6))
    text = t.to_csv()
    assert "norm" in text.splitlines()[1] and text.count("\n") == 7
    assert "check" in t.format_text()
    with pytest.raises(ValueError):
        t.observed[0, 0] = 1.0
    with pytest.raises(errors.ShapeError):
        ResidualTable("x", ["a"], np.zeros((2, 2)), np.zeros((2, 2)), "px")


def test_residual_table_without_redundancy_says_so():
    t = ResidualTable("exact", ["a", "b"], np.zeros((2, 2)), np.zeros((2, 2)), "m", n_params=4)
    assert np.isnan(t.sigma0)
    line = t.summary_line()
    assert "sigma0 undefined (no redundancy: 4 observations, 4 parameters)" in line
    assert "nan" not in line


# ------------------------------------------------------------------- tables
def test_gcp_csv_round_trip(tmp_path):
    p = tmp_path / "g.csv"
    p.write_text("# crs=EPSG:32618\nid,col,row,x,y,check\n1,0,0,100,200,0\n2,10.5,3,110,190,1\n"
                 "3,4,9,105,180,0\n")
    g = read_gcps(p)
    assert g.crs == "EPSG:32618" and g.ids == ("1", "2", "3")
    assert g.check.tolist() == [False, True, False]
    assert len(g.fit) == 2
    out = write_gcps(tmp_path / "h.csv", g)
    g2 = read_gcps(out)
    assert_allclose(g2.pixel, g.pixel)
    assert g2.crs == g.crs == "EPSG:32618"
    with pytest.raises(errors.InvalidInputError, match="exists"):
        write_gcps(out, g)


def test_qgis_points_convention(tmp_path):
    p = tmp_path / "g.points"
    p.write_text("#CRS: EPSG:4326\nmapX,mapY,sourceX,sourceY,enable,dX,dY,residual\n"
                 "10,20,0.5,-0.5,1,0,0,0\n11,21,100.5,-50.5,0,0,0,0\n")
    g = read_gcps(p)
    assert_allclose(g.pixel, [[0, 0], [100, 50]])
    assert g.check.tolist() == [False, True]


@pytest.mark.parametrize("content, text", [
    ("id,col,row,x\n1,2,3,4\n", "missing column"),
    ("id,col,row,x,y\n1,2,zz,4,5\n", "line 2: column 'row' is not a number"),
    ("id,col,row,x,y\n1,2,3,4,5\n1,2,3,4,5\n", "duplicate GCP id"),
    ("id,col,row,x,y\n", "no GCP rows"),
    ("", "no header"),
    ("id,col,row,x,y\n1,2,nan,4,5\n", "not finite"),
])
def test_gcp_csv_errors(tmp_path, content, text):
    p = tmp_path / "g.csv"
    p.write_text(content)
    with pytest.raises(errors.InvalidInputError, match=text):
        read_gcps(p)


def test_unreadable_files(tmp_path):
    with pytest.raises(errors.RasterIOError, match="not found"):
        read_gcps(tmp_path / "nope.csv")
    b = tmp_path / "bin.csv"
    b.write_bytes(b"\xff\xfe\x00\x81")
    with pytest.raises(errors.RasterIOError):
        read_matches(b)


def test_matches_and_control(tmp_path):
    m = Matches(("1", "2"), np.array([[1.0, 2], [3, 4]]), np.array([[5.0, 6], [7, 8]]), np.array([0.5, 0.9]))
    p = write_matches(tmp_path / "m.csv", m)
    back = read_matches(p)
    assert_allclose(back.right, m.right)
    assert back.score is not None
    assert_allclose(back.score, m.score)
    c = tmp_path / "c.csv"
    c.write_text("id,col_left,row_left,col_right,row_right,x,y,z\n1,1,2,3,4,10,20,30\n2,1,2,3,4,,,\n")
    ct = read_control(c)
    assert ct.is_control.tolist() == [True, False]
    c.write_text("id,col_left,row_left,col_right,row_right,x,y,z\n1,1,2,3,4,10,,30\n")
    with pytest.raises(errors.InvalidInputError, match="all given or all empty"):
        read_control(c)


# ---------------------------------------------------------------- fileutil
def test_atomic_output_leaves_nothing_on_error(tmp_path):
    dst = tmp_path / "out.txt"
    with pytest.raises(RuntimeError):
        with atomic_output(dst) as tmp:
            tmp.write_text("half")
            raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []
    atomic_write_text(dst, "ok")
    assert dst.read_text() == "ok"
    with pytest.raises(errors.InvalidInputError, match="--overwrite"):
        atomic_write_text(dst, "again")
    atomic_write_text(dst, "again", overwrite=True)
    assert dst.read_text() == "again"
    with pytest.raises(errors.RasterIOError, match="does not exist"):
        check_output(tmp_path / "no" / "x.txt", overwrite=False)


def test_ids_and_masks():
    from rectify.geometry.points import as_ids, as_mask

    assert as_ids(None, 3) == ("1", "2", "3")
    assert as_ids([7, "a"], 2) == ("7", "a")
    with pytest.raises(errors.ShapeError, match="must have 3 entries .*got 2"):
        as_ids(["a", "b"], 3)
    src = [True, False]
    m = as_mask(src, 2, "check")
    m[1] = True
    assert src == [True, False]  # a copy
    assert not as_mask(None, 4).any()
    with pytest.raises(errors.ShapeError, match=r"`check` must have shape \(3,\); got \(2,\)"):
        as_mask([1, 0], 3, "check")


def test_read_json_errors(tmp_path):
    from rectify.atomic import read_json

    p = tmp_path / "a.json"
    p.write_text('{"k": [1, 2]}')
    assert read_json(p) == {"k": [1, 2]}
    with pytest.raises(errors.RasterIOError, match="cannot read camera file .*file not found"):
        read_json(tmp_path / "missing.json", "camera file")
    p.write_text("{oops")
    with pytest.raises(errors.InvalidInputError, match="transform file .* is not valid JSON"):
        read_json(p, "transform file")
