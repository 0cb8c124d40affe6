"""An async serial port that frames lines (or hands raw bytes to a protocol), survives unplugging, and counts.

Why this shape:

* **Event-driven reads.** Bytes arrive through pyserial-asyncio's transport (the event loop watches the file
  descriptor); there is no blocking ``readline()`` and no per-tick polling of ``in_waiting`` as in Donkeycar's
  ``SerialLineReader``. Opening the port (``open()`` + termios set-up) is blocking, so it runs in an executor.
* **Bounded memory.** Complete lines go into a deque of ``max_lines``; when a consumer falls behind the oldest
  line is dropped and counted (``lines_dropped``), so a stalled consumer can never grow memory. A line longer
  than ``max_line_length`` (a device spewing garbage at the wrong baud rate, a missing newline) is dropped and
  counted (``overlong_dropped``) instead of growing the partial-line buffer. Writes are refused (and counted)
  when the transport's buffer already holds ``max_write_buffer`` bytes.
* **Unplug and replug.** A USB serial device that disappears makes the read fail (EOF or EIO on Linux); the
  transport reports ``connection_lost``, the port counts a disconnect, clears ``connected`` and retries opening
  the same path with exponential backoff on the runtime clock (:func:`asyncdonkey.clock.get_clock`), so on a
  :class:`~asyncdonkey.virtual_loop.VirtualClockLoop` the retry times are exact. Open a stable path such as
  ``/dev/serial/by-id/...``: ``/dev/ttyUSB0`` may come back under another number. ``on_connect`` runs after
  every (re)connect so a driver can put the device back in the state it needs (start streaming, start a scan).
* **Binary mode.** Give a ``receiver`` (any object with ``data_received(bytes)``, optionally
  ``connection_made()`` and ``connection_lost(exc)``) and raw bytes go to it instead of the line framer; the
  RPLidar driver uses this.

Which asyncio serial library, and why: **pyserial-asyncio** (0.6). It is already a declared dependency, its
transport API (``connection_for_serial``, ``SerialTransport``) is exactly the one its maintained fork
*pyserial-asyncio-fast* keeps, and the fork's gain (eager writes that skip a writer registration) matters for
high-rate writers, while our peers receive a few command bytes per second. The import below is the only place
the library is named; switching to the fork is a one-line change (``from serial_asyncio_fast import ...``).
"""

from __future__ import annotations

import asyncio
import collections
import inspect
import logging
from collections.abc import AsyncIterator, Awaitable, Callable
from typing import Any, NamedTuple, Protocol

import serial
from serial_asyncio import connection_for_serial  # the one import of the asyncio serial layer (see docstring)

from ..clock import Clock, DeadlineWaiter, get_clock
from ..errors import AsyncdonkeyError
from ..ratelimit import LogThrottle

__all__ = ["ByteReceiver", "Line", "LineFramer", "SerialPort", "SerialPortClosed"]

logger = logging.getLogger(__name__)

_PARITIES = {"N": serial.PARITY_NONE, "E": serial.PARITY_EVEN, "O": serial.PARITY_ODD}


class Line(NamedTuple):
    """One received line without its line ending, and when it arrived (runtime clock, seconds).

    A plain tuple ``(timestamp, text)``, the shape Donkeycar's ``SerialLineReader`` returns.
    """

    timestamp: float
    text: str


class SerialPortClosed(AsyncdonkeyError, ConnectionError):
    """Raised by :meth:`SerialPort.readline` once the port has been closed and no line is left."""


class ByteReceiver(Protocol):
    """What binary mode hands bytes to. ``connection_made()``/``connection_lost(exc)`` are optional."""

    def data_received(self, data: bytes) -> None: ...


ConnectHook = Callable[["SerialPort"], Awaitable[None] | None]


