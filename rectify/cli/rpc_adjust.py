"""``rectify rpc-adjust IMAGES... -o OUTDIR``: block adjustment of RPC images, refined RPCs GDAL reads."""

from __future__ import annotations

import click

from rectify.actions.rpc_adjust import BIAS_MODELS, ROBUST_METHODS, RpcAdjustOptions
from rectify.actions.rpc_adjust import rpc_adjust as rpc_adjust_action
from rectify.actions.workspace import Workspace
from rectify.cli.options import echo, handle_errors, overwrite_opt, progress, report_opt

_D = RpcAdjustOptions()
_POS = click.FloatRange(min=0, min_open=True)


@click.command("rpc-adjust", short_help="Block adjustment of RPC images; writes refined RPCs.")
@click.argument("images", nargs=-1, required=True, type=click.Path(dir_okay=False))
@click.option("-o", "--output", "outdir", required=True, type=click.Path(file_okay=False),
              help="Output folder (created): <stem>.vrt, <stem>_RPC.TXT, <stem>.RPB, adjustment.json, residuals.csv.")
@click.option("--model", type=click.Choice(list(BIAS_MODELS)), default=_D.model, show_default=True,
              help="Image-space bias per image: shift (2 parameters) or affine (6).")
@click.option("--gcps", type=click.Path(dir_okay=False), default=None,
              help="GCP CSV: id,image,col,row,lon,lat,h[,sigma_xy,sigma_h,sigma] (WGS 84 degrees, ellipsoidal m).")
@click.option("--check", default="", help="Comma-separated GCP ids used as check points.")
@click.option("--ties", type=click.Path(dir_okay=False), default=None,
              help="Tie-point CSV image,id,col,row[,sigma] instead of matching the overlapping pairs.")
@click.option("--sigma", "sigma_px", type=_POS, default=_D.sigma_px, show_default=True,
              help="Standard deviation of a measurement without its own, px.")
@click.option("--prior", "prior_px", type=_POS, default=_D.prior_px, show_default=True,
              help="Standard deviation of the zero prior of each bias parameter, px (the datum without GCPs).")
@click.option("--robust", type=click.Choice(list(ROBUST_METHODS)), default=_D.robust, show_default=True)
@click.option("--refit-tolerance", "refit_tolerance_px", type=_POS, default=_D.refit_tolerance_px,
              show_default=True, help="Largest refit error of a written RPC, px.")
@click.option("--max-matches", type=click.IntRange(20), default=_D.max_matches, show_default=True,
              help="Matches kept per image pair.")
@report_opt
@overwrite_opt
@handle_errors
def rpc_adjust(images, outdir, model, gcps, check, ties, sigma_px, prior_px, robust, refit_tolerance_px,
               max_matches, report_dir, overwrite):
    """Adjust the RPCs of IMAGES (GeoTIFF RPC tags, or an _RPC.TXT/.RPB beside each) together: an
    image-space bias per image (Grodecki and Dial), tie points from matching the overlapping pairs (or
    --ties), optional GCPs and check points. Writes each image's refined RPC as a VRT of the image
    (no pixels copied; GDAL reads its RPC), an _RPC.TXT and an .RPB, with adjustment.json and
    residuals.csv. Prints sigma0, the biases with their standard errors, the check-point accuracy and the
    refit error.
    """
    opts = RpcAdjustOptions(model=model, gcps=gcps or None,
                            check=tuple(c.strip() for c in check.split(",") if c.strip()),
                            ties=ties or None, sigma_px=sigma_px, prior_px=prior_px, robust=robust,
                            refit_tolerance_px=refit_tolerance_px, max_matches=max_matches)
    ws = Workspace(outdir, overwrite=overwrite, report_dir=report_dir)
    with progress("matching pairs") as cb:
        run = rpc_adjust_action(ws, images, opts, progress=cb)
    for line in run.summary_lines():
        echo(line)
