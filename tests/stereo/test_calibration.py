"""Camera calibration (issue 15): DLT, plane and 3D targets, camera JSON, bad input, the published calibration."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rectify.errors import CalibrationError, EstimationError, InvalidInputError
from rectify.formats.camera import intrinsics_document as camera_to_dict
from rectify.geometry.rotation import matrix_from_angles, rodrigues, rotvec_from_matrix
from stereo.calibration.dlt import DLT, interior_from_homographies
from stereo.calibration.model import Intrinsics
from stereo.calibration.result import Calibration
from stereo.calibration.views import TargetView
from stereo.features.targets import parse_pattern, parse_square
from stereo.formats.calibration import camera_from_dict, views_from_csv
from tests.support.calibration_synthetic import DEFAULT_CAMERA, board_scene, field_scene
from tests.support.scripts_support import load_script
from tests.support.shared_data import SHARED_DATA

SHARED = SHARED_DATA  # $RECTIFY_SHARED_DATA, else ../shared/data
TRUTH = DEFAULT_CAMERA


def _normalised_errors(cal: Calibration, truth: Intrinsics) -> dict[str, float]:
    return {n: (cal.value(n) - float(getattr(truth, n))) / cal.std_errors[n] for n in cal.names}


# ---------------------------------------------------------------------------- DLT
@settings(max_examples=40, deadline=None)
@given(fx=st.floats(200, 3000), aspect=st.floats(0.8, 1.25), skew=st.floats(-5, 5), cx=st.floats(100, 900),
       cy=st.floats(100, 700), om=st.floats(-1.2, 1.2), ph=st.floats(-1.2, 1.2), ka=st.floats(-3.1, 3.1),
       c=st.tuples(st.floats(-50, 50), st.floats(-50, 50), st.floats(-50, 50)))
def test_dlt_decomposition_round_trip(fx, aspect, skew, cx, cy, om, ph, ka, c):
    """P built from (K, R, C) decomposes back into the same K, R and C."""
    K = np.array([[fx, skew, cx], [0, fx * aspect, cy], [0, 0, 1.0]])
    R = matrix_from_angles(om, ph, ka)
    d = DLT.from_elements(K, R, np.array(c)).decompose()
    assert np.allclose(d.K, K, rtol=1e-9, atol=1e-7 * fx)
    assert np.allclose(d.rotation, R, atol=1e-9)
    assert np.allclose(d.centre, c, atol=1e-7 * (1 + np.abs(c).max()))


def test_dlt_from_points_exact_and_noisy():
    rng = np.random.default_rng(3)
    K = np.array([[900.0, 0.0, 310.0], [0.0, 905.0, 250.0], [0.0, 0.0, 1.0]])
    R = matrix_from_angles(0.1, -0.2, 0.3)
    C = np.array([0.5, -0.3, 6.0])
    X = rng.uniform(-2, 2, (40, 3))
    P = DLT.from_elements(K, R, C)
    d = DLT.from_points(X, P.project(X))
    assert d.rmse_px < 1e-8
    assert np.allclose(d.decompose().K, K, atol=1e-6)
    dn = DLT.from_points(X, P.project(X) + rng.normal(0, 0.3, (40, 2)))
    assert 0.15 < dn.rmse_px < 0.4
    assert abs(dn.decompose().fx - 900) < 20


def test_dlt_bad_input():
    X = np.random.default_rng(0).uniform(-1, 1, (10, 3))
    with pytest.raises(EstimationError, match="too few points for the DLT: 5 given"):
        DLT.from_points(X[:5], X[:5, :2])
    Xp = X.copy()
    Xp[:, 2] = 0.0
    with pytest.raises(EstimationError, match="coplanar"):
        DLT.from_points(Xp, X[:, :2])
    with pytest.raises(InvalidInputError, match="NaN"):
        DLT.from_points(np.full((8, 3), np.nan), np.zeros((8, 2)))


def test_rotation_vector_round_trip():
    rng = np.random.default_rng(1)
    for rv in rng.normal(0, 1.0, (20, 3)):
        assert np.allclose(rotvec_from_matrix(rodrigues(rv)[0]), rv, atol=1e-10) or np.linalg.norm(rv) > np.pi


# ---------------------------------------------------------------------- plane target
@pytest.fixture(scope="module")
def plane_cal():
    sc = board_scene(np.random.default_rng(11), n_views=8, noise_px=0.2)
    return sc, Calibration.from_views(sc.views, 640, 480)


def test_plane_target_recovers_truth(plane_cal):
    """Synthetic board, 8 views, 0.2 px noise: every element within 3 standard errors, RMS of the
    normalised errors below 2, sigma0 near the simulated noise."""
    sc, cal = plane_cal
    z = _normalised_errors(cal, TRUTH)
    assert max(abs(v) for v in z.values()) < 3.0, z
    assert float(np.sqrt(np.mean(np.square(list(z.values()))))) < 2.0, z
    assert 0.17 < cal.sigma0_px < 0.23
    assert cal.start_method == "homographies"
    lines = cal.summary_lines()
    assert lines[0].startswith("calibration: 8 views, 432 points")
    assert any(line.strip().startswith("fx = ") for line in lines)
    # exterior orientation: centres are at the simulated positions
    for v, pose in zip(cal.views, sc.poses, strict=True):
        Rcv = rodrigues(pose[:3])[0]
        assert np.allclose(v.centre, -Rcv.T @ pose[3:], atol=6 * v.std_centre.max() + 1e-6)


def test_plane_target_exact_data_is_exact():
    sc = board_scene(np.random.default_rng(5), n_views=5, noise_px=0.0)
    cal = Calibration.from_views(sc.views, 640, 480)
    assert cal.rms_px < 1e-6
    assert abs(cal.intrinsics.fx - TRUTH.fx) < 1e-4 and abs(cal.intrinsics.k1 - TRUTH.k1) < 1e-7


def test_symmetry_point_and_robust():
    """A separate point of symmetry is estimated and reported; Huber weights down-weight a gross error."""
    sc = board_scene(np.random.default_rng(2), n_views=3, noise_px=0.1)
    views = list(sc.views)
    px = views[0].pixel.copy()
    px[7] += [6.0, -4.0]
    views[0] = TargetView(views[0].name, views[0].object_xyz, px, views[0].ids)
    cal = Calibration.from_views(views, 640, 480, robust="tukey", distortion=("k1", "k2", "p1", "p2"))
    assert cal.views[0].weights[7] < 0.05
    assert abs(cal.intrinsics.fx - TRUTH.fx) < 4 * cal.std_errors["fx"]
    sym = Calibration.from_views(sc.views, 640, 480, symmetry=True, distortion=("k1", "k2"))
    assert "sx" in sym.names and sym.intrinsics.sx is not None
    assert sym.camera_dict()["point_of_symmetry_px"] == [sym.intrinsics.sx, sym.intrinsics.sy]


# ------------------------------------------------------------------------ 3D field
@pytest.mark.parametrize("n_views, n_points, seed", [(1, 100, 21), (3, 60, 22)])
def test_field_from_dlt_start(n_views, n_points, seed):
    """3D field, 0.3 px noise, DLT start only: RMS normalised error < 1.5 and each element within 3 std."""
    sc = field_scene(np.random.default_rng(seed), n_views=n_views, n_points=n_points, noise_px=0.3)
    cal = Calibration.from_views(sc.views, 640, 480, distortion=("k1", "k2", "p1", "p2"))
    assert cal.start_method.startswith("DLT")
    z = _normalised_errors(cal, TRUTH)
    assert max(abs(v) for v in z.values()) < 3.0, z
    assert float(np.sqrt(np.mean(np.square(list(z.values()))))) < 1.5, z


def test_from_points_single_image():
    sc = field_scene(np.random.default_rng(4), n_views=1, n_points=80, noise_px=0.1)
    v = sc.views[0]
    cal = Calibration.from_points(v.object_xyz, v.pixel, 640, 480, equal_focal=True, distortion=("k1",))
    assert cal.names == ("f", "cx", "cy", "k1")
    assert abs(cal.intrinsics.fx - 798.0) < 15


# ----------------------------------------------------------------------- bad input
def test_too_few_plane_views():
    sc = board_scene(np.random.default_rng(1), n_views=2)
    with pytest.raises(CalibrationError, match="too few views for a plane target: 2 given, at least 3"):
        Calibration.from_views(sc.views, 640, 480)


def test_parallel_views_focal_unobservable():
    sc = board_scene(np.random.default_rng(1), n_views=4, tilt_deg=(0, 0), noise_px=0.1)
    with pytest.raises(CalibrationError, match="focal length unobservable: all 4 views are parallel"):
        Calibration.from_views(sc.views, 640, 480)


def test_points_outside_image():
    sc = board_scene(np.random.default_rng(1), n_views=3)
    v = sc.views[1]
    px = v.pixel.copy()
    px[3] = [700.0, 20.0]
    views = [sc.views[0], TargetView(v.name, v.object_xyz, px, v.ids), sc.views[2]]
    with pytest.raises(InvalidInputError, match=r"view 'view01': point 'r0c3' at \(700.00, 20.00\) px is outside"):
        Calibration.from_views(views, 640, 480)


def test_other_bad_input():
    sc = board_scene(np.random.default_rng(1), n_views=3)
    with pytest.raises(CalibrationError, match="no views"):
        Calibration.from_views([], 640, 480)
    with pytest.raises(InvalidInputError, match="duplicate view name"):
        Calibration.from_views([sc.views[0], sc.views[0], sc.views[1]], 640, 480)
    with pytest.raises(InvalidInputError, match="width must be a positive integer"):
        Calibration.from_views(sc.views, 0, 480)
    with pytest.raises(InvalidInputError, match="unknown distortion"):
        Calibration.from_views(sc.views, 640, 480, distortion=("k9",))
    v = sc.views[0]
    with pytest.raises(CalibrationError, match="view 'tiny' has 3 points"):
        Calibration.from_views([TargetView("tiny", v.object_xyz[:3], v.pixel[:3], v.ids[:3])] + list(sc.views[1:]),
                               640, 480)
    with pytest.raises(InvalidInputError):
        parse_pattern("9by6")
    with pytest.raises(InvalidInputError):
        parse_square("-3mm")
    assert parse_square("2.5cm") == (25.0, "mm") and parse_pattern("9x6") == (9, 6)
    with pytest.raises(CalibrationError, match="principal distance is unobservable"):
        interior_from_homographies([np.eye(3)] * 3, 640, 480)


# ---------------------------------------------------------------------- camera JSON
@pytest.mark.parametrize("intr", [
    Intrinsics(fx=800.0, fy=796.0, cx=330.0, cy=228.0, width=640, height=480, k1=-0.1, p2=0.001),
    Intrinsics(fx=800.0, fy=800.0, cx=330.5, cy=228.25, width=640, height=480, k1=-0.1, k3=0.02, sx=331.0, sy=229.0),
])
def test_camera_json_round_trip_pixels(intr):
    d = camera_to_dict(intr, std_errors={"fx": 1.5, "cx": 0.7, "k1": 0.01}, sigma0_px=0.12)
    back = camera_from_dict(json.loads(json.dumps(d)))
    assert back.intrinsics == intr
    assert back.sigma0_px == 0.12 and back.std_errors["cx_px"] == 0.7
    assert d["format"] == "rectify-stereo/camera" and d["version"] == 2


def test_camera_json_round_trip_mm_and_v1():
    intr = Intrinsics(fx=1000.0, fy=1000.0, cx=330.0, cy=228.0, width=640, height=480, k1=-0.1)
    d = camera_to_dict(intr, std_errors={"f": 2.0, "cx": 1.0}, pixel_size_mm=0.005)
    assert d["focal_length_mm"] == pytest.approx(5.0) and d["std_errors"]["focal_length_mm"] == pytest.approx(0.01)
    assert d["principal_point_mm"] == pytest.approx([(330 - 319.5) * 0.005, -(228 - 239.5) * 0.005])
    back = camera_from_dict(d).intrinsics
    assert back.fx == pytest.approx(1000.0) and back.cx == pytest.approx(330.0) and back.cy == pytest.approx(228.0)
    v1 = {"focal_length_mm": 120.0, "pixel_size_mm": 0.144, "width": 640, "height": 1152}
    assert camera_from_dict(v1).intrinsics.cx == pytest.approx(319.5)
    with pytest.raises(InvalidInputError, match="square pixels"):
        camera_to_dict(Intrinsics(fx=1.0, fy=2.0, cx=0, cy=0, width=2, height=2), pixel_size_mm=0.01)
    with pytest.raises(CalibrationError, match=r"unknown key\(s\) \['bogus'\]"):
        camera_from_dict({**d, "bogus": 1})
    with pytest.raises(CalibrationError, match="needs focal_length_px"):
        camera_from_dict({"width": 10, "height": 10, "principal_point_px": [1, 1]})


def test_calibration_camera_dict_reads_back(plane_cal):
    _, cal = plane_cal
    back = camera_from_dict(cal.camera_dict())
    assert np.allclose(back.intrinsics.vector, cal.intrinsics.vector)
    assert back.std_errors["fx_px"] == cal.std_errors["fx"]


# ------------------------------------------------------------------------ CSV files
def test_csv_views(tmp_path):
    sc = field_scene(np.random.default_rng(9), n_views=2, n_points=30)
    obs = ["view,point,col,row"] + [f"{v.name},{p},{c},{r}" for v in sc.views
                                    for p, (c, r) in zip(v.ids, v.pixel, strict=True)]
    v0 = sc.views[0]
    field = ["point,x,y,z"] + [f"{p},{x},{y},{z}" for p, (x, y, z) in zip(v0.ids, v0.object_xyz, strict=True)]
    (tmp_path / "obs.csv").write_text("\n".join(obs) + "\n")
    (tmp_path / "field.csv").write_text("\n".join(field) + "\n")
    views = views_from_csv(tmp_path / "obs.csv", tmp_path / "field.csv")
    assert [v.name for v in views] == ["img0", "img1"] and np.allclose(views[1].pixel, sc.views[1].pixel)
    (tmp_path / "f2.csv").write_text("\n".join(field[:-3]) + "\n")
    with pytest.raises(CalibrationError, match="3 measured point"):
        views_from_csv(tmp_path / "obs.csv", tmp_path / "f2.csv")
    (tmp_path / "bad.csv").write_text("view,point,col\na,b,1\n")
    with pytest.raises(InvalidInputError, match=r"lacks column\(s\) \['row'\]"):
        views_from_csv(tmp_path / "bad.csv", tmp_path / "field.csv")


# ------------------------------------------------------------ the published calibration
@pytest.mark.shared
def test_published_calibration_calib1():
    """Bouguet's calib1.dat: fc, cc, kc and the pixel error reproduced (k3 fixed at 0, as published)."""
    p = SHARED / "calibration_reference" / "calib1.dat"
    if not p.is_file():
        pytest.skip(f"published calibration not found at {p}")
    data = load_script("calib1_bouguet").read_calib1(p)
    ref = [float(v) for v in data.published]
    cal = Calibration.from_views(data.views, data.width, data.height, distortion=("k1", "k2", "p1", "p2"))
    i = cal.intrinsics
    assert [round(i.fx, 2), round(i.fy, 2), round(i.cx, 2), round(i.cy, 2)] == [809.95, 806.56, 362.00, 214.40]
    assert abs(i.fx - ref[0]) < 0.002 and abs(i.fy - ref[1]) < 0.002
    assert abs(i.cx - ref[2]) < 0.001 and abs(i.cy - ref[3]) < 0.001
    assert [round(v, 5) for v in (i.k1, i.k2, i.p1, i.p2)] == pytest.approx(ref[4:8], abs=5e-5)
    assert [round(float(s), 5) for s in cal.pixel_error_std] == ref[8:10]
    # the toolbox prints 3 x its standard error; its standard errors are 0.5 x ours (OpenCV's equal ours)
    assert cal.std_errors["fx"] == pytest.approx(9.48 / 1.5, rel=0.01)
    assert cal.std_errors["cy"] == pytest.approx(13.28 / 1.5, rel=0.01)


