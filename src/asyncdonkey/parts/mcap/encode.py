"""From a tick's channels and timing to Foxglove messages: one encoder for the MCAP file and the live server.

:class:`TickEncoder` turns one recorded tick (a :class:`TickSnapshot`) into ``(channel, message bytes,
log_time_ns, publish_time_ns)``. It runs on a writer thread, never on the drive loop's. Both sinks, the MCAP
file (:mod:`.sink`) and the WebSocket server (:mod:`.live`), use it, so the file and the live view carry the
same topics, schemas and bytes.

**Topics.** A Memory channel ``cam/image_array`` becomes topic ``/cam/image_array``. The loop's own timing is
on ``/asyncdonkey/tick``, ``/asyncdonkey/parts`` and ``/asyncdonkey/latency`` (see :data:`TICK_TOPIC`).

**Timing, sample for sample.** The profiler keeps its samples in rings; the tick only notes how many each series
had (:class:`TimingLayout`, :meth:`TimingLayout.capture`), and the writer thread emits every sample from where it
left off up to that count, each exactly once: several in one tick when an actuator acted twice between recorder
runs or when the writer fell behind, none when there was none. So a recording holds the drive's timing as the
profiler measured it, whenever the writer gets to it; a sample that left the ring before the writer read it is
counted in :attr:`TickEncoder.timing_dropped` (and in each tick message), never silently lost.

**Schemas.** A value's kind is decided by its first value (or by ``kinds={channel: kind}``):

* ``image``: a uint8 HxWx3 RGB (or HxW grey) array → ``foxglove.CompressedImage`` (protobuf), JPEG-encoded
  exactly as the tub writer encodes it (OpenCV, quality 75 by default), so a frame read back from either is
  the same array;
* ``laserscan``: an object with ``angles`` (degrees, clockwise as the RPLidar reports them) and
  ``distances`` (mm), like :class:`~asyncdonkey.hw.rplidar.Scan` → ``foxglove.LaserScan`` (protobuf): ranges in
  metres on 1° bins counter-clockwise from the front (REP-103 convention), 0 for bins without a return;
* ``json``: everything else (numbers, booleans, strings, lists and small arrays, dicts) → a JSON message
  ``{"value": ..., "age_ms": ...}`` with a JSON schema named ``asyncdonkey.<Type>``; ``age_ms`` is how old the
  sensing behind the value was when the tick recorded it (``now - origin``), so ages can be plotted;
* ``skip``: not recorded.

Each camera frame also gets ``<topic>/steering`` (``foxglove.ImageAnnotations``): the user's and the pilot's
steering drawn over the image. A latitude/longitude channel pair (``gps/latitude``, ``gps/longitude`` by
default) also yields ``foxglove.LocationFix`` on ``/gps/fix``, so the Map panel shows the track.

**Times.** ``log_time`` is when the tick recorded the value, ``publish_time`` (and the ``timestamp`` of the
Foxglove schemas) the value's origin: when the sensing behind it happened (``mem.origins``). Both are runtime-clock
times mapped to nanoseconds by :class:`TimeMap`: a wall-clock anchor taken once, when the first tick is
recorded, plus the runtime clock's progress since then. So timestamps are Unix-epoch nanoseconds that never jump
with NTP during a drive, and on the virtual clock they advance with simulated time.
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from ...core.profiler import TableSeries
from ..tub.encode import make_converter

__all__ = [
    "KINDS",
    "LATENCY_TOPIC",
    "PARTS_TOPIC",
    "TICK_TOPIC",
    "ChannelSpec",
    "TickEncoder",
    "TickSnapshot",
    "TimeMap",
    "TimingLayout",
    "topic_for",
]

logger = logging.getLogger(__name__)

KINDS = ("image", "laserscan", "json", "skip")
TICK_TOPIC = "/asyncdonkey/tick"
"""One message per ended tick, stamped with the tick's start: ``tick`` (its number, from 1), ``lateness_ms`` (its
start minus its deadline), ``duration_ms`` and ``overrun_ms`` (its own), the drive's ``overruns`` and
``skipped_deadlines`` counts after it ended (``None`` for a tick whose own recorder run was dropped: they are not
known), and ``timing_dropped``, the samples of the recording so far that left the profiler's window before the
writer read them. Written when the next tick records (the current tick has not ended then), and for the last
tick when the recorder shuts down. (Files written before ``timing_dropped`` existed carry the *previous* tick's
``duration_ms`` and ``overrun_ms`` in each message; the report reads both.)"""
PARTS_TOPIC = "/asyncdonkey/parts"
"""``{part name: ms}``, stamped when the recorder ran: the part runs completed since the last message, each
exactly once. Parts run in the tick report each ended tick's run (whether before or after the recorder); a
pipelined part reports each of its runs; when a part has several new runs, the k-th message of the tick holds
its k-th run."""
LATENCY_TOPIC = "/asyncdonkey/latency"
"""``{actuator name: ms}``, stamped when the recorder ran: every sensing-to-actuation latency sample since the
last message, one message per sample index as for :data:`PARTS_TOPIC`."""
GPS_TOPIC = "/gps/fix"


def topic_for(channel: str) -> str:
    """The Foxglove topic of a Memory channel: a leading ``/`` added (``cam/image_array`` → ``/cam/image_array``)."""
    return channel if channel.startswith("/") else "/" + channel


@dataclass(frozen=True)
class ChannelSpec:
    """A topic with its schema, as both sinks register it."""

    topic: str
    schema_name: str
    schema_encoding: str  # "protobuf" or "jsonschema"
    schema_data: bytes
    message_encoding: str  # "protobuf" or "json"


@dataclass(frozen=True)
class TimeMap:
    """Runtime-clock seconds ↔ Unix nanoseconds: ``ns = wall_anchor_ns + (t - clock_anchor_s) * 1e9``.

    Taken once per recording (the wall clock is read once, at the anchor), so the mapping is linear and exact
    to the nanosecond over a drive; the anchor is saved in the file's ``asyncdonkey.clock`` metadata record so
    a reader can get runtime-clock times back (:meth:`to_clock`).

    ``resolution_ns`` is the clock's step: a tub's clock counts whole milliseconds (``1_000_000``), and times
    are then rounded to that step before they are scaled, in integers, so a millisecond stamp maps to exactly
    ``wall_anchor_ns + ms * 1_000_000`` however far from the anchor (in floats, seconds since 1970 keep only a
    quarter of a microsecond, and ``(t - anchor) * 1e9`` drifts off the millisecond by nanoseconds months out).
    """

    clock_anchor_s: float
    wall_anchor_ns: int
    clock: str = "monotonic"  # or "virtual", "tub"
    resolution_ns: int = 1

    def to_ns(self, t: float) -> int:
        step = self.resolution_ns
        if step == 1:
            return self.wall_anchor_ns + round((t - self.clock_anchor_s) * 1e9)
        return self.wall_anchor_ns + round((t - self.clock_anchor_s) * (1e9 / step)) * step

    def to_clock(self, ns: int) -> float:
        return self.clock_anchor_s + (ns - self.wall_anchor_ns) / 1e9

    def as_metadata(self) -> dict[str, str]:
        out = {
            "clock_anchor_s": repr(self.clock_anchor_s),
            "wall_anchor_ns": str(self.wall_anchor_ns),
            "clock": self.clock,
        }
        if self.resolution_ns != 1:
            out["resolution_ns"] = str(self.resolution_ns)
        return out

    @classmethod
    def from_metadata(cls, data: Mapping[str, str]) -> TimeMap:
        return cls(
            float(data["clock_anchor_s"]),
            int(data["wall_anchor_ns"]),
            data.get("clock", "monotonic"),
            int(data.get("resolution_ns", "1")),
        )


class TimingLayout:
    """Which timing series of a profiler a tick's snapshot counts, and how (built on the loop thread once per
    drive, and again if a series is added).

    The parts run in the tick share the drive's :class:`~asyncdonkey.core.profiler.TickTable`: their sample counts
    follow from its committed row count, read once. Every other series (a pipelined part, an actuator's
    latency) has its count read in :meth:`capture`. So noting "how far each series had got at this tick"
    costs the tick one attribute read plus one per such series, and the writer thread later reads the samples
    themselves, by number, from the rings.
    """

    __slots__ = ("counted", "profiler", "series", "size", "table")

    def __init__(self, profiler: Any) -> None:
        self.profiler = profiler
        parts, latency = dict(profiler.parts), dict(profiler.latency)
        self.size = len(parts) + len(latency)
        tick = profiler.tick
        self.table = tick.table if isinstance(tick, TableSeries) else None
        self.series: list[tuple[str, str, Any]] = [(PARTS_TOPIC, n, s) for n, s in parts.items()]
        self.series += [(LATENCY_TOPIC, n, s) for n, s in latency.items()]
        self.counted = [s for _, _, s in self.series if not self._from_rows(s)]
        """the series whose count :meth:`capture` reads, in :attr:`series` order"""

    def _from_rows(self, s: Any) -> bool:
        return isinstance(s, TableSeries) and s.table is self.table and not s.running

    def current(self, profiler: Any) -> bool:
        """Still the layout of ``profiler``'s series (no series added since)?"""
        return profiler is self.profiler and self.size == len(profiler.parts) + len(profiler.latency)

    def capture(self) -> tuple[int, list[int]]:
        """(ticks ended, the counted series' sample counts) now; for the loop thread."""
        table = self.table
        rows = table.rows if table is not None else self.profiler.tick.count
        return rows, [s.count for s in self.counted]

    def counts(self, rows: int, counted: Sequence[int]) -> list[int]:
        """Every series' sample count (in :attr:`series` order) from a :meth:`capture`."""
        it = iter(counted)
        return [s.count_at(rows) if self._from_rows(s) else next(it) for _, _, s in self.series]


