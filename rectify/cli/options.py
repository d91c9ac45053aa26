"""Options and helpers shared by every command of ``rectify`` and ``stereo``.

A command parses its arguments, calls one library function, prints a short
summary and maps :class:`~rectify.errors.RectifyError` to a click error (exit 1).
"""

from __future__ import annotations

import contextlib
import functools
import importlib
import importlib.machinery
import importlib.util
import io
import logging
import os
import signal
import sys
import warnings
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import click

from rectify.atomic import note_termination, raise_if_terminated, terminated, write_failure_reason
from rectify.errors import RectifyError, RectifyWarning, SchedulerError

__all__ = ["overwrite_opt", "output_opts", "verbosity_opts", "report_opt", "scheduler_opt", "handle_errors", "progress",
           "setup_logging", "VerbosityGroup", "subcommand_verbosity_params"]

overwrite_opt = click.option("--overwrite", is_flag=True, default=False,
                             help="Replace existing outputs (never done without it).")
report_opt = click.option("--report", "report_dir", type=click.Path(file_okay=False), default=None,
                          help="Write residual tables, plots and an HTML report into this folder.")


def output_opts(compressions: Sequence[str], jpeg_quality: int, *,
                jpeg_note: str = "") -> Callable[[Callable], Callable]:
    """``--cog``, ``--compress`` and ``--jpeg-quality`` of the commands writing orthophotos and mosaics (the
    choices and default quality from the output tail, :mod:`rectify.raster.engine`); ``jpeg_note`` adds
    the command's own limits of JPEG to the help."""
    def deco(f: Callable) -> Callable:
        f = click.option("--jpeg-quality", type=int, default=jpeg_quality, show_default=True,
                         help="JPEG quality 1..100 (--compress jpeg).")(f)
        f = click.option("--compress", type=click.Choice(list(compressions)), default="zstd", show_default=True,
                         help="Output compression: lossless zstd/deflate/lzw (predictor, nodata kept) or none; jpeg: "
                              "JPEG-in-TIFF (YCbCr for RGB) with an internal mask band, 8-bit images only"
                              + jpeg_note + ".")(f)
        return click.option("--cog", is_flag=True, default=False,
                            help="Write a Cloud Optimized GeoTIFF (internal overviews).")(f)
    return deco


def _check_scheduler(ctx: click.Context, param: click.Parameter, value: str | None) -> str | None:
    """Check --scheduler at parse time, before any work: a bad value is refused (exit 2, one line); a cluster
    address must answer as a Dask scheduler with a worker within the bounds of
    :func:`rectify.raster.distributed.check_scheduler` (else exit 1, one line). A scheduler taken from
    $RECTIFY_SCHEDULER is checked by the command itself."""
    if ctx.resilient_parsing:
        return value
    # local: rasterio (imported by the raster wing) must load after cli.main's defer_import("boto3")
    from rectify.raster.distributed import check_scheduler, follow_cli_logging

    follow_cli_logging()  # Dask's own log lines only with -v
    if value is None:
        return None

    try:
        check_scheduler(value)
    except SchedulerError as err:
        raise click.ClickException(f"{type(err).__name__}: {err}") from err
    except RectifyError as err:
        raise click.BadParameter(str(err), ctx=ctx, param=param) from err
    return value


scheduler_opt = click.option(
    "--scheduler", default=None, metavar="threads|processes[:N]|tcp://HOST:PORT", callback=_check_scheduler,
    help="Where the tiles run: local threads (default), N local Dask worker processes, or an existing Dask "
         "cluster; default from $RECTIFY_SCHEDULER, else threads. Every choice writes the same pixels. A cluster "
         "must answer as a Dask scheduler with a worker: bounds from $RECTIFY_SCHEDULER_TIMEOUT (10 s), "
         "$RECTIFY_SCHEDULER_WORKER_TIMEOUT (60 s), $RECTIFY_SCHEDULER_STALL_TIMEOUT (600 s).")


