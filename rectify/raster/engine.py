"""The one tile-engine base and the one GeoTIFF/COG output tail of the warp, ortho and mosaic steps.

A tile engine (:mod:`rectify.raster.warp`, :mod:`rectify.raster.ortho`, :mod:`rectify.raster.mosaic`)
computes one output window with ``engine.tile(col, row, width, height)``, which returns
``(data, valid, empty)`` (the warp engine) or ``(data, empty)`` (the ortho and mosaic engines):
``data`` (h, w, C) in the output dtype, ``valid`` (h, w) bool or None, ``empty`` True when the window
holds no valid pixel. :class:`TileEngine` holds what every engine shares: per-thread readers opened
on first use and closed together, and the pickling rule that ships an engine to Dask workers
(:class:`ProcessLocal`).

:func:`write_tiled` is the one output tail: inside GDAL's bounded block cache and an atomic output
(:func:`rectify.atomic.atomic_output`: a hidden temporary file renamed at the end, removed on any
error) it writes the engine's windows through a :class:`rectify.raster.io.TiledWriter` on the chosen
scheduler (:func:`rectify.raster.distributed.run_windows`; in raw mode on Dask), records tags, and for
a COG copies the uncompressed body into a Cloud Optimized GeoTIFF
(:func:`rectify.raster.io.translate_to_cog`).

Output options (one set for warp, ortho and mosaic): ``compress`` one of :data:`COMPRESSIONS`, ``cog``
and ``quality``. The lossless ones (``zstd``, ``deflate``, ``lzw``; horizontal predictor for integer
rasters) keep the engine's nodata value. ``jpeg`` (8-bit rasters only, :func:`check_output_format`) is
JPEG-in-TIFF, YCbCr for 3 bands, at ``quality`` (1..100): lossy, so a nodata value cannot survive it;
the invalid pixels go to an internal mask band instead (per-dataset mask, GDAL's
``GDAL_TIFF_INTERNAL_MASK``; with a nodata policy a pixel is invalid when every band equals the nodata
value) and the file records no nodata value. With ``cog`` every option gets internal overviews (COG
layout; the mask band gets its own overviews).
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import rasterio
import rasterio.shutil
from numpy.typing import NDArray
from rasterio.errors import RasterioError

from rectify.atomic import atomic_output, write_failure_reason
from rectify.errors import InvalidInputError, RasterIOError
from rectify.raster.distributed import Scheduler, Window, run_windows
from rectify.raster.georef import Grid
from rectify.raster.io import (
    MaskPolicy,
    TiledWriter,
    WindowReader,
    build_overviews,
    cog_driver_available,
    translate_to_cog,
    verify_geotiff,
)

__all__ = ["COMPRESSIONS", "LOSSLESS", "JPEG_QUALITY", "ProcessLocal", "TileEngine", "check_output_format",
           "worker_count", "tile_windows", "run_engine", "write_tiled"]

#: the ``compress`` values of :func:`write_tiled` (``--compress`` of ortho, warp and mosaic)
COMPRESSIONS = ("zstd", "deflate", "lzw", "jpeg", "none")
#: the lossless ones (the engine's nodata value is kept); ``packbits`` and ``lzma`` are accepted too (warp's)
LOSSLESS = ("zstd", "deflate", "lzw", "none", "packbits", "lzma")
#: default JPEG quality (1..100): GDAL's default, which orthority writes too
JPEG_QUALITY = 75


def worker_count(threads: int | None) -> int:
    """Threads of a tiled engine: ``threads`` when given, else every core."""
    return threads or (os.cpu_count() or 1)


class ProcessLocal:
    """Mixin of the tile engines shipped to Dask workers (warp, ortho, mosaic).

    The attributes named in ``_TRANSIENT`` belong to one process (thread-locals, open readers, locks):
    they are left out when the engine is pickled and made anew, by their factory, when it is unpickled.
    """

    _TRANSIENT: dict[str, Any] = {}

    def __getstate__(self) -> dict[str, Any]:
        state = dict(self.__dict__)
        for k in self._TRANSIENT:
            state.pop(k, None)
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        for k, make in self._TRANSIENT.items():
            setattr(self, k, make())


class TileEngine(ProcessLocal):
    """Base of the tile engines: one reader of the source per thread, all closed by :meth:`close`.

    Subclasses call :meth:`_init_readers` in ``__init__``, name their source ``src`` (a path) for
    :meth:`reader`, and define ``tile(col, row, width, height)`` and ``portable()``.
    """

    src: str
    _TRANSIENT: dict[str, Any] = {"_local": threading.local, "_readers": list, "_lock": threading.Lock}

    def _init_readers(self) -> None:
        self._local = threading.local()
        self._readers: list[Any] = []
        self._lock = threading.Lock()

    def _thread_reader(self, make: Callable[[], Any]) -> Any:
        """This thread's reader, made by ``make`` on first use (anything with ``close()``)."""
        r = getattr(self._local, "reader", None)
        if r is None:
            r = make()
            self._local.reader = r
            with self._lock:
                self._readers.append(r)
        return r

    def reader(self) -> WindowReader:
        """This thread's window reader of ``src``."""
        return self._thread_reader(lambda: WindowReader(self.src))

    def close(self) -> None:
        for r in self._readers:
            r.close()


