"""Moved to :mod:`asyncdonkey.safety.watchdog`; this old import path keeps working, with a DeprecationWarning."""

from ._moved import alias

alias(__name__, "asyncdonkey.safety.watchdog")
