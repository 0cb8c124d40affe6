"""Loopback Zenoh sessions for the bridge tests: 127.0.0.1 only, a free port per test, no multicast scouting."""

from __future__ import annotations

import asyncio
import socket
import time
from collections.abc import Callable

from asyncdonkey.parts.zenoh import zenoh_config


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
