"""``rectify rpc-adjust``: block adjustment of RPC images; refined RPCs GDAL reads (``docs/rpc_adjust.md``).

Tie points come from a tie-point CSV (``--ties``) or from matching every pair of overlapping images
(:func:`rectify.features.match_images`, verified by the fundamental matrix) chained into multi-image tracks
(:func:`rectify.geometry.rpc_adjust.chain_matches`). The adjustment is
:class:`rectify.geometry.rpc_adjust.RPCBlockAdjustment`; each image's compensated model is refitted as an RPC
(:func:`rectify.geometry.rpc_adjust.refit_rpc`) and written into the output folder as ``<stem>.vrt`` (a VRT
of the image, pixels not copied, whose RPC metadata is the refined model), ``<stem>_RPC.TXT`` and
``<stem>.RPB``, with ``adjustment.json`` and ``residuals.csv``. Before anything is committed, GDAL's RPC
transformer on each written VRT must reproduce the adjusted projection of the image's tie points within the
refit tolerance.
"""

from __future__ import annotations

import csv
import io
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from rectify.actions.common import Progress
from rectify.actions.workspace import Workspace
from rectify.errors import EstimationError, InvalidInputError
from rectify.features import MatcherConfig, match_images
from rectify.formats.common import stamp
from rectify.formats.rpc import read_rpc_gcps, read_rpc_ties, rpb_text, rpc_from_raster, rpc_txt_text
from rectify.geometry.residuals import ResidualTable
from rectify.geometry.robust import ROBUST_METHODS
from rectify.geometry.rpc import RPC
from rectify.geometry.rpc_adjust import (
    BIAS_MODELS,
    RefitResult,
    RPCBlockAdjustment,
    TieTracks,
    chain_matches,
    check_overlap,
    refit_rpc,
)
from rectify.raster.io import raster_info
from rectify.raster.rpcfiles import gdal_rpc_project, rpc_vrt_text

__all__ = ["BIAS_MODELS", "ROBUST_METHODS", "RpcAdjustOptions", "RpcAdjustRun", "rpc_adjust"]


@dataclass(frozen=True)
class RpcAdjustOptions:
    """Options of :func:`rpc_adjust`.

    model : ``"shift"`` or ``"affine"`` (image-space bias per image).
    gcps : GCP CSV (``id,image,col,row,lon,lat,h[,sigma_xy,sigma_h,sigma]``), optional.
    check : GCP ids used as check points (left out of the adjustment).
    ties : tie-point CSV (``image,id,col,row[,sigma]``); None: match the overlapping pairs.
    sigma_px : standard deviation of a measurement without its own sigma, px.
    prior_px : standard deviation of the zero prior of every bias parameter, px (the datum of a block
        without GCPs).
    robust : ``"none"`` or a psi function.
    refit_tolerance_px : the largest refit error accepted (and the GDAL check's tolerance), px.
    max_matches : matches kept per image pair when matching.
    gcp_sigma_xy, gcp_sigma_h : ground standard deviations of GCPs without their own, metres.
    """

    model: str = "shift"
    gcps: str | Path | None = None
    check: tuple[str, ...] = ()
    ties: str | Path | None = None
    sigma_px: float = 0.5
    prior_px: float = 10.0
    robust: str = "huber"
    refit_tolerance_px: float = 0.01
    max_matches: int = 2000
    gcp_sigma_xy: float = 0.5
    gcp_sigma_h: float = 1.0


