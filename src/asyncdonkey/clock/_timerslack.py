"""A thread's timer slack on Linux: how late the kernel may end its sleeps to batch wake-ups.

Every thread has one (50 µs by default, inherited from the thread that made it); ``nanosleep``, ``poll`` and
futex waits may end up to that much after their deadline, while a timerfd's timer fires on time. A poller
thread sleeps with ``time.sleep`` (``clock_nanosleep``), and its reads are meant to be published just before
the drive's tick on a timerfd: with the default slack it woke some 50 µs later than the tick's timer at the
median, and lost that race whenever its read took longer than what was left of its lead.
"""

from __future__ import annotations

import ctypes

from ._libc import libc_function

__all__ = ["exact_sleeps"]

_PR_SET_TIMERSLACK = 29


_PRCTL = libc_function("prctl", (ctypes.c_int, ctypes.c_ulong, ctypes.c_ulong, ctypes.c_ulong, ctypes.c_ulong))


def exact_sleeps() -> bool:
    """Set the calling thread's timer slack to one nanosecond (the least Linux takes; 0 would mean the default).
    Returns whether it was set (False off Linux, or where the call is refused)."""
    if _PRCTL is None:
        return False
    status: int = _PRCTL(_PR_SET_TIMERSLACK, 1, 0, 0, 0)
    return status == 0
