"""MPU6050 / MPU9250 accelerometer + gyroscope driver (register facts below).

Design notes:

* **One burst per sample.** The 14 data bytes (accel x, y, z, temperature, gyro x, y, z; big-endian int16
  from 0x3B) are read in one I2C transaction. The chip copies its sensor registers to the user-facing ones
  only while the bus is idle, so a burst is one sampling instant; 14 single-byte reads could mix two samples
  (and cost 14 transactions).
* **Checked identity.** WHO_AM_I must read 0x68 (MPU6050) or 0x71 (MPU9250), else the error names the value
  and the address: a wrong chip at 0x68 would otherwise give plausible-looking garbage.
* **Explicit configuration.** Wake (PWR_MGMT_1 = 0), low-pass filter (CONFIG), gyro and accel full-scale
  ranges are written at open; scaling uses the ranges written, never an assumed default.
* **One process per chip.** The driver claims the chip (:meth:`~asyncdonkey.hw.i2c.I2CBus.claim`) before it
  sends it anything: a second process's init would rewrite the ranges under the first, whose readings would
  then be scaled wrong without any error.

``read_sync`` blocks (run it in a worker thread, e.g. through :class:`asyncdonkey.Poller`); ``read`` is the
async form on the bus's worker thread.
"""

from __future__ import annotations

from dataclasses import dataclass

from .i2c import I2CBus, I2CError

__all__ = [
    "ACCEL_RANGES_G",
    "GRAVITY",
    "GYRO_RANGES_DPS",
    "MPU6050",
    "WHO_AM_I_VALUES",
    "IMUSample",
    "MPUIdentityError",
    "decode_sample",
]

DEFAULT_ADDRESS = 0x68
GRAVITY = 9.80665  # m/s² per g

SMPLRT_DIV = 0x19
CONFIG = 0x1A
GYRO_CONFIG = 0x1B
ACCEL_CONFIG = 0x1C
ACCEL_XOUT_H = 0x3B
PWR_MGMT_1 = 0x6B
WHO_AM_I = 0x75

#: WHO_AM_I value → sensor name
WHO_AM_I_VALUES = {0x68: "mpu6050", 0x71: "mpu9250"}
#: full-scale range → (register code, LSB per unit)
ACCEL_RANGES_G = {2: (0, 16384.0), 4: (1, 8192.0), 8: (2, 4096.0), 16: (3, 2048.0)}
GYRO_RANGES_DPS = {250: (0, 131.0), 500: (1, 65.5), 1000: (2, 32.8), 2000: (3, 16.4)}
#: temperature °C = raw / sensitivity + offset
TEMPERATURE = {"mpu6050": (340.0, 36.53), "mpu9250": (333.87, 21.0)}


class MPUIdentityError(I2CError):
    """The chip at the IMU address is not an MPU6050/MPU9250 (or not the one asked for)."""


@dataclass(frozen=True, slots=True)
class IMUSample:
    """One sample: acceleration in m/s², rotation rate in °/s, die temperature in °C."""

    acl_x: float
    acl_y: float
    acl_z: float
    gyr_x: float
    gyr_y: float
    gyr_z: float
    temp_c: float


def decode_sample(data: bytes, accel_lsb_per_g: float, gyro_lsb_per_dps: float, sensor: str = "mpu6050") -> IMUSample:
    """Scale the 14 data bytes read from 0x3B into an :class:`IMUSample`."""
    if len(data) != 14:
        raise ValueError(f"an MPU sample is 14 bytes, got {len(data)}")
    r = [int.from_bytes(data[i : i + 2], "big", signed=True) for i in range(0, 14, 2)]
    a = GRAVITY / accel_lsb_per_g
    sens, offset = TEMPERATURE[sensor]
    return IMUSample(
        r[0] * a,
        r[1] * a,
        r[2] * a,
        r[4] / gyro_lsb_per_dps,
        r[5] / gyro_lsb_per_dps,
        r[6] / gyro_lsb_per_dps,
        r[3] / sens + offset,
    )


