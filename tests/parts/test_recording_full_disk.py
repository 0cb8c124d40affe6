"""Recording onto a disk that fills up, frees again and fills once more before shutdown, with both writers.

What must hold: the writer thread does not spin while the disk is full (it backs off, its CPU time during the
full period stays a small fraction of the period), it records again once space is back, and the counts are
the truth: ``stats.written`` equals the records the readers find in the files (the ``mcap`` package's own
reader for MCAP, Donkeycar's and ours for the tub), what was lost is counted as failed or dropped, and the
tub's ``tub/num_records`` never counts a record that is not on disk.

The full disk is a real one where the test may mount a small tmpfs (root): the kernel answers ``ENOSPC``.
Elsewhere, and always as a second run, the writers' own OS-call seams (``TubFileIO``, ``open_file``) make a
short write and raise ``OSError(ENOSPC)`` while the disk is "full".
"""

from __future__ import annotations

import contextlib
import errno
import io
import json
import logging
import os
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import foxglove.messages  # noqa: F401 - imported now, not by the writer thread during the measured period
import numpy as np
import pytest
from mcap.exceptions import EndOfFile
from mcap.reader import NonSeekingReader, make_reader

from asyncdonkey.loop import Vehicle
from asyncdonkey.parts.mcap import McapRecorder
from asyncdonkey.parts.mcap.reader import read_mcap
from asyncdonkey.parts.tub import Tub, TubFileIO, TubWriter

pytestmark = [pytest.mark.realtime]

with contextlib.redirect_stdout(io.StringIO()):  # Donkeycar prints a banner on import
    from donkeycar.parts.tub_v2 import Tub as DkTub

DISK_BYTES = 4 * 1024 * 1024
RATE_HZ = 20
# ticks (20 Hz): recording on a disk with room, full for 1 s, freed for 1.4 s (longer than the longest pause
# between attempts, 1 s), then full again until shutdown
FILL_AT, FREE_AT, REFILL_AT, TICKS = 8, 28, 56, 62
#: The writer thread's CPU time over the full period, as a share of the period. A spinning thread takes
#: close to all of it (~100% of a core); a bounded retry a few milliseconds in all. 20% leaves room for a
#: loaded 2-core machine.
MAX_CPU_SHARE = 0.2


def frame(k: int) -> np.ndarray:
    yy, xx = np.mgrid[0:120, 0:160]
    return np.dstack([(xx + 9 * k) % 256, (yy * 2) % 256, np.full_like(xx, 25 * k % 256)]).astype(np.uint8)


def thread_cpu(thread: threading.Thread) -> float:
    """CPU seconds the thread has used so far (its own clock, not the process's)."""
    assert thread.ident is not None
    return time.clock_gettime(time.pthread_getcpuclockid(thread.ident))


