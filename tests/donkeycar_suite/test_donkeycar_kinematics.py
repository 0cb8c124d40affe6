"""Donkeycar's own ``donkeycar/tests/test_kinematics.py`` (installed package), on asyncdonkey's Vehicle and Memory."""

import pytest

from asyncdonkey.commands.donkey import donkeycar_replaced

pytestmark = [pytest.mark.donkeycar]

with donkeycar_replaced():
    from donkeycar.tests.test_kinematics import *  # noqa: F403
    from donkeycar.tests.test_kinematics import TestVehicle

TestVehicle = pytest.mark.realtime(TestVehicle)  # its tests start a Vehicle on a real loop
