"""Serial devices on the far end of a pseudo-terminal: a wheel-encoder Arduino, a GPS receiver, an RPLidar A1.

Why a pty and not a mock: the driver under test opens a real tty path with pyserial, the kernel does the
framing and buffering, and an unplug is a real hang-up the driver sees as EOF/EIO, exactly as with a USB
adapter. Each peer:

* runs on the event loop of the test (an asyncio reader on the master fd, timers from ``loop.call_at``), so
  on a :class:`~asyncdonkey.testing.VirtualClockLoop` its streaming and its clock (the encoder's ``millis``,
  the GPS fix times, the lidar's rotation) follow virtual time;
* is reachable at a **stable symlink** ``<tempdir>/usb-asyncdonkey_<name>-if00``, like
  ``/dev/serial/by-id``. :meth:`PtyPeer.unplug` closes the pty pair and removes the link (the driver's read
  fails, reopening fails); :meth:`PtyPeer.plug` opens a new pty pair and points the link at it, so a driver
  that reconnects to the same path finds the device again;
* records every byte the driver sent (:attr:`PtyPeer.received`) so tests can assert exact bytes on the wire;
* makes its writes **visible before returning**: Linux hands pty data to the reading side from a kernel
  worker, a few microseconds (or, on a loaded machine, milliseconds) after ``write()``. On a virtual clock
  that gap is enough for the loop to see "nothing readable" and jump time ahead, so data would arrive late in
  virtual time by a random number of timers. After each write the peer spins (bounded by ``settle_s`` of
  real time) until the bytes are readable on the driver's side; the driver runs on the same thread and
  cannot read meanwhile, so the check is exact. Commands the *driver* writes still reach the peer after
  that worker's delay, which on a virtual clock can be several timer jumps: tests should not depend on
  the exact virtual time a command arrives (wait for the device's first answer instead).

The protocol encoders here are written independently of the drivers in :mod:`asyncdonkey.hw` (a shared
encoder would hide a bug common to both sides).

Usage (inside a running event loop)::

    with EncoderPeer() as arduino:
        port = SerialPort(arduino.path)
        arduino.set_speed(100.0)      # ticks per second
        ...
        arduino.unplug(); ...; arduino.plug()
"""

from __future__ import annotations

import asyncio
import contextlib
import datetime as _dt
import fcntl
import math
import os
import random
import re
import shutil
import struct
import tempfile
import termios
import time
import tty
from collections.abc import Callable

__all__ = [
    "EncoderPeer",
    "LinePeer",
    "NmeaPeer",
    "PtyPeer",
    "RPLidarPeer",
    "SimulatedWheel",
    "nmea_sentence",
]


