"""RPLidar A1 part: the newest complete 360° scan, never making a tick wait.

``async update()`` runs :class:`~asyncdonkey.hw.rplidar.RPLidarDriver` (connect, STOP / GET_INFO /
GET_HEALTH / SCAN, decode nodes as bytes arrive, reconnect after unplug). Each complete revolution is
converted once, when it completes, into the output the part was configured for; ``run()`` returns that
cached value, so the tick costs an attribute read.

Outputs (chosen at construction, ``output=``):

* ``"dist_array"`` (default, Donkeycar's ``RPLidar`` channel ``lidar/dist_array``): distances in mm of the
  valid points (distance > 0, quality > 0) whose angle lies strictly between ``lower_limit`` and
  ``upper_limit``, ordered by angle; an empty array before the first scan. Donkeycar's
  ``RPLidar.run_threaded`` means to return this but returns ``np.argsort`` of the distances (indices, not
  distances); that bug is not copied. Like Donkeycar's code, the limits select the angles that are *kept*
  (its config comment calls them the angles to ignore).
* ``"arrays"``: three outputs ``(angles_deg, distances_mm, qualities)`` of the whole revolution as numpy
  arrays, e.g. ``outputs=["lidar/angles", "lidar/distances", "lidar/qualities"]``; nothing is written before
  the first scan.
* ``"scan"``: the :class:`~asyncdonkey.hw.rplidar.Scan` itself (arrays plus timestamp and index).

Angles are the lidar's own: degrees growing clockwise seen from above, 0 at the lidar's front mark.

Only real revolutions are published: the driver drops line noise (revolutions of a few nodes) and revolutions
that never end (lost start flags) and counts them; :meth:`RPLidar.stats` returns every counter.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from ..hw.rplidar import RPLidarDriver, Scan

__all__ = ["RPLidar"]

_EMPTY = np.zeros(0, dtype=np.float32)


class RPLidar:
    """Drop-in for ``donkeycar.parts.lidar.RPLidar(lower_limit, upper_limit)``, event-driven and async.

    Args:
        lower_limit, upper_limit: ``LIDAR_LOWER_LIMIT`` / ``LIDAR_UPPER_LIMIT`` (degrees) for ``dist_array``.
        port: the lidar's serial device (Donkeycar scans ``/dev/ttyUSB*``; name yours, preferably its
            ``/dev/serial/by-id`` link).
        output: ``"dist_array"``, ``"arrays"`` or ``"scan"`` (see the module docstring).
        driver: a ready :class:`RPLidarDriver` instead of ``port``/``baudrate``.
    """

    def __init__(
        self,
        lower_limit: float = 0,
        upper_limit: float = 360,
        debug: bool = False,
        *,
        port: str = "/dev/ttyUSB0",
        baudrate: int = 115200,
        output: str = "dist_array",
        driver: RPLidarDriver | None = None,
    ) -> None:
        if not (0 <= lower_limit <= 360 and 0 <= upper_limit <= 360 and lower_limit < upper_limit):
            raise ValueError(
                f"RPLidar: need 0 <= lower_limit < upper_limit <= 360 degrees, got {lower_limit!r}, {upper_limit!r}"
            )
        convert: dict[str, Callable[[Scan], Any]] = {
            "dist_array": self._dist_array,
            "arrays": _arrays,
            "scan": _identity,
        }
        if output not in convert:
            raise ValueError(f"RPLidar: output must be one of {sorted(convert)}, got {output!r}")
        self.lower_limit = float(lower_limit)
        self.upper_limit = float(upper_limit)
        self.debug = debug
        self.output = output
        self._convert = convert[output]
        self._value: Any = _EMPTY if output == "dist_array" else None
        self._scan_time: float | None = None
        self._origin: float | None = None
        self.driver = driver if driver is not None else RPLidarDriver(port, baudrate)
        self.driver.on_scan = self._on_scan
        #: the newest complete scan (``None`` before the first)
        self.scan: Scan | None = None

    @classmethod
    def from_config(cls, cfg: Any, port: str = "/dev/ttyUSB0") -> RPLidar:
        return cls(getattr(cfg, "LIDAR_LOWER_LIMIT", 0), getattr(cfg, "LIDAR_UPPER_LIMIT", 360), port=port)

    def stats(self) -> dict[str, Any]:
        """The driver's counters (:meth:`~asyncdonkey.hw.rplidar.RPLidarDriver.stats`): scans, noise, restarts."""
        return self.driver.stats()

    async def update(self) -> None:
        await self.driver.run()

    def run(self) -> Any:
        self._origin = self._scan_time
        return self._value

    def run_threaded(self) -> Any:
        self._origin = self._scan_time
        return self._value

    def output_origin(self) -> float | None:
        """When the revolution behind the value ``run()`` returned completed (``None`` before the first)."""
        return self._origin

    async def shutdown(self) -> None:
        await self.driver.close()

    def _on_scan(self, scan: Scan) -> None:
        self.scan = scan
        self._value = self._convert(scan)
        self._scan_time = scan.timestamp

    def _dist_array(self, scan: Scan) -> np.ndarray:
        a = scan.angles
        keep = (scan.distances > 0) & (scan.qualities > 0) & (a > self.lower_limit) & (a < self.upper_limit)
        angles = a[keep]
        order = np.argsort(angles, kind="stable")
        return scan.distances[keep][order]


def _arrays(scan: Scan) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return scan.angles, scan.distances, scan.qualities


def _identity(scan: Scan) -> Scan:
    return scan
