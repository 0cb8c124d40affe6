"""Crash safety: a writer killed at any moment leaves a tub that Donkeycar's reader and ours open, holding
every record that was reported durable; torn last lines never make a tub unreadable; reopening repairs.

Two kinds of kill:

* ``test_killed_at_every_file_operation``: a forked child drives a :class:`TubAppender` (the writer thread's
  file layer, synchronous so the sequence of file operations is deterministic) and SIGKILLs itself at file
  operation k, for every k of a run (creation, image writes, catalog appends, sync points, a catalog
  roll-over, a deletion), once cleanly between operations and once half way through a write (a torn line,
  a torn image, a torn temporary manifest).
* ``test_sigkill_mid_recording``: the real threaded :class:`TubWriter` in a subprocess, killed with SIGKILL
  while recording flat out.
"""

from __future__ import annotations

import contextlib
import functools
import io
import json
import os
import shutil
import signal
import struct
import subprocess
import sys
import textwrap
import time
import warnings
from pathlib import Path

import numpy as np
import pytest

from asyncdonkey.parts.tub import Tub, TubFileIO, TubNotFoundError, TubWriter, repair_tub
from asyncdonkey.parts.tub.appender import TubAppender

pytestmark = [pytest.mark.donkeycar]

with contextlib.redirect_stdout(io.StringIO()):
    from donkeycar.parts.tub_v2 import Tub as DkTub

INPUTS = ["cam/image_array", "user/angle", "user/mode"]
TYPES = ["image_array", "float", "str"]


@functools.cache
def scene(k: int) -> np.ndarray:
    yy, xx = np.mgrid[0:120, 0:160]
    return np.dstack([(xx + 9 * k) % 256, (yy * 2) % 256, np.full_like(xx, 25 * k % 256)]).astype(np.uint8)


def dk_indexes(path: Path, read_only: bool) -> tuple[int, list[int]]:
    tub = DkTub(str(path), read_only=read_only)
    try:
        return len(tub), [r["_index"] for r in tub]
    finally:
        tub.close()


def check_crashed_tub(root: Path, durable: int, deleted_durable: bool, scratch: Path) -> None:
    """Both readers open the tub and hold every durable record; after repair they agree exactly."""
    if not (root / "manifest.json").exists():  # killed while creating the tub, before its manifest
        assert durable == 0
        with pytest.raises(TubNotFoundError):
            Tub(root)
        TubAppender(root, INPUTS, TYPES).close()  # the writer can still create it
        assert len(Tub(root)) == 0
        return
    tub = Tub(root)
    present = [r.index for r in tub.records(include_deleted=True)]
    assert present == list(range(len(present)))  # no holes
    assert len(present) >= durable
    for r in tub.records(include_deleted=True):  # no line points at a missing or torn image
        assert np.abs(r["cam/image_array"].astype(int) - scene(r.index)).mean() < 3
        assert r["user/angle"] == r.index / 10
    if deleted_durable:
        assert 1 in tub.deleted_indexes
    # the manifests never claim more than the catalogs hold, and never less than what was made durable
    catalog_meta = json.loads((root / "manifest.json").read_text().splitlines()[4])
    assert durable <= catalog_meta["current_index"] <= len(present)
    for cm_path in root.glob("*.catalog_manifest"):
        lengths = json.loads(cm_path.read_text())["line_lengths"]
        lines = (root / cm_path.name.replace("_manifest", "")).read_bytes().split(b"\n")[:-1]
        assert lengths == [len(x) + 1 for x in lines][: len(lengths)]  # complete lines only
    wanted = set(range(durable)) - set(tub.deleted_indexes)
    # Donkeycar's reader. Its read-only mode memory-maps each catalog and cannot open an empty one; like a
    # fresh Donkeycar tub, ours has one only while it holds no records. Its read-write mode may create files,
    # so it reads a copy.
    if (root / "catalog_0.catalog").stat().st_size == 0:
        assert durable == 0
    else:
        _, idx = dk_indexes(root, read_only=True)
        assert wanted <= set(idx)
    copy = scratch / "copy"
    shutil.rmtree(copy, ignore_errors=True)
    shutil.copytree(root, copy)
    _, idx = dk_indexes(copy, read_only=False)
    assert wanted <= set(idx)
    report = repair_tub(root)
    assert report.records == len(present)
    tub = Tub(root)
    assert tub.torn_lines == 0 and not tub.unlisted_catalogs
    if (root / "catalog_0.catalog").stat().st_size:
        n, idx = dk_indexes(root, read_only=True)
        assert n == len(tub) and idx == tub.indexes()


