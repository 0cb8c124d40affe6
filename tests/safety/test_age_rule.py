"""The age rule never makes data younger than the sensing behind it.

Ways it used to: an output whose inputs did not count (their producer was skipped by its run condition on this
tick) was dated *now*, and the "skipped" mark stayed on a channel a later part rewrote, so a switched-off pilot's
last command passed on (by a pass-through, a filter writing back to the same channel, straight into
``DriveMode``, or combined with a fresh input) went out as fresh; and an output that was one of its input objects
kept that input's origin even when the object was an array the part had written other, older data into. Examples
on the PCA9685 register model, then a property over random part graphs (the stronger one, with the true sensing
time carried by the values, is ``test_provenance_properties.py``). All on the virtual clock, so every age and
every time to neutral is exact.
"""

import asyncio
import enum
import math
from dataclasses import dataclass

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from asyncdonkey import Vehicle
from asyncdonkey.testing import VirtualClockLoop

from .rig import HALF, NEUTRAL, Rig
from .test_provenance import Pilot, Record, Seq, _make_drive_mode

RATE = 20
PERIOD = 1 / RATE

#: the cameras here are stand-ins that write the number 1, or a float array fused in place with an IMU's, to
#: ``cam/image_array``: what is measured is the age of the data, not its pixels, and that channel's contract
#: (a uint8 RGB image) rightly refuses it in checked mode
pytestmark = pytest.mark.asyncdonkey_checked(False)

WINDOW = 0.25  # PWMThrottle's failsafe_age_s default


class Switch:
    """A pilot's own on/off switch (its run condition): on for the first ``on_ticks`` ticks, then off."""

    def __init__(self, on_ticks: int) -> None:
        self.on_ticks = on_ticks
        self.k = 0

    def run(self) -> bool:
        self.k += 1
        return self.k <= self.on_ticks


class Trim:
    """The pass-through of the report: a new object made from its one input."""

    def run(self, t):
        return None if t is None else t * 1.0


# ------------------------------------------------------------------ a pass-through after a skipped pilot


def _switched_off_pilot_car(rig: Rig, drive_mode) -> tuple[Vehicle, object, Record]:
    """Mode ``local`` throughout; the pilot runs on ticks 0-9 (its switch then turns it off) and a pass-through
    re-publishes its throttle every tick, straight to the throttle or through ``drive_mode``."""
    v = Vehicle()
    v.add(Seq([1]), outputs=["cam/image_array"])
    v.add(Seq(["local"]), outputs=["user/mode"])
    v.add(Seq([(0.1, 0.5)]), outputs=["user/angle", "user/throttle"])
    v.add(Switch(10), outputs=["pilot/on"])
    v.add(Pilot(), inputs=["cam/image_array"], outputs=["pilot/angle", "pilot/throttle"], run_condition="pilot/on")
    if drive_mode is None:
        v.add(Trim(), inputs=["pilot/throttle"], outputs=["throttle"])
    else:
        v.add(Trim(), inputs=["pilot/throttle"], outputs=["pilot/throttle_trimmed"])
        v.add(
            drive_mode,
            inputs=["user/mode", "user/angle", "user/throttle", "pilot/angle", "pilot/throttle_trimmed"],
            outputs=["angle", "throttle"],
        )
    throttle = rig.throttle()
    v.add(throttle, inputs=["throttle", "throttle@age"], name="throttle")
    ages = Record()
    v.add(ages, inputs=["throttle@age"])
    return v, throttle, ages


@pytest.mark.donkeycar
@pytest.mark.parametrize("drive_mode", [None, "ours", "donkeycar"])
@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_a_pass_through_after_a_switched_off_pilot_stops_within_the_window(drive_mode):
    rig = Rig(asyncio.get_running_loop().time)
    dm = None if drive_mode is None else _make_drive_mode(drive_mode)
    v, throttle, ages = _switched_off_pilot_car(rig, dm)
    await v.run(RATE, 40)
    rig.close()
    last_run = 9 * PERIOD  # the pilot's last command: sensed at 0.45 s
    assert [a[0] for a in ages.seen] == pytest.approx([max(0.0, k * PERIOD - last_run) for k in range(40)])
    assert rig.pca.first_time(HALF, 0.0) == 0.0
    assert rig.pca.pulse_at(last_run + WINDOW - 0.01) == HALF
    assert rig.pca.first_time(NEUTRAL, PERIOD) == pytest.approx(last_run + WINDOW)  # 0.70 s
    assert rig.pca.pulse_at(39 * PERIOD) == NEUTRAL
    assert throttle.failsafe_events == 1


