"""Pipelined parts: heavy work beside the ticks instead of inside them.

Why. Run in order, a part that takes 80 ms (a pilot's inference on a Raspberry Pi 4) makes a 20 Hz tick take
89 ms: the loop falls to about 11 Hz and everything in it (the controller, recording, the failsafe) slows down
with it. Added with ``pipelined=True`` the part runs in a task of its own: whenever it is free it takes the
newest inputs, computes (a sync ``run`` in a worker thread), and publishes its outputs, which the ticks read as
latest values without waiting. It never queues: a start requested while it is busy is remembered once and served
with the inputs as they are when it is free.

When it starts:

* **at each tick** (default): in its place in the part order, so it sees what the parts before it wrote on that
  tick (the camera's frame);
* **on a new value** (``trigger="cam/image_array"``): the moment that input gets a value with a new origin. A
  source that pushes (a part with ``subscribe(callback)``, like the cameras) writes its value into Memory as
  soon as it exists, not at the next tick, so the pilot starts on the frame the moment it is captured.

Its outputs carry the origin of the inputs it read (not of the time it finished), so ``pilot/throttle@age`` is
the true age of the sensing behind the command, and the stale-command failsafe covers a pilot that dies or falls
behind. Parts added with ``react=True`` downstream of it (``DriveMode``, the actuators), or downstream of a push
source (a command received from the network), also run the moment it publishes, so a new command reaches the
output without waiting for the next tick.

What each mode keeps and loses is in ``docs/control-periods.md``.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from .drive import Drive
    from .plan import Entry

__all__ = ["Pipeline", "TickKicker", "build_pipelines"]

logger = logging.getLogger("asyncdonkey.loop")


class Pipeline:
    """One pipelined part's worker task, its start requests and its counters."""

    def __init__(self, drive: Drive, entry: Entry, react: list[Entry]) -> None:
        self.drive = drive
        self.entry = entry
        self.react = react
        self.name = entry.name
        self.trigger = entry.trigger
        self._kick = asyncio.Event()
        self.busy = False
        self.runs = 0
        self.published = 0
        self.superseded = 0
        self.first_start: float | None = None
        self.last_start = 0.0
        self._last_trigger_origin: float | None = None
        self.task: asyncio.Task[None] | None = None

    # -------------------------------------------------------------------------------------- starting
    def kick(self) -> None:
        if self._kick.is_set():
            self.superseded += 1  # a start still pending is replaced by this newer one: its inputs were skipped
        self._kick.set()

    def new_value(self, origin: float | None) -> None:
        """The trigger input was written: start if its origin is new (a new frame, not the same one again)."""
        if origin is not None and origin == self._last_trigger_origin:
            return
        self._last_trigger_origin = origin
        self.kick()

    # ----------------------------------------------------------------------------------------- worker
    async def main(self) -> None:
        drive = self.drive
        e = self.entry
        d = drive.mem.d
        now = drive.clock.now
        series = e.series
        stated = getattr(e.part, "output_origin", None)
        stated = stated if callable(stated) else None
        while True:
            await self._kick.wait()
            self._kick.clear()
            if not drive.on:
                return
            cond = e.run_condition
            if cond is not None and not d.get(cond):
                continue
            self.busy = True
            t = now()
            if self.first_start is None:
                self.first_start = t
            self.last_start = t
            self.runs += 1
            try:
                args = e.args()
                origin = e.input_origin() if e.input_origin is not None else t
                r = e.call(*args)
                if e.awaits:
                    r = await r
                t_end = now()
                if r is not None and e.store_fixed is not None:
                    if stated is not None:
                        o = stated()
                        origin = origin if o is None else o
                    e.store_fixed(r, origin, t_end)
                    self.published += 1
                    if self.react:
                        await self._react(t_end)
            except asyncio.CancelledError:
                raise
            except Exception as exc:
                t_end = now()
                self._failed(e, exc)
            finally:
                self.busy = False
            series.record(t_end - t)

    async def _react(self, t: float) -> None:
        await run_reactions(self.drive, self.react, self._failed)

    def _failed(self, e: Entry, exc: Exception) -> None:
        self.drive.background_failed(e, exc, "pipelined run()" if e is self.entry else "reacting run()")

    def stats(self, elapsed: float) -> dict[str, float]:
        span = self.last_start - self.first_start if self.first_start is not None else 0.0
        return {
            "runs": self.runs,
            "published": self.published,
            "rate_hz": (self.runs - 1) / span if self.runs > 1 and span > 0 else 0.0,
            "superseded": self.superseded,
        }


