"""The loop's timing in an MCAP recording equals the drive's own, sample for sample.

The profiler keeps every part's run times, each tick's lateness, duration and overrun, and each actuator's
sensing-to-actuation latency in rings. The recorder notes in the tick how far each series has got, and its
writer thread writes every sample up to there, each once. What must hold, on the virtual clock where every
figure is exact: the recording (read back directly and through ``asyncdonkey report``) holds the profiler's
samples, the same count and the same values in the same order, also when

* a pipelined part runs at its own rate (several runs in one tick, none in another),
* an actuator acts several times between two recorder runs (it reacts to each of the pilot's commands),
* a part is skipped on some ticks by its run condition,
* the recorder is not the last part,
* the writer falls behind: its disk answers with errors for a while, the queue fills and ticks' snapshots are
  dropped at the door; the timing of those ticks is still written, by the next snapshot that gets in.

And when the writer falls further behind than the profiler's window, the samples it can no longer read are
counted as dropped (in the recorder's stats, in the tick messages, in the report), never silently lost.
"""

from __future__ import annotations

import asyncio
import errno
import io
import json

import numpy as np
import pytest

import asyncdonkey.parts.background_writer as background_writer
from asyncdonkey import Vehicle, get_clock
from asyncdonkey.commands.report import load_timing, render_html
from asyncdonkey.latest import Latest
from asyncdonkey.parts.mcap import McapRecorder
from asyncdonkey.parts.mcap.encode import LATENCY_TOPIC, PARTS_TOPIC, TICK_TOPIC
from asyncdonkey.parts.mcap.reader import read_mcap

#: the camera here writes frame numbers, not images (what is measured is when frames come, not their pixels)
pytestmark = pytest.mark.asyncdonkey_checked(False)

RATE = 20
TICKS = 80


class PushCamera:
    """Captures at ``hz`` on its own schedule and pushes each frame: three frames per tick at 60 Hz."""

    def __init__(self, hz: float) -> None:
        self.hz = hz
        self.frames: Latest[int] = Latest()
        self.n = 0

    async def update(self) -> None:
        clock = get_clock()
        t0 = clock.now() + 0.004
        while True:
            await clock.sleep_until(t0 + self.n / self.hz)
            self.n += 1
            self.frames.publish(self.n, clock.now())

    def run(self):
        s = self.frames.sample
        return None if s is None else s.value

    def output_origin(self):
        s = self.frames.sample
        return None if s is None else s.timestamp

    def subscribe(self, callback):
        return self.frames.subscribe(callback)


class Pilot:
    """Inference of a few (virtual) milliseconds, a different time for each frame."""

    async def run(self, frame):
        await asyncio.sleep(0.001 + 0.001 * (frame % 7))
        return frame / 100, 0.5


class Motor:
    """An actuator reacting to each command: several actuations between two recorder runs."""

    def run(self, angle, throttle):
        return None

    def safe_state_sync(self):
        pass


class Busy:
    """A part in the tick that takes virtual time, on some ticks more than the period (an overrun, deadlines
    skipped); returns whether the next tick runs the part that has it as run condition."""

    def __init__(self) -> None:
        self.k = 0

    async def run(self):
        self.k += 1
        await asyncio.sleep(0.002 * (self.k % 5) + (0.12 if self.k % 17 == 0 else 0.0))  # overruns, skips
        return self.k % 3 != 0  # the next tick's run condition


class FlakyDisk(io.FileIO):
    """A file whose writes fail (full disk) while ``failing`` is set: the writer pauses and falls behind."""

    failing = False

    def write(self, b):
        if FlakyDisk.failing:
            raise OSError(errno.ENOSPC, "No space left on device")
        return super().write(b)


class DiskSwitch:
    """Fails the disk from tick ``start`` to tick ``stop``."""

    def __init__(self, start: int, stop: int) -> None:
        self.start, self.stop, self.k = start, stop, 0

    def run(self) -> None:
        self.k += 1
        if self.k == self.start:
            FlakyDisk.failing = True
        elif self.k == self.stop:
            FlakyDisk.failing = False


