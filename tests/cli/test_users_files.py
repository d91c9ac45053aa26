"""Issue 12, users' files: spreadsheet CSVs (byte-order mark), duplicate match ids, one-to-one matches,
``rectify fit`` on a matches CSV, ``warp --gcps`` with GCPs outside the image."""

from __future__ import annotations

import hashlib
import json

import affine
import cv2
import numpy as np
import pytest
import skimage.data as skd
from click.testing import CliRunner

from rectify.cli.main import cli
from rectify.errors import InvalidInputError
from rectify.features.match import _one_to_one
from rectify.formats.gcps import read_gcps
from rectify.formats.tables import read_matches
from rectify.formats.transform import read_transform
from rectify.raster import io as rio
from rectify.raster.io import write_raster

H_TRUE = np.array([[1.1, 0.05, 10.0], [-0.02, 0.95, 20.0], [1e-4, -5e-5, 1.0]])


def _hash(p):
    return hashlib.sha256(p.read_bytes()).hexdigest()


def _files(d):
    return sorted(p.name for p in d.iterdir())


def _gcp_lines(n=10):
    rng = np.random.default_rng(3)
    pix = rng.uniform(0, 1000, (n, 2))
    q = np.c_[pix, np.ones(n)] @ H_TRUE.T
    tgt = q[:, :2] / q[:, 2:] * 10 + [500000, 4400000]
    return ["id,col,row,x,y"] + [f"G{i},{pix[i, 0]:.10f},{pix[i, 1]:.10f},{tgt[i, 0]:.6f},{tgt[i, 1]:.6f}"
                                 for i in range(n)]


@pytest.mark.parametrize("crs_line", [False, True])
def test_bom_before_header_or_crs_line_is_accepted(tmp_path, crs_line):
    g = tmp_path / "gcps.csv"
    lines = (["# crs=EPSG:32618"] if crs_line else []) + _gcp_lines()
    g.write_bytes(b"\xef\xbb\xbf" + ("\r\n".join(lines) + "\r\n").encode())   # as Excel writes it
    t = read_gcps(g)
    assert t.ids[0] == "G0" and len(t) == 10
    assert t.crs == ("EPSG:32618" if crs_line else None)
    before = _hash(g)
    out = tmp_path / "t.json"
    r = CliRunner().invoke(cli, ["fit", str(g), "-o", str(out)])
    assert r.exit_code == 0, r.output
    assert json.loads(out.read_text())["method"] == "homography"
    assert _hash(g) == before


def _matches_csv(path, rows):
    path.write_text("id,col_left,row_left,col_right,row_right,score\n"
                    + "".join(f"{i},{a:.6f},{b:.6f},{c:.6f},{d:.6f},0.5\n" for i, (a, b, c, d) in rows))


def _matches_rows(n=30):
    rng = np.random.default_rng(5)
    right = rng.uniform(0, 800, (n, 2))
    q = np.c_[right, np.ones(n)] @ H_TRUE.T
    left = q[:, :2] / q[:, 2:]
    return [(str(i + 1), (*left[i], *right[i])) for i in range(n)], left, right


def test_duplicate_match_ids_rejected(tmp_path):
    rows, _, _ = _matches_rows()
    rows[7] = ("3", rows[7][1])
    m = tmp_path / "m.csv"
    _matches_csv(m, rows)
    with pytest.raises(InvalidInputError, match=r"duplicate match id\(s\) \['3'\]"):
        read_matches(m)
    before, files = _hash(m), _files(tmp_path)
    r = CliRunner().invoke(cli, ["fit", str(m), "-o", str(tmp_path / "t.json")])
    assert r.exit_code == 1 and "duplicate match id(s) ['3']" in r.output and "Traceback" not in r.output
    assert _hash(m) == before and _files(tmp_path) == files


def test_fit_reads_a_matches_csv(tmp_path):
    rows, left, right = _matches_rows()
    m = tmp_path / "m.csv"
    _matches_csv(m, rows)
    before = _hash(m)
    out = tmp_path / "t.json"
    r = CliRunner().invoke(cli, ["fit", str(m), "-o", str(out)])
    assert r.exit_code == 0, r.output
    model = read_transform(out).model                   # right pixels -> left pixels
    assert np.abs(model(right) - left).max() < 1e-3
    assert "px" in r.output and _hash(m) == before


