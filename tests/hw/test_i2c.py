"""The async I2C bus over the real smbus2, against simulated buses: wire bytes, retries, errors, threads."""

import asyncio
import errno
import threading
import time

import pytest
import smbus2

from asyncdonkey.clock import get_clock
from asyncdonkey.hw.i2c import I2CBus, I2CBusRegistry, I2CDeviceNotFound, I2CError
from asyncdonkey.testing.i2c_models import I2CSimulator, MPU6050Model, RegisterDeviceModel, SimulatedSMBus


class RAM(RegisterDeviceModel):
    """A 256-byte register file (like a small EEPROM page) that also notes which thread served it."""

    def __init__(self) -> None:
        super().__init__()
        self.mem = bytearray(range(256))
        self.threads: set[str] = set()

    def begin(self) -> None:
        self.threads.add(threading.current_thread().name)

    def read_register(self, register: int) -> int:
        return self.mem[register]

    def write_register(self, register: int, value: int) -> None:
        self.mem[register] = value


@pytest.fixture
def sim():
    s = I2CSimulator()
    s.attach(RAM(), address=0x50, bus=1)
    return s


@pytest.fixture
def bus(sim):
    b = I2CBus(1, smbus_factory=sim.smbus, retry_delay_s=0)
    yield b
    b.close()


# ------------------------------------------------------------------------------ smbus2 runs for real


def test_simulated_smbus_is_smbus2_and_puts_smbus_calls_on_the_wire_as_the_kernel_does(sim):
    ram = sim.bus(1).devices[0x50]
    with sim.smbus(1) as s:
        assert isinstance(s, smbus2.SMBus)
        assert s.funcs & smbus2.I2cFunc.SMBUS_READ_I2C_BLOCK
        assert s.read_byte_data(0x50, 0x10) == 0x10
        s.write_byte_data(0x50, 0x20, 0xAB)
        assert s.read_word_data(0x50, 0x30) == 0x31 << 8 | 0x30  # SMBus words are little-endian
        s.write_i2c_block_data(0x50, 0x40, [1, 2, 3])
        assert s.read_i2c_block_data(0x50, 0x40, 4) == [1, 2, 3, 0x43]
        write, read = smbus2.i2c_msg.write(0x50, [0x60]), smbus2.i2c_msg.read(0x50, 2)
        s.i2c_rdwr(write, read)
        assert list(read) == [0x60, 0x61]
    assert ram.mem[0x20] == 0xAB
    wire = [(t.kind, [(m.read, m.data) for m in t.messages]) for t in sim.bus(1).log]
    assert wire == [
        ("smbus:byte_data", [(False, b"\x10"), (True, b"\x10")]),
        ("smbus:byte_data", [(False, b"\x20\xab")]),
        ("smbus:word_data", [(False, b"\x30"), (True, b"\x30\x31")]),
        ("smbus:i2c_block_data", [(False, b"\x40\x01\x02\x03")]),
        ("smbus:i2c_block_data", [(False, b"\x40"), (True, b"\x01\x02\x03\x43")]),
        ("rdwr", [(False, b"\x60"), (True, b"\x60\x61")]),
    ]


def test_simulated_kernel_errors_look_like_linux(sim):
    with pytest.raises(FileNotFoundError):
        sim.smbus(7)
    s = sim.smbus("/dev/i2c-1")
    with pytest.raises(OSError) as absent:
        s.read_byte_data(0x51, 0)
    assert absent.value.errno == errno.EREMOTEIO
    s.close()
    with pytest.raises(OSError) as closed:
        s.read_byte_data(0x50, 0)
    assert closed.value.errno == errno.EBADF


# ------------------------------------------------------------------------------------- I2CBus


@pytest.mark.realtime
def test_sync_and_async_transfers_return_bytes_and_count(sim, bus):
    assert bus.read_byte_data_sync(0x50, 5) == 5
    bus.write_i2c_block_data_sync(0x50, 0x80, b"\x09\x08")
    assert bus.read_i2c_block_data_sync(0x50, 0x80, 3) == b"\x09\x08\x82"

    async def main():
        await bus.write_byte_data(0x50, 0x81, 0x77)
        return await bus.read_byte_data(0x50, 0x81), await bus.read_i2c_block_data(0x50, 0x80, 2)

    assert asyncio.run(main()) == (0x77, b"\x09\x77")
    assert bus.transfers == 6 and bus.retried == 0 and bus.failures == 0


@pytest.mark.realtime
def test_async_transfers_run_on_the_bus_worker_thread_not_the_loop(sim, bus):
    ram = sim.bus(1).devices[0x50]
    sim.bus(1).transfer_delay_s = 0.03

    async def main():
        ticks = 0

        async def ticker():
            nonlocal ticks
            while True:
                await asyncio.sleep(0.002)
                ticks += 1

        t = asyncio.create_task(ticker())
        value = await bus.read_byte_data(0x50, 3)
        t.cancel()
        return value, ticks

    value, ticks = asyncio.run(main())
    assert value == 3
    assert ticks >= 5  # the loop kept running while the 30 ms transfer was in flight
    assert ram.threads == {"i2c-1_0"}


