"""A vehicle's entries are the plan ``add()`` made: driving the car never writes them.

Everything a drive learns about a part (errors, timing series, latency recorder, pipeline kicks, guard, checked
stores) is in the drive's own ``PartRun``s, so a second drive starts from the same plan and reports only itself.
The car here exercises every one of those: a part that fails on every tick, a push source whose frames trigger a
pipelined pilot, a checked output, and an async ``react=True`` actuator that the loop measures itself and that a
guard keeps to one call at a time (the tick and the pilot's publish both call it).
"""

import asyncio

import pytest

from asyncdonkey import Vehicle, get_clock
from asyncdonkey.core.plan import Entry
from asyncdonkey.latest import Latest

RATE = 20
TICKS = 30


class PushCamera:
    """Pushes a frame number 13 ms after each tick (the channel is not the image channel: numbers, no contract)."""

    def __init__(self) -> None:
        self.frames: Latest[int] = Latest()
        self.n = 0

    async def update(self):
        clock = get_clock()
        t0 = clock.now() + 0.013
        k = 0
        while True:
            await clock.sleep_until(t0 + k / RATE)
            self.n += 1
            self.frames.publish(self.n, clock.now())
            k += 1

    def run(self):
        s = self.frames.sample
        return None if s is None else s.value

    def output_origin(self):
        s = self.frames.sample
        return None if s is None else s.timestamp

    def subscribe(self, callback):
        return self.frames.subscribe(callback)


class Pilot:
    async def run(self, frame):
        await asyncio.sleep(0.01)
        return 0.25 + 0.0


class Throttle:
    """An actuator without ``attach``: the loop records its latency at the end of each run."""

    def __init__(self) -> None:
        self.runs = 0

    async def run(self, throttle):
        self.runs += 1
        await asyncio.sleep(0)

    def safe_state_sync(self):
        pass


class Flaky:
    def run(self):
        raise RuntimeError("always fails")


def _car() -> Vehicle:
    v = Vehicle(checked=True)
    v.add(PushCamera(), outputs=["frame"], name="camera")
    v.add(Pilot(), inputs=["frame"], outputs=["pilot/throttle"], pipelined=True, trigger="frame", name="pilot")
    v.add(Throttle(), inputs=["pilot/throttle"], react=True, name="throttle")
    v.add(Flaky(), on_error="continue", name="flaky")
    return v


def _plan(v: Vehicle) -> list[dict[str, object]]:
    return [{slot: getattr(e, slot) for slot in Entry.__slots__} for e in v.parts]


def _same(before: list[dict[str, object]], after: list[dict[str, object]]) -> list[str]:
    """The (part, slot) pairs whose value is not the very object it was."""
    return [
        f"{b['name']}.{slot}"
        for b, a in zip(before, after, strict=True)
        for slot in Entry.__slots__
        if a[slot] is not b[slot]
    ]


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_driving_writes_nothing_into_the_entries_and_each_drive_counts_afresh():
    v = _car()
    before = _plan(v)
    first = await v.run(RATE, TICKS)
    assert _same(before, _plan(v)) == []

    # the drive did keep per-run state: errors, a pipeline started by pushes, a checked store, a guard, latency
    assert first.part_errors == {"flaky": TICKS}
    assert first.checked_parts >= 1
    assert first.pipelined["pilot"]["runs"] >= TICKS - 2
    assert "throttle" in first.reentries_avoided
    assert first.latency_ms["throttle"]["max"] > 0
    assert set(first.parts) >= {"camera", "throttle", "flaky", "pilot"}

    second = await v.run(RATE, TICKS)
    assert _same(before, _plan(v)) == []
    assert second.part_errors == {"flaky": TICKS}  # counted from zero again, not carried over
    assert second.latency_ms["throttle"]["max"] > 0


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_per_run_state_lives_on_the_drives_runs_not_the_entries():
    v = _car()
    seen = {}

    class Look:
        def run(self):
            d = v.drive
            seen["runs"] = {r.name: r for r in d.runs}

    v.add(Look(), name="look")
    await v.run(RATE, 3)
    runs = seen["runs"]
    assert runs["flaky"].errors == 3 and runs["flaky"].entry is v.parts[3]
    assert runs["pilot"].series is not None and runs["throttle"].latency is not None
    assert runs["camera"].kicks and runs["throttle"].reentry_guard is not None
    for slot in ("errors", "series", "latency", "kicks", "reentry_guard"):
        assert slot not in Entry.__slots__

    await v.run(RATE, 3)
    assert seen["runs"]["flaky"] is not runs["flaky"]  # a fresh run object per drive
    assert seen["runs"]["flaky"].errors == 3
