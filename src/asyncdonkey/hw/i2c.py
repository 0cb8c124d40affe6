"""An I2C bus that never blocks the event loop, retries transient errors and serializes its chips.

Why this layer exists:

* **Blocking transfers stay off the loop thread.** An smbus2 transfer is an ``ioctl`` that blocks for the
  whole transaction (0.2-3 ms on a Raspberry Pi, longer when the bus is busy or clock-stretched). Every async
  method here runs the transfer on the bus's own single worker thread via ``loop.run_in_executor`` (so the
  virtual-clock loop in tests sees and waits for it).
* **One bus object per bus number, one lock per bus.** Several chips share a bus (a PCA9685 and an MPU6050 on
  bus 1); a multi-step sequence on one chip (read-modify-write of a mode register) must not interleave with
  another chip's transfers. Every transfer, async or sync, takes the bus's re-entrant lock, and
  :meth:`I2CBus.locked` holds it across a sequence. :class:`I2CBusRegistry` hands out the one :class:`I2CBus`
  per bus number, and :meth:`I2CBus.shared` keeps one driver per chip on it.
* **One process per chip.** A driver claims its chip (:meth:`I2CBus.claim`) before it sends it anything: an
  advisory lock per bus and address (:mod:`asyncdonkey.hw.owner_lock`), so a second car started on a chip
  that another car drives is refused with :class:`I2CDeviceInUse` naming the owner, instead of resetting the
  chip under it. Every user in one process shares the claim; the kernel drops it when the owner exits or is
  killed.
* **Transient errors are retried, then named.** A servo's electrical noise makes a transfer NACK now and then
  (``OSError`` errno 121 on a Raspberry Pi). Transient errnos are retried ``retries`` times after
  ``retry_delay_s``; the error that finally escapes is an :class:`I2CError` that says which bus, address,
  register and operation failed and how many attempts were made.

Sync variants (``*_sync``) are for code that already runs in a worker thread (a :class:`~asyncdonkey.Poller`
read, a driver's init at construction time); they take the same lock and apply the same retry policy.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import errno
import hashlib
import json
import logging
import os
import threading
import time
import weakref
from collections.abc import Callable, Iterator, Sequence
from typing import Any, Protocol, TypeVar

from ..errors import AsyncdonkeyError
from . import owner_lock
from .owner_lock import DeviceOwner

__all__ = [
    "TRANSIENT_ERRNOS",
    "I2CBus",
    "I2CBusRegistry",
    "I2CDeviceInUse",
    "I2CDeviceNotFound",
    "I2CError",
    "SMBusLike",
    "default_registry",
    "get_bus",
]

logger = logging.getLogger(__name__)
T = TypeVar("T")

#: Errors worth another try: a NACK (EREMOTEIO on the Pi, ENXIO on some adapters), a bus timeout or
#: arbitration loss (ETIMEDOUT, EAGAIN, EBUSY) and a generic I/O error. Anything else (a closed bus, an
#: invalid argument, an unsupported transfer) fails at once.
TRANSIENT_ERRNOS = frozenset({errno.EREMOTEIO, errno.ENXIO, errno.EIO, errno.ETIMEDOUT, errno.EAGAIN, errno.EBUSY})


class SMBusLike(Protocol):
    """The part of ``smbus2.SMBus`` this module uses (a simulated bus provides the same methods)."""

    def read_byte_data(self, i2c_addr: int, register: int, force: bool | None = None) -> int: ...
    def write_byte_data(self, i2c_addr: int, register: int, value: int, force: bool | None = None) -> None: ...
    def read_i2c_block_data(
        self, i2c_addr: int, register: int, length: int, force: bool | None = None
    ) -> list[int]: ...
    def write_i2c_block_data(
        self, i2c_addr: int, register: int, data: Sequence[int], force: bool | None = None
    ) -> None: ...
    def close(self) -> None: ...


class I2CError(AsyncdonkeyError, OSError):
    """An I2C transfer failed for good. Names the bus, device address, register and operation.

    It is an ``OSError`` (with the underlying ``errno``) so code written against smbus2 that catches
    ``OSError`` keeps working; the original error is chained as ``__cause__``.
    """

    def __init__(
        self,
        message: str,
        *,
        bus: int | None = None,
        address: int | None = None,
        register: int | None = None,
        operation: str = "",
        attempts: int = 0,
        cause: OSError | None = None,
    ) -> None:
        super().__init__(getattr(cause, "errno", None), message)
        self.message = message
        self.bus = bus
        self.address = address
        self.register = register
        self.operation = operation
        self.attempts = attempts

    def __str__(self) -> str:
        return self.message


class I2CDeviceNotFound(I2CError):
    """Nothing answered at an address when a driver opened its chip (not wired, wrong address, no power)."""


class I2CDeviceInUse(I2CError):
    """Another process owns the chip (:meth:`I2CBus.claim`): a second car on the same chip. ``errno`` is EBUSY.

    ``owner`` is the :class:`~asyncdonkey.hw.owner_lock.DeviceOwner` its lock file names (pid, command line,
    start time), or ``None`` if it names no live process; ``lock_path`` is that file.
    """

    def __init__(self, message: str, *, owner: DeviceOwner | None, lock_path: str, **kwargs: Any) -> None:
        super().__init__(message, **kwargs)
        self.errno = errno.EBUSY
        self.owner = owner
        self.lock_path = lock_path


def _where(bus: int, address: int, register: int | None) -> str:
    reg = "" if register is None else f", register 0x{register:02X}"
    return f"I2C bus {bus}, device 0x{address:02X}{reg}"


class I2CBus:
    """One I2C bus (``/dev/i2c-<bus_number>``): async and sync transfers, retries, a lock and a worker thread.

    Args:
        bus_number: the Linux bus number (1 on a Raspberry Pi's header pins).
        smbus_factory: ``factory(bus_number) -> SMBus``; default ``smbus2.SMBus``. Tests pass a simulated bus
            (:meth:`asyncdonkey.testing.i2c_models.I2CSimulator.smbus`).
        retries: extra attempts after a transient ``OSError`` (so ``retries + 1`` attempts in all).
        retry_delay_s: pause before each retry (in the worker thread, never on the loop).

    Counters (for reports): ``transfers`` (successful), ``retried`` (attempts that failed and were retried),
    ``failures`` (operations that raised :class:`I2CError`).
    """

    def __init__(
        self,
        bus_number: int,
        *,
        smbus_factory: Callable[[int], SMBusLike] | None = None,
        retries: int = 3,
        retry_delay_s: float = 0.002,
    ) -> None:
        if not isinstance(bus_number, int) or isinstance(bus_number, bool) or bus_number < 0:
            raise ValueError(f"I2CBus: bus_number must be a non-negative int, got {bus_number!r}")
        if not isinstance(retries, int) or retries < 0:
            raise ValueError(f"I2CBus({bus_number}): retries must be a non-negative int, got {retries!r}")
        if not retry_delay_s >= 0:
            raise ValueError(f"I2CBus({bus_number}): retry_delay_s must be >= 0, got {retry_delay_s!r}")
        self.bus_number = bus_number
        self.retries = retries
        self.retry_delay_s = float(retry_delay_s)
        self.transfers = 0
        self.retried = 0
        self.failures = 0
        self._lock = threading.RLock()
        self._executor: concurrent.futures.ThreadPoolExecutor | None = None
        self._shared: dict[Any, Any] = {}
        self._closed = False
        #: address → the lock file claimed for it (``None``: a bus no other process can reach, nothing to lock)
        self._claims: dict[int, str | None] = {}
        self._claims_finalizer = weakref.finalize(self, _release_claims, self._claims)
        if smbus_factory is None:
            import smbus2

            smbus_factory = smbus2.SMBus
        self._factory = smbus_factory
        try:
            self._smbus: SMBusLike = smbus_factory(bus_number)
        except FileNotFoundError as exc:
            raise I2CError(
                f"I2C bus {bus_number} does not exist (/dev/i2c-{bus_number} not found): enable I2C (on a "
                f"Raspberry Pi: raspi-config > Interface Options > I2C) or check the bus number",
                bus=bus_number,
                operation="open",
                cause=exc,
            ) from exc
        except PermissionError as exc:
            raise I2CError(
                f"I2C bus {bus_number}: permission denied opening /dev/i2c-{bus_number}; add the user to the "
                f"'i2c' group",
                bus=bus_number,
                operation="open",
                cause=exc,
            ) from exc
        except OSError as exc:
            raise I2CError(
                f"I2C bus {bus_number}: cannot open /dev/i2c-{bus_number}: {exc}",
                bus=bus_number,
                operation="open",
                cause=exc,
            ) from exc

    def __repr__(self) -> str:
        return f"I2CBus({self.bus_number})"

    # ------------------------------------------------------------------------------------- plumbing
    @contextlib.contextmanager
    def locked(self) -> Iterator[I2CBus]:
        """Hold the bus for a sequence of sync transfers (e.g. read-modify-write of a mode register)."""
        with self._lock:
            yield self

    def cross_process_spec(self) -> dict[str, Any] | None:
        """How another process opens this same bus with a handle of its own, or ``None`` if it cannot.

        The safety process (``asyncdonkey.safety``) writes actuators' safe states through its own handle, so that
        nothing in the car's process (its GIL, its locks, its death) stands between it and the chip. A real bus
        is ``{"path": "/dev/i2c-N"}``. Any other factory may say how another process opens the same bus: an
        object (or the owner of a bound method) with ``cross_process_opener(bus_number)`` returning
        ``{"opener": "module:function", "args": [...]}`` (a served simulator,
        :meth:`asyncdonkey.testing.i2c_models.I2CSimulator.serve`); an in-process fake has no such path.
        """
        factory = self._factory
        import smbus2

        if factory is smbus2.SMBus:
            return {"path": f"/dev/i2c-{self.bus_number}"}
        owner = getattr(factory, "__self__", factory)
        opener = getattr(owner, "cross_process_opener", None)
        spec = opener(self.bus_number) if callable(opener) else None
        return spec if isinstance(spec, dict) else None

    def lock_path(self, address: int) -> str | None:
        """The lock file that makes one process the owner of the chip at ``address`` on this bus.

        A real bus is named by its device: ``/dev/i2c-1`` → ``asyncdonkey-i2c-1-0x40.lock`` in
        :func:`~asyncdonkey.hw.owner_lock.lock_dir`. A simulated bus that another process can open (a served
        simulator, from the serving process and from its clients alike) is named by how it is opened: its
        factory's ``device_lock_path(bus_number, address)`` (a served simulator's: beside its socket, removed
        with it), else a digest of :meth:`cross_process_spec`. So the processes sharing one served model share
        its locks, and unrelated simulators never meet. ``None`` where no other process can reach the bus (an in-process
        simulator): there is nothing to guard.
        """
        spec = self.cross_process_spec()
        if spec is None:
            return None
        name = f"asyncdonkey-i2c-{self.bus_number}-0x{address:02x}.lock"
        if spec.get("path") == f"/dev/i2c-{self.bus_number}":
            return os.path.join(owner_lock.lock_dir(), name)
        owner = getattr(self._factory, "__self__", self._factory)
        path_of = getattr(owner, "device_lock_path", None)
        path = path_of(self.bus_number, address) if callable(path_of) else None
        if isinstance(path, str):
            return path
        digest = hashlib.sha256(json.dumps(spec, sort_keys=True).encode()).hexdigest()[:16]
        return os.path.join(owner_lock.lock_dir(), f"asyncdonkey-i2c-{self.bus_number}-{digest}-0x{address:02x}.lock")

    def claim(self, address: int, what: str = "") -> bool:
        """Make this process the owner of the chip at ``address``; drivers call it before sending the chip anything.

        Returns ``True`` if this call made the claim (``False``: this bus had claimed it already). Every bus of
        this process may claim the same chip (steering and throttle on one PCA9685); another process may not,
        until this one closes the bus or exits: :class:`I2CDeviceInUse` names the owner. ``what`` names the chip
        in the error (``"PCA9685"``).
        """
        with self._lock:
            if self._closed:
                raise I2CError(
                    f"I2C bus {self.bus_number}: claim of 0x{address:02X} on a closed bus", bus=self.bus_number
                )
            if address in self._claims:
                return False
            path = self.lock_path(address)
            chip = (
                f"{what} at 0x{address:02X} on I2C bus {self.bus_number}"
                if what
                else (f"I2C device 0x{address:02X} on bus {self.bus_number}")
            )
            if path is not None:
                try:
                    owner_lock.acquire(path, chip)
                except owner_lock.LockHeld as held:
                    who = held.owner.describe() if held.owner is not None else f"another process (lock file {path})"
                    raise I2CDeviceInUse(
                        f"{chip} is in use by {who}: stop that car first",
                        owner=held.owner,
                        lock_path=path,
                        bus=self.bus_number,
                        address=address,
                        operation="claim",
                    ) from None
                except OSError as exc:
                    raise I2CError(
                        f"{chip}: cannot take its lock file {path}: {exc}",
                        bus=self.bus_number,
                        address=address,
                        operation="claim",
                        cause=exc,
                    ) from exc
            self._claims[address] = path
            return True

    def unclaim(self, address: int) -> None:
        """Let go of this bus's claim on ``address`` (a driver whose init failed); unknown addresses are ignored."""
        with self._lock:
            if address in self._claims:
                path = self._claims.pop(address)
                if path is not None:
                    owner_lock.release(path)

    def shared(self, key: Any, create: Callable[[], T]) -> T:
        """The one object for ``key`` on this bus, made by ``create()`` the first time.

        Drivers use it to keep one instance per chip (``("PCA9685", 0x40)``), so a second user of the chip
        shares its state instead of re-initialising it.
        """
        with self._lock:
            obj = self._shared.get(key)
            if obj is None:
                obj = create()
                self._shared[key] = obj
            return obj

    def _transfer(self, operation: str, address: int, register: int | None, fn: Callable[..., T], *args: Any) -> T:
        """Run one smbus transfer under the lock with the retry policy; the single place errors are shaped."""
        attempts = 0
        with self._lock:
            if self._closed:
                raise I2CError(
                    f"{_where(self.bus_number, address, register)}: {operation} on a closed bus",
                    bus=self.bus_number,
                    address=address,
                    register=register,
                    operation=operation,
                )
            while True:
                attempts += 1
                try:
                    result = fn(address, *args)
                except OSError as exc:
                    transient = exc.errno in TRANSIENT_ERRNOS
                    if transient and attempts <= self.retries:
                        self.retried += 1
                        logger.debug(
                            "%s: %s attempt %d failed (%s); retrying",
                            _where(self.bus_number, address, register),
                            operation,
                            attempts,
                            exc,
                        )
                        if self.retry_delay_s:
                            time.sleep(self.retry_delay_s)
                        continue
                    self.failures += 1
                    if not transient:
                        tries = "(not retried: not a transient error)"
                    elif attempts > 1:
                        tries = f"after {attempts} attempts"
                    else:
                        tries = "(retries disabled)"
                    raise I2CError(
                        f"{_where(self.bus_number, address, register)}: {operation} failed {tries}: {exc}",
                        bus=self.bus_number,
                        address=address,
                        register=register,
                        operation=operation,
                        attempts=attempts,
                        cause=exc,
                    ) from exc
                self.transfers += 1
                return result

    def _worker(self) -> concurrent.futures.ThreadPoolExecutor:
        ex = self._executor
        if ex is None:
            with self._lock:
                if self._closed:
                    raise I2CError(f"I2C bus {self.bus_number}: used after close()", bus=self.bus_number)
                ex = self._executor
                if ex is None:
                    ex = self._executor = concurrent.futures.ThreadPoolExecutor(
                        1, thread_name_prefix=f"i2c-{self.bus_number}"
                    )
        return ex

    async def call(self, fn: Callable[..., T], *args: Any) -> T:
        """Run ``fn(*args)`` on this bus's worker thread and await it.

        ``fn`` is typically a driver's sync method that makes several transfers; they serialize with every
        other user of the bus through the bus lock.
        """
        loop = asyncio.get_running_loop()
        return await loop.run_in_executor(self._worker(), fn, *args)

    # ------------------------------------------------------------------------------------------ sync
    def read_byte_data_sync(self, address: int, register: int) -> int:
        return self._transfer("read_byte_data", address, register, self._smbus.read_byte_data, register)

    def write_byte_data_sync(self, address: int, register: int, value: int) -> None:
        self._transfer("write_byte_data", address, register, self._smbus.write_byte_data, register, value)

    def read_i2c_block_data_sync(self, address: int, register: int, length: int) -> bytes:
        data = self._transfer(
            f"read_i2c_block_data({length})", address, register, self._smbus.read_i2c_block_data, register, length
        )
        return bytes(data)

    def write_i2c_block_data_sync(self, address: int, register: int, data: Sequence[int] | bytes) -> None:
        values = list(data)
        self._transfer(
            f"write_i2c_block_data({len(values)})",
            address,
            register,
            self._smbus.write_i2c_block_data,
            register,
            values,
        )

    def probe_sync(self, address: int, register: int, what: str = "device") -> int:
        """Read one register to check that a chip answers; raise :class:`I2CDeviceNotFound` naming it if not."""
        try:
            return self.read_byte_data_sync(address, register)
        except I2CError as exc:
            raise I2CDeviceNotFound(
                f"no {what} answered at address 0x{address:02X} on I2C bus {self.bus_number} (probe read of "
                f"register 0x{register:02X} failed: {exc.__cause__}); check the wiring, power and address "
                f"(`i2cdetect -y {self.bus_number}` lists the devices that answer)",
                bus=self.bus_number,
                address=address,
                register=register,
                operation="probe",
                attempts=exc.attempts,
                cause=exc.__cause__ if isinstance(exc.__cause__, OSError) else None,
            ) from exc

    # ----------------------------------------------------------------------------------------- async
    async def read_byte_data(self, address: int, register: int) -> int:
        return await self.call(self.read_byte_data_sync, address, register)

    async def write_byte_data(self, address: int, register: int, value: int) -> None:
        await self.call(self.write_byte_data_sync, address, register, value)

    async def read_i2c_block_data(self, address: int, register: int, length: int) -> bytes:
        return await self.call(self.read_i2c_block_data_sync, address, register, length)

    async def write_i2c_block_data(self, address: int, register: int, data: Sequence[int] | bytes) -> None:
        await self.call(self.write_i2c_block_data_sync, address, register, data)

    # ----------------------------------------------------------------------------------------- close
    def close(self) -> None:
        """Close the bus and its worker thread, and let go of its chips' claims; later transfers raise
        :class:`I2CError`."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            self._claims_finalizer()
            ex, self._executor = self._executor, None
            try:
                self._smbus.close()
            except OSError as exc:  # pragma: no cover - closing an fd rarely fails
                logger.warning("I2C bus %d: close failed: %r", self.bus_number, exc)
        if ex is not None:
            ex.shutdown(wait=False)

    @property
    def closed(self) -> bool:
        return self._closed


def _release_claims(claims: dict[int, str | None]) -> None:
    """Release a bus's claims (at close, or when a bus that was never closed is collected)."""
    paths = list(claims.values())
    claims.clear()
    for path in paths:
        if path is not None:
            owner_lock.release(path)


