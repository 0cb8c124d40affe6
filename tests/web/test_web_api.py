"""The web controller's HTTP and WebSocket API on a driving car (real loop, loopback sockets): access token,
origin checks, Donkeycar's messages, one driver at a time, the deadman through the throttle's failsafe,
calibration and the MJPEG stream. Timing assertions only bound what a loaded machine can guarantee."""

import asyncio
import json
import time

import aiohttp
import cv2
import numpy as np
import pytest

from asyncdonkey import PartError
from asyncdonkey.parts.web.video import CONTENT_TYPE

from ..waiting import await_until
from .web_rig import ZERO_PULSE, WebCar, auth, driving, self_signed

pytestmark = [pytest.mark.realtime, pytest.mark.network]

#: a browser opening a page accepts HTML: only then does the token in the URL become a cookie and a redirect
BROWSER = {"Accept": "text/html,application/xhtml+xml,*/*;q=0.8"}


async def next_json(ws: aiohttp.ClientWebSocketResponse, key: str, timeout: float = 5.0) -> dict:
    """The next message from the server that has ``key``."""
    async with asyncio.timeout(timeout):
        while True:
            msg = await ws.receive_json()
            if key in msg:
                return msg


@pytest.mark.asyncio
async def test_without_the_token_everything_is_401_and_the_printed_url_sets_a_cookie(tmp_path):
    jar = aiohttp.CookieJar(unsafe=True)  # a browser keeps cookies of IP-address hosts; aiohttp must be told
    async with driving(WebCar(tmp_path)) as car, aiohttp.ClientSession(cookie_jar=jar) as http:
        base = car.base
        assert car.ctr.token and len(car.ctr.token) >= 20 and car.ctr.url.endswith(f"?token={car.ctr.token}")
        for method, path in (("GET", "/drive"), ("GET", "/video"), ("GET", "/status"), ("POST", "/drive")):
            async with http.request(method, base + path, json={"throttle": 1}) as r:
                assert r.status == 401, path
        async with http.get(base + "/status?token=wrong-token-123") as r:
            assert r.status == 401
        with pytest.raises(aiohttp.WSServerHandshakeError) as exc:
            await http.ws_connect(base + "/wsDrive")
        assert exc.value.status == 401
        assert car.mem.get(["user/throttle"]) == [0.0]  # none of it drove

        async with http.get(car.ctr.url, headers=BROWSER, allow_redirects=False) as r:  # a browser opens it
            assert r.status == 302 and r.headers["Location"] == "/drive"  # the token leaves the address bar
            assert "HttpOnly" in r.headers["Set-Cookie"] and "SameSite=Strict" in r.headers["Set-Cookie"]
        async with http.get(base + "/drive") as r:  # the cookie now opens everything
            assert r.status == 200 and "drive.js" in await r.text()
        async with http.get(base + "/status") as r:
            assert r.status == 200 and (await r.json())["driveMode"] == "user"
    async with aiohttp.ClientSession() as http:
        with pytest.raises(aiohttp.ClientConnectionError):  # the drive's end closed the server
            await http.get(base + "/status", headers=auth(car))


@pytest.mark.asyncio
async def test_served_over_https_the_page_and_its_websocket_drive_the_car(tmp_path):
    """What a phone needs for the screen wake lock and motion sensors: the same controller over TLS."""
    server_ctx, client_ctx = self_signed(tmp_path)
    async with driving(WebCar(tmp_path, ssl_context=server_ctx)) as car:
        port = car.ctr.port
        assert car.ctr.url == f"https://127.0.0.1:{port}/drive?token={car.ctr.token}"  # what the car prints
        base = f"https://127.0.0.1:{port}"
        jar = aiohttp.CookieJar(unsafe=True)
        async with aiohttp.ClientSession(cookie_jar=jar, connector=aiohttp.TCPConnector(ssl=client_ctx)) as http:
            async with http.get(car.ctr.url, headers=BROWSER) as r:  # the token for a cookie, then the page
                assert r.status == 200 and str(r.url) == base + "/drive" and "drive.js" in await r.text()
            async with http.ws_connect(base + "/wsDrive", headers={"Origin": base}) as ws:  # wss://
                assert (await ws.receive_json())["control"] == "free"
                await ws.send_json({"angle": 0.0, "throttle": 0.4})
                await await_until(lambda: car.throttle_pulse() > ZERO_PULSE, what="a forward pulse over wss")
                await ws.send_json({"angle": 0.0, "throttle": 0.0})
                await await_until(lambda: car.throttle_pulse() == ZERO_PULSE, what="stopped over wss")
        async with aiohttp.ClientSession() as http:  # plain HTTP on the TLS port gets nothing
            with pytest.raises(aiohttp.ClientError):
                async with http.get(f"http://127.0.0.1:{port}/status", headers=auth(car)) as r:
                    await r.read()
        async with aiohttp.ClientSession() as http:  # nor does a client that does not trust the certificate
            with pytest.raises(aiohttp.ClientConnectorCertificateError):
                await http.get(base + "/status", headers=auth(car))


