"""GPS position part: NMEA from a serial receiver to latitude/longitude and local metric x/y.

``async update()`` reads the receiver's lines as they arrive (:class:`~asyncdonkey.hw.serial_port.SerialPort`,
reconnecting after unplug) and parses them with :class:`~asyncdonkey.hw.nmea.NmeaParser`; corrupt, void and
cut sentences are counted (``gps.parser.counts``) and dropped, never raised into the drive loop. ``run()``
returns the newest ``(latitude, longitude, x, y, timestamp)`` without waiting.

**Local x/y.** ``x`` is metres east and ``y`` metres north of the first fix (or of ``origin``), from an
equirectangular projection about the mean latitude of the two points with the WGS84 ellipsoid's radii of
curvature::

    x = N(φm) · cos(φm) · Δλ          y = M(φm) · Δφ

(``M`` meridional, ``N`` prime-vertical radius, angles in radians). Its error grows with the square of the
distance from the origin: well under a millimetre at 1 km, so good to centimetres over any track, and it
needs no UTM zone (Donkeycar's path-follow template converts to UTM with the ``utm`` package; UTM
coordinates are absolute and jump at zone borders, local ones start at 0,0 where the car started).

Donkeycar's names: ``GPS_SERIAL`` and ``GPS_SERIAL_BAUDRATE`` configure the port; suggested channels are
``gps/latitude``, ``gps/longitude``, ``pos/x``, ``pos/y`` and ``gps/timestamp``.
"""

from __future__ import annotations

import math
from typing import Any

from ..hw.nmea import Gga, NmeaParser, Rmc
from ..hw.serial_port import Line, SerialPort
from ..latest import Latest

__all__ = ["Gps", "LocalProjection"]

#: WGS84 semi-major axis (m) and first eccentricity squared
WGS84_A = 6378137.0
WGS84_E2 = 6.69437999014e-3

Position = tuple[float | None, float | None, float | None, float | None, float | None]
_NO_FIX: Position = (None, None, None, None, None)


class LocalProjection:
    """East/north metres from a fixed origin (see the module docstring for the formula and its accuracy)."""

    __slots__ = ("lat0", "lon0")

    def __init__(self, lat0: float, lon0: float) -> None:
        if not (-90.0 < lat0 < 90.0 and -180.0 <= lon0 <= 180.0):
            raise ValueError(f"LocalProjection: origin must be a valid latitude/longitude, got {lat0!r}, {lon0!r}")
        self.lat0 = lat0
        self.lon0 = lon0

    def to_xy(self, lat: float, lon: float) -> tuple[float, float]:
        phi_m = math.radians((lat + self.lat0) / 2.0)
        s = math.sin(phi_m)
        w2 = 1.0 - WGS84_E2 * s * s
        n = WGS84_A / math.sqrt(w2)
        m = WGS84_A * (1.0 - WGS84_E2) / (w2 * math.sqrt(w2))
        dlon = lon - self.lon0
        if dlon > 180.0:  # across the antimeridian
            dlon -= 360.0
        elif dlon < -180.0:
            dlon += 360.0
        return n * math.cos(phi_m) * math.radians(dlon), m * math.radians(lat - self.lat0)


class Gps:
    """A native async part reading an NMEA GPS; ``run()`` → ``(latitude, longitude, x, y, timestamp)``.

    ``timestamp`` is when the sentence arrived, on the runtime clock (seconds); the receiver's own UTC time
    of the fix is in :attr:`fix`. Before the first fix ``run()`` returns five ``None``.

    Args:
        port: the receiver's serial device (``GPS_SERIAL``) or a ready :class:`SerialPort`.
        baudrate: ``GPS_SERIAL_BAUDRATE`` (Donkeycar's default 115200; many receivers ship at 9600).
        origin: ``(latitude, longitude)`` of x = y = 0; default: the first fix.
        use: which sentence types give positions (both by default: a receiver sends GGA and RMC each epoch).
    """

    def __init__(
        self,
        port: str | SerialPort = "/dev/ttyUSB0",
        baudrate: int = 115200,
        *,
        origin: tuple[float, float] | None = None,
        use: tuple[str, ...] = ("RMC", "GGA"),
    ) -> None:
        kinds = {"RMC": Rmc, "GGA": Gga}
        if not use or any(k not in kinds for k in use):
            raise ValueError(f"Gps: use must name sentence types among {sorted(kinds)}, got {use!r}")
        self.port = port if isinstance(port, SerialPort) else SerialPort(port, baudrate, name="gps")
        self.parser = NmeaParser()
        self._accept = tuple(kinds[k] for k in use)
        self.projection: LocalProjection | None = LocalProjection(*origin) if origin is not None else None
        #: the newest parsed sentence that gave a position
        self.fix: Rmc | Gga | None = None
        self.latest: Latest[Position] = Latest()
        self._position: Position = _NO_FIX

    @classmethod
    def from_config(cls, cfg: Any) -> Gps:
        return cls(getattr(cfg, "GPS_SERIAL", "/dev/ttyUSB0"), getattr(cfg, "GPS_SERIAL_BAUDRATE", 115200))

    async def update(self) -> None:
        await self.port.serve_lines(self._on_line)

    def run(self) -> Position:
        return self._position

    def output_origin(self) -> float | None:
        """When the sentence behind the position ``run()`` returned arrived (``None`` before a fix: now)."""
        return self._position[4]

    async def shutdown(self) -> None:
        await self.port.close()

    def reset_origin(self) -> None:
        """Make the next fix the new x = y = 0."""
        self.projection = None

    def _on_line(self, line: Line) -> None:
        fix = self.parser.parse(line.text)
        if fix is None or not isinstance(fix, self._accept):
            return
        lat, lon = fix.latitude, fix.longitude
        if self.projection is None:
            self.projection = LocalProjection(lat, lon)
        x, y = self.projection.to_xy(lat, lon)
        self.fix = fix
        position = (lat, lon, x, y, line.timestamp)
        self._position = position
        self.latest.publish(position, line.timestamp)
