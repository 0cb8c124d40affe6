"""The web server's defence against connection floods: a header deadline, a connection cap, a descriptor reserve.

The token protects the car only once a request's headers have arrived. A client that opens connections and never
finishes a request ("slowloris") is never asked for it, and each such connection holds one of the process's file
descriptors: 1024 on Debian and Raspberry Pi OS. When they run out, the driver's next connection cannot be
accepted and the tub writer cannot open the files it records to. :class:`ConnectionGuard` accepts the
connections itself (a listening socket of its own) and hands each to aiohttp's protocol with
``loop.connect_accepted_socket`` (and the TLS handshake, for HTTPS), so it sees every TCP connection from the
moment it is accepted, before any byte is parsed, and decides whether to accept at all:

* **Header deadline.** A connection that has not presented the access token on a request within
  ``header_timeout_s`` of its arrival (slow or missing headers, a TLS handshake that never ends) is closed.
* **Connection cap.** At most ``max_connections`` at a time.
* **Descriptor reserve.** No connection is kept that would leave fewer than ``reserve_fds`` descriptors free
  below the process's ``RLIMIT_NOFILE`` soft limit: those are the car's own (recordings, logs, devices).

When a new connection would break the cap or the reserve, connections that have not been admitted yet (no token
seen) are closed to make room, oldest first: an old one that still has not sent its headers is the flood, a new
one may be the driver coming back. Admitted connections (the driver's WebSocket, a viewer's video) are never
closed by the guard. When nothing can be closed to make room, the guard stops accepting: new connections wait in
the kernel's queue (``backlog``), holding none of the car's descriptors, until a connection ends or descriptors
are freed (checked every ``ROOM_POLL_S``). A client without the token gets its 401 and the connection closes
(:mod:`.auth`), so it cannot hold a descriptor either.

Counting open descriptors means listing ``/proc/self/fd`` (about 0.5 ms with a thousand open), so the guard
does it sparingly (:class:`FdBudget`): at most once a second while far from the limit, every 50 ms when the
estimate comes within twice the reserve of it, and in between it adds its own connections to the last count.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import logging
import math
import os
import socket
import ssl
import sys
from collections.abc import Callable
from typing import Any

from aiohttp import web

from ...ratelimit import LogThrottle
from .auth import WebConfigError

try:
    import resource
except ImportError:  # pragma: no cover - Windows: no RLIMIT_NOFILE to keep a reserve below
    resource = None  # type: ignore[assignment]

__all__ = [
    "DEFAULT_BACKLOG",
    "DEFAULT_HEADER_TIMEOUT_S",
    "DEFAULT_MAX_CONNECTIONS",
    "DEFAULT_RESERVE_FDS",
    "ConnectionGuard",
    "FdBudget",
    "open_fd_count",
]

logger = logging.getLogger(__name__)

DEFAULT_HEADER_TIMEOUT_S = 5.0
DEFAULT_MAX_CONNECTIONS = 100
DEFAULT_RESERVE_FDS = 128
DEFAULT_BACKLOG = 32
#: how often a guard that stopped accepting (no room, nothing to shed) looks again at the descriptor count
ROOM_POLL_S = 0.5

#: accept() errors that mean "no resources now": wait and try again rather than stop serving
_OUT_OF_RESOURCES = {errno.EMFILE, errno.ENFILE, errno.ENOBUFS, errno.ENOMEM}

_FD_DIRS = ("/proc/self/fd", "/dev/fd")


def open_fd_count() -> int | None:
    """The process's open file descriptors, or ``None`` where the system cannot list them.

    Raises ``OSError`` (``EMFILE``) when not even the listing can be opened: no descriptor is free.
    """
    for path in _FD_DIRS:
        try:
            return len(os.listdir(path)) - 1  # the listing's own descriptor
        except (FileNotFoundError, NotADirectoryError):
            continue
    return None


def soft_fd_limit() -> int | None:
    """The ``RLIMIT_NOFILE`` soft limit in force now (``None``: unlimited). Read each time: it may be lowered."""
    if resource is None:  # pragma: no cover
        return None
    soft = resource.getrlimit(resource.RLIMIT_NOFILE)[0]
    return None if soft == resource.RLIM_INFINITY else int(soft)


class FdBudget:
    """How many descriptors the process can still open, counted sparingly (see the module docstring).

    Args:
        counter: counts the open descriptors (``None``: cannot; ``OSError``: none free).
        limit: the soft limit now (``None``: unlimited).
        recount_after_s: the longest an estimate is trusted while far from the limit.
        near: within this many descriptors of the limit, the count is redone every ``near_every_s``: often enough
            for the car's own files (a few a tick) to stay well inside the reserve, seldom enough that a flood
            of connections does not turn into a flood of directory listings.
    """

    def __init__(
        self,
        counter: Callable[[], int | None] = open_fd_count,
        limit: Callable[[], int | None] = soft_fd_limit,
        recount_after_s: float = 1.0,
        near: int = 256,
        near_every_s: float = 0.05,
    ) -> None:
        self._counter = counter
        self._limit = limit
        self.recount_after_s = recount_after_s
        self.near = near
        self.near_every_s = near_every_s
        self._others = 0  # descriptors that are not tracked connections, at the last count
        self._counted_at: float | None = None
        self.counts = 0

    def free(self, now: float, tracked: int) -> int:
        """Descriptors left below the soft limit, ``tracked`` of the open ones being the guard's connections."""
        limit = self._limit()
        if limit is None:
            return sys.maxsize
        estimate = self._others + tracked
        age = math.inf if self._counted_at is None else now - self._counted_at
        if age > self.recount_after_s or (limit - estimate < self.near and age >= self.near_every_s):
            try:
                counted = self._counter()
            except OSError:
                return 0
            self.counts += 1
            if counted is not None:
                self._others = counted - tracked
                self._counted_at = now
                estimate = counted
        return limit - estimate


