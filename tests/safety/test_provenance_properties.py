"""No value is ever dated younger than the sensing that could have produced it: a property over random cars.

Each random car is driven by the project's drive loop (``Vehicle``) on the virtual clock, and every value in it
carries its own true sensing time as data, so the truth is read off the values themselves, not modelled beside
them: a value is ``STALE_BASE - t`` for the oldest sensing time ``t`` behind it (``stamp``/``sensed``). Sources
emit ``stamp(time sensed)``; every other part computes with ``max`` (on stamps: the oldest sensing wins), so a
new value made from several inputs, a value written into an array in place (``np.maximum(a, b, out=a)``), a
selector's pick and a filter writing back to its own channel all hold exactly the sensing behind them. A
constant that is not data (``DriveMode``'s ``0.0`` for a pilot that has said nothing) reads as sensed in the far
future, which any origin satisfies.

The car: a camera (array frames, stating a capture time some lag ago, sometimes silent), the driver's mode and
commands (sometimes silent), a pilot switched by its own run condition or by ``PilotCondition``, sometimes silent
(``None``) or failing (``on_error="continue"``), then a random chain of parts on the pilot's, the driver's and the
camera's channels: pass-throughs, same-channel filters (Donkeycar's ``ThrottleFilter``/``AiLaunch`` pattern),
parts combining a channel with a fresh side input (and an ``@age`` one), in-place array writes, declared
selectors, undeclared selectors, each with a random run condition; then our ``DriveMode`` and an actuator.

Asserted after every tick: each channel's origin is never later than the oldest true sensing in the value it
holds (``Memory.age`` never less than its true age); and at the actuator, on every call, the ``@age`` of the
command it was given is never less than that command's true age.
"""

from __future__ import annotations

import asyncio
import math
from dataclasses import dataclass

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from asyncdonkey import Vehicle
from asyncdonkey.parts.control import DriveMode, PilotCondition
from asyncdonkey.testing import VirtualClockLoop

#: the stand-in frames are float arrays, not the uint8 images ``cam/image_array``'s contract asks for
pytestmark = pytest.mark.asyncdonkey_checked(False)

RATE = 20
TICKS = 16
STALE_BASE = 1e6  # far beyond any time of a run: stamps stay positive and ``max`` picks the oldest sensing


def stamp(t: float) -> float:
    """The value a source emits when sensed at ``t``: the larger, the older."""
    return STALE_BASE - t


def sensed(value: object) -> float:
    """The oldest true sensing time behind ``value`` (``inf``: none, e.g. a constant)."""
    if value is None or isinstance(value, str | bool):
        return math.inf
    top = float(np.max(value))  # type: ignore[arg-type]
    return math.inf if top <= 0 else STALE_BASE - top


def _oldest(*values: object) -> object:
    """A new value made from ``values`` (``None``s ignored): as old as the oldest of them."""
    present = [v for v in values if v is not None]
    if not present:
        return None
    arrays = [v for v in present if isinstance(v, np.ndarray)]
    if arrays:
        return np.maximum.reduce([np.broadcast_to(np.asarray(v, dtype=float), (3,)) for v in present]).copy()
    return max(float(v) for v in present)  # type: ignore[arg-type]


_bits = st.integers(0, 2**TICKS - 1)


def _bit(mask: int, k: int) -> bool:
    return bool(mask >> k & 1)


ARRAYS = ["cam/image_array"]
FLOATS = ["user/angle", "user/throttle", "pilot/angle", "pilot/throttle"]


@dataclass(frozen=True)
class Link:
    """One part of the random chain. ``kind``: ``pass`` (a new value from one input), ``filter`` (the input's
    own value, written back to the same channel), ``combine`` (a new value from its inputs, one of them read
    perhaps only for its ``@age``), ``inplace`` (writes its other inputs into its first, an array, and returns
    it), ``select`` (returns one input's object as it is, declaring which), ``undeclared`` (the same, not
    declaring)."""

    kind: str
    inputs: tuple[str, ...]
    output: str
    runs: int | None  # its run condition, bit k for tick k (None: none)
    salt: int = 0


