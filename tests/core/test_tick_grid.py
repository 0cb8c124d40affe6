"""Background schedules on the drive's tick grid: a drive makes its ticks (``t0 + k / rate_hz``) known to its parts'
``update()`` tasks, and a :class:`Poller` reads on them, a little ahead, so that the machine wakes once for a
tick and the sample due with it, and the tick has that sample."""

from __future__ import annotations

import asyncio
import ctypes
import statistics
import sys
import threading
import time

import pytest
import uvloop

from asyncdonkey import Poller, Vehicle
from asyncdonkey.clock import TickGrid, grid_start, tick_grid
from asyncdonkey.core.drive import START_MARGIN_S
from asyncdonkey.poller import POLL_LEAD_S
from asyncdonkey.testing import VirtualClockLoop


# ------------------------------------------------------------------------------------------- grid_start
def test_without_a_grid_a_schedule_starts_now():
    assert grid_start(None, 60, 12.345, lead_s=1e-4) == 12.345


@pytest.mark.parametrize(
    ("now", "lead_s", "expected"),
    [
        (9.995, 0.0, 10.0),  # before the first tick: the first tick itself
        (10.0, 0.0, 10.0),  # on a point: that point
        (10.001, 0.0, 10.0 + 1 / 60),  # just past one: the next
        (10.3, 0.0, 10.0 + 18 / 60),  # later on: the next point of the poller's own rate, on the ticks' grid
        (9.995, 1e-4, 10.0 - 1e-4),  # ahead of the ticks by the lead
        (10.0, 1e-4, 10.0 - 1e-4 + 1 / 60),  # the lead's point has passed: the next one
    ],
)
def test_a_schedule_starts_at_the_first_grid_point_not_before_now(now, lead_s, expected):
    grid = TickGrid(origin=10.0, period=0.05)
    assert grid_start(grid, 60, now, lead_s) == pytest.approx(expected, abs=1e-12)
    assert grid_start(grid, 60, now, lead_s) >= now - 1e-9


def test_its_points_fall_on_the_ticks_where_the_rates_share_them():
    grid = TickGrid(origin=100.0, period=0.05)  # a 20 Hz drive
    start = grid_start(grid, 60, 100.0)  # a 60 Hz schedule: every third point is a tick
    for j in range(0, 300, 3):
        k = j // 3
        assert start + j / 60 == pytest.approx(grid.origin + k * grid.period, abs=1e-9)


# --------------------------------------------------------------------------------- the drive's grid
def test_a_drives_update_tasks_see_its_grid_and_nothing_else_does():
    seen: dict[str, TickGrid | None] = {}

    class Background:
        def __init__(self, name: str) -> None:
            self.name = name

        async def update(self) -> None:
            seen[self.name] = tick_grid()

        def run_threaded(self) -> None:
            return None

    async def main() -> tuple[float, float]:
        fast, slow = Vehicle(), Vehicle()
        fast.add(Background("fast"), threaded=True)
        slow.add(Background("slow"), threaded=True)
        first: dict[str, float] = {}

        class Stamp:
            def __init__(self, name: str) -> None:
                self.name = name

            def run(self) -> None:
                first.setdefault(self.name, asyncio.get_running_loop().time())

        fast.add(Stamp("fast"))
        slow.add(Stamp("slow"))
        await asyncio.gather(fast.run(rate_hz=50, max_loop_count=3), slow.run(rate_hz=10, max_loop_count=3))
        assert tick_grid() is None  # outside the drives
        return first["fast"], first["slow"]

    with asyncio.Runner(loop_factory=VirtualClockLoop) as runner:
        fast_t0, slow_t0 = runner.run(main())
    assert seen == {"fast": TickGrid(fast_t0, 1 / 50), "slow": TickGrid(slow_t0, 1 / 10)}  # each its own drive's


def test_on_the_virtual_clock_the_first_tick_is_at_once_and_a_poller_reads_on_its_grid():
    stamps: list[float] = []
    ticks: list[float] = []

    async def main() -> None:
        loop = asyncio.get_running_loop()
        t_start = loop.time()

        def read() -> int:
            stamps.append(loop.time())
            return len(stamps)

        class Stamp:
            def run(self) -> None:
                ticks.append(loop.time())

        v = Vehicle()
        v.add(Stamp())
        v.add(Poller(read, rate_hz=60, name="imu"), outputs=["imu"])
        await v.run(rate_hz=20, max_loop_count=21)
        assert ticks[0] == t_start  # no start margin: virtual time stands still while the drive starts

    with asyncio.Runner(loop_factory=VirtualClockLoop) as runner:
        runner.run(main())
    assert stamps[:60:3] == pytest.approx(ticks[:20], abs=1e-12)  # every third read is due with a tick


