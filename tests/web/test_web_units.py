"""The web controller's pieces without a server: command parsing, the one-driver desk, calibration, the
button latch and the video hub (on the virtual clock)."""

import asyncio
import json

import numpy as np
import pytest

from asyncdonkey import Contract, Contracts, Vehicle
from asyncdonkey.parts.actuators import (
    CalibrationLocked,
    PWMSteering,
    PWMThrottle,
    pulse_to_ticks,
)
from asyncdonkey.parts.control import DRIVE_MODES
from asyncdonkey.parts.web import WebConfigError, WebController
from asyncdonkey.parts.web.calibrate import (
    CalibrationError,
    admit_config,
    apply_calibration,
    current_calibration,
    why_not_stopped,
)
from asyncdonkey.parts.web.desk import Command, CommandError, Desk, parse_command
from asyncdonkey.parts.web.intake import MAX_MESSAGE_BYTES, Intake
from asyncdonkey.parts.web.video import FrameHub, encode_jpeg
from asyncdonkey.testing.i2c_models import I2CSimulator, PCA9685Model


def test_commands_are_donkeycar_messages_checked_against_the_contracts_never_clamped_or_parsed():
    c = parse_command({"angle": -1, "throttle": 0.25, "drive_mode": "local_pilot", "recording": True})
    assert (c.angle, c.throttle, c.mode, c.recording) == (-1.0, 0.25, "local", True)
    assert c.drives and not c.stop
    assert not parse_command({"stop": True}).drives
    assert parse_command({"angle": None, "throttle": None}).drives is False
    for bad, word in (
        ({"throttle": "fast"}, "throttle"),
        ({"throttle": "0.25"}, "not a number"),  # a string is not a number: no parsing at the boundary
        ({"angle": -3}, "outside"),  # refused, not clamped: 1e300 made 1.0 would be full lock
        ({"angle": float("nan")}, "NaN"),
        ({"angle": True}, "angle"),
        ({"drive_mode": "autopilot"}, "autopilot"),
        ({"recording": "yes"}, "recording"),
        ({"buttons": ["w1"]}, "buttons"),
        ({"stop": "yes"}, "stop"),
        ([1, 2], "JSON object"),
    ):
        with pytest.raises(CommandError, match=word):
            parse_command(bad)


def test_every_refused_value_is_counted_per_channel_and_reason_and_the_message_refused_whole():
    gate = Contracts().gate("web")
    intake = Intake(gate, ("user",), lambda: 0.0)
    with pytest.raises(CommandError, match=r"angle.*throttle"):
        intake.command({"angle": float("inf"), "throttle": 10**400, "recording": True})
    with pytest.raises(CommandError, match="not available here"):
        intake.command({"drive_mode": "local"})  # in the contract, not on this car
    for raw in ("", "null", "{", "[" * 5000, "[]"):  # empty, empty, not JSON, nested too deep, not an object
        with pytest.raises(CommandError):
            intake.decode(raw)
    with pytest.raises(CommandError, match="bytes"):
        intake.decode(json.dumps({"pad": "x" * MAX_MESSAGE_BYTES}))
    assert gate.counts() == {
        "user/angle": {"inf": 1},
        "user/throttle": {"range": 1},
        "user/mode": {"choice": 1},
        "web/command": {"empty": 2, "encoding": 2, "type": 1, "size": 1},
    }


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_the_controller_checks_what_clients_send_against_the_car_s_own_contracts():
    v = Vehicle()
    v.declare("user/throttle", Contract.number(-0.5, 0.5, safe=0.0))  # a car that must never go faster
    ctr = WebController(host="127.0.0.1", announce=None)
    assert ctr.gate.contracts is not v.contracts  # the defaults until it is added to a vehicle
    v.add(ctr, inputs=list(ctr.inputs), outputs=ctr.outputs)
    assert ctr.gate.contracts is v.contracts and ctr.gate.where == "web"
    with pytest.raises(CommandError, match="outside"):
        ctr.intake.command({"throttle": 0.8})
    assert ctr.refused_values == {"user/throttle": {"range": 1}}
    assert ctr.state()["refused_values"] == {"user/throttle": {"range": 1}}


def test_a_car_that_declares_no_command_contracts_still_gets_them_at_the_web_boundary():
    intake = Intake(Contracts(defaults=False).gate("web"), DRIVE_MODES, lambda: 0.0)
    with pytest.raises(CommandError, match="NaN"):
        intake.command({"throttle": float("nan")})


