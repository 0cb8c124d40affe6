"""The drive page in a real browser (headless Chromium) against a car driving in real time in its own thread.

A person's view: the page loads clean, touch, keys, tilt and a gamepad drive the PWM outputs, the video
moves, mode and recording round-trip, STOP and a closed tab bring the throttle to neutral, and no token means no entry.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import cv2
import numpy as np
import pytest

from ..waiting import wait_until
from .web_rig import ZERO_PULSE, CarThread, WebCar

pytestmark = [pytest.mark.realtime, pytest.mark.browser, pytest.mark.network, pytest.mark.subprocess]


@pytest.fixture(scope="module")
def car(tmp_path_factory: pytest.TempPathFactory) -> Iterator[WebCar]:
    with CarThread(WebCar(tmp_path_factory.mktemp("webcar"))) as c:
        yield c


class Page:
    """A browser tab opened on the URL the car printed, collecting console errors and page errors."""

    def __init__(self, browser: Any, car: WebCar, init_script: str | None = None, **context: Any) -> None:
        self.context = browser.new_context(**context)
        if init_script is not None:  # runs in the page before its own scripts
            self.context.add_init_script(init_script)
        self.page = self.context.new_page()
        self.errors: list[str] = []
        self.page.on("console", lambda m: self.errors.append(m.text) if m.type == "error" else None)
        self.page.on("pageerror", lambda e: self.errors.append(str(e)))
        self.response = self.page.goto(car.ctr.url)
        self.page.wait_for_selector("#conn[data-state=connected]", timeout=10_000)

    def text(self, selector: str) -> str:
        return self.page.locator(selector).inner_text()

    def close(self) -> None:
        self.context.close()


@pytest.fixture
def tab(browser: Any, car: WebCar) -> Iterator[Page]:
    p = Page(browser, car)
    yield p
    p.close()
    wait_until(lambda: car.ctr.desk.driver is None, 5, "control to be free after the tab closed")


def test_page_loads_clean_with_health_and_wake_lock(tab: Page, car: WebCar):
    assert tab.response is not None and tab.response.url.endswith("/drive")  # the token left the address bar
    page = tab.page
    page.wait_for_function("document.getElementById('health').textContent.includes('Hz')", timeout=5_000)
    footer = tab.text("#health")
    assert "late p99" in footer and "watching" in footer
    assert page.locator("#wake").get_attribute("data-state") in ("on", "refused")  # asked for the wake lock
    assert page.locator("#modes [aria-pressed=true]").get_attribute("data-mode") == "user"
    assert tab.errors == []


def test_keyboard_drives_and_releases(tab: Page, car: WebCar):
    kb = tab.page.keyboard
    kb.down("ArrowUp")
    kb.down("ArrowRight")
    wait_until(lambda: car.throttle_pulse() > ZERO_PULSE, what="a forward pulse from the up arrow")
    wait_until(lambda: car.mem["user/angle"] == 1.0, what="full right lock from the right arrow")
    assert car.mem["user/throttle"] == pytest.approx(0.5)  # the page's max throttle slider (0.5)
    assert tab.text("#control") == "you drive"
    kb.up("ArrowRight")
    kb.up("ArrowUp")
    wait_until(lambda: car.mem["user/throttle"] == 0 and car.mem["user/angle"] == 0, what="keys released")
    assert car.throttle_pulse() == ZERO_PULSE
    kb.down("KeyW")
    wait_until(lambda: car.mem["user/throttle"] > 0, what="W drives too")
    kb.press("Space")  # stop
    wait_until(lambda: car.mem["user/throttle"] == 0, what="space stops")
    # the page redraws its status on its own 20 Hz tick, after the stop reached the car
    wait_until(lambda: tab.text("#source") == "stopped", what="the page showing the stop")
    kb.up("KeyW")
    assert tab.errors == []


def test_touch_joystick_drives(browser: Any, car: WebCar):
    phone = Page(browser, car, has_touch=True, is_mobile=True, viewport={"width": 390, "height": 800})
    try:
        page = phone.page
        box = page.locator("#pad").bounding_box()
        cx, cy = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
        cdp = phone.context.new_cdp_session(page)

        def touch(kind: str, x: float, y: float) -> None:
            points = [] if kind == "touchEnd" else [{"x": x, "y": y, "id": 1}]
            cdp.send("Input.dispatchTouchEvent", {"type": kind, "touchPoints": points})

        touch("touchStart", cx, cy)
        for i in range(1, 6):  # a finger dragging up and to the right
            touch("touchMove", cx + 0.07 * i * box["width"], cy - 0.07 * i * box["height"])
        wait_until(lambda: car.mem["user/angle"] > 0.5 and car.mem["user/throttle"] > 0.2, what="touch driving")
        wait_until(lambda: car.throttle_pulse() > ZERO_PULSE, what="a forward pulse from the touch pad")
        # steered right (the steering writer lands its pulse on its own schedule, just after the throttle's)
        wait_until(lambda: car.steering_pulse() < 360, what="a right-steering pulse from the touch pad")
        touch("touchEnd", 0, 0)
        wait_until(lambda: car.mem["user/throttle"] == 0 and car.mem["user/angle"] == 0, what="finger lifted")
        assert phone.errors == []
    finally:
        phone.close()


def test_tilting_the_phone_drives(browser: Any, car: WebCar):
    """The phone's motion sensor, as Chromium emulates it for the page: the way the phone is held when tilt is
    switched on is "stopped"; tipping it forward drives, rolling it steers, holding it level again stops."""
    phone = Page(browser, car, has_touch=True, is_mobile=True, viewport={"width": 390, "height": 800})
    try:
        page = phone.page
        cdp = phone.context.new_cdp_session(page)

        def hold(beta: float, gamma: float) -> None:  # pitch forward/back, roll left/right (degrees)
            cdp.send("DeviceOrientation.setDeviceOrientationOverride", {"alpha": 0, "beta": beta, "gamma": gamma})

        hold(40, 0)
        page.click("#tilt")  # (the page asks for the motion sensors first, where the browser has that step)
        page.wait_for_selector("#tilt[aria-pressed=true]", timeout=5_000)
        wait_until(lambda: phone.text("#source") == "tilt", what="the page steering by tilt")
        hold(30, 15)  # 10 degrees forward of where it was held (of 25 for full throttle), rolled 15 right (of 30)
        wait_until(
            lambda: car.mem["user/throttle"] == pytest.approx(0.2) and car.mem["user/angle"] == pytest.approx(0.5),
            what="tilt driving (0.4 of the page's 0.5 throttle limit, half right lock)",
        )
        wait_until(lambda: car.throttle_pulse() > ZERO_PULSE, what="a forward pulse from the tilt")
        wait_until(lambda: car.steering_pulse() < 360, what="a right-steering pulse from the roll")
        hold(40, 0)  # back as it was held: stopped
        wait_until(lambda: car.mem["user/throttle"] == 0 and car.mem["user/angle"] == 0, what="held level again")
        wait_until(lambda: car.throttle_pulse() == ZERO_PULSE, what="the throttle at neutral")
        page.click("#tilt")
        assert page.locator("#tilt").get_attribute("aria-pressed") == "false"
        assert phone.errors == []
    finally:
        phone.close()


# A gamepad as the page sees one through the Gamepad API (``navigator.getGamepads()``, standard layout): the
# test moves its sticks and presses its buttons by changing ``window.testPad``.
_GAMEPAD = """
window.testPad = {id: "test pad (standard)", index: 0, connected: true, mapping: "standard", timestamp: 0,
                  axes: [0, 0, 0, 0], buttons: Array.from({length: 17}, () => ({pressed: false, value: 0}))};
