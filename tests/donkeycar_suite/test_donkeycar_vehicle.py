"""Donkeycar's own ``donkeycar/tests/test_vehicle.py`` (installed package), on asyncdonkey's Vehicle and Memory."""

import pytest

from asyncdonkey.commands.donkey import donkeycar_replaced

pytestmark = [pytest.mark.donkeycar]

with donkeycar_replaced():
    from donkeycar.tests.test_vehicle import *  # noqa: F403
    from donkeycar.tests.test_vehicle import test_vehicle_run

test_vehicle_run = pytest.mark.realtime(test_vehicle_run)  # it starts a Vehicle on a real loop
