"""Deadline waits on real loops: timerfd and the loop-timer fallback, wake-ups, precise mode, no fd leaks.

These run in real time on asyncio's loop and on uvloop, so they assert only what a noisy 2-core machine can
guarantee: a wait never returns before its deadline, it is late by less than a generous bound, ``wake`` cuts it
short promptly, and nothing is left open afterwards. Figures (lateness percentiles, CPU) live in
``benchmarks/loop.py``.
"""

from __future__ import annotations

import asyncio
import gc
import math
import os
import statistics
import threading
import time
from array import array
from collections.abc import Awaitable, Callable

import pytest
import uvloop

from asyncdonkey import Poller, Vehicle, clock
from asyncdonkey.clock import Clock, DeadlineWaiter, _precise_wait, _timerfd, get_clock
from asyncdonkey.clock.virtual_loop import VirtualClockLoop

from ..waiting import wait_until

LOOPS = [
    pytest.param(asyncio.SelectorEventLoop, id="asyncio"),
    pytest.param(uvloop.new_event_loop, id="uvloop"),
]
GENEROUS_S = 0.5  # no single wait on a busy CI machine should be later than this


def run_on(loop_factory: Callable[[], asyncio.AbstractEventLoop], coro: Awaitable[object]) -> object:
    with asyncio.Runner(loop_factory=loop_factory) as runner:
        return runner.run(coro)  # type: ignore[arg-type]


def open_fds() -> set[int]:
    return {int(fd) for fd in os.listdir("/proc/self/fd")}


@pytest.fixture(params=["timerfd", "loop-timer"])
def wait_mode(request, monkeypatch) -> str:
    """Every real-time test runs on timerfd (where the platform has it) and on the forced fallback."""
    if request.param == "timerfd":
        if not _timerfd.AVAILABLE:  # pragma: no cover - CI is Linux
            pytest.fail("timerfd is expected on Linux")
    else:
        monkeypatch.setattr(clock, "USE_TIMERFD", False)
    return request.param


async def _lateness_of_waits(waiter: DeadlineWaiter, n: int, spacing_s: float) -> list[float]:
    """Wait for n deadlines ``spacing_s`` apart (odd offsets, so none lands on a millisecond); lateness each."""
    now = time.monotonic
    t0 = now()
    late = []
    for k in range(1, n + 1):
        deadline = t0 + k * spacing_s + 0.000317 * (k % 3)
        assert await waiter.wait_until(deadline) is True
        late.append(now() - deadline)
    return late


@pytest.mark.realtime
@pytest.mark.parametrize("loop_factory", LOOPS)
def test_waits_never_return_early_and_are_not_far_late(loop_factory, wait_mode):
    async def main():
        with DeadlineWaiter() as waiter:
            assert waiter.mode == wait_mode
            late = await _lateness_of_waits(waiter, 30, 0.0043)
            assert 0 < waiter.waits <= 30  # a deadline that had passed on a late wake-up is not slept for
        assert min(late) >= 0.0  # never early
        assert max(late) < GENEROUS_S
        # a typical wait is on time to well within the fallback's documented couple of milliseconds
        assert statistics.median(late) < 0.02

    run_on(loop_factory, main())


@pytest.mark.realtime
@pytest.mark.parametrize("loop_factory", LOOPS)
def test_a_deadline_already_passed_returns_at_once(loop_factory, wait_mode):
    async def main():
        with DeadlineWaiter() as waiter:
            t = time.monotonic()
            assert await waiter.wait_until(t - 1.0) is True
            assert await waiter.wait_until(time.monotonic()) is True
            assert waiter.waits == 0  # nothing slept

    run_on(loop_factory, main())


@pytest.mark.realtime
@pytest.mark.parametrize("loop_factory", LOOPS)
def test_wake_cuts_a_long_wait_short_and_the_waiter_goes_on(loop_factory, wait_mode):
    async def main():
        loop = asyncio.get_running_loop()
        with DeadlineWaiter() as waiter:
            wake = loop.create_future()
            loop.call_later(0.02, wake.set_result, None)
            t = time.monotonic()
            assert await waiter.wait_until(t + 30.0, wake) is False
            assert time.monotonic() - t < GENEROUS_S
            # a wake future already done returns at once; the waiter is still good for the next deadline
            assert await waiter.wait_until(time.monotonic() + 30.0, wake) is False
            late = await _lateness_of_waits(waiter, 5, 0.003)
            assert min(late) >= 0.0

    run_on(loop_factory, main())


@pytest.mark.realtime
@pytest.mark.parametrize("loop_factory", LOOPS)
def test_wake_from_another_thread_cuts_the_wait_short(loop_factory, wait_mode):
    async def main():
        loop = asyncio.get_running_loop()
        wake = loop.create_future()
        timer = threading.Timer(0.02, lambda: loop.call_soon_threadsafe(wake.set_result, None))
        with DeadlineWaiter() as waiter:
            t = time.monotonic()
            timer.start()
            assert await waiter.wait_until(t + 30.0, wake) is False
            assert time.monotonic() - t < GENEROUS_S

    run_on(loop_factory, main())


@pytest.mark.realtime
@pytest.mark.parametrize("loop_factory", LOOPS)
def test_same_wake_future_across_many_waits_then_completed(loop_factory, wait_mode):
    """The drive loop passes one wake future for every tick; completing it ends the current wait only."""

    async def main():
        loop = asyncio.get_running_loop()
        wake = loop.create_future()
        with DeadlineWaiter() as waiter:
            t0 = time.monotonic()
            for k in range(1, 11):
                assert await waiter.wait_until(t0 + k * 0.002, wake) is True
            loop.call_later(0.01, wake.set_result, None)
            assert await waiter.wait_until(time.monotonic() + 30.0, wake) is False

    run_on(loop_factory, main())


@pytest.mark.realtime
@pytest.mark.parametrize("loop_factory", LOOPS)
def test_a_cancelled_wait_raises_and_leaves_the_waiter_usable(loop_factory, wait_mode):
    async def main():
        with DeadlineWaiter() as waiter:
            task = asyncio.create_task(waiter.wait_until(time.monotonic() + 30.0))
            await asyncio.sleep(0.01)
            task.cancel()
            with pytest.raises(asyncio.CancelledError):
                await task
            late = await _lateness_of_waits(waiter, 5, 0.003)
            assert min(late) >= 0.0

    run_on(loop_factory, main())


