"""The ``asyncdonkey`` command: ``run`` a car file, ``replay`` a drive, ``donkey`` a Donkeycar car, ``--version``.

The car file convention: a Python file that defines ``build()`` returning a :class:`asyncdonkey.Vehicle`
(a Donkeycar ``Vehicle`` is accepted too and converted). If ``build`` takes a parameter, it receives the
arguments that follow ``--`` on the command line, so a car can have options of its own::

    asyncdonkey run examples/car.py --hz 20 --duration 30 -- --pilot examples/models/sim_pilot.tflite

An optional module-level ``DRIVE_LOOP_HZ`` (Donkeycar's config name) sets the default rate.

Mistakes in the car file (missing, a syntax error, no ``build``, a wrong return type, a ``DRIVE_LOOP_HZ`` that
is not a rate) and bad option values print one line (``asyncdonkey run: error: ...``: every command's error
lines name the command, :func:`error_prefix`) and exit with status 2, without a traceback: the user needs
the file and line, or the option and what it expects, not our stack. So does a missing extra, in any command
(:class:`~asyncdonkey.extras.MissingExtra`: the feature and the command that installs its extra). An
option ``run`` does not know (``--seconds 5`` meant for the car) is named, with where car options go (after
``--``) and ``run``'s own options. A part failing while driving prints its one-line error and exits with status 1;
``--verbose`` adds the traceback.
"""

from __future__ import annotations

import argparse
import importlib.util
import inspect
import logging
import os
import sys
import threading
import time
import traceback
from pathlib import Path
from types import ModuleType
from typing import Any, NoReturn

from .. import __version__
from ..core.buildscope import BuildScope, collecting
from ..errors import AsyncdonkeyError
from ..extras import MissingExtra, extra_for_module
from ..loop import PartError, Vehicle, run_blocking
from ..options import BadValue, positive_float
from ..safety.process import SafetyProcessError
from .drive_options import add_drive_options

__all__ = ["CarFileError", "car_rate_hz", "load_car", "main"]

EXIT_USAGE = 2


def error_prefix(command: str | None) -> str:
    """The start of every error line a command prints, as argparse starts its own: ``asyncdonkey run: error:``
    (the command named, so a line in a log says which command failed)."""
    return f"asyncdonkey {command}: error:" if command else "asyncdonkey: error:"


RUN_ERROR = error_prefix("run")


class CarFileError(AsyncdonkeyError):
    """The car file cannot provide a vehicle; the message is one line for the user."""


def load_car(path: str | Path, car_args: list[str] | None = None) -> tuple[Vehicle, ModuleType]:
    """Import the car file at ``path``, call its ``build()`` and return ``(vehicle, module)``."""
    p = Path(path)
    if not p.is_file():
        raise CarFileError(f"car file {str(p)!r} not found")
    spec = importlib.util.spec_from_file_location(f"asyncdonkey_car_{p.stem}", p)
    if spec is None or spec.loader is None:
        raise CarFileError(f"{p}: cannot be loaded as a Python module")
    module = importlib.util.module_from_spec(spec)
    # registered like an imported module, so dataclasses and pickling in the car file find it
    sys.modules[spec.name] = module
    sys.path.insert(0, str(p.resolve().parent))
    try:
        spec.loader.exec_module(module)
    except MissingExtra:
        sys.modules.pop(spec.name, None)
        raise  # its one line says what to install; main() prints it
    except SyntaxError as exc:
        sys.modules.pop(spec.name, None)
        raise CarFileError(f"{p}:{exc.lineno}: syntax error: {exc.msg}") from None
    except Exception as exc:
        sys.modules.pop(spec.name, None)
        _raise_if_missing_extra(exc, f"{p}")
        raise CarFileError(f"{p}: importing it raised {type(exc).__name__}: {exc}{_where(exc, p)}") from None
    finally:
        with_path = str(p.resolve().parent)
        if sys.path and sys.path[0] == with_path:
            sys.path.pop(0)
    build = getattr(module, "build", None)
    if build is None or not callable(build):
        raise CarFileError(f"{p}: defines no build() function (it must return an asyncdonkey.Vehicle)")
    try:
        takes_args = len(inspect.signature(build).parameters) > 0
    except (TypeError, ValueError):
        takes_args = False
    if car_args and not takes_args:
        raise CarFileError(f"{p}: build() takes no arguments, but car options were given: {' '.join(car_args)}")
    try:
        vehicle = build(list(car_args or [])) if takes_args else build()
    except (SystemExit, MissingExtra):
        raise
    except Exception as exc:
        _raise_if_missing_extra(exc, f"{p}: build()")
        raise CarFileError(f"{p}: build() raised {type(exc).__name__}: {exc}{_where(exc, p)}") from None
    if not isinstance(vehicle, Vehicle):
        converted = _from_donkeycar(vehicle)
        if converted is None:
            raise CarFileError(f"{p}: build() returned {type(vehicle).__name__}, expected an asyncdonkey.Vehicle")
        vehicle = converted
    return vehicle, module


