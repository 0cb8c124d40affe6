"""Damaged recordings: every command that reads one says what is wrong in one line naming the file, never with a
traceback, and still uses what can be read.

The files are small real recordings (a tub written by the project's tub writer, and that tub converted to MCAP
with one chunk per record), damaged by hypothesis (a flipped bit anywhere, or the file cut anywhere) and by
hand where the damage must hit one place (a chunk's data, a record's length, a schema). Each command runs
in-process through ``asyncdonkey``'s ``main()``, as from the shell: it must exit 0 or 2, and with 2 print exactly
one line, ``asyncdonkey <command>: error: ...``, naming the damaged file.
"""

from __future__ import annotations

import contextlib
import io
import json
import re
import shutil
import struct
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from asyncdonkey.commands.cli import main
from asyncdonkey.commands.convert import tub_to_mcap
from asyncdonkey.parts.mcap.reader import McapReadError, McapTub, mcap_info, read_mcap
from asyncdonkey.parts.mcap.sink import McapSink
from asyncdonkey.parts.tub import Tub, TubError
from asyncdonkey.parts.tub.appender import TubAppender

from .test_replay import write_model

pytest.importorskip("mcap")

RECORDS = 8
ROWS, COLS = 12, 16
FUZZ = settings(
    max_examples=10, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow]
)


# ------------------------------------------------------------------------------------------------ helpers
@pytest.fixture(scope="module")
def good(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``tub/`` (8 records of 12x16 frames), ``drive.mcap`` (the same, one chunk per record) and ``pilot.onnx``."""
    d = tmp_path_factory.mktemp("good")
    app = TubAppender(
        d / "tub", ["cam/image_array", "user/angle", "user/throttle"], ["image_array", "float", "float"], fsync=False
    )
    for i in range(RECORDS):
        app.write(1000.0 + i * 0.05, [np.full((ROWS, COLS, 3), 25 * i, np.uint8), 0.1 * i, 0.2])
    app.close()
    write = McapSink.write

    def write_and_end_the_chunk(self: McapSink, t: float, payload: tuple[Any, ...]) -> None:
        write(self, t, payload)
        self.sync()

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(McapSink, "write", write_and_end_the_chunk)
        tub_to_mcap(d / "tub", d / "drive.mcap")
    write_model(d / "pilot.onnx", ROWS, COLS)
    return d


def run(*argv: str | Path) -> tuple[int, str]:
    """``asyncdonkey ARGV`` in this process: its exit status and what it printed on stderr (stdout dropped)."""
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        status = main([str(a) for a in argv])
    return status, err.getvalue()


def assert_one_line_or_success(status: int, err: str, damaged: Path) -> None:
    """Exit 0 (the damage left it readable), or exit 2 with one line naming the damaged file."""
    assert status in (0, 2), (status, err)
    if status == 2:
        lines = err.strip().splitlines()
        assert len(lines) == 1, err
        assert re.match(r"asyncdonkey (replay|convert|report): error: ", lines[0]), lines[0]
        assert str(damaged) in lines[0], lines[0]


def all_commands(recording: Path, good: Path, out: Path) -> list[tuple[int, str]]:
    """replay, convert and report of ``recording``, each in its own fresh output place under ``out``."""
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir()
    target = out / ("converted" if recording.is_file() else "converted.mcap")
    return [
        run("replay", recording, "--pilot", good / "pilot.onnx"),
        run("convert", recording, target),
        run("report", recording, "-o", out / "report.html"),
    ]


def damage(data: bytes, kind: str, where: int) -> bytes:
    """``flip``: bit ``where`` inverted; ``cut``: only the first ``where`` bytes kept."""
    if kind == "cut":
        return data[:where]
    out = bytearray(data)
    out[where // 8] ^= 1 << (where % 8)
    return bytes(out)


def chunk_offsets(path: Path) -> list[tuple[int, int]]:
    """``(start, end)`` of each chunk record of an MCAP file, walking the records' opcode and length fields."""
    data = path.read_bytes()
    pos, out = 8, []
    while pos + 9 <= len(data):
        opcode, length = struct.unpack_from("<BQ", data, pos)
        if opcode == 0x06:  # Chunk
            out.append((pos, pos + 9 + length))
        if opcode == 0x02:  # Footer: then the magic
            break
        pos += 9 + length
    return out


def angles(path: Path) -> list[float]:
    return [rec.raw["user/angle"] for rec in McapTub(path).records()]


# -------------------------------------------------------------------------------------- generated damage
@FUZZ
@given(data=st.data(), kind=st.sampled_from(["flip", "cut"]))
def test_a_damaged_mcap_file_gives_one_line_or_what_can_be_read_in_every_command(good, tmp_path, data, kind):
    clean = (good / "drive.mcap").read_bytes()
    bits = len(clean) * 8 if kind == "flip" else len(clean)
    where = data.draw(st.integers(0, bits - 1), label="where")
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(damage(clean, kind, where))
    for status, err in all_commands(bad, good, tmp_path / "out"):
        assert_one_line_or_success(status, err, bad)


@FUZZ
@given(
    data=st.data(),
    name=st.sampled_from(["manifest.json", "catalog_0.catalog", "catalog_0.catalog_manifest"]),
    kind=st.sampled_from(["flip", "cut"]),
)
def test_a_damaged_tub_gives_one_line_or_what_can_be_read_in_every_command(good, tmp_path, data, name, kind):
    bad = tmp_path / "badtub"
    shutil.rmtree(bad, ignore_errors=True)
    shutil.copytree(good / "tub", bad)
    clean = (bad / name).read_bytes()
    bits = len(clean) * 8 if kind == "flip" else len(clean)
    (bad / name).write_bytes(damage(clean, kind, data.draw(st.integers(0, bits - 1), label="where")))
    for status, err in all_commands(bad, good, tmp_path / "out"):
        assert_one_line_or_success(status, err, bad)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data(), kind=st.sampled_from(["flip", "cut"]))
