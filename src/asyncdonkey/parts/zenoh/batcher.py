"""Which frames a pilot server infers together: one short window, the newest frame per car, oldest arrival first.

A pilot server (:mod:`.pilot_server`) takes camera frames from many cars and runs its model on several at once.
:class:`FrameBatcher` decides *which* frames go into a call (it does no I/O and reads no clock);
:class:`BatchLoop` runs the batches on the runtime clock. Neither touches the network, so both are tested on the
virtual clock without Zenoh:

* **The window.** The first frame that arrives while nothing is pending opens a window of ``window_s``; when it
  closes, everything pending is one batch. A lone car waits at most one window for its command; cars whose
  frames arrive together share one call.
* **Fairness: one frame per car per batch, the newest.** A car that sends faster than the server answers (or
  floods) replaces its own pending frame (counted in ``replaced``); it never takes a second slot, so every
  other car's frame is in the same batch as the flooder's newest. With ``max_batch`` smaller than the number
  of waiting cars, the frames that arrived first go first and the rest are the next batch, whose window has
  then already closed: no car waits more than one batch behind another.
* **Order by arrival.** A batch lists its frames in the order they arrived (answers go out in that order).
* **Too old to be worth it.** A frame older than the car's failsafe window (``max_age_s``, by its origin: the
  car's capture time carried across the network) when its batch is taken is not inferred (counted in
  ``too_old``): the command would reach a car that has already stopped on it. The car's own stale-command stop
  decides, not the server.
"""

from __future__ import annotations

import asyncio
import collections
import concurrent.futures
import inspect
import logging
import math
from collections.abc import Awaitable, Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

from ...clock import get_clock

__all__ = ["BatchLoop", "CarCounters", "Commands", "Frame", "FrameBatcher"]

logger = logging.getLogger(__name__)


@dataclass(slots=True)
class Frame:
    """One car's frame waiting for the model: ``origin`` is the capture time and ``arrival`` when the server got
    it, both on the server's runtime clock."""

    car: str
    image: Any
    origin: float
    arrival: float


@dataclass(slots=True)
class CarCounters:
    """Per car: frames offered, replaced by a newer one before a batch took them, dropped as ``too_old``, and
    taken into a batch."""

    frames: int = 0
    replaced: int = 0
    too_old: int = 0
    batched: int = 0


@dataclass
class FrameBatcher:
    """Pending frames (at most one per car) and the window that closes them into a batch (module docstring).

    Args:
        window_s: how long the first pending frame waits for others (``0``: a batch as soon as the server
            looks).
        max_age_s: a frame older than this (now minus its origin) when its batch is taken is not inferred.
        max_batch: the most frames in one batch (``None``: no limit).
    """

    window_s: float
    max_age_s: float
    max_batch: int | None = None
    cars: dict[str, CarCounters] = field(default_factory=dict)
    batches: int = 0
    _pending: dict[str, Frame] = field(default_factory=dict)
    _opened: float | None = None

    def __post_init__(self) -> None:
        if not (self.window_s >= 0 and math.isfinite(self.window_s)):
            raise ValueError(f"FrameBatcher: window_s must be a finite number >= 0, got {self.window_s!r}")
        if not (self.max_age_s > 0):
            raise ValueError(f"FrameBatcher: max_age_s must be > 0, got {self.max_age_s!r}")
        if self.max_batch is not None and self.max_batch < 1:
            raise ValueError(f"FrameBatcher: max_batch must be >= 1 or None, got {self.max_batch!r}")

    def offer(self, frame: Frame) -> None:
        """A frame arrived: it replaces the car's pending one (which then counts as ``replaced``)."""
        counters = self.cars.get(frame.car)
        if counters is None:
            counters = self.cars[frame.car] = CarCounters()
        counters.frames += 1
        if self._pending.pop(frame.car, None) is not None:
            counters.replaced += 1
        self._pending[frame.car] = frame  # re-inserted: the dict stays in arrival order
        if self._opened is None:
            self._opened = frame.arrival

    @property
    def pending(self) -> int:
        """Frames waiting (one per car at most)."""
        return len(self._pending)

    def due(self) -> float | None:
        """When the open window closes (``None``: nothing pending)."""
        return None if self._opened is None else self._opened + self.window_s

    def take(self, now: float) -> list[Frame]:
        """The batch at ``now``: the pending frames in arrival order (at most ``max_batch``), the ones older than
        ``max_age_s`` left out and counted. Frames left over stay pending, their window already closed."""
        if not self._pending:
            return []
        frames = list(self._pending.values())
        if self.max_batch is not None and len(frames) > self.max_batch:
            frames, rest = frames[: self.max_batch], frames[self.max_batch :]
        else:
            rest = []
        self._pending = {f.car: f for f in rest}
        self._opened = min(f.arrival for f in rest) if rest else None
        batch = []
        for f in frames:
            counters = self.cars[f.car]
            if now - f.origin > self.max_age_s:
                counters.too_old += 1
                continue
            counters.batched += 1
            batch.append(f)
        if batch:
            self.batches += 1
        return batch

    def counters(self) -> dict[str, dict[str, int]]:
        """``{car: {"frames", "replaced", "too_old", "batched"}}``."""
        return {
            car: {"frames": c.frames, "replaced": c.replaced, "too_old": c.too_old, "batched": c.batched}
            for car, c in self.cars.items()
        }


