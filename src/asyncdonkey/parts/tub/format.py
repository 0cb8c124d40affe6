"""Donkeycar's Tub v2 on-disk format: names, the manifest's five lines, catalog manifests, session ids.

Pure functions and small records only, shared by the writer, the reader and the repair code, so there is
exactly one place that knows what the files look like. Learned from Donkeycar 5.3's ``tub_v2.py`` and
``datastore_v2.py`` (read, not copied); the layout of a tub directory is::

    manifest.json                  five JSON lines:
                                     1. inputs         ["cam/image_array", "user/angle", ...]
                                     2. types          ["image_array", "float", ...]
                                     3. user metadata  {"key": "value", ...}
                                     4. manifest meta  {"created_at": <epoch s>, "sessions": {...}}
                                     5. catalog meta   {"paths": [...], "current_index": N, "max_len": M,
                                                        "deleted_indexes": [...]}
    catalog_0.catalog              one JSON record per line, keys sorted, at most ``max_len`` lines
    catalog_0.catalog_manifest     one JSON line: created_at, line_lengths, path, start_index (keys sorted)
    images/0_cam_image_array_.jpg  ``{index}_{key with / replaced by _}_.jpg`` (``.png`` for gray16_array)

Every record also carries ``_index`` (its position in the tub), ``_session_id`` (``"YY-MM-DD_N"``) and
``_timestamp_ms`` (wall clock, ms). Line lengths are counted in characters including the newline; JSON is
written with ``ensure_ascii`` so characters and bytes agree.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ...errors import AsyncdonkeyError

__all__ = [
    "IMAGES_DIR",
    "IMAGE_EXTENSIONS",
    "MANIFEST_NAME",
    "RESERVED_KEYS",
    "TYPES",
    "CatalogManifest",
    "ManifestData",
    "TubError",
    "TubFormatError",
    "TubImageError",
    "TubImagePathError",
    "TubNotFoundError",
    "add_session",
    "catalog_manifest_name",
    "catalog_name",
    "image_file_name",
    "new_session_id",
    "parse_metadata",
    "read_catalog_manifest",
    "read_manifest",
]

logger = logging.getLogger(__name__)

MANIFEST_NAME = "manifest.json"
IMAGES_DIR = "images"

#: The value types Donkeycar's Tub v2 knows.
TYPES: frozenset[str] = frozenset(
    {"float", "int", "str", "boolean", "nparray", "list", "vector", "image_array", "gray16_array"}
)
#: Types stored as files under ``images/``; the catalog holds the file name. JPEG for colour/grey uint8,
#: 16-bit PNG for depth-like uint16 images.
IMAGE_EXTENSIONS: Mapping[str, str] = {"image_array": ".jpg", "gray16_array": ".png"}
#: Keys the tub adds to every record; an input may not use them.
RESERVED_KEYS: tuple[str, ...] = ("_index", "_session_id", "_timestamp_ms")


class TubError(AsyncdonkeyError):
    """Base class for tub errors."""


class TubNotFoundError(TubError, FileNotFoundError):
    """The path is not a tub (no ``manifest.json``)."""


class TubFormatError(TubError, ValueError):
    """A tub file does not follow the format (the message names the file and what was expected)."""


class TubImageError(TubError, OSError):
    """A record's image file is missing or cannot be decoded (the message names the file)."""


class TubImagePathError(TubFormatError):
    """A record's image name leads out of the tub's ``images/`` (absolute, ``..``, a symlink out): refused, never
    read. Not a :class:`TubImageError`: a reader that passes over an unreadable image must not pass over this."""


def catalog_name(n: int) -> str:
    """``catalog_{n}.catalog``: Donkeycar numbers catalogs consecutively from 0."""
    return f"catalog_{n}.catalog"


def catalog_manifest_name(catalog: str) -> str:
    """``catalog_3.catalog`` → ``catalog_3.catalog_manifest``."""
    return f"{Path(catalog).stem}.catalog_manifest"


def image_file_name(index: int, key: str, extension: str) -> str:
    """The file name Donkeycar gives the image of ``key`` in record ``index``: ``0_cam_image_array_.jpg``."""
    return f"{index}_{key.replace('/', '_')}_{extension}"