def test_one_to_one_keeps_the_best_score():
    pl = np.array([[10.0, 10.0], [10.0, 10.0], [20.0, 20.0], [30.0, 30.0], [40.0, 40.0]])
    pr = np.array([[11.0, 11.0], [12.0, 12.0], [21.0, 21.0], [21.02, 21.0], [41.0, 41.0]])
    score = np.array([0.5, 0.2, 0.3, 0.1, 0.4])
    keep = _one_to_one(pl, pr, score)
    assert keep.tolist() == [1, 3, 4]


def test_match_output_is_one_to_one(tmp_path):
    img = skd.astronaut()[:400, :440]
    H = np.array([[0.98, 0.03, 6.0], [-0.02, 1.0, -4.0], [0, 0, 1.0]])
    warped = cv2.warpPerspective(img, H, (440, 400), flags=cv2.INTER_CUBIC)
    lp, rp = tmp_path / "left.tif", tmp_path / "right.tif"
    rio.write_raster(lp, img, affine.Affine.identity(), None)
    rio.write_raster(rp, warped, affine.Affine.identity(), None)
    out = tmp_path / "m.csv"
    r = CliRunner().invoke(cli, ["match", str(lp), str(rp), "-o", str(out)])
    assert r.exit_code == 0, r.output
    m = read_matches(out)
    for p in (m.left, m.right):
        q = np.round(p / 0.1).astype(np.int64)
        assert len(np.unique(q, axis=0)) == len(m)
    # the matches feed 'rectify fit' directly (right -> left)
    r = CliRunner().invoke(cli, ["fit", str(out), "-o", str(tmp_path / "t.json")])
    assert r.exit_code == 0, r.output


def test_warp_accepts_gcps_outside_the_image(tmp_path):
    rr, cc = np.mgrid[0:48, 0:64]
    img = np.stack([10 + 2 * cc + 2 * rr + 10 * k for k in range(3)], axis=-1).astype(np.uint8)
    src = tmp_path / "frame.tif"
    write_raster(src, img, affine.Affine(1, 0, 0, 0, 1.0000001, 0), None, nodata=0)
    A = np.array([[29.0, 6.0, 500100.0], [5.0, -31.0, 4399900.0]])
    pix = np.array([[2, 3], [60, 4], [5, 44], [58, 45], [30, 20], [12, 30], [45, 12], [500, 10]], float)
    tgt = pix @ A[:, :2].T + A[:, 2]
    g = tmp_path / "gcps.csv"
    g.write_text("# crs=EPSG:32618\nid,col,row,x,y\n" + "".join(
        f"p{i},{c},{r},{x:.6f},{y:.6f}\n" for i, ((c, r), (x, y)) in enumerate(zip(pix, tgt, strict=True))))
    out = tmp_path / "o.tif"
    r = CliRunner().invoke(cli, ["warp", str(src), str(out), "--gcps", str(g), "--method", "affine"])
    assert r.exit_code == 0, r.output
    assert "1 GCP(s) outside the 64 x 48 image, used for the fit; first is 'p7'" in r.output
    assert out.is_file()


# --------------------------------------------------------------------------- GCPs from GeoJSON, GeoPackage, GeoTIFF
A_UTM = np.array([[29.0, 6.0, 500100.0], [5.0, -31.0, 4399900.0]])
PIX = np.array([[2, 3], [60, 4], [5, 44], [58, 45], [30, 20], [12, 30], [45, 12]], float)


def _frame(tmp_path, name="frame.tif", gcps=None):
    rr, cc = np.mgrid[0:48, 0:64]
    img = np.stack([10 + 2 * cc + 2 * rr + 10 * k for k in range(3)], axis=-1).astype(np.uint8)
    src = tmp_path / name
    write_raster(src, img, affine.Affine(1, 0, 0, 0, 1.0000001, 0), None, nodata=0)
    if gcps is not None:
        import rasterio
        from rasterio.control import GroundControlPoint
        from rasterio.crs import CRS

        with rasterio.open(src, "r+") as ds:   # GDAL pixel/line: corners, so centres are at +0.5
            ds.gcps = ([GroundControlPoint(row=r + 0.5, col=c + 0.5, x=x, y=y, id=f"e{i}")
                        for i, ((c, r), (x, y)) in enumerate(gcps)], CRS.from_epsg(32618))
    return src


def _tgt():
    return PIX @ A_UTM[:, :2].T + A_UTM[:, 2]


def _check_output(out):
    import rasterio

    with rasterio.open(out) as ds:
        assert ds.crs.to_epsg() == 32618
        x, y = A_UTM[:, :2] @ [30, 20] + A_UTM[:, 2]
        row, col = ds.index(x, y)
        assert abs(int(ds.read(1)[row, col]) - (10 + 2 * 30 + 2 * 20)) <= 3


