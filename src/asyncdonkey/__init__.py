"""asyncdonkey: an asyncio-native robot runtime that runs Donkeycar parts unchanged.

The public core is small: :class:`Vehicle` (the drive loop), :class:`Memory` (named channels),
:class:`Poller` (hardware reads at their own rate off the loop thread) and the clock helpers.
"""

from .clock import Clock, DeadlineWaiter, Schedule, get_clock
from .contracts import REFUSED, Contract, Contracts, ContractViolation, Gate
from .latest import Latest, Sample
from .loop import DriveReport, OutputCountError, PartError, PartSpecError, Vehicle
from .memory import Memory
from .poller import Poller
from .virtual_loop import VirtualClockLoop

__version__ = "0.1.0"

__all__ = [
    "REFUSED",
    "Clock",
    "Contract",
    "ContractViolation",
    "Contracts",
    "DeadlineWaiter",
    "DriveReport",
    "Gate",
    "Latest",
    "Memory",
    "OutputCountError",
    "PartError",
    "PartSpecError",
    "Poller",
    "Sample",
    "Schedule",
    "Vehicle",
    "VirtualClockLoop",
    "__version__",
    "get_clock",
]
