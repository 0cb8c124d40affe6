"""C library calls that Python's standard library does not wrap, found in one place.

A few Linux system calls matter to the runtime and have no ``os`` function on the Pythons it supports:
``timerfd_create``/``timerfd_settime`` before 3.13 (the drive's deadlines), ``prctl(PR_SET_TIMERSLACK)`` (a
poller thread's exact wake-ups) and ``syncfs`` (a tub's sync points). Each is reached through ``ctypes``; this
module finds the C library once, loads it at most twice (with and without ``errno`` saving, which ``ctypes``
decides per library handle, not per function) and hands out each function with its C signature set.

Every lookup answers ``None`` where the call does not exist: another OS, a C library without it, or one that
cannot be loaded. Callers then take their documented fallback.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import sys
from collections.abc import Callable, Sequence
from typing import Any

__all__ = ["libc_function"]


@functools.cache
def _library(use_errno: bool) -> ctypes.CDLL | None:
    if not sys.platform.startswith("linux"):
        return None
    try:
        # None (the process's own symbols, libc among them) where the C library's file name cannot be found
        return ctypes.CDLL(ctypes.util.find_library("c") or None, use_errno=use_errno)
    except OSError:
        return None


def libc_function(
    name: str,
    argtypes: Sequence[Any] | None,
    restype: Any = ctypes.c_int,
    *,
    use_errno: bool = True,
) -> Callable[..., Any] | None:
    """The C library's function ``name`` with the given signature, or None where there is none.

    ``argtypes=None`` leaves the arguments unconverted: the caller passes only ints, ``None`` and ``c_void_p``
    objects, and each call skips the conversion (a timer armed for every wait). ``use_errno=False``
    skips saving ``errno`` after each call too; a caller that needs the error of a failed call repeats it
    through a checked twin. Each call returns a function object of its own, so two callers never share a
    signature.
    """
    library = _library(use_errno)
    if library is None:
        return None
    try:
        fn = library[name]  # (not getattr: the library's attribute cache would hand every caller one object)
    except AttributeError:
        return None
    if argtypes is not None:
        fn.argtypes = tuple(argtypes)
    fn.restype = restype
    return fn
