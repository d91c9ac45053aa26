"""Issue 12: the Dobrynin-Pimshina system works for any base direction (photo frames turned so that the
base runs along x), e.g. for pairs from adjacent strips whose base runs along the image y axis."""

from __future__ import annotations

import numpy as np
import pytest

from rectify.errors import EstimationError
from stereo.relative import RelativeGeometry, RelativeOrientation
from stereo.relative.systems import SYSTEMS, TURNED_SYSTEMS, dobrynin_pimshina_for_base
from tests.support.stereo_support import simulate_pair


def _turned(pts, deg):
    t = np.radians(deg)
    c, s = np.cos(t), np.sin(t)
    return pts @ np.array([[c, -s], [s, c]]).T


@pytest.mark.parametrize("deg,name", [(0, "dobrynin-pimshina"), (90, "dobrynin-pimshina-rot270"),
                                      (-90, "dobrynin-pimshina-rot90"), (180, "dobrynin-pimshina-rot180")])
def test_any_base_direction(deg, name):
    sim = simulate_pair("vertical", n=150, noise_px=0.3, rng=4)
    left, right = _turned(sim.left_mm, deg), _turned(sim.right_mm, deg)   # base along +x, +y, -y, -x
    f = sim.focal_length_mm
    ref = RelativeOrientation.from_points(left, right, focal_length_mm=f, system="left-image")
    ro = RelativeOrientation.from_points(left, right, focal_length_mm=f, system="dobrynin-pimshina")
    assert ro.system == name
    # the same relative geometry as the left-image system, and the same residuals
    assert np.allclose(ro.relative_rotation, ref.relative_rotation, atol=1e-7)
    assert np.allclose(ro.base_left / np.linalg.norm(ro.base_left), ref.base_left / np.linalg.norm(ref.base_left),
                       atol=1e-7)
    assert ro.sigma0_mm == pytest.approx(ref.sigma0_mm, rel=1e-6)
    # downstream users get matrices for the original photo frames (JSON round trip)
    g = RelativeGeometry.from_relative(ro)
    assert np.allclose(g.rotation_left.T @ g.rotation_right, ref.relative_rotation, atol=1e-7)
    assert ro.to_dict()["system"] == name


def test_unturned_system_is_undefined_for_a_base_along_y():
    sim = simulate_pair("vertical", n=100, noise_px=0.0, rng=5)
    left, right = _turned(sim.left_mm, 90), _turned(sim.right_mm, 90)
    ref = RelativeOrientation.from_points(left, right, focal_length_mm=sim.focal_length_mm, system="left-image")
    with pytest.raises(EstimationError, match="undefined for this pair"):
        SYSTEMS["dobrynin-pimshina"].elements_from_relative(ref.relative_rotation, ref.base_left)
    p = TURNED_SYSTEMS["dobrynin-pimshina-rot270"].elements_from_relative(ref.relative_rotation, ref.base_left)
    R1, R2, b = TURNED_SYSTEMS["dobrynin-pimshina-rot270"].geometry(p)
    assert np.allclose(R1.T @ R2, ref.relative_rotation, atol=1e-9)
    assert abs(p[0]) < 0.1   # tau: the base runs along the turned x axis


def test_choice_of_turn():
    assert dobrynin_pimshina_for_base([1, 0.2, 0]).turn_deg == 0
    assert dobrynin_pimshina_for_base([0.1, 1, 0]).turn_deg == 270
    assert dobrynin_pimshina_for_base([0.1, -1, 0]).turn_deg == 90
    assert dobrynin_pimshina_for_base([-1, 0.1, 0]).turn_deg == 180
    for s in TURNED_SYSTEMS.values():
        assert np.allclose(s.turn @ s.turn.T, np.eye(3)) and np.isclose(np.linalg.det(s.turn), 1)
