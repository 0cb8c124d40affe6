"""Data ages follow the data through parts: the origin rule, selectors, sources, and the failsafe on top.

All on the virtual clock, so every age and every time to neutral is exact.
"""

import ast
import asyncio
import math
import types
from pathlib import Path

import pytest

from asyncdonkey import Memory, Vehicle
from asyncdonkey.core.origin_sources import declared_sources
from asyncdonkey.parts.control import DriveMode, PilotCondition
from asyncdonkey.parts.control import DriveMode as OurDriveMode

from .rig import HALF, NEUTRAL, Rig

RATE = 20
PERIOD = 1 / RATE

#: the camera here is a stand-in that writes the number 1 to ``cam/image_array``: what is measured is the age of
#: the data, not its pixels, and that channel's contract (a uint8 RGB image) rightly refuses it in checked mode
pytestmark = pytest.mark.asyncdonkey_checked(False)


class Record:
    """Collects what a part was given each tick."""

    def __init__(self) -> None:
        self.seen: list[tuple] = []

    def run(self, *args):
        self.seen.append(args)


class Seq:
    """Returns the next item each tick (``None`` items write nothing)."""

    def __init__(self, items) -> None:
        self.items = list(items)
        self.k = 0

    def run(self):
        item = self.items[self.k] if self.k < len(self.items) else self.items[-1]
        self.k += 1
        return item


# ------------------------------------------------------------------------------------------ the rule


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_republishing_an_old_value_never_makes_it_young():
    class Sensor:  # a source that states its origin: the sample was read at t=0 and never again
        def run(self):
            return 1.0

        def output_origin(self):
            return 0.0

    class Scale:
        def run(self, x):
            return 2 * x

    ages = Record()
    v = Vehicle()
    v.add(Sensor(), outputs=["raw"])
    v.add(Scale(), inputs=["raw"], outputs=["scaled"])
    v.add(ages, inputs=["raw@age", "scaled@age"])
    await v.run(RATE, 5)
    expected = [k * PERIOD for k in range(5)]
    assert [a[0] for a in ages.seen] == pytest.approx(expected, abs=1e-12)
    assert [a[1] for a in ages.seen] == pytest.approx(expected, abs=1e-12)
    assert v.mem.written_at("scaled") == pytest.approx(4 * PERIOD)  # written just now, sensed long ago


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_outputs_inherit_the_oldest_input_and_sources_are_sensed_when_they_return():
    class Combine:
        def run(self, a, b):
            return a + b

    ages = Record()
    v = Vehicle()
    v.mem.set("old", 1.0, origin=-2.0)  # e.g. a value received over the network, sensed 2 s before start
    v.add(Seq([1.0]), outputs=["new"])
    v.add(Combine(), inputs=["old", "new"], outputs=["sum"])
    v.add(ages, inputs=["new@age", "sum@age"])
    await v.run(RATE, 3)
    assert [a[0] for a in ages.seen] == [0.0, 0.0, 0.0]
    # Memory was re-stamped at the start of the drive (its values were stamped on another clock), so "old"
    # is as old as the drive: 0, 0.05, 0.10
    assert [a[1] for a in ages.seen] == pytest.approx([0.0, 0.05, 0.10])


class _Old:
    """A source sensed at the start and never since (it states so)."""

    def run(self):
        return tuple([1])

    def output_origin(self):
        return 0.0


class _Pick:
    """Passes ``fresh`` through as one output and ``old`` as the other, or makes a new value from both."""

    def __init__(self, pass_through: bool = True) -> None:
        self.pass_through = pass_through

    def run(self, fresh, old):
        return (fresh if self.pass_through else (fresh[0] + old[0],)), old


class _DeclaredPick(_Pick):
    def output_sources(self, fresh, old):
        return (0 if self.pass_through else (0, 1)), 1


