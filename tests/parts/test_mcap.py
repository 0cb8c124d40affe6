"""McapRecorder: every schema read back with the ``mcap`` reader, timing topics, change-only recording, the
time mapping, a ``kill -9`` mid-recording and a full disk."""

from __future__ import annotations

import errno
import io
import json
import math
import signal
import subprocess
import sys
import textwrap
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from mcap.exceptions import EndOfFile
from mcap.reader import NonSeekingReader, make_reader

from asyncdonkey.loop import Vehicle
from asyncdonkey.parts.mcap import McapRecorder, TimeMap
from asyncdonkey.parts.mcap.reader import McapTub, decode_image, mcap_info, read_mcap
from asyncdonkey.parts.tub.encode import make_converter


def frame(k: int) -> np.ndarray:
    yy, xx = np.mgrid[0:120, 0:160]
    return np.dstack([(xx + 9 * k) % 256, (yy * 2) % 256, np.full_like(xx, 25 * k % 256)]).astype(np.uint8)


@dataclass
class FakeScan:
    angles: np.ndarray
    distances: np.ndarray


class Sensors:
    """Every kind of value a car writes, changing each tick."""

    def __init__(self) -> None:
        self.k = 0

    def run(self):
        self.k += 1
        k = self.k
        scan = FakeScan(np.array([0.0, 90.0, 180.0, 270.0]), np.array([1000.0, 2000.0, 0.0, 500.0 + k]))
        return (
            frame(k),
            k / 100,
            0.25,
            "user" if k % 2 else "local",
            k % 3 == 0,
            np.array([0.1, 0.2, 9.8]) * k,
            {"x": k, "y": -k},
            scan,
            45.0 + k * 1e-5,
            7.0,
        )


OUTPUTS = [
    "cam/image_array",
    "user/angle",
    "user/throttle",
    "user/mode",
    "recording",
    "imu/acc",
    "pos/xy",
    "lidar/scan",
    "gps/latitude",
    "gps/longitude",
]


class Motor:
    """An actuator: the loop measures its sensing-to-actuation latency."""

    def run(self, throttle):
        return None

    def safe_state_sync(self):
        pass


