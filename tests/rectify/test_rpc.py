"""RPC model (issue 16): readers, projection and localisation against GDAL's RPC transformer,
the pixel convention, DEM localisation, refinement. Tolerances: 1e-3 px / 1e-3 m against GDAL
(measured: ~1e-9 px, ~1e-9 m at a height, ~3e-7 m on a DEM)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rectify.errors import ConvergenceError, EstimationError, InvalidInputError, RasterIOError, ShapeError
from rectify.formats.rpc import read_rpc
from rectify.geometry.rpc import GDAL_PIXEL_OFFSET, RPC, RPCRefinement, fit_rpc
from tests.support.shared_data import SHARED_DATA

SHARED = SHARED_DATA  # $RECTIFY_SHARED_DATA, else ../shared/data
M_PER_DEG = 111_320.0


def synthetic_rpc() -> RPC:
    """A pushbroom-like RPC: 2000 x 1500 px, about 0.5 m pixels, off-nadir (height moves the column)."""
    return RPC.from_coefficients(
        offsets=(750.0, 1000.0, 45.0, 7.0, 300.0), scales=(750.0, 1000.0, 0.004, 0.006, 500.0),
        samp_num=[0.001, 1.02, 0.03, 0.08, 0.002, 0.001, 0.0, 0.004, 0.001, 0.0, 0.0, 1e-4],
        samp_den=[1.0, 0.002, -0.001, 0.0005],
        line_num=[-0.002, -0.02, -0.99, 0.01, 0.003, 0.0, 0.001, 0.0, 0.002],
        line_den=[1.0, 0.0, 0.001, -0.0004])


def gdal_transformer(rpc: RPC, **opts):
    from rasterio.transform import RPCTransformer

    return RPCTransformer(rpc.to_rasterio(), RPC_PIXEL_ERROR_THRESHOLD=1e-9, RPC_MAX_ITERATIONS=200, **opts)


def gdal_rowcol(rpc: RPC, g: np.ndarray, **opts) -> np.ndarray:
    from rasterio.transform import TransformDirection

    with gdal_transformer(rpc, **opts) as t:
        c, r = t._transform(g[:, 0], g[:, 1], g[:, 2], transform_direction=TransformDirection.reverse)
    return np.column_stack([c, r])


def gdal_lonlat(rpc: RPC, gdal_px: np.ndarray, h: np.ndarray, **opts) -> np.ndarray:
    import warnings

    from rasterio.errors import TransformWarning
    from rasterio.transform import TransformDirection

    with gdal_transformer(rpc, **opts) as t, warnings.catch_warnings():
        warnings.simplefilter("ignore", TransformWarning)  # GDAL gives up on some points (counted by the caller)
        x, y = t._transform(gdal_px[:, 0], gdal_px[:, 1], h, transform_direction=TransformDirection.forward)
    return np.column_stack([x, y])


def metres(dlonlat: np.ndarray, lat: np.ndarray) -> np.ndarray:
    return np.hypot(dlonlat[:, 0] * M_PER_DEG * np.cos(np.radians(lat)), dlonlat[:, 1] * M_PER_DEG)


def image_samples(rpc: RPC, n: int = 300, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    px = np.column_stack([rpc.samp_off + abs(rpc.samp_scale) * rng.uniform(-1, 1, n),
                          rpc.line_off + abs(rpc.line_scale) * rng.uniform(-1, 1, n)])
    h = rpc.height_off + abs(rpc.height_scale) * rng.uniform(-1, 1, n)
    return px, h


def check_against_gdal(rpc: RPC) -> dict:
    """Localise image samples with ours, compare projection and localisation with GDAL."""
    px, h = image_samples(rpc)
    g = rpc.localize(px, h)
    assert np.abs(rpc.project(g) - px).max() < 1e-6
    gd = gdal_rowcol(rpc, g) - GDAL_PIXEL_OFFSET
    proj_err = np.abs(gd - px).max()
    ll = gdal_lonlat(rpc, px + GDAL_PIXEL_OFFSET, h)
    ok = np.isfinite(ll).all(axis=1)
    loc_err = metres(ll[ok] - g[ok, :2], g[ok, 1]).max()
    return {"proj_px": proj_err, "loc_m": loc_err, "gdal_failed": int((~ok).sum()), "n": len(px)}


# ----------------------------------------------------------------- synthetic (always run)
def test_gdal_half_pixel_convention():
    """GDAL's RPC transformer pixel/line = our (col, row) + 0.5: its (0, 0) is the top-left pixel corner."""
    rpc = synthetic_rpc()
    g = rpc.localize([[0.0, 0.0], [1999.0, 1499.0], [1000.0, 750.0]], [300.0, 300.0, 300.0])
    d = gdal_rowcol(rpc, g) - rpc.project(g)
    assert np.allclose(d, 0.5, atol=1e-9)
    assert GDAL_PIXEL_OFFSET == 0.5


