"""``asyncdonkey convert``: a tub into MCAP, and an MCAP recording's camera and controls into a tub.

::

    asyncdonkey convert data/tub_1 data/tub_1.mcap            # look at an old tub in Foxglove
    asyncdonkey convert data/drive.mcap data/tub_2             # train on an MCAP drive with `donkey train`
    asyncdonkey convert data/drive.mcap data/tub_2 --only-when recording

**Tub → MCAP.** Each record becomes one tick at its ``_timestamp_ms``: images as ``foxglove.CompressedImage``
(the tub's JPEG bytes copied, not re-encoded), every other value as the recorder's JSON messages, the tub's
metadata in the ``asyncdonkey.session`` record. A tub knows nothing of origins, so each value's origin is its
record's time (``age_ms`` 0). Deleted records are left out.

**MCAP → tub.** One record per camera frame (:class:`~asyncdonkey.parts.mcap.reader.McapTub`): the frame
(JPEG copied as is) and the newest value of every channel that fits a Tub v2 type at that tick (numbers →
``float``, strings → ``str``, booleans → ``boolean``, arrays → ``list``; dicts, lidar scans and the loop's
timing have no tub type and are left out). ``--only-when CHANNEL`` keeps the ticks where that channel was
truthy, as a ``TubWriter`` with that ``run_condition`` records; ``--channels`` picks the channels. The tub
is written with the project's own tub writer, so Donkeycar's reader (and ``donkey train``) opens it.

**Contracts.** What a file holds is outside data: every value passes a :class:`~asyncdonkey.contracts.Gate` with
the channels' contracts (Donkeycar's defaults, plus ``contracts=``) before it is written, so a NaN throttle, a
string in a number column, a 400-digit integer or a frame of another dtype or shape is never carried into the
new file. Tub → MCAP leaves the refused value out of its tick (the channel's last good value stays the newest
in the file, as a refused network sample leaves Memory); MCAP → tub leaves out the record holding it (a tub row
has every channel, and a row with a hole is no training sample). Checking a frame decodes it. The counts per
channel and reason are in :attr:`ConvertResult.refused` and printed at the end.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..contracts import REFUSED, Contract, Contracts, Gate
from ..errors import AsyncdonkeyError
from ..parts.tub import Tub, TubError, TubImageError

__all__ = [
    "ConvertError",
    "ConvertResult",
    "add_convert_parser",
    "convert",
    "convert_main",
    "mcap_to_tub",
    "tub_to_mcap",
]

EXIT_USAGE = 2

#: JSON schema of the recorder's messages → Tub v2 type
_TUB_TYPES = {
    "asyncdonkey.Number": "float",
    "asyncdonkey.String": "str",
    "asyncdonkey.Bool": "boolean",
    "asyncdonkey.Array": "list",
}


class ConvertError(AsyncdonkeyError, ValueError):
    """A conversion that cannot run; the message names the file and what was expected."""


@dataclass
class ConvertResult:
    source: str
    destination: str
    records: int
    channels: list[str]
    refused: dict[str, dict[str, int]] = field(default_factory=dict)
    """values refused by their channel's contract and not written, ``{channel: {reason: count}}``"""
    records_left_out: int = 0
    """MCAP → tub: records not written because a value of theirs was refused"""

    def summary(self) -> str:
        """What ``asyncdonkey convert`` prints: the records written and, if any, what was refused."""
        lines = [f"{self.records} records: {self.source} -> {self.destination} ({', '.join(self.channels)})"]
        if self.refused:
            n = sum(sum(r.values()) for r in self.refused.values())
            detail = "; ".join(
                f"{ch}: " + ", ".join(f"{reason} {k}" for reason, k in sorted(reasons.items()))
                for ch, reasons in sorted(self.refused.items())
            )
            left_out = f", {self.records_left_out} records left out" if self.records_left_out else ""
            lines.append(f"refused {n} values that break their channel's contract{left_out} ({detail})")
        return "\n".join(lines)


def _gate(contracts: Contracts | Mapping[str, Contract] | None) -> Gate:
    return (contracts if isinstance(contracts, Contracts) else Contracts(contracts)).gate("convert")


def _counts(gate: Gate) -> dict[str, dict[str, int]]:
    return {ch: dict(sorted(r.items())) for ch, r in sorted(gate.counts().items())}


