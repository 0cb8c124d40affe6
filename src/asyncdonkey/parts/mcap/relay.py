"""A TCP relay in front of foxglove-sdk's WebSocket server that accepts both names of Foxglove's subprotocol.

Foxglove's WebSocket protocol was named ``foxglove.websocket.v1``; foxglove-sdk 0.30 and later name the same
protocol ``foxglove.sdk.v1`` and answer a client that offers only the old name with HTTP 400. Older Foxglove
Studio versions and Lichtblick (its community fork) offer only the old name, and the SDK's server has no option
to accept it. :class:`SubprotocolRelay` listens on the public address, the SDK's server on a loopback port, and
each connection is relayed with one change, in the opening handshake only:

* the client's ``Sec-WebSocket-Protocol`` offer gets ``foxglove.sdk.v1`` added when it offers
  ``foxglove.websocket.v1`` without it;
* the server's choice in the ``101 Switching Protocols`` answer is then renamed back to the name the client
  offered (a WebSocket client refuses a protocol it did not offer).

Nothing else is touched: ``Sec-WebSocket-Accept`` depends only on the client's key, the frames after the
handshake are spliced byte for byte. The two names denote the same protocol (Foxglove says so, and the SDK's
server speaks it to either kind of client).

The relay runs on a thread of its own with its own selector, never on the car's event loop, and is bounded:

* ``max_connections`` open connections; one more is answered ``503`` and closed;
* ``handshake_timeout_s`` from accepting a connection to forwarding the server's answer, and ``max_head`` bytes
  for either side's HTTP head: a client that connects and says nothing cannot hold a slot;
* ``buffer_limit`` bytes waiting per direction: when the client reads slower than the server writes, the relay
  stops reading from the server, the socket fills and the SDK's per-client queue drops old messages (as it does
  for a slow client connected directly). The relay never buffers without bound.
"""

from __future__ import annotations

import contextlib
import errno
import logging
import os
import selectors
import socket
import threading
import time
from dataclasses import dataclass
from typing import Any

__all__ = ["NEW_SUBPROTOCOL", "OLD_SUBPROTOCOL", "RelayStats", "SubprotocolRelay"]

logger = logging.getLogger(__name__)

OLD_SUBPROTOCOL = "foxglove.websocket.v1"
NEW_SUBPROTOCOL = "foxglove.sdk.v1"
_HEADER = b"sec-websocket-protocol"
_END = b"\r\n\r\n"
_BUSY = b"HTTP/1.1 503 Service Unavailable\r\nContent-Length: 0\r\nConnection: close\r\n\r\n"
_TOO_BIG = b"HTTP/1.1 431 Request Header Fields Too Large\r\nContent-Length: 0\r\nConnection: close\r\n\r\n"
_RW = selectors.EVENT_READ | selectors.EVENT_WRITE


@dataclass
class RelayStats:
    """Counters of a :class:`SubprotocolRelay` (written by its thread, read by anyone)."""

    accepted: int = 0
    """connections relayed (handshake started)"""
    refused: int = 0
    """connections answered 503: ``max_connections`` were open"""
    timed_out: int = 0
    """connections closed because their handshake took longer than ``handshake_timeout_s``"""
    renamed: int = 0
    """handshakes where the client offered only the old subprotocol name"""
    to_server: int = 0
    """bytes relayed from clients to the server"""
    to_clients: int = 0
    """bytes relayed from the server to clients"""
    cpu_s: float = 0.0
    """CPU time of the relay's thread, known once it has stopped"""


def rewrite_request(head: bytes) -> tuple[bytes, bool]:
    """The client's HTTP head with ``foxglove.sdk.v1`` added to a ``Sec-WebSocket-Protocol`` offer that names
    only ``foxglove.websocket.v1``; and whether it was added (the answer must then be renamed back)."""
    lines = head.split(b"\r\n")
    offered: list[str] = []
    at = None
    for i, line in enumerate(lines[1:], start=1):
        name, sep, value = line.partition(b":")
        if sep and name.strip().lower() == _HEADER:
            offered += [t.strip() for t in value.decode("latin-1").split(",")]
            at = i if at is None else at
    if at is None or OLD_SUBPROTOCOL not in offered or NEW_SUBPROTOCOL in offered:
        return head, False
    lines[at] = lines[at] + b", " + NEW_SUBPROTOCOL.encode()
    return b"\r\n".join(lines), True