class LineFramer:
    """Splits a byte stream into text lines: ``"\n"`` ends a line, one trailing ``"\r"`` is removed, empty
    lines are skipped. A line longer than ``max_line_length`` bytes is dropped whole (``overlong``) without
    ever buffering more than that; undecodable lines are dropped (``decode_errors``). Never raises."""

    __slots__ = ("_buf", "_discarding", "decode_errors", "encoding", "max_line_length", "overlong")

    def __init__(self, max_line_length: int = 256, encoding: str = "ascii") -> None:
        self.max_line_length = max_line_length
        self.encoding = encoding
        self.overlong = 0
        self.decode_errors = 0
        self._buf = bytearray()
        self._discarding = False

    def reset(self) -> None:
        """Forget a partial line (after a reconnect the rest of it will never come)."""
        self._buf.clear()
        self._discarding = False

    def feed(self, data: bytes) -> list[str]:
        buf = self._buf
        buf += data
        max_len = self.max_line_length
        out: list[str] = []
        start = 0
        while True:
            nl = buf.find(b"\n", start)
            if nl < 0:
                break
            raw = bytes(buf[start:nl])
            start = nl + 1
            if self._discarding:  # the tail of a line already counted as overlong
                self._discarding = False
                continue
            if raw.endswith(b"\r"):
                raw = raw[:-1]
            if not raw:
                continue
            if len(raw) > max_len:
                self.overlong += 1
                continue
            try:
                out.append(raw.decode(self.encoding))
            except UnicodeDecodeError:
                self.decode_errors += 1
        if start:
            del buf[:start]
        if len(buf) > max_len + 1:  # +1: a trailing "\r" whose "\n" has not arrived yet
            if not self._discarding:
                self.overlong += 1
                self._discarding = True
            buf.clear()
        return out