#: what a model gives for a batch: one ``(angle, throttle)`` per frame, or ``None`` (no command for that frame)
Commands = Sequence[tuple[float, float] | None]


class BatchLoop:
    """The serving loop around a :class:`FrameBatcher`: wait for a frame, wait out its window, infer the batch,
    answer each frame; again. No network here (the pilot server feeds it and sends the answers), so the timing
    is tested on the virtual clock.

    Args:
        batcher: the rules (window, fairness, too old).
        infer: frames → one command (or ``None``) per frame. A plain function runs in the loop's own worker
            thread (a model call holds its thread for milliseconds: never the event loop's); a coroutine
            function is awaited.
        answer: ``answer(frame, command, now)`` for each frame with a command, in the batch's order, on the loop.

    While a batch is being inferred, frames keep arriving (:meth:`offer`); the next batch is taken as soon as
    the call returns if its window has closed by then.

    Figures, each counting one thing (the batch is the loop's unit; how many *model calls* a batch took is the
    model's to count, e.g. :attr:`.BatchPilot.calls`, since a model whose batch is fixed at 1 makes one per frame):

    * :attr:`batches`: batches inferred and answered; :attr:`errors`: batches the model failed on.
    * :attr:`frames`: frames in those batches (``frames / batches`` is the mean batch size, frames per batch).
    * :attr:`batch_sizes`, :attr:`batch_s`: frames and seconds per batch (one ``infer`` from the batch being
      taken to its commands), the recent 10,000.
    """

    def __init__(
        self,
        batcher: FrameBatcher,
        infer: Callable[[Sequence[Any]], Commands | Awaitable[Commands]],
        answer: Callable[[Frame, tuple[float, float], float], None],
    ) -> None:
        self.batcher = batcher
        self.infer = infer
        self.answer = answer
        self.batch_sizes: collections.deque[int] = collections.deque(maxlen=10_000)
        self.batch_s: collections.deque[float] = collections.deque(maxlen=10_000)
        self.batches = 0
        self.frames = 0
        self.errors = 0
        self._executor: concurrent.futures.ThreadPoolExecutor | None = None
        self._wake: asyncio.Event | None = None
        self._stop: asyncio.Event | None = None
        self._stopped = False

    def offer(self, car: str, image: Any, origin: float) -> None:
        """A frame arrived (on the loop's thread): pending until its batch."""
        self.batcher.offer(Frame(car, image, origin, get_clock().now()))
        if self._wake is not None:
            self._wake.set()

    async def serve(self) -> None:
        """Batches until :meth:`stop`."""
        clock = get_clock()
        self._wake, self._stop = asyncio.Event(), asyncio.Event()
        if self._stopped:
            return
        stopping = asyncio.ensure_future(self._stop.wait())
        try:
            while not self._stop.is_set():
                due = self.batcher.due()
                if due is None:
                    self._wake.clear()
                    waking = asyncio.ensure_future(self._wake.wait())
                    await asyncio.wait([waking, stopping], return_when=asyncio.FIRST_COMPLETED)
                    waking.cancel()
                    continue
                if clock.now() < due:
                    await clock.sleep_until(due)
                await self._serve_batch(self.batcher.take(clock.now()))
        finally:
            stopping.cancel()

    async def _serve_batch(self, batch: list[Frame]) -> None:
        if not batch:
            return
        clock = get_clock()
        images = [f.image for f in batch]
        t0 = clock.now()
        try:
            if inspect.iscoroutinefunction(self.infer):
                result = await self.infer(images)
            else:
                if self._executor is None:
                    self._executor = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="pilot-server")
                result = await asyncio.get_running_loop().run_in_executor(self._executor, self.infer, images)
            if len(result) != len(batch):
                raise ValueError(f"the model gave {len(result)} commands for {len(batch)} frames")
        except Exception as exc:
            self.errors += 1
            logger.warning("pilot server: the model failed on a batch of %d (%s): no commands", len(batch), exc)
            return
        now = clock.now()
        self.batch_s.append(now - t0)
        self.batch_sizes.append(len(batch))
        self.batches += 1
        self.frames += len(batch)
        for frame, command in zip(batch, result, strict=True):
            if command is not None:
                self.answer(frame, command, now)

    def stop(self) -> None:
        """End :meth:`serve` (from the loop's thread; before it started: it returns at once)."""
        self._stopped = True
        if self._stop is not None:
            self._stop.set()

    def close(self) -> None:
        """Stop the worker thread (waits for a call in progress)."""
        ex, self._executor = self._executor, None
        if ex is not None:
            ex.shutdown(wait=True)
