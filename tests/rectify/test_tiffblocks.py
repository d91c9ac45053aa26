"""rectify.raster.tiffblocks: tiles compressed in memory are GDAL's own tiles; appended and indexed, they make a GeoTIFF
with the pixels and masks that GDAL's writer gives (classic TIFF, BigTIFF, either byte order)."""

from __future__ import annotations

import struct

import numpy as np
import pytest
import rasterio
from affine import Affine
from rasterio.windows import Window

from rectify.errors import InvalidInputError, RasterIOError, ShapeError
from rectify.raster.io import MaskPolicy, TiledWriter, _gtiff_profile, verify_geotiff
from rectify.raster.tiffblocks import RAW_COMPRESSIONS, TileEncoder, append_tiles, read_tiff_layout, tile_index

TRANSFORM = Affine(2.0, 0.0, 500000.0, 0.0, -2.0, 4400000.0)
CRS = "EPSG:32618"


def _image(h, w, c, dtype, seed=3):
    """A smooth image with noise (compresses, but not to nothing)."""
    rng = np.random.default_rng(seed)
    rr, cc = np.mgrid[0:h, 0:w]
    base = np.stack([(cc * 0.7 + rr * 0.2 + 40 * k) % 200 for k in range(c)], axis=-1)
    return (base + rng.normal(0, 4, base.shape)).clip(0, 250).astype(dtype)


def _windows(w, h, tile):
    return [(c, r, min(tile, w - c), min(tile, h - r)) for r in range(0, h, tile) for c in range(0, w, tile)]


def _profile(w, h, c, dtype, nodata, *, tile, compress, **extra):
    prof = _gtiff_profile(w, h, c, dtype, TRANSFORM, CRS, nodata, tile=tile, compress=compress, threads=1)
    prof.update(extra)
    return prof


def _gdal_file(path, img, valid, prof, tile):
    """The file GDAL's own writer makes (tile by tile, as TiledWriter's default mode)."""
    h, w = img.shape[:2]
    with rasterio.Env(GDAL_TIFF_INTERNAL_MASK=True), rasterio.open(path, "w", **prof) as ds:
        for c, r, ww, hh in _windows(w, h, tile):
            win = Window(c, r, ww, hh)
            ds.write(np.moveaxis(img[r:r + hh, c:c + ww], -1, 0), window=win)
            if valid is not None:
                ds.write_mask(valid[r:r + hh, c:c + ww].astype(np.uint8) * 255, window=win)


def _tiles_of(path):
    """{(ifd, index): bytes} of every tile in a GDAL-written file."""
    lay = read_tiff_layout(path)
    data = path.read_bytes()
    out = {}
    bo = lay.byte_order

    def values(arr):
        return np.frombuffer(data[arr.pos:arr.pos + arr.count * arr.item_size], dtype=f"{bo}u{arr.item_size}")

    for k, d in enumerate(lay.ifds):
        for i, (o, n) in enumerate(zip(values(d.offsets), values(d.byte_counts), strict=True)):
            out[(k, i)] = data[int(o):int(o + n)]
    return out


def _read(path):
    with rasterio.open(path) as ds:
        return ds.read(), ds.dataset_mask(), ds.profile


def _assert_same_raster(a, b):
    da, ma, pa = _read(a)
    db, mb, pb = _read(b)
    np.testing.assert_array_equal(da, db)
    np.testing.assert_array_equal(ma, mb)
    for k in ("width", "height", "count", "dtype", "crs", "transform", "blockxsize", "blockysize", "compress",
              "interleave", "tiled"):
        assert pa.get(k) == pb.get(k), k
    na, nb = pa.get("nodata"), pb.get("nodata")
    assert na == nb or (np.isnan(na) and np.isnan(nb))


# ----------------------------------------------------------------- the encoder makes GDAL's tiles
CASES = [  # (dtype, bands, compress, nodata, mask)
    ("uint8", 3, "zstd", None, True),
    ("uint8", 3, "deflate", 0.0, False),
    ("uint16", 2, "lzw", None, True),
    ("float32", 1, "zstd", float("nan"), False),
    ("int16", 4, "none", -9999.0, False),
    ("uint8", 1, "packbits", None, True),
]


