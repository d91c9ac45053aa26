"""Parsers at the field's edge (issue 32): bounded JSON, CSV tables read as streams with a stated row limit,
GeoPackage names passed safely to SQLite, and every third-party exception of a parser mapped to the project's
errors. One test per case of the issue; the CLI side is in ``tests/cli/test_field_parsers.py``."""

from __future__ import annotations

import copy
import csv
import io
import json
import os
import sqlite3
import struct
import subprocess
import sys
import tempfile
import textwrap
import zlib
from pathlib import Path

import numpy as np
import pytest
from affine import Affine
from hypothesis import given, settings
from hypothesis import strategies as st

from rectify.atomic import JSON_MAX_BYTES, JSON_MAX_DEPTH, json_depth, parse_json, read_json
from rectify.errors import CRSError, InvalidInputError, RasterIOError, RectifyError
from rectify.formats import common
from rectify.formats.camera import read_camera
from rectify.formats.common import MAX_POINT_ROWS, TableReader, no_duplicates
from rectify.formats.exterior import read_exterior as read_eo_geometry
from rectify.formats.gcps import gcps_geojson_text, gcps_text, read_gcps, write_gcps, write_gcps_gpkg
from rectify.formats.tables import read_control, read_matches
from rectify.formats.transform import read_transform
from rectify.geometry.camera import Camera
from rectify.geometry.points import GcpTable
from rectify.raster.io import write_raster
from rectify.raster.mosaic import mosaic
from stereo.block.types import Pose
from stereo.features.targets import Chessboard, find_chessboards
from stereo.formats.block import block_orientation_text, read_block_control, read_block_orientation
from stereo.formats.calibration import read_observations_csv
from stereo.formats.opensfm import read_opensfm
from stereo.formats.orientation import read_exterior, read_orientation, read_relative
from stereo.formats.poses import read_pose_csv

ROOT = Path(__file__).resolve().parents[2]
RELEASE = ROOT / "tests" / "data" / "release_0_1_0"


def _one_line(err: pytest.ExceptionInfo, *words: str) -> str:
    msg = str(err.value)
    assert "\n" not in msg, msg
    for w in words:
        assert w in msg, msg
    return msg


def _entries(d: Path) -> list[str]:
    return sorted(p.name for p in d.iterdir())


# =========================================================================== JSON: nesting and size
def _reference_depth(data: bytes) -> int:
    """Nesting depth by a byte-by-byte scan: a backslash escapes the next byte, quotes open and close strings."""
    depth = deepest = 0
    in_string = escaped = False
    for ch in data:
        if escaped:
            escaped = False
            if ch in (34, 92):
                continue
        elif ch == 92:
            escaped = True
            continue
        if in_string:
            in_string = ch != 34
        elif ch == 34:
            in_string = True
        elif ch in (91, 123):
            depth += 1
            deepest = max(deepest, depth)
        elif ch in (93, 125):
            depth -= 1
    return deepest


@settings(max_examples=400, deadline=None)
@given(st.binary(min_size=0, max_size=80).map(lambda b: bytes(b'[]{}"\\a,'[x % 8] for x in b)),
       st.sampled_from([1, 2, 3, 7, 4096]))
def test_json_depth_matches_a_byte_by_byte_scan(data, chunk):
    """Quotes escaped by odd runs of backslashes, runs cut by the chunk borders: the vectorised scan agrees."""
    assert json_depth(data, chunk=chunk) == _reference_depth(data)


_JSON = st.recursive(st.none() | st.booleans() | st.integers() | st.floats(allow_nan=False) |
                     st.text(alphabet='ab"\\[]{}\n é', max_size=6),
                     lambda inner: st.lists(inner, max_size=3) | st.dictionaries(
                         st.text(alphabet='k"\\[]{', max_size=3), inner, max_size=3), max_leaves=20)


