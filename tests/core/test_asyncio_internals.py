"""The CPython internals the virtual clock relies on are all present on this Python, and a change is named."""

import sys

import pytest

from asyncdonkey import _asyncio_internals as internals
from asyncdonkey import virtual_loop


def test_every_internal_the_virtual_clock_relies_on_is_present():
    found = internals.problems()
    assert found == [], (
        f"Python {sys.version.split()[0]} changed what VirtualClockLoop relies on (see "
        f"asyncdonkey/_asyncio_internals.py): {found}"
    )


def test_a_changed_internal_is_named(monkeypatch):
    monkeypatch.setattr(internals, "_WRAP_FUTURE", (lambda future: None).__code__)
    monkeypatch.setattr(internals, "_CONDITION_WAIT", (lambda x: x).__code__)
    found = internals.problems()
    assert any("asyncio.wrap_future" in p for p in found), found
    assert any("threading.Condition.wait" in p for p in found), found


def test_the_loop_refuses_to_start_on_a_python_whose_internals_changed(monkeypatch):
    monkeypatch.setattr(virtual_loop, "_internals_problems", lambda: ("asyncio event loops have no list _scheduled",))
    with pytest.raises(virtual_loop.VirtualClockError, match=r"cannot run on Python .*no list _scheduled"):
        virtual_loop.VirtualClockLoop()
