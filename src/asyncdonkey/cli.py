"""Moved to :mod:`asyncdonkey.commands`; this old import path (and ``python -m asyncdonkey.cli``) keeps working,
with a DeprecationWarning on import. ``python -m asyncdonkey.commands`` runs the command from a module now."""

import sys

from ._moved import alias

if __name__ == "__main__":
    from .commands.cli import main

    sys.exit(main())

alias(__name__, "asyncdonkey.commands.cli")