async def run_reactions(drive: Drive, entries: list[Entry], failed: Callable[[Entry, Exception], None]) -> None:
    """Run the ``react=True`` parts ``entries`` now, in their add() order (after a pipelined part or a push
    source published): a new command reaches the actuators without waiting for the next tick."""
    d = drive.mem.d
    now = drive.clock.now
    for e in entries:
        cond = e.run_condition
        if cond is not None and not d.get(cond):
            continue
        try:
            args = e.args()
            r = e.call(*args)
            if e.awaits:
                r = await r
            t_end = now()
            if r is not None and e.store is not None:
                e.store(r, args, t_end)
            if e.latency is not None:
                e.latency(t_end)
        except asyncio.CancelledError:
            raise
        except Exception as exc:
            failed(e, exc)


class Reaction:
    """The ``react=True`` parts downstream of a push source, run in a task of their own each time it pushes
    (a start requested while they run is served once more, with the newest values, never queued)."""

    def __init__(self, drive: Drive, entries: list[Entry]) -> None:
        self.drive = drive
        self.entries = entries
        self._kick = asyncio.Event()
        self.runs = 0
        self.task: asyncio.Task[None] | None = None

    def kick(self) -> None:
        self._kick.set()

    async def main(self) -> None:
        drive = self.drive
        while True:
            await self._kick.wait()
            self._kick.clear()
            if not drive.on:
                return
            self.runs += 1
            await run_reactions(drive, self.entries, lambda e, exc: drive.background_failed(e, exc, "reacting run()"))


def react_chain(entries: tuple[Entry, ...], channels: set[str]) -> list[Entry]:
    """The ``react=True`` entries fed, directly or through each other, by ``channels``, in add() order."""
    chain: list[Entry] = []
    channels = set(channels)
    for r in entries:
        if r.react and channels.intersection(i for i in r.inputs if i is not None):
            chain.append(r)
            channels.update(r.outputs)
    return chain


class TickKicker:
    """What the tick calls in a pipelined part's place: mark it dormant when its run condition is false (done
    by the tick itself, from ``run_condition`` and ``outputs``), else start it if it starts on ticks."""

    __slots__ = (
        "args",
        "awaits",
        "call",
        "errors",
        "inputs",
        "is_sync_inline",
        "kicks",
        "latency",
        "name",
        "on_error",
        "outputs",
        "run_condition",
        "store",
    )

    def __init__(self, pipeline: Pipeline) -> None:
        e = pipeline.entry
        self.name = e.name
        self.run_condition = e.run_condition
        self.outputs = e.outputs
        self.inputs = ()
        self.args = _no_args
        self.call: Callable[[], None] = pipeline.kick if pipeline.trigger is None else _nothing
        self.awaits = False
        self.store = None
        self.latency = None
        self.kicks = ()
        self.is_sync_inline = False
        self.on_error = "continue"
        self.errors = 0


def _no_args() -> tuple[()]:
    return ()


def _nothing() -> None:
    return None


def build_pipelines(drive: Drive) -> tuple[tuple[Any, ...], list[Pipeline]]:
    """The tick's entry list (pipelined parts replaced by their kickers) and the drive's pipelines.

    Also wires the triggers: entries whose outputs feed a trigger get ``kicks`` (checked after their store), and
    push sources (parts with ``subscribe``) feeding a trigger or ``react=True`` parts are subscribed for the
    drive.
    """
    entries = drive.entries
    pipelines: list[Pipeline] = []
    tick: list[Any] = []
    for e in entries:
        if not e.pipelined:
            tick.append(e)
            continue
        p = Pipeline(drive, e, react_chain(entries, set(e.outputs)))
        pipelines.append(p)
        tick.append(TickKicker(p))
    by_trigger: dict[str, list[Pipeline]] = {}
    for p in pipelines:
        if p.trigger is not None:
            by_trigger.setdefault(p.trigger, []).append(p)
    for e in entries:
        e.kicks = ()
        if e.pipelined:
            continue
        fed = [(k, p) for k in e.outputs for p in by_trigger.get(k, ())]
        e.kicks = tuple(fed)
        sub = getattr(e.part, "subscribe", None)
        if not callable(sub) or not e.outputs:
            continue
        # a push source: its values go into Memory as they arrive, starting what they trigger and running the
        # react=True parts they feed at once (a camera frame, a command from the network)
        chain = react_chain(entries, set(e.outputs))
        if fed or chain:
            drive.push_sources.append((e, sub, Reaction(drive, chain) if chain else None))
    return tuple(tick), pipelines


def after_store(e: Any, origins: dict[str, float]) -> None:
    """Tell the pipelines triggered by ``e``'s outputs that they were written (called when ``e.kicks``)."""
    for k, p in e.kicks:
        p.new_value(origins.get(k))