class I2CBusRegistry:
    """Hands out one :class:`I2CBus` per bus number, so every chip on a bus shares its lock and worker.

    The module-level :data:`default_registry` (used by :func:`get_bus` and by parts given a pin spec) opens
    real buses through smbus2. Tests make their own registry over a simulated bus, which keeps each test's
    chips separate::

        registry = I2CBusRegistry(smbus_factory=sim.smbus)
        steering = PWMSteering("PCA9685.1:40.1", buses=registry)

    Extra keyword arguments (``retries``, ``retry_delay_s``) go to every :class:`I2CBus` it opens.
    """

    def __init__(self, smbus_factory: Callable[[int], SMBusLike] | None = None, **bus_kwargs: Any) -> None:
        self.smbus_factory = smbus_factory
        self.bus_kwargs = bus_kwargs
        self._buses: dict[int, I2CBus] = {}
        self._lock = threading.Lock()

    def get(self, bus_number: int) -> I2CBus:
        """The bus for ``bus_number``, opened on first use (a closed bus is reopened)."""
        with self._lock:
            bus = self._buses.get(bus_number)
            if bus is None or bus.closed:
                bus = I2CBus(bus_number, smbus_factory=self.smbus_factory, **self.bus_kwargs)
                self._buses[bus_number] = bus
            return bus

    def close_all(self) -> None:
        with self._lock:
            buses, self._buses = list(self._buses.values()), {}
        for bus in buses:
            bus.close()


#: The registry behind :func:`get_bus`: real buses through smbus2.
default_registry = I2CBusRegistry()


def get_bus(bus_number: int) -> I2CBus:
    """The shared :class:`I2CBus` for ``bus_number`` from :data:`default_registry`."""
    return default_registry.get(bus_number)
