"""Testing support: a virtual-clock event loop, a pytest plugin and device models for ``asyncdonkey.hw``.

The pytest plugin is registered through the ``pytest11`` entry point, so installing asyncdonkey makes the
``virtual_clock`` marker and fixture, and checked mode (``asyncdonkey_checked = true`` in a project's pytest ini,
or the ``asyncdonkey_checked`` marker), available to any project's tests; a project that asks for neither runs
as it would without asyncdonkey (``pytest_plugin``'s docstring, docs/testing.md).

Device models behave like the hardware at the register or byte level, so the real drivers run against them:

* ``i2c_models``: ``I2CSimulator`` with ``PCA9685Model`` and ``MPU6050Model`` behind the real smbus2 API,
  with fault injection (NACK, ``OSError``);
* ``serial_peers``: pseudo-terminal peers (``EncoderPeer``, ``NmeaPeer``, ``RPLidarPeer``) that can be
  unplugged and plugged back;
* ``camera_models``: synthetic MJPG videos and image folders with frame numbers encoded in the pixels;
* ``joystick_model``: ``JoystickModel``, a FIFO emitting Linux joystick events;
* ``picamera2_model``: ``Picamera2Model``, the picamera2 interface of a Raspberry Pi camera (requests, a finite
  buffer pool, ``SensorTimestamp``, stalls and unplugging).

They are importable from here by name; each module loads on first use (OpenCV, for one, is not imported by
a test that only needs the virtual clock).
"""

from __future__ import annotations

import importlib
from typing import Any

from ..clock.virtual_loop import (
    VirtualClockBudgetExceeded,
    VirtualClockDeadlock,
    VirtualClockError,
    VirtualClockLivelock,
    VirtualClockLoop,
    VirtualClockStall,
    virtual_loop_factory,
)

_LAZY = {
    "i2c_models": (
        "I2CDeviceModel",
        "I2CMessage",
        "I2CSimulator",
        "I2CTransfer",
        "MPU6050Model",
        "PCA9685Model",
        "RegisterDeviceModel",
        "RemoteI2CSimulator",
        "SimulatedI2CBus",
        "SimulatedSMBus",
    ),
    "serial_peers": (
        "EncoderPeer",
        "LinePeer",
        "NmeaPeer",
        "PtyPeer",
        "RPLidarPeer",
        "SimulatedWheel",
        "nmea_sentence",
    ),
    "camera_models": ("FRAME_BITS", "make_frame_bgr", "frame_number", "write_image_folder", "write_test_video"),
    "joystick_model": ("JoystickModel",),
    "picamera2_model": ("Picamera2Model", "Picamera2ModelHang"),
}
_WHERE = {name: module for module, names in _LAZY.items() for name in names}

__all__ = [
    "VirtualClockBudgetExceeded",
    "VirtualClockDeadlock",
    "VirtualClockError",
    "VirtualClockLivelock",
    "VirtualClockLoop",
    "VirtualClockStall",
    "virtual_loop_factory",
    *sorted(_WHERE),
]


def __getattr__(name: str) -> Any:
    module = _WHERE.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f".{module}", __name__), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_WHERE))
