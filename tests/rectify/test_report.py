"""Tests of rectify.report.builder (write_report, GeoJSON) and rectify.report.figures (figure helpers)."""

from __future__ import annotations

import csv
import io
import json
import math
import re
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from matplotlib.figure import Figure

from rectify.errors import CRSError, InvalidInputError, RasterIOError, ShapeError
from rectify.geometry.residuals import ResidualTable
from rectify.report.builder import (
    correlation_heatmap_figure,
    format_number,
    height_bars_figure,
    histogram_qq_figure,
    json_safe,
    radial_figure,
    residual_geojson,
    residual_vector_figure,
    slugify,
    write_report,
)
from rectify.report.figures import nice_number, standardised_components

GCP_STEP = "GCP fit (homography)"
RO_STEP = "relative orientation"
PX_TO_GROUND = np.array([[30.0, 0.0], [0.0, -30.0]])  # metres per pixel, north up
GROUND_ORIGIN = np.array([500000.0, 4000000.0])


def make_gcp_table(n: int = 30, seed: int = 7) -> ResidualTable:
    rng = np.random.default_rng(seed)
    pos = rng.uniform(0, [1000, 800], size=(n, 2))
    obs = pos + rng.normal(0, 0.5, (n, 2))
    adj = pos.copy()
    outlier = np.zeros(n, bool)
    check = np.zeros(n, bool)
    if n > 8:
        outlier[3] = True
        adj[3] += 6.0
        check[5:8] = True
    return ResidualTable(GCP_STEP, [f"P{i}" for i in range(n)], obs, adj, "px", outlier=outlier, check=check,
                         position_px=pos, n_params=8, extra={"iterations": 3})


def make_ro_table(n: int = 25, seed: int = 3) -> ResidualTable:
    rng = np.random.default_rng(seed)
    pos = rng.uniform(0, [640, 1152], size=(n, 2))
    q = rng.normal(0, 0.006, n)
    return ResidualTable(RO_STEP, [f"t{i}" for i in range(n)], q, np.zeros(n), "mm", components=("q",),
                         position_px=pos, n_params=5)


def make_tiny(step: str = "tiny fit") -> ResidualTable:
    """A small table without positions: only the CSV and one distribution plot (fast)."""
    return ResidualTable(step, ["a", "b", "c", "d"], np.zeros((4, 2)), [[0.1, 0.0], [0.0, -0.2], [0.3, 0.1],
                                                                      [-0.1, 0.1]], "px", n_params=2)


def ground_of(table: ResidualTable) -> np.ndarray:
    return table.position_px @ PX_TO_GROUND.T + GROUND_ORIGIN


# ----------------------------------------------------------------------------- HTML parsing
class NumberCells(HTMLParser):
    """Collect every element with data-key: (scope, key) -> (data-value or None, text)."""

    def __init__(self) -> None:
        super().__init__()
        self.all: dict[tuple[str, str], list[tuple[str | None, str]]] = {}
        self.images: list[str] = []
        self.sections: list[str] = []
        self.external: list[str] = []
        self._open: tuple[str, str, str | None] | None = None
        self._text: list[str] = []

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        for k in ("src", "href"):
            v = a.get(k)
            if v and re.match(r"^(https?:)?//", v):
                self.external.append(v)
        if tag == "img":
            self.images.append(a.get("src", ""))
        if tag == "section" and "data-section" in a:
            self.sections.append(a["data-section"])
        if "data-key" in a:
            self._open = (a.get("data-scope", ""), a["data-key"], a.get("data-value"))
            self._text = []

    def handle_data(self, data):
        if self._open is not None:
            self._text.append(data)

    def handle_endtag(self, tag):
        if tag == "td" and self._open is not None:
            scope, key, value = self._open
            self.all.setdefault((scope, key), []).append((value, "".join(self._text).strip()))
            self._open = None

    @property
    def cells(self) -> dict[tuple[str, str], tuple[str | None, str]]:
        """The single cell per key (asserts that repeated cells agree)."""
        out = {}
        for k, v in self.all.items():
            assert all(x == v[0] for x in v), (k, v)
            out[k] = v[0]
        return out


