"""The C library lookup behind the timerfd (Python < 3.13), the timer slack and the tub's syncfs."""

from __future__ import annotations

import ctypes
import errno
import os
import sys

import pytest

from asyncdonkey.clock._libc import libc_function

linux_only = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the calls looked up are Linux's")


@linux_only
def test_a_function_comes_with_its_signature_and_keeps_errno():
    prctl = libc_function("prctl", (ctypes.c_int, ctypes.c_ulong, ctypes.c_ulong, ctypes.c_ulong, ctypes.c_ulong))
    assert prctl is not None
    ctypes.set_errno(0)
    assert prctl(-1, 0, 0, 0, 0) == -1  # no such option
    assert ctypes.get_errno() == errno.EINVAL
    with pytest.raises(ctypes.ArgumentError):  # the signature converts (and so checks) the arguments
        prctl("not a number", 0, 0, 0, 0)


@linux_only
def test_each_lookup_is_its_own_function_object():
    checked = libc_function("syncfs", (ctypes.c_int,))
    bare = libc_function("syncfs", None, use_errno=False)
    assert checked is not None and bare is not None and checked is not bare
    assert checked.argtypes == (ctypes.c_int,) and bare.argtypes is None  # one's signature is not the other's
    fd = os.open(os.path.dirname(__file__), os.O_RDONLY)
    try:
        assert checked(fd) == 0 and bare(fd) == 0
    finally:
        os.close(fd)


def test_a_missing_function_is_none_for_the_caller_to_fall_back():
    assert libc_function("asyncdonkey_no_such_function", (ctypes.c_int,)) is None
