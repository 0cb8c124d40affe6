"""Precise mode of the :class:`~asyncdonkey.clock.DeadlineWaiter`: where to arm the timer, and learning it.

Precise mode sleeps to a *spin window* before each deadline and spins the rest on the clock. Where the machine's
wake-ups have a long tail it sleeps twice, to a guard before the window and then to the window, because a short
sleep right after a wake-up wakes more punctually than a long one. The window is learned from the lateness the
sleep before the spin actually shows (a high quantile, less the lateness precise mode accepts), kept per octave
of the period because a timer wakes later after a long sleep than after a short one. Every constant here was
chosen from measurements: docs/timing.md, "The precise waiter's constants: what was measured", has the figures.

:class:`PreciseWait` is the waiter's base class: the state and arithmetic of precise mode, apart from the
timers it arms (the waiter's own job). A base class rather than an object the waiter holds, so that the hot path
of a wait reads these attributes directly.
"""

from __future__ import annotations

import heapq
from array import array
from typing import TYPE_CHECKING, NamedTuple

if TYPE_CHECKING:
    from . import _timerfd

__all__ = ["PRECISE_TOLERANCE_S", "SHORT_SLEEP_MIN_S", "SPIN_BUDGET", "PreciseWait"]

# How the spin window is learned from observed timer lateness.
_LATE_SAMPLES = 1024  # recent samples kept: on a VM the slow wake-ups come in bursts, minutes apart
_LATE_QUANTILE = 0.99  # the ticks precise mode keeps within its tolerance
_LATE_REFRESH = 32  # recompute the window every this many samples
_LATE_WARMUP = 64  # waits with the start window before the first estimate (a few early samples mislead)
#: The lateness precise mode accepts at that quantile: the window is the quantile less this. Spinning the
#: last few microseconds too would cost CPU on every tick for nothing a car can notice (a servo pulse is
#: refreshed every 16-20 ms).
PRECISE_TOLERANCE_S = 20e-6
_WINDOW_FLOOR_S = 5e-6  # the window is at least this (the spin's own check-to-start cost) ...
#: ... and at most this: a longer spin made the next wake-ups later on a busy machine (the scheduler's fairness
#: counts the spin against the task), so the window grew with it.
_WINDOW_CEIL_S = 0.5e-3
#: ... and at most this fraction of the time between successive deadlines: a loaded machine's preemption
#: outliers cannot be spun away, and chasing them would make precise mode spin for a large part of each period.
SPIN_BUDGET = 0.03
#: Until the first samples are in, when no precise waiter has learned a window yet: a guess at the lateness of
#: the second, short sleep (see :data:`_GUARD_S`), well over its measured 99th percentile.
_WINDOW_START_S = 0.2e-3
#: The window the last precise waiter in this process learned: the machine's wake-up latency, which a new
#: waiter starts from instead of the guess (a drive restarted, a second periodic task).
_learned_window_s: float | None = None

#: Precise mode sleeps twice: its first timer is armed this long before the spin window, and a second, short
#: sleep takes it to the window, whose lateness has a tail much closer to its median than a long sleep's. The
#: guard itself is not spun: a longer one only makes the second sleep longer, so it is a constant, well over
#: the first sleep's 99th percentile.
_GUARD_S = 1e-3
_GUARD_SHARE = 0.1  # ... at most this fraction of the time between deadlines
#: ... and at least this, or precise mode sleeps once (1 kHz and faster): its sleeps are short already, and a
#: second wake-up per tick would cost more than the spin it saves.
_GUARD_MIN_S = 0.25e-3
#: A second sleep shorter than this is not armed (the rest is spun): it would wake later than the spin ends.
SHORT_SLEEP_MIN_S = 50e-6
#: Two sleeps pay only where the first sleep's lateness has a long tail: one sleep spins about its 99th
#: percentile less its median (less the tolerance), two sleeps cost a wake-up more and spin the second sleep's
#: spread. So precise mode goes to two sleeps when that percentile is more than this over the median, and back
#: to one when it is less than :data:`_ONE_STAGE_BELOW_S` (in between either costs about the same, and staying
#: put keeps the window learned).
_TWO_STAGE_ABOVE_S = 75e-6
_ONE_STAGE_BELOW_S = 45e-6
_FIRST_SAMPLES = 256  # recent lateness samples of the first sleep, for that choice


class _Learned(NamedTuple):
    """What precise mode learned at one period class (:func:`_period_class`), samples oldest first."""

    late: array[float]  # the window's samples: the lateness of the sleep before the spin
    two_stage: bool  # whether that is the second of two sleeps (see _TWO_STAGE_ABOVE_S) or the only one
    firsts: array[float]  # the first sleep's lateness, for the choice between one sleep and two


