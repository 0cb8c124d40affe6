"""The ``asyncdonkey`` command and its subcommands, one module each.

``cli`` parses the command line and runs a car file; ``replay``, ``report``, ``convert``, ``quantize``,
``donkey`` (a Donkeycar car on this runtime) and ``zenoh`` (``zenoh-pair``, ``top``) are the subcommands;
``recordings`` opens a tub or an MCAP recording for them. These modules use the runtime and the parts; the
runtime core never imports them.
"""

from .cli import main

__all__ = ["main"]
