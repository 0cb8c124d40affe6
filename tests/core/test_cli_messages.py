"""What a new user reads from the commands: help for every option, path errors that say what the path is,
unknown ``run`` options explained, ``--mcap`` into a new folder, and why a timed drive stopped."""

from __future__ import annotations

import argparse
import asyncio
import subprocess
import sys

import pytest

from asyncdonkey.commands import cli
from asyncdonkey.parts.mcap.reader import mcap_info
from asyncdonkey.testing import VirtualClockLoop

from ..examples.example_loader import EXAMPLES, load_example

CLI = [sys.executable, "-m", "asyncdonkey.commands"]
CAR = str(EXAMPLES / "car.py")
MODEL = str(EXAMPLES / "models" / "sim_pilot.onnx")
COMMANDS = ("run", "replay", "report", "convert", "quantize")


def subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return dict(action.choices)


def one_error_line(capsys) -> str:
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert "Traceback" not in err
    return lines[0]


# ------------------------------------------------------------------------------------------------- help
@pytest.mark.parametrize("command", COMMANDS)
def test_every_option_has_help(command):
    parser = subparsers(cli.build_parser())[command]
    missing = [
        a.option_strings or a.dest
        for a in parser._actions
        if not isinstance(a, argparse._HelpAction) and not (a.help and a.help.strip())
    ]
    assert missing == [], f"asyncdonkey {command}: options without help: {missing}"


def test_the_recording_arguments_name_both_formats():
    parsers = subparsers(cli.build_parser())
    for command, dest in (("replay", "tub"), ("report", "source"), ("convert", "source")):
        action = next(a for a in parsers[command]._actions if a.dest == dest)
        assert "tub directory" in action.help and ".mcap" in action.help, (command, action.help)
    tub = next(a for a in parsers["quantize"]._actions if a.dest == "tub")
    assert "tub directory" in tub.help


# ---------------------------------------------------------------------------------------------- paths
def test_a_missing_path_is_named_as_missing(tmp_path, capsys):
    nope = tmp_path / "data" / "nope.mcap"
    for argv in (
        ["report", str(nope)],
        ["replay", str(nope), "--pilot", MODEL],
        ["convert", str(nope), str(tmp_path / "out")],
        ["quantize", MODEL, "--tub", str(nope)],
    ):
        assert cli.main(argv) == 2, argv
        assert one_error_line(capsys) == f"asyncdonkey {argv[0]}: error: no such file or directory: {nope}", argv


def test_a_file_that_is_no_recording_is_named_as_such(tmp_path, capsys):
    notes = tmp_path / "notes.txt"
    notes.write_text("not a recording")
    for argv in (
        ["report", str(notes)],
        ["replay", str(notes), "--pilot", MODEL],
        ["convert", str(notes), str(tmp_path / "out")],
    ):
        assert cli.main(argv) == 2, argv
        expected = f"asyncdonkey {argv[0]}: error: {notes} is not a tub directory or an MCAP file"
        assert one_error_line(capsys) == expected, argv


def test_a_file_given_to_quantize_tub_is_named_as_a_file(tmp_path, capsys):
    notes = tmp_path / "drive.mcap"
    notes.write_bytes(b"\x89MCAP0\r\n")  # even a recording: --tub takes a tub directory
    assert cli.main(["quantize", MODEL, "--tub", str(notes)]) == 2
    assert one_error_line(capsys) == f"asyncdonkey quantize: error: {notes} is a file; --tub needs a tub directory"


def test_a_directory_that_is_no_tub_still_says_so(tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    assert cli.main(["report", str(tmp_path / "empty")]) == 2
    assert "not a tub" in one_error_line(capsys)


# ----------------------------------------------------------------------------------- unknown run options
def test_unknown_run_options_say_that_car_options_go_after_the_separator(monkeypatch, capsys):
    monkeypatch.delenv("MAKELEVEL", raising=False)
    assert cli.main(["run", CAR, "--seconds", "5"]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert lines[0] == "asyncdonkey run: error: unrecognized arguments: --seconds 5"
    assert f"asyncdonkey run {CAR} -- --seconds 5" in lines[1]
    assert not any("make run" in line for line in lines)
    own = lines[-1]
    for option in ("--hz HZ", "--max-loops N", "--duration S", "--verbose", "--no-uvloop", "--precise"):
        assert option in own, own
    listed = own.split(": ", 1)[1].split(" (see")[0].split(", ")
    assert listed == ["--hz HZ", "--max-loops N", "--duration S", "--verbose", "--no-uvloop", "--precise"]


def test_under_make_the_hint_is_the_make_command(monkeypatch, capsys):
    monkeypatch.setenv("MAKELEVEL", "1")  # what make sets for the commands it runs (make run ARGS=...)
    assert cli.main(["run", CAR, "--seconds", "5", "--laps", "2"]) == 2
    err = capsys.readouterr().err
    assert "unrecognized arguments: --seconds 5 --laps 2" in err
    assert 'make run ARGS="-- --seconds 5 --laps 2"' in err


def test_other_commands_name_themselves_in_the_unknown_argument_error(capsys):
    assert cli.main(["report", "x.mcap", "--bogus"]) == 2
    assert capsys.readouterr().err == (
        "asyncdonkey report: error: unrecognized arguments: --bogus (see asyncdonkey report --help)\n"
    )


# ------------------------------------------------------------------------------------ --mcap's folder
def test_mcap_recording_creates_its_folder(tmp_path):
    car_py = load_example("car")
    target = tmp_path / "runs" / "today" / "drive.mcap"
    v, _ = car_py.make_car(pilot="user", mcap=target, seconds=0.5, status=None)
    with asyncio.Runner(loop_factory=VirtualClockLoop) as runner:
        runner.run(v.run(rate_hz=20, max_loop_count=100))
    info = mcap_info(target)
    assert info.messages > 0 and not info.recovered  # a complete file, closed by the recorder


# -------------------------------------------------------------------------------- a timed drive's end
@pytest.mark.subprocess
def test_a_timed_quiet_drive_says_why_it_stopped_and_keeps_its_summary(tmp_path):
    target = tmp_path / "new" / "folder" / "drive.mcap"
    proc = subprocess.run(
        [*CLI, "run", CAR, "--", "--pilot", "user", "--seconds", "1", "--quiet", "--mcap", str(target)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    assert "stopped by: time limit reached (1 s)" in proc.stderr
    assert "drove 0 laps" in proc.stderr  # the summary: quiet drops the live line, not the result
    assert "lateness p99" not in proc.stderr  # ... and the live line is gone
    assert target.is_file()
