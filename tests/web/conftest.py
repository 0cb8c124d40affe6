"""One headless Chromium for the whole session, driven by Playwright.

Playwright's own browser download cannot work on the car's machines (no internet beyond package registries),
so the tests drive Debian's ``chromium`` package, which ``make test`` installs before the session (``make``'s
chromium step). Here it is only located: when it is missing the browser tests fail, naming the command that
installs it. They never skip: a web controller untested in a browser is untested.
"""

from __future__ import annotations

import os
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


def located_chromium() -> Path:
    if CHROMIUM.is_file() and os.access(CHROMIUM, os.X_OK):
        return CHROMIUM
    pytest.fail(
        f"the web controller's browser tests need Chromium at {CHROMIUM}: 'make test' installs it (as root, with "
        "apt-get), or run 'sudo apt-get install -y chromium', or point ASYNCDONKEY_CHROMIUM at a Chromium binary; "
        "'-m \"not browser\"' leaves these tests out",
        pytrace=False,
    )


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    """The browser for the browser-test module (the only one: one browser per test session).

    Module scope, not session: Playwright's sync API keeps an event loop running in the main thread while it is
    open, and the asyncio tests of the modules after it need that thread's loop to themselves.
    """
    from playwright.sync_api import sync_playwright

    path = located_chromium()
    with sync_playwright() as pw:
        b = pw.chromium.launch(executable_path=str(path), args=CHROMIUM_ARGS)
        yield b
        b.close()
