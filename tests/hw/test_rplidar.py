"""RPLidar protocol: exact request bytes, descriptors, node decoding and resynchronisation, and the driver
against the pty device model (info, health, reset on error, scan watchdog, unplug/replug)."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from asyncdonkey.hw.rplidar import (
    CMD_GET_HEALTH,
    CMD_GET_INFO,
    CMD_RESET,
    CMD_SCAN,
    CMD_STOP,
    MAX_REVOLUTION_NODES,
    MIN_REVOLUTION_NODES,
    DeviceInfo,
    Health,
    RPLidarDriver,
    RPLidarError,
    RPLidarProtocol,
    decode_node,
    parse_descriptor,
    request,
)
from asyncdonkey.testing.serial_peers import RPLidarPeer

from ..waiting import await_until


def run(coro) -> None:
    with asyncio.Runner(loop_factory=asyncio.SelectorEventLoop) as runner:
        runner.run(coro)


# -------------------------------------------------------------------------------------------- codec
def test_requests_are_the_documented_bytes():
    assert request(CMD_STOP) == b"\xa5\x25"
    assert request(CMD_RESET) == b"\xa5\x40"
    assert request(CMD_SCAN) == b"\xa5\x20"
    assert request(CMD_GET_INFO) == b"\xa5\x50"
    assert request(CMD_GET_HEALTH) == b"\xa5\x52"
    # a payload request: motor PWM 660 as A2/A3 take it; checksum = XOR of every byte before it
    assert request(0xF0, (660).to_bytes(2, "little")) == bytes.fromhex("a5f0029402c1")
    with pytest.raises(ValueError, match="byte"):
        request(256)


def test_response_descriptors_decode():
    scan = parse_descriptor(bytes.fromhex("a55a0500004081"))
    assert (scan.length, scan.mode, scan.data_type) == (5, 1, 0x81)
    info = parse_descriptor(bytes.fromhex("a55a1400000004"))
    assert (info.length, info.mode, info.data_type) == (20, 0, 0x04)
    with pytest.raises(RPLidarError):
        parse_descriptor(bytes.fromhex("a55b0500004081"))


def test_info_and_health_payloads_decode():
    info = DeviceInfo.decode(bytes((0x18, 29, 1, 7)) + bytes(range(16)))
    assert (info.model, info.firmware, info.hardware) == (0x18, (1, 29), 7)
    assert info.serial_number == "000102030405060708090A0B0C0D0E0F"
    health = Health.decode(bytes((2, 0x34, 0x12)))
    assert (health.status, health.error_code, health.name) == (2, 0x1234, "error")


def test_a_hand_assembled_node_decodes():
    # quality 15, start of scan, 90.0°, 1000 mm: b0 = 15<<2 | S̄=0 | S=1; angle_q6 = 5760; distance_q2 = 4000
    node = decode_node(bytes((0x3D, 0x01, 0x2D, 0xA0, 0x0F)))
    assert node is not None
    assert (node.start, node.quality, node.angle_deg, node.distance_mm) == (True, 15, 90.0, 1000.0)
    not_start = decode_node(bytes((0x3E, 0x03, 0x2D, 0x01, 0x00)))  # S̄=1, S=0, angle_q6 5761 = 90° + 1/64
    assert not_start is not None and not not_start.start and not_start.angle_deg == 90.0 + 1 / 64
    assert not_start.distance_mm == 0.25


@pytest.mark.parametrize(
    "node",
    [
        bytes((0x3C, 0x01, 0x2D, 0xA0, 0x0F)),  # S = S̄ = 0
        bytes((0x3F, 0x01, 0x2D, 0xA0, 0x0F)),  # S = S̄ = 1
        bytes((0x3D, 0x00, 0x2D, 0xA0, 0x0F)),  # check bit C = 0
        bytes((0x3D, 0x01, 0xB4, 0xA0, 0x0F)),  # angle 360.0°: impossible
        bytes((0x3D, 0x01, 0x2D, 0xA0)),  # short
    ],
)
def test_nodes_failing_the_checks_are_rejected(node):
    assert decode_node(node) is None


def _model_bytes(revolutions: int, points: int = 90) -> tuple[RPLidarPeer, bytes]:
    peer = RPLidarPeer(points_per_scan=points, invalid_every=7)
    data = b"".join(peer.encode_node(*peer.node_values(k)) for k in range(revolutions * points + 1))
    peer.close()
    return peer, data


def _scanning_protocol(scans: list) -> RPLidarProtocol:
    proto = RPLidarProtocol(scans.append, lambda: 0.0)
    fut = asyncio.Future(loop=asyncio.new_event_loop())
    proto.expect(0x81, fut)
    proto.data_received(bytes.fromhex("a55a0500004081"))
    assert fut.result() == b"" and proto.scanning
    return proto


def test_scan_stream_decodes_to_the_models_revolutions():
    peer, data = _model_bytes(3)
    scans = []
    proto = _scanning_protocol(scans)
    proto.data_received(b"\x00\x07")  # noise before the first node: resynchronised over
    proto.data_received(data)
    assert [s.index for s in scans] == [1, 2, 3]  # the 4th revolution has only begun
    for r, scan in enumerate(scans):
        expected = [peer.node_values(r * 90 + i) for i in range(90)]  # every 7th node is "no return"
        assert len(scan) == 90
        assert np.array_equal(scan.angles, np.array([a for _, _, a, _ in expected], np.float32) / 64)
        assert np.array_equal(scan.distances, np.array([d for _, _, _, d in expected], np.float32) / 4)
        assert np.array_equal(scan.qualities, np.array([q for _, q, _, _ in expected], np.uint8))
        assert scan.qualities.dtype == np.uint8 and scan.angles.dtype == np.float32
    assert int(np.sum(scans[0].distances == 0)) == len([k for k in range(90) if k % 7 == 6])
    assert proto.bad_nodes >= 1 and proto.nodes == 3 * 90 + 1


def test_garbage_mid_stream_is_skipped_and_counted():
    _, data = _model_bytes(2)
    scans = []
    proto = _scanning_protocol(scans)
    cut = 5 * 30 + 2  # break alignment inside the 31st node
    proto.data_received(data[:cut] + b"\xff\xff\xff" + data[cut + 3 :])
    assert proto.bad_nodes > 0
    assert len(scans) == 2
    assert len(scans[0]) in (89, 90)  # at most the damaged node is lost; a node may survive by chance
    assert len(scans[1]) == 90


def test_partial_revolution_before_the_first_start_flag_is_discarded():
    _, data = _model_bytes(2)
    scans = []
    proto = _scanning_protocol(scans)
    proto.data_received(data[5 * 40 :])  # join mid-revolution
    assert [len(s) for s in scans] == [90]


@settings(max_examples=60, deadline=None)
@given(st.lists(st.integers(min_value=1, max_value=64), min_size=1, max_size=40))
def test_decoding_does_not_depend_on_chunk_boundaries(cuts):
    _, data = _model_bytes(2, points=60)
    ref: list = []
    _scanning_protocol(ref).data_received(data)
    got: list = []
    proto = _scanning_protocol(got)
    i = k = 0
    while i < len(data):
        proto.data_received(data[i : i + cuts[k % len(cuts)]])
        i += cuts[k % len(cuts)]
        k += 1
    assert len(got) == len(ref) == 2
    for a, b in zip(got, ref, strict=True):
        assert np.array_equal(a.angles, b.angles) and np.array_equal(a.distances, b.distances)


@settings(max_examples=100, deadline=None)
@given(st.lists(st.binary(max_size=64), max_size=30))
def test_random_bytes_never_raise_in_any_state(chunks):
    scans: list = []
    idle = RPLidarProtocol(scans.append, lambda: 0.0)
    waiting = RPLidarProtocol(scans.append, lambda: 0.0)
    loop = asyncio.new_event_loop()
    try:
        waiting.expect(0x04, loop.create_future())
        scanning = _scanning_protocol(scans)
        for c in chunks:
            for proto in (idle, waiting, scanning):
                proto.data_received(c)
        for s in scans:
            assert len(s.angles) == len(s.distances) == len(s.qualities)
            assert np.all((s.angles >= 0) & (s.angles < 360))
    finally:
        loop.close()


# ------------------------------------------------------------------------------- driver vs the model
@pytest.mark.realtime
def test_driver_talks_the_protocol_and_publishes_complete_scans():
    async def body():
        with RPLidarPeer(points_per_scan=120, scan_hz=10.0) as peer:
            driver = RPLidarDriver(peer.path)
            task = asyncio.create_task(driver.run())
            await await_until(lambda: driver.latest.sample is not None and driver.latest.sample.seq >= 2)
            # STOP, GET_INFO, GET_HEALTH, SCAN: exactly these bytes, in this order
            assert bytes(peer.received) == bytes.fromhex("a525a550a552a520")
            assert driver.info == DeviceInfo(0x18, (1, 29), 7, "000102030405060708090A0B0C0D0E0F")
            assert driver.health == Health(0, 0)
            scan = driver.latest.value
            assert scan is not None and len(scan) == 120
            expected = peer.revolution()
            assert np.array_equal(scan.distances, np.array([d for *_, d in expected], np.float32) / 4)
            assert np.array_equal(scan.angles, np.array([a for _, _, a, _ in expected], np.float32) / 64)
            assert driver.protocol.bad_nodes == 0
            await driver.close()
            await asyncio.wait_for(task, 1)
            await await_until(lambda: peer.requests[-1][0] == CMD_STOP)
            assert not peer.scanning

    run(body())


@pytest.mark.realtime
def test_error_health_triggers_reset_then_scanning_once_healthy():
    async def body():
        with RPLidarPeer(points_per_scan=60, health=(2, 0x0102)) as peer:
            driver = RPLidarDriver(peer.path, response_timeout_s=0.2, reset_wait_s=0.05)
            task = asyncio.create_task(driver.run())
            await await_until(lambda: driver.session_failures >= 1)
            cmds = [c for c, _ in peer.requests]
            assert cmds[:5] == [CMD_STOP, CMD_GET_INFO, CMD_GET_HEALTH, CMD_RESET, CMD_GET_HEALTH]
            assert CMD_SCAN not in cmds
            assert driver.protocol.garbage_bytes >= len(RPLidarPeer.BANNER)  # the reset banner was skipped
            peer.health = (0, 0)
            await await_until(lambda: driver.latest.sample is not None, timeout=2.0)
            assert driver.health == Health(0, 0)
            await driver.close()
            await asyncio.wait_for(task, 1)

    run(body())


@pytest.mark.realtime
def test_watchdog_restarts_a_stalled_scan():
    async def body():
        with RPLidarPeer(points_per_scan=60, scan_hz=10.0) as peer:
            driver = RPLidarDriver(peer.path, watchdog_s=0.15)
            task = asyncio.create_task(driver.run())
            await await_until(lambda: driver.latest.sample is not None)
            peer.stall()
            before = driver.latest.sample.seq
            await await_until(lambda: driver.restarts == 1 and driver.latest.sample.seq > before, timeout=2.0)
            assert [c for c, _ in peer.requests].count(CMD_SCAN) == 2
            await driver.close()
            await asyncio.wait_for(task, 1)

    run(body())


@pytest.mark.realtime
def test_unplug_and_replug_resumes_scanning():
    async def body():
        with RPLidarPeer(points_per_scan=60, scan_hz=10.0) as peer:
            driver = RPLidarDriver(peer.path)
            driver.port.backoff_initial_s = 0.02
            task = asyncio.create_task(driver.run())
            await await_until(lambda: driver.latest.sample is not None)
            peer.unplug()
            await await_until(lambda: driver.port.disconnects == 1)
            assert driver.protocol.scanning is False
            seq = driver.latest.sample.seq
            peer.plug()
            await await_until(lambda: driver.latest.sample.seq >= seq + 2, timeout=2.0)
            cmds = [c for c, _ in peer.requests]
            assert cmds == [CMD_STOP, CMD_GET_INFO, CMD_GET_HEALTH, CMD_SCAN] * 2
            assert driver.port.connects == 2 and driver.session_failures == 0
            await driver.close()
            await asyncio.wait_for(task, 1)

    run(body())


# --------------------------------------------------------------------------- noise and lost start flags
def test_a_revolution_without_end_is_bounded_and_dropped():
    peer = RPLidarPeer(points_per_scan=200)
    valid = b"".join(peer.encode_node(k == 0, *peer.node_values(k)[1:]) for k in range(20_000))
    peer.close()
    scans: list = []
    proto = _scanning_protocol(scans)
    most = 0
    for i in range(0, len(valid), 4096):  # the serial port hands the bytes over in chunks
        proto.data_received(valid[i : i + 4096])
        most = max(most, proto.pending_nodes)
    assert 7000 < most <= MAX_REVOLUTION_NODES  # never more nodes kept than a revolution can have
    # node 8,001 overflowed: the revolution was dropped, and what follows is ignored until a start flag
    assert scans == [] and proto.overlong_revolutions == 1
    assert proto.dropped_nodes == MAX_REVOLUTION_NODES + 1 and proto.pending_nodes == 0
    one = b"".join(peer.encode_node(*peer.node_values(k)) for k in range(201))
    proto.data_received(one)  # start flags again: back in step, the next revolution is published
    assert [len(s) for s in scans] == [200] and proto.pending_nodes == 1


def test_line_noise_is_counted_not_published():
    rng = np.random.default_rng(7)
    scans: list = []
    proto = _scanning_protocol(scans)
    proto.data_received(rng.integers(0, 256, 100_000, dtype=np.uint8).tobytes())
    assert scans == []  # old decoders published thousands of few-node "scans" here
    assert proto.short_revolutions > 1000 and proto.desyncs > 1000 and proto.bad_nodes > 0
    assert proto.pending_nodes < MIN_REVOLUTION_NODES
    stats = proto.stats()
    assert stats["short_revolutions"] == proto.short_revolutions and stats["scans"] == 0


async def sleep_until(cond, step: float = 0.05, limit: float = 60.0) -> None:
    """Virtual-clock wait for ``cond`` (at most ``limit`` virtual seconds)."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + limit
    while not cond():
        assert loop.time() < deadline, "condition not met"
        await asyncio.sleep(step)


