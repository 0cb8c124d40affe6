"""PWMSteering / PWMThrottle: Donkeycar's mapping, the writer task, arming, failsafe, I2C faults, shutdown."""

import asyncio
import logging
import math
import re
import threading
import types

import donkeycar.utils as dku
import pytest
from donkeycar.parts import actuator as dk
from donkeycar.parts import pins as dkpins
from hypothesis import given, settings
from hypothesis import strategies as st

from asyncdonkey import Vehicle
from asyncdonkey.clock import get_clock
from asyncdonkey.hw.pinspec import PinSpecError
from asyncdonkey.parts.actuators import (
    CalibrationLocked,
    PWMSteering,
    PWMThrottle,
    donkeycar_map_range,
    pulse_to_ticks,
)
from asyncdonkey.testing.i2c_models import I2CSimulator, PCA9685Model

STEERING_TABLE = [(-1, 460), (-0.5, 417), (0, 375), (0.5, 332), (1, 290)]
THROTTLE_TABLE = [(-1, 220), (-0.5, 295), (0, 370), (0.5, 435), (1, 500)]


class Rig:
    """A simulated bus 1 with a PCA9685 at 0x40 and a registry over it."""

    def __init__(self, model: PCA9685Model | None = None) -> None:
        self.sim = I2CSimulator()
        self.pca = self.sim.attach(model or PCA9685Model(), address=0x40, bus=1)
        self.bus = self.sim.bus(1)
        self.buses = self.sim.registry(retry_delay_s=0)

    def steering(self, **kw) -> PWMSteering:
        return PWMSteering("PCA9685.1:40.1", buses=self.buses, **kw)

    def throttle(self, **kw) -> PWMThrottle:
        kw.setdefault("arm_s", 0)
        return PWMThrottle("PCA9685.1:40.0", buses=self.buses, **kw)


@pytest.fixture
def rig():
    r = Rig()
    yield r
    r.buses.close_all()


class Probe:
    """First part of each tick: records what the chip outputs on channels 1 (steering) and 0 (throttle)."""

    def __init__(self, pca: PCA9685Model) -> None:
        self.pca = pca
        self.rows: list[tuple[int, int]] = []

    def run(self):
        self.rows.append((self.pca.pulse(1), self.pca.pulse(0)))


class Script:
    """Outputs ``(angle, throttle)`` from a list, one entry per tick; ``None`` entries write nothing."""

    def __init__(self, commands) -> None:
        self.commands = list(commands)
        self.k = 0

    def run(self):
        cmd = self.commands[self.k] if self.k < len(self.commands) else None
        self.k += 1
        return cmd


# ------------------------------------------------------------------------------------- mapping


@pytest.mark.parametrize(("angle", "pulse"), STEERING_TABLE)
def test_steering_maps_like_donkeycar(rig, angle, pulse):
    s = rig.steering()
    n = len(rig.bus.log)
    s.run(angle)
    assert s.pulse == pulse
    assert len(rig.bus.log) == n  # run() never touches the bus


@pytest.mark.parametrize(("throttle", "pulse"), THROTTLE_TABLE)
def test_throttle_maps_like_donkeycar(rig, throttle, pulse):
    t = rig.throttle()
    assert t.map_throttle(throttle) == pulse


@pytest.mark.parametrize(
    ("value", "steer", "thr"), [(None, 375, 370), (math.nan, 375, 370), (-7, 460, 220), (3, 290, 500)]
)
def test_none_nan_are_neutral_and_inputs_are_clamped(rig, value, steer, thr):
    s, t = rig.steering(), rig.throttle()
    s.run(value)
    assert s.pulse == steer
    assert t.map_throttle(value) == thr


def test_non_numeric_input_names_the_part(rig):
    with pytest.raises(TypeError, match=r"PWMSteering \(channel 1 of PCA9685 at 0x40 on I2C bus 1\): angle"):
        rig.steering().run("left")


@pytest.mark.donkeycar
@settings(max_examples=300, deadline=None)
@given(st.floats(min_value=-1, max_value=1), st.sampled_from([(460, 290), (290, 460), (400, 340), (500, 200)]))
def test_mapping_is_bit_for_bit_donkeycars(x, cal):
    lo, hi = cal
    assert donkeycar_map_range(x, -1, 1, lo, hi) == dku.map_range(x, -1, 1, lo, hi)
    # whole parts: Donkeycar's PWMThrottle without its blocking constructor
    dk_throttle = object.__new__(dk.PWMThrottle)
    dk_throttle.max_pulse, dk_throttle.min_pulse, dk_throttle.zero_pulse = 500, 220, 370
    dk_throttle.run_threaded(x)
    ours = PWMThrottle(types.SimpleNamespace(set_pulse=lambda p: None), arm_s=0)
    assert ours.map_throttle(x) == dk_throttle.pulse


