"""Which numbered samples a receiver takes: plausible ages, and sequence numbers that no sample can lock.

Every asyncdonkey sample carries ``(age, seq, source)`` (:mod:`.codec`). The receiver uses them to drop late
and duplicated samples and to count losses, but whoever can put a sample on a key chooses all three, and a
single bad one must never decide what the receiver does with the good ones that follow. Before these rules, a
sample numbered 2**64-1 under the pilot's own source made every later command "out of order" (the car stopped
for good, and ``lost`` grew by 1.8e19), and a sample aged 1e300 s was taken as the newest command.

**Plausible.** A sample whose age is not a finite number in ``[0, max_age_s]`` (10 s by default: far beyond
any transit or any use a drive loop has for it; the failsafe window is 250 ms), or whose sequence number is 0
(numbering starts at 1), is *implausible*: refused, counted, and it changes nothing here.

**Streams, not one window.** A receiver tracks a few *streams* per key (:data:`STREAMS`): a source and the
newest sequence number taken in it. A sample *continues* a stream of its source when its number is above
that stream's newest by at most :data:`MAX_JUMP` (the gap is counted as lost: never more than ``MAX_JUMP - 1``
a sample, so the count cannot run away); the closest such stream takes it, so the stream that took a
sender's previous sample always takes its next one, whatever the other streams hold. A sample that continues
no stream:

* repeats a stream's newest number: a duplicate, refused (``out_of_order``);
* otherwise starts a new, *unconfirmed* stream and is refused (``out_of_order`` when its number is below one
  of its source's streams, ``implausible`` when it jumps more than ``MAX_JUMP`` past them, ``unconfirmed``
  when its source is new). The next sample continuing it confirms it and is taken: a restarted sender
  (a new source, or its numbering back near 1) or a genuine jump costs one sample;
* except the very first sample a receiver sees: it starts the first stream and is taken.

A late sample's stream lingers (until the table is full) and may take one copy of a later sample; on one
Zenoh route samples are neither reordered nor duplicated, so this costs nothing in practice, and a copy says
nothing a peer allowed to put could not say anyway.

**Why nothing can lock a sender out.** A stream's newest number moves only when a sample continues it, and a
sample that continues no stream moves no stream: it starts its own. So the stream holding the sender's
previous number is still there for its next sample, and no stream lies between the two, unless some other
sample arrived in between (one that continued that stream past it, or evicted it from the table of
:data:`STREAMS`). Hence, for a sender numbering 1, 2, 3, ...: a sample of it
is refused only if some other sample arrived since its previous one, and after the last foreign sample at most
one of its samples is refused (``tests/net/test_sequence.py`` checks this with hypothesis for any interleaving
of hostile samples). What this does not do is tell a hostile *valid* sample from a genuine one: a peer that may
put on the command key can command the car. Who may put is the job of the access rules (``docs/scale-out.md``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

__all__ = ["MAX_AGE_S", "MAX_JUMP", "STREAMS", "SampleOrder", "Verdict", "plausible_age"]

#: the oldest age (s) a sample may say it has at send time (far beyond any transit; see the module docstring)
MAX_AGE_S = 10.0
#: the largest step in sequence numbers a stream takes at once (a longer gap needs a second sample to confirm)
MAX_JUMP = 1000
#: how many streams a receiver tracks per key (a restarted sender's old stream is forgotten when it is full)
STREAMS = 4
#: the largest sequence number on the wire (uint64)
SEQ_MAX = 2**64 - 1

#: why a sample was refused (``Verdict.reason``); ``""``: taken
TAKEN = ""
IMPLAUSIBLE = "implausible"
OUT_OF_ORDER = "out_of_order"
UNCONFIRMED = "unconfirmed"


def plausible_age(age: float, max_age_s: float = MAX_AGE_S) -> bool:
    """Whether ``age`` (s, the sender's age of the sensing behind a sample) is finite and in ``[0, max_age_s]``."""
    return isinstance(age, float | int) and math.isfinite(age) and 0.0 <= age <= max_age_s


@dataclass(frozen=True, slots=True)
class Verdict:
    """What to do with one sample: take it or not (``reason`` says why not), the samples it shows were lost, and
    whether it confirmed a new stream (a restarted sender, or a resync after a jump)."""

    reason: str = TAKEN
    detail: str = ""
    lost: int = 0
    restart: bool = False

    @property
    def taken(self) -> bool:
        return self.reason == TAKEN


_TAKEN = Verdict()


@dataclass(slots=True)
class _Stream:
    source: int
    newest: int
    confirmed: bool
    used: int  # when it last took a sample (the tracker's own count), to forget the stalest first


class SampleOrder:
    """The streams of one key (see the module docstring). Not thread-safe: the receiver holds its lock."""

    __slots__ = ("_streams", "_tick", "max_age_s", "max_jump", "size")

    def __init__(self, max_age_s: float = MAX_AGE_S, max_jump: int = MAX_JUMP, size: int = STREAMS) -> None:
        if not (math.isfinite(max_age_s) and max_age_s > 0):
            raise ValueError(f"SampleOrder: max_age_s must be a positive number of seconds, got {max_age_s!r}")
        if max_jump < 1 or size < 1:
            raise ValueError(f"SampleOrder: max_jump and size must be >= 1, got {max_jump!r} and {size!r}")
        self.max_age_s = float(max_age_s)
        self.max_jump = int(max_jump)
        self.size = int(size)
        self._streams: list[_Stream] = []
        self._tick = 0

    def check(self, age: float, seq: int, source: int) -> Verdict:
        """Judge one sample and update the streams (an implausible sample changes nothing)."""
        if not plausible_age(age, self.max_age_s):
            return Verdict(IMPLAUSIBLE, f"an age of {age!r} s (a plausible one is in [0, {self.max_age_s:g}] s)")
        if not 1 <= seq <= SEQ_MAX:
            return Verdict(IMPLAUSIBLE, f"sequence number {seq} (numbering starts at 1)")
        self._tick += 1
        if not self._streams:
            self._streams.append(_Stream(source, seq, True, self._tick))
            return _TAKEN
        mine = [s for s in self._streams if s.source == source]
        below = [s for s in mine if s.newest < seq <= s.newest + self.max_jump]
        if below:
            return self._continue(max(below, key=lambda s: s.newest), seq)
        if any(s.newest == seq for s in mine):
            return Verdict(OUT_OF_ORDER, f"sequence number {seq} again (a duplicate)")
        self._start(source, seq)
        if not mine:
            return Verdict(UNCONFIRMED, "the first sample of a new source (taken from its next one on)")
        highest = max(s.newest for s in mine)
        if seq < highest:
            return Verdict(OUT_OF_ORDER, f"sequence number {seq} after {highest} (late, or the sender restarted)")
        return Verdict(IMPLAUSIBLE, f"sequence number {seq} after {highest}: a jump of more than {self.max_jump}")

    def _continue(self, stream: _Stream, seq: int) -> Verdict:
        lost = seq - stream.newest - 1
        restart = not stream.confirmed
        stream.newest, stream.confirmed, stream.used = seq, True, self._tick
        # another stream of this source that had reached this number is this one now
        self._streams = [s for s in self._streams if s is stream or s.source != stream.source or s.newest != seq]
        return Verdict(lost=lost, restart=restart) if lost or restart else _TAKEN

    def _start(self, source: int, seq: int) -> None:
        """A new unconfirmed stream; when the table is full, forget an unconfirmed one first, the stalest."""
        if len(self._streams) >= self.size:
            stale = min(self._streams, key=lambda s: (s.confirmed, s.used))
            self._streams.remove(stale)
        self._streams.append(_Stream(source, seq, False, self._tick))

    def streams(self) -> list[tuple[int, int, bool]]:
        """``(source, newest, confirmed)`` of each tracked stream, for tests and reports."""
        return [(s.source, s.newest, s.confirmed) for s in self._streams]
