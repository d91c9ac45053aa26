"""Issue 12: the absolute-orientation report: coordinates in the ground CRS, readable map ticks, a Q-Q
standardisation that is standard normal under the model, the tie points over both images and a
height-difference map at the check points."""

from __future__ import annotations

import csv

import numpy as np
import pytest

from rectify.geometry.points import ControlTable
from rectify.geometry.residuals import rms
from rectify.report.figures import residual_vector_figure, standardised_components
from stereo.actions.scene import make_scene
from stereo.pair.model import ModelOptions, build_model, match_control
from stereo.relative import RelativeGeometry, RelativeOrientation
from stereo.report.pair import absolute_table_in_ground, write_pair_report


@pytest.fixture(scope="module")
def scene():
    return make_scene(0, size_px=480)


def _model(scene, seed, robust="none", n_tie=250, n_ctrl=10, n_chk=30):
    rng = np.random.default_rng(seed)
    n = n_tie + n_ctrl + n_chk
    g = scene.random_ground_points(n, rng)
    cam = scene.camera
    pl = scene.pixel_from_ground(scene.left, g) + rng.normal(0, 0.3, (n, 2))
    pr = scene.pixel_from_ground(scene.right, g) + rng.normal(0, 0.3, (n, 2))
    ids = [f"t{i}" for i in range(n_tie)]
    ro = RelativeOrientation.from_pixels(pl[:n_tie], pr[:n_tie], cam, ids=ids)
    cids = [f"c{i}" for i in range(n_ctrl + n_chk)]
    ctrl = ControlTable(tuple(cids), pl[n_tie:], pr[n_tie:], g[n_tie:], crs=scene.crs)
    m = build_model(cam.photo_from_pixel(pl[:n_tie]), cam.photo_from_pixel(pr[:n_tie]),
                    RelativeGeometry.from_relative(ro), ids=ids, control=ctrl, control_mm=match_control(ctrl, cam),
                    options=ModelOptions(check_ids=tuple(cids[n_ctrl:]), robust=robust),
                    pixel_size_mm=cam.pixel_size_mm)
    return m, ro, g[n_tie:]


def test_table_in_ground_crs_and_standardised(scene):
    z_chk, z_fit = [], []
    for seed in range(4):
        m, _, truth = _model(scene, 40 + seed)
        t = absolute_table_in_ground(m)
        assert m.frame["name"] == "topocentric"
        # observed = the control file's map coordinates (not topocentric offsets)
        assert np.abs(t.observed - truth).max() < 1e-4
        assert np.allclose(t.residual, m.ground[[m.ids.index(i) for i in t.ids]] - truth, atol=1e-4)
        z = standardised_components(t)
        chk = np.asarray(t.check)
        z_chk.append(z[chk])
        z_fit.append(z[~chk])
    # standard normal under the model (the raw table divided metres by a unitless sigma0)
    assert 0.67 <= rms(np.concatenate(z_chk)) <= 1.5
    assert 0.5 <= rms(np.concatenate(z_fit)) <= 1.5


def test_pair_report_files(scene, tmp_path):
    m, ro, truth = _model(scene, 7)
    p = write_pair_report(m, tmp_path / "rep", title="pair", ro=ro, camera=scene.camera)
    d = p.parent
    assert (d / "fig_tie_points_over_the_images.png").is_file()
    assert (d / "fig_height_differences_at_check_points.png").is_file()
    ao_csv = next(f for f in d.glob("*.csv") if "absolute" in f.name)
    rows = list(csv.DictReader(ln for ln in ao_csv.read_text().splitlines() if not ln.startswith("#")))
    obs = np.array([[float(r["observed_0"]), float(r["observed_1"])] for r in rows])
    ids = [r["id"] for r in rows]
    idx = [int(i[1:]) for i in ids]
    assert np.abs(obs - truth[idx, :2]).max() < 1e-3        # map coordinates of the control file


def test_readable_map_ticks(scene):
    m, _, _ = _model(scene, 8)
    t = absolute_table_in_ground(m)
    fig = residual_vector_figure(t, positions=t.observed[:, :2], position_units="m", y_down=False)
    fig.canvas.draw()
    ax = fig.axes[0]
    for labels in (ax.get_xticklabels(), ax.get_yticklabels()):
        texts = [lab.get_text() for lab in labels if lab.get_text()]
        assert 2 <= len(texts) <= 8
        assert all("e" not in s and "\u2009" in s for s in texts if abs(float(s.replace("\u2009", "")
                                                                             .replace("\u2212", "-"))) >= 1e4)
    assert ax.xaxis.get_offset_text().get_text() == ""