@pytest.mark.donkeycar
def test_pulse_to_ticks_matches_donkeycars_pulse_controller_on_the_chip(rig):
    """Donkeycar's PulseController + PCA9685 pin code drive channel 2 of the model, ours drives channel 3."""
    from asyncdonkey.hw.pca9685 import get_pca9685

    chip = get_pca9685(rig.buses.get(1), 0x40, 60)
    dk_pca = object.__new__(dkpins.PCA9685)  # skip its Adafruit import; route its set_pwm to our driver
    dk_pca.pwm = types.SimpleNamespace(set_pwm=chip.set_pwm_sync)
    dk_pca._frequency = 60
    for scale, inverted in [(1.0, False), (1.0, True), (0.83, False), (1.2, True)]:
        ctl = dk.PulseController(dkpins.PwmPinPCA9685(2, dk_pca), pwm_scale=scale, pwm_inverted=inverted)
        for pulse in [0, 1, 5, 220, 290, 370, 375, 460, 500, 2048, 3412, 4094, 4095]:
            try:
                ctl.set_pulse(pulse)
            except ValueError:  # Donkeycar refuses a scaled duty cycle above 1; we clamp instead
                assert int(pulse * scale) > 4095 or int((4095 - pulse) * scale) > 4095
                continue
            chip.set_pulse_sync(3, pulse_to_ticks(pulse, scale, inverted))
            assert rig.pca.pulse(3) == rig.pca.pulse(2), (pulse, scale, inverted)


# ----------------------------------------------------------------------------- driving the chip


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_drive_writes_each_command_to_the_chip_before_the_next_tick(rig):
    commands = [(a, t) for (a, _), (t, _) in zip(STEERING_TABLE, THROTTLE_TABLE, strict=True)]
    v = Vehicle()
    probe = Probe(rig.pca)
    v.add(probe)
    v.add(Script(commands), outputs=["angle", "throttle"])
    steering, throttle = rig.steering(), rig.throttle()
    v.add(steering, inputs=["angle"])
    v.add(throttle, inputs=["throttle", "throttle@age"])
    await v.run(rate_hz=20, max_loop_count=len(commands) + 1)
    expected = [(s, t) for (_, s), (_, t) in zip(STEERING_TABLE, THROTTLE_TABLE, strict=True)]
    assert probe.rows[1:] == expected
    assert rig.pca.frequency_hz == pytest.approx(59.84, abs=0.01)
    # shutdown: steering centred (not pulse 0 as in Donkeycar), throttle stopped
    assert (rig.pca.pulse(1), rig.pca.pulse(0)) == (375, 370)
    assert steering.write_errors == throttle.write_errors == 0


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_only_changes_are_written(rig):
    v = Vehicle()
    v.add(Script([(0.5, 0.2)] * 10 + [(-0.5, 0.2)] * 10), outputs=["angle", "throttle"])
    steering = rig.steering()
    v.add(steering, inputs=["angle"])
    await v.run(rate_hz=20, max_loop_count=20)
    # tick 0 set 0.5 before the writer started, then -0.5, then the shutdown centre
    assert steering.writes == 3
    assert rig.pca.history[1] == [0, 332, 417, 375]


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_esc_is_armed_by_holding_stopped_without_blocking_the_loop(rig):
    v = Vehicle()
    probe = Probe(rig.pca)
    v.add(probe)
    v.add(Script([(0.0, 0.5)] * 40), outputs=["angle", "throttle"])
    throttle = rig.throttle(arm_s=0.98)
    v.add(throttle, inputs=["throttle"])
    report = await v.run(rate_hz=20, max_loop_count=30)
    thr = [t for _, t in probe.rows]
    assert thr[0] == 0  # before the writer's first write
    assert thr[1:20] == [370] * 19  # ticks at 0.05 .. 0.95 s: armed at 0.98 s
    assert thr[20:] == [435] * 10
    assert report.loops == 30 and report.overruns == 0
    assert throttle.armed


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_stale_throttle_goes_to_stopped_counted_and_logged(rig, caplog):
    # fresh commands for ticks 0-9 and 30-39, silence otherwise
    commands = [0.5] * 10 + [None] * 20 + [0.5] * 10 + [None] * 10
    v = Vehicle()
    probe = Probe(rig.pca)
    v.add(probe)
    v.add(Script(commands), outputs=["throttle"])
    throttle = rig.throttle(failsafe_age_s=0.22)
    v.add(throttle, inputs=["throttle", "throttle@age"])
    with caplog.at_level(logging.WARNING, logger="asyncdonkey.parts.actuators"):
        await v.run(rate_hz=20, max_loop_count=50)
    thr = [t for _, t in probe.rows]
    # last fresh command at 0.45 s goes stale at 0.67 s: stopped from tick 14 (0.70 s)
    assert thr[1:14] == [435] * 13
    assert thr[14:31] == [370] * 17
    assert thr[31:44] == [435] * 13  # fresh again at tick 30, stale at 1.47 + 0.22 = 1.69 s
    assert thr[44:] == [370] * 6
    assert throttle.failsafe_events == 2
    warnings = [r for r in caplog.records if "failsafe" in r.getMessage()]
    assert len(warnings) == 2
    assert "PWMThrottle (channel 0 of PCA9685 at 0x40 on I2C bus 1)" in warnings[0].getMessage()


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_failsafe_acts_even_while_the_tick_is_stalled():
    class TimedPCA9685(PCA9685Model):
        """Records (virtual time, channel 0 pulse) at every change, from the writer's thread."""

        def __init__(self, loop):
            self.loop = loop
            self.timeline = []
            super().__init__()

        def end(self):
            super().end()
            p = self.pulse(0)
            if not self.timeline or self.timeline[-1][1] != p:
                self.timeline.append((self.loop.time(), p))

    class Stall:
        def __init__(self):
            self.k = 0

        async def run(self):
            self.k += 1
            if self.k == 11:
                await asyncio.sleep(1.0)  # a pilot that hangs for a second

    rig = Rig(TimedPCA9685(asyncio.get_running_loop()))
    v = Vehicle()
    v.add(Script([0.5] * 100), outputs=["throttle"])
    throttle = rig.throttle(failsafe_age_s=0.22)
    v.add(throttle, inputs=["throttle", "throttle@age"])
    v.add(Stall())
    await v.run(rate_hz=20, max_loop_count=30)
    t0 = rig.pca.timeline[0][0]
    changes = [(round(t - t0, 6), p) for t, p in rig.pca.timeline]
    # tick 10 (0.50 s) wrote the last fresh command, then stalled until 1.50 s: the writer stopped the car at
    # 0.72 s on its own timer, and the next fresh command (tick 11 at 1.50 s) resumed it
    assert changes[:5] == [(0.0, 0), (0.0, 370), (0.0, 435), (0.72, 370), (1.5, 435)]
    assert changes[-1][1] == 370  # shutdown
    assert throttle.failsafe_events == 1
    rig.buses.close_all()


