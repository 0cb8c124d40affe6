"""One bad value never stops or steers the car: what a ZenohSubscriber refuses, and what the car does meanwhile.

Every sample here is numbered and aged as an asyncdonkey publisher would (the attachment), so only its value is
wrong: a peer that gets past the access rules, or a buggy pilot. A refused value is not stored, is counted per
channel and reason, and leaves the channel's last good value ageing, so the stale-command failsafe decides.
"""

import asyncio
import json
import logging
import math
import time

import numpy as np
import pytest
import zenoh

from asyncdonkey import Contract, Contracts, Vehicle
from asyncdonkey.parts.actuators import PWMThrottle
from asyncdonkey.parts.zenoh import ZenohSubscriber
from asyncdonkey.parts.zenoh.codec import JSON, encode, pack_attachment
from asyncdonkey.testing.i2c_models import I2CSimulator, PCA9685Model

from ..waiting import await_until
from .zenoh_loopback import PulseProbe

pytestmark = [pytest.mark.realtime, pytest.mark.network]

CH = "pilot/throttle"

#: (name, payload, encoding, reason): each a value no part can use. ``None`` as payload: a DELETE sample.
BAD = [
    ("nan", b"NaN", JSON, "nan"),
    ("inf", b"Infinity", JSON, "inf"),
    ("-inf", b"-Infinity", JSON, "inf"),
    ("400-digit integer", b"9" * 400, JSON, "range"),
    ("out of range", b"1.5", JSON, "range"),
    ("string as text/plain", b"0.66", "text/plain", "type"),
    ("string as JSON", b'"full"', JSON, "type"),
    ("bool", b"true", JSON, "type"),
    ("list", b"[0.5]", JSON, "type"),
    ("0-d array of nan", None, "ndarray", "type"),
    ("500,000-item list", json.dumps([0.5] * 500_000).encode(), JSON, "size"),
    ("DELETE", None, "delete", "empty"),
    ("empty payload", b"", JSON, "empty"),
    ("wrong encoding", b"0.5", "application/xml", "encoding"),
    ("not JSON", b"0.5]", JSON, "encoding"),
]


class Sender:
    """Raw samples from a peer, numbered 1, 2, ... with age 0, as an asyncdonkey publisher numbers them."""

    def __init__(self, link, channel: str = CH) -> None:
        self.session = link.session
        self.key = link.key(channel)
        self.seq = 0

    def good(self, value: float) -> None:
        self._put(json.dumps(value).encode(), JSON)

    def bad(self, payload: bytes | None, encoding: str) -> None:
        if encoding == "delete":
            self.seq += 1
            self.session.delete(self.key, attachment=pack_attachment(0.0, self.seq, 1), **_BLOCK)
        elif encoding == "ndarray":
            enc = encode(np.array(np.nan), CH)
            self._put(enc.payload, enc.encoding)
        else:
            self._put(payload, encoding)

    def _put(self, payload: bytes, encoding: str) -> None:
        self.seq += 1
        att = pack_attachment(0.0, self.seq, 1)
        self.session.put(self.key, payload, encoding=encoding, attachment=att, **_BLOCK)


# BLOCK: a burst on a busy machine is never dropped, so every sample's fate is known
_BLOCK = {"congestion_control": zenoh.CongestionControl.BLOCK}


async def _route_up(sub: ZenohSubscriber, sender: Sender, value: float = 0.5) -> None:
    """Good values until one arrives (declaring the subscription on the other side takes a moment)."""
    await await_until(lambda: (sender.good(value), sub.received > 0)[1])
    n = await _settled(lambda: sub.received)
    assert n > 0


async def _settled(read, quiet_s: float = 0.15):
    value, since = read(), time.monotonic()
    while time.monotonic() - since < quiet_s:
        await asyncio.sleep(0.02)
        if read() != value:
            value, since = read(), time.monotonic()
    return value


@pytest.mark.asyncio
@pytest.mark.parametrize("name, payload, encoding, reason", BAD, ids=[b[0] for b in BAD])
async def test_a_bad_value_is_refused_counted_and_the_last_good_one_kept(link_pair, name, payload, encoding, reason):
    car, peer = link_pair("cars/c1")
    sub = ZenohSubscriber(car, [CH], ping_every_s=0)
    sender = Sender(peer)
    await _route_up(sub, sender, 0.25)
    before = sub.counters()
    assert before.get("refused", 0) == 0 and sub.run() == 0.25
    origin = sub.output_origin()
    sender.bad(payload, encoding)
    await await_until(lambda: sub.counters().get("refused") == 1 or sub.run() != 0.25, what=f"{name} refused or stored")
    # not stored: the last good value stays, with its old origin (it keeps ageing: the failsafe decides)
    assert sub.run() == 0.25 and sub.output_origin() == origin
    assert sub.refused == {CH: {reason: 1}}
    after = sub.counters()
    assert after["received"] == before["received"] and after["unexpected"] == 0
    # the next good value is taken, and the refused sample's number was seen: no gap, nothing lost
    sender.good(0.3)
    await await_until(lambda: sub.run() == 0.3)
    assert sub.counters()["lost"] == 0 and sub.counters()["out_of_order"] == 0
    sub.shutdown()


@pytest.mark.asyncio
async def test_a_refused_sample_is_not_counted_as_lost(link_pair):
    """A refused sample still used its sequence number: the gap it leaves is not a loss on the network."""
    car, peer = link_pair("cars/c1")
    sub = ZenohSubscriber(car, [CH], ping_every_s=0)
    sender = Sender(peer)
    await _route_up(sub, sender)
    for payload, encoding in [(b"0.5", "application/xml"), (b"{", JSON), (b"", JSON), (None, "delete"), (b"NaN", JSON)]:
        sender.bad(payload, encoding)
    sender.good(0.1)
    await await_until(lambda: sub.run() == 0.1)
    counters = sub.counters()
    assert counters["lost"] == 0 and counters["out_of_order"] == 0
    assert counters["refused"] == 5 and counters["malformed"] == 2


