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
* **One safe pulse per drive.** Every write that puts the car safe (a zero command, the failsafe, the
  watchdog, the safety process, arming, shutdown) uses ``safe_pulse``: the stopped pulse (steering: the centre)
  fixed when the drive starts, the one the ESC was armed with. During a drive ``calibrate()`` refuses to move
  the throttle's stopped pulse (:class:`CalibrationLocked`); the end points may change (a steering calibration
  moves the centre a zero *command* maps to, never the safe pulse). Between drives the safe pulse follows the
  calibration. A zero throttle command is exactly the safe pulse: Donkeycar's floored float map lands one below
  the stopped pulse for some calibrations (reverse 277, stopped 370 maps 0 to 369).
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
import threading
from collections.abc import Awaitable, Callable
from typing import Any

from ..clock import Clock, DeadlineWaiter, get_clock
from ..errors import AsyncdonkeyError
from ..hw.i2c import I2CBusRegistry
from ..hw.pca9685 import PWMChannel, open_pwm_channel
from ..hw.pinspec import PCA9685Pin
from ..ratelimit import LogThrottle
from ..safety.unsafe import UnsafeTime

__all__ = ["CalibrationLocked", "PWMSteering", "PWMThrottle", "donkeycar_map_range", "pulse_to_ticks"]

logger = logging.getLogger(__name__)