def test_synthetic_agrees_with_gdal():
    res = check_against_gdal(synthetic_rpc())
    assert res["gdal_failed"] == 0
    assert res["proj_px"] < 1e-3
    assert res["loc_m"] < 1e-3


def test_fitted_rpc_agrees_with_gdal_and_physical_model():
    """An RPC fitted to a tilted frame geometry reproduces it to < 0.01 px and agrees with GDAL."""
    lon0, lat0 = 10.0, 45.0

    def frame(g):
        e = (g[:, 0] - lon0) * M_PER_DEG * np.cos(np.radians(lat0))
        n = (g[:, 1] - lat0) * M_PER_DEG
        z = g[:, 2] - 600_000.0
        x = e + 0.3 * z * 0.0 - 0.25 * (g[:, 2])  # off-nadir: height shifts the column
        return np.column_stack([1000 + x / 0.7, 800 - n / 0.7])

    box = ((lon0 - 0.01, lon0 + 0.01), (lat0 - 0.008, lat0 + 0.008), (0.0, 1000.0))
    rpc = fit_rpc(frame, box)
    g = np.column_stack([np.full(5, lon0 + 0.003), np.full(5, lat0 - 0.002), np.linspace(0, 1000, 5)])
    assert np.abs(rpc.project(g) - frame(g)).max() < 1e-2
    res = check_against_gdal(rpc)
    assert res["proj_px"] < 1e-3 and res["loc_m"] < 1e-3


@settings(max_examples=60, deadline=None)
@given(u=st.floats(-1, 1), v=st.floats(-1, 1), w=st.floats(-1, 1))
def test_localize_inverts_project(u, v, w):
    rpc = synthetic_rpc()
    g = np.array([[rpc.long_off + u * rpc.long_scale, rpc.lat_off + v * rpc.lat_scale,
                   rpc.height_off + w * rpc.height_scale]])
    back = rpc.localize(rpc.project(g), g[:, 2])
    assert metres(back[:, :2] - g[:, :2], g[:, 1]).max() < 1e-6
    assert back[0, 2] == g[0, 2]


def test_localize_converges_on_the_whole_image_and_beyond():
    rpc = synthetic_rpc()
    c, r = np.meshgrid(np.linspace(-500, 2500, 31), np.linspace(-400, 1900, 24))
    px = np.column_stack([c.ravel(), r.ravel()])
    for h in (-200.0, 300.0, 800.0):
        g = rpc.localize(px, h)
        assert np.abs(rpc.project(g) - px).max() < 1e-6


def _write_dem(path: Path, rpc: RPC, z0: float = 300.0, amp: float = 60.0) -> None:
    import rasterio
    from affine import Affine

    (x0, x1), (y0, y1), _ = rpc.validity_box
    res = (x1 - x0) / 150
    w, h = int((x1 - x0) / res) + 20, int((y1 - y0) / res) + 20
    yy, xx = np.mgrid[0:h, 0:w]
    z = z0 + amp * np.sin(xx / 17.0) * np.cos(yy / 11.0) + 0.5 * xx
    with rasterio.open(path, "w", driver="GTiff", width=w, height=h, count=1, dtype="float32", crs="EPSG:4326",
                       transform=Affine(res, 0, x0 - 10 * res, 0, -res, y1 + 10 * res)) as ds:
        ds.write(z.astype("float32"), 1)


def test_localize_on_dem_agrees_with_gdal_rpc_dem(tmp_path):
    from rectify.raster.dem import Dem

    rpc = synthetic_rpc()
    _write_dem(tmp_path / "dem.tif", rpc)
    dem = Dem.from_path(tmp_path / "dem.tif")
    px, _ = image_samples(rpc, 150, seed=3)
    g = rpc.localize_on_dem(px, dem.lonlat_function(), h_range=(100.0, 600.0))
    assert np.abs(g[:, 2] - dem.sample(g[:, :2])).max() < 1e-3
    ll = gdal_lonlat(rpc, px + GDAL_PIXEL_OFFSET, np.zeros(len(px)), RPC_DEM=str(tmp_path / "dem.tif"))
    assert np.isfinite(ll).all()
    assert metres(ll - g[:, :2], g[:, 1]).max() < 1e-3


