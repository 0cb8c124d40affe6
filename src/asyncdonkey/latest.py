"""Latest-value cells: how background producers hand data to the tick without making it wait.

A producer (a hardware poller, a camera thread, a serial reader) calls :meth:`Latest.publish`; the tick reads
:attr:`Latest.sample`. Publishing swaps one attribute to a new immutable :class:`Sample`, which is atomic
under the GIL, so readers in other threads never see a value paired with the wrong timestamp.

A :class:`Sample` is a named tuple rather than a frozen dataclass: a producer thread builds one per value right
after waking up, when every line of Python is at its most expensive (cold caches), and :meth:`Latest.publish`
builds it with ``tuple.__new__`` alone, in C, where a frozen dataclass runs an ``__init__`` that sets each field
through ``object.__setattr__``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Generic, NamedTuple, TypeVar

__all__ = ["Latest", "Sample"]

T = TypeVar("T")


class Sample(NamedTuple, Generic[T]):
    """One published value, when it was taken (runtime clock, seconds) and its sequence number (1, 2, ...).

    Immutable; being a tuple it also unpacks (``value, timestamp, seq = sample``) and compares field by field.
    """

    value: T
    timestamp: float
    seq: int

    def age(self, now: float) -> float:
        """Seconds since this sample was taken, on the same clock as ``now``."""
        return now - self.timestamp


_new_sample = tuple.__new__  # Sample's fields in one C call, without the generated Python __new__


class Latest(Generic[T]):
    """Holds the newest :class:`Sample` of a stream. Readers never block; staleness is measurable."""

    __slots__ = ("_subscribers", "sample")

    def __init__(self) -> None:
        self.sample: Sample[T] | None = None
        self._subscribers: tuple[Callable[[T, float], None], ...] = ()

    def publish(self, value: T, timestamp: float) -> Sample[T]:
        """Make ``value``, taken at ``timestamp`` (runtime clock), the newest sample and tell the subscribers.

        One producer per cell: the sequence number is the previous sample's plus one. (A hardware poller's
        thread does the same inline, see ``Poller._poll_blocking``: keep the two in step.)
        """
        prev = self.sample
        sample = self.sample = _new_sample(Sample, (value, timestamp, 1 if prev is None else prev.seq + 1))
        subscribers = self._subscribers
        if subscribers:
            for callback in subscribers:
                callback(value, timestamp)
        return sample

    def subscribe(self, callback: Callable[[T, float], None]) -> Callable[[], None]:
        """Call ``callback(value, timestamp)`` on every publish, in the publishing thread (keep it quick and
        thread-safe: hand the value to the event loop with ``call_soon_threadsafe``). Returns the unsubscriber."""
        self._subscribers = (*self._subscribers, callback)

        def unsubscribe() -> None:
            self._subscribers = tuple(c for c in self._subscribers if c is not callback)

        return unsubscribe

    @property
    def value(self) -> T | None:
        s = self.sample
        return None if s is None else s.value

    def age(self, now: float) -> float:
        """Seconds since the newest sample; ``inf`` before the first."""
        s = self.sample
        return math.inf if s is None else now - s.timestamp
