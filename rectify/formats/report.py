"""The report files: ``report.json`` and the residual table CSVs beside it (``docs/formats.md``).

``report.json``: ``"format": "rectify-stereo/report"``, version :data:`REPORT_VERSION` (release 0.1.0
wrote ``report_version: 1``). A residual table CSV starts with a ``# step=...; units=...`` line and holds
the rows of :meth:`rectify.geometry.residuals.ResidualTable.to_csv`.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from rectify.atomic import atomic_write_text, read_json
from rectify.errors import InvalidInputError
from rectify.formats.common import (
    StrPath,
    cell_number,
    check_format,
    load_table,
    need_columns,
    read_table_text,
    stamp,
    unstamped,
)
from rectify.geometry.residuals import ResidualTable

__all__ = ["REPORT_VERSION", "read_report", "report_json_text", "read_residuals", "write_residuals"]

#: Version of ``report.json`` (1: 0.1.0, ``report_version: 1``; 2: ``format``/``version`` keys).
REPORT_VERSION = 2


# --------------------------------------------------------------------------- report JSON
def report_json_text(doc: Mapping[str, Any]) -> str:
    """``report.json`` text: the stamp, then ``doc`` (already JSON-safe: no NaN)."""
    return json.dumps(stamp("report", REPORT_VERSION, doc), indent=2, allow_nan=False)


def read_report(path: StrPath) -> dict[str, Any]:
    """Read ``report.json`` (give the file or the report folder); release 0.1.0's ``report_version: 1``
    is accepted.

    Returns
    -------
    dict
        ``title``, ``created_utc``, ``crs``, ``tables`` (step, slug, units, components, summary, files),
        ``figures``, ``summary``, ``files``, and ``version``.
    """
    p = Path(path)
    if p.is_dir():
        p = p / "report.json"
    doc = read_json(p, "report file")
    version = check_format(doc, "report", REPORT_VERSION, p, version_key="report_version")
    out = unstamped(doc)
    out.pop("report_version", None)
    out["version"] = version
    return out


# --------------------------------------------------------------------------- residual CSV
_STEP_LINE = re.compile(r"#\s*step=(?P<step>.*); units=(?P<units>[^;]*)(;|$)")


def read_residuals(path: StrPath) -> ResidualTable:
    """Read a residual table CSV of a report (``ResidualTable.to_csv``).

    The CSV keeps ids, observed, adjusted, components, weights and the outlier/check flags; the
    parameter count is not stored, so ``sigma0`` of the result is the one of the file's rows with
    ``n_params = 0``.
    """
    text = read_table_text(path)
    first = text.splitlines()[0] if text else ""
    m = _STEP_LINE.match(first)
    if m is None:
        raise InvalidInputError(f"{str(path)!r}: first line must be '# step=...; units=...'; got {first[:60]!r}")
    rows, lines, _, fields = load_table(path, "residual rows")
    k = sum(1 for f in fields if f.startswith("observed_"))
    adj = [f"adjusted_{j}" for j in range(k)]
    comps = tuple(fields[1 + 2 * k: 1 + 3 * k])
    need_columns(fields, ("id", *(f"observed_{j}" for j in range(k)), *adj, "norm", "weight", "outlier", "check"), path)

    def val(r: dict[str, str], key: str, ln: int) -> float:
        return math.nan if r[key] == "nan" else cell_number(r, key, ln, path)

    obs = [[val(r, f"observed_{j}", ln) for j in range(k)] for r, ln in zip(rows, lines, strict=False)]
    adjusted = [[val(r, a, ln) for a in adj] for r, ln in zip(rows, lines, strict=False)]
    return ResidualTable(step=m["step"], ids=[r["id"] for r in rows], observed=np.array(obs).reshape(-1, k),
                         adjusted=np.array(adjusted).reshape(-1, k), units=m["units"].strip(), components=comps,
                         weights=np.array([cell_number(r, "weight", ln, path)
                                           for r, ln in zip(rows, lines, strict=False)]),
                         outlier=np.array([r["outlier"] == "1" for r in rows]),
                         check=np.array([r["check"] == "1" for r in rows]))


def write_residuals(path: StrPath, table: ResidualTable, *, overwrite: bool = False) -> Path:
    """Write a residual table CSV atomically (``ResidualTable.to_csv`` text); return the path."""
    return atomic_write_text(path, table.to_csv(), overwrite=overwrite)
