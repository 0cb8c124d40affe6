"""Simulated I2C buses with PCA9685 and MPU6050/MPU9250 register models, reached through the real smbus2.

How the simulation sits under smbus2 (and why there): smbus2 talks to the kernel only through ``ioctl`` on
``/dev/i2c-N`` (``I2C_SLAVE``, ``I2C_FUNCS``, ``I2C_SMBUS``, ``I2C_RDWR``), passing its own ctypes structs.
:class:`SimulatedSMBus` is an ``smbus2.SMBus`` whose methods are smbus2's own functions (the same code
objects, re-bound so that the name ``ioctl`` resolves to this module's simulated i2c-dev driver), so every
line of smbus2 that builds and reads those structs runs as on a Raspberry Pi. The simulated driver does what
the kernel's i2c-dev and SMBus emulation do: it decodes the structs, turns each SMBus call into I2C messages
(``read_byte_data`` is a one-byte write of the register then a one-byte read, in one transaction) and hands
the messages to the device models at the addressed slots. No global state of smbus2 is patched.

The models behave at the register level like the chips (their datasheets' register maps), so a driver bug
shows up as a wrong register or a wrong output, not as a mismatch with a recorded call:

* :class:`PCA9685Model`: power-on state (asleep, all channels full-off), PRE_SCALE only writable while SLEEP,
  the register pointer auto-increments only with MODE1.AI, ALL_LED_* writes reach every channel and read back
  0, RESTART semantics (set when the running chip is put to sleep, cleared by writing 1 at least 500 µs after
  waking, channels halted in between), full-on / full-off bits, and the output pulse of each channel.
* :class:`MPU6050Model`: asleep at power-up (data registers read 0), WHO_AM_I (0x68, or 0x71 for the MPU9250
  variant), DEVICE_RESET, accel/gyro full-scale ranges, and a physical state (acceleration in g, rotation in
  °/s, temperature in °C) encoded into big-endian registers, latched at the start of each transaction as the
  chip's shadow registers do (a burst read is one atomic sample).

Fault injection per address: :meth:`SimulatedI2CBus.nack` makes the next N transactions (or all of them)
fail with ``OSError`` errno 121 (EREMOTEIO, what a Pi reports for a NACK); an address with no device fails the
same way. :attr:`SimulatedI2CBus.transfer_delay_s` makes each transaction take real time (a slow or
clock-stretched bus). :attr:`SimulatedI2CBus.log` records the messages on the wire as an extra for tests.

Usage::

    sim = I2CSimulator()
    pca = sim.attach(PCA9685Model(), address=0x40, bus=1)
    buses = sim.registry()                      # an I2CBusRegistry over the simulated buses
    steering = PWMSteering("PCA9685.1:40.1", buses=buses)
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import json
import os
import socket
import socketserver
import tempfile
import threading
import time
import types
import weakref
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import smbus2
import smbus2.smbus2 as _smbus2_module

from ..hw.i2c import I2CBusRegistry

__all__ = [
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
]

# ----------------------------------------------------------------------------------- the wire: messages


@dataclass(frozen=True, slots=True)
class I2CMessage:
    """One I2C message: ``data`` written to, or read from, ``address``."""

    address: int
    read: bool
    data: bytes


@dataclass(frozen=True, slots=True)
class I2CTransfer:
    """One transaction (START ... STOP) on a simulated bus, as the log records it.

    ``kind`` says how it was asked for (``"smbus:byte_data"``, ``"smbus:i2c_block_data"``, ``"rdwr"``, ...);
    ``error`` is the errno it failed with, if any (then ``messages`` holds what was attempted, reads empty).
    """

    kind: str
    messages: tuple[I2CMessage, ...]
    error: int | None = None

    @property
    def address(self) -> int:
        return self.messages[0].address if self.messages else 0

    @property
    def written(self) -> bytes:
        return b"".join(m.data for m in self.messages if not m.read)

    @property
    def read_back(self) -> bytes:
        return b"".join(m.data for m in self.messages if m.read)


# ------------------------------------------------------------------------------------- device models


class I2CDeviceModel:
    """A device on a simulated bus, seen as the I2C bus sees it: transactions of write and read messages."""

    def begin(self) -> None:
        """START of a transaction addressed to this device."""

    def write(self, data: bytes) -> None:
        """A write message (the bytes after the address byte)."""

    def read(self, length: int) -> bytes:
        """A read message: return ``length`` bytes."""
        return bytes(length)

    def end(self) -> None:
        """STOP: the transaction is over."""


class RegisterDeviceModel(I2CDeviceModel):
    """The usual register-file protocol: the first byte written sets the register pointer, later bytes of
    the write go to the pointed register, reads come from it, and the pointer advances by
    :meth:`next_register` after each byte.
    """

    def __init__(self) -> None:
        self.pointer = 0

    def read_register(self, register: int) -> int:
        raise NotImplementedError

    def write_register(self, register: int, value: int) -> None:
        raise NotImplementedError

    def next_register(self, register: int) -> int:
        return (register + 1) & 0xFF

    def write(self, data: bytes) -> None:
        if not data:
            return
        self.pointer = data[0]
        for value in data[1:]:
            self.write_register(self.pointer, value)
            self.pointer = self.next_register(self.pointer)

    def read(self, length: int) -> bytes:
        out = bytearray()
        for _ in range(length):
            out.append(self.read_register(self.pointer) & 0xFF)
            self.pointer = self.next_register(self.pointer)
        return bytes(out)


class PCA9685Model(RegisterDeviceModel):
    """A PCA9685 at the register level (NXP datasheet rev. 4), with the output pulse each channel produces.

    Args:
        clock: real-time seconds (``time.monotonic``) used for the 500 µs oscillator start-up rule; the
            driver's wait happens in a worker thread in real time, so this stays real even on a virtual loop.
        oscillator_hz: the internal oscillator (25 MHz).

    Observations: :meth:`pulse` (ticks of 4096 the output is high per period, 0 while asleep or halted),
    :meth:`pulse_us`, :attr:`frequency_hz`, :attr:`running`, :meth:`channel_registers`, :attr:`registers`,
    :attr:`history` (per channel, every output pulse it took, recorded at each STOP), :attr:`pulse_changes` (the
    same changes with the model clock's time of the STOP, so a test sees a pulse held for a moment even if it
    could not look at that moment), and counters of what
    the chip ignored: ``prescale_writes_ignored`` (PRE_SCALE written while awake) and ``early_restarts``
    (RESTART written less than 500 µs after waking).
    """

    MODE1 = 0x00
    MODE2 = 0x01
    LED0 = 0x06
    LAST_LED = 0x45
    ALL_LED = 0xFA
    PRE_SCALE = 0xFE
    RESTART, AI, SLEEP = 0x80, 0x20, 0x10
    OCH = 0x08
    POWER_ON = {0x00: 0x11, 0x01: 0x04, 0x02: 0xE2, 0x03: 0xE4, 0x04: 0xE8, 0x05: 0xE0, 0xFE: 0x1E}

    def __init__(self, *, clock: Callable[[], float] = time.monotonic, oscillator_hz: float = 25_000_000) -> None:
        super().__init__()
        self.clock = clock
        self.oscillator_hz = oscillator_hz
        self.power_cycle()

    def power_cycle(self) -> None:
        """Back to the power-on state: asleep, prescale 30 (200 Hz), every channel full-off."""
        self.registers = bytearray(256)
        for reg, value in self.POWER_ON.items():
            self.registers[reg] = value
        for ch in range(16):
            self.registers[self.LED0 + 4 * ch + 3] = 0x10  # LEDn_OFF_H full-off
        self.pointer = 0
        self.restart_pending = False
        self.woke_at: float | None = None
        self.prescale_writes_ignored = 0
        self.early_restarts = 0
        self._pwm_written = False
        self.history: dict[int, list[int]] = {ch: [0] for ch in range(16)}
        self.pulse_changes: dict[int, list[tuple[float, int]]] = {ch: [(self.clock(), 0)] for ch in range(16)}

    # -- observations -----------------------------------------------------------------------------------
    @property
    def mode1(self) -> int:
        return self.read_register(self.MODE1)

    @property
    def prescale(self) -> int:
        return self.registers[self.PRE_SCALE]

    @property
    def frequency_hz(self) -> float:
        return self.oscillator_hz / (4096 * (self.prescale + 1))

    @property
    def asleep(self) -> bool:
        return bool(self.registers[self.MODE1] & self.SLEEP)

    @property
    def running(self) -> bool:
        """The PWM outputs are active: oscillator on and no restart pending."""
        return not self.asleep and not self.restart_pending

    def channel_registers(self, channel: int) -> bytes:
        """ON_L, ON_H, OFF_L, OFF_H of ``channel`` as stored."""
        base = self.LED0 + 4 * channel
        return bytes(self.registers[base : base + 4])

    def programmed_pulse(self, channel: int) -> int:
        """The high time in ticks the channel's registers describe, whether or not the chip is running."""
        on_l, on_h, off_l, off_h = self.channel_registers(channel)
        if off_h & 0x10:
            return 0  # full-off wins over full-on
        if on_h & 0x10:
            return 4096
        on = on_l | (on_h & 0x0F) << 8
        off = off_l | (off_h & 0x0F) << 8
        return (off - on) % 4096

    def pulse(self, channel: int) -> int:
        """What the output pin does: high ticks per period (0 while asleep or halted for RESTART)."""
        return self.programmed_pulse(channel) if self.running else 0

    def pulse_us(self, channel: int) -> float:
        return self.pulse(channel) * 1e6 / (self.frequency_hz * 4096)

    # -- register semantics -----------------------------------------------------------------------------
    def read_register(self, register: int) -> int:
        if register == self.MODE1:
            return (self.registers[self.MODE1] & ~self.RESTART & 0xFF) | (self.RESTART if self.restart_pending else 0)
        if self.ALL_LED <= register <= self.ALL_LED + 3:
            return 0  # ALL_LED_* read back as 0
        if self.LAST_LED < register < self.ALL_LED:
            return 0  # reserved
        return self.registers[register]

    def write_register(self, register: int, value: int) -> None:
        regs = self.registers
        if register == self.MODE1:
            self._write_mode1(value)
        elif register == self.MODE2:
            regs[register] = value & 0x1F
        elif register == self.PRE_SCALE:
            if regs[self.MODE1] & self.SLEEP:
                regs[register] = max(value, 3)  # the hardware forces a minimum of 3
            else:
                self.prescale_writes_ignored += 1
        elif self.LED0 <= register <= self.LAST_LED:
            regs[register] = value
            self._pwm_written = True
        elif self.ALL_LED <= register <= self.ALL_LED + 3:
            offset = register - self.ALL_LED
            for ch in range(16):
                regs[self.LED0 + 4 * ch + offset] = value
            self._pwm_written = True
        elif register <= 0x05:
            regs[register] = value
        # 0x46..0xF9 reserved, 0xFF test mode: ignored

    def _write_mode1(self, value: int) -> None:
        regs = self.registers
        was_asleep = bool(regs[self.MODE1] & self.SLEEP)
        sleep = bool(value & self.SLEEP)
        if sleep and not was_asleep:
            if any(self.programmed_pulse(ch) for ch in range(16)) and not self.restart_pending:
                self.restart_pending = True  # the running chip was put to sleep
            self.woke_at = None
        elif was_asleep and not sleep:
            self.woke_at = self.clock()
        regs[self.MODE1] = value & ~self.RESTART & 0xFF
        if value & self.RESTART and not sleep and self.restart_pending:
            if self.woke_at is not None and self.clock() - self.woke_at >= 0.0005:
                self.restart_pending = False
            else:
                self.early_restarts += 1  # the oscillator is not stable yet: the write has no effect

    def next_register(self, register: int) -> int:
        if not self.registers[self.MODE1] & self.AI:
            return register
        if register == self.LAST_LED:
            return self.MODE1
        return (register + 1) & 0xFF

    def begin(self) -> None:
        self._pwm_written = False

    def end(self) -> None:
        # MODE2.OCH = 0: outputs change on STOP; a PWM register write there also clears a pending RESTART
        if self._pwm_written and self.restart_pending and not self.registers[self.MODE2] & self.OCH:
            self.restart_pending = False
        self._pwm_written = False
        for ch in range(16):
            p = self.pulse(ch)
            h = self.history[ch]
            if h[-1] != p:
                h.append(p)
                self.pulse_changes[ch].append((self.clock(), p))


