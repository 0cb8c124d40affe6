"""A Raspberry Pi donkey car: camera, gamepad, optional ONNX or TFLite pilot, PCA9685 steering and ESC, IMU, recording.

Run it with::

    asyncdonkey run examples/car_pi.py                                  # drive by hand, record with B
    asyncdonkey run examples/car_pi.py -- --web                         # drive from a phone's browser instead
    asyncdonkey run examples/car_pi.py -- --model models/pilot.onnx     # A cycles user / local_angle / local
    asyncdonkey run examples/car_pi.py -- --camera picamera2 --web      # the CSI camera (libcamera), a phone
    asyncdonkey run examples/car_pi.py -- STEERING_LEFT_PWM=470 CAMERA_INDEX=1 HAVE_IMU=false

Settings use Donkeycar's config names (see :class:`PiCarConfig` and ``docs/car-pi.md``); any of them can be
overridden after ``--`` as ``NAME=VALUE``. ``--camera`` picks the camera: ``opencv`` (the default: a USB camera,
a ``/dev/video*`` device or a video file), ``picamera2`` (the Raspberry Pi camera on its ribbon, through
libcamera; setup in ``docs/raspberry-pi.md``) or ``none``. The parts, in tick order::

    CvCamera/PiCamera   -> cam/image_array                                         (not with --camera none)
    JoystickController  -> user/angle, user/throttle, user/mode, recording
      or WebController  cam/image_array, tub/num_records, user/mode, recording       (--web)
                        -> user/angle, user/throttle, user/mode, recording, web/buttons
    PilotCondition      user/mode -> run_pilot                                     (with --model)
    pilot (load_pilot)  cam/image_array -> pilot/angle, pilot/throttle             (with --model, run_pilot)
    DriveMode           user/mode, user/*, pilot/* -> angle, throttle
    PWMSteering         angle
    PWMThrottle         throttle, throttle@age  (stopped when the command is older than 0.25 s)
    IMU                 -> imu/acl_*, imu/gyr_*                                    (HAVE_IMU)
    TubWriter           cam/image_array, user/*, imu/* -> tub/num_records          (while recording)
"""

import argparse
import dataclasses
import os
from dataclasses import dataclass
from typing import Any

from asyncdonkey import Vehicle
from asyncdonkey.parts.actuators import PWMSteering, PWMThrottle
from asyncdonkey.parts.camera import CvCamera
from asyncdonkey.parts.control import DRIVE_MODES, DriveMode, PilotCondition
from asyncdonkey.parts.controller import JoystickController, JoystickMapping
from asyncdonkey.parts.imu import IMU
from asyncdonkey.parts.picamera import PiCamera
from asyncdonkey.parts.tub import TubWriter

DRIVE_LOOP_HZ = 20
CAMERAS = ("opencv", "picamera2", "none")