def by_topic(path):
    out: dict[str, list] = {}
    for m in read_mcap(path):
        out.setdefault(m.topic, []).append(m)
    return out


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_every_schema_reads_back_with_the_mcap_reader(tmp_path):
    path = tmp_path / "drive.mcap"
    v = Vehicle()
    v.add(Sensors(), outputs=OUTPUTS, name="sensors")
    v.add(Motor(), inputs=["user/throttle"], actuator=True, name="motor")
    rec = McapRecorder(path, v, metadata={"car": "test"}, fsync=False)
    v.add(rec, name="mcap")
    await v.run(rate_hz=20, max_loop_count=10)
    rec.shutdown()
    assert (rec.stats.written, rec.stats.dropped, rec.stats.bad_values) == (10, 0, 0)

    # the plain mcap reader (summary present) sees every topic with its schema
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None
        schemas = {ch.topic: summary.schemas[ch.schema_id].name for ch in summary.channels.values()}
        counts = summary.statistics.channel_message_counts
        topic_counts = {ch.topic: counts[cid] for cid, ch in summary.channels.items()}
    assert schemas["/cam/image_array"] == "foxglove.CompressedImage"
    assert schemas["/lidar/scan"] == "foxglove.LaserScan"
    assert schemas["/gps/fix"] == "foxglove.LocationFix"
    assert schemas["/user/angle"] == "asyncdonkey.Number"
    assert schemas["/user/mode"] == "asyncdonkey.String"
    assert schemas["/recording"] == "asyncdonkey.Bool"
    assert schemas["/imu/acc"] == "asyncdonkey.Array"
    assert schemas["/pos/xy"] == "asyncdonkey.Object"
    assert topic_counts["/cam/image_array"] == 10 and topic_counts["/asyncdonkey/tick"] == 10

    msgs = by_topic(path)
    info = mcap_info(path)
    assert not info.recovered and info.metadata["asyncdonkey.session"] == {"car": "test"}
    times = TimeMap.from_metadata(info.metadata["asyncdonkey.clock"])
    assert times.clock == "virtual"

    # images: the same JPEG the tub writer makes, decoded to the same array
    jpeg = make_converter("image_array")
    for k, m in enumerate(msgs["/cam/image_array"], start=1):
        assert m.value.format == "jpeg" and m.value.frame_id == "cam/image_array"
        assert bytes(m.value.data) == jpeg(frame(k))
        assert np.abs(decode_image(m.value).astype(int) - frame(k)).mean() < 3
    # ticks are 50 ms apart exactly on the virtual clock, and the message timestamp is the origin
    logs = [m.log_time_ns for m in msgs["/cam/image_array"]]
    assert set(np.diff(logs)) == {50_000_000}
    first = msgs["/cam/image_array"][0]
    ts = first.value.timestamp
    assert ts.seconds * 10**9 + ts.nanos == first.publish_time_ns <= first.log_time_ns

    # JSON values, with the age of their sensing at the tick
    assert [m.value["value"] for m in msgs["/user/angle"]] == [k / 100 for k in range(1, 11)]
    assert [m.value["value"] for m in msgs["/user/mode"]][:2] == ["user", "local"]
    assert [m.value["value"] for m in msgs["/recording"]][:3] == [False, False, True]
    assert msgs["/imu/acc"][1].value["value"] == pytest.approx([0.2, 0.4, 19.6])
    assert msgs["/pos/xy"][2].value["value"] == {"x": 3, "y": -3}
    for m in msgs["/user/angle"]:
        assert m.value["age_ms"] == pytest.approx((m.log_time_ns - m.publish_time_ns) / 1e6)

    # lidar: clockwise degrees in mm -> counter-clockwise 1° bins in metres
    scan = msgs["/lidar/scan"][0].value
    ranges = list(scan.ranges)
    assert len(ranges) == 360 and scan.start_angle == 0 and scan.end_angle == pytest.approx(math.radians(359))
    assert ranges[0] == 1.0 and ranges[270] == 2.0 and ranges[90] == pytest.approx(0.501) and ranges[180] == 0.0

    # the steering drawn over each frame: angle k/100 (of ±1 = ±45°) tilts the line right of vertical
    assert schemas["/cam/image_array/steering"] == "foxglove.ImageAnnotations"
    overlay = msgs["/cam/image_array/steering"][9].value  # k = 10: angle 0.1
    (line,) = overlay.points
    (x0, y0), (x1, y1) = ((p.x, p.y) for p in line.points)
    assert (x0, y0) == (80, 120) and y1 < y0
    assert math.degrees(math.atan2(x1 - x0, y0 - y1)) == pytest.approx(4.5)

    fix = msgs["/gps/fix"][-1].value
    assert fix.latitude == pytest.approx(45.0001) and fix.longitude == 7.0

    # the loop's timing: each tick, each part's time, the actuator's latency
    ticks = [m.value for m in msgs["/asyncdonkey/tick"]]
    assert [t["tick"] for t in ticks] == list(range(1, 11))  # the last one written at shutdown
    assert all(t["lateness_ms"] == 0 for t in ticks)  # the virtual clock is never late
    assert all(t["duration_ms"] == 0 and t["overrun_ms"] == 0 for t in ticks)  # each tick's own
    assert all(t["overruns"] == 0 and t["skipped_deadlines"] == 0 and t["timing_dropped"] == 0 for t in ticks)
    starts = [m.log_time_ns for m in msgs["/asyncdonkey/tick"]]  # stamped with the tick's start
    assert set(np.diff(starts)) == {50_000_000} and starts[0] == logs[0]
    parts = [m.value for m in msgs["/asyncdonkey/parts"]]
    assert {"sensors", "motor"} <= set(parts[-1]) and all(v >= 0 for v in parts[-1].values())
    latency = [m.value["motor"] for m in msgs["/asyncdonkey/latency"]]
    assert len(latency) == 10 and all(x >= 0 for x in latency)


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_a_channel_is_recorded_on_the_ticks_that_wrote_it_or_every_tick(tmp_path):
    class Slow:
        def __init__(self):
            self.k = 0

        def run(self):
            self.k += 1
            return self.k if self.k % 4 == 1 else None  # writes on ticks 1, 5, 9

    for every_tick, expected in ((False, [1, 5, 9]), (True, [1, 1, 1, 1, 5, 5, 5, 5, 9, 9])):
        v = Vehicle()
        v.add(Slow(), outputs=["gps/speed"])
        path = tmp_path / f"every_{every_tick}.mcap"
        rec = McapRecorder(path, v, ["gps/speed"], every_tick=every_tick, timing=False, fsync=False)
        v.add(rec)
        await v.run(rate_hz=10, max_loop_count=10)
        rec.shutdown()
        msgs = by_topic(path)
        assert set(msgs) == {"/gps/speed"}
        assert [m.value["value"] for m in msgs["/gps/speed"]] == expected
        # a value re-recorded later keeps its origin: its age grows
        if every_tick:
            ages = [m.value["age_ms"] for m in msgs["/gps/speed"][:4]]
            assert ages == pytest.approx([0, 100, 200, 300], abs=1e-6)


