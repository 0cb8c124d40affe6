"""One Drive per run: stop before start, cancellation, complete reports on every ending, bounded parts,
two-phase shutdown."""

import asyncio
import logging
import math
import threading
import time

import pytest

from asyncdonkey import PartError, Vehicle
from asyncdonkey.core.profiler import Series
from asyncdonkey.errors import PartTimeoutError
from asyncdonkey.loop import run_blocking

from .rig import HALF, NEUTRAL, Const, Rig


class Count:
    def __init__(self) -> None:
        self.n = 0

    def run(self):
        self.n += 1
        return self.n


class Boom:
    def __init__(self, at: int) -> None:
        self.at = at
        self.n = 0

    def run(self):
        self.n += 1
        if self.n > self.at:
            raise ValueError("bad frame")


# ---------------------------------------------------------------------------------------- the stop latch


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_stop_right_after_create_task_is_honoured():
    v = Vehicle()
    c = Count()
    v.add(c, outputs=["n"])
    task = asyncio.create_task(v.run(20, duration=3600))
    v.stop()  # the README's pattern: the task has not started yet
    report = await task
    assert report.loops == 0 and c.n == 0
    assert report.stop_reason == "stop()"
    assert asyncio.get_running_loop().time() < 1.0


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_a_stop_during_one_drive_does_not_leak_into_the_next():
    v = Vehicle()
    v.add(Count(), outputs=["n"])

    class StopAt:
        def __init__(self, k):
            self.k = k
            self.n = 0

        def run(self):
            self.n += 1
            if self.n == self.k:
                v.stop()

    v.add(StopAt(3))
    first = await v.run(20, 100)
    assert first.loops == 3
    second = await v.run(20, 5)
    assert second.loops == 5 and second.stop_reason == "max_loop_count"


# ------------------------------------------------------------------------------------ reports, per drive


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_each_drive_reports_only_itself():
    v = Vehicle()
    v.add(Count(), outputs=["n"])
    v.add(Boom(at=0), on_error="continue", name="flaky")
    first = await v.run(20, 10)
    second = await v.run(20, 4)
    assert first.loops == 10 and first.part_errors == {"flaky": 10}
    assert second.loops == 4 and second.part_errors == {"flaky": 4}
    assert second.parts["Count"]["count"] == 3  # 4 ticks, the first sample ignored as in Donkeycar
    assert v.last_report is second


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_a_part_failure_still_gives_the_whole_report():
    v = Vehicle()
    v.add(Count(), outputs=["n"])
    v.add(Boom(at=7), name="camera")
    with pytest.raises(PartError) as info:
        await v.run(20, 100)
    report = info.value.report
    assert report is v.last_report
    assert report.loops == 7  # ticks 0..6 completed; tick 7 failed
    assert report.elapsed_s == pytest.approx(0.30)  # from the first tick start to the last tick end
    assert report.stop_reason == "error"
    assert "loops: 7 in 0.300 s" in v.format_report(report)


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_a_cancelled_drive_still_gives_the_whole_report():
    v = Vehicle()
    v.add(Count(), outputs=["n"])
    task = asyncio.create_task(v.run(20))
    await asyncio.sleep(1.0)
    task.cancel()
    with pytest.raises(asyncio.CancelledError):
        await task
    assert v.last_report.stop_reason == "cancelled"
    assert v.last_report.loops == 20  # ticks at 0 .. 0.95 s; the cancel at 1.0 s came first


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_a_value_preset_before_a_virtual_drive_ages_from_the_start():
    rig = Rig(asyncio.get_running_loop().time)
    v = Vehicle()
    v.mem["throttle"] = 1.0  # stamped on the monotonic clock before the drive
    ages = []
    v.add(throttle := rig.throttle(), inputs=["throttle", "throttle@age"], name="throttle")

    class Age:
        def run(self, age):
            ages.append(age)

    v.add(Age(), inputs=["throttle@age"])
    await v.run(20, 20)
    rig.close()
    assert ages[0] == 0.0 and ages[5] == pytest.approx(0.25)  # never negative, never hundreds of seconds
    assert throttle.failsafe_events == 1
    assert rig.pca.first_time(NEUTRAL, 0.01) == pytest.approx(0.25)  # a preset full throttle is not held


def test_the_profilers_run_long_max_ignores_the_last_sample_after_the_window_wraps():
    s = Series("part", window=4)
    for value in [9.0, 1.0, 2.0, 3.0, 4.0, 5.0, 100.0]:  # 9 is the ignored first, 100 the ignored last
        s.record(value)
    summary = s.summary()
    assert summary["max"] == pytest.approx(5e3)
    assert summary["min"] == pytest.approx(1e3)


# --------------------------------------------------------------------------------------- bounded parts


