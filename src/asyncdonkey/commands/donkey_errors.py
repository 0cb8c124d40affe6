"""What went wrong in a Donkeycar car, in one line: ``asyncdonkey donkey``'s errors.

A Donkeycar car is run from its own files (``manage.py``, ``config.py``, ``myconfig.py``) through
``runpy.run_path``, so every mistake in them used to reach the user as a 20-40 line traceback through runpy,
Donkeycar's config loader and its pilot classes, with the one useful line at the bottom. ``asyncdonkey run`` prints
one line naming the file and what is wrong; this module gives ``asyncdonkey donkey`` the same, for the mistakes a
user makes when moving a car:

* a syntax error in ``manage.py``, ``config.py`` or ``myconfig.py``: ``myconfig.py:825: syntax error: ...``;
* a model that is missing or is not a model (``--model models/pilot.tflite`` naming a text file):
  ``models/pilot.tflite: cannot be loaded as a tflite_linear model: The model is not a valid Flatbuffer buffer``;
* a setting of the wrong type given to ``V.start`` (``DRIVE_LOOP_HZ = "fast"``): the setting, the file that
  sets it and what it must be (:func:`check_start_values`, called before the drive starts);
* a Keras model (``.h5``) without TensorFlow, which Donkeycar reports as ``NameError: name 'Input' is not
  defined`` (its imports of TensorFlow are guarded, the names they define are not);
* anything else the car raises: the type and message, and the car's own line that led to it.

The traceback is still there for who needs it: ``--verbose`` prints it, and it is logged at debug level.
"""

from __future__ import annotations

import importlib.util
import re
import traceback
from pathlib import Path
from types import FrameType
from typing import Any

from ..errors import AsyncdonkeyError
from ..options import BadValue, non_negative_int, positive_float

__all__ = ["TENSORFLOW_HINT", "CarSettingError", "car_error", "check_start_values"]

#: the way out for a pilot that needs TensorFlow (a missing module, or Donkeycar's unguarded Keras names)
TENSORFLOW_HINT = (
    "the pilot needs {module}, which is not installed: pip install tensorflow, or drive a .tflite model without "
    "it (--type tflite_linear, docs/donkeycar.md)"
)


class CarSettingError(AsyncdonkeyError, ValueError):
    """A value the car gives ``V.start`` is not of the kind it must be; the message names the setting's file."""


# -- V.start's values ----------------------------------------------------------------------------------------
#: V.start's argument -> (the Donkeycar setting the templates pass for it, its check, what it is)
_START_SETTINGS = {
    "rate_hz": ("DRIVE_LOOP_HZ", positive_float, "the drive loop rate in Hz"),
    "max_loop_count": ("MAX_LOOPS", non_negative_int, "the number of ticks to drive, or None for no limit"),
}


def check_start_values(values: dict[str, Any], caller: FrameType | None) -> None:
    """Raise :class:`CarSettingError` for a ``V.start`` value that is not what it must be.

    ``caller`` is the frame that called ``start`` (``manage.py``'s ``drive()``): its ``cfg`` says which setting
    the value came from, and the car's folder which file sets it. ``MAX_LOOPS = None`` (no limit) is accepted; text is
    not,
    not even ``"20"``: the checks would read it as a number, Donkeycar's loop would not.
    """
    for name, value in values.items():
        if name not in _START_SETTINGS or (value is None and name == "max_loop_count"):
            continue
        setting, check, meaning = _START_SETTINGS[name]
        try:
            check(value)
            problem = f"expected a number, got text {value!r}" if isinstance(value, str) else None
        except BadValue as exc:
            problem = str(exc)
        if problem is not None:
            raise CarSettingError(f"{_setting_source(name, setting, value, caller)}: {problem} ({meaning})")


def _setting_source(name: str, setting: str, value: Any, caller: FrameType | None) -> str:
    """``myconfig.py: DRIVE_LOOP_HZ`` when the car's ``cfg`` holds the value (the file that sets it last),
    else ``manage.py:<line>: V.start(rate_hz=...)``."""
    if caller is None:
        return f"V.start({name}=...)"
    where = Path(caller.f_code.co_filename)
    cfg = caller.f_locals.get("cfg")
    if cfg is not None and getattr(cfg, setting, object()) is value:
        for config in ("myconfig.py", "config.py"):  # Donkeycar loads config.py, then myconfig.py over it
            path = where.parent / config
            if _assigns(path, setting):
                return f"{config}: {setting}"
        return f"{where.name}: cfg.{setting}"
    return f"{where.name}:{caller.f_lineno}: V.start({name}=...)"


