"""Reading recordings back: decoded messages, crash recovery, and a tub-like view for replay and conversion.

:func:`read_mcap` yields :class:`McapMessage` (topic, times, decoded value) from any MCAP file this project
writes. It reads the data section record by record rather than through the summary, so a file whose writer
was killed (no summary, maybe a torn last record) gives every message up to the last complete chunk; the
``recovered`` flag of :func:`mcap_info` says whether the file was cut short.

Decoding: JSON messages become dicts; protobuf messages (the Foxglove schemas) are decoded with the schema the
file carries (``google.protobuf``), and a ``foxglove.CompressedImage`` also gets its JPEG decoded to an RGB
array, as the tub reader returns images.

:class:`McapTub` shows a recording as records the way :class:`~asyncdonkey.parts.tub.Tub` does, so replay and
``convert`` treat both alike: one record per tick that wrote the image channel, holding that frame and the
newest value of every other channel at that tick, ``_timestamp_ms`` from the tick's log time and ``_index``
counting records from 0. With ``run_condition`` (say ``"recording"``), only ticks where that channel was
truthy become records, as a :class:`~asyncdonkey.parts.tub.TubWriter` with that run condition would have
recorded them.

A tick's messages are found by their record number, which the recorder writes in each message's ``sequence``
field (:mod:`.sink`): two records may share a log time (a tub converted to MCAP stamps whole milliseconds, and
Donkeycar may stamp several records in one). Files written before record numbers existed have ``sequence`` 0
throughout; their messages are grouped by log time, as they were written.
"""

from __future__ import annotations

import json
import logging
import os
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ...extras import MissingExtra, require
from ..tub import TubFormatError, TubImageError, TubNotFoundError
from .encode import topic_for
from .sink import CLOCK_METADATA, SESSION_METADATA

__all__ = [
    "McapInfo",
    "McapMessage",
    "McapReadError",
    "McapRecord",
    "McapTub",
    "decode_image",
    "mcap_info",
    "protobuf_class",
    "read_mcap",
]

logger = logging.getLogger(__name__)


_MAGIC = b"\x89MCAP0\r\n"


class McapReadError(TubFormatError):
    """A file that is not an MCAP recording (the message names the file); a tub format error, so code that
    opens recordings of either kind handles both alike."""


@dataclass(frozen=True)
class McapMessage:
    topic: str
    log_time_ns: int
    publish_time_ns: int
    schema: str
    value: Any
    """JSON messages as dicts; protobuf messages as ``google.protobuf`` messages."""
    sequence: int = 0
    """the number of the record (tick) the message belongs to, from 1; 0 in files written before record
    numbers (see :class:`McapTub`)"""


@dataclass
class McapInfo:
    path: str
    messages: int
    topics: dict[str, str]
    """topic → schema name"""
    metadata: dict[str, dict[str, str]]
    recovered: bool
    """True when the file has no summary (the writer did not close it) and was read up to its last complete
    record."""
    damage: list[str] = field(default_factory=list)
    """where the reading met damage and what it did: a chunk left out (CRC mismatch), or the byte it could not
    read past; empty for an intact file (a crash's torn end is ``recovered``, and listed here too)"""


#: The most a chunk may claim to hold uncompressed: our recorder ends chunks at 4 MiB; a larger claim is a damaged
#: size field, which would otherwise have the decompressor allocate it.
_MAX_CHUNK_BYTES = 1 << 30


def _records(path: str | os.PathLike[str]) -> Iterator[Any]:
    """The file's records in order. Damage never raises: a chunk that fails its CRC (or does not decompress) is
    left out and reported as :class:`_Damaged`, and the reading goes on with the next record; a record whose
    framing is broken (a torn end after a crash, a length past the end of the file) ends the reading with a
    :class:`_Torn`. Records are never longer than the file, which keeps a flipped length from allocating
    gigabytes."""
    from mcap.records import Chunk
    from mcap.stream_reader import StreamReader, breakup_chunk

    with open(path, "rb") as f:
        size = os.fstat(f.fileno()).st_size
        reader = StreamReader(f, skip_magic=False, emit_chunks=True, record_size_limit=size)
        records = iter(reader.records)
        while True:
            start = f.tell()  # where the next record starts (the reader reads the file unbuffered)
            try:
                rec = next(records)
            except StopIteration:
                return
            except Exception as exc:  # any parse error: the reader cannot go past it
                yield _Torn(start, _why(exc))
                return
            if not isinstance(rec, Chunk):
                yield rec
                continue
            try:
                if rec.uncompressed_size > _MAX_CHUNK_BYTES:
                    raise ValueError(f"claims {rec.uncompressed_size} bytes uncompressed")
                inner = breakup_chunk(rec, validate_crc=True)
            except Exception as exc:  # a CRC mismatch, or zstd/lz4/struct errors with their own types
                yield _Damaged(start, _why(exc))
                continue
            yield from inner