def parse_metadata(items: Iterable[str] | Mapping[str, Any]) -> dict[str, Any]:
    """User metadata from Donkeycar's ``["key:value", ...]`` list (or a mapping, taken as is).

    Donkeycar splits on every ``:`` and drops items with more than one (a time or a URL as the value); we
    split on the first ``:`` only, so ``"start:12:30"`` keeps ``"12:30"``. An item without ``:`` is an error.
    """
    if isinstance(items, Mapping):
        return dict(items)
    if isinstance(items, str):
        raise TypeError(f"tub metadata must be a list of 'key:value' strings, got the string {items!r}")
    out: dict[str, Any] = {}
    for item in items:
        if not isinstance(item, str) or ":" not in item:
            raise ValueError(f"tub metadata item {item!r} is not a 'key:value' string")
        key, _, value = item.partition(":")
        out[key] = value
    return out


def new_session_id(manifest_metadata: Mapping[str, Any], date: str | None = None) -> tuple[int, str]:
    """The next session as ``(number, "YY-MM-DD_number")``: one more than the last recorded, else 0."""
    sessions = manifest_metadata.get("sessions") or {}
    last = sessions.get("last_id")
    number = last + 1 if isinstance(last, int) else 0
    return number, f"{date if date is not None else time.strftime('%y-%m-%d')}_{number}"


def add_session(manifest_metadata: dict[str, Any], session: tuple[int, str]) -> None:
    """Record ``session`` in the manifest metadata the way Donkeycar does when a session wrote records."""
    sessions = manifest_metadata.get("sessions")
    if not isinstance(sessions, dict):
        sessions = {}
    ids = sessions.get("all_full_ids")
    if not isinstance(ids, list):
        ids = []
    number, full_id = session
    if full_id not in ids:
        ids.append(full_id)
    sessions["all_full_ids"] = ids
    sessions["last_id"] = number
    sessions["last_full_id"] = full_id
    manifest_metadata["sessions"] = sessions


@dataclass
class ManifestData:
    """The contents of ``manifest.json``."""

    inputs: list[str]
    types: list[str]
    metadata: dict[str, Any] = field(default_factory=dict)
    manifest_metadata: dict[str, Any] = field(default_factory=dict)
    paths: list[str] = field(default_factory=list)
    current_index: int = 0
    max_len: int = 1000
    deleted_indexes: set[int] = field(default_factory=set)

    def encode(self) -> bytes:
        """The five lines, formatted as Donkeycar formats them (``json.dumps`` defaults, ``\\n`` endings)."""
        catalog_meta = {
            "paths": self.paths,
            "current_index": self.current_index,
            "max_len": self.max_len,
            "deleted_indexes": sorted(self.deleted_indexes),
        }
        lines = (self.inputs, self.types, self.metadata, self.manifest_metadata, catalog_meta)
        return "".join(json.dumps(x) + "\n" for x in lines).encode("ascii")

    @classmethod
    def decode(cls, data: bytes, where: Path | str) -> ManifestData:
        """Parse ``manifest.json`` bytes; ``where`` names the file in errors."""
        try:
            text = data.decode("utf-8")
        except UnicodeDecodeError as exc:
            raise TubFormatError(f"{where}: not UTF-8 text ({exc})") from None
        lines = [ln for ln in text.splitlines() if ln.strip()]
        if len(lines) < 5:
            raise TubFormatError(
                f"{where}: expected 5 JSON lines (inputs, types, metadata, manifest metadata, catalog metadata), "
                f"found {len(lines)} (torn or truncated manifest?)"
            )
        names = ("inputs", "types", "user metadata", "manifest metadata", "catalog metadata")
        parsed: list[Any] = []
        for n, (name, line) in enumerate(zip(names, lines, strict=False), start=1):
            try:
                parsed.append(json.loads(line))
            except json.JSONDecodeError as exc:
                raise TubFormatError(f"{where}: line {n} ({name}) is not valid JSON: {exc}") from None
        inputs, types, metadata, manifest_metadata, catalog = parsed
        if not (isinstance(inputs, list) and all(isinstance(x, str) for x in inputs)):
            raise TubFormatError(f"{where}: line 1 (inputs) must be a list of strings, got {inputs!r}")
        if not (isinstance(types, list) and all(isinstance(x, str) for x in types)):
            raise TubFormatError(f"{where}: line 2 (types) must be a list of strings, got {types!r}")
        if len(inputs) != len(types):
            raise TubFormatError(f"{where}: {len(inputs)} inputs but {len(types)} types")
        if not isinstance(metadata, dict):
            raise TubFormatError(f"{where}: line 3 (user metadata) must be a JSON object, got {metadata!r}")
        if not isinstance(manifest_metadata, dict):
            raise TubFormatError(f"{where}: line 4 (manifest metadata) must be a JSON object")
        if not isinstance(catalog, dict):
            raise TubFormatError(f"{where}: line 5 (catalog metadata) must be a JSON object, got {catalog!r}")
        try:
            paths = catalog["paths"]
            current_index = catalog["current_index"]
            max_len = catalog["max_len"]
            deleted = catalog.get("deleted_indexes", [])
        except KeyError as exc:
            raise TubFormatError(f"{where}: line 5 (catalog metadata) has no {exc.args[0]!r}") from None
        if not (isinstance(paths, list) and all(isinstance(p, str) for p in paths)):
            raise TubFormatError(f"{where}: catalog 'paths' must be a list of file names, got {paths!r}")
        outside = [p for p in paths if not _plain_name(p)]
        if outside:  # a catalog is a file of the tub: a path leading elsewhere is never read
            raise TubFormatError(f"{where}: catalog path {outside[0]!r} is not a file name inside the tub")
        if not (isinstance(current_index, int) and current_index >= 0):
            raise TubFormatError(f"{where}: 'current_index' must be a non-negative integer, got {current_index!r}")
        if not (isinstance(max_len, int) and max_len > 0):
            raise TubFormatError(f"{where}: 'max_len' must be a positive integer, got {max_len!r}")
        if not (isinstance(deleted, list) and all(isinstance(i, int) for i in deleted)):
            raise TubFormatError(f"{where}: 'deleted_indexes' must be a list of integers")
        return cls(inputs, types, metadata, manifest_metadata, paths, current_index, max_len, set(deleted))


