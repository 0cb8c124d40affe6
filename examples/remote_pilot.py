"""The off-board pilot: camera frames in over Zenoh, ``OnnxPilot`` on them, its command out as one sample.

Run the simulated car in one terminal (or on the car), this in another (or on a laptop)::

    asyncdonkey run examples/car.py -- --pilot remote --zenoh-listen tcp/127.0.0.1:7447
    asyncdonkey run examples/remote_pilot.py -- --zenoh-connect tcp/127.0.0.1:7447

Across a shared network use the mutual-TLS configs of ``asyncdonkey zenoh-pair`` instead of plain TCP
(``--zenoh-config car/car.json5`` on the car, ``--zenoh-config pilot/pilot.json5`` here; see
``docs/scale-out.md``).

========================= =============================================== =====================================
part                      inputs                                          outputs
========================= =============================================== =====================================
ZenohSubscriber (pushes)                                                  cam/image_array (origin: the car's
                                                                          capture time, carried across)
OnnxPilot (pipelined,     cam/image_array                                 pilot/angle, pilot/throttle
started by each frame)
ZenohPublisher (react,    pilot/*, pilot/*@age
group pilot/command)
========================= =============================================== =====================================

Each frame starts the pilot the moment it arrives (the subscriber pushes it into Memory, the pilot is
triggered by ``cam/image_array``), and the publisher sends each command the moment the pilot publishes it
(``react=True``), so no tick period is added on this side. The commands inherit the frame's origin, so the age
the car sees on ``pilot/throttle`` is the whole camera-to-command time: the car's capture, the link both ways
and the inference. The ticks (20 Hz) also re-send the newest command with its true (growing) age.

Angle and throttle travel together as one sample on ``cars/sim/pilot/command`` (``group=PILOT_COMMAND``): the
car applies both at once with that sample's origin, never a new angle with the previous throttle.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from asyncdonkey import Vehicle
from asyncdonkey.parts.pilot import OnnxPilot
from asyncdonkey.parts.zenoh import PILOT_COMMAND, ZenohLink, ZenohPublisher, ZenohSubscriber, zenoh_config

DRIVE_LOOP_HZ = 20
DEFAULT_MODEL = Path(__file__).resolve().parent / "models" / "sim_pilot.onnx"


def make_pilot(model: str | Path = DEFAULT_MODEL, *, zenoh: Any = None, prefix: str = "cars/sim") -> Vehicle:
    """The pilot vehicle: ``zenoh`` is a ``zenoh.Config`` or config file, ``prefix`` the car's key prefix."""
    v = Vehicle()
    link = ZenohLink(prefix, zenoh)
    v.add(ZenohSubscriber(link, ["cam/image_array"]), outputs=["cam/image_array"])
    v.add(
        OnnxPilot(model),
        inputs=["cam/image_array"],
        outputs=["pilot/angle", "pilot/throttle"],
        pipelined=True,
        trigger="cam/image_array",
    )
    commands = ZenohPublisher(link, ["pilot/angle", "pilot/throttle"], group=PILOT_COMMAND)
    v.add(commands, inputs=commands.inputs, react=True)
    return v


def build(argv: list[str]) -> Vehicle:
    ap = argparse.ArgumentParser(prog="asyncdonkey run examples/remote_pilot.py --", description="off-board pilot")
    ap.add_argument("--model", default=str(DEFAULT_MODEL), help="ONNX pilot (default: the shipped sim pilot)")
    ap.add_argument("--zenoh-config", metavar="FILE", help="Zenoh config file (e.g. pilot.json5 from zenoh-pair)")
    ap.add_argument("--zenoh-connect", action="append", default=[], metavar="ENDPOINT", help="the car's endpoint")
    ap.add_argument("--prefix", default="cars/sim", help="the car's key prefix (default cars/sim)")
    args = ap.parse_args(argv)
    extra = {"connect/exit_on_failure": False} if args.zenoh_connect else None  # wait for the car to come up
    cfg = zenoh_config(
        args.zenoh_config,
        mode="peer" if args.zenoh_connect else None,
        connect=args.zenoh_connect,
        multicast_scouting=False if args.zenoh_connect else None,
        extra=extra,
    )
    if args.zenoh_connect:
        cfg.insert_json5("listen/endpoints", "[]")  # reachable only through its connection to the car
    return make_pilot(args.model, zenoh=cfg, prefix=args.prefix)