def setup_logging(verbose: int, quiet: int) -> None:
    """Set up a command's process: log level from -v/-q, library warnings, SIGTERM.

    The root log level is WARNING by default, lowered by each -v and raised by each -q. Warnings of
    the libraries (rasterio's ``NotGeoreferencedWarning`` on a plain photo, ...) are shown only with
    -v. SIGTERM (``timeout``, a batch scheduler) raises ``SystemExit(143)`` in the main thread, so
    that temporary files and half-written outputs are removed as on any other error.
    """
    level = logging.WARNING - 10 * verbose + 10 * quiet
    _native_stderr(shown=verbose > 0)
    logging.basicConfig(level=max(level, logging.DEBUG), format="%(levelname)s %(name)s: %(message)s",
                        stream=sys.stderr, force=True)
    if verbose <= 0:
        _hide_library_warnings()
    install_sigterm_handler()


_SAVED_STDERR_FD: list[int] = []   # the process's standard error, kept while fd 2 is silenced


def _native_stderr(*, shown: bool) -> None:
    """Silence what C libraries write straight to file descriptor 2 unless -v (libtiff's
    ``_tiffWriteProc: No space left on device.`` before our one-line error, GDAL's default handler in
    threads without rasterio's): fd 2 goes to the null device, and Python's ``sys.stderr`` (our messages,
    logging, tracebacks) to a copy of the original descriptor. Only in a real process whose ``sys.stderr``
    is fd 2 (not under click's test runner or a capturing test harness); -v restores fd 2."""
    if shown:
        if _SAVED_STDERR_FD:
            sys.stderr.flush()
            os.dup2(_SAVED_STDERR_FD[0], 2)
        return
    if _SAVED_STDERR_FD:
        return
    try:
        if sys.stderr is None or sys.stderr.fileno() != 2:
            return
    except (AttributeError, OSError, ValueError, io.UnsupportedOperation):
        return
    sys.stderr.flush()
    saved = os.dup(2)
    os.set_inheritable(saved, False)
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, 2)
    os.close(devnull)
    _SAVED_STDERR_FD.append(saved)
    enc = getattr(sys.stderr, "encoding", None) or "utf-8"
    sys.stderr = io.TextIOWrapper(io.FileIO(saved, "w", closefd=False), encoding=enc, errors="backslashreplace",
                                  line_buffering=True, write_through=True)


def _hide_library_warnings() -> None:
    """Hide third-party warnings (rasterio, GDAL, numpy, matplotlib); the project's own stay visible."""
    warnings.filterwarnings("ignore")
    warnings.filterwarnings("default", category=RectifyWarning)
    logging.getLogger("rasterio").setLevel(logging.ERROR)


def _sigterm(signum: int, frame: Any) -> None:
    # recorded first: when the SystemExit is swallowed (raised inside a gc callback of Dask's), the commit of
    # every output raises it again, and the command's end turns the record into the exit status
    note_termination(signum)
    raise SystemExit(128 + signum)


def _unraisable(hook_args: Any) -> None:
    """Python's report of an exception it had to drop, but silent for the SIGTERM exit: the handler's
    ``SystemExit`` raised inside a callback (Dask's gc diagnostics) is not an error to print; the record
    of :func:`rectify.atomic.note_termination` carries it on to the exit status."""
    if isinstance(hook_args.exc_value, SystemExit) and terminated():
        return
    _DEFAULT_UNRAISABLE(hook_args)


_DEFAULT_UNRAISABLE = sys.unraisablehook


def install_sigterm_handler() -> None:
    """Turn SIGTERM into ``SystemExit(143)`` (cleanup runs); a no-op outside the main thread.

    The signal is also recorded (:func:`rectify.atomic.note_termination`): outputs are not committed after
    it even when the ``SystemExit`` was swallowed, and the command's end exits 143 then.
    """
    with contextlib.suppress(ValueError, AttributeError):
        signal.signal(signal.SIGTERM, _sigterm)
        sys.unraisablehook = _unraisable