class MPU6050Model(RegisterDeviceModel):
    """An MPU6050 (or, with ``variant="mpu9250"``, the MPU9250's accel/gyro part) at the register level.

    Set the physical state with :meth:`set_motion` or the attributes ``accel_g``, ``gyro_dps``, ``temp_c``;
    each transaction latches it into the data registers (0x3B..0x48) using the configured full-scale ranges,
    saturating at the int16 limits as the sensor does. While asleep the data registers keep their last values
    (all 0 from power-up). ``samples`` counts the latches.
    """

    ACCEL_LSB_PER_G = (16384.0, 8192.0, 4096.0, 2048.0)
    GYRO_LSB_PER_DPS = (131.0, 65.5, 32.8, 16.4)
    WHO_AM_I = 0x75
    PWR_MGMT_1 = 0x6B
    DATA = 0x3B
    READ_ONLY = frozenset({0x3A, 0x75, *range(0x3B, 0x61)})

    def __init__(
        self,
        variant: str = "mpu6050",
        *,
        accel_g: Sequence[float] = (0.0, 0.0, 1.0),
        gyro_dps: Sequence[float] = (0.0, 0.0, 0.0),
        temp_c: float = 25.0,
    ) -> None:
        super().__init__()
        if variant not in ("mpu6050", "mpu9250"):
            raise ValueError(f"MPU6050Model: variant must be 'mpu6050' or 'mpu9250', got {variant!r}")
        self.variant = variant
        self.who_am_i = 0x68 if variant == "mpu6050" else 0x71
        self.accel_g = tuple(accel_g)
        self.gyro_dps = tuple(gyro_dps)
        self.temp_c = float(temp_c)
        self.power_cycle()

    def power_cycle(self) -> None:
        self.registers = bytearray(128)
        self.registers[self.PWR_MGMT_1] = 0x40  # asleep
        self.registers[self.WHO_AM_I] = self.who_am_i
        self.pointer = 0
        self.samples = 0

    def set_motion(
        self,
        accel_g: Sequence[float] | None = None,
        gyro_dps: Sequence[float] | None = None,
        temp_c: float | None = None,
    ) -> None:
        if accel_g is not None:
            self.accel_g = tuple(accel_g)
        if gyro_dps is not None:
            self.gyro_dps = tuple(gyro_dps)
        if temp_c is not None:
            self.temp_c = float(temp_c)

    @property
    def asleep(self) -> bool:
        return bool(self.registers[self.PWR_MGMT_1] & 0x40)

    @property
    def accel_range_index(self) -> int:
        return (self.registers[0x1C] >> 3) & 3

    @property
    def gyro_range_index(self) -> int:
        return (self.registers[0x1B] >> 3) & 3

    @property
    def dlpf(self) -> int:
        return self.registers[0x1A] & 7

    def temperature_raw(self, temp_c: float) -> float:
        if self.variant == "mpu6050":
            return (temp_c - 36.53) * 340.0
        return (temp_c - 21.0) * 333.87

    def _latch(self) -> None:
        a = self.ACCEL_LSB_PER_G[self.accel_range_index]
        g = self.GYRO_LSB_PER_DPS[self.gyro_range_index]
        raws = [v * a for v in self.accel_g] + [self.temperature_raw(self.temp_c)] + [v * g for v in self.gyro_dps]
        out = bytearray()
        for r in raws:
            out += max(-32768, min(32767, round(r))).to_bytes(2, "big", signed=True)
        self.registers[self.DATA : self.DATA + 14] = out
        self.samples += 1

    def begin(self) -> None:
        if not self.asleep:
            self._latch()

    def read_register(self, register: int) -> int:
        return self.registers[register & 0x7F]

    def write_register(self, register: int, value: int) -> None:
        register &= 0x7F
        if register in self.READ_ONLY:
            return
        if register == self.PWR_MGMT_1 and value & 0x80:
            self.power_cycle()  # DEVICE_RESET: registers to defaults, the bit clears itself
            return
        self.registers[register] = value

    def next_register(self, register: int) -> int:
        return (register + 1) & 0x7F


