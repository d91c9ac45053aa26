"""``rectify match LEFT RIGHT -o matches.csv``: tie points between two images."""

from __future__ import annotations

import click

from .options import echo, handle_errors, overwrite_opt, progress, report_opt


@click.command(short_help="Find tie points between two images.")
@click.argument("left", type=click.Path(dir_okay=False))
@click.argument("right", type=click.Path(dir_okay=False))
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False), help="Matches CSV to write.")
@click.option("--detector", type=click.Choice(["sift", "orb", "akaze"]), default="sift", show_default=True)
@click.option("--verify", type=click.Choice(["homography", "fundamental", "none"]), default="homography",
              show_default=True, help="Geometric verification (OpenCV USAC MAGSAC++).")
@click.option("--refine/--no-refine", default=True, show_default=True,
              help="Least-squares matching refinement of the positions.")
@click.option("--max-matches", type=click.IntRange(1), default=None,
              help="At most this many matches, spread evenly (default 20000).")
@click.option("--threshold", "threshold_px", type=click.FloatRange(min=0, min_open=True), default=None,
              help="USAC inlier threshold, px (default 1.5).")
@report_opt
@overwrite_opt
@handle_errors
def match(left, right, output, detector, verify, refine, max_matches, threshold_px, report_dir, overwrite):
    """Match LEFT against RIGHT and write the verified tie points to a CSV
    (id,col_left,row_left,col_right,row_right,score; pixel centres at integers).

    Large images (a side above 4096 px) are matched coarse-to-fine by tiles
    with bounded memory. Prints the counts (detected, matched, verified) and
    the verification residual RMSE.
    """
    from ..features import MatcherConfig, match_images
    from ..fileutil import check_output
    from ..tables import write_matches

    check_output(output, overwrite=overwrite)
    kw = {"detector": detector, "verify": verify, "refine": refine}
    if max_matches is not None:
        kw["max_matches"] = max_matches
    if threshold_px is not None:
        kw["threshold_px"] = threshold_px
    cfg = MatcherConfig(**kw)
    with progress("matching") as cb:
        res = match_images(left, right, config=cfg, progress=cb)
    write_matches(output, res.matches, overwrite=overwrite)
    s = res.summary()
    echo(f"detected: {s['n_detected_left']} left, {s['n_detected_right']} right keypoints "
         f"({detector}{', tiled' if res.tiled else ''})")
    echo(f"matched: {s['n_matched']} (ratio test + mutual check)")
    refined = (f"refined: {s['n_refined']} converged, {s['n_refine_failed']} dropped (least-squares matching"
               f"{', per tile, before verification' if res.tiled else ''})")
    if refine and res.tiled:  # tiled path: candidates are refined in their tile, then verified together
        echo(refined)
    echo(f"verified: {s['n_verified']} ({verify})")
    if refine and not res.tiled:
        echo(refined)
    expected = s["n_verified"] - (s["n_refine_failed"] if refine and not res.tiled else 0)
    if len(res.matches) != expected:
        echo(f"kept: {len(res.matches)} of the verified matches (evenly spread, --max-matches "
             f"{cfg.max_matches}, re-verified)")
    if verify != "none":
        metric = "transfer error" if verify == "homography" else "Sampson distance"
        line = f"verification RMSE: {res.rmse_px:.3f} px ({metric}, n={len(res.matches)})"
        if refine:
            line += f"; raw positions {res.rmse_raw_px:.3f} px"
        echo(line)
        if res.verification.table is not None:
            echo(res.verification.table.summary_line())
    echo(f"wrote {len(res.matches)} matches to {output}")
    if report_dir is not None:
        from .. import io as rio
        from ..plots import match_figures
        from ..report import write_report

        prev = []
        for p in (left, right):
            data, valid, scale = rio.read_overview(p, 1024)
            prev.append((rio.to_uint8(data, valid), scale))
        figs = match_figures(res, prev[0], prev[1])
        tables = [res.verification.table] if res.verification.table is not None else []
        path = write_report(report_dir, title=f"rectify match: {left} / {right}", tables=tables, figures=figs,
                            summary={**s, "left": str(left), "right": str(right)}, overwrite=overwrite,
                            image_shapes={t.step: res.image_shapes[0] for t in tables})
        echo(f"report: {path}")
