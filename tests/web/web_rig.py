"""A car with a web controller for the web tests: a moving camera, drive mode, PCA9685 steering and ESC on a
simulated I2C bus (the chip's model shows what the pins output), and a tub writer while recording."""

from __future__ import annotations

import asyncio
import contextlib
import datetime
import ipaddress
import ssl
import threading
from pathlib import Path
from typing import Any

import numpy as np

from asyncdonkey import Vehicle
from asyncdonkey.parts.actuators import PWMSteering, PWMThrottle
from asyncdonkey.parts.control import DriveMode
from asyncdonkey.parts.tub import TubWriter
from asyncdonkey.parts.web import WebController
from asyncdonkey.testing.i2c_models import I2CSimulator, PCA9685Model

from ..waiting import await_until

STEERING_CH, THROTTLE_CH = 1, 0
ZERO_PULSE = 370


class MovingCamera:
    """A new 160x120 frame every ``every`` ticks (the same array object in between, like a slower camera):
    a bright bar that moves across a dark road, so consecutive frames differ visibly."""

    def __init__(self, every: int = 2) -> None:
        self.every = every
        self.k = 0
        self.frames = 0
        self.frame: np.ndarray | None = None

    def run(self) -> np.ndarray:
        if self.frame is None or self.k % self.every == 0:
            img = np.full((120, 160, 3), 30, np.uint8)
            x = (self.frames * 11) % 140
            img[:, x : x + 20] = (240, 200, 40)
            self.frame = img
            self.frames += 1
        self.k += 1
        return self.frame


class WebCar:
    def __init__(self, tmp_path: Path, *, camera_every: int = 2, executor: bool = False, **controller: Any) -> None:
        self.i2c = I2CSimulator()
        self.pca = self.i2c.attach(PCA9685Model(), address=0x40, bus=1)
        self.buses = self.i2c.registry(retry_delay_s=0)
        v = self.vehicle = Vehicle()
        self.camera = MovingCamera(camera_every)
        v.add(self.camera, outputs=["cam/image_array"], name="camera")
        self.steering = PWMSteering(f"PCA9685.1:40.{STEERING_CH}", buses=self.buses)
        self.throttle = PWMThrottle(f"PCA9685.1:40.{THROTTLE_CH}", buses=self.buses, arm_s=0.05)
        settings: dict[str, Any] = {"host": "127.0.0.1", "port": 0, "announce": None, "health_every_s": 0.2}
        settings.update(controller)
        self.ctr = WebController(vehicle=v, steering=self.steering, throttle=self.throttle, **settings)
        v.add(self.ctr, inputs=list(self.ctr.inputs), outputs=self.ctr.outputs, name="web", executor=executor)
        v.add(
            DriveMode(),
            inputs=["user/mode", "user/angle", "user/throttle", "pilot/angle", "pilot/throttle"],
            outputs=["angle", "throttle"],
        )
        v.add(self.steering, inputs=["angle"], name="steering")
        v.add(self.throttle, inputs=["throttle", "throttle@age"], name="throttle")
        names = ["cam/image_array", "user/angle", "user/throttle", "user/mode"]
        self.tub = TubWriter(tmp_path / "tub", inputs=names, types=["image_array", "float", "float", "str"])
        v.add(self.tub, inputs=names, outputs=["tub/num_records"], run_condition="recording", name="tub")

    @property
    def base(self) -> str:
        return f"http://127.0.0.1:{self.ctr.port}"

    @property
    def mem(self) -> Any:
        return self.vehicle.mem

    def throttle_pulse(self) -> int:
        return self.pca.pulse(THROTTLE_CH)

    def steering_pulse(self) -> int:
        return self.pca.pulse(STEERING_CH)


class CarThread:
    """The car driving in its own thread and event loop (real time), as on a Pi, while a test drives a browser."""

    def __init__(self, car: WebCar, rate_hz: float = 20) -> None:
        self.car = car
        self.error: BaseException | None = None
        self.thread = threading.Thread(target=self._main, args=(rate_hz,), name="web-test-car", daemon=True)

    def _main(self, rate_hz: float) -> None:
        try:
            asyncio.run(self.car.vehicle.run(rate_hz=rate_hz))
        except BaseException as exc:
            self.error = exc

    def __enter__(self) -> WebCar:
        self.thread.start()
        if not self.car.ctr.listening.wait(10):
            raise AssertionError(f"the web controller did not start listening: {self.error!r}")
        return self.car

    def __exit__(self, *exc: object) -> None:
        self.car.vehicle.stop()
        self.thread.join(15)
        self.car.buses.close_all()
        if self.error is not None:
            raise self.error


@contextlib.asynccontextmanager
async def driving(car: WebCar, rate_hz: float = 50):
    """The car driving on the test's own event loop (real time) while the test talks to it."""
    task = asyncio.create_task(car.vehicle.run(rate_hz=rate_hz))
    try:
        await await_until(car.ctr.listening.is_set, 10, "the server to listen")
        yield car
    finally:
        car.vehicle.stop()
        await asyncio.wait_for(task, 15)
        car.buses.close_all()


def auth(car: WebCar) -> dict[str, str]:
    """A script's way to present the car's token."""
    return {"Authorization": f"Token {car.ctr.token}"}


def self_signed(tmp_path) -> tuple[ssl.SSLContext, ssl.SSLContext]:
    """A certificate for 127.0.0.1 as the docs tell a user to make one: the server's context, and a client's
    that trusts exactly that certificate (a phone that accepted it once)."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID

    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "donkey")])
    now = datetime.datetime.now(datetime.UTC)
    cert = (
        x509.CertificateBuilder()
        .subject_name(name)
        .issuer_name(name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=1))
        .not_valid_after(now + datetime.timedelta(days=1))
        .add_extension(x509.SubjectAlternativeName([x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]), False)
        .sign(key, hashes.SHA256())
    )
    crt, pem = tmp_path / "car.crt", tmp_path / "car.key"
    crt.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    pem.write_bytes(
        key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption())
    )
    server = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
    server.load_cert_chain(crt, pem)
    return server, ssl.create_default_context(cafile=crt)