@pytest.mark.realtime
@pytest.mark.parametrize("loop_factory", LOOPS)
def test_one_wait_at_a_time_per_waiter(loop_factory):
    async def main():
        with DeadlineWaiter() as waiter:
            first = asyncio.create_task(waiter.wait_until(time.monotonic() + 0.05))
            await asyncio.sleep(0)
            with pytest.raises(RuntimeError, match="already waiting"):
                await waiter.wait_until(time.monotonic() + 0.05)
            assert await first is True

    run_on(loop_factory, main())


@pytest.mark.realtime
@pytest.mark.parametrize("loop_factory", LOOPS)
def test_closing_during_a_wait_finishes_it_on_the_loop_timers(loop_factory):
    async def main():
        waiter = DeadlineWaiter()
        assert waiter.mode == "timerfd"
        deadline = time.monotonic() + 0.03
        task = asyncio.create_task(waiter.wait_until(deadline))
        await asyncio.sleep(0.005)
        waiter.close()
        assert await task is True
        assert time.monotonic() >= deadline
        assert waiter.mode == "loop-timer" and waiter.closed

    run_on(loop_factory, main())


@pytest.mark.realtime
def test_timerfd_that_cannot_be_created_falls_back_to_loop_timers(monkeypatch):
    def no_timerfd() -> _timerfd.Timerfd:
        raise OSError(24, "Too many open files")

    monkeypatch.setattr(_timerfd, "Timerfd", no_timerfd)

    async def main():
        with DeadlineWaiter() as waiter:
            assert waiter.mode == "loop-timer"
            late = await _lateness_of_waits(waiter, 5, 0.003)
            assert min(late) >= 0.0

    run_on(uvloop.new_event_loop, main())


# ---------------------------------------------------------------------------------------------- precise mode
@pytest.mark.realtime
@pytest.mark.parametrize("sleeps", [1, 2])
@pytest.mark.parametrize("loop_factory", LOOPS)
def test_precise_mode_never_early_and_learns_its_spin_window(loop_factory, wait_mode, sleeps, monkeypatch):
    monkeypatch.setattr(_precise_wait, "_learned", {})  # its own samples only, none taken over
    # one sleep or two throughout, whatever this machine's wake-ups do: a switch swaps the window's samples
    # (tested on its own below)
    monkeypatch.setattr(_precise_wait, "_TWO_STAGE_ABOVE_S", math.inf)
    monkeypatch.setattr(_precise_wait, "_ONE_STAGE_BELOW_S", -math.inf)
    spacing = 0.004
    # how many samples the waiter had at each refresh of its window: on a loaded machine a wait that finds its
    # deadline (or its spin window) already passed learns nothing, so the refreshes need not fall at waits 65
    # and 97
    refreshed_with: list[int] = []
    refresh = DeadlineWaiter._refresh_window

    def recorded_refresh(self: DeadlineWaiter) -> None:
        refreshed_with.append(len(self._late))
        refresh(self)

    monkeypatch.setattr(DeadlineWaiter, "_refresh_window", recorded_refresh)

    async def main():
        with DeadlineWaiter(precise=True) as waiter:
            waiter._two_stage = sleeps == 2
            start_window = waiter.spin_window_s
            late = await _lateness_of_waits(waiter, 100, spacing)
            assert min(late) >= 0.0
            assert max(late) < GENEROUS_S
            # the window now comes from what was observed: after the warm-up, every few waits, a high quantile of
            # the early timer's lateness less the tolerance precise mode accepts, within the floor and the
            # ceiling. On a quiet machine the last refresh was due at wait 96 and applied when wait 97 was armed.
            assert refreshed_with and refreshed_with[-1] >= _precise_wait._LATE_WARMUP
            samples = sorted(waiter._late[: refreshed_with[-1]])
            q = samples[min(len(samples) - 1, int(_precise_wait._LATE_QUANTILE * len(samples)))]
            expected = min(
                max(q - clock.PRECISE_TOLERANCE_S, _precise_wait._WINDOW_FLOOR_S), _precise_wait._WINDOW_CEIL_S
            )
            assert waiter.spin_window_s == pytest.approx(expected)
            assert waiter.spin_window_s != start_window or expected == start_window
            assert waiter.sleeps == (sleeps if waiter.mode == "timerfd" else 1)
            return late

    run_on(loop_factory, main())


@pytest.mark.realtime
def test_precise_spin_stays_within_its_budget_of_the_period():
    """However late the machine has been waking, the spin before each deadline is at most SPIN_BUDGET of the
    time between deadlines: a 4 ms window on a 5 ms period would burn most of a core, the budget 3 %."""

    async def main():
        with DeadlineWaiter(precise=True) as waiter:
            waiter.spin_window_s = 0.004  # as if a loaded machine had taught it 4 ms
            now = time.monotonic
            t0 = now()
            cpu0 = time.thread_time()
            for k in range(1, 41):
                deadline = t0 + k * 0.005
                await waiter.wait_until(deadline)
                assert now() >= deadline
            cpu = time.thread_time() - cpu0
            wall = now() - t0
            assert cpu < 0.4 * wall  # spinning 4 ms of every 5 would be about 0.8

    run_on(uvloop.new_event_loop, main())


@pytest.mark.realtime
def test_precise_vehicle_ticks_are_never_early_and_report_as_usual():
    v = Vehicle()
    stamps: list[float] = []

    class Stamp:
        def run(self):
            stamps.append(time.monotonic())

    v.add(Stamp())
    report = asyncio.run(v.run(rate_hz=200, max_loop_count=60, precise=True))
    assert report.loops == 60 and len(stamps) == 60
    assert report.lateness_ms["min"] >= 0.0  # no tick started before its deadline
    assert report.lateness_ms["50%"] < 50.0
    # what precise mode spun at most per tick is in the report, learned within its bounds
    assert report.spin_window_ms is not None
    assert _precise_wait._WINDOW_FLOOR_S * 1e3 <= report.spin_window_ms <= _precise_wait._WINDOW_CEIL_S * 1e3
    sleeps = {1: "one sleep", 2: "two sleeps"}[report.precise_sleeps]
    assert f"ms (learned; after {sleeps})" in v.format_report(report)
    plain = Vehicle()
    plain.add(Stamp())
    report = asyncio.run(plain.run(rate_hz=200, max_loop_count=5))
    assert report.spin_window_ms is None and "precise spin window" not in plain.format_report(report)
    assert report.precise_sleeps is None


