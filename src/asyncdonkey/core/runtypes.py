"""The narrow views of a running drive that the modules around it need, as :class:`typing.Protocol` classes.

Why. The watchdog, the signal handler, shutdown and the pipelines each read a few fields of the drive in
progress. Typed against the whole ``Drive`` (or ``Vehicle``), each had to import the module that imports it,
and the core became one circle of modules. Each now names only what it reads, here, below all of them; the
``Drive`` and the ``Vehicle`` satisfy these protocols without knowing of them.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import threading
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any, Protocol

if TYPE_CHECKING:  # types only: each of these modules imports this one
    from ..clock import Clock
    from ..memory import Memory
    from ..safety.process import SafetyProcess
    from ..safety.watchdog import Watchdog
    from .partrun import PartRun
    from .pipeline import Reaction, ReentryGuard
    from .plan import Entry

__all__ = ["LoopActivity", "PipelineHost", "RunningCall", "SafetyHost", "ShutdownScope", "Stoppable"]


class RunningCall(Protocol):
    """What the loop thread is inside (a part's run, or what the tick calls in its place), as the watchdog and the
    signal handler name it: whether it holds the loop thread until it returns."""

    @property
    def name(self) -> str: ...

    @property
    def is_sync_inline(self) -> bool: ...


class LoopActivity(Protocol):
    """What the loop thread is doing, read from other threads (the watchdog, the signal handler).

    ``current`` is the entry running now (``None`` between parts), ``part_started`` when it started on the
    runtime clock (``inf`` between parts). Read-only here: only the loop thread writes them."""

    @property
    def current(self) -> RunningCall | None: ...

    @property
    def part_started(self) -> float: ...

    @property
    def entries(self) -> Sequence[Entry]: ...

    @property
    def stop_grace_s(self) -> float: ...


class Stoppable(Protocol):
    """A vehicle as the signal handler sees it: a stop request, and the drive in progress (or ``None``)."""

    def stop(self, reason: str = ...) -> None: ...

    @property
    def drive(self) -> LoopActivity | None: ...


class ShutdownScope(Protocol):
    """What shutdown takes down: the entries, the background work the drive owns, its watchdog."""

    @property
    def entries(self) -> Sequence[Entry]: ...

    @property
    def loop(self) -> asyncio.AbstractEventLoop: ...

    @property
    def tasks(self) -> Sequence[tuple[Entry, asyncio.Task[Any]]]: ...

    @property
    def threads(self) -> Sequence[tuple[Entry, threading.Thread]]: ...

    #: shut down and dropped (set to ``None``) by shutdown
    executor: concurrent.futures.ThreadPoolExecutor | None

    @property
    def watchdog(self) -> Watchdog | None: ...

    @property
    def abandoned(self) -> list[str]: ...


class PipelineHost(Protocol):
    """What the pipelines and reactions use of the drive they run beside (``runs``: each part's
    :class:`~asyncdonkey.core.partrun.PartRun` for this drive, in add() order)."""

    @property
    def runs(self) -> Sequence[PartRun]: ...

    @property
    def loop(self) -> asyncio.AbstractEventLoop: ...

    @property
    def clock(self) -> Clock: ...

    @property
    def mem(self) -> Memory: ...

    @property
    def on(self) -> bool: ...

    #: set by the pipelines' wiring (``guard_entries``)
    reentry_guards: list[ReentryGuard]

    @property
    def push_sources(self) -> list[tuple[PartRun, Callable[..., Any], Reaction | None]]: ...

    def get_executor(self) -> concurrent.futures.ThreadPoolExecutor: ...

    def background_failed(self, e: PartRun, exc: BaseException, what: str = ...) -> None: ...


class SafetyHost(LoopActivity, Protocol):
    """A drive as its safety attachment (``asyncdonkey.safety.attach``) sees it: the parts' runs, the clock, the
    channels' origins, the stop request the safety process may make, and the watchdog and safety process it
    attaches (and the drive reports on)."""

    @property
    def runs(self) -> Sequence[PartRun]: ...

    @property
    def clock(self) -> Clock: ...

    @property
    def mem(self) -> Memory: ...

    #: set by the attachment: the in-process watchdog (``None``: none runs)
    watchdog: Watchdog | None
    #: set by the attachment: the safety process (``None``: none runs)
    safety_process: SafetyProcess | None

    def request_stop(self, reason: str = ...) -> None: ...