class PtyPeer:
    """A serial device model on the master side of a pty; the driver opens :attr:`path`.

    Subclasses override :meth:`data_received`, :meth:`on_plug` and :meth:`on_unplug`; they write with
    :meth:`send`. Output the driver is not reading yet is kept in a bounded buffer and written when the
    pty drains; what does not fit is counted in :attr:`bytes_dropped` (a real UART drops it too).
    """

    #: bytes held while the pty is full; beyond this output is dropped and counted
    max_pending = 1 << 16
    #: real seconds a write may wait for the kernel to make it readable on the driver's side (see above)
    settle_s = 0.05

    def __init__(self, name: str = "peer", *, link_dir: str | None = None) -> None:
        if not re.fullmatch(r"[A-Za-z0-9_.-]+", name):
            raise ValueError(f"{type(self).__name__}: name must be a plain file-name token, got {name!r}")
        self.name = name
        self._tmpdir = tempfile.mkdtemp(prefix="asyncdonkey-serial-") if link_dir is None else None
        #: the stable path to give the driver (a symlink to the current pty slave)
        self.path = os.path.join(link_dir or self._tmpdir or "", f"usb-asyncdonkey_{name}-if00")
        #: the current slave device (``/dev/pts/N``), ``None`` while unplugged
        self.tty_path: str | None = None
        self.master_fd: int | None = None
        self._slave_fd: int | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._pending = bytearray()
        self._writer_on = False
        #: every byte the driver wrote to the device, across plugs
        self.received = bytearray()
        self.bytes_sent = 0
        self.bytes_dropped = 0
        self.plugs = 0
        self.unplugs = 0

    # --------------------------------------------------------------------------------------------- plug
    @property
    def plugged(self) -> bool:
        return self.master_fd is not None

    def plug(self) -> None:
        """Connect the device: a new pty pair in raw mode, the stable link pointed at its slave."""
        if self.plugged:
            return
        loop = self._loop = asyncio.get_running_loop()
        master, slave = os.openpty()
        # Raw mode on the slave side: no echo, no CR/LF translation, 8-bit clean (the driver sets it again).
        tty.setraw(slave)
        os.set_blocking(master, False)
        self.master_fd, self._slave_fd = master, slave
        self.tty_path = os.ttyname(slave)
        tmp = f"{self.path}.{os.getpid()}.tmp"
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        os.symlink(self.tty_path, tmp)
        os.replace(tmp, self.path)  # atomic: the driver never sees a half-made link
        loop.add_reader(master, self._readable)
        self.plugs += 1
        self.on_plug()

    def unplug(self) -> None:
        """Disconnect the device: the link disappears and the driver's open pty hangs up."""
        if not self.plugged:
            return
        self.on_unplug()
        loop, master, slave = self._loop, self.master_fd, self._slave_fd
        assert loop is not None and master is not None and slave is not None
        loop.remove_reader(master)
        if self._writer_on:
            loop.remove_writer(master)
            self._writer_on = False
        with contextlib.suppress(FileNotFoundError):
            os.unlink(self.path)
        self.master_fd = self._slave_fd = None
        self.tty_path = None
        self._pending.clear()
        os.close(master)
        os.close(slave)
        self.unplugs += 1

    def close(self) -> None:
        """Unplug and remove the temporary directory."""
        self.unplug()
        if self._tmpdir is not None:
            shutil.rmtree(self._tmpdir, ignore_errors=True)
            self._tmpdir = None

    def __enter__(self) -> PtyPeer:
        self.plug()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------------------------------------ io
    def now(self) -> float:
        """The peer's clock: the loop's time (virtual on a VirtualClockLoop)."""
        assert self._loop is not None, "peer is not plugged in"
        return self._loop.time()

    def send(self, data: bytes) -> None:
        """Transmit ``data`` to the driver (dropped while unplugged)."""
        if self.master_fd is None:
            self.bytes_dropped += len(data)
            return
        if self._pending:
            self._queue(data)
            return
        before = self._readable_by_driver()
        try:
            n = os.write(self.master_fd, data)
        except BlockingIOError:
            n = 0
        self.bytes_sent += n
        self._settle(before, n)
        if n < len(data):
            self._queue(data[n:])

    def _queue(self, data: bytes) -> None:
        room = self.max_pending - len(self._pending)
        if room < len(data):
            self.bytes_dropped += len(data) - max(room, 0)
            data = data[: max(room, 0)]
        self._pending += data
        if not self._writer_on and self._loop is not None and self.master_fd is not None:
            self._loop.add_writer(self.master_fd, self._writable)
            self._writer_on = True

    def _writable(self) -> None:
        if self.master_fd is None:
            return
        before = self._readable_by_driver()
        try:
            n = os.write(self.master_fd, self._pending)
        except BlockingIOError:
            return
        self.bytes_sent += n
        self._settle(before, n)
        del self._pending[:n]
        if not self._pending and self._loop is not None:
            self._loop.remove_writer(self.master_fd)
            self._writer_on = False

    def _readable_by_driver(self) -> int:
        """Bytes waiting in the tty's input queue on the driver's side (FIONREAD on our slave fd)."""
        if self._slave_fd is None:
            return 0
        try:
            return struct.unpack("i", fcntl.ioctl(self._slave_fd, termios.FIONREAD, b"\0\0\0\0"))[0]
        except OSError:
            return 0

    def _settle(self, before: int, n: int) -> None:
        """Spin until ``n`` more bytes are readable by the driver, it started reading, or ``settle_s`` passed."""
        if n <= 0:
            return
        target = min(before + n, 4000)  # the line discipline's read buffer holds about 4 KiB
        deadline = time.perf_counter() + self.settle_s
        last = before
        while True:
            seen = self._readable_by_driver()
            if seen >= target or seen < last or time.perf_counter() > deadline:
                return
            last = seen
            os.sched_yield()  # the kernel worker that moves the bytes may be queued on this very CPU

    def _readable(self) -> None:
        if self.master_fd is None:
            return
        try:
            data = os.read(self.master_fd, 4096)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:  # EIO: no slave side open (cannot happen while we hold ours, but be safe)
            return
        if data:
            self.received += data
            self.data_received(data)

    # ----------------------------------------------------------------------------------------- for subclasses
    def data_received(self, data: bytes) -> None:
        """Bytes the driver wrote. Override."""

    def on_plug(self) -> None:
        """Power-up: called after a new pty pair is in place. Override."""

    def on_unplug(self) -> None:
        """Power loss: called before the pty pair is closed. Override (cancel timers here)."""


