"""The transform JSON written by ``rectify fit`` and read by ``rectify warp --transform`` (``docs/formats.md``).

``"format": "rectify-stereo/transform"``, version :data:`TRANSFORM_VERSION` (1: release 0.1.0, whose
files say ``"format": "rectify-transform"``). The body is the model's parameters (the transforms'
``transform_to_dict``), its CRS and, after a fit, the residuals of every GCP.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from rectify.atomic import atomic_write_text, read_json
from rectify.errors import InvalidInputError
from rectify.formats.common import StrPath, check_format, malformed, stamp
from rectify.geometry.residuals import ResidualTable
from rectify.geometry.transforms import transform_from_dict, transform_to_dict

__all__ = ["TRANSFORM_VERSION", "TransformFile", "read_transform", "write_transform", "transform_document",
           "transform_text"]

#: Version of the transform JSON (1: 0.1.0, ``format: rectify-transform``; 2: ``rectify-stereo/transform``).
TRANSFORM_VERSION = 2


@dataclass(frozen=True, eq=False)
class TransformFile:
    """A transform JSON file read back.

    Attributes
    ----------
    model : transform
        The model (source pixels -> target), rebuilt by the transforms' ``transform_from_dict``.
    method : str
        Registry name (``homography``, ``cotangent``, ``affine``, ``poly2``, ``poly3``).
    crs : str or None
        CRS of the target coordinates.
    units : str or None
        Units of the residuals.
    rmse, rmse_check : float or None
        Fit and check-point RMSE, ``units``.
    summary : dict
        The residual table's summary (JSON-able entries).
    residuals : list of dict
        One per GCP: ``id``, ``observed``, ``adjusted`` (target), ``dx``, ``dy``, ``norm``, ``check``.
    version : int
        Version the file was written with (1 for release 0.1.0).
    extra : dict
        Other keys (a caller's ``extra``).
    """

    model: Any
    method: str
    crs: str | None = None
    units: str | None = None
    rmse: float | None = None
    rmse_check: float | None = None
    summary: dict[str, Any] = field(default_factory=dict)
    residuals: list[dict[str, Any]] = field(default_factory=list)
    version: int = TRANSFORM_VERSION
    extra: dict[str, Any] = field(default_factory=dict)


_TRANSFORM_KEYS = {"format", "version", "method", "direction", "matrix", "src", "dst", "order", "coefficients",
                   "shift", "scale", "domain", "crs", "rmse", "rmse_check", "units", "summary", "residuals"}


def _jsonable(v: Any) -> bool:
    try:
        json.dumps(v)
        return True
    except (TypeError, ValueError):
        return False


def transform_document(model: Any, *, table: ResidualTable | None = None, crs: str | None = None,
                       extra: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """The transform JSON object.

    Keys: the stamp, ``method``, ``direction`` and the model's parameters (the transforms'
    ``transform_to_dict``), ``crs`` of the target (when known), and, with ``table``, ``rmse``,
    ``rmse_check``, ``units``, ``summary`` and ``residuals`` (one object per GCP), then ``extra``.
    """
    out = stamp("transform", TRANSFORM_VERSION, transform_to_dict(model))
    if crs:
        out["crs"] = crs
    if table is not None:
        s = table.summary()
        out["rmse"] = s["rmse"]
        out["rmse_check"] = s["rmse_check"]
        out["units"] = table.units
        out["summary"] = {k: v for k, v in s.items() if _jsonable(v)}
        res, check = table.residual, np.asarray(table.check, dtype=bool)
        norm, observed, adjusted = table.norm, table.observed, table.adjusted  # each computed once, not per row
        out["residuals"] = [
            {"id": table.ids[i], "observed": observed[i].tolist(), "adjusted": adjusted[i].tolist(),
             "dx": float(res[i, 0]), "dy": float(res[i, 1]), "norm": float(norm[i]),
             "check": bool(check[i])} for i in range(table.n)]
    if extra:
        out.update(extra)
    return out


def transform_text(model: Any, *, table: ResidualTable | None = None, crs: str | None = None,
                   extra: Mapping[str, Any] | None = None) -> str:
    """:func:`transform_document` as indented JSON text (NaN kept as ``NaN``, as in release 0.1.0)."""
    return json.dumps(transform_document(model, table=table, crs=crs, extra=extra), indent=2, allow_nan=True) + "\n"


def write_transform(path: StrPath, model: Any, *, table: ResidualTable | None = None, crs: str | None = None,
                    extra: Mapping[str, Any] | None = None, overwrite: bool = False) -> Path:
    """Write a transform JSON file atomically (:func:`transform_document`); return the path."""
    return atomic_write_text(path, transform_text(model, table=table, crs=crs, extra=extra), overwrite=overwrite)


def read_transform(path: StrPath) -> TransformFile:
    """Read a transform JSON written by ``rectify fit`` (this release or 0.1.0).

    Raises
    ------
    RasterIOError
        File missing or unreadable.
    InvalidInputError
        Not JSON, another format, a newer version, or not a valid transform.
    """
    doc = read_json(path, "transform file")
    version = check_format(doc, "transform", TRANSFORM_VERSION, path, legacy={"rectify-transform": 1})
    for key, kind, name in (("method", str, "a method name"), ("summary", dict, "an object"),
                            ("residuals", list, "a list")):
        if doc.get(key) is not None and not isinstance(doc[key], kind):
            raise InvalidInputError(f"transform file {str(path)!r}: `{key}` must be {name}; got {doc[key]!r:.80}")
    with malformed(f"transform file {str(path)!r}"):  # a third-party error of a malformed value: one line
        model = transform_from_dict(doc)
    return TransformFile(model=model, method=str(doc["method"]), crs=doc.get("crs"), units=doc.get("units"),
                         rmse=doc.get("rmse"), rmse_check=doc.get("rmse_check"), summary=dict(doc.get("summary") or {}),
                         residuals=list(doc.get("residuals") or []), version=version or 1,
                         extra={k: v for k, v in doc.items() if k not in _TRANSFORM_KEYS})
