"""The files of one job: inputs, planned outputs, atomic all-or-nothing writes, the report folder.

A :class:`Workspace` is made by an action (``rectify.actions.common``, ``stereo.actions.common``) before any work
starts. It checks every planned output at once (exists without ``overwrite``, folder missing or not
writable, equal to an input), so that bad paths fail in seconds, not after minutes of matching.
"Equal to an input" is judged on the resolved paths (symlinks and ``..`` followed) and, when both
exist, on the file's identity (``st_dev``/``st_ino``: a hard link or a symlink to an input is the
input); the check is made again for every file at the commit.

Outputs written inside :meth:`Workspace.transaction` are staged as hidden temporary files beside
their destinations, and a report (:meth:`Workspace.report_folder`) as a hidden folder beside the
report folder; they are renamed into place together when the block ends without error. On any
error (including ``KeyboardInterrupt`` or ``SystemExit`` from the SIGTERM handler of the commands)
every staged file and folder is removed, and the folders the job created are removed again, so a
command that writes several files writes them all or none.

Readers and writers of the artefacts themselves live in ``rectify.formats`` (one module per file family) and
``stereo.formats``; the ``load_*``/``save_*`` methods of a workspace call them with the workspace's
paths and overwrite policy.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import tempfile
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

from rectify.atomic import (
    apply_umask,
    check_output,
    current_umask,
    make_temp,
    naming_destination,
    raise_if_terminated,
    write_failure_reason,
)
from rectify.errors import CRSError, InvalidInputError, RasterIOError, RectifyError
from rectify.formats.camera import camera_document, read_camera
from rectify.formats.gcps import gcps_text, read_gcps
from rectify.formats.tables import control_text, matches_text, read_control, read_matches
from rectify.formats.transform import TransformFile, read_transform, transform_text
from rectify.geometry.camera import Camera
from rectify.geometry.crs import check_area_of_use, parse_crs
from rectify.geometry.points import ControlTable, GcpTable, Matches
from rectify.geometry.residuals import ResidualTable

__all__ = ["Workspace", "same_file", "check_table_crs"]

StrPath = str | os.PathLike[str]


def same_file(a: StrPath, b: StrPath) -> bool:
    """True when two paths name the same file: the same ``st_dev``/``st_ino`` when both exist (hard links,
    symlinks), else the same resolved path (symlinks and ``..`` followed)."""
    pa, pb = Path(a), Path(b)
    try:
        if pa.exists() and pb.exists():
            return os.path.samefile(pa, pb)
    except OSError:
        pass
    try:
        return pa.resolve() == pb.resolve()
    except (OSError, RuntimeError):  # a symlink loop: compare the absolute paths
        return Path(os.path.abspath(pa)) == Path(os.path.abspath(pb))


class Workspace:
    """The files of one job.

    Parameters
    ----------
    root : path, optional
        Output folder of a job that writes a fixed set of files (``stereo run``, the demos);
        ``None`` for commands whose outputs are named one by one.
    overwrite : bool
        Replace existing outputs (never done without it).
    inputs : iterable of paths
        Files the job reads. An output equal to any of them is refused, even with ``overwrite``.
    report_dir : path, optional
        Folder for the QA report (``--report DIR``), checked for writability before work.
    """

    def __init__(self, root: StrPath | None = None, *, overwrite: bool = False, inputs: Iterable[StrPath] = (),
                 report_dir: StrPath | None = None) -> None:
        self.root = Path(root) if root is not None else None
        self.overwrite = bool(overwrite)
        self.inputs: tuple[Path, ...] = tuple(Path(p) for p in inputs if p is not None)
        self.report_dir = Path(report_dir) if report_dir is not None else None
        self._staged: list[tuple[Path, Path]] | None = None
        self._staged_dirs: list[tuple[Path, Path]] = []  # (hidden staging folder, report folder)
        self._made_dirs: list[Path] = []  # parents of a report folder made for its staging folder (outermost last)
        self._created_root = False
        self._created_top: Path | None = None  # the outermost folder prepare() created (root or an ancestor)

    # ------------------------------------------------------------------ paths
    def path(self, name: str) -> Path:
        """Path of ``name`` inside the output folder."""
        if self.root is None:
            raise InvalidInputError(f"this job has no output folder to hold {name!r}")
        return self.root / name

    def add_inputs(self, *paths: StrPath | None) -> None:
        """Record more input files (outputs equal to them are refused)."""
        self.inputs = self.inputs + tuple(Path(p) for p in paths if p is not None)

    def check_not_input(self, path: StrPath) -> Path:
        """Refuse an output that is one of the job's inputs (even with ``overwrite``): the same resolved path,
        or the same file (``st_dev``/``st_ino``: a hard link, or a symlink to the input)."""
        p = Path(path)
        for i in self.inputs:
            if same_file(p, i):
                same = "" if Path(os.path.abspath(p)) == Path(os.path.abspath(i)) else f" ({str(i)!r})"
                raise InvalidInputError(f"output {str(p)!r} is also an input{same}; an output that is an input is "
                                        "refused (inputs are never modified): choose another output path")
        return p

    def check_output(self, path: StrPath) -> Path:
        """Check one planned output before work: not an input, overwrite policy, folder writable."""
        return check_output(self.check_not_input(path), overwrite=self.overwrite)

    def plan(self, *paths: StrPath | None) -> list[Path]:
        """Check every planned output at once; return them as paths (``None`` entries are skipped).

        Outputs inside a folder the job creates (the output folder, the report folder or a folder
        below them that does not exist yet) are checked against the inputs and for a file in the
        way; the others also for the overwrite policy and a writable folder.
        """
        out = [Path(p) for p in paths if p is not None]
        seen: list[Path] = []
        for p in out:
            if any(same_file(p, q) for q in seen):
                raise InvalidInputError(f"output {str(p)!r} is named twice")
            seen.append(p)
            self.check_not_input(p)
            if not p.parent.exists() and any(d is not None and (d == p.parent or d in p.parents)
                                             for d in (self.root, self.report_dir)):
                _check_creatable(p.parent)  # the job creates the folder; nothing in it exists yet
                continue
            self.check_output(p)
        return out

    def prepare(self, *names: str) -> None:
        """Create the output folder (if any) and check ``names`` inside it and the report folder."""
        if self.root is not None:
            if self.root.exists() and not self.root.is_dir():
                raise InvalidInputError(f"output {str(self.root)!r} exists and is not a folder")
            if not self.root.exists():
                top = self.root
                while not top.parent.exists() and top.parent != top:
                    top = top.parent
                if top.parent.exists() and not top.parent.is_dir():
                    raise InvalidInputError(f"output folder {str(top.parent)!r} is a file")
                try:
                    self.root.mkdir(parents=True)
                except OSError as err:
                    raise RasterIOError(f"cannot create output folder {str(self.root)!r}: {err.strerror}") from err
                self._created_root = True
                self._created_top = top
            for n in names:
                self.check_output(self.root / n)
        self.check_report_dir()

    def check_report_dir(self) -> None:
        """Fail early when the report folder cannot be written."""
        d = self.report_dir
        if d is None:
            return
        if d.exists() and not d.is_dir():
            raise InvalidInputError(f"report folder {str(d)!r} exists and is not a folder")
        probe = d if d.exists() else next((p for p in d.parents if p.exists()), Path("."))
        if not probe.is_dir():
            raise InvalidInputError(f"report folder {str(d)!r} cannot be created: {str(probe)!r} is a file")
        if not os.access(probe, os.W_OK | os.X_OK):
            raise RasterIOError(f"report folder {str(d)!r} is not writable ({str(probe)!r} is read-only)")
        try:  # access() says yes to root even on a read-only mount: try a file
            fd, name = tempfile.mkstemp(prefix=".write-test.", suffix=".part", dir=probe)
            os.close(fd)
            os.unlink(name)
        except OSError as err:
            raise RasterIOError(f"report folder {str(d)!r} is not writable: "
                                f"{write_failure_reason(err, probe / 'x')}") from err

    def discard_root(self) -> None:
        """Remove the output folder if this workspace created it and it is empty (after a failure)."""
        if self._created_root and self.root is not None:
            d = self.root
            with contextlib.suppress(OSError):
                while True:
                    d.rmdir()
                    if d == self._created_top or d.parent == d:
                        break
                    d = d.parent

    # ------------------------------------------------------------------ writing
    @contextlib.contextmanager
    def transaction(self) -> Iterator[Workspace]:
        """Stage every output written inside the block; rename them all into place at its end.

        On any exception (SIGTERM's ``SystemExit`` included) every staged file and report folder is
        removed and the destinations are left as they were; an output folder created by
        :meth:`prepare` is removed again when it is left empty, so are the parents made for a report.
        """
        if self._staged is not None:
            yield self  # nested: the outer transaction commits
            return
        self._staged = []
        self._staged_dirs = []
        try:
            yield self
            raise_if_terminated()  # a SIGTERM swallowed by a callback still stops the commit
            # the commit holds a lock on every destination folder, so two runs writing one output set
            # commit one after the other: the set is all from one run, never a mix
            moves = [(tmp, dst) for tmp, dst in self._staged]
            for stage, final in self._staged_dirs:
                moves += [(stage / f, final / f) for f in _report_files(stage)]
            with _folder_locks([dst.parent for _tmp, dst in self._staged] + [final.parent for _s, final in
                                                                              self._staged_dirs]):
                for _tmp, dst in moves:
                    self.check_not_input(dst)
                    if dst.exists() and not self.overwrite:
                        raise InvalidInputError(f"output {str(dst)!r} appeared while writing; pass --overwrite")
                for tmp, dst in self._staged:
                    try:
                        os.replace(tmp, dst)
                    except OSError as err:
                        raise RasterIOError(f"cannot write {str(dst)!r}: {write_failure_reason(err, dst)}") from err
                for stage, final in self._staged_dirs:
                    _publish_report(stage, final)
        except BaseException:
            self._discard_staged()
            raise
        finally:
            self._staged = None
            self._staged_dirs = []
            self._made_dirs = []

    def _discard_staged(self) -> None:
        """After a failure: remove every staged file and report folder, and the folders made for them."""
        for tmp, _ in self._staged or ():
            with contextlib.suppress(OSError):
                tmp.unlink()
        for stage, _final in self._staged_dirs:
            shutil.rmtree(stage, ignore_errors=True)
        self._staged_dirs = []
        self.discard_root()
        for d in self._made_dirs:  # innermost first
            with contextlib.suppress(OSError):
                d.rmdir()
        self._made_dirs = []

    @contextlib.contextmanager
    def report_folder(self) -> Iterator[Path]:
        """Yield a hidden staging folder to write the report into, in place of :attr:`report_dir`.

        Its files are moved into the report folder when the enclosing :meth:`transaction` commits
        (at once outside one): the report and the other outputs appear together or not at all. The
        report folder (and missing parents) is created then; a report file that exists is replaced
        only with ``overwrite``; files a previous report listed in its ``report.json`` and this one
        does not write are removed.
        """
        final = self.report_dir
        if final is None:
            raise InvalidInputError("this job writes no report (no report folder given)")
        parent = final.parent if str(final.parent) else Path(".")
        made = []
        d = parent
        while not d.exists() and d.parent != d:
            made.append(d)
            d = d.parent
        try:
            parent.mkdir(parents=True, exist_ok=True)
            stage = Path(tempfile.mkdtemp(prefix=f".{final.name}.", suffix=".part", dir=parent))
            os.chmod(stage, 0o777 & ~current_umask())  # mkdtemp makes it private; a report folder is an ordinary one
        except OSError as err:
            for m in made:
                with contextlib.suppress(OSError):
                    m.rmdir()
            raise RasterIOError(f"cannot create the report folder {str(final)!r}: "
                                f"{write_failure_reason(err, parent / 'x')}") from err
        self._made_dirs = self._made_dirs + made
        try:
            yield stage
        except BaseException as err:
            shutil.rmtree(stage, ignore_errors=True)
            if self._staged is None:
                for m in made:
                    with contextlib.suppress(OSError):
                        m.rmdir()
            _reraise_os_error(err, final)
            raise
        if self._staged is not None:
            self._staged_dirs.append((stage, final))
            return
        try:  # outside a transaction: published at once
            raise_if_terminated()
            for f in _report_files(stage):
                self.check_not_input(final / f)
                if (final / f).exists() and not self.overwrite:
                    raise InvalidInputError(f"output {str(final / f)!r} exists; pass --overwrite to replace it")
            _publish_report(stage, final)
        except BaseException:
            shutil.rmtree(stage, ignore_errors=True)
            raise

    @contextlib.contextmanager
    def output(self, path: StrPath, *, suffix: str | None = None) -> Iterator[Path]:
        """Yield a temporary path to write ``path`` through.

        Inside :meth:`transaction` the file is committed with the others at the end of the block;
        outside it, it is renamed into place as soon as the writer returns without error.
        """
        p = self.check_output(path)
        tmp_path = make_temp(p, suffix)
        try:
            yield tmp_path
            apply_umask(tmp_path)
        except BaseException as err:
            with contextlib.suppress(OSError):
                tmp_path.unlink()
            _reraise_os_error(err, p)
            renamed = naming_destination(err, tmp_path, p)   # name the output, not its temporary
            if renamed is not None:
                raise renamed from err
            raise
        if self._staged is not None:
            self._staged.append((tmp_path, p))
            return
        try:
            raise_if_terminated()
            if p.exists() and not self.overwrite:
                raise InvalidInputError(f"output {str(p)!r} appeared while writing; pass --overwrite")
            os.replace(tmp_path, p)
        except BaseException as err:
            with contextlib.suppress(OSError):
                tmp_path.unlink()
            _reraise_os_error(err, p)
            raise

    def write_text(self, path: StrPath, text: str) -> Path:
        """Write ``text`` to ``path`` through :meth:`output`; return the path."""
        with self.output(path) as tmp:
            _write(tmp, text)
        return Path(path)

    def write_json(self, path: StrPath, obj: Any) -> Path:
        """Write ``obj`` as indented JSON through :meth:`output`; return the path."""
        return self.write_text(path, json.dumps(obj, indent=2, allow_nan=False) + "\n")

    # ------------------------------------------------------------------ artefacts (rectify.formats)
    def load_gcps(self, path: StrPath) -> GcpTable:
        """Read a GCP file (an input of the job); its CRS is checked at once (:func:`check_table_crs`)."""
        self.add_inputs(path)
        g = read_gcps(path)
        check_table_crs(path, g.crs, g.target, g.ids)
        return g

    def save_gcps(self, path: StrPath, gcps: GcpTable) -> Path:
        """Write a GCP CSV through :meth:`output`."""
        return self.write_text(path, gcps_text(gcps))

    def load_matches(self, path: StrPath) -> Matches:
        """Read a matches CSV (an input of the job)."""
        self.add_inputs(path)
        return read_matches(path)

    def save_matches(self, path: StrPath, matches: Matches) -> Path:
        """Write a matches CSV through :meth:`output`."""
        return self.write_text(path, matches_text(matches))

    def load_control(self, path: StrPath) -> ControlTable:
        """Read a stereo control CSV (an input of the job)."""
        self.add_inputs(path)
        c = read_control(path)
        check_table_crs(path, c.crs, c.xyz[:, :2], c.ids)
        return c

    def save_control(self, path: StrPath, control: ControlTable) -> Path:
        """Write a stereo control CSV through :meth:`output`."""
        return self.write_text(path, control_text(control))

    def load_camera(self, path: StrPath) -> Camera:
        """Read a camera JSON file (an input of the job)."""
        self.add_inputs(path)
        return read_camera(path)

    def save_camera(self, path: StrPath, camera: Camera) -> Path:
        """Write a camera JSON file through :meth:`output`."""
        return self.write_json(path, camera_document(camera))

    def load_transform(self, path: StrPath) -> TransformFile:
        """Read a transform JSON file (an input of the job): the model, its CRS and residuals."""
        self.add_inputs(path)
        tf = read_transform(path)
        check_table_crs(path, tf.crs, None)
        return tf

    def save_transform(self, path: StrPath, model: Any, *, table: ResidualTable | None = None,
                       crs: str | None = None, extra: dict[str, Any] | None = None) -> Path:
        """Write a transform JSON file through :meth:`output` (:func:`rectify.formats.transform.transform_document`)."""
        return self.write_text(path, transform_text(model, table=table, crs=crs, extra=extra))


@contextlib.contextmanager
def _folder_locks(folders: Iterable[Path]) -> Iterator[None]:
    """Hold an exclusive ``flock`` on each folder (in a fixed order); a no-op where flock is missing."""
    try:
        import fcntl  # local: POSIX only; without it the folders are not locked
    except ImportError:  # not POSIX
        yield
        return
    fds: list[int] = []
    try:
        for d in sorted({(f if str(f) else Path(".")).resolve() for f in folders}):
            try:
                fd = os.open(d, os.O_RDONLY)
            except OSError:
                continue
            fds.append(fd)
            fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        for fd in reversed(fds):
            with contextlib.suppress(OSError):
                fcntl.flock(fd, fcntl.LOCK_UN)
            os.close(fd)


def check_table_crs(path: StrPath, crs: str | None, xy: Any, ids: Any = None) -> None:
    """Check the CRS of a file when it is read, before any work: it exists (PROJ knows it) and the
    coordinates ``xy`` (N, 2) can be in it (:func:`rectify.geometry.crs.check_area_of_use`; NaN rows skipped).

    Raises
    ------
    CRSError
        Naming the file, the CRS and the first offending point.
    """
    if crs is None:
        return
    try:
        parse_crs(crs)
        if xy is not None:
            check_area_of_use(crs, xy, ids)
    except CRSError as err:
        raise CRSError(f"{str(path)!r}: {err}") from err


def _check_creatable(folder: Path) -> None:
    """A folder the job will create: its nearest existing ancestor must be a writable folder."""
    probe = next((p for p in folder.parents if p.exists()), Path("."))
    if not probe.is_dir():
        raise InvalidInputError(f"output folder {str(folder)!r} cannot be created: {str(probe)!r} is a file")
    if not os.access(probe, os.W_OK | os.X_OK):
        raise RasterIOError(f"output folder {str(folder)!r} cannot be created: {str(probe)!r} is not writable")


def _report_files(stage: Path) -> list[str]:
    """The files of a staged report (relative paths, sorted; ``report.html`` last: a reader of the folder
    never sees a page whose files are missing)."""
    files = sorted(p.relative_to(stage).as_posix() for p in stage.rglob("*") if not p.is_dir())
    return sorted(files, key=lambda f: f == "report.html")


def _publish_report(stage: Path, final: Path) -> None:
    """Move a staged report into its folder (one rename when the folder is new); remove the files a previous
    report listed and this one does not write."""
    try:
        if not final.exists():
            os.rename(stage, final)
            return
        previous: list[str] = []
        with contextlib.suppress(OSError, ValueError, TypeError, AttributeError):
            listed = json.loads((final / "report.json").read_text(encoding="utf-8")).get("files", [])
            previous = [str(f) for f in listed]
        files = _report_files(stage)
        for f in files:
            (final / f).parent.mkdir(parents=True, exist_ok=True)
            os.replace(stage / f, final / f)
        for f in previous:
            if f not in files and "/" not in f and not f.startswith(".") and (final / f).is_file():
                with contextlib.suppress(OSError):
                    (final / f).unlink()
        shutil.rmtree(stage, ignore_errors=True)
    except OSError as err:
        raise RasterIOError(f"cannot move the report into {str(final)!r}: {write_failure_reason(err, final)}") from err


def _write(tmp: Path, text: str) -> None:
    with open(tmp, "w", encoding="utf-8") as fh:
        fh.write(text)
        fh.flush()
        os.fsync(fh.fileno())


def _reraise_os_error(err: BaseException, dst: Path) -> None:
    """An OSError that is not a project error becomes a one-line RasterIOError naming ``dst`` and the reason."""
    if isinstance(err, OSError) and not isinstance(err, RectifyError):
        raise RasterIOError(f"cannot write {str(dst)!r}: {write_failure_reason(err, dst)}") from err
