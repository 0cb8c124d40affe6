"""The options every driving command takes (``asyncdonkey run`` and ``asyncdonkey donkey``), defined once.

Why one definition: each command used to declare its own ``--hz``/``--max-loops``/``--duration``, and the copies
drifted (``MAX_LOOPS`` in one help text, ``N`` in the other; ``--precise`` on ``run`` only). The values are
checked by :mod:`asyncdonkey.options`, so a bad one is the same one-line error in both commands::

    asyncdonkey donkey: error: argument --hz: expected a finite number > 0, got 'inf' (see asyncdonkey donkey --help)

Each option's ``default`` is ``None`` (the car's own value applies) except the flags.
"""

from __future__ import annotations

import argparse

from ..options import non_negative_int, option, positive_float

__all__ = ["DRIVE_OPTIONS", "add_drive_options"]

#: the shared options' destinations, in the order they are added (tests check both commands have them all)
DRIVE_OPTIONS = ("hz", "max_loops", "duration", "verbose", "no_uvloop", "precise")


def add_drive_options(parser: argparse.ArgumentParser, *, default_rate: str) -> None:
    """Add the driving options to ``parser``; ``default_rate`` says where the rate comes from without ``--hz``."""
    parser.add_argument(
        "--hz",
        type=option(positive_float),
        default=None,
        metavar="HZ",
        help=f"drive loop rate in Hz, a positive number (default: {default_rate})",
    )
    parser.add_argument(
        "--max-loops",
        type=option(non_negative_int),
        default=None,
        metavar="N",
        help="stop after N ticks (0 or more)",
    )
    parser.add_argument(
        "--duration", type=option(positive_float), default=None, metavar="S", help="stop after S seconds (S > 0)"
    )
    parser.add_argument(
        "--verbose",
        action="store_true",
        help="jitter warnings, the profiler table every 200 loops, and the traceback of an error",
    )
    parser.add_argument("--no-uvloop", action="store_true", help="use the standard asyncio loop")
    parser.add_argument(
        "--precise", action="store_true", help="spin the last stretch before each tick: tighter ticks for more CPU"
    )