def _true_depth(v) -> int:
    if isinstance(v, list):
        return 1 + max((_true_depth(x) for x in v), default=0)
    if isinstance(v, dict):
        return 1 + max((_true_depth(x) for x in v.values()), default=0)
    return 0


@settings(max_examples=300, deadline=None)
@given(_JSON, st.sampled_from([1, 5, 4096]))
def test_json_depth_of_documents(doc, chunk):
    """The depth of any document, strings full of brackets, quotes and backslashes included."""
    assert json_depth(json.dumps(doc).encode(), chunk=chunk) == _true_depth(doc)
    assert json_depth(json.dumps(doc, ensure_ascii=False).encode(), chunk=chunk) == _true_depth(doc)


def _deep(kind: str, n: int = 10_000) -> str:
    return "[" * n + "]" * n if kind == "array" else '{"a": ' * n + "1" + "}" * n


def _block_json() -> str:
    cam = Camera.from_dict(json.loads((RELEASE / "camera.json").read_text()))
    return block_orientation_text({"c": cam}, [Pose("a.tif", "c", np.array([1.0, 2, 3]), np.eye(3)),
                                              Pose("b.tif", "c", np.array([2.0, 2, 3]), np.eye(3))], crs="EPSG:32633")


def _gcp_table(crs: str | None = "EPSG:32633", z: bool = False) -> GcpTable:
    pix = np.array([[1.0, 2], [300, 4], [5, 270], [280, 290], [150, 140]])
    tgt = np.column_stack([500000 + 2 * pix[:, 0] + 0.1 * pix[:, 1], 4400000 - 2 * pix[:, 1] + 0.05 * pix[:, 0]])
    return GcpTable(tuple(f"g{i}" for i in range(5)), pix, tgt, np.arange(5.0) if z else None,
                    np.zeros(5, dtype=bool), crs)


#: every JSON reader of the project: (reader, file name, what the error names the file)
JSON_READERS = {
    "camera": (read_camera, "cam.json"),
    "relative orientation": (read_relative, "ro.json"),
    "exterior orientation (stereo)": (read_exterior, "eo.json"),
    "exterior orientation (rectify)": (read_eo_geometry, "eo.json"),
    "model orientation": (read_orientation, "orientation.json"),
    "block orientation": (read_block_orientation, "orientation.json"),
    "transform": (read_transform, "transform.json"),
    "GeoJSON GCPs": (read_gcps, "gcps.geojson"),
    "OpenSfM reconstruction": (read_opensfm, "reconstruction.json"),
}


@pytest.mark.parametrize("kind", ["array", "object"])
@pytest.mark.parametrize("reader", list(JSON_READERS))
def test_json_nested_10000_deep_is_one_line(tmp_path, reader, kind):
    """Issue 32: a JSON file nested 10 000 deep raised RecursionError; now one line names the file and the limit."""
    fn, name = JSON_READERS[reader]
    p = tmp_path / name
    p.write_text(_deep(kind))
    with pytest.raises(InvalidInputError) as err:
        fn(p)
    _one_line(err, name, f"more than {JSON_MAX_DEPTH} levels deep")


def test_json_nesting_up_to_the_limit_is_read(tmp_path):
    p = tmp_path / "ok.json"
    p.write_text(json.dumps({"extra": json.loads(_deep("array", JSON_MAX_DEPTH - 1))}))
    assert read_json(p)["extra"] == json.loads(_deep("array", JSON_MAX_DEPTH - 1))
    p.write_text(json.dumps({"extra": json.loads(_deep("array", JSON_MAX_DEPTH))}))
    with pytest.raises(InvalidInputError, match=f"more than {JSON_MAX_DEPTH} levels"):
        read_json(p)


