"""Optional dependencies: one way to import them and to say what to install when one is missing.

A feature that needs an extra of ``pyproject.toml`` (``mcap``, ``tflite``, ``quantize``, ``zenoh``, ...) calls
:func:`require` before it imports the extra's modules::

    require("mcap", "mcap", "reading MCAP recordings")
    from mcap.records import Channel  # the package is there now

A missing module raises :class:`MissingExtra`, whose message is one line: the feature, the extra and the exact
command that installs it (:func:`install_command`). The commands print that line and exit with status 2, never a
traceback: a user missing an extra needs the install command, not our stack. ``MissingExtra`` is an
``ImportError`` too, so code that already catches ``ImportError`` around an optional import keeps working.

asyncdonkey is not on PyPI, so ``pip install 'asyncdonkey[extra]'`` fails for most users: the command names the
source this copy was installed from, as pip recorded it in the distribution's ``direct_url.json`` (PEP 610), and
the interpreter that runs, so it installs into the same environment (docs/install.md):

=========================  ===============================================================================
installed from             the command (``<python>`` is ``sys.executable``)
=========================  ===============================================================================
a checkout, editable       ``<python> -m pip install -e '/path/to/checkout[extra]'``
a directory or a file      ``<python> -m pip install '/path/to/asyncdonkey-0.1.0-py3-none-any.whl[extra]'``
a git URL                  ``<python> -m pip install 'asyncdonkey[extra] @ git+https://...@rev'``
an archive URL             ``<python> -m pip install 'asyncdonkey[extra] @ https://.../asyncdonkey.whl'``
a package index            ``<python> -m pip install 'asyncdonkey[extra]'``
=========================  ===============================================================================

This module is part of the core: it imports nothing of the parts, drivers or commands.
"""

from __future__ import annotations

import importlib
import importlib.metadata
import json
import shlex
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from types import ModuleType
from typing import Any
from urllib.parse import urlsplit
from urllib.request import url2pathname

from .errors import AsyncdonkeyError

__all__ = [
    "EXTRA_OF_MODULE",
    "MissingExtra",
    "extra_for_module",
    "install_command",
    "install_command_for",
    "installed_from",
    "require",
]

#: The distribution's name, and the repository the docs install it from when nothing else is known.
DISTRIBUTION = "asyncdonkey"
REPOSITORY = "https://github.com/asyncdonkey/asyncdonkey"

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
    """The shell command that installs ``extra`` into this environment, from where this copy came from.

    One line, quoted for a POSIX shell: ``<sys.executable> -m pip install ...`` with the checkout, file or URL that
    :func:`installed_from` finds (the table in the module's docstring).
    """
    return install_command_for(extra, installed_from(), sys.executable)


def installed_from() -> Mapping[str, Any] | None:
    """The installed distribution's ``direct_url.json`` (PEP 610) as a mapping, or ``None`` for an index install.

    A copy that is not installed at all (its ``src`` directory on ``sys.path``) reads as an editable install of
    the checkout it sits in. An unreadable or malformed record counts as none: the hint must never raise.
    """
    try:
        text = importlib.metadata.distribution(DISTRIBUTION).read_text("direct_url.json")
    except importlib.metadata.PackageNotFoundError:
        return _source_tree()
    if not text:
        return None
    try:
        data = json.loads(text)
    except ValueError:
        return None
    return data if isinstance(data, dict) and isinstance(data.get("url"), str) else None


def install_command_for(extra: str, direct_url: Mapping[str, Any] | None, python: str) -> str:
    """The command that installs ``extra`` with interpreter ``python`` for a copy installed as ``direct_url`` says.

    ``direct_url`` is a PEP 610 record (``url`` with ``dir_info``, ``archive_info`` or ``vcs_info``), ``None``
    for a copy from a package index. Pure: the tests give it each form.
    """
    target = _install_target(extra, direct_url)
    return f"{shlex.quote(python)} -m pip install {target}"


def _install_target(extra: str, direct_url: Mapping[str, Any] | None) -> str:
    """pip's argument for ``extra`` (with ``-e`` for an editable checkout), quoted for the shell."""
    named = f"{DISTRIBUTION}[{extra}]"
    if direct_url is None:
        return shlex.quote(named)
    url = str(direct_url["url"])
    vcs_info = direct_url.get("vcs_info")
    if isinstance(vcs_info, Mapping):
        return shlex.quote(f"{named} @ {_vcs_url(url, vcs_info, direct_url.get('subdirectory'))}")
    local = _local_path(url)
    if local is None:
        return shlex.quote(f"{named} @ {url}")
    dir_info = direct_url.get("dir_info")
    editable = isinstance(dir_info, Mapping) and dir_info.get("editable") is True
    return ("-e " if editable else "") + shlex.quote(f"{local}[{extra}]")


def _vcs_url(url: str, vcs_info: Mapping[str, Any], subdirectory: object) -> str:
    """pip's VCS requirement URL: ``git+<url>@<the revision asked for>``, and the subdirectory if there was one."""
    vcs = str(vcs_info.get("vcs", "git"))
    out = url if url.startswith(f"{vcs}+") else f"{vcs}+{url}"
    revision = vcs_info.get("requested_revision")
    if isinstance(revision, str) and revision:
        out += f"@{revision}"
    if isinstance(subdirectory, str) and subdirectory:
        out += f"#subdirectory={subdirectory}"
    return out


def _local_path(url: str) -> str | None:
    """The local path of a ``file:`` URL (``None`` for any other scheme)."""
    parts = urlsplit(url)
    if parts.scheme != "file" or parts.netloc not in ("", "localhost"):
        return None
    return url2pathname(parts.path)


def _source_tree() -> Mapping[str, Any] | None:
    """An editable record of the checkout this module sits in (``<checkout>/src/asyncdonkey``), if it is one."""
    checkout = Path(__file__).resolve().parents[2]
    if not (checkout / "pyproject.toml").is_file():
        return None
    return {"url": checkout.as_uri(), "dir_info": {"editable": True}}


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