@dataclass(frozen=True, eq=False)
class RpcAdjustRun:
    """Result of :func:`rpc_adjust`: the adjustment, the refits, GDAL's agreement and the files written."""

    adjustment: RPCBlockAdjustment
    names: tuple[str, ...]
    refits: tuple[RefitResult, ...]
    gdal_max_px: tuple[float, ...]
    tie_source: str
    outputs: tuple[Path, ...]
    n_pairs: int = 0
    notes: tuple[str, ...] = field(default=())
    report: Path | None = None

    def summary_lines(self) -> list[str]:
        a = self.adjustment
        k = BIAS_MODELS[a.model]
        n_tr = len(a.tracks.ids)
        lines = [f"tie points: {n_tr} tracks, {len(a.tracks)} measurements ({self.tie_source})",
                 f"adjustment ({a.model}, robust {a.robust}): sigma0 {a.sigma0:.3f}, redundancy {a.redundancy}, "
                 f"{a.iterations} iterations, {int((a.weights < 0.5).sum())} measurements weighted below 0.5"]
        rms = a.image_rms()
        for j, name in enumerate(self.names):
            p, s = a.params[j], a.std[j]
            bias = (f"bias col {p[0, 0]:+.3f} +- {s[0, 0]:.3f}, row {p[1, 0]:+.3f} +- {s[1, 0]:.3f} px"
                    + (" (at the image centre)" if k > 1 else ""))
            rel = ""
            if j and not len(a.control_ids):
                r = a.relative_std(j)
                rel = f" (+- {r[0, 0]:.3f}, {r[1, 0]:.3f} relative to {self.names[0]})"
            lines.append(f"  {name}: {bias}{rel}; residual RMS col {rms[j, 0]:.3f}, row {rms[j, 1]:.3f} px")
        if len(a.control_ids):
            cr = np.sqrt(np.mean(a.control_residuals ** 2, axis=0))
            lines.append(f"GCPs: {len(a.control_ids)}, residual RMS east {cr[0]:.3f}, north {cr[1]:.3f}, "
                         f"up {cr[2]:.3f} m")
        else:
            lines.append(f"no GCPs: the datum is the bias prior ({a.model} biases of least weighted norm)")
        if a.accuracy is not None:
            lines.extend(a.accuracy.lines())
        mx = max(r.max_px for r in self.refits)
        lines.append(f"refit error: max {mx:.2e} px, RMS {max(r.rms_px for r in self.refits):.2e} px "
                     f"({', '.join(sorted({r.method for r in self.refits}))}; tolerance checked per image)")
        lines.append(f"GDAL RPC transformer on the written VRTs: max {max(self.gdal_max_px):.2e} px from the "
                     "adjusted projection")
        lines.extend(self.notes)
        lines.append(f"wrote {len(self.outputs)} files to {self.outputs[0].parent}")
        if self.report is not None:
            lines.append(f"report: {self.report}")
        return lines


def _stems(images: Sequence[Path]) -> list[str]:
    stems = [p.stem for p in images]
    for s in stems:
        if stems.count(s) > 1:
            raise InvalidInputError(f"two images have the file name stem {s!r}; their refined RPC files would "
                                    "collide: rename one")
    return stems


def _inside(px: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    return (px[:, 0] >= -0.5) & (px[:, 0] <= size[0] - 0.5) & (px[:, 1] >= -0.5) & (px[:, 1] <= size[1] - 0.5)


def _check_gcps(rpcs: Sequence[RPC], sizes: Sequence[tuple[int, int]], names: Sequence[str],
                control: dict, meas_image: np.ndarray, meas_ids: Sequence[str], meas_px: np.ndarray) -> None:
    """Each GCP projects into some image; each measurement lies inside its image."""
    for gid, (g, _s) in control.items():
        gg = np.asarray(g, np.float64)[None, :]
        if not any(_inside(rpc.project(gg), sz)[0] for rpc, sz in zip(rpcs, sizes, strict=True)):
            raise InvalidInputError(f"GCP {gid!r} at lon {g[0]:.6f}, lat {g[1]:.6f}, h {g[2]:.1f} m projects outside "
                                    "every image")
    for j, pid, p in zip(meas_image, meas_ids, meas_px, strict=True):
        if not _inside(p[None, :], sizes[j])[0]:
            raise InvalidInputError(f"GCP {pid!r} is measured at ({p[0]:.1f}, {p[1]:.1f}) outside image "
                                    f"{names[j]!r} ({sizes[j][0]} x {sizes[j][1]} px)")


def _match_pairs(images: Sequence[Path], pairs: Sequence[tuple[int, int]], opts: RpcAdjustOptions,
                 progress: Progress) -> list[tuple[int, int, np.ndarray, np.ndarray]]:
    cfg = MatcherConfig(verify="fundamental", max_matches=opts.max_matches)
    out = []
    for n, (i, j) in enumerate(pairs):
        try:
            res = match_images(images[i], images[j], config=cfg)
        except EstimationError as err:
            raise EstimationError(f"matching {images[i].name} with {images[j].name}: {err}") from None
        out.append((i, j, res.matches.left, res.matches.right))
        if progress is not None:
            progress(n + 1, len(pairs))
    return out


def _residuals_csv(a: RPCBlockAdjustment, names: Sequence[str]) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["image", "id", "col", "row", "res_col", "res_row", "sigma_px", "weight"])  # res = adjusted - measured
    t = a.tracks
    for m in range(len(t)):
        w.writerow([names[t.image[m]], t.ids[t.track[m]], f"{t.pixels[m, 0]:.4f}", f"{t.pixels[m, 1]:.4f}",
                    f"{a.residuals[m, 0]:.4f}", f"{a.residuals[m, 1]:.4f}", f"{t.sigma[m]:.4g}",
                    f"{a.weights[m]:.4f}"])
    return buf.getvalue()


