"""The virtual-clock event loop itself."""

import asyncio
import contextvars
import threading
import time
import warnings

import pytest

from asyncdonkey.testing import (
    VirtualClockDeadlock,
    VirtualClockError,
    VirtualClockLoop,
    VirtualClockStall,
    virtual_loop_factory,
)


def run_virtual(coro_fn, **loop_kwargs):
    with asyncio.Runner(loop_factory=lambda: VirtualClockLoop(**loop_kwargs)) as runner:
        return runner.run(coro_fn())


@pytest.mark.realtime
def test_time_jumps_exactly_to_the_next_timer_and_never_backwards():
    async def main():
        loop = asyncio.get_running_loop()
        seen = []
        await asyncio.sleep(0.08)
        seen.append(loop.time())
        loop.call_at(3600.0, lambda: None)
        await asyncio.sleep(0)
        seen.append(loop.time())  # a future timer does not move time while something is runnable
        await asyncio.sleep(7200 - loop.time())
        seen.append(loop.time())
        return seen

    real = time.perf_counter()
    assert run_virtual(main) == [0.08, 0.08, 7200.0]
    assert time.perf_counter() - real < 0.5


def test_executor_work_finishes_before_time_moves():
    async def main():
        loop = asyncio.get_running_loop()
        woke = []

        async def sleeper():
            await asyncio.sleep(1.0)
            woke.append(loop.time())

        task = asyncio.create_task(sleeper())
        before = loop.time()
        await asyncio.to_thread(time.sleep, 0.05)  # 50 ms of real work in a thread
        after = loop.time()
        await task
        return before, after, woke

    before, after, woke = run_virtual(main)
    assert before == after == 0.0  # the thread cost no virtual time
    assert woke == [1.0]  # and the sleeper beside it woke at exactly +1 s


def test_a_hold_keeps_time_still_while_a_worker_thread_is_busy():
    async def main():
        loop = asyncio.get_running_loop()
        jobs = []  # work handed to a thread of our own, not an executor
        done = threading.Event()

        def worker():
            while not done.is_set():
                if jobs:
                    time.sleep(0.03)  # 30 ms of real work per job
                    jobs.pop()
                else:
                    time.sleep(0.001)

        t = threading.Thread(target=worker, daemon=True)
        t.start()
        release = loop.hold_time_while(lambda: bool(jobs), "worker")
        seen = []
        for _ in range(3):
            jobs.append(1)
            await asyncio.sleep(0.5)
            seen.append((loop.time(), len(jobs)))  # the job finished before time moved 0.5 s
        release()
        jobs.append(1)  # no hold: time moves on at once, the job still in hand
        await asyncio.sleep(0.5)
        seen.append((loop.time(), len(jobs)))
        done.set()
        t.join()
        return seen

    assert run_virtual(main) == [(0.5, 0), (1.0, 0), (1.5, 0), (2.0, 1)]


def test_a_hold_that_never_ends_is_reported_as_a_stall():
    async def main():
        loop = asyncio.get_running_loop()
        loop.hold_time_while(lambda: True, "stuck disk writer")
        await asyncio.sleep(1)

    with pytest.raises(VirtualClockStall, match="stuck disk writer"):
        run_virtual(main, stall_timeout_s=0.2)


@pytest.mark.realtime
def test_deadlock_raises_a_clear_error_instead_of_hanging():
    async def main():
        await asyncio.Event().wait()

    real = time.perf_counter()
    with pytest.raises(VirtualClockDeadlock, match=r"nothing can ever run again.*Waiting tasks: .*main"):
        run_virtual(main, deadlock_grace_s=0.05)
    assert time.perf_counter() - real < 2.0


@pytest.mark.realtime
def test_outside_io_within_grace_is_not_a_deadlock():
    async def main():
        loop = asyncio.get_running_loop()
        fut = loop.create_future()
        threading.Timer(0.05, loop.call_soon_threadsafe, args=(fut.set_result, "from a thread")).start()
        return await fut

    assert run_virtual(main, deadlock_grace_s=2.0) == "from a thread"


def test_stalled_executor_work_is_reported():
    release = threading.Event()

    def busy_until_released():
        while not release.is_set():
            time.sleep(0.005)  # looks like work: the loop cannot tell it will never finish

    async def main():
        try:
            await asyncio.get_running_loop().run_in_executor(None, busy_until_released)
        finally:
            release.set()

    try:
        with pytest.raises(VirtualClockStall, match=r"has not finished after 0.3 s of real time: thread 'asyncio_0'"):
            run_virtual(main, stall_timeout_s=0.3)
    finally:
        release.set()


def test_executor_work_blocked_on_an_event_nobody_sets_is_a_deadlock():
    release = threading.Event()

    async def main():
        await asyncio.get_running_loop().run_in_executor(None, release.wait)

    try:
        blocked = r"blocked waiting to be released: thread 'asyncio_0' \(running Event.wait"
        with pytest.raises(VirtualClockDeadlock, match=blocked):
            run_virtual(main, deadlock_grace_s=0.05)
    finally:
        release.set()


def test_equal_deadlines_fire_in_scheduling_order():
    async def main():
        loop = asyncio.get_running_loop()
        order = []
        done = loop.create_future()
        for i in range(50):
            loop.call_at(5.0, order.append, i)
        loop.call_at(5.0, done.set_result, None)
        await done
        return order

    assert run_virtual(main) == list(range(50))


