"""Issue 30, dense matching: the hole pass, the sub-pixel window, and the real-data figures with tolerances.

Figures measured with ``nice python scripts/bench_dense.py`` (docs/dense.md, "Figures measured"); the
tolerances leave room for OpenCV's thread scheduling and the shared machine, not for a lost method.
The shared-data tests skip when ``../shared/data`` (``$RECTIFY_SHARED_DATA``) is absent.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import rasterio

from rectify.errors import InvalidInputError
from rectify.geometry.camera import Camera
from rectify.geometry.rotation import matrix_from_angles
from stereo.actions.dense import DenseOptions, run_dense
from stereo.dense.matching import MatchOptions, _fill_holes_half, match_pair
from stereo.formats.orientation import write_exterior
from stereo.pair.resection import ExteriorOrientation
from tests.support.shared_data import SHARED_DATA
from tests.support.stereo_support import occlusion_from_truth

LO25 = "+proj=tmerc +lat_0=0 +lon_0=25 +k=1 +x_0=0 +y_0=0 +datum=WGS84 +units=m"
EO = {"0182": (-55094.504480, -3727407.037480, 5258.307930, -0.349216, 0.298484, -179.086702),
      "0184": (-57710.435280, -3727433.893020, 5256.764790, 0.269761, -0.281937, -179.027883)}
CAMERA = {"focal_length_mm": 120.0, "pixel_size_mm": 0.144, "width": 640, "height": 1152}


def _rgb(path: Path) -> np.ndarray:
    """An RGB PNG as (H, W, 3) uint8."""
    img = cv2.imread(str(path))
    assert img is not None, path
    return np.asarray(cv2.cvtColor(img, cv2.COLOR_BGR2RGB))


def _grey_png(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    assert img is not None, path
    return np.asarray(img)


def _texture(h: int, w: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    t = cv2.GaussianBlur(rng.normal(size=(h, w)).astype(np.float32), (0, 0), 1.2)
    return np.clip(128 + 60 * t / t.std(), 0, 255).astype(np.uint8)


def _pair(d: float, flat: tuple[slice, slice] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """A textured plane at disparity ``d`` (left(x) = right(x - d)); ``flat``: a constant patch in both."""
    H, W = 120, 200
    src = _texture(H, W + 40, 4)
    if flat is not None:
        src[flat] = 128
    xs = np.arange(W)[None, :].repeat(H, 0).astype(np.float32)
    ys = np.arange(H)[:, None].repeat(W, 1).astype(np.float32)
    L = np.ascontiguousarray(src[:, 20:W + 20])
    R = cv2.remap(src, xs + 20 + d, ys, cv2.INTER_CUBIC)
    return L, np.asarray(R)


def test_hole_pass_fills_a_textured_hole_with_the_right_disparity():
    """A 30 x 40 hole punched into a correct disparity map of a textured plane (d = 11.5 px) is
    filled by the half-resolution pass to within 1 px (before the sub-pixel step)."""
    L, R = _pair(11.5)
    H, W = L.shape
    d = np.full((H, W), 11.5, np.float32)
    d[40:70, 80:120] = np.nan
    ones = np.ones((H, W), bool)
    out = _fill_holes_half(d, L, R, ones, ones, 0, 24, MatchOptions(hole_p2=128.0))
    hole = out[40:70, 80:120]
    # measured 0.92: before the sub-pixel step the doubled half-resolution disparity is up to 0.5 px
    # off, which brings the 7 x 7 ZNCC of this fine texture below 0.5 at some pixels
    assert np.isfinite(hole).mean() >= 0.85, np.isfinite(hole).mean()
    assert np.nanmax(np.abs(hole - 11.5)) <= 1.0, np.nanmax(np.abs(hole - 11.5))
    # untouched elsewhere (and the masks too), and off by default
    np.testing.assert_array_equal(out[~np.isnan(d)], d[~np.isnan(d)])
    assert ones.all()
    assert np.isnan(_fill_holes_half(d, L, R, ones, ones, 0, 24, MatchOptions())[40:70, 80:120]).all()


def test_hole_pass_leaves_a_textureless_hole_empty():
    """Where both photos are constant nothing can be matched: the ZNCC test keeps such a hole empty
    (SGBM's own paths carry a disparity into it; the hole pass adds none)."""
    L, R = _pair(11.5, (slice(30, 90), slice(90, 160)))  # constant in the left photo at cols 70..140
    H, W = L.shape
    d = np.full((H, W), 11.5, np.float32)
    d[40:80, 80:130] = np.nan
    ones = np.ones((H, W), bool)
    out = _fill_holes_half(d, L, R, ones, ones, 0, 24, MatchOptions(hole_p2=128.0))
    assert not np.isfinite(out[40:80, 80:130]).any()
    res = match_pair(L, R, disparity_range=(0, 24), options=MatchOptions(hole_p2=128.0))
    assert np.abs(res.disparity[res.valid] - 11.5).max() < 1.0 and res.density > 0.6


def test_hole_options_bad_input():
    for kw, msg in ((dict(hole_p2=-1.0), "hole_p2"), (dict(hole_p2=float("nan")), "hole_p2"),
                    (dict(hole_p2=4.0), "hole_p2` must exceed"), (dict(hole_zncc=1.5), "hole_zncc"),
                    (dict(hole_p2=True), "hole_p2"), (dict(hole_zncc="0.3"), "hole_zncc")):
        with pytest.raises(InvalidInputError, match=msg):
            MatchOptions(**kw)
    assert DenseOptions().matching.hole_p2 == 128.0 and MatchOptions().hole_p2 == 0.0


def test_refine_window_default():
    """The sub-pixel step's window (issue 30: radius 6, was 3) and its result on a plane: unbiased."""
    assert MatchOptions().refine_radius == 6
    L, R = _pair(11.3)
    res = match_pair(L, R, disparity_range=(0, 24))
    e = res.disparity[res.valid] - 11.3
    assert abs(float(np.median(e))) < 0.03 and float(np.percentile(np.abs(e), 95)) < 0.15


def test_motorcycle_precision_not_below_the_recorded_figure():
    """Motorcycle: bad-2.0 2.61 % at 95.9 % density measured (2.64 % at 95.9 % before issue 30)."""
    from skimage import data

    left, right, gt = data.stereo_motorcycle()
    res = match_pair(left, right)
    m = ~occlusion_from_truth(gt)
    v = res.valid & m
    density, bad2 = v.sum() / m.sum(), (np.abs(res.disparity - gt) > 2)[v].mean()
    assert density >= 0.955 and bad2 <= 0.0275, (density, bad2)


@pytest.mark.shared
def test_cones_precision_at_the_previous_density():
    """Cones: bad-1.0 2.83 % at 95.3 % density; at the previous round's density (93.2 %, the most
    confident pixels) 2.26 %, against 2.76 % before issue 30 (the issue asks 10 % less: <= 2.48 %)."""
    d = SHARED_DATA / "dense_cones"
    if not d.is_dir():
        pytest.skip(f"shared data absent: {d}")
    L = _rgb(d / "left.png")
    R = _rgb(d / "right.png")
    with rasterio.open(d / "disp_left.tif") as ds:
        gt = ds.read(1)
    nocc = (_grey_png(d / "occlusion.png") > 0) & (gt > 0)
    res = match_pair(L, R)
    v = res.valid & nocc
    err = (np.abs(res.disparity - gt) > 1)[v]
    assert v.sum() / nocc.sum() >= 0.945 and err.mean() <= 0.031, (v.sum() / nocc.sum(), err.mean())
    n = int(round(0.932 * nocc.sum()))
    top = np.argsort(-res.confidence[v], kind="stable")[:n]
    assert err[top].mean() <= 0.0248, err[top].mean()


@pytest.mark.shared
def test_ngi_strip_dsm_coverage_and_rmse(ngi_pair, tmp_path):
    """The NGI strip DSM (aero-triangulated EOs, ``stereo dense`` defaults) against dem.tif: at least
    90 % of the overlap within 1.5 cells RMSE (issue 30; measured 91.0 % and 1.00 cells; before
    issue 30 87.1 % and 1.03 cells), and smoother than before (second-difference NMAD 1.17 m, was 1.67 m)."""
    cam = Camera.from_dict(CAMERA)
    paths = []
    for k, v in EO.items():
        eo = ExteriorOrientation(position=np.array(v[:3]), rotation=matrix_from_angles(*np.radians(v[3:])),
                                 focal_length_mm=120.0, crs=LO25)
        paths.append(write_exterior(tmp_path / f"eo_{k}.json", eo, camera=cam.to_dict()))
    r = run_dense(paths[0], ngi_pair / "3324c_2015_1004_05_0182_RGB.tif", ngi_pair / "3324c_2015_1004_05_0184_RGB.tif",
                  tmp_path / "out", right_orientation=paths[1],
                  options=DenseOptions(cloud_format="none", reference_dem=str(ngi_pair / "dem.tif"),
                                       measure_parallax=False))
    c = r.comparison
    assert c is not None
    assert c.coverage >= 0.90 and c.rmse <= 1.5 * r.dsm_cell, c.summary_line(cell=r.dsm_cell)
    assert c.rmse <= 1.15 * r.dsm_cell and c.nmad <= 4.0, c.summary_line(cell=r.dsm_cell)
    with rasterio.open(tmp_path / "out" / "dsm.tif") as ds:
        z = ds.read(1).astype(np.float64)
        z[z == ds.nodata] = np.nan
    s = np.concatenate([(a[:, 2:] - 2 * a[:, 1:-1] + a[:, :-2]).ravel() for a in (z, z.T)])
    s = s[np.isfinite(s)]
    rough = 1.4826 * np.median(np.abs(s - np.median(s)))
    assert rough <= 1.4, rough
