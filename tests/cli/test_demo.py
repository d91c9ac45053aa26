"""``rectify demo`` end to end (embedded data, ~3 s)."""

import re

import rasterio
from click.testing import CliRunner

from rectify.cli.main import cli
from rectify.raster.io import raster_info


def test_demo(tmp_path):
    out = tmp_path / "demo"
    r = CliRunner().invoke(cli, ["demo", "--out", str(out)])
    assert r.exit_code == 0, r.output
    m = re.search(r"geolocation RMSE against the truth: ([\d.]+) m = ([\d.]+) Landsat px", r.output)
    assert m and float(m.group(2)) < 0.5  # 0.15 px picking noise on 12 GCPs
    assert "12 control, 4 check points" in r.output
    for name in ("tilted_frame.tif", "gcps.csv", "rectified.tif", "report/report.html", "report/report.json"):
        assert (out / name).is_file(), name
    info = raster_info(out / "rectified.tif")
    assert info.crs == "EPSG:32618" and info.nodata == 0
    with rasterio.open(out / "tilted_frame.tif") as ds:
        assert ds.crs is None
    # a second run refuses to replace outputs
    r2 = CliRunner().invoke(cli, ["demo", "--out", str(out)])
    assert r2.exit_code != 0 and "exists" in r2.output
    r3 = CliRunner().invoke(cli, ["demo", "--out", str(out), "--overwrite"])
    assert r3.exit_code == 0, r3.output


def test_command_modules_are_thin():
    """Every ``rectify`` command module parses options and calls one action: it imports click, the
    actions, the workspace and the shared options, and nothing that computes, reads files or draws."""
    import ast
    from pathlib import Path

    import rectify.cli

    allowed = {"__future__", "click", "rectify.cli.options"}
    for path in Path(rectify.cli.__file__).parent.glob("*.py"):
        if path.name in ("__init__.py", "main.py", "options.py"):
            continue
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                names = [node.module or ""] if node.module else [a.name for a in node.names]
            else:
                continue
            assert all(n in allowed or n.startswith("rectify.actions.") for n in names), (path.name, names)
