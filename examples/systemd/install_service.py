#!/usr/bin/env python3
"""Install the car as a systemd service for the user who runs this, from this checkout.

Raspberry Pi Imager asks for a user name: there is no ``pi`` user to assume. So the unit is not shipped ready-made
but as a template (``asyncdonkey-car.service.in``) that this script fills in with the installing user, their home
(from the password database, wherever it is) and the checkout this script lives in, then installs as
``/etc/systemd/system/asyncdonkey-car.service``, enables it at boot and (re)starts it. Run it again after changing
settings: it writes the unit again and restarts the car with them.

Run it as the car's user (it calls sudo for the system steps), with the standard library only, so the system's
``python3`` does::

    python3 examples/systemd/install_service.py --print            # show the unit, install nothing
    python3 examples/systemd/install_service.py -- STEERING_LEFT_PWM=470 --model models/pilot.onnx

Arguments after ``--`` go to ``examples/car_pi.py`` after the unit's own (``--camera picamera2 --web --token-file
~/.asyncdonkey-web-token``, or with ``--js`` ``--camera picamera2 --js``: the gamepad drives, no web page); a later
``--camera opencv`` replaces the default one. Under ``sudo`` the car's user is
the one who called sudo (``SUDO_USER``); as root without it, the script refuses: the car must not run as root.
"""

from __future__ import annotations

import argparse
import os
import pwd
import re
import subprocess
import sys
import tempfile
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path, PurePosixPath

HERE = Path(__file__).resolve().parent
TEMPLATE = HERE / "asyncdonkey-car.service.in"
CHECKOUT = HERE.parent.parent
SERVICE = "asyncdonkey-car"
UNIT_PATH = PurePosixPath("/etc/systemd/system") / f"{SERVICE}.service"

#: An argument systemd's ExecStart= takes as it is: no quotes, spaces, specifiers (%) or variables ($) to escape.
_PLAIN_ARG = re.compile(r"[A-Za-z0-9_@+=:,./-]+")
#: Characters a path in the unit may not have: systemd would split, expand or unquote them.
_UNSAFE_IN_PATH = re.compile(r"[\s\"'\\%$;]")


class InstallError(Exception):
    """One line for the user: what is wrong and what to do."""


@dataclass(frozen=True)
class Target:
    """Whom the car runs as, and from where."""

    user: str
    home: PurePosixPath
    checkout: PurePosixPath


def car_user(requested: str | None, environ: Mapping[str, str], uid: int) -> str:
    """The user the car runs as: the one asked for, else the caller, or under sudo who called sudo; never root."""
    user = requested or (pwd.getpwuid(uid).pw_name if uid != 0 else environ.get("SUDO_USER", ""))
    if user in ("", "root"):
        raise InstallError(
            "install_service: the car must not run as root: run this as the car's user (the one the Imager "
            "made), who needs no root for it (it calls sudo for the system steps), or name one with --user"
        )
    return user


def home_of(user: str) -> PurePosixPath:
    """The user's home from the password database (not $HOME, which sudo may have changed)."""
    try:
        return PurePosixPath(pwd.getpwnam(user).pw_dir)
    except KeyError:
        raise InstallError(f"install_service: no user {user!r} in the password database") from None


def check_path(what: str, path: PurePosixPath) -> None:
    if not path.is_absolute() or _UNSAFE_IN_PATH.search(str(path)):
        raise InstallError(
            f"install_service: the {what} {str(path)!r} must be an absolute path without spaces, quotes, "
            "backslashes, '%', '$' or ';' (systemd would split or expand them): move it, or edit the unit by hand"
        )


def systemd_quote(arg: str) -> str:
    """One ExecStart= argument as systemd reads it back: quoted if needed, '%' and '$' escaped."""
    if "\n" in arg or "\r" in arg:
        raise InstallError(f"install_service: a car argument cannot hold a line break: {arg!r}")
    if _PLAIN_ARG.fullmatch(arg):
        return arg
    escaped = arg.replace("\\", "\\\\").replace('"', '\\"').replace("%", "%%").replace("$", "$$")
    return f'"{escaped}"'


