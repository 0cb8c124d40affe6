"""One sample per command: the remote pilot's angle and throttle travel together and are applied together.

Sent as two samples, a command whose halves straddle a tick (or a push) was applied half-new, with the older
half's origin. As one sample on ``<prefix>/pilot/command``, both channels change at once with that sample's
origin.
"""

import asyncio
import json
import time

import pytest
import zenoh

from asyncdonkey import Vehicle
from asyncdonkey.parts.zenoh import PILOT_COMMAND, ZenohPublisher, ZenohSubscriber
from asyncdonkey.parts.zenoh.codec import GROUP, CodecError, decode_group, encode_group, pack_attachment

from ..waiting import await_until

pytestmark = [pytest.mark.network]

CMD = ("pilot/angle", "pilot/throttle")


def test_the_wire_format_of_a_command_group_reads_from_its_description():
    enc = encode_group({"pilot/angle": -0.25, "pilot/throttle": 0.5}, PILOT_COMMAND)
    assert enc.encoding == "application/json;group;v=1" and enc.encoding.startswith(GROUP)
    assert json.loads(enc.payload) == {"pilot/angle": -0.25, "pilot/throttle": 0.5}
    assert decode_group(enc.payload, enc.encoding, CMD) == (-0.25, 0.5)
    assert decode_group(enc.payload, enc.encoding, CMD[::-1]) == (0.5, -0.25)  # by name, not by place
    for payload, encoding in [
        (enc.payload, "application/json;group;v=2"),  # another version
        (enc.payload, "application/json;group"),  # no version
        (enc.payload, "application/json"),  # not a group
        (b'{"pilot/angle": 0.1}', enc.encoding),  # a half
        (b'{"pilot/angle": 0.1, "pilot/throttle": 0.2, "user/mode": "local"}', enc.encoding),  # more
        (b"[0.1, 0.2]", enc.encoding),
        (b"{", enc.encoding),
    ]:
        with pytest.raises(CodecError, match="pilot/command"):
            decode_group(payload, encoding, CMD, "cars/c1/pilot/command")


class Pilot:
    """From the remote session: command k is (angle -k/100, throttle k/100), sensed as sent, every 7 ms from
    0.3 s; ``sent[k]`` is when it left."""

    def __init__(self, pub: ZenohPublisher, n: int = 60) -> None:
        self.pub = pub
        self.n = n
        self.sent: dict[int, float] = {}

    async def update(self) -> None:
        await asyncio.sleep(0.3)
        for k in range(1, self.n + 1):
            self.sent[k] = time.monotonic()
            self.pub.run(-k / 100, k / 100, 0.0, 0.0)
            await asyncio.sleep(0.007)

    def run(self) -> None:
        pass


class Applied:
    """A react=True part fed by the commands (as ``DriveMode`` on the car): each command as it reached it, with
    both channels' origins in Memory."""

    def __init__(self, vehicle: Vehicle) -> None:
        self.mem = vehicle.mem
        self.rows: list[tuple[float, float, float, float]] = []

    def run(self, angle, throttle) -> None:
        if angle is not None:
            self.rows.append((angle, throttle, self.mem.origin("pilot/angle"), self.mem.origin("pilot/throttle")))