def verbosity_opts(f: Callable) -> Callable:
    """Add -v/--verbose and -q/--quiet (counted) to a click group."""
    f = click.option("-q", "--quiet", count=True, help="Less output (repeatable).")(f)
    f = click.option("-v", "--verbose", count=True, help="More output (repeatable).")(f)
    return f


def matcher_opts(defaults: Any) -> Callable[[Callable], Callable]:
    """--detector, --verify, --refine/--no-refine, --max-matches, --max-keypoints (choices from the library,
    defaults shown from ``defaults``, a :class:`rectify.features.MatcherConfig`); the command gets them as
    keyword arguments of those names (None for the two counts when not given)."""
    # local: the matcher (OpenCV's features) loads only for the commands that match
    from rectify.features import DETECTORS, VERIFY_METHODS

    d = defaults

    def deco(f: Callable) -> Callable:
        for opt in reversed([
            click.option("--detector", type=click.Choice(list(DETECTORS)), default=d.detector, show_default=True,
                         help="Keypoint detector."),
            click.option("--verify", type=click.Choice(list(VERIFY_METHODS)), default=d.verify,
                         show_default=True, help="Geometric verification of the matches (OpenCV USAC MAGSAC++)."),
            click.option("--refine/--no-refine", default=d.refine, show_default=True,
                         help="Least-squares matching refinement of the positions."),
            click.option("--max-matches", type=click.IntRange(1), default=None,
                         help=f"At most this many matches, spread evenly (default {d.max_matches})."),
            click.option("--max-keypoints", type=click.IntRange(1), default=None,
                         help=f"Keypoints kept per image (per tile for large images; default {d.max_keypoints})."),
        ]):
            f = opt(f)
        return f

    return deco


def _add_verbosity(ctx: click.Context, param: click.Parameter, value: int) -> None:
    """-v/-q given after the subcommand: add to the group's counts and set the logging up again."""
    if not value:
        return
    root = ctx.find_root()
    if not isinstance(root.obj, dict):
        root.obj = {"verbose": 0, "quiet": 0}
    root.obj[param.name or ""] = int(root.obj.get(param.name or "", 0)) + int(value)
    setup_logging(int(root.obj.get("verbose", 0)), int(root.obj.get("quiet", 0)))


def subcommand_verbosity_params() -> list[click.Parameter]:
    """-v/--verbose and -q/--quiet for a subcommand: they count together with the group's own."""
    return [click.Option(["-v", "--verbose"], count=True, expose_value=False, callback=_add_verbosity,
                         help="More output (repeatable; also accepted before the subcommand)."),
            click.Option(["-q", "--quiet"], count=True, expose_value=False, callback=_add_verbosity,
                         help="Less output (repeatable; also accepted before the subcommand).")]