@pytest.mark.parametrize("pass_through", [True, False])
@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_a_declared_selectors_outputs_have_the_origin_of_the_inputs_it_declares(pass_through):
    ages = Record()
    v = Vehicle()
    v.add(Seq([(7,)]), outputs=["fresh"])
    v.add(_Old(), outputs=["old"])
    v.add(_DeclaredPick(pass_through), inputs=["fresh", "old"], outputs=["a", "b"])
    v.add(ages, inputs=["a@age", "b@age"])
    await v.run(RATE, 3)
    t = [k * PERIOD for k in range(3)]
    # declared passed through: the fresh input's age; declared made from both: the older one's
    assert [x[0] for x in ages.seen] == ([0.0, 0.0, 0.0] if pass_through else pytest.approx(t))
    assert [x[1] for x in ages.seen] == pytest.approx(t)  # the old input's age


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_an_undeclared_part_passing_an_input_through_gets_the_oldest_origin():
    ages = Record()
    v = Vehicle()
    v.add(Seq([(7,)]), outputs=["fresh"])
    v.add(_Old(), outputs=["old"])
    v.add(_Pick(), inputs=["fresh", "old"], outputs=["a", "b"])
    v.add(ages, inputs=["fresh@age", "a@age", "b@age"])
    await v.run(RATE, 3)
    t = [k * PERIOD for k in range(3)]
    assert [x[0] for x in ages.seen] == [0.0, 0.0, 0.0]  # an immutable value: its own channel is untouched
    assert [x[1] for x in ages.seen] == pytest.approx(t)  # nothing says which input it is: the oldest
    assert [x[2] for x in ages.seen] == pytest.approx(t)


@pytest.mark.parametrize(
    ("declaration", "message"),
    [
        ((0,), "1 entries for 2 outputs"),
        ((0, 2), "with 2 not an input index"),
        ((0, "old"), "with 'old' not an input index"),
        (None, "not a sequence"),
    ],
)
@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_a_declaration_that_does_not_fit_the_part_fails_its_call_naming_it(declaration, message):
    class Wrong(_Pick):
        def output_sources(self, fresh, old):
            return declaration

    v = Vehicle()
    v.add(Seq([(7,)]), outputs=["fresh"])
    v.add(_Old(), outputs=["old"])
    v.add(Wrong(), inputs=["fresh", "old"], outputs=["a", "b"], name="pick")
    with pytest.raises(Exception, match=rf"pick.*output_sources\(\) returned .*{message}"):
        await v.run(RATE, 3)
    assert "a" not in v.mem  # nothing of that call was stored


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_never_written_inputs_do_not_count_and_skipped_ones_do():
    class Mix:
        def run(self, user, pilot, nothing):
            return (user or 0.0) + (pilot or 0.0) + 0.0

    class OnOnce:
        def __init__(self):
            self.k = 0

        def run(self):
            self.k += 1
            return self.k == 1

    ages = Record()
    v = Vehicle()
    v.mem.set("never_on", False)
    v.add(Seq([0.3]), outputs=["user"])
    v.add(Seq([0.9]), outputs=["pilot"], run_condition="never_on")
    v.add(OnOnce(), outputs=["once_on"])
    v.add(Seq([0.9]), outputs=["pilot_once"], run_condition="once_on")
    v.add(Mix(), inputs=["user", "pilot", "nothing"], outputs=["cmd"])
    v.add(Mix(), inputs=["user", "pilot_once", "nothing"], outputs=["cmd_once"])
    v.add(ages, inputs=["cmd@age", "pilot@age", "cmd_once@age"])
    await v.run(RATE, 3)
    assert [a[0] for a in ages.seen] == [0.0, 0.0, 0.0]  # nothing sensed behind the pilot's and nothing's
    assert all(math.isinf(a[1]) for a in ages.seen)
    # a producer skipped after it ran once: its value, sensed at 0, is in every later command
    assert [a[2] for a in ages.seen] == pytest.approx([0.0, 0.05, 0.10])


