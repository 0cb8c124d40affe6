"""Donkeycar's Arduino wheel-encoder protocol (``r`` / ``p`` / ``c<ms>``) and an async client for it.

The microcontroller sketches Donkeycar ships (``arduino/mono_encoder``, ``arduino/quadrature_encoder``) take
one command per line (``"\\n"``-terminated):

* ``r`` — zero the tick counters;
* ``p`` — send one reading now;
* ``c<ms>`` — send a reading every ``ms`` milliseconds; a bare ``c`` stops.

and answer ``"{ticks},{millis}\\r\\n"``, a second encoder appended as ``";{ticks},{millis}"``. Ticks are the
board's 32-bit signed ``long``; ``millis`` its unsigned 32-bit milliseconds since power-up. Both wrap, so
differences are taken modulo 2**32 here (:func:`tick_delta`, :func:`millis_delta`).

:class:`ArduinoEncoder` runs the protocol over a :class:`~asyncdonkey.hw.serial_port.SerialPort` in
*continuous* mode: the board pushes readings at ``stream_ms`` and the event loop reads them as they arrive
(Donkeycar's ``SerialEncoder`` instead sends ``p`` and polls the port from a thread). After every (re)connect
it sends ``r`` then ``c<ms>``; if no reading arrives for ``watchdog_s`` it sends ``c<ms>`` again, which
recovers a board that rebooted without the port noticing (an Uno resets when the port opens and ignores
commands for its first second or two while the bootloader runs).
"""

from __future__ import annotations

import logging
import re
from collections.abc import Callable
from dataclasses import dataclass

from ..clock import get_clock
from ..errors import AsyncdonkeyError
from ..ratelimit import LogThrottle
from .serial_port import Line, SerialPort

__all__ = [
    "CMD_POLL",
    "CMD_RESET",
    "CMD_STOP_CONTINUOUS",
    "ArduinoEncoder",
    "EncoderProtocolError",
    "EncoderReading",
    "continuous",
    "millis_delta",
    "parse_reading",
    "tick_delta",
]

logger = logging.getLogger(__name__)

CMD_RESET = b"r\n"
CMD_POLL = b"p\n"
CMD_STOP_CONTINUOUS = b"c\n"

_PAIR = re.compile(r"(-?[0-9]{1,10}),([0-9]{1,10})")
_INT32_MIN, _INT32_MAX = -(1 << 31), (1 << 31) - 1
_UINT32_MAX = (1 << 32) - 1


def continuous(ms: int) -> bytes:
    """The command that starts continuous mode with a reading every ``ms`` milliseconds (``c<ms>\\n``)."""
    if not (isinstance(ms, int) and 0 <= ms <= _UINT32_MAX):
        raise ValueError(f"encoder continuous mode: ms must be an int in 0..{_UINT32_MAX}, got {ms!r}")
    return b"c%d\n" % ms


class EncoderProtocolError(AsyncdonkeyError, ValueError):
    """A line from the encoder board that is not ``ticks,millis[;ticks,millis]``."""


@dataclass(frozen=True, slots=True)
class EncoderReading:
    """One encoder's count and the board's millis when it was read."""

    ticks: int
    millis: int


def parse_reading(text: str) -> tuple[EncoderReading, ...]:
    """Parse ``"{ticks},{millis}"`` with optional ``";{ticks},{millis}"`` groups; surrounding blanks are ignored.

    Raises :class:`EncoderProtocolError` naming what was wrong; never anything else.
    """
    if not isinstance(text, str):
        raise EncoderProtocolError(f"encoder reading must be text, got {type(text).__name__}")
    out = []
    for group in text.strip().split(";"):
        m = _PAIR.fullmatch(group.strip())
        if m is None:
            raise EncoderProtocolError(f"encoder reading {text!r}: expected 'ticks,millis' groups, got {group!r}")
        ticks, millis = int(m.group(1)), int(m.group(2))
        if not _INT32_MIN <= ticks <= _INT32_MAX:
            raise EncoderProtocolError(f"encoder reading {text!r}: ticks {ticks} outside a 32-bit long")
        if millis > _UINT32_MAX:
            raise EncoderProtocolError(f"encoder reading {text!r}: millis {millis} outside 32 bits")
        out.append(EncoderReading(ticks, millis))
    return tuple(out)