# ------------------------------------------------------------------------------------------ the bus


class _Fault:
    __slots__ = ("errno", "remaining")

    def __init__(self, remaining: int | None, err: int) -> None:
        self.remaining = remaining
        self.errno = err


class SimulatedI2CBus:
    """One simulated I2C adapter: devices at addresses, an adapter lock, faults, delay and a transfer log."""

    def __init__(self, number: int, *, log_size: int = 10_000) -> None:
        self.number = number
        self.devices: dict[int, I2CDeviceModel] = {}
        self.transfer_delay_s = 0.0
        self.absent_errno = errno.EREMOTEIO
        self.log: deque[I2CTransfer] = deque(maxlen=log_size)
        self.transactions = 0
        self._faults: dict[int, _Fault] = {}
        self._lock = threading.Lock()

    def attach(self, address: int, device: I2CDeviceModel) -> None:
        if not 0 <= address <= 0x7F:
            raise ValueError(f"I2C address must be 7-bit (0..0x7F), got {address!r}")
        with self._lock:
            self.devices[address] = device

    def detach(self, address: int) -> None:
        """Unplug the device at ``address``: transfers to it now fail as for an absent device."""
        with self._lock:
            self.devices.pop(address, None)

    def nack(self, address: int, times: int | None = 1, err: int = errno.EREMOTEIO) -> None:
        """Make the next ``times`` transactions to ``address`` fail with ``OSError(err)`` (None: all of them)."""
        with self._lock:
            self._faults[address] = _Fault(times, err)

    def clear_faults(self, address: int | None = None) -> None:
        with self._lock:
            if address is None:
                self._faults.clear()
            else:
                self._faults.pop(address, None)

    def transaction(self, kind: str, messages: Sequence[tuple[int, bool, bytes | int]]) -> list[bytes]:
        """Run one START ... STOP transaction; each message is ``(address, read, data or read length)``.

        Returns what each read message got (b"" for writes). Raises ``OSError`` like the kernel does.
        """
        with self._lock:
            self.transactions += 1
            if self.transfer_delay_s:
                time.sleep(self.transfer_delay_s)
            planned = tuple(
                I2CMessage(addr, read, b"" if read else bytes(payload))  # type: ignore[arg-type]
                for addr, read, payload in messages
            )
            for addr in dict.fromkeys(m.address for m in planned):
                fault = self._faults.get(addr)
                err = None
                if fault is not None:
                    err = fault.errno
                    if fault.remaining is not None:
                        fault.remaining -= 1
                        if fault.remaining <= 0:
                            del self._faults[addr]
                elif addr not in self.devices:
                    err = self.absent_errno
                if err is not None:
                    self.log.append(I2CTransfer(kind, planned, err))
                    raise OSError(err, os.strerror(err))
            touched: list[I2CDeviceModel] = []
            results: list[bytes] = []
            done: list[I2CMessage] = []
            for addr, read, payload in messages:
                dev = self.devices[addr]
                if dev not in touched:
                    touched.append(dev)
                    dev.begin()
                if read:
                    data = bytes(dev.read(int(payload)))  # type: ignore[arg-type]
                else:
                    data = bytes(payload)  # type: ignore[arg-type]
                    dev.write(data)
                results.append(data if read else b"")
                done.append(I2CMessage(addr, read, data))
            for dev in touched:
                dev.end()
            self.log.append(I2CTransfer(kind, tuple(done)))
            return results


