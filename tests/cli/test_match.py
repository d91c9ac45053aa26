"""CLI: rectify match end to end on tiny files; bad input gives a clear error and no CSV."""

from __future__ import annotations

import affine
import cv2
import numpy as np
import skimage.data as skd
from click.testing import CliRunner

from rectify.cli.main import cli
from rectify.formats.tables import read_matches
from rectify.raster import io as rio


def _pair(tmp_path):
    img = skd.astronaut()[:400, :440]
    H = np.array([[0.98, 0.03, 6.0], [-0.02, 1.0, -4.0], [0, 0, 1.0]])
    warped = cv2.warpPerspective(img, H, (440, 400), flags=cv2.INTER_CUBIC)
    lp, rp = tmp_path / "left.tif", tmp_path / "right.png"
    rio.write_raster(lp, img, affine.Affine.identity(), None)
    cv2.imwrite(str(rp), cv2.cvtColor(warped, cv2.COLOR_RGB2BGR))       # plain PNG input too
    return lp, rp, H


def test_match_end_to_end_with_report(tmp_path):
    lp, rp, H = _pair(tmp_path)
    out = tmp_path / "m.csv"
    res = CliRunner().invoke(cli, ["match", str(lp), str(rp), "-o", str(out), "--max-matches", "300",
                                   "--report", str(tmp_path / "rep")])
    assert res.exit_code == 0, res.output
    for word in ("detected:", "matched:", "verified:", "refined:", "verification RMSE:", "px"):
        assert word in res.output
    m = read_matches(out)
    assert 100 < len(m) <= 300
    q = np.c_[m.left, np.ones(len(m))] @ H.T
    e = np.linalg.norm(q[:, :2] / q[:, 2:] - m.right, axis=1)
    assert np.median(e) < 0.1
    assert (tmp_path / "rep" / "report.html").is_file()
    import matplotlib.image

    for name in ("fig_matches.png", "fig_density.png"):  # decoded, drawn (not blank)
        img = matplotlib.image.imread(tmp_path / "rep" / name)
        assert min(img.shape[:2]) >= 200 and np.ptp(img[..., :3]) > 0.5, (name, img.shape)
    # never overwrite without --overwrite
    res2 = CliRunner().invoke(cli, ["match", str(lp), str(rp), "-o", str(out)])
    assert res2.exit_code != 0 and "exists" in res2.output
    res3 = CliRunner().invoke(cli, ["match", str(lp), str(rp), "-o", str(out), "--overwrite", "--no-refine",
                                    "--detector", "orb", "--verify", "fundamental"])
    assert res3.exit_code == 0, res3.output
    assert "Sampson" in res3.output and "refined:" not in res3.output


def test_unreadable_file(tmp_path):
    _, rp, _ = _pair(tmp_path)
    bad = tmp_path / "bad.tif"
    bad.write_bytes(b"\x00garbage")
    out = tmp_path / "m.csv"
    res = CliRunner().invoke(cli, ["match", str(bad), str(rp), "-o", str(out)])
    assert res.exit_code == 1 and "RasterIOError" in res.output and "bad.tif" in res.output
    assert not out.exists()


def test_blank_image(tmp_path):
    lp, _, _ = _pair(tmp_path)
    blank = tmp_path / "blank.tif"
    rio.write_raster(blank, np.full((300, 300, 3), 128, np.uint8), affine.Affine.identity(), None)
    out = tmp_path / "m.csv"
    res = CliRunner().invoke(cli, ["match", str(lp), str(blank), "-o", str(out)])
    assert res.exit_code == 1 and "blank" in res.output
    assert not out.exists()


def test_non_overlapping(tmp_path):
    lp, _, _ = _pair(tmp_path)
    other = tmp_path / "other.tif"
    rio.write_raster(other, skd.coffee(), affine.Affine.identity(), None)
    out = tmp_path / "m.csv"
    res = CliRunner().invoke(cli, ["match", str(lp), str(other), "-o", str(out)])
    assert res.exit_code == 1 and "do not overlap" in res.output
    assert not out.exists()


def test_bad_options(tmp_path):
    lp, rp, _ = _pair(tmp_path)
    out = tmp_path / "m.csv"
    r = CliRunner().invoke(cli, ["match", str(lp), str(rp), "-o", str(out), "--detector", "surf"])
    assert r.exit_code == 2 and "surf" in r.output
    r = CliRunner().invoke(cli, ["match", str(lp), str(rp), "-o", str(out), "--max-matches", "0"])
    assert r.exit_code == 2
    r = CliRunner().invoke(cli, ["match", str(lp), str(rp), "-o", str(tmp_path / "nodir" / "m.csv")])
    assert r.exit_code == 1 and "does not exist" in r.output
    assert not out.exists()
