"""Channel contracts: what a channel's values may be, and the value that is safe when there is none.

Why. A value that enters the process from outside (a Zenoh sample, a web request, a file being replayed) is
whatever its sender made it: ``NaN``, ``inf``, a 400-digit integer, the string ``"0.66"``, a list of half a
million items, an empty DELETE. None of these is a command a part can use, and one of them reaching Memory is
enough to stop a driving car (a part raising on it) or to steer it (a part that does not). ROS 2 types its
messages but has no ranges on topics and nothing about what is safe; Donkeycar checks nothing. A contract is
the kind, the range or shape, and the *safe value* together, in one place per channel.

How it is used:

* **At every boundary** (:class:`Gate`): a receiver asks ``gate.admit(channel, value)`` before it stores
  anything. A value that breaks the contract is *refused*: not stored, counted per channel and reason, logged
  rate-limited. The channel keeps its last good value and its age keeps growing, so the stale-command failsafe
  decides, never the bad value. A refused value is not a lost one: receivers count them apart.
* **Inside the process**, as a test-time aid (checked mode): every part output is checked against its
  channel's contract and a violation names the part that wrote it (``Vehicle(checked=True)``).

A Donkeycar car that declares nothing keeps working: the channels every car has get the contracts of
:func:`default_contracts`, which accept everything Donkeycar's own parts produce; any other channel has no
contract and is not checked. Declare more with :meth:`Contracts.declare` (``Vehicle.contracts.declare``), or
beside the part that produces them (a part's ``contracts`` attribute, a mapping of its output channels).
"""

from __future__ import annotations

import logging
import math
import numbers
import operator
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from enum import Enum
from typing import Any

import numpy as np

from .errors import AsyncdonkeyError
from .ratelimit import LogThrottle

__all__ = [
    "REFUSED",
    "Contract",
    "ContractViolation",
    "Contracts",
    "Gate",
    "Kind",
    "default_contracts",
]

logger = logging.getLogger(__name__)


class Kind(Enum):
    """What sort of value a channel holds."""

    FLOAT = "float"  # a finite real number (an int is taken and made a float; a bool is not a number here)
    INT = "int"  # an integer (not a bool)
    BOOL = "bool"
    ENUM = "enum"  # one of a set of strings
    ARRAY = "array"  # a numpy array of one dtype, with a shape pattern
    BYTES = "bytes"  # bytes, up to a length
    JPEG = "jpeg"  # bytes that start and end as a JPEG does, up to a length


class ContractViolation(AsyncdonkeyError, ValueError):
    """A value broke its channel's contract. ``channel`` and ``reason`` (a short word, e.g. ``"range"``) say
    which and why; ``part`` names the part that wrote it, in checked mode."""

    def __init__(self, channel: str, reason: str, detail: str, part: str | None = None) -> None:
        who = f"part {part!r} wrote " if part else ""
        super().__init__(f"{who}channel {channel!r}: {detail}" if channel else detail)
        self.channel = channel
        self.reason = reason
        self.detail = detail
        self.part = part


class _Refused:
    """The one value :meth:`Gate.admit` returns for a refused value (never a real value: ``None`` is one)."""

    _instance: _Refused | None = None

    def __new__(cls) -> _Refused:
        if cls._instance is None:
            cls._instance = super().__new__(cls)
        return cls._instance

    def __repr__(self) -> str:
        return "REFUSED"

    def __bool__(self) -> bool:
        return False


#: what :meth:`Gate.admit` returns instead of a value it refused
REFUSED: Any = _Refused()


def _short(value: Any) -> str:
    """A value as an error message shows it: never a 400-digit integer or a 500,000-item list in full."""
    if isinstance(value, np.ndarray):
        return f"array of shape {value.shape} and dtype {value.dtype}"
    if isinstance(value, bytes | bytearray | memoryview):
        return f"{type(value).__name__} of {len(value)} bytes"
    if isinstance(value, list | tuple | dict | set):
        return f"{type(value).__name__} of {len(value)} items"
    text = repr(value)
    return text if len(text) <= 40 else f"{text[:37]}..."


