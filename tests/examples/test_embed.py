"""examples/embed.py: the vehicle as one task of an asyncio application, on the real loop."""

import asyncio
import json

import pytest

from .example_loader import load_example

pytestmark = [pytest.mark.realtime, pytest.mark.network]

embed = load_example("embed")


async def http_get(port: int, path: str) -> tuple[str, dict]:
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    writer.write(f"GET {path} HTTP/1.1\r\nHost: x\r\n\r\n".encode())
    await writer.drain()
    raw = await reader.read()
    writer.close()
    head, body = raw.split(b"\r\n\r\n", 1)
    return head.split(b"\r\n", 1)[0].decode(), json.loads(body)


async def wait_for_port() -> int:
    for _ in range(500):
        port = getattr(embed.main, "bound_port", None)
        if port:
            return port
        await asyncio.sleep(0.01)
    raise AssertionError("the status endpoint never started")


@pytest.mark.asyncio
async def test_status_endpoint_serves_while_driving_and_stop_ends_the_drive():
    embed.main.bound_port = None
    app = asyncio.create_task(embed.main(seconds=0, port=0))
    port = await wait_for_port()
    ticks = 0
    for _ in range(200):  # until the car has driven a little (real time; generous for a loaded machine)
        status, body = await http_get(port, "/status")
        ticks = body["ticks"]
        if ticks >= 10:
            break
        await asyncio.sleep(0.05)
    assert status == "HTTP/1.1 200 OK"
    assert ticks >= 10 and body["mode"] == "local" and body["lateness_p99_ms"] is not None
    assert (await http_get(port, "/nowhere"))[0] == "HTTP/1.1 404 Not Found"
    assert (await http_get(port, "/stop"))[1] == {"stopping": True}
    report = await asyncio.wait_for(app, timeout=30)
    assert report.stop_reason == "stop()"
    assert report.loops >= ticks
    with pytest.raises(OSError):  # the app closed its server on the way out
        await asyncio.open_connection("127.0.0.1", port)


@pytest.mark.asyncio
async def test_cancelling_the_app_shuts_the_vehicle_down():
    embed.main.bound_port = None
    app = asyncio.create_task(embed.main(seconds=0, port=0, pilot="user"))
    await wait_for_port()
    await asyncio.sleep(0.3)
    app.cancel()
    with pytest.raises(asyncio.CancelledError):
        await asyncio.wait_for(app, timeout=30)
    leftovers = [t for t in asyncio.all_tasks() if t is not asyncio.current_task() and not t.done()]
    assert leftovers == []  # drive loop, simulator, logger: all ended
