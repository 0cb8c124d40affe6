"""Memory channels over Zenoh on loopback: the car->pilot->car trip, throughput, tick lateness and CPU while publishing.

The trips and the throughput have raw Zenoh beside them on the same sessions (``declare_publisher`` /
``declare_subscriber`` with the parts' options, the same payload bytes, no codec, no parts).

* **car->pilot->car trip** (the off-board pilot of ``examples/car.py --pilot remote`` and
  ``examples/remote_pilot.py``, with the pilot's model replaced by a constant). The car (this process) listens
  on 127.0.0.1 as a peer; the pilot (this script with ``--pilot``, another process, as on another machine)
  connects to it. Ours: the car's ``ZenohPublisher.run()`` sends a camera frame (encode, age attachment, put);
  the pilot's ``ZenohSubscriber`` takes it on Zenoh's thread (decode, the ``cam/image_array`` contract, ages)
  and pushes it to a callback that calls the pilot's ``ZenohPublisher(..., group="pilot/command").run()`` with
  a constant angle and throttle (one JSON sample); the car's ``ZenohSubscriber(..., group=)`` takes it (decode,
  the ``pilot/*`` contracts, newest-value cell) and the car's ``run()`` returns it. The figure is the time from
  the car's publish call to that ``run()`` returning the command: two encodes, two decodes, the loopback TCP
  transport twice and both subscribers' contract checks. Raw: the same trip with the payloads already encoded
  (the same bytes each way): ``put`` -> the pilot's callback takes the payload's bytes and ``put``s the
  command's bytes -> the car's callback takes them. Payloads: a 160x120 RGB frame raw (57,600 bytes) and as
  JPEG (quality 85), each answered by a grouped command; and a scalar trip (a float out on ``user/throttle``, a
  float back on ``pilot/throttle``). One trip in flight at a time, in rounds interleaved ours, raw (raw first
  every other round), so machine load hits both alike: each figure is the median over the rounds of that
  round's p50, p90 or p99, and the ratio the median of the per-round ratios. The same trips then run with the
  pilot's session in the car's process (the headline is the two-process one). Not in the trip: the drive
  loops' hand-overs (the pilot's parts are called on Zenoh's thread here, not pushed into a Vehicle's loop).
* **throughput**: one-way, flat out, to a raw counting subscriber in the pilot process: how many messages per
  second ``put``/``run()`` sends, and how many arrive (congestion control ``DROP``: a sender faster than the
  receiver loses samples instead of blocking the tick).
* **tick lateness and added CPU**: a 20 Hz Vehicle whose camera part produces a new frame each tick, without
  publishing, then publishing the frame raw, then as JPEG (with a remote subscriber connected): tick lateness
  p99, the publisher's time per tick, and process CPU per second of driving.

Loopback only (127.0.0.1, no scouting), Zenoh's shared memory off on every session (``--shm`` leaves it on, its
default, under which payloads of 3 KB or more skip the socket between two processes of one machine; between two
machines every byte crosses the network). Every wait is bounded: a trip lost for 2 s ends the run, the trip rounds
stop at ``--max-trip-s``.

    python benchmarks/zenoh.py              # about a minute
    python benchmarks/zenoh.py --quick      # about 20 s
    python benchmarks/zenoh.py --json       # figures as JSON
    python benchmarks/zenoh.py --trips-only --rounds 2 --trips 20   # the trips alone, tiny
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

HERE = Path(__file__).resolve().parent
# This file is named like the Eclipse Zenoh package: keep its own folder off the import path while importing it.
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != HERE]
import zenoh  # noqa: E402

sys.path.insert(0, str(HERE))

import numpy as np  # noqa: E402
from prettytable import PrettyTable  # noqa: E402

from asyncdonkey import Vehicle  # noqa: E402
from asyncdonkey.loop import run_blocking  # noqa: E402
from asyncdonkey.parts.zenoh import (  # noqa: E402
    PILOT_COMMAND,
    ZenohLink,
    ZenohPublisher,
    ZenohSubscriber,
    encode,
    zenoh_config,
)
from asyncdonkey.parts.zenoh.codec import encode_group  # noqa: E402
from machine_info import describe  # noqa: E402

JPEG_QUALITY = 85
#: the pilot's constant command (its model computes nothing here)
ANGLE, THROTTLE = -0.12, 0.3
#: the car's scalar in the scalar trip
USER_THROTTLE = 0.42
TRIP_TIMEOUT_S = 2.0
WARMUP_TRIPS = 20
#: where the trips of each way of running live: the pilot process and the car's own process answer apart
TWO_PROCESS, ONE_PROCESS = "bench/p2", "bench/p1"


class Trip(NamedTuple):
    """One kind of trip: what the car sends, how (JPEG quality or raw), and what the pilot sends back."""

    name: str
    out: str  # the car's channel
    back: tuple[str, ...]  # the pilot's channels
    group: str | None  # sent back as one sample on this channel
    jpeg: int | None = None

    @property
    def slug(self) -> str:
        return self.name.replace(" ", "_")

    def command(self) -> tuple[float, ...]:
        return (ANGLE, THROTTLE) if self.group else (THROTTLE,)

    def out_value(self) -> Any:
        return frame() if self.out == "cam/image_array" else USER_THROTTLE

    def back_encoded(self):
        if self.group:
            return encode_group(dict(zip(self.back, self.command(), strict=True)), self.group)
        return encode(THROTTLE, self.back[0])

    def back_key(self) -> str:
        return self.group or self.back[0]


TRIPS = (
    Trip("frame raw", "cam/image_array", ("pilot/angle", "pilot/throttle"), PILOT_COMMAND),
    Trip("frame JPEG", "cam/image_array", ("pilot/angle", "pilot/throttle"), PILOT_COMMAND, JPEG_QUALITY),
    Trip("scalar", "user/throttle", ("pilot/throttle",), None),
)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def frame() -> np.ndarray:
    from asyncdonkey.parts.sim import Simulator

    return Simulator().render()


#: Zenoh's shared memory: off unless ``--shm``. On by default in Zenoh, it carries a payload of 3 KB or more
#: between two sessions of one machine through shared memory instead of the socket; between the car and a
#: pilot on another machine every byte crosses the network, so the benchmark's payloads cross the socket.
SHM = {"on": False}


def _shm(cfg):
    cfg.insert_json5("transport/shared_memory/enabled", "true" if SHM["on"] else "false")
    return cfg


def car_config(port: int):
    """The car's session, as ``examples/car.py --zenoh-listen tcp/127.0.0.1:PORT`` opens it."""
    return _shm(zenoh_config(mode="peer", listen=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False))


