"""The virtual-clock event loop itself."""

import asyncio
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


def test_deadlock_raises_a_clear_error_instead_of_hanging():
    async def main():
        await asyncio.Event().wait()

    real = time.perf_counter()
    with pytest.raises(VirtualClockDeadlock, match=r"nothing can ever run again.*Waiting tasks: .*main"):
        run_virtual(main, deadlock_grace_s=0.05)
    assert time.perf_counter() - real < 2.0


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