@pytest.mark.asyncio
@pytest.mark.virtual_clock
@pytest.mark.parametrize("stating", [False, True], ids=["source", "stating-part"])
async def test_a_none_among_a_sources_outputs_has_no_origin(stating):
    """A remote pilot's subscriber returns (None, None) until its first command: nothing sensed, so no age."""

    class Remote:
        def __init__(self) -> None:
            self.k = 0

        def run(self):
            self.k += 1
            return (None, None) if self.k < 3 else (0.1, 0.5)

    part = Remote()
    if stating:
        part.output_origin = lambda: None if part.k < 3 else 0.05  # nothing held: "use the rules"
    ages = Record()
    v = Vehicle()
    v.add(part, outputs=["pilot/angle", "pilot/throttle"])
    v.add(ages, inputs=["pilot/angle@age", "pilot/throttle@age"])
    await v.run(RATE, 4)
    assert ages.seen[:2] == [(math.inf, math.inf)] * 2
    expected = 0.0 if not stating else 2 * PERIOD - 0.05
    assert ages.seen[2] == pytest.approx((expected, expected), abs=1e-12)
    assert v.mem.origin("pilot/throttle") is not None


def test_memory_set_and_age_use_the_origin():
    now = [10.0]
    mem = Memory(clock=lambda: now[0])
    mem.set("x", 1, origin=9.5)
    mem["y"] = 2
    now[0] = 10.25
    assert mem.origin("x") == 9.5 and mem.written_at("x") == 10.0
    assert mem.age("x") == pytest.approx(0.75)
    assert mem.age("y") == pytest.approx(0.25)
    assert math.isinf(mem.age("never"))


# ------------------------------------------------------------------------------- selectors (the trap)


def _donkeycar_drive_mode():
    """Donkeycar 5.x's template DriveMode, compiled from the installed template, used unchanged."""
    import donkeycar

    src = (Path(donkeycar.__file__).parent / "templates" / "complete.py").read_text()
    tree = ast.parse(src)
    node = next(n for n in ast.walk(tree) if isinstance(n, ast.ClassDef) and n.name == "DriveMode")
    ns: dict = {}
    exec(compile(ast.Module(body=[node], type_ignores=[]), "complete.py", "exec"), ns)
    return ns["DriveMode"]


def _make_drive_mode(kind: str):
    if kind == "ours":
        return DriveMode()
    cls = _donkeycar_drive_mode()
    try:
        return cls()
    except TypeError:  # 5.3 takes the config
        import types

        return cls(types.SimpleNamespace(AI_THROTTLE_MULT=1.0))


class Mode:
    """The driver's mode switch: a list of (first tick, mode)."""

    def __init__(self, plan) -> None:
        self.plan = plan
        self.k = 0

    def run(self):
        mode = [m for start, m in self.plan if start <= self.k][-1]
        self.k += 1
        return mode


class Pilot:
    """Publishes 0.5 until ``silent_from`` (then returns None, or raises)."""

    def __init__(self, silent_from: int = 10**9, how: str = "none") -> None:
        self.silent_from = silent_from
        self.how = how
        self.calls = 0

    def run(self, image):
        self.calls += 1
        if self.calls > self.silent_from:
            if self.how == "raise":
                raise RuntimeError("inference failed")
            return None
        return 0.0 + 0.0, 0.5 + 0.0


def _car(rig: Rig, mode_plan, pilot: Pilot, drive_mode) -> tuple[Vehicle, object]:
    v = Vehicle()
    v.add(Seq([1]), outputs=["cam/image_array"])
    v.add(Mode(mode_plan), outputs=["user/mode"])
    v.add(Seq([(0.1, 0.5)]), outputs=["user/angle", "user/throttle"])  # the driver holds half throttle
    v.add(PilotCondition(), inputs=["user/mode"], outputs=["run_pilot"])
    v.add(
        pilot,
        inputs=["cam/image_array"],
        outputs=["pilot/angle", "pilot/throttle"],
        run_condition="run_pilot",
        on_error="continue",
    )
    v.add(
        drive_mode,
        inputs=["user/mode", "user/angle", "user/throttle", "pilot/angle", "pilot/throttle"],
        outputs=["angle", "throttle"],
    )
    throttle = rig.throttle()
    v.add(throttle, inputs=["throttle", "throttle@age"], name="throttle")
    return v, throttle


