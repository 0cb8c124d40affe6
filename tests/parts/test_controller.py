"""JoystickController: mapping, deadzone, mode cycling, recording, e-stop, unplug, and driving a Vehicle."""

import asyncio

import pytest

from asyncdonkey import Vehicle
from asyncdonkey.parts.controller import JoystickController, JoystickMapping, shape_axis
from asyncdonkey.testing.joystick_model import JoystickModel

STEER, THROTTLE, MODE_BTN, REC_BTN, ESTOP_BTN = 0, 4, 0, 1, 3


@pytest.fixture
def pad(tmp_path):
    m = JoystickModel(tmp_path / "js0")
    yield m
    m.unplug()


async def started(ctr: JoystickController) -> JoystickController:
    ctr.reader.open()
    await asyncio.sleep(0.05)
    return ctr


async def settle():
    await asyncio.sleep(0.05)


def test_shape_axis_deadzone_inversion_scale():
    assert shape_axis(0.04, 0.05, False, 1.0) == 0.0
    assert shape_axis(-0.05, 0.05, False, 1.0) == 0.0
    assert shape_axis(1.0, 0.05, False, 1.0) == 1.0
    assert shape_axis(0.525, 0.05, False, 1.0) == pytest.approx(0.5)  # stretched beyond the deadzone
    assert shape_axis(-1.0, 0.0, True, 0.5) == 0.5
    assert shape_axis(1.2, 0.0, False, 1.0) == 1.0


def test_mapping_rejects_shared_buttons_and_bad_deadzone():
    with pytest.raises(ValueError, match="must differ"):
        JoystickMapping(mode_button=2, estop_button=2)
    with pytest.raises(ValueError, match="deadzone"):
        JoystickMapping(deadzone=1.0)


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_axes_scale_by_1_over_32767_with_deadzone_and_inverted_throttle(pad):
    ctr = await started(JoystickController(str(pad.path), JoystickMapping(deadzone=0.0)))
    pad.move_axis(STEER, 32767)
    pad.move_axis(THROTTLE, -16384)  # stick pushed up half way
    await settle()
    angle, throttle, mode, rec = ctr.run()
    assert angle == 1.0
    assert throttle == pytest.approx(16384 / 32767)
    assert (mode, rec) == ("user", False)
    ctr.shutdown()


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_deadzone_and_max_throttle(pad):
    ctr = await started(JoystickController(str(pad.path), JoystickMapping(deadzone=0.1), max_throttle=0.5))
    pad.move_axis(STEER, 3000)  # 0.0916: inside the deadzone
    pad.move_axis(THROTTLE, -32767)
    await settle()
    angle, throttle, _, _ = ctr.run()
    assert angle == 0.0
    assert throttle == 0.5
    pad.move_axis(STEER, -32767)
    await settle()
    assert ctr.run()[0] == -1.0
    ctr.shutdown()


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_mode_button_cycles_user_local_angle_local(pad):
    ctr = await started(JoystickController(str(pad.path)))
    modes = []
    for _ in range(4):
        pad.click(MODE_BTN)  # press and release between two reads: still exactly one step
        await settle()
        modes.append(ctr.run()[2])
    assert modes == ["local_angle", "local", "user", "local_angle"]
    ctr.shutdown()


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_recording_toggles_on_press_not_release(pad):
    ctr = await started(JoystickController(str(pad.path)))
    pad.press(REC_BTN)
    await settle()
    assert ctr.run()[3] is True
    pad.release(REC_BTN)
    await settle()
    assert ctr.run()[3] is True
    pad.click(REC_BTN)
    await settle()
    assert ctr.run()[3] is False
    ctr.shutdown()


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_init_events_do_not_count_as_presses(tmp_path):
    model = JoystickModel(tmp_path / "js0", plugged=False)
    model.buttons[MODE_BTN] = True  # held while the device is opened
    model.buttons[REC_BTN] = True
    model.plug()
    ctr = await started(JoystickController(str(model.path)))
    assert ctr.run()[2:] == ("user", False)
    ctr.shutdown()
    model.unplug()


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_emergency_stop_forces_throttle_zero_and_user_mode_until_stick_is_neutral(pad):
    ctr = await started(JoystickController(str(pad.path), JoystickMapping(deadzone=0.05)))
    pad.click(MODE_BTN)
    pad.click(MODE_BTN)
    pad.move_axis(THROTTLE, -32767)
    await settle()
    assert ctr.run()[1:3] == (1.0, "local")
    pad.press(ESTOP_BTN)
    await settle()
    assert ctr.run()[1:3] == (0.0, "user")
    pad.click(MODE_BTN)  # the mode button is ignored while stopped
    pad.release(ESTOP_BTN)
    await settle()
    assert ctr.run()[1:3] == (0.0, "user")  # released, but the stick is still full forward
    pad.move_axis(THROTTLE, 0)
    await settle()
    assert ctr.estop is False
    pad.move_axis(THROTTLE, -16384)
    await settle()
    assert ctr.run()[1] > 0.4
    assert ctr.estop_events == 1
    ctr.shutdown()


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_unplug_goes_neutral_and_user(pad):
    ctr = await started(JoystickController(str(pad.path), reconnect_s=0.2))
    pad.move_axis(STEER, -20000)
    pad.move_axis(THROTTLE, -30000)
    pad.click(MODE_BTN)
    pad.click(REC_BTN)
    await settle()
    angle, throttle, mode, rec = ctr.run()
    assert angle < -0.5 and throttle > 0.8 and mode == "local_angle" and rec is True
    pad.unplug()
    await settle()
    assert ctr.run() == (0.0, 0.0, "user", False)
    assert not ctr.connected
    pad.axes[THROTTLE] = 0  # the throttle stick was let go while unplugged; steering is still held left
    pad.plug()
    await asyncio.sleep(0.3)
    assert ctr.connected
    # the replugged pad's init events report where the sticks are; mode and recording stay reset
    assert ctr.run() == (shape_axis(-20000 / 32767, 0.05, False, 1.0), 0.0, "user", False)
    ctr.shutdown()


