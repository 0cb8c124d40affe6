"""Loopback Zenoh sessions for the bridge tests: 127.0.0.1 only, a free port per test, no multicast scouting."""

from __future__ import annotations

import math
import socket
import time

from asyncdonkey import Vehicle
from asyncdonkey.parts.actuators import PWMThrottle
from asyncdonkey.parts.zenoh import ZenohLink, ZenohPublisher, ZenohSubscriber, zenoh_config
from asyncdonkey.testing.i2c_models import I2CSimulator, PCA9685Model


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def listener(port: int):
    return zenoh_config(mode="peer", listen=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False)


def connector(port: int, mode: str = "client"):
    return zenoh_config(mode=mode, connect=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False)


class RemotePilot:
    """Publishes a throttle of 0.5 from the remote session each tick for ``seconds``, then goes quiet."""

    def __init__(self, pub: ZenohPublisher, seconds: float = math.inf) -> None:
        self.pub = pub
        self.seconds = seconds
        self.t0: float | None = None

    def run(self) -> None:
        now = time.monotonic()
        self.t0 = self.t0 or now
        if now - self.t0 < self.seconds:
            self.pub.run(0.5, 0.0)


class PulseProbe:
    """Each tick: when, the throttle pulse on the PCA9685 model's channel 0, and the command's age."""

    def __init__(self, pca: PCA9685Model) -> None:
        self.pca = pca
        self.rows: list[tuple[float, int, float]] = []

    def run(self, age):
        self.rows.append((time.monotonic(), self.pca.pulse(0), math.inf if age is None else age))


class RemotePilotCar:
    """A car driven over ``car_link`` by a :class:`RemotePilot` on ``pilot_link`` (``seconds`` long): its
    ``PWMThrottle`` (failsafe at 250 ms) on a PCA9685 model, and a :class:`PulseProbe` reading the chip."""

    def __init__(self, car_link: ZenohLink, pilot_link: ZenohLink, seconds: float = math.inf) -> None:
        sim = I2CSimulator()
        pca = sim.attach(PCA9685Model(), address=0x40, bus=1)
        self.buses = sim.registry(retry_delay_s=0)
        self.vehicle = v = Vehicle()
        self.probe = PulseProbe(pca)
        v.add(self.probe, inputs=["pilot/throttle@age"])
        self.pilot = RemotePilot(ZenohPublisher(pilot_link, ["pilot/throttle"]), seconds)
        v.add(self.pilot)
        self.commands = ZenohSubscriber(car_link, ["pilot/throttle"])
        v.add(self.commands, outputs=["pilot/throttle"])
        self.throttle = PWMThrottle("PCA9685.1:40.0", buses=self.buses, arm_s=0, failsafe_age_s=0.25)
        v.add(self.throttle, inputs=["pilot/throttle", "pilot/throttle@age"])

    async def drive(self, ticks: int) -> None:
        """``ticks`` at 50 Hz, then the I2C buses closed."""
        try:
            await self.vehicle.run(rate_hz=50, max_loop_count=ticks)
        finally:
            self.buses.close_all()