class I2CSimulator:
    """A set of simulated I2C buses (by number) and the smbus2 factory that opens them.

    :meth:`serve` makes the buses reachable from other processes (:class:`RemoteI2CSimulator`), as a real
    ``/dev/i2c-N`` is reachable from every process on a Raspberry Pi: the car in one process and its safety
    process in another then drive one register model, which the test reads in its own.
    """

    def __init__(self) -> None:
        self.buses: dict[int, SimulatedI2CBus] = {}
        self._lock = threading.Lock()
        #: the Unix socket other processes reach these buses at (``None`` until :meth:`serve`)
        self.endpoint: str | None = None
        self._server: _BusServer | None = None

    def bus(self, number: int = 1) -> SimulatedI2CBus:
        """The simulated adapter ``number`` (``/dev/i2c-<number>``), created on first use."""
        with self._lock:
            b = self.buses.get(number)
            if b is None:
                b = self.buses[number] = SimulatedI2CBus(number)
            return b

    def adapter(self, number: int) -> SimulatedI2CBus | None:
        """The adapter a :class:`SimulatedSMBus` opens as ``/dev/i2c-<number>`` (``None``: no such bus)."""
        return self.buses.get(number)

    def attach(self, device: Any, address: int, bus: int = 1) -> Any:
        """Plug ``device`` in at ``address`` on bus ``bus``; returns the device."""
        self.bus(bus).attach(address, device)
        return device

    def smbus(self, bus: int | str) -> SimulatedSMBus:
        """Open a simulated bus as smbus2 would (``SMBus(1)`` or ``SMBus("/dev/i2c-1")``)."""
        return SimulatedSMBus(bus, simulator=self)

    def registry(self, **bus_kwargs: Any) -> I2CBusRegistry:
        """An :class:`~asyncdonkey.hw.i2c.I2CBusRegistry` whose buses are these simulated ones."""
        return I2CBusRegistry(smbus_factory=self.smbus, **bus_kwargs)

    def cross_process_opener(self, bus: int) -> dict[str, Any] | None:
        """How another process opens bus ``bus`` of this simulator: only once it is served."""
        if self.endpoint is None:
            return None
        return {"opener": f"{__name__}:open_served_smbus", "args": [self.endpoint, bus]}

    def device_lock_path(self, bus: int, address: int) -> str | None:
        """The lock file that makes one process the owner of a chip on these buses, for the drivers of every
        process that opens them (:meth:`~asyncdonkey.hw.i2c.I2CBus.lock_path`): beside the socket, named after
        it (so two simulators never share one), removed by :meth:`close`. ``None`` until served."""
        return None if self.endpoint is None else _device_lock_path(self.endpoint, bus, address)

    def serve(self, path: str | None = None) -> str:
        """Serve these buses on a Unix socket (a fresh temporary one unless ``path``); returns its path.

        Each transaction from another process runs on this process's bus objects, under the same adapter lock
        as local ones, so the models see one bus, whoever drives it. Idempotent; :meth:`close` stops serving.
        """
        with self._lock:
            if self._server is None:
                if path is None:
                    folder = tempfile.mkdtemp(prefix="asyncdonkey-i2c-")
                    path = os.path.join(folder, "i2c.sock")
                self._server = _BusServer(path, self)
                threading.Thread(
                    target=self._server.serve_forever,
                    args=(SERVER_POLL_S,),
                    name="i2c-simulator-server",
                    daemon=True,
                ).start()
                self.endpoint = path
            return self.endpoint  # type: ignore[return-value]

    def close(self) -> None:
        """Stop serving (connected clients' next transactions fail with EIO)."""
        with self._lock:
            server, self._server = self._server, None
            path, self.endpoint = self.endpoint, None
        if server is not None:
            server.shutdown()
            server.server_close()
            for conn in list(server.connections):
                with contextlib.suppress(OSError):
                    conn.shutdown(socket.SHUT_RDWR)
            if path is not None:
                folder, mine = os.path.split(path)
                with contextlib.suppress(OSError):
                    os.unlink(path)
                    for name in os.listdir(folder):  # the device locks of these buses (device_lock_path)
                        if name.startswith(mine + ".i2c-") and name.endswith(".lock"):
                            os.unlink(os.path.join(folder, name))
                    os.rmdir(folder)

    def __enter__(self) -> I2CSimulator:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# ------------------------------------------------------------------ the buses, served to other processes
