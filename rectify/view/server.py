"""The local HTTP server of ``rectify view``: one result folder, on 127.0.0.1 only, read-only.

Routes (GET and HEAD; anything else 405), the same names as the files of a static export
(:mod:`rectify.view.export`), so the page works unchanged on both:

- ``/`` and ``/index.html``: the page; ``/static/<name>``: its own files (those of the package only);
- ``/api/manifest.json``, ``/api/layout.json``, ``/api/obs/<i>.json``, ``/api/tracks/<b>.json``,
  ``/api/table/<t>.json``, ``/api/raster/<r>.json``: the answers of :class:`rectify.view.data.ViewData`;
- ``/tiles/<r>/<level>/<x>_<y>.png``: a tile of raster number ``r`` (rasters are named by number only);
- ``/files/<path>``: a result file of a served kind, through :func:`rectify.view.folder.resolve_inside`.

Every other path is 404; a path outside the folder (``..``, an absolute path, a symlink out, in any
percent-encoding: the URL path is decoded once, then checked) or a kind not served is 403. Requests whose
``Host`` header names another host than the loopback address and port are refused (403), so a web page
elsewhere cannot reach the server through a DNS name rebound to 127.0.0.1.
"""

from __future__ import annotations

import json
import logging
import re
import threading
from dataclasses import dataclass
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from pathlib import Path
from typing import Any
from urllib.parse import unquote, urlsplit

from rectify.errors import InvalidInputError, RectifyError
from rectify.view.data import ViewData
from rectify.view.folder import Refused, resolve_inside

log = logging.getLogger(__name__)

#: the only address the server binds to
LOOPBACK = "127.0.0.1"
CONTENT_TYPES = {".html": "text/html; charset=utf-8", ".js": "text/javascript; charset=utf-8",
                 ".css": "text/css; charset=utf-8", ".json": "application/json", ".png": "image/png",
                 ".jpg": "image/jpeg", ".jpeg": "image/jpeg", ".svg": "image/svg+xml",
                 ".csv": "text/csv; charset=utf-8", ".geojson": "application/geo+json",
                 ".md": "text/markdown; charset=utf-8", ".txt": "text/plain; charset=utf-8"}
#: the page's content security policy: nothing from anywhere but the server itself
PAGE_CSP = ("default-src 'self'; img-src 'self' data: blob:; style-src 'self'; script-src 'self'; "
            "connect-src 'self'; frame-ancestors 'none'; base-uri 'none'; form-action 'none'")
_TILE = re.compile(r"^tiles/(\d{1,6})/(\d{1,2})/(\d{1,7})_(\d{1,7})\.png$")
_API = re.compile(r"^api/(obs|tracks|table|raster)/(\d{1,9})\.json$")


def static_files() -> dict[str, bytes]:
    """The page's own files (``rectify/view/static/``), by name."""
    out = {}
    for f in resources.files("rectify.view").joinpath("static").iterdir():
        if f.is_file() and not f.name.startswith("."):
            out[f.name] = f.read_bytes()
    return out


@dataclass(frozen=True)
class Response:
    """One answer: HTTP status, content type and body."""

    status: int
    content_type: str
    body: bytes

    @classmethod
    def json(cls, obj: Any) -> Response:
        return cls(200, CONTENT_TYPES[".json"], json.dumps(obj, separators=(",", ":"), allow_nan=False).encode())

    @classmethod
    def error(cls, status: int, reason: str) -> Response:
        return cls(status, CONTENT_TYPES[".txt"], (reason + "\n").encode())


