"""The virtual clock beside real work: threads, subprocesses, executors, and programs that never finish.

Threads here do their "work" in ``time.sleep`` (real time the clock must not skip) and hand results back with
``call_soon_threadsafe``, as a user's code would. Each test would fail on a loop that simply jumped to the next
timer whenever no callback was ready.
"""

import asyncio
import concurrent.futures
import sys
import threading
import time

import pytest

from asyncdonkey.clock.virtual_loop import (
    VirtualClockBudgetExceeded,
    VirtualClockDeadlock,
    VirtualClockError,
    VirtualClockLivelock,
    VirtualClockLoop,
    VirtualClockStall,
)


def run_virtual(coro_fn, **loop_kwargs):
    with asyncio.Runner(loop_factory=lambda: VirtualClockLoop(**loop_kwargs)) as runner:
        return runner.run(coro_fn())


def reply_from_thread(loop, fut, value, seconds, daemon=False):
    """A plain thread that works ``seconds`` of real time, then completes ``fut`` on the loop."""

    def work():
        time.sleep(seconds)
        loop.call_soon_threadsafe(fut.set_result, value)

    t = threading.Thread(target=work, daemon=daemon)
    t.start()
    return t


SLOW_CHILD = [sys.executable, "-c", "import time; time.sleep(0.15); print('done')"]


# -- real work holds virtual time ----------------------------------------------------------------------------


def test_a_thread_working_longer_than_the_grace_is_not_a_deadlock():
    async def main():
        loop = asyncio.get_running_loop()
        fut = loop.create_future()
        reply_from_thread(loop, fut, "result", 0.15)
        return await fut, loop.time()

    assert run_virtual(main, deadlock_grace_s=0.05) == ("result", 0.0)


def test_a_thread_started_as_another_one_ended_still_holds_time():
    # the loop caches "no thread to watch" while the thread count stays the same: one thread ending as another
    # starts leaves the count as it was, and the new thread must still be seen
    end_old = threading.Event()
    old = threading.Thread(target=end_old.wait, daemon=True)
    old.start()

    async def main():
        loop = asyncio.get_running_loop()
        await asyncio.sleep(1)  # a jump: the census finds nothing to watch, with the old thread counted
        end_old.set()
        old.join()
        fut = loop.create_future()
        reply_from_thread(loop, fut, "done", 0.05)  # a plain (non-daemon) thread at work: time must wait
        return await asyncio.wait_for(fut, 10), loop.time()

    assert run_virtual(main) == ("done", 1.0)


@pytest.mark.subprocess
def test_a_subprocess_working_longer_than_the_grace_is_not_a_deadlock():
    async def main():
        proc = await asyncio.create_subprocess_exec(*SLOW_CHILD, stdout=asyncio.subprocess.PIPE)
        out, _ = await proc.communicate()
        return out.strip(), proc.returncode, asyncio.get_running_loop().time()

    assert run_virtual(main, deadlock_grace_s=0.05) == (b"done", 0, 0.0)


@pytest.mark.parametrize(
    "source", ["thread", pytest.param("subprocess", marks=pytest.mark.subprocess), "cross-thread event"]
)
def test_wait_for_gets_the_answer_of_real_work_instead_of_timing_out(source):
    async def main():
        loop = asyncio.get_running_loop()
        if source == "thread":
            fut = loop.create_future()
            reply_from_thread(loop, fut, "answer", 0.2)
            got = await asyncio.wait_for(fut, 10)
        elif source == "subprocess":
            proc = await asyncio.create_subprocess_exec(*SLOW_CHILD, stdout=asyncio.subprocess.PIPE)
            got = (await asyncio.wait_for(proc.communicate(), 10))[0].strip()
        else:
            event = asyncio.Event()
            threading.Thread(target=lambda: (time.sleep(0.2), loop.call_soon_threadsafe(event.set))).start()
            got = await asyncio.wait_for(event.wait(), 10)
        return got, loop.time()

    got, now = run_virtual(main)
    assert got in ("answer", b"done", True)
    assert now == 0.0  # the real work cost no virtual time