def car(path, *, queue_size=200, window=None, disk=None, skip=True) -> tuple[Vehicle, McapRecorder]:
    v = Vehicle(profiler_window=window)
    v.add(PushCamera(60), outputs=["cam/image_array"], name="camera")
    v.add(Pilot(), inputs=["cam/image_array"], outputs=["pilot/angle", "pilot/throttle"], pipelined=True,
          trigger="cam/image_array", name="pilot")  # fmt: skip
    v.add(Motor(), inputs=["pilot/angle", "pilot/throttle"], react=True, actuator=True, name="motor")
    v.add(Busy(), outputs=["busy"], name="busy")
    if disk is not None:
        v.add(disk, name="disk")
    rec = McapRecorder(path, v, fsync=False, queue_size=queue_size, sync_every=5,
                       open_file=lambda p: FlakyDisk(p, "wb"))  # fmt: skip
    v.add(rec, name="mcap")
    # after the recorder, skipped on some ticks
    v.add(Busy(), outputs=["later"], run_condition="busy" if skip else None, name="after")
    return v, rec


def recorded(path) -> tuple[dict[str, list[float]], dict[str, list[float]], list[dict]]:
    """Part times and latencies per name, in file order, and the tick messages."""
    parts: dict[str, list[float]] = {}
    latency: dict[str, list[float]] = {}
    ticks: list[dict] = []
    for m in read_mcap(path, {TICK_TOPIC, PARTS_TOPIC, LATENCY_TOPIC}):
        if m.topic == TICK_TOPIC:
            ticks.append(m.value)
        else:
            into = parts if m.topic == PARTS_TOPIC else latency
            for name, ms in m.value.items():
                into.setdefault(name, []).append(ms)
    return parts, latency, ticks


def profiler_samples(v: Vehicle) -> tuple[dict[str, list[float]], dict[str, list[float]], dict[str, list[float]]]:
    """The drive's samples in ms, as its report computes them (every run kept, none dropped)."""
    p = v.profiler
    parts = {name: list(s.recent(drop_last=False) * 1e3) for name, s in p.parts.items()}
    latency = {name: list(s.recent(drop_last=False) * 1e3) for name, s in p.latency.items()}
    loop = {name: list(s.recent(drop_last=False) * 1e3) for name, s in (
        ("lateness_ms", p.lateness), ("duration_ms", p.tick), ("overrun_ms", p.overrun))}  # fmt: skip
    return parts, latency, loop


@pytest.fixture
def slow_retry(monkeypatch):
    """The writer's pause after a disk error, long enough for many (virtual) ticks to come meanwhile."""
    monkeypatch.setattr(background_writer, "_RETRY_MIN_S", 0.3)
    FlakyDisk.failing = False
    yield
    FlakyDisk.failing = False


@pytest.mark.asyncio
@pytest.mark.virtual_clock
@pytest.mark.parametrize(
    "writer", ["keeps up", pytest.param("falls behind", marks=pytest.mark.realtime)]
)  # behind: by the writer's pause after a disk error, wall-clock time while the virtual ticks go on
async def test_recorded_timing_equals_the_drives_sample_for_sample(tmp_path, slow_retry, writer):
    path = tmp_path / "drive.mcap"
    lag = writer == "falls behind"
    v, rec = car(path, queue_size=3 if lag else 200, disk=DiskSwitch(20, 60) if lag else None)
    report = await v.run(rate_hz=RATE, max_loop_count=TICKS)
    rec.shutdown()
    s = rec.stats
    if lag:  # the writer did fall behind: snapshots were refused at the door and the disk failed
        assert s.dropped > 0 and s.sync_errors > 0
    else:
        assert s.dropped == 0
    assert s.written + s.dropped == TICKS and s.timing_dropped == 0

    parts, latency, loop = profiler_samples(v)
    got_parts, got_latency, ticks = recorded(path)
    # several pilot runs and actuations per tick on some ticks: the case where only the newest got recorded
    assert max(report.pipelined["pilot"]["runs"] / TICKS, len(latency["motor"]) / TICKS) > 2
    assert got_parts == parts  # every part, every run, in order, the skipped ticks of "after" left out
    assert len(parts["after"]) < TICKS - 1 and len(parts["busy"]) == TICKS - 1  # first run left out, as Donkeycar
    assert got_latency == latency
    assert [t["tick"] for t in ticks] == list(range(1, TICKS + 1))
    for figure, values in loop.items():
        assert [t[figure] for t in ticks] == values, figure
    assert max(loop["duration_ms"]) > 120 and report.overruns > 0 and report.skipped_deadlines > 0
    assert ticks[-1]["overruns"] == report.overruns and ticks[-1]["skipped_deadlines"] == report.skipped_deadlines

    # and so does the report: the same samples, so the same maxima as the drive's own report
    d = load_timing(path)
    assert {k: list(a) for k, a in d.parts.items()} == parts
    assert {k: list(ms) for k, (_, ms) in d.latency.items()} == latency
    assert max(d.latency["motor"][1]) == report.latency_ms["motor"]["max"]
    assert (list(d.lateness_ms), list(d.duration_ms), list(d.overrun_ms)) == (
        loop["lateness_ms"], loop["duration_ms"], loop["overrun_ms"])  # fmt: skip
    assert d.t.size == TICKS and d.overruns == report.overruns and d.timing_dropped == 0


