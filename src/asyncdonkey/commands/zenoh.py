"""The Zenoh subcommands of ``asyncdonkey``: ``zenoh-pair`` (secure configs for a car and its pilot, or for a fleet
and its pilot server), ``top`` (every car's status, live) and ``pilot-server`` (one model for a fleet)."""

from __future__ import annotations

import argparse
import asyncio
import signal
import sys
import time
from typing import Any

from ..extras import require

__all__ = ["add_zenoh_parsers"]


def add_zenoh_parsers(sub: Any) -> None:
    """Register ``zenoh-pair``, ``top`` and ``pilot-server`` on the ``asyncdonkey`` subparsers (each sets
    ``handler``)."""
    _add_pair(sub)
    _add_top(sub)
    _add_pilot_server(sub)


# -- zenoh-pair ---------------------------------------------------------------------------------------------
def _add_pair(sub: Any) -> None:
    pair = sub.add_parser(
        "zenoh-pair",
        help="write certificates and Zenoh configs so one pilot host (only) can command one car, or a fleet",
        description=(
            "One car: writes a private CA, a certificate for the car and one for the pilot host, and the two Zenoh "
            "configs: the car listens on mutual TLS only and accepts command keys only from the pilot's "
            "certificate; authenticated fleet views (--view) may read its telemetry. A fleet (--fleet --cars A B "
            "... --server NAME): one CA, a certificate and config per car and for the pilot server; the server "
            "listens, the cars connect to it, each car takes commands only from the server and no car can command "
            "or watch another. Existing files are never overwritten without --force. Keep OUT/ca/ca-key.pem off "
            "every machine."
        ),
    )
    pair.add_argument("out", help="directory to write into (ca/, and car/ + pilot/, or server/ + one per car)")
    pair.add_argument("--car", help="one car: its name (certificate CN; keys cars/<car>/...). Default: car1")
    pair.add_argument("--pilot", help="one car: the pilot host's name (its certificate CN). Default: pilot")
    pair.add_argument(
        "--car-host",
        action="append",
        dest="car_hosts",
        metavar="HOST",
        help="one car: name or address the pilot reaches the car by (repeatable; the first is dialled). "
        "Default: localhost",
    )
    pair.add_argument("--fleet", action="store_true", help="pair a fleet of cars with one pilot server")
    pair.add_argument("--cars", nargs="+", metavar="CAR", help="--fleet: the cars' names (required with --fleet)")
    pair.add_argument("--server", help="--fleet: the pilot server's name (its certificate CN; required with --fleet)")
    pair.add_argument(
        "--server-host",
        action="append",
        dest="server_hosts",
        metavar="HOST",
        help="--fleet: name or address the cars reach the server by (repeatable; the first is dialled). "
        "Default: localhost",
    )
    pair.add_argument(
        "--standby",
        metavar="NAME",
        help="--fleet: a standby pilot server for the same cars (its certificate CN): every car connects to both and"
        " takes commands from either; the standby answers only while --server is not alive (Zenoh liveliness)",
    )
    pair.add_argument(
        "--standby-host",
        action="append",
        dest="standby_hosts",
        metavar="HOST",
        help="--standby: name or address the cars and the server reach the standby by (repeatable; the first is"
        " dialled). Default: localhost",
    )
    pair.add_argument("--standby-port", type=int, help="--standby: the standby's TLS port (default: --port)")
    pair.add_argument("--port", type=int, default=7447, help="the listening side's TLS port (default 7447)")
    pair.add_argument(
        "--listen-host", default="0.0.0.0", help="address the car (or the server) listens on (default 0.0.0.0)"
    )
    pair.add_argument("--prefix", help="one car: key prefix of the car's channels (default cars/<car>)")
    pair.add_argument(
        "--command",
        action="append",
        dest="commands",
        metavar="CHANNEL",
        help="a channel the pilot may command (repeatable; default pilot/command, pilot/angle and pilot/throttle)",
    )
    pair.add_argument(
        "--view", action="append", default=[], metavar="NAME", help="also a read-only fleet view identity"
    )
    pair.add_argument("--car-dir", help="one car: where the car/ folder will live on the car (default: where written)")
    pair.add_argument("--pilot-dir", help="one car: where the pilot/ folder will live on the pilot host")
    pair.add_argument(
        "--force",
        action="store_true",
        help="overwrite existing files (a new CA: identities issued before stop working)",
    )
    pair.set_defaults(handler=_cmd_pair)


