"""Linux ``timerfd`` on ``CLOCK_MONOTONIC``: a file descriptor that becomes readable at an absolute deadline.

Why a timerfd: it takes the deadline in nanoseconds on the very clock ``time.monotonic()`` reads, as an absolute
time (``TFD_TIMER_ABSTIME``), so there is no "sleep for the remaining time" arithmetic to round or race, and
no timer slack is applied to it (``poll``/``epoll`` timeouts, ``nanosleep`` and futex waits get the thread's
50 µs slack; a timerfd's hrtimer fires on time). The event loop watches it like any socket (``add_reader``),
which works on asyncio's selector loops and on uvloop alike, and uvloop's own timers (whole milliseconds) are
bypassed.

Python 3.13 has ``os.timerfd_create`` / ``os.timerfd_settime_ns``; on 3.11 and 3.12 the same two libc calls go
through ``ctypes``. :data:`AVAILABLE` is false where neither exists (not Linux, or a libc without them); callers
then fall back to the loop's timers. Creating one can still fail at run time (a sandbox that forbids the
syscall): :func:`create` raises ``OSError`` then, and the caller falls back the same way.
"""

from __future__ import annotations

import ctypes
import os
from array import array
from collections.abc import Callable

from ._libc import libc_function

__all__ = ["AVAILABLE", "Timerfd"]

CLOCK_MONOTONIC = 1
TFD_TIMER_ABSTIME = 1
TFD_NONBLOCK = os.O_NONBLOCK
TFD_CLOEXEC = getattr(os, "O_CLOEXEC", 0o2000000)


def _libc_functions() -> tuple[Callable[..., int], Callable[..., int], Callable[..., int]] | None:
    """``timerfd_create`` and ``timerfd_settime`` with errno kept, and ``timerfd_settime`` bare: the arming on
    every wait goes through the bare one (no argument conversion, no errno bookkeeping: about a third cheaper)
    and only a failure is repeated through the checked one, for its errno."""
    create = libc_function("timerfd_create", (ctypes.c_int, ctypes.c_int))
    # struct itimerspec is four C longs (time_t and long are both the platform's long on Linux's classic ABIs,
    # 64-bit and 32-bit ARM alike); it is passed as the address of an array('l'), see Timerfd
    settime = libc_function("timerfd_settime", (ctypes.c_int, ctypes.c_int, ctypes.c_void_p, ctypes.c_void_p))
    # called with (int, int, c_void_p, None): nothing left to convert
    bare_settime = libc_function("timerfd_settime", None, use_errno=False)
    if create is None or settime is None or bare_settime is None:
        return None
    return create, settime, bare_settime


_OS_NATIVE = hasattr(os, "timerfd_create") and hasattr(os, "timerfd_settime_ns")
_LIBC = None if _OS_NATIVE else _libc_functions()

#: True where a timerfd can be created at all (Linux with Python ≥ 3.13, or a libc exporting timerfd_*).
AVAILABLE: bool = _OS_NATIVE or _LIBC is not None


class Timerfd:
    """One non-blocking, close-on-exec timerfd on ``CLOCK_MONOTONIC``, armed at absolute deadlines.

    Arming again replaces the previous deadline and clears a pending expiry (the kernel resets the expiry
    count on ``timerfd_settime``), so a stale readiness seen after re-arming reads as "not fired".
    """

    __slots__ = ("_spec", "arm", "arm_every", "fd")

    #: ``arm(deadline_ns)``: fire once when ``CLOCK_MONOTONIC`` reaches ``deadline_ns`` (absolute); 0 disarms.
    #: A plain function held by the instance rather than a method, so a wait costs one Python call, not two.
    arm: Callable[[int], None]
    #: ``arm_every(first_ns, interval_ns)``: fire at ``first_ns`` (absolute) and every ``interval_ns`` after it.
    #: The kernel moves a periodic timer on by itself when it fires, so a job that keeps to the period
    #: re-arms nothing: each wake-up costs a ``read()`` of the expiry count instead of a ``timerfd_settime``,
    #: which also cancels and restarts the kernel's timer (measured about 20 % less CPU per wake-up on a
    #: 2-core VM at 20 Hz, on Python 3.11 and 3.13 alike).
    arm_every: Callable[[int, int], None]

    def __init__(self) -> None:
        if _OS_NATIVE:
            # (os.timerfd_* are Python 3.13's; mypy checks for 3.11, whose os module has none)
            self.fd: int = os.timerfd_create(CLOCK_MONOTONIC, flags=TFD_NONBLOCK | TFD_CLOEXEC)  # type: ignore[attr-defined,unused-ignore]
            fd = self.fd
            settime_ns = os.timerfd_settime_ns  # type: ignore[attr-defined,unused-ignore]

            def arm_native(deadline_ns: int) -> None:
                settime_ns(fd, flags=TFD_TIMER_ABSTIME, initial=deadline_ns)

            def arm_every_native(first_ns: int, interval_ns: int) -> None:
                settime_ns(fd, flags=TFD_TIMER_ABSTIME, initial=first_ns, interval=interval_ns)

            self.arm = arm_native
            self.arm_every = arm_every_native
            return
        if _LIBC is None:
            raise OSError("timerfd is not available on this platform")
        create, settime, bare_settime = _LIBC
        fd = create(CLOCK_MONOTONIC, TFD_NONBLOCK | TFD_CLOEXEC)
        if fd < 0:
            err = ctypes.get_errno()
            raise OSError(err, f"timerfd_create(CLOCK_MONOTONIC): {os.strerror(err)}")
        self.fd = fd
        # one itimerspec {interval sec, nsec; value sec, nsec}, filled in place on every arm: an array item
        # store is much cheaper than a ctypes Structure field, and nothing is allocated per deadline
        spec = array("l", bytes(4 * array("l").itemsize))
        address = spec.buffer_info()[0]
        pointer = ctypes.c_void_p(address)

        def arm_libc(deadline_ns: int) -> None:
            spec[2], spec[3] = divmod(deadline_ns, 1_000_000_000)
            if bare_settime(fd, TFD_TIMER_ABSTIME, pointer, None) != 0 and settime(fd, 1, address, None) != 0:
                err = ctypes.get_errno()
                raise OSError(err, f"timerfd_settime(fd {fd}): {os.strerror(err)}")

        every = array("l", bytes(4 * array("l").itemsize))  # its own itimerspec: arm() leaves the interval 0
        every_address = every.buffer_info()[0]
        every_pointer = ctypes.c_void_p(every_address)

        def arm_every_libc(first_ns: int, interval_ns: int) -> None:
            every[0], every[1] = divmod(interval_ns, 1_000_000_000)
            every[2], every[3] = divmod(first_ns, 1_000_000_000)
            if bare_settime(fd, TFD_TIMER_ABSTIME, every_pointer, None) != 0 and settime(fd, 1, every_address, None):
                err = ctypes.get_errno()
                raise OSError(err, f"timerfd_settime(fd {fd}): {os.strerror(err)}")

        self.arm = arm_libc
        self.arm_every = arm_every_libc
        self._spec = (spec, every)

    def fired(self) -> bool:
        """Consume a pending expiry: True if the timer fired since it was last armed."""
        try:
            os.read(self.fd, 8)
        except BlockingIOError:
            return False
        return True

    def close(self) -> None:
        fd, self.fd = self.fd, -1
        if fd >= 0:
            os.close(fd)