@pytest.mark.realtime
@pytest.mark.parametrize("two", [True, False], ids=["two-sleeps", "one-sleep"])
def test_the_report_says_how_many_times_precise_ticks_slept(two, monkeypatch):
    """A drive at a rate where the process learned two sleeps pays off reports 2; where one is enough, 1."""
    cls = _precise_wait._period_class(1 / 200)
    monkeypatch.setattr(
        _precise_wait, "_learned", {cls: _precise_wait._Learned(array("d", [100e-6] * 100), two, array("d"))}
    )

    class Noop:
        def run(self):
            pass

    v = Vehicle()
    v.add(Noop())
    report = asyncio.run(v.run(rate_hz=200, max_loop_count=40, precise=True))
    assert report.precise_sleeps == (2 if two else 1)
    assert report.spin_window_ms is not None


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_precise_mode_on_the_virtual_clock_is_the_exact_timer():
    v = Vehicle()
    times: list[float] = []

    class Stamp:
        def run(self):
            times.append(asyncio.get_running_loop().time())

    v.add(Stamp())
    report = await v.run(rate_hz=50, max_loop_count=100, precise=True)
    assert times == [times[0] + k / 50 for k in range(100)]
    assert v.profiler.lateness.max == 0.0
    assert report.spin_window_ms is None and report.precise_sleeps is None  # nothing is spun


# ---------------------------------------------------------------------------------------------- stop()
@pytest.mark.realtime
@pytest.mark.parametrize("use_uvloop", [False, True], ids=["asyncio", "uvloop"])
def test_stop_from_a_thread_cuts_a_long_tick_wait_short(use_uvloop):
    v = Vehicle()
    v.add(Poller(lambda: 1, rate_hz=50, name="p"), outputs=["p"])
    timer = threading.Timer(0.1, v.stop)
    t = time.monotonic()
    timer.start()
    loops, _ = v.start(rate_hz=0.2, use_uvloop=use_uvloop)  # a tick every 5 s: stop() must cut the wait
    assert time.monotonic() - t < 3.0
    assert loops == 1


# ---------------------------------------------------------------------------------------------- leaks
@pytest.mark.realtime
@pytest.mark.parametrize("loop_factory", LOOPS)
def test_no_file_descriptor_left_after_many_waits_sleeps_and_drives(loop_factory):
    gc.collect()
    before = open_fds()

    async def main():
        at_start = open_fds()  # the loop's own descriptors are open by now
        for _ in range(200):
            with DeadlineWaiter() as waiter:
                await waiter.wait_until(time.monotonic() + 0.0001)
        c = get_clock()
        for _ in range(200):
            await c.sleep(0.0001)
        loop = asyncio.get_running_loop()
        for _ in range(10):
            v = Vehicle()
            v.add(Poller(lambda: 1, rate_hz=500, name="p"), outputs=["p"])
            loop.call_later(0.01, v.stop)
            await v.run(rate_hz=400)
        return open_fds() - at_start

    # nothing accumulates while the loop runs ...
    assert run_on(loop_factory, main()) == set()
    gc.collect()
    # ... and nothing is left once it is closed
    assert open_fds() - before == set()


@pytest.mark.realtime
def test_an_unclosed_waiter_releases_its_timerfd_with_its_loop():
    gc.collect()
    before = open_fds()

    async def main():
        waiter = DeadlineWaiter()
        await waiter.wait_until(time.monotonic() + 0.001)
        return waiter.mode

    assert run_on(uvloop.new_event_loop, main()) == "timerfd"
    gc.collect()
    assert open_fds() - before == set()


# ---------------------------------------------------------------------------------------------- the poller
@pytest.mark.realtime
def test_poller_reads_in_its_own_thread_on_a_real_loop_and_stops_promptly():
    names: list[str] = []
    stamps: list[float] = []

    def read():
        names.append(threading.current_thread().name)
        stamps.append(time.monotonic())
        return len(stamps)

    async def main():
        poller = Poller(read, rate_hz=200, name="imu")
        task = asyncio.create_task(poller.update())
        await asyncio.sleep(0.2)
        poller.shutdown()
        await asyncio.wait_for(task, 1.0)
        n = poller.reads
        await asyncio.sleep(0.05)
        assert poller.reads == n  # no read after shutdown
        return poller

    poller = run_on(uvloop.new_event_loop, main())
    assert set(names) == {"poll:imu"}
    assert 5 <= poller.reads <= 45  # about 40 in 0.2 s; a loaded machine skips, never bursts
    assert poller.sample is not None and poller.sample.value == poller.reads
    t0 = stamps[0]
    assert all(t - (t0 + k / 200) >= -1e-6 for k, t in enumerate(stamps) if k < 2)  # the first reads on time
    wait_until(lambda: not any(t.name == "poll:imu" for t in threading.enumerate()), 1.0, "the poll:imu thread to end")


@pytest.mark.realtime
def test_poller_thread_counts_errors_and_skips_when_reads_overrun():
    n = {"i": 0}

    def slow_flaky():
        n["i"] += 1
        time.sleep(0.025)  # longer than two 10 ms periods: deadlines are skipped, not burst
        if n["i"] % 2 == 0:
            raise OSError(121, "Remote I/O error")
        return n["i"]

    async def main():
        poller = Poller(slow_flaky, rate_hz=100, name="slow")
        task = asyncio.create_task(poller.update())
        await asyncio.sleep(0.3)
        poller.shutdown()
        await asyncio.wait_for(task, 1.0)
        return poller

    poller = run_on(uvloop.new_event_loop, main())
    assert poller.errors >= 2 and poller.reads >= 2
    assert abs(poller.errors - poller.reads) <= 1
    assert poller.skipped >= poller.reads  # every slow read skips at least one deadline
    assert isinstance(poller.last_error, OSError)


