"""PCA9685 16-channel 12-bit PWM driver (the servo board of most Donkeycars).

Register facts: the datasheet's register map (MODE1 0x00, MODE2 0x01, LEDn at 0x06 + 4n, PRE_SCALE 0xFE). Design notes:

* **One driver per chip.** :func:`get_pca9685` keeps one :class:`PCA9685` per (bus, address) on the shared
  :class:`~asyncdonkey.hw.i2c.I2CBus`. Donkeycar builds a new chip object per pin and each one re-runs the
  chip init, which zeroes channels another part already set (the steering servo goes limp when the throttle
  pin is opened). Here the second channel reuses the first one's driver and its init never runs again.
* **One process per chip.** The driver claims the chip (:meth:`~asyncdonkey.hw.i2c.I2CBus.claim`, a lock per
  bus and address) before it sends it anything, so a second car started on the same chip is refused with
  :class:`~asyncdonkey.hw.i2c.I2CDeviceInUse` naming the first, instead of resetting its outputs.
* **The init turns off what it finds, but says so.** A chip that is already generating pulses at init was left
  so by a program that has ended (its last pulses, perhaps a driving throttle, must not go on) or by one that
  takes no lock (Donkeycar, ``donkey calibrate``). The outputs still go off, as Donkeycar's init does, but the
  driver first reads them and logs a warning naming each channel and its pulse.
* **Frequency change as the datasheet asks:** read MODE1, write it back with SLEEP set (PRE_SCALE is only
  writable while the oscillator sleeps), write PRE_SCALE, restore MODE1 awake with auto-increment on, wait at
  least 500 µs for the oscillator, then set RESTART so the channels resume.
* **One transfer per channel update.** With auto-increment on, ON_L, ON_H, OFF_L, OFF_H go out as one 4-byte
  block write; the chip (MODE2.OCH = 0) applies them together at the STOP, so a servo never sees a pulse made of
  half the old and half the new value.
* **Pulses in ticks.** A pulse is the high time in 1/4096 of the PWM period, ON at count 0 and OFF at
  ``pulse``. 0 uses the full-off bit and 4096 the full-on bit, as Donkeycar's duty-cycle 0 and 1 do.

The sync methods (``*_sync``) block and are for worker threads and construction time; the async methods run
them on the bus's worker thread.
"""

from __future__ import annotations

import logging
import math
import time
from typing import Any

from .i2c import I2CBus, I2CBusRegistry, get_bus
from .pinspec import PCA9685Pin, parse_pca9685_pin

__all__ = [
    "ALL_LED_OFF_H",
    "ALL_LED_ON_L",
    "DEFAULT_ADDRESS",
    "LED0_ON_L",
    "MODE1",
    "MODE1_AI",
    "MODE1_ALLCALL",
    "MODE1_RESTART",
    "MODE1_SLEEP",
    "MODE2",
    "MODE2_OUTDRV",
    "OSCILLATOR_HZ",
    "PCA9685",
    "PRE_SCALE",
    "PWMChannel",
    "get_pca9685",
    "open_pwm_channel",
    "prescale_for",
    "pulse_of",
]

logger = logging.getLogger(__name__)

DEFAULT_ADDRESS = 0x40
OSCILLATOR_HZ = 25_000_000

MODE1 = 0x00
MODE2 = 0x01
LED0_ON_L = 0x06
ALL_LED_ON_L = 0xFA
ALL_LED_OFF_H = 0xFD
PRE_SCALE = 0xFE

MODE1_RESTART = 0x80
MODE1_AI = 0x20
MODE1_SLEEP = 0x10
MODE1_ALLCALL = 0x01
MODE2_OUTDRV = 0x04
FULL_BIT = 0x10  # bit 4 of LEDn_ON_H (full on) and LEDn_OFF_H (full off)

PRESCALE_MIN = 3
PRESCALE_MAX = 255
#: The oscillator needs 500 µs after SLEEP is cleared before RESTART may be written; a little margin.
OSCILLATOR_SETTLE_S = 0.0006
TICKS = 4096