@pytest.mark.asyncio
async def test_refusals_are_logged_rate_limited_per_channel_and_reason(link_pair, caplog):
    car, peer = link_pair("cars/c1")
    sub = ZenohSubscriber(car, [CH], ping_every_s=0)
    sender = Sender(peer)
    await _route_up(sub, sender)
    with caplog.at_level(logging.WARNING, logger="asyncdonkey.contracts"):
        for _ in range(50):
            sender.bad(b"NaN", JSON)
        sender.bad(b"[1]", JSON)
        await await_until(lambda: sub.counters()["refused"] == 51)
    assert sub.refused == {CH: {"nan": 50, "type": 1}}
    lines = [r.getMessage() for r in caplog.records if "refused" in r.getMessage()]
    assert len(lines) == 2  # one per (channel, reason) per 5 s, whatever the flood
    assert any("'pilot/throttle'" in line and "NaN" in line for line in lines)
    assert sub.counters()["lost"] == 0


@pytest.mark.asyncio
async def test_the_cars_own_contracts_apply_once_the_subscriber_is_added(link_pair):
    """``Vehicle.add`` hands the car's contracts to the part (``use_contracts``): a channel declared on the car
    is checked; given ``contracts=``, the part keeps its own."""
    car, peer = link_pair("cars/c1")
    v = Vehicle()
    v.declare("sim/gain", Contract.number(0.0, 2.0))
    sub = ZenohSubscriber(car, ["sim/gain"], ping_every_s=0)
    v.add(sub, outputs=["sim/gain"])
    own = ZenohSubscriber(car, ["sim/gain"], ping_every_s=0, contracts=Contracts({"sim/gain": Contract.number(0, 9)}))
    v.add(own, outputs=["other"])
    sender = Sender(peer, "sim/gain")
    await _route_up(sub, sender, 1.0)
    sender.good(5.0)
    await await_until(lambda: own.run() == 5.0 and sub.counters()["refused"] == 1)
    assert sub.run() == 1.0 and sub.refused == {"sim/gain": {"range": 1}}
    assert own.refused == {}


class BadPeer:
    """From another session: a good throttle of 0.5 and a bad value every 20 ms for ``good_s``, then only bad
    values (cycling through :data:`BAD`), fresh and correctly numbered, until the drive ends."""

    def __init__(self, sender: Sender, good_s: float) -> None:
        self.sender = sender
        self.good_s = good_s
        self.last_good: float | None = None

    async def update(self) -> None:
        t0 = time.monotonic()
        k = 0
        while True:
            if time.monotonic() - t0 < self.good_s:
                self.sender.good(0.5)
                self.last_good = time.monotonic()
            _, payload, encoding, _ = BAD[k % len(BAD)]
            self.sender.bad(payload, encoding)
            k += 1
            await asyncio.sleep(0.02)

    def run(self) -> None:
        pass


class Seen:
    """Each tick: the throttle value in Memory."""

    def __init__(self) -> None:
        self.values: list[object] = []

    def run(self, value) -> None:
        self.values.append(value)


@pytest.mark.asyncio
async def test_the_car_drives_on_through_bad_values_and_stops_when_the_good_ones_stop(link_pair):
    """On the PCA9685 register model: bad values between good ones never move the throttle pulse; once only bad
    values come, the last good command ages out and the throttle goes to neutral within the failsafe window."""
    car_link, peer_link = link_pair("cars/c1")
    sim = I2CSimulator()
    pca = sim.attach(PCA9685Model(), address=0x40, bus=1)
    buses = sim.registry(retry_delay_s=0)
    sub = ZenohSubscriber(car_link, [CH], ping_every_s=0)
    peer = BadPeer(Sender(peer_link), good_s=0.6)
    probe, seen = PulseProbe(pca), Seen()
    v = Vehicle()
    v.add(peer)
    v.add(sub, outputs=[CH])
    v.add(seen, inputs=[CH])
    v.add(probe, inputs=[f"{CH}@age"])
    throttle = PWMThrottle("PCA9685.1:40.0", buses=buses, arm_s=0, failsafe_age_s=0.25)
    v.add(throttle, inputs=[CH, f"{CH}@age"])
    try:
        await v.run(rate_hz=50, max_loop_count=60)  # 1.2 s: 0.6 s of good and bad values, then bad ones only
    finally:
        buses.close_all()
    # nothing bad reached Memory: the throttle channel held 0.5 or nothing yet
    assert {x for x in seen.values if x is not None} == {0.5}
    t0 = probe.rows[0][0]
    driving = [p for t, p, _ in probe.rows if 0.25 < t - t0 < 0.55]
    assert driving and set(driving) == {435}  # the good command drives, never a NaN stop or an inf full throttle
    assert peer.last_good is not None
    stopped = [p for t, p, _ in probe.rows if t > peer.last_good + 0.25 + 0.02 + 0.05]  # window + a tick + slack
    assert stopped and set(stopped) == {370}  # neutral, although fresh (bad) samples keep coming
    reasons = {reason for *_, reason in BAD}
    assert set(sub.refused[CH]) == reasons
    counters = sub.counters()
    assert counters["lost"] == 0 and counters["unexpected"] == 0
    assert counters["refused"] == sum(sub.refused[CH].values()) >= len(BAD)
    assert throttle.failsafe_events >= 1
    assert math.isfinite(probe.rows[-1][2])  # the age grew from the last good value: it never restarted
