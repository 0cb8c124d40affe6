"""Checking the values a user gives: command-line options and a car file's settings, one check per kind.

Why one module: the same kind of value arrives from several places (``asyncdonkey run --hz``, a car file's
``DRIVE_LOOP_HZ``, ``asyncdonkey replay --speed``, a car's own ``--seconds``), and a check copied into each
place drifts (one copy accepted ``inf`` as a rate, another printed argparse's ``invalid _positive_float
value``). Each check takes the text or the number as given and returns the value, or raises
:class:`BadValue` whose message says what was expected and what was given; :func:`option` turns a check into
an argparse ``type=`` so the error names the option::

    parser.add_argument("--hz", type=option(positive_float))
    # asyncdonkey run: error: argument --hz: expected a finite number > 0, got 'inf'

    rate = positive_float(getattr(module, "DRIVE_LOOP_HZ", 20))   # BadValue: say which setting
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable
from typing import TypeVar

from .errors import AsyncdonkeyError

__all__ = ["BadValue", "non_negative_float", "non_negative_int", "option", "positive_float"]

T = TypeVar("T")


class BadValue(AsyncdonkeyError, ValueError):
    """A value is not of the expected kind; the message is ``expected <kind>, got <value>``."""


def _number(value: object, expected: str) -> float:
    if isinstance(value, bool):  # True is an int, but never a rate or a count
        raise BadValue(f"expected {expected}, got {value!r}")
    if isinstance(value, int | float):
        x = float(value)
    elif isinstance(value, str):
        try:
            x = float(value.strip())
        except ValueError:
            raise BadValue(f"expected {expected}, got {value!r}") from None
    else:
        raise BadValue(f"expected {expected}, got {type(value).__name__} {value!r}")
    if not math.isfinite(x):
        raise BadValue(f"expected {expected}, got {value!r}")
    return x


def positive_float(value: object) -> float:
    """A finite number above 0: a rate in Hz, a duration in seconds, a speed multiple."""
    expected = "a finite number > 0"
    x = _number(value, expected)
    if not x > 0:
        raise BadValue(f"expected {expected}, got {value!r}")
    return x


def non_negative_float(value: object) -> float:
    """A finite number of at least 0 (where 0 means "no limit", as a car's ``--seconds 0``)."""
    expected = "a finite number >= 0"
    x = _number(value, expected)
    if x < 0:
        raise BadValue(f"expected {expected}, got {value!r}")
    return x


def non_negative_int(value: object) -> int:
    """A whole number of at least 0: a count of ticks or laps."""
    expected = "a whole number >= 0"
    if isinstance(value, str):
        try:
            n = int(value.strip(), 10)
        except ValueError:
            raise BadValue(f"expected {expected}, got {value!r}") from None
    elif isinstance(value, int) and not isinstance(value, bool):
        n = value
    else:
        raise BadValue(f"expected {expected}, got {value!r}")
    if n < 0:
        raise BadValue(f"expected {expected}, got {value!r}")
    return n


def option(check: Callable[[str], T]) -> Callable[[str], T]:
    """``check`` as an argparse ``type=``: its :class:`BadValue` becomes argparse's error for that option."""

    def parse(text: str) -> T:
        try:
            return check(text)
        except BadValue as exc:
            raise argparse.ArgumentTypeError(str(exc)) from None

    parse.__name__ = getattr(check, "__name__", "value")
    return parse