def pilot_config(port: int):
    """The pilot's session, as ``examples/remote_pilot.py --zenoh-connect tcp/127.0.0.1:PORT`` opens it."""
    cfg = zenoh_config(
        mode="peer",
        connect=[f"tcp/127.0.0.1:{port}"],
        multicast_scouting=False,
        extra={"connect/exit_on_failure": False},
    )
    cfg.insert_json5("listen/endpoints", "[]")
    return _shm(cfg)


class PilotSide:
    """The pilot's half of every trip on one session, under ``ns``: for each :data:`TRIPS` entry, the parts (a
    ``ZenohSubscriber`` pushing each value to a ``ZenohPublisher`` that sends the constant command back, its
    age the value's) and the raw floor (a subscriber callback taking the payload's bytes and putting the
    command's)."""

    def __init__(self, session: Any, ns: str) -> None:
        self.parts: list[Any] = []
        self.decls: list[Any] = []
        for trip in TRIPS:
            link = ZenohLink(f"{ns}/ours/{trip.slug}", session=session)
            sub = ZenohSubscriber(link, [trip.out], ping_every_s=0)
            pub = ZenohPublisher(link, list(trip.back), group=trip.group)
            sub.subscribe(self._answer(pub, link.now, trip.command()))
            self.parts += [sub, pub]

            enc = trip.back_encoded()
            raw_pub = session.declare_publisher(
                f"{ns}/raw/{trip.slug}/{trip.back_key()}", congestion_control=zenoh.CongestionControl.DROP
            )
            self.decls.append(raw_pub)
            self.decls.append(
                session.declare_subscriber(
                    f"{ns}/raw/{trip.slug}/{trip.out}",
                    self._answer_raw(raw_pub, enc.payload, enc.encoding),
                    allowed_origin=zenoh.Locality.REMOTE,
                )
            )

    @staticmethod
    def _answer(pub: ZenohPublisher, now: Callable[[], float], command: tuple[float, ...]):
        def answer(_value: Any, origin: float) -> None:
            age = now() - origin
            pub.run(*command, *(age for _ in command))

        return answer

    @staticmethod
    def _answer_raw(pub: Any, payload: bytes, encoding: str):
        def answer(sample: Any) -> None:
            sample.payload.to_bytes()  # the pilot's model reads the frame
            pub.put(payload, encoding=encoding)

        return answer

    def close(self) -> None:
        for d in self.decls:
            d.undeclare()
        for p in self.parts:
            p.shutdown()


