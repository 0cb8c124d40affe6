"""TubWriter: every type round-trips, the tick never waits for the disk, drops and failures are counted,
sync points and manifests follow the documented policy, sessions append, and it runs inside a Vehicle on the
virtual clock."""

from __future__ import annotations

import errno
import json
import os
import re
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from asyncdonkey import Vehicle
from asyncdonkey.parts.tub import Tub, TubFileIO, TubFormatError, TubWiper, TubWriter

from ..waiting import wait_until

ALL_INPUTS = ["cam/image_array", "user/angle", "user/throttle", "user/mode", "rec", "n", "arr", "lst", "vec", "depth"]
ALL_TYPES = ["image_array", "float", "float", "str", "boolean", "int", "nparray", "list", "vector", "gray16_array"]
BASIC_INPUTS = ["cam/image_array", "user/angle", "user/throttle", "user/mode"]
BASIC_TYPES = ["image_array", "float", "float", "str"]


def scene(k: int) -> np.ndarray:
    """A smooth 120x160 RGB test image (JPEG keeps it within a few levels), different for each k."""
    yy, xx = np.mgrid[0:120, 0:160]
    r = (xx * 1.5 + k * 7) % 256
    g = (yy * 2.0 + k * 3) % 256
    b = np.full_like(r, (40 + 10 * k) % 256)
    return np.dstack([r, g, b]).astype(np.uint8)


def manifest_lines(path: Path) -> list:
    return [json.loads(line) for line in (path / "manifest.json").read_text().splitlines()]


# ------------------------------------------------------------------------------------------ round trip
def test_every_type_round_trips(tmp_path):
    w = TubWriter(tmp_path / "tub", ALL_INPUTS, ALL_TYPES, metadata=["driver:ann", "at:12:30"])
    sent = []
    for i in range(5):
        depth = (np.arange(12 * 16, dtype=np.uint16).reshape(12, 16) * 300 + i).astype(np.uint16)
        values = (scene(i), 0.25 * i - 0.5, np.float32(0.5), "user", bool(i % 2), np.int64(i), np.arange(3.0) + i,
                  [i, "x"], (1.5, np.float32(2.5)), depth)  # fmt: skip
        assert w.run(*values) == i  # the records in the tub (Donkeycar's current_index); this one is only queued
        assert w.flush(5)
        sent.append(values)
    w.shutdown()
    assert w.stats.written == 5 and w.stats.durable == 5 and w.stats.bad_values == 0

    tub = Tub(tmp_path / "tub")
    assert tub.inputs == ALL_INPUTS and tub.types == ALL_TYPES
    assert tub.metadata == {"driver": "ann", "at": "12:30"}  # split on the first ':' only
    records = list(tub)
    assert len(records) == len(tub) == 5
    session = records[0]["_session_id"]
    assert re.fullmatch(r"\d\d-\d\d-\d\d_0", session)
    assert tub.sessions == [session]
    now_ms = time.time() * 1000
    for i, (rec, values) in enumerate(zip(records, sent, strict=True)):
        assert rec["_index"] == i and rec["_session_id"] == session
        assert now_ms - 60_000 < rec["_timestamp_ms"] <= now_ms
        img = rec["cam/image_array"]
        assert img.dtype == np.uint8 and img.shape == (120, 160, 3)
        assert np.abs(img.astype(int) - values[0]).mean() < 3  # RGB order kept (a BGR swap would be ~100)
        assert rec.raw["cam/image_array"] == f"{i}_cam_image_array_.jpg"
        assert rec["user/angle"] == pytest.approx(0.25 * i - 0.5)
        assert rec["user/throttle"] == 0.5 and type(rec["user/throttle"]) is float
        assert rec["user/mode"] == "user"
        assert rec["rec"] is bool(i % 2)
        assert rec["n"] == i and type(rec["n"]) is int
        assert rec["arr"] == [0.0 + i, 1.0 + i, 2.0 + i]
        assert rec["lst"] == [i, "x"]
        assert rec["vec"] == [1.5, 2.5]
        assert rec.raw["depth"] == f"{i}_depth_.png"
        np.testing.assert_array_equal(rec["depth"], values[9])  # 16-bit PNG is lossless
        assert rec["depth"].dtype == np.uint16
    stamps = [r["_timestamp_ms"] for r in records]
    assert stamps == sorted(stamps)


