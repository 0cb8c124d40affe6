"""Open a recording whatever its format: a Tub v2 directory or an MCAP file.

Replay and conversion read records (``.raw`` values, ``record[key]`` decoding images, ``.index``) from either;
:func:`open_recording` picks the reader by what the path is. MCAP needs the ``asyncdonkey[mcap]`` extra.

What a file holds is outside data, as a network sample is: both pass every value they use through a
:class:`~asyncdonkey.contracts.Gate` (:func:`admit_with_reason`) before it enters a drive or another file.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from ..contracts import REFUSED, Gate
from ..parts.tub import Tub, TubFormatError

__all__ = ["MCAP_MAGIC", "admit_with_reason", "is_mcap", "open_recording"]

MCAP_MAGIC = b"\x89MCAP0\r\n"


def is_mcap(path: str | os.PathLike[str]) -> bool:
    """True for an existing file that starts with MCAP's magic bytes (whatever its name)."""
    p = Path(path)
    if not p.is_file():
        return False
    with open(p, "rb") as f:
        return f.read(len(MCAP_MAGIC)) == MCAP_MAGIC


def open_recording(path: str | os.PathLike[str], image_key: str = "cam/image_array") -> Any:
    """A :class:`~asyncdonkey.parts.tub.Tub` for a directory, a :class:`~asyncdonkey.parts.mcap.reader.McapTub`
    for an MCAP file (one record per camera frame). Raises the tub reader's errors for anything else."""
    if is_mcap(path):
        try:
            from ..parts.mcap.reader import McapTub
        except ImportError as exc:
            raise TubFormatError(f"{os.fspath(path)}: reading MCAP needs asyncdonkey[mcap] ({exc})") from exc
        return McapTub(path, image_key)
    if Path(path).is_file():
        raise TubFormatError(f"{os.fspath(path)}: not a tub directory nor an MCAP file")
    return Tub(path)


def admit_with_reason(gate: Gate, channel: str, value: Any, now: float = 0.0) -> tuple[Any, str | None]:
    """``gate.admit(channel, value, now)`` and, when it refused the value, the reason it counted (``"nan"``), so a
    reader can say per record what it left out (the gate itself counts per channel and reason)."""
    before = {r: n for (ch, r), n in gate.refused.items() if ch == channel}
    v = gate.admit(channel, value, now)
    if v is not REFUSED:
        return v, None
    return v, next(r for (ch, r), n in gate.refused.items() if ch == channel and n != before.get(r, 0))
