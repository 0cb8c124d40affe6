"""The suite's polling helper (tests/waiting.py): what it returns, and what a timeout says.

Every case here holds or times out within a few checks (a timeout already in the past, or a step of 0), so none
waits on the real clock; the async ones run on the virtual clock, where ``step=0`` only yields.
"""

from __future__ import annotations

import asyncio
import itertools
import time
from collections.abc import Callable

import pytest

from .waiting import TimedOut, await_until, time_when, wait_until


def counter(until: int) -> tuple[list[int], Callable[[], int]]:
    """A condition that returns 0 before its ``until``-th call and the call's number from then on, with the list
    of the calls made."""
    calls: list[int] = []
    numbers = itertools.count(1)

    def cond() -> int:
        n = next(numbers)
        calls.append(n)
        return n if n >= until else 0

    return calls, cond


def test_wait_until_returns_the_first_truthy_value_and_checks_no_more() -> None:
    calls, cond = counter(3)
    assert wait_until(cond, 5.0, step=0) == 3
    assert calls == [1, 2, 3]


def test_a_timeout_names_what_was_awaited_and_the_last_value_seen() -> None:
    with pytest.raises(TimedOut, match=r"^timed out after -1 s waiting for the pin at 370; last value: 0$"):
        wait_until(lambda: 0, -1.0, "the pin at 370")


def test_without_what_the_timeout_names_the_condition_by_its_source() -> None:
    pulse = {"throttle": 435}
    with pytest.raises(TimedOut) as err:
        wait_until(lambda: pulse["throttle"] == 370, -1.0)
    assert 'pulse["throttle"] == 370' in str(err.value) and "last value: False" in str(err.value)


def test_a_callable_what_is_read_at_the_timeout() -> None:
    state = {"n": 1}

    def cond() -> bool:
        state["n"] += 1
        return False

    with pytest.raises(TimedOut, match=r"waiting for 5 refused \(so far 2\); last value: False"):
        wait_until(cond, -1.0, lambda: f"5 refused (so far {state['n']})")


def test_a_timed_out_wait_is_an_assertion_error() -> None:
    assert issubclass(TimedOut, AssertionError)  # pytest reports it as a failed test, not an error


@pytest.mark.realtime  # it compares time.monotonic() readings (though no bound on how far apart)
def test_time_when_returns_a_reading_taken_before_the_check_that_held() -> None:
    before = time.monotonic()
    _, cond = counter(2)
    seen = time_when(cond, 5.0, step=0)
    assert before <= seen <= time.monotonic()
    with pytest.raises(TimedOut, match="waiting for the guard to end"):
        time_when(lambda: None, -1.0, "the guard to end")


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_await_until_lets_the_task_that_makes_it_true_run() -> None:
    done: list[str] = []

    async def worker() -> None:
        for _ in range(3):
            await asyncio.sleep(0)
        done.append("stored")

    task = asyncio.create_task(worker())
    assert await await_until(lambda: done, 5.0, step=0) == ["stored"]
    await task


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_await_until_times_out_with_the_same_message() -> None:
    with pytest.raises(TimedOut, match=r"waiting for the server to listen; last value: None$"):
        await await_until(lambda: None, -1.0, "the server to listen")
