"""Open generated report.html pages in headless Chromium: sections render, images decode, no console output.

Debian's ``chromium`` is installed by ``.ci/run`` (the test never installs anything);
without it the test skips and says so.
Chromium runs fully offline on ``file://`` URLs with networking features disabled.

Console messages are captured from Chromium's own log (``--enable-logging=stderr``
prints every page console message as an ``INFO:CONSOLE`` line); the page's
inline render check (in ``rectify.report.builder``) marks the body with the number of
decoded images and each section with ``data-rendered``, read back with
``--dump-dom``. A screenshot of each page is saved next to it (and copied to
``$RECTIFY_REPORT_SCREENSHOT_DIR`` when set).
"""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from rectify.geometry.residuals import ResidualTable
from rectify.report.builder import write_report
from stereo.report.pair import write_stereo_report
from tests.support.rectify_support import verify_report

RUN_TIMEOUT_S = 45
FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--disable-extensions", "--disable-default-apps", "--mute-audio", "--hide-scrollbars",
         "--enable-logging=stderr", "--v=0"]
CONSOLE_RE = re.compile(r":CONSOLE[:(]")


@pytest.fixture(scope="session")
def chromium() -> str:
    """Path of the chromium executable; skip with the reason when it is not installed.

    ``.ci/run`` installs Debian's ``chromium`` before the suite; the test never installs anything.
    """
    for name in ("chromium", "chromium-browser"):
        exe = shutil.which(name)
        if exe:
            return exe
    pytest.skip("chromium is not installed (`.ci/run` installs it; or: apt-get install chromium)")


@dataclass
class PageCheck:
    dom: str
    console: list[str]
    images_in_source: int
    images_total: int | None
    images_decoded: int | None
    sections: dict[str, str]
    render_check_done: bool

    @property
    def problems(self) -> list[str]:
        out = [f"console: {c}" for c in self.console]
        if not self.render_check_done:
            out.append("the page's render check did not run")
        if self.images_total != self.images_in_source:
            out.append(f"{self.images_total} images in the DOM, {self.images_in_source} in the file")
        if self.images_decoded != self.images_in_source:
            out.append(f"only {self.images_decoded} of {self.images_in_source} images decoded")
        out += [f"section {s!r} not rendered" for s, r in self.sections.items() if r != "yes"]
        if not self.sections:
            out.append("no sections")
        return out


def _run(exe: str, args: list[str], user_data_dir: Path) -> subprocess.CompletedProcess:
    cmd = [exe, *FLAGS, f"--user-data-dir={user_data_dir}", *args]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)
    try:
        out, err = proc.communicate(timeout=RUN_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)  # the browser we started and its children
        proc.communicate()
        pytest.fail(f"chromium did not finish within {RUN_TIMEOUT_S} s: {' '.join(cmd)}")
    return subprocess.CompletedProcess(cmd, proc.returncode, out, err)


def check_page(exe: str, page: Path, work: Path, screenshot: Path | None = None) -> PageCheck:
    """Load ``page`` in headless Chromium; return what rendered and every console message."""
    url = page.resolve().as_uri()
    r = _run(exe, ["--virtual-time-budget=5000", "--dump-dom", url], work / "profile-dom")
    assert r.returncode == 0, f"chromium failed ({r.returncode}): {r.stderr[-2000:]}"
    dom = r.stdout
    console = [ln for ln in r.stderr.splitlines() if CONSOLE_RE.search(ln)]
    body = re.search(r"<body([^>]*)>", dom)
    attrs = dict(re.findall(r'([\w-]+)="([^"]*)"', body.group(1))) if body else {}
    sections = dict(re.findall(r'<section[^>]*data-section="([^"]+)"[^>]*data-rendered="([^"]+)"', dom))
    src = page.read_text(encoding="utf-8")
    check = PageCheck(dom=dom, console=console, images_in_source=src.count("<img "),
                      images_total=int(attrs["data-images-total"]) if "data-images-total" in attrs else None,
                      images_decoded=int(attrs["data-images-decoded"]) if "data-images-decoded" in attrs else None,
                      sections=sections, render_check_done=attrs.get("data-render-check") == "done")
    if screenshot is not None:
        r2 = _run(exe, ["--window-size=1280,2600", f"--screenshot={screenshot}", url], work / "profile-shot")
        assert r2.returncode == 0 and screenshot.is_file(), f"no screenshot: {r2.stderr[-2000:]}"
        extra = os.environ.get("RECTIFY_REPORT_SCREENSHOT_DIR")
        if extra:
            Path(extra).mkdir(parents=True, exist_ok=True)
            shutil.copy(screenshot, Path(extra) / screenshot.name)
    return check


def assert_screenshot_shows_page(path: Path) -> None:
    from matplotlib.image import imread

    img = imread(path)
    assert img.shape[0] >= 1000 and img.shape[1] >= 1000
    rgb = img[..., :3]
    # the dark header band and plot content: not a blank page
    assert rgb[:40].mean() < 0.5, "header band missing"
    assert rgb.std() > 0.1