def test_without_age_input_there_is_no_failsafe(rig):
    t = rig.throttle()
    t.armed = True
    t.run(0.5)
    assert t.pulse == 435 and t.failsafe_events == 0


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_never_written_throttle_is_stale(rig):
    v = Vehicle()
    throttle = rig.throttle()
    v.add(throttle, inputs=["throttle", "throttle@age"])
    await v.run(rate_hz=20, max_loop_count=5)
    assert throttle.failsafe_active and throttle.failsafe_events == 1
    assert rig.pca.history[0] == [0, 370]


# ------------------------------------------------------------------------------------ I2C faults


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_i2c_errors_mid_drive_are_counted_logged_and_survived(rig, caplog):
    class Fault:
        def __init__(self):
            self.k = 0

        def run(self):
            self.k += 1
            if self.k == 20:
                rig.bus.nack(0x40, times=None)
            elif self.k == 40:
                rig.bus.clear_faults()

    angles = [(-1) ** k * 0.5 for k in range(60)]
    v = Vehicle()
    probe = Probe(rig.pca)
    v.add(probe)
    v.add(Fault())
    v.add(Script(angles), outputs=["angle"])
    steering = rig.steering(retry_s=0.037)
    v.add(steering, inputs=["angle"])
    with caplog.at_level(logging.ERROR, logger="asyncdonkey.parts.actuators"):
        report = await v.run(rate_hz=20, max_loop_count=60)
    assert report.loops == 60 and report.stop_reason == "max_loop_count" and not report.part_errors
    assert steering.write_errors >= 10
    steer = [s for s, _ in probe.rows]
    assert steer[19] == 332  # tick 18 commanded +0.5, the last write before the bus failed
    assert set(steer[21:40]) == {steer[20]}  # the chip kept its last pulse while the bus failed
    assert steer[45:] == [332 if k % 2 == 0 else 417 for k in range(44, 59)]
    errors = [r for r in caplog.records if "writing pulse" in r.getMessage()]
    assert 1 <= len(errors) <= 2  # rate-limited: 1 s of failures, at most one message per second
    msg = errors[0].getMessage()
    assert "I2C bus 1, device 0x40, register 0x0A" in msg and "4 attempts" in msg


