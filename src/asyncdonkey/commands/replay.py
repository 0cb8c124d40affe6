"""``asyncdonkey replay``: run a recorded drive through a pilot, at the recorded times, and score it.

::

    asyncdonkey replay data/tub_1 --pilot models/pilot.onnx [--csv rows.csv] [--json]

    report = replay("data/tub_1", "models/pilot.onnx", csv_path="rows.csv")
    report.angle_mae, report.throttle_mae, report.rows[0].pilot_angle

A replay is an ordinary :class:`~asyncdonkey.loop.Vehicle` with three parts:

1. a **tub player** that, each tick, sleeps until the next record's time and emits its image and user values
   (``_timestamp_ms`` relative to the first record played; records without an image or user values are
   counted and passed over). It is the one place where recorded values enter the drive, so each of them passes
   the car's :class:`~asyncdonkey.contracts.Gate` there: a record holding a value that breaks its channel's
   contract (a NaN throttle, a string where a number belongs, an image of another dtype or shape) is refused,
   counted per channel and reason, and not played, so every channel keeps its last good value;
2. the **pilot** (a model file loaded with :func:`~asyncdonkey.parts.pilot.load_pilot`: ``.onnx`` or
   ``.tflite``; or any object with ``predict(image) -> (angle, throttle)``, or such a callable), timed in real
   time with :func:`time.perf_counter`;
3. a **scorer** collecting one :class:`ReplayRow` per record.

Why a Vehicle and not a plain loop over the records: the pilot sees frames exactly as it would in a car
(through the drive loop, at the recorded instants on the runtime clock), so a pilot part that looks at the
clock or at ages of channels behaves as it did on the road.

Why the virtual clock: the vehicle runs on :class:`~asyncdonkey.VirtualClockLoop`, where time jumps to
the next record as soon as the current one is done. An hour of driving replays as fast as the CPU runs the
pilot, and every record reaches the pilot at exactly its recorded offset, so two replays produce the same
rows to the bit (the CSV is byte-identical); only the inference times, which are real compute, vary.
``speed=`` replays on a real event loop instead, at that multiple of the recorded pace.

Why the pilot runs inline and not in an executor as in a car: the replay's loop has nothing else to serve, so
offloading would buy nothing and cost a thread hop per frame; the measured times are the pilot's compute alone.

The drive loop's own pacing is turned off (a rate far above any record rate, so every tick is due at once):
the player's sleeps set the pace, which keeps the irregular gaps of a real recording (pauses, dropped
frames, several sessions in one tub).
"""

from __future__ import annotations

import argparse
import asyncio
import csv
import json
import logging
import math
import os
import sys
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..clock import DeadlineWaiter, get_clock
from ..contracts import Contract, Contracts, Gate
from ..errors import AsyncdonkeyError
from ..loop import PartError, Vehicle
from ..options import option, positive_float
from ..parts.tub import Record, Tub, TubError, TubImageError
from .recordings import admit_with_reason, open_recording

__all__ = [
    "CSV_COLUMNS",
    "ReplayError",
    "ReplayReport",
    "ReplayRow",
    "SkippedRecord",
    "add_replay_parser",
    "areplay",
    "replay",
    "replay_main",
]

EXIT_USAGE = 2

CSV_COLUMNS = (
    "index",
    "timestamp_ms",
    "user_angle",
    "pilot_angle",
    "user_throttle",
    "pilot_throttle",
    "angle_err",
    "throttle_err",
    "skipped",
)

#: The drive loop's rate during a replay: far above any recording's rate, so every tick is due at once and
#: the player's sleep until the next record's time is the only pacing.
_UNPACED_HZ = 1e9

#: Channels the replay vehicle uses besides the image and the user values.
_FRESH = "replay/fresh"
_INDEX = "replay/index"
_STAMP = "replay/timestamp_ms"
_AT = "replay/at_s"
_PILOT_OUT = ("pilot/angle", "pilot/throttle")


