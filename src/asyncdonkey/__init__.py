"""asyncdonkey: an asyncio-native robot runtime that runs Donkeycar parts unchanged.

The public core is small: :class:`Vehicle` (the drive loop), :class:`Memory` (named channels),
:class:`Poller` (hardware reads at their own rate off the loop thread) and the clock helpers.
Everything asyncdonkey raises derives from :class:`AsyncdonkeyError` (the tree: :mod:`asyncdonkey.errors`).
"""

from .clock import Clock, DeadlineWaiter, Schedule, get_clock
from .clock.virtual_loop import VirtualClockError, VirtualClockLoop
from .contracts import REFUSED, Contract, Contracts, ContractViolation, Gate
from .errors import AsyncdonkeyError, ChannelCountError, PartInterrupted, PartTimeoutError
from .extras import MissingExtra
from .latest import Latest, Sample
from .loop import DriveReport, OutputCountError, PartError, PartSpecError, Vehicle
from .memory import Memory
from .poller import Poller
from .safety.process import SafetyProcessError

__version__ = "0.1.0"

__all__ = [
    "REFUSED",
    "AsyncdonkeyError",
    "ChannelCountError",
    "Clock",
    "Contract",
    "ContractViolation",
    "Contracts",
    "DeadlineWaiter",
    "DriveReport",
    "Gate",
    "Latest",
    "Memory",
    "MissingExtra",
    "OutputCountError",
    "PartError",
    "PartInterrupted",
    "PartSpecError",
    "PartTimeoutError",
    "Poller",
    "SafetyProcessError",
    "Sample",
    "Schedule",
    "Vehicle",
    "VirtualClockError",
    "VirtualClockLoop",
    "__version__",
    "get_clock",
]
