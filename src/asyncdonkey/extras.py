"""Optional dependencies: one way to import them and to say what to install when one is missing.

A feature that needs an extra of ``pyproject.toml`` (``mcap``, ``tflite``, ``quantize``, ``zenoh``, ...) calls
:func:`require` before it imports the extra's modules::

    require("mcap", "mcap", "reading MCAP recordings")
    from mcap.records import Channel  # the package is there now

A missing module raises :class:`MissingExtra`, whose message is one line: the feature, the extra and the exact
``pip install 'asyncdonkey[extra]'`` command. The commands print that line and exit with status 2, never a
traceback: a user missing an extra needs the install command, not our stack. ``MissingExtra`` is an
``ImportError`` too, so code that already catches ``ImportError`` around an optional import keeps working.

This module is part of the core: it imports nothing of the parts, drivers or commands.
"""

from __future__ import annotations

import importlib
from collections.abc import Sequence
from types import ModuleType

from .errors import AsyncdonkeyError

__all__ = ["EXTRA_OF_MODULE", "MissingExtra", "extra_for_module", "install_command", "require"]

#: The top-level modules the extras of ``pyproject.toml`` install, and their extra: how the commands name the
#: extra when an import that did not go through :func:`require` fails (their last line of defence).
EXTRA_OF_MODULE = {
    "mcap": "mcap",
    "foxglove": "mcap",
    "google.protobuf": "mcap",
    "ai_edge_litert": "tflite",
    "tflite_runtime": "tflite",
    "onnx": "quantize",
    "zenoh": "zenoh",
    "cryptography": "zenoh",
}


def install_command(extra: str) -> str:
    """The shell command that installs ``extra``: ``pip install 'asyncdonkey[extra]'`` (quoted for the shell)."""
    return f"pip install 'asyncdonkey[{extra}]'"


class MissingExtra(AsyncdonkeyError, ImportError):
    """A feature's optional dependency is not installed; the message says which extra to install, in one line.

    ``feature`` is what the user asked for, ``extra`` the ``pyproject.toml`` extra that provides it, ``module``
    the module that did not import and ``reason`` the import error's first line.
    """

    def __init__(self, feature: str, extra: str, module: str, reason: str = "") -> None:
        why = f"{module} cannot be imported: {reason}" if reason else f"{module} is not installed"
        super().__init__(f"{feature} needs the {extra} extra ({why}): {install_command(extra)}", name=module)
        self.feature = feature
        self.extra = extra
        self.module = module
        self.reason = reason


def extra_for_module(name: str | None) -> str | None:
    """The extra that installs module ``name`` (or its package), ``None`` for a module no extra provides."""
    while name:
        extra = EXTRA_OF_MODULE.get(name)
        if extra is not None:
            return extra
        name = name.rpartition(".")[0]
    return None


def require(module: str | Sequence[str], extra: str, feature: str) -> ModuleType:
    """Import and return ``module`` (or the first of several alternatives that imports), which ``extra`` provides.

    Raises :class:`MissingExtra` naming ``feature``, ``extra`` and the install command when none imports.
    Only an ``ImportError`` counts as missing: a package that is installed but fails otherwise raises as is.
    """
    names = [module] if isinstance(module, str) else list(module)
    if not names:
        raise ValueError("require: name at least one module")
    first_error: ImportError | None = None
    for name in names:
        try:
            return importlib.import_module(name)
        except ImportError as exc:
            first_error = first_error or exc
    reason = _first_line(first_error)
    if isinstance(first_error, ModuleNotFoundError) and first_error.name is not None:
        missing = first_error.name
        reason = "" if names[0] == missing or names[0].startswith(missing + ".") else reason
    raise MissingExtra(feature, extra, " or ".join(names), reason)


def _first_line(exc: BaseException | None) -> str:
    text = str(exc or "").strip()
    return text.splitlines()[0] if text else ""
