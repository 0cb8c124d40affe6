"""RPLidar part on a vehicle against the RPLidar A1 model: Donkeycar-compatible ``lidar/dist_array``, the
array outputs, ticks that never wait for a scan, and recovery after unplug/replug."""

from __future__ import annotations

import asyncio
import math
from types import SimpleNamespace

import numpy as np
import pytest

from asyncdonkey import Vehicle
from asyncdonkey.clock import get_clock
from asyncdonkey.hw.rplidar import RPLidarDriver, Scan
from asyncdonkey.parts.lidar import RPLidar
from asyncdonkey.testing.serial_peers import RPLidarPeer


class StopAfterScans:
    def __init__(self, vehicle: Vehicle, driver: RPLidarDriver, scans: int, on_first=None):
        self.vehicle, self.driver, self.scans, self.on_first = vehicle, driver, scans, on_first
        self.first_seq = None

    def run(self):
        s = self.driver.latest.sample
        if s is None:
            return
        if self.first_seq is None:
            self.first_seq = s.seq
            if self.on_first is not None:
                self.on_first()
        if s.seq - self.first_seq >= self.scans:
            self.vehicle.stop()


def lidar_part(peer: RPLidarPeer, **kw) -> RPLidar:
    # On a virtual clock a request reaches the model after the kernel's pty worker runs, possibly several
    # timer jumps later: give answers plenty of virtual time.
    driver = RPLidarDriver(peer.path, response_timeout_s=100.0, watchdog_s=100.0)
    return RPLidar(driver=driver, **kw)


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_dist_array_is_donkeycars_channel_done_right():
    with RPLidarPeer(points_per_scan=180, scan_hz=7.0, invalid_every=11) as peer:
        lidar = lidar_part(peer, lower_limit=90, upper_limit=270)
        v = Vehicle()
        v.add(lidar, outputs=["lidar/dist_array"])
        v.add(StopAfterScans(v, lidar.driver, 3))
        report = await v.run(rate_hz=20, duration=600)
        dist = v.mem["lidar/dist_array"]
        assert isinstance(dist, np.ndarray) and dist.dtype == np.float32
        # the newest scan is a full revolution; every 11th node of the stream is "no return"
        scan = lidar.scan
        assert scan is not None and len(scan) == 180
        k0 = (scan.index - 1) * 180  # scan n is the model's revolution n - 1 (counted from 0)
        nodes = [peer.node_values(k0 + i) for i in range(180)]
        keep = [(a / 64, d / 4) for _, q, a, d in nodes if q and d and 90 < a / 64 < 270]
        keep.sort()
        assert np.array_equal(dist, np.array([d for _, d in keep], np.float32))
        # no scan ever made a tick late: on the virtual clock every tick started on its deadline
        assert report.overruns == 0 and report.lateness_ms["max"] == 0.0
        assert lidar.driver.protocol.bad_nodes == 0
        stats = lidar.stats()
        assert stats["scans"] == scan.index and stats["short_revolutions"] == stats["overlong_revolutions"] == 0


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_array_outputs_and_scan_output():
    with RPLidarPeer(points_per_scan=100, scan_hz=10.0) as peer:
        arrays = lidar_part(peer, output="arrays")
        v = Vehicle()
        outs = ["lidar/angles", "lidar/distances", "lidar/qualities"]
        v.add(arrays, outputs=outs)
        v.add(StopAfterScans(v, arrays.driver, 2))
        await v.run(rate_hz=20, duration=600)
        angles, dists, quals = (v.mem[k] for k in outs)
        assert len(angles) == len(dists) == len(quals) == 100
        assert angles.dtype == dists.dtype == np.float32 and quals.dtype == np.uint8
        assert np.all(np.diff(angles) > 0)  # one revolution, in measuring order
        # the room is 4 m x 3 m with the lidar at (1.5, 1.0) facing +x: straight ahead is the far wall
        ahead = dists[np.argmin(np.abs(angles - 0.2))]
        assert ahead == pytest.approx(2500.0, abs=0.5)
        for i in range(0, 100, 7):
            assert dists[i] == pytest.approx(peer.true_distance_mm(float(angles[i])), abs=0.25)


def test_before_the_first_scan_outputs_are_empty_or_nothing():
    assert RPLidar(port="/dev/null").run().shape == (0,)  # Donkeycar returns [] before a scan
    assert RPLidar(port="/dev/null", output="arrays").run() is None  # nothing is written
    scan = Scan(np.zeros(0, np.float32), np.zeros(0, np.float32), np.zeros(0, np.uint8), 0.0, 1)
    part = RPLidar(port="/dev/null", output="scan")
    part._on_scan(scan)
    assert part.run() is scan


def test_configuration_and_errors():
    part = RPLidar.from_config(SimpleNamespace(LIDAR_LOWER_LIMIT=90, LIDAR_UPPER_LIMIT=270), port="/dev/ttyUSB3")
    assert (part.lower_limit, part.upper_limit, part.driver.port.port) == (90, 270, "/dev/ttyUSB3")
    with pytest.raises(ValueError, match="lower_limit"):
        RPLidar(270, 90)
    with pytest.raises(ValueError, match="output"):
        RPLidar(output="image")


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_unplug_mid_drive_then_scans_resume():
    with RPLidarPeer(points_per_scan=90, scan_hz=10.0) as peer:
        lidar = lidar_part(peer)
        lidar.driver.port.backoff_initial_s = 0.05
        loop = asyncio.get_running_loop()
        v = Vehicle()
        seen = []

        class Watch:
            def run(self, dist):
                seen.append((loop.time(), None if dist is None else len(dist), lidar.driver.port.connected))

        def unplug():
            peer.unplug()
            loop.call_later(0.5, peer.plug)

        v.add(lidar, outputs=["lidar/dist_array"])
        v.add(Watch(), inputs=["lidar/dist_array"])
        v.add(StopAfterScans(v, lidar.driver, 6, on_first=unplug))
        await v.run(rate_hz=20, duration=600)
        port = lidar.driver.port
        assert (port.disconnects, port.connects) == (1, 2)
        assert any(not connected for _, _, connected in seen)  # ticks went on while it was unplugged
        assert [c for c, _ in peer.requests][:8] == [0x25, 0x50, 0x52, 0x20] * 2  # then STOP at shutdown
        assert len(lidar.run()) == 90 and lidar.driver.latest.sample.seq >= 6
        assert math.isfinite(float(lidar.run().sum()))
        assert get_clock().now() > 0.5