class SameChannel:
    """Donkeycar's ``ThrottleFilter`` pattern, ours: reads a channel and writes the value back to it, unchanged."""

    def run(self, t):
        return t


class LaunchLike:
    """Donkeycar's ``AiLaunch`` pattern, ours: reads the mode (fresh every tick) and the pilot's throttle, and
    writes the throttle back to the pilot's channel (unchanged while no launch is active)."""

    def run(self, mode, t):
        return t


class Blend:
    """Combines the pilot's throttle with a fresh input (the driver's): a new value made from both."""

    def run(self, pilot, user):
        return None if pilot is None else pilot + 0.0 * (user or 0.0)


def _straight():
    return []


def _same_channel():
    return [(SameChannel(), ["pilot/throttle"], ["pilot/throttle"])]


def _launch_like():
    return [(LaunchLike(), ["user/mode", "pilot/throttle"], ["pilot/throttle"])]


def _blend():
    return [(Blend(), ["pilot/throttle", "user/throttle"], ["pilot/throttle"])]


def _donkeycar_throttle_filter():
    from donkeycar.parts.throttle_filter import ThrottleFilter

    return [(ThrottleFilter(), ["pilot/throttle"], ["pilot/throttle"])]


def _donkeycar_ai_launch():
    from donkeycar.parts.launch import AiLaunch

    return [(AiLaunch(), ["user/mode", "pilot/throttle"], ["pilot/throttle"])]


def _ours():
    return _make_drive_mode("ours")


def _template():
    return _make_drive_mode("donkeycar")


_DK = pytest.mark.donkeycar
#: (the parts between the pilot and the drive mode, each ``(part, inputs, outputs)``, re-publishing the switched-off
#: pilot's throttle on ``pilot/throttle``; the drive mode, or ``None``: the throttle is that channel)
_PATHS = [
    pytest.param(_straight, _ours, id="straight-DriveMode"),
    pytest.param(_straight, _template, id="straight-template-DriveMode", marks=_DK),
    pytest.param(_same_channel, _ours, id="same-channel-filter-DriveMode"),
    pytest.param(_same_channel, _template, id="same-channel-filter-template-DriveMode", marks=_DK),
    pytest.param(_same_channel, None, id="same-channel-filter-to-the-throttle"),
    pytest.param(_launch_like, _ours, id="launch-like-DriveMode"),
    pytest.param(_blend, _ours, id="combined-with-a-fresh-input-DriveMode"),
    pytest.param(_blend, None, id="combined-with-a-fresh-input-to-the-throttle"),
    pytest.param(_donkeycar_throttle_filter, _ours, id="donkeycar-ThrottleFilter-DriveMode", marks=_DK),
    pytest.param(_donkeycar_throttle_filter, _template, id="donkeycar-ThrottleFilter-template-DriveMode", marks=_DK),
    pytest.param(_donkeycar_ai_launch, _ours, id="donkeycar-AiLaunch-DriveMode", marks=_DK),
    pytest.param(_donkeycar_ai_launch, _template, id="donkeycar-AiLaunch-template-DriveMode", marks=_DK),
]


