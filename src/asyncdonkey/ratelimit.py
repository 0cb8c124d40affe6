"""Rate limiting for log messages raised from hot paths (jitter warnings, retried reads, part errors).

A 1 kHz loop that logs every overrun floods the log and slows itself down; :class:`LogThrottle` lets one
message per key through per interval and counts what it held back, so the next message can say how many.
"""

from __future__ import annotations

__all__ = ["LogThrottle"]


class LogThrottle:
    """``allow(key, now)`` is true at most once per ``interval_s`` per key; ``suppressed(key)`` counts the rest."""

    __slots__ = ("_last", "_suppressed", "interval_s")

    def __init__(self, interval_s: float = 1.0) -> None:
        self.interval_s = interval_s
        self._last: dict[object, float] = {}
        self._suppressed: dict[object, int] = {}

    def allow(self, key: object, now: float) -> bool:
        last = self._last.get(key)
        if last is not None and now - last < self.interval_s:
            self._suppressed[key] = self._suppressed.get(key, 0) + 1
            return False
        self._last[key] = now
        return True

    def take_suppressed(self, key: object) -> int:
        """How many messages for ``key`` were held back since the last one allowed; resets the count."""
        return self._suppressed.pop(key, 0)

    def ready(self, key: object, now: float, what: str = "more") -> str | None:
        """``None`` while ``key`` is held back; else the suffix for the message that goes out: ``""``, or
        ``" (N more since the last report)"`` when messages were held back. The one way every rate-limited
        log line in the project says how much it did not say."""
        if not self.allow(key, now):
            return None
        held = self._suppressed.pop(key, 0)
        return f" ({held} {what} since the last report)" if held else ""
