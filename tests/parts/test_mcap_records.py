"""Records in MCAP files: grouped by their own number, not by time; exact millisecond times from tubs; a file
cut by a full disk read to a clean end by the ``mcap`` package's streaming reader; a shutdown that lost nothing
says so without an error; a value that overflows a float never costs the frame beside it."""

from __future__ import annotations

import asyncio
import contextlib
import ctypes
import errno
import io
import json
import logging
import os
import time
import types

import numpy as np
import pytest
from mcap.reader import NonSeekingReader, make_reader
from mcap.writer import Writer

import asyncdonkey.parts.background_writer as background_writer
import asyncdonkey.parts.mcap.sink as sink_module
from asyncdonkey import Vehicle
from asyncdonkey.commands.convert import tub_to_mcap
from asyncdonkey.parts.mcap import McapRecorder
from asyncdonkey.parts.mcap.encode import TickEncoder, TickSnapshot, TimeMap
from asyncdonkey.parts.mcap.reader import McapTub, read_mcap
from asyncdonkey.parts.tub import Tub
from asyncdonkey.testing import VirtualClockLoop

with contextlib.redirect_stdout(io.StringIO()):  # Donkeycar prints a banner on import
    import donkeycar.parts.tub_v2 as dk_tub_v2


def frame(k: int) -> np.ndarray:
    yy, xx = np.mgrid[0:60, 0:80]
    return np.dstack([(xx + 9 * k) % 256, (yy * 2) % 256, np.full_like(xx, 25 * k % 256)]).astype(np.uint8)


# ------------------------------------------------------------------------------------ records by number
#: 30 records' milliseconds, as Donkeycar stamps them (``int(round(time.time() * 1000))``) for a loop faster than
#: its clock's resolution, or records written in a burst: 17 of them share a millisecond with another
BASE_MS = 1_717_171_717_171
OFFSETS = [0, 0, 0, 1, 1, 1, 100, 100, 100, 100, 150, 151, 200, 200, 250, 300, 301, 350, 350, 350, 400, 450, 500,
           550, 600, 650, 700, 700, 750, 800]  # fmt: skip


def donkeycar_tub(path, monkeypatch) -> list[dict]:
    """A tub written by Donkeycar 5.3's own ``Tub``, its clock made to stamp :data:`OFFSETS`."""
    stamps = iter((BASE_MS + d) / 1000 for d in OFFSETS)
    monkeypatch.setattr(dk_tub_v2, "time", types.SimpleNamespace(time=lambda: next(stamps)))
    tub = dk_tub_v2.Tub(str(path), inputs=["cam/image_array", "user/angle"], types=["image_array", "float"])
    for k in range(len(OFFSETS)):
        tub.write_record({"cam/image_array": frame(k), "user/angle": k / 100})
    tub.close()
    return [dict(r.raw) for r in Tub(path)]


@pytest.mark.donkeycar
def test_a_tub_with_records_sharing_a_millisecond_comes_back_whole(tmp_path, monkeypatch):
    original = donkeycar_tub(tmp_path / "tub", monkeypatch)
    shared = [ms for ms in OFFSETS if OFFSETS.count(ms) > 1]
    assert len(original) == 30 and len(shared) == 17
    mcap = tmp_path / "tub.mcap"
    res = tub_to_mcap(tmp_path / "tub", mcap)
    assert res.records == 30

    back = list(McapTub(mcap).records())
    assert len(back) == 30
    assert (
        [r["_timestamp_ms"] for r in back] == [r["_timestamp_ms"] for r in original] == [BASE_MS + d for d in OFFSETS]
    )
    assert [r["user/angle"] for r in back] == [k / 100 for k in range(30)]
    assert [r["_index"] for r in back] == list(range(30))
    for k in (0, 1, 2, 29):  # each record its own frame (the JPEG the tub holds, copied)
        assert (
            back[k].image_bytes("cam/image_array")
            == (tmp_path / "tub" / "images" / original[k]["cam/image_array"]).read_bytes()
        )

    # log times are the tub's milliseconds exactly, in integer nanoseconds; each record has its own number
    with open(mcap, "rb") as f:
        msgs = [(ch.topic, m.log_time, m.publish_time, m.sequence) for _, ch, m in make_reader(f).iter_messages(
            log_time_order=False)]  # fmt: skip
    frames = [(log, pub, seq) for topic, log, pub, seq in msgs if topic == "/cam/image_array"]
    assert [log for log, _, _ in frames] == [(BASE_MS + d) * 1_000_000 for d in OFFSETS]
    assert all(pub == log for log, pub, _ in frames)
    assert [seq for _, _, seq in frames] == list(range(1, 31))