@pytest.mark.parametrize(("middle", "drive_mode"), _PATHS)
@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_a_switched_off_pilots_throttle_passed_on_in_local_mode_stops_within_the_window(middle, drive_mode):
    """Mode ``local`` throughout; the pilot runs on ticks 0-9, then its own switch turns it off, and its last
    throttle is passed on every tick: straight into the drive mode, through a filter writing back to the same
    channel (Donkeycar's ``ThrottleFilter``, ``AiLaunch``), or combined with the driver's fresh throttle. Each
    re-publication is as old as the pilot's last command, so the throttle stops one window after it."""
    rig = Rig(asyncio.get_running_loop().time)
    v = Vehicle()
    v.add(Seq([1]), outputs=["cam/image_array"])
    v.add(Seq(["local"]), outputs=["user/mode"])
    v.add(Seq([(0.1, 0.5)]), outputs=["user/angle", "user/throttle"])
    v.add(Switch(10), outputs=["pilot/on"])
    v.add(Pilot(), inputs=["cam/image_array"], outputs=["pilot/angle", "pilot/throttle"], run_condition="pilot/on")
    for part, ins, outs in middle():
        v.add(part, inputs=ins, outputs=outs)
    if drive_mode is None:
        v.add(SameChannel(), inputs=["pilot/throttle"], outputs=["throttle"])
    else:
        v.add(
            drive_mode(),
            inputs=["user/mode", "user/angle", "user/throttle", "pilot/angle", "pilot/throttle"],
            outputs=["angle", "throttle"],
        )
    throttle = rig.throttle()
    v.add(throttle, inputs=["throttle", "throttle@age"], name="throttle")
    ages = Record()
    v.add(ages, inputs=["throttle@age"])
    await v.run(RATE, 40)
    rig.close()
    last_run = 9 * PERIOD  # the pilot's last command: sensed at 0.45 s
    assert [a[0] for a in ages.seen] == pytest.approx([max(0.0, k * PERIOD - last_run) for k in range(40)])
    assert rig.pca.first_time(HALF, 0.0) == 0.0
    assert rig.pca.pulse_at(last_run + WINDOW - 0.01) == HALF
    assert rig.pca.first_time(NEUTRAL, PERIOD) == pytest.approx(last_run + WINDOW)  # 0.70 s
    assert rig.pca.pulse_at(39 * PERIOD) == NEUTRAL
    assert throttle.failsafe_events == 1


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_a_pipelined_pass_through_after_a_switched_off_pilot_keeps_its_age():
    class AsyncTrim:
        async def run(self, t):
            return None if t is None else t * 1.0

    ages = Record()
    v = Vehicle()
    v.add(Seq([1]), outputs=["cam/image_array"])
    v.add(Switch(10), outputs=["pilot/on"])
    v.add(Pilot(), inputs=["cam/image_array"], outputs=["pilot/angle", "pilot/throttle"], run_condition="pilot/on")
    v.add(AsyncTrim(), inputs=["pilot/throttle"], outputs=["throttle"], pipelined=True)
    v.add(ages, inputs=["pilot/throttle@age", "throttle@age"])
    await v.run(RATE, 30)
    # from the tick the pilot is off, the pipelined part re-publishes what it computes from the pilot's last
    # command (sensed at 0.45 s): exactly as old as that command, not as young as its own run
    assert [t for _, t in ages.seen[10:]] == pytest.approx([p for p, _ in ages.seen[10:]])
    assert ages.seen[-1] == pytest.approx((29 * PERIOD - 9 * PERIOD,) * 2)


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_a_fresh_channel_read_for_its_age_does_not_make_a_skipped_pilots_command_fresh():
    class Gate:
        """Passes the pilot's throttle on while the frame is young: reads the camera's age, not its data."""

        def run(self, t, frame_age):
            return None if t is None or frame_age > 0.1 else t * 1.0

    ages = Record()
    v = Vehicle()
    v.add(Seq([1]), outputs=["cam/image_array"])
    v.add(Switch(10), outputs=["pilot/on"])
    v.add(Pilot(), inputs=["cam/image_array"], outputs=["pilot/angle", "pilot/throttle"], run_condition="pilot/on")
    v.add(Gate(), inputs=["pilot/throttle", "cam/image_array@age"], outputs=["throttle"])
    v.add(ages, inputs=["throttle@age"])
    await v.run(RATE, 20)
    assert [a[0] for a in ages.seen] == pytest.approx([max(0.0, (k - 9) * PERIOD) for k in range(20)])


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_a_value_made_from_nothing_sensed_has_no_age_to_drive_on():
    class Default:
        """Half throttle when its input (a pilot that never ran) has nothing."""

        def run(self, t):
            return 0.5 if t is None else t

    rig = Rig(asyncio.get_running_loop().time)
    ages = Record()
    v = Vehicle()
    v.add(Default(), inputs=["pilot/throttle"], outputs=["throttle"])
    throttle = rig.throttle()
    v.add(throttle, inputs=["throttle", "throttle@age"], name="throttle")
    v.add(ages, inputs=["throttle@age"])
    await v.run(RATE, 5)
    rig.close()
    assert v.mem["throttle"] == 0.5 and v.mem.origin("throttle") is None
    assert all(math.isinf(a[0]) for a in ages.seen)
    assert HALF not in [p for _, p in rig.pca.timeline]


