"""FoxgloveServer: a client speaking Foxglove's WebSocket protocol on loopback sees the car's topics advertised,
subscribes, and receives the messages the MCAP file would hold.

The protocol's subprotocol name is ``foxglove.websocket.v1``; foxglove-sdk 0.30 and later name the same protocol
``foxglove.sdk.v1`` and refuse the old name, so the client offers both, as Foxglove's app does."""

from __future__ import annotations

import asyncio
import json
import struct

import numpy as np
import pytest
import websockets

from asyncdonkey.loop import Vehicle
from asyncdonkey.parts.mcap.live import FoxgloveServer
from asyncdonkey.parts.mcap.reader import decode_image, protobuf_class

PROTOCOLS = ["foxglove.sdk.v1", "foxglove.websocket.v1"]


class Car:
    def __init__(self):
        self.k = 0

    def run(self):
        self.k += 1
        return np.full((120, 160, 3), self.k % 250, np.uint8), 0.5, self.k


async def advertised(ws, topics: set[str], timeout: float = 5.0) -> dict[str, dict]:
    """Read control messages until every topic in ``topics`` has been advertised."""
    seen: dict[str, dict] = {}
    async with asyncio.timeout(timeout):
        while not topics <= set(seen):
            raw = await ws.recv()
            if isinstance(raw, str):
                msg = json.loads(raw)
                if msg["op"] == "advertise":
                    seen.update({c["topic"]: c for c in msg["channels"]})
    return seen


async def message_data(ws, sub_id: int, timeout: float = 5.0) -> tuple[int, bytes]:
    async with asyncio.timeout(timeout):
        while True:
            raw = await ws.recv()
            if isinstance(raw, bytes) and raw[0] == 0x01:
                sid, log_ns = struct.unpack_from("<IQ", raw, 1)
                if sid == sub_id:
                    return log_ns, raw[13:]


@pytest.mark.asyncio
async def test_a_client_subscribes_and_receives_live_messages():
    v = Vehicle()
    v.add(Car(), outputs=["cam/image_array", "user/angle", "n"])
    live = FoxgloveServer(v, port=0)
    assert live.url.startswith("ws://127.0.0.1:") and live.port > 0
    v.add(live, name="foxglove")
    drive = asyncio.create_task(v.run(rate_hz=50))
    try:
        async with websockets.connect(live.url, subprotocols=PROTOCOLS) as ws:
            assert ws.subprotocol in PROTOCOLS
            info = json.loads(await ws.recv())
            assert info["op"] == "serverInfo" and info["name"] == "asyncdonkey"
            chans = await advertised(ws, {"/n", "/cam/image_array", "/cam/image_array/steering", "/asyncdonkey/tick"})
            assert chans["/n"]["encoding"] == "json" and chans["/n"]["schemaName"] == "asyncdonkey.Number"
            assert chans["/cam/image_array"]["schemaName"] == "foxglove.CompressedImage"
            await ws.send(
                json.dumps(
                    {
                        "op": "subscribe",
                        "subscriptions": [
                            {"id": 1, "channelId": chans["/n"]["id"]},
                            {"id": 2, "channelId": chans["/cam/image_array"]["id"]},
                            {"id": 3, "channelId": chans["/asyncdonkey/tick"]["id"]},
                        ],
                    }
                )
            )
            _, data = await message_data(ws, 1)
            first = json.loads(data)["value"]
            _, data = await message_data(ws, 1)
            assert json.loads(data)["value"] > first  # a counter, live
            log_ns, data = await message_data(ws, 2)
            cls = protobuf_class("foxglove.CompressedImage", _schema_bytes(chans["/cam/image_array"]))
            img = cls.FromString(data)
            assert img.format == "jpeg" and decode_image(img).shape == (120, 160, 3)
            assert img.timestamp.seconds * 10**9 + img.timestamp.nanos <= log_ns  # sensed, then recorded
            _, data = await message_data(ws, 3)
            tick = json.loads(data)
            assert tick["tick"] >= 1 and tick["lateness_ms"] >= 0
    finally:
        v.stop()
        await drive
    assert live.stats.failed == 0
    # the server is gone once the drive has shut the part down
    with pytest.raises(OSError):
        async with websockets.connect(live.url, subprotocols=PROTOCOLS, open_timeout=1):
            pass


def _schema_bytes(channel: dict) -> bytes:
    import base64

    return base64.b64decode(channel["schema"])


@pytest.mark.asyncio
async def test_nobody_watching_costs_no_encoding():
    v = Vehicle()
    v.add(Car(), outputs=["cam/image_array", "user/angle", "n"])
    live = FoxgloveServer(v, port=0)
    v.add(live)
    await v.run(rate_hz=100, max_loop_count=10)
    assert live.stats.written + live.stats.dropped == 10 and live.stats.written > 0
    assert live._sink.messages == 0
    assert set(live._sink.channels) >= {"/cam/image_array", "/n", "/asyncdonkey/tick"}  # advertised anyway


def test_the_shipped_layout_is_the_built_one_and_shows_recorded_topics():
    from asyncdonkey.parts.mcap.layout import build_layout, layout_path

    text = layout_path().read_text().strip()
    assert text == build_layout()
    layout = json.loads(text)
    found = json.dumps(layout)
    for topic in (
        '"/cam/image_array"',
        "/cam/image_array/steering",
        "/user/angle.value",
        "/pilot/angle.value",
        "/asyncdonkey/tick.lateness_ms",
        "/asyncdonkey/parts",
        "/asyncdonkey/latency",
    ):
        assert topic in found


def test_a_busy_port_is_an_error_naming_the_address():
    from asyncdonkey.errors import AsyncdonkeyError
    from asyncdonkey.parts.mcap.live import FoxgloveServerError

    v = Vehicle()
    first = FoxgloveServer(v, port=0)
    try:
        with pytest.raises(FoxgloveServerError, match=rf"127\.0\.0\.1:{first.port}") as err:
            FoxgloveServer(v, port=first.port)
        assert isinstance(err.value, AsyncdonkeyError) and isinstance(err.value, OSError)
    finally:
        first.shutdown()
