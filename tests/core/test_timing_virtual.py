"""Drive-loop timing on the virtual clock: exact, deterministic and fast."""

import asyncio
import logging
import time

import pytest

from asyncdonkey import Vehicle


class Counter:
    def __init__(self) -> None:
        self.n = 0

    def run(self, *_):
        self.n += 1
        return self.n


class TickStamps:
    """Records the loop time at which it runs (it is the first part, so: the tick start)."""

    def __init__(self) -> None:
        self.times: list[float] = []

    def run(self):
        self.times.append(asyncio.get_running_loop().time())


class Await:
    def __init__(self, seconds: float) -> None:
        self.seconds = seconds

    async def run(self):
        await asyncio.sleep(self.seconds)


@pytest.mark.realtime
@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_ten_thousand_ticks_ten_parts_under_a_second():
    v = Vehicle()
    stamps = TickStamps()
    v.add(stamps)
    for i in range(10):
        v.add(Counter(), inputs=[f"c{i - 1}"] if i else [], outputs=[f"c{i}"])
    real = time.perf_counter()
    report = await v.run(rate_hz=20, max_loop_count=10_000)
    real = time.perf_counter() - real
    assert report.loops == 10_000
    assert real < 1.0
    assert stamps.times[-1] - stamps.times[0] == 499.95
    assert report.achieved_hz == pytest.approx(20.0, abs=1e-9)
    assert report.overruns == 0 and report.skipped_deadlines == 0
    assert v.mem["c9"] == 10_000


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_89ms_part_at_20hz_runs_about_11_2_hz_every_tick_overrun():
    v = Vehicle()
    v.add(Await(0.089))
    report = await v.run(rate_hz=20, max_loop_count=200)
    assert report.achieved_hz == pytest.approx(1 / 0.089, rel=1e-6)  # 11.236 Hz
    assert report.overruns == 200
    assert report.skipped_deadlines > 0
    assert report.overrun_ms["min"] == pytest.approx(39.0, abs=1e-6)
    # never a burst: ticks are 89 ms apart, each starting at once or on a deadline, lateness at most one period
    assert report.lateness_ms["max"] <= 50.0 + 1e-6


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_40ms_part_holds_exactly_50ms_between_ticks():
    v = Vehicle()
    stamps = TickStamps()
    v.add(stamps)
    v.add(Await(0.040))
    report = await v.run(rate_hz=20, max_loop_count=100)
    gaps = [b - a for a, b in zip(stamps.times, stamps.times[1:], strict=False)]
    assert all(g == pytest.approx(0.05, abs=1e-9) for g in gaps)
    assert report.overruns == 0
    assert report.lateness_ms["max"] == pytest.approx(0.0, abs=1e-6)
    assert report.parts["Await"]["avg"] == pytest.approx(40.0, abs=1e-6)


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_one_long_stall_skips_deadlines_instead_of_bursting():
    class StallOnce:
        def __init__(self) -> None:
            self.n = 0

        async def run(self):
            self.n += 1
            if self.n == 5:
                await asyncio.sleep(0.520)  # more than ten periods at 20 Hz

    v = Vehicle()
    stamps = TickStamps()
    v.add(stamps)
    v.add(StallOnce())
    report = await v.run(rate_hz=20, max_loop_count=10)
    t = stamps.times
    # ticks 0-4 on schedule, tick 4 ends at 0.72; deadlines 0.25 .. 0.70 are skipped (0.25-0.65: 9)
    assert t[:5] == pytest.approx([0.0, 0.05, 0.10, 0.15, 0.20])
    assert t[5] == pytest.approx(0.72)  # at once, lateness 20 ms, no burst
    assert t[6] == pytest.approx(0.75)  # back on the grid
    assert report.skipped_deadlines == 9
    assert report.overruns == 1


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_duration_stops_the_drive():
    v = Vehicle()
    v.add(Counter(), outputs=["n"])
    report = await v.run(rate_hz=10, duration=3.0)
    assert report.loops == 30
    assert report.stop_reason == "duration"