@pytest.mark.realtime
def test_a_cancel_message_reaches_the_waiting_task():
    async def main():
        with DeadlineWaiter() as waiter:
            task = asyncio.create_task(waiter.wait_until(time.monotonic() + 30.0))
            await asyncio.sleep(0.005)
            task.cancel("car stopped")
            with pytest.raises(asyncio.CancelledError, match="car stopped"):
                await task

    run_on(uvloop.new_event_loop, main())


def _through(deadlines: list[float], done: asyncio.Future[None]) -> tuple[Callable[[], float | None], list[float]]:
    """A ``call_at`` callback that notes when it was called and returns the next of ``deadlines``; after the last
    it completes ``done`` and returns None. Returns the callback and its call times."""
    called: list[float] = []

    def job() -> float | None:
        called.append(time.monotonic())
        if len(called) == len(deadlines):
            done.set_result(None)
            return None
        return deadlines[len(called)]

    return job, called


# ------------------------------------------------------------------------------------------- call_at


@pytest.mark.realtime
@pytest.mark.parametrize("precise", [False, True], ids=["default", "precise"])
@pytest.mark.parametrize("loop_factory", LOOPS)
def test_call_at_runs_a_periodic_callback_never_early_until_it_returns_none(loop_factory, wait_mode, precise):
    async def main() -> tuple[list[float], list[float], DeadlineWaiter]:
        waiter = DeadlineWaiter(precise=precise)
        now = time.monotonic
        t0 = now() + 0.01
        deadlines = [t0 + k * 0.0041 for k in range(12)]
        done = asyncio.get_running_loop().create_future()
        job, called = _through(deadlines, done)
        waiter.call_at(deadlines[0], job)
        await asyncio.wait_for(done, 5)
        await asyncio.sleep(0.02)  # a stray extra call would land here
        waiter.close()
        return called, deadlines, waiter

    called, deadlines, waiter = run_on(loop_factory, main())
    assert len(called) == len(deadlines)  # called once per deadline, then no more
    for t, deadline in zip(called, deadlines, strict=True):
        assert deadline <= t < deadline + GENEROUS_S
    assert waiter.waits == len(deadlines)


@pytest.mark.realtime
@pytest.mark.parametrize("loop_factory", LOOPS)
def test_call_at_is_dropped_by_cancel_call_and_a_past_deadline_is_not_called_inline(loop_factory, wait_mode):
    async def main() -> tuple[list[str], list[str]]:
        waiter = DeadlineWaiter()
        calls: list[str] = []
        waiter.call_at(time.monotonic() + 0.02, lambda: calls.append("cancelled"))
        waiter.cancel_call()
        waiter.call_at(time.monotonic() - 1.0, lambda: calls.append("late"))
        inline = list(calls)  # nothing may run from inside call_at
        await asyncio.sleep(0.05)
        waiter.close()
        return inline, calls

    inline, calls = run_on(loop_factory, main())
    assert inline == []
    assert calls == ["late"]


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_call_at_on_the_virtual_clock_fires_at_exact_deadlines():
    loop = asyncio.get_running_loop()
    waiter = DeadlineWaiter()
    t0 = loop.time()
    seen: list[float] = []

    def job() -> float | None:
        seen.append(loop.time() - t0)
        return t0 + 0.05 * (len(seen) + 1) if len(seen) < 5 else None

    waiter.call_at(t0 + 0.05, job)
    await asyncio.sleep(1.0)
    assert seen == [pytest.approx(0.05 * k, abs=1e-12) for k in range(1, 6)]
    waiter.call_at(loop.time() + 0.1, lambda: seen.append(-1.0))
    waiter.cancel_call()
    await asyncio.sleep(0.2)
    assert -1.0 not in seen


@pytest.mark.realtime
def test_an_all_sync_car_ticks_from_the_timer_and_a_car_with_an_async_part_from_its_task():
    """Both ways of driving ticks give the same report on a real loop: ticks never early, none skipped."""

    class Sync:
        def run(self):
            return 1

    class Async:
        async def run(self, x):
            await asyncio.sleep(0)
            return x

    reports = {}
    for name, parts in (("timer", [Sync()]), ("task", [Sync(), Async()])):
        v = Vehicle()
        v.add(parts[0], outputs=["x"])
        if len(parts) > 1:
            v.add(parts[1], inputs=["x"], outputs=["y"])
        reports[name] = run_on(uvloop.new_event_loop, v.run(200, 40))
    for name, r in reports.items():
        assert r.loops == 40, name
        assert r.lateness_ms["min"] >= 0.0, name
        assert r.parts["Sync"]["count"] == 39, name  # the first tick left out, as in Donkeycar
    assert "Async" in reports["task"].parts


def test_arming_a_timerfd_that_is_gone_raises_oserror_with_its_errno():
    import errno

    tfd = _timerfd.Timerfd()
    fd = tfd.fd
    os.close(fd)
    tfd.fd = -1  # closed behind its back: nothing left for close() to do
    with pytest.raises(OSError) as info:
        tfd.arm(time.monotonic_ns() + 10**9)
    assert info.value.errno in (errno.EBADF, errno.EINVAL)  # EINVAL if the number was reused meanwhile


T0 = 1000.0  # deadlines of taught waits: only the gaps between them matter


def _unrun_precise_waiter() -> DeadlineWaiter:
    """A precise waiter on a timerfd of a loop that never runs: what it learns comes from :func:`_teach`."""
    return DeadlineWaiter(uvloop.new_event_loop(), precise=True)


def _close(waiter: DeadlineWaiter) -> None:
    waiter.close()
    waiter._loop.close()