def test_grey_uint8_image_and_none_values(tmp_path):
    w = TubWriter(tmp_path / "t", ["cam/image_array", "user/angle"], ["image_array", "float"])
    grey = scene(1)[:, :, 0].copy()
    w.run(grey, None)  # None is left out of the record, like Donkeycar
    w.run(None, 0.5)  # e.g. no camera frame yet
    w.shutdown()
    a, b = list(Tub(tmp_path / "t"))
    assert "user/angle" not in a and a["cam/image_array"].shape == (120, 160)
    assert np.abs(a["cam/image_array"].astype(int) - grey).mean() < 3
    assert "cam/image_array" not in b and b["user/angle"] == 0.5
    assert w.stats.bad_values == 0


def test_bad_values_are_left_out_counted_and_logged_and_the_record_kept(tmp_path, caplog):
    w = TubWriter(tmp_path / "t", [*BASIC_INPUTS, "arr"], [*BASIC_TYPES, "nparray"])
    w.run(scene(0).astype(np.float32), float("nan"), "fast", 3, np.array([1.0, np.inf]))
    w.run(scene(1), 0.1, 0.2, "user", np.array([1, 2]))
    w.shutdown()
    first, second = list(Tub(tmp_path / "t"))
    assert set(first.raw) == {"_index", "_session_id", "_timestamp_ms"}  # every value refused, record kept
    assert second["user/mode"] == "user" and second["arr"] == [1, 2]
    assert w.stats.bad_values == 5
    text = caplog.text
    assert "'cam/image_array'" in text and "uint8" in text
    assert "'user/angle'" in text and "finite" in text
    assert "'user/mode'" in text and "expected str" in text


def test_schema_errors_are_clear(tmp_path):
    with pytest.raises(ValueError, match=r"'speed' has unknown type 'double'"):
        TubWriter(tmp_path / "a", ["speed"], ["double"])
    with pytest.raises(ValueError, match="2 inputs but 1 types"):
        TubWriter(tmp_path / "b", ["a", "b"], ["float"])
    with pytest.raises(ValueError, match="reserved"):
        TubWriter(tmp_path / "c", ["_index"], ["int"])
    with pytest.raises(ValueError, match="share file names"):
        TubWriter(tmp_path / "d", ["cam/image", "cam_image"], ["image_array", "image_array"])
    with pytest.raises(ValueError, match="queue_size"):
        TubWriter(tmp_path / "e", ["a"], ["float"], queue_size=0)
    w = TubWriter(tmp_path / "f", ["a", "b"], ["float", "float"])
    with pytest.raises(TypeError, match=r"expected 2 values for \['a', 'b'\], got 1"):
        w.run(1.0)
    w.shutdown()
    with pytest.raises(RuntimeError, match="after shutdown"):
        w.run(1.0, 2.0)


# --------------------------------------------------------------------------------------- format details
def test_catalogs_roll_over_and_manifests_match_donkeycar_layout(tmp_path):
    w = TubWriter(tmp_path / "t", ["user/angle"], ["float"], max_catalog_len=4)
    for i in range(10):
        w.run(i / 10)
    w.shutdown()
    root = tmp_path / "t"
    inputs, types, meta, mmeta, cat = manifest_lines(root)
    assert (inputs, types, meta) == (["user/angle"], ["float"], {})
    assert cat == {
        "paths": ["catalog_0.catalog", "catalog_1.catalog", "catalog_2.catalog"],
        "current_index": 10,
        "max_len": 4,
        "deleted_indexes": [],
    }
    assert isinstance(mmeta["created_at"], float)
    assert mmeta["sessions"]["last_id"] == 0 and len(mmeta["sessions"]["all_full_ids"]) == 1
    for n, (start, count) in enumerate([(0, 4), (4, 4), (8, 2)]):
        lines = (root / f"catalog_{n}.catalog").read_text().splitlines(keepends=True)
        assert len(lines) == count
        assert [json.loads(x)["_index"] for x in lines] == list(range(start, start + count))
        assert all(list(json.loads(x)) == sorted(json.loads(x)) for x in lines)  # keys sorted
        cm = json.loads((root / f"catalog_{n}.catalog_manifest").read_text())
        assert cm["path"] == f"catalog_{n}.catalog_manifest" and cm["start_index"] == start
        assert cm["line_lengths"] == [len(x) for x in lines]
    assert not list(root.glob("*.tmp"))


