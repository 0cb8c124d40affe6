"""PCA9685 driver and register model: init and frequency sequences, pulses, chip sharing, pin specs."""

import asyncio

import pytest

from asyncdonkey.hw.i2c import I2CDeviceNotFound
from asyncdonkey.hw.pca9685 import PCA9685, get_pca9685, open_pwm_channel, prescale_for
from asyncdonkey.hw.pinspec import PCA9685Pin, PinSpecError, parse_pca9685_pin
from asyncdonkey.testing.i2c_models import I2CSimulator, PCA9685Model


@pytest.fixture
def sim():
    s = I2CSimulator()
    s.attach(PCA9685Model(), address=0x40, bus=1)
    return s


@pytest.fixture
def model(sim):
    return sim.bus(1).devices[0x40]


@pytest.fixture
def buses(sim):
    reg = sim.registry(retry_delay_s=0)
    yield reg
    reg.close_all()


def writes(sim, since=0):
    """(register, value...) of every write on bus 1 after ``since`` transfers, reads as ('r', register)."""
    out = []
    for t in list(sim.bus(1).log)[since:]:
        if any(m.read for m in t.messages):
            out.append(("r", t.messages[0].data[0]))
        else:
            out.append(tuple(t.written))
    return out


# ------------------------------------------------------------------------------------ prescale


@pytest.mark.parametrize(("freq", "prescale"), [(60, 101), (50, 121), (200, 30), (1526, 3), (24, 253)])
def test_prescale_for(freq, prescale):
    assert prescale_for(freq) == prescale


@pytest.mark.parametrize("freq", [23, 2000, 0, -5, float("nan")])
def test_prescale_outside_the_chip_limits_is_refused(freq):
    with pytest.raises(ValueError, match="PCA9685"):
        prescale_for(freq)


# ------------------------------------------------------------------------------- init sequence


def test_power_on_state_of_the_model(model):
    assert model.mode1 == 0x11 and model.asleep and not model.running
    assert model.prescale == 30 and model.registers[0x01] == 0x04
    assert all(model.channel_registers(ch) == b"\x00\x00\x00\x10" for ch in range(16))
    assert all(model.pulse(ch) == 0 for ch in range(16))


def test_init_at_60_hz_leaves_exact_registers_and_a_running_chip(sim, model, buses):
    chip = PCA9685(buses.get(1), 0x40, 60)
    assert chip.prescale == 101 and chip.frequency_hz == pytest.approx(25e6 / (4096 * 102))
    assert model.mode1 == 0x21  # AI | ALLCALL, awake, RESTART clear
    assert model.registers[0x01] == 0x04  # MODE2 OUTDRV
    assert model.prescale == 101
    assert model.running and model.early_restarts == 0 and model.prescale_writes_ignored == 0
    assert all(model.channel_registers(ch) == b"\x00\x00\x00\x10" for ch in range(16))
    assert writes(sim) == [
        ("r", 0x00),  # probe
        (0x01, 0x04),  # MODE2 = OUTDRV
        (0xFD, 0x10),  # ALL_LED_OFF_H = full off
        ("r", 0x00),  # read MODE1
        (0x00, 0x11),  # MODE1 with SLEEP
        (0xFE, 101),  # PRE_SCALE
        (0x00, 0x21),  # restore, awake, AI on
        (0x00, 0xA1),  # RESTART (after >= 500 us)
    ]


def test_frequency_change_keeps_pulses_and_follows_the_datasheet_sequence(sim, model, buses):
    chip = PCA9685(buses.get(1), 0x40, 60)
    chip.set_pulse_sync(3, 375)
    assert model.pulse(3) == 375
    n = len(sim.bus(1).log)
    chip.set_frequency_sync(50)
    assert model.prescale == 121 and chip.prescale == 121
    assert chip.frequency_hz == pytest.approx(25e6 / (4096 * 122))
    assert writes(sim, n) == [("r", 0x00), (0x00, 0x31), (0xFE, 121), (0x00, 0x21), (0x00, 0xA1)]
    assert model.running and model.mode1 == 0x21 and model.early_restarts == 0
    assert model.pulse(3) == 375
    assert model.history[3] == [0, 375, 0, 375]  # halted while asleep, resumed by RESTART


@pytest.mark.realtime
def test_async_frequency_change(sim, model, buses):
    chip = PCA9685(buses.get(1), 0x40, 50)
    asyncio.run(chip.set_frequency(60))
    assert model.prescale == 101 and model.running


# --------------------------------------------------------------------------------- the model


