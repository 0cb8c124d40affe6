"""Run an existing Donkeycar car, its own ``manage.py``, on asyncdonkey's loop: ``asyncdonkey donkey``.

A Donkeycar car is a directory made by ``donkey createcar``: ``manage.py`` (a template such as ``complete``),
``config.py`` and ``myconfig.py``. ``manage.py`` builds ``dk.vehicle.Vehicle()``, adds Donkeycar parts and
calls ``V.start(rate_hz=cfg.DRIVE_LOOP_HZ, max_loop_count=cfg.MAX_LOOPS)``. Nothing in it needs to change for
the car to drive on asyncdonkey: the command puts :class:`DonkeycarVehicle` where Donkeycar's ``Vehicle`` is
looked up (``donkeycar.vehicle.Vehicle`` and ``donkeycar.Vehicle``; asyncdonkey's :class:`~asyncdonkey.Memory`
likewise) and then runs the file as ``__main__`` with the car's own arguments::

    cd ~/mycar
    asyncdonkey donkey manage.py drive --js

Why substitution rather than conversion. ``Vehicle.from_donkeycar`` converts a built Donkeycar vehicle, but a
``manage.py`` never hands its vehicle back: it builds it and calls ``start()`` inside ``drive()``. Replacing the
class before the file runs is the one place where an unchanged car can be reached, and every part it adds then
goes through asyncdonkey's ``add()`` checks.

The same substitution, with the plain :class:`~asyncdonkey.Vehicle`, runs Donkeycar's own test suite against
asyncdonkey (``tests/donkeycar_suite``): :func:`donkeycar_replaced`.

Two more things the command does for a car moved from Donkeycar:

* ``.tflite`` pilots (``--type tflite_linear`` ...) get Donkeycar's ``TfLite`` interpreter made to take quantized
  models and to find LiteRT (:mod:`.donkey_tflite`), so they drive without TensorFlow.
* A module the car imports that is missing ends the command with one line saying which setting needs it and
  what to do (:func:`missing_module_hint`): the default template's ``CAMERA_TYPE = "PICAM"`` without
  ``picamera2`` is the first thing a car copied to a bench meets. Donkeycar prints a traceback.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import logging
import os
import runpy
import sys
import traceback
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..errors import PartError
from ..extras import MissingExtra, install_command
from ..loop import DriveReport, Vehicle
from ..memory import Memory
from .donkey_errors import TENSORFLOW_HINT as _TENSORFLOW_HINT
from .donkey_errors import car_error, check_start_values
from .donkey_tflite import tflite_pilots_replaced
from .drive_options import add_drive_options

__all__ = [
    "DonkeycarVehicle",
    "DriveOptions",
    "add_donkey_parser",
    "donkey_main",
    "donkeycar_replaced",
    "missing_module_hint",
    "run_manage_py",
]

logger = logging.getLogger(__name__)

EXIT_USAGE = 2
#: the exit status of a car interrupted by Ctrl-C before it drove (128 + SIGINT), as ``asyncdonkey run``'s
EXIT_INTERRUPTED = 130
#: every error line the command prints starts so (as argparse's usage errors do)
ERROR = "asyncdonkey donkey: error:"

#: where Donkeycar code looks its Vehicle and Memory up: the modules, and the package's re-exports
#: (``dk.vehicle.Vehicle()`` in the templates, ``dk.Vehicle()`` in its tests)
_VEHICLE_NAMES = (("donkeycar.vehicle", "Vehicle"), ("donkeycar", "Vehicle"))
_MEMORY_NAMES = (("donkeycar.memory", "Memory"), ("donkeycar", "Memory"))


@contextlib.contextmanager
def donkeycar_replaced(vehicle_class: type[Vehicle] = Vehicle, memory_class: type[Memory] = Memory) -> Iterator[None]:
    """Within the block, Donkeycar's ``Vehicle`` and ``Memory`` are asyncdonkey's (or the classes given).

    Code that looks the names up when it runs (``dk.vehicle.Vehicle()``) and modules imported inside the block
    (``from donkeycar.vehicle import Vehicle``) get the replacements; the originals are put back on exit.
    Importing ``donkeycar`` prints its banner, as it does for any Donkeycar program.
    """
    saved: list[tuple[Any, str, Any]] = []
    try:
        for names, cls in ((_VEHICLE_NAMES, vehicle_class), (_MEMORY_NAMES, memory_class)):
            for module_name, attr in names:
                module = importlib.import_module(module_name)
                saved.append((module, attr, getattr(module, attr)))
                setattr(module, attr, cls)
        yield
    finally:
        for module, attr, original in reversed(saved):
            setattr(module, attr, original)


@dataclass
class DriveOptions:
    """What the command line overrides in the car's own ``V.start(...)`` call (``None``: the car's value)."""

    rate_hz: float | None = None
    max_loop_count: int | None = None
    duration: float | None = None
    verbose: bool = False
    use_uvloop: bool = True
    precise: bool = False
    #: the report of every drive the car ran, in order (a ``manage.py`` normally runs one)
    reports: list[DriveReport] = field(default_factory=list)


class DonkeycarVehicle(Vehicle):
    """asyncdonkey's :class:`~asyncdonkey.Vehicle` with the rest of Donkeycar's ``Vehicle`` API.

    ``start()`` drives on asyncdonkey's loop with its signal handling (:meth:`Vehicle.start`), applying the
    command line's :class:`DriveOptions`; it returns ``(loop_count, seconds)`` as Donkeycar's does. A part that
    fails raises :class:`~asyncdonkey.PartError` after the car has been shut down (Donkeycar prints the
    traceback and returns ``None``, so ``manage.py`` carried on as if the drive had ended normally).
    """

    #: set by :func:`run_manage_py` on the class it installs; ``None``: the car's own arguments, nothing recorded
    options: DriveOptions | None = None

    def __init__(self, mem: Memory | None = None, **kwargs: Any) -> None:
        super().__init__(mem, **kwargs)
        #: Donkeycar keeps the threads of threaded parts here; asyncdonkey starts them per drive
        self.threads: list[Any] = []

    def add(self, part: Any, inputs: Any = (), outputs: Any = (), *args: Any, **kwargs: Any) -> None:
        if _serves_on_tornado(part):
            kwargs.setdefault("name", type(part).__name__)
            _announce_web_part(part)
            part = _StoppableServer(part)
        super().add(part, inputs, outputs, *args, **kwargs)

    def remove(self, part: Any) -> None:
        """Remove a part, given the part object (or the entry ``parts`` holds for it)."""
        for i, entry in enumerate(self.parts):
            if entry is part or entry.part is part or getattr(entry.part, "wrapped", None) is part:
                del self.parts[i]
                return
        raise ValueError(f"Vehicle.remove: {type(part).__name__} is not a part of this vehicle")

    def start(  # type: ignore[override]
        self, rate_hz: float = 10, max_loop_count: int | None = None, verbose: bool = False, **kwargs: Any
    ) -> tuple[int, float]:
        o = self.options if self.options is not None else DriveOptions()
        rate = o.rate_hz if o.rate_hz is not None else rate_hz
        loops = o.max_loop_count if o.max_loop_count is not None else max_loop_count
        duration = o.duration if o.duration is not None else kwargs.pop("duration", None)
        check_start_values({"rate_hz": rate, "max_loop_count": loops}, sys._getframe(1))
        kwargs.setdefault("use_uvloop", o.use_uvloop)
        if o.precise:
            kwargs["precise"] = True
        before = self.last_report
        try:
            return super().start(rate, loops, verbose or o.verbose, duration=duration, **kwargs)
        finally:
            if self.last_report is not None and self.last_report is not before:  # a drive ran (maybe to an error)
                o.reports.append(self.last_report)


def _serves_on_tornado(part: Any) -> bool:
    """A Donkeycar web part (``LocalWebController``): a tornado application whose ``update()`` serves forever."""
    return any(c.__module__.startswith("tornado.") for c in type(part).__mro__) and callable(
        getattr(part, "update", None)
    )


def _announce_web_part(part: Any) -> None:
    """Print the addresses a phone can open for a Donkeycar web part: Donkeycar logs only
    ``<hostname>.local:<port>``, which Debian and Pi OS do not resolve without mDNS (see
    :mod:`asyncdonkey.parts.web.addresses`). Donkeycar's server listens on every IPv4 interface."""
    port = getattr(part, "port", None)
    if not isinstance(port, int):
        return
    from ..parts.web.addresses import drive_urls, loopback_url  # here: the web package loads aiohttp

    page = "/drive" if type(part).__name__ == "LocalWebController" else "/"
    urls = [*drive_urls("http", port, page, versions=(4,)), loopback_url("http", port, page, versions=(4,))]
    lines = [f"{type(part).__name__} (Donkeycar's), from a phone on the car's network:"]
    lines += [f"  {u.url}" + (f"  ({u.note})" if u.note else "") for u in urls]
    print("\n".join(lines), file=sys.stderr, flush=True)


