"""Donkeycar's own ``donkeycar/tests/test_memory.py`` (installed package), on asyncdonkey's Vehicle and Memory."""

from asyncdonkey.donkey import donkeycar_replaced

with donkeycar_replaced():
    from donkeycar.tests.test_memory import *  # noqa: F403
