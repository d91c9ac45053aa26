"""RPC models as GDAL sees them: a VRT that gives an image a new RPC without copying its pixels, and GDAL's own
RPC transformer on the model a file carries (the check that GDAL reads what :mod:`rectify.formats.rpc` writes).

Pixel frames: GDAL's RPC transformer counts pixel/line from the top-left pixel *corner*; the project's
(col, row) from the top-left pixel *centre*: ``col = gdal_pixel - 0.5`` (see :mod:`rectify.geometry.rpc`).
"""

from __future__ import annotations

import warnings
from pathlib import Path
from xml.sax.saxutils import escape, quoteattr

import numpy as np
import rasterio
from numpy.typing import ArrayLike, NDArray
from rasterio.errors import RasterioIOError, TransformWarning
from rasterio.transform import RPCTransformer, TransformDirection

from rectify.errors import InvalidInputError, RasterIOError
from rectify.geometry.rpc import GDAL_PIXEL_OFFSET
from rectify.raster.io import open_raster

__all__ = ["gdal_rpc_project", "rpc_vrt_text"]

#: numpy dtype name -> GDAL data type name of a VRT band
_GDAL_TYPES = {"uint8": "Byte", "int8": "Int8", "uint16": "UInt16", "int16": "Int16", "uint32": "UInt32",
               "int32": "Int32", "uint64": "UInt64", "int64": "Int64", "float32": "Float32", "float64": "Float64",
               "complex64": "CFloat32", "complex128": "CFloat64"}


def _gdal_typename(dtype: str) -> str:
    try:
        return _GDAL_TYPES[str(dtype)]
    except KeyError:
        raise InvalidInputError(f"a VRT cannot reference bands of data type {dtype!r}") from None


def rpc_vrt_text(image: str | Path, rpc_metadata: dict[str, str]) -> str:
    """A GDAL VRT of every band of ``image`` (referenced by its absolute path, pixels not copied) whose
    ``RPC`` metadata domain is ``rpc_metadata`` (GDAL's keys: ``LINE_OFF``, ..., ``SAMP_DEN_COEFF``, the
    form of :meth:`rectify.geometry.rpc.RPC.to_rasterio`).

    Raises
    ------
    RasterIOError
        The image cannot be read.
    """
    src = Path(image).resolve()
    with open_raster(src) as ds:
        width, height, count = ds.width, ds.height, ds.count
        dtypes = list(ds.dtypes)
        nodata = ds.nodata
        blocks = [ds.block_shapes[i] for i in range(count)]
        interp = [c.name for c in ds.colorinterp]
    items = "".join(f"    <MDI key={quoteattr(k)}>{escape(v)}</MDI>\n" for k, v in sorted(rpc_metadata.items()))
    bands = []
    for b in range(1, count + 1):
        by, bx = blocks[b - 1]
        nd = "" if nodata is None else f"    <NoDataValue>{nodata!r}</NoDataValue>\n"
        ci = interp[b - 1].capitalize() if interp[b - 1] not in ("undefined",) else "Undefined"
        bands.append(
            f'  <VRTRasterBand dataType="{_gdal_typename(dtypes[b - 1])}" band="{b}">\n{nd}'
            f"    <ColorInterp>{ci}</ColorInterp>\n"
            f"    <SimpleSource>\n"
            f'      <SourceFilename relativeToVRT="0">{escape(str(src))}</SourceFilename>\n'
            f"      <SourceBand>{b}</SourceBand>\n"
            f'      <SourceProperties RasterXSize="{width}" RasterYSize="{height}" '
            f'DataType="{_gdal_typename(dtypes[b - 1])}" BlockXSize="{bx}" BlockYSize="{by}" />\n'
            f'      <SrcRect xOff="0" yOff="0" xSize="{width}" ySize="{height}" />\n'
            f'      <DstRect xOff="0" yOff="0" xSize="{width}" ySize="{height}" />\n'
            f"    </SimpleSource>\n  </VRTRasterBand>\n")
    return (f'<VRTDataset rasterXSize="{width}" rasterYSize="{height}">\n'
            f'  <Metadata domain="RPC">\n{items}  </Metadata>\n' + "".join(bands) + "</VRTDataset>\n")


def gdal_rpc_project(path: str | Path, ground: ArrayLike) -> NDArray[np.float64]:
    """Project ground (N, 3) (lon, lat, h WGS 84 degrees, ellipsoidal metres) with GDAL's RPC transformer on the
    RPC that GDAL reads from ``path`` (a raster's tags or sidecar, or a VRT's RPC domain); returns (N, 2) in
    the project's (col, row) frame (NaN where GDAL fails).

    Raises
    ------
    RasterIOError
        Unreadable file.
    InvalidInputError
        GDAL finds no RPC in it.
    """
    g = np.asarray(ground, dtype=np.float64).reshape(-1, 3)
    try:
        with rasterio.open(path) as ds:
            rpcs = ds.rpcs
    except RasterioIOError as err:
        raise RasterIOError(f"cannot read {str(path)!r}: {err}") from None
    if rpcs is None:
        raise InvalidInputError(f"GDAL finds no RPC in {str(path)!r}")
    with RPCTransformer(rpcs, RPC_PIXEL_ERROR_THRESHOLD=1e-9, RPC_MAX_ITERATIONS=200) as t, \
            warnings.catch_warnings():
        warnings.simplefilter("ignore", TransformWarning)
        c, r = t._transform(g[:, 0], g[:, 1], g[:, 2], transform_direction=TransformDirection.reverse)
    return np.column_stack([c, r]) - GDAL_PIXEL_OFFSET
