"""What the tick runs is one kind of thing: a :class:`TickStep`, declared once.

A part's run, a pipelined part's kicker and a guarded part's stand-in are all steps: each subclasses the protocol
(its fields and slots) and declares only the slots of its own job, so the step cannot drift into copies that
disagree. A drive with all three kinds shows every object in its tick list is a step with every field readable.
"""

import asyncio

import pytest

from asyncdonkey import Vehicle
from asyncdonkey.core.partrun import PartRun
from asyncdonkey.core.pipeline import GuardedTick, TickKicker
from asyncdonkey.core.runtypes import TickStep

STEP_CLASSES = (PartRun, TickKicker, GuardedTick)


@pytest.mark.parametrize("cls", STEP_CLASSES, ids=lambda c: c.__name__)
def test_each_step_class_is_a_tick_step_and_declares_no_step_slot_again(cls):
    assert TickStep in cls.__mro__
    own = set(cls.__dict__.get("__slots__", ()))
    assert not own & set(TickStep.__slots__), (
        f"{cls.__name__} declares step slots again: {own & set(TickStep.__slots__)}"
    )
    assert cls.__dictoffset__ == 0  # slotted through and through: no instance dict


def test_the_step_slots_are_its_fields():
    assert set(TickStep.__slots__) == set(TickStep.__annotations__)


class Counter:
    def __init__(self) -> None:
        self.n = 0

    def run(self):
        self.n += 1
        return self.n


class Pilot:
    async def run(self, n):
        await asyncio.sleep(0.001)
        return n


class Motor:
    async def run(self, throttle):
        await asyncio.sleep(0)


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_a_drive_ticks_only_tick_steps():
    v = Vehicle()
    v.add(Counter(), outputs=["n"], name="counter")
    v.add(Pilot(), inputs=["n"], outputs=["command"], pipelined=True, name="pilot")
    v.add(Motor(), inputs=["command"], react=True, name="motor")  # awaited and reacting: guarded
    seen = {}

    class Look:
        def run(self):
            seen["steps"] = v.drive.tick_runs

    v.add(Look(), name="look")
    report = await v.run(20, 10)
    steps = seen["steps"]
    assert [type(s).__name__ for s in steps] == ["PartRun", "TickKicker", "GuardedTick", "PartRun"]
    for s in steps:
        assert TickStep in type(s).__mro__
        for field in TickStep.__annotations__:
            getattr(s, field)  # every field the tick reads is set
    assert [s.name for s in steps] == ["counter", "pilot", "motor", "look"]
    assert report.pipelined["pilot"]["runs"] >= 8 and "motor" in report.reentries_avoided
