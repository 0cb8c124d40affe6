"""Failing parts, error policies, shutdown exactly once, stop() and cancellation."""

import asyncio
import logging
import threading

import pytest

from asyncdonkey import PartError, Vehicle


class Boom:
    def __init__(self, at: int, exc: Exception | None = None) -> None:
        self.at = at
        self.n = 0
        self.exc = exc or ValueError("bad frame")

    def run(self):
        self.n += 1
        if self.n > self.at:
            raise self.exc
        return self.n


class Throttle:
    """Records what shutdown does, like an ESC that must go to neutral."""

    def __init__(self) -> None:
        self.shutdowns = 0
        self.value = 0.5

    def run(self):
        return self.value

    def shutdown(self):
        self.shutdowns += 1
        self.value = 0.0


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_failing_part_stops_car_cleanly_and_names_part_and_tick():
    throttle = Throttle()
    v = Vehicle()
    v.add(throttle, outputs=["throttle"])
    v.add(Boom(at=3), name="camera")
    with pytest.raises(PartError, match=r"part 'camera' failed on tick 3: ValueError: bad frame") as info:
        await v.run(20, 100)
    assert info.value.part == "camera" and info.value.tick == 3
    assert isinstance(info.value.__cause__, ValueError)
    assert throttle.shutdowns == 1 and throttle.value == 0.0
    assert not v.on


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_continue_policy_logs_rate_limited_and_counts(caplog):
    v = Vehicle()
    v.add(Boom(at=0), on_error="continue", name="flaky")
    v.add(Throttle(), outputs=["t"])
    with caplog.at_level(logging.ERROR, logger="asyncdonkey.loop"):
        report = await v.run(20, 100)  # 5 s of loop time, 100 failures
    assert report.loops == 100
    assert report.part_errors == {"flaky": 100}
    logged = [r for r in caplog.records if "part 'flaky' failed" in r.getMessage()]
    assert 4 <= len(logged) <= 6  # one per second, not one per tick
    assert "more errors since the last report" in logged[1].getMessage()


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_shutdown_runs_exactly_once_sync_and_async_errors_logged(caplog):
    calls = []

    class SyncShut:
        def run(self):
            return None

        def shutdown(self):
            calls.append("sync")
            raise RuntimeError("servo already off")

    class AsyncShut:
        def run(self):
            return None

        async def shutdown(self):
            await asyncio.sleep(0.1)
            calls.append("async")

    class NoShutdown:
        def run(self):
            return None

    v = Vehicle()
    v.add(SyncShut())
    v.add(AsyncShut())
    v.add(NoShutdown())
    with caplog.at_level(logging.ERROR):
        await v.run(20, 3)
    assert calls == ["sync", "async"]
    assert any("SyncShut" in r.getMessage() and "servo already off" in r.getMessage() for r in caplog.records)


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_hanging_async_shutdown_times_out_and_the_rest_still_shut_down(caplog):
    after = Throttle()

    class Hang:
        def run(self):
            return None

        async def shutdown(self):
            await asyncio.Event().wait()

    v = Vehicle()
    v.add(Hang(), shutdown_timeout=0.5)
    v.add(after, outputs=["t"])
    with caplog.at_level(logging.ERROR):
        await v.run(20, 2)
    assert after.shutdowns == 1
    assert any("did not finish within 0.5 s" in r.getMessage() for r in caplog.records)


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_stop_from_a_part_finishes_the_tick_then_shuts_down():
    v = Vehicle()
    order = []

    class Stopper:
        def run(self):
            order.append("stopper")
            v.stop()

    class After:
        def run(self):
            order.append("after")

    t = Throttle()
    v.add(Stopper())
    v.add(After())
    v.add(t, outputs=["t"])
    report = await v.run(20, 100)
    assert order == ["stopper", "after"]
    assert report.loops == 1 and report.stop_reason == "stop()"
    assert t.shutdowns == 1


@pytest.mark.realtime
@pytest.mark.asyncio
async def test_stop_from_another_thread_wakes_a_slow_loop_at_once():
    v = Vehicle()
    t = Throttle()
    v.add(t, outputs=["t"])
    loop = asyncio.get_running_loop()
    timer = threading.Timer(0.05, v.stop)
    start = loop.time()
    timer.start()
    report = await v.run(rate_hz=0.2, max_loop_count=None)  # one tick every 5 s
    assert loop.time() - start < 2.0
    assert report.loops == 1 and t.shutdowns == 1


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_cancelling_the_run_task_shuts_down_cleanly():
    t = Throttle()
    v = Vehicle()
    v.add(t, outputs=["t"])
    task = asyncio.create_task(v.run(20))
    await asyncio.sleep(1.0)
    task.cancel()
    with pytest.raises(asyncio.CancelledError):
        await task
    assert t.shutdowns == 1
    assert not v.on


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_failing_background_update_stops_the_car():
    class Sensor:
        async def update(self):
            await asyncio.sleep(0.3)
            raise OSError(5, "Input/output error")

        def run(self):
            return 1

    t = Throttle()
    v = Vehicle()
    v.add(Sensor(), outputs=["s"])
    v.add(t, outputs=["t"])
    with pytest.raises(PartError, match=r"part 'Sensor' failed in its background task: OSError"):
        await v.run(20, 1000)
    assert t.shutdowns == 1
    assert asyncio.get_running_loop().time() == pytest.approx(0.3)


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_run_refuses_bad_arguments_and_reentry():
    v = Vehicle()
    v.add(Throttle(), outputs=["t"])
    with pytest.raises(ValueError, match="rate_hz must be a positive number"):
        await v.run(0)
    task = asyncio.create_task(v.run(20, 10))
    await asyncio.sleep(0)
    with pytest.raises(RuntimeError, match="already running"):
        await v.run(20, 1)
    await task


@pytest.mark.realtime
def test_start_is_blocking_on_uvloop_and_returns_count_and_seconds():
    import uvloop

    loops_seen = []

    class Which:
        def run(self):
            loops_seen.append(type(asyncio.get_running_loop()))

    v = Vehicle()
    v.add(Which())
    count, seconds = v.start(rate_hz=100, max_loop_count=5)
    assert count == 5
    assert 0.035 <= seconds < 2.0  # five ticks at 100 Hz: at least four periods
    assert loops_seen == [uvloop.Loop] * 5
