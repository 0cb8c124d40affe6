"""Periodic background loops: Schedule deadlines (no drift, skip-and-count), one waiter for the loop's life."""

from __future__ import annotations

import asyncio
import math
import time

import pytest
import uvloop

from asyncdonkey.clock import get_clock
from asyncdonkey.parts.web.controller import WebController
from asyncdonkey.periodic import Periodic


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_rounds_start_on_the_schedule_and_overruns_skip_without_bursting():
    loop = asyncio.get_running_loop()
    work_s = [0.0, 0.05, 0.13, 0.0, 0.35, 0.0, 0.0]  # 100 ms period: a late round, then one 3.5 periods long
    starts: list[float] = []
    skips: list[int] = []
    t0 = loop.time()
    with Periodic(0.1) as every:
        for w in work_s:
            starts.append(round(loop.time() - t0, 9))
            await asyncio.sleep(w)
            skips.append(await every.next())
    # 0.13 s of work from 0.2 ends at 0.33: the round due at 0.3 starts at once (late, not skipped); 0.35 s
    # from 0.4 ends at 0.75: deadlines 0.5 and 0.6 are skipped, the one due at 0.7 starts at once
    assert starts == [0.0, 0.1, 0.2, 0.33, 0.4, 0.75, 0.8]
    assert skips == [0, 0, 0, 0, 2, 0, 0] and every.schedule.skipped == 2
    assert every.waiter.closed


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_a_thousand_rounds_do_not_drift():
    loop = asyncio.get_running_loop()
    t0 = loop.time()
    with Periodic(0.3) as every:
        for _ in range(1000):
            await asyncio.sleep(0.01)  # the work: without a schedule each round would be 0.31 s long
            await every.next()
    assert loop.time() - t0 == pytest.approx(300.0, abs=1e-9)


@pytest.mark.realtime
def test_one_timer_for_the_whole_loop_never_early_and_released_at_the_end():
    async def main():
        now = get_clock().now
        late: list[float] = []
        with Periodic(0.004) as every:
            assert every.waiter.mode == "timerfd"
            fd = every.waiter._tfd.fd
            for _ in range(20):
                await every.next()
                late.append(now() - every.schedule.deadline)
                assert every.waiter._tfd is not None and every.waiter._tfd.fd == fd  # the same OS timer
        return late, every

    with asyncio.Runner(loop_factory=uvloop.new_event_loop) as runner:
        late, every = runner.run(main())
    assert min(late) >= 0.0  # never early
    assert every.waiter.closed and every.waiter._tfd is None
    assert every.schedule.k == 20 + every.schedule.skipped


@pytest.mark.realtime
def test_a_round_longer_than_its_period_still_lets_other_tasks_run():
    async def main():
        others = 0

        async def other():
            nonlocal others
            while True:
                others += 1
                await asyncio.sleep(0)

        task = asyncio.create_task(other())
        with Periodic(0.002) as every:
            for _ in range(5):
                time.sleep(0.005)  # blocking work, longer than two periods: every deadline has passed
                before = others
                await every.next()
                assert others > before
        task.cancel()
        return every

    with asyncio.Runner() as runner:
        every = runner.run(main())
    assert every.schedule.skipped >= 5


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_a_period_must_be_positive_and_finite():
    for bad in (0, -1.0, math.inf, math.nan):
        with pytest.raises(ValueError, match="period_s"):
            Periodic(bad)


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_web_health_is_pushed_every_period_with_the_tick_rate():
    loop = asyncio.get_running_loop()
    made: list[float] = []

    def status() -> dict[str, float]:
        made.append(round(loop.time() - t0, 9))
        return {}

    web = WebController(host="127.0.0.1", token=None, announce=None, status=status, health_every_s=0.25)
    web._clock = get_clock(loop)  # what update() sets before starting the health loop
    t0 = loop.time()
    health = asyncio.create_task(web._health_loop())
    for _ in range(40):  # 20 Hz ticks for 2 s
        web.run()
        await asyncio.sleep(0.05)
    health.cancel()
    await asyncio.gather(health, return_exceptions=True)
    assert made == [0.25 * k for k in range(1, 9)]
    assert web.last_health is not None and web.last_health["hz"] == 20.0
