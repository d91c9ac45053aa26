"""Command line of :mod:`stereo`."""
