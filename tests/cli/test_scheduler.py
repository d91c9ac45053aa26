"""``--scheduler`` of ``rectify warp``, ``ortho`` and ``mosaic``: local Dask processes end to end, bad values."""

import numpy as np
import pytest
import rasterio
from affine import Affine
from click.testing import CliRunner

from rectify.cli.main import cli
from rectify.formats.transform import write_transform
from rectify.geometry.transforms.matrix import AffineTransform
from rectify.raster.io import write_raster

# distributed may warn while its local cluster shuts down: only here, narrowly
pytestmark = [pytest.mark.filterwarnings("ignore::ResourceWarning"),
              pytest.mark.filterwarnings("ignore:.*[Cc]lient.*:UserWarning"),
              pytest.mark.filterwarnings("ignore:.*[Ww]orker.*:UserWarning"),
              pytest.mark.filterwarnings("ignore:.*[Cc]omm.*:UserWarning")]


@pytest.fixture()
def scene(tmp_path):
    """A 600 x 500 RGB frame (no CRS) and a saved affine transform to UTM 18N (30 m pixels)."""
    rng = np.random.default_rng(5)
    rr, cc = np.mgrid[0:500, 0:600]
    img = np.stack([cc * 0.3 + rr * 0.1, 120 + 80 * np.sin(cc / 17.0), rr * 0.4], axis=-1)
    img = np.clip(img + rng.normal(0, 5, img.shape), 1, 255).astype(np.uint8)
    src = tmp_path / "frame.tif"
    write_raster(src, img, Affine(1, 0, 0, 0, 1.0000001, 0), None, nodata=0)
    m = np.array([[29.0, 6.0, 500100.0], [5.0, -31.0, 4399900.0], [0.0, 0.0, 1.0]])
    write_transform(tmp_path / "affine.json", AffineTransform(m), crs="EPSG:32618")
    return tmp_path, src


def _pixels(path):
    with rasterio.open(path) as ds:
        return ds.read(), ds.read_masks(1), ds.transform, ds.crs


def test_warp_with_local_processes_equals_threads(scene):
    d, src = scene
    base = ["warp", str(src), None, "--transform", str(d / "affine.json"), "--resolution", "25",
            "--resampling", "nearest"]
    r1 = CliRunner().invoke(cli, [str(d / "threads.tif") if a is None else a for a in base])
    assert r1.exit_code == 0, r1.output
    r2 = CliRunner().invoke(cli, [str(d / "dask.tif") if a is None else a for a in base]
                            + ["--scheduler", "processes:2"])
    assert r2.exit_code == 0, r2.output
    assert "wrote" in r2.output
    a, b = _pixels(d / "threads.tif"), _pixels(d / "dask.tif")
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])
    assert a[2:] == b[2:]
    # no block folder or temporary file left (a warp's own sidecars, such as its STAC item, aside)
    assert sorted(p.name for p in d.iterdir() if not p.name.endswith(".stac.json")) == [
        "affine.json", "dask.tif", "frame.tif", "threads.tif"]


@pytest.mark.parametrize("command", ["warp", "ortho", "mosaic"])
def test_bad_scheduler_is_refused_before_any_work(scene, command):
    d, src = scene
    args = {"warp": ["warp", str(src), str(d / "o.tif"), "--transform", str(d / "affine.json")],
            "ortho": ["ortho", str(src), "-o", str(d / "o.tif"), "--dem", str(src), "--rpc"],
            "mosaic": ["mosaic", str(src), "-o", str(d / "o.tif")]}[command]
    r = CliRunner().invoke(cli, args + ["--scheduler", "gpus:4"])
    assert r.exit_code == 2
    assert "Invalid value for '--scheduler': unknown scheduler 'gpus:4'; expected 'threads', 'processes', " \
           "'processes:N' or 'tcp://HOST:PORT'" in r.output
    assert not (d / "o.tif").exists()


def test_scheduler_from_the_environment(scene, monkeypatch):
    d, src = scene
    monkeypatch.setenv("RECTIFY_SCHEDULER", "processes:0")
    r = CliRunner().invoke(cli, ["warp", str(src), str(d / "o.tif"), "--transform", str(d / "affine.json")])
    assert r.exit_code == 1
    assert r.output.strip() == "Error: InvalidInputError: bad scheduler in $RECTIFY_SCHEDULER 'processes:0': the " \
                               "worker count must be an integer in 1..1024"
    assert not (d / "o.tif").exists()
    # an explicit option wins over the environment
    r = CliRunner().invoke(cli, ["warp", str(src), str(d / "o.tif"), "--transform", str(d / "affine.json"),
                                 "--scheduler", "threads"])
    assert r.exit_code == 0, r.output


def test_unreachable_cluster_is_one_line(scene, monkeypatch):
    import socket

    d, src = scene
    monkeypatch.setenv("RECTIFY_SCHEDULER_TIMEOUT", "2")
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    r = CliRunner().invoke(cli, ["warp", str(src), str(d / "o.tif"), "--transform", str(d / "affine.json"),
                                 "--scheduler", f"tcp://127.0.0.1:{port}"])
    assert r.exit_code == 1
    line = r.output.strip()
    assert line.startswith(f"Error: SchedulerError: cannot reach the Dask scheduler 'tcp://127.0.0.1:{port}' "
                           "within 2 s") and "\n" not in line
    assert sorted(p.name for p in d.iterdir()) == ["affine.json", "frame.tif"]
