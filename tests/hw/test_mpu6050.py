"""MPU6050/MPU9250 driver against the register model: identity, configuration, scaling, one burst per sample."""

import asyncio

import pytest

from asyncdonkey.hw.i2c import I2CDeviceNotFound
from asyncdonkey.hw.mpu6050 import GRAVITY, MPU6050, MPUIdentityError, decode_sample
from asyncdonkey.testing.i2c_models import I2CSimulator, MPU6050Model


def setup(variant="mpu6050", address=0x68, **motion):
    """(model, bus, wire): the MPU model on simulated bus 1, the I2CBus over it, the simulated bus (its log)."""
    sim = I2CSimulator()
    model = sim.attach(MPU6050Model(variant, **motion), address=address, bus=1)
    return model, sim.registry(retry_delay_s=0).get(1), sim.bus(1)


def test_model_powers_up_asleep_with_data_registers_zero():
    model, bus, _wire = setup(accel_g=(0.5, 0.5, 1.0))
    assert model.asleep
    assert bus.read_byte_data_sync(0x68, 0x6B) == 0x40
    assert bus.read_i2c_block_data_sync(0x68, 0x3B, 14) == bytes(14)


def test_init_checks_identity_wakes_and_configures():
    model, bus, wire = setup()
    imu = MPU6050(bus, accel_range_g=8, gyro_range_dps=500, dlpf=3)
    assert imu.sensor == "mpu6050"
    assert not model.asleep
    regs = model.registers
    assert (regs[0x6B], regs[0x1A], regs[0x1B], regs[0x1C]) == (0x00, 3, 1 << 3, 2 << 3)
    assert (model.accel_range_index, model.gyro_range_index, model.dlpf) == (2, 1, 3)
    wire = [t.written for t in wire.log]
    assert wire == [b"\x75", b"\x6b\x00", b"\x1a\x03", b"\x1b\x08", b"\x1c\x10"]


def test_mpu9250_is_recognised():
    _model, bus, _wire = setup("mpu9250")
    assert MPU6050(bus).sensor == "mpu9250"
    assert MPU6050(bus, sensor="mpu9250").sensor == "mpu9250"


def test_wrong_who_am_i_is_a_clear_error():
    model, bus, _wire = setup()
    model.registers[0x75] = 0x12
    with pytest.raises(MPUIdentityError) as info:
        MPU6050(bus)
    text = str(info.value)
    assert "0x12" in text and "0x68 (MPU6050)" in text and "0x71 (MPU9250)" in text and "I2C bus 1" in text


def test_asking_for_the_other_sensor_is_a_clear_error():
    _model, bus, _wire = setup("mpu6050")
    with pytest.raises(MPUIdentityError, match=r"is an MPU6050 .*sensor='mpu9250'"):
        MPU6050(bus, sensor="mpu9250")


def test_absent_imu_is_named():
    _model, bus, _wire = setup(address=0x69)
    with pytest.raises(I2CDeviceNotFound, match=r"no MPU6050/MPU9250 IMU answered at address 0x68 on I2C bus 1"):
        MPU6050(bus)


@pytest.mark.parametrize("bad", [{"accel_range_g": 3}, {"gyro_range_dps": 300}, {"dlpf": 7}, {"sensor": "bno055"}])
def test_bad_configuration_is_refused(bad):
    _model, bus, _wire = setup()
    with pytest.raises(ValueError):
        MPU6050(bus, **bad)


