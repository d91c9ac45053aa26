"""Issue 24, the orthophoto seams: height datums (items 2, 3), the relief figure (6), block orientations (12).

Synthetic RPC scene with known truth: the delivered RPC is off by (2.5, -1.5) px, the image is rendered
with the true model over a DEM of ellipsoidal heights h (bands 1/2 = the easting/northing each pixel
sees, as in ``test_ortho.py``), the DEM files hold orthometric heights H = h - N. GCPs are true ground
points (ellipsoidal heights) at exact pixels. The orthophoto of a correctly refined model has no
geolocation error; a height datum applied twice or not at all shifts it by N x 0.3 px/m.
"""

from __future__ import annotations

import html
import json
import re
import struct
import warnings
from pathlib import Path

import numpy as np
import pytest
import rasterio
from affine import Affine
from click.testing import CliRunner
from rasterio.crs import CRS as RioCRS

from rectify.cli.main import cli
from rectify.geometry.crs import transform_xy
from rectify.geometry.rpc import RPC, RPCRefinement
from rectify.raster.dem import Dem
from tests.rectify.test_ortho import CRS, E0, N0, frame_scene, geolocation_error, hills, write_dem, write_image

N_GEOID = 30.0  # m, the undulation of the scene (constant unless a grid says otherwise)
BIAS = np.array([2.5, -1.5])  # px, the delivered RPC's error
GCP_PX = np.array([[20, 25], [170, 30], [100, 100], [30, 175], [175, 170], [60, 120]], float)


def _rpc() -> RPC:
    lon0, lat0 = transform_xy(CRS, "EPSG:4326", [[E0, N0]])[0]
    m_lon = 1.0 / (111_320 * np.cos(np.radians(lat0)))
    m_lat = 1.0 / 111_320
    # 200 x 200 px at ~1 m; 0.3 px per m of height across track
    return RPC.from_coefficients(
        offsets=(100.0, 100.0, lat0, lon0, 100.0), scales=(100.0, 100.0, 100 * m_lat, 100 * m_lon, 100.0),
        samp_num=[0.0, 1.0, 0.05, 0.3, 0.001, 0.0, 0.0, 0.002], samp_den=[1.0, 0.001],
        line_num=[0.0, 0.04, -1.0, 0.05, 0.0, 0.0, 0.001], line_den=[1.0, 0.0, 0.001])


def _write(path: Path, z: np.ndarray, crs, res: float = 2.0, size: float = 600.0) -> None:
    with rasterio.open(path, "w", driver="GTiff", width=z.shape[1], height=z.shape[0], count=1, dtype="float32",
                       crs=crs, transform=Affine(res, 0, E0 - size / 2, 0, -res, N0 + size / 2)) as ds:
        ds.write(z.astype("float32"), 1)


def _dem_grid(res: float = 2.0, size: float = 600.0) -> tuple[np.ndarray, np.ndarray]:
    n = int(size / res)
    X, Y = np.meshgrid(E0 - size / 2 + res * (np.arange(n) + 0.5), N0 + size / 2 - res * (np.arange(n) + 0.5))
    return X, Y


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    """The RPC image (tags: the delivered RPC), dem_ell.tif (h), dem_H.tif (h - 30 m) and the GCP truth."""
    d = tmp_path_factory.mktemp("rpc_scene")
    rpc = _rpc()
    write_dem(d / "dem_ell.tif", hills)
    X, Y = _dem_grid()
    _write(d / "dem_H.tif", hills(X, Y) - N_GEOID, CRS)
    truth = RPCRefinement(rpc, "shift", BIAS.reshape(2, 1))
    dem = Dem.from_path(d / "dem_ell.tif")
    cc, rr = np.meshgrid(np.arange(200), np.arange(200))
    px = np.column_stack([cc.ravel(), rr.ravel()]).astype(float)
    g = truth.localize_on_dem(px, dem.lonlat_function(), h_range=(40.0, 200.0))
    write_image(d / "plain.tif", transform_xy("EPSG:4326", CRS, g[:, :2]), (200, 200))
    with rasterio.open(d / "plain.tif") as src:
        bands = src.read()
    with rasterio.open(d / "rpc.tif", "w", driver="GTiff", width=200, height=200, count=3, dtype="float32",
                       nodata=np.nan, rpcs=rpc.to_rasterio()) as ds:
        ds.write(bands)
    ground = truth.localize_on_dem(GCP_PX, dem.lonlat_function(), h_range=(40.0, 200.0))
    np.save(d / "gcp_ground.npy", ground)
    return d