class _StoppableServer:
    """A Donkeycar tornado part whose ``shutdown()`` also stops the server its ``update()`` thread runs.

    Donkeycar's ``LocalWebController.shutdown()`` does nothing and its ``update()`` never returns: Donkeycar
    leaves the thread to die with the process. asyncdonkey joins ``update()`` threads at shutdown, so without
    this the drive's end would wait out the part's shutdown timeout and report the thread abandoned. The
    part's own object is untouched; every other attribute is read from it.
    """

    def __init__(self, wrapped: Any) -> None:
        self.wrapped = wrapped

    def update(self) -> None:
        self.wrapped.update()

    def run(self, *args: Any) -> Any:
        return self.wrapped.run(*args)

    def run_threaded(self, *args: Any) -> Any:
        return self.wrapped.run_threaded(*args)

    def shutdown(self) -> None:
        loop = getattr(self.wrapped, "loop", None)  # LocalWebController keeps the IOLoop its thread runs
        if loop is not None:
            loop.add_callback(loop.stop)  # thread-safe: the loop stops, update() returns
        shutdown = getattr(self.wrapped, "shutdown", None)
        if callable(shutdown):
            shutdown()

    def __getattr__(self, name: str) -> Any:
        return getattr(self.wrapped, name)


def run_manage_py(path: str | Path, car_args: list[str], options: DriveOptions | None = None) -> DriveOptions:
    """Run the Donkeycar car file ``path`` as ``python manage.py <car_args>`` would, on asyncdonkey's loop.

    The car runs in its own directory (Donkeycar reads ``config.py`` and ``myconfig.py`` from the working
    directory), with ``sys.argv`` set to the file and its arguments. Returns the options with the reports of
    the drives it ran. Exceptions from the car propagate, as they would from ``python manage.py``.
    """
    options = options if options is not None else DriveOptions()
    car = Path(path).resolve()
    vehicle_class = type("Vehicle", (DonkeycarVehicle,), {"options": options, "__module__": __name__})
    saved_argv, saved_path, saved_cwd = list(sys.argv), list(sys.path), os.getcwd()
    sys.argv = [str(car), *car_args]
    sys.path.insert(0, str(car.parent))
    os.chdir(car.parent)
    try:
        with donkeycar_replaced(vehicle_class, Memory), tflite_pilots_replaced():
            runpy.run_path(str(car), run_name="__main__")
    finally:
        os.chdir(saved_cwd)
        sys.argv[:] = saved_argv
        sys.path[:] = saved_path
    return options