#
# One JSON object a line each way over a Unix stream socket. A request is {"bus": N, "kind": str, "messages":
# [[address, read, hex data or read length], ...]} and its answer {"ok": [hex, ...]} (what each message read)
# or {"errno": E}; {"buses": true} answers {"buses": [N, ...]}. JSON keeps the wire readable in a capture and
# needs nothing but the standard library on either side.


#: How often the serving thread looks for :meth:`I2CSimulator.close`: ``close()`` waits up to this long (the
#: standard library's 0.5 s made every test with a served simulator half a second longer).
SERVER_POLL_S = 0.02


class _BusHandler(socketserver.StreamRequestHandler):
    server: _BusServer

    def setup(self) -> None:
        super().setup()
        self.server.connections.add(self.connection)

    def finish(self) -> None:
        self.server.connections.discard(self.connection)
        super().finish()

    def handle(self) -> None:
        sim = self.server.simulator
        try:
            for line in self.rfile:
                request = json.loads(line)
                if request.get("buses"):
                    answer: dict[str, Any] = {"buses": sorted(sim.buses)}
                else:
                    answer = self._transaction(sim, request)
                self.wfile.write(json.dumps(answer).encode() + b"\n")
        except OSError:  # the client went away mid-request (a car killed with SIGKILL): nothing to answer
            return

    @staticmethod
    def _transaction(sim: I2CSimulator, request: dict[str, Any]) -> dict[str, Any]:
        bus = sim.adapter(int(request["bus"]))
        if bus is None:
            return {"errno": errno.ENODEV}
        messages = [
            (int(addr), bool(read), int(payload) if read else bytes.fromhex(payload))
            for addr, read, payload in request["messages"]
        ]
        try:
            results = bus.transaction(str(request["kind"]), messages)
        except OSError as exc:
            return {"errno": exc.errno or errno.EIO}
        return {"ok": [r.hex() for r in results]}