# --------------------------------------------------------------------------------- on a real loop
@pytest.mark.realtime
def test_on_a_real_loop_the_first_tick_waits_the_start_margin_and_the_poller_reads_on_its_grid():
    """Real time on a possibly busy machine: only what it can guarantee. The first tick is never before the drive's
    t0, reads are never before their grid point, and most are within a couple of milliseconds of it."""
    reads: list[float] = []
    threads: set[str] = set()
    ticks: list[float] = []

    def read() -> int:
        reads.append(time.monotonic())
        threads.add(threading.current_thread().name)
        return len(reads)

    class Stamp:
        def run(self) -> None:
            ticks.append(time.monotonic())

    async def main() -> float:
        v = Vehicle()
        v.add(Stamp())
        v.add(Poller(read, rate_hz=60, name="imu"), outputs=["imu"])
        started = time.monotonic()
        task = asyncio.create_task(v.run(rate_hz=20, max_loop_count=20))
        await asyncio.sleep(0)  # the drive has started its background work and fixed its first tick
        t0 = v.drive.t0
        assert t0 is not None and started + START_MARGIN_S <= t0 <= time.monotonic() + START_MARGIN_S
        await task
        return t0

    with asyncio.Runner(loop_factory=uvloop.new_event_loop) as runner:
        t0 = runner.run(main())
    assert threads == {"poll:imu"}
    assert ticks[0] >= t0
    origin = t0 - POLL_LEAD_S
    offsets = []
    for t in reads:
        j = round((t - origin) * 60)
        if (t - origin) * 60 < j:  # (after the grid point's own rounding: a read is never before its point)
            j -= 1
        assert t >= origin + j / 60 - 1e-9
        offsets.append(t - (origin + j / 60))
    assert reads[0] >= origin - 1e-9
    assert statistics.median(offsets) < 2e-3


@pytest.mark.realtime
@pytest.mark.parametrize("precise", [False, True])
def test_on_a_real_loop_every_tick_has_the_sample_read_just_before_it(precise):
    """A 60 Hz poller beside a 20 Hz drive reads just ahead of every tick, so each tick has a sample a fraction
    of a millisecond old, not one from the read before (a poll period, 16.7 ms). In precise mode the reads are
    ahead of the drive's spin too: one due inside it would be published only after the tick. Real time: the
    fraction of fresh ticks, which a busy machine's odd late wake-up does not decide: with the poller at a random
    phase about an eighth of the ticks would have a sample that young, and in precise mode without the spin's
    lead none."""
    ages: list[float] = []

    class Age:
        def run(self, read_at: float | None) -> None:
            if read_at is not None:
                ages.append(time.monotonic() - read_at)

    async def main() -> None:
        v = Vehicle()
        v.add(Poller(time.monotonic, rate_hz=60, name="clock"), outputs=["read_at"])
        v.add(Age(), inputs=["read_at"])
        await v.run(rate_hz=20, max_loop_count=40, precise=precise)

    with asyncio.Runner(loop_factory=uvloop.new_event_loop) as runner:
        runner.run(main())
    assert len(ages) >= 39  # the first tick already has the first read
    lead = POLL_LEAD_S + (min(0.5e-3, 0.03 * 0.05) if precise else 0.0)
    fresh = sum(age < lead + 2e-3 for age in ages)
    assert fresh >= len(ages) / 2, sorted(ages)


@pytest.mark.realtime
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="timer slack is Linux's")
def test_the_poller_thread_sleeps_without_timer_slack():
    """Its sleeps end on their deadlines, as the drive's timerfd does, not up to 50 µs later (the default slack,
    which the thread that starts it keeps)."""
    prctl = ctypes.CDLL(None, use_errno=True).prctl
    pr_get_timerslack = 30  # the calling thread's slack, in ns, as the return value
    slack: list[int] = []

    def read() -> int:
        slack.append(prctl(pr_get_timerslack, 0, 0, 0, 0))
        return 0

    async def main() -> None:
        v = Vehicle()
        v.add(Poller(read, rate_hz=100, name="slack"), outputs=["x"])
        await v.run(rate_hz=20, max_loop_count=3)

    with asyncio.Runner(loop_factory=uvloop.new_event_loop) as runner:
        runner.run(main())
    assert prctl(pr_get_timerslack, 0, 0, 0, 0) > 1  # the test's own thread keeps its slack
    assert slack and set(slack) == {1}