# -- the command ---------------------------------------------------------------------------------------------
def add_donkey_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Add the ``donkey`` subcommand to the ``asyncdonkey`` parser's subparsers."""
    p = subparsers.add_parser(
        "donkey",
        help="run an existing Donkeycar car (its manage.py) on asyncdonkey's loop, unchanged",
        description="Run a Donkeycar car's own manage.py with asyncdonkey's Vehicle in place of Donkeycar's. "
        "Everything after the car file is the car's own arguments, e.g. `asyncdonkey donkey manage.py drive "
        "--js`. The car runs in its own directory, as `python manage.py` does when run from there.",
    )
    add_drive_options(p, default_rate="the car's DRIVE_LOOP_HZ, as manage.py passes it to V.start")
    p.add_argument("car", help="the car's manage.py (made by `donkey createcar`)")
    p.add_argument(
        "manage_args", nargs=argparse.REMAINDER, metavar="...", help="the car's own arguments, e.g. drive --js"
    )
    return p


def donkey_main(args: argparse.Namespace) -> int:
    """Run the ``donkey`` subcommand; returns the exit status.

    Every error is one line, ``asyncdonkey donkey: error: <file>: <what is wrong>``: the car's mistakes (a file,
    a setting, a model, a missing module) with status 2 before it drove, a part failing while driving with
    status 1, as ``asyncdonkey run`` does. ``--verbose`` adds the traceback.
    """
    car = Path(args.car)
    if not car.is_file():
        print(f"{ERROR} car file {str(car)!r} not found", file=sys.stderr)
        return EXIT_USAGE
    try:
        importlib.import_module("donkeycar")
    except ImportError as exc:
        print(
            f"{ERROR} {car} is a Donkeycar car, but Donkeycar cannot be imported ({exc});"
            " install it into this environment (see docs/donkeycar.md)",
            file=sys.stderr,
        )
        return EXIT_USAGE
    options = DriveOptions(
        rate_hz=args.hz,
        max_loop_count=args.max_loops,
        duration=args.duration,
        verbose=args.verbose,
        use_uvloop=not args.no_uvloop,
        precise=args.precise,
    )
    try:
        run_manage_py(car, list(args.manage_args), options)
    except PartError as exc:
        _show_traceback(exc, args.verbose)
        print(f"{ERROR} {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return EXIT_INTERRUPTED
    except Exception as exc:  # the car's own code, its files, its model: one line, never a traceback
        _show_traceback(exc, args.verbose)
        hint = missing_module_hint(exc)
        print(f"{ERROR} {car.name}: {hint}" if hint else f"{ERROR} {car_error(exc, car)}", file=sys.stderr)
        return EXIT_USAGE if not options.reports else 1
    if not options.reports:
        logger.info("asyncdonkey: %s ran without driving (it never called Vehicle.start)", car.name)
    return 0


def _show_traceback(exc: BaseException, verbose: bool) -> None:
    """The traceback behind a one-line error: printed with ``--verbose``, logged at debug level always."""
    if verbose:
        traceback.print_exception(exc, file=sys.stderr)
    else:
        logger.debug("the traceback of the error", exc_info=exc)


# -- what a missing module means -----------------------------------------------------------------------------
_CAMERA_HINT = (
    'the camera CAMERA_TYPE = "{camera}" needs the {module} module, which this Python cannot import: '
    'for a bench run without the camera set CAMERA_TYPE = "MOCK" in myconfig.py; on the Raspberry Pi, '
    "sudo apt install python3-picamera2 and use a venv made with --system-site-packages "
    "(python3 -m venv --system-site-packages ~/env)"
)
_PCA9685_HINT = (
    'the drivetrain DRIVE_TRAIN_TYPE = "{drivetrain}" needs the {module} module, which is not installed: '
    'for a bench run set DRIVE_TRAIN_TYPE = "MOCK" in myconfig.py; on the car, pip install Adafruit_PCA9685'
)
#: a missing module the car's own settings decide on -> the line that says so
_SETTING_HINTS = {
    "picamera2": _CAMERA_HINT,
    "libcamera": _CAMERA_HINT,
    "Adafruit_PCA9685": _PCA9685_HINT,
    "tensorflow": _TENSORFLOW_HINT,
    "keras": _TENSORFLOW_HINT,
}
#: modules Donkeycar's command and templates import, provided by the donkeycar-cli extra
_EXTRA_MODULES = frozenset(
    {"progress", "docopt", "tornado", "requests", "pyfiglet", "PIL", "albumentations", "simple_pid", "prettytable"}
)


def missing_module_hint(exc: BaseException) -> str | None:
    """One line for an import that failed in a Donkeycar car: the setting that needs the module and the ways
    out, the extra to install, or where the car imports it. ``None`` when ``exc`` is not a failed import.

    A compiled module built for numpy 1 (on the Pi, apt's ``simplejpeg``, which picamera2 imports, in a venv
    with numpy 2) fails with numpy's "size changed" ``ValueError`` or an ``ImportError``; a PyPI wheel built for
    numpy 2 installed into the venv replaces it.

    The car's settings are read from the failing code's own ``cfg`` (the templates pass it down), so the line
    names the value the car was configured with.
    """
    if isinstance(exc, MissingExtra):
        return str(exc)
    text = str(exc).splitlines()[0] if str(exc) else ""
    if "numpy" in text and ("size changed" in text or "multiarray" in text or "NumPy 1.x" in text):
        return (
            f"a compiled module the car imports was built for numpy 1 ({text}); on the Raspberry Pi it is apt's "
            "simplejpeg, which picamera2 imports: pip install --force-reinstall --no-deps simplejpeg "
            "(a wheel built for numpy 2)"
        )
    if not isinstance(exc, ImportError):
        return None
    module = (exc.name or "").split(".")[0]
    if not isinstance(exc, ModuleNotFoundError) or not module:
        return None
    cfg = _car_config(exc)
    template = _SETTING_HINTS.get(module)
    if template is not None:
        return template.format(
            module=module,
            camera=getattr(cfg, "CAMERA_TYPE", "PICAM"),
            drivetrain=getattr(cfg, "DRIVE_TRAIN_TYPE", "PWM_STEERING_THROTTLE"),
        )
    if module in _EXTRA_MODULES:
        return f"Donkeycar's code needs {module}, which is not installed: {install_command('donkeycar-cli')}"
    where = _importer(exc)
    return f"{where} imports {module}, which is not installed in this environment ({sys.executable})"


def _car_config(exc: BaseException) -> Any:
    """The ``cfg`` the failing code had (the innermost frame that has one), or ``None``."""
    found = None
    for frame, _ in traceback.walk_tb(exc.__traceback__):
        cfg = frame.f_locals.get("cfg")
        if cfg is not None and hasattr(cfg, "CAMERA_TYPE"):
            found = cfg
    return found


def _importer(exc: BaseException) -> str:
    """``file:line`` of the innermost frame outside the import machinery: the import statement that failed."""
    where = "the car"
    for frame, line in traceback.walk_tb(exc.__traceback__):
        name = frame.f_code.co_filename
        if not name.startswith("<frozen"):
            where = f"{name}:{line}"
    return where
