"""Block triangulation formulas: poses, tracks, navigation angles, independent models, bundle adjustment.

See ``docs/block.md``. The command ``stereo block`` runs :func:`stereo.actions.block.run_block`;
the tie points come from :mod:`stereo.features.tracks`, the files from :mod:`stereo.formats.poses`,
:mod:`stereo.formats.opensfm` and :mod:`stereo.formats.block`, the report from
:mod:`stereo.report.block`.

Modules
-------
types
    :class:`Pose` (one image's exterior orientation), :class:`Tracks` (multi-image tie points),
    :class:`BlockControl` (control and check points) and :class:`GnssObservations` (GNSS/INS).
navigation
    GNSS/INS navigation angles (heading, pitch, roll) <-> camera rotations; boresight, lever arm.
tracks_pairs, tracks_graph
    Image pairs to match (footprints, overview); union-find tracks from pairwise matches, even
    spread.
independent, models
    Initial orientation without poses by independent models (image graph, final multi-ray
    intersection, ``triangulate_tracks``, ``to_ground``); the models, their join and
    simultaneous adjustment, and ``IndependentOptions``.
bundle
    The bundle adjustment (package: ``adjust``, ``result``, ``model``, ``solve``, ``datum``).
"""