def test_time_map_is_linear_and_round_trips():
    tm = TimeMap(100.0, 1_700_000_000_000_000_000)
    assert tm.to_ns(100.0) == 1_700_000_000_000_000_000
    assert tm.to_ns(101.5) - tm.to_ns(100.0) == 1_500_000_000
    assert tm.to_clock(tm.to_ns(123.456789)) == pytest.approx(123.456789, abs=1e-9)
    assert TimeMap.from_metadata(tm.as_metadata()) == tm


def test_bad_arguments_name_the_recorder(tmp_path):
    with pytest.raises(ValueError, match=r"McapRecorder\(.*x.mcap\): queue_size"):
        McapRecorder(tmp_path / "x.mcap", Vehicle(), queue_size=0)
    with pytest.raises(ValueError, match="compression"):
        McapRecorder(tmp_path / "y.mcap", Vehicle(), compression="gzip")
    with pytest.raises(TypeError, match="vehicle"):
        McapRecorder(tmp_path / "z.mcap", object())
    with pytest.raises(ValueError, match="kind"):
        McapRecorder(tmp_path / "w.mcap", Vehicle(), kinds={"a": "video"})


CHILD = textwrap.dedent(
    """
    import asyncio, sys
    import numpy as np
    from asyncdonkey.loop import Vehicle
    from asyncdonkey.parts.mcap import McapRecorder

    class Cam:
        def __init__(self):
            self.k = 0
        def run(self):
            self.k += 1
            return np.full((120, 160, 3), self.k % 200, np.uint8), self.k / 1000

    class Report:
        def __init__(self, rec):
            self.rec, self.last = rec, -1
        def run(self):
            d = self.rec.stats.durable
            if d != self.last:
                print(d, flush=True)
                self.last = d

    async def main():
        v = Vehicle()
        v.add(Cam(), outputs=["cam/image_array", "user/angle"])
        rec = McapRecorder(sys.argv[1], v, sync_interval_s=0.05, sync_every=20)
        v.add(rec)
        v.add(Report(rec))
        await v.run(rate_hz=200)

    asyncio.run(main())
    """
)


