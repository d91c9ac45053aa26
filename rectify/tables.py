"""Moved to :mod:`rectify.formats` (issue 11); this name is kept only until every importer is updated."""

from .formats import (  # noqa: F401
    ControlTable,
    GcpTable,
    Matches,
    read_control,
    read_gcps,
    read_matches,
    write_gcps,
    write_matches,
)
