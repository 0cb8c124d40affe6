"""Memory channels over Zenoh on loopback: round trip, throughput, tick lateness and CPU while publishing.

Floors are raw Zenoh (``put`` and a subscriber callback, no encoding, no Memory). Payloads: a scalar (a
throttle command, JSON), a 160x120 RGB camera frame raw (57,600 bytes plus the ndarray encoding) and as JPEG
(quality 85).

* **round trip**: this process puts on ``bench/ping/<channel>``; an echo process (this script with ``--echo``,
  a raw Zenoh session) puts every sample back on ``bench/pong/<channel>`` unchanged (payload, encoding,
  attachment). Raw: ``put`` -> echo -> subscriber callback. Channel: ``ZenohPublisher.run()`` (encode, age
  attachment, put) -> echo -> ``ZenohSubscriber`` (decode, ages, newest-value cell) -> ``run()``. One message
  in flight at a time; p50 and p99 over all.
* **throughput**: one-way, flat out for two seconds, to a raw counting subscriber in the echo process: how many
  messages per second ``put``/``run()`` sends, and how many arrive (congestion control ``DROP``: a sender
  faster than the receiver loses samples instead of blocking the tick). Sessions in one process would show
  far higher, meaningless figures: Zenoh then skips most of the transport.
* **tick lateness and added CPU**: a 20 Hz Vehicle whose camera part produces a new frame each tick, without
  publishing, then publishing the frame raw, then as JPEG (with an echo-free remote subscriber connected):
  tick lateness p99, the publisher's time per tick, and process CPU per second of driving.

    python benchmarks/zenoh.py            # about 40 s
    python benchmarks/zenoh.py --quick    # about 12 s
    python benchmarks/zenoh.py --json     # figures as JSON
"""

from __future__ import annotations

import argparse
import json
import logging
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
# This file is named like the Eclipse Zenoh package: keep its own folder off the import path while importing it.
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != HERE]
import zenoh  # noqa: E402

sys.path.insert(0, str(HERE))

import numpy as np  # noqa: E402
from prettytable import PrettyTable  # noqa: E402

from asyncdonkey import Vehicle  # noqa: E402
from asyncdonkey.loop import run_blocking  # noqa: E402
from asyncdonkey.parts.zenoh import ZenohLink, ZenohPublisher, ZenohSubscriber, encode, zenoh_config  # noqa: E402
from machine_info import describe  # noqa: E402

JPEG_QUALITY = 85


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def frame() -> np.ndarray:
    from asyncdonkey.parts.sim import Simulator

    return Simulator().render()


def echo(port: int) -> None:
    """The echo process: every sample on ``bench/ping/**`` goes back on ``bench/pong/**`` unchanged; samples on
    ``bench/tp/**`` are counted, and each line read from stdin prints (and resets) ``count bytes``."""
    session = zenoh.open(zenoh_config(mode="peer", listen=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False))
    counted = [0, 0]

    def back(sample) -> None:
        key = str(sample.key_expr).replace("bench/ping", "bench/pong", 1)
        session.put(key, sample.payload, encoding=sample.encoding, attachment=sample.attachment)

    def count(sample) -> None:
        counted[0] += 1
        counted[1] += len(sample.payload)

    session.declare_subscriber("bench/ping/**", back)
    session.declare_subscriber("bench/tp/**", count)
    print("ready", flush=True)
    for _ in sys.stdin:  # until the parent closes our stdin
        print(counted[0], counted[1], flush=True)
        counted[0] = counted[1] = 0
    session.close()


def _ms(samples) -> dict[str, float]:
    ms = np.asarray(samples) * 1e3
    return {"p50_ms": float(np.percentile(ms, 50)), "p99_ms": float(np.percentile(ms, 99)), "n": len(ms)}