class ReplayError(AsyncdonkeyError):
    """A replay cannot run or cannot go on; the message is one line naming the tub, model or record."""


@dataclass(frozen=True)
class ReplayRow:
    """One record as the pilot saw it."""

    index: int
    timestamp_ms: int | float
    at_s: float
    """Seconds after the first replayed record at which this record reached the pilot (virtual time, or real
    time with ``speed``); equals ``(timestamp_ms - first timestamp_ms) / 1000`` on the virtual clock."""
    user_angle: float
    pilot_angle: float
    user_throttle: float
    pilot_throttle: float

    @property
    def angle_err(self) -> float:
        return abs(self.pilot_angle - self.user_angle)

    @property
    def throttle_err(self) -> float:
        return abs(self.pilot_throttle - self.user_throttle)

    def csv_fields(self) -> list[str]:
        """The row as CSV text, floats in their shortest exact form (``repr``), so identical runs match byte for
        byte and the file reads back to the very same numbers; the ``skipped`` column is empty."""
        return [
            str(self.index),
            repr(self.timestamp_ms),
            repr(self.user_angle),
            repr(self.pilot_angle),
            repr(self.user_throttle),
            repr(self.pilot_throttle),
            repr(self.angle_err),
            repr(self.throttle_err),
            "",
        ]


@dataclass(frozen=True)
class SkippedRecord:
    """A record that was not scored, and why (a ``skipped`` reason; a corrupt line also says where it is)."""

    index: int | None
    timestamp_ms: int | float | None
    reason: str
    catalog: str | None = None
    line: int | None = None
    detail: str | None = None
    """for a ``refused`` record, the channels and reasons: ``"user/throttle: nan"``"""

    @property
    def why(self) -> str:
        if self.detail is not None:
            return f"{self.reason} ({self.detail})"
        if self.catalog is None:
            return self.reason
        return f"{self.reason} ({self.catalog} line {self.line})"

    def csv_fields(self) -> list[str]:
        """Index, timestamp (when known), empty figures, and the reason in the ``skipped`` column."""
        ts = "" if self.timestamp_ms is None else repr(self.timestamp_ms)
        return ["" if self.index is None else str(self.index), ts, "", "", "", "", "", "", self.why]