def _gcps(path: Path, ground: np.ndarray, crs: str) -> Path:
    lines = [f"# crs={crs}", "id,col,row,x,y,z"] + [
        f"g{i},{c!r},{r!r},{x!r},{y!r},{z!r}" for i, ((c, r), (x, y, z)) in
        enumerate(zip(GCP_PX.tolist(), ground.tolist(), strict=True))]
    path.write_text("\n".join(lines) + "\n")
    return path


def _run(*args: str):
    return CliRunner().invoke(cli, ["ortho", *map(str, args)])


def _ortho(d: Path, dem: str, out: str, *extra) -> tuple[object, str]:
    r = _run(d / "rpc.tif", "--rpc", "--dem", d / dem, "-o", d / out, "--resolution", "1", "--threads", "2",
             "--overwrite", *extra)
    return r, r.output


def _geoloc(path: Path, q: float = 99.9) -> float:
    """A percentile of the orthophoto's geolocation error, output pixels (1 m)."""
    err, _, _ = geolocation_error(path)
    ok = np.isfinite(err)
    assert ok.mean() > 0.5
    return float(np.percentile(err[ok], q))


def _number(pattern: str, text: str) -> float:
    m = re.search(pattern, text)
    assert m, f"{pattern!r} not in:\n{text}"
    return float(m.group(1))


# =========================================================================== item 2: GCP heights
def test_gcp_heights_declared_ellipsoidal_are_not_moved_by_the_dem_undulation(scene):
    """GCPs in EPSG:4979 (ellipsoidal) with a DEM of geoid heights (--undulation 30): converted once."""
    d = scene
    g = _gcps(d / "gcps_4979.csv", np.load(d / "gcp_ground.npy"), "EPSG:4979")
    r, out = _ortho(d, "dem_H.tif", "o_4979.tif", "--undulation", N_GEOID, "--gcps", g)
    assert r.exit_code == 0, out
    # before: the GCP heights got +30 m too, so the refined ortho moved by 30 m x 0.3 px/m = 9 px
    assert _geoloc(d / "o_4979.tif") < 0.1
    assert "GCP heights: ellipsoidal (the CRS of" in out and "used as they are" in out
    assert "DEM heights + 30 m undulation (--undulation)" in out
    assert _number(r"leave-one-out check on the orthophoto .*?: RMSE ([0-9.]+) m", out) < 0.01
    # the same said by the option on a 2D GCP file
    g2 = _gcps(d / "gcps_4326.csv", np.load(d / "gcp_ground.npy"), "EPSG:4326")
    r, out = _ortho(d, "dem_H.tif", "o_opt.tif", "--undulation", N_GEOID, "--gcps", g2, "--gcp-heights",
                    "ellipsoidal")
    assert r.exit_code == 0, out
    assert _geoloc(d / "o_opt.tif") < 0.1


def test_gcp_heights_of_no_stated_datum_with_a_converted_dem_are_refused(scene):
    d = scene
    g = _gcps(d / "gcps_plain.csv", np.load(d / "gcp_ground.npy"), "EPSG:4326")
    (d / "o_refused.tif").unlink(missing_ok=True)
    r, out = _ortho(d, "dem_H.tif", "o_refused.tif", "--undulation", N_GEOID, "--gcps", g)
    assert r.exit_code == 1, out
    assert "state no datum" in out and "--gcp-heights ellipsoidal|dem" in out and "Traceback" not in out
    assert len(out.strip().splitlines()) == 1
    assert not (d / "o_refused.tif").exists()
    # a DEM that is not converted leaves no doubt: the GCP heights are the DEM's (backward compatible)
    r, out = _ortho(d, "dem_ell.tif", "o_same.tif", "--gcps", g)
    assert r.exit_code == 0, out
    assert "no datum stated: taken in the DEM's datum" in out
    assert _geoloc(d / "o_same.tif") < 0.1