# ---------------------------------------------------------------------------------- in-place writes


@pytest.mark.parametrize("stale", ["frame", "imu"])
@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_an_array_written_into_in_place_is_as_old_as_what_was_written_into_it(stale):
    class Sensor:
        """A fresh array each tick; sensed at t=0 and never again if it is the stale one, else now."""

        def __init__(self, fill: float, is_stale: bool) -> None:
            self.fill = fill
            self.is_stale = is_stale

        def run(self):
            return np.full(4, self.fill)

        def output_origin(self):
            return 0.0 if self.is_stale else None

    class Fuse:
        def run(self, img, imu):
            np.add(img, imu, out=img)
            return img

    ages = Record()
    v = Vehicle()
    v.add(Sensor(1.0, stale == "frame"), outputs=["cam/image_array"])
    v.add(Sensor(2.0, stale == "imu"), outputs=["imu"])
    v.add(Fuse(), inputs=["cam/image_array", "imu"], outputs=["cam/fused"])
    v.add(ages, inputs=["cam/image_array@age", "imu@age", "cam/fused@age"])
    await v.run(RATE, 31)
    assert v.mem["cam/fused"] is v.mem["cam/image_array"]
    assert list(v.mem["cam/fused"]) == [3.0] * 4
    assert ages.seen[-1][1] == pytest.approx(0.0 if stale == "frame" else 1.5)
    # the 1.5 s old data is in the fused array, whichever input it came from, and so in the camera's channel,
    # which holds that same array
    assert ages.seen[-1][0] == pytest.approx(1.5)
    assert ages.seen[-1][2] == pytest.approx(1.5)


class Gear(enum.Enum):
    LOW = 1


_VALUES = {
    "float": (0.25, True),
    "str": ("local", True),
    "enum": (Gear.LOW, True),
    "numpy-scalar": (np.float32(0.5), True),
    "tuple": ((0.1, 0.5), True),
    "list": ([0.1, 0.5], False),
    "dict": ({"a": 1}, False),
    "bytearray": (bytearray(b"x"), False),
    "ndarray": (np.zeros(2), False),
    "tuple-with-array": ((0.1, np.zeros(2)), False),
}


@pytest.mark.parametrize("declared", [False, True], ids=["undeclared", "declared"])
@pytest.mark.parametrize(("value", "immutable"), list(_VALUES.values()), ids=list(_VALUES))
@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_a_part_passing_an_input_through_is_dated_by_its_declaration_or_the_oldest_input(
    value, immutable, declared
):
    class Old:
        def run(self):
            return 1.0 + 0.0

        def output_origin(self):
            return 0.0  # sensed at the start, never since

    class Pick:
        def run(self, fresh, old):
            return fresh

    class DeclaredPick(Pick):
        def output_sources(self, fresh, old):
            return (0,)

    ages = Record()
    v = Vehicle()
    v.add(Seq([value]), outputs=["fresh"])
    v.add(Old(), outputs=["old"])
    v.add(DeclaredPick() if declared else Pick(), inputs=["fresh", "old"], outputs=["picked"])
    v.add(ages, inputs=["picked@age", "fresh@age"])
    await v.run(RATE, 5)
    assert v.mem["picked"] is value
    old = pytest.approx(4 * PERIOD)
    # declared: the fresh input's value, its age; not declared: nothing says which input it is, the oldest
    assert ages.seen[-1][0] == (0.0 if declared else old)
    # a mutable object returned as it is by an undeclared part may have had the old data written into it: the
    # fresh channel, which holds that object, is as old as it
    assert ages.seen[-1][1] == (0.0 if declared or immutable else old)


# ------------------------------------------------------------------------ the property: random graphs


