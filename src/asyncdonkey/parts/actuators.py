"""PWM steering and throttle parts: Donkeycar's calibration and mapping, without blocking the tick.

What is the same as Donkeycar's ``PWMSteering`` / ``PWMThrottle``:

* Constructor names and calibration defaults (``left_pulse=460, right_pulse=290``; ``max_pulse=500,
  zero_pulse=370, min_pulse=220``), Donkeycar's pin specs (``"PCA9685.1:40.1"``) and ``pwm_scale`` /
  ``pwm_inverted`` (``PWM_STEERING_SCALE``, ``PWM_STEERING_INVERTED``, ...).
* The mapping, bit for bit: inputs clamped to [-1, 1], then Donkeycar's ``map_range`` (a linear map floored
  to an int): steering -1/-0.5/0/0.5/1 → 460/417/375/332/290, throttle → 220/295/370/435/500 (stopped →
  forward for t > 0, reverse → stopped for t <= 0).

What is different, and why:

* **The tick never waits for I2C.** ``run()`` only computes the pulse and stores it. An ``async update()``
  writer task (started by the Vehicle before the first tick) pushes the newest pulse to the chip on the I2C
  bus's worker thread, and only when it changed: the PCA9685 holds its outputs by itself, so rewriting an
  unchanged pulse would only load the bus. A failed write is retried every ``retry_s`` until it lands or a
  newer pulse replaces it; errors are counted (``write_errors``) and logged at most once a second, never
  raised into the tick. (Donkeycar writes inline, 2-3 ms per write, or spins a thread rewriting in a loop.)
* **``None`` or NaN → neutral** (Donkeycar crashes on ``None``).
* **Shutdown → steering centre, throttle stopped.** Donkeycar's steering shutdown writes pulse 0, which cuts
  the servo signal instead of centring it.
* **ESC arming without blocking:** the writer holds the stopped pulse for ``arm_s`` (1 s) before following
  commands; the loop keeps ticking. Donkeycar blocks its constructor for a second and first sends a 10 ms
  full-forward then full-reverse pulse, which we do not (on an armed ESC that is a lurch).
* **Throttle failsafe.** Give ``PWMThrottle`` the age of its command (``inputs=["throttle",
  "throttle@age"]``, the Vehicle supplies ``@age``): a command ``failsafe_age_s`` old (default 0.25 s) or
  older is replaced by the stopped pulse. The writer task checks too, on its own timer, so the car stops even
  when the tick itself stalls. Each entry into the failsafe is counted (``failsafe_events``) and logged
  (rate-limited).
* **One chip driver per (bus, address)**: opening the throttle pin does not re-initialise the chip the
  steering pin already set up (Donkeycar's does, zeroing the steering channel).

``controller`` may be a pin spec, a :class:`~asyncdonkey.hw.pca9685.PWMChannel` (or anything with an
``async set_pulse(ticks)``), or a Donkeycar controller with a blocking ``set_pulse(pulse)`` such as
``PulseController``, which is then called on its own worker thread.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import inspect
import logging
import math
import numbers
from collections.abc import Awaitable, Callable
from typing import Any

from ..clock import Clock, get_clock
from ..hw.i2c import I2CBusRegistry
from ..hw.pca9685 import open_pwm_channel
from ..hw.pinspec import PCA9685Pin
from ..ratelimit import LogThrottle

__all__ = ["PWMSteering", "PWMThrottle", "donkeycar_map_range", "pulse_to_ticks"]

logger = logging.getLogger(__name__)


def donkeycar_map_range(x: float, x_min: float, x_max: float, y_min: float, y_max: float) -> int:
    """Donkeycar's linear map from [x_min, x_max] to [y_min, y_max], floored to an int (same arithmetic)."""
    ratio = (x_max - x_min) / (y_max - y_min)
    return math.floor((x - x_min) / ratio + y_min)


def pulse_to_ticks(pulse: int, scale: float = 1.0, inverted: bool = False) -> int:
    """A Donkeycar pulse (0..4095) to PCA9685 ticks as ``PulseController`` + Donkeycar's PCA9685 pin do it.

    Inverted pulses are ``4095 - pulse``; the scale compensates a non-60 Hz frequency; a duty cycle of 0 is
    full-off (0) and of 1 full-on (4096). Out-of-range values are clamped (Donkeycar raises on some).
    """
    p = min(max(int(pulse), 0), 4095)
    if inverted:
        p = 4095 - p
    d = min(max(int(p * scale), 0), 4095)
    if d == 0:
        return 0
    if d == 4095:
        return 4096
    return int(4096 * (d / 4095))


