"""Stereo photogrammetry: relative and absolute orientation, resection,
intersection and stereo models. Builds on :mod:`rectify` (never the reverse)."""

__version__ = "0.1.0"