class _Connection(asyncio.Protocol):
    """One accepted TCP connection: the guard's record of it, in front of aiohttp's protocol for it.

    Made when the socket is accepted; its deadline runs from then. ``connect_accepted_socket`` calls
    :meth:`connection_made` once the transport exists (for HTTPS, after the handshake), which attaches aiohttp's
    request handler; from then on every protocol call is forwarded to it unchanged.
    """

    def __init__(self, guard: ConnectionGuard, sock: socket.socket, now: float) -> None:
        self.guard = guard
        self.accepted_at = now
        self.transport: asyncio.BaseTransport | None = None
        self.handler: Any = None  # aiohttp's RequestHandler once attached
        self.admitted = False
        self.closed = False
        self._sock: socket.socket | None = sock  # ours until connect_accepted_socket takes it
        self._deadline: asyncio.TimerHandle | None = guard.loop.call_later(guard.header_timeout_s, self._on_deadline)
        self._setup: asyncio.Task[None] | None = guard.loop.create_task(self._connect())

    async def _connect(self) -> None:
        sock, self._sock = self._sock, None
        assert sock is not None
        guard = self.guard
        tls = guard.ssl_context
        try:
            await guard.loop.connect_accepted_socket(
                lambda: self,
                sock,
                ssl=tls,
                ssl_handshake_timeout=guard.header_timeout_s if tls is not None else None,
            )
        except Exception:  # a failed TLS handshake (bad client, reset, timeout): the transport closed the socket
            self.closed = True
            guard.forget(self)
        finally:
            self._setup = None

    # --------------------------------------------------------------------------- the guard's side
    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = transport
        if self.closed:
            transport.abort()  # type: ignore[attr-defined]
            return
        self.handler = self.guard.new_handler(self)
        self.handler.connection_made(transport)

    def admit(self) -> None:
        """A request on this connection presented the token: it is the car's user, never to be shed."""
        self.admitted = True
        if self._deadline is not None:
            self._deadline.cancel()
            self._deadline = None

    def close(self) -> None:
        """Drop the connection now (no reply: it never sent a request worth one)."""
        if self.closed:
            return
        self.closed = True
        if self._deadline is not None:
            self._deadline.cancel()
            self._deadline = None
        if self.transport is not None:
            self.transport.abort()  # type: ignore[attr-defined]
        elif self._sock is not None:  # the setup task has not run yet: it never will
            self._sock.close()
            self._sock = None
            if self._setup is not None:
                self._setup.cancel()
        elif self._setup is not None:  # in the TLS handshake: cancelling closes the transport
            self._setup.cancel()

    def _on_deadline(self) -> None:
        self._deadline = None
        if not self.admitted and not self.closed:
            self.guard.timed_out += 1
            self.guard.forget(self)
            self.close()

    # --------------------------------------------------------------------------- forwarded to aiohttp
    def data_received(self, data: bytes) -> None:
        if self.handler is not None:
            self.handler.data_received(data)

    def eof_received(self) -> bool | None:
        if self.handler is not None:
            return self.handler.eof_received()  # type: ignore[no-any-return]
        return None

    def pause_writing(self) -> None:
        if self.handler is not None:
            self.handler.pause_writing()

    def resume_writing(self) -> None:
        if self.handler is not None:
            self.handler.resume_writing()

    def connection_lost(self, exc: BaseException | None) -> None:
        self.closed = True
        if self._deadline is not None:
            self._deadline.cancel()
            self._deadline = None
        self.guard.forget(self)
        handler, self.handler = self.handler, None
        if handler is not None:
            handler.connection_lost(exc)


