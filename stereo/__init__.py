"""Stereo photogrammetry: relative and absolute orientation, resection,
intersection and stereo models. Builds on :mod:`rectify` (never the reverse)."""

from rectify import __version__  # the version lives in one place: rectify/__init__.py

__all__ = ["__version__"]