@pytest.mark.parametrize(("dtype", "bands", "compress", "nodata", "mask"), CASES)
def test_encoded_tiles_are_gdals_tiles(tmp_path, dtype, bands, compress, nodata, mask):
    """Interior and edge windows (700 x 530 on 256 px tiles), image and mask tiles: the same bytes."""
    w, h, tile = 700, 530, 256
    img = _image(h, w, bands, dtype)
    valid = (np.random.default_rng(5).random((h, w)) > 0.2) if mask else None
    prof = _profile(w, h, bands, dtype, nodata, tile=tile, compress=compress)
    _gdal_file(tmp_path / "gdal.tif", img, valid, prof, tile)
    ref = _tiles_of(tmp_path / "gdal.tif")
    enc = TileEncoder.from_profile(prof, mask=mask)
    for c, r, ww, hh in _windows(w, h, tile):
        i = tile_index(c, r, tile, w)
        e = enc.encode(img[r:r + hh, c:c + ww], None if valid is None else valid[r:r + hh, c:c + ww])
        assert e.data.dtype == np.uint8 and bytes(e.data) == ref[(0, i)], (c, r)
        if mask:
            assert e.mask is not None and bytes(e.mask) == ref[(1, i)], (c, r)
        else:
            assert e.mask is None


def test_encode_window_takes_both_result_forms():
    prof = _profile(64, 64, 3, "uint8", None, tile=64, compress="zstd")
    enc = TileEncoder.from_profile(prof, mask=True)
    img = _image(64, 64, 3, "uint8")
    valid = np.ones((64, 64), bool)
    valid[:10] = False
    data, mask, empty = enc.encode_window((img, valid, False))
    assert (bytes(data), bytes(mask), empty) == (bytes(enc.encode(img, valid).data),
                                                 bytes(enc.encode(img, valid).mask), False)
    data2, mask2, empty2 = enc.encode_window((img, True))  # (data, empty): every pixel valid
    assert empty2 is True and bytes(mask2) == bytes(enc.encode(img, None).mask) != bytes(mask)
    with pytest.raises(InvalidInputError, match="a window result is"):
        enc.encode_window((img,))


def test_encoding_warns_nothing():
    """The one-tile files in memory have no geotransform: rasterio's NotGeoreferencedWarning must not reach
    the console of every Dask worker, once per tile."""
    import warnings

    prof = _profile(64, 64, 3, "uint8", None, tile=64, compress="zstd")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        enc = TileEncoder.from_profile(prof, mask=True)
        tile = enc.encode(_image(64, 64, 3, "uint8"), None)
        image, mask = enc.layout()
    assert [str(w.message) for w in caught] == []
    assert tile.data.size > 0 and tile.mask is not None and image and mask


def test_encoder_pickles_and_refuses_bad_input():
    import pickle

    prof = _profile(100, 100, 3, "uint8", None, tile=32, compress="zstd")
    enc = pickle.loads(pickle.dumps(TileEncoder.from_profile(prof, mask=False)))
    assert (enc.tile, enc.count, enc.dtype, enc.mask) == (32, 3, np.dtype("uint8"), False)
    with pytest.raises(ShapeError, match=r"`data` must be \(h, w, 3\) with h, w in 1..32; got \(33, 32, 3\)"):
        enc.encode(np.zeros((33, 32, 3), np.uint8))
    with pytest.raises(ShapeError, match="got \\(8, 8, 2\\)"):
        enc.encode(np.zeros((8, 8, 2), np.uint8))
    with pytest.raises(InvalidInputError, match="compression 'jpeg' cannot be encoded tile by tile"):
        TileEncoder.from_profile(dict(prof, compress="jpeg"), mask=False)
    assert "jpeg" not in RAW_COMPRESSIONS and "zstd" in RAW_COMPRESSIONS


def test_tile_index_needs_the_tile_grid():
    assert tile_index(0, 0, 256, 700) == 0 and tile_index(512, 256, 256, 700) == 5
    with pytest.raises(InvalidInputError, match=r"window offset \(100, 0\) is not on the 256 px tile grid"):
        tile_index(100, 0, 256, 700)


