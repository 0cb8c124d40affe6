"""IMU part: Donkeycar's outputs from the MPU model, polled at 60 Hz off the loop, errors survived."""

import itertools
import logging

import pytest

from asyncdonkey import Vehicle
from asyncdonkey.clock import get_clock
from asyncdonkey.hw.i2c import I2CDeviceNotFound
from asyncdonkey.hw.mpu6050 import GRAVITY, MPU6050
from asyncdonkey.parts.imu import IMU, IMU_OUTPUTS
from asyncdonkey.testing.i2c_models import I2CSimulator, MPU6050Model


class Rig:
    def __init__(self, variant="mpu6050", **motion) -> None:
        self.sim = I2CSimulator()
        self.mpu = self.sim.attach(MPU6050Model(variant, **motion), address=0x68, bus=1)
        self.bus = self.sim.bus(1)
        self.buses = self.sim.registry(retry_delay_s=0)


class Collect:
    """Records the inputs it is given each tick, and the tick's time."""

    def __init__(self) -> None:
        self.rows = []
        self.times = []

    def run(self, *values):
        self.rows.append(values)
        self.times.append(get_clock().now())


def test_outputs_are_donkeycars_names():
    rig = Rig()
    assert (
        IMU(buses=rig.buses).outputs
        == list(IMU_OUTPUTS)
        == [
            "imu/acl_x",
            "imu/acl_y",
            "imu/acl_z",
            "imu/gyr_x",
            "imu/gyr_y",
            "imu/gyr_z",
        ]
    )
    imu = IMU(buses=rig.buses, temperature=True, timestamp=True)
    assert imu.outputs[-2:] == ["imu/temp", "imu/timestamp"]


def test_construction_configures_the_chip_like_donkeycar():
    rig = Rig("mpu6050")
    IMU(dlp_setting=3, buses=rig.buses)
    assert (rig.mpu.accel_range_index, rig.mpu.gyro_range_index, rig.mpu.dlpf) == (0, 0, 3)  # ±2 g, ±250 °/s
    rig9250 = Rig("mpu9250")
    IMU(sensor="mpu9250", buses=rig9250.buses)
    assert (rig9250.mpu.accel_range_index, rig9250.mpu.gyro_range_index) == (1, 2)  # ±4 g, ±1000 °/s


def test_absent_imu_fails_at_construction_with_a_clear_error():
    rig = Rig()
    with pytest.raises(I2CDeviceNotFound, match="0x69 on I2C bus 1"):
        IMU(addr=0x69, buses=rig.buses)


def test_sensor_mismatch_is_read_as_the_chip_says_and_logged(caplog):
    rig = Rig("mpu9250", temp_c=30.0)
    with caplog.at_level(logging.WARNING, logger="asyncdonkey.parts.imu"):
        imu = IMU(sensor="mpu6050", buses=rig.buses)
    assert imu.device.sensor == "mpu9250"
    assert "identifies as MPU9250" in caplog.text
    assert imu.device.read_sync().temp_c == pytest.approx(30.0, abs=0.01)


def test_run_before_the_first_sample_writes_nothing():
    rig = Rig()
    imu = IMU(buses=rig.buses)
    assert imu.run() is None and imu.sample is None


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_polled_at_60_hz_with_one_burst_per_sample_and_scaled_outputs():
    rig = Rig(accel_g=(0.1, -0.2, 1.0), gyro_dps=(5.0, -10.0, 90.0), temp_c=31.0)
    imu = IMU(buses=rig.buses, temperature=True, timestamp=True)
    n0 = len(rig.bus.log)
    v = Vehicle()
    v.add(imu, outputs=imu.outputs)
    collect = Collect()
    v.add(collect, inputs=imu.outputs)
    await v.run(rate_hz=20, duration=2.0)
    # ~60 reads a second, each exactly one 14-byte burst from 0x3B
    reads = list(rig.bus.log)[n0:]
    assert imu.reads == len(reads) and 118 <= imu.reads <= 122
    assert all(t.kind == "smbus:i2c_block_data" and t.written == b"\x3b" and len(t.read_back) == 14 for t in reads)
    assert imu.errors == 0
    last = collect.rows[-1]
    ax, ay, az, gx, gy, gz, temp, _ = last
    assert (ax, ay, az) == pytest.approx((0.1 * GRAVITY, -0.2 * GRAVITY, GRAVITY), abs=1e-3)
    assert (gx, gy, gz) == pytest.approx((5.0, -10.0, 90.0), abs=0.01)
    assert temp == pytest.approx(31.0, abs=0.01)
    assert v.mem["imu/acl_z"] == pytest.approx(GRAVITY, abs=1e-3)
    # each tick sees the newest sample, never older than one poll period
    stamps = [row[-1] for row in collect.rows[1:]]
    assert all(b > a for a, b in itertools.pairwise(stamps))
    ages = [t - st for t, st in zip(collect.times[1:], stamps, strict=True)]
    assert all(0 <= age < 1 / 60 + 1e-9 for age in ages)
    s = imu.sample
    assert s is not None and s.seq == imu.reads


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_motion_changes_reach_the_outputs():
    rig = Rig(accel_g=(0, 0, 1))
    imu = IMU(buses=rig.buses)
    v = Vehicle()
    v.add(imu, outputs=imu.outputs)

    class Turn:
        def __init__(self):
            self.k = 0

        def run(self):
            self.k += 1
            if self.k == 10:
                rig.mpu.set_motion(gyro_dps=(0, 0, 45.0))

    v.add(Turn())
    collect = Collect()
    v.add(collect, inputs=["imu/gyr_z"])
    await v.run(rate_hz=20, max_loop_count=20)
    gz = [r[0] for r in collect.rows]
    assert gz[0] is None  # tick 0 runs before the poller's first read: nothing written yet
    assert gz[1] == pytest.approx(0.0)
    assert gz[-1] == pytest.approx(45.0, abs=0.01)


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_read_errors_are_counted_and_never_reach_the_tick(caplog):
    rig = Rig(accel_g=(0, 0, 1))
    imu = IMU(buses=rig.buses)
    v = Vehicle()
    v.add(imu, outputs=imu.outputs)

    class Fault:
        def __init__(self):
            self.k = 0

        def run(self):
            self.k += 1
            if self.k == 10:
                rig.bus.nack(0x68, times=None)
            elif self.k == 30:
                rig.bus.clear_faults()

    v.add(Fault())
    with caplog.at_level(logging.WARNING, logger="asyncdonkey.poller"):
        report = await v.run(rate_hz=20, max_loop_count=50)
    assert report.loops == 50 and not report.part_errors
    assert 50 <= imu.errors <= 70  # about a second of failed 60 Hz reads
    assert imu.reads > 50
    assert "0x68" in caplog.text and "register 0x3B" in caplog.text


def test_a_prebuilt_driver_can_be_given():
    rig = Rig()
    dev = MPU6050(rig.buses.get(1), accel_range_g=16)
    imu = IMU(device=dev)
    assert imu.device is dev and rig.mpu.accel_range_index == 3


@pytest.mark.parametrize("bad", [{"sensor": "bno055"}, {"poll_delay": 0}])
def test_bad_configuration(bad):
    rig = Rig()
    with pytest.raises(ValueError):
        IMU(buses=rig.buses, **bad)