class _BlockingController:
    """A Donkeycar controller with a blocking ``set_pulse``, called on its own single worker thread."""

    def __init__(self, controller: Any) -> None:
        self.controller = controller
        self.name = type(controller).__name__
        self._executor: concurrent.futures.ThreadPoolExecutor | None = None

    async def set_pulse(self, pulse: int) -> None:
        if self._executor is None:
            self._executor = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix=f"pwm:{self.name}")
        loop = asyncio.get_running_loop()
        await loop.run_in_executor(self._executor, self.controller.set_pulse, pulse)

    def close(self) -> None:
        if self._executor is not None:
            self._executor.shutdown(wait=False)
            self._executor = None


def _is_number(x: Any) -> bool:
    return isinstance(x, numbers.Real) and not isinstance(x, bool) and math.isfinite(x)


class _PWMPart:
    """The writer machinery shared by steering and throttle: target pulse, writer task, errors, shutdown."""

    def __init__(
        self,
        controller: Any,
        neutral_pulse: int,
        *,
        frequency_hz: float,
        pwm_scale: float,
        pwm_inverted: bool,
        buses: I2CBusRegistry | None,
        retry_s: float,
    ) -> None:
        kind = type(self).__name__
        if not (_is_number(pwm_scale) and pwm_scale > 0):
            raise ValueError(f"{kind}: pwm_scale must be a positive number, got {pwm_scale!r}")
        if not (_is_number(retry_s) and retry_s > 0):
            raise ValueError(f"{kind}: retry_s must be a positive number, got {retry_s!r}")
        self._closer: Callable[[], None] | None = None
        setter: Callable[[int], Awaitable[None]]
        if isinstance(controller, str | PCA9685Pin):
            channel = open_pwm_channel(controller, frequency_hz, buses=buses)
            setter, where = channel.set_pulse, channel.name
            convert = True
        elif inspect.iscoroutinefunction(getattr(controller, "set_pulse", None)):
            setter, where = controller.set_pulse, getattr(controller, "name", repr(controller))
            convert = True
        elif callable(getattr(controller, "set_pulse", None)):
            if pwm_scale != 1.0 or pwm_inverted:
                raise ValueError(
                    f"{kind}: pwm_scale/pwm_inverted apply to pin specs and PWMChannels; give them to the Donkeycar "
                    f"controller {type(controller).__name__} instead"
                )
            blocking = _BlockingController(controller)
            setter, where, self._closer = blocking.set_pulse, blocking.name, blocking.close
            convert = False
        else:
            raise TypeError(
                f"{kind}: controller must be a PCA9685 pin spec like 'PCA9685.1:40.1', a PWMChannel, or an object "
                f"with set_pulse(pulse); got {controller!r}"
            )
        if convert:
            scale, inverted = float(pwm_scale), bool(pwm_inverted)

            def write(pulse: int) -> Awaitable[None]:
                return setter(pulse_to_ticks(pulse, scale, inverted))

            self._write_pulse: Callable[[int], Awaitable[None]] = write
        else:
            self._write_pulse = setter
        self.name = f"{kind} ({where})"
        self.neutral_pulse = int(neutral_pulse)
        self.retry_s = float(retry_s)
        self.pulse = self.neutral_pulse  # the newest target, in Donkeycar pulse units
        self.written_pulse: int | None = None  # what the chip was last told
        self.writes = 0
        self.write_errors = 0
        self.last_error: BaseException | None = None
        self._wake: asyncio.Future[None] | None = None
        self._writer_deadline = math.inf
        self._running = False
        self._now: Callable[[], float] | None = None
        self._log = LogThrottle(1.0)

    # ---------------------------------------------------------------------------------- hot path
    def _set_target(self, pulse: int) -> None:
        if pulse != self.pulse:
            self.pulse = pulse
            w = self._wake
            if w is not None and not w.done():
                w.set_result(None)

    def _desired(self, now: float) -> tuple[int, float]:
        """The pulse to output now and when to look again (``inf``: only when woken)."""
        return self.pulse, math.inf

    # ------------------------------------------------------------------------------ writer task
    async def _write(self, pulse: int, clock: Clock) -> bool:
        try:
            await self._write_pulse(pulse)
        except OSError as exc:
            self.write_errors += 1
            self.last_error = exc
            self.written_pulse = None
            now = clock.now()
            if self._log.allow("write", now):
                held = self._log.take_suppressed("write")
                logger.error(
                    "%s: writing pulse %d failed (%d errors so far%s); retrying every %.0f ms: %s",
                    self.name,
                    pulse,
                    self.write_errors,
                    f", {held} not logged" if held else "",
                    self.retry_s * 1e3,
                    exc,
                )
            return False
        self.written_pulse = pulse
        self.writes += 1
        return True

    async def _before_driving(self, clock: Clock) -> None:
        """Hook run once when the writer starts (the throttle arms the ESC here)."""

    async def update(self) -> None:
        """The writer task: push the newest target pulse to the output whenever it changes."""
        loop = asyncio.get_running_loop()
        clock = get_clock(loop)
        self._now = clock.now
        self._running = True
        try:
            await self._before_driving(clock)
            while self._running:
                wake = self._wake = loop.create_future()
                pulse, recheck_at = self._desired(clock.now())
                if pulse != self.written_pulse:
                    if await self._write(pulse, clock):
                        continue
                    recheck_at = min(recheck_at, clock.now() + self.retry_s)
                if wake.done():
                    continue
                self._writer_deadline = recheck_at
                if recheck_at == math.inf:
                    await wake
                else:
                    await clock.sleep_until(recheck_at, wake)
        finally:
            self._running = False
            self._wake = None
            self._writer_deadline = math.inf

    async def shutdown(self) -> None:
        """Stop the writer and leave the output at the neutral pulse (steering centre, throttle stopped)."""
        self._running = False
        self.pulse = self.neutral_pulse
        w = self._wake
        if w is not None and not w.done():
            w.set_result(None)
        try:
            await self._write_pulse(self.neutral_pulse)
            self.written_pulse = self.neutral_pulse
            self.writes += 1
        except OSError as exc:
            self.write_errors += 1
            logger.error("%s: could not set the neutral pulse %d at shutdown: %s", self.name, self.neutral_pulse, exc)
        finally:
            if self._closer is not None:
                self._closer()