@dataclass
class ReplayReport:
    """What a replay measured. Error figures are ``None`` when no record could be scored.

    Everything but ``inference_ms`` and ``real_s`` is identical from one replay of the same tub and pilot on the
    virtual clock to the next.
    """

    tub: str
    pilot: str
    records: int = 0
    """records scored (played through the pilot)."""
    skipped: dict[str, int] = field(default_factory=dict)
    """records passed over, by reason: ``corrupt`` (a catalog line that is not a record: see ``corrupt``),
    ``no_timestamp``, ``no_image``, ``bad_image`` (file missing or not decodable), ``no_user_values`` (missing, or
    not a finite number on a channel without a contract), ``refused`` (a value broke its channel's contract: see
    ``refused``). Deleted records are not played at all."""
    refused: dict[str, dict[str, int]] = field(default_factory=dict)
    """values refused by the replay's gate, ``{channel: {reason: count}}`` (``nan``, ``type``, ``range``,
    ``dtype``, ``shape``...: see ``docs/contracts.md``)."""
    corrupt: list[dict[str, Any]] = field(default_factory=list)
    """where each corrupt record is: ``{"index", "catalog", "line"}`` (the line counted from 1)."""
    angle_mae: float | None = None
    throttle_mae: float | None = None
    angle_max_err: float | None = None
    throttle_max_err: float | None = None
    baseline_angle_mae: float | None = None
    """MAE of a pilot that always steers straight (angle 0): the mean absolute user angle, for context."""
    inference_ms: dict[str, float] = field(default_factory=dict)
    """the pilot's real compute time per frame (``time.perf_counter``): ``avg, 50%, 90%, 99%, max``."""
    replayed_s: float = 0.0
    """seconds of recording replayed: the span of the scored records' ``_timestamp_ms`` (whatever the speed)."""
    real_s: float = 0.0
    """wall-clock seconds the replay took."""
    late_ms_max: float = 0.0
    """worst delay of a record behind its recorded time (0 on the virtual clock unless timestamps go back)."""
    speed: float | None = None
    """``None``: the virtual clock; else the real-time pace multiple."""
    rows: list[ReplayRow] = field(default_factory=list, repr=False)
    skipped_records: list[SkippedRecord] = field(default_factory=list, repr=False)
    """every record counted in ``skipped``, in index order."""

    @property
    def skipped_total(self) -> int:
        return sum(self.skipped.values())

    def as_dict(self) -> dict[str, Any]:
        """The report without the per-record rows (JSON-ready: no NaN, ``None`` for undefined figures)."""
        return {
            "tub": self.tub,
            "pilot": self.pilot,
            "records": self.records,
            "skipped": dict(self.skipped),
            "refused": {ch: dict(reasons) for ch, reasons in self.refused.items()},
            "corrupt": [dict(c) for c in self.corrupt],
            "angle_mae": self.angle_mae,
            "throttle_mae": self.throttle_mae,
            "angle_max_err": self.angle_max_err,
            "throttle_max_err": self.throttle_max_err,
            "baseline_angle_mae": self.baseline_angle_mae,
            "inference_ms": dict(self.inference_ms),
            "replayed_s": self.replayed_s,
            "real_s": self.real_s,
            "late_ms_max": self.late_ms_max,
            "speed": self.speed,
        }

    def write_csv(self, path: str | os.PathLike[str]) -> None:
        """Write one line per record in index order (:data:`CSV_COLUMNS`), ``\\n`` line ends: a scored record
        with its figures and an empty ``skipped``, a skipped one with empty figures and the reason."""
        lines: list[tuple[int, int, list[str]]] = [(row.index, 0, row.csv_fields()) for row in self.rows]
        lines += [(-1 if s.index is None else s.index, 1, s.csv_fields()) for s in self.skipped_records]
        lines.sort(key=lambda t: (t[0], t[1]))
        with open(path, "w", newline="", encoding="utf-8") as f:
            w = csv.writer(f, lineterminator="\n")
            w.writerow(CSV_COLUMNS)
            for _, _, fields in lines:
                w.writerow(fields)

    def format_table(self) -> str:
        """A short human-readable summary."""
        skipped = ", ".join(f"{k} {v}" for k, v in sorted(self.skipped.items())) or "none"
        ratio = f" ({_pace(self.replayed_s / self.real_s)})" if self.real_s > 0 and self.replayed_s > 0 else ""
        clock = "virtual clock" if self.speed is None else f"real time x{self.speed:g}"
        lines = [
            f"replay of {self.tub}",
            f"pilot            {self.pilot}",
            f"records          {self.records} scored, {self.skipped_total} skipped ({skipped})",
        ]
        if self.corrupt:
            shown = ", ".join(f"{c['catalog']} line {c['line']}" for c in self.corrupt[:_CORRUPT_SHOWN])
            more = len(self.corrupt) - _CORRUPT_SHOWN
            lines.append(f"corrupt          {shown}" + (f" and {more} more" if more > 0 else ""))
        if self.refused:
            lines.append(f"refused          {_refusals(self.refused)}")
        lines.append(f"replayed         {self.replayed_s:.1f} s of recording in {self.real_s:.2f} s{ratio}, {clock}")
        if self.records:
            lines += [
                f"angle MAE        {self.angle_mae:.4f}   max {self.angle_max_err:.4f}"
                f"   (always straight: {self.baseline_angle_mae:.4f})",
                f"throttle MAE     {self.throttle_mae:.4f}   max {self.throttle_max_err:.4f}",
                "inference ms     " + "  ".join(f"{k} {v:.3f}" for k, v in self.inference_ms.items()),
            ]
        else:
            lines.append("angle MAE        n/a (no record could be scored)")
        return "\n".join(lines)