class _BusServer(socketserver.ThreadingUnixStreamServer):
    daemon_threads = True

    def __init__(self, path: str, simulator: I2CSimulator) -> None:
        self.simulator = simulator
        self.connections: set[socket.socket] = set()
        super().__init__(path, _BusHandler)


class _RemoteAdapter:
    """One bus of a served simulator, seen from another process: ``transaction()`` as on the local adapter."""

    def __init__(self, endpoint: str, number: int) -> None:
        self.endpoint = endpoint
        self.number = number
        self._lock = threading.Lock()
        self._sock: socket.socket | None = None
        self._rfile: Any = None

    def _connect(self) -> None:
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        sock.connect(self.endpoint)
        self._sock, self._rfile = sock, sock.makefile("rb")

    def transaction(self, kind: str, messages: Sequence[tuple[int, bool, bytes | int]]) -> list[bytes]:
        wire = [[a, r, int(p) if r else bytes(p).hex()] for a, r, p in messages]  # type: ignore[arg-type]
        request = json.dumps({"bus": self.number, "kind": kind, "messages": wire}).encode() + b"\n"
        with self._lock:
            try:
                if self._sock is None:
                    self._connect()
                assert self._sock is not None
                self._sock.sendall(request)
                line = self._rfile.readline()
            except OSError as exc:
                self.close()
                raise OSError(errno.EIO, f"simulated I2C bus {self.number} at {self.endpoint}: {exc}") from exc
            if not line:
                self.close()
                raise OSError(errno.EIO, f"simulated I2C bus {self.number} at {self.endpoint}: server gone")
        answer = json.loads(line)
        if "errno" in answer:
            err = int(answer["errno"])
            raise OSError(err, os.strerror(err))
        return [bytes.fromhex(h) for h in answer["ok"]]

    def close(self) -> None:
        sock, self._sock = self._sock, None
        if sock is not None:
            with contextlib.suppress(OSError):
                sock.close()


class RemoteI2CSimulator:
    """The buses of an :class:`I2CSimulator` served by another process (:meth:`I2CSimulator.serve`).

    Opens them through smbus2's own code exactly as the local simulator does, so a driver in a child process
    (a car under test, its safety process) sees the same register models as the test that reads them::

        buses = RemoteI2CSimulator(endpoint).registry()
        throttle = PWMThrottle("PCA9685.1:40.0", buses=buses)
    """

    def __init__(self, endpoint: str) -> None:
        self.endpoint = endpoint
        self._adapters: dict[int, _RemoteAdapter] = {}
        self._known: list[int] | None = None
        self._lock = threading.Lock()

    def adapter(self, number: int) -> _RemoteAdapter | None:
        with self._lock:
            if self._known is None:
                probe = _RemoteAdapter(self.endpoint, -1)
                try:
                    probe._connect()
                    assert probe._sock is not None
                    probe._sock.sendall(b'{"buses": true}\n')
                    self._known = list(json.loads(probe._rfile.readline())["buses"])
                finally:
                    probe.close()
            if number not in self._known:
                return None
            a = self._adapters.get(number)
            if a is None:
                a = self._adapters[number] = _RemoteAdapter(self.endpoint, number)
            return a

    def smbus(self, bus: int | str) -> SimulatedSMBus:
        return SimulatedSMBus(bus, simulator=self)

    def registry(self, **bus_kwargs: Any) -> I2CBusRegistry:
        return I2CBusRegistry(smbus_factory=self.smbus, **bus_kwargs)

    def cross_process_opener(self, bus: int) -> dict[str, Any]:
        """Another process opens the same served buses the same way."""
        return {"opener": f"{__name__}:open_served_smbus", "args": [self.endpoint, bus]}

    def device_lock_path(self, bus: int, address: int) -> str:
        """The same lock file as the serving simulator's :meth:`I2CSimulator.device_lock_path`."""
        return _device_lock_path(self.endpoint, bus, address)


