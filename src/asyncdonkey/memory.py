"""Memory: the named channels parts read and write, with Donkeycar's API plus the age of every value.

Donkeycar's ``Memory`` is a dict with a few helpers; asyncdonkey keeps that API so existing code that pokes at
``vehicle.mem`` keeps working, and adds what Donkeycar lacks: for each channel, *when it was last written* and
*how old the sensing behind its value is*, both on the runtime clock.

Why two times. A value's age is the age of the sensing behind it (a camera frame's capture, a sensor read, a
controller event's arrival), not of its last write: a drive-mode selector that re-publishes a stale pilot
command every tick writes a fresh value of old data. ``stamps`` keeps the write time (what Donkeycar users
would call "last set"); ``origins`` keeps the origin time that the drive loop propagates from a part's inputs
to its outputs (see ``docs/provenance.md``). ``"<channel>@age"`` inputs and :meth:`Memory.age` are
``now - origin``. A plain write from outside the loop (``mem["x"] = 1``) is its own origin.

The drive loop writes the dicts directly with times it already measured, so stamping costs no extra clock
read on the hot path.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, ItemsView, Iterable, KeysView, Mapping, Sequence, ValuesView
from typing import Any

from .errors import ChannelCountError

__all__ = ["Memory"]


def _count(values: Any) -> str:
    try:
        return str(len(values))
    except TypeError:
        return "fewer"


class Memory:
    """Named channels (``str`` → any value) and the clock time each was last written.

    Compatible with Donkeycar's ``Memory``: ``mem['a'] = 1``, ``mem['a', 'b'] = (1, 2)``, ``mem['a']``,
    ``mem['a', 'b']`` (a list), ``put(keys, values)``, ``get(keys)`` (missing → ``None``), ``update``,
    ``keys``, ``values``, ``items``. The dict itself is ``mem.d``, as in Donkeycar. The deliberate differences
    (Donkeycar's bugs not reproduced, no half-written multi-channel writes, a keyword-only ``clock``) are
    listed in ``docs/donkeycar.md``.
    """

    __slots__ = ("_now", "d", "origins", "stamps")

    def __init__(self, *, clock: Callable[[], float] | None = None) -> None:
        # keyword-only: Donkeycar's Memory(*args, **kw) ignores its arguments, so a positional one here would
        # silently become a clock
        self.d: dict[str, Any] = {}
        #: channel → runtime-clock time of the last write
        self.stamps: dict[str, float] = {}
        #: channel → runtime-clock time of the sensing behind the current value (its origin)
        self.origins: dict[str, float] = {}
        self._now: Callable[[], float] = clock or time.monotonic

    def use_clock(self, now: Callable[[], float]) -> None:
        """Stamp writes with ``now`` from here on (the Vehicle passes the clock of the loop it runs on).

        Times taken on another clock cannot be compared with the new one (a channel preset on the monotonic
        clock before a virtual-clock drive would be hundreds of seconds "in the future"), so when the clock
        changes every existing value is re-stamped as written, and sensed, now: it then ages normally, and a
        preset command still trips a stale-command failsafe after its window.
        """
        if now is self._now:
            return
        self._now = now
        t = now()
        for k in self.d:
            self.stamps[k] = t
            self.origins[k] = t

    # -- Donkeycar's API -------------------------------------------------------------------------------
    # Semantics follow donkeycar.memory.Memory (5.3/5.4) call for call, except where its behaviour is a bug;
    # each difference is listed in docs/donkeycar.md ("Compatibility notes").
    def __setitem__(self, key: str | Sequence[str], value: Any) -> None:
        if isinstance(key, str):
            self._store(key, value, self._now())
            return
        # Donkeycar stores the key names as the values when the keys are a list (``value = tuple(key)``);
        # any sequence of names works here as a tuple does there
        keys = tuple(key)
        self._store_many("Memory[...] =", keys, value)

    def __getitem__(self, key: str | tuple[str, ...]) -> Any:
        if isinstance(key, tuple):
            return [self.d[k] for k in key]
        return self.d[key]

    def __contains__(self, key: object) -> bool:
        return key in self.d

    def __len__(self) -> int:
        return len(self.d)

    def update(self, new_d: Mapping[str, Any] | Iterable[tuple[str, Any]]) -> None:
        """Write every pair of ``new_d``: a mapping or an iterable of ``(key, value)`` pairs, as ``dict.update``."""
        pairs = dict(new_d)  # dict's own rules and errors; nothing is written if a pair is malformed
        now = self._now()
        for k, v in pairs.items():
            self._store(k, v, now)

    def put(self, keys: Sequence[str], inputs: Any) -> None:
        """Write ``inputs`` to ``keys``: one key stores the value as is, several take ``inputs[i]`` in order.

        As in Donkeycar, values beyond the keys are ignored and too few raise ``IndexError`` (here a
        :class:`~asyncdonkey.errors.ChannelCountError` naming the channels, raised before anything is written).
        """
        if isinstance(keys, str):
            raise TypeError(
                f"Memory.put: keys must be a list of channel names, got the string {keys!r} (write [{keys!r}])"
            )
        keys = tuple(keys)
        if len(keys) == 1:
            self._store(keys[0], inputs, self._now())
            return
        if not keys:
            raise ChannelCountError("Memory.put: no channels given")
        self._store_many("Memory.put:", keys, inputs)

    def get(self, keys: Iterable[str]) -> list[Any]:
        d = self.d
        return [d.get(k) for k in keys]

    def _store_many(self, where: str, keys: tuple[str, ...], values: Any) -> None:
        """Store ``values[i]`` in ``keys[i]``, all with one time stamp, or nothing if a value is missing."""
        try:
            picked = [values[i] for i in range(len(keys))]
        except IndexError:
            raise ChannelCountError(
                f"{where} {len(keys)} channels {list(keys)!r} but only {_count(values)} values"
            ) from None
        except KeyError as exc:
            # Donkeycar indexes values[i] too, so a dict fails there as well; say why
            raise KeyError(
                f"{where} values are looked up by position (values[{exc.args[0]!r}]);"
                f" got a {type(values).__name__} without that key: pass the values as a list in channel order"
            ) from None
        except TypeError:
            if hasattr(values, "__getitem__"):
                raise
            raise TypeError(
                f"{where} {len(keys)} channels {list(keys)!r} need an indexable sequence of values,"
                f" got {type(values).__name__}"
            ) from None
        now = self._now()
        for k, v in zip(keys, picked, strict=True):
            self._store(k, v, now)

    def keys(self) -> KeysView[str]:
        return self.d.keys()

    def values(self) -> ValuesView[Any]:
        return self.d.values()

    def items(self) -> ItemsView[str, Any]:
        return self.d.items()

    # -- write times -----------------------------------------------------------------------------------
    def set(self, key: str, value: Any, origin: float | None = None) -> None:
        """Write one channel whose value was sensed at ``origin`` (runtime clock; default: now).

        For code outside the drive loop that knows how old its data is: a network receiver, a web request
        handler, a test presetting a stale command.
        """
        now = self._now()
        self._store(key, value, now, now if origin is None else origin)

    def written_at(self, key: str) -> float | None:
        """Runtime-clock time of the last write to ``key``, or ``None`` if it was never written."""
        return self.stamps.get(key)

    def origin(self, key: str) -> float | None:
        """Runtime-clock time of the sensing behind ``key``'s value, or ``None`` if it was never written (or was
        computed from channels with nothing sensed behind them, see ``docs/provenance.md``)."""
        return self.origins.get(key)

    def age(self, key: str, now: float | None = None) -> float:
        """Seconds since the sensing behind ``key``'s value (``inf`` if it has no origin); what ``@age`` gives."""
        t = self.origins.get(key)
        if t is None:
            return math.inf
        return (self._now() if now is None else now) - t

    def _store(self, key: str, value: Any, now: float, origin: float | None = None) -> None:
        self.d[key] = value
        self.stamps[key] = now
        self.origins[key] = now if origin is None else origin

    def __repr__(self) -> str:
        return f"Memory({self.d!r})"
