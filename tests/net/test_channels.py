"""Publisher and subscriber parts on loopback: values, newest-wins, counters, true ages, the failsafe across a link."""

import asyncio
import logging
import time

import numpy as np
import pytest
import zenoh

from asyncdonkey import Vehicle
from asyncdonkey.parts.zenoh import ZenohPublisher, ZenohSubscriber
from asyncdonkey.parts.zenoh.codec import pack_attachment
from asyncdonkey.parts.zenoh.parts import covering_key

from ..waiting import await_until
from .zenoh_loopback import RemotePilotCar


@pytest.mark.realtime
@pytest.mark.network
@pytest.mark.asyncio
async def test_channels_arrive_under_prefix_with_their_values(link_pair):
    car, pilot = link_pair("cars/c1")
    sub = ZenohSubscriber(car, ["pilot/angle", "pilot/throttle", "cam/image_array", "user/mode"])
    pub = ZenohPublisher(pilot, ["pilot/angle", "pilot/throttle", "cam/image_array", "user/mode"])
    assert pub.inputs[4:] == ["pilot/angle@age", "pilot/throttle@age", "cam/image_array@age", "user/mode@age"]
    img = np.random.default_rng(1).integers(0, 255, (120, 160, 3), dtype=np.uint8)
    assert sub.run() == (None, None, None, None) and sub.output_origin() is None
    # the route is up once something arrives: declaring the subscription on the other side takes a moment,
    # longer on a loaded machine, and a value published before that is not delivered
    blank = np.zeros_like(img)
    await await_until(lambda: (pub.run(0.0, 0.0, blank, "user", 0.0, 0.0, 0.0, 0.0), sub.received >= 4)[1])
    await asyncio.sleep(0.1)  # the last of those arrive
    before = sub.received
    pub.run(-0.25, 0.5, img, "local", 0.0, 0.0, 0.0, 0.0)
    await await_until(lambda: sub.received == before + 4)
    angle, throttle, frame, mode = sub.run()
    assert (angle, throttle, mode) == (-0.25, 0.5, "local")
    np.testing.assert_array_equal(frame, img)
    assert sub.counters()["unexpected"] == 0
    pub.shutdown()
    sub.shutdown()


@pytest.mark.realtime
@pytest.mark.network
@pytest.mark.asyncio
async def test_newest_value_wins_and_overwritten_values_count_as_dropped(link_pair):
    car, pilot = link_pair()
    sub = ZenohSubscriber(car, ["pilot/throttle"])
    pub = ZenohPublisher(pilot, ["pilot/throttle"])
    await await_until(lambda: (pub.run(0.0, 0.0), sub.received > 0)[1])  # the route is up
    await asyncio.sleep(0.1)
    sub.run()
    before = sub.counters()
    for k in range(1, 11):
        pub.run(k / 10, 0.0)
    await await_until(
        lambda: sub.received == before["received"] + 10,
        what=lambda: f"10 more received: counters {list(before.values())} before, {list(sub.counters().values())} now",
    )
    assert sub.run() == 1.0
    assert sub.dropped - before["dropped"] == 9 and sub.lost == 0 and sub.out_of_order == 0
    assert sub.run() == 1.0  # held, not consumed: the value stays until a newer one comes
    assert sub.dropped - before["dropped"] == 9
    pub.shutdown()
    sub.shutdown()


