"""A car driven over Zenoh on 127.0.0.1 keeps taking its pilot's commands whatever numbers and ages other
samples on its command key carry: the sample that used to stop it for good (sequence 2**64-1 under the pilot's
own source) and one aged 1e300 s are refused, counted and never reach the throttle."""

from __future__ import annotations

import math

import pytest
import zenoh

from asyncdonkey.parts.zenoh import ZenohPublisher
from asyncdonkey.parts.zenoh.codec import pack_attachment

from .zenoh_loopback import RemotePilotCar

#: the chip's pulse for the pilot's 0.5 throttle, and for a stopped one (PWMThrottle's defaults)
DRIVING, STOPPED = 435, 370


class Saboteur:
    """At chosen ticks, puts hostile samples on the car's command key from the pilot's own session, under the
    pilot publisher's source: ``(tick, value, age, seq)``, ``seq=None`` for the pilot's next number."""

    def __init__(self, car: RemotePilotCar, plan: list[tuple[int, float, float, int | None]]) -> None:
        self.car = car
        self.plan = plan
        self.tick = 0

    def run(self) -> None:
        self.tick += 1
        pub = self.car.pilot.pub
        for tick, value, age, seq in self.plan:
            if tick == self.tick:
                number = pub._seq[0] + 1 if seq is None else seq
                pub.link.session.put(
                    pub.link.key("pilot/throttle"),
                    repr(value).encode(),
                    encoding="application/json",
                    attachment=pack_attachment(age, number, pub.source),
                    congestion_control=zenoh.CongestionControl.BLOCK,
                )


@pytest.mark.realtime
@pytest.mark.network
@pytest.mark.asyncio
async def test_hostile_sequence_numbers_and_ages_never_stop_or_move_a_car_driven_over_zenoh(link_pair):
    car = RemotePilotCar(*link_pair("cars/c1"))
    plan = [
        (15, 0.0, 0.0, 2**64 - 1),  # would have made every later command "out of order": stopped for good
        (25, 1.0, 1e300, None),  # the pilot's next number, aged 1e300 s: taken as the newest, it stopped the car
        (30, 1.0, math.nan, None),
        (35, 1.0, -1.0, None),
        (40, 0.0, 3600.0, None),  # an hour old: beyond any transit
    ]
    car.vehicle.add(Saboteur(car, plan))
    await car.drive(60)  # 1.2 s at 50 Hz, the pilot sending 0.5 every tick throughout
    rows = car.probe.rows
    t0 = rows[0][0]
    driving = [pulse for t, pulse, _ in rows if t - t0 > 0.2]
    assert driving and set(driving) == {DRIVING}  # never stopped, never moved by a hostile value
    counters = car.commands.counters()
    assert counters["implausible"] == len(plan)
    assert counters["lost"] == 0 and counters["out_of_order"] == 0 and counters["restarts"] == 0
    # the pilot's commands kept coming in (one each tick, give or take what a loaded machine merges)
    assert counters["received"] >= 40
    assert max(age for t, _, age in rows if t - t0 > 0.2) < 0.25  # never stale: the failsafe never held


class Restarter:
    """At ``new_source_at`` the pilot restarts as a new process would (a new publisher: a new source, numbering
    from 1); at ``renumber_at`` it numbers from 1 again under the same source (a sender that keeps its source)."""

    def __init__(self, car: RemotePilotCar, new_source_at: int, renumber_at: int) -> None:
        self.car = car
        self.new_source_at = new_source_at
        self.renumber_at = renumber_at
        self.tick = 0

    def run(self) -> None:
        self.tick += 1
        pilot = self.car.pilot
        if self.tick == self.new_source_at:
            old = pilot.pub
            pilot.pub = ZenohPublisher(old.link, ["pilot/throttle"])
            old.shutdown()
        elif self.tick == self.renumber_at:
            pilot.pub._seq[0] = 0


@pytest.mark.realtime
@pytest.mark.network
@pytest.mark.asyncio
async def test_a_restarted_pilot_is_taken_again_from_its_second_sample(link_pair):
    car_link, pilot_link = link_pair("cars/c1")
    pilot_link.acquire()  # the restart closes the first publisher, not the session
    car = RemotePilotCar(car_link, pilot_link)
    car.vehicle.add(Restarter(car, new_source_at=20, renumber_at=40))
    await car.drive(60)
    rows = car.probe.rows
    t0 = rows[0][0]
    assert set(pulse for t, pulse, _ in rows if t - t0 > 0.2) == {DRIVING}  # one sample missed is 20 ms
    counters = car.commands.counters()
    assert counters["restarts"] == 2 and counters["unconfirmed"] == 1 and counters["out_of_order"] == 1
    assert counters["implausible"] == 0 and counters["lost"] == 0
    # each restart cost one sample, nothing more: the command never grew stale
    assert max(age for t, _, age in rows if t - t0 > 0.2) < 0.25  # never stale: the failsafe never held