def test_one_driver_at_a_time_with_idle_release_and_stop_for_everyone():
    desk = Desk(idle_release_s=1.0)
    assert desk.role("a", 0.0) == "free"
    assert desk.claim("a", 0.0)
    assert desk.role("a", 0.1) == "you" and desk.role("b", 0.1) == "other"
    assert not desk.claim("b", 0.5)  # a still drives
    assert desk.claim("a", 0.9)  # a's steady commands keep it in control
    assert not desk.claim("b", 1.8)
    assert desk.refused == 2
    assert desk.claim("b", 1.9, force=True)  # stop: anyone, any time
    assert desk.role("a", 1.9) == "other"
    assert desk.release("b") and desk.role("a", 2.0) == "free"
    assert desk.claim("a", 2.0)
    assert desk.role("b", 3.0) == "free"  # a went quiet for idle_release_s
    assert desk.claim("b", 3.0)
    assert not desk.release("a")  # not a's to release
    assert desk.expire(4.5) and desk.driver is None
    with pytest.raises(WebConfigError):
        Desk(idle_release_s=0)


@pytest.fixture
def pwm():
    sim = I2CSimulator()
    sim.attach(PCA9685Model(), address=0x40, bus=1)
    buses = sim.registry(retry_delay_s=0)
    yield PWMSteering("PCA9685.1:40.1", buses=buses), PWMThrottle("PCA9685.1:40.0", buses=buses)
    buses.close_all()


def test_calibration_sets_pulses_and_neutrals_or_nothing(pwm):
    steering, throttle = pwm
    assert current_calibration(steering, throttle) == {
        "STEERING_LEFT_PWM": 460,
        "STEERING_RIGHT_PWM": 290,
        "THROTTLE_FORWARD_PWM": 500,
        "THROTTLE_STOPPED_PWM": 370,
        "THROTTLE_REVERSE_PWM": 220,
    }
    got = apply_calibration(steering, throttle, {"STEERING_LEFT_PWM": 480, "THROTTLE_STOPPED_PWM": 380})
    assert got["STEERING_LEFT_PWM"] == 480 and steering.left_pulse == 480
    assert steering.neutral_pulse == 385  # centre of 480 and 290, where shutdown leaves the wheels
    assert throttle.zero_pulse == 380 and throttle.neutral_pulse == 380
    assert throttle.safe_pulse == 380  # between drives the failsafe's stopped pulse follows the calibration
    for bad, word in (
        ({"STEERING_LEFT_PWM": 250}, "both 250"),
        ({"THROTTLE_FORWARD_PWM": 380}, "must differ"),
        ({"STEERING_RIGHT_PWM": 5000}, "0..4095"),
        ({"STEERING_RIGHT_PWM": 300.5}, "whole number"),
        ({"MM1_STEERING_MID": 1500}, "unknown setting"),
        ("460", "object"),
    ):
        with pytest.raises(CalibrationError, match=word):
            apply_calibration(steering, throttle, {"STEERING_RIGHT_PWM": 250, **bad} if isinstance(bad, dict) else bad)
        assert steering.right_pulse == 290  # checked first, then applied: a refused request changes nothing
    with pytest.raises(CalibrationError, match="steering part"):
        apply_calibration(None, throttle, {"STEERING_LEFT_PWM": 470})


def test_the_stopped_pulse_must_lie_strictly_between_reverse_and_forward(pwm):
    steering, throttle = pwm
    for zero in (500, 600, 220, 100):  # at an end point or past it, "stopped" would drive
        with pytest.raises(CalibrationError, match=r"must differ|strictly between"):
            apply_calibration(steering, throttle, {"THROTTLE_STOPPED_PWM": zero})
    with pytest.raises(CalibrationError, match="strictly between"):
        apply_calibration(steering, throttle, {"THROTTLE_FORWARD_PWM": 300})  # forward moved below stopped
    assert current_calibration(None, throttle)["THROTTLE_STOPPED_PWM"] == 370  # nothing set
    reversed_esc = {"THROTTLE_FORWARD_PWM": 220, "THROTTLE_REVERSE_PWM": 500, "THROTTLE_STOPPED_PWM": 360}
    assert apply_calibration(steering, throttle, reversed_esc)["THROTTLE_STOPPED_PWM"] == 360  # either way round
    for bad in (float("nan"), float("inf"), 10**400, "370", True):  # the gate-less path raises its own error too
        with pytest.raises(CalibrationError):
            apply_calibration(steering, throttle, {"THROTTLE_STOPPED_PWM": bad})


