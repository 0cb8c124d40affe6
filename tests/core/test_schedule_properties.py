"""Properties of the deadline schedule (``clock.Schedule``) for arbitrary work durations: in the drive loop on the
virtual clock, on its own, and in the poller (hypothesis)."""

import asyncio
import math
from collections.abc import Callable

import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from asyncdonkey import Poller, Sample, Vehicle
from asyncdonkey.clock import Schedule, TickGrid
from asyncdonkey.core.drive import START_MARGIN_S
from asyncdonkey.poller import POLL_LEAD_S, STOP_CHECK_S
from asyncdonkey.testing import VirtualClockLoop


async def _drive(durations_ms: list[int], rate_hz: int):
    starts: list[float] = []
    ends: list[float] = []
    it = iter(durations_ms)

    class Work:
        async def run(self):
            loop = asyncio.get_running_loop()
            starts.append(loop.time())
            await asyncio.sleep(next(it) / 1000)
            ends.append(loop.time())

    v = Vehicle()
    v.add(Work())
    report = await v.run(rate_hz, len(durations_ms))
    return starts, ends, report


def reference_schedule(durations_ms: list[int], period_ms: int) -> tuple[list[int], int]:
    """The documented rule in integer milliseconds: tick k is due at k * period; after an overrun the next tick
    starts at once; when more than a period behind, jump to the latest deadline already passed."""
    starts, skipped, k, end = [], 0, 0, 0
    for d in durations_ms:
        start = max(end, k * period_ms)
        starts.append(start)
        end = start + d
        k += 1
        if end - k * period_ms > period_ms:
            behind = end // period_ms
            skipped += behind - k
            k = behind
    return starts, skipped


@settings(max_examples=60, deadline=None)
@given(
    durations=st.lists(st.integers(min_value=0, max_value=400), min_size=2, max_size=60),
    rate_hz=st.sampled_from([5, 10, 20, 50, 100]),
)
@example(durations=[297, 400, 400, 152, 291], rate_hz=50)  # ends a few ulps before a deadline: 1.54 - 2e-16 s
def test_schedule_matches_the_documented_rule(durations, rate_hz):
    with asyncio.Runner(loop_factory=VirtualClockLoop) as runner:
        starts, ends, report = runner.run(_drive(durations, rate_hz))
    period_ms = 1000 // rate_hz
    expected_starts, expected_skipped = reference_schedule(durations, period_ms)
    assert [round(s * 1000, 6) for s in starts] == expected_starts
    assert report.skipped_deadlines == expected_skipped
    assert report.overruns == sum(1 for d in durations if d > period_ms)
    for i in range(1, len(starts)):
        assert starts[i] >= ends[i - 1] - 1e-9  # ticks never overlap
    assert report.lateness_ms["max"] <= period_ms + 1e-6  # never more than a period late: no backlog, no burst


# ------------------------------------------------------------------------------ the Schedule object itself
@settings(max_examples=200, deadline=None)
@given(
    durations=st.lists(st.integers(min_value=0, max_value=400), min_size=1, max_size=80),
    rate_hz=st.sampled_from([5, 10, 20, 50, 100]),
    t0=st.sampled_from([0.0, 0.4, 1234.5678, 86_400.123456789]),
)
def test_schedule_object_follows_the_documented_rule(durations, rate_hz, t0):
    """Schedule.advance, fed the same work, gives the reference rule's start times and skip count, from any t0
    (float noise of a few ulps in t0 + k / rate is neither an overrun nor "behind")."""
    period_ms = 1000 // rate_hz
    expected_starts, expected_skipped = reference_schedule(durations, period_ms)
    sched = Schedule(rate_hz, t0)
    end = t0
    starts = []
    assert sched.deadline == t0
    for d in durations:
        start = max(end, sched.deadline)
        starts.append(start)
        end = start + d / 1000
        sched.advance(end)
        assert sched.deadline == t0 + sched.k / rate_hz  # the same float, computed from t0: no drift
    assert [round((s - t0) * 1000, 3) for s in starts] == expected_starts
    assert sched.skipped == expected_skipped


