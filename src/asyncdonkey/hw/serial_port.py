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
  :class:`~asyncdonkey.clock.virtual_loop.VirtualClockLoop` the retry times are exact. Open a stable path such as
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
import dataclasses
import inspect
import logging
from collections.abc import AsyncIterator, Awaitable, Callable
from typing import Any, Generic, NamedTuple, Protocol, TypeVar, overload

import serial
from serial_asyncio import connection_for_serial  # the one import of the asyncio serial layer (see docstring)

from ..clock import Clock, DeadlineWaiter, get_clock
from ..errors import AsyncdonkeyError
from ..ratelimit import LogThrottle
from .serial_config import PARITIES, SERIAL_SETTINGS, SerialConfig

__all__ = [
    "ByteReceiver",
    "Line",
    "LineFramer",
    "LineQueue",
    "SerialConfig",
    "SerialCounters",
    "SerialPort",
    "SerialPortClosed",
]

logger = logging.getLogger(__name__)

T = TypeVar("T")


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


@dataclasses.dataclass(slots=True)
class SerialCounters:
    """What a port counts (never reset; :meth:`SerialPort.stats` takes them all, with the live figures)."""

    connects: int = 0
    disconnects: int = 0
    open_attempts: int = 0
    open_failures: int = 0
    bytes_received: int = 0
    bytes_written: int = 0
    lines_received: int = 0
    lines_dropped: int = 0
    first_lines_skipped: int = 0
    writes_dropped: int = 0
    receiver_errors: int = 0
    hook_errors: int = 0


class LineQueue:
    """The line reader's state: the framer, the bounded queue of complete lines, and the first-line skip.

    A consumer that falls behind loses the oldest lines (counted), never memory; the skip is re-armed at each
    (re)connect, since the first "line" of a device already streaming is a tail fragment.
    """

    __slots__ = ("framer", "lines", "max_lines", "ready", "skip_first", "skip_next")

    def __init__(self, config: SerialConfig) -> None:
        self.framer = LineFramer(config.max_line_length, config.encoding)
        self.lines: collections.deque[Line] = collections.deque()
        self.max_lines = config.max_lines
        self.skip_first = config.skip_first_line
        self.skip_next = False
        #: set when lines arrive (made on the loop, by the first reader or by ``run()``)
        self.ready: asyncio.Event | None = None

    def reconnected(self) -> None:
        """A new connection: forget a partial line (its rest will never come), arm the first-line skip."""
        self.framer.reset()
        self.skip_next = self.skip_first

    def feed(self, data: bytes, now: Callable[[], float], counters: SerialCounters) -> None:
        """Frame ``data`` and queue its complete lines, stamped ``now()``."""
        texts = self.framer.feed(data)
        if not texts:
            return
        if self.skip_next:
            self.skip_next = False
            counters.first_lines_skipped += 1
            del texts[0]
            if not texts:
                return
        t = now()
        lines = self.lines
        for text in texts:
            if len(lines) >= self.max_lines:
                lines.popleft()
                counters.lines_dropped += 1
            lines.append(Line(t, text))
        counters.lines_received += len(texts)
        if self.ready is not None:
            self.ready.set()


class _Lifecycle:
    """The reconnect loop's state: whether ``run()`` is running or the port closing, and what wakes or ends it."""

    __slots__ = ("closing", "running", "stopped", "task", "wake")

    def __init__(self) -> None:
        self.closing = False
        self.running = False
        self.task: asyncio.Task[None] | None = None  # the run() task start() spawned
        self.wake: asyncio.Future[None] | None = None  # cuts a back-off pause short (close)
        self.stopped: asyncio.Event | None = None  # set when run() returns


class _From(Generic[T]):
    """A read-only attribute of the port kept in one of its parts (its config, its counters), by the same name."""

    __slots__ = ("holder", "name")

    def __init__(self, holder: str) -> None:
        self.holder = holder
        self.name = ""

    def __set_name__(self, owner: type, name: str) -> None:
        self.name = name

    @overload
    def __get__(self, obj: None, owner: type) -> _From[T]: ...
    @overload
    def __get__(self, obj: object, owner: type) -> T: ...
    def __get__(self, obj: object | None, owner: type) -> _From[T] | T:
        if obj is None:
            return self
        value: T = getattr(getattr(obj, self.holder), self.name)
        return value


