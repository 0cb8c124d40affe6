"""Memory channels on the network: a publisher part and a subscriber part sharing a :class:`.ZenohLink`.

Wiring, on the car (camera out, commands in)::

    link = ZenohLink("cars/car1", zenoh_config("car.json5"))
    v.add(ZenohSubscriber(link, ["pilot/angle", "pilot/throttle"]), outputs=["pilot/angle", "pilot/throttle"])
    cam_out = ZenohPublisher(link, ["cam/image_array"], jpeg={"cam/image_array": 85})
    v.add(cam_out, inputs=cam_out.inputs)            # the channels and their "@age" inputs

**Nothing blocks a tick, nothing queues.** Zenoh calls the subscriber back on its own threads; the callback
decodes the payload there and swaps it into a one-slot cell per channel under a lock. ``run()`` takes the
newest value of every channel without waiting. A value that is overwritten before a tick took it is counted
in ``dropped``; a sample older (by sequence number) than the one already held is discarded and counted in
``out_of_order``; a sample whose age on arrival exceeds ``late_after_s`` is counted in ``late`` (and still
used: it is the newest there is); gaps in sequence numbers are counted in ``lost``.

**Pushing.** A subscriber of one channel is also a push source (``subscribe(callback)``, as the cameras): when
its channel triggers a pipelined part (``trigger="cam/image_array"``), the drive loop writes each value into
Memory the moment it arrives and starts that part at once, instead of at the next tick
(``examples/remote_pilot.py`` runs its pilot this way; see ``docs/control-periods.md``).

**Ages stay true.** The subscriber's ``output_origin()`` is the oldest origin among the values its last
``run()`` returned, each being ``receipt - age_at_send - link.transit_s`` (:mod:`.link`). When the sender
goes quiet, the values keep their old origin, so ``"pilot/throttle@age"`` grows and a stale-command failsafe
downstream stops the car.

**Only the configured keys.** The subscriber listens, for samples from other sessions, to the smallest key
expression that covers its channels (``cars/car1/pilot/**`` for ``pilot/angle, pilot/throttle``; or the
``key_expr`` given) and takes only ``<prefix>/<channel>`` for its channels; anything else it receives there
(``cars/car1/pilot/mode`` from a misbehaving peer) is counted in ``unexpected`` and logged (rate-limited)
with its key. This is a second line behind the access-control rules of a secure config
(``docs/scale-out.md``), which stop unauthorised puts before they reach the process at all.
"""

from __future__ import annotations

import logging
import math
import random
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ...clock import get_clock
from ...periodic import Periodic
from ...ratelimit import LogThrottle
from .codec import CodecError, decode, encode, pack_attachment, unpack_attachment
from .link import INTERNAL, ZenohLink

__all__ = ["ZenohPublisher", "ZenohSubscriber", "covering_key"]

logger = logging.getLogger(__name__)