class CalibrationLocked(AsyncdonkeyError, ValueError):
    """A calibration refused because it would change what "stopped" is during a drive (the message says which
    pulse, the drive's and the one asked)."""


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

    async def call(self, fn: Callable[..., Any], *args: Any) -> Any:
        if self._executor is None:
            self._executor = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix=f"pwm:{self.name}")
        loop = asyncio.get_running_loop()
        return await loop.run_in_executor(self._executor, fn, *args)

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
        #: a blocking write in Donkeycar pulse units, callable from any thread (the watchdog's path)
        self._raw_write: Callable[[int], None] | None = None
        #: runs a sync function off the loop thread where the output's transfers run
        self._run_off_loop: Callable[..., Awaitable[Any]] | None = None
        self._async_write: Callable[[int], Awaitable[None]] | None = None
        #: the PCA9685 output, when there is one: the safety process reaches it through a route of its own
        self._channel: PWMChannel | None = None
        scale, inverted = float(pwm_scale), bool(pwm_inverted)
        self._scale, self._inverted = scale, inverted
        if isinstance(controller, str | PCA9685Pin):
            controller = open_pwm_channel(controller, frequency_hz, buses=buses)
        if isinstance(controller, PWMChannel):
            channel = self._channel = controller
            where = channel.name

            def raw(pulse: int) -> None:
                channel.set_pulse_sync(pulse_to_ticks(pulse, scale, inverted))

            self._raw_write, self._run_off_loop = raw, channel.chip.bus.call
        elif inspect.iscoroutinefunction(getattr(controller, "set_pulse", None)):
            setter = controller.set_pulse
            where = getattr(controller, "name", repr(controller))

            def write(pulse: int) -> Awaitable[None]:
                return setter(pulse_to_ticks(pulse, scale, inverted))

            self._async_write = write
            sync = getattr(controller, "set_pulse_sync", None)
            if callable(sync):

                def raw_sync(pulse: int) -> None:
                    sync(pulse_to_ticks(pulse, scale, inverted))

                self._raw_write = raw_sync
        elif callable(getattr(controller, "set_pulse", None)):
            if pwm_scale != 1.0 or pwm_inverted:
                raise ValueError(
                    f"{kind}: pwm_scale/pwm_inverted apply to pin specs and PWMChannels; give them to the Donkeycar "
                    f"controller {type(controller).__name__} instead"
                )
            blocking = _BlockingController(controller)
            where, self._closer = blocking.name, blocking.close
            self._raw_write, self._run_off_loop = controller.set_pulse, blocking.call
        else:
            raise TypeError(
                f"{kind}: controller must be a PCA9685 pin spec like 'PCA9685.1:40.1', a PWMChannel, or an object "
                f"with set_pulse(pulse); got {controller!r}"
            )
        # Writes from the writer (on the output's worker thread) and from the watchdog are serialised by
        # _wlock, and once the watchdog has tripped no command but the neutral one is written until a fresh
        # command un-trips it: a driving pulse queued before a stall can never land after the safe state.
        self._wlock = threading.Lock()
        self._tripped = False
        self._runtime: Any = None
        self._pending_origin: float | None = None
        self.name = f"{kind} ({where})"
        self.neutral_pulse = int(neutral_pulse)
        #: the pulse every safe-state write uses (the failsafe, the watchdog, the safety process's route, arming,
        #: shutdown; the throttle's zero command too): the neutral pulse as the drive started. Fixed from the
        #: drive's start (:meth:`safety_route`, :meth:`attach`, or a writer started on its own) to its end: a
        #: value typed into a web page must not redefine the stop every safe path falls back to.
        self.safe_pulse = self.neutral_pulse
        self._safe_fixed = False
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
        #: how long the output was unsafe this drive (a command deadline passed, the safe state not yet landed)
        self.unsafe = UnsafeTime()

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

    # ------------------------------------------------------------------------------ output writes
    def _guarded_write(self, pulse: int) -> None:
        """The blocking write, serialised with the watchdog; skips a driving pulse while tripped."""
        raw = self._raw_write
        assert raw is not None
        with self._wlock:
            if self._tripped and pulse != self.safe_pulse:
                return
            raw(pulse)
            if pulse == self.safe_pulse and self.unsafe.open_since is not None and self._now is not None:
                self.unsafe.closed(self._now())

    async def _write_pulse(self, pulse: int) -> None:
        if self._raw_write is not None and self._run_off_loop is not None:
            await self._run_off_loop(self._guarded_write, pulse)
        elif self._async_write is not None:
            await self._async_write(pulse)
        else:  # pragma: no cover - the constructor guarantees one path
            raise RuntimeError(f"{self.name}: no way to write a pulse")

    # ------------------------------------------------------------------------ the Actuator protocol
    def safe_state_sync(self) -> None:
        """Write the neutral pulse now, from any thread (the watchdog, a forced exit); latch until a fresh
        command. Raises ``RuntimeError`` for an output with only an async path (nothing to call from a thread)."""
        raw = self._raw_write
        if raw is None:
            raise RuntimeError(f"{self.name}: the output has no synchronous write, so only the loop can stop it")
        with self._wlock:
            self._tripped = True
            self.unsafe.stale(self.command_deadline(), self.written_pulse == self.safe_pulse)
            raw(self.safe_pulse)
            if self._now is not None:
                self.unsafe.closed(self._now())
        self.written_pulse = self.safe_pulse
        self.pulse = self.safe_pulse

    def safety_route(self) -> dict[str, Any] | None:
        """How the safety process puts this output in its safe state by itself (``None``: it cannot).

        Only a PCA9685 channel has one: a Donkeycar controller object or an async-only output lives in this
        process alone. The drive asks for it first thing, so this fixes the drive's safe pulse: the safety process
        and every path in this process write the same one."""
        self._fix_safe_pulse()
        ch = self._channel
        if ch is None:
            return None
        return ch.safety_route(pulse_to_ticks(self.safe_pulse, self._scale, self._inverted))

    @property
    def safe_pulse_fixed(self) -> bool:
        """True from a drive's start to its end: :attr:`safe_pulse` cannot change meanwhile."""
        return self._safe_fixed

    def _fix_safe_pulse(self) -> None:
        """The drive starts: the safe pulse is the neutral pulse in force now, until :meth:`_release_safe_pulse`."""
        if not self._safe_fixed:
            self.safe_pulse = self.neutral_pulse
            self._safe_fixed = True

    def _release_safe_pulse(self) -> None:
        """The drive ended: the calibration in force is the next drive's safe pulse."""
        self._safe_fixed = False
        self.safe_pulse = self.neutral_pulse

    def _calibrated(self) -> None:
        """A calibration changed :attr:`neutral_pulse`: between drives it is the safe pulse from now on; during
        one the safe pulse stays the drive's (see :attr:`safe_pulse`)."""
        if not self._safe_fixed:
            self.safe_pulse = self.neutral_pulse

    def output_overridden(self) -> None:
        """Someone else (the safety process) wrote the output: write our own target again (on the loop thread)."""
        self.written_pulse = None
        w = self._wake
        if w is not None and not w.done():
            w.set_result(None)

    def command_deadline(self) -> float:
        """When the current command goes stale on the runtime clock (``inf``: no failsafe)."""
        return math.inf

    def attach(self, runtime: Any) -> None:
        """Called by the drive at its start (its latency recorder and watchdog) and with ``None`` at its end."""
        if runtime is None:
            if self._runtime is not None:
                with self._wlock:  # the drive ends: an event still open ends with it
                    if self._now is not None:
                        self.unsafe.closed(self._now())
            self._release_safe_pulse()
        else:
            self._fix_safe_pulse()  # the drive's safe pulse (already, if the safety process asked for its route)
            self.unsafe = UnsafeTime()
            self.unsafe.guard_last = getattr(runtime, "guard_last", None)
        self._runtime = runtime
        self._pending_origin = None

    def _command_applied(self, origin: float | None, now: float) -> None:
        """A command sensed at ``origin`` became the target: record its latency now if the output already
        shows it, else when the writer has written it."""
        rt = self._runtime
        if rt is None or origin is None:
            return
        if self.pulse == self.written_pulse:
            rt.record_latency(now, origin)
            self._pending_origin = None
        else:
            self._pending_origin = origin

    # ------------------------------------------------------------------------------ writer task
    async def _write(self, pulse: int, clock: Clock) -> bool:
        try:
            await self._write_pulse(pulse)
        except OSError as exc:
            self.write_errors += 1
            self.last_error = exc
            self.written_pulse = None
            now = clock.now()
            more = self._log.ready("write", now)
            if more is not None:
                logger.error(
                    "%s: writing pulse %d failed (%d errors so far); retrying every %.0f ms: %s%s",
                    self.name,
                    pulse,
                    self.write_errors,
                    self.retry_s * 1e3,
                    exc,
                    more,
                )
            return False
        self.written_pulse = pulse
        self.writes += 1
        origin = self._pending_origin
        if origin is not None and pulse == self.pulse and self._runtime is not None:
            self._pending_origin = None
            self._runtime.record_latency(clock.now(), origin)
        return True

    async def _before_driving(self, clock: Clock, waiter: DeadlineWaiter) -> None:
        """Hook run once when the writer starts (the throttle arms the ESC here), waiting with the writer's
        ``waiter``."""

    async def update(self) -> None:
        """The writer task: push the newest target pulse to the output whenever it changes."""
        loop = asyncio.get_running_loop()
        clock = get_clock(loop)
        self._now = clock.now
        self._running = True
        self._fix_safe_pulse()  # a writer started without a drive (a script, a test) arms the ESC with it too
        waiter = DeadlineWaiter(loop)  # one OS timer for every wait of this writer
        try:
            await self._before_driving(clock, waiter)
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
                    await waiter.wait_until(recheck_at, wake)
        finally:
            waiter.close()
            self._running = False
            self._wake = None
            self._writer_deadline = math.inf
            if self._runtime is None:  # no drive to end it: the writer's run was the drive
                self._release_safe_pulse()

    async def shutdown(self) -> None:
        """Stop the writer and leave the output at the safe pulse (steering centre, throttle stopped)."""
        self._running = False
        safe = self.pulse = self.safe_pulse
        w = self._wake
        if w is not None and not w.done():
            w.set_result(None)
        try:
            await self._write_pulse(safe)
            self.written_pulse = safe
            self.writes += 1
        except OSError as exc:
            self.write_errors += 1
            logger.error("%s: could not set the neutral pulse %d at shutdown: %s", self.name, safe, exc)
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
        self._check_calibration(left_pulse, right_pulse)
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

    @staticmethod
    def _check_calibration(left_pulse: Any, right_pulse: Any) -> None:
        for n, v in (("left_pulse", left_pulse), ("right_pulse", right_pulse)):
            if not _is_number(v):
                raise ValueError(f"PWMSteering: {n} (STEERING_{n[:-6].upper()}_PWM) must be a number, got {v!r}")
        if left_pulse == right_pulse:
            raise ValueError(f"PWMSteering: left_pulse and right_pulse are both {left_pulse}; calibrate them apart")

    def calibrate(
        self, left_pulse: int | None = None, right_pulse: int | None = None, *, check_only: bool = False
    ) -> dict[str, int]:
        """Change the calibration live (``STEERING_LEFT_PWM``, ``STEERING_RIGHT_PWM``); ``None`` keeps a value.

        Checked as the constructor checks it (``ValueError`` naming the setting); with ``check_only`` nothing
        changes. The centre pulse follows. Returns the calibration in force (or that would be)."""
        left = self.left_pulse if left_pulse is None else left_pulse
        right = self.right_pulse if right_pulse is None else right_pulse
        self._check_calibration(left, right)
        if not check_only:
            self.left_pulse, self.right_pulse = left, right
            self.neutral_pulse = donkeycar_map_range(0, self.LEFT_ANGLE, self.RIGHT_ANGLE, left, right)
            self._calibrated()
        return {"left_pulse": int(left), "right_pulse": int(right)}

    def run(self, angle: float | None, angle_age: float | None = None) -> None:
        """Set the steering target (returns at once; the writer task does the I2C). ``angle_age`` (from an
        ``"angle@age"`` input) lets the drive report the steering's sensing-to-actuation latency."""
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
        if angle_age is not None and self._runtime is not None and angle_age < math.inf:
            now_fn = self._now
            if now_fn is None:
                now_fn = self._now = get_clock().now
            now = now_fn()
            self._command_applied(now - float(angle_age), now)

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
    #: the output that moves the car: its safety process serves it first, and the car stops it in-process when
    #: it loses its guard (``asyncdonkey.safety.GuardedOutput.stops_motion``)
    stops_motion = True

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
        self._check_calibration(max_pulse, zero_pulse, min_pulse)
        if failsafe_age_s is not None and not (_is_number(failsafe_age_s) and failsafe_age_s > 0):
            raise ValueError(f"PWMThrottle: failsafe_age_s must be a positive number or None, got {failsafe_age_s!r}")
        if not (_is_number(arm_s) and arm_s >= 0):
            raise ValueError(f"PWMThrottle: arm_s must be a number >= 0, got {arm_s!r}")
        self.max_pulse = max_pulse
        self.min_pulse = min_pulse
        self._zero_pulse = zero_pulse
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

    @staticmethod
    def _check_calibration(max_pulse: Any, zero_pulse: Any, min_pulse: Any) -> None:
        for n, v in (("max_pulse", max_pulse), ("min_pulse", min_pulse), ("zero_pulse", zero_pulse)):
            if not _is_number(v):
                raise ValueError(f"PWMThrottle: {n} must be a number, got {v!r}")
        if max_pulse == zero_pulse or min_pulse == zero_pulse:
            raise ValueError(
                f"PWMThrottle: zero_pulse ({zero_pulse}) must differ from max_pulse ({max_pulse}) and min_pulse "
                f"({min_pulse}); calibrate THROTTLE_FORWARD_PWM / THROTTLE_STOPPED_PWM / THROTTLE_REVERSE_PWM"
            )

    def calibrate(
        self,
        max_pulse: int | None = None,
        zero_pulse: int | None = None,
        min_pulse: int | None = None,
        *,
        check_only: bool = False,
    ) -> dict[str, int]:
        """Change the calibration live (``THROTTLE_FORWARD_PWM``, ``THROTTLE_STOPPED_PWM``,
        ``THROTTLE_REVERSE_PWM``); ``None`` keeps a value. Checked as the constructor checks it; with
        ``check_only`` nothing changes.

        Between drives the stopped pulse becomes the safe pulse (failsafe, shutdown, the next drive's arming).
        During a drive it is the pulse the ESC was armed with, so changing it raises :class:`CalibrationLocked`
        (after the constructor's checks): the end points may change, "stopped" may not. Set
        ``THROTTLE_STOPPED_PWM`` in the car's settings and start the drive again to re-arm at a new one."""
        vals = {
            "max_pulse": self.max_pulse if max_pulse is None else max_pulse,
            "zero_pulse": self.zero_pulse if zero_pulse is None else zero_pulse,
            "min_pulse": self.min_pulse if min_pulse is None else min_pulse,
        }
        self._check_calibration(vals["max_pulse"], vals["zero_pulse"], vals["min_pulse"])
        if self._safe_fixed and vals["zero_pulse"] != self.safe_pulse:
            raise CalibrationLocked(
                f"{self.name}: THROTTLE_STOPPED_PWM stays {self.safe_pulse} during a drive (the ESC was armed with "
                f"it), not {vals['zero_pulse']}; set it in the car's settings and start the drive again"
            )
        if not check_only:
            self.max_pulse, self._zero_pulse, self.min_pulse = vals["max_pulse"], vals["zero_pulse"], vals["min_pulse"]
            self.neutral_pulse = int(self._zero_pulse)
            self._calibrated()
        return {k: int(v) for k, v in vals.items()}

    @property
    def zero_pulse(self) -> Any:
        """``THROTTLE_STOPPED_PWM``. Setting it is :meth:`calibrate` (checked, and refused during a drive)."""
        return self._zero_pulse

    @zero_pulse.setter
    def zero_pulse(self, value: Any) -> None:
        self.calibrate(zero_pulse=value)

    def map_throttle(self, throttle: float | None) -> int:
        """Donkeycar's throttle mapping (clamped); ``None``, NaN and 0 are exactly the safe (stopped) pulse."""
        if throttle is None:
            return self.safe_pulse
        try:
            t = float(throttle)
        except (TypeError, ValueError):
            raise TypeError(f"{self.name}: throttle must be a number or None, got {throttle!r}") from None
        if t != t or t == 0.0:
            return self.safe_pulse
        t = -1.0 if t < -1.0 else 1.0 if t > 1.0 else t
        if t > 0:
            return donkeycar_map_range(t, 0, 1, self._zero_pulse, self.max_pulse)
        return donkeycar_map_range(t, -1, 0, self.min_pulse, self._zero_pulse)

    def run(self, throttle: float | None, throttle_age: float | None = None) -> None:
        """Set the throttle target; ``throttle_age`` (from a ``"...@age"`` input: the age of the sensing behind
        the command) enables the failsafe and the sensing-to-actuation latency."""
        self.command_pulse = self.map_throttle(throttle)
        fs = self.failsafe_age_s
        origin = None
        if throttle_age is None:
            stale_at = math.inf
            stale = False
            now = 0.0
        else:
            now_fn = self._now
            if now_fn is None:
                now_fn = self._now = get_clock().now
            now = now_fn()
            age = float(throttle_age)
            if age == age and age != math.inf:
                origin = now - age
            stale_at = math.inf if fs is None else -math.inf if origin is None else origin + fs
            stale = now >= stale_at
            if fs is not None:
                self._failsafe(stale, now, age)
        self._stale_at = stale_at
        unsafe = self.unsafe
        if stale:
            with self._wlock:
                unsafe.stale(stale_at, self.written_pulse == self.safe_pulse)
        elif unsafe.open_since is not None and throttle_age is not None:
            with self._wlock:
                unsafe.closed(now)  # a fresh command: the stale one's event ends, landed or not
        if self._tripped and not stale:
            self._tripped = False  # a fresh command after a watchdog event: drive again
        driving = not stale and self.armed
        self._set_target(self.command_pulse if driving else self.safe_pulse)
        if stale_at < self._writer_deadline:
            w = self._wake
            if w is not None and not w.done():
                w.set_result(None)
        rt = self._runtime
        if rt is not None:
            rt.deadline_changed(stale_at)
            if driving:
                self._command_applied(origin, now)

    def command_deadline(self) -> float:
        """When the current command goes stale (origin + ``failsafe_age_s``), on the runtime clock."""
        return self._stale_at if self.armed else math.inf

    run_threaded = run

    def _failsafe(self, stale: bool, now: float, age: float) -> None:
        if stale == self.failsafe_active:
            return
        self.failsafe_active = stale
        if stale:
            self.failsafe_events += 1
            more = self._log.ready("failsafe", now)
            if more is not None:
                logger.warning(
                    "%s: throttle command is %.0f ms old (failsafe at %.0f ms): holding stopped pulse %d "
                    "(failsafe event %d)%s",
                    self.name,
                    age * 1e3,
                    (self.failsafe_age_s or 0) * 1e3,
                    self.safe_pulse,
                    self.failsafe_events,
                    more,
                )

    def _desired(self, now: float) -> tuple[int, float]:
        if not self.armed:
            return self.safe_pulse, math.inf
        stale_at = self._stale_at
        if now >= stale_at:
            # the command went stale between ticks (or the tick stalled): stop without waiting for run()
            with self._wlock:
                self.unsafe.stale(stale_at, self.written_pulse == self.safe_pulse)
            self._failsafe(True, now, now - stale_at + (self.failsafe_age_s or 0))
            self.pulse = self.safe_pulse  # so the next fresh command counts as a change and wakes us
            return self.safe_pulse, math.inf
        return self.pulse, stale_at

    async def _before_driving(self, clock: Clock, waiter: DeadlineWaiter) -> None:
        neutral = self.safe_pulse
        while self._running and not await self._write(neutral, clock):
            await waiter.wait_until(clock.now() + self.retry_s)
        if self.arm_s:
            await waiter.wait_until(clock.now() + self.arm_s)
        self.armed = True
        self.pulse = self.command_pulse  # _desired() applies the failsafe to it
        logger.info("%s: ESC armed (stopped pulse %d held %.1f s)", self.name, neutral, self.arm_s)