def residual_tables(a: RPCBlockAdjustment, names: Sequence[str]) -> list[ResidualTable]:
    """The adjustment's residuals as report tables: one per image (px, adjusted minus measured) and the check
    points (m east/north/up, intersected minus surveyed)."""
    t = a.tracks
    out = []
    for j, name in enumerate(names):
        s = t.image == j
        out.append(ResidualTable(step=f"image residuals: {name}", ids=[t.ids[i] for i in t.track[s]],
                                 observed=t.pixels[s], adjusted=t.pixels[s] + a.residuals[s], units="px",
                                 components=("dcol", "drow"), weights=a.weights[s], std=t.sigma[s],
                                 position_px=t.pixels[s], n_params=0,
                                 extra={"model": a.model, "sigma0_block": a.sigma0}))
    if len(a.check_ids):
        n = len(a.check_ids)
        out.append(ResidualTable(step="check points", ids=list(a.check_ids), observed=np.zeros((n, 3)),
                                 adjusted=a.check_errors, units="m", components=("de", "dn", "du"),
                                 check=np.ones(n, bool)))
    return out


def _document(run: RpcAdjustRun, opts: RpcAdjustOptions, images: Sequence[Path]) -> dict:
    a = run.adjustment
    rms = a.image_rms()
    imgs = []
    for j, name in enumerate(run.names):
        imgs.append({"image": str(images[j]), "name": name, "size": list(a.sizes[j]),
                     "params": a.params[j].tolist(), "std": a.std[j].tolist(),
                     "std_relative_to_first": a.relative_std(j).tolist(),
                     "params_plain": a.plain_params(j).tolist(),
                     "n_measurements": int((a.tracks.image == j).sum()),
                     "residual_rms_px": rms[j].tolist(),
                     "refit": {"method": run.refits[j].method, "max_px": run.refits[j].max_px,
                               "rms_px": run.refits[j].rms_px, "n_check": run.refits[j].n_check},
                     "gdal_check_max_px": run.gdal_max_px[j]})
    doc = {"model": a.model, "params_frame": "normalised: (col - c0) / s, (row - r0) / s; c0, r0 the image centre, "
           "s half the longer side; params_plain: RPCRefinement's dc = a0 + a1 col + a2 row",
           "robust": a.robust, "sigma0": a.sigma0, "redundancy": a.redundancy, "iterations": a.iterations,
           "prior_px": opts.prior_px, "sigma_px": opts.sigma_px, "tie_source": run.tie_source,
           "n_tracks": len(a.tracks.ids), "n_measurements": len(a.tracks),
           "refit_tolerance_px": opts.refit_tolerance_px, "images": imgs,
           "gcps": {i: r.tolist() for i, r in zip(a.control_ids, a.control_residuals, strict=True)},
           "check_points": {i: e.tolist() for i, e in zip(a.check_ids, a.check_errors, strict=True)},
           "accuracy": None if a.accuracy is None else a.accuracy.to_dict()}
    return stamp("rpc_adjustment", 1, doc)