@pytest.mark.asyncio
async def test_each_start_makes_a_new_token(tmp_path):
    car = WebCar(tmp_path)
    tokens = []
    for _ in range(2):
        task = asyncio.create_task(car.vehicle.run(rate_hz=50))
        await await_until(car.ctr.listening.is_set, 10, "the server to listen")
        tokens.append(car.ctr.token)
        car.vehicle.stop()
        await asyncio.wait_for(task, 15)
    car.buses.close_all()
    assert tokens[0] != tokens[1]


@pytest.mark.asyncio
async def test_token_none_on_loopback_needs_no_token(tmp_path):
    async with driving(WebCar(tmp_path, token=None)) as car, aiohttp.ClientSession() as http:
        async with http.post(car.base + "/drive", json={"angle": 0.5}) as r:
            assert r.status == 200
        # the drive may not have stored any user/angle yet when the answer comes: read it without a KeyError
        await await_until(lambda: car.mem.get(["user/angle"]) == [0.5], what="user/angle 0.5")


@pytest.mark.asyncio
async def test_pages_of_other_sites_cannot_drive(tmp_path):
    async with driving(WebCar(tmp_path)) as car, aiohttp.ClientSession(headers=auth(car)) as http:
        evil = {"Origin": "http://evil.example"}
        with pytest.raises(aiohttp.WSServerHandshakeError) as exc:
            await http.ws_connect(car.base + "/wsDrive", headers=evil)
        assert exc.value.status == 403
        async with http.post(car.base + "/drive", json={"throttle": 0.5}, headers=evil) as r:
            assert r.status == 403
        own = {"Origin": car.base}
        async with http.ws_connect(car.base + "/wsDrive", headers=own) as ws:
            assert (await ws.receive_json())["control"] == "free"


async def until_forward(car: WebCar, ws: aiohttp.ClientWebSocketResponse, what: str) -> None:
    """Send the driver's command every 100 ms, as a page does while a key is held, until the throttle pin shows a
    forward pulse. One command is not enough on a loaded machine: it can reach the PWM writer older than the
    failsafe window (250 ms), which then holds the stopped pulse, as it should."""
    deadline = time.monotonic() + 10
    while car.throttle_pulse() <= ZERO_PULSE:
        assert time.monotonic() < deadline, f"timed out after 10 s waiting for {what}"
        await ws.send_json({"angle": 0.5, "throttle": 0.4})
        await asyncio.sleep(0.1)


@pytest.mark.asyncio
async def test_a_command_drives_the_pwm_and_a_silent_driver_trips_the_failsafe(tmp_path):
    car = WebCar(tmp_path, idle_release_s=30.0)  # control stays with the quiet page: only the failsafe acts
    async with driving(car), aiohttp.ClientSession(headers=auth(car)) as http:
        async with http.ws_connect(car.base + "/wsDrive") as ws:
            hello = await ws.receive_json()
            assert hello == {
                "driveMode": "user",
                "recording": False,
                "num_records": 0,
                "control": "free",
                "modes": ["user", "local_angle", "local"],
            }
            await ws.send_json({"angle": 0.5, "throttle": 0.4})
            assert (await next_json(ws, "control"))["control"] == "you"
            await until_forward(car, ws, "a forward throttle pulse")
            assert car.mem["user/throttle"] == 0.4 and car.mem["throttle"] == 0.4
            assert car.steering_pulse() < 375  # right of centre (460 left .. 290 right)
            # nothing more comes from the page: the command ages and PWMThrottle stops the car
            await await_until(lambda: car.throttle_pulse() == ZERO_PULSE, 3, "the failsafe's stopped pulse")
            assert car.mem["user/throttle"] == 0.4  # the controller invented no zero: the age did it
            assert car.mem.age("throttle") >= 0.25
            # the watchdog's thread may write the stopped pulse a moment before the PWM writer counts its event
            await await_until(lambda: car.throttle.failsafe_events >= 1, 1, "the failsafe event counted")
            await until_forward(car, ws, "driving again")  # the driver is back
        # closing the page releases control at once and the throttle stops
        await await_until(lambda: car.throttle_pulse() == ZERO_PULSE, 3, "stopped after the page closed")
        assert car.ctr.desk.driver is None and car.mem["user/throttle"] == 0.0
        latency = car.vehicle.profiler.latency.get("throttle")  # command arrival -> PWM write, measured
        assert latency is not None and latency.count > 0 and 0 <= latency.recent(drop_last=False).min() < 1.0


