"""The examples' web option: the simulated car (`car.py --web`) and the Pi car (`car_pi.py --web`) driven over
HTTP like Donkeycar's web API, on the real loop with loopback sockets."""

import asyncio

import aiohttp
import pytest

from asyncdonkey.parts.web import WebController

from ..waiting import await_until
from .example_loader import load_example
from .test_car_pi import Rig

car_py = load_example("car")
car_pi = load_example("car_pi")


def controller_of(vehicle) -> WebController:
    (ctr,) = [e.part for e in vehicle.parts if isinstance(e.part, WebController)]
    return ctr


def test_car_py_web_options():
    args = car_py.parse_args(["--web", "--web-port", "9000"])
    assert (args.web, args.web_port, args.web_host, args.seconds) == (True, 9000, "0.0.0.0", 0.0)


@pytest.mark.realtime
@pytest.mark.network
@pytest.mark.asyncio
async def test_simulated_car_drives_from_the_web_and_stops_when_the_page_goes_quiet():
    web = {"port": 0, "host": "127.0.0.1", "announce": None, "idle_release_s": 30.0}
    v, car = car_py.make_car(pilot="user", seconds=0, status=None, web=web)
    ctr = controller_of(v)
    assert ctr.mode == "user"
    drive = asyncio.create_task(v.run(rate_hz=20))
    try:
        await await_until(ctr.listening.is_set, 10, "the web controller")
        async with aiohttp.ClientSession(headers={"Authorization": f"Token {ctr.token}"}) as http:
            for _ in range(6):  # a page's steady commands
                async with http.post(f"http://127.0.0.1:{ctr.port}/drive", json={"angle": 0, "throttle": 0.6}) as r:
                    assert r.status == 200
                await asyncio.sleep(0.05)
            await await_until(lambda: car.throttle == 0.6, what="the simulated car to get the throttle")
            # the page goes quiet: the stand-in for the ESC failsafe stops the car, the command itself is unchanged
            await await_until(lambda: car.throttle == 0.0, 2, "the stale command to stop the car")
            assert v.mem["user/throttle"] == 0.6
        assert car.sim.progress > 0
    finally:
        v.stop()
        await asyncio.wait_for(drive, 15)


@pytest.mark.realtime
@pytest.mark.network
@pytest.mark.asyncio
async def test_pi_car_offers_web_or_gamepad(tmp_path):
    rig = Rig(tmp_path)
    try:
        v = car_pi.build(["--js", *rig.argv("HAVE_IMU=false")], buses=rig.buses)
        assert not [e for e in v.parts if isinstance(e.part, WebController)]
        token_file = tmp_path / "web-token"
        argv = ["--web", "--token-file", str(token_file), *rig.argv("WEB_CONTROL_PORT=0", "HAVE_IMU=false")]
        v = car_pi.build(argv, buses=rig.buses)
        ctr = controller_of(v)
        assert ctr.modes == ("user",)  # no model: the page cannot hand the car to a pilot
        assert ctr.steering is not None and ctr.throttle_part is not None  # /calibrate has the PWM parts
        # Donkeycar's config switch picks the web controller too
        v2 = car_pi.build(rig.argv("USE_JOYSTICK_AS_DEFAULT=false", "HAVE_IMU=false"), buses=rig.buses)
        assert controller_of(v2)
        ctr.announce = None
        drive = asyncio.create_task(v.run(rate_hz=20))
        try:
            await await_until(ctr.listening.is_set, 10, "the web controller")
            assert ctr.token == token_file.read_text().strip()  # the token of every start, kept for the phone
            base = f"http://127.0.0.1:{ctr.port}"
            async with aiohttp.ClientSession(headers={"Authorization": f"Token {ctr.token}"}) as http:
                async with http.post(base + "/drive", json={"drive_mode": "local"}) as r:
                    assert r.status == 400 and "not available" in (await r.json())["error"]
                async with http.post(base + "/drive", json={"angle": -1.0, "throttle": 0}) as r:
                    assert r.status == 200
                await await_until(lambda: rig.pca.pulse(1) == 460, what="full left on the steering pin")
        finally:
            v.stop()
            await asyncio.wait_for(drive, 15)
    finally:
        rig.close()
