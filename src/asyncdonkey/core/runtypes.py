"""The narrow views of a running drive that the modules around it need, as :class:`typing.Protocol` classes.

Why. The watchdog, the signal handler, shutdown, the safety attachment and the pipelines each read a few fields
of the drive in progress. Typed against the whole ``Drive`` (or ``Vehicle``), each had to import the module that
imports it, and the core became one circle of modules. Each now names only what it reads; the ``Drive`` and the
``Vehicle`` satisfy these protocols without knowing of them. The views that several modules share are here, below
all of them, and import nothing of the drive (:mod:`.plan`'s types only), so that no circle closes even through
imports for the type checker; a view only one module uses lives with it (``ShutdownScope`` in
:mod:`.shutdown`, ``PipelineHost`` in :mod:`.pipeline`, ``SafetyHost`` in :mod:`asyncdonkey.safety.attach`), and
what the threads that watch the loop read of it (``LoopActivity``, ``RunningCall``) in
:mod:`asyncdonkey.safety.activity`, below the core.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any, Protocol

if TYPE_CHECKING:  # types only
    from ..safety.activity import LoopActivity
    from .plan import OnError

__all__ = ["Kickable", "Stoppable", "TickStep"]


class Kickable(Protocol):
    """What a step's outputs trigger (a pipeline started by a new value: ``asyncdonkey.core.pipeline.Pipeline``):
    told after each store that the channel got a value sensed at ``origin``."""

    def new_value(self, origin: float | None) -> None: ...


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
    kicks: tuple[tuple[str, Kickable], ...]
    #: an actuator the loop measures itself: ``latency(end of its call)``
    latency: Callable[[float], None] | None
    #: what a failure does (``"stop"``, ``"continue"``) and how many there were this drive
    on_error: OnError
    errors: int
    #: an awaited call's bound in seconds (``None``: none), which the safety process's heartbeat waits for
    timeout: float | None


class Stoppable(Protocol):
    """A vehicle as the signal handler sees it: a stop request, and the drive in progress (or ``None``)."""

    def stop(self, reason: str = ...) -> None: ...

    @property
    def drive(self) -> LoopActivity | None: ...