class CountingDisk(TubFileIO):
    """A real disk that remembers the order of the operations that matter for durability."""

    def __init__(self, has_syncfs: bool = True) -> None:
        self.has_syncfs = has_syncfs
        self.ops: list[tuple[str, str]] = []
        self._names: dict[int, str] = {}

    def write_file(self, path, data):
        self.ops.append(("write", os.path.basename(path)))
        super().write_file(path, data)

    def open_append(self, path):
        fd = super().open_append(path)
        self._names[fd] = os.path.basename(path)
        return fd

    def append(self, fd, data):
        self.ops.append(("append", self._names[fd]))
        super().append(fd, data)

    def replace(self, src, dst):
        self.ops.append(("replace", os.path.basename(dst)))
        super().replace(src, dst)

    def sync_file(self, fd):
        self.ops.append(("sync", self._names[fd]))
        super().sync_file(fd)

    def sync_path(self, path):
        self.ops.append(("sync", os.path.basename(path)))
        super().sync_path(path)

    def sync_dir(self, path):
        self.ops.append(("syncdir", os.path.basename(path)))
        super().sync_dir(path)

    def sync_filesystem(self, fd):
        self.ops.append(("syncfs", self._names[fd]))
        super().sync_filesystem(fd)


def test_manifests_are_rewritten_at_sync_points_not_per_record(tmp_path):
    disk = CountingDisk()
    w = TubWriter(tmp_path / "t", BASIC_INPUTS, BASIC_TYPES, sync_every=25, sync_interval_s=60, file_io=disk)
    for i in range(100):
        w.run(scene(i % 5), 0.0, 0.0, "user")
    w.shutdown()
    replaces = [name for op, name in disk.ops if op == "replace" and name == "manifest.json"]
    assert 4 <= len(replaces) <= 6  # creation + one per 25 records (+ close), never one per record
    assert w.stats.syncs == 4 and w.stats.durable == 100


@pytest.mark.parametrize("has_syncfs", [True, False], ids=["syncfs", "per-file-fsync"])
def test_sync_point_flushes_data_before_the_manifests_name_it(tmp_path, has_syncfs):
    disk = CountingDisk(has_syncfs=has_syncfs)
    w = TubWriter(tmp_path / "t", BASIC_INPUTS, BASIC_TYPES, sync_every=3, sync_interval_s=60, file_io=disk)
    for i in range(3):
        w.run(scene(i), 0.0, 0.0, "user")
    assert w.flush(timeout=5)
    w.shutdown()
    ops = disk.ops
    # each record: its image is written before its catalog line
    for i in range(3):
        assert ops.index(("write", f"{i}_cam_image_array_.jpg")) < [k for k, o in enumerate(ops) if o[0] == "append"][i]
    last_append = max(k for k, o in enumerate(ops) if o[0] == "append")
    first_rename = min(k for k, o in enumerate(ops) if o == ("replace", "manifest.json") and k > last_append)
    between = ops[last_append:first_rename]
    if has_syncfs:
        assert ("syncfs", "catalog_0.catalog") in between
    else:
        for i in range(3):
            assert ("sync", f"{i}_cam_image_array_.jpg") in between
        assert ("sync", "catalog_0.catalog") in between and ("sync", "manifest.json.tmp") in between
    assert ("syncdir", "t") in ops[first_rename:]


@pytest.mark.realtime
def test_records_become_durable_within_the_sync_interval(tmp_path):
    w = TubWriter(tmp_path / "t", ["user/angle"], ["float"], sync_every=1000, sync_interval_s=0.05)
    w.run(0.5)
    wait_until(lambda: w.durable_index >= 1, 2.0, "the first record durable", step=0.005)
    assert w.durable_index == 1
    assert w.stats.durable_lag_max_ms < 1000
    w.shutdown()