async def _drive_once() -> list[float]:
    v = Vehicle()
    stamps = TickStamps()
    v.add(stamps)

    class Jittery:
        def __init__(self) -> None:
            self.k = 0

        async def run(self):
            self.k += 1
            await asyncio.sleep((self.k * 7919 % 13) / 200)  # 0-60 ms, a fixed pattern

    v.add(Jittery())
    v.add(Await(0.001), executor=False)
    await v.run(rate_hz=20, max_loop_count=300)
    return stamps.times


def test_two_identical_runs_give_identical_timings():
    from asyncdonkey.testing import VirtualClockLoop

    runs = []
    for _ in range(2):
        with asyncio.Runner(loop_factory=VirtualClockLoop) as runner:
            runs.append(runner.run(_drive_once()))
    assert runs[0] == runs[1]
    assert len(runs[0]) == 300


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_verbose_jitter_warning_is_rate_limited(caplog):
    v = Vehicle()
    v.add(Await(0.0015))  # every tick of a 1 kHz loop overruns by 0.5 ms
    with caplog.at_level(logging.INFO, logger="asyncdonkey.loop"):
        report = await v.run(rate_hz=1000, max_loop_count=2000, verbose=True, report_every=500)
    warnings = [r for r in caplog.records if "jitter violation" in r.getMessage()]
    assert report.overruns == 2000
    assert 2 <= len(warnings) <= 4  # about 3 s of loop time, one warning per second
    assert "0 ms overrun" in warnings[0].getMessage() or "1 ms overrun" in warnings[0].getMessage()
    assert "more since the last report" in warnings[1].getMessage()
    tables = [r for r in caplog.records if "Part Profile Summary" in r.getMessage()]
    assert len(tables) >= 4  # every 500 loops, plus the final report


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_runtime_clock_is_the_virtual_loop():
    from asyncdonkey import get_clock

    clock = get_clock()
    assert clock.is_virtual
    await asyncio.sleep(12.5)
    assert clock.now() == 12.5


class _LateStart:
    """A background task that takes ``late_s`` of loop time as soon as it runs (right after the first tick), as a
    loaded machine does: the next tick comes late and the deadlines before it are skipped."""

    def __init__(self, late_s: float) -> None:
        self.late_s = late_s

    async def update(self) -> None:
        asyncio.get_running_loop().jump(self.late_s)  # type: ignore[attr-defined]
        await asyncio.sleep(3600)

    def run_threaded(self) -> None:
        return None


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_the_summary_of_a_drive_with_skipped_deadlines_adds_up_and_never_claims_more_than_the_asked_rate():
    """Seen under load: 'loops: 87 in 4.242 s', 'achieved: 20.280 Hz of 20 Hz', 'skipped deadlines: 13' for a
    5 s drive (its first tick came late; counted from that tick's start, the rate looked higher than asked). The
    drive's time counts from its first deadline, so the loops and the skipped deadlines add up to the deadlines in
    it, and the achieved rate is never above the asked one."""
    v = Vehicle()
    v.add(_LateStart(0.66), threaded=True)
    v.add(Await(0.0))
    report = await v.run(rate_hz=20, duration=5.0)
    # tick 0 on time; the tick at 0.66 s serves deadline 1 late and deadlines 2..13 are skipped
    assert report.skipped_deadlines == 12 and report.loops == 88
    assert report.loops + report.skipped_deadlines == 100  # every deadline of the 5 s is a tick or a skip
    assert report.elapsed_s == pytest.approx(4.95, abs=1e-9)  # first deadline to the last tick's end
    assert report.achieved_hz <= 20.0
    assert report.achieved_hz == pytest.approx(87 / 4.95)  # 17.58 Hz: 88 ticks where 100 were asked for
    summary = v.format_report(report)
    assert "88 in 4.950 s" in summary and "17.576 Hz of 20 Hz" in summary
