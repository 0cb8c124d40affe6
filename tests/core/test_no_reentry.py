"""A part is never entered while it is still running, whatever path calls it: the tick, a pipelined part's worker,
the reactions to a pipelined part or to a push source. Each part below counts its own concurrent entries."""

import asyncio
import threading
import time

import pytest

from asyncdonkey import Vehicle, get_clock
from asyncdonkey.latest import Latest

RATE = 20


class Overlap:
    """How many calls of one part run at once: ``overlaps`` counts the entries made while another was running."""

    def __init__(self) -> None:
        self.active = 0
        self.overlaps = 0
        self.calls = 0
        self._lock = threading.Lock()

    def enter(self) -> None:
        with self._lock:
            self.active += 1
            self.calls += 1
            if self.active > 1:
                self.overlaps += 1

    def leave(self) -> None:
        with self._lock:
            self.active -= 1


class Counter:
    """A tick-read source: 1, 2, 3, ..."""

    def __init__(self) -> None:
        self.n = 0

    def run(self):
        self.n += 1
        return self.n


class NumberedPilot:
    """An 80 ms inference whose every command is a new number, so each one can be followed to the actuator."""

    def __init__(self, seconds: float) -> None:
        self.seconds = seconds
        self.published: list[float] = []

    async def run(self, frame):
        await asyncio.sleep(self.seconds)
        cmd = float(len(self.published) + 1)
        self.published.append(cmd)
        return cmd


class AsyncActuator:
    """Takes 5 ms to write each command (an async bus write); records every command it was entered with."""

    def __init__(self, seconds: float = 0.005) -> None:
        self.seconds = seconds
        self.o = Overlap()
        self.applied: list[float] = []

    async def run(self, cmd):
        self.o.enter()
        try:
            self.applied.append(cmd)
            await asyncio.sleep(self.seconds)
        finally:
            self.o.leave()


class Pusher:
    """A source on its own schedule (``offset`` after each tick) that pushes each new number as it makes it."""

    def __init__(self, hz: float, offset: float) -> None:
        self.hz = hz
        self.offset = offset
        self.values: Latest[int] = Latest()
        self.pushed: list[int] = []

    async def update(self):
        clock = get_clock()
        t0 = clock.now() + self.offset
        k = 0
        while True:
            await clock.sleep_until(t0 + k / self.hz)
            self.pushed.append(len(self.pushed) + 1)
            self.values.publish(self.pushed[-1], clock.now())
            k += 1

    def run(self):
        s = self.values.sample
        return None if s is None else s.value

    def output_origin(self):
        s = self.values.sample
        return None if s is None else s.timestamp

    def subscribe(self, callback):
        return self.values.subscribe(callback)


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_an_async_react_actuator_is_never_entered_twice_by_the_tick_and_the_pilots_publish():
    pilot = NumberedPilot(0.08)
    act = AsyncActuator(0.005)
    v = Vehicle()
    v.add(Counter(), outputs=["frame"])
    v.add(pilot, inputs=["frame"], outputs=["cmd"], pipelined=True)
    v.add(act, inputs=["cmd"], react=True, name="act")
    report = await v.run(RATE, 400)
    assert act.o.calls > 400
    assert act.o.overlaps == 0
    # every command the pilot published reached the actuator, or was counted as superseded by a newer one (the
    # last may have been published as the drive ended)
    missing = set(pilot.published) - set(act.applied)
    assert len(missing - {pilot.published[-1]}) <= report.reentries_avoided["act"]["coalesced"]
    assert not missing - {pilot.published[-1]}
    # the publish found the tick's write running and waited for it: counted, and in the report's table
    assert report.reentries_avoided["act"]["waited"] > 0
    assert "one call at a time (act)" in v.format_report(report)
    # the loop still keeps its rate
    assert report.overruns == 0


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_a_react_part_fed_by_a_push_source_waits_for_the_ticks_call_and_the_tick_for_its():
    pusher = Pusher(hz=20, offset=0.048)  # 48 ms after each tick: its reaction still runs when the next tick comes

    class Mixer:
        """5 ms of async work on the tick's frame and the pushed value; its output is read later in the tick."""

        def __init__(self):
            self.o = Overlap()
            self.seen: list[int] = []

        async def run(self, frame, pushed):
            self.o.enter()
            try:
                self.seen.append(pushed)
                await asyncio.sleep(0.005)
                return frame
            finally:
                self.o.leave()

    class Reader:
        def __init__(self):
            self.rows = []

        def run(self, frame, mixed):
            self.rows.append((frame, mixed))

    mixer, reader = Mixer(), Reader()
    v = Vehicle()
    v.add(Counter(), outputs=["frame"])
    v.add(pusher, outputs=["pushed"])
    v.add(mixer, inputs=["frame", "pushed"], outputs=["mixed"], react=True, name="mixer")
    v.add(reader, inputs=["frame", "mixed"])
    report = await v.run(RATE, 100)
    assert mixer.o.overlaps == 0
    # every pushed value reached the part (the last push may come as the drive ends)
    assert set(pusher.pushed[:-1]) <= set(mixer.seen)
    # the tick waited for the reaction's call, then ran the part itself: its later parts see this tick's output
    assert reader.rows and all(mixed == frame for frame, mixed in reader.rows)
    assert report.reentries_avoided["mixer"]["waited"] >= 90
    assert report.reentries_avoided["mixer"]["coalesced"] == 0


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_a_sync_executor_part_is_not_run_in_two_threads_by_the_tick_and_a_reaction():
    pusher = Pusher(hz=20, offset=0.0)  # pushes as each tick starts

    class SyncWriter:
        def __init__(self):
            self.o = Overlap()
            self.seen: list[int] = []

        def run(self, pushed):
            self.o.enter()
            try:
                self.seen.append(pushed)
                time.sleep(0.002)  # real work in the worker thread
            finally:
                self.o.leave()

    writer = SyncWriter()
    v = Vehicle()
    v.add(pusher, outputs=["pushed"])
    v.add(writer, inputs=["pushed"], executor=True, react=True, name="writer")
    report = await v.run(RATE, 30)
    assert writer.o.calls >= 30
    assert writer.o.overlaps == 0
    assert set(pusher.pushed[:-1]) <= set(writer.seen)
    assert report.reentries_avoided["writer"]["waited"] > 0


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_requests_arriving_while_one_waits_are_coalesced_into_it_newest_wins():
    # three sources push at the same instants into one 10 ms part: the first push runs it, the second waits for
    # that call, the third is served by the second's run (which reads the newest values of all three)
    sources = [Pusher(hz=20, offset=0.02) for _ in range(3)]

    class Joiner:
        def __init__(self):
            self.o = Overlap()
            self.seen: list[tuple[int, int, int]] = []

        async def run(self, a, b, c):
            self.o.enter()
            try:
                self.seen.append((a, b, c))
                await asyncio.sleep(0.01)
            finally:
                self.o.leave()

    joiner = Joiner()
    v = Vehicle()
    for k, s in zip("abc", sources, strict=True):
        v.add(s, outputs=[k], name=f"source {k}")
    v.add(joiner, inputs=["a", "b", "c"], react=True, name="joiner")
    report = await v.run(RATE, 40)
    assert joiner.o.overlaps == 0
    figures = report.reentries_avoided["joiner"]
    assert figures["coalesced"] > 0 and figures["waited"] > 0
    # nothing lost: every value of every source reached the part
    for i, s in enumerate(sources):
        assert set(s.pushed[:-1]) <= {row[i] for row in joiner.seen}
    # a coalesced request is served by a run that starts after it: never more runs than requests
    assert joiner.o.calls < 40 + 3 * len(sources[0].pushed)


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_pushes_faster_than_their_reactions_are_superseded_counted_never_queued():
    pusher = Pusher(hz=100, offset=0.003)  # a push every 10 ms into a part that takes 25 ms
    act = AsyncActuator(0.025)
    v = Vehicle()
    v.add(pusher, outputs=["cmd"], name="receiver")
    v.add(act, inputs=["cmd"], react=True, name="act")
    report = await v.run(RATE, 40)
    assert act.o.overlaps == 0
    pushed = report.pushed["receiver"]
    assert pushed["superseded"] > 0
    # every push reached the part, or was counted as superseded by a newer one (the last ones may come as the
    # drive ends)
    never_run = set(pusher.pushed[:-3]) - set(act.applied)
    assert 0 < len(never_run) <= pushed["superseded"]
    assert "pushed receiver" in v.format_report(report)