def test_a_tub_far_from_its_first_record_still_maps_to_the_exact_millisecond(tmp_path):
    tm = TimeMap(0.0, BASE_MS * 1_000_000, "tub", resolution_ns=1_000_000)
    for d in (1, 49, 86_400_000 * 365 + 7, 2**40 + 3):  # a year, and 35 years, after the first record
        assert tm.to_ns(d / 1000) == (BASE_MS + d) * 1_000_000
    assert TimeMap.from_metadata(tm.as_metadata()) == tm


def test_a_file_without_record_numbers_is_grouped_by_log_time(tmp_path):
    """Files written before records were numbered carry ``sequence`` 0: their ticks are told apart by log
    time, as they were recorded (one log time per tick)."""
    path = tmp_path / "old.mcap"
    enc = TickEncoder(every_tick=True, timing=False, steering=())
    times = TimeMap(0.0, BASE_MS * 1_000_000, "virtual")
    with open(path, "wb") as f:
        w = Writer(f)
        w.start()
        channels: dict[str, int] = {}
        for k in range(4):
            snap = TickSnapshot(k * 0.05, {"cam/image_array": frame(k), "user/angle": k / 10}, {}, 0, None, None, None)
            for spec, data, log_ns, pub_ns in enc.encode(snap, times):
                if spec.topic not in channels:
                    sid = w.register_schema(spec.schema_name, spec.schema_encoding, spec.schema_data)
                    channels[spec.topic] = w.register_channel(spec.topic, spec.message_encoding, sid)
                w.add_message(channels[spec.topic], log_ns, data, pub_ns)  # no sequence: 0
        w.finish()
    assert {m.sequence for m in read_mcap(path)} == {0}
    back = list(McapTub(path).records())
    assert [r["user/angle"] for r in back] == [0.0, 0.1, 0.2, 0.3]
    assert [r["_timestamp_ms"] for r in back] == [BASE_MS + 50 * k for k in range(4)]


# ------------------------------------------------------------------------------------ a full disk
class BudgetDisk(io.FileIO):
    """A file alone on a disk of ``room`` bytes. A write takes what fits and reports it (a short write), the
    next one fails with ``ENOSPC``; bytes the file has, or has reserved, take no new room; truncating frees
    what lies beyond, reservations included (as ``ftruncate`` does)."""

    room = 0
    reserved = 0  # the end of the blocks the file holds beyond its size (fallocate, keeping the size)

    def _held(self) -> int:
        return max(os.fstat(self.fileno()).st_size, BudgetDisk.reserved)

    def write(self, b) -> int:
        held = self._held()
        free = self.room - held + max(0, held - self.tell())
        if free <= 0:
            raise OSError(errno.ENOSPC, "No space left on device")
        return super().write(bytes(b)[:free])

    def truncate(self, size=None) -> int:
        BudgetDisk.reserved = self.tell() if size is None else size
        return super().truncate(size)


def budget_fallocate(disk: list[BudgetDisk]):
    """``fallocate`` on the budget disk: reserves room up to ``offset + length`` or fails with ENOSPC."""

    def fallocate(fd, mode, offset, length) -> int:
        held = disk[0]._held()
        if offset + length - held > BudgetDisk.room - held:
            ctypes.set_errno(errno.ENOSPC)
            return -1
        BudgetDisk.reserved = max(BudgetDisk.reserved, offset + length)
        return 0

    return fallocate


class Cam:
    def __init__(self) -> None:
        self.k = 0

    def run(self):
        self.k += 1
        return frame(self.k), self.k


def record_onto(path, room: int, opened: list[BudgetDisk]) -> McapRecorder:
    BudgetDisk.room, BudgetDisk.reserved = room, 0

    def open_file(p) -> BudgetDisk:
        opened[:] = [BudgetDisk(p, "wb")]
        return opened[0]

    async def drive() -> McapRecorder:
        v = Vehicle()
        v.add(Cam(), outputs=["cam/image_array", "n"])
        rec = McapRecorder(path, v, sync_every=4, fsync=False, open_file=open_file)
        v.add(rec)
        await v.run(rate_hz=20, max_loop_count=30)
        rec.shutdown()
        return rec

    # Time jumps at once (autojump_threshold=0): the writer is a daemon thread that answers the loop only to wake
    # it when its queue runs dry, and the loop holds time while the writer has records in hand; waiting the
    # default millisecond of real time before every jump, for an answer on its way, only made the test slower.
    with asyncio.Runner(loop_factory=lambda: VirtualClockLoop(autojump_threshold=0)) as runner:
        return runner.run(drive())


