"""The command groups import a subcommand's module only when it runs; boto3 (imported by rasterio for AWS
sessions) loads only when used."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
import textwrap

import pytest
from click.testing import CliRunner

from rectify.cli.main import cli
from stereo.cli.main import cli as stereo_cli


def _run(code: str) -> str:
    p = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    return p.stdout.strip()


def test_group_lists_every_command_sorted_and_help_names_them():
    names = ["compare", "demo", "fit", "match", "mosaic", "ortho", "rpc-adjust", "view", "warp"]
    assert sorted(cli.all_commands) == names
    r = CliRunner().invoke(cli, ["--help"])
    assert r.exit_code == 0
    assert all(f"  {n} " in r.output for n in names)
    snames = ["block", "calibrate", "demo", "dense", "dense-rpc", "disparity", "model", "orient", "resect", "run",
              "sat-intersect", "surface", "view"]
    assert sorted(stereo_cli.all_commands) == snames
    r = CliRunner().invoke(stereo_cli, ["--help"])
    assert r.exit_code == 0 and "dense-rpc" in r.output


def test_a_command_imports_only_its_own_module():
    out = _run("""
        import sys
        from rectify.cli.main import cli
        try:
            cli(["fit", "--help"], standalone_mode=False)
        except SystemExit:
            pass
        print(" ".join(sorted(m for m in sys.modules if m.startswith("rectify.cli."))))
    """)
    assert "rectify.cli.fit" in out.split()
    assert not {"rectify.cli.match", "rectify.cli.warp", "rectify.cli.ortho", "rectify.cli.mosaic"} & set(out.split())


def test_unknown_command_is_a_usage_error():
    r = CliRunner().invoke(cli, ["nosuch"])
    assert r.exit_code == 2 and "No such command 'nosuch'" in r.output


def test_deferred_module_loads_on_first_use():
    out = _run("""
        import sys
        from rectify.cli.options import defer_import
        defer_import("wave")
        import wave
        lazy = type(sys.modules["wave"]).__name__
        has = callable(wave.open)              # first attribute access runs the module
        print(lazy, has, type(sys.modules["wave"]).__name__)
    """)
    assert out == "_LazyModule True module"


@pytest.mark.skipif(importlib.util.find_spec("boto3") is None, reason="boto3 is not installed")
def test_boto3_is_not_run_at_start_but_works_when_used():
    out = _run("""
        import sys
        import rectify.cli.main, rectify.cli.match   # imports rasterio (which imports boto3)
        before = "boto3.session" in sys.modules
        import rasterio.session
        ok = rasterio.session.boto3 is not None and rasterio.session.boto3.Session is not None
        print(before, ok, "boto3.session" in sys.modules)
    """)
    assert out == "False True True"