def _cmd_pair(args: argparse.Namespace) -> int:
    require("cryptography", "zenoh", "asyncdonkey zenoh-pair")
    from ..parts.zenoh.pairing import DEFAULT_COMMANDS, make_fleet, make_pair

    commands = args.commands or DEFAULT_COMMANDS
    try:
        if args.fleet:
            return _pair_fleet(args, commands, make_fleet)
        single_only = [
            o
            for o, v in (
                ("--cars", args.cars),
                ("--server", args.server),
                ("--server-host", args.server_hosts),
                ("--standby", args.standby),
            )
            if v
        ]
        if single_only:
            raise ValueError(f"{', '.join(single_only)} pair a fleet: add --fleet")
        defaults = []
        if args.car is None:
            defaults.append("car name 'car1'")
        if args.pilot is None:
            defaults.append("pilot name 'pilot'")
        if not args.car_hosts:
            defaults.append("car host 'localhost'")
        files = make_pair(
            args.out,
            car=args.car or "car1",
            pilot=args.pilot or "pilot",
            car_hosts=args.car_hosts or ["localhost"],
            port=args.port,
            listen_host=args.listen_host,
            prefix=args.prefix,
            commands=commands,
            views=args.view,
            car_dir=args.car_dir,
            pilot_dir=args.pilot_dir,
            force=args.force,
        )
    except (ValueError, OSError) as exc:
        print(f"asyncdonkey zenoh-pair: error: {exc}", file=sys.stderr)
        return 2
    if defaults:
        print(f"defaults used (name them with --car, --pilot, --car-host): {', '.join(defaults)}")
    print(f"car   {args.car or 'car1'}: copy {files.car_dir}/ to the car; its config: {files.car_config.name}")
    print(
        f"pilot {args.pilot or 'pilot'}: copy {files.pilot_dir}/ to the pilot host; its config:"
        f" {files.pilot_config.name}"
    )
    for view, cfg in files.view_configs.items():
        print(f"view  {view}: {cfg}")
    print(f"CA key (issue nothing else with it; keep it on neither machine): {files.ca_key}")
    print(_validity_line(files.valid))
    return 0


def _validity_line(valid: Any) -> str:
    """When the certificates are valid: a machine whose clock is outside that window can neither connect nor be
    connected to (a Raspberry Pi without a clock battery is behind until NTP answers)."""
    start, end = (t.strftime("%Y-%m-%d %H:%M UTC") for t in valid)
    return f"certificates valid from {start} to {end}: every machine's clock must be inside that window (NTP)"


def _pair_fleet(args: argparse.Namespace, commands: Any, make_fleet: Any) -> int:
    missing = [o for o, v in (("--cars CAR [CAR ...]", args.cars), ("--server NAME", args.server)) if not v]
    if missing:
        raise ValueError(f"--fleet needs {' and '.join(missing)}")
    one_car = [o for o, v in (("--car", args.car), ("--pilot", args.pilot), ("--car-host", args.car_hosts)) if v]
    if one_car:
        raise ValueError(f"{', '.join(one_car)} pair one car; a fleet names --cars and --server")
    if (args.standby_hosts or args.standby_port is not None) and not args.standby:
        raise ValueError("--standby-host and --standby-port describe a standby server: name it with --standby NAME")
    files = make_fleet(
        args.out,
        cars=args.cars,
        server=args.server,
        server_hosts=args.server_hosts or ["localhost"],
        standby=args.standby,
        standby_hosts=args.standby_hosts or ["localhost"],
        standby_port=args.standby_port,
        port=args.port,
        listen_host=args.listen_host,
        views=args.view,
        commands=commands,
        force=args.force,
    )
    if not args.server_hosts:
        print("defaults used (name it with --server-host): server host 'localhost'")
    print(f"server {args.server}: copy {files.server_dir}/ to the pilot server; its config: {files.server_config}")
    if files.standby_config is not None:
        print(
            f"standby {args.standby}: copy {files.standby_dir}/ to the standby server; its config:"
            f" {files.standby_config} (it answers while {args.server} is not alive)"
        )
    for car, cfg in files.car_configs.items():
        print(f"car    {car}: copy {files.car_dirs[car]}/ to the car; its config: {cfg}")
    for view, cfg in files.view_configs.items():
        print(f"view   {view}: {cfg}")
    print(f"CA key (issue nothing else with it; keep it on no machine of the fleet): {files.ca_key}")
    print(_validity_line(files.valid))
    return 0


