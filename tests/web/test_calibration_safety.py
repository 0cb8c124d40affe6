"""Who may calibrate, when, and the invariant behind it: whatever calibration messages come (from the driver or a
watcher, with the car driving or disarmed, any key, any value), the pulse the throttle writes for a zero command,
a STOP, the failsafe, the watchdog and shutdown is the stopped pulse the drive started with.

Deterministic: the controller's rules without its server (the pages are the desk's), the throttle and steering on
the PCA9685 register model, the drive on the virtual clock."""

from __future__ import annotations

import asyncio
import logging
from dataclasses import dataclass, field
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from asyncdonkey import Vehicle, get_clock
from asyncdonkey.parts.actuators import PWMSteering, PWMThrottle
from asyncdonkey.parts.web import WebController
from asyncdonkey.parts.web.calibrate import STEERING_KEYS, THROTTLE_KEYS, CalibrationError
from asyncdonkey.parts.web.desk import Command, Desk
from asyncdonkey.testing import VirtualClockLoop
from asyncdonkey.testing.i2c_models import I2CSimulator, PCA9685Model

STOPPED = 370  # PWMThrottle's default THROTTLE_STOPPED_PWM: the pulse every drive here starts (and arms) with
THROTTLE_CH, STEERING_CH = 0, 1
RATE_HZ = 20


# ---------------------------------------------------------------------------------------------- the desk's rule


def test_only_the_driver_calibrates_and_free_control_is_a_lone_pages_or_the_lapsed_drivers():
    desk = Desk(idle_release_s=1.0)
    desk.opened("driver"), desk.opened("watcher")
    assert desk.claim("driver", 0.0)
    assert desk.why_not_calibrator("driver", 0.5) is None
    assert "another client is driving" in desk.why_not_calibrator("watcher", 0.5)
    # the attack: the watcher stops the car (taking control), closes its page, comes back on a new one
    assert desk.claim("watcher", 0.6, force=True) and desk.closed("watcher")
    desk.opened("watcher again")
    assert "1 other page(s) are open" in desk.why_not_calibrator("watcher again", 0.7)
    assert "take control first" in desk.why_not_calibrator("driver", 0.7)  # the STOP took it from the driver too
    # a calibration page at rest sends nothing: its control lapses, and stays its own until someone takes it
    assert desk.claim("driver", 1.0) and desk.expire(2.5)
    assert desk.why_not_calibrator("driver", 2.5) is None
    assert desk.why_not_calibrator("watcher again", 2.5) is not None
    assert desk.claim("watcher again", 2.6)  # a stopped drive command: the watcher is now the driver
    assert desk.why_not_calibrator("driver", 2.7) is not None
    # a page alone with nobody driving is the driver to be
    desk.closed("watcher again"), desk.closed("driver")
    desk.opened("owner")
    assert desk.why_not_calibrator("owner", 9.0) is None


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_a_driver_calibrating_steering_while_disarmed_is_accepted_and_logged(caplog):
    rig = _Rig()
    ctr, steering, throttle = rig.ctr, rig.steering, rig.throttle
    steering.attach(_Runtime()), throttle.attach(_Runtime())  # the drive has started
    writer = asyncio.create_task(throttle.update())  # arms the ESC at the stopped pulse, then writes commands
    try:
        ctr.desk.opened("owner"), ctr.desk.opened("phone")
        ctr.apply("owner", Command(angle=0.0, throttle=0.0))
        await rig.write(0.0)  # disarmed: a zero command, the output at the stopped pulse
        with caplog.at_level(logging.INFO, "asyncdonkey.parts.web.controller"):
            got = ctr.calibrate("owner", {"STEERING_LEFT_PWM": 480, "STEERING_RIGHT_PWM": 300})
            assert (got["STEERING_LEFT_PWM"], steering.left_pulse, steering.right_pulse) == (480, 480, 300)
            assert "calibration by owner: STEERING_LEFT_PWM 460 -> 480, STEERING_RIGHT_PWM 290 -> 300" in caplog.text
            with pytest.raises(CalibrationError, match="another client is driving"):
                ctr.calibrate("phone", {"STEERING_LEFT_PWM": 470})
            assert "calibration refused for phone" in caplog.text and "STEERING_LEFT_PWM" in caplog.text
            ctr.apply("owner", Command(throttle=0.3))  # driving
            await rig.write(ctr.throttle)
            with pytest.raises(CalibrationError, match=r"must be stopped.*\+0\.30"):
                ctr.calibrate("owner", {"STEERING_LEFT_PWM": 470})
            ctr.apply("owner", Command(throttle=0.0, mode="local"))  # stopped, but a pilot may drive next tick
            await rig.write(0.0)
            with pytest.raises(CalibrationError, match="pilot may be driving"):
                ctr.calibrate("owner", {"STEERING_LEFT_PWM": 470})
            ctr.apply("owner", Command(mode="user"))
            with pytest.raises(CalibrationError, match="stays 370 during a drive"):
                ctr.calibrate("owner", {"THROTTLE_STOPPED_PWM": 440})
        assert steering.left_pulse == 480 and throttle.zero_pulse == STOPPED
        assert [r["refused"] is None for r in ctr.calibrations] == [True, False, False, False, False]
        assert ctr.calibrations[0]["changed"] == {"STEERING_LEFT_PWM": [460, 480], "STEERING_RIGHT_PWM": [290, 300]}
        assert ctr.refused_values["web/calibration"] == {"not_driver": 1, "moving": 2}
        assert ctr.refused_values["calibration/THROTTLE_STOPPED_PWM"] == {"armed": 1}
    finally:
        await throttle.shutdown()
        await writer
        rig.close()