def _raise_if_missing_extra(exc: BaseException, feature: str) -> None:
    """Raise :class:`MissingExtra` for an import of an extra's module that failed without :func:`require`
    (a car file's own ``import zenoh``, a part that imports its extra directly)."""
    if isinstance(exc, ModuleNotFoundError):
        extra = extra_for_module(exc.name)
        if extra is not None:
            raise MissingExtra(feature, extra, str(exc.name)) from exc


def _from_donkeycar(obj: Any) -> Vehicle | None:
    cls = type(obj)
    if cls.__name__ == "Vehicle" and cls.__module__.startswith("donkeycar"):
        return Vehicle.from_donkeycar(obj)
    return None


def _where(exc: BaseException, path: Path) -> str:
    for frame in reversed(traceback.extract_tb(exc.__traceback__)):
        if Path(frame.filename).resolve() == path.resolve():
            return f" (line {frame.lineno})"
    return ""


def car_rate_hz(module: ModuleType, path: str | Path, default: float = 20.0) -> float:
    """The car file's ``DRIVE_LOOP_HZ`` (``default`` without one); :class:`CarFileError` if it is not a rate."""
    value = getattr(module, "DRIVE_LOOP_HZ", default)
    try:
        return positive_float(value)
    except BadValue as exc:
        raise CarFileError(f"{path}: DRIVE_LOOP_HZ: {exc} (the drive loop rate in Hz)") from None