def pilot_process(port: int) -> None:
    """The pilot process: :class:`PilotSide` for :data:`TWO_PROCESS`, and a counter of the samples on each key
    under ``bench/tp/``; each key read from stdin prints (and resets) that key's ``count bytes``."""
    logging.disable(logging.INFO)
    link = ZenohLink("bench/pilot", pilot_config(port)).acquire()  # as examples/remote_pilot.py opens it
    session = link.session
    counted: dict[str, list[int]] = {}

    def count(sample) -> None:
        c = counted.setdefault(str(sample.key_expr), [0, 0])
        c[0] += 1
        c[1] += len(sample.payload)

    pilot = PilotSide(session, TWO_PROCESS)
    tp = session.declare_subscriber("bench/tp/**", count)
    print("ready", flush=True)
    for line in sys.stdin:  # until the car closes our stdin
        n, nbytes = counted.pop(line.strip(), (0, 0))
        print(n, nbytes, flush=True)
    tp.undeclare()
    pilot.close()
    link.close()


class CarTrip:
    """The car's half of one trip, ours (``raw=False``) or raw Zenoh: :meth:`once` runs one trip and returns
    its time (s), from the publish call to the car holding the command."""

    def __init__(self, session: Any, ns: str, trip: Trip, raw: bool) -> None:
        self.trip, self.raw = trip, raw
        self.value = trip.out_value()
        enc = encode(self.value, trip.out, jpeg_quality=trip.jpeg)
        self.out_payload, self.out_encoding = enc.payload, enc.encoding
        back = trip.back_encoded()
        self.bytes = (len(enc.payload), len(back.payload))
        self.arrived = threading.Event()
        self.held: list[Any] = [None]
        self.parts: list[Any] = []
        if raw:
            self.pub = session.declare_publisher(
                f"{ns}/raw/{trip.slug}/{trip.out}", congestion_control=zenoh.CongestionControl.DROP
            )
            self.sub = session.declare_subscriber(
                f"{ns}/raw/{trip.slug}/{trip.back_key()}", self._on_raw, allowed_origin=zenoh.Locality.REMOTE
            )
            self.expected: Any = back.payload
        else:
            link = ZenohLink(f"{ns}/ours/{trip.slug}", session=session)
            self.publisher = ZenohPublisher(link, [trip.out], jpeg={trip.out: trip.jpeg} if trip.jpeg else None)
            self.subscriber = ZenohSubscriber(
                link, list(trip.back), group=trip.group, ping_every_s=0, on_arrival=self._on_arrival
            )
            self.parts = [self.publisher, self.subscriber]
            cmd = trip.command()
            self.expected = cmd if len(cmd) > 1 else cmd[0]

    def _on_raw(self, sample: Any) -> None:
        self.held[0] = sample.payload.to_bytes()
        self.arrived.set()

    def _on_arrival(self, _channel: str) -> None:
        self.arrived.set()

    def once(self, timeout: float = TRIP_TIMEOUT_S) -> float | None:
        """One trip; ``None`` if the command did not come back within ``timeout``."""
        arrived = self.arrived
        arrived.clear()
        if self.raw:
            t0 = time.perf_counter()
            self.pub.put(self.out_payload, encoding=self.out_encoding)
            if not arrived.wait(timeout):
                return None
            got = self.held[0]
            t1 = time.perf_counter()
        else:
            t0 = time.perf_counter()
            self.publisher.run(self.value, 0.0)
            if not arrived.wait(timeout):
                return None
            got = self.subscriber.run()
            t1 = time.perf_counter()
        if got != self.expected:
            raise SystemExit(f"zenoh bench: {self} got {got!r} back, not {self.expected!r}")
        return t1 - t0

    def connect(self, timeout: float = 10.0) -> None:
        """Trips until one comes back (the pilot's declarations reach the car some time after it connects),
        then let any answer to an earlier try arrive before measuring."""
        end = time.monotonic() + timeout
        while self.once(0.1) is None:
            if time.monotonic() > end:
                raise SystemExit(f"zenoh bench: {self}: the pilot never answered")
        time.sleep(0.1)

    def close(self) -> None:
        if self.raw:
            self.sub.undeclare()
            self.pub.undeclare()
        for p in self.parts:
            p.shutdown()

    def __repr__(self) -> str:
        return f"{self.trip.name} trip ({'raw Zenoh' if self.raw else 'ours'})"


