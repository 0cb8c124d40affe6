"""One headless Chromium for the whole session, driven by Playwright.

Playwright's own browser download cannot work on the car's machines (no internet beyond package registries),
so the tests drive Debian's ``chromium`` package. When it is missing and we are root, it is installed here
(``apt-get update`` then ``apt-get install -y chromium``); otherwise the browser tests fail with the command
to run. They never skip: a web controller untested in a browser is untested.
"""

from __future__ import annotations

import os
import shutil
import subprocess
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

CHROMIUM = Path(os.environ.get("ASYNCDONKEY_CHROMIUM", "/usr/bin/chromium"))
CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]


def ensure_chromium() -> Path:
    if CHROMIUM.exists():
        return CHROMIUM
    if os.geteuid() == 0 and shutil.which("apt-get"):
        env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
        for cmd in (["apt-get", "update"], ["apt-get", "install", "-y", "chromium"]):
            done = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=900)
            if done.returncode != 0:
                pytest.fail(f"installing the browser for the web tests failed: {' '.join(cmd)}:\n{done.stderr[-2000:]}")
        if CHROMIUM.exists():
            return CHROMIUM
    pytest.fail(
        f"the web controller's browser tests need Chromium at {CHROMIUM}: install it with "
        "'sudo apt-get install -y chromium' (or point ASYNCDONKEY_CHROMIUM at a Chromium binary)"
    )


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    """The browser for the browser-test module (the only one: one browser per test session).

    Module scope, not session: Playwright's sync API keeps an event loop running in the main thread while it is
    open, and the asyncio tests of the modules after it need that thread's loop to themselves.
    """
    from playwright.sync_api import sync_playwright

    path = ensure_chromium()
    with sync_playwright() as pw:
        b = pw.chromium.launch(executable_path=str(path), args=CHROMIUM_ARGS)
        yield b
        b.close()