def test_json_larger_than_the_limit_is_refused_unread(tmp_path):
    """A (sparse) camera file past the size limit is refused from its size, before a byte is parsed."""
    p = tmp_path / "cam.json"
    with open(p, "wb") as fh:
        fh.truncate(JSON_MAX_BYTES + 1)
    with pytest.raises(InvalidInputError) as err:
        read_camera(p)
    _one_line(err, "cam.json", str(JSON_MAX_BYTES + 1), str(JSON_MAX_BYTES))
    p.write_text('{"a": 1}' + " " * 100)
    with pytest.raises(InvalidInputError, match="more than the 50 bytes"):
        read_json(p, max_bytes=50)


@pytest.mark.parametrize("text, words", [
    (b'{"a": ' + b"7" * 5000 + b"}", ["not valid JSON", "4300 digits"]),
    (b'{"a": "\xe9t\xe9"}', ["not UTF-8 text", "byte 7"]),
    (b'{"a": [1, 2}', ["not valid JSON"]),
])
def test_json_third_party_errors_are_one_line(tmp_path, text, words):
    p = tmp_path / "x.json"
    p.write_bytes(text)
    with pytest.raises(InvalidInputError) as err:
        read_json(p, "camera file")
    _one_line(err, "camera file", "x.json", *words)


def test_json_byte_order_mark_is_read():
    assert parse_json(b'\xef\xbb\xbf{"a": [1]}', "f") == {"a": [1]}
    assert parse_json('{"a": "]]"}', "f") == {"a": "]]"}


# =========================================================================== JSON: third-party exceptions
def _samples(tmp_path: Path) -> dict[str, Path]:
    (tmp_path / "block.json").write_text(_block_json())
    (tmp_path / "g.geojson").write_text(gcps_geojson_text(_gcp_table(z=True)))
    return {"camera": RELEASE / "camera.json", "relative orientation": RELEASE / "ro.json",
            "exterior orientation (stereo)": RELEASE / "eo.json",
            "exterior orientation (rectify)": RELEASE / "eo.json",
            "model orientation": RELEASE / "points.orientation.json", "block orientation": tmp_path / "block.json",
            "transform": RELEASE / "transform_poly2.json", "GeoJSON GCPs": tmp_path / "g.geojson"}


def _paths(o, pre=()):
    yield pre
    if isinstance(o, dict):
        for k, v in o.items():
            yield from _paths(v, (*pre, k))
    elif isinstance(o, list):
        for i, v in enumerate(o):
            yield from _paths(v, (*pre, i))


_ODD = st.one_of(st.sampled_from(["1,2,3", "abc", "", None, True, False, [], {}, [1], [[1, 2]], {"a": 1}, 0, -1,
                                  10 ** 30, 1.5, "1e400", float("inf"), float("nan"), [None] * 3,
                                  ["1", "2", "3"], [[0] * 3] * 3]), _JSON)


@pytest.mark.parametrize("reader", [k for k in JSON_READERS if k != "OpenSfM reconstruction"])
def test_malformed_values_raise_project_errors_only(tmp_path, reader):
    """Any value of a valid file replaced by a string, a list, null, a huge or non-finite number...: the reader
    succeeds or raises a project error (found before: TypeError, ValueError, OverflowError)."""
    fn, name = JSON_READERS[reader]
    src = _samples(tmp_path)[reader]
    doc = json.loads(src.read_text())
    paths = list(_paths(doc))
    target = tmp_path / f"m_{name}"

    @settings(max_examples=120, deadline=None)
    @given(st.sampled_from(paths), _ODD)
    def check(path, value):
        d = copy.deepcopy(doc)
        if not path:
            d = value
        else:
            cur = d
            for k in path[:-1]:
                cur = cur[k]
            cur[path[-1]] = value
        target.write_text(json.dumps(d))
        try:
            fn(target)
        except RectifyError as err:
            assert "\n" not in str(err)

    check()