def rewrite_response(head: bytes) -> bytes:
    """The server's HTTP head with its chosen ``foxglove.sdk.v1`` renamed ``foxglove.websocket.v1``."""
    lines = head.split(b"\r\n")
    for i, line in enumerate(lines[1:], start=1):
        name, sep, value = line.partition(b":")
        if sep and name.strip().lower() == _HEADER and value.strip() == NEW_SUBPROTOCOL.encode():
            lines[i] = name + b": " + OLD_SUBPROTOCOL.encode()
    return b"\r\n".join(lines)


class _Side:
    """One socket of a relayed connection and what waits to be written to it."""

    __slots__ = ("connected", "eof", "events", "head", "out", "shut", "sock")

    def __init__(self, sock: socket.socket, *, head: bool, connected: bool = True) -> None:
        self.sock = sock
        self.out = bytearray()
        self.eof = False  # nothing more will be read from this socket
        self.shut = False  # its write half has been shut down
        self.events = 0
        # the HTTP head read from this side so far; None once it has been forwarded
        self.head: bytearray | None = bytearray() if head else None
        self.connected = connected


class _Conn:
    __slots__ = ("client", "deadline", "renamed", "server")

    def __init__(self, client: _Side, server: _Side, deadline: float) -> None:
        self.client = client
        self.server = server
        self.deadline: float | None = deadline
        self.renamed = False


