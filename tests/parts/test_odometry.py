"""Odometer part against the Arduino encoder model: calibration, Donkeycar's direction modes, exact commands,
unplug/replug mid-drive, the stream watchdog, and Donkeycar's own client speaking to the model."""

from __future__ import annotations

import asyncio
import itertools
import math
import threading
import time
from types import SimpleNamespace

import pytest

from asyncdonkey import Vehicle
from asyncdonkey.clock import get_clock
from asyncdonkey.hw.encoder_protocol import (
    EncoderProtocolError,
    EncoderReading,
    continuous,
    millis_delta,
    parse_reading,
    tick_delta,
)
from asyncdonkey.parts.odometry import (
    FORWARD_ONLY,
    FORWARD_REVERSE,
    FORWARD_REVERSE_STOP,
    Odometer,
    meters_per_tick,
)
from asyncdonkey.testing.serial_peers import EncoderPeer

from ..waiting import await_until


async def delivered(peer: EncoderPeer, tail: bytes, timeout: float = 1.0) -> None:
    """Wait (real time; virtual time stands still) until the model has received bytes ending in ``tail``."""
    await await_until(
        lambda: peer.received.endswith(tail),
        timeout,
        lambda: f"{tail!r} at the model (got {bytes(peer.received)!r})",
        0,
    )


# ------------------------------------------------------------------------------------------- protocol
def test_readings_parse_one_or_two_encoders():
    assert parse_reading("123,4567\r\n") == (EncoderReading(123, 4567),)
    assert parse_reading("-5,10;7,10") == (EncoderReading(-5, 10), EncoderReading(7, 10))
    for bad in ("", "12", "1,2,3", "a,1", "1,-2", "1.5,2", "1_0,2", "1,2;", "99999999999,1", "1,4294967296"):
        with pytest.raises(EncoderProtocolError):
            parse_reading(bad)


def test_commands_and_wraparound_arithmetic():
    assert continuous(16) == b"c16\n" and continuous(0) == b"c0\n"
    with pytest.raises(ValueError, match="ms"):
        continuous(-1)
    assert tick_delta(2**31 - 2, -(2**31) + 3) == 5  # a 32-bit long rolling over forwards
    assert tick_delta(5, -5) == -10
    assert millis_delta(2**32 - 10, 5) == 15  # the 49.7-day millis wrap


def test_calibration_names_and_errors():
    assert meters_per_tick(mm_per_tick=12.7625) == pytest.approx(0.0127625)
    assert meters_per_tick(ticks_per_meter=200) == pytest.approx(0.005)
    assert meters_per_tick(encoder_ppr=20, wheel_radius=0.0315) == pytest.approx(2 * math.pi * 0.0315 / 20)
    with pytest.raises(ValueError, match="exactly one"):
        meters_per_tick()
    with pytest.raises(ValueError, match="exactly one"):
        meters_per_tick(mm_per_tick=1, ticks_per_meter=2)
    with pytest.raises(ValueError, match="wheel_radius"):
        meters_per_tick(encoder_ppr=20)
    with pytest.raises(ValueError, match="direction_mode"):
        Odometer("/dev/null", mm_per_tick=1, direction_mode=4)


def test_from_config_reads_donkeycar_names():
    cfg = SimpleNamespace(
        ODOM_SERIAL="/dev/ttyACM7",
        ODOM_SERIAL_BAUDRATE=57600,
        MM_PER_TICK=12.5,
        TACHOMETER_MODE=FORWARD_REVERSE,
        ODOM_SMOOTHING=3,
    )
    odom = Odometer.from_config(cfg)
    assert odom.meters_per_tick == pytest.approx(0.0125)
    assert (odom.direction_mode, odom.smoothing_count) == (FORWARD_REVERSE, 3)
    assert (odom.encoder.port.port, odom.encoder.port.baudrate) == ("/dev/ttyACM7", 57600)
    by_ppr = Odometer.from_config(SimpleNamespace(ENCODER_PPR=40, WHEEL_RADIUS=0.05))
    assert by_ppr.meters_per_tick == pytest.approx(2 * math.pi * 0.05 / 40)
    assert odom.run() == (0.0, 0.0, None)  # Donkeycar's Odometer output before the first reading


# -------------------------------------------------------------------------------- driving on virtual time
# A command the driver writes reaches the model when the kernel's pty worker runs, which on a virtual clock
# can be several timer jumps later (see asyncdonkey.testing.serial_peers). These tests therefore key their
# timing on what the model answered (the first reading), not on fixed virtual times from the start.