class PWMSteering(_PWMPart):
    """Steering servo on a PWM output: ``run(angle)`` with angle -1 (left) .. 1 (right).

    Args:
        controller: ``"PCA9685.<bus>:<hex address>.<channel>"`` (Donkeycar's ``PWM_STEERING_PIN``), a
            :class:`~asyncdonkey.hw.pca9685.PWMChannel`, or a Donkeycar controller with ``set_pulse``.
        left_pulse, right_pulse: calibration (``STEERING_LEFT_PWM``, ``STEERING_RIGHT_PWM``).
        pwm_scale, pwm_inverted: ``PWM_STEERING_SCALE``, ``PWM_STEERING_INVERTED``.
        frequency_hz: PCA9685 frequency when opening a pin spec (Donkeycar uses 60).
        buses: the :class:`~asyncdonkey.hw.i2c.I2CBusRegistry` pin specs open on (default: real buses).
        retry_s: how often a failed write is retried.
    """

    LEFT_ANGLE = -1
    RIGHT_ANGLE = 1

    def __init__(
        self,
        controller: Any,
        left_pulse: int = 460,
        right_pulse: int = 290,
        *,
        pwm_scale: float = 1.0,
        pwm_inverted: bool = False,
        frequency_hz: float = 60,
        buses: I2CBusRegistry | None = None,
        retry_s: float = 0.05,
    ) -> None:
        for n, v in (("left_pulse", left_pulse), ("right_pulse", right_pulse)):
            if not _is_number(v):
                raise ValueError(f"PWMSteering: {n} (STEERING_{n[:-6].upper()}_PWM) must be a number, got {v!r}")
        if left_pulse == right_pulse:
            raise ValueError(f"PWMSteering: left_pulse and right_pulse are both {left_pulse}; calibrate them apart")
        self.left_pulse = left_pulse
        self.right_pulse = right_pulse
        centre = donkeycar_map_range(0, self.LEFT_ANGLE, self.RIGHT_ANGLE, left_pulse, right_pulse)
        super().__init__(
            controller,
            centre,
            frequency_hz=frequency_hz,
            pwm_scale=pwm_scale,
            pwm_inverted=pwm_inverted,
            buses=buses,
            retry_s=retry_s,
        )

    @classmethod
    def from_config(cls, cfg: Any, *, buses: I2CBusRegistry | None = None, **kwargs: Any) -> PWMSteering:
        """Build from a Donkeycar config's ``PWM_STEERING_THROTTLE`` dict."""
        dt = cfg.PWM_STEERING_THROTTLE
        return cls(
            dt["PWM_STEERING_PIN"],
            left_pulse=dt["STEERING_LEFT_PWM"],
            right_pulse=dt["STEERING_RIGHT_PWM"],
            pwm_scale=dt.get("PWM_STEERING_SCALE", 1.0),
            pwm_inverted=dt.get("PWM_STEERING_INVERTED", False),
            buses=buses,
            **kwargs,
        )

    def run(self, angle: float | None) -> None:
        """Set the steering target (returns at once; the writer task does the I2C)."""
        if angle is None:
            self._set_target(self.neutral_pulse)
            return
        try:
            a = float(angle)
        except (TypeError, ValueError):
            raise TypeError(f"{self.name}: angle must be a number or None, got {angle!r}") from None
        if a != a:  # NaN
            self._set_target(self.neutral_pulse)
            return
        a = -1.0 if a < -1.0 else 1.0 if a > 1.0 else a
        self._set_target(donkeycar_map_range(a, -1, 1, self.left_pulse, self.right_pulse))

    run_threaded = run