class ConnectionGuard:
    """Admission control for the web server's connections (see the module docstring).

    Args:
        header_timeout_s: a connection that has not presented the token within this time is closed.
        max_connections: connections open at once, admitted or not.
        reserve_fds: descriptors kept free for the rest of the car below the ``RLIMIT_NOFILE`` soft limit.
        budget: the descriptor count (tests give their own).

    Counters: ``accepted`` (connections kept on arrival), ``refused`` (closed on arrival: no room and none to
    shed), ``shed`` (unadmitted ones closed to make room), ``timed_out`` (closed at the header deadline),
    ``paused`` (times the guard stopped accepting for want of room).
    """

    def __init__(
        self,
        header_timeout_s: float = DEFAULT_HEADER_TIMEOUT_S,
        max_connections: int = DEFAULT_MAX_CONNECTIONS,
        reserve_fds: int = DEFAULT_RESERVE_FDS,
        *,
        budget: FdBudget | None = None,
    ) -> None:
        check_limits(header_timeout_s, max_connections, reserve_fds)
        self.header_timeout_s = float(header_timeout_s)
        self.max_connections = int(max_connections)
        self.reserve_fds = int(reserve_fds)
        self.budget = budget if budget is not None else FdBudget(near=2 * self.reserve_fds + 64)
        self.accepted = 0
        self.refused = 0
        self.shed = 0
        self.timed_out = 0
        self.paused = 0
        self.ssl_context: ssl.SSLContext | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._server: Callable[[], Any] | None = None
        self._open: dict[_Connection, None] = {}  # in order of arrival: the oldest are shed first
        self._handlers: dict[Any, _Connection] = {}
        self._listeners: list[socket.socket] = []
        self._acceptors: list[asyncio.Task[None]] = []
        self._room: asyncio.Event | None = None
        self._log = LogThrottle(5.0)

    @property
    def loop(self) -> asyncio.AbstractEventLoop:
        assert self._loop is not None, "ConnectionGuard: start() first"
        return self._loop

    # --------------------------------------------------------------------------- serving
    async def start(
        self,
        server: Callable[[], Any],
        host: str,
        port: int,
        *,
        backlog: int = DEFAULT_BACKLOG,
        ssl_context: ssl.SSLContext | None = None,
    ) -> list[Any]:
        """Listen on ``host:port`` and serve the connections it admits with ``server`` (aiohttp's
        ``runner.server``: a factory of request handlers). Returns the bound addresses (``port`` 0 picks one).

        Raises ``OSError`` when the address cannot be bound.
        """
        self._loop = asyncio.get_running_loop()
        self._server = server
        self.ssl_context = ssl_context
        self._room = asyncio.Event()
        self._listeners = await _listening_sockets(host, port, backlog)
        self._acceptors = [
            self.loop.create_task(self._accept_loop(sock), name=f"web accept {sock.getsockname()}")
            for sock in self._listeners
        ]
        self.check_room()
        return [sock.getsockname() for sock in self._listeners]

    async def stop(self) -> None:
        """Stop listening and drop the connections not handed to aiohttp yet (aiohttp closes its own)."""
        for task in self._acceptors:
            task.cancel()
        await asyncio.gather(*self._acceptors, return_exceptions=True)
        self._acceptors = []
        for sock in self._listeners:
            sock.close()
        self._listeners = []
        for conn in list(self._open):
            if conn.handler is None:
                self.forget(conn)
                conn.close()

    async def _accept_loop(self, listener: socket.socket) -> None:
        """Accept while there is room (or a connection to shed for it); otherwise leave newcomers in the kernel's
        queue. The room is checked before each accept, so a connection is never accepted only to be refused."""
        loop = self.loop
        while True:
            if self._shortfall(loop.time(), coming=1) > self._sheddable():
                await self._wait_for_room()
                continue
            try:
                sock, _ = listener.accept()
            except (BlockingIOError, InterruptedError):
                await self._readable(listener)
                continue
            except OSError as exc:
                if exc.errno in _OUT_OF_RESOURCES:  # the rest of the car took the last descriptors
                    self._warn(loop.time(), f"accept failed: {exc}")
                    await asyncio.sleep(ROOM_POLL_S)
                continue  # or the client gave up before we accepted it
            sock.setblocking(False)
            self.take(sock)
            await asyncio.sleep(0)  # a burst of connections must not hold the loop (the car's ticks run on it)

    async def _readable(self, listener: socket.socket) -> None:
        """Until a connection waits to be accepted."""
        loop = self.loop
        ready = loop.create_future()
        try:
            loop.add_reader(listener.fileno(), lambda: ready.done() or ready.set_result(None))
        except NotImplementedError:  # pragma: no cover - Windows' proactor loop: look again soon
            await asyncio.sleep(0.02)
            return
        try:
            await ready
        finally:
            loop.remove_reader(listener.fileno())

    async def _wait_for_room(self) -> None:
        """Until a connection ends, or ``ROOM_POLL_S`` (the car may have closed files of its own)."""
        room = self._room
        assert room is not None
        self.paused += 1
        self._warn(self.loop.time(), "no room: not accepting")
        room.clear()
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(room.wait(), ROOM_POLL_S)

    def new_handler(self, conn: _Connection) -> Any:
        """aiohttp's protocol for ``conn``, remembered so a request can be traced back to its connection."""
        assert self._server is not None
        handler = self._server()
        self._handlers[handler] = conn
        return handler

    def admit(self, request: web.Request) -> None:
        """The request presented the token: its connection is never shed nor timed out (from :class:`.Access`)."""
        conn = self._handlers.get(request.protocol)
        if conn is not None and not conn.admitted:
            conn.admit()

    # --------------------------------------------------------------------------- admission
    @property
    def open(self) -> int:
        return len(self._open)

    @property
    def admitted(self) -> int:
        return sum(1 for c in self._open if c.admitted)

    def counters(self) -> dict[str, int]:
        """For ``/status``: connections now and what the guard did since the server started."""
        return {
            "open": self.open,
            "admitted": self.admitted,
            "accepted": self.accepted,
            "refused": self.refused,
            "shed": self.shed,
            "timed_out": self.timed_out,
            "paused": self.paused,
        }

    def take(self, sock: socket.socket) -> _Connection | None:
        """Keep the just-accepted ``sock`` if there is room, making room by shedding unadmitted connections;
        else close it. Returns the connection kept."""
        now = self.loop.time()
        conn = _Connection(self, sock, now)
        self._open[conn] = None
        need = self._shortfall(now, coming=0)
        if need > 0:
            victims = [c for c in self._open if not c.admitted and c is not conn][:need]
            for victim in victims:
                self.shed += 1
                self.forget(victim)
                victim.close()
            self._warn(now, "shedding connections without the token")
            if len(victims) < need:
                self.refused += 1
                self.forget(conn)
                conn.close()
                return None
        self.accepted += 1
        return conn

    def forget(self, conn: _Connection) -> None:
        if conn in self._open:
            del self._open[conn]
            if self._room is not None:
                self._room.set()  # an accept loop waiting for room may go on
        if conn.handler is not None:
            self._handlers.pop(conn.handler, None)

    def _sheddable(self) -> int:
        return sum(1 for c in self._open if not c.admitted)

    def _shortfall(self, now: float, coming: int) -> int:
        """How many connections must go to keep one more (``coming`` = 1: not accepted yet) under the cap and
        above the reserve."""
        over_cap = len(self._open) + coming - self.max_connections
        over_reserve = self.reserve_fds - (self.budget.free(now, len(self._open)) - coming)
        return max(over_cap, over_reserve, 0)

    def _warn(self, now: float, what: str) -> None:
        held = self._log.ready("full", now, "times")
        if held is not None:
            logger.warning(
                "web: %s (%d connections open, %d with the token; cap %d, %d descriptors kept for the car): a "
                "client may be opening connections without completing requests%s",
                what,
                self.open,
                self.admitted,
                self.max_connections,
                self.reserve_fds,
                held,
            )

    def check_room(self) -> None:
        """Log once at start when the descriptor reserve leaves the server (almost) no room at all."""
        free = self.budget.free(self.loop.time(), len(self._open))
        if free - self.reserve_fds < 8:
            logger.warning(
                "web: only %d file descriptors free below the limit (ulimit -n) and %d kept for the car: the web "
                "controller will refuse connections; raise the limit or lower reserve_fds",
                free,
                self.reserve_fds,
            )


