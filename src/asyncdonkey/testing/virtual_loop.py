"""Moved to :mod:`asyncdonkey.virtual_loop` (runtime code: ``asyncdonkey replay`` drives it; the testing package
re-exports it as ``asyncdonkey.testing.VirtualClockLoop``); this old import path keeps working, with a
DeprecationWarning."""

from .._moved import alias

alias(__name__, "asyncdonkey.virtual_loop")