class ZenohPublisher:
    """Send chosen Memory channels as ``<prefix>/<channel>``, each tick or only on change.

    Args:
        link: the :class:`.ZenohLink` to publish on.
        channels: the Memory channels to send.
        on_change: send a channel only when its value changed (a different object, or an unequal scalar), but
            at least every ``max_interval_s`` so receivers can tell "unchanged" from "sender gone". An unchanged
            value re-sensed in between is not re-sent, so the receiver may see it up to ``max_interval_s`` older
            than it is: keep ``on_change`` for slow channels (modes, settings), not for commands.
        max_interval_s: the longest silence per channel with ``on_change`` (keep it well under the receiver's
            failsafe window).
        jpeg: channel → JPEG quality (1-100) for image channels to send as JPEG instead of raw arrays.

    Add it with ``inputs=publisher.inputs``: the channels, then ``"<channel>@age"`` for each, so every sample
    carries the age of the sensing behind it (added with the channels alone, values count as sensed when sent).
    A value whose age is unknown (``inf``: no sensing behind it, e.g. computed from channels never written) is
    not sent: sent with any finite age it would look fresh to the receiver. ``sent``, ``skipped`` (unchanged),
    ``unaged`` (no sensing behind them) and ``errors`` count samples.
    """

    def __init__(
        self,
        link: ZenohLink,
        channels: Sequence[str],
        *,
        on_change: bool = False,
        max_interval_s: float = 0.1,
        jpeg: Mapping[str, int] | None = None,
    ) -> None:
        import zenoh

        if isinstance(channels, str) or not channels:
            raise ValueError(f"ZenohPublisher: channels must be a non-empty list of names, got {channels!r}")
        if not max_interval_s > 0:
            raise ValueError(f"ZenohPublisher: max_interval_s must be > 0, got {max_interval_s!r}")
        jpeg = dict(jpeg or {})
        for ch, q in jpeg.items():
            if ch not in channels:
                raise ValueError(f"ZenohPublisher: jpeg channel {ch!r} is not one of the channels {list(channels)!r}")
            if not (isinstance(q, int) and 1 <= q <= 100):
                raise ValueError(f"ZenohPublisher: JPEG quality for {ch!r} must be an int 1-100, got {q!r}")
        self.link = link.acquire()
        self.channels = tuple(channels)
        self.on_change = on_change
        self.max_interval_s = float(max_interval_s)
        self.jpeg = jpeg
        self._pubs = [
            link.session.declare_publisher(link.key(ch), congestion_control=zenoh.CongestionControl.DROP)
            for ch in self.channels
        ]
        self._seq = [0] * len(self.channels)
        #: drawn at start, sent with every sample: receivers tell a restarted publisher from late samples
        self.source = random.getrandbits(63) + 1
        self._last: list[Any] = [None] * len(self.channels)
        self._last_t = [-math.inf] * len(self.channels)
        self._log = LogThrottle(5.0)
        self.sent = 0
        self.skipped = 0
        self.unaged = 0
        self.errors = 0
        self.bytes_sent = 0

    @property
    def inputs(self) -> list[str]:
        """The inputs to add this part with: the channels, then their ``@age``."""
        return [*self.channels, *(f"{ch}@age" for ch in self.channels)]

    def run(self, *values: Any) -> None:
        n = len(self.channels)
        ages = values[n:] if len(values) == 2 * n else (0.0,) * n
        now = _now()
        for i in range(n):
            value = values[i]
            if value is None:
                continue
            if self.on_change and now - self._last_t[i] < self.max_interval_s and _same(value, self._last[i]):
                self.skipped += 1
                continue
            age = ages[i]
            ch = self.channels[i]
            if age is None or not math.isfinite(age):
                self.unaged += 1
                if self._log.allow(("unaged", ch), now):
                    logger.warning("ZenohPublisher: %r has no sensing behind it (age %r): not sent", ch, age)
                continue
            age = float(age) if age > 0 else 0.0
            try:
                enc = encode(value, ch, jpeg_quality=self.jpeg.get(ch))
            except CodecError as exc:
                self.errors += 1
                if self._log.allow(ch, now):
                    logger.warning("ZenohPublisher: %s (not sent)", exc)
                continue
            self._seq[i] += 1
            self._pubs[i].put(
                enc.payload, encoding=enc.encoding, attachment=pack_attachment(age, self._seq[i], self.source)
            )
            self._last[i] = value
            self._last_t[i] = now
            self.sent += 1
            self.bytes_sent += len(enc.payload)

    def shutdown(self) -> None:
        for p in self._pubs:
            try:
                p.undeclare()
            except Exception:
                pass
        self._pubs = []
        self.link.release()

    def __repr__(self) -> str:
        return f"ZenohPublisher({self.link.prefix!r}, {list(self.channels)!r})"


def _same(a: Any, b: Any) -> bool:
    if a is b:
        return True
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return False  # a new array object is a new frame; comparing pixels costs more than sending
    try:
        return bool(a == b) and type(a) is type(b)
    except Exception:
        return False


@dataclass(slots=True)
class _Held:
    value: Any
    origin: float
    seq: int
    source: int
    fresh: bool  # not yet taken by run()