def _why(exc: BaseException) -> str:
    return f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__


@dataclass(frozen=True)
class _Torn:
    """The reading stopped at byte ``offset``: the record there cannot be framed (a torn end, a bad length)."""

    offset: int
    why: str


@dataclass(frozen=True)
class _Damaged:
    """The chunk at byte ``offset`` was left out (its messages are lost; the records after it are read)."""

    offset: int
    why: str


_WARNED: set[tuple[str, int, str]] = set()


def _warn_once(path: str | os.PathLike[str], offset: int, what: str) -> None:
    """Log a damage once per file and place: replay and convert read a file more than once."""
    key = (os.fspath(path), offset, what)
    if key not in _WARNED:
        _WARNED.add(key)
        logger.warning("%s: %s", os.fspath(path), what)


def read_mcap(
    path: str | os.PathLike[str], topics: set[str] | None = None, *, decode: bool = True
) -> Iterator[McapMessage]:
    """Every message of the file (or of ``topics``), in file order, decoded (``decode=False``: raw bytes).

    What damage leaves readable is read (see :func:`_records`); what was lost is logged once per file and place.
    A message that does not decode with its schema is left out (logged); a schema that cannot be built at all
    raises :class:`McapReadError`, naming the file, the topic and the schema."""
    require("mcap", "mcap", "reading MCAP recordings")
    from mcap.records import Channel, Message, Schema

    where = os.fspath(path)
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    decoders: dict[int, Any] = {}
    damaged = False
    for rec in _records(path):
        if isinstance(rec, Schema):
            schemas[rec.id] = rec
        elif isinstance(rec, Channel):
            channels[rec.id] = rec
        elif isinstance(rec, Message):
            ch = channels.get(rec.channel_id)
            if ch is None and damaged:  # its definition was in a lost chunk: the summary repeats it
                ch = _definitions_from_summary(path, schemas, channels).get(rec.channel_id)
            if ch is None or (topics is not None and ch.topic not in topics):
                continue
            schema = schemas.get(ch.schema_id)
            name = schema.name if schema is not None else ""
            value: Any = rec.data
            if decode:
                dec = decoders.get(ch.id)
                if dec is None:
                    dec = decoders[ch.id] = _decoder_for(where, ch, schema)
                try:
                    value = dec(rec.data)
                except Exception as exc:  # protobuf's DecodeError, json's, UnicodeDecodeError
                    _warn_once(path, -1, f"{ch.topic}: a message that is not valid {name or 'data'} left out ({exc})")
                    continue
            yield McapMessage(ch.topic, rec.log_time, rec.publish_time, name, value, rec.sequence)
        elif isinstance(rec, _Damaged):
            damaged = True
            _warn_once(path, rec.offset, f"damaged chunk at byte {rec.offset} left out ({rec.why}); read on past it")
        elif isinstance(rec, _Torn):
            _check_torn(where, rec)


def _check_torn(where: str, torn: _Torn) -> None:
    """A file that breaks off before its first record is not a recording: raise. A later break is a crash's torn
    end (or damage to a record's framing): every record before it was read, so log it and stop."""
    if torn.offset < len(_MAGIC):
        raise McapReadError(f"{where}: not an MCAP file ({torn.why})")
    _warn_once(where, torn.offset, f"cannot read past byte {torn.offset} ({torn.why}); every record before it read")


def _decoder_for(where: str, channel: Any, schema: Any) -> Any:
    """:func:`_decoder`, with a schema that cannot be built reported as the file's fault, in one line."""
    try:
        return _decoder(channel, schema)
    except MissingExtra:
        raise
    except Exception as exc:  # protobuf raises TypeError, DecodeError or KeyError on a corrupt descriptor set
        name = schema.name if schema is not None else "?"
        raise McapReadError(f"{where}: the schema {name!r} of {channel.topic} is corrupt ({_why(exc)})") from None