@pytest.mark.shared
def test_real_chessboard_against_opencv():
    """Real views (8 of the chessboard samples): RMS <= OpenCV's on the same corners, interior within 0.01
    standard error of OpenCV's, standard errors equal to OpenCV's stdDeviationsIntrinsics within 1%."""
    import cv2

    from stereo.features.targets import Chessboard, detect_chessboards

    folder = SHARED / "calibration_chessboard"
    paths = sorted(folder.glob("left*.jpg"))[:8]
    if len(paths) < 8:
        pytest.skip(f"chessboard views not found under {folder}")
    views, missing, size = detect_chessboards(paths, Chessboard(9, 6, 1.0))
    assert not missing and size == (640, 512)
    # both adjustments see the same corners: OpenCV takes float32 pixels
    views = [TargetView(v.name, v.object_xyz, v.pixel.astype(np.float32), v.ids) for v in views]
    cal = Calibration.from_views(views, *size)
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-15)
    r = cv2.calibrateCameraExtended([v.object_xyz.astype(np.float32) for v in views],
                                    [v.pixel.astype(np.float32).reshape(-1, 1, 2) for v in views], size, None, None,
                                    criteria=crit)  # type: ignore[call-overload]
    rms, K, d, std = r[0], r[1], r[2].ravel(), r[5].ravel()
    assert cal.rms_px <= rms * (1 + 1e-9)
    cv_vals = {"fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2], "k1": d[0], "k2": d[1], "p1": d[2],
               "p2": d[3], "k3": d[4]}
    cv_std = dict(zip(("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3"), std[:9], strict=True))
    for n in cal.names:
        assert abs(cal.value(n) - cv_vals[n]) < 0.01 * cal.std_errors[n], n
        assert cal.std_errors[n] == pytest.approx(cv_std[n], rel=0.01), n


def test_detect_chessboards_bad_input(tmp_path):
    import cv2

    from rectify.errors import RasterIOError
    from stereo.features.targets import Chessboard, detect_chessboards

    (tmp_path / "junk.png").write_text("not an image")
    with pytest.raises(RasterIOError, match="cannot read image"):
        detect_chessboards([tmp_path / "junk.png"], Chessboard(9, 6))
    cv2.imwrite(str(tmp_path / "a.png"), np.zeros((40, 60), np.uint8))
    cv2.imwrite(str(tmp_path / "b.png"), np.zeros((50, 60), np.uint8))
    with pytest.raises(InvalidInputError, match="'b.png' is 60 x 50 px, the first was 60 x 40"):
        detect_chessboards([tmp_path / "a.png", tmp_path / "b.png"], Chessboard(9, 6))
    views, missing, size = detect_chessboards([tmp_path / "a.png"], Chessboard(9, 6))
    assert views == [] and missing == ["a.png"] and size == (60, 40)
    with pytest.raises(InvalidInputError, match="at least 2 x 2"):
        Chessboard(1, 6)
