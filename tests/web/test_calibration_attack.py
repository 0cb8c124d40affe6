"""A watcher tries to redefine "stopped" on a driving car (real loop, loopback sockets, the PCA9685 register
model): it presses STOP (open to all), which hands it control; it drops its socket, which frees control; and
within one of the driver's command periods it sends ``THROTTLE_STOPPED_PWM=440`` over ``/wsCalibrate``. That was
accepted 4 times in 4, after which the driver's throttle 0 and its STOP wrote pulse 440 (forward).

Timing assertions bound only what a loaded machine guarantees: the pin is awaited, never timed."""

from __future__ import annotations

import asyncio
import logging

import aiohttp
import pytest

from ..waiting import await_until
from .web_rig import ZERO_PULSE, WebCar, auth, driving

pytestmark = [pytest.mark.realtime, pytest.mark.network]

ATTACK = {"config": {"THROTTLE_STOPPED_PWM": 440}}


async def next_json(ws: aiohttp.ClientWebSocketResponse, *keys: str, timeout: float = 5.0) -> dict:
    """The next message from the server that has one of ``keys``."""
    async with asyncio.timeout(timeout):
        while True:
            msg = await ws.receive_json()
            if any(k in msg for k in keys):
                return msg


async def until_control(ws: aiohttp.ClientWebSocketResponse, role: str) -> None:
    while (await next_json(ws, "control"))["control"] != role:
        pass


@pytest.mark.asyncio
async def test_a_watcher_that_stops_drops_and_recalibrates_cannot_redefine_stopped(tmp_path, caplog):
    car = WebCar(tmp_path)
    caplog.set_level(logging.INFO, "asyncdonkey.parts.web.controller")
    async with (
        driving(car),
        aiohttp.ClientSession(headers=auth(car)) as http,
        http.ws_connect(car.base + "/wsDrive") as driver,
    ):
        await driver.receive_json()
        await driver.send_json({"angle": 0.0, "throttle": 0.4})
        await until_control(driver, "you")
        await await_until(lambda: car.throttle_pulse() > ZERO_PULSE, what="the driver driving")
        await driver.send_json({"angle": 0.0, "throttle": 0.0})  # the driver stops; its page stays open
        await await_until(lambda: car.throttle_pulse() == ZERO_PULSE, what="the car stopped")

        watcher = await http.ws_connect(car.base + "/wsDrive")
        await watcher.receive_json()
        await watcher.send_json({"stop": True})  # anyone may stop the car: it takes control
        await until_control(watcher, "you")
        await watcher.close()  # control is free again
        async with http.ws_connect(car.base + "/wsCalibrate") as cal:
            await cal.receive_json()
            answers = []
            for _ in range(4):
                await cal.send_json(ATTACK)
                answers.append(await next_json(cal, "config", "error"))
        assert all("error" in a and "config" not in a for a in answers), answers
        assert "take control first" in answers[0]["error"]
        assert car.throttle.zero_pulse == car.throttle.safe_pulse == ZERO_PULSE
        assert car.ctr.refused_values["web/calibration"]["not_driver"] == 4
        refusals = [r for r in car.ctr.calibrations if r["refused"]]
        assert len(refusals) == 4 and all("from 127.0.0.1" in r["who"] for r in refusals)
        assert all(r["asked"] == ATTACK["config"] for r in refusals)
        assert "calibration refused for page" in caplog.text and "THROTTLE_STOPPED_PWM" in caplog.text

        # afterwards the driver's throttle 0, its STOP, the failsafe and shutdown write the drive's stopped pulse
        await driver.send_json({"angle": 0.0, "throttle": 0.4})
        await until_control(driver, "you")
        await await_until(lambda: car.throttle_pulse() > ZERO_PULSE, what="the driver driving again")
        await driver.send_json({"angle": 0.0, "throttle": 0.0})
        await await_until(lambda: car.throttle_pulse() == ZERO_PULSE, what="throttle 0 at the stopped pulse")
        await driver.send_json({"angle": 0.0, "throttle": 0.4})
        await await_until(lambda: car.throttle_pulse() > ZERO_PULSE, what="driving")
        await driver.send_json({"stop": True})
        await await_until(lambda: car.throttle_pulse() == ZERO_PULSE, what="STOP at the stopped pulse")
        events = car.throttle.failsafe_events
        await driver.send_json({"angle": 0.0, "throttle": 0.4})
        await await_until(lambda: car.throttle_pulse() > ZERO_PULSE, what="driving")
        await await_until(lambda: car.throttle.failsafe_events > events, 3, "the failsafe (the page went quiet)")
        await await_until(lambda: car.throttle_pulse() == ZERO_PULSE, 3, "the failsafe at the stopped pulse")
    assert car.throttle_pulse() == ZERO_PULSE  # shutdown


@pytest.mark.asyncio
async def test_the_driver_calibrates_steering_while_disarmed_but_never_the_stopped_pulse(tmp_path, caplog):
    caplog.set_level(logging.INFO, "asyncdonkey.parts.web.controller")
    async with (
        driving(WebCar(tmp_path)) as car,
        aiohttp.ClientSession(headers=auth(car)) as http,
        http.ws_connect(car.base + "/wsCalibrate") as cal,  # a lone page: the driver to be
    ):
        await cal.receive_json()
        await cal.send_json({"config": {"STEERING_LEFT_PWM": 480, "STEERING_RIGHT_PWM": 300}})
        assert (await next_json(cal, "config"))["config"]["STEERING_LEFT_PWM"] == 480
        assert "STEERING_LEFT_PWM 460 -> 480, STEERING_RIGHT_PWM 290 -> 300" in caplog.text
        assert "from 127.0.0.1" in car.ctr.calibrations[-1]["who"]
        await cal.send_json(ATTACK)  # the driver itself: "stopped" is what the ESC was armed with
        assert "stays 370 during a drive" in (await next_json(cal, "error"))["error"]
        await cal.send_json({"throttle": 0.3})  # the test slider: driving
        await next_json(cal, "control")
        await await_until(lambda: car.throttle_pulse() > ZERO_PULSE, what="the wheels turning")
        await cal.send_json({"config": {"STEERING_LEFT_PWM": 470}})
        assert "must be stopped" in (await next_json(cal, "error"))["error"]
        await cal.send_json({"throttle": 0.0})
        await await_until(lambda: car.throttle_pulse() == ZERO_PULSE, what="the car stopped")
        assert (car.steering.left_pulse, car.throttle.zero_pulse) == (480, ZERO_PULSE)
        assert car.ctr.refused_values["calibration/THROTTLE_STOPPED_PWM"] == {"armed": 1}
        assert car.ctr.refused_values["web/calibration"] == {"moving": 1}
