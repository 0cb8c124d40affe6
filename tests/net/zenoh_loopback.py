"""Loopback Zenoh sessions for the bridge tests: 127.0.0.1 only, a free port per test, no multicast scouting."""

from __future__ import annotations

import asyncio
import math
import socket
import time
from collections.abc import Callable

from asyncdonkey.parts.zenoh import ZenohPublisher, zenoh_config
from asyncdonkey.testing.i2c_models import PCA9685Model


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def listener(port: int):
    return zenoh_config(mode="peer", listen=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False)


def connector(port: int, mode: str = "client"):
    return zenoh_config(mode=mode, connect=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False)


async def until(cond: Callable[[], bool], timeout: float = 5.0) -> bool:
    """Poll ``cond`` until true or ``timeout`` seconds (network arrival is asynchronous), letting tasks run."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if cond():
            return True
        await asyncio.sleep(0.005)
    return cond()


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
