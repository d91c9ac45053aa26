"""Sensor models of the orthorectifier: ground points -> image pixels, and back at a given height.

Formulas only (arrays in, arrays out; no files or rasters). Frame and RPC models share one small
interface, :class:`SensorModel`: ``crs`` (the ground CRS of the model), ``width``/``height`` (image
size), ``project(ground (N, 3)) -> pixels (N, 2)`` (NaN where it cannot),
``ground_at_height(pixels (N, 2), h) -> ground (N, 3)`` and ``nadir`` (the ground point under the
sensor, or the image centre for RPCs, in ``crs``). Pixels are (col, row) with pixel centres at
integers; heights in metres.

A frame model is read from a camera JSON and an exterior orientation JSON by
:func:`rectify.formats.exterior.read_frame_model`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from rectify.errors import CRSError, ShapeError
from rectify.geometry.camera import Camera
from rectify.geometry.crs import crs_to_string
from rectify.geometry.rotation import check_rotation

__all__ = ["SensorModel", "FrameModel", "RPCModel"]


class SensorModel(Protocol):
    """What the orthorectifier needs of a sensor (module docstring)."""

    @property
    def crs(self) -> str: ...

    @property
    def width(self) -> int: ...

    @property
    def height(self) -> int: ...

    def project(self, ground: NDArray[np.float64]) -> NDArray[np.float64]: ...

    def ground_at_height(self, pixels: NDArray[np.float64], h: NDArray[np.float64] | float
                         ) -> NDArray[np.float64]: ...

    @property
    def nadir(self) -> NDArray[np.float64]: ...


@dataclass(frozen=True, eq=False)
class FrameModel:
    """A frame camera: interior orientation + exterior orientation in a ground CRS.

    Attributes
    ----------
    camera : Camera
    position : (3,) projection centre (X, Y, Z) in ``crs`` units (heights in metres)
    rotation : (3, 3) photo vector (x, y, -f) -> ground frame
    crs : str
        The ground CRS (a projected CRS; heights as the DEM's after datum correction).
    """

    camera: Camera
    position: NDArray[np.float64]
    rotation: NDArray[np.float64]
    crs: str

    def __post_init__(self) -> None:
        pos = np.array(self.position, dtype=np.float64).reshape(-1)
        if pos.shape != (3,) or not np.isfinite(pos).all():
            raise ShapeError(f"`position` must be 3 finite numbers; got {np.asarray(self.position).tolist()}")
        R = check_rotation(self.rotation, "rotation")
        if self.crs is None:
            raise CRSError("a frame model needs the CRS of its exterior orientation (--eo-crs or 'crs' in the JSON)")
        object.__setattr__(self, "position", pos)
        object.__setattr__(self, "rotation", R)
        object.__setattr__(self, "crs", crs_to_string(self.crs))

    @property
    def width(self) -> int:
        return self.camera.width

    @property
    def height(self) -> int:
        return self.camera.height

    @property
    def nadir(self) -> NDArray[np.float64]:
        return self.position[:2].copy()

    def project(self, ground: NDArray[np.float64]) -> NDArray[np.float64]:
        g = np.asarray(ground, dtype=np.float64).reshape(-1, 3)
        p = (g - self.position) @ self.rotation  # R^T (P - C), row-wise
        f = self.camera.focal_length_mm
        out = np.full((len(g), 2), np.nan)
        ok = np.isfinite(p).all(axis=1) & (p[:, 2] < 0)  # in front of the camera
        if ok.any():
            mm = np.column_stack([-f * p[ok, 0] / p[ok, 2], -f * p[ok, 1] / p[ok, 2]])
            out[ok] = self.camera.pixel_from_photo(mm)
        return out

    def ground_at_height(self, pixels: NDArray[np.float64], h: NDArray[np.float64] | float) -> NDArray[np.float64]:
        px = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
        hh = np.broadcast_to(np.asarray(h, dtype=np.float64), (len(px),))
        rays = self.camera.rays_from_pixel(px) @ self.rotation.T
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (hh - self.position[2]) / rays[:, 2]
        out = self.position + t[:, None] * rays
        out[:, 2] = hh
        out[~(t > 0)] = np.nan
        return out


@dataclass(frozen=True, eq=False)
class RPCModel:
    """An RPC (or refined RPC) image: ground (lon, lat, ellipsoidal h) on WGS 84 -> pixels."""

    rpc: Any  # rectify.geometry.rpc.RPC or RPCRefinement
    width: int
    height: int
    crs: str = "EPSG:4326"

    def project(self, ground: NDArray[np.float64]) -> NDArray[np.float64]:
        g = np.asarray(ground, dtype=np.float64).reshape(-1, 3)
        return self.rpc._project(g)

    def ground_at_height(self, pixels: NDArray[np.float64], h: NDArray[np.float64] | float) -> NDArray[np.float64]:
        return self.rpc.localize(pixels, h, on_failure="nan")

    @property
    def nadir(self) -> NDArray[np.float64]:
        """The image centre at the model's mean height (an RPC has no nadir point)."""
        c = np.array([[(self.width - 1) / 2.0, (self.height - 1) / 2.0]])
        return self.rpc.localize(c, self.rpc.validity_box[2][0] / 2 + self.rpc.validity_box[2][1] / 2)[0, :2]