@pytest.mark.realtime  # the kill lands after a real-time wait for the child's progress
@pytest.mark.subprocess
@pytest.mark.parametrize("kill_after", [30, 77])
def test_kill_9_mid_recording_leaves_a_readable_file(tmp_path, kill_after):
    path = tmp_path / "killed.mcap"
    proc = subprocess.Popen([sys.executable, "-c", CHILD, str(path)], stdout=subprocess.PIPE, text=True)
    durable = 0
    deadline = time.monotonic() + 30
    try:
        assert proc.stdout is not None
        for line in proc.stdout:
            durable = int(line)
            if durable >= kill_after or time.monotonic() > deadline:
                break
        time.sleep(0.001 * (kill_after % 7))
        proc.send_signal(signal.SIGKILL)
    finally:
        proc.kill()
        proc.wait()
    assert durable >= kill_after, "the child never reported enough durable ticks"
    info = mcap_info(path)
    assert info.recovered  # no summary: the writer never closed the file
    angles = [m.value["value"] for m in read_mcap(path, {"/user/angle"})]
    assert len(angles) >= durable
    assert angles == [k / 1000 for k in range(1, len(angles) + 1)]  # every tick, in order, no holes
    images = [m.value for m in read_mcap(path, {"/cam/image_array"})]
    assert len(images) == len(angles)
    assert decode_image(images[-1])[0, 0, 0] == len(images) % 200
    # and it replays as a tub
    assert sum(1 for _ in McapTub(path).records()) == len(images)
    # the mcap package's own streaming reader gets the same messages, then reports the torn end
    plain = []
    with open(path, "rb") as f, pytest.raises(EndOfFile):
        for _, channel, message in NonSeekingReader(f).iter_messages(log_time_order=False):
            if channel.topic == "/user/angle":
                plain.append(json.loads(message.data)["value"])
    assert plain == angles


class FullDisk(io.FileIO):
    """A file on a disk that fills up after ``room`` bytes."""

    room = 0

    def write(self, b):
        if self.tell() + len(b) > self.room:
            raise OSError(errno.ENOSPC, "No space left on device")
        return super().write(b)


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_a_full_disk_leaves_every_synced_tick_readable(tmp_path, caplog):
    path = tmp_path / "full.mcap"
    FullDisk.room = 60_000

    class Cam:
        def __init__(self):
            self.k = 0

        def run(self):
            self.k += 1
            return frame(self.k), self.k

    v = Vehicle()
    v.add(Cam(), outputs=["cam/image_array", "n"])
    rec = McapRecorder(path, v, sync_every=5, fsync=False, compression="none", open_file=lambda p: FullDisk(p, "wb"))
    v.add(rec)
    await v.run(rate_hz=20, max_loop_count=60)
    rec.shutdown()
    s = rec.stats
    assert s.failed > 0 and s.written + s.failed == 60 and s.sync_errors >= 1
    assert s.durable % 5 == 0 and s.durable > 0
    assert Path(path).stat().st_size <= FullDisk.room
    ns = [m.value["value"] for m in read_mcap(path, {"/n"})]
    assert ns == list(range(1, s.written + 1)) and s.written == s.durable  # written = in the file
    assert not mcap_info(path).recovered  # closed with a footer, in the room reserved for it
    with open(path, "rb") as f:  # the mcap package's streaming reader reads to that clean end
        plain = [json.loads(m.data)["value"] for _, ch, m in NonSeekingReader(f).iter_messages() if ch.topic == "/n"]
    assert plain == ns


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_a_value_no_schema_fits_leaves_its_channel_out_once_and_the_rest_recorded(tmp_path, caplog):
    class Odd:
        def run(self):
            return object(), float("nan"), 1.0

    v = Vehicle()
    v.add(Odd(), outputs=["odd", "maybe", "fine"])
    path = tmp_path / "odd.mcap"
    rec = McapRecorder(path, v, timing=False, fsync=False)
    v.add(rec)
    await v.run(rate_hz=20, max_loop_count=5)
    rec.shutdown()
    assert rec.stats.bad_values == 1 and "odd" in rec.encoder.bad_channels
    assert "'odd' is not recorded" in caplog.text
    msgs = by_topic(path)
    assert set(msgs) == {"/maybe", "/fine"}
    assert [m.value["value"] for m in msgs["/maybe"]] == [None] * 5  # NaN has no JSON form: null