@dataclass(frozen=True)
class Car:
    cam_lag: float
    cam_quiet: int
    user_quiet: int
    modes: tuple[str, ...]
    pilot_switch: int | None  # None: PilotCondition decides (any mode but user)
    pilot_silent: int
    pilot_raises: bool
    chain: tuple[Link, ...]
    drive_mode_throttle: str


@st.composite
def cars(draw: st.DrawFn) -> Car:
    arrays, floats = list(ARRAYS), list(FLOATS)
    chain = []
    for j in range(draw(st.integers(0, 6))):
        kind = draw(st.sampled_from(["pass", "filter", "combine", "inplace", "select", "undeclared"]))
        runs = draw(st.none() | _bits)
        if kind == "inplace":
            target = draw(st.sampled_from(arrays))
            other = draw(st.sampled_from([c for c in arrays + floats if c != target]))
            out = draw(st.sampled_from([target, f"x{j}"]))
            chain.append(Link(kind, (target, other), out, runs))
            if out not in arrays:
                arrays.append(out)
            continue
        pool = draw(st.sampled_from([arrays, floats]))
        if kind in ("pass", "filter"):
            ins: tuple[str, ...] = (draw(st.sampled_from(pool)),)
        else:
            ins = tuple(draw(st.lists(st.sampled_from([*pool, "never"]), min_size=2, max_size=3, unique=True)))
            if kind == "combine" and draw(st.booleans()):
                ins += (draw(st.sampled_from(arrays + floats)) + "@age",)
        out = ins[0] if kind == "filter" else draw(st.sampled_from([ins[0], f"x{j}"]))
        if out == "never":
            out = f"x{j}"
        chain.append(Link(kind, ins, out, runs, draw(st.integers(0, 2))))
        if out not in pool:
            pool.append(out)
    return Car(
        cam_lag=draw(st.sampled_from([0.0, 0.03, 0.3])),
        cam_quiet=draw(_bits),
        user_quiet=draw(_bits),
        modes=tuple(draw(st.lists(st.sampled_from(["user", "local_angle", "local"]), min_size=TICKS, max_size=TICKS))),
        pilot_switch=draw(st.none() | _bits),
        pilot_silent=draw(_bits),
        pilot_raises=draw(st.booleans()),
        chain=tuple(chain),
        drive_mode_throttle=draw(st.sampled_from(floats)),
    )


class Run:
    """One car's drive: the tick number the parts see, the checks made."""

    def __init__(self, car: Car) -> None:
        self.car = car
        self.tick = -1
        self.now = asyncio.get_running_loop().time
        self.checked = 0
        self.actuated = 0


class Camera:
    def __init__(self, run: Run) -> None:
        self.r = run
        self.t: float | None = None

    def run(self) -> np.ndarray | None:
        self.r.tick += 1
        if _bit(self.r.car.cam_quiet, self.r.tick):
            return None
        self.t = self.r.now() - self.r.car.cam_lag
        return np.full(3, stamp(self.t))

    def output_origin(self) -> float | None:
        return self.t


class Driver:
    """The driver's mode and commands, sensed when returned (a source without a stated origin)."""

    def __init__(self, run: Run) -> None:
        self.r = run

    def run(self) -> tuple[str, float, float] | None:
        if _bit(self.r.car.user_quiet, self.r.tick):
            return None
        s = stamp(self.r.now())
        return self.r.car.modes[self.r.tick], s, s


class Switch:
    def __init__(self, run: Run) -> None:
        self.r = run

    def run(self) -> bool:
        mask = self.r.car.pilot_switch
        return mask is not None and _bit(mask, self.r.tick)


class Pilot:
    def __init__(self, run: Run) -> None:
        self.r = run

    def run(self, frame: np.ndarray | None) -> tuple[float, float] | None:
        if _bit(self.r.car.pilot_silent, self.r.tick):
            if self.r.car.pilot_raises:
                raise RuntimeError("inference failed")
            return None
        if frame is None:
            return None
        s = float(np.max(frame))
        return s, s


