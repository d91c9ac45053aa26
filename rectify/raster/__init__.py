"""Rasters: the only code that imports rasterio.

Windowed reading and writing (``io``), pixel <-> world grids (``georef``), DEMs and heights (``dem``), the
tile engines and their schedulers (``tiles``, ``engine``, ``distributed``, ``tiffblocks``), and the raster
steps: resampling and georectification (``warp``, ``georectify``), orthophotos (``ortho``), mosaics
(``mosaic``). See ``docs/architecture.md``.
"""