class LinePeer(PtyPeer):
    """A peer that receives newline-terminated commands (recorded in :attr:`commands`, CR stripped)."""

    def __init__(self, name: str = "peer", *, link_dir: str | None = None) -> None:
        super().__init__(name, link_dir=link_dir)
        self._rx_line = bytearray()
        #: every command line received, across plugs
        self.commands: list[str] = []

    def data_received(self, data: bytes) -> None:
        buf = self._rx_line
        buf += data
        while True:
            nl = buf.find(b"\n")
            if nl < 0:
                break
            raw = bytes(buf[:nl]).rstrip(b"\r")
            del buf[: nl + 1]
            text = raw.decode("ascii", "replace")
            self.commands.append(text)
            self.line_received(text)

    def on_unplug(self) -> None:
        self._rx_line.clear()

    def line_received(self, text: str) -> None:
        """One command line. Override."""


# ====================================================================================== wheel encoder
class SimulatedWheel:
    """An encoder disc turning at a settable rate, integrated exactly between speed changes.

    ``position`` is signed (a quadrature encoder's count); ``travel`` only grows (a single-channel encoder
    counts every slot whichever way the wheel turns).
    """

    def __init__(self) -> None:
        self._t0: float | None = None
        self._pos0 = 0.0
        self._travel0 = 0.0
        self.rate = 0.0

    def _advance(self, now: float) -> None:
        if self._t0 is not None:
            dt = now - self._t0
            self._pos0 += self.rate * dt
            self._travel0 += abs(self.rate) * dt
        self._t0 = now

    def set_rate(self, ticks_per_s: float, now: float) -> None:
        self._advance(now)
        self.rate = float(ticks_per_s)

    def position(self, now: float) -> float:
        if self._t0 is None:
            return 0.0
        return self._pos0 + self.rate * (now - self._t0)

    def travel(self, now: float) -> float:
        if self._t0 is None:
            return 0.0
        return self._travel0 + abs(self.rate) * (now - self._t0)

    def count(self, now: float, quadrature: bool) -> int:
        x = self.position(now) if quadrature else self.travel(now)
        return math.floor(x + 1e-9)


def _int32(v: int) -> int:
    return ((v + (1 << 31)) & 0xFFFFFFFF) - (1 << 31)


