"""Wheel odometry from a serial encoder board: distance (m), velocity (m/s) and when it was measured.

Donkeycar splits this over ``SerialEncoder`` → ``Tachometer`` → ``Odometer``, each a thread polling the one
before it. Here one native async part does it: its ``async update()`` reads the board's continuous stream
as lines arrive (:class:`~asyncdonkey.hw.encoder_protocol.ArduinoEncoder`) and integrates each reading the
moment it lands; ``run(throttle)`` only takes the throttle (for the direction) and returns the newest
``(distance, velocity, timestamp)``, so a tick never waits for the serial port.

Semantics kept from Donkeycar:

* Direction modes (``TACHOMETER_MODE``): ``FORWARD_ONLY`` (1) adds tick changes as they come (a quadrature
  encoder's count is already signed); ``FORWARD_REVERSE`` (2) multiplies them by the sign of the last
  non-zero throttle (a single-channel encoder coasting at zero throttle keeps its last direction);
  ``FORWARD_REVERSE_STOP`` (3) by the sign of the throttle, so ticks at zero throttle are ignored.
* Calibration: ``MM_PER_TICK`` (or ``ENCODER_PPR`` with ``WHEEL_RADIUS``), ``ODOM_SMOOTHING`` readings for
  the velocity, ``ODOM_SERIAL`` / ``ODOM_SERIAL_BAUDRATE`` for the port.
* Output before the first reading: ``(0.0, 0.0, None)``.

Differences, on purpose:

* Velocity uses the board's own ``millis`` between readings, not the host's arrival times, so USB latency
  jitter does not show up as speed noise. ``timestamp`` is the runtime-clock time the reading arrived (the
  clock every other part uses), in seconds.
* After a reconnect (or a board reboot seen as ``millis`` going backwards) the counters restart at 0; the
  first reading then only sets the new baseline, so distance continues from where it was instead of jumping
  by minus the old count. Distance travelled while unplugged is not known and not invented.
"""

from __future__ import annotations

import collections
import logging
import math
from collections.abc import Callable
from typing import Any

from ..hw.encoder_protocol import ArduinoEncoder, EncoderReading, millis_delta, tick_delta
from ..latest import Latest
from ..ratelimit import LogThrottle

__all__ = ["FORWARD_ONLY", "FORWARD_REVERSE", "FORWARD_REVERSE_STOP", "Odometer"]

logger = logging.getLogger(__name__)

FORWARD_ONLY = 1
FORWARD_REVERSE = 2
FORWARD_REVERSE_STOP = 3
_MODES = {
    FORWARD_ONLY: "FORWARD_ONLY",
    FORWARD_REVERSE: "FORWARD_REVERSE",
    FORWARD_REVERSE_STOP: "FORWARD_REVERSE_STOP",
}

#: a millis value this close below 2**32 that is followed by a small one is a wrap, not a reboot
_WRAP_WINDOW_MS = 60_000

Reading = tuple[float, float, float | None]


def meters_per_tick(
    mm_per_tick: float | None = None,
    ticks_per_meter: float | None = None,
    encoder_ppr: float | None = None,
    wheel_radius: float | None = None,
) -> float:
    """Metres per encoder tick from exactly one of: ``mm_per_tick``; ``ticks_per_meter``; ``encoder_ppr``
    together with ``wheel_radius`` (metres), as Donkeycar computes ``MM_PER_TICK`` from them."""
    given = [
        name
        for name, v in (
            ("mm_per_tick", mm_per_tick),
            ("ticks_per_meter", ticks_per_meter),
            ("encoder_ppr", encoder_ppr),
        )
        if v is not None
    ]
    if len(given) != 1:
        raise ValueError(
            "Odometer: give exactly one calibration: mm_per_tick (MM_PER_TICK), ticks_per_meter, or encoder_ppr "
            f"(ENCODER_PPR) with wheel_radius (WHEEL_RADIUS); got {given or 'none'}"
        )
    if mm_per_tick is not None:
        value = float(mm_per_tick) / 1000.0
    elif ticks_per_meter is not None:
        if not ticks_per_meter > 0:
            raise ValueError(f"Odometer: ticks_per_meter must be positive, got {ticks_per_meter!r}")
        value = 1.0 / float(ticks_per_meter)
    else:
        if wheel_radius is None or not wheel_radius > 0 or not encoder_ppr > 0:  # type: ignore[operator]
            raise ValueError(
                "Odometer: encoder_ppr needs a positive wheel_radius (metres) and a positive encoder_ppr, got "
                f"encoder_ppr={encoder_ppr!r}, wheel_radius={wheel_radius!r}"
            )
        value = 2.0 * math.pi * float(wheel_radius) / float(encoder_ppr)
    if not (value > 0 and math.isfinite(value)):
        raise ValueError(f"Odometer: the calibration must give a positive distance per tick, got {value!r} m")
    return value


