"""FoxgloveServer: a client speaking Foxglove's WebSocket protocol on loopback sees the car's topics advertised,
subscribes, and receives the messages the MCAP file would hold.

The protocol's subprotocol name is ``foxglove.websocket.v1``; foxglove-sdk 0.30 and later name the same protocol
``foxglove.sdk.v1`` and refuse the old name. Clients offering either name, or both as Foxglove's app does, are
served (the relay in front of the SDK's server renames the offer); the relay's bounds are tested against a plain
socket server standing in for the SDK's."""

from __future__ import annotations

import asyncio
import json
import socket
import struct
import threading
import time

import numpy as np
import pytest
import websockets

from asyncdonkey.loop import Vehicle
from asyncdonkey.parts.mcap.live import FoxgloveServer
from asyncdonkey.parts.mcap.reader import decode_image, protobuf_class

from ..waiting import wait_until

PROTOCOLS = ["foxglove.sdk.v1", "foxglove.websocket.v1"]

pytestmark = [pytest.mark.network]


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


@pytest.mark.realtime
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


@pytest.mark.realtime
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


@pytest.mark.realtime
@pytest.mark.asyncio
@pytest.mark.parametrize(
    "offer, chosen",
    [
        (["foxglove.websocket.v1"], "foxglove.websocket.v1"),  # Lichtblick, older Foxglove Studio
        (["foxglove.sdk.v1"], "foxglove.sdk.v1"),  # clients written for the SDK
        (PROTOCOLS, "foxglove.sdk.v1"),  # Foxglove's app
    ],
)
async def test_clients_offering_either_subprotocol_name_are_served(offer, chosen):
    v = Vehicle()
    v.add(Car(), outputs=["cam/image_array", "user/angle", "n"])
    live = FoxgloveServer(v, port=0)
    v.add(live, name="foxglove")
    drive = asyncio.create_task(v.run(rate_hz=50))
    try:
        async with websockets.connect(live.url, subprotocols=offer, open_timeout=5) as ws:
            assert ws.subprotocol == chosen
            info = json.loads(await ws.recv())
            assert info["op"] == "serverInfo" and info["name"] == "asyncdonkey"
            chans = await advertised(ws, {"/n", "/cam/image_array", "/asyncdonkey/tick"})
            sub = {"op": "subscribe", "subscriptions": [{"id": 7, "channelId": chans["/n"]["id"]}]}
            await ws.send(json.dumps(sub))
            _, data = await message_data(ws, 7)
            assert json.loads(data)["value"] >= 1
    finally:
        v.stop()
        await drive


@pytest.mark.realtime
@pytest.mark.asyncio
async def test_a_client_offering_neither_name_is_refused_by_the_server():
    live = FoxgloveServer(Vehicle(), port=0)
    try:
        with pytest.raises(websockets.InvalidStatus) as err:
            async with websockets.connect(live.url, subprotocols=["chat"], open_timeout=5):
                pass
        assert err.value.response.status_code == 400
    finally:
        live.shutdown()


# --------------------------------------------------------------------------------------------- the relay's bounds
HANDSHAKE = (
    b"GET / HTTP/1.1\r\nHost: car\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
    b"Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n"
    b"Sec-WebSocket-Protocol: foxglove.websocket.v1\r\n\r\n"
)


class FakeServer:
    """Stands in for the SDK's server: answers the handshake with ``foxglove.sdk.v1`` (or 400 when not offered),
    then sends ``blast`` bytes of a counting pattern as fast as the socket takes them, and records what it got."""

    def __init__(self, blast: int = 0):

        self.blast = blast
        self.sent = 0
        self.heads: list[bytes] = []
        self.blocked = threading.Event()
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.port = self.listener.getsockname()[1]
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _serve(self):
        conn, _ = self.listener.accept()
        with conn:
            head = b""
            while b"\r\n\r\n" not in head:
                head += conn.recv(4096)
            self.heads.append(head)
            if b"foxglove.sdk.v1" not in head:
                conn.sendall(b"HTTP/1.1 400 Bad Request\r\nContent-Length: 0\r\n\r\n")
                return
            conn.sendall(
                b"HTTP/1.1 101 Switching Protocols\r\nconnection: Upgrade\r\nupgrade: websocket\r\n"
                b"sec-websocket-accept: s3pPLMBiTxaQ9kYGzzhZRbK+xOo=\r\nsec-websocket-protocol: foxglove.sdk.v1\r\n\r\n"
            )
            conn.settimeout(0.5)
            try:
                while self.sent < self.blast:
                    off = self.sent % 256
                    try:
                        self.sent += conn.send(BLOCK[off : off + min(65536, self.blast - self.sent)])
                    except TimeoutError:
                        self.blocked.set()  # the relay stopped reading: backpressure reached the server
                        conn.settimeout(10.0)
                conn.recv(1)  # until the relay closes
            except OSError:
                pass

    def close(self):
        self.listener.close()


BLOCK = bytes(i % 256 for i in range(65536 + 256))
"""a counting pattern: the byte at stream offset k is ``k % 256``"""


