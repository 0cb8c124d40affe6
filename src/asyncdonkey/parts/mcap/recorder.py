"""``McapRecorder``: the whole drive (every channel, the loop's timing) to one MCAP file, off the loop thread.

Where the tub keeps what Donkeycar trains on, the MCAP file keeps everything the car knew: every Memory
channel (or a chosen list), each stamped with its origin, plus each tick's lateness and duration, each part's
time and each actuator's sensing-to-actuation latency. Open it in Foxglove, read it with the ``mcap``
package (:func:`~.reader.read_mcap`), replay it (``asyncdonkey replay run.mcap``), turn it into a tub
(``asyncdonkey convert``) or into a timing report (``asyncdonkey report``).

The tick's cost is close to the tub writer's: :meth:`McapRecorder.run` copies two small dicts (values and
origins: references, not the values), notes how far the profiler's timing series have got (the ended ticks'
count, plus one count per pipelined part and actuator: :class:`~.encode.TimingLayout`) and appends a tuple to
the queue of :class:`~asyncdonkey.parts.background_writer.BackgroundWriter` (bounded, drop newest, counted).
The writer thread reads the timing samples up to those counts from the profiler's ring buffers, each once
(so every part run, latency and tick of the drive is in the file, however far behind the writer is, or
counted as dropped if it left the ring first), encodes (JPEG, protobuf, JSON; :mod:`.encode`) and writes
chunks; a sync point ends the chunk at most ``sync_interval_s`` after a record (:mod:`.sink` for what a crash
or a full disk leaves). At shutdown the recorder adds the last tick's figures and the samples taken after its
last run.

Values must not be mutated after the tick that recorded them (the runtime's contract, as for the tub).
"""

from __future__ import annotations

import os
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from ...clock import get_clock
from ..background_writer import BackgroundWriter, WriterStats
from .encode import TickEncoder, TimeMap, TimingLayout
from .sink import McapSink

__all__ = ["McapRecorder", "RecorderStats", "TickRecorder"]


@dataclass(frozen=True)
class RecorderStats(WriterStats):
    """:class:`~asyncdonkey.parts.background_writer.WriterStats` plus the timing samples lost."""

    timing_dropped: int = 0
    """timing samples (part runs, latencies, ticks) that left the profiler's ring before the writer thread read
    them (it was more than the profiler's window behind): not in the file, also in each tick message."""


class TickRecorder(BackgroundWriter):
    """A part that hands each tick's Memory (and the loop's timing) to a sink on the writer thread.

    The sink has a ``times`` attribute that receives the :class:`~.encode.TimeMap` before the first tick is
    queued. Subclasses set ``self.vehicle`` and ``self._timing`` and call ``_start_writer(...,
    time_fn=self._first_time)``.
    """

    vehicle: Any
    _timing: bool
    _layout: TimingLayout | None = None

    def _first_time(self) -> float:
        """Anchor the runtime clock to the wall clock on the first record (the loop is known only then); on the
        virtual clock to a whole millisecond of it, as the tub writer does, so that simulated ticks keep their
        millisecond steps when read back."""
        try:
            clock = get_clock()
        except RuntimeError:  # called outside an event loop (a script driving run() itself)
            clock = None
        now = clock.now if clock is not None else time.monotonic
        virtual = clock is not None and clock.is_virtual
        t = now()
        wall_ns = time.time_ns()
        if virtual:
            wall_ns -= wall_ns % 1_000_000
        self._sink.times = TimeMap(t, wall_ns, "virtual" if virtual else "monotonic")
        self._now = self._on_virtual_time(now) if virtual else now
        return t

    # ------------------------------------------------------------------------------------ the tick
    def run(self) -> None:
        """Queue this tick's channels and timing for the writer thread; never blocks."""
        q = self._queue
        n = len(q)
        if n >= self._queue_size:
            if self._closed:
                raise RuntimeError(f"{self._label}: run() after shutdown()")
            self._dropped += 1
            return
        v = self.vehicle
        mem = v.mem
        t = self._now()
        if self._timing:
            # _timing_snapshot, inlined (the tick's cost): how far the timing series have got, counts only
            p = v.profiler
            layout = self._layout
            if layout is None or p is not layout.profiler or layout.size != len(p.parts) + len(p.latency):
                layout = self._layout = TimingLayout(p)
            table = layout.table
            rows = table.rows if table is not None else p.tick.count
            counted = layout.counted
            counts = [s.count for s in counted] if counted else ()
            drive = v.drive
            if drive is not None:
                snap = (t, dict(mem.d), dict(mem.origins), rows, layout, drive.overruns, drive.skipped, counts)
            else:
                snap = (t, dict(mem.d), dict(mem.origins), rows, layout, None, None, counts)
        else:
            snap = (t, dict(mem.d), dict(mem.origins), 0, None, None, None)
        q.append((t, time.monotonic(), snap))
        if n >= self._high_water:
            self._high_water = n + 1
        self._accepted += 1

    def _timing_snapshot(self, t: float, values: dict[str, Any], origins: dict[str, float]) -> tuple[Any, ...]:
        """A :class:`~.encode.TickSnapshot` with how far the drive's timing series have got now: counts only,
        the samples stay in the profiler's rings until the writer thread reads them (:meth:`run` does the same
        inline)."""
        v = self.vehicle
        layout = self._layout
        if layout is None or not layout.current(v.profiler):
            layout = self._layout = TimingLayout(v.profiler)
        rows, counts = layout.capture()
        drive = v.drive
        if drive is not None:
            return (t, values, origins, rows, layout, drive.overruns, drive.skipped, counts)
        return (t, values, origins, rows, layout, None, None, counts)


