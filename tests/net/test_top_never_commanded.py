"""``top`` shows a car that no command has reached as ``NO-CMD``, not ``live``.

A car's status lists the ages of channels it names, ``null`` for a channel that holds no value. A remote pilot's
subscriber writes ``None`` (dated by the tick, so with a fresh age) until its first command arrives: the status
gave that ``None`` an age of a few ms, and ``top`` said ``live`` for a car standing on its failsafe. When every
command channel (``pilot/...``) the car lists holds no value, the car has no command: ``NO-CMD``. The documents
below are the car's own (``FleetStatus``), first as plain JSON, then published by a car on loopback that gets its
first command half-way.
"""

from __future__ import annotations

import asyncio
import json

import numpy as np
import pytest

from asyncdonkey import Vehicle
from asyncdonkey.parts.zenoh import PILOT_COMMAND, ZenohLink, ZenohPublisher, ZenohSubscriber, zenoh_config
from asyncdonkey.parts.zenoh.fleet import FleetStatus, FleetWatcher, car_state, never_commanded, render_fleet

from ..waiting import await_until
from .zenoh_loopback import free_port, listener

#: ages as FleetStatus publishes them (examples/car.py lists these three)
NEVER = {"cam/image_array": 12.5, "pilot/throttle": None, "sim/throttle": None}
DRIVING = {"cam/image_array": 12.5, "pilot/throttle": 31.0, "sim/throttle": 31.0}


def _doc(ages: dict | None) -> dict:
    doc = {"car": "cars/x", "hz": 20.0, "mode": "local", "parts": {}}
    if ages is not None:
        doc["ages_ms"] = ages
    return json.loads(json.dumps(doc))  # what a watcher decodes: None as JSON null


@pytest.mark.parametrize(
    ("ages", "state"),
    [
        (NEVER, "NO-CMD"),
        (DRIVING, "live"),
        ({"pilot/angle": None, "pilot/throttle": None}, "NO-CMD"),
        ({"pilot/angle": None, "pilot/throttle": 40.0}, "live"),  # one command channel written: commanded
        ({"cam/image_array": 400.0, "pilot/throttle": None}, "NO-CMD"),  # no command yet says more than STALE
        ({"cam/image_array": 12.0, "pilot/throttle": 400.0}, "STALE"),  # commanded once, then the commands stopped
        ({"cam/image_array": None}, "live"),  # no command channel listed: nothing to judge by
        ({}, "live"),
        (None, "live"),
    ],
)
def test_the_state_of_a_car_by_its_command_ages(ages, state):
    doc = _doc(ages)
    assert car_state(doc, 0.5) == state
    assert never_commanded(doc) is (state == "NO-CMD")


def test_a_silent_car_is_silent_whether_or_not_it_was_ever_commanded():
    assert car_state(_doc(NEVER), 5.0, gone_after_s=3.0) == "SILENT"


def test_the_screen_counts_never_commanded_cars_and_marks_their_rows():
    cars = {
        "cars/car1": (_doc(DRIVING), 100.0),
        "cars/car2": (_doc(NEVER), 100.0),
        "cars/car3": (_doc({"pilot/throttle": 900.0}), 100.0),
        "cars/car4": (_doc(NEVER), 90.0),  # silent for 10 s
        "cars/car5": (_doc(NEVER), 100.0),
    }
    lines = render_fleet(cars, 100.5).splitlines()
    assert lines[0] == ("asyncdonkey top - 5 cars seen, 1 live, 2 no command, 1 stale, 1 silent (sorted by name)")
    states = {line.split()[0]: line.split()[1] for line in lines[2:]}
    assert states == {"cars/car1": "live", "cars/car2": "NO-CMD", "cars/car3": "STALE", "cars/car4": "SILENT",
                      "cars/car5": "NO-CMD"}  # fmt: skip
    row = next(line for line in lines if line.startswith("cars/car2"))
    assert "pilot/throttle=- " in row + " "  # the age column says why


class Camera:
    def run(self):
        return np.zeros((12, 16, 3), np.uint8)


@pytest.mark.realtime
@pytest.mark.network
@pytest.mark.asyncio
async def test_a_car_shows_no_cmd_until_its_first_command_then_live():
    """A car on loopback with a remote pilot's subscriber and its FleetStatus: before any command the view
    shows it NO-CMD; once a pilot sends it commands, live."""
    port = free_port()
    view = ZenohLink("fleet/view", listener(port))
    connect = zenoh_config(mode="client", connect=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False)
    car = ZenohLink("cars/car1", connect)
    pilot = ZenohLink("cars/car1", zenoh_config(mode="client", connect=[f"tcp/127.0.0.1:{port}"],
                                                multicast_scouting=False))  # fmt: skip
    watcher = FleetWatcher(view.session)
    cmd = ["pilot/angle", "pilot/throttle"]
    try:
        v = Vehicle()
        v.add(Camera(), outputs=["cam/image_array"])
        v.add(ZenohSubscriber(car, cmd, group=PILOT_COMMAND), outputs=cmd)
        v.add(FleetStatus(car, v, ages=["cam/image_array", *cmd], every_s=0.1), inputs=["user/mode"])
        publisher = ZenohPublisher(pilot, cmd, group=PILOT_COMMAND)
        drive = asyncio.ensure_future(v.run(rate_hz=20, duration=8.0))

        def state() -> str | None:
            seen = watcher.snapshot().get("cars/car1")
            return None if seen is None else car_state(seen[0], 0.0)

        await await_until(lambda: state() == "NO-CMD", timeout=5, what=lambda: f"NO-CMD in {watcher.snapshot()}")
        doc = watcher.snapshot()["cars/car1"][0]
        assert doc["ages_ms"]["pilot/throttle"] is None and doc["ages_ms"]["cam/image_array"] is not None
        assert "1 no command" in render_fleet(watcher.snapshot(), 0.0)

        async def command() -> None:
            while not drive.done():
                publisher.run(0.0, 0.3, 0.0, 0.0)
                await asyncio.sleep(0.05)

        commanding = asyncio.ensure_future(command())
        await await_until(lambda: state() == "live", timeout=5, what="the car's status once commanded")
        assert watcher.snapshot()["cars/car1"][0]["ages_ms"]["pilot/throttle"] is not None
        v.stop()
        await drive
        commanding.cancel()
    finally:
        watcher.close()
        for link in (car, pilot, view):
            link.close()
