"""``Tub``: read a Tub v2 directory (ours or Donkeycar's), records as mappings with images loaded on access.

::

    tub = Tub("data/tub_1")
    len(tub)                              # records not deleted
    for record in tub:                    # in index order, deleted records skipped
        record["_index"], record["user/angle"]
        img = record["cam/image_array"]   # RGB uint8 array, read and decoded only now
        record.raw["cam/image_array"]     # the file name as stored: "0_cam_image_array_.jpg"
    tub.delete_records([3, 4]); tub.restore_records([4])   # persisted in manifest.json at once

What the reader trusts. The catalogs, not the manifests: it finds every complete line of every catalog
(including one a crashed writer had started but not yet listed in ``manifest.json``), so a tub whose writer
was killed shows every record whose line reached the file. A torn last line (no newline) is skipped and
counted in :attr:`Tub.torn_lines`; a complete line that is not a JSON object keeps its position (so later
indexes stay right) but is skipped and counted in :attr:`Tub.corrupt_lines`. Like Donkeycar, a record's index
is its position: the catalog's ``start_index`` plus its line number.

Do not edit a tub that a writer is recording into: delete through the writer (or a
:class:`~.wiper.TubWiper`) instead, which orders the change with the records.
"""

from __future__ import annotations

import json
import logging
import os
from collections.abc import Iterable, Iterator, Mapping
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from .format import (
    IMAGE_EXTENSIONS,
    IMAGES_DIR,
    MANIFEST_NAME,
    ManifestData,
    TubImageError,
    TubImagePathError,
    read_manifest,
)
from .scan import CatalogScan, scan_tub

__all__ = ["Record", "Tub", "load_image"]

logger = logging.getLogger(__name__)


def load_image(path: str | os.PathLike[str]) -> np.ndarray:
    """Read a tub image as Donkeycar's reader returns it: RGB (or grey) uint8, uint16 for 16-bit PNG."""
    try:
        with open(path, "rb") as f:  # read here, not by cv2.imread, which prints its own warning on a missing file
            data = f.read()
    except FileNotFoundError:
        raise TubImageError(f"{path}: image file is missing") from None
    except OSError as exc:
        raise TubImageError(f"{path}: cannot be read ({exc.strerror or exc})") from None
    img = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED) if data else None
    if img is None:
        raise TubImageError(f"{path}: not a readable image (empty or corrupt file)")
    if img.ndim == 3:
        if img.shape[2] == 3:
            img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
        elif img.shape[2] == 4:
            img = cv2.cvtColor(img, cv2.COLOR_BGRA2RGBA)
    return img


def _inside(images_dir: Path, name: str) -> bool:
    """Whether image name ``name`` stays inside ``images_dir``: relative, no ``..`` component, no NUL, and still
    inside once symlinks are followed (``images_dir`` itself resolved; a tub may keep its images elsewhere)."""
    if not name or "\x00" in name or os.path.isabs(name) or ".." in Path(name).parts:
        return False
    root = images_dir.resolve()
    return (root / name).resolve().is_relative_to(root)