def _changes(rig: Rig, t0: float = 0.0):
    return [(round(t - t0, 6), p) for t, p in rig.pca.timeline]


@pytest.mark.donkeycar
@pytest.mark.parametrize("kind", ["ours", "donkeycar"])
@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_case_1_user_mode_with_the_pilot_never_run_drives(kind):
    rig = Rig(asyncio.get_running_loop().time)
    pilot = Pilot()
    v, throttle = _car(rig, [(0, "user")], pilot, _make_drive_mode(kind))
    await v.run(RATE, 40)
    rig.close()
    assert pilot.calls == 0
    assert _changes(rig)[:3] == [(0.0, 0), (0.0, NEUTRAL), (0.0, HALF)]  # drives from the first tick
    assert throttle.failsafe_events == 0
    assert rig.pca.pulse_at(38 * PERIOD) == HALF


@pytest.mark.donkeycar
@pytest.mark.parametrize("kind", ["ours", "donkeycar"])
@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_case_2_back_to_user_with_a_stale_pilot_drives_from_the_first_user_tick(kind):
    rig = Rig(asyncio.get_running_loop().time)
    # local for 10 ticks, the pilot dies at tick 5 (throttle stopped by the failsafe), user again at tick 20
    pilot = Pilot(silent_from=5)
    v, throttle = _car(rig, [(0, "local"), (20, "user")], pilot, _make_drive_mode(kind))
    await v.run(RATE, 40)
    rig.close()
    assert throttle.failsafe_events == 1
    # the pilot's last command (tick 4, 0.20 s) went stale at 0.45 s; the driver has the car at tick 20
    assert rig.pca.pulse_at(0.44) == HALF
    assert rig.pca.pulse_at(0.46) == NEUTRAL
    assert rig.pca.first_time(HALF, 0.46) == pytest.approx(20 * PERIOD)


@pytest.mark.donkeycar
@pytest.mark.parametrize("how", ["none", "raise"])
@pytest.mark.parametrize("kind", ["ours", "donkeycar"])
@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_case_3_a_silent_pilot_in_local_mode_stops_within_the_window(kind, how):
    rig = Rig(asyncio.get_running_loop().time)
    pilot = Pilot(silent_from=10, how=how)
    v, throttle = _car(rig, [(0, "local")], pilot, _make_drive_mode(kind))
    ages = Record()
    v.add(ages, inputs=["pilot/throttle@age", "throttle@age"])
    await v.run(RATE, 30)
    rig.close()
    # last fresh pilot command at tick 9 (0.45 s): neutral exactly one window (0.25 s) later, held
    assert rig.pca.pulse_at(0.69) == HALF
    assert rig.pca.first_time(NEUTRAL, 0.46) == pytest.approx(0.70)
    assert rig.pca.pulse_at(28 * PERIOD) == NEUTRAL
    assert throttle.failsafe_events == 1
    # a fresh gamepad does not hide the dead pilot: the selected command is as old as the pilot's
    assert ages.seen[-1][0] == pytest.approx(20 * PERIOD)
    assert ages.seen[-1][1] == pytest.approx(20 * PERIOD)


@pytest.mark.donkeycar
@pytest.mark.parametrize("kind", ["ours", "donkeycar"])
@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_case_4_a_fresh_pilot_in_local_mode_drives(kind):
    rig = Rig(asyncio.get_running_loop().time)
    pilot = Pilot()
    v, throttle = _car(rig, [(0, "local")], pilot, _make_drive_mode(kind))
    await v.run(RATE, 40)
    rig.close()
    assert pilot.calls == 40
    assert throttle.failsafe_events == 0
    assert rig.pca.first_time(HALF, 0.0) == 0.0
    assert NEUTRAL not in [p for t, p in rig.pca.timeline if 0.0 < t < 38.5 * PERIOD]