def _device_lock_path(endpoint: str, bus: int, address: int) -> str:
    return f"{endpoint}.i2c-{int(bus)}-0x{int(address):02x}.lock"


def open_served_smbus(endpoint: str, bus: int) -> SimulatedSMBus:
    """Bus ``bus`` of the simulator served at ``endpoint``, through smbus2's own code (the safety process's opener
    in tests)."""
    return RemoteI2CSimulator(endpoint).smbus(int(bus))


# ------------------------------------------------------------------------ the simulated i2c-dev driver

_I2C_SLAVE = _smbus2_module.I2C_SLAVE
_I2C_SLAVE_FORCE = _smbus2_module.I2C_SLAVE_FORCE
_I2C_FUNCS = _smbus2_module.I2C_FUNCS
_I2C_RDWR = _smbus2_module.I2C_RDWR
_I2C_SMBUS = _smbus2_module.I2C_SMBUS
_I2C_M_RD = _smbus2_module.I2C_M_RD
#: What a Raspberry Pi's adapter reports: plain I2C plus SMBus emulation.
ADAPTER_FUNCS = int(smbus2.I2cFunc.I2C | smbus2.I2cFunc.SMBUS_EMUL)


class _OpenFile:
    """One open ``/dev/i2c-N``: the adapter and the slave address set with ``I2C_SLAVE``."""

    __slots__ = ("address", "bus")

    def __init__(self, bus: SimulatedI2CBus | _RemoteAdapter) -> None:
        self.bus = bus
        self.address = 0


_open_files: dict[int, _OpenFile] = {}
_open_lock = threading.Lock()


def _einval(what: str) -> OSError:
    return OSError(errno.EINVAL, f"{os.strerror(errno.EINVAL)} ({what})")


def _smbus_transfer(f: _OpenFile, data: Any) -> None:
    """``I2C_SMBUS``: the kernel's SMBus-over-I2C emulation (i2c_smbus_xfer_emulated)."""
    S = _smbus2_module
    addr, cmd, size = f.address, data.command, data.size
    read = data.read_write == S.I2C_SMBUS_READ
    u = data.data.contents if data.data else None
    bus = f.bus
    if size == S.I2C_SMBUS_QUICK:
        bus.transaction("smbus:quick", [(addr, read, 0 if read else b"")])
    elif size == S.I2C_SMBUS_BYTE:
        if read:
            u.byte = bus.transaction("smbus:byte", [(addr, True, 1)])[0][0]
        else:
            bus.transaction("smbus:byte", [(addr, False, bytes((cmd,)))])
    elif size == S.I2C_SMBUS_BYTE_DATA:
        if read:
            u.byte = bus.transaction("smbus:byte_data", [(addr, False, bytes((cmd,))), (addr, True, 1)])[1][0]
        else:
            bus.transaction("smbus:byte_data", [(addr, False, bytes((cmd, u.byte)))])
    elif size == S.I2C_SMBUS_WORD_DATA:
        if read:
            got = bus.transaction("smbus:word_data", [(addr, False, bytes((cmd,))), (addr, True, 2)])[1]
            u.word = got[0] | got[1] << 8
        else:
            bus.transaction("smbus:word_data", [(addr, False, bytes((cmd, u.word & 0xFF, u.word >> 8)))])
    elif size == S.I2C_SMBUS_PROC_CALL:
        w = u.word
        got = bus.transaction("smbus:proc_call", [(addr, False, bytes((cmd, w & 0xFF, w >> 8))), (addr, True, 2)])[1]
        u.word = got[0] | got[1] << 8
    elif size == S.I2C_SMBUS_I2C_BLOCK_DATA:
        length = u.block[0]
        if not 1 <= length <= S.I2C_SMBUS_BLOCK_MAX:
            raise _einval(f"i2c block length {length}")
        if read:
            got = bus.transaction("smbus:i2c_block_data", [(addr, False, bytes((cmd,))), (addr, True, length)])[1]
            u.block[0] = length
            u.block[1 : length + 1] = list(got)
        else:
            payload = bytes((cmd, *u.block[1 : length + 1]))
            bus.transaction("smbus:i2c_block_data", [(addr, False, payload)])
    elif size == S.I2C_SMBUS_BLOCK_DATA and not read:
        length = u.block[0]
        if not 1 <= length <= S.I2C_SMBUS_BLOCK_MAX:
            raise _einval(f"block length {length}")
        bus.transaction("smbus:block_data", [(addr, False, bytes((cmd, length, *u.block[1 : length + 1])))])
    else:
        # SMBus block reads and block process calls need I2C_M_RECV_LEN, which a Pi's adapter lacks
        raise OSError(errno.EOPNOTSUPP, os.strerror(errno.EOPNOTSUPP))