class EncoderPeer(LinePeer):
    """Donkeycar's Arduino encoder sketch (``mono_encoder.ino`` / ``quadrature_encoder.ino``) as a device model.

    Protocol, as the sketch implements it: commands one per line; ``r`` zeroes the tick counters; ``p`` sends
    one reading now; ``c<ms>`` sends a reading every ``ms`` milliseconds (the first at once); ``c`` alone stops;
    anything else is ignored. A reading is ``"{ticks},{millis}"`` per encoder joined by ``";"``, ended by
    ``println`` (``"\\r\\n"``). Ticks are a 32-bit ``long``; millis an unsigned 32-bit count since power-up.

    Power-up (every :meth:`plug`) resets the board as a USB re-plug does: counters at 0, millis from 0,
    continuous mode off. ``millis`` may be replaced by your own clock (``millis=lambda: ...``).

    Args:
        encoders: 1 or 2 wheels (the sketch's ``ENCODER_2_PIN``).
        quadrature: signed counts (True) or a single-channel count that only grows (False).
        millis: a callable returning the board's millis; default: loop time since power-up.
        boot_s: after power-up, commands are ignored for this long (an Uno's bootloader runs for 1-2 s
            after the port opens; the sketch never sees what was sent meanwhile).
    """

    def __init__(
        self,
        name: str = "encoder",
        *,
        encoders: int = 1,
        quadrature: bool = True,
        millis: Callable[[], int] | None = None,
        boot_s: float = 0.0,
        link_dir: str | None = None,
    ) -> None:
        if encoders not in (1, 2):
            raise ValueError(f"EncoderPeer: encoders must be 1 or 2, got {encoders!r}")
        super().__init__(name, link_dir=link_dir)
        self.wheels = [SimulatedWheel() for _ in range(encoders)]
        self.quadrature = quadrature
        self._millis_fn = millis
        self.boot_s = float(boot_s)
        #: commands that arrived while the bootloader ran, and were lost
        self.ignored_while_booting = 0
        self._boot = 0.0
        self._zero = [0] * encoders
        self.continuous = False
        self.delay_ms = 0
        self._timer: asyncio.TimerHandle | None = None
        #: readings sent, as the exact text lines (without CR LF)
        self.sent_lines: list[str] = []
        self.unknown_commands = 0

    # the simulated wheel
    def set_speed(self, ticks_per_s: float, wheel: int | None = None) -> None:
        """Turn wheel ``wheel`` (default: all) at ``ticks_per_s`` from now on (negative: backwards)."""
        now = self._time()
        for i, w in enumerate(self.wheels):
            if wheel is None or i == wheel:
                w.set_rate(ticks_per_s, now)

    def raw_count(self, wheel: int = 0) -> int:
        """The wheel's count since the model started, ignoring resets."""
        return self.wheels[wheel].count(self._time(), self.quadrature)

    def ticks(self, wheel: int = 0) -> int:
        """What the board would report now for ``wheel``."""
        return _int32(self.raw_count(wheel) - self._zero[wheel])

    def millis(self) -> int:
        if self._millis_fn is not None:
            return int(self._millis_fn()) & 0xFFFFFFFF
        return math.floor((self._time() - self._boot) * 1000.0 + 1e-6) & 0xFFFFFFFF

    def _time(self) -> float:
        if self._loop is None:
            self._loop = asyncio.get_running_loop()
        return self._loop.time()

    # power
    def on_plug(self) -> None:
        self._boot = self._time()
        self._zero = [self.raw_count(i) for i in range(len(self.wheels))]
        self.continuous = False
        self.delay_ms = 0

    def on_unplug(self) -> None:
        super().on_unplug()
        self._stop_stream()

    # protocol
    def line_received(self, text: str) -> None:
        if self._time() - self._boot < self.boot_s:
            self.ignored_while_booting += 1
            return
        cmd = text.strip()
        if cmd == "r":
            self._zero = [self.raw_count(i) for i in range(len(self.wheels))]
        elif cmd == "p":
            self._send_reading()
        elif cmd.startswith("c"):
            if len(cmd) == 1:
                self._stop_stream()
            elif cmd[1].isdigit():
                digits = re.match(r"\d+", cmd[1:])
                assert digits is not None
                self.delay_ms = int(digits.group())
                self._start_stream()
            # 'c' followed by a non-digit: the sketch ignores it
        else:
            self.unknown_commands += 1

    def reading_text(self) -> str:
        ms = self.millis()
        return ";".join(f"{self.ticks(i)},{ms}" for i in range(len(self.wheels)))

    def _send_reading(self) -> None:
        text = self.reading_text()
        self.sent_lines.append(text)
        self.send(text.encode("ascii") + b"\r\n")

    def _start_stream(self) -> None:
        self._stop_stream()
        self.continuous = True
        self._stream_at(self._time())

    def _stream_at(self, when: float) -> None:
        assert self._loop is not None
        self._timer = self._loop.call_at(when, self._stream_tick, when)

    def _stream_tick(self, when: float) -> None:
        self._timer = None
        if not self.continuous or not self.plugged:
            return
        self._send_reading()
        # A zero delay means "every loop()" on the board; one reading per millisecond models it.
        self._stream_at(when + max(self.delay_ms, 1) / 1000.0)

    def _stop_stream(self) -> None:
        self.continuous = False
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None