def round_trips(port: int, n: int) -> dict:
    img = frame()
    cases = {
        "scalar": (0.42, None),
        "frame raw": (img, None),
        "frame JPEG": (img, JPEG_QUALITY),
    }
    cfg = zenoh_config(mode="client", connect=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False)
    out: dict[str, dict] = {}
    ping = ZenohLink("bench/ping", cfg).acquire()  # held for the whole run, not just one case's parts
    pong = ZenohLink("bench/pong", session=ping.session).acquire()
    try:
        for name, (value, quality) in cases.items():
            ch = name.replace(" ", "_")
            # raw floor: the payload already encoded, put -> echo -> callback
            enc = encode(value, ch, jpeg_quality=quality)
            got = threading.Event()
            raw_sub = ping.session.declare_subscriber(f"bench/pong/raw/{ch}", lambda _s, e=got: e.set())
            raw_pub = ping.session.declare_publisher(f"bench/ping/raw/{ch}")
            # channel path: part -> echo -> part
            arrived = threading.Event()
            sub = ZenohSubscriber(pong, [ch], ping_every_s=0, on_arrival=lambda _c, e=arrived: e.set())
            pub = ZenohPublisher(ping, [ch], jpeg={ch: quality} if quality else None)
            time.sleep(0.3)
            raw_t, chan_t = np.empty(n), np.empty(n)
            for i in range(-20, n):  # 20 warm-up round trips each
                got.clear()
                t0 = time.perf_counter()
                raw_pub.put(enc.payload, encoding=enc.encoding)
                if not got.wait(2.0):
                    raise SystemExit(f"zenoh bench: raw {name} round trip lost")
                t1 = time.perf_counter()
                arrived.clear()
                t2 = time.perf_counter()
                pub.run(value, 0.0)
                if not arrived.wait(2.0):
                    raise SystemExit(f"zenoh bench: channel {name} round trip lost")
                sub.run()
                t3 = time.perf_counter()
                if i >= 0:
                    raw_t[i], chan_t[i] = t1 - t0, t3 - t2
            out[name] = {"bytes": len(enc.payload), "raw": _ms(raw_t), "channel": _ms(chan_t)}
            raw_sub.undeclare()
            raw_pub.undeclare()
            pub.shutdown()
            sub.shutdown()
    finally:
        pong.close()
        ping.close()
    return out


def throughput(port: int, echo_proc: subprocess.Popen, seconds: float) -> dict:
    img = frame()
    tx_link = ZenohLink(
        "bench/tp", zenoh_config(mode="client", connect=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False)
    ).acquire()

    def received() -> tuple[int, int]:
        echo_proc.stdin.write("\n")
        echo_proc.stdin.flush()
        n, nbytes = echo_proc.stdout.readline().split()
        return int(n), int(nbytes)

    out: dict[str, dict] = {}
    try:
        for name, value, quality in (
            ("scalar", 0.42, None),
            ("frame raw", img, None),
            ("frame JPEG", img, JPEG_QUALITY),
        ):
            ch = name.replace(" ", "_")
            enc = encode(value, ch, jpeg_quality=quality)
            row: dict = {"bytes": len(enc.payload)}
            for path in ("raw", "channel"):
                key = f"bench/tp/{path}/{ch}"
                if path == "raw":
                    p = tx_link.session.declare_publisher(key, congestion_control=zenoh.CongestionControl.DROP)

                    def send(p=p, enc=enc) -> None:
                        p.put(enc.payload, encoding=enc.encoding)
                else:
                    part = ZenohPublisher(
                        tx_link, [f"{path}/{ch}"], jpeg={f"{path}/{ch}": quality} if quality else None
                    )

                    def send(part=part, value=value) -> None:
                        part.run(value, 0.0)

                time.sleep(0.3)
                received()  # reset the count
                sent = 0
                t0 = time.perf_counter()
                end = t0 + seconds
                while time.perf_counter() < end:
                    for _ in range(20):
                        send()
                    sent += 20
                elapsed = time.perf_counter() - t0
                time.sleep(0.5)  # let the tail arrive
                n, nbytes = received()
                row[path] = {
                    "sent_per_s": sent / elapsed,
                    "received_per_s": n / elapsed,
                    "received_share": n / sent,
                    "mbyte_per_s": nbytes / elapsed / 1e6,
                }
                if path == "channel":
                    part.shutdown()
                else:
                    p.undeclare()
            out[name] = row
    finally:
        tx_link.close()
    return out


class NewFrames:
    """A camera that hands out a new frame object every tick (as a real one does)."""

    def __init__(self, image: np.ndarray) -> None:
        self.frames = [image.copy() for _ in range(4)]
        self.k = 0

    def run(self) -> np.ndarray:
        self.k += 1
        return self.frames[self.k % 4]


