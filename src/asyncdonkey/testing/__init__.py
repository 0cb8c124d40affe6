"""Testing support: a virtual-clock event loop, a pytest plugin and device models for ``asyncdonkey.hw``.

The pytest plugin is registered through the ``pytest11`` entry point, so installing asyncdonkey makes the
``virtual_clock`` marker and fixture available to any project's tests.
"""

from .virtual_loop import (
    VirtualClockDeadlock,
    VirtualClockError,
    VirtualClockLoop,
    VirtualClockStall,
    virtual_loop_factory,
)

__all__ = [
    "VirtualClockDeadlock",
    "VirtualClockError",
    "VirtualClockLoop",
    "VirtualClockStall",
    "virtual_loop_factory",
]
