"""Finding the records in a catalog file, and the catalogs in a tub, without trusting the manifests.

After a crash the catalog files are the truth: ``manifest.json`` and the catalog manifests are rewritten only
at sync points, so they may lag the catalog by the records written since, and the last line of a catalog may
be torn (no trailing newline). The reader and the writer's repair both start from :func:`scan_catalog`.

A *complete* line ends with ``\\n``. A complete line that does not look like a JSON object (``{...}``, e.g.
zero bytes left by a power cut) is *corrupt*: it keeps its position, so later records keep their indexes, but
it is never returned as a record. The bytes after the last newline are the *torn* tail.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

from .format import CatalogManifest, ManifestData, catalog_name, read_catalog_manifest

__all__ = ["CatalogScan", "scan_catalog", "scan_tub"]

logger = logging.getLogger(__name__)


@dataclass
class CatalogScan:
    """Where the lines of one catalog are.

    ``offsets[i]`` is where line ``i`` starts and ``offsets[i + 1]`` where the next starts, so there are
    ``len(offsets) - 1`` complete lines and ``offsets[-1]`` is the end of the last one.
    """

    name: str
    start_index: int
    offsets: list[int] = field(default_factory=lambda: [0])
    corrupt: set[int] = field(default_factory=set)
    torn_bytes: int = 0
    listed: bool = True
    missing: bool = False
    manifest: CatalogManifest | None = None

    @property
    def lines(self) -> int:
        return len(self.offsets) - 1

    @property
    def end(self) -> int:
        """Byte offset just past the last complete line."""
        return self.offsets[-1]

    @property
    def next_index(self) -> int:
        return self.start_index + self.lines

    def line_lengths(self) -> list[int]:
        o = self.offsets
        return [o[i + 1] - o[i] for i in range(len(o) - 1)]


def scan_catalog(data: bytes, name: str, start_index: int) -> CatalogScan:
    """Line positions of ``data`` (a catalog file's bytes)."""
    scan = CatalogScan(name=name, start_index=start_index)
    offsets = scan.offsets
    corrupt = scan.corrupt
    find = data.find
    pos = 0
    n = 0
    while True:
        nl = find(b"\n", pos)
        if nl < 0:
            break
        end = nl - 1 if nl > pos and data[nl - 1] == 0x0D else nl  # tolerate \r\n
        if not (end > pos and data[pos] == 0x7B and data[end - 1] == 0x7D):  # "{" ... "}"
            corrupt.add(n)
        pos = nl + 1
        offsets.append(pos)
        n += 1
    scan.torn_bytes = len(data) - pos
    return scan


def scan_tub(base_path: Path, manifest: ManifestData) -> list[CatalogScan]:
    """Scan every catalog of a tub: the listed ones, then any consecutive unlisted ``catalog_N.catalog``.

    An unlisted catalog is one the writer started (on rolling over to a new catalog) but had not yet listed
    in ``manifest.json`` when it stopped; its records are found and returned like the others. A catalog's
    first index comes from its catalog manifest, else it follows the previous catalog.
    """
    scans: list[CatalogScan] = []
    names = list(manifest.paths)
    n = len(names)
    while (base_path / catalog_name(n)).exists() and catalog_name(n) not in names:
        names.append(catalog_name(n))
        n += 1
    next_index = 0
    for i, name in enumerate(names):
        listed = i < len(manifest.paths)
        cm = read_catalog_manifest(base_path, name)
        start = cm.start_index if cm is not None else next_index
        path = base_path / name
        try:
            data = path.read_bytes()
        except FileNotFoundError:
            logger.warning("%s: catalog listed in the manifest is missing; its records are lost", path)
            scan = CatalogScan(name=name, start_index=start, missing=True, listed=listed, manifest=cm)
        else:
            scan = scan_catalog(data, name, start)
            scan.listed = listed
            scan.manifest = cm
        scans.append(scan)
        next_index = scan.next_index
    return scans