def test_a_second_session_appends_with_the_next_session_id(tmp_path):
    root = tmp_path / "t"
    w = TubWriter(root, ["user/angle"], ["float"], metadata=["car:one"], max_catalog_len=3)
    for i in range(4):
        w.run(float(i))
    w.shutdown()
    w2 = TubWriter(root, metadata={"track": "home"})  # no inputs: append with the stored ones
    assert w2.inputs == ["user/angle"] and w2.session_id.endswith("_1")
    assert w2.run(9.0) == 4  # the records in the tub: the first session's; this one is only queued
    w2.shutdown()
    tub = Tub(root)
    recs = list(tub)
    assert [r["_index"] for r in recs] == [0, 1, 2, 3, 4]
    assert [r["_session_id"][-2:] for r in recs] == ["_0"] * 4 + ["_1"]
    assert tub.sessions == [recs[0]["_session_id"], recs[4]["_session_id"]]
    assert tub.metadata == {"car": "one", "track": "home"}
    with pytest.raises(TubFormatError, match=r"manifest\.json.*stores inputs \['user/angle'\]"):
        TubWriter(root, ["user/throttle"], ["float"])


def test_a_session_without_records_leaves_the_sessions_alone(tmp_path):
    w = TubWriter(tmp_path / "t", ["a"], ["float"])
    w.shutdown()
    assert "sessions" not in manifest_lines(tmp_path / "t")[3]
    assert len(Tub(tmp_path / "t")) == 0


# ------------------------------------------------------------------------------------- the slow disk
class GatedDisk(TubFileIO):
    """A disk whose image writes block until the test opens the gate (a stalled SD card)."""

    def __init__(self) -> None:
        self.gate = threading.Event()

    def write_file(self, path, data):
        if path.endswith(".jpg"):
            self.gate.wait()
        super().write_file(path, data)


class SlowDisk(TubFileIO):
    """Every file write takes 200 ms."""

    def write_file(self, path, data):
        time.sleep(0.2)
        super().write_file(path, data)


@pytest.mark.realtime
def test_a_200ms_disk_stall_is_never_seen_in_run(tmp_path):
    w = TubWriter(tmp_path / "t", BASIC_INPUTS, BASIC_TYPES, file_io=SlowDisk(), queue_size=50, fsync=False)
    frames = [scene(k) for k in range(4)]
    calls = []
    t_end = time.monotonic() + 0.5  # 2-3 stalled writes happen meanwhile
    i = 0
    while time.monotonic() < t_end:
        t0 = time.perf_counter()
        w.run(frames[i % 4], 0.1, 0.2, "user")
        calls.append(time.perf_counter() - t0)
        i += 1
        time.sleep(0.01)
    assert w.stats.written < w.stats.accepted  # the disk really was behind while we measured
    # waiting for the disk would take the stall's 200 ms; a loaded 2-core machine can add tens of ms to any call
    assert max(calls) < 0.1, f"run() took {max(calls) * 1e3:.2f} ms during a 200 ms stall"
    assert float(np.median(calls)) < 0.001
    w.shutdown(timeout=0.1)  # do not wait for 40 slow writes: the rest is abandoned and counted
    s = w.stats
    assert s.abandoned > 0
    assert s.accepted - 1 <= s.written + s.failed + s.abandoned <= s.accepted  # one may be mid-write


@pytest.mark.realtime
def test_a_full_queue_drops_the_newest_and_counts_them(tmp_path):
    disk = GatedDisk()
    w = TubWriter(tmp_path / "t", BASIC_INPUTS, BASIC_TYPES, file_io=disk, queue_size=5)
    counts = []
    for i in range(20):
        t0 = time.perf_counter()
        counts.append(w.run(scene(i % 3), i / 100, 0.0, "user"))
        assert time.perf_counter() - t0 < 0.5  # waiting for the gated disk would never return
    s = w.stats
    # five wait in the queue, the rest were refused; a sixth got in if the writer thread took the first off the
    # queue (to block on the gated disk) while the records were offered, on a loaded machine as late as the last
    assert s.accepted in (5, 6) and s.dropped == 20 - s.accepted
    assert s.queue_high_water == 5
    assert counts[-1] == 0  # run() reports the records written: none yet, the disk is gated
    disk.gate.set()
    w.shutdown()
    s = w.stats
    assert s.written == s.accepted and s.abandoned == 0
    recs = list(Tub(tmp_path / "t"))
    assert [r["_index"] for r in recs] == list(range(s.accepted))  # no gaps: the drops never got an index
    angles = [r["user/angle"] for r in recs]
    assert angles[:5] == [i / 100 for i in range(5)]  # oldest kept, newest dropped
    # the sixth, if any: the record offered when the thread freed a place, the sixth or (loaded machine) a later one
    assert len(angles) == s.accepted and all(0.05 <= a < 0.2 for a in angles[5:])