@pytest.mark.realtime
@pytest.mark.network
@pytest.mark.asyncio
async def test_sequence_gaps_old_samples_and_late_arrivals_are_counted(link_pair):
    car, pilot = link_pair()
    sub = ZenohSubscriber(car, ["x"], late_after_s=0.1)
    key = car.key("x")
    await asyncio.sleep(0.2)
    for seq, age in [(1, 0.0), (2, 0.0), (5, 0.0), (4, 0.0), (6, 0.5)]:
        att = pack_attachment(age, seq, source=1)
        _put(pilot, key, b"%d" % seq, encoding="application/json", attachment=att)
    await await_until(lambda: sub.received + sub.out_of_order == 5)
    assert sub.run() == 6
    assert (sub.lost, sub.out_of_order, sub.late) == (2, 1, 1)
    # the sender restarts: a new source numbering from 1 again (and its first sample may be lost)
    for seq in (2, 3):
        att = pack_attachment(0, seq, source=2)
        _put(pilot, key, b"%d" % (100 + seq), encoding="application/json", attachment=att)
    await await_until(lambda: sub.run() == 103)
    assert sub.restarts == 1 and sub.out_of_order == 1


@pytest.mark.realtime
@pytest.mark.network
@pytest.mark.asyncio
async def test_only_configured_keys_are_taken_others_are_counted_and_logged(link_pair, caplog):
    car, stranger = link_pair("cars/c1")
    sub = ZenohSubscriber(car, ["pilot/angle", "pilot/throttle"])
    assert sub.key_expr == "cars/c1/pilot/**"
    await asyncio.sleep(0.2)
    with caplog.at_level(logging.WARNING, logger="asyncdonkey.parts.zenoh.parts"):
        _put(stranger, "cars/c1/pilot/throttle", b"1.0")  # no age attachment: not ours
        await await_until(lambda: sub.unexpected == 1)
        _put(stranger, "cars/c1/sim/cte", b"1.0", attachment=pack_attachment(0, 1))  # not listened to
        for k in range(20):  # a peer spraying keys
            _put(stranger, f"cars/c1/pilot/x{k}", b"1.0", attachment=pack_attachment(0, 1))
        await await_until(lambda: sub.unexpected == 21)
        await asyncio.sleep(0.1)
    assert sub.unexpected == 21
    assert sub.run() == (None, None) and sub.received == 0
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 1  # rate-limited whatever the keys: one line per 5 s
    assert "'cars/c1/pilot/throttle'" in lines[0] and "no age attachment" in lines[0]
    _put(stranger, "cars/c1/pilot/mode", b"1.0", attachment=pack_attachment(0, 1))
    await await_until(lambda: sub.unexpected == 22)


@pytest.mark.network
def test_the_rejection_message_names_the_key_and_why(link_pair, caplog):
    car, _ = link_pair("cars/c1")
    sub = ZenohSubscriber(car, ["pilot/throttle"])
    with caplog.at_level(logging.WARNING, logger="asyncdonkey.parts.zenoh.parts"):
        sub._reject("cars/c1/pilot/mode", "is not one of the configured channels")
    assert "'cars/c1/pilot/mode': it is not one of the configured channels (1 ignored so far)" in caplog.text


@pytest.mark.realtime
@pytest.mark.network
@pytest.mark.asyncio
async def test_received_age_is_sender_age_plus_transit(link_pair):
    car, pilot = link_pair()
    sub = ZenohSubscriber(car, ["cam/image_array"], ping_every_s=0.05)
    pub = ZenohPublisher(pilot, ["cam/image_array"])
    task = asyncio.create_task(sub.update())
    await await_until(lambda: car.pongs_received >= 3)
    await asyncio.sleep(0.15)
    rtt_min, _ = car.rtt_s()
    assert 0 < rtt_min < 0.05 and car.transit_s == pytest.approx(rtt_min / 2)
    frame = np.zeros((120, 160, 3), np.uint8)
    t_send = time.monotonic()
    pub.run(frame, 0.2)  # sensed 200 ms before it was sent
    await await_until(lambda: sub.received == 1)
    t_seen = time.monotonic()
    sub.run()
    origin = sub.output_origin()
    # truth is t_send - 0.2; the estimate errs by (this sample's transit - estimated transit): never older than
    # the truth by more than the estimate, never younger than if the whole send-to-seen time had been free
    assert t_send - 0.2 - car.transit_s - 1e-4 <= origin <= t_seen - 0.2 - car.transit_s + 1e-4
    age = sub.ages()["cam/image_array"]
    assert 0.2 <= age < 0.3
    task.cancel()
    pub.shutdown()
    sub.shutdown()