@pytest.mark.parametrize("position", ["1,2,3", ["1", "2", "3"], "500000"])
def test_eo_position_as_a_string_is_one_line(tmp_path, position):
    """Issue 32: an EO position given as a string raised ValueError."""
    doc = json.loads((RELEASE / "eo.json").read_text())
    doc["position"] = position
    p = tmp_path / "eo.json"
    p.write_text(json.dumps(doc))
    for fn in (read_exterior, read_eo_geometry):
        with pytest.raises(InvalidInputError) as err:
            fn(p)
        _one_line(err, "eo.json", "position", repr(position))
    block = json.loads(_block_json())
    block["images"][0]["position"] = position
    p.write_text(json.dumps(block))
    with pytest.raises(InvalidInputError) as err:
        read_block_orientation(p)
    _one_line(err, "eo.json", "position", "a.tif")


# =========================================================================== CSV tables as streams
_CELL = st.text(alphabet=' a1.,"#\n\ufeff-', max_size=5)


@settings(max_examples=200, deadline=None)
@given(st.integers(1, 4).flatmap(lambda nf: st.tuples(
    st.just(nf), st.lists(st.tuples(st.lists(_CELL, min_size=1, max_size=nf + 1),
                                    st.sampled_from(["", "# note=1", "   ", "# crs=EPSG:4326"])), max_size=12))),
    st.sampled_from([1, 2, 3, 65536]), st.sampled_from([1, 7, 1 << 20]))
def test_table_reader_rows_and_lines(spec, chunk_rows, block_chars):
    """Cells with commas, quotes, line breaks, '#' and byte-order marks; comment and blank lines anywhere;
    chunk and block borders anywhere: the cells read back stripped, each row named by the line it starts on."""
    nf, body = spec
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow([f"c{i}" for i in range(nf)])
    line = 2
    expect, starts, crs = [], [], None
    for cells, extra in body:
        if any(c.strip() for c in cells) or len(cells) > 1:
            row_text = io.StringIO()
            csv.writer(row_text, lineterminator="\n").writerow(cells)
            txt = row_text.getvalue()
            if any(not ln.strip() or ln.lstrip().startswith("#") for ln in txt.split("\n")[:-1]) or "\ufeff" in txt:
                continue  # a line the format reads as a comment or blank, or a byte-order mark: not this row
            buf.write(txt)
            expect.append(tuple((cells[i] if i < len(cells) else "").strip() for i in range(nf)))
            starts.append(line)
            line += txt.count("\n")
        if extra:
            buf.write(extra + "\n")
            line += 1
            if extra.startswith("# crs="):
                crs = "EPSG:4326"
    fd, name = tempfile.mkstemp(suffix=".csv")
    os.close(fd)
    d = Path(name)
    d.write_text(buf.getvalue(), encoding="utf-8")
    old = common._CHUNK_ROWS, common._BLOCK_CHARS
    common._CHUNK_ROWS, common._BLOCK_CHARS = chunk_rows, block_chars
    try:
        with TableReader(d) as t:
            if not expect:
                with pytest.raises(InvalidInputError, match="has a header but no rows"):
                    t.read("rows", texts=t.fields)
                return
            cols = t.read("rows", texts=t.fields)
    finally:
        common._CHUNK_ROWS, common._BLOCK_CHARS = old
        d.unlink()
    got = list(zip(*(cols.texts[f"c{i}"] for i in range(nf)), strict=True))
    assert got == expect
    assert cols.lines.tolist() == starts
    assert cols.crs == crs


def test_table_reader_numbers_name_the_line_and_column(tmp_path):
    p = tmp_path / "t.csv"
    p.write_text("# crs=EPSG:32633\nid,a,b\n\np1,1.5,\n# c\np2, 2 ,7\np3,x,8\n")
    with TableReader(p) as t:
        with pytest.raises(InvalidInputError) as err:
            t.read("rows", numbers=("a", "b"), texts=("id",), empty=("b",))
    _one_line(err, "t.csv", "line 7", "column 'a'", "'x'")
    p.write_text("id,a\np1,1\np2,inf\n")
    with TableReader(p) as t, pytest.raises(InvalidInputError, match=r"line 3: column 'a' is not finite: 'inf'"):
        t.read("rows", numbers=("a",))
    p.write_text("id,a,b\np1,1,\np2, 2 ,7\n")
    with TableReader(p) as t:
        c = t.read("rows", numbers=("a", "b"), texts=("id",), empty=("b",))
    assert c.numbers["a"].tolist() == [1.0, 2.0] and np.isnan(c.numbers["b"][0]) and c.lines.tolist() == [2, 3]


