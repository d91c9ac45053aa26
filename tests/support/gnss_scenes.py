"""Synthetic blocks with systematic GNSS/INS errors, shared by the tests of `stereo.block.bundle.systematic`
and `scripts/gnss_ins_study.py` (issue 25).

Every scene is a :func:`tests.support.block_synthetic.make_block` block (image names ``s{strip}_{order}``)
whose GNSS or INS observations carry a known error:

- :func:`drift_block`: per-strip GNSS shifts ``SHIFT`` (m) and drifts ``DRIFT`` (m/s) about the strip's mean
  exposure time;
- :func:`boresight_block`: INS angles rotated by a boresight error ``BORESIGHT`` (radians, rotation vector);
- :func:`correlated_gnss_block`: GNSS errors correlated along (1, 1, 0) in strip 0 and (1, -1, 0) in strip 1
  (rho +-0.995, sigma 0.5 m plan, 0.05 m height) with their full 3 x 3 covariances.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from rectify.geometry.rotation import angles_from_matrix
from stereo.block.types import GnssObservations
from tests.support.block_synthetic import SyntheticBlock, make_block

SHIFT = np.array([[0.9, -0.6, 0.75], [-0.75, 0.45, -0.9], [0.3, 0.9, 0.6], [-0.6, -0.3, 1.05]])     # m
DRIFT = np.array([[0.03, -0.015, 0.024], [-0.018, 0.03, 0.012], [0.0, -0.024, 0.03], [0.015, 0.015, -0.03]])  # m/s
BORESIGHT = np.radians([0.05, -0.08, 0.12])  # rotation vector, radians


def strips(names: tuple[str, ...]) -> tuple[tuple[str, ...], np.ndarray, np.ndarray]:
    """Strip labels, strip index (N,) and exposure time (N,) in s (600 s between strips, 4 s between images)
    of make_block's image names ``s{strip}_{order}``."""
    strip = tuple(n.split("_")[0] for n in names)
    lab = np.array([int(s[1:]) for s in strip])
    order = np.array([int(n.split("_")[1]) for n in names])
    return strip, lab, 600.0 * lab + 4.0 * order


def drift_block() -> tuple[SyntheticBlock, GnssObservations]:
    """4 strips of 8 images, 5 control points, 8 check points; GNSS with SHIFT and DRIFT per strip (time and strip
    given, so that ``--gnss-drift`` can model them)."""
    blk = make_block(3, strips=4, images_per_strip=8, n_points=900, gnss_noise_m=0.05, ins_noise_rad=2e-4, n_check=8)
    g = blk.gnss
    strip, lab, t = strips(g.images)
    tm = np.array([t[lab == k].mean() for k in range(4)])
    pos = g.position + SHIFT[lab] + DRIFT[lab] * (t - tm[lab])[:, None]
    return blk, GnssObservations(g.images, pos, g.sigma_m, g.lever_arm_m, g.angles, g.sigma_rad, time=t, strip=strip)


def boresight_block() -> tuple[SyntheticBlock, GnssObservations]:
    """3 strips of 8 images; INS omega-phi-kappa angles of R @ Rot(-BORESIGHT) plus 2e-4 rad noise, strips given."""
    blk = make_block(5, strips=3, images_per_strip=8, n_points=900, gnss_noise_m=0.05, ins_noise_rad=2e-4, n_check=8)
    g = blk.gnss
    strip, _, _ = strips(g.images)
    R = np.array([p.rotation for p in blk.true_poses])
    Ro = R @ Rotation.from_rotvec(-BORESIGHT).as_matrix()
    ang = np.asarray(angles_from_matrix(Ro, "omega-phi-kappa")).reshape(-1, 3)
    ang = ang + np.random.default_rng(1).normal(0, 2e-4, ang.shape)
    return blk, GnssObservations(g.images, g.position, g.sigma_m, g.lever_arm_m, ang, g.sigma_rad, strip=strip)


def correlated_gnss_block() -> tuple[SyntheticBlock, GnssObservations, GnssObservations]:
    """2 strips of 10 images, no control (GNSS datum), tight INS angles (2e-5 rad); GNSS positions with strongly
    correlated plan errors. Returns the block and its observations with the full covariances (N, 3, 3) and with
    the diagonal sigmas (N, 3) alone."""
    blk = make_block(11, strips=2, images_per_strip=10, n_points=1500, gnss_noise_m=0.0, ins_noise_rad=2e-5,
                     control_layout="none", n_check=8, forward_overlap=0.8, side_overlap=0.5)
    g = blk.gnss
    _, lab, _ = strips(g.images)
    rng = np.random.default_rng(4)
    s, rho = 0.5, 0.995
    cov = np.zeros((len(lab), 3, 3))
    err = np.zeros((len(lab), 3))
    for i, k in enumerate(lab):
        r = rho if k == 0 else -rho
        cov[i] = [[s * s, r * s * s, 0.0], [r * s * s, s * s, 0.0], [0.0, 0.0, 0.05 ** 2]]
        err[i] = np.linalg.cholesky(cov[i]) @ rng.normal(size=3)
    pos = g.position + err
    sig = np.sqrt(np.diagonal(cov, axis1=1, axis2=2))
    return (blk, GnssObservations(g.images, pos, sig, None, g.angles, g.sigma_rad, covariance=cov),
            GnssObservations(g.images, pos, sig, None, g.angles, g.sigma_rad))