async def _listening_sockets(host: str, port: int, backlog: int) -> list[socket.socket]:
    """Bound, listening, non-blocking sockets for ``host:port``, as ``loop.create_server`` makes them (every
    address the host resolves to; ``""`` every interface; IPv6 sockets IPv6-only; ``SO_REUSEADDR``)."""
    loop = asyncio.get_running_loop()
    infos = await loop.getaddrinfo(
        host or None, port, family=socket.AF_UNSPEC, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE
    )
    socks: list[socket.socket] = []
    try:
        for family, type_, proto, _, address in dict.fromkeys(infos):
            sock = socket.socket(family, type_, proto)
            socks.append(sock)
            if os.name == "posix":
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            if family == socket.AF_INET6 and hasattr(socket, "IPPROTO_IPV6"):
                sock.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_V6ONLY, 1)
            sock.bind(address)
            sock.listen(backlog)
            sock.setblocking(False)
    except OSError:
        for sock in socks:
            sock.close()
        raise
    return socks


def check_limits(header_timeout_s: float, max_connections: int, reserve_fds: int, backlog: int = 1) -> None:
    """Raise :class:`.WebConfigError` for limits that cannot work (the message names the setting)."""
    if not (isinstance(header_timeout_s, int | float) and header_timeout_s > 0 and math.isfinite(header_timeout_s)):
        raise WebConfigError(f"WebController: header_timeout_s must be a positive number, got {header_timeout_s!r}")
    for name, value, least in (("max_connections", max_connections, 1), ("reserve_fds", reserve_fds, 0)):
        if not (isinstance(value, int) and not isinstance(value, bool) and value >= least):
            raise WebConfigError(f"WebController: {name} must be a whole number >= {least}, got {value!r}")
    if not (isinstance(backlog, int) and not isinstance(backlog, bool) and backlog >= 1):
        raise WebConfigError(f"WebController: backlog must be a whole number >= 1, got {backlog!r}")
