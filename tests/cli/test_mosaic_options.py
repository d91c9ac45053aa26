"""``rectify mosaic`` end to end with the issue 27 options (--dsm, --seams, --blend, --balance, --provenance) and
its bad input: one-line errors, non-zero exit, nothing written."""

from __future__ import annotations

import json

import numpy as np
import rasterio
from click.testing import CliRunner

from rectify.cli.main import cli
from rectify.geometry.crs import transform_xy
from rectify.geometry.rotation import matrix_from_angles
from rectify.geometry.rpc import RPC
from tests.support.mosaic_scene import CENTRE_A, CRS, X0, Y0, ridge_pair, texture, write_dsm, write_ortho


def _run(args):
    return CliRunner().invoke(cli, ["mosaic", *map(str, args)])


def _outputs(folder, inputs):
    return sorted(p.name for p in folder.iterdir() if p.name not in inputs)


def test_mosaic_least_transformed_with_provenance_and_balance(tmp_path):
    a, b, dsm = ridge_pair(tmp_path, true_ortho=True, gain=1.1, offset=-5.0)
    out = tmp_path / "m.tif"
    r = _run([a, b, "-o", out, "--dsm", dsm, "--balance", "reference", "--provenance", "--feather", "8"])
    assert r.exit_code == 0, r.output
    assert "seams of the least-transformed image" in r.output
    assert "radiometric balance (reference, a.tif kept)" in r.output
    assert "wrote " + str(tmp_path / "m.source.tif") in r.output
    assert _outputs(tmp_path, {"a.tif", "b.tif", "dsm.tif"}) == ["m.source.tif", "m.stac.json", "m.tif"]
    with rasterio.open(out) as ds:
        m, t = ds.read(1), ds.transform
        assert ds.count == 1  # the visibility band is not carried over
        assert ds.tags()["MOSAIC_SEAMS"] == "normal"
    X, Y = np.meshgrid(t.c + t.a * (np.arange(m.shape[1]) + 0.5), t.f + t.e * (np.arange(m.shape[0]) + 0.5))
    assert np.abs(m - texture(X, Y)).max() < 0.01  # B balanced onto A
    with rasterio.open(tmp_path / "m.source.tif") as ds:
        s = ds.read(1)
        assert ds.tags()["MOSAIC_SOURCE_1"] == "a.tif" and ds.tags()["MOSAIC_SOURCE_2"] == "b.tif"
    assert set(np.unique(s)) == {1, 2}
    item = json.loads((tmp_path / "m.stac.json").read_text())
    assert "provenance" in item["assets"]


def test_mosaic_average_blend(tmp_path):
    """B = T + 10 over A = T: the overlap is their mean (T + 5); with --feather 16 each footprint's weight ramps
    up from its edge over about 16 px, so the 5-unit steps at the footprint edges become steps of at most
    1.5 (measured 0.55); with --feather 0 they stay 5."""
    a, b, _ = ridge_pair(tmp_path, offset=10.0)
    steps = {}
    for f in ("16", "0"):
        out = tmp_path / f"m{f}.tif"
        r = _run([a, b, "-o", out, "--blend", "average", "--no-stac", "--feather", f])
        assert r.exit_code == 0, r.output
        with rasterio.open(out) as ds:
            m, t = ds.read(1), ds.transform
        X, Y = np.meshgrid(t.c + t.a * (np.arange(m.shape[1]) + 0.5), t.f + t.e * (np.arange(m.shape[0]) + 0.5))
        d = m - texture(X, Y)
        assert np.allclose(d[:, 60:180], 5.0, atol=1e-3)  # the overlap (20 px in): the mean of T and T + 10
        assert np.allclose(d[:, :30], 0.0, atol=1e-3) and np.allclose(d[:, 210:], 10.0, atol=1e-3)
        steps[f] = np.abs(np.diff(d, axis=1)).max()
    assert steps["16"] <= 1.5 and steps["0"] > 4.99, steps