def test_schedule_skips_only_when_more_than_a_period_behind_and_never_bursts():
    s = Schedule(10, 0.0)  # 100 ms period
    assert s.advance(0.15) == 0 and s.deadline == pytest.approx(0.1)  # late by 50 ms: run at once, no skip
    assert s.advance(0.3 - 1e-15) == 0 and s.k == 2  # a few ulps short of "a period behind" is not behind
    assert s.advance(0.55) == 2  # deadlines 0.3 and 0.4 missed: resume at 0.5, already passed
    assert s.k == 5 and s.deadline == pytest.approx(0.5) and s.skipped == 2


def test_schedule_deadline_is_computed_from_t0_not_summed():
    """100,000 on-time ticks at 1 kHz: every deadline is exactly t0 + k / rate (adding periods would drift)."""
    t0 = 86_400.123456789
    s = Schedule(1000, t0)
    summed = t0
    for k in range(1, 100_001):
        assert s.advance(s.deadline) == 0  # each tick ends the moment it is due
        summed += s.period
        assert s.k == k and s.deadline == t0 + k / 1000
    assert s.skipped == 0 and summed != s.deadline  # the sum has drifted; the schedule has not


def test_schedule_rejects_a_rate_that_is_not_positive_and_finite():
    for bad in (0, -1.0, math.inf, math.nan):
        with pytest.raises(ValueError, match="rate_hz"):
            Schedule(bad, 0.0)


# ------------------------------------------------------------------------------ the poller on the virtual clock
@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_poller_samples_land_exactly_on_their_deadlines_on_the_virtual_clock():
    loop = asyncio.get_running_loop()
    stamps = []

    def read():  # runs in the poller's executor thread while virtual time stands still
        stamps.append(loop.time())
        return len(stamps)

    poller = Poller(read, rate_hz=60, name="imu")
    v = Vehicle()
    v.add(poller, outputs=["imu"])
    await v.run(rate_hz=20, max_loop_count=2001)  # 100 s
    t0 = stamps[0]
    # The poller's last deadline can fall on the drive's last tick (both at 100 s): that read may still be in its
    # thread when the drive ends and cancels the poller, and is then never published.
    assert len(stamps) in (6000, 6001) and poller.reads in (len(stamps) - 1, len(stamps)) and poller.skipped == 0
    assert stamps == [t0 + k / 60 for k in range(len(stamps))]  # exact: the same float the schedule computed
    assert poller.sample is not None and poller.sample.timestamp == stamps[poller.reads - 1]


# ------------------------------------------------------------------ the poller thread's loop on modelled time
class ModelTime:
    """Time that moves only when the poller thread sleeps or reads: a model of the thread's clock and sleep.

    ``early_s``: a sleep longer than twice this wakes this much too early (as a sleep that is not an absolute
    wait on the same clock might), to check that the poller looks at the clock again before reading.
    """

    def __init__(self, t0: float, early_s: float = 0.0) -> None:
        self.t = t0
        self.early_s = early_s
        self.sleeps: list[float] = []
        self.at: Callable[[], None] | None = None  # called once time passes stop_at
        self.stop_at = math.inf

    def now(self) -> float:
        return self.t

    def sleep(self, seconds: float) -> None:
        assert seconds > 0
        self.sleeps.append(seconds)
        self.t += seconds - self.early_s if seconds > 2 * self.early_s else seconds
        if self.t >= self.stop_at and self.at is not None:
            self.at()
            self.at = None


def poll_on_model(poller: Poller, time_model: ModelTime, recheck: bool, grid: TickGrid | None = None) -> None:
    poller._running = True  # what update() does before starting the thread
    poller._poll_blocking(time_model.now, time_model.sleep, recheck, grid)


