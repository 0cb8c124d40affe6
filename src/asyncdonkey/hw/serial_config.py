"""``SerialConfig``: every setting of a :class:`~asyncdonkey.hw.serial_port.SerialPort`, its default and its check.

Why a separate object: what a serial port can be told is listed here once instead of among the port's
connection state and counters; the settings are checked once, when the config is made (a bad one is refused with
a one-line error naming the port and the setting, before anything opens); and a frozen config can be shared
between cars and tests and varied with :func:`dataclasses.replace` (the same line settings for another device
path). What the port is *wired to* (a binary-mode ``receiver``, an ``on_connect`` hook) is not a setting: the
port takes those itself.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Final

import serial

__all__ = ["PARITIES", "SERIAL_SETTINGS", "SerialConfig"]

#: the parity letters a config takes, and pyserial's constants for them
PARITIES: Final = {"N": serial.PARITY_NONE, "E": serial.PARITY_EVEN, "O": serial.PARITY_ODD}


@dataclass(frozen=True, slots=True)
class SerialConfig:
    """A serial port's settings (``docs/hardware-serial.md``). Made, checked, then never changed.

    Args:
        port: device path (prefer a stable ``/dev/serial/by-id/...`` path) or a pyserial URL.
        baudrate, bytesize, parity (``"N"``, ``"E"``, ``"O"``), stopbits: line settings (default 115200 8N1).
        max_lines: complete lines kept for consumers; the oldest is dropped (and counted) when full.
        max_line_length: longer lines are dropped and counted, never buffered without bound.
        encoding: how lines are decoded; undecodable lines are dropped and counted.
        skip_first_line: drop the first line after each (re)connect. A device that was already streaming
            when the port opened makes the first "line" a tail fragment, which for a protocol without a
            checksum (the wheel encoder) would parse as a wrong value.
        backoff_initial_s, backoff_max_s: retry delays after a failed open, doubling up to the maximum; the
            first retry after a disconnect waits ``backoff_initial_s``.
        max_write_buffer: bytes the transport may hold unsent before writes are refused.
        name: used in log messages (default: the port path; see :attr:`label`).
    """

    port: str
    baudrate: int = 115200
    bytesize: int = 8
    parity: str = "N"
    stopbits: float = 1
    max_lines: int = 256
    max_line_length: int = 256
    encoding: str = "ascii"
    skip_first_line: bool = False
    backoff_initial_s: float = 0.05
    backoff_max_s: float = 2.0
    max_write_buffer: int = 4096
    name: str | None = None

    @property
    def label(self) -> str:
        """How logs and errors name the port: ``name``, or the port path."""
        return self.name or str(self.port)

    def __post_init__(self) -> None:
        """Check every setting; the error names the port and the setting."""
        where = f"SerialPort({self.label!r})"
        port, baudrate = self.port, self.baudrate
        if not isinstance(port, str) or not port:
            raise ValueError(f"{where}: port must be a device path such as '/dev/ttyACM0', got {port!r}")
        if not (isinstance(baudrate, int) and baudrate > 0):
            raise ValueError(f"{where}: baudrate must be a positive int, got {baudrate!r}")
        if self.parity not in PARITIES:
            raise ValueError(f"{where}: parity must be one of {sorted(PARITIES)}, got {self.parity!r}")
        if self.bytesize not in (5, 6, 7, 8):
            raise ValueError(f"{where}: bytesize must be 5, 6, 7 or 8, got {self.bytesize!r}")
        if self.stopbits not in (1, 1.5, 2):
            raise ValueError(f"{where}: stopbits must be 1, 1.5 or 2, got {self.stopbits!r}")
        for name in ("max_lines", "max_line_length"):
            value = getattr(self, name)
            if not (isinstance(value, int) and value > 0):
                raise ValueError(f"{where}: {name} must be a positive int, got {value!r}")
        initial, most = self.backoff_initial_s, self.backoff_max_s
        if not 0 < initial <= most:
            raise ValueError(f"{where}: need 0 < backoff_initial_s <= backoff_max_s, got {initial!r}, {most!r}")
        "".encode(self.encoding)  # unknown encodings fail here, not on the first line
        object.__setattr__(self, "backoff_initial_s", float(initial))  # frozen: stored once, as floats
        object.__setattr__(self, "backoff_max_s", float(most))


#: the names of :class:`SerialConfig`'s settings (the keywords ``SerialPort`` takes besides what it is wired to)
SERIAL_SETTINGS: Final = frozenset(f.name for f in fields(SerialConfig))