class _Parser(argparse.ArgumentParser):
    """An argparse parser whose errors are one line (``prog: error: message``) with exit status 2."""

    def error(self, message: str) -> NoReturn:
        self.exit(EXIT_USAGE, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="asyncdonkey", description="asyncio-native robot runtime")
    parser.add_argument("--version", action="version", version=f"asyncdonkey {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    run = sub.add_parser("run", help="drive a car file (a Python file whose build() returns a Vehicle)")
    run.add_argument("car", help="path to the car file (a .py file defining build()), e.g. examples/car.py")
    add_drive_options(run, default_rate="the file's DRIVE_LOOP_HZ, else 20")
    run.epilog = (
        "Arguments after a lone -- are passed to the car's build(): asyncdonkey run examples/car.py -- --seconds 5 "
        '(with make: make run ARGS="-- --seconds 5").'
    )
    parser.run_parser = run  # type: ignore[attr-defined]  # for the error naming run's own options
    try:
        from .replay import add_replay_parser
    except ImportError:
        pass
    else:
        add_replay_parser(sub)
    from .donkey import add_donkey_parser

    add_donkey_parser(sub)
    from .convert import add_convert_parser
    from .report import add_report_parser

    add_convert_parser(sub)
    add_report_parser(sub)
    from .quantize import add_quantize_parser

    add_quantize_parser(sub)
    from .zenoh import add_zenoh_parsers

    add_zenoh_parsers(sub)
    return parser


def _cmd_run(args: argparse.Namespace) -> int:
    car_args = list(getattr(args, "car_args", []))
    with collecting() as opened:  # what build() opens, closed again if the car refuses to start
        try:
            vehicle, module = load_car(args.car, car_args)
            rate = args.hz if args.hz is not None else car_rate_hz(module, args.car)
        except (CarFileError, MissingExtra) as exc:
            print(f"{RUN_ERROR} {exc}", file=sys.stderr)
            return _refused(opened, EXIT_USAGE)
        except SystemExit as exc:  # the car's own option parser: its usage error or --help, already printed
            return _refused(opened, _exit_status(exc))
        except KeyboardInterrupt:
            return _refused(opened, EXIT_INTERRUPTED)
    try:
        report = run_blocking(
            vehicle.run_with_signals(
                rate, args.max_loops, duration=args.duration, verbose=args.verbose, precise=args.precise
            ),
            use_uvloop=not args.no_uvloop,
        )
    except PartError as exc:
        if isinstance(exc.__cause__, MissingExtra):  # a part importing its extra when it starts
            print(f"{RUN_ERROR} {exc.part}: {exc.__cause__}", file=sys.stderr)
            return _leave(EXIT_USAGE)
        if args.verbose:
            traceback.print_exception(exc, file=sys.stderr)
        print(f"{RUN_ERROR} {exc}", file=sys.stderr)
        return _leave(1)
    except (AsyncdonkeyError, SafetyProcessError) as exc:  # the drive refused to start; run() shut the parts down
        if args.verbose:
            traceback.print_exception(exc, file=sys.stderr)
        print(f"{RUN_ERROR} {exc}", file=sys.stderr)
        return _leave(EXIT_USAGE)
    except Exception:  # a fault of ours: its traceback, and still no process left running
        traceback.print_exc(file=sys.stderr)
        return _leave(1)
    if report.shutdown_abandoned:
        print(
            f"{RUN_ERROR} shutdown of {', '.join(map(repr, report.shutdown_abandoned))} did not finish in time",
            file=sys.stderr,
        )
        return _leave(1)
    return _leave(0)


#: the exit status of a ``run`` interrupted by Ctrl-C while the car was being built (128 + SIGINT)
EXIT_INTERRUPTED = 130


def _exit_status(exc: SystemExit) -> int:
    """The status a ``SystemExit`` asks for, as the interpreter reads it (a message is printed, status 1)."""
    if exc.code is None:
        return 0
    if isinstance(exc.code, int):
        return exc.code
    print(exc.code, file=sys.stderr)
    return 1


def _refused(opened: BuildScope, status: int) -> int:
    """The car refused to start (its one line is printed): close what its build() opened (its vehicles' parts,
    Zenoh sessions), then leave with ``status`` even if a thread it started is still running."""
    opened.close()
    return _leave(status, if_stuck=status)


#: how long the interpreter may take to exit after a drive before the process is ended without it
EXIT_GRACE_S = 2.0

#: set by :func:`main` when it runs as the program (``argv`` from the command line): only then may the exit guard
#: end the process (a test or an application calling ``main([...])`` in its own process is never ended by it)
_guard_exit = False


def _leave(status: int, *, if_stuck: int | None = None) -> int:
    """Return ``status``, guarding the interpreter's exit: a part that left a thread busy (a hung executor
    call, a Zenoh session's callback threads, which the interpreter joins at exit) must not keep the process
    alive after the report or the error. A daemon timer ends the process ``EXIT_GRACE_S`` later, with
    ``if_stuck`` (default: ``status``, or 1 after a drive that ended well), if the normal exit has not happened
    by then. Armed only when ``main`` is the program."""
    if not _guard_exit:
        return status
    stuck_status = if_stuck if if_stuck is not None else (status or 1)

    def guard() -> None:
        time.sleep(EXIT_GRACE_S)
        main = threading.main_thread()
        busy = [t.name for t in threading.enumerate() if t.is_alive() and not t.daemon and t is not main]
        print(f"asyncdonkey: exiting without waiting for threads still running: {', '.join(busy)}", file=sys.stderr)
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except Exception:  # pragma: no cover - a closed stream: nothing more to say
                pass
        os._exit(stuck_status)

    threading.Thread(target=guard, name="asyncdonkey-exit-guard", daemon=True).start()
    return status


def main(argv: list[str] | None = None) -> int:
    global _guard_exit
    _guard_exit = argv is None
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    parser = build_parser()
    argv = list(sys.argv[1:] if argv is None else argv)
    car_args: list[str] = []
    if argv[:1] == ["run"] and "--" in argv:
        cut = argv.index("--")
        argv, car_args = argv[:cut], argv[cut + 1 :]
    args, unknown = parser.parse_known_args(argv)
    if unknown:
        if args.command == "run":
            print(_unknown_run_options(parser, args.car, unknown), file=sys.stderr)
            return EXIT_USAGE
        if args.command:  # named like argparse's own errors in that command: asyncdonkey replay: error: ...
            given, see = " ".join(unknown), f"see asyncdonkey {args.command} --help"
            print(f"{error_prefix(args.command)} unrecognized arguments: {given} ({see})", file=sys.stderr)
            return EXIT_USAGE
        parser.error(f"unrecognized arguments: {' '.join(unknown)}")
    args.car_args = car_args
    try:
        try:
            return _dispatch(parser, args)
        except ModuleNotFoundError as exc:
            _raise_if_missing_extra(exc, f"asyncdonkey {args.command}")
            raise
    except MissingExtra as exc:
        print(f"{error_prefix(args.command)} {exc}", file=sys.stderr)
        return EXIT_USAGE


def _unknown_run_options(parser: argparse.ArgumentParser, car: str, unknown: list[str]) -> str:
    """The error for options ``run`` does not know: most often the car's own, given before ``--``."""
    given = " ".join(unknown)
    lines = [
        f"asyncdonkey run: error: unrecognized arguments: {given}",
        f"  options of the car file go after a lone --: asyncdonkey run {car} -- {given}",
    ]
    if os.environ.get("MAKELEVEL"):  # started by make: `make run ARGS="..."`
        lines.append(f'  with make: make run ARGS="-- {given}"')
    run_parser = getattr(parser, "run_parser", None)
    if run_parser is not None:
        own = [
            " ".join(a.option_strings) + (f" {a.metavar or a.dest.upper()}" if a.nargs != 0 else "")
            for a in run_parser._actions
            if a.option_strings and a.dest != "help"
        ]
        lines.append(f"  asyncdonkey run's own options: {', '.join(own)} (see asyncdonkey run --help)")
    return "\n".join(lines)


def _dispatch(parser: argparse.ArgumentParser, args: argparse.Namespace) -> int:
    if args.command == "run":
        return _cmd_run(args)
    if args.command == "replay":
        from .replay import replay_main

        return int(replay_main(args))
    if args.command == "donkey":
        from .donkey import donkey_main

        return donkey_main(args)
    handler = getattr(args, "handler", None)
    if handler is not None:  # subcommands that name their own handler (convert, report)
        return int(handler(args))
    parser.print_help()
    return EXIT_USAGE


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
