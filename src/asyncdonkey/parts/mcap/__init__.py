"""MCAP recording and the Foxglove live view (extra ``asyncdonkey[mcap]``).

* :class:`McapRecorder` — the part that records every channel and the loop's timing to an MCAP file.
* :class:`FoxgloveServer` — the part that publishes the same topics live on Foxglove's WebSocket protocol.
* :func:`read_mcap` — messages of a file, decoded, including a file cut short by a crash.

See ``docs/mcap-foxglove.md``.
"""

from .encode import TICK_TOPIC, TickEncoder, TimeMap, topic_for
from .recorder import McapRecorder

__all__ = ["TICK_TOPIC", "McapRecorder", "TickEncoder", "TimeMap", "topic_for"]