class ViewApp:
    """The answers of the view for one folder, by request path (no networking: the handler and the static
    export both call :meth:`respond`).

    Parameters
    ----------
    data : ViewData
    """

    def __init__(self, data: ViewData) -> None:
        self.data = data
        self.static = static_files()
        self._manifest: dict[str, Any] | None = None
        self._lock = threading.Lock()

    def manifest(self) -> dict[str, Any]:
        """The manifest (built once)."""
        with self._lock:
            if self._manifest is None:
                self._manifest = self.data.manifest()
            return self._manifest

    def respond(self, raw_path: str) -> Response:
        """The answer to a GET of ``raw_path`` (the request target: a URL path and an optional query)."""
        try:
            path = unquote(urlsplit(raw_path).path, errors="strict")
        except UnicodeDecodeError:
            return Response.error(400, "the path is not UTF-8")
        if not path.startswith("/"):
            return Response.error(400, "the request target must be a path")
        rel = path[1:]
        try:
            return self._route(rel)
        except Refused as err:
            return Response.error(err.status, str(err))
        except InvalidInputError as err:
            return Response.error(404, str(err))
        except RectifyError as err:
            log.warning("view: %s: %s", rel, err)
            return Response.error(500, f"{type(err).__name__}: {err}")
        except (ValueError, TypeError, KeyError, IndexError, OSError) as err:  # a malformed result file
            log.warning("view: %s: %s: %s", rel, type(err).__name__, err)
            log.debug("view: %s", rel, exc_info=True)
            return Response.error(500, f"cannot answer {rel!r}: {type(err).__name__}: {err}")

    def _route(self, rel: str) -> Response:
        if rel in ("", "index.html"):
            return Response(200, CONTENT_TYPES[".html"], self.static["index.html"])
        if rel.startswith("static/"):
            name = rel[len("static/"):]
            if name not in self.static or name.startswith("."):
                raise Refused(404, f"no page file {name!r}")
            return Response(200, CONTENT_TYPES.get(Path(name).suffix, "application/octet-stream"), self.static[name])
        if rel == "api/manifest.json":
            return Response.json(self.manifest())
        if rel == "api/layout.json":
            return Response.json(self.data.layout())
        m = _API.match(rel)
        if m:
            kind, n = m.group(1), int(m.group(2))
            if kind == "obs":
                return Response.json(self.data.image_observations(n))
            if kind == "tracks":
                return Response.json(self.data.track_bucket(n, self.manifest()["n_buckets"]))
            if kind == "raster":
                return Response.json(self.data.raster_info(n))
            return Response.json(self.data.table(n))
        m = _TILE.match(rel)
        if m:
            r, z, x, y = (int(g) for g in m.groups())
            return Response(200, "image/png", self.data.source(r).tile_png(z, x, y))
        if rel.startswith("files/"):
            f = resolve_inside(self.data.contents.root, rel[len("files/"):])
            return Response(200, CONTENT_TYPES.get(f.suffix.lower(), "application/octet-stream"), f.read_bytes())
        raise Refused(404, f"no such page {rel!r}")


def _handler(app: ViewApp) -> type[BaseHTTPRequestHandler]:
    class Handler(BaseHTTPRequestHandler):
        server_version = "rectify-view"
        sys_version = ""

        def _allowed_host(self) -> bool:
            host = (self.headers.get("Host") or "").strip().lower()
            port = self.server.server_address[1]  # type: ignore[index]  # an (host, port) AF_INET address
            return host in (f"{LOOPBACK}:{port}", f"localhost:{port}", LOOPBACK, "localhost")

        def _send(self, head_only: bool) -> None:
            if not self._allowed_host():
                res = Response.error(403, "the Host header must name the loopback address")
            else:
                res = app.respond(self.path)
            self.send_response(res.status)
            self.send_header("Content-Type", res.content_type)
            self.send_header("Content-Length", str(len(res.body)))
            self.send_header("X-Content-Type-Options", "nosniff")
            self.send_header("Cache-Control", "max-age=3600" if self.path.startswith("/tiles/") else "no-store")
            if res.content_type.startswith("text/html") and self.path.split("?")[0] in ("/", "/index.html"):
                self.send_header("Content-Security-Policy", PAGE_CSP)
            self.end_headers()
            if not head_only:
                self.wfile.write(res.body)

        def do_GET(self) -> None:  # noqa: N802 (the name http.server calls)
            self._send(False)

        def do_HEAD(self) -> None:  # noqa: N802
            self._send(True)

        def _refuse_method(self) -> None:
            body = b"only GET and HEAD\n"
            self.send_response(405)
            self.send_header("Allow", "GET, HEAD")
            self.send_header("Content-Type", CONTENT_TYPES[".txt"])
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

        do_POST = do_PUT = do_DELETE = do_PATCH = do_OPTIONS = _refuse_method  # noqa: N815

        def log_message(self, format: str, *args: Any) -> None:  # noqa: A002 (http.server's name)
            log.debug("view: " + format, *args)

    return Handler


class ViewServer(ThreadingHTTPServer):
    """A threading HTTP server of one :class:`ViewApp`, bound to 127.0.0.1 (``port`` 0: any free port).

    Raises
    ------
    InvalidInputError
        The port is taken or not allowed.
    """

    daemon_threads = True
    allow_reuse_address = True

    def __init__(self, app: ViewApp, port: int = 0) -> None:
        self.app = app
        try:
            super().__init__((LOOPBACK, int(port)), _handler(app))
        except OSError as err:
            raise InvalidInputError(f"cannot listen on {LOOPBACK}:{port}: {err.strerror or err}") from None

    @property
    def url(self) -> str:
        """The page's address."""
        host, port = self.server_address[:2]
        return f"http://{host!s}:{port}/"
