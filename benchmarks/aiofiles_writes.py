"""Recording's file writes: aiofiles on the event loop against the writer thread asyncdonkey uses.

Why asyncdonkey does not use aiofiles (docs/dependencies.md). aiofiles makes a file's blocking calls awaitable by
handing each one (open, write, close, flush) to the event loop's default executor: every call is a future, a
hop to a pool thread and a wake-up of the loop when it is done. A tub record is an image file (open, write,
close) and a catalog line (write): four hops per record. asyncdonkey's recorders instead append the record to a
queue on the tick and let one writer thread of their own do the plain writes (parts/background_writer.py).

Measured per record, the same bytes (a 160x120 JPEG of about 10 kB and a catalog line of about 200 bytes) into a
fresh directory on the same disk, ``N`` records:

* ``loop CPU``: CPU time the event loop's thread spends per record (``time.thread_time``), what a drive's ticks
  compete with;
* ``await``: for aiofiles, how long the coroutine that writes one record waits (mean and p99): a tick that
  awaited its writes would be this late;
* ``per call``: one ``write`` of 200 bytes to an open file, through aiofiles and directly.

Needs aiofiles (not a dependency): ``pip install aiofiles``, or ``pip install --target /tmp/aio aiofiles`` and
``PYTHONPATH=/tmp/aio``. Run: ``.venv/bin/python benchmarks/aiofiles_writes.py [--records N] [--uvloop]``.
"""

from __future__ import annotations

import argparse
import asyncio
import collections
import json
import statistics
import tempfile
import threading
import time
from pathlib import Path

import cv2
import numpy as np

try:
    import aiofiles
except ImportError as exc:  # pragma: no cover - a benchmark's own message
    raise SystemExit(f"aiofiles_writes.py: needs aiofiles ({exc}): pip install aiofiles") from exc


def record_bytes() -> tuple[bytes, bytes]:
    """A JPEG as the tub writes one (160x120, quality 75) and a catalog line of Donkeycar's form."""
    rng = np.random.default_rng(0)
    image = cv2.GaussianBlur(rng.integers(0, 255, (120, 160, 3), dtype=np.uint8), (5, 5), 0)
    ok, jpeg = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 75])
    assert ok
    line = {
        "_index": 123456,
        "_session_id": "25-01-01_0",
        "_timestamp_ms": 1735689600000,
        "cam/image_array": "123456_cam_image_array_.jpg",
        "user/angle": -0.123456,
        "user/throttle": 0.345678,
        "user/mode": "user",
    }
    return jpeg.tobytes(), (json.dumps(line) + "\n").encode()


async def aiofiles_records(root: Path, n: int, jpeg: bytes, line: bytes) -> tuple[float, list[float]]:
    """Each record awaited as aiofiles writes it: image open/write/close, catalog write. (loop CPU, awaits)."""
    waits: list[float] = []
    async with aiofiles.open(root / "catalog_0.catalog", "ab") as catalog:
        cpu0 = time.thread_time()
        for i in range(n):
            t0 = time.perf_counter()
            async with aiofiles.open(root / f"{i}_cam_image_array_.jpg", "wb") as f:
                await f.write(jpeg)
            await catalog.write(line)
            waits.append(time.perf_counter() - t0)
        cpu = time.thread_time() - cpu0
    return cpu, waits


async def writer_thread_records(root: Path, n: int, jpeg: bytes, line: bytes) -> tuple[float, float, float]:
    """Each record appended to a deque that a writer thread drains with plain writes. (loop CPU, thread CPU, wall)."""
    queue: collections.deque[int] = collections.deque()
    done = threading.Event()
    thread_cpu = [0.0]

    def writer() -> None:
        cpu0 = time.thread_time()
        written = 0
        with open(root / "catalog_0.catalog", "ab") as catalog:
            while written < n:
                if not queue:
                    time.sleep(0.005)  # the recorders poll: the tick never wakes the thread
                    continue
                i = queue.popleft()
                with open(root / f"{i}_cam_image_array_.jpg", "wb") as f:
                    f.write(jpeg)
                catalog.write(line)
                written += 1
        thread_cpu[0] = time.thread_time() - cpu0
        done.set()

    start = time.perf_counter()
    worker = threading.Thread(target=writer, name="writer")
    worker.start()
    cpu0 = time.thread_time()
    for i in range(n):
        queue.append(i)
        if i % 50 == 49:
            await asyncio.sleep(0)  # let the loop turn, as ticks do
    cpu = time.thread_time() - cpu0
    while not done.is_set():
        await asyncio.sleep(0.005)
    worker.join()
    return cpu, thread_cpu[0], time.perf_counter() - start


async def per_call(root: Path, line: bytes, calls: int) -> tuple[float, float]:
    """Mean seconds of one 200-byte write to an open file: through aiofiles, and directly."""
    async with aiofiles.open(root / "a.bin", "wb") as f:
        t0 = time.perf_counter()
        for _ in range(calls):
            await f.write(line)
        through = (time.perf_counter() - t0) / calls
    with open(root / "b.bin", "wb") as g:
        t0 = time.perf_counter()
        for _ in range(calls):
            g.write(line)
        direct = (time.perf_counter() - t0) / calls
    return through, direct


def us(seconds: float) -> str:
    return f"{seconds * 1e6:,.1f} µs"


async def main_async(n: int) -> None:
    jpeg, line = record_bytes()
    print(f"{n} records of {len(jpeg):,} B JPEG + {len(line)} B catalog line, loop: {type(asyncio.get_running_loop())}")
    with (
        tempfile.TemporaryDirectory(prefix="aiofiles-bench-", dir=".") as a,
        tempfile.TemporaryDirectory(prefix="writer-bench-", dir=".") as b,
    ):
        cpu, waits = await aiofiles_records(Path(a), n, jpeg, line)
        waits.sort()
        p99 = waits[int(0.99 * (len(waits) - 1))]
        print(
            f"aiofiles:      loop CPU {us(cpu / n)} per record; await mean {us(statistics.fmean(waits))}, "
            f"p99 {us(p99)}; {n / sum(waits):,.0f} records/s"
        )
        cpu, thread_cpu, wall = await writer_thread_records(Path(b), n, jpeg, line)
        print(
            f"writer thread: loop CPU {us(cpu / n)} per record; writer thread CPU {us(thread_cpu / n)} per record; "
            f"{n / wall:,.0f} records/s (5 ms polls included)"
        )
        through, direct = await per_call(Path(a), line, 4 * n)
        print(f"one 200 B write: aiofiles {us(through)}, direct {us(direct)} ({through / direct:,.0f}x)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--records", type=int, default=2000)
    ap.add_argument("--uvloop", action="store_true", help="run on uvloop, as asyncdonkey run does by default")
    args = ap.parse_args()
    if args.uvloop:
        import uvloop

        uvloop.run(main_async(args.records))
    else:
        asyncio.run(main_async(args.records))


if __name__ == "__main__":
    main()
