"""Command line of :mod:`rectify`: a thin click layer over the library."""