# --------------------------------------------------------------------------------------------- sources


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_a_sensor_sample_two_seconds_old_reads_two_seconds_old():
    from asyncdonkey import Poller

    reads = {"n": 0}

    def read_once():
        reads["n"] += 1
        if reads["n"] > 1:
            raise OSError(121, "Remote I/O error")  # the sensor goes quiet after its first sample
        return (0.0, 0.0, 9.81)

    poller = Poller(read_once, rate_hz=50, name="imu")
    ages = Record()
    v = Vehicle()
    v.add(poller, outputs=["imu/sample"])
    v.add(ages, inputs=["imu/sample@age"])
    await v.run(RATE, 41)
    assert v.mem["imu/sample"] == (0.0, 0.0, 9.81)  # re-published every tick ...
    assert ages.seen[-1][0] == pytest.approx(2.0)  # ... and still 2 s old
    assert poller.errors > 0


# ------------------------------------------------------------------------ declarations by interface


def _template_class(template: str, name: str):
    """A class of a Donkeycar template (``complete.py``, ``simulator.py``), compiled from the installed file."""
    import donkeycar

    src = (Path(donkeycar.__file__).parent / "templates" / template).read_text()
    node = next(n for n in ast.walk(ast.parse(src)) if isinstance(n, ast.ClassDef) and n.name == name)
    ns: dict = {"cfg": types.SimpleNamespace(AI_THROTTLE_MULT=1.0)}
    exec(compile(ast.Module(body=[node], type_ignores=[]), template, "exec"), ns)
    return ns[name]


@pytest.mark.donkeycar
@pytest.mark.parametrize(
    ("mode", "expected"), [("user", (1, 2, 3)), ("local_angle", (4, 2, 3)), ("local", (4, 5, 6)), (None, (4, 5, 6))]
)
def test_donkeycars_simulator_drive_mode_is_declared_as_its_code_chooses(mode, expected):
    part = _template_class("simulator.py", "DriveMode")()
    sources = declared_sources(part, 7, 3)
    args = (mode, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6)
    assert sources is not None and tuple(sources(*args)) == expected
    # the outputs it returns are the inputs the declaration names (a pilot value that is there passes as it is)
    out = part.run(*args)
    assert tuple(args[i] for i in expected) == tuple(out)


@pytest.mark.donkeycar
@pytest.mark.parametrize("show_pilot_image", [False, True])
@pytest.mark.parametrize("mode", ["user", "local"])
def test_donkeycars_user_pilot_condition_is_declared_as_its_code_chooses(mode, show_pilot_image):
    part = _template_class("complete.py", "UserPilotCondition")(show_pilot_image=show_pilot_image)
    sources = declared_sources(part, 3, 3)
    args = (mode, "user image", "pilot image")
    assert sources is not None
    declared = tuple(sources(*args))
    assert declared[:2] == (0, 0)  # the run conditions, from the mode
    assert args[declared[2]] == part.run(*args)[2]  # the image it shows, from the image it picked


def test_a_part_named_like_a_known_selector_with_another_interface_is_not_declared():
    class DriveMode:  # a user's own, with other inputs
        def run(self, mode, a, b, c, d):
            return a, b

    class UserPilotCondition:
        def run(self, mode, image):
            return True, False, image

    assert declared_sources(DriveMode(), 5, 2) is None
    assert declared_sources(UserPilotCondition(), 2, 3) is None
    # ours declares itself; the interface must also match the car's wiring (5 inputs, 2 outputs)
    ours = declared_sources(OurDriveMode(), 5, 2)
    assert ours is not None and tuple(ours("local", 1, 2, 3, 4)) == (3, 4)
