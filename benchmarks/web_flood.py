"""The web controller under a flood of slow connections: does the driver keep the car, and the car its files?

A slow client ("slowloris") opens a connection, sends part of a request line and never finishes it. The server
cannot check a token it never receives, so each such connection holds one of the car's file descriptors for as
long as the server lets it. On Debian and Raspberry Pi OS a process may have 1024 (``ulimit -n``); when they are
gone, the car can neither accept its driver's next connection nor open the files it records to.

Each round runs a car in this process (a camera, the :class:`~asyncdonkey.parts.web.WebController` with its
default settings, a ``TubWriter`` recording every tick) under a lowered ``RLIMIT_NOFILE`` soft limit, one
client process (its own descriptor limit and event loop, so only the car's descriptors count) that

1. connects the driver's WebSocket (with the token) and sends a command every 50 ms, recording on;
2. during the flood, every 1.5 s, tries a new authenticated client: ``GET /status`` and a ``/wsDrive``
   handshake, 3 s each;

and another client process that opens ``N`` slow connections to 127.0.0.1 (``GET /drive HTT``, never
finished), holds them for ``--flood-s`` seconds and, with ``--reconnect yes``, reopens any the server closes
(at most ``MAX_ATTEMPTS`` times each, at once: the harder case for the car).

The car's side counts the commands applied while flooded, tries to open a file every 0.25 s (as the tub does
for every image), and reads the tub writer's counters. Every loop is bounded in count and time; all traffic
goes to 127.0.0.1.

    python benchmarks/web_flood.py          # 250, 500, 1000, 1200 slow connections, held then reopened; nofile 1024
    python benchmarks/web_flood.py --conns 1200 --nofile 1024 --flood-s 12
    python benchmarks/web_flood.py --json
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import logging
import os
import resource
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
from prettytable import PrettyTable

from asyncdonkey import Vehicle
from asyncdonkey.loop import run_blocking
from asyncdonkey.parts.tub import TubWriter
from asyncdonkey.parts.web import WEB_INPUTS, WEB_OUTPUTS, WebController
from machine_info import describe

RATE_HZ = 20
PARTIAL_REQUEST = b"GET /drive HTT"  # a request line that never ends
MAX_ATTEMPTS = 40  # reconnections per slow-connection slot, whatever the flood's length
CONNECT_TIMEOUT_S = 3.0
PROBE_EVERY_S = 1.5
PROBE_TIMEOUT_S = 3.0
FLOOD_DELAY_S = 1.0  # the driver drives alone this long before the flood starts
DRIVER_START_S = 20.0  # the longest the driver's process may take to start driving


class Camera:
    """A new 160x120 frame each tick, so the tub writes (and opens) an image file per record."""

    def __init__(self) -> None:
        rng = np.random.default_rng(0)
        self.frames = [rng.integers(0, 255, (120, 160, 3), dtype=np.uint8) for _ in range(8)]
        self.k = 0

    def run(self) -> np.ndarray:
        self.k += 1
        return self.frames[self.k % len(self.frames)].copy()


# ====================================================================================== the client process
async def _slow_slot(port: int, spec: dict[str, Any], stats: dict[str, Any]) -> None:
    """One slow connection until the flood's end; reopened when the server closes it (``reconnect``, at most
    MAX_ATTEMPTS times)."""
    until = spec["flood_end"]
    for _ in range(MAX_ATTEMPTS if spec["reconnect"] else 1):
        left = until - time.monotonic()
        if left <= 0:
            return
        try:
            reader, writer = await asyncio.wait_for(
                asyncio.open_connection("127.0.0.1", port), min(CONNECT_TIMEOUT_S, left)
            )
        except (OSError, TimeoutError):
            stats["connect_failed"] += 1
            await asyncio.sleep(min(0.2, max(0.0, until - time.monotonic())))
            continue
        stats["opened"] += 1
        stats["open"] += 1
        stats["max_open"] = max(stats["max_open"], stats["open"])
        t0 = time.monotonic()
        try:
            writer.write(PARTIAL_REQUEST)
            await asyncio.wait_for(reader.read(), max(0.0, until - time.monotonic()))  # b"" when closed
            stats["closed_by_server"] += 1
            stats["lifetimes"].append(time.monotonic() - t0)
        except TimeoutError:
            pass  # held to the end of the flood
        except OSError:
            stats["closed_by_server"] += 1
            stats["lifetimes"].append(time.monotonic() - t0)
        finally:
            stats["open"] -= 1
            writer.close()


async def _flood_main(spec: dict[str, Any]) -> dict[str, Any]:
    """``conns`` slow connections from ``flood_start`` to ``flood_end`` (monotonic times, shared by processes)."""
    flood: dict[str, Any] = {"opened": 0, "open": 0, "max_open": 0, "connect_failed": 0, "closed_by_server": 0}
    lifetimes: list[float] = []
    flood["lifetimes"] = lifetimes
    await asyncio.sleep(max(0.0, spec["flood_start"] - time.monotonic()))
    await asyncio.gather(*(_slow_slot(spec["port"], spec, flood) for _ in range(spec["conns"])))
    del flood["lifetimes"]
    flood["lifetime_median_s"] = float(np.median(lifetimes)) if lifetimes else None
    return flood


async def _driver(port: int, token: str, stop: asyncio.Event, out: dict[str, Any]) -> None:
    """The driver's phone: a WebSocket sending a command every 50 ms, recording on, until ``stop``."""
    import aiohttp

    headers = {"Authorization": f"Token {token}"}
    url = f"http://127.0.0.1:{port}/wsDrive"
    async with (
        aiohttp.ClientSession(headers=headers) as http,
        http.ws_connect(url, timeout=aiohttp.ClientWSTimeout(5)) as ws,
    ):
        out["connected_at"] = time.monotonic()

        async def read() -> None:  # answers the server's pings, notices a close
            async for _ in ws:
                pass

        reader = asyncio.create_task(read())
        k = 0
        while not stop.is_set() and not ws.closed:
            k += 1
            try:
                await ws.send_str(json.dumps({"angle": (k % 20) / 40, "throttle": 0.1, "recording": True}))
                out["sent"] += 1
            except (ConnectionError, RuntimeError):
                break
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(stop.wait(), 0.05)
        out["closed_by_server"] = ws.closed
        out["close"] = f"{ws.close_code} {ws.exception()!r}" if ws.closed else None
        reader.cancel()