def _cpu_ticks(pid: int | None = None) -> int:
    """CPU time of a process (utime + stime), or of the whole machine (every core's busy time), in clock ticks."""
    if pid is None:
        fields = [int(x) for x in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
        return sum(fields) - fields[3] - fields[4]  # all but idle and iowait
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return int(fields[11]) + int(fields[12])


class Load:
    """The machine's load over a stretch of time: load averages at both ends, every core's busy share, and of
    it what the benchmark's own processes used (so the rest is what other processes took)."""

    def __init__(self, pids: list[int]) -> None:
        self.pids = pids
        self.avg0 = os.getloadavg()
        self.t0 = time.monotonic()
        self.machine0 = _cpu_ticks()
        self.own0 = sum(_cpu_ticks(p) for p in pids)

    def done(self) -> dict[str, Any]:
        wall = time.monotonic() - self.t0
        hz, cores = os.sysconf("SC_CLK_TCK"), os.cpu_count() or 1
        machine = (_cpu_ticks() - self.machine0) / hz / wall / cores * 100
        own = (sum(_cpu_ticks(p) for p in self.pids) - self.own0) / hz / wall / cores * 100
        return {
            "loadavg_start": [round(x, 2) for x in self.avg0],
            "loadavg_end": [round(x, 2) for x in os.getloadavg()],
            "cores": cores,
            "busy_pct": machine,  # of all cores, every process
            "benchmark_busy_pct": own,  # of all cores, the car and pilot processes
            "others_busy_pct": max(0.0, machine - own),
            "seconds": wall,
        }


_QUANTILES = (50, 90, 99)


def _ms(samples) -> dict[str, float]:
    ms = np.asarray(samples) * 1e3
    return {"p50_ms": float(np.percentile(ms, 50)), "p99_ms": float(np.percentile(ms, 99)), "n": len(ms)}


def _summary(rounds: list[np.ndarray]) -> dict[str, Any]:
    """Each quantile per round (ms), and its median over the rounds."""
    out: dict[str, Any] = {"n": int(sum(len(r) for r in rounds))}
    per_round = {q: [float(np.percentile(r, q)) * 1e3 for r in rounds] for q in _QUANTILES}
    for q, values in per_round.items():
        out[f"p{q}_ms"] = float(np.median(values))
        out[f"p{q}_ms_rounds"] = values
    pooled = np.concatenate(rounds) * 1e3
    out["max_ms"] = float(pooled.max())
    out["p99_ms_pooled"] = float(np.percentile(pooled, 99))
    return out


def trips(session: Any, ns: str, pids: list[int], rounds: int, per_round: int, max_s: float) -> dict[str, Any]:
    """Every :data:`TRIPS` entry, ours and raw, ``per_round`` trips each per round, the rounds interleaved."""
    paths = {
        t.name: {"ours": CarTrip(session, ns, t, raw=False), "raw": CarTrip(session, ns, t, raw=True)} for t in TRIPS
    }
    times: dict[str, dict[str, list[np.ndarray]]] = {t.name: {"ours": [], "raw": []} for t in TRIPS}
    try:
        for both in paths.values():
            for path in both.values():
                path.connect()
                for _ in range(WARMUP_TRIPS):
                    path.once()
        load = Load(pids)
        end = time.monotonic() + max_s
        done = 0
        for r in range(rounds):
            if r and time.monotonic() > end:
                break
            for name, both in paths.items():
                for who in ("ours", "raw") if r % 2 == 0 else ("raw", "ours"):
                    path, t = both[who], np.empty(per_round)
                    for i in range(per_round):
                        dt = path.once()
                        if dt is None:
                            raise SystemExit(f"zenoh bench: {path} lost (no answer in {TRIP_TIMEOUT_S} s)")
                        t[i] = dt
                    times[name][who].append(t)
            done += 1
        out: dict[str, Any] = {"rounds": done, "trips_per_round": per_round, "load": load.done(), "trips": {}}
        for name, both in paths.items():
            ours, raw = _summary(times[name]["ours"]), _summary(times[name]["raw"])
            ratio: dict[str, Any] = {}
            for q in _QUANTILES:
                per = sorted(o / w for o, w in zip(ours[f"p{q}_ms_rounds"], raw[f"p{q}_ms_rounds"], strict=True))
                ratio[f"p{q}"] = float(np.median(per))
                ratio[f"p{q}_min"], ratio[f"p{q}_max"] = per[0], per[-1]
            out_bytes, back_bytes = both["ours"].bytes
            out["trips"][name] = {
                "bytes_out": out_bytes,
                "bytes_back": back_bytes,
                "ours": ours,
                "raw": raw,
                "ours_over_raw": ratio,
            }
        return out
    finally:
        for both in paths.values():
            for path in both.values():
                path.close()


def throughput(session: Any, pilot: subprocess.Popen, seconds: float) -> dict:
    img = frame()
    tx_link = ZenohLink("bench/tp", session=session).acquire()

    def received(key: str) -> tuple[int, int]:
        """What arrived on ``key`` since the last call (counted per key: a backlog of the previous path's
        samples still being delivered is not counted for this one)."""
        pilot.stdin.write(f"{key}\n")
        pilot.stdin.flush()
        n, nbytes = pilot.stdout.readline().split()
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
                    p = session.declare_publisher(key, congestion_control=zenoh.CongestionControl.DROP)

                    def send(p=p, enc=enc) -> None:
                        p.put(enc.payload, encoding=enc.encoding)
                else:
                    part = ZenohPublisher(
                        tx_link, [f"{path}/{ch}"], jpeg={f"{path}/{ch}": quality} if quality else None
                    )

                    def send(part=part, value=value) -> None:
                        part.run(value, 0.0)

                time.sleep(0.3)
                received(key)  # reset the count
                sent = 0
                t0 = time.perf_counter()
                end = t0 + seconds
                while time.perf_counter() < end:
                    for _ in range(20):
                        send()
                    sent += 20
                elapsed = time.perf_counter() - t0
                time.sleep(0.5)  # let the tail arrive
                n, nbytes = received(key)
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
        tx_link.release()
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
    rx = zenoh.open(car_config(port))  # the remote subscriber listens; the car connects to it
    received = [0]
    rx.declare_subscriber("bench/car/**", lambda _s: received.__setitem__(0, received[0] + 1))
    link = ZenohLink(
        "bench/car", _shm(zenoh_config(mode="client", connect=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False))
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


def _wait_ready(proc: subprocess.Popen, timeout: float = 30.0) -> None:
    import select

    ready, _, _ = select.select([proc.stdout], [], [], timeout)
    if not ready or proc.stdout.readline().strip() != "ready":
        raise SystemExit("zenoh bench: the pilot process did not start")


def measure(
    quick: bool,
    rounds: int | None = None,
    per_round: int | None = None,
    max_trip_s: float = 60.0,
    trips_only: bool = False,
    one_process: bool = True,
) -> dict:
    rounds = rounds or (4 if quick else 12)
    per_round = per_round or (50 if quick else 150)
    port = free_port()
    car = ZenohLink("bench/car", car_config(port)).acquire()  # the car's session, as examples/car.py opens it
    trip: dict[str, Any] = {
        "method": {
            "transport": f"tcp/127.0.0.1 (the car listens as a peer, the pilot connects; port {port})",
            "shared_memory": SHM["on"],
            "rounds": rounds,
            "trips_per_round": per_round,
            "warmup_trips": WARMUP_TRIPS,
            "timeout_s": TRIP_TIMEOUT_S,
            "max_trip_s": max_trip_s,
            "figures": "median over the rounds of each round's quantile; ours_over_raw: median of per-round ratios",
        }
    }
    out: dict[str, Any] = {"machine": describe(), "quick": quick, "trip": trip}
    try:
        proc = subprocess.Popen(
            [sys.executable, __file__, "--pilot", str(port), *(["--shm"] if SHM["on"] else [])],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
        )
        try:
            _wait_ready(proc)
            pids = [os.getpid(), proc.pid]
            trip["two_process"] = trips(car.session, TWO_PROCESS, pids, rounds, per_round, max_trip_s)
            if not trips_only:
                out["throughput"] = throughput(car.session, proc, 0.5 if quick else 2.0)
        finally:
            proc.stdin.close()
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        if one_process:
            pilot = ZenohLink("bench/pilot", pilot_config(port)).acquire()
            side = PilotSide(pilot.session, ONE_PROCESS)
            try:
                trip["one_process"] = trips(car.session, ONE_PROCESS, [os.getpid()], rounds, per_round, max_trip_s)
            finally:
                side.close()
                pilot.close()
    finally:
        car.close()
    if not trips_only:
        out["ticks_20hz"] = ticks_while_publishing(2.0 if quick else 8.0)
    return out


def _load_line(load: dict[str, Any]) -> str:
    return (
        f"machine busy {load['busy_pct']:.0f} % of {load['cores']} cores over {load['seconds']:.1f} s (this"
        f" benchmark {load['benchmark_busy_pct']:.0f} %, other processes {load['others_busy_pct']:.0f} %); load"
        f" average {load['loadavg_start'][0]:.2f} -> {load['loadavg_end'][0]:.2f}"
    )


def trip_table(t: dict[str, Any], title: str) -> list[str]:
    pt = PrettyTable()
    q = ("p50", "p90", "p99")
    pt.field_names = ["trip", "bytes out / back", *(f"ours {x}" for x in q), *(f"raw {x}" for x in q), "ours/raw"]
    for name, row in t["trips"].items():
        ours, raw, ratio = row["ours"], row["raw"], row["ours_over_raw"]
        pt.add_row(
            [
                name,
                f"{row['bytes_out']:,} / {row['bytes_back']}",
                *(f"{ours[f'{x}_ms']:.3f}" for x in q),
                *(f"{raw[f'{x}_ms']:.3f}" for x in q),
                " / ".join(f"{ratio[x]:.2f}" for x in q),
            ]
        )
    rounds = f"{t['rounds']} rounds of {t['trips_per_round']} trips each way, interleaved; medians of the rounds"
    return [f"{title} (ms; {rounds})", pt.get_string(), _load_line(t["load"]), ""]


def table(r: dict) -> str:
    out: list[str] = []
    trip = r["trip"]
    out += trip_table(trip["two_process"], "car->pilot->car trip, the pilot in another process (loopback TCP)")
    if "one_process" in trip:
        out += trip_table(trip["one_process"], "the same trip, the pilot's session in the car's process")
    if "throughput" in r:
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
    if "ticks_20hz" in r:
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
        out += ["tick lateness and CPU while publishing the camera", pt.get_string(), ""]
    out.append(f"machine: {r['machine']}")
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="fewer samples (about 20 s)")
    parser.add_argument("--json", action="store_true", help="print the figures as JSON")
    parser.add_argument("--rounds", type=int, help="trip rounds (default 12, quick 4)")
    parser.add_argument("--trips", type=int, help="trips each way per round (default 150, quick 50)")
    parser.add_argument(
        "--max-trip-s", type=float, default=60.0, help="stop the trip rounds after this long (default 60)"
    )
    parser.add_argument("--trips-only", action="store_true", help="only the car->pilot->car trips")
    parser.add_argument(
        "--no-one-process", action="store_true", help="only the trips with the pilot in another process"
    )
    parser.add_argument(
        "--shm",
        action="store_true",
        help="leave Zenoh's shared memory on (its default), as for two processes of one machine: payloads of 3 KB"
        " or more then skip the socket",
    )
    parser.add_argument("--pilot", type=int, metavar="PORT", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    SHM["on"] = args.shm
    if args.pilot:
        pilot_process(args.pilot)
        return 0
    logging.disable(logging.INFO)
    results = measure(
        args.quick,
        rounds=args.rounds,
        per_round=args.trips,
        max_trip_s=args.max_trip_s,
        trips_only=args.trips_only,
        one_process=not args.no_one_process,
    )
    print(json.dumps(results, indent=2) if args.json else table(results))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
