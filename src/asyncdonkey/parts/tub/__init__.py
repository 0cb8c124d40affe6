"""Recording: Donkeycar's Tub v2 format, written off the drive loop and crash-safe, and read back.

* :class:`TubWriter` — the part that records (queue + writer thread; never blocks the tick).
* :class:`Tub` — the reader: records as mappings, images loaded on access, delete/restore.
* :class:`TubWiper` — deletes the last N records on a button press.
* :func:`repair_tub` — makes a crashed tub's manifests match its catalogs.

See ``docs/recording.md`` for the format, the queue and durability policies and crash behaviour.
"""

from .appender import RepairReport, repair_tub
from .fileio import TubFileIO
from .format import TYPES, TubError, TubFormatError, TubImageError, TubImagePathError, TubNotFoundError
from .reader import Record, Tub, load_image
from .wiper import TubWiper
from .writer import TubWriter, TubWriterStats

__all__ = [
    "TYPES",
    "Record",
    "RepairReport",
    "Tub",
    "TubError",
    "TubFileIO",
    "TubFormatError",
    "TubImageError",
    "TubImagePathError",
    "TubNotFoundError",
    "TubWiper",
    "TubWriter",
    "TubWriterStats",
    "load_image",
    "repair_tub",
]