# ------------------------------------------------------------------------------- never blocking


@pytest.mark.realtime
@pytest.mark.asyncio
async def test_slow_i2c_never_shows_in_the_tick():
    """Each transfer takes 20 ms of real time; the parts' run() still costs well under a millisecond."""
    rig = Rig()
    rig.bus.transfer_delay_s = 0.02
    v = Vehicle()
    v.add(Script([((-1) ** k * 0.5, 0.3 * (-1) ** k) for k in range(12)]), outputs=["angle", "throttle"])
    steering, throttle = rig.steering(), rig.throttle()
    v.add(steering, inputs=["angle"], name="steering")
    v.add(throttle, inputs=["throttle"], name="throttle")
    report = await v.run(rate_hz=50, max_loop_count=12)
    assert report.parts["steering"]["max"] < 5 and report.parts["throttle"]["max"] < 5
    assert steering.writes >= 3 and throttle.writes >= 3
    assert (rig.pca.pulse(1), rig.pca.pulse(0)) == (375, 370)
    rig.buses.close_all()


# ------------------------------------------------------------------------------ construction paths


@pytest.mark.realtime
def test_parts_accept_a_prebuilt_channel(rig):
    from asyncdonkey.hw.pca9685 import open_pwm_channel

    ch = open_pwm_channel("PCA9685.1:40.5", buses=rig.buses)
    s = PWMSteering(ch)
    asyncio.run(s.shutdown())
    assert rig.pca.pulse(5) == 375


@pytest.mark.realtime
def test_parts_accept_a_donkeycar_blocking_controller_called_off_the_loop(rig):
    from asyncdonkey.hw.pca9685 import get_pca9685

    chip = get_pca9685(rig.buses.get(1), 0x40)
    threads = []

    class DonkeycarStyleController:
        def set_pulse(self, pulse):
            threads.append(threading.current_thread().name)
            chip.set_pulse_sync(6, pulse)

    async def main():
        s = PWMSteering(DonkeycarStyleController(), left_pulse=400, right_pulse=300)
        task = asyncio.create_task(s.update())
        s.run(1)
        await asyncio.sleep(0.05)
        assert rig.pca.pulse(6) == 300
        await s.shutdown()
        task.cancel()

    asyncio.run(main())
    assert rig.pca.pulse(6) == 350
    assert threads and all(name.startswith("pwm:DonkeycarStyleController") for name in threads)
    with pytest.raises(ValueError, match="pwm_scale/pwm_inverted"):
        PWMSteering(DonkeycarStyleController(), pwm_scale=1.2)


@pytest.mark.realtime
def test_from_donkeycar_config(rig):
    cfg = types.SimpleNamespace(
        PWM_STEERING_THROTTLE={
            "PWM_STEERING_PIN": "PCA9685.1:40.1",
            "PWM_STEERING_SCALE": 1.0,
            "PWM_STEERING_INVERTED": False,
            "PWM_THROTTLE_PIN": "PCA9685.1:40.0",
            "PWM_THROTTLE_SCALE": 1.0,
            "PWM_THROTTLE_INVERTED": True,
            "STEERING_LEFT_PWM": 470,
            "STEERING_RIGHT_PWM": 280,
            "THROTTLE_FORWARD_PWM": 510,
            "THROTTLE_STOPPED_PWM": 380,
            "THROTTLE_REVERSE_PWM": 230,
        }
    )
    s = PWMSteering.from_config(cfg, buses=rig.buses)
    t = PWMThrottle.from_config(cfg, buses=rig.buses, arm_s=0)
    assert (s.left_pulse, s.right_pulse, s.neutral_pulse) == (470, 280, 375)
    assert (t.max_pulse, t.zero_pulse, t.min_pulse) == (510, 380, 230)
    assert s.pulse == 375 and t.map_throttle(1) == 510
    asyncio.run(t.shutdown())
    assert rig.pca.pulse(0) == 4095 - 380  # inverted output


