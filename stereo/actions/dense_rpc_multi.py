"""``run_dense_rpc_multi``: three or more RPC images -> RPC block adjustment -> pairs -> one fused DSM.

Steps (``docs/dense.md``, "Several RPC images"):

1. every image's RPC is read and the images' footprints checked to overlap
   (:func:`rectify.geometry.rpc_adjust.check_overlap`) before any work;
2. the RPC block adjustment (unless ``adjust=False``): tie points of every overlapping pair
   (:func:`rectify.features.match_images`, verified by the fundamental matrix), chained into tracks
   (:func:`rectify.geometry.rpc_adjust.chain_matches`), image-space biases per image
   (:class:`rectify.geometry.rpc_adjust.RPCBlockAdjustment`, ``shift`` or ``affine``; without GCPs the datum
   is the biases' least weighted norm), each compensated model refitted as an RPC
   (:func:`rectify.geometry.rpc_adjust.refit_rpc`, within ``refit_tolerance_px``) and used from then on;
3. the pairs (:func:`stereo.dense.rpc_views.select_rpc_pairs`): the reference image (the first) with each
   other image whose intersection angle at the scene centre lies in the range and which sees enough of the
   region of interest;
4. each pair through the pair chain (:func:`stereo.actions.dense_rpc.run_dense_rpc`, in a scratch folder)
   with ``pair_sigma``: its heights and sigma_Z on cells of one size, on whole multiples of the cell;
5. the fusion (:func:`stereo.dense.fusion.fuse_heights`): per cell the robust precision-weighted height,
   its sigma_Z, the count of agreeing pairs and the provenance (the pair of the smallest sigma_Z); the
   pairs' sigmas scaled first by the a-posteriori variance factor of their agreement
   (:func:`stereo.dense.fusion.variance_factor`).

Outputs in ``out_dir`` (written together at the end, or none on an error; a folder the run created is
removed again on an error):

===============================  ============================================================
``dsm.tif``                      the fused DSM (UTM, WGS 84 ellipsoidal heights), cell edges on
                                 whole multiples of the cell: band 1 height, 2 sigma_Z, 3 count,
                                 4 provenance (index into ``pairs`` of ``dense_rpc.json``; -1
                                 none); float32, nodata -9999, band descriptions in the file
``pair_<ref>__<other>_dsm.tif``  each pair's own DSM (the pair chain's three bands)
``<stem>_RPC.TXT``               the adjusted RPC of each image (with the adjustment)
``dense_rpc.json``               images, viewing angles, the candidate pairs, the adjustment
                                 (sigma0, biases, refit errors), per pair its parallax, ROI
                                 statistics and median sigma_Z, the pairs' agreement (median
                                 of their differences), the fused DSM's ROI statistics, the
                                 comparison with a reference DEM
``report/``                      with a reference DEM: ``dsm.png``, ``dz.png``,
                                 ``dz_histogram.png``
===============================  ============================================================
"""

from __future__ import annotations

import contextlib
import json
import math
import shutil
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from affine import Affine
from numpy.typing import NDArray
from scipy import ndimage

from rectify.actions.workspace import Workspace
from rectify.errors import EstimationError, InvalidInputError, StereoError
from rectify.features import MatcherConfig, match_images
from rectify.formats.common import stamp
from rectify.formats.rpc import read_rpc_gcps, rpc_from_raster, rpc_txt_text
from rectify.geometry.crs import transform_xy
from rectify.geometry.rpc import RPC
from rectify.geometry.rpc_adjust import (
    BIAS_MODELS,
    RPCBlockAdjustment,
    TieTracks,
    chain_matches,
    check_overlap,
    refit_rpc,
)
from rectify.raster.io import MaskPolicy, TiledWriter, raster_info
from rectify.report.builder import json_safe
from stereo.actions.dense_rpc import RpcDenseOptions, RpcDenseResult, roi_statistics, run_dense_rpc
from stereo.dense.dsm import DSM_NODATA, DsmResult, fill_holes
from stereo.dense.fusion import FUSED_BANDS, fuse_heights, fused_band_descriptions, nodata_of, variance_factor
from stereo.dense.rpc_views import PairCandidate, select_rpc_pairs
from stereo.report.dense import HeightComparison, compare_with_dem, save_histogram, save_picture

__all__ = ["FUSED_FILL_CELLS", "MultiRpcOptions", "MultiRpcResult", "fill_fused_holes", "pairs_agreement", "roi_cells",
           "run_dense_rpc_multi"]