@pytest.mark.realtime
@pytest.mark.asyncio
async def test_a_remote_command_is_applied_whole_with_its_own_origin(link_pair):
    car, pilot_link = link_pair("cars/c1")
    v = Vehicle()
    pilot = Pilot(ZenohPublisher(pilot_link, list(CMD), group=PILOT_COMMAND))
    applied = Applied(v)
    v.add(pilot)
    sub = ZenohSubscriber(car, list(CMD), group=PILOT_COMMAND, ping_every_s=0)
    v.add(sub, outputs=list(CMD))
    v.add(applied, inputs=list(CMD), react=True)
    # ticks 200 ms apart: the commands arrive between them. The pilot's 60 commands take 0.72 s from 0.3 s on a quiet
    # machine and its 7 ms sleeps stretch on a loaded one: the drive lasts 1.8 s, so the last one is sent and
    # received before it ends (at 0.8 s it was, on a machine with both cores busy, one command short)
    await v.run(rate_hz=5, max_loop_count=10)
    assert len(pilot.sent) == pilot.n, f"the pilot sent {len(pilot.sent)} of its {pilot.n} commands in the drive"
    assert sub.key_expr == "cars/c1/pilot/command" and sub.counters()["refused"] == 0
    rows = [r for r in applied.rows if r[1] > 0]
    assert len(rows) >= pilot.n // 3, len(rows)  # a busy loop may merge pushes; most commands are seen
    for angle, throttle, angle_origin, throttle_origin in rows:
        k = round(throttle * 100)
        assert angle == -throttle, (angle, throttle)  # never this command's throttle with another's angle
        assert angle_origin == throttle_origin  # one sample, one origin
        # this command's own origin (sensed as it was sent), not the previous command's (7 ms older)
        assert angle_origin >= pilot.sent[k] - 0.001, (k, pilot.sent[k] - angle_origin)
    assert rows[-1][:2] == (-pilot.n / 100, pilot.n / 100)


@pytest.mark.realtime
@pytest.mark.asyncio
async def test_a_group_with_one_bad_half_is_refused_whole(link_pair):
    car, peer = link_pair("cars/c1")
    sub = ZenohSubscriber(car, list(CMD), group=PILOT_COMMAND, ping_every_s=0)
    key = car.key(PILOT_COMMAND)
    seq = 0

    def put(payload: bytes, encoding: str = "application/json;group;v=1") -> None:
        nonlocal seq
        seq += 1
        att = pack_attachment(0.0, seq, 7)
        peer.session.put(key, payload, encoding=encoding, attachment=att, congestion_control=_BLOCK)

    await await_until(lambda: (put(b'{"pilot/angle": 0.1, "pilot/throttle": 0.2}'), sub.received > 0)[1])
    await asyncio.sleep(0.1)
    assert sub.run() == (0.1, 0.2)
    put(b'{"pilot/angle": -0.9, "pilot/throttle": NaN}')  # a new angle with a NaN throttle
    put(b'{"pilot/angle": "left", "pilot/throttle": 0.9}')
    put(b'{"pilot/angle": 0.0}')
    put(b'{"pilot/angle": 0.0, "pilot/throttle": 0.0}', "application/json;group;v=9")
    peer.session.delete(key, attachment=pack_attachment(0.0, seq + 1, 7), congestion_control=_BLOCK)
    seq += 1
    await await_until(lambda: sub.counters()["refused"] == 5, what=lambda: f"5 refused (so far {sub.refused})")
    assert sub.refused == {
        "pilot/throttle": {"nan": 1},
        "pilot/angle": {"type": 1},
        PILOT_COMMAND: {"encoding": 2, "empty": 1},  # a half command, a version it does not know; a DELETE
    }
    assert sub.run() == (0.1, 0.2)  # neither half of a bad command was stored
    put(b'{"pilot/angle": 0.3, "pilot/throttle": 0.4}')
    await await_until(lambda: sub.run() == (0.3, 0.4))
    assert sub.counters()["lost"] == 0
    assert set(sub.ages()) == set(CMD) and len(set(sub.ages().values())) == 1


def test_a_group_publisher_sends_nothing_of_a_half_command(link_pair):
    _, pilot = link_pair("cars/c1")
    pub = ZenohPublisher(pilot, list(CMD), group=PILOT_COMMAND)
    pub.run(0.1, None, 0.0, 0.0)
    pub.run(0.1, 0.2, 0.0, float("inf"))  # the throttle has no sensing behind it
    assert (pub.sent, pub.incomplete, pub.unaged) == (0, 1, 1)
    pub.run(0.1, 0.2, 0.01, 0.03)
    assert pub.sent == 1
    with pytest.raises(ValueError, match="group must be a plain channel name"):
        ZenohPublisher(pilot, list(CMD), group="pilot/angle")
    pub.shutdown()


_BLOCK = zenoh.CongestionControl.BLOCK
