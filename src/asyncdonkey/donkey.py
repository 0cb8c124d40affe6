"""Moved to :mod:`asyncdonkey.commands.donkey`; this old import path keeps working, with a DeprecationWarning."""

from ._moved import alias

alias(__name__, "asyncdonkey.commands.donkey")