# ------------------------------------------------------------------------------------ the property, on a drive


class _Runtime:
    """What a drive gives an actuator (the parts of it these tests use)."""

    guard_last = None

    def deadline_changed(self, t: float) -> None:
        pass

    def record_latency(self, now: float, origin: float) -> None:
        pass


class _Rig:
    """A web controller (no server) with PWM steering and throttle on a PCA9685 register model."""

    def __init__(self) -> None:
        self.sim = I2CSimulator()
        self.pca = self.sim.attach(PCA9685Model(), address=0x40, bus=1)
        self.buses = self.sim.registry(retry_delay_s=0)
        self.steering = PWMSteering(f"PCA9685.1:40.{STEERING_CH}", buses=self.buses)
        self.throttle = PWMThrottle(f"PCA9685.1:40.{THROTTLE_CH}", buses=self.buses, arm_s=0)
        self.ctr = WebController(
            host="127.0.0.1", announce=None, steering=self.steering, throttle=self.throttle, modes=("user", "local")
        )

    async def write(self, command: float) -> None:
        """The throttle's tick, then the time for its writer to put the pulse on the pin."""
        self.throttle.run(command)
        await asyncio.sleep(0.01)
        assert self.pca.pulse(THROTTLE_CH) == self.throttle.pulse

    def close(self) -> None:
        self.buses.close_all()


WHO = ("driver", "watcher")
KEYS = (*STEERING_KEYS, *THROTTLE_KEYS)


def _value(key: str) -> st.SearchStrategy[int]:
    if key == "THROTTLE_STOPPED_PWM":  # around the stopped pulse, and the attack's 440
        return st.sampled_from([300, 369, 370, 371, 440])
    return st.integers(100, 700)


calibration = st.sampled_from(KEYS).flatmap(lambda k: st.tuples(st.just("calibrate"), st.just(k), _value(k)))
action = st.one_of(
    st.tuples(st.just("drive"), st.sampled_from([-0.5, 0.0, 0.3, 1.0])),
    st.tuples(st.just("stop")),
    st.tuples(st.just("release")),
    st.tuples(st.just("reopen")),  # the page closes and comes back as a new client (the attack's drop)
    st.tuples(st.just("quiet"), st.integers(1, 30)),  # nobody sends for that many ticks
    calibration,
    calibration,
)
steps = st.lists(st.tuples(st.sampled_from(WHO), action), min_size=1, max_size=25)


@dataclass
class _Row:
    """One tick as the throttle saw it: its command, the pulse it targets, and its calibration."""

    pin_before: int
    command: Any
    target: int
    stale: bool
    safe: int
    zero: int
    zero_maps_to: int
    step: tuple[Any, ...] | None = None


@dataclass
class _Outcome:
    """A calibration request and the state it met."""

    who: str
    key: str
    value: int
    accepted: bool
    command: float
    written: int | None
    other_drives: bool
    error: str = ""


@dataclass
class _Script:
    """Each tick, the step due: a command, a stop, a page closing or a calibration, sent to the controller."""

    rig: _Rig
    plan: list[tuple[str, tuple[Any, ...]]]
    rows: list[_Row] = field(default_factory=list)
    outcomes: list[_Outcome] = field(default_factory=list)
    generation: dict[str, int] = field(default_factory=lambda: dict.fromkeys(WHO, 0))
    quiet: int = 0
    current: tuple[Any, ...] | None = None

    def __post_init__(self) -> None:
        for who in WHO:
            self.rig.ctr.desk.opened(self.client(who))

    def client(self, who: str) -> str:
        return f"{who}#{self.generation[who]}"

    def run(self) -> None:
        self.current = None
        if self.quiet:
            self.quiet -= 1
            return
        if not self.plan:
            return
        who, step = self.plan.pop(0)
        self.current = step
        ctr, client = self.rig.ctr, self.client(who)
        if step[0] == "drive":
            ctr.apply(client, Command(angle=0.0, throttle=step[1]))
        elif step[0] == "stop":
            ctr.apply(client, Command(stop=True))
        elif step[0] == "release":
            ctr.apply(client, Command(release=True))
        elif step[0] == "reopen":  # what the server does when a page closes: release, then forget the page
            ctr.apply(client, Command(release=True))
            ctr.desk.closed(client)
            self.generation[who] += 1
            ctr.desk.opened(self.client(who))
        elif step[0] == "quiet":
            self.quiet = step[1] - 1
        else:
            self.calibrate(who, client, step[1], step[2])

    def calibrate(self, who: str, client: str, key: str, value: int) -> None:
        ctr, throttle = self.rig.ctr, self.rig.throttle
        now = get_clock().now()
        other = ctr.desk.role(client, now) == "other"
        seen = (ctr.throttle, throttle.written_pulse)
        try:
            ctr.calibrate(client, {key: value})
        except CalibrationError as exc:
            self.outcomes.append(_Outcome(who, key, value, False, *seen, other, str(exc)))
        else:
            self.outcomes.append(_Outcome(who, key, value, True, *seen, other))