class CrashingDisk(TubFileIO):
    """Counts file operations and SIGKILLs the process at operation ``kill_at`` (half way through it if
    ``torn`` and it writes data). ``kill_at = -1`` never kills; ``ops`` then tells how many there were."""

    def __init__(self, kill_at: int, torn: bool) -> None:
        self.kill_at = kill_at
        self.torn = torn
        self.ops = 0
        self.writes: list[int] = []  # the operations that write data (where a kill can tear something)

    def _op(self, fd: int | None = None, data: bytes | None = None) -> None:
        if data is not None:
            self.writes.append(self.ops)
        if self.ops == self.kill_at:
            if self.torn and fd is not None and data is not None:
                os.write(fd, data[: max(1, len(data) // 2)])
            os.kill(os.getpid(), signal.SIGKILL)
        self.ops += 1

    def write_file(self, path, data):
        if self.ops == self.kill_at and self.torn:
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
            self._op(fd, data)
        self._op(None, data)
        super().write_file(path, data)

    def append(self, fd, data):
        self._op(fd, data)
        super().append(fd, data)

    def open_append(self, path):
        self._op()
        return super().open_append(path)

    def replace(self, src, dst):
        self._op()
        super().replace(src, dst)

    def truncate(self, fd, size):
        self._op()
        super().truncate(fd, size)

    def sync_filesystem(self, fd):
        self._op()
        super().sync_filesystem(fd)

    def sync_dir(self, path):
        self._op()
        super().sync_dir(path)


def record_session(root: Path, disk: CrashingDisk, report_fd: int) -> None:
    """The scripted session: 10 records, catalogs of 4, a sync point every 3 records, a deletion."""
    app = TubAppender(root, INPUTS, TYPES, max_catalog_len=4, file_io=disk)
    deleted = 0
    for i in range(10):
        app.write(time.time(), (scene(i), i / 10, "user"))
        if i % 3 == 2:
            app.sync()
            os.write(report_fd, struct.pack("<ii", app.durable, deleted))
        if i == 6:
            app.delete([1])
            app.sync()
            deleted = 1
            os.write(report_fd, struct.pack("<ii", app.durable, deleted))
    app.close()
    os.write(report_fd, struct.pack("<ii", app.durable, deleted))


def run_forked(root: Path, kill_at: int, torn: bool) -> tuple[int, int, int]:
    """Run the session in a forked child; returns (-signal or exit code, durable, deleted_durable) where the
    last two are what the child had reported when it died."""
    r, w = os.pipe()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)  # fork with threads: the child only uses its own
        pid = os.fork()
    if pid == 0:  # pragma: no cover - child
        code = 0
        try:
            os.close(r)
            record_session(root, CrashingDisk(kill_at, torn), w)
        except BaseException:
            code = 3
        finally:
            os._exit(code)
    os.close(w)
    _, status = os.waitpid(pid, 0)
    reports = b""
    while chunk := os.read(r, 4096):
        reports += chunk
    os.close(r)
    durable, deleted = struct.unpack("<ii", reports[-8:]) if reports else (0, 0)
    outcome = -os.WTERMSIG(status) if os.WIFSIGNALED(status) else os.WEXITSTATUS(status)
    return outcome, durable, deleted


@pytest.mark.subprocess
@pytest.mark.skipif(not hasattr(os, "fork"), reason="needs os.fork (POSIX)")
def test_killed_at_every_file_operation(tmp_path):
    clean = CrashingDisk(-1, torn=False)
    with open(os.devnull, "wb") as sink:
        record_session(tmp_path / "clean", clean, sink.fileno())
    total_ops = clean.ops
    assert 40 < total_ops < 120 and len(clean.writes) > 20
    check_crashed_tub(tmp_path / "clean", 10, True, tmp_path)
    points = [(k, False) for k in range(total_ops)] + [(k, True) for k in sorted(set(clean.writes))]
    for k, torn in points:
        root = tmp_path / f"k{k}_{torn}"
        outcome, durable, deleted = run_forked(root, k, torn)
        assert outcome == -signal.SIGKILL, f"op {k}: child ended with {outcome}"
        try:
            check_crashed_tub(root, durable, bool(deleted), tmp_path)
        except AssertionError as exc:
            raise AssertionError(f"killed at file operation {k} (torn={torn}), durable={durable}: {exc}") from exc
        shutil.rmtree(root)


CHILD = textwrap.dedent(
    """
    import sys, time
    import numpy as np
    from asyncdonkey.parts.tub import TubWriter

    root, seed = sys.argv[1], int(sys.argv[2])
    yy, xx = np.mgrid[0:120, 0:160]
    frames = [np.dstack([(xx + 9 * k) % 256, (yy * 2) % 256, np.full_like(xx, 25 * k % 256)]).astype(np.uint8)
              for k in range(8)]
    w = TubWriter(root, ["cam/image_array", "user/angle", "user/mode"], ["image_array", "float", "str"],
                  max_catalog_len=40, sync_every=9, sync_interval_s=0.02, queue_size=100000)
    last = -1
    i = 0
    while True:
        w.run(frames[i % 8], i / 10, "user")
        i += 1
        if i % 4 == 0:
            time.sleep(0.001)
        d = w.durable_index
        if d != last:
            print(d, flush=True)
            last = d
    """
)


@pytest.mark.realtime
@pytest.mark.subprocess
@pytest.mark.parametrize("kill_after", [45, 83, 130])
def test_sigkill_mid_recording(tmp_path, kill_after):
    root = tmp_path / "tub"
    proc = subprocess.Popen(
        [sys.executable, "-c", CHILD, str(root), str(kill_after)], stdout=subprocess.PIPE, text=True
    )
    durable = 0
    deadline = time.monotonic() + 30
    try:
        assert proc.stdout is not None
        for line in proc.stdout:
            durable = int(line)
            if durable >= kill_after or time.monotonic() > deadline:
                break
        time.sleep(0.001 * (kill_after % 7))  # land somewhere inside the next write or sync point
        proc.send_signal(signal.SIGKILL)
    finally:
        proc.kill()
        proc.wait()
    assert durable >= kill_after, "the child never reported enough durable records"
    tub = Tub(root)
    indexes = [r.index for r in tub]
    assert indexes == list(range(len(indexes))) and len(indexes) >= durable
    n_ro, dk_ro = dk_indexes(root, read_only=True)
    assert set(range(durable)) <= set(dk_ro)
    assert n_ro >= durable  # Donkeycar's len() comes from manifest.json, at least the last sync point
    for r in list(tub)[: durable : max(1, durable // 10)]:
        assert np.abs(r["cam/image_array"].astype(int) - scene(r.index % 8)).mean() < 3
    # appending again repairs first: afterwards both readers agree exactly
    w = TubWriter(root)
    w.run(scene(0), 99.0, "user")
    w.shutdown()
    tub = Tub(root)
    n, idx = dk_indexes(root, read_only=True)
    assert n == len(tub) and idx == tub.indexes() == list(range(len(indexes) + 1))


def test_torn_last_lines_in_any_catalog_never_make_a_tub_unreadable(tmp_path):
    root = tmp_path / "tub"
    w = TubWriter(root, INPUTS, TYPES, max_catalog_len=5)
    for i in range(12):
        w.run(scene(i), i / 10, "user")
    w.shutdown()
    with open(root / "catalog_2.catalog", "ab") as f:
        f.write(b'{"_index": 12, "_session_id": "x", "cam/image_array": "12_cam_im')
    with open(root / "catalog_0.catalog", "ab") as f:  # even where a later catalog follows
        f.write(b"\x00\x00\x00")
    tub = Tub(root)
    assert tub.torn_lines == 2 and tub.indexes() == list(range(12))
    for read_only in (True, False):
        _, idx = dk_indexes(root, read_only)
        assert idx[:5] == list(range(5)) and set(idx) == set(range(12))
    report = repair_tub(root)
    assert report.torn_bytes_removed > 60 and report.records == 12
    n, idx = dk_indexes(root, read_only=True)
    assert n == 12 and idx == list(range(12))


def test_reopening_adopts_a_catalog_the_writer_had_not_listed(tmp_path):
    root = tmp_path / "tub"
    app = TubAppender(root, INPUTS, TYPES, max_catalog_len=3)
    for i in range(5):  # records 3 and 4 go to catalog_1, which only the next sync point would list
        app.write(time.time(), (scene(i), i / 10, "user"))
    assert app.sync_requested  # the writer thread would sync now; pretend the process died instead
    listed = json.loads((root / "manifest.json").read_text().splitlines()[4])["paths"]
    assert listed == ["catalog_0.catalog"]
    assert Tub(root).indexes() == [0, 1, 2, 3, 4]  # our reader finds them anyway
    assert dk_indexes(root, read_only=True)[1] == [0, 1, 2]  # Donkeycar sees the durable ones
    report = repair_tub(root)
    assert report.adopted_catalogs == ["catalog_1.catalog"] and report.records == 5
    assert dk_indexes(root, read_only=True) == (5, [0, 1, 2, 3, 4])