# -- top ----------------------------------------------------------------------------------------------------
#: top's orders (fleet.SORT_KEYS; written here so that building the parser imports no part)
SORT_KEYS = ("name", "latency", "age")


def _add_top(sub: Any) -> None:
    top = sub.add_parser(
        "top",
        help="every car on the network, live, like htop (reads cars/*/status)",
        description=(
            "Shows one line per car from the status each car publishes on cars/<car>/status (FleetStatus): its "
            "state (live; STALE when an age it reports is past --stale-ms, so it is probably holding its failsafe; "
            "NO-CMD when no command has reached it yet: every pilot/ channel it reports holds no value; "
            "SILENT when no status came for three refresh periods), tick rate, sensing-to-actuation latency, tick "
            "lateness, drive mode, round trip and the ages of its channels. Connect with a view config of "
            "zenoh-pair (--config), or to an endpoint (--connect)."
        ),
    )
    top.add_argument("--config", help="Zenoh config file (e.g. a view config written by zenoh-pair)")
    top.add_argument(
        "--connect",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="an endpoint to connect to, e.g. tcp/192.168.1.20:7447 (repeatable)",
    )
    top.add_argument(
        "--listen",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="an endpoint to listen on, for cars that connect to the view (repeatable)",
    )
    top.add_argument(
        "--mode",
        choices=["peer", "client", "router"],
        help="the Zenoh session's mode (default: the config's, or peer)",
    )
    top.add_argument("--key", default="cars/*/status", help="status key expression (default cars/*/status)")
    top.add_argument(
        "--sort",
        choices=SORT_KEYS,
        default="name",
        help="order the cars by name (default), latency (slowest first) or age (oldest channel first)",
    )
    top.add_argument(
        "--stale-ms", type=float, default=250.0, help="mark a car STALE when an age it reports passes this (250)"
    )
    top.add_argument("--no-parts", action="store_true", help="one line per car: leave out the part times")
    top.add_argument("--every", type=float, default=1.0, help="refresh period in seconds (default 1)")
    top.add_argument("--once", type=float, metavar="SECONDS", help="listen this long, print one table and exit")
    top.set_defaults(handler=_cmd_top)


def _cmd_top(args: argparse.Namespace) -> int:
    require("zenoh", "zenoh", "asyncdonkey top")
    from ..parts.zenoh.fleet import top_main

    return top_main(args)


# -- pilot-server -------------------------------------------------------------------------------------------
def _add_pilot_server(sub: Any) -> None:
    ps = sub.add_parser(
        "pilot-server",
        help="one pilot model for a fleet: every car's frames in, batched inference, each car its command back",
        description=(
            "Subscribes to cars/<car>/cam/image_array of each car named, infers the frames that arrive within "
            "--batch-window-ms in one model call (one per frame when the model's batch is fixed at 1; the log says "
            "so), and answers each car on cars/<car>/pilot/command with its own frame's origin, as "
            "examples/remote_pilot.py does. Frames older than --max-age-ms are not inferred. A car whose server is "
            "slow or gone stops by its own stale-command failsafe. Secure it with the server config of "
            "`asyncdonkey zenoh-pair --fleet` (--config)."
        ),
    )
    ps.add_argument("model", metavar="MODEL", help="the pilot model (.onnx, or .tflite with the tflite extra)")
    ps.add_argument("--cars", nargs="+", required=True, metavar="CAR", help="the cars to serve (their names)")
    ps.add_argument("--config", help="Zenoh config file (the server.json5 of zenoh-pair --fleet)")
    ps.add_argument("--listen", action="append", default=[], metavar="ENDPOINT", help="e.g. tcp/127.0.0.1:7447")
    ps.add_argument("--connect", action="append", default=[], metavar="ENDPOINT", help="e.g. tcp/127.0.0.1:7447")
    ps.add_argument("--mode", choices=["peer", "client", "router"], help="the session's mode (default: the config's)")
    ps.add_argument(
        "--batch-window-ms", type=float, default=5.0, help="how long a batch waits for more cars' frames (default 5)"
    )
    ps.add_argument(
        "--max-age-ms",
        type=float,
        default=250.0,
        help="the cars' failsafe window: older frames are not inferred (default 250)",
    )
    ps.add_argument("--max-batch", type=int, default=32, help="the most frames in one model call (default 32)")
    ps.add_argument("--prefix", default="cars/{car}", help="a car's key prefix, {car} for its name (cars/{car})")
    ps.add_argument(
        "--gpu",
        action="store_true",
        help="ONNX on onnxruntime's CUDA provider (onnxruntime-gpu); without one: a warning, and the CPU",
    )
    ps.add_argument("--threads", type=int, help="the model runtime's compute threads (default: physical cores)")
    ps.add_argument(
        "--insecure",
        action="store_true",
        help="serve even on a session others can publish to (whoever sends a car's frames steers it): an isolated"
        " bench network only",
    )
    ps.add_argument(
        "--standby-of",
        metavar="PRIMARY",
        help="run as the standby of pilot server PRIMARY: answer the cars only while PRIMARY's Zenoh liveliness"
        " token is absent (default: the role the config of zenoh-pair --standby gives, or none: answer alone)",
    )
    ps.add_argument(
        "--standby",
        metavar="NAME",
        help="run as a primary whose standby is NAME: answer unless NAME answers (at start, after a 1 s watch)",
    )
    ps.add_argument("--name", help="this server's name in a pair (default: its certificate's common name)")
    ps.add_argument(
        "--stats-every", type=float, default=5.0, help="print a line of counters every S seconds (0: never)"
    )
    ps.add_argument("--seconds", type=float, default=0.0, help="stop after S seconds (0: until Ctrl-C)")
    ps.set_defaults(handler=_cmd_pilot_server)