@pytest.mark.parametrize("content, cls, words", [
    (b"id,col,row,x,y\n\xe9,2,3,4,5\n", RasterIOError, ["not UTF-8 text"]),
    (b"id,col,row,x,y\n" + b"a" * 200_000 + b",2,3,4,5\n", InvalidInputError, ["line 2", "field limit"]),
    (b"id,col,row,x,y\n1,2\x00,3,4,5\n", InvalidInputError, ["line 2", "column 'col'"]),
    (b"", InvalidInputError, ["no header and no rows"]),
])
def test_csv_third_party_errors_are_one_line(tmp_path, content, cls, words):
    p = tmp_path / "g.csv"
    p.write_bytes(content)
    for fn in (read_gcps, read_matches, read_control, read_block_control, read_pose_csv, read_observations_csv):
        with pytest.raises(cls) as err:
            fn(p)
        _one_line(err, "g.csv")
    with pytest.raises(cls) as err:
        read_gcps(p)
    _one_line(err, *words)


def test_no_duplicates_names_them_among_many():
    ids = [f"p{i}" for i in range(200_000)]
    no_duplicates(ids, "t.csv", "id(s)")
    ids[150_000] = "p7"
    ids[199_999] = "p42"
    ids.append("p42")
    with pytest.raises(InvalidInputError, match=r"duplicate id\(s\) \['p42', 'p7'\]"):
        no_duplicates(ids, "t.csv", "id(s)")


def _big_table(path: Path, kind: str, n: int) -> Path:
    """A valid table of ``kind`` with ``n`` rows."""
    k = np.arange(n)
    head, fmt = {
        "gcps": ("id,col,row,x,y", "g{0},{1},{2},{3},{4}"),
        "poses": ("image,x,y,z,omega,phi,kappa", "i{0}.tif,{3},{4},900,0,0,{1}"),
        "block control": ("id,image,col,row,x,y,z", "p{0},a.tif,{1},{2},{3},{4},100"),
        "stereo control": ("id,col_left,row_left,col_right,row_right,x,y,z", "p{0},{1},{2},{2},{1},{3},{4},100"),
    }[kind]
    with open(path, "w") as fh:
        fh.write("# crs=EPSG:32633\n" + head + "\n")
        for s in range(0, n, 100_000):
            fh.write("".join(fmt.format(i, i % 4000, i % 3000, 500000 + i % 9000, 4400000 + i % 7000) + "\n"
                             for i in k[s:s + 100_000].tolist()))
    return path


@pytest.mark.parametrize("kind, reader", [("gcps", read_gcps), ("poses", read_pose_csv),
                                          ("block control", read_block_control), ("stereo control", read_control)])
def test_point_tables_over_the_row_limit_are_refused_by_name(tmp_path, kind, reader):
    """Issue 32: GCP, pose, block-control and stereo-control CSVs of millions of rows ran out of memory; a table of
    one row past the stated limit is refused while reading, the limit and the line named; one at the limit reads."""
    p = _big_table(tmp_path / "t.csv", kind, MAX_POINT_ROWS + 1)
    with pytest.raises(InvalidInputError) as err:
        reader(p)
    _one_line(err, "t.csv", f"more than {MAX_POINT_ROWS}", f"row {MAX_POINT_ROWS + 1} is on line {MAX_POINT_ROWS + 3}")
    if kind == "gcps":
        assert len(reader(_big_table(tmp_path / "ok.csv", kind, MAX_POINT_ROWS))) == MAX_POINT_ROWS


