"""Textbook known answers that run on a fresh clone (no shared data needed).

The numbers are small copies, in ``tests/data/textbook``, of the sample inputs and printed results of
the public-domain programs that accompany Wolf & Dewitt, "Elements of Photogrammetry"
(resect_sample, relor_sample, 3DCONF_sample). They pin the estimates *and* sigma0 and the standard
errors: dividing by n instead of the redundancy, or a wrong covariance scaling, changes printed digits.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from numpy.testing import assert_allclose

from rectify.geometry.rotation import matrix_from_angles
from stereo.pair.absolute import AbsoluteOrientation
from stereo.pair.intersection import intersect
from stereo.pair.resection import resect
from stereo.relative import RelativeOrientation

DATA = Path(__file__).resolve().parents[1] / "data" / "textbook"
SYSTEMS = ("left-image", "basis", "dobrynin-pimshina")


def _load(name: str) -> dict:
    return json.loads((DATA / name).read_text())


def test_files_are_present():
    """The copies are part of the repository: these tests never skip."""
    for name in ("resect_sample.json", "relor_sample.json", "3dconf_sample.json"):
        d = _load(name)
        assert "Wolf & Dewitt" in d["source"]


# ------------------------------------------------------------------ resection
def test_resect_sample():
    d = _load("resect_sample.json")
    pr = d["printed"]
    ids = [r[0] for r in d["points"]]
    a = np.array([r[1:] for r in d["points"]], float)
    eo = resect(a[:, :2], a[:, 2:], focal_length_mm=d["focal_length_mm"], ids=ids)
    assert_allclose(np.degrees(eo.angles), pr["omega_phi_kappa_deg"], atol=0.5e-4)
    assert_allclose(eo.position, pr["position"], atol=0.5e-4)
    assert_allclose(eo.residuals.residual, pr["residuals_xy"], atol=0.5e-4)
    # The program prints sqrt(v'v / n_obs) (10 observations) although it states 4 degrees of freedom.
    # sigma0 here divides by the redundancy 2 * 5 - 6 = 4: the exact ratio sqrt(10 / 4) pins it.
    n_obs, dof = 2 * len(ids), d["printed"]["degrees_of_freedom"]
    v = np.asarray(eo.residuals.residual)
    assert eo.sigma0 == pytest.approx(math.sqrt(float(np.sum(v * v)) / dof), rel=1e-12)
    k = math.sqrt(dof / n_obs)
    assert round(eo.sigma0 * k, 4) == pr["sigma0"]
    # and from the printed residuals themselves (4 decimals): sqrt(v'v / 4)
    pv = np.asarray(pr["residuals_xy"])
    assert eo.sigma0 == pytest.approx(math.sqrt(float(np.sum(pv * pv)) / dof), rel=0.03)
    se = eo.std_errors
    assert_allclose(np.degrees([se["omega"], se["phi"], se["kappa"]]) * k, pr["std_omega_phi_kappa_deg"],
                    atol=0.5e-4)
    assert_allclose(np.array([se["x"], se["y"], se["z"]]) * k, pr["std_position"], atol=0.5e-4)


# -------------------------------------------------------- relative orientation
@pytest.mark.parametrize("system", SYSTEMS)
def test_relor_sample(system):
    d = _load("relor_sample.json")
    pr = d["printed"]
    f, bx = d["focal_length_mm"], d["base_x"]
    ids = [r[0] for r in d["points"]]
    a = np.array([r[1:] for r in d["points"]], float)
    ro = RelativeOrientation.from_points(a[:, :2], a[:, 2:], focal_length_mm=f, system=system, ids=ids)
    wf = ro.western(bx=bx)
    got = {"omega_deg": (math.degrees(wf.omega), math.degrees(wf.std_omega)),
           "phi_deg": (math.degrees(wf.phi), math.degrees(wf.std_phi)),
           "kappa_deg": (math.degrees(wf.kappa), math.degrees(wf.std_kappa)),
           "YL": (wf.by, wf.std_by), "ZL": (f + wf.bz, wf.std_bz)}
    for key, (value, sd) in got.items():
        assert round(value, 4) == pytest.approx(pr[key][0], abs=1e-9), (key, value)
        assert round(sd, 4) == pytest.approx(pr[key][1], abs=1e-9), (key, sd)
    # one degree of freedom: 6 points - 5 elements
    assert round(ro.sigma0_mm, 4) == pr["sigma0"]
    assert ro.n_used - 5 == pr["degrees_of_freedom"]
    # Dewitt's y-residuals: yl - yr is our residual vertical parallax (printed to 4 decimals each)
    q = np.subtract(pr["y_residuals_left"], pr["y_residuals_right"])
    assert_allclose(np.abs(ro.parallax_mm), np.abs(q), atol=1.1e-4)


def test_relor_sample_object_points():
    """The printed model points: left centre at (0, 0, f), base (91.9825, YL, ZL - f), scale of the photo."""
    d = _load("relor_sample.json")
    pr = d["printed"]
    f, bx = d["focal_length_mm"], d["base_x"]
    a = np.array([r[1:] for r in d["points"]], float)
    ro = RelativeOrientation.from_points(a[:, :2], a[:, 2:], focal_length_mm=f, system="left-image")
    wf = ro.western(bx=bx)
    R2 = matrix_from_angles(wf.omega, wf.phi, wf.kappa)
    it = intersect(a[:, :2], a[:, 2:], rotation_left=np.eye(3), rotation_right=R2, base=[bx, wf.by, wf.bz],
                   focal_length_mm=f, centre_left=(0.0, 0.0, f))
    assert_allclose(it.points, pr["object_points"], atol=0.6e-4)


# -------------------------------------------------------- absolute orientation
def test_3dconf_sample():
    d = _load("3dconf_sample.json")
    pr = d["printed"]
    ids = [r[0] for r in d["control"]]
    c = np.array([r[1:] for r in d["control"]], float)
    pts = np.array([r[1:] for r in d["points"]], float)
    ao = AbsoluteOrientation.from_points(c[:, :3], c[:, 3:], ids=ids)
    p, se = ao.parameters, ao.std_errors
    assert round(p[0], 5) == pr["scale"][0]
    assert round(se[0], 5) == pr["scale"][1]
    assert_allclose(np.degrees(p[1:4]), pr["omega_phi_kappa_deg"], atol=0.5e-4)
    assert_allclose(np.degrees(se[1:4]), pr["std_omega_phi_kappa_deg"], atol=0.5e-4)
    assert_allclose(p[4:], pr["translation"], atol=0.5e-3)
    assert_allclose(se[4:], pr["std_translation"], atol=0.5e-3)
    # 18 observations - 7 parameters = 11 degrees of freedom
    v = np.asarray(ao.residuals.residual)
    assert ao.sigma0 == pytest.approx(math.sqrt(float(np.sum(v * v)) / 11), rel=1e-9)
    assert round(ao.sigma0, 5) == pr["sigma0"]
    assert_allclose(v, pr["residuals"], atol=0.5e-3)
    assert_allclose(ao(pts), pr["transformed_points"], atol=0.5e-3)
    sd = np.sqrt(np.einsum("nii->ni", ao.point_covariance(pts)))
    assert_allclose(sd, pr["transformed_points_sd"], atol=0.5e-3)