def _definitions_from_summary(path: str | os.PathLike[str], schemas: dict[int, Any], channels: dict[int, Any]) -> Any:
    """Add the schemas and channels of the file's summary section (a closed file repeats every definition there)
    to those read so far, and return the channels. A damaged chunk may have held a channel's only definition in
    the data section; without a readable summary, that channel's later messages stay lost."""
    from mcap.reader import make_reader

    try:
        with open(path, "rb") as f:
            summary = make_reader(f).get_summary()
    except Exception:  # no summary (a crash), or a damaged one: nothing more to learn
        summary = None
    if summary is not None:
        for k, v in summary.schemas.items():
            schemas.setdefault(k, v)
        for k, v in summary.channels.items():
            channels.setdefault(k, v)
    return channels


def mcap_info(path: str | os.PathLike[str]) -> McapInfo:
    """Topics, message count, metadata records, whether the file was cut short and what damage was read past."""
    require("mcap", "mcap", "reading MCAP recordings")
    from mcap.records import Channel, DataEnd, Footer, Message, Metadata, Schema

    if not Path(path).is_file():
        raise TubNotFoundError(f"{os.fspath(path)}: no such MCAP file")
    schemas: dict[int, str] = {}
    topics: dict[str, str] = {}
    metadata: dict[str, dict[str, str]] = {}
    damage: list[str] = []
    n = 0
    finished = False
    for rec in _records(path):
        if isinstance(rec, Schema):
            schemas[rec.id] = rec.name
        elif isinstance(rec, Channel):
            topics[rec.topic] = schemas.get(rec.schema_id, "")
        elif isinstance(rec, Message):
            n += 1
        elif isinstance(rec, Metadata):
            metadata[rec.name] = dict(rec.metadata)
        elif isinstance(rec, DataEnd | Footer):
            finished = True
        elif isinstance(rec, _Damaged):
            damage.append(f"byte {rec.offset}: chunk left out ({rec.why})")
        elif isinstance(rec, _Torn):
            _check_torn(os.fspath(path), rec)
            if finished:
                break  # the data section was read whole; damage in the summary loses nothing
            damage.append(f"byte {rec.offset}: read up to here ({rec.why})")
    return McapInfo(os.fspath(path), n, topics, metadata, recovered=not finished, damage=damage)


def _decoder(channel: Any, schema: Any) -> Any:
    if channel.message_encoding == "json":
        return lambda data: json.loads(data)
    if channel.message_encoding == "protobuf" and schema is not None:
        cls = protobuf_class(schema.name, schema.data)
        return lambda data: _parse(cls, data)
    return lambda data: data


_PROTO_CACHE: dict[tuple[str, bytes], Any] = {}


def protobuf_class(name: str, data: bytes) -> Any:
    """The ``google.protobuf`` message class of schema ``name`` from its serialized ``FileDescriptorSet``."""
    key = (name, data)
    cls = _PROTO_CACHE.get(key)
    if cls is None:
        require("google.protobuf", "mcap", "decoding the Foxglove messages of MCAP recordings")
        from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

        fds = descriptor_pb2.FileDescriptorSet.FromString(data)
        pool = descriptor_pool.DescriptorPool()
        for fd in fds.file:
            pool.Add(fd)
        cls = _PROTO_CACHE[key] = message_factory.GetMessageClass(pool.FindMessageTypeByName(name))
    return cls


def _parse(cls: Any, data: bytes) -> Any:
    msg = cls()
    msg.ParseFromString(data)
    return msg


