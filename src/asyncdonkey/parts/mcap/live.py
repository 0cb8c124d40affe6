"""``FoxgloveServer``: the car's channels and timing live in Foxglove, over its WebSocket protocol.

The part runs foxglove-sdk's WebSocket server (the server itself is a native thread of the SDK) and publishes
the same topics, schemas and bytes as :class:`~.recorder.McapRecorder` writes (:mod:`.encode`). Open Foxglove,
*Open connection* → ``ws://<car>:8765``, and load the layout shipped with the package
(:func:`~.layout.layout_path`; ``python -m asyncdonkey.parts.mcap.layout`` prints it).

The SDK's server names the protocol ``foxglove.sdk.v1`` and refuses clients that offer only its older name,
``foxglove.websocket.v1`` (older Foxglove Studio versions, Lichtblick). So the SDK's server listens on a loopback
port and a :class:`~.relay.SubprotocolRelay` on the public address (its own thread) accepts both names, renaming
the offer in the handshake and splicing the bytes after it (``max_clients`` connections at once).

The tick pays what the recorder's tick pays (two small dict copies and a queue append, see
:class:`~.recorder.TickRecorder`); encoding and sending happen on the writer thread, and a value is encoded
only if a client subscribed to its topic, so a server nobody watches costs no JPEG encoding. When the thread
falls behind (a slow Wi-Fi link), ticks are dropped at the queue (``stats.dropped``) and the SDK drops the
oldest messages of a slow client: the live view skips frames rather than delaying the car.

Bound to 127.0.0.1 by default: anyone who can reach the port sees the camera. Pass ``host="0.0.0.0"`` to watch
from a laptop on the car's network.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from typing import Any

from ...errors import AsyncdonkeyError
from ...extras import require
from .encode import ChannelSpec, TickEncoder, TickSnapshot, TimeMap
from .recorder import TickRecorder
from .relay import SubprotocolRelay

__all__ = ["FoxgloveServer", "FoxgloveServerError"]

logger = logging.getLogger(__name__)


class FoxgloveServerError(AsyncdonkeyError, OSError):
    """The WebSocket server could not start (a port in use, an address not on this machine)."""


class _LiveSink:
    """Publishes encoded ticks to the server's channels (one per topic, created when first seen)."""

    def __init__(self, encoder: TickEncoder, context: Any) -> None:
        self.encoder = encoder
        self.context = context
        self.times: TimeMap | None = None
        self.channels: dict[str, Any] = {}
        self.unsynced = 0
        self.sync_requested = False
        self.durable = 0
        self.syncs = 0
        self.messages = 0

    @property
    def bad_values(self) -> int:
        return self.encoder.bad_values

    def _channel(self, spec: ChannelSpec) -> Any:
        ch = self.channels.get(spec.topic)
        if ch is None:
            import foxglove

            schema = foxglove.Schema(name=spec.schema_name, encoding=spec.schema_encoding, data=spec.schema_data)
            ch = self.channels[spec.topic] = foxglove.Channel(
                spec.topic, schema=schema, message_encoding=spec.message_encoding, context=self.context
            )
        return ch

    def _wanted(self, spec: ChannelSpec) -> bool:
        return self._channel(spec).has_sinks()

    def write(self, t: float, payload: tuple[Any, ...]) -> None:
        assert self.times is not None
        for spec, data, log_ns, _origin_ns in self.encoder.encode(TickSnapshot(*payload), self.times, self._wanted):
            self.channels[spec.topic].log(data, log_time=log_ns)
            self.messages += 1

    def sync(self) -> bool:
        return False

    def close(self) -> None:
        for ch in self.channels.values():
            ch.close()


class FoxgloveServer(TickRecorder):
    """A drive-loop part that serves the vehicle's Memory and timing live to Foxglove.

    ::

        live = FoxgloveServer(vehicle)                    # ws://127.0.0.1:8765
        vehicle.add(live, name="foxglove")

    Args:
        vehicle: the :class:`~asyncdonkey.loop.Vehicle` whose ``mem`` and ``profiler`` are published.
        channels, every_tick, kinds, gps, timing, jpeg_quality: as :class:`~.recorder.McapRecorder`.
        host, port: where the server listens (``port=0``: any free port, see :attr:`port`).
        name: the server name clients show.
        queue_size: ticks that may wait for the sending thread before new ones are dropped.
        max_clients: clients connected at once; one more is answered HTTP 503.
    """

    def __init__(
        self,
        vehicle: Any,
        channels: Sequence[str] | None = None,
        *,
        host: str = "127.0.0.1",
        port: int = 8765,
        name: str = "asyncdonkey",
        every_tick: bool = False,
        kinds: Mapping[str, str] | None = None,
        gps: tuple[str, str] | None = ("gps/latitude", "gps/longitude"),
        timing: bool = True,
        jpeg_quality: int = 75,
        queue_size: int = 4,
        drain_timeout_s: float = 2.0,
        max_clients: int = 8,
    ) -> None:
        foxglove = require("foxglove", "mcap", "the Foxglove live view")

        where = f"FoxgloveServer({host}:{port})"
        self._check_writer_args(where, queue_size, 1, 1.0, drain_timeout_s)
        if not (isinstance(max_clients, int) and max_clients > 0):
            raise ValueError(f"{where}: max_clients must be a positive integer, got {max_clients!r}")
        if not hasattr(vehicle, "mem"):
            raise TypeError(f"{where}: vehicle must be a Vehicle (with .mem and .profiler), got {vehicle!r}")
        self.vehicle = vehicle
        self._timing = timing
        self.encoder = TickEncoder(channels, every_tick=every_tick, kinds=kinds, gps=gps, jpeg_quality=jpeg_quality)
        self._context = foxglove.Context()
        self.server, self.relay = _start(foxglove, self._context, name, host, port, max_clients, where)
        self.host = host
        self.port: int = self.relay.port
        """the port the server listens on (the one chosen when ``port=0``)"""
        self._sink = sink = _LiveSink(self.encoder, self._context)
        self._start_writer(
            sink,
            f"FoxgloveServer({host}:{self.port})",
            queue_size=queue_size,
            sync_interval_s=1.0,
            sync_every=1,
            drain_timeout_s=drain_timeout_s,
            time_fn=self._first_time,
        )
        logger.info("Foxglove live view on ws://%s:%d", host, self.port)

    @property
    def url(self) -> str:
        return f"ws://{self.host}:{self.port}"

    def shutdown(self, timeout: float | None = None) -> None:
        """Stop publishing, then stop the server."""
        was_closed = self._closed
        super().shutdown(timeout)
        if not was_closed:
            self.relay.stop()
            self.server.stop()

    close = shutdown

    def __repr__(self) -> str:
        return f"<FoxgloveServer {self.url}>"


def _start(
    foxglove: Any, context: Any, name: str, host: str, port: int, max_clients: int, where: str
) -> tuple[Any, SubprotocolRelay]:
    """The SDK's server on a loopback port, and the relay on the public address in front of it."""
    try:
        server = foxglove.start_server(name=name, host="127.0.0.1", port=0, context=context)
    except Exception as exc:  # the SDK raises its own error types
        raise FoxgloveServerError(f"{where}: cannot start the WebSocket server: {exc}") from exc
    try:
        relay = SubprotocolRelay(host, port, ("127.0.0.1", server.port), max_connections=max_clients)
    except OSError as exc:
        server.stop()
        raise FoxgloveServerError(f"{where}: cannot listen: {exc}") from exc
    return server, relay