def test_bad_input_one_line_nothing_written(tmp_path):
    a, b, dsm = ridge_pair(tmp_path)
    plain = write_ortho(tmp_path / "plain.tif", X0 + 20, X0 + 120, centre=None)
    far = write_ortho(tmp_path / "far.tif", X0 + 5000, X0 + 5060, centre=CENTRE_A)
    other = write_ortho(tmp_path / "utm33.tif", X0, X0 + 60, centre=CENTRE_A, crs="EPSG:32633")
    with rasterio.open(dsm) as ds:  # the same DSM 100 km away
        prof, z = ds.profile, ds.read(1)
    prof["transform"] = prof["transform"] * rasterio.Affine.translation(50_000, 0)
    with rasterio.open(tmp_path / "far_dsm.tif", "w", **prof) as ds:
        ds.write(z, 1)
    before = sorted(p.name for p in tmp_path.iterdir())
    cases = [
        ([a, plain, "--dsm", dsm], "has no projection centre", "--seams nadir"),
        ([a, b, "--seams", "normal"], "needs a DSM", "--dsm FILE"),
        ([a, far, "--balance", "mean"], "overlaps no other orthophoto", "a.tif"),
        ([a, other], "must share one CRS", "utm33.tif"),
        ([a, b, "--dsm", tmp_path / "missing.tif"], "missing.tif", ""),
        ([a, b, "--dsm", tmp_path / "far_dsm.tif"], "has no height under the mosaic", "far_dsm.tif"),
        ([a, b, "--compress", "jpeg"], "needs an 8-bit (uint8) output", "float32"),
    ]
    for args, what, more in cases:
        r = _run([*args, "-o", tmp_path / "m.tif"])
        assert r.exit_code != 0, args
        line = r.output.strip()
        assert "\n" not in line and "Traceback" not in line, line
        assert what in line and more in line, line
        assert sorted(p.name for p in tmp_path.iterdir()) == before, args


def test_different_resolutions_are_resampled_onto_the_finest(tmp_path):
    """A 2 m orthophoto beside a 1 m one: the mosaic is on the 1 m grid, the 2 m input resampled bilinearly
    (the texture's periods of 9-40 m keep the bilinear error below 3 grey levels)."""
    a = write_ortho(tmp_path / "a.tif", X0, X0 + 120, centre=CENTRE_A)
    b = write_ortho(tmp_path / "b.tif", X0 + 80, X0 + 200, centre=CENTRE_A, res=2.0)
    out = tmp_path / "m.tif"
    r = _run([a, b, "-o", out, "--dsm", write_dsm(tmp_path / "dsm.tif"), "--no-stac"])
    assert r.exit_code == 0, r.output
    with rasterio.open(out) as ds:
        m, t = ds.read(1), ds.transform
    assert t.a == 1.0 and m.shape == (120, 200)
    X, Y = np.meshgrid(t.c + t.a * (np.arange(m.shape[1]) + 0.5), t.f + t.e * (np.arange(m.shape[0]) + 0.5))
    assert np.abs(m - texture(X, Y))[2:-2, 2:-2].max() < 3.0


def _frame_dem(path):
    n = 120
    yy, xx = np.mgrid[0:n, 0:n]
    z = 100 + 8 * np.sin(xx / 7.0) + 0.1 * yy
    with rasterio.open(path, "w", driver="GTiff", width=n, height=n, count=1, dtype="float32", crs=CRS,
                       transform=rasterio.Affine(4.0, 0, X0 - 240, 0, -4.0, Y0 + 240)) as ds:
        ds.write(z.astype("float32"), 1)