def test_model_restart_needs_500us_after_wake():
    # the model's clock stands still unless the test moves it: "too early" must not depend on how fast two
    # writes follow each other in real time (under qemu, or on a loaded machine, they can be 500 us apart)
    now = [100.0]
    model = PCA9685Model(clock=lambda: now[0])
    sim = I2CSimulator()
    sim.attach(model, address=0x40, bus=1)
    s = sim.smbus(1)
    s.write_byte_data(0x40, 0x00, 0x21)  # wake with AI
    s.write_i2c_block_data(0x40, 0x06, [0, 0, 100, 0])
    assert model.pulse(0) == 100
    s.write_byte_data(0x40, 0x00, 0x31)  # sleep: the running chip sets RESTART
    assert s.read_byte_data(0x40, 0x00) == 0xB1 and model.pulse(0) == 0
    s.write_byte_data(0x40, 0x00, 0x21)
    now[0] += 0.0004
    s.write_byte_data(0x40, 0x00, 0xA1)  # too early: 400 us after waking
    assert model.early_restarts == 1 and model.restart_pending and model.pulse(0) == 0
    now[0] += 0.0001
    s.write_byte_data(0x40, 0x00, 0xA1)  # 500 us after waking: the pulses resume
    assert model.early_restarts == 1 and not model.restart_pending and model.pulse(0) == 100
    s.close()


def test_model_prescale_only_writable_while_asleep(sim, model):
    s = sim.smbus(1)
    s.write_byte_data(0x40, 0xFE, 50)  # asleep at power-on: accepted
    assert model.prescale == 50
    s.write_byte_data(0x40, 0x00, 0x01)  # wake
    s.write_byte_data(0x40, 0xFE, 90)
    assert model.prescale == 50 and model.prescale_writes_ignored == 1
    s.write_byte_data(0x40, 0x00, 0x11)
    s.write_byte_data(0x40, 0xFE, 1)  # the hardware minimum is 3
    assert model.prescale == 3
    s.close()


def test_model_auto_increments_only_with_ai(sim, model):
    s = sim.smbus(1)
    s.write_byte_data(0x40, 0x00, 0x01)  # awake, AI off
    s.write_i2c_block_data(0x40, 0x06, [1, 2, 3, 4])
    assert model.channel_registers(0) == b"\x04\x00\x00\x10"  # every byte landed in LED0_ON_L
    s.write_byte_data(0x40, 0x00, 0x21)  # AI on
    s.write_i2c_block_data(0x40, 0x06, [1, 2, 3, 4])
    assert model.channel_registers(0) == b"\x01\x02\x03\x04"
    assert s.read_i2c_block_data(0x40, 0x06, 4) == [1, 2, 3, 4]
    s.close()


def test_model_all_led_reaches_every_channel_and_reads_back_zero(sim, model):
    s = sim.smbus(1)
    s.write_byte_data(0x40, 0x00, 0x21)
    s.write_i2c_block_data(0x40, 0xFA, [0, 0, 0x2C, 0x01])
    assert all(model.pulse(ch) == 300 for ch in range(16))
    assert s.read_i2c_block_data(0x40, 0xFA, 4) == [0, 0, 0, 0]
    s.close()


def test_model_full_on_full_off_and_offset_pulses(sim, model):
    s = sim.smbus(1)
    s.write_byte_data(0x40, 0x00, 0x21)
    s.write_i2c_block_data(0x40, 0x06, [0, 0x10, 0, 0])  # full on
    s.write_i2c_block_data(0x40, 0x0A, [0, 0x10, 0, 0x10])  # both: off wins
    s.write_i2c_block_data(0x40, 0x0E, [0x00, 0x0F, 0x64, 0x00])  # ON 3840, OFF 100: wraps the period
    assert (model.pulse(0), model.pulse(1), model.pulse(2)) == (4096, 0, 356)
    s.close()


# ------------------------------------------------------------------------------------ pulses


@pytest.mark.parametrize(
    ("pulse", "regs"),
    [(375, b"\x00\x00\x77\x01"), (1, b"\x00\x00\x01\x00"), (4095, b"\x00\x00\xff\x0f"), (0, b"\x00\x00\x00\x10")],
)
def test_set_pulse_is_one_4_byte_block_write(sim, model, buses, pulse, regs):
    chip = PCA9685(buses.get(1), 0x40, 60)
    n = len(sim.bus(1).log)
    chip.set_pulse_sync(5, pulse)
    log = list(sim.bus(1).log)[n:]
    assert len(log) == 1 and log[0].kind == "smbus:i2c_block_data"
    assert log[0].written == bytes([0x06 + 4 * 5]) + regs
    assert model.channel_registers(5) == regs
    assert model.pulse(5) == pulse
    assert chip.read_channel_sync(5) == (0, pulse if pulse else 0x1000)


@pytest.mark.realtime
def test_full_on_and_full_off(sim, model, buses):
    chip = PCA9685(buses.get(1), 0x40, 60)
    chip.set_pulse_sync(7, 4096)
    assert model.pulse(7) == 4096 and model.channel_registers(7) == b"\x00\x10\x00\x00"
    chip.full_off_sync(7)
    assert model.pulse(7) == 0 and model.channel_registers(7) == b"\x00\x00\x00\x10"
    asyncio.run(chip.set_pulse(7, 300))
    assert model.pulse(7) == 300
    asyncio.run(chip.full_off(7))
    assert model.pulse(7) == 0