def test_what_a_damaged_mcap_file_gives_is_what_was_recorded_and_a_cut_keeps_every_whole_chunk(
    good, tmp_path, data, kind
):
    clean_path = good / "drive.mcap"
    clean = clean_path.read_bytes()
    recorded = {(r.raw["user/angle"], r.image_bytes("cam/image_array")) for r in McapTub(clean_path).records()}
    bits = len(clean) * 8 if kind == "flip" else len(clean)
    where = data.draw(st.integers(0, bits - 1), label="where")
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(damage(clean, kind, where))
    try:
        read = [(r.raw.get("user/angle"), r.image_bytes("cam/image_array")) for r in McapTub(bad).records()]
    except TubError as exc:  # McapReadError is one
        assert str(bad) in str(exc) and "\n" not in str(exc)
        return
    assert set(read) <= recorded  # chunks are CRC-checked: nothing damaged is passed on
    if kind == "cut":
        whole = sum(1 for _, end in chunk_offsets(clean_path) if end <= where)
        assert len(read) >= whole


# ------------------------------------------------------------------------------------------ named damage
def test_a_chunk_that_fails_its_crc_is_left_out_and_the_chunks_after_it_are_read(good, tmp_path, caplog):
    chunks = chunk_offsets(good / "drive.mcap")
    assert len(chunks) == RECORDS
    start, end = chunks[3]
    bad = tmp_path / "bad.mcap"
    data = bytearray((good / "drive.mcap").read_bytes())
    data[end - 5] ^= 0x10  # in the chunk's compressed records, not its framing
    bad.write_bytes(bytes(data))
    assert angles(bad) == pytest.approx([0.1 * i for i in range(RECORDS) if i != 3])
    info = mcap_info(bad)
    assert len(info.damage) == 1 and info.damage[0].startswith(f"byte {start}: chunk left out")
    assert f"damaged chunk at byte {start} left out" in caplog.text
    status, err = run("convert", bad, tmp_path / "tub")
    assert status == 0, err
    assert len(Tub(tmp_path / "tub")) == RECORDS - 1


def test_when_the_chunk_defining_the_channels_is_lost_the_summary_still_names_them(good, tmp_path):
    _, end = chunk_offsets(good / "drive.mcap")[0]
    bad = tmp_path / "bad.mcap"
    data = bytearray((good / "drive.mcap").read_bytes())
    data[end - 5] ^= 0x01
    bad.write_bytes(bytes(data))
    assert angles(bad) == pytest.approx([0.1 * i for i in range(1, RECORDS)])