class MPU6050:
    """An MPU6050 or MPU9250 (accel, gyro, temperature) on an :class:`~asyncdonkey.hw.i2c.I2CBus`.

    Args:
        bus: the shared bus.
        address: 0x68 (AD0 low) or 0x69.
        sensor: ``"mpu6050"`` or ``"mpu9250"`` to insist on one (an error if WHO_AM_I says otherwise), or
            ``None`` to accept either.
        accel_range_g: 2, 4, 8 or 16. gyro_range_dps: 250, 500, 1000 or 2000.
        dlpf: digital low-pass filter setting 0..6 for CONFIG (0 = off), Donkeycar's ``IMU_DLP_CONFIG``.

    Construction claims the chip for this process (:class:`~asyncdonkey.hw.i2c.I2CDeviceInUse` if another
    process has it), probes it, checks WHO_AM_I, wakes it and writes the configuration (blocking I2C: do it at
    setup, or through ``await bus.call(MPU6050, ...)``).
    """

    def __init__(
        self,
        bus: I2CBus,
        address: int = DEFAULT_ADDRESS,
        *,
        sensor: str | None = None,
        accel_range_g: int = 2,
        gyro_range_dps: int = 250,
        dlpf: int = 0,
    ) -> None:
        if sensor is not None and sensor not in TEMPERATURE:
            raise ValueError(f"MPU6050: sensor must be 'mpu6050', 'mpu9250' or None, got {sensor!r}")
        if accel_range_g not in ACCEL_RANGES_G:
            raise ValueError(f"MPU6050: accel_range_g must be one of {sorted(ACCEL_RANGES_G)}, got {accel_range_g!r}")
        if gyro_range_dps not in GYRO_RANGES_DPS:
            raise ValueError(
                f"MPU6050: gyro_range_dps must be one of {sorted(GYRO_RANGES_DPS)}, got {gyro_range_dps!r}"
            )
        if not isinstance(dlpf, int) or not 0 <= dlpf <= 6:
            raise ValueError(f"MPU6050: dlpf (IMU_DLP_CONFIG) must be an int 0..6, got {dlpf!r}")
        self.bus = bus
        self.address = address
        self.name = f"IMU at 0x{address:02X} on I2C bus {bus.bus_number}"
        accel_code, self.accel_lsb_per_g = ACCEL_RANGES_G[accel_range_g]
        gyro_code, self.gyro_lsb_per_dps = GYRO_RANGES_DPS[gyro_range_dps]
        self.accel_range_g = accel_range_g
        self.gyro_range_dps = gyro_range_dps
        self.dlpf = dlpf
        claimed = bus.claim(address, "MPU6050/MPU9250 IMU")  # before anything reaches the chip
        try:
            self._configure_sync(sensor, accel_code, gyro_code)
        except BaseException:
            if claimed:
                bus.unclaim(address)
            raise

    def _configure_sync(self, sensor: str | None, accel_code: int, gyro_code: int) -> None:
        """Identify the chip, wake it and write its configuration, as one sequence on the bus."""
        bus, address, dlpf = self.bus, self.address, self.dlpf
        with bus.locked():
            who = bus.probe_sync(address, WHO_AM_I, "MPU6050/MPU9250 IMU")
            found = WHO_AM_I_VALUES.get(who)
            if found is None:
                raise MPUIdentityError(
                    f"the device at 0x{address:02X} on I2C bus {bus.bus_number} answered WHO_AM_I (0x75) = "
                    f"0x{who:02X}; expected 0x68 (MPU6050) or 0x71 (MPU9250)",
                    bus=bus.bus_number,
                    address=address,
                    register=WHO_AM_I,
                    operation="identify",
                )
            if sensor is not None and found != sensor:
                raise MPUIdentityError(
                    f"the device at 0x{address:02X} on I2C bus {bus.bus_number} is an {found.upper()} "
                    f"(WHO_AM_I 0x{who:02X}), but sensor={sensor!r} was asked for",
                    bus=bus.bus_number,
                    address=address,
                    register=WHO_AM_I,
                    operation="identify",
                )
            self.sensor = found
            bus.write_byte_data_sync(address, PWR_MGMT_1, 0x00)
            bus.write_byte_data_sync(address, CONFIG, dlpf)
            bus.write_byte_data_sync(address, GYRO_CONFIG, gyro_code << 3)
            bus.write_byte_data_sync(address, ACCEL_CONFIG, accel_code << 3)

    def __repr__(self) -> str:
        return f"<{self.sensor.upper()} {self.name}, ±{self.accel_range_g} g, ±{self.gyro_range_dps} °/s>"

    def read_raw_sync(self) -> bytes:
        """The 14 data bytes from 0x3B, in one transfer."""
        return self.bus.read_i2c_block_data_sync(self.address, ACCEL_XOUT_H, 14)

    def read_sync(self) -> IMUSample:
        """One scaled sample (one 14-byte burst read). Blocks: call it from a worker thread."""
        return decode_sample(self.read_raw_sync(), self.accel_lsb_per_g, self.gyro_lsb_per_dps, self.sensor)

    async def read(self) -> IMUSample:
        return await self.bus.call(self.read_sync)
