"""Donkeycar's own tests, from the installed ``donkeycar`` package, run against asyncdonkey's classes.

Each ``test_donkeycar_*.py`` here imports one of Donkeycar's test modules (``donkeycar/tests/...``, unchanged,
not copied) while ``donkeycar.vehicle.Vehicle`` / ``donkeycar.Vehicle`` and ``donkeycar.memory.Memory`` /
``donkeycar.Memory`` are asyncdonkey's, so names bound at import (``from donkeycar.vehicle import Vehicle``)
are ours; pytest then collects the imported tests. The autouse fixture keeps the substitution in force while
each test runs, for names looked up at call time (``dk.Vehicle()``), and restores Donkeycar's classes after.
"""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from asyncdonkey.commands.donkey import donkeycar_replaced


@pytest.fixture(autouse=True)
def _asyncdonkey_in_donkeycar() -> Iterator[None]:
    with donkeycar_replaced():
        yield
