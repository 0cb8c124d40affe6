"""The virtual-clock loop, where it used to live: it is runtime code now, in :mod:`asyncdonkey.virtual_loop`
(``asyncdonkey replay`` drives it). This module re-exports it so existing imports keep working."""

from ..virtual_loop import *  # noqa: F403
from ..virtual_loop import __all__  # noqa: F401