class Record(Mapping[str, Any]):
    """One record: a read-only mapping over the stored JSON whose image keys load their image on access.

    ``record[key]`` for an ``image_array``/``gray16_array`` key returns the decoded array (loaded once, then
    cached); :attr:`raw` holds the values as stored (image file names). ``dict(record)`` loads every image.

    An image name is data from the catalog, not a path to trust: one that is absolute, has a ``..`` component or
    leads out of ``images/`` through a symlink raises :class:`~.format.TubImagePathError` (naming the tub, the
    record and the name) instead of reading a file of the machine.
    """

    __slots__ = ("_cache", "_image_keys", "_images_dir", "_position", "raw")

    def __init__(
        self, raw: dict[str, Any], image_keys: frozenset[str], images_dir: Path, position: int | None = None
    ) -> None:
        self.raw = raw
        self._image_keys = image_keys
        self._images_dir = images_dir
        self._position = position
        self._cache: dict[str, Any] = {}

    def __getitem__(self, key: str) -> Any:
        value = self.raw[key]
        if key in self._image_keys and isinstance(value, str):
            cached = self._cache.get(key)
            if cached is None:
                cached = self._cache[key] = load_image(self.image_path(key))
            return cached
        return value

    def __iter__(self) -> Iterator[str]:
        return iter(self.raw)

    def __len__(self) -> int:
        return len(self.raw)

    def __contains__(self, key: object) -> bool:
        return key in self.raw

    @property
    def index(self) -> int:
        """The record's position in the tub (what ``_index`` holds in an intact catalog line)."""
        return self._position if self._position is not None else self.raw["_index"]

    def image_path(self, key: str) -> Path:
        """The file holding ``key``'s image, checked to be inside the tub's ``images/``."""
        name = self.raw[key]
        if not (isinstance(name, str) and _inside(self._images_dir, name)):
            where = "" if self._position is None else f" record {self._position}:"
            raise TubImagePathError(
                f"{self._images_dir.parent}:{where} image name {name!r} of {key!r} is not a file inside "
                f"{IMAGES_DIR}/ (absolute, '..' or a symlink leading out); refused"
            )
        return self._images_dir / name

    def __repr__(self) -> str:
        return f"Record({self.raw!r})"


