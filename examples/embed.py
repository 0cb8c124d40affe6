"""The drive loop inside an asyncio application of your own, beside its other tasks.

    python examples/embed.py                   # 15 s; meanwhile: curl http://127.0.0.1:8887/status
    python examples/embed.py --seconds 0       # until Ctrl-C or GET /stop

The application owns the event loop, its signal handling and its lifetime; the vehicle is one task among
others. ``Vehicle.run()`` is an ordinary coroutine: it installs no signal handlers, never touches the event
loop policy, and stops cleanly either way the application chooses:

* ``vehicle.stop()`` — the current tick finishes, parts shut down, ``run()`` returns its report;
* cancelling the task awaiting ``run()`` — the same shutdown, then ``CancelledError`` propagates.

Beside the car, this application runs a telemetry logger (one line a second from the vehicle's channels) and
a tiny HTTP status endpoint (``GET /status`` returns JSON, ``GET /stop`` stops the car) on asyncio streams.
Both read the vehicle's ``Memory`` and profiler on the same thread as the ticks, so no locks are needed.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import logging
import signal
import sys
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
from asyncdonkey import DriveReport, Vehicle
from car import DEFAULT_MODEL, make_car, recent_lateness_p99_ms

log = logging.getLogger("embed")


def snapshot(vehicle: Vehicle) -> dict[str, Any]:
    """What the app reports about the car: channels plus the loop's recent timing."""
    mem = vehicle.mem
    p99 = recent_lateness_p99_ms(vehicle)
    return {
        "ticks": vehicle.profiler.tick.count,
        "laps": mem.get(["sim/laps"])[0],
        "speed_m_s": _rounded(mem.get(["sim/speed"])[0]),
        "cte_m": _rounded(mem.get(["sim/cte"])[0]),
        "mode": mem.get(["user/mode"])[0],
        "angle": _rounded(mem.get(["angle"])[0]),
        "throttle": _rounded(mem.get(["throttle"])[0]),
        "lateness_p99_ms": None if p99 is None else round(p99, 3),
    }


def _rounded(x: Any) -> float | None:
    return None if x is None else round(float(x), 4)


async def telemetry_logger(vehicle: Vehicle, every: float = 1.0) -> None:
    """One of the application's own tasks: logs the car's state periodically."""
    while True:
        await asyncio.sleep(every)
        s = snapshot(vehicle)
        log.info(
            "telemetry: laps %s, %s m/s, cte %s m, lateness p99 %s ms",
            s["laps"],
            s["speed_m_s"],
            s["cte_m"],
            s["lateness_p99_ms"],
        )


class StatusEndpoint:
    """``GET /status`` → the snapshot as JSON; ``GET /stop`` → asks the app to stop the car."""

    def __init__(self, vehicle: Vehicle) -> None:
        self.vehicle = vehicle
        self.stop_requested = asyncio.Event()

    async def handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            request = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), timeout=5)
            method, path, *_ = request.split(b"\r\n", 1)[0].decode("latin-1").split(" ")
            if method != "GET":
                status, body = "405 Method Not Allowed", {"error": f"{method} not allowed; use GET"}
            elif path == "/status":
                status, body = "200 OK", snapshot(self.vehicle)
            elif path == "/stop":
                self.stop_requested.set()
                status, body = "200 OK", {"stopping": True}
            else:
                status, body = "404 Not Found", {"error": f"no such path {path}; try /status or /stop"}
            data = json.dumps(body).encode()
            writer.write(
                f"HTTP/1.1 {status}\r\nContent-Type: application/json\r\nContent-Length: {len(data)}\r\n"
                f"Connection: close\r\n\r\n".encode()
                + data
            )
            await writer.drain()
        except (asyncio.IncompleteReadError, asyncio.LimitOverrunError, TimeoutError, ValueError):
            pass  # a client that hung up or sent garbage gets nothing
        finally:
            writer.close()
            with contextlib.suppress(ConnectionError):
                await writer.wait_closed()


async def main(
    seconds: float = 15.0, host: str = "127.0.0.1", port: int = 8887, pilot: str | Path = DEFAULT_MODEL
) -> DriveReport:
    """The application: starts its server and logger, drives the car, stops everything, returns the report."""
    vehicle, _car = make_car(pilot=pilot, seconds=0, status=None)  # the app decides when to stop
    endpoint = StatusEndpoint(vehicle)
    server = await asyncio.start_server(endpoint.handle, host, port)
    bound = server.sockets[0].getsockname()
    log.info("status endpoint on http://%s:%s/status", bound[0], bound[1])
    main.bound_port = bound[1]  # type: ignore[attr-defined]  # for tests that pass port=0

    loop = asyncio.get_running_loop()
    with contextlib.suppress(NotImplementedError, RuntimeError):  # the app's own signal policy
        loop.add_signal_handler(signal.SIGINT, endpoint.stop_requested.set)
        loop.add_signal_handler(signal.SIGTERM, endpoint.stop_requested.set)

    drive = asyncio.create_task(vehicle.run(rate_hz=20), name="drive loop")
    logger_task = asyncio.create_task(telemetry_logger(vehicle), name="telemetry logger")
    stop_wait = asyncio.create_task(endpoint.stop_requested.wait())
    try:
        await asyncio.wait({drive, stop_wait}, timeout=seconds or None, return_when=asyncio.FIRST_COMPLETED)
        vehicle.stop()  # safe from anywhere; the current tick finishes, then parts shut down
        return await drive
    finally:
        # the app itself being cancelled: cancelling the drive task runs the same clean shutdown
        for task in (drive, logger_task, stop_wait):
            task.cancel()
        await asyncio.gather(drive, logger_task, stop_wait, return_exceptions=True)
        server.close()
        await server.wait_closed()
        with contextlib.suppress(NotImplementedError, RuntimeError):
            loop.remove_signal_handler(signal.SIGINT)
            loop.remove_signal_handler(signal.SIGTERM)


def cli(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="the simulated car inside an asyncio application")
    ap.add_argument("--seconds", type=float, default=15.0, help="stop the car after S seconds (0: on /stop or Ctrl-C)")
    ap.add_argument("--host", default="127.0.0.1")
    ap.add_argument("--port", type=int, default=8887, help="status endpoint port (Donkeycar's web UI port)")
    ap.add_argument("--pilot", default=str(DEFAULT_MODEL), help="ONNX model, or 'user' for the scripted driver")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    report = asyncio.run(main(args.seconds, args.host, args.port, args.pilot))
    print(f"the app stopped the car after {report.loops} ticks ({report.achieved_hz:.2f} Hz, {report.stop_reason})")
    return 0


if __name__ == "__main__":
    sys.exit(cli())