@pytest.mark.parametrize("reserve", ["fallocate", "no fallocate"])
def test_a_file_cut_by_a_full_disk_reads_to_a_clean_end_without_seeking(tmp_path, monkeypatch, caplog, reserve):
    opened: list[BudgetDisk] = []
    # blocks reserved on the budget disk, or a system or file system that cannot reserve any (the write finds out)
    monkeypatch.setattr(sink_module, "_FALLOCATE", budget_fallocate(opened) if reserve == "fallocate" else None)
    monkeypatch.setattr(background_writer, "_RETRY_MIN_S", 0.001)  # the pauses after errors: short, many drives
    caplog.set_level(logging.WARNING)
    path = tmp_path / "full.mcap"
    ends = set()
    for room in range(300, 20_000, 419):  # the disk fills at every kind of place: header, chunks, summary
        rec = record_onto(path, room, opened)
        s = rec.stats
        assert s.written + s.failed == 30 and os.path.getsize(path) <= room
        ns = []
        with open(path, "rb") as f:  # the mcap package's streaming reader, no seeking: to the end, no error
            for _, channel, message in NonSeekingReader(f).iter_messages(log_time_order=False):
                if channel.topic == "/n":
                    ns.append(json.loads(message.data)["value"])
        assert ns == list(range(1, s.written + 1))  # every tick counted as written, in order, and no other
        ends.add(s.written < 30)
    assert ends == {True, False}  # some drives lost their end to the full disk, some fitted
    assert " 0 queued records not written" not in caplog.text


@pytest.mark.realtime  # the writer thread's slow writes and shutdown's timeout are wall-clock time
def test_a_shutdown_that_lost_nothing_logs_no_error(tmp_path, caplog):
    """The writer thread is still closing the file when shutdown's timeout ends: nothing queued is lost, so
    there is no "0 queued records not written" error."""

    class SlowDisk(io.FileIO):
        def write(self, b) -> int:
            time.sleep(0.3)
            return super().write(b)

    caplog.set_level(logging.INFO)
    v = Vehicle()
    rec = McapRecorder(tmp_path / "slow.mcap", v, fsync=False, open_file=lambda p: SlowDisk(p, "wb"))
    for k in range(3):
        v.mem["n"] = k
        rec.run()
    rec.shutdown(timeout=0.05)
    rec._thread.join(10)
    assert not rec._thread.is_alive()
    errors = [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]
    assert errors == [] and "queued records not written" not in caplog.text
    assert "still closing the files" in caplog.text
    s = rec.stats
    assert (s.written, s.abandoned, s.failed) == (3, 0, 0)
    assert [m.value["value"] for m in read_mcap(tmp_path / "slow.mcap", {"/n"})] == [0, 1, 2]


# ------------------------------------------------------------------------------------ a value too big
@pytest.mark.asyncio
@pytest.mark.virtual_clock
@pytest.mark.asyncdonkey_checked(False)  # the value breaks user/angle's contract: what the recorder does with it
async def test_a_400_digit_angle_keeps_its_frame(tmp_path):
    class Camera:
        def __init__(self) -> None:
            self.k = 0

        def run(self):
            self.k += 1
            return frame(self.k), (10**400 if self.k == 2 else self.k / 10)

    v = Vehicle()
    v.add(Camera(), outputs=["cam/image_array", "user/angle"])
    path = tmp_path / "huge.mcap"
    rec = McapRecorder(path, v, fsync=False)
    v.add(rec)
    await v.run(rate_hz=20, max_loop_count=3)
    rec.shutdown()
    frames = list(read_mcap(path, {"/cam/image_array"}))
    overlays = list(read_mcap(path, {"/cam/image_array/steering"}))
    assert len(frames) == 3  # tick 2's frame too
    assert len(overlays) == 2  # no line for an angle no float holds; the others drawn
    assert [m.value["value"] for m in read_mcap(path, {"/user/angle"})] == [0.1, 10**400, 0.3]
    assert [len(r) > 0 for r in McapTub(path).records()] == [True] * 3
