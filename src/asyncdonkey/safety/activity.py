"""What the loop thread is doing, as the threads that watch it read it: the watchdog and the signal handler.

Why here. The watchdog (this package) and the signal handler (:mod:`asyncdonkey.core.signals`) read a few fields
of the drive in progress from their own threads. Declared as Protocols below the core, they let the safety
package name what it reads without importing the core, and the core's ``Drive`` satisfies them without knowing
of them.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Protocol

if TYPE_CHECKING:  # types only
    from ..core.plan import Entry

__all__ = ["LoopActivity", "RunningCall"]


class RunningCall(Protocol):
    """What the loop thread is inside (a part's run, or what the tick calls in its place), as the watchdog and the
    signal handler name it: whether it holds the loop thread until it returns."""

    @property
    def name(self) -> str: ...

    @property
    def is_sync_inline(self) -> bool: ...


class LoopActivity(Protocol):
    """What the loop thread is doing, read from other threads (the watchdog, the signal handler).

    ``current`` is the step running now (``None`` between parts), ``part_started`` when it started on the
    runtime clock (``inf`` between parts), ``on`` whether the drive ticks. Read-only here: only the loop thread
    writes them."""

    @property
    def on(self) -> bool: ...

    @property
    def current(self) -> RunningCall | None: ...

    @property
    def part_started(self) -> float: ...

    @property
    def entries(self) -> Sequence[Entry]: ...

    @property
    def stop_grace_s(self) -> float: ...