def _assigns(path: Path, setting: str) -> bool:
    """Whether the config file ``path`` sets ``setting`` on a line of its own (not commented out)."""
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except OSError:
        return False
    return re.search(rf"^{re.escape(setting)}\s*=", text, re.MULTILINE) is not None


# -- an exception from the car -------------------------------------------------------------------------------
def car_error(exc: BaseException, car: Path) -> str:
    """One line for ``exc``, raised while running the car file ``car``: ``<file>: <what is wrong>``."""
    folder = car.resolve().parent
    if isinstance(exc, SyntaxError):
        return _syntax_error(exc, folder)
    if isinstance(exc, CarSettingError):
        return str(exc)
    model = _model_error(exc, folder)
    if model is not None:
        return model
    keras_without_tensorflow = isinstance(exc, NameError) and _raised_in(exc, "donkeycar/parts/keras.py")
    if keras_without_tensorflow and importlib.util.find_spec("tensorflow") is None:
        return f"{car.name}: " + TENSORFLOW_HINT.format(module="tensorflow")
    return f"{_car_line(exc, folder, car)}: {type(exc).__name__}: {_first_line(exc)}{_raised_at(exc, folder)}"


def _syntax_error(exc: SyntaxError, folder: Path) -> str:
    name = _shown(Path(exc.filename), folder) if exc.filename else "the car"
    return f"{name}:{exc.lineno}: syntax error: {exc.msg}"


def _model_error(exc: BaseException, folder: Path) -> str | None:
    """The model file that failed to load, and why: found in the traceback as Donkeycar's loaders' ``model_path``
    (``manage.py``'s ``load_model``, ``KerasPilot.load``, each interpreter's ``load``)."""
    path = model_type = None
    for frame, _ in traceback.walk_tb(exc.__traceback__):
        local = frame.f_locals
        if isinstance(local.get("model_type"), str):
            model_type = local["model_type"]
        if frame.f_code.co_name in ("load", "load_model") and isinstance(local.get("model_path"), str):
            path = path or local["model_path"]
    if path is None:
        return None
    if not (folder / path).exists():
        return f"{path}: no such model file (in {folder})" if not Path(path).is_absolute() else f"{path}: no such file"
    message = _first_line(exc)
    if message.startswith(path):  # asyncdonkey's own loaders name the file already
        return message
    kind = f" a {model_type}" if model_type else " a"
    return f"{path}: cannot be loaded as{kind} model: {message}"


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def _raised_in(exc: BaseException, suffix: str) -> bool:
    frames = traceback.extract_tb(exc.__traceback__)
    return bool(frames) and Path(frames[-1].filename).as_posix().endswith(suffix)


def _car_line(exc: BaseException, folder: Path, car: Path) -> str:
    """``file:line`` of the innermost frame in the car's folder (its own code that led to the error)."""
    where = car.name
    for frame in traceback.extract_tb(exc.__traceback__):
        path = Path(frame.filename)
        if path.is_absolute() and path.resolve().parent == folder:
            where = f"{path.name}:{frame.lineno}"
    return where


def _raised_at(exc: BaseException, folder: Path) -> str:
    """`` (raised at donkeycar/utils.py:550)`` when the error was raised outside the car's own files."""
    frames = traceback.extract_tb(exc.__traceback__)
    if not frames:
        return ""
    last = Path(frames[-1].filename)
    if last.is_absolute() and last.resolve().parent == folder:
        return ""
    parts = last.parts
    shown = "/".join(parts[parts.index("site-packages") + 1 :]) if "site-packages" in parts else str(last)
    return f" (raised at {shown}:{frames[-1].lineno})"


def _shown(path: Path, folder: Path) -> str:
    """``path`` relative to the car's folder when it is in it (``myconfig.py``), else as it is."""
    try:
        return str(path.resolve().relative_to(folder))
    except ValueError:
        return str(path)