def prescale_for(frequency_hz: float, oscillator_hz: float = OSCILLATOR_HZ) -> int:
    """PRE_SCALE for a PWM frequency: ``round(osc / (4096 * f)) - 1`` (60 Hz → 101, 50 Hz → 121).

    Raises ``ValueError`` when the result is outside the chip's 3..255 (about 24-1526 Hz on the internal
    25 MHz oscillator).
    """
    if not (isinstance(frequency_hz, int | float) and math.isfinite(frequency_hz) and frequency_hz > 0):
        raise ValueError(f"PCA9685 frequency must be a positive number of Hz, got {frequency_hz!r}")
    prescale = math.floor(oscillator_hz / (TICKS * frequency_hz) + 0.5) - 1
    if not PRESCALE_MIN <= prescale <= PRESCALE_MAX:
        lo = oscillator_hz / (TICKS * (PRESCALE_MAX + 1))
        hi = oscillator_hz / (TICKS * (PRESCALE_MIN + 1))
        raise ValueError(
            f"PCA9685 cannot run at {frequency_hz:g} Hz (prescale {prescale} outside {PRESCALE_MIN}..{PRESCALE_MAX});"
            f" the range is {lo:.1f}..{hi:.1f} Hz"
        )
    return prescale


def _check_channel(channel: int) -> None:
    if not isinstance(channel, int) or isinstance(channel, bool) or not 0 <= channel <= 15:
        raise ValueError(f"PCA9685 channel must be an int 0..15, got {channel!r}")


def channel_bytes(pulse: int) -> bytes:
    """The 4 register bytes (ON_L, ON_H, OFF_L, OFF_H) for a pulse of ``pulse`` ticks starting at count 0."""
    if pulse <= 0:
        return bytes((0, 0, 0, FULL_BIT))
    if pulse >= TICKS:
        return bytes((0, FULL_BIT, 0, 0))
    return bytes((0, 0, pulse & 0xFF, pulse >> 8))


def pulse_of(registers: bytes) -> int:
    """The high ticks per period that a channel's ON_L, ON_H, OFF_L, OFF_H describe (full-off wins)."""
    on_l, on_h, off_l, off_h = registers
    if off_h & FULL_BIT:
        return 0
    if on_h & FULL_BIT:
        return TICKS
    return ((off_l | (off_h & 0x0F) << 8) - (on_l | (on_h & 0x0F) << 8)) % TICKS