# ------------------------------------------------------------------------------------------------ parts
#: corrupt records named in the table (all of them are in the JSON and the CSV)
_CORRUPT_SHOWN = 5


def _refusals(refused: Mapping[str, Mapping[str, int]]) -> str:
    """``user/throttle: nan 2, type 1; cam/image_array: shape 1``"""
    return "; ".join(
        f"{ch}: " + ", ".join(f"{reason} {n}" for reason, n in sorted(reasons.items()))
        for ch, reasons in sorted(refused.items())
    )


def _pace(ratio: float) -> str:
    """Seconds of recording per second of replay: ``128x``, ``9.9x``, ``0.50x`` (a slow one must not read 0x)."""
    return f"{ratio:.{0 if ratio >= 20 else 1 if ratio >= 2 else 2}f}x"


class TubPlayer:
    """Emits one playable record per tick, at its recorded time on the runtime clock.

    Outputs: image, user angle, user throttle, index, ``_timestamp_ms``, seconds since the first record
    played, and ``True``; once the records run out, ``None`` values with ``False`` (so the parts gated on the
    last channel do not run) and the vehicle is asked to stop.

    Every recorded value passes ``gate`` before it is emitted: a file is outside data like any network sample. A
    record with a refused value is not played (skipped as ``refused``), so nothing it holds reaches Memory and
    every channel keeps its last good value.
    """

    def __init__(
        self,
        records: Iterator[Record],
        image_key: str,
        user_keys: Sequence[str],
        speed: float,
        on_end: Callable[[], None],
        gate: Gate | None = None,
    ) -> None:
        self._records = records
        self._image_key = image_key
        self._angle_key, self._throttle_key = user_keys
        self._speed = speed
        self._on_end = on_end
        self.gate = gate if gate is not None else Contracts().gate("replay")
        self.skipped: dict[str, int] = {}
        self.skipped_records: list[SkippedRecord] = []
        self.late_max_s = 0.0
        self._t0: float | None = None  # clock time of the first record played
        self._ts0: float = 0.0
        self._last_at = 0.0
        self._waiter: DeadlineWaiter | None = None  # one OS timer for the waits of every tick

    def _skip(self, reason: str, rec: Record, detail: str | None = None) -> None:
        self.skipped[reason] = self.skipped.get(reason, 0) + 1
        ts = rec.raw.get("_timestamp_ms")
        index = rec.raw.get("_index")
        self.skipped_records.append(
            SkippedRecord(
                index if isinstance(index, int) else None, ts if _is_number(ts) else None, reason, detail=detail
            )
        )

    def _admit(self, values: tuple[tuple[str, Any], ...]) -> tuple[list[Any], str | None]:
        """Each ``(channel, value)`` through the gate (every one, so each refusal is counted): the admitted values,
        and ``None``, or what was refused (``"user/throttle: nan"``)."""
        now = get_clock().now()
        admitted: list[Any] = []
        refused: list[str] = []
        for channel, value in values:
            v, reason = admit_with_reason(self.gate, channel, value, now)
            if reason is not None:
                refused.append(f"{channel}: {reason}")
            admitted.append(v)
        return admitted, ("; ".join(refused) if refused else None)

    def _next(self) -> tuple[Record, Any, float, float, Any] | None:
        """The next playable record and its values; counts the others."""
        for rec in self._records:
            raw = rec.raw
            ts = raw.get("_timestamp_ms")
            if not _is_number(ts):
                self._skip("no_timestamp", rec)
                continue
            ua, ut = raw.get(self._angle_key), raw.get(self._throttle_key)
            if ua is None or ut is None:
                self._skip("no_user_values", rec)
                continue
            if raw.get(self._image_key) is None:
                self._skip("no_image", rec)
                continue
            try:
                image = rec[self._image_key]
            except TubImageError:  # a name leading out of the tub is not passed over
                self._skip("bad_image", rec)
                continue
            (image, ua, ut), refused = self._admit(
                ((self._image_key, image), (self._angle_key, ua), (self._throttle_key, ut))
            )
            if refused is not None:
                self._skip("refused", rec, refused)
                continue
            if not (_is_number(ua) and _is_number(ut)):  # channels without a contract: still numbers to score
                self._skip("no_user_values", rec)
                continue
            if not isinstance(image, np.ndarray):
                self._skip("no_image", rec)
                continue
            return rec, image, float(ua), float(ut), ts
        return None

    async def run(self) -> tuple[Any, ...]:
        nxt = self._next()
        if nxt is None:
            self.shutdown()
            self._on_end()
            return (None, None, None, None, None, None, False)
        rec, image, ua, ut, ts = nxt
        clock = get_clock()
        if self._t0 is None:
            self._t0, self._ts0 = clock.now(), float(ts)
        due = self._t0 + (float(ts) - self._ts0) / 1000.0 / self._speed
        waiter = self._waiter
        if waiter is None:
            waiter = self._waiter = DeadlineWaiter()
        await waiter.wait_until(due)
        now = clock.now()
        self.late_max_s = max(self.late_max_s, now - due)
        return (image, ua, ut, rec.index, ts, now - self._t0, True)

    def shutdown(self) -> None:
        """Release the OS timer of the waits (at the end of the records, and when the drive stops)."""
        waiter, self._waiter = self._waiter, None
        if waiter is not None:
            waiter.close()