# ----------------------------------------------------------------------------- pages under test
def full_report(out: Path) -> Path:
    """A report with every kind of section: 2D fit with check points/outliers/GeoJSON, RO, AO, figures."""
    rng = np.random.default_rng(21)
    n = 60
    pos = rng.uniform(0, [1200, 900], (n, 2))
    obs = pos + rng.normal(0, 0.4, (n, 2))
    out_m = np.zeros(n, bool)
    out_m[[4, 9]] = True
    chk = np.zeros(n, bool)
    chk[10:16] = True
    adj = pos.copy()
    adj[out_m] += 5.0
    gcp = ResidualTable("GCP fit (homography)", [f"P{i}" for i in range(n)], obs, adj, "px", outlier=out_m,
                        check=chk, position_px=pos, n_params=8)
    ground = pos * [30.0, -30.0] + [600000.0, 4500000.0]
    bg = rng.uniform(0, 255, (900, 1200)).astype(np.uint8)
    p1 = write_report(out / "rectify", title="Browser test: rectification", tables=[gcp],
                      summary={"method": "homography", "matrix": np.eye(3)}, crs="EPSG:32618",
                      ground_xy={gcp.step: ground}, backgrounds={gcp.step: bg})
    q = rng.normal(0, 0.004, 40)
    ro = ResidualTable("relative orientation", [f"t{i}" for i in range(40)], q, np.zeros(40), "mm",
                       components=("q",), position_px=rng.uniform(0, [640, 1152], (40, 2)), n_params=5)
    g = rng.uniform([0, 0], [1000, 1000], (7, 2))
    ao_obs = np.column_stack([g, rng.uniform(10, 50, 7)])
    ao = ResidualTable("absolute orientation", [f"G{i}" for i in range(7)], ao_obs,
                       ao_obs + rng.normal(0, 0.3, (7, 3)), "m", components=("dX", "dY", "dZ"), n_params=7)
    c = np.eye(5)
    c[1, 2] = c[2, 1] = 0.85
    p2 = write_stereo_report(out / "stereo", title="Browser test: stereo", relative=ro,
                             correlation=(["tau", "nu", "alpha2", "omega2", "kappa2"], c), absolute=ao,
                             absolute_ground_xy=g, crs="EPSG:32734", left_image_shape=(1152, 640),
                             summary={"sigma0_mm": 0.004})
    return p1, p2


@pytest.fixture(scope="module")
def pages(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    return full_report(tmp_path_factory.mktemp("browser_reports"))


def test_reports_render_in_chromium(chromium: str, pages, tmp_path: Path):
    for page in pages:
        shot = tmp_path / f"screenshot_{page.parent.name}.png"
        res = check_page(chromium, page, tmp_path / f"work_{page.parent.name}", screenshot=shot)
        assert res.problems == [], res.problems
        assert res.images_in_source >= 3
        assert set(res.sections) >= {"overview", "files"}
        assert len([s for s in res.sections if s.startswith("table-")]) >= 1
        assert_screenshot_shows_page(shot)
        assert verify_report(page.parent) == []


def test_checker_catches_broken_page(chromium: str, pages, tmp_path: Path):
    """The same check fails on a page with an undecodable image and a script error."""
    page = pages[0]
    text = page.read_text(encoding="utf-8")
    first = text.index("data:image/png;base64,") + len("data:image/png;base64,")
    broken = text[:first] + "AAAA" + text[first + 40:]
    broken = broken.replace("</main>", "<script>notAFunction();</script></main>")
    bad = tmp_path / "broken.html"
    bad.write_text(broken, encoding="utf-8")
    res = check_page(chromium, bad, tmp_path / "work_bad")
    problems = "\n".join(res.problems)
    assert "notAFunction" in problems
    assert "images failed to decode" in problems
    assert f"only {res.images_in_source - 1} of {res.images_in_source} images decoded" in problems


def _demo_report(group_module: str, tmp_path: Path) -> Path:
    import importlib

    from click.testing import CliRunner

    cli = importlib.import_module(group_module).cli
    assert "demo" in cli.all_commands, f"`{group_module.split('.')[0]} demo` is not registered"
    out = tmp_path / "demo"
    res = CliRunner().invoke(cli, ["demo", "--out", str(out)], catch_exceptions=False)
    assert res.exit_code == 0, res.output
    pages = sorted(out.rglob("report.html"))
    if not pages:
        pytest.fail(f"`{group_module.split('.')[0]} demo` wrote no report.html under {out}")
    return pages[0]


@pytest.mark.slow
@pytest.mark.parametrize("group", ["rectify.cli.main", "stereo.cli.main"])
def test_demo_report_renders(chromium: str, tmp_path: Path, group: str):
    page = _demo_report(group, tmp_path)
    shot = tmp_path / f"screenshot_{group.split('.')[0]}_demo.png"
    res = check_page(chromium, page, tmp_path / "work", screenshot=shot)
    assert res.problems == [], res.problems
    assert_screenshot_shows_page(shot)
    # every number in the demo's HTML matches its CSV and JSON
    assert verify_report(page.parent) == []