class PCA9685:
    """One PCA9685 chip. Prefer :func:`get_pca9685`, which shares one instance per (bus, address).

    Construction claims the chip for this process (:class:`~asyncdonkey.hw.i2c.I2CDeviceInUse` naming the
    owner if another process has it), probes it (a clear :class:`~asyncdonkey.hw.i2c.I2CDeviceNotFound` if
    nothing answers) and initialises it: MODE2 totem-pole outputs, every channel full-off (no stale pulse from
    a previous process; a warning names the channels that were generating one) unless
    ``reset_outputs=False``, then the frequency sequence, which leaves the chip awake with auto-increment on.
    """

    def __init__(
        self,
        bus: I2CBus,
        address: int = DEFAULT_ADDRESS,
        frequency_hz: float = 60,
        *,
        oscillator_hz: float = OSCILLATOR_HZ,
        reset_outputs: bool = True,
    ) -> None:
        self.bus = bus
        self.address = address
        self.oscillator_hz = oscillator_hz
        self.prescale = prescale_for(frequency_hz, oscillator_hz)
        self.requested_frequency_hz = float(frequency_hz)
        self.name = f"PCA9685 at 0x{address:02X} on I2C bus {bus.bus_number}"
        claimed = bus.claim(address, "PCA9685")  # before anything reaches the chip
        try:
            with bus.locked():
                mode1 = bus.probe_sync(address, MODE1, "PCA9685")
                bus.write_byte_data_sync(address, MODE2, MODE2_OUTDRV)
                if reset_outputs:
                    self._warn_of_pulses_left(mode1)
                    # a single-byte write: works before auto-increment is on
                    bus.write_byte_data_sync(address, ALL_LED_OFF_H, FULL_BIT)
                self._write_prescale(self.prescale)
        except BaseException:
            if claimed:
                bus.unclaim(address)
            raise

    def __repr__(self) -> str:
        return f"<{self.name}, {self.frequency_hz:.2f} Hz>"

    @property
    def frequency_hz(self) -> float:
        """The PWM frequency the chip actually runs at (the prescale rounds the requested one)."""
        return self.oscillator_hz / (TICKS * (self.prescale + 1))

    @property
    def period_s(self) -> float:
        return 1.0 / self.frequency_hz

    def _pulses_left_sync(self, mode1: int) -> dict[int, int]:
        """The pulses (ticks, by channel) an awake chip is generating before the init, from its registers."""
        if mode1 & (MODE1_SLEEP | MODE1_RESTART):
            return {}  # asleep, or halted until a RESTART: no output
        bus, addr = self.bus, self.address
        if mode1 & MODE1_AI:  # two 32-byte bursts (the SMBus limit) cover the 64 LED registers
            raw = bus.read_i2c_block_data_sync(addr, LED0_ON_L, 32) + bus.read_i2c_block_data_sync(
                addr, LED0_ON_L + 32, 32
            )
        else:  # without auto-increment (as Donkeycar's Adafruit driver leaves it) one register per read
            raw = bytes(bus.read_byte_data_sync(addr, LED0_ON_L + i) for i in range(4 * 16))
        pulses = {ch: pulse_of(raw[4 * ch : 4 * ch + 4]) for ch in range(16)}
        return {ch: p for ch, p in pulses.items() if p}

    def _warn_of_pulses_left(self, mode1: int) -> None:
        left = self._pulses_left_sync(mode1)
        if left:
            channels = ", ".join(f"channel {ch} ({p} ticks)" for ch, p in left.items())
            logger.warning(
                "%s was already generating pulses on %s, left by a program that has ended or one that takes no "
                "device lock (Donkeycar, donkey calibrate); the init turns them off",
                self.name,
                channels,
            )

    def _write_prescale(self, prescale: int) -> None:
        bus, addr = self.bus, self.address
        with bus.locked():
            old = bus.read_byte_data_sync(addr, MODE1)
            bus.write_byte_data_sync(addr, MODE1, (old & ~MODE1_RESTART) | MODE1_SLEEP)
            bus.write_byte_data_sync(addr, PRE_SCALE, prescale)
            awake = (old | MODE1_AI) & ~(MODE1_SLEEP | MODE1_RESTART)
            bus.write_byte_data_sync(addr, MODE1, awake)
            time.sleep(OSCILLATOR_SETTLE_S)
            bus.write_byte_data_sync(addr, MODE1, awake | MODE1_RESTART)

    # ----------------------------------------------------------------------------------------- sync
    def set_frequency_sync(self, frequency_hz: float) -> None:
        """Change the PWM frequency of all 16 channels (the SLEEP / PRE_SCALE / RESTART sequence)."""
        prescale = prescale_for(frequency_hz, self.oscillator_hz)
        self._write_prescale(prescale)
        self.prescale = prescale
        self.requested_frequency_hz = float(frequency_hz)

    def set_pulse_sync(self, channel: int, pulse: int) -> None:
        """Output a pulse of ``pulse`` ticks (of 4096 per period) on ``channel``: 0 is off, 4096 is always on."""
        _check_channel(channel)
        self.bus.write_i2c_block_data_sync(self.address, LED0_ON_L + 4 * channel, channel_bytes(int(pulse)))

    def set_pwm_sync(self, channel: int, on: int, off: int) -> None:
        """Raw ON/OFF counts (0..4095, bit 12 = full on/off), as Adafruit's ``set_pwm``."""
        _check_channel(channel)
        data = (on & 0xFF, (on >> 8) & 0x1F, off & 0xFF, (off >> 8) & 0x1F)
        self.bus.write_i2c_block_data_sync(self.address, LED0_ON_L + 4 * channel, data)

    def full_off_sync(self, channel: int) -> None:
        self.set_pulse_sync(channel, 0)

    def read_channel_sync(self, channel: int) -> tuple[int, int]:
        """(ON, OFF) as 13-bit values read back from the chip (bit 12 is the full-on / full-off flag)."""
        _check_channel(channel)
        b = self.bus.read_i2c_block_data_sync(self.address, LED0_ON_L + 4 * channel, 4)
        return b[0] | (b[1] & 0x1F) << 8, b[2] | (b[3] & 0x1F) << 8

    # ---------------------------------------------------------------------------------------- async
    async def set_frequency(self, frequency_hz: float) -> None:
        await self.bus.call(self.set_frequency_sync, frequency_hz)

    async def set_pulse(self, channel: int, pulse: int) -> None:
        await self.bus.call(self.set_pulse_sync, channel, pulse)

    async def full_off(self, channel: int) -> None:
        await self.bus.call(self.set_pulse_sync, channel, 0)

    def channel(self, channel: int) -> PWMChannel:
        """A handle on one output of this chip."""
        _check_channel(channel)
        return PWMChannel(self, channel)