# ---------------------------------------------------------------------------------------------- the disk
class SmallDisk:
    """A small disk a test fills to the last page and frees again.

    ``tmpfs``: a real tmpfs of ``DISK_BYTES``; ``fill()`` writes a ballast file until the kernel answers
    ``ENOSPC``, ``free()`` deletes it. ``injected``: while full, every write through the writers' seams
    writes half its bytes and raises ``OSError(ENOSPC)``, as a device that fills mid-write does.
    """

    def __init__(self, root: Path, kind: str) -> None:
        self.root = root
        self.kind = kind
        self.full = False
        self._ballast = root / ".ballast"

    @property
    def real(self) -> bool:
        return self.kind == "tmpfs"

    def fill(self) -> None:
        self.full = True
        if not self.real:
            return
        fd = os.open(self._ballast, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
        try:
            for size in (1 << 20, 1 << 12, 1):
                block = b"\0" * size
                with contextlib.suppress(OSError):
                    while os.write(fd, block) == size:
                        pass
        finally:
            os.close(fd)
        assert os.statvfs(self.root).f_bavail == 0

    def free(self) -> None:
        self.full = False
        if self.real:
            self._ballast.unlink()

    def tub_io(self) -> TubFileIO | None:
        return None if self.real else _InjectedTubIO(self)

    def open_file(self):
        if self.real:
            return None
        return lambda path: _InjectedFile(self, path)


def _enospc() -> OSError:
    return OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


class _InjectedTubIO(TubFileIO):
    def __init__(self, disk: SmallDisk) -> None:
        self.disk = disk

    def _write_all(self, fd: int, data: bytes) -> None:
        if self.disk.full:
            os.write(fd, bytes(data[: len(data) // 2]))
            raise _enospc()
        super()._write_all(fd, data)


class _InjectedFile(io.FileIO):
    def __init__(self, disk: SmallDisk, path: str) -> None:
        super().__init__(path, "wb")
        self.disk = disk

    def write(self, b) -> int:
        if self.disk.full:
            super().write(bytes(b)[: len(b) // 2])
            raise _enospc()
        return super().write(b)


def _can_mount() -> bool:
    return sys.platform.startswith("linux") and os.geteuid() == 0 and shutil.which("mount") is not None


@pytest.fixture(params=[pytest.param("tmpfs", marks=pytest.mark.subprocess), "injected"])  # (mount and umount)
def disk(request, tmp_path):
    root = tmp_path / "disk"
    root.mkdir()
    if request.param == "injected":
        yield SmallDisk(root, "injected")
        return
    if not _can_mount():
        pytest.skip("mounting a tmpfs needs root on Linux; the injected run covers the writers")
    cmd = ["mount", "-t", "tmpfs", "-o", f"size={DISK_BYTES}", "tmpfs", str(root)]
    done = subprocess.run(cmd, capture_output=True, text=True)
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here ({done.stderr.strip()}); the injected run covers the writers")
    try:
        yield SmallDisk(root, "tmpfs")
    finally:
        subprocess.run(["umount", "-l", str(root)], capture_output=True)


# ---------------------------------------------------------------------------------------------- MCAP
def official_reader_values(path: Path) -> tuple[list[int], bool]:
    """The ``/n`` values the ``mcap`` package's streaming reader yields, and whether it reached a clean end
    (True) or stopped at a file cut short (``EndOfFile``)."""
    values = []
    with open(path, "rb") as f:
        try:
            for _, channel, message in NonSeekingReader(f).iter_messages(log_time_order=False):
                if channel.topic == "/n":
                    values.append(json.loads(message.data)["value"])
        except EndOfFile:
            return values, False
    return values, True


@pytest.mark.asyncio
async def test_mcap_backs_off_on_a_full_disk_resumes_and_counts_what_is_in_the_file(disk, caplog):
    caplog.set_level(logging.WARNING)
    path = disk.root / "drive.mcap"
    seen: dict[str, float] = {}

    class Cam:
        def __init__(self) -> None:
            self.k = 0

        def run(self):
            self.k += 1
            return frame(self.k), self.k

    class Disk:
        """Fills and frees the disk at given ticks and reads the writer thread's CPU clock at each."""

        def __init__(self) -> None:
            self.k = 0

        def run(self) -> None:
            self.k += 1
            if self.k in (FILL_AT, REFILL_AT):
                disk.fill()
                seen[f"cpu{self.k}"], seen[f"t{self.k}"] = thread_cpu(rec._thread), time.monotonic()
            elif self.k == FREE_AT:
                seen["cpu_free"], seen["t_free"] = thread_cpu(rec._thread), time.monotonic()
                disk.free()

    v = Vehicle()
    v.add(Cam(), outputs=["cam/image_array", "n"])
    v.add(Disk())
    rec = McapRecorder(path, v, channels=["cam/image_array", "n"], sync_interval_s=0.2, open_file=disk.open_file())
    v.add(rec)
    await v.run(rate_hz=RATE_HZ, max_loop_count=TICKS)
    rec.shutdown()

    full_s = seen["t_free"] - seen[f"t{FILL_AT}"]
    cpu_s = seen["cpu_free"] - seen[f"cpu{FILL_AT}"]
    print(f"mcap on {disk.kind}: writer thread CPU {cpu_s * 1e3:.1f} ms in {full_s:.2f} s of full disk; {rec.stats}")
    assert cpu_s < MAX_CPU_SHARE * full_s, f"writer thread used {cpu_s:.3f} s of CPU in {full_s:.3f} s of full disk"

    s = rec.stats
    assert s.accepted + s.dropped == TICKS
    assert s.written + s.failed + s.abandoned == s.accepted
    values, clean_end = official_reader_values(path)
    assert len(values) == s.written  # counted as written = in the file, read back by the mcap package
    assert values == sorted(set(values))  # in order, each once
    assert any(FREE_AT < n <= REFILL_AT for n in values), "nothing recorded after the disk had room again"
    assert s.failed > 0  # the ticks of the last full period never reached the file, and say so
    assert [m.value["value"] for m in read_mcap(path, {"/n"})] == values  # our reader agrees
    if disk.real:
        # the end reserved at each sync point lets the file end cleanly even on a full disk
        assert clean_end
        with open(path, "rb") as f:
            plain = [m for _, ch, m in make_reader(f).iter_messages() if ch.topic == "/n"]
        assert len(plain) == s.written
    warnings = [r for r in caplog.records if r.levelno >= logging.WARNING and "McapRecorder" in r.getMessage()]
    assert any(str(path) in r.getMessage() and "No space left" in r.getMessage() for r in warnings)
    assert len(warnings) <= 12, [r.getMessage() for r in warnings]  # rate-limited, not one per attempt


# ---------------------------------------------------------------------------------------------- tub
def dk_iterated(path: Path) -> list[dict]:
    tub = DkTub(str(path), read_only=True)
    try:
        return list(tub)
    finally:
        tub.close()


@pytest.mark.donkeycar
def test_tub_num_records_counts_only_records_on_disk_and_recording_resumes(disk, caplog):
    caplog.set_level(logging.WARNING)
    root = disk.root / "tub"
    w = TubWriter(root, ["cam/image_array", "n"], ["image_array", "int"], sync_interval_s=0.2, file_io=disk.tub_io())
    reported: list[int] = []
    mark: dict[str, float] = {}
    start = time.monotonic()
    for k in range(1, TICKS + 1):
        if k == FILL_AT:
            mark["cpu0"], mark["t0"] = thread_cpu(w._thread), time.monotonic()
            disk.fill()
        elif k == FREE_AT:
            mark["cpu1"], mark["t1"] = thread_cpu(w._thread), time.monotonic()
            disk.free()
            assert w.flush(10), "the tub never became writable again"
            on_disk = len(Tub(root))
            assert w.run(frame(0), 0) == on_disk  # tub/num_records as the car publishes it
            reported.append(on_disk)
        elif k == REFILL_AT:
            disk.fill()
        reported.append(w.run(frame(k), k))
        time.sleep(max(0.0, start + k / RATE_HZ - time.monotonic()))
    w.shutdown()

    cpu_s, full_s = mark["cpu1"] - mark["cpu0"], mark["t1"] - mark["t0"]
    print(f"tub on {disk.kind}: writer thread CPU {cpu_s * 1e3:.1f} ms in {full_s:.2f} s of full disk; {w.stats}")
    assert cpu_s < MAX_CPU_SHARE * full_s, f"writer thread used {cpu_s:.3f} s of CPU in {full_s:.3f} s of full disk"

    s = w.stats
    ours = list(Tub(root))
    theirs = dk_iterated(root)
    assert s.written == len(ours) == len(theirs)
    assert s.written + s.failed + s.dropped + s.abandoned == TICKS + 1
    assert s.failed > 0
    assert reported == sorted(reported) and max(reported) <= s.written  # never a failed record
    assert [r["_index"] for r in ours] == list(range(len(ours)))  # no holes
    assert [r["n"] for r in theirs] == [r["n"] for r in ours]
    assert any(FREE_AT < r["n"] <= REFILL_AT for r in ours), "nothing recorded after the disk had room again"
    for r in ours[-3:]:
        assert np.abs(r["cam/image_array"].astype(int) - frame(r["n"])).mean() < 3  # its own image, whole
    warnings = [r for r in caplog.records if r.levelno >= logging.WARNING and "TubWriter" in r.getMessage()]
    assert any(str(root) in r.getMessage() and "No space left" in r.getMessage() for r in warnings)
    assert len(warnings) <= 12, [r.getMessage() for r in warnings]