class TimedPilot:
    """Calls ``predict(image) -> (angle, throttle)`` inline and keeps its real compute time per frame."""

    def __init__(self, predict: Callable[[np.ndarray], Any], name: str) -> None:
        self._predict = predict
        self.name = name
        self.seconds: list[float] = []

    def run(self, image: np.ndarray, index: int) -> tuple[float, float]:
        t = time.perf_counter()
        try:
            out = self._predict(image)
        except Exception as exc:
            shape = f"{'x'.join(map(str, image.shape))} {image.dtype}"
            raise ReplayError(f"record {index}: pilot {self.name} failed on a {shape} frame: {exc}") from exc
        self.seconds.append(time.perf_counter() - t)
        try:
            angle, throttle = out
            return _scalar(angle), _scalar(throttle)
        except (TypeError, ValueError):
            raise ReplayError(
                f"record {index}: pilot {self.name} returned {out!r}; expected (angle, throttle) numbers"
            ) from None


class Scorer:
    """Collects one :class:`ReplayRow` per record played."""

    def __init__(self) -> None:
        self.rows: list[ReplayRow] = []

    def run(self, index: int, ts: Any, at: float, ua: float, ut: float, pa: float, pt: float) -> None:
        self.rows.append(ReplayRow(index, ts, at, ua, pa, ut, pt))


# ---------------------------------------------------------------------------------------------- replay
def replay(
    tub_path: str | os.PathLike[str],
    pilot: Any,
    *,
    speed: float | None = None,
    csv_path: str | os.PathLike[str] | None = None,
    user_keys: Sequence[str] = ("user/angle", "user/throttle"),
    image_key: str = "cam/image_array",
    contracts: Contracts | Mapping[str, Contract] | None = None,
) -> ReplayReport:
    """Replay the tub at ``tub_path`` through ``pilot`` and compare with the recorded user values.

    ``pilot`` is a model path (``.onnx`` or ``.tflite``, loaded with :func:`~asyncdonkey.parts.pilot.load_pilot`
    and shut down at the end), an object with ``predict(image) -> (angle, throttle)``, or such a callable.
    ``speed=None`` replays on the virtual clock (as fast as the CPU allows, deterministic); a number replays on a
    real event loop at that multiple of the recorded pace. ``csv_path`` also writes the per-record rows.
    ``contracts`` declares what the recorded channels' values may be, beside (or replacing) Donkeycar's defaults;
    a record holding a value that breaks one is refused (``report.refused``) and not played.

    Must be called outside a running event loop (use :func:`areplay` inside one). Raises :class:`ReplayError`
    (bad model, pilot failure, a tub without the channels) and :class:`~asyncdonkey.parts.tub.TubError`
    subclasses (missing tub, not a tub).
    """
    if speed is None:
        from ..clock.virtual_loop import VirtualClockLoop

        runner = asyncio.Runner(loop_factory=VirtualClockLoop)
    else:
        runner = asyncio.Runner()
    with runner:
        return runner.run(
            areplay(
                tub_path,
                pilot,
                speed=speed,
                csv_path=csv_path,
                user_keys=user_keys,
                image_key=image_key,
                contracts=contracts,
            )
        )