@settings(max_examples=100, deadline=None)
@given(
    durations=st.lists(st.integers(min_value=0, max_value=400), min_size=1, max_size=60),
    rate_hz=st.sampled_from([5, 10, 20, 50, 100]),
    t0=st.sampled_from([0.0, 0.4, 1234.5678, 86_400.123456789]),
    sleep_kind=st.sampled_from(["exact", "wakes-early"]),
)
def test_poller_thread_follows_the_documented_rule(durations, rate_hz, t0, sleep_kind):
    """The thread's loop (Schedule's on-time case inline, overruns handed to Schedule) reads at the reference
    rule's times and skips what it skips, whether the sleep is trusted (exact) or checked (wakes early)."""
    clock = ModelTime(t0, early_s=0.0 if sleep_kind == "exact" else 1e-3)
    starts: list[float] = []
    work = iter(durations)

    def read() -> int:
        starts.append(clock.t)
        d = next(work, None)
        clock.t += (d or 0) / 1000
        if len(starts) == len(durations):
            poller.shutdown()
        return len(starts)

    poller = Poller(read, rate_hz)
    poll_on_model(poller, clock, recheck=sleep_kind == "wakes-early")
    expected_starts, expected_skipped = reference_schedule(durations, 1000 // rate_hz)
    assert [round((s - t0) * 1000, 3) for s in starts] == expected_starts  # never early, never later
    assert poller.skipped == expected_skipped
    assert poller.reads == len(durations) and poller.sample is not None and poller.sample.value == len(durations)


def test_poller_thread_publishes_what_publish_would_and_counts_errors():
    clock = ModelTime(50.0)
    calls = 0
    pushed: list[tuple[int, float]] = []

    def flaky() -> int:
        nonlocal calls
        calls += 1
        if calls % 3 == 0:
            raise OSError(121, "Remote I/O error")
        if calls == 11:
            poller.shutdown()
        return calls

    poller = Poller(flaky, rate_hz=10, name="imu")
    samples: list[Sample[int]] = []
    poller.latest.subscribe(lambda v, t: (pushed.append((v, t)), samples.append(poller.latest.sample)))
    poll_on_model(poller, clock, recheck=False)
    assert poller.errors == 3 and isinstance(poller.last_error, OSError) and poller.reads == 8
    assert [s.value for s in samples] == [1, 2, 4, 5, 7, 8, 10, 11]
    assert [s.seq for s in samples] == list(range(1, 9))
    assert pushed == [(s.value, s.timestamp) for s in samples]
    assert [s.timestamp for s in samples] == pytest.approx([50.0 + (v - 1) / 10 for v in (1, 2, 4, 5, 7, 8, 10, 11)])
    # started again (a second drive), it goes on numbering its samples
    calls = 0
    poll_on_model(poller, clock, recheck=False)
    assert [s.seq for s in samples[8:]] == list(range(9, 17)) and poller.reads == 16 and poller.errors == 6


def test_a_slow_poller_thread_notices_shutdown_within_stop_check():
    clock = ModelTime(0.0)
    poller = Poller(lambda: 1, rate_hz=0.5)  # a read every two seconds
    clock.stop_at, clock.at = 3.05, poller.shutdown
    poll_on_model(poller, clock, recheck=False)
    assert poller.reads == 2  # at 0 s and 2 s; none after the shutdown at 3.05 s
    assert max(clock.sleeps) <= STOP_CHECK_S
    assert 3.05 <= clock.t <= 3.05 + STOP_CHECK_S


@pytest.mark.parametrize("spin_s", [0.0, 0.5e-3])
def test_the_poller_thread_reads_on_the_drives_grid_ahead_of_the_ticks_by_its_lead(spin_s):
    """In a drive the first read is on the drive's tick grid, just before its first tick (still to come), and
    the others follow at the poller's rate: every third of a 60 Hz poller's just before a 20 Hz tick. Ahead by
    POLL_LEAD_S, and by the drive's spin too when it has one (precise mode)."""
    clock = ModelTime(100.0)
    grid = TickGrid(origin=100.0 + START_MARGIN_S, period=0.05, spin_s=spin_s)
    starts: list[float] = []

    def read() -> int:
        starts.append(clock.t)
        if len(starts) == 30:
            poller.shutdown()
        return len(starts)

    poller = Poller(read, rate_hz=60)
    poll_on_model(poller, clock, recheck=False, grid=grid)
    first = grid.origin - POLL_LEAD_S - spin_s
    assert starts == pytest.approx([first + j / 60 for j in range(30)], abs=1e-9)
    assert starts[::3] == pytest.approx([first + k * grid.period for k in range(10)], abs=1e-9)
    assert poller.skipped == 0