async def _new_client(port: int, token: str) -> bool:
    """A client that arrives during the flood: ``GET /status`` and a WebSocket handshake, on new connections."""
    import aiohttp

    headers = {"Authorization": f"Token {token}"}
    timeout = aiohttp.ClientTimeout(total=PROBE_TIMEOUT_S)
    try:
        async with aiohttp.ClientSession(headers=headers, timeout=timeout) as http:
            async with http.get(f"http://127.0.0.1:{port}/status") as r:
                if r.status != 200:
                    return False
            async with asyncio.timeout(PROBE_TIMEOUT_S):
                async with http.ws_connect(f"http://127.0.0.1:{port}/wsDrive") as ws:
                    hello = await ws.receive_json()
                    return "control" in hello
    except (OSError, TimeoutError, aiohttp.ClientError, ValueError):
        return False


async def _driver_main(spec: dict[str, Any]) -> dict[str, Any]:
    """The driver (connected before the flood) and, during the flood, newcomers every PROBE_EVERY_S."""
    port, token = spec["port"], spec["token"]
    stop = asyncio.Event()
    driver: dict[str, Any] = {"connected_at": None, "sent": 0, "closed_by_server": False}
    driving = asyncio.create_task(_driver(port, token, stop, driver))
    # the flood's times, once the car has seen this driver drive (a loaded machine starts processes slowly)
    spec.update(json.loads(await asyncio.to_thread(sys.stdin.readline)))
    await asyncio.sleep(max(0.0, spec["flood_start"] + 2.0 - time.monotonic()))
    probes: list[bool] = []
    while time.monotonic() + PROBE_TIMEOUT_S < spec["flood_end"] and len(probes) < 100:
        probes.append(await _new_client(port, token))
        await asyncio.sleep(PROBE_EVERY_S)
    await asyncio.sleep(max(0.0, spec["flood_end"] + 0.5 - time.monotonic()))
    after = await _new_client(port, token)
    stop.set()
    with contextlib.suppress(Exception):
        await asyncio.wait_for(driving, 5)
    connected = driver["connected_at"] is not None and driver["connected_at"] < spec["flood_start"]
    return {
        "driver_connected": connected,
        "driver_dropped": driver["closed_by_server"],
        "driver_sent": driver["sent"],
        "driver_close": driver.get("close"),
        "new_client_ok": sum(probes),
        "new_client_tries": len(probes),
        "new_client_after": after,
    }