@pytest.mark.parametrize(
    ("make", "error", "match"),
    [
        (lambda r: PWMSteering("PCA9685.1.40.1", buses=r.buses), PinSpecError, "PCA9685.<bus>:<hex address>"),
        (lambda r: PWMSteering(42), TypeError, "controller must be a PCA9685 pin spec"),
        (lambda r: r.steering(left_pulse=300, right_pulse=300), ValueError, "calibrate them apart"),
        (lambda r: r.steering(left_pulse="460"), ValueError, "STEERING_LEFT_PWM"),
        (lambda r: r.throttle(zero_pulse=500), ValueError, "THROTTLE_STOPPED_PWM"),
        (lambda r: r.throttle(failsafe_age_s=0), ValueError, "failsafe_age_s"),
        (lambda r: r.steering(pwm_scale=0), ValueError, "pwm_scale"),
    ],
)
def test_bad_construction_is_explained(rig, make, error, match):
    with pytest.raises(error, match=re.escape(match)):
        make(rig)


@pytest.mark.realtime
def test_clock_is_taken_lazily_from_the_running_loop(rig):
    async def main():
        t = rig.throttle()
        t.run(0.5, 0.0)  # before update() started: still computes staleness on the loop's clock
        return t._now == get_clock().now

    assert asyncio.run(main())


def test_calibration_changes_live_and_is_checked_like_the_constructor(rig):
    s, t = rig.steering(), rig.throttle()
    assert s.calibrate(left_pulse=480, check_only=True) == {"left_pulse": 480, "right_pulse": 290}
    assert s.left_pulse == 460  # a check changes nothing
    s.calibrate(left_pulse=480, right_pulse=300)
    assert s.neutral_pulse == donkeycar_map_range(0, -1, 1, 480, 300)
    s.run(-1.0)
    assert s.pulse == 480
    with pytest.raises(ValueError, match="left_pulse and right_pulse are both 300"):
        s.calibrate(left_pulse=300)
    t.calibrate(zero_pulse=380)
    assert t.neutral_pulse == 380 and t.map_throttle(0.0) == 380
    with pytest.raises(ValueError, match=r"THROTTLE_STOPPED_PWM"):
        t.calibrate(max_pulse=380)
    assert t.max_pulse == 500


def test_a_zero_throttle_is_exactly_the_stopped_pulse_where_donkeycars_float_map_lands_one_below(rig):
    """A reversed ESC (forward 200, stopped 300, reverse 692): Donkeycar's floored map sends 299 for "stopped"."""
    assert donkeycar_map_range(0, -1, 0, 692, 300) == 299
    t = rig.throttle(max_pulse=200, zero_pulse=300, min_pulse=692)
    assert t.map_throttle(0.0) == t.map_throttle(-0.0) == t.map_throttle(None) == t.map_throttle(math.nan) == 300
    for x in (-1.0, -0.5, -1e-9, 1e-9, 0.5, 1.0):  # the rest of the map stays Donkeycar's
        span = (-1, 0, 692, 300) if x < 0 else (0, 1, 300, 200)
        assert t.map_throttle(x) == donkeycar_map_range(x, *span)


def test_the_stopped_pulse_is_locked_from_the_drives_start_to_its_end(rig):
    t, s = rig.throttle(), rig.steering()

    class Runtime:
        guard_last = None

    t.calibrate(zero_pulse=380)  # before a drive: the stopped pulse moves, and the safe one with it
    assert (t.safe_pulse, t.map_throttle(0)) == (380, 380)
    t.attach(Runtime()), s.attach(Runtime())
    for change in (lambda: t.calibrate(zero_pulse=370), lambda: setattr(t, "zero_pulse", 390)):
        with pytest.raises(CalibrationLocked, match=r"PWMThrottle \(channel 0 .*\): THROTTLE_STOPPED_PWM stays 380"):
            change()
    assert (t.zero_pulse, t.safe_pulse, t.map_throttle(0)) == (380, 380, 380)
    assert t.calibrate(zero_pulse=380, max_pulse=510) == {"max_pulse": 510, "zero_pulse": 380, "min_pulse": 220}
    s.calibrate(left_pulse=480)  # the steering end points move the centre a zero angle maps to, not the safe one
    assert (s.neutral_pulse, s.safe_pulse) == (385, 375)
    t.attach(None), s.attach(None)
    assert s.safe_pulse == 385
    t.zero_pulse = 370
    assert (t.safe_pulse, t.map_throttle(0)) == (370, 370)


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_a_writer_run_without_a_drive_locks_the_stopped_pulse_it_armed_with(rig):
    t = rig.throttle(arm_s=0.1)
    writer = asyncio.create_task(t.update())
    await asyncio.sleep(0.2)
    assert t.armed and rig.pca.pulse(0) == 370
    with pytest.raises(CalibrationLocked):
        t.calibrate(zero_pulse=400)
    await t.shutdown()
    await writer
    assert rig.pca.pulse(0) == 370 and not t.safe_pulse_fixed
    t.calibrate(zero_pulse=400)
    assert t.safe_pulse == 400
