"""From a tick's channels and timing to Foxglove messages: one encoder for the MCAP file and the live server.

:class:`TickEncoder` turns one recorded tick (a :class:`TickSnapshot`) into ``(channel, message bytes,
log_time_ns, publish_time_ns)``. It runs on a writer thread, never on the drive loop's. Both sinks, the MCAP
file (:mod:`.sink`) and the WebSocket server (:mod:`.live`), use it, so the file and the live view carry the
same topics, schemas and bytes.

**Topics.** A Memory channel ``cam/image_array`` becomes topic ``/cam/image_array``. The loop's own timing is
on ``/asyncdonkey/tick``, ``/asyncdonkey/parts`` and ``/asyncdonkey/latency`` (see :data:`TICK_TOPIC`).

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
    "topic_for",
]

logger = logging.getLogger(__name__)

KINDS = ("image", "laserscan", "json", "skip")
TICK_TOPIC = "/asyncdonkey/tick"
"""Each tick: ``tick`` (its number), ``lateness_ms`` (its start minus its deadline), ``duration_ms`` and
``overrun_ms`` of the *previous* tick (the current one has not ended when the recorder runs), cumulative
``overruns`` and ``skipped_deadlines``."""
PARTS_TOPIC = "/asyncdonkey/parts"
"""Each tick: ``{part name: ms}`` for every part that completed a run since the last message (parts after the
recorder in the loop report the previous tick's run)."""
LATENCY_TOPIC = "/asyncdonkey/latency"
"""``{actuator name: ms}``: sensing-to-actuation latency of each actuator's newest command."""
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
    """

    clock_anchor_s: float
    wall_anchor_ns: int
    clock: str = "monotonic"  # or "virtual"

    def to_ns(self, t: float) -> int:
        return self.wall_anchor_ns + round((t - self.clock_anchor_s) * 1e9)

    def to_clock(self, ns: int) -> float:
        return self.clock_anchor_s + (ns - self.wall_anchor_ns) / 1e9

    def as_metadata(self) -> dict[str, str]:
        return {
            "clock_anchor_s": repr(self.clock_anchor_s),
            "wall_anchor_ns": str(self.wall_anchor_ns),
            "clock": self.clock,
        }

    @classmethod
    def from_metadata(cls, data: Mapping[str, str]) -> TimeMap:
        return cls(float(data["clock_anchor_s"]), int(data["wall_anchor_ns"]), data.get("clock", "monotonic"))


class TickSnapshot(NamedTuple):
    """What ``run()`` hands over for one tick: references and small dict copies, never copies of the values.

    The timing is not copied in the tick: the writer thread reads the profiler's ring buffers itself
    (:meth:`~asyncdonkey.profiler.Series.at`), sample by number, which costs the tick nothing.
    """

    t: float
    """runtime-clock time at which the tick recorded"""
    values: dict[str, Any]
    origins: dict[str, float]
    ticks: int
    """ticks started in this drive when the recorder ran (the profiler's lateness sample count)"""
    profiler: Any
    """the drive's :class:`~asyncdonkey.profiler.Profiler` (``None``: no timing)"""
    overruns: int | None
    """the drive's overrun count when the recorder ran"""
    skipped: int | None
    """the drive's skipped-deadline count when the recorder ran"""


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
        self._counts: dict[tuple[str, str], int] = {}
        self._tick_count = 0
        self._profiler: Any = None
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
            overlay = None
            try:
                spec = self._spec_for(ch, value)
                if spec is None:
                    continue
                if self.steering and self._kinds[ch] == "image":
                    ospec = self._overlay_spec(ch)
                    if wanted is None or wanted(ospec):
                        overlay = self._steering(ospec, value, values, times.to_ns(origin))
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
            if overlay is not None:
                yield overlay[0], overlay[1], t_ns, times.to_ns(origin)
        if gps_due:
            fix = self._gps_fix(values, origins, snap.t, times)
            if fix is not None and (wanted is None or wanted(fix[0])):
                yield fix[0], fix[1], t_ns, fix[2]
        if self.timing and snap.profiler is not None:
            for msg in self._timing(snap, t_ns):
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

    def _timing(self, snap: TickSnapshot, t_ns: int) -> Iterator[tuple[ChannelSpec, bytes, int, int]]:
        p, ticks = snap.profiler, snap.ticks
        counts = self._counts
        if p is not self._profiler:  # a new drive: its profiler counts from 0 again
            self._profiler = p
            counts.clear()
            self._tick_count = 0
        if ticks != self._tick_count:
            lateness = p.lateness.at(ticks - 1)
            duration = p.tick.at(ticks - 2)  # the previous tick: the current one has not ended
            overrun = p.overrun.at(ticks - 2)
            msg = {
                "tick": ticks,
                "lateness_ms": None if lateness is None else lateness * 1e3,
                "duration_ms": None if duration is None else duration * 1e3,
                "overrun_ms": None if overrun is None else overrun * 1e3,
                "overruns": snap.overruns,
                "skipped_deadlines": snap.skipped,
            }
            self._tick_count = ticks
            yield self._json_spec(TICK_TOPIC, "asyncdonkey.Tick", msg), _dumps(msg), t_ns, t_ns
        for topic, schema, series in (
            (PARTS_TOPIC, "asyncdonkey.PartTimes", p.parts),
            (LATENCY_TOPIC, "asyncdonkey.Latency", p.latency),
        ):
            msg = {}
            for name, s in list(series.items()):
                key = (topic, name)
                n = s.count
                if n != counts.get(key, 0):
                    last = s.at(n - 1)
                    if last is not None:
                        msg[name] = last * 1e3
                    counts[key] = n
            if msg:
                yield self._json_spec(topic, schema, msg), _dumps(msg), t_ns, t_ns

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
    return isinstance(x, int | float | np.number) and not isinstance(x, bool) and math.isfinite(float(x))


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
