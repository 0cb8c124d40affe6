"""Values read from files pass the channels' contracts: `replay` and `convert` refuse what breaks them.

A tub whose catalog lines were edited (a NaN throttle, a string angle, a 400-digit integer, a throttle of 1.5)
and whose image files were swapped (an RGBA frame, a 16-bit frame), and an MCAP file recorded with such values
(an angle of 2.0, a string throttle), are replayed on the virtual clock: the drive does not stop, the pilot sees
only good frames, every scored row has good user values, and the report counts what was refused per channel and
reason. `convert` leaves refused values out of the file it writes and says how many.
"""

from __future__ import annotations

import asyncio
import csv
import json
import logging
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from asyncdonkey import Contract, Contracts, Vehicle
from asyncdonkey.commands.cli import main as cli_main
from asyncdonkey.commands.convert import convert
from asyncdonkey.commands.replay import replay
from asyncdonkey.parts.mcap import McapRecorder
from asyncdonkey.parts.mcap.reader import McapTub, read_mcap
from asyncdonkey.parts.tub import Tub
from asyncdonkey.testing import VirtualClockLoop

from .test_replay import INPUTS, record_tub

HUGE = 10**400


class Pilot:
    """Steers straight; keeps every frame it is given (what reached Memory's camera channel)."""

    def __init__(self) -> None:
        self.frames: list[np.ndarray] = []

    def predict(self, image):
        self.frames.append(image)
        return 0.0, 0.0


def assert_only_good_values_were_played(report, pilot: Pilot) -> None:
    assert pilot.frames and all(f.dtype == np.uint8 and f.ndim == 3 and f.shape[2] == 3 for f in pilot.frames)
    for row in report.rows:
        for v in (row.user_angle, row.user_throttle):
            assert type(v) is float and math.isfinite(v) and -1.0 <= v <= 1.0


# ------------------------------------------------------------------------------------------------- tub
def edit_catalog(path: Path, edits: dict[int, dict[str, object]]) -> None:
    """Rewrite the catalog lines of the records in ``edits`` with those values (as a hand edit or a buggy
    writer would leave them; JSON's ``NaN`` is what Python's json writes for a NaN)."""
    catalog = path / "catalog_0.catalog"
    lines = catalog.read_text().split("\n")
    for index, values in edits.items():
        record = json.loads(lines[index])
        record.update(values)
        lines[index] = json.dumps(record)
    catalog.write_text("\n".join(lines))


@pytest.fixture
def bad_tub(tmp_path) -> Path:
    path = record_tub(tmp_path / "tub", ticks=16)  # records 0-15, 50 ms apart
    edit_catalog(
        path,
        {
            2: {"user/throttle": math.nan},
            4: {"user/angle": "0.66"},
            6: {"user/angle": HUGE},
            8: {"user/throttle": 1.5},
            10: {"cam/image_array": "10_cam_image_array_.png"},
            12: {"cam/image_array": "12_cam_image_array_.png"},
        },
    )
    images = path / "images"
    cv2.imwrite(str(images / "10_cam_image_array_.png"), np.zeros((120, 160, 4), np.uint8))  # RGBA: (120, 160, 4)
    cv2.imwrite(str(images / "12_cam_image_array_.png"), np.zeros((120, 160, 3), np.uint16))  # 16-bit
    return path


def test_a_tub_with_bad_values_replays_to_the_end_and_nothing_bad_reaches_the_drive(bad_tub, tmp_path, caplog):
    pilot = Pilot()
    with caplog.at_level(logging.WARNING, logger="asyncdonkey.contracts"):
        report = replay(bad_tub, pilot, csv_path=tmp_path / "rows.csv")
    # the drive went on to the last record: every good record was played and scored
    assert report.records == 10 and [r.index for r in report.rows] == [0, 1, 3, 5, 7, 9, 11, 13, 14, 15]
    assert report.skipped == {"refused": 6}
    assert report.refused == {
        "cam/image_array": {"dtype": 1, "shape": 1},
        "user/angle": {"range": 1, "type": 1},
        "user/throttle": {"nan": 1, "range": 1},
    }
    assert len(pilot.frames) == 10
    assert_only_good_values_were_played(report, pilot)
    # the refusals are logged (rate-limited per channel and reason), the huge integer shortened
    logged = [r.getMessage() for r in caplog.records]
    assert any("replay: refused a value for 'user/throttle': got NaN" in m for m in logged)
    assert any("too large for a float" in m and len(m) < 200 for m in logged)
    # and each refused record is in the CSV with what was refused, and in the table and the JSON
    with open(tmp_path / "rows.csv", newline="") as f:
        rows = {int(r["index"]): r["skipped"] for r in csv.DictReader(f)}
    assert rows[2] == "refused (user/throttle: nan)" and rows[4] == "refused (user/angle: type)"
    assert rows[10] == "refused (cam/image_array: shape)" and rows[12] == "refused (cam/image_array: dtype)"
    assert "refused          cam/image_array: dtype 1, shape 1; user/angle: range 1, type 1;" in report.format_table()
    assert json.loads(json.dumps(report.as_dict()))["refused"] == report.refused


