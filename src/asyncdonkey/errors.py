"""The errors of the drive loop, under one root so a user can catch everything asyncdonkey raises.

:class:`AsyncdonkeyError` is the root. Each error also keeps the standard-library base a user would reach for
first (``ValueError`` for a bad argument, ``RuntimeError`` for a failure while driving), so code written
against Donkeycar or the standard library keeps catching what it caught before.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from .drive_report import DriveReport

__all__ = [
    "AsyncdonkeyError",
    "ChannelCountError",
    "OutputCountError",
    "PartError",
    "PartInterrupted",
    "PartSpecError",
    "PartTimeoutError",
]


class AsyncdonkeyError(Exception):
    """Root of asyncdonkey's own errors."""


class PartSpecError(AsyncdonkeyError, ValueError, AssertionError):
    """``Vehicle.add`` was given something that cannot run; the message names the part and the argument.

    Also an ``AssertionError``: Donkeycar's ``Vehicle.add`` asserts on a bare-string ``inputs`` and a non-bool
    ``threaded``, and its tests (and user code) expect that type.
    """


class OutputCountError(AsyncdonkeyError, ValueError):
    """A part returned a value that does not unpack into its declared outputs."""


class ChannelCountError(AsyncdonkeyError, IndexError, ValueError):
    """A multi-channel write to ``Memory`` (``put``, ``mem[a, b] = ...``) got fewer values than channels.

    Also an ``IndexError``, which Donkeycar's ``Memory`` raises in that case, and a ``ValueError``.
    """


class PartTimeoutError(AsyncdonkeyError, TimeoutError):
    """An awaited part did not return within the ``timeout`` given to ``Vehicle.add``."""


class PartError(AsyncdonkeyError, RuntimeError):
    """A part failed while driving. ``part`` names it, ``tick`` is the loop count it failed on (0-based).

    ``report`` is the :class:`~asyncdonkey.loop.DriveReport` of the drive the failure ended (filled in once
    the car has been shut down), so a caller catching the error still gets the timing of the whole drive.
    """

    def __init__(self, part: str, tick: int | None, message: str) -> None:
        where = f" on tick {tick}" if tick is not None else " in its background task"
        super().__init__(f"part {part!r} failed{where}: {message}")
        self.part = part
        self.tick = tick
        self.report: DriveReport | None = None


class PartInterrupted(BaseException):
    """Raised inside a sync part that still held the loop thread after a stop request's grace.

    A ``BaseException`` (like ``KeyboardInterrupt``), not an ``Exception``, so a part's ``except Exception``
    does not swallow it; the drive loop catches it, counts it against the part and goes on stopping.
    """
