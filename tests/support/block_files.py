"""A synthetic block (:func:`tests.support.block_synthetic.make_block`) written as the files a user gives
``stereo block``: placeholder images named like the block's, a camera JSON, a position/angle CSV (GNSS
positions with their sigma, perturbed angles), a block control CSV (the control points' image measurements
and ground coordinates); the tie tracks are returned, so that the matching can be skipped
(``run_block(..., tracks=ties)``).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from rectify.geometry.rotation import angles_from_matrix
from stereo.block.types import Tracks
from tests.support.block_synthetic import SyntheticBlock

__all__ = ["write_block_files"]


def write_block_files(tmp_path: Path, blk: SyntheticBlock, *, gnss: bool = True, control: bool = True,
                      checks: bool = True, pose_noise: bool = True, crs: str = "EPSG:32633",
                      pixels: dict[str, np.ndarray] | None = None
                      ) -> tuple[list[Path], Path, Path, Path | None, Tracks, tuple[str, ...]]:
    """Images, camera JSON, pose CSV, control CSV (None without control), tie tracks and check ids.

    ``pixels`` replaces the measured pixels of control points by id ((k, 2) in the order of their
    observations in the block's tracks).
    """
    d = tmp_path / "in"
    d.mkdir()
    images = []
    for name in blk.tracks.images:
        p = d / name
        p.write_bytes(b"placeholder")
        images.append(p)
    cam = d / "camera.json"
    cam.write_text(json.dumps(blk.camera.to_dict()))
    poses = d / "poses.csv"
    rows = [f"# crs={crs}", "# angles=deg", "image,x,y,z,omega,phi,kappa" + (",sx,sy,sz" if gnss else "")]
    src = blk.initial_poses if pose_noise else blk.true_poses
    for k, p in enumerate(src):
        pos = blk.gnss.position[k] if gnss else p.position
        a = np.degrees(angles_from_matrix(p.rotation))
        row = [p.image, *(repr(float(v)) for v in pos), *(repr(float(v)) for v in a)]
        if gnss:
            row += [repr(float(v)) for v in blk.gnss.sigma_m[k]]
        rows.append(",".join(row))
    poses.write_text("\n".join(rows) + "\n")
    ctrl_ids = set(blk.control.ids)
    t = blk.tracks
    is_ctrl = np.array([t.point_ids[i] in ctrl_ids for i in t.obs_point])
    cpath = None
    if control:
        cpath = d / "control.csv"
        lines = [f"# crs={crs}", "id,image,col,row,x,y,z,sx,sy,sz"]
        where = {c: k for k, c in enumerate(blk.control.ids)}
        seen: dict[str, int] = {}
        for k in np.flatnonzero(is_ctrl):
            pid = t.point_ids[t.obs_point[k]]
            g = blk.control.xyz[where[pid]]
            s = blk.control.sigma_m[where[pid]]
            px = t.obs_pixel[k]
            if pixels is not None and pid in pixels:
                px = pixels[pid][seen.get(pid, 0)]
            seen[pid] = seen.get(pid, 0) + 1
            lines.append(",".join([pid, t.images[t.obs_image[k]], repr(float(px[0])), repr(float(px[1])),
                                   *(repr(float(v)) for v in g), *(repr(float(v)) for v in s)]))
        cpath.write_text("\n".join(lines) + "\n")
    ties = t.subset(~is_ctrl)
    checks_ids = tuple(c for c, chk in zip(blk.control.ids, blk.control.check, strict=True) if chk) if checks else ()
    return images, cam, poses, cpath, ties, checks_ids