navigator.getGamepads = () => [window.testPad, null, null, null];
"""


def test_a_gamepad_drives_and_its_b_button_stops(browser: Any, car: WebCar):
    pad = Page(browser, car, init_script=_GAMEPAD)
    try:
        page = pad.page

        def sticks(left_x: float, right_y: float) -> None:
            page.evaluate(f"window.testPad.axes = [{left_x}, 0, 0, {right_y}]")

        sticks(-0.6, -0.8)  # left stick to the left, right stick forward (Donkeycar's layout)
        wait_until(
            lambda: car.mem["user/throttle"] == pytest.approx(0.4) and car.mem["user/angle"] == pytest.approx(-0.6),
            what="gamepad driving (0.8 of the page's 0.5 throttle limit, 0.6 left)",
        )
        assert pad.text("#source") == "gamepad" and pad.text("#control") == "you drive"
        wait_until(lambda: car.throttle_pulse() > ZERO_PULSE, what="a forward pulse from the gamepad")
        wait_until(lambda: car.steering_pulse() > 390, what="a left-steering pulse from the gamepad")
        sticks(0.05, -0.1)  # a stick resting a little off centre is inside the dead zone
        wait_until(lambda: car.mem["user/throttle"] == 0 and car.mem["user/angle"] == 0, what="sticks at rest")
        sticks(0, -0.8)
        wait_until(lambda: car.mem["user/throttle"] > 0, what="driving again")
        page.evaluate("window.testPad.buttons[1] = {pressed: true, value: 1}")  # B / circle
        wait_until(lambda: car.mem["user/throttle"] == 0, 2, "B to stop")
        wait_until(lambda: car.throttle_pulse() == ZERO_PULSE, 2, "the throttle at neutral")
        page.evaluate("window.testPad.buttons[1] = {pressed: false, value: 0}")
        page.wait_for_timeout(300)  # the stick is still forward: the stop holds until everything is at rest
        assert car.mem["user/throttle"] == 0
        sticks(0, 0)
        page.wait_for_timeout(200)
        sticks(0, -0.8)
        wait_until(lambda: car.mem["user/throttle"] > 0, what="driving after the sticks came back to rest")
        sticks(0, 0)
        assert pad.errors == []
    finally:
        pad.close()
    wait_until(lambda: car.ctr.desk.driver is None, 5, "control to be free after the tab closed")


def _pixels(png: bytes) -> np.ndarray:
    return cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR).astype(np.int16)


def test_video_shows_frames_that_change(tab: Page, car: WebCar):
    video = tab.page.locator("#video")
    tab.page.wait_for_function("document.getElementById('video').naturalWidth === 160", timeout=5_000)
    first = _pixels(video.screenshot())
    wait_until(lambda: np.abs(_pixels(video.screenshot()) - first).mean() > 5, 5, "the picture to change")
    # the camera's yellow bar (RGB 240, 200, 40) is on screen: the car's frames, not a placeholder
    b, g, r = first[..., 0], first[..., 1], first[..., 2]
    assert ((r > 180) & (g > 140) & (b < 110)).mean() > 0.02
    assert car.ctr.hub.encodes <= car.camera.frames  # never more encodes than camera frames


def test_mode_and_record_toggles_round_trip(tab: Page, car: WebCar):
    page = tab.page
    page.click("#modes [data-mode=local_angle]")
    wait_until(lambda: car.mem["user/mode"] == "local_angle", what="mode local_angle in memory")
    page.wait_for_selector("#modes [data-mode=local_angle][aria-pressed=true]", timeout=5_000)
    page.click("#modes [data-mode=user]")
    wait_until(lambda: car.mem["user/mode"] == "user", what="mode user in memory")
    page.click("#record")
    wait_until(lambda: car.mem["recording"] is True, what="recording on")
    page.wait_for_selector("#record[aria-pressed=true]", timeout=5_000)
    wait_until(lambda: int(tab.text("#count")) >= 10, 10, "the record count on the page")
    page.click("#record")
    wait_until(lambda: car.mem["recording"] is False, what="recording off")
    page.wait_for_selector("#record[aria-pressed=false]", timeout=5_000)
    assert car.mem["tub/num_records"] >= 10
    assert tab.errors == []


def test_stop_button_from_a_watching_tab_stops_the_driver(browser: Any, tab: Page, car: WebCar):
    tab.page.keyboard.down("ArrowUp")
    wait_until(lambda: car.throttle_pulse() > ZERO_PULSE, what="the first tab driving")
    watcher = Page(browser, car)
    try:
        watcher.page.wait_for_selector("#control[data-role=other]", timeout=5_000)
        watcher.page.keyboard.down("ArrowDown")  # a watcher's stick is ignored
        watcher.page.wait_for_timeout(300)
        assert car.mem["user/throttle"] > 0
        watcher.page.keyboard.up("ArrowDown")
        watcher.page.click("#stop")
        # the STOP itself, not only a neutral pulse: on a loaded machine the driver's held key can reach the car
        # late enough for the failsafe to hold the pulse at neutral a moment before the STOP arrives
        stopped = wait_until(
            lambda: car.throttle_pulse() == ZERO_PULSE and car.mem["user/throttle"] == 0, 2, "STOP to stop the car"
        )
        assert stopped and car.mem["user/mode"] == "user"
        tab.page.wait_for_selector("#control[data-role=other]", timeout=5_000)  # the driver lost control
        tab.page.wait_for_timeout(300)
        assert car.throttle_pulse() == ZERO_PULSE  # though its up arrow is still held
    finally:
        tab.page.keyboard.up("ArrowUp")
        watcher.close()


def test_a_closed_tab_stops_the_car_through_the_failsafe(browser: Any, car: WebCar):
    driver = Page(browser, car)
    driver.page.keyboard.down("ArrowUp")
    wait_until(lambda: car.throttle_pulse() > ZERO_PULSE, what="the tab driving")
    events = car.throttle.failsafe_events
    driver.page.close()  # the tab goes away mid-drive
    # one condition, not three in a row: on a loaded machine the failsafe can also fire during a stall just
    # before the close, and the tab's last command can still land after it
    wait_until(
        lambda: (
            car.ctr.desk.driver is None
            and car.mem.age("throttle") >= 0.25
            and car.throttle_pulse() == ZERO_PULSE
            and car.throttle.failsafe_events > events
        ),
        3,
        "the tab's last command gone stale and the failsafe holding neutral",
    )
    driver.close()


def test_a_page_that_goes_hidden_hands_the_car_back(tab: Page, car: WebCar):
    page = tab.page
    car.ctr.desk.idle_release_s = 30.0  # only the page's own release can free control within the test
    page.keyboard.down("ArrowUp")
    wait_until(lambda: car.throttle_pulse() > ZERO_PULSE, what="the tab driving")
    # what the browser does when the phone locks or another app comes to the front
    page.evaluate(
        "Object.defineProperty(document, 'visibilityState', {value: 'hidden', configurable: true});"
        "document.dispatchEvent(new Event('visibilitychange'))"
    )
    wait_until(lambda: car.ctr.desk.driver is None, 2, "the hidden page to release control")
    wait_until(lambda: car.throttle_pulse() == ZERO_PULSE, 2, "the throttle at neutral")
    page.wait_for_timeout(300)  # the key is still held, but a hidden page sends nothing
    assert car.ctr.desk.driver is None and car.mem["user/throttle"] == 0
    page.keyboard.up("ArrowUp")
    car.ctr.desk.idle_release_s = 1.0


def test_calibration_page_sets_the_steering_end_point(tab: Page, car: WebCar):
    page = tab.page
    page.goto(f"{car.base}/calibrate")
    field = page.locator("#cfg-STEERING_LEFT_PWM")
    field.wait_for(timeout=5_000)
    assert field.input_value() == "460"
    try:
        field.fill("470")
        page.click("#apply")
        wait_until(lambda: car.steering.left_pulse == 470, what="the new left end point")
        assert car.steering.neutral_pulse == 380  # the centre follows
        field.fill("470")
        page.locator("#cfg-STEERING_RIGHT_PWM").fill("470")
        page.click("#apply")
        page.wait_for_selector("#msg.bad", timeout=5_000)  # refused, with the reason shown
        assert "both 470" in tab.text("#msg") and car.steering.right_pulse == 290
    finally:
        page.locator("#cfg-STEERING_LEFT_PWM").fill("460")
        page.locator("#cfg-STEERING_RIGHT_PWM").fill("290")
        page.click("#apply")
        wait_until(lambda: car.steering.left_pulse == 460, what="the calibration restored")
    assert tab.errors == []


def test_the_calibration_page_is_refused_while_another_page_drives(browser: Any, tab: Page, car: WebCar):
    tab.page.keyboard.down("ArrowUp")
    wait_until(lambda: car.throttle_pulse() > ZERO_PULSE, what="the first tab driving")
    tab.page.keyboard.up("ArrowUp")  # at rest, but still the driver: its page keeps sending
    wait_until(lambda: car.throttle_pulse() == ZERO_PULSE, what="the car stopped")
    other = Page(browser, car)
    try:
        page = other.page
        page.goto(f"{car.base}/calibrate")
        page.locator("#cfg-THROTTLE_STOPPED_PWM").fill("480")  # what a watcher once made "stopped" and "safe"
        page.click("#apply")
        page.wait_for_selector("#msg.bad", timeout=5_000)
        assert "another client is driving" in other.text("#msg")
        assert (car.throttle.zero_pulse, car.throttle.safe_pulse) == (ZERO_PULSE, ZERO_PULSE)
        assert tab.text("#control") == "you drive" and other.errors == []
    finally:
        other.close()


def test_without_the_token_the_browser_is_refused(browser: Any, car: WebCar):
    context = browser.new_context()
    try:
        page = context.new_page()
        resp = page.goto(f"{car.base}/drive")
        assert resp is not None and resp.status == 401
        assert "access token" in page.content()
        status = page.evaluate("fetch('/status').then(r => r.status)")
        assert status == 401
    finally:
        context.close()
