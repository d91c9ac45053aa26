"""Who answers at a Dask scheduler address: checked on a plain socket, with bounded waits and reads.

``distributed.Client`` trusts its peer: it waits for the peer's handshake without a time limit (a
server that accepts and never answers hangs it) and allocates whatever length the first 8 bytes it
reads announce (an HTTP server's ``HTTP/1.1`` is a length of 3.5e18 bytes: Dask tries to allocate
3.07 EiB). So before Dask connects, :func:`identify` speaks the opening of Dask's TCP protocol
itself:

1. connect (refused connections are retried until the deadline, as Dask does: a scheduler may be
   starting);
2. send Dask's handshake and read the peer's: a message announced by its 8-byte length (at most
   :data:`MAX_MESSAGE_BYTES`, else the peer is not Dask), a frame table, and a msgpack map with
   Dask's handshake keys;
3. ask for the peer's ``identity`` (``n_workers=0``: totals only, a small reply) and require
   ``type == "Scheduler"`` (a worker's or a nanny's port answers too, as something else);
4. say ``close`` and close the socket.

Every wait shares one deadline (``timeout_s``); no buffer is sized by the peer beyond
:data:`MAX_MESSAGE_BYTES`; msgpack is decoded without Dask's hooks, so nothing the peer sends is
unpickled. :func:`wait_for_workers` repeats :func:`identify` until the scheduler has a worker.

Wire format (``distributed/comm/tcp.py``): ``uint64 n`` then ``n`` bytes holding ``uint64 frames``,
``frames`` times ``uint64 length``, then the frames; a plain message is one msgpack frame. Integers
are little-endian (Dask writes them in the machine's order; every platform it supports is
little-endian).
"""

from __future__ import annotations

import contextlib
import re
import socket
import struct
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from rectify.errors import InvalidInputError, SchedulerError

__all__ = ["MAX_MESSAGE_BYTES", "SchedulerIdentity", "split_address", "identify", "wait_for_workers"]

#: the largest message the check accepts from a peer (a handshake is about 80 bytes, an identity with
#: ``n_workers=0`` a few hundred)
MAX_MESSAGE_BYTES = 1 << 20
#: the largest answer to a plain ``identity`` accepted (an older scheduler lists every worker: about 1 kB each)
MAX_IDENTITY_BYTES = 16 << 20
#: frames a checked message may have (plain messages have one)
MAX_FRAMES = 64
#: keys of Dask's handshake message (``distributed.comm.core.Comm.handshake_info``)
HANDSHAKE_KEYS = ("compression", "python", "pickle-protocol")
#: pickle protocol offered in our handshake (the scheduler never pickles what it sends to this check)
PICKLE_PROTOCOL = 5

_ADDRESS = re.compile(r"^tcp://(?P<host>\[[0-9A-Fa-f:.]+\]|[^\s/:\[\]@?#]+):(?P<port>\d{1,5})/?$")


@dataclass(frozen=True)
class SchedulerIdentity:
    """What a Dask scheduler says of itself.

    Attributes
    ----------
    address : str
        The address asked (``tcp://HOST:PORT``).
    n_workers : int
        Workers connected to it.
    total_threads : int
        Their threads (task slots); 0 when the scheduler does not say.
    """

    address: str
    n_workers: int
    total_threads: int


def split_address(address: str, *, source: str = "scheduler") -> tuple[str, int]:
    """``tcp://HOST:PORT`` -> (host, port); IPv6 hosts in brackets (``tcp://[::1]:8786``).

    Raises
    ------
    InvalidInputError
        Another scheme, no port, a port outside 1..65535 (one line naming ``source`` and the value).

    Examples
    --------
    >>> split_address("tcp://10.0.0.5:8786")
    ('10.0.0.5', 8786)
    >>> split_address("tcp://[::1]:8786")
    ('::1', 8786)
    >>> split_address("tcp://127.0.0.1")
    Traceback (most recent call last):
    ...
    rectify.errors.InvalidInputError: bad scheduler address 'tcp://127.0.0.1': no port; expected tcp://HOST:PORT
    """
    s = str(address).strip()
    scheme = s.split("://", 1)[0].lower() if "://" in s else ""
    if scheme and scheme != "tcp":
        raise InvalidInputError(f"bad {source} address {s!r}: only tcp:// schedulers are supported; expected "
                                "tcp://HOST:PORT")
    m = _ADDRESS.match(s)
    if m is None:
        rest = s.split("://", 1)[-1].rstrip("/")
        if rest and re.fullmatch(r"\[[0-9A-Fa-f:.]+\]|[^\s/:\[\]@?#]+", rest):
            raise InvalidInputError(f"bad {source} address {s!r}: no port; expected tcp://HOST:PORT")
        raise InvalidInputError(f"bad {source} address {s!r}; expected tcp://HOST:PORT")
    port = int(m["port"])
    if not 1 <= port <= 65535:
        raise InvalidInputError(f"bad {source} address {s!r}: port {port} is outside 1..65535")
    return m["host"].strip("[]"), port