def _image_admitted(gate: Gate, rec: Any, key: str, now: float) -> bool:
    """Does ``rec``'s frame ``key`` keep its channel's contract? Decoded only when there is one to keep; a frame
    that does not decode breaks it (``encoding``)."""
    if gate.contracts.get(key) is None:
        return True
    try:
        image = rec[key]
    except TubImageError as exc:  # not TubImagePathError: a name leading out stops
        gate.refuse(key, "encoding", str(exc), now)
        return False
    return gate.admit(key, image, now) is not REFUSED


def _values_admitted(gate: Gate, pairs: Sequence[tuple[str, Any]], now: float) -> bool:
    """Whether every ``(channel, value)`` keeps its contract (``None``, a value not recorded, is not checked);
    each is asked, so every refusal is counted."""
    ok = True
    for ch, value in pairs:
        if value is not None and gate.admit(ch, value, now) is REFUSED:
            ok = False
    return ok


def tub_to_mcap(
    tub_path: str | os.PathLike[str],
    mcap_path: str | os.PathLike[str],
    *,
    compression: str = "zstd",
    contracts: Contracts | Mapping[str, Contract] | None = None,
) -> ConvertResult:
    """Write the tub's records to a new MCAP file (see the module docstring); values that break their channel's
    contract are left out and counted."""
    from ..parts.mcap.encode import TickEncoder, TickSnapshot, TimeMap
    from ..parts.mcap.sink import McapSink

    tub = Tub(tub_path)
    image_keys = [k for k, t in zip(tub.inputs, tub.types, strict=True) if t == "image_array"]
    skipped = {k for k, t in zip(tub.inputs, tub.types, strict=True) if t == "gray16_array"}
    kinds = {k: "image" for k in image_keys} | {k: "skip" for k in skipped}
    encoder = TickEncoder(every_tick=True, kinds=kinds, timing=False, steering=())
    meta = {str(k): str(v) for k, v in tub.metadata.items()} if isinstance(tub.metadata, dict) else {}
    meta["converted_from"] = str(tub.base_path)
    gate = _gate(contracts)
    sink = McapSink(mcap_path, encoder, metadata=meta, fsync=False, compression=compression)
    n = 0
    first_ms: int | None = None
    try:
        for rec in tub.records():
            ts = rec.raw.get("_timestamp_ms")
            if not isinstance(ts, int | float) or isinstance(ts, bool):
                continue
            if first_ms is None:
                # the first record's millisecond is the anchor, in integers; later records are milliseconds from
                # it, which the tub clock maps to nanoseconds exactly (TimeMap.resolution_ns)
                first_ms = round(ts)
                sink.times = TimeMap(0.0, first_ms * 1_000_000, "tub", resolution_ns=1_000_000)
            t = (ts - first_ms) / 1000.0
            now = time.monotonic()
            values: dict[str, Any] = {}
            for key, value in rec.raw.items():
                if key.startswith("_") or key in skipped or value is None:
                    continue
                if key in image_keys:
                    if not isinstance(value, str):  # a damaged line: no image name, no image
                        continue
                    try:
                        value = rec.image_path(key).read_bytes()
                    except OSError:
                        continue
                    if not _image_admitted(gate, rec, key, now):
                        continue
                elif gate.admit(key, value, now) is REFUSED:
                    continue  # the value as recorded is written, never a normalised copy: only checked here
                values[key] = value
            sink.write(t, tuple(TickSnapshot(t, values, dict.fromkeys(values, t), 0, None, None, None)))
            n += 1
            if sink.unsynced >= 200:
                sink.sync()
    except BaseException:
        sink.close()
        _remove_partial(Path(mcap_path))
        raise
    sink.close()
    channels = [k for k in tub.inputs if k not in skipped]
    return ConvertResult(str(tub.base_path), os.fspath(mcap_path), n, channels, _counts(gate))


