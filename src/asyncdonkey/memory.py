"""Memory: the named channels parts read and write, with Donkeycar's API plus write times.

Donkeycar's ``Memory`` is a dict with a few helpers; asyncdonkey keeps that API so existing code that pokes at
``vehicle.mem`` keeps working, and adds one thing Donkeycar lacks: *when* each channel was last written, on
the runtime clock. That makes staleness measurable (DESIGN.md §3.3): an actuator can tell that its throttle
command is 300 ms old because the pilot stopped publishing, and fall back to neutral.

The drive loop writes through :meth:`Memory._store` with the time it already measured, so stamping costs no
extra clock read on the hot path.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, ItemsView, Iterable, KeysView, Mapping, Sequence, ValuesView
from typing import Any

__all__ = ["Memory"]


class Memory:
    """Named channels (``str`` → any value) and the clock time each was last written.

    Compatible with Donkeycar's ``Memory``: ``mem['a'] = 1``, ``mem['a', 'b'] = (1, 2)``, ``mem['a']``,
    ``mem['a', 'b']`` (a list), ``put(keys, values)``, ``get(keys)`` (missing → ``None``), ``update``,
    ``keys``, ``values``, ``items``. The dict itself is ``mem.d``, as in Donkeycar.
    """

    __slots__ = ("_now", "d", "stamps")

    def __init__(self, clock: Callable[[], float] | None = None) -> None:
        self.d: dict[str, Any] = {}
        #: channel → runtime-clock time of the last write
        self.stamps: dict[str, float] = {}
        self._now: Callable[[], float] = clock or time.monotonic

    def use_clock(self, now: Callable[[], float]) -> None:
        """Stamp writes with ``now`` from here on (the Vehicle passes the clock of the loop it runs on)."""
        self._now = now

    # -- Donkeycar's API -------------------------------------------------------------------------------
    def __setitem__(self, key: str | Sequence[str], value: Any) -> None:
        if isinstance(key, str):
            self._store(key, value, self._now())
            return
        keys = tuple(key)
        values = tuple(value)
        if len(keys) != len(values):
            raise ValueError(f"Memory: {len(keys)} channels {keys!r} but {len(values)} values")
        now = self._now()
        for k, v in zip(keys, values, strict=True):
            self._store(k, v, now)

    def __getitem__(self, key: str | tuple[str, ...]) -> Any:
        if isinstance(key, tuple):
            return [self.d[k] for k in key]
        return self.d[key]

    def __contains__(self, key: object) -> bool:
        return key in self.d

    def __len__(self) -> int:
        return len(self.d)

    def update(self, new_d: Mapping[str, Any]) -> None:
        now = self._now()
        for k, v in new_d.items():
            self._store(k, v, now)

    def put(self, keys: Sequence[str], inputs: Any) -> None:
        """Write ``inputs`` to ``keys``: one key stores the value as is, several unpack it."""
        now = self._now()
        if len(keys) == 1:
            self._store(keys[0], inputs, now)
            return
        try:
            n = len(inputs)
        except TypeError:
            raise ValueError(
                f"Memory.put: {len(keys)} channels {list(keys)!r} need a sequence of {len(keys)} values,"
                f" got {type(inputs).__name__}"
            ) from None
        if n != len(keys):
            raise ValueError(f"Memory.put: {len(keys)} channels {list(keys)!r} but {n} values")
        for k, v in zip(keys, inputs, strict=True):
            self._store(k, v, now)

    def get(self, keys: Iterable[str]) -> list[Any]:
        d = self.d
        return [d.get(k) for k in keys]

    def keys(self) -> KeysView[str]:
        return self.d.keys()

    def values(self) -> ValuesView[Any]:
        return self.d.values()

    def items(self) -> ItemsView[str, Any]:
        return self.d.items()

    # -- write times -----------------------------------------------------------------------------------
    def written_at(self, key: str) -> float | None:
        """Runtime-clock time of the last write to ``key``, or ``None`` if it was never written."""
        return self.stamps.get(key)

    def age(self, key: str, now: float | None = None) -> float:
        """Seconds since ``key`` was last written (``inf`` if never)."""
        t = self.stamps.get(key)
        if t is None:
            return math.inf
        return (self._now() if now is None else now) - t

    def _store(self, key: str, value: Any, now: float) -> None:
        self.d[key] = value
        self.stamps[key] = now

    def __repr__(self) -> str:
        return f"Memory({self.d!r})"
