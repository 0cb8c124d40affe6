"""A joystick device model: a FIFO at a path, fed with the bytes the Linux joystick driver would send.

:class:`~asyncdonkey.hw.joystick.JoystickReader` opens a path, registers the fd with the event loop and reads
8-byte ``<IhBB`` events. This model puts a named pipe (FIFO) at a path of your choice and writes exactly those
bytes into it, so the reader's real code (non-blocking open, ``add_reader``, partial reads, end of file) runs
unchanged, byte for byte:

* **plugging in** creates the FIFO and writes the kernel's synthetic initial-state events (type | 0x80) for
  every axis and button, as the driver does when a device is opened;
* :meth:`JoystickModel.move_axis`, :meth:`press`, :meth:`release` write one event each;
  :meth:`write_raw` writes arbitrary bytes (half an event, to test partial reads);
* :meth:`unplug` closes the writing end (the reader sees end of file, as a pipe reports a vanished writer)
  and removes the FIFO, so reopening fails until :meth:`plug` is called again.

Axis values are the driver's raw range, -32767..32767. Event timestamps are milliseconds from ``clock``.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from pathlib import Path

from ..hw.joystick import AXIS_MAX, JS_EVENT_AXIS, JS_EVENT_BUTTON, encode_event

__all__ = ["JoystickModel"]


class JoystickModel:
    """A gamepad with ``n_axes`` axes and ``n_buttons`` buttons behind a FIFO at ``path``.

    Args:
        path: where the device node appears (e.g. ``tmp_path / "js0"``).
        n_axes, n_buttons: the pad's layout (6 axes and 11 buttons: an Xbox-style pad under xpad).
        plugged: create the device at once.
        clock: seconds for the events' millisecond timestamps.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        n_axes: int = 6,
        n_buttons: int = 11,
        *,
        plugged: bool = True,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.path = Path(path)
        self.axes = [0] * n_axes
        self.buttons = [False] * n_buttons
        self.clock = clock
        self.bytes_written = 0
        self._fd: int | None = None
        if plugged:
            self.plug()

    @property
    def plugged(self) -> bool:
        return self._fd is not None

    def _ms(self) -> int:
        return int(self.clock() * 1000) & 0xFFFFFFFF

    def plug(self) -> None:
        """Make the device appear and queue its initial-state events (axes and buttons with the init flag)."""
        if self._fd is not None:
            return
        if self.path.exists():
            self.path.unlink()
        os.mkfifo(self.path)
        # O_RDWR never blocks on a FIFO and keeps a writer attached while no reader has it open yet.
        self._fd = os.open(self.path, os.O_RDWR | os.O_NONBLOCK)
        t = self._ms()
        init = b"".join(encode_event(t, int(b), JS_EVENT_BUTTON, n, init=True) for n, b in enumerate(self.buttons))
        init += b"".join(encode_event(t, v, JS_EVENT_AXIS, n, init=True) for n, v in enumerate(self.axes))
        self.write_raw(init)

    def unplug(self) -> None:
        """The device vanishes: the reader gets end of file and the path is gone."""
        fd, self._fd = self._fd, None
        if fd is not None:
            os.close(fd)
        if self.path.exists():
            self.path.unlink()

    close = unplug

    def write_raw(self, data: bytes) -> None:
        """Write bytes as they are (any length; need not be whole events)."""
        if self._fd is None:
            raise RuntimeError(f"JoystickModel({self.path}): unplugged; plug() it first")
        view = memoryview(data)
        while view:
            n = os.write(self._fd, view)
            view = view[n:]
            self.bytes_written += n

    def event_bytes(self, kind: int, number: int, value: int) -> bytes:
        """The 8 bytes of one event now (for tests that split events by hand)."""
        return encode_event(self._ms(), value, kind, number)

    def move_axis(self, n: int, value: int) -> None:
        """Move axis ``n`` to the raw ``value`` (-32767..32767)."""
        if not -AXIS_MAX - 1 <= value <= AXIS_MAX:
            raise ValueError(f"JoystickModel: axis value must be in -32768..32767, got {value!r}")
        self.axes[n] = int(value)
        self.write_raw(self.event_bytes(JS_EVENT_AXIS, n, int(value)))

    def press(self, n: int) -> None:
        self.buttons[n] = True
        self.write_raw(self.event_bytes(JS_EVENT_BUTTON, n, 1))

    def release(self, n: int) -> None:
        self.buttons[n] = False
        self.write_raw(self.event_bytes(JS_EVENT_BUTTON, n, 0))

    def click(self, n: int) -> None:
        """Press and release button ``n`` (two events, written back to back)."""
        self.press(n)
        self.release(n)