@pytest.mark.asyncio
@pytest.mark.virtual_clock
@pytest.mark.parametrize("pipelined", [False, True], ids=["executor", "pipelined"])
async def test_a_thread_left_running_by_a_timeout_is_not_entered_again(pipelined):
    release, returned = threading.Event(), threading.Event()

    class Stuck:
        """Its first call hangs in its worker thread until released; the call itself times out meanwhile."""

        def __init__(self):
            self.o = Overlap()

        def run(self, frame):
            self.o.enter()
            first = self.o.calls == 1
            try:
                if first:
                    release.wait()
                return frame
            finally:
                self.o.leave()
                if first:
                    returned.set()

    class Releaser:
        """Releases the hung call on tick 5, and holds the loop until it has returned (virtual time would
        otherwise run on to the end of the drive while the thread wakes up)."""

        def run(self, frame):
            if frame == 5:
                release.set()
                returned.wait(5.0)

    stuck = Stuck()
    v = Vehicle()
    v.add(Counter(), outputs=["frame"])
    kind = {"pipelined": True} if pipelined else {"executor": True}
    v.add(stuck, inputs=["frame"], outputs=["out"], timeout=0.01, on_error="continue", name="stuck", **kind)
    v.add(Releaser(), inputs=["frame"])
    try:
        report = await v.run(RATE, 12)
    finally:
        release.set()
    assert stuck.o.overlaps == 0
    # the timed-out call on tick 1, then the calls that found its thread still running on ticks 2-5, each failing
    # after its own timeout; except pipelined on tick 5, whose start waits until after the tick, when the releaser
    # has let the thread return: that wait ends with the thread
    last_failed = 4 if pipelined else 5
    assert report.part_errors["stuck"] == last_failed
    assert report.reentries_avoided["stuck"] == {"waited": 4, "coalesced": 0}
    # once its thread was free it ran again, on every tick (pipelined, the last tick's start may come as the drive
    # ends)
    assert 1 + 12 - last_failed - pipelined <= stuck.o.calls <= 1 + 12 - last_failed
    assert v.mem["out"] >= 12 - pipelined