class McapRecorder(TickRecorder):
    """A drive-loop part that records the vehicle's Memory and timing to an MCAP file.

    ::

        rec = McapRecorder("data/drive.mcap", vehicle)
        vehicle.add(rec, name="mcap")          # last, so it records the values this tick wrote

    Args:
        path: the ``.mcap`` file (created; an existing file is replaced).
        vehicle: the :class:`~asyncdonkey.loop.Vehicle` whose ``mem`` and ``profiler`` are recorded.
        channels: Memory channels to record (default: all, including ones that appear later).
        every_tick: record every channel on every tick (default: a channel when its value or origin changed).
        kinds: ``{channel: "image" | "laserscan" | "json" | "skip"}`` to override the kind guessed from the
            first value (:mod:`.encode`).
        gps: (latitude, longitude) channels also published as ``foxglove.LocationFix`` on ``/gps/fix``.
        timing: record ``/asyncdonkey/tick``, ``/asyncdonkey/parts`` and ``/asyncdonkey/latency``.
        metadata: strings saved in the file's ``asyncdonkey.session`` metadata record.
        jpeg_quality: JPEG quality of images (75, as the tub writer).
        compression: chunk compression, ``"zstd"``, ``"lz4"`` or ``"none"``.
        queue_size, sync_interval_s, sync_every, fsync, drain_timeout_s: as :class:`~asyncdonkey.parts.tub.TubWriter`.
        open_file: opens the file for writing, unbuffered (tests simulate a full disk with it).

    ``run()`` takes no inputs (it reads ``vehicle.mem``) and returns nothing; :attr:`stats` has the counters
    (``written`` counts ticks; ``timing_dropped`` the timing samples the writer could no longer read).
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        vehicle: Any,
        channels: Sequence[str] | None = None,
        *,
        every_tick: bool = False,
        kinds: Mapping[str, str] | None = None,
        gps: tuple[str, str] | None = ("gps/latitude", "gps/longitude"),
        timing: bool = True,
        metadata: Mapping[str, Any] | None = None,
        jpeg_quality: int = 75,
        compression: str = "zstd",
        queue_size: int = 200,
        sync_interval_s: float = 1.0,
        sync_every: int = 100,
        fsync: bool = True,
        drain_timeout_s: float = 5.0,
        open_file: Any = None,
    ) -> None:
        where = f"McapRecorder({os.fspath(path)})"
        self._check_writer_args(where, queue_size, sync_every, sync_interval_s, drain_timeout_s)
        if not hasattr(vehicle, "mem"):
            raise TypeError(f"{where}: vehicle must be a Vehicle (with .mem and .profiler), got {vehicle!r}")
        self.path = os.fspath(path)
        self.vehicle = vehicle
        self.encoder = TickEncoder(channels, every_tick=every_tick, kinds=kinds, gps=gps, jpeg_quality=jpeg_quality)
        self._timing = timing
        self._sink = sink = McapSink(
            self.path,
            self.encoder,
            metadata={str(k): str(v) for k, v in (metadata or {}).items()},
            fsync=fsync,
            compression=compression,
            open_file=open_file,
        )
        self._start_writer(
            sink,
            where,
            queue_size=queue_size,
            sync_interval_s=sync_interval_s,
            sync_every=sync_every,
            drain_timeout_s=drain_timeout_s,
            time_fn=self._first_time,
        )

    def shutdown(self, timeout: float | None = None) -> None:
        """As :meth:`BackgroundWriter.shutdown`, after queueing the timing the ticks could not carry: the last
        tick's figures (a tick's are written when the next one records) and the samples taken since the last
        recorded tick, so the file holds every sample of the drive. Samples a pipelined part takes after this
        (a run still in flight while the car shuts down) are not in it."""
        drive = self.vehicle.drive
        if not self._closed and self._timing and drive is not None and self._sink.times is not None:
            self._command(self._sink.write_timing, self._timing_snapshot(drive.last_end, {}, {}))
        super().shutdown(timeout)

    close = shutdown

    @property
    def stats(self) -> RecorderStats:
        """The writer's counters (:class:`RecorderStats`), with the timing samples dropped."""
        base = super().stats
        return RecorderStats(**base.__dict__, timing_dropped=self.encoder.timing_dropped)

    def __repr__(self) -> str:
        return f"<McapRecorder {self.path}>"