def test_teardown_after_default_executor_gives_no_warning_and_no_jump():
    async def main():
        await asyncio.to_thread(lambda: None)
        await asyncio.sleep(10)
        return asyncio.get_running_loop()

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        loop = run_virtual(main)
    assert loop.time() == 10.0  # closing did not jump the 300 s executor-join timeout


def test_virtual_uvloop_is_refused_loudly():
    with pytest.raises(VirtualClockError, match="uvloop keeps its clock and timers inside libuv"):
        virtual_loop_factory("uvloop")
    assert isinstance(virtual_loop_factory()(), VirtualClockLoop)


def test_wait_for_timeouts_use_virtual_time():
    async def main():
        loop = asyncio.get_running_loop()
        with pytest.raises(TimeoutError):
            await asyncio.wait_for(asyncio.Event().wait(), timeout=30)
        return loop.time()

    assert run_virtual(main) == 30.0


def _mixed_workload():
    """Sleeps, equal deadlines, a timer already due, executor work and a timeout: what each saw, and when."""

    async def main():
        loop = asyncio.get_running_loop()
        seen = []

        async def ticker(name, period, n):
            for _ in range(n):
                await asyncio.sleep(period)
                seen.append((name, loop.time()))

        tasks = [asyncio.create_task(ticker("fast", 0.05, 6)), asyncio.create_task(ticker("slow", 0.1, 3))]
        for i in range(3):
            loop.call_at(0.1, seen.append, (f"equal{i}", 0.1))
        await asyncio.to_thread(time.sleep, 0.01)
        seen.append(("thread done", loop.time()))
        await asyncio.gather(*tasks)
        due = loop.create_future()
        loop.call_at(0.05, due.set_result, None)  # already in the past: fires without moving time
        await due
        seen.append(("past timer", loop.time()))
        with pytest.raises(TimeoutError):
            await asyncio.wait_for(asyncio.Event().wait(), timeout=2.5)
        seen.append(("timeout", loop.time()))
        return seen

    return main


def test_debug_mode_keeps_the_same_virtual_times_and_order():
    # debug mode runs asyncio's own loop iteration (it times callbacks), the same policy deciding when time moves
    runs = []
    for debug in (False, True):
        with asyncio.Runner(loop_factory=VirtualClockLoop, debug=debug) as runner:
            runs.append(runner.run(_mixed_workload()()))
    fast = [("fast", round(0.05 * k, 2)) for k in range(1, 7)]
    assert [(n, round(t, 9)) for n, t in runs[0] if n == "fast"] == fast
    assert [(n, round(t, 9)) for n, t in runs[0] if n == "slow"] == [("slow", 0.1), ("slow", 0.2), ("slow", 0.3)]
    assert runs[0][0] == ("thread done", 0.0)
    assert [n for n, _ in runs[0] if n.startswith("equal")] == ["equal0", "equal1", "equal2"]
    assert runs[0][-2:] == [("past timer", 0.3), ("timeout", 2.8)]
    assert runs[1] == runs[0]


@pytest.mark.parametrize("which", ["first 10", "last 250"])  # dropped at the head; most of the heap: rebuilt
def test_cancelled_timers_never_fire_nor_stop_time_and_do_not_pile_up(which):
    cancelled = range(10) if which == "first 10" else range(50, 300)

    async def main():
        loop = asyncio.get_running_loop()
        fired = []
        handles = [loop.call_at(1.0 + i, fired.append, i) for i in range(300)]
        for i in cancelled:
            handles[i].cancel()
        jumps = loop.jumps
        await asyncio.sleep(0)
        pending = len(loop._scheduled)
        await asyncio.sleep(400)
        return fired, loop.jumps - jumps, pending

    fired, jumps, pending = run_virtual(main)
    live = [i for i in range(300) if i not in cancelled]
    assert fired == live
    assert jumps == len(live) + 1  # each live timer and the sleep; never to a cancelled deadline
    assert pending == len(live)  # no cancelled timer is kept


def test_callbacks_run_in_the_context_they_were_given():
    var = contextvars.ContextVar("var", default="unset")

    async def main():
        loop = asyncio.get_running_loop()
        given = contextvars.copy_context()
        given.run(var.set, "given")
        var.set("current")
        seen = []
        loop.call_soon(lambda: seen.append(("soon", var.get())), context=given)
        loop.call_soon(lambda: seen.append(("soon, no context", var.get())))
        loop.call_at(1.0, lambda: seen.append(("at", var.get())), context=given)
        loop.call_later(2.0, lambda: seen.append(("later, no context", var.get())))
        var.set("changed after scheduling")
        await asyncio.sleep(3)
        return seen

    assert run_virtual(main) == [
        ("soon", "given"),
        ("soon, no context", "current"),
        ("at", "given"),
        ("later, no context", "current"),
    ]


def test_a_closed_loop_refuses_callbacks_as_asyncio_does():
    loop = VirtualClockLoop()
    loop.close()
    for schedule in (
        lambda: loop.call_soon(print),
        lambda: loop.call_at(1.0, print),
        lambda: loop.call_later(1, print),
    ):
        with pytest.raises(RuntimeError, match="Event loop is closed"):
            schedule()