@pytest.mark.asyncio
@pytest.mark.virtual_clock
@pytest.mark.realtime  # behind by the writer's pause after a disk error, wall-clock time
async def test_samples_that_left_the_ring_before_the_writer_read_them_are_counted_as_dropped(tmp_path, slow_retry):
    path = tmp_path / "drive.mcap"
    window = 32
    # the disk fails for longer than the window: the snapshots queued before can no longer find their samples
    v, rec = car(path, queue_size=2, window=window, disk=DiskSwitch(10, 10 + 3 * window), skip=False)
    await v.run(rate_hz=RATE, max_loop_count=TICKS + 2 * window)
    rec.shutdown()
    s = rec.stats
    assert s.timing_dropped > 0 and s.dropped > 0

    p = v.profiler
    got_parts, got_latency, ticks = recorded(path)
    taken = p.tick.count + sum(x.count for x in [*p.parts.values(), *p.latency.values()])
    in_file = len(ticks) + sum(map(len, got_parts.values())) + sum(map(len, got_latency.values()))
    assert in_file + s.timing_dropped == taken  # every sample is in the file or counted as dropped
    assert ticks[-1]["timing_dropped"] == s.timing_dropped
    # what is in the file is each sample once, in order: the newest (still in the window) are all there
    newest = list(p.latency["motor"].recent(False) * 1e3)[1:]
    assert got_latency["motor"][-len(newest) :] == newest
    assert [t["tick"] for t in ticks] == sorted({t["tick"] for t in ticks})
    d = load_timing(path)
    assert d.timing_dropped == s.timing_dropped
    assert f"<b>{s.timing_dropped}</b> timing samples are not in this recording" in render_html(d)


def test_the_report_reads_files_whose_tick_messages_carried_the_previous_ticks_duration(tmp_path):
    """Before each tick message carried its own tick's figures (and ``timing_dropped``), it carried the duration
    and overrun of the tick before it, and the counters the recorder read then; such files still read right."""
    from mcap.writer import Writer

    path = tmp_path / "old.mcap"
    durations = [10.0, 170.0, 12.0, 11.0]  # tick 2 overran, 2 deadlines skipped after it
    with open(path, "wb") as f:
        w = Writer(f)
        w.start()
        sid = w.register_schema("asyncdonkey.Tick", "jsonschema", b"{}")
        cid = w.register_channel(TICK_TOPIC, "json", sid)
        starts = [0.0, 0.05, 0.25, 0.30, 0.35]
        for k in range(1, 6):
            prev = durations[k - 2] if k > 1 else None
            msg = {
                "tick": k,
                "lateness_ms": 20.0 if k == 3 else 0.0,
                "duration_ms": prev,
                "overrun_ms": None if prev is None else max(0.0, prev - 50.0),
                "overruns": 1 if k >= 3 else 0,
                "skipped_deadlines": 2 if k >= 3 else 0,
            }
            ns = int(starts[k - 1] * 1e9)
            w.add_message(cid, ns, json.dumps(msg).encode(), ns)
        w.finish()
    d = load_timing(path)
    assert d.t.size == 5 and list(d.lateness_ms) == [0.0, 0.0, 20.0, 0.0, 0.0]
    assert list(d.duration_ms[:4]) == durations and np.isnan(d.duration_ms[4])  # each tick's own, the last unknown
    assert list(d.overrun_ms[:4]) == [0.0, 120.0, 0.0, 0.0]
    assert d.overruns == 1 and d.skipped_deadlines == 2 and d.skipped_at == [(0.25, 2)]
    assert render_html(d).count("overran by") == 1