def test_a_calibration_is_read_back_and_a_part_that_keeps_another_value_is_an_error(pwm):
    _, throttle = pwm

    class Stubborn(PWMThrottle):
        def calibrate(self, *args, check_only=False, **kwargs):
            return super().calibrate(*args, check_only=True, **kwargs)  # checks, says yes, keeps what it had

    stubborn = Stubborn(throttle._channel)
    with pytest.raises(CalibrationError, match="read-back differs") as err:
        apply_calibration(None, stubborn, {"THROTTLE_STOPPED_PWM": 380})
    assert err.value.in_force["THROTTLE_STOPPED_PWM"] == 370  # what the page is shown: what is in force


def test_the_car_is_stopped_only_with_a_zero_command_and_the_output_at_a_stopped_pulse(pwm):
    _, throttle = pwm
    throttle.pulse = throttle.written_pulse = 370
    assert why_not_stopped(0.0, "user", throttle) is None
    assert "command is +0.20" in why_not_stopped(0.2, "user", throttle)
    throttle.pulse = throttle.written_pulse = 420  # a pilot drives while the web's own command is 0
    assert "pulse 420" in why_not_stopped(0.0, "local", throttle)
    throttle.pulse, throttle.written_pulse = 370, None  # nothing written yet (or the write failed)
    assert why_not_stopped(0.0, "user", throttle) is not None
    assert "pilot" in why_not_stopped(0.0, "local", None)  # no output to look at: the mode must be user
    throttle.pulse = throttle.written_pulse = 370
    assert "pilot" in why_not_stopped(0.0, "local", throttle)  # stopped now, but a pilot may drive at the next tick
    assert why_not_stopped(0.0, "user", None) is None


def test_calibration_values_pass_the_web_gate_and_are_counted():
    gate = Contracts().gate("web")
    intake = Intake(gate, DRIVE_MODES, lambda: 0.0)
    assert admit_config(intake, {"STEERING_LEFT_PWM": 470, "THROTTLE_STOPPED_PWM": 380.0}) == {
        "STEERING_LEFT_PWM": 470,
        "THROTTLE_STOPPED_PWM": 380,
    }
    config = {
        "THROTTLE_STOPPED_PWM": float("nan"),
        "THROTTLE_FORWARD_PWM": 10**400,
        "THROTTLE_REVERSE_PWM": "220",
        "STEERING_LEFT_PWM": 4096,
        "STEERING_RIGHT_PWM": 290.5,
        "MM1_STEERING_MID": 1500,
    }
    with pytest.raises(CalibrationError):
        admit_config(intake, config)
    with pytest.raises(CalibrationError):
        admit_config(intake, [460])
    assert gate.counts() == {
        "calibration/THROTTLE_STOPPED_PWM": {"nan": 1},
        "calibration/THROTTLE_FORWARD_PWM": {"range": 1},
        "calibration/THROTTLE_REVERSE_PWM": {"type": 1},
        "calibration/STEERING_LEFT_PWM": {"range": 1},
        "calibration/STEERING_RIGHT_PWM": {"fraction": 1},
        "web/calibration": {"unknown": 1, "type": 1},
    }


class _Drive:
    """What an actuator is attached to at a drive's start (the parts of it these tests touch)."""

    guard_last = None

    def deadline_changed(self, t: float) -> None:
        pass

    def record_latency(self, now: float, origin: float) -> None:
        pass


class _Route:
    """A PCA9685 channel's route as the safety process is given it at the drive's start (the pulse, in ticks)."""

    def safety_route(self, ticks: int) -> dict:
        return {"ticks": ticks}