def test_pulse_width_in_microseconds(sim, model, buses):
    chip = PCA9685(buses.get(1), 0x40, 60)
    chip.set_pulse_sync(0, 370)
    assert model.pulse_us(0) == pytest.approx(370 / 4096 / chip.frequency_hz * 1e6)
    assert 1500 < model.pulse_us(0) < 1550  # a neutral servo pulse


def test_bad_channel_is_refused(buses):
    chip = PCA9685(buses.get(1), 0x40, 60)
    with pytest.raises(ValueError, match=r"0\.\.15"):
        chip.set_pulse_sync(16, 300)
    with pytest.raises(ValueError, match=r"0\.\.15"):
        chip.channel(-1)


def test_absent_chip_is_named_at_open(buses):
    with pytest.raises(I2CDeviceNotFound, match=r"no PCA9685 answered at address 0x41 on I2C bus 1"):
        PCA9685(buses.get(1), 0x41, 60)


# ------------------------------------------------------------------------------------- sharing


def test_one_driver_per_chip_second_channel_does_not_reinit_or_zero(sim, model, buses):
    steering = open_pwm_channel("PCA9685.1:40.1", 60, buses=buses)
    steering.set_pulse_sync(375)
    n = len(sim.bus(1).log)
    throttle = open_pwm_channel("PCA9685.1:40.0", 60, buses=buses)
    assert throttle.chip is steering.chip
    assert len(sim.bus(1).log) == n  # nothing was sent to the chip
    throttle.set_pulse_sync(370)
    assert (model.pulse(1), model.pulse(0)) == (375, 370)
    assert get_pca9685(buses.get(1), 0x40, 60) is steering.chip


def test_reinitialising_the_chip_zeroes_channels_which_is_the_bug_sharing_avoids(sim, model, buses):
    """What Donkeycar does (a new chip object per pin): the second init cuts the first channel's pulse."""
    bus = buses.get(1)
    PCA9685(bus, 0x40, 60).set_pulse_sync(1, 375)
    PCA9685(bus, 0x40, 60)
    assert model.pulse(1) == 0


def test_sharing_a_chip_at_another_frequency_is_refused(buses):
    open_pwm_channel("PCA9685.1:40.1", 60, buses=buses)
    with pytest.raises(ValueError, match="already runs at 60 Hz"):
        open_pwm_channel("PCA9685.1:40.2", 50, buses=buses)


@pytest.mark.realtime
def test_chips_at_two_addresses_are_separate(sim, model, buses):
    other = sim.attach(PCA9685Model(), address=0x41, bus=1)
    a = open_pwm_channel("PCA9685.1:40.0", 60, buses=buses)
    b = open_pwm_channel("PCA9685.1:41.0", 50, buses=buses)
    assert a.chip is not b.chip
    asyncio.run(b.set_pulse(300))
    assert other.pulse(0) == 300 and model.pulse(0) == 0 and other.prescale == 121


# ------------------------------------------------------------------------------------ pin specs


@pytest.mark.parametrize(
    ("spec", "pin"),
    [
        ("PCA9685.1:40.1", PCA9685Pin(1, 0x40, 1)),
        ("PCA9685.0:40.7", PCA9685Pin(0, 0x40, 7)),
        ("PCA9685.1:0x41.15", PCA9685Pin(1, 0x41, 15)),
        (" pca9685.10:77.0 ", PCA9685Pin(10, 0x77, 0)),
    ],
)
def test_pin_specs(spec, pin):
    assert parse_pca9685_pin(spec) == pin


def test_pin_spec_round_trips():
    assert str(parse_pca9685_pin("PCA9685.1:40.1")) == "PCA9685.1:40.1"


@pytest.mark.parametrize(
    ("spec", "why"),
    [
        ("PCA9685.1.40.1", "malformed"),
        ("PCA9685.1:40", "malformed"),
        ("PCA9685.1:zz.1", "malformed"),
        ("PCA9685:40.1", "malformed"),
        ("", "malformed"),
        ("PCA9685.1:40.16", "channel 16 is out of range"),
        ("PCA9685.1:80.1", "address 0x80"),
        ("RPI_GPIO.BCM.13", "'RPI_GPIO' pin provider"),
        ("PIGPIO.BCM.13", "'PIGPIO' pin provider"),
    ],
)
def test_bad_pin_specs_name_the_spec_and_the_expected_form(spec, why):
    with pytest.raises(PinSpecError) as info:
        parse_pca9685_pin(spec)
    text = str(info.value)
    assert repr(spec) in text and why in text
    if why != "channel 16 is out of range":
        assert "PCA9685.<bus>:<hex address>.<channel>" in text


def test_non_string_pin_spec():
    with pytest.raises(PinSpecError, match="must be a string"):
        parse_pca9685_pin(40)