def tile_windows(width: int, height: int, tile: int) -> list[Window]:
    """The output windows (col, row, width, height) of a ``width`` x ``height`` grid, row by row."""
    return [(c, r, min(tile, width - c), min(tile, height - r))
            for r in range(0, height, tile) for c in range(0, width, tile)]


def run_engine(engine: Any, writer: TiledWriter, windows: Sequence[Window], threads: int,
               progress: Callable[[int, int], None] | None, *, scheduler: Scheduler | str | None = None,
               workdir: str | Path = ".", name: str = "tile") -> int:
    """Compute the windows with ``engine.tile`` on the scheduler and write each; return the empty count.

    A window result is ``(data, valid, empty)`` or ``(data, empty)`` (module docstring). A raw
    ``writer`` (Dask schedulers) gets the tiles compressed on the workers.
    """
    def write(res: tuple[Any, ...], c: int, r: int) -> bool:
        data, *valid, empty = res
        writer.write(data, c, r, *valid)
        return bool(empty)

    return run_windows(engine, write, windows, threads=threads, progress=progress, scheduler=scheduler,
                       workdir=workdir, name=name, raw_writer=writer if writer.raw else None)


def check_output_format(compress: str, dtype: Any, count: int, quality: int = JPEG_QUALITY) -> None:
    """Refuse an output option the raster cannot take, in one line naming the value.

    Raises
    ------
    InvalidInputError
        An unknown compression; ``jpeg`` for a raster other than 8-bit (``uint8``) or of more than 4 bands;
        a JPEG quality outside 1..100.
    """
    c = str(compress).lower()
    if c not in COMPRESSIONS and c not in LOSSLESS:
        raise InvalidInputError(f"unknown compression {compress!r}; expected one of {', '.join(COMPRESSIONS)}")
    if c == "jpeg":
        dt = np.dtype(dtype)
        if dt != np.uint8:
            raise InvalidInputError(f"--compress jpeg needs an 8-bit (uint8) output; this one is {dt.name}: use a "
                                    f"lossless compression (zstd, deflate, lzw)")
        if not 1 <= int(count) <= 4:
            raise InvalidInputError(f"--compress jpeg takes 1 to 4 bands; this output has {count}")
    if isinstance(quality, bool) or not isinstance(quality, (int, np.integer)) or not 1 <= int(quality) <= 100:
        raise InvalidInputError(f"JPEG quality must be an integer in 1..100; got {quality!r}")


class _NodataToMask:
    """An engine whose windows carry a validity mask made from the nodata value (for a lossy output).

    A pixel is invalid where the inner engine's ``valid`` says so or where every band equals ``nodata``
    (NaN matches NaN).
    """

    def __init__(self, inner: Any, nodata: float | None):
        self.inner, self.nodata = inner, nodata

    def tile(self, c0: int, r0: int, w: int, h: int) -> tuple[NDArray, NDArray[np.bool_], bool]:
        data, *valid, empty = self.inner.tile(c0, r0, w, h)
        v = valid[0] if valid and valid[0] is not None else np.ones(data.shape[:2], bool)
        if self.nodata is not None:
            nd = np.isnan(data) if (data.dtype.kind == "f" and np.isnan(self.nodata)) else data == self.nodata
            v = v & ~nd.all(axis=-1)
        return data, v, empty

    def close(self) -> None:
        self.inner.close()

    def portable(self) -> _NodataToMask:
        return _NodataToMask(self.inner.portable(), self.nodata)

    def stats(self) -> Any:
        fn = getattr(self.inner, "stats", None)
        return fn() if fn is not None else None

    def merge_stats(self, stats: Any) -> None:
        fn = getattr(self.inner, "merge_stats", None)
        if fn is not None and stats is not None:
            fn(stats)


def _copy_jpeg(body: Path, dst: Path, *, cog: bool, tile: int, threads: int, quality: int, resampling: str,
               count: int) -> None:
    """Copy an uncompressed, masked body into JPEG-in-TIFF (YCbCr for 3 bands), a COG with ``cog``."""
    try:
        if cog and cog_driver_available():
            rasterio.shutil.copy(str(body), str(dst), driver="COG", COMPRESS="JPEG", QUALITY=str(int(quality)),
                                 BLOCKSIZE=str(tile), NUM_THREADS=str(max(1, threads)), OVERVIEWS="AUTO",
                                 OVERVIEW_RESAMPLING=resampling.upper(), BIGTIFF="IF_SAFER")
        else:
            if cog:  # GDAL without the COG driver: overviews on the body, copied into the tiled file
                build_overviews(body, tile, resampling)
            extra = {"PHOTOMETRIC": "YCBCR"} if count == 3 else {}
            rasterio.shutil.copy(str(body), str(dst), driver="GTiff", TILED="YES", BLOCKXSIZE=str(tile),
                                 BLOCKYSIZE=str(tile), COMPRESS="JPEG", JPEG_QUALITY=str(int(quality)),
                                 NUM_THREADS=str(max(1, threads)), BIGTIFF="IF_SAFER",
                                 COPY_SRC_OVERVIEWS="YES" if cog else "NO", **extra)
        verify_geotiff(dst)
    except RasterIOError:
        raise
    except (RasterioError, OSError) as err:
        raise RasterIOError(f"cannot write {str(dst)!r}: {write_failure_reason(err, dst)}") from err