_RSS_SCRIPT = textwrap.dedent("""
    import sys
    from rectify.formats.common import TableReader
    with TableReader(sys.argv[1]) as t:
        c = t.read("GCP rows", numbers=("col", "row", "x", "y", "z"), texts=("id",), max_rows=10**8)
    assert len(c) == int(sys.argv[2]) and c.numbers["x"].dtype == "float64"
    # the peak of this process's own memory (ru_maxrss would keep the forked test runner's peak across exec)
    print(next(ln.split()[1] for ln in open("/proc/self/status") if ln.startswith("VmHWM:")))  # KiB
""")


def _gcp_csv(path: Path, n: int) -> int:
    """A GCP CSV of ``n`` rows like the issue's (about 64 bytes a row); return its size in bytes."""
    rng = np.random.default_rng(0)
    with open(path, "w") as fh:
        fh.write("# crs=EPSG:32633\nid,col,row,x,y,z\n")
        for s in range(0, n, 250_000):
            m = min(250_000, n - s)
            v = (rng.random((m, 5)) * [4000, 3000, 1e4, 1e4, 500] + [0, 0, 5e5, 4.4e6, 0]).tolist()
            fh.write("".join(f"gcp{s + i},{a:.4f},{b:.4f},{x:.4f},{y:.4f},{z:.4f}\n"
                             for i, (a, b, x, y, z) in enumerate(v)))
    return path.stat().st_size


@pytest.mark.slow
@pytest.mark.skipif(not Path("/proc/self/status").is_file(), reason="needs /proc for the peak memory")
def test_table_memory_follows_the_rows_not_the_text(tmp_path):
    """The mechanism on one million rows (64 MB): the columns go straight into arrays. Peak RSS of the whole
    process (interpreter and numpy included; 0.23 GB measured) stays under 400 MB; the former list of dicts of
    strings took 1.27 GB for this file (12.1 GB for ten million rows; docs/formats.md, limits)."""
    p = tmp_path / "big.csv"
    _gcp_csv(p, 1_000_000)
    r = subprocess.run([sys.executable, "-c", _RSS_SCRIPT, str(p), "1000000"], capture_output=True, text=True,
                       cwd=ROOT, timeout=300)
    assert r.returncode == 0, r.stderr
    peak_mb = int(r.stdout.split()[-1]) / 1024
    assert peak_mb < 400, peak_mb


# =========================================================================== CRS comments checked on reading
@pytest.mark.parametrize("reader, text", [
    (read_control, "id,col_left,row_left,col_right,row_right,x,y,z\na,1,2,3,4,5,6,7\n"),
    (read_gcps, "id,col,row,x,y\na,1,2,3,4\n"),
    (read_block_control, "id,image,col,row,x,y,z\na,i.tif,1,2,3,4,5\n"),
    (read_pose_csv, "image,x,y,z,omega,phi,kappa\ni.tif,1,2,3,0,0,0\n"),
])
def test_unknown_epsg_in_a_table_is_named_on_reading(tmp_path, reader, text):
    """Issue 32: a control CSV with an unknown EPSG code reached rasterio's CRSError when `stereo dense` wrote its
    DSM; the reader names the file, the line and the code."""
    p = tmp_path / "c.csv"
    p.write_text("# crs=EPSG:999999\n" + text)
    with pytest.raises(CRSError) as err:
        reader(p)
    _one_line(err, "c.csv", "line 1", "EPSG:999999")


# =========================================================================== GeoPackage names
NAMES = ["it's", "100%", "a%41b", "why?", "no#1", "two words", 'say "x"', "%2e%2e", "file:x"]