def _typed(value: Any) -> str:
    """A value with its type, for "expected X, got Y" (containers already name theirs)."""
    if isinstance(value, np.ndarray | bytes | bytearray | memoryview | list | tuple | dict | set):
        return _short(value)
    return f"{type(value).__name__} {_short(value)}"


#: a check returns the value to store (normalised: an int made a float, a numpy scalar a Python one) or raises
Check = Callable[[Any], Any]


@dataclass(frozen=True)
class Contract:
    """What one channel's values may be. Build one with the class methods (:meth:`number`, :meth:`choice`, ...).

    ``safe`` is the value a failsafe writes for the channel (``None``: it has none, e.g. an image).
    """

    kind: Kind
    low: float | None = None
    high: float | None = None
    choices: frozenset[str] | None = None
    dtype: str | None = None
    shape: tuple[tuple[int | None, ...], ...] | None = None
    max_len: int | None = None
    safe: Any = None
    check: Check = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "check", _compile(self))
        if self.safe is not None:
            self.check(self.safe)  # a contract whose safe value breaks it is a mistake: say so when it is made

    # --------------------------------------------------------------------------------- constructors
    @classmethod
    def number(cls, low: float = -math.inf, high: float = math.inf, *, safe: float | None = None) -> Contract:
        """A finite real number in ``[low, high]`` (ints are taken and stored as floats)."""
        return cls(Kind.FLOAT, low=float(low), high=float(high), safe=safe)

    @classmethod
    def integer(cls, low: int | None = None, high: int | None = None, *, safe: int | None = None) -> Contract:
        """An integer in ``[low, high]``."""
        return cls(Kind.INT, low=low, high=high, safe=safe)

    @classmethod
    def boolean(cls, *, safe: bool | None = None) -> Contract:
        """``True`` or ``False`` (not 0 and 1: a sender that means a number should say so)."""
        return cls(Kind.BOOL, safe=safe)

    @classmethod
    def choice(cls, *options: str, safe: str | None = None) -> Contract:
        """One of ``options`` (strings)."""
        if not options or not all(isinstance(o, str) for o in options):
            raise ValueError(f"Contract.choice needs one or more strings, got {options!r}")
        return cls(Kind.ENUM, choices=frozenset(options), safe=safe)

    @classmethod
    def array(
        cls,
        dtype: Any,
        shape: Iterable[int | None] | Iterable[Iterable[int | None]] | None = None,
        *,
        max_len: int | None = None,
    ) -> Contract:
        """A numpy array of ``dtype`` whose shape matches ``shape`` (``None`` for any length on an axis; a list of
        such patterns for any of them: ``[(None, None, 3), (None, None)]`` takes colour and grey frames), and at
        most ``max_len`` elements in all."""
        return cls(
            Kind.ARRAY,
            dtype=np.dtype(dtype).str,
            shape=None if shape is None else _patterns(shape),
            max_len=max_len,
        )

    @classmethod
    def blob(cls, max_len: int) -> Contract:
        """``bytes`` of at most ``max_len``."""
        return cls(Kind.BYTES, max_len=int(max_len))

    @classmethod
    def jpeg(cls, max_len: int = 4 << 20) -> Contract:
        """A JPEG file's bytes (SOI marker first, EOI last) of at most ``max_len``."""
        return cls(Kind.JPEG, max_len=int(max_len))

    def describe(self) -> str:
        """The contract in words, for docs and error messages."""
        k = self.kind
        if k is Kind.FLOAT or k is Kind.INT:
            lo = "" if self.low is None or self.low == -math.inf else f"{self.low:g}"
            hi = "" if self.high is None or self.high == math.inf else f"{self.high:g}"
            what = "a finite number" if k is Kind.FLOAT else "an integer"
            return f"{what} in [{lo or '-inf'}, {hi or 'inf'}]" if (lo or hi) else what
        if k is Kind.BOOL:
            return "true or false"
        if k is Kind.ENUM:
            return "one of " + ", ".join(repr(c) for c in sorted(self.choices or ()))
        if k is Kind.ARRAY:
            shape = "any shape" if self.shape is None else " or ".join(_shape_text(p) for p in self.shape)
            return f"a {np.dtype(self.dtype).name} array of shape {shape}"
        return f"{'JPEG ' if k is Kind.JPEG else ''}bytes up to {self.max_len} long"


