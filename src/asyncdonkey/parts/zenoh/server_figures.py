"""A pilot server's figures, each named as what it counts: frames, batches, model calls, and the time of each.

Three units are easy to confuse, and a line that mixes them misleads (it once read ``501 calls, batch mean
1.4`` for 686 frames answered by a model of batch 1: it counted batches and called them calls):

* a **frame** is one car's camera frame: *received* (offered to the batcher: the model's frame size, the
  channel contract passed), *too old* (older than the cars' failsafe window when its batch was taken: not
  inferred), *inferred* (in a batch the model answered), *answered* (a command sent back), and among those
  *late* (sent when its frame was already older than the failsafe window: the car's own stale-command stop
  holds the throttle regardless);
* a **batch** is what the server hands the model at once (:class:`.BatchLoop`): its size is in frames, its time
  runs from the batch being taken to its commands;
* a **model call** is one run of the model runtime (:class:`.BatchPilot`): one per batch when the model's batch
  dimension is dynamic, one per *frame* when it is fixed at 1. Only the model knows how many calls a batch
  took, so the count comes from it; a model that does not count its calls (a plain function) leaves the calls
  and their times unknown, never guessed.

:meth:`ServerFigures.of` reads them from the loop, the model and the per-car counters at one moment;
:meth:`ServerFigures.line` is the line ``asyncdonkey pilot-server`` prints every ``--stats-every`` seconds and
at the end.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = ["ServerFigures"]


def _p50_p99_ms(seconds: Iterable[float]) -> tuple[float, float] | None:
    """The median and 99th percentile of ``seconds``, in ms (``None``: no sample)."""
    ms = np.fromiter(seconds, dtype=float) * 1e3
    if not len(ms):
        return None
    return float(np.percentile(ms, 50)), float(np.percentile(ms, 99))


def _times(label: str, p: tuple[float, float] | None) -> str:
    return f"{label} p50 - p99 -" if p is None else f"{label} p50 {p[0]:.2f} ms p99 {p[1]:.2f} ms"


@dataclass(frozen=True, slots=True)
class ServerFigures:
    """The server's totals since it started (times: over the recent 10,000 batches and calls).

    Attributes:
        frames_received: frames offered to the batcher (all cars).
        frames_replaced: frames replaced by a newer one of the same car before a batch took them.
        frames_too_old: frames older than the failsafe window when their batch was taken (not inferred).
        frames_inferred: frames in batches the model answered.
        frames_answered: commands sent.
        answered_late: commands sent when their frame was already older than the failsafe window.
        withheld: commands computed but not sent (the server had stopped answering meanwhile).
        wrong_frames: frames dropped before the batcher for not being the model's frame size.
        batches: batches inferred and answered; failed_batches: batches the model failed on.
        model_calls: calls of the model runtime (``None``: the model does not count them).
        batch_ms, call_ms: p50 and p99 of the time per batch and per model call, in ms (``None``: no sample).
        cars: the per-car counters they were summed from.
    """

    frames_received: int
    frames_replaced: int
    frames_too_old: int
    frames_inferred: int
    frames_answered: int
    answered_late: int
    withheld: int
    wrong_frames: int
    batches: int
    failed_batches: int
    model_calls: int | None
    batch_ms: tuple[float, float] | None
    call_ms: tuple[float, float] | None
    cars: Mapping[str, Mapping[str, int]] = field(default_factory=dict)

    @classmethod
    def of(cls, loop: Any, model: Any, cars: Mapping[str, Mapping[str, int]], *, withheld: int = 0) -> ServerFigures:
        """Read the figures now: ``loop`` a :class:`.BatchLoop`; ``model`` what it infers with (a
        :class:`.BatchPilot` counts its calls in ``calls`` and times them in ``call_s``; anything else: calls
        unknown); ``cars`` the per-car counters (``frames``, ``replaced``, ``too_old``, ``answered``, ``late``,
        ``wrong_frames``, as :meth:`.PilotServer.counters` gives them)."""

        def total(key: str) -> int:
            return sum(int(c.get(key, 0)) for c in cars.values())

        calls = getattr(model, "calls", None)
        call_s = getattr(model, "call_s", None)
        return cls(
            frames_received=total("frames"),
            frames_replaced=total("replaced"),
            frames_too_old=total("too_old"),
            frames_inferred=int(loop.frames),
            frames_answered=total("answered"),
            answered_late=total("late"),
            withheld=int(withheld),
            wrong_frames=total("wrong_frames"),
            batches=int(loop.batches),
            failed_batches=int(loop.errors),
            model_calls=calls if isinstance(calls, int) and not isinstance(calls, bool) else None,
            batch_ms=_p50_p99_ms(list(loop.batch_s)),
            call_ms=_p50_p99_ms(list(call_s)) if call_s is not None and isinstance(calls, int) else None,
            cars={name: dict(c) for name, c in cars.items()},
        )

    @property
    def frames_per_batch(self) -> float:
        """The mean batch size: frames inferred over batches (0 before the first batch)."""
        return self.frames_inferred / self.batches if self.batches else 0.0

    @property
    def frames_per_call(self) -> float | None:
        """Frames inferred over model calls (1.0 for a model of batch 1; ``None``: calls unknown or none)."""
        return self.frames_inferred / self.model_calls if self.model_calls else None

    def line(self) -> str:
        """One line: frames, batches, model calls, then each car's commands over its frames."""
        frames = (
            f"frames {self.frames_received} received, {self.frames_inferred} inferred, {self.frames_answered}"
            f" answered ({self.answered_late} late), {self.frames_too_old} too old, {self.frames_replaced} replaced"
        )
        if self.wrong_frames:
            frames += f", {self.wrong_frames} wrong size"
        if self.withheld:
            frames += f", {self.withheld} withheld"
        failed = f" ({self.failed_batches} failed)" if self.failed_batches else ""
        batches = (
            f"{self.batches} batches{failed}, {self.frames_per_batch:.2f} frames per batch,"
            f" {_times('per batch', self.batch_ms)}"
        )
        if self.model_calls is None:
            calls = "model calls not counted by this model"
        else:
            per_call = self.frames_per_call or 0.0
            calls = (
                f"{self.model_calls} model calls, {per_call:.2f} frames per call, {_times('per call', self.call_ms)}"
            )
        return f"{frames} | {batches} | {calls} | answered/received per car: {self._cars()}"

    def _cars(self) -> str:
        rows = []
        for car, c in self.cars.items():
            row = f"{car} {c.get('answered', 0)}/{c.get('frames', 0)}"
            row += "".join(f" {key} {c[key]}" for key in ("late", "too_old") if c.get(key))
            rows.append(row)
        return "; ".join(rows) or "-"
