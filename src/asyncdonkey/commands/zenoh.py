"""The Zenoh subcommands of ``asyncdonkey``: ``zenoh-pair`` (secure configs for a car and its pilot) and ``top``."""

from __future__ import annotations

import argparse
import sys
from typing import Any

__all__ = ["add_zenoh_parsers"]


def add_zenoh_parsers(sub: Any) -> None:
    """Register ``zenoh-pair`` and ``top`` on the ``asyncdonkey`` subparsers (each sets ``handler``)."""
    pair = sub.add_parser(
        "zenoh-pair",
        help="write certificates and Zenoh configs so one pilot host (only) can command one car",
        description=(
            "Writes a private CA, a certificate for the car and one for the pilot host, and the two Zenoh configs: "
            "the car listens on mutual TLS only and accepts command keys only from the pilot's certificate; "
            "authenticated fleet views (--view) may read its telemetry. Keep OUT/ca/ca-key.pem off both machines."
        ),
    )
    pair.add_argument("out", help="directory to write into (car/, pilot/, ca/ and one per --view)")
    pair.add_argument("--car", default="car1", help="the car's name (certificate CN; keys cars/<car>/...)")
    pair.add_argument("--pilot", default="pilot", help="the pilot host's name (its certificate CN)")
    pair.add_argument(
        "--car-host",
        action="append",
        dest="car_hosts",
        metavar="HOST",
        help="name or address the pilot reaches the car by (repeatable; the first is dialled). Default: localhost",
    )
    pair.add_argument("--port", type=int, default=7447, help="the car's TLS port (default 7447)")
    pair.add_argument("--listen-host", default="0.0.0.0", help="address the car listens on (default 0.0.0.0)")
    pair.add_argument("--prefix", help="key prefix of the car's channels (default cars/<car>)")
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
    pair.add_argument("--car-dir", help="where the car/ folder will live on the car (default: where it is written)")
    pair.add_argument("--pilot-dir", help="where the pilot/ folder will live on the pilot host")
    pair.set_defaults(handler=_cmd_pair)

    top = sub.add_parser("top", help="every car on the network, live, like htop (reads cars/*/status)")
    top.add_argument("--config", help="Zenoh config file (e.g. a view config written by zenoh-pair)")
    top.add_argument("--connect", action="append", default=[], metavar="ENDPOINT", help="e.g. tcp/192.168.1.20:7447")
    top.add_argument("--listen", action="append", default=[], metavar="ENDPOINT")
    top.add_argument("--mode", choices=["peer", "client", "router"])
    top.add_argument("--key", default="cars/*/status", help="status key expression (default cars/*/status)")
    top.add_argument("--every", type=float, default=1.0, help="refresh period in seconds (default 1)")
    top.add_argument("--once", type=float, metavar="SECONDS", help="listen this long, print one table and exit")
    top.set_defaults(handler=_cmd_top)


def _cmd_pair(args: argparse.Namespace) -> int:
    try:
        from ..parts.zenoh.pairing import DEFAULT_COMMANDS, make_pair
    except ImportError as exc:  # pragma: no cover - the zenoh extra is missing
        print(
            f"asyncdonkey zenoh-pair: needs the zenoh extra (pip install 'asyncdonkey[zenoh]'): {exc}", file=sys.stderr
        )
        return 2
    try:
        files = make_pair(
            args.out,
            car=args.car,
            pilot=args.pilot,
            car_hosts=args.car_hosts or ["localhost"],
            port=args.port,
            listen_host=args.listen_host,
            prefix=args.prefix,
            commands=args.commands or DEFAULT_COMMANDS,
            views=args.view,
            car_dir=args.car_dir,
            pilot_dir=args.pilot_dir,
        )
    except (ValueError, OSError) as exc:
        print(f"asyncdonkey zenoh-pair: error: {exc}", file=sys.stderr)
        return 2
    print(f"car   {args.car}: copy {files.car_dir}/ to the car; its config: {files.car_config.name}")
    print(f"pilot {args.pilot}: copy {files.pilot_dir}/ to the pilot host; its config: {files.pilot_config.name}")
    for view, cfg in files.view_configs.items():
        print(f"view  {view}: {cfg}")
    print(f"CA key (issue nothing else with it; keep it on neither machine): {files.ca_key}")
    return 0


def _cmd_top(args: argparse.Namespace) -> int:
    from ..parts.zenoh.fleet import top_main

    return top_main(args)