def lidar_driver(peer: RPLidarPeer) -> RPLidarDriver:
    # on the virtual clock a request reaches the model after the pty worker runs: generous answer times
    return RPLidarDriver(peer.path, response_timeout_s=100.0, watchdog_s=100.0)


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_model_without_start_flags_keeps_memory_bounded_and_recovers(caplog):
    with RPLidarPeer(points_per_scan=200, scan_hz=10.0) as peer:  # 2,000 nodes/s
        driver = lidar_driver(peer)
        task = asyncio.create_task(driver.run())
        await sleep_until(lambda: driver.latest.sample is not None)
        peer.set_fault("no_start_flag")
        await asyncio.sleep(0.2)  # the revolution under way when the fault began still completes
        seq, sent = driver.latest.sample.seq, peer.nodes_sent
        most = 0
        for _ in range(120):  # 12 s: 24,000 nodes with no start flag
            await asyncio.sleep(0.1)
            most = max(most, driver.protocol.pending_nodes)
        assert peer.nodes_sent - sent >= 24_000
        assert most <= MAX_REVOLUTION_NODES
        assert driver.latest.sample.seq == seq  # nothing published from the endless revolution
        stats = driver.stats()
        assert stats["overlong_revolutions"] == 1 and stats["dropped_nodes"] > MAX_REVOLUTION_NODES
        assert stats["restarts"] == 0  # nodes kept coming: not a stalled scan
        assert [r.getMessage() for r in caplog.records if "without a start flag" in r.getMessage()] == [
            f"RPLidar {peer.path!r}: dropped a revolution of over 8000 nodes without a start flag (lost start flags?)"
        ]
        peer.set_fault(None)
        await sleep_until(lambda: driver.latest.sample.seq >= seq + 2)
        assert len(driver.latest.value) == 200
        await driver.close()
        await asyncio.wait_for(task, 10)


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_model_sending_noise_publishes_nothing_and_logs_rate_limited(caplog):
    with RPLidarPeer(points_per_scan=200, scan_hz=10.0, noise_seed=3) as peer:
        driver = lidar_driver(peer)
        task = asyncio.create_task(driver.run())
        await sleep_until(lambda: driver.latest.sample is not None)
        peer.set_fault("noise")
        await asyncio.sleep(0.2)
        seq = driver.latest.sample.seq
        most = 0
        for _ in range(100):  # 10 s of noise: 100 kB
            await asyncio.sleep(0.1)
            most = max(most, driver.protocol.pending_nodes)
        assert driver.latest.sample.seq == seq
        stats = driver.stats()
        assert stats["short_revolutions"] > 500 and stats["desyncs"] > 500 and stats["bad_nodes"] > 0
        assert most < MIN_REVOLUTION_NODES
        short_logs = [r for r in caplog.records if "fewer than" in r.getMessage()]
        assert 1 <= len(short_logs) <= 3
        assert "more since the last report" in short_logs[-1].getMessage() or len(short_logs) == 1
        peer.set_fault(None)
        await sleep_until(lambda: driver.latest.sample.seq >= seq + 2)
        assert len(driver.latest.value) == 200
        await driver.close()
        await asyncio.wait_for(task, 10)
