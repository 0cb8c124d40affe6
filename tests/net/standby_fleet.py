"""A fleet on a primary pilot server and its standby, on loopback: what the standby tests and
``benchmarks/fleet_failover.py`` pair and start.

:func:`pair_standby_fleet` writes the certificates and configs (``make_fleet(..., standby=)``, primary ``gpu1``
and standby ``gpu2`` each on a free port of 127.0.0.1); :class:`StandbyFleet` starts a server on one of those
configs (``asyncdonkey pilot-server`` on the shipped ``sim_pilot.onnx``, with no periodic stats line) and one car
process per car (``fleet_car.py`` playing recorded frames), so the test and the benchmark start the same fleet
and differ only in what they do to it and what they read back.
"""

from __future__ import annotations

from pathlib import Path

from asyncdonkey.parts.zenoh.pairing import FleetFiles, make_fleet

from .fleet_car import SCRIPT, FleetProcess
from .zenoh_loopback import free_port

ROOT = Path(__file__).resolve().parents[2]
MODEL = ROOT / "examples" / "models" / "sim_pilot.onnx"


def pair_standby_fleet(folder: Path, cars: list[str]) -> FleetFiles:
    """The fleet's files under ``folder``: each car takes commands from ``gpu1`` (primary) or ``gpu2`` (standby)."""
    return make_fleet(
        folder, cars=cars, server="gpu1", standby="gpu2", server_hosts=["127.0.0.1"],
        standby_hosts=["127.0.0.1"], port=free_port(), standby_port=free_port(), listen_host="127.0.0.1",
    )  # fmt: skip


class StandbyFleet:
    """A paired fleet under ``folder`` and the processes that run it."""

    def __init__(self, folder: Path, cars: list[str]) -> None:
        self.folder = folder
        self.cars = cars
        self.files = pair_standby_fleet(folder, cars)

    def server(self, config: Path) -> FleetProcess:
        """A pilot server on ``config`` (``files.server_config`` for the primary, ``files.standby_config``)."""
        args = ["pilot-server", str(MODEL), "--cars", *self.cars, "--config", str(config), "--stats-every", "0"]
        return FleetProcess(["-m", "asyncdonkey.commands", *args], cwd=ROOT)

    def car_processes(self, frames: Path) -> list[FleetProcess]:
        """One car process per car, each playing ``frames`` on its own paired config."""
        cfg = str(self.folder / "{car}" / "car.json5")
        return [
            FleetProcess([str(SCRIPT), "--frames", str(frames), "--car", car, "--config", cfg], cwd=ROOT)
            for car in self.cars
        ]