def test_transient_nacks_are_retried_then_succeed(sim, bus):
    sim.bus(1).nack(0x50, times=3)
    assert bus.read_byte_data_sync(0x50, 9) == 9
    assert bus.retried == 3 and bus.failures == 0
    failed = [t for t in sim.bus(1).log if t.error == errno.EREMOTEIO]
    assert len(failed) == 3


def test_persistent_nack_raises_a_clear_error_naming_bus_address_register(sim, bus):
    sim.bus(1).nack(0x50, times=None)
    with pytest.raises(I2CError) as info:
        bus.write_byte_data_sync(0x50, 0x2A, 1)
    err = info.value
    assert isinstance(err, OSError) and err.errno == errno.EREMOTEIO
    assert (err.bus, err.address, err.register, err.attempts) == (1, 0x50, 0x2A, 4)
    text = str(err)
    assert "I2C bus 1" in text and "0x50" in text and "0x2A" in text and "write_byte_data" in text
    assert "4 attempts" in text
    assert isinstance(err.__cause__, OSError)
    assert len(sim.bus(1).log) == 4
    sim.bus(1).clear_faults()
    bus.write_byte_data_sync(0x50, 0x2A, 1)  # the bus is usable again


def test_non_transient_errors_are_not_retried(sim, bus):
    sim.bus(1).nack(0x50, times=None, err=errno.EINVAL)
    with pytest.raises(I2CError, match="not retried"):
        bus.read_byte_data_sync(0x50, 0)
    assert len(sim.bus(1).log) == 1


@pytest.mark.realtime
def test_retries_pause_between_attempts(sim):
    b = I2CBus(1, smbus_factory=sim.smbus, retries=2, retry_delay_s=0.01)
    sim.bus(1).nack(0x50, times=None)
    t0 = time.monotonic()
    with pytest.raises(I2CError, match="3 attempts"):
        b.read_byte_data_sync(0x50, 0)
    assert time.monotonic() - t0 >= 0.02
    b.close()


@pytest.mark.realtime
def test_async_error_surfaces_as_i2c_error(sim, bus):
    sim.bus(1).nack(0x50, times=None)

    async def main():
        await bus.read_i2c_block_data(0x50, 0x3B, 14)

    with pytest.raises(I2CError, match=r"read_i2c_block_data\(14\)"):
        asyncio.run(main())


def test_probe_of_an_absent_device_names_it(sim, bus):
    with pytest.raises(I2CDeviceNotFound) as info:
        bus.probe_sync(0x68, 0x75, "MPU6050/MPU9250 IMU")
    text = str(info.value)
    assert "MPU6050/MPU9250 IMU" in text and "0x68" in text and "bus 1" in text and "i2cdetect -y 1" in text


def test_a_missing_bus_gives_a_clear_error(sim):
    with pytest.raises(I2CError, match=r"I2C bus 3 does not exist \(/dev/i2c-3 not found\)"):
        I2CBus(3, smbus_factory=sim.smbus)


def test_closed_bus_refuses_transfers(sim, bus):
    bus.close()
    with pytest.raises(I2CError, match="closed bus"):
        bus.read_byte_data_sync(0x50, 0)


@pytest.mark.realtime
def test_a_locked_sequence_is_not_interleaved_with_other_users(sim, bus):
    """A read-modify-write on one chip holds the bus; an async transfer from the loop waits for it."""
    started = threading.Event()

    def sequence():
        with bus.locked():
            bus.write_byte_data_sync(0x50, 0x01, 0xA1)
            started.set()
            time.sleep(0.03)
            bus.write_byte_data_sync(0x50, 0x02, 0xA2)

    async def main():
        th = threading.Thread(target=sequence)
        th.start()
        await asyncio.get_running_loop().run_in_executor(None, started.wait)
        await bus.write_byte_data(0x50, 0x03, 0xA3)
        th.join()

    asyncio.run(main())
    order = [t.messages[0].data[0] for t in sim.bus(1).log]
    assert order == [0x01, 0x02, 0x03]


def test_registry_shares_one_bus_per_number_and_one_object_per_key(sim):
    sim.bus(2)
    reg = I2CBusRegistry(smbus_factory=sim.smbus, retries=1)
    b1 = reg.get(1)
    assert reg.get(1) is b1 and reg.get(2) is not b1 and b1.retries == 1
    made = []
    obj = b1.shared(("chip", 0x40), lambda: made.append(1) or object())
    assert b1.shared(("chip", 0x40), lambda: made.append(1) or object()) is obj and made == [1]
    reg.close_all()
    assert b1.closed
    assert reg.get(1) is not b1  # reopened on demand


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_bus_work_costs_no_virtual_time():
    """The virtual clock sees the bus's executor work and waits for it in real time without moving."""
    sim = I2CSimulator()
    sim.attach(MPU6050Model(), 0x68)
    sim.bus(1).transfer_delay_s = 0.02
    bus = I2CBus(1, smbus_factory=sim.smbus)
    clock = get_clock()
    t0 = clock.now()
    assert await bus.read_byte_data(0x68, 0x75) == 0x68
    assert clock.now() == t0
    bus.close()


def test_simulated_smbus_releases_its_descriptor_when_collected(sim):
    import gc

    from asyncdonkey.testing import i2c_models

    s = SimulatedSMBus(1, simulator=sim)
    fd = s.fd
    assert fd in i2c_models._open_files
    del s
    gc.collect()
    assert fd not in i2c_models._open_files