StrPath = str | Path
Progress = Callable[[str, int, int], None]
HEIGHTS = "m above the WGS 84 ellipsoid"
#: default largest hole of the fused DSM that is interpolated, cells (50 x 50; 25 m x 25 m at 0.5 m), as CARS
#: interpolates its DSM's holes by default; ``--fill-holes 0`` turns it off
FUSED_FILL_CELLS = 2500


@dataclass(frozen=True)
class MultiRpcOptions:
    """Options of :func:`run_dense_rpc_multi`.

    Attributes
    ----------
    pair : RpcDenseOptions
        The pair chain's options (``pair_sigma``, ``stac``, the cloud and the reference DEM are set by the
        multi-view run; ``dsm_cell`` None: the first pair's default cell for all). Its ``fill_holes`` fills
        each pair's own DSM only.
    fill_holes : the fused DSM's holes of at most this many cells are interpolated from their rim
        (:func:`fill_fused_holes`; default :data:`FUSED_FILL_CELLS`; 0: off): enclosed holes, and the empty
        cells of the ROI that connect to the grid's empty outside (bounded by the ROI). A filled cell has a
        height, sigma_Z nodata, count 0 and provenance -1.
    adjust : bool
        Run the RPC block adjustment first.
    bias_model : ``"shift"`` or ``"affine"``
    sigma_px : standard deviation of a tie measurement, px.
    prior_px : standard deviation of the zero prior of every bias parameter, px.
    refit_tolerance_px : the largest refit error of an adjusted RPC, px.
    max_matches : matches kept per image pair for the adjustment.
    min_angle_deg, max_angle_deg : the intersection angle range of a pair, degrees (5-45).
    min_overlap : the least share of the ROI the other image of a pair must see.
    max_pairs : at most this many pairs (0: every passing pair).
    k_sigma : the fusion's rejection threshold, standard errors.
    reference_dem : compare the fused DSM with this DEM (statistics, pictures in ``report/``).
    gcps : GCP CSV of the adjustment (``id,image,col,row,lon,lat,h[,sigma_xy,sigma_h,sigma]``, as
        ``rectify rpc-adjust --gcps``), optional. Without GCPs the adjustment fixes the images' *relative*
        pointing only: a bias pattern that moves every tie point up or down together (the row biases in
        proportion to each view's parallax per metre) fits the tie points equally well, and the prior picks
        the one of least norm, so the fused DSM's absolute height keeps a part of the RPCs' own errors
        (on the synthetic triplet of the tests, tie points only: biases off the truth by the pattern of a 1.7 m
        height shift, of the 3.6 m a 2 px along-track bias makes in its pair).
    gcp_sigma_xy, gcp_sigma_h : ground standard deviations of GCPs without their own, metres.
    """

    pair: RpcDenseOptions = field(default_factory=lambda: RpcDenseOptions(cloud_format="none", stac=False))
    adjust: bool = True
    bias_model: str = "shift"
    sigma_px: float = 0.5
    prior_px: float = 10.0
    refit_tolerance_px: float = 0.01
    max_matches: int = 2000
    min_angle_deg: float = 5.0
    max_angle_deg: float = 45.0
    min_overlap: float = 0.5
    max_pairs: int = 0
    k_sigma: float = 3.0
    reference_dem: str | None = None
    gcps: str | Path | None = None
    gcp_sigma_xy: float = 0.5
    gcp_sigma_h: float = 1.0
    fill_holes: int = FUSED_FILL_CELLS

    def __post_init__(self) -> None:
        if not isinstance(self.pair, RpcDenseOptions):
            raise InvalidInputError(f"`pair` must be an RpcDenseOptions; got {type(self.pair).__name__}")
        if self.bias_model not in BIAS_MODELS:
            raise InvalidInputError(f"unknown bias model {self.bias_model!r}; expected one of {list(BIAS_MODELS)}")
        for name in ("sigma_px", "prior_px", "refit_tolerance_px", "k_sigma", "gcp_sigma_xy", "gcp_sigma_h"):
            v = getattr(self, name)
            if isinstance(v, bool) or not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise InvalidInputError(f"`{name}` must be a finite number > 0; got {v!r}")
        if not (isinstance(self.min_angle_deg, (int, float)) and isinstance(self.max_angle_deg, (int, float))
                and 0 <= self.min_angle_deg < self.max_angle_deg <= 90):
            raise InvalidInputError(f"the intersection angle range must satisfy 0 <= min < max <= 90 deg; got "
                                    f"{self.min_angle_deg!r}..{self.max_angle_deg!r}")
        if not (isinstance(self.min_overlap, (int, float)) and 0 <= self.min_overlap <= 1):
            raise InvalidInputError(f"`min_overlap` must be in [0, 1]; got {self.min_overlap!r}")
        if self.gcps is not None and not self.adjust:
            raise InvalidInputError("GCPs are used by the RPC adjustment: drop --no-adjust or the GCPs")
        for name, lo in (("max_pairs", 0), ("max_matches", 20), ("fill_holes", 0)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < lo:
                raise InvalidInputError(f"`{name}` must be an integer >= {lo}; got {v!r}")


@dataclass(frozen=True, eq=False)
class MultiRpcResult:
    """What :func:`run_dense_rpc_multi` did and wrote.

    ``adjustment``: None with ``adjust=False``; ``refit_max_px``: the worst refit error of the adjusted
    RPCs. ``pairs``: the kept candidates, in the order of the fused DSM's provenance band; ``pair_results``:
    their pair chain results. ``agreement``: per two pairs (a, b) the median and NMAD of pair a's heights
    minus pair b's over their common cells, metres. ``roi_stats``: the fused DSM's cells in the ROI
    (:func:`stereo.actions.dense_rpc.roi_statistics`).
    """

    out_dir: Path
    files: tuple[Path, ...]
    names: tuple[str, ...]
    candidates: tuple[PairCandidate, ...]
    pairs: tuple[PairCandidate, ...]
    pair_results: tuple[RpcDenseResult, ...]
    adjustment: RPCBlockAdjustment | None
    refit_max_px: float
    agreement: tuple[tuple[int, int, float, float, int], ...]
    dsm: DsmResult
    sigma: NDArray[np.float64]
    cell: float
    crs: str
    roi: tuple[int, int, int, int]
    roi_stats: dict[str, float]
    variance_factor: float
    median_sigma_z: float
    seconds: float
    adjust_seconds: float
    comparison: HeightComparison | None = None
    measured_coverage: float = float("nan")

    def summary_lines(self) -> list[str]:
        lines = [f"images: {len(self.names)} ({', '.join(self.names)}); reference {self.names[0]}, ROI "
                 f"{self.roi[2]} x {self.roi[3]} px at ({self.roi[0]}, {self.roi[1]})"]
        a = self.adjustment
        if a is None:
            lines.append("RPC adjustment: not run (--no-adjust); the images' own RPCs are used")
        else:
            biases = "; ".join(f"{n}: col {a.params[j, 0, 0]:+.3f}, row {a.params[j, 1, 0]:+.3f} px"
                               for j, n in enumerate(self.names))
            lines.append(f"RPC adjustment ({a.model}): {len(a.tracks.ids)} tie tracks, sigma0 {a.sigma0:.3f}, biases "
                         f"{biases}; refit error of the adjusted RPCs max {self.refit_max_px:.2e} px "
                         f"({self.adjust_seconds:.1f} s)")
        for c in self.candidates:
            lines.append(f"pair {self.names[c.left]} + {self.names[c.right]}: intersection angle {c.angle_deg:.1f} "
                         f"deg, sees {100 * c.overlap:.0f}% of the ROI: {c.reason}")
        for k, (c, r) in enumerate(zip(self.pairs, self.pair_results, strict=True)):
            lines.append(f"  pair {k} ({self.names[c.right]}): {r.n_points} points, "
                         f"{100 * r.roi_stats['coverage']:.1f}% of the ROI, median {r.roi_stats['median_m']:.2f} m, "
                         "vertical parallax RMS "
                         f"{r.parallax_rms_px:.3f} px")
        for i, j, med, nmad, n in self.agreement:
            lines.append(f"  pair {i} - pair {j}: median {med:+.3f} m, NMAD {nmad:.3f} m over {n} common cells")
        lines.append(f"fused DSM: {self.dsm.height.shape[1]} x {self.dsm.height.shape[0]} cells of {self.cell:g} m "
                     f"({self.crs}, heights {HEIGHTS}), {100 * self.roi_stats['coverage']:.1f}% of the ROI cells have "
                     f"a height, median {self.roi_stats['median_m']:.1f} m, 1-99% {self.roi_stats['p01_m']:.1f}-"
                     f"{self.roi_stats['p99_m']:.1f} m; median sigma_Z {self.median_sigma_z:.3f} m (variance factor "
                     f"{self.variance_factor:.2f})"
                     + (f"; {int(self.dsm.filled.sum())} cells interpolated over holes (--fill-holes; "
                        f"{100 * self.measured_coverage:.1f}% of the ROI cells without them)"
                        if self.dsm.filled.any() else ""))
        if self.comparison is not None:
            lines.append(self.comparison.summary_line(cell=self.cell)
                         + " (the reference DEM's heights taken as they are: the DSM's are ellipsoidal)")
        lines.append(f"outputs in {self.out_dir}: " + ", ".join(
            p.relative_to(self.out_dir).as_posix() if p.is_relative_to(self.out_dir) else str(p) for p in self.files))
        lines.append(f"time {self.seconds:.1f} s")
        return lines


# ---------------------------------------------------------------------------- helpers
def _nmad(v: NDArray[np.float64]) -> float:
    return float(1.4826 * np.median(np.abs(v - np.median(v)))) if len(v) else float("nan")


def pairs_agreement(heights: Sequence[NDArray[np.float64]]) -> list[tuple[int, int, float, float, int]]:
    """Per two grids (a < b) of one shape: (a, b, median, NMAD of a - b, common cells); NaN = no height."""
    out = []
    for a in range(len(heights)):
        for b in range(a + 1, len(heights)):
            d = heights[a] - heights[b]
            d = d[np.isfinite(d)]
            out.append((a, b, float(np.median(d)) if len(d) else float("nan"), _nmad(d), int(len(d))))
    return out


def fill_fused_holes(height: NDArray[np.float64], max_cells: int, inside: NDArray[np.bool_] | None = None
                     ) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Holes (NaN) of at most ``max_cells`` cells interpolated from their rim; returns the heights and the
    filled mask (H, W).

    Filled: every hole enclosed by heights (not touching the grid's border) of at most ``max_cells`` cells
    and, with ``inside`` (H, W; the ROI's cells), every connected group of empty cells *inside* of at most
    ``max_cells`` cells even where it joins the empty outside (only its cells inside are filled). The fill
    starts from the nearest height and is smoothed by 50 sweeps of four-neighbour averaging inside the holes
    (the DSM grid's harmonic fill, :func:`stereo.dense.dsm.fill_holes`): every filled height lies within the
    range of the heights around it (maximum principle)."""
    has = np.isfinite(height)
    none = np.zeros(height.shape, bool)
    if max_cells <= 0 or not has.any() or has.all():
        return height, none
    hf, target = fill_holes(np.where(has, height, 0.0), has, max_cells)
    if inside is not None:
        lab, n = ndimage.label(~has & inside)
        if n:
            small = np.bincount(lab.ravel(), minlength=n + 1) <= max_cells
            small[0] = False
            target = target | small[lab]
    if not target.any():
        return height, none
    idx = ndimage.distance_transform_edt(~has, return_distances=False, return_indices=True)
    out = height[idx[0], idx[1]]
    for _ in range(50):
        pad = np.pad(out, 1, mode="edge")
        avg = 0.25 * (pad[:-2, 1:-1] + pad[2:, 1:-1] + pad[1:-1, :-2] + pad[1:-1, 2:])
        out[target] = avg[target]
    return np.where(target, out, height), target


def roi_cells(height: NDArray[np.float64], transform: Affine, crs: str, rpc: RPC,
              roi: tuple[int, int, int, int]) -> NDArray[np.bool_]:
    """(H, W) True where the cell's centre, at its height (the median where it has none; NaN = none),
    projects into ``roi`` (x, y, width, height, px) of the RPC's image (as
    :func:`stereo.actions.dense_rpc.roi_statistics`)."""
    H, W = height.shape
    rr, cc = np.mgrid[0:H, 0:W]
    x = transform.c + (cc.ravel() + 0.5) * transform.a
    y = transform.f + (rr.ravel() + 0.5) * transform.e
    z = height.ravel()
    has = np.isfinite(z)
    med = float(np.median(z[has])) if has.any() else float(rpc.height_off)
    p = rpc.project(np.column_stack([transform_xy(crs, "EPSG:4326", np.column_stack([x, y])),
                                     np.where(has, z, med)]))
    x0, y0, w, h = roi
    ok = (p[:, 0] >= x0 - 0.5) & (p[:, 0] < x0 + w - 0.5) & (p[:, 1] >= y0 - 0.5) & (p[:, 1] < y0 + h - 0.5)
    return ok.reshape(H, W)


def _union(transforms: Sequence[Any], shapes: Sequence[tuple[int, int]], cell: float
           ) -> tuple[Affine, tuple[int, int], list[tuple[int, int]]]:
    """The grid covering grids of one cell whose edges lie on whole multiples of it; each one's (row, col) offset."""
    left = min(t.c for t in transforms)
    top = max(t.f for t in transforms)
    right = max(t.c + s[1] * cell for t, s in zip(transforms, shapes, strict=True))
    bottom = min(t.f - s[0] * cell for t, s in zip(transforms, shapes, strict=True))
    W, H = int(round((right - left) / cell)), int(round((top - bottom) / cell))
    offs = [(int(round((top - t.f) / cell)), int(round((t.c - left) / cell))) for t in transforms]
    return Affine(cell, 0.0, left, 0.0, -cell, top), (H, W), offs


def _adjust(paths: Sequence[Path], rpcs: Sequence[RPC], sizes: Sequence[tuple[int, int]], names: Sequence[str],
            pairs: Sequence[tuple[int, int]], o: MultiRpcOptions, prog: Progress
            ) -> tuple[RPCBlockAdjustment, list[RPC], float]:
    """The RPC block adjustment of the images and their refitted RPCs (module docstring, step 2)."""
    control: dict = {}
    gm = None
    if o.gcps is not None:  # checked before any matching
        gm, control = read_rpc_gcps(o.gcps, [str(p) for p in paths], sigma_xy=o.gcp_sigma_xy, sigma_h=o.gcp_sigma_h)
        for j, pid, px in zip(gm.image, gm.ids, gm.pixels, strict=True):
            w, h = sizes[j]
            if not (-0.5 <= px[0] <= w - 0.5 and -0.5 <= px[1] <= h - 0.5):
                raise InvalidInputError(f"GCP {pid!r} is measured at ({px[0]:.1f}, {px[1]:.1f}) outside image "
                                        f"{names[j]!r} ({w} x {h} px)")
    cfg = MatcherConfig(verify="fundamental", max_matches=o.max_matches)
    matched = []
    for n, (i, j) in enumerate(pairs):
        try:
            m = match_images(paths[i], paths[j], config=cfg).matches
        except EstimationError as err:
            raise EstimationError(f"tie points of {names[i]} and {names[j]}: {err}") from None
        matched.append((i, j, m.left, m.right))
        prog("tie points", n + 1, len(pairs))
    ids, image, track, pixels = chain_matches(matched, prefix="t")
    t_ids = [ids[t] for t in track]
    sig = np.full(len(image), o.sigma_px)
    if gm is not None:
        t_ids += list(gm.ids)
        image = np.concatenate([image, gm.image])
        pixels = np.vstack([pixels, gm.pixels])
        sig = np.concatenate([sig, np.where(np.isfinite(gm.sigma), gm.sigma, o.sigma_px)])
    uniq = tuple(dict.fromkeys(t_ids))
    index = {u: i for i, u in enumerate(uniq)}
    tracks = TieTracks.from_arrays(uniq, image, [index[i] for i in t_ids], pixels, sig)
    adj = RPCBlockAdjustment.from_observations(rpcs, sizes, tracks, control=control, model=o.bias_model,
                                               prior_px=o.prior_px, names=names)
    refits = [refit_rpc(adj.refinement(j), tolerance_px=o.refit_tolerance_px, source=names[j])
              for j in range(len(rpcs))]
    return adj, [r.rpc for r in refits], max(r.max_px for r in refits)


# ---------------------------------------------------------------------------- the action
def run_dense_rpc_multi(images: Sequence[StrPath], out_dir: StrPath, *, roi: tuple[int, int, int, int] | None = None,
                        options: MultiRpcOptions | None = None, overwrite: bool = False,
                        progress: Progress | None = None) -> MultiRpcResult:
    """Three or more RPC images -> adjusted RPCs -> pairs of the reference -> one fused DSM (module docstring).

    Parameters
    ----------
    images : paths
        The images (GeoTIFF with RPC tags, or any raster GDAL finds an RPC for); the first is the reference,
        whose ROI is matched.
    out_dir : path
    roi : (x, y, width, height) of the reference image, px; default the whole image.
    options : MultiRpcOptions
    overwrite : bool
    progress : callable(stage, done, total), optional

    Raises
    ------
    InvalidInputError
        Fewer than 3 images, an image twice, an image without RPC, images that do not overlap, bad options.
    EstimationError
        The adjustment fails (too few tie points, singular) or a refit cannot reach its tolerance.
    StereoError
        No pair passes the selection, or no pair gives points.
    RasterIOError
        Unreadable inputs, unwritable outputs.

    On any error nothing is left in ``out_dir`` (a folder the run created is removed again).
    """
    t0 = time.perf_counter()
    o = options or MultiRpcOptions()
    if not isinstance(o, MultiRpcOptions):
        raise InvalidInputError(f"`options` must be a MultiRpcOptions; got {type(o).__name__}")
    paths = [Path(p) for p in images]
    if len(paths) < 3:
        raise InvalidInputError(f"the multi-view chain needs at least 3 images; got {len(paths)} (two images: "
                                "run_dense_rpc)")
    seen: set[Path] = set()
    for p in paths:
        key = p.resolve()
        if key in seen:
            raise InvalidInputError(f"image {str(p)!r} is given twice")
        seen.add(key)
    if o.reference_dem is not None and not Path(o.reference_dem).is_file():
        raise InvalidInputError(f"reference DEM file not found: {str(o.reference_dem)!r}")
    names = [p.name for p in paths]
    stems = [p.stem for p in paths]
    infos = [raster_info(p) for p in paths]
    rpcs = [rpc_from_raster(p) for p in paths]
    sizes = [(i.width, i.height) for i in infos]
    overlapping = check_overlap(rpcs, sizes, names)
    W0, H0 = sizes[0]
    box = roi if roi is not None else (0, 0, W0, H0)
    try:
        x, y, w, h = (int(v) for v in box)
    except (TypeError, ValueError):
        raise InvalidInputError(f"`roi` must be four integers (x, y, width, height); got {roi!r}") from None
    if w < 32 or h < 32 or x < 0 or y < 0 or x + w > W0 or y + h > H0:
        raise InvalidInputError(f"`roi` {roi!r} must lie inside the reference image ({W0} x {H0} px) and be at "
                                "least 32 x 32 px")
    box = (x, y, w, h)
    out = Path(out_dir)
    ws = Workspace(out, overwrite=overwrite, inputs=[*paths] + [f for f in (o.reference_dem, o.gcps) if f])
    ws.prepare("dsm.tif", "dense_rpc.json", *([f"{s}_RPC.TXT" for s in stems] if o.adjust else []))

    def prog(stage: str, done: int, total: int) -> None:
        if progress is not None:
            progress(stage, done, total)

    try:
        return _run(paths, names, stems, rpcs, sizes, overlapping, box, out, ws, o, prog, t0)
    except BaseException:
        ws.discard_root()
        raise


def _run(paths: list[Path], names: list[str], stems: list[str], rpcs: list[RPC], sizes: list[tuple[int, int]],
         overlapping: list[tuple[int, int]], box: tuple[int, int, int, int], out: Path, ws: Workspace,
         o: MultiRpcOptions, prog: Progress, t0: float) -> MultiRpcResult:
    """The chain of :func:`run_dense_rpc_multi` after its inputs are checked and its folder prepared."""
    adj = None
    refit_max = float("nan")
    t_adj = time.perf_counter()
    if o.adjust:
        adj, rpcs, refit_max = _adjust(paths, rpcs, sizes, names, overlapping, o, prog)
    t_adj = time.perf_counter() - t_adj
    x, y, w, h = box
    r0 = rpcs[0]
    z0 = float(np.median(adj.ground[:, 2])) if adj is not None else float(r0.height_off)
    centre = r0.localize(np.array([[x + (w - 1) / 2, y + (h - 1) / 2]]), z0)[0]
    cands = select_rpc_pairs(rpcs, sizes, box, centre, min_angle_deg=o.min_angle_deg,
                             max_angle_deg=o.max_angle_deg, min_overlap=o.min_overlap, max_pairs=o.max_pairs,
                             names=names)
    kept = [c for c in cands if c.kept]
    pair_opts = replace(o.pair, pair_sigma=True, stac=False, cloud_format="none", reference_dem=None)
    results: list[RpcDenseResult] = []
    pair_names = [f"pair_{stems[c.left]}__{stems[c.right]}_dsm.tif" for c in kept]
    ws.plan(*(out / n for n in pair_names))
    with tempfile.TemporaryDirectory(prefix="dense_rpc_multi_") as scratch:
        used: list[PairCandidate] = []
        failed: dict[tuple[int, int], str] = {}
        for k, c in enumerate(kept):
            try:  # a pair without tie points or points is left out, with its reason
                res = run_dense_rpc(paths[c.left], paths[c.right], Path(scratch) / f"pair{k}", roi=box,
                                    left_rpc=rpcs[c.left], right_rpc=rpcs[c.right], options=pair_opts)
            except StereoError as err:
                failed[(c.left, c.right)] = str(err)
                continue
            if res.sigma is None:  # pragma: no cover - pair_sigma is set
                raise StereoError("the pair chain returned no sigma grid")
            results.append(res)
            used.append(c)
            (Path(scratch) / f"pair{k}" / "dsm.tif").rename(Path(scratch) / f"used{len(used) - 1}.tif")
            if pair_opts.dsm_cell is None:
                pair_opts = replace(pair_opts, dsm_cell=res.dsm_cell)
            prog("pairs", k + 1, len(kept))
        if not results:
            raise StereoError("no pair gave points: " + "; ".join(f"{names[j]}: {e}" for (_i, j), e in failed.items()))
        if failed:
            cands = [PairCandidate(c.left, c.right, c.angle_deg, c.overlap, False,
                                   f"matched, no points: {failed[(c.left, c.right)]}")
                     if (c.left, c.right) in failed else c for c in cands]
            kept = used
            pair_names = [f"pair_{stems[c.left]}__{stems[c.right]}_dsm.tif" for c in kept]
        crs = results[0].crs
        if any(r.crs != crs for r in results):
            raise StereoError(f"the pairs' DSMs fall in different UTM zones ({sorted({r.crs for r in results})})")
        cell = results[0].dsm_cell
        sig = [r.sigma for r in results if r.sigma is not None]
        transform, (H, W), offs = _union([s[2] for s in sig], [s[0].shape for s in sig], cell)
        hs = np.full((len(sig), H, W), np.nan)
        ss = np.full((len(sig), H, W), np.nan)
        for k, ((hh, sg, _t), (ro, co)) in enumerate(zip(sig, offs, strict=True)):
            hs[k, ro:ro + hh.shape[0], co:co + hh.shape[1]] = hh
            ss[k, ro:ro + hh.shape[0], co:co + hh.shape[1]] = sg
        first = fuse_heights(hs, ss, k=o.k_sigma)
        factor = variance_factor(float(first.chi2.sum()), int(first.dof.sum()))
        fused = fuse_heights(hs, factor * ss, k=o.k_sigma)
        agreement = pairs_agreement(list(hs))
        del hs, ss
        count = fused.count.astype(np.uint16)
        measured = roi_statistics(DsmResult(nodata_of(fused.height), count, np.zeros(count.shape, bool), transform,
                                            crs, heights=HEIGHTS), rpcs[0], box, crs)["coverage"]
        height, filled = fill_fused_holes(fused.height, o.fill_holes,
                                          roi_cells(fused.height, transform, crs, rpcs[0], box))
        dsm = DsmResult(nodata_of(height), count, filled, transform, crs, heights=HEIGHTS)
        stats = roi_statistics(dsm, rpcs[0], box, crs)
        ok = np.isfinite(fused.sigma)
        med_sigma = float(np.median(fused.sigma[ok])) if ok.any() else float("nan")
        comparison = dz = None
        if o.reference_dem is not None:
            comparison, dz = compare_with_dem(dsm, o.reference_dem)
        files: list[Path] = []
        rep = out / "report"
        made_rep = False
        try:
            with ws.transaction():
                with ws.output(out / "dsm.tif") as tmp, TiledWriter(
                        tmp, W, H, len(FUSED_BANDS), "float32", transform, crs, MaskPolicy("nodata", DSM_NODATA),
                        tile=256, descriptions=fused_band_descriptions(HEIGHTS, o.k_sigma)) as wr:
                    wr.write(np.dstack([nodata_of(height), nodata_of(fused.sigma),
                                        fused.count.astype(np.float32), fused.provenance.astype(np.float32)]), 0, 0)
                files.append(out / "dsm.tif")
                for k, name in enumerate(pair_names):
                    with ws.output(out / name) as tmp:
                        shutil.copyfile(Path(scratch) / f"used{k}.tif", tmp)
                    files.append(out / name)
                if adj is not None:
                    for j, s in enumerate(stems):
                        files.append(ws.write_text(out / f"{s}_RPC.TXT", rpc_txt_text(rpcs[j])))
                doc = _document(names, paths, cands, kept, results, pair_names, adj, refit_max, agreement, dsm,
                                stats, cell, crs, box, factor, med_sigma, o, comparison, int(fused.rejected.sum()),
                                measured)
                with ws.output(out / "dense_rpc.json") as tmp:
                    tmp.write_text(json.dumps(json_safe(doc), indent=2) + "\n", encoding="utf-8")
                files.append(out / "dense_rpc.json")
                if comparison is not None and dz is not None:
                    if not rep.exists():
                        rep.mkdir()
                        made_rep = True
                    cmp = comparison
                    for name, draw in (
                            ("dsm.png", lambda t: save_picture(t, dsm.height, title="fused DSM", cmap="terrain",
                                                               label="height (m)", nodata=DSM_NODATA)),
                            ("dz.png", lambda t: save_picture(t, dz, title="fused DSM - reference DEM",
                                                              cmap="RdBu_r", label="dz (m)", symmetric=True)),
                            ("dz_histogram.png", lambda t: save_histogram(t, cmp))):
                        with ws.output(rep / name) as tmp:
                            draw(tmp)
                        files.append(rep / name)
        except BaseException:
            if made_rep:
                with contextlib.suppress(OSError):
                    rep.rmdir()
            raise
    return MultiRpcResult(out, tuple(files), tuple(names), tuple(cands), tuple(kept), tuple(results), adj, refit_max,
                          tuple(agreement), dsm, fused.sigma, cell, crs, box, stats, factor, med_sigma,
                          time.perf_counter() - t0, t_adj, comparison, measured)


def _document(names: list[str], paths: list[Path], cands: list[PairCandidate], kept: list[PairCandidate],
              results: list[RpcDenseResult], pair_names: list[str], adj: RPCBlockAdjustment | None,
              refit_max: float, agreement: list[tuple[int, int, float, float, int]], dsm: DsmResult,
              stats: dict[str, float], cell: float, crs: str, box: tuple[int, int, int, int], factor: float,
              med_sigma: float, o: MultiRpcOptions, comparison: HeightComparison | None, rejected: int,
              measured: float) -> dict[str, Any]:
    adjustment = None
    if adj is not None:
        rms = adj.image_rms()
        adjustment = {"model": adj.model, "sigma0": adj.sigma0, "redundancy": adj.redundancy,
                      "iterations": adj.iterations, "n_tracks": len(adj.tracks.ids),
                      "n_measurements": len(adj.tracks), "refit_max_px": refit_max,
                      "prior_px": o.prior_px, "sigma_px": o.sigma_px,
                      "images": [{"name": n, "params": adj.params[j].tolist(), "std": adj.std[j].tolist(),
                                  "std_relative_to_first": adj.relative_std(j).tolist(),
                                  "residual_rms_px": rms[j].tolist()} for j, n in enumerate(names)],
                      "params_frame": "px; row 0 the column correction, row 1 the row correction (shift: a0, b0; "
                                      "affine: at the image centre, then per half image side)"}
    doc = {
        "images": [str(p) for p in paths], "reference": names[0], "roi": list(box), "crs": crs, "dsm_cell": cell,
        "selection": {"min_angle_deg": o.min_angle_deg, "max_angle_deg": o.max_angle_deg,
                      "min_overlap": o.min_overlap, "max_pairs": o.max_pairs,
                      "candidates": [{**c.to_dict(), "left_name": names[c.left], "right_name": names[c.right]}
                                     for c in cands]},
        "adjustment": adjustment,
        "pairs": [{"index": k, "left": names[c.left], "right": names[c.right], "dsm": pair_names[k],
                   "angle_deg": c.angle_deg, "overlap": c.overlap, "n_points": r.n_points,
                   "roi": r.roi_stats, "vertical_parallax_rms_px": r.parallax_rms_px,
                   "vertical_parallax_before_rms_px": r.parallax_before_rms_px,
                   "median_sigma_z_m": (float(np.nanmedian(r.sigma[1])) if r.sigma is not None
                                        and np.isfinite(r.sigma[1]).any() else None)}
                  for k, (c, r) in enumerate(zip(kept, results, strict=True))],
        "agreement": [{"a": a, "b": b, "median_m": med, "nmad_m": nm, "n_cells": n} for a, b, med, nm, n in agreement],
        "dsm": {"file": "dsm.tif", "bands": list(FUSED_BANDS), "width": int(dsm.height.shape[1]),
                "height": int(dsm.height.shape[0]), "transform": list(dsm.transform)[:6], "heights": HEIGHTS,
                "roi": stats, "median_sigma_z_m": med_sigma, "variance_factor": factor, "k_sigma": o.k_sigma,
                "rejected_heights": rejected, "filled_cells": int(dsm.filled.sum()),
                "fill_holes": o.fill_holes, "roi_coverage_without_filled": measured},
        "comparison": None if comparison is None else {
            "reference_dem": str(o.reference_dem),
            **{k: v for k, v in comparison.__dict__.items() if k != "histogram"}},
    }
    return stamp("dense_rpc_multi", 1, doc)