def ticks_while_publishing(seconds: float) -> dict:
    img = frame()
    port = free_port()
    rx = zenoh.open(zenoh_config(mode="peer", listen=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False))
    received = [0]
    rx.declare_subscriber("bench/car/**", lambda _s: received.__setitem__(0, received[0] + 1))
    link = ZenohLink(
        "bench/car", zenoh_config(mode="client", connect=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False)
    ).acquire()
    out: dict[str, dict] = {}
    try:
        warm = Vehicle()  # the first drive of a process pays for imports and first calls: not measured
        warm.add(NewFrames(img), outputs=["cam/image_array"])
        run_blocking(warm.run(20, 20))
        for name, quality in (("no publishing", None), ("frame raw", None), ("frame JPEG", JPEG_QUALITY)):
            v = Vehicle(profiler_window=int(seconds * 20) + 10)
            v.add(NewFrames(img), outputs=["cam/image_array"])
            if name != "no publishing":
                pub = ZenohPublisher(link, ["cam/image_array"], jpeg={"cam/image_array": quality} if quality else None)
                v.add(pub, inputs=pub.inputs, name="publisher")
            before = received[0]
            cpu0, t0 = time.process_time(), time.perf_counter()
            run_blocking(v.run(20, int(seconds * 20)))
            cpu, wall = time.process_time() - cpu0, time.perf_counter() - t0
            time.sleep(0.2)
            late = v.profiler.lateness.recent(drop_last=False)
            row = {
                "lateness_p99_ms": float(np.percentile(late, 99)) * 1e3,
                "cpu_ms_per_s": cpu / wall * 1e3,
                "frames_received": received[0] - before,
                "ticks": int(seconds * 20),
            }
            if "publisher" in v.profiler.parts:
                row["publisher"] = _ms(v.profiler.parts["publisher"].recent())
            out[name] = row
        base = out["no publishing"]["cpu_ms_per_s"]
        for name in ("frame raw", "frame JPEG"):
            out[name]["added_cpu_ms_per_s"] = out[name]["cpu_ms_per_s"] - base
    finally:
        link.close()
        rx.close()
    return out


def measure(quick: bool) -> dict:
    port = free_port()
    proc = subprocess.Popen(
        [sys.executable, __file__, "--echo", str(port)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
    )
    try:
        if proc.stdout.readline().strip() != "ready":
            raise SystemExit("zenoh bench: the echo process did not start")
        rtt = round_trips(port, 200 if quick else 1000)
        tp = throughput(port, proc, 0.5 if quick else 2.0)
    finally:
        proc.stdin.close()
        proc.wait(timeout=10)
    return {
        "machine": describe(),
        "quick": quick,
        "round_trip": rtt,
        "throughput": tp,
        "ticks_20hz": ticks_while_publishing(2.0 if quick else 8.0),
    }


def table(r: dict) -> str:
    out = []
    pt = PrettyTable()
    pt.field_names = ["payload", "bytes", "raw p50 (ms)", "raw p99 (ms)", "channel p50 (ms)", "channel p99 (ms)"]
    for name, row in r["round_trip"].items():
        raw, ch = row["raw"], row["channel"]
        pt.add_row(
            [
                name,
                row["bytes"],
                f"{raw['p50_ms']:.3f}",
                f"{raw['p99_ms']:.3f}",
                f"{ch['p50_ms']:.3f}",
                f"{ch['p99_ms']:.3f}",
            ]
        )
    out += ["round trip through an echo process (loopback TCP)", pt.get_string(), ""]
    pt = PrettyTable()
    pt.field_names = ["payload", "path", "sent/s", "received/s", "received", "MB/s"]
    for name, row in r["throughput"].items():
        for path in ("raw", "channel"):
            t = row[path]
            pt.add_row(
                [
                    name if path == "raw" else "",
                    path,
                    f"{t['sent_per_s']:,.0f}",
                    f"{t['received_per_s']:,.0f}",
                    f"{t['received_share']:.0%}",
                    f"{t['mbyte_per_s']:.1f}",
                ]
            )
    out += ["one-way throughput to another process, flat out", pt.get_string(), ""]
    pt = PrettyTable()
    pt.field_names = [
        "20 Hz car",
        "lateness p99 (ms)",
        "publisher p50 (ms)",
        "CPU (ms/s)",
        "added CPU (ms/s)",
        "frames received",
    ]
    for name, row in r["ticks_20hz"].items():
        p = row.get("publisher")
        pt.add_row(
            [
                name,
                f"{row['lateness_p99_ms']:.3f}",
                f"{p['p50_ms']:.3f}" if p else "-",
                f"{row['cpu_ms_per_s']:.1f}",
                f"{row['added_cpu_ms_per_s']:.1f}" if "added_cpu_ms_per_s" in row else "-",
                f"{row['frames_received']}/{row['ticks']}",
            ]
        )
    out += ["tick lateness and CPU while publishing the camera", pt.get_string(), f"machine: {r['machine']}"]
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="fewer samples (about 12 s)")
    parser.add_argument("--json", action="store_true", help="print the figures as JSON")
    parser.add_argument("--echo", type=int, metavar="PORT", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.echo:
        echo(args.echo)
        return 0
    logging.disable(logging.INFO)
    results = measure(args.quick)
    print(json.dumps(results, indent=2) if args.json else table(results))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