async def areplay(
    tub_path: str | os.PathLike[str],
    pilot: Any,
    *,
    speed: float | None = None,
    csv_path: str | os.PathLike[str] | None = None,
    user_keys: Sequence[str] = ("user/angle", "user/throttle"),
    image_key: str = "cam/image_array",
    contracts: Contracts | Mapping[str, Contract] | None = None,
) -> ReplayReport:
    """:func:`replay` on the running loop (a :class:`~asyncdonkey.VirtualClockLoop` for exact times)."""
    if speed is not None and not (isinstance(speed, int | float) and speed > 0 and math.isfinite(speed)):
        raise ValueError(f"replay: speed must be a positive number or None, got {speed!r}")
    user_keys = tuple(user_keys)
    if len(user_keys) != 2:
        raise ValueError(f"replay: user_keys must name the angle and throttle channels, got {list(user_keys)}")
    if csv_path is not None and not Path(csv_path).absolute().parent.is_dir():
        raise ReplayError(f"cannot write CSV {os.fspath(csv_path)!r}: its directory does not exist")
    tub = open_recording(tub_path, image_key)  # a tub directory or an MCAP file
    missing = [k for k in (image_key, *user_keys) if k not in tub.inputs]
    if missing:
        raise ReplayError(f"{tub.base_path}: the tub records no {', '.join(missing)} (it records {tub.inputs})")
    predict, pilot_name, owned = _resolve_pilot(pilot, lambda: _readable_frame_shape(tub, image_key))
    real_start = time.perf_counter()
    try:
        vehicle = Vehicle(contracts=contracts)
        pace = 1.0 if speed is None else float(speed)
        gate = vehicle.contracts.gate("replay")
        player = TubPlayer(tub.records(), image_key, user_keys, pace, vehicle.stop, gate)
        timed = TimedPilot(predict, pilot_name)
        scorer = Scorer()
        angle_key, throttle_key = user_keys
        vehicle.add(
            player,
            outputs=[image_key, angle_key, throttle_key, _INDEX, _STAMP, _AT, _FRESH],
            name="tub player",
        )
        vehicle.add(timed, inputs=[image_key, _INDEX], outputs=list(_PILOT_OUT), run_condition=_FRESH, name="pilot")
        vehicle.add(
            scorer,
            inputs=[_INDEX, _STAMP, _AT, angle_key, throttle_key, *_PILOT_OUT],
            run_condition=_FRESH,
            name="scorer",
        )
        try:
            await vehicle.run(rate_hz=_UNPACED_HZ)
        except PartError as exc:
            cause = exc.__cause__
            if isinstance(cause, ReplayError):
                raise ReplayError(f"{tub.base_path}: {cause}") from cause.__cause__
            if isinstance(cause, TubError):  # the recording's own error names it (an image name leading out)
                raise cause from None
            raise
    finally:
        if owned is not None:
            _shutdown_quietly(owned)
    report = _build_report(tub, pilot_name, speed, scorer.rows, player, timed.seconds)
    report.real_s = time.perf_counter() - real_start
    if csv_path is not None:
        report.write_csv(csv_path)
    return report


