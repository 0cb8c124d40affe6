"""RPLidar A1 over serial: the binary protocol, a resynchronising scan decoder and an async driver.

Protocol (Slamtec's serial protocol as the A1 speaks it, 115200 8N1):

* **Request** ``A5 <cmd>``; commands ≥ 0x80 add ``<size> <payload> <checksum>`` (XOR of every byte before
  it). STOP ``0x25`` and RESET ``0x40`` get no answer (the A1 prints an ASCII banner after a reset); SCAN
  ``0x20`` / FORCE_SCAN ``0x21``, GET_INFO ``0x50``, GET_HEALTH ``0x52``, GET_SAMPLERATE ``0x59`` do.
* **Response descriptor** ``A5 5A`` + 32-bit little-endian word (low 30 bits: response length, high 2 bits:
  send mode, 1 = "multiple responses follow") + data type. GET_INFO: 20 bytes, type 0x04; GET_HEALTH: 3
  bytes, type 0x06; SCAN: length 5, mode 1, type 0x81, then measurement nodes until STOP.
* **Measurement node** (5 bytes): ``quality << 2 | S̄ << 1 | S``, ``angle_q6[6:0] << 1 | C``,
  ``angle_q6[14:7]``, ``distance_q2`` (little-endian 16 bit). ``S`` marks the first node of a new 360°
  revolution and ``S̄`` must be its inverse; the check bit ``C`` is always 1. Angle = ``angle_q6 / 64`` degrees
  (growing clockwise seen from above), distance = ``distance_q2 / 4`` mm, 0 meaning no return.

Decoding: a node failing the ``S̄``/``C`` checks (or with an angle ≥ 360°) means the byte stream is
misaligned (a dropped byte, line noise, the reset banner): the decoder slides one byte and tries again,
counting ``bad_nodes`` and ``resync_bytes`` (and ``desyncs``, the times it lost alignment). A revolution is
complete when the next ``S`` node arrives; it is published as a :class:`Scan` of numpy arrays into
:attr:`RPLidarDriver.latest`, so readers take the newest complete scan without waiting. The partial revolution
before the first ``S`` is discarded.

What a revolution can hold, and what is noise. An RPLidar A1 measures at most 8,000 samples/s and turns at
1 Hz at the slowest (A1M8 datasheet: 4,000 typical, 8,000 max; 1 to 10 Hz); the A2 and A3 (up to 16,000
samples/s, 5 Hz and faster) stay under 3,200. So a real revolution never holds more than
:data:`MAX_REVOLUTION_NODES` = 8,000 nodes: one that grows past it (a stream whose start flags are lost, a
stuck firmware) is dropped and counted in ``overlong_revolutions``, and the decoder waits for the next ``S``,
so it never keeps more than 8,000 nodes (RSS stays flat instead of growing by about 85 bytes a node). At the
other end, the standard SCAN measures at least 2,000 samples/s and no model turns faster than 20 Hz, so a real
revolution has at least 100 nodes; line noise that happens to pass the node checks makes "revolutions" of a
handful of nodes (half of the random nodes carry a start flag). A revolution under
:data:`MIN_REVOLUTION_NODES` = 50 (half the fewest real ones, for margin) is dropped and counted in
``short_revolutions``. The nodes dropped either way are counted in ``dropped_nodes``; both kinds are logged
at most once every 5 s with the count held back, and :meth:`RPLidarProtocol.stats` has every counter.

Motor: the A1's USB adapter drives the motor from DTR (DTR low = spinning); the driver lowers DTR when it
connects and raises it on close where the port supports modem lines (a pty does not; that is ignored).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..clock import DeadlineWaiter, get_clock
from ..errors import AsyncdonkeyError
from ..latest import Latest
from ..ratelimit import LogThrottle
from .serial_port import SerialPort, SerialPortClosed

__all__ = [
    "CMD_FORCE_SCAN",
    "CMD_GET_HEALTH",
    "CMD_GET_INFO",
    "CMD_GET_SAMPLERATE",
    "CMD_RESET",
    "CMD_SCAN",
    "CMD_STOP",
    "HEALTH_STATUS",
    "MAX_REVOLUTION_NODES",
    "MIN_REVOLUTION_NODES",
    "DeviceInfo",
    "Health",
    "Node",
    "RPLidarDriver",
    "RPLidarError",
    "RPLidarProtocol",
    "Scan",
    "decode_node",
    "parse_descriptor",
    "request",
]

logger = logging.getLogger(__name__)

SYNC = 0xA5
SYNC2 = 0x5A
CMD_STOP = 0x25
CMD_RESET = 0x40
CMD_SCAN = 0x20
CMD_FORCE_SCAN = 0x21
CMD_GET_INFO = 0x50
CMD_GET_HEALTH = 0x52
CMD_GET_SAMPLERATE = 0x59

TYPE_SCAN = 0x81
TYPE_INFO = 0x04
TYPE_HEALTH = 0x06
TYPE_SAMPLERATE = 0x15

MODE_SINGLE = 0
MODE_MULTI = 1

HEALTH_STATUS = {0: "good", 1: "warning", 2: "error"}
_MAX_ANGLE_Q6 = 360 * 64

#: The most nodes a real revolution holds: 8,000 samples/s (the A1's maximum) at 1 Hz (its slowest rotation).
MAX_REVOLUTION_NODES = 8000
#: Fewer nodes than this is not a revolution but noise: real ones have at least 100 (2,000 samples/s at 20 Hz).
MIN_REVOLUTION_NODES = 50


class RPLidarError(AsyncdonkeyError, RuntimeError):
    """The lidar answered something other than what was asked, or reported an error."""


def request(cmd: int, payload: bytes = b"") -> bytes:
    """The bytes of a request: ``A5 cmd`` or, with a payload, ``A5 cmd size payload checksum``."""
    if not 0 <= cmd <= 0xFF:
        raise ValueError(f"RPLidar request: cmd must be a byte, got {cmd!r}")
    if not payload:
        return bytes((SYNC, cmd))
    if len(payload) > 255:
        raise ValueError(f"RPLidar request: payload of {len(payload)} bytes is over 255")
    head = bytes((SYNC, cmd, len(payload))) + payload
    cs = 0
    for b in head:
        cs ^= b
    return head + bytes((cs,))


@dataclass(frozen=True, slots=True)
class Descriptor:
    length: int
    mode: int
    data_type: int


def parse_descriptor(data: bytes) -> Descriptor:
    """Decode a 7-byte response descriptor (raises :class:`RPLidarError` without the ``A5 5A`` start)."""
    if len(data) != 7 or data[0] != SYNC or data[1] != SYNC2:
        raise RPLidarError(f"not a response descriptor: {bytes(data).hex(' ')}")
    word = int.from_bytes(data[2:6], "little")
    return Descriptor(word & 0x3FFFFFFF, word >> 30, data[6])


@dataclass(frozen=True, slots=True)
class DeviceInfo:
    model: int
    firmware: tuple[int, int]  # (major, minor)
    hardware: int
    serial_number: str  # 32 hex digits

    @classmethod
    def decode(cls, payload: bytes) -> DeviceInfo:
        if len(payload) != 20:
            raise RPLidarError(f"GET_INFO answer must be 20 bytes, got {len(payload)}")
        return cls(payload[0], (payload[2], payload[1]), payload[3], payload[4:20].hex().upper())


@dataclass(frozen=True, slots=True)
class Health:
    status: int
    error_code: int

    @property
    def name(self) -> str:
        return HEALTH_STATUS.get(self.status, f"unknown({self.status})")

    @classmethod
    def decode(cls, payload: bytes) -> Health:
        if len(payload) != 3:
            raise RPLidarError(f"GET_HEALTH answer must be 3 bytes, got {len(payload)}")
        return cls(payload[0], payload[1] | (payload[2] << 8))


@dataclass(frozen=True, slots=True)
class Node:
    start: bool
    quality: int
    angle_deg: float
    distance_mm: float


def _check(b0: int, b1: int, b2: int) -> bool:
    return ((b0 ^ (b0 >> 1)) & 1) == 1 and (b1 & 1) == 1 and ((b1 >> 1) | (b2 << 7)) < _MAX_ANGLE_Q6


def decode_node(data: bytes) -> Node | None:
    """Decode one 5-byte node; ``None`` when the S̄/S or C checks fail (a misaligned or corrupt node)."""
    if len(data) != 5:
        return None
    b0, b1, b2, b3, b4 = data
    if not _check(b0, b1, b2):
        return None
    return Node(bool(b0 & 1), b0 >> 2, ((b1 >> 1) | (b2 << 7)) / 64.0, (b3 | (b4 << 8)) / 4.0)


@dataclass(frozen=True, slots=True)
class Scan:
    """One complete revolution, in the order measured.

    ``angles`` degrees (float32, clockwise), ``distances`` mm (float32, 0 = no return), ``qualities`` (uint8).
    ``timestamp`` is when the revolution completed (runtime clock); ``index`` counts scans from 1.
    """

    angles: np.ndarray
    distances: np.ndarray
    qualities: np.ndarray
    timestamp: float
    index: int

    def __len__(self) -> int:
        return len(self.angles)


class RPLidarProtocol:
    """The byte-level state machine; a :class:`SerialPort` in binary mode feeds it.

    States: *idle* (bytes are garbage: counted, dropped), *awaiting a descriptor* (hunt for ``A5 5A``, then
    the response of the announced length), *scanning* (5-byte nodes with resynchronisation).

    ``min_nodes`` / ``max_nodes``: revolutions with fewer nodes are dropped as noise, revolutions growing past
    ``max_nodes`` are dropped as over-long (see the module docstring for the defaults); ``name`` is used in
    the log.
    """

    def __init__(
        self,
        on_scan: Callable[[Scan], None],
        now: Callable[[], float],
        *,
        min_nodes: int = MIN_REVOLUTION_NODES,
        max_nodes: int = MAX_REVOLUTION_NODES,
        name: str = "rplidar",
    ) -> None:
        if not 1 <= min_nodes <= max_nodes:
            raise ValueError(f"RPLidarProtocol: need 1 <= min_nodes <= max_nodes, got {min_nodes}, {max_nodes}")
        self._on_scan = on_scan
        self._now = now
        self.min_nodes = int(min_nodes)
        self.max_nodes = int(max_nodes)
        self.name = name
        self._log = LogThrottle(5.0)
        self._synced = True
        self._buf = bytearray()
        self._expect: tuple[int, asyncio.Future[bytes]] | None = None
        self._descriptor: Descriptor | None = None
        self.scanning = False
        self._in_revolution = False
        self._angles: list[int] = []
        self._dists: list[int] = []
        self._quals: list[int] = []
        self.scans = 0
        self.nodes = 0
        self.bad_nodes = 0
        self.resync_bytes = 0
        self.garbage_bytes = 0
        self.unexpected_descriptors = 0
        self.desyncs = 0
        self.short_revolutions = 0
        self.overlong_revolutions = 0
        self.dropped_nodes = 0

    @property
    def pending_nodes(self) -> int:
        """Nodes of the revolution being received (never more than ``max_nodes``)."""
        return len(self._angles)

    def stats(self) -> dict[str, int]:
        """Every counter, plus ``pending_nodes``, as a dict (for reports and logs)."""
        return {
            "scans": self.scans,
            "nodes": self.nodes,
            "bad_nodes": self.bad_nodes,
            "resync_bytes": self.resync_bytes,
            "desyncs": self.desyncs,
            "short_revolutions": self.short_revolutions,
            "overlong_revolutions": self.overlong_revolutions,
            "dropped_nodes": self.dropped_nodes,
            "pending_nodes": self.pending_nodes,
            "garbage_bytes": self.garbage_bytes,
            "unexpected_descriptors": self.unexpected_descriptors,
        }

    # ----------------------------------------------------------------------------------------- control
    def expect(self, data_type: int, future: asyncio.Future[bytes]) -> None:
        """Wait for the descriptor of ``data_type``; ``future`` gets the response payload (``b""`` for SCAN)."""
        self.scanning = False
        self._reset_revolution()
        self._buf.clear()
        self._descriptor = None
        self._expect = (data_type, future)

    def stop(self) -> None:
        self.scanning = False
        self._expect = None
        self._descriptor = None
        self._buf.clear()
        self._reset_revolution()

    def connection_made(self) -> None:
        self.stop()

    def connection_lost(self, exc: BaseException | None) -> None:
        expect = self._expect
        self.stop()
        if expect is not None and not expect[1].done():
            expect[1].set_exception(ConnectionError("RPLidar: serial device lost while waiting for an answer"))

    def _reset_revolution(self) -> None:
        self._in_revolution = False
        self._angles.clear()
        self._dists.clear()
        self._quals.clear()

    # ------------------------------------------------------------------------------------------- bytes
    def data_received(self, data: bytes) -> None:
        buf = self._buf
        buf += data
        if self.scanning:
            self._nodes()
        elif self._expect is not None:
            self._response()
        else:
            self.garbage_bytes += len(buf)
            buf.clear()

    def _response(self) -> None:
        buf = self._buf
        assert self._expect is not None
        data_type, future = self._expect
        if self._descriptor is None:
            i = buf.find(b"\xa5\x5a")
            if i < 0:
                keep = 1 if buf[-1:] == b"\xa5" else 0
                self.garbage_bytes += len(buf) - keep
                del buf[: len(buf) - keep]
                return
            self.garbage_bytes += i
            del buf[:i]
            if len(buf) < 7:
                return
            d = parse_descriptor(bytes(buf[:7]))
            del buf[:7]
            if d.data_type != data_type:
                self.unexpected_descriptors += 1
                self._response()  # keep hunting for the one we asked for
                return
            self._descriptor = d
        d = self._descriptor
        if d.data_type == TYPE_SCAN:
            self._expect = None
            self._descriptor = None
            self.scanning = True
            if not future.done():
                future.set_result(b"")
            self._nodes()
            return
        if len(buf) < d.length:
            return
        payload = bytes(buf[: d.length])
        del buf[: d.length]
        self._expect = None
        self._descriptor = None
        if not future.done():
            future.set_result(payload)
        if buf:
            self.garbage_bytes += len(buf)
            buf.clear()

    def _nodes(self) -> None:
        buf = self._buf
        n = len(buf)
        i = 0
        angles, dists, quals = self._angles, self._dists, self._quals
        max_nodes = self.max_nodes
        while n - i >= 5:
            b0, b1, b2 = buf[i], buf[i + 1], buf[i + 2]
            if not (((b0 ^ (b0 >> 1)) & 1) == 1 and (b1 & 1) == 1 and ((b1 >> 1) | (b2 << 7)) < _MAX_ANGLE_Q6):
                self.bad_nodes += 1
                self.resync_bytes += 1
                if self._synced:
                    self._synced = False
                    self.desyncs += 1
                i += 1
                continue
            self._synced = True
            if b0 & 1:
                if self._in_revolution and angles:
                    self._complete()
                self._in_revolution = True
            if self._in_revolution:
                if len(angles) >= max_nodes:
                    self._drop_overlong()  # wait for the next start flag; this node is dropped with the rest
                else:
                    angles.append((b1 >> 1) | (b2 << 7))
                    dists.append(buf[i + 3] | (buf[i + 4] << 8))
                    quals.append(b0 >> 2)
            self.nodes += 1
            i += 5
        if i:
            del buf[:i]

    def _complete(self) -> None:
        """A start flag ended the revolution: publish it, or drop it as noise when too short."""
        count = len(self._angles)
        if count >= self.min_nodes:
            self._publish()
            return
        self.short_revolutions += 1
        self.dropped_nodes += count
        self._angles.clear()
        self._dists.clear()
        self._quals.clear()
        self._warn(
            "short",
            "dropped a revolution of %d node(s), fewer than %d (line noise?)",
            count,
            self.min_nodes,
        )

    def _drop_overlong(self) -> None:
        self.overlong_revolutions += 1
        self.dropped_nodes += len(self._angles) + 1
        self._reset_revolution()
        self._warn(
            "overlong",
            "dropped a revolution of over %d nodes without a start flag (lost start flags?)",
            self.max_nodes,
        )

    def _warn(self, key: str, message: str, *args: object) -> None:
        more = self._log.ready(key, self._now())
        if more is None:
            return
        logger.warning("RPLidar %r: " + message + more, self.name, *args)

    def _publish(self) -> None:
        self.scans += 1
        scan = Scan(
            np.asarray(self._angles, dtype=np.float32) / np.float32(64.0),
            np.asarray(self._dists, dtype=np.float32) / np.float32(4.0),
            np.asarray(self._quals, dtype=np.uint8),
            self._now(),
            self.scans,
        )
        self._angles.clear()
        self._dists.clear()
        self._quals.clear()
        self._on_scan(scan)


class RPLidarDriver:
    """Keeps an RPLidar A1 scanning over a reconnecting serial port; the newest scan is in :attr:`latest`.

    ``await driver.run()`` until :meth:`close`. After each (re)connect: STOP, GET_INFO, GET_HEALTH (an
    ``error`` status triggers RESET and a retry), then SCAN. If no node arrives for ``watchdog_s`` while
    connected, the scan is started again (``restarts``).

    Args:
        port: device path (e.g. ``/dev/ttyUSB0``, better its ``/dev/serial/by-id`` link); the driver makes a
            binary-mode :class:`SerialPort` (``driver.port``) with itself as the receiver.
        response_timeout_s: how long to wait for a descriptor and its answer.
        watchdog_s: silence while scanning that restarts the scan.
        on_scan: called with each complete :class:`Scan` (on the event loop thread; keep it short).
    """

    def __init__(
        self,
        port: str = "/dev/ttyUSB0",
        baudrate: int = 115200,
        *,
        response_timeout_s: float = 0.5,
        watchdog_s: float = 1.0,
        reset_wait_s: float = 0.5,
        on_scan: Callable[[Scan], None] | None = None,
    ) -> None:
        if not (response_timeout_s > 0 and watchdog_s > 0 and reset_wait_s >= 0):
            raise ValueError("RPLidarDriver: response_timeout_s and watchdog_s must be positive")
        self.latest: Latest[Scan] = Latest()
        self.on_scan = on_scan
        self._clock_now: Callable[[], float] = lambda: 0.0
        self.protocol = RPLidarProtocol(self._scan_done, lambda: self._clock_now(), name=port)
        self.port = SerialPort(port, baudrate, receiver=self, name="rplidar")
        self.response_timeout_s = float(response_timeout_s)
        self.watchdog_s = float(watchdog_s)
        self.reset_wait_s = float(reset_wait_s)
        self.info: DeviceInfo | None = None
        self.health: Health | None = None
        self.restarts = 0
        self.session_failures = 0
        self.resets_sent = 0
        self._conn_changed: asyncio.Event | None = None
        self._closing = False
        self._log = LogThrottle(5.0)

    # receiver interface for the SerialPort: forward bytes, note connection changes
    def data_received(self, data: bytes) -> None:
        self.protocol.data_received(data)

    def connection_made(self) -> None:
        self.protocol.connection_made()
        self._set_motor(True)
        if self._conn_changed is not None:
            self._conn_changed.set()

    def connection_lost(self, exc: BaseException | None) -> None:
        self.protocol.connection_lost(exc)
        if self._conn_changed is not None:
            self._conn_changed.set()

    def stats(self) -> dict[str, Any]:
        """The decoder's counters (:meth:`RPLidarProtocol.stats`) and the driver's own, as one dict."""
        return {
            **self.protocol.stats(),
            "restarts": self.restarts,
            "session_failures": self.session_failures,
            "resets_sent": self.resets_sent,
        }

    def _scan_done(self, scan: Scan) -> None:
        self.latest.publish(scan, scan.timestamp)
        if self.on_scan is not None:
            self.on_scan(scan)

    def _set_motor(self, on: bool) -> None:
        ser = self.port.serial
        if ser is None:
            return
        with contextlib.suppress(OSError, ValueError, AttributeError):
            ser.dtr = not on  # the A1 adapter: DTR low spins the motor

    # ------------------------------------------------------------------------------------------- requests
    async def _ask(self, cmd: int, data_type: int) -> bytes:
        fut: asyncio.Future[bytes] = asyncio.get_running_loop().create_future()
        self.protocol.expect(data_type, fut)
        if not self.port.write(request(cmd)):
            self.protocol.stop()
            raise ConnectionError("RPLidar: not connected")
        try:
            return await asyncio.wait_for(fut, self.response_timeout_s)
        except TimeoutError:
            self.protocol.stop()
            raise RPLidarError(f"no answer to request 0x{cmd:02X} within {self.response_timeout_s} s") from None

    async def get_info(self) -> DeviceInfo:
        self.info = DeviceInfo.decode(await self._ask(CMD_GET_INFO, TYPE_INFO))
        return self.info

    async def get_health(self) -> Health:
        self.health = Health.decode(await self._ask(CMD_GET_HEALTH, TYPE_HEALTH))
        return self.health

    def stop(self) -> None:
        """Send STOP (the device stops streaming; no answer)."""
        self.protocol.stop()
        self.port.write(request(CMD_STOP))

    async def reset(self) -> None:
        """Send RESET and wait ``reset_wait_s`` while the firmware reboots (its banner is discarded)."""
        self.protocol.stop()
        self.resets_sent += 1
        self.port.write(request(CMD_RESET))
        await get_clock().sleep(self.reset_wait_s)
        self.protocol.stop()

    async def start_scan(self) -> None:
        await self._ask(CMD_SCAN, TYPE_SCAN)

    async def _session(self, waiter: DeadlineWaiter) -> None:
        clock = get_clock()
        self.stop()
        await waiter.wait_until(clock.now() + 0.002)  # the A1 needs ≥ 1 ms after STOP before the next request
        self.protocol.stop()
        await self.get_info()
        health = await self.get_health()
        if health.status == 2:
            logger.error("RPLidar reports error status (code 0x%04X); resetting it", health.error_code)
            await self.reset()
            health = await self.get_health()
            if health.status == 2:
                raise RPLidarError(f"lidar still in error state after RESET (code 0x{health.error_code:04X})")
        await self.start_scan()

    # ------------------------------------------------------------------------------------------- running
    async def run(self) -> None:
        """Connect, scan, recover; until :meth:`close`."""
        if self._closing:
            return
        loop = asyncio.get_running_loop()
        clock = get_clock(loop)
        self._clock_now = clock.now
        self._conn_changed = asyncio.Event()
        supervisor = loop.create_task(self.port.run(), name=f"serial:{self.port.name}")
        waiter = DeadlineWaiter(loop)  # one OS timer for every pause of this run
        try:
            while not self._closing and not supervisor.done():
                try:
                    await self.port.wait_connected()
                except SerialPortClosed:
                    break
                epoch = self.port.connects
                self._conn_changed.clear()
                try:
                    await self._session(waiter)
                except (RPLidarError, ConnectionError) as exc:
                    self.session_failures += 1
                    if self._log.allow("session", clock.now()):
                        logger.warning("RPLidar %r: could not start scanning: %s", self.port.name, exc)
                    await waiter.wait_until(clock.now() + self.response_timeout_s)
                    continue
                await self._watch(epoch)
        finally:
            waiter.close()
            if not supervisor.done():
                await self.port.close()
                await asyncio.wait({supervisor}, timeout=1.0)
            if not supervisor.done():
                supervisor.cancel()

    async def _watch(self, epoch: int) -> None:
        """Return when the connection changes, or restart the scan when nodes stop coming."""
        assert self._conn_changed is not None
        seen = self.protocol.nodes
        while not self._closing and self.port.connected and self.port.connects == epoch:
            try:
                await asyncio.wait_for(self._conn_changed.wait(), self.watchdog_s)
                return
            except TimeoutError:
                pass
            if self.protocol.nodes == seen and self.port.connected and not self._closing:
                self.restarts += 1
                logger.warning(
                    "RPLidar %r: no measurements for %.1f s; restarting the scan", self.port.name, self.watchdog_s
                )
                return
            seen = self.protocol.nodes

    async def close(self) -> None:
        """STOP the scan, stop the motor, close the port."""
        self._closing = True
        if self.port.connected:
            self.stop()
            self._set_motor(False)
        if self._conn_changed is not None:
            self._conn_changed.set()
        await self.port.close()