class Recorder:
    def __init__(self):
        self.rows = []

    def run(self, angle, throttle, mode, recording):
        self.rows.append((angle, throttle, mode, recording))


class Script:
    """Acts on the pad at given ticks, as a driver would between two ticks."""

    def __init__(self, actions):
        self.actions = dict(actions)
        self.k = 0

    def run(self):
        action = self.actions.get(self.k)
        if action is not None:
            action()
        self.k += 1


@pytest.mark.asyncio
@pytest.mark.virtual_clock
@pytest.mark.parametrize("threaded", [False, True])
async def test_vehicle_drives_with_the_controller(pad, threaded):
    ctr = JoystickController(str(pad.path))
    rec = Recorder()
    v = Vehicle()
    v.add(
        Script(
            {
                2: lambda: pad.move_axis(THROTTLE, -32767),
                4: lambda: pad.click(MODE_BTN),
                6: lambda: pad.unplug(),
            }
        ),
        name="driver",
    )
    v.add(ctr, outputs=ctr.outputs, threaded=threaded)
    v.add(rec, inputs=ctr.outputs)
    report = await v.run(rate_hz=20, max_loop_count=9)
    assert report.loops == 9
    assert report.elapsed_s == pytest.approx(8 / 20, abs=1e-9)  # the reader never delays a tick
    throttles = [r[1] for r in rec.rows]
    modes = [r[2] for r in rec.rows]
    # The script writes during tick k; the loop reads the bytes before tick k+1.
    assert throttles == [0.0, 0.0, 0.0, 1.0, 1.0, 1.0, 1.0, 0.0, 0.0]
    assert modes == ["user"] * 5 + ["local_angle"] * 2 + ["user"] * 2
    assert not ctr.connected


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_a_held_stick_is_fresh_and_an_unplugged_pad_ages(pad):
    """A held stick sends no events yet the command is current; once unplugged, the commands age from then."""
    ctr = JoystickController(str(pad.path))

    class Ages:
        def __init__(self):
            self.rows = []

        def run(self, age):
            self.rows.append(age)

    ages = Ages()
    v = Vehicle()
    v.add(Script({2: lambda: pad.move_axis(THROTTLE, -32767), 10: lambda: pad.unplug()}), name="driver")
    v.add(ctr, outputs=ctr.outputs)
    v.add(ages, inputs=["user/throttle@age"])
    await v.run(rate_hz=20, max_loop_count=20)
    assert ages.rows[:11] == [0.0] * 11  # held from tick 3 on: no events, still fresh
    unplugged = ages.rows[11:]
    # the reader notices the unplug before tick 11; from then the commands age by one period per tick
    assert unplugged == pytest.approx([0.05 * (k + 1) for k in range(len(unplugged))])
