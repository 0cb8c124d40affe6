"""Moved to :mod:`asyncdonkey.commands.zenoh`; this old import path keeps working, with a DeprecationWarning."""

from ..._moved import alias

alias(__name__, "asyncdonkey.commands.zenoh")