@pytest.mark.realtime
@pytest.mark.network
@pytest.mark.asyncio
async def test_on_change_sends_changes_and_a_keepalive(link_pair):
    car, pilot = link_pair()
    sub = ZenohSubscriber(car, ["user/mode"])
    pub = ZenohPublisher(pilot, ["user/mode"], on_change=True, max_interval_s=0.05)
    await asyncio.sleep(0.2)
    for _ in range(5):
        pub.run("user", 0.0)
    pub.run("local", 0.0)
    assert (pub.sent, pub.skipped) == (2, 4)
    await asyncio.sleep(0.06)
    pub.run("local", 0.0)  # unchanged, but the keepalive is due
    assert pub.sent == 3
    await await_until(lambda: sub.received == 3)


def test_covering_key():
    assert covering_key(["cars/a/pilot/angle", "cars/a/pilot/throttle"]) == "cars/a/pilot/**"
    assert covering_key(["cars/a/cam/image_array"]) == "cars/a/cam/image_array"
    assert covering_key(["cars/a/x", "cars/a/y/z"]) == "cars/a/**"


@pytest.mark.network
def test_bad_arguments_name_the_part(link_pair):
    car, _ = link_pair()
    with pytest.raises(ValueError, match="ZenohPublisher: channels"):
        ZenohPublisher(car, "pilot/angle")
    with pytest.raises(ValueError, match="jpeg channel 'cam'"):
        ZenohPublisher(car, ["x"], jpeg={"cam": 80})
    with pytest.raises(ValueError, match="quality for 'x'"):
        ZenohPublisher(car, ["x"], jpeg={"x": 0})
    with pytest.raises(ValueError, match="ZenohSubscriber: channels"):
        ZenohSubscriber(car, [])


def _put(link, key, payload, **kw):
    """A raw put from a test's peer; BLOCK so a burst is never dropped on a busy machine."""
    link.session.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK, **kw)


@pytest.mark.realtime
@pytest.mark.network
@pytest.mark.asyncio
async def test_stale_command_failsafe_stops_the_car_when_the_remote_pilot_goes_quiet(link_pair):
    car = RemotePilotCar(*link_pair("cars/c1"), seconds=0.6)
    await car.drive(60)  # 1.2 s: 0.6 s driven, then silence
    probe, throttle = car.probe, car.throttle
    t0 = probe.rows[0][0]
    driving = [p for t, p, _ in probe.rows if 0.2 < t - t0 < 0.55]
    stopped = [p for t, p, _ in probe.rows if t - t0 > 0.6 + 0.25 + 0.1]
    assert driving and set(driving) == {435}  # the remote 0.5 throttle reached the PWM chip
    assert stopped and set(stopped) == {370}  # neutral once the command was 250 ms old
    # (the first ticks may also count one: no command has arrived yet)
    assert throttle.failsafe_events in (1, 2)
    ages = [a for t, _, a in probe.rows if 0.2 < t - t0 < 0.55]
    # while the pilot talks, its commands are fresh: well under the failsafe's 0.25 s; 0.2 s leaves room for a
    # tick or a delivery delayed by a loaded 2-core machine (the 50 Hz pilot's commands are 20 ms apart)
    assert max(ages) < 0.2


class _Seen:
    """A pipelined part triggered by the remote channel: records when each value reached it."""

    def __init__(self) -> None:
        self.rows: list[tuple[float, float]] = []

    def run(self, value):
        self.rows.append((time.monotonic(), value))


class _Sender:
    """From the remote session: one value every 30 ms, from the second tick on (the route is up by then)."""

    def __init__(self, pub: ZenohPublisher) -> None:
        self.pub = pub

    async def update(self) -> None:
        await asyncio.sleep(0.3)
        for k in range(1, 6):
            self.pub.run(float(k), 0.0)
            await asyncio.sleep(0.03)

    def run(self) -> None:
        pass