@pytest.mark.parametrize(("accel_range", "lsb_g"), [(2, 16384), (4, 8192), (8, 4096), (16, 2048)])
@pytest.mark.parametrize(("gyro_range", "lsb_dps"), [(250, 131), (500, 65.5), (1000, 32.8), (2000, 16.4)])
def test_scaling_for_every_range(accel_range, lsb_g, gyro_range, lsb_dps):
    accel = (0.25 * accel_range, -0.5 * accel_range, 0.9 * accel_range)
    gyro = (0.1 * gyro_range, -0.75 * gyro_range, 0.3 * gyro_range)
    _model, bus, _wire = setup(accel_g=accel, gyro_dps=gyro, temp_c=30.0)
    imu = MPU6050(bus, accel_range_g=accel_range, gyro_range_dps=gyro_range)
    s = imu.read_sync()
    for got, g in zip((s.acl_x, s.acl_y, s.acl_z), accel, strict=True):
        assert got == pytest.approx(g * GRAVITY, abs=GRAVITY / lsb_g)
    for got, w in zip((s.gyr_x, s.gyr_y, s.gyr_z), gyro, strict=True):
        assert got == pytest.approx(w, abs=1 / lsb_dps)
    assert s.temp_c == pytest.approx(30.0, abs=1 / 340)
    # the raw registers hold the model's encoding in the configured range
    raw = bus.read_i2c_block_data_sync(0x68, 0x3B, 2)
    assert int.from_bytes(raw, "big", signed=True) == round(accel[0] * lsb_g)


def test_readings_saturate_at_the_range_limit():
    _model, bus, _wire = setup(accel_g=(3.0, -3.0, 0.0), gyro_dps=(300.0, 0, 0))
    s = MPU6050(bus, accel_range_g=2, gyro_range_dps=250).read_sync()
    assert s.acl_x == pytest.approx(32767 / 16384 * GRAVITY)
    assert s.acl_y == pytest.approx(-2 * GRAVITY)
    assert s.gyr_x == pytest.approx(32767 / 131)


@pytest.mark.parametrize(
    ("variant", "temp"), [("mpu6050", -10.0), ("mpu6050", 41.5), ("mpu9250", 21.0), ("mpu9250", 55.0)]
)
def test_temperature_formula_per_sensor(variant, temp):
    _model, bus, _wire = setup(variant, temp_c=temp)
    assert MPU6050(bus).read_sync().temp_c == pytest.approx(temp, abs=0.005)


def test_one_14_byte_burst_per_sample():
    model, bus, wire = setup(accel_g=(0, 0, 1))
    imu = MPU6050(bus)
    n = len(wire.log)
    before = model.samples
    for _ in range(5):
        imu.read_sync()
    log = list(wire.log)[n:]
    assert len(log) == 5
    for t in log:
        assert t.kind == "smbus:i2c_block_data"
        assert t.written == b"\x3b" and len(t.read_back) == 14
    assert model.samples - before == 5


def test_a_sample_is_one_sampling_instant():
    """The burst is latched at the start of the transaction: all 14 bytes belong to one physical state."""
    model, bus, _wire = setup(accel_g=(1.0, 1.0, 1.0), gyro_dps=(100, 100, 100))
    imu = MPU6050(bus)
    a = imu.read_sync()
    model.set_motion(accel_g=(-1.0, -1.0, -1.0), gyro_dps=(-100, -100, -100), temp_c=40.0)
    b = imu.read_sync()
    assert a.acl_x == a.acl_z > 0 and a.gyr_x == a.gyr_z > 0
    assert b.acl_x == b.acl_z < 0 and b.gyr_x == b.gyr_z < 0 and b.temp_c == pytest.approx(40.0, abs=0.01)


def test_device_reset_puts_the_chip_back_to_sleep():
    model, bus, _wire = setup()
    MPU6050(bus, accel_range_g=16)
    bus.write_byte_data_sync(0x68, 0x6B, 0x80)
    assert model.asleep and model.registers[0x1C] == 0 and model.registers[0x6B] == 0x40


@pytest.mark.realtime
def test_async_read():
    _model, bus, _wire = setup(accel_g=(0, 1, 0))
    imu = MPU6050(bus)
    s = asyncio.run(imu.read())
    assert s.acl_y == pytest.approx(GRAVITY, abs=1e-3)


def test_decode_sample_rejects_short_data():
    with pytest.raises(ValueError, match="14 bytes"):
        decode_sample(b"\x00" * 12, 16384, 131)
