"""The tub's files as the writer thread sees them: create or repair, append records, sync, close.

:class:`TubAppender` is synchronous and single-threaded on purpose: :class:`~.writer.TubWriter` owns the
queue and the thread, this class owns the files. It is also what :func:`repair_tub` uses.

Sync points (durability). A record is *written* once its catalog line has been handed to the OS, and
*durable* once a sync point covering it has completed. A sync point, in this order:

1. flushes the image files and catalog lines written since the last one (one ``syncfs`` on Linux, else
   ``fdatasync`` per file and ``fsync`` of ``images/``);
2. writes the new catalog manifest (``line_lengths`` of complete lines only) and ``manifest.json``
   (``current_index``, ``paths``, ``deleted_indexes``, sessions) to temporary files and flushes them;
3. renames both over the old ones and ``fsync``\\ s the tub directory.

A crash at any moment therefore leaves either the old or the new manifests, each consistent with data that
is already on disk. Between sync points the catalog may hold more lines than the manifests say; readers trust
the catalog (see :mod:`.scan`), and opening the tub for writing again repairs the manifests.

Images are written before the catalog line that names them, so after the *process* dies (the OS page cache
survives) no line ever points at a missing image. After a power cut only records up to the last sync point
are guaranteed; later lines may be missing or torn and later images empty.
"""

from __future__ import annotations

import json
import logging
import os
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .encode import json_default, make_converter
from .fileio import TubFileIO, with_filename
from .format import (
    IMAGE_EXTENSIONS,
    IMAGES_DIR,
    MANIFEST_NAME,
    RESERVED_KEYS,
    TYPES,
    CatalogManifest,
    ManifestData,
    TubFormatError,
    TubNotFoundError,
    add_session,
    catalog_manifest_name,
    catalog_name,
    image_file_name,
    new_session_id,
    parse_metadata,
    read_manifest,
)
from .scan import scan_tub

__all__ = ["RepairReport", "TubAppender", "check_schema", "repair_tub"]

logger = logging.getLogger(__name__)

TMP_SUFFIX = ".tmp"

BadValueHook = Callable[[str, Exception], None]


@dataclass
class RepairReport:
    """What opening an existing tub for writing found and fixed."""

    path: str
    records: int = 0
    manifest_index: int = 0
    torn_bytes_removed: int = 0
    corrupt_lines: int = 0
    adopted_catalogs: list[str] = field(default_factory=list)
    removed_files: list[str] = field(default_factory=list)

    @property
    def changed(self) -> bool:
        return bool(
            self.torn_bytes_removed
            or self.adopted_catalogs
            or self.removed_files
            or self.records != self.manifest_index
        )


def check_schema(inputs: Sequence[str], types: Sequence[str], where: str) -> None:
    """Raise a clear error for inputs/types a tub cannot store."""
    if isinstance(inputs, str) or isinstance(types, str):
        raise TypeError(f"{where}: inputs and types must be lists of strings, not a single string")
    if len(inputs) != len(types):
        raise ValueError(f"{where}: {len(inputs)} inputs but {len(types)} types; give one type per input")
    seen: dict[str, str] = {}
    for key, typ in zip(inputs, types, strict=True):
        if not isinstance(key, str) or not key:
            raise ValueError(f"{where}: input names must be non-empty strings, got {key!r}")
        if typ not in TYPES:
            raise ValueError(f"{where}: input {key!r} has unknown type {typ!r}; expected one of {sorted(TYPES)}")
        if key in RESERVED_KEYS:
            raise ValueError(f"{where}: input {key!r} is reserved for the tub's own fields {list(RESERVED_KEYS)}")
        if key in seen:
            raise ValueError(f"{where}: input {key!r} is listed twice")
        seen[key] = typ
    image_names: dict[str, str] = {}
    for key, typ in seen.items():
        if typ in IMAGE_EXTENSIONS:
            name = image_file_name(0, key, IMAGE_EXTENSIONS[typ])
            if name in image_names:
                raise ValueError(
                    f"{where}: image inputs {image_names[name]!r} and {key!r} would share file names ({name})"
                )
            image_names[name] = key