class Script:
    """Waits for the odometer's first reading, then plays ``phases`` of (seconds, throttle, wheel ticks/s)
    and stops the vehicle.

    Each phase turns the wheel for its first half only, so every tick is delivered and counted before the
    throttle (and so the direction) changes."""

    def __init__(self, peer: EncoderPeer, odom: Odometer, vehicle: Vehicle, phases, rate_hz: int = 20):
        self.peer, self.odom, self.vehicle = peer, odom, vehicle
        self.steps = []
        for seconds, throttle, speed in phases:
            n = round(seconds * rate_hz)
            self.steps += [(throttle, speed)] * (n // 2) + [(throttle, 0.0)] * (n - n // 2)
        self.k = None
        self.done = False

    def run(self):
        if self.k is None:
            if self.odom.latest.sample is None:
                return 0.0
            self.k = 0
        if self.k >= len(self.steps):
            self.done = True
            self.vehicle.stop()
            return self.steps[-1][0]
        throttle, speed = self.steps[self.k]
        self.peer.set_speed(speed)
        self.k += 1
        return throttle


PHASES = [(0.5, 0.5, 200.0), (0.5, 0.0, 80.0), (0.5, -0.5, -120.0), (0.5, -0.5, 0.0)]  # +50, +20, -30 ticks


@pytest.mark.asyncio
@pytest.mark.virtual_clock
@pytest.mark.parametrize(
    ("quadrature", "mode", "expected_ticks"),
    [
        (False, FORWARD_ONLY, 100),  # a single-channel count only grows
        (False, FORWARD_REVERSE, 40),  # coasting ticks count in the last direction
        (False, FORWARD_REVERSE_STOP, 20),  # ticks at zero throttle are ignored
        (True, FORWARD_ONLY, 40),  # a quadrature count is already signed
    ],
)
async def test_direction_modes_integrate_like_donkeycar(quadrature, mode, expected_ticks):
    with EncoderPeer(quadrature=quadrature) as peer:
        # a long watchdog: a late command must not look like a silent board
        odom = Odometer(peer.path, mm_per_tick=10.0, direction_mode=mode, watchdog_s=1000.0)
        v = Vehicle()
        script = Script(peer, odom, v, PHASES)
        v.add(script, outputs=["throttle"])
        v.add(odom, inputs=["throttle"], outputs=["enc/distance", "enc/speed", "enc/timestamp"])
        report = await v.run(rate_hz=20, duration=600)
        assert script.done
        assert v.mem["enc/distance"] == pytest.approx(expected_ticks * 0.01)
        assert v.mem["enc/speed"] == pytest.approx(0.0)
        assert 0 < v.mem["enc/timestamp"] <= get_clock().now()
        assert report.overruns == 0
        # exactly these bytes went to the board: reset, stream every 16 ms, and "stop streaming" at shutdown
        await delivered(peer, b"c\n")
        assert bytes(peer.received) == b"r\nc16\nc\n"
    assert odom.encoder.bad_lines == 0 and odom.rebases == 0


class StopAfterFirstReading:
    """Stops the vehicle ``seconds`` after the odometer's first reading; optional actions on the way."""

    def __init__(self, odom: Odometer, vehicle: Vehicle, seconds: float, at=()):
        self.odom, self.vehicle, self.seconds, self.at = odom, vehicle, seconds, sorted(at)
        self.t0 = None

    def run(self):
        now = get_clock().now()
        if self.t0 is None:
            if self.odom.latest.sample is None:
                return
            self.t0 = now
        while self.at and now - self.t0 >= self.at[0][0] - 1e-9:
            self.at.pop(0)[1]()
        if now - self.t0 >= self.seconds - 1e-9:
            self.vehicle.stop()


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_velocity_uses_the_boards_millis():
    with EncoderPeer() as peer:
        odom = Odometer(peer.path, ticks_per_meter=100, smoothing_count=5, stream_ms=20, watchdog_s=1000.0)
        v = Vehicle()
        v.add(odom, inputs=["throttle"], outputs=["enc/distance", "enc/speed", "enc/timestamp"])
        v.add(StopAfterFirstReading(odom, v, 1.0))
        v.mem["throttle"] = 0.3
        peer.set_speed(150.0)  # 1.5 m/s
        await v.run(rate_hz=20, duration=600)
        assert odom.encoder.port.first_lines_skipped == 1
        assert v.mem["enc/speed"] == pytest.approx(1.5, rel=0.05)
        # distance counts from the baseline reading (the second: the first is skipped); the board's own
        # millis say how long ago that was
        received = odom.encoder.readings
        base_ms = int(peer.sent_lines[1].split(",")[1])
        last_ms = int(peer.sent_lines[received].split(",")[1])
        assert v.mem["enc/distance"] == pytest.approx(1.5 * (last_ms - base_ms) / 1000, abs=0.03)


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_unplug_and_replug_mid_drive_keeps_distance_continuous():
    with EncoderPeer() as peer:
        odom = Odometer(peer.path, mm_per_tick=10.0, smoothing_count=5, stream_ms=20, watchdog_s=1000.0)
        odom.encoder.port.backoff_initial_s = 0.05
        trace = []
        loop = asyncio.get_running_loop()

        class Recorder:
            def __init__(self):
                self.resumed_at = None

            def run(self, distance, speed):
                trace.append((loop.time(), distance, speed))
                if odom.rebases and self.resumed_at is None:
                    self.resumed_at = loop.time()
                if self.resumed_at is not None and loop.time() - self.resumed_at >= 1.0 - 1e-9:
                    v.stop()

        v = Vehicle()
        v.add(odom, inputs=["throttle"], outputs=["enc/distance", "enc/speed", "enc/timestamp"])
        v.add(StopAfterFirstReading(odom, v, 600, at=[(1.0, peer.unplug), (1.5, peer.plug)]))
        recorder = Recorder()
        v.add(recorder, inputs=["enc/distance", "enc/speed"])
        v.mem["throttle"] = 0.5
        peer.set_speed(100.0)  # 1 m/s
        await v.run(rate_hz=20, duration=600)
        port = odom.encoder.port
        assert (port.disconnects, port.connects, odom.rebases) == (1, 2, 1)
        distances = [d for _, d, _ in trace]
        steps = [b - a for a, b in itertools.pairwise(distances)]
        assert min(steps) >= 0.0  # never backwards: the restarted counter did not subtract
        assert max(steps) <= 0.1  # and never a jump: 1 m/s for 50 ms is 0.05 m
        # before the unplug: ~1 m; after the replug it integrates at the wheel's speed again
        d_resume = next(d for t, d, _ in trace if t >= recorder.resumed_at)
        assert 0.9 <= d_resume <= 1.1
        assert distances[-1] - d_resume == pytest.approx(1.0, abs=0.06)
        assert trace[-1][2] == pytest.approx(1.0, rel=0.1)
        await delivered(peer, b"c\n")
    assert bytes(peer.received) == b"r\nc20\nr\nc20\nc\n"


@pytest.mark.realtime
def test_watchdog_restarts_the_stream_after_a_board_ignored_it_while_booting():
    """Real time (the point is when commands arrive relative to the board's boot, which on a virtual clock
    depends on the kernel's pty worker): r and c16 at connect are lost in the bootloader, the watchdog asks
    again every 0.1 s until the sketch listens."""

    async def body():
        with EncoderPeer(boot_s=0.3) as peer:
            odom = Odometer(peer.path, mm_per_tick=10.0, watchdog_s=0.1)
            peer.set_speed(100.0)
            task = asyncio.create_task(odom.update())
            await await_until(lambda: odom.encoder.readings >= 10, 3.0, "the stream to start", 0.01)
            await odom.shutdown()
            await asyncio.wait_for(task, 1)
            await delivered(peer, b"c\n")
            assert peer.ignored_while_booting >= 3  # r, c16, and at least the first re-ask
            assert odom.encoder.stream_restarts >= 2
            assert peer.commands.count("c16") == 1 + odom.encoder.stream_restarts
            assert odom.distance > 0

    with asyncio.Runner(loop_factory=asyncio.SelectorEventLoop) as runner:
        runner.run(body())


def test_run_ignores_none_and_nan_throttle():
    odom = Odometer("/dev/null", mm_per_tick=1.0, direction_mode=FORWARD_REVERSE_STOP)
    odom.run(-0.2)
    assert odom.direction == -1
    odom.run(None)
    odom.run(float("nan"))
    assert odom.direction == -1
    odom.run(0.0)
    assert odom.direction == 0


# ------------------------------------------------------------------------------ Donkeycar's client
@pytest.mark.realtime
@pytest.mark.donkeycar
def test_donkeycars_serial_encoder_reads_the_model():
    """Donkeycar's own SerialEncoder + Tachometer (blocking pyserial, in a thread) against the peer: the
    model answers ``r`` / ``p`` the way the sketch does, so Donkeycar counts the same ticks."""
    from donkeycar.parts.serial_port import SerialPort as DkSerialPort
    from donkeycar.parts.tachometer import SerialEncoder, Tachometer

    async def body():
        with EncoderPeer() as peer:
            peer.set_speed(200.0)
            stop = threading.Event()

            def donkeycar_side():
                tach = Tachometer(SerialEncoder(DkSerialPort(peer.path, 115200, timeout=0.05)), ticks_per_revolution=1)
                try:
                    revs = 0.0
                    for _ in range(60):
                        revs, _ = tach.run(throttle=1.0)
                        time.sleep(0.005)
                        if stop.is_set():
                            break
                    return revs
                finally:
                    tach.shutdown()

            revs = await asyncio.wait_for(asyncio.to_thread(donkeycar_side), 5)
            stop.set()
            assert peer.commands[0] == "r" and set(peer.commands[1:]) == {"p"}
            assert len(peer.sent_lines) >= 10
            last = int(peer.sent_lines[-2].split(",")[0])  # the last answer Donkeycar had read
            assert 10 <= revs <= last + 1

    with asyncio.Runner(loop_factory=asyncio.SelectorEventLoop) as runner:
        runner.run(body())
