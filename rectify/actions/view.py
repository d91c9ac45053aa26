"""``rectify view`` / ``stereo view``: a step's results in the browser, served on 127.0.0.1 or written as a
static folder (docs/view.md).

:func:`start_view` scans the folder, builds the answers and binds the server (it does not serve yet: the
command prints the address, opens the browser and then calls :meth:`ViewSession.serve_forever`);
:func:`export_view` writes the static folder instead.
"""

from __future__ import annotations

import threading
import webbrowser
from dataclasses import dataclass
from pathlib import Path

from rectify.actions.common import Progress
from rectify.actions.workspace import Workspace
from rectify.errors import InvalidInputError
from rectify.raster.io import bound_gdal_cache
from rectify.view.data import ViewData
from rectify.view.export import MAX_STATIC_TILES, StaticExport, write_static
from rectify.view.folder import scan
from rectify.view.server import ViewApp, ViewServer

#: GDAL's block cache of the server, MB (the memory bound of docs/view.md rests on it)
VIEW_GDAL_CACHE_MB = 48


@dataclass(frozen=True)
class ViewOptions:
    """Options of the view: the port (0: any free one), the folders of a block's photos, the static tile budget."""

    port: int = 0
    images: tuple[str, ...] = ()
    max_static_tiles: int = MAX_STATIC_TILES

    def __post_init__(self) -> None:
        if not 0 <= int(self.port) <= 65535:
            raise InvalidInputError(f"--port must be 0..65535; got {self.port}")
        if int(self.max_static_tiles) < 1:
            raise InvalidInputError(f"--max-tiles must be >= 1; got {self.max_static_tiles}")


def _app(outdir: str | Path, options: ViewOptions) -> ViewApp:
    bound_gdal_cache(VIEW_GDAL_CACHE_MB)
    app = ViewApp(ViewData(scan(outdir, tuple(options.images))))
    app.manifest()  # read the folder's summary files now: a broken file fails before the server starts
    return app


def _describe(app: ViewApp) -> str:
    m = app.manifest()
    rasters = sum(1 for r in m["rasters"] if r["role"] != "photo")
    photos = sum(1 for im in m["images"] if im["raster"] is not None)
    return (f"{m['title']}: {m['kind']}; {len(m['images'])} images ({photos} photos found), {rasters} rasters, "
            f"{len(m['tables'])} residual tables, {len(m['figures'])} report figures")


@dataclass(frozen=True, eq=False)
class ViewSession:
    """A bound (not yet serving) view server: :meth:`serve_forever` serves until :meth:`close`."""

    server: ViewServer
    folder: Path

    @property
    def url(self) -> str:
        return self.server.url

    def summary_lines(self) -> list[str]:
        """What is shown, and where."""
        return [_describe(self.server.app), f"serving {self.url} (127.0.0.1 only; Ctrl-C stops)"]

    def serve_forever(self) -> None:
        self.server.serve_forever(poll_interval=0.2)

    def open_browser(self, delay_s: float = 0.3) -> None:
        """Open the page in the user's browser shortly after serving starts (a background timer)."""
        threading.Timer(delay_s, webbrowser.open, args=(self.url,)).start()

    def close(self) -> None:
        """Stop serving (from another thread) and release the port."""
        self.server.shutdown()
        self.server.server_close()


def start_view(outdir: str | Path, options: ViewOptions = ViewOptions()) -> ViewSession:
    """Scan ``outdir``, read its summary files and bind the server on 127.0.0.1 (``options.port``); the
    previews of the result rasters are read in a background thread meanwhile (the first coarse tiles need
    them)."""
    app = _app(outdir, options)
    server = ViewServer(app, options.port)
    threading.Thread(target=app.data.warm_up, name="view-warm-up", daemon=True).start()
    return ViewSession(server, app.data.contents.root)


@dataclass(frozen=True, eq=False)
class StaticViewRun:
    """Result of :func:`export_view`."""

    export: StaticExport
    description: str
    note: str

    def summary_lines(self) -> list[str]:
        e = self.export
        return [self.description, f"static view: {e.files} files ({e.tiles} tiles, {e.bytes / 2**20:.1f} MiB)",
                self.note, f"wrote {e.path} (serve it with any web server, e.g. python3 -m http.server -d "
                           f"{e.path} -b 127.0.0.1)"]


def export_view(ws: Workspace, outdir: str | Path, dest: str | Path, options: ViewOptions = ViewOptions(), *,
                progress: Progress = None) -> StaticViewRun:
    """Write the view of ``outdir`` as a static folder ``dest`` (nothing at ``dest`` on failure)."""
    app = _app(outdir, options)
    ex = write_static(app, dest, overwrite=ws.overwrite, max_tiles=options.max_static_tiles, progress=progress)
    note = str(app.manifest().get("static", {}) or "")
    m = app.manifest()
    rasters = [r for r in m["rasters"] if "max_level" in r]
    lacking = [r["label"] for r in rasters if ex.levels.get(r["id"], 0) < r["max_level"]]
    note = (f"not at full resolution (tile budget {options.max_static_tiles}): {', '.join(lacking[:5])}"
            + (f" and {len(lacking) - 5} more" if len(lacking) > 5 else "")) if lacking else \
        "every raster at full resolution"
    return StaticViewRun(ex, _describe(app), note)