@dataclass(frozen=True)
class PartSpec:
    """One part of a random graph. ``kind``: ``source`` (no inputs; a fresh tuple or list each time, or one
    list re-served and overwritten like a camera's buffer), ``pass`` (a new object from its one input),
    ``combine`` (a new object from its inputs), ``select`` (returns one input's object as it is), ``inplace``
    (writes its other inputs into its first input's list and returns that list), ``split`` (two outputs: a
    selected input object and a combined new one)."""

    kind: str
    inputs: tuple[str, ...] = ()
    runs: int | None = None  # its run condition, bit k for tick k (None: no run condition)
    quiet: int = 0  # sources: bit k set: returns None (writes nothing) on tick k
    lag: float | None = None  # sources: states its origin as this long before now (None: states none)
    value: str = "tuple"  # sources: "tuple", "list" or "buffer" (one list re-served)
    salt: int = 0  # selectors: which input is picked on tick k is (k + salt) % len(inputs)


TICKS = 10
_bits = st.integers(0, 2**TICKS - 1)


def _bit(mask: int, k: int) -> bool:
    return bool(mask >> k & 1)


@st.composite
def graphs(draw) -> list[PartSpec]:
    n = draw(st.integers(3, 8))
    n_sources = draw(st.integers(1, 3))
    channels = [f"c{j}" for j in range(n)] + ["never"]
    specs = []
    for j in range(n):
        runs = draw(st.none() | _bits)
        if j < n_sources:
            specs.append(
                PartSpec(
                    "source",
                    runs=runs,
                    quiet=draw(_bits),
                    lag=draw(st.sampled_from([None, 0.0, 0.05, 0.3, 1.5])),
                    value=draw(st.sampled_from(["tuple", "list", "buffer"])),
                )
            )
            continue
        kind = draw(st.sampled_from(["pass", "combine", "select", "inplace", "split"]))
        others = [c for c in channels if c != f"c{j}"]  # earlier, later (last tick's value) or never written
        k = 1 if kind == "pass" else draw(st.integers(1 if kind == "select" else 2, 3))
        ins = tuple(draw(st.lists(st.sampled_from(others), min_size=k, max_size=k, unique=True)))
        if kind == "combine" and draw(st.booleans()):
            ins += (draw(st.sampled_from(others)) + "@age",)  # a time, not data: it must not make others fresh
        specs.append(PartSpec(kind, ins, runs=runs, salt=draw(st.integers(0, 2))))
    return specs