def test_rectify_ortho_tags_the_centre_and_the_chain_runs(tmp_path):
    """The chain `rectify ortho --true-ortho` (two frames) -> `rectify mosaic --dsm`: the orthophotos carry the
    projection centres (ORTHO_CENTER_X/Y/Z = the exterior orientations' positions) and the mosaic takes them."""
    _frame_dem(tmp_path / "dem.tif")
    rr, cc = np.mgrid[0:60, 0:80]
    with rasterio.open(tmp_path / "img.tif", "w", driver="GTiff", width=80, height=60, count=1,
                       dtype="uint8") as ds:
        ds.write((100 + 50 * np.sin(cc / 3.0) * np.cos(rr / 4.0)).astype(np.uint8)[None])
    (tmp_path / "cam.json").write_text(json.dumps({"focal_length_mm": 10.0, "pixel_size_mm": 0.02, "width": 80,
                                                   "height": 60}))
    orthos = []
    for k, dx in enumerate((-40.0, 40.0)):
        pos = [X0 + dx, Y0, 600.0]
        (tmp_path / f"eo{k}.json").write_text(json.dumps({"position": pos, "crs": CRS,
                                                          "rotation": matrix_from_angles(0.02, -0.01, 0.1).tolist()}))
        o = tmp_path / f"o{k}.tif"
        r = CliRunner().invoke(cli, ["ortho", str(tmp_path / "img.tif"), "--dem", str(tmp_path / "dem.tif"),
                                     "--camera", str(tmp_path / "cam.json"), "--exterior",
                                     str(tmp_path / f"eo{k}.json"), "-o", str(o), "--resolution", "2",
                                     "--true-ortho", "--no-stac"])
        assert r.exit_code == 0, r.output
        with rasterio.open(o) as ds:
            tags = ds.tags()
        assert [float(tags[f"ORTHO_CENTER_{a}"]) for a in "XYZ"] == pos
        orthos.append(o)
    r = _run([*orthos, "-o", tmp_path / "m.tif", "--dsm", tmp_path / "dem.tif", "--provenance", "--no-stac"])
    assert r.exit_code == 0, r.output
    assert "seams of the least-transformed image" in r.output
    with rasterio.open(tmp_path / "m.source.tif") as ds:
        s = ds.read(1)
    assert (s == 1).sum() > 100 and (s == 2).sum() > 100
    # the lossy output of the shared tail: JPEG-in-TIFF COG, the invalid pixels in an internal mask
    r = _run([*orthos, "-o", tmp_path / "j.tif", "--dsm", tmp_path / "dem.tif", "--compress", "jpeg", "--cog",
              "--no-stac"])
    assert r.exit_code == 0, r.output
    with rasterio.open(tmp_path / "j.tif") as ds, rasterio.open(tmp_path / "m.tif") as lossless:
        assert ds.compression.name.lower() == "jpeg"  # (no overviews: smaller than one 512 px block)
        assert (ds.read_masks(1) > 0).sum() == (lossless.read_masks(1) > 0).sum()


def test_rpc_orthophotos_carry_a_view_direction(tmp_path):
    """An RPC has no projection centre: `rectify ortho --rpc` tags a point 1000 km up along the line of sight of
    the image centre (ORTHO_CENTER_KIND direction); its horizontal offset per metre up is the RPC's (from a
    localisation at two heights), so `--seams normal` works on RPC orthophotos too."""
    _frame_dem(tmp_path / "dem.tif")
    lon0, lat0 = transform_xy(CRS, "EPSG:4326", [[X0, Y0]])[0]
    m_lon, m_lat = 1.0 / (111_320 * np.cos(np.radians(lat0))), 1.0 / 111_320
    rpc = RPC.from_coefficients(offsets=(40.0, 40.0, lat0, lon0, 100.0),
                                scales=(40.0, 40.0, 80 * m_lat, 80 * m_lon, 50.0),
                                samp_num=[0.0, 1.0, 0.02, 0.1], line_num=[0.0, 0.02, -1.0, 0.03])
    with rasterio.open(tmp_path / "sat.tif", "w", driver="GTiff", width=80, height=80, count=1, dtype="uint8",
                       rpcs=rpc.to_rasterio()) as ds:
        ds.write(np.full((1, 80, 80), 120, np.uint8))
    r = CliRunner().invoke(cli, ["ortho", str(tmp_path / "sat.tif"), "--dem", str(tmp_path / "dem.tif"), "--rpc",
                                 "-o", str(tmp_path / "o.tif"), "--resolution", "2", "--dst-crs", CRS, "--no-stac"])
    assert r.exit_code == 0, r.output
    with rasterio.open(tmp_path / "o.tif") as ds:
        tags = ds.tags()
    assert tags["ORTHO_CENTER_KIND"] == "direction"
    c = np.array([float(tags[f"ORTHO_CENTER_{a}"]) for a in "XYZ"])
    # the RPC's own line of sight at the image centre: ground at 100 m and 200 m
    g = [transform_xy("EPSG:4326", CRS, rpc.localize(np.array([[39.5, 39.5]]), h)[:, :2])[0] for h in (100.0, 200.0)]
    d = (g[1] - g[0]) / 100.0
    assert np.allclose((c[:2] - g[0]) / (c[2] - 100.0), d, atol=1e-6)
