"""Space resection: Dewitt known answer, synthetic truth, initial methods, bad input."""

from __future__ import annotations

import json

import numpy as np
import pytest
from numpy.testing import assert_allclose

from rectify.errors import EstimationError, InvalidInputError, ShapeError
from rectify.geometry.rotation import matrix_from_angles
from stereo.formats.orientation import read_exterior
from stereo.pair.resection import ExteriorOrientation, resect


def _dewitt(path):
    lines = [ln for ln in (path / "resect_sample.dat").read_text().splitlines() if ln.strip()]
    f = float(lines[0])
    rows = [ln.split() for ln in lines[1:]]
    a = np.array([r[1:] for r in rows], float)
    return f, [r[0] for r in rows], a[:, :2], a[:, 2:]


def test_dewitt_resect_sample(dewitt):
    f, ids, xy, XYZ = _dewitt(dewitt)
    eo = resect(xy, XYZ, focal_length_mm=f, ids=ids)
    # printed: Omega -0.4109, Phi 1.2108, Kappa 102.8003 deg; XL 1027.8700, YL 1044.1143, ZL 611.1973
    assert_allclose(np.degrees(eo.angles), [-0.4109, 1.2108, 102.8003], atol=0.5e-4)
    assert_allclose(eo.position, [1027.8700, 1044.1143, 611.1973], atol=0.5e-4)
    # printed residuals (x, y), 4 decimals
    printed = np.array([[0.0014, -0.0014], [0.0006, 0.0030], [0.0015, 0.0009], [-0.0030, 0.0001],
                        [-0.0005, -0.0025]])
    assert_allclose(eo.residuals.residual, printed, atol=0.5e-4)
    assert eo.residuals.ids == tuple(ids)
    # Dewitt prints "Standard error of unit weight: 0.0018" with "Degrees of freedom: 4", but
    # 0.0018 = sqrt(v'v / 10): it divides by the 10 observations, not the redundancy 4. Our
    # sigma0 divides by the redundancy; rescaled to Dewitt's divisor every printed figure matches.
    k = np.sqrt(4 / 10)
    assert round(eo.sigma0 * k, 4) == 0.0018
    se = eo.std_errors
    assert_allclose(np.degrees([se["omega"], se["phi"], se["kappa"]]) * k, [0.0009, 0.0009, 0.0004],
                    atol=0.5e-4)
    assert_allclose(np.array([se["x"], se["y"], se["z"]]) * k, [0.0124, 0.0125, 0.0045], atol=0.5e-4)


def _scene(rng, n=12, noise=0.003, pp=(0.02, -0.03)):
    R = matrix_from_angles(0.05, -0.03, 2.0)
    C = np.array([-55094.5, -3727407.0, 5258.3])
    G = np.column_stack([C[0] + rng.uniform(-3000, 3000, n), C[1] + rng.uniform(-3000, 3000, n),
                         rng.uniform(150, 780, n)])
    eo = ExteriorOrientation(position=C, rotation=R, focal_length_mm=120.0, principal_point_mm=pp)
    return eo, G, eo.project(G) + rng.normal(0, noise, (n, 2))


@pytest.mark.parametrize("initial", ["pnp", "dlt"])
@pytest.mark.parametrize("free", [False, True])
def test_synthetic_truth_exact(initial, free):
    eo0, G, x = _scene(np.random.default_rng(1), noise=0.0)
    eo = resect(x, G, focal_length_mm=118.0 if free else 120.0,
                principal_point_mm=(0.0, 0.0) if free else (0.02, -0.03), initial=initial,
                free_interior=free)
    assert_allclose(eo.position, eo0.position, atol=1e-5)
    assert_allclose(eo.rotation, eo0.rotation, atol=1e-9)
    assert_allclose(eo.focal_length_mm, 120.0, atol=1e-8)
    assert_allclose(eo.principal_point_mm, [0.02, -0.03], atol=1e-8)
    assert len(eo.std_errors) == (9 if free else 6)


def test_std_errors_predict_scatter():
    rng = np.random.default_rng(2)
    z = []
    for _ in range(150):
        eo0, G, x = _scene(rng, noise=0.004)
        eo = resect(x, G, focal_length_mm=120.0, principal_point_mm=(0.02, -0.03))
        se = eo.std_errors
        z.append((eo.position - eo0.position) / [se["x"], se["y"], se["z"]])
    rms = np.sqrt(np.mean(np.square(z), axis=0))
    assert np.all((rms > 0.75) & (rms < 1.3)), rms


def test_check_points_and_json_roundtrip(tmp_path):
    eo0, G, x = _scene(np.random.default_rng(3))
    chk = np.zeros(len(G), bool)
    chk[:3] = True
    eo = resect(x, G, focal_length_mm=120.0, principal_point_mm=(0.02, -0.03), check=chk, crs="EPSG:32735")
    s = eo.residuals.summary()
    assert s["n_check"] == 3 and s["n_fit"] == 9 and s["rmse_check"] < 0.02
    d = eo.to_dict()
    assert d["angles"]["system"] == "omega-phi-kappa" and d["crs"] == "EPSG:32735"
    p = tmp_path / "eo.json"
    p.write_text(json.dumps(d))
    eo2 = read_exterior(p)
    assert_allclose(eo2.project(G), eo.project(G), atol=1e-12)


def test_bad_input():
    eo0, G, x = _scene(np.random.default_rng(4))
    with pytest.raises(EstimationError, match="too few control points for space resection: 2 given"):
        resect(x[:2], G[:2], focal_length_mm=120.0)
    with pytest.raises(EstimationError, match="4 given, at least 5 needed"):
        resect(x[:4], G[:4], focal_length_mm=120.0, free_interior=True)
    line = np.column_stack([np.linspace(0, 100, 5), np.linspace(0, 50, 5), np.full(5, 10.0)])
    with pytest.raises(EstimationError, match="collinear"):
        resect(x[:5], line, focal_length_mm=120.0)
    with pytest.raises(EstimationError, match="too few points for the DLT: 5 given"):
        resect(x[:5], G[:5], focal_length_mm=120.0, initial="dlt")
    with pytest.raises(InvalidInputError, match="unknown initial method 'svd'"):
        resect(x, G, focal_length_mm=120.0, initial="svd")
    with pytest.raises(ShapeError, match="same number of points"):
        resect(x, G[:-1], focal_length_mm=120.0)
    with pytest.raises(InvalidInputError, match="focal_length_mm"):
        resect(x, G, focal_length_mm=0.0)