def _geojson(path, style):
    tgt = _tgt()
    feats = []
    for i, ((c, r), (x, y)) in enumerate(zip(PIX, tgt, strict=True)):
        if style == "colrow":
            props = {"id": f"g{i}", "col": c, "row": r}
        else:    # QGIS-like: pixel corners, negative rows, a 'name'
            props = {"name": f"g{i}", "sourceX": c + 0.5, "sourceY": -(r + 0.5), "enable": 1}
        feats.append({"type": "Feature", "geometry": {"type": "Point", "coordinates": [x, y]}, "properties": props})
    doc = {"type": "FeatureCollection", "crs": {"type": "name", "properties": {"name": "urn:ogc:def:crs:EPSG::32618"}},
           "features": feats}
    path.write_text(json.dumps(doc))


@pytest.mark.parametrize("kind", ["geojson-colrow", "geojson-qgis", "gpkg", "embedded", "embedded-auto"])
def test_gcp_files_rectify_end_to_end(tmp_path, kind):
    from rectify.formats.gcps import write_gcps_gpkg
    from rectify.geometry.points import GcpTable

    src = _frame(tmp_path, gcps=list(zip(PIX, _tgt(), strict=True)) if kind.startswith("embedded") else None)
    args_gcps: list[str] = []
    if kind.startswith("geojson"):
        g = tmp_path / "gcps.geojson"
        _geojson(g, kind.split("-")[1])
        args_gcps = ["--gcps", str(g)]
    elif kind == "gpkg":
        g = tmp_path / "gcps.gpkg"
        write_gcps_gpkg(g, GcpTable(tuple(f"g{i}" for i in range(len(PIX))), PIX, _tgt(), None,
                                    np.zeros(len(PIX), bool), "EPSG:32618"))
        args_gcps = ["--gcps", str(g)]
    elif kind == "embedded":
        g = src
        args_gcps = ["--gcps", str(src)]
    else:
        g = src
    t = read_gcps(g)
    assert len(t) == 7 and t.crs == "EPSG:32618"
    assert np.abs(t.pixel - PIX).max() < 1e-9 and np.abs(t.target - _tgt()).max() < 1e-6
    before = {p.name: _hash(p) for p in tmp_path.iterdir()}
    out = tmp_path / "out.tif"
    r = CliRunner().invoke(cli, ["warp", str(src), str(out), *args_gcps, "--method", "affine"])
    assert r.exit_code == 0, r.output
    assert "7 fit points" in r.output
    _check_output(out)
    assert (tmp_path / "out.stac.json").is_file()  # the STAC Item beside the output (issue 29)
    assert {p.name: _hash(p) for p in tmp_path.iterdir() if p.name not in ("out.tif", "out.stac.json")} == before
    r = CliRunner().invoke(cli, ["fit", str(g), "-o", str(tmp_path / "t.json"), "--method", "affine"])
    assert r.exit_code == 0, r.output


def test_geojson_without_crs_is_lonlat_and_bad_geojson_is_named(tmp_path):
    g = tmp_path / "g.geojson"
    feats = [{"type": "Feature", "geometry": {"type": "Point", "coordinates": [30.0 + i * 0.01, 50.0 + i * 0.01]},
              "properties": {"col": float(c), "row": float(r)}} for i, (c, r) in enumerate(PIX)]
    g.write_text(json.dumps({"type": "FeatureCollection", "features": feats}))
    t = read_gcps(g)
    assert t.crs == "EPSG:4326" and t.ids[0] == "1"
    feats[2]["properties"] = {"x": 1}
    g.write_text(json.dumps({"type": "FeatureCollection", "features": feats}))
    src = _frame(tmp_path)
    before = {p.name: _hash(p) for p in tmp_path.iterdir()}
    r = CliRunner().invoke(cli, ["warp", str(src), str(tmp_path / "o.tif"), "--gcps", str(g)])
    assert r.exit_code == 1 and "feature 2: no pixel coordinates" in r.output and "Traceback" not in r.output
    assert {p.name: _hash(p) for p in tmp_path.iterdir()} == before
    # no --gcps and no embedded GCPs: named
    r = CliRunner().invoke(cli, ["warp", str(src), str(tmp_path / "o.tif")])
    assert r.exit_code != 0 and "carries no embedded GCPs" in r.output
    assert {p.name: _hash(p) for p in tmp_path.iterdir()} == before
