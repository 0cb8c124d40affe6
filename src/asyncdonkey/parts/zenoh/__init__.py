"""Memory channels over Zenoh: an off-board pilot, a fleet view, with true data ages across the network.

Needs the ``zenoh`` extra (``pip install 'asyncdonkey[zenoh]'``). See ``docs/scale-out.md``.

* :class:`ZenohLink`, :func:`zenoh_config` — one session and the key prefix of a car's channels.
* :class:`ZenohPublisher`, :class:`ZenohSubscriber` — the parts.
* :mod:`.codec` — the wire format (documented for non-Python clients).
"""

from .codec import CodecError, decode, encode
from .link import ZenohConfigError, ZenohLink, zenoh_config
from .parts import ZenohPublisher, ZenohSubscriber

__all__ = [
    "CodecError",
    "ZenohConfigError",
    "ZenohLink",
    "ZenohPublisher",
    "ZenohSubscriber",
    "decode",
    "encode",
    "zenoh_config",
]
