"""StaleCommandStop: an old command becomes the stopped value, counted and logged once per entry."""

import logging

import pytest

from asyncdonkey import Vehicle
from asyncdonkey.parts.failsafe import StaleCommandStop


class Commands:
    """A controller that answers on the ticks listed, and is silent otherwise (its channel keeps its origin)."""

    def __init__(self, live_ticks: set[int]) -> None:
        self.live = live_ticks
        self.k = -1

    def run(self):
        self.k += 1
        return 0.6 if self.k in self.live else None


class Probe:
    def __init__(self) -> None:
        self.rows = []

    def run(self, throttle):
        self.rows.append(throttle)


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_old_command_is_replaced_by_stop_and_fresh_command_resumes(caplog):
    v = Vehicle()
    v.add(Commands(set(range(5)) | {20, 21}), outputs=["throttle"])
    stop = StaleCommandStop(0.25)
    v.add(stop, inputs=["throttle", "throttle@age"], outputs=["throttle"])
    probe = Probe()
    v.add(probe, inputs=["throttle"])
    with caplog.at_level(logging.WARNING, logger="asyncdonkey.parts.failsafe"):
        await v.run(rate_hz=20, max_loop_count=30)
    # the last fresh command at tick 4 (0.20 s) is 0.25 s old at tick 9: stopped from there to tick 19
    assert probe.rows[:9] == [0.6] * 9
    assert probe.rows[9:20] == [0.0] * 11
    assert probe.rows[20:26] == [0.6] * 6 and probe.rows[26:] == [0.0] * 4
    assert stop.events == 2
    assert "throttle command is 250 ms old (limit 250 ms)" in caplog.text


def test_arguments_are_checked():
    with pytest.raises(ValueError, match="max_age_s"):
        StaleCommandStop(0)
    assert StaleCommandStop().run(None, None) is None


class Neutral:
    """A controller nobody has touched: neutral at start-up, then nothing (its channel keeps its origin)."""

    def __init__(self, then: dict[int, float] | None = None) -> None:
        self.then = then or {}
        self.k = -1

    def run(self):
        self.k += 1
        if self.k == 0:
            return 0.0
        return self.then.get(self.k)


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_a_neutral_command_going_stale_before_anyone_drives_is_no_event(caplog):
    v = Vehicle()
    v.add(Neutral(then={40: 0.5}), outputs=["throttle"])
    stop = StaleCommandStop(0.25)
    v.add(stop, inputs=["throttle", "throttle@age"], outputs=["throttle"])
    probe = Probe()
    v.add(probe, inputs=["throttle"])
    with caplog.at_level(logging.WARNING, logger="asyncdonkey.parts.failsafe"):
        await v.run(rate_hz=20, max_loop_count=60)
    # neutral from start-up, stale from tick 5: nothing held back, nothing said
    assert probe.rows[:40] == [0.0] * 40
    # the first real command (tick 40) drives, and is stopped 250 ms later: that one is an event
    assert probe.rows[40:45] == [0.5] * 5 and probe.rows[45:] == [0.0] * 15
    assert stop.events == 1
    assert caplog.text.count("StaleCommandStop") == 1 and "(event 1)" in caplog.text