def parse_html(path: Path) -> NumberCells:
    p = NumberCells()
    p.feed(path.read_text(encoding="utf-8"))
    return p


def read_csv(path: Path) -> list[dict[str, str]]:
    lines = [ln for ln in path.read_text().splitlines() if not ln.startswith("#")]
    return list(csv.DictReader(io.StringIO("\n".join(lines))))


def assert_cell_matches(cell: tuple[str | None, str], expected) -> None:
    """The HTML cell carries exactly `expected` and shows it rounded to 4 significant digits."""
    value, text = cell
    if expected is None:
        assert value in ("", None) and text == "n/a"
        return
    assert value is not None and value != ""
    assert float(value) == float(expected)
    assert text == format_number(int(value) if re.fullmatch(r"-?\d+", value) else float(value))


@pytest.fixture(scope="module")
def report_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One report shared by the read-only tests of this module (tests must not modify it)."""
    tmp_path = tmp_path_factory.mktemp("shared_report")
    gcp, ro = make_gcp_table(), make_ro_table()
    c = np.eye(5)
    c[0, 1] = c[1, 0] = -0.7
    write_report(tmp_path / "rep", title="Test run", tables=[gcp, ro],
                 figures={"RO correlation": correlation_heatmap_figure(list("abcde"), c)},
                 summary={"method": "homography", "transform": {"det": 1.25, "cond": np.float64(3.5)},
                          "angles_rad": np.array([0.1, 0.2])},
                 crs="EPSG:32618", ground_xy={GCP_STEP: ground_of(gcp)},
                 image_shapes={GCP_STEP: (800, 1000)}, html_max_rows=1000)
    return tmp_path / "rep"


# ----------------------------------------------------------------------------- write_report
def test_files_written(report_dir: Path):
    names = sorted(p.name for p in report_dir.iterdir())
    assert names == sorted([
        "fig_ro_correlation.png", "gcp_fit_homography.csv", "gcp_fit_homography.geojson",
        "gcp_fit_homography_distribution.png", "gcp_fit_homography_radial.png", "gcp_fit_homography_vectors.png",
        "relative_orientation.csv", "relative_orientation_distribution.png", "relative_orientation_radial.png",
        "relative_orientation_vectors.png", "report.html", "report.json"])
    doc = json.loads((report_dir / "report.json").read_text())
    assert sorted(doc["files"]) == sorted(n for n in names)
    for f in names:
        if f.endswith(".png"):
            assert (report_dir / f).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # no temporary folder left beside the report
    assert [p.name for p in report_dir.parent.iterdir()] == ["rep"]


def test_csv_is_the_table(report_dir: Path):
    gcp = make_gcp_table()
    assert (report_dir / "gcp_fit_homography.csv").read_text() == gcp.to_csv()
    rows = read_csv(report_dir / "gcp_fit_homography.csv")
    assert list(rows[0]) == ["id", "observed_0", "observed_1", "adjusted_0", "adjusted_1", "dx", "dy", "norm",
                             "normalised", "weight", "outlier", "check"]
    assert rows[3]["outlier"] == "1" and rows[5]["check"] == "1"


def test_json_summary(report_dir: Path):
    doc = json.loads((report_dir / "report.json").read_text())
    gcp = make_gcp_table()
    t = doc["tables"][0]
    assert t["step"] == GCP_STEP and t["units"] == "px" and t["components"] == ["dx", "dy"]
    s = t["summary"]
    assert s["n_points"] == 30 and s["n_fit"] == 26 and s["n_check"] == 3 and s["n_outliers"] == 1
    fit = gcp.fit_mask
    assert s["rmse"] == pytest.approx(math.sqrt(np.mean(np.sum(gcp.residual[fit] ** 2, axis=1))), rel=1e-12)
    assert s["sigma0"] == pytest.approx(math.sqrt(np.sum(gcp.residual[fit] ** 2) / (2 * 26 - 8)), rel=1e-12)
    assert s["rmse_check"] == pytest.approx(math.sqrt(np.mean(gcp.norm[gcp.check] ** 2)), rel=1e-12)
    assert s["iterations"] == 3
    assert doc["summary"] == {"method": "homography", "transform": {"det": 1.25, "cond": 3.5},
                              "angles_rad": [0.1, 0.2]}
    assert doc["crs"] == "EPSG:32618"
    assert doc["figures"] == {"RO correlation": "fig_ro_correlation.png"}


def test_every_html_number_matches_csv_and_json(report_dir: Path):
    p = parse_html(report_dir / "report.html")
    cells = p.cells
    doc = json.loads((report_dir / "report.json").read_text())
    checked: set[tuple[str, str]] = set()

    def check(key, expected):
        assert key in cells, key
        assert_cell_matches(cells[key], expected)
        checked.add(key)

    for t in doc["tables"]:
        slug = t["slug"]
        for key, val in t["summary"].items():  # overview row and the table's summary block
            if key not in ("step", "units"):
                check((slug, key), val)
        assert cells[(slug, "units")][1] == t["units"]
        checked.add((slug, "units"))
        assert len(p.all[(slug, "rmse")]) == 2  # overview + section, identical
        rows = read_csv(report_dir / t["files"]["csv"])
        for i, row in enumerate(rows):
            for col, val in row.items():
                if col != "id":
                    check((f"{slug}#{i}", col), None if val == "nan" else
                          (int(val) if col in ("outlier", "check") else float(val)))
    check(("summary", "transform.det"), doc["summary"]["transform"]["det"])
    check(("summary", "transform.cond"), doc["summary"]["transform"]["cond"])
    assert cells[("summary", "method")][1] == doc["summary"]["method"]
    assert json.loads(re.search(r"data-json='([^']*)'", (report_dir / "report.html").read_text())
                      .group(1).replace("&quot;", '"')) == doc["summary"]["angles_rad"]
    checked |= {("summary", "method"), ("summary", "angles_rad")}
    # every number-bearing element of the page was compared
    assert set(cells) - checked == set()
    assert len(checked) > 30 * 10


def test_html_self_contained(report_dir: Path):
    p = parse_html(report_dir / "report.html")
    assert p.external == []
    assert len(p.images) == 7
    assert all(src.startswith("data:image/png;base64,") for src in p.images)
    assert p.sections == ["overview", "table-gcp_fit_homography", "table-relative_orientation", "figures",
                          "summary", "files"]
    text = (report_dir / "report.html").read_text()
    assert "RMSE" in text and "sigma0" in text and "<link" not in text
    assert "RMSE fit" in text and "(px)" in text and "(mm)" in text


def test_html_max_rows_limits_rows_not_csv(tmp_path: Path):
    t = make_gcp_table(50)
    write_report(tmp_path / "r", title="t", tables=[t], html_max_rows=10)
    p = parse_html(tmp_path / "r" / "report.html")
    rows = {k[0] for k in p.cells if "#" in k[0]}
    assert len(rows) == 10
    # the ten shown are the worst by normalised residual
    worst = set(np.argsort(-t.normalised)[:10].tolist())
    assert {int(r.split("#")[1]) for r in rows} == worst
    assert len(read_csv(tmp_path / "r" / "gcp_fit_homography.csv")) == 50


def test_refuses_overwrite_then_overwrites(tmp_path: Path):
    t = make_tiny()
    out = tmp_path / "r"
    write_report(out, title="first", tables=[t, make_tiny("second step")])
    before = (out / "report.html").read_text()
    with pytest.raises(InvalidInputError, match="overwrite"):
        write_report(out, title="second", tables=[t])
    assert (out / "report.html").read_text() == before
    write_report(out, title="second", tables=[t], overwrite=True)
    assert "second" in (out / "report.html").read_text()
    # files of the previous report that the new one does not produce are removed
    assert not (out / "second_step.csv").exists()
    assert [p.name for p in tmp_path.iterdir()] == ["r"]


def test_existing_folder_with_other_files_is_fine(tmp_path: Path):
    out = tmp_path / "r"
    out.mkdir()
    (out / "notes.txt").write_text("keep me")
    write_report(out, title="t", tables=[make_tiny()])
    assert (out / "notes.txt").read_text() == "keep me"
    assert (out / "report.html").is_file()
    write_report(out, title="t", tables=[make_tiny()], overwrite=True)
    assert (out / "notes.txt").read_text() == "keep me"


class ExplodingFigure(Figure):
    def savefig(self, *args, **kwargs):
        raise RuntimeError("disk full (simulated)")


def test_error_leaves_nothing(tmp_path: Path):
    with pytest.raises(RuntimeError, match="simulated"):
        write_report(tmp_path / "r", title="t", tables=[make_tiny()], figures={"boom": ExplodingFigure()})
    assert list(tmp_path.iterdir()) == []


def test_error_keeps_previous_report(tmp_path: Path):
    out = tmp_path / "r"
    write_report(out, title="old", tables=[make_tiny()])
    before = sorted((p.name, p.read_bytes()) for p in out.iterdir())
    with pytest.raises(RuntimeError, match="simulated"):
        write_report(out, title="new", tables=[make_tiny()], figures={"boom": ExplodingFigure()},
                     overwrite=True)
    assert sorted((p.name, p.read_bytes()) for p in out.iterdir()) == before
    assert [p.name for p in tmp_path.iterdir()] == ["r"]


def test_duplicate_steps_get_unique_files(tmp_path: Path):
    t = make_tiny()
    write_report(tmp_path / "r", title="t", tables=[t, t])
    doc = json.loads((tmp_path / "r" / "report.json").read_text())
    assert [x["files"]["csv"] for x in doc["tables"]] == ["tiny_fit.csv", "tiny_fit_2.csv"]


def test_table_without_positions_and_empty_table(tmp_path: Path):
    t = ResidualTable("no positions", ["a", "b", "c"], np.zeros((3, 2)), np.ones((3, 2)), "m", n_params=1)
    e = ResidualTable("empty", [], np.zeros((0, 2)), np.zeros((0, 2)), "px")
    write_report(tmp_path / "r", title="t", tables=[t, e])
    names = sorted(p.name for p in (tmp_path / "r").iterdir())
    assert names == ["empty.csv", "no_positions.csv", "no_positions_distribution.png", "report.html",
                     "report.json"]
    doc = json.loads((tmp_path / "r" / "report.json").read_text())
    assert doc["tables"][1]["summary"]["rmse"] is None  # NaN -> null, valid JSON
    p = parse_html(tmp_path / "r" / "report.html")
    assert p.cells[("empty", "rmse")] == ("", "n/a")


def test_figures_only(tmp_path: Path):
    fig = correlation_heatmap_figure(["a", "b"], np.eye(2))
    write_report(tmp_path / "r", title="figs", tables=[], figures={"heat": fig})
    _assert_figure(tmp_path / "r", "fig_heat.png")


def test_background_and_principal_point(tmp_path: Path):
    t = make_gcp_table()
    bg = np.random.default_rng(0).uniform(0, 1000, (800, 1000)).astype(np.float32)
    write_report(tmp_path / "r", title="t", tables=[t], backgrounds={GCP_STEP: bg},
                 principal_point_px={GCP_STEP: (480.0, 410.0)})
    assert (tmp_path / "r" / "gcp_fit_homography_vectors.png").stat().st_size > 10_000


def test_does_not_modify_inputs(tmp_path: Path):
    g = ground_of(make_gcp_table())
    g0 = g.copy()
    summary = {"a": [1, 2]}
    write_report(tmp_path / "r", title="t", tables=[make_gcp_table()], crs="EPSG:32618",
                 ground_xy={GCP_STEP: g}, summary=summary)
    np.testing.assert_array_equal(g, g0)
    assert summary == {"a": [1, 2]}


@pytest.mark.parametrize("kwargs, exc, msg", [
    ({"title": ""}, InvalidInputError, "title"),
    ({"title": 3}, InvalidInputError, "title"),
    ({"tables": "x"}, InvalidInputError, "list of ResidualTable"),
    ({"tables": [1]}, InvalidInputError, r"tables\[0\]"),
    ({"tables": []}, InvalidInputError, "nothing to report"),
    ({"figures": {"a": 1}}, InvalidInputError, "matplotlib Figure"),
    ({"figures": [1]}, InvalidInputError, "dict name"),
    ({"summary": [1]}, InvalidInputError, "summary"),
    ({"crs": "EPSG:32618"}, InvalidInputError, "go together"),
    ({"ground_xy": {GCP_STEP: np.zeros((30, 2))}}, InvalidInputError, "go together"),
    ({"crs": "EPSG:32618", "ground_xy": {"nope": np.zeros((30, 2))}}, InvalidInputError, "unknown steps"),
    ({"crs": "EPSG:32618", "ground_xy": {GCP_STEP: np.zeros((29, 2))}}, ShapeError, r"\(30, 2\); got \(29, 2\)"),
    ({"crs": "EPSG:99999999", "ground_xy": {GCP_STEP: np.zeros((30, 2))}}, CRSError, "99999999"),
    ({"backgrounds": {"nope": np.zeros((2, 2))}}, InvalidInputError, "unknown steps"),
    ({"principal_point_px": {"nope": (1, 2)}}, InvalidInputError, "unknown steps"),
    ({"html_max_rows": -1}, InvalidInputError, "html_max_rows"),
])
def test_bad_input(tmp_path: Path, kwargs, exc, msg):
    args = {"title": "t", "tables": [make_gcp_table()]}
    args.update(kwargs)
    with pytest.raises(exc, match=msg):
        write_report(tmp_path / "r", **args)
    assert not (tmp_path / "r").exists()


def test_out_dir_is_a_file(tmp_path: Path):
    f = tmp_path / "file"
    f.write_text("x")
    with pytest.raises(InvalidInputError, match="not a folder"):
        write_report(f, title="t", tables=[make_gcp_table()])


def test_unwritable_parent(tmp_path: Path):
    f = tmp_path / "file"
    f.write_text("x")
    with pytest.raises(RasterIOError, match="cannot create"):
        write_report(f / "sub" / "r", title="t", tables=[make_gcp_table()])


# ----------------------------------------------------------------------------- GeoJSON
def test_geojson_vectors_in_ground_crs(report_dir: Path):
    gj = json.loads((report_dir / "gcp_fit_homography.geojson").read_text())
    t = make_gcp_table()
    assert gj["type"] == "FeatureCollection"
    assert gj["crs"]["properties"]["name"] == "urn:ogc:def:crs:EPSG::32618"
    assert len(gj["features"]) == t.n
    ex = gj["rectify"]["exaggeration"]
    g = ground_of(t)
    for i, f in enumerate(gj["features"]):
        assert f["geometry"]["type"] == "LineString"
        (x0, y0), (x1, y1) = f["geometry"]["coordinates"]
        np.testing.assert_allclose([x0, y0], g[i])
        # pixel residual mapped by the pixel->ground affine: 30 m per px, row down = north negative
        expected = PX_TO_GROUND @ t.residual[i]
        np.testing.assert_allclose([(x1 - x0) / ex, (y1 - y0) / ex], expected, rtol=1e-9, atol=1e-6)
        np.testing.assert_allclose([f["properties"]["v_ground_x"], f["properties"]["v_ground_y"]], expected,
                                   rtol=1e-9, atol=1e-6)
        assert f["properties"]["id"] == t.ids[i]
        assert f["properties"]["outlier"] is bool(t.outlier[i])
        assert f["properties"]["norm"] == pytest.approx(t.norm[i])


def test_geojson_points_when_no_vector(tmp_path: Path):
    t = make_ro_table()
    gj = residual_geojson(t, ground_of(t), "EPSG:32634")
    assert {f["geometry"]["type"] for f in gj["features"]} == {"Point"}
    assert gj["features"][0]["properties"]["q"] == pytest.approx(t.residual[0, 0])


def test_geojson_metre_table_and_wkt_crs():
    from pyproj import CRS

    t = ResidualTable("abs", ["a", "b"], np.zeros((2, 3)), [[1.0, 2.0, 3.0], [0.0, -1.0, 0.5]], "m",
                      components=("dX", "dY", "dZ"))
    wkt = CRS.from_epsg(32618).to_wkt()
    gj = residual_geojson(t, [[10.0, 20.0], [30.0, 40.0]], wkt, exaggeration=10.0)
    (x0, y0), (x1, y1) = gj["features"][0]["geometry"]["coordinates"]
    assert (x1 - x0, y1 - y0) == (10.0, 20.0)
    assert gj["crs"]["properties"]["name"] == "urn:ogc:def:crs:EPSG::32618"
    with pytest.raises(ShapeError, match=r"\(2, 2\)"):
        residual_geojson(t, [[1.0, 2.0]], "EPSG:32618")


# ----------------------------------------------------------------------------- figure helpers
def test_figure_helpers_return_figures():
    t = make_gcp_table()
    for fig in (residual_vector_figure(t), residual_vector_figure(t, image_shape=(800, 1000)),
                residual_vector_figure(t, positions=ground_of(t), position_units="m", y_down=False),
                histogram_qq_figure(t), radial_figure(t, (500, 400)), height_bars_figure(t, component="dy"),
                correlation_heatmap_figure(["a", "b", "c"], np.eye(3)), residual_vector_figure(make_ro_table())):
        assert isinstance(fig, Figure)
        assert fig.axes and all(ax.get_xlabel() for ax in fig.axes if ax.get_label() != "<colorbar>")


def test_vector_figure_arrows_follow_residuals():
    t = make_gcp_table()
    fig = residual_vector_figure(t, scale=10.0)
    q = next(c for c in fig.axes[0].collections if c.__class__.__name__ == "Quiver")
    np.testing.assert_allclose(q.U, t.residual[:, 0] * 10.0)
    np.testing.assert_allclose(q.V, t.residual[:, 1] * 10.0)
    assert fig.axes[0].yaxis_inverted()
    fig2 = residual_vector_figure(t, scale=10.0, components_y_up=True)
    q2 = next(c for c in fig2.axes[0].collections if c.__class__.__name__ == "Quiver")
    np.testing.assert_allclose(q2.V, -t.residual[:, 1] * 10.0)


def test_figure_helper_errors():
    t = make_gcp_table()
    nopos = ResidualTable("np", ["a"], [[0.0, 0.0]], [[1.0, 1.0]], "px")
    with pytest.raises(InvalidInputError, match="no position_px"):
        residual_vector_figure(nopos)
    with pytest.raises(ShapeError, match=r"\(30, 2\)"):
        residual_vector_figure(t, positions=np.zeros((3, 2)))
    with pytest.raises(ShapeError, match="image_shape"):
        residual_vector_figure(t, image_shape=(0, 5))
    with pytest.raises(ShapeError, match="background"):
        residual_vector_figure(t, background=np.zeros((4, 4, 7)))
    with pytest.raises(InvalidInputError, match="no position_px"):
        radial_figure(nopos, (0, 0))
    with pytest.raises(ShapeError, match="principal_point_px"):
        radial_figure(t, (1, 2, 3))
    with pytest.raises(InvalidInputError, match="n_bins"):
        radial_figure(t, (1, 2), n_bins=0)
    with pytest.raises(ShapeError, match=r"\(2, 2\)"):
        correlation_heatmap_figure(["a", "b"], np.eye(3))
    with pytest.raises(InvalidInputError, match=r"\[-1, 1\]"):
        correlation_heatmap_figure(["a", "b"], [[1, 2], [2, 1]])
    with pytest.raises(InvalidInputError, match="unknown component 'dz'"):
        height_bars_figure(t, component="dz")
    with pytest.raises(InvalidInputError, match="out of range"):
        height_bars_figure(t, component=5)
    empty = ResidualTable("e", [], np.zeros((0, 2)), np.zeros((0, 2)), "px")
    with pytest.raises(InvalidInputError, match="no points"):
        histogram_qq_figure(empty)


def test_standardised_components_known_answer():
    """With sigma0 from the fit points, sum of w*z^2 over fit points equals the redundancy."""
    rng = np.random.default_rng(11)
    n = 40
    w = rng.uniform(0.5, 2.0, n)
    t = ResidualTable("w", [str(i) for i in range(n)], rng.normal(0, 1, (n, 2)), np.zeros((n, 2)), "px",
                      weights=w, n_params=6)
    z = standardised_components(t)
    assert np.sum(z ** 2) == pytest.approx(2 * n - 6, rel=1e-12)
    std = rng.uniform(0.5, 2.0, n)
    t2 = ResidualTable("s", [str(i) for i in range(n)], t.observed, t.adjusted, "px", std=std)
    np.testing.assert_allclose(standardised_components(t2), t2.residual / (std[:, None] / math.sqrt(2)))


@settings(max_examples=200, deadline=None)
@given(st.floats(min_value=1e-9, max_value=1e9, allow_nan=False))
def test_nice_number_property(x):
    y = nice_number(x)
    mant = y / 10 ** math.floor(math.log10(y) + 1e-12)
    assert round(mant, 9) in (1.0, 2.0, 5.0)
    assert x / 1.5 <= y <= x * 1.5 + 1e-12 * x or x / 2.0 <= y <= x * 1.34


def test_small_helpers():
    assert slugify("Absolute orientation: plan (X, Y)") == "absolute_orientation_plan_x_y"
    assert json_safe({"x": np.float32(np.inf), "y": np.int64(3), "z": Path("/a")}) == {"x": None, "y": 3, "z": "/a"}
    assert format_number(float("nan")) == "n/a"
    assert format_number(np.int64(7)) == "7"
    assert nice_number(0.0) == 1.0


def test_vector_figure_grids_many_points():
    rng = np.random.default_rng(2)
    n = 3000
    pos = rng.uniform(0, 1000, (n, 2))
    out = np.zeros(n, bool)
    out[:10] = True
    adj = pos + [1.0, 2.0]
    adj[:10] += 50.0  # outliers are excluded from the cell means
    t = ResidualTable("many", [str(i) for i in range(n)], pos, adj, "px", outlier=out, position_px=pos)
    fig = residual_vector_figure(t, image_shape=(1000, 1000), scale=3.0, max_arrows=200)
    q = next(c for c in fig.axes[0].collections if c.__class__.__name__ == "Quiver")
    assert 50 <= len(q.U) <= 100  # a 10 x 10 grid
    np.testing.assert_allclose(q.U, 3.0)
    np.testing.assert_allclose(q.V, 6.0)
    assert "10\u00d710 grid" in fig.axes[0].get_title(loc="left").replace("\n", " ")
    with pytest.raises(InvalidInputError, match="max_arrows"):
        residual_vector_figure(t, max_arrows=0)


def test_radial_figure_scales_to_fit_points():
    rng = np.random.default_rng(1)
    n = 300
    pos = rng.uniform(0, [640, 480], (n, 2))
    v = rng.normal(0, 0.01, (n, 2))
    out = np.zeros(n, bool)
    out[:5] = True
    v[:5] = 5.0
    t = ResidualTable("ro", [str(i) for i in range(n)], np.zeros((n, 2)), v, "px", outlier=out, position_px=pos)
    fig = radial_figure(t, (320, 240))
    ax = fig.axes[0]
    assert ax.get_ylim()[1] < 0.1  # not stretched by the 7 px outliers
    assert any("5 outlier(s) beyond" in txt.get_text() for txt in ax.texts)
    np.testing.assert_allclose(ax.collections[0].get_offsets()[:, 1], t.norm[~out])


def test_verify_report_agrees_and_catches_tampering(tmp_path: Path):
    from tests.support.rectify_support import verify_report

    t = ResidualTable("flags", ["a", "b", "c", "d"], np.zeros((4, 2)), [[0.1, 0.0], [0.0, -0.2], [0.3, 0.1],
                                                                      [-0.1, 0.1]], "px", n_params=2,
                      extra={"converged": True, "system": "basis"})
    out = tmp_path / "r"
    write_report(out, title="t", tables=[t], summary={"ok": False, "n": 3, "x": [1.5], "name": "q"})
    assert verify_report(out) == []
    html_text = (out / "report.html").read_text()
    rmse = repr(t.summary()["rmse"])
    # a shown value that disagrees with its data-value
    bad = html_text.replace(f'data-value="{rmse}">{format_number(t.summary()["rmse"])}<',
                            f'data-value="{rmse}">9.999<', 1)
    assert bad != html_text
    (out / "report.html").write_text(bad)
    assert any("rmse" in p for p in verify_report(out))
    # a CSV value that disagrees with the page
    (out / "report.html").write_text(html_text)
    csv_text = (out / "flags.csv").read_text()
    (out / "flags.csv").write_text(csv_text.replace("0.30000000000000004", "0.4").replace(",0.3,", ",0.4,"))
    assert any("flags#2" in p for p in verify_report(out))
    with pytest.raises(RasterIOError, match="cannot read"):
        verify_report(tmp_path / "nowhere")


def test_verify_report_on_shared_report(report_dir: Path):
    from tests.support.rectify_support import verify_report

    assert verify_report(report_dir) == []


def test_ground_unit_residuals_drawn_on_map_axes(tmp_path: Path):
    """Residuals in metres are map-frame (north up): drawn at ground positions, or flipped over the image."""
    import rectify.report.builder as rep

    t = make_gcp_table()
    tm = ResidualTable("map fit", t.ids, t.observed, t.adjusted, "m", position_px=t.position_px)
    g = ground_of(t)
    fig = rep._vector_figure(tm, (800, 1000), None, g, "EPSG:32618")
    ax = fig.axes[0]
    assert not ax.yaxis_inverted() and ax.get_xlabel() == "X (m)"
    q = next(c for c in ax.collections if c.__class__.__name__ == "Quiver")
    np.testing.assert_allclose(q.get_offsets(), g)
    assert np.all(q.V * tm.residual[:, 1] >= 0)  # north component drawn upwards on north-up axes
    fig2 = rep._vector_figure(tm, (800, 1000), None, None, None)
    q2 = next(c for c in fig2.axes[0].collections if c.__class__.__name__ == "Quiver")
    assert fig2.axes[0].yaxis_inverted()
    assert np.all(q2.V * tm.residual[:, 1] <= 0)  # image axes: north is up, i.e. negative row
    write_report(tmp_path / "r", title="t", tables=[tm], crs="EPSG:32618", ground_xy={"map fit": g})
    _assert_figure(tmp_path / "r", "map_fit_vectors.png")


def _assert_figure(folder: Path, name: str) -> None:
    """A written figure decodes as a PNG of a plausible size with drawn content, and the HTML shows it."""
    import matplotlib.image

    img = matplotlib.image.imread(folder / name)
    assert img.ndim == 3 and img.shape[0] >= 200 and img.shape[1] >= 200, img.shape
    colours = np.unique((img[..., :3] * 255).astype(np.uint8).reshape(-1, 3), axis=0)
    assert len(colours) > 20, len(colours)  # not blank
    assert f'data-file="{name}" src="data:image/png;base64,' in (folder / "report.html").read_text()
