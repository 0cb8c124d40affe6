"""Linux joystick devices (``/dev/input/jsN``) read by the event loop itself, with unplug and reconnect.

The kernel's joystick API delivers 8-byte little-endian events ``<IhBB``: a timestamp in milliseconds, a
signed 16-bit value, a type (``0x01`` button, ``0x02`` axis, with ``0x80`` or-ed in for the synthetic events
the kernel sends at open to report the initial state) and the axis or button number. Axes range over
-32767..32767 and scale by 1/32767.

Why event-driven: Donkeycar reads the device with a blocking ``read()`` in a thread and polls shared dicts.
Here the device is opened non-blocking and registered with the event loop (``loop.add_reader``); the loop
calls us when bytes are waiting and we read all of them, so there is no thread, no per-tick read, and a button
press and release between two ticks are both seen (``on_event`` listeners get every event, in order).

Robustness:

* **Partial reads.** A read may end mid-event (a pipe, or a slow USB hub); leftover bytes are kept and joined
  with the next read, so an event split across reads is decoded once and correctly.
* **Unplug.** ``ENODEV`` (the kernel's answer for a vanished device) or end-of-file closes the device, resets
  the state to neutral (every axis 0, every button released), notifies listeners (``on_disconnect``) and tries
  to open the device again every ``reconnect_s`` on the runtime clock. A reopened device sends its initial
  state again.
"""

from __future__ import annotations

import asyncio
import errno
import logging
import os
import struct
from collections.abc import Callable
from dataclasses import dataclass

from ..clock import get_clock
from ..ratelimit import LogThrottle

__all__ = [
    "AXIS_MAX",
    "EVENT_SIZE",
    "JS_EVENT_AXIS",
    "JS_EVENT_BUTTON",
    "JS_EVENT_INIT",
    "JoystickEvent",
    "JoystickReader",
    "JoystickState",
    "decode_events",
    "encode_event",
]

logger = logging.getLogger(__name__)

EVENT = struct.Struct("<IhBB")
EVENT_SIZE = EVENT.size  # 8
JS_EVENT_BUTTON = 0x01
JS_EVENT_AXIS = 0x02
JS_EVENT_INIT = 0x80
AXIS_MAX = 32767


@dataclass(frozen=True, slots=True)
class JoystickEvent:
    """One decoded kernel event. ``kind`` is ``JS_EVENT_BUTTON`` or ``JS_EVENT_AXIS`` (init flag removed)."""

    time_ms: int
    value: int
    kind: int
    number: int
    init: bool = False

    @property
    def is_button(self) -> bool:
        return self.kind == JS_EVENT_BUTTON

    @property
    def is_axis(self) -> bool:
        return self.kind == JS_EVENT_AXIS


def encode_event(time_ms: int, value: int, kind: int, number: int, init: bool = False) -> bytes:
    """The 8 bytes the kernel would send for this event."""
    return EVENT.pack(time_ms & 0xFFFFFFFF, value, kind | (JS_EVENT_INIT if init else 0), number)


def decode_events(data: bytes) -> tuple[list[JoystickEvent], bytes]:
    """Decode every whole event in ``data``; return them and the trailing partial bytes (0..7)."""
    whole = len(data) - len(data) % EVENT_SIZE
    events = []
    for t, value, raw_type, number in EVENT.iter_unpack(data[:whole]):
        events.append(JoystickEvent(t, value, raw_type & ~JS_EVENT_INIT, number, bool(raw_type & JS_EVENT_INIT)))
    return events, data[whole:]


class JoystickState:
    """Current axis values (raw, -32767..32767) and button states, updated event by event."""

    __slots__ = ("axes", "buttons")

    def __init__(self) -> None:
        self.axes: dict[int, int] = {}
        self.buttons: dict[int, bool] = {}

    def apply(self, ev: JoystickEvent) -> None:
        if ev.kind == JS_EVENT_AXIS:
            self.axes[ev.number] = ev.value
        elif ev.kind == JS_EVENT_BUTTON:
            self.buttons[ev.number] = bool(ev.value)

    def axis(self, n: int) -> float:
        """Axis ``n`` scaled to [-1, 1] (0 when unknown)."""
        v = self.axes.get(n, 0) / AXIS_MAX
        return -1.0 if v < -1.0 else v

    def button(self, n: int) -> bool:
        return self.buttons.get(n, False)

    def reset(self) -> None:
        """Neutral: every known axis centred, every button released."""
        for n in self.axes:
            self.axes[n] = 0
        for n in self.buttons:
            self.buttons[n] = False


EventListener = Callable[[JoystickEvent], None]