def test_the_safe_pulses_are_fixed_at_the_drives_start_and_shared_by_every_safe_path():
    sim = I2CSimulator()
    pca = sim.attach(PCA9685Model(), address=0x40, bus=1)
    buses = sim.registry(retry_delay_s=0)
    steering, throttle = PWMSteering("PCA9685.1:40.1", buses=buses), PWMThrottle("PCA9685.1:40.0", buses=buses)
    throttle._channel = steering._channel = _Route()
    try:
        # the drive starts: the safety process is given its routes first, then the parts are attached
        assert throttle.safety_route() == {"ticks": pulse_to_ticks(370)}
        assert steering.safety_route() == {"ticks": pulse_to_ticks(375)}
        with pytest.raises(CalibrationLocked, match="stays 370 during a drive"):
            throttle.calibrate(zero_pulse=380)  # fixed from the route on, before the parts are attached
        steering.attach(_Drive()), throttle.attach(_Drive())
        with pytest.raises(CalibrationError, match="stays 370 during a drive") as err:
            apply_calibration(steering, throttle, {"THROTTLE_STOPPED_PWM": 380, "STEERING_LEFT_PWM": 480})
        assert (err.value.channel, err.value.reason) == ("calibration/THROTTLE_STOPPED_PWM", "armed")
        assert steering.left_pulse == 460  # refused whole: the steering half is not set either
        with pytest.raises(CalibrationLocked):
            throttle.zero_pulse = 380  # Donkeycar's attribute is the same calibration, refused the same way
        # the end points may change, and the stopped pulse may be "set" to what it is (the page sends all five)
        got = {"STEERING_LEFT_PWM": 480, "THROTTLE_REVERSE_PWM": 277, "THROTTLE_STOPPED_PWM": 370}
        assert apply_calibration(steering, throttle, got)["THROTTLE_REVERSE_PWM"] == 277
        assert throttle.map_throttle(0.0) == throttle.map_throttle(-0.0) == throttle.map_throttle(None) == 370
        assert steering.neutral_pulse == 385 and steering.safe_pulse == 375  # a zero angle maps to the new centre
        throttle.safe_state_sync()  # the watchdog's write
        steering.safe_state_sync()
        assert (pca.pulse(0), pca.pulse(1)) == (370, 375)
        assert steering.safety_route() == {"ticks": pulse_to_ticks(375)}  # asked again: still the drive's
        throttle.attach(None), steering.attach(None)  # the drive ends; the next one starts from the calibration
        assert not throttle.safe_pulse_fixed and steering.safe_pulse == 385
        throttle.calibrate(zero_pulse=380)  # between drives the stopped pulse may move, and "safe" with it
        assert throttle.safe_pulse == 380 == throttle.map_throttle(0.0)
    finally:
        buses.close_all()


def test_token_none_is_refused_unless_loopback():
    with pytest.raises(WebConfigError, match="loopback"):
        WebController(token=None)
    with pytest.raises(WebConfigError, match="loopback"):
        WebController(token=None, host="192.168.1.20")
    WebController(token=None, host="127.0.0.1")
    WebController(token=None, host="::1")
    with pytest.raises(WebConfigError, match="8 characters"):
        WebController(token="abc")


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_button_presses_are_latched_for_one_tick_as_donkeycar_does():
    ctr = WebController(host="127.0.0.1", announce=None)
    assert ctr.apply("script", Command(buttons={"w1": True, "w2": False})) == "you"
    assert ctr.run()[4] == {"w1": True}
    assert ctr.run()[4] == {"w1": False}
    assert ctr.run()[4] == {}


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_mode_and_recording_latch_over_the_inputs_then_follow_them():
    ctr = WebController(host="127.0.0.1", announce=None)
    assert ctr.run(None, 0, "user", False)[2:4] == ("user", False)
    ctr.apply("page", Command(mode="local", recording=True))
    # the page's choice wins over the (older) values the tick reads back from memory
    assert ctr.run(None, 0, "user", False)[2:4] == ("local", True)
    # after that the inputs rule again, as with Donkeycar (another part may switch modes)
    assert ctr.run(None, 0, "local_angle", False)[2:4] == ("local_angle", False)
    with pytest.raises(ValueError, match="autopilot"):
        ctr.run(None, 0, "autopilot", False)


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_stop_takes_control_zeroes_throttle_and_hands_back_from_the_pilot():
    ctr = WebController(host="127.0.0.1", announce=None, max_throttle=0.5)
    ctr.apply("driver", Command(throttle=0.8, mode="local"))
    assert ctr.run()[1:3] == (0.4, "local")  # max_throttle scales the page's throttle
    assert ctr.apply("watcher", Command(throttle=1.0)) == "other"
    assert ctr.throttle == 0.4
    assert ctr.apply("watcher", Command(stop=True)) == "you"
    assert ctr.run()[1:3] == (0.0, "user")
    assert ctr.apply("driver", Command(throttle=0.5)) == "other"


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_outputs_take_their_origin_from_the_commands_arrival():
    from asyncdonkey import get_clock

    clock = get_clock()
    ctr = WebController(host="127.0.0.1", announce=None)
    assert ctr.output_origin() is None
    await asyncio.sleep(1.0)
    ctr.apply("page", Command(angle=0.1, throttle=0.2))
    t = clock.now()
    await asyncio.sleep(0.3)
    ctr.run()
    assert ctr.output_origin() == t  # 0.3 s old: the tick does not make the command fresh
    ctr.apply("page", Command(angle=0.1, throttle=0.2))  # the page's steady resend
    assert ctr.output_origin() == clock.now()
    ctr.apply("page", Command(release=True))
    assert (ctr.throttle, ctr.output_origin()) == (0.0, clock.now())  # neutral, with the old arrival time
    await asyncio.sleep(0.5)
    assert clock.now() - ctr.output_origin() == pytest.approx(0.5)