@dataclass
class PiCarConfig:
    """The car's settings, named as in Donkeycar's ``config.py`` / ``myconfig.py``."""

    # camera (the loop rate is DRIVE_LOOP_HZ at module level, 20; `asyncdonkey run --hz N` overrides it)
    CAMERA_INDEX: int | str = 0  # device index, /dev/video* path, or a video file (replays it); picamera2: number
    IMAGE_W: int = 160
    IMAGE_H: int = 120
    IMAGE_DEPTH: int = 3
    CAMERA_FRAMERATE: int = 20  # picamera2: the camera's rate; opencv: pacing of a video file
    CAMERA_LOOP: bool = True  # a video file restarts at its end (False: the drive stops there)
    CAMERA_VFLIP: bool = False  # picamera2: flip the picture (a camera mounted upside down: both)
    CAMERA_HFLIP: bool = False
    # joystick
    JOYSTICK_DEVICE_FILE: str = "/dev/input/js0"
    JOYSTICK_MAX_THROTTLE: float = 0.5
    JOYSTICK_STEERING_SCALE: float = 1.0
    JOYSTICK_DEADZONE: float = 0.01
    JOYSTICK_STEERING_AXIS: int = 0
    JOYSTICK_THROTTLE_AXIS: int = 4
    JOYSTICK_THROTTLE_INVERTED: bool = True
    JOYSTICK_MODE_BUTTON: int = 0
    JOYSTICK_RECORD_BUTTON: int = 1
    JOYSTICK_ESTOP_BUTTON: int = 3
    # controller: the gamepad (--js, the default here) or the web page (--web)
    USE_JOYSTICK_AS_DEFAULT: bool = True
    WEB_CONTROL_PORT: int = 8887
    WEB_INIT_MODE: str = "user"
    # PWM steering and throttle (PCA9685)
    PWM_STEERING_PIN: str = "PCA9685.1:40.1"
    PWM_STEERING_SCALE: float = 1.0
    PWM_STEERING_INVERTED: bool = False
    STEERING_LEFT_PWM: int = 460
    STEERING_RIGHT_PWM: int = 290
    PWM_THROTTLE_PIN: str = "PCA9685.1:40.0"
    PWM_THROTTLE_SCALE: float = 1.0
    PWM_THROTTLE_INVERTED: bool = False
    THROTTLE_FORWARD_PWM: int = 500
    THROTTLE_STOPPED_PWM: int = 370
    THROTTLE_REVERSE_PWM: int = 220
    # IMU
    HAVE_IMU: bool = True
    IMU_SENSOR: str = "mpu6050"
    IMU_ADDRESS: int = 0x68
    IMU_DLP_CONFIG: int = 0
    # pilot and recording
    AI_THROTTLE_MULT: float = 1.0
    DATA_PATH: str = "data"

    @property
    def PWM_STEERING_THROTTLE(self) -> dict[str, Any]:
        """The dict Donkeycar's ``PWM_STEERING_THROTTLE`` drive train reads (``from_config`` takes it)."""
        names = [
            "PWM_STEERING_PIN",
            "PWM_STEERING_SCALE",
            "PWM_STEERING_INVERTED",
            "STEERING_LEFT_PWM",
            "STEERING_RIGHT_PWM",
            "PWM_THROTTLE_PIN",
            "PWM_THROTTLE_SCALE",
            "PWM_THROTTLE_INVERTED",
            "THROTTLE_FORWARD_PWM",
            "THROTTLE_STOPPED_PWM",
            "THROTTLE_REVERSE_PWM",
        ]
        return {n: getattr(self, n) for n in names}

    def override(self, assignment: str) -> None:
        """Apply one ``NAME=VALUE`` from the command line, converting VALUE to the setting's type."""
        name, sep, text = assignment.partition("=")
        name = name.strip().upper()
        if name == "JOYSTICK_DEVICE":
            name = "JOYSTICK_DEVICE_FILE"
        fields = {f.name: f for f in dataclasses.fields(self)}
        if not sep or name not in fields:
            known = ", ".join(sorted(fields))
            raise ValueError(f"car_pi: unknown setting {assignment!r}; expected NAME=VALUE with NAME one of: {known}")
        current = getattr(self, name)
        setattr(self, name, _convert(name, text.strip(), current))


def _convert(name: str, text: str, current: Any) -> Any:
    try:
        if isinstance(current, bool):
            if text.lower() in ("1", "true", "yes", "on"):
                return True
            if text.lower() in ("0", "false", "no", "off"):
                return False
            raise ValueError(text)
        if name == "CAMERA_INDEX":
            return int(text) if text.isdigit() else text
        if isinstance(current, int):
            return int(text, 0)
        if isinstance(current, float):
            return float(text)
    except ValueError:
        raise ValueError(f"car_pi: {name}={text!r} is not a valid {type(current).__name__}") from None
    return text


def parse_args(argv: list[str] | None) -> tuple[PiCarConfig, argparse.Namespace]:
    parser = argparse.ArgumentParser(prog="car_pi.py", description="Raspberry Pi donkey car")
    parser.add_argument("--model", help="pilot model, .onnx or .tflite (enables the local_angle and local modes)")
    parser.add_argument("--tub", help="record into this tub (default: DATA_PATH)")
    parser.add_argument(
        "--camera",
        choices=CAMERAS,
        default="opencv",
        help="opencv: USB camera, /dev/video* or a video file (CAMERA_INDEX); picamera2: the Pi's ribbon camera "
        "through libcamera; none: no camera (no pilot, no images recorded)",
    )
    which = parser.add_mutually_exclusive_group()
    which.add_argument("--js", action="store_true", help="drive with the gamepad (USE_JOYSTICK_AS_DEFAULT)")
    which.add_argument("--web", action="store_true", help="drive from a browser (prints the URL with its token)")
    parser.add_argument(
        "--token-file",
        metavar="PATH",
        help="with --web: keep the access token in this file (made on first start, owner-only) so the phone's "
        "bookmark survives restarts; default: a new token at every start",
    )
    parser.add_argument("settings", nargs="*", metavar="NAME=VALUE", help="override a setting (Donkeycar names)")
    args = parser.parse_args(argv or [])
    cfg = PiCarConfig()
    for s in args.settings:
        cfg.override(s)
    if args.token_file and not (args.web or (cfg.USE_JOYSTICK_AS_DEFAULT is False and not args.js)):
        parser.error("--token-file is for the web controller: add --web")
    if args.camera == "none" and args.model:
        parser.error("--model needs a camera: the pilot drives from cam/image_array (use --camera opencv or picamera2)")
    if args.camera == "picamera2" and not isinstance(cfg.CAMERA_INDEX, int):
        parser.error(f"--camera picamera2 takes a camera number as CAMERA_INDEX, got {cfg.CAMERA_INDEX!r}")
    return cfg, args


