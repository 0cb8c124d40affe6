import numpy as np
import pytest

from asyncdonkey.core.profiler import Profiler, Series


def test_first_and_last_samples_ignored_like_donkeycar():
    s = Series("p")
    for v in [9.0, 0.001, 0.002, 0.003, 5.0]:
        s.record(v)
    summary = s.summary()
    assert summary["max"] == pytest.approx(3.0)
    assert summary["min"] == pytest.approx(1.0)
    assert summary["avg"] == pytest.approx(2.0)


def test_memory_is_bounded_by_the_window():
    s = Series("p", window=100)
    for i in range(10_001):
        s.record(i / 1000)
    assert len(s.recent(drop_last=False)) == 100
    assert s.recent(drop_last=False)[-1] == pytest.approx(10.0)
    assert len(s._buf) == 100
    summary = s.summary()
    assert summary["min"] == pytest.approx(0.001 * 1e3)  # run-long min survives the window
    assert summary["50%"] == pytest.approx(np.percentile(np.arange(9901, 10000) / 1000, 50) * 1e3)


def test_report_has_donkeycar_columns_and_loop_rows():
    p = Profiler(window=64)
    s = p.series_for("PWMSteering")
    for v in (0.001, 0.002, 0.003, 0.004):
        s.record(v)
    p.lateness.record(0.0001)
    p.overrun.record(0.0)
    p.tick.record(0.005)
    text = p.table([("achieved", "20.000 Hz")])
    header = [c.strip() for c in text.splitlines()[2].split("|") if c.strip()]
    assert header == ["part", "max", "min", "avg", "50%", "90%", "99%", "99.9%"]
    assert "PWMSteering" in text and "[tick lateness]" in text and "achieved: 20.000 Hz" in text
    d = p.as_dict()
    assert d["parts"]["PWMSteering"]["max"] == pytest.approx(3.0)
    assert d["loop"]["lateness"]["max"] == pytest.approx(0.1)


def test_at_reads_samples_by_number_while_they_are_in_the_window():
    s = Series("x", window=4)
    s.record(99.0)  # the skipped first sample is not numbered
    for v in (1.0, 2.0, 3.0, 4.0, 5.0, 6.0):
        s.record(v)
    assert s.count == 6
    assert [s.at(n) for n in range(6)] == [None, None, 3.0, 4.0, 5.0, 6.0]  # 0 and 1 left the window
    assert s.at(6) is None and s.at(-1) is None  # not recorded yet / no such sample