class SerialPort:
    """A serial port read by the event loop, framed into lines (or raw bytes), reconnecting after unplug.

    Use ``await port.run()`` as (part of) a background task, or ``await port.start()`` to spawn it; stop
    with ``await port.close()``. ``connected`` tells whether a device is there right now.

    Args:
        port: device path (prefer a stable ``/dev/serial/by-id/...`` path) or a pyserial URL.
        baudrate, bytesize, parity (``"N"``, ``"E"``, ``"O"``), stopbits: line settings (default 115200 8N1).
        receiver: binary mode: raw bytes go to ``receiver.data_received`` instead of the line framer.
        max_lines: complete lines kept for consumers; the oldest is dropped (and counted) when full.
        max_line_length: longer lines are dropped and counted, never buffered without bound.
        encoding: how lines are decoded; undecodable lines are dropped and counted.
        skip_first_line: drop the first line after each (re)connect. A device that was already streaming
            when the port opened makes the first "line" a tail fragment, which for a protocol without a
            checksum (the wheel encoder) would parse as a wrong value.
        on_connect: ``hook(port)`` (sync or async) run after every successful open, e.g. to send commands.
        backoff_initial_s, backoff_max_s: retry delays after a failed open, doubling up to the maximum; the
            first retry after a disconnect waits ``backoff_initial_s``.
        max_write_buffer: bytes the transport may hold unsent before writes are refused.
        name: used in log messages (default: the port path).
    """

    def __init__(
        self,
        port: str,
        baudrate: int = 115200,
        *,
        bytesize: int = 8,
        parity: str = "N",
        stopbits: float = 1,
        receiver: ByteReceiver | None = None,
        max_lines: int = 256,
        max_line_length: int = 256,
        encoding: str = "ascii",
        skip_first_line: bool = False,
        on_connect: ConnectHook | None = None,
        backoff_initial_s: float = 0.05,
        backoff_max_s: float = 2.0,
        max_write_buffer: int = 4096,
        name: str | None = None,
    ) -> None:
        self.name = name or str(port)
        where = f"SerialPort({self.name!r})"
        if not isinstance(port, str) or not port:
            raise ValueError(f"{where}: port must be a device path such as '/dev/ttyACM0', got {port!r}")
        if not (isinstance(baudrate, int) and baudrate > 0):
            raise ValueError(f"{where}: baudrate must be a positive int, got {baudrate!r}")
        if parity not in _PARITIES:
            raise ValueError(f"{where}: parity must be one of {sorted(_PARITIES)}, got {parity!r}")
        if bytesize not in (5, 6, 7, 8):
            raise ValueError(f"{where}: bytesize must be 5, 6, 7 or 8, got {bytesize!r}")
        if stopbits not in (1, 1.5, 2):
            raise ValueError(f"{where}: stopbits must be 1, 1.5 or 2, got {stopbits!r}")
        if not (isinstance(max_lines, int) and max_lines > 0):
            raise ValueError(f"{where}: max_lines must be a positive int, got {max_lines!r}")
        if not (isinstance(max_line_length, int) and max_line_length > 0):
            raise ValueError(f"{where}: max_line_length must be a positive int, got {max_line_length!r}")
        if not 0 < backoff_initial_s <= backoff_max_s:
            raise ValueError(
                f"{where}: need 0 < backoff_initial_s <= backoff_max_s, got {backoff_initial_s!r}, {backoff_max_s!r}"
            )
        if receiver is not None and not callable(getattr(receiver, "data_received", None)):
            raise TypeError(f"{where}: receiver must have a data_received(bytes) method, got {receiver!r}")
        "".encode(encoding)  # unknown encodings fail here, not on the first line

        self.port = port
        self.baudrate = baudrate
        self.bytesize = bytesize
        self.parity = parity
        self.stopbits = stopbits
        self.receiver = receiver
        self.max_lines = max_lines
        self.max_line_length = max_line_length
        self.encoding = encoding
        self.skip_first_line = skip_first_line
        self.on_connect = on_connect
        self.backoff_initial_s = float(backoff_initial_s)
        self.backoff_max_s = float(backoff_max_s)
        self.max_write_buffer = max_write_buffer

        #: True while a device is open and readable.
        self.connected = False
        # counters (never reset; read them, or take them all with stats())
        self.connects = 0
        self.disconnects = 0
        self.open_attempts = 0
        self.open_failures = 0
        self.bytes_received = 0
        self.bytes_written = 0
        self.lines_received = 0
        self.lines_dropped = 0
        self.first_lines_skipped = 0
        self.writes_dropped = 0
        self.receiver_errors = 0
        self.hook_errors = 0
        #: the last open or read error, for diagnostics
        self.last_error: BaseException | None = None

        self._lines: collections.deque[Line] = collections.deque()
        self._framer = LineFramer(max_line_length, encoding)
        self._skip_next_line = False
        self._transport: asyncio.Transport | None = None
        self._clock: Clock | None = None
        self._now: Callable[[], float] | None = None
        self._closing = False
        self._running = False
        self._task: asyncio.Task[None] | None = None
        self._wake: asyncio.Future[None] | None = None
        self._lines_ready: asyncio.Event | None = None
        self._connected_event: asyncio.Event | None = None
        self._stopped: asyncio.Event | None = None
        self._log = LogThrottle(5.0)
        self._on_data: Callable[[bytes], None] = self._feed_receiver if receiver is not None else self._feed_lines
        self._receiver_made = getattr(receiver, "connection_made", None)
        self._receiver_lost = getattr(receiver, "connection_lost", None)

    def __repr__(self) -> str:
        state = "connected" if self.connected else "disconnected"
        return f"<SerialPort {self.name!r} {self.baudrate} baud, {state}>"

    # ------------------------------------------------------------------------------------------ lifecycle
    async def start(self) -> None:
        """Spawn :meth:`run` as a task and return at once (the first open happens in the background)."""
        if self._task is None or self._task.done():
            self._task = asyncio.get_running_loop().create_task(self.run(), name=f"serial:{self.name}")
            await asyncio.sleep(0)

    async def __aenter__(self) -> SerialPort:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    async def run(self) -> None:
        """Open the port, keep it open, reopen it after unplug; return when :meth:`close` is called.

        A closed port stays closed: ``run()`` after :meth:`close` returns at once.
        """
        if self._running:
            raise RuntimeError(f"serial port {self.name!r}: run() is already running")
        if self._closing:
            return
        loop = asyncio.get_running_loop()
        clock = self._clock = get_clock(loop)
        self._now = clock.now
        self._running = True
        self._lines_ready = self._lines_ready or asyncio.Event()
        self._connected_event = self._connected_event or asyncio.Event()
        self._stopped = asyncio.Event()
        delay = self.backoff_initial_s
        waiter = DeadlineWaiter(loop)  # one OS timer for every back-off pause of this run
        try:
            while not self._closing:
                ser = await self._open(loop)
                if ser is None:
                    await self._pause(clock, waiter, delay)
                    delay = min(delay * 2.0, self.backoff_max_s)
                    continue
                lost: asyncio.Future[BaseException | None] = loop.create_future()
                transport, _ = await connection_for_serial(loop, lambda lost=lost: _Link(self, lost), ser)
                self._attach(transport)
                await self._run_hooks()
                if not self._closing:
                    exc = await lost
                else:
                    exc = None
                    transport.close()
                    await _wait_briefly(lost, transport)
                self._detach()
                if self._closing:
                    break
                self.disconnects += 1
                self.last_error = exc
                logger.warning(
                    "serial port %r: device lost (%s); reconnecting (disconnect #%d)",
                    self.name,
                    exc or "closed",
                    self.disconnects,
                )
                delay = self.backoff_initial_s
                await self._pause(clock, waiter, delay)
                delay = min(delay * 2.0, self.backoff_max_s)
        finally:
            waiter.close()
            t = self._transport
            if t is not None:
                if not t.is_closing():
                    t.abort()
                self._detach()
            self._running = False
            self._stopped.set()

    async def close(self) -> None:
        """Stop reconnecting, close the device (pending writes are flushed first) and wait for :meth:`run`."""
        self._closing = True
        wake = self._wake
        if wake is not None and not wake.done():
            wake.set_result(None)
        for event in (self._lines_ready, self._connected_event):
            if event is not None:
                event.set()  # wake waiters so they see the port is closed
        t = self._transport
        if t is not None:
            t.close()
        if self._running and self._stopped is not None:
            try:
                await asyncio.wait_for(self._stopped.wait(), 1.0)
            except TimeoutError:
                t = self._transport
                if t is not None:
                    _force_close(t)
        task = self._task
        if task is not None and not task.done():
            try:
                await asyncio.wait_for(task, 1.0)
            except (TimeoutError, asyncio.CancelledError):
                task.cancel()
        self._task = None

    async def wait_connected(self) -> None:
        """Return once a device is open (at once if it already is). Wrap in ``asyncio.wait_for`` for a limit.

        Raises :class:`SerialPortClosed` if the port is closed meanwhile.
        """
        while not self.connected:
            if self._closing:
                raise SerialPortClosed(f"serial port {self.name!r} is closed")
            if self._connected_event is None:
                self._connected_event = asyncio.Event()
            self._connected_event.clear()
            await self._connected_event.wait()

    # --------------------------------------------------------------------------------------------- lines
    async def readline(self) -> Line:
        """The oldest unread line, waiting for one if none is buffered (across reconnects).

        Raises :class:`SerialPortClosed` once :meth:`close` has been called and the buffer is empty.
        """
        lines = self._lines
        while not lines:
            if self._closing:
                raise SerialPortClosed(f"serial port {self.name!r} is closed")
            if self._lines_ready is None:
                self._lines_ready = asyncio.Event()
            self._lines_ready.clear()
            await self._lines_ready.wait()
        return lines.popleft()

    def get_line_nowait(self) -> Line | None:
        """The oldest unread line, or ``None``."""
        lines = self._lines
        return lines.popleft() if lines else None

    def drain(self) -> list[Line]:
        """All unread lines, oldest first (like Donkeycar's ``SerialLineReader.run_threaded``)."""
        out = list(self._lines)
        self._lines.clear()
        return out

    @property
    def overlong_dropped(self) -> int:
        """Lines longer than ``max_line_length``, dropped."""
        return self._framer.overlong

    @property
    def decode_errors(self) -> int:
        """Lines that did not decode with ``encoding``, dropped."""
        return self._framer.decode_errors

    @property
    def serial(self) -> serial.Serial | None:
        """The open pyserial object (for modem lines such as DTR), ``None`` while disconnected."""
        t = self._transport
        return getattr(t, "serial", None) if t is not None else None

    @property
    def lines_buffered(self) -> int:
        return len(self._lines)

    async def lines(self) -> AsyncIterator[Line]:
        """Iterate over lines as they arrive, forever (until the consumer stops)."""
        while True:
            yield await self.readline()

    async def serve_lines(
        self,
        handle: Callable[[Line], None],
        *,
        idle_s: float | None = None,
        on_idle: Callable[[SerialPort], None] | None = None,
    ) -> None:
        """Run the port (open, reconnect) and call ``handle(line)`` for every line until :meth:`close`.

        With ``idle_s``, ``on_idle(port)`` is called whenever no line arrived for that long while connected
        (a watchdog: ask a device that went quiet to stream again). Errors raised by ``handle`` propagate.
        """
        supervisor = asyncio.get_running_loop().create_task(self.run(), name=f"serial:{self.name}")
        await asyncio.sleep(0)
        try:
            while not supervisor.done():
                try:
                    if idle_s is None:
                        line = await self.readline()
                    else:
                        line = await asyncio.wait_for(self.readline(), idle_s)
                except SerialPortClosed:
                    break
                except TimeoutError:
                    if self.connected and not self._closing and on_idle is not None:
                        on_idle(self)
                    continue
                handle(line)
        finally:
            if not supervisor.done():
                await self.close()
                await asyncio.wait({supervisor}, timeout=1.0)
            if not supervisor.done():
                supervisor.cancel()
        if not supervisor.cancelled() and supervisor.exception() is not None:
            raise supervisor.exception()  # type: ignore[misc]

    # -------------------------------------------------------------------------------------------- writes
    def write(self, data: bytes) -> bool:
        """Queue ``data`` on the transport. ``False`` (and counted in ``writes_dropped``) when no device is
        connected or the device is not draining what was already written."""
        t = self._transport
        if t is None or t.is_closing():
            self.writes_dropped += 1
            return False
        if t.get_write_buffer_size() + len(data) > self.max_write_buffer:
            self.writes_dropped += 1
            now = self._now() if self._now is not None else 0.0
            if self._log.allow("write", now):
                logger.warning("serial port %r: device is not reading; write of %d bytes dropped", self.name, len(data))
            return False
        t.write(data)
        self.bytes_written += len(data)
        return True

    def writeln(self, text: str) -> bool:
        """Write ``text`` plus ``"\\n"`` (the line ending Donkeycar's serial peers expect)."""
        return self.write(text.encode(self.encoding) + b"\n")

    def stats(self) -> dict[str, Any]:
        """Every counter, plus ``connected``, as a dict (for reports and logs)."""
        return {
            "connected": self.connected,
            "connects": self.connects,
            "disconnects": self.disconnects,
            "open_attempts": self.open_attempts,
            "open_failures": self.open_failures,
            "bytes_received": self.bytes_received,
            "bytes_written": self.bytes_written,
            "lines_received": self.lines_received,
            "lines_buffered": len(self._lines),
            "lines_dropped": self.lines_dropped,
            "overlong_dropped": self.overlong_dropped,
            "decode_errors": self.decode_errors,
            "first_lines_skipped": self.first_lines_skipped,
            "writes_dropped": self.writes_dropped,
            "receiver_errors": self.receiver_errors,
            "hook_errors": self.hook_errors,
        }

    # ---------------------------------------------------------------------------------------- internals
    def _open_serial(self) -> serial.Serial:
        """Blocking open; runs in an executor. Stale input buffered by the kernel is discarded."""
        ser = serial.serial_for_url(
            self.port,
            baudrate=self.baudrate,
            bytesize=self.bytesize,
            parity=_PARITIES[self.parity],
            stopbits=self.stopbits,
            timeout=0,
        )
        try:
            ser.reset_input_buffer()
        except (OSError, serial.SerialException):
            pass
        return ser

    async def _open(self, loop: asyncio.AbstractEventLoop) -> serial.Serial | None:
        self.open_attempts += 1
        fut = loop.run_in_executor(None, self._open_serial)
        try:
            return await asyncio.shield(fut)
        except asyncio.CancelledError:
            fut.add_done_callback(_close_opened)
            raise
        except (OSError, serial.SerialException, ValueError) as exc:
            self.open_failures += 1
            self.last_error = exc
            now = self._now() if self._now is not None else 0.0
            more = self._log.ready("open", now, "more failures")
            if more is not None:
                logger.warning("serial port %r: cannot open (%s); retrying%s", self.name, exc, more)
            return None

    async def _pause(self, clock: Clock, waiter: DeadlineWaiter, seconds: float) -> None:
        if self._closing:
            return
        wake = self._wake = asyncio.get_running_loop().create_future()
        try:
            await waiter.wait_until(clock.now() + seconds, wake)
        finally:
            self._wake = None

    def _attach(self, transport: asyncio.Transport) -> None:
        self._transport = transport
        self._framer.reset()
        self._skip_next_line = self.skip_first_line
        self.connected = True
        self.connects += 1
        if self._connected_event is not None:
            self._connected_event.set()
        if self.connects > 1:
            logger.info("serial port %r: reconnected (connection #%d)", self.name, self.connects)
        if self._receiver_made is not None:
            self._call_receiver(self._receiver_made)

    def _detach(self) -> None:
        was = self._transport is not None
        self._transport = None
        self.connected = False
        if self._connected_event is not None:
            self._connected_event.clear()
        if was and self._receiver_lost is not None:
            self._call_receiver(self._receiver_lost, self.last_error)

    async def _run_hooks(self) -> None:
        hook = self.on_connect
        if hook is None:
            return
        try:
            result = hook(self)
            if inspect.isawaitable(result):
                await result
        except asyncio.CancelledError:
            raise
        except Exception as exc:
            self.hook_errors += 1
            logger.error("serial port %r: on_connect hook failed: %r", self.name, exc, exc_info=exc)

    def _call_receiver(self, fn: Callable[..., Any], *args: Any) -> None:
        try:
            fn(*args)
        except Exception as exc:
            self.receiver_errors += 1
            logger.error("serial port %r: receiver %r raised %r", self.name, fn, exc, exc_info=exc)

    def _feed_receiver(self, data: bytes) -> None:
        self.bytes_received += len(data)
        try:
            self.receiver.data_received(data)  # type: ignore[union-attr]
        except Exception as exc:
            self.receiver_errors += 1
            now = self._now() if self._now is not None else 0.0
            if self._log.allow("receiver", now):
                logger.error("serial port %r: receiver failed on %d bytes: %r", self.name, len(data), exc)

    def _feed_lines(self, data: bytes) -> None:
        self.bytes_received += len(data)
        texts = self._framer.feed(data)
        if not texts:
            return
        if self._skip_next_line:
            self._skip_next_line = False
            self.first_lines_skipped += 1
            del texts[0]
            if not texts:
                return
        now = self._now()  # type: ignore[misc]
        lines = self._lines
        for text in texts:
            if len(lines) >= self.max_lines:
                lines.popleft()
                self.lines_dropped += 1
            lines.append(Line(now, text))
        self.lines_received += len(texts)
        if self._lines_ready is not None:
            self._lines_ready.set()


