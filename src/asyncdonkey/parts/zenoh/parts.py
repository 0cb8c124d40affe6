"""Memory channels on the network: a publisher part and a subscriber part sharing a :class:`.ZenohLink`.

Wiring, on the car (camera out, commands in)::

    link = ZenohLink("cars/car1", zenoh_config("car.json5"))
    commands = ZenohSubscriber(link, ["pilot/angle", "pilot/throttle"], group="pilot/command")
    v.add(commands, outputs=["pilot/angle", "pilot/throttle"])
    cam_out = ZenohPublisher(link, ["cam/image_array"], jpeg={"cam/image_array": 85})
    v.add(cam_out, inputs=cam_out.inputs)            # the channels and their "@age" inputs

and on the pilot, ``ZenohPublisher(link, ["pilot/angle", "pilot/throttle"], group="pilot/command")``.

**Nothing blocks a tick, nothing queues.** Zenoh calls the subscriber back on its own threads; the callback
decodes the payload there and swaps it into a one-slot cell per channel under a lock. ``run()`` takes the
newest value of every channel without waiting. A value that is overwritten before a tick took it is counted
in ``dropped``; a sample whose age on arrival exceeds ``late_after_s`` is counted in ``late`` (and still
used: it is the newest there is); gaps in sequence numbers are counted in ``lost``.

**No sample locks the sender out** (:mod:`.sequence`). A sample whose age is not finite and within
``[0, max_age_s]`` (10 s), or numbered 0, is refused (``implausible``); a late or repeated one
(``out_of_order``), the first of a new sender or a restarted one (``unconfirmed``: the next one confirms it),
and a jump of more than 1000 in numbering (``implausible``, confirmed by the next one) too. Each sender's
numbering is tracked on its own, and a refused sample moves none of it, so a sample numbered 2**64-1 under
the pilot's own source costs the pilot nothing, and any burst of foreign samples costs it at most one sample
once they stop. A refused sample is absent: the channel keeps its last good value, whose age keeps growing.

**One sample per command.** With ``group=`` the publisher sends its channels together as one sample on
``<prefix>/<group>`` (:func:`.codec.encode_group`) and the subscriber outputs them together with that sample's
one origin: a steering angle is never applied with the previous command's throttle, and a command is never
aged by the half that came first.

**Only good values.** Every value passes the car's channel contracts (:class:`asyncdonkey.contracts.Gate`)
before it is stored: ``NaN``, ``inf``, a string, a list, a number out of range, a DELETE sample, an empty
payload, a payload that does not decode, a group with a bad half are *refused*: not stored, counted per channel
and reason (``refused``), logged rate-limited. The channel keeps its last good value and that value keeps
ageing, so the stale-command failsafe decides what the car does, never the bad value.

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
from ...contracts import REFUSED, Contract, Contracts, Gate, Kind
from ...extras import require
from ...periodic import Periodic
from ...ratelimit import LogThrottle
from .certs import certificate_problems, config_value
from .codec import NDARRAY, CodecError, decode, decode_group, encode, encode_group, pack_attachment, unpack_attachment
from .link import INTERNAL, ZenohLink
from .sequence import IMPLAUSIBLE, MAX_AGE_S, OUT_OF_ORDER, UNCONFIRMED, SampleOrder

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
        group: send all the channels together as one sample on ``<prefix>/<group>`` (e.g. ``"pilot/command"``
            for ``pilot/angle, pilot/throttle``), with the oldest of their ages, so a receiver taking the same
            group applies them together (see :mod:`.codec` for the layout). A tick where one of them is ``None``
            sends nothing (counted in ``incomplete``): half a command is not a command.

    Add it with ``inputs=publisher.inputs``: the channels, then ``"<channel>@age"`` for each, so every sample
    carries the age of the sensing behind it (added with the channels alone, values count as sensed when sent).
    A value whose age is unknown (``inf``: no sensing behind it, e.g. computed from channels never written) is
    not sent: sent with any finite age it would look fresh to the receiver. ``sent``, ``skipped`` (unchanged),
    ``unaged`` (no sensing behind them), ``incomplete`` and ``errors`` count samples.
    """

    def __init__(
        self,
        link: ZenohLink,
        channels: Sequence[str],
        *,
        on_change: bool = False,
        max_interval_s: float = 0.1,
        jpeg: Mapping[str, int] | None = None,
        group: str | None = None,
    ) -> None:
        zenoh = require("zenoh", "zenoh", "a Zenoh link")

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
        self.group = _group_name(group, channels, "ZenohPublisher")
        if self.group is not None and jpeg:
            raise ValueError("ZenohPublisher: a group carries JSON scalars, not JPEG images")
        self.link = link.acquire()
        self.channels = tuple(channels)
        self.on_change = on_change
        self.max_interval_s = float(max_interval_s)
        self.jpeg = jpeg
        keys = [self.group] if self.group is not None else self.channels
        self._pubs: list[Any] = []
        try:
            for k in keys:
                self._pubs.append(
                    link.session.declare_publisher(link.key(k), congestion_control=zenoh.CongestionControl.DROP)
                )
        except BaseException:
            self.shutdown()  # undeclares what was declared and gives the link back: a failed part holds nothing
            raise
        self._seq = [0] * len(keys)
        #: drawn at start, sent with every sample: receivers tell a restarted publisher from late samples
        self.source = random.getrandbits(63) + 1
        self._last: list[Any] = [None] * len(keys)
        self._last_t = [-math.inf] * len(keys)
        self._log = LogThrottle(5.0)
        self.sent = 0
        self.skipped = 0
        self.unaged = 0
        self.incomplete = 0
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
        if self.group is not None:
            self._send_group(values[:n], ages, now)
            return
        for i in range(n):
            value = values[i]
            if value is None or self._unchanged(i, value, now):
                continue
            ch = self.channels[i]
            age = self._age(ages[i], ch, now)
            if age is None:
                continue
            try:
                enc = encode(value, ch, jpeg_quality=self.jpeg.get(ch))
            except CodecError as exc:
                self._error(ch, exc, now)
                continue
            self._put(i, enc.payload, enc.encoding, age, value, now)

    def _send_group(self, values: Sequence[Any], ages: Sequence[Any], now: float) -> None:
        """All the channels as one sample, aged by the oldest of them (never younger than any half)."""
        if any(v is None for v in values):
            self.incomplete += 1
            return
        values = tuple(values)
        if self._unchanged(0, values, now):
            return
        group = self.group or ""
        age = self._age(max(ages, key=lambda a: math.inf if a is None or a != a else a), group, now)
        if age is None:
            return
        try:
            enc = encode_group(dict(zip(self.channels, values, strict=True)), group)
        except CodecError as exc:
            self._error(group, exc, now)
            return
        self._put(0, enc.payload, enc.encoding, age, values, now)

    def _unchanged(self, i: int, value: Any, now: float) -> bool:
        """With ``on_change``: ``value`` is the one last sent and the keepalive is not due (counted)."""
        if not self.on_change or now - self._last_t[i] >= self.max_interval_s:
            return False
        last = self._last[i]
        if isinstance(value, tuple):
            same = isinstance(last, tuple) and len(last) == len(value) and all(map(_same, value, last))
        else:
            same = _same(value, last)
        if same:
            self.skipped += 1
        return same

    def _age(self, age: Any, name: str, now: float) -> float | None:
        """The age to send, or ``None`` (counted, logged) when nothing sensed is behind the value."""
        if age is None or not math.isfinite(age):
            self.unaged += 1
            if self._log.allow(("unaged", name), now):
                logger.warning("ZenohPublisher: %r has no sensing behind it (age %r): not sent", name, age)
            return None
        return float(age) if age > 0 else 0.0

    def _error(self, name: str, exc: CodecError, now: float) -> None:
        self.errors += 1
        if self._log.allow(name, now):
            logger.warning("ZenohPublisher: %s (not sent)", exc)

    def _put(self, i: int, payload: bytes, encoding: str, age: float, value: Any, now: float) -> None:
        self._seq[i] += 1
        self._pubs[i].put(payload, encoding=encoding, attachment=pack_attachment(age, self._seq[i], self.source))
        self._last[i] = value
        self._last_t[i] = now
        self.sent += 1
        self.bytes_sent += len(payload)

    def shutdown(self) -> None:
        for p in self._pubs:
            try:
                p.undeclare()
            except Exception:
                pass
        self._pubs = []
        self.link.release()

    def __repr__(self) -> str:
        group = f", group={self.group!r}" if self.group is not None else ""
        return f"ZenohPublisher({self.link.prefix!r}, {list(self.channels)!r}{group})"


