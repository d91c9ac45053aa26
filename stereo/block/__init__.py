"""Block triangulation: multi-image tie points, poses in, independent models, bundle adjustment.

See ``docs/block.md``. The command ``stereo block`` runs :func:`stereo.actions.block.run_block`.

Modules
-------
types
    :class:`Pose` (one image's exterior orientation) and :class:`Tracks` (multi-image tie points).
poses, files
    Position/angle CSV, navigation angles, OpenSfM ``reconstruction.json``; block control CSV,
    observations CSV, block orientation JSON.
tracks, tracks_pairs, tracks_graph, render
    Block tie points (pair selection, union-find tracks, even spread); rendered synthetic blocks.
independent
    Initial orientation by independent models; ``to_ground``; ``triangulate_tracks``.
bundle, bundle_model, bundle_solve, bundle_datum, synthetic
    The bundle adjustment and synthetic blocks with known truth.
report, workflow
    The QA report and ``run_block``.
"""