def _patterns(shape: Any) -> tuple[tuple[int | None, ...], ...]:
    """One shape pattern, or several, as a tuple of patterns."""
    items = list(shape)
    if items and all(isinstance(p, tuple | list) for p in items):
        return tuple(tuple(p) for p in items)
    return (tuple(items),)


def _shape_test(patterns: tuple[tuple[int | None, ...], ...]) -> Callable[[tuple[int, ...]], bool]:
    """``matches(shape)`` for a set of patterns, decided once: by the number of axes, then only the axes whose
    length is fixed (a camera frame's (*, *, 3) tests one axis), with no loop where there is nothing to test."""
    by_ndim: dict[int, list[tuple[Callable[[tuple[int, ...]], Any], Any]]] = {}
    free: set[int] = set()
    for p in patterns:
        fixed = [(i, d) for i, d in enumerate(p) if d is not None]
        if not fixed:
            free.add(len(p))
            continue
        # itemgetter picks the fixed axes in C: one call and one comparison, whatever the pattern
        idx, want = [i for i, _ in fixed], tuple(d for _, d in fixed)
        by_ndim.setdefault(len(p), []).append((operator.itemgetter(*idx), want if len(want) > 1 else want[0]))
    get = by_ndim.get

    def matches(shape: tuple[int, ...]) -> bool:
        nd = len(shape)
        if nd in free:
            return True
        for pick, want in get(nd, ()):  # noqa: SIM110 - a loop: any() and its generator cost twice as much
            if pick(shape) == want:
                return True
        return False

    return matches


def _shape_text(shape: tuple[int | None, ...]) -> str:
    return "(" + ", ".join("*" if d is None else str(d) for d in shape) + ")"


def _fail(reason: str, detail: str) -> ContractViolation:
    return ContractViolation("", reason, detail)


def _compile(c: Contract) -> Check:
    """The contract's check as one closure, decided once: the common case is a type test and a comparison."""
    return _BUILDERS[c.kind](c)


def _float_check(c: Contract) -> Check:
    lo = -math.inf if c.low is None else c.low
    hi = math.inf if c.high is None else c.high

    def check_float(v: Any) -> Any:
        if v.__class__ is float and lo <= v <= hi:
            return v
        if isinstance(v, bool) or not isinstance(v, numbers.Real):
            raise _fail("type", f"got {_typed(v)}, not a number")
        try:
            f = float(v)
        except (OverflowError, ValueError):
            raise _fail("range", f"{_short(v)} is too large for a float") from None
        if f != f:
            raise _fail("nan", "got NaN")
        if f in (math.inf, -math.inf):
            raise _fail("inf", f"got {f}")
        if not lo <= f <= hi:
            raise _fail("range", f"{_short(v)} is outside [{lo:g}, {hi:g}]")
        return f

    return check_float


def _int_check(c: Contract) -> Check:
    lo, hi = c.low, c.high

    def check_int(v: Any) -> Any:
        if isinstance(v, bool) or not isinstance(v, numbers.Integral):
            raise _fail("type", f"got {_typed(v)}, not an integer")
        i = int(v)
        if (lo is not None and i < lo) or (hi is not None and i > hi):
            raise _fail("range", f"{_short(v)} is outside [{lo}, {hi}]")
        return i

    return check_int


