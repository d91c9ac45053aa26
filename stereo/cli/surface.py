"""``stereo surface``: a block's orientation -> one fused DSM with sigma_Z, count and provenance bands."""

from __future__ import annotations

import click

from rectify.cli.options import echo, handle_errors, overwrite_opt, scheduler_opt
from stereo.actions.surface import ORIENTATION_SIGMA, SurfaceOptions, run_surface

_D = SurfaceOptions()


@click.command(short_help="One DSM from a block's orientation: stereo pairs, dense matching, robust fusion, sigma_Z.")
@click.argument("orientation", type=click.Path())
@click.option("-o", "--out", "out_dir", required=True, type=click.Path(file_okay=False),
              help="Output folder (dsm.tif: height, sigma_Z, count, provenance; pairs.json).")
@click.option("--images", type=click.Path(file_okay=False), default=None,
              help="Folder of the images named in the orientation [default: the orientation's folder].")
@click.option("--cell", type=float, default=None,
              help="DSM cell, ground units [default: the ground pixel, 2 significant digits; at least a tenth of it].")
@click.option("--ground-z", type=float, default=None,
              help="Mean terrain height [default: the median height of the block's points.csv].")
@click.option("--relief", type=float, default=None,
              help="Height range about --ground-z for the disparity search [default: the block points' range plus a "
                   "tenth of the flying height].")
@click.option("--min-overlap", type=float, default=_D.min_overlap, show_default=True,
              help="Smallest footprint overlap of a pair (share of the smaller footprint).")
@click.option("--base-height", nargs=2, type=float, default=(_D.min_base_height, _D.max_base_height),
              show_default=True, help="Range of the pairs' base-to-height ratio.")
@click.option("--angle", nargs=2, type=float, default=(_D.min_angle_deg, _D.max_angle_deg), show_default=True,
              help="Range of the pairs' intersection angle, degrees.")
@click.option("--pairs-per-area", type=int, default=_D.pairs_per_area, show_default=True,
              help="Pairs kept per area (an 8 x 8 grid over the block), best first.")
@click.option("--k-sigma", type=float, default=_D.k_sigma, show_default=True,
              help="Pair heights farther than this many sigma from the others are rejected.")
@click.option("--reference-dem", type=click.Path(dir_okay=False), default=None,
              help="Compare the DSM with this DEM (RMSE, NMAD, coverage; in pairs.json and the summary).")
@click.option("--orientation-sigma", type=click.Choice(list(ORIENTATION_SIGMA)), default=_D.orientation_sigma,
              show_default=True,
              help="The orientation's share of sigma_Z: the block points' height standard errors (points.csv), the "
                   "pose standard errors taken as independent (poses), none; auto: points, else poses, else none.")
@scheduler_opt
@overwrite_opt
@handle_errors
def surface(orientation, out_dir, images, cell, ground_z, relief, min_overlap, base_height, angle, pairs_per_area,
            k_sigma, reference_dem, orientation_sigma, scheduler, overwrite):
    """Fuse the dense surfaces of a block's stereo pairs into one DSM. ORIENTATION is the output folder of
    `stereo block` (its orientation.json) or a block orientation JSON; the images are found by the names
    it records, in --images."""
    opts = SurfaceOptions(images=images, cell=cell, ground_z=ground_z, relief=relief, min_overlap=min_overlap,
                          min_base_height=base_height[0], max_base_height=base_height[1], min_angle_deg=angle[0],
                          max_angle_deg=angle[1], pairs_per_area=pairs_per_area, k_sigma=k_sigma,
                          reference_dem=reference_dem, orientation_sigma=orientation_sigma,
                          scheduler=scheduler)
    result = run_surface(orientation, out_dir, options=opts, overwrite=overwrite)
    for line in result.summary_lines():
        echo(line)
