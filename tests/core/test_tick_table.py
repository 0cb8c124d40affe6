"""The tick's timing table: rows written in place, figures worked out when a report asks."""

from __future__ import annotations

import math

import numpy as np
import pytest

from asyncdonkey import Vehicle
from asyncdonkey.core.profiler import TableSeries, TickTable

NAN = math.nan


def write(table: TickTable, deadline: float, start: float, ends: list[float], end: float) -> None:
    """One tick's row, as the drive writes it."""
    pos = table.offset(table.rows)
    table.begun = table.rows + 1
    for i, v in enumerate([deadline, start, *ends, end]):
        table.buf[pos + i] = v
    table.commit()


def series(table: TickTable) -> tuple[TableSeries, TableSeries, TableSeries, TableSeries, TableSeries]:
    a = TableSeries("a", table, 0, skip_first=True)
    b = TableSeries("b", table, 1, skip_first=True)
    late = TableSeries("lateness", table, TickTable.LATENESS, skip_first=False, running=True)
    dur = TableSeries("duration", table, TickTable.TICK, skip_first=False)
    over = TableSeries("overrun", table, TickTable.OVERRUN, skip_first=False)
    return a, b, late, dur, over


def test_durations_lateness_and_overrun_follow_from_the_rows():
    t = TickTable(2, period=0.1, window=64)
    write(t, 0.0, 0.001, [0.003, 0.006], 0.007)
    write(t, 0.1, 0.102, [NAN, 0.105], 0.25)  # part a skipped: b starts when the tick did
    a, b, late, dur, over = series(t)
    v = t.values(0, 2)
    assert v[0, :2] == pytest.approx([0.002, 0.003])
    assert math.isnan(v[1, 0]) and v[1, 1] == pytest.approx(0.003)
    assert [late.at(0), late.at(1)] == [pytest.approx(0.001), pytest.approx(0.002)]
    assert [dur.at(0), dur.at(1)] == [pytest.approx(0.006), pytest.approx(0.148)]
    assert over.at(0) == 0.0 and over.at(1) == pytest.approx(0.048)
    assert a.at(0) is None  # tick 1 skipped a (its sample 0)
    assert b.at(0) == pytest.approx(0.003)
    assert a.count == b.count == 1 and late.count == 2


def test_first_tick_left_out_and_newest_dropped_from_part_reports():
    t = TickTable(1, period=1.0, window=64)
    for k, d in enumerate([9.0, 1.0, 2.0, 3.0, 100.0]):  # 9: the first tick, 100: the newest
        write(t, k * 10.0, k * 10.0, [k * 10.0 + d], k * 10.0 + d)
    a, *_rest = series(t)
    s = a.summary()
    assert s["max"] == pytest.approx(3e3) and s["min"] == pytest.approx(1e3) and s["avg"] == pytest.approx(2e3)
    assert s["count"] == 4  # as a Series counts: the first left out, the newest included
    assert list(a.recent(drop_last=False)) == [1.0, 2.0, 3.0, 100.0]


def test_run_long_extremes_survive_the_window():
    t = TickTable(1, period=1.0, window=8)
    durations = [0.5, 7.0, 0.01, *([1.0] * 30)]
    for k, d in enumerate(durations):
        write(t, float(k), float(k), [k + d], k + d)
    a, _b, late, dur, over = series(t)
    recent = a.recent(drop_last=False)
    assert len(recent) < 8 and set(recent) == {1.0}  # the window holds only the newest ticks
    s = a.summary()
    assert s["max"] == pytest.approx(7e3) and s["min"] == pytest.approx(10.0)  # from ticks long overwritten
    assert dur.summary()["max"] == pytest.approx(7e3) and over.summary()["max"] == pytest.approx(6e3)
    assert a.at(0) is None  # left the window
    assert late.count == len(durations)


def test_lateness_of_the_running_tick_is_readable_before_it_ends():
    t = TickTable(1, period=1.0, window=8)
    write(t, 0.0, 0.25, [0.5], 0.5)
    pos = t.offset(1)
    t.buf[pos], t.buf[pos + 1] = 1.0, 1.125  # tick 1 has begun, not ended
    t.begun = 2
    *_parts, late, dur, _over = series(t)
    assert late.count == 2 and late.at(1) == pytest.approx(0.125)
    assert dur.count == 1 and dur.at(1) is None


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_a_drive_reports_a_skipped_part_as_missing_samples_not_zeros():
    class Toggle:
        def __init__(self):
            self.n = 0

        def run(self):
            self.n += 1
            return self.n % 2 == 0

    class Slow:
        def __init__(self):
            self.calls = 0

        def run(self):
            self.calls += 1

    v = Vehicle()
    v.add(Toggle(), outputs=["go"])
    slow = Slow()
    v.add(slow, run_condition="go")
    report = await v.run(20, 10)
    assert slow.calls == 5
    col = v.profiler.parts["Slow"]
    samples = [col.at(n) for n in range(col.count)]
    assert sum(s is not None for s in samples) == 5  # ticks 1..9, every other one ran the part
    assert report.parts["Slow"]["count"] == 5
    assert report.lateness_ms["max"] == 0.0  # the virtual clock is never late
    assert np.all(v.profiler.tick.recent(drop_last=False) >= 0)