class _Watch:
    """After the throttle's run: what it was told and what it targets (the writer writes that before the next
    tick); the pin as this tick began (what the previous tick's target became)."""

    def __init__(self, rig: _Rig, script: _Script) -> None:
        self.rig, self.script = rig, script
        self.pin = rig.pca.pulse(THROTTLE_CH)

    def run(self, command: Any) -> None:
        t = self.rig.throttle
        zero = t.map_throttle(0.0)
        row = _Row(self.pin, command, t.pulse, t.failsafe_active, t.safe_pulse, t.zero_pulse, zero, self.script.current)
        self.script.rows.append(row)

    def sample_pin(self) -> None:
        self.pin = self.rig.pca.pulse(THROTTLE_CH)


class _PinProbe:
    def __init__(self, watch: _Watch) -> None:
        self.watch = watch

    def run(self) -> None:
        self.watch.sample_pin()


class _WebTick:
    """The controller's tick as the vehicle runs it (its server is not started: no sockets here)."""

    def __init__(self, ctr: WebController) -> None:
        self.ctr = ctr
        self.start: float | None = None  # where a started server's commands age from before the first one

    def run(self) -> tuple[float, float]:
        if self.start is None:
            self.start = get_clock().now()
        angle, throttle, *_ = self.ctr.run()
        return angle, throttle

    def output_origin(self) -> float | None:
        origin = self.ctr.output_origin()
        return self.start if origin is None else origin


class _SafeStateAtTheEnd:
    """On the last tick, the watchdog's write (from the loop thread here): the pin at once."""

    def __init__(self, rig: _Rig, last: int) -> None:
        self.rig, self.last, self.k = rig, last, 0
        self.pin: int | None = None

    def run(self) -> None:
        self.k += 1
        if self.k == self.last:
            self.rig.throttle.safe_state_sync()
            self.pin = self.rig.pca.pulse(THROTTLE_CH)


async def _drive(plan: list[tuple[str, tuple[Any, ...]]]) -> tuple[_Script, _Rig, int | None, int]:
    rig = _Rig()
    try:
        script = _Script(rig, list(plan))
        watch = _Watch(rig, script)
        ticks = sum(s[1] if s[0] == "quiet" else 1 for _, s in plan) + 12  # then 0.6 s of silence: the failsafe
        end = _SafeStateAtTheEnd(rig, ticks)
        v = Vehicle()
        v.add(_PinProbe(watch), name="pin")
        v.add(script, name="pages")
        v.add(_WebTick(rig.ctr), outputs=["angle", "throttle"], name="web")
        v.add(rig.steering, inputs=["angle"], name="steering")
        v.add(rig.throttle, inputs=["throttle", "throttle@age"], name="throttle")
        v.add(watch, inputs=["throttle"], name="watch")
        v.add(end, name="end")
        await v.run(rate_hz=RATE_HZ, max_loop_count=ticks)
        return script, rig, end.pin, rig.pca.pulse(THROTTLE_CH)
    finally:
        rig.close()


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(plan=steps)
def test_no_calibration_sequence_moves_the_pulse_of_a_zero_command_stop_failsafe_watchdog_or_shutdown(plan):
    with asyncio.Runner(loop_factory=VirtualClockLoop) as runner:
        script, rig, watchdog_pin, shutdown_pin = runner.run(_drive(plan))
    rows = script.rows
    for k, row in enumerate(rows):
        assert (row.safe, row.zero, row.zero_maps_to) == (STOPPED, STOPPED, STOPPED), (k, row)
        if row.command == 0.0 or row.stale or (row.step is not None and row.step[0] == "stop"):
            assert row.target == STOPPED, (k, row)  # a zero command, a STOP, the failsafe: the stopped pulse
        if k > 1 and rows[k - 1].target == STOPPED:  # (tick 0 ran before the writer started and armed the ESC)
            assert row.pin_before == STOPPED, (k, row)  # ... and it is what the pin showed next
    assert rows[-1].stale and rows[-1].pin_before == STOPPED  # the silence at the end: the failsafe
    assert watchdog_pin == STOPPED and shutdown_pin == STOPPED
    for o in script.outcomes:
        if o.accepted:  # only from the driver, only while disarmed, never moving "stopped"
            assert not o.other_drives and o.command == 0.0 and o.written == STOPPED, o
            assert o.key != "THROTTLE_STOPPED_PWM" or o.value == STOPPED, o
        elif o.other_drives:
            assert "another client is driving" in o.error, o
    assert len(rig.ctr.calibrations) == len(script.outcomes)  # every request kept, with who made it
    assert all(r["who"].split("#")[0] in WHO for r in rig.ctr.calibrations)
