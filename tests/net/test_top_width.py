"""``asyncdonkey top``'s width: a terminal's columns on a terminal, no limit in a file or a pipe.

``top > fleet.txt`` used to cut every row at 120 columns (``pilot/thrott``): the ages column, the last one, was
lost exactly where a file or a pipe has room for it.
"""

from __future__ import annotations

import fcntl
import io
import os
import struct
import termios

from asyncdonkey.parts.zenoh.fleet import render_fleet, screen_width

#: a car whose row is well past 120 columns: many channel ages, many parts
AGES = {f"pilot/throttle_{i}": 12.0 + i for i in range(8)}
CARS = {
    "cars/wide": (
        {"hz": 20.0, "mode": "pilot", "ages_ms": AGES, "parts": {f"Part{i}": 0.5 + i for i in range(12)}},
        100.0,
    )
}


def test_without_a_width_no_row_is_cut():
    lines = render_fleet(CARS, 100.2).splitlines()
    row = next(line for line in lines if line.startswith("cars/wide"))
    parts = next(line for line in lines if line.strip().startswith("parts ms:"))
    assert len(row) > 120 and row.endswith("pilot/throttle_7=19")
    assert len(parts) > 120 and "Part0 0.50" in parts


def test_a_width_cuts_every_row_to_it():
    lines = render_fleet(CARS, 100.2, width=60).splitlines()
    assert [line for line in lines[2:] if len(line) > 60] == []
    assert any(line.startswith("cars/wide") and len(line) == 60 for line in lines)


def test_a_file_or_a_pipe_has_no_width(tmp_path):
    assert screen_width(io.StringIO()) is None
    with open(tmp_path / "fleet.txt", "w") as f:
        assert screen_width(f) is None
    read, write = os.pipe()
    with os.fdopen(read) as r, os.fdopen(write, "w") as w:
        assert screen_width(w) is None and not r.closed


def test_a_terminal_has_its_own_width():
    parent, child = os.openpty()
    try:
        fcntl.ioctl(child, termios.TIOCSWINSZ, struct.pack("HHHH", 30, 77, 0, 0))  # rows, columns: a 77-column tty
        with os.fdopen(child, "w", closefd=False) as tty:
            assert screen_width(tty) == 77
    finally:
        os.close(parent)
        os.close(child)