def test_leave_one_out_in_metres_shows_a_wrong_gcp_datum(scene):
    """Ellipsoidal GCP heights declared as the DEM's: the pixel check stays tiny, the ground check does not."""
    d = scene
    g = _gcps(d / "gcps_plain.csv", np.load(d / "gcp_ground.npy"), "EPSG:4326")
    r, out = _ortho(d, "dem_H.tif", "o_wrong.tif", "--undulation", N_GEOID, "--gcps", g, "--gcp-heights", "dem")
    assert r.exit_code == 0, out
    assert _number(r"leave-one-out check RMSE after refinement ([0-9.e-]+) px", out) < 0.05
    loo_m = _number(r"leave-one-out check on the orthophoto .*?: RMSE ([0-9.]+) m", out)
    shift_m = _geoloc(d / "o_wrong.tif", 50)  # the orthophoto's real error (median, 1 m pixels)
    assert shift_m > 5
    assert loo_m == pytest.approx(shift_m, rel=0.15)  # the printed check is the orthophoto's error
    assert "GCP heights - DEM at the GCPs: median +30.00 m" in out


@pytest.mark.parametrize("model", ["shift", "drift", "affine"])
def test_leave_one_out_in_metres_equals_explicit_refits(scene, model):
    """The ground leave-one-out figure is the error of a refit without the point, placed on the DEM."""
    from rectify.actions.ortho import ground_errors
    from rectify.formats.gcps import read_gcps
    from rectify.geometry.sensors import RPCModel
    from rectify.raster.dem import ground_on_dem

    d = scene
    rng = np.random.default_rng(3)
    truth = np.load(d / "gcp_ground.npy")
    g = read_gcps(_gcps(d / "gcps_loo.csv", truth, "EPSG:4326"))
    pix = g.pixel + rng.normal(0, 0.4, g.pixel.shape)
    rpc = _rpc()
    ref = RPCRefinement.from_gcps(rpc, pix, truth, model=model, ids=list(g.ids))
    dem = Dem.from_path(d / "dem_ell.tif")
    g2 = type(g)(g.ids, pix, g.target, g.z, g.check, g.crs)
    got = ground_errors(RPCModel(ref, 200, 200), dem, g2, truth, ref.residuals)["leave_one_out"]["errors_m"]
    for i, name in enumerate(g.ids):
        keep = np.arange(len(pix)) != i
        sub = RPCRefinement.from_gcps(rpc, pix[keep], truth[keep], model=model)
        p = ground_on_dem(RPCModel(sub, 200, 200), dem, pix[i:i + 1])[0]
        e = transform_xy("EPSG:4326", CRS, np.vstack([p[:2], truth[i, :2]]))
        assert got[name] == pytest.approx(float(np.hypot(*(e[0] - e[1]))), abs=0.01), name


def _frame_gcp_run(d, name: str, shift=(0.0, 0.0)):
    """``rectify ortho`` of the frame image with 5 GCPs whose map coordinates are the truth moved by ``shift``
    (m, east and north); the CLI result."""
    with rasterio.open(d / "frame.tif") as ds:
        bands = ds.read()
    px = np.array([[10, 12], [100, 15], [60, 50], [15, 85], [105, 88]])
    rows = [f"c{i},{c},{r},{float(bands[0, r, c]) + E0 + shift[0]!r},{float(bands[1, r, c]) + N0 + shift[1]!r}"
            for i, (c, r) in enumerate(px.tolist())]
    (d / f"{name}.csv").write_text("\n".join([f"# crs={CRS}", "id,col,row,x,y", *rows]) + "\n")
    return _run(d / "frame.tif", "--camera", d / "cam.json", "--exterior", d / "eo.json", "--dem", d / "dem.tif",
                "--gcps", d / f"{name}.csv", "-o", d / f"{name}.tif", "--resolution", "1")