def test_a_declared_contract_is_kept_in_replay_too(tmp_path):
    path = record_tub(tmp_path / "tub", ticks=10)
    angles = [r["user/angle"] for r in Tub(path)]
    gentle = Contract.number(-0.5, 0.5, safe=0.0)  # this car never steers harder than half
    report = replay(path, Pilot(), contracts={"user/angle": gentle})
    over = sum(abs(a) > 0.5 for a in angles)
    assert 0 < over < 10
    assert report.refused == {"user/angle": {"range": over}} and report.records == 10 - over


def test_a_huge_integer_where_no_contract_applies_is_skipped_not_raised(tmp_path):
    path = record_tub(tmp_path / "tub", ticks=6)
    edit_catalog(path, {1: {"_timestamp_ms": HUGE}, 3: {"user/angle": HUGE}})
    report = replay(path, Pilot(), contracts=Contracts(defaults=False))  # no contract on any channel
    assert report.skipped == {"no_timestamp": 1, "no_user_values": 1} and report.refused == {}
    assert [r.index for r in report.rows] == [0, 2, 4, 5]


def test_convert_leaves_out_what_breaks_a_contract_and_says_how_much(bad_tub, tmp_path, capsys):
    mcap = tmp_path / "out.mcap"
    assert cli_main(["convert", str(bad_tub), str(mcap)]) == 0
    printed = capsys.readouterr().out
    assert "16 records" in printed
    assert "refused 6 values that break their channel's contract" in printed
    assert "user/throttle: nan 1, range 1" in printed
    written: dict[str, list[object]] = {}
    for m in read_mcap(mcap):
        if m.topic in ("/user/angle", "/user/throttle"):
            written.setdefault(m.topic, []).append(m.value["value"])
    # the good values are all there, as recorded; none of the bad ones
    assert len(written["/user/angle"]) == 14 and len(written["/user/throttle"]) == 14
    for v in written["/user/angle"] + written["/user/throttle"]:
        assert type(v) is float and -1.0 <= v <= 1.0
    frames = sum(1 for m in read_mcap(mcap, {"/cam/image_array"}))
    assert frames == 14
    # and the MCAP file converts back to a tub that holds only good records
    back = tmp_path / "back"
    res = convert(mcap, back)
    assert res.refused == {} and res.records_left_out == 0
    assert res.records == 14 and len(Tub(back)) == 14


# ------------------------------------------------------------------------------------------------ MCAP
class BadDrive:
    """A car writing the given bad values at some ticks (unchecked: this is the buggy car being recorded)."""

    BAD = {
        3: ("user/throttle", "0.66"),
        5: ("user/throttle", 1.5),
        7: ("user/angle", 2.0),
        9: ("user/mode", "turbo"),
        11: ("user/throttle", HUGE),
    }

    def __init__(self) -> None:
        self.k = 0

    def run(self):
        self.k += 1
        k = self.k
        values = {
            "cam/image_array": np.full((120, 160, 3), (k * 9) % 256, np.uint8),
            "user/angle": 0.1 * (k % 5),
            "user/throttle": 0.25 + 0.0,
            "user/mode": "user",
        }
        bad = self.BAD.get(k)
        if bad is not None:
            values[bad[0]] = bad[1]
        return tuple(values[c] for c in (*INPUTS, "user/mode"))


@pytest.fixture
def bad_mcap(tmp_path) -> Path:
    path = tmp_path / "bad.mcap"

    async def drive() -> None:
        v = Vehicle(checked=False)  # it records what a buggy car wrote: checking would stop it at the first
        v.add(BadDrive(), outputs=[*INPUTS, "user/mode"])
        rec = McapRecorder(path, v, every_tick=True, timing=False, fsync=False)
        v.add(rec)
        await v.run(rate_hz=20, max_loop_count=14)
        rec.shutdown()

    with asyncio.Runner(loop_factory=VirtualClockLoop) as runner:
        runner.run(drive())
    return path


def test_an_mcap_file_with_bad_values_replays_to_the_end_and_nothing_bad_reaches_the_drive(bad_mcap):
    pilot = Pilot()
    report = replay(bad_mcap, pilot)
    assert len(list(McapTub(bad_mcap).records())) == 14
    assert report.records == 10 and [r.index for r in report.rows] == [0, 1, 3, 5, 7, 8, 9, 11, 12, 13]
    assert report.skipped == {"refused": 4}
    assert report.refused == {"user/angle": {"range": 1}, "user/throttle": {"range": 2, "type": 1}}
    assert_only_good_values_were_played(report, pilot)


def test_converting_an_mcap_file_with_bad_values_leaves_out_their_records(bad_mcap, tmp_path, capsys):
    out = tmp_path / "tub"
    assert cli_main(["convert", str(bad_mcap), str(out)]) == 0
    printed = capsys.readouterr().out
    assert "9 records" in printed and "5 records left out" in printed
    assert "user/mode: choice 1" in printed and "user/angle: range 1" in printed
    recs = list(Tub(out))
    assert len(recs) == 9
    for r in recs:
        assert r["cam/image_array"].shape == (120, 160, 3)
        assert type(r["user/throttle"]) is float and -1.0 <= r["user/throttle"] <= 1.0
        assert r["user/mode"] == "user"