def _bool_check(c: Contract) -> Check:
    def check_bool(v: Any) -> Any:
        if v is True or v is False:
            return v
        if isinstance(v, np.bool_):
            return bool(v)
        raise _fail("type", f"got {_typed(v)}, not true or false")

    return check_bool


def _enum_check(c: Contract) -> Check:
    choices = c.choices or frozenset()

    def check_enum(v: Any) -> Any:
        if v.__class__ is str and v in choices:
            return v
        if not isinstance(v, str):
            raise _fail("type", f"got {_typed(v)}, not a string")
        raise _fail("choice", f"{_short(v)} is not one of {sorted(choices)}")

    return check_enum


def _array_check(c: Contract) -> Check:
    dtype = np.dtype(c.dtype)
    max_len = c.max_len
    shape_ok = None if c.shape is None else _shape_test(c.shape)
    floats = dtype.kind in "fc"

    def check_array(v: Any) -> Any:
        if not isinstance(v, np.ndarray):
            raise _fail("type", f"got {_typed(v)}, not an array")
        if v.dtype is not dtype and v.dtype != dtype:
            raise _fail("dtype", f"got an array of dtype {v.dtype}")
        if shape_ok is not None and not shape_ok(v.shape):
            raise _fail("shape", f"got an array of shape {v.shape}")
        if max_len is not None and v.size > max_len:
            raise _fail("size", f"{v.size} elements, more than {max_len}")
        if floats and not np.isfinite(v).all():
            raise _fail("nan", "the array holds NaN or inf")
        return v

    return check_array


def _bytes_check(c: Contract) -> Check:
    blen = c.max_len if c.max_len is not None else 1 << 62
    jpeg = c.kind is Kind.JPEG

    def check_bytes(v: Any) -> Any:
        if isinstance(v, bytearray | memoryview):
            v = bytes(v)
        if not isinstance(v, bytes):
            raise _fail("type", f"got {_typed(v)}, not bytes")
        if len(v) > blen:
            raise _fail("size", f"{len(v)} bytes, more than {blen}")
        if jpeg and not (v[:2] == b"\xff\xd8" and v[-2:] == b"\xff\xd9"):
            raise _fail("encoding", "not a JPEG (no SOI/EOI markers)")
        return v

    return check_bytes


_BUILDERS: dict[Kind, Callable[[Contract], Check]] = {
    Kind.FLOAT: _float_check,
    Kind.INT: _int_check,
    Kind.BOOL: _bool_check,
    Kind.ENUM: _enum_check,
    Kind.ARRAY: _array_check,
    Kind.BYTES: _bytes_check,
    Kind.JPEG: _bytes_check,
}


#: Donkeycar's drive modes (the web page, the gamepad and DriveMode speak these)
_MODES = ("user", "local_angle", "local")
#: the largest camera frame a boundary takes: 4096 x 4096 x 3 (a Pi HQ camera's full frame is 4056 x 3040)
_MAX_IMAGE = 4096 * 4096 * 3


def default_contracts() -> dict[str, Contract]:
    """The contracts of the channels every Donkeycar car has.

    Steering and throttle commands are numbers in [-1, 1] with the safe value 0 (straight, stopped); the mode
    is one of Donkeycar's three with ``"user"`` safe; ``recording`` is a bool, ``False`` safe; the camera frame is
    a ``uint8`` image of any size up to 4096 x 4096, RGB (H, W, 3) or grey (H, W) as Donkeycar's cameras write
    with ``IMAGE_DEPTH`` 3 or 1 (``cam/image_array``)."""
    command = Contract.number(-1.0, 1.0, safe=0.0)
    return {
        "user/angle": command,
        "user/throttle": command,
        "pilot/angle": command,
        "pilot/throttle": command,
        "angle": command,
        "throttle": command,
        "user/mode": Contract.choice(*_MODES, safe="user"),
        "recording": Contract.boolean(safe=False),
        "cam/image_array": Contract.array(np.uint8, [(None, None, 3), (None, None)], max_len=_MAX_IMAGE),
    }


