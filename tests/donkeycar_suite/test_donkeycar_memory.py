"""Donkeycar's own ``donkeycar/tests/test_memory.py`` (installed package), on asyncdonkey's Vehicle and Memory."""

import pytest

from asyncdonkey.commands.donkey import donkeycar_replaced

pytestmark = [pytest.mark.donkeycar]

with donkeycar_replaced():
    from donkeycar.tests.test_memory import *  # noqa: F403
