"""The CPython internals the virtual clock relies on are all present on this Python, and a change is named."""

import sys
import threading

import pytest

from asyncdonkey.clock import _asyncio_internals as internals
from asyncdonkey.clock import virtual_loop


def test_every_internal_the_virtual_clock_relies_on_is_present():
    found = internals.problems()
    assert found == [], (
        f"Python {sys.version.split()[0]} changed what VirtualClockLoop relies on (see "
        f"asyncdonkey/clock/_asyncio_internals.py): {found}"
    )


def test_a_changed_internal_is_named(monkeypatch):
    monkeypatch.setattr(internals, "_WRAP_FUTURE", (lambda future: None).__code__)
    monkeypatch.setattr(internals, "_UNTIMED_ACQUIRE_LINE", None)  # Condition.wait was rewritten
    found = internals.problems()
    assert any("asyncio.wrap_future" in p for p in found), found
    assert any("threading.Condition.wait" in p for p in found), found


def test_the_loop_refuses_to_start_on_a_python_whose_internals_changed(monkeypatch):
    monkeypatch.setattr(virtual_loop, "_internals_problems", lambda: ("asyncio event loops have no list _scheduled",))
    with pytest.raises(virtual_loop.VirtualClockError, match=r"cannot run on Python .*no list _scheduled"):
        virtual_loop.VirtualClockLoop()


@pytest.mark.realtime
def test_a_thread_blocked_with_and_without_timeout_is_told_apart():
    import time

    forever, timed, release = threading.Event(), threading.Event(), threading.Event()
    threads = [
        threading.Thread(target=forever.wait),
        threading.Thread(target=timed.wait, args=(30,)),
        threading.Thread(target=lambda: release.wait() or time.sleep(0)),
    ]
    for t in threads:
        t.start()
    try:
        time.sleep(0.05)
        frames = sys._current_frames()
        states = [internals.waiting(frames[t.ident]) for t in threads]
    finally:
        forever.set()
        timed.set()
        release.set()
        for t in threads:
            t.join()
    assert states == ["blocked", "timed", "blocked"]


def test_handles_built_field_by_field_match_asyncio_and_a_difference_is_named(monkeypatch):
    real = internals.queue_callback

    def forgets_a_field(loop, callback, args, context):  # as if asyncio's Handle had grown a field
        handle = real(loop, callback, args, context)
        del handle._repr
        return handle

    monkeypatch.setattr(internals, "queue_callback", forgets_a_field)
    found = internals.problems()
    assert found == ["asyncio.Handle has fields the virtual loop does not set as asyncio does: _repr"], found


def test_a_thread_count_that_disagrees_with_threading_is_named(monkeypatch):
    monkeypatch.setattr(internals, "thread_count", lambda: threading.active_count() + 1)
    assert any("threading.active_count() no longer counts" in p for p in internals.problems())


def test_a_timer_cancel_that_differs_from_asyncio_is_named(monkeypatch):
    def forgets_the_count(handle):  # as if asyncio's loop had started to track cancelled timers differently
        handle._cancelled = True
        handle._callback = handle._args = None

    monkeypatch.setattr(internals.SeqTimerHandle, "cancel", forgets_the_count)
    assert any("TimerHandle.cancel does what" in p for p in internals.problems())
