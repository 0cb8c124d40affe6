"""``TubWiper``: delete the last N records when a button is pressed, once per press (edge-triggered).

Donkeycar's part of the same name, for a controller button bound to ``user/wiper_on`` (or any boolean
channel): a crash into the wall is wiped from the recording while driving. Holding the button deletes once;
releasing and pressing again deletes the next N.

With a :class:`~.writer.TubWriter` the deletion is queued to the writer thread in order with the records, so
the tick never waits for the disk and "the last N" are the last N handed to the writer. It also works with a
:class:`~.reader.Tub` or Donkeycar's own ``Tub`` (anything with ``delete_last_n_records(n)``).
"""

from __future__ import annotations

from typing import Any, Protocol

__all__ = ["TubWiper"]


class _Deletes(Protocol):
    def delete_last_n_records(self, n: int) -> Any: ...


class TubWiper:
    """Args: ``tub``: the writer (or tub) to delete from; ``num_records``: records per press (default 20)."""

    def __init__(self, tub: _Deletes, num_records: int = 20) -> None:
        if not callable(getattr(tub, "delete_last_n_records", None)):
            raise TypeError(f"TubWiper: {tub!r} has no delete_last_n_records(n) method")
        if not (isinstance(num_records, int) and num_records > 0):
            raise ValueError(f"TubWiper: num_records must be a positive integer, got {num_records!r}")
        self._delete = tub.delete_last_n_records
        self._num_records = num_records
        self._pressed = False
        self.wipes = 0

    def run(self, is_delete: Any) -> None:
        """Delete on the rising edge of ``is_delete``; nothing while it stays true."""
        if is_delete:
            if not self._pressed:
                self._pressed = True
                self._delete(self._num_records)
                self.wipes += 1
        else:
            self._pressed = False
