"""A synthetic aerial block on a curved Earth, written as the files of ``stereo block --observations``.

:func:`make_curved_block` flies ``strips`` straight lines along grid east of UTM zone 33N (central
meridian 15 E), the block's centre about ``offset_km`` east of the central meridian (meridian
convergence about 0.25 degrees at 48 N), at a constant ellipsoidal height. Ground points are given
in the map (E, N) with ellipsoidal heights from a terrain function, converted to geocentric
coordinates through PROJ and projected into every image through the true geocentric geometry
(camera position and attitude in ECEF): nothing of the adjustment's frame is assumed.

Attitude: GNSS/INS navigation angles (heading from true north, pitch and roll from the local
ellipsoid normal at the camera, seed 004 convention, :mod:`stereo.block.navigation`), camera =
body frame (no boresight). Noise: image 0.5 px, GNSS 5 cm per axis, INS 0.005 deg per angle;
control 3 cm (written with that sigma), check points exact (written with 1 mm).

Files (:func:`write_curved_block`): ``observations.csv`` (``image,id,col,row,sigma_px``), camera
JSON, pose CSV (``heading,pitch,roll`` with ``sx..sroll``, ``# crs=EPSG:32633``) and a control CSV
with ground coordinates only (the measurements are in the observations CSV).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from rectify.geometry.camera import Camera
from rectify.geometry.geodesy import ecef_from_map, enu_rotation, geodetic_from_map, map_from_geodetic
from stereo.block.navigation import body_rotation

__all__ = ["CRS", "CurvedBlock", "make_curved_block", "write_curved_block"]

F64 = NDArray[np.float64]
#: the block's CRS: UTM zone 33N (ellipsoidal heights)
CRS = "EPSG:32633"
_CM_E = 500_000.0


@dataclass(frozen=True, eq=False)
class CurvedBlock:
    """The block and its truth (map coordinates in :data:`CRS`, ellipsoidal heights).

    Attributes
    ----------
    camera : Camera
    images : tuple of str
    centres : (n, 3) true projection centres, map
    nav_deg : (n, 3) true heading, pitch, roll, degrees
    gnss : (n, 3) observed centres (5 cm noise), map
    nav_obs_deg : (n, 3) observed navigation angles (INS noise), degrees
    point_ids : tuple of str
    points : (P, 3) true ground points, map
    obs_point, obs_image : (M,) int64
    obs_pixel : (M, 2) measured pixels (0.5 px noise)
    control_ids, check_ids : tuple of str
    control_given : (C, 3) control coordinates as written (3 cm noise), map
    extent_m : (2,) the block's extent in E and N, m
    """

    camera: Camera
    images: tuple[str, ...]
    centres: F64
    nav_deg: F64
    gnss: F64
    nav_obs_deg: F64
    point_ids: tuple[str, ...]
    points: F64
    obs_point: NDArray[np.int64]
    obs_image: NDArray[np.int64]
    obs_pixel: F64
    control_ids: tuple[str, ...]
    check_ids: tuple[str, ...]
    control_given: F64
    extent_m: F64


def _terrain(e: F64, n: F64) -> F64:
    """Ellipsoidal terrain height (m) at map E, N: 250-750 m."""
    return np.asarray(500.0 + 180.0 * np.sin(e / 3100.0) * np.cos(n / 4300.0) + 70.0 * np.sin((e + 2 * n) / 1700.0),
                      dtype=np.float64)


def make_curved_block(seed: int = 0, *, strips: int = 10, images_per_strip: int = 14, offset_km: float = 25.0,
                      lat_deg: float = 48.0, image_noise_px: float = 0.5, gnss_noise_m: float = 0.05,
                      ins_noise_deg: float = 0.005, control_noise_m: float = 0.03, n_grid: int = 62,
                      n_control: int = 28, n_check: int = 24) -> CurvedBlock:
    """Make the block (see the module docstring); about 4 000 points, 140 images in a second or two."""
    rng = np.random.default_rng(seed)
    f_mm, pix_mm, size = 152.0, 0.023, 10_000
    cam = Camera(focal_length_mm=f_mm, pixel_size_mm=pix_mm, width=size, height=size)
    frame_m = size * pix_mm / 1000.0  # 0.23 m
    H = 2760.0  # flying height above the mean terrain
    foot = H * frame_m / (f_mm / 1000.0)  # about 4.1 km
    base, spacing = 0.4 * foot, 0.7 * foot
    centre = map_from_geodetic([[15.0, lat_deg, 0.0]], CRS)[0]
    e0 = _CM_E + offset_km * 1000.0 - 0.5 * (images_per_strip - 1) * base
    n0 = centre[1] - 0.5 * (strips - 1) * spacing
    s_idx = np.repeat(np.arange(strips), images_per_strip)
    k_idx = np.tile(np.arange(images_per_strip), strips)
    east = s_idx % 2 == 0
    n_img = strips * images_per_strip
    ce = e0 + k_idx * base + rng.normal(0.0, 20.0, n_img)
    cn = n0 + s_idx * spacing + rng.normal(0.0, 20.0, n_img)
    ch = 500.0 + H + rng.normal(0.0, 10.0, n_img)
    centres = np.column_stack([ce, cn, ch])
    llc = geodetic_from_map(centres, CRS)
    # true heading of grid east / west at each camera: grid north is -a from true north (a: azimuth of true north)
    up = map_from_geodetic(np.column_stack([llc[:, 0], llc[:, 1] + 1e-4, np.zeros(n_img)]), CRS)
    dn = map_from_geodetic(np.column_stack([llc[:, 0], llc[:, 1] - 1e-4, np.zeros(n_img)]), CRS)
    a = np.arctan2(up[:, 0] - dn[:, 0], up[:, 1] - dn[:, 1])
    heading = np.where(east, 0.5 * math.pi, 1.5 * math.pi) - a + np.radians(rng.normal(0.0, 1.0, n_img))
    pitch = np.radians(rng.normal(0.0, 0.5, n_img))
    roll = np.radians(rng.normal(0.0, 0.5, n_img))
    R_enu = body_rotation(heading, pitch, roll)  # photo (= body) -> ENU at the camera
    E = np.stack([enu_rotation(float(lo), float(la)) for lo, la in llc[:, :2]])  # ECEF -> ENU at each camera
    R_ecef = np.swapaxes(E, 1, 2) @ R_enu
    C_ecef = ecef_from_map(centres, CRS)
    names = tuple(f"s{s:02d}_{k:02d}.tif" for s, k in zip(s_idx, k_idx, strict=True))
    # ground points: a jittered grid over the block in the map
    lo = np.array([e0 - 0.45 * foot, n0 - 0.45 * foot])
    hi = np.array([e0 + (images_per_strip - 1) * base + 0.45 * foot, n0 + (strips - 1) * spacing + 0.45 * foot])
    g = (np.arange(n_grid) + 0.5) / n_grid
    ge, gn = np.meshgrid(lo[0] + g * (hi[0] - lo[0]), lo[1] + g * (hi[1] - lo[1]), indexing="ij")
    step = (hi - lo) / n_grid
    pe = ge.ravel() + rng.uniform(-0.3, 0.3, ge.size) * step[0]
    pn = gn.ravel() + rng.uniform(-0.3, 0.3, gn.size) * step[1]
    X = np.column_stack([pe, pn, _terrain(pe, pn)])
    X_ecef = ecef_from_map(X, CRS)
    # project every point into every image (true geocentric geometry)
    f, half = f_mm, 0.5 * size * pix_mm
    margin = 20 * pix_mm
    pts, ims, pxs = [], [], []
    for i in range(n_img):
        p = (X_ecef - C_ecef[i]) @ R_ecef[i]
        with np.errstate(divide="ignore", invalid="ignore"):
            mm = np.column_stack([-f * p[:, 0] / p[:, 2], -f * p[:, 1] / p[:, 2]])
        ok = (p[:, 2] < 0) & (np.abs(mm) < half - margin).all(axis=1)
        k = np.flatnonzero(ok)
        pts.append(k)
        ims.append(np.full(len(k), i))
        pxs.append(cam.pixel_from_photo(mm[k]))
    pt, im, px = np.concatenate(pts), np.concatenate(ims), np.vstack(pxs)
    counts = np.bincount(pt, minlength=len(X))
    keep_pt = np.flatnonzero(counts >= 2)
    remap = np.full(len(X), -1, dtype=np.int64)
    remap[keep_pt] = np.arange(len(keep_pt))
    sel = remap[pt] >= 0
    pt, im, px = remap[pt[sel]], im[sel], px[sel]
    X = X[keep_pt]
    counts = np.bincount(pt, minlength=len(X))
    px = px + rng.normal(0.0, image_noise_px, px.shape)
    # control: the points seen 3+ times nearest to a ring and a cross over the block; checks inside
    good = np.flatnonzero(counts >= 3)
    span = hi - lo
    u = 0.06 + 0.88 * np.arange(n_control // 4) / max(n_control // 4, 1)  # a ring of n_control points
    ring = [(a, 0.06) for a in u] + [(0.94, a) for a in u] + [(1 - a, 0.94) for a in u] + [(0.06, 1 - a) for a in u]
    targets = lo + np.array(ring[:n_control]) * span
    chosen: list[int] = []
    for tt in targets:
        d = np.linalg.norm(X[good, :2] - tt, axis=1)
        for j in good[np.argsort(d)]:
            if int(j) not in chosen:
                chosen.append(int(j))
                break
    rest = np.setdiff1d(good, chosen)
    inner = rest[np.all(np.abs(X[rest, :2] - (lo + hi) / 2) < 0.38 * span, axis=1)]
    checks = [int(j) for j in rng.choice(inner, min(n_check, len(inner)), replace=False)]
    ids = [f"p{j}" for j in range(len(X))]
    for m, jc in enumerate(chosen):
        ids[jc] = f"gcp{m:02d}"
    for m, jk in enumerate(checks):
        ids[jk] = f"chk{m:02d}"
    gnss = centres + np.column_stack([rng.normal(0.0, gnss_noise_m, n_img) for _ in range(3)])
    nav_deg = np.degrees(np.column_stack([np.mod(heading, 2 * math.pi), pitch, roll]))
    nav_obs = nav_deg + rng.normal(0.0, ins_noise_deg, nav_deg.shape)
    ctrl_given = X[chosen] + rng.normal(0.0, control_noise_m, (len(chosen), 3))
    return CurvedBlock(cam, names, centres, nav_deg, gnss, nav_obs, tuple(ids), X, pt.astype(np.int64),
                       im.astype(np.int64), px, tuple(ids[j] for j in chosen), tuple(ids[j] for j in checks),
                       ctrl_given, hi - lo)


def write_curved_block(folder: Path, blk: CurvedBlock, *, gnss_sigma_m: float = 0.05,
                       ins_sigma_deg: float | None = 0.005, control_sigma_m: float = 0.03) -> dict[str, Path]:
    """Write ``observations.csv``, ``camera.json``, ``poses.csv`` and ``control.csv`` into ``folder``; their paths.

    ``ins_sigma_deg`` None writes no angle sigmas: the angles are initial values only (no INS observations).
    """
    folder.mkdir(parents=True, exist_ok=True)
    out = {k: folder / n for k, n in (("observations", "observations.csv"), ("camera", "camera.json"),
                                      ("poses", "poses.csv"), ("control", "control.csv"))}
    lines = ["image,id,col,row,sigma_px"]
    lines += [f"{blk.images[i]},{blk.point_ids[p]},{c:.4f},{r:.4f},0.5"
              for p, i, (c, r) in zip(blk.obs_point, blk.obs_image, blk.obs_pixel, strict=True)]
    out["observations"].write_text("\n".join(lines) + "\n")
    out["camera"].write_text(json.dumps(blk.camera.to_dict()))
    ins = ",sheading,spitch,sroll" if ins_sigma_deg is not None else ""
    rows = [f"# crs={CRS}", "# angles=deg", "image,x,y,z,heading,pitch,roll,sx,sy,sz" + ins]
    for i, name in enumerate(blk.images):
        rows.append(",".join([name, *(f"{v:.4f}" for v in blk.gnss[i]), *(f"{v:.6f}" for v in blk.nav_obs_deg[i]),
                              *([f"{gnss_sigma_m:g}"] * 3),
                              *([f"{ins_sigma_deg:g}"] * 3 if ins_sigma_deg is not None else [])]))
    out["poses"].write_text("\n".join(rows) + "\n")
    where = {p: k for k, p in enumerate(blk.point_ids)}
    crow = [f"# crs={CRS}", "id,image,col,row,x,y,z,sx,sy,sz"]
    for k, cid in enumerate(blk.control_ids):
        crow.append(",".join([cid, "", "", "", *(f"{v:.4f}" for v in blk.control_given[k]),
                              *([f"{control_sigma_m:g}"] * 3)]))
    for cid in blk.check_ids:
        crow.append(",".join([cid, "", "", "", *(f"{v:.4f}" for v in blk.points[where[cid]]), "0.001", "0.001",
                              "0.001"]))
    out["control"].write_text("\n".join(crow) + "\n")
    return out