def mcap_to_tub(
    mcap_path: str | os.PathLike[str],
    tub_path: str | os.PathLike[str],
    *,
    image_key: str = "cam/image_array",
    channels: list[str] | None = None,
    only_when: str | None = None,
    contracts: Contracts | Mapping[str, Contract] | None = None,
) -> ConvertResult:
    """Write the recording's camera frames and controls to a new tub (see the module docstring); a record holding
    a value that breaks its channel's contract is left out and counted."""
    from ..parts.mcap.encode import topic_for
    from ..parts.mcap.reader import McapTub
    from ..parts.tub.appender import TubAppender

    src = McapTub(mcap_path, image_key, run_condition=only_when)
    topics = src.info.topics
    if topic_for(image_key) not in topics:
        raise ConvertError(f"{os.fspath(mcap_path)}: no {image_key!r} frames (its topics: {sorted(topics)})")
    wanted = channels if channels is not None else [c for c in src.inputs if c != image_key]
    inputs, types = [image_key], ["image_array"]
    for ch in wanted:
        t = _TUB_TYPES.get(topics.get(topic_for(ch), ""))
        if t is None:
            if channels is not None:
                have = topics.get(topic_for(ch), "not recorded")
                raise ConvertError(f"{os.fspath(mcap_path)}: channel {ch!r} has no tub type ({have})")
            continue
        inputs.append(ch)
        types.append(t)
    if Path(tub_path).exists():
        raise ConvertError(f"{os.fspath(tub_path)} already exists; convert into a new tub directory")
    meta = {k: v for k, v in src.metadata.items()}
    meta["converted_from"] = os.fspath(mcap_path)
    gate = _gate(contracts)
    app = TubAppender(tub_path, inputs, types, meta)
    n = left_out = 0
    try:
        for rec in src.records():
            now = time.monotonic()
            values = [rec.image_bytes(image_key), *(rec.raw.get(ch) for ch in inputs[1:])]
            image_ok = _image_admitted(gate, rec, image_key, now)
            if not (_values_admitted(gate, list(zip(inputs[1:], values[1:], strict=True)), now) and image_ok):
                left_out += 1
                continue
            app.write(rec.raw["_timestamp_ms"] / 1000.0, values)
            n += 1
            if app.unsynced >= 200:
                app.sync()
    except BaseException:
        app.close()
        _remove_partial(app.base)
        raise
    app.close()
    return ConvertResult(os.fspath(mcap_path), str(app.base), n, inputs, _counts(gate), left_out)


def _remove_partial(path: Path) -> None:
    """Remove what a conversion that failed half-way created (the destination did not exist before it started), so
    the half-written file does not pass for a conversion and the command can be run again as it was."""
    try:
        if path.is_dir():
            shutil.rmtree(path)
        else:
            path.unlink(missing_ok=True)
    except OSError:
        pass  # the error that stopped the conversion is the one to report


def convert(
    source: str | os.PathLike[str],
    destination: str | os.PathLike[str],
    *,
    image_key: str = "cam/image_array",
    channels: list[str] | None = None,
    only_when: str | None = None,
    contracts: Contracts | Mapping[str, Contract] | None = None,
) -> ConvertResult:
    """Tub directory → MCAP file, or MCAP file → tub directory, by what ``source`` is."""
    from .recordings import check_recording, is_mcap

    check_recording(source)
    if is_mcap(source):
        return mcap_to_tub(
            source, destination, image_key=image_key, channels=channels, only_when=only_when, contracts=contracts
        )
    if not Path(source).is_dir():
        raise ConvertError(f"{os.fspath(source)}: neither a tub directory nor an MCAP file")
    if Path(destination).exists():
        raise ConvertError(f"{os.fspath(destination)} already exists; convert into a new file")
    return tub_to_mcap(source, destination, contracts=contracts)


def add_convert_parser(subparsers: Any) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "convert",
        help="convert a tub to MCAP, or an MCAP recording's camera and controls to a tub",
        description="Tub directory -> MCAP file (look at it in Foxglove), or MCAP file -> tub directory "
        "(train on it with donkey train). The direction follows the source.",
    )
    p.add_argument(
        "source", help="what to convert: a tub directory or an .mcap file (both directions need the mcap extra)"
    )
    p.add_argument(
        "destination",
        help="what to create: an .mcap file from a tub, a new tub directory from an .mcap file (must not exist)",
    )
    p.add_argument(
        "--image-key",
        default="cam/image_array",
        metavar="CHANNEL",
        help="MCAP -> tub: the camera channel, one record per frame (default: %(default)s)",
    )
    p.add_argument(
        "--channels",
        nargs="+",
        default=None,
        metavar="CHANNEL",
        help="MCAP -> tub: the channels to keep (default: every one a tub can store)",
    )
    p.add_argument(
        "--only-when",
        metavar="CHANNEL",
        default=None,
        help="MCAP -> tub: keep only the ticks where CHANNEL was true, e.g. recording",
    )
    p.set_defaults(handler=convert_main)
    return p


def convert_main(args: argparse.Namespace) -> int:
    try:
        res = convert(
            args.source, args.destination, image_key=args.image_key, channels=args.channels, only_when=args.only_when
        )
    except (ConvertError, TubError, OSError, ImportError) as exc:
        print(f"asyncdonkey convert: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    print(res.summary())
    return 0