def write_tiled(engine: Any, dst: str | Path, grid: Grid, windows: Sequence[Window], *, count: int,
                dtype: np.dtype, policy: MaskPolicy, tile: int, compress: str, cog: bool, threads: int,
                scheduler: Scheduler, overwrite: bool, progress: Callable[[int, int], None] | None, name: str,
                cache_bytes: int, colorinterp: Sequence[Any] | None = None, cog_resampling: str | None = None,
                tags: Mapping[str, str] | None = None, band_descriptions: Mapping[int, str] | None = None,
                quality: int = JPEG_QUALITY, workers: int | None = None) -> int:
    """Write ``engine``'s windows into the GeoTIFF ``dst`` (a COG with ``cog``); return the empty windows.

    The engine is closed at the end, on success or error.

    Parameters
    ----------
    engine : TileEngine
    dst : path
        Written atomically; a COG is first written uncompressed beside it (``<tmp>.body.tif``).
    grid : Grid
        Size, geotransform and CRS of the output.
    windows : sequence of (col, row, width, height)
    count, dtype, policy, colorinterp
        Bands, data type, how invalid pixels are stored and the band colour interpretation.
    tile, compress, threads
        GeoTIFF block size, compression (:data:`COMPRESSIONS`; ``jpeg``: module docstring) and compression
        threads.
    cog : bool
        Cloud Optimized GeoTIFF with internal overviews.
    scheduler : Scheduler
        Local threads, or Dask (the tiles are then compressed on the workers, raw mode).
    name : str
        Label of the tasks and threads.
    cache_bytes : int
        GDAL block cache while writing.
    cog_resampling : str, optional
        Overview resampling of the COG (default :func:`rectify.raster.io.translate_to_cog`'s).
    tags, band_descriptions : mapping, optional
        Dataset tags and band descriptions (1-based band -> text) recorded before the COG copy.
    quality : int
        JPEG quality, 1..100 (``compress="jpeg"`` only).
    workers : int, optional
        Tile threads of the local scheduler (default ``threads``; the compression keeps ``threads``).

    Raises
    ------
    InvalidInputError
        An output option the raster cannot take (:func:`check_output_format`), before anything is written.
    """
    compress = str(compress).lower()
    try:
        check_output_format(compress, dtype, count, quality)
    except InvalidInputError:
        engine.close()
        raise
    jpeg = compress == "jpeg"
    if jpeg and policy.kind == "nodata":  # lossy: the invalid pixels go to an internal mask, not a nodata value
        engine, policy = _NodataToMask(engine, policy.nodata), MaskPolicy("mask")
    elif jpeg and policy.kind == "alpha":
        engine.close()
        raise InvalidInputError("--compress jpeg cannot keep an alpha band exactly; use a lossless compression")
    staged = cog or jpeg
    try:
        with rasterio.Env(GDAL_CACHEMAX=cache_bytes), atomic_output(dst, overwrite=overwrite) as tmp:
            body = tmp.with_name(tmp.name + ".body.tif") if staged else tmp
            try:
                # on Dask the workers compress the tiles and this process copies their bytes (raw mode)
                with TiledWriter(body, grid.width, grid.height, count, dtype.name, grid.transform, grid.crs, policy,
                                 tile=tile, compress="none" if staged else compress, threads=threads,
                                 colorinterp=colorinterp, raw=not scheduler.is_local_threads) as writer:
                    n_empty = run_engine(engine, writer, windows, workers or threads, progress, scheduler=scheduler,
                                         workdir=tmp.parent, name=name)
                if tags or band_descriptions:
                    with rasterio.open(body, "r+") as ds:
                        ds.update_tags(**(tags or {}))
                        for band, text in (band_descriptions or {}).items():
                            ds.set_band_description(band, text)
                if jpeg:
                    _copy_jpeg(body, tmp, cog=cog, tile=tile, threads=threads, quality=quality,
                               resampling=cog_resampling or "average", count=count)
                elif cog:
                    extra = {} if cog_resampling is None else {"resampling": cog_resampling}
                    translate_to_cog(body, tmp, compress=compress, threads=threads, tile=tile, **extra)
            finally:
                if staged and body.exists():
                    body.unlink()
    finally:
        engine.close()
    return n_empty