class SubprotocolRelay:
    """Listens on ``(host, port)`` and relays each connection to ``upstream``, renaming the subprotocol.

    ::

        relay = SubprotocolRelay("0.0.0.0", 8765, ("127.0.0.1", sdk_server.port))
        ...
        relay.stop()

    Args:
        host, port: where clients connect (``port=0``: any free port, see :attr:`port`).
        upstream: the SDK's server, on loopback.
        max_connections: connections relayed at once; more are answered 503.
        handshake_timeout_s: from accepting a connection to forwarding the server's 101.
        buffer_limit: bytes that may wait per direction of a connection before the relay stops reading.
        max_head: the largest HTTP head accepted from either side.

    Raises:
        OSError: the address cannot be bound (a port in use, an address not on this machine).
    """

    def __init__(
        self,
        host: str,
        port: int,
        upstream: tuple[str, int],
        *,
        max_connections: int = 8,
        handshake_timeout_s: float = 5.0,
        buffer_limit: int = 256 * 1024,
        max_head: int = 16 * 1024,
    ) -> None:
        if not (isinstance(max_connections, int) and max_connections > 0):
            raise ValueError(f"max_connections must be a positive integer, got {max_connections!r}")
        if not handshake_timeout_s > 0:
            raise ValueError(f"handshake_timeout_s must be positive, got {handshake_timeout_s!r}")
        if not (isinstance(buffer_limit, int) and buffer_limit >= 4096):
            raise ValueError(f"buffer_limit must be an integer of at least 4096, got {buffer_limit!r}")
        self.upstream = upstream
        self.max_connections = max_connections
        self.handshake_timeout_s = handshake_timeout_s
        self.buffer_limit = buffer_limit
        self.max_head = max_head
        self.stats = RelayStats()
        self._listener = _listen(host, port)
        self.port: int = self._listener.getsockname()[1]
        """the port clients connect to (the one chosen when ``port=0``)"""
        self._conns: set[_Conn] = set()
        self._sel = selectors.DefaultSelector()
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        self._wake_w.setblocking(False)
        self._sel.register(self._listener, selectors.EVENT_READ, "accept")
        self._sel.register(self._wake_r, selectors.EVENT_READ, "wake")
        self._stopping = False
        self._thread = threading.Thread(target=self._serve, name=f"foxglove-relay:{self.port}", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------------------------ public
    @property
    def connections(self) -> int:
        """Connections open now."""
        return len(self._conns)

    def buffered(self) -> int:
        """Bytes waiting in the relay's buffers now (at most ``2 * buffer_limit`` per connection, plus heads)."""
        total = 0
        for c in list(self._conns):
            total += len(c.client.out) + len(c.server.out)
        return total

    def stop(self, timeout: float = 2.0) -> None:
        """Stop listening and close every relayed connection (the server sees its clients leave)."""
        if self._stopping:
            return
        self._stopping = True
        with contextlib.suppress(OSError):
            self._wake_w.send(b"x")
        self._thread.join(timeout)
        self._wake_w.close()

    # ------------------------------------------------------------------------------------ the thread
    def _serve(self) -> None:
        try:
            while not self._stopping:
                timeout = self._next_timeout()
                for key, events in self._sel.select(timeout):
                    data = key.data
                    if data.__class__ is _Conn:
                        self._ready(data, key.fileobj, events)
                    elif data == "accept":
                        self._accept()
                    else:  # woken by stop()
                        with contextlib.suppress(OSError):
                            self._wake_r.recv(64)
                if timeout is not None:
                    self._expire()
        except Exception:  # a bug here must not go unseen: the live view would silently stop
            logger.exception("Foxglove relay on port %d failed", self.port)
        finally:
            for conn in list(self._conns):
                self._close(conn)
            self._sel.close()
            self._listener.close()
            self._wake_r.close()
            self.stats.cpu_s = time.thread_time()

    def _next_timeout(self) -> float | None:
        deadlines = [c.deadline for c in self._conns if c.deadline is not None]
        return max(0.0, min(deadlines) - time.monotonic()) if deadlines else None

    def _expire(self) -> None:
        now = time.monotonic()
        for conn in [c for c in self._conns if c.deadline is not None and c.deadline <= now]:
            self.stats.timed_out += 1
            self._close(conn)

    def _accept(self) -> None:
        try:
            sock, _addr = self._listener.accept()
        except (BlockingIOError, InterruptedError, ConnectionAbortedError):
            return
        except OSError as exc:  # out of file descriptors: wait a little rather than spin on the listener
            logger.warning("Foxglove relay on port %d cannot accept: %s", self.port, exc)
            time.sleep(0.05)
            return
        sock.setblocking(False)
        if len(self._conns) >= self.max_connections:
            self.stats.refused += 1
            with contextlib.suppress(OSError):
                sock.send(_BUSY)
            sock.close()
            return
        _no_delay(sock)
        up = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        up.setblocking(False)
        _no_delay(up)
        err = up.connect_ex(self.upstream)
        if err not in (0, errno.EINPROGRESS, errno.EWOULDBLOCK):
            logger.warning("Foxglove relay: cannot reach the server at %s:%d: %s", *self.upstream, os.strerror(err))
            up.close()
            sock.close()
            return
        deadline = time.monotonic() + self.handshake_timeout_s
        conn = _Conn(_Side(sock, head=True), _Side(up, head=True, connected=err == 0), deadline)
        self._conns.add(conn)
        self.stats.accepted += 1
        self._update(conn)

    def _ready(self, conn: _Conn, sock: Any, events: int) -> None:
        if conn not in self._conns:  # closed while handling its other socket's event of the same select
            return
        side, other = (conn.client, conn.server) if sock is conn.client.sock else (conn.server, conn.client)
        if events == selectors.EVENT_READ and side.head is None and not other.out and other.connected:
            self._pass(conn, side, other)
            return
        try:
            if events & selectors.EVENT_WRITE:
                if not side.connected:
                    err = side.sock.getsockopt(socket.SOL_SOCKET, socket.SO_ERROR)
                    if err:
                        raise OSError(err, "cannot reach the Foxglove server")
                    side.connected = True
                self._flush(side)
            if events & selectors.EVENT_READ:
                self._read(conn, side, other)
        except OSError:
            self._close(conn)
            return
        if self._finished(conn):
            self._close(conn)
        else:
            self._update(conn)

    def _pass(self, conn: _Conn, side: _Side, other: _Side) -> None:
        """The common case after the handshake: what came in goes straight out, and the sockets are watched as
        they were unless the other side could not take it all (or this one ended)."""
        try:
            data = side.sock.recv(self.buffer_limit)
            if data:
                # counted before it goes out, so a reader of the stats never sees fewer bytes than a peer got
                if side is conn.client:
                    self.stats.to_server += len(data)
                else:
                    self.stats.to_clients += len(data)
                sent = _send(other.sock, data)
        except OSError:
            self._close(conn)
            return
        if data:
            if sent == len(data):
                return
            other.out += memoryview(data)[sent:]
        else:
            side.eof = True
        if self._finished(conn):
            self._close(conn)
        else:
            self._update(conn)

    def _read(self, conn: _Conn, side: _Side, other: _Side) -> None:
        """Read what ``other`` has room for; forward it (the head once complete, rewritten)."""
        room = self.buffer_limit - len(other.out)
        data = side.sock.recv(max(room, 1) if side.head is None else self.max_head)
        if not data:
            side.eof = True
            if side.head is not None:  # the handshake ended half way
                raise ConnectionAbortedError
            return
        if side.head is not None:
            data = self._head(conn, side, data)
            if not data:
                return
        if side is conn.client:
            self.stats.to_server += len(data)
        else:
            self.stats.to_clients += len(data)
        if other.out or not other.connected:
            other.out += data
        else:
            sent = _send(other.sock, data)
            if sent < len(data):
                other.out += memoryview(data)[sent:]

    def _head(self, conn: _Conn, side: _Side, data: bytes) -> bytes:
        """Collect an HTTP head; once complete, the bytes to forward (the head rewritten, then what followed)."""
        head = side.head
        assert head is not None
        head += data
        end = head.find(_END)
        if end < 0:
            if len(head) > self.max_head:
                if side is conn.client:
                    with contextlib.suppress(OSError):
                        side.sock.send(_TOO_BIG)
                raise ConnectionAbortedError
            return b""
        raw, rest = bytes(head[:end]), bytes(head[end + len(_END) :])
        side.head = None
        if side is conn.client:
            raw, conn.renamed = rewrite_request(raw)
            self.stats.renamed += conn.renamed
        else:
            conn.deadline = None  # the handshake is over, whatever the answer
            if conn.renamed:
                raw = rewrite_response(raw)
        return raw + _END + rest

    def _flush(self, side: _Side) -> None:
        if side.out:
            sent = _send(side.sock, side.out)
            del side.out[:sent]

    def _finished(self, conn: _Conn) -> bool:
        """Shut each write half whose source has ended and whose buffer is empty; True when both are."""
        for src, dst in ((conn.client, conn.server), (conn.server, conn.client)):
            if src.eof and not dst.out and not dst.shut and dst.connected:
                dst.shut = True
                with contextlib.suppress(OSError):
                    dst.sock.shutdown(socket.SHUT_WR)
        return conn.client.shut and conn.server.shut

    def _update(self, conn: _Conn) -> None:
        """Watch each socket for what can make progress: reading while the other side has room, writing while
        something waits (or the connection to the server is being made)."""
        limit = self.buffer_limit
        for side, other in ((conn.client, conn.server), (conn.server, conn.client)):
            want = 0
            if not side.eof and len(other.out) < limit:
                want |= selectors.EVENT_READ
            if side.out or not side.connected:
                want |= selectors.EVENT_WRITE
            if side is conn.server and not side.connected:
                want = selectors.EVENT_WRITE
            if want != side.events:
                if side.events == 0:
                    self._sel.register(side.sock, want, conn)
                elif want == 0:
                    self._sel.unregister(side.sock)
                else:
                    self._sel.modify(side.sock, want, conn)
                side.events = want

    def _close(self, conn: _Conn) -> None:
        for side in (conn.client, conn.server):
            if side.events:
                with contextlib.suppress(KeyError, ValueError):
                    self._sel.unregister(side.sock)
                side.events = 0
        self._conns.discard(conn)
        for side in (conn.client, conn.server):
            side.sock.close()


def _listen(host: str, port: int) -> socket.socket:
    family, kind, proto, _name, addr = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)[
        0
    ]
    sock = socket.socket(family, kind, proto)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind(addr)
        sock.listen(64)
        sock.setblocking(False)
    except BaseException:
        sock.close()
        raise
    return sock


def _no_delay(sock: socket.socket) -> None:
    """Small WebSocket frames (a JSON value, a ping) go out at once, as they would from the server itself."""
    with contextlib.suppress(OSError):
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)


def _send(sock: socket.socket, data: bytes | bytearray) -> int:
    try:
        return sock.send(data)
    except (BlockingIOError, InterruptedError):
        return 0
