"""The rendered block of ``docs/block.md``'s example and of ``tests/cli/test_block.py``.

Two strips of three 400 x 300 px images rendered over a textured terrain with 8 m relief (0.25 m
ground pixel, :mod:`tests.support.block_render`), with the inputs a user gives ``stereo block``:
``camera.json``, ``poses.csv`` (GNSS positions with 5 cm noise in UTM 33N map coordinates, angles
0.5 deg off) and ``control.csv`` (12 control points on the terrain, measured in every image that
sees them with 0.2 px noise). Write them with::

    python -m tests.support.block_example OUTDIR

:func:`write_example_reconstruction` writes the same block as an OpenSfM ``reconstruction.json`` (its
local frame taken as topocentric about :data:`REFERENCE_LLA`, the shots' ``gps_position`` with 5 cm noise
and ``gps_dop`` 0.05 m; angles 0.5 deg off), as ``python -m tests.support.block_example OUTDIR --opensfm``.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from rectify.geometry.camera import Camera
from rectify.geometry.rotation import angles_from_matrix, matrix_from_angles
from stereo.block.types import Pose, project_pixel
from tests.support.block_render import make_terrain, render_block, strip_poses

__all__ = ["CAM", "CRS", "E0", "GSD", "H_FLY", "N0", "REFERENCE_LLA", "Z0", "write_example_block",
           "write_example_reconstruction"]

CAM = Camera(focal_length_mm=20.0, pixel_size_mm=0.05, width=400, height=300)
H_FLY = 100.0
Z0 = 50.0
GSD = H_FLY * CAM.pixel_size_mm / CAM.focal_length_mm  # 0.25 m
CRS = "EPSG:32633"
E0, N0 = 500000.0, 5000000.0  # the block sits at these map coordinates
#: the topocentric origin of the example's OpenSfM reconstruction: longitude, latitude (deg), height (m)
REFERENCE_LLA = (15.0, 45.13, 0.0)


def write_example_block(d: Path) -> tuple[list[Path], list[Pose], NDArray[np.float64]]:
    """Render the block into ``d`` and write its inputs; return the image paths, the true poses (local frame:
    add (E0, N0, 0) for map coordinates) and the true control points (local frame)."""
    d = Path(d)
    d.mkdir(parents=True, exist_ok=True)
    w, h = CAM.width * GSD, CAM.height * GSD
    ext = (-w / 2 - 20, -(1 - 0.3) * h - h / 2 - 20, 2 * 0.4 * w + w / 2 + 20, h / 2 + 20)
    terrain = make_terrain(ext, cell_m=GSD, base_height_m=Z0 - 3.0, relief_m=8.0, seed=3)
    poses = strip_poses(CAM, n_strips=2, n_per_strip=3, flying_height_m=H_FLY, ground_z=Z0, alternate=True,
                        angle_sigma_rad=0.01, seed=1, camera_id="camera")
    images = render_block(CAM, poses, terrain, d)
    (d / "camera.json").write_text(json.dumps(CAM.to_dict()))
    rng = np.random.default_rng(5)
    # GNSS positions (5 cm noise) in map coordinates, angles 0.5 deg off
    lines = [f"# crs={CRS}", "# angles=deg", "image,x,y,z,omega,phi,kappa,sx,sy,sz"]
    for p, path in zip(poses, images, strict=True):
        pos = p.position + [E0, N0, 0.0] + rng.normal(0, 0.05, 3)
        a = np.degrees(angles_from_matrix(p.rotation)) + rng.normal(0, 0.5, 3)
        lines.append(",".join([path.name, *(f"{v:.4f}" for v in pos), *(f"{v:.6f}" for v in a),
                               "0.05", "0.05", "0.05"]))
    (d / "poses.csv").write_text("\n".join(lines) + "\n")
    # control points on the terrain, measured in every image that sees them (0.2 px noise)
    x0, y0, x1, y1 = ext
    gx, gy = np.meshgrid(np.linspace(x0 + 40, x1 - 40, 4), np.linspace(y0 + 35, y1 - 35, 3))
    xy = np.column_stack([gx.ravel(), gy.ravel()])
    xyz = np.column_stack([xy, terrain.height(xy)])
    rows = [f"# crs={CRS}", "id,image,col,row,x,y,z"]
    for k, g in enumerate(xyz):
        for p, path in zip(poses, images, strict=True):
            px = project_pixel(CAM, p, g[None])[0]
            if np.isfinite(px).all() and 5 < px[0] < CAM.width - 6 and 5 < px[1] < CAM.height - 6:
                px = px + rng.normal(0, 0.2, 2)
                rows.append(f"C{k},{path.name},{px[0]:.3f},{px[1]:.3f},{g[0] + E0:.4f},{g[1] + N0:.4f},{g[2]:.4f}")
    (d / "control.csv").write_text("\n".join(rows) + "\n")
    return images, poses, xyz


def write_example_reconstruction(d: Path, images: list[Path], poses: list[Pose]) -> Path:
    """``d/reconstruction.json``: the example block as OpenSfM writes it (one ``perspective`` camera ``v1``;
    poses 0.5 deg and 5 cm off, ``gps_position`` with 5 cm noise, ``gps_dop`` 0.05 m; ``reference_lla``)."""
    rng = np.random.default_rng(7)
    s = max(CAM.width, CAM.height)
    shots = {}
    for p, path in zip(poses, images, strict=True):
        R = p.rotation @ matrix_from_angles(*rng.normal(0.0, np.radians(0.5), 3))
        C = p.position + rng.normal(0.0, 0.05, 3)
        R_cw = np.diag([1.0, -1.0, -1.0]) @ R.T  # world -> OpenCV camera axes
        shots[path.name] = {"camera": "v1", "rotation": Rotation.from_matrix(R_cw).as_rotvec().tolist(),
                            "translation": (-R_cw @ C).tolist(),
                            "gps_position": (p.position + rng.normal(0.0, 0.05, 3)).tolist(), "gps_dop": 0.05}
    rec = [{"cameras": {"v1": {"projection_type": "perspective", "width": CAM.width, "height": CAM.height,
                               "focal": CAM.focal_px / s, "k1": 0.0, "k2": 0.0}},
            "shots": shots, "points": {},
            "reference_lla": {"longitude": REFERENCE_LLA[0], "latitude": REFERENCE_LLA[1],
                              "altitude": REFERENCE_LLA[2]}}]
    out = Path(d) / "reconstruction.json"
    out.write_text(json.dumps(rec, indent=1))
    return out


if __name__ == "__main__":  # pragma: no cover - the docs' example inputs
    out = Path(sys.argv[1] if len(sys.argv) > 1 else "block_example")
    imgs, true_poses, _ = write_example_block(out)
    if "--opensfm" in sys.argv[2:]:
        write_example_reconstruction(out, imgs, true_poses)
    for p in imgs:
        print(p)