class Part:
    """One link of the chain."""

    def __init__(self, run: Run, link: Link) -> None:
        self.r = run
        self.link = link
        self.picked = 0

    def run(self, *args: object) -> object:
        kind, ins = self.link.kind, self.link.inputs
        if kind in ("pass", "filter"):
            (x,) = args
            if kind == "pass" and x is not None:
                return x.copy() if isinstance(x, np.ndarray) else float(x) + 0.0  # type: ignore[arg-type]
            return x
        if kind == "combine":
            return _oldest(*(a for a, k in zip(args, ins, strict=True) if not k.endswith("@age")))
        if kind == "inplace":
            target, other = args
            if not isinstance(target, np.ndarray) or other is None:
                return None
            np.maximum(target, np.max(other), out=target)  # type: ignore[arg-type]
            return target
        self.picked = (self.r.tick + self.link.salt) % len(args)
        return args[self.picked]


class Selector(Part):
    """Returns one input's object as it is, and says which."""

    def output_sources(self, *args: object) -> tuple[int]:
        return (self.picked,)


class Actuator:
    """Checks each command against its ``@age``: never younger than the sensing it carries."""

    def __init__(self, run: Run) -> None:
        self.r = run

    def run(self, angle: object, angle_age: float, throttle: object, throttle_age: float) -> None:
        now = self.r.now()
        for name, value, age in (("angle", angle, angle_age), ("throttle", throttle, throttle_age)):
            truth = sensed(value)
            if truth < math.inf:
                assert age >= now - truth - 1e-9, (
                    f"tick {self.r.tick}: {name} {value} acted on at age {age}, true age {now - truth}"
                )
                self.r.actuated += 1

    def safe_state_sync(self) -> None:
        pass


def _check(run: Run, v: Vehicle) -> None:
    mem = v.mem
    for k, value in mem.items():
        truth = sensed(value)
        if truth == math.inf:
            continue
        origin = mem.origin(k)
        assert origin is None or origin <= truth + 1e-9, (
            f"tick {run.tick}: {k} dated {origin}, holds data sensed at {truth}"
        )
        run.checked += 1


async def _drive(car: Car) -> Run:
    run = Run(car)
    v = Vehicle()
    v.add(Camera(run), outputs=["cam/image_array"])
    v.add(Driver(run), outputs=["user/mode", "user/angle", "user/throttle"])
    if car.pilot_switch is None:
        v.add(PilotCondition(), inputs=["user/mode"], outputs=["run_pilot"])
    else:
        v.add(Switch(run), outputs=["run_pilot"])
    v.add(
        Pilot(run),
        inputs=["cam/image_array"],
        outputs=["pilot/angle", "pilot/throttle"],
        run_condition="run_pilot",
        on_error="continue",
    )
    for j, link in enumerate(car.chain):
        if link.runs is not None:
            v.add(_Bits(run, link.runs), outputs=[f"on/{j}"])
        cls = Selector if link.kind == "select" else Part
        cond = None if link.runs is None else f"on/{j}"
        v.add(cls(run, link), inputs=list(link.inputs), outputs=[link.output], run_condition=cond, name=f"link{j}")
    v.add(
        DriveMode(),
        inputs=["user/mode", "user/angle", "user/throttle", "pilot/angle", car.drive_mode_throttle],
        outputs=["angle", "throttle"],
    )
    v.add(Actuator(run), inputs=["angle", "angle@age", "throttle", "throttle@age"], actuator=True)
    v.add(_Check(run, v))
    await v.run(RATE, TICKS)
    return run


class _Bits:
    def __init__(self, run: Run, mask: int) -> None:
        self.r = run
        self.mask = mask

    def run(self) -> bool:
        return _bit(self.mask, self.r.tick)


class _Check:
    def __init__(self, run: Run, v: Vehicle) -> None:
        self.r = run
        self.v = v

    def run(self) -> None:
        _check(self.r, self.v)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(car=cars())
def test_no_value_is_ever_dated_younger_than_the_sensing_behind_it(car: Car) -> None:
    with asyncio.Runner(loop_factory=VirtualClockLoop) as runner:
        run = runner.run(_drive(car))
    assert run.tick == TICKS - 1
    # the check ran whenever something was sensed (a car whose camera and driver are quiet on every tick holds
    # nothing sensed, so there is nothing to date)
    sensed_anything = any(not (_bit(car.cam_quiet, t) and _bit(car.user_quiet, t)) for t in range(TICKS))
    assert run.checked > 0 or not sensed_anything