class TickSnapshot(NamedTuple):
    """What ``run()`` hands over for one tick: references and small dict copies, never copies of the values.

    The timing is not copied in the tick, only counted: how many ticks had ended and how many samples each
    timing series had (:meth:`TimingLayout.capture`). The writer thread reads those samples from the
    profiler's rings itself (:meth:`~asyncdonkey.core.profiler.Series.at`), by number, so that each lands in the
    tick that took it, exactly once, however far behind the writer is.
    """

    t: float
    """runtime-clock time at which the tick recorded"""
    values: dict[str, Any]
    origins: dict[str, float]
    ticks: int
    """ticks ended in this drive when the recorder ran (the current one has not)"""
    timing: TimingLayout | None
    """the drive's timing series (``None``: no timing)"""
    overruns: int | None
    """the drive's overrun count when the recorder ran"""
    skipped: int | None
    """the drive's skipped-deadline count when the recorder ran"""
    counts: Sequence[int] = ()
    """the sample counts of ``timing.counted`` when the recorder ran"""


class TickEncoder:
    """Encodes ticks into messages, registering each channel's kind on its first value (see module docstring).

    Args:
        channels: the Memory channels to record (``None``: all of them).
        every_tick: record every channel each tick; default records a channel when it changed: a new value
            (another object) or a new origin (the same value sensed again).
        kinds: ``{channel: kind}`` overrides (``"image"``, ``"laserscan"``, ``"json"``, ``"skip"``).
        gps: the (latitude, longitude) channels for ``/gps/fix``, or ``None``.
        jpeg_quality: JPEG quality of ``image`` channels.
        timing: record the loop's timing topics.
        steering: angle channels drawn over each camera frame (``<image topic>/steering``,
            ``foxglove.ImageAnnotations``): a line from the bottom centre, full left/right at ``±1`` drawn
            ``steering_max_deg`` from vertical; the first channel green, the second magenta.
    """

    def __init__(
        self,
        channels: Sequence[str] | None = None,
        *,
        every_tick: bool = False,
        kinds: Mapping[str, str] | None = None,
        gps: tuple[str, str] | None = ("gps/latitude", "gps/longitude"),
        jpeg_quality: int = 75,
        timing: bool = True,
        steering: Sequence[str] = ("user/angle", "pilot/angle"),
        steering_max_deg: float = 45.0,
    ) -> None:
        kinds = dict(kinds or {})
        for ch, kind in kinds.items():
            if kind not in KINDS:
                raise ValueError(f"channel {ch!r}: kind must be one of {KINDS}, got {kind!r}")
        self.channels = None if channels is None else list(channels)
        self.every_tick = every_tick
        self.gps = gps
        self.timing = timing
        self.steering = tuple(steering)
        self._steer_rad = math.radians(steering_max_deg)
        self._kinds: dict[str, str] = kinds
        self._specs: dict[str, ChannelSpec | None] = {}
        self._last_seen: dict[str, tuple[Any, float]] = {}
        self._jpeg = make_converter("image_array", jpeg_quality=jpeg_quality)
        # the timing emitted so far (writer thread): per series the next sample number, and the next tick
        self._next: dict[tuple[str, str], int] = {}
        self._next_tick = 0
        self._profiler: Any = None
        self.timing_dropped = 0
        """timing samples (a part's run, a latency, a tick's figures) that left the profiler's ring before the
        writer thread read them: not in the recording, counted here and in each tick message."""
        self.bad_values = 0
        self.bad_channels: dict[str, str] = {}
        """channel → why it is not recorded (a value the encoder cannot represent)."""

    # ------------------------------------------------------------------------------------ channels
    def _spec_for(self, ch: str, value: Any) -> ChannelSpec | None:
        spec = self._specs.get(ch, ...)
        if spec is not ...:
            return spec  # type: ignore[return-value]
        kind = self._kinds.get(ch) or _kind_of(value)
        try:
            spec = None if kind == "skip" else _make_spec(topic_for(ch), kind, value)
        except TypeError as exc:  # a value no schema fits (an arbitrary object): leave the channel out, say so once
            logger.warning("channel %r is not recorded: %s", ch, exc)
            self.bad_values += 1
            self.bad_channels[ch] = str(exc)
            spec, kind = None, "skip"
        self._specs[ch] = spec
        self._kinds[ch] = kind
        return spec

    def encode(
        self, snap: TickSnapshot, times: TimeMap, wanted: Callable[[ChannelSpec], bool] | None = None
    ) -> Iterator[tuple[ChannelSpec, bytes, int, int]]:
        """The messages of one tick; values that cannot be encoded are counted in :attr:`bad_values`.

        ``wanted(spec)`` (the live server: has the topic a subscriber?) is asked before a value is encoded, so
        nobody watching costs no JPEG encoding; the topic is registered either way.
        """
        t_ns = times.to_ns(snap.t)
        values, origins = snap.values, snap.origins
        names = values.keys() if self.channels is None else [c for c in self.channels if c in values]
        last = self._last_seen
        gps_due = False
        for ch in names:
            value = values[ch]
            if value is None:
                continue
            origin = origins.get(ch, snap.t)
            seen = last.get(ch)
            if not self.every_tick and seen is not None and seen[0] is value and seen[1] == origin:
                continue
            last[ch] = (value, origin)
            if self.gps is not None and ch in self.gps:
                gps_due = True
            try:
                spec = self._spec_for(ch, value)
                if spec is None:
                    continue
                if wanted is not None and not wanted(spec):
                    data = None
                else:
                    data = self._message(spec, ch, value, origin, snap.t, times)
            except (TypeError, ValueError, OverflowError) as exc:
                self.bad_values += 1
                self.bad_channels.setdefault(ch, str(exc))
                continue
            if data is not None:
                yield spec, data, t_ns, times.to_ns(origin)
            if self.steering and self._kinds[ch] == "image":
                overlay = self._overlay(ch, value, values, times.to_ns(origin), wanted)
                if overlay is not None:
                    yield overlay[0], overlay[1], t_ns, times.to_ns(origin)
        if gps_due:
            fix = self._gps_fix(values, origins, snap.t, times)
            if fix is not None and (wanted is None or wanted(fix[0])):
                yield fix[0], fix[1], t_ns, fix[2]
        if self.timing and snap.timing is not None:
            for msg in self.timing_messages(snap, times):
                if wanted is None or wanted(msg[0]):
                    yield msg

    def _message(self, spec: ChannelSpec, ch: str, value: Any, origin: float, t: float, times: TimeMap) -> bytes:
        kind = self._kinds[ch]
        if kind == "image":
            from foxglove.messages import CompressedImage

            return CompressedImage(
                timestamp=_stamp(times.to_ns(origin)), frame_id=ch, data=self._jpeg(value), format="jpeg"
            ).encode()
        if kind == "laserscan":
            return _laser_scan(value, ch, _stamp(times.to_ns(origin)))
        return _dumps({"value": _plain(value), "age_ms": (t - origin) * 1e3})

    def _overlay_spec(self, ch: str) -> ChannelSpec:
        topic = topic_for(ch) + "/steering"
        spec = self._specs.get(topic)
        if spec is None:
            from foxglove.messages import ImageAnnotations

            spec = self._specs[topic] = _schema_spec(topic, ImageAnnotations)
        return spec

    def _overlay(
        self, ch: str, image: Any, values: dict[str, Any], ns: int, wanted: Callable[[ChannelSpec], bool] | None
    ) -> tuple[ChannelSpec, bytes] | None:
        """The steering drawn over frame ``ch``, or None. Apart from the frame's own message: a drawing that
        fails (a JPEG that does not decode) is counted and never costs the frame."""
        spec = self._overlay_spec(ch)
        if wanted is not None and not wanted(spec):
            return None
        try:
            return self._steering(spec, image, values, ns)
        except (TypeError, ValueError, OverflowError) as exc:
            self.bad_values += 1
            self.bad_channels.setdefault(spec.topic[1:], str(exc))
            return None

    def _steering(
        self, spec: ChannelSpec, image: np.ndarray, values: dict[str, Any], ns: int
    ) -> tuple[ChannelSpec, bytes] | None:
        from foxglove.messages import Color, ImageAnnotations, Point2, PointsAnnotation, PointsAnnotationType

        h, w = _image_size(image)
        stamp = _stamp(ns)
        lines = []
        colors = (Color(r=0.1, g=0.9, b=0.2, a=1.0), Color(r=0.9, g=0.2, b=0.9, a=1.0))
        for i, key in enumerate(self.steering[:2]):
            a = values.get(key)
            if not _is_number(a):
                continue
            theta = max(-1.0, min(1.0, float(a))) * self._steer_rad
            length = 0.6 * h
            tip = Point2(x=w / 2 + length * math.sin(theta), y=h - length * math.cos(theta))
            lines.append(
                PointsAnnotation(
                    timestamp=stamp,
                    type=PointsAnnotationType.LineStrip,
                    points=[Point2(x=w / 2, y=float(h)), tip],
                    outline_color=colors[i],
                    thickness=2.0,
                )
            )
        if not lines:
            return None
        return spec, ImageAnnotations(timestamp=stamp, points=lines).encode()

    def _gps_fix(
        self, values: dict[str, Any], origins: dict[str, float], t: float, times: TimeMap
    ) -> tuple[ChannelSpec, bytes, int] | None:
        lat_ch, lon_ch = self.gps  # type: ignore[misc]
        lat, lon = values.get(lat_ch), values.get(lon_ch)
        if not (_is_number(lat) and _is_number(lon)):
            return None
        from foxglove.messages import LocationFix

        spec = self._specs.get(GPS_TOPIC)
        if spec is None:
            spec = self._specs[GPS_TOPIC] = _schema_spec(GPS_TOPIC, LocationFix)
        origin = min(origins.get(lat_ch, t), origins.get(lon_ch, t))
        ns = times.to_ns(origin)
        msg = LocationFix(timestamp=_stamp(ns), frame_id="gps", latitude=float(lat), longitude=float(lon))
        return spec, msg.encode(), ns

    def timing_messages(self, snap: TickSnapshot, times: TimeMap) -> Iterator[tuple[ChannelSpec, bytes, int, int]]:
        """The timing messages due at ``snap``: every tick ended and every part and latency sample taken since the
        last snapshot, each exactly once (module docstring); samples already gone from the rings are counted in
        :attr:`timing_dropped`."""
        layout = snap.timing
        if layout is None:
            return
        if layout.profiler is not self._profiler:  # a new drive: its series count from 0 again
            self._profiler = layout.profiler
            self._next.clear()
            self._next_tick = 0
        t_ns = times.to_ns(snap.t)
        samples = self._samples(layout, layout.counts(snap.ticks, snap.counts))
        # the ticks first: their message carries the drops counted so far, these samples' included
        yield from self._tick_messages(snap, layout, times, t_ns)
        for topic, schema in ((PARTS_TOPIC, "asyncdonkey.PartTimes"), (LATENCY_TOPIC, "asyncdonkey.Latency")):
            for msg in samples[topic]:
                yield self._json_spec(topic, schema, msg), _dumps(msg), t_ns, t_ns

    def _samples(self, layout: TimingLayout, counts: list[int]) -> dict[str, list[dict[str, float]]]:
        """Per topic, the new samples as messages: the k-th holds each series' k-th new sample (ms)."""
        out: dict[str, list[dict[str, float]]] = {PARTS_TOPIC: [], LATENCY_TOPIC: []}
        nxt = self._next
        for (topic, name, series), count in zip(layout.series, counts, strict=True):
            key = (topic, name)
            n = nxt.get(key, 0)
            if count <= n:
                continue
            nxt[key] = count
            first = series.first_readable()
            if n < first:  # left the ring before the writer got to them
                self.timing_dropped += min(first, count) - n
                n = first
            msgs = out[topic]
            k = 0
            for i in range(n, count):
                v = _sample(series, i)
                if v is _GONE:
                    self.timing_dropped += 1
                    continue
                if v is None:  # a tick whose run condition skipped the part: no run, no sample
                    continue
                if k == len(msgs):
                    msgs.append({})
                msgs[k][name] = v * 1e3
                k += 1
        return out

    def _tick_messages(
        self, snap: TickSnapshot, layout: TimingLayout, times: TimeMap, t_ns: int
    ) -> Iterator[tuple[ChannelSpec, bytes, int, int]]:
        """One message per tick ended since the last snapshot, stamped with its start."""
        p, table, end = layout.profiler, layout.table, snap.ticks
        k = self._next_tick
        if end <= k:
            return
        self._next_tick = end
        first = p.tick.first_readable()
        if k < first:
            self.timing_dropped += min(first, end) - k
            k = first
        for tick in range(k, end):
            figures = [_sample(s, tick) for s in (p.lateness, p.tick, p.overrun)]
            start = table.start_of(tick) if table is not None else None
            if _GONE in figures:
                self.timing_dropped += 1
                continue
            own = tick == end - 1  # the counters the snapshot read are this tick's (it ended just before)
            msg = {
                "tick": tick + 1,
                **{f: None if v is None else v * 1e3 for f, v in zip(_TICK_FIGURES, figures, strict=True)},
                "overruns": snap.overruns if own else None,
                "skipped_deadlines": snap.skipped if own else None,
                "timing_dropped": self.timing_dropped,
            }
            ns = t_ns if start is None else times.to_ns(start)
            yield self._json_spec(TICK_TOPIC, "asyncdonkey.Tick", msg), _dumps(msg), ns, ns

    def _json_spec(self, topic: str, name: str, example: dict[str, Any]) -> ChannelSpec:
        spec = self._specs.get(topic)
        if spec is None:
            schema = {"type": "object", "additionalProperties": {"type": ["number", "null"]}}
            if topic == TICK_TOPIC:
                schema = {"type": "object", "properties": {k: {"type": ["number", "null"]} for k in example}}
            spec = self._specs[topic] = ChannelSpec(topic, name, "jsonschema", _dumps(schema), "json")
        return spec


