"""The narrow views of a running drive that the modules around it need, as :class:`typing.Protocol` classes.

Why. The watchdog, the signal handler, shutdown and the pipelines each read a few fields of the drive in
progress. Typed against the whole ``Drive`` (or ``Vehicle``), each had to import the module that imports it,
and the core became one circle of modules. Each now names only what it reads, here, below all of them; the
``Drive`` and the ``Vehicle`` satisfy these protocols without knowing of them.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any, Protocol

if TYPE_CHECKING:  # types only: each of these modules imports this one
    from ..clock import Clock
    from ..memory import Memory
    from ..safety.process import SafetyProcess
    from ..safety.watchdog import Watchdog
    from .drivestate import BackgroundWork
    from .partrun import PartRun
    from .pipeline import Pipeline
    from .plan import Entry, OnError

__all__ = ["LoopActivity", "PipelineHost", "RunningCall", "SafetyHost", "ShutdownScope", "Stoppable", "TickStep"]


class TickStep(Protocol):
    """One step of the tick: what ``Drive._ticks`` reads of each object in its list, and nothing else.

    A part's :class:`~asyncdonkey.core.partrun.PartRun` is a step; so are what the tick calls in a part's place
    (``asyncdonkey.core.pipeline``): a pipelined part's ``TickKicker`` and a guarded part's ``GuardedTick``. Each
    subclasses this protocol, so the step's fields, their types and their slots are declared once, here; each
    class adds only the slots of its own job. The tick reads every field with one attribute lookup on a fast
    local, whatever the step's class: what differs between steps is decided when the drive builds its list
    (``build_pipelines``), never per tick.
    """

    __slots__ = (
        "args",
        "awaits",
        "call",
        "errors",
        "is_sync_inline",
        "kicks",
        "latency",
        "name",
        "on_error",
        "run_condition",
        "store",
        "timeout",
    )

    #: the part's name (reports, errors, the watchdog's and the signal handler's messages)
    name: str
    #: a channel: the step runs only on ticks where it is truthy (``None``: always)
    run_condition: str | None
    #: ``args()``: the call's arguments, read from Memory when the step runs
    args: Callable[[], Sequence[Any]]
    #: what the tick calls with them: the part's method (offloaded, bounded), or a stand-in's
    call: Callable[..., Any]
    #: the call returns an awaitable the drive task awaits; ``is_sync_inline``: it holds the loop thread instead
    awaits: bool
    is_sync_inline: bool
    #: ``store(result, args, now)``: the outputs into Memory (``None``: the step stores nothing itself)
    store: Callable[[Any, Any, float], None] | None
    #: (channel, pipeline) pairs its outputs trigger, told after each store (``after_store``)
    kicks: tuple[tuple[str, Pipeline], ...]
    #: an actuator the loop measures itself: ``latency(end of its call)``
    latency: Callable[[float], None] | None
    #: what a failure does (``"stop"``, ``"continue"``) and how many there were this drive
    on_error: OnError
    errors: int
    #: an awaited call's bound in seconds (``None``: none), which the safety process's heartbeat waits for
    timeout: float | None


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


class Stoppable(Protocol):
    """A vehicle as the signal handler sees it: a stop request, and the drive in progress (or ``None``)."""

    def stop(self, reason: str = ...) -> None: ...

    @property
    def drive(self) -> LoopActivity | None: ...


class ShutdownScope(Protocol):
    """What shutdown takes down: the entries, the background work the drive owns (its tasks, threads and worker
    pool; the parts abandoned are noted there), its watchdog."""

    @property
    def entries(self) -> Sequence[Entry]: ...

    @property
    def loop(self) -> asyncio.AbstractEventLoop: ...

    @property
    def work(self) -> BackgroundWork: ...

    @property
    def watchdog(self) -> Watchdog | None: ...


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

    #: the work beside the ticks: the pipelines' wiring fills its push sources and re-entry guards, a guarded
    #: executor part's calls use its worker pool
    @property
    def work(self) -> BackgroundWork: ...

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