class PWMThrottle(_PWMPart):
    """ESC on a PWM output: ``run(throttle, throttle_age=None)`` with throttle -1 (reverse) .. 1 (forward).

    Args:
        controller: ``"PCA9685.<bus>:<hex address>.<channel>"`` (``PWM_THROTTLE_PIN``), a
            :class:`~asyncdonkey.hw.pca9685.PWMChannel`, or a Donkeycar controller with ``set_pulse``.
        max_pulse, zero_pulse, min_pulse: calibration (``THROTTLE_FORWARD_PWM``, ``THROTTLE_STOPPED_PWM``,
            ``THROTTLE_REVERSE_PWM``).
        failsafe_age_s: a command this old or older is replaced by the stopped pulse (needs the
            ``"<channel>@age"`` input). ``None`` disables the failsafe.
        arm_s: how long the stopped pulse is held when the writer starts, to arm the ESC.
        pwm_scale, pwm_inverted, frequency_hz, buses, retry_s: as for :class:`PWMSteering`.
    """

    MIN_THROTTLE = -1
    MAX_THROTTLE = 1

    def __init__(
        self,
        controller: Any,
        max_pulse: int = 500,
        min_pulse: int = 220,
        zero_pulse: int = 370,
        *,
        failsafe_age_s: float | None = 0.25,
        arm_s: float = 1.0,
        pwm_scale: float = 1.0,
        pwm_inverted: bool = False,
        frequency_hz: float = 60,
        buses: I2CBusRegistry | None = None,
        retry_s: float = 0.05,
    ) -> None:
        for n, v in (("max_pulse", max_pulse), ("min_pulse", min_pulse), ("zero_pulse", zero_pulse)):
            if not _is_number(v):
                raise ValueError(f"PWMThrottle: {n} must be a number, got {v!r}")
        if max_pulse == zero_pulse or min_pulse == zero_pulse:
            raise ValueError(
                f"PWMThrottle: zero_pulse ({zero_pulse}) must differ from max_pulse ({max_pulse}) and min_pulse "
                f"({min_pulse}); calibrate THROTTLE_FORWARD_PWM / THROTTLE_STOPPED_PWM / THROTTLE_REVERSE_PWM"
            )
        if failsafe_age_s is not None and not (_is_number(failsafe_age_s) and failsafe_age_s > 0):
            raise ValueError(f"PWMThrottle: failsafe_age_s must be a positive number or None, got {failsafe_age_s!r}")
        if not (_is_number(arm_s) and arm_s >= 0):
            raise ValueError(f"PWMThrottle: arm_s must be a number >= 0, got {arm_s!r}")
        self.max_pulse = max_pulse
        self.min_pulse = min_pulse
        self.zero_pulse = zero_pulse
        self.failsafe_age_s = failsafe_age_s
        self.arm_s = float(arm_s)
        super().__init__(
            controller,
            int(zero_pulse),
            frequency_hz=frequency_hz,
            pwm_scale=pwm_scale,
            pwm_inverted=pwm_inverted,
            buses=buses,
            retry_s=retry_s,
        )
        self.command_pulse = self.neutral_pulse  # the mapped command, before arming and failsafe
        self.armed = False
        self.failsafe_active = False
        self.failsafe_events = 0
        self._stale_at = math.inf

    @classmethod
    def from_config(cls, cfg: Any, *, buses: I2CBusRegistry | None = None, **kwargs: Any) -> PWMThrottle:
        """Build from a Donkeycar config's ``PWM_STEERING_THROTTLE`` dict."""
        dt = cfg.PWM_STEERING_THROTTLE
        return cls(
            dt["PWM_THROTTLE_PIN"],
            max_pulse=dt["THROTTLE_FORWARD_PWM"],
            zero_pulse=dt["THROTTLE_STOPPED_PWM"],
            min_pulse=dt["THROTTLE_REVERSE_PWM"],
            pwm_scale=dt.get("PWM_THROTTLE_SCALE", 1.0),
            pwm_inverted=dt.get("PWM_THROTTLE_INVERTED", False),
            buses=buses,
            **kwargs,
        )

    def map_throttle(self, throttle: float | None) -> int:
        """Donkeycar's throttle mapping (clamped; ``None``/NaN → stopped)."""
        if throttle is None:
            return self.neutral_pulse
        try:
            t = float(throttle)
        except (TypeError, ValueError):
            raise TypeError(f"{self.name}: throttle must be a number or None, got {throttle!r}") from None
        if t != t:
            return self.neutral_pulse
        t = -1.0 if t < -1.0 else 1.0 if t > 1.0 else t
        if t > 0:
            return donkeycar_map_range(t, 0, 1, self.zero_pulse, self.max_pulse)
        return donkeycar_map_range(t, -1, 0, self.min_pulse, self.zero_pulse)

    def run(self, throttle: float | None, throttle_age: float | None = None) -> None:
        """Set the throttle target; ``throttle_age`` (from a ``"...@age"`` input) enables the failsafe."""
        self.command_pulse = self.map_throttle(throttle)
        fs = self.failsafe_age_s
        if throttle_age is None or fs is None:
            stale_at = math.inf
            stale = False
        else:
            now_fn = self._now
            if now_fn is None:
                now_fn = self._now = get_clock().now
            now = now_fn()
            age = float(throttle_age)
            stale_at = now - age + fs if age == age else -math.inf
            stale = now >= stale_at
            self._failsafe(stale, now, age)
        self._stale_at = stale_at
        self._set_target(self.neutral_pulse if stale or not self.armed else self.command_pulse)
        if stale_at < self._writer_deadline:
            w = self._wake
            if w is not None and not w.done():
                w.set_result(None)

    run_threaded = run

    def _failsafe(self, stale: bool, now: float, age: float) -> None:
        if stale == self.failsafe_active:
            return
        self.failsafe_active = stale
        if stale:
            self.failsafe_events += 1
            if self._log.allow("failsafe", now):
                held = self._log.take_suppressed("failsafe")
                logger.warning(
                    "%s: throttle command is %.0f ms old (failsafe at %.0f ms): holding stopped pulse %d "
                    "(failsafe event %d%s)",
                    self.name,
                    age * 1e3,
                    (self.failsafe_age_s or 0) * 1e3,
                    self.neutral_pulse,
                    self.failsafe_events,
                    f", {held} not logged" if held else "",
                )

    def _desired(self, now: float) -> tuple[int, float]:
        if not self.armed:
            return self.neutral_pulse, math.inf
        stale_at = self._stale_at
        if now >= stale_at:
            # the command went stale between ticks (or the tick stalled): stop without waiting for run()
            self._failsafe(True, now, now - stale_at + (self.failsafe_age_s or 0))
            self.pulse = self.neutral_pulse  # so the next fresh command counts as a change and wakes us
            return self.neutral_pulse, math.inf
        return self.pulse, stale_at

    async def _before_driving(self, clock: Clock) -> None:
        neutral = self.neutral_pulse
        while self._running and not await self._write(neutral, clock):
            await clock.sleep(self.retry_s)
        if self.arm_s:
            await clock.sleep(self.arm_s)
        self.armed = True
        self.pulse = self.command_pulse  # _desired() applies the failsafe to it
        logger.info("%s: ESC armed (stopped pulse %d held %.1f s)", self.name, neutral, self.arm_s)
