"""``stereo sat-intersect``: seed 001's satellite workflow, intersection in the geocentric frame."""

from __future__ import annotations

import click

from rectify.cli.options import echo, handle_errors, overwrite_opt
from stereo.actions.sat_intersect import SatIntersectOptions
from stereo.actions.sat_intersect import sat_intersect as sat_action

_D = SatIntersectOptions()


@click.command("sat-intersect", short_help="Intersect satellite image rays in the geocentric frame (seed 001).")
@click.option("--stations", "stations_path", required=True, type=click.Path(exists=True, dir_okay=False),
              help="Stations CSV image,x,y,z,heading,pitch,roll,f_mm (map x east, y north; heights as --geoid).")
@click.option("--points", "points_path", required=True, type=click.Path(exists=True, dir_okay=False),
              help="Image points CSV id,image,x_mm,y_mm[,sigma_mm] (photo mm, x right, y up).")
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False), help="Points CSV to write.")
@click.option("--crs", default=None, help="Map CRS (Gauss-Krueger, e.g. EPSG:28404; compound with a vertical CRS "
                                          "allowed); default the stations file's '# crs=' line.")
@click.option("--geoid", default=None,
              help="Quasi-geoid / geoid model of the heights: a PROJ grid file (GeoTIFF, GTX) or a vertical CRS "
                   "whose grid is installed (nothing is downloaded).")
@click.option("--ellipsoidal", is_flag=True, default=False, help="The heights are ellipsoidal (no model).")
@click.option("--sigma-mm", type=float, default=_D.sigma_mm, show_default=True,
              help="Standard deviation of an image coordinate, mm (points without sigma_mm).")
@overwrite_opt
@handle_errors
def sat_intersect(stations_path, points_path, output, crs, geoid, ellipsoidal, sigma_mm, overwrite):
    """Gauss-Krueger and normal heights -> geocentric -> intersection -> B, L, H -> Gauss-Krueger (seed 001)."""
    result = sat_action(stations=stations_path, points=points_path, output=output, overwrite=overwrite,
                        options=SatIntersectOptions(crs=crs, geoid=geoid, ellipsoidal=ellipsoidal, sigma_mm=sigma_mm))
    for line in result.summary_lines():
        echo(line)
