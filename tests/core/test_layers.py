"""The package's layers: the core loads no command, and the command runs as a module."""

from __future__ import annotations

import importlib
import subprocess
import sys

import pytest


@pytest.mark.subprocess
def test_the_core_does_not_load_the_commands() -> None:
    code = "import sys, asyncdonkey; print(sorted(m for m in sys.modules if m.startswith('asyncdonkey.commands')))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


@pytest.mark.subprocess
def test_the_command_runs_as_a_module() -> None:
    done = subprocess.run(
        [sys.executable, "-m", "asyncdonkey.commands", "--version"], capture_output=True, text=True, timeout=60
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip().endswith(importlib.import_module("asyncdonkey").__version__)
