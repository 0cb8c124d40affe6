"""NMEA 0183 parsing for GPS receivers: RMC and GGA, checksums verified, bad input counted and dropped.

A sentence is ``$<address>,<field>,...*HH`` where ``HH`` (two hex digits) is the XOR of every byte between
``$`` and ``*``. A serial GPS streams these as lines; at start-up and after line noise some are cut,
corrupted or report no fix. :class:`NmeaParser` never raises for any input: it returns a parsed
:class:`Rmc` / :class:`Gga` for a sentence that carries a valid position and ``None`` otherwise, counting
why in :attr:`NmeaParser.counts`:

``no_start``      the line does not begin with ``$`` (a fragment, noise)
``truncated``     no ``*HH`` at the end (the line was cut)
``bad_checksum``  the checksum does not match
``malformed``     checksum fine but a field cannot be read (bad number, latitude over 90°, missing fields)
``void``          RMC status ``V`` (or mode ``N``): the receiver says the position is not valid
``no_fix``        GGA fix quality 0
``unsupported``   a well-formed sentence of another type (GSV, VTG, ...) — ignored, not an error

Any talker is accepted (``GP``, ``GN``, ``GL``, ``GA``, ``BD``, ...). Latitude/longitude are decimal degrees,
south and west negative.
"""

from __future__ import annotations

import datetime as _dt
import re
from dataclasses import dataclass

__all__ = ["REASONS", "Gga", "NmeaParser", "Rmc", "nmea_checksum", "parse_latitude", "parse_longitude"]

REASONS = ("no_start", "truncated", "bad_checksum", "malformed", "void", "no_fix", "unsupported")

_COORD = re.compile(r"([0-9]{1,3})([0-9]{2}(?:\.[0-9]+)?)")
_TIME = re.compile(r"([0-9]{2})([0-9]{2})([0-9]{2})(?:\.([0-9]{1,6}))?")
_DATE = re.compile(r"([0-9]{2})([0-9]{2})([0-9]{2})")
_HEX = re.compile(r"[0-9A-Fa-f]{2}")
_ADDRESS = re.compile(r"[A-Z]{2}([A-Z]{3})")
_FLOAT = re.compile(r"-?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)")


class _Malformed(ValueError):
    pass


def nmea_checksum(body: str | bytes) -> int:
    """XOR of the bytes of ``body`` (the text between ``$`` and ``*``)."""
    data = body.encode("ascii") if isinstance(body, str) else body
    cs = 0
    for b in data:
        cs ^= b
    return cs


@dataclass(frozen=True, slots=True)
class Rmc:
    """Recommended minimum data: a valid (status ``A``) position with time, date, speed and course."""

    talker: str
    utc_time: _dt.time | None
    latitude: float
    longitude: float
    speed_knots: float | None
    course_deg: float | None
    date: _dt.date | None


@dataclass(frozen=True, slots=True)
class Gga:
    """Fix data: a position with fix quality (1 GPS, 2 DGPS, 4 RTK fixed, ...), satellites, HDOP, altitude."""

    talker: str
    utc_time: _dt.time | None
    latitude: float
    longitude: float
    quality: int
    satellites: int | None
    hdop: float | None
    altitude_m: float | None


def _coord(value: str, hemi: str, max_deg: int, pos: str, neg: str) -> float:
    m = _COORD.fullmatch(value)
    if m is None:
        raise _Malformed(f"coordinate {value!r}")
    deg = int(m.group(1))
    minutes = float(m.group(2))
    if minutes >= 60.0:
        raise _Malformed(f"minutes {minutes} >= 60 in {value!r}")
    out = deg + minutes / 60.0
    if out > max_deg:
        raise _Malformed(f"{out}° beyond {max_deg}°")
    if hemi == pos:
        return out
    if hemi == neg:
        return -out
    raise _Malformed(f"hemisphere {hemi!r}, expected {pos} or {neg}")


def parse_latitude(value: str, hemi: str) -> float:
    """``DDMM.MMMM`` plus ``N``/``S`` to signed decimal degrees (raises ``ValueError``)."""
    return _coord(value, hemi, 90, "N", "S")


def parse_longitude(value: str, hemi: str) -> float:
    """``DDDMM.MMMM`` plus ``E``/``W`` to signed decimal degrees (raises ``ValueError``)."""
    return _coord(value, hemi, 180, "E", "W")