def _cmd_pilot_server(args: argparse.Namespace) -> int:
    require("zenoh", "zenoh", "asyncdonkey pilot-server")
    from ..parts.pilot_base import PilotModelError
    from ..parts.zenoh.batch_infer import BatchPilot
    from ..parts.zenoh.link import ZenohConfigError, zenoh_config
    from ..parts.zenoh.pilot_server import PilotServer
    from ..parts.zenoh.standby import role_for

    for name, value in (("--batch-window-ms", args.batch_window_ms), ("--max-age-ms", args.max_age_ms)):
        if not value >= 0 or (name == "--max-age-ms" and value == 0):
            print(f"asyncdonkey pilot-server: error: {name} must be a positive number, got {value}", file=sys.stderr)
            return 2
    try:
        model = BatchPilot(args.model, max_batch=args.max_batch, gpu=args.gpu, threads=args.threads)
        config = zenoh_config(args.config, mode=args.mode, connect=args.connect, listen=args.listen)
        role = role_for(config, name=args.name, standby_of=args.standby_of, standby=args.standby)
        server = PilotServer(
            model,
            args.cars,
            config=config,
            window_s=args.batch_window_ms / 1e3,
            max_age_s=args.max_age_ms / 1e3,
            max_batch=args.max_batch,
            prefix=args.prefix,
            insecure=args.insecure,
            role=role,
        )
    except (PilotModelError, ZenohConfigError, ValueError, OSError) as exc:
        print(f"asyncdonkey pilot-server: error: {exc}", file=sys.stderr)
        return 2
    how = f"batches of up to {args.max_batch}" if model.batched else "one call per frame (the model's batch is 1)"
    print(
        f"pilot server: {model.path.name} on {model.provider}, {how}, window {args.batch_window_ms:g} ms, serving"
        f" {', '.join(args.cars)}" + (f"; {server.role.name}, {server.role.describe()}" if server.role else ""),
        flush=True,
    )
    try:
        asyncio.run(_serve(server, args.stats_every, args.seconds))
    finally:
        server.close()
        print(_stats_line(server, final=True), flush=True)
    return 0


async def _serve(server: Any, stats_every: float, seconds: float) -> None:
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, server.stop)
    if seconds > 0:
        loop.call_later(seconds, server.stop)

    async def stats() -> None:
        while True:
            await asyncio.sleep(stats_every)
            print(_stats_line(server), flush=True)

    task = asyncio.ensure_future(stats()) if stats_every > 0 else None
    try:
        await server.serve()
    finally:
        if task is not None:
            task.cancel()


def _stats_line(server: Any, final: bool = False) -> str:
    """The server's counters as one line, each figure named as what it counts (frames, batches, model calls:
    :class:`asyncdonkey.parts.zenoh.server_figures.ServerFigures`)."""
    return f"{time.strftime('%H:%M:%S')} {'final: ' if final else ''}{server.figures().line()}"