@pytest.mark.asyncio
async def test_one_driver_others_watch_anyone_stops(tmp_path):
    async with driving(WebCar(tmp_path)) as car, aiohttp.ClientSession(headers=auth(car)) as http:
        a = await http.ws_connect(car.base + "/wsDrive")
        b = await http.ws_connect(car.base + "/wsDrive")
        await a.receive_json(), await b.receive_json()
        await a.send_json({"angle": 0.0, "throttle": 0.3})
        assert (await next_json(a, "control"))["control"] == "you"
        assert (await next_json(b, "control"))["control"] == "other"
        await b.send_json({"angle": 0.0, "throttle": -0.9})  # ignored: a drives
        async with http.post(car.base + "/drive", json={"throttle": -0.9}) as r:  # a script too
            assert r.status == 409
        await asyncio.sleep(0.1)
        assert car.mem["user/throttle"] == 0.3 and car.ctr.desk.refused >= 2
        await a.send_json({"drive_mode": "local"})
        await await_until(lambda: car.mem["user/mode"] == "local", what="mode local")

        await b.send_json({"stop": True})  # a watcher can always stop the car
        assert (await next_json(b, "control"))["control"] == "you"
        assert (await next_json(a, "control"))["control"] == "other"
        await await_until(lambda: car.mem["user/mode"] == "user", what="stop hands the car back from the pilot")
        assert car.mem["user/throttle"] == 0.0 and car.throttle_pulse() == ZERO_PULSE

        await b.send_json({"release": True})
        assert (await next_json(a, "control"))["control"] == "free"
        await a.send_json({"angle": 0.0, "throttle": 0.2})
        await await_until(lambda: car.mem["user/throttle"] == 0.2, what="a drives again")
        await a.close(), await b.close()


@pytest.mark.asyncio
async def test_mode_recording_and_record_count_round_trip(tmp_path):
    async with driving(WebCar(tmp_path)) as car, aiohttp.ClientSession(headers=auth(car)) as http:
        async with http.ws_connect(car.base + "/wsDrive") as ws:
            await ws.receive_json()
            await ws.send_json({"drive_mode": "local_angle"})
            assert (await next_json(ws, "driveMode"))["driveMode"] == "local_angle"
            assert car.mem["user/mode"] == "local_angle"
            await ws.send_json({"drive_mode": "autopilot"})
            assert "autopilot" in (await next_json(ws, "error"))["error"]
            await ws.send_json({"recording": True})
            assert (await next_json(ws, "recording"))["recording"] is True
            # pushed when the tub's count passes a multiple of ten, as it is then: 10, or more when the writer
            # thread wrote several records between two ticks (a loaded machine)
            assert 10 <= (await next_json(ws, "num_records", 10))["num_records"] < 20
            await ws.send_json({"recording": False})
            assert (await next_json(ws, "recording"))["recording"] is False
        assert car.mem["user/mode"] == "local_angle"


@pytest.mark.asyncio
async def test_calibration_page_sets_the_pulses_live(tmp_path):
    async with driving(WebCar(tmp_path)) as car, aiohttp.ClientSession(headers=auth(car)) as http:
        async with http.get(car.base + "/calibrate") as r:
            assert r.status == 200 and "calibrate.js" in await r.text()
        async with http.ws_connect(car.base + "/wsCalibrate") as ws:
            assert (await ws.receive_json())["config"]["STEERING_LEFT_PWM"] == 460
            await ws.send_json({"config": {"STEERING_LEFT_PWM": 480, "STEERING_RIGHT_PWM": 300}})
            assert (await ws.receive_json())["config"]["STEERING_RIGHT_PWM"] == 300
            await await_until(lambda: car.steering_pulse() == 390, what="the new steering centre on the pin")
            await ws.send_json({"angle": -1.0})  # full left: the new end point
            await next_json(ws, "control")
            await await_until(lambda: car.steering_pulse() == 480, what="the new left end point on the pin")
            await ws.send_json({"config": {"THROTTLE_STOPPED_PWM": 500}})
            assert "must differ" in (await next_json(ws, "error"))["error"]
            assert car.throttle.zero_pulse == ZERO_PULSE