class JoystickReader:
    """Reads a joystick device on the running event loop.

    Args:
        device: the device path, e.g. ``/dev/input/js0`` (Donkeycar's ``JOYSTICK_DEVICE_FILE``).
        reconnect_s: seconds between attempts to open a missing or unplugged device.
        on_event: called with every event (init events included), on the loop thread, after the state is
            updated.
        on_disconnect: called after an unplug, once the state is neutral.

    ``await reader.run()`` opens the device (retrying until it appears) and keeps it read until
    :meth:`close`; :meth:`open` / :meth:`close` do the same without a task.
    """

    def __init__(
        self,
        device: str | os.PathLike[str] = "/dev/input/js0",
        *,
        reconnect_s: float = 1.0,
        on_event: EventListener | None = None,
        on_disconnect: Callable[[], None] | None = None,
    ) -> None:
        if not (isinstance(reconnect_s, int | float) and reconnect_s > 0):
            raise ValueError(f"JoystickReader({device}): reconnect_s must be a positive number, got {reconnect_s!r}")
        self.device = os.fspath(device)
        self.reconnect_s = float(reconnect_s)
        self.state = JoystickState()
        self.on_event = on_event
        self.on_disconnect = on_disconnect
        self.connected = False
        self.events = 0
        self.disconnects = 0
        self.connects = 0
        self.open_failures = 0
        self.last_error: str | None = None
        self._fd: int | None = None
        self._partial = b""
        self._loop: asyncio.AbstractEventLoop | None = None
        self._retry: asyncio.TimerHandle | None = None
        self._closed = False
        self._done: asyncio.Future[None] | None = None
        self._log = LogThrottle(10.0)

    # ----------------------------------------------------------------------------------------- opening
    def open(self) -> bool:
        """Try to open the device now and register it with the running loop. False (and a retry) if absent."""
        loop = self._loop = asyncio.get_running_loop()
        self._closed = False
        self._retry = None
        if self._fd is not None:
            return True
        try:
            fd = os.open(self.device, os.O_RDONLY | os.O_NONBLOCK)
        except OSError as exc:
            self.open_failures += 1
            self.last_error = f"{exc.strerror or exc}"
            if self._log.allow("open", get_clock(loop).now()):
                logger.warning(
                    "joystick %s: cannot open (%s); retrying every %.1f s",
                    self.device,
                    self.last_error,
                    self.reconnect_s,
                )
            self._schedule_retry()
            return False
        self._fd = fd
        self._partial = b""
        loop.add_reader(fd, self._readable)
        self.connected = True
        self.connects += 1
        logger.info("joystick %s: connected", self.device)
        return True

    def _schedule_retry(self) -> None:
        if self._closed or self._loop is None or self._retry is not None:
            return
        self._retry = self._loop.call_later(self.reconnect_s, self._retry_open)

    def _retry_open(self) -> None:
        self._retry = None
        if not self._closed:
            self.open()

    # ----------------------------------------------------------------------------------------- reading
    def _readable(self) -> None:
        fd = self._fd
        if fd is None:
            return
        chunks = []
        while True:
            try:
                data = os.read(fd, 64 * EVENT_SIZE)
            except BlockingIOError:
                break
            except InterruptedError:
                continue
            except OSError as exc:
                self._feed(b"".join(chunks))
                reason = "unplugged (ENODEV)" if exc.errno == errno.ENODEV else f"read failed: {exc.strerror or exc}"
                self._lost(reason)
                return
            if not data:
                self._feed(b"".join(chunks))
                self._lost("end of file (device gone)")
                return
            chunks.append(data)
        self._feed(b"".join(chunks))

    def _feed(self, data: bytes) -> None:
        if not data:
            return
        events, self._partial = decode_events(self._partial + data)
        listener = self.on_event
        state = self.state
        for ev in events:
            state.apply(ev)
            self.events += 1
            if listener is not None:
                listener(ev)

    def _lost(self, reason: str) -> None:
        self._unregister()
        self.disconnects += 1
        self.last_error = reason
        self.state.reset()
        logger.warning(
            "joystick %s: %s; outputs neutral, reconnecting every %.1f s", self.device, reason, self.reconnect_s
        )
        if self.on_disconnect is not None:
            self.on_disconnect()
        self._schedule_retry()

    def _unregister(self) -> None:
        fd, self._fd = self._fd, None
        self.connected = False
        self._partial = b""
        if fd is None:
            return
        if self._loop is not None and not self._loop.is_closed():
            self._loop.remove_reader(fd)
        os.close(fd)

    # ------------------------------------------------------------------------------------------ control
    async def run(self) -> None:
        """Open (retrying) and read until :meth:`close` or cancellation."""
        done: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        self._done = done
        self.open()
        try:
            await done
        finally:
            self.close()

    def close(self) -> None:
        """Stop reading and retrying; close the device. Safe from any thread (the work is done on the loop)."""
        loop = self._loop
        if loop is not None and loop.is_running() and not _on_loop(loop):
            loop.call_soon_threadsafe(self._close_now)
            return
        self._close_now()

    def _close_now(self) -> None:
        self._closed = True
        if self._retry is not None:
            self._retry.cancel()
            self._retry = None
        self._unregister()
        done = self._done
        if done is not None and not done.done():
            done.set_result(None)


def _on_loop(loop: asyncio.AbstractEventLoop) -> bool:
    try:
        return asyncio.get_running_loop() is loop
    except RuntimeError:
        return False