def _frame(v: int) -> np.ndarray:
    return np.full((120, 160, 3), v, np.uint8)


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_video_hub_encodes_each_new_frame_once_for_all_viewers_and_nothing_unwatched():
    hub = FrameHub()
    runner = asyncio.create_task(hub.run())
    await asyncio.sleep(0)
    for v in range(5):
        hub.offer(_frame(v))
        await asyncio.sleep(0.05)
    assert (hub.offered, hub.encodes) == (5, 0)  # nobody watches: nothing is encoded

    got: dict[str, list[int]] = {"a": [], "b": [], "c": [], "slow": []}

    async def viewer(name: str, pause: float) -> None:
        seq = 0
        while True:
            nxt = await hub.next_after(seq)
            if nxt is None:
                return
            seq = nxt[0]
            got[name].append(seq)
            await asyncio.sleep(pause)

    hub.viewers = 4  # what four open /video streams count
    hub.offer(_frame(99))
    viewers = [asyncio.create_task(viewer(n, 0.26 if n == "slow" else 0)) for n in got]
    await asyncio.sleep(0.01)
    for v in range(20):
        frame = _frame(v)
        for _ in range(3):  # the tick sees the same frame object three times (a camera slower than the loop)
            hub.offer(frame)
            await asyncio.sleep(0.0167)
    await asyncio.sleep(0.1)
    await hub.close()
    await asyncio.gather(*viewers)
    runner.cancel()
    assert hub.offered == 5 + 1 + 20
    assert hub.encodes == 21  # each new frame once, however many viewers
    assert got["a"] == got["b"] == got["c"] == list(range(1, 22))
    slow = got["slow"]
    assert len(slow) < 10 and slow[-1] == 21  # the slow viewer skipped to the newest instead of queueing


def test_jpeg_encoding_keeps_colours_and_names_bad_frames():
    import cv2

    img = np.zeros((120, 160, 3), np.uint8)
    img[..., 0] = 250  # red in RGB
    back = cv2.imdecode(np.frombuffer(encode_jpeg(img, 90), np.uint8), cv2.IMREAD_COLOR)
    assert back.shape == (120, 160, 3) and back[60, 80, 2] > 200 and back[60, 80, 0] < 40  # BGR: red is last
    with pytest.raises(TypeError, match="uint8"):
        encode_jpeg(img.astype(np.float32), 90)
    with pytest.raises(ValueError, match="shape"):
        encode_jpeg(np.zeros((4, 4, 2), np.uint8), 90)


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_a_frame_that_cannot_be_encoded_is_skipped_logged_and_counted(caplog):
    hub = FrameHub()
    runner = asyncio.create_task(hub.run())
    await asyncio.sleep(0)
    hub.viewers = 1
    hub.offer(np.zeros((120, 160, 3), np.float32))  # not uint8
    await asyncio.sleep(0.05)
    assert (hub.encode_errors, hub.encodes, hub.seq) == (1, 0, 0)
    assert "frame could not be shown" in caplog.text and "uint8" in caplog.text
    hub.offer(_frame(7))
    await asyncio.sleep(0.05)
    assert (hub.encodes, hub.seq) == (1, 1)
    await hub.close()
    runner.cancel()


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_the_record_count_is_pushed_each_time_it_crosses_ten_even_in_a_jump():
    """The tub counts a record once it is on disk, so the count can move by two: 9 → 11 still crosses 10."""
    ctr = WebController(host="127.0.0.1", announce=None)
    pushed: list[dict] = []
    ctr.pages.broadcast = pushed.append  # type: ignore[method-assign]  # what would go to every page
    ctr.run(None, 0, "user", True)
    for n in (3, 9, 11, 12, 19, 20, 21, 33):
        ctr.run(None, n, "user", True)
    assert [p["num_records"] for p in pushed if "num_records" in p] == [11, 20, 33]