@pytest.mark.asyncio
async def test_video_is_donkeycars_mjpeg_and_costs_one_encode_per_frame(tmp_path):
    async with driving(WebCar(tmp_path, camera_every=3), rate_hz=30) as car:
        await asyncio.sleep(0.5)
        assert car.ctr.hub.encodes == 0  # nobody watching: nothing encoded

        async def watch(http: aiohttp.ClientSession, parts: int) -> list[bytes]:
            async with http.get(car.base + "/video") as r:
                assert r.headers["Content-Type"] == CONTENT_TYPE
                buf, out = b"", []
                while len(out) < parts:
                    buf += await r.content.read(65536)
                    while True:
                        head = buf.find(b"--boundarydonotcross\nContent-type: image/jpeg\r\nContent-length: ")
                        if head < 0:
                            break
                        start = buf.index(b"\r\n\r\n", head) + 4
                        length = int(buf[head:start].split(b"Content-length: ")[1].split(b"\r\n")[0])
                        if len(buf) < start + length:
                            break
                        out.append(buf[start : start + length])
                        buf = buf[start + length :]
                return out

        async with aiohttp.ClientSession(headers=auth(car)) as http:
            frames0 = car.camera.frames
            streams = await asyncio.gather(*(watch(http, 12) for _ in range(3)))
            new_frames = car.camera.frames - frames0
        for jpegs in streams:
            img = cv2.imdecode(np.frombuffer(jpegs[-1], np.uint8), cv2.IMREAD_COLOR)
            assert img.shape == (120, 160, 3)
            assert len(set(jpegs[1:])) == len(jpegs) - 1  # every part a new frame, none sent twice
        # one encode per new camera frame for three viewers (+1: the frame there when the first one came)
        assert car.ctr.hub.encodes <= new_frames + 1
        assert json.dumps(car.ctr.state())  # /status is JSON-able


@pytest.mark.asyncio
async def test_a_quiet_driver_loses_control_with_the_tick_in_a_worker_thread(tmp_path):
    # executor=True: run() happens off the loop thread, and its pushes must still reach the pages
    car = WebCar(tmp_path, executor=True, idle_release_s=0.3, health_every_s=60)
    async with (
        driving(car),
        aiohttp.ClientSession(headers=auth(car)) as http,
        http.ws_connect(car.base + "/wsDrive") as ws,
    ):
        await ws.receive_json()
        await ws.send_json({"angle": 0.2, "throttle": 0.3})
        assert (await next_json(ws, "control"))["control"] == "you"
        # 0.3 s of silence: the tick (in its worker) releases the driver and tells the page
        assert (await next_json(ws, "control"))["control"] == "free"
        await await_until(lambda: car.mem["user/throttle"] == 0.0 and car.mem["user/angle"] == 0.0, 2, "neutral")


@pytest.mark.asyncio
async def test_a_taken_port_is_an_error_naming_it(tmp_path):
    first = WebCar(tmp_path / "a")
    async with driving(first):
        second = WebCar(tmp_path / "b", port=first.ctr.port)
        with pytest.raises(PartError, match=f"cannot listen on 127.0.0.1:{first.ctr.port}"):
            await asyncio.wait_for(second.vehicle.run(rate_hz=50), 15)
        second.buses.close_all()


@pytest.mark.asyncio
async def test_the_start_up_message_prints_the_url_and_a_qr_code(tmp_path):
    import io

    out = io.StringIO()
    async with driving(WebCar(tmp_path, announce=out, qr=True)) as car:
        text = out.getvalue()
    assert car.ctr.url in text and "token changes at every start" in text
    qr_lines = [line for line in text.splitlines() if set(line) & set("█▀▄")]
    assert len(qr_lines) >= 10  # a version-2+ QR code, two modules per line in compact mode