def _group_name(group: str | None, channels: Sequence[str], who: str) -> str | None:
    """The group's channel name (its key under the prefix), checked: a plain name that is none of the channels."""
    if group is None:
        return None
    name = str(group).strip("/")
    if not name or any(c in name for c in "*$?#") or name in channels:
        raise ValueError(f"{who}: group must be a plain channel name other than the channels, got {group!r}")
    return name


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
    fresh: bool  # not yet taken by run()
    source: int = 0  # the sender's source (:mod:`.codec`'s attachment)


#: two senders' samples whose origins are this close answer the same frame (:class:`ZenohSubscriber`)
SAME_FRAME_S = 0.010


class ZenohSubscriber:
    """Write remote channels into Memory: ``run()`` returns the newest value of each (``None`` until one came).

    Args:
        link: the :class:`.ZenohLink` to listen on; the keys are ``<prefix>/<channel>``.
        channels: the channels to take, in the order of the part's outputs.
        late_after_s: an arrival whose age (sender's age plus transit) exceeds this is counted in ``late``.
        max_age_s: the oldest age a sample may say it has at send time; an older one (or one whose age is not
            a finite number >= 0) is refused as ``implausible`` (:mod:`.sequence`). Raise it for a slow channel
            whose values may legitimately be older (a mode chosen minutes ago).
        silent_after_s: when nothing has arrived on the keys for this long (``update()`` watching), log once
            why, as far as this side can tell (:meth:`silence_report`: nothing connected, and then the config's
            certificates against this clock; or connected, and then the sender or the access rules); ``0``:
            never.
        ping_every_s: how often ``update()`` measures the round trip (``0``: never; ``transit_s`` stays 0).
        key_expr: what to listen to (default: the smallest key expression covering the channels; give
            ``"<prefix>/**"`` to audit every key of the car).
        on_arrival: called with the channel name on Zenoh's thread after each value is stored (to wake an
            event-driven consumer; it must be quick and must not block).
        group: take the channels together from one sample on ``<prefix>/<group>``, as a
            ``ZenohPublisher(..., group=)`` sends them: all of them stored at once with that sample's origin,
            or none (a group with one bad value is refused whole).
        contracts: the channel contracts values are checked against (default: the car's, given by
            ``Vehicle.add`` through :meth:`use_contracts`; before that, or outside a vehicle,
            :class:`asyncdonkey.contracts.Contracts` defaults). Given here, they are kept.
        same_frame_s: a sample from *another sender* than the held value's whose origin is not newer than the
            held one's by more than this answers the same frame (or an older one), as two pilot servers of a
            pair both answer a frame during a split (:mod:`.standby`): it is not stored, counted in
            ``duplicates``. So the first answer of a frame is kept, and a second one never makes the command look
            younger (or older) than the first made it. 10 ms: far above two servers' differences in estimating
            the same frame's origin, below half the period of any camera up to 50 Hz. One sender's own samples
            are never judged by it.

    A subscriber that takes any of the car's command channels (``pairing.COMMAND_CHANNELS``) refuses to start
    on a session that others can publish to (:meth:`.ZenohLink.guard_commands`): :class:`.ZenohConfigError`.

    Counters: ``received`` (samples taken into a cell), ``dropped`` (overwritten before a tick took them, when
    nothing is subscribed to the pushes),
    ``out_of_order`` (late or repeated sequence numbers: discarded), ``late``, ``lost`` (sequence gaps, at most
    999 per sample; a refused sample is not lost), ``restarts`` (new numberings taken: a restarted or new
    sender, a resync after a jump), ``implausible`` (ages outside ``[0, max_age_s]``, sequence number 0, jumps
    not yet confirmed), ``unconfirmed`` (the first sample of a new sender, held back until its next one),
    ``unexpected`` (keys not configured, or samples without our attachment), ``refused`` (values not stored,
    per channel and reason, see :attr:`refused`), of which ``malformed`` (payloads that did not decode),
    ``duplicates`` (another sender's answer to a frame already answered, see ``same_frame_s``).
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
        group: str | None = None,
        contracts: Contracts | None = None,
        max_age_s: float = MAX_AGE_S,
        silent_after_s: float = 5.0,
        same_frame_s: float = SAME_FRAME_S,
    ) -> None:
        zenoh = require("zenoh", "zenoh", "a Zenoh link")

        if isinstance(channels, str) or not channels:
            raise ValueError(f"ZenohSubscriber: channels must be a non-empty list of names, got {channels!r}")
        if not (math.isfinite(same_frame_s) and same_frame_s >= 0):
            raise ValueError(f"ZenohSubscriber: same_frame_s must be a number of seconds >= 0, got {same_frame_s!r}")
        self.same_frame_s = float(same_frame_s)
        self.group = _group_name(group, channels, "ZenohSubscriber")
        link.guard_commands([*channels, *([self.group] if self.group else [])], f"ZenohSubscriber {list(channels)}")
        self.link = link
        self.channels = tuple(channels)
        self.late_after_s = float(late_after_s)
        self.ping_every_s = float(ping_every_s)
        self.silent_after_s = float(silent_after_s)
        self._heard_at: float | None = None
        self._watch_from: float | None = None
        self._silence_logged = False
        #: silences logged (nothing on the keys for ``silent_after_s``)
        self.silences = 0
        #: what each cell holds: one channel each, or the whole group in one
        self._cells: tuple[str, ...] = (self.group,) if self.group is not None else self.channels
        self._index = {link.key(name): i for i, name in enumerate(self._cells)}
        self._held: list[_Held | None] = [None] * len(self._cells)
        #: each cell's senders and their numbering, judged for every numbered sample, stored or refused (a value
        #: the contracts refuse still used its number: it is no gap)
        self._orders = [SampleOrder(max_age_s) for _ in self._cells]
        self.max_age_s = self._orders[0].max_age_s
        self._lock = threading.Lock()
        self._gate_lock = threading.Lock()
        self._log = LogThrottle(5.0)
        self._own_contracts = contracts is not None
        self.gate: Gate = (contracts if contracts is not None else Contracts()).gate("ZenohSubscriber")
        self._caps = self._payload_caps()
        self._delete = zenoh.SampleKind.DELETE
        self._origin: float | None = None
        self.received = 0
        self.dropped = 0
        self.out_of_order = 0
        self.late = 0
        self.lost = 0
        self.unexpected = 0
        self.malformed = 0
        self.restarts = 0
        self.implausible = 0
        self.unconfirmed = 0
        self.duplicates = 0
        self.on_arrival = on_arrival
        self._pushes: tuple[Callable[[Any, float], None], ...] = ()
        self.key_expr = key_expr or covering_key(list(self._index))
        link.acquire()  # taken last, and given back if the subscription fails: a failed part holds no session
        try:
            self._sub = link.session.declare_subscriber(
                self.key_expr, self._on_sample, allowed_origin=zenoh.Locality.REMOTE
            )
        except BaseException:
            link.release()
            raise

    # -- contracts -------------------------------------------------------------------------------------
    def use_contracts(self, contracts: Contracts) -> None:
        """Check values against the car's contracts (``Vehicle.add`` calls this), unless given ``contracts=``.
        Refusals counted so far are kept."""
        if self._own_contracts:
            return
        gate = contracts.gate("ZenohSubscriber")
        with self._gate_lock:
            gate.refused.update(self.gate.refused)
            self.gate = gate
            self._caps = self._payload_caps()

    def _payload_caps(self) -> tuple[int | None, ...]:
        """Per cell, the largest payload worth decoding (``None``: no limit): a number's JSON is a few dozen
        bytes, so a megabyte sent as a throttle is refused before it costs a decode on Zenoh's thread."""
        caps = [_payload_cap(self.gate.contracts.get(ch)) for ch in self.channels]
        if self.group is None:
            return tuple(caps)
        return (sum(_SCALAR_CAP if c is None else c for c in caps),)

    @property
    def refused(self) -> dict[str, dict[str, int]]:
        """Values refused, as ``{channel: {reason: count}}`` (a group's sample-wide refusals under its name)."""
        with self._gate_lock:
            return self.gate.counts()

    # -- Zenoh's threads -------------------------------------------------------------------------------
    def _on_sample(self, sample: Any) -> None:
        key = str(sample.key_expr)
        i = self._index.get(key)
        if i is None:
            if not key.startswith(f"{self.link.prefix}/{INTERNAL}/"):
                self._reject(key, "is not one of the configured channels")
            return
        self._heard_at = self.link.now()  # something reaches us, whatever becomes of it
        meta = unpack_attachment(_bytes(sample.attachment))
        delete = sample.kind == self._delete
        if meta is None and not delete:
            self._reject(key, "carries no age attachment (not an asyncdonkey publisher)")
            return
        if meta is not None and not self._in_order(i, *meta):
            return
        now = self.link.now()
        if delete:  # the absence of a value, whoever sends it
            self._refuse(i, "empty", "a DELETE sample is not a value", now)
            return
        value = self._value(i, sample, now)
        if value is not REFUSED and meta is not None:
            self._store(i, value, meta, now)

    def _in_order(self, i: int, age: float, seq: int, source: int) -> bool:
        """Age and sequence sanity for every numbered sample (:mod:`.sequence`): ``False`` for one not to take
        (counted; an implausible one logged, rate-limited)."""
        with self._lock:
            verdict = self._orders[i].check(age, seq, source)
            self.lost += verdict.lost
            self.restarts += verdict.restart
            if verdict.reason == OUT_OF_ORDER:
                self.out_of_order += 1
            elif verdict.reason == UNCONFIRMED:
                self.unconfirmed += 1
            elif verdict.reason == IMPLAUSIBLE:
                self.implausible += 1
            n = self.implausible
        if verdict.reason == IMPLAUSIBLE:
            key = self.link.key(self._cells[i])
            more = self._log.ready(("implausible", i), self.link.now())
            if more is not None:
                logger.warning(
                    "ZenohSubscriber on %r: refused a sample on %r: %s (%d implausible so far)%s",
                    self.link.prefix,
                    key,
                    verdict.detail,
                    n,
                    more,
                )
        return verdict.taken

    def _value(self, i: int, sample: Any, now: float) -> Any:
        """The sample's value as it may be stored (a group: the tuple of its values), or :data:`REFUSED`."""
        payload = sample.payload.to_bytes()
        encoding = str(sample.encoding)
        if not payload and not encoding.startswith(NDARRAY):  # a zero-size array has no bytes; nothing else
            return self._refuse(i, "empty", "an empty payload is not a value", now)
        cap = self._caps[i]
        if cap is not None and len(payload) > cap:
            return self._refuse(i, "size", f"a payload of {len(payload)} bytes, more than {cap}", now)
        key = self.link.key(self._cells[i])
        try:
            if self.group is not None:
                values = decode_group(payload, encoding, self.channels, key)
            else:
                values = (decode(payload, encoding, key),)
        except CodecError as exc:
            with self._gate_lock:
                self.malformed += 1
            return self._refuse(i, "encoding", str(exc), now)
        with self._gate_lock:
            admitted = tuple(self.gate.admit(ch, v, now) for ch, v in zip(self._channels_of(i), values, strict=True))
        if any(v is REFUSED for v in admitted):
            return REFUSED  # a command with a bad half is no command: neither half is stored
        return admitted if self.group is not None else admitted[0]

    def _channels_of(self, i: int) -> tuple[str, ...]:
        return self.channels if self.group is not None else (self.channels[i],)

    def _refuse(self, i: int, reason: str, detail: str, now: float) -> Any:
        key = self.link.key(self._cells[i])
        if key not in detail:
            detail = f"{detail} (on {key!r})"
        with self._gate_lock:
            return self.gate.refuse(self._cells[i], reason, detail, now)

    def _store(self, i: int, value: Any, meta: tuple[float, int, int], now: float) -> None:
        age_here = meta[0] + self.link.transit_s
        origin = now - age_here
        with self._lock:
            held = self._held[i]
            if held is not None and held.source != meta[2] and origin <= held.origin + self.same_frame_s:
                self.duplicates += 1  # another sender's answer to a frame already answered (or an older one)
                return
            if held is not None and held.fresh and not self._pushes:
                self.dropped += 1
            self._held[i] = _Held(value, origin, True, meta[2])
            self.received += 1
            if age_here > self.late_after_s:
                self.late += 1
        if self._pushes:
            if len(self.channels) == 1:
                pushed, pushed_origin = (value[0] if self.group is not None else value), origin
            else:  # every channel's newest value, as run() would return them, with the oldest origin
                pushed, pushed_origin = self._snapshot()
            for push in self._pushes:
                push(pushed, pushed_origin)
        if self.on_arrival is not None:
            self.on_arrival(self._cells[i])

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
        if self.group is not None:  # one cell holding every channel's value
            out = list(out[0]) if out[0] is not None else [None] * len(self.channels)
        return (out[0] if len(out) == 1 else tuple(out)), (oldest if math.isfinite(oldest) else None)

    def output_origin(self) -> float | None:
        """The oldest origin among the values the last ``run()`` returned (runtime clock)."""
        return self._origin

    def ages(self) -> dict[str, float]:
        """Channel → age of its held value now (s); ``inf`` for a channel that never arrived."""
        now = self.link.now()
        with self._lock:
            held = [self._held[0]] * len(self.channels) if self.group is not None else self._held
            return {ch: (now - h.origin if h else math.inf) for ch, h in zip(self.channels, held, strict=True)}

    async def update(self) -> None:
        """Measure the round trip to the other sessions on the prefix every ``ping_every_s`` (for the ages), and
        say once why nothing arrives when nothing has for ``silent_after_s``."""
        clock = get_clock()
        self.link.now = clock.now
        periods = [p for p in (self.ping_every_s, self.silent_after_s / 2) if p > 0]
        if not periods:
            return
        self._watch_from = clock.now()
        next_ping = -math.inf
        with Periodic(min(periods)) as every:
            while not self.link.closed:
                now = clock.now()
                if self.ping_every_s > 0 and now >= next_ping:
                    self.link.ping()
                    next_ping = now + self.ping_every_s - 1e-9
                self._watch_silence(now)
                await every.next()

    # -- silence -----------------------------------------------------------------------------------------
    def _watch_silence(self, now: float) -> None:
        """Log once per silence (nothing on the keys for ``silent_after_s``) why this receiver thinks nothing
        comes (:meth:`silence_report`), and once when samples come again."""
        if self.silent_after_s <= 0:
            return
        heard = self._heard_at
        since = heard if heard is not None else self._watch_from
        if since is None or now - since < self.silent_after_s:
            if self._silence_logged and heard is not None:
                self._silence_logged = False
                logger.info("ZenohSubscriber on %r: samples arrive again", self.link.prefix)
            return
        if not self._silence_logged:
            self._silence_logged = True
            self.silences += 1
            logger.warning("%s", self.silence_report(now - since))

    def silence_report(self, silent_s: float) -> str:
        """Why nothing has come for ``silent_s`` seconds, as far as this side can tell: what the session is
        connected to and, when that is nothing, the certificates of its config against this clock."""
        keys = ", ".join(repr(k) for k in self._index)
        head = f"ZenohSubscriber on {self.link.prefix!r}: nothing on {keys} for {silent_s:.1f} s"
        connected = _connections(self.link.session)
        if connected is None:
            return f"{head} (the session cannot say what it is connected to)"
        if connected:
            return (
                f"{head}, though this session is connected to {connected} other Zenoh session(s): the sender is"
                " not publishing these keys, or access rules drop its puts (a car takes commands only from the"
                " certificate name its rules give)"
            )
        config = self.link.config
        endpoints = config_value(config, "connect/endpoints") if config is not None else None
        where = f" at {', '.join(map(str, endpoints))}" if endpoints else ""
        problems = certificate_problems(config) if config is not None else []
        why = (
            f"; on this side: {'; '.join(problems)}"
            if problems
            else " (a certificate of another CA, or outside its validity window on either side's clock)"
        )
        return (
            f"{head}, and this session is connected to no other Zenoh session: the sender is not running, cannot"
            f" reach this machine{where}, or the TLS handshake fails{why}"
        )

    def counters(self) -> dict[str, int]:
        with self._gate_lock:
            refused = self.gate.total_refused
            malformed = self.malformed
        with self._lock:
            return {
                "received": self.received,
                "dropped": self.dropped,
                "out_of_order": self.out_of_order,
                "late": self.late,
                "lost": self.lost,
                "unexpected": self.unexpected,
                "refused": refused,
                "malformed": malformed,
                "restarts": self.restarts,
                "implausible": self.implausible,
                "unconfirmed": self.unconfirmed,
                "duplicates": self.duplicates,
            }

    def shutdown(self) -> None:
        try:
            self._sub.undeclare()
        except Exception:
            pass
        self.link.release()

    def __repr__(self) -> str:
        group = f", group={self.group!r}" if self.group is not None else ""
        return f"ZenohSubscriber({self.link.prefix!r}, {list(self.channels)!r}{group})"


#: the largest payload decoded for a scalar channel (a number, a bool, a mode): far more than any JSON of one
_SCALAR_CAP = 1024


def _payload_cap(contract: Contract | None) -> int | None:
    """The largest payload a value of this contract can arrive in (``None``: no contract, no limit)."""
    if contract is None:
        return None
    if contract.kind in (Kind.FLOAT, Kind.INT, Kind.BOOL, Kind.ENUM):
        return _SCALAR_CAP
    if contract.max_len is None:
        return None
    if contract.kind is Kind.ARRAY:
        return contract.max_len * np.dtype(contract.dtype).itemsize
    return contract.max_len


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


def _connections(session: Any) -> int | None:
    """How many other Zenoh sessions (peers, routers, clients) this session is connected to; ``None`` if it
    cannot say."""
    try:
        return len(list(session.info.transports()))
    except Exception:
        try:
            return len(list(session.info.peers_zid())) + len(list(session.info.routers_zid()))
        except Exception:
            return None


def _bytes(z: Any) -> bytes | None:
    return None if z is None else z.to_bytes()
