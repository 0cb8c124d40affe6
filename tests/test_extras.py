"""A missing extra: one line naming the feature, the extra and its install command, never a traceback.

The unit tests exercise :func:`asyncdonkey.extras.require`. The command tests run each command that needs an
extra in a subprocess where the extra's modules cannot be imported (a meta path finder placed first refuses
them, as an environment without the package does) and check the exit status, the one line and its command.
"""

from __future__ import annotations

import asyncio
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from asyncdonkey.errors import AsyncdonkeyError
from asyncdonkey.extras import EXTRA_OF_MODULE, MissingExtra, extra_for_module, install_command, require
from asyncdonkey.testing import VirtualClockLoop

from .examples.example_loader import EXAMPLES, load_example

ROOT = Path(__file__).resolve().parents[1]
MODELS = EXAMPLES / "models"

#: Runs the asyncdonkey command (or an example script, for an argument ending in .py) with the modules named
#: in argv[1] (comma-separated) impossible to import.
HIDING_RUNNER = textwrap.dedent(
    """
    import importlib.abc, runpy, sys

    hidden = sys.argv[1].split(",")

    class Hide(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path=None, target=None):
            if any(name == h or name.startswith(h + ".") for h in hidden):
                raise ModuleNotFoundError(f"No module named {name!r}", name=name)
            return None

    sys.meta_path.insert(0, Hide())
    args = sys.argv[2:]
    if args[0].endswith(".py"):
        sys.argv = args
        runpy.run_path(args[0], run_name="__main__")
    else:
        from asyncdonkey.commands import main

        sys.argv = ["asyncdonkey", *args]
        sys.exit(main())
    """
)


# ------------------------------------------------------------------------------------------------ require
def test_require_returns_the_module_when_it_is_there():
    assert require("json", "none", "a feature") is sys.modules["json"]
    # alternatives: the first one that imports
    assert require(("asyncdonkey_no_such_module", "json.decoder"), "x", "f") is sys.modules["json.decoder"]


def test_a_missing_module_is_one_line_with_the_install_command():
    with pytest.raises(MissingExtra) as info:
        require("asyncdonkey_no_such_module", "mcap", "reading MCAP recordings")
    exc = info.value
    text = str(exc)
    assert "\n" not in text
    assert text == (
        "reading MCAP recordings needs the mcap extra (asyncdonkey_no_such_module is not installed): "
        + install_command("mcap")
    )
    assert install_command("mcap").startswith(f"{sys.executable} -m pip install ")
    # catchable as what code around optional imports already catches, and as the project's own errors
    assert isinstance(exc, ImportError) and isinstance(exc, AsyncdonkeyError)
    assert (exc.feature, exc.extra, exc.module) == ("reading MCAP recordings", "mcap", "asyncdonkey_no_such_module")