def rpc_adjust(ws: Workspace, images: Sequence[str | Path], options: RpcAdjustOptions = RpcAdjustOptions(), *,
               progress: Progress = None) -> RpcAdjustRun:
    """Adjust the RPC images ``images`` and write the refined RPCs and the adjustment's files into the
    workspace's output folder ``ws.root`` (all or none; the folder is created only when the files are written).

    Raises
    ------
    InvalidInputError
        Fewer than 2 images, an image without RPC, images that do not overlap, a GCP outside every image,
        bad tables or options.
    EstimationError
        Matching fails, the adjustment is singular, or a refit cannot reach its tolerance.
    RasterIOError
        Unreadable inputs, unwritable outputs.
    """
    o = options
    if o.model not in BIAS_MODELS:
        raise InvalidInputError(f"unknown bias model {o.model!r}; expected one of {list(BIAS_MODELS)}")
    if not (o.sigma_px > 0 and o.refit_tolerance_px > 0 and o.prior_px > 0):
        raise InvalidInputError(f"sigma_px, prior_px and refit_tolerance_px must be > 0; got {o.sigma_px!r}, "
                                f"{o.prior_px!r}, {o.refit_tolerance_px!r}")
    paths = [Path(p) for p in images]
    if len(paths) < 2:
        raise InvalidInputError(f"rpc-adjust needs at least 2 images; got {len(paths)}")
    if ws.root is None:
        raise InvalidInputError("rpc-adjust needs an output folder")
    out = ws.root
    stems = _stems(paths)
    names = [p.name for p in paths]
    ws.add_inputs(*paths, o.ties, o.gcps)
    planned = [out / n for s in stems for n in (f"{s}.vrt", f"{s}_RPC.TXT", f"{s}.RPB")]
    planned += [out / "adjustment.json", out / "residuals.csv"]
    ws.plan(*planned)
    ws.check_report_dir()
    rpcs = [rpc_from_raster(p) for p in paths]
    sizes = [(raster_info(p).width, raster_info(p).height) for p in paths]
    pairs = check_overlap(rpcs, sizes, names)
    control: dict = {}
    g_im, g_px, g_sg = np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros(0)
    g_ids: tuple[str, ...] = ()
    if o.gcps is not None:
        gm, control = read_rpc_gcps(o.gcps, [str(p) for p in paths], sigma_xy=o.gcp_sigma_xy, sigma_h=o.gcp_sigma_h)
        _check_gcps(rpcs, sizes, names, control, gm.image, gm.ids, gm.pixels)
        g_im, g_ids, g_px, g_sg = gm.image, gm.ids, gm.pixels, gm.sigma
    for c in o.check:
        if c not in control:
            raise InvalidInputError(f"check point {c!r} is not a GCP of {str(o.gcps)!r}" if o.gcps else
                                    f"check point {c!r} given without --gcps")
    if o.ties is not None:
        tm = read_rpc_ties(o.ties, [str(p) for p in paths])
        clash = sorted(set(tm.ids) & set(control))
        if clash:
            raise InvalidInputError(f"tie point id {clash[0]!r} is also a GCP id; use distinct ids")
        t_ids, t_im, t_px, t_sg = tm.ids, tm.image, tm.pixels, tm.sigma
        source = f"tie-point file {o.ties}"
    else:
        matched = _match_pairs(paths, pairs, o, progress)
        ids, t_im, tr, t_px = chain_matches(matched, prefix="t")
        t_ids = tuple(ids[t] for t in tr)
        t_sg = np.full(len(t_im), np.nan)
        source = f"matched {len(pairs)} overlapping pairs, chained"
    all_ids = tuple(t_ids) + tuple(g_ids)
    uniq = tuple(dict.fromkeys(all_ids))
    index = {u: i for i, u in enumerate(uniq)}
    sig = np.concatenate([t_sg, g_sg])
    sig = np.where(np.isfinite(sig), sig, o.sigma_px)
    tracks = TieTracks.from_arrays(uniq, np.concatenate([t_im, g_im]), [index[i] for i in all_ids],
                                   np.vstack([t_px, g_px]), sig)
    adj = RPCBlockAdjustment.from_observations(rpcs, sizes, tracks, control=control, check=o.check, model=o.model,
                                               prior_px=o.prior_px, robust=o.robust, names=names)
    refits = tuple(refit_rpc(adj.refinement(j), tolerance_px=o.refit_tolerance_px, source=names[j])
                   for j in range(len(paths)))
    gdal_max: list[float] = []
    ws.prepare()
    try:
        with ws.transaction():
            written = []
            for j, (p, s) in enumerate(zip(paths, stems, strict=True)):
                vrt = out / f"{s}.vrt"
                with ws.output(vrt, suffix=".vrt") as tmp:
                    tmp.write_text(rpc_vrt_text(p, refits[j].rpc.to_rasterio()))
                    sel = adj.tracks.image == j
                    g = adj.ground[adj.tracks.track[sel]]
                    ours = adj.refinement(j).project(g)
                    theirs = gdal_rpc_project(tmp, g)
                    err = float(np.nanmax(np.hypot(*(theirs - ours).T))) if len(g) else 0.0
                    if not np.isfinite(theirs).all() or not err <= o.refit_tolerance_px:
                        raise EstimationError(f"GDAL's RPC transformer on the refined RPC of {names[j]} is "
                                              f"{err:.3g} px from the adjusted projection (tolerance "
                                              f"{o.refit_tolerance_px:g} px)")
                    gdal_max.append(err)
                written.append(vrt)
                written.append(ws.write_text(out / f"{s}_RPC.TXT", rpc_txt_text(refits[j].rpc)))
                written.append(ws.write_text(out / f"{s}.RPB", rpb_text(refits[j].rpc)))
            run = RpcAdjustRun(adj, tuple(names), refits, tuple(gdal_max), source,
                               tuple(written) + (out / "adjustment.json", out / "residuals.csv"), len(pairs))
            ws.write_json(out / "adjustment.json", _document(run, o, paths))
            ws.write_text(out / "residuals.csv", _residuals_csv(adj, names))
            if ws.report_dir is not None:
                # local: the report (matplotlib) loads only when --report asks for it
                from rectify.report.builder import write_report

                with ws.report_folder() as stage:
                    write_report(stage, title=f"rectify rpc-adjust: {', '.join(names)}",
                                 tables=residual_tables(adj, names), summary=_document(run, o, paths),
                                 image_shapes={f"image residuals: {n}": (sz[1], sz[0])
                                               for n, sz in zip(names, sizes, strict=True)}, overwrite=True)
                run = replace(run, report=ws.report_dir / "report.html")
    except BaseException:
        ws.discard_root()
        raise
    return run