def test_a_file_cut_inside_a_chunk_keeps_every_chunk_before_it(good, tmp_path):
    start, end = chunk_offsets(good / "drive.mcap")[5]
    bad = tmp_path / "bad.mcap"
    bad.write_bytes((good / "drive.mcap").read_bytes()[: (start + end) // 2])
    assert angles(bad) == pytest.approx([0.1 * i for i in range(5)])
    assert mcap_info(bad).recovered
    status, err = run("replay", bad, "--pilot", good / "pilot.onnx", "--json")
    assert status == 0, err


def test_a_record_length_past_the_end_of_the_file_is_never_allocated(good, tmp_path):
    start, _ = chunk_offsets(good / "drive.mcap")[2]
    data = bytearray((good / "drive.mcap").read_bytes())
    struct.pack_into("<Q", data, start + 1, 1 << 62)  # the chunk says it is 4 EiB long: a MemoryError before
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    assert angles(bad) == pytest.approx([0.0, 0.1])
    for status, err in all_commands(bad, good, tmp_path / "out"):
        assert_one_line_or_success(status, err, bad)


def test_a_schema_that_cannot_be_built_is_one_line_naming_the_file_the_topic_and_the_schema(good, tmp_path):
    from mcap.writer import Writer

    bad = tmp_path / "bad.mcap"
    with open(bad, "wb") as f:
        w = Writer(f)
        w.start()
        schema = w.register_schema("foxglove.CompressedImage", "protobuf", b"\xff\x01 not a descriptor set")
        image = w.register_channel("/cam/image_array", "protobuf", schema)
        number = w.register_schema("asyncdonkey.Number", "jsonschema", b"{}")
        for topic in ("/user/angle", "/user/throttle"):
            w.add_message(w.register_channel(topic, "json", number), 1, b'{"value": 0.5}', 1, sequence=1)
        w.add_message(image, log_time=1, publish_time=1, data=b"\x00", sequence=1)
        w.finish()
    with pytest.raises(McapReadError, match=r"bad\.mcap: the schema 'foxglove\.CompressedImage' of /cam/image_array"):
        list(read_mcap(bad))
    status, err = run("replay", bad, "--pilot", good / "pilot.onnx")
    assert status == 2 and err.count("\n") == 1 and "schema 'foxglove.CompressedImage'" in err and str(bad) in err
    status, err = run("convert", bad, tmp_path / "out")
    assert status == 2 and err.count("\n") == 1 and str(bad) in err
    assert not (tmp_path / "out").exists()  # no half-made tub left to pass for a conversion


def test_a_json_message_that_does_not_decode_is_left_out_and_the_rest_read(tmp_path):
    from mcap.writer import Writer

    bad = tmp_path / "bad.mcap"
    with open(bad, "wb") as f:
        w = Writer(f)
        w.start()
        schema = w.register_schema("asyncdonkey.Number", "jsonschema", b"{}")
        channel = w.register_channel("/user/angle", "json", schema)
        for i, data in enumerate([b'{"value": 0.5}', b'{"value": 0.', b'{"value": 0.7}']):
            w.add_message(channel, log_time=i, publish_time=i, data=data, sequence=i + 1)
        w.finish()
    assert [m.value["value"] for m in read_mcap(bad)] == [0.5, 0.7]


def test_a_catalog_line_with_its_keys_damaged_is_passed_over_by_position(good, tmp_path):
    bad = tmp_path / "tub"
    shutil.copytree(good / "tub", bad)
    lines = (bad / "catalog_0.catalog").read_text().splitlines(keepends=True)
    record = json.loads(lines[2])
    record["_indey"] = record.pop("_index")  # one flipped bit in a key
    lines[2] = json.dumps(record, sort_keys=True) + "\n"
    (bad / "catalog_0.catalog").write_text("".join(lines))
    assert [r.index for r in Tub(bad)] == list(range(RECORDS))  # the index is the position, as in Donkeycar
    status, err = run("replay", bad, "--pilot", good / "pilot.onnx")
    assert status == 0, err