def read_head(sock) -> tuple[bytes, bytes]:
    data = b""
    while b"\r\n\r\n" not in data:
        chunk = sock.recv(4096)
        if not chunk:
            break
        data += chunk
    head, _, rest = data.partition(b"\r\n\r\n")
    return head, rest


def test_the_relay_renames_the_offer_and_the_answer_and_nothing_else():
    from asyncdonkey.parts.mcap.relay import SubprotocolRelay

    server = FakeServer(blast=1000)
    relay = SubprotocolRelay("127.0.0.1", 0, ("127.0.0.1", server.port))
    try:
        with socket.create_connection(("127.0.0.1", relay.port), timeout=5) as c:
            c.sendall(HANDSHAKE)
            head, rest = read_head(c)
            assert head.startswith(b"HTTP/1.1 101") and b"sec-websocket-protocol: foxglove.websocket.v1" in head
            assert b"s3pPLMBiTxaQ9kYGzzhZRbK+xOo=" in head  # the accept key untouched
            while len(rest) < 1000:
                rest += c.recv(4096)
            assert rest == BLOCK[:1000]
        assert b"Sec-WebSocket-Protocol: foxglove.websocket.v1, foxglove.sdk.v1\r\n" in server.heads[0]
        assert relay.stats.renamed == 1 and relay.stats.to_clients >= 1000
    finally:
        relay.stop()
        server.close()


@pytest.mark.realtime
def test_a_slow_client_gets_backpressure_not_an_unbounded_buffer():
    from asyncdonkey.parts.mcap.relay import SubprotocolRelay

    total = 64 * 1024 * 1024
    server = FakeServer(blast=total)
    relay = SubprotocolRelay("127.0.0.1", 0, ("127.0.0.1", server.port), buffer_limit=64 * 1024)
    try:
        with socket.socket() as c:
            c.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 64 * 1024)
            c.settimeout(10)
            c.connect(("127.0.0.1", relay.port))
            c.sendall(HANDSHAKE)
            head, rest = read_head(c)
            assert head.startswith(b"HTTP/1.1 101")
            assert server.blocked.wait(10)  # the client reads nothing more: the server's sends stall
            assert relay.buffered() <= 64 * 1024
            assert server.sent < total // 2  # socket buffers and the relay's hold a few MB, not the whole blast
            # the client catches up: every byte arrives, in order
            assert rest == BLOCK[: len(rest)]
            got = len(rest)
            while got < total:
                chunk = c.recv(65536)
                assert chunk, f"closed after {got} bytes"
                off = got % 256
                assert chunk == BLOCK[off : off + len(chunk)]
                got += len(chunk)
        # the relay counts what it sent after its send returns, which can be after the client has read it all
        wait_until(
            lambda: relay.stats.to_clients >= total,
            5.0,
            lambda: f"{total} bytes counted as sent ({relay.stats.to_clients})",
        )
    finally:
        relay.stop()
        server.close()


@pytest.mark.realtime
def test_a_silent_client_is_dropped_after_the_handshake_timeout():

    from asyncdonkey.parts.mcap.relay import SubprotocolRelay

    server = FakeServer()
    relay = SubprotocolRelay("127.0.0.1", 0, ("127.0.0.1", server.port), handshake_timeout_s=0.3)
    try:
        with socket.create_connection(("127.0.0.1", relay.port), timeout=5) as c:
            c.sendall(b"GET / HTTP/1.1\r\n")  # and nothing more
            t0 = time.monotonic()
            assert c.recv(100) == b""  # closed by the relay
            assert 0.2 < time.monotonic() - t0 < 3
        assert relay.stats.timed_out == 1 and relay.connections == 0
    finally:
        relay.stop()
        server.close()


def test_connections_beyond_the_cap_are_answered_503():
    from asyncdonkey.parts.mcap.relay import SubprotocolRelay

    server = FakeServer()
    relay = SubprotocolRelay("127.0.0.1", 0, ("127.0.0.1", server.port), max_connections=2)
    try:
        held = [socket.create_connection(("127.0.0.1", relay.port), timeout=5) for _ in range(2)]
        for c in held:
            c.sendall(b"GET")  # a handshake under way holds its slot
        with socket.create_connection(("127.0.0.1", relay.port), timeout=5) as extra:
            assert extra.recv(100).startswith(b"HTTP/1.1 503")
        assert relay.stats.refused == 1 and relay.connections == 2
        for c in held:
            c.close()
    finally:
        relay.stop()
        server.close()


def test_an_oversized_handshake_is_refused():
    from asyncdonkey.parts.mcap.relay import SubprotocolRelay

    server = FakeServer()
    relay = SubprotocolRelay("127.0.0.1", 0, ("127.0.0.1", server.port), max_head=1024)
    try:
        with socket.create_connection(("127.0.0.1", relay.port), timeout=5) as c:
            c.sendall(b"GET / HTTP/1.1\r\nX-Junk: " + b"a" * 4096)
            assert c.recv(100).startswith(b"HTTP/1.1 431")
    finally:
        relay.stop()
        server.close()