def _time(value: str) -> _dt.time | None:
    if not value:
        return None
    m = _TIME.fullmatch(value)
    if m is None:
        raise _Malformed(f"time {value!r}")
    frac = m.group(4) or ""
    micro = int((frac + "000000")[:6])
    try:
        return _dt.time(int(m.group(1)), int(m.group(2)), min(int(m.group(3)), 59), micro, tzinfo=_dt.UTC)
    except ValueError as exc:
        raise _Malformed(f"time {value!r}") from exc


def _date(value: str) -> _dt.date | None:
    if not value:
        return None
    m = _DATE.fullmatch(value)
    if m is None:
        raise _Malformed(f"date {value!r}")
    yy = int(m.group(3))
    try:  # two-digit years: GPS began in 1980, so 80-99 are 19xx and 00-79 are 20xx
        return _dt.date((1900 if yy >= 80 else 2000) + yy, int(m.group(2)), int(m.group(1)))
    except ValueError as exc:
        raise _Malformed(f"date {value!r}") from exc


def _opt_float(value: str) -> float | None:
    if not value:
        return None
    if _FLOAT.fullmatch(value) is None:
        raise _Malformed(f"number {value!r}")
    return float(value)


def _opt_int(value: str) -> int | None:
    if not value:
        return None
    if not (value.isascii() and value.isdigit()):
        raise _Malformed(f"integer {value!r}")
    return int(value)


class NmeaParser:
    """Turns NMEA lines into :class:`Rmc` / :class:`Gga`; everything else is counted and dropped."""

    def __init__(self) -> None:
        #: dropped lines per reason (see the module docstring)
        self.counts: dict[str, int] = dict.fromkeys(REASONS, 0)
        #: sentences that gave a position
        self.accepted = 0
        #: the reason the most recent line was dropped (``None`` if it was accepted)
        self.last_reason: str | None = None

    @property
    def dropped(self) -> int:
        """Lines dropped for a real fault (everything but ``unsupported``)."""
        return sum(v for k, v in self.counts.items() if k != "unsupported")

    def parse(self, line: str) -> Rmc | Gga | None:
        """A position from one line, or ``None`` (with the reason counted). Never raises."""
        try:
            result = self._parse(line)
        except _Malformed:
            result = "malformed"
        except Exception:  # pragma: no cover - defensive: a parser bug must not stop the drive loop
            result = "malformed"
        if isinstance(result, str):
            self.counts[result] += 1
            self.last_reason = result
            return None
        self.accepted += 1
        self.last_reason = None
        return result

    def _parse(self, line: str) -> Rmc | Gga | str:
        if not isinstance(line, str):
            return "malformed"
        line = line.strip()
        if not line.startswith("$"):
            return "no_start"
        star = line.rfind("*")
        if star < 0 or len(line) - star < 3:
            return "truncated"
        if len(line) - star > 3 or _HEX.fullmatch(line[star + 1 :]) is None:
            return "malformed"
        body = line[1:star]
        if not body.isascii():
            return "malformed"
        if nmea_checksum(body) != int(line[star + 1 :], 16):
            return "bad_checksum"
        fields = body.split(",")
        m = _ADDRESS.fullmatch(fields[0])
        if m is None:
            return "unsupported" if fields[0][:1] == "P" else "malformed"
        kind = m.group(1)
        talker = fields[0][:2]
        if kind == "RMC":
            return self._rmc(talker, fields)
        if kind == "GGA":
            return self._gga(talker, fields)
        return "unsupported"

    @staticmethod
    def _rmc(talker: str, f: list[str]) -> Rmc | str:
        if len(f) < 10:
            return "malformed"
        status = f[2]
        if status == "V" or (len(f) > 12 and f[12] == "N"):
            return "void"
        if status != "A":
            return "malformed"
        return Rmc(
            talker=talker,
            utc_time=_time(f[1]),
            latitude=parse_latitude(f[3], f[4]),
            longitude=parse_longitude(f[5], f[6]),
            speed_knots=_opt_float(f[7]),
            course_deg=_opt_float(f[8]),
            date=_date(f[9]),
        )

    @staticmethod
    def _gga(talker: str, f: list[str]) -> Gga | str:
        if len(f) < 10:
            return "malformed"
        quality = _opt_int(f[6])
        if quality is None:
            return "malformed"
        if quality == 0:
            return "no_fix"
        return Gga(
            talker=talker,
            utc_time=_time(f[1]),
            latitude=parse_latitude(f[2], f[3]),
            longitude=parse_longitude(f[4], f[5]),
            quality=quality,
            satellites=_opt_int(f[7]),
            hdop=_opt_float(f[8]),
            altitude_m=_opt_float(f[9]),
        )