def build(
    argv: list[str] | None = None,
    *,
    buses: Any = None,
    cfg: PiCarConfig | None = None,
    camera_options: dict[str, Any] | None = None,
) -> Vehicle:
    """Build the car. ``buses`` is an I2C bus registry (tests pass a simulated one; default: the real buses);
    ``camera_options`` are more keyword arguments for the camera part (tests give ``PiCamera`` a picamera2 model's
    module and sensor clock)."""
    parsed_cfg, args = parse_args(argv)
    cfg = cfg or parsed_cfg
    v = Vehicle()

    if args.camera == "picamera2":
        camera: Any = PiCamera(
            cfg.IMAGE_W,
            cfg.IMAGE_H,
            cfg.IMAGE_DEPTH,
            vflip=cfg.CAMERA_VFLIP,
            hflip=cfg.CAMERA_HFLIP,
            framerate=cfg.CAMERA_FRAMERATE,
            camera_num=int(cfg.CAMERA_INDEX),
            **(camera_options or {}),
        )
        v.add(camera, outputs=["cam/image_array"], name="camera")
    elif args.camera == "opencv":
        camera = CvCamera(
            cfg.IMAGE_W,
            cfg.IMAGE_H,
            cfg.IMAGE_DEPTH,
            iCam=cfg.CAMERA_INDEX,
            framerate=cfg.CAMERA_FRAMERATE,
            loop=cfg.CAMERA_LOOP,
            on_end=v.stop,
            **(camera_options or {}),
        )
        v.add(camera, outputs=["cam/image_array"], threaded=True, name="camera")

    steering = PWMSteering.from_config(cfg, buses=buses)
    throttle = PWMThrottle.from_config(cfg, buses=buses)
    # Without a pilot there is nobody to hand the wheel to: the mode stays "user".
    modes = DRIVE_MODES if args.model else ("user",)
    if args.web or (cfg.USE_JOYSTICK_AS_DEFAULT is False and not args.js):
        from asyncdonkey.parts.web import NEW_TOKEN, WebController
        from asyncdonkey.parts.web.auth import token_from_file

        web = WebController(
            cfg.WEB_CONTROL_PORT,
            cfg.WEB_INIT_MODE,
            modes=modes,
            vehicle=v,
            steering=steering,
            throttle=throttle,
            token=token_from_file(args.token_file) if args.token_file else NEW_TOKEN,
        )
        v.add(web, inputs=web.inputs, outputs=web.outputs, name="web")
    else:
        mapping = JoystickMapping(
            steering_axis=cfg.JOYSTICK_STEERING_AXIS,
            throttle_axis=cfg.JOYSTICK_THROTTLE_AXIS,
            invert_throttle=cfg.JOYSTICK_THROTTLE_INVERTED,
            steering_scale=cfg.JOYSTICK_STEERING_SCALE,
            deadzone=cfg.JOYSTICK_DEADZONE,
            mode_button=cfg.JOYSTICK_MODE_BUTTON,
            record_button=cfg.JOYSTICK_RECORD_BUTTON,
            estop_button=cfg.JOYSTICK_ESTOP_BUTTON,
            modes=modes,
        )
        controller = JoystickController(cfg.JOYSTICK_DEVICE_FILE, mapping, max_throttle=cfg.JOYSTICK_MAX_THROTTLE)
        v.add(controller, outputs=controller.outputs, name="joystick")

    if args.model:
        from asyncdonkey.parts.pilot import load_pilot

        v.add(PilotCondition(), inputs=["user/mode"], outputs=["run_pilot"])
        v.add(
            load_pilot(args.model),
            inputs=["cam/image_array"],
            outputs=["pilot/angle", "pilot/throttle"],
            run_condition="run_pilot",
            name="pilot",
        )
    v.add(
        DriveMode(ai_throttle_mult=cfg.AI_THROTTLE_MULT),
        inputs=["user/mode", "user/angle", "user/throttle", "pilot/angle", "pilot/throttle"],
        outputs=["angle", "throttle"],
    )
    v.add(steering, inputs=["angle"], name="steering")
    v.add(throttle, inputs=["throttle", "throttle@age"], name="throttle")

    inputs = ["user/angle", "user/throttle", "user/mode"]
    types = ["float", "float", "str"]
    if args.camera != "none":
        inputs.insert(0, "cam/image_array")
        types.insert(0, "image_array")
    if cfg.HAVE_IMU:
        imu = IMU(cfg.IMU_ADDRESS, sensor=cfg.IMU_SENSOR, dlp_setting=cfg.IMU_DLP_CONFIG, buses=buses)
        v.add(imu, outputs=imu.outputs, name="imu")
        inputs += imu.outputs
        types += ["float"] * len(imu.outputs)

    tub_path = args.tub or cfg.DATA_PATH
    os.makedirs(os.path.dirname(os.path.abspath(tub_path)), exist_ok=True)
    writer = TubWriter(tub_path, inputs=inputs, types=types, metadata=["car:car_pi"])
    v.add(writer, inputs=inputs, outputs=["tub/num_records"], run_condition="recording", name="tub")
    return v