@pytest.mark.realtime
def test_shutdown_gives_up_after_its_timeout_and_counts_what_was_abandoned(tmp_path, caplog):
    disk = GatedDisk()
    w = TubWriter(tmp_path / "t", BASIC_INPUTS, BASIC_TYPES, file_io=disk, queue_size=10)
    for _i in range(4):
        w.run(scene(0), 0.0, 0.0, "user")
    t0 = time.monotonic()
    w.shutdown(timeout=0.1)
    assert time.monotonic() - t0 < 1.5
    assert w.stats.abandoned >= 3
    assert "queued records not written" in caplog.text
    disk.gate.set()  # let the thread finish its record and close


class FullDisk(TubFileIO):
    """A disk that fills up: while ``full``, image writes fail and catalog appends write half and fail."""

    def __init__(self) -> None:
        self.full = False

    def write_file(self, path, data):
        if self.full and path.endswith(".jpg"):
            raise OSError(errno.ENOSPC, "No space left on device", path)
        super().write_file(path, data)

    def append(self, fd, data):
        if self.full:
            os.write(fd, data[: len(data) // 2])  # a short write, then the device is full
            raise OSError(errno.ENOSPC, "No space left on device")
        super().append(fd, data)


def test_a_full_disk_loses_records_counted_without_holes_or_torn_lines(tmp_path, caplog):
    disk = FullDisk()
    w = TubWriter(tmp_path / "t", ["user/angle", "cam/image_array"], ["float", "image_array"], file_io=disk)
    w.run(0.0, scene(0))
    assert w.flush(5)
    disk.full = True
    w.run(1.0, scene(1))  # image write fails
    w.run(2.0, None)  # no image: the catalog append fails half way
    w.flush(5)
    disk.full = False
    w.run(3.0, scene(3))
    w.shutdown()
    s = w.stats
    assert (s.written, s.failed) == (2, 2)
    assert "not written" in caplog.text and "No space left" in caplog.text
    tub = Tub(tmp_path / "t")
    assert tub.torn_lines == 0 and tub.corrupt_lines == 0
    recs = list(tub)
    assert [(r["_index"], r["user/angle"]) for r in recs] == [(0, 0.0), (1, 3.0)]
    assert np.abs(recs[1]["cam/image_array"].astype(int) - scene(3)).mean() < 3  # not the failed record's


# ------------------------------------------------------------------------------------ deleting, options
def test_writer_deletes_and_restores_in_order_with_records(tmp_path):
    w = TubWriter(tmp_path / "t", ["a"], ["int"])
    for i in range(10):
        w.run(i)
    w.delete_last_n_records(3)  # the last three handed over, even if still queued
    w.run(10)
    w.delete_records([0, 1])
    w.restore_records(1)
    w.shutdown()
    tub = Tub(tmp_path / "t")
    assert tub.deleted_indexes == {0, 7, 8, 9}
    assert [r["a"] for r in tub] == [1, 2, 3, 4, 5, 6, 10]
    assert len(tub) == 7


def test_tub_wiper_deletes_once_per_press(tmp_path):
    w = TubWriter(tmp_path / "t", ["a"], ["int"])
    wiper = TubWiper(w.tub, num_records=2)  # Donkeycar's spelling: TubWiper(tub_writer.tub, ...)
    presses = [False, False, True, True, True, False, False, True, False, False]
    for i, pressed in enumerate(presses):
        w.run(i)
        wiper.run(pressed)
    w.shutdown()
    assert wiper.wipes == 2
    assert Tub(tmp_path / "t").deleted_indexes == {1, 2, 6, 7}
    with pytest.raises(TypeError, match="delete_last_n_records"):
        TubWiper(object())


def test_copy_values_protects_against_producers_that_reuse_buffers(tmp_path):
    disk = GatedDisk()
    buf = scene(0)
    for copy, name in [(True, "copied"), (False, "shared")]:
        disk.gate.clear()
        w = TubWriter(tmp_path / name, ["cam/image_array"], ["image_array"], file_io=disk, copy_values=copy)
        w.run(buf)
        w.run(buf)  # queued behind the blocked write
        time.sleep(0.02)
        buf_before = buf.copy()
        buf[:] = 0  # the producer reuses its buffer in place
        disk.gate.set()
        w.shutdown()
        buf[:] = buf_before
        second = list(Tub(tmp_path / name))[1]["cam/image_array"]
        if copy:
            assert np.abs(second.astype(int) - scene(0)).mean() < 3
        else:
            assert second.max() < 5  # documented: without copies the writer sees the mutation


# ------------------------------------------------------------------------------------ in a Vehicle
class Counter:
    def __init__(self) -> None:
        self.i = 0

    def run(self):
        self.i += 1
        return scene(self.i % 7), self.i / 100, 0.3, "user", self.i % 10 < 5


@pytest.mark.asyncio
@pytest.mark.virtual_clock
@pytest.mark.asyncdonkey_checked(False)  # Counter numbers the records on user/angle, past 1.0
async def test_records_a_drive_on_the_virtual_clock_with_simulated_timestamps(tmp_path):
    v = Vehicle()
    v.add(Counter(), outputs=["cam/image_array", "user/angle", "user/throttle", "user/mode", "recording"])
    w = TubWriter(tmp_path / "t", BASIC_INPUTS, BASIC_TYPES)
    v.add(w, inputs=BASIC_INPUTS, outputs=["tub/num_records"], run_condition="recording", shutdown_timeout=10)
    v.add(TubWiper(w.tub, num_records=1), inputs=["user/wipe"])
    report = await v.run(rate_hz=20, max_loop_count=200)
    assert report is not None
    assert v.mem["tub/num_records"] == 99  # written when the 100th was handed over (written just after)
    s = w.stats
    assert (s.written, s.durable, s.dropped) == (100, 100, 0)
    recs = list(Tub(tmp_path / "t"))
    assert len(recs) == 100
    stamps = np.array([r["_timestamp_ms"] for r in recs])
    gaps = np.diff(stamps)
    # ticks i with i % 10 < 5 record (1-4, 10-14, ..., 200): 50 ms apart on the virtual clock, 300 ms over a gap
    assert set(np.unique(gaps)) <= {49, 50, 51, 299, 300, 301}
    assert stamps[-1] - stamps[0] == pytest.approx((200 - 1) * 50, abs=2)
    assert [r["user/angle"] for r in recs[:5]] == [0.01, 0.02, 0.03, 0.04, 0.1]


@pytest.mark.asyncio
@pytest.mark.virtual_clock
@pytest.mark.asyncdonkey_checked(False)  # Counter numbers the records on user/angle, past 1.0
async def test_on_the_virtual_clock_the_disk_takes_no_time_and_nothing_is_dropped(tmp_path):
    """Virtual time jumps 50 ms per tick in microseconds of real time; the writer thread holds it while it
    has records in hand, so a fast simulated drive records every frame even with a small queue."""
    v = Vehicle()
    v.add(Counter(), outputs=["cam/image_array", "user/angle", "user/throttle", "user/mode", "recording"])
    w = TubWriter(tmp_path / "t", BASIC_INPUTS, BASIC_TYPES, queue_size=2, fsync=False)
    v.add(w, inputs=BASIC_INPUTS, outputs=["tub/num_records"])
    report = await v.run(rate_hz=20, max_loop_count=300)
    assert report.loops == 300
    assert (w.stats.written, w.stats.dropped) == (300, 0)
    assert len(list(Tub(tmp_path / "t"))) == 300
