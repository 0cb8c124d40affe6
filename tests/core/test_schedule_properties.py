"""Properties of the deadline scheduler for arbitrary part durations (virtual clock, hypothesis)."""

import asyncio

from hypothesis import example, given, settings
from hypothesis import strategies as st

from asyncdonkey import Vehicle
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
