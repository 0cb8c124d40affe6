"""The fleet view: two cars publish their status on loopback, ``top`` renders both (and notices one leave)."""

import asyncio
import io
import json
import types

import pytest

from asyncdonkey import Vehicle
from asyncdonkey.parts.zenoh import ZenohLink, zenoh_config
from asyncdonkey.parts.zenoh.fleet import FleetStatus, FleetWatcher, render_fleet, top_main

from ..waiting import await_until
from .zenoh_loopback import free_port, listener


class Busy:
    def run(self):
        return 1.0


class Mode:
    def __init__(self, mode: str) -> None:
        self.mode = mode

    def run(self):
        return self.mode


def _car(link: ZenohLink, mode: str) -> tuple[Vehicle, FleetStatus]:
    v = Vehicle()
    v.add(Busy(), outputs=["pilot/throttle"])
    v.add(Mode(mode), outputs=["user/mode"])
    status = FleetStatus(link, v, ages=["pilot/throttle", "cam/image_array"], every_s=0.1)
    v.add(status, inputs=["user/mode", "tub/num_records"])
    return v, status


@pytest.mark.realtime
@pytest.mark.network
@pytest.mark.asyncio
async def test_two_cars_publish_status_and_the_view_shows_both():
    port = free_port()
    view_link = ZenohLink("fleet/view", listener(port))
    a = ZenohLink(
        "cars/alpha", zenoh_config(mode="client", connect=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False)
    )
    b = ZenohLink(
        "cars/bravo", zenoh_config(mode="client", connect=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False)
    )
    watcher = FleetWatcher(view_link.session)
    try:
        va, status_a = _car(a, "local")
        vb, status_b = _car(b, "user")
        await asyncio.gather(va.run(rate_hz=50, duration=0.6), vb.run(rate_hz=20, duration=0.6))
        await await_until(lambda: len(watcher.snapshot()) == 2)
        assert status_a.published >= 4 and status_b.published >= 4
        cars = watcher.snapshot()
        doc = cars["cars/alpha"][0]
        # the rate is what the car achieved: on a loaded 2-core machine a 50 Hz car may reach 31 Hz, never more
        # than its own rate, and the status counts every tick that ran
        assert doc["mode"] == "local" and 0 < doc["hz"] <= 55 and doc["ticks"] >= 4
        assert set(doc["parts"]) >= {"Busy", "FleetStatus"}
        assert doc["ages_ms"]["cam/image_array"] is None and doc["ages_ms"]["pilot/throttle"] < 1000
        assert doc["lateness_p99_ms"] is not None and doc["overruns"] <= doc["ticks"]
        assert cars["cars/bravo"][0]["mode"] == "user" and 0 < cars["cars/bravo"][0]["hz"] <= 22
        now = max(t for _, t in cars.values())
        screen = render_fleet(cars, now, width=200)  # the state and latency columns leave 120 too few for the ages
        lines = screen.splitlines()
        assert lines[0] == ("asyncdonkey top - 2 cars seen, 2 live, 0 no command, 0 stale, 0 silent (sorted by name)")
        assert lines[1].split()[:4] == ["CAR", "STATE", "HZ", "LAT"]
        alpha = next(line for line in lines if line.startswith("cars/alpha"))
        bravo = next(line for line in lines if line.startswith("cars/bravo"))
        assert " local " in alpha and " user " in bravo and alpha.split()[1] == "live"
        assert "pilot/throttle=" in alpha and "cam/image_array=-" in alpha
        assert any(line.strip().startswith("parts ms: ") and "Busy" in line for line in lines)
        # 10 s later nothing more came from either: both shown as silent
        assert "0 live" in render_fleet(cars, now + 10) and "2 silent" in render_fleet(cars, now + 10)
        assert render_fleet(cars, now + 10).count(" SILENT ") == 2
    finally:
        watcher.close()
        for link in (a, b, view_link):
            link.close()


def test_status_documents_are_plain_json_for_any_client():
    cars = {"cars/x": (json.loads('{"hz": 19.9, "mode": null, "parts": {}, "ages_ms": {}}'), 100.0)}
    screen = render_fleet(cars, 100.5)
    assert "cars/x" in screen and "19.9" in screen
    assert "no car status yet" in render_fleet({}, 0.0)


@pytest.mark.network
@pytest.mark.realtime  # the car's status comes from a thread every 50 ms of real time while top listens
def test_top_once_prints_the_cars_it_heard(capsys):
    port = free_port()
    car = ZenohLink("cars/solo", listener(port))
    try:
        pub = car.session.declare_publisher("cars/solo/status")
        stop = False

        import threading
        import time

        def talk():
            while not stop:
                pub.put(json.dumps({"hz": 20.0, "mode": "local", "parts": {"Pilot": 3.5}}).encode())
                time.sleep(0.05)

        t = threading.Thread(target=talk)
        t.start()
        args = types.SimpleNamespace(
            config=None,
            mode="client",
            connect=[f"tcp/127.0.0.1:{port}"],
            listen=[],
            key="cars/*/status",
            every=1.0,
            once=0.5,
        )
        out = io.StringIO()
        assert top_main(args, stream=out) == 0
        stop = True
        t.join()
        text = out.getvalue()
        assert "1 car seen, 1 live" in text and "cars/solo" in text and "Pilot 3.50" in text
    finally:
        car.close()