class VerbosityGroup(click.Group):
    """A click group whose subcommands take -v/-q too, so that ``rectify -v warp ...`` and
    ``rectify warp ... -v`` do the same (the counts add up).

    Subcommands are registered by name and ``"module:attribute"`` (:meth:`add_lazy`) and imported
    only when they run (or when the group's help lists them): ``rectify match`` does not pay for
    the imports of the orthophoto or mosaic code."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._lazy: dict[str, str] = {}

    def add_command(self, cmd: click.Command, name: str | None = None) -> None:
        taken = {o for p in cmd.params for o in getattr(p, "opts", [])}
        if not taken & {"-v", "--verbose", "-q", "--quiet"}:
            cmd.params.extend(subcommand_verbosity_params())
        super().add_command(cmd, name)

    def add_lazy(self, name: str, target: str) -> None:
        """Register the subcommand ``name`` as ``"package.module:attribute"``, imported on first use."""
        self._lazy[name] = target

    def list_commands(self, ctx: click.Context) -> list[str]:
        return sorted({*self._lazy, *super().list_commands(ctx)})

    def invoke(self, ctx: click.Context) -> Any:
        result = super().invoke(ctx)
        raise_if_terminated()  # SIGTERM arrived but its SystemExit was swallowed: still exit 143
        return result

    def get_command(self, ctx: click.Context, cmd_name: str) -> click.Command | None:
        target = self._lazy.get(cmd_name)
        if target is not None and cmd_name not in self.commands:
            module, attr = target.split(":")
            self.add_command(getattr(importlib.import_module(module), attr), cmd_name)
        return super().get_command(ctx, cmd_name)

    @property
    def all_commands(self) -> dict[str, click.Command]:
        """Every subcommand by name (imports the lazy ones)."""
        ctx = click.Context(self)
        out = {}
        for name in self.list_commands(ctx):
            cmd = self.get_command(ctx, name)
            if cmd is not None:
                out[name] = cmd
        return out


def defer_import(name: str) -> None:
    """Make the first ``import name`` of this process lazy: the module runs on first attribute access.

    For optional modules that a dependency imports eagerly but a command rarely uses (rasterio
    imports boto3, when installed, for its AWS sessions: 0.1-0.2 s at every start). A finder put
    first on ``sys.meta_path`` wraps the module's loader in the standard library's
    :class:`importlib.util.LazyLoader`; no-op when the module is already imported."""
    if name in sys.modules or any(isinstance(f, _LazyFinder) and f.name == name for f in sys.meta_path):
        return
    sys.meta_path.insert(0, _LazyFinder(name))


class _LazyFinder:
    """A meta-path finder that gives one module (by exact name) a lazy loader."""

    def __init__(self, name: str) -> None:
        self.name = name

    def find_spec(self, fullname: str, path: Any = None, target: Any = None) -> Any:
        if fullname != self.name:
            return None
        spec = importlib.machinery.PathFinder.find_spec(fullname, path)
        if spec is None or spec.loader is None:
            return None
        spec.loader = importlib.util.LazyLoader(spec.loader)
        return spec


def handle_errors(f: Callable) -> Callable:
    """Map project errors to ``click.ClickException`` (message, exit code 1)."""

    @functools.wraps(f)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return f(*args, **kwargs)
        except RectifyError as err:
            raise click.ClickException(f"{type(err).__name__}: {err}") from err
        except OSError as err:  # a file-system failure the library did not wrap: one line (traceback with -v)
            if _verbose_level() > 0:
                raise
            where = f" {err.filename!r}" if getattr(err, "filename", None) else ""
            raise click.ClickException(f"{type(err).__name__}:{where} {write_failure_reason(err, err.filename)}"
                                       ) from err

    return wrapper


@contextlib.contextmanager
def progress(label: str, *, enabled: bool = True) -> Iterator[Callable[[int, int], None]]:
    """Yield a ``callback(done, total)`` that drives a click progress bar on stderr.

    Library functions take such callbacks as ``progress=``; the bar shows only
    on a terminal and when ``enabled``.
    """
    show = enabled and sys.stderr.isatty()
    bar = None
    state = {"done": 0}

    def cb(done: int, total: int) -> None:
        nonlocal bar
        if not show:
            return
        if bar is None:
            bar = click.progressbar(length=total, label=label, file=sys.stderr)
            bar.__enter__()
        bar.update(done - state["done"])
        state["done"] = done

    try:
        yield cb
    finally:
        if bar is not None:
            bar.__exit__(None, None, None)


def _verbose_level() -> int:
    """The -v count of the current click context's root (0 when outside click)."""
    ctx = click.get_current_context(silent=True)
    while ctx is not None and ctx.parent is not None:
        ctx = ctx.parent
    return int((ctx.obj or {}).get("verbose", 0)) if ctx is not None else 0


def quiet_level() -> int:
    """The -q count less the -v count of the current click context's root (0 when outside click)."""
    ctx = click.get_current_context(silent=True)
    while ctx is not None and ctx.parent is not None:
        ctx = ctx.parent
    if ctx is None or not isinstance(ctx.obj, dict):
        return 0
    return max(int(ctx.obj.get("quiet", 0)) - int(ctx.obj.get("verbose", 0)), 0)


def echo(msg: str = "", *, err: bool = False) -> None:
    """Print unless -q was given."""
    if quiet_level() == 0:
        click.echo(msg, err=err)