def test_a_periodic_task_does_not_run_ahead_of_a_working_thread():
    async def main():
        loop = asyncio.get_running_loop()
        ticks = []

        async def periodic():
            while True:
                await asyncio.sleep(0.05)
                ticks.append(loop.time())

        task = asyncio.create_task(periodic())
        fut = loop.create_future()
        reply_from_thread(loop, fut, None, 0.2)
        await fut
        at_answer = loop.time()
        await asyncio.sleep(0.12)
        task.cancel()
        return at_answer, ticks

    at_answer, ticks = run_virtual(main)
    assert at_answer == 0.0 and ticks == [0.05, 0.1]


def test_wrap_future_of_a_pool_job_holds_time_like_run_in_executor():
    async def main():
        loop = asyncio.get_running_loop()
        order = []

        async def sleeper():
            await asyncio.sleep(1.0)
            order.append(("sleeper", loop.time()))

        task = asyncio.create_task(sleeper())
        with concurrent.futures.ThreadPoolExecutor(1) as pool:
            await asyncio.wrap_future(pool.submit(time.sleep, 0.15))
            order.append(("pool job", loop.time()))
        await task
        return order

    assert run_virtual(main) == [("pool job", 0.0), ("sleeper", 1.0)]


def test_a_daemon_thread_does_not_freeze_time():
    """A Donkeycar part's update() loop runs forever in a daemon thread: time must keep moving beside it."""
    stop = threading.Event()

    def update_loop():
        while not stop.is_set():
            time.sleep(0.001)

    async def main():
        threading.Thread(target=update_loop, daemon=True).start()
        for _ in range(20):
            await asyncio.sleep(0.05)
        return asyncio.get_running_loop().time()

    try:
        assert run_virtual(main, stall_timeout_s=0.5) == pytest.approx(1.0)
    finally:
        stop.set()


@pytest.mark.realtime
def test_an_answer_from_a_daemon_thread_within_the_threshold_arrives_before_time_moves():
    async def main():
        loop = asyncio.get_running_loop()
        fut = loop.create_future()
        reply_from_thread(loop, fut, "in time", 0.02, daemon=True)
        return await asyncio.wait_for(fut, 10), loop.time()

    assert run_virtual(main, autojump_threshold=1.0) == ("in time", 0.0)


# -- threads that wait on the loop ---------------------------------------------------------------------------


def test_a_thread_waiting_for_an_event_a_task_sets_does_not_stall():
    async def main():
        loop = asyncio.get_running_loop()
        ev = threading.Event()

        async def setter():
            await asyncio.sleep(1.0)
            ev.set()

        task = asyncio.create_task(setter())
        await asyncio.to_thread(ev.wait)
        await task
        return loop.time()

    assert run_virtual(main, stall_timeout_s=0.5) == 1.0


def test_a_thread_calling_run_coroutine_threadsafe_does_not_stall():
    handed_over = []  # the threads' futures, cancelled at the end so no thread can outlive a failed test

    async def main():
        loop = asyncio.get_running_loop()

        async def on_the_loop():
            await asyncio.sleep(2.0)
            return loop.time()

        def in_a_thread():
            handed_over.append(asyncio.run_coroutine_threadsafe(on_the_loop(), loop))
            return handed_over[-1].result()

        from_executor = await asyncio.to_thread(in_a_thread)
        fut = loop.create_future()

        def plain_thread():
            answer = in_a_thread()
            loop.call_soon_threadsafe(fut.set_result, answer)

        threading.Thread(target=plain_thread).start()
        return from_executor, await fut

    try:
        assert run_virtual(main, stall_timeout_s=0.5) == (2.0, 4.0)
    finally:
        for cf in handed_over:
            cf.cancel()