class Hang:
    """An async part that hangs on one tick (for ``seconds``, or forever)."""

    def __init__(self, at: int, seconds: float = math.inf) -> None:
        self.at = at
        self.seconds = seconds
        self.n = 0
        self.cancelled = 0

    async def run(self):
        self.n += 1
        if self.n == self.at:
            try:
                if self.seconds == math.inf:
                    await asyncio.Event().wait()
                await asyncio.sleep(self.seconds)
            except asyncio.CancelledError:
                self.cancelled += 1
                raise


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_timeout_cancels_an_awaited_part_and_on_error_decides():
    v = Vehicle()
    hang = Hang(at=3)
    v.add(hang, timeout=0.1, on_error="continue", name="pilot")
    report = await v.run(20, 10)
    assert hang.cancelled == 1
    assert report.loops == 10 and report.part_errors == {"pilot": 1}
    assert report.parts["pilot"]["max"] == pytest.approx(100.0)  # the hung call cost exactly its timeout

    v2 = Vehicle()
    v2.add(Hang(at=2), timeout=0.1, name="pilot")
    with pytest.raises(PartError, match=r"part 'pilot' failed on tick 1: PartTimeoutError: did not return within"):
        await v2.run(20, 10)


def test_timeout_is_refused_where_it_cannot_work():
    v = Vehicle()
    with pytest.raises(ValueError, match=r"timeout applies to awaited parts.*executor=True"):
        v.add(Count(), timeout=1.0)
    with pytest.raises(AssertionError, match="timeout must be a positive number"):
        v.add(Hang(1), timeout=-1)
    assert issubclass(PartTimeoutError, TimeoutError)


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_a_stop_ends_the_drive_even_when_an_awaited_part_never_returns(caplog):
    v = Vehicle()
    hang = Hang(at=5)
    v.add(hang, name="pilot")
    loop = asyncio.get_running_loop()
    loop.call_later(2.0, v.stop)
    report = await v.run(20, stop_grace_s=0.5)
    assert hang.cancelled == 1
    assert report.stop_reason == "stop()"
    assert loop.time() == pytest.approx(2.5)  # the stop at 2 s, the grace of 0.5 s
    assert any("did not return within 0.5 s of the stop request" in r.getMessage() for r in caplog.records)


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_cancelling_during_an_async_shutdown_propagates():
    class SlowShutdown:
        def run(self):
            return 1

        async def shutdown(self):
            await asyncio.sleep(1.0)

    v = Vehicle()
    v.add(SlowShutdown(), outputs=["x"], shutdown_timeout=5)
    with pytest.raises(TimeoutError):
        async with asyncio.timeout(0.5):  # the drive ends at 0.2 s; the timeout fires during shutdown
            await v.run(20, 5)
    assert v.last_report.loops == 5
    assert not v.on


# --------------------------------------------------------------------------------- two-phase shutdown


@pytest.mark.realtime
def test_actuators_reach_neutral_before_a_hanging_shutdown_is_waited_for(caplog):
    caplog.set_level(logging.ERROR)
    rig = Rig()

    class Camera:
        def __init__(self):
            self.shutdown_started = None

        def run(self):
            return 1

        def shutdown(self):
            self.shutdown_started = time.monotonic()
            time.sleep(30)  # a driver that never lets go

    cam = Camera()
    v = Vehicle()
    v.add(cam, outputs=["cam"], shutdown_timeout=0.3)
    v.add(Const(0.5), outputs=["throttle"])
    v.add(rig.throttle(), inputs=["throttle", "throttle@age"], name="throttle")
    started = time.monotonic()
    report = run_blocking(v.run(20, 10))
    took = time.monotonic() - started
    rig.close()
    neutral_at = rig.pca.first_time(NEUTRAL, started + 0.3)
    assert rig.pca.pulse_at(started + 0.4) == HALF
    assert neutral_at is not None and cam.shutdown_started is not None
    assert neutral_at <= cam.shutdown_started + 0.05  # the throttle first, not after the camera's timeout
    assert took < 3.0  # the 30 s shutdown was abandoned on a daemon thread
    assert report.shutdown_abandoned == ["Camera"]
    assert any("did not finish within 0.3 s; abandoned" in r.getMessage() for r in caplog.records)
    hung = [t for t in threading.enumerate() if t.name == "shutdown:Camera"]
    assert hung and all(t.daemon for t in hung)  # cannot keep the process alive


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_shutdown_timeout_reaches_a_part_that_takes_one(tmp_path):
    from asyncdonkey.parts.tub import TubWriter

    writer = TubWriter(tmp_path / "tub", inputs=["n"], types=["int"])
    seen = {}
    original = writer.shutdown

    def spy(timeout=None):
        seen["timeout"] = timeout
        return original(timeout=timeout)

    writer.shutdown = spy  # before add(): the entry, frozen there, keeps the shutdown it found
    v = Vehicle()
    v.add(Count(), outputs=["n"])
    v.add(writer, inputs=["n"], outputs=["tub/num_records"], shutdown_timeout=10)
    await v.run(20, 5)
    assert seen["timeout"] == 10