class PWMChannel:
    """One PCA9685 output: what a servo or an ESC is plugged into. Pulses are in ticks of 4096 per period."""

    __slots__ = ("channel", "chip", "name")

    def __init__(self, chip: PCA9685, channel: int) -> None:
        _check_channel(channel)
        self.chip = chip
        self.channel = channel
        self.name = f"channel {channel} of {chip.name}"

    def __repr__(self) -> str:
        return f"<PWMChannel {self.name}>"

    async def set_pulse(self, pulse: int) -> None:
        await self.chip.bus.call(self.chip.set_pulse_sync, self.channel, pulse)

    def set_pulse_sync(self, pulse: int) -> None:
        self.chip.set_pulse_sync(self.channel, pulse)

    async def full_off(self) -> None:
        await self.set_pulse(0)

    def safety_route(self, pulse: int) -> dict[str, Any] | None:
        """What another process needs to put ``pulse`` on this output by itself, or ``None`` if it cannot.

        The route is plain data (the safety process is a separate interpreter that imports no driver): the bus
        (:meth:`~asyncdonkey.hw.i2c.I2CBus.cross_process_spec`), the chip's address, the channel's first
        register and the four register bytes of the pulse. The block write needs the chip's auto-increment, so
        the route names MODE1 and its AI bit: where a power glitch has reset MODE1, the bytes go one at a time.
        """
        spec = self.chip.bus.cross_process_spec()
        if spec is None:
            return None
        return {
            "smbus": spec,
            "address": self.chip.address,
            "register": LED0_ON_L + 4 * self.channel,
            "data": list(channel_bytes(int(pulse))),
            "auto_increment": [MODE1, MODE1_AI],
            "name": self.name,
        }


def get_pca9685(bus: I2CBus, address: int = DEFAULT_ADDRESS, frequency_hz: float = 60) -> PCA9685:
    """The one :class:`PCA9685` at ``address`` on ``bus``, initialised on first use only.

    Asking again for the same chip returns the same driver without touching the chip, so channels already
    set keep their pulses. Asking for a different frequency is an error: all 16 channels share one.
    """
    chip = bus.shared(("PCA9685", address), lambda: PCA9685(bus, address, frequency_hz))
    if prescale_for(frequency_hz, chip.oscillator_hz) != chip.prescale:
        raise ValueError(
            f"{chip.name} already runs at {chip.requested_frequency_hz:g} Hz; cannot also use it at "
            f"{frequency_hz:g} Hz (all 16 channels share one frequency)"
        )
    return chip


def open_pwm_channel(
    spec: str | PCA9685Pin, frequency_hz: float = 60, *, buses: I2CBusRegistry | None = None
) -> PWMChannel:
    """Open a Donkeycar pin spec such as ``"PCA9685.1:40.1"`` as a :class:`PWMChannel`.

    ``buses`` is an :class:`~asyncdonkey.hw.i2c.I2CBusRegistry` (default: the real buses).
    """
    pin = spec if isinstance(spec, PCA9685Pin) else parse_pca9685_pin(spec)
    bus = get_bus(pin.bus) if buses is None else buses.get(pin.bus)
    return get_pca9685(bus, pin.address, frequency_hz).channel(pin.channel)