def test_frame_gcp_check_in_metres(block):
    """A frame camera is checked by GCPs; their error on the orthophoto is given in metres too."""
    r = _frame_gcp_run(block, "gcps")
    assert r.exit_code == 0, r.output
    assert "GCP heights: none in the file: taken from the DEM" in r.output
    assert _number(r"GCPs on the orthophoto .*?: RMSE ([0-9.]+) m", r.output) < 0.01


def test_frame_gcp_check_accuracy_statement(block):
    """Issue 27: the orthophoto's check points are stated in the standard forms: GCPs moved by a known
    (+0.30 m, -0.20 m) give RMSE_x 0.30 m, RMSE_y 0.20 m, RMSE_r 0.36 m and the ASPRS sentence."""
    r = _frame_gcp_run(block, "gcps_moved", (0.3, -0.2))
    assert r.exit_code == 0, r.output
    assert "accuracy statement from 5 check points (m;" in r.output
    assert abs(_number(r"  x: mean ([-+0-9.]+),", r.output) + 0.3) < 0.01
    assert abs(_number(r"  y: mean ([-+0-9.]+),", r.output) - 0.2) < 0.01
    assert abs(_number(r"RMSE_r ([0-9.]+) m", r.output) - np.hypot(0.3, 0.2)) < 0.01
    assert "RMSE_H = 36" in r.output and "produced to meet" in r.output


# =========================================================================== item 3: the DEM's declared datum
def test_dem_declaring_egm2008_without_its_grid_is_refused(scene):
    from pyproj.transformer import TransformerGroup

    d = scene
    X, Y = _dem_grid()
    _write(d / "dem_egm08.tif", hills(X, Y) - N_GEOID, "EPSG:32632+3855")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # pyproj warns about the missing grid
        installed = TransformerGroup("EPSG:4326+3855", "EPSG:4979").best_available
    if installed:
        pytest.skip("the EGM2008 grid is installed here: the refusal cannot be seen")
    (d / "o_egm.tif").unlink(missing_ok=True)
    r, out = _ortho(d, "dem_egm08.tif", "o_egm.tif")
    assert r.exit_code == 1, out
    assert "EGM2008" in out and "--undulation" in out and "us_nga_egm08_25.tif" in out
    assert len(out.strip().splitlines()) == 1 and not (d / "o_egm.tif").exists()
    # the constant undulation the message asks for is used instead of the grid, and said so
    g = _gcps(d / "gcps_4979.csv", np.load(d / "gcp_ground.npy"), "EPSG:4979")
    r, out = _ortho(d, "dem_egm08.tif", "o_egm.tif", "--undulation", N_GEOID, "--gcps", g)
    assert r.exit_code == 0, out
    assert "its CRS declares EGM2008 height (EPSG:3855)" in out
    assert _geoloc(d / "o_egm.tif") < 0.1


def _write_gtx(path: Path, lat0: float, lon0: float, step: float, n: np.ndarray) -> None:
    """A geoid grid in the .gtx format PROJ reads: the header, then float32 rows from the south."""
    rows, cols = n.shape
    with open(path, "wb") as f:
        f.write(struct.pack(">4d2i", lat0, lon0, step, step, rows, cols))
        f.write(np.asarray(n, ">f4").tobytes())


def _undulation(lon, lat):
    return N_GEOID + 2.0 * (lon - 9.0) + 1.0 * (lat - 45.0)