def _teach(waiter: DeadlineWaiter, deadlines: list[float], late: Callable[[int], float]) -> None:
    """Teach ``waiter`` what precise waits for ``deadlines`` would, without sleeping: each wait's own bookkeeping,
    in :meth:`DeadlineWaiter.wait_until`'s order (``_target``: the period class from the gap and a refresh of the
    window that fell due; the first sleep's wake-up; ``_learn``: the lateness of the sleep before the spin), with
    wake-ups ``late(k)`` seconds late for the k-th wait instead of what a real timer did. Real wake-ups decide
    nothing here: on a loaded machine a wait that finds its deadline passed learns nothing, which moved the
    refreshes and the gaps (so the period class that learned) from run to run."""
    for k, deadline in enumerate(deadlines):
        target = waiter._target(deadline)
        first = target - waiter._guard_s
        waiter._first_at = first
        waiter._first_woke(first + late(k))
        waiter._learn(late(k))


def _every(spacing_s: float, n: int, after: float = T0) -> list[float]:
    return [after + k * spacing_s for k in range(1, n + 1)]


def _lateness(k: int) -> float:
    """A quiet machine's wake-ups: 50 to 95 µs late."""
    return 50e-6 + (k % 10) * 5e-6


def test_a_new_precise_waiter_starts_from_the_window_the_last_one_learned(monkeypatch):
    monkeypatch.setattr(_precise_wait, "_learned", {})
    monkeypatch.setattr(_precise_wait, "_learned_window_s", None)
    first = _unrun_precise_waiter()
    try:
        assert first.spin_window_s == _precise_wait._WINDOW_START_S  # nothing learned in this process yet: the guess
        _teach(first, _every(0.002, _precise_wait._LATE_WARMUP + 2), _lateness)
        learned = first.spin_window_s
    finally:
        _close(first)
    second = _unrun_precise_waiter()
    try:
        start = second.spin_window_s
    finally:
        _close(second)
    assert learned == pytest.approx(95e-6 - clock.PRECISE_TOLERANCE_S)  # it did learn: its q99, less the tolerance
    assert start == learned  # the machine's wake-up latency, not the guess


def test_a_precise_waiter_starts_from_what_was_learned_at_its_own_period(monkeypatch):
    """Wake-up latency depends on how long the machine slept: what is learned is kept per period class, and a
    new waiter starts from its own rate's, not from whatever rate learned last."""
    monkeypatch.setattr(_precise_wait, "_learned", {})
    monkeypatch.setattr(_precise_wait, "_learned_window_s", None)
    # two sleeps throughout: a switch to one would start the window's samples afresh from the first sleep's
    monkeypatch.setattr(_precise_wait, "_ONE_STAGE_BELOW_S", -math.inf)

    def learn(spacing_s: float, late_s: float) -> float:
        waiter = _unrun_precise_waiter()
        try:
            _teach(waiter, _every(spacing_s, _precise_wait._LATE_WARMUP + 2), lambda k: late_s)
            return waiter.spin_window_s
        finally:
            _close(waiter)

    def started_at(period: float) -> tuple[float, int]:
        waiter = _unrun_precise_waiter()
        try:
            waiter.call_at(time.monotonic() + 60, lambda: None, period=period)  # never due: only arms
            started = waiter.spin_window_s, len(waiter._late)
            waiter.cancel_call()
            return started
        finally:
            _close(waiter)

    slow = learn(0.006, 150e-6)  # deadlines 6 ms apart, then 1.1 ms apart
    fast = learn(0.0011, 60e-6)
    assert (slow, fast) == (pytest.approx(130e-6), pytest.approx(40e-6))
    slow_class, fast_class = _precise_wait._period_class(0.006), _precise_wait._period_class(0.0011)
    assert slow_class != fast_class
    # what each rate learned from is kept under its class
    assert list(_precise_wait._learned[slow_class].late) == [150e-6] * _precise_wait._LATE_WARMUP
    assert list(_precise_wait._learned[fast_class].late) == [60e-6] * _precise_wait._LATE_WARMUP
    assert _precise_wait._learned_window_s == fast  # the last one learned: the start for an unknown period
    # pretend the two rates woke differently late, so which one a new waiter starts from shows
    _precise_wait._learned[slow_class] = _precise_wait._Learned(array("d", [300e-6] * 200), True, array("d"))
    _precise_wait._learned[fast_class] = _precise_wait._Learned(array("d", [100e-6] * 200), True, array("d"))
    assert started_at(0.006) == (pytest.approx(300e-6 - clock.PRECISE_TOLERANCE_S), 200)
    assert started_at(0.0011) == (pytest.approx(100e-6 - clock.PRECISE_TOLERANCE_S), 200)
    unknown = _precise_wait._period_class(0.5)
    assert unknown not in _precise_wait._learned
    assert started_at(0.5) == (_precise_wait._learned_window_s, 0)  # nothing for that rate: the last window


def test_a_waiter_that_takes_over_learned_samples_is_not_thrown_by_one_outlier(monkeypatch):
    """A restarted drive keeps the quantile over the wake-ups before it: its first few dozen, one of them an
    outlier, do not set the window (a fresh waiter's first estimate is the largest of them)."""
    monkeypatch.setattr(_precise_wait, "_learned", {})
    period = 0.01
    cls = _precise_wait._period_class(period)
    typical, outlier = 100e-6, 400e-6

    def first_window(past: array | None) -> float:
        if past is not None:
            _precise_wait._learned[cls] = _precise_wait._Learned(past, True, array("d"))
        waiter = DeadlineWaiter(uvloop.new_event_loop(), precise=True)
        try:
            waiter._enter_period_class(cls)
            waiter._learn(outlier)
            for _ in range(_precise_wait._LATE_WARMUP - 1):
                waiter._learn(typical)
            waiter._refresh_window()
            return waiter.spin_window_s
        finally:
            waiter.close()
            waiter._loop.close()

    fresh = first_window(None)
    assert fresh == pytest.approx(outlier - clock.PRECISE_TOLERANCE_S)  # the largest of 64
    carried = first_window(array("d", [typical] * 1000))
    assert carried == pytest.approx(typical - clock.PRECISE_TOLERANCE_S)
    # and what it learned is stored oldest first, its own samples last, for the next one
    stored = _precise_wait._learned[cls].late
    assert len(stored) == _precise_wait._LATE_SAMPLES and stored[-_precise_wait._LATE_WARMUP] == outlier