class TubAppender:
    """Appends records to a Tub v2 directory, creating it or repairing it first. Not thread-safe.

    Args:
        base_path: the tub directory (created if missing).
        inputs, types: the record keys and their Tub v2 types. Empty for an existing tub means "as stored".
        metadata: user metadata, Donkeycar's ``["key:value", ...]`` or a mapping; merged into a stored tub's.
        max_catalog_len: records per catalog for a new tub (an existing tub keeps its own).
        file_io: the file operations to use (tests inject slow or failing disks).
        fsync: flush data at sync points (False: only atomic renames; safe against a process crash only).
        jpeg_quality: JPEG quality for ``image_array`` (75, PIL's default, which Donkeycar uses).
        on_bad_value: called with ``(key, exception)`` for each value left out of a record.
        create: create the tub if it does not exist (``repair_tub`` passes False).
    """

    def __init__(
        self,
        base_path: str | os.PathLike[str],
        inputs: Sequence[str] = (),
        types: Sequence[str] = (),
        metadata: Iterable[str] | Mapping[str, Any] = (),
        max_catalog_len: int = 1000,
        *,
        file_io: TubFileIO | None = None,
        fsync: bool = True,
        jpeg_quality: int = 75,
        on_bad_value: BadValueHook | None = None,
        create: bool = True,
    ) -> None:
        self.base = Path(base_path).expanduser().absolute()
        where = f"tub {self.base}"
        check_schema(list(inputs), list(types), where)
        if not (isinstance(max_catalog_len, int) and max_catalog_len > 0):
            raise ValueError(f"{where}: max_catalog_len must be a positive integer, got {max_catalog_len!r}")
        if not (isinstance(jpeg_quality, int) and 1 <= jpeg_quality <= 100):
            raise ValueError(f"{where}: jpeg_quality must be an integer 1..100, got {jpeg_quality!r}")
        self.io = file_io if file_io is not None else TubFileIO()
        self.fsync = bool(fsync)
        self._on_bad_value = on_bad_value
        self.images_dir = self.base / IMAGES_DIR
        self.repair: RepairReport | None = None
        self._images = str(self.images_dir)
        self._pending_images: list[str] = []
        user_meta = parse_metadata(metadata)
        if (self.base / MANIFEST_NAME).exists():
            self.manifest = self._open_existing(list(inputs), list(types), user_meta)
        elif not create:
            raise TubNotFoundError(f"{self.base}: not a tub (no {MANIFEST_NAME})")
        else:
            self.manifest = self._create(list(inputs), list(types), user_meta, max_catalog_len)
        m = self.manifest
        self.inputs: list[str] = list(m.inputs)
        self.types: list[str] = list(m.types)
        self.max_len = m.max_len
        self.session: tuple[int, str] = new_session_id(m.manifest_metadata)
        self._session_start = self.index
        self._session_recorded = False
        # Per-input plan, decided once: (key, converter, image extension or None).
        self._plan: list[tuple[str, Callable[[Any], Any], str | None]] = [
            (k, make_converter(t, jpeg_quality=jpeg_quality), IMAGE_EXTENSIONS.get(t))
            for k, t in zip(self.inputs, self.types, strict=True)
        ]
        self._unsynced = 0
        self._meta_dirty = False
        self._needs_truncate = False
        self.sync_requested = False
        self.durable = self.index
        self.bad_values = 0
        self.syncs = 0
        self.lost = 0  # a record is in the tub once its line is written: none is lost after write() returned

    # ---------------------------------------------------------------------------------------- opening
    def _create(self, inputs: list[str], types: list[str], metadata: dict[str, Any], max_len: int) -> ManifestData:
        first = self.base / catalog_name(0)
        if first.exists() and first.stat().st_size > 0:  # an empty one is left by a crash during creation
            raise TubFormatError(
                f"{self.base}: holds {catalog_name(0)} but no {MANIFEST_NAME}; refusing to overwrite it "
                "(restore the manifest or choose another directory)"
            )
        self.images_dir.mkdir(parents=True, exist_ok=True)
        m = ManifestData(
            inputs=inputs,
            types=types,
            metadata=metadata,
            manifest_metadata={"created_at": time.time()},
            paths=[catalog_name(0)],
            current_index=0,
            max_len=max_len,
        )
        self._set_catalog(catalog_name(0), start_index=0, lengths=[], size=0, listed=True)
        self._write_catalog_manifest()
        self._write_manifest(m)
        if self.fsync:
            self.io.sync_dir(str(self.base))
        self.index = 0
        logger.info("created tub %s", self.base)
        return m

    def _open_existing(self, inputs: list[str], types: list[str], metadata: dict[str, Any]) -> ManifestData:
        m = read_manifest(self.base)
        if (inputs or types) and (inputs != m.inputs or types != m.types):
            raise TubFormatError(
                f"{self.base / MANIFEST_NAME}: the tub stores inputs {m.inputs} with types {m.types}; "
                f"cannot append records with inputs {inputs} and types {types} (use a new directory, or pass "
                "no inputs to append with the stored ones)"
            )
        m.metadata.update(metadata)
        report = RepairReport(path=str(self.base), manifest_index=m.current_index)
        self.images_dir.mkdir(parents=True, exist_ok=True)
        for tmp in self.base.glob(f"*{TMP_SUFFIX}"):
            self.io.remove(str(tmp))
            report.removed_files.append(tmp.name)
        scans = scan_tub(self.base, m)
        while len(scans) > 1 and not scans[-1].listed and scans[-1].lines == 0:
            dead = scans.pop()  # an unlisted catalog with no complete line: the writer had only created it
            for name in (dead.name, catalog_manifest_name(dead.name)):
                if (self.base / name).exists():
                    self.io.remove(str(self.base / name))
                    report.removed_files.append(name)
        for s in scans:
            report.corrupt_lines += len(s.corrupt)
            if s.torn_bytes and not s.missing:
                fd = self.io.open_append(str(self.base / s.name))
                try:
                    self.io.truncate(fd, s.end)
                    if self.fsync:
                        self.io.sync_file(fd)
                finally:
                    self.io.close(fd)
                report.torn_bytes_removed += s.torn_bytes
                logger.warning("%s: removed a torn last line (%d bytes)", self.base / s.name, s.torn_bytes)
            if not s.listed:
                report.adopted_catalogs.append(s.name)
        m.paths = [s.name for s in scans]
        if not scans:  # a manifest without catalogs: start the first one, as Donkeycar does
            m.paths = [catalog_name(0)]
            self._set_catalog(catalog_name(0), start_index=m.current_index, lengths=[], size=0, listed=True)
        else:
            last = scans[-1]
            self._set_catalog(last.name, last.start_index, last.line_lengths(), last.end, listed=True)
            if last.manifest is not None:
                self._cat_created_at = last.manifest.created_at
        self.index = self._start + len(self._lengths)
        report.records = self.index
        if report.records != m.current_index:
            logger.warning(
                "%s: manifest said %d records, the catalogs hold %d; manifest repaired",
                self.base,
                m.current_index,
                report.records,
            )
        m.current_index = self.index
        if self.fsync and report.records != report.manifest_index:
            self._flush_data()  # lines the old manifest did not count may still be only in the page cache
        for s in scans[:-1]:  # earlier catalogs: make their manifests match what is on disk
            if s.manifest is None or s.manifest.line_lengths != s.line_lengths():
                created = s.manifest.created_at if s.manifest is not None else time.time()
                cm = CatalogManifest(catalog_manifest_name(s.name), s.start_index, created, s.line_lengths())
                self._replace(str(self.base / catalog_manifest_name(s.name)), cm.encode())
        self._write_catalog_manifest()
        self._write_manifest(m)
        if self.fsync:
            self.io.sync_dir(str(self.base))
        self.repair = report
        if report.changed:
            logger.info("repaired tub %s: %s", self.base, report)
        return m

    def _set_catalog(self, name: str, start_index: int, lengths: list[int], size: int, listed: bool) -> None:
        self._catalog = name
        self._catalog_path = str(self.base / name)
        self._cm_path = str(self.base / catalog_manifest_name(name))
        self._start = start_index
        self._lengths = lengths
        self._size = size
        self._listed = listed
        self._cat_created_at = time.time()
        self._fd = self.io.open_append(self._catalog_path)

    # ---------------------------------------------------------------------------------------- writing
    def write(self, t_wall: float, values: Sequence[Any]) -> int:
        """Write one record (images first, then its catalog line); returns its index.

        Raises ``OSError`` when a file cannot be written; the record is then not in the tub (its image files
        are removed, a partial line is cut off) and its index is given to the next record (no gaps:
        Donkeycar's reader counts positions). :attr:`index` counts only records whose line was written.
        """
        if self._needs_truncate:
            self.io.truncate(self._fd, self._size)
            self._needs_truncate = False
        if len(self._lengths) >= self.max_len:
            self._roll_over()
        idx = self.index
        images: list[str] = []
        try:
            rec = self._record(idx, t_wall, values, images)
            try:
                text = json.dumps(rec, allow_nan=False, sort_keys=True, default=json_default)
            except (TypeError, ValueError):
                text = self._dumps_dropping_bad(rec)
            line = (text + "\n").encode("ascii")
            self._append_line(line)
        except OSError:
            self._remove_quietly(images)
            raise
        self._pending_images.extend(images)
        self._size += len(line)
        self._lengths.append(len(line))
        self.index = idx + 1
        self._unsynced += 1
        if not self._listed:
            self.sync_requested = True  # list a new catalog as soon as it has a line
        return idx

    def _record(self, idx: int, t_wall: float, values: Sequence[Any], images: list[str]) -> dict[str, Any]:
        """The record's catalog entry, its image files written first (each path goes into ``images`` before
        its write, so a failed record's files, a partial one included, can be removed)."""
        rec: dict[str, Any] = {}
        for (key, conv, ext), v in zip(self._plan, values, strict=True):
            if v is None:
                continue
            try:
                out = conv(v)
            except (TypeError, ValueError) as exc:
                self._bad_value(key, exc)
                continue
            if ext is None:
                rec[key] = out
            else:
                name = image_file_name(idx, key, ext)
                path = os.path.join(self._images, name)
                images.append(path)
                self._write_file(path, out)
                rec[key] = name
        rec["_index"] = idx
        rec["_session_id"] = self.session[1]
        rec["_timestamp_ms"] = round(t_wall * 1000)
        return rec

    def _append_line(self, line: bytes) -> None:
        """Append a catalog line whole or not at all: a partial line (the disk filled mid-write) is cut off
        so the next record does not merge with it. The error names the catalog."""
        try:
            self.io.append(self._fd, line)
        except OSError as exc:
            try:
                self.io.truncate(self._fd, self._size)
            except OSError:
                self._needs_truncate = True
            raise with_filename(exc, self._catalog_path) from exc

    def _write_file(self, path: str, data: bytes) -> None:
        try:
            self.io.write_file(path, data)
        except OSError as exc:
            raise with_filename(exc, path) from exc

    def _remove_quietly(self, paths: Iterable[str]) -> None:
        """Remove files of a write that failed (best effort: they are not referenced, and on a full disk the
        space they hold is what the next attempt needs)."""
        for path in paths:
            try:
                self.io.remove(path)
            except OSError:
                pass

    def _dumps_dropping_bad(self, rec: dict[str, Any]) -> str:
        for key in [k for k in rec if not k.startswith("_")]:
            try:
                json.dumps(rec[key], allow_nan=False, default=json_default)
            except (TypeError, ValueError) as exc:
                del rec[key]
                self._bad_value(key, exc)
        return json.dumps(rec, allow_nan=False, sort_keys=True, default=json_default)

    def _bad_value(self, key: str, exc: Exception) -> None:
        self.bad_values += 1
        if self._on_bad_value is not None:
            self._on_bad_value(key, exc)

    def _roll_over(self) -> None:
        """Close the full catalog (synced, so its manifest is final) and start the next, not yet listed."""
        self.sync()
        self.io.close(self._fd)
        self._set_catalog(catalog_name(len(self.manifest.paths)), self.index, [], 0, listed=False)

    # ------------------------------------------------------------------------------------ deleting
    def delete_last(self, n: int) -> list[int]:
        """Mark the last ``n`` records that are not deleted yet as deleted (Donkeycar's TubWiper)."""
        deleted = self.manifest.deleted_indexes
        out: list[int] = []
        i = self.index - 1
        while i >= 0 and len(out) < n:
            if i not in deleted:
                out.append(i)
            i -= 1
        self.delete(out)
        return out

    def delete(self, indexes: Iterable[int]) -> None:
        self.manifest.deleted_indexes.update(indexes)
        self._meta_dirty = True
        self.sync_requested = True

    def restore(self, indexes: Iterable[int]) -> None:
        self.manifest.deleted_indexes.difference_update(indexes)
        self._meta_dirty = True
        self.sync_requested = True

    # ------------------------------------------------------------------------------------- syncing
    @property
    def unsynced(self) -> int:
        return self._unsynced

    def sync(self) -> bool:
        """Make everything written so far durable (see the module docstring). Returns False if nothing to do."""
        self.sync_requested = False
        if not (self._unsynced or self._meta_dirty):
            return False
        io = self.io
        m = self.manifest
        if self.index > self._session_start and not self._session_recorded:
            add_session(m.manifest_metadata, self.session)
            self._session_recorded = True
        # A rolled-over catalog is listed only once it holds a line: Donkeycar's read-only reader cannot
        # open an empty catalog file (it memory-maps it).
        listing = not self._listed and bool(self._lengths)
        if listing:
            m.paths.append(self._catalog)
        m.current_index = self.index
        man_path = str(self.base / MANIFEST_NAME)
        man_tmp = man_path + TMP_SUFFIX
        cm_tmp = self._cm_path + TMP_SUFFIX
        write_cm = self._listed or listing
        try:
            if write_cm:
                cm = CatalogManifest(
                    catalog_manifest_name(self._catalog), self._start, self._cat_created_at, self._lengths
                )
                self._write_file(cm_tmp, cm.encode())
            self._write_file(man_tmp, m.encode())
            if self.fsync:
                if io.has_syncfs:
                    io.sync_filesystem(self._fd)  # images, catalog lines and both temporaries in one flush
                else:
                    self._flush_data()
                    if write_cm:
                        io.sync_path(cm_tmp)
                    io.sync_path(man_tmp)
                    if listing:
                        io.sync_dir(str(self.base))  # the new catalog's entry before the manifest names it
            if write_cm:
                io.replace(cm_tmp, self._cm_path)
            io.replace(man_tmp, man_path)
            if self.fsync:
                io.sync_dir(str(self.base))
        except OSError as exc:
            if listing:
                m.paths.pop()
            self._remove_quietly(p for p in (cm_tmp, man_tmp) if os.path.exists(p))
            raise with_filename(exc, str(self.base)) from exc
        if listing:
            self._listed = True
        self._pending_images.clear()
        self._unsynced = 0
        self._meta_dirty = False
        self.durable = self.index
        self.syncs += 1
        return True

    def _flush_data(self) -> None:
        """Flush the images and catalog lines written since the last sync point."""
        io = self.io
        if io.has_syncfs:
            io.sync_filesystem(self._fd)
            return
        for p in self._pending_images:
            io.sync_path(p)
        if self._pending_images:
            io.sync_dir(self._images)
        io.sync_file(self._fd)

    def _replace(self, path: str, data: bytes) -> None:
        tmp = path + TMP_SUFFIX
        self._write_file(tmp, data)
        if self.fsync:
            self.io.sync_path(tmp)
        self.io.replace(tmp, path)

    def _write_catalog_manifest(self) -> None:
        cm = CatalogManifest(catalog_manifest_name(self._catalog), self._start, self._cat_created_at, self._lengths)
        self._replace(self._cm_path, cm.encode())

    def _write_manifest(self, m: ManifestData) -> None:
        self._replace(str(self.base / MANIFEST_NAME), m.encode())

    def close(self) -> None:
        """Sync what is left, then close the catalog. Safe to call twice.

        When the last sync point fails (a full disk), the records are still in the catalogs, which every reader
        reads; only the manifests lag behind, until the tub is opened for writing again (or
        :func:`repair_tub`). The ``OSError`` raised says so.
        """
        if self._fd < 0:
            return
        try:
            self.sync()
        except OSError as exc:
            raise OSError(
                exc.errno,
                f"{exc.strerror or exc}: the last sync point failed; the catalogs hold {self.index} records, "
                f"manifest.json counts {self.durable} (readers read the catalogs; reopening the tub repairs it)",
                exc.filename,
            ) from exc
        finally:
            self.io.close(self._fd)
            self._fd = -1


def repair_tub(base_path: str | os.PathLike[str], *, fsync: bool = True) -> RepairReport:
    """Make a tub's manifests match its catalogs after a crash (what opening it for writing does).

    Removes a torn last line from each catalog, lists a catalog the writer had started but not yet listed,
    sets ``current_index`` to the records actually present, rewrites the catalog manifests' ``line_lengths``
    and deletes leftover temporary files. Run it before appending to a crashed tub with Donkeycar's own
    writer, which trusts the manifests. Records are never removed.
    """
    appender = TubAppender(base_path, create=False, fsync=fsync)
    appender.close()
    assert appender.repair is not None
    return appender.repair