def test_localize_on_dem_clear_error_outside(tmp_path):
    from rectify.raster.dem import Dem

    rpc = synthetic_rpc()
    _write_dem(tmp_path / "dem.tif", rpc)
    dem = Dem.from_path(tmp_path / "dem.tif")
    with pytest.raises(ConvergenceError, match="does not meet the DEM"):
        rpc.localize_on_dem([[1000.0, 750.0]], dem.lonlat_function(), h_range=(2000.0, 3000.0))
    out = rpc.localize_on_dem([[1000.0, 750.0]], dem.lonlat_function(), h_range=(2000.0, 3000.0), on_failure="nan")
    assert np.isnan(out).all()


# ----------------------------------------------------------------- readers
def test_rpc_txt_round_trip(tmp_path):
    rpc = synthetic_rpc()
    p = tmp_path / "img_RPC.TXT"
    p.write_text(rpc.to_rpc_txt())
    back = read_rpc(p)
    g = rpc.localize([[10.0, 20.0], [1500.0, 1400.0]], 250.0)
    assert np.abs(back.project(g) - rpc.project(g)).max() < 1e-9


def test_rpb_reader(tmp_path):
    rpc = synthetic_rpc()

    def lst(c):
        return "(\n" + ",\n".join(f"    {v:+.15E}" for v in c) + ")"
    text = (f'satId = "XX";\nBEGIN_GROUP = IMAGE\n\terrBias = 1.5;\n\terrRand = 0.2;\n'
            f"\tlineOffset = {rpc.line_off};\n\tsampOffset = {rpc.samp_off};\n\tlatOffset = {rpc.lat_off};\n"
            f"\tlongOffset = {rpc.long_off};\n\theightOffset = {rpc.height_off};\n\tlineScale = {rpc.line_scale};\n"
            f"\tsampScale = {rpc.samp_scale};\n\tlatScale = {rpc.lat_scale};\n\tlongScale = {rpc.long_scale};\n"
            f"\theightScale = {rpc.height_scale};\n\tlineNumCoef = {lst(rpc.line_num_coeff)};\n"
            f"\tlineDenCoef = {lst(rpc.line_den_coeff)};\n\tsampNumCoef = {lst(rpc.samp_num_coeff)};\n"
            f"\tsampDenCoef = {lst(rpc.samp_den_coeff)};\nEND_GROUP = IMAGE\nEND;\n")
    p = tmp_path / "img.RPB"
    p.write_text(text)
    back = read_rpc(p)
    assert back.err_bias == 1.5 and back.err_rand == 0.2
    g = rpc.localize([[100.0, 200.0]], 0.0)
    assert np.abs(back.project(g) - rpc.project(g)).max() < 1e-9


def test_geotiff_rpc_tags(tmp_path):
    import rasterio

    rpc = synthetic_rpc()
    with rasterio.open(tmp_path / "img.tif", "w", driver="GTiff", width=20, height=10, count=1, dtype="uint8",
                       rpcs=rpc.to_rasterio()) as ds:
        ds.write(np.zeros((1, 10, 20), np.uint8))
    back = read_rpc(tmp_path / "img.tif")
    g = rpc.localize([[100.0, 200.0]], 100.0)
    assert np.abs(back.project(g) - rpc.project(g)).max() < 1e-6


def test_dimap_offsets_are_one_based(tmp_path):
    rpc = synthetic_rpc()
    inv = "".join(f"<{t}_{i + 1}>{float(c)!r}</{t}_{i + 1}>" for t, cc in
                  (("SAMP_NUM_COEFF", rpc.samp_num_coeff), ("SAMP_DEN_COEFF", rpc.samp_den_coeff),
                   ("LINE_NUM_COEFF", rpc.line_num_coeff), ("LINE_DEN_COEFF", rpc.line_den_coeff))
                  for i, c in enumerate(cc))
    val = (f"<LONG_SCALE>{rpc.long_scale}</LONG_SCALE><LONG_OFF>{rpc.long_off}</LONG_OFF>"
           f"<LAT_SCALE>{rpc.lat_scale}</LAT_SCALE><LAT_OFF>{rpc.lat_off}</LAT_OFF>"
           f"<HEIGHT_SCALE>{rpc.height_scale}</HEIGHT_SCALE><HEIGHT_OFF>{rpc.height_off}</HEIGHT_OFF>"
           f"<SAMP_SCALE>{rpc.samp_scale}</SAMP_SCALE><SAMP_OFF>{rpc.samp_off + 1}</SAMP_OFF>"
           f"<LINE_SCALE>{rpc.line_scale}</LINE_SCALE><LINE_OFF>{rpc.line_off + 1}</LINE_OFF>")
    xml = (f'<?xml version="1.0"?><Dimap_Document><Rational_Function_Model><Global_RFM>'
           f"<Inverse_Model>{inv}</Inverse_Model><RFM_Validity>{val}</RFM_Validity></Global_RFM>"
           f"</Rational_Function_Model></Dimap_Document>")
    (tmp_path / "RPC_x.XML").write_text(xml)
    back = read_rpc(tmp_path / "RPC_x.XML")
    g = rpc.localize([[100.0, 200.0]], 100.0)
    assert np.abs(back.project(g) - rpc.project(g)).max() < 1e-9


