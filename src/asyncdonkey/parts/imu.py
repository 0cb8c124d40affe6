"""IMU part (MPU6050 / MPU9250) with Donkeycar's outputs, polled at its own rate off the loop thread.

Donkeycar's ``IMU`` polls in a thread that sleeps ``poll_delay`` after each read (so it drifts) and shares
three dicts with ``run_threaded`` unprotected. Here a :class:`~asyncdonkey.poller.Poller` reads the chip on
its own deadline schedule in a worker thread (one 14-byte burst per sample) and publishes each sample with
its timestamp; ``run()`` returns the newest one without waiting. Read errors are counted and logged
(rate-limited), never raised into the tick.

Outputs, in order (:attr:`IMU.outputs` lists them for ``Vehicle.add``): ``imu/acl_x, imu/acl_y, imu/acl_z``
(m/s²), ``imu/gyr_x, imu/gyr_y, imu/gyr_z`` (°/s), then ``imu/temp`` (°C) with ``temperature=True`` and
``imu/timestamp`` (runtime clock seconds of the sample) with ``timestamp=True``. Before the first sample
``run()`` returns ``None`` and nothing is written (Donkeycar reports zeros, which look like a real reading).
"""

from __future__ import annotations

import logging
from typing import Any

from ..hw.i2c import I2CBusRegistry, get_bus
from ..hw.mpu6050 import MPU6050, IMUSample
from ..latest import Sample
from ..poller import Poller

__all__ = ["IMU", "IMU_OUTPUTS", "SENSOR_MPU6050", "SENSOR_MPU9250"]

logger = logging.getLogger(__name__)

SENSOR_MPU6050 = "mpu6050"
SENSOR_MPU9250 = "mpu9250"
IMU_OUTPUTS = ("imu/acl_x", "imu/acl_y", "imu/acl_z", "imu/gyr_x", "imu/gyr_y", "imu/gyr_z")
#: Donkeycar's ranges: the mpu6050 library leaves the power-on ±2 g / ±250 °/s, its MPU9250 path sets
#: ±4 g / ±1000 °/s.
DEFAULT_RANGES = {SENSOR_MPU6050: (2, 250), SENSOR_MPU9250: (4, 1000)}


class IMU:
    """MPU6050/MPU9250 part. Constructor names follow Donkeycar's (``IMU_ADDRESS``, ``IMU_SENSOR``,
    ``IMU_DLP_CONFIG``); ``poll_delay`` 0.0166 s is about 60 Hz.

    Args:
        addr: I2C address (0x68, or 0x69 with AD0 high).
        poll_delay: seconds between samples (the poll rate is ``1 / poll_delay``).
        sensor: ``"mpu6050"`` or ``"mpu9250"``; picks the default ranges. The chip's WHO_AM_I decides how
            it is read; a mismatch is logged.
        dlp_setting: the digital low-pass filter (CONFIG register, 0..6).
        busnum: I2C bus number (1 on a Raspberry Pi).
        buses: the bus registry to open ``busnum`` from (default: real buses; tests pass a simulated one).
        device: a ready :class:`~asyncdonkey.hw.mpu6050.MPU6050` driver instead of opening one.
        accel_range_g, gyro_range_dps: full-scale ranges (default: Donkeycar's for the sensor).
        temperature, timestamp: also output ``imu/temp`` and ``imu/timestamp``.
    """

    def __init__(
        self,
        addr: int = 0x68,
        poll_delay: float = 0.0166,
        sensor: str = SENSOR_MPU6050,
        dlp_setting: int = 0,
        *,
        busnum: int = 1,
        buses: I2CBusRegistry | None = None,
        device: MPU6050 | None = None,
        accel_range_g: int | None = None,
        gyro_range_dps: int | None = None,
        temperature: bool = False,
        timestamp: bool = False,
    ) -> None:
        if sensor not in DEFAULT_RANGES:
            raise ValueError(f"IMU: sensor (IMU_SENSOR) must be 'mpu6050' or 'mpu9250', got {sensor!r}")
        if not (isinstance(poll_delay, int | float) and poll_delay > 0):
            raise ValueError(f"IMU: poll_delay must be a positive number of seconds, got {poll_delay!r}")
        if device is None:
            acc, gyr = DEFAULT_RANGES[sensor]
            bus = get_bus(busnum) if buses is None else buses.get(busnum)
            device = MPU6050(
                bus,
                addr,
                accel_range_g=acc if accel_range_g is None else accel_range_g,
                gyro_range_dps=gyr if gyro_range_dps is None else gyro_range_dps,
                dlpf=dlp_setting,
            )
            if device.sensor != sensor:
                logger.warning(
                    "IMU: sensor=%r was configured but the chip at 0x%02X identifies as %s; reading it as %s",
                    sensor,
                    addr,
                    device.sensor.upper(),
                    device.sensor.upper(),
                )
        self.device = device
        self.poll_delay = float(poll_delay)
        self.poller: Poller[IMUSample] = Poller(device.read_sync, 1.0 / self.poll_delay, name=device.name)
        outputs = list(IMU_OUTPUTS)
        if temperature:
            outputs.append("imu/temp")
        if timestamp:
            outputs.append("imu/timestamp")
        self.outputs: list[str] = outputs
        self._pack = _packer(temperature, timestamp)
        self._origin: float | None = None

    @property
    def sample(self) -> Sample[IMUSample] | None:
        """The newest sample with its timestamp (runtime clock) and sequence number."""
        return self.poller.latest.sample

    @property
    def reads(self) -> int:
        return self.poller.reads

    @property
    def errors(self) -> int:
        return self.poller.errors

    def run(self) -> tuple[float, ...] | None:
        s = self.poller.latest.sample
        if s is None:
            return None
        self._origin = s.timestamp
        return self._pack(s)

    def output_origin(self) -> float | None:
        """When the sample ``run()`` returned was read: its outputs are that old, however often re-published."""
        return self._origin

    run_threaded = run

    async def update(self) -> None:
        await self.poller.update()

    def shutdown(self) -> None:
        self.poller.shutdown()


def _packer(temperature: bool, timestamp: bool) -> Any:
    """Decide once what ``run()`` returns, so the tick does no branching on options."""
    if temperature and timestamp:
        return lambda s: (*_motion(s.value), s.value.temp_c, s.timestamp)
    if temperature:
        return lambda s: (*_motion(s.value), s.value.temp_c)
    if timestamp:
        return lambda s: (*_motion(s.value), s.timestamp)
    return lambda s: _motion(s.value)


def _motion(v: IMUSample) -> tuple[float, float, float, float, float, float]:
    return v.acl_x, v.acl_y, v.acl_z, v.gyr_x, v.gyr_y, v.gyr_z