class Tub:
    """A Tub v2 directory opened for reading (and for deleting/restoring records).

    Raises :class:`~.format.TubNotFoundError` when ``base_path`` has no ``manifest.json`` and
    :class:`~.format.TubFormatError` when the manifest is corrupt, both naming the file.
    """

    def __init__(self, base_path: str | os.PathLike[str]) -> None:
        self.base_path = Path(base_path).expanduser().absolute()
        self._manifest: ManifestData = read_manifest(self.base_path)
        m = self._manifest
        self.images_dir = self.base_path / IMAGES_DIR
        self._image_keys = frozenset(k for k, t in zip(m.inputs, m.types, strict=True) if t in IMAGE_EXTENSIONS)
        self._scans: list[CatalogScan] = scan_tub(self.base_path, m)
        self.torn_lines = sum(1 for s in self._scans if s.torn_bytes)
        self.corrupt_lines = sum(len(s.corrupt) for s in self._scans)
        self.unlisted_catalogs = [s.name for s in self._scans if not s.listed]
        self.missing_catalogs = [s.name for s in self._scans if s.missing]
        if self.torn_lines or self.unlisted_catalogs:
            logger.info(
                "%s: %d torn last line(s) skipped, %d catalog(s) not yet listed in the manifest read",
                self.base_path,
                self.torn_lines,
                len(self.unlisted_catalogs),
            )

    # ------------------------------------------------------------------------------------ metadata
    @property
    def inputs(self) -> list[str]:
        return list(self._manifest.inputs)

    @property
    def types(self) -> list[str]:
        return list(self._manifest.types)

    @property
    def metadata(self) -> dict[str, Any]:
        """User metadata (manifest line 3)."""
        return dict(self._manifest.metadata)

    @property
    def manifest_metadata(self) -> dict[str, Any]:
        """``created_at`` and ``sessions`` (manifest line 4)."""
        return dict(self._manifest.manifest_metadata)

    @property
    def sessions(self) -> list[str]:
        """Full ids of the sessions recorded in the manifest, e.g. ``["24-05-01_0", "24-05-01_1"]``."""
        s = self._manifest.manifest_metadata.get("sessions") or {}
        return list(s.get("all_full_ids") or [])

    @property
    def max_len(self) -> int:
        return self._manifest.max_len

    @property
    def deleted_indexes(self) -> frozenset[int]:
        return frozenset(self._manifest.deleted_indexes)

    def indexes(self) -> list[int]:
        """Indexes of the records present and not deleted, in order."""
        deleted = self._manifest.deleted_indexes
        out: list[int] = []
        for s in self._scans:
            start, corrupt = s.start_index, s.corrupt
            out.extend(start + i for i in range(s.lines) if i not in corrupt and start + i not in deleted)
        return out

    def corrupt_records(self, include_deleted: bool = False) -> list[tuple[int, str, int]]:
        """``(index, catalog file name, line number from 1)`` of each corrupt line found so far, in index order.

        Lines that do not look like a record are found when the tub is opened; a line that looks like one but
        is not valid JSON is found when it is read (iterate the records first for the complete list).
        Deleted records are left out unless ``include_deleted``.
        """
        deleted = () if include_deleted else self._manifest.deleted_indexes
        return [
            (s.start_index + i, s.name, i + 1)
            for s in self._scans
            for i in sorted(s.corrupt)
            if s.start_index + i not in deleted
        ]

    def __len__(self) -> int:
        deleted = self._manifest.deleted_indexes
        n = 0
        for s in self._scans:
            start, end = s.start_index, s.next_index
            n += s.lines - len(s.corrupt) - sum(1 for d in deleted if start <= d < end and d - start not in s.corrupt)
        return n

    # ---------------------------------------------------------------------------------- iterating
    def __iter__(self) -> Iterator[Record]:
        return self.records()

    def records(self, include_deleted: bool = False) -> Iterator[Record]:
        """Records in index order; deleted ones too if ``include_deleted``."""
        deleted = self._manifest.deleted_indexes
        keys, images = self._image_keys, self.images_dir
        for s in self._scans:
            if s.missing or not s.lines:
                continue
            path = self.base_path / s.name
            with open(path, "rb") as f:
                data = f.read(s.end)
            offsets, corrupt, start = s.offsets, s.corrupt, s.start_index
            for i in range(s.lines):
                if i in corrupt or (not include_deleted and start + i in deleted):
                    continue
                line = data[offsets[i] : offsets[i + 1]]
                try:
                    raw = json.loads(line)
                except (json.JSONDecodeError, UnicodeDecodeError):
                    raw = None
                if not isinstance(raw, dict):
                    corrupt.add(i)
                    self.corrupt_lines += 1
                    logger.warning("%s: line %d is not a JSON record; skipped", path, i + 1)
                    continue
                yield Record(raw, keys, images, start + i)

    # ------------------------------------------------------------------------------------ editing
    def delete_records(self, indexes: int | Iterable[int]) -> None:
        """Mark records as deleted and rewrite ``manifest.json`` (atomically)."""
        self._edit_deleted(_index_set(indexes), add=True)

    def restore_records(self, indexes: int | Iterable[int]) -> None:
        """Unmark deleted records and rewrite ``manifest.json`` (atomically)."""
        self._edit_deleted(_index_set(indexes), add=False)

    def delete_last_n_records(self, n: int) -> list[int]:
        """Delete the last ``n`` records not deleted yet (what Donkeycar's ``TubWiper`` calls)."""
        alive = self.indexes()
        chosen = alive[-n:] if n > 0 else []
        self.delete_records(chosen)
        return chosen

    def _edit_deleted(self, indexes: set[int], add: bool) -> None:
        current = read_manifest(self.base_path)  # re-read: keep anything written since we opened
        if add:
            current.deleted_indexes |= indexes
        else:
            current.deleted_indexes -= indexes
        _replace_atomic(self.base_path / MANIFEST_NAME, current.encode())
        self._manifest.deleted_indexes = set(current.deleted_indexes)

    def __repr__(self) -> str:
        return f"<Tub {self.base_path} records={len(self)}>"


def _index_set(indexes: int | Iterable[int]) -> set[int]:
    if isinstance(indexes, int):
        return {indexes}
    return {int(i) for i in indexes}


def _replace_atomic(path: Path, data: bytes) -> None:
    tmp = path.with_name(path.name + ".tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
    try:
        os.write(fd, data)
        os.fsync(fd)
    finally:
        os.close(fd)
    os.replace(tmp, path)
    dfd = os.open(path.parent, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    try:
        os.fsync(dfd)
    finally:
        os.close(dfd)