def client_process(spec: dict[str, Any]) -> None:
    """The flood (``role`` "flood") or the driver and newcomers ("driver"), each in a process of its own with
    its own descriptor limit and event loop, so that neither the car nor the driver shares the flood's."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    want = spec["conns"] + 256
    if hard == resource.RLIM_INFINITY or hard >= want:
        resource.setrlimit(resource.RLIMIT_NOFILE, (max(soft, want), hard))
    main = _flood_main if spec["role"] == "flood" else _driver_main
    print(json.dumps(asyncio.run(main(spec))))


# ====================================================================================== the car process
class CarThread:
    """The car on its own thread and event loop, as on a Pi; this thread watches it."""

    def __init__(self, tub_dir: Path, use_uvloop: bool) -> None:
        self.use_uvloop = use_uvloop
        self.vehicle = v = Vehicle()
        v.add(Camera(), outputs=["cam/image_array"], name="camera")
        self.web = WebController(0, host="127.0.0.1", announce=None)
        v.add(self.web, inputs=list(WEB_INPUTS), outputs=list(WEB_OUTPUTS), name="web")
        names = ["cam/image_array", "user/angle", "user/throttle", "user/mode"]
        self.tub = TubWriter(tub_dir, inputs=names, types=["image_array", "float", "float", "str"])
        v.add(self.tub, inputs=names, outputs=["tub/num_records"], run_condition="recording", name="tub")
        self.error: BaseException | None = None
        self.thread = threading.Thread(target=self._main, name="car", daemon=True)

    def _main(self) -> None:
        try:
            run_blocking(self.vehicle.run(rate_hz=RATE_HZ), use_uvloop=self.use_uvloop)
        except BaseException as exc:
            self.error = exc

    def start(self) -> None:
        self.thread.start()
        if not self.web.listening.wait(10):
            raise RuntimeError(f"the web controller did not start: {self.error!r}")

    def stop(self) -> None:
        self.vehicle.stop()
        self.thread.join(15)


def _open_fds() -> int:
    """The process's open descriptors; the soft limit when even listing them fails (none left to list with)."""
    try:
        return len(os.listdir("/proc/self/fd"))
    except OSError:
        return resource.getrlimit(resource.RLIMIT_NOFILE)[0]


class ErrorCount(logging.Handler):
    """Counts the errors logged, by logger (asyncio's ``accept() out of system resource``, the tub's failures),
    instead of printing a traceback a second."""

    def __init__(self) -> None:
        super().__init__(logging.ERROR)
        self.by_logger: dict[str, int] = {}

    def emit(self, record: logging.LogRecord) -> None:
        self.by_logger[record.name] = self.by_logger.get(record.name, 0) + 1


def _try_open(path: Path) -> bool:
    try:
        with open(path, "a") as f:
            f.write("x")
        return True
    except OSError:
        return False


