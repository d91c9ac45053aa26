"""Seed 003's studies (scripts/convergent_study.py, square_block_study.py, projective_images_study.py) on tiny
configurations, against closed forms and counts stated by the seed."""

from __future__ import annotations

import importlib.util
import math
import sys
from types import ModuleType

import numpy as np
import pytest

from tests.support.scripts_support import SCRIPTS


def load_script(name: str) -> ModuleType:
    """``scripts/<name>.py`` as a module registered in ``sys.modules`` (its dataclasses need it)."""
    spec = importlib.util.spec_from_file_location(f"seed003_{name}", SCRIPTS / f"{name}.py")
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def conv():
    return load_script("convergent_study")


@pytest.fixture(scope="module")
def block():
    return load_script("square_block_study")


@pytest.fixture(scope="module")
def proj():
    return load_script("projective_images_study")


def test_normal_case_height_precision_formula(conv):
    """The intersection code's propagated precision equals the normal-case formulas (m_Y = Y^2 / (B f) sqrt 2
    m_x, m_X = m_Z = Y / (f sqrt 2) m_x) for a point midway in front of the base; Monte Carlo agrees within 6 %."""
    depth, base, sigma = 15.0, 5.0, 0.5
    fx, fz, fy = conv.normal_case_sigmas(depth, base, conv.FOCAL_PX, sigma)
    assert fy == pytest.approx(15.0 ** 2 / (5.0 * 2400.0) * math.sqrt(2) * 0.5)  # 13.26 mm
    P = np.array([[base / 2, 0.0, -depth]])
    prop, mc, inside = conv.precision(conv.Pair(base), P, sigma, 4000, np.random.default_rng(0))
    assert inside == 1.0
    assert prop == pytest.approx([fx, fz, fy], rel=2e-3)
    assert mc == pytest.approx([fx, fz, fy], rel=0.06)
    # convergence at the same base and point: the same intersection angle, the same depth precision (within 3 %)
    conv_prop, _, _ = conv.precision(conv.Pair(base, math.atan(base / 2 / depth)), P, sigma, 0, None)
    assert conv_prop[2] == pytest.approx(fy, rel=0.03)
    assert conv.normal_max_base(15.0, 8.0) == pytest.approx(15.0 * 2048 / 2400 - 8.0)


def test_square_block_counts_of_the_seed(block):
    """Seed 003, 2.2.1: a square-symmetric 60/60 block shows a point in up to 9 images and up to 20 models
    (neighbour pairs: 12 along/across + 8 diagonal); the 60/30 block up to 6 images; the useful areas of
    20 x 20 blocks are 19 b x 19 a."""
    sq = block.block_geometry(block.SQUARE, samples=81)
    tr = block.block_geometry(block.TRADITIONAL, samples=81)
    assert (sq.max_images, sq.max_models) == (9, 20)
    assert (tr.max_images, tr.max_models) == (6, 11)
    assert sq.useful_area == pytest.approx((19 * 0.4) ** 2)
    assert tr.useful_area == pytest.approx(19 * 0.4 * 19 * 0.7)


def test_square_block_bundle_tiny(block):
    f = block.adjust_scheme(block.SQUARE, 3, 4, 0, 300)
    assert f.images == 12 and f.points > 30
    assert 0.8 < f.sigma0 < 1.2
    assert 0.7 < f.sx / f.sy < 1.4 and f.sz > f.sx


def test_projective_images_dlt_residual_closed_form(proj):
    """Images with set errors sigma: the realised errors have that standard deviation, and the DLT's RMS residual
    is sigma sqrt((2N - 11) / 2N) (within 8 % over 12 images)."""
    r = proj.simulate(proj.ProjectiveCamera(), 0.5, 12, np.random.default_rng(1), 60)
    assert r["std_x"] == pytest.approx(0.5, rel=0.08) and r["std_y"] == pytest.approx(0.5, rel=0.08)
    assert r["rms"] == pytest.approx(proj.expected_dlt_rms(0.5, 60), rel=0.08)
    assert proj.expected_dlt_rms(1.0, 60) == pytest.approx(math.sqrt(109 / 120))