def decode_image(msg: Any) -> np.ndarray:
    """A ``foxglove.CompressedImage``'s pixels as the tub reader returns them: RGB (or grey) uint8."""
    img = cv2.imdecode(np.frombuffer(msg.data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise TubImageError(f"{msg.frame_id}: image data is not decodable ({msg.format or 'no format'})")
    if img.ndim == 3 and img.shape[2] == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    return img


# ------------------------------------------------------------------------------------------ tub view
def _record_key(m: McapMessage) -> tuple[int, int]:
    """Which record a message belongs to: its record number, or (in files without them, ``sequence`` 0) its log
    time."""
    return (1, m.sequence) if m.sequence else (0, m.log_time_ns)


class McapRecord(Mapping[str, Any]):
    """One record of a :class:`McapTub`; image keys decode their JPEG on access, like the tub's ``Record``."""

    __slots__ = ("_cache", "_images", "raw")

    def __init__(self, raw: dict[str, Any], images: dict[str, Any]) -> None:
        self.raw = raw
        self._images = images
        self._cache: dict[str, np.ndarray] = {}

    def __getitem__(self, key: str) -> Any:
        if key in self._images:
            img = self._cache.get(key)
            if img is None:
                img = self._cache[key] = decode_image(self._images[key])
            return img
        return self.raw[key]

    def __iter__(self) -> Iterator[str]:
        return iter(self.raw)

    def __len__(self) -> int:
        return len(self.raw)

    @property
    def index(self) -> int:
        return self.raw["_index"]

    def image_bytes(self, key: str) -> bytes:
        """The JPEG as recorded (``convert`` copies it into a tub without re-encoding)."""
        return bytes(self._images[key].data)


def _time_map(path: Path, clock: dict[str, str] | None) -> Any:
    """The recording's clock mapping (a :class:`~.encode.TimeMap`), or ``None`` when it has none or it is damaged
    (metadata records lie outside the chunks, with no CRC): the records' log times do not need it."""
    from .encode import TimeMap

    if not clock:
        return None
    try:
        return TimeMap.from_metadata(clock)
    except (KeyError, ValueError) as exc:
        _warn_once(path, -2, f"the {CLOCK_METADATA} metadata is damaged ({_why(exc)}); left out")
        return None


class McapTub:
    """A recording seen as tub records (see the module docstring); ``inputs`` are its Memory channels."""

    def __init__(
        self, path: str | os.PathLike[str], image_key: str = "cam/image_array", run_condition: str | None = None
    ) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise TubNotFoundError(f"{os.fspath(path)}: no such MCAP file")
        with open(self.path, "rb") as f:
            if f.read(len(_MAGIC)) != _MAGIC:
                raise McapReadError(f"{os.fspath(path)}: not an MCAP file")
        self.base_path = str(self.path)
        self.image_key = image_key
        self.run_condition = run_condition
        self.info = mcap_info(self.path)
        self.inputs: list[str] = [
            t[1:] for t in self.info.topics if t.startswith("/") and not t.startswith(("/asyncdonkey/", "/gps/fix"))
        ]
        self.metadata: dict[str, str] = self.info.metadata.get(SESSION_METADATA, {})
        self.times = _time_map(self.path, self.info.metadata.get(CLOCK_METADATA))

    def records(self) -> Iterator[McapRecord]:
        image_topic = topic_for(self.image_key)
        latest: dict[str, Any] = {}
        # the tick being assembled: (its key, its log time, its image message); the key is its record number,
        # or its log time in a file without record numbers
        pending: tuple[tuple[int, int], int, Any] | None = None
        index = 0
        for m in read_mcap(self.path):
            key = _record_key(m)
            if pending is not None and key != pending[0]:
                if self.run_condition is None or latest.get(self.run_condition):
                    yield self._record(pending[1:], latest, index)
                    index += 1
                pending = None
            if m.topic == image_topic:
                pending = (key, m.log_time_ns, m.value)
            elif isinstance(m.value, dict) and "value" in m.value and m.topic.startswith("/"):
                latest[m.topic[1:]] = m.value["value"]
        if pending is not None and (self.run_condition is None or latest.get(self.run_condition)):
            yield self._record(pending[1:], latest, index)

    def _record(self, pending: tuple[int, Any], latest: dict[str, Any], index: int) -> McapRecord:
        log_ns, image = pending
        raw = dict(latest)
        raw[self.image_key] = f"{index}_{self.image_key.replace('/', '_')}.jpg"
        raw["_timestamp_ms"] = (log_ns + 500_000) // 1_000_000  # in integers: a float has no nanoseconds left
        raw["_index"] = index
        return McapRecord(raw, {self.image_key: image})

    def __iter__(self) -> Iterator[McapRecord]:
        return self.records()

    def corrupt_records(self, include_deleted: bool = False) -> list[tuple[int, str, int]]:
        """The tub reader's list of corrupt catalog lines: an MCAP file has none (a torn end after a crash is
        not a record; :attr:`info` ``.recovered`` says whether the file was cut short)."""
        return []