def test_reader_bad_input(tmp_path):
    with pytest.raises(RasterIOError, match="not found"):
        read_rpc(tmp_path / "missing_RPC.TXT")
    (tmp_path / "x.txt").write_text("hello: world\n")
    with pytest.raises(InvalidInputError, match="not an RPC file"):
        read_rpc(tmp_path / "x.txt")
    txt = synthetic_rpc().to_rpc_txt().replace("HEIGHT_SCALE", "HEIGHT_SKALE")
    (tmp_path / "bad_RPC.TXT").write_text(txt)
    with pytest.raises(InvalidInputError, match="HEIGHT_SCALE"):
        read_rpc(tmp_path / "bad_RPC.TXT")
    (tmp_path / "bad.xml").write_text("<a><b/></a>")
    with pytest.raises(InvalidInputError, match="neither"):
        read_rpc(tmp_path / "bad.xml")
    import rasterio
    with rasterio.open(tmp_path / "plain.tif", "w", driver="GTiff", width=4, height=4, count=1,
                       dtype="uint8") as ds:
        ds.write(np.zeros((1, 4, 4), np.uint8))
    with pytest.raises(InvalidInputError, match="has no RPC"):
        read_rpc(tmp_path / "plain.tif")


def test_model_bad_input():
    rpc = synthetic_rpc()
    with pytest.raises(ShapeError):
        rpc.project([[1.0, 2.0]])
    with pytest.raises(InvalidInputError, match="not finite"):
        rpc.project([[7.0, np.nan, 0.0]])
    with pytest.raises(ShapeError):
        rpc.localize([[1.0, 2.0]], [1.0, 2.0])
    with pytest.raises(InvalidInputError, match="not finite"):
        rpc.localize([[1.0, 2.0]], np.nan)
    with pytest.raises(InvalidInputError, match="on_failure"):
        rpc.localize([[1.0, 2.0]], 0.0, on_failure="ignore")
    with pytest.raises(InvalidInputError, match="non-zero"):
        RPC.from_coefficients(offsets=(0, 0, 0, 0, 0), scales=(1, 1, 0, 1, 1), samp_num=[0, 1], line_num=[0, 0, 1])
    with pytest.raises(InvalidInputError, match="all zeros"):
        RPC.from_coefficients(offsets=(0, 0, 0, 0, 0), scales=(1, 1, 1, 1, 1), samp_num=[0, 1], line_num=[0, 0, 1],
                              samp_den=[0.0])
    # a singular model: the line does not depend on the ground -> localisation cannot converge
    flat = RPC.from_coefficients(offsets=(0, 0, 0, 0, 0), scales=(1, 1, 1, 1, 1), samp_num=[0, 1], line_num=[5.0])
    with pytest.raises(ConvergenceError, match="did not converge"):
        flat.localize([[0.2, 0.3]], 0.0)


# ----------------------------------------------------------------- refinement
def _gcps(rpc: RPC, n: int, bias, noise: float, seed: int = 0):
    rng = np.random.default_rng(seed)
    px = np.column_stack([rng.uniform(50, 1950, n), rng.uniform(50, 1450, n)])
    h = rng.uniform(0, 600, n)
    g = rpc.localize(px, h)  # true ground; the image as delivered is the RPC plus a bias
    obs = px + bias(px) + rng.normal(0, noise, (n, 2))
    return obs, g


