"""examples/car_pi.py built against device models: an MJPG file as the camera, a FIFO joystick, simulated I2C."""

from pathlib import Path

import pytest

from asyncdonkey.parts.tub import Tub
from asyncdonkey.testing.camera_models import write_test_video
from asyncdonkey.testing.i2c_models import I2CSimulator, MPU6050Model, PCA9685Model
from asyncdonkey.testing.joystick_model import JoystickModel

from .example_loader import load_example


class Rig:
    def __init__(self, tmp_path: Path) -> None:
        self.sim = I2CSimulator()
        self.pca = self.sim.attach(PCA9685Model(), address=0x40, bus=1)
        self.mpu = self.sim.attach(MPU6050Model(accel_g=(0.0, 0.0, 1.0)), address=0x68, bus=1)
        self.buses = self.sim.registry(retry_delay_s=0)
        self.video = write_test_video(tmp_path / "road.avi", 40, fps=40)
        self.pad = JoystickModel(tmp_path / "js0")
        self.tub = tmp_path / "data" / "tub_1"

    def argv(self, *extra: str) -> list[str]:
        return [
            "--tub",
            str(self.tub),
            f"CAMERA_INDEX={self.video}",
            f"JOYSTICK_DEVICE_FILE={self.pad.path}",
            *extra,
        ]

    def close(self) -> None:
        self.pad.unplug()
        self.buses.close_all()


@pytest.fixture
def rig(tmp_path):
    r = Rig(tmp_path)
    yield r
    r.close()


class Driver:
    """The person holding the pad: acts between ticks, and records what the chip outputs each tick."""

    def __init__(self, rig: Rig, actions: dict) -> None:
        self.rig = rig
        self.actions = actions
        self.k = 0
        self.pulses: list[tuple[int, int]] = []

    def run(self) -> None:
        self.pulses.append((self.rig.pca.pulse(1), self.rig.pca.pulse(0)))
        action = self.actions.get(self.k)
        if action is not None:
            action()
        self.k += 1


def test_settings_override_with_donkeycar_names():
    car_pi = load_example("car_pi")
    cfg, args = car_pi.parse_args(["--model", "m.onnx", "STEERING_LEFT_PWM=470", "HAVE_IMU=false", "CAMERA_INDEX=2"])
    assert (cfg.STEERING_LEFT_PWM, cfg.HAVE_IMU, cfg.CAMERA_INDEX, args.model) == (470, False, 2, "m.onnx")
    assert cfg.PWM_STEERING_THROTTLE["STEERING_LEFT_PWM"] == 470
    with pytest.raises(ValueError, match="unknown setting 'STEERING_LEFTPWM=1'"):
        car_pi.parse_args(["STEERING_LEFTPWM=1"])
    with pytest.raises(ValueError, match="IMAGE_W='wide' is not a valid int"):
        car_pi.parse_args(["IMAGE_W=wide"])


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_car_drives_records_and_stops_on_models(rig):
    car_pi = load_example("car_pi")
    v = car_pi.build(rig.argv("JOYSTICK_DEADZONE=0.0"), buses=rig.buses)
    pad = rig.pad

    def go():
        pad.press(1)  # recording on
        pad.move_axis(0, 32767)  # full right
        pad.move_axis(4, -32767)  # full forward: JOYSTICK_MAX_THROTTLE 0.5

    driver = Driver(rig, {5: go, 35: lambda: pad.press(3)})  # 35: emergency stop
    v.add(driver, name="driver")
    report = await v.run(rate_hz=20, max_loop_count=45)
    assert report.loops == 45 and not report.part_errors

    assert driver.pulses[0] == (0, 0)  # before the first write the chip's outputs are off
    assert driver.pulses[1:7] == [(375, 370)] * 6  # centred and stopped
    # steering follows the stick at once; the ESC arming holds the stopped pulse for 1 s (20 ticks)
    assert driver.pulses[7:20] == [(290, 370)] * 13
    # then throttle 0.5 (JOYSTICK_MAX_THROTTLE): Donkeycar's map gives 435
    assert driver.pulses[22:36] == [(290, 435)] * 14
    # after the e-stop: throttle stopped, steering still follows the stick
    assert driver.pulses[37:] == [(290, 370)] * (45 - 37)
    # shutdown: centre and stopped
    assert (rig.pca.pulse(1), rig.pca.pulse(0)) == (375, 370)

    tub = Tub(rig.tub)
    rows = list(tub)
    assert len(rows) == 45 - 6  # recording on from tick 6 to the end
    assert {r["user/mode"] for r in rows} == {"user"}
    assert max(r["user/throttle"] for r in rows) == 0.5
    assert rows[-1]["user/throttle"] == 0.0  # after the e-stop
    assert rows[0]["imu/acl_z"] == pytest.approx(9.81, abs=0.05)
    image = rows[0]["cam/image_array"]
    assert image.shape == (120, 160, 3)


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_pilot_modes_without_a_model_stay_user(rig):
    car_pi = load_example("car_pi")
    v = car_pi.build(rig.argv("HAVE_IMU=false"), buses=rig.buses)
    modes = []

    class Watch:
        def run(self, mode):
            modes.append(mode)

    v.add(Driver(rig, {2: lambda: rig.pad.click(0)}), name="driver")
    v.add(Watch(), inputs=["user/mode"])
    await v.run(rate_hz=20, max_loop_count=6)
    assert modes == ["user"] * 6


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_with_a_model_the_mode_button_hands_steering_to_the_pilot(rig):
    car_pi = load_example("car_pi")
    model = str(Path(__file__).resolve().parents[2] / "examples" / "models" / "sim_pilot.onnx")
    v = car_pi.build(rig.argv("HAVE_IMU=false", "--model", model), buses=rig.buses)
    seen = []

    class Watch:
        def run(self, mode, run_pilot, pilot_angle, angle, user_throttle, throttle):
            seen.append((mode, bool(run_pilot), pilot_angle, angle, user_throttle, throttle))

    def stick():
        rig.pad.move_axis(0, -32767)  # the user steers full left
        rig.pad.move_axis(4, -16384)  # and opens the throttle a little

    v.add(Driver(rig, {1: stick, 4: lambda: rig.pad.click(0)}), name="driver")  # A: user -> local_angle
    v.add(
        Watch(),
        inputs=["user/mode", "run_pilot", "pilot/angle", "angle", "user/throttle", "throttle"],
    )
    await v.run(rate_hz=20, max_loop_count=10)
    before = [s for s in seen if s[0] == "user"]
    after = [s for s in seen if s[0] == "local_angle"]
    assert before and after
    assert all(not s[1] and s[2] is None for s in before)  # no inference while the user drives
    assert all(s[3] == -1.0 for s in before[2:])  # the stick's full left
    for _mode, run_pilot, pilot_angle, angle, user_throttle, throttle in after:
        assert run_pilot and pilot_angle is not None
        assert angle == pilot_angle != -1.0  # steering from the pilot
        assert throttle == user_throttle > 0  # throttle still the user's
