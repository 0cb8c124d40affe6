"""Open a recording whatever its format: a Tub v2 directory or an MCAP file.

Replay and conversion read records (``.raw`` values, ``record[key]`` decoding images, ``.index``) from either;
:func:`open_recording` picks the reader by what the path is. MCAP needs the ``asyncdonkey[mcap]`` extra.

:func:`check_recording` and :func:`check_tub_directory` say what is wrong with a path before any reader sees it:
a missing path, a file that is neither kind, a file where a tub directory is needed. The readers' own errors
speak of tubs ("no such tub directory"), which misleads a user who gave an MCAP file or mistyped a name.

What a file holds is outside data, as a network sample is: both pass every value they use through a
:class:`~asyncdonkey.contracts.Gate` (:func:`admit_with_reason`) before it enters a drive or another file.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from ..contracts import REFUSED, Gate
from ..parts.tub import Tub, TubFormatError, TubNotFoundError

__all__ = ["MCAP_MAGIC", "admit_with_reason", "check_recording", "check_tub_directory", "is_mcap", "open_recording"]

MCAP_MAGIC = b"\x89MCAP0\r\n"


def is_mcap(path: str | os.PathLike[str]) -> bool:
    """True for an existing file that starts with MCAP's magic bytes (whatever its name)."""
    p = Path(path)
    if not p.is_file():
        return False
    with open(p, "rb") as f:
        return f.read(len(MCAP_MAGIC)) == MCAP_MAGIC


def check_recording(path: str | os.PathLike[str]) -> None:
    """Raise :class:`~asyncdonkey.parts.tub.TubNotFoundError` for a missing ``path`` and
    :class:`~asyncdonkey.parts.tub.TubFormatError` for a file that is not an MCAP recording; a directory passes
    (the tub reader then says whether it is a tub)."""
    p = Path(path)
    if not p.exists():
        raise TubNotFoundError(f"no such file or directory: {os.fspath(path)}")
    if p.is_file() and not is_mcap(p):
        raise TubFormatError(f"{os.fspath(path)} is not a tub directory or an MCAP file")


def check_tub_directory(path: str | os.PathLike[str], option: str) -> None:
    """As :func:`check_recording` for where only a tub directory will do (``option`` names it: ``--tub``)."""
    p = Path(path)
    if not p.exists():
        raise TubNotFoundError(f"no such file or directory: {os.fspath(path)}")
    if not p.is_dir():
        raise TubFormatError(f"{os.fspath(path)} is a file; {option} needs a tub directory")


def open_recording(path: str | os.PathLike[str], image_key: str = "cam/image_array") -> Any:
    """A :class:`~asyncdonkey.parts.tub.Tub` for a directory, a :class:`~asyncdonkey.parts.mcap.reader.McapTub`
    for an MCAP file (one record per camera frame). Raises :func:`check_recording`'s errors for a missing path
    or a file of another kind, and the tub reader's errors for a directory that is not a tub."""
    check_recording(path)
    if is_mcap(path):
        from ..parts.mcap.reader import McapTub  # raises MissingExtra without the mcap extra

        return McapTub(path, image_key)
    return Tub(path)


def admit_with_reason(gate: Gate, channel: str, value: Any, now: float = 0.0) -> tuple[Any, str | None]:
    """``gate.admit(channel, value, now)`` and, when it refused the value, the reason it counted (``"nan"``), so a
    reader can say per record what it left out (the gate itself counts per channel and reason)."""
    before = {r: n for (ch, r), n in gate.refused.items() if ch == channel}
    v = gate.admit(channel, value, now)
    if v is not REFUSED:
        return v, None
    return v, next(r for (ch, r), n in gate.refused.items() if ch == channel and n != before.get(r, 0))
