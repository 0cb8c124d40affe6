"""Old import paths of the command modules keep working: each is the moved module itself, with a warning."""

from __future__ import annotations

import importlib
import subprocess
import sys
import warnings

import pytest

MOVED = {
    "asyncdonkey.cli": "asyncdonkey.commands.cli",
    "asyncdonkey.replay": "asyncdonkey.commands.replay",
    "asyncdonkey.report": "asyncdonkey.commands.report",
    "asyncdonkey.convert": "asyncdonkey.commands.convert",
    "asyncdonkey.quantize": "asyncdonkey.commands.quantize",
    "asyncdonkey.donkey": "asyncdonkey.commands.donkey",
    "asyncdonkey.recordings": "asyncdonkey.commands.recordings",
    "asyncdonkey.parts.zenoh.cli": "asyncdonkey.commands.zenoh",
    "asyncdonkey.testing.virtual_loop": "asyncdonkey.virtual_loop",
    "asyncdonkey.watchdog": "asyncdonkey.safety.watchdog",
}


@pytest.mark.parametrize("old, new", sorted(MOVED.items()))
def test_an_old_path_is_the_new_module_and_warns_once(old: str, new: str) -> None:
    sys.modules.pop(old, None)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        module = importlib.import_module(old)
    assert module is importlib.import_module(new)
    assert sys.modules[old] is module
    messages = [str(w.message) for w in caught if issubclass(w.category, DeprecationWarning)]
    expected = f"{old} moved to {new}; import it from there (the old path will be removed in a future release)"
    assert messages == [expected]


@pytest.mark.subprocess
def test_the_core_does_not_load_the_commands() -> None:
    code = "import sys, asyncdonkey; print(sorted(m for m in sys.modules if m.startswith('asyncdonkey.commands')))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


@pytest.mark.subprocess
@pytest.mark.parametrize("module", ["asyncdonkey.commands", "asyncdonkey.cli"])
def test_the_command_runs_as_a_module(module: str) -> None:
    done = subprocess.run([sys.executable, "-m", module, "--version"], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip().endswith(importlib.import_module("asyncdonkey").__version__)