@pytest.mark.realtime
@pytest.mark.network
@pytest.mark.asyncio
async def test_a_one_channel_subscriber_pushes_each_value_to_a_triggered_part_between_ticks(link_pair):
    car, pilot = link_pair()
    seen = _Seen()
    v = Vehicle()
    v.add(_Sender(ZenohPublisher(pilot, ["x"])))
    v.add(ZenohSubscriber(car, ["x"], ping_every_s=0), outputs=["x"])
    v.add(seen, inputs=["x"], pipelined=True, trigger="x")
    await v.run(rate_hz=2, max_loop_count=3)  # ticks 0.5 s apart: the values arrive between them
    values = [val for _, val in seen.rows if val is not None]
    assert values[-1] == 5.0 and len(values) >= 4  # each arrival started the part (a busy one may merge two)


class _Commands:
    """From the remote session: (angle, throttle) pairs every 30 ms, from the second tick on."""

    def __init__(self, pub: ZenohPublisher) -> None:
        self.pub = pub

    async def update(self) -> None:
        await asyncio.sleep(0.3)
        for k in range(1, 6):
            self.pub.run(-0.1 * k, 0.1 * k)
            await asyncio.sleep(0.03)

    def run(self) -> None:
        pass


class _Actuator:
    """A react=True part fed by the remote commands: records when each (angle, throttle) reached it."""

    def __init__(self) -> None:
        self.rows: list[tuple[float, float, float]] = []

    def run(self, angle, throttle):
        if angle is not None:
            self.rows.append((time.monotonic(), angle, throttle))


@pytest.mark.realtime
@pytest.mark.network
@pytest.mark.asyncio
async def test_remote_commands_reach_react_parts_when_they_arrive_not_at_the_next_tick(link_pair):
    car, pilot = link_pair()
    act = _Actuator()
    v = Vehicle()
    v.add(_Commands(ZenohPublisher(pilot, ["pilot/angle", "pilot/throttle"])))
    v.add(ZenohSubscriber(car, ["pilot/angle", "pilot/throttle"], ping_every_s=0), outputs=["angle", "throttle"])
    v.add(act, inputs=["angle", "throttle"], react=True)
    t0 = time.monotonic()
    report = await v.run(rate_hz=2, max_loop_count=3)  # ticks at 0, 0.5 and 1.0 s; commands from 0.3 to 0.42 s
    assert report.loops == 3
    # the actuator ran as the commands arrived, between the first two ticks (not only at 0.5 s), and ended on
    # the last command with both channels' newest values
    between_ticks = [t - t0 for t, _a, _th in act.rows if 0.2 < t - t0 < 0.49]
    assert len(between_ticks) >= 3
    assert act.rows[-1][1:] == pytest.approx((-0.5, 0.5))


@pytest.mark.realtime
@pytest.mark.network
@pytest.mark.asyncio
async def test_a_value_with_no_sensing_behind_it_is_never_sent_as_fresh(link_pair, caplog):
    """An infinite (or unknown) age means nothing sensed is behind the value: sending it with age 0 would make a
    receiver's failsafe trust it. It is not sent, and counted."""
    car, pilot = link_pair()
    sub = ZenohSubscriber(car, ["pilot/throttle"])
    pub = ZenohPublisher(pilot, ["pilot/throttle"])
    await await_until(lambda: (pub.run(0.0, 0.0), sub.received > 0)[1])  # the route is up
    await asyncio.sleep(0.1)
    before = sub.received
    pub.run(0.9, float("inf"))
    pub.run(0.8, float("nan"))
    assert pub.unaged == 2
    pub.run(0.1, 0.05)
    await await_until(lambda: sub.received == before + 1)
    assert sub.run() == 0.1
    assert any("has no sensing behind it" in r.getMessage() for r in caplog.records)
    pub.shutdown()
    sub.shutdown()