def _watch(car: CarThread, procs: list[subprocess.Popen[str]], probe_file: Path, budget_s: float) -> dict[str, Any]:
    """Until the client processes end (at most ``budget_s``): the car's commands and ticks, its CPU time, its open
    descriptors, and whether it can still open a file."""
    samples: list[tuple[float, int, int, float]] = []
    opens = failed_opens = max_fds = 0
    deadline = time.monotonic() + budget_s
    while any(p.poll() is None for p in procs) and time.monotonic() < deadline:
        samples.append((time.monotonic(), car.web.commands, car.web.ticks, time.process_time()))
        opens += 1
        failed_opens += not _try_open(probe_file)
        max_fds = max(max_fds, _open_fds())
        time.sleep(0.25)
    return {"samples": samples, "opens": opens, "failed_opens": failed_opens, "max_fds": max_fds}


def _rates_between(samples: list[tuple[float, int, int, float]], t0: float, t1: float) -> tuple[float, float, float]:
    """Commands applied and ticks per second, and the car's CPU in % of a core, between ``t0`` and ``t1``."""
    inside = [s for s in samples if t0 <= s[0] <= t1]
    if len(inside) < 2 or inside[-1][0] <= inside[0][0]:
        return 0.0, 0.0, 0.0
    (ta, ca, ka, pa), (tb, cb, kb, pb) = inside[0], inside[-1]
    return (cb - ca) / (tb - ta), (kb - ka) / (tb - ta), 100.0 * (pb - pa) / (tb - ta)


def _spawn(spec: dict[str, Any]) -> subprocess.Popen[str]:
    cmd = [sys.executable, str(Path(__file__).resolve()), "--client-process", json.dumps(spec)]
    return subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)


def _wait_for_driver(car: CarThread, proc: subprocess.Popen[str]) -> None:
    deadline = time.monotonic() + DRIVER_START_S
    while car.web.commands < 5:
        if proc.poll() is not None or time.monotonic() > deadline:
            raise RuntimeError("the driver's process did not start driving the car")
        time.sleep(0.05)


def _result(proc: subprocess.Popen[str]) -> dict[str, Any]:
    try:
        out, _ = proc.communicate(timeout=30)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, _ = proc.communicate()
    return json.loads(out)


def flood_round(conns: int, nofile: int, flood_s: float, reconnect: bool, use_uvloop: bool) -> dict[str, Any]:
    """One car, one flood of ``conns`` slow connections for ``flood_s`` seconds, under ``nofile`` descriptors."""
    errors = ErrorCount()
    logging.getLogger().addHandler(errors)
    saved = resource.getrlimit(resource.RLIMIT_NOFILE)
    resource.setrlimit(resource.RLIMIT_NOFILE, (nofile, saved[1]))
    try:
        with tempfile.TemporaryDirectory(prefix="web_flood_") as tmp:
            car = CarThread(Path(tmp) / "tub", use_uvloop)
            car.start()
            try:
                assert car.web.token is not None
                spec = {"port": car.web.port, "token": car.web.token, "conns": conns, "reconnect": reconnect}
                driver = _spawn({**spec, "role": "driver"})
                _wait_for_driver(car, driver)
                start = time.monotonic() + FLOOD_DELAY_S
                times = {"flood_start": start, "flood_end": start + flood_s}
                assert driver.stdin is not None
                driver.stdin.write(json.dumps(times) + "\n")
                driver.stdin.flush()
                flood = _spawn({**spec, **times, "role": "flood"})
                watched = _watch(car, [driver, flood], Path(tmp) / "probe.txt", FLOOD_DELAY_S + flood_s + 30)
                got, flooded = _result(driver), _result(flood)
            finally:
                car.stop()
            stats = car.tub.stats
    finally:
        resource.setrlimit(resource.RLIMIT_NOFILE, saved)
        logging.getLogger().removeHandler(errors)
    cmds, ticks, cpu = _rates_between(watched["samples"], start + 2.0, start + flood_s)
    return {
        "conns": conns,
        "reconnect": reconnect,
        "uvloop": use_uvloop,
        "nofile": nofile,
        "flood_s": flood_s,
        "car_max_fds": watched["max_fds"],
        **got,
        "driver_commands_per_s_flooded": round(cmds, 1),
        "car_ticks_per_s_flooded": round(ticks, 1),
        "car_cpu_pct_flooded": round(cpu, 1),
        "file_opens_failed": watched["failed_opens"],
        "file_opens": watched["opens"],
        "records_written": stats.written,
        "records_lost": stats.failed + stats.dropped + stats.abandoned,
        "errors_logged": errors.by_logger,
        "flood": flooded,
    }


