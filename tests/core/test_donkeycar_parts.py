"""Donkeycar's own parts, unchanged, on asyncdonkey's loop (donkeycar is installed by `make test`)."""

import numpy as np
import pytest
from donkeycar.parts.camera import MockCamera
from donkeycar.parts.throttle_filter import ThrottleFilter
from donkeycar.parts.transform import Lambda, PIDController
from donkeycar.vehicle import Vehicle as DonkeyVehicle

from asyncdonkey import Vehicle
from asyncdonkey.core.plan import Background

pytestmark = [pytest.mark.donkeycar]


class Script:
    def __init__(self, values):
        self.values = iter(values)

    def run(self):
        return next(self.values)


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_donkeycar_parts_run_unchanged():
    frame = np.full((120, 160, 3), 7, dtype=np.uint8)
    v = Vehicle()
    v.add(MockCamera(image=frame), outputs=["cam/image_array"], threaded=True)
    v.add(Script([0.5, -0.5, -0.5, 0.3]), outputs=["user/throttle"])
    v.add(ThrottleFilter(), inputs=["user/throttle"], outputs=["throttle"])
    v.add(Lambda(lambda img: float(img.mean())), inputs=["cam/image_array"], outputs=["brightness"])
    seen = []
    v.add(Lambda(lambda t: seen.append(t)), inputs=["throttle"])
    await v.run(20, 4)
    assert v.mem["brightness"] == 7.0
    # ThrottleFilter's ESC reverse logic: the second reverse command in a row is held at 0 once
    assert seen == [0.5, -0.5, 0.0, 0.3]
    assert v.mem["cam/image_array"] is frame


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_donkeycar_pid_controller_converges_on_our_loop():
    pid = PIDController(p=0.5, i=0.05, d=0.0)
    v = Vehicle()
    v.mem["target"] = 10.0
    v.mem["pos"] = 0.0

    class Plant:
        def run(self, pos, u):
            return pos - (u or 0.0)  # Donkeycar's PID outputs -Kp * err

    class Err:
        def run(self, target, pos):
            return target - pos

    v.add(Err(), inputs=["target", "pos"], outputs=["err"])
    v.add(pid, inputs=["err"], outputs=["u"])
    v.add(Plant(), inputs=["pos", "u"], outputs=["pos"])
    await v.run(50, 200)
    assert v.mem["pos"] == pytest.approx(10.0, abs=0.05)


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_a_donkeycar_vehicle_converts_with_its_parts_and_memory():
    dk = DonkeyVehicle()
    dk.mem["constant"] = 3
    dk.add(MockCamera(image=np.zeros((2, 2, 3), np.uint8)), outputs=["cam/image_array"], threaded=True)
    dk.add(Lambda(lambda c: c * 2), inputs=["constant"], outputs=["doubled"])
    dk.add(Lambda(lambda: "ran"), outputs=["cond_part"], run_condition="never_set")
    v = Vehicle.from_donkeycar(dk)
    assert [e.beside.background for e in v.parts] == [Background.THREAD, Background.NONE, Background.NONE]
    await v.run(20, 2)
    assert v.mem["doubled"] == 6
    assert "cond_part" not in v.mem