def test_a_precise_waiter_that_has_learned_keeps_its_own_window_when_its_period_changes(monkeypatch):
    monkeypatch.setattr(_precise_wait, "_learned", {})
    waiter = _unrun_precise_waiter()
    try:
        deadlines = _every(0.0021, _precise_wait._LATE_WARMUP + 2)
        _teach(waiter, deadlines, _lateness)
        own = waiter.spin_window_s
        assert own == pytest.approx(95e-6 - clock.PRECISE_TOLERANCE_S)  # learned from its own wake-ups
        another_rate = _precise_wait._Learned(array("d", [own + 0.000_2] * 200), waiter._two_stage, array("d"))
        _precise_wait._learned[_precise_wait._period_class(0.04)] = another_rate
        _teach(waiter, _every(0.04, 2, after=deadlines[-1]), _lateness)  # two deadlines 40 ms apart: a new class
        assert waiter._period_class == _precise_wait._period_class(0.04)
        assert waiter.spin_window_s == own
    finally:
        _close(waiter)


def test_precise_mode_sleeps_once_where_the_first_sleeps_tail_is_short_and_twice_where_it_is_long(monkeypatch):
    """The first sleep's lateness decides: a 99th percentile close to the median (a busy machine, a small board)
    means one sleep is enough and the window is learned from that sleep; a long tail (an idle virtual machine)
    means two, with the window of the second sleep, as learned the last time this waiter slept twice."""
    monkeypatch.setattr(_precise_wait, "_learned", {})
    waiter = DeadlineWaiter(uvloop.new_event_loop(), precise=True)

    def first_sleeps(lateness: list[float]) -> None:
        for late in lateness:
            waiter._first_at = 1.0
            waiter._first_woke(1.0 + late)

    try:
        assert waiter._two_stage
        for _ in range(_precise_wait._LATE_WARMUP):
            waiter._learn(60e-6)  # the second sleep's lateness
        first_sleeps([50e-6 + (k % 10) * 2e-6 for k in range(_precise_wait._FIRST_SAMPLES)])  # tail 18 µs over median
        waiter._refresh_window()
        assert not waiter._two_stage
        assert waiter.spin_window_s == pytest.approx(68e-6 - clock.PRECISE_TOLERANCE_S)  # the first sleep's q99
        assert list(waiter._other_late) == [60e-6] * _precise_wait._LATE_WARMUP  # the second sleep's, kept
        # a long tail: 3 % of the (now only) sleeps 400 µs late
        for k in range(_precise_wait._FIRST_SAMPLES):
            waiter._learn(400e-6 if k % 32 == 0 else 50e-6)
        waiter._refresh_window()
        assert waiter._two_stage and waiter._guard_s == 0.0  # (armed at the next wait)
        assert waiter.spin_window_s == pytest.approx(60e-6 - clock.PRECISE_TOLERANCE_S)
        waiter._target(time.monotonic() + 1)
        assert waiter._guard_s == _precise_wait._GUARD_S
    finally:
        waiter.close()
        waiter._loop.close()


# ------------------------------------------------------------------------------------ periodic timerfd
def _timerfd_state(fd: int) -> tuple[int, int]:
    """What the kernel holds for a timerfd (``timerfd_gettime``): nanoseconds to its next expiry (0: disarmed)
    and its interval (0: one-shot)."""
    import ctypes

    libc = ctypes.CDLL(None, use_errno=True)
    spec = (ctypes.c_long * 4)()
    assert libc.timerfd_gettime(fd, spec) == 0, os.strerror(ctypes.get_errno())
    return spec[2] * 10**9 + spec[3], spec[0] * 10**9 + spec[1]


def _record_arms(tfd: _timerfd.Timerfd | None) -> list[int]:
    """Every one-shot arming of ``tfd`` from now on, in nanoseconds (0: disarmed), as the waiter asks for it."""
    assert tfd is not None
    armed: list[int] = []
    arm = tfd.arm

    def recording_arm(ns: int) -> None:
        armed.append(ns)
        arm(ns)

    tfd.arm = recording_arm  # type: ignore[method-assign]
    return armed


@pytest.mark.realtime
@pytest.mark.parametrize("loop_factory", LOOPS)
def test_call_at_with_a_period_arms_the_timer_once_for_deadlines_on_its_grid(loop_factory):
    """On the grid, the kernel moves the timer on by itself: one arming for the whole series. A deadline off
    the grid (a skip after an overrun) arms a new grid; the series' end leaves the timer disarmed."""
    period = 0.004

    async def main() -> tuple[list[float], list[float], list[int], list[tuple[int, int]], tuple[int, int]]:
        waiter = DeadlineWaiter()
        tfd = waiter._tfd
        assert tfd is not None and waiter.mode == "timerfd"
        armed: list[int] = []
        arm_every = tfd.arm_every

        def counting_arm_every(first_ns: int, interval_ns: int) -> None:
            armed.append(first_ns)
            arm_every(first_ns, interval_ns)

        tfd.arm_every = counting_arm_every
        now = time.monotonic
        t0 = now() + 0.01
        # six on the grid, a skip of three periods, four more on the new grid
        deadlines = [t0 + k * period for k in range(6)] + [t0 + k * period for k in range(9, 13)]
        called: list[float] = []
        states: list[tuple[int, int]] = []
        classes: set[int] = set()
        done = asyncio.get_running_loop().create_future()

        def job() -> float | None:
            called.append(now())
            states.append(_timerfd_state(tfd.fd))
            classes.add(waiter._period_class)
            if len(called) == len(deadlines):
                done.set_result(None)
                return None
            return deadlines[len(called)]

        waiter.call_at(deadlines[0], job, period=period)
        await asyncio.wait_for(done, 5)
        await asyncio.sleep(3 * period)  # a timer left running would fire here
        after = _timerfd_state(tfd.fd)
        waiter.close()
        assert classes == {0}  # (only precise mode keeps a period class)
        return called, deadlines, armed, states, after

    called, deadlines, armed, states, after = run_on(loop_factory, main())
    assert len(called) == len(deadlines)
    for t, deadline in zip(called, deadlines, strict=True):
        assert deadline <= t < deadline + GENEROUS_S
    # armed for the first deadline and again for the skip, unless the machine stalled past a deadline (then
    # the grid is armed afresh for the next one): never once per deadline
    assert 2 <= len(armed) < len(deadlines) // 2 + 2
    assert armed[0] >= deadlines[0] * 1e9
    assert all(interval == round(period * 1e9) + 1 for _, interval in states[:-1])  # periodic throughout
    assert after == (0, 0)  # the series ended: disarmed