#: What was last learned at each *period class* (:func:`_period_class`): how late a timer wakes depends on how
#: long the machine slept before it. A waiter starting at a period this process has learned takes over that
#: period's samples and adds its own to them: a 20 Hz drive restarted after a 100 Hz one does not spin for
#: 100 Hz's latency, and a drive restarted at the same rate keeps its quantile over a thousand wake-ups instead of
#: starting again from the largest of its first few dozen (one outlier would set the window).
_learned: dict[int, _Learned] = {}


def _oldest_first(ring: array[float], n: int, size: int) -> array[float]:
    """A copy of a ring of at most ``size`` samples that ``n`` samples have been written to (appended until it
    is full, then each over the oldest, at ``n % size``), oldest first."""
    start = n % size if len(ring) == size else 0
    return ring[start:] + ring[:start]


def _period_class(gap_s: float) -> int:
    """The octave of the time between two deadlines, in microseconds (20 Hz and 100 Hz differ, 20 and 25 Hz
    do not): the key of :data:`_learned`."""
    return int(gap_s * 1e6).bit_length()


class PreciseWait:
    """Precise mode's state and arithmetic, for the :class:`~asyncdonkey.clock.DeadlineWaiter` built on it.

    The waiter arms its timer for :meth:`_target` (the deadline, or in precise mode the spin window before it),
    with the first of two sleeps ending :attr:`_guard_s` before that; it reports each wake-up of a first sleep to
    :meth:`_first_woke` and the lateness of the sleep before the spin to :meth:`_learn`. Outside precise mode
    :meth:`_target` is the deadline and nothing is learned.
    """

    __slots__ = (
        "_first_at",
        "_first_late",
        "_first_n",
        "_guard_s",
        "_last_deadline",
        "_late",
        "_late_n",
        "_other_late",
        "_period_class",
        "_period_given",
        "_refresh_due",
        "_two_stage",
        "precise",
        "spin_window_s",
    )

    #: The waiter's timerfd (None on the loop's timers, which are too coarse for a second sleep): a slot of the
    #: waiter's, read here.
    _tfd: _timerfd.Timerfd | None

    def __init__(self, precise: bool) -> None:
        self.precise = precise
        #: precise mode on a timerfd: how long before the spin window the first of its two sleeps ends
        self._guard_s = 0.0
        self._two_stage = True  # precise mode sleeps twice (until the first sleep's lateness says otherwise)
        self._first_at = 0.0  # when the pending first sleep was armed to end (0: none pending)
        self._first_late = array("d")  # the first sleep's recent lateness, in both modes
        self._first_n = 0
        self._other_late = array("d")  # the window's samples of the other mode, kept for a switch back
        #: Precise mode: seconds before the deadline the timer is armed; the rest is spun. Learned.
        start = _WINDOW_START_S if _learned_window_s is None else _learned_window_s
        self.spin_window_s = start if precise else 0.0
        self._late = array("d")
        self._late_n = 0
        self._refresh_due = False
        self._last_deadline = float("inf")
        self._period_class = 0  # of the time between this waiter's deadlines: not known yet
        self._period_given = False  # by call_at(period=): then a skip's longer gap does not change the class

    def _start_period(self, deadline: float, period: float) -> None:
        """Deadlines ``period`` apart start at ``deadline`` (``call_at(period=...)`` in precise mode): the first
        wait already starts from this period's window, spin budget and guard."""
        self._enter_period_class(_period_class(period))
        self._last_deadline = deadline - period

    def _target(self, deadline: float) -> float:
        """When to arm the timer for ``deadline``: the deadline itself, or in precise mode the learned spin window
        before it (at most :data:`SPIN_BUDGET` of the time since the previous deadline)."""
        if not self.precise:
            return deadline
        if self._refresh_due:
            self._refresh_window()
        gap, self._last_deadline = deadline - self._last_deadline, deadline
        if gap > 0 and not self._period_given:
            self._enter_period_class(_period_class(gap))
        window = self.spin_window_s
        if gap > 0 and window > gap * SPIN_BUDGET:
            window = gap * SPIN_BUDGET
        if self._tfd is not None and self._two_stage:  # (the loop's timers are too coarse for a second sleep)
            guard = gap * _GUARD_SHARE if 0 < gap * _GUARD_SHARE < _GUARD_S else _GUARD_S
            self._guard_s = guard if guard >= _GUARD_MIN_S else 0.0
        else:
            self._guard_s = 0.0
        return deadline - window

    def _first_woke(self, t: float) -> None:
        """A wake-up at ``t`` while a first sleep is pending: with two sleeps, keep its lateness (with one, the
        window's sample is the first sleep's: :meth:`_learn`), unless it is a readiness left from an earlier
        arming (before the first sleep's end)."""
        first = self._first_at
        if t < first:
            return
        self._first_at = 0.0
        if self._two_stage:
            self._keep_first(t - first)

    def _keep_first(self, late: float) -> None:
        samples = self._first_late
        if len(samples) < _FIRST_SAMPLES:
            samples.append(late)
        else:
            samples[self._first_n % _FIRST_SAMPLES] = late
        self._first_n += 1

    def _learn(self, late: float) -> None:
        """Keep the recent lateness of the early timer. Called between the wake-up and the deadline, so it only
        stores: the window is worked out again when the next wait is armed (:meth:`_target`), after the work."""
        samples = self._late
        n = self._late_n
        if len(samples) < _LATE_SAMPLES:
            samples.append(late)
        else:
            samples[n % _LATE_SAMPLES] = late
        n = self._late_n = n + 1
        if n % _LATE_REFRESH == 0 and n >= _LATE_WARMUP:
            self._refresh_due = True
        if not self._two_stage:  # one sleep: it is the first sleep too
            self._keep_first(late)

    def _enter_period_class(self, cls: int) -> None:
        """The time between deadlines is in period class ``cls``: until this waiter has learned a window of its
        own, take over the samples last learned from at that class, if any, and set the window from them with
        its own. A waiter that has learned keeps its own samples whatever its deadlines do (irregular waits
        change class from one wait to the next)."""
        if cls == self._period_class:
            return
        self._period_class = cls
        if self._late_n < _LATE_WARMUP:
            past = _learned.get(cls)
            if past is not None:
                if self._first_n < _LATE_WARMUP:  # the first sleeps' too, for the choice
                    self._first_late = (past.firsts + self._firsts_oldest_first())[-_FIRST_SAMPLES:]
                    self._first_n = len(self._first_late)
                own = self._late if past.two_stage == self._two_stage else array("d")  # (of the same kind only)
                self._two_stage = past.two_stage
                self._late = samples = (past.late + own)[-_LATE_SAMPLES:]  # oldest first: the next replaces [0]
                self._late_n = len(samples)
                self._refresh_window()

    def _refresh_window(self) -> None:
        """Choose one sleep or two (:data:`_TWO_STAGE_ABOVE_S`), and set the spin window to the high quantile of
        the recent lateness of the sleep before the spin, less the tolerance."""
        self._refresh_due = False
        if self._first_n >= _LATE_WARMUP and self._tfd is not None:
            firsts = sorted(self._first_late)
            spread = firsts[int(_LATE_QUANTILE * (len(firsts) - 1))] - firsts[len(firsts) // 2]
            if spread > _TWO_STAGE_ABOVE_S if not self._two_stage else spread < _ONE_STAGE_BELOW_S:
                self._switch_stages()
        samples = self._late
        if not samples:  # two sleeps again, none learned of the second yet: the window so far until then
            return
        rank = len(samples) - min(len(samples) - 1, int(_LATE_QUANTILE * len(samples)))  # from the top, 1-based
        q = heapq.nlargest(rank, samples)[-1]
        global _learned_window_s
        self.spin_window_s = _learned_window_s = min(max(q - PRECISE_TOLERANCE_S, _WINDOW_FLOOR_S), _WINDOW_CEIL_S)
        if self._period_class:
            late = _oldest_first(samples, self._late_n, _LATE_SAMPLES)
            _learned[self._period_class] = _Learned(late, self._two_stage, self._firsts_oldest_first())

    def _firsts_oldest_first(self) -> array[float]:
        return _oldest_first(self._first_late, self._first_n, _FIRST_SAMPLES)

    def _switch_stages(self) -> None:
        """From two sleeps to one or back. The window's samples change kind with it, to those of the last time
        this waiter was in the other mode; going to one sleep for the first time, to the first sleep's lateness
        so far (which lacks the way from the timer into the callback that ``arrived()`` measures, but the
        window learns it within :data:`_FIRST_SAMPLES` waits); going to two for the first time, to none (the
        window stays as it is until the second sleep's own samples are in)."""
        two = not self._two_stage
        current = self._late
        if two or len(self._other_late) >= _LATE_WARMUP:
            self._late = self._other_late
        else:
            self._late = self._firsts_oldest_first()
        self._other_late = current
        self._late_n = len(self._late)
        self._two_stage = two

    def max_spin_s(self, period: float) -> float:
        """The longest this waiter spins before a deadline when deadlines are ``period`` apart: precise mode's
        window at its ceiling or its budget, whichever is less (0 outside precise mode)."""
        return min(_WINDOW_CEIL_S, SPIN_BUDGET * period) if self.precise else 0.0

    @property
    def sleeps(self) -> int:
        """How many times precise mode slept before its spin at the last wait: 2 where the machine's wake-ups
        have a long tail (a guard sleep, then a short one; see :data:`_TWO_STAGE_ABOVE_S`), else 1 (and 1
        outside precise mode)."""
        return 2 if self.precise and self._two_stage and self._guard_s > 0 else 1
