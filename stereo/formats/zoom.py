"""Focal settings of the views of a zoom calibration (``stereo calibrate --zoom``).

The zoom camera JSON itself is read and written by :mod:`rectify.formats.camera` (``docs/formats.md``,
"Zoom camera JSON"). A view's focal setting comes from, in this order:

- a settings CSV (``--settings``), one row per view or image::

      view,setting
      img01.jpg,18.0

  ``view`` is the view name of the observation CSV, or an image's file name or stem (the column may
  be named ``image`` instead: ``stereo block --focal-settings`` reads the same file, ``image,setting``);
- a ``setting`` column of the observation CSV (``--points``): every row of a view holds the same value;
- the EXIF FocalLength of a chessboard image (mm).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rectify.errors import InvalidInputError
from rectify.formats.common import MAX_MATCH_ROWS, TableReader

__all__ = ["SETTING_COLUMN", "read_settings_csv", "observation_settings", "setting_for"]

#: the column of the focal setting (observation CSV, settings CSV)
SETTING_COLUMN = "setting"


def read_settings_csv(path: str | Path) -> dict[str, float]:
    """Read a settings CSV ``view,setting`` (or ``image,setting``) -> {view or image: setting}.

    Raises
    ------
    InvalidInputError
        Missing columns, an empty file, a bad number, a view named twice.
    """
    label = f"settings file {str(path)!r}"
    try:
        with TableReader(path, lower=True) as t:
            key = "image" if "image" in t.fields and "view" not in t.fields else "view"
            miss = [c for c in (key, SETTING_COLUMN) if c not in t.fields]
            if miss:
                raise InvalidInputError(f"{label} lacks column(s) {miss}; expected view,setting (or image,setting)")
            cols = t.read("rows", numbers=(SETTING_COLUMN,), texts=(key,), max_rows=MAX_MATCH_ROWS)
    except InvalidInputError as err:
        if "has no header and no rows" in str(err):
            raise InvalidInputError(f"{label} is empty") from None
        raise
    out: dict[str, float] = {}
    for k, (v, z) in enumerate(zip(cols.texts[key], cols.numbers[SETTING_COLUMN].tolist(), strict=True)):
        if v in out:
            raise InvalidInputError(f"{label} line {cols.lines[k]}: {key} {v!r} given twice")
        out[v] = float(z)
    return out


def observation_settings(path: str | Path) -> dict[str, float] | None:
    """The ``setting`` column of an observation CSV -> {view: setting}; None when the file has no such column.

    Raises
    ------
    InvalidInputError
        A bad number, or two settings in one view (line named).
    """
    with TableReader(path, lower=True) as t:
        if SETTING_COLUMN not in t.fields:
            return None
        cols = t.read("rows", numbers=(SETTING_COLUMN,), texts=("view",), max_rows=MAX_MATCH_ROWS)
    out: dict[str, float] = {}
    for k, (v, z) in enumerate(zip(cols.texts["view"], cols.numbers[SETTING_COLUMN].tolist(), strict=True)):
        if v in out and not np.isclose(out[v], z, rtol=0, atol=0):
            raise InvalidInputError(f"observation file {str(path)!r} line {cols.lines[k]}: view {v!r} has two "
                                    f"focal settings ({out[v]:g} and {z:g})")
        out[v] = float(z)
    return out


def setting_for(name: str, table: dict[str, float]) -> float | None:
    """The setting of a view or image ``name`` in ``table`` (by the name, its file name or its stem)."""
    p = Path(name)
    for key in (name, p.name, p.stem):
        if key in table:
            return table[key]
    return None