def test_a_module_that_fails_on_a_missing_dependency_says_which(tmp_path, monkeypatch):
    """Installed but broken (its own dependency is missing): the message says what failed, not 'not installed'."""
    (tmp_path / "asyncdonkey_half_installed.py").write_text("import asyncdonkey_its_missing_dependency\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    with pytest.raises(MissingExtra, match=r"cannot be imported: No module named 'asyncdonkey_its_missing_dep"):
        require("asyncdonkey_half_installed", "zenoh", "the Zenoh link")


def test_none_of_the_alternatives_names_them_all(monkeypatch):
    monkeypatch.setitem(sys.modules, "asyncdonkey_alt_a", None)  # as if not installed
    with pytest.raises(MissingExtra) as info:
        require(("asyncdonkey_alt_a", "asyncdonkey_alt_b"), "tflite", "running .tflite pilots")
    assert "asyncdonkey_alt_a or asyncdonkey_alt_b" in str(info.value)
    assert str(info.value).endswith(install_command("tflite"))


def test_an_error_other_than_import_is_not_a_missing_extra(tmp_path, monkeypatch):
    (tmp_path / "asyncdonkey_broken_mod.py").write_text("raise RuntimeError('broken at import')\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    with pytest.raises(RuntimeError, match="broken at import"):
        require("asyncdonkey_broken_mod", "x", "f")


def test_the_module_map_names_the_extras_of_pyproject():
    import tomllib

    extras = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    assert set(EXTRA_OF_MODULE.values()) <= set(extras)
    assert extra_for_module("mcap.records") == "mcap"  # a submodule: its package's extra
    assert extra_for_module("google.protobuf.descriptor_pb2") == "mcap"
    assert extra_for_module("google") is None and extra_for_module("numpy") is None and extra_for_module(None) is None


@pytest.mark.subprocess
def test_the_helper_is_core_it_imports_no_parts_drivers_or_commands():
    code = (
        "import sys, asyncdonkey.extras\n"
        "print([m for m in sys.modules if m.startswith(('asyncdonkey.parts', 'asyncdonkey.hw', "
        "'asyncdonkey.testing', 'asyncdonkey.commands'))])"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"


# ----------------------------------------------------------------------------------------------- commands
@pytest.fixture(scope="module")
def recorded(tmp_path_factory) -> tuple[Path, Path]:
    """Two seconds of the simulated car on the virtual clock, recorded to a tub and to MCAP."""
    car_py = load_example("car")
    root = tmp_path_factory.mktemp("recorded")
    tub, mcap = root / "tub", root / "drive.mcap"
    v, _ = car_py.make_car(pilot="user", record=tub, mcap=mcap, seconds=2.0, status=None)
    with asyncio.Runner(loop_factory=VirtualClockLoop) as runner:
        runner.run(v.run(rate_hz=20, max_loop_count=1000))
    return tub, mcap


def run_hiding(modules: str, *args: object, cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-c", HIDING_RUNNER, modules, *map(str, args)],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=cwd,
    )


def assert_missing_extra(proc: subprocess.CompletedProcess[str], extra: str, *fragments: str) -> None:
    assert "Traceback" not in proc.stderr, proc.stderr
    assert proc.returncode == 2, (proc.returncode, proc.stdout, proc.stderr)
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert lines[0].endswith(install_command(extra)), lines[0]  # the child runs this interpreter and this copy
    for f in fragments:
        assert f in lines[0], lines[0]


CAR = str(EXAMPLES / "car.py")
TFLITE = "ai_edge_litert,tflite_runtime"


@pytest.mark.subprocess
@pytest.mark.parametrize(
    ("name", "hidden", "extra", "command", "says"),
    [
        ("replay mcap", "mcap", "mcap", ["replay", "{mcap}", "--pilot", MODELS / "sim_pilot.onnx"], "reading MCAP"),
        ("replay tflite", TFLITE, "tflite", ["replay", "{tub}", "--pilot", MODELS / "sim_pilot.tflite"], ".tflite"),
        ("report mcap", "mcap", "mcap", ["report", "{mcap}", "-o", "{tmp}/r.html"], "reading MCAP"),
        ("convert mcap->tub", "mcap", "mcap", ["convert", "{mcap}", "{tmp}/tub2"], "reading MCAP"),
        ("convert tub->mcap", "mcap", "mcap", ["convert", "{tub}", "{tmp}/t.mcap"], "recording MCAP"),
        ("quantize", "onnx", "quantize", ["quantize", MODELS / "sim_pilot.onnx", "--tub", "{tub}"], "quantize"),
        ("run --mcap", "mcap", "mcap", ["run", CAR, "--max-loops", "3", "--", "--mcap", "{tmp}/x.mcap"], "MCAP"),
        ("run foxglove", "foxglove", "mcap", ["run", CAR, "--max-loops", "3", "--", "--mcap", "{tmp}/x.mcap"], "MCAP"),
        (
            "run --pilot remote",
            "zenoh",
            "zenoh",
            ["run", CAR, "--", "--pilot", "remote", "--zenoh-listen", "tcp/127.0.0.1:7447"],
            "--pilot remote",
        ),
        ("top", "zenoh", "zenoh", ["top", "--once", "0.1"], "asyncdonkey top"),
        ("zenoh-pair", "cryptography", "zenoh", ["zenoh-pair", "{tmp}/pair"], "asyncdonkey zenoh-pair"),
        (
            "run .tflite pilot",
            TFLITE,
            "tflite",
            ["run", CAR, "--max-loops", "3", "--", "--pilot", MODELS / "sim_pilot.tflite"],
            "running .tflite pilots",
        ),
    ],
)
def test_each_command_prints_the_install_line_and_exits_2(recorded, tmp_path, name, hidden, extra, command, says):
    tub, mcap = recorded
    args = [str(a).format(tub=tub, mcap=mcap, tmp=tmp_path) for a in command]
    assert_missing_extra(run_hiding(hidden, *args), extra, says)


@pytest.mark.subprocess
def test_a_car_file_importing_an_extra_itself_gets_the_install_line(tmp_path):
    """The last line of defence: an import that did not go through require() still names its extra."""
    car = tmp_path / "zcar.py"
    car.write_text("import zenoh\n\n\ndef build():\n    raise AssertionError('not reached')\n")
    assert_missing_extra(run_hiding("zenoh", "run", car), "zenoh", f"{car} needs the zenoh extra")
    late = tmp_path / "late.py"
    late.write_text("def build():\n    from mcap.writer import Writer\n")
    assert_missing_extra(run_hiding("mcap", "run", late), "mcap", f"{late}: build() needs the mcap extra")


@pytest.mark.subprocess
def test_the_same_commands_run_with_the_extras_there(recorded, tmp_path):
    """The hiding runner hides only what it is told: with nothing hidden, the MCAP report is written."""
    _, mcap = recorded
    proc = run_hiding("asyncdonkey_nothing", "report", mcap, "-o", tmp_path / "r.html")
    assert proc.returncode == 0, proc.stderr
    assert (tmp_path / "r.html").read_text().startswith("<!doctype html>")


@pytest.mark.subprocess
def test_train_example_says_what_to_install_before_training(tmp_path):
    proc = run_hiding("onnx", EXAMPLES / "train.py", "--out", tmp_path / "m.onnx", cwd=tmp_path)
    assert "Traceback" not in proc.stderr, proc.stderr
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == [
        "train.py: error: examples/train.py (it writes the pilot as an ONNX model) needs the quantize extra "
        "(onnx is not installed): " + install_command("quantize")
    ]
    assert proc.stdout == ""  # nothing trained: it stopped before the minute of work


def test_a_zenoh_link_built_in_a_program_without_the_extra_says_what_to_install(monkeypatch):
    """Embedded in an application (no command to catch it), the link still raises the one-line error."""
    from asyncdonkey.parts.zenoh import ZenohLink

    monkeypatch.setitem(sys.modules, "zenoh", None)  # importing it now fails as a missing package does
    with pytest.raises(
        MissingExtra, match=r"a Zenoh link needs the zenoh extra .*" + re.escape(install_command("zenoh"))
    ):
        ZenohLink("cars/x")