def _config(config: SerialConfig | str | None, baudrate: int | None, settings: dict[str, Any]) -> SerialConfig:
    """The port's config: ``config`` with the keyword ``settings`` applied over it (a path and baud rate given
    positionally, as Donkeycar's serial parts take them, are settings too)."""
    unknown = sorted(set(settings) - SERIAL_SETTINGS)
    if unknown:
        raise TypeError(
            f"SerialPort: unknown setting {unknown[0]!r}; the settings are SerialConfig's: "
            f"{', '.join(sorted(SERIAL_SETTINGS))}"
        )
    if not isinstance(config, SerialConfig | None):
        settings["port"] = config  # SerialPort("/dev/ttyACM0", ...): checked by SerialConfig like any path
        config = None
    if baudrate is not None:
        settings["baudrate"] = baudrate
    if config is None:
        return SerialConfig(**settings)
    return dataclasses.replace(config, **settings) if settings else config


class SerialPort:
    """A serial port read by the event loop, framed into lines (or raw bytes), reconnecting after unplug.

    Use ``await port.run()`` as (part of) a background task, or ``await port.start()`` to spawn it; stop
    with ``await port.close()``. ``connected`` tells whether a device is there right now.

    Its settings are a :class:`~asyncdonkey.hw.serial_config.SerialConfig`, kept apart from the port's state: the
    config is the one place that lists what is settable, with defaults and checks (every setting is validated
    once, when the config is made, with a one-line error naming it), and, frozen, it can be shared between cars
    and tests and varied with :func:`dataclasses.replace`. ``SerialPort(config)`` takes one; the keyword form
    (``SerialPort("/dev/ttyACM0", 115200, skip_first_line=True)``) builds one, and keywords given with a config
    are applied over it. The state is split by job: :class:`SerialCounters` (the counts), :class:`LineQueue`
    (the line reader) and the reconnect loop's state; the settings and counters read as attributes of the port.

    Args:
        config: the settings (:class:`~asyncdonkey.hw.serial_config.SerialConfig`), or the device path.
        baudrate: the baud rate, as the keyword form passes it second.
        receiver: binary mode: raw bytes go to ``receiver.data_received`` instead of the line framer.
        on_connect: ``hook(port)`` (sync or async) run after every successful open, e.g. to send commands.
        settings: any of :class:`~asyncdonkey.hw.serial_config.SerialConfig`'s settings, applied over ``config``.
    """

    port = _From[str]("config")
    baudrate = _From[int]("config")
    bytesize = _From[int]("config")
    parity = _From[str]("config")
    stopbits = _From[float]("config")
    max_lines = _From[int]("config")
    max_line_length = _From[int]("config")
    encoding = _From[str]("config")
    skip_first_line = _From[bool]("config")
    backoff_initial_s = _From[float]("config")
    backoff_max_s = _From[float]("config")
    max_write_buffer = _From[int]("config")
    connects = _From[int]("counters")
    disconnects = _From[int]("counters")
    open_attempts = _From[int]("counters")
    open_failures = _From[int]("counters")
    bytes_received = _From[int]("counters")
    bytes_written = _From[int]("counters")
    lines_received = _From[int]("counters")
    lines_dropped = _From[int]("counters")
    first_lines_skipped = _From[int]("counters")
    writes_dropped = _From[int]("counters")
    receiver_errors = _From[int]("counters")
    hook_errors = _From[int]("counters")

    def __init__(
        self,
        config: SerialConfig | str | None = None,
        baudrate: int | None = None,
        *,
        receiver: ByteReceiver | None = None,
        on_connect: ConnectHook | None = None,
        **settings: Any,
    ) -> None:
        cfg = self.config = _config(config, baudrate, settings)
        if receiver is not None and not callable(getattr(receiver, "data_received", None)):
            where = f"SerialPort({cfg.label!r})"
            raise TypeError(f"{where}: receiver must have a data_received(bytes) method, got {receiver!r}")
        self.receiver = receiver
        self.on_connect = on_connect
        #: True while a device is open and readable.
        self.connected = False
        self.counters = SerialCounters()
        #: the last open or read error, for diagnostics
        self.last_error: BaseException | None = None
        self._lines = LineQueue(cfg)
        self._life = _Lifecycle()
        self._transport: asyncio.Transport | None = None
        self._connected_event: asyncio.Event | None = None
        self._clock: Clock | None = None
        self._now: Callable[[], float] | None = None
        self._log = LogThrottle(5.0)
        self._on_data: Callable[[bytes], None] = self._feed_receiver if receiver is not None else self._feed_lines
        self._receiver_made = getattr(receiver, "connection_made", None)
        self._receiver_lost = getattr(receiver, "connection_lost", None)

    @property
    def name(self) -> str:
        """How logs and errors name the port: the ``name`` setting, or the port path."""
        return self.config.label

    def __repr__(self) -> str:
        state = "connected" if self.connected else "disconnected"
        return f"<SerialPort {self.name!r} {self.baudrate} baud, {state}>"

    # ------------------------------------------------------------------------------------------ lifecycle
    async def start(self) -> None:
        """Spawn :meth:`run` as a task and return at once (the first open happens in the background)."""
        life = self._life
        if life.task is None or life.task.done():
            life.task = asyncio.get_running_loop().create_task(self.run(), name=f"serial:{self.name}")
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
        life = self._life
        if life.running:
            raise RuntimeError(f"serial port {self.name!r}: run() is already running")
        if life.closing:
            return
        loop = asyncio.get_running_loop()
        clock = self._clock = get_clock(loop)
        self._now = clock.now
        life.running = True
        self._lines.ready = self._lines.ready or asyncio.Event()
        self._connected_event = self._connected_event or asyncio.Event()
        life.stopped = asyncio.Event()
        delay = self.backoff_initial_s
        waiter = DeadlineWaiter(loop)  # one OS timer for every back-off pause of this run
        try:
            while not life.closing:
                ser = await self._open(loop)
                if ser is None:
                    await self._pause(clock, waiter, delay)
                    delay = min(delay * 2.0, self.backoff_max_s)
                    continue
                lost: asyncio.Future[BaseException | None] = loop.create_future()
                transport, _ = await connection_for_serial(loop, lambda lost=lost: _Link(self, lost), ser)
                self._attach(transport)
                await self._run_hooks()
                if not life.closing:
                    exc = await lost
                else:
                    exc = None
                    transport.close()
                    await _wait_briefly(lost, transport)
                self._detach()
                if life.closing:
                    break
                self.counters.disconnects += 1
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
            life.running = False
            life.stopped.set()

    async def close(self) -> None:
        """Stop reconnecting, close the device (pending writes are flushed first) and wait for :meth:`run`."""
        life = self._life
        life.closing = True
        wake = life.wake
        if wake is not None and not wake.done():
            wake.set_result(None)
        for event in (self._lines.ready, self._connected_event):
            if event is not None:
                event.set()  # wake waiters so they see the port is closed
        t = self._transport
        if t is not None:
            t.close()
        if life.running and life.stopped is not None:
            try:
                await asyncio.wait_for(life.stopped.wait(), 1.0)
            except TimeoutError:
                t = self._transport
                if t is not None:
                    _force_close(t)
        task = life.task
        if task is not None and not task.done():
            try:
                await asyncio.wait_for(task, 1.0)
            except (TimeoutError, asyncio.CancelledError):
                task.cancel()
        life.task = None

    async def wait_connected(self) -> None:
        """Return once a device is open (at once if it already is). Wrap in ``asyncio.wait_for`` for a limit.

        Raises :class:`SerialPortClosed` if the port is closed meanwhile.
        """
        while not self.connected:
            if self._life.closing:
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
        queue = self._lines
        lines = queue.lines
        while not lines:
            if self._life.closing:
                raise SerialPortClosed(f"serial port {self.name!r} is closed")
            if queue.ready is None:
                queue.ready = asyncio.Event()
            queue.ready.clear()
            await queue.ready.wait()
        return lines.popleft()

    def get_line_nowait(self) -> Line | None:
        """The oldest unread line, or ``None``."""
        lines = self._lines.lines
        return lines.popleft() if lines else None

    def drain(self) -> list[Line]:
        """All unread lines, oldest first (like Donkeycar's ``SerialLineReader.run_threaded``)."""
        lines = self._lines.lines
        out = list(lines)
        lines.clear()
        return out

    @property
    def overlong_dropped(self) -> int:
        """Lines longer than ``max_line_length``, dropped."""
        return self._lines.framer.overlong

    @property
    def decode_errors(self) -> int:
        """Lines that did not decode with ``encoding``, dropped."""
        return self._lines.framer.decode_errors

    @property
    def serial(self) -> serial.Serial | None:
        """The open pyserial object (for modem lines such as DTR), ``None`` while disconnected."""
        t = self._transport
        return getattr(t, "serial", None) if t is not None else None

    @property
    def lines_buffered(self) -> int:
        """Complete lines waiting for a consumer."""
        return len(self._lines.lines)

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
                    if self.connected and not self._life.closing and on_idle is not None:
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
            self.counters.writes_dropped += 1
            return False
        if t.get_write_buffer_size() + len(data) > self.max_write_buffer:
            self.counters.writes_dropped += 1
            now = self._now() if self._now is not None else 0.0
            if self._log.allow("write", now):
                logger.warning("serial port %r: device is not reading; write of %d bytes dropped", self.name, len(data))
            return False
        t.write(data)
        self.counters.bytes_written += len(data)
        return True

    def writeln(self, text: str) -> bool:
        """Write ``text`` plus ``"\\n"`` (the line ending Donkeycar's serial peers expect)."""
        return self.write(text.encode(self.encoding) + b"\n")

    def stats(self) -> dict[str, Any]:
        """Every counter, plus ``connected``, as a dict (for reports and logs)."""
        counts = dataclasses.asdict(self.counters)
        return {
            "connected": self.connected,
            **{k: counts[k] for k in ("connects", "disconnects", "open_attempts", "open_failures")},
            **{k: counts[k] for k in ("bytes_received", "bytes_written", "lines_received")},
            "lines_buffered": self.lines_buffered,
            "lines_dropped": counts["lines_dropped"],
            "overlong_dropped": self.overlong_dropped,
            "decode_errors": self.decode_errors,
            **{k: counts[k] for k in ("first_lines_skipped", "writes_dropped", "receiver_errors", "hook_errors")},
        }

    # ---------------------------------------------------------------------------------------- internals
    def _open_serial(self) -> serial.Serial:
        """Blocking open; runs in an executor. Stale input buffered by the kernel is discarded."""
        ser = serial.serial_for_url(
            self.port,
            baudrate=self.baudrate,
            bytesize=self.bytesize,
            parity=PARITIES[self.parity],
            stopbits=self.stopbits,
            timeout=0,
        )
        try:
            ser.reset_input_buffer()
        except (OSError, serial.SerialException):
            pass
        return ser

    async def _open(self, loop: asyncio.AbstractEventLoop) -> serial.Serial | None:
        self.counters.open_attempts += 1
        fut = loop.run_in_executor(None, self._open_serial)
        try:
            return await asyncio.shield(fut)
        except asyncio.CancelledError:
            fut.add_done_callback(_close_opened)
            raise
        except (OSError, serial.SerialException, ValueError) as exc:
            self.counters.open_failures += 1
            self.last_error = exc
            now = self._now() if self._now is not None else 0.0
            more = self._log.ready("open", now, "more failures")
            if more is not None:
                logger.warning("serial port %r: cannot open (%s); retrying%s", self.name, exc, more)
            return None

    async def _pause(self, clock: Clock, waiter: DeadlineWaiter, seconds: float) -> None:
        life = self._life
        if life.closing:
            return
        wake = life.wake = asyncio.get_running_loop().create_future()
        try:
            await waiter.wait_until(clock.now() + seconds, wake)
        finally:
            life.wake = None

    def _attach(self, transport: asyncio.Transport) -> None:
        self._transport = transport
        self._lines.reconnected()
        self.connected = True
        self.counters.connects += 1
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
            self.counters.hook_errors += 1
            logger.error("serial port %r: on_connect hook failed: %r", self.name, exc, exc_info=exc)

    def _call_receiver(self, fn: Callable[..., Any], *args: Any) -> None:
        try:
            fn(*args)
        except Exception as exc:
            self.counters.receiver_errors += 1
            logger.error("serial port %r: receiver %r raised %r", self.name, fn, exc, exc_info=exc)

    def _feed_receiver(self, data: bytes) -> None:
        self.counters.bytes_received += len(data)
        try:
            self.receiver.data_received(data)  # type: ignore[union-attr]
        except Exception as exc:
            self.counters.receiver_errors += 1
            now = self._now() if self._now is not None else 0.0
            if self._log.allow("receiver", now):
                logger.error("serial port %r: receiver failed on %d bytes: %r", self.name, len(data), exc)

    def _feed_lines(self, data: bytes) -> None:
        self.counters.bytes_received += len(data)
        self._lines.feed(data, self._now, self.counters)  # type: ignore[arg-type]  # set before any data


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