def test_a_stall_is_raised_once_and_names_the_stuck_call():
    release = threading.Event()

    def stuck_job():
        while not release.is_set():
            time.sleep(0.005)

    async def main():
        await asyncio.to_thread(stuck_job)

    try:
        with pytest.raises(VirtualClockStall) as info:
            run_virtual(main, stall_timeout_s=0.2)
    finally:
        release.set()
    message = str(info.value)
    assert "stuck_job, at " in message and "Waiting tasks: " in message
    assert "shutdown" not in message  # not the echo from closing the loop...
    assert not isinstance(info.value.__context__, VirtualClockError)  # ...and no first error hidden behind it


# -- programs that can never finish --------------------------------------------------------------------------


@pytest.mark.realtime
def test_a_wait_that_never_ends_beside_a_periodic_task_exhausts_the_budget():
    async def main():
        async def heartbeat():
            while True:
                await asyncio.sleep(1.0)

        beating = asyncio.create_task(heartbeat(), name="heartbeat")
        await asyncio.Event().wait()  # nobody will ever set it
        beating.cancel()

    real = time.perf_counter()
    with pytest.raises(VirtualClockBudgetExceeded) as info:
        run_virtual(main, budget_s=100)
    message = str(info.value)
    assert "past the budget of 100 s" in message and "to 101.000000 s" in message
    assert "heartbeat (" in message and "main.<locals>.heartbeat at " in message
    assert "main at " in message and "awaiting Event.wait" in message
    assert time.perf_counter() - real < 5.0


def test_jump_moves_time_and_due_timers_fire_in_order_after_it():
    async def main():
        loop = asyncio.get_running_loop()
        fired = []
        for t in (3.0, 1.0, 2.0):
            loop.call_at(t, lambda t=t: fired.append((t, loop.time())))
        loop.jump(5.0)
        assert loop.time() == 5.0 and fired == []
        await asyncio.sleep(0)
        with pytest.raises(ValueError, match="forward"):
            loop.jump(-1)
        with pytest.raises(VirtualClockBudgetExceeded, match="jump"):
            loop.jump(100)
        return fired

    assert run_virtual(main, budget_s=50) == [(1.0, 5.0), (2.0, 5.0), (3.0, 5.0)]


def test_a_task_that_only_yields_is_reported_as_a_livelock():
    async def main():
        async def spin():
            while True:
                await asyncio.sleep(0)

        await asyncio.create_task(spin(), name="spinner")

    where = r"spinner \(.*main.<locals>.spin at .*test_virtual_loop_outside.py:\d+, awaiting sleep"
    with pytest.raises(VirtualClockLivelock, match=where):
        run_virtual(main, livelock_iterations=50_000)
    with pytest.raises(VirtualClockLivelock, match="spinner"):
        run_virtual(main, livelock_s=0.2)


def test_a_task_polling_for_a_working_thread_is_not_a_livelock():
    async def main():
        done = []
        threading.Thread(target=lambda: (time.sleep(0.15), done.append(1))).start()
        while not done:
            await asyncio.sleep(0)
        return asyncio.get_running_loop().time()

    assert run_virtual(main, livelock_s=0.05) == 0.0


def test_a_blocked_plain_thread_and_a_waiting_task_are_both_named_in_a_deadlock():
    release = threading.Event()

    async def main():
        threading.Thread(target=release.wait, name="waiter").start()
        await asyncio.Event().wait()

    try:
        with pytest.raises(VirtualClockDeadlock) as info:
            run_virtual(main, deadlock_grace_s=0.05)
    finally:
        release.set()
    message = str(info.value)
    assert "Waiting tasks: " in message and "main" in message
    assert "threads blocked waiting to be released: thread 'waiter'" in message


def test_knobs_are_checked():
    with pytest.raises(ValueError, match="budget_s"):
        VirtualClockLoop(budget_s=0)
    with pytest.raises(ValueError, match="autojump_threshold"):
        VirtualClockLoop(autojump_threshold=-1)
    loop = VirtualClockLoop(start=10, budget_s=5)
    try:
        assert loop.budget_s == 5 and loop.time() == 10
        loop.budget_s = None
        assert loop.budget_s is None
    finally:
        loop.close()
