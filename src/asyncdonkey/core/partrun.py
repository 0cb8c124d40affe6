"""One part in one drive: what a run keeps about a part, apart from the plan ``Vehicle.add()`` made.

A :class:`~asyncdonkey.core.plan.Entry` is the plan decided at ``add()`` and belongs to the vehicle, which can be
driven again and again; it is frozen, so nothing can write it while a car drives. Everything a drive learns or
decides about a part lives in its :class:`PartRun`, made fresh when the drive starts and dropped when it ends: the
errors counted, the timing series the profiler reports, the actuator's latency recorder, the pipelines its outputs
trigger, the re-entry guard that keeps it to one call at a time, and in checked mode its stores with their contract
checks. So a second run starts from the plan as added, and a drive cannot change what the next one does.

Why it also holds copies of the plan's fields the tick reads (``run_condition``, ``args``, ``call``, ...): the tick
walks one list of these objects and reads each field with one attribute lookup, as it did when they were all on
the entry; a run that read the plan through ``run.entry`` would pay a second lookup per field per part per tick.
The copies are the plan's own objects, never changed, except ``store``/``store_fixed``, which checked mode wraps
for this drive only.
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable
from typing import TYPE_CHECKING, Any, Protocol

from .runtypes import Kickable, TickStep

if TYPE_CHECKING:
    from .plan import Entry

__all__ = ["CallGuard", "PartRun"]


class PartRun(TickStep):
    """A part as one drive runs it: the per-run state, beside the plan fields the paths that call it read.

    A :class:`~asyncdonkey.core.runtypes.TickStep` (the fields the tick reads are declared there); its own slots
    are what the pipelines, the reactions and the drive's background work read besides."""

    __slots__ = ("entry", "input_origin", "inputs", "outputs", "reentry_guard", "series", "store_fixed")

    def __init__(self, entry: Entry) -> None:
        #: the plan this run follows (read-only here)
        self.entry = entry
        # the plan's fields each call reads, copied once (module docstring)
        self.name = entry.name
        self.inputs = entry.inputs
        self.outputs = entry.outputs
        self.run_condition = entry.run_condition
        self.on_error = entry.on_error
        self.timeout = entry.timeout
        self.args = entry.args
        self.call = entry.call
        self.awaits = entry.awaits
        self.is_sync_inline = entry.is_sync_inline
        self.input_origin = entry.input_origin
        #: the output stores: the plan's, or (checked mode) wrapped in this drive's contract checks
        self.store = entry.store
        self.store_fixed: Callable[[Any, float, float], None] | None = entry.store_fixed
        # what this run keeps
        #: errors caught (``on_error="continue"``) or that stopped the drive, for ``DriveReport.part_errors``
        self.errors = 0
        #: the profiler's timing series of the part's calls (a column of the tick table, or a pipelined part's runs)
        self.series: Any = None
        #: an actuator the loop measures itself: ``latency(run end)`` records its sensing-to-actuation latency
        self.latency: Callable[[float], None] | None = None
        #: (channel, pipeline) pairs the part's outputs trigger (``asyncdonkey.core.pipeline``)
        self.kicks: tuple[tuple[str, Kickable], ...] = ()
        #: its :class:`~asyncdonkey.core.pipeline.ReentryGuard` when more than one path can be inside its call at once
        self.reentry_guard: CallGuard | None = None


class CallGuard(Protocol):
    """A part's re-entry guard (:class:`~asyncdonkey.core.pipeline.ReentryGuard`) as the paths that call the part
    hold it: declared beside the run it guards, so that the run does not import the module that builds guards
    around it. A path enters (:meth:`enter`), calls through :attr:`call`, then leaves (:meth:`leave`); a reaction
    or the tick uses :meth:`run_stored` (enter, read the inputs, call, store, leave) instead."""

    @property
    def run(self) -> PartRun: ...

    @property
    def call(self) -> Callable[..., Awaitable[Any]]: ...

    async def enter(self) -> bool: ...

    def leave(self) -> None: ...

    async def run_stored(self, kicks: bool = False) -> float | None: ...