def test_dem_declaring_a_vertical_datum_is_converted_through_pyproj(scene):
    """A DEM whose CRS declares a geoid (a bound vertical CRS naming its grid, written here): h = H + N(lon, lat)."""
    d = scene
    lat, lon = np.mgrid[44.0:46.51:0.25, 8.0:10.01:0.25]
    _write_gtx(d / "geoid.gtx", 44.0, 8.0, 0.25, _undulation(lon, lat))
    X, Y = _dem_grid()
    ll = transform_xy(CRS, "EPSG:4326", np.column_stack([X.ravel(), Y.ravel()]))
    H = hills(X, Y) - _undulation(ll[:, 0], ll[:, 1]).reshape(X.shape)
    _write(d / "dem_raw.tif", H, None)
    horizontal = RioCRS.from_epsg(32632).to_wkt()
    wkt = (f'COMPD_CS["UTM 32N + test height",{horizontal},VERT_CS["test height",VERT_DATUM["test geoid",2005,'
           f'EXTENSION["PROJ4_GRIDS","{d / "geoid.gtx"}"]],UNIT["metre",1],AXIS["Gravity-related height",UP]]]')
    (d / "dem_geoid.vrt").write_text(
        f'<VRTDataset rasterXSize="300" rasterYSize="300"><SRS>{html.escape(wkt)}</SRS>'
        f'<GeoTransform>{E0 - 300}, 2.0, 0, {N0 + 300}, 0, -2.0</GeoTransform>'
        '<VRTRasterBand dataType="Float32" band="1"><SimpleSource><SourceFilename relativeToVRT="1">dem_raw.tif'
        '</SourceFilename><SourceBand>1</SourceBand></SimpleSource></VRTRasterBand></VRTDataset>')
    g = _gcps(d / "gcps_4979.csv", np.load(d / "gcp_ground.npy"), "EPSG:4979")
    r, out = _ortho(d, "dem_geoid.vrt", "o_geoid.tif", "--gcps", g)
    assert r.exit_code == 0, out
    # before: the declared heights were used as ellipsoidal, 30 m off: 9 px
    assert _geoloc(d / "o_geoid.tif") < 0.1
    assert "DEM heights above test height (declared by its CRS) + the geoid undulation from PROJ" in out
    dem = Dem.from_path(d / "dem_geoid.vrt")
    assert dem.geoid is not None and "declared by its CRS" in dem.datum
    p = np.array([[E0 - 300 + 201.0, N0 + 300 - 301.0]])  # a DEM cell centre: h exactly
    assert dem.sample(p)[0] == pytest.approx(hills(*p.T)[0], abs=1e-4)


def test_dem_declaring_ellipsoidal_heights_refuses_a_second_conversion(scene):
    d = scene
    with rasterio.open(d / "dem_ell.tif") as src:
        z, tr = src.read(1), src.transform
    with rasterio.open(d / "dem_4979.tif", "w", driver="GTiff", width=z.shape[1], height=z.shape[0], count=1,
                       dtype="float32", crs="EPSG:4979",
                       transform=Affine(tr.a / 111_000, 0, 9.0, 0, tr.e / 111_000, 45.2)) as ds:
        ds.write(z, 1)
    r = _run(d / "rpc.tif", "--rpc", "--dem", d / "dem_4979.tif", "-o", d / "o_4979dem.tif", "--undulation", "30")
    assert r.exit_code == 1 and "declares ellipsoidal heights" in r.output
    assert not (d / "o_4979dem.tif").exists()