def controller_args(home: PurePosixPath, gamepad: bool) -> list[str]:
    """car_pi's controller: the gamepad, or the phone's page with its token kept in the user's home."""
    return ["--js"] if gamepad else ["--web", "--token-file", str(home / ".asyncdonkey-web-token")]


def render(template: str, target: Target, car_args: Sequence[str], gamepad: bool = False) -> str:
    """The unit for this user and checkout, with the car's extra arguments after the unit's own."""
    check_path("home", target.home)
    check_path("checkout", target.checkout)
    if not re.fullmatch(r"[a-z_][a-z0-9_-]*\$?", target.user):
        raise InstallError(f"install_service: {target.user!r} is not a user name systemd accepts in User=")
    values = {
        "@USER@": target.user,
        "@CHECKOUT@": str(target.checkout),
        "@CONTROLLER@": " ".join(controller_args(target.home, gamepad)),
        "@CAR_ARGS@": " ".join(systemd_quote(arg) for arg in car_args),
    }
    text = template
    for placeholder, value in values.items():
        text = text.replace(placeholder, value)
    # no trailing blank where there were no extra arguments
    return "\n".join(line.rstrip() for line in text.splitlines()) + "\n"


def install_steps(unit_file: Path, as_root: bool, start: bool) -> list[list[str]]:
    """The system commands that put the unit in place, make systemd read it, enable it and (re)start it."""
    sudo = [] if as_root else ["sudo"]
    steps = [
        [*sudo, "install", "-m", "0644", "-o", "root", "-g", "root", str(unit_file), str(UNIT_PATH)],
        [*sudo, "systemctl", "daemon-reload"],
        [*sudo, "systemctl", "enable", SERVICE],
    ]
    if start:
        steps.append([*sudo, "systemctl", "restart", SERVICE])
    return steps


def install(unit: str, target: Target, as_root: bool, start: bool) -> None:
    python = Path(target.checkout) / ".venv" / "bin" / "python"
    if not python.exists():
        raise InstallError(
            f"install_service: {python} does not exist: make the venv first (docs/raspberry-pi.md, step 4)"
        )
    with tempfile.TemporaryDirectory() as tmp:
        unit_file = Path(tmp) / f"{SERVICE}.service"
        unit_file.write_text(unit)
        for step in install_steps(unit_file, as_root, start):
            print("+", " ".join(step), flush=True)
            done = subprocess.run(step, check=False)
            if done.returncode != 0:
                raise InstallError(f"install_service: {' '.join(step)!r} failed (exit {done.returncode})")


def parse_args(argv: Sequence[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="install_service.py",
        description="Install the car (examples/car_pi.py) as the systemd service asyncdonkey-car, run as you.",
        epilog="Arguments after -- go to car_pi.py: settings NAME=VALUE and options, e.g. "
        "-- STEERING_LEFT_PWM=470 --model models/pilot.onnx",
    )
    parser.add_argument("--print", action="store_true", help="print the unit and install nothing")
    parser.add_argument("--js", action="store_true", help="drive with the gamepad (car_pi --js), not the web page")
    parser.add_argument("--no-start", action="store_true", help="install and enable it, but do not (re)start it")
    parser.add_argument("--user", help="run the car as this user (default: you, or under sudo who called sudo)")
    parser.add_argument("--checkout", type=Path, default=CHECKOUT, help=f"the checkout (default: {CHECKOUT})")
    parser.add_argument("car_args", nargs="*", metavar="-- CAR_ARGS", help="settings and options for car_pi.py")
    return parser.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> int:
    args = parse_args(sys.argv[1:] if argv is None else argv)
    try:
        user = car_user(args.user, os.environ, os.geteuid())
        target = Target(user, home_of(user), PurePosixPath(args.checkout.resolve()))
        unit = render(TEMPLATE.read_text(), target, args.car_args, gamepad=args.js)
        if args.print:
            print(unit, end="")
            return 0
        install(unit, target, as_root=os.geteuid() == 0, start=not args.no_start)
    except InstallError as error:
        print(error, file=sys.stderr)
        return 1
    print(f"installed {UNIT_PATH} for {target.user}: journalctl -u {SERVICE} -f shows the drive URL and the car")
    return 0


if __name__ == "__main__":
    sys.exit(main())