def _rdwr_transfer(f: _OpenFile, data: Any) -> None:
    """``I2C_RDWR``: a combined transaction of ``nmsgs`` messages, each with its own address."""
    msgs = [data.msgs[i] for i in range(data.nmsgs)]
    plan: list[tuple[int, bool, bytes | int]] = []
    for m in msgs:
        if m.flags & _I2C_M_RD:
            plan.append((m.addr, True, m.len))
        else:
            plan.append((m.addr, False, ctypes.string_at(m.buf, m.len)))
    results = f.bus.transaction("rdwr", plan)
    for m, got in zip(msgs, results, strict=True):
        if m.flags & _I2C_M_RD:
            ctypes.memmove(m.buf, got, len(got))


def _simulated_ioctl(fd: int, request: int, arg: Any = 0, mutate_flag: bool = True) -> int:
    """Stands in for ``fcntl.ioctl`` inside smbus2's methods on a :class:`SimulatedSMBus`."""
    f = _open_files.get(fd)
    if f is None:
        raise OSError(errno.EBADF, os.strerror(errno.EBADF))
    if request in (_I2C_SLAVE, _I2C_SLAVE_FORCE):
        if not isinstance(arg, int) or not 0 <= arg <= 0x7F:
            raise _einval(f"slave address {arg!r}")
        f.address = arg
    elif request == _I2C_FUNCS:
        arg.value = ADAPTER_FUNCS
    elif request == _I2C_SMBUS:
        _smbus_transfer(f, arg)
    elif request == _I2C_RDWR:
        _rdwr_transfer(f, arg)
    else:
        raise OSError(errno.ENOTTY, os.strerror(errno.ENOTTY))
    return 0


def _rebind(fn: types.FunctionType, namespace: dict[str, Any]) -> types.FunctionType:
    new = types.FunctionType(fn.__code__, namespace, fn.__name__, fn.__defaults__, fn.__closure__)
    new.__kwdefaults__ = fn.__kwdefaults__
    new.__doc__ = fn.__doc__
    new.__qualname__ = fn.__qualname__
    return new


def _smbus2_on_simulated_kernel() -> type:
    """``smbus2.SMBus`` with its own methods re-bound so that ``ioctl`` is :func:`_simulated_ioctl`."""
    namespace = dict(vars(_smbus2_module))
    namespace["ioctl"] = _simulated_ioctl
    members: dict[str, Any] = {}
    for name, attr in vars(smbus2.SMBus).items():
        if isinstance(attr, types.FunctionType):
            members[name] = _rebind(attr, namespace)
        elif isinstance(attr, property):
            members[name] = property(
                attr.fget and _rebind(attr.fget, namespace),  # type: ignore[arg-type]
                attr.fset and _rebind(attr.fset, namespace),  # type: ignore[arg-type]
                attr.fdel and _rebind(attr.fdel, namespace),  # type: ignore[arg-type]
                attr.__doc__,
            )
    return type("_SMBusOnSimulatedKernel", (smbus2.SMBus,), members)


class SimulatedSMBus(_smbus2_on_simulated_kernel()):  # type: ignore[misc]
    """An ``smbus2.SMBus`` on a simulated bus: smbus2's own code, a simulated i2c-dev underneath.

    Opening holds a real file descriptor (of ``/dev/null``) so that smbus2's ``close()`` closes a descriptor
    that is ours; ``ioctl`` calls on it are served by the simulator.
    """

    def __init__(
        self, bus: int | str | None = None, force: bool = False, *, simulator: I2CSimulator | RemoteI2CSimulator
    ) -> None:
        self._simulator = simulator
        super().__init__(bus, force)

    def open(self, bus: int | str) -> None:
        if isinstance(bus, int):
            number, path = bus, f"/dev/i2c-{bus}"
        elif isinstance(bus, str):
            path = bus
            number = int(bus[9:]) if bus.startswith("/dev/i2c-") and bus[9:].isdigit() else -1
        else:
            raise TypeError(f"Unexpected type(bus)={type(bus)}")
        adapter = self._simulator.adapter(number)
        if adapter is None:
            raise FileNotFoundError(errno.ENOENT, os.strerror(errno.ENOENT), path)
        fd = os.open(os.devnull, os.O_RDWR)
        with _open_lock:
            _open_files[fd] = _OpenFile(adapter)
        self._finalizer = weakref.finalize(self, _release, fd)
        self.fd = fd
        self.funcs = self._get_funcs()

    def close(self) -> None:
        fd = self.fd
        if fd:
            self._finalizer.detach()
            with _open_lock:
                _open_files.pop(fd, None)
        super().close()


def _release(fd: int) -> None:
    """Close a simulated bus that was garbage-collected without ``close()``."""
    with _open_lock:
        _open_files.pop(fd, None)
    try:
        os.close(fd)
    except OSError:
        pass
