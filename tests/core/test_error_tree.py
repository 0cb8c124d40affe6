"""Every error asyncdonkey raises is an ``AsyncdonkeyError``, so ``except AsyncdonkeyError`` catches them all.

The walk imports every module of the package (all optional extras are installed where the tests run), so a
new exception class anywhere that forgets the root fails here by name.
"""

from __future__ import annotations

import ast
import importlib
import inspect
import pkgutil
from pathlib import Path
from types import ModuleType

import pytest

import asyncdonkey
from asyncdonkey.errors import AsyncdonkeyError, PartInterrupted

#: BaseException on purpose: a part's ``except Exception`` must not swallow the stop request it carries
OUTSIDE_THE_ROOT = {PartInterrupted}


def _every_module() -> list[ModuleType]:
    """Every module of the package, imported; ``__main__`` modules are skipped (importing one runs the CLI)."""
    modules = []
    for info in pkgutil.walk_packages(asyncdonkey.__path__, "asyncdonkey."):
        if info.name.rsplit(".", 1)[-1] == "__main__":
            continue
        modules.append(importlib.import_module(info.name))
    return modules


def _public_exceptions() -> dict[str, type[BaseException]]:
    """``module.Class`` -> class, for each public exception class defined in the module that holds it."""
    found = {}
    for module in _every_module():
        for name, obj in vars(module).items():
            if name.startswith("_") or not inspect.isclass(obj) or not issubclass(obj, BaseException):
                continue
            if obj.__module__ == module.__name__:  # defined here, not imported
                found[f"{obj.__module__}.{name}"] = obj
    return found


def test_every_public_exception_class_of_the_package_is_under_the_root() -> None:
    found = _public_exceptions()
    assert len(found) >= 45, sorted(found)  # the walk really reached the hardware, parts and command modules
    outside = sorted(
        name for name, cls in found.items() if cls not in OUTSIDE_THE_ROOT and not issubclass(cls, AsyncdonkeyError)
    )
    assert outside == [], f"not subclasses of asyncdonkey.errors.AsyncdonkeyError: {', '.join(outside)}"


def test_the_one_class_outside_the_root_is_not_an_exception_at_all() -> None:
    """PartInterrupted stays outside only because it is a BaseException; an Exception must be under the root."""
    for cls in OUTSIDE_THE_ROOT:
        assert not issubclass(cls, Exception), cls


@pytest.mark.parametrize(
    "module, name, stdlib_base",
    [
        ("asyncdonkey.safety.process", "SafetyProcessError", RuntimeError),
        ("asyncdonkey.clock.virtual_loop", "VirtualClockError", RuntimeError),
        ("asyncdonkey.clock.virtual_loop", "VirtualClockDeadlock", RuntimeError),
        ("asyncdonkey.options", "BadValue", ValueError),
        ("asyncdonkey.parts.actuators", "CalibrationLocked", ValueError),
        ("asyncdonkey.parts.zenoh.pairing", "PairExists", ValueError),
        ("asyncdonkey.hw.i2c", "I2CDeviceInUse", OSError),
        ("asyncdonkey.parts.tub.format", "TubImagePathError", ValueError),
        ("asyncdonkey.parts.mcap.reader", "McapReadError", ValueError),
        ("asyncdonkey.testing.picamera2_model", "Picamera2ModelHang", AssertionError),
        ("asyncdonkey.errors", "PartSpecError", AssertionError),
        ("asyncdonkey.errors", "ChannelCountError", IndexError),
    ],
)
def test_errors_keep_the_standard_library_base_callers_catch(module: str, name: str, stdlib_base: type) -> None:
    cls = getattr(importlib.import_module(module), name)
    assert issubclass(cls, AsyncdonkeyError)
    assert issubclass(cls, stdlib_base)


def test_the_errors_exported_from_asyncdonkey_are_the_classes_their_modules_define() -> None:
    exported = {n: getattr(asyncdonkey, n) for n in asyncdonkey.__all__}
    errors = {n: obj for n, obj in exported.items() if inspect.isclass(obj) and issubclass(obj, BaseException)}
    assert {"AsyncdonkeyError", "PartError", "SafetyProcessError", "VirtualClockError"} <= set(errors)
    for name, cls in errors.items():
        assert getattr(importlib.import_module(cls.__module__), name) is cls, name
        assert cls in OUTSIDE_THE_ROOT or issubclass(cls, AsyncdonkeyError), name
    assert asyncdonkey.AsyncdonkeyError is AsyncdonkeyError


def test_errors_module_imports_nothing_from_the_package_at_run_time() -> None:
    """errors.py sits below every module; importing the package from it would make an import cycle."""
    tree = ast.parse(Path(asyncdonkey.errors.__file__).read_text())
    runtime_imports = []
    for node in tree.body:  # module level only; an ``if TYPE_CHECKING:`` block is not run
        if isinstance(node, ast.ImportFrom):
            runtime_imports.append((node.level, node.module or ""))
        elif isinstance(node, ast.Import):
            runtime_imports.extend((0, alias.name) for alias in node.names)
    inside = [m for level, m in runtime_imports if level > 0 or m.split(".")[0] == "asyncdonkey"]
    assert inside == []


def test_a_caller_catches_a_bad_option_with_the_root() -> None:
    from asyncdonkey.options import positive_float

    with pytest.raises(AsyncdonkeyError, match=r"expected a finite number > 0, got -1"):
        positive_float(-1)
