"""Memory channels over Zenoh: an off-board pilot, a fleet view, with true data ages across the network.

Needs the ``zenoh`` extra (``pip install -e '.[zenoh]'`` in a checkout; ``docs/install.md``). See ``docs/scale-out.md``.

* :class:`ZenohLink`, :func:`zenoh_config` — one session and the key prefix of a car's channels.
* :class:`ZenohPublisher`, :class:`ZenohSubscriber` — the parts (``group=PILOT_COMMAND``: the remote
  pilot's angle and throttle as one sample).
* :class:`PilotServer`, :class:`BatchPilot`, :class:`FrameBatcher` — one pilot model for a fleet, batched.
* :mod:`.pairing` — the secure configs of ``asyncdonkey zenoh-pair`` (one car, or a fleet and its server).
* :mod:`.codec` — the wire format (documented for non-Python clients); :mod:`.sequence` — which numbered
  samples a receiver takes (plausible ages; no sample can lock a sender out).
* :mod:`.certs` — a Zenoh config's certificates against this machine's clock (a refused handshake says why).
"""

from .batch_infer import BatchPilot
from .batcher import FrameBatcher
from .codec import CodecError, decode, encode
from .link import ZenohConfigError, ZenohLink, link_config, zenoh_config
from .pairing import COMMAND_CHANNELS, PILOT_COMMAND
from .parts import ZenohPublisher, ZenohSubscriber
from .pilot_server import PilotServer

__all__ = [
    "COMMAND_CHANNELS",
    "PILOT_COMMAND",
    "BatchPilot",
    "CodecError",
    "FrameBatcher",
    "PilotServer",
    "ZenohConfigError",
    "ZenohLink",
    "ZenohPublisher",
    "ZenohSubscriber",
    "decode",
    "encode",
    "link_config",
    "zenoh_config",
]