class _Link(asyncio.Protocol):
    """The asyncio protocol of one connection; forwards to its :class:`SerialPort`."""

    def __init__(self, port: SerialPort, lost: asyncio.Future[BaseException | None]) -> None:
        self._lost = lost
        self.data_received = port._on_data  # type: ignore[method-assign]

    def connection_lost(self, exc: BaseException | None) -> None:
        if not self._lost.done():
            self._lost.set_result(exc)


async def _wait_briefly(lost: asyncio.Future[Any], transport: asyncio.Transport) -> None:
    """Give a closing transport a moment to flush; abort it if the device does not drain."""
    try:
        await asyncio.wait_for(asyncio.shield(lost), 0.5)
    except TimeoutError:
        _force_close(transport)


def _force_close(transport: asyncio.Transport) -> None:
    """Abort a transport whose graceful close is stuck behind unsent data (pyserial-asyncio's ``close`` waits
    for the write buffer to drain; a device that stopped reading never drains it)."""
    if getattr(transport, "_loop", None) is not None:  # not yet finished closing
        transport.abort()


def _close_opened(fut: asyncio.Future[serial.Serial]) -> None:
    """An open that finished after its waiter was cancelled: close the port instead of leaking it."""
    if not fut.cancelled() and fut.exception() is None:
        fut.result().close()