# ================================================================================================ GPS
def nmea_sentence(body: str) -> str:
    """``$<body>*HH`` with HH the XOR of the body's bytes (what a receiver sends, without CR LF)."""
    cs = 0
    for ch in body.encode("ascii"):
        cs ^= ch
    return f"${body}*{cs:02X}"


def _nmea_coord(value: float, lat: bool, decimals: int) -> tuple[str, str]:
    hemi = ("N" if value >= 0 else "S") if lat else ("E" if value >= 0 else "W")
    value = abs(value)
    deg = int(value)
    minutes = round((value - deg) * 60.0, decimals)
    if minutes >= 60.0:
        deg += 1
        minutes -= 60.0
    width = 2 if lat else 3
    return f"{deg:0{width}d}{minutes:0{3 + decimals}.{decimals}f}", hemi


# WGS84, for turning the model's metric motion into latitude/longitude
_A = 6378137.0
_E2 = 6.69437999014e-3


def _radii(lat_deg: float) -> tuple[float, float]:
    s = math.sin(math.radians(lat_deg))
    w = math.sqrt(1.0 - _E2 * s * s)
    return _A * (1.0 - _E2) / (w * w * w), _A / w  # meridian M, prime vertical N


class NmeaPeer(PtyPeer):
    """A GPS receiver streaming NMEA 0183 ``GGA`` and ``RMC`` for a moving antenna, with corruption on demand.

    The antenna starts at ``origin`` (degrees) and moves with ``velocity`` (east, north) in m/s, or along
    ``track(t) -> (east_m, north_m)`` (``t`` seconds since the first plug). Each epoch (``rate_hz``) sends GGA
    then RMC for the same instant; the UTC time is ``start_utc`` plus elapsed loop time.

    :meth:`corrupt_next` damages the next sentences: ``"checksum"`` (wrong checksum), ``"void"`` (RMC status
    V), ``"truncated"`` (cut mid-sentence, no checksum), ``"no_fix"`` (GGA quality 0), ``"garbage"`` (a line
    of noise). :attr:`sent` keeps every line sent, and :attr:`fixes` the true position of each epoch.
    """

    def __init__(
        self,
        name: str = "gps",
        *,
        origin: tuple[float, float] = (37.7749, -122.4194),
        velocity: tuple[float, float] = (0.0, 0.0),
        track: Callable[[float], tuple[float, float]] | None = None,
        rate_hz: float = 5.0,
        decimals: int = 6,
        start_utc: _dt.datetime | None = None,
        talker: str = "GP",
        link_dir: str | None = None,
    ) -> None:
        if not rate_hz > 0:
            raise ValueError(f"NmeaPeer: rate_hz must be positive, got {rate_hz!r}")
        super().__init__(name, link_dir=link_dir)
        self.origin = origin
        self.velocity = velocity
        self.track = track
        self.rate_hz = float(rate_hz)
        self.decimals = decimals
        self.start_utc = start_utc or _dt.datetime(2024, 6, 1, 12, 0, 0, tzinfo=_dt.UTC)
        self.talker = talker
        self.t_start: float | None = None
        self._timer: asyncio.TimerHandle | None = None
        self._corrupt: list[str] = []
        #: every line sent, without CR LF
        self.sent: list[str] = []
        #: (t, latitude, longitude) of each epoch sent with a valid fix
        self.fixes: list[tuple[float, float, float]] = []

    def corrupt_next(self, kind: str, count: int = 1) -> None:
        kinds = ("checksum", "void", "truncated", "no_fix", "garbage")
        if kind not in kinds:
            raise ValueError(f"NmeaPeer.corrupt_next: kind must be one of {kinds}, got {kind!r}")
        self._corrupt.extend([kind] * count)

    def send_line(self, text: str) -> None:
        self.sent.append(text)
        self.send(text.encode("ascii", "replace") + b"\r\n")

    def offset_m(self, t: float) -> tuple[float, float]:
        if self.track is not None:
            return self.track(t)
        return self.velocity[0] * t, self.velocity[1] * t

    def position(self, t: float) -> tuple[float, float]:
        """True (latitude, longitude) ``t`` seconds after the first plug."""
        east, north = self.offset_m(t)
        lat0, lon0 = self.origin
        m, n = _radii(lat0)
        lat = lat0 + math.degrees(north / m)
        lon = lon0 + math.degrees(east / (n * math.cos(math.radians((lat + lat0) / 2.0))))
        return lat, lon

    def on_plug(self) -> None:
        now = self.now()
        if self.t_start is None:
            self.t_start = now
        self._schedule(now)

    def on_unplug(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None

    def _schedule(self, when: float) -> None:
        assert self._loop is not None
        self._timer = self._loop.call_at(when, self._epoch, when)

    def _epoch(self, when: float) -> None:
        self._timer = None
        if not self.plugged:
            return
        assert self.t_start is not None
        t = when - self.t_start
        lat, lon = self.position(t)
        utc = self.start_utc + _dt.timedelta(seconds=t)
        hhmmss = f"{utc:%H%M%S}.{utc.microsecond // 10000:02d}"
        ddmmyy = f"{utc:%d%m%y}"
        la, ns = _nmea_coord(lat, True, self.decimals)
        lo, ew = _nmea_coord(lon, False, self.decimals)
        valid = True
        for kind in ("gga", "rmc"):
            fault = self._corrupt.pop(0) if self._corrupt else None
            if kind == "gga":
                quality = "0" if fault == "no_fix" else "1"
                body = f"{self.talker}GGA,{hhmmss},{la},{ns},{lo},{ew},{quality},08,0.9,12.3,M,-25.0,M,,"
            else:
                status = "V" if fault == "void" else "A"
                body = f"{self.talker}RMC,{hhmmss},{status},{la},{ns},{lo},{ew},0.5,54.7,{ddmmyy},,,A"
            line = nmea_sentence(body)
            if fault == "checksum":
                wrong = (int(line[-2:], 16) ^ 0x5A) & 0xFF
                line = f"{line[:-2]}{wrong:02X}"
            elif fault == "truncated":
                line = line[: len(line) // 2]
            elif fault == "garbage":
                line = "\x7f#%!garbage)(*&"
            if fault is not None:
                valid = False
            self.send_line(line)
        if valid:
            self.fixes.append((when, lat, lon))
        self._schedule(when + 1.0 / self.rate_hz)


# ============================================================================================ RPLidar
class RPLidarPeer(PtyPeer):
    """An RPLidar A1 in a rectangular room, speaking the serial protocol at the byte level.

    Requests are ``A5 <cmd>`` (commands ≥ 0x80 carry ``<size> <payload> <checksum>``). Answered: GET_INFO
    0x50 (descriptor ``A5 5A 14 00 00 00 04`` + model, firmware minor, major, hardware, 16-byte serial),
    GET_HEALTH 0x52 (``A5 5A 03 00 00 00 06`` + status, error code LE16), GET_SAMPLERATE 0x59, SCAN 0x20 /
    FORCE_SCAN 0x21 (``A5 5A 05 00 00 40 81`` then 5-byte nodes forever), STOP 0x25 (streaming stops, no
    answer), RESET 0x40 (streaming stops; after a few ms the firmware prints its ASCII banner, as the A1
    does). Unknown commands are ignored. Every request is recorded in :attr:`requests`.

    The room is ``room`` (width, depth) metres with the lidar at ``position`` facing ``heading_deg`` (0 = +x,
    counter-clockwise). RPLidar angles grow clockwise seen from above; node ``k`` of a revolution is at
    ``k * 360 / points_per_scan`` degrees plus ``angle_offset_deg``. Every ``invalid_every``-th point is
    reported as no return (distance 0, quality 0).

    Faults, while scanning, at the same byte rate: :meth:`set_fault` ``"no_start_flag"`` (valid nodes whose
    start flag is never set: a revolution that never ends), ``"noise"`` (random bytes from a seeded generator,
    ``noise_seed``: line noise in place of the nodes), ``None`` (back to normal); :meth:`stall` stops sending.
    """

    FAULTS = (None, "no_start_flag", "noise")

    #: the A1's standard scan descriptor, and the others it answers with
    SCAN_DESCRIPTOR = bytes.fromhex("a55a0500004081")
    INFO_DESCRIPTOR = bytes.fromhex("a55a1400000004")
    HEALTH_DESCRIPTOR = bytes.fromhex("a55a0300000006")
    SAMPLERATE_DESCRIPTOR = bytes.fromhex("a55a0400000015")
    BANNER = b"RP LIDAR System.\r\nFirmware Ver 1.29 - rc9, HW Ver 7\r\nModel: 18\r\n"

    def __init__(
        self,
        name: str = "rplidar",
        *,
        room: tuple[float, float] = (4.0, 3.0),
        position: tuple[float, float] = (1.5, 1.0),
        heading_deg: float = 0.0,
        scan_hz: float = 7.0,
        points_per_scan: int = 264,
        angle_offset_deg: float = 0.2,
        quality: int = 15,
        invalid_every: int = 0,
        model: int = 0x18,
        firmware: tuple[int, int] = (1, 29),
        hardware: int = 7,
        serial_number: bytes = bytes(range(16)),
        health: tuple[int, int] = (0, 0),
        noise_seed: int = 0,
        link_dir: str | None = None,
    ) -> None:
        if len(serial_number) != 16:
            raise ValueError("RPLidarPeer: serial_number must be 16 bytes")
        super().__init__(name, link_dir=link_dir)
        self.room = room
        self.position = position
        self.heading_deg = heading_deg
        self.scan_hz = float(scan_hz)
        self.points_per_scan = int(points_per_scan)
        self.angle_offset_deg = angle_offset_deg
        self.quality = quality
        self.invalid_every = invalid_every
        self.model = model
        self.firmware = firmware
        self.hardware = hardware
        self.serial_number = serial_number
        #: (status, error_code) answered to GET_HEALTH: status 0 good, 1 warning, 2 error
        self.health = health
        self._rx = bytearray()
        self._timer: asyncio.TimerHandle | None = None
        self._banner_timer: asyncio.TimerHandle | None = None
        self.scanning = False
        self._next_node = 0
        self._t_scan0 = 0.0
        #: (cmd, payload) of every request received, across plugs
        self.requests: list[tuple[int, bytes]] = []
        #: measurement nodes sent since the model was made (node-sized slots of noise included)
        self.nodes_sent = 0
        self.revolutions_started = 0
        #: the fault being simulated (one of :attr:`FAULTS`)
        self.fault: str | None = None
        self._noise = random.Random(noise_seed)

    # ----------------------------------------------------------------------------------------- the room
    def true_distance_mm(self, angle_deg: float) -> float:
        """Distance from the lidar to the wall along its (clockwise) ``angle_deg``."""
        theta = math.radians(self.heading_deg - angle_deg)
        dx, dy = math.cos(theta), math.sin(theta)
        x0, y0 = self.position
        w, h = self.room
        best = math.inf
        if dx > 1e-12:
            best = min(best, (w - x0) / dx)
        elif dx < -1e-12:
            best = min(best, -x0 / dx)
        if dy > 1e-12:
            best = min(best, (h - y0) / dy)
        elif dy < -1e-12:
            best = min(best, -y0 / dy)
        return best * 1000.0

    def node_values(self, k: int) -> tuple[bool, int, int, int]:
        """(start, quality, angle_q6, distance_q2) of the ``k``-th node since the scan started."""
        p = self.points_per_scan
        i = k % p
        angle = (i * 360.0 / p + self.angle_offset_deg) % 360.0
        angle_q6 = round(angle * 64.0) % (360 * 64)
        if self.invalid_every and k % self.invalid_every == self.invalid_every - 1:
            return i == 0, 0, angle_q6, 0
        dist = self.true_distance_mm(angle_q6 / 64.0)
        dist_q2 = min(round(dist * 4.0), 0xFFFF)
        return i == 0, self.quality, angle_q6, dist_q2

    @staticmethod
    def encode_node(start: bool, quality: int, angle_q6: int, distance_q2: int) -> bytes:
        """The 5 bytes of a standard-scan measurement node."""
        s = 1 if start else 0
        b0 = ((quality & 0x3F) << 2) | ((s ^ 1) << 1) | s
        b1 = ((angle_q6 & 0x7F) << 1) | 1  # check bit C = 1
        b2 = (angle_q6 >> 7) & 0xFF
        return bytes((b0, b1, b2, distance_q2 & 0xFF, (distance_q2 >> 8) & 0xFF))

    # --------------------------------------------------------------------------------------- protocol
    def on_plug(self) -> None:
        self._rx.clear()
        self.scanning = False

    def on_unplug(self) -> None:
        self._stop_scan()
        if self._banner_timer is not None:
            self._banner_timer.cancel()
            self._banner_timer = None

    def inject(self, data: bytes) -> None:
        """Send raw bytes (line noise, a partial node) as they are."""
        self.send(data)

    def set_fault(self, fault: str | None) -> None:
        """From the next burst on: ``"no_start_flag"``, ``"noise"`` or ``None`` (see the class docstring)."""
        if fault not in self.FAULTS:
            raise ValueError(f"RPLidarPeer: fault must be one of {self.FAULTS}, got {fault!r}")
        self.fault = fault

    def stall(self) -> None:
        """Fault: stop sending measurements without being told to (the motor stalled, the firmware hung)."""
        self._stop_scan()

    def data_received(self, data: bytes) -> None:
        rx = self._rx
        rx += data
        while rx:
            if rx[0] != 0xA5:
                del rx[0]
                continue
            if len(rx) < 2:
                return
            cmd = rx[1]
            if cmd & 0x80:
                if len(rx) < 3 or len(rx) < 4 + rx[2]:
                    return
                size = rx[2]
                payload = bytes(rx[3 : 3 + size])
                checksum = rx[3 + size]
                calc = 0
                for b in rx[: 3 + size]:
                    calc ^= b
                del rx[: 4 + size]
                if calc != checksum:
                    continue  # the firmware drops a request with a bad checksum
            else:
                payload = b""
                del rx[:2]
            self.requests.append((cmd, payload))
            self._handle(cmd)

    def _handle(self, cmd: int) -> None:
        if cmd == 0x25:  # STOP
            self._stop_scan()
        elif cmd == 0x40:  # RESET
            self._stop_scan()
            assert self._loop is not None
            self._banner_timer = self._loop.call_later(0.005, self._banner)
        elif cmd in (0x20, 0x21):  # SCAN, FORCE_SCAN
            self._stop_scan()
            self.send(self.SCAN_DESCRIPTOR)
            self._start_scan()
        elif cmd == 0x50:  # GET_INFO
            minor, major = self.firmware[1], self.firmware[0]
            self.send(
                self.INFO_DESCRIPTOR + bytes((self.model, minor, major, self.hardware)) + bytes(self.serial_number)
            )
        elif cmd == 0x52:  # GET_HEALTH
            status, code = self.health
            self.send(self.HEALTH_DESCRIPTOR + bytes((status, code & 0xFF, (code >> 8) & 0xFF)))
        elif cmd == 0x59:  # GET_SAMPLERATE: standard and express sample duration in µs
            us = round(1e6 / (self.scan_hz * self.points_per_scan))
            self.send(self.SAMPLERATE_DESCRIPTOR + us.to_bytes(2, "little") + (us // 2).to_bytes(2, "little"))

    def _banner(self) -> None:
        self._banner_timer = None
        self.send(self.BANNER)

    def _start_scan(self) -> None:
        self.scanning = True
        self._next_node = 0
        self._t_scan0 = self.now()
        self._stream(self._t_scan0)

    def _stop_scan(self) -> None:
        self.scanning = False
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None

    #: nodes are sent in bursts every this many seconds (a UART would trickle them; the content is the same)
    burst_s = 0.01

    def _stream(self, when: float) -> None:
        self._timer = None
        if not self.scanning or not self.plugged:
            return
        rate = self.scan_hz * self.points_per_scan
        due = math.floor((when - self._t_scan0) * rate + 1e-9) + 1
        out = bytearray()
        fault = self.fault
        while self._next_node < due:
            if fault == "noise":
                out += self._noise.randbytes(5)
            else:
                start, q, a, d = self.node_values(self._next_node)
                start = start and fault != "no_start_flag"
                if start:
                    self.revolutions_started += 1
                out += self.encode_node(start, q, a, d)
            self._next_node += 1
        self.nodes_sent += len(out) // 5
        if out:
            self.send(bytes(out))
        assert self._loop is not None
        self._timer = self._loop.call_at(when + self.burst_s, self._stream, when + self.burst_s)

    def revolution(self) -> list[tuple[bool, int, int, int]]:
        """The node values of one full revolution, as this model sends them."""
        return [self.node_values(k) for k in range(self.points_per_scan)]