# =========================================================================== item 6: the relief figure
def test_relief_displacement_is_one_figure_over_the_valid_cells(tmp_path):
    """An oblique view (57 degrees off nadir): console and report give the same figures, those of the definition."""
    from rectify.geometry.camera import Camera
    from rectify.geometry.rotation import matrix_from_angles
    from rectify.geometry.sensors import FrameModel

    cam = Camera(focal_length_mm=8.0, pixel_size_mm=0.01, width=160, height=120)
    model = FrameModel(cam, [E0 - 300.0, N0, 300.0], matrix_from_angles(0.0, -1.0, 0.2), CRS)
    write_dem(tmp_path / "dem.tif", hills)
    rr, cc = np.mgrid[0:120, 0:160]
    with rasterio.open(tmp_path / "frame.tif", "w", driver="GTiff", width=160, height=120, count=1,
                       dtype="uint8") as ds:
        ds.write((100 + 50 * np.sin(cc / 3.0) * np.cos(rr / 4.0)).astype(np.uint8)[None])
    (tmp_path / "cam.json").write_text(json.dumps(model.camera.to_dict()))
    (tmp_path / "eo.json").write_text(json.dumps({"position": model.position.tolist(),
                                                  "rotation": model.rotation.tolist(), "crs": CRS}))
    r = _run(tmp_path / "frame.tif", "--camera", tmp_path / "cam.json", "--exterior", tmp_path / "eo.json",
             "--dem", tmp_path / "dem.tif", "-o", tmp_path / "o.tif", "--resolution", "1", "--report",
             tmp_path / "rep")
    assert r.exit_code == 0, r.output
    out = r.output
    doc = json.loads((tmp_path / "rep" / "ortho_report.json").read_text())["relief_shift_removed"]
    for key, pat in (("median_m", r"median ([0-9.]+) m"), ("p95_m", r"95th percentile ([0-9.]+) m"),
                     ("max_m", r"max ([0-9.]+) m")):
        assert _number(r"relief displacement removed .*?" + pat, out) == pytest.approx(doc[key], abs=0.006), key
    assert doc["max"] == doc["max_m"]
    with rasterio.open(tmp_path / "rep" / "relief_shift.tif") as ds:
        assert float(np.nanmax(ds.read(1))) == pytest.approx(doc["max_m"], rel=1e-6)
    # the definition, by brute force over every valid output cell of the written orthophoto
    with rasterio.open(tmp_path / "o.tif") as ds:
        valid = ds.read_masks(1) > 0
        tr = ds.transform
    rows, cols = np.nonzero(valid)
    xy = np.column_stack([tr.c + tr.a * (cols + 0.5), tr.f + tr.e * (rows + 0.5)])
    dem = Dem.from_path(tmp_path / "dem.tif")
    z = dem.sample(xy)
    h_ref = doc["plane_height_m"]
    assert h_ref == pytest.approx(float(np.nanmean(z)), abs=1.0)  # the lattice's mean height
    g = model.ground_at_height(model.project(np.column_stack([xy, z])), h_ref)
    brute = np.hypot(*(g[:, :2] - xy).T)
    brute = brute[np.isfinite(brute)]
    assert doc["max_m"] <= brute.max() + 1e-6  # the lattice is a subset of the valid cells
    assert doc["median_m"] == pytest.approx(float(np.median(brute)), rel=0.05)
    assert doc["p95_m"] == pytest.approx(float(np.percentile(brute, 95)), rel=0.05)
    assert doc["cells"] > 200


# =========================================================================== item 12: a block's orientation
@pytest.fixture()
def block(tmp_path):
    from stereo.block.types import Pose
    from stereo.formats.block import block_orientation_text
    from stereo.formats.poses import write_pose_csv

    model = frame_scene(tmp_path, size=(120, 100))
    (tmp_path / "cam.json").write_text(json.dumps(model.camera.to_dict()))
    (tmp_path / "eo.json").write_text(json.dumps({"position": model.position.tolist(),
                                                  "rotation": model.rotation.tolist(), "crs": CRS}))
    other = Pose("IMG_2.JPG", "cam1", model.position + [50.0, 0.0, 0.0], model.rotation)
    poses = [Pose("frame.tif", "cam1", model.position, model.rotation), other]
    (tmp_path / "orientation.json").write_text(block_orientation_text({"cam1": model.camera}, poses, crs=CRS))
    write_pose_csv(tmp_path / "poses.csv", poses, crs=CRS)
    return tmp_path


def test_block_orientation_and_poses_feed_the_orthophoto(block):
    d = block
    base = ["--dem", d / "dem.tif", "--resolution", "1", "--threads", "2"]
    r = _run(d / "frame.tif", "--camera", d / "cam.json", "--exterior", d / "eo.json", "-o", d / "eo.tif", *base)
    assert r.exit_code == 0, r.output
    # the block's orientation.json alone (the camera is in it), the image by the source's file stem
    r = _run(d / "frame.tif", "--exterior", d / "orientation.json", "-o", d / "block.tif", *base)
    assert r.exit_code == 0, r.output
    assert "image 'frame.tif' of block orientation" in r.output and "camera 'cam1' of the block" in r.output
    # poses.csv with the camera JSON, the image by id
    r = _run(d / "frame.tif", "--exterior", d / "poses.csv", "--camera", d / "cam.json", "--image-id", "frame",
             "-o", d / "poses.tif", *base)
    assert r.exit_code == 0, r.output
    with rasterio.open(d / "eo.tif") as a, rasterio.open(d / "block.tif") as b, rasterio.open(d / "poses.tif") as c:
        A, B, C = a.read(), b.read(), c.read()
        assert a.transform == b.transform == c.transform
    assert np.array_equal(A, B, equal_nan=True)
    # poses.csv stores degrees in 17 digits: the same orthophoto to float32 rounding
    assert np.allclose(A, C, equal_nan=True, atol=1e-4)


