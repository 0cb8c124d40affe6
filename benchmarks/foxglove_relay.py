"""What the subprotocol relay in front of foxglove-sdk's WebSocket server costs, against connecting directly.

The SDK's server runs on loopback and publishes one topic at a fixed rate; a WebSocket client in another process
(so its work is not counted here) subscribes either straight to the SDK's port or through the
:class:`~asyncdonkey.parts.mcap.relay.SubprotocolRelay`, and stamps each message's arrival. Two loads:

* ``small``: 200-byte JSON messages at 2,000 per second (many scalar channels);
* ``frames``: 20 kB messages at 200 per second (a camera's JPEGs, 4 MB/s).

Figures per load and path: messages received, one-way latency (publish → client, p50 / p99), this process's CPU
time over the run (the SDK's threads plus, through the relay, the relay's thread), and the relay thread's own CPU
time per message and per MB.

    python benchmarks/foxglove_relay.py           # about 20 s
    python benchmarks/foxglove_relay.py --quick   # about 6 s
    python benchmarks/foxglove_relay.py --json
"""

from __future__ import annotations

import argparse
import json
import logging
import subprocess
import sys
import textwrap
import time

import numpy as np

from machine_info import describe

LOADS = {"small": (200, 2000.0), "frames": (20_000, 200.0)}

CLIENT = textwrap.dedent(
    """
    import asyncio, json, struct, sys, time
    import websockets

    async def main(url, expected):
        lat = []
        async with websockets.connect(url, subprotocols=["foxglove.websocket.v1"], max_size=None) as ws:
            while True:
                msg = json.loads(await ws.recv())
                if msg["op"] == "advertise" and any(c["topic"] == "/bench" for c in msg["channels"]):
                    cid = next(c["id"] for c in msg["channels"] if c["topic"] == "/bench")
                    break
            await ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": 1, "channelId": cid}]}))
            await asyncio.sleep(0.2)
            print("ready", flush=True)
            try:
                while len(lat) < expected:
                    raw = await asyncio.wait_for(ws.recv(), 2.0)
                    if isinstance(raw, bytes) and raw[0] == 1:
                        now = time.monotonic_ns()
                        sent = json.loads(raw[13:])["t"]
                        if sent:  # not a message logged before the run
                            lat.append((now - sent) / 1e6)
            except asyncio.TimeoutError:
                pass
        print(json.dumps(lat), flush=True)

    asyncio.run(main(sys.argv[1], int(sys.argv[2])))
    """
)


def run_load(path: str, size: int, rate: float, seconds: float) -> dict[str, float]:
    import foxglove

    from asyncdonkey.parts.mcap.relay import SubprotocolRelay

    ctx = foxglove.Context()
    server = foxglove.start_server(host="127.0.0.1", port=0, context=ctx)
    channel = foxglove.Channel("/bench", message_encoding="json", context=ctx)
    relay = SubprotocolRelay("127.0.0.1", 0, ("127.0.0.1", server.port)) if path == "relay" else None
    port = relay.port if relay is not None else server.port
    offer = "relay" if relay is not None else "direct"
    n = int(rate * seconds)
    client_code = CLIENT if offer == "relay" else CLIENT.replace('["foxglove.websocket.v1"]', '["foxglove.sdk.v1"]')
    client = subprocess.Popen(
        [sys.executable, "-c", client_code, f"ws://127.0.0.1:{port}", str(n)],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        while client.stdout.readline().strip() != "ready":  # type: ignore[union-attr]
            channel.log(b'{"t": 0}')  # the channel is advertised once something is logged
            time.sleep(0.05)
        pad = b"x" * max(0, size - 40)
        cpu0 = time.process_time()
        start = time.monotonic()
        for i in range(n):
            due = start + i / rate
            while (now := time.monotonic()) < due:
                time.sleep(min(due - now, 0.002))
            channel.log(b'{"t":%d,"pad":"%s"}' % (time.monotonic_ns(), pad))
        out, _ = client.communicate(timeout=30)
        cpu = time.process_time() - cpu0
    finally:
        client.kill()
        if relay is not None:
            relay.stop()
        server.stop()
    lat = np.array(json.loads(out.strip().splitlines()[-1]))
    res = {
        "sent": n,
        "received": int(lat.size),
        "p50_ms": float(np.percentile(lat, 50)) if lat.size else float("nan"),
        "p99_ms": float(np.percentile(lat, 99)) if lat.size else float("nan"),
        "process_cpu_ms_per_s": cpu / seconds * 1e3,
    }
    if relay is not None:
        s = relay.stats
        res["relay_cpu_us_per_msg"] = s.cpu_s / max(1, res["received"]) * 1e6
        res["relay_cpu_ms_per_mb"] = s.cpu_s / max(1, s.to_clients) * 1e9
        res["relay_cpu_percent"] = s.cpu_s / seconds * 100
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    logging.basicConfig(level=logging.ERROR)
    seconds = 1.0 if args.quick else 4.0
    res: dict[str, object] = {"machine": describe(with_load=True)}
    for load, (size, rate) in LOADS.items():
        for path in ("direct", "relay"):
            res[f"{load}_{path}"] = run_load(path, size, rate, seconds)
    if args.json:
        print(json.dumps(res, indent=2))
        return
    print(res["machine"])
    for load, (size, rate) in LOADS.items():
        print(f"{load}: {size} B at {rate:.0f}/s for {seconds:.0f} s")
        for path in ("direct", "relay"):
            r = res[f"{load}_{path}"]
            assert isinstance(r, dict)
            extra = ""
            if path == "relay":
                extra = (
                    f"  relay thread {r['relay_cpu_us_per_msg']:.1f} us/msg, {r['relay_cpu_ms_per_mb']:.2f} ms/MB,"
                    f" {r['relay_cpu_percent']:.1f}% of a core"
                )
            print(
                f"  {path:6s} {r['received']}/{r['sent']} received, latency p50 {r['p50_ms']:.3f} ms"
                f" p99 {r['p99_ms']:.3f} ms, process CPU {r['process_cpu_ms_per_s']:.0f} ms/s{extra}"
            )


if __name__ == "__main__":
    main()