class Contracts:
    """The contracts of one car's channels: the defaults, then whatever the user and its parts declare."""

    def __init__(self, declared: Mapping[str, Contract] | None = None, *, defaults: bool = True) -> None:
        self._by_channel: dict[str, Contract] = default_contracts() if defaults else {}
        for channel, contract in (declared or {}).items():
            self.declare(channel, contract)

    def declare(self, channel: str, contract: Contract) -> None:
        """Give ``channel`` this contract (replacing any, a default included)."""
        if not isinstance(channel, str) or not channel:
            raise ValueError(f"Contracts.declare: a channel is a non-empty string, got {channel!r}")
        if not isinstance(contract, Contract):
            raise TypeError(f"Contracts.declare({channel!r}): expected a Contract, got {contract!r}")
        self._by_channel[channel] = contract

    def get(self, channel: str) -> Contract | None:
        return self._by_channel.get(channel)

    def __contains__(self, channel: object) -> bool:
        return channel in self._by_channel

    def items(self) -> Iterable[tuple[str, Contract]]:
        return self._by_channel.items()

    def safe_value(self, channel: str) -> Any:
        c = self._by_channel.get(channel)
        return None if c is None else c.safe

    def check(self, channel: str, value: Any, part: str | None = None) -> Any:
        """The value to store for ``channel`` (normalised), or :class:`ContractViolation` naming the channel
        (and ``part``). A channel without a contract takes anything."""
        c = self._by_channel.get(channel)
        if c is None:
            return value
        try:
            return c.check(value)
        except ContractViolation as exc:
            raise ContractViolation(channel, exc.reason, f"{exc.detail} (expected {c.describe()})", part) from None

    def gate(self, where: str) -> Gate:
        """A :class:`Gate` for one boundary (``where`` names it in logs: ``"ZenohSubscriber"``, ``"web"``)."""
        return Gate(self, where)


class Gate:
    """One boundary's admission control: each value checked, refusals counted per channel and reason.

    ``admit(channel, value)`` returns the value to store, or :data:`REFUSED`. ``None`` and empty payloads (a
    Zenoh DELETE) are refused as ``"empty"``: they are the absence of a value, not a value. Thread-safe for
    counting from one receiver thread at a time; the counters are plain ints read by reports.
    """

    def __init__(self, contracts: Contracts, where: str, log_every_s: float = 5.0) -> None:
        self.contracts = contracts
        self.where = where
        #: (channel, reason) → values refused
        self.refused: dict[tuple[str, str], int] = {}
        self._log = LogThrottle(log_every_s)

    def admit(self, channel: str, value: Any, now: float = 0.0) -> Any:
        if value is None:
            return self.refuse(channel, "empty", "no value (None)", now)
        c = self.contracts.get(channel)
        if c is None:
            return value
        try:
            return c.check(value)
        except ContractViolation as exc:
            return self.refuse(channel, exc.reason, f"{exc.detail} (expected {c.describe()})", now)

    def refuse(self, channel: str, reason: str, detail: str, now: float = 0.0) -> Any:
        """Count and log (rate-limited) one refused value; returns :data:`REFUSED`. Receivers that find a value
        unusable before it can be checked (a DELETE, a payload that does not decode) call this directly."""
        key = (channel, reason)
        self.refused[key] = self.refused.get(key, 0) + 1
        more = self._log.ready(key, now)
        if more is not None:
            logger.warning("%s: refused a value for %r: %s%s", self.where, channel, detail, more)
        return REFUSED

    @property
    def total_refused(self) -> int:
        return sum(self.refused.values())

    def counts(self) -> dict[str, dict[str, int]]:
        """Refusals as ``{channel: {reason: count}}``."""
        out: dict[str, dict[str, int]] = {}
        for (channel, reason), n in self.refused.items():
            out.setdefault(channel, {})[reason] = n
        return out