def _resolve_pilot(
    pilot: Any, frame_shape: Callable[[], tuple[int, ...] | None]
) -> tuple[Callable[[np.ndarray], Any], str, Any]:
    """``(predict, name, object to shut down or None)`` for a model path, a predictor or a callable.

    A model is loaded for the tub's frame size (``frame_shape()``, the first readable image), so a model that
    does not fit the recorded frames is refused at load with both shapes in the message, before any replay.
    """
    if isinstance(pilot, str | os.PathLike):
        path = Path(pilot)
        if not path.is_file():
            raise ReplayError(f"model {str(path)!r} not found")
        from ..parts.pilot import load_pilot

        shape = frame_shape()
        kwargs: dict[str, Any] = {} if shape is None or len(shape) != 3 else {"image_shape": shape}
        try:
            model_pilot = load_pilot(path, offload=False, **kwargs)
        except (OSError, ValueError, ImportError) as exc:
            raise ReplayError(str(exc)) from exc
        return model_pilot.predict, str(path), model_pilot
    predict = getattr(pilot, "predict", None)
    if callable(predict):
        return predict, type(pilot).__name__, None
    if callable(pilot):
        return pilot, getattr(pilot, "__name__", type(pilot).__name__), None
    raise TypeError(f"replay: pilot must be a model path, an object with predict(image) or a callable; got {pilot!r}")


def _readable_frame_shape(tub: Tub, image_key: str) -> tuple[int, ...]:
    """:func:`_first_frame_shape`, or a one-line error naming the recording when no frame is readable (a model
    loaded for a default shape would blame the model for the recording's damage)."""
    shape = _first_frame_shape(tub, image_key)
    if shape is None:
        raise ReplayError(f"{tub.base_path}: no readable {image_key} frame to load the model for")
    return shape


def _first_frame_shape(tub: Tub, image_key: str) -> tuple[int, ...] | None:
    """The shape of the first readable ``image_key`` image in ``tub`` (``None`` if there is none)."""
    for rec in tub.records():
        if rec.raw.get(image_key) is None:
            continue
        try:
            image = rec[image_key]
        except TubImageError:
            continue
        if isinstance(image, np.ndarray):
            return tuple(int(d) for d in image.shape)
    return None


def _shutdown_quietly(obj: Any) -> None:
    fn = getattr(obj, "shutdown", None)
    if callable(fn):
        try:
            fn()
        except Exception:
            logging.getLogger(__name__).exception("pilot shutdown() failed")


def _build_report(
    tub: Tub,
    pilot_name: str,
    speed: float | None,
    rows: list[ReplayRow],
    player: TubPlayer,
    seconds: list[float],
) -> ReplayReport:
    skipped = dict(player.skipped)
    skipped_records = list(player.skipped_records)
    corrupt = tub.corrupt_records()  # complete now: every record has been read
    if corrupt:
        skipped["corrupt"] = len(corrupt)
        skipped_records += [SkippedRecord(i, None, "corrupt", name, line) for i, name, line in corrupt]
        skipped_records.sort(key=lambda r: -1 if r.index is None else r.index)
    report = ReplayReport(
        tub=str(tub.base_path),
        pilot=pilot_name,
        records=len(rows),
        skipped=dict(sorted(skipped.items())),
        refused={ch: dict(sorted(r.items())) for ch, r in sorted(player.gate.counts().items())},
        corrupt=[{"index": i, "catalog": name, "line": line} for i, name, line in corrupt],
        late_ms_max=player.late_max_s * 1e3,
        speed=None if speed is None else float(speed),
        rows=rows,
        skipped_records=skipped_records,
    )
    if rows:
        ua = np.array([r.user_angle for r in rows], dtype=np.float64)
        pa = np.array([r.pilot_angle for r in rows], dtype=np.float64)
        ut = np.array([r.user_throttle for r in rows], dtype=np.float64)
        pt = np.array([r.pilot_throttle for r in rows], dtype=np.float64)
        angle_err, throttle_err = np.abs(pa - ua), np.abs(pt - ut)
        report.angle_mae = float(angle_err.mean())
        report.throttle_mae = float(throttle_err.mean())
        report.angle_max_err = float(angle_err.max())
        report.throttle_max_err = float(throttle_err.max())
        report.baseline_angle_mae = float(np.abs(ua).mean())
        # recording time, not replay-clock time: with speed=10, 40 s of recording replay in 4 s
        report.replayed_s = (max(float(r.timestamp_ms) for r in rows) - float(rows[0].timestamp_ms)) / 1000.0
    if seconds:
        ms = np.array(seconds) * 1e3
        p50, p90, p99 = np.percentile(ms, [50, 90, 99])
        report.inference_ms = {
            "avg": float(ms.mean()),
            "50%": float(p50),
            "90%": float(p90),
            "99%": float(p99),
            "max": float(ms.max()),
        }
    return report