def table(rows: list[dict[str, Any]], machine: str) -> str:
    t = PrettyTable(
        [
            "slow conns",
            "reopened",
            "car fds max/limit",
            "driver kept / cmds/s",
            "ticks/s, CPU %",
            "newcomers served",
            "file opens failed",
            "records lost / written",
            "slow conns opened / closed by car",
            "lifetime median s",
            "errors logged",
        ]
    )
    for r in rows:
        f = r["flood"]
        life = f["lifetime_median_s"]
        after = "yes" if r["new_client_after"] else "no"
        kept = "yes" if r["driver_connected"] and not r["driver_dropped"] else "NO"
        t.add_row(
            [
                r["conns"],
                "yes" if r["reconnect"] else "no",
                f"{r['car_max_fds']}/{r['nofile']}",
                f"{kept} / {r['driver_commands_per_s_flooded']}",
                f"{r['car_ticks_per_s_flooded']}, {r['car_cpu_pct_flooded']}",
                f"{r['new_client_ok']}/{r['new_client_tries']}, after: {after}",
                f"{r['file_opens_failed']}/{r['file_opens']}",
                f"{r['records_lost']} / {r['records_written']}",
                f"{f['opened']} / {f['closed_by_server']}",
                "-" if life is None else f"{life:.1f}",
                ", ".join(f"{k} {v}" for k, v in r["errors_logged"].items()) or "-",
            ]
        )
    loop = "uvloop" if rows and rows[0]["uvloop"] else "asyncio's loop"
    return f"{t}\nmachine: {machine}; the car on {loop}"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--conns", default="250,500,1000,1200", help="slow connections per round, comma-separated")
    ap.add_argument("--nofile", type=int, default=1024, help="the car's RLIMIT_NOFILE soft limit")
    ap.add_argument("--flood-s", type=float, default=12.0)
    ap.add_argument(
        "--reconnect",
        choices=("no", "yes", "both"),
        default="both",
        help="whether the flood reopens the connections the car closes",
    )
    ap.add_argument("--uvloop", action="store_true", help="the car on uvloop (as `asyncdonkey run`), not asyncio's")
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--client-process", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.client_process:
        client_process(json.loads(args.client_process))
        return 0
    hard = resource.getrlimit(resource.RLIMIT_NOFILE)[1]
    if hard != resource.RLIM_INFINITY and hard < args.nofile:
        ap.error(f"--nofile {args.nofile} is above this shell's hard limit ({hard})")
    logging.getLogger().setLevel(logging.ERROR)  # counted by ErrorCount, not printed
    machine = describe(with_load=True)
    modes = {"no": [False], "yes": [True], "both": [False, True]}[args.reconnect]
    rows = [
        flood_round(int(n), args.nofile, args.flood_s, reconnect, args.uvloop)
        for reconnect in modes
        for n in args.conns.split(",")
    ]
    if args.json:
        print(json.dumps({"machine": machine, "rounds": rows}, indent=1))
    else:
        print(table(rows, machine))
    return 0


if __name__ == "__main__":
    sys.exit(main())