class ZenohSubscriber:
    """Write remote channels into Memory: ``run()`` returns the newest value of each (``None`` until one came).

    Args:
        link: the :class:`.ZenohLink` to listen on; the keys are ``<prefix>/<channel>``.
        channels: the channels to take, in the order of the part's outputs.
        late_after_s: an arrival whose age (sender's age plus transit) exceeds this is counted in ``late``.
        ping_every_s: how often ``update()`` measures the round trip (``0``: never; ``transit_s`` stays 0).
        key_expr: what to listen to (default: the smallest key expression covering the channels; give
            ``"<prefix>/**"`` to audit every key of the car).
        on_arrival: called with the channel name on Zenoh's thread after each value is stored (to wake an
            event-driven consumer; it must be quick and must not block).

    Counters: ``received`` (samples taken into a cell), ``dropped`` (overwritten before a tick took them, when
    nothing is subscribed to the pushes),
    ``out_of_order`` (numbered below the newest: discarded), ``late``, ``lost`` (sequence gaps), ``restarts``
    (a sample from a new source, e.g. a restarted pilot: taken), ``unexpected`` (keys not configured, or
    samples without our attachment), ``malformed`` (payloads that did not decode).
    """

    def __init__(
        self,
        link: ZenohLink,
        channels: Sequence[str],
        *,
        late_after_s: float = 0.1,
        ping_every_s: float = 0.5,
        key_expr: str | None = None,
        on_arrival: Callable[[str], None] | None = None,
    ) -> None:
        import zenoh

        if isinstance(channels, str) or not channels:
            raise ValueError(f"ZenohSubscriber: channels must be a non-empty list of names, got {channels!r}")
        self.link = link.acquire()
        self.channels = tuple(channels)
        self.late_after_s = float(late_after_s)
        self.ping_every_s = float(ping_every_s)
        self._index = {link.key(ch): i for i, ch in enumerate(self.channels)}
        self._held: list[_Held | None] = [None] * len(self.channels)
        self._lock = threading.Lock()
        self._log = LogThrottle(5.0)
        self._origin: float | None = None
        self.received = 0
        self.dropped = 0
        self.out_of_order = 0
        self.late = 0
        self.lost = 0
        self.unexpected = 0
        self.malformed = 0
        self.restarts = 0
        self.on_arrival = on_arrival
        self._pushes: tuple[Callable[[Any, float], None], ...] = ()
        self.key_expr = key_expr or covering_key(list(self._index))
        if link.exposure:
            logger.warning(
                "ZenohSubscriber %s: anyone who can reach this session can write these channels (it %s). "
                "For commands, use the configs of `asyncdonkey zenoh-pair` (docs/scale-out.md).",
                list(self.channels),
                "; ".join(link.exposure),
            )
        self._sub = link.session.declare_subscriber(
            self.key_expr, self._on_sample, allowed_origin=zenoh.Locality.REMOTE
        )

    # -- Zenoh's threads -------------------------------------------------------------------------------
    def _on_sample(self, sample: Any) -> None:
        key = str(sample.key_expr)
        i = self._index.get(key)
        if i is None:
            if not key.startswith(f"{self.link.prefix}/{INTERNAL}/"):
                self._reject(key, "is not one of the configured channels")
            return
        meta = unpack_attachment(_bytes(sample.attachment))
        if meta is None:
            self._reject(key, "carries no age attachment (not an asyncdonkey publisher)")
            return
        age, seq, source = meta
        try:
            value = decode(sample.payload.to_bytes(), str(sample.encoding), key)
        except CodecError as exc:
            with self._lock:
                self.malformed += 1
            if self._log.allow("malformed", self.link.now()):
                logger.warning("ZenohSubscriber: %s (ignored)", exc)
            return
        now = self.link.now()
        age_here = age + self.link.transit_s
        with self._lock:
            held = self._held[i]
            if held is not None:
                if source != held.source:
                    self.restarts += 1  # another sender, or the same one restarted: its numbering starts over
                elif seq <= held.seq:
                    self.out_of_order += 1
                    return
                elif seq > held.seq + 1:
                    self.lost += seq - held.seq - 1
                if held.fresh and not self._pushes:
                    self.dropped += 1
            origin = now - age_here
            self._held[i] = _Held(value, origin, seq, source, True)
            self.received += 1
            if age_here > self.late_after_s:
                self.late += 1
        if self._pushes:
            if len(self.channels) == 1:
                pushed, pushed_origin = value, origin
            else:  # every channel's newest value, as run() would return them, with the oldest origin
                pushed, pushed_origin = self._snapshot()
            for push in self._pushes:
                push(pushed, pushed_origin)
        if self.on_arrival is not None:
            self.on_arrival(self.channels[i])

    def _reject(self, key: str, why: str) -> None:
        with self._lock:
            self.unexpected += 1
            n = self.unexpected
        # one line per 5 s whatever the keys: a peer spraying new keys must not flood the log
        if self._log.allow("unexpected", self.link.now()):
            logger.warning(
                "ZenohSubscriber on %r: ignored a sample on %r: it %s (%d ignored so far)",
                self.link.prefix,
                key,
                why,
                n,
            )

    def subscribe(self, callback: Callable[[Any, float], None]) -> Callable[[], None]:
        """Call ``callback(value, origin)`` on Zenoh's thread for each value taken: the value as ``run()`` would
        return it (one channel: its value; several: all of them, with the oldest origin).

        The drive loop subscribes when this part's channels trigger a pipelined part or feed ``react=True``
        parts, so a remote command reaches the actuators when it arrives, not at the next tick. The callback
        must be thread-safe (the loop's hands the value over with ``call_soon_threadsafe``). Returns the
        unsubscriber.
        """
        self._pushes = (*self._pushes, callback)

        def unsubscribe() -> None:
            self._pushes = tuple(c for c in self._pushes if c is not callback)

        return unsubscribe

    # -- the tick --------------------------------------------------------------------------------------
    def run(self) -> Any:
        value, self._origin = self._snapshot(taken=True)
        return value

    def _snapshot(self, taken: bool = False) -> tuple[Any, float | None]:
        """The newest value of every channel (one channel: its value) and the oldest of their origins."""
        out: list[Any] = []
        oldest = math.inf
        with self._lock:
            for held in self._held:
                if held is None:
                    out.append(None)
                    continue
                if taken:
                    held.fresh = False
                out.append(held.value)
                oldest = min(oldest, held.origin)
        return (out[0] if len(out) == 1 else tuple(out)), (oldest if math.isfinite(oldest) else None)

    def output_origin(self) -> float | None:
        """The oldest origin among the values the last ``run()`` returned (runtime clock)."""
        return self._origin

    def ages(self) -> dict[str, float]:
        """Channel → age of its held value now (s); ``inf`` for a channel that never arrived."""
        now = self.link.now()
        with self._lock:
            return {ch: (now - h.origin if h else math.inf) for ch, h in zip(self.channels, self._held, strict=True)}

    async def update(self) -> None:
        """Measure the round trip to the other sessions on the prefix every ``ping_every_s`` (for the ages)."""
        clock = get_clock()
        self.link.now = clock.now
        if self.ping_every_s <= 0:
            return
        with Periodic(self.ping_every_s) as every:
            while not self.link.closed:
                self.link.ping()
                await every.next()

    def counters(self) -> dict[str, int]:
        with self._lock:
            return {
                "received": self.received,
                "dropped": self.dropped,
                "out_of_order": self.out_of_order,
                "late": self.late,
                "lost": self.lost,
                "unexpected": self.unexpected,
                "malformed": self.malformed,
                "restarts": self.restarts,
            }

    def shutdown(self) -> None:
        try:
            self._sub.undeclare()
        except Exception:
            pass
        self.link.release()

    def __repr__(self) -> str:
        return f"ZenohSubscriber({self.link.prefix!r}, {list(self.channels)!r})"


def _now() -> float:
    """The runtime clock; ``time.monotonic()`` (its value on real loops) when called outside a loop."""
    try:
        return get_clock().now()
    except RuntimeError:
        return time.monotonic()


def covering_key(keys: Sequence[str]) -> str:
    """The smallest key expression matching all ``keys``: the key itself, or their common chunks + ``/**``."""
    chunks = [k.split("/") for k in keys]
    if all(c == chunks[0] for c in chunks):
        return keys[0]
    common: list[str] = []
    for parts in zip(*chunks, strict=False):
        if any(p != parts[0] for p in parts):
            break
        common.append(parts[0])
    return "/".join([*common, "**"])


def _bytes(z: Any) -> bytes | None:
    return None if z is None else z.to_bytes()
