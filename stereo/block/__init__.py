"""Block triangulation: multi-image tie points, poses in, independent models, bundle adjustment.

Modules
-------
types
    :class:`Pose` (one image's exterior orientation) and :class:`Tracks` (multi-image tie points).
"""

from .types import Pose, Tracks, cameras_for, project_pixel

__all__ = ["Pose", "Tracks", "cameras_for", "project_pixel"]