@pytest.mark.parametrize("model,bias", [
    ("shift", lambda p: np.array([12.3, -7.5])),
    ("drift", lambda p: np.column_stack([3 + 0.004 * p[:, 1], -2 + 0.002 * p[:, 1]])),
    ("affine", lambda p: np.column_stack([3 + 1e-3 * p[:, 0] - 2e-3 * p[:, 1], -2 + 5e-4 * p[:, 0] + 1e-3 * p[:, 1]])),
])
def test_refinement_recovers_bias(model, bias):
    rpc = synthetic_rpc()
    obs, g = _gcps(rpc, 12, bias, 0.1)
    ref = RPCRefinement.from_gcps(rpc, obs, g, model=model)
    s = ref.residuals.summary()
    assert s["rmse"] < 0.2  # 0.1 px noise per axis
    assert ref.residuals.extra["loo_rmse_px"] < 0.35
    assert ref.residuals.extra["rpc_only_rmse_px"] > 2
    # corrected projection and its inverse
    gt = rpc.localize([[500.0, 600.0]], 100.0)
    p = ref.project(gt)
    assert np.abs(p - ([[500.0, 600.0]] + bias(np.array([[500.0, 600.0]])))).max() < 0.2
    back = ref.localize(p, 100.0)
    assert metres(back[:, :2] - gt[:, :2], gt[:, 1]).max() < 1e-6


def test_refinement_check_points_and_errors():
    rpc = synthetic_rpc()
    obs, g = _gcps(rpc, 6, lambda p: np.array([4.0, 1.0]), 0.05)
    chk = np.array([0, 0, 0, 0, 1, 1], bool)
    ref = RPCRefinement.from_gcps(rpc, obs, g, model="shift", ids=list("abcdef"), check=chk)
    s = ref.residuals.summary()
    assert s["n_check"] == 2 and s["rmse_check"] < 0.3
    assert ref.residuals.step == "RPC refinement (shift)" and "2 check points" in ref.residuals.summary_line()
    with pytest.raises(EstimationError, match="at least 3"):
        RPCRefinement.from_gcps(rpc, obs[:2], g[:2], model="affine")
    with pytest.raises(EstimationError, match="degenerate"):
        RPCRefinement.from_gcps(rpc, np.repeat(obs[:1], 4, 0), np.repeat(g[:1], 4, 0), model="affine")
    with pytest.raises(InvalidInputError, match="unknown refinement"):
        RPCRefinement.from_gcps(rpc, obs, g, model="spline")
    with pytest.raises(ShapeError):
        RPCRefinement.from_gcps(rpc, obs, g[:3])


# ----------------------------------------------------------------- real files (shared data)
def _shared_files() -> list[Path]:
    out = []
    if (SHARED / "rpc_models").is_dir():
        out += sorted((SHARED / "rpc_models").iterdir())
    if (SHARED / "pleiades_triplet").is_dir():
        out += sorted((SHARED / "pleiades_triplet").glob("img_*.tif"))
    return out


@pytest.mark.shared
@pytest.mark.parametrize("name", [p.name for p in _shared_files()] or ["(absent)"])
def test_real_rpcs_agree_with_gdal(name):
    files = {p.name: p for p in _shared_files()}
    if name not in files:
        pytest.skip(f"shared data not found at {SHARED}")
    rpc = read_rpc(files[name])
    res = check_against_gdal(rpc)
    assert res["proj_px"] < 1e-3, res
    assert res["loc_m"] < 1e-3, res
    # GDAL's iteration gives up on part of the Planet samples (extreme heights); ours converge on all
    assert res["gdal_failed"] < res["n"]


def test_fit_and_dem_localisation_bad_input():
    rpc = synthetic_rpc()
    with pytest.raises(EstimationError, match="finite"):
        fit_rpc(lambda g: np.full((len(g), 2), np.nan), ((0, 1), (0, 1), (0, 1)))
    with pytest.raises(InvalidInputError, match="h_range"):
        rpc.localize_on_dem([[1.0, 2.0]], lambda ll: np.zeros(len(ll)), h_range=(5.0, 1.0))
    with pytest.raises(InvalidInputError, match="on_failure"):
        rpc.localize_on_dem([[1.0, 2.0]], lambda ll: np.zeros(len(ll)), h_range=(0.0, 1.0), on_failure="skip")
    with pytest.raises(ShapeError):
        rpc.localize_on_dem([1.0, 2.0, 3.0], lambda ll: np.zeros(len(ll)))
    with pytest.raises(InvalidInputError, match="5 numbers"):
        RPC.from_coefficients(offsets=(0, 0, 0), scales=(1, 1, 1, 1, 1), samp_num=[0, 1], line_num=[0, 0, 1])
    with pytest.raises(InvalidInputError, match="missing key"):
        RPC.from_dict({"line_off": 1.0})