# ----------------------------------------------------------------- the reader
@pytest.mark.parametrize("options", [{}, {"BIGTIFF": "YES"}, {"ENDIANNESS": "BIG"},
                                     {"BIGTIFF": "YES", "ENDIANNESS": "BIG"}])
@pytest.mark.parametrize("width", [200, 700])  # 200 x 200: one tile (arrays inline in the IFD entries)
def test_reader_finds_the_tile_arrays_gdal_reports(tmp_path, options, width):
    h, tile = min(width, 300), 256
    img = _image(h, width, 3, "uint8")
    valid = np.random.default_rng(2).random((h, width)) > 0.3
    prof = _profile(width, h, 3, "uint8", None, tile=tile, compress="deflate", **options)
    _gdal_file(tmp_path / "a.tif", img, valid, prof, tile)
    lay = read_tiff_layout(tmp_path / "a.tif")
    assert lay.byte_order == (">" if "ENDIANNESS" in options else "<")
    assert lay.bigtiff == ("BIGTIFF" in options)
    assert lay.mask is not None and not lay.image.is_mask and lay.image.offsets.count == lay.mask.offsets.count
    data = (tmp_path / "a.tif").read_bytes()
    bo = lay.byte_order
    with rasterio.open(tmp_path / "a.tif") as ds:
        nx = -(-width // tile)
        def value(arr, i):
            return int(np.frombuffer(data[arr.pos + i * arr.item_size:arr.pos + (i + 1) * arr.item_size],
                                     f"{bo}u{arr.item_size}")[0])

        for i in range(lay.image.offsets.count):
            off, cnt = value(lay.image.offsets, i), value(lay.image.byte_counts, i)
            assert off == int(ds.get_tag_item(f"BLOCK_OFFSET_{i % nx}_{i // nx}", "TIFF", bidx=1))
            assert cnt == int(ds.get_tag_item(f"BLOCK_SIZE_{i % nx}_{i // nx}", "TIFF", bidx=1))
    if width == 200 and not lay.bigtiff:  # one LONG fits in a classic entry
        assert lay.image.offsets.inline and lay.image.byte_counts.inline
    # the same structure from bytes and from an open file
    assert read_tiff_layout(data) == lay
    with open(tmp_path / "a.tif", "rb") as fh:
        assert read_tiff_layout(fh) == lay


def test_reader_refuses_what_is_not_a_tiled_tiff(tmp_path):
    with pytest.raises(RasterIOError, match=r"'<bytes>' is not a TIFF file \(header b'GIF8'\)"):
        read_tiff_layout(b"GIF89a" + bytes(20))
    with pytest.raises(RasterIOError, match="is not a TIFF file"):
        read_tiff_layout(b"II")
    with pytest.raises(RasterIOError, match="ends at byte"):
        read_tiff_layout(b"II*\x00" + struct.pack("<I", 4000))
    with rasterio.open(tmp_path / "strips.tif", "w", driver="GTiff", width=20, height=20, count=1, dtype="uint8") as ds:
        ds.write(np.zeros((1, 20, 20), np.uint8))
    with pytest.raises(RasterIOError, match="is not a tiled TIFF"):
        read_tiff_layout(tmp_path / "strips.tif")
    with pytest.raises(RasterIOError, match="cannot read"):
        read_tiff_layout(tmp_path / "missing.tif")


# ----------------------------------------------------------------- appending tiles
def _sparse_file(path, prof, mask):
    with rasterio.Env(GDAL_TIFF_INTERNAL_MASK=True), rasterio.open(path, "w", SPARSE_OK="TRUE", **prof) as ds:
        if mask:
            ds.write_mask(np.zeros((1, 1), np.uint8), window=Window(0, 0, 1, 1))


@pytest.mark.parametrize("options", [{}, {"BIGTIFF": "YES"}, {"ENDIANNESS": "BIG"},
                                     {"BIGTIFF": "YES", "ENDIANNESS": "BIG"}])
@pytest.mark.parametrize("size", [(700, 530), (200, 150)])
def test_appended_tiles_make_gdals_raster(tmp_path, options, size):
    w, h = size
    tile = 256
    img = _image(h, w, 3, "uint8")
    valid = np.random.default_rng(7).random((h, w)) > 0.25
    prof = _profile(w, h, 3, "uint8", None, tile=tile, compress="zstd", **options)
    _gdal_file(tmp_path / "gdal.tif", img, valid, prof, tile)
    _sparse_file(tmp_path / "raw.tif", prof, True)
    lay = read_tiff_layout(tmp_path / "raw.tif")
    mask_ifd = lay.ifds.index(lay.mask)
    enc = TileEncoder.from_profile(prof, mask=True)
    tiles = []
    for c, r, ww, hh in reversed(_windows(w, h, tile)):  # any order
        e = enc.encode(img[r:r + hh, c:c + ww], valid[r:r + hh, c:c + ww])
        i = tile_index(c, r, tile, w)
        tiles += [(0, i, e.data), (mask_ifd, i, bytes(e.mask))]
    append_tiles(tmp_path / "raw.tif", tiles)
    verify_geotiff(tmp_path / "raw.tif")
    _assert_same_raster(tmp_path / "gdal.tif", tmp_path / "raw.tif")
    after = read_tiff_layout(tmp_path / "raw.tif")
    assert (after.byte_order, after.bigtiff) == (lay.byte_order, lay.bigtiff)


def test_an_array_too_narrow_for_the_offsets_is_rewritten_wider(tmp_path):
    """A TileOffsets array of SHORTs (legal TIFF; here made by editing GDAL's LONG entry) cannot hold offsets past
    64 KiB: it is written anew, as LONGs, at the end of the file and its entry points there."""
    w, h, tile = 512, 512, 128
    img = _image(h, w, 3, "uint8")
    prof = _profile(w, h, 3, "uint8", 0.0, tile=tile, compress="none")
    _gdal_file(tmp_path / "gdal.tif", img, None, prof, tile)
    _sparse_file(tmp_path / "raw.tif", prof, False)
    lay = read_tiff_layout(tmp_path / "raw.tif")
    assert not lay.bigtiff and lay.image.offsets.field_type == 4
    with open(tmp_path / "raw.tif", "r+b") as fh:  # LONG -> SHORT (the zeros stay zeros)
        fh.seek(lay.image.offsets.entry_pos + 2)
        fh.write(struct.pack("<H", 3))
    assert read_tiff_layout(tmp_path / "raw.tif").image.offsets.field_type == 3
    enc = TileEncoder.from_profile(prof, mask=False)
    append_tiles(tmp_path / "raw.tif", [(0, tile_index(c, r, tile, w), enc.encode(img[r:r + hh, c:c + ww]).data)
                                        for c, r, ww, hh in _windows(w, h, tile)])
    after = read_tiff_layout(tmp_path / "raw.tif")
    assert after.image.offsets.field_type == 4 and after.image.offsets.pos > lay.image.offsets.pos
    verify_geotiff(tmp_path / "raw.tif")
    _assert_same_raster(tmp_path / "gdal.tif", tmp_path / "raw.tif")


def test_append_refuses_a_tile_index_outside_the_grid(tmp_path):
    prof = _profile(100, 100, 1, "uint8", 0.0, tile=64, compress="zstd")
    _sparse_file(tmp_path / "raw.tif", prof, False)
    with pytest.raises(InvalidInputError, match=r"tile index 4 is outside 0..3 of IFD 0"):
        append_tiles(tmp_path / "raw.tif", [(0, 4, b"xx")])


# ----------------------------------------------------------------- TiledWriter in raw mode
@pytest.mark.parametrize(("dtype", "bands", "policy", "compress"), [
    ("uint8", 3, MaskPolicy("mask"), "zstd"),
    ("uint8", 3, MaskPolicy("nodata", 0.0), "deflate"),
    ("uint8", 4, MaskPolicy("alpha", None, 3), "zstd"),
    ("float32", 2, MaskPolicy("nodata", float("nan")), "zstd"),
    ("uint16", 1, MaskPolicy("none"), "none"),
])
def test_raw_writer_writes_what_the_default_writer_writes(tmp_path, dtype, bands, policy, compress):
    w, h, tile = 300, 200, 64
    img = _image(h, w, bands, dtype)
    valid = np.random.default_rng(11).random((h, w)) > 0.3
    if policy.kind == "alpha":
        img[..., 3] = np.where(valid, 255, 0)
    kw = dict(tile=tile, compress=compress, colorinterp=None)
    files = {}
    for raw in (False, True):
        p = tmp_path / f"{'raw' if raw else 'gdal'}.tif"
        with TiledWriter(p, w, h, bands, dtype, TRANSFORM, CRS, policy, raw=raw, **kw) as tw:
            assert tw.raw is raw
            for c, r, ww, hh in _windows(w, h, tile):
                data, v = img[r:r + hh, c:c + ww], valid[r:r + hh, c:c + ww]
                if raw and (c // tile) % 2:  # encoded elsewhere, or pixels encoded by the writer itself
                    tw.write_encoded(c, r, tw.encoder.encode_window((data, v, False)))
                else:
                    tw.write(data, c, r, v)
        files[raw] = p
    _assert_same_raster(files[False], files[True])
    # nothing but the header, the IFDs and the tiles: no garbage from creating the file
    lay = read_tiff_layout(files[True])
    tiles = sum(len(b) for b in _tiles_of(files[True]).values())
    assert files[True].stat().st_size - tiles < 4096 + 16 * sum(d.offsets.count for d in lay.ifds)


def test_raw_writer_mode_errors(tmp_path):
    with TiledWriter(tmp_path / "a.tif", 100, 100, 1, "uint8", TRANSFORM, CRS, MaskPolicy("none"), tile=64) as tw:
        with pytest.raises(InvalidInputError, match="is not written in raw mode: it has no tile encoder"):
            _ = tw.encoder
        with pytest.raises(InvalidInputError, match="is not written in raw mode: write pixels with write"):
            tw.write_encoded(0, 0, (b"", None))
        tw.write(np.zeros((100, 100, 1), np.uint8), 0, 0)
    with TiledWriter(tmp_path / "b.tif", 100, 100, 1, "uint8", TRANSFORM, CRS, MaskPolicy("mask"), tile=64,
                     compress="zstd", raw=True) as tw:
        with pytest.raises(InvalidInputError, match="needs its mask tile"):
            tw.write_encoded(0, 0, (tw.encoder.encode(np.zeros((64, 64, 1), np.uint8)).data, None))
        with pytest.raises(InvalidInputError, match="not on the 64 px tile grid"):
            tw.write(np.zeros((10, 10, 1), np.uint8), 10, 0)
        for c, r, ww, hh in _windows(100, 100, 64):
            tw.write(np.full((hh, ww, 1), 7, np.uint8), c, r)
    with rasterio.open(tmp_path / "b.tif") as ds:
        assert (ds.read() == 7).all() and (ds.dataset_mask() == 255).all()
    with pytest.raises(InvalidInputError, match="compression 'jpeg' cannot be encoded tile by tile"):
        TiledWriter(tmp_path / "c.tif", 100, 100, 3, "uint8", TRANSFORM, CRS, MaskPolicy("none"), tile=64,
                    compress="jpeg", raw=True)


def test_raw_writer_on_a_full_disk_says_so(small_disk):
    """Noise does not compress: 600 x 600 x 3 bytes cannot fit a 200 KiB file system."""
    img = (np.random.default_rng(0).random((600, 600, 3)) * 255).astype(np.uint8)
    with pytest.raises(RasterIOError, match="no space left on device"):
        with TiledWriter(small_disk / "out.tif", 600, 600, 3, "uint8", TRANSFORM, CRS, MaskPolicy("mask"), tile=128,
                         compress="zstd", raw=True) as tw:
            for c, r, ww, hh in _windows(600, 600, 128):
                tw.write_encoded(c, r, tw.encoder.encode(img[r:r + hh, c:c + ww]))