@pytest.mark.parametrize("name", NAMES)
def test_geopackage_names_are_passed_safely(tmp_path, name):
    """Issue 32: '%', '?' and '#' in a GeoPackage's name were read as URI syntax: 'a%41b.gpkg' opened 'aAb.gpkg'
    (a different transform, silently), 'why?.gpkg' created an empty file 'why' and failed. The same points as
    the CSV are read, and nothing else is opened or created."""
    g = _gcp_table()
    decoy = tmp_path / "aAb.gpkg"  # what 'a%41b.gpkg' decoded to
    write_gcps(decoy, GcpTable(g.ids, g.pixel + 50, g.target, None, g.check, g.crs))
    (tmp_path / "gcps.csv").write_text(gcps_text(g))
    p = tmp_path / f"{name}.gpkg"
    write_gcps(p, g)
    before = _entries(tmp_path)
    back, ref = read_gcps(p), read_gcps(tmp_path / "gcps.csv")
    assert back.ids == ref.ids and back.crs == ref.crs
    np.testing.assert_array_equal(back.pixel, ref.pixel)
    np.testing.assert_array_equal(back.target, ref.target)
    assert _entries(tmp_path) == before


@pytest.mark.parametrize("layer", ['a"b', "it's", "x; DROP TABLE gpkg_contents"])
def test_geopackage_layer_names_are_quoted(tmp_path, layer):
    p = tmp_path / "g.gpkg"
    write_gcps_gpkg(p, _gcp_table(), layer=layer)
    assert read_gcps(p).ids == _gcp_table().ids


def test_geopackage_faults_are_one_line(tmp_path):
    p = tmp_path / "g.gpkg"
    p.write_bytes(b"not a database at all" * 100)
    with pytest.raises(InvalidInputError) as err:
        read_gcps(p)
    _one_line(err, "g.gpkg", "not a GeoPackage")
    p.unlink()
    write_gcps_gpkg(p, _gcp_table())
    con = sqlite3.connect(p)
    con.execute('UPDATE "gcps" SET geom = ?', (10 ** 12,))  # an integer where the geometry blob belongs
    con.commit()
    con.close()
    with pytest.raises(InvalidInputError) as err:
        read_gcps(p)
    _one_line(err, "g.gpkg", "not a GeoPackage geometry")


# =========================================================================== images and grids
def _png_declaring(path: Path, width: int, height: int) -> Path:
    """A small PNG file whose header declares ``width`` x ``height`` grey pixels."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\0" * 1000))
                     + chunk(b"IEND", b""))
    return path


def test_chessboard_image_larger_than_opencv_reads_is_named(tmp_path):
    """Issue 32: an image declaring more pixels than OpenCV allows raised cv2.error."""
    p = _png_declaring(tmp_path / "huge.png", 100_000, 100_000)
    with pytest.raises(RasterIOError) as err:
        find_chessboards([p], Chessboard(9, 6))
    _one_line(err, "huge.png", "100000 x 100000 px", str(1 << 30))
    bad = tmp_path / "cut.png"
    bad.write_bytes(p.read_bytes()[:30])
    with pytest.raises(RasterIOError) as err:
        find_chessboards([bad], Chessboard(9, 6))
    _one_line(err, "cut.png")


@pytest.mark.parametrize("resolution", [1e-320, 1e-300, 1e-6])
def test_mosaic_tiny_resolution_refused_with_the_numbers(tmp_path, resolution):
    """Issue 32: `rectify mosaic` with a tiny resolution died with MemoryError (1e-320: OverflowError)."""
    src = tmp_path / "o.tif"
    img = (np.random.default_rng(0).random((64, 64)) * 200 + 1).astype(np.uint8)
    write_raster(src, img, Affine(1, 0, 500000, 0, -1, 4400000), "EPSG:32618")
    out = tmp_path / "out"
    out.mkdir()
    with pytest.raises(InvalidInputError) as err:
        mosaic([src], out / "m.tif", resolution=resolution)
    _one_line(err, f"{resolution:.6g}", "px", "coarser --resolution")
    assert _entries(out) == []

