"""Cars, their pilots and the fleet view as clients of one Zenoh router: the 10-car layout of the scale-out guide.

Clients never talk to each other directly; everything goes through the router (a Zenoh session in router mode,
here in the test's process, listening on 127.0.0.1 only). Each car's commands reach that car and no other,
ages stay honest across the two hops, the fleet view hears every car, and when the router goes away the cars'
throttles go to neutral within the failsafe window.
"""

import asyncio
import time
from collections.abc import Iterator

import pytest
import zenoh

from asyncdonkey import Vehicle
from asyncdonkey.parts.zenoh import ZenohLink, ZenohPublisher, ZenohSubscriber, zenoh_config
from asyncdonkey.parts.zenoh.fleet import FleetStatus, FleetWatcher

from ..waiting import await_until
from .zenoh_loopback import RemotePilotCar, connector, free_port

pytestmark = [pytest.mark.realtime, pytest.mark.network]


class Router:
    """A Zenoh router on a free loopback port, and client links to it (all closed by :meth:`close`)."""

    def __init__(self) -> None:
        self.port = free_port()
        config = zenoh_config(mode="router", listen=[f"tcp/127.0.0.1:{self.port}"], multicast_scouting=False)
        self.session = zenoh.open(config)
        self.zid = str(self.session.zid())
        self.links: list[ZenohLink] = []

    def client(self, prefix: str) -> ZenohLink:
        link = ZenohLink(prefix, connector(self.port))
        self.links.append(link)
        return link

    def stop(self) -> None:
        self.session.close()

    def close(self) -> None:
        for link in self.links:
            link.close()
        if not self.session.is_closed():
            self.session.close()


@pytest.fixture
def router() -> Iterator[Router]:
    r = Router()
    yield r
    r.close()


@pytest.mark.asyncio
async def test_each_car_gets_its_own_pilots_commands_through_the_router_with_true_ages(router):
    alpha, alpha_pilot = router.client("cars/alpha"), router.client("cars/alpha")
    bravo, bravo_pilot = router.client("cars/bravo"), router.client("cars/bravo")
    for link in (alpha, alpha_pilot, bravo, bravo_pilot):  # clients: the router is their only neighbour
        assert [str(z) for z in link.session.info.routers_zid()] == [router.zid]
        assert list(link.session.info.peers_zid()) == []
    sub_a = ZenohSubscriber(alpha, ["pilot/angle", "pilot/throttle"], ping_every_s=0.05)
    sub_b = ZenohSubscriber(bravo, ["pilot/angle", "pilot/throttle"], ping_every_s=0.05)
    pub_a = ZenohPublisher(alpha_pilot, ["pilot/angle", "pilot/throttle"])
    pub_b = ZenohPublisher(bravo_pilot, ["pilot/angle", "pilot/throttle"])
    pings = [asyncio.create_task(sub_a.update()), asyncio.create_task(sub_b.update())]
    try:
        # the routes are up once something arrives (a subscription takes a moment to reach the router)
        await await_until(lambda: (pub_a.run(0.0, 0.0, 0.0, 0.0), sub_a.received >= 2)[1])
        await await_until(lambda: (pub_b.run(0.0, 0.0, 0.0, 0.0), sub_b.received >= 2)[1])
        await await_until(lambda: alpha.pongs_received >= 3 and bravo.pongs_received >= 3)
        await asyncio.sleep(0.1)  # the last warm-up values arrive
        before_a, before_b = sub_a.received, sub_b.received
        t_send = time.monotonic()
        pub_a.run(0.25, 0.5, 0.1, 0.1)  # alpha's pilot: sensed 100 ms before it was sent
        pub_b.run(-0.75, 0.2, 0.0, 0.0)
        await await_until(lambda: sub_a.received == before_a + 2 and sub_b.received == before_b + 2)
        t_seen = time.monotonic()
        assert sub_a.run() == (0.25, 0.5) and sub_b.run() == (-0.75, 0.2)  # each car its own pilot's
        assert sub_a.counters()["unexpected"] == 0 and sub_b.counters()["unexpected"] == 0
        # the round trip is through the router, both hops each way, and the age is the sender's plus transit
        rtt_min, _ = alpha.rtt_s()
        assert 0 < rtt_min < 0.05 and alpha.transit_s == pytest.approx(rtt_min / 2)
        origin = sub_a.output_origin()
        assert t_send - 0.1 - alpha.transit_s - 1e-4 <= origin <= t_seen - 0.1 - alpha.transit_s + 1e-4
        assert 0.1 <= sub_a.ages()["pilot/throttle"] < 0.2
    finally:
        for task in pings:
            task.cancel()
        for part in (pub_a, pub_b, sub_a, sub_b):
            part.shutdown()


class _Mode:
    def __init__(self, mode: str) -> None:
        self.mode = mode

    def run(self) -> str:
        return self.mode


@pytest.mark.asyncio
async def test_the_fleet_view_hears_every_car_through_the_router(router):
    view = router.client("fleet/view")
    watcher = FleetWatcher(view.session)
    try:
        cars = []
        for name, mode in (("cars/alpha", "local"), ("cars/bravo", "user")):
            v = Vehicle()
            v.add(_Mode(mode), outputs=["user/mode"])
            v.add(FleetStatus(router.client(name), v, every_s=0.1), inputs=["user/mode", "tub/num_records"])
            cars.append(v)
        await asyncio.gather(*(v.run(rate_hz=20, duration=0.8) for v in cars))
        await await_until(lambda: len(watcher.snapshot()) == 2)
        seen = watcher.snapshot()
        assert seen["cars/alpha"][0]["mode"] == "local" and seen["cars/bravo"][0]["mode"] == "user"
        assert all(doc["ticks"] > 5 for doc, _ in seen.values())
    finally:
        watcher.close()


@pytest.mark.asyncio
async def test_when_the_router_goes_away_the_car_stops_within_the_failsafe_window(router):
    # the pilot never goes quiet: the network does
    car = RemotePilotCar(router.client("cars/alpha"), router.client("cars/alpha"))
    probe, throttle = car.probe, car.throttle
    stopped_at: list[float] = []

    def router_down() -> None:
        router.stop()
        stopped_at.append(time.monotonic())

    asyncio.get_running_loop().call_later(0.6, router_down)
    await car.drive(60)  # 1.2 s: the router goes at 0.6 s
    assert stopped_at, "the router was not stopped during the drive"
    t0 = probe.rows[0][0]
    down = stopped_at[0]
    driving = [p for t, p, _ in probe.rows if t0 + 0.2 < t < down]
    stopped = [p for t, p, _ in probe.rows if t > down + 0.25 + 0.1]
    assert driving and driving[-1] == 435  # the remote 0.5 throttle reached the PWM chip through the router
    assert stopped and set(stopped) == {370}  # neutral once the last command through it was 250 ms old
    assert throttle.failsafe_events >= 1