class World:
    """Runs a random graph and models, for every channel, the set of sensing times that could have reached the
    value it holds, from the data flow alone.

    Precisely: a source's value has its own sensing time behind it (the stated one, else the time it returned).
    A part reading several channels may use every input holding a value (a producer skipped by its run condition
    still holds its last one). Then:

    * a new object has the union of the sets of the inputs it used behind it;
    * an input's immutable object passed through (a tuple) has only that input's set behind it;
    * an input's mutable object returned as it is (a list; whether the part wrote into it cannot be seen from
      outside) has that input's set and those of the inputs it used: anything could have been written into it.

    A channel's set is that of the value as written to it (a later in-place write into the same object through
    another channel is not added to it here: the runtime ages those holders too, which this model does not
    follow). ``@age`` inputs bring no sensing (they are times). The property: no channel's origin is later than
    the oldest sensing time in its set (its age is never less than that sensing's), and a channel with sensing
    behind it has an origin no earlier than the run's first sensing.
    """

    def __init__(self, specs: list[PartSpec]) -> None:
        self.specs = specs
        self.sets: dict[str, frozenset[float]] = {}
        self.values: dict[str, object] = {}
        self.tick = -1
        self.uid = 0
        self.checked = 0
        self.earliest = math.inf  # the earliest sensing time of the run
        self.now = asyncio.get_running_loop().time

    # -- the model
    def new_uid(self) -> int:
        self.uid += 1
        return self.uid

    def used(self, j: int, ins: tuple[str, ...]) -> list[str]:
        return [c for c in ins if not c.endswith("@age") and c in self.sets]

    def union(self, channels) -> frozenset[float]:
        return frozenset().union(*(self.sets[c] for c in channels))

    def passed(self, j: int, c: str) -> tuple[object, frozenset[float]]:
        """Input ``c``'s object as it is, with what could be behind it."""
        value = self.values[c]
        if isinstance(value, tuple):
            return value, self.sets[c]
        return value, self.sets[c] | self.union(self.used(j, self.specs[j].inputs))

    def fresh(self, behind: frozenset[float]) -> tuple[object, frozenset[float]]:
        return (self.new_uid(),), behind

    # -- the parts
    def part(self, j: int):
        spec = self.specs[j]
        world = self

        class Part:
            stated: float | None = None

            def run(self, *args):
                out = world.compute(j, spec)
                if out is None:
                    return None
                results, self.stated = out
                for k, (value, behind) in zip((f"c{j}", f"c{j}b"), results, strict=False):
                    world.values[k] = value
                    world.sets[k] = behind
                return results[0][0] if len(results) == 1 else tuple(r[0] for r in results)

        if spec.kind == "source" and spec.lag is not None:
            Part.output_origin = lambda self: self.stated
        return Part()

    def compute(self, j: int, spec: PartSpec):
        """``([(value, behind), ...], stated origin)`` for part ``j`` on this tick, or ``None``: writes nothing."""
        k = self.tick
        if spec.kind == "source":
            if _bit(spec.quiet, k):
                return None
            sensed = self.now() - (spec.lag or 0.0)
            self.earliest = min(self.earliest, sensed)
            if spec.value == "buffer":
                value = self.values.get(f"c{j}") or []
                value[:] = [self.new_uid()]
            else:
                value = [self.new_uid()] if spec.value == "list" else (self.new_uid(),)
            return [(value, frozenset({sensed}))], (sensed if spec.lag is not None else None)
        held = [c for c in spec.inputs if not c.endswith("@age") and c in self.sets]
        if not held:
            return None
        used = self.used(j, spec.inputs)
        if spec.kind in ("pass", "combine"):
            return [self.fresh(self.union(used))], None
        pick = spec.inputs[(k + spec.salt) % len(spec.inputs)]
        if spec.kind == "inplace":
            target = self.values.get(spec.inputs[0])
            if not isinstance(target, list):
                return None
            target.append(self.new_uid())  # (what it wrote does not matter: the model follows the sets)
            return [(target, self.sets[spec.inputs[0]] | self.union(used))], None
        if pick not in self.sets:
            return None
        if spec.kind == "select":
            return [self.passed(j, pick)], None
        return [self.passed(j, pick), self.fresh(self.union(used))], None

    def check(self, mem) -> None:
        """The property, for every channel a part of the graph wrote."""
        for c, behind in self.sets.items():
            origin = mem.origin(c)
            assert origin is not None, f"{c}: sensing {sorted(behind)} behind it, no origin"
            assert origin <= min(behind), f"tick {self.tick}: {c} dated {origin}, sensed as early as {min(behind)}"
            assert mem.age(c) >= self.now() - min(behind)
            assert origin >= self.earliest  # not an invented age: as old as some sensing that happened
            self.checked += 1


async def _run_world(specs: list[PartSpec]) -> World:
    world = World(specs)
    v = Vehicle()

    class Ticks:
        def run(self):
            world.tick += 1
            return tuple(s.runs is None or _bit(s.runs, world.tick) for s in specs)

    class Check:
        def run(self):
            world.check(v.mem)

    v.add(Ticks(), outputs=[f"on/{j}" for j in range(len(specs))])  # the run conditions (3 parts or more)
    for j, spec in enumerate(specs):
        outs = [f"c{j}", f"c{j}b"] if spec.kind == "split" else [f"c{j}"]
        cond = None if spec.runs is None else f"on/{j}"
        v.add(world.part(j), inputs=list(spec.inputs), outputs=outs, run_condition=cond, name=f"p{j}")
    v.add(Check())
    await v.run(RATE, TICKS)
    return world


@settings(max_examples=150, deadline=None)
@given(specs=graphs())
def test_no_channel_is_ever_younger_than_the_sensing_that_could_have_reached_it(specs):
    with asyncio.Runner(loop_factory=VirtualClockLoop) as runner:
        world = runner.run(_run_world(specs))
    assert world.tick == TICKS - 1