def tick_delta(previous: int, current: int) -> int:
    """Signed change of a 32-bit tick counter, correct across wrap-around."""
    return ((current - previous + (1 << 31)) & _UINT32_MAX) - (1 << 31)


def millis_delta(previous: int, current: int) -> int:
    """Milliseconds elapsed on the board's 32-bit clock, correct across its 49.7-day wrap."""
    return (current - previous) & _UINT32_MAX


ReadingCallback = Callable[[tuple[EncoderReading, ...], float, int], None]


class ArduinoEncoder:
    """Keeps an encoder board streaming over a (reconnecting) serial port and hands each reading on.

    ``await encoder.run(callback)`` runs until :meth:`close`; ``callback(readings, timestamp, epoch)`` gets
    each parsed line, the runtime-clock time it arrived, and the connection number (it changes after a
    reconnect, when the board's counters and millis have restarted).

    Args:
        port: a device path (a :class:`SerialPort` is made) or a ready :class:`SerialPort` (its
            ``on_connect`` is taken over).
        baudrate: the sketch's ``Serial.begin`` rate (Donkeycar's ``ODOM_SERIAL_BAUDRATE``, 115200).
        stream_ms: continuous-mode period asked of the board (16 ms ≈ Donkeycar's 60 Hz encoder polling).
        watchdog_s: with no reading for this long, ask for the stream again (counted in ``stream_restarts``).
    """

    def __init__(
        self,
        port: str | SerialPort,
        baudrate: int = 115200,
        *,
        stream_ms: int = 16,
        watchdog_s: float = 0.5,
        name: str | None = None,
    ) -> None:
        self._stream_cmd = continuous(stream_ms)
        if not watchdog_s > 0:
            raise ValueError(f"ArduinoEncoder: watchdog_s must be positive, got {watchdog_s!r}")
        if isinstance(port, SerialPort):
            self.port = port
        else:
            self.port = SerialPort(port, baudrate, skip_first_line=True, max_line_length=64, name=name or "encoder")
        self.port.on_connect = self._on_connect
        self.stream_ms = stream_ms
        self.watchdog_s = float(watchdog_s)
        self.readings = 0
        self.bad_lines = 0
        self.stream_restarts = 0
        self._log = LogThrottle(5.0)
        self._closing = False

    def _on_connect(self, port: SerialPort) -> None:
        port.write(CMD_RESET)
        port.write(self._stream_cmd)

    async def run(self, callback: ReadingCallback) -> None:
        """Read readings until :meth:`close`; the serial port is opened and supervised meanwhile."""
        if self._closing:
            return
        port = self.port
        now = get_clock().now

        def handle(line: Line) -> None:
            try:
                readings = parse_reading(line.text)
            except EncoderProtocolError as exc:
                self.bad_lines += 1
                if self._log.allow("bad", now()):
                    logger.warning("encoder %r: %s (%d bad lines so far)", port.name, exc, self.bad_lines)
                return
            self.readings += 1
            callback(readings, line.timestamp, port.connects)

        await port.serve_lines(handle, idle_s=self.watchdog_s, on_idle=self._restart_stream)

    def _restart_stream(self, port: SerialPort) -> None:
        self.stream_restarts += 1
        logger.info(
            "encoder %r: no reading for %.2f s; asking for the stream again (#%d)",
            port.name,
            self.watchdog_s,
            self.stream_restarts,
        )
        port.write(self._stream_cmd)

    async def close(self) -> None:
        """Stop the board's stream (``c``), then close the port."""
        self._closing = True
        if self.port.connected:
            self.port.write(CMD_STOP_CONTINUOUS)
        await self.port.close()