def identify(address: str, timeout_s: float, *, env_var: str = "") -> SchedulerIdentity:
    """Connect to ``address``, check that a Dask scheduler answers, return what it says of itself.

    Parameters
    ----------
    address : str
        ``tcp://HOST:PORT``.
    timeout_s : float
        Seconds for the whole exchange (connect, handshake, identity).
    env_var : str
        The setting of ``timeout_s``, named in the messages (e.g. ``$RECTIFY_SCHEDULER_TIMEOUT``).

    Raises
    ------
    SchedulerError
        Nothing listening within ``timeout_s``; a peer that does not answer in time; a peer that
        does not speak Dask's protocol, or answers as something other than a scheduler. One line
        naming the address (and the timeout where one ran out).
    """
    host, port = split_address(address)
    deadline = time.monotonic() + timeout_s
    within = f"within {timeout_s:g} s" + (f" ({env_var})" if env_var else "")
    sock = _connect(address, host, port, deadline, within)
    try:
        peer = _Peer(sock, address, deadline, within)
        peer.send({"compression": None, "python": tuple(sys.version_info)[:3], "pickle-protocol": PICKLE_PROTOCOL})
        hello = peer.receive("Dask handshake")
        if not (isinstance(hello, dict) and all(k in hello for k in HANDSHAKE_KEYS)):
            raise SchedulerError(f"{address!r} is not a Dask scheduler: its first message is not a Dask handshake "
                                 f"({_describe(hello)})")
        peer.send({"op": "identity", "n_workers": 0, "reply": True})
        ident = peer.receive("answer to 'identity'")
        if _refused_argument(ident, "n_workers"):
            # a worker or a nanny (or a scheduler older than identity(n_workers=)): ask plainly, which a
            # scheduler answers with every worker's description
            peer.send({"op": "identity", "reply": True})
            ident = peer.receive("answer to 'identity'", limit=MAX_IDENTITY_BYTES)
        kind = ident.get("type") if isinstance(ident, dict) else None
        if kind != "Scheduler":
            what = f"a Dask {kind}" if isinstance(kind, str) and kind else f"a Dask peer ({_describe(ident)})"
            raise SchedulerError(f"{address!r} is not a Dask scheduler: it answers as {what}")
        with contextlib.suppress(OSError):
            peer.send({"op": "close", "reply": False})
    finally:
        with contextlib.suppress(OSError):
            sock.close()
    n_workers = ident.get("n_workers")
    if not isinstance(n_workers, int):
        workers = ident.get("workers")
        n_workers = len(workers) if isinstance(workers, dict) else 0
    threads = ident.get("total_threads")
    return SchedulerIdentity(address, max(int(n_workers), 0), int(threads) if isinstance(threads, int) else 0)


def wait_for_workers(address: str, timeout_s: float, worker_timeout_s: float, *, timeout_var: str = "",
                     worker_var: str = "", sleep: Callable[[float], None] = time.sleep) -> SchedulerIdentity:
    """:func:`identify` until the scheduler has at least one worker, for at most ``worker_timeout_s``.

    Raises
    ------
    SchedulerError
        As :func:`identify`; or no worker within ``worker_timeout_s`` (named with ``worker_var``).
    """
    deadline = time.monotonic() + worker_timeout_s
    while True:
        ident = identify(address, timeout_s, env_var=timeout_var)
        if ident.n_workers > 0:
            return ident
        left = deadline - time.monotonic()
        if left <= 0:
            raise SchedulerError(f"the Dask scheduler {address!r} has no workers: none joined within "
                                 f"{worker_timeout_s:g} s" + (f" ({worker_var})" if worker_var else ""))
        sleep(min(0.5, left))


# --------------------------------------------------------------------------- the exchange
def _connect(address: str, host: str, port: int, deadline: float, within: str) -> socket.socket:
    """A connected socket; refused connections retried until ``deadline`` (a scheduler may be starting)."""
    last: OSError | None = None
    pause = 0.05
    while True:
        left = deadline - time.monotonic()
        if left <= 0:
            reason = _reason(last) if last is not None else "timed out"
            raise SchedulerError(f"cannot reach the Dask scheduler {address!r} {within}: {reason}")
        try:
            return socket.create_connection((host, port), timeout=left)
        except socket.gaierror as err:  # a name that does not resolve will not start resolving
            raise SchedulerError(f"cannot reach the Dask scheduler {address!r}: unknown host {host!r} "
                                 f"({_reason(err)})") from err
        except OSError as err:  # refused (nothing listening yet), unreachable, timed out: retried until the deadline
            last = err
            time.sleep(max(0.0, min(pause, deadline - time.monotonic())))
            pause = min(2 * pause, 0.5)