@pytest.mark.parametrize("args,msg", [
    (["--exterior", "orientation.json", "--image-id", "IMG_9"], "image id 'IMG_9' is not in block orientation"),
    (["--exterior", "poses.csv", "--image-id", "frame"], "has no camera model: pass the camera JSON (--camera)"),
    (["--exterior", "eo.json", "--camera", "cam.json", "--image-id", "frame"], "is the exterior orientation of one"),
    (["--exterior", "eo.json"], "has no camera model"),
    (["--rpc", "--image-id", "frame"], "an RPC image needs none"),
])
def test_block_orientation_bad_input(block, args, msg):
    d = block
    full = [str(d / a) if a.endswith((".json", ".csv")) else a for a in args]
    r = _run(d / "frame.tif", "--dem", d / "dem.tif", "-o", d / "x.tif", *full)
    assert r.exit_code == 1, r.output
    assert msg in r.output and len(r.output.strip().splitlines()) == 1
    assert not (d / "x.tif").exists()


def test_frame_orientation_declaring_its_heights(block):
    """An EO CRS with a vertical part: its horizontal part georeferences, its heights must match the DEM's."""
    d = block
    eo = json.loads((d / "eo.json").read_text())
    eo["crs"] = "EPSG:32632+5773"
    (d / "eo_egm96.json").write_text(json.dumps(eo))
    args = ["--camera", d / "cam.json", "--exterior", d / "eo_egm96.json", "--resolution", "1"]
    r = _run(d / "frame.tif", "--dem", d / "dem.tif", "-o", d / "o96.tif", *args)
    assert r.exit_code == 0, r.output
    assert "the model takes EGM96 height (EPSG:5773) (declared by the exterior orientation's CRS)" in r.output
    with rasterio.open(d / "o96.tif") as ds:
        assert ds.crs.to_epsg() == 32632
    with rasterio.open(d / "dem.tif") as src:
        z, tr = src.read(1), src.transform
    _write(d / "dem08.tif", z, "EPSG:32632+3855", res=tr.a)
    r = _run(d / "frame.tif", "--dem", d / "dem08.tif", "-o", d / "o08.tif", *args)
    assert r.exit_code == 1 and "EGM96 height" in r.output and "EGM2008" in r.output, r.output
    assert not (d / "o08.tif").exists()


def test_default_image_id_is_the_file_stem(block):
    d = block
    (d / "IMG_2.tif").write_bytes((d / "frame.tif").read_bytes())
    r = _run(d / "IMG_2.tif", "--exterior", d / "orientation.json", "--dem", d / "dem.tif", "-o", d / "o2.tif",
             "--resolution", "1")
    assert r.exit_code == 0, r.output
    assert "image 'IMG_2.JPG' of block orientation" in r.output


# =========================================================================== the HTML report
def test_ortho_report_writes_the_html_page_its_help_promises(scene):
    from tests.support.rectify_support import verify_report

    d = scene
    help_text = CliRunner().invoke(cli, ["ortho", "--help"]).output
    assert "report.html" in help_text
    g = _gcps(d / "gcps_rep.csv", np.load(d / "gcp_ground.npy"), "EPSG:4979")
    r, out = _ortho(d, "dem_ell.tif", "o_rep.tif", "--gcps", g, "--report", d / "rep")
    assert r.exit_code == 0, out
    page = (d / "rep" / "report.html").read_text()
    assert "relief" in page and "RPC refinement" in page
    assert verify_report(d / "rep") == []
    doc = json.loads((d / "rep" / "ortho_report.json").read_text())
    assert doc["gcp_ground_errors"]["leave_one_out"]["rmse_m"] < 0.01
    assert "GCP heights" in doc["heights"]