def _plain_name(name: str) -> bool:
    """A file name of the tub's own directory: no directory part, not ``.``/``..``, no NUL."""
    return bool(name) and name not in (".", "..") and not any(c in name for c in "/\\\x00")


def read_manifest(base_path: Path) -> ManifestData:
    """Read and check ``base_path/manifest.json``; errors name the path."""
    path = base_path / MANIFEST_NAME
    if not base_path.is_dir():
        raise TubNotFoundError(f"{base_path}: no such tub directory")
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise TubNotFoundError(f"{base_path}: not a tub (no {MANIFEST_NAME})") from None
    return ManifestData.decode(data, path)


@dataclass
class CatalogManifest:
    """The one line of ``catalog_N.catalog_manifest``."""

    path: str
    start_index: int
    created_at: float
    line_lengths: list[int] = field(default_factory=list)

    def encode(self) -> bytes:
        contents = {
            "created_at": self.created_at,
            "line_lengths": self.line_lengths,
            "path": self.path,
            "start_index": self.start_index,
        }
        return (json.dumps(contents, allow_nan=False, sort_keys=True) + "\n").encode("ascii")

    @classmethod
    def decode(cls, data: bytes, where: Path | str) -> CatalogManifest:
        try:
            first = data.decode("utf-8").splitlines()[0]
            contents = json.loads(first)
            start = contents["start_index"]
            lengths = contents.get("line_lengths", [])
        except (UnicodeDecodeError, IndexError, json.JSONDecodeError, KeyError, TypeError) as exc:
            raise TubFormatError(f"{where}: not a catalog manifest line ({type(exc).__name__}: {exc})") from None
        if not (isinstance(start, int) and start >= 0):
            raise TubFormatError(f"{where}: 'start_index' must be a non-negative integer, got {start!r}")
        if not (isinstance(lengths, list) and all(isinstance(n, int) and n > 0 for n in lengths)):
            raise TubFormatError(f"{where}: 'line_lengths' must be a list of positive integers")
        return cls(
            path=str(contents.get("path", Path(where).name)),
            start_index=start,
            created_at=float(contents.get("created_at", 0.0)),
            line_lengths=lengths,
        )


def read_catalog_manifest(base_path: Path, catalog: str) -> CatalogManifest | None:
    """The manifest of ``catalog``, or ``None`` when it is missing or unreadable (logged)."""
    path = base_path / catalog_manifest_name(catalog)
    try:
        return CatalogManifest.decode(path.read_bytes(), path)
    except FileNotFoundError:
        return None
    except TubFormatError as exc:
        logger.warning("%s", exc)
        return None
