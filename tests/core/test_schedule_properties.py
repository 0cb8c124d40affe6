"""Properties of the deadline schedule (``clock.Schedule``) for arbitrary work durations: in the drive loop on the
virtual clock, on its own, and in the poller (hypothesis)."""

import asyncio
import math

import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from asyncdonkey import Poller, Vehicle
from asyncdonkey.clock import Schedule
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
    assert len(stamps) in (6000, 6001) and poller.reads == len(stamps) and poller.skipped == 0
    assert stamps == [t0 + k / 60 for k in range(len(stamps))]  # exact: the same float the schedule computed
    assert poller.sample is not None and poller.sample.timestamp == stamps[-1]