def _is_number(x: Any) -> bool:
    """A finite number a float can hold (a 400-digit integer is not one: ``math.isfinite`` would raise on it)."""
    if not isinstance(x, int | float) or isinstance(x, bool):
        return False
    try:
        return math.isfinite(x)
    except OverflowError:
        return False


def _scalar(x: Any) -> float:
    """A float from a number or a one-element array (an ONNX output is often ``[[value]]``)."""
    a = np.asarray(x, dtype=np.float64)
    if a.size != 1:
        raise ValueError(f"expected one number, got shape {a.shape}")
    return float(a.reshape(()))


# ------------------------------------------------------------------------------------------------- CLI
def add_replay_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Add the ``replay`` subcommand to the ``asyncdonkey`` parser's subparsers."""
    p = subparsers.add_parser(
        "replay",
        help="run a recorded drive (a tub or an MCAP file) through a pilot at the recorded times and report its error",
        description="Replay a recording's frames (a tub directory, or an MCAP file with the mcap extra) through a "
        "pilot on the virtual clock, at their recorded times, and compare the pilot's angle and throttle with "
        "the recorded user values.",
    )
    p.add_argument(
        "tub",
        metavar="RECORDING",
        help="the recorded drive: a tub directory (data/tub_1) or an .mcap file (data/drive.mcap, mcap extra)",
    )
    p.add_argument(
        "--pilot",
        required=True,
        metavar="MODEL",
        help="the model file to replay: .onnx, or .tflite with the tflite extra, e.g. models/pilot.onnx",
    )
    p.add_argument("--csv", metavar="FILE", default=None, help="write one row per record to FILE (a new CSV file)")
    p.add_argument("--json", action="store_true", help="print the report as JSON instead of a table")
    p.add_argument(
        "--speed",
        type=option(positive_float),
        default=None,
        metavar="FACTOR",
        help="replay in real time at this multiple of the recorded pace, a positive number (default: the "
        "virtual clock, as fast as the CPU allows)",
    )
    p.add_argument(
        "--image-key",
        default="cam/image_array",
        metavar="CHANNEL",
        help="the camera channel the pilot sees (default: %(default)s)",
    )
    p.add_argument(
        "--angle-key",
        default="user/angle",
        metavar="CHANNEL",
        help="the recorded angle to compare with (default: %(default)s)",
    )
    p.add_argument(
        "--throttle-key",
        default="user/throttle",
        metavar="CHANNEL",
        help="the recorded throttle to compare with (default: %(default)s)",
    )
    return p


def replay_main(args: argparse.Namespace) -> int:
    """Run ``asyncdonkey replay``; errors print one line and return 2."""
    loop_logger = logging.getLogger("asyncdonkey.loop")
    level = loop_logger.level
    loop_logger.setLevel(logging.WARNING)  # the replay vehicle's drive report says nothing about the pilot
    try:
        report = replay(
            args.tub,
            args.pilot,
            speed=args.speed,
            csv_path=args.csv,
            user_keys=(args.angle_key, args.throttle_key),
            image_key=args.image_key,
        )
    except (ReplayError, TubError, OSError) as exc:
        print(f"asyncdonkey replay: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    finally:
        loop_logger.setLevel(level)
    if args.json:
        print(json.dumps(report.as_dict(), indent=2))
    else:
        print(report.format_table())
    return 0