class _Peer:
    """Messages over one socket, each wait bounded by the shared deadline."""

    def __init__(self, sock: socket.socket, address: str, deadline: float, within: str):
        self.sock, self.address, self.deadline, self.within = sock, address, deadline, within

    def _left(self, what: str) -> float:
        """Seconds left; past the deadline, the error: ``what`` did not happen in time."""
        left = self.deadline - time.monotonic()
        if left <= 0:
            raise SchedulerError(f"the peer at {self.address!r} {what} {self.within}; is it a Dask scheduler?")
        return left

    def send(self, msg: dict[str, Any]) -> None:
        frame = _msgpack().packb(msg, use_bin_type=True)
        data = struct.pack("<QQQ", 16 + len(frame), 1, len(frame)) + frame
        self.sock.settimeout(self._left("took no data"))
        try:
            self.sock.sendall(data)
        except TimeoutError as err:
            raise SchedulerError(f"the peer at {self.address!r} took no data {self.within}; is it a Dask "
                                 "scheduler?") from err
        except OSError as err:
            raise SchedulerError(f"the peer at {self.address!r} closed the connection ({_reason(err)}); is it a "
                                 "Dask scheduler?") from err

    def _read(self, n: int, what: str) -> bytes:
        buf = bytearray()
        while len(buf) < n:
            self.sock.settimeout(self._left(f"sent no {what}"))
            try:
                chunk = self.sock.recv(min(n - len(buf), 65536))
            except TimeoutError:
                continue  # the deadline check of the next round names what was missing
            except OSError as err:
                raise SchedulerError(f"the peer at {self.address!r} closed the connection before its {what} "
                                     f"({_reason(err)}); is it a Dask scheduler?") from err
            if not chunk:
                seen = f" after sending {bytes(buf[:32])!r}" if buf else ""
                raise SchedulerError(f"the peer at {self.address!r} closed the connection before its {what}{seen}; "
                                     "is it a Dask scheduler?")
            buf += chunk
        return bytes(buf)

    def receive(self, what: str, *, limit: int = MAX_MESSAGE_BYTES) -> Any:
        """One message: a length (bounded), a frame table, a msgpack frame decoded without hooks."""
        head = self._read(8, what)
        (size,) = struct.unpack("<Q", head)
        if not 16 <= size <= limit:
            raise SchedulerError(f"{self.address!r} is not a Dask scheduler: where a {what} was expected it sent "
                                 f"{head!r} (read as a Dask message length: {size} bytes, outside 16..{limit})")
        body = self._read(size, what)
        (n_frames,) = struct.unpack_from("<Q", body)
        if not 1 <= n_frames <= MAX_FRAMES or 8 * (1 + n_frames) > size:
            raise SchedulerError(f"{self.address!r} is not a Dask scheduler: a message of {size} bytes announces "
                                 f"{n_frames} frames")
        lengths = struct.unpack_from(f"<{n_frames}Q", body, 8)
        start = 8 * (1 + n_frames)
        if lengths[0] > size - start:
            raise SchedulerError(f"{self.address!r} is not a Dask scheduler: a frame of {lengths[0]} bytes in a "
                                 f"message of {size}")
        if sum(lengths) > size - start:  # frames sent after the message: a reply this check never asks for
            raise SchedulerError(f"{self.address!r} sent its {what} with {sum(lengths)} bytes of frames beyond "
                                 "its message; not a Dask scheduler this check understands")
        frame = body[start:start + lengths[0]]
        try:
            return _msgpack().unpackb(frame, raw=False, strict_map_key=False, use_list=True)
        except (ValueError, TypeError) as err:  # msgpack's errors are ValueErrors; unhashable keys TypeErrors
            raise SchedulerError(f"{self.address!r} is not a Dask scheduler: its {what} is not a msgpack message "
                                 f"({_reason(err)})") from err


def _msgpack() -> Any:
    """The msgpack package (a dependency of dask.distributed), loaded when a scheduler is checked."""
    import msgpack  # local: needed only when a Dask cluster is used; dask.distributed depends on it

    return msgpack


def _refused_argument(reply: Any, name: str) -> bool:
    """A Dask error reply saying that the handler took no argument ``name``."""
    return isinstance(reply, dict) and reply.get("status") in ("error", "uncaught-error") \
        and name in str(reply.get("exception_text", ""))


def _describe(obj: Any) -> str:
    if isinstance(obj, dict):
        keys = ", ".join(repr(k) for k in list(obj)[:6])
        return f"a map of {len(obj)} keys: {keys}" if obj else "an empty map"
    text = repr(obj)
    return f"{type(obj).__name__} {text[:40]}{'...' if len(text) > 40 else ''}"


def _reason(err: BaseException) -> str:
    if isinstance(err, OSError) and err.strerror:
        return err.strerror.lower()
    text = " ".join(str(err).split())
    return text or type(err).__name__