# ------------------------------------------------------------------------------------------- helpers
def _image_size(image: Any) -> tuple[int, int]:
    if isinstance(image, np.ndarray):
        return int(image.shape[0]), int(image.shape[1])
    import cv2  # a JPEG handed over already encoded (a tub converted to MCAP)

    decoded = cv2.imdecode(np.frombuffer(image, dtype=np.uint8), cv2.IMREAD_GRAYSCALE)
    if decoded is None:
        raise ValueError("image data is not a decodable JPEG")
    return int(decoded.shape[0]), int(decoded.shape[1])


def _kind_of(value: Any) -> str:
    if isinstance(value, np.ndarray) and value.dtype == np.uint8:
        if value.ndim == 3 and value.shape[2] in (1, 3) and min(value.shape[:2]) >= 8:
            return "image"
        if value.ndim == 2 and min(value.shape) >= 8:
            return "image"
    if hasattr(value, "angles") and hasattr(value, "distances"):
        return "laserscan"
    return "json"


def _json_type(value: Any) -> tuple[str, dict[str, Any]]:
    if isinstance(value, bool | np.bool_):
        return "Bool", {"type": "boolean"}
    if isinstance(value, int | float | np.number):
        return "Number", {"type": "number"}
    if isinstance(value, str):
        return "String", {"type": "string"}
    if isinstance(value, list | tuple | np.ndarray):
        return "Array", {"type": "array"}
    if isinstance(value, dict):
        return "Object", {"type": "object"}
    raise TypeError(f"cannot record a {type(value).__name__} value")