class Odometer:
    """A native async part: ``update()`` reads the encoder board, ``run(throttle)`` returns
    ``(distance_m, velocity_m_s, timestamp_s)``.

    Add it as::

        odom = Odometer("/dev/ttyACM0", mm_per_tick=cfg.MM_PER_TICK, direction_mode=cfg.TACHOMETER_MODE)
        vehicle.add(odom, inputs=["throttle"], outputs=["enc/distance", "enc/speed", "enc/timestamp"])

    Args:
        port: the board's serial device (``ODOM_SERIAL``) or a ready :class:`ArduinoEncoder`.
        baudrate: ``ODOM_SERIAL_BAUDRATE``.
        mm_per_tick, ticks_per_meter, encoder_ppr + wheel_radius: calibration (exactly one).
        direction_mode: ``FORWARD_ONLY``, ``FORWARD_REVERSE`` or ``FORWARD_REVERSE_STOP`` (1, 2, 3).
        encoder_index: which encoder of a two-encoder board (0 or 1).
        smoothing_count: readings the velocity is averaged over (``ODOM_SMOOTHING``).
        stream_ms: the board's continuous-mode period.
        watchdog_s: silence after which the stream is asked for again.
    """

    def __init__(
        self,
        port: str | ArduinoEncoder = "/dev/ttyACM0",
        baudrate: int = 115200,
        *,
        mm_per_tick: float | None = None,
        ticks_per_meter: float | None = None,
        encoder_ppr: float | None = None,
        wheel_radius: float | None = None,
        direction_mode: int = FORWARD_ONLY,
        encoder_index: int = 0,
        smoothing_count: int = 1,
        stream_ms: int = 16,
        watchdog_s: float = 0.5,
    ) -> None:
        self.meters_per_tick = meters_per_tick(mm_per_tick, ticks_per_meter, encoder_ppr, wheel_radius)
        if direction_mode not in _MODES:
            raise ValueError(
                f"Odometer: direction_mode must be FORWARD_ONLY (1), FORWARD_REVERSE (2) or FORWARD_REVERSE_STOP "
                f"(3), got {direction_mode!r}"
            )
        if encoder_index not in (0, 1):
            raise ValueError(f"Odometer: encoder_index must be 0 or 1, got {encoder_index!r}")
        if not (isinstance(smoothing_count, int) and smoothing_count >= 1):
            raise ValueError(f"Odometer: smoothing_count must be an int >= 1, got {smoothing_count!r}")
        self.encoder = (
            port
            if isinstance(port, ArduinoEncoder)
            else ArduinoEncoder(port, baudrate, stream_ms=stream_ms, watchdog_s=watchdog_s)
        )
        self.direction_mode = direction_mode
        self.encoder_index = encoder_index
        self.smoothing_count = smoothing_count
        self._set_direction: Callable[[float], None] = {
            FORWARD_ONLY: _ignore,
            FORWARD_REVERSE: self._direction_coasting,
            FORWARD_REVERSE_STOP: self._direction_strict,
        }[direction_mode]
        #: +1, -1 or 0: what tick changes are multiplied by
        self.direction = 1
        #: the newest (distance m, velocity m/s, timestamp s), also as a Latest cell
        self.latest: Latest[Reading] = Latest()
        self._reading: Reading = (0.0, 0.0, None)
        self._ticks = 0
        self._last: EncoderReading | None = None
        self._epoch: int | None = None
        self._device_s = 0.0
        self._history: collections.deque[tuple[float, float]] = collections.deque(maxlen=smoothing_count + 1)
        self._velocity = 0.0
        #: times the counters restarted (reconnect or board reboot) and a new baseline was taken
        self.rebases = 0
        self.device_resets = 0
        self.missing_channel = 0
        self._log = LogThrottle(5.0)

    @classmethod
    def from_config(cls, cfg: Any) -> Odometer:
        """Build from a Donkeycar config: ``ODOM_SERIAL``, ``ODOM_SERIAL_BAUDRATE``, ``MM_PER_TICK`` (else
        ``ENCODER_PPR`` and ``WHEEL_RADIUS``), ``TACHOMETER_MODE``, ``ODOM_SMOOTHING``."""
        mm = getattr(cfg, "MM_PER_TICK", None)
        calib: dict[str, float | None] = (
            {"mm_per_tick": mm}
            if mm is not None
            else {"encoder_ppr": getattr(cfg, "ENCODER_PPR", None), "wheel_radius": getattr(cfg, "WHEEL_RADIUS", None)}
        )
        return cls(
            getattr(cfg, "ODOM_SERIAL", "/dev/ttyACM0"),
            getattr(cfg, "ODOM_SERIAL_BAUDRATE", 115200),
            direction_mode=getattr(cfg, "TACHOMETER_MODE", FORWARD_ONLY),
            smoothing_count=max(1, int(getattr(cfg, "ODOM_SMOOTHING", 1))),
            **calib,  # type: ignore[arg-type]
        )

    # ------------------------------------------------------------------------------------- part contract
    async def update(self) -> None:
        await self.encoder.run(self._on_readings)

    def run(self, throttle: float | None = None) -> Reading:
        if throttle is not None and throttle == throttle:  # None or NaN leave the direction alone
            self._set_direction(throttle)
        return self._reading

    def output_origin(self) -> float | None:
        """When the encoder reading behind the outputs arrived (not the throttle input's age)."""
        return self._reading[2]

    async def shutdown(self) -> None:
        await self.encoder.close()

    @property
    def distance(self) -> float:
        return self._reading[0]

    @property
    def velocity(self) -> float:
        return self._reading[1]

    # -------------------------------------------------------------------------------------------- logic
    def _direction_coasting(self, throttle: float) -> None:
        if throttle > 0:
            self.direction = 1
        elif throttle < 0:
            self.direction = -1

    def _direction_strict(self, throttle: float) -> None:
        self.direction = 1 if throttle > 0 else (-1 if throttle < 0 else 0)

    def _on_readings(self, readings: tuple[EncoderReading, ...], timestamp: float, epoch: int) -> None:
        if self.encoder_index >= len(readings):
            self.missing_channel += 1
            if self._log.allow("channel", timestamp):
                logger.warning(
                    "odometer: encoder_index %d but the board sends %d encoder(s)", self.encoder_index, len(readings)
                )
            return
        r = readings[self.encoder_index]
        last = self._last
        self._last = r
        if last is None or epoch != self._epoch:
            if last is not None:
                self.rebases += 1
            self._epoch = epoch
            self._rebase(timestamp, publish=last is None)
            return
        if r.millis < last.millis and last.millis < (1 << 32) - _WRAP_WINDOW_MS:
            self.device_resets += 1
            self.rebases += 1
            self._rebase(timestamp, publish=False)
            return
        self._ticks += tick_delta(last.ticks, r.ticks) * self.direction
        self._device_s += millis_delta(last.millis, r.millis) / 1000.0
        distance = self._ticks * self.meters_per_tick
        history = self._history
        history.append((distance, self._device_s))
        d0, t0 = history[0]
        if self._device_s > t0:
            self._velocity = (distance - d0) / (self._device_s - t0)
        self._publish((distance, self._velocity, timestamp))

    def _rebase(self, timestamp: float, publish: bool) -> None:
        self._history.clear()
        self._history.append((self._ticks * self.meters_per_tick, self._device_s))
        if publish:
            self._publish((self._ticks * self.meters_per_tick, 0.0, timestamp))

    def _publish(self, reading: Reading) -> None:
        self._reading = reading
        self.latest.publish(reading, reading[2])  # type: ignore[arg-type]


def _ignore(_throttle: float) -> None:
    pass
