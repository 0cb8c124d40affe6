"""Old import paths of modules that moved: each old module replaces itself with the new one.

The command modules moved into :mod:`asyncdonkey.commands` (the runtime core never imports them). Code written
against the old paths (``from asyncdonkey.replay import replay``) keeps working: the old module imports the new
one, warns once with a :class:`DeprecationWarning` naming the new path, and puts the new module in its place in
``sys.modules``, so both names are the same module object (patching one patches the other).
"""

from __future__ import annotations

import importlib
import sys
import warnings


def alias(old: str, new: str) -> None:
    """Make module ``old`` (being imported now) an alias of ``new``, with a warning aimed at the importer."""
    module = importlib.import_module(new)
    warnings.warn(
        f"{old} moved to {new}; import it from there (the old path will be removed in a future release)",
        DeprecationWarning,
        stacklevel=3,
    )
    sys.modules[old] = module
