"""The watchdog stops the car when the loop thread cannot: on the real loop, against the PCA9685 register model.

These are real-time tests: they assert bounds a loaded 2-core machine keeps (the failsafe window plus 500 ms),
not the figures, which ``benchmarks/safety.py`` measures.
"""

import logging
import time

import pytest

from asyncdonkey import Vehicle
from asyncdonkey.loop import run_blocking

from .rig import HALF, NEUTRAL, Const, Rig

pytestmark = [pytest.mark.realtime]

WINDOW = 0.25
# What a loaded 2-core machine adds to the failsafe window before the chip shows neutral: the watchdog's thread and
# the bus's must be scheduled. 150 ms was not enough beside a busy process per core and a second test suite (the
# pin went neutral 282 ms late). The tests still tell a watchdog that works from one that does not: without it
# the pin would stay at the command until the block ends, 1 s or more after it began (asserted apart).
SLACK = 0.5


class Blocker:
    """A sync part that holds the loop thread on one tick: sleeping (GIL released) or spinning (GIL held)."""

    def __init__(self, at: int, seconds: float, spin: bool = False) -> None:
        self.at = at
        self.seconds = seconds
        self.spin = spin
        self.k = 0
        self.started: float | None = None
        self.ended: float | None = None

    def run(self) -> None:
        self.k += 1
        if self.k != self.at:
            return
        self.started = time.monotonic()
        if self.spin:
            end = self.started + self.seconds
            while time.monotonic() < end:
                pass
        else:
            time.sleep(self.seconds)
        self.ended = time.monotonic()


def _drive(blocker: Blocker, **throttle_kw):
    rig = Rig()
    v = Vehicle()
    v.add(Const(0.5), outputs=["throttle"])
    throttle = rig.throttle(**throttle_kw)
    v.add(throttle, inputs=["throttle", "throttle@age"], name="throttle")
    v.add(blocker, name="Pilot")
    try:
        report = run_blocking(v.run(20, max_loop_count=blocker.at + 10))
    finally:
        rig.close()
    return rig, throttle, report


@pytest.mark.parametrize("spin", [False, True], ids=["sleeping", "spinning-with-the-GIL"])
def test_a_blocked_loop_cannot_defeat_the_throttle_failsafe(spin, caplog):
    caplog.set_level(logging.WARNING)
    blocker = Blocker(at=10, seconds=1.2, spin=spin)
    rig, _throttle, report = _drive(blocker)
    t0 = blocker.started
    assert t0 is not None and blocker.ended is not None
    # driving at 0.5 when the part blocked the loop thread ...
    assert rig.pca.pulse_at(t0) == HALF
    # ... stopped by the watchdog within the failsafe window (the command's age), long before the block ended
    stopped = rig.pca.first_time(NEUTRAL, t0)
    assert stopped is not None
    assert stopped - t0 <= WINDOW + SLACK
    assert stopped < blocker.ended
    # and driving again once fresh commands flow
    assert rig.pca.first_time(HALF, blocker.ended) is not None
    assert report.watchdog_events >= 1
    ms, part = report.longest_block_ms
    assert part == "Pilot" and ms >= 1150
    messages = [r.getMessage() for r in caplog.records]
    assert any("watchdog" in m and "'throttle'" in m and "blocked" in m and "by part 'Pilot'" in m for m in messages), (
        messages
    )
    assert any(m.startswith("loop blocked 1,") and "by part 'Pilot'" in m for m in messages), messages


def test_no_watchdog_event_while_commands_are_fresh():
    blocker = Blocker(at=10, seconds=0.05)  # a 50 ms hiccup is well inside the window
    rig, _throttle, report = _drive(blocker)
    assert report.watchdog_events == 0
    assert report.longest_block_ms is None
    assert NEUTRAL not in [p for t, p in rig.pca.timeline if blocker.started <= t <= blocker.ended + 0.1]


def test_the_failsafe_window_is_the_actuators():
    blocker = Blocker(at=10, seconds=1.0)
    rig, _throttle, _report = _drive(blocker, failsafe_age_s=0.6)
    stopped = rig.pca.first_time(NEUTRAL, blocker.started)
    assert stopped is not None
    assert 0.6 - 0.06 <= stopped - blocker.started <= 0.6 + SLACK


def test_without_an_age_input_there_is_nothing_to_watch():
    rig = Rig()
    v = Vehicle()
    v.add(Const(0.5), outputs=["throttle"])
    v.add(rig.throttle(), inputs=["throttle"], name="throttle")
    blocker = Blocker(at=5, seconds=0.5)
    v.add(blocker)
    report = run_blocking(v.run(20, max_loop_count=10))
    rig.close()
    assert report.watchdog_events == 0
    assert rig.pca.pulse_at(blocker.ended) == HALF  # documented: wire "throttle@age" to get the failsafe


class NackingBlocker(Blocker):
    """Blocks the loop thread while the servo board NACKs: the first safe-state writes fail."""

    def __init__(self, rig: Rig, nacks: int, **kw) -> None:
        super().__init__(**kw)
        self.rig, self.nacks = rig, nacks

    def run(self) -> None:
        if self.k + 1 == self.at:
            self.rig.sim.bus(1).nack(0x40, times=self.nacks)
        super().run()


def test_a_safe_state_write_that_fails_is_retried_until_it_lands(caplog):
    """12 NACKs: three of the watchdog's writes fail (each is the bus's four attempts); the fourth lands."""
    caplog.set_level(logging.WARNING)
    rig = Rig()
    blocker = NackingBlocker(rig, 12, at=10, seconds=2.0)
    v = Vehicle()
    v.add(Const(0.5), outputs=["throttle"])
    v.add(rig.throttle(), inputs=["throttle", "throttle@age"], name="throttle")
    v.add(blocker, name="Pilot")
    try:
        report = run_blocking(v.run(20, max_loop_count=20))
    finally:
        rig.close()
    t0 = blocker.started
    assert rig.pca.pulse_at(t0) == HALF
    stopped = rig.pca.first_time(NEUTRAL, t0)
    assert stopped is not None and stopped < blocker.ended  # not left driving for the whole block
    assert stopped - t0 <= WINDOW + SLACK
    assert report.watchdog_failed_attempts == 3
    unsafe = report.unsafe_ms["throttle"]
    assert unsafe["events"] == 1
    assert 0 < unsafe["max"] <= SLACK * 1e3  # from the deadline to the landing, retries included
    messages = [r.getMessage() for r in caplog.records]
    assert any("retrying until it lands" in m and "'throttle'" in m for m in messages), messages
    assert any("safe state written after 4 attempts" in m for m in messages), messages
    assert "unsafe (throttle): 1 times" in v.format_report(report)
