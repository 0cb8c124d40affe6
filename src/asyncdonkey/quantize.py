"""Moved to :mod:`asyncdonkey.commands.quantize`; this old import path keeps working, with a DeprecationWarning."""

from ._moved import alias

alias(__name__, "asyncdonkey.commands.quantize")