@pytest.mark.realtime
@pytest.mark.parametrize(
    ("period", "learned_once", "sleeps"),
    [(0.02, False, 2), (0.02, True, 1), (0.001, False, 1)],
    ids=["50Hz", "50Hz-learned-one-sleep", "1kHz"],
)
@pytest.mark.parametrize("loop_factory", LOOPS)
def test_precise_mode_sleeps_twice_a_guard_before_its_window_then_spins(
    loop_factory, period, learned_once, sleeps, monkeypatch
):
    """Precise mode's first sleep ends a guard before the spin window, a second, short one at the window, and
    the rest is spun: each deadline arms two one-shot timers, never a periodic one, and the callback never runs
    early. A series too fast for a guard sleeps once per deadline, and so does one at a rate where this process
    learned that one sleep is enough (the window then from those samples)."""
    # the start window throughout (no refresh in 20 waits)
    monkeypatch.setattr(_precise_wait, "_learned_window_s", None)
    monkeypatch.setattr(_precise_wait, "_learned", {})
    if learned_once:
        cls = _precise_wait._period_class(period)
        _precise_wait._learned[cls] = _precise_wait._Learned(array("d", [150e-6] * 100), False, array("d"))
    n = 20

    async def main() -> tuple[list[float], list[float], list[int], list[tuple[int, int]], float, float]:
        waiter = DeadlineWaiter(precise=True)
        tfd = waiter._tfd
        armed = _record_arms(tfd)
        now = time.monotonic
        t0 = now() + 0.01
        deadlines = [t0 + k * period for k in range(n)]
        called: list[float] = []
        states: list[tuple[int, int]] = []
        done = asyncio.get_running_loop().create_future()

        def job() -> float | None:
            called.append(now())
            states.append(_timerfd_state(tfd.fd))
            if len(called) == n:
                done.set_result(None)
                return None
            return deadlines[len(called)]

        waiter.call_at(deadlines[0], job, period=period)
        await asyncio.wait_for(done, 5)
        window, guard = waiter.spin_window_s, waiter._guard_s
        waiter.close()
        return called, deadlines, armed, states, window, guard

    called, deadlines, armed, states, window, guard = run_on(loop_factory, main())
    for t, deadline in zip(called, deadlines, strict=True):
        assert deadline <= t < deadline + GENEROUS_S
    assert all(interval == 0 for _, interval in states)  # one-shots, never the periodic timer
    if learned_once:
        assert window == pytest.approx(150e-6 - clock.PRECISE_TOLERANCE_S)
    window = min(window, period * clock.SPIN_BUDGET)
    targets = {math.ceil((d - window) * 1e9) for d in deadlines}
    if sleeps == 2:
        assert guard == _precise_wait._GUARD_S
        firsts = {math.ceil((d - window - guard) * 1e9) for d in deadlines}
        # every deadline arms its guard, and then its window unless the first sleep woke too
        # late for a second one (a stalled machine): then it spins from there
        assert firsts <= set(armed)
        assert len(targets & set(armed)) >= n // 2
        assert set(armed) <= firsts | targets | {math.ceil((deadlines[0] - window - guard) * 1e9), 0}
    else:
        assert guard == 0.0
        assert set(armed) <= targets | {0}  # one sleep per deadline, to its window (0: disarmed at the end)
        assert len(armed) <= n + 1


@pytest.mark.realtime
@pytest.mark.parametrize("loop_factory", LOOPS)
def test_precise_mode_spins_from_a_guard_sleep_that_woke_too_late_for_a_second(loop_factory, monkeypatch):
    """The loop is held past the end of the guard sleep until just before the spin window: too close for a
    second sleep (it would wake after the spin), so the waiter spins from there, arming nothing more."""
    monkeypatch.setattr(_precise_wait, "_learned_window_s", None)

    async def main() -> tuple[list[int], float, float, float]:
        waiter = DeadlineWaiter(precise=True)
        armed = _record_arms(waiter._tfd)
        now = time.monotonic
        deadline = now() + 0.02
        task = asyncio.ensure_future(waiter.wait_until(deadline))
        await asyncio.sleep(0)  # the wait has armed its guard sleep
        target = deadline - waiter.spin_window_s
        while now() < target - 10e-6:  # hold the loop past the guard sleep's end, up to just before the window
            pass
        await task
        returned = now()
        waiter.close()
        return armed, deadline, target, returned

    armed, deadline, target, returned = run_on(loop_factory, main())
    assert returned >= deadline
    assert armed == [math.ceil((target - _precise_wait._GUARD_S) * 1e9)]  # the guard sleep only


@pytest.mark.realtime
@pytest.mark.parametrize("loop_factory", LOOPS)
def test_call_at_with_a_period_follows_a_callback_that_raises_and_stops_its_timer(loop_factory):
    async def main() -> tuple[int, tuple[int, int], BaseException | None]:
        loop = asyncio.get_running_loop()
        caught: list[BaseException] = []
        loop.set_exception_handler(lambda _loop, ctx: caught.append(ctx.get("exception")))
        waiter = DeadlineWaiter()
        calls = 0

        def job() -> float | None:
            nonlocal calls
            calls += 1
            raise RuntimeError("part failed")

        waiter.call_at(time.monotonic() + 0.005, job, period=0.005)
        await asyncio.sleep(0.1)  # about 20 periods: a timer left running wakes the loop, but calls nothing
        state = _timerfd_state(waiter._tfd.fd)  # type: ignore[union-attr]
        waiter.close()
        return calls, state, caught[0] if caught else None

    calls, state, error = run_on(loop_factory, main())
    assert calls == 1
    assert state == (0, 0)  # stopped at its next wake-up
    assert isinstance(error, RuntimeError)