def _make_spec(topic: str, kind: str, value: Any) -> ChannelSpec:
    if kind == "image":
        from foxglove.messages import CompressedImage

        return _schema_spec(topic, CompressedImage)
    if kind == "laserscan":
        from foxglove.messages import LaserScan

        return _schema_spec(topic, LaserScan)
    name, value_schema = _json_type(value)
    schema = {
        "type": "object",
        "properties": {"value": value_schema, "age_ms": {"type": "number"}},
    }
    return ChannelSpec(topic, f"asyncdonkey.{name}", "jsonschema", _dumps(schema), "json")


def _schema_spec(topic: str, cls: Any) -> ChannelSpec:
    s = cls.get_schema()
    return ChannelSpec(topic, s.name, s.encoding, bytes(s.data), "protobuf")


def _stamp(ns: int) -> Any:
    from foxglove.messages import Timestamp

    return Timestamp(sec=ns // 1_000_000_000, nsec=ns % 1_000_000_000)


def _laser_scan(scan: Any, frame: str, stamp: Any) -> bytes:
    from foxglove.messages import LaserScan

    angles = np.asarray(scan.angles, dtype=np.float64)
    dist = np.asarray(scan.distances, dtype=np.float64)
    if angles.shape != dist.shape:
        raise ValueError(f"scan has {angles.size} angles but {dist.size} distances")
    ranges = np.zeros(360, dtype=np.float64)
    valid = dist > 0
    # clockwise degrees -> counter-clockwise 1° bins; the nearest return wins a bin (the closer obstacle)
    bins = np.round(-angles[valid]).astype(np.int64) % 360
    metres = dist[valid] / 1000.0
    order = np.argsort(-metres)  # farthest first, so the nearest is written last
    ranges[bins[order]] = metres[order]
    return LaserScan(
        timestamp=stamp,
        frame_id=frame,
        start_angle=0.0,
        end_angle=math.radians(359.0),
        ranges=ranges.tolist(),
    ).encode()


def _is_number(x: Any) -> bool:
    """A real number a float holds, finite (a 400-digit integer is not: ``float()`` overflows on it)."""
    if isinstance(x, bool | np.bool_ | np.complexfloating) or not isinstance(x, int | float | np.number):
        return False
    try:
        return math.isfinite(float(x))
    except (OverflowError, TypeError, ValueError):
        return False


_TICK_FIGURES = ("lateness_ms", "duration_ms", "overrun_ms")
_GONE: Any = object()
"""a sample that left its ring before it was read"""


def _sample(series: Any, n: int) -> Any:
    """Sample ``n`` of a profiler series read from the writer thread: its value, ``None`` (not a sample: a part
    skipped on that tick), or :data:`_GONE` when it left the ring (checked after the read, so a slot reused
    while it was read is never taken for the sample)."""
    v = series.at(n)
    return _GONE if n < series.first_readable() else v


def _plain(v: Any) -> Any:
    """A JSON-safe copy: numpy to Python, non-finite floats to ``None`` (JSON has no NaN)."""
    if isinstance(v, float | np.floating):
        f = float(v)
        return f if math.isfinite(f) else None
    if isinstance(v, bool | np.bool_):
        return bool(v)
    if isinstance(v, int | np.integer):
        return int(v)
    if isinstance(v, str) or v is None:
        return v
    if isinstance(v, np.ndarray):
        return _plain(v.tolist())
    if isinstance(v, list | tuple):
        return [_plain(x) for x in v]
    if isinstance(v, dict):
        return {str(k): _plain(x) for k, x in v.items()}
    raise TypeError(f"cannot record a {type(v).__name__} value")


def _dumps(obj: Any) -> bytes:
    return json.dumps(obj, separators=(",", ":"), allow_nan=False).encode()