@pytest.mark.realtime
@pytest.mark.parametrize("end", ["returns None", "cancel_call", "raises", "new series"])
@pytest.mark.parametrize("loop_factory", LOOPS)
def test_after_a_periodic_series_the_waiter_waits_and_calls_back_as_before(loop_factory, end):
    """A periodic series watches the timerfd with a loop callback of its own; however the series ends, the
    waiter's next wait and next series still wake on time (a wait left to the series' callback would hang)."""
    period = 0.003

    async def main() -> tuple[list[float], float, float, list[tuple[float, float]], list[float]]:
        loop = asyncio.get_running_loop()
        loop.set_exception_handler(lambda _loop, _ctx: None)  # the "raises" case's error, expected
        now = time.monotonic
        waiter = DeadlineWaiter()
        first_done = loop.create_future()
        t0 = now() + 0.005
        called: list[float] = []
        second_deadlines = [t0 + 10 * period + k * 2 * period for k in range(4)]
        then, second = _through(second_deadlines, first_done)  # started from inside the first one's callback

        def job() -> float | None:
            called.append(now())
            if len(called) < 3:
                return t0 + len(called) * period
            if end == "raises":
                loop.call_soon(first_done.set_result, None)
                raise RuntimeError("part failed")
            if end == "new series":
                waiter.call_at(second_deadlines[0], then, period=2 * period)
                return None
            if end == "cancel_call":
                loop.call_soon(first_done.set_result, None)
                # a next deadline, dropped below before it is due: a second ahead, as the next period (3 ms) could
                # come before the task that drops it runs again on a loaded machine
                return now() + 1.0
            loop.call_soon(first_done.set_result, None)
            return None

        waiter.call_at(t0, job, period=period)
        await asyncio.wait_for(first_done, 5)
        if end == "cancel_call":
            waiter.cancel_call()
        deadline = now() + 0.004
        assert await asyncio.wait_for(waiter.wait_until(deadline), 5)
        woke = now()
        # and a new series on the same waiter
        again_done = loop.create_future()
        t1 = now() + 0.004
        once_more, again = _through([t1 + k * period for k in range(3)], again_done)
        waiter.call_at(t1, once_more, period=period)
        await asyncio.wait_for(again_done, 5)
        waiter.close()
        return called, deadline, woke, list(zip(second_deadlines, second, strict=False)), again

    called, deadline, woke, second, again = run_on(loop_factory, main())
    assert len(called) == 3
    assert deadline <= woke < deadline + GENEROUS_S
    assert len(again) == 3
    if end == "new series":
        assert len(second) == 4
        assert all(d <= t < d + GENEROUS_S for d, t in second)  # on its own deadlines, 2 x the first's period


@pytest.mark.realtime
def test_call_at_period_must_be_positive():
    async def main() -> None:
        with DeadlineWaiter() as waiter:
            for bad in (0.0, -0.01, float("nan"), float("inf")):
                with pytest.raises(ValueError, match="period must be a positive number"):
                    waiter.call_at(time.monotonic() + 1, lambda: None, period=bad)

    run_on(uvloop.new_event_loop, main())


@pytest.mark.realtime
def test_precise_call_at_early_leaves_the_last_stretch_to_the_callback(monkeypatch):
    """``early=True``: the callback runs when the early timer wakes (the spin window before the deadline) and
    spins the rest itself; without it the waiter spins and the callback never runs before its deadline."""

    monkeypatch.setattr(_precise_wait, "_learned_window_s", None)  # start from the guess, so learning shows

    async def main() -> tuple[list[float], list[float], float]:
        waiter = DeadlineWaiter(precise=True)
        now = time.monotonic
        t0 = now() + 0.01
        deadlines = [t0 + k * 0.003 for k in range(_precise_wait._LATE_WARMUP + 40)]
        entered: list[float] = []
        done = asyncio.get_running_loop().create_future()

        def job() -> float | None:
            entered.append(now())
            waiter.arrived(entered[-1])  # the window is learned from when the callback got here
            deadline = deadlines[len(entered) - 1]
            while now() < deadline:  # the callback's own spin
                pass
            if len(entered) == len(deadlines):
                done.set_result(None)
                return None
            return deadlines[len(entered)]

        waiter.call_at(deadlines[0], job, early=True)
        await asyncio.wait_for(done, 10)
        window = waiter.spin_window_s
        waiter.close()
        return entered, deadlines, window

    entered, deadlines, window = run_on(uvloop.new_event_loop, main())
    early = [d - t for t, d in zip(entered, deadlines, strict=True)]
    assert max(early) > 0  # some calls came before their deadline: the waiter did not spin for them
    assert all(e <= _precise_wait._WINDOW_CEIL_S + 1e-4 for e in early)  # never before the armed (early) target
    assert window <= _precise_wait._WINDOW_CEIL_S
    # learned from the arrivals
    assert window != _precise_wait._WINDOW_START_S or window == _precise_wait._WINDOW_CEIL_S


@pytest.mark.parametrize(
    "loop_factory",
    [
        pytest.param(asyncio.new_event_loop, marks=pytest.mark.realtime),
        pytest.param(uvloop.new_event_loop, marks=pytest.mark.realtime),
        VirtualClockLoop,
    ],
)
def test_the_clock_cache_lets_closed_loops_go(loop_factory):
    """A loop's clock holds the loop; the cache drops the clocks of closed loops, so a program that runs loop
    after loop (a test suite, a benchmark's segments) does not keep every loop it ever ran."""
    import weakref

    async def ask() -> Clock:
        return get_clock()

    first = loop_factory()
    clock = first.run_until_complete(ask())
    assert first.run_until_complete(ask()) is clock  # cached while the loop lives
    first.close()
    gone = weakref.ref(first)
    del first, clock
    later = loop_factory()
    later.run_until_complete(ask())  # a new loop's clock: the closed loop's is dropped
    gc.collect()
    try:
        assert gone() is None, "the closed loop is still held"
    finally:
        later.close()
